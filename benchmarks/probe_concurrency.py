"""Concurrency and kill probe of issue 40: two writers racing for one output, and a survey
killed (SIGKILL, SIGTERM) at many points, each run as ``python -m prism3d.cli``.

Why: the output lock, the staging folders and ``survey --resume`` promise that a second
writer is refused with one line, that a race or a kill never leaves a half-written output,
a staging folder, a lock or a child process behind, and that the next run gives the same
bytes as an undisturbed one. This measures those promises; it never asserts (the fast
check is ``tests/root/test_concurrency_probe.py``).

    python benchmarks/probe_concurrency.py [--reps 20] [--points 10] [--only concurrency|kill]
                                           [--work DIR] [--small] [--json OUT]

Concurrency: ``survey``, ``stitch`` and ``db render`` (one job, one database), each
twice into one output, the second started 0-1 s (random) after the first; the output is
compared file by file with a run alone. Kills: the signal goes to the survey's own pid
(as ``kill PID`` would), not its process group, so its COLMAP worker must go by itself.
Every run has ``PRISM3D_NUM_THREADS=1`` (the survey is then bit-reproducible); ``stitch``
is also pinned to one CPU (Open3D's threads follow the CPUs it may use, and its sums then
vary in the last digits from run to run). Files that legitimately differ from run to run
(stage times in JSON, unit statistics in Parquet metadata) are compared without those
fields and listed as run-dependent.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.probe.cases import file_hash  # noqa: E402

try:
    import psutil
except ImportError:  # the probe reads /proc instead
    psutil = None

#: one line per survey stage when stderr is not a terminal (prism3d.progress._StageLines)
STAGE_PREFIX = "survey: "
STAGE_SUFFIX = "..."
#: JSON keys and Parquet unit statistics that record how a run went, not what it made
RUN_KEYS = frozenset({"seconds", "pid", "rss_mb"})
#: the survey's note of what a resumed run reused
RESUME_KEYS = frozenset({"resumed"})
TIMEOUT_S = 900.0


# -- running the CLI ----------------------------------------------------------------------


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("PYOPENGL_PLATFORM", "osmesa")
    env.setdefault("NUMBA_THREADING_LAYER", "omp")
    env.setdefault("MPLBACKEND", "Agg")
    env["PRISM3D_NUM_THREADS"] = "1"
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def cli(*args: object, cpu: int | None = None) -> list[str]:
    """``python -m prism3d.cli ARGS``, pinned to one CPU when ``cpu`` is given."""
    cmd = [sys.executable, "-m", "prism3d.cli", *map(str, args)]
    if cpu is not None and shutil.which("taskset"):
        cmd = ["taskset", "-c", str(cpu % (os.cpu_count() or 1)), *cmd]
    return cmd


@dataclass
class Run:
    """One finished CLI process: exit code (negative: the signal that ended it), stderr
    lines, and start and end on the monotonic clock."""

    rc: int
    err: list[str]
    start: float
    end: float

    @property
    def seconds(self) -> float:
        return self.end - self.start


class Child:
    """A CLI process with stdout and stderr in files under ``logs``, in its own session
    (so that every process it starts can be found by session id)."""

    def __init__(self, cmd: list[str], logs: Path, name: str) -> None:
        logs.mkdir(parents=True, exist_ok=True)
        self.err_path = logs / f"{name}.err"
        self.out_path = logs / f"{name}.out"
        self.cmd = cmd
        with open(self.out_path, "wb") as out, open(self.err_path, "wb") as err:
            self.start = time.monotonic()
            self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=err, env=_env(),
                                         cwd=REPO, start_new_session=True)
        self.end: float | None = None

    def running(self) -> bool:
        """Whether it still runs; notes when it was first seen ended (polled every 20 ms)."""
        if self.proc.poll() is None:
            return True
        if self.end is None:
            self.end = time.monotonic()
        return False

    def wait(self, timeout: float = TIMEOUT_S) -> Run:
        wait_all([self], timeout)
        return Run(self.proc.returncode, self.err_lines(), self.start, self.end or time.monotonic())

    def err_lines(self) -> list[str]:
        return self.err_path.read_text(errors="replace").splitlines()


def _suppress_gone() -> contextlib.suppress:
    return contextlib.suppress(ProcessLookupError, PermissionError)


def wait_all(children: list[Child], timeout: float = TIMEOUT_S) -> None:
    """Until every child has ended (each one's end time noted); past ``timeout`` the rest
    are killed with their process groups."""
    deadline = time.monotonic() + timeout
    while [c for c in children if c.running()]:
        if time.monotonic() > deadline:
            for c in children:
                if c.running():
                    with _suppress_gone():
                        os.killpg(c.proc.pid, signal.SIGKILL)
                    c.proc.wait()
        time.sleep(0.02)


def run_alone(cmd: list[str], logs: Path, name: str) -> Run:
    return Child(cmd, logs, name).wait()


# -- inputs --------------------------------------------------------------------------------


@dataclass
class Inputs:
    """What the commands run on: a simulated flight, two overlapping scans, and a database
    with one target (no render job yet)."""

    flight: Path
    scans: list[Path]
    db: Path
    render_args: list[str]
    small: bool

    @property
    def frames(self) -> list[Path]:
        return sorted(self.flight.glob("IMG_*.JPG"))


def _wavy_patch(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points of a smooth bumpy surface 500 mm away, and their normals (mm)."""
    x, y = rng.uniform(-60.0, 60.0, (2, n))
    z = 500.0 + 8.0 * np.cos(x / 13.0) * np.sin(y / 19.0) + 0.002 * (x * x - y * y)
    dz_dx = -8.0 / 13.0 * np.sin(x / 13.0) * np.sin(y / 19.0) + 0.004 * x
    dz_dy = 8.0 / 19.0 * np.cos(x / 13.0) * np.cos(y / 19.0) - 0.004 * y
    normals = np.stack([dz_dx, dz_dy, -np.ones(n)], axis=1)
    return np.stack([x, y, z], axis=1), normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * (k @ k)


def build_inputs(work: Path, *, small: bool = False) -> Inputs:
    """The inputs in ``work/inputs`` (kept: a second call reuses what is there). Normal: an
    8-frame 640x480 flight (a survey alone: 15-35 s on two busy cores); small: 4 frames of 400x300
    (5-8 s)."""
    from prism3d.io.ply import write_ply

    d = work / "inputs"
    logs = work / "logs" / "inputs"
    frames, size = ("4", "400x300") if small else ("8", "640x480")
    flight = d / f"flight_{frames}x{size}"
    if not (flight / "geoinfo.txt").is_file():
        r = run_alone(cli("-q", "simulate", "flight", flight, "--frames", frames, "--size", size, "--altitude", "40",
                          "--no-depth", "--seed", "2"), logs, "flight")
        if r.rc != 0:
            raise RuntimeError(f"simulate flight failed: {r.err[-1:]}")
    scans = [d / "scan_a.ply", d / "scan_b.ply"]
    if not all(p.is_file() for p in scans):
        points, normals = _wavy_patch(40000, np.random.default_rng(11))
        R = _rotation(np.array([0.3, 1.0, 0.2]), 5.0)
        write_ply(scans[0], points, normals=normals)
        write_ply(scans[1], points @ R.T + np.array([5.0, -4.0, 3.0]), normals=normals @ R.T)
    db = d / "db"
    if not (db / "targets.parquet").is_file():
        shutil.rmtree(db, ignore_errors=True)
        for args in (["init", db], ["add", db, "--builtin", "tank_t1"]):
            r = run_alone(cli("-q", "db", *args), logs, f"db_{args[0]}")
            if r.rc != 0:
                raise RuntimeError(f"db {args[0]} failed: {r.err[-1:]}")
    azimuth = "0:360:15" if small else "0:360:10"
    render_args = ["--job", "j", "--azimuth", azimuth, "--elevation", "20:40:20", "--range", "3000", "--size", "64"]
    return Inputs(flight, scans, db, render_args, small)


def survey_cmd(inp: Inputs, out: Path, *, quiet: bool, resume: bool = False) -> list[str]:
    return cli(*(["-q"] if quiet else []), "survey", *inp.frames, "--calib", inp.flight / "camera.yaml",
               "--gps", inp.flight / "geoinfo.txt", "-o", out, *(["--resume"] if resume else []))


# -- comparing outputs ---------------------------------------------------------------------


def tree(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (hidden ones too): relative path -> sha256, or "dir"."""
    found: dict[str, str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        base = Path(dirpath)
        for name in dirnames:
            found[str((base / name).relative_to(root))] = "dir"
        for name in filenames:
            p = base / name
            found[str(p.relative_to(root))] = file_hash(p) if p.is_file() else "special"
    return found


def _json_paths_differing(a: object, b: object, at: str = "") -> list[str]:
    """Where two JSON documents differ, as dotted paths (list indices as ``[]``)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for k in sorted(set(a) | set(b)):
            p = f"{at}.{k}" if at else str(k)
            out += [p] if (k in a) != (k in b) else _json_paths_differing(a[k], b[k], p)
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [p for x, y in zip(a, b) for p in _json_paths_differing(x, y, f"{at}[]")]
    return [] if a == b else [at]


def _run_dependent(paths: list[str], keys: frozenset[str]) -> bool:
    """All differing paths go through a key that records the run (``keys``)."""
    return all(any(part.removesuffix("[]") in keys for part in p.split(".")) for p in paths)


def _parquet_difference(a: Path, b: Path) -> list[str]:
    """Where two Parquet files differ: ``data`` (the table itself), or metadata paths
    (``meta:KEY`` or ``meta:KEY.field`` for JSON values)."""
    import pyarrow.parquet as pq

    ta, tb = pq.read_table(a), pq.read_table(b)
    out = [] if ta.replace_schema_metadata(None).equals(tb.replace_schema_metadata(None)) else ["data"]
    ma, mb = ta.schema.metadata or {}, tb.schema.metadata or {}
    for k in sorted(set(ma) | set(mb)):
        key = k.decode(errors="replace")
        va, vb = ma.get(k), mb.get(k)
        if va == vb:
            continue
        try:
            out += [f"meta:{key}.{p}" for p in _json_paths_differing(json.loads(va), json.loads(vb))]
        except (TypeError, ValueError):
            out.append(f"meta:{key}")
    return out


def _content_difference(a: Path, b: Path) -> list[str]:
    """Where two files with different bytes differ, when their format is known (JSON,
    Parquet), else ``["bytes"]``."""
    try:
        if a.suffix == ".json":
            return _json_paths_differing(json.loads(a.read_text()), json.loads(b.read_text())) or ["bytes"]
        if a.suffix == ".parquet":
            return _parquet_difference(a, b) or ["bytes"]
    except (OSError, ValueError) as exc:
        return [f"unreadable: {exc}"]
    return ["bytes"]


@dataclass
class Comparison:
    """A folder against a reference: entries missing or extra, files that differ in what
    they hold, and files that differ only in fields that record the run."""

    missing: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)
    different: dict[str, list[str]] = field(default_factory=dict)
    run_dependent: dict[str, list[str]] = field(default_factory=dict)

    @property
    def identical_bytes(self) -> bool:
        return not (self.missing or self.extra or self.different or self.run_dependent)

    @property
    def same_content(self) -> bool:
        return not (self.missing or self.extra or self.different)


def compare(ref_root: Path, ref: dict[str, str], root: Path, *, keys: frozenset[str] = RUN_KEYS) -> Comparison:
    got = tree(root) if root.exists() else {}
    c = Comparison(missing=sorted(set(ref) - set(got)), extra=sorted(set(got) - set(ref)))
    for rel in sorted(set(ref) & set(got)):
        if ref[rel] == got[rel]:
            continue
        where = _content_difference(ref_root / rel, root / rel)
        (c.run_dependent if _run_dependent(where, keys) else c.different)[rel] = _collapse(where)
    return c


def _collapse(paths: list[str]) -> list[str]:
    """Differing paths with counts: ``dense.pairs[].seconds (17)``."""
    counts: dict[str, int] = {}
    for p in paths:
        counts[p] = counts.get(p, 0) + 1
    return [f"{p} ({n})" if n > 1 else p for p, n in counts.items()]


# -- processes left behind -----------------------------------------------------------------


def _proc_children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (psutil, or /proc's parent links)."""
    if psutil is not None:
        try:
            return [c.pid for c in psutil.Process(pid).children(recursive=True)]
        except psutil.Error:
            return []
    parent: dict[int, int] = {}
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                parent[int(p.name)] = int((p / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                pass
    found, todo = [], [pid]
    while todo:
        kids = [c for c, pp in parent.items() if pp == todo.pop()]
        found += kids
        todo += kids
    return found


def _start_time(pid: int) -> str | None:
    """The process's start (clock ticks since boot) from /proc: tells a pid from its reuse."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _alive_not_zombie(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def survivors(tracked: dict[int, tuple[str | None, str]], session: int, marker: str) -> dict[int, str]:
    """Live processes that belong to a finished run: one seen as its descendant (same
    start time), one still in its session, or one whose command line names ``marker``
    (its work folder). ``tracked``: pid -> (start time, command line). pid -> command line."""
    me = {os.getpid(), os.getppid()}
    found: dict[int, str] = {}
    for pid, (started, _) in tracked.items():
        if _alive_not_zombie(pid) and _start_time(pid) == started:
            found[pid] = _cmdline(pid)
    for p in Path("/proc").iterdir():
        if not p.name.isdigit() or int(p.name) in me or int(p.name) in found:
            continue
        pid = int(p.name)
        try:
            sid = os.getsid(pid)
        except OSError:
            continue
        cmd = _cmdline(pid)
        if _alive_not_zombie(pid) and (sid == session or marker in cmd):
            found[pid] = cmd
    return found


def _kill_all(pids: list[int]) -> None:
    for pid in pids:
        with _suppress_gone():
            os.kill(pid, signal.SIGKILL)


# -- concurrency ---------------------------------------------------------------------------


@dataclass
class RaceRecord:
    """One race: both runs' exit codes, stderr line counts and first lines; ``delay``
    between the starts; what the winner's output looks like against the run alone."""

    command: str
    rep: int
    delay_s: float
    rc: list[int]
    err_lines: list[int]
    err_first: list[str]
    overlapped: bool
    outcome: str
    identical_bytes: bool
    same_content: bool
    leftovers: list[str]
    missing: list[str]
    different: dict[str, list[str]]
    run_dependent: dict[str, list[str]]
    seconds: float
    problems: list[str]


def _outcome(a: Run, b: Run) -> str:
    refused = [r.rc == 2 for r in (a, b)]
    if sorted(r.rc for r in (a, b)) == [0, 2]:
        loser = (a, b)[refused.index(True)]
        return "one refused" if len(loser.err) == 1 else f"one refused ({len(loser.err)} stderr lines)"
    if a.rc == b.rc == 0:
        return "both ran"
    return f"exit {a.rc} and {b.rc}"


@dataclass
class RaceSpec:
    """A command raced against itself in a unit folder (the output and whatever lies beside
    it): ``prepare(unit, k)`` is racer k's command, ``setup`` copies inputs into a fresh unit;
    the reference is a unit with one run alone."""

    name: str
    prepare: Callable[[Path, int], list[str]]  # unit folder, racer index -> command
    setup: Callable[[Path], None] | None = None  # inputs copied into the unit folder


def _race_specs(inp: Inputs) -> list[RaceSpec]:
    def survey(unit: Path, k: int) -> list[str]:
        return survey_cmd(inp, unit / "s", quiet=True)

    def stitch(unit: Path, k: int) -> list[str]:
        return cli("-q", "stitch", *inp.scans, "-o", unit / "model.ply", cpu=k)

    def db_render(unit: Path, k: int) -> list[str]:
        return cli("-q", "db", "render", unit / "db", *inp.render_args)

    def db_copy(unit: Path) -> None:
        shutil.copytree(inp.db, unit / "db", symlinks=True)

    return [RaceSpec("survey", survey), RaceSpec("stitch", stitch), RaceSpec("db render", db_render, db_copy)]


def _fresh_unit(path: Path, spec: RaceSpec) -> Path:
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    if spec.setup is not None:
        spec.setup(path)
    return path


def probe_concurrency(inp: Inputs, work: Path, reps: int, *, seed: int = 0, say=print) -> dict:
    """Each command raced ``reps`` times; returns per command the reference's time, the
    run-dependent files of two runs alone, and a :class:`RaceRecord` per race."""
    rng = random.Random(seed)
    root = work / "concurrency"
    logs = work / "logs" / "concurrency"
    results: dict = {}
    for spec in _race_specs(inp):
        tag = spec.name.replace(" ", "_")
        ref_dir = _fresh_unit(root / tag / "ref", spec)
        ref_run = run_alone(spec.prepare(ref_dir, 0), logs, f"{tag}_ref")
        ref = tree(ref_dir)
        again_dir = _fresh_unit(root / tag / "ref_again", spec)
        again_run = run_alone(spec.prepare(again_dir, 1), logs, f"{tag}_ref_again")
        again = compare(ref_dir, ref, again_dir)
        shutil.rmtree(again_dir, ignore_errors=True)
        entry = {"reference_seconds": ref_run.seconds, "reference_rc": [ref_run.rc, again_run.rc],
                 "reference_err": ref_run.err[-3:] + again_run.err[-3:],
                 "alone_twice": asdict(again), "races": []}
        say(f"{spec.name}: alone {ref_run.seconds:.1f} s (exit {ref_run.rc}, again {again_run.rc}); "
            f"two runs alone: {'identical' if again.identical_bytes else again}")
        for rep in range(reps):
            rec = _race(spec, root / tag / f"rep{rep:02d}", logs, f"{tag}_{rep:02d}", rng.uniform(0.0, 1.0),
                        ref_dir, ref)
            rec.rep = rep
            entry["races"].append(rec)
            say(f"{spec.name} rep {rep}: delay {rec.delay_s:.2f} s, exit {rec.rc[0]}/{rec.rc[1]}, {rec.outcome}, "
                f"{_products(rec.identical_bytes, rec.same_content)}"
                + (f"; {'; '.join(rec.problems)}" if rec.problems else ""))
        results[spec.name] = entry
    return results


def _race(spec: RaceSpec, unit: Path, logs: Path, name: str, delay: float, ref_dir: Path,
          ref: dict[str, str]) -> RaceRecord:
    """Two runs of ``spec`` into a fresh ``unit``, the second ``delay`` s after the first;
    the unit is removed when all went as promised (kept to look at otherwise)."""
    _fresh_unit(unit, spec)
    first = Child(spec.prepare(unit, 0), logs, f"{name}_a")
    time.sleep(delay)
    second = Child(spec.prepare(unit, 1), logs, f"{name}_b")
    wait_all([first, second])
    a, b = first.wait(), second.wait()
    c = compare(ref_dir, ref, unit)
    outcome = _outcome(a, b)
    problems = []
    left = {**survivors({}, first.proc.pid, str(unit)), **survivors({}, second.proc.pid, str(unit))}
    if left:
        problems.append(f"processes left: {left}")
        _kill_all(list(left))
    if outcome != "one refused":
        problems.append(f"{outcome} (exit {a.rc}, {b.rc}; stderr {a.err[:2]} / {b.err[:2]})")
    if c.extra:
        problems.append(f"left beside the output: {c.extra}")
    if c.missing:
        problems.append(f"missing against the run alone: {c.missing}")
    if c.different:
        problems.append(f"different from the run alone: {c.different}")
    if any("Traceback" in ln for ln in a.err + b.err):
        problems.append("traceback on stderr")
    if not problems:
        shutil.rmtree(unit, ignore_errors=True)
    return RaceRecord(spec.name, 0, round(delay, 3), [a.rc, b.rc], [len(a.err), len(b.err)],
                      [(a.err or [""])[0][:240], (b.err or [""])[0][:240]],
                      b.start < a.end and a.start < b.end, outcome, c.identical_bytes, c.same_content,
                      c.extra, c.missing, c.different, c.run_dependent, round(max(a.end, b.end) - a.start, 2),
                      problems)


# -- kills ---------------------------------------------------------------------------------


@dataclass
class KillRecord:
    """One survey killed at ``at_s`` (``fraction`` of the run alone) with ``signal``, then
    rerun (``--resume`` or not); ``late``: earlier tries whose signal came once the output
    was in place (their exit code and stderr lines)."""

    point: int
    fraction: float
    at_s: float
    signal: str
    stage: str
    rc: int | None
    exit_latency_s: float | None
    other_lines: list[str]
    left_after_kill: list[str]
    children_seen: list[str]
    orphans: dict[int, str]
    rerun_resume: bool
    rerun_rc: int | None
    rerun_s: float | None
    rerun_err: list[str]
    identical_bytes: bool
    same_content: bool
    run_dependent: dict[str, list[str]]
    different: dict[str, list[str]]
    missing: list[str]
    leftovers: list[str]
    resumed: dict
    problems: list[str]
    late: list[dict]


def _stage_line(line: str) -> bool:
    return line.startswith(STAGE_PREFIX) and line.endswith(STAGE_SUFFIX)


def _watch(child: Child, until: float, tracked: dict[int, tuple[str | None, str]]) -> None:
    """Follow ``child`` until it exits or ``until`` (monotonic), noting its descendants
    (pid -> start time, command line) in ``tracked``."""
    while child.proc.poll() is None and time.monotonic() < until:
        for pid in _proc_children(child.proc.pid):
            if pid not in tracked:
                tracked[pid] = (_start_time(pid), _cmdline(pid))
        time.sleep(0.02)


def _timed_run(cmd: list[str], logs: Path, name: str) -> tuple[Run, list[tuple[float, str]]]:
    """A run alone with the time of each stage line (s from the start)."""
    child = Child(cmd, logs, name)
    seen: list[tuple[float, str]] = []
    n = 0
    while child.proc.poll() is None:
        lines = child.err_lines()
        for ln in lines[n:]:
            seen.append((time.monotonic() - child.start, ln))
        n = len(lines)
        time.sleep(0.02)
    run = child.wait()
    seen += [(run.seconds, ln) for ln in run.err[n:]]
    return run, [(t, ln) for t, ln in seen if _stage_line(ln)]


def probe_kills(inp: Inputs, work: Path, points: int, *, say=print) -> dict:
    """The survey killed at ``points`` moments (fractions (k + 0.5) / points of its time
    alone), once with SIGKILL and once with SIGTERM; after each, processes left, files
    left, then a rerun with and without ``--resume`` (alternating) against the run alone."""
    root = work / "kill"
    logs = work / "logs" / "kill"
    ref_dir = root / "ref"
    shutil.rmtree(ref_dir, ignore_errors=True)
    ref_dir.mkdir(parents=True)
    ref_run, stages = _timed_run(survey_cmd(inp, ref_dir / "s", quiet=False), logs, "ref")
    ref = tree(ref_dir)
    say(f"survey alone: {ref_run.seconds:.1f} s, exit {ref_run.rc}; stages at "
        + ", ".join(f"{t:.1f} s {ln[len(STAGE_PREFIX):-len(STAGE_SUFFIX)]}" for t, ln in stages))
    out = {"reference_seconds": ref_run.seconds, "reference_rc": ref_run.rc,
           "stages": [[round(t, 2), ln] for t, ln in stages], "kills": []}
    if ref_run.rc != 0:
        out["problems"] = [f"the survey alone failed: {ref_run.err[-3:]}"]
        return out
    for k in range(points):
        frac = (k + 0.5) / points
        for sig in (signal.SIGKILL, signal.SIGTERM):
            resume = (k % 2 == 0) == (sig == signal.SIGKILL)
            rec = _one_kill(inp, root, logs, ref_dir, ref, ref_run.seconds, k, frac, sig, resume)
            out["kills"].append(rec)
            say(f"point {k} ({frac:.2f}, {rec.at_s:.1f} s, {rec.stage}) {rec.signal}: exit {rec.rc}, "
                f"left {rec.left_after_kill or 'nothing'}, rerun{' --resume' if resume else ''} exit {rec.rerun_rc}"
                f" in {rec.rerun_s or 0:.1f} s, {_products(rec.identical_bytes, rec.same_content)}"
                + (f"; {'; '.join(rec.problems)}" if rec.problems else ""))
    return out


def _send(child: Child, sig: signal.Signals) -> tuple[float | None, list[str]]:
    """``sig`` to the survey's pid; the seconds until it exits (None: it had ended)."""
    if child.proc.poll() is not None:
        return None, []
    t_sig = time.monotonic()
    os.kill(child.proc.pid, sig)
    try:
        child.proc.wait(60)
    except subprocess.TimeoutExpired:
        with _suppress_gone():
            os.killpg(child.proc.pid, signal.SIGKILL)
        child.proc.wait()
        return time.monotonic() - t_sig, [f"still running 60 s after {sig.name}"]
    return time.monotonic() - t_sig, []


def _after_kill_problems(sig: signal.Signals, rc: int, other: list[str], left: list[str]) -> list[str]:
    """What a killed survey should have done: SIGKILL ends it (-9); SIGTERM gives exit
    143 and one line, and leaves at most the resume folder."""
    if sig == signal.SIGKILL:
        return [] if rc == -signal.SIGKILL else [f"exit {rc} after SIGKILL"]
    out = []
    if rc == -signal.SIGTERM:
        out.append("ended by SIGTERM itself (exit -15, no line): the signal came before the handler")
    elif rc != 143:
        out.append(f"exit {rc} after SIGTERM, not 143")
    if rc == 143 and len(other) != 1:
        out.append(f"{len(other)} stderr lines besides the stage lines: {other[:4]}")
    stray = [n for n in left if n != ".s.resume"]
    if stray:
        out.append(f"left after SIGTERM: {stray}")
    return out


@dataclass
class _Attempt:
    """One survey started and signalled: when, in which stage, how long it took to end."""

    child: Child
    tracked: dict[int, tuple[str | None, str]]
    at: float
    stage: str
    latency: float | None
    problems: list[str]


def _attempt(inp: Inputs, unit: Path, logs: Path, name: str, after_s: float, sig: signal.Signals) -> _Attempt:
    shutil.rmtree(unit, ignore_errors=True)
    unit.mkdir(parents=True)
    child = Child(survey_cmd(inp, unit / "s", quiet=False), logs, name)
    tracked: dict[int, tuple[str | None, str]] = {}
    _watch(child, child.start + after_s, tracked)
    at = time.monotonic() - child.start
    stage_lines = [ln for ln in child.err_lines() if _stage_line(ln)]
    stage = stage_lines[-1][len(STAGE_PREFIX):-len(STAGE_SUFFIX)].split(" (")[0] if stage_lines else "start-up"
    latency, problems = _send(child, sig)
    return _Attempt(child, tracked, at, stage, latency, problems)


def _one_kill(inp: Inputs, root: Path, logs: Path, ref_dir: Path, ref: dict[str, str], ref_s: float, k: int,
              frac: float, sig: signal.Signals, resume: bool) -> KillRecord:
    """The survey signalled at ``frac`` of its time alone. On a shared machine a run may be
    faster than the reference: one that ended first, or had its output in place when the
    signal came (noted in ``late``: it was winding down), is tried again, sooner."""
    name = f"p{k:02d}_{sig.name}"
    unit = root / name
    expected, late = ref_s, []
    for _ in range(3):
        a = _attempt(inp, unit, logs, name, frac * expected, sig)
        if a.latency is not None and not (unit / "s").exists():
            break
        if a.latency is None:
            expected = time.monotonic() - a.child.start
        else:
            late.append({"at_s": round(a.at, 2), "stage": a.stage, "exit": a.child.proc.returncode,
                         "lines": [ln for ln in a.child.err_lines() if not _stage_line(ln)][:3]})
            expected *= 0.9
        a.stage = "finished before the kill"
    err = a.child.err_lines()
    other = [ln for ln in err if not _stage_line(ln)]
    time.sleep(2.0)
    problems = a.problems
    orphans = survivors(a.tracked, a.child.proc.pid, str(unit))
    if orphans:
        problems.append(f"processes left 2 s after the kill: {orphans}")
        _kill_all(list(orphans))
    left = sorted(p.name for p in unit.iterdir())
    if a.stage != "finished before the kill":
        problems += _after_kill_problems(sig, a.child.proc.returncode, other, left)
    if any("Traceback" in ln for ln in err):
        problems.append("traceback on stderr")
    if a.stage == "finished before the kill":  # three tries too late: nothing to rerun
        r, c, resumed = None, compare(ref_dir, ref, unit, keys=RUN_KEYS | RESUME_KEYS), {}
    else:
        r, c, resumed = _rerun(inp, unit, logs, name, resume, ref_dir, ref, problems)
    if not problems:
        shutil.rmtree(unit, ignore_errors=True)
    return KillRecord(k, round(frac, 3), round(a.at, 2), sig.name, a.stage, a.child.proc.returncode,
                      None if a.latency is None else round(a.latency, 3), other[:6], left,
                      sorted({_short(cmd) for _, cmd in a.tracked.values() if cmd}), orphans, resume,
                      None if r is None else r.rc, None if r is None else round(r.seconds, 2),
                      r.err[-3:] if r is not None and r.rc else [], c.identical_bytes, c.same_content,
                      c.run_dependent, c.different, c.missing, c.extra, resumed, problems, late)


def _short(cmd: str) -> str:
    """A command line without its long arguments: the program and module."""
    parts = cmd.split()
    return " ".join(Path(parts[0]).name if i == 0 else a for i, a in enumerate(parts[:3])) if parts else cmd


def _rerun(inp: Inputs, unit: Path, logs: Path, name: str, resume: bool, ref_dir: Path, ref: dict[str, str],
           problems: list[str]) -> tuple[Run, Comparison, dict]:
    """The same survey again (with ``--resume`` or not) until it ends; its folder against
    the run alone; what it says it reused. Problems are added to ``problems``."""
    rerun = Child(survey_cmd(inp, unit / "s", quiet=False, resume=resume), logs, f"{name}_rerun")
    r = rerun.wait()
    c = compare(ref_dir, ref, unit, keys=RUN_KEYS | RESUME_KEYS)
    resumed = {}
    with contextlib.suppress(OSError, ValueError):
        resumed = json.loads((unit / "s" / "poses.json").read_text()).get("resumed", {})
    if r.rc != 0:
        problems.append(f"rerun exit {r.rc}: {r.err[-2:]}")
    if c.extra:
        problems.append(f"left after the rerun: {c.extra}")
    if c.missing:
        problems.append(f"missing after the rerun: {c.missing}")
    if c.different:
        problems.append(f"rerun's products differ from the run alone: {c.different}")
    if any("Traceback" in ln for ln in r.err):
        problems.append("traceback in the rerun")
    left = survivors({}, rerun.proc.pid, str(unit))
    if left:
        problems.append(f"processes left after the rerun: {left}")
        _kill_all(list(left))
    return r, c, resumed


# -- the report ----------------------------------------------------------------------------


def _products(identical_bytes: bool, same_content: bool) -> str:
    return "identical" if identical_bytes else "same content" if same_content else "DIFFERENT"


def _median(xs: list[float]) -> str:
    return f"{statistics.median(xs):.1f}" if xs else "-"


def _cell(x: object) -> str:
    return str(x).replace("|", "\\|")


def _run_dependent_summary(records: list[dict[str, list[str]]]) -> str:
    fields: dict[str, set[str]] = {}
    for rd in records:
        for f, where in rd.items():
            fields.setdefault(f, set()).update(w.split(" (")[0] for w in where)
    return "; ".join(f"`{f}`: {', '.join(sorted(w))}" for f, w in sorted(fields.items())) or "none"


def report_concurrency(res: dict, reps: int) -> list[str]:
    out = ["## Two writers into one output", "",
           f"{reps} races per command; the second started 0-1 s (random) after the first.", "",
           "| command | races | one refused (exit 2, 1 line) | both ran | other | output identical (bytes) "
           "| same up to run-dependent fields | different | leftovers | overlapped | race wall median (s) "
           "| alone (s) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, e in res.items():
        rs: list[RaceRecord] = e["races"]
        out.append(
            f"| {name} | {len(rs)} | {sum(r.outcome == 'one refused' for r in rs)} | "
            f"{sum(r.outcome == 'both ran' for r in rs)} | "
            f"{sum(r.outcome not in ('one refused', 'both ran') for r in rs)} | {sum(r.identical_bytes for r in rs)} | "
            f"{sum(r.same_content and not r.identical_bytes for r in rs)} | {sum(not r.same_content for r in rs)} | "
            f"{sum(bool(r.leftovers) for r in rs)} | {sum(r.overlapped for r in rs)} | "
            f"{_median([r.seconds for r in rs])} | {e['reference_seconds']:.1f} |")
    out += ["", "Run-dependent fields (two runs alone; then in the races):", ""]
    for name, e in res.items():
        out.append(f"- {name}: alone twice: {_run_dependent_summary([e['alone_twice']['run_dependent']])}"
                   + (f", other differences {e['alone_twice']['different']}" if e["alone_twice"]["different"] else "")
                   + f"; races: {_run_dependent_summary([r.run_dependent for r in e['races']])}")
    refusals = sorted({re.sub(r"pid \d+", "pid N", re.sub(r"\S*/rep\d\d", "UNIT", ln))
                       for e in res.values() for r in e["races"] for rc, ln in zip(r.rc, r.err_first) if rc == 2})
    if refusals:
        out += ["", "Refusal lines seen (UNIT: the race's folder):", ""] + [f"- `{ln}`" for ln in refusals]
    fails = [r for e in res.values() for r in e["races"] if r.problems]
    if fails:
        out += ["", "### Races that did not go as promised", "",
                "| command | rep | delay (s) | exits | what happened |", "|---|---|---|---|---|"]
        for r in fails:
            out.append(f"| {r.command} | {r.rep} | {r.delay_s:.2f} | {r.rc[0]}, {r.rc[1]} | "
                       f"{_cell('; '.join(r.problems))} |")
    return out


def report_kills(res: dict, points: int) -> list[str]:
    out = ["## A survey killed at many points", "",
           f"{points} points (fractions (k + 0.5) / {points} of the time alone), each with SIGKILL and SIGTERM to "
           f"the survey's pid. Survey alone: {res['reference_seconds']:.1f} s; stage lines at "
           + ", ".join(f"{t:.1f} s ({ln})" for t, ln in res["stages"]) + ".", ""]
    if res.get("problems"):
        return out + [f"Not run: {res['problems']}"]
    ks: list[KillRecord] = res["kills"]
    out += ["| signal | kills | interrupted | exit as promised | orphans | rerun exit 0 | rerun identical (bytes) "
            "| same up to run-dependent fields | leftovers after rerun | exit latency median (s) "
            "| rerun median (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for sig in ("SIGKILL", "SIGTERM"):
        rs = [r for r in ks if r.signal == sig]
        hit = [r for r in rs if r.stage != "finished before the kill"]
        promised = [r for r in hit if (r.rc == -9 if sig == "SIGKILL" else r.rc == 143 and len(r.other_lines) == 1)]
        out.append(
            f"| {sig} | {len(rs)} | {len(hit)} | {len(promised)} | {sum(bool(r.orphans) for r in rs)} | "
            f"{sum(r.rerun_rc == 0 for r in rs)} | {sum(r.identical_bytes for r in rs)} | "
            f"{sum(r.same_content and not r.identical_bytes for r in rs)} | {sum(bool(r.leftovers) for r in rs)} | "
            f"{_median([r.exit_latency_s for r in hit if r.exit_latency_s is not None])} | "
            f"{_median([r.rerun_s for r in rs if r.rerun_s is not None])} |")
    out += ["", "| point | at (s) | stage | signal | exit | children seen | orphans after 2 s | left after the kill "
            "| rerun | rerun exit | rerun (s) | reused (poses, pairs) | products |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in ks:
        reused = f"{r.resumed.get('poses', '-')}, {r.resumed.get('pairs_reused', '-')}" if r.resumed else "-"
        out.append(f"| {r.point} | {r.at_s:.1f} | {r.stage} | {r.signal} | {r.rc} | {len(r.children_seen)} | "
                   f"{len(r.orphans)} | {_cell(', '.join(r.left_after_kill) or 'nothing')} | "
                   f"{'--resume' if r.rerun_resume else 'plain'} | {r.rerun_rc} | {r.rerun_s} | {reused} | "
                   f"{_products(r.identical_bytes, r.same_content)} |")
    kinds = sorted({c for r in ks for c in r.children_seen})
    out += ["", "Child processes seen while the surveys ran: " + (", ".join(f"`{c}`" for c in kinds) or "none"),
            "", f"Run-dependent fields of the reruns: {_run_dependent_summary([r.run_dependent for r in ks])}"]
    term_lines = sorted({ln for r in ks for ln in r.other_lines if r.signal == "SIGTERM"})
    if term_lines:
        out += ["", "SIGTERM lines seen: " + ", ".join(f"`{ln}`" for ln in term_lines[:4])]
    late = [(r, t) for r in ks for t in r.late]
    if late:
        out += ["", "### Signals that came once the output was in place (tried again sooner)", "",
                "The survey had written its output and was winding down (interpreter exit) when the signal came.", "",
                "| point | signal | at (s) | stage | exit | stderr lines |", "|---|---|---|---|---|---|"]
        for r, t in late:
            out.append(f"| {r.point} | {r.signal} | {t['at_s']:.1f} | {t['stage']} | {t['exit']} | "
                       f"{_cell(t['lines'] or 'none')} |")
    fails = [r for r in ks if r.problems]
    if fails:
        out += ["", "### Kills that did not go as promised", "",
                "| point | signal | at (s) | stage | what happened |", "|---|---|---|---|---|"]
        for r in fails:
            out.append(f"| {r.point} | {r.signal} | {r.at_s:.1f} | {r.stage} | {_cell('; '.join(r.problems))} |")
    return out


def _jsonable(x: object) -> object:
    if isinstance(x, (RaceRecord, KillRecord)):
        return asdict(x)
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_jsonable(v) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=20, help="races per command (default 20)")
    ap.add_argument("--points", type=int, default=10, help="kill points, each with SIGKILL and SIGTERM (default 10)")
    ap.add_argument("--only", choices=("concurrency", "kill"), help="only one of the two probes")
    ap.add_argument("--work", type=Path, help="work folder (kept; inputs reused); default a new temporary one")
    ap.add_argument("--small", action="store_true", help="the smallest inputs (a 4-frame survey of ~5 s)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the start delays")
    ap.add_argument("--json", type=Path, metavar="OUT", help="also write every record as JSON")
    args = ap.parse_args(argv)

    work = args.work or Path(tempfile.mkdtemp(prefix="prism3d_concurrency_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def say(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    inp = build_inputs(work, small=args.small)
    say(f"inputs in {work / 'inputs'}: {len(inp.frames)} frames, {len(inp.scans)} scans, database {inp.db}")
    lines = ["# Concurrency and kill probe (issue 40)", ""]
    results: dict = {}
    if args.only in (None, "concurrency"):
        results["concurrency"] = probe_concurrency(inp, work, args.reps, seed=args.seed, say=say)
        lines += report_concurrency(results["concurrency"], args.reps) + [""]
    if args.only in (None, "kill"):
        results["kill"] = probe_kills(inp, work, args.points, say=say)
        lines += report_kills(results["kill"], args.points) + [""]
    wall = time.perf_counter() - t0
    lines += [f"Wall time {wall:.0f} s; work folder {work}; load average at the end "
              f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}."]
    if args.json:
        args.json.write_text(json.dumps(_jsonable({"wall_s": wall, **results}), indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
