"""Tests of the projector gratings (prism3d.capture.pattern)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from prism3d.capture.pattern import (
    DEFAULT_COLORS,
    check_window_unique,
    de_bruijn,
    grid_pattern,
    save_pattern_png,
    stripe_ids,
    stripe_pattern,
    stripe_sequence,
)
from prism3d.errors import InputError


def test_de_bruijn_known_answer_and_windows():
    assert de_bruijn(2, 3).tolist() == [0, 0, 0, 1, 0, 1, 1, 1]
    for k, n in ((2, 4), (3, 3), (6, 3), (4, 5)):
        s = de_bruijn(k, n)
        assert len(s) == k**n
        cyc = np.concatenate([s, s[: n - 1]])
        words = np.lib.stride_tricks.sliding_window_view(cyc, n)
        assert len(np.unique(words, axis=0)) == k**n


@pytest.mark.parametrize("window", [1, 2, 3, 4])
def test_stripe_sequence_is_maximal_and_unique(window):
    k = 6
    cap = k * (k - 1) ** (window - 1) + (window - 1 if window > 1 else 0)
    s = stripe_sequence(cap, n_colors=k, window=window)
    assert check_window_unique(s, window)
    with pytest.raises(InputError, match="uniquely coded"):
        stripe_sequence(cap + 1, n_colors=k, window=window)


def test_stripe_pattern_windows_unique_along_x():
    p = stripe_pattern(1024, 40, period_px=8, seed=None)
    assert p.shape == (40, 1024, 3) and p.dtype == np.uint8
    assert (p == p[:1]).all()
    ids = stripe_ids(1024, period_px=8)
    # decode the colours back from the image
    table = {tuple(c): i for i, c in enumerate(DEFAULT_COLORS.tolist())}
    decoded = np.array([table[tuple(c)] for c in p[0, ::8].tolist()])
    assert np.array_equal(decoded, ids[::8])
    assert check_window_unique(decoded, 3)
    assert not np.any(decoded[1:] == decoded[:-1])


def test_seed_is_deterministic():
    a = stripe_pattern(512, 4, seed=3)
    b = stripe_pattern(512, 4, seed=3)
    c = stripe_pattern(512, 4, seed=4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert check_window_unique(stripe_ids(512, seed=4)[::8], 3)


def test_grid_pattern_rows_unique():
    g = grid_pattern(640, 160, period_px=8, line_px=1, row_shift=3)
    assert g.shape == (160, 640, 3)
    assert (g[0] == 0).all() and (g[:, 0] == 0).all()  # grid lines
    table = {tuple(c): i for i, c in enumerate(DEFAULT_COLORS.tolist())}
    rows = []
    for r in range(4, 160, 8):
        ids = np.array([table[tuple(c)] for c in g[r, 4::8].tolist()])
        assert check_window_unique(ids, 3)
        rows.append(ids)
    assert not np.array_equal(rows[0], rows[1])  # rows are shifted


def test_check_window_unique_false_cases():
    assert not check_window_unique(np.array([0, 1, 1, 2]), 2)  # equal neighbours
    assert not check_window_unique(np.array([0, 1, 2, 0, 1, 2]), 3)  # repeated run
    assert check_window_unique(np.array([0, 1]), 3)


def test_save_pattern_png_roundtrip_rgb(tmp_path):
    p = stripe_pattern(64, 8)
    path = tmp_path / "pattern.png"
    save_pattern_png(path, p)
    back = cv2.imread(str(path))[:, :, ::-1]
    assert np.array_equal(back, p)
    assert [x.name for x in tmp_path.iterdir()] == ["pattern.png"]


def test_pattern_errors(tmp_path):
    with pytest.raises(InputError, match="k \\(alphabet size\\)"):
        de_bruijn(1, 3)
    with pytest.raises(InputError, match="n \\(word length\\)"):
        de_bruijn(3, 0)
    with pytest.raises(InputError, match="too long"):
        de_bruijn(100, 5)
    with pytest.raises(InputError, match="at least 3 colours"):
        stripe_sequence(5, n_colors=2)
    with pytest.raises(InputError, match="window"):
        stripe_sequence(5, window=0)
    with pytest.raises(InputError, match="n_stripes"):
        stripe_sequence(0)
    with pytest.raises(InputError, match="period_px"):
        stripe_pattern(64, 8, period_px=0)
    with pytest.raises(InputError, match="period_px: expected an integer"):
        stripe_ids(64, period_px=2.5)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="width"):
        stripe_ids(0)
    with pytest.raises(InputError, match="height"):
        stripe_pattern(64, 0)
    with pytest.raises(InputError, match="colours must be distinct"):
        stripe_pattern(64, 8, colors=np.array([[0, 0, 0], [0, 0, 0], [1, 1, 1]]))
    with pytest.raises(InputError, match="at least 3 colours"):
        stripe_pattern(64, 8, colors=np.array([[0, 0, 0], [255, 0, 0]]))
    with pytest.raises(InputError, match="\\[0, 255\\]"):
        stripe_pattern(64, 8, colors=np.array([[0, 0, 0], [256, 0, 0], [0, 9, 0]]))
    with pytest.raises(InputError, match="colors: expected shape"):
        stripe_pattern(64, 8, colors=np.zeros((3, 4)))
    with pytest.raises(InputError, match="grid columns"):
        grid_pattern(10000, 8, period_px=8)
    with pytest.raises(InputError, match="line_px"):
        grid_pattern(64, 64, line_px=8)
    with pytest.raises(InputError, match="period_px"):
        grid_pattern(64, 64, period_px=1)
    with pytest.raises(InputError, match="row_shift"):
        grid_pattern(64, 64, row_shift=-1)
    with pytest.raises(InputError, match="width and height"):
        grid_pattern(0, 64)
    with pytest.raises(InputError, match="window"):
        check_window_unique(np.array([0, 1]), 0)
    with pytest.raises(InputError, match=".png"):
        save_pattern_png(tmp_path / "p.jpg", stripe_pattern(8, 8))
    with pytest.raises(InputError, match="uint8"):
        save_pattern_png(tmp_path / "p.png", np.zeros((8, 8, 3), np.uint16))
    with pytest.raises(InputError, match="3 channels"):
        save_pattern_png(tmp_path / "p.png", np.zeros((8, 8, 4), np.uint8))
