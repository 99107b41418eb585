"""The child process of :func:`prism3d.reconstruct.survey.sfm.map_frames`: COLMAP's feature
extraction, matching and incremental mapping through pycolmap, driven by a JSON request.

It runs apart from the caller because COLMAP logs to stderr at the file-descriptor level
(the parent sends it to ``colmap.log``) and because a crash or a runaway mapper must not
take the caller down. It imports only json, numpy and pycolmap so it starts fast.

Usage: ``python -m prism3d.reconstruct.survey._sfm_worker REQUEST.json``. Stage names go, one a
line, to the stdout it was started with (the parent's progress channel); everything else
that writes to stdout is sent to stderr, the log. Results: ``result.npz`` (arrays, no
pickles) and ``result.json`` (timings, model sizes), both written atomically, and the
chosen model in COLMAP's text format.
"""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path

SCHEMA_VERSION = 1


def _atomic(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp" + path.suffix)
    write(tmp)
    os.replace(tmp, path)


def _reader_options(pycolmap, req: dict):
    ro = pycolmap.ImageReaderOptions()
    ro.camera_model = "RADIAL"
    ro.camera_params = ",".join(repr(float(v)) for v in req["camera_params"])
    return ro


def _extraction_options(pycolmap, req: dict):
    eo = pycolmap.FeatureExtractionOptions()
    eo.max_image_size = int(req["max_image_size"])
    eo.num_threads = int(req["threads"])
    eo.use_gpu = False
    eo.sift.max_num_features = int(req["max_features"])
    return eo


def _pipeline_options(pycolmap, req: dict):
    po = pycolmap.IncrementalPipelineOptions()
    po.num_threads = int(req["threads"])
    po.random_seed = 0
    po.min_model_size = 2  # keep every model of two images or more, so the log and result can name them
    po.triangulation.ignore_two_view_tracks = False  # else two frames triangulate nothing
    po.ba_refine_focal_length = bool(req["refine_focal"])
    po.ba_refine_principal_point = bool(req["refine_principal_point"])
    po.ba_refine_extra_params = bool(req["refine_distortion"])
    po.mapper.abs_pose_refine_focal_length = bool(req["refine_focal"])
    po.mapper.abs_pose_refine_extra_params = bool(req["refine_distortion"])
    return po


def _export(pycolmap, rec, np) -> dict:
    """Poses, camera, points and every observation of ``rec`` as arrays (COLMAP's pixel
    convention: (0, 0) is the top-left corner of the image)."""
    reg_ids = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)
    names, poses, index = [], [], {}
    for k, iid in enumerate(reg_ids):
        im = rec.images[iid]
        names.append(im.name)
        poses.append(np.asarray(im.cam_from_world().matrix(), dtype=np.float64))
        index[iid] = k
    pid_index, xyz, rgb, tlen = {}, [], [], []
    for pid, p in rec.points3D.items():
        pid_index[pid] = len(xyz)
        xyz.append(p.xyz)
        rgb.append(p.color)
        tlen.append(p.track.length())
    obs_img, obs_pt, obs_xy = [], [], []
    for iid in reg_ids:
        for p2 in rec.images[iid].points2D:
            if p2.has_point3D():
                obs_img.append(index[iid])
                obs_pt.append(pid_index[p2.point3D_id])
                obs_xy.append(p2.xy)
    cams = list(rec.cameras.values())
    return {
        "camera_model": np.array(str(cams[0].model.name)),
        "reg_names": np.array(names, dtype=str),
        "cam_from_world": np.array(poses, dtype=np.float64).reshape(-1, 3, 4),
        "camera_params": np.asarray(cams[0].params, dtype=np.float64),
        "camera_size": np.array([cams[0].width, cams[0].height], dtype=np.int64),
        "points": np.array(xyz, dtype=np.float64).reshape(-1, 3),
        "colors": np.array(rgb, dtype=np.uint8).reshape(-1, 3),
        "track_length": np.array(tlen, dtype=np.int64),
        "obs_image": np.array(obs_img, dtype=np.int64),
        "obs_point": np.array(obs_pt, dtype=np.int64),
        "obs_xy": np.array(obs_xy, dtype=np.float64).reshape(-1, 2),
    }


