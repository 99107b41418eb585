"""PCD point clouds (Point Cloud Library format): reader for ascii, binary and
binary_compressed data.

Reads ``x y z`` plus, when present, packed colour (``rgb`` as a float or ``rgba``
as an unsigned int, both ``0x00RRGGBB`` / ``0xAARRGGBB`` bit patterns) and normals
(``normal_x normal_y normal_z``). Points with a non-finite coordinate (PCL's "no
measurement" in organised clouds) are dropped. Other scalar fields are returned in
``extra``.

References
----------
.. [1] Point Cloud Library, "The PCD (Point Cloud Data) file format",
   https://pointclouds.org/documentation/tutorials/pcd_file_format.html
.. [2] M. Lehmann, "LibLZF" (the LZF compression format used by
   ``binary_compressed``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_file
from prism3d.errors import InputError
from prism3d.io._pcd_kernels import lzf_decompress

__all__ = ["PcdData", "read_pcd"]

_TYPE_CODES = {
    ("F", 4): "f4", ("F", 8): "f8",
    ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8",
    ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
}
_MAX_HEADER = 64 * 1024


@dataclass
class PcdData:
    """Contents of a PCD file (finite points only).

    Attributes
    ----------
    points : (N, 3) float64
        Point positions, units as stored (PCL data is usually in metres).
    colors : (N, 3) uint8 or None
        RGB from a packed ``rgb``/``rgba`` field.
    normals : (N, 3) float32 or None
    extra : dict of str -> (N,) array
        Other single-valued fields (e.g. ``curvature``).
    width, height : int
        The stored organisation (``height > 1``: an organised, image-like cloud).
    viewpoint : (7,) float64
        Acquisition viewpoint ``tx ty tz qw qx qy qz``.
    n_dropped : int
        Points dropped for non-finite coordinates.
    """

    points: NDArray[np.float64]
    colors: NDArray[np.uint8] | None = None
    normals: NDArray[np.float32] | None = None
    extra: dict[str, NDArray] = field(default_factory=dict)
    width: int = 0
    height: int = 1
    viewpoint: NDArray[np.float64] = field(
        default_factory=lambda: np.array([0, 0, 0, 1, 0, 0, 0], dtype=np.float64)
    )
    n_dropped: int = 0


def _parse_header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = raw.find(b"\n", pos)
        if nl < 0 or pos > _MAX_HEADER:
            raise InputError(f"{path}: not a PCD file (no 'DATA' line in the header)")
        line = raw[pos:nl].decode("ascii", errors="replace").strip()
        pos = nl + 1
        if not line or line.startswith("#"):
            continue
        key, _, rest = line.partition(" ")
        key = key.upper()
        header[key] = rest.split()
        if key == "DATA":
            return header, pos


def _int_value(path: Path, header: dict[str, list[str]], key: str, default: int | None) -> int:
    if key not in header:
        if default is None:
            raise InputError(f"{path}: PCD header lacks {key}")
        return default
    try:
        value = int(header[key][0])
    except (ValueError, IndexError) as exc:
        raise InputError(f"{path}: PCD {key} must be an integer, got {header[key]!r}") from exc
    if value < 0:
        raise InputError(f"{path}: PCD {key} must be >= 0, got {value}")
    return value


def _record_dtype(path: Path, header: dict[str, list[str]]) -> np.dtype:
    names = header.get("FIELDS", header.get("COLUMNS"))
    if not names:
        raise InputError(f"{path}: PCD header lacks FIELDS")
    n = len(names)
    sizes = header.get("SIZE", ["4"] * n)
    types = header.get("TYPE", ["F"] * n)
    counts = header.get("COUNT", ["1"] * n)
    if not (len(sizes) == len(types) == len(counts) == n):
        raise InputError(
            f"{path}: PCD FIELDS/SIZE/TYPE/COUNT lengths differ "
            f"({n}, {len(sizes)}, {len(types)}, {len(counts)})"
        )
    fields = []
    seen: set[str] = set()
    for i, (name, s, t, c) in enumerate(zip(names, sizes, types, counts, strict=True)):
        try:
            code = _TYPE_CODES[(t.upper(), int(s))]
            cnt = int(c)
        except (KeyError, ValueError) as exc:
            raise InputError(
                f"{path}: unsupported PCD field {name!r} (TYPE {t}, SIZE {s}, COUNT {c})"
            ) from exc
        if cnt < 1:
            raise InputError(f"{path}: PCD field {name!r} has COUNT {cnt}, expected >= 1")
        uname = name if name not in seen and name != "_" else f"_pad{i}"
        seen.add(uname)
        fields.append((uname, "<" + code, (cnt,)) if cnt > 1 else (uname, "<" + code))
    return np.dtype(fields)


#: LZF's largest expansion: a 3-byte back-reference yields at most 264 bytes (88x), so a
#: header claiming more from its compressed size is corrupt, refused before allocating.
_LZF_MAX_RATIO = 88


def _decode_binary_compressed(path: Path, body: bytes, dtype: np.dtype, n: int) -> np.ndarray:
    if len(body) < 8:
        raise InputError(f"{path}: binary_compressed PCD is truncated (no size words)")
    comp, uncomp = np.frombuffer(body[:8], dtype="<u4")
    if uncomp != n * dtype.itemsize:
        raise InputError(
            f"{path}: binary_compressed PCD holds {uncomp} bytes, expected "
            f"{n * dtype.itemsize} for {n} points"
        )
    if len(body) < 8 + comp:
        raise InputError(f"{path}: binary_compressed PCD is truncated ({len(body) - 8} < {comp} bytes)")
    if uncomp > _LZF_MAX_RATIO * int(comp) + 64:
        raise InputError(f"{path}: binary_compressed PCD claims {uncomp} bytes from {comp}, more than LZF "
                         "can expand to; corrupt header")
    src = np.frombuffer(body[8 : 8 + int(comp)], dtype=np.uint8)
    out, status = lzf_decompress(src, int(uncomp))
    if status != uncomp:
        raise InputError(f"{path}: corrupt LZF data in binary_compressed PCD")
    # Uncompressed layout: one contiguous block per field (structure of arrays).
    rec = np.empty(n, dtype=dtype)
    off = 0
    for name in dtype.names or ():
        sub = dtype.fields[name][0]  # type: ignore[index]
        nbytes = n * sub.itemsize
        rec[name] = np.frombuffer(out[off : off + nbytes].tobytes(), dtype=sub.base).reshape(
            rec[name].shape
        )
        off += nbytes
    return rec


def _decode_ascii(path: Path, body: bytes, dtype: np.dtype, n: int) -> np.ndarray:
    flat = []
    for name in dtype.names or ():
        sub = dtype.fields[name][0]  # type: ignore[index]
        flat.append((name, sub, int(np.prod(sub.shape)) if sub.shape else 1))
    width = sum(c for _, _, c in flat)
    try:
        values = np.array(body.decode("ascii").split(), dtype=np.float64)
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: malformed ascii PCD data ({exc})") from exc
    if values.size < n * width:
        raise InputError(f"{path}: ascii PCD has {values.size} values, expected {n * width}")
    values = values[: n * width].reshape(n, width)
    rec = np.empty(n, dtype=dtype)
    col = 0
    for name, sub, cnt in flat:
        block = values[:, col : col + cnt]
        col += cnt
        base = sub.base
        if name in ("rgb",) and base.kind == "f":
            rec[name] = block.reshape(rec[name].shape).astype(np.float32)
        elif base.kind in "iu":
            rec[name] = np.round(block).astype(base).reshape(rec[name].shape)
        else:
            rec[name] = block.astype(base).reshape(rec[name].shape)
    return rec


def _decode_body(p: Path, header: dict[str, list[str]], body: bytes, dtype: np.dtype, n: int) -> np.ndarray:
    """The ``n`` records of a PCD body in its ``DATA`` mode."""
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    if mode == "ascii":
        return _decode_ascii(p, body, dtype, n)
    if mode == "binary":
        need = n * dtype.itemsize
        if len(body) < need:
            raise InputError(f"{p}: binary PCD is truncated ({len(body)} < {need} bytes)")
        return np.frombuffer(body[:need], dtype=dtype)
    if mode == "binary_compressed":
        return _decode_binary_compressed(p, body, dtype, n)
    raise InputError(f"{p}: unknown PCD DATA mode {mode!r} (expected ascii, binary or binary_compressed)")


def _packed_colors(rec: np.ndarray, names: tuple[str, ...]) -> NDArray[np.uint8] | None:
    """(N, 3) RGB from the first packed ``rgb`` (float bits) or ``rgba`` (uint) field,
    ``0x00RRGGBB`` / ``0xAARRGGBB``; None without one."""
    for cname in ("rgb", "rgba"):
        if cname in names:
            v = np.ascontiguousarray(rec[cname])
            bits = v.view(np.uint32) if v.dtype.itemsize == 4 else v.astype(np.uint32)
            return np.stack(
                [(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], axis=1
            ).astype(np.uint8)
    return None


def _extra_fields(rec: np.ndarray, names: tuple[str, ...]) -> dict[str, NDArray]:
    """The scalar fields other than coordinates, colour, normals and padding (copies)."""
    used = {"x", "y", "z", "rgb", "rgba", "normal_x", "normal_y", "normal_z"}
    return {
        k: np.array(rec[k])
        for k in names
        if k not in used and not k.startswith("_pad") and rec[k].ndim == 1
    }


def _viewpoint(p: Path, header: dict[str, list[str]]) -> NDArray[np.float64]:
    """The header's 7-number ``VIEWPOINT`` (translation, quaternion w x y z); identity when
    absent or not 7 values."""
    vp = np.array([0, 0, 0, 1, 0, 0, 0], dtype=np.float64)
    if "VIEWPOINT" in header and len(header["VIEWPOINT"]) == 7:
        try:
            vp = np.array([float(v) for v in header["VIEWPOINT"]])
        except ValueError as exc:
            raise InputError(f"{p}: PCD VIEWPOINT must be 7 numbers, got {header['VIEWPOINT']!r}") from exc
    return vp


def read_pcd(path: str | Path) -> PcdData:
    """Read a PCD file (``DATA ascii``, ``binary`` or ``binary_compressed``).

    Parameters
    ----------
    path : path
        The ``.pcd`` file.

    Returns
    -------
    PcdData
        Finite points (non-finite ones dropped), colours from a packed ``rgb`` /
        ``rgba`` field, normals from ``normal_x/y/z``.

    Raises
    ------
    InputError
        Missing file, malformed header, unsupported field types, no ``x y z``
        fields, truncated or corrupt data.
    """
    p = check_file(path, "pcd file")
    raw = p.read_bytes()
    header, start = _parse_header(p, raw)
    dtype = _record_dtype(p, header)
    width = _int_value(p, header, "WIDTH", None)
    height = _int_value(p, header, "HEIGHT", 1)
    n = _int_value(p, header, "POINTS", width * height)
    names = dtype.names or ()
    for c in "xyz":
        if c not in names:
            raise InputError(f"{p}: PCD has no {c!r} field (fields: {' '.join(names)}); not a point cloud")
    rec = _decode_body(p, header, raw[start:], dtype, n)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    keep = np.isfinite(pts).all(axis=1)
    pts = pts[keep]
    rec = rec[keep]
    colors = _packed_colors(rec, names)
    normals = None
    if all(k in names for k in ("normal_x", "normal_y", "normal_z")):
        normals = np.stack(
            [rec["normal_x"], rec["normal_y"], rec["normal_z"]], axis=1
        ).astype(np.float32)
    return PcdData(
        points=pts,
        colors=colors,
        normals=normals,
        extra=_extra_fields(rec, names),
        width=width,
        height=height,
        viewpoint=_viewpoint(p, header),
        n_dropped=int((~keep).sum()),
    )
