"""Scanned training targets: a target shot on the (virtual) turntable, reconstructed,
stitched into a mesh in its object frame, and used like any other model; banks trained on
such scans set beside banks trained on the true meshes (docs/atr.md "Scanned targets").

The scan runs the same steps a user runs: ``simulate scene`` (8 views), ``reconstruct``
per view (scan PLYs with their confidence and the shot's and calibration's hashes),
``stitch --turntable-step --frame object --mesh --mesh-max-distance 2``.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from prism3d.atr.bank import BANK_CHIP_SPEC, train_bank
from prism3d.atr.evaluate import EVAL_CHIP_SPEC, BankEvaluation, evaluate_bank, heldout_seed
from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
from prism3d.datasets.models.targets import builtin_target
from prism3d.errors import InputError, ReconstructionError
from prism3d.progress import ProgressFn, null_progress
from prism3d.reconstruct.stereo.pipeline import reconstruct_to_files
from prism3d.reconstruct.scan.stitch import StitchOptions, stitch_to_files

__all__ = ["ScanBankComparison", "ScannedTarget", "compare_scan_banks", "scan_builtin_target", "SCAN_RETRY_CONFIDENCE"]

log = logging.getLogger(__name__)

#: When the stitcher refuses a target at its default confidence (a long thin hull seen
#: end-on: two views overlap too little), the scan is stitched again on the points at or
#: above this confidence with the checks as warnings, and the result says so.
SCAN_RETRY_CONFIDENCE = 0.5
#: The mesh is kept within this many point spacings of the fused points (the closed
#: Poisson surface balloons under the model and around thin wings).
SCAN_MESH_MAX_SPACINGS = 2.0


@dataclass
class ScannedTarget:
    """A scanned target's files: ``mesh`` (object frame, mm, z up, scanned colours),
    ``model`` (fused cloud), ``poses`` (poses.json beside them), ``scans`` (one PLY per
    view), ``shots`` (the simulated folder with its truth) and ``notes`` (what the
    stitcher warned about, and any retry)."""

    name: str
    mesh: Path
    model: Path
    poses: Path
    scans: list[Path]
    shots: Path
    notes: list[str] = field(default_factory=list)


def scan_builtin_target(
    name: str,
    out_dir: str | Path,
    *,
    views: int = 8,
    seed: int = 0,
    rig=None,
    calib_rig=None,
    supersample: int = 1,
    progress: ProgressFn = null_progress,
) -> ScannedTarget:
    """Scan the built-in target ``name`` on the simulated turntable into ``out_dir``
    (``shots/``, ``scans/``, ``model.ply``, the mesh ``<name>.ply``, ``poses.json``); files already
    there are reused (an interrupted run resumes). ``rig``: the simulated rig (None: the
    simulator's); ``calib_rig``: the rig the shots are reconstructed with (None: the true
    one, as written beside the shots)."""
    if not isinstance(views, int) or views < 3:
        raise InputError(f"views: expected an integer >= 3, got {views!r}")
    out = Path(out_dir)
    shots = out / "shots"
    if not (shots / "poses.json").is_file():
        simulate_to_folder("scene", shots, SimulateOptions(views=views, seed=seed, supersample=supersample),
                           rig=rig, target=builtin_target(name, seed=seed))
    calib = shots / "rig.yaml"
    if calib_rig is not None:
        calib = out / "calib_rig.yaml"
        if not calib.is_file():
            calib_rig.save(calib)
    scans = []
    for k in range(views):
        progress(k, views + 1, f"{name}: reconstruct view {k}")
        p = out / "scans" / f"scan_{k:02d}.ply"
        if not p.is_file():
            p.parent.mkdir(parents=True, exist_ok=True)
            reconstruct_to_files(shots / f"shot_{k:02d}.png", calib, p)
        scans.append(p)
    progress(views, views + 1, f"{name}: stitch")
    model, mesh = out / "model.ply", out / f"{name}.ply"  # the mesh names the target in a database
    opts = StitchOptions(turntable_step_deg=360.0 / views, mesh_max_spacings=SCAN_MESH_MAX_SPACINGS)
    notes: list[str] = []
    front = _front_view(shots / "poses.json")
    try:
        res = stitch_to_files(scans, model, opts, mesh_out=mesh, frame="object", front_view=front)
    except ReconstructionError as exc:
        notes.append(f"stitching refused ({exc}); stitched again on points of confidence >= "
                     f"{SCAN_RETRY_CONFIDENCE} with the checks as warnings")
        res = stitch_to_files(scans, model, dataclasses.replace(
            opts, min_confidence=SCAN_RETRY_CONFIDENCE, on_failure="warn"), mesh_out=mesh, frame="object",
            front_view=front)
    notes += list(res.diagnostics.get("warnings", []))
    notes += list(res.diagnostics.get("object_frame", {}).get("notes", []))
    progress(views + 1, views + 1, f"{name}: done")
    return ScannedTarget(name, mesh, model, out / "poses.json", scans, shots, notes)


def _front_view(poses_json: Path) -> int:
    """The simulated view whose camera faced the target's front (+x of the turntable
    frame), as the person at a real turntable knows which shot faced the front."""
    import json

    import numpy as np

    views = json.loads(poses_json.read_text())["views"]
    pos = np.array([np.asarray(v["T_world_cam"], np.float64)[:3, 3] for v in views])
    horiz = pos[:, :2] / np.maximum(np.linalg.norm(pos[:, :2], axis=1, keepdims=True), 1e-300)
    return int(np.argmax(horiz[:, 0]))


@dataclass(frozen=True)
class ScanBankComparison:
    """One channel's banks, from scans and from the true meshes, scored on the same test chips."""

    scan: BankEvaluation
    """The bank trained on the scans."""
    mesh: BankEvaluation
    """The bank trained on the true meshes."""

    @property
    def difference_points(self) -> float:
        """Pcc of the scans' bank less the meshes', percentage points."""
        return 100.0 * (self.scan.pcc - self.mesh.pcc)

    def to_json(self) -> dict:
        return {"scan": self.scan.to_json(), "mesh": self.mesh.to_json(), "difference_points": self.difference_points}