#: The camera models compared, simplest first: (COLMAP model, principal point freed).
CAMERA_CANDIDATES = (("RADIAL", False), ("RADIAL", True), ("OPENCV", False))
#: Share of the sparse points held back to score each camera model on.
HOLD_SHARE = 0.2
#: A richer model is kept only if it cuts the held-back RMS by this share ...
MIN_GAIN = 0.02
#: ... and the cut is significant: the paired per-point differences of squared residuals
#: at least this many standard errors from zero.
MIN_Z = 3.0
#: Fewer sparse points than this: too few to tell the models apart; RADIAL is kept.
MIN_POINTS_TO_COMPARE = 300
#: OPENCV has two focal lengths; camera sensors have square pixels, so a fit whose fx / fy
#: departs from 1 by more than this is a degenerate one (nadir frames trade the focal
#: length against the height) and is refused.
MAX_ASPECT_DEPARTURE = 0.01


def _as_model(pycolmap, rec, model: str) -> None:
    """Give ``rec``'s one camera ``model`` (OPENCV from RADIAL: fx = fy = f, p1 = p2 = 0)."""
    c = next(iter(rec.cameras.values()))
    if model == "RADIAL":
        return
    f, cx, cy, k1, k2 = c.params
    rec.cameras[c.camera_id] = pycolmap.Camera(model="OPENCV", width=c.width, height=c.height,
                                               params=[f, f, cx, cy, k1, k2, 0.0, 0.0], camera_id=c.camera_id)


def _adjust(pycolmap, rec, free_pp: bool) -> None:
    bo = pycolmap.BundleAdjustmentOptions()
    bo.refine_focal_length = True
    bo.refine_extra_params = True
    bo.refine_principal_point = bool(free_pp)
    pycolmap.bundle_adjustment(rec, bo)


def _held_out_sq(np, rec, held: dict):
    """Per held-back point, the mean squared reprojection error (px^2) of its observations
    (NaN if it cannot be triangulated): each triangulated afresh (linear, in normalised
    coordinates) from its observations through ``rec``'s camera and poses, then projected
    back into each."""
    cam = next(iter(rec.cameras.values()))
    out = []
    for obs in held.values():
        res = []
        posed = [(iid, xy_i) for iid, xy_i in obs if iid in rec.images and rec.images[iid].has_pose]
        X, P = _dlt(np, rec, posed) if len(posed) >= 2 else (None, [])
        if X is not None:
            for M, (_, xy_i) in zip(P, posed):
                pc = M[:, :3] @ X + M[:, 3]
                if pc[2] > 0:
                    uv = np.asarray(cam.img_from_cam(pc), dtype=np.float64).ravel()[:2]
                    res.append(float(np.sum((uv - np.asarray(xy_i)) ** 2)))
        out.append(float(np.mean(res)) if res else float("nan"))
    return np.asarray(out)


def _better(np, rich, simple) -> bool:
    """Whether per-point squared residuals ``rich`` beat ``simple`` (:data:`MIN_GAIN`, :data:`MIN_Z`)."""
    ok = np.isfinite(rich) & np.isfinite(simple)
    if ok.sum() < 10:
        return False
    d = simple[ok] - rich[ok]
    z = float(d.mean() / (d.std(ddof=1) / np.sqrt(len(d)) + 1e-300))
    return bool(np.sqrt(rich[ok].mean()) < (1.0 - MIN_GAIN) * np.sqrt(simple[ok].mean()) and z >= MIN_Z)


