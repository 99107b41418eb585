"""Tests of prism3d.io.units: units and up axis declared in PLY comments."""

from __future__ import annotations

import numpy as np
from prism3d.io.ply import read_ply, write_ply
from prism3d.io.units import declared_units


def test_declared_units_known_forms() -> None:
    assert declared_units(["units mm"]) == ("mm", None)
    assert declared_units([" units  m "]) == ("m", None)
    # export_builtin_target's form: units then a ';'-separated tail
    assert declared_units(["prism3d builtin target x", "units mm; frame x forward, y left, z up"]) == ("mm", None)
    assert declared_units(["units mm", "up z", "source a.glb sha256 00"]) == ("mm", "z")
    assert declared_units(["up -y", "units cm", "units m"]) == ("cm", "-y")  # the first wins
    assert declared_units([]) == (None, None)
    assert declared_units(["unit mm", "upz", "up to date", "units"]) == (None, None)


def test_declared_units_from_a_written_ply(tmp_path) -> None:
    p = tmp_path / "a.ply"
    write_ply(p, np.zeros((3, 3)), faces=np.array([[0, 1, 2]]), comments=["units in", "up y"])
    assert declared_units(read_ply(p).comments) == ("in", "y")
