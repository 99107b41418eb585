"""Numba kernels behind :mod:`prism3d.reconstruct.stereo.refine` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def solve_planes(mask, a00, a01, a02, a11, a22, a12, r0, r1, r2, ridge, max_step,
                 disp, inv00):  # pragma: no cover - compiled
    """Solve each masked pixel's 3x3 normal equations; write the plane's centre value
    into ``disp`` (moved by at most ``max_step``) and the (0, 0) element of the
    inverse normal matrix into ``inv00`` (the centre value's variance per unit
    residual variance)."""
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
            inv00[y, x] = c00 / det
            cur = disp[y, x]
            if dn > cur + max_step:
                dn = cur + max_step
            elif dn < cur - max_step:
                dn = cur - max_step
            disp[y, x] = dn


@njit(cache=True, nogil=True, parallel=True)
def warp_rows(coef, x0, disp, d_ref, val, grad):  # pragma: no cover - compiled
    """Cubic B-spline interpolation along rows, and its exact x-derivative.

    coef : (C, H, Wf) float32 B-spline coefficients of each channel's rows;
    val, grad : (H, W, C) float32 out, at ``x = x0 + col - (disp[row, col] + d_ref)``.
    Indices beyond the row are clamped.
    """
    nc, h, wf = coef.shape
    w = disp.shape[1]
    for y in prange(h):
        for x in range(w):
            xs = x0 + x - (disp[y, x] + d_ref)
            i = int(np.floor(xs))
            t = xs - i
            t2 = t * t
            t3 = t2 * t
            u = 1.0 - t
            w0 = u * u * u / 6.0
            w1 = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
            w2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
            w3 = t3 / 6.0
            g0 = -0.5 * u * u
            g1 = 0.5 * (3.0 * t2 - 4.0 * t)
            g2 = 0.5 * (-3.0 * t2 + 2.0 * t + 1.0)
            g3 = 0.5 * t2
            i0 = min(max(i - 1, 0), wf - 1)
            i1 = min(max(i, 0), wf - 1)
            i2 = min(max(i + 1, 0), wf - 1)
            i3 = min(max(i + 2, 0), wf - 1)
            for c in range(nc):
                a0 = coef[c, y, i0]
                a1 = coef[c, y, i1]
                a2 = coef[c, y, i2]
                a3 = coef[c, y, i3]
                val[y, x, c] = w0 * a0 + w1 * a1 + w2 * a2 + w3 * a3
                grad[y, x, c] = g0 * a0 + g1 * a1 + g2 * a2 + g3 * a3


@njit(cache=True, nogil=True, parallel=True)
def row_curvature(mask, m, md, ridge, curv):  # pragma: no cover - compiled
    """Per masked pixel, the ``c`` of the least-squares fit ``d(q) = d0 + a qx + b qy +
    c qx^2`` to a map over a window (coordinates relative to the pixel).

    m : 9 (H, W) arrays: window sums of the weights times ``1, x, y, x^2, y^2, xy, x^3,
    x^2 y, x^4``; md : 4 (H, W) arrays: window sums of the weights times ``d`` and ``d x, d
    y, d x^2``; ``ridge`` times the weight sum is added to the diagonal of the three
    shape terms. Cholesky solve of the 4x4 normal equations; ``curv`` (H, W) out,
    left unchanged where the system is singular.
    """
    h, w = mask.shape
    for y in prange(h):
        A = np.empty((4, 4))
        L = np.zeros((4, 4))
        z = np.empty(4)
        for x in range(w):
            if not mask[y, x]:
                continue
            s0 = m[0][y, x]
            if s0 <= 0.0:
                continue
            lam = ridge * s0 + 1e-9
            A[0, 0] = s0
            A[0, 1] = m[1][y, x]
            A[0, 2] = m[2][y, x]
            A[0, 3] = m[3][y, x]
            A[1, 1] = m[3][y, x] + lam
            A[1, 2] = m[5][y, x]
            A[1, 3] = m[6][y, x]
            A[2, 2] = m[4][y, x] + lam
            A[2, 3] = m[7][y, x]
            A[3, 3] = m[8][y, x] + lam
            ok = True
            for i in range(4):
                for j in range(i + 1):
                    s = A[j, i]
                    for k in range(j):
                        s -= L[i, k] * L[j, k]
                    if i == j:
                        if not s > 1e-12 * s0:
                            ok = False
                            break
                        L[i, i] = np.sqrt(s)
                    else:
                        L[i, j] = s / L[j, j]
                if not ok:
                    break
            if not ok:
                continue
            # forward substitution; the last unknown of L^T x = z is z[3] / L[3, 3]
            for i in range(4):
                s = md[i][y, x]
                for k in range(i):
                    s -= L[i, k] * z[k]
                z[i] = s / L[i, i]
            c = z[3] / L[3, 3]
            if np.isfinite(c):
                curv[y, x] = c


@njit(cache=True, nogil=True, parallel=True)
def products_offset(left, warped, grad, mask, disp, owt, g2, ge, g1, y1, wt):  # pragma: no cover - compiled
    """:func:`products` and, for the per-window offset, ``g1 = w sum_c G``, ``y1 = w
    sum_c (G d - e)`` and the sample weight ``wt = w nc`` (``w`` = ``owt`` or 1 on the
    mask, 0 off it; ``owt`` of shape (0, 0) means no orientation weights)."""
    h, w, nc = left.shape
    weighted = owt.shape[0] > 0
    for y in prange(h):
        for x in range(w):
            if not mask[y, x]:
                g2[y, x] = 0.0
                ge[y, x] = 0.0
                g1[y, x] = 0.0
                y1[y, x] = 0.0
                wt[y, x] = 0.0
                continue
            s2 = 0.0
            se = 0.0
            s1 = 0.0
            sr = 0.0
            for c in range(nc):
                g = grad[y, x, c]
                e = left[y, x, c] - warped[y, x, c]
                s2 += g * g
                se += g * e
                s1 += g
                sr += e
            q = owt[y, x] if weighted else 1.0
            d = disp[y, x]
            g2[y, x] = q * s2
            ge[y, x] = q * (s2 * d - se)
            g1[y, x] = q * s1
            y1[y, x] = q * (s1 * d - sr)
            wt[y, x] = q * nc


@njit(cache=True, nogil=True, parallel=True)
def eliminate_offset(a00, a01, a02, a11, a22, a12, r0, r1, r2, n, s0, sx, sy, yy):  # pragma: no cover
    """In place, the plane's normal equations with the window offset eliminated (Schur
    complement): ``A - s s' / n`` and ``r - s y / n`` (unchanged where ``n`` is 0)."""
    h, w = a00.shape
    for y in prange(h):
        for x in range(w):
            nn = n[y, x]
            if nn <= 0.0:
                continue
            inv = 1.0 / nn
            p0 = s0[y, x]
            px = sx[y, x]
            py = sy[y, x]
            q = yy[y, x]
            a00[y, x] -= p0 * p0 * inv
            a01[y, x] -= p0 * px * inv
            a02[y, x] -= p0 * py * inv
            a11[y, x] -= px * px * inv
            a22[y, x] -= py * py * inv
            a12[y, x] -= px * py * inv
            r0[y, x] -= p0 * q * inv
            r1[y, x] -= px * q * inv
            r2[y, x] -= py * q * inv


@njit(cache=True, nogil=True, parallel=True)
def residual_sums(left, warped, lgrad, mask, e2, e1, gl2):  # pragma: no cover - compiled
    """Per masked pixel: ``e2 = sum_c e^2``, ``e1 = sum_c e`` (``e = L - Rw``) and
    ``gl2 = sum_c gl^2`` (0 off the mask)."""
    h, w, nc = left.shape
    for y in prange(h):
        for x in range(w):
            if not mask[y, x]:
                e2[y, x] = 0.0
                e1[y, x] = 0.0
                gl2[y, x] = 0.0
                continue
            a = 0.0
            b = 0.0
            g = 0.0
            for c in range(nc):
                e = left[y, x, c] - warped[y, x, c]
                a += e * e
                b += e
                g += lgrad[y, x, c] * lgrad[y, x, c]
            e2[y, x] = a
            e1[y, x] = b
            gl2[y, x] = g
