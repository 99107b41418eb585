"""One shot (or one ordinary stereo pair) to one scan: rectify, match, refine, select,
triangulate (``prism3d reconstruct``).

Which pixels become points is decided in :mod:`prism3d.reconstruct.selection`, by
rules stated against the shot itself (its noise, its black level, the matcher's
consistency), and every point carries its predicted disparity standard deviation;
``min_confidence`` trades density for precision. docs/reconstruction.md tells how
the rules were chosen and what they were measured to do on real pairs.
"""

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
from prism3d.errors import InputError, ReconstructionError
from prism3d.io.atomic import atomic_path
from prism3d.progress import ProgressFn, null_progress
from prism3d.reconstruct.defaults import DEFAULT_MIN_CONFIDENCE
from prism3d.reconstruct.meshing import mesh_from_grid, smooth_depth
from prism3d.reconstruct.triangulate import Scan, scan_from_depth

if TYPE_CHECKING:
    from prism3d.reconstruct.rectify import RectifyMaps
    from prism3d.reconstruct.selection import Coverage

__all__ = [
    "DEFAULT_MIN_CONFIDENCE",
    "Reconstruction",
    "convergence_distance_mm",
    "disparity_range",
    "estimate_disparity_range",
    "reconstruct_pair",
    "reconstruct_shot",
    "reconstruct_to_files",
]


#: Axes that cross further than this many baselines away (a convergence angle below
#: ~3 deg) belong to a parallel rig with a small toe-in, not one aimed at a distance.
_CONVERGING_MAX_BASELINES = 20.0


def convergence_distance_mm(rig: StereoRig) -> float | None:
    """Distance (along the left optical axis) where the two optical axes pass closest,
    for a rig aimed at a working distance (the prism adapter's views cross at ~6
    baselines); ``None`` for parallel cameras, including a toe-in of a fraction of a
    degree (axes crossing beyond ``_CONVERGING_MAX_BASELINES`` baselines)."""
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
    if not 0 < s <= _CONVERGING_MAX_BASELINES * rig.baseline_mm:
        return None
    return float(s)


def _bspline_views(views: tuple[NDArray, NDArray], maps: RectifyMaps, r0: int, r1: int) -> tuple[NDArray, NDArray]:
    """Both views rectified with cubic B-splines (float32 in 8-bit units, 0..255),
    computed on rows ``r0..r1`` only (the refinement's windows) and 0 elsewhere."""
    from prism3d.reconstruct.rectify import RectifyMaps

    scale = np.float32(1.0) if views[0].dtype == np.uint8 else np.float32(255.0)
    r0, r1 = max(int(r0), 0), min(int(r1) + 1, maps.left_x.shape[0])
    band = RectifyMaps(maps.rect, maps.left_x[r0:r1], maps.left_y[r0:r1], maps.right_x[r0:r1], maps.right_y[r0:r1])
    out = []
    for part in band.remap(*(np.asarray(v, np.float32) * scale for v in views), interpolation="bspline"):
        full = np.zeros(maps.left_x.shape + part.shape[2:], np.float32)
        full[r0:r1] = part
        out.append(full)
    return out[0], out[1]


#: Colour detail both views hold: Bayer sensors and JPEG's 4:2:0 store chroma at half
#: resolution, on a grid whose phase differs between the views; a Gaussian of 2 px keeps
#: chroma below that grid's Nyquist band.
_CHROMA_SIGMA_PX = 2.0
#: Scale (px) of the local contrast normalisation before the refinement: wider than the
#: refinement window (7 x 19), so that within a window only the scene's own contrast
#: remains, while gain and offset that change more slowly (a flash highlight seen from
#: two angles, vignetting the gain field left) cancel between the views.
_NORMALISE_SIGMA_PX = 12.0


