"""Camera sources named by command-line strings: ``folder:PATH`` (files from a
tethered camera), ``opencv:INDEX_OR_URL``, ``virtual[:TARGET]`` (targets via a
``resolver``: this layer must not import :mod:`prism3d.datasets`). Frames are
``(H, W, 3) uint8`` RGB; waits are bounded; failures raise DeviceError.
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.capture.pattern import DEFAULT_COLORS, stripe_ids
from prism3d.checks import check_positive
from prism3d.errors import DeviceError, InputError

__all__ = [
    "CameraSource",
    "FolderSource",
    "OpenCVSource",
    "VirtualSource",
    "RenderFn",
    "TargetResolver",
    "open_source",
    "to_rgb8",
    "synthetic_plate_render",
    "SOURCE_FORMS",
    "IMAGE_SUFFIXES",
]

log = logging.getLogger(__name__)

#: The accepted source spellings (shown in error messages and ``--help``).
SOURCE_FORMS = ("folder:PATH", "opencv:INDEX_OR_URL", "virtual[:TARGET]")
#: File types the folder source decodes.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")

#: ``render(flash_fired, pattern_id, shot_index) -> (H, W, 3) uint8`` RGB.
RenderFn = Callable[[bool, int, int], NDArray[np.uint8]]
#: ``resolver(target_name) -> RenderFn`` (supplied by the CLI from prism3d.datasets).
TargetResolver = Callable[[str], RenderFn]


@runtime_checkable
class CameraSource(Protocol):
    """What :func:`~prism3d.capture.acquire.capture_shots` needs from a camera:
    ``open()`` once, per shot ``prepare(pattern_id)`` before the trigger and
    ``grab(timeout, flash_fired=...)`` after it, ``close()`` at the end.
    """

    spec: str

    def open(self) -> None:
        """Acquire the device (idempotent)."""

    def close(self) -> None:
        """Release the device (idempotent)."""

    def prepare(self, pattern_id: int) -> None:
        """Called just before the trigger fires (record the arm time, flush buffers)."""

    def grab(self, timeout: float, *, flash_fired: bool = False) -> NDArray[np.uint8]:
        """Return the frame of the shot just fired, ``(H, W, 3) uint8`` RGB."""

    def info(self) -> dict[str, Any]:
        """JSON-ready description for the shot's side-car file."""


def to_rgb8(image: NDArray, name: str = "image") -> NDArray[np.uint8]:
    """RGB uint8 from a frame as ``cv2.imread(..., IMREAD_UNCHANGED)`` decodes it:
    (H, W) or (H, W, 3|4) BGR(A), uint8 or uint16; DeviceError otherwise.
    """
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise DeviceError(f"{name}: expected 8- or 16-bit pixels, got {img.dtype}")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.ndim == 3 and img.shape[2] == 3:
        return np.ascontiguousarray(img[:, :, ::-1])
    if img.ndim == 3 and img.shape[2] == 4:
        return np.ascontiguousarray(img[:, :, 2::-1])
    raise DeviceError(f"{name}: expected a grey or colour image, got shape {img.shape}")


# -- folder -------------------------------------------------------------------------------


def _tail_complete(path: Path) -> bool:
    """Whether a PNG ends in its IEND chunk and a JPEG in its EOI marker: some decoder
    builds accept a truncated file (libjpeg pads it with grey), so a file caught
    mid-write must not count as a frame. Other types cannot be told.
    """
    suffix = path.suffix.lower()
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            size = fh.tell()
            fh.seek(max(0, size - 12))
            tail = fh.read()
    except OSError:
        return False
    if suffix == ".png":
        return tail[-12:-4] == b"\x00\x00\x00\x00IEND"
    if suffix in (".jpg", ".jpeg"):
        return tail.rstrip(b"\x00").endswith(b"\xff\xd9")
    return True


def _digest(path: Path) -> str:
    """Content digest of a file ("" when it cannot be read)."""
    try:
        return hashlib.blake2b(path.read_bytes(), digest_size=16).hexdigest()
    except OSError:
        return ""


