from __future__ import annotations

import numpy as np
import pytest

from prism3d.capture.rig import (
    CameraModel,
    PrismSplit,
    StereoRig,
    compute_rectification,
    look_at,
    paper_rig,
    scaled_rig,
)
from prism3d.errors import InputError


def test_paper_rig_numbers():
    rig = paper_rig()
    assert rig.split.sensor_size == (2592, 1944)
    assert rig.split.view_size == (1296, 1944)
    assert rig.left.fx == 5107 and rig.baseline_mm == pytest.approx(197.9)
    # both optical axes pass through the convergence point 1250 mm ahead
    for T in (rig.T_rig_left, rig.T_rig_right):
        c, z = T[:3, 3], T[:3, 2]
        s = (1250.0 - c[2]) / z[2]
        np.testing.assert_allclose(c + s * z, [0, 0, 1250], atol=1e-9)


def test_projection_matches_opencv():
    import cv2

    rig = paper_rig(dist=(-0.08, 0.15, 1e-4, -2e-4, 0.01))
    pts = np.random.default_rng(0).uniform([-150, -150, 1000], [150, 150, 1500], (200, 3))
    ours = rig.left.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), rig.left.K, rig.left.dist)
    np.testing.assert_allclose(ours, ref[:, 0], atol=1e-9)


def test_pixel_rays_invert_projection():
    cam = paper_rig(dist=(-0.2, 0.3, 1e-3, 1e-3, 0.0)).left
    pts = np.random.default_rng(1).uniform([-200, -200, 900], [200, 200, 1500], (500, 3))
    rays = cam.pixel_rays(cam.project(pts))
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-12)


def test_skew_projection():
    K = np.array([[1000.0, 5.0, 320.0], [0, 1000.0, 240.0], [0, 0, 1]])
    cam = CameraModel(K, np.zeros(5), (640, 480))
    uv = cam.project(np.array([[10.0, 20.0, 100.0]]))
    np.testing.assert_allclose(uv, [[320 + 100 + 1.0, 240 + 200]])
    np.testing.assert_allclose(cam.pixel_rays(uv)[0] * np.linalg.norm([10, 20, 100]), [10, 20, 100])


def test_scaled_camera_pixel_centres():
    cam = paper_rig().left
    s = cam.scaled(2)
    p = np.array([[12.0, -30.0, 1200.0]])
    uv, uv2 = cam.project(p)[0], s.project(p)[0]
    np.testing.assert_allclose(uv2, (uv + 0.5) * 2 - 0.5, atol=1e-9)
    assert s.size == (2592, 3888)


@pytest.mark.parametrize("flip", [(False, False), (True, False), (False, True), (True, True)])
def test_split_join_lossless(flip):
    split = PrismSplit.side_by_side((40, 10), flip_left=flip[0], flip_right=flip[1])
    img = np.random.default_rng(2).integers(0, 256, (10, 40, 3), dtype=np.uint8)
    left, right = split.split(img)
    assert left.shape == right.shape == (10, 20, 3)
    np.testing.assert_array_equal(split.join(left, right), img)
    if flip[0]:
        np.testing.assert_array_equal(left, img[:, :20][:, ::-1])


