"""The UAV survey mode: photographs from one moving camera become a georeferenced point
cloud, DSM, orthophoto and normalised DSM (the paper's closing proposal: "the
neighboring images in the sequence form stereo pairs").

Stages (docs/uav.md): poses and refined intrinsics from pycolmap's incremental mapping
(:mod:`prism3d.reconstruct.sfm`); a similarity onto the GPS positions in a local
east-north-up frame (:func:`georeference`); each pair of neighbouring frames, and the
next-but-one, rectified from its poses and matched by our matcher (:func:`dense_pair`,
one independent unit per pair, run in this process or on Dask); the pairs' heights fused
cell by cell with a consistency check (:func:`fuse_tiles`); then the products.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.capture.calib_formats import load_camera_calibration
from prism3d.capture.geotag import exif_focal_px, exif_geotag, read_position_table, wgs84_to_enu
from prism3d.capture.rig import CameraModel
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path, atomic_write_text, staged_folder
from prism3d.io.geo import local_enu_crs_wkt, write_geotiff, write_las
from prism3d.io.images import read_image
from prism3d.io.ply import write_ply
from prism3d.reconstruct.dsm import MAX_CELLS, grid_points, normalised_dsm
from prism3d.reconstruct.flatness import ransac_plane
from prism3d.reconstruct.match_options import MatchOptions
from prism3d.reconstruct.ortho import true_orthophoto
from prism3d.reconstruct.sfm import SfmOptions, map_frames, similarity_align
from prism3d.reconstruct.survey_pair import pair_cloud
from prism3d.reconstruct.two_view import TwoViewPose

__all__ = [
    "SURVEY_SCHEMA_VERSION", "SURVEY_FILES", "Georef", "SurveyOptions", "dense_pair", "fuse_tiles",
    "georeference", "run_survey",
]

SURVEY_SCHEMA_VERSION = 1
#: Files every survey writes (``survey -o OUT``), besides ``colmap/`` and ``depth/``.
SURVEY_FILES = ("poses.json", "cloud.ply", "cloud.las", "dsm.tif", "ndsm.tif", "ground.tif", "ortho.tif",
                "ortho_quality.tif", "survey.png")
#: Disparity noise assumed for a pair's height tolerance, px at the matched scale.
DISPARITY_SIGMA_PX = 0.25


@dataclass(frozen=True)
class SurveyOptions:
    """How a survey is computed (``prism3d survey`` options)."""

    max_image_size: int = 2000
    """Features for the poses on frames downscaled to this side (keypoints stay full-res)."""
    dense_max_pixels: float = 3.2e6
    """Frames are matched at the largest scale (1, 1/2, 1/3...) keeping them under this
    many pixels: dense matching dominates the time and its memory grows with the area."""
    pair_steps: tuple[int, ...] = (1, 2)
    """Pairs: each frame with the next (1) and the next-but-one (2, twice the baseline)."""
    cross_pairs: bool = True
    """Also pair each frame with the frame further along the sequence that shares most of
    its view (the neighbouring flight line): the strips' ends and edges are seen only so."""
    cell_m: float | None = None
    """DSM cell, m (model units without GPS); None: twice the matched frames' ground sample distance."""
    ortho_gsd_m: float | None = None
    """Orthophoto cell, m; None: the photographs' own ground sample distance (the median
    camera height above the ground over the focal length), finer than the DSM's cell."""
    min_shared_points: int = 30
    """A pair needs this many sparse points seen by both frames, else it is skipped (no overlap)."""
    min_base_to_height: float = 0.03
    """A pair whose baseline is below this fraction of its depth is skipped (too short)."""
    refine_intrinsics: str = "auto"
    """What the bundle adjustment refines: "focal+distortion" (f, k1, k2), "none", or
    "auto": none when the start is a calibration file, f, k1 and k2 from EXIF. Nadir
    frames over gentle relief hardly tell the focal length from the flying height (the
    image scale gives only their ratio), so a calibrated camera is best left as it is."""
    refine_principal_point: bool = False
    """Free the principal point in the bundle adjustment (poorly fixed by few nadir frames)."""
    matcher: str = "ours"
    """The dense matcher: ours, or "sgbm" (OpenCV's, the benchmarks' anchor)."""
    lk_window: int = 9
    """Our matcher's sub-pixel (Lucas-Kanade) window, px, with 3 iterations: nadir pairs
    see ground that is flat at the window's scale, and a wider window than the stereo
    default (5) averages more noise (docs/uav.md: on the simulator the DSM's median error
    0.26 -> 0.19 GSD; the real pair's open ground 7.3 -> 5.3 cm rough)."""

    def __post_init__(self) -> None:
        if isinstance(self.max_image_size, bool) or not 320 <= int(self.max_image_size) <= 20000:
            raise InputError(f"max_image_size: expected 320-20000 px, got {self.max_image_size!r}")
        if not (math.isfinite(self.dense_max_pixels) and self.dense_max_pixels >= 1e4):
            raise InputError(f"dense_max_pixels: expected >= 10000, got {self.dense_max_pixels!r}")
        steps = tuple(int(s) for s in self.pair_steps)
        if not steps or any(s < 1 or s > 10 for s in steps) or len(set(steps)) != len(steps):
            raise InputError(f"pair_steps: expected distinct steps in 1-10, got {self.pair_steps!r}")
        object.__setattr__(self, "pair_steps", steps)
        if self.cell_m is not None and not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise InputError(f"cell: expected a DSM cell size > 0, got {self.cell_m!r}")
        if self.ortho_gsd_m is not None and not (math.isfinite(self.ortho_gsd_m) and self.ortho_gsd_m > 0):
            raise InputError(f"ortho-gsd: expected an orthophoto cell > 0, got {self.ortho_gsd_m!r}")
        if isinstance(self.lk_window, bool) or int(self.lk_window) != self.lk_window or self.lk_window < 3 \
                or self.lk_window % 2 == 0:
            raise InputError(f"lk_window: expected an odd integer >= 3, got {self.lk_window!r}")
        if self.matcher not in ("ours", "sgbm"):
            raise InputError(f"matcher: expected ours or sgbm, got {self.matcher!r}")
        if self.refine_intrinsics not in ("auto", "focal+distortion", "none"):
            raise InputError(f"refine_intrinsics: expected auto, focal+distortion or none, got {self.refine_intrinsics!r}")


