"""Benchmark: one 5 MP prism shot -> scan, prism3d against an OpenCV pipeline on the same
shot in the same run.

Run::

    .venv/bin/python benchmarks/bench_reconstruct.py [--repeat N] [--cache DIR]

Shots: the paper's plate (grating on) and a camouflaged tank view, 2592x1944, simulated
once with the real camera effects into ``--cache``. prism3d: ``reconstruct_shot`` (split,
rectify, match, select, refine, fill, triangulate with normals), min of ``--repeat`` runs
after a warm-up, with its stage times; and the whole ``prism3d reconstruct`` command in a
fresh process. OpenCV on the same geometry: ``remap`` with prism3d's rectification
tables (fixed point), StereoSGBM 3-way on the same disparity range, ``reprojectImageTo3D``
and the valid points (no normals, no refinement, no selection). Benchmarks print; they never assert.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import prism3d  # noqa: F401,I001  (first: the thread pools' idle policy, before numpy loads OpenBLAS)
import cv2
import numpy as np


PRISM3D = Path(sys.executable).parent / "prism3d"


def _shots(cache: Path) -> dict[str, Path]:
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
    from prism3d.datasets.models.targets import builtin_target

    out = {}
    for name, kw in (("plate", dict(kind="plate", pattern=True, camouflage=False)),
                     ("tank view 1", dict(kind="scene", target=builtin_target("tank_t1", seed=0), views=2))):
        folder = cache / name.replace(" ", "_")
        if not (folder / "rig.yaml").exists():
            kind = kw.pop("kind")
            simulate_to_folder(kind, folder, SimulateOptions(**{k: v for k, v in kw.items() if k != "target"}),
                               target=kw.get("target"))
        out[name] = folder
    return out


def _opencv(shot: np.ndarray, rig, min_disp: int, num_disp: int) -> tuple[float, int]:
    """OpenCV on the same geometry: remap with prism3d's rectification tables, StereoSGBM
    3-way on the same disparity range, reprojectImageTo3D with the same Q."""
    from prism3d.capture.rig import compute_rectification
    from prism3d.reconstruct.stereo.rectify import rectify_maps

    rect = compute_rectification(rig)
    maps = rectify_maps(rig, rect, fixed_point=True)
    t = time.perf_counter()
    left, right = rig.split.split(shot)
    lr = cv2.remap(left, maps.left_x, maps.left_y, cv2.INTER_LINEAR)
    rr = cv2.remap(right, maps.right_x, maps.right_y, cv2.INTER_LINEAR)
    m = cv2.StereoSGBM_create(minDisparity=int(min_disp), numDisparities=int(num_disp), blockSize=5,
                              P1=8 * 3 * 25, P2=32 * 3 * 25, uniquenessRatio=10, speckleWindowSize=100,
                              speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    d = m.compute(lr[:, :, ::-1], rr[:, :, ::-1]).astype(np.float32) / 16.0
    ok = d > min_disp
    pts = cv2.reprojectImageTo3D(d, np.asarray(rect.Q))[ok]
    return time.perf_counter() - t, len(pts)


def main() -> None:
    from prism3d.capture.rig import StereoRig
    from prism3d.io.images import read_image
    from prism3d.reconstruct.stereo.pipeline import reconstruct_shot

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/prism3d_bench_reconstruct"))
    a = ap.parse_args()
    cv2.setNumThreads(2)
    print(f"## 5 MP shot -> scan ({time.strftime('%Y-%m-%d')}; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores; min of {a.repeat} after a warm-up)\n")
    print("| shot | prism3d s | stages (s) | points | CLI fresh process s | OpenCV rectify+SGBM+reproject s | "
          "points | ratio |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for name, folder in _shots(a.cache).items():
        rig = StereoRig.load(folder / "rig.yaml")
        shot_file = folder / ("shot.png" if (folder / "shot.png").exists() else "shot_01.png")
        shot = read_image(shot_file)
        rec = reconstruct_shot(shot, rig)
        best, stages = math.inf, {}
        for _ in range(a.repeat):
            t = time.perf_counter()
            rec = reconstruct_shot(shot, rig)
            dt = time.perf_counter() - t
            if dt < best:
                best, stages = dt, rec.timings_s
        with tempfile.TemporaryDirectory() as td:
            t = time.perf_counter()
            subprocess.run([str(PRISM3D), "-q", "reconstruct", str(shot_file), "--calib", str(folder / "rig.yaml"),
                            "-o", str(Path(td) / "scan.ply")], check=True)
            cli = time.perf_counter() - t
        cv_best, n_cv = math.inf, 0
        _opencv(shot, rig, rec.min_disp, rec.num_disp)
        for _ in range(a.repeat):
            dt, n_cv = _opencv(shot, rig, rec.min_disp, rec.num_disp)
            cv_best = min(cv_best, dt)
        st = ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
        print(f"| {name} | {best:.2f} | {st} | {len(rec.scan)} | {cli:.2f} | {cv_best:.2f} | {n_cv} | "
              f"{best / cv_best:.2f} |", flush=True)


if __name__ == "__main__":
    main()