def _smooth(img: NDArray[np.float32], sigma: float) -> NDArray[np.float32]:
    """Gaussian smoothing at a large ``sigma``, computed on a level ``sigma / 3`` times
    smaller and interpolated back (the result is smooth on that scale anyway)."""
    import cv2

    k = max(1, int(sigma // 3))
    h, w = img.shape[:2]
    if k == 1 or h < 4 * k or w < 4 * k:
        return cv2.GaussianBlur(img, (0, 0), sigma).reshape(img.shape)
    small = cv2.resize(img, (-(-w // k), -(-h // k)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma / k)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).reshape(img.shape)


def _refinement_view(view: NDArray, noise: float, rows: tuple[int, int] | None = None) -> NDArray[np.float32]:
    """A view as the slanted-plane refinement compares it: luma at full resolution,
    chroma low-passed to the band both views of a real camera hold, then each pixel's
    deviation from its neighbourhood's mean over the neighbourhood's contrast (the
    shot's noise keeps flat regions from being amplified). Only ``rows`` (start, stop)
    are computed (0 elsewhere). docs/reconstruction.md has what each step bought on
    the simulated plate."""
    import cv2

    full = np.asarray(view, dtype=np.float32)
    r0, r1 = (0, full.shape[0]) if rows is None else (max(rows[0], 0), min(rows[1], full.shape[0]))
    v = full[r0:r1]
    if v.ndim == 3 and v.shape[2] == 3:
        luma = (0.299 * v[..., 0] + 0.587 * v[..., 1] + 0.114 * v[..., 2])[..., None]
        chroma = cv2.GaussianBlur(np.ascontiguousarray(v - luma), (0, 0), _CHROMA_SIGMA_PX)
        v = chroma + luma
    v3 = np.ascontiguousarray(v if v.ndim == 3 else v[..., None])
    dev = v3 - _smooth(v3, _NORMALISE_SIGMA_PX)
    var = _smooth(np.ascontiguousarray((dev * dev).mean(-1)), _NORMALISE_SIGMA_PX)
    scale = np.float32(64.0) / np.sqrt(np.maximum(var, 0.0) + np.float32(max(noise, 1.0)) ** 2)
    out = np.zeros(full.shape[:2] + v3.shape[2:], np.float32)
    out[r0:r1] = dev * scale[..., None] + np.float32(128.0)
    return out if full.ndim == 3 else out[..., 0]


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



#: A refined disparity that moved further than this (px) from the matcher's is not
#: a refinement of that match: the pixel is inconsistent.
_MAX_REFINE_CHANGE_PX = 1.5
#: Sparse matches needed before their disparities are trusted to set a search range.
_MIN_RANGE_MATCHES = 20


def estimate_disparity_range(left: NDArray, right: NDArray) -> tuple[int, int]:
    """``(min_disp, num_disp)`` for a rectified pair from sparse feature matches.

    ORB features matched across the views (mutual nearest neighbours, Lowe's ratio
    test) on the same row (within 1.5 px): the 1st to 99th percentile of their
    disparities, widened by a quarter of that span and 8 px each way, and never below
    0 (with equal principal points a point in front of the cameras has ``d = f B / z
    > 0``). Used when the cameras are parallel and the user gives no range.

    Raises
    ------
    ReconstructionError
        Fewer than 20 matches: the range cannot be told from the images.
    """
    import cv2

    def grey(img: NDArray) -> NDArray[np.uint8]:
        a = np.asarray(img)
        if a.dtype != np.uint8:
            a = np.clip(np.rint(a * (255.0 if a.dtype.kind == "f" and a.max() <= 1.0 else 1.0)), 0, 255).astype(np.uint8)
        return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a

    gl, gr = grey(left), grey(right)
    orb = cv2.ORB_create(nfeatures=4000, fastThreshold=7)
    kl, dl = orb.detectAndCompute(gl, None)
    kr, dr = orb.detectAndCompute(gr, None)
    disp: list[float] = []
    if dl is not None and dr is not None and len(kl) >= 2 and len(kr) >= 2:
        bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        back = {m.queryIdx: m.trainIdx for m in bf.match(dr, dl)}
        for pair in bf.knnMatch(dl, dr, k=2):
            if len(pair) < 2 or pair[0].distance >= 0.8 * pair[1].distance:
                continue
            if back.get(pair[0].trainIdx) != pair[0].queryIdx:
                continue
            pl, pr = kl[pair[0].queryIdx].pt, kr[pair[0].trainIdx].pt
            if abs(pl[1] - pr[1]) <= 1.5:
                disp.append(pl[0] - pr[0])
    if len(disp) < _MIN_RANGE_MATCHES:
        raise ReconstructionError(
            f"cannot tell the disparity range from the images ({len(disp)} feature matches on the "
            "same rows): give --min-disp/--num-disp or --depth-range NEAR:FAR")
    lo, hi = np.percentile(np.asarray(disp), [1.0, 99.0])
    margin = 0.25 * (hi - lo) + 8.0
    d0 = max(int(math.floor(lo - margin)), 0)
    num = int(math.ceil((hi + margin - d0 + 1) / 16.0) * 16)
    return d0, num


@dataclass
class Reconstruction:
    """Everything one shot produced.

    Attributes
    ----------
    scan : Scan
        The points (left camera frame, mm) with colours, normals, confidence and
        disparity std.
    rect : Rectification
    left_rect : (H, W, 3) uint8
        The rectified left view (the points' colours).
    disparity : (H, W) float32
        Disparity of the kept pixels on the rectified-left grid (NaN elsewhere).
    disparity_std : (H, W) float32
        Its predicted standard deviation (px; NaN where no point).
    measured : (H, W) bool
        Kept pixels matched and refined (the rest of the kept were estimated from
        their neighbours).
    coverage : Coverage
        The share kept and why the rest was dropped.
    """

    scan: Scan
    rect: Rectification
    left_rect: NDArray[np.uint8]
    disparity: NDArray[np.float32]
    disparity_std: NDArray[np.float32]
    measured: NDArray[np.bool_]
    coverage: Coverage
    min_disp: int
    num_disp: int
    noise: float
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Pixels that gave a point."""
        return np.isfinite(self.disparity)

    @property
    def depth_mm(self) -> NDArray[np.float32]:
        """Rectified-left depth of the points (NaN elsewhere)."""
        return self.scan.depth_mm


def _search_range(rig: StereoRig, rect: Rectification, left: NDArray, right: NDArray,
                  min_disp: int | None, num_disp: int | None,
                  depth_range_mm: tuple[float, float] | None,
                  max_disparity: float | None = None) -> tuple[int, int]:
    """The disparity search range: as given, from a depth range, from the rig's
    convergence distance (converging views), or from the images (parallel views;
    ``max_disparity`` bounds it, and serves alone when the images cannot tell)."""
    if (min_disp is None) != (num_disp is None):
        raise InputError("give both min_disp and num_disp, or neither (then the depth range is used)")
    if min_disp is not None:
        return int(min_disp), int(num_disp)  # type: ignore[arg-type]
    if depth_range_mm is not None:
        return disparity_range(rect, depth_range_mm)
    wd = convergence_distance_mm(rig)
    if wd is not None:
        return disparity_range(rect, (0.85 * wd, 1.2 * wd))
    try:
        d0, n = estimate_disparity_range(left, right)
    except ReconstructionError:
        if max_disparity is None:
            raise
        return 0, int(math.ceil((math.floor(max_disparity) + 2) / 16.0) * 16)
    if max_disparity is not None:
        d1 = min(d0 + n - 1, int(math.floor(max_disparity)) + 1)
        d0 = max(d0, 0)
        n = int(math.ceil((d1 - d0 + 1) / 16.0) * 16)
    return d0, n


def _coverage_mask(maps: RectifyMaps, size: tuple[int, int]) -> NDArray[np.bool_]:
    """Rectified-left pixels whose source lies inside the left view."""
    w, h = size
    return (maps.left_x >= 0) & (maps.left_x <= w - 1) & (maps.left_y >= 0) & (maps.left_y <= h - 1)


def _reconstruct_views(
    views: tuple[NDArray, NDArray],
    rig: StereoRig,
    *,
    min_disp: int | None,
    num_disp: int | None,
    depth_range_mm: tuple[float, float] | None,
    max_disparity: float | None,
    alpha: float,
    smooth_sigma_px: float,
    min_confidence: float,
    fill: bool,
    refine_window: tuple[int, int],
    refine_orientation_weight: bool,
    refine_curvature: bool,
    refine_interpolation: str,
    progress: ProgressFn,
    match_kwargs: dict[str, Any],
) -> Reconstruction:
    """The pipeline on the two (un-flipped) views of a calibrated rig."""
    from prism3d.reconstruct.match import match_stereo_full
    from prism3d.reconstruct.rectify import rectify_maps
    from prism3d.reconstruct.refine import refine_slanted
    from prism3d.reconstruct.selection import (
        REASONS, Coverage, enclosed, estimate_noise, fill_from_planes, near, occlusions, std_from_confidence,
        textured, unlit)

    check_choice(refine_interpolation, "refine_interpolation", ("bspline", "linear"))
    if not (0.0 <= float(min_confidence) < 1.0):
        raise InputError(f"min_confidence: expected a value in [0, 1), got {min_confidence!r}")
    max_std = std_from_confidence(min_confidence) if min_confidence > 0 else np.inf
    t: dict[str, float] = {}
    t0 = time.perf_counter()
    progress(0, 5, "rectify")
    rect = compute_rectification(rig, alpha=alpha)
    maps = rectify_maps(rig, rect)
    left, right = maps.remap(*views)
    covered = _coverage_mask(maps, rig.left.size)
    t["rectify"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress(1, 5, "match")
    min_disp, num_disp = _search_range(rig, rect, left, right, min_disp, num_disp, depth_range_mm,
                                       max_disparity)
    match_kwargs.setdefault("lk_window", 9)  # 9 px halves the LK noise on 5 MP views (docs/reconstruction.md)
    res = match_stereo_full(left, right, min_disp=int(min_disp), num_disp=int(num_disp), **match_kwargs)
    t["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress(2, 5, "select")
    noise = estimate_noise(left, covered)
    dense = res.disparity
    # a winner on the first or last level may have its minimum beyond the range
    in_range = covered & (dense > min_disp + 0.5) & (dense < min_disp + num_disp - 1.5)
    tex = textured(left, noise, window=refine_window)
    dark = unlit(left, noise, tex) & covered
    # a match whose census window reaches unlit background is the edge's, not the pixel's
    census_r = max(match_kwargs.get("census_window", (5, 5))) // 2
    rim = near(dark, census_r)
    occluded, outside = occlusions(dense)
    hidden = (occluded | outside) & ~res.valid
    usable = in_range & ~dark & ~rim
    measured = res.valid & usable & tex
    holes = ~res.valid & usable & tex & ~hidden
    t["select"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    progress(3, 5, "refine")
    refined = np.full(dense.shape, np.nan, np.float32)
    own_std = np.full(dense.shape, np.nan, np.float32)
    if measured.any() or holes.any():
        rows = np.flatnonzero((measured | holes).any(axis=1))
        r0, r1 = rows[0] - refine_window[0], rows[-1] + refine_window[0]
        if refine_interpolation == "bspline":
            left_r, right_r = _bspline_views(views, maps, r0, r1)
        else:
            left_r, right_r = left, right
        band = (max(r0, 0), min(r1 + 1, right_r.shape[0]))
        if res.right_gain is not None and not res.right_gain.negligible():
            right_r = np.array(right_r, dtype=np.float32)
            right_r[band[0]:band[1]] = res.right_gain.apply(right_r[band[0]:band[1]], row0=band[0])
        left_r, right_r = _refinement_view(left_r, noise, band), _refinement_view(right_r, noise, band)
        d_ref, _, d_std = refine_slanted(left_r, right_r, dense, measured, window=refine_window,
                                         extra=holes, orientation_weight=refine_orientation_weight,
                                         curvature=refine_curvature, max_change=_MAX_REFINE_CHANGE_PX)
        ok = (measured | holes) & np.isfinite(d_std)
        refined[ok] = d_ref[ok]
        own_std[ok] = d_std[ok]
    measured_ok = measured & np.isfinite(own_std)
    inconsistent = measured & ~measured_ok
    disparity = np.where(measured_ok, refined, np.nan).astype(np.float32)
    std = np.where(measured_ok, own_std, np.nan).astype(np.float32)
    t["refine"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    estimated = np.zeros_like(measured)
    if fill:
        # pixels the matcher could not measure keep its estimate (a refined hole, else
        # the matcher's background-favouring fill); their std is the local surface's
        # prediction std, widened by how far the estimate strays from that surface
        # untextured pixels are filled only where measured surface encloses them
        blank = usable & ~tex & ~measured_ok
        targets = usable & ~measured_ok & (tex | enclosed(blank, dark | rim | ~covered))
        est = np.where(np.isfinite(refined), refined, dense).astype(np.float32)
        e_own = np.where(np.isfinite(own_std), own_std, 0.0).astype(np.float32)
        plane = np.full(dense.shape, np.nan, np.float32)
        p_std = np.full(dense.shape, np.nan, np.float32)
        for sides, m in ((("centre",), targets & ~hidden), (("left", "right"), targets & hidden & outside),
                         (("left",), targets & hidden & ~outside)):
            if m.any():
                pe, ps = fill_from_planes(disparity, measured_ok, m, sides=sides, radii=(8, 24, 64))
                plane[m], p_std[m] = pe[m], ps[m]
        e_std = np.sqrt(e_own ** 2 + p_std ** 2 + (est - plane) ** 2)
        estimated = targets & np.isfinite(e_std)
        disparity[estimated] = est[estimated]
        std[estimated] = e_std[estimated]
    kept = (measured_ok | estimated) & (std <= max_std)
    low_conf = (measured_ok | estimated) & ~kept
    disparity[~kept] = np.nan
    std[~kept] = np.nan
    t["fill"] = time.perf_counter() - t0

    not_kept = covered & ~kept
    reason_masks = {
        "outside depth range": not_kept & ~in_range,
        "no texture": not_kept & (dark | ~tex) & ~hidden & ~low_conf,
        "silhouette": not_kept & rim & ~low_conf,
        "occluded": not_kept & hidden & ~low_conf,
        "inconsistent": not_kept & inconsistent & ~low_conf,
        "low confidence": not_kept & low_conf,
    }
    dropped, taken = {}, np.zeros_like(kept)
    for name in REASONS:
        m = reason_masks[name] & ~taken
        dropped[name] = int(m.sum())
        taken |= m
    dropped["no texture"] += int((not_kept & ~taken).sum())  # holes nothing around could serve
    cov = Coverage(int(covered.sum()), int((kept & measured_ok).sum()), int((kept & ~measured_ok).sum()),
                   dropped)

    t0 = time.perf_counter()
    progress(4, 5, "triangulate")
    depth = rect.disparity_to_depth(disparity)
    if smooth_sigma_px > 0:
        depth = smooth_depth(depth, sigma_px=smooth_sigma_px, focal_px=rect.focal_px,
                             baseline_mm=rect.baseline_mm)
    scan = scan_from_depth(depth, rect, left, std)
    scan.meta.update(focal_px=rect.focal_px, baseline_mm=rect.baseline_mm, min_disp=int(min_disp),
                     num_disp=int(num_disp), smooth_sigma_px=float(smooth_sigma_px),
                     min_confidence=float(min_confidence))
    t["triangulate"] = time.perf_counter() - t0
    progress(5, 5, "done")
    return Reconstruction(scan, rect, left, disparity, std, kept & measured_ok, cov, int(min_disp),
                          int(num_disp), float(noise), t)


_DEFAULTS: dict[str, Any] = dict(
    min_disp=None, num_disp=None, depth_range_mm=None, max_disparity=None, alpha=1.0, smooth_sigma_px=0.0,
    min_confidence=DEFAULT_MIN_CONFIDENCE, fill=True, refine_window=(7, 19),
    refine_orientation_weight=False, refine_curvature=True, refine_interpolation="bspline",
)


def reconstruct_shot(shot: NDArray, rig: StereoRig, *, progress: ProgressFn = null_progress,
                     **options: Any) -> Reconstruction:
    """Split a side-by-side shot with ``rig.split``, then :func:`reconstruct_pair`.

    Parameters
    ----------
    shot : (H, W, 3) uint8
        The sensor image (``rig.split.sensor_size``).
    rig : StereoRig
        The calibration.
    **options
        As :func:`reconstruct_pair`.
    """
    img = check_array(shot, "shot", ndim=(2, 3))
    sw, sh = rig.split.sensor_size
    if img.shape[1] != sw or img.shape[0] != sh:
        raise InputError(
            f"shot is {img.shape[1]}x{img.shape[0]} but the calibration expects a {sw}x{sh} sensor image"
        )
    return reconstruct_pair(*rig.split.split(img), rig, progress=progress, **options)


def reconstruct_pair(left: NDArray, right: NDArray, rig: StereoRig, *,
                     progress: ProgressFn = null_progress, **options: Any) -> Reconstruction:
    """Rectify, match, refine, select and triangulate the two views of a rig.

    Parameters
    ----------
    left, right : (h, w, 3) uint8
        The views, each ``rig.left.size`` (un-flipped; e.g. two camera files).
    rig : StereoRig
    min_disp, num_disp : int, optional
        Disparity search range; by default from ``depth_range_mm``, else 0.85x-1.2x
        the rig's convergence distance, else (parallel cameras) from sparse feature
        matches (:func:`estimate_disparity_range`).
    depth_range_mm : (near, far), optional
    max_disparity : float, optional
        A bound on the estimated range (e.g. a calibration's stated ``ndisp``).
    alpha : float
        See :func:`~prism3d.capture.rig.compute_rectification`.
    smooth_sigma_px : float
        Edge-preserving depth smoothing (0 = none); see
        :func:`~prism3d.reconstruct.meshing.smooth_depth`.
    min_confidence : float in [0, 1)
        Keep a pixel when the chance that its disparity is within 1 px of the truth,
        judged from its predicted std, reaches this
        (:func:`~prism3d.reconstruct.selection.confidence_from_std`); 0 keeps every
        pixel with an estimate. Default :data:`DEFAULT_MIN_CONFIDENCE`.
    fill : bool
        Estimate pixels the matcher could not measure (holes, occlusions, the
        left view's edge band) from local planes through the measured ones
        (:func:`~prism3d.reconstruct.selection.fill_from_planes`), each with its own
        predicted std.
    refine_window : (rows, cols)
        Window of the slanted-plane refinement
        (:func:`~prism3d.reconstruct.refine.refine_slanted`); 7 x 19 holds creases
        better than its own default (docs/reconstruction.md).
    refine_orientation_weight, refine_curvature : bool
        See :func:`~prism3d.reconstruct.refine.refine_slanted`.
    refine_interpolation : {"bspline", "linear"}
        Views for the refinement: rectified again with exact cubic B-splines (default;
        bilinear resampling biases the fit along colour edges) or the matcher's.
    **match_kwargs
        Passed to :func:`~prism3d.reconstruct.match.match_stereo_full`
        (``lk_window`` defaults to 9 here).
    """
    la = check_array(left, "left", ndim=(2, 3))
    ra = check_array(right, "right", ndim=(2, 3))
    for name, a, cam in (("left", la, rig.left), ("right", ra, rig.right)):
        if (a.shape[1], a.shape[0]) != cam.size:
            raise InputError(f"{name} view is {a.shape[1]}x{a.shape[0]} but the calibration expects "
                             f"{cam.size[0]}x{cam.size[1]}")
    opts = dict(_DEFAULTS)
    match_kwargs = {k: v for k, v in options.items() if k not in _DEFAULTS}
    opts.update({k: v for k, v in options.items() if k in _DEFAULTS})
    return _reconstruct_views((la, ra), rig, progress=progress, match_kwargs=match_kwargs, **opts)


def reconstruct_to_files(
    shot_path: str | Path | None,
    calib_paths: str | Path | list[str | Path],
    out_ply: str | Path,
    *,
    left_path: str | Path | None = None,
    right_path: str | Path | None = None,
    disparity_out: str | Path | None = None,
    depth_out: str | Path | None = None,
    mesh_out: str | Path | None = None,
    image_size: tuple[int, int] | None = None,
    progress: ProgressFn = null_progress,
    **options: Any,
) -> Reconstruction:
    """What ``prism3d reconstruct`` calls: a side-by-side shot (``shot_path``) or two
    view files (``left_path``, ``right_path``) and a calibration in any format
    :func:`~prism3d.capture.calib_formats.load_stereo_calibration` reads.

    Writes the scan PLY (the kept points, left camera frame, mm, with colours, normals
    and the per-point ``confidence``, ``disparity_std`` and ``depth_std``), and
    optionally the disparity (PFM, rectified-left grid, ``inf`` where no point, as
    Middlebury writes unknowns), the depth (float32 mm, NaN where no point) and a mesh
    of the organised grid. Everything is computed first; then all files are written
    to temporary names and moved into place together.

    When the range is not given, a range the calibration states (Middlebury ``ndisp``)
    bounds the one estimated from the images.
    """
    import contextlib

    from prism3d.capture.calib_formats import load_stereo_calibration
    from prism3d.io.images import read_image, write_depth
    from prism3d.io.pfm import write_pfm
    from prism3d.io.ply import write_ply

    out_ply = Path(out_ply)
    outs = [Path(p) for p in (out_ply, disparity_out, depth_out, mesh_out) if p is not None]
    for p in outs:
        if p.is_dir():
            raise InputError(f"{p}: is a directory; give an output file name")
    if len({p.resolve() for p in outs}) != len(outs):
        raise InputError("two outputs name the same file; give each output its own path")
    if out_ply.suffix.lower() != ".ply":
        raise InputError(f"{out_ply}: the scan must be written as .ply")
    if mesh_out is not None and Path(mesh_out).suffix.lower() != ".ply":
        raise InputError(f"{mesh_out}: the mesh must be written as .ply")
    if disparity_out is not None and Path(disparity_out).suffix.lower() != ".pfm":
        raise InputError(f"{disparity_out}: the disparity is written as PFM; name it .pfm")
    if depth_out is not None and Path(depth_out).suffix.lower() not in (".tif", ".tiff", ".npy", ".npz"):
        raise InputError(f"{depth_out}: the depth is written as .tiff, .npy or .npz")
    two_files = left_path is not None or right_path is not None
    if two_files == (shot_path is not None) or (two_files and (left_path is None or right_path is None)):
        raise InputError("give either a side-by-side SHOT or both --left and --right view files")
    cal = load_stereo_calibration(calib_paths,
                                  image_size=image_size)
    rig = cal.rig
    if two_files:
        left, right = read_image(left_path), read_image(right_path)  # type: ignore[arg-type]
        if left.shape != right.shape:
            raise InputError(f"{left_path} is {left.shape[1]}x{left.shape[0]} but {right_path} is "
                             f"{right.shape[1]}x{right.shape[0]}: the two views must have the same size")
        views = (left, right)
        source = f"{left_path}, {right_path}"
    else:
        shot = read_image(shot_path)  # type: ignore[arg-type]
        sw, sh = rig.split.sensor_size
        if shot.shape[1] != sw or shot.shape[0] != sh:
            raise InputError(f"{shot_path}: image is {shot.shape[1]}x{shot.shape[0]} but the calibration "
                             f"describes a {sw}x{sh} sensor (two {sw // 2}x{sh} views side by side)")
        views = rig.split.split(shot)
        source = str(shot_path)
    if options.get("min_disp") is None and options.get("depth_range_mm") is None and \
            cal.disparity_range is not None and convergence_distance_mm(rig) is None:
        options["max_disparity"] = _stated_max_disparity(cal)
    try:
        rec = reconstruct_pair(*views, rig, progress=progress, **options)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from exc
    faces = verts = None
    if mesh_out is not None:
        grid, m = rec.scan.grid()
        verts, faces = mesh_from_grid(grid, m, focal_px=rec.rect.focal_px)
    meta = [f"{k} {v}" for k, v in rec.scan.meta.items()]
    cov = rec.coverage
    meta.append("coverage " + " ".join(f"{k}={v:.4f}" for k, v in cov.shares().items()))
    props = rec.scan.point_properties()
    with contextlib.ExitStack() as stack:
        tmp = {p: stack.enter_context(atomic_path(p)) for p in outs}
        write_ply(tmp[out_ply], rec.scan.points, colors=rec.scan.colors, normals=rec.scan.normals,
                  extra=props, comments=["prism3d scan", "units mm", "frame left camera (OpenCV axes)", *meta])
        if mesh_out is not None:
            write_ply(tmp[Path(mesh_out)], verts, faces=faces, colors=rec.scan.colors, normals=rec.scan.normals,
                      comments=["prism3d scan mesh", "units mm", *meta])
        if disparity_out is not None:
            write_pfm(tmp[Path(disparity_out)], np.where(np.isfinite(rec.disparity), rec.disparity, np.inf))
        if depth_out is not None:
            write_depth(tmp[Path(depth_out)], rec.scan.depth_mm)
    return rec


def _stated_max_disparity(cal: Any) -> float:
    """The largest rectified disparity a calibration's stated range allows (its
    ``doffs`` added: rectification moves the views by it)."""
    lo, n = cal.disparity_range
    return float(lo + n - 1 + (cal.doffs or 0.0))