class FolderSource:
    """Frames dropped into the existing folder ``path`` by a tethered camera; a file
    is complete when size and mtime hold over two polls ``poll_s`` apart, a PNG or JPEG
    ends in its end marker, and it decodes.
    """

    def __init__(self, path: str | Path, *, poll_s: float = 0.05) -> None:
        self.path = Path(path)
        self.spec = f"folder:{self.path}"
        self.poll_s = check_positive(poll_s, "poll_s")
        self._before: dict[str, tuple[int, int]] = {}
        self._t_armed_ns = 0
        self._last_file: Path | None = None
        self._delivered: dict[str, tuple[int, str]] = {}  # name -> (size, digest)

    def open(self) -> None:
        if not self.path.is_dir():
            raise DeviceError(
                f"{self.spec}: folder not found; create it or point the camera's "
                "tether/download directory there"
            )

    def close(self) -> None:
        pass

    def _snapshot(self) -> dict[str, tuple[int, int]]:
        out: dict[str, tuple[int, int]] = {}
        try:
            entries = list(os.scandir(self.path))
        except OSError as exc:
            raise DeviceError(f"{self.spec}: cannot list the folder ({exc})") from exc
        for e in entries:
            if e.name.startswith(".") or Path(e.name).suffix.lower() not in IMAGE_SUFFIXES:
                continue
            try:
                st = e.stat()
            except FileNotFoundError:
                continue
            if e.is_file():
                out[e.name] = (st.st_size, st.st_mtime_ns)
        return out

    def prepare(self, pattern_id: int = 0) -> None:
        """Remember which files exist now; only files created or changed later count."""
        self.open()
        self._before = self._snapshot()
        self._t_armed_ns = time.time_ns()

    def grab(self, timeout: float, *, flash_fired: bool = False) -> NDArray[np.uint8]:
        """Wait for a new complete image file and decode it (DeviceError after ``timeout`` s)."""
        check_positive(timeout, "timeout")
        deadline = time.monotonic() + timeout
        seen: dict[str, tuple[int, int]] = {}
        undecodable: set[str] = set()
        while True:
            now = self._snapshot()
            for name in sorted(now, key=lambda n: now[n][1]):
                sig = now[name]
                if self._before.get(name) == sig:
                    continue  # existed (unchanged) before the shot
                if self._delivered.get(name, (-1, ""))[0] == sig[0] and self._delivered[name][1] == _digest(
                    self.path / name
                ):
                    self._before[name] = sig  # touched, not rewritten: never the same frame twice
                    continue
                if sig[0] > 0 and seen.get(name) == sig:
                    if not _tail_complete(self.path / name):
                        undecodable.add(name)  # still being written, or truncated: wait
                        continue
                    img = cv2.imread(str(self.path / name), cv2.IMREAD_UNCHANGED)
                    if img is not None:
                        self._last_file = self.path / name
                        self._before[name] = sig
                        self._delivered[name] = (sig[0], _digest(self.path / name))
                        return to_rgb8(img, str(self.path / name))
                    undecodable.add(name)
            seen = now
            if time.monotonic() >= deadline:
                extra = f" ({len(undecodable)} file(s) never decoded: {sorted(undecodable)[:3]})" if undecodable else ""
                raise DeviceError(
                    f"{self.spec}: no new complete image within {timeout:g} s{extra}; "
                    "is the camera tethered and saving into this folder?"
                )
            time.sleep(self.poll_s)

    def info(self) -> dict[str, Any]:
        return {
            "spec": self.spec,
            "kind": "folder",
            "file": str(self._last_file) if self._last_file else None,
        }


# -- OpenCV ---------------------------------------------------------------------------------


class OpenCVSource:
    """``cv2.VideoCapture`` on a device index or URL/path ``target``; ``prepare``
    discards ``flush_frames`` stale buffered frames.
    """

    def __init__(self, target: int | str, *, flush_frames: int = 0) -> None:
        self.target = target
        self.spec = f"opencv:{target}"
        self.flush_frames = int(flush_frames)
        self._cap: cv2.VideoCapture | None = None
        self._lock = threading.Lock()

    def open(self) -> None:
        if self._cap is not None:
            return
        cap = cv2.VideoCapture(self.target)
        if not cap.isOpened():
            cap.release()
            raise DeviceError(
                f"{self.spec}: cannot open the camera or stream (wrong index/URL, "
                "device busy, or no permission)"
            )
        self._cap = cap

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _read(self, timeout: float) -> NDArray[np.uint8]:
        if self._cap is None:
            raise DeviceError(f"{self.spec}: not open")
        cap = self._cap
        result: list[Any] = []

        def work() -> None:
            with self._lock:
                result.append(cap.read())

        th = threading.Thread(target=work, daemon=True, name="opencv-grab")
        th.start()
        th.join(timeout)
        if th.is_alive() or not result:
            raise DeviceError(f"{self.spec}: no frame within {timeout:g} s")
        ok, frame = result[0]
        if not ok or frame is None:
            raise DeviceError(f"{self.spec}: the camera returned no frame (end of stream?)")
        return to_rgb8(frame, self.spec)

    def prepare(self, pattern_id: int = 0) -> None:
        self.open()
        for _ in range(self.flush_frames):
            self._read(1.0)

    def grab(self, timeout: float, *, flash_fired: bool = False) -> NDArray[np.uint8]:
        check_positive(timeout, "timeout")
        self.open()
        return self._read(timeout)

    def info(self) -> dict[str, Any]:
        d: dict[str, Any] = {"spec": self.spec, "kind": "opencv"}
        if self._cap is not None:
            d["backend"] = self._cap.getBackendName()
        return d


# -- virtual --------------------------------------------------------------------------------


