from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from prism3d.capture.calib_formats import (
    StereoCalibration,
    convert_calibration,
    load_stereo_calibration,
    read_kitti_calib,
    read_middlebury_calib,
    read_opencv_calibration,
    read_ros_camera_info,
)
from prism3d.capture.rig import CameraModel, PrismSplit, StereoRig, compute_rectification
from prism3d.errors import InputError

SIZE = (640, 480)


def _rig(T=(-120.5, 1.3, 2.7)) -> StereoRig:
    """A two-camera rig with a real rotation and distortion."""
    import cv2

    K1 = np.array([[812.3, 0.0, 321.7], [0.0, 809.9, 238.4], [0.0, 0.0, 1.0]])
    K2 = np.array([[805.1, 0.0, 316.2], [0.0, 803.8, 244.9], [0.0, 0.0, 1.0]])
    D1 = np.array([-0.21, 0.11, 1.2e-3, -8e-4, -0.03])
    D2 = np.array([-0.19, 0.07, -5e-4, 6e-4, 0.01])
    Tm = np.eye(4)
    Tm[:3, :3] = cv2.Rodrigues(np.array([0.012, -0.035, 0.008]))[0]
    Tm[:3, 3] = T
    split = PrismSplit.side_by_side((2 * SIZE[0], SIZE[1]))
    return StereoRig(CameraModel(K1, D1, SIZE), CameraModel(K2, D2, SIZE), Tm, split)


def _rectified_rig(doffs: float = 37.25, B: float = 174.8125) -> StereoRig:
    """A rig as Middlebury/ETH3D/KITTI describe theirs: R = I, no distortion."""
    K0 = np.array([[1733.74, 0.0, 792.27], [0.0, 1733.74, 541.89], [0.0, 0.0, 1.0]])
    K1 = K0.copy()
    K1[0, 2] += doffs
    T = np.eye(4)
    T[0, 3] = -B
    size = (1600, 1100)
    split = PrismSplit.side_by_side((2 * size[0], size[1]))
    return StereoRig(CameraModel(K0, np.zeros(5), size), CameraModel(K1, np.zeros(5), size),
                     T, split)


def _assert_rig_close(a: StereoRig, b: StereoRig, tol: float = 1e-9) -> None:
    assert a.left.size == b.left.size and a.split == b.split
    for x, y in ((a.left.K, b.left.K), (a.right.K, b.right.K), (a.R, b.R)):
        np.testing.assert_allclose(x, y, rtol=tol, atol=tol)
    np.testing.assert_allclose(a.left.dist, b.left.dist, atol=tol)
    np.testing.assert_allclose(a.right.dist, b.right.dist, atol=tol)
    np.testing.assert_allclose(a.T, b.T, atol=tol * 1000)


def _write_fs(path: Path, values: dict) -> Path:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in values.items():
        fs.write(k, v)
    fs.release()
    return path


def _stereo_rectify(rig: StereoRig, scale: float = 1.0) -> tuple[np.ndarray, ...]:
    import cv2

    return cv2.stereoRectify(rig.left.K, rig.left.dist, rig.right.K, rig.right.dist, SIZE,
                             rig.R, rig.T.reshape(3, 1) * scale)


def _mat(a) -> str:
    return "[" + "; ".join(" ".join(repr(float(v)) for v in row) for row in np.asarray(a)) + "]"


def _middlebury_text(rig: StereoRig, extra: str = "ndisp=64\n") -> str:
    w, h = rig.left.size
    doffs = rig.right.cx - rig.left.cx
    return (f"cam0={_mat(rig.left.K)}\ncam1={_mat(rig.right.K)}\ndoffs={doffs!r}\n"
            f"baseline={rig.baseline_mm!r}\nwidth={w}\nheight={h}\n{extra}")


# -- prism3d / OpenCV FileStorage ------------------------------------------------------
def test_prism3d_yaml_round_trip(tmp_path):
    rig = _rig()
    rig.save(tmp_path / "rig.yaml")
    cal = load_stereo_calibration(tmp_path / "rig.yaml")
    assert isinstance(cal, StereoCalibration) and cal.source_format == "prism3d"
    assert cal.rig == rig and cal.disparity_range is None and cal.doffs is None


def _opencv_pair(tmp_path: Path, rig: StereoRig, suffix: str = ".yml") -> tuple[Path, Path]:
    """What OpenCV's stereo_calib sample writes: intrinsics.yml and extrinsics.yml."""
    R1, R2, P1, P2, Q, _, _ = _stereo_rectify(rig)
    intr = _write_fs(tmp_path / f"intrinsics{suffix}",
                     {"M1": rig.left.K, "D1": rig.left.dist.reshape(1, 5),
                      "M2": rig.right.K, "D2": rig.right.dist.reshape(1, 5)})
    extr = _write_fs(tmp_path / f"extrinsics{suffix}",
                     {"R": rig.R, "T": rig.T.reshape(3, 1), "R1": R1, "R2": R2, "P1": P1,
                      "P2": P2, "Q": Q})
    return intr, extr


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_stereo_calib_pair_either_order(tmp_path, suffix):
    rig = _rig()
    intr, extr = _opencv_pair(tmp_path, rig, suffix)
    for paths in ((intr, extr), [str(extr), str(intr)]):
        cal = load_stereo_calibration(paths, image_size=SIZE)
        assert cal.source_format == "opencv"
        _assert_rig_close(cal.rig, rig, 1e-12)
        assert any("R1 R2 P1 P2 Q ignored" in n for n in cal.notes)
        assert any("millimetres" in n for n in cal.notes)