def _choose_camera(pycolmap, np, rec) -> tuple:
    """The simplest camera model that explains held-back matches (docs/uav.md): each
    candidate adjusted on 80 % of the points, scored on the rest; a richer one must cut
    that RMS by :data:`MIN_GAIN`, significantly (:func:`_better`). Returns the model
    adjusted on all points with the chosen camera, and the comparison."""
    ids = sorted(rec.points3D.keys())
    if len(ids) < MIN_POINTS_TO_COMPARE:
        return rec, {"chosen": "RADIAL", "principal_point": "fixed",
                     "why": f"{len(ids)} sparse points, fewer than {MIN_POINTS_TO_COMPARE} to compare models on"}
    rng = np.random.default_rng(0)
    held_ids = set(int(v) for v in rng.choice(ids, size=max(1, int(HOLD_SHARE * len(ids))), replace=False))
    held = {}
    for pid in held_ids:
        obs = []
        for el in rec.points3D[pid].track.elements:
            obs.append((el.image_id, np.asarray(rec.images[el.image_id].points2D[el.point2D_idx].xy, dtype=np.float64)))
        held[pid] = obs
    scores, sqs = [], []
    for model, pp in CAMERA_CANDIDATES:
        r = pycolmap.Reconstruction(rec)
        _as_model(pycolmap, r, model)
        for pid in held_ids:
            r.delete_point3D(pid)
        _adjust(pycolmap, r, pp)
        c = next(iter(r.cameras.values()))
        sq = _held_out_sq(np, r, held)
        sqs.append(sq)
        sc = {"model": model, "principal_point": "free" if pp else "fixed", "params": [float(v) for v in c.params],
              "held_out_rms_px": float(np.sqrt(np.nanmean(sq))) if np.isfinite(sq).any() else None,
              "fit_rms_px": float(r.compute_mean_reprojection_error())}
        if model == "OPENCV" and abs(float(c.params[0]) / float(c.params[1]) - 1.0) > MAX_ASPECT_DEPARTURE:
            sc["refused"] = f"fx / fy = {float(c.params[0]) / float(c.params[1]):.3f}: not square pixels"
        scores.append(sc)
    pick = 0
    for k in range(1, len(scores)):
        if "refused" not in scores[k] and _better(np, sqs[k], sqs[pick]):
            pick = k
    report = {"chosen": scores[pick]["model"], "principal_point": scores[pick]["principal_point"],
              "held_back_points": len(held_ids), "candidates": scores,
              "why": "the simplest whose held-back RMS no richer model cuts by "
                     f"{MIN_GAIN:.0%} or more, significantly (paired, z >= {MIN_Z:g})"}
    if pick == 0:
        return rec, report
    model, pp = CAMERA_CANDIDATES[pick]
    out = pycolmap.Reconstruction(rec)
    _as_model(pycolmap, out, model)
    _adjust(pycolmap, out, pp)
    return out, report


def umeyama(np, src, dst):
    """The least-squares similarity ``dst ~ s R src + t`` of (N, 3) point sets (Umeyama,
    TPAMI 1991; a proper rotation): ``(s, R, t)``. Unchecked: callers check their input."""
    ma, mb = src.mean(axis=0), dst.mean(axis=0)
    ac, bc = src - ma, dst - mb
    U, S, Vt = np.linalg.svd(bc.T @ ac / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (np.sum(ac**2) / len(src)))
    return s, R, mb - s * R @ ma


def _dlt(np, rec, obs):
    """The linear triangulation (in normalised coordinates) of ``[(image_id, xy COLMAP px)]``
    in two posed images or more of ``rec``'s one camera: the point (None at infinity) and
    each image's 3 x 4 ``cam_from_world``."""
    cam = next(iter(rec.cameras.values()))
    rows, Ms = [], []
    for iid, xy in obs:
        M = np.asarray(rec.images[iid].cam_from_world().matrix(), dtype=np.float64)
        n = np.asarray(cam.cam_from_img(np.asarray(xy, dtype=np.float64)), dtype=np.float64).ravel()[:2]
        rows += [n[0] * M[2] - M[0], n[1] * M[2] - M[1]]
        Ms.append(M)
    vt = np.linalg.svd(np.asarray(rows))[2]
    return (None if abs(vt[-1][3]) <= 1e-12 else vt[-1][:3] / vt[-1][3]), Ms


def _triangulate(np, rec, obs):
    """:func:`_dlt`'s point, or None when it falls behind a camera."""
    X, Ms = _dlt(np, rec, obs)
    return X if X is not None and all((M[:, :3] @ X + M[:, 3])[2] > 0 for M in Ms) else None


def _control(np, rec, req):
    """The request's control points observed in two posed images or more, each as
    ``(point, [(image_id, xy)], X_model)`` (triangulated in ``rec``'s frame)."""
    by_name = {rec.images[i].name: i for i in rec.reg_image_ids()}
    out = []
    for g in req.get("gcps") or []:
        obs = [(by_name[n], (float(x), float(y))) for n, x, y in g["obs"] if n in by_name]
        X = _triangulate(np, rec, obs) if len(obs) >= 2 else None
        if X is not None:
            out.append((g, obs, X))
    return out


def _bundle_options(pycolmap, req: dict, free_pp: bool, *, focal: bool | None = None):
    bo = pycolmap.BundleAdjustmentOptions()
    bo.refine_focal_length = bool(req["refine_focal"]) if focal is None else focal
    bo.refine_extra_params = bool(req["refine_distortion"])
    bo.refine_principal_point = bool(free_pp)
    return bo


