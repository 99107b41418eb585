"""The ground/object split of whole-scene detection on a real street scene (KITTI 2015,
frame 000046_10: a passenger car crossing 13 m ahead), on the benchmark's LiDAR-derived
depth and on our matcher's depth of the same pair: the car stands out as one object of a
car's size, the road stays ground."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

#: KITTI's rectified colour cameras (devkit calibration, the 2011_09_26 drives): focal
#: length and principal point (px) and baseline (mm). Lateral sizes and heights depend on
#: the baseline only (X = (u - cx) B / d), which is the same 0.54 m on every drive.
KITTI_F, KITTI_CX, KITTI_CY, KITTI_B_MM = 721.5377, 609.5593, 172.854, 537.2
#: The car in the left view (rows, cols), drawn by hand from the image.
CAR = np.s_[185:262, 615:835]
ROAD_ROWS = np.s_[300:, :]


def _scene(depth_from_disp: np.ndarray, left: np.ndarray):
    from prism3d.atr.detect import scene_channels

    d = depth_from_disp
    depth = np.where(d > 0.5, KITTI_F * KITTI_B_MM / np.maximum(d, 1e-6), np.nan).astype(np.float32)
    K = np.array([[KITTI_F, 0, KITTI_CX], [0, KITTI_F, KITTI_CY], [0, 0, 1.0]])
    grey = left.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32) / 255.0
    return scene_channels(grey, depth, K), depth


def _car(sc) -> tuple[int, np.ndarray]:
    labs = sc.labels[CAR]
    labs = labs[labs > 0]
    assert labs.size, "the car is not an object"
    k = int(np.bincount(labs).argmax())
    return k, sc.object_dims_mm[k]


@pytest.fixture(scope="module")
def kitti(shared_data: Path):
    from prism3d.reconstruct.stereo.stereo_eval import load_benchmark_pair

    return load_benchmark_pair(shared_data, "kitti")


@pytest.mark.realdata
def test_a_real_car_stands_out_with_a_cars_size(kitti):
    left, _, gt, _ = kitti
    sc, depth = _scene(gt, left)
    k, (length, _, height) = _car(sc)
    on_car = np.isfinite(depth[CAR])
    assert sc.figure[CAR][on_car].mean() > 0.8
    assert 3500 <= length <= 5000 and 1300 <= height <= 1800, (length, height)  # any passenger car
    assert 11_000 < sc.object_depth_mm[k] < 15_000
    road = np.isfinite(depth[ROAD_ROWS])
    assert sc.figure[ROAD_ROWS][road].mean() < 0.02  # the road is ground
    assert sc.up[1] < -0.99  # the road's normal is the camera's up (KITTI's cameras are level)


@pytest.mark.realdata
def test_our_stereo_gives_the_same_car(kitti):
    """Our matcher's depth of the same pair: the car's length and height within 10 % of
    those measured on the benchmark's depth, the road still ground."""
    from prism3d.reconstruct.stereo.match import match_stereo

    left, right, gt, _ = kitti
    ref = _car(_scene(gt, left)[0])[1]
    d = match_stereo(left, right, min_disp=0, num_disp=int(np.ceil(gt.max() + 1)))
    sc, depth = _scene(d, left)
    _, dims = _car(sc)
    assert abs(dims[0] / ref[0] - 1) < 0.10 and abs(dims[2] / ref[2] - 1) < 0.10, (dims, ref)
    road = np.isfinite(depth[ROAD_ROWS])
    assert sc.figure[ROAD_ROWS][road].mean() < 0.03
