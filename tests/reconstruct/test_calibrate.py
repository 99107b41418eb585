"""Calibration: known-answer tests on the virtual paper rig (synthetic corners), on
rendered chessboard images, on Zhang's and OpenCV's real data, file round trips and
error branches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from prism3d.capture.rig import StereoRig, paper_rig
from prism3d.geometry import matrix_from_rotvec, rotation_angle_deg
from prism3d.reconstruct.stereo.calibrate import (
    Calibration,
    CalibrationOptions,
    calibrate_camera,
    calibrate_stereo,
    calibrate_stereo_points,
    calibrate_to_file,
    parse_board,
    rectification_residual,
)
from prism3d.reconstruct.stereo.corners import (
    board_object_points,
    detect_square_grid,
    grid_symmetries,
    load_image,
)

from prism3d.errors import CalibrationError, InputError

from .test_corners import board_pose, render_board, small_camera

# (tilt x, tilt y, in-plane, offset x, offset y) in the rig frame, board centre 1250 mm away
PAPER_POSES = [
    (0, 0, 0, 0, 0),
    (35, 20, 10, -15, -140),
    (-35, 20, -10, 15, -140),
    (20, -35, 80, -15, 140),
    (-20, -35, -80, 15, 140),
]


def paper_corners(rig: StereoRig, noise: float, seed: int = 0):
    obj = board_object_points((9, 6), 25.0)
    rng = np.random.default_rng(seed)
    L, R, Lt, Rt = [], [], [], []
    for ax, ay, az, ox, oy in PAPER_POSES:
        T = np.eye(4)
        T[:3, :3] = (
            matrix_from_rotvec(np.radians([ax, ay, 0.0])) @ matrix_from_rotvec(np.radians([0.0, 0.0, az]))
        )
        T[:3, 3] = np.array([ox, oy, 1250.0]) - T[:3, :3] @ np.array([100.0, 62.5, 0.0])
        for cam, Tc, noisy, true in (
            (rig.left, np.linalg.inv(rig.T_rig_left) @ T, L, Lt),
            (rig.right, np.linalg.inv(rig.T_rig_right) @ T, R, Rt),
        ):
            uv = cam.project(obj @ Tc[:3, :3].T + Tc[:3, 3])
            true.append(uv)
            noisy.append(uv + rng.normal(0.0, noise, uv.shape))
    return L, R, Lt, Rt


def test_paper_rig_exact_recovery_without_noise() -> None:
    rig = paper_rig()
    L, R, _, _ = paper_corners(rig, 0.0)
    cal = calibrate_stereo_points(L, R, rig.left.size)
    for est, ref in ((cal.rig.left, rig.left), (cal.rig.right, rig.right)):
        np.testing.assert_allclose(est.K, ref.K, rtol=1e-7, atol=1e-4)
        np.testing.assert_allclose(est.dist, ref.dist, atol=1e-6)
    np.testing.assert_allclose(cal.rig.T, rig.T, atol=1e-5)
    assert rotation_angle_deg(cal.rig.R @ rig.R.T) < 1e-6
    assert cal.rms_px < 1e-6 and cal.rectification_rms_px < 1e-6
    # the recovered rig frame matches the paper rig's (midway, z to convergence)
    np.testing.assert_allclose(cal.rig.T_rig_left, rig.T_rig_left, atol=1e-5)


def test_paper_rig_with_noise_k1k2_model() -> None:
    """The paper's model (k1 k2, no tangential): 5 poses, 0.1 px corner noise."""
    rig = paper_rig()
    L, R, Lt, Rt = paper_corners(rig, 0.1)
    cal = calibrate_stereo_points(L, R, rig.left.size, tangential=False)
    for est in (cal.rig.left, cal.rig.right):
        assert abs(est.fx / 5107.0 - 1) < 1e-3 and abs(est.fy / 5107.0 - 1) < 1e-3
        assert abs(est.cx - rig.left.cx) < 2.0 and abs(est.cy - rig.left.cy) < 2.0
        # k1 is weakly observable with a 200 mm board at f = 5107 px (std ~0.005)
        assert abs(est.dist[0] + 0.06) < 0.015
        assert est.dist[2] == 0.0 and est.dist[3] == 0.0
    assert abs(cal.rig.baseline_mm / rig.baseline_mm - 1) < 1e-3
    assert rotation_angle_deg(cal.rig.R @ rig.R.T) < 0.02
    # residual of detected (noisy) corners is at the noise floor (sqrt(2) * 0.1)
    assert 0.1 < cal.rectification_rms_px < 0.17
    # the calibration itself rectifies the true corners to within 0.05 px
    assert rectification_residual(cal.rig, Lt, Rt) < 0.05
    assert 0.1 < cal.rms_px < 0.16 and cal.n_views == 5 and cal.outlier_views == ()
    # standard deviations are meaningful: the errors are within ~3 sigma
    assert 0 < cal.std["fx_left"] < 10
    assert abs(cal.rig.left.fx - 5107.0) < 4 * cal.std["fx_left"] + 1e-9
    assert abs(cal.rig.baseline_mm - 197.9) < 4 * np.linalg.norm([cal.std["tx"], cal.std["tz"]])


