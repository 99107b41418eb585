"""Tests of prism3d.atr.evaluate: metrics on known answers, evaluate_bank, plots, baseline."""

from __future__ import annotations

import json

import numpy as np
import pytest
from prism3d.atr.bank import train_bank
from prism3d.atr.chips import ChipSpec
from prism3d.atr.evaluate import (
    EVAL_CHIP_SPEC,
    HELDOUT_SEED_OFFSET,
    BankEvaluation,
    accuracy_by,
    confusion_matrix,
    evaluate_bank,
    feature_baseline,
    format_results,
    heldout_seed,
    pcc,
    plot_confusion,
    roc_curve,
)

from prism3d.errors import InputError


def _targets():
    from prism3d.datasets.models.targets import builtin_target

    return [
        ("tank", builtin_target("tank_t1")),
        ("jet", builtin_target("jet_j1")),
        ("ship", builtin_target("ship_s1")),
    ]


def test_metrics_known_answers():
    t = ["a", "a", "b", "b", "c"]
    p = ["a", "b", "b", "b", "a"]
    assert pcc(t, p) == pytest.approx(0.6)
    np.testing.assert_array_equal(
        confusion_matrix(t, p, ["a", "b", "c"]), [[1, 1, 0], [0, 2, 0], [1, 0, 0]]
    )
    assert accuracy_by([0, 10, 10, 20], [True, False, True, True]) == {
        0.0: 1.0,
        10.0: 0.5,
        20.0: 1.0,
    }
    assert accuracy_by([1, 9, 31], [True, False, True], 10) == {0.0: 1.0, 10.0: 0.0, 30.0: 1.0}
    r = roc_curve([5, 6, 7], [1, 2, 3])
    assert r["auc"] == pytest.approx(1.0)
    r = roc_curve([1, 2], [1, 2])
    assert r["auc"] == pytest.approx(0.5)
    with pytest.raises(InputError, match="unknown class 'd'"):
        confusion_matrix(["d"], ["a"], ["a", "b"])
    with pytest.raises(InputError, match="equal, non-empty"):
        pcc([], [])
    with pytest.raises(InputError, match="at least one target"):
        roc_curve([], [1.0])


@pytest.fixture(scope="module")
def bank():
    return train_bank(
        _targets(),
        channel="shape",
        azimuth="0:360:30",
        elevation="20",
        bin_deg=30,
        chip_spec=ChipSpec(size=48),
    )


def test_evaluate_bank_writes_results(tmp_path, bank):
    spec = ChipSpec(noise_sigma=0.02, seed=heldout_seed(0), size=200)  # size: the bank's wins
    res = evaluate_bank(bank, _targets(), chip_spec=spec, out_json=tmp_path / "res.json")
    assert res.classes == ["tank", "jet", "ship"]
    assert res.n_chips == 36
    assert 0.0 <= res.pcc <= 1.0 and res.pcc >= 0.8
    assert np.sum(res.confusion) == 36
    assert res.conditions["azimuth"][0] == pytest.approx(7.5)  # quarter step: unseen
    assert set(res.per_aspect) and set(res.per_range)
    assert 0.0 <= res.roc["auc"] <= 1.0
    on_disk = json.loads((tmp_path / "res.json").read_text())
    assert on_disk == json.loads(json.dumps(res.to_json())) and BankEvaluation.from_json(on_disk) == res
    with pytest.raises(InputError, match="missing pcc"):
        BankEvaluation.from_json({k: v for k, v in on_disk.items() if k != "pcc"})
    for suffix in ("_chips.parquet", "_confusion.png", "_aspect.png", "_roc.png", "_psr.png"):
        assert (tmp_path / f"res{suffix}").stat().st_size > 0
    fig = plot_confusion(res)
    assert fig.axes
    assert res.conditions["seed"] == 1 and res.conditions["noise_sigma"] == 0.02
    text = format_results(res)
    assert text.startswith(f"Pcc {100 * res.pcc:.1f}% over 3 classes (tank, jet, ship)")
    assert len(text.splitlines()) == 4


def test_heldout_seed_rule():
    assert HELDOUT_SEED_OFFSET == 1
    assert heldout_seed(0) == 1 and heldout_seed(41) == 42
    assert EVAL_CHIP_SPEC.seed == heldout_seed(0)


def test_evaluate_unknown_class(bank):
    from prism3d.datasets.models.targets import builtin_target

    with pytest.raises(InputError, match="unknown class 'truck'"):
        evaluate_bank(bank, [("truck", builtin_target("truck_k1"))])
    with pytest.raises(InputError, match="FilterBank"):
        evaluate_bank("bank.npz", _targets())


def test_feature_baseline_with_own_feature_fn():
    def feats(depth_mm, mask, K):
        z = np.nanmedian(depth_mm[mask]) if mask.any() else 0.0
        rows, cols = np.nonzero(mask)
        if rows.size == 0:
            return {"w": 0.0, "h": 0.0, "area": 0.0, "relief": 0.0}
        scale = z / K[0, 0]
        return {
            "w": float(np.ptp(cols) + 1) * scale,
            "h": float(np.ptp(rows) + 1) * scale,
            "area": float(mask.sum()) * scale**2,
            "relief": float(np.nanmax(depth_mm) - np.nanmin(depth_mm)),
        }

    res = feature_baseline(
        _targets(), feature_fn=feats, train_azimuth="0:360:30", elevation="20", size=48
    )
    assert res["classes"] == ["tank", "jet", "ship"] and res["pcc"] >= 0.6
    assert res["feature_names"] == ["area", "h", "relief", "w"]


def test_feature_baseline_with_view_features():
    pytest.importorskip("prism3d.atr.features")
    res = feature_baseline(_targets(), train_azimuth="0:360:30", elevation="20", size=48)
    assert res["pcc"] >= 0.6
    assert len(res["feature_names"]) >= 3


def test_roc_auc_orders_scores():
    """A channel whose target scores are clearly higher than clutter's gets AUC > 0.5, and
    the same scores swapped get 1 - AUC: the ROC is not inverted."""
    rng = np.random.default_rng(0)
    t, c = rng.normal(2.0, 1.0, 300), rng.normal(0.0, 1.0, 300)
    good, swapped = roc_curve(t, c)["auc"], roc_curve(c, t)["auc"]
    assert good > 0.85
    assert swapped == pytest.approx(1.0 - good, abs=1e-9)


def test_intensity_bank_separates_targets_from_unseen_background():
    """Trained over the black training background, shown over a brighter noise background
    (the silhouette's contrast flipped) with a new camouflage: the intensity bank's target
    scores stay above the clutter-only chips' (AUC 0.81; 0.40 on raw intensity)."""
    from prism3d.datasets.models.targets import builtin_target

    b = train_bank(_targets(), channel="intensity", azimuth="0:360:30", elevation="20", bin_deg=30)
    assert b.intensity_prep == "gradient"
    test = [(c, builtin_target(m.name, camouflage=True, seed=17)) for c, m in _targets()]
    res = evaluate_bank(b, test, chip_spec=ChipSpec(seed=heldout_seed(0), noise_sigma=0.03, clutter="noise"))
    assert res.roc["auc"] > 0.75
