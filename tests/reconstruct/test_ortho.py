"""The true orthophoto: a synthetic scene photographed from two known poses, mosaicked
through its DSM: every covered cell coloured, holes filled and marked, each cell from the
most direct frame, colours where the ground truth puts them."""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from prism3d.capture.rig import CameraModel
from prism3d.errors import InputError
from prism3d.reconstruct.survey.ortho import fill_dsm, photo_gsd, true_orthophoto


def _ground_colour(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A checkerboard of 2 m squares painted on the ground (RGB uint8)."""
    k = (np.floor(x / 2.0) + np.floor(y / 2.0)).astype(np.int64) % 2
    return np.where(k[..., None] == 1, np.array([220, 40, 40]), np.array([30, 160, 60])).astype(np.uint8)


def _photo(T_enu_cam: np.ndarray, cam: CameraModel) -> np.ndarray:
    """A nadir photograph of flat ground at z = 0."""
    w, h = cam.size
    uv = np.stack(np.meshgrid(np.arange(w), np.arange(h)), axis=-1).reshape(-1, 2).astype(np.float64)
    rays = cam.pixel_rays(uv) @ T_enu_cam[:3, :3].T
    t = -T_enu_cam[2, 3] / rays[:, 2]
    p = T_enu_cam[:3, 3] + rays * t[:, None]
    return _ground_colour(p[:, 0], p[:, 1]).reshape(h, w, 3)


def test_orthophoto_of_flat_ground(tmp_path) -> None:
    K = np.array([[400.0, 0, 199.5], [0, 400.0, 149.5], [0, 0, 1]])
    cam = CameraModel(K, np.zeros(5), (400, 300))
    frames = []
    for k, x in enumerate((-5.0, 5.0)):
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down, image up = north
        T[:3, 3] = (x, 0.0, 40.0)
        p = tmp_path / f"f{k}.png"
        cv2.imwrite(str(p), _photo(T, cam)[..., ::-1])
        frames.append((str(p), T))
    cell = 0.5
    dsm = np.zeros((60, 80), np.float32)
    dsm[20:30, 30:45] = np.nan  # a hole inside the coverage: filled and marked
    west, north = -20.0, 15.0
    ortho = true_orthophoto(dsm, west, north, cell, frames, K, np.zeros(5), (400, 300))
    assert ortho.gsd == pytest.approx(photo_gsd([T for _, T in frames], 400.0, 0.0)) == pytest.approx(0.1)
    H, W = ortho.rgba.shape[:2]
    assert (H, W) == (300, 400)
    covered = ortho.quality > 0
    assert covered.mean() > 0.9 and (ortho.rgba[..., 3][covered] == 255).all()
    hole = np.zeros((H, W), bool)
    hole[100:150, 150:225] = True
    assert (ortho.quality[hole] == 2).all() and (ortho.quality[covered & ~hole] == 1).mean() > 0.99
    X, Y = np.meshgrid(west + (np.arange(W) + 0.5) * ortho.gsd, north - (np.arange(H) + 0.5) * ortho.gsd)
    want = _ground_colour(X, Y)
    edge = (np.abs(np.mod(X, 2.0) - 1.0) > 0.8) | (np.abs(np.mod(Y, 2.0) - 1.0) > 0.8)
    ok = covered & ~edge
    assert (np.abs(ortho.rgba[..., :3].astype(int) - want)[ok].max(axis=1) < 40).mean() > 0.99
    # the west half from the west frame, the east half from the east one
    assert set(ortho.cells_per_frame) == {0, 1}


def test_fill_dsm_and_bad_input() -> None:
    d = np.full((20, 20), 5.0, np.float32)
    d[8:12, 8:12] = np.nan
    filled, cov = fill_dsm(d)
    assert cov.all() and np.allclose(filled, 5.0, atol=1e-4)
    with pytest.raises(InputError, match="no height"):
        fill_dsm(np.full((5, 5), np.nan))
    with pytest.raises(InputError, match="no camera"):
        photo_gsd([np.eye(4)], 100.0, 10.0)
