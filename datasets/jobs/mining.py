"""Training a scene recogniser: filter banks over the targets and the classes to refuse,
then the verifier on the objects of simulated field scenes (hard negatives and positives
mined with exact truth).

Each mining scene is ``prism3d simulate field`` with the recogniser's targets as its bank
classes (seeds from :data:`MINING_SEED_BASE`, far from any scene a benchmark scores),
reconstructed with our matcher as ``detect`` would, cut into objects
(:func:`~prism3d.atr.scene.scene_channels`), and every object big enough to be judged is
labelled from the simulator's object ids: the largest piece of a target is a positive of
its class, a smaller piece is left out, everything else (clutter, ground, siblings, crates,
fuel tanks) is ``none``. Scenes are independent units on the jobs runner (this process or
Dask); only their features come back. Method: docs/atr.md "Learning what is not a target".
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.bank import BankOptions, train_bank
from prism3d.atr.chips import ChipSpec
from prism3d.atr.scene import scene_channels
from prism3d.atr.verifier import (
    NONE,
    SceneRecogniser,
    n_size_features,
    object_features,
    object_gate,
    train_prefilter,
    train_verifier,
)
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.rig import StereoRig
from prism3d.datasets.simulation.field import SHAPE_CONFUSERS, FieldOptions, prop_mesh, simulate_field
from prism3d.datasets.runner import RunOptions, run_tasks
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets
from prism3d.errors import InputError
from prism3d.io.images import read_image
from prism3d.reconstruct.stereo.pipeline import (
    ReconstructOptions,
    convergence_distance_mm,
    reconstruct_shot,
)

__all__ = ["MINING_SEED_BASE", "MinedRows", "MiningOptions", "default_rejects", "fit_recogniser", "mine_rows", "mine_scene",
           "recogniser_banks", "train_scene_recogniser"]

#: Seeds of the mining scenes start here (benchmarks score scenes 100-119; tests 0-99).
MINING_SEED_BASE = 1_000_000
#: Mining scenes a default ``bank train`` simulates.
DEFAULT_SCENES = 40
#: Targets and confusers in a mining scene: denser than the scenes scored (3-6 and 1-3), so
#: each scene's simulation and reconstruction yields more positives and hard negatives.
MINING_TARGETS, MINING_CONFUSERS = 6, 4
#: Channels of a default recogniser: the shape image (camouflage removed) and the depth relief.
DEFAULT_CHANNELS = ("shape", "depth")


def default_rejects(targets: Sequence[tuple[str, SceneMesh]], *, seed: int = 0) -> list[tuple[str, SceneMesh]]:
    """What a recogniser of ``targets`` learns to refuse: every military built-in that is not a
    target (by its own name, so a sibling is a class of its own) and the crates and fuel
    tanks of the field scenes, at the targets' scale (full size or kit)."""
    names = {m.name for _, m in targets}
    full = all(float(m.metadata.get("scale", 1.0) or 1.0) == 1.0 for _, m in targets)
    out = [(n, builtin_target(n, scale="full" if full else "model")) for n in list_builtin_targets("military")
           if n not in names]
    rng = np.random.default_rng([seed, 43])
    for kind in SHAPE_CONFUSERS:
        m = prop_mesh(kind, rng, seed)
        if not full:
            k = float(np.median([float(t.metadata.get("scale", 1.0) or 1.0) for _, t in targets]))
            m = SceneMesh(m.vertices * k, m.faces, m.vertex_albedo, m.albedo_field, m.name, dict(m.metadata))
        out.append((kind, m))
    return out


def _labels_rect(rig: StereoRig, K_rect: NDArray, R1: NDArray, oid_left: NDArray, shape: tuple[int, int],
                 step: int = 2) -> NDArray[np.int32]:
    """The simulator's left-view object ids seen through the rectified grid (every ``step``
    px, nearest): each rectified pixel's ray turned back into the left camera and projected
    with its distortion."""
    h, w = shape
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    q = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], axis=1) @ np.linalg.inv(K_rect).T
    pc = q @ np.asarray(R1, dtype=np.float64)  # R1^T applied to rows
    uv = rig.left.project(pc)
    H, W = oid_left.shape
    c = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, W - 1)
    r = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, H - 1)
    ok = np.isfinite(uv).all(axis=1)
    out = np.full(xs.size, -1, np.int32)
    out[ok] = oid_left[r[ok], c[ok]]
    return out.reshape(xs.shape)


