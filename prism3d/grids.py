"""Grid helpers shared by the scene detector's ground, the survey's DSM and the
decamouflage: an order statistic per cell of scattered values, and holes filled from the
nearest valid cell. One implementation each, so a fix reaches every pipeline."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

__all__ = ["cell_quantile", "nearest_valid"]


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
