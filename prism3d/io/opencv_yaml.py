"""OpenCV FileStorage YAML: the calibration file format users already know.

Files are written by ``cv2.FileStorage`` itself (so any OpenCV reader can load
them), atomically. Reading parses them here and returns plain Python / numpy values.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_file
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_write_text

__all__ = ["write_filestorage", "read_filestorage"]

_Value = int | float | str | np.ndarray | list


def write_filestorage(path: str | Path, values: Mapping[str, Any]) -> None:
    """Write ``values`` (name -> scalar, string, array or list of numbers) as YAML.

    Arrays become ``!!opencv-matrix`` nodes (float64 unless integer); 1-D arrays are
    stored as column vectors, as OpenCV does. Booleans become integers 0/1.
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() not in (".yaml", ".yml", ".xml", ".json"):
        raise InputError(f"{path}: calibration files must end in .yaml, .yml, .xml or .json")
    # composed in memory, then written by Python: a full disk is an OSError, whereas
    # FileStorage writing to a file leaves it empty and says nothing
    fs = cv2.FileStorage(path.suffix.lower(), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    try:
        for key, value in values.items():
            if not key.isidentifier():
                raise InputError(f"{path}: invalid FileStorage key {key!r}")
            if isinstance(value, bool | np.bool_):
                fs.write(key, int(value))
            elif isinstance(value, int | np.integer):
                fs.write(key, int(value))
            elif isinstance(value, float | np.floating):
                fs.write(key, float(value))
            elif isinstance(value, str):
                fs.write(key, value)
            else:
                arr = np.asarray(value)
                if arr.dtype.kind in "iub":
                    arr = arr.astype(np.int32)
                else:
                    arr = arr.astype(np.float64)
                if arr.ndim == 0:
                    fs.write(key, arr.item())
                else:
                    fs.write(key, np.ascontiguousarray(arr.reshape(arr.shape[0], -1)))
    except BaseException:
        fs.release()
        raise
    atomic_write_text(path, fs.releaseAndGetString())


def read_filestorage(path: str | Path, keys: list[str] | None = None) -> dict[str, Any]:
    """Read a FileStorage file's top-level entries into a dict.

    Matrices come back as ``np.ndarray`` (float64 or int32), numbers as ``float``
    (or ``int`` when integral and stored as an int), strings as ``str``; sequences of
    numbers as 1-D arrays. ``keys`` restricts (and requires) the entries read.

    The YAML, JSON and XML flavours are parsed here (PyYAML, json, ElementTree), not by
    ``cv2.FileStorage``: OpenCV 5.0's reader overflows its heap on a matrix whose
    ``rows x cols`` disagree with its data (found by fuzzing), so it never sees a user's
    bytes.

    Raises
    ------
    InputError
        If the file is missing, not a FileStorage document, or lacks a required key.
    """
    path = check_file(path, "calibration file")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a FileStorage file (not UTF-8 text)") from None
    head = text[:64].lstrip()
    if text.startswith("%YAML"):
        doc = _parse_yaml(text, path)
    elif head.startswith("<?xml") or head.startswith("<opencv_storage"):
        doc = _parse_xml(text, path)
    elif head.startswith("{"):
        doc = _parse_json(text, path)
    else:
        raise InputError(f"{path}: not an OpenCV FileStorage file (expected a '%YAML:1.0' header)")
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{path}: the FileStorage document holds no entries")
    names = list(doc) if keys is None else keys
    out: dict[str, Any] = {}
    for name in names:
        if doc.get(name) is None:
            raise InputError(f"{path}: missing entry {name!r}")
        out[name] = _value(doc[name], path, str(name))
    return out


#: FileStorage ``dt`` depth codes -> numpy dtypes (``u`` uint8 ... ``d`` float64).
_DEPTHS = {"u": np.uint8, "c": np.int8, "w": np.uint16, "s": np.int16, "i": np.int32,
           "f": np.float32, "d": np.float64, "h": np.float16}
#: A plain YAML scalar that FileStorage reads as a real number (YAML 1.2 style: "1e-5",
#: "1.", ".5"), which PyYAML's YAML 1.1 rules would leave a string.
_REAL = re.compile(r"^[-+]?(?:\.[0-9]+|[0-9]+\.?[0-9]*)(?:[eE][-+]?[0-9]+)?$|^[-+]?\.inf$|^\.nan$", re.IGNORECASE)


_MATRIX_TYPES = ("opencv-matrix", "opencv-nd-matrix")


class _Matrix(dict):
    """An ``opencv-matrix`` / ``opencv-nd-matrix`` node's fields until :func:`_matrix`
    checks them."""


def _yaml_loader() -> type:
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    # FileStorage has no booleans or dates: "yes", "on", "2020-01-01" stay strings
    Loader.yaml_implicit_resolvers = {
        k: [(tag, rx) for tag, rx in v if tag not in ("tag:yaml.org,2002:bool", "tag:yaml.org,2002:timestamp")]
        for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }

    def plain_str(loader: Any, node: Any) -> Any:
        value = loader.construct_scalar(node)
        return _real(value) if node.style is None and _REAL.match(value) else value

    def matrix(loader: Any, node: Any) -> _Matrix:
        if not isinstance(node, yaml.MappingNode):
            raise InputError("an opencv-matrix must be a map of rows, cols, dt and data")
        return _Matrix(loader.construct_mapping(node, deep=True))

    Loader.add_constructor("tag:yaml.org,2002:str", plain_str)
    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    Loader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix", matrix)
    return Loader


def _parse_yaml(text: str, path: Path) -> Any:
    import yaml

    body = text.split("\n", 1)[1] if "\n" in text else ""  # "%YAML:1.0" is not a YAML directive
    try:
        return yaml.load(body, Loader=_yaml_loader())  # noqa: S506 - a SafeLoader subclass
    except InputError as exc:
        raise InputError(f"{path}: malformed FileStorage file ({exc})") from None
    except (yaml.YAMLError, ValueError, TypeError, RecursionError) as exc:
        msg = " ".join(str(exc).split())[:200] or "parse error"
        raise InputError(f"{path}: malformed FileStorage file ({msg})") from None


def _parse_json(text: str, path: Path) -> Any:
    import json

    def hook(d: dict) -> Any:
        return _Matrix(d) if d.get("type_id") in _MATRIX_TYPES else d

    # OpenCV writes NaN and infinity as bare .Nan / .Inf, which JSON does not have
    text = re.sub(r"(?<=[\s:\[,])([-+]?)\.(Inf|Nan)\b",
                  lambda m: {"Inf": "Infinity", "Nan": "NaN"}[m.group(2)] if m.group(1) != "-" else "-Infinity",
                  text, flags=re.IGNORECASE)
    try:
        return json.loads(text, object_hook=hook)
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{path}: malformed FileStorage file ({exc})") from None


def _parse_xml(text: str, path: Path) -> Any:
    import xml.etree.ElementTree as ET

    if "<!DOCTYPE" in text or "<!ENTITY" in text:  # no entity expansion (billion laughs)
        raise InputError(f"{path}: FileStorage XML must not declare a DOCTYPE or entities")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise InputError(f"{path}: malformed FileStorage file ({exc})") from None
    if root.tag != "opencv_storage":
        raise InputError(f"{path}: not an OpenCV FileStorage file (root <{root.tag}>)")
    return {el.tag: _xml_value(el) for el in root}


def _xml_value(el: Any) -> Any:
    if el.get("type_id") in _MATRIX_TYPES:
        return _Matrix({c.tag: (c.text or "").strip() for c in el})
    if len(el):  # a sequence (<_> items) or a map
        if all(c.tag == "_" for c in el):
            return [_xml_value(c) for c in el]
        return {c.tag: _xml_value(c) for c in el}
    # a text of several items is a sequence; an item in quotes may hold spaces
    vals = [_xml_scalar(w) for w in re.findall(r'"[^"]*"|\S+', el.text or "")]
    if len(vals) == 1:
        return vals[0]
    return vals if vals else ""


def _xml_scalar(word: str) -> Any:
    try:
        return int(word)
    except ValueError:
        pass
    return _real(word) if _REAL.match(word) else word.strip('"')


def _real(text: str) -> float:
    """A number as FileStorage writes it, ``.Nan`` and ``-.Inf`` included."""
    t = text.lower()
    return float(t.replace(".inf", "inf").replace(".nan", "nan")) if t.lstrip("+-").startswith((".inf", ".nan")) else float(t)


def _value(v: Any, path: Path, name: str) -> Any:
    """A parsed entry as read_filestorage returns it (the types OpenCV's nodes give)."""
    if isinstance(v, _Matrix):
        return _matrix(v, path, name)
    if isinstance(v, bool):  # JSON true/false
        return int(v)
    if isinstance(v, int | float | str):
        return v
    if isinstance(v, list):
        if all(isinstance(it, int | float) and not isinstance(it, bool) for it in v):
            return np.array(v, dtype=np.float64)
        return [_value(it, path, f"{name}[{i}]") for i, it in enumerate(v)]
    raise InputError(f"{path}: entry {name!r} is neither a number, string nor matrix")


def _matrix(m: dict, path: Path, name: str) -> NDArray:
    """An opencv-matrix node checked: rows x cols x channels numbers of type ``dt``."""
    def whole_value(v: Any, key: str) -> int:
        if isinstance(v, str) and v.strip().isdigit():
            v = int(v)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise InputError(f"{path}: matrix {name!r}: '{key}' must be a whole number >= 0, got {v!r}")
        return v

    def whole(key: str) -> int:
        return whole_value(m.get(key), key)

    if "sizes" in m:  # opencv-nd-matrix (OpenCV writes 1-D arrays so)
        sizes = m["sizes"]
        sizes = sizes.split() if isinstance(sizes, str) else sizes if isinstance(sizes, list) else [sizes]
        shape = []
        for k, v in enumerate(sizes):
            shape.append(whole_value(v, f"sizes[{k}]"))
    else:
        shape = [whole("rows"), whole("cols")]
    if not 1 <= len(shape) <= 8:
        raise InputError(f"{path}: matrix {name!r}: expected 1 to 8 dimensions, got {len(shape)}")
    dt = str(m.get("dt", "")).strip()
    mt = re.fullmatch(r"([1-4]?)([ucwsifdh])", dt)
    if mt is None:
        raise InputError(f"{path}: matrix {name!r}: unsupported dt {dt!r}")
    ch = int(mt.group(1) or 1)
    data = m.get("data", [])
    if isinstance(data, str):  # XML: whitespace-separated numbers
        data = data.split()
    if not isinstance(data, list):
        raise InputError(f"{path}: matrix {name!r}: 'data' must be a list of numbers")
    n = int(np.prod(shape, dtype=object)) * ch
    if len(data) != n:
        dims = "x".join(map(str, [*shape, ch]))
        raise InputError(f"{path}: matrix {name!r}: {len(data)} numbers for {dims}")
    try:
        arr = np.array([_real(x) if isinstance(x, str) and _REAL.match(x) else float(x) for x in data],
                       dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{path}: matrix {name!r}: 'data' must hold numbers only") from None
    dtype = _DEPTHS[mt.group(2)]
    if np.dtype(dtype).kind in "iu":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise InputError(f"{path}: matrix {name!r}: dt {dt!r} needs whole numbers")
        info = np.iinfo(dtype)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            raise InputError(f"{path}: matrix {name!r}: values outside {np.dtype(dtype).name}")
    return arr.astype(dtype).reshape((*shape, ch) if ch > 1 else tuple(shape))
