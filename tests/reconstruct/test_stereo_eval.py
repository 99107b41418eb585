"""Tests of prism3d.reconstruct.stereo.stereo_eval (disparity scoring)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from prism3d.reconstruct.stereo.stereo_eval import DisparityScore, score_disparity

from prism3d.errors import InputError


def test_known_answer_small() -> None:
    gt = np.array([[10.0, 10.0, 10.0, 0.0], [20.0, 20.0, 20.0, 20.0]], np.float32)
    est = np.array([[10.5, 11.5, 13.0, 99.0], [np.nan, 20.0, 17.5, 21.0]], np.float32)
    s = score_disparity(est, gt)
    assert isinstance(s, DisparityScore)
    assert s.n_scored == 7  # gt == 0 is unknown
    # errors on the 6 estimated pixels: 0.5 1.5 3.0 0.0 2.5 1.0 ; one missing
    assert s.bad1 == pytest.approx(4 / 7)  # 1.5, 3.0, 2.5 and the missing pixel
    assert s.bad2 == pytest.approx(3 / 7)  # 3.0, 2.5, missing
    assert s.bad1_valid == pytest.approx(3 / 6)
    assert s.bad2_valid == pytest.approx(2 / 6)
    assert s.density == pytest.approx(6 / 7)
    assert s.avg_err == pytest.approx(np.mean([0.5, 1.5, 3.0, 0.0, 2.5, 1.0]))
    assert s.rms_err == pytest.approx(np.sqrt(np.mean(np.square([0.5, 1.5, 3.0, 0.0, 2.5, 1.0]))))
    assert set(s.as_dict()) >= {"bad1", "bad2", "avg_err", "density"}


def test_mask_gt_valid_and_negative_invalid() -> None:
    gt = np.full((2, 2), 5.0)
    est = np.array([[5.0, -1.0], [9.0, 5.0]])
    s = score_disparity(est, gt, negative_invalid=True)
    assert s.density == pytest.approx(0.75) and s.bad2 == pytest.approx(0.5)
    mask = np.array([[True, False], [False, True]])
    assert score_disparity(est, gt, mask=mask).bad1 == 0.0
    gv = np.array([[True, True], [False, False]])
    s = score_disparity(est, gt, gt_valid=gv)
    assert s.n_scored == 2 and s.bad2 == pytest.approx(0.5)  # -1 is an estimate here


def test_errors() -> None:
    with pytest.raises(InputError, match="same shape"):
        score_disparity(np.zeros((2, 3)), np.ones((3, 2)))
    with pytest.raises(InputError, match="disparity: expected 2 dimensions"):
        score_disparity(np.zeros(3), np.ones(3))
    with pytest.raises(InputError, match="no pixel to score"):
        score_disparity(np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(InputError, match="mask: expected dtype kind"):
        score_disparity(np.zeros((2, 2)), np.ones((2, 2)), mask=np.ones((2, 2)))
    with pytest.raises(InputError, match="mask and gt must have the same shape"):
        score_disparity(np.zeros((2, 2)), np.ones((2, 2)), mask=np.ones((1, 2), bool))
    with pytest.raises(InputError, match="gt_valid and gt"):
        score_disparity(np.zeros((2, 2)), np.ones((2, 2)), gt_valid=np.ones((2, 1), bool))
    with pytest.raises(InputError, match="thresholds"):
        score_disparity(np.zeros((2, 2)), np.ones((2, 2)), thresholds=(0.0, 2.0))


@pytest.mark.realdata
@pytest.mark.parametrize("scene,scale", [("tsukuba", 16), ("venus", 8), ("teddy", 4), ("cones", 4)])
def test_reproduces_middlebury_reference_rates(shared_data, scene: str, scale: int) -> None:
    """Scoring the published alg117 result reproduces Middlebury's official rates."""
    folder = shared_data / "stereo" / "middlebury_2001_2003"
    rows = [r.split(",") for r in (folder / "reference_badpixel_rates_alg117.csv").read_text().split()]
    ref = {(r[0], float(r[2])): float(r[3]) for r in rows[1:]}
    d = folder / scene
    gt = cv2.imread(str(d / "groundtruth.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64) / scale
    est = cv2.imread(str(d / "alg117_patchmatch_result.png"), cv2.IMREAD_GRAYSCALE) / scale
    mask = cv2.imread(str(d / "nonocc.png"), cv2.IMREAD_GRAYSCALE) == 255
    s = score_disparity(est, gt, mask=mask, gt_valid=mask, thresholds=(1.0, 2.0))
    assert 100 * s.bad1 == pytest.approx(ref[(scene, 1.0)], abs=0.006)
    assert 100 * s.bad2 == pytest.approx(ref[(scene, 2.0)], abs=0.006)
