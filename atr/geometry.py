"""Geometry helpers shared by ATR modules: point maps and normals from a depth map,
up-axis handling, gravity-aligned and minimum oriented boxes.

Conventions: millimetres, OpenCV camera frame (x right, y down, z forward), pixel
(0, 0) = centre of the top-left pixel, depth float32 mm along z with NaN = no surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from prism3d.capture.rig import CameraModel

from prism3d.checks import check_array, check_choice
from prism3d.errors import InputError

__all__ = [
    "UP_AXES",
    "GravityBox",
    "as_camera",
    "depth_to_points",
    "gravity_box",
    "min_oriented_box",
    "normals_from_depth",
    "surface_axis",
    "up_rotation",
]

#: Accepted up-axis names (a leading "-" means the negative axis points up).
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


def as_camera(K_or_camera: NDArray | CameraModel, size: tuple[int, int]) -> CameraModel:
    """A :class:`CameraModel` from a camera or a ``(3, 3)`` ``K`` (no distortion),
    checked against the depth map's ``(width, height)``.
    """
    if isinstance(K_or_camera, CameraModel):
        if tuple(K_or_camera.size) != tuple(size):
            raise InputError(
                f"camera: its image size {K_or_camera.size[0]}x{K_or_camera.size[1]} differs "
                f"from the depth map's {size[0]}x{size[1]}"
            )
        return K_or_camera
    K = check_array(K_or_camera, "K", shape=(3, 3), dtype_kind="fiu")
    return CameraModel(K, np.zeros(5), size)


def depth_to_points(depth_mm: NDArray, K_or_camera: NDArray | CameraModel) -> NDArray[np.float64]:
    """Back-project ``(H, W)`` depth (mm along z, NaN = none) to ``(H, W, 3)`` float64
    camera-frame points (mm, NaN where depth is); a CameraModel's distortion is inverted exactly.
    """
    d = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="fiu").astype(np.float64)
    h, w = d.shape
    cam = as_camera(K_or_camera, (w, h))
    if cam.has_distortion or cam.skew != 0:
        rays = cam.pixel_grid_rays()
        with np.errstate(divide="ignore", invalid="ignore"):
            rays = rays / rays[..., 2:3]
    else:
        u = (np.arange(w, dtype=np.float64) - cam.cx) / cam.fx
        v = (np.arange(h, dtype=np.float64) - cam.cy) / cam.fy
        rays = np.empty((h, w, 3))
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        rays[..., 2] = 1.0
    return rays * d[..., None]


def _shift(a: NDArray, k: int, axis: int) -> NDArray:
    """``out[i] = a[i + k]`` along ``axis`` (NaN outside)."""
    out = np.full_like(a, np.nan)
    n = a.shape[axis]
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    if k >= 0:
        src[axis] = slice(k, n)
        dst[axis] = slice(0, n - k)
    else:
        src[axis] = slice(0, n + k)
        dst[axis] = slice(-k, n)
    out[tuple(dst)] = a[tuple(src)]
    return out


def _tangent(P: NDArray, axis: int) -> NDArray:
    """One-sided tangent along ``axis`` taken on the side where the surface continues
    most linearly (smallest second difference), so that it does not cross creases or
    depth discontinuities; falls back to the smaller depth step near borders."""
    fwd = _shift(P, 1, axis) - P
    bwd = P - _shift(P, -1, axis)
    fwd2 = _shift(P, 2, axis) - _shift(P, 1, axis)
    bwd2 = _shift(P, -1, axis) - _shift(P, -2, axis)
    cf = np.linalg.norm(fwd2 - fwd, axis=-1)
    cb = np.linalg.norm(bwd - bwd2, axis=-1)
    # without a second neighbour, judge by the depth step
    cf = np.where(np.isnan(cf), np.abs(fwd[..., 2]) + 1e6, cf)
    cb = np.where(np.isnan(cb), np.abs(bwd[..., 2]) + 1e6, cb)
    use_b = np.isnan(cf) | (cb < cf)
    return np.where(use_b[..., None], bwd, fwd)


def normals_from_depth(
    depth_mm: NDArray,
    K_or_camera: NDArray | CameraModel,
    *,
    max_step_ratio: float = 0.05,
) -> NDArray[np.float32]:
    """Unit camera-frame normals ``(H, W, 3)`` float32 of a depth map (mm, NaN = none).

    Tangents are one-sided differences of the point map on the side where the surface
    continues most linearly (no smearing across creases); a depth step over
    ``max_step_ratio * depth`` on both sides is a discontinuity (NaN). Normals face the
    camera; no smoothing (smooth noisy depth first).
    """
    P = depth_to_points(depth_mm, K_or_camera)
    du = _tangent(P, 1)
    dv = _tangent(P, 0)
    z = P[..., 2]
    with np.errstate(invalid="ignore"):
        bad = (np.abs(du[..., 2]) > max_step_ratio * z) | (np.abs(dv[..., 2]) > max_step_ratio * z)
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
        flip = np.sum(n * P, axis=-1) > 0
    n[flip] *= -1.0
    n[bad | ~np.isfinite(z)] = np.nan
    return n.astype(np.float32)


def up_rotation(up: str) -> NDArray[np.float64]:
    """Rotation ``R`` with ``R @ p`` expressing points in a frame whose +z is ``up``.

    ``up`` is one of :data:`UP_AXES`. The result is a proper rotation (det +1), so
    handedness is kept: ``"y"`` maps (x, y, z) to (x, -z, y)... e.g. a Y-up model
    (glTF convention) becomes Z-up with its forward axis unchanged in x.
    """
    check_choice(up, "up", UP_AXES)
    sign = -1.0 if up.startswith("-") else 1.0
    axis = up[-1]
    if axis == "z":
        R = np.eye(3)
    elif axis == "y":
        R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # y -> z
    else:
        R = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # x -> z
    if sign < 0:
        R = np.diag([1.0, -1.0, -1.0]) @ R  # turn upside down about x
    return R


@dataclass(frozen=True)
class GravityBox:
    """Gravity-aligned box: ``length_mm`` >= ``width_mm`` (footprint sides),
    ``height_mm``; ``axes`` (3, 3) rows length, width, up; ``center`` (3,) mm.
    """

    length_mm: float
    width_mm: float
    height_mm: float
    axes: NDArray[np.float64]
    center: NDArray[np.float64]


def _min_area_rect(xy: NDArray[np.float64]) -> tuple[float, float, NDArray[np.float64], NDArray[np.float64]]:
    """Minimum-area enclosing rectangle of 2-D points by rotating calipers over the
    convex hull edges. Returns ``(side_a, side_b, unit_dir_a, centre)``."""
    from scipy.spatial import ConvexHull, QhullError

    pts = np.unique(xy, axis=0)
    if len(pts) < 3:
        hull = pts
    else:
        try:
            hull = pts[ConvexHull(pts).vertices]
        except QhullError:  # collinear footprint
            hull = pts
    if len(hull) < 2:
        return 0.0, 0.0, np.array([1.0, 0.0]), hull.mean(axis=0)
    edges = np.roll(hull, -1, axis=0) - hull
    ang = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    best = None
    for a in ang:
        c, s = np.cos(a), np.sin(a)
        e1 = np.array([c, s])
        e2 = np.array([-s, c])
        p1 = hull @ e1
        p2 = hull @ e2
        area = (p1.max() - p1.min()) * (p2.max() - p2.min())
        if best is None or area < best[0] - 1e-9 * max(area, 1e-12):
            best = (area, e1, e2, p1, p2)
    _, e1, e2, p1, p2 = best
    a_len, b_len = p1.max() - p1.min(), p2.max() - p2.min()
    centre = e1 * (p1.max() + p1.min()) / 2 + e2 * (p2.max() + p2.min()) / 2
    if b_len > a_len:
        return float(b_len), float(a_len), e2, centre
    return float(a_len), float(b_len), e1, centre


def _pca_axis(xy: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Unit major principal axis of 2-D points, or None when the spread is isotropic."""
    c = xy - xy.mean(axis=0)
    cov = c.T @ c / max(len(c), 1)
    ev, vec = np.linalg.eigh(cov)
    if ev[1] <= 0 or ev[0] / ev[1] > 0.98:
        return None
    return vec[:, 1]


