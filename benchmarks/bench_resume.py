"""Resume (issue 39): a simulated 50-frame survey run whole, then killed with SIGKILL in its
dense stage once half its pairs are done and rerun with ``--resume``; the time the
resumed run took against the whole one, and whether their products are the same bits.

    python benchmarks/bench_resume.py [--frames 50] [--size 800x600] [--work DIR]

COLMAP runs on one thread (``PRISM3D_NUM_THREADS=1``) so that both surveys can be
compared bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight
from prism3d.io.geo import read_geotiff


def _cmd(flight: Path, out: Path) -> list[str]:
    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))
    return [sys.executable, "-m", "prism3d.cli", "-q", "survey", *frames, "--calib", str(flight / "camera.yaml"),
            "--gps", str(flight / "geoinfo.txt"), "-o", str(out)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--size", default="800x600")
    ap.add_argument("--work", type=Path)
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.split("x"))
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_resume."))
    env = dict(os.environ, PRISM3D_NUM_THREADS="1")
    try:
        flight = work / "flight"
        if not flight.is_dir():
            simulate_flight(flight, FlightOptions(size=(w, h), altitude_m=40.0, seed=11, frames=a.frames,
                                                  lines=2, targets=8))
        whole = work / "whole"
        shutil.rmtree(whole, ignore_errors=True)
        t0 = time.perf_counter()
        subprocess.run(_cmd(flight, whole), env=env, check=True)
        t_whole = time.perf_counter() - t0
        n_pairs = len(json.loads((whole / "poses.json").read_text())["dense"]["pairs"])
        out = work / "killed"
        shutil.rmtree(out, ignore_errors=True)
        shutil.rmtree(work / ".killed.resume", ignore_errors=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen(_cmd(flight, out), env=env)
        pairs = work / ".killed.resume" / "pairs"
        while proc.poll() is None and len(list(pairs.glob("*.npz"))) < n_pairs // 2:
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        t_killed = time.perf_counter() - t0
        kept = len(list(pairs.glob("*.npz")))
        t0 = time.perf_counter()
        subprocess.run(_cmd(flight, out) + ["--resume"], env=env, check=True)
        t_resumed = time.perf_counter() - t0
        same = all(np.array_equal(read_geotiff(whole / n)[0], read_geotiff(out / n)[0], equal_nan=True)
                   for n in ("dsm.tif", "ground.tif", "ndsm.tif", "ortho.tif"))
        left = sorted(p.name for p in work.iterdir() if p.name.startswith(".killed"))
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print(f"| frames | pairs | whole run (s) | killed after (s), pairs kept | resumed run (s) | saved | "
          f"products identical | left behind |")
    print("|---|---|---|---|---|---|---|---|")
    print(f"| {a.frames} ({w}x{h}) | {n_pairs} | {t_whole:.1f} | {t_killed:.1f}, {kept} | {t_resumed:.1f} | "
          f"{1 - t_resumed / t_whole:.0%} | {same} | {left or 'nothing'} |")
    return 0 if same and not left else 1


if __name__ == "__main__":
    sys.exit(main())
