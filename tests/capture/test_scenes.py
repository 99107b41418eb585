"""Scenes: calibration board poses (options and validation) and the 4x4 rotation helper."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.capture.rig import paper_rig
from prism3d.capture.scenes import BoardPoseOptions, calibration_board_poses, rotation_about
from prism3d.geometry import make_transform
from prism3d.geometry import rotation_about as rotation_about_3x3

from prism3d.errors import InputError


def test_rotation_about_is_the_geometry_rotation_as_4x4() -> None:
    T = rotation_about((1, 2, 3), 0.4)
    assert T.shape == (4, 4)
    np.testing.assert_array_equal(T, make_transform(rotation_about_3x3((1, 2, 3), 0.4)))
    with pytest.raises(InputError, match="axis must be non-zero"):
        rotation_about((0, 0, 0), 1.0)


def test_calibration_board_poses_options() -> None:
    rig = paper_rig()
    default = calibration_board_poses(rig, 3)
    explicit = calibration_board_poses(rig, 3, options=BoardPoseOptions())
    np.testing.assert_array_equal(np.stack(default), np.stack(explicit))
    o = BoardPoseOptions(cols=19, rows=13, square_mm=12.0, seed=7, distance_range_mm=(1200.0, 1300.0))
    poses = calibration_board_poses(rig, 4, options=o)
    assert len(poses) == 4
    for T in poses:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        centre = T[:3, :3] @ np.array([9 * 12.0, 6 * 12.0, 0.0]) + T[:3, 3]
        assert 1200.0 <= centre[2] <= 1300.0
    with pytest.raises(InputError, match="could not place 2 chessboards"):
        calibration_board_poses(rig, 2, options=BoardPoseOptions(square_mm=400.0, max_tries=50))
    with pytest.raises(InputError, match="n: expected >= 1"):
        calibration_board_poses(rig, 0)
    with pytest.raises(InputError, match="options: expected BoardPoseOptions"):
        calibration_board_poses(rig, 2, options={"seed": 1})


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"cols": 1}, "at least 2x2 inner corners"),
        ({"square_mm": 0.0}, "square_mm: expected a finite number > 0"),
        ({"margin_squares": -1.0}, "margin_squares: expected a finite number >= 0"),
        ({"edge_px": -1.0}, "edge_px: expected a finite number >= 0"),
        ({"distance_range_mm": (1400.0, 1100.0)}, "distance_range_mm: expected .low, high."),
        ({"tilt_range_deg": (40.0, 20.0)}, "tilt_range_deg: expected .low, high."),
        ({"distance_range_mm": (-5.0, 100.0)}, "distance_range_mm: expected a finite number > 0"),
        ({"max_tries": 0}, "max_tries: expected >= 1"),
    ],
)
def test_board_pose_options_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(InputError, match=match):
        BoardPoseOptions(**kwargs)