def _solve(pycolmap, rec, req, free_pp: bool, control_ids, priors, *, focal: bool | None = None):
    """One bundle adjustment of every posed image: control points held where the map puts
    them, GPS positions (``priors``) as soft constraints; else the usual gauge."""
    config = pycolmap.BundleAdjustmentConfig()
    for iid in rec.reg_image_ids():
        config.add_image(iid)
    for pid in control_ids:
        config.add_constant_point(pid)
    bo = _bundle_options(pycolmap, req, free_pp, focal=focal)
    if priors:
        po = pycolmap.PosePriorBundleAdjustmentOptions()
        adjuster = pycolmap.create_pose_prior_bundle_adjuster(bo, po, config, priors, rec)
    else:
        if not control_ids:
            config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        adjuster = pycolmap.create_default_bundle_adjuster(bo, config, rec)
    summary = adjuster.solve()
    rec.update_point_3d_errors()
    return summary


#: Positions whose second singular value is below this share of the first lie on one line:
#: the roll about it is free, and the positions cannot place the model alone.
MIN_SPREAD = 0.05


def _spread(np, positions) -> bool:
    """Three positions or more, not on one line (:data:`MIN_SPREAD`)."""
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(P) < 3:
        return False
    sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return bool(sv[1] > MIN_SPREAD * sv[0])


#: The finest GPS accuracy an estimate may give (m): an RTK receiver's.
MIN_GPS_SIGMA = 0.02


def _priors(pycolmap, np, rec, ids, pos: dict, sigma_h: float, sigma_v: float) -> list:
    """COLMAP pose priors for images ``ids`` at their positions, of the given accuracy.
    The image residuals keep COLMAP's unit weight (a 1 px a-priori accuracy, the
    photogrammetric default for tie points), not their own sigma (0.15 px on the
    simulator): weighed at that, the images' biased optimum along the focal length /
    flying height valley wins (docs/uav.md, "GPS in the adjustment")."""
    cov = np.diag([sigma_h**2, sigma_h**2, sigma_v**2])
    out = []
    for iid in ids:
        pr = pycolmap.PosePrior()
        pr.corr_data_id = rec.images[iid].data_id
        pr.position = np.asarray(pos[rec.images[iid].name], dtype=np.float64)
        pr.position_covariance = cov
        pr.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
        out.append(pr)
    return out


def _gps_sigma(np, rec, ids, pos: dict) -> tuple[float, float]:
    """The positions' accuracy (horizontal per axis, vertical; m) from their residuals to
    the adjusted camera centres, corrected for the 7 parameters of the frame they fix
    (a variance-component estimate), and no finer than :data:`MIN_GPS_SIGMA`."""
    d = np.array([rec.images[i].projection_center() - np.asarray(pos[rec.images[i].name]) for i in ids])
    n = len(d)
    k = np.sqrt(3.0 * n / max(3.0 * n - 7.0, 1.0))
    sh = k * float(np.sqrt(np.mean(d[:, :2] ** 2)))
    sv = k * float(np.sqrt(np.mean(d[:, 2] ** 2)))
    return max(sh, MIN_GPS_SIGMA), max(sv, MIN_GPS_SIGMA)


def _adjust_held(pycolmap, np, out, req, free_pp: bool, control, control_ids, priors) -> None:
    """The adjustment with the control points held. COLMAP's pose-prior adjustment first
    moves the whole model, held points too, by a similarity onto the positions; held
    points move only by that similarity, so the one that takes them back onto the map
    (three or more) undoes it exactly."""
    _solve(pycolmap, out, req, free_pp, control_ids, priors)
    if not control_ids:
        return
    P = np.array([out.points3D[pid].xyz for pid in control_ids], dtype=np.float64)
    Q = np.array([g["enu"] for g, _, _ in control], dtype=np.float64)
    if float(np.abs(P - Q).max()) > 1e-6:
        s, R, t = umeyama(np, P, Q)
        out.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))

