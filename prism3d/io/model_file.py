"""Model files: one ``.npz`` of named arrays plus JSON metadata (no pickle), written
atomically and read back with one clear error for anything that is not such a file.
Shared by the trained recognisers (:mod:`prism3d.atr.aerial`, :mod:`prism3d.atr.verifier`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path

__all__ = ["read_model_npz", "write_model_npz"]


def write_model_npz(path: Path, meta: dict[str, Any], arrays: dict[str, NDArray]) -> Path:
    """Write ``meta`` (as ``meta_json``) and ``arrays`` into ``path`` atomically."""
    blob = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, meta_json=blob, **arrays)
    return path


def read_model_npz(path: Path, what: str) -> tuple[dict[str, Any], dict[str, NDArray]]:
    """The metadata and arrays of a file written by :func:`write_model_npz`; ``what`` names
    the expected file in the error for a missing one ("model", "recogniser")."""
    if not path.is_file():
        raise InputError(f"{path}: no such {what} file")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta_json"]).decode("utf-8"))
            arrays = {k: z[k] for k in z.files if k != "meta_json"}
    except Exception as exc:  # noqa: BLE001 - zip/numpy/json raise many types on a damaged file
        raise InputError(f"{path}: not a prism3d model file ({exc or type(exc).__name__})") from None
    return meta, arrays
