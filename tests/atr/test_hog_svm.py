"""Tests of prism3d.atr.hog_svm: training, held-out accuracy, dense scoring, persistence."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from prism3d.atr.bank import BANK_CHIP_SPEC, class_scale_facts, render_class_chips
from prism3d.atr.hog_svm import HogParams, HogSvm, chip_units

from prism3d.errors import InputError

NAMES = ("tank_t1", "jet_j1", "ship_s1", "truck_k1")
SPEC = replace(BANK_CHIP_SPEC, size=64)
TRAIN_AZ, HELD_AZ = "0:360:30", "15:360:30"


def _targets(seed: int = 0):
    from prism3d.datasets.models.targets import builtin_target

    return [(n.split("_")[0], builtin_target(n, seed=seed)) for n in NAMES]


@pytest.fixture(scope="module")
def models():
    """One 4-class model per channel, trained on a 30-degree azimuth grid."""
    return {
        ch: HogSvm.train(_targets(), channel=ch, azimuth=TRAIN_AZ, chip_spec=SPEC)
        for ch in ("depth", "intensity")
    }


@pytest.fixture(scope="module")
def heldout():
    """Views half a grid step from the training ones, another camouflage seed, in channel units."""
    out = {}
    for ch in ("depth", "intensity"):
        X, lab, _, _, _, fx = render_class_chips(
            _targets(seed=1), channel=ch, azimuth=HELD_AZ, elevation="20", chip_spec=SPEC
        )
        out[ch] = (chip_units(X, ch, fx), np.array(lab))
    return out


# Measured on these 48 held-out chips (C = 0.1): depth 1.00, intensity 0.94 (chance 0.25).
# The bars leave room for 2 and 4 misses, so a solver or renderer change may move a view
# or two, but a model that has stopped separating the classes fails.
@pytest.mark.parametrize(("channel", "bar"), [("depth", 0.95), ("intensity", 0.85)])
def test_heldout_accuracy(models, heldout, channel, bar):
    m = models[channel]
    U, lab = heldout[channel]
    acc = float(np.mean(np.array(m.predict(U)) == lab))
    assert acc >= bar, f"{channel}: held-out accuracy {acc:.3f} < {bar}"
    assert m.metadata["training_accuracy"] == 1.0


@pytest.mark.parametrize("channel", ["depth", "intensity"])
@pytest.mark.parametrize("shift", [(32, 0), (0, 32), (-32, 0), (0, -32)])
def test_centred_beats_shifted(models, heldout, channel, shift):
    """A window half a chip off the target (background) scores lower for the target's
    class than the centred window, for every held-out chip."""
    m = models[channel]
    U, lab = heldout[channel]
    idx = np.array([m.classes.index(c) for c in lab])
    moved = np.roll(U, shift, axis=(1, 2))
    dr, dc = shift  # blank the wrapped-around part: background, not the target's far side
    if dr > 0:
        moved[:, :dr] = 0
    elif dr < 0:
        moved[:, dr:] = 0
    if dc > 0:
        moved[:, :, :dc] = 0
    elif dc < 0:
        moved[:, :, dc:] = 0
    n = np.arange(len(lab))
    centred = m.score_windows(U)[n, idx]
    shifted = m.score_windows(moved)[n, idx]
    assert np.all(centred > shifted)
    assert np.mean(centred > 0) >= 0.85 and np.mean(shifted < 0) >= 0.9


def _canvas(chips: np.ndarray, rng: np.random.Generator):
    """Eight chips on a blank canvas at cell-aligned top-left corners, 8 px apart or more."""
    S = chips.shape[-1]
    canvas = np.zeros((2 * (S + 16) + 8, 4 * (S + 8) + 8))
    corners = []
    for k, chip in enumerate(chips[:8]):
        r = (k // 4) * (S + 16) + 8 * int(rng.integers(0, 3))
        c = (k % 4) * (S + 8) + 8 * int(rng.integers(0, 2))
        canvas[r : r + S, c : c + S] = chip
        corners.append((r, c))
    return canvas, corners


@pytest.mark.parametrize("channel", ["depth", "intensity"])
def test_dense_matches_windows(models, heldout, channel):
    """dense_scores equals score_windows on cell-aligned windows (chips have a blank rim,
    so HOG's zero border gradient of a cut-out window changes nothing)."""
    m = models[channel]
    U, _ = heldout[channel]
    S = m.size
    assert np.all(U[:, [0, 1, -2, -1], :] == 0) and np.all(U[:, :, [0, 1, -2, -1]] == 0)
    canvas, corners = _canvas(U[::5], np.random.default_rng(3))
    scores, row0, col0, stride = m.dense_scores(canvas)
    assert (row0, col0, stride) == (S // 2, S // 2, 8)
    h, w = canvas.shape
    assert scores.shape == (len(m.classes), (h - S) // stride + 1, (w - S) // stride + 1)
    corners.append((h - S - (h - S) % stride, w - S - (w - S) % stride))  # a blank window
    for r, c in corners:
        want = m.score_windows(canvas[None, r : r + S, c : c + S])[0]
        got = scores[:, r // stride, c // stride]
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("channel", ["depth", "intensity"])
def test_dense_centre_convention(models, heldout, channel):
    """The best window over a scene holding one chip is centred on the chip: within one
    cell (8 px) for most chips. Measured 88 % (depth) and 94 % (intensity) of the 48
    held-out chips; the rest, long targets seen side-on, peak 16-24 px along their
    length, still on the target, so no peak may be further than 24 px off."""
    m = models[channel]
    U, lab = heldout[channel]
    err, peak = [], []
    for k in range(len(U)):
        img = np.zeros((176, 160))
        img[48 : 48 + 64, 40 : 40 + 64] = U[k]
        scores, row0, col0, stride = m.dense_scores(img)
        own = scores[m.classes.index(lab[k])]
        i, j = np.unravel_index(np.argmax(own), own.shape)
        peak.append(own[i, j])
        err.append(max(abs(row0 + i * stride - 80), abs(col0 + j * stride - 72)))
    err = np.array(err)
    assert np.mean(err <= 8) >= 0.8 and err.max() <= 24
    assert np.mean(np.array(peak) > 0) >= 0.85


def test_dense_small_and_bad_images(models):
    m = models["depth"]
    s, row0, col0, stride = m.dense_scores(np.zeros((63, 200)))
    assert s.shape == (4, 0, 0) and (row0, col0, stride) == (32, 32, 8)
    assert m.dense_scores(np.zeros((64, 64)))[0].shape == (4, 1, 1)
    with pytest.raises(InputError):
        m.dense_scores(np.zeros((2, 64, 64)))
    with pytest.raises(InputError):
        m.dense_scores(np.full((80, 80), np.nan))


def test_metadata(models):
    m = models["depth"]
    meta = json.loads(json.dumps(m.metadata))
    assert meta["channel"] == "depth" and meta["augmentation"] is None
    assert meta["targets"] == [[n.split("_")[0], n] for n in NAMES]
    assert meta["n_positives"] == {c: 12 for c in m.classes}
    assert sum(meta["n_background"].values()) >= 2 * sum(meta["n_positives"].values())
    assert meta["hog"] == m.hog.to_json() and m.weights.shape == (4, 7 * 7 * 36)
    X, lab, _, _, rng_mm, fx = render_class_chips(
        _targets(), channel="depth", azimuth=TRAIN_AZ, elevation="20", chip_spec=SPEC
    )
    facts = class_scale_facts(_targets(), lab, fx, rng_mm)
    for key, per_class in facts.items():
        assert set(meta[key]) == set(per_class)
        for c, v in per_class.items():
            assert meta[key][c] == pytest.approx(v)


def test_save_load_round_trip(models, heldout, tmp_path):
    m = models["intensity"]
    U, _ = heldout["intensity"]
    p = m.save(tmp_path / "hog.npz")
    m2 = HogSvm.load(p)
    assert m2.classes == m.classes and m2.channel == m.channel and m2.size == m.size
    assert m2.hog == m.hog and m2.metadata == json.loads(json.dumps(m.metadata))
    np.testing.assert_array_equal(m2.score_windows(U), m.score_windows(U))
    img = np.zeros((100, 120))
    img[10:74, 30:94] = U[0]
    np.testing.assert_array_equal(m2.dense_scores(img)[0], m.dense_scores(img)[0])


def test_persistence_errors(models, tmp_path):
    m = models["depth"]
    with pytest.raises(InputError, match="npz"):
        m.save(tmp_path / "hog.pkl")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match="not a prism3d HOG"):
        HogSvm.load(bad)
    other = tmp_path / "other.npz"
    np.savez(other, meta_json=np.frombuffer(b'{"kind": "bank"}', dtype=np.uint8),
             weights=np.zeros(1), bias=np.zeros(1))
    with pytest.raises(InputError, match="hog_svm"):
        HogSvm.load(other)
    with pytest.raises(InputError, match="not found"):
        HogSvm.load(tmp_path / "missing.npz")
    # a truncated real file
    good = m.save(tmp_path / "good.npz")
    cut = tmp_path / "cut.npz"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(InputError):
        HogSvm.load(cut)


def test_bad_inputs(models):
    m = models["depth"]
    with pytest.raises(InputError, match="2 classes"):
        HogSvm.train(_targets()[:1], channel="depth", azimuth="0:360:90", chip_spec=SPEC)
    with pytest.raises(InputError, match="channel"):
        HogSvm.train(_targets()[:2], channel="mask", azimuth="0:360:90", chip_spec=SPEC)
    with pytest.raises(InputError, match="windows"):
        m.score_windows(np.zeros((2, 48, 48)))
    with pytest.raises(InputError, match="windows"):
        m.score_windows(np.zeros((64, 64)))
    with pytest.raises(InputError, match="finite"):
        m.score_windows(np.full((1, 64, 64), np.nan))
    with pytest.raises(InputError, match="classes"):
        HogSvm(["tank"], "depth", 64, m.weights[:1], m.bias[:1], m.hog)
    with pytest.raises(InputError, match="weights"):
        HogSvm(m.classes, "depth", 64, m.weights[:, :-1], m.bias, m.hog)
    assert m.score_windows(np.zeros((0, 64, 64))).shape == (0, 4)


def test_chip_units():
    X, _, _, _, _, fx = render_class_chips(
        _targets()[:2], channel="depth", azimuth="0:360:180", elevation="20", chip_spec=SPEC
    )
    with pytest.raises(InputError, match="fx"):
        chip_units(X, "depth")
    u = chip_units(X, "depth", fx)
    assert u.dtype == np.float64 and u.shape == X.shape
    assert np.all((u >= 0) & (u <= 1)) and np.all(u[np.isnan(X)] == 0) and u.max() > 0.5
    # relief depends on fx: the slab depth is the chip width at the target's range
    assert not np.allclose(chip_units(X, "depth", fx * 2), u)
    g = np.full((1, 4, 4), np.nan)
    assert np.all(chip_units(g, "intensity") == 0) and np.all(chip_units(g, "shape") == 0)
    with pytest.raises(InputError, match="channel"):
        chip_units(X, "mask")


def test_deterministic(models):
    m = HogSvm.train(_targets(), channel="depth", azimuth=TRAIN_AZ, chip_spec=SPEC)
    np.testing.assert_array_equal(m.weights, models["depth"].weights)
    np.testing.assert_array_equal(m.bias, models["depth"].bias)


def test_hog_params_check_and_round_trip():
    p = HogParams(orientations=12, pixels_per_cell=[4, 4], cells_per_block=(3, 2))
    assert p.pixels_per_cell == (4, 4) and HogParams.from_json(json.loads(json.dumps(p.to_json()))) == p
    with pytest.raises(InputError, match="unknown settings"):
        HogParams.from_json({**HogParams().to_json(), "gamma": 1})
    with pytest.raises(InputError, match="square cells"):
        HogParams(pixels_per_cell=(8, 4))
    with pytest.raises(InputError, match="block_norm"):
        HogParams(block_norm="L3")
    with pytest.raises(InputError, match="expected a dict"):
        HogParams.from_json([9, 8, 2])