#: Corner noise (px, per coordinate) of the X-junction detector on the virtual rig's
#: rendered calibration shots: 0.019 px RMS (2D) against the true corners for the 9x6
#: board of 25 mm squares (~100 px); 0.017-0.026 px (2D) for the 19x13 board of
#: 12 mm squares (~49 px, a smaller fit window; seeds 0-2), taken as 0.02 per coordinate.
SIM_CORNER_NOISE = {(9, 6): 0.0134, (19, 13): 0.02}
SQUARE_MM = {(9, 6): 25.0, (19, 13): 12.0}


def _simulator_pose_corners(board, noise_seed, pose_seed=0):
    from prism3d.capture.scenes import BoardPoseOptions, calibration_board_poses

    rig = paper_rig()
    sq = SQUARE_MM[board]
    obj = board_object_points(board, sq)
    rng = np.random.default_rng(noise_seed)
    L, R, Lt, Rt = [], [], [], []
    for T in calibration_board_poses(
        rig, 5, options=BoardPoseOptions(cols=board[0], rows=board[1], square_mm=sq, seed=pose_seed)
    ):
        for cam, T_cam_rig, noisy, true in (
            (rig.left, np.linalg.inv(rig.T_rig_left), L, Lt),
            (rig.right, np.linalg.inv(rig.T_rig_right), R, Rt),
        ):
            Tc = T_cam_rig @ T
            uv = cam.project(obj @ Tc[:3, :3].T + Tc[:3, 3])
            true.append(uv)
            noisy.append(uv + rng.normal(0.0, SIM_CORNER_NOISE[board], uv.shape))
    cal = calibrate_stereo_points(L, R, rig.left.size, board=board, square_mm=sq, tangential=False)
    return rig, cal, Lt, Rt


def _check_targets_except_principal_point(rig, cal, Lt, Rt):
    for est, ref in ((cal.rig.left, rig.left), (cal.rig.right, rig.right)):
        assert abs(est.fx / ref.fx - 1) < 1e-3 and abs(est.fy / ref.fy - 1) < 1e-3
        assert abs(est.dist[0] - ref.dist[0]) < 0.005
    assert abs(cal.rig.baseline_mm / rig.baseline_mm - 1) < 1e-3
    assert rotation_angle_deg(cal.rig.R @ rig.R.T) < 0.02
    assert cal.rectification_rms_px < 0.05
    assert rectification_residual(cal.rig, Lt, Rt) < 0.01


def _pp_errors(rig, cal):
    return {
        f"{c}_{side}": getattr(e, c) - getattr(r, c)
        for side, e, r in (("left", cal.rig.left, rig.left), ("right", cal.rig.right, rig.right))
        for c in ("cx", "cy")
    }


@pytest.mark.parametrize("pose_seed,noise_seed", [(0, 0), (0, 1), (1, 2), (2, 3), (3, 4)])
def test_virtual_rig_targets_dense_board(pose_seed: int, noise_seed: int) -> None:
    """Issue target (a), all of it, on the simulator's poses with the detector's noise:
    5 poses of the 19x13 board (the demo's) pin cx, cy to within 1 px."""
    rig, cal, Lt, Rt = _simulator_pose_corners((19, 13), noise_seed, pose_seed)
    _check_targets_except_principal_point(rig, cal, Lt, Rt)
    err = _pp_errors(rig, cal)
    assert max(abs(v) for v in err.values()) < 1.0, err
    assert max(cal.std[k] for k in err) < 0.5


@pytest.mark.parametrize("noise_seed", [0, 1])
def test_virtual_rig_9x6_board_principal_point_is_weak(noise_seed: int) -> None:
    """With 54 corners per view the principal point is weakly determined at f = 5107 px:
    its standard deviation is ~0.6 px (OpenCV's calibrateCameraExtended reports
    0.9-1.4 px for one camera on the same corners), so 1 px is met only by chance.
    Every other target holds, and the reported standard deviations are honest."""
    rig, cal, Lt, Rt = _simulator_pose_corners((9, 6), noise_seed)
    _check_targets_except_principal_point(rig, cal, Lt, Rt)
    err = _pp_errors(rig, cal)
    assert 0.4 < max(cal.std[k] for k in err) < 0.9
    for k, v in err.items():
        assert abs(v) < 4 * cal.std[k], (k, v, cal.std[k])


def test_paper_rig_default_model_and_outlier_flag() -> None:
    rig = paper_rig()
    L, R, _, _ = paper_corners(rig, 0.1, seed=3)
    R[2] = R[2] + np.random.default_rng(5).normal(0, 1.5, R[2].shape)  # a bad view
    cal = calibrate_stereo_points(L, R, rig.left.size)
    assert cal.flags == {"skew": False, "tangential": True, "k3": False}
    assert cal.outlier_views == (2,)
    assert cal.per_view_rms_px.shape == (5, 2) and cal.per_view_rms_px[2, 1] > 1.0
    assert abs(cal.rig.baseline_mm / rig.baseline_mm - 1) < 5e-3
    assert "outlier" in cal.summary()


