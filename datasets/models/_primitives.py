"""Closed mesh primitives the built-in targets are made of (private).

All parts are closed, consistently outward-oriented triangle meshes in millimetres:
lofted cross-sections, extruded polygons, tapers, boxes, cylinders and wheels, plus
mirror/rotate helpers. See :mod:`prism3d.datasets.models.targets` for the frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "SEGMENTS", "Part", "both_sides", "box", "cylinder", "ellipse", "embed", "hull_plan", "loft",
    "mirror_y", "oriented", "prism", "rotate_x", "taper", "wheel",
]

Part = tuple[NDArray[np.float64], NDArray[np.int64]]

SEGMENTS = 20  # facets around a cylinder / wheel

# ---------------------------------------------------------------------------------
# Closed primitives (all at full scale, millimetres; geometry given in metres * 1000)
# ---------------------------------------------------------------------------------


def oriented(vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> Part:
    """Flip a closed, consistently wound part so its normals point outward."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    signed_volume = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    if signed_volume < 0:
        faces = faces[:, ::-1]
    return vertices, np.ascontiguousarray(faces, dtype=np.int64)


def loft(
    rings: Sequence[NDArray[np.float64]],
    *,
    start_apex: Sequence[float] | None = None,
    end_apex: Sequence[float] | None = None,
) -> Part:
    """Closed surface through cross-section rings, capped at both ends.

    Each ring is ``(K, 3)`` (same K, same cyclic order, star-shaped about its
    centroid). The ends are closed by a fan to the ring centroid (a flat cap) or to
    ``start_apex`` / ``end_apex`` (a cone tip).
    """
    rs = [np.asarray(r, dtype=np.float64) for r in rings]
    k = len(rs[0])
    m = len(rs)
    idx = np.arange(k)
    nxt = (idx + 1) % k
    faces = []
    for r in range(m - 1):
        a = r * k + idx
        b = r * k + nxt
        c = (r + 1) * k + nxt
        d = (r + 1) * k + idx
        faces.append(np.stack([a, b, c], axis=1))
        faces.append(np.stack([a, c, d], axis=1))
    start = rs[0].mean(axis=0) if start_apex is None else np.asarray(start_apex, dtype=np.float64)
    end = rs[-1].mean(axis=0) if end_apex is None else np.asarray(end_apex, dtype=np.float64)
    s_i = m * k
    faces.append(np.stack([np.full(k, s_i), nxt, idx], axis=1))
    last = (m - 1) * k
    faces.append(np.stack([np.full(k, s_i + 1), last + idx, last + nxt], axis=1))
    vertices = np.vstack(rs + [start[None], end[None]])
    return oriented(vertices, np.concatenate(faces))


def embed(poly: Sequence[Sequence[float]], axis: int, value: float) -> NDArray[np.float64]:
    """2-D polygon in the plane ``coord[axis] = value`` (other axes in x, y, z order)."""
    p = np.asarray(poly, dtype=np.float64) * 1000.0
    out = np.empty((len(p), 3))
    others = [i for i in range(3) if i != axis]
    out[:, others[0]] = p[:, 0]
    out[:, others[1]] = p[:, 1]
    out[:, axis] = value * 1000.0
    return out


def prism(poly: Sequence[Sequence[float]], axis: int, lo: float, hi: float) -> Part:
    """Polygon (metres; coordinates of the other two axes in x, y, z order) extruded
    along ``axis`` from ``lo`` to ``hi`` metres."""
    return loft([embed(poly, axis, lo), embed(poly, axis, hi)])


def taper(
    poly_lo: Sequence[Sequence[float]],
    poly_hi: Sequence[Sequence[float]],
    axis: int,
    lo: float,
    hi: float,
) -> Part:
    """Loft between two polygons with the same vertex count at ``lo`` and ``hi``."""
    return loft([embed(poly_lo, axis, lo), embed(poly_hi, axis, hi)])


def box(lo: Sequence[float], hi: Sequence[float]) -> Part:
    """Axis-aligned box between corners ``lo`` and ``hi`` (metres)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    return prism([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], 2, z0, z1)


def ellipse(
    center: Sequence[float], axis: int, r1: float, r2: float, n: int = SEGMENTS
) -> NDArray[np.float64]:
    """Ring of ``n`` points on an ellipse perpendicular to ``axis`` (metres in, mm out);
    ``r1``, ``r2`` are the semi-axes along the other two axes in x, y, z order."""
    t = 2.0 * np.pi * np.arange(n) / n
    c = np.asarray(center, dtype=np.float64)
    others = [i for i in range(3) if i != axis]
    ring = np.tile(c, (n, 1))
    ring[:, others[0]] += r1 * np.cos(t)
    ring[:, others[1]] += r2 * np.sin(t)
    return ring * 1000.0


def cylinder(
    p0: Sequence[float], p1: Sequence[float], r0: float, r1: float | None = None, n: int = SEGMENTS
) -> Part:
    """Cylinder or cone frustum from ``p0`` to ``p1`` (metres), radii ``r0``, ``r1``;
    ``r1 = 0`` gives a cone with its apex at ``p1``."""
    a = np.asarray(p0, dtype=np.float64)
    b = np.asarray(p1, dtype=np.float64)
    d = (b - a) / np.linalg.norm(b - a)
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    t = 2.0 * np.pi * np.arange(n) / n
    circle = np.cos(t)[:, None] * u + np.sin(t)[:, None] * v
    r1 = r0 if r1 is None else r1
    ring0 = (a + r0 * circle) * 1000.0
    if r1 == 0:
        return loft([ring0], end_apex=b * 1000.0)
    return loft([ring0, (b + r1 * circle) * 1000.0])


def wheel(x: float, y_in: float, y_out: float, radius: float, n: int = SEGMENTS) -> Part:
    """Wheel (cylinder along y) touching the ground, centre at ``x``."""
    return cylinder((x, y_in, radius), (x, y_out, radius), radius, n=n)


def rotate_x(part: Part, angle_rad: float, pivot: Sequence[float]) -> Part:
    """Rotate a part about the x axis through ``pivot`` (metres)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    p = np.asarray(pivot, dtype=np.float64) * 1000.0
    return (part[0] - p) @ R.T + p, part[1]


def mirror_y(part: Part) -> Part:
    """Mirror a part across the x-z plane (keeps outward orientation)."""
    v = part[0] * np.array([1.0, -1.0, 1.0])
    return v, np.ascontiguousarray(part[1][:, ::-1])


def both_sides(part: Part) -> list[Part]:
    return [part, mirror_y(part)]


def hull_plan(
    length: float,
    beam: float,
    x_bow: float,
    stern_frac: float,
    x_center: float = 0.0,
    n_bow: int = 8,
) -> list[tuple[float, float]]:
    """Ship plan polygon (x, y), counter-clockwise from above: transom stern of width
    ``stern_frac * beam``, parallel sides, elliptic bow from ``x_bow`` to the tip."""
    half = beam / 2.0
    x0 = x_center - length / 2.0
    x1 = x_center + length / 2.0
    pts = [(x0, -half * stern_frac), (x_bow, -half)]
    for i in range(1, n_bow):
        t = 0.5 * np.pi * i / n_bow
        pts.append((x_bow + (x1 - x_bow) * np.sin(t), -half * np.cos(t)))
    pts.append((x1, 0.0))
    pts += [(x, -y) for x, y in reversed(pts[1:-1])]
    pts.append((x0, half * stern_frac))
    return pts
