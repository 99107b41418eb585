"""Time a full-resolution simulated plate shot (2592x1944 sensor, colour pattern,
2x2 supersampling) and print the breakdown.

Run: ``.venv/bin/python benchmarks/bench_simulate.py [--supersample 2] [--repeat 1]``
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

import prism3d  # noqa: F401  (environment first)
from prism3d.capture import render as render_mod
from prism3d.capture.rig import paper_rig
from prism3d.capture.camouflage import CamouflageField
from prism3d.capture.scenes import flat_plate, translation
from prism3d.capture.simulate import Projector, simulate_shot


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()

    timings: dict[str, float] = {}

    def timed(name, fn):
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                timings[name] = timings.get(name, 0.0) + time.perf_counter() - t

        return wrapper

    R = render_mod.RaycastRenderer
    R.render = timed("render (rays + cast + refine + albedo)", R.render)
    R.visible_from = timed("  of which shadow rays", R.visible_from)
    R.albedo = timed("  of which albedo field", R.albedo)
    render_mod.box_downsample = timed("box downsample", render_mod.box_downsample)

    rig = paper_rig()
    projector = Projector.for_rig(rig, pattern=True)
    objs = [(flat_plate(300, 300, albedo=CamouflageField.from_palette("woodland", patch_size_mm=60.0)), translation(0, 0, 1250))]
    # warm-up (numba compile / cache load) on a tiny rig
    small = paper_rig(sensor_size=(324, 244), focal_px=5107 / 8)
    simulate_shot(small, objs, projector=Projector.for_rig(small), supersample=2)
    timings.clear()
    best = np.inf
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        shot = simulate_shot(rig, objs, projector=projector, supersample=args.supersample, noise=True, seed=0)
        best = min(best, time.perf_counter() - t0)
    n = args.repeat
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"python {platform.python_version()}")
    print(f"full plate shot {shot.sensor_image.shape[1]}x{shot.sensor_image.shape[0]}, "
          f"supersample {args.supersample}, pattern on, noise on: best {best:.2f} s")
    for k, v in timings.items():
        print(f"  {k:42s} {v / n:7.2f} s")
    # shadow rays and albedo happen inside render/_illumination; the remainder is
    # illumination maths, the disparity view, noise and the join
    print(f"  rays traced per shot: {(args.supersample**2 + 1) * 2 * 1296 * 1944 * 2 / 1e6:.1f} M "
          "(camera + shadow, colour + truth)")


if __name__ == "__main__":
    main()
