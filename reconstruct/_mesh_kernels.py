"""Numba kernels behind :mod:`prism3d.reconstruct.meshing` (private)."""

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
