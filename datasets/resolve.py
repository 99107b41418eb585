"""Turn command-line target specs into ``(class, SceneMesh)`` lists.

The ATR layer works on meshes; the CLI lets users name targets three ways:
``builtin`` (every built-in target), a built-in name (``tank_t1``), or a mesh file,
optionally with its class after ``=`` (``tank_1.glb=tank``; without it the class is
the file name up to the first ``_`` or digit: ``tank_1.glb`` -> ``tank``).
"""

from __future__ import annotations

import re
from pathlib import Path

from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.targets import builtin_target, list_builtin_targets
from prism3d.errors import InputError

__all__ = ["resolve_targets", "resolve_model"]


def _class_from_stem(stem: str) -> str:
    m = re.match(r"[A-Za-z]+", stem)
    if not m:
        raise InputError(f"{stem}: cannot infer a class from the file name; write FILE=CLASS")
    return m.group(0).lower()


def resolve_model(
    spec: str, *, units: str | None = None, up: str | None = None, camouflage: bool = True, seed: int = 0
) -> tuple[str, SceneMesh]:
    """One target spec -> ``(class, SceneMesh)`` (see the module docstring)."""
    from prism3d.atr.chips import load_mesh_file

    path_text, _, cls = spec.partition("=")
    if path_text in list_builtin_targets():
        mesh = builtin_target(path_text, camouflage=camouflage, seed=seed)
        return (cls or str(mesh.metadata["class"])), mesh
    path = Path(path_text)
    if not path.is_file():
        valid = ", ".join(list_builtin_targets())
        raise InputError(f"{path_text}: neither a mesh file nor a built-in target ({valid})")
    if units is None:
        raise InputError(f"{path}: give --units (mm, cm, m, in): mesh files do not say their units")
    mesh = load_mesh_file(path, units=units, up=up or "z")
    return (cls or _class_from_stem(path.stem)), mesh


def resolve_targets(
    specs: list[str], *, units: str | None = None, up: str | None = None, camouflage: bool = True,
    seed: int = 0,
) -> list[tuple[str, SceneMesh]]:
    """Target specs (``builtin``, names, ``FILE[=CLASS]``) -> ``[(class, SceneMesh), ...]``."""
    if not specs:
        raise InputError("no targets given (use 'builtin', built-in names or mesh files)")
    out: list[tuple[str, SceneMesh]] = []
    for spec in specs:
        if spec == "builtin":
            out += [resolve_model(n, camouflage=camouflage, seed=seed) for n in list_builtin_targets()]
        else:
            out.append(resolve_model(spec, units=units, up=up, camouflage=camouflage, seed=seed))
    return out
