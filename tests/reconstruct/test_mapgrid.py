"""Rasters from the survey's ENU grid onto a UTM grid, against exact per-cell conversions."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.geo import MapFrame
from prism3d.reconstruct.survey.mapgrid import LATTICE, Grid, GridWarp, map_grid, resample

# a site mapped in the next zone east (as --crs EPSG:32654 asks), 4.2 deg west of that zone's
# central meridian: the grids turn by 2.5 deg and UTM's scale is 1.0013
FRAME = MapFrame((36.0, 136.8, 0.0), 32654)
ENU = Grid(-640.0, 480.0, 0.25, (3840, 5120))  # 1.28 x 0.96 km


def test_map_grid_covers_the_enu_grid_on_round_corners():
    g = map_grid(FRAME, ENU, 0.25, 50.0, max_cells=10**9)
    assert g.west % 0.25 == 0 and g.north % 0.25 == 0
    H, W = ENU.shape
    corners = np.array([[ENU.west, ENU.north, 50.0], [ENU.west + W * 0.25, ENU.north, 50.0],
                        [ENU.west, ENU.north - H * 0.25, 50.0], [ENU.west + W * 0.25, ENU.north - H * 0.25, 50.0]])
    q = FRAME.enu_to_map(corners)
    assert (q[:, 0] >= g.west).all() and (q[:, 0] <= g.west + g.shape[1] * g.cell).all()
    assert (q[:, 1] <= g.north).all() and (q[:, 1] >= g.north - g.shape[0] * g.cell).all()
    # turned by the convergence and scaled: wider by the scale and sin(gamma) of the other side
    gamma = np.radians(abs(float(FRAME.grid_north_deg(q[:1])[0])))
    assert g.shape[1] * g.cell == pytest.approx(1.0013 * (W * np.cos(gamma) + H * np.sin(gamma)) * 0.25, abs=1.0)
    with pytest.raises(InputError, match="larger cell"):
        map_grid(FRAME, ENU, 0.25, 50.0, max_cells=1000)


def test_warp_matches_exact_conversion_between_lattice_points():
    g = map_grid(FRAME, ENU, 0.25, 50.0, max_cells=10**9)
    w = GridWarp(FRAME, g, 50.0)
    rng = np.random.default_rng(1)
    r = rng.integers(0, g.shape[0], 300)
    c = rng.integers(0, g.shape[1], 300)
    X, Y = w.enu_xy(0, g.shape[0], 0, g.shape[1])
    exact = FRAME.map_to_enu(np.c_[g.west + (c + 0.5) * g.cell, g.north - (r + 0.5) * g.cell, np.full(300, 50.0)])
    err = np.hypot(X[r, c] - exact[:, 0], Y[r, c] - exact[:, 1])
    assert err.max() < 1e-4  # 0.1 mm across lattice steps of LATTICE cells
    dh = w.height_offset(0, g.shape[0], 0, g.shape[1])[r, c]
    np.testing.assert_allclose(exact[:, 2] + dh[:], 50.0, atol=1e-4)
    assert LATTICE > 1


def test_resample_a_plane_exactly_and_keeps_the_holes():
    """A sloping plane (and a hole) sampled on the map grid: the plane at each cell's
    exact ENU position (bilinear is exact on a plane), the hole where it was."""
    small = Grid(-40.0, 30.0, 0.2, (300, 400))
    H, W = small.shape
    yy, xx = np.mgrid[:H, :W]
    X = small.west + (xx + 0.5) * small.cell
    Y = small.north - (yy + 0.5) * small.cell
    plane = (0.05 * X - 0.02 * Y + 12.0).astype(np.float32)
    src = plane.copy()
    src[100:140, 200:260] = np.nan
    g = map_grid(FRAME, small, 0.2, 0.0, max_cells=10**7)
    w = GridWarp(FRAME, g, 0.0)
    out = resample(src, small, w, mode="linear")
    near = resample(src, small, w, mode="nearest")
    assert np.array_equal(np.isfinite(out), np.isfinite(near))
    rr, cc = np.nonzero(np.isfinite(out))
    e = FRAME.map_to_enu(np.c_[g.west + (cc + 0.5) * g.cell, g.north - (rr + 0.5) * g.cell, np.zeros(len(rr))])
    inner = (np.abs(e[:, 0]) < 35) & (np.abs(e[:, 1]) < 25)  # away from the raster's edges
    hole = (e[:, 0] > -0.2 + 200 * 0.2 - 40) & (e[:, 0] < 260 * 0.2 - 40 + 0.2) & \
           (e[:, 1] < 30 - 100 * 0.2 + 0.2) & (e[:, 1] > 30 - 140 * 0.2 - 0.2)
    ok = inner & ~hole
    expect = 0.05 * e[ok, 0] - 0.02 * e[ok, 1] + 12.0
    np.testing.assert_allclose(out[rr[ok], cc[ok]], expect, atol=1e-4)
    # the hole stays a hole: no map cell whose centre is well inside it has a value
    ii, jj = np.mgrid[:g.shape[0], :g.shape[1]]
    m = FRAME.map_to_enu(np.c_[g.west + (jj.ravel() + 0.5) * g.cell, g.north - (ii.ravel() + 0.5) * g.cell,
                               np.zeros(ii.size)])
    deep = (m[:, 0] > 200 * 0.2 - 40 + 0.5) & (m[:, 0] < 260 * 0.2 - 40 - 0.5) & \
           (m[:, 1] < 30 - 100 * 0.2 - 0.5) & (m[:, 1] > 30 - 140 * 0.2 + 0.5)
    assert deep.sum() > 500 and not np.isfinite(out.ravel()[deep]).any()
    with pytest.raises(InputError, match="mode"):
        resample(src, small, w, mode="cubic")
