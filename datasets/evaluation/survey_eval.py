"""A survey scored against the exact truth of a simulated flight (``prism3d simulate
flight``): the issue's checks as numbers (docs/uav.md).

The survey's frame (GPS-fixed ENU at its first frame) and the truth's (ENU at the
flight's origin) are related through WGS84 exactly; the GPS noise then leaves a small
similarity between them, so shape is scored after the similarity that best maps the
estimated camera centres onto the true ones (as the issue asks), and the GPS-limited
absolute placement is reported beside it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import laspy
import numpy as np
from numpy.typing import NDArray

from prism3d.atr.scene_eval import MapDetection, MapTarget, score_detections
from prism3d.errors import InputError
from prism3d.geo import MapFrame, enu_to_wgs84, wgs84_to_enu
from prism3d.geometry import rotation_angle_deg
from prism3d.io.geo import read_geotiff
from prism3d.reconstruct.survey.model import METRIC_SCALES
from prism3d.reconstruct.survey.sfm import similarity_align

__all__ = ["evaluate_survey", "ground_roughness", "map_targets"]

#: Open ground for the DSM score: ground or road cells at least this far (m) from any object.
OPEN_MARGIN_M = 1.5


def _to_truth_frame(P: NDArray, survey_origin: NDArray, truth_origin: NDArray) -> NDArray[np.float64]:
    return wgs84_to_enu(enu_to_wgs84(np.asarray(P, dtype=np.float64), survey_origin), truth_origin)


@dataclass
class _Frames:
    """The survey and the truth side by side: both ENU origins, the similarity (``s``,
    ``R``, ``t``) from the survey's camera centres (in the truth's frame) onto the true
    ones, and the true ``T_enu_cam`` of the placed frames."""

    so: NDArray[np.float64]
    to: NDArray[np.float64]
    s: float
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    true_poses: list[NDArray[np.float64]]

    def to_truth(self, P: NDArray) -> NDArray[np.float64]:
        """Survey-frame points into the truth's frame, aligned."""
        return self.s * _to_truth_frame(P, self.so, self.to) @ self.R.T + self.t


def _pose_scores(poses: dict, truth: dict) -> tuple[dict[str, Any], _Frames]:
    so = np.asarray(poses["origin_lla"], dtype=np.float64)
    to = np.asarray(truth["origin_lla"], dtype=np.float64)
    gsd = float(truth["gsd_m"])
    tf = {f["image"]: np.asarray(f["T_enu_cam"], dtype=np.float64) for f in truth["frames"]}
    est, tru = [], []
    for f in poses["frames"]:
        name = Path(f["image"]).name
        if f["T_enu_cam"] is None or name not in tf:
            continue
        T = np.asarray(f["T_enu_cam"], dtype=np.float64)
        # the two ENU frames' axes differ by the meridian convergence (~1e-5 rad): ignored
        est.append((_to_truth_frame(T[:3, 3][None], so, to)[0], T[:3, :3]))
        tru.append(tf[name])
    if len(est) < 3:
        raise InputError("evaluate: fewer than 3 placed frames to align")
    C = np.array([c for c, _ in est])
    Ct = np.array([T[:3, 3] for T in tru])
    s, R, t = similarity_align(C, Ct)
    pos_err = np.linalg.norm(s * C @ R.T + t - Ct, axis=1)
    rot_err = np.array([rotation_angle_deg(T[:3, :3].T @ (R @ Re)) for (_, Re), T in zip(est, tru)])
    scores = {
        "frames_placed": len(est), "frames": len(truth["frames"]), "gsd_m": gsd,
        "position_error_gsd": {"max": float(pos_err.max() / gsd), "rms": float(np.sqrt(np.mean(pos_err**2)) / gsd)},
        "rotation_error_deg": {"max": float(rot_err.max()), "rms": float(np.sqrt(np.mean(rot_err**2)))},
        "absolute_placement_m": {"max": float(np.linalg.norm(C - Ct, axis=1).max()),
                                 "alignment_scale": float(s), "alignment_rotation_deg": rotation_angle_deg(R)},
    }
    return scores, _Frames(so, to, s, R, t, tru)