def test_inconsistent_corner_order_is_corrected() -> None:
    rig = paper_rig()
    L, R, _, _ = paper_corners(rig, 0.05)
    R_bad = list(R)
    R_bad[1] = R[1][::-1]  # board reported upside down in one view only
    R_bad[3] = R[3].reshape(6, 9, 2)[::-1].reshape(-1, 2)  # rows reversed (seen from behind)
    ref = calibrate_stereo_points(L, R, rig.left.size)
    cal = calibrate_stereo_points(L, R_bad, rig.left.size)
    assert cal.n_views == 5
    assert abs(cal.rms_px - ref.rms_px) < 1e-6
    np.testing.assert_allclose(cal.rig.T, ref.rig.T, atol=1e-6)


def test_single_camera_skew_recovery() -> None:
    cam0 = small_camera(dist=(-0.2, 0.1, 0.001, -0.0005, 0.0))
    K = cam0.K.copy()
    K[0, 1] = 0.8
    from prism3d.capture.rig import CameraModel

    cam = CameraModel(K, cam0.dist, cam0.size)
    obj = board_object_points((9, 6), 25.0)
    poses = [
        board_pose(a, 450.0, s)
        for a, s in (
            ((0, 0, 0), (0, 0)),
            ((30, 0, 5), (40, 20)),
            ((-25, 20, -5), (-40, -20)),
            ((10, -30, 90), (30, -30)),
        )
    ]
    img = [cam.project(obj @ T[:3, :3].T + T[:3, 3]) for T in poses]
    res = calibrate_camera([obj] * 4, img, cam.size, skew=True)
    np.testing.assert_allclose(res.camera.K, K, atol=1e-5)
    np.testing.assert_allclose(res.camera.dist, cam.dist, atol=1e-8)
    assert res.rms_px < 1e-6 and res.per_view_rms_px.shape == (4,)
    np.testing.assert_allclose(res.T_cam_board, np.stack(poses), atol=1e-5)
    res0 = calibrate_camera([obj] * 4, img, cam.size)  # skew off: K[0, 1] stays 0
    assert res0.camera.skew == 0.0 and res0.std["skew"] == 0.0 and res0.rms_px > 1e-3


def test_calibrate_stereo_from_rendered_images(tmp_path: Path) -> None:
    """End to end on rendered pairs (pairs mode, files), then save/load."""
    import cv2

    cam = small_camera(480, 360, 520.0)
    T_rl = np.eye(4)
    T_rl[:3, :3] = matrix_from_rotvec(np.radians([0.0, -4.0, 0.5]))
    T_rl[:3, 3] = [-60.0, 0.5, 2.0]
    images = []
    poses = [
        ((0, 0, 0), (20, 0)),
        ((30, 10, 5), (30, 15)),
        ((-30, 15, -5), (20, -15)),
        ((10, -30, 90), (30, 0)),
    ]
    for i, (a, s) in enumerate(poses):
        T = board_pose(a, 420.0, s)
        for side, Tc in (("left", T), ("right", T_rl @ T)):
            img, _ = render_board(cam, Tc, ss=2, seed=i)
            p = tmp_path / f"{side}{i}.png"
            cv2.imwrite(str(p), img)
            images.append(p)
    calls = []
    n_threads = cv2.getNumThreads()
    cal = calibrate_stereo(images, options=CalibrationOptions(pairs=True), progress=lambda d, n: calls.append((d, n)))
    assert calls[-1] == (4, 4)
    # reproducible to the last bit (OpenCV runs single-threaded inside, then is restored)
    assert cv2.getNumThreads() == n_threads
    again = calibrate_stereo(images, options=CalibrationOptions(pairs=True))
    assert again.rig == cal.rig and again.rms_px == cal.rms_px
    assert cal.rms_px < 0.25 and cal.rectification_rms_px < 0.25
    np.testing.assert_allclose(cal.rig.T, T_rl[:3, 3], atol=1.5)
    assert abs(cal.rig.baseline_mm - np.linalg.norm(T_rl[:3, 3])) < 0.5
    # 4 small rendered views (ss=2 box-filter renders: ~0.1-0.25 px corner bias): loose
    assert rotation_angle_deg(cal.rig.R @ T_rl[:3, :3].T) < 0.6
    assert abs(cal.rig.left.fx / 520.0 - 1) < 0.01
    assert len(cal.detections) == 8 and all(d.found for d in cal.detections)

    out = tmp_path / "calib.yaml"
    cal.save(out)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("K1").mat(), cal.rig.left.K)
    assert fs.getNode("rms_px").real() == pytest.approx(cal.rms_px)
    assert fs.getNode("std_K1").mat().shape == (5, 1)
    fs.release()
    back = Calibration.load(out)
    assert back.rig == cal.rig
    # the pinning check's figures and warnings are not stored
    assert cal.precision and back.precision == {} and back.needs == {} and back.warnings == ()
    assert back.rms_px == pytest.approx(cal.rms_px)
    assert back.std["fx_left"] == pytest.approx(cal.std["fx_left"])
    assert back.flags == cal.flags and back.board == (9, 6) and back.n_views == 4
    np.testing.assert_allclose(back.per_view_rms_px, cal.per_view_rms_px)
    assert "RMS reprojection error" in back.summary()


