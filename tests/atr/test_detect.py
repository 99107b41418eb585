"""Whole-scene detection: the ground/object split against the simulator's truth, the
detections' contract, and bad inputs (one line, exit 2, nothing written)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from prism3d.atr.detect import DetectOptions, SceneDetection, detect_scene, scene_channels
from prism3d.errors import InputError

SMALL = dict(sensor_size=(720, 540), focal_px=600.0, clutter=10, supersample=1)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    from prism3d.datasets.simulation.field import FieldOptions, simulate_field

    out = tmp_path_factory.mktemp("field") / "scene"
    simulate_field(out, FieldOptions(seed=3, targets=3, confusers=1, **SMALL))
    truth = json.loads((out / "truth.json").read_text())
    z = np.load(out / "truth.npz")
    from prism3d.capture.rig import StereoRig
    from prism3d.io.images import read_image

    rig = StereoRig.load(out / "rig.yaml")
    return out, truth, z["depth_left_mm"], z["object_id_left"], rig, read_image(out / "shot.png")


@pytest.fixture(scope="module")
def small_bank():
    from prism3d.atr.bank import train_bank
    from prism3d.datasets.database.resolve import resolve_targets

    return train_bank(resolve_targets(["tank_t1", "truck_k1"]), channel="depth", azimuth="0:360:30",
                      bin_deg=30.0, params=(1.0, 0.0, 0.0))


def _scene(field):
    _, _, depth, _, rig, _ = field
    grey = np.full(depth.shape, 0.5, dtype=np.float32)
    K = rig.left.K.copy()
    return scene_channels(grey, depth, K)


def test_objects_stand_out_of_the_ground_as_in_the_truth(field):
    """On the true depth, target pixels are objects and open ground is not."""
    _, _, depth, oid, _, _ = field
    sc = _scene(field)
    ground = (oid == 0) & np.isfinite(depth)
    assert sc.figure[ground].mean() < 0.03  # rolling terrain stays ground
    idx = [i for i in np.unique(oid) if i > 0]  # 0 is the ground; targets, confusers, clutter after
    covered = [sc.figure[oid == i].mean() for i in idx if (oid == i).sum() > 200]
    assert np.median(covered) > 0.7
    assert sc.up[1] < -0.8  # the ground's normal points up (camera -y)


def test_object_sizes_match_the_true_targets(field):
    """Length (footprint) and height of the object under each visible target, against the
    target's true size: what the 3D size gate relies on."""
    from prism3d.datasets.models.targets import builtin_target

    _, truth, _, oid, _, _ = field
    sc = _scene(field)
    ratios_l, ratios_h = [], []
    for t in truth["targets"]:
        if t["difficult"] or t["name"] in ("crate", "fuel_tank"):
            continue
        m = oid == t["object_index"]
        labs = sc.labels[m]
        labs = labs[labs > 0]
        assert labs.size, f"{t['name']}: not found as an object"
        length, _, height = sc.object_dims_mm[np.bincount(labs).argmax()]
        ext = builtin_target(t["name"], scale="full").extent_mm
        ratios_l.append(length / max(ext[0], ext[1]))
        ratios_h.append(height / ext[2])
    assert ratios_l
    assert 0.7 <= np.median(ratios_l) <= 1.1, ratios_l
    assert abs(np.median(ratios_h) - 1) < 0.15, ratios_h


def test_detections_follow_the_contract(field, small_bank):
    sc = _scene(field)
    dets = detect_scene(small_bank, sc)
    assert dets, "no detections at all"
    scores = [d.score for d in dets]
    assert scores == sorted(scores, reverse=True)
    for d in dets:
        assert {"row", "col", "class", "score", "xyz_mm", "aspect_deg", "range_mm"} <= set(d.to_json())
        assert SceneDetection.from_json(json.loads(json.dumps(d.to_json()))) == d
        assert d.class_name in small_bank.classes
        assert 0 <= d.row < sc.depth_mm.shape[0] and 0 <= d.col < sc.depth_mm.shape[1]