def test_rectified_disparity_of_a_plane():
    """A point at rectified depth z has disparity f*B/z; rectified rows agree."""
    rig = paper_rig()
    rect = compute_rectification(rig)
    rng = np.random.default_rng(3)
    p_rig = np.c_[rng.uniform(-150, 150, (50, 2)), np.full(50, 1250.0), np.ones(50)]
    p_left = (np.linalg.inv(rig.T_rig_left) @ p_rig.T).T[:, :3]
    x_rect = p_left @ rect.R1.T
    ul = x_rect @ rect.P1[:, :3].T
    ul = ul[:, :2] / ul[:, 2:]
    ur = np.c_[x_rect, np.ones(50)] @ rect.P2.T
    ur = ur[:, :2] / ur[:, 2:]
    np.testing.assert_allclose(ul[:, 1], ur[:, 1], atol=1e-9)
    d = ul[:, 0] - ur[:, 0]
    np.testing.assert_allclose(d, rect.focal_px * rect.baseline_mm / x_rect[:, 2], rtol=1e-12)
    # the rectified frame is parallel to the rig frame for the symmetric paper rig
    np.testing.assert_allclose(x_rect[:, 2], 1250.0, atol=1e-6)
    assert 800 < d.mean() < 820
    # and via the same path the right camera gives the same rectified point
    p_right = (rig.T_right_left @ np.c_[p_left, np.ones(50)].T).T[:, :3]
    np.testing.assert_allclose(p_right @ rect.R2.T + [rect.baseline_mm, 0, 0], x_rect, atol=1e-9)


def test_rectification_size_options():
    rig = paper_rig()
    full = compute_rectification(rig, alpha=1.0)
    inner = compute_rectification(rig, alpha=0.0)
    assert inner.size[0] <= full.size[0] and inner.size[1] <= full.size[1]
    small = compute_rectification(rig, size=(640, 600))
    assert small.size == (640, 600) and small.focal_px < full.focal_px
    with pytest.raises(InputError, match="alpha"):
        compute_rectification(rig, alpha=2)


def test_yaml_round_trip_and_opencv_names(tmp_path):
    import cv2

    rig = paper_rig(flip_right=True)
    rig.save(tmp_path / "rig.yaml", extra={"rms_px": 0.1})
    back = StereoRig.load(tmp_path / "rig.yaml")
    assert back.split == rig.split
    np.testing.assert_allclose(back.T_right_left, rig.T_right_left, atol=1e-12)
    np.testing.assert_allclose(back.left.K, rig.left.K)
    fs = cv2.FileStorage(str(tmp_path / "rig.yaml"), cv2.FILE_STORAGE_READ)
    for k in ("K1", "D1", "K2", "D2", "R", "T"):
        assert not fs.getNode(k).empty(), k
    np.testing.assert_allclose(fs.getNode("T").mat().ravel(), rig.T)
    fs.release()


@pytest.mark.parametrize("flip_right", [False, True])
def test_yaml_rectifies_with_opencv_alone(tmp_path, flip_right):
    """R1 R2 P1 P2 Q and rectified_size in the YAML: cv2.initUndistortRectifyMap alone
    gives the maps prism3d rectifies with, and Q reprojects a disparity to our depth."""
    import cv2

    from prism3d.reconstruct.stereo.rectify import rectify_maps

    rig = paper_rig(flip_right=flip_right)
    rig.save(tmp_path / "rig.yaml")
    fs = cv2.FileStorage(str(tmp_path / "rig.yaml"), cv2.FILE_STORAGE_READ)
    m = {k: fs.getNode(k).mat() for k in ("K1", "D1", "K2", "D2", "R1", "R2", "P1", "P2", "Q", "rectified_size")}
    fs.release()
    size = tuple(int(v) for v in m["rectified_size"].ravel())
    ours = rectify_maps(rig, compute_rectification(rig))
    for K, D, R, P, (x, y) in ((m["K1"], m["D1"], m["R1"], m["P1"], (ours.left_x, ours.left_y)),
                               (m["K2"], m["D2"], m["R2"], m["P2"], (ours.right_x, ours.right_y))):
        mx, my = cv2.initUndistortRectifyMap(K, D, R, P, size, cv2.CV_32FC1)
        np.testing.assert_allclose(mx, x, atol=1e-3)
        np.testing.assert_allclose(my, y, atol=1e-3)
    rect = compute_rectification(rig)
    pts = cv2.reprojectImageTo3D(np.full((4, 4), 20.0, np.float32), m["Q"])
    assert pts[0, 0, 2] == pytest.approx(float(rect.disparity_to_depth(np.array([20.0]))[0]), rel=1e-5)


