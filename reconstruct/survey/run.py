"""The UAV survey mode: photographs from one moving camera become a georeferenced point
cloud, DSM, orthophoto and normalised DSM (the paper's closing proposal: "the
neighboring images in the sequence form stereo pairs").

Stages (docs/uav.md): poses and refined intrinsics from pycolmap's incremental mapping
(:mod:`prism3d.reconstruct.survey.sfm`); a similarity onto the GPS positions in a local
east-north-up frame (:func:`georeference`); each pair of neighbouring frames, and the
next-but-one, rectified from its poses and matched by our matcher (:func:`dense_pair`,
one independent unit per pair, run in this process or on Dask); the pairs' heights fused
cell by cell with a consistency check (:func:`fuse_tiles`); then the products.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError, ReconstructionError
from prism3d.geo import MapFrame, wgs84_to_enu
from prism3d.io.atomic import atomic_write_text, staged_folder
from prism3d.reconstruct.stereo.flatness import ransac_plane
from prism3d.reconstruct.stereo.match_options import MatchOptions
from prism3d.reconstruct.survey._sfm_worker import MIN_SPREAD
from prism3d.reconstruct.survey.dsm import MAX_CELLS, grid_points
from prism3d.reconstruct.survey.gcp import (
    GcpFile,
    check_points_report,
    gps_only_accuracy,
    read_gcp_file,
    survey_control,
)
from prism3d.reconstruct.survey.inputs import (
    VIDEO_SUFFIXES,
    check_frames,
    gps_positions,
    load_frame,
    starting_camera,
    video_frames,
)
from prism3d.reconstruct.survey.model import (
    DISPARITY_SIGMA_PX,
    SURVEY_FILES,
    SURVEY_SCHEMA_VERSION,
    FusedSurface,
    Georef,
    PairRequest,
    PairResult,
    PairTile,
    SurveyOptions,
    SurveyState,
    TwoViewPose,
)
from prism3d.reconstruct.survey.pair import pair_cloud
from prism3d.reconstruct.survey.products import (
    write_products,
)
from prism3d.reconstruct.survey.resume import ResumeFolder, save_pair
from prism3d.reconstruct.survey.sfm import SfmOptions, map_frames, similarity_align

_log = logging.getLogger(__name__)

__all__ = [
    "SURVEY_SCHEMA_VERSION", "SURVEY_FILES", "Georef", "PairRequest", "PairResult", "PairTile", "SurveyOptions",
    "dense_pair", "fuse_tiles", "georeference", "run_survey",
]


# -- georeferencing ----------------------------------------------------------------------


def _ground_up(points: NDArray, centres: NDArray) -> NDArray[np.float64]:
    """The dominant plane's normal of sparse ``points`` (a nadir survey's ground),
    pointing towards the cameras."""
    rng = np.random.default_rng(0)
    P = np.asarray(points, dtype=np.float64)
    if len(P) < 20:
        raise InputError("survey: fewer than 20 sparse points; the ground cannot be levelled")
    sample = P[rng.choice(len(P), size=min(len(P), 20000), replace=False)]
    spread = float(np.median(np.linalg.norm(sample - np.median(sample, axis=0), axis=1)))
    n, _, _ = ransac_plane(sample, 0.02 * max(spread, 1e-9), rng)
    if n @ (centres.mean(axis=0) - np.median(P, axis=0)) < 0:
        n = -n
    return n / np.linalg.norm(n)


def georeference(centres: NDArray, gps_enu: NDArray | None, points: NDArray) -> Georef:
    """The similarity from the model frame to local ENU. With GPS at three or more
    camera centres not on one line: the least-squares similarity onto them (frames more
    than 3x the median residual away dropped once). On one line (two frames, or one
    straight strip), positions leave the roll about the line free: scale and the track
    come from the positions and "up" from the ground's dominant plane. Without GPS: the
    model levelled on its ground (at height 0), camera 1 above the origin, its scale
    unknown."""
    C = np.asarray(centres, dtype=np.float64)
    up_model = _ground_up(points, C)
    if gps_enu is None:
        x = np.array([1.0, 0.0, 0.0]) - up_model[0] * up_model
        if np.linalg.norm(x) < 1e-6:
            x = np.array([0.0, 1.0, 0.0]) - up_model[1] * up_model
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(up_model, x), up_model])
        t = -R @ C[0]
        t[2] = -float(np.median(np.asarray(points, dtype=np.float64) @ up_model))  # the ground at 0
        return Georef(1.0, R, t, "levelled on the ground (no GPS: scale unknown)", None)
    G = np.asarray(gps_enu, dtype=np.float64)
    if G.shape != C.shape:
        raise InputError(f"GPS: {len(G)} positions for {len(C)} cameras")
    sv = np.linalg.svd(G - G.mean(axis=0), compute_uv=False)
    if len(C) >= 3 and sv[1] > MIN_SPREAD * sv[0]:
        keep = np.ones(len(C), bool)
        for _ in range(2):
            s, R, t = similarity_align(C[keep], G[keep])
            res = np.linalg.norm(s * C @ R.T + t - G, axis=1)
            med = float(np.median(res[keep]))
            new = res <= max(3.0 * med, 1e-9)
            if new.sum() < 3 or np.array_equal(new, keep):
                break
            keep = new
        return Georef(s, R, t, "similarity to the GPS positions",
                      float(np.sqrt(np.mean(res[keep] ** 2))))
    # one line: scale from the spreads, heading from the track, up from the ground
    a, b = C - C.mean(axis=0), G - G.mean(axis=0)
    s = float(np.sqrt((b**2).sum() / max((a**2).sum(), 1e-300)))
    if s == 0:
        raise InputError("GPS: every frame has the same position; no scale or heading")
    dm = a[np.argmax(np.linalg.norm(a, axis=1))]
    dm = dm if dm @ a[-1] >= 0 else -dm
    dg = G[-1] - G[0]
    dm_h = dm - (dm @ up_model) * up_model
    dg_h = np.array([dg[0], dg[1], 0.0])
    if np.linalg.norm(dm_h) < 1e-12 or np.linalg.norm(dg_h) < 1e-6:
        raise InputError("GPS: the frames do not move horizontally; no heading to align to")
    dm_h /= np.linalg.norm(dm_h)
    dg_h /= np.linalg.norm(dg_h)
    z = np.array([0.0, 0.0, 1.0])
    src = np.stack([dm_h, np.cross(up_model, dm_h), up_model], axis=1)
    dst = np.stack([dg_h, np.cross(z, dg_h), z], axis=1)
    R = dst @ src.T
    t = G.mean(axis=0) - s * R @ C.mean(axis=0)
    res = np.linalg.norm(s * C @ R.T + t - G, axis=1)
    return Georef(s, R, t, "GPS track and scale, levelled on the ground (frames on one line)",
                  float(np.sqrt(np.mean(res**2))))


# -- one pair ---------------------------------------------------------------------------
def _dense_scale(size: tuple[int, int], max_pixels: float) -> int:
    """The integer downscale factor keeping a ``(w, h)`` frame under ``max_pixels``."""
    w, h = size
    return max(1, math.ceil(math.sqrt(w * h / max_pixels) - 1e-9))


def _project(T_cam_enu: NDArray, K: NDArray, P: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pixels (n, 2) and depths (n,) of ENU points in a camera (no distortion)."""
    pc = P @ T_cam_enu[:3, :3].T + T_cam_enu[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (pc[:, :2] / z[:, None]) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    return uv, z


def _tile_bounds(P: NDArray, cell: float) -> tuple[float, float, float, float]:
    """Bounds (west, south, east, north) of points snapped to the survey's cell lattice."""
    w = math.floor(P[:, 0].min() / cell) * cell
    n = (math.floor(P[:, 1].max() / cell) + 1) * cell
    e = math.floor(P[:, 0].max() / cell) * cell + 0.5 * cell
    s = n - (math.floor((n - P[:, 1].min()) / cell) + 0.5) * cell
    return w, s, e, n - 1e-9 * cell


def dense_pair(req: PairRequest) -> PairResult:
    """:func:`match_pair`, the result also written to ``req.save_to`` when given (the
    survey's resume folder: a pair finished before an interruption is not matched again)."""
    res = match_pair(req)
    if req.save_to:
        save_pair(res, req.save_to)
    return res


def match_pair(req: PairRequest) -> PairResult:
    """One pair's dense heights: frames ``i`` and ``j`` undistorted and downscaled by
    ``factor``, rectified from their poses, matched over the disparity range of the sparse
    points both see, triangulated in ENU and gridded on the survey's lattice. Returns the
    pair's result (status "ok" or "skipped" with a reason) and, when ok, its tile and
    camera i's depth map. A pair that cannot be a stereo pair is skipped, never raised:
    other pairs carry on."""
    t0 = time.perf_counter()
    Ti, Tj = np.asarray(req.T_enu_cam_i, dtype=np.float64), np.asarray(req.T_enu_cam_j, dtype=np.float64)
    ci, cj = Ti[:3, 3], Tj[:3, 3]
    base = float(np.linalg.norm(cj - ci))
    res = PairResult(int(req.i), int(req.j), baseline=base)
    P = np.asarray(req.shared, dtype=np.float64)
    if len(P) < int(req.min_shared):
        res.reason = f"no overlap ({len(P)} shared sparse points)"
        return res
    Tci, Tcj = np.linalg.inv(Ti), np.linalg.inv(Tj)
    K, dist, factor = np.asarray(req.K, dtype=np.float64), np.asarray(req.dist, dtype=np.float64), int(req.factor)
    img_i, Ks = load_frame(req.path_i, K, dist, factor)
    img_j, _ = load_frame(req.path_j, K, dist, factor)
    q1, zi = _project(Tci, Ks, P)
    q2, _ = _project(Tcj, Ks, P)
    zmed = float(np.median(zi))
    res.depth_median = zmed
    if base < float(req.min_base_to_height) * zmed:
        res.reason = f"baseline {base:.3g} is under {req.min_base_to_height:g} of the depth {zmed:.3g}"
        return res
    t = Tcj[:3, :3] @ ci + Tcj[:3, 3]
    pose = TwoViewPose(Tcj[:3, :3] @ Ti[:3, :3], t / np.linalg.norm(t), q1, q2, len(P), 0.0)
    lk = int(req.lk_window)
    try:
        pc = pair_cloud(img_i, img_j, Ks, pose, baseline=base, matcher=req.matcher,
                        options=MatchOptions(lk_window=lk, lk_iters=3 if lk > 5 else 1))
    except InputError as exc:
        res.reason = str(exc).removeprefix("pair: ")
        return res
    except Exception as exc:  # noqa: BLE001 - the matcher finding nothing is a skipped pair
        res.reason = f"matching failed ({type(exc).__name__}: {exc})"
        return res
    Pe = pc.points @ Ti[:3, :3].T + ci
    if len(Pe) < 100:
        res.reason = f"matching kept {len(Pe)} points"
        return res
    g = grid_points(Pe, pc.colours, float(req.cell), bounds=_tile_bounds(Pe, float(req.cell)))
    res.status, res.n_points, res.valid_fraction = "ok", int(len(Pe)), round(pc.valid_fraction, 4)
    res.disparity_range = list(pc.disparity_range)
    res.sigma_z = float(zmed**2 / (Ks[0, 0] * base) * DISPARITY_SIGMA_PX)
    res.seconds = round(time.perf_counter() - t0, 3)
    res.tile = PairTile(g.west, g.north, g.gsd, g.dsm, g.count, g.ortho[..., :3])
    res.depth, res.K_depth = _depth_map(pc.points, Ks, img_i.shape[:2]), Ks
    return res


def _depth_map(points: NDArray, Ks: NDArray, shape: tuple[int, int]) -> NDArray[np.float32]:
    """Camera i's depth map at the matched scale from its points (camera frame): the
    nearest surface per pixel (NaN: none)."""
    h, w = shape
    Z = points[:, 2]
    u = np.round(points[:, 0] / Z * Ks[0, 0] + Ks[0, 2]).astype(np.int64)
    v = np.round(points[:, 1] / Z * Ks[1, 1] + Ks[1, 2]).astype(np.int64)
    ok = (Z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full((h, w), np.nan, dtype=np.float32)
    order = np.argsort(-Z[ok])
    depth[v[ok][order], u[ok][order]] = Z[ok][order]
    return depth


# -- fusion ------------------------------------------------------------------------------


def fuse_tiles(tiles: Sequence[PairTile], sigmas: Sequence[float], *, band_rows: int = 512) -> FusedSurface:
    """Fuse pairs' height tiles on one lattice: per cell the median of the pairs'
    heights; a pair agrees when within ``3 sigma + cell/2`` of it (``sigma`` its
    expected height noise); cells seen by two or more pairs keep the mean of those that
    agree when at least two do (else no height: the pairs contradict each other); cells
    only one pair saw keep its height. Processed in square blocks of ``band_rows`` cells
    (memory ~ one block times the tiles over it)."""
    if not tiles:
        raise InputError("fusion: no pair produced heights")
    cell = float(tiles[0].cell)
    west = min(float(t.west) for t in tiles)
    north = max(float(t.north) for t in tiles)
    offs = []
    H = W = 0
    for t in tiles:
        c0 = int(round((float(t.west) - west) / cell))
        r0 = int(round((north - float(t.north)) / cell))
        h, w = t.dsm.shape
        offs.append((r0, c0, h, w))
        H, W = max(H, r0 + h), max(W, c0 + w)
    if H * W > MAX_CELLS:
        raise InputError(f"fusion: {W} x {H} cells is over the {MAX_CELLS:,} budget; give a larger cell")
    dsm = np.full((H, W), np.nan, dtype=np.float32)
    rgb = np.zeros((H, W, 3), dtype=np.uint8)
    agree = np.zeros((H, W), dtype=np.uint8)
    seen = np.zeros((H, W), dtype=np.uint8)
    for b0 in range(0, H, band_rows):  # blocks of the lattice, each with the tiles over it: the cost
        b1 = min(H, b0 + band_rows)       # grows with the tiles' area, not with the block's width too
        for e0 in range(0, W, band_rows):
            e1 = min(W, e0 + band_rows)
            idx = [k for k, (r0, c0, h, w) in enumerate(offs) if r0 < b1 and r0 + h > b0 and c0 < e1 and c0 + w > e0]
            if not idx:
                continue
            Z = np.full((len(idx), b1 - b0, e1 - e0), np.nan, dtype=np.float32)
            C = np.zeros((len(idx), b1 - b0, e1 - e0, 3), dtype=np.float32)
            tol = np.empty((len(idx), 1, 1), dtype=np.float32)
            for n, k in enumerate(idx):
                r0, c0, h, w = offs[k]
                s0, s1 = max(b0, r0), min(b1, r0 + h)
                t0, t1 = max(e0, c0), min(e1, c0 + w)
                Z[n, s0 - b0:s1 - b0, t0 - e0:t1 - e0] = tiles[k].dsm[s0 - r0:s1 - r0, t0 - c0:t1 - c0]
                C[n, s0 - b0:s1 - b0, t0 - e0:t1 - e0] = tiles[k].rgb[s0 - r0:s1 - r0, t0 - c0:t1 - c0]
                tol[n] = 3.0 * float(sigmas[k]) + 0.5 * cell
            dsm[b0:b1, e0:e1], rgb[b0:b1, e0:e1], agree[b0:b1, e0:e1], seen[b0:b1, e0:e1] = _fuse_band(Z, C, tol)
    rgb[~np.isfinite(dsm)] = 0
    return FusedSurface(dsm, rgb, agree, seen, west, north, cell)


def _fuse_band(Z: NDArray, C: NDArray, tol: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """One band's fusion (:func:`fuse_tiles`) from the pairs' heights ``Z`` (n, h, w),
    colours ``C`` (n, h, w, 3) and tolerances ``tol`` (n, 1, 1): height, colour, agreeing
    and seeing pairs per cell."""
    fin = np.isfinite(Z)
    nseen = fin.sum(axis=0)
    if len(Z) == 1:
        med = Z[0]
    else:  # median of the finite values: NaN sorts last, so take the middle of the first n
        Zs = np.sort(Z, axis=0)
        lo_i = np.maximum(nseen - 1, 0) // 2
        hi_i = np.maximum(nseen, 1) // 2
        med = 0.5 * (np.take_along_axis(Zs, lo_i[None], 0)[0] + np.take_along_axis(Zs, hi_i[None], 0)[0])
    ok = fin & (np.abs(Z - med[None]) <= tol)
    nok = ok.sum(axis=0)
    keep = (nseen == 1) | (nok >= 2)
    wsum = np.where(ok, 1.0, 0.0).astype(np.float32)
    zf = np.where(ok, Z, 0.0).sum(axis=0) / np.maximum(nok, 1)
    cf = (C * wsum[..., None]).sum(axis=0) / np.maximum(nok, 1)[..., None]
    return (np.where(keep & (nok > 0), zf, np.nan), np.clip(np.round(cf), 0, 255).astype(np.uint8),
            np.minimum(nok, 255), np.minimum(nseen, 255))


# -- the survey ---------------------------------------------------------------------------


def _shared_points(P: NDArray, Ti: NDArray, Tj: NDArray, K: NDArray, size: tuple[int, int],
                   margin: float = 0.02) -> NDArray[np.float64]:
    """Sparse points projecting inside both frames (a small margin in), in front of both."""
    w, h = size
    keep = np.ones(len(P), bool)
    for T in (Ti, Tj):
        uv, z = _project(np.linalg.inv(T), K, P)
        keep &= (z > 0) & (uv[:, 0] > margin * w) & (uv[:, 0] < (1 - margin) * w) \
            & (uv[:, 1] > margin * h) & (uv[:, 1] < (1 - margin) * h)
    return P[keep]


#: Runs the dense pairs: ``run_pairs(requests, progress) -> records`` (any order); the
#: CLI passes one on the database jobs' runner (local processes or Dask).
PairRunner = Callable[[list[PairRequest], Callable[[int, int, str], None] | None], list[PairResult]]


def run_pairs_here(reqs: list[PairRequest], progress: Callable[[int, int, str], None] | None = None
                   ) -> list[PairResult]:
    """The dense pairs one after the other in this process."""
    out = []
    for k, r in enumerate(reqs):
        if progress:
            progress(k, len(reqs), f"frames {r.i}-{r.j}")
        out.append(dense_pair(r))
    if progress:
        progress(len(reqs), len(reqs), "done")
    return out


def _in_stage(progress: Callable[[int, int, str], None] | None, stage: str
              ) -> Callable[[int, int, str], None] | None:
    """``progress`` with its labels put in ``stage`` (``"stage: label"``)."""
    if progress is None:
        return None
    return lambda done, total, label="": progress(done, total, f"{stage}: {label}")


def _gps_enu(tags: list[Any] | None) -> tuple[NDArray | None, NDArray | None]:
    """The survey's ENU origin (the first frame's latitude and longitude, height 0) and the
    frames' GPS positions in it; (None, None) without GPS."""
    if tags is None:
        return None, None
    origin = np.array([tags[0].lat_deg, tags[0].lon_deg, 0.0])
    return origin, wgs84_to_enu(np.array([[t.lat_deg, t.lon_deg, t.alt_m] for t in tags]), origin)


def _georeference_model(sfm: Any, tags: list[Any] | None) -> tuple[Georef, dict[int, NDArray], NDArray, Any, Any]:
    """The model in ENU (or levelled, without GPS): the similarity, ``T_enu_cam`` per
    placed frame, the sparse points, the ENU origin (lat, lon, 0) and the GPS positions.
    A model the adjustment already put in ENU (GPS priors, control points) keeps its frame."""
    reg = [k for k, r in enumerate(sfm.registered) if r]
    C_model = np.array([np.linalg.inv(sfm.cam_from_world[k])[:3, 3] for k in reg])
    origin, gps_enu = _gps_enu(tags)
    if getattr(sfm, "frame", "model") == "enu":
        g = sfm.georeferencing
        rms = None if gps_enu is None else float(np.sqrt(np.mean(np.sum((C_model - gps_enu[reg]) ** 2, axis=1))))
        how = (f"bundle adjustment in the local frame on {g.get('aligned_to', '?')}"
               + (f" (GPS a constraint: {g['gps_priors']} positions)" if g.get("gps_priors") else ""))
        geo = Georef(1.0, np.eye(3), np.zeros(3), how, rms)
    else:
        geo = georeference(C_model, None if gps_enu is None else gps_enu[reg], sfm.points)
    T_enu = {k: geo.pose(sfm.cam_from_world[k]) for k in reg}
    return geo, T_enu, geo.apply(sfm.points), origin, gps_enu


def plan_pairs(T_enu: dict[int, NDArray], points_enu: NDArray, K: NDArray, size: tuple[int, int],
               o: SurveyOptions) -> dict[tuple[int, int], NDArray[np.float64]]:
    """The pairs to match, each with the sparse points both frames see: each placed frame
    with the ones ``pair_steps`` later, and (``cross_pairs``) with the later frame beyond
    those sharing most of its view, when it shares a quarter of a typical pair's points."""
    reg = sorted(T_enu)
    shared: dict[tuple[int, int], NDArray[np.float64]] = {}
    for step in o.pair_steps:
        for a in range(len(reg) - step):
            i, j = reg[a], reg[a + step]
            shared[(i, j)] = _shared_points(points_enu, T_enu[i], T_enu[j], K, size)
    if o.cross_pairs and shared:
        floor = 0.25 * float(np.median([len(v) for v in shared.values()]))
        far = max(o.pair_steps)
        for a in range(len(reg)):
            best, best_n = None, floor
            for b in range(a + far + 1, len(reg)):
                sp = _shared_points(points_enu, T_enu[reg[a]], T_enu[reg[b]], K, size)
                if len(sp) > best_n:
                    best, best_n = (reg[b], sp), len(sp)
            if best is not None:
                shared[(reg[a], best[0])] = best[1]
    return shared


def _default_cell(T_enu: dict[int, NDArray], K: NDArray, points_enu: NDArray, factor: int) -> float:
    """Twice the matched frames' ground sample distance at the median depth (at one cell
    per matched pixel, perspective and rotation leave every few cells empty)."""
    depths = [np.median(_project(np.linalg.inv(T), K, points_enu)[1]) for T in T_enu.values()]
    return float(f"{2.0 * float(np.median(depths)) / float(K[0, 0]) * factor:.2g}")


def run_survey(images: Sequence[str | Path], out_dir: str | Path, *, calib: str | Path | None = None,
               gps_table: str | Path | None = None, options: SurveyOptions | None = None,
               progress: Callable[[int, int, str], None] | None = None,
               run_pairs: PairRunner | None = None, video_step_s: float = 1.0, resume: bool = False) -> dict[str, Any]:
    """Survey ``images`` (frames of one camera, in flight order; or one video, sampled
    every ``video_step_s`` into ``OUT/frames/``) into ``out_dir``: poses, a COLMAP model,
    per-pair depth maps, cloud (PLY, LAS), DSM, ground, nDSM and orthophoto (GeoTIFF),
    poses.json and a drawing; all written together or nothing. ``run_pairs`` runs the
    dense pairs (default: here, one after the other). The finished work is kept beside the
    output while it runs; ``resume`` reuses what an interrupted run of the same command
    kept (:mod:`~prism3d.reconstruct.survey.resume`; frames, not a video)."""
    o = SurveyOptions() if options is None else options
    t_all = time.perf_counter()
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not an empty folder; give a new folder for the survey")
    videos = [p for p in images if Path(p).suffix.lower() in VIDEO_SUFFIXES]
    if videos and len(images) > 1:
        raise InputError("survey: give one video, or image frames, not both")
    if not videos:  # checked before anything is written
        frames = _Frames.of(images, gps_table, calib, o.crs, o.gcp_file, o.gcp_check)
    with staged_folder(out) as stage:
        if videos:  # frames into the survey's own folder, then the same checks
            images = [str(p) for p in video_frames(videos[0], stage / "frames", step_s=video_step_s)]
            frames = _Frames.of(images, gps_table, calib, o.crs, o.gcp_file, o.gcp_check)
        cache = ResumeFolder(out, [Path(p) for p in images], None if gps_table is None else Path(gps_table),
                             None if calib is None else Path(calib), o, resume=resume and not videos)
        try:
            free = (o.refine_intrinsics if o.refine_intrinsics != "auto" else "none" if calib else "focal+distortion") != "none"
            summary = _stages(stage, out, [str(p) for p in images], frames, o, bool(videos), free, cache, run_pairs,
                              progress)
            summary["seconds"]["total"] = round(time.perf_counter() - t_all, 2)
            _record(stage / "poses.json", {"seconds": summary["seconds"], "resumed": summary["resumed"],
                                           "absolute_accuracy": summary["absolute_accuracy"]})
        except Exception:
            cache.remove()  # a failure on the input: nothing there is worth keeping
            raise
    cache.remove()
    summary["out_dir"] = str(out)
    return summary


def _without_staged_log(exc: Exception, log: Path) -> Exception:
    """An SfM error that points at COLMAP's log in the staging folder, which goes with the
    failed run: the pointer becomes "-v", and with -v the log's tail goes to the log now."""
    msg = str(exc)
    if str(log) not in msg:
        return exc
    try:
        tail = log.read_text(errors="replace").splitlines()[-40:]
    except OSError:
        tail = []
    if tail:
        _log.info("COLMAP's log, last %d lines:\n%s", len(tail), "\n".join(tail))
    return type(exc)(msg.replace(f"see {log}", "-v shows COLMAP's log"))


def _stages(stage: Path, out: Path, images: list[str], frames: _Frames, o: SurveyOptions, video: bool, free: bool,
            cache: ResumeFolder, run_pairs: PairRunner | None, progress: Callable[[int, int, str], None] | None
            ) -> dict[str, Any]:
    """Poses (intrinsics refined when ``free``), dense pairs, fusion and products into
    ``stage`` (:func:`run_survey`)."""
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    sfm, reused_poses = _poses(stage, images, frames, o, free, cache, progress)
    control, checks = list(frames.control), list(frames.checks)
    seconds["poses"] = time.perf_counter() - t0
    geo, T_enu, points_enu, origin, gps_enu = _georeference_model(sfm, frames.tags)
    if origin is None and frames.origin is not None:  # no GPS: placed by the control points, or not at all
        if sfm.frame != "enu":
            raise InputError("survey: no GPS, and fewer than 3 control points are seen in two placed frames; "
                             "the survey cannot be placed (give GPS, or control points seen in more frames)")
        origin = frames.origin
    gcp_line = None if frames.gcp is None else _gcp_check(stage, frames.gcp, control, checks, sfm, T_enu, points_enu,
                                                           origin, geo)
    absolute = _absolute_accuracy(sfm, geo, T_enu, points_enu, gps_enu, len(control), len(checks))
    factor = _dense_scale(frames.size, o.dense_max_pixels)
    t0 = time.perf_counter()
    reqs = _pair_requests(frames, sfm, T_enu, points_enu, factor, o)
    kept = [cache.finished_pair(r.i, r.j) for r in reqs]
    todo = [replace(r, save_to=str(cache.pair_path(r.i, r.j))) for r, k in zip(reqs, kept) if k is None]
    new = (run_pairs or run_pairs_here)(todo, _in_stage(progress, "dense pairs")) if todo else []
    recs = sorted([k for k in kept if k is not None] + list(new), key=lambda r: (r.i, r.j))
    seconds["dense"] = time.perf_counter() - t0
    ok = [r for r in recs if r.ok]
    if not ok:
        reasons = "; ".join(f"{frames.paths[r.i].name}+{frames.paths[r.j].name}: {r.reason}" for r in recs[:3])
        raise InputError(f"survey: no pair of frames gave depth ({reasons})")
    t0 = time.perf_counter()
    if progress:
        progress(0, 1, f"fusion: {len(ok)} depth maps")
    fused = fuse_tiles([r.tile for r in ok], [r.sigma_z for r in ok])
    seconds["fusion"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    shown = [str(out / "frames" / p.name) for p in frames.paths] if video else list(images)
    summary = write_products(stage, fused, SurveyState(
        frames.paths, shown, sfm, geo, T_enu, recs, origin, gps_enu, frames.gps_source, frames.calib_source,
        _refined(sfm, free, o), factor, o), progress=_in_stage(progress, "products"))
    shutil.copytree(sfm.model_dir, stage / "colmap", dirs_exist_ok=True)
    shutil.rmtree(stage / "sfm_work", ignore_errors=True)
    seconds["products"] = time.perf_counter() - t0
    if gcp_line is not None:
        summary["gcp_check"] = gcp_line
    summary["absolute_accuracy"] = absolute
    summary["seconds"] = {k: round(v, 2) for k, v in seconds.items()}
    summary["resumed"] = {"poses": reused_poses, "pairs_reused": len(reqs) - len(todo), "pairs_matched": len(todo)}
    return summary


def _poses(stage: Path, images: list[str], frames: _Frames, o: SurveyOptions, free: bool, cache: ResumeFolder,
           progress: Callable[[int, int, str], None] | None) -> tuple[Any, bool]:
    """The SfM result (kept from an interrupted run, or computed with the GPS priors and
    control points) and whether it was kept."""
    sfm = cache.load_sfm(stage / "sfm_work" / "colmap.log")
    reused = sfm is not None
    positions = _gps_enu(frames.tags)[1]  # GPS: spatial matching above 40 frames, and priors
    control = list(frames.control)
    if sfm is None:
        work = stage / "sfm_work"
        try:
            sfm = map_frames(images, work, camera=frames.camera,
                             options=SfmOptions(max_image_size=o.max_image_size, refine_focal=free,
                                                refine_distortion=free, refine_principal_point=o.refine_principal_point,
                                                matching=o.matching),
                             progress=_in_stage(progress, "poses"), positions=positions,
                             gps_accuracy=(o.gps_accuracy or "estimate") if o.gps_prior else None,
                             control=control)
        except (InputError, ReconstructionError) as exc:
            raise _without_staged_log(exc, work / "colmap.log") from None
        cache.save_sfm(sfm)
    _warn_self_calibration(sfm.self_calibration)
    used = int(sfm.georeferencing.get("control_points", 0))
    if control and used < len(control):
        _log.warning("survey: %d of %d control points held in the adjustment (the rest are seen in fewer than two "
                     "placed frames%s); gcp_check.json measures them all", used, len(control),
                     "; fewer than 3 left, so none is held" if used == 0 else "")
    return sfm, reused


def _gcp_check(stage: Path, gf: GcpFile, control: list, checks: list, sfm: Any, T_enu: dict[int, NDArray],
               points_enu: NDArray, origin: NDArray, geo: Georef) -> str:
    """``gcp_check.json`` into ``stage`` (every point measured through the final poses);
    returns its one-line summary."""
    K = np.asarray(sfm.K, dtype=np.float64)
    gsd = float(np.median([np.median(_project(np.linalg.inv(T), K, points_enu)[1]) for T in T_enu.values()]) / K[0, 0])
    report = check_points_report(gf, control, checks, T_enu, K, np.asarray(sfm.dist, dtype=np.float64), origin, gsd,
                                 geo.method)
    atomic_write_text(stage / "gcp_check.json", json.dumps(report, indent=1))
    return "; ".join(f"{r} points RMS {report[r]['rms_horizontal_m']:.3f} m horizontal, "
                     f"{report[r]['rms_vertical_m']:.3f} m vertical" for r in ("control", "check") if r in report
                     ) + " (gcp_check.json)"


def _absolute_accuracy(sfm: Any, geo: Georef, T_enu: dict[int, NDArray], points_enu: NDArray,
                       gps_enu: NDArray | None, n_control: int, n_checks: int) -> dict[str, Any]:
    """What the products' absolute placement rests on, and without control points its
    expected error from the GPS (:func:`gps_only_accuracy`; the accuracy the adjustment
    used or estimated, else the positions' residual RMS after the similarity)."""
    if n_control:
        return {"control": f"{n_control} ground control points", "measured": True, "report": "gcp_check.json"}
    if gps_enu is None:
        return {"control": "none and no GPS: scale and position unknown", "measured": False}
    acc = getattr(sfm, "georeferencing", {}).get("gps_accuracy_m")
    if acc is None:
        r = float(geo.residual_rms_m or 0.0)
        acc = [r / math.sqrt(3.0), r / math.sqrt(3.0)]
    C = np.array([T[:3, 3] for T in T_enu.values()])
    out = gps_only_accuracy(C, points_enu, float(acc[0]), float(acc[1]))
    if n_checks:
        out.update(measured=True, report=f"gcp_check.json ({n_checks} check points)")
    return out


def _warn_self_calibration(sc: dict) -> None:
    """A warning when the adjustment refined the focal length but the block cannot
    determine it (a nadir block at one altitude with nothing holding heights from outside)."""
    if not sc or sc.get("determined", True):
        return
    if "error" in sc:
        _log.warning("survey: the focal length's uncertainty could not be estimated (%s)", sc["error"])
        return
    g = sc["geometry"]
    sig = sc["focal_sigma_pct"]
    why = ("nadir frames at one altitude tie it to the flying height, and its formal uncertainty understates that"
           if g["one_direction"] and g["one_altitude"] else "its uncertainty is above 0.5 %")
    _log.warning("survey: the focal length (%.1f px, formal +-%s) is not determined by this block: %s. Give ground "
                 "control points (--gcp) with GPS, a calibration (--calib), or fly oblique or at a second altitude",
                 sc["focal_px"], "inf" if sig is None else f"{sig:.2f} %", why)


def _refined(sfm: Any, free: bool, o: SurveyOptions) -> list[str]:
    """The intrinsics the adjustment refined, by the camera model it kept."""
    out = [] if not free else ["f", "k1", "k2"] if sfm.camera_model == "RADIAL" else ["fx", "fy", "k1", "k2", "p1", "p2"]
    if o.refine_principal_point or sfm.camera_choice.get("principal_point") == "free":
        out += ["cx", "cy"]
    return out


def _record(poses: Path, entries: dict[str, Any]) -> None:
    """Entries added to poses.json (the stages' times, what was resumed: known only after
    it was written)."""
    doc = json.loads(poses.read_text())
    doc.update(entries)
    atomic_write_text(poses, json.dumps(doc, indent=1))


@dataclass(frozen=True)
class _Frames:
    """A survey's checked frames: paths, size (w, h), GPS tags and their source, the
    starting camera and its source."""

    paths: list[Path]
    size: tuple[int, int]
    tags: list[Any] | None
    gps_source: str
    camera: Any
    calib_source: str
    gcp: GcpFile | None = None
    origin: NDArray | None = None  # the local frame's (lat, lon, 0): the first frame's GPS, else the first control point
    control: tuple = ()  # the control and check points in that frame (ControlPoint)
    checks: tuple = ()

    @classmethod
    def of(cls, images: Sequence[str | Path], gps_table: str | Path | None, calib: str | Path | None,
           crs: str | None = None, gcp: str | None = None, gcp_check: Sequence[str] = ()) -> _Frames:
        """The frames checked, that ``crs`` can be given (a CRS needs GPS), and the control
        points (their file, images and check names)."""
        paths, size = check_frames(images)
        tags, gps_source = gps_positions(paths, gps_table)
        gf = None if gcp is None else read_gcp_file(gcp)
        origin = None if tags is None else np.array([tags[0].lat_deg, tags[0].lon_deg, 0.0])
        if origin is None and gf is not None and len(gf.points) > len(set(gcp_check)):
            lla = gf.to_lla(np.array([gf.points[0].xyz]))[0]
            origin = np.array([lla[0], lla[1], 0.0])
        MapFrame.for_site(crs, origin)
        control, checks = ([], []) if gf is None else survey_control(gf, [str(p) for p in paths], origin, gcp_check)
        camera, calib_source = starting_camera(paths, size, calib)
        return cls(list(paths), size, tags, gps_source, camera, calib_source, gf, origin, tuple(control),
                   tuple(checks))


def _pair_requests(frames: _Frames, sfm: Any, T_enu: dict[int, NDArray], points_enu: NDArray, factor: int,
                   o: SurveyOptions) -> list[PairRequest]:
    """The dense pairs to match (:func:`plan_pairs`) as requests on the survey's lattice."""
    K, dist = np.asarray(sfm.K, dtype=np.float64), np.asarray(sfm.dist, dtype=np.float64)
    cell = o.cell_m if o.cell_m is not None else _default_cell(T_enu, K, points_enu, factor)
    return [PairRequest(i, j, str(frames.paths[i]), str(frames.paths[j]), K, dist, factor, T_enu[i], T_enu[j], sp,
                        cell, min_shared=o.min_shared_points, min_base_to_height=o.min_base_to_height,
                        matcher=o.matcher, lk_window=o.lk_window)
            for (i, j), sp in plan_pairs(T_enu, points_enu, K, frames.size, o).items()]