def test_one_detection_per_target_placed_on_it(field, small_bank):
    """On the true depth: a detection near a true target (within its radius) sits inside
    its box (the object, not the window peak, places it), and no two detections fall
    within one target (objects split at depth steps are one target)."""
    _, truth, _, _, _, _ = field
    sc = _scene(field)
    dets = detect_scene(small_bank, sc)
    near_any = 0
    for t in truth["targets"]:
        if t["difficult"]:
            continue
        on = [d for d in dets if d.xyz_mm is not None
              and np.linalg.norm(np.subtract(d.xyz_mm, t["xyz_mm"])) < 0.5 * t["radius_mm"]]
        assert len(on) <= 1, (t["name"], on)
        r0, c0, r1, c1 = t["box_rc"]
        for d in on:
            near_any += 1
            assert r0 - 2 <= d.row <= r1 + 2 and c0 - 2 <= d.col <= c1 + 2, (t["name"], d, t["box_rc"])
    assert near_any >= 1


def test_field_truth_boxes_hold_their_targets(field):
    _, truth, _, oid, rig, _ = field
    assert truth["targets"]
    for t in truth["targets"]:
        r0, c0, r1, c1 = t["box_rc"]
        uv = rig.left.project(np.asarray([t["xyz_mm"]]))[0]
        assert r0 - 5 <= uv[1] <= r1 + 5 and c0 - 5 <= uv[0] <= c1 + 5
        assert 0 < t["visible_fraction"] <= 1.0
    assert any(not t["confuser"] for t in truth["targets"])
    assert all(t["class"] in ("tank", "jet", "ship", "truck", "crate", "fuel_tank") for t in truth["targets"])


def test_bad_inputs():
    with pytest.raises(InputError, match="depth map of the image's size"):
        scene_channels(np.zeros((10, 12)), np.zeros((10, 11)), np.eye(3))
    with pytest.raises(InputError, match="fewer than 100 pixels"):
        scene_channels(np.zeros((20, 20)), np.full((20, 20), np.nan), np.eye(3))
    with pytest.raises(InputError):
        DetectOptions(band_ratio=1.0)


def test_bank_without_scale_is_refused(small_bank, field):
    import dataclasses

    old = dataclasses.replace(small_bank, metadata={k: v for k, v in small_bank.metadata.items()
                                                   if k != "chip_px_per_mm"})
    with pytest.raises(InputError, match="train it again"):
        detect_scene(old, _scene(field))


def test_cli_bad_inputs_exit_2_and_write_nothing(field, small_bank, tmp_path):
    from prism3d.cli import main

    bank = tmp_path / "b.npz"
    small_bank.save(bank)
    img = tmp_path / "i.png"
    from prism3d.io.images import write_image

    write_image(img, np.zeros((40, 50, 3), dtype=np.uint8))
    np.save(tmp_path / "d.npy", np.ones((40, 49), dtype=np.float32))
    out = tmp_path / "det.json"
    assert main(["-q", "detect", "--image", str(img), "--depth", str(tmp_path / "d.npy"), "--fx", "100",
                 "--bank", str(bank), "-o", str(out)]) == 2
    assert main(["-q", "bank", "eval-scenes", str(bank), "--json", str(tmp_path / "r.json")]) == 2
    assert main(["-q", "simulate", "field", str(tmp_path / "f"), "--targets", "0"]) == 2
    assert not out.exists() and not (tmp_path / "r.json").exists() and not (tmp_path / "f").exists()


def test_detect_on_a_shot_writes_left_view_detections(field, small_bank, tmp_path):
    """The shot route end to end: reconstruct, detect, map back to the left view."""
    from prism3d.atr.detect import SceneSource, detect_to_file

    out_dir = field[0]
    bank = tmp_path / "b.npz"
    small_bank.save(bank)
    doc = detect_to_file(bank, tmp_path / "det.json", SceneSource(shot=out_dir / "shot.png", calib=out_dir / "rig.yaml"),
                         draw=tmp_path / "det.png")
    assert (tmp_path / "det.png").is_file()
    saved = json.loads((tmp_path / "det.json").read_text())
    assert saved["detections"] == doc["detections"]
    assert set(doc["timings_s"]) == {"reconstruct_s", "channels_s", "detect_s"}
    w, h = field[4].left.size
    for d in doc["detections"]:
        assert -w <= d["col"] <= 2 * w and -h <= d["row"] <= 2 * h
        if d["xyz_mm"] is not None:
            assert d["xyz_mm"][2] > 0


