"""A real street scene (KITTI 2015, frame 000046_10; ../shared/data/stereo): reconstructed
with our matcher, then ``prism3d detect --targets car`` (the recogniser of the civilian
cars, trained on rendered models and mined simulated scenes) and, beside it, a plain filter
bank of the same cars and the van (``bank train --scenes 0``: a bank needs two classes).
Passes when the top detection falls on the crossing car (drawn by hand: rows 185-262,
columns 615-835) and is called a car; the sky's and far points' depths (our matcher gives
them kilometres) must not stop ``detect``.

    python benchmarks/bench_kitti_detect.py --data ../shared/data
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from prism3d.io.images import read_image, write_image
from prism3d.reconstruct.stereo.match import match_stereo
from prism3d.reconstruct.stereo.stereo_eval import load_benchmark_pair, sky_mask

#: KITTI's rectified colour cameras (devkit calibration of the 2011_09_26 drives).
KITTI_F, KITTI_B_MM = 721.5377, 537.2
CAR_ROWS, CAR_COLS = (185, 262), (615, 835)


KITTI_CALIB = ("S_rect_02: 1242 375\n"
               "P_rect_02: 721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884\n"
               "S_rect_03: 1242 375\n"
               "P_rect_03: 721.5377 0 609.5593 -339.5242 0 721.5377 172.854 2.199936 0 0 1 0.002729905\n")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--work", type=Path, default=Path("/tmp/kitti_detect"))
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "kitti_detect.json")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    left, right, gt, _ = load_benchmark_pair(a.data, "kitti")
    t0 = time.perf_counter()
    d = match_stereo(left, right, min_disp=0, num_disp=int(np.ceil(gt.max() + 1)))
    t_match = time.perf_counter() - t0
    depth = np.where(np.isfinite(d) & (d > 0), KITTI_F * KITTI_B_MM / np.maximum(d, 1e-6), np.nan).astype(np.float32)
    write_image(a.work / "left.png", left)
    np.save(a.work / "depth.npy", depth)
    far = float(np.nanmax(depth)) / 1000.0
    res = {"matcher_s": round(t_match, 2), "depth_max_km": round(far / 1000.0, 2),
           "sky_share_with_depth": float(np.isfinite(depth[:60]).mean()), "runs": {}}
    # the user's route: `prism3d reconstruct --left --right` (the far-point, isolation and
    # enclosure rules of a search reaching infinity) -> its depth map
    cal = a.work / "calib_cam_to_cam.txt"
    cal.write_text(KITTI_CALIB)
    k = a.data / "stereo" / "kitti2015_sample"
    subprocess.run([sys.executable, "-m", "prism3d.cli", "-q", "reconstruct", "--left", str(k / "image_2_000046_10.png"),
                    "--right", str(k / "image_3_000046_10.png"), "--calib", str(cal), "-o", str(a.work / "scan.ply"),
                    "--depth-out", str(a.work / "depth_pipeline.npy")], check=True)
    sky = sky_mask(read_image(k / "image_2_000046_10.png"))
    res["sky_with_depth"] = {"matcher": float(np.isfinite(depth[sky]).mean()),
                             "reconstruct": float(np.isfinite(np.load(a.work / "depth_pipeline.npy")[sky]).mean())}
    print(f"sky pixels with a depth: matcher alone {res['sky_with_depth']['matcher']:.1%}, "
          f"prism3d reconstruct {res['sky_with_depth']['reconstruct']:.1%}")
    cmd = [sys.executable, "-m", "prism3d.cli", "-q", "detect", "--image", str(a.work / "left.png"), "--depth",
           str(a.work / "depth.npy"), "--fx", str(KITTI_F)]
    subprocess.run([sys.executable, "-m", "prism3d.cli", "-q", "bank", "train", "--scenes", "0", "--targets", "car", "van",
                    "--channel", "shape", "-o", str(a.work / "car_bank.npz")], check=True)
    raw_depth = str(a.work / "depth.npy")
    pipeline = [str(a.work / "depth_pipeline.npy") if arg == raw_depth else arg for arg in cmd]
    for name, base, extra in (("recogniser", cmd, ["--targets", "car"]),
                              ("recogniser on reconstruct's depth", pipeline, ["--targets", "car"]),
                              ("bank", cmd, ["--bank", str(a.work / "car_bank.npz")])):
        out = a.work / f"det_{name.replace(' ', '_').replace(chr(39), '')}.json"
        t1 = time.perf_counter()
        r = subprocess.run(base + extra + ["-o", str(out), "--draw", str(out.with_suffix(".png"))],
                           capture_output=True, text=True)
        wall = time.perf_counter() - t1
        if r.returncode != 0:
            res["runs"][name] = {"error": r.stderr.strip()}
            print(name, "failed:", r.stderr.strip())
            continue
        doc = json.loads(out.read_text())
        dets = sorted(doc["detections"], key=lambda x: -x["score"])
        top = dets[0] if dets else None
        on_car = bool(top and CAR_ROWS[0] <= top["row"] <= CAR_ROWS[1] and CAR_COLS[0] <= top["col"] <= CAR_COLS[1])
        res["runs"][name] = {"n_detections": len(dets), "top": top, "top_on_car": on_car,
                             "top_called_car": bool(top and top["class"] == "car"), "timings_s": doc["timings_s"],
                             "wall_s": round(wall, 1)}
        print(f"{name}: {len(dets)} detections; top at row {top['row']:.0f} col {top['col']:.0f}, {top['class']} "
              f"{top['score']:.3f}: on the car {on_car}; {wall:.0f} s wall" if top else f"{name}: no detection")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1, default=float))


if __name__ == "__main__":
    main()
