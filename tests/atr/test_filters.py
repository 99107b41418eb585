"""Known-answer tests of the correlation filters and peak metrics."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.atr.filters import (
    correlate,
    mace_filter,
    mach_filter,
    otmach_filter,
    peak_metrics,
    psr,
    umace_filter,
)

from prism3d.errors import InputError


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(3)
    base = np.zeros((32, 32))
    base[10:22, 8:24] = 1.0
    return np.stack([base + 0.3 * rng.standard_normal((32, 32)) for _ in range(5)])


def test_mace_constraints_exact(images):
    f = mace_filter(images)
    for x in images:
        c = correlate(f, x)
        assert c[16, 16] == pytest.approx(1.0, abs=1e-9)
        assert np.argmax(c) == 16 * 32 + 16  # the constraint value is the peak


def test_shift_moves_peak(images):
    f = mace_filter(images)
    shifted = np.roll(images[2], (3, -5), axis=(0, 1))
    c = correlate(f, shifted)
    r, q = np.unravel_index(np.argmax(c), c.shape)
    assert (r, q) == (16 + 3, 16 - 5)
    assert c[r, q] == pytest.approx(1.0, abs=1e-9)
    m = peak_metrics(c[None])
    assert (m["row"][0], m["col"][0]) == (19, 11)


def test_otmach_limits(images):
    X = np.fft.fft2(images)
    m = X.mean(axis=0)
    D = np.mean(np.abs(X) ** 2, axis=0)
    S = np.mean(np.abs(X - m) ** 2, axis=0)
    # (0, 1, 0) is UMACE, (0, 0, 1) is MACH (same up to the tiny regulariser)
    np.testing.assert_allclose(
        otmach_filter(images, 0, 1, 0).freq, umace_filter(images).freq, rtol=1e-12
    )
    np.testing.assert_allclose(
        otmach_filter(images, 0, 0, 1).freq, mach_filter(images).freq, rtol=1e-12
    )
    np.testing.assert_allclose(umace_filter(images).freq, m / D, rtol=1e-6)
    np.testing.assert_allclose(mach_filter(images).freq, m / S, rtol=1e-6)
    # (1, 0, 0): matched filter of the mean image (a constant times fft(mean))
    f = otmach_filter(images, 1, 0, 0).freq
    ratio = f / m
    np.testing.assert_allclose(ratio, ratio.flat[0], rtol=1e-9)
    # scaling all weights scales the filter: PSR unchanged
    a = otmach_filter(images, 0.1, 0.5, 1.0)
    b = otmach_filter(images, 1.0, 5.0, 10.0)
    np.testing.assert_allclose(a.freq, 10 * b.freq, rtol=1e-9)
    assert psr(correlate(a, images[0])) == pytest.approx(psr(correlate(b, images[0])))


def test_mach_peak_equals_mean_correlation_energy_ratio(images):
    # UMACE correlation of the class mean at the origin = (1/d) sum |m|^2 / D
    f = umace_filter(images)
    mean_img = images.mean(axis=0)
    c = correlate(f, mean_img)
    X = np.fft.fft2(images)
    m = X.mean(axis=0)
    D = np.mean(np.abs(X) ** 2, axis=0)
    assert c[16, 16] == pytest.approx(float(np.sum(np.abs(m) ** 2 / D) / m.size), rel=1e-6)


def test_peak_metrics_known_plane():
    c = np.zeros((40, 40))
    rng = np.random.default_rng(0)
    c += rng.normal(0, 1.0, c.shape)
    c[7, 33] = 50.0
    m = peak_metrics(c)
    assert (m["row"], m["col"]) == (7, 33)
    # recompute PSR by hand: 20x20 window centred on the peak (wrapping) minus 5x5
    rr = np.arange(-10, 10) + 7
    cc = np.arange(-10, 10) + 33
    win = c[np.ix_(rr % 40, cc % 40)]
    keep = np.ones((20, 20), bool)
    keep[8:13, 8:13] = False
    side = win[keep]
    assert m["psr"] == pytest.approx((50 - side.mean()) / side.std())
    assert m["pce"] == pytest.approx(2500 / np.sum(c**2))


def test_filter_errors(images):
    with pytest.raises(InputError, match="linearly dependent"):
        mace_filter(np.stack([images[0], images[0]]))
    with pytest.raises(InputError, match="NaN"):
        bad = images.copy()
        bad[0, 0, 0] = np.nan
        umace_filter(bad)
    with pytest.raises(InputError, match="ndim|dimensions|expected"):
        umace_filter(images[0])
    with pytest.raises(InputError, match="alpha"):
        otmach_filter(images, -1, 0, 1)
    with pytest.raises(InputError, match="must be > 0"):
        otmach_filter(images, 0, 0, 0)
    with pytest.raises(InputError, match="S = 0"):
        mach_filter(np.stack([images[0], images[0]]))
    with pytest.raises(InputError, match="shape"):
        correlate(umace_filter(images), np.zeros((8, 8)))
    with pytest.raises(InputError, match="exceeds"):
        peak_metrics(np.zeros((10, 10)))
    with pytest.raises(InputError, match="exclude"):
        peak_metrics(np.zeros((40, 40)), window=5, exclude=5)
