"""The survey's rasters on a map grid (UTM or another projected CRS) from its local ENU grid.

The survey measures and fuses in its local east-north-up frame; its products lie on a
grid of the map CRS (:class:`~prism3d.geo.MapFrame`): square cells whose corners are
multiples of the cell size (grids of two surveys at one cell size line up), covering the
ENU grid. The map grid is turned a little against the ENU grid (the meridian
convergence, up to a few degrees off a zone's central meridian) and scaled (UTM's 0.9996
and more), so every map cell's centre is taken back to ENU and the ENU raster sampled
there. The exact conversion (PROJ) is made on a lattice every :data:`LATTICE` cells and
interpolated bilinearly between (the map is smooth: well under a millimetre off over a
lattice step of hundreds of metres), as GDAL's approximate transformer does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from prism3d.errors import InputError
from prism3d.geo import MapFrame

__all__ = ["Grid", "GridWarp", "map_grid", "resample"]

#: Map cells between two exact conversions of the lattice.
LATTICE = 32
#: Rows of a raster resampled at once.
BAND_ROWS = 1024


@dataclass(frozen=True)
class Grid:
    """A north-up grid: ``west``, ``north`` its outer corner, square cells of ``cell``
    (m), ``shape`` (rows, columns); cell (r, c) is centred at ``west + (c + .5) cell``,
    ``north - (r + .5) cell``."""

    west: float
    north: float
    cell: float
    shape: tuple[int, int]


def map_grid(frame: MapFrame, enu: Grid, cell: float, z: float, *, max_cells: int) -> Grid:
    """The map grid of ``cell`` covering ``enu`` (points at ENU height ``z``), its corners on
    multiples of ``cell``; more than ``max_cells`` cells is a one-line error."""
    H, W = enu.shape
    t = np.linspace(0.0, 1.0, 65)
    xs = enu.west + np.r_[t * W, np.full_like(t, W), t * W, np.zeros_like(t)] * enu.cell
    ys = enu.north - np.r_[np.zeros_like(t), t * H, np.full_like(t, H), t * H] * enu.cell
    q = frame.enu_to_map(np.c_[xs, ys, np.full_like(xs, z)])
    west = math.floor(q[:, 0].min() / cell) * cell
    north = math.ceil(q[:, 1].max() / cell) * cell
    Wm = int(math.ceil((q[:, 0].max() - west) / cell))
    Hm = int(math.ceil((north - q[:, 1].min()) / cell))
    if Wm * Hm > max_cells:
        raise InputError(f"map grid: {Wm} x {Hm} cells of {cell:g} m, more than {max_cells:,}; give a larger cell")
    return Grid(float(west), float(north), float(cell), (max(1, Hm), max(1, Wm)))


class GridWarp:
    """ENU coordinates of a map grid's cell centres, and the ellipsoidal height of ENU
    ``up`` there (module docstring): ``enu_xy(r0, r1, c0, c1)`` and ``height_offset``."""

    def __init__(self, frame: MapFrame, grid: Grid, z: float) -> None:
        self.grid = grid
        H, W = grid.shape
        self.rl = np.arange(0, H + LATTICE, LATTICE, dtype=np.float64)
        self.cl = np.arange(0, W + LATTICE, LATTICE, dtype=np.float64)
        C, R = np.meshgrid(self.cl, self.rl)
        x = grid.west + (C.ravel() + 0.5) * grid.cell
        y = grid.north - (R.ravel() + 0.5) * grid.cell
        e = frame.map_to_enu(np.c_[x, y, np.full(x.shape, z)])
        shape = (len(self.rl), len(self.cl))
        self._x, self._y = e[:, 0].reshape(shape), e[:, 1].reshape(shape)
        self._dh = (z - e[:, 2]).reshape(shape)  # h = up + dh at these cells

    def _interp(self, a: NDArray, r0: int, r1: int, c0: int, c1: int) -> NDArray[np.float64]:
        R, C = np.meshgrid(np.arange(r0, r1) / LATTICE, np.arange(c0, c1) / LATTICE, indexing="ij")
        return ndimage.map_coordinates(a, [R, C], order=1, mode="nearest")

    def enu_xy(self, r0: int, r1: int, c0: int, c1: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """ENU (x, y) of the centres of map cells ``[r0, r1) x [c0, c1)``."""
        return self._interp(self._x, r0, r1, c0, c1), self._interp(self._y, r0, r1, c0, c1)

    def height_offset(self, r0: int, r1: int, c0: int, c1: int) -> NDArray[np.float64]:
        """What to add to an ENU ``up`` at those cells to get the height above the ellipsoid."""
        return self._interp(self._dh, r0, r1, c0, c1)


def resample(src: NDArray, enu: Grid, warp: GridWarp, *, mode: str) -> NDArray[np.float32]:
    """A float raster on the ENU grid ``enu`` sampled at the map grid's cell centres:
    ``"nearest"``, or ``"linear"`` (bilinear over the finite ones of the four neighbours;
    NaN where the nearest cell is NaN, so the coverage is the nearest cell's). NaN outside."""
    if mode not in ("nearest", "linear"):
        raise InputError(f"resample: mode must be nearest or linear, got {mode!r}")
    a = np.asarray(src, dtype=np.float32)
    H, W = warp.grid.shape
    out = np.full((H, W), np.nan, dtype=np.float32)
    h, w = a.shape
    pad = np.pad(a, 1, constant_values=np.nan)
    for r0 in range(0, H, BAND_ROWS):
        r1 = min(H, r0 + BAND_ROWS)
        X, Y = warp.enu_xy(r0, r1, 0, W)
        fc = (X - enu.west) / enu.cell - 0.5
        fr = (enu.north - Y) / enu.cell - 0.5
        ni = np.clip(np.floor(fr + 0.5).astype(np.int64), -1, h) + 1
        nj = np.clip(np.floor(fc + 0.5).astype(np.int64), -1, w) + 1
        near = pad[ni, nj]
        if mode == "nearest":
            out[r0:r1] = near
            continue
        i0 = np.clip(np.floor(fr).astype(np.int64), -1, h) + 1
        j0 = np.clip(np.floor(fc).astype(np.int64), -1, w) + 1
        ty, tx = np.clip(fr - (i0 - 1), 0, 1), np.clip(fc - (j0 - 1), 0, 1)
        i1, j1 = np.minimum(i0 + 1, h + 1), np.minimum(j0 + 1, w + 1)
        num = np.zeros(X.shape)
        den = np.zeros(X.shape)
        for ii, jj, wt in ((i0, j0, (1 - ty) * (1 - tx)), (i0, j1, (1 - ty) * tx), (i1, j0, ty * (1 - tx)),
                           (i1, j1, ty * tx)):
            v = pad[ii, jj]
            ok = np.isfinite(v)
            num += np.where(ok, v, 0.0) * wt
            den += ok * wt
        with np.errstate(invalid="ignore", divide="ignore"):
            val = num / den
        out[r0:r1] = np.where(np.isfinite(near) & (den > 0), val, np.nan)
    return out
