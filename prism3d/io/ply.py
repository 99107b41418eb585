"""PLY point clouds and meshes (binary little/big-endian and ASCII).

Writes binary little-endian PLY with ``x y z`` (float32 by default, float64 on
request), optional ``nx ny nz``, ``red green blue`` (uchar), any extra per-vertex
float properties, and triangle faces (``vertex_indices``), atomically. Reads what
common tools write (Open3D, MeshLab, PCL, Blender, Middlebury).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_file
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_open

__all__ = ["PlyData", "read_ply", "write_ply"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_MAX_ELEMENTS = 2_000_000_000


@dataclass
class PlyData:
    """Contents of a PLY file.

    Attributes
    ----------
    points : (N, 3) float64
        Vertex positions (units as stored; prism3d writes millimetres).
    colors : (N, 3) uint8 or None
    normals : (N, 3) float32 or None
    faces : (M, 3) int64 or None
        Triangles (polygons with more vertices are fan-triangulated on read).
    extra : dict of str -> (N,) array
        Other per-vertex properties (e.g. ``confidence``).
    comments : list of str
    """

    points: NDArray[np.float64]
    colors: NDArray[np.uint8] | None = None
    normals: NDArray[np.float32] | None = None
    faces: NDArray[np.int64] | None = None
    extra: dict[str, NDArray] = field(default_factory=dict)
    comments: list[str] = field(default_factory=list)


def _header_text(text: object) -> str:
    """A comment as one ASCII header line: line breaks become spaces, other characters
    ``\\uXXXX`` escapes (a PLY header is ASCII; a file name may not be)."""
    one = str(text).replace("\r", " ").replace("\n", " ")
    return one.encode("ascii", "backslashreplace").decode("ascii")


def _vertex_columns(
    pts: NDArray,
    normals: NDArray | None,
    colors: NDArray | None,
    extra: dict[str, NDArray] | None,
    double: bool,
) -> tuple[list[tuple[str, str]], dict[str, NDArray]]:
    """Checked per-vertex properties ``(name, dtype code)`` in file order and their columns,
    for :func:`write_ply` (colours in [0, 1] scaled to uchar)."""
    n = len(pts)
    props: list[tuple[str, str]] = [(c, "f8" if double else "f4") for c in "xyz"]
    cols: dict[str, NDArray] = {c: pts[:, i] for i, c in enumerate("xyz")}
    if normals is not None:
        nrm = check_array(normals, "normals", shape=(n, 3), dtype_kind="f")
        for i, c in enumerate(("nx", "ny", "nz")):
            props.append((c, "f4"))
            cols[c] = nrm[:, i]
    if colors is not None:
        col = check_array(colors, "colors", shape=(n, 3), dtype_kind="fiu")
        if col.dtype.kind == "f":
            col = np.clip(np.round(col * 255.0), 0, 255)
        for i, c in enumerate(("red", "green", "blue")):
            props.append((c, "u1"))
            cols[c] = col[:, i]
    for name, arr in (extra or {}).items():
        if not name.isidentifier() or name in cols:
            raise InputError(f"extra: invalid or duplicate property name {name!r}")
        a = check_array(arr, f"extra[{name!r}]", shape=(n,), dtype_kind="fiub")
        props.append((name, "f4"))
        cols[name] = a
    return props, cols


def _face_block(faces: NDArray | None, n: int) -> tuple[bytes, int]:
    """The binary face element (uchar count 3, three int32 indices each) and its face
    count; empty when ``faces`` is None. Indices are checked against ``n`` vertices."""
    if faces is None:
        return b"", 0
    f = check_array(faces, "faces", shape=(None, 3), dtype_kind="iu")
    if len(f) and (f.min() < 0 or f.max() >= n):
        raise InputError(f"faces: indices must lie in [0, {n})")
    n_faces = len(f)
    fdtype = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])
    fb = np.empty(n_faces, dtype=fdtype)
    fb["n"] = 3
    fb["idx"] = f
    return fb.tobytes(), n_faces


def write_ply(
    path: str | Path,
    points: NDArray,
    *,
    colors: NDArray | None = None,
    normals: NDArray | None = None,
    faces: NDArray | None = None,
    extra: dict[str, NDArray] | None = None,
    comments: list[str] | None = None,
    double: bool = False,
) -> None:
    """Write a binary little-endian PLY atomically.

    Parameters
    ----------
    points : (N, 3) float
    colors : (N, 3) uint8, or float in [0, 1]
    normals : (N, 3) float
    faces : (M, 3) int
    extra : name -> (N,) float arrays
    double : store coordinates as float64 (default float32)
    """
    pts = check_array(points, "points", shape=(None, 3), dtype_kind="fiu")
    n = len(pts)
    props, cols = _vertex_columns(pts, normals, colors, extra, double)
    vdtype = np.dtype([(p, "<" + t) for p, t in props])
    vert = np.empty(n, dtype=vdtype)
    for p, _ in props:
        vert[p] = cols[p]
    face_block, n_faces = _face_block(faces, n)
    rev = {"f4": "float", "f8": "double", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {_header_text(c)}" for c in (comments or [])]
    header.append(f"element vertex {n}")
    header += [f"property {rev[t]} {p}" for p, t in props]
    if faces is not None:
        header.append(f"element face {n_faces}")
        header.append("property list uchar int vertex_indices")
    header.append("end_header")
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face_block)


@dataclass
class _Element:
    name: str
    count: int
    props: list[tuple[str, str, str | None]]  # (name, type, list-count type or None)


def _parse_header(path: Path, raw: bytes) -> tuple[str, list[_Element], list[str], int]:
    import re

    # the header ends at a line that is "end_header" (a comment may contain the word)
    m = re.search(rb"\nend_header[ \t\r]*(\n|$)", raw)
    if not raw.startswith(b"ply") or m is None:
        raise InputError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    end = m.start() + 1
    if not m.group(1):
        raise InputError(f"{path}: PLY header is not terminated by a newline")
    nl = m.end() - 1
    lines = raw[:end].decode("ascii", errors="replace").replace("\r", "").split("\n")
    fmt = None
    elements: list[_Element] = []
    comments: list[str] = []
    for line in lines[1:]:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise InputError(f"{path}: unsupported PLY format line {line!r}")
            fmt = tok[1]
        elif tok[0] in ("comment", "obj_info"):
            comments.append(line.partition(" ")[2])
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit() or int(tok[2]) > _MAX_ELEMENTS:
                raise InputError(f"{path}: malformed element line {line!r}")
            elements.append(_Element(tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise InputError(f"{path}: property before any element")
            if len(tok) >= 3 and tok[-1] in {n for n, _, _ in elements[-1].props}:
                raise InputError(f"{path}: property {tok[-1]!r} appears twice in element {elements[-1].name!r}")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in _TYPES or tok[3] not in _TYPES:
                    raise InputError(f"{path}: unknown PLY list type in {line!r}")
                elements[-1].props.append((tok[4], _TYPES[tok[3]], _TYPES[tok[2]]))
            elif len(tok) == 3 and tok[1] in _TYPES:
                elements[-1].props.append((tok[2], _TYPES[tok[1]], None))
            else:
                raise InputError(f"{path}: malformed property line {line!r}")
        else:
            raise InputError(f"{path}: unexpected PLY header line {line!r}")
    if fmt is None:
        raise InputError(f"{path}: PLY header has no format line")
    return fmt, elements, comments, nl + 1


def read_ply(path: str | Path) -> PlyData:
    """Read a PLY point cloud or mesh.

    Raises
    ------
    InputError
        Missing file, bad header, truncated body, no vertex element or no x y z.
    """
    path = check_file(path, "PLY file")
    raw = path.read_bytes()
    fmt, elements, comments, offset = _parse_header(path, raw)
    data: dict[str, dict[str, NDArray] | list] = {}
    if fmt == "ascii":
        tokens = raw[offset:].split()
        pos = 0
        for el in elements:
            pos = _read_ascii_element(path, el, tokens, pos, data)
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        for el in elements:
            offset = _read_binary_element(path, el, raw, offset, endian, data)
    vert = data.get("vertex")
    if not isinstance(vert, dict) or not all(k in vert for k in "xyz"):
        raise InputError(f"{path}: PLY has no vertex element with x, y, z")
    with np.errstate(invalid="ignore", over="ignore"):  # a file's signalling NaNs stay NaN, quietly
        pts = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
        out = PlyData(points=pts, comments=comments)
        if all(k in vert for k in ("nx", "ny", "nz")):
            out.normals = np.stack([vert["nx"], vert["ny"], vert["nz"]], 1).astype(np.float32)
        for names in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
            if all(k in vert for k in names):
                c = np.stack([vert[k] for k in names], 1)
                if c.dtype.kind == "f":
                    c = np.clip(np.round(np.nan_to_num(c * 255.0 if np.nanmax(c, initial=0) <= 1.0 else c)), 0, 255)
                out.colors = c.astype(np.uint8)
                break
    known = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "r", "g", "b", "alpha",
             "diffuse_red", "diffuse_green", "diffuse_blue"}
    out.extra = {k: v for k, v in vert.items() if k not in known}
    face = data.get("face")
    if isinstance(face, dict) and face:
        polys = next(iter(face.values()))
        out.faces = _triangulate(path, polys, len(pts))
    return out


def _triangulate(path: Path, polys: list | NDArray, n_vertices: int) -> NDArray[np.int64]:
    if isinstance(polys, np.ndarray) and polys.ndim == 2:
        if polys.shape[1] == 3:
            tris = polys.astype(np.int64)
        else:
            k = polys.shape[1]
            tris = np.concatenate([polys[:, [0, i, i + 1]] for i in range(1, k - 1)]).astype(np.int64)
    else:
        out = []
        for p in polys:
            p = np.asarray(p, dtype=np.int64)
            for i in range(1, len(p) - 1):
                out.append((p[0], p[i], p[i + 1]))
        tris = np.asarray(out, dtype=np.int64).reshape(-1, 3)
    if len(tris) and (tris.min() < 0 or tris.max() >= n_vertices):
        raise InputError(f"{path}: face indices out of range [0, {n_vertices})")
    return tris


def _read_binary_element(path: Path, el: _Element, raw: bytes, offset: int, endian: str, data: dict) -> int:
    if all(lt is None for _, _, lt in el.props):
        dt = np.dtype([(n, endian + t) for n, t, _ in el.props])
        need = dt.itemsize * el.count
        if len(raw) - offset < need:
            raise InputError(f"{path}: truncated PLY: element {el.name!r} needs {need} bytes, {len(raw) - offset} left")
        arr = np.frombuffer(raw, dtype=dt, count=el.count, offset=offset)
        data[el.name] = {n: np.array(arr[n]) for n, _, _ in el.props}
        return offset + need
    # one list property (faces): try the fixed-size fast path first
    if len(el.props) == 1:
        name, t, lt0 = el.props[0]
        lt = lt0 or "u1"
        cnt_size = np.dtype(lt).itemsize
        if el.count == 0:
            data[el.name] = {name: np.zeros((0, 3), np.int64)}
            return offset
        if len(raw) - offset < cnt_size:
            raise InputError(f"{path}: truncated PLY in element {el.name!r}")
        k = int(np.frombuffer(raw, dtype=endian + lt, count=1, offset=offset)[0])
        dt = np.dtype([("n", endian + lt), ("idx", endian + t, (max(k, 1),))])
        need = dt.itemsize * el.count
        if k >= 3 and len(raw) - offset >= need:
            arr = np.frombuffer(raw, dtype=dt, count=el.count, offset=offset)
            if np.all(arr["n"] == k):
                data[el.name] = {name: np.array(arr["idx"])}
                return offset + need
    # general slow path
    cols: dict[str, list] = {n: [] for n, _, _ in el.props}
    for _ in range(el.count):
        for n, t, lt in el.props:
            if lt is None:
                size = np.dtype(t).itemsize
                if offset + size > len(raw):
                    raise InputError(f"{path}: truncated PLY in element {el.name!r}")
                cols[n].append(np.frombuffer(raw, dtype=endian + t, count=1, offset=offset)[0])
                offset += size
            else:
                csize = np.dtype(lt).itemsize
                if offset + csize > len(raw):
                    raise InputError(f"{path}: truncated PLY in element {el.name!r}")
                k = int(np.frombuffer(raw, dtype=endian + lt, count=1, offset=offset)[0])
                offset += csize
                size = np.dtype(t).itemsize * k
                if k < 0 or offset + size > len(raw):
                    raise InputError(f"{path}: truncated PLY in element {el.name!r}")
                cols[n].append(np.frombuffer(raw, dtype=endian + t, count=k, offset=offset))
                offset += size
    data[el.name] = {
        n: (cols[n] if lt is not None else np.asarray(cols[n])) for n, _, lt in el.props
    }
    return offset


def _read_ascii_element(path: Path, el: _Element, tokens: list[bytes], pos: int, data: dict) -> int:
    cols: dict[str, list] = {n: [] for n, _, _ in el.props}
    try:
        for _ in range(el.count):
            for n, t, lt in el.props:
                if lt is None:
                    cols[n].append(float(tokens[pos]))
                    pos += 1
                else:
                    k = int(tokens[pos])
                    cols[n].append([int(v) for v in tokens[pos + 1 : pos + 1 + k]])
                    if len(cols[n][-1]) != k:
                        raise IndexError
                    pos += 1 + k
    except (IndexError, ValueError) as exc:
        raise InputError(f"{path}: truncated or malformed ASCII PLY in element {el.name!r}") from exc
    out: dict[str, NDArray | list] = {}
    for n, t, lt in el.props:
        if lt is None:
            v = np.asarray(cols[n], dtype=np.float64)
            if np.dtype(t).kind in "iu" and len(v):
                info = np.iinfo(np.dtype(t))
                if not (np.isfinite(v).all() and v.min() >= info.min and v.max() <= info.max):
                    raise InputError(f"{path}: property {n!r} of element {el.name!r} holds values outside "
                                     f"its type {np.dtype(t).name} [{info.min}, {info.max}]")
            out[n] = v.astype(t)
        else:
            out[n] = cols[n]
    data[el.name] = out
    return pos
