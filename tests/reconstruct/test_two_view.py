"""Two-view relative pose (the survey mode's pose anchor): exact on synthetic matches
with known motion over uneven ground, and on the real drone pair against the drone's own
attitude and flight direction."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.geometry import rotation_angle_deg
from tests.reconstruct.two_view_anchor import pose_from_matches, relative_pose


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def test_pose_from_synthetic_matches_over_uneven_ground():
    """A nadir camera 120 m up moves 36 m along its image's -y and turns 12 deg; ground
    with 0-15 m relief; 0.3 px noise and 20 % wrong matches: the rotation within
    0.05 deg, the direction of motion within 0.5 deg (measured 0.009 and 0.004)."""
    rng = np.random.default_rng(3)
    K = np.array([[1100.0, 0, 800], [0, 1100.0, 600], [0, 0, 1]])
    n = 800
    X = np.c_[rng.uniform(-70, 70, n), rng.uniform(-50, 50, n), 120.0 - rng.uniform(0, 15, n)]  # camera-1 frame
    R = _rot("z", 12.0) @ _rot("x", 1.5)
    c2 = np.array([1.0, -36.0, 0.5])  # camera 2's centre in camera 1's frame
    t = -R @ c2
    x1 = X @ K.T
    x1 = x1[:, :2] / x1[:, 2:]
    Xc2 = X @ R.T + t
    x2 = Xc2 @ K.T
    x2 = x2[:, :2] / x2[:, 2:]
    x1 += rng.normal(0, 0.3, x1.shape)
    x2 += rng.normal(0, 0.3, x2.shape)
    bad = rng.random(n) < 0.2
    x2[bad] = rng.uniform([0, 0], [1600, 1200], (bad.sum(), 2))
    pose = pose_from_matches(x1, x2, K)
    assert rotation_angle_deg(pose.R.T @ R) < 0.05
    cos = float(pose.baseline_cam1 @ (c2 / np.linalg.norm(c2)))
    assert math.degrees(math.acos(min(1.0, cos))) < 0.5
    assert pose.n_inliers >= 0.75 * n and pose.inlier_rms_px < 0.6


def test_bad_input():
    K = np.eye(3)
    with pytest.raises(InputError, match="only 5 matches"):
        pose_from_matches(np.zeros((5, 2)), np.zeros((5, 2)), K)
    with pytest.raises(InputError, match="same n"):
        pose_from_matches(np.zeros((50, 2)), np.zeros((40, 2)), K)
    flat = np.full((200, 300), 128, dtype=np.uint8)
    with pytest.raises(InputError, match="too few features"):
        relative_pose(flat, flat, np.array([[300.0, 0, 150], [0, 300.0, 100], [0, 0, 1]]))


def _attitude(heading: float, pitch: float, roll: float) -> np.ndarray:
    return _rot("z", -heading) @ _rot("y", pitch) @ _rot("x", roll)  # any fixed convention: only the relative angle is used


@pytest.mark.realdata
def test_real_drone_pair_against_its_attitude_and_track(shared_data):
    """IMG_2188 -> IMG_2189 (consecutive frames on one flight line), 1600 px wide, focal
    length from EXIF: the relative rotation within 1 deg of the one in the drone's
    heading/pitch/roll record (13.1 deg; ours 12.55; a small UAV's attitude is good to
    about a degree), and the camera moved along the image's vertical (the flight
    direction)."""
    import cv2

    from prism3d.capture.geotag import exif_focal_px, read_position_table

    d = shared_data / "aerial/snowpeak_internal_only"
    s = 1600 / 4608
    imgs = [cv2.resize(cv2.imread(str(d / n)), None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            for n in ("IMG_2188.JPG", "IMG_2189.JPG")]
    h, w = imgs[0].shape[:2]
    f = exif_focal_px(d / "IMG_2188.JPG") * s
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    pose = relative_pose(imgs[0][..., ::-1], imgs[1][..., ::-1], K)
    tags = read_position_table(d / "geoinfo.txt")
    a, b = tags["IMG_2188.JPG"], tags["IMG_2189.JPG"]
    imu = rotation_angle_deg(_attitude(a.heading_deg, a.pitch_deg, a.roll_deg).T
                             @ _attitude(b.heading_deg, b.pitch_deg, b.roll_deg))
    assert abs(rotation_angle_deg(pose.R) - imu) < 1.0, (rotation_angle_deg(pose.R), imu)
    assert abs(pose.baseline_cam1[1]) > 0.98  # along the image's vertical
    assert pose.n_inliers >= 300 and pose.inlier_rms_px < 0.5
