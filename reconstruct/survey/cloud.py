"""The survey's point cloud at the matching's full density.

Every matched pixel of the dense pairs' depth maps, back-projected into the local ENU
frame and coloured from its frame, rather than one point per DSM cell. Two rules keep it a
cloud a GIS user can trust:

- **One pair per cell.** Each DSM cell takes its points from the pair that measured it with
  the smallest expected height noise (``sigma_z``), so overlapping pairs do not stack two or
  three copies of the same surface, and no global de-duplication is needed: memory grows
  with the points kept, not with the pairs.
- **Agreement with the fused surface.** A point is kept when its height lies within that
  pair's fusion tolerance (3 sigma_z + cell / 2) of the DSM's lowest / highest height in its
  3 x 3 cells, which removes the mismatches the fusion voted out but keeps roof edges.

``--cloud-spacing`` thins to one point per cube of that side. The point count is estimated
from the depth maps before any point is made; above :data:`MAX_CLOUD_POINTS` the spacing
is raised to fit, and a warning says so. Method and figures: docs/uav.md "Point cloud".
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.reconstruct.survey.inputs import load_frame
from prism3d.reconstruct.survey.model import FusedSurface, PairResult

__all__ = ["MAX_CLOUD_POINTS", "DenseCloud", "cells_of", "dense_cloud", "pair_owners"]

log = logging.getLogger(__name__)

#: Most points a survey's cloud holds (about 100 bytes each while it is written: ENU and
#: map coordinates, colour, class, LAS buffers); a larger cloud is thinned to fit.
MAX_CLOUD_POINTS = 25_000_000


@dataclass(frozen=True)
class DenseCloud:
    """Points (N, 3) in the local ENU frame (m), colours (N, 3) uint8, the thinning
    ``spacing`` applied (m; None: every matched pixel), where the points came from
    (``source``: "matched pixels" or "dsm cells") and how many pairs gave points."""

    xyz: NDArray[np.float64]
    rgb: NDArray[np.uint8]
    spacing: float | None
    source: str
    pairs_used: int


def pair_owners(fused: FusedSurface, pairs: Sequence[PairResult]) -> NDArray[np.int32]:
    """Per DSM cell, the index in ``pairs`` of the ok pair with the smallest ``sigma_z``
    whose tile holds a height there (-1: none)."""
    H, W = fused.dsm.shape
    owner = np.full((H, W), -1, dtype=np.int32)
    best = np.full((H, W), np.inf, dtype=np.float64)
    for k, r in enumerate(pairs):
        t = r.tile
        if not r.ok or t is None or r.depth is None:
            continue
        r0 = int(round((fused.north - float(t.north)) / fused.cell))
        c0 = int(round((float(t.west) - fused.west) / fused.cell))
        h, w = t.dsm.shape
        s0, s1, e0, e1 = max(r0, 0), min(r0 + h, H), max(c0, 0), min(c0 + w, W)
        if s0 >= s1 or e0 >= e1:
            continue
        has = np.isfinite(t.dsm[s0 - r0:s1 - r0, e0 - c0:e1 - c0])
        sig = float(r.sigma_z) if r.sigma_z is not None else fused.cell
        better = has & (sig < best[s0:s1, e0:e1])
        best[s0:s1, e0:e1][better] = sig
        owner[s0:s1, e0:e1][better] = k
    return owner


def cells_of(fused: FusedSurface, P: NDArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The DSM row and column of ENU points (n, 3), unclipped."""
    return (np.floor((fused.north - P[:, 1]) / fused.cell).astype(np.int64),
            np.floor((P[:, 0] - fused.west) / fused.cell).astype(np.int64))


