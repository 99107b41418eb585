"""Images and float depth maps.

Images are RGB ``uint8`` in memory (BGR only at the OpenCV boundary, here). Depth
maps are float32 millimetres with NaN = no surface, stored as float32 TIFF, ``.npy``
or a key of an ``.npz`` (``file.npz:depth_left_mm``), or PFM.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_file
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path

__all__ = ["read_image", "write_image", "read_depth", "write_depth", "split_npz_spec"]

_IMAGE_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".pnm", ".webp"}


def read_image(path: str | Path, *, grey: bool = False) -> NDArray[np.uint8]:
    """Read an 8-bit image as RGB ``(H, W, 3)`` (or ``(H, W)`` grey when ``grey``).

    16-bit images are scaled to 8 bits. Raises InputError naming the file when it is
    missing or cannot be decoded.
    """
    import cv2

    path = check_file(path, "image")
    buf = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None:
        raise InputError(f"{path}: cannot decode as an image (corrupt or unsupported format)")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(f"{path}: expected an 8- or 16-bit image, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 3:
        img = img[:, :, ::-1]
    if grey:
        if img.ndim == 3:
            img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
        return np.ascontiguousarray(img)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img)


def write_image(path: str | Path, image: NDArray) -> None:
    """Write an RGB ``(H, W, 3)`` or grey ``(H, W)`` uint8 (or bool) image atomically."""
    import cv2

    img = check_array(image, "image", ndim=(2, 3))
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.dtype != np.uint8:
        raise InputError(f"image: expected uint8, got {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] != 3:
            raise InputError(f"image: expected 3 channels, got {img.shape[2]}")
        img = np.ascontiguousarray(img[:, :, ::-1])
    path = Path(path)
    if path.suffix.lower() not in _IMAGE_EXT:
        raise InputError(f"{path}: unsupported image extension {path.suffix!r}")
    ok, enc = cv2.imencode(path.suffix.lower(), img)
    if not ok:
        raise InputError(f"{path}: OpenCV could not encode the image")
    with atomic_path(path) as tmp:
        tmp.write_bytes(enc.tobytes())


def split_npz_spec(spec: str | Path) -> tuple[Path, str | None]:
    """Split ``file.npz:key`` into ``(Path('file.npz'), 'key')``; other paths get ``None``."""
    s = str(spec)
    if ".npz:" in s:
        head, _, key = s.rpartition(":")
        return Path(head), key
    return Path(s), None


def read_depth(spec: str | Path) -> NDArray[np.float32]:
    """Read a depth map ``(H, W)`` float32 mm from ``.tif/.tiff``, ``.npy``, ``.pfm`` or
    ``file.npz:key`` (key optional when the archive holds one array)."""
    path, key = split_npz_spec(spec)
    path = check_file(path, "depth map")
    suffix = path.suffix.lower()
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            arr = tifffile.imread(str(path))
        elif suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                names = list(z.files)
                if key is None:
                    if len(names) != 1:
                        raise InputError(
                            f"{path}: holds {len(names)} arrays; name one as {path}:KEY "
                            f"({', '.join(names)})"
                        )
                    key = names[0]
                if key not in names:
                    raise InputError(f"{path}: no array {key!r}; it holds {', '.join(names)}")
                arr = z[key]
        elif suffix == ".pfm":
            from prism3d.io.pfm import read_pfm

            arr = read_pfm(path)
        else:
            raise InputError(f"{path}: unsupported depth format {suffix!r} (use .tiff, .npy, .npz:KEY, .pfm)")
    except InputError:
        raise
    except Exception as exc:  # corrupt files from numpy/tifffile
        raise InputError(f"{path}: cannot read depth map ({type(exc).__name__}: {exc})") from exc
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2 or arr.dtype.kind not in "fiu":
        raise InputError(f"{path}: expected a 2-D numeric depth map, got shape {arr.shape} {arr.dtype}")
    return arr.astype(np.float32)


def write_depth(path: str | Path, depth_mm: NDArray) -> None:
    """Write a float32 depth map atomically as ``.tiff``, ``.npy`` or ``.npz`` (key ``depth_mm``)."""
    d = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="fiu").astype(np.float32)
    path = Path(path)
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix in (".tif", ".tiff"):
            import tifffile

            tifffile.imwrite(str(tmp), d)
        elif suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, d)
        elif suffix == ".npz":
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, depth_mm=d)
        else:
            raise InputError(f"{path}: unsupported depth format {suffix!r} (use .tiff, .npy, .npz)")
