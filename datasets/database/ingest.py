"""Adding targets to a database: mesh files (explicit units and up axis) and built-ins.

Each target becomes a row of ``targets.parquet`` and a normalised ``models/<id>.ply``
(binary, mm, z up / x forward, origin at the footprint centre on the ground, comments
``units mm`` and ``up z``). Units are never guessed (flag, ``FILE.units.yaml`` sidecar
or PLY comment); duplicates are found by SHA-256; everything is checked before the DB
is touched, and the table is replaced atomically under ``DB/.lock``. Details:
docs/targets.md.
"""

from __future__ import annotations

import logging
import math
import re
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.chips import load_mesh_file
from prism3d.atr.features import read_units_sidecar
from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.database.db import (
    TABLE_SCHEMA_VERSION,
    TargetDB,
    as_db,
    check_name,
    sha256_file,
    utc_timestamp,
    write_table,
)
from prism3d.datasets.models.targets import builtin_target, export_builtin_target, list_builtin_targets
from prism3d.errors import DatasetError, Prism3dError
from prism3d.io.atomic import atomic_write_bytes
from prism3d.io.mesh import UNITS_MM
from prism3d.io.ply import read_ply, write_ply
from prism3d.io.units import FORWARD_AXES, declared_forward, declared_units, forward_yaw_deg

__all__ = [
    "mesh_units",
    "size_warning",
    "CLASS_LENGTH_M",
    "KIT_SCALE",
    "MESH_SUFFIXES",
    "QUATERNIUS_VEHICLES",
    "UNITS_MM",
    "AddReport",
    "add_builtin",
    "add_meshes",
    "add_quaternius_vehicles",
]

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
_UPS = ("y", "z")
MAX_ID_LEN = 100  # target ids are file names: well under every file system's limit


@dataclass
class AddReport:
    """What an ``add`` did."""

    added: list[str] = field(default_factory=list)
    """New target ids."""
    skipped: list[str] = field(default_factory=list)
    """One message per duplicate that was skipped."""

    def summary(self) -> str:
        lines = [
            f"added {len(self.added)} target(s)"
            + (f": {', '.join(self.added)}" if self.added else "")
        ]
        lines += [f"skipped: {m}" for m in self.skipped]
        return "\n".join(lines)


@dataclass
class _Pending:
    """A loaded target, ready to be written (model PLY bytes already generated)."""

    name: str
    target_class: str
    source_kind: str
    source_file: str
    source_sha256: str
    model_bytes: bytes
    units: str
    scale_to_mm: float
    up: str
    dims: tuple[float, float, float]
    n_vertices: int
    n_faces: int
    provenance: str
    builtin_scale: float = float("nan")
    coverage: float = float("nan")


#: Longest target accepted, mm: 1 km, beyond the largest ship; 1e300 is a typo.
MAX_TARGET_LENGTH_MM = 1e6


def _sanitize(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_.\-]", "_", name).strip("._-") or "target"
    return s[:MAX_ID_LEN]


def _file_units(path: Path) -> tuple[str | None, str | None]:
    """``(units, up)`` a PLY file declares in its comments; ``(None, None)`` for other types."""
    if path.suffix.lower() != ".ply":
        return None, None
    try:
        ply = read_ply(path)
    except Prism3dError as exc:
        raise DatasetError(f"{path}: cannot read PLY ({exc})") from None
    return declared_units(ply.comments)


def check_length_mm(length_mm: object) -> float:
    """A stated target length (mm): finite, positive, at most MAX_TARGET_LENGTH_MM."""
    if not (isinstance(length_mm, (int, float)) and not isinstance(length_mm, bool) and math.isfinite(length_mm)
            and 0 < length_mm <= MAX_TARGET_LENGTH_MM):
        raise DatasetError(f"length_mm: expected a length in (0, {MAX_TARGET_LENGTH_MM:g}] mm, got {length_mm!r}")
    return float(length_mm)


