"""One shot (or one ordinary stereo pair) to one scan: rectify, match, select, refine,
fill, keep, report, triangulate (``prism3d reconstruct``).

Which pixels become points is decided by rules stated against the shot itself
(:mod:`prism3d.reconstruct.stereo.selection`); every point carries its predicted disparity std.
docs/reconstruction.md tells how the rules were chosen and what they were measured to do.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.calib_formats import load_stereo_calibration
from prism3d.capture.rig import Rectification, StereoRig, compute_rectification
from prism3d.checks import check_array, check_choice, check_in_range
from prism3d.errors import InputError, ReconstructionError
from prism3d.io.atomic import atomic_path
from prism3d.io.hashes import sha256_files
from prism3d.io.images import read_image, write_depth
from prism3d.io.pfm import write_pfm
from prism3d.io.ply import write_ply
from prism3d.progress import ProgressFn, null_progress
from prism3d.reconstruct.stereo.defaults import DEFAULT_MIN_CONFIDENCE
from prism3d.reconstruct.stereo.match import match_stereo_full
from prism3d.reconstruct.stereo.match_options import MatchOptions
from prism3d.reconstruct.stereo.meshing import mesh_from_grid, smooth_depth
from prism3d.reconstruct.stereo.rectify import RectifyMaps, rectify_maps
from prism3d.reconstruct.stereo.refine import refine_slanted
from prism3d.reconstruct.stereo.selection import (
    REASONS,
    Coverage,
    enclosed,
    estimate_noise,
    fill_from_planes,
    isolated_matches,
    near,
    occlusions,
    std_from_confidence,
    surrounded,
    texture_energy,
    textured,
    unlit,
)
from prism3d.reconstruct.stereo.triangulate import Scan, scan_from_depth

if TYPE_CHECKING:
    from prism3d.reconstruct.stereo.match import StereoResult

__all__ = [
    "DEFAULT_MIN_CONFIDENCE",
    "Reconstruction",
    "ReconstructOptions",
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
#: Search range of a converging rig, as multiples of its convergence distance: the
#: prism rig's working volume around the distance it is aimed at.
_CONVERGENCE_DEPTH_FACTORS = (0.85, 1.2)
#: The matcher's disparity counts come in multiples of this (its SIMD width).
_DISP_STEP = 16
#: The matcher's Lucas-Kanade window for whole shots: 9 px halves the LK noise on 5 MP
#: views against the matcher's own default (docs/reconstruction.md).
_SHOT_LK_WINDOW = 9


def _shot_match_options() -> MatchOptions:
    return MatchOptions(lk_window=_SHOT_LK_WINDOW)


#: Largest depth smoothing sigma, px: beyond it the scan is a blur of itself (and the
#: kernel's size grows with the square of it).
MAX_SMOOTH_SIGMA_PX = 50.0


@dataclass(frozen=True)
class ReconstructOptions:
    """Options of :func:`reconstruct_pair` (why each default: docs/reconstruction.md)."""

    min_disp: int | None = None
    """Smallest disparity searched (px), with ``num_disp``; None: from ``depth_range_mm``,
    else the rig's convergence distance, else sparse feature matches."""
    num_disp: int | None = None
    """Number of disparities searched."""
    depth_range_mm: tuple[float, float] | None = None
    """(near, far) depths (mm) the search range covers; None: 0.85x..1.2x the rig's
    convergence distance (parallel cameras: from the images)."""
    max_disparity: float | None = None
    """A bound on the range estimated from the images (e.g. a calibration's ``ndisp``)."""
    alpha: float = 1.0
    """Rectification scaling; see :func:`~prism3d.capture.rig.compute_rectification`."""
    smooth_sigma_px: float = 0.0
    """Edge-preserving depth smoothing, Gaussian sigma (px, 0 = none); see :func:`~.meshing.smooth_depth`."""
    min_confidence: float = DEFAULT_MIN_CONFIDENCE
    """Keep a pixel when the chance its disparity is within 1 px of the truth reaches
    this, in [0, 1); 0 keeps every pixel with an estimate."""
    fill: bool = True
    """Estimate unmeasured pixels from local planes (:func:`~.selection.fill_from_planes`)."""
    refine_window: tuple[int, int] = (7, 19)
    """(rows, cols) of the refinement; 7 x 19 holds creases better than 7 x 25."""
    refine_orientation_weight: bool = False
    """See :func:`~.refine.refine_slanted`."""
    refine_curvature: bool = True
    """See :func:`~.refine.refine_slanted`."""
    refine_interpolation: str = "bspline"
    """Views for the refinement: ``"bspline"`` (rectified again with exact cubic
    B-splines; bilinear biases the fit along colour edges) or ``"linear"``."""
    match: MatchOptions = field(default_factory=_shot_match_options)
    """Matcher options; default ``MatchOptions(lk_window=9)`` (``_SHOT_LK_WINDOW``)."""

    def __post_init__(self) -> None:
        check_choice(self.refine_interpolation, "refine_interpolation", ("bspline", "linear"))
        if not (0.0 <= float(self.min_confidence) < 1.0):
            raise InputError(f"min_confidence: expected a value in [0, 1), got {self.min_confidence!r}")
        if (self.min_disp is None) != (self.num_disp is None):
            raise InputError("give both min_disp and num_disp, or neither (then the depth range is used)")
        check_in_range(self.smooth_sigma_px, "smooth_sigma_px", 0.0, MAX_SMOOTH_SIGMA_PX)


