"""Benchmark: the UAV survey mode (issue 30) against its anchors, in one run.

Run::

    .venv/bin/python benchmarks/bench_survey.py [--flight DIR] [--work /tmp/bench_survey] [--quick]

Every survey runs through :func:`prism3d.reconstruct.survey.run.run_survey` in this process
(the dense pairs here or on a local Dask cluster); its output folders stay under
``--work``. Prints progress lines and tables; writes ``benchmarks/results/bench_survey.json``
(after each section, so a late failure keeps what was measured).

1. **Speed**: the 12-frame 12 MP simulated flight (``simulate_flight`` defaults, or
   ``--flight``) surveyed with its ``camera.yaml`` and ``geoinfo.txt``, default options:
   total and per-stage seconds (``poses.json``), seconds per frame; then the same survey
   with the dense pairs on 1 and on 2 local Dask workers (dense stage and total; 2 vs 1).
2. **Poses vs truth** (``evaluate_survey``: positions in GSD and rotations in deg after
   the similarity alignment). Anchor: OpenCV's two-view pose
   (``tests/reconstruct/two_view_anchor.py``: SIFT, MAGSAC essential matrix, refinement) for every
   neighbouring pair (i, i+1) in flight order, on frames undistorted with the camera's
   K/dist and area-downscaled to at most ``ANCHOR_MAX_SIDE`` px (K scaled); its relative
   rotation (and baseline direction) against the truth's ``T_enu_cam``, beside the same
   pairs' relative rotation from the survey's poses. Seconds per pair (frames read,
   undistorted and downscaled, then the pose) against the survey's pose stage per frame.
3. **Dense anchor**: the same survey with ``SurveyOptions(matcher="sgbm")`` (OpenCV SGBM
   on the very same rectified pairs): DSM median/RMS error on open ground in GSD,
   overlap filled, vehicle heights within 5 %, dense seconds, beside ours.
4. **Targets from the air**: ``--seeds`` flights of ``DET_SIZE`` px at ``DET_ALTITUDE_M``
   (5-10 vehicles each, GSD about 3.9 cm: like the 12 MP case at 1/6 of its pixels, and
   matched at full size where the 12 MP frames are matched at half), surveyed with our
   matcher, searched with ``detect_in_survey`` and the default vehicles (what
   ``prism3d survey-detect`` runs). Pd at 0.1 and 1 false positives per frame per flight
   and pooled over the flights (all candidates ranked by score together; frames summed),
   each target missed at the pooled 0.1 FPPF threshold with the nearest candidate to it
   (why it was missed), and the confusers called. The candidates are walked by the
   library's ``match_map_detections`` (to know which target each hit), beside the library's
   own ``evaluate_survey`` figures (or the error it refuses with); a candidate without a
   ground height (``z_local``) is put on the survey's ground near it, and counted. The
   two 12 MP surveys (ours, SGBM) are searched too, as rows outside the pool.
5. **Real pair** IMG_2188 -> IMG_2189 (``../shared/data/aerial/snowpeak_internal_only``,
   skipped when absent): ``run_survey`` with the ``geoinfo.txt`` table and the EXIF focal
   length, ours and SGBM: reprojection RMS, sparse points, DSM overlap filled, ground
   roughness (``ground_roughness``) in m and in GSD (117 m / 3210 px), the pose baseline
   against the GPS baseline, seconds.

``--quick`` is a smoke run of every section on small frames (results in the work folder,
not in ``benchmarks/results``). Benchmarks print; they never assert.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from prism3d.atr.scene_eval import MapDetection, match_map_detections
from prism3d.atr.survey_detect import detect_in_survey
from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight
from prism3d.datasets.runner import RunOptions, run_survey_pairs
from prism3d.datasets.evaluation.survey_eval import evaluate_survey, ground_roughness, map_targets
from prism3d.datasets.database.resolve import resolve_targets
from prism3d.datasets.jobs.recognisers import aerial_recogniser
from prism3d.errors import InputError
from prism3d.geo import MapFrame
from prism3d.geometry import rotation_angle_deg
from prism3d.reconstruct.survey.run import SurveyOptions, run_survey

HERE = Path(__file__).resolve().parent
REAL_DIR = HERE.parents[1] / "shared" / "data" / "aerial" / "snowpeak_internal_only"
REAL_FRAMES = ("IMG_2188.JPG", "IMG_2189.JPG")
REAL_GSD_M = 117.0 / 3210.0  # ground ~117 m below, f = 3210 px at full size (docs/uav.md)
ANCHOR_MAX_SIDE = 2000      # the two-view anchor's frames: area-downscaled to at most this side
GROUND_WINDOW_M = 3.0       # a candidate without z_local: the ground's median within this of it
DET_SEEDS = (11, 12, 13, 14, 15, 16)
DET_SIZE = (1600, 1200)
DET_ALTITUDE_M = 45.0
WORKERS = (1, 2)
#: The field flights' vehicles (simulate_flight's default scene), searched for in section 4.
FIELD_VEHICLES = ("tank_t1", "tank_t2", "tank_t3", "truck_k1", "truck_k2", "truck_k3")


def _stamp() -> str:
    return time.strftime("%H:%M:%S")


def _load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def _say(msg: str) -> None:
    print(f"{_stamp()} {msg}", flush=True)


def _progress(tag: str) -> Callable[[int, int, str], None]:
    def cb(done: int, total: int, label: str) -> None:
        _say(f"  {tag}: {label} {done}/{total}")
    return cb


def _git() -> dict[str, Any]:
    def run(*a: str) -> str:
        p = subprocess.run(["git", *a], cwd=HERE.parent, capture_output=True, text=True)
        return p.stdout
    import hashlib

    return {"commit": run("rev-parse", "--short", "HEAD").strip(),
            "changed": [ln[3:] for ln in run("status", "--short").splitlines() if not ln.startswith("??")],
            "diff_sha1": hashlib.sha1(run("diff", "HEAD").encode()).hexdigest()[:12]}


def _n(v: float | None, digits: int = 4) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _relative(Ti: np.ndarray, Tj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R``, unit ``t`` with x_j = R x_i + t from two ``T_enu_cam`` (two_view's convention)."""
    R = Tj[:3, :3].T @ Ti[:3, :3]
    t = Tj[:3, :3].T @ (Ti[:3, 3] - Tj[:3, 3])
    return R, t / np.linalg.norm(t)


