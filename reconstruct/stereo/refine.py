"""Slanted-plane sub-pixel refinement of a disparity map: around every pixel a plane
``d(q) = d0 + a (qx - px) + b (qy - py)`` is fitted to the photometric error of the
views over a wide window (Gauss-Newton, box-filter sums weighted by the squared
horizontal gradient) and ``d0`` kept: the slanted windows of [1]_ in the direct
least-squares form of [2]_. Why and what it was measured to do: docs/reconstruction.md.

References
----------
.. [1] M. Bleyer, C. Rhemann, C. Rother, "PatchMatch Stereo - Stereo matching with
   slanted support windows", BMVC 2011.
.. [2] B. D. Lucas and T. Kanade, "An iterative image registration technique with an
   application to stereo vision", IJCAI 1981.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_same_shape
from prism3d.errors import InputError

from . import _refine_kernels as _k
from ._match_kernels import bspline_rows

__all__ = ["refine_slanted"]

#: Ridge on the plane's slopes (relative to the window's weight): keeps windows with
#: texture in one column only well posed.
_RIDGE = 1e-6
#: One Gauss-Newton step moves a pixel by at most this (px): the linearisation holds
#: within about a pixel.
_MAX_STEP_PX = 1.0
#: Added to the window's gradient energy before the residual ratio divides by it.
_RATIO_EPS = 1e-6
#: Largest lag-1 correlation of the residuals believed: bounds the variance inflation.
_MAX_LAG_CORRELATION = 0.95
#: The residuals' correlation is a property of the whole field: every 4th pair of rows
#: measures it well enough.
_CORRELATION_ROW_STEP = 4


def _as_float_channels(img: NDArray, name: str) -> NDArray[np.float32]:
    arr = check_array(img, name, ndim=(2, 3), dtype_kind="uf", min_size=1)
    out = arr.astype(np.float32)
    if arr.dtype.kind == "f" and np.nanmax(np.abs(out)) <= 1.0 + 1e-6:
        out = out * 255.0
    if out.ndim == 2:
        out = out[..., None]
    return np.ascontiguousarray(out)


def _correlation_factor(left: NDArray[np.float32], warped: NDArray[np.float32], mask: NDArray[np.bool_]) -> float:
    """Variance inflation (>= 1) for residuals correlated between neighbours: ``(1 + r) /
    (1 - r)`` per axis for lag-1 correlations ``r`` of ``left - warped`` (AR(1) model)."""
    h = left.shape[0]
    rows = np.arange(0, h - 1, _CORRELATION_ROW_STEP)
    m0 = mask[rows][..., None]
    e0 = np.where(m0, left[rows] - warped[rows], 0.0).astype(np.float64)
    e1 = np.where(mask[rows + 1][..., None], left[rows + 1] - warped[rows + 1], 0.0).astype(np.float64)
    den = float((e0 * e0).sum())
    if den <= 0.0:
        return 1.0
    rx = float((e0[:, 1:] * e0[:, :-1]).sum()) / den
    ry = float((e0 * e1).sum()) / den
    rx, ry = (min(max(r, 0.0), _MAX_LAG_CORRELATION) for r in (rx, ry))
    return (1.0 + rx) / (1.0 - rx) * (1.0 + ry) / (1.0 - ry)


class _Window:
    # window moments by separable correlation: sum_q f(q) (qx-px)^i (qy-py)^j

    def __init__(self, ry: int, rx: int) -> None:
        self.one_x = np.ones(2 * rx + 1)
        self.one_y = np.ones(2 * ry + 1)
        self.ramp_x = np.arange(-rx, rx + 1, dtype=np.float64)
        self.ramp_y = np.arange(-ry, ry + 1, dtype=np.float64)

    @staticmethod
    def mom(f: NDArray, kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float64]:
        return cv2.sepFilter2D(f, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT)

    @staticmethod
    def mom32(f: NDArray, kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float64]:
        # for a 0/1 float32 f: exact in float32, twice as fast
        return cv2.sepFilter2D(f, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_CONSTANT).astype(np.float64)

    def sum(self, f: NDArray) -> NDArray[np.float64]:
        return self.mom(f, self.one_x, self.one_y)

    def plane(self, f: NDArray) -> list[NDArray[np.float64]]:
        # sums of f times 1, x, y
        return [self.sum(f), self.mom(f, self.ramp_x, self.one_y), self.mom(f, self.one_x, self.ramp_y)]


@dataclass
class _Normal:
    # the last Gauss-Newton iteration's window sums (offset eliminated when fitted)

    moments: list[NDArray[np.float64]]  # A00 A01 A02 A11 A22 A12 r0 r1 r2
    g2: NDArray[np.float64]
    g1: NDArray[np.float64]
    n_off: NDArray[np.float64] | None
    s_off: tuple[NDArray[np.float64], ...] | None
    inv00: NDArray[np.float64]


def _checked_inputs(left: NDArray, right: NDArray, disparity: NDArray, valid: NDArray, extra: NDArray | None,
                    window: tuple[int, int], iterations: int, max_change: float
                    ) -> tuple[NDArray, NDArray, NDArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """Views as float channels, the disparity, and the valid and extra masks (finite only)."""
    L = _as_float_channels(left, "left")
    R = _as_float_channels(right, "right")
    check_same_shape(L, R, ("left", "right"))
    d_in = check_array(disparity, "disparity", ndim=2, dtype_kind="f")
    m = check_array(valid, "valid", ndim=2)
    if d_in.shape != L.shape[:2] or m.shape != L.shape[:2]:
        raise InputError(
            f"disparity {d_in.shape} and valid {m.shape} must match the images {L.shape[:2]}"
        )
    if len(window) != 2 or any(int(w) != w or w < 3 or w % 2 == 0 for w in window):
        raise InputError(f"window: expected two odd sizes >= 3, got {window!r}")
    if int(iterations) != iterations or iterations < 1:
        raise InputError(f"iterations: expected an integer >= 1, got {iterations!r}")
    if not (np.isfinite(max_change) and max_change > 0):
        raise InputError(f"max_change: expected a number > 0, got {max_change!r}")
    m = m.astype(bool) & np.isfinite(d_in)
    if extra is not None:
        ex = check_array(extra, "extra", shape=m.shape).astype(bool) & np.isfinite(d_in) & ~m
    else:
        ex = np.zeros_like(m)
    return L, R, d_in, m, ex


def _spline_coefficients(Rc: NDArray[np.float32]) -> NDArray[np.float32]:
    """Cubic B-spline coefficients ``(C, H, W)`` of the right view's rows (value and
    derivative from one spline; docs/reconstruction.md says why not bicubic)."""
    nc = Rc.shape[2]
    coef = np.empty((nc,) + Rc.shape[:2], np.float32)
    for c in range(nc):
        bspline_rows(np.ascontiguousarray(Rc[..., c]), coef[c])
    return coef


def _left_gradients(Lf: NDArray[np.float32], orientation_weight: bool
                    ) -> tuple[NDArray[np.float32], NDArray[np.float64] | None]:
    """The left view's horizontal gradient per channel and, if asked, the orientation
    weight ``gx^2 / (gx^2 + gy^2 + 1)`` (summed over channels)."""
    h, w, nc = Lf.shape
    gl = np.empty_like(Lf)
    for c in range(nc):
        gl[..., c] = cv2.Sobel(Lf[..., c], cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    if not orientation_weight:
        return gl, None
    sx = (gl * gl).sum(-1)
    sy = np.zeros((h, w), np.float32)
    for c in range(nc):
        gy = cv2.Sobel(Lf[..., c], cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
        sy += gy * gy
    return gl, (sx / (sx + sy + np.float32(1.0))).astype(np.float64)


def _gauss_newton(win: _Window, coef: NDArray, x0: int, Lf: NDArray, support: NDArray, mc: NDArray,
                  has_extra: bool, owt: NDArray | None, dd: NDArray[np.float64], d_ref: float,
                  iterations: int, offset: bool, Rw: NDArray, G: NDArray) -> _Normal:
    """Iterate the plane fits in place on ``dd`` (disparity minus ``d_ref``)."""
    # L - R(x - d_plane) ~ e_q + G_q (d_plane(q) - d_q) - beta = 0 about each window pixel's
    # d_q: sum G^2 d_plane [1 x y] = sum (G^2 d_q - G e_q) [1 x y], beta eliminated
    # (A - s s'/n, r - s y/n; s = sum G [1 x y])
    h, w = dd.shape
    g2, ge, g1, yo, wt = (np.empty((h, w), np.float64) for _ in range(5))
    no_owt = np.empty((0, 0), np.float64)
    inv00 = np.full((h, w), np.inf)
    ox, oy, rx, ry = win.one_x, win.one_y, win.ramp_x, win.ramp_y
    n_off = s_off = None
    for it in range(int(iterations)):
        if it > 0 and has_extra:
            support = mc  # the planes reached the extra pixels: they now carry measurements
        _k.warp_rows(coef, x0, dd, d_ref, Rw, G)
        _k.products_offset(Lf, Rw, G, support, dd, no_owt if owt is None else owt, g2, ge, g1, yo, wt)
        moments = [win.mom(g2, ox, oy), win.mom(g2, rx, oy), win.mom(g2, ox, ry),
                   win.mom(g2, rx * rx, oy), win.mom(g2, ox, ry * ry),
                   win.mom(g2, rx, ry), *win.plane(ge)]
        if offset:
            n_off = win.sum(wt)
            s_off = tuple(win.plane(g1))
            _k.eliminate_offset(*moments, n_off, *s_off, win.sum(yo))
        _k.solve_planes(mc, *moments, _RIDGE, _MAX_STEP_PX, dd, inv00)
    return _Normal(moments, g2, g1, n_off, s_off, inv00)


def _curvature_bias_factor(win: _Window, ne: _Normal, mc: NDArray, offset: bool) -> NDArray[np.float64]:
    """``kappa``: a window of ``d0 + a x + b y + c x^2`` yields ``d0 + c kappa``, with
    ``kappa = e0' A^-1 sum(g2 x^2 [1 x y])`` (``A``: the last iteration's normal matrix)."""
    ox, oy, rx, ry = win.one_x, win.one_y, win.ramp_x, win.ramp_y
    h, w = mc.shape
    rx2 = rx * rx
    kappa = np.zeros((h, w))
    rhs = [win.mom(ne.g2, rx2, oy), win.mom(ne.g2, rx2 * rx, oy), win.mom(ne.g2, rx2, ry)]
    if offset:
        # the x^2 regressor's own correlation with the offset, removed as for the plane
        s_x2 = win.mom(ne.g1, rx2, oy)
        zero = np.zeros_like(s_x2)
        _k.eliminate_offset(zero, zero.copy(), zero.copy(), zero.copy(), zero.copy(), zero.copy(),
                            *rhs, ne.n_off, *ne.s_off, s_x2)
    _k.solve_planes(mc, *ne.moments[:6], *rhs, _RIDGE, np.inf, kappa, np.empty((h, w)))
    return kappa


def _row_curvature(win: _Window, mc: NDArray, dd: NDArray[np.float64]) -> NDArray[np.float64]:
    """Curvature ``c`` of ``d0 + a x + b y + c x^2`` fitted to the refined map over the window."""
    ox, oy, rx, ry = win.one_x, win.one_y, win.ramp_x, win.ramp_y
    rx2, ry2 = rx * rx, ry * ry
    wm = mc.astype(np.float32)
    m32 = win.mom32
    m = (m32(wm, ox, oy), m32(wm, rx, oy), m32(wm, ox, ry), m32(wm, rx2, oy), m32(wm, ox, ry2),
         m32(wm, rx, ry), m32(wm, rx2 * rx, oy), m32(wm, rx2, ry), m32(wm, rx2 * rx2, oy))
    dm = np.where(mc, dd, 0.0)
    md = (*win.plane(dm), win.mom(dm, rx2, oy))
    curv = np.zeros(mc.shape)
    _k.row_curvature(mc, m, md, _RIDGE, curv)
    return curv


def _residual_and_variance(win: _Window, coef: NDArray, x0: int, Lf: NDArray, gl: NDArray, mc: NDArray,
                           dd: NDArray[np.float64], d_ref: float, inv00: NDArray, offset: bool, Rw: NDArray,
                           G: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """At the ``mc`` pixels (in ``np.nonzero`` order): the residual ratio and the centre
    value's variance ``sigma_e^2 (A^-1)_00`` times the correlation inflation."""
    h, w, nc = Lf.shape
    idx = np.nonzero(mc)
    _k.warp_rows(coef, x0, dd, d_ref, Rw, G)
    e2, e1, gl2 = (np.empty((h, w), np.float64) for _ in range(3))
    _k.residual_sums(Lf, Rw, gl, mc, e2, e1, gl2)
    s_e2 = win.sum(e2)[idx]
    n_obs = win.sum(mc.astype(np.float32))[idx] * nc
    if offset:
        # the residual about the window's best offset: sum e^2 - (sum e)^2 / n
        s_e = win.sum(e1)[idx]
        s_e2 = np.maximum(s_e2 - np.divide(s_e * s_e, n_obs, out=np.zeros_like(s_e), where=n_obs > 0), 0.0)
    ratio = s_e2 / (win.sum(gl2)[idx] + _RATIO_EPS)
    with np.errstate(invalid="ignore"):  # inv00 is inf where a window was singular
        var = s_e2 / np.maximum(n_obs - 3.0 - offset, 1.0) * inv00[idx] * _correlation_factor(Lf, Rw, mc)
    return ratio, np.where(np.isfinite(var) & (var >= 0), var, np.inf)