def convergence_distance_mm(rig: StereoRig) -> float | None:
    """Distance (mm, along the left optical axis) where the optical axes pass closest;
    ``None`` for parallel cameras."""
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
    """Both views rectified with cubic B-splines (float32, 0..255) on rows ``r0..r1``."""
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
#: Contrast (grey levels) and mid level of the normalised views: 8-bit-like figures,
#: so the refinement's small constants keep their meaning.
_NORMALISED_CONTRAST = 64.0
_NORMALISED_MID = 128.0
#: Noise floor (grey levels) of the normalisation, so flat noiseless regions are not
#: amplified without bound.
_MIN_NOISE = 1.0


def _smooth(img: NDArray[np.float32], sigma: float) -> NDArray[np.float32]:
    """Gaussian smoothing at a large ``sigma``, computed ``sigma / 3`` times smaller."""
    import cv2

    k = max(1, int(sigma // 3))
    h, w = img.shape[:2]
    if k == 1 or h < 4 * k or w < 4 * k:
        return cv2.GaussianBlur(img, (0, 0), sigma).reshape(img.shape)
    small = cv2.resize(img, (-(-w // k), -(-h // k)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma / k)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR).reshape(img.shape)


def _refinement_view(view: NDArray, noise: float, rows: tuple[int, int] | None = None) -> NDArray[np.float32]:
    """A view as the refinement compares it: chroma low-passed, then local contrast
    normalised; only ``rows`` (start, stop) are computed (0 elsewhere)."""
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
    scale = np.float32(_NORMALISED_CONTRAST) / np.sqrt(np.maximum(var, 0.0)
                                                       + np.float32(max(noise, _MIN_NOISE)) ** 2)
    out = np.zeros(full.shape[:2] + v3.shape[2:], np.float32)
    out[r0:r1] = dev * scale[..., None] + np.float32(_NORMALISED_MID)
    return out if full.ndim == 3 else out[..., 0]


def _round_up_disparities(n: float) -> int:
    return int(math.ceil(n / float(_DISP_STEP)) * _DISP_STEP)


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
    return d_min, _round_up_disparities(d_max - d_min + 1)


#: A refined disparity that moved further than this (px) from the matcher's is not
#: a refinement of that match: the pixel is inconsistent.
_MAX_REFINE_CHANGE_PX = 1.5
#: Sparse matches needed before their disparities are trusted to set a search range.
_MIN_RANGE_MATCHES = 20
#: ORB features per view: enough for a few hundred matches on a textured pair.
_ORB_FEATURES = 4000
#: ORB's FAST threshold, lower than OpenCV's 20 so weakly textured views give corners.
_ORB_FAST_THRESHOLD = 7
#: Lowe's ratio test: the best match must beat the second best by this factor.
_LOWE_RATIO = 0.8
#: Rectified matches lie on the same row, within this (px).
_SAME_ROW_PX = 1.5
#: Percentiles of the matches' disparities taken as the range (outliers cut).
_RANGE_PERCENTILES = (1.0, 99.0)
#: Widening of that range: this share of its span plus a fixed margin (px) each way.
_RANGE_WIDEN_SHARE = 0.25
_RANGE_WIDEN_PX = 8.0


def _grey_u8(img: NDArray) -> NDArray[np.uint8]:
    import cv2

    a = np.asarray(img)
    if a.dtype != np.uint8:
        a = np.clip(np.rint(a * (255.0 if a.dtype.kind == "f" and a.max() <= 1.0 else 1.0)), 0, 255).astype(np.uint8)
    return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.ndim == 3 else a


def _sparse_disparities(left: NDArray, right: NDArray) -> list[float]:
    """Disparities of ORB matches (mutual nearest neighbours, Lowe's ratio test) on the
    same row."""
    import cv2

    gl, gr = _grey_u8(left), _grey_u8(right)
    orb = cv2.ORB_create(nfeatures=_ORB_FEATURES, fastThreshold=_ORB_FAST_THRESHOLD)
    kl, dl = orb.detectAndCompute(gl, None)
    kr, dr = orb.detectAndCompute(gr, None)
    disp: list[float] = []
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return disp
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    back = {m.queryIdx: m.trainIdx for m in bf.match(dr, dl)}
    for pair in bf.knnMatch(dl, dr, k=2):
        if len(pair) < 2 or pair[0].distance >= _LOWE_RATIO * pair[1].distance:
            continue
        if back.get(pair[0].trainIdx) != pair[0].queryIdx:
            continue
        pl, pr = kl[pair[0].queryIdx].pt, kr[pair[0].trainIdx].pt
        if abs(pl[1] - pr[1]) <= _SAME_ROW_PX:
            disp.append(pl[0] - pr[0])
    return disp


def estimate_disparity_range(left: NDArray, right: NDArray) -> tuple[int, int]:
    """``(min_disp, num_disp)`` of a rectified pair from the 1st-99th percentile of its
    sparse feature matches' disparities, widened, never below 0.

    Raises
    ------
    ReconstructionError
        Too few matches: the range cannot be told from the images.
    """
    disp = _sparse_disparities(left, right)
    if len(disp) < _MIN_RANGE_MATCHES:
        raise ReconstructionError(
            f"cannot tell the disparity range from the images ({len(disp)} feature matches on the "
            "same rows): give --min-disp/--num-disp or --depth-range NEAR:FAR")
    lo, hi = np.percentile(np.asarray(disp), list(_RANGE_PERCENTILES))
    margin = _RANGE_WIDEN_SHARE * (hi - lo) + _RANGE_WIDEN_PX
    d0 = max(int(math.floor(lo - margin)), 0)
    return d0, _round_up_disparities(hi + margin - d0 + 1)


@dataclass
class Reconstruction:
    """One shot's scan (left camera frame, mm), rectification, rectified left view, kept
    pixels' disparity and predicted std ``(H, W)`` float32 px (NaN elsewhere), which were
    ``measured`` (not estimated), coverage, search range, noise and timings."""

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
                  opts: ReconstructOptions) -> tuple[int, int]:
    """The disparity search range: as given, from a depth range, from the rig's
    convergence distance, or from the images (bounded by ``max_disparity``)."""
    if opts.min_disp is not None:
        return int(opts.min_disp), int(opts.num_disp)  # type: ignore[arg-type]
    if opts.depth_range_mm is not None:
        return disparity_range(rect, opts.depth_range_mm)
    wd = convergence_distance_mm(rig)
    if wd is not None:
        near, far = _CONVERGENCE_DEPTH_FACTORS
        return disparity_range(rect, (near * wd, far * wd))
    max_disparity = opts.max_disparity
    try:
        d0, n = estimate_disparity_range(left, right)
    except ReconstructionError:
        if max_disparity is None:
            raise
        return 0, _round_up_disparities(math.floor(max_disparity) + 2)
    if max_disparity is not None:
        d1 = min(d0 + n - 1, int(math.floor(max_disparity)) + 1)
        d0 = max(d0, 0)
        n = _round_up_disparities(d1 - d0 + 1)
    return d0, n


def _coverage_mask(maps: RectifyMaps, size: tuple[int, int]) -> NDArray[np.bool_]:
    """Rectified-left pixels whose source lies inside the left view."""
    w, h = size
    return (maps.left_x >= 0) & (maps.left_x <= w - 1) & (maps.left_y >= 0) & (maps.left_y <= h - 1)


#: A winner within this (px) of the first or last disparity level may have its true
#: minimum beyond the range: such pixels count as outside the range.
_RANGE_LOW_MARGIN_PX = 0.5
_RANGE_HIGH_MARGIN_PX = 1.5
#: Radii (px) of the local planes that fill unmeasured pixels, tried from the smallest.
_FILL_RADII_PX = (8, 24, 64)


@dataclass
class _Selection:
    """Rectified-left pixel classes (each (H, W) bool) the later stages use."""

    covered: NDArray[np.bool_]
    in_range: NDArray[np.bool_]
    textured: NDArray[np.bool_]
    dark: NDArray[np.bool_]
    rim: NDArray[np.bool_]
    outside: NDArray[np.bool_]
    hidden: NDArray[np.bool_]
    usable: NDArray[np.bool_]
    measured: NDArray[np.bool_]
    holes: NDArray[np.bool_]


def _rectify(views: tuple[NDArray, NDArray], rig: StereoRig, alpha: float
             ) -> tuple[Rectification, RectifyMaps, NDArray, NDArray, NDArray[np.bool_]]:
    """The rectification, its maps, both rectified views and the left view's coverage."""
    rect = compute_rectification(rig, alpha=alpha)
    maps = rectify_maps(rig, rect)
    left, right = maps.remap(*views)
    return rect, maps, left, right, _coverage_mask(maps, rig.left.size)


def _select(left: NDArray, res: StereoResult, covered: NDArray[np.bool_], min_disp: int, num_disp: int,
            opts: ReconstructOptions) -> tuple[float, _Selection]:
    """The shot's noise and which pixels to refine (``measured``) or estimate (``holes``)."""
    noise = estimate_noise(left, covered)
    dense = res.disparity
    in_range = covered & (dense > min_disp + _RANGE_LOW_MARGIN_PX) & \
        (dense < min_disp + num_disp - _RANGE_HIGH_MARGIN_PX)
    tex = textured(left, noise, window=opts.refine_window)
    dark = unlit(left, noise, tex) & covered
    # a match whose census window reaches unlit background is the edge's, not the pixel's
    rim = near(dark, max(opts.match.census_window) // 2)
    occluded, outside = occlusions(dense)
    hidden = (occluded | outside) & ~res.valid
    usable = in_range & ~dark & ~rim
    measured = res.valid & usable & tex
    holes = ~res.valid & usable & tex & ~hidden
    return noise, _Selection(covered, in_range, tex, dark, rim, outside, hidden, usable, measured, holes)


def _refine(views: tuple[NDArray, NDArray], maps: RectifyMaps, left: NDArray, right: NDArray,
            res: StereoResult, sel: _Selection, noise: float, opts: ReconstructOptions
            ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Slanted-plane refinement of the measured pixels and the holes: disparity and its
    std (NaN where not refined or inconsistent)."""
    dense = res.disparity
    refined = np.full(dense.shape, np.nan, np.float32)
    own_std = np.full(dense.shape, np.nan, np.float32)
    targets = sel.measured | sel.holes
    if not targets.any():
        return refined, own_std
    rows = np.flatnonzero(targets.any(axis=1))
    r0, r1 = rows[0] - opts.refine_window[0], rows[-1] + opts.refine_window[0]
    if opts.refine_interpolation == "bspline":
        left_r, right_r = _bspline_views(views, maps, r0, r1)
    else:
        left_r, right_r = left, right
    band = (max(r0, 0), min(r1 + 1, right_r.shape[0]))
    if res.right_gain is not None and not res.right_gain.negligible():
        right_r = np.array(right_r, dtype=np.float32)
        right_r[band[0]:band[1]] = res.right_gain.apply(right_r[band[0]:band[1]], row0=band[0])
    left_r, right_r = _refinement_view(left_r, noise, band), _refinement_view(right_r, noise, band)
    d_ref, _, d_std = refine_slanted(left_r, right_r, dense, sel.measured, window=opts.refine_window,
                                     extra=sel.holes, orientation_weight=opts.refine_orientation_weight,
                                     curvature=opts.refine_curvature, max_change=_MAX_REFINE_CHANGE_PX)
    ok = targets & np.isfinite(d_std)
    refined[ok] = d_ref[ok]
    own_std[ok] = d_std[ok]
    return refined, own_std


def _fill(dense: NDArray, refined: NDArray, own_std: NDArray, disparity: NDArray, measured_ok: NDArray,
          sel: _Selection, *, open_regions: bool = True
          ) -> tuple[NDArray[np.bool_], NDArray[np.float32], NDArray[np.float32]]:
    """Unmeasured pixels keep the matcher's estimate with the local planes' prediction
    std widened by the estimate's distance from them: ``(estimated, disparity, std)``.
    Untextured pixels are filled only where measured surface encloses them; without
    ``open_regions`` (a search reaching infinity, where what lies beyond a surface may be
    sky) every unmeasured pixel needs measured surface above, below and to both sides
    within the planes' reach, occlusions excepted."""
    unmeasured = sel.usable & ~measured_ok
    targets = unmeasured & (sel.textured | enclosed(unmeasured & ~sel.textured, sel.dark | sel.rim | ~sel.covered))
    if not open_regions:
        targets &= sel.hidden | surrounded(measured_ok, _FILL_RADII_PX[-1])
    est = np.where(np.isfinite(refined), refined, dense).astype(np.float32)
    e_own = np.where(np.isfinite(own_std), own_std, 0.0).astype(np.float32)
    plane = np.full(dense.shape, np.nan, np.float32)
    p_std = np.full(dense.shape, np.nan, np.float32)
    hidden, outside = sel.hidden, sel.outside
    for sides, m in ((("centre",), targets & ~hidden), (("left", "right"), targets & hidden & outside),
                     (("left",), targets & hidden & ~outside)):
        if m.any():
            pe, ps = fill_from_planes(disparity, measured_ok, m, sides=sides, radii=_FILL_RADII_PX)
            plane[m], p_std[m] = pe[m], ps[m]
    e_std = np.sqrt(e_own ** 2 + p_std ** 2 + (est - plane) ** 2)
    return targets & np.isfinite(e_std), est, e_std


def _keep(disparity: NDArray, std: NDArray, candidates: NDArray[np.bool_], max_std: float
          ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Keep the candidates whose std is at most ``max_std`` (the rest set to NaN in
    place): ``(kept, low_confidence)``."""
    kept = candidates & (std <= max_std)
    low_conf = candidates & ~kept
    disparity[~kept] = np.nan
    std[~kept] = np.nan
    return kept, low_conf


#: Where the disparity search reaches 0 (infinity: two-camera pairs without a stated depth
#: range), a point needs its disparity this many stds above 0, its own std and the
#: matcher's median one, to be told from infinity; nearer to 0 it is "too far to measure"
#: (sky and distance come back kilometres away otherwise: KITTI up to 14,000 km).
FAR_SIGMAS = 3.0


def _too_far(disparity: NDArray, std: NDArray, kept: NDArray[np.bool_], measured_ok: NDArray[np.bool_]
             ) -> tuple[NDArray[np.bool_], float]:
    """Kept pixels whose disparity is within :data:`FAR_SIGMAS` stds of 0 (set to NaN in
    place), and the matcher's median std that floor used (NaN without measured pixels)."""
    ref = std[kept & measured_ok]
    med = float(np.median(ref)) if ref.size else float("nan")
    floor = FAR_SIGMAS * np.maximum(std, med if ref.size else 0.0)
    far = kept & (disparity < floor)
    disparity[far] = np.nan
    std[far] = np.nan
    return far, med


def _report(kept: NDArray, measured_ok: NDArray, inconsistent: NDArray, isolated: NDArray, low_conf: NDArray,
            sel: _Selection, too_far: NDArray) -> Coverage:
    """The share kept and, for each of the dropped, the first reason that applies."""
    not_kept = sel.covered & ~kept
    hidden = sel.hidden
    reason_masks = {
        "outside depth range": not_kept & ~sel.in_range,
        "too far to measure": not_kept & too_far,
        "no texture": not_kept & (sel.dark | ~sel.textured) & ~hidden & ~low_conf,
        "silhouette": not_kept & sel.rim & ~low_conf,
        "occluded": not_kept & hidden & ~low_conf,
        "inconsistent": not_kept & inconsistent & ~low_conf,
        "isolated match": not_kept & isolated & ~low_conf,
        "unmatched": np.zeros_like(not_kept),  # the remainder, below
        "low confidence": not_kept & low_conf,
    }
    dropped, taken = {}, np.zeros_like(kept)
    for name in REASONS:
        m = reason_masks[name] & ~taken
        dropped[name] = int(m.sum())
        taken |= m
    rest = not_kept & ~taken  # holes nothing around could serve: failed matches if textured
    dropped["unmatched"] += int((rest & sel.textured).sum())
    dropped["no texture"] += int((rest & ~sel.textured).sum())
    return Coverage(int(sel.covered.sum()), int((kept & measured_ok).sum()), int((kept & ~measured_ok).sum()),
                    dropped)


def _triangulate(disparity: NDArray, std: NDArray, rect: Rectification, left: NDArray,
                 min_disp: int, num_disp: int, opts: ReconstructOptions) -> Scan:
    depth = rect.disparity_to_depth(disparity)
    if opts.smooth_sigma_px > 0:
        depth = smooth_depth(depth, sigma_px=opts.smooth_sigma_px, focal_px=rect.focal_px,
                             baseline_mm=rect.baseline_mm)
    scan = scan_from_depth(depth, rect, left, std)
    scan.meta.update(focal_px=rect.focal_px, baseline_mm=rect.baseline_mm, min_disp=int(min_disp),
                     num_disp=int(num_disp), smooth_sigma_px=float(opts.smooth_sigma_px),
                     min_confidence=float(opts.min_confidence))
    return scan


class _Stopwatch:
    # wall time per stage, reported through ``progress`` as the stages start

    def __init__(self, progress: ProgressFn, total: int) -> None:
        self.progress, self.total, self.times = progress, total, {}
        self._step, self._name, self._t0 = 0, "", 0.0

    def start(self, name: str, *, announce: bool = True) -> None:
        self.stop()
        if announce:
            self.progress(self._step, self.total, name)
            self._step += 1
        self._name, self._t0 = name, time.perf_counter()

    def stop(self) -> None:
        if self._name:
            self.times[self._name] = time.perf_counter() - self._t0
            self._name = ""


_STAGES = 5  # rectify, match, select, refine, triangulate (fill is timed within refine's step)


def _reconstruct_views(views: tuple[NDArray, NDArray], rig: StereoRig, opts: ReconstructOptions,
                       progress: ProgressFn) -> Reconstruction:
    """The pipeline on the two (un-flipped) views of a calibrated rig."""
    max_std = std_from_confidence(opts.min_confidence) if opts.min_confidence > 0 else np.inf
    clock = _Stopwatch(progress, _STAGES)
    clock.start("rectify")
    rect, maps, left, right, covered = _rectify(views, rig, opts.alpha)
    clock.start("match")
    min_disp, num_disp = _search_range(rig, rect, left, right, opts)
    res = match_stereo_full(left, right, min_disp=int(min_disp), num_disp=int(num_disp), options=opts.match)
    clock.start("select")
    noise, sel = _select(left, res, covered, min_disp, num_disp, opts)
    clock.start("refine")
    refined, own_std = _refine(views, maps, left, right, res, sel, noise, opts)
    measured_ok = sel.measured & np.isfinite(own_std)
    inconsistent = sel.measured & ~measured_ok
    reaches_infinity = min_disp <= 0  # a two-camera pair without a stated depth range
    isolated = np.zeros_like(measured_ok)
    if reaches_infinity:  # there a chance match is a point kilometres away: matches need company
        isolated = isolated_matches(measured_ok, sel.usable & sel.textured & ~sel.hidden,
                                    texture_energy(left, window=opts.refine_window))
        measured_ok &= ~isolated
    disparity = np.where(measured_ok, refined, np.nan).astype(np.float32)
    std = np.where(measured_ok, own_std, np.nan).astype(np.float32)
    clock.start("fill", announce=False)
    estimated = np.zeros_like(sel.measured)
    if opts.fill:
        estimated, est, e_std = _fill(res.disparity, refined, own_std, disparity, measured_ok, sel,
                                      open_regions=not reaches_infinity)
        disparity[estimated] = est[estimated]
        std[estimated] = e_std[estimated]
    kept, low_conf = _keep(disparity, std, measured_ok | estimated, max_std)
    too_far, med_std = np.zeros_like(kept), float("nan")
    if reaches_infinity:  # drop what cannot be told from infinity
        too_far, med_std = _too_far(disparity, std, kept, measured_ok)
        kept &= ~too_far
    clock.stop()
    cov = _report(kept, measured_ok, inconsistent, isolated, low_conf, sel, too_far)
    clock.start("triangulate")
    scan = _triangulate(disparity, std, rect, left, min_disp, num_disp, opts)
    if np.isfinite(med_std) and med_std > 0:
        scan.meta["max_range_mm"] = float(rect.focal_px * rect.baseline_mm / (FAR_SIGMAS * med_std))
    clock.stop()
    progress(_STAGES, _STAGES, "done")
    return Reconstruction(scan, rect, left, disparity, std, kept & measured_ok, cov, int(min_disp),
                          int(num_disp), float(noise), clock.times)


def reconstruct_shot(shot: NDArray, rig: StereoRig, options: ReconstructOptions | None = None, *,
                     progress: ProgressFn = null_progress) -> Reconstruction:
    """Split a side-by-side shot ``(H, W, 3) uint8`` (``rig.split.sensor_size``) with
    ``rig.split``, then :func:`reconstruct_pair`."""
    img = check_array(shot, "shot", ndim=(2, 3))
    sw, sh = rig.split.sensor_size
    if img.shape[1] != sw or img.shape[0] != sh:
        raise InputError(
            f"shot is {img.shape[1]}x{img.shape[0]} but the calibration expects a {sw}x{sh} sensor image"
        )
    return reconstruct_pair(*rig.split.split(img), rig, options, progress=progress)


def reconstruct_pair(left: NDArray, right: NDArray, rig: StereoRig, options: ReconstructOptions | None = None,
                     *, progress: ProgressFn = null_progress) -> Reconstruction:
    """Rectify, match, select, refine, fill and triangulate the views ``(h, w, 3)`` uint8
    (each ``rig.left.size``, un-flipped) of a rig; ``options`` None = the defaults."""
    opts = ReconstructOptions() if options is None else options
    la = check_array(left, "left", ndim=(2, 3))
    ra = check_array(right, "right", ndim=(2, 3))
    for name, a, cam in (("left", la, rig.left), ("right", ra, rig.right)):
        if (a.shape[1], a.shape[0]) != cam.size:
            raise InputError(f"{name} view is {a.shape[1]}x{a.shape[0]} but the calibration expects "
                             f"{cam.size[0]}x{cam.size[1]}")
    return _reconstruct_views((la, ra), rig, opts, progress)


#: Depth map formats :func:`~prism3d.io.images.write_depth` writes.
_DEPTH_SUFFIXES = (".tif", ".tiff", ".npy", ".npz")


def _check_outputs(out_ply: Path, disparity_out: Path | None, depth_out: Path | None,
                   mesh_out: Path | None) -> list[Path]:
    """The output paths, checked: no directory, no two alike, known suffixes."""
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
    if depth_out is not None and Path(depth_out).suffix.lower() not in _DEPTH_SUFFIXES:
        raise InputError(f"{depth_out}: the depth is written as .tiff, .npy or .npz")
    return outs


def _read_views(shot_path: str | Path | None, left_path: str | Path | None, right_path: str | Path | None,
                rig: StereoRig) -> tuple[tuple[NDArray, NDArray], str]:
    """The two views (from a side-by-side shot or two files) and their source's name."""
    if left_path is not None:
        left, right = read_image(left_path), read_image(right_path)  # type: ignore[arg-type]
        if left.shape != right.shape:
            raise InputError(f"{left_path} is {left.shape[1]}x{left.shape[0]} but {right_path} is "
                             f"{right.shape[1]}x{right.shape[0]}: the two views must have the same size")
        return (left, right), f"{left_path}, {right_path}"
    shot = read_image(shot_path)  # type: ignore[arg-type]
    sw, sh = rig.split.sensor_size
    if shot.shape[1] != sw or shot.shape[0] != sh:
        raise InputError(f"{shot_path}: image is {shot.shape[1]}x{shot.shape[0]} but the calibration "
                         f"describes a {sw}x{sh} sensor (two {sw // 2}x{sh} views side by side)")
    return rig.split.split(shot), str(shot_path)


def _write_outputs(rec: Reconstruction, outs: list[Path], out_ply: Path, disparity_out: Path | None,
                   depth_out: Path | None, mesh_out: Path | None) -> None:
    """All files to temporary names first, then moved into place together."""
    faces = verts = None
    if mesh_out is not None:
        grid, m = rec.scan.grid()
        verts, faces = mesh_from_grid(grid, m, focal_px=rec.rect.focal_px)
    meta = [f"{k} {v}" for k, v in rec.scan.meta.items()]
    meta.append("coverage " + " ".join(f"{k}={v:.4f}" for k, v in rec.coverage.shares().items()))
    props = rec.scan.point_properties()
    px = rec.scan.pixels  # 1: matched, 0: estimated from its neighbours (local planes)
    props["measured"] = rec.measured[px[:, 0], px[:, 1]].astype(np.uint8)
    with contextlib.ExitStack() as stack:
        tmp = {p: stack.enter_context(atomic_path(p)) for p in outs}
        write_ply(tmp[out_ply], rec.scan.points, colors=rec.scan.colors, normals=rec.scan.normals,
                  extra=props, comments=["prism3d scan", "units mm", "frame left camera (OpenCV axes)", *meta])
        if mesh_out is not None:
            write_ply(tmp[Path(mesh_out)], verts, faces=faces, colors=rec.scan.colors, normals=rec.scan.normals,
                      comments=["prism3d scan mesh", "units mm", "frame left camera (OpenCV axes)", *meta])
        if disparity_out is not None:
            write_pfm(tmp[Path(disparity_out)], np.where(np.isfinite(rec.disparity), rec.disparity, np.inf))
        if depth_out is not None:
            write_depth(tmp[Path(depth_out)], rec.scan.depth_mm)


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
    options: ReconstructOptions | None = None,
    progress: ProgressFn = null_progress,
) -> Reconstruction:
    """What ``prism3d reconstruct`` calls: a side-by-side shot or two view files and a
    calibration (any format :func:`~prism3d.capture.calib_formats.load_stereo_calibration`
    reads) to the scan PLY (with per-point ``confidence``, ``disparity_std``,
    ``depth_std`` and ``measured``: 0 for a point estimated from its neighbours) and optionally the disparity (PFM, ``inf`` where no point), the depth
    (float32 mm) and a mesh. A range the calibration states bounds an estimated one."""
    opts = ReconstructOptions() if options is None else options
    out_ply = Path(out_ply)
    outs = _check_outputs(out_ply, disparity_out, depth_out, mesh_out)  # type: ignore[arg-type]
    two_files = left_path is not None or right_path is not None
    if two_files == (shot_path is not None) or (two_files and (left_path is None or right_path is None)):
        raise InputError("give either a side-by-side SHOT or both --left and --right view files")
    cal = load_stereo_calibration(calib_paths, image_size=image_size)
    views, source = _read_views(shot_path, left_path, right_path, cal.rig)
    if opts.min_disp is None and opts.depth_range_mm is None and \
            cal.disparity_range is not None and convergence_distance_mm(cal.rig) is None:
        opts = dataclasses.replace(opts, max_disparity=_stated_max_disparity(cal))
    try:
        rec = reconstruct_pair(*views, cal.rig, opts, progress=progress)
    except InputError as exc:
        raise InputError(f"{source}: {exc}") from exc

    # what the scan came from, in its header: a model stitched from it can say so
    shots = [shot_path] if shot_path is not None else [left_path, right_path]
    calibs = list(calib_paths) if isinstance(calib_paths, (list, tuple)) else [calib_paths]
    rec.scan.meta.update(shot_sha256=sha256_files(shots), calibration_sha256=sha256_files(calibs))
    _write_outputs(rec, outs, out_ply, disparity_out, depth_out, mesh_out)  # type: ignore[arg-type]
    return rec


def _stated_max_disparity(cal: Any) -> float:
    """The largest rectified disparity a calibration's stated range allows (its
    ``doffs`` added: rectification moves the views by it)."""
    lo, n = cal.disparity_range
    return float(lo + n - 1 + (cal.doffs or 0.0))
