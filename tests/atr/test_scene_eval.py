"""Scene scoring on hand-counted cases: hits by box or 3D radius, greedy matching,
duplicates and confusers as false positives, Pd and identification at an FPPI, bad input."""

from __future__ import annotations

import json
import math

import pytest

from prism3d.atr.scene_eval import (MapDetection, MapTarget, SceneScore, match_map_detections, score_detections,
                                    score_scenes)
from prism3d.errors import InputError


def _t(cls, box, confuser=False, xyz=None, radius=None):
    d = {"class": cls, "confuser": confuser, "box_rc": box}
    if xyz is not None:
        d.update(xyz_mm=xyz, radius_mm=radius)
    return d


def _d(row, col, cls, score, xyz=None):
    return {"row": row, "col": col, "class": cls, "score": score, "xyz_mm": xyz}


def test_known_counts():
    truth1 = {"targets": [_t("tank", [10, 10, 50, 90]), _t("truck", [100, 100, 140, 200]),
                          _t("crate", [200, 10, 240, 60], confuser=True)]}
    dets1 = {"detections": [_d(30, 50, "tank", 9.0), _d(31, 52, "tank", 8.0),  # a duplicate: a false positive
                            _d(120, 150, "jet", 7.0),  # a hit, misidentified
                            _d(220, 30, "tank", 6.0),  # on the crate: a confuser called a target
                            _d(400, 400, "ship", 5.0)]}  # on nothing
    truth2 = {"targets": [_t("ship", [0, 0, 10, 10], xyz=[0, 0, 20000], radius=3000)]}
    dets2 = {"detections": [_d(300, 300, "ship", 8.5, xyz=[1000, 0, 21000])]}  # outside the box, near in 3D
    r = score_scenes([(dets1, truth1), (dets2, truth2)])
    assert (r.n_images, r.n_targets, r.n_confusers) == (2, 3, 1)
    c = r.curve
    assert c.threshold == [9.0, 8.5, 8.0, 7.0, 6.0, 5.0]
    assert c.pd == pytest.approx([1 / 3, 2 / 3, 2 / 3, 1.0, 1.0, 1.0])
    assert c.fppi == pytest.approx([0.0, 0.0, 0.5, 0.5, 1.0, 1.5])
    assert c.id_accuracy == pytest.approx([1.0, 1.0, 1.0, 2 / 3, 2 / 3, 2 / 3])
    a01, a1 = r.at_fppi["0.1"], r.at_fppi["1"]
    assert (a01.pd, a01.threshold, a01.confusers_called) == (pytest.approx(2 / 3), 8.5, 0.0)
    assert (a1.pd, a1.threshold, a1.confusers_called) == (1.0, 7.0, 0.0)  # the highest threshold at Pd 1
    assert r.pd_max == 1.0
    # the results file's document, and back
    doc = json.loads(json.dumps(r.to_json()))
    assert list(doc) == ["n_images", "n_targets", "n_confusers", "curve", "at_fppi", "pd_max"]
    assert doc["at_fppi"]["0.1"] == {"pd": pytest.approx(2 / 3), "id_accuracy": 1.0, "threshold": 8.5,
                                     "confusers_called": 0.0}
    assert SceneScore.from_json(doc) == r
    with pytest.raises(InputError, match="scores"):
        SceneScore.from_json({"n_images": 1})


def test_no_detections_and_equal_scores():
    truth = {"targets": [_t("tank", [0, 0, 10, 10]), _t("tank", [20, 20, 30, 30])]}
    r = score_scenes([({"detections": []}, truth)])
    assert r.curve.pd == [] and r.at_fppi["0.1"].pd == 0.0
    r = score_scenes([({"detections": [_d(5, 5, "tank", 1.0), _d(50, 50, "tank", 1.0)]}, truth)])
    assert r.curve.threshold == [1.0]  # tied scores pass a threshold together
    assert r.curve.pd == [0.5] and r.curve.fppi == [1.0]
    assert math.isnan(r.at_fppi["0.1"].id_accuracy)


