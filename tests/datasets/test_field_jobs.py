"""Field-scene batches and their evaluation as jobs: units, resume, batch.json, the
eval-scenes results (JSON + Pd-FPPI plot), and bad input refused before any work."""

from __future__ import annotations

import json

import pytest

from prism3d.atr.scene_eval import SceneScore
from prism3d.errors import InputError

SMALL = dict(sensor_size=(720, 540), focal_px=600.0, clutter=4, supersample=1, targets=2, confusers=1)


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    from prism3d.datasets.simulation.field import FieldOptions, simulate_field_batch

    out = tmp_path_factory.mktemp("batch") / "scenes"
    report = simulate_field_batch(out, 2, FieldOptions(seed=7, **SMALL))
    return out, report


def test_a_batch_writes_one_folder_per_seed_and_its_figures(batch):
    out, report = batch
    assert report.ok and report.done_units == 2 and report.skipped_units == 0
    names = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert names == ["scene_0007", "scene_0008"]
    for n in names:
        assert sorted(p.name for p in (out / n).iterdir()) == ["rig.yaml", "shot.png", "truth.json", "truth.npz"]
    doc = json.loads((out / "batch.json").read_text())
    assert doc["scenes"] == names and doc["made_now"] == 2 and doc["scenes_per_minute"] > 0
    t7 = json.loads((out / "scene_0007" / "truth.json").read_text())
    t8 = json.loads((out / "scene_0008" / "truth.json").read_text())
    assert t7["options"]["seed"] == 7 and t8["options"]["seed"] == 8  # each unit its own seed
    assert t7["targets"] != t8["targets"]


def test_a_rerun_resumes_and_extends(batch, tmp_path):
    import shutil

    from prism3d.datasets.simulation.field import FieldOptions, simulate_field_batch

    out = tmp_path / "scenes"
    shutil.copytree(batch[0], out)
    before = (out / "scene_0007" / "shot.png").stat().st_mtime_ns
    report = simulate_field_batch(out, 3, FieldOptions(seed=7, **SMALL))
    assert report.skipped_units == 2 and report.done_units == 1 and report.total_units == 3
    assert (out / "scene_0009" / "truth.json").is_file()
    assert (out / "scene_0007" / "shot.png").stat().st_mtime_ns == before  # kept, not redone
    with pytest.raises(InputError, match="other options"):
        simulate_field_batch(out, 3, FieldOptions(seed=7, **{**SMALL, "clutter": 5}))


def test_batch_bad_input_is_refused_before_any_work(tmp_path):
    from prism3d.datasets.simulation.field import FieldOptions, simulate_field_batch

    with pytest.raises(InputError, match="count"):
        simulate_field_batch(tmp_path / "a", 0, FieldOptions(**SMALL))
    (tmp_path / "b" / "scene_0000").mkdir(parents=True)
    (tmp_path / "b" / "scene_0000" / "shot.png").write_bytes(b"")
    with pytest.raises(InputError, match="not a complete field scene"):
        simulate_field_batch(tmp_path / "b", 1, FieldOptions(**SMALL))
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["scene_0000"]  # nothing added
    assert not (tmp_path / "a").exists()


def test_eval_scenes_scores_every_scene_and_plots(batch, tmp_path):
    from prism3d.atr.bank import train_bank
    from prism3d.datasets.simulation.field import eval_scene_folders
    from prism3d.datasets.database.resolve import resolve_targets

    out, _ = batch
    bank = train_bank(resolve_targets(["tank_t1", "jet_j1"]), channel="depth", azimuth="0:360:30",
                      bin_deg=30.0, params=(1.0, 0.0, 0.0))
    bank.save(tmp_path / "b.npz")
    scenes = [str(out / "scene_0008"), str(out / "scene_0007")]
    res = eval_scene_folders(tmp_path / "b.npz", scenes, out_json=tmp_path / "r.json")
    assert [s["scene"] for s in res.scenes] == scenes  # in the order given
    assert res.score.n_images == 2
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved == json.loads(json.dumps(res.to_json()))
    assert SceneScore.from_json(saved).at_fppi.keys() == res.score.at_fppi.keys()
    assert (tmp_path / "r_fppi.png").stat().st_size > 1000
    truths = [json.loads((out / s / "truth.json").read_text()) for s in ("scene_0008", "scene_0007")]
    assert res.score.n_targets == sum(not t["confuser"] and not t["difficult"] for tr in truths
                                      for t in tr["targets"])


def test_cli_batch_and_eval_bad_inputs_exit_2(tmp_path):
    from prism3d.cli import main

    assert main(["-q", "simulate", "field", str(tmp_path / "f"), "--count", "0"]) == 2
    assert main(["-q", "simulate", "field", str(tmp_path / "g"), "--workers", "2"]) == 2  # no --count
    assert main(["-q", "bank", "eval", str(tmp_path / "b.npz"), "--workers", "2"]) == 2
    assert not (tmp_path / "f").exists() and not (tmp_path / "g").exists()