def _work_box(tgt: NDArray[np.bool_], ry: int, rx: int) -> tuple[int, int, int, int]:
    """Rows ``y0:y1`` and columns ``x0:x1`` holding every target pixel and its window."""
    rows = np.flatnonzero(tgt.any(axis=1))
    cols = np.flatnonzero(tgt.any(axis=0))
    y0, y1 = max(rows[0] - ry, 0), min(rows[-1] + ry + 1, tgt.shape[0])
    x0, x1 = max(cols[0] - rx, 0), min(cols[-1] + rx + 1, tgt.shape[1])
    return y0, y1, x0, x1


def _solve_crop(win: _Window, coef: NDArray, x0: int, Lf: NDArray, support: NDArray, mc: NDArray,
                has_extra: bool, d0: NDArray, d_ref: float, iterations: int, orientation_weight: bool,
                curvature: bool, offset: bool
                ) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float64]]:
    """The crop's plane fits, less the curvature bias if asked: the disparity (minus
    ``d_ref``) and, at the ``mc`` pixels, the residual ratio and variance."""
    h, w, nc = Lf.shape
    Rw, G = np.empty((h, w, nc), np.float32), np.empty((h, w, nc), np.float32)
    gl, owt = _left_gradients(Lf, orientation_weight)
    dd = np.where(mc, d0, np.float32(0.0)).astype(np.float64)
    ne = _gauss_newton(win, coef, x0, Lf, support, mc, has_extra, owt, dd, d_ref, iterations, offset, Rw, G)
    if curvature:
        kappa = _curvature_bias_factor(win, ne, mc, offset)
        dd -= np.where(mc, _row_curvature(win, mc, dd) * kappa, 0.0)
    d = dd.astype(np.float32)
    ratio, var = _residual_and_variance(win, coef, x0, Lf, gl, mc, dd, d_ref, ne.inv00, offset, Rw, G)
    return d, ratio, var


