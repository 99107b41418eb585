"""PFM (Portable Float Map) as Middlebury and ETH3D write it.

Header: ``PF`` (3 channels) or ``Pf`` (1 channel), then ``width height``, then a
scale whose sign gives the byte order (negative = little-endian); rows are stored
bottom-up. Infinity (ETH3D's "unknown") is kept as ``inf``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_file
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_open

__all__ = ["read_pfm", "write_pfm"]

_MAX_SIDE = 1 << 16


def read_pfm(path: str | Path) -> NDArray[np.float32]:
    """Read a PFM file.

    Returns
    -------
    (H, W) or (H, W, 3) float32
        Rows in top-down order (row 0 is the top of the image), native byte order.

    Raises
    ------
    InputError
        Missing file, wrong magic, bad header, or truncated / oversized data.
    """
    path = check_file(path, "PFM file")
    data = path.read_bytes()
    # three whitespace-separated header tokens after the magic, each ended by one
    # whitespace byte; the last is followed by exactly one whitespace char
    m = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data[:256])
    if m is None:
        if not data.startswith((b"PF", b"Pf")):
            raise InputError(f"{path}: not a PFM file (expected 'PF' or 'Pf' magic)")
        raise InputError(f"{path}: malformed PFM header")
    channels = 3 if m.group(1) == b"PF" else 1
    width, height = int(m.group(2)), int(m.group(3))
    try:
        scale = float(m.group(4))
    except ValueError as exc:
        raise InputError(f"{path}: malformed PFM scale {m.group(4)!r}") from exc
    if width <= 0 or height <= 0 or width > _MAX_SIDE or height > _MAX_SIDE:
        raise InputError(f"{path}: implausible PFM size {width}x{height}")
    if scale == 0 or not np.isfinite(scale):
        raise InputError(f"{path}: PFM scale must be non-zero, got {scale}")
    offset = m.end()
    n = width * height * channels
    if len(data) - offset < 4 * n:
        raise InputError(
            f"{path}: truncated PFM data: expected {4 * n} bytes for {width}x{height}x{channels}, "
            f"found {len(data) - offset}"
        )
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    arr = np.frombuffer(data, dtype=dtype, count=n, offset=offset)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.ascontiguousarray(arr.reshape(shape)[::-1]).astype(np.float32)


def write_pfm(path: str | Path, image: NDArray, *, little_endian: bool = True) -> None:
    """Write ``(H, W)`` or ``(H, W, 3)`` float data as PFM, atomically (bottom-up rows)."""
    img = check_array(image, "image", ndim=(2, 3), dtype_kind="fiu")
    if img.ndim == 3 and img.shape[2] != 3:
        raise InputError(f"image: PFM holds 1 or 3 channels, got {img.shape[2]}")
    if img.size == 0:
        raise InputError("image: empty array")
    h, w = img.shape[:2]
    magic = b"PF" if img.ndim == 3 else b"Pf"
    dtype = np.dtype("<f4") if little_endian else np.dtype(">f4")
    scale = b"-1.0" if little_endian else b"1.0"
    body = np.ascontiguousarray(img[::-1].astype(dtype)).tobytes()
    with atomic_open(path, "wb") as fh:
        fh.write(magic + b"\n" + f"{w} {h}".encode() + b"\n" + scale + b"\n")
        fh.write(body)