def test_eval_scenes_refuses_a_scene_missing_a_file_before_any_work(batch, tmp_path, capsys):
    import shutil

    from prism3d.cli import main

    out, _ = batch
    broken = tmp_path / "broken"
    shutil.copytree(out / "scene_0007", broken)
    (broken / "shot.png").unlink()
    r = tmp_path / "r.json"
    assert main(["-q", "bank", "eval-scenes", str(tmp_path / "no_bank.npz"), str(out / "scene_0008"), str(broken),
                 "--json", str(r)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no shot.png" in err[0], err
    assert not r.exists() and not (tmp_path / "r_fppi.png").exists()


def _broken_scene(src, dst, case: str) -> str:
    """A copy of scene ``src`` at ``dst`` with one file damaged as ``case`` says."""
    import shutil

    import numpy as np

    from prism3d.io.images import write_image

    shutil.copytree(src, dst)
    if case == "shot_grey10":
        write_image(dst / "shot.png", np.full((10, 10), 128, np.uint8))
    elif case == "shot_half_size":
        write_image(dst / "shot.png", np.zeros((540, 360, 3), np.uint8))
    elif case == "shot_garbage":
        (dst / "shot.png").write_bytes(b"garbage, not a PNG" * 10)
    elif case == "rig_garbage":
        (dst / "rig.yaml").write_bytes(b"\x00\xff\x00 garbage")
    elif case == "rig_is_a_camera_yaml":
        (dst / "rig.yaml").write_text("%YAML:1.0\n---\nimage_width: 720\nimage_height: 540\n")
    elif case.startswith("truth_"):
        doc = json.loads((dst / "truth.json").read_text())
        doc["targets"][0]["radius_mm"] = -150.0
        text = "[" * 100_000 + "]" * 100_000 if case == "truth_deep_nesting" else json.dumps(doc)
        (dst / "truth.json").write_text(text)
    return str(dst)


@pytest.mark.parametrize("case, match", [
    ("shot_grey10", "10x10 px, but its rig.yaml has a 720x540 sensor"),
    ("shot_half_size", "360x540 px"),
    ("shot_garbage", "not a readable image"),
    ("shot_over_the_pixel_budget", "limit"),
    ("rig_garbage", "rig.yaml"),
    ("rig_is_a_camera_yaml", "rig.yaml"),
    ("truth_radius_negative", "radius_mm: expected a radius > 0 mm"),
    ("truth_deep_nesting", "not valid JSON"),
])
def test_eval_scenes_refuses_a_broken_scene_in_one_line_before_any_detection(batch, tmp_path, monkeypatch, capsys,
                                                                             case, match):
    """Each scene is checked whole before any detection: one line naming the scene and its
    problem (once a runner warning came first, and a negative radius was taken)."""
    import prism3d.datasets.simulation.field as field
    from prism3d.cli import main

    def no_detection(*a, **k):
        raise AssertionError("detected before the scenes were checked")

    monkeypatch.setattr(field, "detect_scene_folder", no_detection)
    out, _ = batch
    if case == "shot_over_the_pixel_budget":
        monkeypatch.setenv("PRISM3D_MAX_PIXELS", "100000")  # the 720x540 shot is 388,800 pixels
    broken = _broken_scene(out / "scene_0007", tmp_path / "broken", case)
    scenes = [broken] if case == "shot_over_the_pixel_budget" else [str(out / "scene_0008"), broken]
    r = tmp_path / "r.json"
    assert main(["-q", "bank", "eval-scenes", str(tmp_path / "b.npz"), *scenes, "--json", str(r)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0] and broken in err[0], err
    assert not r.exists() and not (tmp_path / "r_fppi.png").exists()


@pytest.mark.parametrize("name", ["truth.json", "r.json", "sub/r.json"])
def test_eval_scenes_writes_nothing_into_a_scene_folder(batch, tmp_path, capsys, name):
    """--json naming a scene's own truth.json (once overwritten, exit 0) or any file in a
    scene folder is refused, and the scene is left as it was."""
    import shutil

    from prism3d.cli import main

    sc = tmp_path / "sc"
    shutil.copytree(batch[0] / "scene_0007", sc)
    before = {p.name: p.read_bytes() for p in sc.iterdir()}
    assert main(["-q", "bank", "eval-scenes", str(tmp_path / "b.npz"), str(sc), "--json", str(sc / name)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lies in the input folder" in err[0], err
    assert {p.name: p.read_bytes() for p in sc.iterdir()} == before


def test_a_failed_unit_is_reported_once(batch, tmp_path, monkeypatch, capsys, caplog):
    """A scene that fails in its detection unit: the command's one error line, and no
    runner warning before it (the runner logs failed units at INFO, shown with -v)."""
    import logging

    import prism3d.datasets.simulation.field as field
    from prism3d.atr.bank import train_bank
    from prism3d.cli import main
    from prism3d.datasets.database.resolve import resolve_targets

    train_bank(resolve_targets(["tank_t1", "jet_j1"]), channel="depth", azimuth="0:360:90", bin_deg=90.0,
               params=(1.0, 0.0, 0.0)).save(tmp_path / "b.npz")

    def fails(bank_path, scene):
        raise InputError(f"{scene}/shot.png: cannot decode as an image")

    monkeypatch.setattr(field, "detect_scene_folder", fails)
    r = tmp_path / "r.json"
    args = ["bank", "eval-scenes", str(tmp_path / "b.npz"), str(batch[0] / "scene_0007"), "--json", str(r)]
    with caplog.at_level(logging.INFO):
        assert main(["-q", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot decode" in err[0], err
    assert not [rec for rec in caplog.records if rec.levelno >= logging.WARNING], caplog.text
    assert not r.exists()
    caplog.clear()
    with caplog.at_level(logging.INFO):
        assert main(["-q", "-v", *args]) == 2  # -v shows the unit's failure as it happens
    assert any("failed" in rec.getMessage() for rec in caplog.records if rec.name.endswith("runner"))