def mesh_units(path: Path, units: str | None, up: str | None, *, rescaled: bool = False) -> tuple[str, str]:
    """Units and up axis of a mesh file, one rule for every command that reads one:
    the given ``units``/``up`` (flags or a per-target spec), a ``FILE.units.yaml`` sidecar
    or a PLY's ``units``/``up`` comments; a contradiction is an error, and nothing is
    guessed (DatasetError naming what to pass). ``rescaled``: the mesh is rescaled to a
    stated length, so undeclared units do not matter (read as mm)."""
    try:
        side = read_units_sidecar(path) or {}
    except Prism3dError as exc:
        raise DatasetError(str(exc)) from None
    file_units, file_up = _file_units(path)
    for nm, v, allowed in (("units", units, UNITS_MM), ("up", up, _UPS)):
        if v is not None and v not in allowed:
            raise DatasetError(f"{nm}: expected one of {', '.join(allowed)}, got {v!r}")
    declared = side.get("units", file_units)
    if declared is not None and units is not None and declared != units:
        raise DatasetError(
            f"{path}: declares units {declared!r} (sidecar or PLY comment) but units={units!r} was given"
        )
    u = declared if declared is not None else units
    if u is None and rescaled:
        u = "mm"
    if u is None:
        raise DatasetError(
            f"{path}: units unknown; pass --units (mm, cm, m, in) or write {path.name}.units.yaml "
            "with 'units: ...' and 'up: ...' (units are never guessed)"
        )
    if u not in UNITS_MM:
        raise DatasetError(f"{path}: units: expected one of {', '.join(UNITS_MM)}, got {u!r}")
    if "up" in side and up is not None and side["up"] != up:
        raise DatasetError(f"{path}: sidecar says up {side['up']!r} but up={up!r} was given")
    up_v = side.get("up", up)
    if up_v is None and file_units is not None:
        up_v = file_up or "z"  # prism3d PLY files are z up
    if up_v is None:
        raise DatasetError(
            f"{path}: up axis unknown; pass --up (y or z) or set 'up:' in {path.name}.units.yaml"
        )
    if up_v not in _UPS:
        raise DatasetError(f"{path}: up: expected one of {', '.join(_UPS)}, got {up_v!r}")
    return u, up_v


def mesh_forward(path: Path, forward: str | None, up: str) -> str:
    """The axis of a mesh file its vehicle's nose points along, one rule as for units:
    the given ``forward`` (a flag or a per-target spec), the ``FILE.units.yaml`` sidecar's
    ``forward``, or a PLY's ``frame x forward`` / ``forward x`` comment; a contradiction is
    an error and nothing is guessed (the heading of every detection and chip depends on it)."""
    try:
        side = read_units_sidecar(path) or {}
    except Prism3dError as exc:
        raise DatasetError(str(exc)) from None
    if forward is not None and forward not in FORWARD_AXES:
        raise DatasetError(f"forward: expected one of {', '.join(FORWARD_AXES)}, got {forward!r}")
    declared = side.get("forward")
    if declared is None and path.suffix.lower() == ".ply":
        try:
            declared = declared_forward(read_ply(path).comments)
        except Prism3dError as exc:
            raise DatasetError(f"{path}: cannot read PLY ({exc})") from None
    if declared is not None and forward is not None and declared != forward:
        raise DatasetError(f"{path}: declares forward {declared!r} (sidecar or PLY comment) but forward={forward!r} "
                           "was given")
    f = forward if forward is not None else declared
    if f is None:
        raise DatasetError(f"{path}: forward axis unknown; give FILE=CLASS:UNITS:UP:FORWARD (x, -x, y, -y, z, -z: "
                           f"where the nose points), --forward, or 'forward: ...' in {path.name}.units.yaml")
    try:
        forward_yaw_deg(f, up)
    except ValueError as exc:
        raise DatasetError(f"{path}: {exc}") from None
    return f


def _model_bytes(mesh: Any, comments: list[str]) -> bytes:
    cols = (
        mesh.vertex_albedo
        if mesh.vertex_albedo is not None
        else np.full((len(mesh.vertices), 3), 0.7)
    )
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "m.ply"
        write_ply(f, mesh.vertices, colors=cols, faces=mesh.faces, comments=comments)
        return f.read_bytes()


def _scaled_to_length(path: Path, mesh: SceneMesh, length_mm: float) -> tuple[SceneMesh, float]:
    """``mesh`` scaled so its larger horizontal extent is ``length_mm``, and the factor."""
    check_length_mm(length_mm)
    ext = float(np.max(np.ptp(mesh.vertices[:, :2], axis=0)))
    if not ext > 0:
        raise DatasetError(f"{path}: degenerate mesh (zero horizontal extent)")
    k = float(length_mm) / ext
    mesh = SceneMesh(
        mesh.vertices * k, mesh.faces, vertex_albedo=mesh.vertex_albedo, name=mesh.name
    )
    return mesh, k