# -- georeferencing ----------------------------------------------------------------------
@dataclass(frozen=True)
class Georef:
    """``x_enu = s R x_model + t``; ``method`` says how it was found, ``residual_rms_m``
    the camera centres' RMS distance to their GPS positions after it (None without GPS)."""

    s: float
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    method: str
    residual_rms_m: float | None

    def apply(self, P: NDArray) -> NDArray[np.float64]:
        return self.s * np.asarray(P, dtype=np.float64) @ self.R.T + self.t

    def pose(self, cam_from_model: NDArray) -> NDArray[np.float64]:
        """``T_enu_cam`` (4, 4) of a camera given ``cam_from_model`` (4, 4)."""
        T = np.linalg.inv(np.asarray(cam_from_model, dtype=np.float64))  # model <- cam
        out = np.eye(4)
        out[:3, :3] = self.R @ T[:3, :3]
        out[:3, 3] = self.apply(T[:3, 3])
        return out


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
    if len(C) >= 3 and sv[1] > 0.05 * sv[0]:

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


def _load_frame(path: str, K: NDArray, dist: NDArray, factor: int) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """A frame undistorted onto ``K`` and area-downscaled by ``factor``: the image and its K."""


    img = read_image(path)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = np.ascontiguousarray(img[..., :3])
    if np.any(np.asarray(dist) != 0):
        img = cv2.undistort(img, K, np.asarray(dist, dtype=np.float64))
    Ks = np.asarray(K, dtype=np.float64).copy()
    if factor > 1:
        h, w = img.shape[:2]
        img = cv2.resize(img, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
        Ks[:2] /= factor
        Ks[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
        Ks[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return img, Ks


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


def dense_pair(req: dict[str, Any]) -> dict[str, Any]:
    """One pair's dense heights: frames ``i`` and ``j`` (paths, shared ``K``/``dist``,
    ``T_enu_cam``) undistorted and downscaled by ``factor``, rectified from their poses,
    matched over the disparity range of the sparse points both see (``shared`` ENU
    points), triangulated in ENU and gridded on the survey's lattice (``cell``). Returns
    the pair's record (status "ok" or "skipped" with a reason) and, when ok, its tile
    (per-cell median height, point count, mean colour) and camera i's depth map. A pair
    that cannot be a stereo pair is skipped, never raised: other pairs carry on."""
    t0 = time.perf_counter()
    i, j = int(req["i"]), int(req["j"])
    rec: dict[str, Any] = {"i": i, "j": j, "status": "skipped", "reason": None}
    Ti, Tj = np.asarray(req["T_enu_cam_i"]), np.asarray(req["T_enu_cam_j"])
    ci, cj = Ti[:3, 3], Tj[:3, 3]
    base = float(np.linalg.norm(cj - ci))
    rec["baseline"] = base
    P = np.asarray(req["shared"], dtype=np.float64)
    if len(P) < int(req["min_shared"]):
        rec["reason"] = f"no overlap ({len(P)} shared sparse points)"
        return rec
    Tci, Tcj = np.linalg.inv(Ti), np.linalg.inv(Tj)
    K, dist, factor = np.asarray(req["K"]), np.asarray(req["dist"]), int(req["factor"])
    img_i, Ks = _load_frame(req["path_i"], K, dist, factor)
    img_j, _ = _load_frame(req["path_j"], K, dist, factor)
    q1, zi = _project(Tci, Ks, P)
    q2, _ = _project(Tcj, Ks, P)
    zmed = float(np.median(zi))
    rec["depth_median"] = zmed
    if base < float(req["min_base_to_height"]) * zmed:
        rec["reason"] = f"baseline {base:.3g} is under {req['min_base_to_height']:g} of the depth {zmed:.3g}"
        return rec
    R = Tcj[:3, :3] @ Ti[:3, :3]
    t = Tcj[:3, :3] @ ci + Tcj[:3, 3]
    pose = TwoViewPose(R, t / np.linalg.norm(t), q1, q2, len(P), 0.0)
    try:

        lk = int(req.get("lk_window", 5))
        pc = pair_cloud(img_i, img_j, Ks, pose, baseline=base, matcher=req.get("matcher", "ours"),
                        options=MatchOptions(lk_window=lk, lk_iters=3 if lk > 5 else 1))
    except InputError as exc:
        rec["reason"] = str(exc).removeprefix("pair: ")
        return rec
    except Exception as exc:  # noqa: BLE001 - the matcher finding nothing is a skipped pair
        rec["reason"] = f"matching failed ({type(exc).__name__}: {exc})"
        return rec
    Pe = pc.points @ Ti[:3, :3].T + ci
    cell = float(req["cell"])
    if len(Pe) < 100:
        rec["reason"] = f"matching kept {len(Pe)} points"
        return rec
    g = grid_points(Pe, pc.colours, cell, bounds=_tile_bounds(Pe, cell))
    # camera i's depth map at the matched scale (nearest surface per pixel)
    h, w = img_i.shape[:2]
    Z = pc.points[:, 2]
    u = np.round(pc.points[:, 0] / Z * Ks[0, 0] + Ks[0, 2]).astype(np.int64)
    v = np.round(pc.points[:, 1] / Z * Ks[1, 1] + Ks[1, 2]).astype(np.int64)
    ok = (Z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full((h, w), np.nan, dtype=np.float32)
    order = np.argsort(-Z[ok])
    depth[v[ok][order], u[ok][order]] = Z[ok][order]
    rec.update(status="ok", reason=None, n_points=int(len(Pe)), valid_fraction=round(pc.valid_fraction, 4),
               disparity_range=list(pc.disparity_range),
               sigma_z=float(zmed**2 / (Ks[0, 0] * base) * DISPARITY_SIGMA_PX),
               seconds=round(time.perf_counter() - t0, 3))
    rec["tile"] = {"west": g.west, "north": g.north, "cell": g.gsd, "dsm": g.dsm, "count": g.count,
                   "rgb": g.ortho[..., :3]}
    rec["depth"] = depth
    rec["K_depth"] = Ks.tolist()
    return rec


# -- fusion ------------------------------------------------------------------------------
@dataclass(frozen=True)
class FusedSurface:
    """The fused DSM (H, W) float32 (NaN: no consistent height), its colour (H, W, 3)
    uint8, per-cell number of agreeing pairs and of pairs seen, north-west corner, cell."""

    dsm: NDArray[np.float32]
    rgb: NDArray[np.uint8]
    agree: NDArray[np.uint8]
    seen: NDArray[np.uint8]
    west: float
    north: float
    cell: float


def fuse_tiles(tiles: Sequence[dict[str, Any]], sigmas: Sequence[float], *, band_rows: int = 512) -> FusedSurface:
    """Fuse pairs' height tiles on one lattice: per cell the median of the pairs'
    heights; a pair agrees when within ``3 sigma + cell/2`` of it (``sigma`` its
    expected height noise); cells seen by two or more pairs keep the mean of those that
    agree when at least two do (else no height: the pairs contradict each other); cells
    only one pair saw keep its height. Processed in bands of rows (memory ~ one band)."""
    if not tiles:
        raise InputError("fusion: no pair produced heights")
    cell = float(tiles[0]["cell"])
    west = min(float(t["west"]) for t in tiles)
    north = max(float(t["north"]) for t in tiles)
    offs = []
    H = W = 0
    for t in tiles:
        c0 = int(round((float(t["west"]) - west) / cell))
        r0 = int(round((north - float(t["north"])) / cell))
        h, w = t["dsm"].shape
        offs.append((r0, c0, h, w))
        H, W = max(H, r0 + h), max(W, c0 + w)

    if H * W > MAX_CELLS:
        raise InputError(f"fusion: {W} x {H} cells is over the {MAX_CELLS:,} budget; give a larger cell")
    dsm = np.full((H, W), np.nan, dtype=np.float32)
    rgb = np.zeros((H, W, 3), dtype=np.uint8)
    agree = np.zeros((H, W), dtype=np.uint8)
    seen = np.zeros((H, W), dtype=np.uint8)
    for b0 in range(0, H, band_rows):
        b1 = min(H, b0 + band_rows)
        idx = [k for k, (r0, _, h, _) in enumerate(offs) if r0 < b1 and r0 + h > b0]
        if not idx:
            continue
        Z = np.full((len(idx), b1 - b0, W), np.nan, dtype=np.float32)
        C = np.zeros((len(idx), b1 - b0, W, 3), dtype=np.float32)
        tol = np.empty((len(idx), 1, 1), dtype=np.float32)
        for n, k in enumerate(idx):
            r0, c0, h, w = offs[k]
            s0, s1 = max(b0, r0), min(b1, r0 + h)
            Z[n, s0 - b0:s1 - b0, c0:c0 + w] = tiles[k]["dsm"][s0 - r0:s1 - r0]
            C[n, s0 - b0:s1 - b0, c0:c0 + w] = tiles[k]["rgb"][s0 - r0:s1 - r0]
            tol[n] = 3.0 * float(sigmas[k]) + 0.5 * cell
        fin = np.isfinite(Z)
        nseen = fin.sum(axis=0)
        if len(idx) == 1:
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
        dsm[b0:b1] = np.where(keep & (nok > 0), zf, np.nan)
        rgb[b0:b1] = np.clip(np.round(cf), 0, 255).astype(np.uint8)
        agree[b0:b1] = np.minimum(nok, 255)
        seen[b0:b1] = np.minimum(nseen, 255)
    rgb[~np.isfinite(dsm)] = 0
    return FusedSurface(dsm, rgb, agree, seen, west, north, cell)


# -- the survey ---------------------------------------------------------------------------
def _image_sizes(paths: Sequence[Path]) -> list[tuple[int, int]]:
    from PIL import Image, UnidentifiedImageError

    sizes = []
    for p in paths:
        if p.is_dir():
            raise InputError(f"{p}: is a folder; give the frames themselves (e.g. {p}/*.JPG)")
        if not p.is_file():
            raise InputError(f"{p}: image not found")
        try:
            with Image.open(p) as im:
                sizes.append(im.size)
        except (UnidentifiedImageError, OSError) as exc:
            raise InputError(f"{p}: not an image this tool can read ({exc})") from None
    return sizes


#: Inputs read as videos (frames taken every ``video_step_s``).
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v")


def video_frames(video: str | Path, folder: Path, *, step_s: float = 1.0, max_frames: int = 500) -> list[Path]:
    """Frames of a video every ``step_s`` seconds (by its frame rate; every frame when it
    states none) written as JPEGs into ``folder``: the survey's frames. A video without
    two readable frames is refused."""
    v = Path(video)
    if not v.is_file():
        raise InputError(f"{v}: video not found")
    if not (math.isfinite(step_s) and step_s > 0):
        raise InputError(f"video step: expected seconds > 0, got {step_s}")
    cap = cv2.VideoCapture(str(v))
    try:
        if not cap.isOpened():
            raise InputError(f"{v}: cannot open as a video (unknown container or codec)")
        fps = cap.get(cv2.CAP_PROP_FPS)
        every = max(1, int(round(step_s * fps))) if fps and math.isfinite(fps) and fps > 0 else 1
        folder.mkdir(parents=True, exist_ok=True)
        out, k = [], 0
        while len(out) < max_frames:
            ok, img = cap.read()
            if not ok:
                break
            if k % every == 0:
                p = folder / f"{v.stem}_{k:06d}.jpg"
                if not cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 95]):
                    raise InputError(f"{p}: cannot write the frame")
                out.append(p)
            k += 1
    finally:
        cap.release()
    if len(out) < 2:
        raise InputError(f"{v}: {len(out)} frame(s) read every {step_s:g} s; a survey needs at least 2")
    return out


def check_frames(images: Sequence[str | Path]) -> tuple[list[Path], tuple[int, int]]:
    """The frames as paths and their common (width, height); one-line errors for fewer
    than two frames, a missing or unreadable one, a repeated one, or different sizes."""
    paths = [Path(p) for p in images]
    if len(paths) < 2:
        raise InputError(f"survey: {len(paths)} frame(s) given; a survey needs at least 2 overlapping frames")
    names = [p.name for p in paths]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"survey: frames named {', '.join(dup[:3])} more than once; names identify frames")
    sizes = _image_sizes(paths)
    for p, s in zip(paths[1:], sizes[1:]):
        if s != sizes[0]:
            raise InputError(f"survey: frames of different sizes: {paths[0].name} is {sizes[0][0]}x{sizes[0][1]}, "
                             f"{p.name} is {s[0]}x{s[1]}; one camera at one setting is needed")
    return paths, sizes[0]


def _gps_positions(paths: Sequence[Path], gps_table: str | Path | None) -> tuple[list[Any] | None, str]:
    """GeoTags per frame from a position table (every frame must be in it, and every
    image the table names must exist), else from EXIF when every frame has it."""
    if gps_table is not None:
        folders = {p.resolve().parent for p in paths}
        table = read_position_table(gps_table, images_dir=folders.pop() if len(folders) == 1 else None)
        if len({p.parent for p in paths}) > 1:
            given = {p.name for p in paths}
            absent = [n for n in table if n not in given]
            if absent:
                raise InputError(f"{gps_table}: names {len(absent)} image(s) not among the frames: "
                                 f"{', '.join(absent[:5])}")
        missing = [p.name for p in paths if p.name not in table]
        if missing:
            raise InputError(f"{gps_table}: no position for {', '.join(missing[:5])}"
                             + (" ..." if len(missing) > 5 else ""))
        return [table[p.name] for p in paths], f"table {Path(gps_table).name}"
    tags = [exif_geotag(p) for p in paths]
    if all(t is not None for t in tags):
        return tags, "EXIF"
    return None, "none"


def _starting_camera(paths: Sequence[Path], size: tuple[int, int], calib: str | Path | None):
    """The starting calibration: a camera YAML, else the EXIF focal length."""
    if calib is not None:
        return load_camera_calibration(calib, image_size=size), "calibration file"
    f = exif_focal_px(paths[0])
    if f is None:
        raise InputError("survey: no starting calibration: give --calib or frames whose EXIF has the focal "
                         "length and focal-plane resolution")
    w, h = size
    K = np.array([[f, 0, (w - 1) / 2.0], [0, f, (h - 1) / 2.0], [0, 0, 1.0]])
    return CameraModel(K, np.zeros(5), size), "EXIF focal length"


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
PairRunner = Callable[[list[dict[str, Any]], Callable[[int, int, str], None] | None], list[dict[str, Any]]]


def run_pairs_here(reqs: list[dict[str, Any]], progress: Callable[[int, int, str], None] | None = None
                   ) -> list[dict[str, Any]]:
    """The dense pairs one after the other in this process."""
    out = []
    for k, r in enumerate(reqs):
        if progress:
            progress(k, len(reqs), f"pair {r['i']}-{r['j']}")
        out.append(dense_pair(r))
    if progress:
        progress(len(reqs), len(reqs), "pairs")
    return out


def _georeference_model(sfm: Any, tags: list[Any] | None) -> tuple[Georef, dict[int, NDArray], NDArray, Any, Any]:
    """The model in ENU (or levelled, without GPS): the similarity, ``T_enu_cam`` per
    placed frame, the sparse points, the ENU origin (lat, lon, 0) and the GPS positions."""
    reg = [k for k, r in enumerate(sfm.registered) if r]
    C_model = np.array([np.linalg.inv(sfm.cam_from_world[k])[:3, 3] for k in reg])
    origin = gps_enu = None
    if tags is not None:

        origin = np.array([tags[0].lat_deg, tags[0].lon_deg, 0.0])
        gps_enu = wgs84_to_enu(np.array([[t.lat_deg, t.lon_deg, t.alt_m] for t in tags]), origin)
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
               run_pairs: PairRunner | None = None, video_step_s: float = 1.0) -> dict[str, Any]:
    """Survey ``images`` (frames of one camera, in flight order; or one video, sampled
    every ``video_step_s`` into ``OUT/frames/``) into ``out_dir``: poses, a COLMAP model,
    per-pair depth maps, cloud (PLY, LAS), DSM, ground, nDSM and orthophoto (GeoTIFF),
    poses.json and a drawing; all written together or nothing. ``run_pairs`` runs the
    dense pairs (default: here, one after the other)."""


    o = SurveyOptions() if options is None else options
    t_all = time.perf_counter()
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not an empty folder; give a new folder for the survey")
    videos = [p for p in images if Path(p).suffix.lower() in VIDEO_SUFFIXES]
    if videos and len(images) > 1:
        raise InputError("survey: give one video, or image frames, not both")
    if not videos:
        paths, size = check_frames(images)
        tags, gps_source = _gps_positions(paths, gps_table)
        camera0, calib_source = _starting_camera(paths, size, calib)
    refine = o.refine_intrinsics if o.refine_intrinsics != "auto" else ("none" if calib else "focal+distortion")
    free = refine != "none"
    seconds: dict[str, float] = {}
    with staged_folder(out) as stage:
        if videos:  # frames into the survey's own folder, then the same checks
            images = [str(p) for p in video_frames(videos[0], stage / "frames", step_s=video_step_s)]
            paths, size = check_frames(images)
            tags, gps_source = _gps_positions(paths, gps_table)
            camera0, calib_source = _starting_camera(paths, size, calib)
        t0 = time.perf_counter()
        sfm = map_frames([str(p) for p in images], stage / "sfm_work", camera=camera0,
                         options=SfmOptions(max_image_size=o.max_image_size, refine_focal=free, refine_distortion=free,
                                            refine_principal_point=o.refine_principal_point),
                         progress=progress)
        seconds["poses"] = time.perf_counter() - t0
        geo, T_enu, points_enu, origin, gps_enu = _georeference_model(sfm, tags)
        K, dist = np.asarray(sfm.K, dtype=np.float64), np.asarray(sfm.dist, dtype=np.float64)
        factor = _dense_scale(size, o.dense_max_pixels)
        cell = o.cell_m if o.cell_m is not None else _default_cell(T_enu, K, points_enu, factor)
        t0 = time.perf_counter()
        reqs = [{"i": i, "j": j, "path_i": str(paths[i]), "path_j": str(paths[j]), "K": K.tolist(),
                 "dist": dist.tolist(), "factor": factor, "T_enu_cam_i": T_enu[i].tolist(),
                 "T_enu_cam_j": T_enu[j].tolist(), "cell": cell, "min_shared": o.min_shared_points,
                 "min_base_to_height": o.min_base_to_height, "shared": sp, "matcher": o.matcher,
                 "lk_window": o.lk_window}
                for (i, j), sp in plan_pairs(T_enu, points_enu, K, size, o).items()]
        recs = sorted((run_pairs or run_pairs_here)(reqs, progress), key=lambda r: (r["i"], r["j"]))
        seconds["dense"] = time.perf_counter() - t0
        ok = [r for r in recs if r["status"] == "ok"]
        if not ok:
            reasons = "; ".join(f"{paths[r['i']].name}+{paths[r['j']].name}: {r['reason']}" for r in recs[:3])
            raise InputError(f"survey: no pair of frames gave depth ({reasons})")
        t0 = time.perf_counter()
        fused = fuse_tiles([r["tile"] for r in ok], [r["sigma_z"] for r in ok])
        seconds["fusion"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        refined = (["f", "k1", "k2"] if free else []) + (["cx", "cy"] if o.refine_principal_point else [])
        shown = [str(out / "frames" / p.name) for p in paths] if videos else [str(p) for p in images]
        summary = _write_products(stage, fused, paths, shown, sfm, geo, T_enu, recs, origin, gps_enu, gps_source,
                                  calib_source, refined, factor, o)
        shutil.copytree(sfm.model_dir, stage / "colmap", dirs_exist_ok=True)
        shutil.rmtree(stage / "sfm_work", ignore_errors=True)
        seconds["products"] = time.perf_counter() - t0
        seconds["total"] = time.perf_counter() - t_all
        summary["seconds"] = {k: round(v, 2) for k, v in seconds.items()}
        doc = json.loads((stage / "poses.json").read_text())
        doc["seconds"] = summary["seconds"]
        atomic_write_text(stage / "poses.json", json.dumps(doc, indent=1))
    summary["out_dir"] = str(out)
    return summary


def _write_products(stage: Path, fused: FusedSurface, paths: Sequence[Path], shown: Sequence[str], sfm: Any, geo: Georef,
                    T_enu: dict[int, NDArray], recs: list[dict], origin: NDArray | None, gps_enu: NDArray | None,
                    gps_source: str, calib_source: str, refined: list[str], factor: int,
                    o: SurveyOptions) -> dict[str, Any]:

    scaled = origin is not None
    crs = local_enu_crs_wkt(float(origin[0]), float(origin[1])) if scaled else None
    tags = {"SCALE": "gps" if scaled else "unknown", "SOFTWARE": "prism3d survey",
            "HEIGHTS": "metres above the WGS84 ellipsoid" if scaled else "model units, frame levelled on the ground"}
    cell = fused.cell
    ground, ndsm = normalised_dsm(fused.dsm * (1000.0 if scaled else 1.0), cell * (1000.0 if scaled else 1.0))
    if scaled:
        ground, ndsm = ground / 1000.0, ndsm / 1000.0
    common = dict(west=fused.west, north=fused.north, gsd=cell, crs_wkt=crs, tags=tags)
    write_geotiff(stage / "dsm.tif", fused.dsm, nodata=float("nan"), band_names=["height"], **common)
    write_geotiff(stage / "ground.tif", ground.astype(np.float32), nodata=float("nan"), band_names=["ground"], **common)
    write_geotiff(stage / "ndsm.tif", ndsm.astype(np.float32), nodata=float("nan"),
                  band_names=["height above ground"], **common)
    ortho = true_orthophoto(fused.dsm, fused.west, fused.north, cell,
                            [(str(paths[k]), T_enu[k]) for k in sorted(T_enu)], np.asarray(sfm.K, dtype=np.float64),
                            np.asarray(sfm.dist, dtype=np.float64), tuple(sfm.size), gsd=o.ortho_gsd_m)
    ocommon = dict(common, gsd=ortho.gsd)
    write_geotiff(stage / "ortho.tif", ortho.rgba, **ocommon)
    write_geotiff(stage / "ortho_quality.tif", ortho.quality, nodata=0, band_names=[
        "1 measured surface, 2 interpolated surface"], **ocommon)
    rr, cc = np.nonzero(np.isfinite(fused.dsm))
    xyz = np.c_[fused.west + (cc + 0.5) * cell, fused.north - (rr + 0.5) * cell, fused.dsm[rr, cc]]
    col = fused.rgb[rr, cc]
    write_ply(stage / "cloud.ply", xyz, colors=col, double=True,
              comments=[f"prism3d survey: fused surface, one point per {cell:g} cell",
                        "frame: local east-north-up, metres" if scaled else "frame: model, scale unknown"])
    write_las(stage / "cloud.las", xyz, col, crs_wkt=crs, scale_m=min(0.001, cell / 100.0),
              system_identifier="prism3d survey" if scaled else "prism3d survey: scale unknown")
    depth_dir = stage / "depth"
    depth_dir.mkdir()
    finite = np.isfinite(fused.dsm)
    per_pair, overlap_filled = overlap_coverage(recs, T_enu, np.asarray(sfm.K, dtype=np.float64), sfm.size,
                                                float(np.nanmedian(ground)), fused)
    pairs = []
    for r in recs:
        entry = {k: v for k, v in r.items() if k not in ("tile", "depth", "K_depth")}
        entry["frames"] = [shown[r["i"]], shown[r["j"]]]
        if (r["i"], r["j"]) in per_pair:
            entry["overlap_filled_fraction"] = per_pair[(r["i"], r["j"])]
        if r["status"] == "ok":
            name = f"{paths[r['i']].stem}__{paths[r['j']].stem}.npz"
            np.savez_compressed(depth_dir / name, depth=r["depth"], K=np.asarray(r["K_depth"]),
                                T_enu_cam=T_enu[r["i"]])
            entry["depth_map"] = f"depth/{name}"
        pairs.append(entry)
    frames = []
    for k, p in enumerate(paths):
        fr: dict[str, Any] = {"image": shown[k], "colmap_name": sfm.model_names[k], "registered": bool(sfm.registered[k]),
                              "T_enu_cam": T_enu[k].tolist() if k in T_enu else None}
        if gps_enu is not None:
            fr["gps_enu"] = [float(v) for v in gps_enu[k]]
            if k in T_enu:
                fr["gps_residual_m"] = float(np.linalg.norm(T_enu[k][:3, 3] - gps_enu[k]))
        frames.append(fr)
    doc = {
        "schema_version": SURVEY_SCHEMA_VERSION,
        "frames": frames,
        "reprojection_rms_px": float(sfm.reprojection_rms_px),
        "n_observations": int(sfm.n_observations),
        "n_sparse_points": int(len(sfm.points)),
        "scale": "gps" if scaled else "unknown",
        "units": "m" if scaled else "model units (scale unknown)",
        "frame": ("local east-north-up at the origin (x east, y north, z up; heights above the WGS84 "
                  "ellipsoid); T_enu_cam maps OpenCV camera coordinates (x right, y down, z forward)")
        if scaled else "the model levelled on its ground (z up), camera 1 above the origin; scale unknown",
        "origin_lla": None if origin is None else [float(v) for v in origin],
        "crs_wkt": crs,
        "gps_source": gps_source,
        "georeference": {"method": geo.method, "scale": geo.s, "residual_rms_m": geo.residual_rms_m},
        "camera": {"model": "RADIAL (f, cx, cy, k1, k2)", "start": calib_source, "refined": refined,
                   "K": np.asarray(sfm.K).tolist(),
                   "dist": np.asarray(sfm.dist).tolist(), "size": list(sfm.size)},
        "dense": {"downscale": factor, "pair_steps": list(o.pair_steps), "pairs": pairs},
        "ortho": {"gsd": ortho.gsd, "shape": list(ortho.rgba.shape[:2]),
                  "cells_per_frame": {shown[k]: v for k, v in sorted(ortho.cells_per_frame.items())},
                  "interpolated_surface_fraction": float((ortho.quality == 2).sum() / max(1, (ortho.quality > 0).sum()))},
        "dsm": {"cell": cell, "west": fused.west, "north": fused.north, "shape": list(fused.dsm.shape),
                "filled_cells": int(finite.sum()), "cells_seen_by_2_or_more_pairs": int((fused.seen >= 2).sum()),
                "overlap_filled_fraction": overlap_filled},
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(o).items()},
    }
    atomic_write_text(stage / "poses.json", json.dumps(doc, indent=1))
    _draw_survey(stage / "survey.png", fused, ndsm, T_enu, scaled)
    n_ok = sum(r["status"] == "ok" for r in recs)
    return {"n_frames": len(paths), "n_registered": int(sum(sfm.registered)),
            "reprojection_rms_px": float(sfm.reprojection_rms_px), "scale": doc["scale"],
            "pairs_ok": n_ok, "pairs_skipped": len(recs) - n_ok, "cell": cell, "dsm_cells": int(finite.sum()),
            "overlap_filled_fraction": doc["dsm"]["overlap_filled_fraction"]}


