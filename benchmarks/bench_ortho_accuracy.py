"""Orthophoto accuracy on the simulator (issue 39): where painted marks land in
``ortho.tif`` against their true positions, and how far two frames' colours disagree where
a seam could join them.

A flight with painted 2 x 2 chequer markers (``simulate flight --gcp N``) is surveyed twice,
in the local ENU frame (``--crs enu``: the orthophoto on the survey's own grid):

- **GPS only** (the default). The marks are scored *after* the similarity that takes the
  survey's camera centres onto the true ones, as the DSM is scored (``evaluate_survey``).
  This is the orthophoto's own geometry; the GPS's placement error is issue 42's.
- **With control points** (``--gcp``, the first ``--control`` markers held, the rest
  checks). The check marks are scored with no alignment at all: absolute positions.

A mark is found by a chequer-centre detector (point symmetry with a quarter-turn sign flip,
then OpenCV's ``cornerSubPix``) near where it should be. Seams: each pair of neighbouring
frames is orthorectified alone over the same DSM, and OpenCV's phase correlation measures
the shift between the two in 128-pixel tiles of their overlap.

    python benchmarks/bench_ortho_accuracy.py [--work DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

os.environ.setdefault("PRISM3D_NUM_THREADS", "1")  # COLMAP on one thread: reproducible surveys

from prism3d.cli import main  # noqa: E402
from prism3d.datasets.evaluation.survey_eval import _pose_scores, _to_truth_frame  # noqa: E402
from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight  # noqa: E402
from prism3d.datasets.simulation.flight_gcp import marker_side_m  # noqa: E402
from prism3d.io.geo import read_geotiff  # noqa: E402
from prism3d.reconstruct.survey.ortho import true_orthophoto  # noqa: E402

TILE = 128


def chequer_centre(grey: np.ndarray, r0: float, c0: float, search: int, radius: int) -> tuple[float, float] | None:
    """The 2 x 2 chequer centre nearest (r0, c0) within ``search`` px: the pixel where the
    patch is most point-symmetric and most unlike its quarter turn, refined by cornerSubPix."""
    g = grey.astype(np.float32)
    R, C = int(round(r0)), int(round(c0))
    pad = search + radius + 2
    if R - pad < 0 or C - pad < 0 or R + pad >= g.shape[0] or C + pad >= g.shape[1]:
        return None
    win = g[R - pad:R + pad + 1, C - pad:C + pad + 1]
    n = 2 * search + 1
    sym = np.zeros((n, n), np.float32)
    turn = np.zeros((n, n), np.float32)
    o = radius + 2
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy * dy + dx * dx > radius * radius or (dy == 0 and dx == 0):
                continue
            a = win[o + dy:o + dy + n, o + dx:o + dx + n]
            b = win[o - dy:o - dy + n, o - dx:o - dx + n]
            q = win[o - dx:o - dx + n, o + dy:o + dy + n]  # the offset turned a quarter
            sym += (a - b) ** 2
            turn += (a - q) ** 2
    score = turn - sym
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    if score[i, j] <= 0:
        return None
    pt = np.array([[[C - search + j, R - search + i]]], np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.01)
    cv2.cornerSubPix(grey.astype(np.uint8), pt, (max(2, radius // 2),) * 2, (-1, -1), crit)
    return float(pt[0, 0, 1]), float(pt[0, 0, 0])


def marks(survey: Path, truth: dict, *, aligned: bool, names: set[str] | None = None) -> list[dict]:
    """Each marker's error in the orthophoto (GSD): found against expected."""
    doc = json.loads((survey / "poses.json").read_text())
    ortho, om = read_geotiff(survey / "ortho.tif")
    grey = cv2.cvtColor(np.ascontiguousarray(ortho[..., :3]), cv2.COLOR_RGB2GRAY)
    gsd, so, to = float(truth["gsd_m"]), np.asarray(doc["origin_lla"]), np.asarray(truth["origin_lla"])
    _, fr = _pose_scores(doc, truth)
    side_px = marker_side_m(gsd) / om["gsd"]
    out = []
    for g in truth["gcps"]["points"]:
        if names is not None and g["name"] not in names:
            continue
        p_true = np.asarray(g["enu"], dtype=np.float64)
        # expected in the survey's ENU: the true point through the inverse alignment, or as it is
        q = (p_true - fr.t) @ fr.R / fr.s if aligned else p_true
        p_s = _to_truth_frame(q[None], to, so)[0]
        r0, c0 = (om["north"] - p_s[1]) / om["gsd"] - 0.5, (p_s[0] - om["west"]) / om["gsd"] - 0.5
        found = chequer_centre(grey, r0, c0, search=max(6, int(side_px / 3)), radius=max(3, int(side_px / 3)))
        if found is None:
            out.append({"name": g["name"], "found": False})
            continue
        e = np.hypot(found[0] - r0, found[1] - c0) * om["gsd"] / gsd
        out.append({"name": g["name"], "found": True, "error_gsd": round(float(e), 3)})
    return out


