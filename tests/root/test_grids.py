"""Grid helpers against brute force: per-cell order statistics and nearest valid cells."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.grids import cell_quantile, nearest_valid


@pytest.mark.parametrize("q, of_count", [(0.5, False), (0.1, True), (0.0, False), (1.0, False), (0.9, True)])
def test_cell_quantile_is_the_sorted_value_at_its_rank(q, of_count):
    rng = np.random.default_rng(3)
    n_cells = 50
    cells = rng.integers(0, n_cells - 5, 4000)  # the last cells stay empty
    values = rng.normal(size=4000).round(2)  # ties within a cell too
    got = cell_quantile(values, cells, n_cells, q, empty=-99.0, of_count=of_count)
    for k in range(n_cells):
        v = np.sort(values[cells == k])
        if not len(v):
            assert got[k] == -99.0
            continue
        rank = int(q * len(v)) if of_count else int(np.floor(q * (len(v) - 1) + 0.5))
        assert got[k] == v[min(rank, len(v) - 1)]


def test_cell_quantile_of_nothing_and_the_median():
    assert np.isnan(cell_quantile([], [], 3, 0.5)).all()
    assert cell_quantile([5.0, 1.0, 3.0], [0, 0, 0], 1, 0.5)[0] == 3.0


def test_nearest_valid_points_at_the_closest_good_cell():
    bad = np.ones((7, 9), bool)
    bad[1, 1] = bad[5, 7] = False
    dist, (ri, ci) = nearest_valid(bad)
    for r in range(7):
        for c in range(9):
            d1, d2 = np.hypot(r - 1, c - 1), np.hypot(r - 5, c - 7)
            assert dist[r, c] == pytest.approx(min(d1, d2))
            if abs(d1 - d2) > 1e-9:
                assert (ri[r, c], ci[r, c]) == ((1, 1) if d1 < d2 else (5, 7))