def test_load_plain_rig_yaml(tmp_path: Path) -> None:
    rig = paper_rig()
    p = tmp_path / "rig.yaml"
    rig.save(p)
    cal = Calibration.load(p)
    assert cal.rig == rig and np.isnan(cal.rms_px) and cal.std == {} and cal.n_views == 0
    # and a calibration file is a valid rig file
    q = tmp_path / "calib.yaml"
    Calibration(rig=rig, rms_px=0.1, n_views=3, board=(9, 6), square_mm=25.0).save(q)
    assert StereoRig.load(q) == rig


@pytest.mark.realdata
def test_zhang_corner_data(shared_data: Path) -> None:
    d = shared_data / "calibration" / "zhang_5views"
    m = np.loadtxt(d / "Model.txt").reshape(-1, 2)
    obj = np.c_[m, np.zeros(len(m))]
    img = [np.loadtxt(d / f"data{i}.txt").reshape(-1, 2) for i in range(1, 6)]
    res = calibrate_camera([obj] * 5, img, (640, 480), skew=True, tangential=False)
    K = res.camera.K
    # Zhang's published values: alpha 832.5, gamma 0.2045, beta 832.53, u0 303.959, v0 206.585
    assert abs(K[0, 0] / 832.5 - 1) < 1e-4 and abs(K[1, 1] / 832.53 - 1) < 1e-4
    assert abs(K[0, 1] - 0.2045) < 0.01
    assert abs(K[0, 2] - 303.959) < 0.05 and abs(K[1, 2] - 206.585) < 0.05
    assert abs(res.camera.dist[0] + 0.228601) < 1e-3 and abs(res.camera.dist[1] - 0.190353) < 2e-3
    assert res.rms_px == pytest.approx(0.336, abs=0.005)


@pytest.mark.realdata
def test_zhang_images_square_detector(shared_data: Path) -> None:
    d = shared_data / "calibration" / "zhang_5views"
    m = np.loadtxt(d / "Model.txt").reshape(-1, 2)
    obj = np.c_[m, np.zeros(len(m))]
    pts = []
    for i in range(1, 6):
        c = detect_square_grid(load_image(d / f"CalibIm{i}.png"), (8, 8))
        assert c is not None and c.shape == (256, 2)
        c = c.reshape(8, 8, 4, 2)[::-1].reshape(-1, 2)  # Model.txt rows start at the image bottom
        ref = np.loadtxt(d / f"data{i}.txt").reshape(-1, 2)
        assert np.sqrt(np.mean(np.sum((c - ref) ** 2, axis=1))) < 0.4  # measured 0.25-0.33
        pts.append(c)
    res = calibrate_camera([obj] * 5, pts, (640, 480), skew=True, tangential=False)
    # measured: 831.43, 831.79, k1 -0.2299 (Zhang: 832.5, 832.53, -0.2286)
    assert abs(res.camera.fx / 832.5 - 1) < 0.005 and abs(res.camera.fy / 832.53 - 1) < 0.005
    assert abs(res.camera.dist[0] + 0.2286) < 0.01
    assert res.rms_px < 0.45
    assert detect_square_grid(np.full((480, 640), 200, np.uint8)) is None


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_simulated_calibration_shots(tmp_path: Path, seed: int) -> None:
    """Issue target (a) end to end: the virtual rig's 5 rendered calibration shots
    (``prism3d simulate calib --board 19x13 --square 12``, noise on; ~1 min per seed),
    the paper's k1 k2 model. Measured (seeds 0, 1, 2): cx, cy within 0.32 px, fx
    within 0.007 %, baseline within 0.004 %, rotation within 0.003 deg."""
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder

    board, sq = (19, 13), 12.0
    simulate_to_folder("calib", tmp_path, SimulateOptions(seed=seed, noise=True, board=board, square_mm=sq))
    rig = StereoRig.load(tmp_path / "rig.yaml")
    images = sorted(tmp_path.glob("calib_*.png"))
    truth = [np.load(p, allow_pickle=False) for p in sorted(tmp_path.glob("truth_*.npz"))]
    cal = calibrate_stereo(images, options=CalibrationOptions(board=board, square_mm=sq, tangential=False))
    assert cal.n_views == len(images) == 5
    for est, ref in ((cal.rig.left, rig.left), (cal.rig.right, rig.right)):
        assert abs(est.fx / ref.fx - 1) < 1e-3 and abs(est.fy / ref.fy - 1) < 1e-3
        assert abs(est.dist[0] - ref.dist[0]) < 0.005
        assert abs(est.cx - ref.cx) < 1.0 and abs(est.cy - ref.cy) < 1.0
    assert abs(cal.rig.baseline_mm / rig.baseline_mm - 1) < 1e-3
    assert rotation_angle_deg(cal.rig.R @ rig.R.T) < 0.02
    assert cal.rms_px < 0.04
    assert cal.rectification_rms_px < 0.05
    true_l = [t["corners_left"] for t in truth]
    true_r = [t["corners_right"] for t in truth]
    assert rectification_residual(cal.rig, true_l, true_r) < 0.02
    # the detected corners against the truth (X-junction fit)
    err = []
    true_views = [x for tr in truth for x in (tr["corners_left"], tr["corners_right"])]
    for det, tv in zip(cal.detections, true_views, strict=True):
        err.append(min(np.mean(np.sum((det.corners[p] - tv) ** 2, axis=1)) for p in grid_symmetries(board)))
    corner_rms = float(np.sqrt(np.mean(err)))
    # SIM_CORNER_NOISE (per coordinate) used by the fast tests is not optimistic
    assert corner_rms < np.sqrt(2) * SIM_CORNER_NOISE[board]