def _model_comments(path: Path, sha: str, scale: float) -> list[str]:
    """PLY comments of a normalised model: its frame and units, source file and scale."""
    return [
        "units mm",
        "up z",
        "prism3d normalised target model (x forward, y left, z up)",
        f"source {path.name} sha256 {sha}",
        f"scale_to_mm {scale:.9g}",
    ]


def _load_file(
    path: Path,
    target_class: str,
    units: str | None,
    up: str | None,
    length_mm: float | None,
    yaw_deg: float,
) -> _Pending:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DatasetError(
            f"{path}: unsupported mesh format {path.suffix!r}; expected one of {' '.join(MESH_SUFFIXES)}"
        )
    u, up_v = mesh_units(path, units, up, rescaled=length_mm is not None)
    try:
        mesh = load_mesh_file(path, units=u, up=up_v, yaw_deg=yaw_deg)
    except Prism3dError as exc:
        raise DatasetError(f"{path}: cannot load mesh ({exc})") from None
    scale = UNITS_MM[u]
    if length_mm is not None:
        mesh, k = _scaled_to_length(path, mesh, length_mm)
        scale *= k
    dims = tuple(float(x) for x in np.ptp(mesh.vertices, axis=0))
    if not all(math.isfinite(d) for d in dims) or max(dims) <= 0:
        raise DatasetError(f"{path}: degenerate mesh (extents {dims})")
    warning = size_warning(path.name, target_class, max(dims[0], dims[1]), u)
    if warning:
        log.warning("%s", warning)
    sha = sha256_file(path)
    comments = _model_comments(path, sha, scale)
    kind, provenance, coverage = "file", f"file {path.name}", float("nan")
    if _is_scan(path):
        kind = "scan"
        provenance, coverage = _scan_provenance(path, mesh.vertices)
    return _Pending(
        name=path.stem,
        target_class=target_class,
        source_kind=kind,
        source_file=str(path.resolve()),
        source_sha256=sha,
        model_bytes=_model_bytes(mesh, comments),
        units=u,
        scale_to_mm=scale,
        up=up_v,
        dims=dims,  # type: ignore[arg-type]
        n_vertices=len(mesh.vertices),
        n_faces=len(mesh.faces),
        provenance=provenance,
        coverage=coverage,
    )


#: Full-size length range per class, m (main battle tanks, fighters to airliners, boats
#: to the largest ships, trucks, cars to buses); a model is plausible from a 1:700 kit
#: (the smallest hobby scale) to full size.
CLASS_LENGTH_M = {"tank": (4.0, 12.0), "jet": (8.0, 40.0), "aircraft": (5.0, 85.0),
                  "ship": (3.0, 460.0), "truck": (4.0, 25.0), "vehicle": (2.5, 25.0)}
SMALLEST_KIT_SCALE = 1 / 700


def size_warning(name: str, target_class: str, length_mm: float, units: str) -> str | None:
    """A warning when a mesh's length in its stated ``units`` is implausible for its class
    (a ModelNet airplane read as metres is a 357 m biplane); None when plausible or the
    class is not one of :data:`CLASS_LENGTH_M`."""
    rng = CLASS_LENGTH_M.get(target_class)
    if rng is None or not math.isfinite(length_mm):
        return None
    lo, hi = rng[0] * 1000 * SMALLEST_KIT_SCALE, rng[1] * 1000
    if lo <= length_mm <= hi:
        return None
    how, fix = ((f"with units {units!r}", "check the units or give --length-mm") if units != "--length-mm"
                else ("as --length-mm says", "check the length"))
    return (f"{name}: {length_mm / 1000:.4g} m long {how} is implausible for the class {target_class!r} "
            f"(a model of one is {lo / 1000:.3g}-{hi / 1000:.3g} m); {fix}")


#: A direction of the view sphere counts as observed within this angle of a camera's.
COVERAGE_ANGLE_DEG = 45.0
_COVERAGE_SAMPLES = 2000


def _is_scan(path: Path) -> bool:
    """A model ``prism3d stitch`` wrote (its PLY header says so)."""
    if path.suffix.lower() != ".ply":
        return False

    try:
        return any(c.startswith("prism3d stitch") for c in read_ply(path).comments)
    except Prism3dError:
        return False


def _ply_meta(path: Path) -> dict[str, str]:
    """``key value`` comments of a PLY header (the scan's metadata); {} when unreadable."""
    try:
        comments = read_ply(path).comments
    except Prism3dError:
        return {}
    return dict(c.split(" ", 1) for c in comments if " " in c)


