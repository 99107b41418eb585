"""Surfaces on a map grid: a DSM (and its orthophoto) from a cloud of points in a local
metric frame (z up), and the ground under it (a progressive morphological filter), so
the normalised DSM (height above the ground) shows what stands on it. Rows run north
to south: row 0 is the grid's north edge, as GeoTIFFs store it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.grids import cell_quantile, nearest_valid

__all__ = ["DsmGrid", "grid_points", "normalised_dsm", "progressive_ground"]


@dataclass(frozen=True)
class DsmGrid:
    """``dsm`` (H, W) float32 height per cell (NaN: no point), ``ortho`` (H, W, 4) uint8
    RGBA (alpha 0 where empty), ``count`` points per cell, the north-west corner
    (``west``, ``north``) and the cell size ``gsd`` (the points' units)."""

    dsm: NDArray[np.float32]
    ortho: NDArray[np.uint8]
    count: NDArray[np.int32]
    west: float
    north: float
    gsd: float


#: Cells a DSM may have (a budget checked before allocating).
MAX_CELLS = 200_000_000


def grid_points(xyz: NDArray, rgb: NDArray | None, gsd: float, *, bounds: tuple[float, float, float, float] | None = None,
                percentile: float = 50.0) -> DsmGrid:
    """Grid points (n, 3), x east, y north, z up, into cells of ``gsd``: each cell's
    ``percentile`` of its heights (the median by default: robust to stray matches) and
    the mean colour of its points; ``bounds`` (west, south, east, north) or the points'
    extent."""
    p = check_array(xyz, "points", ndim=2).astype(np.float64)
    if p.shape[1] != 3:
        raise InputError(f"points: expected (n, 3), got {p.shape}")
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) == 0:
        raise InputError("points: none finite; nothing to grid")
    if not (np.isfinite(gsd) and gsd > 0):
        raise InputError(f"gsd: expected a cell size > 0, got {gsd}")
    if not 0 <= percentile <= 100:
        raise InputError(f"percentile: expected 0-100, got {percentile}")
    w, s, e, n = bounds if bounds is not None else (p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max())
    W = int(np.floor((e - w) / gsd)) + 1
    H = int(np.floor((n - s) / gsd)) + 1
    if W * H > MAX_CELLS:
        raise InputError(f"DSM: {W} x {H} cells at {gsd:g} per cell is over the {MAX_CELLS:,} budget; "
                         "give a larger cell")
    col = np.floor((p[:, 0] - w) / gsd).astype(np.int64)
    row = np.floor((n - p[:, 1]) / gsd).astype(np.int64)
    ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    col, row, z = col[ok], row[ok], p[ok, 2]
    cell = row * W + col
    dsm = cell_quantile(z, cell, H * W, percentile / 100.0).astype(np.float32)
    cnt = np.bincount(cell, minlength=H * W).astype(np.int32)
    ortho = np.zeros((H * W, 4), dtype=np.uint8)
    if rgb is not None:
        c = check_array(rgb, "colours", ndim=2)
        if c.shape[0] != len(ok) or c.shape[1] < 3:
            raise InputError(f"colours: expected ({len(ok)}, 3), got {c.shape}")
        c = np.asarray(c, dtype=np.float64)[np.isfinite(np.asarray(xyz, dtype=np.float64)).all(axis=1)][ok][:, :3]
        for k in range(3):
            sums = np.bincount(cell, weights=c[:, k], minlength=H * W)
            ortho[:, k] = np.clip(np.round(sums / np.maximum(cnt, 1)), 0, 255)
    ortho[:, 3] = np.where(cnt > 0, 255, 0)
    return DsmGrid(dsm.reshape(H, W), ortho.reshape(H, W, 4), cnt.reshape(H, W), float(w), float(n), float(gsd))


def normalised_dsm(dsm: NDArray, gsd_mm: float, *, fill: str = "inpaint") -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The ground under a DSM (heights in mm, cells of ``gsd_mm``; NaN cells filled from
    their nearest neighbour for the filter, NaN again after) by :func:`progressive_ground`,
    and the normalised DSM: height above that ground. Returns ``(ground, ndsm)``."""
    d = check_array(dsm, "DSM", ndim=2).astype(np.float64)
    g = progressive_ground(d, gsd_mm, fill=fill)
    g = np.where(np.isfinite(d), g, np.nan)
    return g.astype(np.float32), (d - g).astype(np.float32)


#: Progressive morphological ground filter (Zhang et al. 2003): window sides and the
#: terrain slope and base tolerance allowed between a cell and the opened surface (mm).
_PMF_WINDOWS_MM = (4000.0, 8000.0, 16000.0, 32000.0)
_PMF_SLOPE = 0.15
_PMF_BASE_MM = 300.0
#: Width of the objects' stereo fringe left out of the ground carried under them (mm).
_INPAINT_FRINGE_MM = 500.0


def progressive_ground(grid: NDArray, cell_mm: float, *, fill: str = "opened") -> NDArray[np.float64]:
    """The ground under a grid of low heights: openings with growing windows flag cells
    that stand above the opened surface by more than the slope allows (objects up to the
    largest window wide); flagged cells take the opened surface (``fill="opened"``), or
    the ground around them carried in (``"inpaint"``: on a slope the opened surface lies
    below the ground by the slope times half the window, and objects on it grow by as
    much); then a light smoothing."""
    from scipy import ndimage

    g = np.array(grid, dtype=np.float64)
    bad = ~np.isfinite(g)
    if bad.all():
        return np.zeros_like(g)
    if bad.any():
        _, (ri, ci) = nearest_valid(bad)
        g = g[ri, ci]
    obj = np.zeros(g.shape, dtype=bool)
    surf = g.copy()
    for w_mm in _PMF_WINDOWS_MM:
        w = max(1, int(round(w_mm / cell_mm)))
        opened = ndimage.grey_opening(surf, size=(w, w), mode="nearest")
        obj |= (g - opened) > _PMF_BASE_MM + _PMF_SLOPE * w_mm
        surf = opened
    if fill == "inpaint" and obj.any() and not obj.all():
        import cv2

        # the hole takes the objects' fringe too: stereo rounds their edges off over about
        # half a metre, and a fringe left in the ring would lift the ground carried in
        hole = ndimage.binary_dilation(obj, iterations=max(1, int(round(_INPAINT_FRINGE_MM / cell_mm))))
        base = np.where(hole, surf, g)
        off = float(np.median(base))
        ground = cv2.inpaint((base - off).astype(np.float32), hole.astype(np.uint8), 3, cv2.INPAINT_TELEA)
        ground = ground.astype(np.float64) + off
    elif fill in ("opened", "inpaint"):
        ground = np.where(obj, surf, g)
    else:
        raise InputError(f"fill: expected 'opened' or 'inpaint', got {fill!r}")
    return ndimage.gaussian_filter(ground, 1.0, mode="nearest")