@pytest.mark.realdata
def test_opencv_stereo_set(shared_data: Path) -> None:
    """Issue target (b) on OpenCV's real 9x6 stereo set (13 pairs, 640x480)."""
    d = shared_data / "calibration" / "opencv_stereo_9x6"
    images = []
    for i in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14):
        images += [d / f"left{i:02d}.jpg", d / f"right{i:02d}.jpg"]
    cal = calibrate_stereo(images, options=CalibrationOptions(pairs=True))  # default model: k1 k2 p1 p2
    assert cal.n_views == 13 and all(dt.found for dt in cal.detections)
    assert abs(cal.rig.baseline_mm - 83.2) < 0.3
    # vertical disparity of the detected corners after rectification: measured 0.095
    assert cal.rectification_rms_px <= 0.1
    assert cal.rms_left_px < 0.2 and cal.rms_right_px < 0.2  # measured 0.172 / 0.168
    # The set does not pin the rig at its working distance (310 mm; measured rows 0.55 px,
    # disparity 0.64 px = 1.38 mm, 1 sigma): the worst points are the image corners, where
    # the strong distortion (k1 -0.29) is extrapolated -- no corner within ~150 px of the
    # left view's left edge or the right view's right edge.
    pr = cal.precision
    assert 300 < pr["working_distance_mm"] < 320
    assert pr["row_offset_px"] > 0.3 and pr["disparity_px"] > 0.3
    assert cal.warnings[0].startswith("the 13 shots do not pin the rig")
    groups = [w.split(":")[0] for w in cal.warnings[1:]]
    assert {"focal length", "distortion", "rig translation"} <= set(groups)
    assert groups[-1] == "image regions without corners"
    left, right = cal.warnings[-1].split("; ")
    assert "left edge" in left and left.endswith("left view")
    assert "right edge" in right and right.endswith("right view")
    for k in ("k1_left", "k2_left", "k1_right", "k2_right", "fx_left", "fy_right"):
        assert cal.std[k] > 2 * cal.needs[k], (k, cal.std[k], cal.needs[k])
    # the paper's model (k1 k2): joint adjustment measured 0.181 / 0.174, rectification 0.137
    k12 = calibrate_stereo_points(
        [dt.corners for dt in cal.detections if dt.view == "left"],
        [dt.corners for dt in cal.detections if dt.view == "right"],
        (640, 480),
        tangential=False,
    )
    assert k12.rms_left_px <= 0.2 and k12.rms_right_px <= 0.2
    assert abs(k12.rig.baseline_mm - 83.2) < 0.3
    # each camera on its own (the shipped reference file has RMS 0.39): measured 0.164 / 0.156
    obj = board_object_points((9, 6), 25.0)
    for side in ("left", "right"):
        pts = [dt.corners for dt in cal.detections if dt.view == side]
        res = calibrate_camera([obj] * len(pts), pts, (640, 480), tangential=False)
        assert res.rms_px <= 0.2


# --------------------------------------------------------------------------------------
# does a set of shots pin the rig? (Calibration.precision / needs / warnings)
# --------------------------------------------------------------------------------------
#: Corner noise (px per coordinate) that reproduces the fit residual of the rendered 19x13
#: shots of ``prism3d simulate calib --board 19x13 --square 12 --seed 7`` (RMS 0.047 px over
#: both coordinates): with it the default model's standard deviations match the CLI's on
#: those renders (cx 0.83 / 0.87, cy 1.13 / 1.22 px against 0.85 / 0.89, 1.15 / 1.24).
SEED7_RESIDUAL_NOISE = 0.033


def _board_corners(poses, noise: float, seed: int, board=(19, 13)):
    """Corners of the board at ``T_rig_board`` poses in both views of the paper rig (the
    whole board inside each view), with Gaussian noise."""
    rig = paper_rig()
    obj = board_object_points(board, SQUARE_MM[board])
    rng = np.random.default_rng(seed)
    L, R = [], []
    for T in poses:
        for cam, T_rig_cam, out in ((rig.left, rig.T_rig_left, L), (rig.right, rig.T_rig_right, R)):
            Tc = np.linalg.inv(T_rig_cam) @ T
            uv = cam.project(obj @ Tc[:3, :3].T + Tc[:3, 3])
            assert uv.min() >= 0 and np.all(uv <= np.array(cam.size) - 1)
            out.append(uv + rng.normal(0.0, noise, uv.shape))
    return rig, L, R