def compare_scan_banks(
    scanned: Sequence[tuple[str, object]],
    true: Sequence[tuple[str, object]],
    test: Sequence[tuple[str, object]],
    *,
    channels: Sequence[str] = ("depth", "shape", "intensity"),
    azimuth: str = "0:360:10",
    elevation: str = "20",
    bin_deg: float = 10.0,
    noise_sigma: float = 0.03,
    clutter: str | None = "noise",
    seed: int = 0,
) -> dict[str, ScanBankComparison]:
    """Banks trained on ``scanned`` ``[(class, SceneMesh)]`` and on ``true`` (the same
    classes), both evaluated on ``test`` (renders of the true meshes in a new paint) at
    azimuths between the training ones, with ``noise_sigma`` and ``clutter``. Each mesh
    keeps its own paint in training (a scan's is what the camera saw). Returns the
    comparison of each channel."""
    if sorted(c for c, _ in scanned) != sorted(c for c, _ in true):
        raise InputError("scanned and true targets must name the same classes")
    train_spec = dataclasses.replace(BANK_CHIP_SPEC, seed=seed)  # camouflage on: the meshes' own paint
    test_spec = dataclasses.replace(EVAL_CHIP_SPEC, noise_sigma=noise_sigma, clutter=clutter,
                                    seed=heldout_seed(seed))
    out: dict[str, ScanBankComparison] = {}
    for ch in channels:
        row = {}
        for key, items in (("scan", scanned), ("mesh", true)):
            log.info("bank on %s targets, channel %s", key, ch)
            bank = train_bank(list(items), channel=ch, azimuth=azimuth, elevation=elevation, bin_deg=bin_deg,
                              chip_spec=train_spec)
            row[key] = evaluate_bank(bank, list(test), chip_spec=test_spec)
        out[ch] = ScanBankComparison(row["scan"], row["mesh"])
    return out
