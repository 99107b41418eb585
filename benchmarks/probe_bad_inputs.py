"""The bad-input probe of issue 27, one subprocess per case (``python -m prism3d.cli
--quiet ...``): exit code, stderr line count, traceback, files created or changed in the
work folder, protected files, what it left in its own $TMPDIR, and the child's peak RSS (its ``VmHWM``, written at exit;
sampled every 0.25 s for a child killed at the timeout).
Prints a Markdown summary; never asserts (the in-process test is
``tests/root/test_bad_inputs.py``).

    python benchmarks/probe_bad_inputs.py [--jobs 2] [--only PREFIX] [--json OUT]
                                         [--fixtures DIR] [--timeout S]

Cases come from :mod:`tests.probe.cases`. Each runs in a fresh work folder under a
temporary directory, with an 8 GiB address-space cap (a runaway allocation becomes a
MemoryError rather than swapping a shared machine) and a timeout. Cases that need the
simulated trigger controller run one after another against one ``trigger simulate``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.probe.cases import (  # noqa: E402
    Case,
    build_fixtures,
    cases,
    command_of,
    file_hash,
    outcome_problems,
    prepare_work,
    shared_data_dir,
    snapshot,
)

AS_CAP = 8 << 30
MEMORY_BUDGET_MB = 1024.0


#: runs ``prism3d.cli`` as ``python -m`` would, and writes its VmHWM (KiB) at exit
_CHILD = (
    "import atexit, os, runpy\n"
    "def _hwm():\n"
    "    with open('/proc/self/status') as f:\n"
    "        kib = next(ln.split()[1] for ln in f if ln.startswith('VmHWM:'))\n"
    "    with open(os.environ['PRISM3D_PROBE_HWM'], 'w') as f:\n"
    "        f.write(kib)\n"
    "atexit.register(_hwm)\n"
    "runpy.run_module('prism3d.cli', run_name='__main__', alter_sys=True)\n"
)


def _vm_hwm_kib(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((int(ln.split()[1]) for ln in f if ln.startswith("VmHWM:")), 0)
    except (OSError, ValueError):
        return 0


def run_case(case: Case, fx: Path, work: Path, trigger: str, timeout: float) -> dict:
    work.mkdir(parents=True)
    prepare_work(case, work, fx)
    before = snapshot(work)
    fx_before = snapshot(fx, hashes=False)
    prot = {p: file_hash(work / p) for p in case.protect if (work / p).is_file()}
    # The child's peak RSS is its own VmHWM, written at exit by _CHILD; ru_maxrss from
    # wait4 is not usable: Linux carries the parent's high-water mark across fork + exec.
    hwm_file = work.parent / f"{work.name}.hwm"
    tmpdir = work.parent / f"{work.name}.tmpdir"  # the child's own $TMPDIR: what it leaves there is seen
    tmpdir.mkdir()
    argv = ["prlimit", f"--as={AS_CAP}", sys.executable, "-c", _CHILD, "--quiet", *case.resolve(fx, trigger)]
    t0 = time.perf_counter()
    with open(work.parent / f"{work.name}.err", "w+b") as err_f:
        proc = subprocess.Popen(argv, cwd=work, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=err_f, start_new_session=True,
                                env={**os.environ, "PYTHONPATH": str(REPO), "PRISM3D_PROBE_HWM": str(hwm_file),
                                     "TMPDIR": str(tmpdir)})
        timed_out = False
        done = threading.Event()
        polled_kib = [0]

        def killer() -> None:  # samples VmHWM (for a child killed at the timeout) and kills it
            nonlocal timed_out
            t_end = time.monotonic() + timeout
            while not done.wait(0.25):
                polled_kib[0] = max(polled_kib[0], _vm_hwm_kib(proc.pid))
                if time.monotonic() > t_end:
                    timed_out = True
                    try:
                        os.killpg(proc.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    return

        threading.Thread(target=killer, daemon=True).start()
        _, status, _usage = os.wait4(proc.pid, 0)
        done.set()
        proc.returncode = os.waitstatus_to_exitcode(status)
        err_f.seek(0)
        err = err_f.read().decode("utf-8", "replace")
    seconds = time.perf_counter() - t0
    rc: int | str = "timeout" if timed_out else proc.returncode
    try:
        hwm_kib = int(hwm_file.read_text())
    except (OSError, ValueError):  # killed, or died before atexit
        hwm_kib = 0
    peak_mb = max(hwm_kib, polled_kib[0]) / 1024.0
    lines = err.strip().splitlines()
    problems = []
    traceback = "Traceback (most recent call last)" in err
    if traceback:
        last = next((ln for ln in reversed(lines) if re.match(r"^[\w.]+(Error|Exception|Interrupt|Exit)\b", ln)),
                    lines[-1] if lines else "")
        problems.append(f"traceback: {last.strip()[:200]}")
    problems += outcome_problems(case, rc, lines, work, before, fx, fx_before, prot)
    if peak_mb >= MEMORY_BUDGET_MB and rc != 0:  # the budget is a refusal's: accepted input did real work
        problems.append(f"peak RSS {peak_mb:.0f} MB >= 1 GB")
    left = sorted(q.name for q in tmpdir.iterdir())
    if left:
        problems.append(f"left in $TMPDIR: {left[:5]}")
    shutil.rmtree(tmpdir, ignore_errors=True)
    return {"id": case.id, "command": command_of(case.id), "expect": case.expect, "rc": rc,
            "stderr_lines": len(lines), "stderr_first": lines[0][:300] if lines else "",
            "traceback": traceback, "peak_rss_mb": round(peak_mb, 1), "seconds": round(seconds, 2),
            "problems": problems}


def _start_trigger() -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "prism3d.cli", "trigger", "simulate"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    port = proc.stdout.readline().strip()
    return proc, port


def summary(results: list[dict], skipped: list[str], wall_s: float) -> str:
    by = defaultdict(list)
    for r in results:
        by[r["command"]].append(r)
    out = ["# Bad-input probe (subprocess per case)", "",
           f"{len(results)} cases run, {sum(not r['problems'] for r in results)} pass, "
           f"{sum(bool(r['problems']) for r in results)} fail, {len(skipped)} skipped; wall {wall_s:.0f} s.", "",
           "| command | cases | pass | fail | max peak RSS (MB) | slowest (s) |", "|---|---|---|---|---|---|"]
    for cmd in sorted(by):
        rs = by[cmd]
        out.append(f"| {cmd} | {len(rs)} | {sum(not r['problems'] for r in rs)} | "
                   f"{sum(bool(r['problems']) for r in rs)} | {max(r['peak_rss_mb'] for r in rs):.0f} | "
                   f"{max(r['seconds'] for r in rs):.1f} |")
    if results:
        top = max(results, key=lambda r: r["peak_rss_mb"])
        out += ["", f"Max peak RSS overall: {top['peak_rss_mb']:.0f} MB ({top['id']})."]
    fails = [r for r in results if r["problems"]]
    if fails:
        out += ["", "## Failing cases", "", "| case | rc | peak MB | what happened |", "|---|---|---|---|"]
        for r in fails:
            what = "; ".join(r["problems"]).replace("|", "\\|")
            out.append(f"| `{r['id']}` | {r['rc']} | {r['peak_rss_mb']:.0f} | {what} |")
    if skipped:
        out += ["", "Skipped: " + ", ".join(skipped)]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=2, help="cases run in parallel (default 2)")
    ap.add_argument("--only", metavar="PREFIX", help="only case ids starting with PREFIX (several: comma-separated)")
    ap.add_argument("--json", type=Path, metavar="OUT", help="write every case's result as JSON")
    ap.add_argument("--fixtures", type=Path, metavar="DIR", help="reuse (or build once into) this folder")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds per case (default 60)")
    args = ap.parse_args(argv)

    prefixes = tuple(args.only.split(",")) if args.only else ("",)
    selected = [c for c in cases() if c.id.startswith(prefixes)]
    tmp = Path(tempfile.mkdtemp(prefix="prism3d_probe_"))
    fx = args.fixtures or tmp / "fx"
    if not (fx / "bad").is_dir():
        t = time.perf_counter()
        build_fixtures(fx)
        print(f"fixtures built in {time.perf_counter() - t:.1f} s at {fx}", file=sys.stderr)
    skipped = [c.id for c in selected if c.needs == "shared_data" and shared_data_dir() is None]
    selected = [c for c in selected if c.id not in skipped]
    serial = [c for c in selected if c.needs == "trigger"]
    parallel = [c for c in selected if c.needs != "trigger"]
    index = {c.id: i for i, c in enumerate(selected)}
    results: list[dict] = []
    t0 = time.perf_counter()

    def one(case: Case, trigger: str = "") -> dict:
        try:
            r = run_case(case, fx, tmp / "work" / f"{index[case.id]:04d}", trigger, args.timeout)
        except Exception as exc:  # noqa: BLE001 - the probe reports, never stops
            r = {"id": case.id, "command": command_of(case.id), "expect": case.expect, "rc": "not run",
                 "stderr_lines": 0, "stderr_first": "", "traceback": False, "peak_rss_mb": 0.0, "seconds": 0.0,
                 "problems": [f"could not run: {type(exc).__name__}: {exc}"]}
        mark = "ok " if not r["problems"] else "FAIL"
        print(f"{mark} {r['id']}: rc {r['rc']}, {r['peak_rss_mb']:.0f} MB, {r['seconds']:.1f} s"
              + (f" -- {'; '.join(r['problems'])}" if r["problems"] else ""), file=sys.stderr, flush=True)
        return r

    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        results += list(pool.map(one, parallel))
    if serial:
        proc, port = _start_trigger()
        try:
            results += [one(c, port) for c in serial]
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    results.sort(key=lambda r: index[r["id"]])
    wall = time.perf_counter() - t0
    if args.json:
        args.json.write_text(json.dumps({"wall_s": wall, "skipped": skipped, "results": results}, indent=1))
    print(summary(results, skipped, wall))
    return 0


if __name__ == "__main__":
    sys.exit(main())
