"""Turn command-line target specs into ``(class, SceneMesh)`` lists.

The ATR layer works on meshes; the CLI lets users name targets three ways:
``builtin`` (every built-in target), a built-in name (``tank_t1``), or a mesh file,
optionally with its class, units and up axis after ``=``: ``FILE[=CLASS[:UNITS[:UP]]]``
(``tank_1.glb=tank:m:y``; without a class it is the file name up to the first ``_`` or
digit: ``tank_1.glb`` -> ``tank``). Units and up follow one rule
(:func:`~prism3d.datasets.ingest.mesh_units`): this spec, else the command's flags, else
the file's sidecar or PLY header; never guessed.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.targets import builtin_target, list_builtin_targets
from prism3d.errors import InputError

__all__ = ["resolve_targets", "resolve_model"]

log = logging.getLogger(__name__)


def _class_from_stem(stem: str) -> str:
    m = re.match(r"[A-Za-z]+", stem)
    if not m:
        raise InputError(f"{stem}: cannot infer a class from the file name; write FILE=CLASS")
    return m.group(0).lower()


def resolve_model(
    spec: str, *, units: str | None = None, up: str | None = None, camouflage: bool = True, seed: int = 0,
    length_mm: float | None = None,
) -> tuple[str, SceneMesh]:
    """One target spec -> ``(class, SceneMesh)`` (see the module docstring). ``length_mm``:
    a mesh file is rescaled to this length (its longest horizontal extent; units it does
    not declare then do not matter); built-in targets keep theirs."""
    from prism3d.atr.chips import load_mesh_file

    from prism3d.datasets.ingest import check_length_mm, mesh_units, size_warning

    if length_mm is not None:
        check_length_mm(length_mm)

    path_text, _, rest = spec.partition("=")
    parts = rest.split(":") if rest else []
    if len(parts) > 3:
        raise InputError(f"{spec}: expected FILE[=CLASS[:UNITS[:UP]]]")
    cls, t_units, t_up = ([*parts, "", "", ""])[:3]
    if path_text in list_builtin_targets():
        if t_units or t_up:
            raise InputError(f"{spec}: built-in targets are in mm, z up; give no units or up")
        mesh = builtin_target(path_text, camouflage=camouflage, seed=seed)
        return (cls or str(mesh.metadata["class"])), mesh
    path = Path(path_text)
    if not path.is_file():
        valid = ", ".join(list_builtin_targets())
        raise InputError(f"{path_text}: neither a mesh file nor a built-in target ({valid})")
    # this target's own units/up win over the command's flags
    u, up_v = mesh_units(path, t_units or units, t_up or up, rescaled=length_mm is not None)
    mesh = load_mesh_file(path, units=u, up=up_v, length_mm=length_mm)
    cls = cls or _class_from_stem(path.stem)
    warning = size_warning(path.name, cls, float(np.max(mesh.extent_mm[:2])),
                           u if length_mm is None else "--length-mm")
    if warning:
        log.warning("%s", warning)
    return cls, mesh


def resolve_targets(
    specs: list[str], *, units: str | None = None, up: str | None = None, camouflage: bool = True,
    seed: int = 0, length_mm: float | None = None,
) -> list[tuple[str, SceneMesh]]:
    """Target specs (``builtin``, names, ``FILE[=CLASS]``) -> ``[(class, SceneMesh), ...]``;
    ``length_mm`` rescales every mesh file (:func:`resolve_model`)."""
    if not specs:
        raise InputError("no targets given (use 'builtin', built-in names or mesh files)")
    out: list[tuple[str, SceneMesh]] = []
    for spec in specs:
        if spec == "builtin":
            out += [resolve_model(n, camouflage=camouflage, seed=seed) for n in list_builtin_targets()]
        else:
            out.append(resolve_model(spec, units=units, up=up, camouflage=camouflage, seed=seed,
                                     length_mm=length_mm))
    return out
