"""The ground a simulated flight sees: gravel roads, a smooth height field, land cover and its
albedo (grass, soil, paving), as the renderer's surfaces ask for them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.capture.scenes import value_noise
from prism3d.datasets.simulation.carpark import Lot, lot_albedo
from prism3d.datasets.simulation.field import (
    GroundAlbedo,
    Terrain,
)

__all__ = ["ROAD_WIDTH_M", "HeightField", "Land", "Road", "SurveyGroundAlbedo", "on_road"]

#: Width of the gravel roads, m.
ROAD_WIDTH_M = 6.0


@dataclass(frozen=True)
class Road:
    """A straight road: a point on its centre line and its direction (ENU m), its width."""

    x0: float
    y0: float
    ux: float
    uy: float
    width: float = ROAD_WIDTH_M

    def offset(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Distance from the centre line, m."""
        return np.abs((np.asarray(x) - self.x0) * self.uy - (np.asarray(y) - self.y0) * self.ux)

    def foot(self, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        s = (np.asarray(x) - self.x0) * self.ux + (np.asarray(y) - self.y0) * self.uy
        return self.x0 + s * self.ux, self.y0 + s * self.uy


def on_road(roads: tuple[Road, ...], x: NDArray, y: NDArray) -> NDArray[np.bool_]:
    on = np.zeros(np.shape(x), dtype=bool)
    for rd in roads:
        on |= rd.offset(x, y) <= rd.width / 2.0
    return on


@dataclass(frozen=True)
class HeightField:
    """The hills (plane waves, m) levelled across each road and its 3.5 m shoulders, and
    flat on each car park (``lots``, blended over 4 m)."""

    hills: Terrain
    roads: tuple[Road, ...]
    lots: tuple[Lot, ...] = ()

    def __call__(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        h = self.hills.height(x, y)
        for rd in self.roads:
            fx, fy = rd.foot(x, y)
            s = np.clip((rd.offset(x, y) - rd.width / 2.0 - 0.5) / 3.5, 0.0, 1.0)
            w = 1.0 - s * s * (3.0 - 2.0 * s)
            h = h + w * (self.hills.height(fx, fy) - h)
        for lot in self.lots:
            h = h + lot.level_weight(x, y) * (lot.z - h)
        return h


@dataclass(frozen=True, eq=False)
class Land:
    """The terrain mesh: heights ``z`` (ny, nx) m at ``x0 + i d``, ``y0 + j d``; two
    triangles a square, split along the (i, j)-(i+1, j+1) diagonal."""

    x0: float
    y0: float
    d: float
    z: NDArray[np.float64]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        ny, nx = self.z.shape
        return self.x0, self.x0 + (nx - 1) * self.d, self.y0, self.y0 + (ny - 1) * self.d

    def height_at(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """The mesh's height (exactly its piecewise-linear surface) at ENU points, m."""
        ny, nx = self.z.shape
        u = (np.asarray(x, dtype=np.float64) - self.x0) / self.d
        v = (np.asarray(y, dtype=np.float64) - self.y0) / self.d
        i = np.clip(np.floor(u).astype(np.int64), 0, nx - 2)
        j = np.clip(np.floor(v).astype(np.int64), 0, ny - 2)
        fu, fv = u - i, v - j
        z = self.z
        h00, h10, h01, h11 = z[j, i], z[j, i + 1], z[j + 1, i], z[j + 1, i + 1]
        lower = fu >= fv  # triangle (i, j), (i+1, j), (i+1, j+1)
        return np.where(lower, h00 + fu * (h10 - h00) + fv * (h11 - h10),
                        h00 + fv * (h01 - h00) + fu * (h11 - h01))

    def mesh(self, albedo: Any) -> SceneMesh:
        ny, nx = self.z.shape
        xs = self.x0 + self.d * np.arange(nx)
        ys = self.y0 + self.d * np.arange(ny)
        X, Y = np.meshgrid(xs, ys)
        V = np.stack([X.ravel(), Y.ravel(), self.z.ravel()], axis=1) * 1000.0
        i = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
        F = np.concatenate([np.stack([i, i + 1, i + nx + 1], 1), np.stack([i, i + nx + 1, i + nx], 1)])
        return SceneMesh(V, F, None, albedo, "ground", {"material": "lambertian"})


@dataclass(frozen=True)
class SurveyGroundAlbedo:
    """The field scenes' grass and soil with every noise cell ``scale`` times larger (no
    texture finer than the camera resolves) and gravel roads painted on (mm in)."""

    seed: int
    scale: float
    roads: tuple[Road, ...]
    lots: tuple[Lot, ...] = ()

    def __call__(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = GroundAlbedo(self.seed, math.inf)(p / self.scale)
        for lot in self.lots:
            on, paved = lot_albedo(lot, p, self.scale)
            out[on] = paved[on]
        x, y = p[:, 0] / 1000.0, p[:, 1] / 1000.0
        edge = np.full(len(p), np.inf)
        for rd in self.roads:
            edge = np.minimum(edge, rd.offset(x, y) - rd.width / 2.0)
        road = np.flatnonzero(edge < 0.6)
        if len(road):
            q = p[road]
            n = 0.6 * value_noise(q, 250.0 * self.scale, self.seed + 11) \
                + 0.4 * value_noise(q, 90.0 * self.scale, self.seed + 12)
            gravel = np.array([0.36, 0.34, 0.31])[None, :] * (0.7 + 0.6 * n)[:, None]
            t = np.clip((0.6 - edge[road]) / 0.6, 0.0, 1.0)[:, None]  # a soft verge
            out[road] = (1.0 - t) * out[road] + t * gravel
        return np.clip(out, 0.0, 1.0)