def _table(head: list[str], rows: list[list[Any]]) -> str:
    def f(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"
        return str(v)
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(f(v) for v in r) + " |" for r in rows]
    return "\n".join(out)


def _frames(flight: Path) -> list[Path]:
    truth = json.loads((flight / "truth.json").read_text())
    return [flight / Path(f["image"]).name for f in truth["frames"]]


def _ensure_flight(folder: Path, options: FlightOptions) -> tuple[Path, float | None]:
    """A simulated flight in ``folder`` (reused when its truth.json is there)."""
    if (folder / "truth.json").is_file():
        _say(f"reusing the flight in {folder}")
        return folder, None
    shutil.rmtree(folder, ignore_errors=True)
    t0 = time.perf_counter()
    _say(f"simulating {folder.name}: {options.frames} frames of {options.size[0]}x{options.size[1]} at "
         f"{options.altitude_m:g} m, seed {options.seed}")
    simulate_flight(folder, options, progress=_progress(f"simulate {folder.name}"))
    return folder, time.perf_counter() - t0


def _survey(frames: list[Path], out: Path, tag: str, *, workers: int = 0, **kw: Any) -> dict[str, Any]:
    """One survey into ``out`` (emptied first): run_survey's summary and its poses.json."""
    shutil.rmtree(out, ignore_errors=True)
    run_pairs = None
    if workers:
        def run_pairs(reqs: list, progress: Any) -> list:
            return run_survey_pairs(reqs, RunOptions(workers=workers, retries=0), progress)
    _say(f"survey {tag} -> {out} (load {_load()})")
    t0 = time.perf_counter()
    s = run_survey(frames, out, progress=_progress(tag), run_pairs=run_pairs, **kw)
    wall = time.perf_counter() - t0
    doc = json.loads((out / "poses.json").read_text())
    sec = doc["seconds"]
    _say(f"survey {tag}: {s['n_registered']}/{s['n_frames']} placed, {s['pairs_ok']} pairs ok, "
         f"{s['pairs_skipped']} skipped; " + ", ".join(f"{k} {v:.1f} s" for k, v in sec.items()))
    return {"summary": s, "poses": doc, "seconds": sec, "wall_s": round(wall, 2), "out_dir": str(out)}


