"""Rotations, rigid transforms and point conversions, shared by every layer.

Conventions (``../DESIGN.md``): transforms are 4x4 float64 named ``T_<to>_<from>``;
rotation vectors are axis * angle in radians; depth is mm along the camera z axis in
the OpenCV camera frame (x right, y down, z forward).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError

__all__ = [
    "backproject",
    "invert_transform",
    "make_transform",
    "matrix_from_rotvec",
    "rotation_about",
    "rotation_angle_deg",
    "rotvec_from_matrix",
    "transform_points",
]


def rotation_angle_deg(R: NDArray) -> float:
    """Angle in degrees, in [0, 180], of a 3x3 rotation or of a 4x4 transform's rotation."""
    M = np.asarray(R, dtype=np.float64)[:3, :3]
    c = (float(np.trace(M)) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def rotvec_from_matrix(R: NDArray) -> NDArray[np.float64]:
    """Rotation vector (3,) of a 3x3 rotation, accurate at any angle up to 180 deg
    (the quaternion route; the arccos of the trace loses 1e-6 rad twists)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)[:3, :3]).as_rotvec()


def matrix_from_rotvec(rvec: NDArray) -> NDArray[np.float64]:
    """Rotation matrices from rotation vectors (Rodrigues): (3,) -> (3, 3), (N, 3) -> (N, 3, 3).
    Series expansions below 1e-8 rad keep tiny rotations exact."""
    r = np.asarray(rvec, dtype=np.float64)
    single = r.ndim == 1
    r = r.reshape(-1, 3)
    theta2 = np.einsum("ij,ij->i", r, r)
    theta = np.sqrt(theta2)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = np.zeros((r.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -r[:, 2], r[:, 1]
    K[:, 1, 0], K[:, 1, 2] = r[:, 2], -r[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -r[:, 1], r[:, 0]
    out = np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)
    return out[0] if single else out


def rotation_about(axis: Sequence[float] | NDArray, angle_rad: float) -> NDArray[np.float64]:
    """3x3 rotation by ``angle_rad`` about ``axis`` (any non-zero length)."""
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(a))
    if not n > 0:
        raise InputError("rotation_about: the axis must be non-zero")
    a = a / n
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * K @ K


def make_transform(R: NDArray | None = None, t: Sequence[float] | NDArray | None = None) -> NDArray[np.float64]:
    """4x4 transform from a 3x3 rotation (default identity) and a translation (default 0)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_transform(T: NDArray) -> NDArray[np.float64]:
    """Inverse of a rigid 4x4 transform (transpose of the rotation; exact, no solve)."""
    M = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


def transform_points(T: NDArray, points: NDArray) -> NDArray[np.float64]:
    """Apply a 4x4 transform to ``(..., 3)`` points."""
    M = np.asarray(T, dtype=np.float64)
    P = np.asarray(points, dtype=np.float64)
    return P @ M[:3, :3].T + M[:3, 3]


def backproject(depth_mm: NDArray, fx: float, fy: float, cx: float, cy: float) -> NDArray[np.float64]:
    """Organised pinhole points ``(H, W, 3)`` float64 mm in the camera frame from a depth
    map ``(H, W)`` mm along z; NaN depth gives NaN points."""
    z = np.asarray(depth_mm, dtype=np.float64)
    if z.ndim != 2:
        raise InputError(f"depth_mm: expected a 2-D map, got shape {z.shape}")
    h, w = z.shape
    pts = np.empty((h, w, 3), dtype=np.float64)
    pts[..., 0] = (np.arange(w, dtype=np.float64)[None, :] - cx) * z / fx
    pts[..., 1] = (np.arange(h, dtype=np.float64)[:, None] - cy) * z / fy
    pts[..., 2] = z
    return pts