def test_opencv_single_file_with_everything(tmp_path):
    rig = _rig()
    f = _write_fs(tmp_path / "stereo.yml",
                  {"image_width": 640, "image_height": 480, "M1": rig.left.K, "D1": rig.left.dist,
                   "M2": rig.right.K, "D2": rig.right.dist, "R": rig.R, "T": rig.T})
    _assert_rig_close(read_opencv_calibration(f).rig, rig, 1e-12)
    # K1..T without schema_version is an OpenCV tool's file; the size comes from the caller
    g = _write_fs(tmp_path / "k.yml", {"K1": rig.left.K, "D1": rig.left.dist, "K2": rig.right.K,
                                       "D2": rig.right.dist, "R": rig.R, "T": rig.T})
    cal = load_stereo_calibration(g, image_size=SIZE)
    assert cal.source_format == "opencv"
    _assert_rig_close(cal.rig, rig, 1e-12)


def test_opencv_baseline_in_metres_is_flagged(tmp_path):
    intr, extr = _opencv_pair(tmp_path, _rig(T=(-0.12, 0.0, 0.0)))
    cal = load_stereo_calibration([intr, extr], image_size=SIZE)
    assert any("implausibly small" in n for n in cal.notes)


def test_opencv_errors(tmp_path):
    rig = _rig()
    intr, extr = _opencv_pair(tmp_path, rig)
    with pytest.raises(InputError, match=r"intrinsics\.yml \+ .*does not state the image size"):
        load_stereo_calibration([intr, extr])
    with pytest.raises(InputError, match=r"intrinsics\.yml: holds intrinsics only .*extrinsics"):
        load_stereo_calibration(intr, image_size=SIZE)
    with pytest.raises(InputError, match=r"extrinsics\.yml: holds extrinsics only"):
        load_stereo_calibration(extr, image_size=SIZE)
    with pytest.raises(InputError, match=r"entry 'M1' is also in .*intrinsics\.yml"):
        load_stereo_calibration([intr, intr], image_size=SIZE)
    rig.save(tmp_path / "rig.yaml")
    with pytest.raises(InputError, match=r"rig\.yaml: the file gives 640x480 images but "
                                         r"image_size is 320x240"):
        load_stereo_calibration(tmp_path / "rig.yaml", image_size=(320, 240))
    other = _write_fs(tmp_path / "other.yml", {"foo": 1.0})
    with pytest.raises(InputError, match=r"other\.yml: has no stereo calibration entries "
                                         r"\(found foo\)"):
        load_stereo_calibration(other)
    bad = _write_fs(tmp_path / "bad.yml", {"K1": np.eye(3), "D1": np.zeros(5), "K2": np.eye(3),
                                           "D2": np.zeros(5), "R": np.eye(3) * 2, "T": np.ones(3)})
    with pytest.raises(InputError, match=r"bad\.yml: T_right_left: rotation part is not"):
        load_stereo_calibration(bad, image_size=SIZE)
    size = _write_fs(tmp_path / "size.yml", {"image_size": np.array([640, 480, 3]),
                                             "M1": rig.left.K, "D1": rig.left.dist,
                                             "M2": rig.right.K, "D2": rig.right.dist,
                                             "R": rig.R, "T": rig.T})
    with pytest.raises(InputError, match=r"size\.yml: image_size must hold \(width, height\)"):
        load_stereo_calibration(size)
    values = {"image_size": "640x480", "M1": rig.left.K, "D1": rig.left.dist, "M2": rig.right.K,
              "D2": rig.right.dist, "R": rig.R, "T": rig.T}
    _write_fs(size, values)
    with pytest.raises(InputError, match=r"size\.yml: image_size: expected numbers, got '640x480'"):
        load_stereo_calibration(size)
    _write_fs(size, dict(values, image_size=np.array(SIZE), disparity_range=np.arange(3)))
    with pytest.raises(InputError, match=r"size\.yml: disparity_range: expected 2 values, got 3"):
        load_stereo_calibration(size)
    mono = _write_fs(tmp_path / "mono.yml", {"camera_matrix": rig.left.K, "image_width": 640})
    with pytest.raises(InputError, match=r"mono\.yml: is a single-camera calibration"):
        load_stereo_calibration(mono)


