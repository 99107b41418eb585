"""Field-scene batches and their evaluation as jobs: units, resume, batch.json, the
eval-scenes results (JSON + Pd-FPPI plot), and bad input refused before any work."""

from __future__ import annotations

import json

import pytest

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
    assert [s["scene"] for s in res["scenes"]] == scenes  # in the order given
    assert res["n_images"] == 2
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["at_fppi"] == json.loads(json.dumps(res["at_fppi"]))
    assert (tmp_path / "r_fppi.png").stat().st_size > 1000
    truths = [json.loads((out / s / "truth.json").read_text()) for s in ("scene_0008", "scene_0007")]
    assert res["n_targets"] == sum(not t["confuser"] and not t["difficult"] for tr in truths for t in tr["targets"])


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
