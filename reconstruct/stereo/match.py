"""Dense stereo matching: census cost, semi-global aggregation, sub-pixel refinement.

:func:`match_stereo_full` matches a *rectified* pair (``d = x_left - x_right``, px,
float32): census of every channel + truncated colour difference (AD-Census [2, 6]);
SGM along 4 or 8 paths, gradient-adaptive P2 [1]; winner-take-all, uniqueness,
left-right check, speckle removal; equiangular sub-pixel fit [4], then 1-D
Lucas-Kanade [5] on a cubic B-spline of the right view [7]; background-favouring
hole fill. Above :data:`C2F_AUTO_CELLS` cells it runs coarse-to-fine (tSGM [3]).
Why and measurements: docs/matching.md.

References: [1] Hirschmüller, TPAMI 2008 (SGM). [2] Zabih, Woodfill, ECCV 1994
(census). [3] Rothermel et al., LC3D 2012 (SURE/tSGM). [4] Shimizu, Okutomi, IJCV
2005. [5] Lucas, Kanade, IJCAI 1981. [6] Mei et al., ICCVW 2011 (AD-Census).
[7] Unser, IEEE SPM 16(6), 1999 (splines).
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

from prism3d.checks import check_array, check_choice, check_int, check_same_shape
from prism3d.errors import InputError, ReconstructionError
from prism3d.io.atomic import atomic_paths
from prism3d.io.images import IMAGE_EXTENSIONS, read_image, write_image
from prism3d.io.pfm import write_pfm

from . import _match_kernels as _k
from .match_options import MatchOptions
from .photometric import GainField, fit_gain_field

__all__ = ["C2F_AUTO_CELLS", "MatchOptions", "StereoResult", "match_files", "match_stereo", "match_stereo_full"]

log = logging.getLogger(__name__)

#: Above this many cost cells (W * H * num_disp) the coarse-to-fine path is used.
C2F_AUTO_CELLS = 48_000_000
#: Target size (cells) of the coarse level's full cost volume.
_COARSE_CELLS = 12_000_000
#: Largest pyramid factor of the coarse level.
_MAX_SCALE = 16
#: A coarse level (matching or gain fit) needs at least this many rows and columns.
_MIN_COARSE_SIDE = 8
#: The gain fit runs on a level at least this many times smaller (its field is smooth) ...
_GAIN_SCALE = 4
#: ... that keeps this many pixels on its short side (docs/matching.md).
_GAIN_MIN_SIDE = 128
#: Default speckle size: this many pixels at the reference area, scaled with the area ...
_SPECKLE_PX, _SPECKLE_REF_AREA = 100, 450 * 375
#: ... and clamped to this range.
_SPECKLE_MIN, _SPECKLE_MAX = 4, 400
#: Fine-search half-window beyond the coarse neighbourhood's +-scale (levels).
_FINE_MARGIN = 4
#: Side of the box mean the band-pass subtracts before Lucas-Kanade (exposure offsets).
_BANDPASS_BOX = 11
#: Channel spread below which the right view's AD features keep gain 1.
_MIN_SPREAD = 1e-6
#: SGM vertical pass: columns per parallel block, within [16, 128], ~4 blocks a thread.
_BLOCK_MIN, _BLOCK_MAX, _BLOCKS_PER_THREAD = 16, 128, 4
#: Lucas-Kanade stripes: 4 per thread (load balance), each at least 32 rows.
_LK_STRIPES_PER_THREAD, _LK_MIN_STRIPE_ROWS = 4, 32
#: Largest Lucas-Kanade correction (px): its window sums cover the start's integer
#: part +-1 only; a larger move means the match was wrong.
_LK_MAX_STEP = 1.0
#: Radius of the median that smooths the filled holes (3x3).
_FILL_MEDIAN_RADIUS = 1


@dataclass(frozen=True)
class StereoResult:
    """Result of :func:`match_stereo_full`; maps (H, W).

    ``disparity`` float32 px, holes filled; ``valid`` bool: passed uniqueness, left-right
    and speckle checks; ``confidence`` float32 in [0, 1] (relative gap to the best cost
    outside +-1 level, 0 where not valid); ``raw``: ``disparity`` where valid, else NaN;
    ``right_gain``: gain applied to the right view (None when ``equalize`` is off).
    """

    disparity: NDArray[np.float32]
    valid: NDArray[np.bool_]
    confidence: NDArray[np.float32]
    raw: NDArray[np.float32]
    coarse_to_fine: bool
    right_gain: GainField | None = None


class _Workspace(threading.local):
    """Per-thread scratch volumes reused between calls, at most ``CAP`` bytes (fresh
    large arrays cost page faults: docs/matching.md). Kernels overwrite them whole."""

    CAP = 64 << 20

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def take(self, name: str, shape: tuple[int, ...], dtype: Any, keep: bool = True
             ) -> np.ndarray:
        """Uninitialised C-contiguous array for ``name`` (reused when shape and dtype
        match); ``keep`` False: neither reused nor kept (large problems)."""
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
        """Whether an ``h x w`` match of ``levels`` levels (3 bytes a cell) fits ``CAP``."""
        return 3 * h * w * levels <= cls.CAP


_WS = _Workspace()


def _prepare(img: Any, name: str) -> NDArray[np.uint8] | NDArray[np.float32]:
    """(H, W, C) C-contiguous image: uint8 as is (no copy when possible), float scaled
    to [0, 255] float32."""
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


def _census_dtype(ry: int, rx: int) -> type:
    """uint32 codes up to 32 comparisons, else uint64."""
    return np.uint32 if (2 * ry + 1) * (2 * rx + 1) - 1 <= 32 else np.uint64


def _census(img: NDArray[Any], ry: int, rx: int, reverse: bool,
            out: NDArray[np.unsignedinteger] | None = None) -> NDArray[np.unsignedinteger]:
    """(C, H, W) census codes of an (H, W, C) image (into ``out`` when given), borders
    replicated; rows mirrored when ``reverse`` (the right view's layout)."""
    h, w, c = img.shape
    if out is None:
        out = np.empty((c, h, w), _census_dtype(ry, rx))
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
    """Grey minus its box mean (exposure offsets out before Lucas-Kanade)."""
    box = cv2.blur(grey, (_BANDPASS_BOX, _BANDPASS_BOX), dst=tmp, borderType=cv2.BORDER_REFLECT)
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
    """(C, H, W) uint8 features of the AD term for both views, the right view's rows
    mirrored when ``reverse``: "intensity" the colours, the right view's channels
    matched in mean and spread to the left's; "gradient" horizontal central
    differences + 128."""
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
        g = s_l / s_i if s_i > _MIN_SPREAD else 1.0
        gain[c] = np.float32(g)
        offset[c] = np.float32(m_l - m_i * g)
    fl = _WS.take("feat_l", (nc, h, w), np.uint8, keep)
    fr = _WS.take("feat_r", (nc, h, w), np.uint8, keep)
    _k.features_hwc(left, right, gain, offset, bool(reverse), fl, fr)
    return fl, fr


@dataclass(frozen=True)
class _Params:
    """:class:`MatchOptions` resolved for one image size (the kernels' arguments)."""

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


def _resolve(opts: MatchOptions, h: int, w: int) -> _Params:
    speckle_size = opts.speckle_size
    if speckle_size is None:
        speckle_size = max(_SPECKLE_MIN, round(_SPECKLE_PX * h * w / _SPECKLE_REF_AREA))
        speckle_size = min(speckle_size, _SPECKLE_MAX)
    return _Params(
        census_ry=opts.census_window[0] // 2,
        census_rx=opts.census_window[1] // 2,
        p1=int(opts.p1),
        p2=int(opts.p2),
        p2_gamma=float(opts.p2_gamma),
        paths=int(opts.paths),
        uniqueness=float(opts.uniqueness),
        lr_max_diff=float(opts.lr_max_diff),
        speckle_size=int(speckle_size),
        speckle_range=float(opts.speckle_range),
        subpixel=opts.subpixel,
        lk_window=int(opts.lk_window),
        lk_iters=int(opts.lk_iters),
        ad_weight=float(opts.ad_weight),
        ad_trunc=float(opts.ad_trunc),
        ad_mode=opts.ad_mode,
    )


def _match_cost(left: NDArray[Any], right: NDArray[Any], dlo: NDArray[np.int32], kp: int,
                prm: _Params, keep: bool) -> NDArray[np.uint8]:
    """(H, W, kp) uint8 census + AD cost of disparities ``dlo + k``."""
    h, w, nc = left.shape
    ry, rx = prm.census_ry, prm.census_rx
    nbits = (2 * ry + 1) * (2 * rx + 1) - 1
    ctype = _census_dtype(ry, rx)
    cl = _census(left, ry, rx, False, _WS.take("census_l", (nc, h, w), ctype, keep))
    cr = _census(right, ry, rx, True, _WS.take("census_r", (nc, h, w), ctype, keep))
    oob = np.uint8(min(255, (nbits * nc) // 2))  # a candidate outside the right view
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
    return cost


def _refine_lk(left: NDArray[Any], right: NDArray[Any], guide: NDArray[np.float32],
               disp: NDArray[np.float32], prm: _Params, keep: bool) -> None:
    """Lucas-Kanade sub-pixel refinement of ``disp`` in place, on band-passed greys."""
    h, w = disp.shape
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
    _k.refine_lk_gram(lg, rcoef, disp, r, r, prm.lk_iters, _LK_MAX_STEP, _lk_stripes(h))


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
    """One SGM pass over the per-pixel windows ``dlo + 0 .. k_levels - 1``; returns
    (raw disparity, NaN = invalid; confidence)."""
    h, w, nc = left.shape
    keep = _Workspace.small(h, w, _volume_levels(k_levels))
    # levels padded to whole 16-level vectors; the SGM kernels never select the padding
    kp = _volume_levels(k_levels)
    cost = _match_cost(left, right, dlo, kp, prm, keep)
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
    block = int(min(_BLOCK_MAX, max(_BLOCK_MIN, -(-w // (_BLOCKS_PER_THREAD * nthreads)))))
    _k.sgm_vertical_wta(cost, dlo, guide, p1, p2, gamma, k_levels, block,
                        float(prm.uniqueness), agg, disp, conf)
    del cost
    _k.right_lr_check(agg, dlo, k_levels, float(prm.lr_max_diff), disp)
    del agg
    if speckle_size > 0:
        _k.remove_speckles(disp, speckle_size, np.float64(prm.speckle_range))
    if subpixel == "lk":
        _refine_lk(left, right, guide, disp, prm, keep)
    return disp, conf


def _volume_levels(k_levels: int) -> int:
    """``k_levels`` rounded up to whole 16-level vectors (the volumes' depth)."""
    return -(-k_levels // 16) * 16


def _lk_stripes(h: int) -> int:
    """Row stripes of the Lucas-Kanade pass (its window sums slide down a stripe)."""
    return max(1, min(_LK_STRIPES_PER_THREAD * max(1, numba.get_num_threads()),
                      h // _LK_MIN_STRIPE_ROWS))


def _fill(raw: NDArray[np.float32]) -> NDArray[np.float32]:
    filled = np.empty_like(raw)
    _k.fill_holes(raw, filled)
    _k.fill_columns(filled)
    out = np.empty_like(raw)
    _k.median_filled(filled, ~np.isnan(raw), _FILL_MEDIAN_RADIUS, out)
    return out


def _check_pair(left: Any, right: Any, min_disp: Any, num_disp: Any
                ) -> tuple[NDArray[Any], NDArray[Any], int, int]:
    """Validated (H, W, C) views (one channel when all channels are equal) and range."""
    lf = _prepare(left, "left")
    rf = _prepare(right, "right")
    check_same_shape(lf, rf, ("left", "right"))
    min_disp = check_int(min_disp, "min_disp")
    num_disp = check_int(num_disp, "num_disp")
    if num_disp <= 0:
        raise InputError(f"num_disp: expected an integer > 0, got {num_disp}")
    # a disparity of the image width or more matches no pixel: search only what can match
    w = lf.shape[1]
    lo, hi = max(min_disp, -(w - 1)), min(min_disp + num_disp - 1, w - 1)
    if lo > hi:
        raise InputError(f"disparity range {min_disp}..{min_disp + num_disp - 1} lies outside what a "
                         f"{w} px wide image can hold (-{w - 1}..{w - 1})")
    min_disp, num_disp = lo, hi - lo + 1
    if lf.shape[2] == 3 and _k.channels_equal(lf) and _k.channels_equal(rf):
        lf = np.ascontiguousarray(lf[..., :1])
        rf = np.ascontiguousarray(rf[..., :1])
    return lf, rf, min_disp, num_disp


def _pyramid_scale(h: int, w: int, num_disp: int) -> int:
    """Factor of the coarse level: the smallest power of 2 that brings its cost volume
    under ``_COARSE_CELLS``."""
    scale = 2
    while (h // scale) * (w // scale) * (num_disp / scale) > _COARSE_CELLS and scale < _MAX_SCALE:
        scale *= 2
    return scale


def _equalize(lf: NDArray[Any], rf: NDArray[Any], min_disp: int, num_disp: int, scale: int,
              prm: _Params) -> tuple[NDArray[Any], GainField | None]:
    """The right view with the left's exposure, and the gain applied (None: too small)."""
    h, w, _ = lf.shape
    g_scale = scale
    while g_scale < _GAIN_SCALE and min(h, w) // (2 * g_scale) >= _GAIN_MIN_SIDE:
        g_scale *= 2
    if h // g_scale < _MIN_COARSE_SIDE or w // g_scale < _MIN_COARSE_SIDE:
        return rf, None
    gain = _right_gain(lf, rf, min_disp, num_disp, g_scale, prm)
    return np.ascontiguousarray(gain.apply(rf)), gain


def _match_full(lf: NDArray[Any], rf: NDArray[Any], min_disp: int, num_disp: int,
                prm: _Params) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Raw disparity and confidence of a full search ``min_disp + 0 .. num_disp - 1``."""
    h, w, _ = lf.shape
    dlo = _WS.take("dlo", (h, w), np.int32, _Workspace.small(h, w, num_disp))
    dlo.fill(min_disp)
    return _match_level(lf, rf, dlo, num_disp, prm, subpixel=prm.subpixel,
                        speckle_size=prm.speckle_size, dmin=min_disp)


def _assemble(raw: NDArray[np.float32], conf: NDArray[np.float32], keep: bool, use_c2f: bool,
              gain: GainField | None, dmin: int, dmax: int) -> StereoResult:
    """Fill the holes of ``raw`` (background first, then a median) into a StereoResult."""
    filled = _WS.take("filled", raw.shape, np.float32, keep)
    _k.fill_holes(raw, filled)
    _k.fill_columns(filled)
    dense = np.empty_like(raw)
    valid = np.empty(raw.shape, np.bool_)
    conf_out = np.empty(raw.shape, np.float32)
    _k.median_fill_final(filled, raw, conf, _FILL_MEDIAN_RADIUS, dense, valid, conf_out)
    del filled
    if not valid.any():
        raise ReconstructionError(
            "match_stereo: no pixel passed the consistency checks; check that the pair "
            f"is rectified and that disparities lie in [{dmin}, {dmax}]"
        )
    return StereoResult(disparity=dense, valid=valid, confidence=conf_out, raw=raw,
                        coarse_to_fine=use_c2f, right_gain=gain)


def match_stereo_full(
    left: NDArray[Any],
    right: NDArray[Any],
    *,
    min_disp: int,
    num_disp: int,
    options: MatchOptions | None = None,
) -> StereoResult:
    """Match a rectified pair; dense disparity plus validity and confidence.

    ``left``, ``right``: (H, W) or (H, W, 3) uint8, or float in [0, 1], same shape
    (channels used separately; equal channels count as grey). Searches ``min_disp ..
    min_disp + num_disp - 1`` (``num_disp > 0``). ``options`` None: the defaults.
    Raises InputError for bad arrays or range, ReconstructionError when no pixel passed
    the consistency checks.
    """
    opts = MatchOptions() if options is None else options
    if not isinstance(opts, MatchOptions):
        raise InputError(f"options: expected a MatchOptions, got {type(opts).__name__}")
    lf, rf, min_disp, num_disp = _check_pair(left, right, min_disp, num_disp)
    h, w, _ = lf.shape
    prm = _resolve(opts, h, w)
    keep = _Workspace.small(h, w, num_disp)  # scratch kept between calls (small problems)
    use_c2f = (h * w * num_disp > C2F_AUTO_CELLS if opts.coarse_to_fine is None
               else bool(opts.coarse_to_fine))
    scale = _pyramid_scale(h, w, num_disp)
    if use_c2f and (h // scale < _MIN_COARSE_SIDE or w // scale < _MIN_COARSE_SIDE):
        use_c2f = False
    gain = None
    if opts.equalize:
        rf, gain = _equalize(lf, rf, min_disp, num_disp, scale, prm)
    if use_c2f:
        raw, conf = _match_c2f(lf, rf, min_disp, num_disp, scale, prm, opts.fine_window)
    else:
        raw, conf = _match_full(lf, rf, min_disp, num_disp, prm)
    return _assemble(raw, conf, keep, use_c2f, gain, min_disp, min_disp + num_disp - 1)


def _downsample(img: NDArray[Any], scale: int) -> NDArray[Any]:
    """Area-averaged ``1/scale`` level of an (H, W, C) image (same dtype; uint8 rounded)."""
    h, w, nc = img.shape
    hc, wc = h // scale, w // scale
    crop = np.ascontiguousarray(img[: hc * scale, : wc * scale])
    small = cv2.resize(crop, (wc, hc), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small.reshape(hc, wc, nc))


def _coarse_range(min_disp: int, num_disp: int, scale: int) -> tuple[int, int]:
    """Disparity range of the ``1/scale`` level, one level of margin each side."""
    return (math.floor(min_disp / scale) - 1,
            math.ceil((min_disp + num_disp - 1) / scale) + 1)


def _right_gain(lf: NDArray[Any], rf: NDArray[Any], min_disp: int, num_disp: int, scale: int,
                prm: _Params) -> GainField:
    """The right view's gain field, fitted at pixels a census-only (gain-blind) match
    finds on the ``1/scale`` level."""
    h, w, nc = lf.shape
    lc, rc = _downsample(lf, scale), _downsample(rf, scale)
    dmin_c, dmax_c = _coarse_range(min_disp, num_disp, scale)
    dlo_c = np.full(lc.shape[:2], dmin_c, np.int32)
    blind = dataclasses.replace(prm, ad_weight=0.0)
    raw_c, _ = _match_level(lc, rc, dlo_c, dmax_c - dmin_c + 1, blind, subpixel="equiangular",
                            speckle_size=max(_SPECKLE_MIN, prm.speckle_size // (scale * scale)),
                            dmin=dmin_c)
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
    """Full SGM on the ``1/scale`` level, then a ``fine_window``-level search per pixel
    around the upsampled coarse disparity; returns (raw disparity, confidence)."""
    h, w, nc = lf.shape
    hc, wc = h // scale, w // scale
    lc, rc = (_downsample(np.asarray(v, dtype=np.float32), scale) for v in (lf, rf))
    dmin_c, dmax_c = _coarse_range(min_disp, num_disp, scale)
    dlo_c = np.full((hc, wc), dmin_c, np.int32)
    sp_c = max(_SPECKLE_MIN, prm.speckle_size // (scale * scale))
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
        # the coarse neighbourhood's range (+-scale) and a margin; with 4 paths the
        # volumes are padded to whole 16-level vectors anyway, so search them all
        k_levels = 2 * (scale + _FINE_MARGIN) + 1
        if prm.paths == 4:
            k_levels = _volume_levels(k_levels)
    k_levels = int(min(max(k_levels, 3), num_disp))
    dlo = np.empty((h, w), np.int32)
    _k.fine_ranges(coarse, float(scale), _FINE_MARGIN, k_levels, min_disp,
                   min_disp + num_disp - 1, dlo)
    log.debug("coarse-to-fine: scale %d, fine window %d levels", scale, k_levels)
    return _match_level(lf, rf, dlo, k_levels, prm, subpixel=prm.subpixel,
                        speckle_size=prm.speckle_size)


def match_stereo(
    left: NDArray[Any],
    right: NDArray[Any],
    *,
    min_disp: int,
    num_disp: int,
    options: MatchOptions | None = None,
) -> NDArray[np.float32]:
    """Dense (H, W) float32 disparity ``x_left - x_right`` (px) of a rectified pair,
    holes filled: :func:`match_stereo_full` (same arguments and errors) ``.disparity``."""
    return match_stereo_full(left, right, min_disp=min_disp, num_disp=num_disp,
                             options=options).disparity


def match_files(
    left_path: str | Path,
    right_path: str | Path,
    out_path: str | Path,
    *,
    num_disp: int,
    min_disp: int = 0,
    options: MatchOptions | None = None,
    dense: bool = True,
    valid_out: str | Path | None = None,
) -> StereoResult:
    """``prism3d match``: match two rectified image files (8/16-bit, colour used), write
    the disparity as PFM (atomic; NaN where not valid unless ``dense``) and, with
    ``valid_out``, the validity mask image. InputError: missing or unreadable files,
    different sizes, bad options; ReconstructionError: nothing matched.
    """
    outs = [Path(out_path)] + ([] if valid_out is None else [Path(valid_out)])
    _check_match_outputs(outs)
    left = read_image(left_path)
    right = read_image(right_path)
    if left.shape != right.shape:
        raise InputError(
            f"{left_path} and {right_path}: rectified views must have the same size, got "
            f"{left.shape[1]}x{left.shape[0]} and {right.shape[1]}x{right.shape[0]}"
        )
    res = match_stereo_full(left, right, min_disp=min_disp, num_disp=num_disp, options=options)
    disp = res.disparity if dense else np.where(res.valid, res.disparity, np.nan).astype(np.float32)
    with atomic_paths(*outs) as tmp:  # the disparity and the mask appear together
        write_pfm(tmp[0], disp)
        if valid_out is not None:
            write_image(tmp[1], res.valid)
    return res


def _check_match_outputs(outs: list[Path]) -> None:
    """The disparity ``.pfm`` and the optional mask image: file names, distinct, their
    folders present, checked before any work."""
    if outs[0].suffix.lower() != ".pfm":
        raise InputError(f"{outs[0]}: disparity is written as PFM (.pfm)")
    if len(outs) > 1 and outs[1].suffix.lower() not in IMAGE_EXTENSIONS:
        raise InputError(f"{outs[1]}: the validity mask is an image; use one of {', '.join(IMAGE_EXTENSIONS)}")
    if len(outs) > 1 and outs[0].resolve() == outs[1].resolve():
        raise InputError(f"{outs[1]}: the same file as the disparity output")
    for o in outs:
        if o.is_dir():
            raise InputError(f"{o}: is a directory; give an output file name")
        if not o.parent.is_dir():
            raise InputError(f"{o.parent}: no such folder for {o.name}")
