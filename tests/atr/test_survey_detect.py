"""Vehicles in a normalised DSM: nadir templates against exact synthetic height maps
(the class meshes ray-cast from above, pasted at known places and headings among a
crate, a building and trees), and the GeoJSON they are written to."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from prism3d.atr.scene_eval import MapDetection, MapTarget, score_detections
from prism3d.atr.survey_detect import (
    find_vehicles,
    nadir_templates,
    write_geojson,
)
from prism3d.datasets.models.targets import builtin_target
from prism3d.errors import InputError

CELL = 0.1
NAMES = ("tank_t1", "truck_k1", "truck_k2")


@pytest.fixture(scope="module")
def templates():
    return nadir_templates([(n, builtin_target(n, scale="full")) for n in NAMES], CELL)


def _paste(nd: np.ndarray, heights: np.ndarray, r: int, c: int, ang: float) -> None:
    h, w = heights.shape
    s = int(max(h, w) * 1.5)
    M = cv2.getRotationMatrix2D((w / 2, h / 2), ang, 1.0)
    M[:, 2] += [s / 2 - w / 2, s / 2 - h / 2]
    warped = cv2.warpAffine(heights, M, (s, s))
    win = nd[r - s // 2:r - s // 2 + s, c - s // 2:c - s // 2 + s]
    np.maximum(win, warped, out=win)


def test_templates_have_the_meshes_size(templates) -> None:
    for t, n in zip(templates, NAMES):
        ext = np.asarray(builtin_target(n, scale="full").extent_mm) / 1000.0
        assert t.height == pytest.approx(ext[2], rel=1e-6)
        assert float(t.heights.max()) == pytest.approx(ext[2], abs=0.02)  # the top seen from above
        assert t.heights.shape[1] > t.heights.shape[0]  # length along x
        footprint = (t.heights > 0.05).sum() * CELL**2
        assert 0.4 * t.length * t.width < footprint <= 1.05 * t.length * t.width


def test_vehicles_found_at_their_place_and_told_from_clutter(templates) -> None:
    rng = np.random.default_rng(0)
    nd = rng.normal(0.0, 0.03, (900, 1200)).astype(np.float32)
    truth = []
    for k, (t, (r, c, ang)) in enumerate(zip(templates, [(200, 250, 25.0), (200, 700, 100.0), (650, 300, 160.0)])):
        _paste(nd, t.heights, r, c, ang)
        truth.append({"x": (c + 0.5) * CELL, "y": -(r + 0.5) * CELL, "length_m": t.length, "cls": t.cls,
                      "heading": (90.0 - ang) % 180.0})
    nd[600:635, 700:780] = 2.9  # a crate 8 x 3.5 x 2.9 m: vehicle-sized, but a box
    nd[100:220, 950:1100] = 6.0  # a building
    yy, xx = np.mgrid[:900, :1200]
    for cy, cx in ((750, 900), (820, 1100)):  # trees: round crowns 7 m high
        nd = np.maximum(nd, np.clip(7.0 - ((yy - cy) ** 2 + (xx - cx) ** 2) / 250.0, 0, None).astype(np.float32))
    dets = find_vehicles(nd, CELL, templates)
    top = [d for d in dets if d.score > -1][:3]
    for tr in truth:
        # within 15 % of its length (the tank's thin gun is opened away with the noise)
        near = [d for d in top if math.hypot(d.x - tr["x"], d.y - tr["y"]) < 0.15 * tr["length_m"]]
        assert len(near) == 1 and near[0].class_name == tr["cls"]
        dh = abs(near[0].heading_deg - tr["heading"]) % 180.0
        assert min(dh, 180.0 - dh) < 5.0
    crate = [d for d in dets if abs(d.x - 74.0) < 3 and abs(d.y + 61.7) < 3]
    assert crate and crate[0].score < min(d.score for d in top)
    assert not any(d.score > -1 and d.height_m > 5 for d in dets)  # building, trees: no class fits
    assert top[0].to_record()["class"] == top[0].class_name  # write_geojson's record
    s = score_detections([MapDetection(d.x, d.y, d.score, d.class_name) for d in dets],
                         [MapTarget(t["x"], t["y"], t["length_m"]) for t in truth], n_frames=10)
    assert s["pd_at_0.1_fppf"] == 1.0


def test_geojson_in_wgs84(tmp_path) -> None:
    from prism3d.geo import wgs84_to_enu

    origin = (37.5, 139.0, 0.0)
    p = tmp_path / "d.geojson"
    write_geojson(p, [{"x": 100.0, "y": -50.0, "score": 0.9, "class": "tank"}], origin_lla=origin)
    doc = json.loads(p.read_text())
    lon, lat = doc["features"][0]["geometry"]["coordinates"]
    back = wgs84_to_enu(np.array([[lat, lon, 0.0]]), np.array(origin))[0]
    assert back[:2] == pytest.approx([100.0, -50.0], abs=1e-3)
    assert doc["features"][0]["properties"]["class"] == "tank"


def test_find_vehicles_refuses_bad_input(templates) -> None:
    with pytest.raises(InputError, match="no class templates"):
        find_vehicles(np.zeros((10, 10)), CELL, [])
    with pytest.raises(InputError, match=r"\(H, W\)"):
        find_vehicles(np.zeros((10, 10, 2)), CELL, templates)