def synthetic_plate_render(
    sensor_size: tuple[int, int] = (640, 480),
    *,
    disparity_px: float = 40.0,
    seed: int = 0,
) -> RenderFn:
    """A cheap 2-D stand-in render (no lens model, constant ``disparity_px``): a
    speckled plate in two side-by-side views, dim ambient light, and with the flash the
    De Bruijn grating (stripe period ``4 + 2 * pattern_id`` px, 0 = white); noise seeded
    per shot. Returns ``render(flash_fired, pattern_id, shot_index) -> (H, W, 3) uint8``.
    """
    w, h = (int(v) for v in sensor_size)
    if w < 16 or h < 16 or w % 2:
        raise InputError(f"sensor_size: expected an even width >= 16 and height >= 16, got {sensor_size}")
    vw = w // 2
    rng = np.random.default_rng(seed)
    coarse = rng.random((h // 8 + 2, (vw + 64) // 8 + 2)).astype(np.float32)
    speckle = cv2.resize(coarse, ((vw + 64), h), interpolation=cv2.INTER_CUBIC)
    albedo = np.clip(0.55 + 0.25 * (speckle - 0.5), 0.05, 1.0)  # (h, vw + 64)
    shift = int(round(disparity_px))

    def render(flash_fired: bool, pattern_id: int, shot_index: int) -> NDArray[np.uint8]:
        views = []
        for offset in (0, shift):
            a = albedo[:, offset : offset + vw]
            light = np.full((h, vw, 3), 0.15, np.float32)
            if flash_fired:
                if pattern_id == 0:
                    proj = np.ones((vw + 64, 3), np.float32)
                else:
                    ids = stripe_ids(vw + 64, period_px=4 + 2 * int(pattern_id), seed=int(pattern_id))
                    proj = DEFAULT_COLORS[ids].astype(np.float32) / 255.0
                light = light + 0.75 * proj[None, offset : offset + vw, :]
            views.append(a[:, :, None] * light)
        img = np.concatenate(views, axis=1) * 255.0
        noise = np.random.default_rng((seed, shot_index)).normal(0.0, 1.5, img.shape)
        return np.clip(img + noise, 0, 255).astype(np.uint8)

    return render


class VirtualSource:
    """The virtual rig as a camera: renders a shot when grabbed, with ``render`` (wins),
    else ``resolver(target)``, else the built-in plate of ``sensor_size`` and ``seed``.
    """

    def __init__(
        self,
        target: str | None = None,
        *,
        render: RenderFn | None = None,
        resolver: TargetResolver | None = None,
        sensor_size: tuple[int, int] = (640, 480),
        seed: int = 0,
    ) -> None:
        self.target = target or None
        self.spec = "virtual" + (f":{self.target}" if self.target else "")
        self._render = render
        self._resolver = resolver
        self._sensor_size = sensor_size
        self._seed = seed
        self._pattern = 0
        self._shots = 0

    def open(self) -> None:
        if self._render is not None:
            return
        if self.target is None:
            self._render = synthetic_plate_render(self._sensor_size, seed=self._seed)
            return
        if self._resolver is None:
            raise InputError(
                f"{self.spec}: no target resolver available; use 'virtual' (built-in plate) "
                "or run through the prism3d CLI, which knows the target names"
            )
        self._render = self._resolver(self.target)

    def close(self) -> None:
        pass

    def prepare(self, pattern_id: int = 0) -> None:
        self.open()
        self._pattern = int(pattern_id)

    def grab(self, timeout: float, *, flash_fired: bool = False) -> NDArray[np.uint8]:
        """Render the shot; the grating is visible only when ``flash_fired``."""
        check_positive(timeout, "timeout")
        self.open()
        render = self._render
        if render is None:  # pragma: no cover - open() sets it or raises
            raise DeviceError(f"{self.spec}: no renderer")
        img = np.asarray(render(bool(flash_fired), self._pattern, self._shots))
        self._shots += 1
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise DeviceError(
                f"{self.spec}: renderer returned {img.dtype} {img.shape}, expected (H, W, 3) uint8"
            )
        return img

    def info(self) -> dict[str, Any]:
        return {"spec": self.spec, "kind": "virtual", "target": self.target or "plate"}


# -- factory --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Spec:
    scheme: str
    rest: str


def _split_spec(spec: str) -> _Spec:
    scheme, sep, rest = str(spec).partition(":")
    return _Spec(scheme.strip().lower(), rest if sep else "")


def open_source(spec: str, *, resolver: TargetResolver | None = None) -> CameraSource:
    """Build (not yet open) a camera source from ``folder:PATH``,
    ``opencv:INDEX_OR_URL`` or ``virtual[:TARGET]`` (``resolver`` names targets);
    InputError listing the valid forms otherwise.
    """
    s = _split_spec(spec)
    forms = ", ".join(SOURCE_FORMS)
    if s.scheme == "folder":
        if not s.rest:
            raise InputError(f"camera source {spec!r}: folder needs a path; valid forms: {forms}")
        return FolderSource(s.rest)
    if s.scheme == "opencv":
        if not s.rest:
            raise InputError(f"camera source {spec!r}: opencv needs an index or URL; valid forms: {forms}")
        target: int | str = int(s.rest) if s.rest.isdigit() else s.rest
        return OpenCVSource(target)
    if s.scheme == "virtual":
        return VirtualSource(s.rest or None, resolver=resolver)
    raise InputError(f"camera source {spec!r}: unknown kind {s.scheme!r}; valid forms: {forms}")