# -- Middlebury / ETH3D ----------------------------------------------------------------
def test_middlebury_round_trip(tmp_path):
    rig = _rectified_rig()
    f = tmp_path / "calib.txt"
    f.write_text(_middlebury_text(rig, "ndisp=290\nisint=0\nvmin=55\nvmax=260\ndyavg=0\ndymax=0\n"))
    cal = load_stereo_calibration(f)
    assert cal.source_format == "middlebury" and cal.rig == rig
    assert cal.doffs == 37.25 and cal.disparity_range == (0, 290)
    assert any("colour-coding only" in n for n in cal.notes)


def test_middlebury_optional_entries(tmp_path):
    rig = _rectified_rig()
    f = tmp_path / "calib.txt"
    text = _middlebury_text(rig, "vmin=55.5\nvmax=260.2\ndymax=0.7\nfoo=1\n")
    f.write_text(text.replace("doffs=37.25\n", ""))
    cal = read_middlebury_calib(f)
    assert cal.doffs == pytest.approx(37.25) and cal.disparity_range == (55, 207)
    assert any("no doffs entry" in n for n in cal.notes)
    assert any("dymax" in n for n in cal.notes)
    assert any("unknown entries: foo" in n for n in cal.notes)
    f.write_text(_middlebury_text(rig).replace("doffs=37.25", "doffs=40"))
    assert any("differs from cam1 cx - cam0 cx" in n for n in read_middlebury_calib(f).notes)


