"""One shot to one scan: split, rectify, match, triangulate (``prism3d reconstruct``)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import Rectification, StereoRig, compute_rectification
from prism3d.checks import check_array, check_choice
from prism3d.errors import InputError
from prism3d.progress import ProgressFn, null_progress
from prism3d.reconstruct.meshing import mesh_from_grid, smooth_depth
from prism3d.reconstruct.triangulate import Scan, scan_from_depth

if TYPE_CHECKING:
    from prism3d.reconstruct.rectify import RectifyMaps

__all__ = [
    "Reconstruction",
    "convergence_distance_mm",
    "disparity_range",
    "inside_silhouette",
    "lit_mask",
    "local_contrast",
    "reconstruct_shot",
    "reconstruct_to_files",
]


def convergence_distance_mm(rig: StereoRig) -> float | None:
    """Distance (along the left optical axis) where the two optical axes pass closest;
    ``None`` for (near-)parallel cameras."""
    c_r = rig.T_left_right[:3, 3]
    z_l = np.array([0.0, 0.0, 1.0])
    z_r = rig.T_left_right[:3, 2]
    cross = np.cross(z_l, z_r)
    if np.linalg.norm(cross) < 1e-6:
        return None
    # closest points of the lines s*z_l and c_r + t*z_r
    A = np.array([[z_l @ z_l, -z_l @ z_r], [z_l @ z_r, -z_r @ z_r]])
    b = np.array([c_r @ z_l, c_r @ z_r])
    s, _ = np.linalg.solve(A, b)
    return float(s) if s > 0 else None


def local_contrast(image: NDArray, *, size: int = 15) -> NDArray[np.float32]:
    """Local standard deviation ``(H, W)`` of the image (8-bit units) in a
    ``size x size`` window; for colour, the root mean of the channels' variances.

    Colour counts: the grating's neighbouring stripes can have nearly the same grey
    level (green ``(35, 130, 22)`` beside red ``(143, 31, 22)``: grey 62 and 65),
    so a grey-level test calls the inside of such a stripe pair featureless although
    each channel has a 100-level edge there. For a grey image (or equal channels)
    this is the grey-level standard deviation.
    """
    import cv2

    img = np.asarray(image, dtype=np.float32)
    chans = [img[..., c] for c in range(img.shape[2])] if img.ndim == 3 else [img]
    var = np.zeros(img.shape[:2], np.float32)
    for ch in chans:
        ch = np.ascontiguousarray(ch)
        mean = cv2.blur(ch, (size, size))
        var += np.maximum(cv2.blur(ch * ch, (size, size)) - mean * mean, 0.0)
    return np.sqrt(var / len(chans)).astype(np.float32)


def inside_silhouette(valid: NDArray, margin_px: int, *, close_px: int = 15) -> NDArray[np.bool_]:
    """Pixels at least ``margin_px`` inside the outline of the matched region.

    The region is ``valid`` with gaps up to ``close_px`` closed (a striped or
    camouflaged surface leaves holes that are not the outline).
    """
    import cv2

    m = np.asarray(valid, dtype=np.uint8)
    closed = cv2.morphologyEx(m, cv2.MORPH_CLOSE, np.ones((close_px, close_px), np.uint8))
    k = 2 * int(margin_px) + 1
    return cv2.erode(closed, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def lit_mask(image: NDArray, *, k_sigma: float = 5.0, min_step: float = 6.0) -> NDArray[np.bool_]:
    """Pixels that show a lit surface: the 3x3 maximum of the brightest channel lies
    above the image's dark population.

    The dark population is the pixels within 16 grey levels of the 1st percentile
    (the floor) of the brightest channel; with ``m`` its median and ``s = (m -
    floor) / 2.33`` its noise (the 1st percentile of a normal distribution lies
    2.33 sigma below its centre), the threshold is ``max(floor + min_step, m +
    k_sigma * s)``. On a shot against an unlit background these are the
    background's black level and read noise: on the simulated paper rig it reads
    0-3 grey levels (99.9th percentile 3), so the threshold is ``min_step`` = 6. A
    shot with no dark background loses at most its darkest ~1 % of pixels, as
    specks that a silhouette's closing fills.
    """
    import cv2

    img = np.asarray(image)
    v = (img.max(axis=2) if img.ndim == 3 else img).astype(np.float32)
    floor = float(np.percentile(v, 1.0))
    m = float(np.median(v[v <= floor + 16.0]))
    thr = max(floor + float(min_step), m + float(k_sigma) * (m - floor) / 2.33)
    return cv2.dilate(v, np.ones((3, 3), np.uint8)) >= thr


def _bspline_views(views: tuple[NDArray, NDArray], maps: RectifyMaps, r0: int, r1: int) -> tuple[NDArray, NDArray]:
    """Both views rectified with cubic B-splines (float32 in [0, 1]), computed on rows
    ``r0..r1`` only (the refinement's windows) and 0 elsewhere."""
    from prism3d.reconstruct.rectify import RectifyMaps

    scale = np.float32(1.0 / 255.0) if views[0].dtype == np.uint8 else np.float32(1.0)
    r0, r1 = max(int(r0), 0), min(int(r1) + 1, maps.left_x.shape[0])
    band = RectifyMaps(maps.rect, maps.left_x[r0:r1], maps.left_y[r0:r1], maps.right_x[r0:r1], maps.right_y[r0:r1])
    out = []
    for part in band.remap(*(np.asarray(v, np.float32) * scale for v in views), interpolation="bspline"):
        full = np.zeros(maps.left_x.shape + part.shape[2:], np.float32)
        full[r0:r1] = part
        out.append(full)
    return out[0], out[1]


def disparity_range(
    rect: Rectification, depth_range_mm: tuple[float, float]
) -> tuple[int, int]:
    """``(min_disp, num_disp)`` covering depths ``[z_near, z_far]`` (num_disp a multiple of 16)."""
    z0, z1 = (float(v) for v in depth_range_mm)
    if not (0 < z0 < z1):
        raise InputError(f"depth range: expected 0 < near < far, got {z0}:{z1}")
    fb = rect.focal_px * rect.baseline_mm
    d_min = math.floor(fb / z1)
    d_max = math.ceil(fb / z0)
    num = int(math.ceil((d_max - d_min + 1) / 16.0) * 16)
    return d_min, num


@dataclass
class Reconstruction:
    """Everything one shot produced."""

    scan: Scan
    rect: Rectification
    left_rect: NDArray[np.uint8]
    disparity: NDArray[np.float32]
    """Dense (filled) disparity on the rectified-left grid."""
    valid: NDArray[np.bool_]
    """Pixels that passed the matcher's checks and gave a point."""
    min_disp: int
    num_disp: int
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def depth_mm(self) -> NDArray[np.float32]:
        """Rectified-left depth of the valid points (NaN elsewhere)."""
        return self.scan.depth_mm


def reconstruct_shot(
    shot: NDArray,
    rig: StereoRig,
    *,
    min_disp: int | None = None,
    num_disp: int | None = None,
    depth_range_mm: tuple[float, float] | None = None,
    alpha: float = 1.0,
    smooth_sigma_px: float = 0.0,
    min_texture: float = 2.0,
    silhouette_margin_px: int = 3,
    lit_outline: bool = True,
    refine: bool = True,
    refine_window: tuple[int, int] = (7, 19),
    refine_orientation_weight: bool = False,
    refine_curvature: bool = True,
    refine_interpolation: str = "bspline",
    max_residual: float = 1.0,
    max_disparity_std: float = float("inf"),
    progress: ProgressFn = null_progress,
    **match_kwargs: Any,
) -> Reconstruction:
    """Split a side-by-side shot, rectify, match and triangulate it.

    Parameters
    ----------
    shot : (H, W, 3) uint8
        The sensor image (``rig.split.sensor_size``).
    rig : StereoRig
        The calibration.
    min_disp, num_disp : int, optional
        Disparity search range. By default it covers ``depth_range_mm``.
    depth_range_mm : (near, far), optional
        Default: 0.85x to 1.2x the rig's convergence distance.
    smooth_sigma_px : float
        Edge-preserving depth smoothing (0 = none); see
        :func:`~prism3d.reconstruct.meshing.smooth_depth`.
    min_texture : float
        Pixels whose local grey-level standard deviation (15x15, 8-bit units) is below
        this are not triangulated: on a featureless (e.g. unlit, black) background any
        match the checks let through is noise (on a striped, camouflaged target at the
        paper's geometry this keeps 91% of the matched target pixels and drops 98% of
        the background ones). 0 disables the test.
    silhouette_margin_px : int
        Drop points within this many pixels of the object's outline (the outline
        of the matched region, gaps closed). Semi-global matching smears foreground
        disparities a pixel or two onto the background there ("edge fattening"):
        points floating beside the object that bias ICP when views are stitched.
        0 keeps them.
    lit_outline : bool
        Take that outline from matched pixels that are also lit (:func:`lit_mask`:
        clear of the shot's dark floor by at least 6 grey levels, more on a noisy
        floor), not from the texture test alone, whose 15x15 window reaches ~7 px
        into an unlit background (there 1-1.5 mm of points per view lie beside the
        object). On 8 stitched views of a camouflaged tank this took the model's
        height error from +3.7 % to +0.4 %, for 3 % fewer points.
    refine : bool
        Slanted-plane sub-pixel refinement of the matched disparity
        (:func:`~prism3d.reconstruct.refine.refine_slanted`, window ``refine_window``
        rows x cols). The grating's stripes are flat colours, so constant-disparity
        windows make a staircase on slanted surfaces; the plane fit removes it
        (45-degree view of a target: disparity MAD 0.48 -> 0.10 px; flat plate:
        RMS 0.055 -> 0.026 px). Holes the matcher's checks left inside the
        surface are estimated the same way (26 % more points on that view, as
        accurate as the rest).
    refine_window : (rows, cols)
        Default 7 x 19, narrower than :func:`refine_slanted`'s own 7 x 25: a
        plane fitted over a window rounds every crease over half its width, and
        the curvature correction spreads that over half a window more; both
        tilt the flat faces beside a crease, differently in every view, and
        stitched turntable views inherit it as pose errors. Worst stitched
        view pose, 10 built-in targets x 8 views, rendered at 1 and 2x2 rays
        per pixel: 0.010-0.068 deg (mean 0.033, 3 of 20 above 0.05) with 25
        columns, 0.010-0.047 deg (mean 0.026) with 19. The price is noise: the
        flat plate of Table I goes from 0.034-0.035 to 0.050-0.053 mm RMS with
        the grating (0.032-0.033 -> 0.040-0.042 mm smoothed; 0.047 -> 0.054
        mm without the grating). 17 columns doubles it (0.073-0.077 mm).
    refine_orientation_weight : bool
        Down-weight edges nearly parallel to the epipolar lines in the refinement
        (off by default; see :func:`~prism3d.reconstruct.refine.refine_slanted` for
        what it gains and costs).
    refine_interpolation : {"bspline", "linear"}
        How the refinement's images are rectified. ``"bspline"`` (default)
        resamples the views a second time with exact cubic B-splines, in float
        (see :meth:`~prism3d.reconstruct.rectify.RectifyMaps.remap`); ``"linear"``
        refines on the matcher's images (OpenCV bilinear, uint8). Bilinear
        resampling blurs each view by an amount that depends on the sub-pixel
        offset of its map, which differs between the views and drifts across the
        image: at the true disparity the two rectified views of an edge differ,
        and the plane fit reads that as a disparity bias that follows the colour
        and camouflage edges, the same with and without sensor noise. On a ship's
        end-on view (whose turn rests on a 47 mm wide stern) the bias turned the
        scan 0.17 deg; with B-splines 0.10 deg. Worst stitched view pose over 12
        built-in targets rendered with 1 and 2x2 rays per pixel: 23 of 24 within
        0.05 deg (before: 20), ship_s2 0.109 / 0.078 -> 0.026 / 0.032 deg; the
        flat plate of Table I 0.047-0.054 -> 0.026-0.036 mm RMS. Adds ~0.15 s to a
        5 MP shot (the refinement stage 0.05-0.07 -> 0.22 s).
    refine_curvature : bool
        Correct the plane fit for the surface's curvature along the rows, which
        otherwise flattens convex surfaces by up to ~0.1 mm, differently in every
        view (see :func:`~prism3d.reconstruct.refine.refine_slanted`).
    max_residual : float
        After refinement, drop pixels whose window the fitted plane does not
        explain: mean squared colour residual over mean squared gradient above this
        (occlusions, wrong matches). ``inf`` keeps all.
    match_kwargs
        Passed to :func:`~prism3d.reconstruct.match.match_stereo_full`. The
        sub-pixel refinement window defaults to 9 px here (5 in the matcher): on the
        paper's 5 MP views this halves the disparity noise on a patterned plate
        (0.094 -> 0.054 px RMS; 13 px gives 0.042) at the cost of lateral
        resolution at depth edges.
    """
    from prism3d.reconstruct.match import match_stereo_full
    from prism3d.reconstruct.rectify import rectify_maps

    img = check_array(shot, "shot", ndim=(2, 3))
    sw, sh = rig.split.sensor_size
    if img.shape[1] != sw or img.shape[0] != sh:
        raise InputError(
            f"shot is {img.shape[1]}x{img.shape[0]} but the calibration expects a {sw}x{sh} sensor image"
        )
    check_choice(refine_interpolation, "refine_interpolation", ("bspline", "linear"))
    t = {}
    t0 = time.perf_counter()
    progress(0, 4, "rectify")
    # rectify_shot's steps, keeping the maps and views for the refinement's B-spline
    # views (the rig guarantees each view's size; the shot's was checked above)
    rect = compute_rectification(rig, alpha=alpha)
    maps = rectify_maps(rig, rect)
    views = rig.split.split(img)
    left, right = maps.remap(*views)
    t["rectify"] = time.perf_counter() - t0
    if (min_disp is None) != (num_disp is None):
        raise InputError("give both min_disp and num_disp, or neither (then depth_range_mm is used)")
    if min_disp is None:
        if depth_range_mm is None:
            wd = convergence_distance_mm(rig)
            if wd is None:
                raise InputError(
                    "the cameras are parallel: give the disparity range (--min-disp/--num-disp) "
                    "or the depth range (--depth-range NEAR:FAR mm)"
                )
            depth_range_mm = (0.85 * wd, 1.2 * wd)
        min_disp, num_disp = disparity_range(rect, depth_range_mm)
    t0 = time.perf_counter()
    progress(1, 4, "match")
    match_kwargs.setdefault("lk_window", 9)
    res = match_stereo_full(left, right, min_disp=int(min_disp), num_disp=int(num_disp), **match_kwargs)
    t["match"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    progress(2, 4, "triangulate")
    in_range = np.isfinite(res.disparity) & (res.disparity > 0)
    # matches pinned to either end of the search range are not measurements
    in_range &= (res.disparity > min_disp + 1.0) & (res.disparity < min_disp + num_disp - 2.0)
    valid = res.valid & in_range
    textured = local_contrast(left) >= min_texture if min_texture > 0 else np.ones_like(valid)
    valid &= textured
    # the outline comes from matched pixels that show the lit surface: the 15x15
    # texture test passes black background up to ~7 px from the object, where the
    # matcher and the refinement carry the object's disparity outwards
    outline = valid & lit_mask(left) if lit_outline else valid
    inside = inside_silhouette(outline, silhouette_margin_px) if silhouette_margin_px > 0 else None
    if inside is not None:
        valid &= inside
    disparity = res.disparity
    if refine and valid.any():
        from prism3d.reconstruct.refine import refine_slanted

        t1 = time.perf_counter()
        # holes the matcher's checks left inside the surface (flat-coloured stripe
        # interiors) are estimated too, from the planes of their windows
        holes = (inside if inside is not None else inside_silhouette(valid, 0)) & textured & in_range & ~valid
        if refine_interpolation == "bspline":
            rows = np.flatnonzero((valid | holes).any(axis=1))
            left_r, right_r = _bspline_views(views, maps, rows[0] - refine_window[0], rows[-1] + refine_window[0])
        else:
            left_r, right_r = left, right
        disparity, resid, dstd = refine_slanted(left_r, right_r, res.disparity, valid, window=refine_window,
                                                extra=holes,
                                                orientation_weight=refine_orientation_weight,
                                                curvature=refine_curvature)
        valid = (valid | holes) & (resid <= max_residual) & (dstd <= max_disparity_std)
        t["refine"] = time.perf_counter() - t1
    depth = np.where(valid, rect.disparity_to_depth(disparity), np.nan).astype(np.float32)
    if smooth_sigma_px > 0:
        depth = smooth_depth(depth, sigma_px=smooth_sigma_px, focal_px=rect.focal_px,
                             baseline_mm=rect.baseline_mm)
    scan = scan_from_depth(depth, rect, left, res.confidence)
    scan.meta.update(focal_px=rect.focal_px, baseline_mm=rect.baseline_mm, min_disp=int(min_disp),
                     num_disp=int(num_disp), smooth_sigma_px=float(smooth_sigma_px))
    t["triangulate"] = time.perf_counter() - t0 - t.get("refine", 0.0)
    progress(4, 4, "done")
    return Reconstruction(scan, rect, left, disparity, np.isfinite(scan.depth_mm), int(min_disp),
                          int(num_disp), t)


def reconstruct_to_files(
    shot_path: str | Path,
    calib_path: str | Path,
    out_ply: str | Path,
    *,
    disparity_out: str | Path | None = None,
    depth_out: str | Path | None = None,
    mesh_out: str | Path | None = None,
    min_disp: int | None = None,
    num_disp: int | None = None,
    depth_range_mm: tuple[float, float] | None = None,
    smooth_sigma_px: float = 0.0,
    progress: ProgressFn = null_progress,
) -> Reconstruction:
    """What ``prism3d reconstruct SHOT --calib calib.yaml -o scan.ply`` calls.

    Writes the scan PLY (valid points only, left camera frame, mm, with colours,
    normals and confidence), and optionally the dense disparity (PFM, rectified-left
    grid), the depth map (float32 mm, rectified-left grid, NaN = no point) and a
    mesh of the organised grid that does not bridge depth jumps. Outputs are written
    only after everything has been computed, each atomically.
    """
    from prism3d.io.images import read_image, write_depth
    from prism3d.io.pfm import write_pfm

    out_ply = Path(out_ply)
    for p in (out_ply, disparity_out, depth_out, mesh_out):
        if p is not None and Path(p).is_dir():
            raise InputError(f"{p}: is a directory; give an output file name")
    if out_ply.suffix.lower() != ".ply":
        raise InputError(f"{out_ply}: the scan must be written as .ply")
    rig = StereoRig.load(calib_path)
    shot = read_image(shot_path)
    sw, sh = rig.split.sensor_size
    if shot.shape[1] != sw or shot.shape[0] != sh:
        raise InputError(f"{shot_path}: image is {shot.shape[1]}x{shot.shape[0]} but {calib_path} "
                         f"describes a {sw}x{sh} sensor")
    rec = reconstruct_shot(shot, rig, min_disp=min_disp, num_disp=num_disp, depth_range_mm=depth_range_mm,
                           smooth_sigma_px=smooth_sigma_px, progress=progress)
    faces = None
    if mesh_out is not None:
        grid, m = rec.scan.grid()
        verts, faces = mesh_from_grid(grid, m, focal_px=rec.rect.focal_px)
    comments = [f"{k} {v}" for k, v in rec.scan.meta.items()]
    from prism3d.io.ply import write_ply

    write_ply(out_ply, rec.scan.points, colors=rec.scan.colors, normals=rec.scan.normals,
              extra={"confidence": rec.scan.confidence},
              comments=["prism3d scan", "units mm", "frame left camera (OpenCV axes)", *comments])
    if mesh_out is not None:
        write_ply(mesh_out, verts, faces=faces, colors=rec.scan.colors, normals=rec.scan.normals,
                  comments=["prism3d scan mesh", "units mm", *comments])
    if disparity_out is not None:
        write_pfm(disparity_out, rec.disparity)
    if depth_out is not None:
        write_depth(depth_out, rec.scan.depth_mm)
    return rec
