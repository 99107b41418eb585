"""Turn command-line target specs into ``(class, SceneMesh)`` lists: one target list for
``bank train|eval``, ``detect``, ``survey-detect``, ``render`` and the database.

A spec is one of:

* ``builtin`` (every military built-in: the camouflaged tanks, jets, ships, trucks),
  ``civilian`` (every civilian built-in: cars, vans, buses, trucks);
* a built-in name (``tank_t1``, ``car_kei``);
* a class name (``car``, ``van``, ``truck``, ``bus``, ``tank``...): every built-in of that
  class (``truck`` is the military trucks and the civilian box truck, pickup and kei truck);
* a mesh file with its class, units, up and forward axes after ``=``:
  ``FILE[=CLASS[:UNITS[:UP[:FORWARD]]]]`` (``car_suv.glb=car:m:y:-z``); without a class it
  is the file name up to the first ``_`` or digit (``tank_1.glb`` -> ``tank``). Units, up
  and forward follow one rule (:func:`~prism3d.datasets.database.ingest.mesh_units`,
  :func:`~prism3d.datasets.database.ingest.mesh_forward`): this spec, else the command's flags, else
  the file's sidecar or PLY header; never guessed.

A database (``--db``) gives its own targets (:func:`resolve_db_targets`); a trained model
file is not a target list but a recogniser, told apart by :func:`model_kind`.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from prism3d.atr.chips import load_mesh_file
from prism3d.atr.models import model_kind
from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.database.db import as_db, target_mesh
from prism3d.datasets.database.ingest import check_length_mm, mesh_forward, mesh_units, size_warning
from prism3d.datasets.models.targets import (
    builtin_classes,
    builtin_target,
    builtin_targets_of_class,
    list_builtin_targets,
)
from prism3d.errors import InputError
from prism3d.io.units import forward_yaw_deg

__all__ = ["resolve_db_targets", "resolve_model", "resolve_targets"]

log = logging.getLogger(__name__)

def _class_from_stem(stem: str) -> str:
    m = re.match(r"[A-Za-z]+", stem)
    if not m:
        raise InputError(f"{stem}: cannot infer a class from the file name; write FILE=CLASS")
    return m.group(0).lower()


def resolve_model(
    spec: str, *, units: str | None = None, up: str | None = None, forward: str | None = None,
    camouflage: bool = True, seed: int = 0, length_mm: float | None = None, scale: float | str = "model",
) -> tuple[str, SceneMesh]:
    """One target spec (a built-in name or a mesh file) -> ``(class, SceneMesh)`` (see the
    module docstring). ``length_mm``: a mesh file is rescaled to this length (its longest
    horizontal extent; units it does not declare then do not matter); built-in targets keep
    theirs, at ``scale`` (``model`` kit scale or ``full``)."""
    if length_mm is not None:
        check_length_mm(length_mm)
    path_text, _, rest = spec.partition("=")
    parts = rest.split(":") if rest else []
    if len(parts) > 4:
        raise InputError(f"{spec}: expected FILE[=CLASS[:UNITS[:UP[:FORWARD]]]]")
    cls, t_units, t_up, t_fwd = ([*parts, "", "", "", ""])[:4]
    if path_text in list_builtin_targets():
        if t_units or t_up or t_fwd:
            raise InputError(f"{spec}: built-in targets are in mm, z up, x forward; give no units, up or forward")
        mesh = builtin_target(path_text, camouflage=camouflage, seed=seed, scale=scale)
        return (cls or str(mesh.metadata["class"])), mesh
    path = Path(path_text)
    if not path.is_file():
        raise InputError(f"{path_text}: neither a mesh file, a built-in target nor a class "
                         f"({', '.join(builtin_classes())}, builtin, civilian; names: {', '.join(list_builtin_targets())})")
    if model_kind(path) is not None:
        raise InputError(f"{path_text}: a trained model, not a target mesh; give it where a model is taken "
                         "(detect --bank, survey-detect --targets MODEL.npz alone)")
    # this target's own units/up/forward win over the command's flags
    u, up_v = mesh_units(path, t_units or units, t_up or up, rescaled=length_mm is not None)
    fwd = mesh_forward(path, t_fwd or forward, up_v)
    mesh = load_mesh_file(path, units=u, up=up_v, length_mm=length_mm, yaw_deg=forward_yaw_deg(fwd, up_v))
    mesh.metadata["forward"] = fwd
    cls = cls or _class_from_stem(path.stem)
    warning = size_warning(path.name, cls, float(np.max(mesh.extent_mm[:2])),
                           u if length_mm is None else "--length-mm")
    if warning:
        log.warning("%s", warning)
    return cls, mesh


def resolve_targets(
    specs: list[str], *, units: str | None = None, up: str | None = None, forward: str | None = None,
    camouflage: bool = True, seed: int = 0, length_mm: float | None = None, scale: float | str = "model",
) -> list[tuple[str, SceneMesh]]:
    """Target specs (``builtin``, ``civilian``, names, classes, ``FILE[=CLASS...]``) ->
    ``[(class, SceneMesh), ...]``; ``length_mm`` rescales every mesh file
    (:func:`resolve_model`); built-ins at ``scale``."""
    if not specs:
        raise InputError("no targets given (use 'builtin', built-in names, classes or mesh files)")
    out: list[tuple[str, SceneMesh]] = []

    def builtins(names: list[str]) -> list[tuple[str, SceneMesh]]:
        return [resolve_model(n, camouflage=camouflage, seed=seed, scale=scale) for n in names]

    for spec in specs:
        if spec == "builtin":
            out += builtins(list_builtin_targets("military"))
        elif spec == "civilian":
            out += builtins(list_builtin_targets("civilian"))
        elif "=" not in spec and spec in builtin_classes() and not Path(spec).is_file():
            out += builtins(builtin_targets_of_class(spec))
        else:
            out.append(resolve_model(spec, units=units, up=up, forward=forward, camouflage=camouflage, seed=seed,
                                     length_mm=length_mm, scale=scale))
    return out


def resolve_db_targets(db: str | Path, *, classes: list[str] | None = None, scale: str = "model"
                       ) -> list[tuple[str, SceneMesh]]:
    """The targets of a database (its normalised models: mm, z up, x forward; built-ins at
    their stored scale, or full size with ``scale="full"``), optionally only those of
    ``classes`` (a class the database lacks is an error)."""
    d = as_db(db)
    table = d.targets()
    if classes:
        unknown = sorted(set(classes) - set(table["class"]))
        if unknown:
            have = ", ".join(sorted(set(table["class"]))) or "none"
            raise InputError(f"{d.path}: no targets of class {', '.join(unknown)} (it has {have})")
        table = table[table["class"].isin(classes)]
    if not len(table):
        raise InputError(f"{d.path}: the database has no targets; add some with 'prism3d db add'")
    out = []
    for tid, kind, name in zip(table["target_id"], table["source_kind"], table["name"]):
        mesh, cls = target_mesh(d, str(tid))
        if kind == "builtin" and scale == "full":
            mesh = builtin_target(str(name), scale="full")
        out.append((cls, mesh))
    return out
