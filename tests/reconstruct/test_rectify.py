"""Rectification maps: known-answer tests through the paper rig, shot splitting, the
folder writer and error branches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from prism3d.capture.rig import CameraModel, PrismSplit, StereoRig, compute_rectification, paper_rig
from prism3d.reconstruct.stereo.rectify import (
    rectify_maps,
    rectify_pair,
    rectify_shot,
    rectify_to_folder,
)

from prism3d.errors import InputError


def small_rig(skew: float = 0.0) -> StereoRig:
    """A 160x120-view version of the paper's geometry (fast maps)."""
    rig = paper_rig(focal_px=5107.0 / 10.8, sensor_size=(320, 120), working_distance_mm=1250.0)
    K = rig.left.K.copy()
    K[0, 1] = skew
    cam = CameraModel(K, rig.left.dist, rig.left.size)
    return StereoRig(cam, cam, rig.T_right_left, rig.split, rig.T_rig_left)


def _sample(map_x: np.ndarray, map_y: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of the maps at rectified pixels ``uv``."""
    import cv2

    mx = cv2.remap(
        map_x,
        uv[:, 0].astype(np.float32)[None],
        uv[:, 1].astype(np.float32)[None],
        cv2.INTER_LINEAR,
    )
    my = cv2.remap(
        map_y,
        uv[:, 0].astype(np.float32)[None],
        uv[:, 1].astype(np.float32)[None],
        cv2.INTER_LINEAR,
    )
    return np.stack([mx[0], my[0]], axis=1)


@pytest.mark.parametrize("skew", [0.0, 0.7])
def test_maps_send_rectified_pixels_to_the_true_source_pixels(skew: float) -> None:
    rig = small_rig(skew)
    rect = compute_rectification(rig)
    maps = rectify_maps(rig, rect)
    h, w = rect.size[1], rect.size[0]
    assert maps.left_x.shape == (h, w) and maps.left_x.dtype == np.float32
    # points on a plane 1250 mm away, in the left camera frame
    rng = np.random.default_rng(0)
    T_left_rig = np.linalg.inv(rig.T_rig_left)
    P_rig = np.c_[rng.uniform(-60, 60, 50), rng.uniform(-60, 60, 50), np.full(50, 1250.0)]
    X = P_rig @ T_left_rig[:3, :3].T + T_left_rig[:3, 3]
    Xr = X @ rect.R1.T
    ul = Xr @ rect.P1[:, :3].T
    ul = ul[:, :2] / ul[:, 2:]
    ur = np.c_[Xr, np.ones(50)] @ rect.P2.T
    ur = ur[:, :2] / ur[:, 2:]
    np.testing.assert_allclose(ul[:, 1], ur[:, 1], atol=1e-9)  # same row
    z = Xr[:, 2]
    np.testing.assert_allclose(ul[:, 0] - ur[:, 0], rect.focal_px * rect.baseline_mm / z, rtol=1e-9)
    src_l = rig.left.project(X)
    src_r = rig.right.project(X @ rig.R.T + rig.T)
    np.testing.assert_allclose(_sample(maps.left_x, maps.left_y, ul), src_l, atol=0.02)
    np.testing.assert_allclose(_sample(maps.right_x, maps.right_y, ur), src_r, atol=0.02)


def test_fixed_point_maps_and_rectify_pair() -> None:
    import cv2

    rig = small_rig()
    rect = compute_rectification(rig)
    fm = rectify_maps(rig, rect, fixed_point=True)
    assert fm.fixed_point and fm.left_x.dtype == np.int16 and fm.left_x.shape[2] == 2
    rng = np.random.default_rng(1)
    left = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    right = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    lr, _, rect2 = rectify_pair(left, right, rig)
    assert lr.shape == (rect.size[1], rect.size[0], 3) and lr.dtype == np.uint8
    np.testing.assert_array_equal(rect2.P1, rect.P1)
    # the float and fixed-point maps agree to the 1/32 px table resolution
    _, xx = np.mgrid[0:120, 0:160]
    smooth = (xx * 1.5).astype(np.uint8)
    fl = rectify_maps(rig, rect).remap(smooth, smooth)
    fx = fm.remap(smooth, smooth, interpolation=cv2.INTER_LINEAR)
    diff = np.abs(fl[0].astype(int) - fx[0].astype(int))
    assert np.median(diff[fl[0] > 0]) <= 1
    # float32 images stay float32
    lf, _ = rectify_maps(rig, rect).remap(
        left.astype(np.float64) / 255, right.astype(np.float64) / 255
    )
    assert lf.dtype == np.float32


def test_bspline_remap_interpolates_exactly() -> None:
    """The B-spline path against scipy's independent spline interpolation, and the
    property that matters for sub-pixel matching: a sampled smooth signal comes back
    at the maps' exact positions, where OpenCV's bilinear remap is off (on uint8 by
    more than 0.2 px on a ramp of 1.5 grey levels per pixel)."""
    import cv2
    from scipy import ndimage

    rig = small_rig()
    rect = compute_rectification(rig)
    maps = rectify_maps(rig, rect)
    rng = np.random.default_rng(4)
    img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    out, out_r = maps.remap(img, img[..., 0], interpolation="bspline")
    assert out.dtype == np.float32 and out.shape == (rect.size[1], rect.size[0], 3)
    assert out_r.shape == (rect.size[1], rect.size[0])
    inside = (maps.left_x >= 2) & (maps.left_x <= 157) & (maps.left_y >= 2) & (maps.left_y <= 117)
    assert inside.sum() > 10000
    for c in range(3):
        ref = ndimage.map_coordinates(img[..., c].astype(np.float64), [maps.left_y, maps.left_x], order=3,
                                      mode="mirror")
        ref = np.clip(ref, img.min(), img.max())
        np.testing.assert_allclose(out[..., c][inside], ref[inside], atol=2e-3)
    outside = (maps.left_x < 0) | (maps.left_x > 159) | (maps.left_y < 0) | (maps.left_y > 119)
    assert outside.any() and np.all(out[outside] == 0)
    assert out.min() >= 0 and out.max() <= 255  # clipped to the input's range
    # a sinusoid of 9.3 px period: its values at the exact positions (8 px clear of
    # the border, whose mirroring the spline sees); bilinear is off by up to 8
    yy, xx = np.mgrid[0:120, 0:160].astype(np.float64)
    wave = 127.5 + 100 * np.sin(2 * np.pi * xx / 9.3) * np.cos(2 * np.pi * yy / 13.1)
    true = 127.5 + 100 * np.sin(2 * np.pi * maps.left_x / 9.3) * np.cos(2 * np.pi * maps.left_y / 13.1)
    clear = (maps.left_x >= 8) & (maps.left_x <= 151) & (maps.left_y >= 8) & (maps.left_y <= 111)
    got, _ = maps.remap(wave, wave, interpolation="bspline")
    assert np.max(np.abs(got - true)[clear]) < 0.15  # of 200 peak to peak
    lin, _ = maps.remap(wave.astype(np.float32), wave.astype(np.float32))
    assert np.max(np.abs(lin - true)[clear]) > 5.0
    # the ramp (4 grey levels per pixel) reads back its position exactly
    ramp = (xx * 1.5).astype(np.float32)
    got, _ = maps.remap(ramp, ramp, interpolation="bspline")
    np.testing.assert_allclose(got[clear] / 1.5, maps.left_x[clear], atol=1e-3)
    lin, _ = maps.remap((xx * 1.5).astype(np.uint8), ramp, interpolation=cv2.INTER_LINEAR)
    assert np.max(np.abs(lin[clear] / 1.5 - maps.left_x[clear])) > 0.2


def test_rectify_shot_splits_with_the_rig() -> None:
    base = small_rig()
    split = PrismSplit.side_by_side((320, 120), flip_right=True)
    rig = StereoRig(base.left, base.right, base.T_right_left, split, base.T_rig_left)
    rng = np.random.default_rng(2)
    left = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    right = rng.integers(0, 255, (120, 160), dtype=np.uint8)
    shot = split.join(left, right)
    a = rectify_shot(shot, rig)
    b = rectify_pair(left, right, rig)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_rectify_to_folder(tmp_path: Path) -> None:
    import cv2

    rig = small_rig()
    calib = tmp_path / "calib.yaml"
    rig.save(calib)
    rng = np.random.default_rng(3)
    shot = rng.integers(0, 255, (120, 320, 3), dtype=np.uint8)
    shot_path = tmp_path / "shot.png"
    cv2.imwrite(str(shot_path), shot[..., ::-1])
    out = tmp_path / "out"
    paths = rectify_to_folder(shot_path, calib, out)
    assert sorted(p.name for p in out.iterdir()) == ["left.png", "rectification.yaml", "right.png"]
    left_rect, _, rect = rectify_shot(shot, rig)
    np.testing.assert_array_equal(cv2.imread(str(paths["left"]))[..., ::-1], left_rect)
    fs = cv2.FileStorage(str(paths["rectification"]), cv2.FILE_STORAGE_READ)
    for k in ("R1", "R2", "P1", "P2", "Q"):
        np.testing.assert_allclose(fs.getNode(k).mat(), getattr(rect, k))
    np.testing.assert_allclose(fs.getNode("K1").mat(), rig.left.K)
    fs.release()


def test_errors(tmp_path: Path) -> None:
    rig = small_rig()
    rect = compute_rectification(rig)
    with pytest.raises(InputError, match="rig: expected a StereoRig"):
        rectify_maps("rig", rect)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="rect: expected a Rectification"):
        rectify_maps(rig, None)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="left: expected a 160x120 view"):
        rectify_pair(np.zeros((10, 10), np.uint8), np.zeros((120, 160), np.uint8), rig)
    with pytest.raises(InputError, match="expected a 320x120 sensor image"):
        rectify_shot(np.zeros((120, 300), np.uint8), rig)
    calib = tmp_path / "calib.yaml"
    rig.save(calib)
    wrong = tmp_path / "wrong.png"
    import cv2

    cv2.imwrite(str(wrong), np.zeros((50, 60, 3), np.uint8))
    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"wrong.png: .*320x120 sensor image"):
        rectify_to_folder(wrong, calib, out)
    with pytest.raises(InputError, match="not found"):
        rectify_to_folder(tmp_path / "missing.png", calib, out)
    with pytest.raises(InputError, match="calibration file not found"):
        rectify_to_folder(wrong, tmp_path / "missing.yaml", out)
    assert not out.exists()


def test_bspline_errors() -> None:
    rig = small_rig()
    rect = compute_rectification(rig)
    img = np.zeros((120, 160), np.uint8)
    with pytest.raises(InputError, match="interpolation: expected an OpenCV flag or 'bspline'"):
        rectify_maps(rig, rect).remap(img, img, interpolation="cubic")
    with pytest.raises(InputError, match="needs float maps"):
        rectify_maps(rig, rect, fixed_point=True).remap(img, img, interpolation="bspline")
