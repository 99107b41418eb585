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
        rows, P, xy = [], [], []
        for iid, xy_i in obs:
            if iid not in rec.images or not rec.images[iid].has_pose:
                continue
            M = np.asarray(rec.images[iid].cam_from_world().matrix(), dtype=np.float64)
            n = np.asarray(cam.cam_from_img(np.asarray(xy_i, dtype=np.float64)), dtype=np.float64).ravel()[:2]
            rows += [n[0] * M[2] - M[0], n[1] * M[2] - M[1]]
            P.append(M)
            xy.append(xy_i)
        _, _, vt = np.linalg.svd(np.asarray(rows)) if len(P) >= 2 else (None, None, None)
        if vt is not None and abs(vt[-1][3]) > 1e-12:
            X = vt[-1][:3] / vt[-1][3]
            for M, xy_i in zip(P, xy):
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
        best = ranked[0]
        if req.get("choose_camera"):
            stage("camera model")
            t0 = time.perf_counter()
            best, info["camera_choice"] = _choose_camera(pycolmap, np, best)
            seconds["camera model"] = time.perf_counter() - t0
        _write_model(pycolmap, np, req, best)
    stage("done")
    _atomic(Path(req["result_json"]), lambda p: p.write_text(json.dumps(info, indent=1)))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
