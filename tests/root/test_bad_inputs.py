"""The bad-input probe of issue 27, in-process: every case of :mod:`tests.probe.cases`
through ``prism3d.cli.main(["--quiet", *argv])`` in its own work folder.

Each case must exit as its ``expect`` says (2, or 0/2); on exit 2 print exactly one
stderr line ``prism3d ...``; never a traceback; on a non-zero exit leave the work folder
exactly as it was (no output, partial or whole; nothing touched); never change the
fixtures or a ``protect`` file; and peak at < 1 GiB of traced memory (tracemalloc:
Python objects and numpy buffers; OpenCV's own buffers are not traced — the subprocess
probe ``benchmarks/probe_bad_inputs.py`` measures the RSS).

stderr is captured at the file-descriptor level (``capfd``), so what libpng, OpenCV
or a library warning prints counts as it would in a terminal; logging and warnings are set
up as the console script has them (:func:`_like_the_cli`). Each case runs under an alarm
(:data:`TIMEOUT_S`) and an address-space cap 4 GiB above the current size.
``PRISM3D_PROBE_LOG=FILE`` appends one JSON line per case (exit, stderr, peak, seconds).

Cases that fail today are listed in :data:`KNOWN` (strict xfail): remove an entry when
its finding is fixed. Read-only outputs: we run as root, so chmod does nothing; the
cases use a path under /sys (sysfs refuses new names even to root) and a path whose
parent is a regular file.
"""

from __future__ import annotations

import contextlib
import logging
import os
import resource
import signal
import sys
import time
import tracemalloc
import warnings
import zlib
from pathlib import Path

import pytest

from tests.probe.cases import (
    Case,
    build_fixtures,
    cases,
    file_hash,
    outcome_problems,
    prepare_work,
    shared_data_dir,
    snapshot,
)

#: peak traced memory allowed per case
MEMORY_BUDGET = 1 << 30
#: seconds a case may run in-process (a case still running is a finding)
TIMEOUT_S = 30.0

#: case id -> the finding; strict xfail, so a fixed case shows up as XPASS (remove it here)
KNOWN: dict[str, str] = {}

#: findings that keep the process busy inside C code (the alarm cannot stop them): not
#: run in-process (xfail run=False); the subprocess probe runs them with a timeout
HANGS: dict[str, str] = {}


#: cases that take > 5 s in-process (tracemalloc slows numpy-heavy Python code ~3x): marked
#: ``slow``; the simulate-calib ones do ~4 s (subprocess) of work before they are refused
SLOW = {"simulate-calib/--board/1000x1000", "simulate-calib/--views/huge", "simulate-calib/--square/huge",
        "simulate-calib/--rig/t_1e300", "demo/OUT_DIR/exists_nonempty",
        # a whole survey (~7 s in-process), or a 20000^2 nDSM read (~8 s)
        "survey/--crs/EPSG:2056_other_continent", "survey/--dense-max-pixels/huge",
        "survey-detect/SURVEY_DIR/ndsm_bomb_20000",
        # valid runs of survey-detect (a whole detection, > 30 s under tracemalloc)
        "survey-detect/SURVEY_DIR/ortho_half_gsd", "survey-detect/--threshold/zero",
        "survey-detect/SURVEY_DIR/no_ground", "survey-detect/--threshold/one", "survey-detect/-o/exists",
        "survey-detect/-o/missing_parent", "survey-detect/--draw/missing_parent"}
#: seconds a SLOW case may run in-process
SLOW_TIMEOUT_S = 180.0


class _CaseTimeout(BaseException):
    """Raised by the alarm in the case's thread: the command did not stop in time."""


@pytest.fixture(scope="module")
def fx(tmp_path_factory) -> Path:
    return build_fixtures(tmp_path_factory.mktemp("probe_fixtures") / "fx")["root"]


@pytest.fixture(scope="module")
def trigger_port():
    from prism3d.capture.trigger_sim import TriggerSimulator

    with TriggerSimulator() as sim:
        yield sim.port


#: commands whose cases often run a survey, a simulated flight or field scene or a
#: recogniser (seconds to tens of seconds each, ~640 cases): ``make test`` samples one
#: case in 16 of them (issue 40); ``make test-all`` and the subprocess probe run them all
SAMPLED_COMMANDS = {"survey", "survey-detect", "detect", "simulate-flight", "simulate-field", "bank-eval-scenes"}


def _in_default_run(case_id: str) -> bool:
    """Half of the cases (one in 16 of :data:`SAMPLED_COMMANDS`), chosen by a hash of
    their id (stable, spread over every command and kind), and the first three of every
    command run in ``make test``; all of them with ``make test-all`` and in the subprocess
    probe. Keeps the default suite within its time budget."""
    from tests.probe.cases import command_of

    share = 16 if command_of(case_id) in SAMPLED_COMMANDS else 2
    return zlib.crc32(case_id.encode()) % share == 0 or case_id in _FIRST_OF_EACH_COMMAND


def _first_of_each_command(n: int = 3) -> set[str]:
    from collections import defaultdict

    from tests.probe.cases import command_of

    seen: dict[str, list[str]] = defaultdict(list)
    for c in cases():
        if c.id not in SLOW and len(seen[command_of(c.id)]) < n:
            seen[command_of(c.id)].append(c.id)
    return {i for ids in seen.values() for i in ids}


_FIRST_OF_EACH_COMMAND = _first_of_each_command()


