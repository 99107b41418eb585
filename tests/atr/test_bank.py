"""Tests of prism3d.atr.bank: training, classification, detection, persistence."""

from __future__ import annotations

import json

import numpy as np
import pytest
from prism3d.atr.bank import (
    FilterBank,
    check_bank_command,
    prepare_chips,
    render_class_chips,
    train_bank,
)
from prism3d.atr.chips import ChipSpec

from prism3d.errors import InputError


def _targets(variants: str = "1", seed: int = 0):
    from prism3d.datasets.models.targets import builtin_target, list_builtin_targets

    names = [n for n in list_builtin_targets() if n[-1] in variants]
    return [(n.split("_")[0], builtin_target(n, seed=seed)) for n in names]


def _pcc(bank, targets, azimuth, elevation, **chip_fields):
    spec = ChipSpec(size=bank.size, **chip_fields)
    X, lab, _, _, _, fx = render_class_chips(
        targets, channel=bank.channel, azimuth=azimuth, elevation=elevation, chip_spec=spec
    )
    df = bank.classify(X, fx)
    return float(np.mean(df["pred_class"].to_numpy() == np.array(lab))), df


@pytest.fixture(scope="module")
def small_bank():
    return train_bank(
        _targets("1"),
        channel="depth",
        azimuth="0:360:15",
        elevation="20",
        bin_deg=15,
        chip_spec=ChipSpec(size=48),
    )


def test_small_bank_unseen_azimuths(small_bank):
    """Fast version: 4 classes (one variant each), test azimuths between the training
    ones, camouflage and noise on."""
    pcc, df = _pcc(
        small_bank,
        _targets("1"),
        azimuth=list(np.arange(5.0, 360, 15)),
        elevation="20",
        noise_sigma=0.03,
        depth_noise_mm=0.3,
        seed=5,
    )
    assert pcc >= 0.95
    assert set(df["pred_class"]) <= set(small_bank.classes)
    assert small_bank.classes == ["tank", "jet", "ship", "truck"]
    assert len(small_bank) == 4 * 24
    # aspect: the winning bin is usually the nearest one (the filters know the pose)
    assert small_bank.metadata["chosen_params"] in [
        list(p)
        for p in [
            (1.0, 1.0, 1.0),
            (1.0, 0.1, 1.0),
            (0.1, 1.0, 1.0),
            (1.0, 1.0, 0.1),
            (0.0, 0.1, 1.0),
            (0.0, 1.0, 0.0),
        ]
    ]


