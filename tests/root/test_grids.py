"""Grid helpers against brute force: per-cell order statistics, nearest valid cells, voxel means."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.grids import cell_quantile, nearest_valid, voxel_mean


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


def _brute_voxel_mean(p: np.ndarray, voxel: float, origin: np.ndarray) -> dict[tuple[int, ...], np.ndarray]:
    cells: dict[tuple[int, ...], list[np.ndarray]] = {}
    for q in p:
        cells.setdefault(tuple(np.floor((q - origin) / voxel).astype(int)), []).append(q)
    return {k: np.mean(v, axis=0) for k, v in cells.items()}


def test_voxel_mean_averages_each_cell_and_maps_every_point() -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(0, 1.0, (3000, 3))
    col = rng.random((3000, 2))
    m, (cm,), inv = voxel_mean(p, 0.5, col)
    truth = _brute_voxel_mean(p, 0.5, p.min(axis=0) - 0.25)
    assert len(m) == len(truth)
    got = {tuple(np.floor((q - (p.min(axis=0) - 0.25)) / 0.5).astype(int)): q for q in m}
    for k, q in truth.items():
        np.testing.assert_allclose(got[k], q, atol=1e-12)
    np.testing.assert_allclose(m[inv], np.array([truth[tuple(np.floor((q - (p.min(axis=0) - 0.25)) / 0.5)
                                                             .astype(int))] for q in p]), atol=1e-12)
    for c in range(len(m)):  # the column averaged over the same points
        np.testing.assert_allclose(cm[c], col[inv == c].mean(axis=0), atol=1e-12)


def test_voxel_mean_is_open3d_voxel_down_sample() -> None:
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(4)
    p = rng.random((20000, 3)) * [50.0, 20.0, 5.0]
    col = rng.random((20000, 3))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    pc.colors = o3d.utility.Vector3dVector(col)
    down = pc.voxel_down_sample(0.7)
    m, (cm,), _ = voxel_mean(p, 0.7, col)
    a, b = np.asarray(down.points), np.asarray(down.colors)
    ia, ib = np.lexsort(a.T), np.lexsort(m.T)
    np.testing.assert_allclose(m[ib], a[ia], atol=1e-12)
    np.testing.assert_allclose(cm[ib], b[ia], atol=1e-12)


def test_voxel_mean_with_more_cells_than_one_key_holds_and_empty_input() -> None:
    rng = np.random.default_rng(5)
    p = rng.random((500, 3)) * 1e7  # 1e7 / 1e-6 = 1e13 cells an axis: no int64 key
    m, (c,), inv = voxel_mean(p, 1e-6, p[:, :1])
    assert len(m) == 500 and np.array_equal(np.sort(inv), np.arange(500))
    np.testing.assert_allclose(m[inv], p)
    m, (c,), inv = voxel_mean(np.zeros((0, 3)), 1.0, np.zeros((0, 2)))
    assert m.shape == (0, 3) and c.shape == (0, 2) and inv.shape == (0,)


def test_voxel_mean_refuses_what_it_cannot_index() -> None:
    p = np.random.default_rng(6).random((10, 3))
    with pytest.raises(InputError, match="voxel"):
        voxel_mean(p, 0.0)
    with pytest.raises(InputError, match="origin"):
        voxel_mean(p, 0.1, origin=np.full(3, 0.5))  # points below the origin
    q = p.copy()
    q[3, 1] = np.nan
    with pytest.raises(InputError, match="finite"):
        voxel_mean(q, 0.1)
