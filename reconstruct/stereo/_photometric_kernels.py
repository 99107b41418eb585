"""Numba kernel behind :mod:`prism3d.reconstruct.stereo.photometric` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def tukey_weights(resid, tukey_c, mad_to_sigma, min_scale, weights):  # pragma: no cover - compiled
    """Tukey's biweight of each channel's residuals on that channel's MAD scale.

    resid : (N, C) float64 residuals; weights : (N, C) float64 out,
    ``(1 - u^2)^2`` for ``|u| < 1`` else 0, ``u = r / (tukey_c * s)``,
    ``s = mad_to_sigma * median(|r|) + min_scale``.
    """
    n, nc = resid.shape
    for c in prange(nc):
        a = np.empty(n)
        for k in range(n):
            a[k] = abs(resid[k, c])
        cs = tukey_c * (mad_to_sigma * np.median(a) + min_scale)
        for k in range(n):
            u = resid[k, c] / cs
            weights[k, c] = (1.0 - u * u) ** 2 if abs(u) < 1.0 else 0.0
