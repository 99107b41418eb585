"""The right view's gain field: recovered from a matched pair, and what it buys the
matcher when the views differ in exposure, colour balance and vignetting."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.reconstruct.stereo.photometric import GainField, fit_gain_field


def _scene(h: int, w: int, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    out = np.empty((h, w, 3), np.float32)
    for c in range(3):
        t = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5)
        out[..., c] = 120 + 35 * t / t.std()
    return out


def _vignetting(h: int, w: int, corner: float) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    return 1.0 - (1.0 - corner) * r2


def test_fit_recovers_a_known_gain_field() -> None:
    """Right = left shifted by 12 px, darker by 0.7, cast (0.8, 1, 1.2), 40 % vignetting:
    the fitted field undoes it to within 1 % everywhere the views overlap."""
    h, w, d = 200, 260, 12
    scene = _scene(h, w + d)
    left = scene[:, :w]
    vig = _vignetting(h, w, 0.6)
    true_gain = 0.7 * vig[..., None] * np.array([0.8, 1.0, 1.2])
    right = scene[:, d:d + w] * true_gain  # right(x - d) = left(x)
    disp = np.full((h, w), float(d))
    field = fit_gain_field(np.clip(left, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8),
                           disp, np.ones((h, w), bool))
    g = field.evaluate()
    np.testing.assert_allclose(g[:, :w - d], 1.0 / true_gain[:, :w - d], rtol=0.01)
    corrected = field.apply(np.clip(right, 0, 255).astype(np.uint8)).astype(np.float64)
    assert np.abs(corrected[:, :w - d] - np.clip(left[:, d:], 0, 255)).mean() < 1.5


def test_fit_ignores_wrong_matches_in_one_channel_only() -> None:
    """A quarter of the matches wrong in the red channel alone (a saturated highlight, a
    coloured reflection): the robust weights are each channel's own, so red is still
    recovered to 1 % and green and blue exactly as without the outliers."""
    h, w, d = 200, 260, 12
    scene = _scene(h, w + d, 4)
    left = np.clip(scene[:, :w], 0, 255).astype(np.uint8)
    true_gain = 0.8 * _vignetting(h, w, 0.7)[..., None] * np.array([0.9, 1.0, 1.1])
    right = np.clip(scene[:, d:d + w] * true_gain, 0, 255).astype(np.uint8)
    disp, valid = np.full((h, w), float(d)), np.ones((h, w), bool)
    clean = fit_gain_field(left, right, disp, valid).evaluate()
    # wrong values that stay usable (neither near black nor near white): the same samples
    wrong = (np.random.default_rng(7).random((h, w)) < 0.25) & (left[..., 0] > 20) & (left[..., 0] < 150)
    hurt = left.copy()
    hurt[..., 0][wrong] += 80
    g = fit_gain_field(hurt, right, disp, valid).evaluate()
    np.testing.assert_allclose(g[:, :w - d, 0], 1.0 / true_gain[:, :w - d, 0], rtol=0.01)
    np.testing.assert_allclose(g[..., 1:], clean[..., 1:], rtol=1e-12)


def test_identity_and_negligible_fields() -> None:
    img = np.full((10, 12, 3), 100, np.uint8)
    f = GainField.identity(3, (12, 10))
    assert f.is_identity and f.negligible()
    assert f.apply(img) is img
    assert np.all(f.evaluate() == 1.0)
    # too few samples: identity
    few = fit_gain_field(img, img, np.zeros((10, 12)), np.zeros((10, 12), bool))
    assert few.is_identity


def test_evaluate_rows_and_scale() -> None:
    rng = np.random.default_rng(3)
    coef = rng.normal(0, 0.05, (1, 6))
    f = GainField(coef, 2, (300, 200))
    full = f.evaluate()
    np.testing.assert_allclose(f.evaluate(slice(50, 90)), full[50:90], rtol=2e-4)
    # against a direct evaluation at the pixel centres (the grid's interpolation error
    # is ~1e-4 of the gain, far below what an 8-bit view resolves)
    y, x = np.mgrid[0:200, 0:300].astype(np.float64)
    xn, yn = x / 299 * 2 - 1, y / 199 * 2 - 1
    terms = [(i, j) for i in range(3) for j in range(3 - i)]
    direct = np.exp(sum(c * xn**i * yn**j for c, (i, j) in zip(coef[0], terms, strict=True)))
    np.testing.assert_allclose(full[..., 0], direct, rtol=2e-4)


def test_fit_checks_its_inputs() -> None:
    a = np.zeros((5, 6, 3), np.uint8)
    with pytest.raises(InputError, match="same shape"):
        fit_gain_field(a, a[:, :5], np.zeros((5, 6)), np.ones((5, 6), bool))
    with pytest.raises(InputError, match="max_degree"):
        fit_gain_field(a, a, np.zeros((5, 6)), np.ones((5, 6), bool), max_degree=9)


def test_matcher_equalizes_a_vignetted_darker_right_view() -> None:
    """The dense matcher on a pair whose right view is 30 % darker, colour-cast and
    vignetted 40 % at the corners (a heavy colour-difference weight, so the views'
    values matter): with ``equalize`` the error rate stays that of the untouched
    pair; without it, it grows."""
    from prism3d.reconstruct.stereo.match import MatchOptions, match_stereo_full

    h, w, d = 180, 240, 9
    scene = _scene(h, w + 40, 5)
    left = np.clip(scene[:, 20:20 + w], 0, 255).astype(np.uint8)
    right = scene[:, 20 + d:20 + d + w]  # right(x - d) = left(x)
    truth = np.full((h, w), float(d))
    gain = 0.7 * _vignetting(h, w, 0.6)[..., None] * np.array([0.8, 1.0, 1.2])
    clean = np.clip(right, 0, 255).astype(np.uint8)
    dark = np.clip(right * gain, 0, 255).astype(np.uint8)

    def bad(r: np.ndarray, equalize: bool) -> float:
        res = match_stereo_full(left, r, min_disp=0, num_disp=32,
                                options=MatchOptions(equalize=equalize, ad_weight=3.0))
        return float(np.mean(np.abs(res.disparity[:, 20:-20] - truth[:, 20:-20]) > 0.5))

    base = bad(clean, True)
    assert bad(dark, True) <= base + 0.01
    assert bad(dark, False) > bad(dark, True) + 0.01