def _seed7_poses():
    from prism3d.capture.scenes import BoardPoseOptions, calibration_board_poses

    return calibration_board_poses(paper_rig(), 5, options=BoardPoseOptions(cols=19, rows=13, square_mm=12.0, seed=7))


def test_five_shots_do_not_pin_the_rig(caplog) -> None:
    """The 5 poses of the seed-7 simulated set: the check warns that rows and disparities
    are not pinned to the matcher's precision at the working distance and names what is
    loose -- the focal lengths (every board is tilted the same way about the vertical
    axis), k1 k2 and tz -- and the image regions without corners. The principal point is
    poorly known (std 0.83-1.22 px) but not named: the rig rotation absorbs its error
    (its needs are 1.8-4.9 px). Measured with the CLI on the renders: rows 0.13 px,
    disparity 0.13 px = 0.21 mm; the same warnings."""
    import logging

    rig, L, R = _board_corners(_seed7_poses(), SEED7_RESIDUAL_NOISE, 0)
    with caplog.at_level(logging.WARNING, logger="prism3d.reconstruct.stereo.calibrate"):
        cal = calibrate_stereo_points(L, R, rig.left.size, board=(19, 13), square_mm=12.0)
    pr = cal.precision
    assert 1250 < pr["working_distance_mm"] < 1300  # measured 1273
    assert 0.1 < pr["row_offset_px"] < 0.15 and 0.1 < pr["disparity_px"] < 0.15  # 0.121, 0.125
    assert pr["depth_mm"] == pytest.approx(
        pr["disparity_px"] * pr["working_distance_mm"] ** 2 / (rig.left.fy * cal.rig.baseline_mm), rel=1e-3)
    w = cal.warnings
    assert w[0].startswith("the 5 shots do not pin the rig to what stereo matching needs at the working "
                           "distance (1273 mm): rectified rows may be 0.12 px apart (needs <= 0.1 px) and "
                           "disparities off by 0.12 px = 0.20 mm of depth"), w[0]
    assert [x.split(":")[0] for x in w[1:]] == [
        "focal length", "distortion", "rig translation", "image regions without corners"], w
    assert "fx left ±0.53 px (needs <= 0.31 px)" in w[1]
    assert "add shots tilted 20-40 deg about the vertical axis, both ways (now +1..+19 deg)" in w[1]
    assert "k2 left ±0.059 (needs <= 0.042)" in w[2] and "in the image regions that have none" in w[2]
    assert "tz ±0.1 mm" in w[3] and "place boards nearer and farther (now 1170-1379 mm)" in w[3]
    assert w[4] == ("image regions without corners: the upper-left corner, top edge, upper-right corner and "
                    "lower-left corner of the left view; the upper-left corner, top edge, upper-right corner, "
                    "left edge and lower-left corner of the right view")
    for k in ("cx_left", "cy_left", "cx_right", "cy_right"):
        assert 0.8 < cal.std[k] < cal.needs[k], (k, cal.std[k], cal.needs[k])
    for k in ("fx_left", "k2_right", "tz"):
        assert cal.std[k] > cal.needs[k]
    assert [r.getMessage() for r in caplog.records] == list(w)
    assert "precision at the working distance (1273 mm" in cal.summary()


def test_pinning_precision_is_honest() -> None:
    """Known answer: over 8 noise draws of the seed-7 set, the rows' and disparities' actual
    errors against the true rig (RMS over the draws, worst grid point) match the predicted
    standard deviations (measured 0.117 / 0.158 px against 0.123 / 0.126; over 40 draws
    0.127 / 0.125). Putting the true principal point into each calibration, the rest
    unchanged, makes them 8-10x worse (1.2 px): its error is compensated by the others,
    which is why it is not named."""
    from prism3d.reconstruct.stereo.calibrate import _cam_vector, _pose_vec
    from prism3d.reconstruct.stereo.calibration_pinning import _check_pixels, _stereo_errors

    def vec(r):
        return np.concatenate([_cam_vector(r.left.K, r.left.dist), _cam_vector(r.right.K, r.right.dist),
                               _pose_vec(r.T_right_left)])

    truth = paper_rig()
    uv_l, uv_r = _check_pixels(truth, 1273.0)
    m = len(uv_l)
    args = (truth.left.size, truth.split, uv_l, uv_r, truth.left.fy, truth.baseline_mm)
    p_true = vec(truth)
    q_true = _stereo_errors(p_true, *args)
    err, err_pp, predicted = [], [], []
    for seed in range(8):
        _, L, R = _board_corners(_seed7_poses(), SEED7_RESIDUAL_NOISE, seed)
        cal = calibrate_stereo_points(L, R, truth.left.size, board=(19, 13), square_mm=12.0)
        p = vec(cal.rig)
        err.append(_stereo_errors(p, *args) - q_true)
        p[[2, 3, 12, 13]] = p_true[[2, 3, 12, 13]]  # cx, cy of both cameras
        err_pp.append(_stereo_errors(p, *args) - q_true)
        predicted.append((cal.precision["row_offset_px"], cal.precision["disparity_px"]))
    rms = np.sqrt(np.mean(np.square(err), axis=0))
    ratio = np.array([rms[:m].max(), rms[m:].max()]) / np.mean(predicted, axis=0)
    assert np.all((0.6 < ratio) & (ratio < 1.5)), ratio
    rms_pp = np.sqrt(np.mean(np.square(err_pp), axis=0))
    assert rms_pp[m:].max() > 4 * rms[m:].max() and rms_pp[:m].max() > 4 * rms[:m].max()


