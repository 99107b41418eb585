"""Images and float depth maps.

Images are RGB ``uint8`` in memory (BGR only at the OpenCV boundary, here). Depth
maps are float32 millimetres with NaN = no surface, stored as float32 TIFF, ``.npy``
or a key of an ``.npz`` (``file.npz:depth_left_mm``), or PFM.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_file
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path
from prism3d.io.pfm import read_pfm

__all__ = ["DEFAULT_MAX_PIXELS", "IMAGE_EXTENSIONS", "max_pixels", "pixel_count", "check_image_size", "check_npy_header", "read_image", "write_image",
           "read_depth", "write_depth", "split_npz_spec", "decode_image"]

#: Largest image decoded unless ``PRISM3D_MAX_PIXELS`` says otherwise: 100 MP is twice
#: the largest common camera sensors, ~300 MB as RGB; a small file claiming more (a
#: decompression bomb) is refused from its header, before any memory is taken.
DEFAULT_MAX_PIXELS = 100_000_000

#: File extensions :func:`write_image` writes (OpenCV chooses the encoder by them).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".pnm", ".webp")
_IMAGE_EXT = set(IMAGE_EXTENSIONS)


def read_image(path: str | Path, *, grey: bool = False) -> NDArray[np.uint8]:
    """Read an 8-bit image as RGB ``(H, W, 3)`` (or ``(H, W)`` grey when ``grey``).

    16-bit images are scaled to 8 bits. Raises InputError naming the file when it is
    missing or cannot be decoded.
    """
    import cv2

    path = check_file(path, "image")
    check_image_size(path)
    buf = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    img = decode_image(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
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


def decode_image(buf: NDArray[np.uint8], flags: int) -> NDArray | None:
    """``cv2.imdecode`` with the C libraries' own messages (libpng's "PNG input buffer is
    incomplete"...) kept off stderr: a corrupt file is reported once, by our error."""
    import cv2

    with _c_stderr_silenced():
        return cv2.imdecode(buf, flags)


@contextlib.contextmanager
def _c_stderr_silenced() -> Iterator[None]:
    """File descriptor 2 points at /dev/null for the block (what C code writes there)."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr at all
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def max_pixels() -> int:
    """The pixel budget of one decoded image: ``PRISM3D_MAX_PIXELS`` or :data:`DEFAULT_MAX_PIXELS`."""
    text = os.environ.get("PRISM3D_MAX_PIXELS")
    if text is None:
        return DEFAULT_MAX_PIXELS
    try:
        value = int(float(text))
    except ValueError:
        raise InputError(f"PRISM3D_MAX_PIXELS: expected a number of pixels, got {text!r}") from None
    if value <= 0:
        raise InputError(f"PRISM3D_MAX_PIXELS: expected a number > 0, got {text!r}")
    return value


def check_image_size(path: Path) -> None:
    """InputError when the image's header declares more than :func:`max_pixels` pixels
    (read by Pillow without decoding; formats it does not read meet OpenCV's own limit)."""
    import warnings

    from PIL import Image

    limit = max_pixels()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                w, h = im.size
    except Image.DecompressionBombError as exc:  # Pillow's own, lower limit: its message has the count
        import re

        m = re.search(r"\((\d+) pixels\)", str(exc))
        n = int(m.group(1)) if m else None
        if n is not None and n <= limit:
            return
        declared = f"declares {pixel_count(n)}" if n is not None else "declares too many pixels"
        raise InputError(f"{path}: the image {declared}, more than the {pixel_count(limit)} limit "
                         "(--max-pixels or PRISM3D_MAX_PIXELS raises it)") from None
    except Exception:  # noqa: BLE001 - not a format Pillow reads: the decoder decides
        return
    if w * h > limit:
        raise InputError(f"{path}: {w}x{h} is {pixel_count(w * h)}, more than the {pixel_count(limit)} limit "
                         "(--max-pixels or PRISM3D_MAX_PIXELS raises it)")


def pixel_count(n: int) -> str:
    """A pixel count for a message: ``"12 MP"``, ``"1.7 MP"`` or ``"172,800 pixels"``."""
    if n >= 10_000_000:
        return f"{n / 1e6:,.0f} MP"
    return f"{n / 1e6:.1f} MP" if n >= 1_000_000 else f"{n:,} pixels"


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
            with open(path, "rb") as fh:
                check_npy_header(fh, path)
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
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
                with z.zip.open(f"{key}.npy") as member:  # the shape, before decompressing it all
                    check_npy_header(member, f"{path}:{key}")
                arr = z[key]
        elif suffix == ".pfm":
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


def check_npy_header(fh: Any, where: str | Path) -> None:
    """InputError when an ``.npy`` stream declares more elements than :func:`max_pixels`
    (a few compressed bytes can declare gigabytes)."""
    fmt = np.lib.format
    version = fmt.read_magic(fh)
    shape, _, _ = (fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0)(fh)
    n = math.prod(int(v) for v in shape)  # Python ints: a forged shape cannot overflow to small
    if n > max_pixels():
        raise InputError(f"{where}: the array declares {pixel_count(n)}, more than the {pixel_count(max_pixels())} "
                         "limit (--max-pixels or PRISM3D_MAX_PIXELS raises it)")


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
