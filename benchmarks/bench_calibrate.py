"""Benchmark: chessboard corner detectors and our bundle adjustment vs OpenCV.

Run::

    .venv/bin/python benchmarks/bench_calibrate.py [--sim DIR]

* Corner accuracy against the virtual rig's true corners (``prism3d simulate calib``;
  written to DIR first if it holds no ``calib_*.png``; takes ~2.5 min).
* OpenCV's real 9x6 stereo set (``../shared/data``): per-camera and joint stereo RMS
  of our calibration for each detector, next to ``cv2.calibrateCamera`` /
  ``cv2.stereoCalibrate`` on the same corners, with timings.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import prism3d.reconstruct.stereo.corners as corners_mod
from prism3d.reconstruct.stereo.calibrate import CalibrationOptions, calibrate_camera, calibrate_stereo
from prism3d.reconstruct.stereo.corners import board_object_points, detect_views, grid_symmetries

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "calibration"
VARIANTS = [
    ("xjunction", None),
    ("classic", 3),
    ("classic", 5),
    ("classic", 7),
    ("classic", 11),
    ("classic", None),
    ("sb", None),
]


def _name(method: str, window: int | None) -> str:
    if method == "sb":
        return "findChessboardCornersSB"
    if method == "xjunction":
        return f"classic + X-junction model fit, radius {corners_mod.XJ_RADIUS_FRACTION} x spacing"
    w = f"half-window {window}" if window else f"half-window {corners_mod.WINDOW_FRACTION} x square"
    return f"findChessboardCorners + cornerSubPix, {w}"


def bench_sim(folder: Path) -> None:
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder

    if not list(folder.glob("calib_*.png")):
        simulate_to_folder("calib", folder, SimulateOptions(seed=0, noise=True))
    images = sorted(folder.glob("calib_*.png"))
    truth = [np.load(p, allow_pickle=False) for p in sorted(folder.glob("truth_*.npz"))]
    perms = grid_symmetries((9, 6))
    print("\n# virtual paper rig: corner error vs truth (px)")
    for method, window in VARIANTS:
        t = time.perf_counter()
        dets, _ = detect_views(images, method=method, window=window)
        dt = time.perf_counter() - t
        errs, missing = [], 0
        for (lft, rgt), tr in zip(dets, truth, strict=True):
            for d, key in ((lft, "corners_left"), (rgt, "corners_right")):
                if not d.found:
                    missing += 1
                    continue
                errs.append(
                    min(
                        (np.linalg.norm(d.corners[p] - tr[key], axis=1) for p in perms), key=np.mean
                    )
                )
        e = np.concatenate(errs) if errs else np.array([np.nan])
        print(
            f"{_name(method, window):60s} RMS {np.sqrt(np.mean(e**2)):.4f} max {e.max():.4f} "
            f"missed {missing:2d} views  {dt:.1f} s"
        )


def bench_real() -> None:
    import cv2

    d = DATA / "opencv_stereo_9x6"
    if not d.is_dir():
        print("real data not found:", d)
        return
    images = []
    for i in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14):
        images += [d / f"left{i:02d}.jpg", d / f"right{i:02d}.jpg"]
    obj = board_object_points((9, 6), 25.0)
    print("\n# OpenCV 9x6 stereo set, k1 k2 model: RMS px (left / right)")
    for method, window in VARIANTS:
        t = time.perf_counter()
        opts = CalibrationOptions(pairs=True, tangential=False, method=method, window=window)
        cal = calibrate_stereo(images, options=opts)
        cal_def = calibrate_stereo(images, options=CalibrationOptions(pairs=True, method=method, window=window))
        dt = time.perf_counter() - t
        pts = {s: [x.corners for x in cal.detections if x.view == s] for s in ("left", "right")}
        ok = [
            i
            for i in range(len(pts["left"]))
            if pts["left"][i] is not None and pts["right"][i] is not None
        ]
        single = [
            calibrate_camera(
                [obj] * len(ok), [pts[s][i] for i in ok], (640, 480), tangential=False
            ).rms_px
            for s in ("left", "right")
        ]
        print(
            f"{_name(method, window):60s} ours: single {single[0]:.4f} / {single[1]:.4f}, "
            f"stereo {cal.rms_left_px:.4f} / {cal.rms_right_px:.4f}, rect {cal.rectification_rms_px:.4f}, "
            f"B {cal.rig.baseline_mm:.2f} mm; default k1k2p1p2 rect {cal_def.rectification_rms_px:.4f} "
            f"({dt:.1f} s incl. detection)"
        )
    # OpenCV on our default corners
    cal = calibrate_stereo(images, options=CalibrationOptions(pairs=True, tangential=False))
    pl = [x.corners.astype(np.float32) for x in cal.detections if x.view == "left"]
    pr = [x.corners.astype(np.float32) for x in cal.detections if x.view == "right"]
    o = [obj.astype(np.float32)] * len(pl)
    flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    t = time.perf_counter()
    r1, K1, D1, _, _ = cv2.calibrateCamera(o, pl, (640, 480), None, None, flags=flags)
    r2, K2, D2, _, _ = cv2.calibrateCamera(o, pr, (640, 480), None, None, flags=flags)
    rs, *_, T, _, _ = cv2.stereoCalibrate(
        o, pl, pr, K1, D1, K2, D2, (640, 480), flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS
    )
    dt = time.perf_counter() - t
    print(
        f"{'OpenCV calibrateCamera x2 + stereoCalibrate (same corners)':60s} single {r1:.4f} / {r2:.4f}, "
        f"stereo {rs:.4f} (both cameras), B {np.linalg.norm(T):.2f} mm  ({dt:.2f} s)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument(
        "--sim", type=Path, default=None, help="folder of a 'prism3d simulate calib' run"
    )
    args = ap.parse_args()
    if args.sim is not None:
        bench_sim(args.sim)
    bench_real()


if __name__ == "__main__":
    main()
