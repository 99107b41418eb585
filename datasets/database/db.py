"""The target database: a plain folder of YAML, Parquet, PLY and ``.npz`` files.

Create, open, read (with schema checks), load chips, summarise and verify a database.
The folder format is ``datasets/FORMAT.md`` (layout also in docs/atr.md); it is
readable without prism3d (pandas, pyarrow, DuckDB).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import logging
import os
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.models.targets import builtin_target
from prism3d.errors import DatasetError, InputError
from prism3d.io.atomic import atomic_path, staged_folder
from prism3d.io.hashes import sha256_file  # noqa: F401 - re-exported: callers import it from here
from prism3d.io.ply import read_ply

__all__ = [
    "target_mesh",
    "DB_SCHEMA_VERSION",
    "TABLE_SCHEMA_VERSION",
    "TARGET_COLUMNS",
    "TargetDB",
    "as_db",
    "check_add_request",
    "check_name",
    "DbInfo",
    "JobStatus",
    "init_db",
    "open_db",
    "read_table",
    "read_yaml",
    "sha256_file",
    "utc_timestamp",
    "verify_db",
    "write_table",
]

log = logging.getLogger(__name__)

#: Version of the folder layout and of ``db.yaml``.
DB_SCHEMA_VERSION = 1
#: Version of every Parquet table (column ``schema_version`` and key-value metadata).
TABLE_SCHEMA_VERSION = 1
#: Parquet key-value metadata key holding the table schema version.
SCHEMA_KEY = b"prism3d_schema_version"
#: Parquet key-value metadata key naming the table kind (targets, manifest, ...).
KIND_KEY = b"prism3d_table"

#: Columns of ``targets.parquet`` and their pandas dtypes.
TARGET_COLUMNS: dict[str, str] = {
    "target_id": "str",
    "class": "str",
    "name": "str",
    "source_kind": "str",  # "file", "scan" (a prism3d stitch model) or "builtin"
    "source_file": "str",
    "source_sha256": "str",
    "model_file": "str",
    "model_sha256": "str",
    "units": "str",
    "scale_to_mm": "float64",
    "up": "str",
    "length_mm": "float64",
    "width_mm": "float64",
    "height_mm": "float64",
    "n_vertices": "int64",
    "n_faces": "int64",
    "provenance": "str",
    "builtin_scale": "float64",  # built-ins: ratio to full size; NaN for files
    "coverage": "float64",  # scans: share of the view sphere observed; NaN otherwise
    "added": "str",
    "schema_version": "int64",
}

_DB_YAML_KEYS = {"schema_version", "units", "created", "prism3d_version", "format"}


def utc_timestamp() -> str:
    """Current UTC time, ISO 8601 to the second."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _prism3d_version() -> str:
    try:
        from importlib.metadata import version

        return version("prism3d")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        return "unknown"


# ---------------------------------------------------------------------------------
# Parquet tables
# ---------------------------------------------------------------------------------


