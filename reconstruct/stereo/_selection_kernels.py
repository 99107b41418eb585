"""Numba kernels behind :mod:`prism3d.reconstruct.stereo.selection` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def occlusions(disp, occluded, outside, margin):  # pragma: no cover - compiled
    """Per row of a dense disparity map ``(H, W)``: ``outside`` where ``x - d < 0`` (the
    match lies beyond the right view's left edge) and ``occluded`` where a pixel to the
    right, nearer by more than ``margin`` px of disparity, maps onto the same right-view
    column (within half a pixel) or left of it: that pixel hides this one from the
    right camera."""
    h, w = disp.shape
    for y in prange(h):
        lowest = np.inf  # smallest right-view column x - d seen so far, scanning right to left
        d_lowest = 0.0
        for x in range(w - 1, -1, -1):
            d = disp[y, x]
            occluded[y, x] = False
            outside[y, x] = False
            if not np.isfinite(d):
                continue
            xr = x - d
            outside[y, x] = xr < 0.0
            if xr > lowest - 0.5 and d_lowest > d + margin:
                occluded[y, x] = True
            elif xr < lowest:
                lowest = xr
                d_lowest = d


@njit(cache=True, nogil=True, parallel=True)
def cell_sums(disp, known, s, ref, out):  # pragma: no cover - compiled
    """Sums over ``s x s`` cells of the known pixels: ``out[:, cy, cx]`` = count and the
    sums of ``x, y, x^2, y^2, x y, d, d x, d y, d^2`` (``d = disp - ref``, absolute pixel
    coordinates)."""
    h, w = disp.shape
    hs, ws = out.shape[1], out.shape[2]
    for cy in prange(hs):
        for cx in range(ws):
            acc = np.zeros(10)
            for y in range(cy * s, min(cy * s + s, h)):
                for x in range(cx * s, min(cx * s + s, w)):
                    if not known[y, x]:
                        continue
                    d = disp[y, x] - ref
                    fx = np.float64(x)
                    fy = np.float64(y)
                    acc[0] += 1.0
                    acc[1] += fx
                    acc[2] += fy
                    acc[3] += fx * fx
                    acc[4] += fy * fy
                    acc[5] += fx * fy
                    acc[6] += d
                    acc[7] += d * fx
                    acc[8] += d * fy
                    acc[9] += d * d
            for i in range(10):
                out[i, cy, cx] = acc[i]


@njit(cache=True, nogil=True, parallel=True)
def plane_predict(ys, xs, cells, s, k, side, min_n, est, var):  # pragma: no cover - compiled
    """For each target pixel ``(ys[i], xs[i])``, the least-squares plane ``d = a + b dx +
    c dy`` through the known pixels of the cells around it (``cells`` from
    :func:`cell_sums` at cell size ``s``; ``k`` cells each way, only to the left for
    ``side`` -1, only to the right for +1): ``est[i] = a`` and ``var[i] = s2 (1 +
    (M^-1)_00)``, the variance of a new observation at the pixel (``s2`` the residual
    variance of the fit, ``M`` the moment matrix). A target keeps ``est``/``var`` when
    this window has fewer than ``min_n`` known pixels, is singular, or predicts a
    larger variance."""
    hs, ws = cells.shape[1], cells.shape[2]
    for i in prange(len(ys)):
        py = np.float64(ys[i])
        px = np.float64(xs[i])
        cy0 = ys[i] // s
        cx0 = xs[i] // s
        lo = cx0 - k if side <= 0 else cx0
        hi = cx0 + k if side >= 0 else cx0
        acc = np.zeros(10)
        for cy in range(max(cy0 - k, 0), min(cy0 + k + 1, hs)):
            for cx in range(max(lo, 0), min(hi + 1, ws)):
                if cells[0, cy, cx] == 0.0:
                    continue
                for j in range(10):
                    acc[j] += cells[j, cy, cx]
        n = acc[0]
        if n < min_n:
            continue
        # moments about the target pixel
        a01 = acc[1] - px * n
        a02 = acc[2] - py * n
        a11 = acc[3] - 2.0 * px * acc[1] + px * px * n
        a22 = acc[4] - 2.0 * py * acc[2] + py * py * n
        a12 = acc[5] - px * acc[2] - py * acc[1] + px * py * n
        r0 = acc[6]
        r1 = acc[7] - px * acc[6]
        r2 = acc[8] - py * acc[6]
        c00 = a11 * a22 - a12 * a12
        c01 = a02 * a12 - a01 * a22
        c02 = a01 * a12 - a02 * a11
        c11 = n * a22 - a02 * a02
        c12 = a01 * a02 - n * a12
        c22 = n * a11 - a01 * a01
        det = n * c00 + a01 * c01 + a02 * c02
        if not (det > 1e-9 * n * n * n):
            continue
        b0 = (c00 * r0 + c01 * r1 + c02 * r2) / det
        b1 = (c01 * r0 + c11 * r1 + c12 * r2) / det
        b2 = (c02 * r0 + c12 * r1 + c22 * r2) / det
        rss = acc[9] - (b0 * r0 + b1 * r1 + b2 * r2)
        s2 = max(rss, 0.0) / max(n - 3.0, 1.0)
        v = s2 * (1.0 + c00 / det)
        if np.isfinite(b0) and np.isfinite(v) and v < var[i]:
            est[i] = b0
            var[i] = v
