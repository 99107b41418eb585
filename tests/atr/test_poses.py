"""Tests of prism3d.atr.poses: grids, view-sphere samplings, pose tables."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.atr.poses import (
    ChipPose,
    camera_T_obj_cam,
    fibonacci_directions,
    grid_directions,
    icosphere_directions,
    make_poses,
    parse_range,
    poses_table,
)

from prism3d.errors import InputError


def test_parse_range_wraps_and_includes():
    assert parse_range("0:360:10") == [float(a) for a in range(0, 360, 10)]
    assert parse_range("10:60:25") == [10.0, 35.0, 60.0]
    assert parse_range("1000,2000") == [1000.0, 2000.0]
    assert parse_range(5) == [5.0]
    assert parse_range([1, 2]) == [1.0, 2.0]


@pytest.mark.parametrize(
    "bad,match",
    [
        ("0:10", "A0:A1:STEP"),
        ("a,b", "A0:A1:STEP"),
        ("0:10:0", "STEP must be > 0"),
        ("", "no values"),
        ([], "empty"),
    ],
)
def test_parse_range_errors(bad, match):
    with pytest.raises(InputError, match=match):
        parse_range(bad)


def test_camera_looks_at_centre_with_z_up():
    c = np.array([10.0, -5.0, 30.0])
    for az, el in [(0, 0), (90, 30), (200, -20), (45, 90), (0, -90)]:
        T = camera_T_obj_cam(az, el, 1000.0, 0.0, c)
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        p_cam = np.linalg.inv(T) @ np.append(c, 1)
        np.testing.assert_allclose(p_cam[:3], [0, 0, 1000.0], atol=1e-9)
        if abs(el) < 90:
            up_cam = R.T @ np.array([0, 0, 1.0])
            assert up_cam[1] < 0  # object +z points up (-y) in the image
    # az = 90: camera on +y (left side of the target)
    T = camera_T_obj_cam(90, 0, 500.0)
    np.testing.assert_allclose(T[:3, 3], [0, 500, 0], atol=1e-9)


def test_roll_rotates_image():
    T0 = camera_T_obj_cam(0, 0, 1000.0, 0.0)
    T1 = camera_T_obj_cam(0, 0, 1000.0, 90.0)
    p = np.array([0.0, 0.0, 100.0, 1.0])  # a point above the centre: up in the image
    q0 = np.linalg.inv(T0) @ p
    q1 = np.linalg.inv(T1) @ p
    assert q0[1] < 0 and abs(q0[0]) < 1e-9
    assert abs(q1[1]) < 1e-9 and q1[0] != 0  # rolled by 90 deg: now sideways


def test_fibonacci_and_icosphere_near_uniform():
    f = fibonacci_directions(200)
    assert f.shape == (200, 2)
    z = np.sin(np.radians(f[:, 1]))
    assert abs(z.mean()) < 1e-9  # equal-area spacing in z
    ico = icosphere_directions(1)
    assert ico.shape == (42, 2)
    assert icosphere_directions(0).shape == (12, 2)
    assert np.all(icosphere_directions(2, min_el_deg=0)[:, 1] >= 0)
    np.testing.assert_array_equal(icosphere_directions(1), icosphere_directions(1))  # deterministic
    with pytest.raises(InputError, match="positive integer"):
        fibonacci_directions(0)
    with pytest.raises(InputError, match="elevation limits"):
        fibonacci_directions(10, min_el_deg=30, max_el_deg=10)
    with pytest.raises(InputError, match="subdivisions"):
        icosphere_directions(9)


def test_make_poses_and_table_roundtrip():
    dirs = grid_directions(parse_range("0:360:90"), [10, 40])
    poses = make_poses(dirs, [1000, 2000], size=64, rolls_deg=[0, 15])
    assert len(poses) == 4 * 2 * 2 * 2
    df = poses_table(poses)
    assert list(df.columns[:8]) == [
        "az_deg",
        "el_deg",
        "range_mm",
        "roll_deg",
        "fx",
        "fy",
        "cx",
        "cy",
    ]
    assert df.shape == (32, 24)
    back = ChipPose.from_row(df.iloc[5].to_dict())
    np.testing.assert_allclose(back.T_cam_obj, poses[5].T_cam_obj)
    np.testing.assert_allclose(back.K, poses[5].K)
    with pytest.raises(InputError, match="missing column"):
        ChipPose.from_row({"az_deg": 0})
    with pytest.raises(InputError, match="positive distances"):
        make_poses(dirs, [-1.0])
    with pytest.raises(InputError, match="chip size"):
        make_poses(dirs, [100.0], size=0)
    with pytest.raises(InputError, match="range_mm"):
        ChipPose(0, 0, 0.0, 0, np.eye(3), np.eye(4))


@pytest.mark.parametrize("spec", ["nan", "0:nan:10", "1,inf", [1.0, float("nan")], float("inf")])
def test_parse_range_refuses_non_finite(spec):
    """``--azimuth nan`` rendered a chip at az NaN; now it is a clear error."""
    with pytest.raises(InputError, match="finite"):
        parse_range(spec)


def test_parse_range_refuses_a_typo_of_billions_of_poses():
    with pytest.raises(InputError, match="3600000001 values, more than 100000"):
        parse_range("0:360:1e-7")
    assert len(parse_range("0:360:0.0036")) == 100_000  # the limit itself is fine
