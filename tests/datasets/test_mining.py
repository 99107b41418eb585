"""A scene recogniser trained end to end on small mining scenes: filters over the targets
and what to refuse, the verifier mined with the simulator's truth, its file, and its
judgement of a scene it never saw."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from prism3d.atr.bank import BankOptions
from prism3d.atr.detect import detect_scene, scene_channels
from prism3d.atr.verifier import NONE, SceneRecogniser, train_verifier
from prism3d.datasets.simulation.field import FieldOptions, simulate_field
from prism3d.datasets.jobs.mining import MiningOptions, default_rejects, train_scene_recogniser
from prism3d.datasets.database.resolve import resolve_targets
from prism3d.errors import InputError

SMALL = dict(sensor_size=(720, 540), focal_px=600.0, clutter=10, supersample=1)
NAMES = ["tank_t1", "truck_k1"]


@pytest.fixture(scope="module")
def recogniser() -> SceneRecogniser:
    return train_scene_recogniser(resolve_targets(NAMES), NAMES, options=MiningOptions(
        scenes=3, simulation=replace(MiningOptions().simulation, **SMALL), bank=BankOptions(azimuth="0:360:30", bin_deg=30.0)))


def test_what_it_refuses() -> None:
    rej = default_rejects(resolve_targets(NAMES))
    names = [c for c, _ in rej]
    assert "tank_t2" in names and "truck_k3" in names and "crate" in names and "fuel_tank" in names
    assert "tank_t1" not in names and "tank" not in names


def test_trained_banks_and_verifier(recogniser: SceneRecogniser, tmp_path) -> None:
    assert recogniser.targets == ("tank", "truck")
    assert "tank_t2" in recogniser.banks[0].classes and recogniser.channels == ["shape", "depth"]
    rows = recogniser.metadata["mining"]["rows"]
    assert rows["positive"] >= 6 and rows["negative"] > rows["positive"]
    back = SceneRecogniser.load(recogniser.save(tmp_path / "r.npz"))
    X = np.random.default_rng(0).normal(size=(5, len(recogniser.verifier.mean)))
    assert np.allclose(back.verifier.proba(X), recogniser.verifier.proba(X))


def test_judges_a_scene_it_never_saw(recogniser: SceneRecogniser, tmp_path) -> None:
    out = tmp_path / "scene"
    simulate_field(out, FieldOptions(seed=7, targets=3, confusers=2, classes=tuple(NAMES), **SMALL))
    truth = json.loads((out / "truth.json").read_text())
    from prism3d.capture.rig import StereoRig

    rig = StereoRig.load(out / "rig.yaml")
    z = np.load(out / "truth.npz")
    sc = scene_channels(np.full(z["depth_left_mm"].shape, 0.5, np.float32), z["depth_left_mm"], rig.left.K)
    dets = detect_scene(recogniser, sc)
    assert dets and all(d.class_name in recogniser.targets for d in dets)
    assert all(abs(sum(d.p_classes.values()) - 1.0) < 1e-3 for d in dets)
    oid = z["object_id_left"]
    target_ids = {t["object_index"]: t for t in truth["targets"] if not t["confuser"] and not t["difficult"]}

    def on(d):
        r, c = int(round(d.row)), int(round(d.col))
        return int(oid[min(max(r, 0), oid.shape[0] - 1), min(max(c, 0), oid.shape[1] - 1)])

    hits = [d for d in dets if on(d) in target_ids]
    others = [d for d in dets if on(d) not in target_ids]
    assert hits, "no target found"
    assert np.mean([d.score for d in hits]) > np.mean([d.score for d in others] or [0.0])


def test_verifier_refusals() -> None:
    with pytest.raises(InputError, match="targets and negatives"):
        train_verifier(np.zeros((3, 2)), [NONE, NONE, NONE], ["tank"])
    with pytest.raises(InputError, match="mining scenes"):
        train_scene_recogniser(resolve_targets(NAMES), NAMES, options=MiningOptions(scenes=0))


def test_sigterm_while_mining_leaves_no_temp_folder(tmp_path, monkeypatch) -> None:
    """SIGTERM (the command line turns it into an unwinding KeyboardInterrupt) in the middle
    of a mining scene removes the mining folder from $TMPDIR (once left behind, 73 MB)."""
    import os
    import signal
    import tempfile
    import time
    from pathlib import Path

    import prism3d.cli as cli
    import prism3d.datasets.jobs.mining as mining
    from prism3d.datasets.simulation.field import prop_mesh

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    seen = []

    def simulating_when_terminated(out, options):
        Path(out).mkdir(parents=True)
        (Path(out) / "shot.png").write_bytes(bytes(100_000))
        seen.append(sorted(p.name for p in tmp.iterdir()))
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler interrupts this

    monkeypatch.setattr(mining, "simulate_field", simulating_when_terminated)
    old = signal.signal(signal.SIGTERM, cli._on_sigterm)
    try:
        with pytest.raises(KeyboardInterrupt):
            train_scene_recogniser(resolve_targets(["tank_t1"]), ["tank_t1"],
                                   rejects=[("crate", prop_mesh("crate", np.random.default_rng(0), 0))],
                                   options=MiningOptions(scenes=2, channels=("depth",), bank=BankOptions(
                                       azimuth="0:360:90", bin_deg=90.0, params=(1.0, 0.0, 0.0))))
    finally:
        signal.signal(signal.SIGTERM, old)
    assert seen and seen[0][0].startswith("prism3d-mining-")  # it was mining in $TMPDIR
    assert list(tmp.iterdir()) == []


def test_cli_bank_train_reaches_the_scheduler_before_training(tmp_path, monkeypatch, capsys) -> None:
    """An unreachable --scheduler is refused before the filter banks are trained (it was
    first tried when mining started, minutes later)."""
    import prism3d.datasets.jobs.recognisers as recognisers
    from prism3d.cli import main

    def trained(*a, **k):
        raise AssertionError("trained before the scheduler was reached")

    monkeypatch.setattr(recognisers, "scene_recogniser", trained)
    out = tmp_path / "r.npz"
    assert main(["-q", "bank", "train", "--targets", *NAMES, "--scheduler", "tcp://127.0.0.1:1", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot connect" in err[0], err
    assert not out.exists()
