"""The orthophoto-accuracy benchmark's measuring tools (``benchmarks/bench_ortho_accuracy.py``)
on synthetic images with a known answer: a painted chequer's centre and a known shift."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_ortho_accuracy", ROOT / "benchmarks" / "bench_ortho_accuracy.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _chequer(cy: float, cx: float, angle_deg: float, half: float, rng: np.random.Generator, S: int = 8) -> np.ndarray:
    """A 2 x 2 chequer board on grey ground, rendered 8 x 8 supersampled, with noise."""
    yy, xx = (np.mgrid[0:100 * S, 0:100 * S] + 0.5) / S - 0.5
    t = np.radians(angle_deg)
    u = (xx - cx) * np.cos(t) + (yy - cy) * np.sin(t)
    v = -(xx - cx) * np.sin(t) + (yy - cy) * np.cos(t)
    img = np.where((np.abs(u) < half) & (np.abs(v) < half), np.where(u * v > 0, 30.0, 220.0), 110.0).astype(np.float32)
    img = cv2.resize(img, (100, 100), interpolation=cv2.INTER_AREA) + rng.normal(0, 5, (100, 100)).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("angle", [0.0, 20.0, 45.0, 70.0])
def test_chequer_centre_to_a_fraction_of_a_pixel(bench, angle: float) -> None:
    rng = np.random.default_rng(int(angle))
    img = _chequer(50.3, 47.8, angle, 8.0, rng)
    r, c = bench.chequer_centre(img, 52.0, 46.0, search=6, radius=5)  # started 2.7 px away
    assert np.hypot(r - 50.3, c - 47.8) < 0.25


def test_no_chequer_no_centre(bench) -> None:
    flat = np.full((100, 100), 120, np.uint8)
    assert bench.chequer_centre(flat, 50.0, 50.0, search=6, radius=5) is None


def test_a_false_shift_is_not_confirmed(bench) -> None:
    rng = np.random.default_rng(3)
    a = cv2.GaussianBlur(rng.normal(0, 40, (128, 128)).astype(np.float32), (0, 0), 1.5)
    b = np.roll(a, (3, -4), axis=(0, 1))  # b is a moved 4 px left, 3 px down
    assert bench._ncc_shifted(a, b, -4.0, 3.0) > 0.95
    assert bench._ncc_shifted(a, b, 20.0, 0.0) < bench._ncc_shifted(a, b, -4.0, 3.0)