def mine_scene(folder: str | Path, recogniser: SceneRecogniser) -> tuple[NDArray[np.float64], list[str], dict]:
    """The labelled verifier rows of one field scene folder (module docstring)."""
    d = Path(folder)
    rig = StereoRig.load(d / "rig.yaml")
    truth = json.loads((d / "truth.json").read_text())
    wd = convergence_distance_mm(rig)
    rec = reconstruct_shot(read_image(d / "shot.png"), rig, ReconstructOptions(depth_range_mm=(0.3 * wd, 10 * wd)))
    grey = rec.left_rect.astype(np.float32)
    grey = grey @ np.array([0.299, 0.587, 0.114], np.float32) if grey.ndim == 3 else grey
    K = np.asarray(rec.rect.P1, dtype=np.float64)[:, :3]
    sc = scene_channels(grey / 255.0, rec.depth_mm, K)
    with np.load(d / "truth.npz") as tz:
        ids = _labels_rect(rig, K, np.asarray(rec.rect.R1), tz["object_id_left"], sc.labels.shape)
    lab_small = sc.labels[::2, ::2]
    by_index = {int(t["object_index"]): t for t in truth["targets"]}
    # the majority truth id of every object, and each target's largest object
    n = len(sc.object_dims_mm)
    major = np.zeros(n, np.int64)
    for lab in range(1, n):
        v = ids[lab_small == lab]
        v = v[v >= 0]
        major[lab] = int(np.bincount(v).argmax()) if v.size else 0
    largest: dict[int, int] = {}
    for lab in range(1, n):
        k = int(major[lab])
        if k in by_index and (k not in largest or sc.object_npx[lab] > sc.object_npx[largest[k]]):
            largest[k] = lab
    X, y = [], []
    counts = {"positive": 0, "negative": 0, "piece": 0}
    for lab in range(1, n):
        if not object_gate(sc, lab):
            continue
        t = by_index.get(int(major[lab]))
        if t is not None and not t["confuser"] and (largest.get(int(major[lab])) != lab or t["difficult"]):
            counts["piece"] += 1
            continue
        label = NONE if t is None or t["confuser"] else str(t["class"])
        if label != NONE and label not in recogniser.targets:
            label = NONE
        X.append(object_features(recogniser.banks, recogniser.targets, sc, lab))
        y.append(label)
        counts["positive" if label != NONE else "negative"] += 1
    return np.asarray(X, dtype=np.float64).reshape(len(X), -1), y, counts


def _mine_unit(work: str, seed: int, options: FieldOptions, recogniser_path: str) -> dict[str, Any]:
    """One mining scene (a jobs-runner unit): simulate, mine, delete; features back."""
    t0 = time.perf_counter()
    d = Path(work) / f"scene_{seed}"
    shutil.rmtree(d, ignore_errors=True)
    try:
        simulate_field(d, replace(options, seed=seed))
        X, y, counts = mine_scene(d, SceneRecogniser.load(recogniser_path))
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return {"seed": seed, "X": X.tolist(), "y": y, "counts": counts, "seconds": time.perf_counter() - t0}


@dataclass(frozen=True)
class MiningOptions:
    """How a scene recogniser is trained (one place per default)."""

    scenes: int = DEFAULT_SCENES
    """Mining scenes simulated for the verifier."""
    channels: tuple[str, ...] = DEFAULT_CHANNELS
    """Filter channels (one bank each)."""
    chip_spec: ChipSpec | None = None
    """Training chips of the banks (None: the bank's default)."""
    bank: BankOptions = BankOptions()
    """How each channel's bank is trained."""
    simulation: FieldOptions = FieldOptions(targets=MINING_TARGETS, confusers=MINING_CONFUSERS)
    """The mining scenes (their ``classes`` are the targets', their seeds from
    :data:`MINING_SEED_BASE`): denser than the scenes scored."""
    C: float = 0.1
    """Inverse L2 strength of the verifier's logistic regression."""


@dataclass(frozen=True)
class MinedRows:
    """The verifier's labelled feature rows from the mining scenes, and what each scene gave."""

    X: NDArray[np.float64]
    y: list[str]
    per_scene: list[dict]


def recogniser_banks(targets: Sequence[tuple[str, SceneMesh]], *, rejects: Sequence[tuple[str, SceneMesh]] | None = None,
                     options: MiningOptions | None = None) -> tuple[tuple, list[str], list[tuple[str, SceneMesh]]]:
    """The filter banks over ``targets`` + ``rejects`` (default :func:`default_rejects`), one
    per channel of the options, the target classes and the refused items."""
    o = MiningOptions() if options is None else options
    if not targets:
        raise InputError("bank train: no targets")
    rej = default_rejects(targets) if rejects is None else list(rejects)
    classes = sorted({c for c, _ in targets})
    clash = sorted({c for c, _ in rej} & set(classes))
    if clash:
        raise InputError(f"bank train: {', '.join(clash)} is both a target class and a class to refuse")
    items = list(targets) + list(rej)
    banks = tuple(train_bank(items, channel=ch, chip_spec=o.chip_spec, **o.bank.train_kwargs()) for ch in o.channels)
    return banks, classes, rej


