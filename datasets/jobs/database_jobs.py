"""Render and feature jobs over a target database, in-process or on a Dask cluster.

A job is split into units (one target x a slice of its poses); a unit writes its chips,
then its manifest part last, both atomically, tagged with the job's spec hash, so a
rerun skips finished units (resume). Units run in this process or on Dask workers
(:class:`RunOptions`). Units, resume and runners: docs/atr.md "Target database and jobs".
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import os
import time
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.chips import (
    CHANNELS,
    ChipSpec,
    as_chip_spec,
    check_ranges,
    render_chips,
    spec_poses,
)
from prism3d.atr.features import model_features, view_features
from prism3d.atr.poses import parse_range
from prism3d.datasets.database.db import (
    DbInfo,
    JobStatus,
    TargetDB,
    as_db,
    check_name,
    open_db,
    read_metadata,
    read_table,
    read_yaml,
    sha256_file,
    target_mesh,
    write_table,
)
from prism3d.datasets.runner import (
    JobReport,
    RunOptions,
    Task,
    check_scheduler,
    execute_tasks,
    run_tasks,
)
from prism3d.errors import DatasetError, Prism3dError
from prism3d.io.atomic import atomic_path, atomic_write_text
from prism3d.io.ply import read_ply

__all__ = [
    "JOB_CHIP_FIELDS",
    "JOB_SCHEMA_VERSION",
    "JobReport",
    "RenderSpec",
    "RunOptions",
    "Unit",
    "check_scheduler",
    "database_info",
    "job_status",
    "plan_units",
    "run_features_job",
    "run_render_job",
    "run_tasks",
    "unit_stats",
    "write_npz_deterministic",
]

log = logging.getLogger(__name__)

JOB_SCHEMA_VERSION = 1
_CHANNELS = CHANNELS
#: ChipSpec fields a render job stores (the others must keep their defaults).
JOB_CHIP_FIELDS = ("size", "channels", "framing", "camouflage", "clutter", "seed", "backend")


# ---------------------------------------------------------------------------------
# Specs and units
# ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderSpec:
    """A render job, stored as ``renders/<job>/job.yaml`` (its JSON hashes the job).

    The chip fields (:data:`JOB_CHIP_FIELDS`) take their defaults from
    :class:`~prism3d.atr.chips.ChipSpec` (:attr:`chip_spec`); ``seed`` is the job seed,
    each unit derives its own from it, the target and the slice.
    """

    name: str
    """Job name (folder name under ``renders/``)."""
    targets: tuple[str, ...]
    """Target ids, fixed when the job is created."""
    azimuth: str = "0:360:30"
    """Azimuth grid, degrees (``"0:360:10"``, ``"10,30"``)."""
    elevation: str = "20"
    """Elevation grid, degrees."""
    range_mm: str | None = None
    """Range grid, mm; None = :func:`~prism3d.atr.chips.default_range_mm` of each target."""
    size: int = ChipSpec.size
    channels: tuple[str, ...] = ChipSpec.channels
    framing: str = ChipSpec.framing
    camouflage: bool = ChipSpec.camouflage
    clutter: str | None = ChipSpec.clutter
    seed: int = ChipSpec.seed
    chips_per_unit: int = 100
    """Poses per unit (50-200 balances overhead and lost work on a kill)."""
    backend: str = ChipSpec.backend

    def __post_init__(self) -> None:
        check_name(self.name, "job")
        if not self.targets:
            raise DatasetError(f"job {self.name}: no targets to render (add targets first)")
        for nm in ("azimuth", "elevation") + (("range_mm",) if self.range_mm is not None else ()):
            v = getattr(self, nm)
            try:
                (check_ranges if nm == "range_mm" else parse_range)(str(v))
            except Prism3dError as exc:
                raise DatasetError(f"{nm}: {exc}") from None
            object.__setattr__(self, nm, str(v))
        if (
            isinstance(self.size, bool)
            or not isinstance(self.size, int)
            or not 8 <= self.size <= 4096
        ):
            raise DatasetError(f"size: expected an integer in [8, 4096], got {self.size!r}")
        chans = tuple(self.channels)
        if not chans or any(c not in _CHANNELS for c in chans) or len(set(chans)) != len(chans):
            raise DatasetError(
                f"channels: expected distinct names among {', '.join(_CHANNELS)}, got {chans}"
            )
        object.__setattr__(self, "channels", chans)
        object.__setattr__(self, "targets", tuple(self.targets))
        if self.framing not in ("fit", "range"):
            raise DatasetError(f"framing: expected fit or range, got {self.framing!r}")
        if self.clutter not in (None, "ground", "noise"):
            raise DatasetError(f"clutter: expected none, ground or noise, got {self.clutter!r}")
        if self.backend not in ("raycast", "pyrender"):
            raise DatasetError(f"backend: expected raycast or pyrender, got {self.backend!r}")
        for nm, lo in (("seed", 0), ("chips_per_unit", 1)):
            v = getattr(self, nm)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise DatasetError(f"{nm}: expected an integer >= {lo}, got {v!r}")

    @classmethod
    def create(
        cls, name: str, targets: Sequence[str], chip_spec: ChipSpec, chips_per_unit: int, *,
        azimuth: str | None = None, elevation: str | None = None, range_mm: str | float | None = None,
    ) -> RenderSpec:
        """The spec of a job rendering ``targets`` at every azimuth x elevation x range with
        ``chip_spec`` (None: the spec's default grid)."""
        extra = [
            f.name for f in fields(ChipSpec)
            if f.name not in JOB_CHIP_FIELDS and getattr(chip_spec, f.name) != f.default
        ]
        if extra:
            raise DatasetError(
                f"chip_spec: a render job stores only {', '.join(JOB_CHIP_FIELDS)}; "
                f"leave {', '.join(extra)} at their defaults"
            )
        return cls(
            name=name,
            targets=tuple(targets),
            azimuth=str(cls.azimuth if azimuth is None else azimuth),
            elevation=str(cls.elevation if elevation is None else elevation),
            range_mm=None if range_mm is None else str(range_mm),
            chips_per_unit=chips_per_unit,
            **{k: getattr(chip_spec, k) for k in JOB_CHIP_FIELDS},
        )

    @property
    def chip_spec(self) -> ChipSpec:
        """The chip settings of this job (job seed; units replace it with their own)."""
        return ChipSpec(**{k: getattr(self, k) for k in JOB_CHIP_FIELDS})

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["targets"] = list(self.targets)
        d["channels"] = list(self.channels)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "job spec") -> RenderSpec:
        allowed = {f.name for f in fields(cls)}
        unknown = set(d) - allowed
        if unknown:
            raise DatasetError(
                f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(allowed)}"
            )
        try:
            return cls(
                **{
                    **d,
                    "targets": tuple(d.get("targets", ())),
                    "channels": tuple(d.get("channels", _CHANNELS)),
                }
            )
        except TypeError as exc:
            raise DatasetError(f"{where}: {exc}") from None

    @property
    def spec_hash(self) -> str:
        """SHA-256 of the canonical JSON of the spec (what a finished unit must match)."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()

    @property
    def n_poses(self) -> int:
        """Poses per target (azimuths x elevations x ranges)."""
        n_r = 1 if self.range_mm is None else len(parse_range(self.range_mm))
        return len(parse_range(self.azimuth)) * len(parse_range(self.elevation)) * n_r


@dataclass(frozen=True)
class Unit:
    """One unit of work: ``target_id`` poses ``[start, stop)``."""

    unit_id: str
    target_id: str
    start: int
    stop: int

    def describe(self) -> str:
        return f"target {self.target_id} poses {self.start}..{self.stop - 1}"


def plan_units(spec: RenderSpec) -> list[Unit]:
    """Split a render job into units (per target, ``chips_per_unit`` poses each)."""
    n = spec.n_poses
    out = []
    for tid in spec.targets:
        for s in range(0, n, spec.chips_per_unit):
            out.append(Unit(f"{tid}-{s:06d}", tid, s, min(n, s + spec.chips_per_unit)))
    return out


# ---------------------------------------------------------------------------------
# Worker-side code
# ---------------------------------------------------------------------------------


def write_npz_deterministic(path: str | Path, arrays: dict[str, NDArray]) -> str:
    """Write arrays as a compressed ``.npz`` with fixed zip timestamps, atomically.

    The same arrays give the same bytes, so the returned sha256 identifies the content.
    """
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            npy = io.BytesIO()
            np.lib.format.write_array(npy, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            zf.writestr(info, npy.getvalue())
    data = buf.getvalue()
    # temp file + rename, without a per-file fsync (it cost 3 ms per chip, more than the
    # rendering, and serialised the workers on the disk): a killed process leaves the
    # old file or the new one; after a power loss, ``verify`` finds damaged chips by hash.
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return hashlib.sha256(data).hexdigest()


def _unit_seed(seed: int, unit: Unit) -> int:
    h = hashlib.sha256(f"{seed}/{unit.target_id}/{unit.start}".encode()).digest()
    return int.from_bytes(h[:4], "little")


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def render_unit(db_path: str, spec: RenderSpec, unit: Unit) -> dict[str, Any]:
    """Render one unit: its chips, then its manifest part (worker entry point).

    Returns
    -------
    dict
        Unit stats: ``unit``, ``chips``, ``seconds``, ``pid``, ``rss_mb``.
    """
    t0 = time.perf_counter()
    db = open_db(db_path)
    check_name(unit.target_id, "target_id")
    mesh, cls = target_mesh(db, unit.target_id)
    chip_spec = replace(spec.chip_spec, seed=_unit_seed(spec.seed, unit))
    poses = spec_poses(mesh, spec.azimuth, spec.elevation, spec.range_mm, chip_spec)
    poses = poses[unit.start : unit.stop]
    chips = render_chips(mesh, poses, chip_spec=chip_spec)
    table = chips.table.drop(columns=["chip", "target"])
    files, shas = [], []
    for i in range(len(poses)):
        idx = unit.start + i
        rel = f"renders/{spec.name}/chips/{unit.target_id}/{idx:06d}.npz"
        shas.append(
            write_npz_deterministic(
                db.resolve(rel, "chip file"), {ch: chips.channels[ch][i] for ch in spec.channels}
            )
        )
        files.append(rel)
    table.insert(0, "target_id", unit.target_id)
    table.insert(1, "class", cls)
    table.insert(2, "chip_index", np.arange(unit.start, unit.stop, dtype=np.int64))
    table.insert(3, "unit", unit.unit_id)
    table["size"] = np.int64(spec.size)
    table["framing"] = spec.framing
    table["chip_file"] = files
    table["channels"] = ",".join(spec.channels)
    table["sha256"] = shas
    stats = {
        "unit": unit.unit_id,
        "chips": len(poses),
        "seconds": round(time.perf_counter() - t0, 4),
        "pid": os.getpid(),
        "rss_mb": round(_rss_mb(), 1),
    }
    part = db.resolve(f"renders/{spec.name}/manifest/part-{unit.unit_id}.parquet", "manifest part")
    write_table(
        table,
        part,
        kind="manifest",
        extra_meta={"prism3d_spec_hash": spec.spec_hash, "prism3d_unit_stats": json.dumps(stats)},
    )
    return stats


def features_unit(db_path: str, job: str, unit_id: str) -> dict[str, Any]:
    """View features of one finished render unit (worker entry point)."""
    t0 = time.perf_counter()
    db = open_db(db_path)
    src = db.job_dir(job) / "manifest" / f"part-{unit_id}.parquet"
    src_sha = sha256_file(src)
    m = read_table(src)
    if "depth" not in str(m["channels"].iloc[0]).split(","):
        raise DatasetError(
            f"job {job}: view features need the depth channel (rendered: {m['channels'].iloc[0]})"
        )
    rows = []
    keep = ["target_id", "class", "chip_index", "az_deg", "el_deg", "range_mm", "roll_deg"]
    for r in m.to_dict("records"):
        with np.load(db.resolve(r["chip_file"], "manifest chip_file"), allow_pickle=False) as z:
            depth = z["depth"]
            mask = z["mask"] if "mask" in z.files else None
        K = np.array([[r["fx"], 0.0, r["cx"]], [0.0, r["fy"], r["cy"]], [0.0, 0.0, 1.0]])
        try:
            # view_features' Hu-moment log evaluates both np.where branches (harmless NaN)
            with np.errstate(invalid="ignore", divide="ignore"):
                f = view_features(depth, mask, K)
        except Prism3dError:
            f = {}  # target not visible: the row keeps NaN features
        rows.append({**{k: r[k] for k in keep}, **f})
    import pandas as pd

    df = pd.DataFrame(rows)
    out = db.path / "features" / job / f"part-{unit_id}.parquet"
    write_table(df, out, kind="view_features", extra_meta={"prism3d_source_sha256": src_sha})
    return {
        "unit": unit_id,
        "chips": len(df),
        "seconds": round(time.perf_counter() - t0, 4),
        "pid": os.getpid(),
        "rss_mb": round(_rss_mb(), 1),
    }


def model_features_unit(db_path: str, target_id: str) -> dict[str, Any]:
    """Model features of one target's normalised model (worker entry point)."""
    import pandas as pd

    db = open_db(db_path)
    t = db.targets()
    r = t[t["target_id"] == target_id].iloc[0]
    ply = read_ply(db.resolve(r["model_file"], "model_file"))
    f = model_features(ply.points, ply.faces, up="z")
    df = pd.DataFrame([{"target_id": target_id, "class": r["class"], **f}])
    write_table(
        df,
        db.path / "features" / "models" / f"part-{target_id}.parquet",
        kind="model_features",
        extra_meta={"prism3d_source_sha256": r["model_sha256"]},
    )
    return {
        "unit": f"model-{target_id}",
        "chips": 0,
        "pid": os.getpid(),
        "rss_mb": round(_rss_mb(), 1),
    }


