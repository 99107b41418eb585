"""Chessboard corner detection: accuracy against rendered boards with known corners,
canonical ordering, detection reports and error branches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from prism3d.capture.rig import CameraModel, PrismSplit
from prism3d.reconstruct.stereo.corners import (
    board_object_points,
    canonical_order,
    detect_corners,
    detect_views,
    grid_symmetries,
    load_image,
    refine_xjunction,
    to_gray,
    to_gray_float,
)

from prism3d.errors import InputError


def render_board(
    cam: CameraModel,
    T_cam_board: np.ndarray,
    board: tuple[int, int] = (9, 6),
    square: float = 25.0,
    *,
    ss: int = 3,
    noise: float = 2.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Render a chessboard through ``cam`` (exact distortion, supersampled) and return
    the grey uint8 image and the true corner pixels in board_object_points order."""
    cols, rows = board
    cs = cam.scaled(ss)
    rays = cs.pixel_grid_rays().reshape(-1, 3)
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    n = R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t) / (rays @ n)
    P = rays * s[:, None]
    b = (P - t) @ R  # board coordinates
    bx, by = b[:, 0] / square, b[:, 1] / square
    inside = (bx >= -1) & (bx < cols) & (by >= -1) & (by < rows) & (s > 0)
    margin = (bx >= -2) & (bx < cols + 1) & (by >= -2) & (by < rows + 1) & (s > 0)
    val = np.full(bx.shape, 90.0)
    val[margin] = 230.0
    black = ((np.floor(bx) + np.floor(by)) % 2 == 0) & inside
    val[black] = 25.0
    w, h = cam.size
    img = val.reshape(h, ss, w, ss).mean(axis=(1, 3))
    rng = np.random.default_rng(seed)
    img = img + rng.normal(0.0, noise, img.shape)
    img = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    obj = board_object_points(board, square)
    truth = cam.project(obj @ R.T + t)
    return img, truth


def small_camera(
    w: int = 640, h: int = 480, f: float = 700.0, dist=(-0.1, 0.05, 0, 0, 0)
) -> CameraModel:
    K = np.array([[f, 0, (w - 1) / 2 + 3.0], [0, f, (h - 1) / 2 - 2.0], [0, 0, 1]])
    return CameraModel(K, np.array(dist, dtype=float), (w, h))


def board_pose(
    angles_deg=(20.0, -15.0, 5.0), dist_mm: float = 500.0, shift=(0.0, 0.0)
) -> np.ndarray:
    from prism3d.geometry import matrix_from_rotvec

    R = matrix_from_rotvec(np.radians(angles_deg))
    T = np.eye(4)
    T[:3, :3] = R
    centre = np.array([100.0, 62.5, 0.0])
    T[:3, 3] = np.array([shift[0], shift[1], dist_mm]) - R @ centre
    return T


