"""Slanted-plane sub-pixel refinement of a disparity map.

Window-based sub-pixel methods (the matcher's Lucas-Kanade step included) assume the
disparity is constant over the window. On the rig's colour grating that assumption
fails where it matters: each stripe is one flat colour, so a pixel inside a stripe
has no horizontal texture of its own and its window sees only the stripe's edges;
on a surface slanted to the rig the disparity changes by ~0.1 px per pixel, and a
constant-disparity fit makes a staircase -- one step per stripe, a sawtooth of
about +-0.5 px (+-0.7 mm at 1250 mm) along every slanted surface.

:func:`refine_slanted` fits, around every pixel, a *plane* of disparity
``d(q) = d0 + a (qx - px) + b (qy - py)`` to the photometric error of the colour
images over a wide window (default 7 rows x 25 columns, wide enough to hold stripe
edges on both sides), Gauss-Newton linearised about the current disparity at each
window pixel, and keeps ``d0``. This is the affine (slanted-window) matching model
of Bleyer et al. [1]_ and of the first-order windows of [2]_ in a direct least
squares form: every sum over the window is a box filter, so the cost per pixel does
not depend on the window size. Each window pixel is weighted by its squared
horizontal gradient (the information it carries about disparity), summed over the
colour channels.

Measured on a simulated turntable view of a camouflaged tank at 45 deg (paper rig,
grating on, noise): disparity error MAD 0.48 -> 0.10 px, within 0.1 px 19 % -> 61 %
of the pixels; on the flat 30 x 30 cm plate of Table I it does no harm.

A plane is the wrong model on a curved surface. If the disparity along a row is
``d0 + a x + c x^2``, the weighted plane fit returns ``d0 + c * kappa`` with ``kappa``
the projection of ``x^2`` onto the fit (``e0' A^-1 sum w x^2 [1 x y]``, ~50 px^2 for a
25-column window): a convex surface comes out flattened, pushed away from the
camera, and differently in every view (the bias follows the curvature *seen along
the rows*). Stitched turntable views inherit it as pose errors: on a jet's fuselage
(radius ~15 mm, ~0.1 mm of bias) one view pair was off by 0.1 deg. Fitting ``c`` in
the window itself removes the bias but makes the centre value 1.5x noisier (the
``1`` and ``x^2`` columns are strongly correlated; measured on a jet's 8 views:
median point error 0.047 -> 0.085 mm). Instead ``c`` is fitted to the *refined map*
over the window and ``c * kappa`` subtracted (``curvature=True``): median point
error unchanged (0.048 mm), the views' mean signed error -0.025 -> -0.015 mm, the
worst stitched view pose 0.095 -> 0.030 deg (6 targets: 0.026-0.095 -> 0.027-0.063;
the demo's tank 0.057 -> 0.023). The price is the noise of the estimated
curvature: the flat plate of Table I goes from 0.027-0.033 to 0.031-0.037 mm RMS.
On a synthetic cylinder pair the correction removes 77-84 % of the bias (the plane
map's curvature is itself slightly disturbed by the stripes).

Its side effect on flat faces (measured on 8 views of a truck, no sensor noise):
the curvature fit also sees the map rounded over a crease, out to ~24 px from
it, twice the reach of the plane fit's own bias. Between 4 and 24 px from the
creases the mean error goes from -0.013..+0.004 px to +0.006..+0.010 px. On the
planar faces beside a crease this adds a tilt in proportion to the face's
disparity gradient: over 37 faces, the relief is stretched by 0.14-0.18 %
(0.00 % without the correction), about 0.07 deg on a face seen at 45 deg.
Applying the window's own plane-fit operator ``S`` instead (one Van Cittert
step, ``d + (d - S d)`` with the last iteration's weights) removes the stretch
and took the truck's worst stitched view pose from 0.068 to 0.041 deg. But it
under-corrects strongly convex surfaces: mean error at a jet's most curved
pixels -0.10 px, against -0.046 with ``c * kappa`` and -0.16 without either.
The jet's worst pose went from 0.032 to 0.067 deg, so it was not adopted.
A minmod curvature was also rejected: the two half-windows' fits, the smaller
when they agree in sign, else 0. The truck went 0.068 -> 0.016 deg and the jet
0.032 -> 0.065 deg.

Three more alternatives were measured (worst stitched view pose, 8 views):

- The curvature fitted over a narrower window than the plane (13 columns):
  truck 0.068 -> 0.050 deg, but a ship 0.044 -> 0.088 deg.
- One Van Cittert step where the window lies wholly inside the valid pixels,
  and ``c * kappa`` near the outline, where the step under-corrects:
  ship 0.044 -> 0.023 deg, truck 0.047 deg, but jet_j2 0.052 -> 0.072 deg.
- A narrower *plane* window: it shrinks the crease rounding and the curvature
  fit's spill together, and the bias ``c * kappa`` with the square of the width.
  This one improved the worst case over 10 targets at two renderings
  (0.068 -> 0.047 deg) and is what
  :func:`~prism3d.reconstruct.pipeline.reconstruct_shot` uses (7 x 19; see its
  ``refine_window``). This function keeps 7 x 25, the lower-noise choice for a
  single view.

References
----------
.. [1] M. Bleyer, C. Rhemann, C. Rother, "PatchMatch Stereo - Stereo matching with
   slanted support windows", BMVC 2011.
.. [2] B. D. Lucas and T. Kanade, "An iterative image registration technique with an
   application to stereo vision", IJCAI 1981.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_same_shape
from prism3d.errors import InputError

from . import _refine_kernels as _k
from ._match_kernels import bspline_rows

__all__ = ["refine_slanted"]


def _as_float_channels(img: NDArray, name: str) -> NDArray[np.float32]:
    arr = check_array(img, name, ndim=(2, 3), dtype_kind="uf", min_size=1)
    out = arr.astype(np.float32)
    if arr.dtype.kind == "f" and np.nanmax(np.abs(out)) <= 1.0 + 1e-6:
        out = out * 255.0
    if out.ndim == 2:
        out = out[..., None]
    return np.ascontiguousarray(out)


def _correlation_factor(left: NDArray[np.float32], warped: NDArray[np.float32], mask: NDArray[np.bool_]) -> float:
    """Variance inflation for residuals correlated between neighbouring pixels.

    The least-squares variance assumes every window sample is independent; image
    residuals are smooth over a few pixels, so a window holds fewer independent
    samples. With lag-1 correlations ``rx``, ``ry`` of the residual field ``left -
    warped`` (measured over ``mask``, on every fourth pair of rows: a correlation is a
    property of the whole field) and a first-order autoregressive model, the effective
    sample count shrinks by ``(1 - r) / (1 + r)`` along each axis; the variance grows by
    the inverse (at least 1).
    """
    h = left.shape[0]
    rows = np.arange(0, h - 1, 4)
    m0 = mask[rows][..., None]
    e0 = np.where(m0, left[rows] - warped[rows], 0.0).astype(np.float64)
    e1 = np.where(mask[rows + 1][..., None], left[rows + 1] - warped[rows + 1], 0.0).astype(np.float64)
    den = float((e0 * e0).sum())
    if den <= 0.0:
        return 1.0
    rx = float((e0[:, 1:] * e0[:, :-1]).sum()) / den
    ry = float((e0 * e1).sum()) / den
    rx, ry = (min(max(r, 0.0), 0.95) for r in (rx, ry))
    return (1.0 + rx) / (1.0 - rx) * (1.0 + ry) / (1.0 - ry)


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
        The rectified pair the disparity was matched on (``d = x_left - x_right``).
        How they were resampled matters at this precision: views rectified with
        bilinear interpolation differ at every edge even at the true disparity,
        and the fit reads that as a bias of a few hundredths of a pixel;
        :func:`~prism3d.reconstruct.pipeline.reconstruct_shot` passes views
        rectified with exact B-splines (``RectifyMaps.remap(...,
        interpolation="bspline")``).
    disparity : (H, W) float
        Current disparity (sub-pixel or integer; within ~1 px of the truth).
    valid : (H, W) bool
        Pixels to refine; only these take part in the window sums (so holes and
        the background do not pull on the fit).
    window : (rows, cols)
        Odd window size. Wider than tall: the grating's stripes are vertical.
    iterations : int
        Gauss-Newton iterations (each re-warps the right view).
    extra : (H, W) bool, optional
        Further pixels to estimate (e.g. holes the matcher's checks left inside a
        surface), starting from ``disparity`` there (e.g. the matcher's dense,
        filled output). They take no part in the first iteration's window sums;
        from the second on, those the planes reached do.
    max_change : float
        A pixel whose refined disparity moves by more than this (px) from the input
        keeps the input value and is reported with residual ``inf``.
    orientation_weight : bool
        Weight each pixel's equations by ``gx^2 / (gx^2 + gy^2 + 1)`` of the left
        view's gradient (summed over channels). An edge nearly parallel to the
        epipolar lines says little about horizontal disparity but turns any vertical
        misalignment or noise into a large one (a 0.05 px vertical error reads as
        0.6 px of disparity on a bare 5-degree edge); camouflage outlines are full
        of such edges. A 15-degree edge over a weak grating, 0.05 px misaligned:
        error near the edge 0.061 -> 0.037 px. Off by default because the evidence
        is mixed: on 6 targets x 8 stitched views (matcher scans, paper rig) the
        worst view pose went 0.100 -> 0.078 deg on average (worst case 0.237 ->
        0.145; tank_t2 0.099 -> 0.109), but the flat plate's RMS rises 2 % with the
        grating and 10 % without it, the demo's poses do not change (0.093 ->
        0.092) and its tank comes out 0.4 % wider.
    curvature : bool
        Correct each plane's centre value for the curvature of the surface along
        the rows (see the module notes): the curvature ``c`` of ``d0 + a x + b y +
        c x^2`` is fitted to the refined map over the same window, and the bias it
        gives the plane fit, ``c`` times a factor from the window's own weights, is
        subtracted.

    offset : bool
        Fit an additive offset between the views per window along with the plane
        (``L = R(x - d) + beta``; it is eliminated from the normal equations, so the
        system stays 3 x 3): light that differs between the views but varies slowly,
        such as a flash's specular highlight seen from two angles, or a JPEG block's
        DC error, is absorbed instead of read as disparity.

    Returns
    -------
    disparity : (H, W) float32
        Refined at ``valid`` pixels, unchanged elsewhere.
    residual : (H, W) float32
        Per pixel, the window's mean squared colour error after refinement divided
        by its mean squared horizontal gradient (small = the plane explains the
        images; large = occlusion, specular, or a wrong match); NaN where not valid.
    std : (H, W) float32
        Predicted standard deviation of the refined disparity (px): the least-squares
        covariance of the plane's centre value, ``sigma_e^2 (A^-1)_00``, with the
        residual variance ``sigma_e^2`` of the window; NaN where not valid.

    Raises
    ------
    InputError
        Shapes differ, wrong dtypes, even or too small window, bad counts.
    """
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
    ry, rx = int(window[0]) // 2, int(window[1]) // 2
    m = m.astype(bool) & np.isfinite(d_in)
    if extra is not None:
        ex = check_array(extra, "extra", shape=m.shape).astype(bool) & np.isfinite(d_in) & ~m
    else:
        ex = np.zeros_like(m)
    out = d_in.astype(np.float32).copy()
    resid = np.full(out.shape, np.nan, np.float32)
    std = np.full(out.shape, np.nan, np.float32)
    if not (m.any() or ex.any()):
        return out, resid, std

    # work on the rows/columns around the valid pixels only
    tgt = m | ex
    rows = np.flatnonzero(tgt.any(axis=1))
    cols = np.flatnonzero(tgt.any(axis=0))
    y0, y1 = max(rows[0] - ry, 0), min(rows[-1] + ry + 1, m.shape[0])
    x0, x1 = max(cols[0] - rx, 0), min(cols[-1] + rx + 1, m.shape[1])
    Lc = L[y0:y1, x0:x1]
    Rc = np.ascontiguousarray(R[y0:y1])  # full width: matches may lie left of x0
    support = np.ascontiguousarray(m[y0:y1, x0:x1])
    mc = np.ascontiguousarray(tgt[y0:y1, x0:x1])
    d_ref = float(np.median(out[m])) if m.any() else float(np.median(out[tgt]))
    d0 = np.ascontiguousarray(out[y0:y1, x0:x1] - np.float32(d_ref))
    h, w, nc = Lc.shape
    # the right view is interpolated with cubic B-splines along its rows, value and
    # derivative from the same spline: bicubic convolution (cv2.INTER_CUBIC) pulls
    # the estimate toward whole pixels by up to 0.15 px on crisp stripe edges
    coef = np.empty((nc,) + Rc.shape[:2], np.float32)
    for c in range(nc):
        bspline_rows(np.ascontiguousarray(Rc[..., c]), coef[c])
    Rw = np.empty((h, w, nc), np.float32)
    G = np.empty((h, w, nc), np.float32)
    # window moments by separable correlation: sum over q of f(q) (qx-px)^i (qy-py)^j
    one_x = np.ones(2 * rx + 1)
    one_y = np.ones(2 * ry + 1)
    ramp_x = np.arange(-rx, rx + 1, dtype=np.float64)
    ramp_y = np.arange(-ry, ry + 1, dtype=np.float64)

    def mom(f: NDArray, kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float64]:
        return cv2.sepFilter2D(f, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT)

    Lf = np.ascontiguousarray(Lc, dtype=np.float32)
    # horizontal gradient of the left view: the residual's scale, and the weights
    gl = np.empty_like(Lf)
    for c in range(nc):
        gl[..., c] = cv2.Sobel(Lf[..., c], cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    owt = None
    if orientation_weight:
        sx = (gl * gl).sum(-1)
        sy = np.zeros((h, w), np.float32)
        for c in range(nc):
            gy = cv2.Sobel(Lf[..., c], cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
            sy += gy * gy
        owt = (sx / (sx + sy + np.float32(1.0))).astype(np.float64)
    g2 = np.empty((h, w), np.float64)
    ge = np.empty((h, w), np.float64)
    g1 = np.empty((h, w), np.float64)
    yo = np.empty((h, w), np.float64)
    wt = np.empty((h, w), np.float64)
    no_owt = np.empty((0, 0), np.float64)
    dd = np.where(mc, d0, np.float32(0.0)).astype(np.float64)
    inv00 = np.full((h, w), np.inf)
    for it in range(int(iterations)):
        if it > 0 and ex.any():
            support = mc  # the planes reached the extra pixels: they now carry measurements
        _k.warp_rows(coef, x0, dd, d_ref, Rw, G)
        # linearised about each window pixel's own current disparity d_q, with an
        # offset beta per window when ``offset``:
        # L - R(x - d_plane) ~ e_q + G_q (d_plane(q) - d_q) - beta = 0
        # => normal equations  sum G^2 d_plane [1 x y] = sum (G^2 d_q - G e_q) [1 x y],
        #    with beta eliminated (A - s s'/n, r - s y/n; s = sum G [1 x y])
        _k.products_offset(Lf, Rw, G, support, dd, no_owt if owt is None else owt, g2, ge, g1, yo, wt)
        moments = [mom(g2, one_x, one_y), mom(g2, ramp_x, one_y), mom(g2, one_x, ramp_y),
                   mom(g2, ramp_x * ramp_x, one_y), mom(g2, one_x, ramp_y * ramp_y),
                   mom(g2, ramp_x, ramp_y), mom(ge, one_x, one_y), mom(ge, ramp_x, one_y),
                   mom(ge, one_x, ramp_y)]
        if offset:
            n_off = mom(wt, one_x, one_y)
            s_off = (mom(g1, one_x, one_y), mom(g1, ramp_x, one_y), mom(g1, one_x, ramp_y))
            _k.eliminate_offset(*moments, n_off, *s_off, mom(yo, one_x, one_y))
        # one Gauss-Newton step moves a pixel by at most 1 px; a small ridge on the
        # slopes keeps windows with texture in one column only well posed
        _k.solve_planes(mc, *moments, 1e-6, 1.0, dd, inv00)
    if curvature:
        # the plane fit's bias under curvature c along the rows: a window of
        # d0 + a x + b y + c x^2 yields d0 + c * kappa, kappa = e0' A^-1 sum(g2 x^2 [1 x y])
        # (A: the last iteration's normal matrix); c from the refined map itself
        rx2 = ramp_x * ramp_x
        kappa = np.zeros((h, w))
        rhs = [mom(g2, rx2, one_y), mom(g2, rx2 * ramp_x, one_y), mom(g2, rx2, ramp_y)]
        if offset:
            # the x^2 regressor's own correlation with the offset, removed as for the plane
            s_x2 = mom(g1, rx2, one_y)
            zero = np.zeros_like(s_x2)
            _k.eliminate_offset(zero, zero.copy(), zero.copy(), zero.copy(), zero.copy(), zero.copy(),
                                *rhs, n_off, *s_off, s_x2)
        _k.solve_planes(mc, *moments[:6], *rhs, 1e-6, np.inf, kappa, np.empty((h, w)))
        wm = mc.astype(np.float32)  # 0/1: exact in float32, twice as fast to filter
        ry2 = ramp_y * ramp_y

        def mom32(f: NDArray, kx: NDArray[np.float64], ky: NDArray[np.float64]) -> NDArray[np.float64]:
            return cv2.sepFilter2D(f, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_CONSTANT).astype(np.float64)

        m = (mom32(wm, one_x, one_y), mom32(wm, ramp_x, one_y), mom32(wm, one_x, ramp_y),
             mom32(wm, rx2, one_y), mom32(wm, one_x, ry2), mom32(wm, ramp_x, ramp_y),
             mom32(wm, rx2 * ramp_x, one_y), mom32(wm, rx2, ramp_y), mom32(wm, rx2 * rx2, one_y))
        dm = np.where(mc, dd, 0.0)
        md = (mom(dm, one_x, one_y), mom(dm, ramp_x, one_y), mom(dm, one_x, ramp_y), mom(dm, rx2, one_y))
        curv = np.zeros((h, w))
        _k.row_curvature(mc, m, md, 1e-6, curv)
        dd -= np.where(mc, curv * kappa, 0.0)
    d = dd.astype(np.float32)
    # residual after the last update
    idx = np.nonzero(mc)
    _k.warp_rows(coef, x0, dd, d_ref, Rw, G)
    e2 = np.empty((h, w), np.float64)
    e1 = np.empty((h, w), np.float64)
    gl2 = np.empty((h, w), np.float64)
    _k.residual_sums(Lf, Rw, gl, mc, e2, e1, gl2)
    s_e2 = mom(e2, one_x, one_y)[idx]
    n_obs = mom(mc.astype(np.float32), one_x, one_y)[idx] * nc
    if offset:
        # the residual about the window's best offset: sum e^2 - (sum e)^2 / n
        s_e = mom(e1, one_x, one_y)[idx]
        s_e2 = np.maximum(s_e2 - np.divide(s_e * s_e, n_obs, out=np.zeros_like(s_e), where=n_obs > 0), 0.0)
    ratio = s_e2 / (mom(gl2, one_x, one_y)[idx] + 1e-6)
    with np.errstate(invalid="ignore"):  # inv00 is inf where a window was singular
        var = s_e2 / np.maximum(n_obs - 3.0 - offset, 1.0) * inv00[idx] * _correlation_factor(Lf, Rw, mc)
    var = np.where(np.isfinite(var) & (var >= 0), var, np.inf)
    moved = np.abs(d[idx] - d0[idx]) > float(max_change)
    d[idx] = np.where(moved, d0[idx], d[idx])
    ratio = np.where(moved, np.inf, ratio)
    var = np.where(moved, np.inf, var)
    out[y0:y1, x0:x1] = np.where(mc, d + np.float32(d_ref), out[y0:y1, x0:x1])
    rc = resid[y0:y1, x0:x1]
    rc[idx] = ratio.astype(np.float32)
    sd = std[y0:y1, x0:x1]
    sd[idx] = np.sqrt(var).astype(np.float32)
    return out, resid, std
