"""Numba kernels behind :mod:`prism3d.capture.scenes` and :mod:`prism3d.capture.camouflage` (private)."""

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


@njit(cache=True, nogil=True, parallel=True)
def camouflage_labels(
    q: np.ndarray,
    offsets: np.ndarray,
    tables: np.ndarray,
    thresholds: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Paint labels from lattice coordinates (the loops of ``camouflage._noise``).

    ``q`` ``(octaves, 3, n)`` float64 holds ``(rotation_o * freq_o) @ points.T`` (the
    matrix product stays in numpy so its rounding is numpy's); everything after it
    -- offset, floor, float32 smoothstep fade, 8-corner gather, trilinear blend,
    octave sum, thresholds -- repeats ``_noise`` operation for operation in the same
    precision and order, so the labels are bit-identical to the numpy path. Layers
    are tested from the top down: the first one above its threshold is the label,
    and the layers below it are never evaluated.
    """
    octaves = q.shape[0]
    n = q.shape[2]
    layers = tables.shape[2]
    three = np.float32(3.0)
    two = np.float32(2.0)
    half = np.float32(0.5)
    block = 1024
    for blk in prange((n + block - 1) // block):
        # per-octave cell and fade of the current point, shared by all layers
        fade = np.empty((octaves, 3), dtype=np.float32)
        base = np.empty(octaves, dtype=np.int64)
        for i in range(blk * block, min(n, (blk + 1) * block)):
            for o in range(octaves):
                x = q[o, 0, i] + offsets[o, 0]
                y = q[o, 1, i] + offsets[o, 1]
                z = q[o, 2, i] + offsets[o, 2]
                xi = np.floor(x)
                yi = np.floor(y)
                zi = np.floor(z)
                fx = np.float32(x - xi)
                fy = np.float32(y - yi)
                fz = np.float32(z - zi)
                fade[o, 0] = fx * fx * (three - two * fx)
                fade[o, 1] = fy * fy * (three - two * fy)
                fade[o, 2] = fz * fz * (three - two * fz)
                base[o] = (np.int64(xi) & 31) * 1024 + (np.int64(yi) & 31) * 32 + (np.int64(zi) & 31)
            lab = 0
            for k in range(layers - 1, -1, -1):
                acc = np.float32(0.0)
                amp = np.float32(1.0)
                for o in range(octaves):
                    b = base[o]
                    ux = fade[o, 0]
                    uy = fade[o, 1]
                    uz = fade[o, 2]
                    # corners c[4 dz + 2 dy + dx]; blend along z, then y, then x
                    l0 = tables[b, 0, k]
                    l1 = tables[b, 1, k]
                    l2 = tables[b, 2, k]
                    l3 = tables[b, 3, k]
                    l0 = l0 + (tables[b, 4, k] - l0) * uz
                    l1 = l1 + (tables[b, 5, k] - l1) * uz
                    l2 = l2 + (tables[b, 6, k] - l2) * uz
                    l3 = l3 + (tables[b, 7, k] - l3) * uz
                    v0 = l0 + (l2 - l0) * uy
                    v1 = l1 + (l3 - l1) * uy
                    acc = acc + ((v1 - v0) * ux + v0) * amp
                    amp = amp * half
                if acc > thresholds[k]:
                    lab = k + 1
                    break
            out[i] = lab