def _params():
    out = []
    for c in cases():
        if c.id in HANGS:
            marks = [pytest.mark.xfail(run=False, reason=f"finding (hangs): {HANGS[c.id]}")]
        elif c.id in KNOWN:
            marks = [pytest.mark.xfail(strict=True, reason=f"finding: {KNOWN[c.id]}")]
        else:
            marks = []
        if c.id in SLOW or not _in_default_run(c.id):
            marks.append(pytest.mark.slow)
        out.append(pytest.param(c, id=c.id, marks=marks))
    return out


@contextlib.contextmanager
def _like_the_cli():
    """The console's warning filters and a logging handler on the (captured) stderr,
    as ``python -m prism3d.cli`` has; pytest's own settings are put back afterwards."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    root.handlers = []
    with warnings.catch_warnings():
        warnings.resetwarnings()
        for f in ("ignore::ResourceWarning", "ignore::ImportWarning", "ignore::PendingDeprecationWarning",
                  "ignore::DeprecationWarning", "default::DeprecationWarning:__main__"):
            action, _, cat, *rest = f.split(":")
            warnings.filterwarnings(action, category={"ResourceWarning": ResourceWarning,
                                                      "ImportWarning": ImportWarning,
                                                      "PendingDeprecationWarning": PendingDeprecationWarning,
                                                      "DeprecationWarning": DeprecationWarning}[cat],
                                    module=rest[0] if rest else "")
        # a fresh process's warnings.showwarning; logging.captureWarnings(True) in main() then
        # wraps it as it would the first time in a process
        logging.captureWarnings(False)
        warnings.showwarning = lambda m, c, f, n, file=None, line=None: sys.stderr.write(
            warnings.formatwarning(m, c, f, n, line))
        try:
            yield
        finally:
            logging.captureWarnings(False)
            for h in root.handlers:
                with contextlib.suppress(Exception):
                    h.close()
            root.handlers = handlers
            root.setLevel(level)


def _vm_size() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


@contextlib.contextmanager
def _guarded(timeout_s: float):
    """An alarm after ``timeout_s`` and an address-space cap 4 GiB above the current
    size, so a runaway case fails instead of stalling or swapping the shared machine."""
    def on_alarm(signum, frame):
        raise _CaseTimeout(f"still running after {timeout_s:.0f} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = _vm_size() + (4 << 30)
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))
    signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def run_in_process(case: Case, fx: Path, work: Path, trigger: str, capfd) -> dict:
    """Run one case in ``work`` (the cwd); return what happened and the problems."""
    from prism3d.cli import main

    prepare_work(case, work, fx)
    before = snapshot(work)
    fx_before = snapshot(fx, hashes=False)
    prot = {p: file_hash(work / p) for p in case.protect if (work / p).is_file()}
    argv = ["--quiet", *case.resolve(fx, trigger)]
    capfd.readouterr()
    rc: int | str
    error = ""
    t0 = time.perf_counter()
    tracemalloc.start()
    try:
        with _like_the_cli(), _guarded(5.0 if case.id.startswith("trigger-simulate")
                                           else SLOW_TIMEOUT_S if case.id in SLOW else TIMEOUT_S):
            rc = main(argv)
    except SystemExit as exc:  # argparse: exit 2 with its one line
        rc = exc.code if isinstance(exc.code, int) else 2
    except _CaseTimeout as exc:
        rc, error = "timeout", str(exc)
    except BaseException as exc:  # noqa: BLE001 - any other exception is the finding
        rc = "traceback"
        error = f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    seconds = time.perf_counter() - t0
    _, err = capfd.readouterr()

    lines = err.strip().splitlines()
    problems = outcome_problems(case, rc, lines, work, before, fx, fx_before, prot)
    if error:
        problems.append(error)
    if "Traceback (most recent call last)" in err:
        problems.append("traceback on stderr")
    if peak >= MEMORY_BUDGET:
        problems.append(f"peak traced memory {peak / 2**20:.0f} MiB >= 1 GiB")
    return {"rc": rc, "stderr": lines, "error": error, "peak_mb": peak / 2**20, "seconds": seconds,
            "problems": problems}


@pytest.mark.parametrize("case", _params())
def test_bad_input(case: Case, fx, tmp_path, monkeypatch, capfd, request):
    if case.needs == "shared_data" and shared_data_dir() is None:
        pytest.skip("real test data not found (set PRISM3D_TEST_DATA or place ../shared/data)")
    trigger = request.getfixturevalue("trigger_port") if case.needs == "trigger" else ""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    res = run_in_process(case, fx, work, trigger, capfd)
    log = os.environ.get("PRISM3D_PROBE_LOG")  # optional: one JSON line per case, for reports
    if log:
        import json

        with open(log, "a") as f:
            f.write(json.dumps({"id": case.id, **res}, default=str) + "\n")
    assert not res["problems"], f"{case.id}: {'; '.join(res['problems'])} (stderr: {res['stderr'][:2]})"


def test_case_ids_are_known():
    """Every KNOWN entry names a case that exists (a renamed case must not hide here)."""
    ids = {c.id for c in cases()}
    assert not set(KNOWN) - ids, sorted(set(KNOWN) - ids)


def test_enough_cases_per_command():
    from collections import Counter

    from tests.probe.cases import command_of

    n = Counter(command_of(c.id) for c in cases())
    assert sum(n.values()) >= 800 and min(n.values()) >= 5, n
    fast = Counter(command_of(c.id) for c in cases() if _in_default_run(c.id) and c.id not in SLOW)
    assert set(fast) == set(n) and min(fast.values()) >= 2, fast  # every command in make test
