"""Known-answer tests for the procedural camouflage paint (prism3d.capture.camouflage)."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.capture.mesh import UniformAlbedo
from prism3d.capture.camouflage import (
    CLASS_PALETTES,
    PALETTES,
    CamouflageField,
    camouflage_field,
    plain_paint,
)
from prism3d.errors import InputError


@pytest.fixture(scope="module")
def woodland() -> CamouflageField:
    return CamouflageField.from_palette("woodland", patch_size_mm=30.0, seed=7)


def test_values_are_exactly_the_palette(woodland: CamouflageField) -> None:
    pts = np.random.default_rng(1).uniform(-500, 500, (50_000, 3))
    alb = woodland(pts)
    assert alb.shape == (50_000, 3) and alb.dtype == np.float64
    lab = woodland.labels(pts)
    assert lab.dtype == np.uint8
    np.testing.assert_array_equal(alb, np.array(woodland.colors)[lab])
    assert set(np.unique(lab)) == {0, 1, 2, 3}


def test_area_fractions_match_the_palette(woodland: CamouflageField) -> None:
    # a big volume holds many patches: fractions approach the calibrated targets
    pts = np.random.default_rng(2).uniform(-1000, 1000, (200_000, 3))
    frac = np.bincount(woodland.labels(pts), minlength=4) / len(pts)
    np.testing.assert_allclose(frac, woodland.fractions, atol=0.04)


def test_dark_patches(woodland: CamouflageField) -> None:
    k = woodland.dark_index
    lum = np.array(woodland.colors[k]) @ np.array([0.2126, 0.7152, 0.0722])
    assert lum < 0.08
    for name in PALETTES:
        f = CamouflageField.from_palette(name, patch_size_mm=10.0)
        dark = np.array(f.colors[f.dark_index]) @ np.array([0.2126, 0.7152, 0.0722])
        assert dark < 0.1 and f.fractions[f.dark_index] >= 0.1, name


def test_piecewise_constant_with_hard_edges_and_patch_size(woodland: CamouflageField) -> None:
    # 20000 samples along a 3 m line: long flat runs, few switches, and the mean run
    # length is of the order of the patch size (30 mm).
    t = np.linspace(0.0, 3000.0, 20_001)
    pts = np.stack([t, 0.3 * t + 5.0, -0.2 * t + 11.0], axis=1)
    lab = woodland.labels(pts)
    switches = np.count_nonzero(np.diff(lab))
    mean_run_mm = 3000.0 * 1.0442 / max(switches, 1)  # line length is 3000 * |(1, .3, -.2)|
    assert 5.0 < mean_run_mm < 80.0
    # patch size scales the pattern exactly
    big = CamouflageField.from_palette("woodland", patch_size_mm=300.0, seed=7)
    np.testing.assert_array_equal(big.labels(pts * 10.0), lab)


def test_deterministic_and_seed_dependent() -> None:
    pts = np.random.default_rng(3).uniform(-200, 200, (20_000, 3))
    a = CamouflageField.from_palette("desert", patch_size_mm=20.0, seed=1)
    b = CamouflageField.from_palette("desert", patch_size_mm=20.0, seed=1)
    c = CamouflageField.from_palette("desert", patch_size_mm=20.0, seed=2)
    np.testing.assert_array_equal(a(pts), b(pts))
    assert (a.labels(pts) != c.labels(pts)).mean() > 0.3


def test_chunking_does_not_change_results(woodland: CamouflageField) -> None:
    pts = np.random.default_rng(4).uniform(-300, 300, (30_000, 3))
    whole = woodland.labels(pts)
    parts = np.concatenate([woodland.labels(pts[i : i + 777]) for i in range(0, len(pts), 777)])
    np.testing.assert_array_equal(whole, parts)
    assert woodland.labels(np.zeros((0, 3))).shape == (0,)
    np.testing.assert_array_equal(woodland.labels(pts.astype(np.float32)[:10]).shape, (10,))


def test_custom_two_colour_field() -> None:
    bw = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    f = CamouflageField(bw, (0.5, 0.5), patch_size_mm=5.0, octaves=1)
    pts = np.random.default_rng(5).uniform(-200, 200, (100_000, 3))
    assert abs(f.labels(pts).mean() - 0.5) < 0.04
    assert f.name == "custom"


def test_plain_paint_and_class_defaults() -> None:
    for cls, pal in CLASS_PALETTES.items():
        paint = plain_paint(cls)
        assert isinstance(paint, UniformAlbedo)
        assert paint.rgb == PALETTES[pal].colors[0]
        field = camouflage_field(cls, patch_size_mm=10.0)
        assert field.name == pal
    assert camouflage_field("tank", patch_size_mm=10.0, palette="naval").name == "naval"


GOOD = dict(colors=((0.1, 0.1, 0.1), (0.5, 0.5, 0.5)), fractions=(0.5, 0.5))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            {"colors": ((0.1, 0.1, 0.1),), "fractions": (1.0,)},
            r"colors: expected 2 to 8 paint colours, got 1",
        ),
        (
            {"colors": ((0.1, 0.1), (0.2, 0.2)), "fractions": (0.5, 0.5)},
            r"colors: expected shape \(\*, 3\)",
        ),
        (
            {"colors": ((0.1, 0.1, 1.5), (0.2, 0.2, 0.2))},
            r"colors: expected albedo values in \[0, 1\]",
        ),
        ({"fractions": (0.2, 0.3, 0.5)}, r"fractions: expected 2 values \(one per colour\), got 3"),
        ({"fractions": (0.7, 0.7)}, r"fractions: expected positive values summing to 1"),
        ({"fractions": (1.0, 0.0)}, r"fractions: expected positive values summing to 1"),
        ({"patch_size_mm": 0.0}, r"patch_size_mm: expected a finite number > 0"),
        ({"seed": -3}, r"seed: expected a non-negative integer"),
        ({"octaves": 0}, r"octaves: expected a value in \[1, 4\]"),
        ({"octaves": 2.5}, r"octaves: expected an integer in \[1, 4\]"),
    ],
)
def test_field_errors(kwargs: dict, match: str) -> None:
    args = {**GOOD, **kwargs}
    with pytest.raises(InputError, match=match):
        CamouflageField(**args)


def test_other_errors(woodland: CamouflageField) -> None:
    with pytest.raises(InputError, match=r"palette: expected one of woodland, desert"):
        CamouflageField.from_palette("zebra")
    with pytest.raises(InputError, match=r"target_class: expected one of tank"):
        plain_paint("boat")
    with pytest.raises(InputError, match=r"target_class: expected one of tank"):
        camouflage_field("boat", patch_size_mm=1.0)
    with pytest.raises(InputError, match=r"palette: expected one of"):
        plain_paint("tank", palette="zebra")
    with pytest.raises(InputError, match=r"points_obj: expected shape \(\*, 3\), got \(4, 2\)"):
        woodland.labels(np.zeros((4, 2)))


def test_copy_rebuilds_the_same_field(woodland: CamouflageField) -> None:
    import copy

    twin = copy.deepcopy(woodland)
    assert twin is not woodland and twin.patch_size_mm == woodland.patch_size_mm
    pts = np.random.default_rng(6).uniform(-100, 100, (2000, 3))
    np.testing.assert_array_equal(twin(pts), woodland(pts))
    assert len(woodland.__reduce__()[1]) == 6  # parameters only, no lattice table