def _seen_twice(G: NDArray, truth: dict, poses: list[NDArray]) -> NDArray[np.bool_]:
    """Which points ``G`` (n, 3) two frames or more see (inside the image, in front)."""
    K = np.asarray(truth["K"], dtype=np.float64)
    w, h = truth["size"]
    seen = np.zeros(len(G), np.int32)
    for T in poses:
        Tc = np.linalg.inv(T)
        pc = G @ Tc[:3, :3].T + Tc[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
            v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        seen += (pc[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return seen >= 2


def _dsm_scores(dsm: NDArray, meta: dict, tz: Any, truth: dict, fr: _Frames, frame: MapFrame) -> dict[str, Any]:
    """Each true cell centre into the survey's frame (the alignment undone, then WGS84),
    onto its map grid, the estimated height there, and that estimated point back into
    the truth's frame."""
    gsd = float(truth["gsd_m"])
    tdsm, tid = tz["dsm"], tz["object_id"]
    west, north, cell = float(tz["west"]), float(tz["north"]), float(tz["cell_m"])
    H, W = tdsm.shape
    yy, xx = np.mgrid[:H, :W]
    G = np.c_[west + (xx.ravel() + 0.5) * cell, north - (yy.ravel() + 0.5) * cell, tdsm.ravel()]
    okg = np.flatnonzero(np.isfinite(G[:, 2]))
    Gs = frame.enu_to_map(wgs84_to_enu(enu_to_wgs84(((G[okg] - fr.t) @ fr.R) / fr.s, fr.to), fr.so))
    ei = np.floor((meta["north"] - Gs[:, 1]) / meta["gsd"]).astype(np.int64)
    ej = np.floor((Gs[:, 0] - meta["west"]) / meta["gsd"]).astype(np.int64)
    inside = (ei >= 0) & (ei < dsm.shape[0]) & (ej >= 0) & (ej < dsm.shape[1])
    ze = np.full(len(Gs), np.nan)
    ze[inside] = dsm[ei[inside], ej[inside]]
    fe = np.isfinite(ze)
    est = np.full(H * W, np.nan)
    est[okg[fe]] = fr.to_truth(frame.map_to_enu(np.c_[Gs[fe, :2], ze[fe]]))[:, 2]
    est = est.reshape(H, W)
    overlap = np.zeros(H * W, bool)
    overlap[okg] = _seen_twice(G[okg], truth, fr.true_poses)
    overlap = overlap.reshape(H, W)
    open_ground = overlap & _open_ground(tid, cell)
    e = (est - tdsm)[open_ground & np.isfinite(est)]
    if not len(e):
        raise InputError("evaluate: no open ground of the truth has an estimated height")
    detrended = _without_shift_and_plane(est, tdsm, open_ground & np.isfinite(est), west, north, cell)
    return {
        "open_ground_cells": int(open_ground.sum()), "scored_cells": int(len(e)),
        "median_abs_error_m": float(np.median(np.abs(e))), "rms_error_m": float(np.sqrt(np.mean(e**2))),
        "median_abs_error_gsd": float(np.median(np.abs(e)) / gsd), "rms_error_gsd": float(np.sqrt(np.mean(e**2)) / gsd),
        "bias_m": float(np.median(e)), "overlap_cells": int(overlap.sum()),
        "overlap_filled_fraction": float(np.isfinite(est[overlap]).mean()) if overlap.any() else 0.0,
        "after_shift_and_plane": {**detrended, "median_abs_error_gsd": detrended["median_abs_error_m"] / gsd,
                                  "rms_error_gsd": detrended["rms_error_m"] / gsd},
    }


def _without_shift_and_plane(est: NDArray, tdsm: NDArray, ok: NDArray, west: float, north: float, cell: float
                             ) -> dict[str, Any]:
    """The open-ground error once a horizontal shift and a plane are removed (what an
    absolute placement error leaves out: a survey without control is off by a shift, a
    tilt and a height): ``est - true ~ c + a x + b y - grad(true) . (dx, dy)``, linear
    least squares (the shift linearised on the true surface's gradient), then the
    residuals' median |e| and RMS. ``shift_m`` (east, north) is d in est(p) ~ true(p + d)."""
    gy, gx = np.gradient(tdsm.astype(np.float64), cell)
    r, c = np.nonzero(ok)
    x = (c + 0.5) * cell
    y = -(r + 0.5) * cell
    A = np.c_[np.ones(len(r)), x - x.mean(), y - y.mean(), gx[r, c], -gy[r, c]]  # y grows north, rows south
    b = (est - tdsm)[r, c]
    fin = np.isfinite(A).all(axis=1)
    p = np.linalg.lstsq(A[fin], b[fin], rcond=None)[0]
    res = b[fin] - A[fin] @ p
    return {"median_abs_error_m": float(np.median(np.abs(res))), "rms_error_m": float(np.sqrt(np.mean(res**2))),
            "shift_m": [float(p[3]), float(p[4])], "height_m": float(p[0]),
            "tilt_deg": float(np.degrees(np.arctan(np.hypot(p[1], p[2]))))}


def _open_ground(tid: NDArray, cell: float) -> NDArray[np.bool_]:
    """True cells of ground or road at least :data:`OPEN_MARGIN_M` from any object."""
    r = max(1, int(round(OPEN_MARGIN_M / cell)))
    near_obj = cv2.dilate((tid > 1).astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) > 0
    return (tid <= 1) & ~near_obj


def _cloud_scores(path: Path, tz: Any, truth: dict, fr: _Frames, frame: MapFrame) -> dict[str, Any]:
    """The LAS/LAZ cloud against the truth: its points per m2 of the truth cells they fall
    in, the median |height error| of its points over open ground (:func:`_open_ground`),
    the share of those that are ASPRS class 2, and of its points on a vehicle (inside a
    counted target's footprint, above half its height) that are not."""
    las = laspy.read(path)
    P = fr.to_truth(frame.map_to_enu(np.c_[las.x, las.y, las.z]))
    cls = np.asarray(las.classification)
    tid = tz["object_id"]
    west, north, cell = float(tz["west"]), float(tz["north"]), float(tz["cell_m"])
    r = np.floor((north - P[:, 1]) / cell).astype(np.int64)
    c = np.floor((P[:, 0] - west) / cell).astype(np.int64)
    inside = (r >= 0) & (r < tid.shape[0]) & (c >= 0) & (c < tid.shape[1])
    og = np.zeros(len(P), bool)
    og[inside] = _open_ground(tid, cell)[r[inside], c[inside]]
    on_vehicle = np.zeros(len(P), bool)
    for tg in truth["targets"]:
        if tg.get("confuser"):
            continue
        R = np.asarray(tg["T_enu_obj"], dtype=np.float64)[:3, :3]
        local = (P - np.asarray(tg["xyz_enu"], dtype=np.float64)) @ R
        on_vehicle |= (np.abs(local[:, 0]) <= tg["length_m"] / 2) & (np.abs(local[:, 1]) <= tg["width_m"] / 2) & \
            (local[:, 2] >= tg["height_m"] / 2)
    ez = P[og, 2] - tz["dsm"][r[og], c[og]]  # open ground is flat at the cell's scale
    ez = ez[np.isfinite(ez)]
    return {"points": int(len(P)), "open_ground_points": int(og.sum()),
            "points_per_m2": float(len(P) / max(1.0, len(np.unique(r[inside] * tid.shape[1] + c[inside])) * cell**2)),
            "open_ground_median_abs_error_m": float(np.median(np.abs(ez))) if len(ez) else None,
            "open_ground_class_2_fraction": float((cls[og] == 2).mean()) if og.any() else None,
            "vehicle_points": int(on_vehicle.sum()),
            "vehicle_not_ground_fraction": float((cls[on_vehicle] != 2).mean()) if on_vehicle.any() else None}


def _vehicle_scores(dsm: NDArray, ndsm: NDArray, meta: dict, truth: dict, fr: _Frames, frame: MapFrame
                    ) -> dict[str, Any]:
    """Each counted vehicle's height in the nDSM: the highest cell within its true
    footprint (the fused heights have passed the pairs' consistency check; a median
    filter would shave a turret's top, a few cells wide), against its true height."""
    nd = ndsm
    rr, cc = np.nonzero(np.isfinite(ndsm) & np.isfinite(dsm))
    # at their height: the alignment's tilt moves points sideways otherwise
    Pn = fr.to_truth(frame.map_to_enu(np.c_[meta["west"] + (cc + 0.5) * meta["gsd"],
                                            meta["north"] - (rr + 0.5) * meta["gsd"], dsm[rr, cc]]))
    each = []
    for tg in truth["targets"]:
        if tg.get("confuser"):
            continue
        R = np.asarray(tg["T_enu_obj"], dtype=np.float64)[:3, :3]
        local = (Pn - np.asarray(tg["xyz_enu"], dtype=np.float64)) @ R  # about the footprint's centre
        inside = (np.abs(local[:, 0]) <= tg["length_m"] / 2) & (np.abs(local[:, 1]) <= tg["width_m"] / 2)
        rec = {"instance": tg["instance"], "name": tg["name"], "true_height_m": tg["height_m"], "ndsm_height_m": None}
        if inside.sum() >= 5:
            hv = float(np.max(nd[rr[inside], cc[inside]]))
            rec.update(ndsm_height_m=round(hv, 3), relative_error=round(hv / tg["height_m"] - 1.0, 4))
        each.append(rec)
    errs = [abs(v["relative_error"]) for v in each if v["ndsm_height_m"] is not None]
    return {"n": len(each), "measured": len(errs), "max_relative_height_error": max(errs) if errs else None,
            "within_5_percent": sum(e <= 0.05 for e in errs), "each": each}


def map_targets(truth: dict) -> list[MapTarget]:
    """A simulated flight's vehicles and confusers (its ``truth.json``) as the map scorer's
    targets, in the truth's local frame."""
    return [MapTarget(float(x["xyz_enu"][0]), float(x["xyz_enu"][1]), float(x["length_m"]), not x["confuser"],
                      x["class"]) for x in truth["targets"]]


def _detection_scores(path: str | Path, truth: dict, fr: _Frames, radius_m: float | None = None,
                      threshold: float | None = None) -> dict[str, Any]:
    gj = json.loads(Path(path).read_text())
    dets = []
    for f in gj["features"]:
        p = f["properties"]
        z = p.get("z_local")
        if z is None:
            raise InputError(f"{path}: a detection without its ground height (z_local); rerun survey-detect")
        q = fr.to_truth(np.array([[p["x_local"], p["y_local"], z]]))
        dets.append(MapDetection(float(q[0, 0]), float(q[0, 1]), float(p["score"]), p.get("class")))
    sc = score_detections(dets, map_targets(truth), len(truth["frames"]), radius_m=radius_m, threshold=threshold)
    sc.pop("curve")
    return sc


def evaluate_survey(survey_dir: str | Path, flight_dir: str | Path, *, detections: str | Path | None = None,
                    radius_m: float | None = None, threshold: float | None = None) -> dict[str, Any]:
    """Score ``survey_dir`` against ``flight_dir``'s truth: camera positions (in GSD)
    and rotations (deg) after a similarity alignment; DSM error on open ground (median
    |e|, RMS, in m and GSD); the share of the overlapped area (true DSM cells seen by two
    frames or more) with a height; each counted vehicle's height in the nDSM against
    its true height; with ``detections`` (survey-detect GeoJSON), Pd against false
    positives per frame (a hit within ``radius_m`` of a vehicle's centre, default half its
    length; ``threshold``: also Pd, false positives and class accuracy at that score)."""
    sd, fd = Path(survey_dir), Path(flight_dir)
    poses = json.loads((sd / "poses.json").read_text())
    truth = json.loads((fd / "truth.json").read_text())
    if poses.get("scale") not in METRIC_SCALES:
        raise InputError(f"{sd}: the survey has no GPS scale; nothing to compare in metres")
    out, fr = _pose_scores(poses, truth)
    dsm, meta = read_geotiff(sd / "dsm.tif")
    ndsm, _ = read_geotiff(sd / "ndsm.tif")
    frame = MapFrame.from_record(poses)
    cloud = next((p for p in (sd / "cloud.las", sd / "cloud.laz") if p.is_file()), None)
    with np.load(fd / "truth.npz") as tz:
        out["dsm"] = _dsm_scores(dsm, meta, tz, truth, fr, frame)
        out["vehicles"] = _vehicle_scores(dsm, ndsm, meta, truth, fr, frame)
        if cloud is not None:
            out["cloud"] = _cloud_scores(cloud, tz, truth, fr, frame)
    if detections is not None:
        out["detection"] = _detection_scores(detections, truth, fr, radius_m, threshold)
    return out


def ground_roughness(dsm: NDArray, ndsm: NDArray, cell: float, *, patch_m: float = 3.0,
                     max_height_m: float = 0.3, min_filled: float = 0.8) -> dict[str, Any]:
    """How flat the open ground of a DSM is, without truth: the DSM cut into square
    patches of ``patch_m``; in each patch mostly filled with ground (nDSM within
    ``max_height_m``), the RMS of the heights about their least-squares plane. Returns
    the number of patches and the median and 90th percentile of those RMS (m)."""
    d = np.asarray(dsm, dtype=np.float64)
    n = np.asarray(ndsm, dtype=np.float64)
    k = max(3, int(round(patch_m / cell)))
    yy, xx = np.mgrid[:k, :k]
    A = np.c_[xx.ravel() * cell, yy.ravel() * cell, np.ones(k * k)]
    res = []
    for r in range(0, d.shape[0] - k + 1, k):
        for c in range(0, d.shape[1] - k + 1, k):
            w = d[r:r + k, c:c + k].ravel()
            ok = np.isfinite(w) & (np.abs(n[r:r + k, c:c + k].ravel()) < max_height_m)
            if ok.mean() < min_filled:
                continue
            sol, *_ = np.linalg.lstsq(A[ok], w[ok], rcond=None)
            res.append(float(np.sqrt(np.mean((w[ok] - A[ok] @ sol) ** 2))))
    if not res:
        return {"patches": 0, "median_rms_m": None, "p90_rms_m": None}
    return {"patches": len(res), "median_rms_m": float(np.median(res)), "p90_rms_m": float(np.percentile(res, 90))}