# --- 1. speed --------------------------------------------------------------------------------
def speed(flight: Path, work: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    frames = _frames(flight)
    kw = {"calib": flight / "camera.yaml", "gps_table": flight / "geoinfo.txt"}
    load0 = _load()
    ours = _survey(frames, work / "survey_ours", "ours in-process", **kw)
    runs = {"in_process": ours}
    for w in WORKERS:
        runs[f"dask_{w}"] = _survey(frames, work / f"survey_dask{w}", f"ours dask {w}", workers=w, **kw)
    n = len(frames)
    rows, out = [], {"n_frames": n, "frame_size": ours["poses"]["camera"]["size"], "load_before": load0,
                     "load_after": _load(), "runs": {}}
    for name, r in runs.items():
        sec = r["seconds"]
        out["runs"][name] = {"seconds": sec, "wall_s": r["wall_s"], "s_per_frame": round(sec["total"] / n, 2),
                             "pairs_ok": r["summary"]["pairs_ok"], "pairs_skipped": r["summary"]["pairs_skipped"],
                             "dsm_cells": r["summary"]["dsm_cells"],
                             "overlap_filled_fraction": r["summary"]["overlap_filled_fraction"]}
        rows.append([name, sec["poses"], sec["dense"], sec["fusion"], sec["products"], sec["total"],
                     sec["total"] / n, r["summary"]["pairs_ok"]])
    d1, d2 = runs["dask_1"]["seconds"], runs["dask_2"]["seconds"]
    out["dask_2_vs_1"] = {"dense_speedup": round(d1["dense"] / d2["dense"], 3),
                          "total_speedup": round(d1["total"] / d2["total"], 3)}
    print(f"\n1. Speed, {n} frames of {out['frame_size'][0]}x{out['frame_size'][1]} "
          f"(load {load0} -> {out['load_after']})")
    print(_table(["run", "poses s", "dense s", "fusion s", "products s", "total s", "s/frame", "pairs ok"], rows))
    print(f"2 Dask workers vs 1: dense {out['dask_2_vs_1']['dense_speedup']:.2f}x, "
          f"total {out['dask_2_vs_1']['total_speedup']:.2f}x faster\n", flush=True)
    return out, ours


# --- 2. poses and the two-view anchor --------------------------------------------------------
def poses(flight: Path, ours: dict[str, Any], ev: dict[str, Any]) -> dict[str, Any]:
    import cv2

    from prism3d.capture.calib_formats import load_camera_calibration
    from prism3d.io.images import read_image
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the anchor lives with the tests
    from tests.reconstruct.two_view_anchor import relative_pose

    truth = json.loads((flight / "truth.json").read_text())
    T_true = [np.asarray(f["T_enu_cam"], dtype=np.float64) for f in truth["frames"]]
    by_name = {Path(f["image"]).name: f["T_enu_cam"] for f in ours["poses"]["frames"]}
    T_est = [None if by_name.get(Path(f["image"]).name) is None else np.asarray(by_name[Path(f["image"]).name])
             for f in truth["frames"]]
    cam = load_camera_calibration(flight / "camera.yaml")
    K, dist = np.asarray(cam.K, dtype=np.float64), np.asarray(cam.dist, dtype=np.float64)
    factor = max(1, math.ceil(max(cam.size) / ANCHOR_MAX_SIDE))
    Ks = K.copy()
    if factor > 1:
        Ks[:2] /= factor
        Ks[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
        Ks[1, 2] = (K[1, 2] + 0.5) / factor - 0.5

    def frame(k: int) -> np.ndarray:
        img = cv2.undistort(read_image(flight / Path(truth["frames"][k]["image"]).name), K, dist)
        if factor > 1:
            h, w = img.shape[:2]
            img = cv2.resize(img, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
        return img

    load0 = _load()
    pairs = []
    for i in range(len(T_true) - 1):
        j = i + 1
        R_t, t_t = _relative(T_true[i], T_true[j])
        rec: dict[str, Any] = {"i": i, "j": j, "true_rotation_deg": round(rotation_angle_deg(R_t), 3),
                               "same_line": truth["frames"][i]["line"] == truth["frames"][j]["line"]}
        t0 = time.perf_counter()
        a, b = frame(i), frame(j)
        t1 = time.perf_counter()
        try:
            p = relative_pose(a, b, Ks)
            rec.update(anchor_rotation_error_deg=rotation_angle_deg(p.R.T @ R_t),
                       anchor_direction_error_deg=_angle_deg(p.t, t_t), anchor_inliers=p.n_inliers,
                       anchor_failed=None)
        except InputError as exc:
            rec.update(anchor_rotation_error_deg=None, anchor_direction_error_deg=None, anchor_inliers=0,
                       anchor_failed=str(exc))
        t2 = time.perf_counter()
        rec.update(anchor_s=round(t2 - t0, 2), anchor_pose_s=round(t2 - t1, 2))
        if T_est[i] is not None and T_est[j] is not None:
            R_e, t_e = _relative(T_est[i], T_est[j])
            rec.update(survey_rotation_error_deg=rotation_angle_deg(R_e.T @ R_t),
                       survey_direction_error_deg=_angle_deg(t_e, t_t))
        else:
            rec.update(survey_rotation_error_deg=None, survey_direction_error_deg=None)
        pairs.append(rec)
        _say(f"  anchor pair {i}-{j}: true turn {rec['true_rotation_deg']:.2f} deg; rotation error anchor "
             f"{_n(rec['anchor_rotation_error_deg']) if rec['anchor_failed'] is None else rec['anchor_failed']}, "
             f"survey {_n(rec['survey_rotation_error_deg'])} deg; {rec['anchor_s']:.1f} s")

    def stats(key: str) -> dict[str, Any]:
        v = np.array([p[key] for p in pairs if p[key] is not None])
        return {"n": int(len(v)), "median": float(np.median(v)) if len(v) else None,
                "max": float(v.max()) if len(v) else None}

    n = len(T_true)
    out = {"evaluate": {k: ev[k] for k in ("frames_placed", "frames", "gsd_m", "position_error_gsd",
                                          "rotation_error_deg", "absolute_placement_m")},
           "anchor_downscale": factor, "pairs": pairs, "load_before": load0, "load_after": _load(),
           "anchor_rotation_error_deg": stats("anchor_rotation_error_deg"),
           "survey_rotation_error_deg": stats("survey_rotation_error_deg"),
           "anchor_direction_error_deg": stats("anchor_direction_error_deg"),
           "survey_direction_error_deg": stats("survey_direction_error_deg"),
           "anchor_s_per_pair": float(np.median([p["anchor_s"] for p in pairs])),
           "anchor_pose_s_per_pair": float(np.median([p["anchor_pose_s"] for p in pairs])),
           "survey_pose_s_per_frame": round(ours["seconds"]["poses"] / n, 2)}
    e = out["evaluate"]
    print(f"\n2. Poses vs truth ({e['frames_placed']}/{e['frames']} placed, GSD {100 * e['gsd_m']:.2f} cm): "
          f"positions max {e['position_error_gsd']['max']:.2f} / RMS {e['position_error_gsd']['rms']:.2f} GSD, "
          f"rotations max {e['rotation_error_deg']['max']:.4f} / RMS {e['rotation_error_deg']['rms']:.4f} deg; "
          f"absolute placement max {e['absolute_placement_m']['max']:.2f} m")
    print(_table(["pair", "same line", "true turn deg", "anchor rot err deg", "survey rot err deg",
                  "anchor dir err deg", "survey dir err deg", "anchor inliers", "anchor s"],
                 [[f"{p['i']}-{p['j']}", p["same_line"], p["true_rotation_deg"], p["anchor_rotation_error_deg"],
                   p["survey_rotation_error_deg"], p["anchor_direction_error_deg"], p["survey_direction_error_deg"],
                   p["anchor_inliers"], p["anchor_s"]] for p in pairs]))
    a, s = out["anchor_rotation_error_deg"], out["survey_rotation_error_deg"]
    print(f"relative rotation error, median / max: anchor {_n(a['median'])} / {_n(a['max'])} deg "
          f"({a['n']} pairs), survey {_n(s['median'])} / {_n(s['max'])} deg ({s['n']} pairs); anchor "
          f"{out['anchor_s_per_pair']:.2f} s per pair ({out['anchor_pose_s_per_pair']:.2f} s the pose alone, "
          f"frames 1/{factor}), survey's pose stage {out['survey_pose_s_per_frame']:.2f} s per frame\n",
          flush=True)
    return out


# --- 3. dense anchor ------------------------------------------------------------------------
def _dense_row(ev: dict[str, Any], run: dict[str, Any]) -> dict[str, Any]:
    d, v = ev["dsm"], ev["vehicles"]
    return {"dsm_median_abs_error_gsd": d["median_abs_error_gsd"], "dsm_rms_error_gsd": d["rms_error_gsd"],
            "dsm_bias_m": d["bias_m"], "scored_cells": d["scored_cells"],
            "overlap_filled_fraction": d["overlap_filled_fraction"],
            "poses_json_overlap_filled_fraction": run["poses"]["dsm"]["overlap_filled_fraction"],
            "vehicles_n": v["n"], "vehicles_measured": v["measured"],
            "vehicles_within_5_percent": v["within_5_percent"],
            "vehicles_max_relative_error": v["max_relative_height_error"],
            "vehicles_each": [{k: x.get(k) for k in ("name", "true_height_m", "ndsm_height_m", "relative_error")}
                              for x in v["each"]],
            "dense_s": run["seconds"]["dense"], "total_s": run["seconds"]["total"],
            "cell_m": run["poses"]["dsm"]["cell"]}


def dense_anchor(flight: Path, work: Path, ours: dict[str, Any], ev_ours: dict[str, Any]
                 ) -> tuple[dict[str, Any], dict[str, Any]]:
    load0 = _load()
    sg = _survey(_frames(flight), work / "survey_sgbm", "sgbm in-process", calib=flight / "camera.yaml",
                 gps_table=flight / "geoinfo.txt", options=SurveyOptions(matcher="sgbm"))
    _say("evaluating the SGBM survey")
    ev_sg = evaluate_survey(sg["out_dir"], flight)
    out = {"ours": _dense_row(ev_ours, ours), "sgbm": _dense_row(ev_sg, sg), "load_before": load0,
           "load_after": _load()}
    print(f"\n3. Dense: ours vs OpenCV SGBM on the same rectified pairs (load {load0} -> {out['load_after']})")
    rows = []
    for name, r in (("ours", out["ours"]), ("SGBM", out["sgbm"])):
        rows.append([name, r["dsm_median_abs_error_gsd"], r["dsm_rms_error_gsd"], r["dsm_bias_m"],
                     r["overlap_filled_fraction"], f"{r['vehicles_within_5_percent']}/{r['vehicles_measured']} "
                     f"(of {r['vehicles_n']})", r["vehicles_max_relative_error"], r["dense_s"], r["total_s"]])
    print(_table(["matcher", "DSM median |e| GSD", "DSM RMS GSD", "bias m", "overlap filled",
                  "vehicles within 5 %", "worst vehicle rel. err", "dense s", "total s"], rows))
    o, g = out["ours"], out["sgbm"]
    out["ratios_ours_over_sgbm"] = {
        "dsm_median_abs_error": o["dsm_median_abs_error_gsd"] / g["dsm_median_abs_error_gsd"],
        "dsm_rms_error": o["dsm_rms_error_gsd"] / g["dsm_rms_error_gsd"], "dense_s": o["dense_s"] / g["dense_s"]}
    r = out["ratios_ours_over_sgbm"]
    print(f"ratios ours / SGBM: median error {r['dsm_median_abs_error']:.2f}, RMS {r['dsm_rms_error']:.2f}, "
          f"dense seconds {r['dense_s']:.2f}\n", flush=True)
    return out, sg


# --- 4. targets from the air ----------------------------------------------------------------
def _detect(survey_dir: Path, out: Path) -> dict[str, Any]:
    """``survey-detect`` of the field flights' vehicles: the aerial recogniser of their
    built-in targets (trained once, then cached like any target list)."""
    model, _ = aerial_recogniser(resolve_targets(list(FIELD_VEHICLES), scale="full"))
    return detect_in_survey(survey_dir, out, model)


def _ground_z(ground: np.ndarray, meta: dict, x: float, y: float) -> float:
    """The survey's ground height near (x, y): the median of ``ground.tif`` within
    ``GROUND_WINDOW_M`` (a vehicle's centre cell can be a hole), else of all of it."""
    cell = float(meta["gsd"])
    r, c, k = int((meta["north"] - y) / cell), int((x - meta["west"]) / cell), int(GROUND_WINDOW_M / cell)
    w = ground[max(r - k, 0):r + k + 1, max(c - k, 0):c + k + 1]
    return float(np.nanmedian(w)) if np.isfinite(w).any() else float(np.nanmedian(ground))


def _matched(survey_dir: Path, flight: Path, geojson: Path) -> tuple[list[dict], list[dict], int, int]:
    """The candidates in the truth's frame, each marked tp / fp / ignored (near a confuser)
    and the target it hit, walked best first by the rules of ``match_map_detections``; the
    targets with the candidate nearest to each; the number of frames; how many candidates
    came without a ground height (``z_local``) and were put on ``_ground_z``. A candidate is
    a point on the ground: put at height 0 (the ellipsoid, ~150 m below), the alignment's
    rotation (0.4-1.6 deg from the GPS noise) would move it metres sideways."""
    from prism3d.datasets.evaluation.survey_eval import _pose_scores  # the scorer's own alignment
    from prism3d.io.geo import read_geotiff

    poses_doc = json.loads((survey_dir / "poses.json").read_text())
    truth = json.loads((flight / "truth.json").read_text())
    _, fr = _pose_scores(poses_doc, truth)
    ground, gmeta = read_geotiff(survey_dir / "ground.tif")
    feats = json.loads(geojson.read_text())["features"]
    frame = MapFrame.from_record(poses_doc)
    dets, filled = [], 0
    for f in feats:
        p = f["properties"]
        z = p.get("z_local")
        if z is None:  # the ground's map height there, as an ENU up
            q = frame.enu_to_map([[p["x_local"], p["y_local"], 0.0]])[0]
            z = float(frame.map_to_enu([[q[0], q[1], _ground_z(ground, gmeta, q[0], q[1])]])[0, 2])
            filled += 1
        q = fr.to_truth(np.array([[p["x_local"], p["y_local"], z]]))[0]
        dets.append({**{k: p.get(k) for k in ("score", "class", "template", "length_m", "width_m", "height_m")},
                     "x": float(q[0]), "y": float(q[1]), "z_local_given": p.get("z_local") is not None})
    tg = truth["targets"]
    counted = np.array([not t["confuser"] for t in tg], bool)
    radius = np.array([max(0.5 * t["length_m"], 2.0) for t in tg])
    # walked by the library's own scorer, so the kinds are the figures' kinds
    for d in dets:
        d["kind"], d["target"] = None, None
    points = [MapDetection(d["x"], d["y"], float(d["score"]), d["class"]) for d in dets]
    for m in match_map_detections(points, map_targets(truth)):
        dets[m.index]["kind"], dets[m.index]["target"] = ("tp" if m.kind == "hit" else m.kind), m.target
    targets = []
    for k, t in enumerate(tg):
        dist = np.array([math.hypot(d["x"] - t["xyz_enu"][0], d["y"] - t["xyz_enu"][1]) for d in dets])
        near = int(np.argmin(dist)) if len(dist) else None
        vis = [float(v) for v in t.get("visible_fraction", {}).values()]
        targets.append({"k": k, "name": t["name"], "class": t["class"], "counted": bool(counted[k]),
                        "length_m": t["length_m"], "width_m": t["width_m"], "height_m": t["height_m"],
                        "frames_fully_visible": len(t.get("frames", [])),
                        "max_visible_fraction": max(vis) if vis else None,
                        "radius_m": float(radius[k]),
                        "nearest": None if near is None else {**{x: dets[near][x] for x in
                                                                 ("score", "class", "length_m", "width_m", "height_m")},
                                                              "distance_m": round(float(dist[near]), 2),
                                                              "kind": dets[near]["kind"]}})
    return dets, targets, len(truth["frames"]), filled


def _confuser_hit(d: dict[str, Any]) -> bool:
    return d["kind"] == "ignored" and d["target"] is not None


def _pooled(flights: list[dict[str, Any]], fppf: float, *, confusers_fp: bool = False) -> dict[str, Any]:
    """Pd at ``fppf`` with every flight's candidates ranked together: the longest prefix
    with at most ``fppf`` x frames false positives, and its score threshold.
    ``confusers_fp``: a confuser called a vehicle counts as a false positive (the
    scorer counts it as neither a hit nor a false positive)."""
    events = sorted(((d["score"], "fp" if confusers_fp and _confuser_hit(d) else d["kind"])
                     for f in flights for d in f["dets"] if d["kind"]), key=lambda e: -e[0])
    n_frames = sum(f["n_frames"] for f in flights)
    n_targets = sum(sum(t["counted"] for t in f["targets"]) for f in flights)
    tp = fp = 0
    best_tp, thr = 0, math.inf
    for s, kind in events:
        if kind == "fp" and (fp + 1) / n_frames > fppf:
            break
        tp += kind == "tp"
        fp += kind == "fp"
        best_tp, thr = tp, s
    return {"pd": best_tp / max(n_targets, 1), "hits": best_tp, "n_targets": n_targets, "false_positives": fp,
            "n_frames": n_frames, "fppf": fp / n_frames, "score_threshold": thr}


def _why(t: dict[str, Any], thr: float, veh: dict[str, Any] | None) -> str:
    vis = (f"fully visible in {t['frames_fully_visible']} frames" if t["frames_fully_visible"]
           else f"never fully visible (best {t['max_visible_fraction']})")
    h = "" if veh is None or veh.get("ndsm_height_m") is None else \
        f"; nDSM height {veh['ndsm_height_m']:.2f} m of {t['height_m']:.2f}"
    n = t["nearest"]
    if n is None or n["distance_m"] > t["radius_m"]:
        d = "no candidate" if n is None else f"nearest candidate {n['distance_m']:.1f} m away"
        return f"{vis}; {d} (within {t['radius_m']:.1f} m needed){h}"
    size = f"{n['length_m']:.1f}x{n['width_m']:.1f}x{n['height_m']:.1f} m vs true " \
           f"{t['length_m']:.1f}x{t['width_m']:.1f}x{t['height_m']:.1f}"
    if n["score"] <= -1:
        return f"{vis}; candidate {n['distance_m']:.1f} m off fits no class's size ({size}){h}"
    if n["score"] < thr:
        return f"{vis}; candidate scored {n['score']:.3f} < threshold {thr:.3f} as {n['class']} ({size}){h}"
    return f"{vis}; candidate {n['score']:.3f} taken by another target first ({n['kind']}){h}"


def _target_flight(work: Path, seed: int, size: tuple[int, int], altitude: float) -> dict[str, Any]:
    """One target flight simulated (or reused), surveyed with our matcher, searched and scored."""
    fd, sim_s = _ensure_flight(work / f"det_flight_{seed}",
                               FlightOptions(size=size, altitude_m=altitude, seed=seed))
    sd = work / f"det_survey_{seed}"
    run = _survey(_frames(fd), sd, f"det seed {seed}", calib=fd / "camera.yaml", gps_table=fd / "geoinfo.txt")
    gj = work / f"det_survey_{seed}.geojson"
    t0 = time.perf_counter()
    det = _detect(sd, gj)
    det_s = time.perf_counter() - t0
    ev = evaluate_survey(sd, fd)
    f = {"seed": seed, "instances": [t["instance"] for t in json.loads((fd / "truth.json").read_text())["targets"]],
         "ev": ev, "run": run, "detect_s": det_s, "simulate_s": sim_s, "n_candidates": det["n_detections"],
         "n_scored": det["n_scored"], **_scored(sd, fd, gj)}
    own, lib = f["own"], f["library"]
    _say(f"  seed {seed}: {own['n_targets']} vehicles, Pd {own['pd_at_0.1_fppf']:.2f} @0.1 / "
         f"{own['pd_at_1_fppf']:.2f} @1 FPPF ({f['z_filled']} candidates without z_local); library scorer: "
         f"{lib.get('error') or (lib['pd_at_0.1_fppf'], lib['pd_at_1_fppf'])}; {det['n_scored']} scored "
         f"candidates; detect {det_s:.1f} s")
    return f


def _scored(sd: Path, fd: Path, gj: Path) -> dict[str, Any]:
    """A survey's candidates scored here (``_matched``, Pd at 0.1 and 1 FPPF) and by the
    library's ``evaluate_survey`` (its figures, or the error it refuses with)."""
    dets, tg, n_frames, filled = _matched(sd, fd, gj)
    one = [{"dets": dets, "targets": tg, "n_frames": n_frames}]
    p01, p1 = _pooled(one, 0.1), _pooled(one, 1.0)
    own = {"n_targets": p01["n_targets"], "pd_at_0.1_fppf": p01["pd"], "pd_at_1_fppf": p1["pd"]}
    try:
        d = evaluate_survey(sd, fd, detections=gj)["detection"]
        lib = {k: d[k] for k in ("n_targets", "pd_at_0.1_fppf", "pd_at_1_fppf")}
    except InputError as exc:
        lib = {"error": str(exc)}
    return {"dets": dets, "targets": tg, "n_frames": n_frames, "z_filled": filled, "own": own, "library": lib}


def _scores(items: list[dict[str, Any]]) -> str:
    return ", ".join(f"{x['score']:.2f}" for x in items)


def _confusers_called(f: dict[str, Any]) -> list[dict[str, Any]]:
    return [{"name": f["targets"][x["target"]]["name"], "score": x["score"], "called": x["class"]}
            for x in f["dets"] if _confuser_hit(x)]


def _flight_row(f: dict[str, Any], thr01: float) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A target flight's row and its targets missed at the pooled 0.1 FPPF threshold."""
    d, ev = f["own"], f["ev"]
    veh = {v["instance"]: v for v in ev["vehicles"]["each"]}
    taken = [x for x in f["dets"] if x["kind"] == "tp" and x["score"] >= thr01]
    hit01 = {x["target"] for x in taken}
    row = {"seed": f["seed"], "vehicles": d["n_targets"], "confusers": sum(not t["counted"] for t in f["targets"]),
           "pd_at_0.1_fppf": d["pd_at_0.1_fppf"], "pd_at_1_fppf": d["pd_at_1_fppf"], "library_scorer": f["library"],
           "candidates_without_z_local": f["z_filled"], "hits_at_pooled_0.1": len(hit01),
           "fp_at_pooled_0.1": sum(x["kind"] == "fp" and x["score"] >= thr01 for x in f["dets"]),
           "id_correct_at_pooled_0.1": sum(x["class"] == f["targets"][x["target"]]["class"] for x in taken),
           "scored_candidates": f["n_scored"], "candidates": f["n_candidates"],
           "false_candidates_scored": sum(x["kind"] == "fp" for x in f["dets"]),
           "confusers_called": _confusers_called(f),
           "detect_s": round(f["detect_s"], 2), "survey_s": f["run"]["seconds"]["total"],
           "cell_m": f["run"]["poses"]["dsm"]["cell"],
           "dsm_median_abs_error_gsd": ev["dsm"]["median_abs_error_gsd"],
           "vehicles_within_5_percent": ev["vehicles"]["within_5_percent"],
           "position_error_gsd_max": ev["position_error_gsd"]["max"]}
    missed = []
    for t in f["targets"]:
        if t["counted"] and t["k"] not in hit01:
            v = veh.get(f["instances"][t["k"]])
            missed.append({"seed": f["seed"], "name": t["name"], **{k: t[k] for k in (
                "frames_fully_visible", "max_visible_fraction", "length_m", "width_m", "height_m", "nearest")},
                "ndsm_height_m": None if v is None else v.get("ndsm_height_m"), "why": _why(t, thr01, v)})
    return row, missed


def _lib(d: dict[str, Any]) -> str:
    return "refused" if "error" in d else f"{d['pd_at_0.1_fppf']:.3g} / {d['pd_at_1_fppf']:.3g}"


def targets(work: Path, seeds: tuple[int, ...], size: tuple[int, int], altitude: float,
            extra: list[tuple[str, Path, Path]]) -> dict[str, Any]:
    load0 = _load()
    flights, refused = [], []
    for seed in seeds:
        try:
            flights.append(_target_flight(work, seed, size, altitude))
        except InputError as exc:  # a flight the simulator or the survey refuses is reported, not scored
            _say(f"  seed {seed} REFUSED: {exc}")
            refused.append({"seed": seed, "error": str(exc)})
    pooled = {x: _pooled(flights, x) for x in (0.1, 1.0)}
    pooled_conf = {x: _pooled(flights, x, confusers_fp=True) for x in (0.1, 1.0)}
    thr01 = pooled[0.1]["score_threshold"]
    per_flight, missed = [], []
    for f in flights:
        row, miss = _flight_row(f, thr01)
        per_flight.append(row)
        missed += miss
    extras = []
    for label, sd, fd in extra:
        gj = work / f"{sd.name}.geojson"
        _detect(sd, gj)
        sc = _scored(sd, fd, gj)
        extras.append({"run": label, "vehicles": sc["own"]["n_targets"], "pd_at_0.1_fppf": sc["own"]["pd_at_0.1_fppf"],
                       "pd_at_1_fppf": sc["own"]["pd_at_1_fppf"], "library_scorer": sc["library"],
                       "candidates_without_z_local": sc["z_filled"],
                       "scored_candidates": sum(x["score"] > -1 for x in sc["dets"]),
                       "false_candidates_scored": sum(x["kind"] == "fp" for x in sc["dets"]),
                       "confusers": sum(not t["counted"] for t in sc["targets"]),
                       "confusers_called": _confusers_called(sc),
                       "pd_at_0.1_fppf_confusers_as_fp": _pooled([sc], 0.1, confusers_fp=True)["pd"],
                       "cell_m": json.loads((sd / "poses.json").read_text())["dsm"]["cell"]})
    n_frames = pooled[0.1]["n_frames"]
    id_hits = sum(p["id_correct_at_pooled_0.1"] for p in per_flight)
    out = {"flight_size": list(size), "altitude_m": altitude, "seeds": list(seeds), "refused": refused,
           "gsd_m": flights[0]["ev"]["gsd_m"] if flights else None,
           "pooled": {str(k): v for k, v in pooled.items()}, "id_correct_among_hits_at_0.1": id_hits,
           "pooled_confusers_as_fp": {str(k): v for k, v in pooled_conf.items()},
           "per_flight": per_flight, "missed_at_pooled_0.1": missed,
           "false_candidates_per_frame": sum(p["false_candidates_scored"] for p in per_flight) / max(n_frames, 1),
           "simulate_s": [f["simulate_s"] for f in flights if f["simulate_s"] is not None],
           "extra_12mp": extras, "load_before": load0, "load_after": _load()}
    p1, p10 = pooled[0.1], pooled[1.0]
    print(f"\n4. Targets from the air: {len(flights)} flight(s) of {size[0]}x{size[1]} at {altitude:g} m "
          f"(GSD {100 * (out['gsd_m'] or 0):.2f} cm), {p1['n_targets']} vehicles, {n_frames} frames "
          f"(load {load0} -> {out['load_after']})")
    print(f"pooled Pd @0.1 FPPF {p1['pd']:.3f} ({p1['hits']}/{p1['n_targets']}, {p1['false_positives']} FP = "
          f"{p1['fppf']:.3f} per frame, score >= {p1['score_threshold']:.3f}; class right {id_hits}/{p1['hits']}); "
          f"@1 FPPF {p10['pd']:.3f} ({p10['hits']}/{p10['n_targets']}, {p10['false_positives']} FP, "
          f"score >= {p10['score_threshold']:.3f}); false candidates with a score: "
          f"{out['false_candidates_per_frame']:.2f} per frame")
    called = [c for p in per_flight for c in p["confusers_called"]]
    n_conf = sum(p["confusers"] for p in per_flight)
    print(f"confusers called vehicles: {len(called)} of {n_conf}"
          + (f" (scores {min(c['score'] for c in called):.3f}-{max(c['score'] for c in called):.3f})" if called else "")
          + f"; counted as false positives: Pd @0.1 FPPF {pooled_conf[0.1]['pd']:.3f} "
          f"({pooled_conf[0.1]['false_positives']} FP), @1 FPPF {pooled_conf[1.0]['pd']:.3f}")
    print(_table(["seed", "vehicles", "confusers", "Pd @0.1", "Pd @1", "library scorer @0.1 / @1",
                  "no z_local", "hits / FP at pooled 0.1 thr.", "scored cand.", "false cand.", "confusers called",
                  "DSM med GSD",
                  "veh. within 5 %", "cell m", "survey s", "detect s"],
                 [[p["seed"], p["vehicles"], p["confusers"], p["pd_at_0.1_fppf"], p["pd_at_1_fppf"],
                   _lib(p["library_scorer"]), p["candidates_without_z_local"],
                   f"{p['hits_at_pooled_0.1']} / {p['fp_at_pooled_0.1']}", p["scored_candidates"],
                   p["false_candidates_scored"], len(p["confusers_called"]), p["dsm_median_abs_error_gsd"],
                   p["vehicles_within_5_percent"],
                   p["cell_m"], p["survey_s"], p["detect_s"]] for p in per_flight]))
    if extras:
        print(_table(["12 MP survey", "vehicles", "Pd @0.1", "Pd @1", "library scorer @0.1 / @1", "no z_local",
                      "scored cand.", "false cand.", "confusers called (scores)", "Pd @0.1, confusers as FP",
                      "cell m"],
                     [[e["run"], e["vehicles"], e["pd_at_0.1_fppf"], e["pd_at_1_fppf"], _lib(e["library_scorer"]),
                       e["candidates_without_z_local"], e["scored_candidates"], e["false_candidates_scored"],
                       f"{len(e['confusers_called'])} of {e['confusers']} ({_scores(e['confusers_called'])})",
                       e["pd_at_0.1_fppf_confusers_as_fp"], e["cell_m"]] for e in extras]))
    errors = sorted({x["library_scorer"]["error"] for x in per_flight + extras if "error" in x["library_scorer"]})
    for err in errors:
        print(f"library scorer refused: {err}")
    print("missed at the pooled 0.1 FPPF threshold:")
    for m in missed:
        print(f"  seed {m['seed']} {m['name']}: {m['why']}")
    print(flush=True)
    return out


# --- 5. the real pair -----------------------------------------------------------------------
def real_pair(work: Path) -> dict[str, Any] | None:
    from prism3d.io.geo import read_geotiff

    if not all((REAL_DIR / n).is_file() for n in (*REAL_FRAMES, "geoinfo.txt")):
        _say(f"real pair skipped: {REAL_DIR} is absent")
        return None
    load0 = _load()
    out: dict[str, Any] = {"frames": list(REAL_FRAMES), "gsd_m": REAL_GSD_M}
    for matcher in ("ours", "sgbm"):
        r = _survey([REAL_DIR / n for n in REAL_FRAMES], work / f"real_{matcher}", f"real {matcher}",
                    gps_table=REAL_DIR / "geoinfo.txt", options=SurveyOptions(matcher=matcher))
        doc = r["poses"]
        dsm, meta = read_geotiff(Path(r["out_dir"]) / "dsm.tif")
        ndsm, _ = read_geotiff(Path(r["out_dir"]) / "ndsm.tif")
        rough = ground_roughness(dsm, ndsm, float(meta["gsd"]))
        fr = doc["frames"]
        C = [np.asarray(f["T_enu_cam"])[:3, 3] for f in fr]
        G = [np.asarray(f["gps_enu"]) for f in fr]
        out[matcher] = {"reprojection_rms_px": doc["reprojection_rms_px"], "sparse_points": doc["n_sparse_points"],
                        "observations": doc["n_observations"],
                        "overlap_filled_fraction": doc["dsm"]["overlap_filled_fraction"],
                        "dsm_cells": doc["dsm"]["filled_cells"], "cell_m": doc["dsm"]["cell"], "roughness": rough,
                        "roughness_median_gsd": None if rough["median_rms_m"] is None
                        else rough["median_rms_m"] / REAL_GSD_M,
                        "pose_baseline_m": float(np.linalg.norm(C[1] - C[0])),
                        "gps_baseline_m": float(np.linalg.norm(G[1] - G[0])),
                        "georeference": doc["georeference"], "camera_f_px": doc["camera"]["K"][0][0],
                        "camera_start": doc["camera"]["start"], "seconds": r["seconds"],
                        "pairs": [{k: p.get(k) for k in ("i", "j", "status", "reason", "valid_fraction", "n_points")}
                                  for p in doc["dense"]["pairs"]]}
    out["load_before"], out["load_after"] = load0, _load()
    print(f"\n5. Real pair {REAL_FRAMES[0]} -> {REAL_FRAMES[1]} (EXIF focal, geoinfo.txt; "
          f"load {load0} -> {out['load_after']})")
    rows = []
    for m in ("ours", "sgbm"):
        r = out[m]
        rows.append([m, r["reprojection_rms_px"], r["sparse_points"], r["overlap_filled_fraction"], r["cell_m"],
                     r["roughness"]["median_rms_m"], r["roughness_median_gsd"], r["roughness"]["patches"],
                     f"{r['pose_baseline_m']:.3f} / {r['gps_baseline_m']:.3f}", r["seconds"]["dense"],
                     r["seconds"]["total"]])
    print(_table(["matcher", "reproj. RMS px", "sparse points", "overlap filled", "cell m", "roughness median m",
                  "roughness GSD", "patches", "baseline pose / GPS m", "dense s", "total s"], rows))
    print(flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--flight", type=Path, help="an existing 12 MP simulated flight (default: simulate one in --work)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_survey"))
    ap.add_argument("--quick", action="store_true", help="smoke run on small frames (results in the work folder)")
    ap.add_argument("--seeds", type=int, nargs="+",
                    help=f"target flights' seeds (default {DET_SEEDS[0]}-{DET_SEEDS[-1]})")
    ap.add_argument("--out", type=Path, help="results JSON (default benchmarks/results/bench_survey.json; "
                    "--quick: WORK/bench_survey_quick.json)")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    out_path = a.out or (a.work / "bench_survey_quick.json" if a.quick else HERE / "results" / "bench_survey.json")
    if a.quick:
        main_opts = FlightOptions(size=(1200, 900))
        seeds, det_size, det_alt = tuple(a.seeds or DET_SEEDS[:1]), (800, 600), DET_ALTITUDE_M
    else:
        main_opts = FlightOptions()
        seeds, det_size, det_alt = tuple(a.seeds or DET_SEEDS), DET_SIZE, DET_ALTITUDE_M
    res: dict[str, Any] = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "quick": a.quick,
                           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                                       "python": platform.python_version()},
                           "git": _git(), "load_at_start": _load()}

    def save() -> None:
        res["finished"] = time.strftime("%Y-%m-%d %H:%M:%S")
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(res, indent=1, default=float))

    _say(f"bench_survey: work {a.work}, results -> {out_path}, load {res['load_at_start']}")
    if a.flight is not None:
        flight, sim_s = a.flight, None
        _say(f"using the flight in {flight}")
    else:
        flight, sim_s = _ensure_flight(a.work / ("flight_quick" if a.quick else "flight12"), main_opts)
    res["flight"] = {"dir": str(flight), "simulate_s": sim_s,
                     "options": json.loads((flight / "truth.json").read_text())["options"]}
    res["speed"], ours = speed(flight, a.work)
    save()
    _say("evaluating our survey against the truth")
    ev_ours = evaluate_survey(ours["out_dir"], flight)
    res["poses"] = poses(flight, ours, ev_ours)
    save()
    res["dense"], sg = dense_anchor(flight, a.work, ours, ev_ours)
    save()
    res["targets"] = targets(a.work, seeds, det_size, det_alt,
                             [("ours", Path(ours["out_dir"]), flight), ("sgbm", Path(sg["out_dir"]), flight)])
    save()
    res["real_pair"] = real_pair(a.work)
    res["load_at_end"] = _load()
    res["git_at_end"] = _git()  # the tree is shared: a change during the run shows here
    save()
    _say(f"done; wrote {out_path}")


if __name__ == "__main__":
    main()
