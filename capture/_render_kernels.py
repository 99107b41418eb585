"""Numba kernels behind :mod:`prism3d.capture.render` (private).

Inputs are validated by the public wrappers; these loops assume contiguous float64.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def grid_rays(
    K: np.ndarray,
    dist: np.ndarray,
    width: int,
    height: int,
    R: np.ndarray,
    out: np.ndarray,
    out_z: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Unit rays through every distorted pixel centre, rotated by ``R``.

    ``out[v, u] = R @ ray_cam`` and ``out_z[v, u] = ray_cam[2]``. Same model and
    Newton inversion as ``CameraModel.undistort_normalized``.
    """
    fx = K[0, 0]
    s = K[0, 1]
    cx = K[0, 2]
    fy = K[1, 1]
    cy = K[1, 2]
    k1 = dist[0]
    k2 = dist[1]
    p1 = dist[2]
    p2 = dist[3]
    k3 = dist[4]
    has_dist = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    for v in prange(height):
        yd = (v - cy) / fy
        for u in range(width):
            xd = (u - cx - s * yd) / fx
            x = xd
            y = yd
            if has_dist:
                for _ in range(30):
                    r2 = x * x + y * y
                    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
                    fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
                    fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
                    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
                    j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
                    j21 = j12
                    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
                    det = j11 * j22 - j12 * j21
                    dx = (j22 * fx_ - j12 * fy_) / det
                    dy = (-j21 * fx_ + j11 * fy_) / det
                    x -= dx
                    y -= dy
                    if abs(dx) < 1e-15 and abs(dy) < 1e-15:
                        break
            n = 1.0 / np.sqrt(x * x + y * y + 1.0)
            cx_ = x * n
            cy_ = y * n
            out[v, u, 0] = R[0, 0] * cx_ + R[0, 1] * cy_ + R[0, 2] * n
            out[v, u, 1] = R[1, 0] * cx_ + R[1, 1] * cy_ + R[1, 2] * n
            out[v, u, 2] = R[2, 0] * cx_ + R[2, 1] * cy_ + R[2, 2] * n
            out_z[v, u] = n


@njit(cache=True, nogil=True, parallel=True)
def refine_hits(
    o: np.ndarray,
    d: np.ndarray,
    gface: np.ndarray,
    A: np.ndarray,
    E1: np.ndarray,
    E2: np.ndarray,
    N: np.ndarray,
    t32: np.ndarray,
    uv32: np.ndarray,
    t_out: np.ndarray,
    uv_out: np.ndarray,
    p_out: np.ndarray,
    n_out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Moller-Trumbore in float64 on the triangles float32 ray casting picked.

    ``o`` may have one row (shared origin) or one row per ray.
    """
    stride = 0 if o.shape[0] == 1 else 1
    for i in prange(d.shape[0]):
        f = gface[i]
        oi = i * stride
        ox = o[oi, 0]
        oy = o[oi, 1]
        oz = o[oi, 2]
        dx = d[i, 0]
        dy = d[i, 1]
        dz = d[i, 2]
        e1x = E1[f, 0]
        e1y = E1[f, 1]
        e1z = E1[f, 2]
        e2x = E2[f, 0]
        e2y = E2[f, 1]
        e2z = E2[f, 2]
        px = dy * e2z - dz * e2y
        py = dz * e2x - dx * e2z
        pz = dx * e2y - dy * e2x
        det = e1x * px + e1y * py + e1z * pz
        tx = ox - A[f, 0]
        ty = oy - A[f, 1]
        tz = oz - A[f, 2]
        qx = ty * e1z - tz * e1y
        qy = tz * e1x - tx * e1z
        qz = tx * e1y - ty * e1x
        if det != 0.0 and np.isfinite(det):
            inv = 1.0 / det
            u = (tx * px + ty * py + tz * pz) * inv
            v = (dx * qx + dy * qy + dz * qz) * inv
            t = (e2x * qx + e2y * qy + e2z * qz) * inv
        else:
            u = uv32[i, 0]
            v = uv32[i, 1]
            t = t32[i]
        t_out[i] = t
        uv_out[i, 0] = u
        uv_out[i, 1] = v
        p_out[i, 0] = ox + t * dx
        p_out[i, 1] = oy + t * dy
        p_out[i, 2] = oz + t * dz
        nx = N[f, 0]
        ny = N[f, 1]
        nz = N[f, 2]
        if nx * dx + ny * dy + nz * dz > 0.0:
            nx = -nx
            ny = -ny
            nz = -nz
        n_out[i, 0] = nx
        n_out[i, 1] = ny
        n_out[i, 2] = nz