def _envelope(dsm: NDArray) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The lowest and highest fused height over each cell's 3 x 3 neighbours (NaN: none)."""
    fin = np.isfinite(dsm)
    k = np.ones((3, 3), np.uint8)
    lo = cv2.erode(np.where(fin, dsm, np.inf).astype(np.float32), k, borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(np.where(fin, dsm, -np.inf).astype(np.float32), k, borderType=cv2.BORDER_REPLICATE)
    ok = np.isfinite(lo) & np.isfinite(hi)
    return np.where(ok, lo, np.nan).astype(np.float32), np.where(ok, hi, np.nan).astype(np.float32)


def _pair_points(r: PairResult, T: NDArray, fused: FusedSurface, owner: NDArray, k: int,
                 lo: NDArray, hi: NDArray) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
    """Pair ``k``'s matched pixels in ENU that fall in cells it owns and agree with the fused
    surface: points (n, 3) and their pixel rows and columns in its depth map."""
    Z = np.asarray(r.depth, dtype=np.float64)
    v, u = np.nonzero(np.isfinite(Z))
    z = Z[v, u]
    Ks = np.asarray(r.K_depth, dtype=np.float64)
    Xc = np.c_[(u - Ks[0, 2]) / Ks[0, 0] * z, (v - Ks[1, 2]) / Ks[1, 1] * z, z]
    P = Xc @ T[:3, :3].T + T[:3, 3]
    H, W = fused.dsm.shape
    row, col = cells_of(fused, P)
    inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
    P, v, u, row, col = P[inside], v[inside], u[inside], row[inside], col[inside]
    tol = 3.0 * float(r.sigma_z if r.sigma_z is not None else fused.cell) + 0.5 * fused.cell
    a, b = lo[row, col], hi[row, col]
    keep = (owner[row, col] == k) & np.isfinite(a) & (P[:, 2] >= a - tol) & (P[:, 2] <= b + tol)
    return P[keep], v[keep], u[keep]


def _thin(P: NDArray, rgb: NDArray, spacing: float, origin: NDArray) -> tuple[NDArray, NDArray]:
    """One point per ``spacing`` cube (the first in each), cubes counted from ``origin``."""
    q = np.floor((P - origin) / spacing).astype(np.int64)
    _, first = np.unique(q, axis=0, return_index=True)
    first.sort()
    return P[first], rgb[first]


def _estimate(pairs: Sequence[PairResult], owner: NDArray, fused: FusedSurface) -> float:
    """Points the cloud will hold: each used pair's matched pixels times the share of its
    tile's cells it owns."""
    n = 0.0
    owned_cells = np.bincount(owner[owner >= 0].ravel(), minlength=len(pairs))
    for k, r in enumerate(pairs):
        if not r.ok or r.depth is None or r.tile is None:
            continue
        owned = int(owned_cells[k])
        cells = max(1, int(np.isfinite(r.tile.dsm).sum()))
        n += float(np.isfinite(r.depth).sum()) * min(1.0, owned / cells)
    return n


def dense_cloud(pairs: Sequence[PairResult], T_enu: dict[int, NDArray], paths: Sequence[str], K: NDArray,
                dist: NDArray, factor: int, fused: FusedSurface, *, spacing: float | None = None,
                max_points: int = MAX_CLOUD_POINTS,
                progress: Callable[[int, int, str], None] | None = None) -> DenseCloud:
    """The survey's cloud at the matching's density (module docstring); one point per filled
    DSM cell when no pair kept its depth map."""
    owner = pair_owners(fused, pairs)
    used = sorted({int(k) for k in np.unique(owner) if k >= 0}, key=lambda k: (pairs[k].i, k))
    if not used:
        rr, cc = np.nonzero(np.isfinite(fused.dsm))
        xyz = np.c_[fused.west + (cc + 0.5) * fused.cell, fused.north - (rr + 0.5) * fused.cell, fused.dsm[rr, cc]]
        return DenseCloud(xyz.astype(np.float64), fused.rgb[rr, cc], None, "dsm cells", 0)
    est = _estimate(pairs, owner, fused)
    if est > max_points:
        # thinning to cubes of side s keeps about (pixel footprint / s)^2 of a flat surface's points
        pix = float(np.median([pairs[k].depth_median or 1.0 for k in used])) * factor / float(K[0, 0])
        needed = pix * math.sqrt(est / max_points) * 1.05
        log.warning("cloud: about %.3g points at full density is over the %.3g budget; thinned to one per %.3g m"
                    " (--cloud-spacing)", est, max_points, needed)
        spacing = max(spacing or 0.0, needed)
    lo, hi = _envelope(fused.dsm)
    origin = np.array([fused.west, fused.north - fused.dsm.shape[0] * fused.cell, float(np.nanmin(lo)) - 1.0])
    pts, cols = [], []
    img_i, cached = None, None
    for n, k in enumerate(used):
        r = pairs[k]
        P, v, u = _pair_points(r, T_enu[r.i], fused, owner, k, lo, hi)
        if cached != r.i:
            img_i, _ = load_frame(str(paths[r.i]), K, dist, factor)
            cached = r.i
        c = img_i[np.clip(v, 0, img_i.shape[0] - 1), np.clip(u, 0, img_i.shape[1] - 1)]
        if spacing:
            P, c = _thin(P, c, float(spacing), origin)
        pts.append(P)
        cols.append(c)
        if progress:
            progress(n + 1, len(used), "cloud")
    xyz = np.concatenate(pts) if pts else np.zeros((0, 3))
    rgb = np.concatenate(cols).astype(np.uint8) if cols else np.zeros((0, 3), np.uint8)
    return DenseCloud(xyz, rgb, None if not spacing else float(spacing), "matched pixels", len(used))