@pytest.fixture
def no_training(monkeypatch):
    """Any recogniser training fails the test: bad input must be refused before it."""
    import prism3d.datasets.jobs.recognisers as recognisers

    def trained(*a, **k):
        raise AssertionError("trained before the inputs were checked")

    monkeypatch.setattr(recognisers, "scene_recogniser", trained)


def _rig_and_shot(tmp_path, size=(720, 540)):
    from prism3d.capture.rig import paper_rig
    from prism3d.io.images import write_image

    rig = tmp_path / "rig.yaml"
    paper_rig(sensor_size=(720, 540), focal_px=600.0).save(rig)
    shot = tmp_path / "shot.png"
    write_image(shot, np.full((size[1], size[0], 3), 90, np.uint8))
    return rig, shot


@pytest.mark.parametrize("case", ["missing_shot", "shot_of_another_size", "garbage_calib", "missing_calib",
                                  "image_with_a_bad_depth"])
def test_cli_detect_checks_every_input_before_training(tmp_path, capsys, no_training, case):
    """Each input is read before a recogniser is trained (minutes): a missing shot was once
    noticed only after the training."""
    from prism3d.cli import main

    rig, shot = _rig_and_shot(tmp_path, size=(360, 540) if case == "shot_of_another_size" else (720, 540))
    if case == "garbage_calib":
        rig.write_bytes(b"\x00\x01 not yaml")
    src = {"missing_shot": [str(tmp_path / "missing_input.png"), "--calib", str(rig)],
           "missing_calib": [str(shot), "--calib", str(tmp_path / "no_rig.yaml")],
           "image_with_a_bad_depth": ["--image", str(shot), "--depth", str(tmp_path / "no_depth.npy"), "--fx", "600"]
           }.get(case, [str(shot), "--calib", str(rig)])
    match = {"missing_shot": "missing_input.png", "shot_of_another_size": "sensor", "garbage_calib": "rig.yaml",
             "missing_calib": "no_rig.yaml", "image_with_a_bad_depth": "no_depth.npy"}[case]
    out = tmp_path / "det.json"
    assert main(["-q", "detect", *src, "--targets", "tank_t1", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("case", ["draw_is_the_shot", "draw_is_a_link_to_the_shot", "draw_is_the_output",
                                  "draw_in_a_file", "draw_is_a_folder"])
def test_cli_detect_draw_is_checked_first_and_never_replaces_an_input(tmp_path, capsys, no_training, case):
    """``--draw`` is an output like -o: checked before any work, and never the input shot
    (which it once overwrote, exit 0)."""
    import os

    from prism3d.cli import main

    rig, shot = _rig_and_shot(tmp_path)
    before = shot.read_bytes()
    (tmp_path / "blocker").write_text("x")
    (tmp_path / "taken.png").mkdir()
    (tmp_path / "link.png").symlink_to(shot)
    draw = {"draw_is_the_shot": shot, "draw_is_a_link_to_the_shot": tmp_path / "link.png",
            "draw_is_the_output": tmp_path / "det.json", "draw_in_a_file": tmp_path / "blocker" / "d.png",
            "draw_is_a_folder": tmp_path / "taken.png"}[case]
    match = {"draw_is_the_shot": "is also an input", "draw_is_a_link_to_the_shot": "is also an input",
             "draw_is_the_output": "named twice", "draw_in_a_file": "is a file, not a folder",
             "draw_is_a_folder": "is a directory"}[case]
    cwd = os.getcwd()
    os.chdir(tmp_path)  # relative names, as typed
    try:
        rc = main(["-q", "detect", "shot.png", "--calib", str(rig), "--targets", "tank_t1", "-o", "det.json",
                   "--draw", os.path.relpath(draw, tmp_path)])
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert shot.read_bytes() == before and not (tmp_path / "det.json").exists()