@pytest.mark.parametrize(
    ("method", "rms", "worst"), [("xjunction", 0.03, 0.1), ("classic", 0.1, 0.3), ("sb", 0.1, 0.3)]
)
def test_detect_corners_accuracy_against_truth(method: str, rms: float, worst: float) -> None:
    cam = small_camera()
    img, truth = render_board(cam, board_pose())
    c = detect_corners(img, (9, 6), method=method)
    assert c is not None and c.shape == (54, 2)
    err = np.linalg.norm(c - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < rms
    assert err.max() < worst


@pytest.mark.parametrize(("method", "rms", "worst"), [("xjunction", 0.03, 0.1), ("classic", 0.1, 0.3),
                                                     ("sb", 0.1, 0.3)])
def test_a_large_view_is_searched_small_and_refined_at_full_size(monkeypatch, method, rms, worst) -> None:
    """Above DETECT_MAX_PIXELS the board is found in a reduced copy (here 0.1 MP, a
    scale of 0.57) and the corners refined at full resolution: the same accuracy as the
    direct search; the x-junction fit on the board's crop equals the whole-view fit."""
    import prism3d.reconstruct.stereo.corners as C

    cam = small_camera()
    img, truth = render_board(cam, board_pose())
    monkeypatch.setattr(C, "DETECT_MAX_PIXELS", 100_000)
    assert C._detection_copy(img)[1] < 0.6
    c = detect_corners(img, (9, 6), method=method)
    assert c is not None and c.shape == (54, 2)
    err = np.linalg.norm(c - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < rms and err.max() < worst
    whole = C._refine_xjunction_in(img, truth, (9, 6), crop=False)
    np.testing.assert_allclose(C._refine_xjunction_in(img, truth, (9, 6), crop=True), whole, atol=1e-9)


def test_refine_xjunction_beats_cornersubpix() -> None:
    """The X-junction fit on a strongly tilted, blurred, noisy board (float grey)."""
    import cv2

    cam = small_camera()
    img, truth = render_board(cam, board_pose((45.0, -30.0, 10.0), 520.0), noise=3.0, seed=2)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    classic = detect_corners(img, (9, 6), method="classic")
    assert classic is not None
    refined = refine_xjunction(to_gray_float(img), classic, (9, 6))
    e_classic = np.sqrt(np.mean(np.sum((classic - truth) ** 2, axis=1)))
    e_refined = np.sqrt(np.mean(np.sum((refined - truth) ** 2, axis=1)))
    assert e_refined < 0.6 * e_classic and e_refined < 0.05
    # a corner already at the truth stays there; a blank window keeps its input
    blank = np.full(img.shape, 128.0)
    np.testing.assert_array_equal(refine_xjunction(blank, classic, (9, 6)), classic)


def test_to_gray_float_keeps_precision() -> None:
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[0, 0] = (10, 20, 31)
    g = to_gray_float(rgb)
    assert g.dtype == np.float64 and g.shape == (2, 3)
    assert g[0, 0] == pytest.approx(0.299 * 10 + 0.587 * 20 + 0.114 * 31)
    np.testing.assert_allclose(to_gray_float(np.full((2, 2), 0.5, np.float32)), 127.5)
    assert to_gray_float(np.ones((2, 2, 1), np.uint8)).shape == (2, 2)
    with pytest.raises(InputError, match="channels"):
        to_gray_float(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(InputError, match="expected uint8 or float"):
        to_gray_float(np.zeros((4, 4), bool))
    with pytest.raises(InputError, match="expected 54 corners"):
        refine_xjunction(np.zeros((20, 20)), np.zeros((10, 2)), (9, 6))


def test_rotated_board_gets_canonical_order() -> None:
    cam = small_camera()
    # board rotated by 180 degrees in its plane: OpenCV's raw order is reversed
    img, truth = render_board(cam, board_pose((10.0, 10.0, 180.0)))
    c = detect_corners(img, (9, 6))
    assert c is not None
    # canonical: rows along +x, columns along +y, so corner 0 is the top-left one
    g = c.reshape(6, 9, 2)
    assert (g[:, -1, 0] > g[:, 0, 0]).all()
    assert (g[-1, :, 1] > g[0, :, 1]).all()
    # it is the truth read backwards (the physical board is upside down)
    np.testing.assert_allclose(c, truth[::-1], atol=0.3)


def test_canonical_order_is_invariant_to_symmetries() -> None:
    rng = np.random.default_rng(1)
    base = board_object_points((9, 6), 1.0)[:, :2] * 30 + 100 + rng.normal(0, 0.5, (54, 2))
    for board, pts in (((9, 6), base), ((7, 7), board_object_points((7, 7), 1.0)[:, :2] * 30 + 50)):
        ref = canonical_order(pts, board)
        np.testing.assert_array_equal(ref, pts)  # already canonical
        for p in grid_symmetries(board):
            np.testing.assert_array_equal(canonical_order(pts[p], board), ref)
    assert len(grid_symmetries((9, 6))) == 4
    assert len(grid_symmetries((7, 7))) == 8


def test_detect_views_shot_split_and_report(tmp_path: Path) -> None:
    import cv2

    cam = small_camera()
    left, _ = render_board(cam, board_pose(shift=(-10.0, 0.0)))
    right, _ = render_board(cam, board_pose(shift=(10.0, 0.0)), seed=1)
    blank = np.full_like(left, 128)
    split = PrismSplit.side_by_side((1280, 480))
    shot = split.join(left, right)
    path = tmp_path / "shot.png"
    cv2.imwrite(str(path), shot)
    dets, size = detect_views([path, split.join(left, blank)], board=(9, 6))
    assert size == (640, 480)
    (l0, r0), (l1, r1) = dets
    assert l0.found and r0.found and l1.found and not r1.found
    assert l0.source == str(path) and l0.view == "left" and r0.view == "right"
    assert l0.n_corners == 54 and r1.n_corners == 0 and r1.corners is None
    assert 0 < l0.sharpness < 5 and np.isnan(r1.sharpness)
    # pairs mode: the same views as separate arrays
    dets2, _ = detect_views([left, right], pairs=True)
    np.testing.assert_allclose(dets2[0][0].corners, l0.corners, atol=1e-3)
    assert dets2[0][1].source == "<array 1>"


def test_load_image_and_gray(tmp_path: Path) -> None:
    import cv2

    img = np.zeros((4, 6, 3), np.uint8)
    img[..., 0] = 255  # red in RGB
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), img[..., ::-1])
    back = load_image(p)
    np.testing.assert_array_equal(back, img)
    assert to_gray(back).shape == (4, 6)
    assert to_gray(np.ones((4, 6), np.float32)).max() == 255


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        load_image(tmp_path / "missing.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(InputError, match="not a readable image"):
        load_image(bad)
    with pytest.raises(InputError, match="board"):
        board_object_points((1, 6), 25.0)
    with pytest.raises(InputError, match="board"):
        detect_corners(np.zeros((10, 10), np.uint8), ("a", 3))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="method"):
        detect_corners(np.zeros((10, 10), np.uint8), (9, 6), method="magic")
    with pytest.raises(InputError, match="window"):
        detect_corners(np.zeros((10, 10), np.uint8), (9, 6), window=0)
    with pytest.raises(InputError, match="expected 54 corners"):
        canonical_order(np.zeros((10, 2)), (9, 6))
    with pytest.raises(InputError, match="expected uint8 or float"):
        to_gray(np.zeros((4, 4), np.int16))
    with pytest.raises(InputError, match="channels"):
        to_gray(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(InputError, match="at least one image"):
        detect_views([])
    with pytest.raises(InputError, match="odd count"):
        detect_views([np.zeros((8, 8), np.uint8)] * 3, pairs=True)
    with pytest.raises(InputError, match=r"differs from <array 0>"):
        detect_views([np.zeros((8, 8), np.uint8), np.zeros((8, 10), np.uint8)], pairs=True)
    with pytest.raises(InputError, match="odd"):
        detect_views([np.zeros((8, 9), np.uint8)])
    with pytest.raises(InputError, match="PrismSplit"):
        detect_views([np.zeros((8, 8), np.uint8)], split="halves")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"<array 0>: image: expected a 20x8"):
        detect_views([np.zeros((8, 8), np.uint8)], split=PrismSplit.side_by_side((20, 8)))
