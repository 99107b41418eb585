"""Dense stereo matching: census cost, semi-global aggregation, sub-pixel refinement.

:func:`match_stereo` is the entry point other tools call; :func:`match_stereo_full`
also returns the validity and confidence maps. Inputs are a *rectified* pair
(rows are epipolar lines); the output follows the project convention
``d = x_left - x_right`` in pixels, float32.

Pipeline (numba kernels in :mod:`._match_kernels`):

1. census transform (5x5 window by default) of every colour channel; matching cost
   = Hamming distance summed over channels (the projector grating is colour coded,
   so each channel carries its own texture) plus a truncated absolute colour
   difference (after matching the right view's per-channel mean and spread to the
   left's), as in AD-Census [6];
2. semi-global aggregation along 4 (default) or 8 paths with P2 adaptive to the
   image gradient;
3. winner-take-all, uniqueness ratio, left-right check with the right disparity taken
   from the same aggregated volume, small-segment (speckle) removal;
4. sub-pixel: equiangular fit on the aggregated costs [4], then 1-D Lucas-Kanade
   warping [5] on band-passed intensities, the right view interpolated with cubic
   B-splines [7] (no pile-up at integers: RMS ~0.01 px on a textured shift sweep);
5. dense fill: background-favouring horizontal fill followed by a median on the
   filled pixels only.

Large searches (``W * H * num_disp`` above :data:`C2F_AUTO_CELLS`) take a
coarse-to-fine path: full SGM on a 2^n-times smaller pyramid level, then at full
resolution each pixel searches only a narrow window (``fine_window`` levels) around
the upsampled coarse disparity, so memory is ``H * W * fine_window * 3`` bytes.

References
----------
.. [1] H. Hirschmüller, "Stereo processing by semiglobal matching and mutual
   information", IEEE TPAMI 30(2), 2008.
.. [2] R. Zabih and J. Woodfill, "Non-parametric local transforms for computing
   visual correspondence", ECCV 1994.
.. [3] M. Rothermel et al., "SURE: Photogrammetric surface reconstruction from
   imagery", LC3D Workshop 2012 (tSGM).
.. [4] M. Shimizu and M. Okutomi, "Sub-pixel estimation error cancellation on
   area-based matching", IJCV 63(3), 2005.
.. [5] B. D. Lucas and T. Kanade, "An iterative image registration technique with an
   application to stereo vision", IJCAI 1981.
.. [6] X. Mei et al., "On building an accurate stereo matching system on graphics
   hardware", ICCV Workshops 2011 (AD-Census).
.. [7] M. Unser, "Splines: a perfect fit for signal and image processing", IEEE Signal
   Processing Magazine 16(6), 1999.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_choice, check_same_shape
from prism3d.errors import InputError, ReconstructionError

from . import _match_kernels as _k
from .photometric import GainField, fit_gain_field

__all__ = ["C2F_AUTO_CELLS", "MatchOptions", "StereoResult", "match_files", "match_stereo", "match_stereo_full"]

log = logging.getLogger(__name__)

#: Above this many cost cells (W * H * num_disp) the coarse-to-fine path is used.
C2F_AUTO_CELLS = 48_000_000
#: Target size (cells) of the coarse level's full cost volume.
_COARSE_CELLS = 12_000_000


@dataclass(frozen=True)
class StereoResult:
    """Result of :func:`match_stereo_full`.

    Attributes
    ----------
    disparity : (H, W) float32
        Dense disparity ``x_left - x_right`` in pixels, holes filled (no NaN).
    valid : (H, W) bool
        Pixels that passed the uniqueness and left-right checks and speckle removal
        (not filled).
    confidence : (H, W) float32
        In [0, 1]: relative gap between the best aggregated cost and the best one
        outside +-1 level of the winner; 0 where not ``valid``.
    raw : (H, W) float32
        The unfilled disparity: ``disparity`` where ``valid``, NaN elsewhere.
    coarse_to_fine : bool
        Whether the coarse-to-fine path was used.
    right_gain : GainField or None
        The gain applied to the right view before matching (``equalize``); ``None``
        when off.
    """

    disparity: NDArray[np.float32]
    valid: NDArray[np.bool_]
    confidence: NDArray[np.float32]
    raw: NDArray[np.float32]
    coarse_to_fine: bool
    right_gain: GainField | None = None


@dataclass(frozen=True)
class MatchOptions:
    """Options of :func:`match_stereo_full` (defaults: docs/matching.md)."""

    coarse_to_fine: bool | None = None
    census_window: tuple[int, int] = (5, 5)
    p1: int = 10
    p2: int = 120
    p2_gamma: float = 20.0
    paths: int = 4
    uniqueness: float = 5.0
    lr_max_diff: float = 1.0
    speckle_size: int | None = None
    speckle_range: float = 2.0
    subpixel: str = "lk"
    lk_window: int = 5
    lk_iters: int = 1
    fine_window: int | None = None
    ad_weight: float = 1.0
    ad_trunc: float = 15.0
    ad_mode: str = "intensity"
    equalize: bool = True


class _Workspace(threading.local):
    """Scratch volumes (census codes, features, costs, path sums) kept between calls,
    one set per thread, at most ``CAP`` bytes in all.

    A fresh multi-megabyte array is handed out by ``mmap`` once glibc's dynamic
    threshold says so and its pages are faulted in and zeroed on first touch: on a
    384x288 pair that was ~1900 page faults and ~4 ms of system time per call, a
    quarter of the match (measured). Reusing the arrays, as OpenCV's matchers reuse
    their buffer, avoids it. Every kernel overwrites the whole scratch array, so
    nothing leaks from one call into the next; larger requests are allocated and
    dropped as usual (a 5 MP coarse-to-fine match keeps at most ``CAP``).
    """

    CAP = 64 << 20

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def take(self, name: str, shape: tuple[int, ...], dtype: Any, keep: bool = True
             ) -> np.ndarray:
        """An uninitialised C-contiguous array for ``name`` (the previous one when its
        shape and dtype match; the caller must not keep it past its call). With
        ``keep`` False (a large problem) the array is neither reused nor kept, so
        that it is freed as soon as the caller drops it (peak memory as without the
        workspace)."""
        dtype = np.dtype(dtype)
        old = self.arrays.pop(name, None)
        if keep and old is not None and old.shape == tuple(shape) and old.dtype == dtype:
            self.arrays[name] = old
            return old
        del old
        out = np.empty(shape, dtype)
        if keep and out.nbytes + sum(a.nbytes for a in self.arrays.values()) <= self.CAP:
            self.arrays[name] = out
        return out

    @classmethod
    def small(cls, h: int, w: int, levels: int) -> bool:
        """True when a match of ``levels`` levels at ``h x w`` is small enough to keep
        its scratch (cost and path-sum volumes, 3 bytes a cell, within ``CAP``)."""
        return 3 * h * w * levels <= cls.CAP


_WS = _Workspace()


def _as_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name}: expected an integer, got {value!r} ({type(value).__name__})")
    return int(value)


def _prepare(img: Any, name: str) -> NDArray[np.uint8] | NDArray[np.float32]:
    """(H, W, C) C-contiguous image: uint8 kept as is (no copy when possible), float
    scaled to [0, 255] float32."""
    arr = check_array(img, name, ndim=(2, 3), dtype_kind="uf", min_size=1)
    if arr.dtype.kind == "u" and arr.dtype != np.uint8:
        raise InputError(f"{name}: expected uint8 or float image, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] not in (1, 3):
        raise InputError(f"{name}: expected (H, W) or (H, W, 3) image, got shape {arr.shape}")
    if arr.dtype == np.uint8:
        out8 = np.ascontiguousarray(arr)
        return out8[:, :, None] if out8.ndim == 2 else out8
    out = arr.astype(np.float32)
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(out)):
            raise InputError(f"{name}: expected finite values, found NaN or inf")
        out *= 255.0
    if out.ndim == 2:
        out = out[:, :, None]
    return np.ascontiguousarray(out)


def _census(img: NDArray[Any], ry: int, rx: int, reverse: bool) -> NDArray[np.unsignedinteger]:
    """(C, H, W) census codes (uint32 up to 32 comparisons, else uint64) of an
    (H, W, C) image, borders replicated; rows mirrored when ``reverse`` (the right
    view's layout for :func:`._match_kernels.matching_cost`)."""
    h, w, c = img.shape
    nbits = (2 * ry + 1) * (2 * rx + 1) - 1
    out = np.empty((c, h, w), np.uint32 if nbits <= 32 else np.uint64)
    _k.census_hwc(np.ascontiguousarray(img), ry, rx, bool(reverse), out)
    return out


def _grey(img: NDArray[Any], out: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """(H, W) float32 channel mean of an (H, W, C) image (into ``out`` when given)."""
    if out is None:
        out = np.empty(img.shape[:2], np.float32)
    _k.grey_hwc(img, out)
    return out


def _bandpass(grey: NDArray[np.float32], out: NDArray[np.float32] | None = None,
              tmp: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """Grey minus its 11x11 box mean: removes exposure offsets before LK refinement
    (into ``out``, with scratch ``tmp``, when given)."""
    box = cv2.blur(grey, (11, 11), dst=tmp, borderType=cv2.BORDER_REFLECT)
    return np.subtract(grey, box, out=out)


_DIRS4 = ((0, 1), (0, -1), (1, 0), (-1, 0))
_DIRS8 = _DIRS4 + ((1, 1), (1, -1), (-1, 1), (-1, -1))


def _to_u8(img: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Non-negative float image -> uint8, rounded and saturated (OpenCV, fast)."""
    out = np.empty(img.shape, np.uint8)
    for c in range(img.shape[2]):
        out[:, :, c] = cv2.convertScaleAbs(np.ascontiguousarray(img[:, :, c]))
    return out


def _features(left: NDArray[Any], right: NDArray[Any], mode: str, reverse: bool,
              keep: bool = False) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Per-pixel uint8 features of the AD term for both views, planar (C, H, W), the
    right view's rows mirrored when ``reverse``.

    ``"intensity"``: the colour values, the right view's channels first matched in
    mean and standard deviation to the left's (global exposure / gain compensation);
    ``"gradient"``: horizontal central differences, offset by 128.
    """
    h, w, nc = left.shape
    if mode == "gradient":
        out = []
        for img in (left, right):
            f = img.astype(np.float32)
            g = np.full_like(f, 128.0)
            g[:, 1:-1] += 0.5 * (f[:, 2:] - f[:, :-2])
            out.append(np.ascontiguousarray(np.moveaxis(_to_u8(g), 2, 0)))
        if reverse:
            out[1] = np.ascontiguousarray(out[1][:, :, ::-1])
        return out[0], out[1]
    ml, sl = cv2.meanStdDev(left)
    mi, si = cv2.meanStdDev(right)
    gain = np.ones(nc, np.float32)
    offset = np.zeros(nc, np.float32)
    for c in range(nc):
        s_i, s_l = float(si[c][0]), float(sl[c][0])
        m_i, m_l = float(mi[c][0]), float(ml[c][0])
        g = s_l / s_i if s_i > 1e-6 else 1.0
        gain[c] = np.float32(g)
        offset[c] = np.float32(m_l - m_i * g)
    fl = _WS.take("feat_l", (nc, h, w), np.uint8, keep)
    fr = _WS.take("feat_r", (nc, h, w), np.uint8, keep)
    _k.features_hwc(left, right, gain, offset, bool(reverse), fl, fr)
    return fl, fr


@dataclass(frozen=True)
class _Params:
    census_ry: int
    census_rx: int
    p1: int
    p2: int
    p2_gamma: float
    paths: int
    uniqueness: float
    lr_max_diff: float
    speckle_size: int
    speckle_range: float
    subpixel: str
    lk_window: int
    lk_iters: int
    ad_weight: float
    ad_trunc: float
    ad_mode: str


def _match_level(
    left: NDArray[Any],
    right: NDArray[Any],
    dlo: NDArray[np.int32],
    k_levels: int,
    prm: _Params,
    *,
    subpixel: str,
    speckle_size: int,
    dmin: int | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """One SGM pass with per-pixel windows; returns (raw disparity NaN=invalid, conf).

    ``dmin`` set: a full search (``dlo == dmin`` everywhere). With 4 paths the levels
    are padded to a multiple of 16 in the cost volumes (whole vectors in the SGM
    kernels; the padded levels are never selected).
    """
    h, w, nc = left.shape
    ry, rx = prm.census_ry, prm.census_rx
    nbits = (2 * ry + 1) * (2 * rx + 1) - 1
    ctype = np.uint32 if nbits <= 32 else np.uint64
    keep = _Workspace.small(h, w, _volume_levels(k_levels))
    cl = _WS.take("census_l", (nc, h, w), ctype, keep)
    cr = _WS.take("census_r", (nc, h, w), ctype, keep)
    _k.census_hwc(left, ry, rx, False, cl)
    _k.census_hwc(right, ry, rx, True, cr)
    oob = np.uint8(min(255, (nbits * nc) // 2))
    # levels padded to a multiple of 16 (vector width) in the volumes; padded levels
    # are held at "infinite" cost by the SGM kernels, never selected
    kp = _volume_levels(k_levels)
    if prm.ad_weight > 0:
        fl, fr = _features(left, right, prm.ad_mode, True, keep)
    else:
        fl = fr = np.zeros((0, h, w), np.uint8)
    nf = max(fl.shape[0], 1)
    # AD cost of a summed |difference| a: weight * nc * min(a / nf, trunc)
    ad_scale = prm.ad_weight * nc / nf
    ad_clip = prm.ad_trunc * nf
    cost = _WS.take("cost", (h, w, kp), np.uint8, keep)
    _k.matching_cost(cl, cr, fl, fr, ad_scale, ad_clip, dlo, kp, oob, cost)
    del cl, cr, fl, fr
    guide = _grey(left, _WS.take("guide", (h, w), np.float32, keep))
    p1 = np.int32(prm.p1 * nc)
    p2 = np.int32(prm.p2 * nc)
    gamma = float(prm.p2_gamma)
    agg = _WS.take("agg", (h, w, kp), np.uint16, keep)
    _k.sgm_horizontal(cost, dlo, guide, p1, p2, gamma, k_levels, agg)
    if prm.paths == 8:
        for dy, dx in _DIRS8[4:]:
            _k.aggregate_path(cost, dlo, guide, p1, p2, gamma, dy, dx, k_levels, agg)
    disp = np.empty((h, w), np.float32)
    conf = _WS.take("conf", (h, w), np.float32, keep)  # internal: the final one is a copy
    nthreads = max(1, numba.get_num_threads())
    block = int(min(128, max(16, -(-w // (4 * nthreads)))))
    _k.sgm_vertical_wta(cost, dlo, guide, p1, p2, gamma, k_levels, block,
                        float(prm.uniqueness), agg, disp, conf)
    del cost
    _k.right_lr_check(agg, dlo, k_levels, float(prm.lr_max_diff), disp)
    del agg
    if speckle_size > 0:
        _k.remove_speckles(disp, speckle_size, np.float64(prm.speckle_range))
    if subpixel == "lk":
        tmp = _WS.take("box", (h, w), np.float32, keep)
        lg = _bandpass(guide, _WS.take("band_l", (h, w), np.float32, keep), tmp)
        rg = _bandpass(_grey(right, _WS.take("grey_r", (h, w), np.float32, keep)),
                       _WS.take("band_r", (h, w), np.float32, keep), tmp)
        # one spare (zero) column on the left, three on the right (8-lane products)
        rcoef = _WS.take("rcoef", (h, w + 4), np.float32, keep)
        rcoef[:, 0] = 0.0
        rcoef[:, w + 1:] = 0.0
        _k.bspline_rows(rg, rcoef[:, 1:w + 1])
        del rg
        r = prm.lk_window // 2
        _k.refine_lk_gram(lg, rcoef, disp, r, r, prm.lk_iters, 1.0, _lk_stripes(h))
    return disp, conf


def _volume_levels(k_levels: int) -> int:
    """Levels held in the cost volumes: ``k_levels`` rounded up to whole 16-level
    vectors (the padding is held at "infinite" cost by the SGM kernels)."""
    return -(-k_levels // 16) * 16


def _lk_stripes(h: int) -> int:
    """Row stripes of the Lucas-Kanade pass: 4 per thread (load balance), each at
    least 32 rows (the window sums slide down a stripe; a stripe start sums afresh)."""
    return max(1, min(4 * max(1, numba.get_num_threads()), h // 32))


def _fill(raw: NDArray[np.float32]) -> NDArray[np.float32]:
    filled = np.empty_like(raw)
    _k.fill_holes(raw, filled)
    _k.fill_columns(filled)
    out = np.empty_like(raw)
    _k.median_filled(filled, ~np.isnan(raw), 1, out)
    return out


def match_stereo_full(
    left: NDArray[Any],
    right: NDArray[Any],
    *,
    min_disp: int,
    num_disp: int,
    coarse_to_fine: bool | None = None,
    census_window: tuple[int, int] = (5, 5),
    p1: int = 10,
    p2: int = 120,
    p2_gamma: float = 20.0,
    paths: int = 4,
    uniqueness: float = 5.0,
    lr_max_diff: float = 1.0,
    speckle_size: int | None = None,
    speckle_range: float = 2.0,
    subpixel: str = "lk",
    lk_window: int = 5,
    lk_iters: int = 1,
    fine_window: int | None = None,
    ad_weight: float = 1.0,
    ad_trunc: float = 15.0,
    ad_mode: str = "intensity",
    equalize: bool = True,
    options: MatchOptions | None = None,
) -> StereoResult:
    """Match a rectified pair; return dense disparity plus validity and confidence.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) uint8, or float in [0, 1]
        Rectified grey or RGB views of the same shape. Colour is used: one census
        per channel, costs summed (a pair whose channels are all equal is treated
        as grey).
    min_disp : int
        Smallest disparity searched (may be negative or large, e.g. ~700 px).
    num_disp : int
        Number of disparity levels searched, ``> 0``: ``min_disp .. min_disp +
        num_disp - 1``.
    coarse_to_fine : bool, optional
        Force (True) or forbid (False) the coarse-to-fine path; by default it is used
        when ``W * H * num_disp > C2F_AUTO_CELLS``.
    census_window : (int, int)
        Census window (rows, cols), odd, at most 64 comparisons.
    p1, p2 : int
        SGM penalties per colour channel for 1-level and larger disparity changes.
    p2_gamma : float
        Intensity step (grey levels) at which the adaptive P2 is halved.
    paths : {4, 8}
        Number of aggregation paths.
    uniqueness : float
        Minimum margin in percent between the best cost and the best cost outside
        +-1 level of the winner.
    lr_max_diff : float
        Maximum left-right disagreement in pixels.
    speckle_size : int, optional
        Valid regions smaller than this (pixels) are invalidated; default scales
        with the image area (100 px at 450x375).
    speckle_range : float
        Disparity step (px) that separates speckle regions.
    subpixel : {"lk", "equiangular"}
        Sub-pixel method: equiangular fit then Lucas-Kanade refinement (default),
        or the equiangular fit alone (faster, some pixel-locking).
    lk_window : int
        Odd side of the square Lucas-Kanade window.
    lk_iters : int
        Maximum Gauss-Newton iterations. One is the default: the equiangular start
        is already within ~0.1 px, and on the sub-pixel shift sweep one step gives
        RMS 0.0105 px with a flatter histogram of fractional parts than two
        (0.0078 px), for ~15 % less refinement time; bad-1/bad-2 on the real pairs
        change by < 0.003.
    fine_window : int, optional
        Levels searched per pixel in the coarse-to-fine pass (default: ``2 * (scale
        + 4) + 1`` for pyramid factor ``scale``, rounded up to a multiple of 16 with
        4 paths -- 32 at the paper's geometry).
    ad_weight, ad_trunc : float
        Weight and truncation (grey levels per channel) of the colour-difference term
        added to the census cost.
    ad_mode : {"intensity", "gradient"}
        What the colour-difference term compares: the colour values (after
        ``equalize`` and a global mean/spread match) or horizontal gradients.
    equalize : bool
        Before matching, bring the right view's exposure, colour balance and
        vignetting to the left's: a census-only pass on a coarse level, then a smooth
        per-channel gain fitted to the matched pixels
        (:func:`~prism3d.reconstruct.photometric.fit_gain_field`). Views that already
        agree get a gain of ~1.

    Returns
    -------
    StereoResult

    Raises
    ------
    InputError
        Arrays of different shapes, wrong ndim/dtype, non-integer ``min_disp`` or
        ``num_disp``, ``num_disp <= 0``, or an out-of-range option.
    ReconstructionError
        No pixel passed the consistency checks.
    """
    if options is not None:  # transitional: the keywords go once callers pass options
        return match_stereo_full(left, right, min_disp=min_disp, num_disp=num_disp,
                                 **dataclasses.asdict(options))
    lf = _prepare(left, "left")
    rf = _prepare(right, "right")
    check_same_shape(lf, rf, ("left", "right"))
    min_disp = _as_int(min_disp, "min_disp")
    num_disp = _as_int(num_disp, "num_disp")
    if num_disp <= 0:
        raise InputError(f"num_disp: expected an integer > 0, got {num_disp}")
    check_choice(paths, "paths", (4, 8))
    check_choice(subpixel, "subpixel", ("lk", "equiangular"))
    check_choice(ad_mode, "ad_mode", ("intensity", "gradient"))
    if not (np.isfinite(ad_weight) and ad_weight >= 0):
        raise InputError(f"ad_weight: expected a finite number >= 0, got {ad_weight!r}")
    if not (np.isfinite(ad_trunc) and ad_trunc > 0):
        raise InputError(f"ad_trunc: expected a finite number > 0, got {ad_trunc!r}")
    if fine_window is not None and _as_int(fine_window, "fine_window") < 3:
        raise InputError(f"fine_window: expected an integer >= 3, got {fine_window}")
    if (
        len(census_window) != 2
        or any(_as_int(c, "census_window") % 2 == 0 or c < 3 for c in census_window)
        or census_window[0] * census_window[1] - 1 > 64
    ):
        raise InputError(
            f"census_window: expected two odd sizes >= 3 with rows*cols <= 65, "
            f"got {census_window!r}"
        )
    if _as_int(lk_window, "lk_window") < 3 or lk_window % 2 == 0:
        raise InputError(f"lk_window: expected an odd integer >= 3, got {lk_window}")
    for nm, v in (("p1", p1), ("p2", p2)):
        if _as_int(v, nm) <= 0:
            raise InputError(f"{nm}: expected an integer > 0, got {v}")
    if p2 <= p1:
        raise InputError(f"p2: expected p2 > p1, got p1={p1}, p2={p2}")
    if p2 * 3 * 8 > 40000:
        raise InputError(f"p2: expected at most 1600, got {p2}")

    if lf.shape[2] == 3 and _k.channels_equal(lf) and _k.channels_equal(rf):
        lf = np.ascontiguousarray(lf[..., :1])
        rf = np.ascontiguousarray(rf[..., :1])

    h, w, _ = lf.shape
    if speckle_size is None:
        speckle_size = max(4, round(100 * h * w / (450 * 375)))
        speckle_size = min(speckle_size, 400)
    prm = _Params(
        census_ry=census_window[0] // 2,
        census_rx=census_window[1] // 2,
        p1=int(p1),
        p2=int(p2),
        p2_gamma=float(p2_gamma),
        paths=int(paths),
        uniqueness=float(uniqueness),
        lr_max_diff=float(lr_max_diff),
        speckle_size=int(speckle_size),
        speckle_range=float(speckle_range),
        subpixel=subpixel,
        lk_window=int(lk_window),
        lk_iters=int(lk_iters),
        ad_weight=float(ad_weight),
        ad_trunc=float(ad_trunc),
        ad_mode=ad_mode,
    )
    cells = h * w * num_disp
    keep = _Workspace.small(h, w, num_disp)  # scratch kept between calls (small problems)
    use_c2f = cells > C2F_AUTO_CELLS if coarse_to_fine is None else bool(coarse_to_fine)
    scale = 2
    while (h // scale) * (w // scale) * (num_disp / scale) > _COARSE_CELLS and scale < 16:
        scale *= 2
    if use_c2f and (h // scale < 8 or w // scale < 8):
        use_c2f = False
    gain = None
    # the gain field is smooth: a level 4x smaller holds thousands of samples for its 15
    # terms at 1/64 of the full match's cost, when it keeps 128 px on its short side
    # (tsukuba's 384x288 at 1/4 fitted a field worse: bad-2 1.01 -> 1.22x under vignetting)
    g_scale = scale
    while g_scale < 4 and min(h, w) // (2 * g_scale) >= 128:
        g_scale *= 2
    if equalize and h // g_scale >= 8 and w // g_scale >= 8:
        gain = _right_gain(lf, rf, min_disp, num_disp, g_scale, prm)
        rf = np.ascontiguousarray(gain.apply(rf))
    if not use_c2f:
        dlo = _WS.take("dlo", (h, w), np.int32, keep)
        dlo.fill(min_disp)
        raw, conf = _match_level(lf, rf, dlo, num_disp, prm, subpixel=subpixel,
                                 speckle_size=speckle_size, dmin=min_disp)
    else:
        raw, conf = _match_c2f(lf, rf, min_disp, num_disp, scale, prm, fine_window)
    filled = _WS.take("filled", raw.shape, np.float32, keep)
    _k.fill_holes(raw, filled)
    _k.fill_columns(filled)
    dense = np.empty_like(raw)
    valid = np.empty(raw.shape, np.bool_)
    conf_out = np.empty(raw.shape, np.float32)
    _k.median_fill_final(filled, raw, conf, 1, dense, valid, conf_out)
    del filled
    if not valid.any():
        raise ReconstructionError(
            "match_stereo: no pixel passed the consistency checks; check that the pair "
            f"is rectified and that disparities lie in [{min_disp}, {min_disp + num_disp - 1}]"
        )
    return StereoResult(disparity=dense, valid=valid, confidence=conf_out, raw=raw,
                        coarse_to_fine=use_c2f, right_gain=gain)


def _downsample(img: NDArray[Any], scale: int) -> NDArray[Any]:
    """Area-averaged ``1/scale`` level of an (H, W, C) image (same dtype; uint8 rounded)."""
    h, w, nc = img.shape
    hc, wc = h // scale, w // scale
    crop = np.ascontiguousarray(img[: hc * scale, : wc * scale])
    small = cv2.resize(crop, (wc, hc), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small.reshape(hc, wc, nc))


def _right_gain(lf: NDArray[Any], rf: NDArray[Any], min_disp: int, num_disp: int, scale: int,
                prm: _Params) -> GainField:
    """The right view's gain field, fitted at pixels a census-only (gain-blind) match
    finds on the ``1/scale`` level."""
    import dataclasses

    h, w, nc = lf.shape
    lc, rc = _downsample(lf, scale), _downsample(rf, scale)
    dmin_c = math.floor(min_disp / scale) - 1
    dmax_c = math.ceil((min_disp + num_disp - 1) / scale) + 1
    dlo_c = np.full(lc.shape[:2], dmin_c, np.int32)
    blind = dataclasses.replace(prm, ad_weight=0.0)
    raw_c, _ = _match_level(lc, rc, dlo_c, dmax_c - dmin_c + 1, blind, subpixel="equiangular",
                            speckle_size=max(4, prm.speckle_size // (scale * scale)), dmin=dmin_c)
    ok = np.isfinite(raw_c)
    if not ok.any():
        return GainField.identity(nc, (w, h))
    return fit_gain_field(lc, rc, raw_c, ok, scale=float(scale), size=(w, h))


def _match_c2f(
    lf: NDArray[np.float32],
    rf: NDArray[np.float32],
    min_disp: int,
    num_disp: int,
    scale: int,
    prm: _Params,
    fine_window: int | None,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    h, w, nc = lf.shape
    hc, wc = h // scale, w // scale
    lc, rc = (_downsample(np.asarray(v, dtype=np.float32), scale) for v in (lf, rf))
    dmin_c = math.floor(min_disp / scale) - 1
    dmax_c = math.ceil((min_disp + num_disp - 1) / scale) + 1
    dlo_c = np.full((hc, wc), dmin_c, np.int32)
    sp_c = max(4, prm.speckle_size // (scale * scale))
    raw_c, _ = _match_level(lc, rc, dlo_c, dmax_c - dmin_c + 1, prm, subpixel="equiangular",
                            speckle_size=sp_c, dmin=dmin_c)
    if not np.any(~np.isnan(raw_c)):
        raise ReconstructionError(
            "match_stereo: the coarse level found no consistent match; check the pair "
            f"and the range [{min_disp}, {min_disp + num_disp - 1}]"
        )
    coarse = _fill(raw_c)
    if fine_window is not None:
        k_levels = fine_window
    else:
        # cover the coarse neighbourhood's range (+-scale) and +-4 levels; with 4 paths
        # the volumes are padded to whole 16-level vectors anyway, so search them all
        k_levels = 2 * (scale + 4) + 1
        if prm.paths == 4:
            k_levels = _volume_levels(k_levels)
    k_levels = int(min(max(k_levels, 3), num_disp))
    dlo = np.empty((h, w), np.int32)
    _k.fine_ranges(coarse, float(scale), 4, k_levels, min_disp, min_disp + num_disp - 1, dlo)
    log.debug("coarse-to-fine: scale %d, fine window %d levels", scale, k_levels)
    return _match_level(lf, rf, dlo, k_levels, prm, subpixel=prm.subpixel,
                        speckle_size=prm.speckle_size)


def match_stereo(
    left: NDArray[Any],
    right: NDArray[Any],
    *,
    min_disp: int,
    num_disp: int,
    **options: Any,
) -> NDArray[np.float32]:
    """Dense disparity of a rectified pair (holes filled).

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) uint8, or float in [0, 1]
        Rectified views of the same shape.
    min_disp : int
        Smallest disparity searched.
    num_disp : int
        Number of levels searched (> 0).
    **options
        Any keyword option of :func:`match_stereo_full`.

    Returns
    -------
    (H, W) float32
        ``d = x_left - x_right`` in pixels. Dense (no NaN): pixels that failed the
        consistency checks are filled from their background neighbours; use
        :func:`match_stereo_full` for the validity mask.

    Raises
    ------
    InputError
        Invalid arrays or options (see :func:`match_stereo_full`).
    ReconstructionError
        No pixel passed the consistency checks (nothing to fill from).
    """
    return match_stereo_full(left, right, min_disp=min_disp, num_disp=num_disp,
                             **options).disparity


def match_files(
    left_path: str | Path,
    right_path: str | Path,
    out_path: str | Path,
    *,
    num_disp: int,
    min_disp: int = 0,
    **options: Any,
) -> StereoResult:
    """Match two rectified image files and write the dense disparity as PFM.

    The entry point of ``prism3d match LEFT RIGHT -o disp.pfm --num-disp N
    [--min-disp M]``.

    Parameters
    ----------
    left_path, right_path : str or Path
        Rectified views (any 8/16-bit format OpenCV reads; colour is used).
    out_path : str or Path
        PFM file to write (Middlebury layout), atomically.
    num_disp, min_disp : int
        Search range ``min_disp .. min_disp + num_disp - 1``.
    **options
        Any keyword option of :func:`match_stereo_full`.

    Returns
    -------
    StereoResult

    Raises
    ------
    InputError
        Missing or unreadable files, images of different sizes, bad options.
    ReconstructionError
        Nothing could be matched.
    """
    from prism3d.io.images import read_image
    from prism3d.io.pfm import write_pfm

    left = read_image(left_path)
    right = read_image(right_path)
    if left.shape != right.shape:
        raise InputError(
            f"{left_path} and {right_path}: rectified views must have the same size, got "
            f"{left.shape[1]}x{left.shape[0]} and {right.shape[1]}x{right.shape[0]}"
        )
    res = match_stereo_full(left, right, min_disp=min_disp, num_disp=num_disp, **options)
    write_pfm(out_path, res.disparity)
    return res
