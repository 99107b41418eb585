"""Numba kernels behind :mod:`prism3d.capture.scenes` (private)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

_M1 = np.uint64(0x9E3779B97F4A7C15)
_M2 = np.uint64(0xC2B2AE3D27D4EB4F)
_M3 = np.uint64(0x165667B19E3779F9)
_M4 = np.uint64(0x27D4EB2F165667C5)
_F1 = np.uint64(0xBF58476D1CE4E5B9)
_F2 = np.uint64(0x94D049BB133111EB)


@njit(cache=True, nogil=True, inline="always")
def _hash01(ix: np.int64, iy: np.int64, iz: np.int64, seed: np.uint64) -> float:  # pragma: no cover
    h = (
        np.uint64(ix) * _M1
        ^ np.uint64(iy) * _M2
        ^ np.uint64(iz) * _M3
        ^ seed * _M4
    )
    h ^= h >> np.uint64(30)
    h *= _F1
    h ^= h >> np.uint64(27)
    h *= _F2
    h ^= h >> np.uint64(31)
    return float(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, nogil=True, parallel=True)
def value_noise(points: np.ndarray, inv_cell: float, seed: np.uint64, out: np.ndarray) -> None:  # pragma: no cover
    """Trilinear value noise with the quintic fade; ``out[i]`` in [0, 1]."""
    for i in prange(points.shape[0]):
        px = points[i, 0] * inv_cell
        py = points[i, 1] * inv_cell
        pz = points[i, 2] * inv_cell
        fx0 = np.floor(px)
        fy0 = np.floor(py)
        fz0 = np.floor(pz)
        fx = px - fx0
        fy = py - fy0
        fz = pz - fz0
        wx = fx * fx * fx * (fx * (fx * 6.0 - 15.0) + 10.0)
        wy = fy * fy * fy * (fy * (fy * 6.0 - 15.0) + 10.0)
        wz = fz * fz * fz * (fz * (fz * 6.0 - 15.0) + 10.0)
        ix = np.int64(fx0)
        iy = np.int64(fy0)
        iz = np.int64(fz0)
        acc = 0.0
        for dx in range(2):
            ax = wx if dx else 1.0 - wx
            for dy in range(2):
                ay = wy if dy else 1.0 - wy
                for dz in range(2):
                    az = wz if dz else 1.0 - wz
                    acc += ax * ay * az * _hash01(ix + dx, iy + dy, iz + dz, seed)
        out[i] = acc
