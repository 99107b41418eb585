"""Benchmark: fresh-process wall time of ``prism3d match`` vs a plain OpenCV script.

Run::

    .venv/bin/python benchmarks/bench_startup.py [--repeat N] [--pair DIR] [--breakdown]

Both commands match the Middlebury teddy pair (450 x 375, 64 disparities) in a new
Python process each time, read the PNGs and write the disparity under a temporary
folder, so the times include interpreter start-up, imports, numba's loading of its
cached kernels and the matching itself:

* ``prism3d match LEFT RIGHT -o disp.pfm --num-disp 64`` (``python -m prism3d.cli``);
* a plain script: ``cv2.StereoSGBM_create(minDisparity=0, numDisparities=64,
  blockSize=5, P1=8*25, P2=32*25, uniquenessRatio=10, speckleWindowSize=100,
  speckleRange=2, mode=STEREO_SGBM_MODE_SGBM_3WAY)``, written as ``.npy``.

The runs alternate, after one warm-up run of each (the OS file cache; the numba
kernels should already be in numba's on-disk cache: ``make setup`` puts them
there). ``--breakdown`` also times the floors: a bare interpreter, ``import numpy``,
``import numpy, cv2``, ``import numba``, and one cached numba kernel call. Prints
a Markdown section with min and median; wall times on a shared machine are noisy,
so the minimum is the figure to compare. It never asserts.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[0].parent / "shared" / "data"
PAIR = "stereo/middlebury_2001_2003/teddy"

SGBM = """
import sys
import cv2, numpy as np
left = cv2.imread(sys.argv[1]); right = cv2.imread(sys.argv[2])
m = cv2.StereoSGBM_create(minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 25, P2=32 * 25,
                          uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                          mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
np.save(sys.argv[3], m.compute(left, right).astype(np.float32) / 16.0)
"""

CACHED_KERNEL = """
import numpy as np
from prism3d.reconstruct.stereo import _match_kernels as k
k.channels_equal(np.zeros((2, 2, 3), np.uint8))
"""


def _data_dir() -> Path | None:
    env = os.environ.get("PRISM3D_TEST_DATA")
    for d in ([Path(env)] if env else []) + [DATA]:
        if d.is_dir():
            return d
    return None


def _time(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                       text=True)
    dt = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed: {r.stderr[-2000:]}")
    return dt


def _measure(cmds: dict[str, list[str]], repeat: int) -> dict[str, list[float]]:
    for cmd in cmds.values():  # warm-up: file cache, numba cache check
        _time(cmd)
    times: dict[str, list[float]] = {k: [] for k in cmds}
    for _ in range(repeat):
        for name, cmd in cmds.items():
            times[name].append(_time(cmd))
    return times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=10, help="runs of each command (default 10)")
    ap.add_argument("--pair", type=Path,
                    help="folder with im2.png and im6.png (default: Middlebury teddy)")
    ap.add_argument("--breakdown", action="store_true", help="also time the import floors")
    args = ap.parse_args(argv)
    pair = args.pair
    if pair is None:
        data = _data_dir()
        if data is None or not (data / PAIR).is_dir():
            print("## Start-up\n\nskipped: the teddy pair was not found "
                  "(set PRISM3D_TEST_DATA or --pair)")
            return 0
        pair = data / PAIR
    left, right = str(pair / "im2.png"), str(pair / "im6.png")
    py = sys.executable
    with tempfile.TemporaryDirectory(prefix="prism3d-bench-") as tmp:
        cmds = {
            "prism3d match": [py, "-m", "prism3d.cli", "match", left, right, "-o", f"{tmp}/d.pfm",
                              "--num-disp", "64"],
            "OpenCV SGBM script": [py, "-c", SGBM, left, right, f"{tmp}/d.npy"],
        }
        if args.breakdown:
            cmds.update({
                "python -c pass": [py, "-c", "pass"],
                "import numpy": [py, "-c", "import numpy"],
                "import numpy, cv2": [py, "-c", "import numpy, cv2"],
                "import numba": [py, "-c", "import numba"],
                "import prism3d.cli": [py, "-c", "import prism3d.cli"],
                "one cached kernel call": [py, "-c", CACHED_KERNEL],
            })
        times = _measure(cmds, args.repeat)
    print(f"## Start-up: fresh-process wall time, teddy 450x375, 64 disparities "
          f"({args.repeat} runs)\n")
    print("| command | min (ms) | median (ms) |")
    print("|---|---:|---:|")
    for name, ts in times.items():
        print(f"| {name} | {1e3 * min(ts):.0f} | {1e3 * statistics.median(ts):.0f} |")
    a, b = times["prism3d match"], times["OpenCV SGBM script"]
    print(f"\nratio prism3d / OpenCV: {min(a) / min(b):.2f}x (min), "
          f"{statistics.median(a) / statistics.median(b):.2f}x (median)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
