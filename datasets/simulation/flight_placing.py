"""Placing objects on a simulated site without overlap: each object's footprint on the
ground (ENU m), kept clear of those placed before and of the roads.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.simulation.flight_ground import Land, Road

__all__ = ["Placer", "corners_enu"]


class Placer:
    """Places footprints on open ground: clear of roads and of each other (ENU m)."""

    def __init__(self, rng: np.random.Generator, land: Land, roads: tuple[Road, ...]) -> None:
        self.rng, self.land, self.roads = rng, land, roads
        self.taken = np.zeros((0, 3))  # (x, y, radius) of the placed footprints

    def place(self, mesh: SceneMesh, zone: tuple[float, float, float, float], *, spacing: float, tries: int,
              tilt: bool, accept: Callable[[NDArray], bool] | None = None) -> NDArray[np.float64] | None:
        """``T_world_obj`` (mm) of a free spot in ``zone`` (x0, x1, y0, y1), or None."""
        lo, hi = mesh.bounds / 1000.0
        rad = float(np.hypot(*(hi[:2] - lo[:2])) / 2.0)
        for _ in range(tries):
            x, y = self.rng.uniform(zone[0], zone[1]), self.rng.uniform(zone[2], zone[3])
            tk = self.taken
            if np.any(np.hypot(tk[:, 0] - x, tk[:, 1] - y) < spacing * (tk[:, 2] + rad)):
                continue
            if any(float(rd.offset(x, y)) < rd.width / 2.0 + rad + 1.0 for rd in self.roads):
                continue
            T = self._stand(lo, hi, x, y, math.radians(self.rng.uniform(0.0, 360.0)), tilt)
            if accept is not None and not accept(T):
                continue
            self.taken = np.vstack([self.taken, [x, y, rad]])
            T[:3, 3] *= 1000.0
            return T
        return None

    def clear(self, x: float, y: float, rad: float, spacing: float) -> bool:
        """Whether a footprint of radius ``rad`` (m) at (x, y) keeps ``spacing`` from those
        placed and 1 m beyond the roads' edges."""
        tk = self.taken
        if np.any(np.hypot(tk[:, 0] - x, tk[:, 1] - y) < spacing * (tk[:, 2] + rad)):
            return False
        return all(float(rd.offset(x, y)) >= rd.width / 2.0 + rad + 1.0 for rd in self.roads)

    def put(self, mesh: SceneMesh, x: float, y: float, angle_rad: float, *, tilt: bool) -> NDArray[np.float64]:
        """``T_world_obj`` (mm) of ``mesh`` stood at (x, y) turned by ``angle_rad``, marked taken."""
        lo, hi = mesh.bounds / 1000.0
        T = self._stand(lo, hi, x, y, angle_rad, tilt)
        self.taken = np.vstack([self.taken, [x, y, float(np.hypot(*(hi[:2] - lo[:2])) / 2.0)]])
        T[:3, 3] *= 1000.0
        return T

    def _stand(self, lo: NDArray, hi: NDArray, x: float, y: float, a: float, tilt: bool) -> NDArray[np.float64]:
        """The pose (m) at (x, y), turned by ``a`` (rad, from east), its base below the ground
        at 5 x 5 footprint points and touching it at one; tilted to the fitted slope."""
        u, v = np.meshgrid(np.linspace(lo[0], hi[0], 5), np.linspace(lo[1], hi[1], 5))
        fp = np.stack([u.ravel(), v.ravel(), np.full(u.size, lo[2])], axis=1)
        R = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        if tilt:
            w = fp[:, :2] @ R[:2, :2].T
            g = self.land.height_at(x + w[:, 0], y + w[:, 1])
            (ga, gb, _), *_ = np.linalg.lstsq(np.c_[w, np.ones(len(w))], g, rcond=None)
            n = np.array([-ga, -gb, 1.0]) / math.sqrt(ga * ga + gb * gb + 1.0)
            k = np.cross([0.0, 0.0, 1.0], n)
            K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
            R = (np.eye(3) + K + K @ K / (1.0 + n[2])) @ R
        P = fp @ R.T
        g = self.land.height_at(x + P[:, 0], y + P[:, 1])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = (x, y, float(np.min(g - P[:, 2])) - 0.03)
        return T


def corners_enu(mesh: SceneMesh, T_mm: NDArray) -> NDArray[np.float64]:
    lo, hi = mesh.bounds
    c = np.array([[a, b, z] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return (c @ T_mm[:3, :3].T + T_mm[:3, 3]) / 1000.0
