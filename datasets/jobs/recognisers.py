"""Recognisers for a target list: what ``survey-detect``, ``detect`` and ``bank train``
build from the user's targets, with the negatives they must learn to refuse, kept in a
cache so the second run of a command does not train again.

Negatives of the aerial recogniser: clutter meshes (trees, bushes, rocks, buildings,
crates, fuel tanks, people, light poles) and every built-in vehicle whose class is not a
target class (``vehicle:<class>``). A model is cached (:func:`cache_dir`) by the SHA-256 of everything that makes it: the targets' geometry and paint at the training
grid, their classes, the negatives, the training options and the model schema.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

import prism3d.atr.aerial as aerial_module
import prism3d.atr.aerial_features as aerial_features_module
import prism3d.atr.aerial_scenes as aerial_scenes_module
import prism3d.atr.aerial_train as aerial_train_module
import prism3d.atr.bank as bank_module
import prism3d.atr.scene as scene_module
import prism3d.atr.verifier as verifier_module
import prism3d.capture.nadir as nadir_module
import prism3d.datasets.jobs.mining as mining_module
from prism3d.atr.aerial import AERIAL_SCHEMA_VERSION, AerialModel
from prism3d.atr.aerial_train import AerialTrainOptions, train_aerial
from prism3d.atr.verifier import SceneRecogniser
from prism3d.capture.mesh import SceneMesh
from prism3d.datasets.simulation.carpark import person_mesh, pole_mesh
from prism3d.datasets.simulation.field import prop_mesh
from prism3d.datasets.jobs.mining import MiningOptions, default_rejects, train_scene_recogniser
from prism3d.datasets.models.targets import builtin_classes, builtin_target, builtin_targets_of_class
from prism3d.errors import InputError

__all__ = ["aerial_negatives", "aerial_recogniser", "cache_dir", "field_specs", "scene_recogniser"]

#: Clutter of the aerial training scenes: kind and how many meshes of it.
AERIAL_CLUTTER = (("tree", 5), ("bush", 4), ("rock", 3), ("building", 3), ("crate", 1), ("fuel_tank", 1))


def cache_dir() -> Path:
    """Where trained recognisers are kept: ``$PRISM3D_CACHE``; else, in a virtual
    environment, its own ``var/cache/prism3d`` (removed with it; ``make setup`` fills it);
    else ``$XDG_CACHE_HOME/prism3d`` (default ``~/.cache/prism3d``)."""
    if os.environ.get("PRISM3D_CACHE"):
        return Path(os.environ["PRISM3D_CACHE"])
    if sys.prefix != sys.base_prefix and os.access(sys.prefix, os.W_OK):
        return Path(sys.prefix) / "var" / "cache" / "prism3d"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "prism3d"


def aerial_negatives(target_classes: Sequence[str], *, seed: int = 0) -> list[tuple[str, SceneMesh]]:
    """Clutter and the built-in vehicles of the other classes (module docstring)."""
    rng = np.random.default_rng([seed, 41])
    out: list[tuple[str, SceneMesh]] = []
    for kind, n in AERIAL_CLUTTER:
        out += [(kind, prop_mesh(kind, rng, seed * 1000 + len(out))) for _ in range(n)]
    out += [("person", person_mesh(rng)) for _ in range(3)] + [("pole", pole_mesh())]
    for cls in builtin_classes():
        if cls in target_classes or cls == "ship":
            continue
        out += [(f"vehicle:{cls}", builtin_target(n, scale="full")) for n in builtin_targets_of_class(cls)]
    return out


def _code_digest(h: hashlib._Hash, modules: Sequence[Any]) -> None:
    """The source of the modules that train a recogniser: a change to how it is trained is a
    new cache entry, not a stale model."""
    for mod in modules:
        h.update(Path(mod.__file__).read_bytes())


def _mesh_digest(h: hashlib._Hash, mesh: SceneMesh) -> None:
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    # the paint as the renderer sees it: sampled at the vertices and face centres
    pts = np.vstack([mesh.vertices, mesh.vertices[mesh.faces].mean(axis=1)])
    h.update(np.round(np.asarray(mesh.vertex_colors() if mesh.albedo_field is None else mesh.albedo_field(pts)), 4)
             .astype(np.float32).tobytes())


def _key(targets: Sequence[tuple[str, SceneMesh]], negatives: Sequence[tuple[str, SceneMesh]],
         options: AerialTrainOptions) -> str:
    h = hashlib.sha256()
    h.update(json.dumps({"schema": AERIAL_SCHEMA_VERSION, "options": asdict(options)}, sort_keys=True,
                        default=str).encode())
    _code_digest(h, [aerial_train_module, aerial_scenes_module, aerial_features_module, aerial_module, nadir_module])
    for label, items in (("t", targets), ("n", negatives)):
        for cls, m in items:
            h.update(f"{label}:{cls}".encode())
            _mesh_digest(h, m)
    return h.hexdigest()[:24]


def aerial_recogniser(targets: Sequence[tuple[str, SceneMesh]], *, options: AerialTrainOptions | None = None,
                      cache: bool = True, progress: Callable[[int, int, str], None] | None = None,
                      before_training: Callable[[AerialTrainOptions], None] | None = None
                      ) -> tuple[AerialModel, dict]:
    """The aerial recogniser of ``targets`` (``(class, SceneMesh)`` at full size): from the
    cache when this exact training was done before, else trained (minutes) and cached;
    ``before_training(options)`` is called only when it must be trained (a caller checks
    there, at the model's grid, the inputs it will read, so a bad one costs no training).
    Returns the model and ``{"cached": bool, "path": str | None}``."""
    if not targets:
        raise InputError("survey-detect: no targets to look for")
    for cls, m in targets:
        if float(np.max(m.extent_mm)) < 500.0:
            raise InputError(f"{m.name} ({cls}): {np.max(m.extent_mm):.0f} mm long; aerial targets are full size "
                             "(built-ins are taken at full size; give a mesh file's true units or --length-mm)")
    o = AerialTrainOptions() if options is None else options
    negatives = aerial_negatives(sorted({c for c, _ in targets}))
    key = _key(targets, negatives, o)
    path = cache_dir() / "recognisers" / f"aerial-{key}.npz"
    if cache and path.is_file():
        try:
            return AerialModel.load(path), {"cached": True, "path": str(path)}
        except InputError:
            pass  # a damaged cache entry is trained again
    if before_training is not None:
        before_training(o)
    model = train_aerial(targets, negatives, o, progress=progress)
    if cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            model.save(path)
        except OSError:
            return model, {"cached": False, "path": None}  # a read-only cache costs time, not the run
    return model, {"cached": False, "path": str(path) if cache else None}


def field_specs(targets: Sequence[tuple[str, SceneMesh]]) -> list[str]:
    """The targets as ``simulate field --classes`` takes them: built-in names, or mesh files
    ``FILE=CLASS:UNITS:UP:FORWARD`` as loaded (full size: a rescaled file cannot be placed)."""
    out = []
    for cls, m in targets:
        md = m.metadata
        if md.get("provenance") == "builtin procedural":
            out.append(str(md["name"]))
        elif md.get("source") and md.get("units") and md.get("length_mm") is None:
            out.append(f"{md['source']}={cls}:{md['units']}:{md.get('up', 'z')}:{md.get('forward', 'x')}")
        else:
            raise InputError(f"{m.name}: the mining scenes place targets at full size from their files; give the "
                             "file's units instead of --length-mm, or train the filters alone (--scenes 0)")
    return out


def _mining_key(o: MiningOptions, specs: list[str]) -> dict[str, Any]:
    """What a scene recogniser's cache key holds of its training options: the defaults'
    keys as they always were, and any other field only when changed."""
    key: dict[str, Any] = {"scenes": int(o.scenes), "channels": list(o.channels), "specs": specs,
                           "chip_spec": None if o.chip_spec is None else asdict(o.chip_spec), "bank": o.bank.changed()}
    default = MiningOptions()
    if o.simulation != default.simulation:
        key["simulation"] = asdict(o.simulation)
    if o.C != default.C:
        key["C"] = o.C
    return key


def scene_recogniser(targets: Sequence[tuple[str, SceneMesh]], options: MiningOptions | None = None, *,
                     run: Any = None, cache: bool = True,
                     progress: Callable[[int, int, str], None] | None = None) -> tuple[Any, dict]:
    """The scene recogniser of ``targets`` (:func:`prism3d.datasets.jobs.mining.train_scene_recogniser`),
    from the cache when this exact training was done before. Returns it and
    ``{"cached": bool, "path": str | None}``."""
    o = MiningOptions() if options is None else options
    specs = field_specs(targets)
    rejects = default_rejects(targets)
    h = hashlib.sha256(json.dumps(_mining_key(o, specs), sort_keys=True, default=str).encode())
    for label, items in (("t", targets), ("r", rejects)):
        for cls, m in items:
            h.update(f"{label}:{cls}".encode())
            _mesh_digest(h, m)
    _code_digest(h, [mining_module, verifier_module, scene_module, bank_module])
    path = cache_dir() / "recognisers" / f"scene-{h.hexdigest()[:24]}.npz"
    if cache and path.is_file():
        try:
            return SceneRecogniser.load(path), {"cached": True, "path": str(path)}
        except InputError:
            pass
    model = train_scene_recogniser(targets, specs, rejects=rejects, run=run, progress=progress, options=o)
    if cache:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            model.save(path)
        except OSError:
            return model, {"cached": False, "path": None}
    return model, {"cached": False, "path": str(path) if cache else None}