def test_well_posed_shots_give_no_warning() -> None:
    """18 shots of the same board with the same noise, tilted both ways about both axes,
    reaching into every image corner, at two distances: rows 0.017 px and disparity
    0.042 px (1 sigma), nothing to warn about."""
    centre = board_object_points((19, 13), 12.0).mean(axis=0)
    tilts = [(0, 0), (30, 0), (-30, 0), (0, 30), (0, -30), (25, 25), (-25, 25), (25, -25), (-25, -25)]
    offsets = [(0, 0), (-50, -95), (50, -95), (-50, 95), (50, 95), (-50, 0), (50, 0), (0, -95), (0, 95)]
    poses = []
    for rep, z in enumerate((1250.0, 1150.0)):
        for i, (ox, oy) in enumerate(offsets):
            ax, ay = tilts[(i + 3 * rep) % 9]
            T = np.eye(4)
            T[:3, :3] = matrix_from_rotvec(np.radians([ax, ay, 0.0])) @ matrix_from_rotvec(np.radians([0.0, 0.0, 90.0]))
            T[:3, 3] = np.array([ox * z / 1250.0, oy * z / 1250.0, z]) - T[:3, :3] @ centre
            poses.append(T)
    rig, L, R = _board_corners(poses, SEED7_RESIDUAL_NOISE, 0)
    cal = calibrate_stereo_points(L, R, rig.left.size, board=(19, 13), square_mm=12.0)
    assert cal.warnings == ()
    assert cal.precision["row_offset_px"] < 0.05 and cal.precision["disparity_px"] < 0.05  # 0.017, 0.042
    assert all(cal.std[k] <= cal.needs[k] for k in cal.needs if k in cal.std)


def test_pinning_not_checked_without_common_pixels(monkeypatch, caplog) -> None:
    """When the views share (almost) no pixels at the boards' distance there is nothing to
    check: no figures, no warnings, a note in the log."""
    import logging

    import prism3d.reconstruct.stereo.calibration_pinning as pinning

    monkeypatch.setattr(pinning, "_check_pixels", lambda rig, depth: (np.zeros((2, 2)), np.zeros((2, 2))))
    rig, L, R = _board_corners(_seed7_poses(), SEED7_RESIDUAL_NOISE, 0)
    with caplog.at_level(logging.INFO, logger="prism3d.reconstruct.stereo.calibrate"):
        cal = calibrate_stereo_points(L, R, rig.left.size, board=(19, 13), square_mm=12.0)
    assert cal.precision == {} and cal.needs == {} and cal.warnings == ()
    assert any("precision not checked: the views share too few pixels" in m for m in caplog.messages)
    assert "precision at the working distance" not in cal.summary()


def test_cli_prints_calibration_warnings_once(monkeypatch, capsys, caplog, tmp_path) -> None:
    """`prism3d calibrate` prints each warning as one `warning:` line on stderr, also with
    --quiet; logging does not repeat them, and other log records still pass."""
    import logging

    import prism3d.reconstruct.stereo.calibrate as calibrate
    from prism3d.cli import main

    msg = "focal length: fx left ±0.53 px (needs <= 0.31 px): add shots"

    def fake_calibrate_to_file(images, out, **kwargs):
        lib = logging.getLogger("prism3d.reconstruct.stereo.calibrate")
        lib.warning("%s", msg, extra={"prism3d_calibration_warning": True})
        lib.warning("view 3: right view dropped")
        return Calibration(rig=paper_rig(), warnings=(msg,))

    monkeypatch.setattr(calibrate, "calibrate_to_file", fake_calibrate_to_file)
    for quiet in (["--quiet"], []):
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            assert main([*quiet, "calibrate", str(tmp_path / "a.png"), "-o", str(tmp_path / "c.yaml")]) == 0
        out, err = capsys.readouterr()
        assert err == f"warning: {msg}\n"
        assert ("wrote" in out) != bool(quiet)
        assert caplog.messages == ["view 3: right view dropped"]
    assert not logging.getLogger("prism3d.reconstruct.stereo.calibrate").filters