def overlap_coverage(recs: Sequence[dict], T_enu: dict[int, NDArray], K: NDArray, size: tuple[int, int],
                     ground_z: float, fused: FusedSurface) -> tuple[dict[tuple[int, int], float], float]:
    """The share of each pair's ground overlap (the two frames' footprints on the plane
    ``z = ground_z`` intersected) holding a fused height, and of the union of those
    overlaps; on the DSM's lattice widened to hold every footprint whole."""
    cell = fused.cell
    finite = np.isfinite(fused.dsm)
    quads = {(r["i"], r["j"]): [footprint(T_enu[r["i"]], K, size, ground_z), footprint(T_enu[r["j"]], K, size, ground_z)]
             for r in recs if r["i"] in T_enu and r["j"] in T_enu}
    if not quads:
        return {}, 0.0
    allq = np.concatenate([np.concatenate(q) for q in quads.values()])
    pad_w = max(0, int(math.ceil((fused.west - allq[:, 0].min()) / cell)))
    pad_n = max(0, int(math.ceil((allq[:, 1].max() - fused.north) / cell)))
    H0, W0 = finite.shape
    Hc = max(H0 + pad_n, int(math.ceil((fused.north + pad_n * cell - allq[:, 1].min()) / cell)))
    Wc = max(W0 + pad_w, int(math.ceil((allq[:, 0].max() - fused.west + pad_w * cell) / cell)))
    if Hc * Wc > 800_000_000:
        raise InputError("survey: the frames' footprints are far larger than the DSM; poses or GPS are wrong")
    filled = np.zeros((Hc, Wc), bool)
    filled[pad_n:pad_n + H0, pad_w:pad_w + W0] = finite
    union = np.zeros((Hc, Wc), bool)
    per_pair = {}
    for key, q in quads.items():
        m = overlap_mask(q, (Hc, Wc), fused.west - pad_w * cell, fused.north + pad_n * cell, cell)
        union |= m
        per_pair[key] = round(float(filled[m].mean()) if m.any() else 0.0, 4)
    return per_pair, round(float(filled[union].mean()) if union.any() else 0.0, 4)