def _georeferenced(pycolmap, np, rec, req, free_pp: bool):
    """The model moved into the request's local ENU frame and adjusted there. GPS priors
    asked (and three positions or more off one line): moved onto the positions, which are
    soft constraints (COLMAP's pose-prior adjustment, their accuracy the covariance).
    Control points (three or more triangulated): held where the map puts them (moved onto
    them first when there is no GPS prior). Returns the model and a record; the model is
    untouched when neither applies."""
    gps = req.get("gps_prior")
    pos = dict(zip(req["image_names"], req.get("positions") or []))
    control = _control(np, rec, req)
    reg = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)
    named = [i for i in reg if rec.images[i].name in pos]  # image ids: the same in the copy below
    gps = gps if gps and _spread(np, [pos[rec.images[i].name] for i in named]) else None
    if len(control) >= 3 and not gps:
        src = np.array([X for _, _, X in control])
        dst = np.array([g["enu"] for g, _, _ in control], dtype=np.float64)
        how = f"{len(control)} ground control points"
    elif gps:
        src = np.array([rec.images[i].projection_center() for i in named])
        dst = np.array([pos[rec.images[i].name] for i in named], dtype=np.float64)
        how = "the GPS positions" + (f" and {len(control)} ground control points" if len(control) >= 3 else "")
    else:
        return rec, {"frame": "model", "why": f"{len(control)} control point(s) triangulated (3 needed) and no GPS "
                                              "prior (not asked, or fewer than 3 positions off one line)"}
    s, R, t = umeyama(np, src, dst)
    out = pycolmap.Reconstruction(rec)
    out.transform(pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t))
    control_ids = []
    for g, obs, X in control if len(control) >= 3 else ():
        track = pycolmap.Track()
        for iid, xy in obs:
            pts = out.images[iid].points2D
            pts.append(pycolmap.Point2D(np.asarray(xy, dtype=np.float64)))
            track.add_element(iid, len(pts) - 1)
        control_ids.append(out.add_point3D(np.asarray(g["enu"], dtype=np.float64), track))
    named = named if gps else []
    priors = _priors(pycolmap, np, out, named, pos, gps["sigma_h"], gps["sigma_v"]) if gps else []
    out.update_point_3d_errors()
    before = float(out.compute_mean_reprojection_error())
    _adjust_held(pycolmap, np, out, req, free_pp, control, control_ids, priors)
    rec_out = {"frame": "enu", "aligned_to": how, "control_points": len(control_ids), "gps_priors": len(priors),
               "similarity_scale": s, "mean_reprojection_px_before": before}
    if gps:
        rec_out["gps_accuracy_m"] = [gps["sigma_h"], gps["sigma_v"]]
    if gps and gps.get("estimate"):
        sh, sv = _gps_sigma(np, out, named, pos)
        rec_out["gps_accuracy_m"] = [sh, sv]
        rec_out["gps_accuracy_source"] = "estimated from the positions' residuals after a first adjustment"
        priors = _priors(pycolmap, np, out, named, pos, sh, sv)
        _adjust_held(pycolmap, np, out, req, free_pp, control, control_ids, priors)
    rec_out["mean_reprojection_px_after"] = float(out.compute_mean_reprojection_error())
    if req["refine_focal"]:
        rec_out["self_calibration"] = _determined(_focal_profile(
            pycolmap, np, out, lambda r, focal: _solve(pycolmap, r, req, free_pp, control_ids, priors, focal=focal)),
            bool(control_ids) and bool(priors))
    rec_out["control_residuals_px"] = {g["name"]: float(out.points3D[pid].error)
                                       for (g, _, _), pid in zip(control, control_ids)}
    for pid in control_ids:
        out.delete_point3D(pid)
    return out, rec_out


#: The focal length's relative step for its profile (:func:`_focal_profile`).
PROFILE_STEP = 0.005
#: A relative focal-length uncertainty (1 sigma) above this: the block does not determine it.
MAX_FOCAL_SIGMA = 0.005
#: Viewing directions all within this of their mean (deg): a one-direction (nadir) block.
ONE_DIRECTION_DEG = 10.0
#: Camera heights along the viewing direction spread less than this share of the depth: one altitude.
ONE_ALTITUDE_SPREAD = 0.05


