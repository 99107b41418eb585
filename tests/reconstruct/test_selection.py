"""Pixel selection: noise from the shot, texture above that noise, unlit background,
occlusions, plane fills with their predicted std, confidence <-> std."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.reconstruct.stereo.selection import (
    Coverage,
    confidence_from_std,
    enclosed,
    estimate_noise,
    fill_from_planes,
    isolated_matches,
    near,
    occlusions,
    std_from_confidence,
    surrounded,
    texture_energy,
    textured,
    unlit,
)


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5)
    return 128 + 40 * t / t.std()


@pytest.mark.parametrize("sigma", [0.8, 2.0, 5.0])
def test_estimate_noise_recovers_the_added_noise(sigma: float) -> None:
    """Known Gaussian noise on a scene that is half smooth ramp, half texture."""
    rng = np.random.default_rng(1)
    h, w = 256, 320
    img = np.tile(np.linspace(30, 200, w, dtype=np.float32), (h, 1))
    img[:, w // 2:] = _texture(h, w - w // 2)
    noisy = img + rng.normal(0, sigma, img.shape)
    est = estimate_noise(noisy)
    assert abs(est - sigma) < 0.12 * sigma, (est, sigma)


def test_estimate_noise_floor_and_checks() -> None:
    assert estimate_noise(np.full((64, 64), 7.0)) == pytest.approx(0.29)
    with pytest.raises(InputError, match="image"):
        estimate_noise(np.zeros((2, 2)))


def test_textured_is_energy_above_the_noise() -> None:
    """Pure noise is untextured at any noise level; a weak texture well above the noise
    is textured; an isoluminant colour edge is textured (each channel sees it)."""
    rng = np.random.default_rng(2)
    sigma = 2.0
    noise_only = 100 + rng.normal(0, sigma, (80, 120))
    assert textured(noise_only, sigma).mean() < 0.02
    weak = 100 + 0.3 * (_texture(80, 120, 3) - 128) + rng.normal(0, sigma, (80, 120))
    assert textured(weak, sigma)[10:-10, 15:-15].mean() > 0.95
    img = np.empty((60, 80, 3), np.float32)
    img[:, :40] = (35, 130, 22)
    img[:, 40:] = (143, 31, 22)
    img += rng.normal(0, 1.0, img.shape)
    tex = textured(img, 1.0)
    assert tex[30, 40] and not tex[30, 5] and not tex[30, 75]


def test_unlit_background_only_when_it_is_a_floor_of_noise() -> None:
    """A lit textured object on a black, noisy floor: the floor is unlit, the object
    (including its dark camouflage patches) is not; the same dark patch in a
    photograph without a black floor is not unlit."""
    rng = np.random.default_rng(4)
    img = np.clip(rng.normal(1.0, 0.7, (160, 200)), 0, 255)
    obj = _texture(80, 100, 5)
    obj[20:40, 20:50] = 0.15 * obj[20:40, 20:50]  # a dark camouflage patch
    img[40:120, 50:150] = obj
    noise = estimate_noise(img)
    tex = textured(img, noise)
    u = unlit(img, noise, tex)
    assert u[:30].all() and u[:, :40].all()
    assert not u[45:115, 55:145].any()
    photo = _texture(160, 200, 6)
    photo[60:90, 60:120] = 8 + rng.normal(0, 0.5, (30, 60))  # small dark flat patch
    assert not unlit(photo, estimate_noise(photo), textured(photo, estimate_noise(photo))).any()


def test_near_and_enclosed() -> None:
    m = np.zeros((20, 20), bool)
    m[10, 10] = True
    n = near(m, 2)
    assert n.sum() == 24 and not n[10, 10]
    region = np.zeros((20, 30), bool)
    region[5:10, 5:10] = True  # enclosed hole
    region[0:4, 20:25] = True  # touches the border
    region[12:15, 12:15] = True  # touches the outside mask
    out = np.zeros_like(region)
    out[15:18, 12:15] = True
    e = enclosed(region, out)
    assert e[5:10, 5:10].all() and not e[0:4, 20:25].any() and not e[12:15, 12:15].any()


def test_occlusions_of_a_step() -> None:
    """A foreground strip (d = 20) in front of a background (d = 5): the background
    pixels just left of the strip are hidden from the right camera (15 px wide), and
    the first 5 columns match outside the right view."""
    d = np.full((10, 100), 5.0, np.float32)
    d[:, 50:70] = 20.0
    occ, out = occlusions(d)
    assert occ[:, 35:50].all() and not occ[:, :35].any() and not occ[:, 50:].any()
    assert out[:, :5].all() and not out[:, 5:].any()


def test_fill_from_planes_predicts_a_plane_and_its_scatter() -> None:
    rng = np.random.default_rng(7)
    h, w = 60, 80
    yy, xx = np.mgrid[0:h, 0:w]
    plane = 30 + 0.05 * xx - 0.02 * yy
    noise = 0.1
    d = (plane + rng.normal(0, noise, plane.shape)).astype(np.float32)
    known = np.ones((h, w), bool)
    known[20:40, 30:50] = False
    est, std = fill_from_planes(d, known, ~known)
    hole = ~known
    # the plane through ~1000 pixels of scatter 0.1 predicts the hole within a few 0.01
    np.testing.assert_allclose(est[hole], plane[hole], atol=0.06)
    assert np.all(np.abs(std[hole] - noise) < 0.04)  # s^2 (1 + small): about the scatter
    assert np.isnan(est[known]).all()
    # one-sided: a step edge; the left window keeps to its own side
    d2 = np.where(xx < 40, 10.0, 30.0).astype(np.float32)
    k2 = np.ones((h, w), bool)
    k2[:, 36:40] = False
    e_left, s_left = fill_from_planes(d2, k2, ~k2, sides=("left",))
    e_any, s_any = fill_from_planes(d2, k2, ~k2, sides=("centre", "left", "right"))
    assert np.allclose(e_left[~k2], 10.0, atol=1e-3) and np.allclose(e_any[~k2], 10.0, atol=1e-3)
    with pytest.raises(InputError, match="sides"):
        fill_from_planes(d, known, ~known, sides=("up",))
    with pytest.raises(InputError, match="min_fraction"):
        fill_from_planes(d, known, ~known, min_fraction=0)


def test_confidence_and_std_are_inverse() -> None:
    for c in (0.05, 0.5, 0.9, 0.99):
        s = std_from_confidence(c)
        assert confidence_from_std(np.array([s]))[0] == pytest.approx(c, abs=1e-6)
    # 1 px = one standard deviation: the chance of |e| <= 1 is 68 %
    assert confidence_from_std(np.array([1.0]))[0] == pytest.approx(0.6827, abs=1e-4)
    assert confidence_from_std(np.array([np.nan]))[0] == 0.0
    with pytest.raises(InputError, match="confidence"):
        std_from_confidence(1.0)


def test_coverage_summary() -> None:
    c = Coverage(1000, 700, 200, {"no texture": 60, "occluded": 40})
    assert c.kept == 900
    s = c.shares()
    assert s["kept"] == 0.9 and s["occluded"] == 0.04
    line = c.summary()
    assert "kept 90.0%" in line and "6.0% no texture" in line and "4.0% occluded" in line


def test_chance_matches_in_faint_texture_are_isolated_and_a_boards_edges_are_not() -> None:
    """Left half: faint texture where 5 % of the pixels passed the matcher's checks (chance
    agreements, as in a sky); right half: a board of flat squares whose strong edges all
    matched and whose flat, noisy interiors failed. The faint half's matches go; every
    edge match stays, judged by the other edges, not by the failed squares."""
    rng = np.random.default_rng(3)
    h, w = 120, 240
    img = 128 + rng.normal(0, 1.0, (h, w)).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    board = xx >= w // 2
    img[board] = np.where(((yy[board] // 30) + (xx[board] // 30)) % 2 == 0, 40.0, 215.0)
    img[board] += rng.normal(0, 1.0, board.sum())
    energy = texture_energy(img)
    edges = board & (energy > 50 * np.median(energy[board]))
    valid = np.zeros((h, w), bool)
    valid[~board] = rng.random((~board).sum()) < 0.05
    valid |= edges
    out = isolated_matches(valid, np.ones((h, w), bool), energy)
    assert out[~board & valid].mean() > 0.95
    assert not out[edges].any()
    assert not out[~valid].any()


def test_surrounded_needs_surface_on_all_four_sides() -> None:
    m = np.zeros((60, 60), bool)
    m[20:40, 20] = m[20:40, 39] = m[20, 20:40] = m[39, 20:40] = True  # a square outline
    inside = surrounded(m, 25)
    assert inside[25:35, 25:35].all()  # the outline on every side
    assert not inside[5:15, 25:35].any()  # above it: nothing further up
    assert not surrounded(m, 3)[25:35, 25:35].any()  # too far for a 3 px reach
