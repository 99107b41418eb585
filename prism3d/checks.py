"""The one input-check helper family used everywhere in prism3d.

Every message states what was expected and what was found, and names the argument
(or file), so a user can act on it. All checks raise :class:`~prism3d.errors.InputError`
(or the error class passed as ``error``).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from prism3d.errors import InputError, Prism3dError

__all__ = [
    "check_array",
    "check_same_shape",
    "check_positive",
    "check_in_range",
    "check_choice",
    "check_seed",
    "check_file",
    "check_finite",
    "check_outputs_not_inputs",
]


def _describe_shape(shape: Sequence[int | None]) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"


def check_array(
    value: Any,
    name: str,
    *,
    ndim: int | Iterable[int] | None = None,
    shape: Sequence[int | None] | None = None,
    dtype_kind: str | None = None,
    min_size: int = 0,
    error: type[Prism3dError] = InputError,
) -> np.ndarray:
    """Validate an array argument and return it as ``np.ndarray`` (no copy if possible).

    Parameters
    ----------
    value : array_like
        The argument to check.
    name : str
        Its name in messages.
    ndim : int or iterable of int, optional
        Allowed numbers of dimensions.
    shape : sequence of int or None, optional
        Expected shape; ``None`` entries match any length. Implies ``ndim``.
    dtype_kind : str, optional
        Allowed numpy dtype kinds, e.g. ``"f"``, ``"fiu"``, ``"b"``, ``"u"``.
    min_size : int
        Minimum number of elements.
    error : type
        Error class raised (default :class:`InputError`).
    """
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged lists and the like
        raise error(f"{name}: expected an array, got {type(value).__name__} ({exc})") from exc
    if shape is not None:
        ok = arr.ndim == len(shape) and all(
            s is None or s == a for s, a in zip(shape, arr.shape, strict=False)
        )
        if not ok:
            raise error(
                f"{name}: expected shape {_describe_shape(shape)}, got {tuple(arr.shape)}"
            )
    elif ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else tuple(ndim)
        if arr.ndim not in allowed:
            want = " or ".join(str(a) for a in allowed)
            raise error(
                f"{name}: expected {want} dimensions, got {arr.ndim} (shape {tuple(arr.shape)})"
            )
    if dtype_kind is not None and arr.dtype.kind not in dtype_kind:
        raise error(f"{name}: expected dtype kind in {dtype_kind!r}, got {arr.dtype}")
    if arr.size < min_size:
        raise error(f"{name}: expected at least {min_size} elements, got {arr.size}")
    return arr


def check_same_shape(
    a: np.ndarray, b: np.ndarray, names: tuple[str, str], *, dims: int | None = None
) -> None:
    """Raise unless ``a.shape[:dims] == b.shape[:dims]`` (all dims when ``None``)."""
    sa = a.shape if dims is None else a.shape[:dims]
    sb = b.shape if dims is None else b.shape[:dims]
    if sa != sb:
        raise InputError(
            f"{names[0]} and {names[1]} must have the same shape, got {tuple(sa)} and {tuple(sb)}"
        )


def check_positive(value: float, name: str, *, strict: bool = True) -> float:
    """Raise unless ``value`` is a finite number > 0 (>= 0 when ``strict`` is False)."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a number, got {value!r}") from exc
    if not np.isfinite(v) or (v <= 0 if strict else v < 0):
        rel = "> 0" if strict else ">= 0"
        raise InputError(f"{name}: expected a finite number {rel}, got {value!r}")
    return v


def check_in_range(value: float, name: str, lo: float, hi: float) -> float:
    """Raise unless ``lo <= value <= hi``."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected a number, got {value!r}") from exc
    if not (lo <= v <= hi):
        raise InputError(f"{name}: expected a value in [{lo}, {hi}], got {value!r}")
    return v


def check_int(value: Any, name: str) -> int:
    """``value`` as an int; a bool, float or anything else is an InputError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name}: expected an integer, got {value!r} ({type(value).__name__})")
    return int(value)


def check_seed(value: Any, name: str = "seed") -> int:
    """A random seed: an integer in [0, 2**63) (numpy's generators take no negative seed)."""
    v = check_int(value, name)
    if not 0 <= v < 2**63:
        raise InputError(f"{name}: expected an integer in [0, 2**63), got {v}")
    return v


def check_choice(value: Any, name: str, choices: Iterable[Any]) -> Any:
    """Raise unless ``value`` is one of ``choices``."""
    options = list(choices)
    if value not in options:
        raise InputError(
            f"{name}: expected one of {', '.join(map(str, options))}; got {value!r}"
        )
    return value


def check_finite(arr: np.ndarray, name: str) -> np.ndarray:
    """Raise unless every element of ``arr`` is finite."""
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: expected finite values, found NaN or inf")
    return arr


def check_file(path: str | Path, what: str = "file") -> Path:
    """Return ``Path(path)`` if it is an existing regular file, else raise InputError."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: {what} not found; check the path")
    if not p.is_file():
        raise InputError(f"{p}: expected a {what}, found a directory or special file")
    return p


def _same_path(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name one file or folder (hard links and symlinks included)."""
    try:
        if a.exists() and b.exists() and os.path.samefile(a, b):
            return True
    except OSError:
        pass
    return a.resolve() == b.resolve()


def check_outputs_not_inputs(
    outputs: Iterable[str | Path | None],
    inputs: Iterable[str | Path | None] = (),
    *,
    input_folders: Iterable[str | Path | None] = (),
) -> None:
    """Raise InputError when an output would replace an input: an output path that is
    one of ``inputs`` (the same file, through any link), or lies inside one of
    ``input_folders``. Checked before any work, since the outputs are written last and an
    input overwritten by its own results is lost. ``None`` entries are skipped."""
    ins = [Path(p) for p in inputs if p is not None]
    dirs = [Path(p) for p in input_folders if p is not None]
    for out in (Path(p) for p in outputs if p is not None):
        for inp in ins:
            if _same_path(out, inp):
                raise InputError(f"{out}: is also an input ({inp}); give another output path")
        r = out.resolve()
        for d in dirs:
            if _same_path(out, d) or r.is_relative_to(d.resolve()):
                raise InputError(f"{out}: lies in the input folder {d}; write it elsewhere")