@pytest.mark.parametrize("scenes, match", [
    ([], "non-empty"),
    ([({"detections": []},)], "pair"),
    ([({"detections": [{"row": 1, "col": 1, "class": "t", "score": float("nan")}]}, {"targets": []})], "score"),
    ([({"detections": []}, {"targets": [{"class": "t", "box_rc": [5, 0, 1, 9]}]})], "r0 <= r1"),
    ([({"detections": []}, {"objects": []})], "truth"),
    ([({"detections": [{"row": 1, "col": 1, "class": "t", "score": 1, "xyz_mm": [1, 2]}]}, {"targets": []})],
     "xyz_mm"),
])
def test_bad_input_is_named(scenes, match):
    with pytest.raises(InputError, match=match):
        score_scenes(scenes)


def test_confusers_called_at_an_operating_point():
    truth = {"targets": [_t("tank", [0, 0, 10, 10]), _t("bus", [20, 20, 30, 30], confuser=True)]}
    dets = {"detections": [_d(25, 25, "truck", 9.0), _d(5, 5, "tank", 8.0)]}
    a = score_scenes([(dets, truth)]).at_fppi["1"]
    assert (a.pd, a.threshold, a.confusers_called, a.id_accuracy) == (1.0, 8.0, 1.0, 1.0)


def test_difficult_targets_are_neither_found_nor_missed():
    truth = {"targets": [
        {"class": "tank", "confuser": False, "box_rc": [0, 0, 10, 10]},
        {"class": "tank", "confuser": False, "box_rc": [20, 20, 30, 30], "difficult": True},
    ]}
    dets = {"detections": [{"row": 25, "col": 25, "class": "tank", "score": 9.0},
                           {"row": 26, "col": 26, "class": "tank", "score": 8.0},
                           {"row": 5, "col": 5, "class": "tank", "score": 1.0}]}
    r = score_scenes([(dets, truth)])
    assert r.n_targets == 1
    assert r.at_fppi["0.1"].pd == 1.0  # the two detections on the hidden target cost nothing


def test_map_detections_known_counts():
    """The map rules on a hand-counted case: a confuser is neither hit nor miss and a
    detection near it is no false alarm; a second detection on a found vehicle is one."""
    targets = [MapTarget(0.0, 0.0, 4.0, class_name="car"), MapTarget(20.0, 0.0, 10.0, class_name="bus"),
               MapTarget(40.0, 0.0, 6.0, counted=False, class_name="truck")]
    dets = [MapDetection(0.5, 0.0, 0.9, "car"),  # hit, class right
            MapDetection(41.0, 0.0, 0.8, "car"),  # on the confuser: ignored
            MapDetection(19.0, 1.0, 0.7, "truck"),  # hit, class wrong
            MapDetection(0.0, 1.0, 0.6, "car"),  # the car again: a false positive
            MapDetection(40.5, 0.5, 0.5, "car"),  # near the confuser: ignored
            MapDetection(80.0, 0.0, 0.4, "car"),  # nothing there
            MapDetection(80.0, 9.0, -1.0, None)]  # no class fits: not a detection
    kinds = [(m.index, m.kind, m.target) for m in match_map_detections(dets, targets)]
    assert kinds == [(0, "hit", 0), (1, "ignored", 2), (2, "hit", 1), (3, "fp", None), (4, "ignored", None),
                     (5, "fp", None)]
    s = score_detections(dets, targets, n_frames=10, threshold=0.65)
    assert s["n_targets"] == 2 and s["pd_at_0.1_fppf"] == 1.0 and s["class_accuracy_at_0.1_fppf"] == 0.5
    assert s["at_threshold"] == {"threshold": 0.65, "pd": 1.0, "false_positives": 0, "fp_per_frame": 0.0,
                                 "class_accuracy": 0.5}
    assert [c["fp"] for c in s["curve"]] == [0, 0, 0, 1, 1, 2]
