"""Run every ``benchmarks/bench_*.py`` and record their output in ``RESULTS.md``.

Each benchmark compares prism3d with OpenCV / Open3D in the same run and prints a
Markdown section (timings and ratios). Wall times are noisy: benchmarks print, they
never assert.

Usage: ``python benchmarks/run_all.py [NAME ...]`` (names without ``bench_``/``.py``).
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent


def machine_details() -> str:
    import numpy

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M UTC}; {cpu}; {os.cpu_count()} cores; "
            f"Python {platform.python_version()}; numpy {numpy.__version__}")


def main(argv: list[str]) -> int:
    names = argv or sorted(p.stem[len("bench_"):] for p in HERE.glob("bench_*.py"))
    sections = [f"_Run: {machine_details()}_\n"]
    rc = 0
    for name in names:
        script = HERE / f"bench_{name}.py"
        print(f"== {script.name}", flush=True)
        r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True)
        print(r.stdout, end="")
        if r.returncode:
            print(r.stderr, file=sys.stderr)
            rc = 1
            sections.append(f"## {name}\n\nFAILED (exit {r.returncode})\n")
        else:
            sections.append(r.stdout.strip() + "\n")
    out = HERE / "RESULTS_latest.md"
    out.write_text("# Benchmark run\n\n" + "\n".join(sections))
    print(f"wrote {out} (copy the sections you trust into RESULTS.md)")
    return rc


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