def _store(out: NDArray[np.float32], resid: NDArray[np.float32], std: NDArray[np.float32],
           box: tuple[int, int, int, int], mc: NDArray, d: NDArray[np.float32], d0: NDArray, d_ref: float,
           ratio: NDArray[np.float64], var: NDArray[np.float64], max_change: float) -> None:
    """Write the crop's results into the full-size outputs; a pixel moved more than
    ``max_change`` px keeps its input value, with an infinite residual and std."""
    y0, y1, x0, x1 = box
    idx = np.nonzero(mc)
    moved = np.abs(d[idx] - d0[idx]) > float(max_change)
    d[idx] = np.where(moved, d0[idx], d[idx])
    out[y0:y1, x0:x1] = np.where(mc, d + np.float32(d_ref), out[y0:y1, x0:x1])
    resid[y0:y1, x0:x1][idx] = np.where(moved, np.inf, ratio).astype(np.float32)
    std[y0:y1, x0:x1][idx] = np.sqrt(np.where(moved, np.inf, var)).astype(np.float32)


def refine_slanted(
    left: NDArray,
    right: NDArray,
    disparity: NDArray,
    valid: NDArray,
    *,
    window: tuple[int, int] = (7, 25),
    iterations: int = 3,
    max_change: float = 1.5,
    extra: NDArray | None = None,
    orientation_weight: bool = False,
    curvature: bool = True,
    offset: bool = True,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Refine ``disparity`` at ``valid`` pixels with slanted-plane windows.

    Parameters
    ----------
    left, right : (H, W) or (H, W, C) uint8 or float
        The rectified pair (``d = x_left - x_right``), best rectified with B-splines.
    disparity, valid : (H, W) float, (H, W) bool
        Current disparity (within ~1 px of the truth); pixels to refine.
    window : (rows, cols)
        Odd sizes; 7 x 25 is the lower-noise choice for a single view.
    extra : (H, W) bool, optional
        Further pixels to estimate; in the window sums from the second iteration on.
    orientation_weight, curvature, offset : bool
        Weight pixels by ``gx^2 / (gx^2 + gy^2 + 1)``; subtract the plane's bias under
        curvature along the rows; fit an additive offset per window.

    A pixel moving more than ``max_change`` px keeps its input value.

    Returns
    -------
    disparity, residual, std : (H, W) float32
        Refined disparity (input elsewhere); residual (mean squared colour error over
        mean squared gradient; ``inf`` where moved too far) and predicted std (px), NaN
        where not refined.
    """
    L, R, d_in, m, ex = _checked_inputs(left, right, disparity, valid, extra, window, iterations, max_change)
    out = d_in.astype(np.float32).copy()
    resid = np.full(out.shape, np.nan, np.float32)
    std = np.full(out.shape, np.nan, np.float32)
    if not (m.any() or ex.any()):
        return out, resid, std
    # work on the rows/columns around the valid pixels only
    ry, rx = int(window[0]) // 2, int(window[1]) // 2
    tgt = m | ex
    y0, y1, x0, x1 = _work_box(tgt, ry, rx)
    Lf = np.ascontiguousarray(L[y0:y1, x0:x1], dtype=np.float32)
    coef = _spline_coefficients(np.ascontiguousarray(R[y0:y1]))  # full width: matches may lie left of x0
    support = np.ascontiguousarray(m[y0:y1, x0:x1])
    mc = np.ascontiguousarray(tgt[y0:y1, x0:x1])
    d_ref = float(np.median(out[m])) if m.any() else float(np.median(out[tgt]))
    d0 = np.ascontiguousarray(out[y0:y1, x0:x1] - np.float32(d_ref))
    d, ratio, var = _solve_crop(_Window(ry, rx), coef, x0, Lf, support, mc, bool(ex.any()), d0, d_ref,
                                iterations, orientation_weight, curvature, offset)
    _store(out, resid, std, (y0, y1, x0, x1), mc, d, d0, d_ref, ratio, var, max_change)
    return out, resid, std