def footprint(T_enu_cam: NDArray, K: NDArray, size: tuple[int, int], ground_z: float) -> NDArray[np.float64]:
    """The frame's corners (4, 2) on the horizontal plane ``z = ground_z`` (east, north)."""
    w, h = size
    uv = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
    rays = np.c_[(uv - [K[0, 2], K[1, 2]]) / [K[0, 0], K[1, 1]], np.ones(4)] @ T_enu_cam[:3, :3].T
    c = T_enu_cam[:3, 3]
    if np.any(rays[:, 2] >= 0):
        raise InputError("survey: a frame's corner looks above the horizon; not a nadir survey")
    s = (ground_z - c[2]) / rays[:, 2]
    return c[:2] + s[:, None] * rays[:, :2]


def overlap_mask(quads: Sequence[NDArray], shape: tuple[int, int], west: float, north: float,
                 cell: float) -> NDArray[np.bool_]:
    """Cells of a (H, W) grid inside the intersection of convex ground quads (n, 4, 2)."""
    poly = np.asarray(quads[0], dtype=np.float32)
    for q in quads[1:]:
        area, inter = cv2.intersectConvexConvex(poly, np.asarray(q, dtype=np.float32))
        if area <= 0 or inter is None:
            return np.zeros(shape, bool)
        poly = inter.reshape(-1, 2)
    px = np.c_[(poly[:, 0] - west) / cell - 0.5, (north - poly[:, 1]) / cell - 0.5]
    m = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(m, np.round(px * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def _draw_survey(path: Path, fused: FusedSurface, ndsm: NDArray, T_enu: dict[int, NDArray], scaled: bool) -> None:
    """The orthophoto, the DSM (hill-shaded) and the nDSM side by side, cameras marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    unit = "m" if scaled else "units"
    H, W = fused.dsm.shape
    ext = (fused.west, fused.west + W * fused.cell, fused.north - H * fused.cell, fused.north)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), constrained_layout=True)
    rgba = np.dstack([fused.rgb, np.where(np.isfinite(fused.dsm), 255, 0).astype(np.uint8)])
    axes[0].imshow(rgba, extent=ext)
    axes[0].set_title("orthophoto")
    d = np.where(np.isfinite(fused.dsm), fused.dsm, np.nanmedian(fused.dsm))
    gy, gx = np.gradient(d, fused.cell)
    shade = np.clip(0.5 + 0.5 * (-gx - gy) / np.sqrt(1 + gx**2 + gy**2), 0, 1)
    lo, hi = (np.nanpercentile(fused.dsm, [1, 99]) if np.isfinite(fused.dsm).any() else (0.0, 1.0))
    im = axes[1].imshow(np.where(np.isfinite(fused.dsm), fused.dsm, np.nan), extent=ext, cmap="terrain",
                        vmin=lo, vmax=max(hi, lo + 1e-6))
    axes[1].imshow(np.where(np.isfinite(fused.dsm), shade, np.nan), extent=ext, cmap="gray", alpha=0.35)
    fig.colorbar(im, ax=axes[1], shrink=0.8, label=f"height ({unit})")
    axes[1].set_title("DSM")
    lim = float(np.nanpercentile(ndsm, 99.5)) if np.isfinite(ndsm).any() else 1.0
    im2 = axes[2].imshow(ndsm, extent=ext, cmap="magma", vmin=0, vmax=max(lim, 1e-6))
    fig.colorbar(im2, ax=axes[2], shrink=0.8, label=f"above ground ({unit})")
    axes[2].set_title("normalised DSM")
    C = np.array([T[:3, 3] for T in T_enu.values()])
    for ax in axes:
        ax.plot(C[:, 0], C[:, 1], "c.-", ms=6, lw=0.8)
        ax.set_xlabel(f"east ({unit})")
    axes[0].set_ylabel(f"north ({unit})")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
