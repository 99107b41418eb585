"""The verifier's robust object measures against an exact depth map of a box on the ground."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.atr.scene import scene_channels
from prism3d.atr.verifier import object_gate, object_stats

F, W_PX, H_PX = 1500.0, 900, 700
#: A camera 40 m above flat ground, looking straight down (camera z = depth).
CAM_H = 40_000.0


def _box_scene(L: float, W: float, H: float, yaw_deg: float):
    """Exact depth of a box L x W x H (mm) standing on the ground under the camera, turned
    by ``yaw_deg`` about the vertical; the grey image is its top lit, the ground darker."""
    K = np.array([[F, 0, W_PX / 2], [0, F, H_PX / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:H_PX, 0:W_PX].astype(np.float64)
    dx, dy = (u - K[0, 2]) / F, (v - K[1, 2]) / F
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    depth = np.full((H_PX, W_PX), CAM_H)
    # entry depth of each ray into the box (slab method in the box's frame; rays go +z)
    lo, hi = np.zeros_like(dx), np.full_like(dx, np.inf)
    for (ox, oy), half in (((c, s), L / 2), ((-s, c), W / 2)):
        d = dx * ox + dy * oy
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half) / d, half / d
        near, far = np.minimum(t1, t2), np.maximum(t1, t2)
        inside = np.abs(d) < 1e-12
        lo = np.where(inside, lo, np.maximum(lo, near))
        hi = np.where(inside, hi, np.minimum(hi, far))
    lo = np.maximum(lo, CAM_H - H)
    hit = lo <= np.minimum(hi, CAM_H)
    depth[hit] = lo[hit]
    grey = np.where(hit, 0.7, 0.3) + 0.02 * np.random.default_rng(0).standard_normal(depth.shape)
    return scene_channels(np.clip(grey, 0, 1), depth, K), hit


@pytest.mark.parametrize("yaw", [0.0, 30.0, 90.0])
def test_stats_of_a_box_match_its_true_size(yaw):
    L, W, H = 8000.0, 3000.0, 2500.0
    sc, hit = _box_scene(L, W, H, yaw)
    labs = [lab for lab in range(1, len(sc.object_dims_mm)) if object_gate(sc, lab)]
    assert len(labs) == 1
    across, down, fill, h50, h75, h90, L2, W2, dstd = object_stats(sc, labs[0])
    # the footprint between its 5th and 95th percentiles along its axes: 0.9 of a uniform side
    assert L2 == pytest.approx(0.9 * L, rel=0.05)
    assert W2 == pytest.approx(0.9 * W, rel=0.08)
    # the flat top stands H high; its image extents are its projection at the top's depth
    assert h50 == pytest.approx(H, abs=60) and h90 == pytest.approx(H, abs=60)
    rr, cc = np.nonzero(hit)  # the box's true pixels, at the top's true depth
    z = CAM_H - H
    assert across == pytest.approx(np.ptp(np.percentile(cc, [2, 98])) * z / F, rel=0.05)
    assert down == pytest.approx(np.ptp(np.percentile(rr, [2, 98])) * z / F, rel=0.05)
    assert dstd < 50.0  # a flat top: its depths agree
    if yaw in (0.0, 90.0):  # an upright rectangle fills its 2-98 % box; its extents are its sides
        assert fill == pytest.approx(1 / 0.96 ** 2, rel=0.05)
        side = L if yaw == 0.0 else W
        assert across == pytest.approx(0.96 * side, rel=0.05)


def test_a_turned_box_keeps_its_footprint_measures():
    a, _ = _box_scene(9000.0, 3500.0, 2800.0, 0.0)
    b, _ = _box_scene(9000.0, 3500.0, 2800.0, 55.0)
    sa = object_stats(a, [k for k in range(1, len(a.object_dims_mm)) if object_gate(a, k)][0])
    sb = object_stats(b, [k for k in range(1, len(b.object_dims_mm)) if object_gate(b, k)][0])
    assert sb[6] == pytest.approx(sa[6], rel=0.04) and sb[7] == pytest.approx(sa[7], rel=0.08)