def write_table(
    df: Any, path: str | Path, *, kind: str, extra_meta: dict[str, str] | None = None
) -> None:
    """Write ``df`` as Parquet atomically, with a ``schema_version`` column and
    ``prism3d_table`` = ``kind`` plus ``extra_meta`` in the key-value metadata.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    df = df.copy()
    df["schema_version"] = np.int64(TABLE_SCHEMA_VERSION)
    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[SCHEMA_KEY] = str(TABLE_SCHEMA_VERSION).encode()
    meta[KIND_KEY] = kind.encode()
    for k, v in (extra_meta or {}).items():
        meta[k.encode()] = str(v).encode()
    table = table.replace_schema_metadata(meta)
    with atomic_path(path, keep_suffix=False) as tmp:  # a killed write never looks like a part
        pq.write_table(table, str(tmp))


def read_metadata(path: str | Path) -> dict[str, str]:
    """Key-value metadata of a Parquet file (prism3d keys only), schema-checked."""
    import pyarrow.parquet as pq

    try:
        raw = pq.read_schema(str(path)).metadata or {}
    except Exception as exc:  # noqa: BLE001 - pyarrow raises several types on bad files
        raise DatasetError(f"{path}: not a readable Parquet file ({exc})") from None
    meta = {k.decode(): v.decode() for k, v in raw.items() if k.startswith(b"prism3d")}
    _check_version(meta.get(SCHEMA_KEY.decode()), path)
    return meta


def _check_version(value: Any, path: str | Path) -> None:
    if value is None:
        raise DatasetError(f"{path}: no prism3d schema_version (not a prism3d table?)")
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: schema_version {value!r} is not an integer") from None
    if v != TABLE_SCHEMA_VERSION:
        raise DatasetError(
            f"{path}: unknown schema_version {v} (this prism3d reads version "
            f"{TABLE_SCHEMA_VERSION}); upgrade prism3d or rebuild the table"
        )


def read_table(path: str | Path) -> Any:
    """Read one prism3d Parquet table, rejecting unknown schema versions.

    Raises
    ------
    DatasetError
        Unreadable file, missing or unknown ``schema_version`` (metadata or column).
    """
    import pandas as pd

    read_metadata(path)
    df = pd.read_parquet(path)
    if "schema_version" in df.columns and len(df):
        bad = set(df["schema_version"].unique().tolist()) - {TABLE_SCHEMA_VERSION}
        if bad:
            raise DatasetError(f"{path}: unknown schema_version {sorted(bad)} in rows")
    return df


def _read_parts(folder: Path) -> Any:
    import pandas as pd

    parts = sorted(folder.glob("part-*.parquet"))
    if not parts:
        return None
    return pd.concat([read_table(p) for p in parts], ignore_index=True)


def _empty_targets() -> Any:
    import pandas as pd

    return pd.DataFrame(
        {c: pd.Series(dtype="object" if t == "str" else t) for c, t in TARGET_COLUMNS.items()}
    )


# ---------------------------------------------------------------------------------
# The database
# ---------------------------------------------------------------------------------


def _safe_rel(root: Path, rel: str, what: str) -> Path:
    """``root / rel`` after checking ``rel`` is relative and stays inside ``root``."""
    if not isinstance(rel, str) or not rel:
        raise DatasetError(f"{what}: empty path")
    p = Path(rel)
    if p.is_absolute() or rel.startswith(("/", "\\")) or ".." in p.parts:
        raise DatasetError(f"{what}: path {rel!r} escapes the database folder {root}")
    full = (root / p).resolve()
    if not full.is_relative_to(root.resolve()):
        raise DatasetError(f"{what}: path {rel!r} escapes the database folder {root}")
    return root / p


@dataclass(frozen=True)
class JobStatus:
    """How far a render job is."""

    units: int
    """Units the job is split into."""
    done_units: int
    """Units finished (their manifest part matches the job's spec)."""
    chips: int
    """Chips in the finished units."""
    features: bool
    """Whether the job's features table has been written."""


@dataclass(frozen=True)
class DbInfo:
    """What ``prism3d db info`` shows: the targets by class and the render jobs."""

    path: str
    """The database folder."""
    schema_version: int | None
    """The folder's schema version (db.yaml)."""
    targets: int
    """Targets in targets.parquet."""
    targets_per_class: dict[str, int]
    """Targets per class, classes sorted."""
    jobs: dict[str, JobStatus | None] = field(default_factory=dict)
    """Render jobs by name, with their completion when asked for (None: not asked)."""

    def to_json(self) -> dict[str, Any]:
        """As ``db info --json`` prints it (a job without status as {})."""
        return {"path": self.path, "schema_version": self.schema_version, "targets": self.targets,
                "targets_per_class": dict(self.targets_per_class),
                "jobs": {k: {} if v is None else asdict(v) for k, v in self.jobs.items()}}

    def text(self) -> str:
        """Human-readable lines (``db info``)."""
        lines = [f"database {self.path} (schema {self.schema_version})", f"targets: {self.targets}"]
        lines += [f"  {c}: {n}" for c, n in self.targets_per_class.items()]
        lines.append(f"render jobs: {len(self.jobs)}")
        for job, st in self.jobs.items():
            lines.append(f"  {job}: {st.done_units}/{st.units} units done, {st.chips} chips, "
                         f"features {'yes' if st.features else 'no'}" if st else f"  {job}")
        return "\n".join(lines)


class TargetDB:
    """An opened target database: ``path`` (the folder) and ``meta`` (``db.yaml``)."""

    def __init__(self, path: Path, meta: dict[str, Any]) -> None:
        self.path = path
        self.meta = meta

    def __repr__(self) -> str:
        return f"TargetDB({str(self.path)!r})"

    # -- locations -------------------------------------------------------------------
    @property
    def targets_file(self) -> Path:
        return self.path / "targets.parquet"

    def job_dir(self, job: str) -> Path:
        """``renders/<job>`` (the name is checked)."""
        check_name(job, "job")
        return self.path / "renders" / job

    def resolve(self, rel: str, what: str = "path") -> Path:
        """An absolute path for a DB-relative path; DatasetError if it escapes the DB."""
        return _safe_rel(self.path, rel, what)

    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Exclusive ``fcntl.flock`` on ``DB/.lock`` (blocks until free)."""
        fd = os.open(self.path / ".lock", os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    # -- tables ----------------------------------------------------------------------
    def targets(self) -> Any:
        """The targets table (pandas DataFrame, columns :data:`TARGET_COLUMNS`); every
        ``target_id`` is checked to be a safe, unique name (ids become folder names)."""
        if not self.targets_file.is_file():
            if self.targets_file.exists():
                raise DatasetError(f"{self.targets_file}: not a file")
            return _empty_targets()
        t = read_table(self.targets_file)
        for tid in t["target_id"]:
            check_name(tid, f"{self.targets_file}: target_id")
        dup = t["target_id"][t["target_id"].duplicated()]
        if len(dup):
            raise DatasetError(f"{self.targets_file}: duplicate target_id {dup.iloc[0]!r}")
        return t

    def jobs(self) -> list[str]:
        """Names of the render jobs (folders under ``renders/`` with a ``job.yaml``)."""
        d = self.path / "renders"
        if not d.is_dir():
            return []
        return sorted(p.name for p in d.iterdir() if (p / "job.yaml").is_file())

    def renders(self, job: str) -> Any:
        """The manifest of render job ``job``: one row per chip (finished units only).

        Raises
        ------
        DatasetError
            Unknown job, or a manifest part with an unknown schema version.
        """
        d = self.job_dir(job)
        if not (d / "job.yaml").is_file():
            raise DatasetError(
                f"{self.path}: no render job {job!r}; jobs: {', '.join(self.jobs()) or 'none'}"
            )
        df = _read_parts(d / "manifest")
        if df is None:
            import pandas as pd

            return pd.DataFrame()
        return df.sort_values(["target_id", "chip_index"], kind="stable").reset_index(drop=True)

    def features(self, job: str) -> Any:
        """Per-chip view features of render job ``job`` (``features/<job>/part-*.parquet``),
        or the per-target model features for ``job="models"`` (``features/models/``)."""
        check_name(job, "job")
        df = _read_parts(self.path / "features" / job)
        if df is None:
            raise DatasetError(
                f"{self.path}: no features for {job!r} (run: prism3d db features DB --job JOB)"
            )
        keys = ["target_id", "chip_index"] if "chip_index" in df.columns else ["target_id"]
        return df.sort_values(keys, kind="stable").reset_index(drop=True)

    # -- chips -----------------------------------------------------------------------
    def select(
        self,
        job: str,
        *,
        targets: Sequence[str] | None = None,
        classes: Sequence[str] | None = None,
        az_range: tuple[float, float] | None = None,
        el_range: tuple[float, float] | None = None,
        range_mm: tuple[float, float] | None = None,
    ) -> Any:
        """Manifest rows of ``job`` matching the filters (ranges are inclusive ``(lo, hi)``)."""
        df = self.renders(job)
        if len(df) == 0:
            return df
        keep = np.ones(len(df), dtype=bool)
        if targets is not None:
            keep &= df["target_id"].isin(list(targets)).to_numpy()
        if classes is not None:
            keep &= df["class"].isin(list(classes)).to_numpy()
        for col, rng in (("az_deg", az_range), ("el_deg", el_range), ("range_mm", range_mm)):
            if rng is not None:
                lo, hi = rng
                keep &= ((df[col] >= lo) & (df[col] <= hi)).to_numpy()
        return df[keep].reset_index(drop=True)

    def _load_rows(self, rows: Any, channel: str) -> NDArray:
        arrays = []
        for rel, chans in zip(rows["chip_file"], rows["channels"]):
            if channel not in str(chans).split(","):
                raise DatasetError(f"channel {channel!r} was not rendered (job channels: {chans})")
            f = self.resolve(rel, "manifest chip_file")
            try:
                with np.load(f, allow_pickle=False) as z:
                    arrays.append(z[channel])
            except (OSError, ValueError, KeyError) as exc:
                raise DatasetError(f"{f}: cannot read chip ({exc})") from None
        return np.stack(arrays) if arrays else np.zeros((0, 0, 0), dtype=np.float32)

    def load_chips(
        self, job: str, *, channel: str = "depth", **filters: Any
    ) -> tuple[NDArray, Any]:
        """Chips of one channel ``(N, H, W)`` (depth float32 mm, intensity/shape float32,
        mask bool) and their N manifest rows, in the same order (filters as :meth:`select`).
        """
        rows = self.select(job, **filters)
        return self._load_rows(rows, channel), rows

    def iter_batches(
        self, job: str, batch_size: int, *, channel: str = "depth", **filters: Any
    ) -> Iterator[tuple[NDArray, Any]]:
        """Yield ``(X, meta)`` batches of at most ``batch_size`` chips (filters as
        :meth:`select`), without loading the whole job into memory."""
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise DatasetError(f"batch_size: expected a positive integer, got {batch_size!r}")
        rows = self.select(job, **filters)
        for s in range(0, len(rows), batch_size):
            part = rows.iloc[s : s + batch_size].reset_index(drop=True)
            yield self._load_rows(part, channel), part

    def export_split(
        self, job: str, out_npz: str | Path, *, channels: Sequence[str] = ("depth",), **filters: Any
    ) -> Path:
        """Write the selected chips to one plain ``.npz`` (no pickle), atomically.

        Arrays: one ``(N, H, W)`` per channel, ``labels`` (N,) int64 (index into
        ``classes``), ``classes`` (K,) unicode, ``target_id`` (N,) unicode, and
        ``az_deg``, ``el_deg``, ``range_mm`` (N,) float64.
        """
        rows = self.select(job, **filters)
        if len(rows) == 0:
            raise DatasetError(f"export_split: no chips of job {job!r} match the filters")
        out: dict[str, NDArray] = {ch: self._load_rows(rows, ch) for ch in channels}
        classes = sorted(rows["class"].unique().tolist())
        out["classes"] = np.array(classes, dtype=str)
        out["labels"] = rows["class"].map({c: i for i, c in enumerate(classes)}).to_numpy(np.int64)
        out["target_id"] = rows["target_id"].to_numpy(dtype=str)
        for col in ("az_deg", "el_deg", "range_mm"):
            out[col] = rows[col].to_numpy(np.float64)
        with atomic_path(out_npz) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **out)
        return Path(out_npz)

    # -- summary / checks ------------------------------------------------------------
    def info(self) -> DbInfo:
        """Counts per table and class, and the render jobs by name
        (:func:`prism3d.datasets.jobs.database_jobs.database_info` adds each job's completion)."""
        t = self.targets()
        per_class = {str(k): int(v) for k, v in t["class"].value_counts().sort_index().items()} if len(t) else {}
        return DbInfo(str(self.path), self.meta.get("schema_version"), len(t), per_class,
                      {job: None for job in self.jobs()})

    def verify(self) -> list[str]:
        """Problems found (empty list = healthy); see :func:`verify_db`."""
        return verify_db(self)


def check_add_request(
    meshes: Sequence[str | Path], builtin: Sequence[str] | None, target_class: str | None
) -> str:
    """Which targets ``db add`` adds: ``"builtin"`` (``builtin`` not None; an empty list
    means all) or ``"meshes"`` (mesh files, which need ``target_class``)."""
    if builtin is not None:
        if meshes:
            raise InputError("db add: give mesh files or --builtin, not both")
        return "builtin"
    if not meshes:
        raise InputError("db add: give mesh files (with --class) or --builtin")
    if target_class is None:
        raise InputError("db add: give the targets' --class")
    return "meshes"


def check_name(name: str, what: str) -> None:
    """DatasetError unless ``name`` is a safe folder/file name (``what`` names it)."""
    import re

    if (
        not isinstance(name, str)
        or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,127}", name)
        or ".." in name
    ):
        raise DatasetError(
            f"{what}: {name!r} is not a valid name (letters, digits, '_', '-', '.'; no '..' or '/')"
        )


def init_db(path: str | Path) -> TargetDB:
    """Create an empty database folder (``prism3d db init DB``).

    Raises
    ------
    DatasetError
        ``path`` is already a database, or an existing non-empty folder, or a file.
    """
    import yaml

    p = Path(path)
    if (p / "db.yaml").exists():
        raise DatasetError(f"{p}: already a prism3d database (db.yaml exists)")
    if p.exists() and (not p.is_dir() or any(p.iterdir())):
        raise DatasetError(f"{p}: exists and is not an empty folder; choose a new path")
    meta = {
        "format": "prism3d-target-db",
        "schema_version": DB_SCHEMA_VERSION,
        "units": "mm",
        "created": utc_timestamp(),
        "prism3d_version": _prism3d_version(),
    }
    with staged_folder(p) as stage:  # the database appears whole or not at all
        for sub in ("models", "renders", "features", "evals"):
            (stage / sub).mkdir()
        write_table(_empty_targets(), TargetDB(stage, meta).targets_file, kind="targets")
        (stage / "db.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
    return TargetDB(p, meta)


def read_yaml(f: Path) -> Any:
    """The YAML document in file ``f`` (DatasetError if it is not valid YAML)."""
    import yaml

    try:
        return yaml.safe_load(f.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise DatasetError(f"{f}: not UTF-8 text; not a prism3d YAML file") from None
    except yaml.YAMLError as exc:
        raise DatasetError(f"{f}: invalid YAML ({exc})") from None


def open_db(path: str | Path) -> TargetDB:
    """Open an existing database folder.

    Raises
    ------
    DatasetError
        No ``db.yaml``, invalid YAML, unknown keys, unknown schema version, units not mm.
    """
    p = Path(path)
    f = p / "db.yaml"
    if not f.is_file():
        raise DatasetError(
            f"{p}: not a prism3d database (no db.yaml); create one with 'prism3d db init {p}'"
        )
    meta = read_yaml(f)
    if not isinstance(meta, dict):
        raise DatasetError(f"{f}: expected a mapping")
    unknown = set(meta) - _DB_YAML_KEYS
    if unknown:
        raise DatasetError(f"{f}: unknown keys {sorted(unknown)}; allowed: {sorted(_DB_YAML_KEYS)}")
    if meta.get("schema_version") != DB_SCHEMA_VERSION:
        raise DatasetError(
            f"{f}: unknown schema_version {meta.get('schema_version')!r} (this prism3d reads "
            f"version {DB_SCHEMA_VERSION})"
        )
    if meta.get("units") != "mm":
        raise DatasetError(f"{f}: units must be 'mm', got {meta.get('units')!r}")
    return TargetDB(p, meta)


def as_db(db: TargetDB | str | Path) -> TargetDB:
    """``db`` itself, or the database opened at that path."""
    return db if isinstance(db, TargetDB) else open_db(db)


def verify_db(db: TargetDB | str | Path, *, check_hashes: bool = True) -> list[str]:
    """Problems of a database, one line each (empty when healthy).

    Checks schema versions, model files and hashes, chip files (present, inside the DB,
    sha256), orphan chips of killed units and leftover temporary files.
    """
    db = as_db(db)
    problems: list[str] = []
    try:
        t = db.targets()
    except DatasetError as exc:
        return [str(exc)]
    problems += _model_problems(db, t, check_hashes)
    for job in db.jobs():
        problems += _job_yaml_problems(db, job)
        referenced: set[Path] = set()
        problems += _manifest_problems(db, job, check_hashes, referenced)
        problems += _orphan_chip_problems(db, job, referenced)
        fdir = db.path / "features" / job
        for part in sorted(fdir.glob("part-*.parquet")) if fdir.is_dir() else []:
            try:
                read_metadata(part)
            except DatasetError as exc:
                problems.append(str(exc))
    fm = db.path / "features" / "models"
    for part in sorted(fm.glob("part-*.parquet")) if fm.is_dir() else []:
        try:
            read_metadata(part)
        except DatasetError as exc:
            problems.append(str(exc))
    for f in sorted(db.path.rglob(".*.tmp*")):
        problems.append(
            f"leftover temporary file {f.relative_to(db.path)} (interrupted write; safe to delete)"
        )
    return problems


def _model_problems(db: TargetDB, t: Any, check_hashes: bool) -> list[str]:
    """Model files of the targets table ``t`` outside the DB, missing or (``check_hashes``)
    not matching their recorded sha256."""
    problems: list[str] = []
    for r in t.itertuples(index=False):
        try:
            f = db.resolve(r.model_file, f"targets {r.target_id} model_file")
        except DatasetError as exc:
            problems.append(str(exc))
            continue
        if not f.is_file():
            problems.append(f"target {r.target_id}: model file {r.model_file} missing")
        elif check_hashes and sha256_file(f) != r.model_sha256:
            problems.append(f"target {r.target_id}: model file {r.model_file} sha256 mismatch")
    return problems


def _manifest_problems(db: TargetDB, job: str, check_hashes: bool, referenced: set[Path]) -> list[str]:
    """Unreadable manifest parts of ``job``, duplicate (target_id, chip_index) rows and chip
    files outside the DB, missing or with a wrong sha256; adds the chips found to ``referenced``."""
    problems: list[str] = []
    mdir = db.job_dir(job) / "manifest"
    seen_chips: set[tuple[str, int]] = set()
    for part in sorted(mdir.glob("part-*.parquet")):
        try:
            df = read_table(part)
        except DatasetError as exc:
            problems.append(str(exc))
            continue
        keys = set(zip(df["target_id"], df["chip_index"].astype(int)))
        if len(keys) < len(df) or keys & seen_chips:
            problems.append(f"job {job}: duplicate manifest rows (target_id, chip_index) in {part.name}")
        seen_chips |= keys
        for rel, sha in zip(df["chip_file"], df["sha256"]):
            try:
                f = db.resolve(rel, f"{part.relative_to(db.path)} chip_file")
            except DatasetError as exc:
                problems.append(str(exc))
                continue
            referenced.add(f.resolve())
            if not f.is_file():
                problems.append(f"job {job}: chip file {rel} missing ({part.name})")
            elif check_hashes and sha256_file(f) != sha:
                problems.append(f"job {job}: chip file {rel} sha256 mismatch ({part.name})")
    return problems


def _orphan_chip_problems(db: TargetDB, job: str, referenced: set[Path]) -> list[str]:
    """Chip files of ``job`` no manifest row references (left by an interrupted unit)."""
    problems: list[str] = []
    cdir = db.job_dir(job) / "chips"
    if cdir.is_dir():
        for f in sorted(cdir.rglob("*.npz")):
            if f.name.startswith("."):
                continue
            if f.resolve() not in referenced:
                problems.append(
                    f"job {job}: orphan chip {f.relative_to(db.path)} (no manifest row; "
                    "from an interrupted unit, rerun the job to complete it)"
                )
    return problems


def _job_yaml_problems(db: TargetDB, job: str) -> list[str]:
    """A job.yaml that does not parse, is not a mapping or has no schema_version."""
    f = db.job_dir(job) / "job.yaml"
    try:
        d = read_yaml(f)
    except DatasetError as exc:
        return [str(exc)]
    if not isinstance(d, dict) or "schema_version" not in d or "spec_hash" not in d:
        return [f"job {job}: {f.name} is not a render job spec (no schema_version / spec_hash)"]
    return []


def target_mesh(db: TargetDB, tid: str) -> tuple[SceneMesh, str]:
    """The render mesh of target ``tid`` (mm, z up, x forward; a built-in at its stored
    scale, with its procedural paint) and its class."""
    t = db.targets()
    rows = t[t["target_id"] == tid]
    if len(rows) != 1:
        raise DatasetError(f"{db.path}: target {tid!r} not in targets.parquet")
    r = rows.iloc[0]
    if r["source_kind"] == "builtin":
        mesh = builtin_target(r["name"], scale=float(r["builtin_scale"]))
        return mesh, str(r["class"])
    ply = read_ply(db.resolve(r["model_file"], f"target {tid} model_file"))
    if ply.faces is None or not len(ply.faces):
        raise DatasetError(f"{r['model_file']}: model has no faces")
    alb = None if ply.colors is None else ply.colors.astype(np.float64) / 255.0
    return SceneMesh(ply.points, ply.faces, vertex_albedo=alb, name=tid), str(r["class"])
