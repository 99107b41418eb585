"""The survey's dense cloud (reconstruct/survey/cloud.py) on synthetic pairs with exact
geometry: a nadir camera over a flat plane with one box standing on it."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from prism3d.io.images import write_image
from prism3d.reconstruct.survey.cloud import dense_cloud, pair_owners
from prism3d.reconstruct.survey.model import FusedSurface, PairResult, PairTile

F, W, H, ALT = 200.0, 120, 100, 20.0  # px, px, px, m: a pixel is 0.1 m on the ground
CELL = 0.2
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
BOX = (-1.0, 1.0, -1.0, 1.0, 2.0)  # x0 x1 y0 y1 (m, ENU) and height


def _surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0, x1, y0, y1, h = BOX
    return np.where((x >= x0) & (x < x1) & (y >= y0) & (y < y1), h, 0.0)


def _nadir(cx: float) -> np.ndarray:
    """A camera at (cx, 0, ALT) looking down (x right = east, y down = south)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1.0]])
    T[:3, 3] = [cx, 0.0, ALT]
    return T


def _pair(k: int, cx: float, sigma: float, fused: FusedSurface, noise: float = 0.0) -> PairResult:
    """Camera i's exact depth map over the scene, one outlier pixel, and the tile it covers."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x = cx + (u - K[0, 2]) / F * ALT  # first guess on the ground, then the box's top where it stands
    y = -(v - K[1, 2]) / F * ALT
    zs = _surface(x, y)
    depth = (ALT - zs) * (1.0 + noise * np.random.default_rng(k).standard_normal(zs.shape))
    x = cx + (u - K[0, 2]) / F * depth
    y = -(v - K[1, 2]) / F * depth
    depth[_surface(x, y) != zs] = np.nan  # the box's walls: no exact pixel, leave them out
    depth[50, 60] = ALT - 8.0  # a mismatch 8 m above the ground
    r = PairResult(k, k + 1, status="ok", sigma_z=sigma, depth_median=ALT)
    r.depth, r.K_depth = depth.astype(np.float32), K
    r.tile = PairTile(fused.west, fused.north, CELL, np.where(np.isfinite(fused.dsm), fused.dsm, np.nan),
                      np.ones(fused.dsm.shape, np.int32), fused.rgb)
    return r


@pytest.fixture()
def scene(tmp_path):
    west, north, n = -6.0, 5.0, 50
    cc, rr = np.meshgrid(np.arange(n + 20), np.arange(n))  # wider than every frame
    dsm = _surface(west + (cc + 0.5) * CELL, north - (rr + 0.5) * CELL).astype(np.float32)
    fused = FusedSurface(dsm, np.zeros(dsm.shape + (3,), np.uint8), np.ones(dsm.shape, np.uint8),
                         np.ones(dsm.shape, np.uint8), west, north, CELL)
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = np.arange(W, dtype=np.uint8)[None, :]  # red = column: colours show the pixel taken
    paths = []
    for k in range(3):
        p = tmp_path / f"f{k}.png"
        write_image(p, img)
        paths.append(str(p))
    T = {0: _nadir(0.0), 1: _nadir(0.5), 2: _nadir(1.0)}
    return fused, paths, T


def test_each_cell_from_its_best_pair_and_on_the_surface(scene) -> None:
    fused, paths, T = scene
    pairs = [_pair(0, 0.0, 0.05, fused), _pair(1, 0.5, 0.02, fused)]  # pair 1 measures finer
    owner = pair_owners(fused, pairs)
    assert set(np.unique(owner)) == {1}  # both cover every cell: the finer pair owns them all
    c = dense_cloud(pairs, T, paths, K, np.zeros(5), 1, fused)
    assert c.source == "matched pixels" and c.pairs_used == 1 and c.spacing is None
    # every pixel of pair 1 on the grid but the outlier, on the true surface (exact depths)
    assert len(c.xyz) == int(np.isfinite(pairs[1].depth).sum()) - 1
    np.testing.assert_allclose(c.xyz[:, 2], _surface(c.xyz[:, 0], c.xyz[:, 1]), atol=1e-6)
    assert c.xyz[:, 2].max() <= BOX[4] + 1e-6  # the mismatch 8 m up is gone
    # colours from frame i at each point's own pixel: red = column
    col = np.round((c.xyz[:, 0] - 0.5) / ALT * F + K[0, 2]).astype(int)
    on_ground = c.xyz[:, 2] == 0
    np.testing.assert_array_equal(c.rgb[on_ground, 0], col[on_ground])


def test_thinning_and_budget(scene, caplog) -> None:
    fused, paths, T = scene
    pairs = [_pair(0, 0.0, 0.05, fused, noise=1e-4)]
    full = dense_cloud(pairs, T, paths, K, np.zeros(5), 1, fused)
    thin = dense_cloud(pairs, T, paths, K, np.zeros(5), 1, fused, spacing=0.3)
    q = np.floor((thin.xyz - thin.xyz.min(axis=0)) / 0.3).astype(int)
    assert thin.spacing == 0.3 and len(thin.xyz) < len(full.xyz) / 4
    assert len(np.unique(q, axis=0)) >= 0.9 * len(q)  # about one point per cube
    with caplog.at_level(logging.WARNING):
        capped = dense_cloud(pairs, T, paths, K, np.zeros(5), 1, fused, max_points=2000)
    assert len(capped.xyz) <= 2000 and capped.spacing is not None
    assert "budget" in caplog.text


def test_without_depth_maps_one_point_per_cell(scene) -> None:
    fused, paths, T = scene
    r = PairResult(0, 1, status="ok", sigma_z=0.05)
    c = dense_cloud([r], T, paths, K, np.zeros(5), 1, fused)
    assert c.source == "dsm cells" and len(c.xyz) == int(np.isfinite(fused.dsm).sum())
