"""Numba kernels behind :mod:`prism3d.reconstruct.stereo.meshing` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def range_limited_gaussian(depth: np.ndarray, weights: np.ndarray, jump: np.ndarray,
                           out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Gaussian smoothing of ``depth`` (NaN = hole) that only averages neighbours
    within ``jump[r, c]`` of the centre pixel's depth (no smoothing across steps)."""
    h, w = depth.shape
    k = weights.shape[0]
    r0 = k // 2
    for r in prange(h):
        for c in range(w):
            zc = depth[r, c]
            if np.isnan(zc):
                out[r, c] = np.nan
                continue
            lim = jump[r, c]
            s = 0.0
            sw = 0.0
            for i in range(k):
                rr = r + i - r0
                if rr < 0 or rr >= h:
                    continue
                for j in range(k):
                    cc = c + j - r0
                    if cc < 0 or cc >= w:
                        continue
                    z = depth[rr, cc]
                    if np.isnan(z) or abs(z - zc) > lim:
                        continue
                    wt = weights[i, j]
                    s += wt * z
                    sw += wt
            out[r, c] = s / sw


@njit(cache=True, nogil=True, inline="always")
def _grid_diff(p, m, y, x, dy, dx, out):  # pragma: no cover - compiled
    """Difference of the grid along (dy, dx) at (y, x): central where both neighbours
    are valid, one-sided where one is; False where neither is."""
    h, w = m.shape
    yf, xf = y + dy, x + dx
    yb, xb = y - dy, x - dx
    has_f = yf < h and xf < w and m[yf, xf]
    has_b = yb >= 0 and xb >= 0 and m[yb, xb]
    if has_f and has_b:
        for c in range(3):
            out[c] = 0.5 * ((np.float64(p[yf, xf, c]) - np.float64(p[y, x, c]))
                            + (np.float64(p[y, x, c]) - np.float64(p[yb, xb, c])))
    elif has_f:
        for c in range(3):
            out[c] = np.float64(p[yf, xf, c]) - np.float64(p[y, x, c])
    elif has_b:
        for c in range(3):
            out[c] = np.float64(p[y, x, c]) - np.float64(p[yb, xb, c])
    else:
        return False
    return True


@njit(cache=True, nogil=True, parallel=True)
def grid_normals(p, m, out):  # pragma: no cover - compiled
    """Unit normals of an organised grid ``p`` (H, W, 3) valid where ``m``, facing
    the origin; ``out`` (H, W, 3) float32, NaN where no normal can be formed."""
    h, w = m.shape
    nan = np.float32(np.nan)
    for y in prange(h):
        du = np.empty(3, np.float64)
        dv = np.empty(3, np.float64)
        for x in range(w):
            ok = m[y, x] and _grid_diff(p, m, y, x, 0, 1, du) and _grid_diff(p, m, y, x, 1, 0, dv)
            if not ok:
                out[y, x, 0] = nan
                out[y, x, 1] = nan
                out[y, x, 2] = nan
                continue
            n0 = du[1] * dv[2] - du[2] * dv[1]
            n1 = du[2] * dv[0] - du[0] * dv[2]
            n2 = du[0] * dv[1] - du[1] * dv[0]
            nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if not nn > 0:
                out[y, x, 0] = nan
                out[y, x, 1] = nan
                out[y, x, 2] = nan
                continue
            if n0 * p[y, x, 0] + n1 * p[y, x, 1] + n2 * p[y, x, 2] > 0:
                nn = -nn
            out[y, x, 0] = np.float32(n0 / nn)
            out[y, x, 1] = np.float32(n1 / nn)
            out[y, x, 2] = np.float32(n2 / nn)
