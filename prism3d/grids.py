"""Grid helpers shared by the scene detector's ground, the survey's DSM, the decamouflage
and the scans' fusion: an order statistic per cell of scattered values, holes filled from
the nearest valid cell, and the mean of points per cubic voxel. One implementation each,
so a fix reaches every pipeline."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from prism3d._grid_kernels import bounds, cell_keys, cell_means, sorted_cells
from prism3d.checks import check_positive
from prism3d.errors import InputError

__all__ = ["cell_quantile", "nearest_valid", "voxel_mean"]


def cell_quantile(values: NDArray, cells: NDArray, n_cells: int, q: float, *, empty: float = np.nan,
                  of_count: bool = False) -> NDArray[np.float64]:
    """Per cell (``cells``: each value's cell index in ``[0, n_cells)``), the value at
    quantile ``q`` (0-1) of its values sorted: rank ``round(q (n - 1))`` (the median at
    0.5), or ``floor(q n)`` with ``of_count`` (a low quantile that skips the lowest value
    of every ten: stray low points stay out of the ground). Cells without a value hold
    ``empty``."""
    v = np.asarray(values, dtype=np.float64).ravel()
    c = np.asarray(cells, dtype=np.int64).ravel()
    out = np.full(int(n_cells), empty, dtype=np.float64)
    if not len(v):
        return out
    order = np.lexsort((v, c))  # by cell, then value
    v, c = v[order], c[order]
    first = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    counts = np.diff(np.r_[first, len(c)])
    if of_count:
        rank = (counts * q).astype(np.int64)
    else:
        rank = np.minimum((counts - 1) * q + 0.5, counts - 1).astype(np.int64)
    out[c[first]] = v[first + np.minimum(rank, counts - 1)]
    return out


def nearest_valid(bad: NDArray[np.bool_]) -> tuple[NDArray[np.float64], tuple[NDArray[np.intp], NDArray[np.intp]]]:
    """For every cell of a 2-D grid, the distance (cells) to the nearest cell not ``bad``
    and that cell's row and column indices (Euclidean distance transform)."""
    dist, (ri, ci) = ndimage.distance_transform_edt(np.asarray(bad, dtype=bool), return_indices=True)
    return dist, (ri, ci)


def voxel_mean(points: NDArray, voxel: float, *columns: NDArray | None,
               origin: NDArray | None = None) -> tuple[NDArray[np.float64], list[NDArray[np.float64] | None],
                                                       NDArray[np.intp]]:
    """Points ``(N, 3)`` averaged per cubic ``voxel`` (cells ``floor((p - origin) / voxel)``;
    ``origin`` by default half a voxel below the points' minimum, Open3D's
    ``voxel_down_sample`` grid): the means ``(M, 3)`` in cell order, each of ``columns``
    (``(N, k)`` or None) averaged alike, and each point's cell index ``(N,)`` into the
    means. A sort and one pass of sums in place of Open3D's hash map: 3-5x faster on a
    fused scan of 2 M points. A given ``origin`` must lie at or below every point."""
    check_positive(voxel, "voxel")
    p = np.ascontiguousarray(points, dtype=np.float64)
    if len(p) == 0:
        return np.zeros((0, 3)), [None if c is None else np.zeros((0, np.shape(c)[1])) for c in columns], \
            np.zeros(0, dtype=np.intp)
    lo, hi = bounds(p)
    o = lo - 0.5 * voxel if origin is None else np.asarray(origin, dtype=np.float64)
    if not np.isfinite(p).all() or (lo < o).any():
        raise InputError("voxel_mean: the points must be finite and at or above the origin")
    dims = np.floor((hi - o) / voxel).astype(np.int64) + 1  # floor is monotonic: the largest index
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2.0**62:  # one int64 key a cell
        key = cell_keys(p, o, float(voxel), dims)
        inverse, m = sorted_cells(key, np.argsort(key, kind="stable"))
    else:  # too many cells for one key: sorted by the three indices
        ijk = np.floor((p - o) / voxel).astype(np.int64)
        _, inverse = np.unique(ijk, axis=0, return_inverse=True)
        inverse, m = inverse.ravel().astype(np.intp), int(inverse.max()) + 1
    means = [None if c is None else cell_means(inverse, m, np.ascontiguousarray(np.asarray(c, dtype=np.float64)
                                                                                 .reshape(len(p), -1)))
             for c in (p, *columns)]
    return means[0], means[1:], inverse
