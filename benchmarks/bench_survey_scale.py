"""Survey cost against block size (issue 39): simulated lawnmower blocks (70 % forward /
60 % side overlap) of 12, 50 and 100 frames (``--frames``), each surveyed with the default
matching (all pairs up to 40 frames, then each frame with its 20 nearest by GPS) and with
pycolmap's exhaustive matching (the anchor) in the same run: seconds per frame of each
stage, peak memory of the survey process, and the poses against the flight's truth.

    python benchmarks/bench_survey_scale.py [--frames 12 50 100] [--size 800x600] [--work DIR] [--json OUT]
        [--matchings auto exhaustive] [--workers 0 2]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from prism3d.datasets.evaluation.survey_eval import evaluate_survey
from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight


def _lines(frames: int) -> int:
    """Flight lines for a block: about square, frames a multiple of the lines."""
    for n in (4, 3, 2):
        if frames % n == 0 and frames // n >= 6:
            return n
    return 2


def _survey(flight: Path, out: Path, matching: str, env: dict, workers: int = 0) -> dict:
    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    r = subprocess.run(["/usr/bin/time", "-f", "maxrss_kb %M", sys.executable, "-m", "prism3d.cli", "-q", "survey",
                        *frames, "--calib", str(flight / "camera.yaml"), "--gps", str(flight / "geoinfo.txt"),
                        "--matching", matching, *(["--workers", str(workers)] if workers else []), "-o", str(out)],
                       env=env, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    peak = max(int(ln.split()[1]) for ln in r.stderr.splitlines() if ln.startswith("maxrss_kb"))
    doc = json.loads((out / "poses.json").read_text())
    ev = evaluate_survey(out, flight)
    n = len(frames)
    return {"frames": n, "matching": matching, "workers": workers, "wall_s": round(wall, 1),
            "per_frame_s": {k: round(v / n, 3) for k, v in doc["seconds"].items()},
            "peak_rss_mb": round(peak / 1024), "placed": ev["frames_placed"],
            "position_error_gsd_max": round(ev["position_error_gsd"]["max"], 3),
            "rotation_error_deg_max": round(ev["rotation_error_deg"]["max"], 4),
            "dsm_median_error_gsd": round(ev["dsm"]["median_abs_error_gsd"], 3)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[12, 50, 100])
    ap.add_argument("--size", default="800x600")
    ap.add_argument("--work", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--matchings", nargs="+", default=["auto", "exhaustive"], help="matchings surveyed per block")
    ap.add_argument("--workers", type=int, nargs="+", default=[0],
                    help="dense pairs in this process (0) and/or on N Dask workers, per block and matching")
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.split("x"))
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_scale."))
    env = dict(os.environ, PRISM3D_NUM_THREADS=os.environ.get("PRISM3D_NUM_THREADS", "0"))
    rows = []
    try:
        for n in a.frames:
            flight = work / f"flight_{n}"
            if not flight.is_dir():
                simulate_flight(flight, FlightOptions(size=(w, h), altitude_m=40.0, seed=21, frames=n, lines=_lines(n),
                                                      targets=8))
            for m in a.matchings:
                for nw in a.workers:
                    rows.append(_survey(flight, work / f"s_{n}_{m}_{nw}", m, env, nw))
                    print(json.dumps(rows[-1]), flush=True)
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print("| frames | matching | workers | poses s/frame | dense s/frame | fusion s/frame | products s/frame | total s/frame "
          "| peak MB | placed | position err max (GSD) | rotation err max (deg) | DSM median err (GSD) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        p = r["per_frame_s"]
        print(f"| {r['frames']} | {r['matching']} | {r['workers']} | {p['poses']} | {p['dense']} | {p['fusion']} | {p['products']} | "
              f"{p['total']} | {r['peak_rss_mb']} | {r['placed']} | {r['position_error_gsd_max']} | {r['rotation_error_deg_max']} | "
              f"{r['dsm_median_error_gsd']} |")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