def test_yaml_from_plain_opencv_stereo_file(tmp_path):
    from prism3d.io.opencv_yaml import write_filestorage

    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    write_filestorage(tmp_path / "s.yml", {"K1": K, "D1": np.zeros(5), "K2": K, "D2": np.zeros(5),
                                           "R": np.eye(3), "T": np.array([-60.0, 0, 0]),
                                           "image_size": np.array([640, 480])})
    rig = StereoRig.load(tmp_path / "s.yml")
    assert rig.split.view_size == (640, 480) and rig.baseline_mm == 60


def test_yaml_errors(tmp_path):
    from prism3d.io.opencv_yaml import write_filestorage

    write_filestorage(tmp_path / "a.yaml", {"K1": np.eye(3)})
    with pytest.raises(InputError, match="missing D1, K2, D2, R, T"):
        StereoRig.load(tmp_path / "a.yaml")
    write_filestorage(tmp_path / "b.yaml", {"schema_version": 99})
    with pytest.raises(InputError, match="schema_version 99"):
        StereoRig.load(tmp_path / "b.yaml")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(K=np.array([[-1.0, 0, 1], [0, 1, 1], [0, 0, 1]]), dist=np.zeros(5), size=(10, 10)), "focal"),
        (dict(K=np.eye(3), dist=np.zeros(5), size=(0, 10)), "size"),
        (dict(K=np.eye(2), dist=np.zeros(5), size=(10, 10)), "shape"),
        (dict(K=np.eye(3), dist=np.ones(8), size=(10, 10)), "only"),
        (dict(K=np.array([[1.0, 0, 1], [1, 1, 1], [0, 0, 1]]), dist=np.zeros(5), size=(10, 10)), "expected"),
    ],
)
def test_bad_camera(kwargs, match):
    with pytest.raises(InputError, match=match):
        CameraModel(**kwargs)


def test_bad_split_and_rig():
    with pytest.raises(InputError, match="outside"):
        PrismSplit((100, 50), (0, 0, 60, 50), (60, 0, 60, 50))
    with pytest.raises(InputError, match="same size"):
        PrismSplit((100, 50), (0, 0, 50, 50), (50, 0, 40, 50))
    with pytest.raises(InputError, match="even"):
        PrismSplit.side_by_side((101, 50))
    split = PrismSplit.side_by_side((100, 50))
    with pytest.raises(InputError, match="sensor image"):
        split.split(np.zeros((50, 90), np.uint8))
    cam = CameraModel(np.array([[100.0, 0, 25], [0, 100, 25], [0, 0, 1]]), np.zeros(5), (50, 50))
    bad = np.eye(4)
    bad[:3, :3] = np.diag([1, 1, -1])
    with pytest.raises(InputError, match="proper rotation"):
        StereoRig(cam, cam, bad, split)
    with pytest.raises(InputError, match="baseline"):
        StereoRig(cam, cam, np.eye(4), split)
    with pytest.raises(InputError, match="do not match"):
        StereoRig(cam.with_size((40, 50)), cam, np.eye(4), split)
    with pytest.raises(InputError, match="range_mm"):
        scaled_rig(-1, 100)
    with pytest.raises(InputError, match="coincide"):
        look_at(np.zeros(3), np.zeros(3))


def test_scaled_rig_geometry():
    rig = scaled_rig(20000.0, 4000.0)
    assert rig.baseline_mm == pytest.approx(4000)
    rect = compute_rectification(rig)
    assert rect.baseline_mm == pytest.approx(4000)


def test_absurd_distortion_is_refused():
    """A calibration file with k1 = 1e30 was accepted and gave meaningless rectification."""
    from prism3d.capture.rig import CameraModel

    K = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    CameraModel(K, np.array([-0.3, 0.1, 0, 0, 0.05]), (640, 480))  # a real wide-angle lens
    with pytest.raises(InputError, match="describe no lens"):
        CameraModel(K, np.array([1e30, 0, 0, 0, 0]), (640, 480))
