"""OpenCV FileStorage YAML: the calibration file format users already know.

Files are written by ``cv2.FileStorage`` itself (so any OpenCV reader can load
them), atomically. Reading returns plain Python / numpy values.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

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

    Raises
    ------
    InputError
        If the file is missing, not a FileStorage document, or lacks a required key.
    """
    import cv2

    path = check_file(path, "calibration file")
    head = path.read_bytes()[:64]
    if not (head.startswith(b"%YAML") or head.lstrip().startswith((b"<?xml", b"{"))):
        raise InputError(
            f"{path}: not an OpenCV FileStorage file (expected a '%YAML:1.0' header)"
        )
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV's parser raises either
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "parse error"
        raise InputError(f"{path}: malformed FileStorage file ({msg})") from exc
    try:
        if not fs.isOpened():
            raise InputError(f"{path}: could not open as an OpenCV FileStorage file")
        root = fs.root()
        if not root.isMap():
            raise InputError(f"{path}: the FileStorage document holds no entries")
        names = list(root.keys()) if keys is None else keys
        out: dict[str, Any] = {}
        for name in names:
            node = fs.getNode(name)
            if node.empty() or node.isNone():
                raise InputError(f"{path}: missing entry {name!r}")
            out[name] = _node_value(node, path, name)
        return out
    except (cv2.error, SystemError) as exc:  # e.g. a matrix whose data does not fill rows x cols
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "parse error"
        raise InputError(f"{path}: malformed FileStorage file ({msg})") from None
    finally:
        fs.release()


def _node_value(node: Any, path: Path, name: str) -> Any:
    if node.isString():
        return node.string()
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isSeq():
        items = [node.at(i) for i in range(node.size())]
        if all(it.isInt() or it.isReal() for it in items):
            return np.array([it.real() for it in items], dtype=np.float64)
        return [_node_value(it, path, f"{name}[{i}]") for i, it in enumerate(items)]
    mat = node.mat()
    if mat is None:
        raise InputError(f"{path}: entry {name!r} is neither a number, string nor matrix")
    return np.asarray(mat)