# ---------------------------------------------------------------------------------
# Runners
# ---------------------------------------------------------------------------------


def load_spec(db: TargetDB, job: str) -> RenderSpec:
    """The stored spec of render job ``job``."""
    f = db.job_dir(job) / "job.yaml"
    if not f.is_file():
        raise DatasetError(
            f"{db.path}: no render job {job!r}; jobs: {', '.join(db.jobs()) or 'none'}"
        )
    d = read_yaml(f)
    if not isinstance(d, dict) or d.get("schema_version") != JOB_SCHEMA_VERSION:
        raise DatasetError(
            f"{f}: unknown schema_version {d.get('schema_version') if isinstance(d, dict) else None!r} "
            f"(this prism3d reads {JOB_SCHEMA_VERSION})"
        )
    d = dict(d)
    d.pop("schema_version")
    d.pop("spec_hash", None)
    return RenderSpec.from_dict(d, str(f))


def _part_done(part: Path, key: str, value: str) -> bool:
    if not part.is_file():
        return False
    try:
        return read_metadata(part).get(key) == value
    except DatasetError:
        return False


def run_render_job(
    db: TargetDB | str | Path,
    job: str,
    *,
    azimuth: str = RenderSpec.azimuth,
    elevation: str = RenderSpec.elevation,
    range_mm: str | None = None,
    chip_spec: ChipSpec | None = None,
    targets: Sequence[str] | None = None,
    classes: Sequence[str] | None = None,
    chips_per_unit: int = RenderSpec.chips_per_unit,
    run: RunOptions | None = None,
) -> JobReport:
    """Create (or resume) render job ``job`` and run its unfinished units.

    The first run stores the spec (targets resolved from ``targets`` ids and/or
    ``classes``, default every target; chips per ``chip_spec``, None = ``ChipSpec()``)
    in ``renders/<job>/job.yaml``; a rerun with the same parameters resumes, with others
    it raises :class:`DatasetError` (as for unknown targets). ``run``: where units run.
    The report's ``exit_code`` is 1 when a unit failed after its retries.
    """
    t0 = time.perf_counter()
    db = as_db(db)
    run = RunOptions() if run is None else run
    chosen = _select_targets(db, job, targets, classes)
    check_scheduler(run.scheduler)  # before anything is written
    spec = RenderSpec.create(job, chosen, as_chip_spec(chip_spec), chips_per_unit, azimuth=azimuth,
                             elevation=elevation, range_mm=range_mm)
    with _job_lock(db, job):
        _store_spec(db, spec)
        report = _run_units(db, spec, run)
    report.seconds = time.perf_counter() - t0
    return report


