"""Top-down orthographic sprites: a box of known size seen from above."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.nadir import render_nadir
from prism3d.errors import InputError


def _box(L: float, W: float, H: float) -> SceneMesh:
    import trimesh

    b = trimesh.creation.box(extents=(L, W, H))
    b.apply_translation((0, 0, H / 2))
    return SceneMesh(np.asarray(b.vertices), np.asarray(b.faces), None, UniformAlbedo((0.2, 0.4, 0.6)), "box")


def test_a_box_from_above() -> None:
    sp = render_nadir(_box(4000.0, 2000.0, 1500.0), 0.05, margin_m=0.5)
    inside = sp.alpha > 0.5
    assert sp.alpha.sum() * 0.05**2 == pytest.approx(4.0 * 2.0, rel=0.01)  # coverage, edges half-covered
    rows, cols = np.nonzero(sp.alpha >= 0.5)
    assert (cols.max() - cols.min() + 1) * 0.05 == pytest.approx(4.0, abs=0.06)  # length along columns
    assert (rows.max() - rows.min() + 1) * 0.05 == pytest.approx(2.0, abs=0.06)
    assert sp.height[inside].mean() == pytest.approx(1.5, abs=1e-3) and sp.height[sp.alpha == 0].max() == 0.0
    assert np.allclose(sp.normal[inside], (0, 0, 1), atol=1e-6)
    assert np.allclose(sp.albedo[inside & (sp.alpha == 1.0)], (0.2, 0.4, 0.6), atol=1e-6)
    assert (sp.length_m, sp.width_m, sp.height_m) == pytest.approx((4.0, 2.0, 1.5))


def test_bad_sizes_are_refused() -> None:
    with pytest.raises(InputError, match="gsd"):
        render_nadir(_box(1000, 1000, 1000), 0.0)
    with pytest.raises(InputError, match="too large"):
        render_nadir(_box(1e6, 1e6, 1000), 0.001)