def surface_axis(vertices_zup: NDArray, faces: NDArray) -> NDArray[np.float64] | None:
    """Major horizontal principal axis of a triangle surface (exact, area-weighted
    second moments of the triangles' horizontal coordinates), or None if isotropic.

    Exact integrals keep mirror-symmetric targets exactly aligned with their
    symmetry plane (sampling would tilt the axis by noise).
    """
    V = np.asarray(vertices_zup, dtype=np.float64)[:, :2]
    F = np.asarray(faces, dtype=np.int64)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    V3 = np.asarray(vertices_zup, dtype=np.float64)
    area = 0.5 * np.linalg.norm(np.cross(V3[F[:, 1]] - V3[F[:, 0]], V3[F[:, 2]] - V3[F[:, 0]]), axis=1)
    tot = area.sum()
    if tot <= 0:
        return None
    s = a + b + c
    mean = (area[:, None] * s / 3.0).sum(axis=0) / tot
    # integral of x x^T over a triangle = A/12 (sum v v^T + s s^T)
    M = np.einsum("n,ni,nj->ij", area / 12.0, s, s)
    for v in (a, b, c):
        M += np.einsum("n,ni,nj->ij", area / 12.0, v, v)
    cov = M / tot - np.outer(mean, mean)
    ev, vec = np.linalg.eigh(cov)
    if ev[1] <= 0 or ev[0] / ev[1] > 0.98:
        return None
    return vec[:, 1]


