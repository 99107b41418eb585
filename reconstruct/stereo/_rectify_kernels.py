"""Numba kernels behind :mod:`prism3d.reconstruct.stereo.rectify` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, inline="always")
def _taps(t, base, n, wt, ii):  # pragma: no cover - compiled
    """Cubic B-spline weights at fraction ``t`` and the 4 clamped indices from ``base - 1``."""
    u = 1.0 - t
    t2 = t * t
    wt[0] = u * u * u / 6.0
    wt[1] = (3.0 * t2 * t - 6.0 * t2 + 4.0) / 6.0
    wt[2] = (-3.0 * t2 * t + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    wt[3] = t2 * t / 6.0
    for k in range(4):
        ii[k] = min(max(base - 1 + k, 0), n - 1)


@njit(cache=True, nogil=True, parallel=True)
def bspline_remap(coef, map_x, map_y, lo, hi, out):  # pragma: no cover - compiled
    """Sample a cubic B-spline image at arbitrary points.

    coef : (C, h, w) float32 B-spline coefficients of each channel (both axes
    prefiltered); map_x, map_y : (H, W) float32 source positions; out : (H, W, C)
    float32. A point outside ``[0, w - 1] x [0, h - 1]`` (or NaN) gives 0, as
    OpenCV's constant border; values are clipped to ``[lo, hi]``. Indices beyond
    the coefficient grid are clamped (its boundary is mirrored by the prefilter).
    """
    nc, h, w = coef.shape
    oh, ow = map_x.shape
    for r in prange(oh):
        wx = np.empty(4)
        wy = np.empty(4)
        ix = np.empty(4, np.int64)
        iy = np.empty(4, np.int64)
        for q in range(ow):
            xs = map_x[r, q]
            ys = map_y[r, q]
            if not (xs >= 0.0 and xs <= w - 1.0 and ys >= 0.0 and ys <= h - 1.0):
                for c in range(nc):
                    out[r, q, c] = 0.0
                continue
            i = int(np.floor(xs))
            j = int(np.floor(ys))
            _taps(xs - i, i, w, wx, ix)
            _taps(ys - j, j, h, wy, iy)
            for c in range(nc):
                s = 0.0
                for a in range(4):
                    row = 0.0
                    for b in range(4):
                        row += wx[b] * coef[c, iy[a], ix[b]]
                    s += wy[a] * row
                out[r, q, c] = min(max(s, lo), hi)