@contextlib.contextmanager
def _job_lock(db: TargetDB, job: str) -> Iterator[None]:
    """Hold ``renders/<job>/.lock`` for a run: a second run of the same job is refused,
    and the temporary files found on entry belong to no live writer (a killed run's),
    so they are removed."""
    import fcntl

    jdir = db.resolve(f"renders/{job}", "job folder")
    jdir.mkdir(parents=True, exist_ok=True)
    fd = os.open(jdir / ".lock", os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DatasetError(f"job {job}: another process is running it; wait for it or stop it") from None
        for f in jdir.rglob(".*.tmp*"):
            f.unlink(missing_ok=True)
        yield
    finally:
        os.close(fd)


def _run_units(db: TargetDB, spec: RenderSpec, run: RunOptions) -> JobReport:
    """Run the units of a stored spec not yet done (resume)."""
    job = spec.name
    units = plan_units(spec)
    report = JobReport(job=job, total_units=len(units))
    mdir = db.job_dir(job) / "manifest"
    tasks: list[Task] = []
    for u in units:
        if _part_done(mdir / f"part-{u.unit_id}.parquet", "prism3d_spec_hash", spec.spec_hash):
            report.skipped_units += 1
        else:
            tasks.append((u.unit_id, u.describe(), render_unit, (str(db.path), spec, u)))
    execute_tasks(tasks, report, run)
    return report


def _select_targets(
    db: TargetDB, job: str, targets: Sequence[str] | None, classes: Sequence[str] | None
) -> tuple[str, ...]:
    """Target ids of a job: ``targets`` and/or ``classes``, else the stored job's, else all."""
    table = db.targets()
    ids = list(table["target_id"])
    if targets:
        unknown = [t for t in targets if t not in ids]
        if unknown:
            raise DatasetError(
                f"targets: unknown target ids {unknown}; known: {', '.join(ids) or 'none'}"
            )
    sel = table
    if targets:
        sel = sel[sel["target_id"].isin(list(targets))]
    if classes:
        sel = sel[sel["class"].isin(list(classes))]
    if (db.job_dir(job) / "job.yaml").is_file() and not targets and not classes:
        return load_spec(db, job).targets  # resume with the job's targets (new ones are not added)
    return tuple(sorted(sel["target_id"]))


def _store_spec(db: TargetDB, spec: RenderSpec) -> None:
    """Write ``job.yaml``, or check that the stored spec is the same."""
    import yaml

    jf = db.job_dir(spec.name) / "job.yaml"
    if jf.is_file():
        old = load_spec(db, spec.name)
        if old.spec_hash != spec.spec_hash:
            new = spec.to_dict()
            diff = {k: (v, new[k]) for k, v in old.to_dict().items() if new[k] != v}
            raise DatasetError(
                f"job {spec.name!r} exists with a different spec (stored vs given: {diff}); "
                "rerun with the same parameters to resume, or choose a new --job name"
            )
        return
    head = {"schema_version": JOB_SCHEMA_VERSION, "spec_hash": spec.spec_hash}
    atomic_write_text(jf, yaml.safe_dump({**head, **spec.to_dict()}, sort_keys=False))


def run_features_job(
    db: TargetDB | str | Path,
    job: str,
    *,
    run: RunOptions | None = None,
    models: bool = True,
) -> JobReport:
    """Features of render job ``job`` (``prism3d db features DB --job NAME``).

    Writes ``features/<job>/part-<unit>.parquet`` (view features of every chip of
    each finished render unit; needs the depth channel) and, with ``models``,
    ``features/models/part-<target_id>.parquet`` (model features of each target of the
    job). Resumable: a part whose recorded source sha256 matches is skipped.
    """
    t0 = time.perf_counter()
    db = as_db(db)
    run = RunOptions() if run is None else run
    spec = load_spec(db, job)
    check_scheduler(run.scheduler)
    if "depth" not in spec.channels:
        raise DatasetError(
            f"job {job}: view features need the depth channel (rendered: {', '.join(spec.channels)})"
        )
    mdir = db.job_dir(job) / "manifest"
    fdir = db.path / "features" / job
    tasks: list[Task] = []
    report = JobReport(job=f"{job}-features")
    for part in sorted(mdir.glob("part-*.parquet")):
        unit_id = part.stem[len("part-") :]
        report.total_units += 1
        if _part_done(fdir / part.name, "prism3d_source_sha256", sha256_file(part)):
            report.skipped_units += 1
        else:
            tasks.append(
                (
                    unit_id,
                    f"features of render unit {unit_id}",
                    features_unit,
                    (str(db.path), job, unit_id),
                )
            )
    if models:
        t = db.targets().set_index("target_id")
        for tid in spec.targets:
            report.total_units += 1
            f = db.path / "features" / "models" / f"part-{tid}.parquet"
            if _part_done(f, "prism3d_source_sha256", str(t.loc[tid, "model_sha256"])):
                report.skipped_units += 1
            else:
                tasks.append(
                    (
                        f"model-{tid}",
                        f"model features of {tid}",
                        model_features_unit,
                        (str(db.path), tid),
                    )
                )
    execute_tasks(tasks, report, run)
    report.seconds = time.perf_counter() - t0
    return report


def job_status(db: TargetDB, job: str) -> JobStatus:
    """How far render job ``job`` is."""
    import pyarrow.parquet as pq

    spec = load_spec(db, job)
    units = plan_units(spec)
    mdir = db.job_dir(job) / "manifest"
    done = chips = 0
    for u in units:
        p = mdir / f"part-{u.unit_id}.parquet"
        if _part_done(p, "prism3d_spec_hash", spec.spec_hash):
            done += 1
            chips += pq.read_metadata(str(p)).num_rows
    fdir = db.path / "features" / job
    return JobStatus(len(units), done, chips, fdir.is_dir() and any(fdir.glob("part-*.parquet")))


def database_info(db: TargetDB | str | Path) -> DbInfo:
    """:meth:`TargetDB.info` with each render job's completion (:func:`job_status`)."""
    db = as_db(db)
    info = db.info()
    return replace(info, jobs={job: job_status(db, job) for job in info.jobs})


def unit_stats(db: TargetDB | str | Path, job: str) -> Any:
    """Per-unit worker stats of a render job (``pid``, ``rss_mb``, ``seconds``, ``chips``)
    from the manifest parts' metadata, as a DataFrame."""
    import pandas as pd

    db = as_db(db)
    rows = []
    for p in sorted((db.job_dir(job) / "manifest").glob("part-*.parquet")):
        s = read_metadata(p).get("prism3d_unit_stats")
        if s:
            rows.append(json.loads(s))
    return pd.DataFrame(rows)
