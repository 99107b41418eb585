"""Numba kernels behind :mod:`prism3d.reconstruct.refine` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def products(left, warped, grad, mask, disp, g2, ge):  # pragma: no cover - compiled
    """Per pixel: ``g2 = sum_c G^2`` and ``ge = g2 d - sum_c G (L - Rw)`` (0 off mask)."""
    h, w, nc = left.shape
    for y in prange(h):
        for x in range(w):
            if not mask[y, x]:
                g2[y, x] = 0.0
                ge[y, x] = 0.0
                continue
            s2 = 0.0
            se = 0.0
            for c in range(nc):
                g = grad[y, x, c]
                s2 += g * g
                se += g * (left[y, x, c] - warped[y, x, c])
            g2[y, x] = s2
            ge[y, x] = s2 * disp[y, x] - se


@njit(cache=True, nogil=True, parallel=True)
def solve_planes(mask, a00, a01, a02, a11, a22, a12, r0, r1, r2, ridge, max_step,
                 disp):  # pragma: no cover - compiled
    """Solve each masked pixel's 3x3 normal equations; write the plane's centre value
    into ``disp`` (moved by at most ``max_step``)."""
    h, w = mask.shape
    for y in prange(h):
        for x in range(w):
            if not mask[y, x]:
                continue
            s0 = np.float64(a00[y, x])
            if s0 <= 0.0:
                continue
            sx = np.float64(a01[y, x])
            sy = np.float64(a02[y, x])
            lam = ridge * s0 + 1e-9
            sxx = np.float64(a11[y, x]) + lam
            syy = np.float64(a22[y, x]) + lam
            sxy = np.float64(a12[y, x])
            c00 = sxx * syy - sxy * sxy
            c01 = sy * sxy - sx * syy
            c02 = sx * sxy - sy * sxx
            det = s0 * c00 + sx * c01 + sy * c02
            if not (abs(det) > 1e-12 * s0 * s0 * s0 + 1e-30):
                continue
            dn = (np.float64(r0[y, x]) * c00 + np.float64(r1[y, x]) * c01
                  + np.float64(r2[y, x]) * c02) / det
            if not np.isfinite(dn):
                continue
            cur = disp[y, x]
            if dn > cur + max_step:
                dn = cur + max_step
            elif dn < cur - max_step:
                dn = cur - max_step
            disp[y, x] = dn


@njit(cache=True, nogil=True, parallel=True)
def solve_planes_shiftable(mask, a00, a01, a02, a11, a22, a12, r0, r1, r2, q, shifts, min_support,
                           ridge, max_step, disp, resid):  # pragma: no cover - compiled
    """Shiftable-window variant of :func:`solve_planes`.

    For every masked pixel p, the plane is fitted in each window centred at
    ``p + shift`` (``shifts`` (K, 2) rows, cols; the first is (0, 0)), and the
    window whose plane explains its disparity measurements best (smallest
    gradient-weighted mean squared deviation, ``resid``, px^2) gives the value at p.
    A shifted window must hold at least ``min_support`` times the texture of the
    centred one. ``q`` is the window sum of ``g2 t^2`` (``t`` the per-pixel
    disparity measurement), so a window's residual is ``q - sol . rhs``.
    """
    h, w = mask.shape
    ns = shifts.shape[0]
    for y in prange(h):
        for x in range(w):
            if not mask[y, x]:
                continue
            s_c = a00[y, x]
            if s_c <= 0.0:
                continue
            best = np.inf
            best_d = disp[y, x]
            for k in range(ns):
                yy = y + shifts[k, 0]
                xx = x + shifts[k, 1]
                if yy < 0 or yy >= h or xx < 0 or xx >= w:
                    continue
                s0 = a00[yy, xx]
                if s0 <= 0.0 or s0 < min_support * s_c:
                    continue
                sx = a01[yy, xx]
                sy = a02[yy, xx]
                lam = ridge * s0 + 1e-9
                sxx = a11[yy, xx] + lam
                syy = a22[yy, xx] + lam
                sxy = a12[yy, xx]
                c00 = sxx * syy - sxy * sxy
                c01 = sy * sxy - sx * syy
                c02 = sx * sxy - sy * sxx
                c11 = s0 * syy - sy * sy
                c12 = sx * sy - s0 * sxy
                c22 = s0 * sxx - sx * sx
                det = s0 * c00 + sx * c01 + sy * c02
                if not (abs(det) > 1e-12 * s0 * s0 * s0 + 1e-30):
                    continue
                b0 = r0[yy, xx]
                b1 = r1[yy, xx]
                b2 = r2[yy, xx]
                p0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
                p1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
                p2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
                if not (np.isfinite(p0) and np.isfinite(p1) and np.isfinite(p2)):
                    continue
                res = (q[yy, xx] - (p0 * b0 + p1 * b1 + p2 * b2)) / s0
                if res < best:
                    best = res
                    # the window's plane evaluated at p (p - centre = -shift)
                    best_d = p0 - p1 * shifts[k, 1] - p2 * shifts[k, 0]
            if best == np.inf:
                continue
            cur = disp[y, x]
            if best_d > cur + max_step:
                best_d = cur + max_step
            elif best_d < cur - max_step:
                best_d = cur - max_step
            disp[y, x] = best_d
            resid[y, x] = max(best, 0.0)


@njit(cache=True, nogil=True, parallel=True)
def products_q(g2, ge, mask, q):  # pragma: no cover - compiled
    """``q = ge^2 / g2`` (= g2 t^2 with t = ge / g2), 0 off the mask or without texture."""
    h, w = g2.shape
    for y in prange(h):
        for x in range(w):
            g = g2[y, x]
            q[y, x] = ge[y, x] * ge[y, x] / g if (mask[y, x] and g > 0.0) else 0.0