def _refine_axis(xy: NDArray[np.float64], e1: NDArray[np.float64], window_deg: float = 5.0) -> NDArray[np.float64]:
    """Among the principal axis and the convex-hull edge directions within
    ``window_deg`` of it (modulo 90 deg), the one of minimum footprint area: snaps
    the box to the straight sides of boxy, slightly asymmetric targets."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        return e1
    a0 = np.arctan2(e1[1], e1[0])
    edges = np.roll(hull, -1, axis=0) - hull
    ang = np.arctan2(edges[:, 1], edges[:, 0])
    diff = np.mod(ang - a0 + np.pi / 4, np.pi / 2) - np.pi / 4
    cands = np.concatenate([[0.0], diff[np.abs(diff) <= np.radians(window_deg)]])
    best, best_area = 0.0, np.inf
    for dlt in cands:
        c, s_ = np.cos(a0 + dlt), np.sin(a0 + dlt)
        p1 = hull @ np.array([c, s_])
        p2 = hull @ np.array([-s_, c])
        area = (p1.max() - p1.min()) * (p2.max() - p2.min())
        if area < best_area * (1 - 1e-9):
            best, best_area = dlt, area
    return np.array([np.cos(a0 + best), np.sin(a0 + best)])


def gravity_box(
    points_zup: NDArray,
    *,
    axis_points: NDArray | None = None,
    axis: NDArray | None = None,
) -> GravityBox:
    """Gravity-aligned box of ``(N, 3)`` points (mm, +z up).

    Horizontal axes: ``axis`` if given, else the principal axes of ``axis_points``
    (default the points), else the minimum-area footprint rectangle when that spread is
    isotropic; invariant to rotations about the vertical. ``length`` is the longer side.
    """
    p = check_array(points_zup, "points", shape=(None, 3), dtype_kind="fiu", min_size=3)
    p = p[np.all(np.isfinite(p), axis=1)].astype(np.float64)
    if len(p) == 0:
        raise InputError("points: no finite point")
    ap = p if axis_points is None else np.asarray(axis_points, dtype=np.float64)
    e1 = _pca_axis(ap[:, :2]) if axis is None else np.asarray(axis, dtype=np.float64)[:2]
    if e1 is not None:
        e1 = _refine_axis(p[:, :2], e1)
    if e1 is None:
        L, W, e1, c2 = _min_area_rect(p[:, :2])
    else:
        e2 = np.array([-e1[1], e1[0]])
        p1, p2 = p[:, :2] @ e1, p[:, :2] @ e2
        L, W = float(p1.max() - p1.min()), float(p2.max() - p2.min())
        c2 = e1 * (p1.max() + p1.min()) / 2 + e2 * (p2.max() + p2.min()) / 2
        if W > L:
            L, W, e1 = W, L, e2
    axes = np.array([[e1[0], e1[1], 0.0], [-e1[1], e1[0], 0.0], [0.0, 0.0, 1.0]])
    z0, z1 = float(p[:, 2].min()), float(p[:, 2].max())
    return GravityBox(L, W, z1 - z0, axes, np.array([c2[0], c2[1], (z0 + z1) / 2]))


def min_oriented_box(points: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Minimum-volume oriented box of ``(N, 3)`` points (trimesh; PCA axes for planar input).

    Returns ``extents`` (3,) mm in decreasing order and ``T_box_points`` (4, 4), points'
    frame -> the centred box frame.
    """
    import trimesh

    p = check_array(points, "points", shape=(None, 3), dtype_kind="fiu", min_size=3).astype(np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 4:
        raise InputError(f"points: need at least 4 finite points for an oriented box, got {len(p)}")
    try:
        T, ext = trimesh.bounds.oriented_bounds(p)
    except Exception:  # noqa: BLE001  (qhull fails on planar input): fall back to PCA axes
        c = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - c, full_matrices=False)
        q = (p - c) @ vt.T
        ext = q.max(axis=0) - q.min(axis=0)
        T = np.eye(4)
        T[:3, :3] = vt
        T[:3, 3] = -vt @ c
    return np.sort(np.asarray(ext, dtype=np.float64))[::-1], np.asarray(T, dtype=np.float64)