def _check_disparity_convention(cal: StereoCalibration) -> None:
    """d = f B / z - doffs in the images as given. prism3d's rectification of such a rig
    keeps the right view's pixels and shifts the left view right by doffs (rectified
    cx = cam1's cx), so its disparity is d + doffs = f B / z."""
    rig = cal.rig
    f, B, doffs = rig.left.fx, rig.baseline_mm, cal.doffs
    rng = np.random.default_rng(3)
    z = rng.uniform(1000.0, 8000.0, 50)
    p = np.stack([rng.uniform(-0.3, 0.3, 50) * z, rng.uniform(-0.2, 0.2, 50) * z, z], axis=1)
    ul = rig.left.project(p)
    ur = rig.right.project(p @ rig.R.T + rig.T)
    np.testing.assert_allclose(ul[:, 1], ur[:, 1], atol=1e-9)
    np.testing.assert_allclose(ul[:, 0] - ur[:, 0], f * B / z - doffs, atol=1e-9)
    rect = compute_rectification(rig)
    np.testing.assert_allclose(rect.R1, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(rect.R2, np.eye(3), atol=1e-15)
    x = np.c_[p @ rect.R1.T, np.ones(len(p))]
    ul_rect = (x @ rect.P1.T)[:, :2] / z[:, None]
    ur_rect = (x @ rect.P2.T)[:, :2] / z[:, None]
    np.testing.assert_allclose(ul_rect[:, 0], ul[:, 0] + doffs, atol=1e-9)
    np.testing.assert_allclose(ur_rect, ur, atol=1e-9)
    np.testing.assert_allclose(ul_rect[:, 0] - ur_rect[:, 0], f * B / z, rtol=1e-12)
    assert rect.P1[0, 2] == pytest.approx(rig.left.cx + doffs)
    assert rect.size[0] >= rig.left.width + doffs


def test_middlebury_synthetic_disparity_convention():
    _check_disparity_convention(StereoCalibration(_rectified_rig(), "middlebury", None, 37.25))


@pytest.mark.realdata
@pytest.mark.parametrize(
    "rel, f, cx0, cx1, cy, B, doffs, size, disp",
    [
        ("stereo/eth3d_two_view/playground", 542.019, 541.836, 541.836, 255.198, 59.5549, 0.0,
         (941, 490), (0, 941)),
        ("stereo/eth3d_two_view/terrace", 711.499, 376.135, 376.135, 227.447, 59.9432, 0.0,
         (713, 434), (0, 713)),
        ("stereo/middlebury_2014_Q/ArtL", 935.0, 148.0, 198.0, 138.0, 160.0, 50.0,
         (347, 277), (0, 64)),
        ("stereo/middlebury_2014_Q/Teddy", 1500.0, 199.0, 251.0, 187.0, 80.0, 52.0,
         (450, 375), (0, 64)),
    ],
)
def test_real_middlebury_and_eth3d_calib(shared_data, rel, f, cx0, cx1, cy, B, doffs, size,
                                         disp):
    cal = load_stereo_calibration(shared_data / rel / "calib.txt")
    rig = cal.rig
    assert cal.source_format == "middlebury" and cal.doffs == doffs
    assert cal.disparity_range == disp
    assert rig.left.size == size and rig.split.sensor_size == (2 * size[0], size[1])
    assert (rig.left.fx, rig.left.fy, rig.left.cx, rig.left.cy) == (f, f, cx0, cy)
    assert (rig.right.fx, rig.right.cx, rig.right.cy) == (f, cx1, cy)
    assert rig.baseline_mm == B and tuple(rig.T) == (-B, 0.0, 0.0)
    assert not rig.left.has_distortion and np.array_equal(rig.R, np.eye(3))
    _check_disparity_convention(cal)


def test_middlebury_errors(tmp_path):
    good = _middlebury_text(_rectified_rig())
    f = tmp_path / "calib.txt"
    cases = [
        (good.replace("cam1=", "#cam1="), r"calib\.txt: missing cam1; .* needs cam0, cam1"),
        (good.replace("baseline=174.8125\n", ""), r"calib\.txt: missing baseline"),
        (good.replace("width=1600\n", "").replace("height=1100\n", ""),
         r"calib\.txt: the file does not state the image size; pass it"),
        (good.replace("height=1100\n", ""), r"calib\.txt: gives only one of width and height"),
        (good.replace("cam0=[1733.74 0.0", "cam0=[1733.74"),
         r"calib\.txt: cam0: expected a 3x3 matrix '\[fx 0 cx; 0 fy cy; 0 0 1\]', got 8 values"),
        (good.replace("cam0=[", "cam0="), r"calib\.txt: cam0: expected a matrix"),
        (good.replace("cam1=[1733.74 ", "cam1=[f "), r"calib\.txt: cam1: expected a number"),
        (good.replace("=174.8125", "=abc"), r"calib\.txt: baseline: expected a number, got 'abc'"),
        (good.replace("=174.8125", "=nan"), r"calib\.txt: baseline: expected a finite number"),
        (good.replace("=174.8125", "=0"), r"calib\.txt: baseline must be > 0 \(mm\), got 0"),
        (good.replace("=174.8125", "=-3"), r"calib\.txt: baseline must be > 0"),
        (good.replace("width=1600", "width=16.5"), r"calib\.txt: width: expected a positive int"),
        (good.replace("ndisp=64", "ndisp=0"), r"calib\.txt: ndisp: expected a positive integer"),
        (good + "baseline=3\n", r"calib\.txt: line 8: baseline is given twice"),
        (good + "just words\n", r"calib\.txt: line 8: expected 'name=value'"),
        (good.replace("0.0 1.0]", "0.0 2.0]", 1), r"calib\.txt: K: expected \[\[fx, s, cx\]"),
    ]
    for text, msg in cases:
        f.write_text(text)
        with pytest.raises(InputError, match=msg):
            load_stereo_calibration(f)


# -- KITTI -----------------------------------------------------------------------------
_KITTI_P = {  # KITTI raw 2011_09_26 rectified projections as published (metres in column 4)
    0: "7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 0.000000e+00 7.215377e+02 "
       "1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00",
    1: "7.215377e+02 0.000000e+00 6.095593e+02 -3.875744e+02 0.000000e+00 7.215377e+02 "
       "1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00",
    2: "7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 "
       "1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03",
    3: "7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0.000000e+00 7.215377e+02 "
       "1.728540e+02 2.199936e+00 0.000000e+00 0.000000e+00 1.000000e+00 2.729905e-03",
}


def _kitti_cam_to_cam(drop: str = "") -> str:
    """A calib_cam_to_cam.txt in KITTI's layout (unrectified entries are placeholders)."""
    lines = ["calib_time: 09-Jan-2012 13:57:47", "corner_dist: 9.950000e-02"]
    for i in range(4):
        lines += [
            f"S_{i:02d}: 1.392000e+03 5.120000e+02",
            f"K_{i:02d}: 9.842439e+02 0.000000e+00 6.900000e+02 0.000000e+00 9.808141e+02 "
            "2.331966e+02 0.000000e+00 0.000000e+00 1.000000e+00",
            f"D_{i:02d}: -3.728755e-01 2.037299e-01 2.219027e-03 1.383707e-03 -7.233722e-02",
            f"R_{i:02d}: 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 "
            "0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00",
            f"T_{i:02d}: {-0.5327 * (i % 2):e} 0.000000e+00 0.000000e+00",
            f"S_rect_{i:02d}: 1.242000e+03 3.750000e+02",
            f"R_rect_{i:02d}: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 "
            "9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01",
            f"P_rect_{i:02d}: {_KITTI_P[i]}",
        ]
    return "\n".join(ln for ln in lines if not (drop and ln.startswith(drop + ":"))) + "\n"


def test_kitti_cam_to_cam(tmp_path):
    f = tmp_path / "calib_cam_to_cam.txt"
    f.write_text(_kitti_cam_to_cam())
    cal = load_stereo_calibration(f)
    rig = cal.rig
    assert cal.source_format == "kitti" and rig.left.size == (1242, 375)
    K = [[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]]
    np.testing.assert_array_equal(rig.left.K, K)
    np.testing.assert_array_equal(rig.right.K, K)
    B = 1000.0 * (44.85728 + 339.5242) / 721.5377
    assert rig.baseline_mm == pytest.approx(B, rel=1e-12)
    assert rig.baseline_mm == pytest.approx(532.72, abs=0.01)
    np.testing.assert_allclose(rig.T, [-B, 0.0, 0.0], rtol=1e-12)
    assert np.array_equal(rig.R, np.eye(3)) and not rig.right.has_distortion
    assert any("(dy, dz)" in n for n in cal.notes)  # the colour cameras' off-baseline offsets
    grey = load_stereo_calibration(f, kitti_cameras=(0, 1))
    assert grey.rig.baseline_mm == pytest.approx(537.1505, abs=1e-3)
    assert not any("(dy, dz)" in n for n in grey.notes)


def test_kitti_calib_txt_round_trip_of_a_rectified_rig(tmp_path):
    f_px, cx, cy, B = 707.0493, 604.0814, 180.5066, 537.165718864418
    P0 = np.array([[f_px, 0, cx, 0], [0, f_px, cy, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -f_px * B / 1000.0
    text = "".join(f"P{i}: " + " ".join(repr(float(v)) for v in (P0, P1)[i % 2].ravel()) + "\n"
                   for i in range(4))
    f = tmp_path / "calib.txt"
    f.write_text(text + "Tr: " + " ".join(["0.0"] * 12) + "\n")
    cal = read_kitti_calib(f, cameras=(0, 1), image_size=(1226, 370))
    assert cal.rig.left.size == (1226, 370)
    np.testing.assert_array_equal(cal.rig.left.K, P0[:, :3])
    np.testing.assert_allclose(cal.rig.T, [-B, 0, 0], rtol=1e-12)
    with pytest.raises(InputError, match=r"calib\.txt: the file does not state the image size"):
        load_stereo_calibration(f, kitti_cameras=(0, 1))


def test_kitti_errors(tmp_path):
    f = tmp_path / "calib_cam_to_cam.txt"
    good = _kitti_cam_to_cam()
    f.write_text(_kitti_cam_to_cam(drop="P_rect_03"))
    with pytest.raises(InputError, match=r"calib_cam_to_cam\.txt: missing P_rect_03; a KITTI"):
        load_stereo_calibration(f)
    f.write_text(_kitti_cam_to_cam(drop="S_rect_02"))
    with pytest.raises(InputError, match=r"calib_cam_to_cam\.txt: missing S_rect_02"):
        load_stereo_calibration(f)
    f.write_text(good)
    with pytest.raises(InputError, match=r"camera 2 is not to the right of camera 3"):
        load_stereo_calibration(f, kitti_cameras=(3, 2))
    with pytest.raises(InputError, match=r"kitti_cameras: expected two different indices"):
        load_stereo_calibration(f, kitti_cameras=(2, 2))
    with pytest.raises(InputError, match=r"kitti_cameras: expected \(left, right\)"):
        load_stereo_calibration(f, kitti_cameras="ab")  # type: ignore[arg-type]
    p3 = "P_rect_03: 7.215377e+02"
    cases = [
        (good.replace(p3 + " 0.000000e+00", p3), r"P_rect_03: expected 12 values, got 11"),
        (good.replace(p3, "P_rect_03: x"), r"P_rect_03: expected a number, got 'x'"),
        (good.replace("4.485728e+01 0.000000e+00", "4.485728e+01 1.0"),
         r"P_rect_02 is not a rectified projection"),
        (good.replace("S_rect_03: 1.242000e+03", "S_rect_03: 1.241000e+03"),
         r"S_rect_02 \(1242, 375\) and S_rect_03 \(1241, 375\) differ"),
        (good.replace("corner_dist:", "corner_dist"), r"line 2: expected 'name:value'"),
    ]
    for text, msg in cases:
        f.write_text(text)
        with pytest.raises(InputError, match=r"calib_cam_to_cam\.txt: .*" + msg):
            load_stereo_calibration(f)


# -- ROS camera_info -------------------------------------------------------------------
def _ros_matrix(name: str, a: np.ndarray, fmt=repr, indent: str = "") -> str:
    a = np.atleast_2d(a)
    data = ", ".join(fmt(float(v)) for v in a.ravel())
    return (f"{indent}{name}:\n{indent}  rows: {a.shape[0]}\n{indent}  cols: {a.shape[1]}\n"
            f"{indent}  data: [{data}]\n")


def _ros_text(cam: CameraModel, R: np.ndarray, P: np.ndarray, name: str, fmt=repr,
              indent: str = "", model: str = "plumb_bob") -> str:
    """A camera_info YAML in the camera_calibration / camera_info_manager layout."""
    return (f"{indent}image_width: {cam.width}\n{indent}image_height: {cam.height}\n"
            f"{indent}camera_name: {name}\n"
            + _ros_matrix("camera_matrix", cam.K, fmt, indent)
            + f"{indent}distortion_model: {model}\n"
            + _ros_matrix("distortion_coefficients", cam.dist, fmt, indent)
            + _ros_matrix("rectification_matrix", R, fmt, indent)
            + _ros_matrix("projection_matrix", P, fmt, indent))


def _ros_pair(tmp_path: Path, rig: StereoRig, fmt=repr) -> tuple[Path, Path]:
    R1, R2, P1, P2, *_ = _stereo_rectify(rig, 1e-3)  # ROS files are in metres
    left, right = tmp_path / "left.yaml", tmp_path / "right.yaml"
    left.write_text(_ros_text(rig.left, R1, P1, "stereo/left", fmt))
    right.write_text(_ros_text(rig.right, R2, P2, "stereo/right", fmt))
    return left, right


def test_ros_pair_known_answer(tmp_path):
    rig = _rig()
    left, right = _ros_pair(tmp_path, rig)
    cal = load_stereo_calibration([left, right])
    assert cal.source_format == "ros"
    _assert_rig_close(cal.rig, rig, 1e-9)
    swapped = read_ros_camera_info([right, left])
    _assert_rig_close(swapped.rig, rig, 1e-9)
    assert any("swapped" in n for n in swapped.notes)


def test_ros_pair_printed_with_few_digits(tmp_path):
    rig = _rig()
    left, right = _ros_pair(tmp_path, rig, fmt=lambda v: f"{v:.6f}")
    cal = load_stereo_calibration([left, right])
    np.testing.assert_allclose(cal.rig.R, rig.R, atol=2e-6)
    np.testing.assert_allclose(cal.rig.T, rig.T, atol=0.01)


def test_ros_single_file_with_left_and_right(tmp_path):
    rig = _rig()
    R1, R2, P1, P2, *_ = _stereo_rectify(rig, 1e-3)
    f = tmp_path / "stereo.yaml"
    f.write_text("left:\n" + _ros_text(rig.left, R1, P1, "l", indent="  ")
                 + "right:\n" + _ros_text(rig.right, R2, P2, "r", indent="  "))
    _assert_rig_close(load_stereo_calibration(f).rig, rig, 1e-9)


def test_ros_errors(tmp_path):
    rig = _rig()
    left, right = _ros_pair(tmp_path, rig)
    with pytest.raises(InputError, match=r"left\.yaml \+ .*left\.yaml: both cameras have "
                                         r"P\[0,3\] == 0"):
        load_stereo_calibration([left, left])
    with pytest.raises(InputError, match=r"left\.yaml: holds one camera; give the left and"):
        load_stereo_calibration(left)
    R1, R2, P1, P2, *_ = _stereo_rectify(rig, 1e-3)
    small = tmp_path / "small.yaml"
    small.write_text(_ros_text(rig.right.with_size((320, 240)), R2, P2, "r"))
    with pytest.raises(InputError, match=r"image sizes differ \(.*left\.yaml: \(640, 480\), "
                                         r".*\(320, 240\)\)"):
        load_stereo_calibration([left, small])
    text = _ros_text(rig.right, R2, P2, "r")
    cases = [
        (_ros_text(rig.right, R2, P2, "r", model="equidistant"),
         r"distortion_model 'equidistant' is not supported"),
        (text.replace("data: [0.", "data: [x", 1),
         r"rectification_matrix: expected a number, got 'x"),
        (text.replace("  rows: 3\n  cols: 4", "  rows: 3\n  cols: 3"),
         r"projection_matrix: expected 3x4, got 3x3"),
        (_ros_text(rig.right, R2[:, :2], P2, "r").replace("cols: 2", "cols: 3"),
         r"rectification_matrix: expected 9 values \(3x3\), got 6"),
        (_ros_text(rig.right, R2 * 1.1, P2, "r"), r"rectification_matrix is not a rotation"),
        (_ros_text(rig.right, R2, np.zeros((3, 4)), "r"),
         r"projection_matrix is not a rectified projection"),
        (text.replace("image_width: 640\n", ""), r"missing image_width"),
        (text.replace("image_width: 640", "image_width: -640"),
         r"image_width: expected a positive integer"),
        (text.replace("image_width: 640", "image_width: true"),
         r"image_width: expected a number, got 'True'"),
        (re.sub(r"camera_matrix:\n(  .*\n){3}", "camera_matrix: abc\n", text),
         r"camera_matrix: expected a mapping with rows, cols and a data list"),
    ]
    bad = tmp_path / "bad.yaml"
    for content, msg in cases:
        bad.write_text(content)
        with pytest.raises(InputError, match=r"bad\.yaml: " + msg):
            load_stereo_calibration([left, bad])
    bad2 = tmp_path / "bad2.yaml"
    bad2.write_text(_ros_text(rig.right, R2, P2, "r"))
    with pytest.raises(InputError, match=r"neither camera is the reference \(left\) one"):
        read_ros_camera_info([right, bad2])
    two = tmp_path / "two.yaml"
    two.write_text("left:\n" + _ros_text(rig.left, R1, P1, "l", indent="  ")
                   + "right:\n" + _ros_text(rig.right, R2, P2, "r", indent="  "))
    with pytest.raises(InputError, match=r"two\.yaml: not a single camera_info file"):
        load_stereo_calibration([left, two])
    two.write_text("left: 3\nright:\n" + _ros_text(rig.right, R2, P2, "r", indent="  "))
    with pytest.raises(InputError, match=r"two\.yaml \(left\): expected a camera_info mapping"):
        load_stereo_calibration(two)


# -- files in general, dispatch and conversion -----------------------------------------
def test_bad_files(tmp_path):
    with pytest.raises(InputError, match=r"nope\.yaml: calibration file not found; check the"):
        load_stereo_calibration(tmp_path / "nope.yaml")
    with pytest.raises(InputError, match=r": is a directory or special file; give the calib"):
        load_stereo_calibration(tmp_path)
    (tmp_path / "empty.txt").write_text(" \n")
    with pytest.raises(InputError, match=r"empty\.txt: file is empty"):
        load_stereo_calibration(tmp_path / "empty.txt")
    (tmp_path / "bin.txt").write_bytes(b"cam0=[1 0 0; 0 1 0; 0 0 1]\n\xff\xfe\x00")
    with pytest.raises(InputError, match=r"bin\.txt: not a text file \(invalid UTF-8 at byte 27"):
        load_stereo_calibration(tmp_path / "bin.txt")
    (tmp_path / "notes.txt").write_text("hello: world\n")
    with pytest.raises(InputError, match=r"notes\.txt: not a stereo calibration format .*ROS"):
        load_stereo_calibration(tmp_path / "notes.txt")
    with pytest.raises(InputError, match=r"expected one or two files, got 3"):
        load_stereo_calibration([tmp_path / "a", tmp_path / "b", tmp_path / "c"])
    with pytest.raises(InputError, match=r"expected one or two files, got 0"):
        load_stereo_calibration([])
    with pytest.raises(InputError, match=r"expected one or two file paths"):
        load_stereo_calibration(3)  # type: ignore[arg-type]
    mb = tmp_path / "calib.txt"
    mb.write_text(_middlebury_text(_rectified_rig()))
    with pytest.raises(InputError, match=r"calib\.txt \(middlebury\) and .*calib\.txt "
                                         r"\(middlebury\): two files must be"):
        load_stereo_calibration([mb, mb])
    with pytest.raises(InputError, match=r"image_size: width and height must be > 0"):
        load_stereo_calibration(mb, image_size=(0, 10))
    with pytest.raises(InputError, match=r"image_size: expected \(width, height\)"):
        load_stereo_calibration(mb, image_size=(1, 2, 3))  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"calib\.txt: not an OpenCV FileStorage file"):
        read_opencv_calibration(mb)
    with pytest.raises(InputError, match=r"calib\.txt: not a ROS camera_info YAML"):
        read_ros_camera_info([mb, mb])


def test_stereo_calibration_checks():
    rig = _rectified_rig()
    with pytest.raises(InputError, match=r"source_format: expected one of prism3d, opencv"):
        StereoCalibration(rig, "zed")
    with pytest.raises(InputError, match=r"disparity_range: num_disp must be > 0"):
        StereoCalibration(rig, "middlebury", (0, 0))
    with pytest.raises(InputError, match=r"disparity_range: expected \(min_disp, num_disp\)"):
        StereoCalibration(rig, "middlebury", (0, 1, 2))  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"rig: expected a StereoRig"):
        StereoCalibration(None, "middlebury")  # type: ignore[arg-type]


def test_convert_round_trip(tmp_path):
    rig = _rectified_rig()
    src = tmp_path / "calib.txt"
    src.write_text(_middlebury_text(rig, "ndisp=290\n"))
    out = tmp_path / "out" / "rig.yaml"
    cal = convert_calibration(src, out)
    assert cal.source_format == "middlebury" and StereoRig.load(out) == rig
    back = load_stereo_calibration(out)
    assert back.source_format == "prism3d" and back.rig == rig
    assert back.disparity_range == (0, 290) and back.doffs == 37.25
    assert any("converted by prism3d from a middlebury" in n for n in back.notes)
    left, right = _ros_pair(tmp_path, _rig())
    convert_calibration([right, left], tmp_path / "ros.yml")
    _assert_rig_close(StereoRig.load(tmp_path / "ros.yml"), _rig(), 1e-9)


def test_convert_errors_write_nothing(tmp_path):
    src = tmp_path / "calib.txt"
    src.write_text(_middlebury_text(_rectified_rig()))
    with pytest.raises(InputError, match=r"rig\.json: the converted calibration must be a "
                                         r"\.yaml or \.yml file"):
        convert_calibration(src, tmp_path / "rig.json")
    yml = tmp_path / "rig.yaml"
    _rectified_rig().save(yml)
    before = yml.read_bytes()
    with pytest.raises(InputError, match=r"rig\.yaml: is also the input file"):
        convert_calibration(yml, yml)
    assert yml.read_bytes() == before
    (tmp_path / "d.yaml").mkdir()
    with pytest.raises(InputError, match=r"d\.yaml: is a directory; give the output file name"):
        convert_calibration(src, tmp_path / "d.yaml")
    src.write_text(_middlebury_text(_rectified_rig()).replace("=174.8125", "=0"))
    with pytest.raises(InputError, match=r"baseline must be > 0"):
        convert_calibration(src, tmp_path / "new.yaml")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.txt", "d.yaml", "rig.yaml"]


# -- real OpenCV sample files ----------------------------------------------------------
@pytest.mark.realdata
def test_real_opencv_stereo_intrinsics(shared_data, tmp_path):
    import cv2

    d = shared_data / "calibration" / "opencv_stereo_9x6"
    intr = d / "reference_stereo_intrinsics.yml"
    with pytest.raises(InputError, match=r"reference_stereo_intrinsics\.yml: holds intrinsics"):
        load_stereo_calibration(intr)
    # OpenCV ships no extrinsics.yml for this set: the test writes its own R, T
    R = cv2.Rodrigues(np.array([0.004, 0.011, -0.002]))[0]
    T = np.array([[-83.3], [0.8], [0.2]])
    extr = _write_fs(tmp_path / "extrinsics.yml", {"R": R, "T": T})
    with pytest.raises(InputError, match=r"does not state the image size; pass it"):
        load_stereo_calibration([intr, extr])
    cal = load_stereo_calibration([extr, intr], image_size=(640, 480))
    left, right = cal.rig.left, cal.rig.right
    assert cal.source_format == "opencv" and left.size == (640, 480)
    f = 5.3480326845051309e02
    assert (left.fx, left.fy, left.cx, left.cy) == (f, f, 3.3568643204394891e02,
                                                    2.4066183054066337e02)
    assert (right.fx, right.cx, right.cy) == (f, 3.3455744527912015e02, 2.4205324573376600e02)
    np.testing.assert_array_equal(left.dist, [2.9589439552724328e-01, -1.0354662043042675, 0, 0, 0])
    np.testing.assert_array_equal(right.dist,
                                  [-1.6916358306948096e-01, -1.1214173641213163e-01, 0, 0, 0])
    np.testing.assert_allclose(cal.rig.R, R, atol=1e-15)
    with pytest.raises(InputError, match=r"reference_left_intrinsics\.yml: is a single-camera"):
        load_stereo_calibration(d / "reference_left_intrinsics.yml")
    with pytest.raises(InputError, match=r"stereo_calib\.xml: has no stereo calibration entries "
                                         r"\(found imagelist\)"):
        load_stereo_calibration(d / "stereo_calib.xml")


def test_single_camera_calibration_opencv_and_ros(tmp_path: Path) -> None:
    """A survey camera's starting calibration: OpenCV's calibration output and a ROS
    camera_info, read to the same CameraModel; sizes checked against the frames."""
    import cv2

    from prism3d.capture.calib_formats import load_camera_calibration

    K = np.array([[2857.0, 0.0, 1999.5], [0.0, 2857.0, 1499.5], [0.0, 0.0, 1.0]])
    D = np.array([-0.02, 0.01, 0.0, 0.0, 0.0])
    fs = cv2.FileStorage(str(tmp_path / "cam.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 4000)
    fs.write("image_height", 3000)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", D.reshape(1, 5))
    fs.release()
    cam = load_camera_calibration(tmp_path / "cam.yaml")
    np.testing.assert_allclose(cam.K, K)
    np.testing.assert_allclose(cam.dist, D)
    assert cam.size == (4000, 3000)
    ros = tmp_path / "ros.yaml"
    ros.write_text(
        "image_width: 4000\nimage_height: 3000\ncamera_name: survey\n"
        f"camera_matrix: {{rows: 3, cols: 3, data: {K.ravel().tolist()}}}\n"
        "distortion_model: plumb_bob\n"
        f"distortion_coefficients: {{rows: 1, cols: 5, data: {D.tolist()}}}\n"
    )
    cam2 = load_camera_calibration(ros, image_size=(4000, 3000))
    np.testing.assert_allclose(cam2.K, K)
    np.testing.assert_allclose(cam2.dist, D)
    with pytest.raises(InputError, match="calibrated for 4000x3000 px, the frames are 1600x1200"):
        load_camera_calibration(tmp_path / "cam.yaml", image_size=(1600, 1200))
    fs = cv2.FileStorage(str(tmp_path / "nosize.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", K)
    fs.release()
    with pytest.raises(InputError, match="states no image size"):
        load_camera_calibration(tmp_path / "nosize.yaml")
    assert load_camera_calibration(tmp_path / "nosize.yaml", image_size=(4000, 3000)).size == (4000, 3000)
    with pytest.raises(InputError, match="not found"):
        load_camera_calibration(tmp_path / "absent.yaml")
