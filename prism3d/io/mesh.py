"""Triangle meshes from the files users have (OBJ, PLY, GLB/GLTF, OFF, STL).

One loader for every layer: scene graphs (GLB) are flattened with their node
transforms applied, per-vertex colours come from vertex colours or material
colours where trimesh can convert them. Coordinates stay in the file's units;
:data:`UNITS_MM` converts them (units are never guessed: callers ask the user).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_file
from prism3d.errors import InputError

__all__ = ["UNITS_MM", "MESH_SUFFIXES", "MeshData", "read_mesh"]

#: Millimetres per unit.
UNITS_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
#: File types :func:`read_mesh` reads.
MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")


@dataclass
class MeshData:
    """A mesh as stored in a file (file units, file axes)."""

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    vertex_colors: NDArray[np.float64] | None
    """(N, 3) in [0, 1], or None when the file has no colours."""


#: Largest vertex coordinate accepted, in the file's units: 1e12 mm is a million km;
#: 1e30 is a corrupt file, whose squares overflow later arithmetic.
MAX_COORDINATE = 1e12


def read_mesh(path: str | Path) -> MeshData:
    """Read a triangle mesh; a multi-part scene is concatenated in its world frame.

    Raises
    ------
    InputError
        Missing file, unsupported type, unreadable content, or no triangles.
    """
    import trimesh

    p = check_file(path, "mesh file")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{p}: unsupported mesh format {p.suffix!r} (use {' '.join(MESH_SUFFIXES)})")
    try:
        loaded = trimesh.load(str(p), force=None, process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise InputError(f"{p}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    geoms = []
    if isinstance(loaded, trimesh.Scene):
        for node in loaded.graph.nodes_geometry:
            T, gname = loaded.graph[node]
            g = loaded.geometry[gname]
            if isinstance(g, trimesh.Trimesh) and len(g.faces):
                g = g.copy()
                g.apply_transform(T)
                geoms.append(g)
    elif isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
        geoms = [loaded]
    if not geoms:
        raise InputError(f"{p}: no triangles in the file (empty mesh)")
    verts, faces, cols = [], [], []
    any_colour = False
    off = 0
    gltf = _gltf_base_colours(p) if p.suffix.lower() in (".glb", ".gltf") else {}
    for g in geoms:
        vc = _vertex_colours(g, gltf)
        if vc is None or vc.shape != (len(g.vertices), 3):
            vc = np.full((len(g.vertices), 3), 0.7)
        else:
            any_colour = True
        verts.append(np.asarray(g.vertices, dtype=np.float64))
        faces.append(np.asarray(g.faces, dtype=np.int64) + off)
        cols.append(vc)
        off += len(g.vertices)
    v = np.concatenate(verts)
    _check_vertices(p, v)
    f = np.concatenate(faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    if not np.any(np.linalg.norm(np.cross(b - a, c - a), axis=1) > 0):
        raise InputError(f"{p}: every triangle has zero area (the vertices coincide or lie on a line)")
    return MeshData(v, f, np.clip(np.concatenate(cols), 0, 1) if any_colour else None)


def _vertex_colours(g: Any, gltf: dict[str, NDArray[np.float64]]) -> NDArray[np.float64] | None:
    """Per-vertex RGB in [0, 1] of one trimesh geometry ``g`` (material, vertex, face or
    sampled texture colours; ``gltf`` from :func:`_gltf_base_colours`); None without them."""
    vc = None
    try:
        vis = g.visual
        material = getattr(vis, "material", None)
        if vis.kind == "texture" and getattr(vis, "uv", None) is None and material is not None:
            # a material colour without a texture (OBJ Kd, glTF baseColorFactor; trimesh
            # loses the latter when a material also has the specular-glossiness extension)
            rgb = gltf.get(getattr(material, "name", None))
            if rgb is None:
                rgb = np.asarray(material.main_color, dtype=np.float64)[:3] / 255.0
            vc = np.broadcast_to(rgb, (len(g.vertices), 3)).copy()
        elif vis.kind in ("vertex", "face"):  # colours per vertex (PLY, OFF) or per face
            vc = np.asarray(vis.vertex_colors, dtype=np.float64)[:, :3] / 255.0
        elif vis.kind is not None:  # a texture: its colours sampled at the vertices
            vc = np.asarray(vis.to_color().vertex_colors, dtype=np.float64)[:, :3] / 255.0
    except Exception:  # textures trimesh cannot convert: no colour
        vc = None
    return vc


def _check_vertices(p: Path, v: NDArray[np.float64]) -> None:
    """Reject NaN/inf and coordinates beyond :data:`MAX_COORDINATE` (a corrupt file)."""
    if not np.all(np.isfinite(v)):
        raise InputError(f"{p}: vertices contain NaN or inf")
    if np.abs(v).max() > MAX_COORDINATE:
        raise InputError(f"{p}: vertex coordinates up to {np.abs(v).max():.3g} are beyond any model "
                         f"(at most {MAX_COORDINATE:g} in the file's units); the file is corrupt")


def _gltf_base_colours(path: Path) -> dict[str, NDArray[np.float64]]:
    """Material name -> base colour RGB (linear, as OBJ's Kd) of the untextured materials
    of a ``.glb``/``.gltf`` file, read from its JSON: ``pbrMetallicRoughness.baseColorFactor``,
    else ``KHR_materials_pbrSpecularGlossiness.diffuseFactor``. Empty when unreadable."""
    import json
    import struct

    try:
        raw = path.read_bytes()
        if raw[:4] == b"glTF":
            n, kind = struct.unpack("<II", raw[12:20])
            doc = json.loads(raw[20:20 + n]) if kind == 0x4E4F534A else {}
        else:
            doc = json.loads(raw)
    except (OSError, ValueError, struct.error, UnicodeDecodeError):
        return {}
    out: dict[str, NDArray[np.float64]] = {}
    for m in doc.get("materials", []) if isinstance(doc, dict) else []:
        if not isinstance(m, dict) or not isinstance(m.get("name"), str):
            continue
        pbr = m.get("pbrMetallicRoughness") or {}
        sg = (m.get("extensions") or {}).get("KHR_materials_pbrSpecularGlossiness") or {}
        if pbr.get("baseColorTexture") or sg.get("diffuseTexture"):
            continue  # textured: trimesh samples the texture
        f = pbr.get("baseColorFactor", sg.get("diffuseFactor"))
        try:
            rgb = np.asarray(f, dtype=np.float64).ravel()[:3] if f is not None else None
        except (TypeError, ValueError):
            rgb = None
        if rgb is not None and rgb.size == 3 and np.all(np.isfinite(rgb)):
            out[m["name"]] = np.clip(rgb, 0.0, 1.0)
    return out