def _depth_in_baselines(np, rec) -> float:
    """The median depth of the points in the images that see them over the median
    distance from each image to its nearest: the flying height in baselines (scale-free)."""
    ids = list(rec.reg_image_ids())
    C = np.array([rec.images[i].projection_center() for i in ids])
    depths = []
    for i in ids:
        im = rec.images[i]
        M = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        X = np.array([rec.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()]).reshape(-1, 3)
        if len(X):
            depths.append(float(np.median(X @ M[2, :3] + M[2, 3])))
    d = np.linalg.norm(C[:, None] - C[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(depths) / max(float(np.median(d.min(axis=1))), 1e-12))


def _block_geometry(np, rec) -> dict:
    """Whether the images look one way (nadir) from one altitude: the two geometries that
    leave the focal length tied to the flying height."""
    ids = list(rec.reg_image_ids())
    V = np.array([np.asarray(rec.images[i].cam_from_world().matrix(), dtype=np.float64)[2, :3] for i in ids])
    m = V.mean(axis=0)
    m /= np.linalg.norm(m)
    spread_deg = float(np.degrees(np.arccos(np.clip(V @ m, -1.0, 1.0))).max())
    C = np.array([rec.images[i].projection_center() for i in ids])
    along = C @ m
    depth = _depth_in_baselines(np, rec)
    d = np.linalg.norm(C[:, None] - C[None], axis=2)
    np.fill_diagonal(d, np.inf)
    height_spread = float(np.std(along) / max(depth * float(np.median(d.min(axis=1))), 1e-12))
    return {"viewing_directions_within_deg": round(spread_deg, 2), "one_direction": spread_deg <= ONE_DIRECTION_DEG,
            "height_spread_of_depth": round(height_spread, 4), "one_altitude": height_spread <= ONE_ALTITUDE_SPREAD}


def _scaled_focal(pycolmap, np, rec, factor: float) -> None:
    cam = next(iter(rec.cameras.values()))
    p = np.array(cam.params, dtype=np.float64)
    p[:2 if cam.model.name == "OPENCV" else 1] *= factor
    cam.params = p


def _focal_profile(pycolmap, np, rec, solve) -> dict:
    """:func:`_profile`, or why it could not be computed (it only reports: it never stops a survey)."""
    try:
        return _profile(pycolmap, np, rec, solve)
    except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
        return {"error": f"{type(exc).__name__}: {exc}"[:200]}


def _profile(pycolmap, np, rec, solve) -> dict:
    """How well the block determines the focal length, and what it trades against: the
    adjustment (``solve(model, refine_focal)``, returning Ceres' summary) repeated with
    the focal length held :data:`PROFILE_STEP` above and below its value. The cost's rise gives
    its 1-sigma uncertainty (least squares: S(f) - S0 = (df / sigma_f)^2 sigma^2, sigma^2 the
    residual variance); the flying height's change (in baselines) per focal change gives
    the tie (1.0: a 1 % longer focal length is a 1 % higher flight, nothing else)."""
    base = pycolmap.Reconstruction(rec)
    s0 = solve(base, None).ceres_summary
    c0, dof = float(s0.final_cost), max(1, int(s0.num_residuals_reduced) - int(s0.num_effective_parameters_reduced))
    sigma2 = 2.0 * c0 / dof
    h0 = _depth_in_baselines(np, base)
    cost, height = [], []
    for sign in (1.0, -1.0):
        r = pycolmap.Reconstruction(base)
        _scaled_focal(pycolmap, np, r, 1.0 + sign * PROFILE_STEP)
        cost.append(float(solve(r, False).ceres_summary.final_cost))
        height.append(_depth_in_baselines(np, r))
    rise = cost[0] + cost[1] - 2.0 * c0  # = (S+ + S-) / 2 - S0 with S = 2 cost
    sig = PROFILE_STEP * float(np.sqrt(sigma2 / rise)) if rise > 0 else float("inf")
    f = float(next(iter(base.cameras.values())).params[0])
    out = {"focal_px": f, "focal_sigma_pct": None if not np.isfinite(sig) else 100.0 * sig,
           "height_change_per_focal_change": (height[0] - height[1]) / (2.0 * PROFILE_STEP * h0),
           "geometry": _block_geometry(np, base),
           "method": f"the adjustment repeated with f held {100 * PROFILE_STEP:g} % above and below"}
    return out


def _determined(report: dict, anchored: bool) -> dict:
    """``report`` with ``determined``: a formal uncertainty within :data:`MAX_FOCAL_SIGMA`,
    and either a block that is not nadir-only at one altitude or heights held from outside
    the images (control points with GPS priors). A nadir block at one altitude ties the
    focal length to the flying height, and the formal figure (a curvature at the optimum)
    then understates the error: on the simulator's 12-frame nadir block the images' own
    optimum lay 3.6 % (7 formal sigma) from the true focal length."""
    if "error" in report:
        return {**report, "determined": False}
    g = report["geometry"]
    weak = g["one_direction"] and g["one_altitude"] and not anchored
    sig = report["focal_sigma_pct"]
    return {**report, "determined": bool(sig is not None and sig <= 100.0 * MAX_FOCAL_SIGMA and not weak),
            "anchored_by": "control points and GPS heights" if anchored else None}


def _verified_pairs(pycolmap, db: Path) -> dict[str, int]:
    """Image pairs that passed geometric verification, counted by COLMAP's configuration
    (CALIBRATED, PLANAR_OR_PANORAMIC, ...): tells "no overlap" from "no parallax"."""
    database = pycolmap.Database.open(db)
    try:
        _, geometries = database.read_two_view_geometries()
    finally:
        database.close()
    counts: dict[str, int] = {}
    for g in geometries:
        if len(g.inlier_matches) > 0:
            name = pycolmap.TwoViewGeometryConfiguration(int(g.config)).name  # an int when read back
            counts[name] = counts.get(name, 0) + 1
    return counts


def _pair_inliers(pycolmap, db: Path) -> dict[str, dict[str, int]]:
    """Per image name, the images it was verified with and their inlier matches: why a
    frame was not placed (no partner at all, or partners with few inliers)."""
    database = pycolmap.Database.open(db)
    try:
        name = {im.image_id: im.name for im in database.read_all_images()}
        pair_ids, geometries = database.read_two_view_geometries()
    finally:
        database.close()
    out: dict[str, dict[str, int]] = {}
    for pid, g in zip(pair_ids, geometries):
        n = len(g.inlier_matches)
        if n == 0:
            continue
        a, b = (name.get(int(i)) for i in pycolmap.pair_id_to_image_pair(int(pid)))
        if a is not None and b is not None:
            out.setdefault(a, {})[b] = n
            out.setdefault(b, {})[a] = n
    return out


def _keypoint_counts(pycolmap, db: Path) -> dict[str, int]:
    """Keypoints stored per image name: an image missing here could not be read."""
    database = pycolmap.Database.open(db)
    try:
        return {im.name: database.num_keypoints_for_image(im.image_id) for im in database.read_all_images()}
    finally:
        database.close()


def _match(pycolmap, req: dict, db: Path) -> None:
    """Match the features on the CPU, sequentially or exhaustively as the request says."""
    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = int(req["threads"])
    mo.use_gpu = False
    if req["matching"] == "sequential":
        so = pycolmap.SequentialPairingOptions()
        so.overlap = int(req["sequential_overlap"])
        so.loop_detection = False
        pycolmap.match_sequential(db, matching_options=mo, pairing_options=so, device=pycolmap.Device.cpu)
    elif req["matching"] == "spatial":
        _write_position_priors(pycolmap, req, db)
        so = pycolmap.SpatialPairingOptions()
        so.max_num_neighbors = int(req["spatial_neighbours"])
        so.max_distance = 1e9  # the nearest, however far: the flying height sets the spacing
        so.ignore_z = False
        pycolmap.match_spatial(db, matching_options=mo, pairing_options=so, device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(db, matching_options=mo, device=pycolmap.Device.cpu)


def _write_position_priors(pycolmap, req: dict, db: Path) -> None:
    """The frames' positions (the request's local metres) as the database's pose priors,
    replacing those extraction read from EXIF (a position table may be the better source)."""
    pos = dict(zip(req["image_names"], req["positions"]))
    database = pycolmap.Database.open(db)
    try:
        database.clear_pose_priors()
        for im in database.read_all_images():
            if im.name in pos:
                pr = pycolmap.PosePrior()
                pr.corr_data_id = im.data_id
                pr.position = [float(v) for v in pos[im.name]]
                pr.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
                database.write_pose_prior(pr)
    finally:
        database.close()


def _map(pycolmap, req: dict, db: Path, image_dir: Path) -> dict:
    """Incremental mapping: every model of two images or more, by pycolmap's model index."""
    # pycolmap 4.2.1 writes some models (binary) there, only when it finds several: the
    # chosen one is written by main in text format, the scratch folder is dropped.
    scratch = Path(req["work_dir"]) / "sparse"
    models = pycolmap.incremental_mapping(db, image_dir, scratch, options=_pipeline_options(pycolmap, req))
    shutil.rmtree(scratch, ignore_errors=True)
    return models


def _write_model(pycolmap, np, req: dict, best) -> None:
    """The chosen model in COLMAP's text format and its arrays in ``result.npz`` (atomic)."""
    arrays = _export(pycolmap, best, np)
    model_dir = Path(req["model_dir"])
    model_dir.mkdir(parents=True, exist_ok=True)
    best.write_text(model_dir)
    _atomic(Path(req["result_npz"]), lambda p: np.savez(p, **arrays))


def die_with_parent() -> None:
    """Have the kernel kill this process when its parent dies (Linux PR_SET_PDEATHSIG), so
    a killed survey leaves no COLMAP behind; elsewhere, nothing. A parent already gone
    before the call ends this process at once."""
    parent = os.getppid()
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            return
    if os.getppid() != parent or parent == 1:
        os._exit(3)


def main(argv: list[str]) -> int:
    die_with_parent()
    if len(argv) != 1:
        print("usage: python -m prism3d.reconstruct.survey._sfm_worker REQUEST.json", file=sys.stderr)
        return 2
    # The stage channel is the stdout we were given; from here on fd 1 is the log.
    chan = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)

    def stage(name: str) -> None:
        chan.write(f"stage {name}\n")
        chan.flush()

    req = json.loads(Path(argv[0]).read_text())
    if req.get("schema_version") != SCHEMA_VERSION:
        print(f"request schema_version {req.get('schema_version')!r} is not {SCHEMA_VERSION}", file=sys.stderr)
        return 2
    _run(req, stage)
    return 0


def _refine(pycolmap, np, best, req: dict, info: dict, stage):
    """The largest model after the camera-model choice, the adjustment in the local frame
    (GPS priors, control points) and the focal length's profile, each as the request asks;
    their records and times go into ``info``."""
    seconds = info["seconds"]
    if req.get("choose_camera"):
        stage("camera model")
        t0 = time.perf_counter()
        best, info["camera_choice"] = _choose_camera(pycolmap, np, best)
        seconds["camera model"] = time.perf_counter() - t0
    free_pp = bool(req["refine_principal_point"]) or info.get("camera_choice", {}).get("principal_point") == "free"
    if req.get("gcps") or req.get("gps_prior"):
        stage("georeferencing")
        t0 = time.perf_counter()
        best, info["georeferencing"] = _georeferenced(pycolmap, np, best, req, free_pp)
        seconds["georeferencing"] = time.perf_counter() - t0
    if "self_calibration" in info.get("georeferencing", {}):
        info["self_calibration"] = info["georeferencing"].pop("self_calibration")
    elif req["refine_focal"]:
        info["self_calibration"] = _determined(_focal_profile(
            pycolmap, np, best, lambda r, focal: _solve(pycolmap, r, req, free_pp, [], [], focal=focal)), False)
    return best


def _run(req: dict, stage) -> None:
    """Features, matching and mapping for one request; ``stage(name)`` reports each."""
    import numpy as np
    import pycolmap

    db = Path(req["database"])
    image_dir = Path(req["image_dir"])
    names = list(req["image_names"])
    pycolmap.set_random_seed(0)
    seconds: dict[str, float] = {}

    stage("features")
    t0 = time.perf_counter()
    pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=_reader_options(pycolmap, req),
                              extraction_options=_extraction_options(pycolmap, req), device=pycolmap.Device.cpu)
    seconds["features"] = time.perf_counter() - t0
    have = _keypoint_counts(pycolmap, db)
    unread = [n for n in names if n not in have]

    stage("matching")
    t0 = time.perf_counter()
    if not unread:
        _match(pycolmap, req, db)
    seconds["matching"] = time.perf_counter() - t0
    pairs = _verified_pairs(pycolmap, db) if not unread else {}
    partners = _pair_inliers(pycolmap, db) if not unread else {}

    stage("mapping")
    t0 = time.perf_counter()
    models = _map(pycolmap, req, db, image_dir) if not unread else {}
    seconds["mapping"] = time.perf_counter() - t0
    ranked = sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), reverse=True)
    info = {
        "schema_version": SCHEMA_VERSION,
        "seconds": seconds,
        "unreadable": unread,
        "keypoints": have,
        "model_sizes": [int(r.num_reg_images()) for r in ranked],
        "verified_pairs": pairs,
        "pair_inliers": partners,
        "pycolmap_version": pycolmap.__version__,
    }
    if ranked:
        _write_model(pycolmap, np, req, _refine(pycolmap, np, ranked[0], req, info, stage))
    stage("done")
    _atomic(Path(req["result_json"]), lambda p: p.write_text(json.dumps(info, indent=1)))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
