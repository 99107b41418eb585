"""Slanted-plane sub-pixel refinement: known-answer tests on synthetic stripe pairs.

The stripes are flat colours (like the rig's grating) integrated over each pixel and
blurred by a lens PSF of sigma 1.5 px: sub-pixel disparity needs images sampled finely
enough to interpolate (unblurred box-integrated steps alias by up to ~0.15 px with any
interpolator; at sigma 1.0 the error is ~0.004 px on an exactly shifted pair)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from prism3d.reconstruct.stereo.refine import refine_slanted

from prism3d.errors import InputError

H, W = 120, 260
STRIPE = 11.0  # px, flat-coloured stripes like the rig's grating
PSF = 1.5  # px, Gaussian optical blur


def _stripe_colours(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(40, 220, size=(n, 3))


def _render(xsrc: np.ndarray, colours: np.ndarray, ss: int = 8) -> np.ndarray:
    """Box-integrate flat-coloured stripes over each pixel; ``xsrc(x, y)`` maps image
    x to stripe coordinate (ss sub-samples per pixel along x)."""
    out = np.zeros((H, W, 3))
    for s in range(ss):
        u = xsrc((np.arange(W)[None, :] - 0.5 + (s + 0.5) / ss), np.arange(H)[:, None])
        idx = np.floor(u / STRIPE).astype(int) % len(colours)
        out += colours[idx]
    return out / ss


def _noisy(left: np.ndarray, right: np.ndarray, seed: int, sigma: float = 1.0):
    """Both views with Gaussian sensor noise, as 8-bit images."""
    rng = np.random.default_rng(seed)
    return tuple(np.clip(v + rng.normal(0, sigma, v.shape), 0, 255).astype(np.uint8) for v in (left, right))


def _pair(slope: float, seed: int = 0, noise: float = 1.0):
    """Left/right views of a slanted plane d(x, y) = d0 + slope x + 0.02 y."""
    d0 = 40.0
    cols = _stripe_colours(64, seed)

    def disparity(x, y):
        return d0 + slope * x + 0.02 * y

    left = cv2.GaussianBlur(_render(lambda x, y: x + 0.0 * y, cols), (0, 0), PSF)
    # right pixel xr sees the point of left pixel x with x - d(x, y) = xr
    right = cv2.GaussianBlur(_render(lambda xr, y: (xr + d0 + 0.02 * y) / (1.0 - slope), cols), (0, 0), PSF)
    left, right = _noisy(left, right, seed + 1, noise)
    xx, yy = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    return left, right, disparity(xx, yy).astype(np.float32)


def _inner(region: np.ndarray, window: tuple[int, int] = (7, 25)) -> np.ndarray:
    """Pixels whose whole refinement window lies in ``region``."""
    k = np.ones(window, np.uint8)
    return cv2.erode(region.astype(np.uint8), k, borderValue=0).astype(bool)


def _staircase(truth: np.ndarray) -> np.ndarray:
    """What a constant-disparity window matcher returns inside flat stripes: one
    value per stripe (the plane at the stripe's centre)."""
    xx = np.arange(W)[None, :]
    centre = (np.floor(xx / STRIPE) + 0.5) * STRIPE
    cols = np.clip(np.round(centre).astype(int), 0, W - 1)
    return np.take_along_axis(truth, np.broadcast_to(cols, truth.shape), axis=1).astype(np.float32)


@pytest.mark.parametrize("slope", [0.0, 0.08, -0.1])
def test_removes_the_staircase_on_slanted_stripes(slope: float) -> None:
    left, right, truth = _pair(slope)
    init = _staircase(truth)
    valid = np.zeros((H, W), bool)
    valid[15:-15, 60:-20] = True
    before = np.sqrt(np.mean((init - truth)[valid] ** 2))
    d, resid, std = refine_slanted(left, right, init, valid)
    # away from the region's outline (half a window): there a one-sided window with
    # one stripe edge extrapolates the plane (0.04-0.23 px here, measured)
    inner = _inner(valid)
    rms = np.sqrt(np.mean((d - truth)[inner] ** 2))
    assert rms < 0.03, (rms, before)
    if slope != 0.0:
        assert before > 0.25  # the staircase was real
    assert np.all(np.isfinite(resid[valid])) and np.all(np.isnan(resid[~valid]))
    assert np.median(resid[valid]) < 0.2
    # the predicted standard deviation is of the order of the pixel noise's effect
    assert 0 < np.median(std[valid]) < 0.05 and np.all(np.isnan(std[~valid]))
    np.testing.assert_array_equal(d[~valid], init[~valid])  # untouched elsewhere


def test_fills_holes_from_the_planes_of_their_windows() -> None:
    left, right, truth = _pair(0.08, seed=3)
    init = _staircase(truth)
    rng = np.random.default_rng(0)
    region = np.zeros((H, W), bool)
    region[15:-15, 60:-20] = True
    holes = region & (rng.random((H, W)) < 0.4)
    valid = region & ~holes
    d, resid, _ = refine_slanted(left, right, init, valid, extra=holes)
    inner = _inner(region)
    for m in (valid & inner, holes & inner):
        assert np.sqrt(np.mean((d - truth)[m] ** 2)) < 0.03
        assert np.all(np.isfinite(resid[m]))


def test_residual_flags_pixels_the_plane_does_not_explain() -> None:
    left, right, truth = _pair(0.05, seed=5)
    right = right.copy()
    # an occluder in the right view only: the left pixels behind it have no match
    right[40:80, 100:140] = np.random.default_rng(9).integers(0, 255, (40, 40, 3), dtype=np.uint8)
    valid = np.zeros((H, W), bool)
    valid[15:-15, 60:-20] = True
    d, resid, std = refine_slanted(left, right, truth + 0.3, valid)
    occluded = np.zeros_like(valid)
    occluded[45:75, 148:170] = True  # maps into the occluder: x - d in [107, 129]
    clear = _inner(valid)
    clear[30:90, 110:215] = False  # windows touching the occluded matches
    assert np.median(resid[occluded]) > 10 * np.median(resid[clear])
    assert np.median(std[occluded]) > 3 * np.median(std[clear])
    assert np.sqrt(np.mean((d - truth)[clear] ** 2)) < 0.03


def test_bad_input() -> None:
    left, right, truth = _pair(0.0)
    valid = np.ones((H, W), bool)
    with pytest.raises(InputError, match="same shape|shape"):
        refine_slanted(left, right[:, :-1], truth, valid)
    with pytest.raises(InputError, match="window"):
        refine_slanted(left, right, truth, valid, window=(6, 25))
    with pytest.raises(InputError, match="iterations"):
        refine_slanted(left, right, truth, valid, iterations=0)
    with pytest.raises(InputError, match="must match"):
        refine_slanted(left, right, truth[:-1], valid)
    # nothing to refine: returned as given
    d, resid, std = refine_slanted(left, right, truth, np.zeros((H, W), bool))
    np.testing.assert_array_equal(d, truth)
    assert np.isnan(resid).all() and np.isnan(std).all()


def test_orientation_weight_resists_vertical_misalignment() -> None:
    """A strong edge 15 degrees off the epipolar lines over a weak vertical grating,
    the right view 0.05 px out of vertical alignment: unweighted, the edge turns the
    misalignment into 0.06 px of disparity near it (measured); weighting each
    pixel's equations by gx^2 / (gx^2 + gy^2 + 1) leaves more of the fit to the
    grating (0.037 px measured). Aligned views: both exact. Measured on the plane fit
    alone (``offset=False``): the per-window offset, on by default, absorbs part of the
    misalignment itself (0.043 / 0.035 px unweighted / weighted), which is asserted
    last."""
    h, w, d_true = 80, 200, 8.3
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    slope = np.tan(np.radians(15.0))

    def scene(x, y):
        edge = 1.0 / (1.0 + np.exp(-(y - 40.0 - slope * (x - 100.0)) / 0.8))
        return 60.0 + 10.0 * np.sin(2 * np.pi * x / 7.3) + 120.0 * edge

    left = scene(xx, yy).astype(np.float32)
    valid = np.zeros((h, w), bool)
    valid[10:-10, 30:-30] = True
    d0 = np.full((h, w), d_true + 0.3, np.float32)
    near = valid & (np.abs(yy - 40.0 - slope * (xx - 100.0)) < 4)
    err = {}
    for eps in (0.0, 0.05):
        right = scene(xx + d_true, yy + eps).astype(np.float32)
        for ow in (False, True):
            d, _, _ = refine_slanted(left, right, d0, valid, orientation_weight=ow, offset=False)
            err[eps, ow] = float(np.median(np.abs(d[near] - d_true)))
    assert err[0.0, True] < 0.002 and err[0.0, False] < 0.002, err
    assert err[0.05, True] < 0.7 * err[0.05, False], err
    right = scene(xx + d_true, yy + 0.05).astype(np.float32)
    d, _, _ = refine_slanted(left, right, d0, valid)
    assert float(np.median(np.abs(d[near] - d_true))) < err[0.05, False], err


@pytest.mark.parametrize("c", [0.0015, -0.0015])
def test_curvature_correction_removes_the_plane_fits_bias(c: float) -> None:
    """Disparity curved along the rows, d = d0 + c (x - xc)^2: a cylinder seen across
    its axis (c = 0.0015 px/px^2 is a 15 mm radius at the paper's geometry). A plane
    fit over a 25-column window is off by ~c * 50 px^2 (0.075 px measured, towards a
    flatter surface); the curvature correction removes 77-84 % of that (measured)."""
    d0, xc = 40.0, 150.0
    cols = _stripe_colours(64, 7)
    left = cv2.GaussianBlur(_render(lambda x, y: x + 0.0 * y, cols), (0, 0), PSF)

    def left_x(xr, y):
        # the left pixel x = xc + t seen at right pixel xr: xr = x - d0 - c t^2
        # (right pixels no left pixel in the image reaches: clamped, never used)
        q = xr - xc + d0
        return xc + (1.0 - np.sqrt(np.maximum(1.0 - 4.0 * c * q, 0.0))) / (2.0 * c) + 0.0 * y

    right = cv2.GaussianBlur(_render(left_x, cols), (0, 0), PSF)
    left, right = _noisy(left, right, 8)
    xx = np.broadcast_to(np.arange(W, dtype=float)[None, :], (H, W))
    truth = (d0 + c * (xx - xc) ** 2).astype(np.float32)
    valid = np.zeros((H, W), bool)
    valid[15:-15, 60:-20] = True
    inner = _inner(valid)
    init = truth + np.float32(0.3)
    err = {}
    for corr in (False, True):
        d, _, _ = refine_slanted(left, right, init, valid, curvature=corr)
        err[corr] = (d - truth)[inner]
    # the plane fit flattens the surface: an error of the sign of c, about c * kappa
    bias = float(np.mean(err[False]))
    assert 0.05 < abs(bias) < 0.12 and np.sign(bias) == np.sign(c), bias
    assert abs(float(np.mean(err[True]))) < 0.3 * abs(bias), (float(np.mean(err[True])), bias)
    rms = {k: float(np.sqrt(np.mean(v ** 2))) for k, v in err.items()}
    assert rms[True] < 0.75 * rms[False], rms


@pytest.mark.parametrize("s", [0.08, -0.08])
def test_narrow_window_keeps_a_crease_from_tilting_its_faces(s: float) -> None:
    """Two planes meeting in a vertical crease, d = d0 + s |x - xc|. A window plane
    fit rounds the crease over half its width and the curvature correction spreads
    that over half a window more: the flat faces 4-24 px from the crease come out
    tilted. The pipeline's 7x19 window (see ``reconstruct_shot``) shrinks that by
    ~40 % against 7x25 (measured: mean |error| 0.074-0.080 -> 0.040-0.048 px); far from the
    crease both are accurate."""
    d0, xc = 40.0, 140.0
    cols = _stripe_colours(64, 3)
    left = cv2.GaussianBlur(_render(lambda x, y: x + 0.0 * y, cols), (0, 0), PSF)

    def left_x(xr, y):
        # the left pixel x seen at right pixel xr = x - d0 - s |x - xc|, per face
        beyond = (xr + d0 - s * xc) / (1.0 - s)
        before = (xr + d0 + s * xc) / (1.0 + s)
        return np.where(xr >= xc - d0, beyond, before) + 0.0 * y

    right = cv2.GaussianBlur(_render(left_x, cols), (0, 0), PSF)
    left, right = _noisy(left, right, 4)
    xx = np.broadcast_to(np.arange(W, dtype=float)[None, :], (H, W))
    truth = (d0 + s * np.abs(xx - xc)).astype(np.float32)
    valid = np.zeros((H, W), bool)
    valid[15:-15, 30:-30] = True
    dist = np.abs(xx - xc)
    inner = _inner(valid)  # whole 7x25 window inside: the same pixels for both widths
    near = inner & (dist >= 4) & (dist < 24)
    far = inner & (dist >= 24) & (dist < 40)  # further left, matches leave the right view
    err = {}
    for cols_ in (25, 19):
        d, _, _ = refine_slanted(left, right, truth + np.float32(0.3), valid, window=(7, cols_))
        err[cols_] = d - truth
    near_err = {k: float(np.mean(np.abs(v[near]))) for k, v in err.items()}
    assert near_err[19] < 0.75 * near_err[25], near_err
    assert max(abs(float(np.mean(v[far]))) for v in err.values()) < 0.02