def test_save_load_roundtrip(tmp_path, small_bank):
    p = small_bank.save(tmp_path / "bank.npz")
    b = FilterBank.load(p)
    assert b.classes == small_bank.classes and b.channel == "depth" and b.metric == "pce"
    np.testing.assert_array_equal(b.freqs, small_bank.freqs)
    np.testing.assert_array_equal(b.filter_az_deg, small_bank.filter_az_deg)
    with np.load(p, allow_pickle=False) as z:  # readable without pickle
        meta = json.loads(bytes(z["meta_json"]).decode())
    assert meta["schema_version"] == 1
    # an unknown version is rejected
    meta["schema_version"] = 99
    with np.load(p, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(tmp_path / "v99.npz", **arrays)
    with pytest.raises(InputError, match="unknown filter bank schema_version 99"):
        FilterBank.load(tmp_path / "v99.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a prism3d filter bank"):
        FilterBank.load(tmp_path / "junk.npz")


def test_detect_in_scene(small_bank):
    targets = _targets("1")
    X, _lab, _az, _, _, fx = render_class_chips(
        targets[:1], channel="depth", azimuth=[30.0], elevation="20", chip_spec=ChipSpec(size=48)
    )
    chip = X[0]
    scene = np.full((128, 160), np.nan, dtype=np.float32)
    scene[40:88, 90:138] = chip
    dets = small_bank.detect(scene, fx=fx[0], threshold=5.0, max_detections=3)
    assert dets, "no detection"
    d = dets[0]
    assert abs(d.row - (40 + 24)) <= 2 and abs(d.col - (90 + 24)) <= 2
    assert d.target_class == "tank"
    assert d.psr > 5.0
    with pytest.raises(InputError, match="at least 48x48"):
        small_bank.detect(np.zeros((20, 20)), fx=100.0)


def test_bank_errors():
    t = _targets("1")
    s32 = ChipSpec(size=32)
    with pytest.raises(InputError, match="at least 2 classes"):
        train_bank(t[:1], chip_spec=s32, azimuth="0:360:90")
    with pytest.raises(InputError, match="empty list"):
        train_bank([], chip_spec=s32)
    with pytest.raises(InputError, match="360 / bin_deg"):
        train_bank(t, bin_deg=7, chip_spec=s32)
    with pytest.raises(InputError, match="SceneMesh"):
        train_bank([("tank", "mesh.obj")], chip_spec=s32)
    with pytest.raises(InputError, match="channel"):
        train_bank(t, channel="rgb", chip_spec=s32)
    with pytest.raises(InputError, match="params: expected 'auto'"):
        train_bank(t, params=(1.0, 1.0), chip_spec=s32)
    with pytest.raises(InputError, match="give -o BANK.npz"):
        check_bank_command("train", output=None, bank=None)
    with pytest.raises(InputError, match="give the bank file"):
        check_bank_command("eval", output="b.npz", bank=None)
    check_bank_command("eval", output=None, bank="b.npz")
    with pytest.raises(InputError, match="fx"):
        prepare_chips(np.zeros((1, 8, 8)), "depth")


@pytest.mark.slow
def test_builtin_full_pcc_depth_shape_intensity():
    """All 12 built-in targets (4 classes x 3 variants), unseen interleaved azimuths,
    camouflage on (the test targets wear a different pattern than the training
    ones), sensor noise on: depth and shape-image banks >= 95% Pcc; the intensity
    bank falls well below (measured 77.5%: camouflage hurts it)."""
    t = _targets("123")
    t_test = _targets("123", seed=1)
    res = {}
    for ch in ("depth", "shape", "intensity"):
        bank = train_bank(
            t, channel=ch, azimuth="0:360:10", elevation="15,35", bin_deg=10,
            chip_spec=ChipSpec(size=64),
        )
        res[ch], _ = _pcc(
            bank,
            t_test,
            azimuth=list(np.arange(2.5, 360, 10)),
            elevation="20,30",
            noise_sigma=0.03,
            depth_noise_mm=0.3,
            lighting_variation=10.0,
            seed=99,
        )
    assert res["depth"] >= 0.95
    assert res["shape"] >= 0.95
    assert res["intensity"] < res["shape"] - 0.1


@pytest.mark.slow
@pytest.mark.realdata
def test_real_meshes_tank_airplane_ship(shared_data):
    """Quaternius CC0 meshes (glTF, Y-up, arbitrary units), normalised to 250 mm:
    4 tanks vs 5 aircraft vs 5 ships, unseen azimuths, noise on."""
    from prism3d.atr.chips import load_mesh_file

    d = shared_data / "meshes" / "quaternius_vehicles_cc0" / "glb"
    if not d.is_dir():
        pytest.skip("quaternius_vehicles_cc0 not present")
    groups = {
        "tank": [f"tank_{i}" for i in (1, 2, 3, 4)],
        "airplane": [
            "airplane_military_1",
            "airplane_military_2",
            "airplane_commercial",
            "airplane_private",
            "airplane_small",
        ],
        "ship": ["ship_boat", "ship_cruise", "ship_lifeboat", "ship_sail", "ship_viking"],
    }
    t = [
        (
            c,
            load_mesh_file(
                d / f"{n}.glb", up="y", yaw_deg=0.0 if c == "tank" else 90.0, length_mm=250.0
            ),
        )
        for c, names in groups.items()
        for n in names
    ]
    bank = train_bank(
        t, channel="depth", azimuth="0:360:10", elevation="15,35", bin_deg=10,
        chip_spec=ChipSpec(size=64),
    )
    pcc, _ = _pcc(
        bank,
        t,
        azimuth=list(np.arange(2.5, 360, 10)),
        elevation="20,30",
        noise_sigma=0.03,
        depth_noise_mm=0.3,
        seed=99,
    )
    assert pcc >= 0.9


def test_a_bank_of_nan_filters_is_refused(tmp_path):
    """It scored 50 % on two classes instead of saying it was broken."""
    from prism3d.atr.bank import FilterBank
    from prism3d.errors import InputError

    rng = np.random.default_rng(0)
    freqs = rng.normal(size=(2, 8, 8)) + 1j * rng.normal(size=(2, 8, 8))
    bank = FilterBank(["a", "b"], "depth", 8, 90.0, freqs, np.array([0, 1]), np.array([0.0, 0.0]),
                      np.zeros((2, 3)), {}, "pce")
    bank.save(tmp_path / "ok.npz")
    assert FilterBank.load(tmp_path / "ok.npz").classes == ["a", "b"]
    freqs[0, 0, 0] = np.nan
    FilterBank(["a", "b"], "depth", 8, 90.0, freqs, np.array([0, 1]), np.array([0.0, 0.0]),
               np.zeros((2, 3)), {}, "pce").save(tmp_path / "nan.npz")
    with pytest.raises(InputError, match="NaN or infinite"):
        FilterBank.load(tmp_path / "nan.npz")


def test_intensity_prep_is_polarity_free_and_old_banks_stay_raw(tmp_path):
    """A bright target on a dark ground and the same target on a brighter ground give
    nearly the same gradient input; a bank saved without ``intensity_prep`` keeps raw."""
    import dataclasses

    from prism3d.atr.bank import FilterBank, prepare_chips

    yy, xx = np.mgrid[:48, :48]
    body = ((yy - 24) ** 2 / 100 + (xx - 24) ** 2 / 300) < 1
    dark = np.where(body, 0.3, 0.0)[None]
    bright = np.where(body, 0.3, 0.6)[None]
    g = [prepare_chips(x, "intensity")[0] for x in (dark, bright)]
    r = [prepare_chips(x, "intensity", intensity_prep="raw")[0] for x in (dark, bright)]
    assert float(np.sum(g[0] * g[1])) > 0.99  # unit energy: this is the correlation
    assert float(np.sum(r[0] * r[1])) < -0.99  # raw: the contrast flips sign
    b = FilterBank(["a", "b"], "intensity", 8, 180.0, np.ones((2, 8, 8), complex), np.array([0, 1]),
                   np.array([0.0, 0.0]), np.ones((2, 3)), {})
    assert b.intensity_prep == "raw"
    b2 = FilterBank.load(b.save(tmp_path / "old.npz"))
    assert b2.intensity_prep == "raw"
    with pytest.raises(InputError, match="intensity_prep"):
        dataclasses.replace(b, metadata={"intensity_prep": "edges"})