def seams(survey: Path, truth: dict) -> list[dict]:
    """Shift (GSD) between neighbouring frames' orthophotos over the same DSM, per tile of overlap."""
    doc = json.loads((survey / "poses.json").read_text())
    dsm, meta = read_geotiff(survey / "dsm.tif")
    K, dist, size = np.asarray(doc["camera"]["K"]), np.asarray(doc["camera"]["dist"]), tuple(doc["camera"]["size"])
    frames = [(f["image"], np.asarray(f["T_enu_cam"])) for f in doc["frames"] if f["T_enu_cam"] is not None]
    gsd = float(truth["gsd_m"])
    out = []
    og = float(doc["ortho"]["gsd"])

    def alone(f: tuple[str, np.ndarray]):
        return true_orthophoto(dsm, meta["west"], meta["north"], meta["gsd"], [f], K, dist, size, gsd=og)

    ob = alone(frames[0]) if frames else None
    for (pa, _), (pb, Tb) in zip(frames, frames[1:]):
        oa, ob = ob, alone((pb, Tb))  # each frame orthorectified once
        both = (oa.rgba[..., 3] > 0) & (ob.rgba[..., 3] > 0) & (oa.quality == 1) & (ob.quality == 1)
        ga = cv2.cvtColor(oa.rgba[..., :3], cv2.COLOR_RGB2GRAY).astype(np.float64)
        gb = cv2.cvtColor(ob.rgba[..., :3], cv2.COLOR_RGB2GRAY).astype(np.float64)
        win = cv2.createHanningWindow((TILE, TILE), cv2.CV_64F)
        for r in range(0, both.shape[0] - TILE, TILE):
            for c in range(0, both.shape[1] - TILE, TILE):
                if both[r:r + TILE, c:c + TILE].mean() < 0.95 or ga[r:r + TILE, c:c + TILE].std() < 4:
                    continue
                (dx, dy), resp = cv2.phaseCorrelate(ga[r:r + TILE, c:c + TILE], gb[r:r + TILE, c:c + TILE], win)
                if resp > 0.2:
                    a, b = ga[r:r + TILE, c:c + TILE], gb[r:r + TILE, c:c + TILE]
                    out.append({"frames": [Path(pa).name, Path(pb).name], "tile_rc": [r, c],
                                "ncc_zero_shift": round(_ncc_shifted(a, b, 0.0, 0.0), 3),
                                "shift_gsd": round(float(np.hypot(dx, dy)) * oa.gsd / gsd, 3),
                                "confirmed": bool(np.hypot(dx, dy) < 1.0  # sub-pixel: resampling would decide
                                                  or _ncc_shifted(a, b, dx, dy) >= _ncc_shifted(a, b, 0.0, 0.0))})
    return out


def _ncc_shifted(a: np.ndarray, b: np.ndarray, dx: float, dy: float) -> float:
    """Normalised cross-correlation of ``a`` with ``b`` moved back by (dx, dy), inside the
    part both cover: whether a phase-correlation peak is a real shift or a false one."""
    M = np.float32([[1, 0, -dx], [0, 1, -dy]])
    bb = cv2.warpAffine(b.astype(np.float32), M, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR)
    m = int(np.ceil(max(abs(dx), abs(dy)))) + 1
    if 2 * m >= min(a.shape) - 8:
        return -1.0
    x, y = a[m:-m, m:-m].ravel(), bb[m:-m, m:-m].ravel()
    x, y = x - x.mean(), y - y.mean()
    return float((x @ y) / max(1e-9, np.sqrt((x @ x) * (y @ y))))


def survey(frames: list[Path], out: Path, *extra: str) -> None:
    """Survey into ``out`` in the local frame (kept when a finished one is there: ``--work``)."""
    if (out / "poses.json").is_file():
        return
    shutil.rmtree(out, ignore_errors=True)
    if main(["-q", "survey", *map(str, frames), "--crs", "enu", *extra, "-o", str(out)]) != 0:
        raise SystemExit(f"survey into {out} failed")


def main_(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--markers", type=int, default=8)
    ap.add_argument("--control", type=int, default=5, help="markers held in the adjustment; the rest are checks")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_ortho."))
    try:
        flight = work / "flight"
        if not flight.is_dir():
            simulate_flight(flight, FlightOptions(size=(1152, 864), altitude_m=40.0, seed=a.seed, targets=8,
                                                  gcp=a.markers))
        truth = json.loads((flight / "truth.json").read_text())
        frames = sorted(flight.glob("IMG_*.JPG"))
        base = ["--calib", str(flight / "camera.yaml"), "--gps", str(flight / "geoinfo.txt")]
        survey(frames, work / "gps", *base)
        names = [g["name"] for g in truth["gcps"]["points"]]
        checks = names[a.control:]
        survey(frames, work / "gcp", *base, "--gcp", str(flight / "gcp_list.txt"), "--gcp-check", *checks)
        res = {"gsd_m": truth["gsd_m"],
               "gps_marks_aligned": marks(work / "gps", truth, aligned=True),
               "gcp_check_marks_absolute": marks(work / "gcp", truth, aligned=False, names=set(checks)),
               "gps_seams": seams(work / "gps", truth)}
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)
    for k in ("gps_marks_aligned", "gcp_check_marks_absolute"):
        e = [m["error_gsd"] for m in res[k] if m["found"]]
        print(f"{k}: found {len(e)} of {len(res[k])}; error median {np.median(e):.3f} max {np.max(e):.3f} GSD"
              if e else f"{k}: none found")
    s = [x["shift_gsd"] for x in res["gps_seams"] if x["confirmed"]]
    print(f"seams: {len(s)} tiles confirmed of {len(res['gps_seams'])}; shift median {np.median(s):.3f}, "
          f"p95 {np.percentile(s, 95):.3f}, max {np.max(s):.3f} GSD; unconfirmed peaks "
          f"{sorted(x['shift_gsd'] for x in res['gps_seams'] if not x['confirmed'])}" if s else "seams: no tile")
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main_())