def _scan_provenance(path: Path, vertices: NDArray) -> tuple[str, float]:
    """What a scanned model came from (``poses.json`` beside it: its hash, the scans' hashes)
    and its coverage: the share of the view sphere within COVERAGE_ANGLE_DEG of a camera,
    and the elevation below which nothing was seen. Without poses.json: unknown (NaN)."""
    import json

    poses = path.parent / "poses.json"
    if not poses.is_file():
        return f"scan {path.name}; no poses.json beside it: views and coverage unknown", float("nan")
    try:
        doc = json.loads(poses.read_text(encoding="utf-8"))
        Ts = [np.asarray(s["T_model_scan"], np.float64) for s in doc["scans"]]
        T_om = np.asarray(doc.get("object_frame", {}).get("T_object_model", np.eye(4)), np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{poses}: not a prism3d stitch poses file ({exc})") from None
    scan_hashes, shots, calibs = [], [], []
    for s_ in doc["scans"]:
        f = Path(s_.get("path", ""))
        f = f if f.is_absolute() else poses.parent / f
        scan_hashes.append(sha256_file(f) if f.is_file() else "missing")
        if f.is_file():  # what `prism3d reconstruct` wrote in the scan's header
            meta = _ply_meta(f)
            shots.append(meta.get("shot_sha256", "unknown"))
            calibs.append(meta.get("calibration_sha256", "unknown"))
    import hashlib

    views = hashlib.sha256(" ".join(scan_hashes).encode()).hexdigest()
    shot_text = (f", shots sha256 {hashlib.sha256(' '.join(shots).encode()).hexdigest()}"
                 if shots and "unknown" not in shots else ", shots unknown")
    cal_set = sorted(set(calibs))
    cal_text = (f", calibration sha256 {cal_set[0]}" if len(cal_set) == 1 and cal_set[0] != "unknown"
                else ", calibration unknown" if not cal_set or "unknown" in cal_set
                else f", calibrations sha256 {' '.join(cal_set)}")
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    cams = np.array([(T_om @ T[:, 3])[:3] for T in Ts]) - centre
    cams /= np.linalg.norm(cams, axis=1, keepdims=True)
    k = np.arange(_COVERAGE_SAMPLES) + 0.5
    z = 1 - 2 * k / _COVERAGE_SAMPLES  # a Fibonacci sphere: equal-area directions
    phi = np.pi * (1 + 5**0.5) * k
    sphere = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    seen = (sphere @ cams.T).max(axis=1) >= np.cos(np.radians(COVERAGE_ANGLE_DEG))
    coverage = float(seen.mean())
    lowest = float(np.degrees(np.arcsin(z[seen].min()))) if seen.any() else 90.0
    missing = sum(h == "missing" for h in scan_hashes)
    text = (f"scan of {len(Ts)} views (poses.json sha256 {sha256_file(poses)}, scans sha256 {views}"
            + shot_text + cal_text
            + (f", {missing} scan files not found" if missing else "")
            + f"); coverage {coverage:.2f} of the view sphere, nothing seen below {lowest:.0f} deg elevation")
    return text, coverage


def _commit(db: TargetDB, pending: list[_Pending], strict: bool) -> AddReport:
    """Under the DB lock: skip duplicates, write models, then the targets table."""
    import pandas as pd

    report = AddReport()
    with db.lock():
        table = db.targets()
        by_sha = dict(zip(table["source_sha256"], table["target_id"]))
        ids = set(table["target_id"])
        rows = []
        for p in pending:
            if p.source_sha256 in by_sha:
                msg = f"{p.source_file}: already in the database as {by_sha[p.source_sha256]} (same sha256)"
                if strict:
                    raise DatasetError(f"duplicate: {msg}")
                log.info("skipping duplicate %s", msg)
                report.skipped.append(msg)
                continue
            tid = _sanitize(p.name)
            k = 2
            while tid in ids:
                tid = f"{_sanitize(p.name)}_{k}"
                k += 1
            ids.add(tid)
            by_sha[p.source_sha256] = tid
            rows.append((tid, p))
        written: list[Path] = []  # removed again if the table cannot be written
        try:
            new_rows = _write_models(db, rows, written)
            report.added.extend(r["target_id"] for r in new_rows)
            if new_rows:
                new = pd.DataFrame(new_rows, columns=list(table.columns))
                out = new if len(table) == 0 else pd.concat([table, new], ignore_index=True)
                write_table(out, db.targets_file, kind="targets")
        except BaseException:
            for f in written:
                f.unlink(missing_ok=True)
            raise
    return report


def _write_models(db: TargetDB, rows: list[tuple[str, _Pending]], written: list[Path]) -> list[dict]:
    """Write each new target's model file (appending to ``written`` the ones this call
    created) and return the targets-table rows."""
    new_rows = []
    for tid, p in rows:
        rel = f"models/{tid}.ply"
        f = db.path / rel
        existed = f.exists()
        atomic_write_bytes(f, p.model_bytes)
        if not existed:
            written.append(f)
        new_rows.append({
            "target_id": tid, "class": p.target_class, "name": p.name,
            "source_kind": p.source_kind, "source_file": p.source_file,
            "source_sha256": p.source_sha256, "model_file": rel,
            "model_sha256": _sha_bytes(p.model_bytes), "units": p.units,
            "scale_to_mm": float(p.scale_to_mm), "up": p.up,
            "length_mm": p.dims[0], "width_mm": p.dims[1], "height_mm": p.dims[2],
            "n_vertices": p.n_vertices, "n_faces": p.n_faces, "provenance": p.provenance,
            "builtin_scale": float(p.builtin_scale), "coverage": float(p.coverage), "added": utc_timestamp(),
            "schema_version": TABLE_SCHEMA_VERSION,
        })
    return new_rows


def _sha_bytes(b: bytes) -> str:
    import hashlib

    return hashlib.sha256(b).hexdigest()


def _check_dups(db: TargetDB, pending: list[_Pending], strict: bool) -> None:
    """Strict mode: refuse duplicates (in the DB or within the batch) before writing."""
    if not strict:
        return
    known = set(db.targets()["source_sha256"])
    seen: set[str] = set()
    for p in pending:
        if p.source_sha256 in known or p.source_sha256 in seen:
            raise DatasetError(
                f"duplicate: {p.source_file} is already in the database (same sha256); nothing added"
            )
        seen.add(p.source_sha256)


def add_meshes(
    db: TargetDB | str | Path,
    paths: Sequence[str | Path],
    *,
    target_class: str,
    units: str | None = None,
    up: str | None = None,
    length_mm: float | None = None,
    yaw_deg: float = 0.0,
    strict: bool = False,
) -> AddReport:
    """Add mesh files as targets (``prism3d db add DB MESH... --class C --units U --up A``).

    ``paths``: OBJ, PLY, GLB/glTF, OFF or STL files, all of class ``target_class``.
    ``units`` (mm cm m in) and ``up`` (y z) unless a sidecar ``FILE.units.yaml`` or a
    PLY comment declares them (a contradiction is an error). ``length_mm``: rescale so
    the longest horizontal extent is this long (recorded in ``scale_to_mm``);
    ``yaw_deg``: rotation about up to put the nose on +x; ``strict``: a duplicate (same
    source sha256) is an error, not a skip. Raises DatasetError (nothing written) on a
    missing file, bad format, unknown units/up, corrupt mesh or strict duplicate.
    """
    db = as_db(db)
    check_name(target_class, "class")
    if isinstance(paths, (str, Path)):
        paths = [paths]
    if not paths:
        raise DatasetError("add: no mesh files given")
    if not math.isfinite(float(yaw_deg)):
        raise DatasetError(f"yaw_deg: expected a finite angle, got {yaw_deg!r}")
    pending = [
        _load_file(Path(p), target_class, units, up, length_mm, float(yaw_deg)) for p in paths
    ]
    _check_dups(db, pending, strict)
    return _commit(db, pending, strict)


def add_builtin(
    db: TargetDB | str | Path,
    names: Sequence[str] | None = None,
    *,
    scale: float | str = "model",
    strict: bool = False,
) -> AddReport:
    """Add built-in targets (``prism3d db add DB --builtin [NAMES...]``).

    The model file is the exported PLY (:func:`~prism3d.datasets.models.targets.export_builtin_target`,
    paint sampled at vertices); render jobs use the exact procedural paint of
    :func:`~prism3d.datasets.models.targets.builtin_target` at the same ``scale``. The
    duplicate key is the sha256 of the generated model.
    """
    db = as_db(db)
    all_names = list_builtin_targets()
    names = list_builtin_targets("military") if not names else list(names)  # no names: the military set
    for n in names:
        if n not in all_names:
            raise DatasetError(
                f"unknown built-in target {n!r}; valid names: {', '.join(all_names)}"
            )
    pending = []
    with tempfile.TemporaryDirectory() as d:
        for n in names:
            try:
                mesh = builtin_target(n, scale=scale)
                f = export_builtin_target(n, Path(d) / f"{n}.ply", scale=scale)
            except Prism3dError as exc:
                raise DatasetError(f"built-in {n}: {exc}") from None
            data = f.read_bytes()
            md = mesh.metadata
            pending.append(
                _Pending(
                    name=n,
                    target_class=md["class"],
                    source_kind="builtin",
                    source_file=f"builtin:{n}",
                    source_sha256=_sha_bytes(data),
                    model_bytes=data,
                    units="mm",
                    scale_to_mm=1.0,
                    up="z",
                    dims=(md["length_mm"], md["width_mm"], md["height_mm"]),
                    n_vertices=len(mesh.vertices),
                    n_faces=len(mesh.faces),
                    provenance=f"{md['provenance']} {md['model_scale_label']} scale {md['scale']:.9g}",
                    builtin_scale=float(md["scale"]),
                )
            )
    _check_dups(db, pending, strict)
    return _commit(db, pending, strict)


#: Ingest policy of the Quaternius CC0 low-poly vehicles (``meshes/quaternius_vehicles_cc0``
#: of the shared test data): ``name -> (class, up, yaw_deg, nominal real length m)``.
#: The files' coordinates are in arbitrary FBX units (extents 40-1800 after the
#: assimp conversion), so "units" are declared as ``m`` (what glTF says) and every
#: model is then rescaled to its nominal real length x the hobby kit scale of its
#: class (:data:`KIT_SCALE`), like the built-in targets. glTF is y up; the car pack
#: was exported z up. ``yaw_deg`` puts the long axis on x (ships, vans, cars).
QUATERNIUS_VEHICLES: dict[str, tuple[str, str, float, float]] = {
    "tank_1": ("tank", "y", 0.0, 7.5),
    "tank_2": ("tank", "y", 0.0, 7.5),
    "tank_3": ("tank", "y", 0.0, 7.0),
    "tank_4": ("tank", "y", 0.0, 7.5),
    "airplane_military_1": ("jet", "y", 0.0, 17.0),
    "airplane_military_2": ("jet", "y", 0.0, 17.0),
    "airplane_commercial": ("aircraft", "y", 0.0, 40.0),
    "airplane_private": ("aircraft", "y", 0.0, 9.0),
    "airplane_small": ("aircraft", "y", 0.0, 7.0),
    "ship_boat": ("ship", "y", 90.0, 8.0),
    "ship_cruise": ("ship", "y", 90.0, 300.0),
    "ship_lifeboat": ("ship", "y", 90.0, 7.0),
    "ship_sail": ("ship", "y", 90.0, 40.0),
    "ship_viking": ("ship", "y", 90.0, 23.0),
    "car_normal_1": ("vehicle", "z", 90.0, 4.5),
    "car_police_suv": ("vehicle", "z", 90.0, 4.8),
    "car_sports": ("vehicle", "z", 90.0, 4.4),
    "car_suv": ("vehicle", "z", 90.0, 4.8),
    "bus": ("vehicle", "y", 0.0, 12.0),
    "bus_school": ("vehicle", "y", 0.0, 11.0),
    "van_ambulance": ("vehicle", "y", 90.0, 6.0),
}
#: Kit scale per class for :data:`QUATERNIUS_VEHICLES` (models of 30-600 mm).
KIT_SCALE = {"tank": 1 / 35, "jet": 1 / 72, "aircraft": 1 / 72, "ship": 1 / 700, "vehicle": 1 / 35}


def add_quaternius_vehicles(
    db: TargetDB | str | Path,
    folder: str | Path,
    *,
    names: Sequence[str] | None = None,
    strict: bool = False,
) -> AddReport:
    """Add the Quaternius CC0 vehicles (``folder/glb/<name>.glb``) with the documented
    policy :data:`QUATERNIUS_VEHICLES` (class, up axis, yaw, kit-scale length)."""
    folder = Path(folder)
    report = AddReport()
    for n in names or list(QUATERNIUS_VEHICLES):
        if n not in QUATERNIUS_VEHICLES:
            raise DatasetError(
                f"unknown Quaternius model {n!r}; known: {', '.join(QUATERNIUS_VEHICLES)}"
            )
        cls, up, yaw, length_m = QUATERNIUS_VEHICLES[n]
        r = add_meshes(
            db,
            [folder / "glb" / f"{n}.glb"],
            target_class=cls,
            units="m",
            up=up,
            yaw_deg=yaw,
            length_mm=length_m * 1000.0 * KIT_SCALE[cls],
            strict=strict,
        )
        report.added += r.added
        report.skipped += r.skipped
    return report
