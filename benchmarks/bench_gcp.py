"""Benchmark: survey accuracy without a lab calibration (issue 42): GPS as a constraint in
the bundle adjustment, and ground control points, beside today's survey (a similarity onto
the GPS after the adjustment) in the same run.

Run::

    .venv/bin/python benchmarks/bench_gcp.py [--work /tmp/bench_gcp] [--blocks 12:3 12:4 48:3]

Per block (``simulate flight`` at 1600 x 1200, two lines of 6 for 12 frames, four of 12 for
48; FRAMES:SEED, two seeds of 12 frames as COLMAP's threads make each run differ; 8 painted
control points), every survey starts from EXIF only (no ``--calib``)
and runs through ``prism3d survey`` in this process:

- ``today``: ``--no-gps-prior`` (the similarity onto the GPS afterwards);
- ``gps prior``: the default (positions weighted at 1 m / 2 m);
- ``gps prior, true sigma``: ``--gps-accuracy 0.3,0.6`` (the simulator's GPS noise);
- ``5 gcp + gps``: the default with ``--gcp`` and 3 of the 8 points as checks.

The GPS-only rows give all 8 points as check points, so their absolute error in the map
frame is measured the same way (``gcp_check.json``: each point triangulated through the
final poses, compared with its map coordinates, no alignment). Scores: ``evaluate_survey``
(camera centres in GSD and rotations in deg after a similarity onto the truth; DSM error
on open ground after the same similarity, and once a horizontal shift and a plane are
removed as the issue scores it), the focal length against the truth, the check
points' RMS in GSD. Writes ``benchmarks/results/bench_gcp.json`` after each survey.
Benchmarks print; they never assert.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

from prism3d.cli import main as cli
from prism3d.datasets.evaluation.survey_eval import evaluate_survey

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "bench_gcp.json"
SIZE = "1600x1200"
N_GCP = 8
CHECKS = ("gcp06", "gcp07", "gcp08")
RUNS = (
    ("today", ["--no-gps-prior"], False),
    ("gps prior", [], False),
    ("gps prior, true sigma", ["--gps-accuracy", "0.3,0.6"], False),
    ("5 gcp + gps", [], True),
)


def _flight(work: Path, frames: int, seed: int) -> Path:
    d = work / f"flight_{frames}_{seed}"
    if not (d / "truth.json").is_file():
        lines = 2 if frames <= 24 else 4
        rc = cli(["-q", "simulate", "flight", str(d), "--frames", str(frames), "--lines", str(lines), "--size", SIZE,
                   "--seed", str(seed), "--gcp", str(N_GCP), "--no-depth"])
        assert rc == 0, rc
    return d


def _survey(flight: Path, out: Path, extra: list[str], control: bool) -> float:
    names = [p["name"] for p in json.loads((flight / "truth.json").read_text())["gcps"]["points"]]
    checks = list(CHECKS) if control else names
    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))
    t0 = time.perf_counter()
    rc = cli(["-q", "survey", *frames, "--gps", str(flight / "geoinfo.txt"), "--gcp", str(flight / "gcp_list.txt"),
               "--gcp-check", *checks, "-o", str(out), *extra])
    if rc != 0:
        raise SystemExit(f"survey {out} failed ({rc})")
    return time.perf_counter() - t0


def _score(flight: Path, out: Path) -> dict:
    truth = json.loads((flight / "truth.json").read_text())
    r = evaluate_survey(out, flight)
    poses = json.loads((out / "poses.json").read_text())
    check = json.loads((out / "gcp_check.json").read_text())
    f_true = truth["K"][0][0]
    return {
        "centres_max_gsd": r["position_error_gsd"]["max"], "centres_rms_gsd": r["position_error_gsd"]["rms"],
        "rotations_max_deg": r["rotation_error_deg"]["max"],
        "focal_error_pct": 100.0 * (poses["camera"]["K"][0][0] / f_true - 1.0),
        "dsm_median_gsd": r["dsm"]["median_abs_error_gsd"], "dsm_rms_gsd": r["dsm"]["rms_error_gsd"],
        "dsm_bias_m": r["dsm"]["bias_m"],
        "dsm_detrended_median_gsd": r["dsm"]["after_shift_and_plane"]["median_abs_error_gsd"],
        "dsm_detrended_rms_gsd": r["dsm"]["after_shift_and_plane"]["rms_error_gsd"],
        "self_calibration": poses["camera"].get("self_calibration"),
        "check_rms_h_gsd": check["check"]["rms_horizontal_gsd"], "check_rms_v_gsd": check["check"]["rms_vertical_gsd"],
        "check_points": check["check"]["points"],
        "georeference": poses["georeference"]["method"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_gcp"))
    ap.add_argument("--blocks", nargs="+", default=["12:3", "12:4", "48:3"], metavar="FRAMES:SEED")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    doc = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.node()} {os.cpu_count()} cores",
           "size": SIZE, "rows": []}
    for block in a.blocks:
        n, seed = (int(v) for v in block.split(":"))
        fl = _flight(a.work, n, seed)
        gsd = json.loads((fl / "truth.json").read_text())["gsd_m"]
        print(f"-- {n} frames, seed {seed}, GSD {100 * gsd:.1f} cm", flush=True)
        for label, extra, control in RUNS:
            out = a.work / f"s{n}_{seed}_{label.replace(' ', '_').replace(',', '').replace('+', 'and')}"
            if not (out / "poses.json").is_file():  # a rerun rescores the surveys it finds
                _survey(fl, out, extra, control)
            secs = float(json.loads((out / "poses.json").read_text())["seconds"]["total"])
            row = {"frames": n, "seed": seed, "run": label, "seconds": round(secs, 1), **_score(fl, out)}
            doc["rows"].append(row)
            print(f"{n:3d} {label:24s} centres max {row['centres_max_gsd']:.2f} rms {row['centres_rms_gsd']:.2f} GSD, "
                  f"rot max {row['rotations_max_deg']:.3f} deg, f {row['focal_error_pct']:+.2f} %, DSM median "
                  f"{row['dsm_median_gsd']:.2f} RMS {row['dsm_rms_gsd']:.2f} GSD (shift+plane removed: "
                  f"{row['dsm_detrended_median_gsd']:.2f} / {row['dsm_detrended_rms_gsd']:.2f}), check points "
                  f"({row['check_points']}) RMS h {row['check_rms_h_gsd']:.2f} v {row['check_rms_v_gsd']:.2f} GSD, "
                  f"{secs:.0f} s", flush=True)
            RESULTS.write_text(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