def test_errors(tmp_path: Path) -> None:
    rig = paper_rig()
    L, R, _, _ = paper_corners(rig, 0.0)
    with pytest.raises(CalibrationError, match="at least 3 shots"):
        calibrate_stereo_points(L[:2], R[:2], rig.left.size)
    with pytest.raises(CalibrationError, match="at least 3 shots, got 2"):
        calibrate_stereo_points(L[:3], [R[0], R[1], None], rig.left.size)
    with pytest.raises(InputError, match="same length"):
        calibrate_stereo_points(L, R[:4], rig.left.size)
    with pytest.raises(InputError, match=r"right_points\[0\]: expected 54 corners"):
        calibrate_stereo_points(L, [R[0][:10]] + R[1:], rig.left.size)
    with pytest.raises(InputError, match="square_mm"):
        calibrate_stereo_points(L, R, rig.left.size, square_mm=0)
    obj = board_object_points((9, 6), 25.0)
    with pytest.raises(CalibrationError, match="at least 3 views"):
        calibrate_camera([obj] * 2, L[:2], rig.left.size)
    with pytest.raises(InputError, match="same length"):
        calibrate_camera([obj] * 3, L[:2], rig.left.size)
    with pytest.raises(InputError, match="view 0: 54 object points but 10"):
        calibrate_camera([obj] * 3, [L[0][:10], L[1], L[2]], rig.left.size)
    with pytest.raises(InputError, match=r"image_points_list\[0\]: expected finite"):
        calibrate_camera([obj] * 3, [L[0] * np.nan, L[1], L[2]], rig.left.size)
    with pytest.raises(InputError, match=r"object_points_list\[0\]: expected \(N >= 4, 3\)"):
        calibrate_camera([obj[:, :2]] * 3, L[:3], rig.left.size)
    with pytest.raises(InputError, match="image_size"):
        calibrate_camera([obj] * 3, L[:3], (0, 10))

    # image-level errors, and no output written
    PAIRS = CalibrationOptions(pairs=True)
    blank = np.full((360, 480), 128, np.uint8)
    cam = small_camera(480, 360, 520.0)
    board_img, _ = render_board(cam, board_pose((0, 0, 0), 420.0, (20, 0)), ss=2)
    with pytest.raises(CalibrationError, match="no 9x6 chessboard found in any image"):
        calibrate_stereo([blank, blank, blank, blank], options=PAIRS)
    with pytest.raises(CalibrationError, match=r"no 9x6 chessboard found in <array 2> / <array 3>"):
        calibrate_stereo([board_img, board_img, blank, blank], options=PAIRS)
    with pytest.raises(CalibrationError, match="no 8x6 chessboard found in any image"):
        calibrate_stereo([board_img, board_img], options=CalibrationOptions(pairs=True, board=(8, 6)))
    with pytest.raises(CalibrationError, match="at least 3 shots, got 1"):
        calibrate_stereo([board_img, board_img], options=PAIRS)
    with pytest.raises(InputError, match="same size"):
        calibrate_stereo([board_img, board_img[:, :400]], options=PAIRS)
    with pytest.raises(InputError, match="not found"):
        calibrate_stereo([tmp_path / "nope.png", tmp_path / "nope2.png"], options=PAIRS)
    assert list(tmp_path.iterdir()) == []


def test_calibration_options_validation() -> None:
    assert CalibrationOptions().board == (9, 6) and CalibrationOptions().tangential
    with pytest.raises(InputError, match="square_mm: expected a finite number > 0"):
        CalibrationOptions(square_mm=0)
    with pytest.raises(InputError, match="method: expected one of xjunction, classic, sb"):
        CalibrationOptions(method="harris")
    with pytest.raises(InputError, match="window: expected a half-window >= 1 pixel"):
        CalibrationOptions(window=0)
    with pytest.raises(InputError, match="split: expected a PrismSplit"):
        CalibrationOptions(split=(1, 2))
    with pytest.raises(InputError, match="options: expected CalibrationOptions"):
        calibrate_stereo([], options={"pairs": True})


def test_calibrate_to_file_and_parse_board(tmp_path: Path) -> None:
    assert parse_board("9x6") == (9, 6) and parse_board("7X7") == (7, 7)
    with pytest.raises(InputError, match="COLSxROWS"):
        parse_board("nine")
    with pytest.raises(InputError, match="at least 2x2"):
        parse_board("1x6")
    with pytest.raises(InputError, match="must end in .yaml"):
        calibrate_to_file([], tmp_path / "calib.txt")
    (tmp_path / "d.yaml").mkdir()
    with pytest.raises(InputError, match="is a folder"):
        calibrate_to_file([], tmp_path / "d.yaml")
    blank = tmp_path / "blank.png"
    import cv2

    cv2.imwrite(str(blank), np.full((60, 80), 128, np.uint8))
    blank2 = tmp_path / "blank2.png"
    cv2.imwrite(str(blank2), np.full((60, 80), 120, np.uint8))
    out = tmp_path / "calib.yaml"
    with pytest.raises(CalibrationError, match="no 9x6 chessboard"):
        calibrate_to_file([blank, blank2], out, board="9x6", pairs=True)
    with pytest.raises(InputError, match="the same image as"):
        calibrate_to_file([blank, blank], out, board="9x6", pairs=True)
    assert not out.exists()