def mine_rows(banks: Sequence, classes: Sequence[str], specs: Sequence[str], *, options: MiningOptions | None = None,
              run: RunOptions | None = None, progress: Callable[[int, int, str], None] | None = None) -> MinedRows:
    """The verifier's rows of the options' ``scenes`` mining scenes (seeds from
    :data:`MINING_SEED_BASE`), every bank's responses included, scenes as jobs-runner units."""
    o = MiningOptions() if options is None else options
    classes = list(classes)
    placeholder = SceneRecogniser(tuple(banks), tuple(classes),
                                  train_verifier(np.zeros((2, 1)), [classes[0], NONE], classes), {})
    run = RunOptions() if run is None else run
    with tempfile.TemporaryDirectory(prefix="prism3d-mining-") as work:
        rpath = Path(work) / "banks.npz"
        placeholder.save(rpath)
        opts = replace(o.simulation, classes=tuple(specs))
        tasks = [(f"scene {MINING_SEED_BASE + k}", "mining scene", _mine_unit,
                  (work, MINING_SEED_BASE + k, opts, str(rpath))) for k in range(int(o.scenes))]
        report = run_tasks("mining", tasks, replace(run, progress=run.progress or progress))
    if not report.ok:
        raise InputError(f"bank train: mining failed ({report.failure_line()})")
    rows = sorted(report.stats, key=lambda r: r["seed"])
    X = np.vstack([np.asarray(r["X"], dtype=np.float64).reshape(len(r["y"]), -1) for r in rows if r["y"]])
    y = [lab for r in rows for lab in r["y"]]
    per_scene = [{"seed": r["seed"], **r["counts"], "seconds": round(r["seconds"], 1)} for r in rows]
    return MinedRows(X, y, per_scene)


def fit_recogniser(banks: Sequence, classes: Sequence[str], mined: MinedRows, *, C: float = 0.1,
                   metadata: dict | None = None) -> SceneRecogniser:
    """The recogniser of ``banks`` with its verifier and the cascade's prefilter fitted on
    ``mined`` (whose rows hold these banks' responses, in this order)."""
    classes = list(classes)
    verifier = train_verifier(mined.X, mined.y, classes, C=C)
    prefilter, threshold = train_prefilter(mined.X[:, :n_size_features(len(classes))], mined.y)
    return SceneRecogniser(tuple(banks), tuple(classes), verifier, dict(metadata or {}), prefilter, threshold)


def train_scene_recogniser(targets: Sequence[tuple[str, SceneMesh]], specs: Sequence[str], *,
                           rejects: Sequence[tuple[str, SceneMesh]] | None = None,
                           options: MiningOptions | None = None, run: RunOptions | None = None,
                           progress: Callable[[int, int, str], None] | None = None) -> SceneRecogniser:
    """Banks over ``targets`` + ``rejects`` (default :func:`default_rejects`) in each of the
    options' channels, then the verifier mined from the options' ``scenes`` field scenes
    whose bank classes are ``specs`` (the targets as ``simulate field --classes`` takes
    them: built-in names or ``FILE=CLASS:UNITS:UP:FORWARD`` at full size)."""
    o = MiningOptions() if options is None else options
    scenes = o.scenes
    if isinstance(scenes, bool) or int(scenes) != scenes or not 1 <= int(scenes) <= 10_000:
        raise InputError(f"scenes: expected 1-10000 mining scenes, got {scenes!r}")
    t0 = time.perf_counter()
    banks, classes, rej = recogniser_banks(targets, rejects=rejects, options=o)
    if progress:
        progress(0, int(scenes) + 1, "filter banks trained")
    mined = mine_rows(banks, classes, specs, options=o, run=run, progress=progress)
    y = mined.y
    meta = {"targets": [[c, m.name] for c, m in targets], "rejects": [[c, m.name] for c, m in rej],
            "channels": list(o.channels), "mining": {"scenes": int(scenes), "seed_base": MINING_SEED_BASE,
                                                     "field_classes": list(specs),
                                                     "rows": {"positive": sum(v != NONE for v in y),
                                                              "negative": sum(v == NONE for v in y)},
                                                     "per_scene": mined.per_scene},
            "verifier_C": o.C, "seconds": round(time.perf_counter() - t0, 1)}
    return fit_recogniser(banks, classes, mined, C=o.C, metadata=meta)
