"""One-shot (or sequence) capture: arm, fire, grab, check, save ``shot_NNN.png`` +
``shot_NNN.json`` atomically, the JSON last (side-car schema: docs/capture.md).
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.capture.sources import CameraSource, TargetResolver, open_source
from prism3d.capture.trigger import (
    DEFAULT_FLASH_DELAY_US,
    DEFAULT_FLASH_US,
    DEFAULT_SHUTTER_US,
    TriggerClient,
)
from prism3d.checks import check_in_range, check_positive
from prism3d.errors import DeviceError, InputError
from prism3d.io.atomic import atomic_path

__all__ = ["CaptureOptions", "capture_shots", "check_frame", "SHOT_SCHEMA_VERSION"]

log = logging.getLogger(__name__)

#: Version of the ``shot_NNN.json`` side-car layout.
SHOT_SCHEMA_VERSION = 1

#: Frame checks (8-bit levels and fractions of pixels).
BLACK_MEAN = 8.0
SATURATED_LEVEL = 250
SATURATED_MAX_FRACTION = 0.5
PATTERN_CHROMA = 40
PATTERN_MIN_FRACTION = 0.05

_SHOT_RE = re.compile(r"^shot_(\d{3,})\.(png|json)$")


def check_frame(
    image: NDArray,
    *,
    expected_size: tuple[int, int] | None = None,
    pattern_visible: bool = False,
    source: str = "camera",
) -> dict[str, float]:
    """Check a captured ``(H, W, 3) uint8`` RGB frame; return ``width, height, mean,
    saturated_fraction, pattern_fraction``.

    ``expected_size`` is the calibration's sensor ``(width, height)`` (InputError when
    it differs); DeviceError for a black or saturated frame, or, with
    ``pattern_visible``, fewer than :data:`PATTERN_MIN_FRACTION` pixels of chroma
    >= :data:`PATTERN_CHROMA` (no grating). ``source`` names the camera in messages.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise DeviceError(f"{source}: expected an (H, W, 3) uint8 frame, got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    if expected_size is not None and (w, h) != tuple(int(v) for v in expected_size):
        ew, eh = expected_size
        raise InputError(
            f"{source}: frame is {w}x{h} but the calibration expects a {ew}x{eh} sensor; "
            "wrong camera, resolution setting or calibration file"
        )
    mx = img.max(axis=2)
    mean = float(img.mean())
    sat = float(np.mean(mx >= SATURATED_LEVEL))
    chroma = mx.astype(np.int16) - img.min(axis=2)
    pattern = float(np.mean(chroma >= PATTERN_CHROMA))
    stats = {"width": w, "height": h, "mean": round(mean, 3),
             "saturated_fraction": round(sat, 5), "pattern_fraction": round(pattern, 5)}
    if mean < BLACK_MEAN:
        raise DeviceError(
            f"{source}: frame is black (mean level {mean:.1f}/255); lens cap, exposure too "
            "short, or the trigger is not wired to the camera"
        )
    if sat > SATURATED_MAX_FRACTION:
        raise DeviceError(
            f"{source}: frame is saturated ({100 * sat:.0f}% of pixels >= {SATURATED_LEVEL}); "
            "shorten the exposure or reduce the flash power"
        )
    if pattern_visible and pattern < PATTERN_MIN_FRACTION:
        raise DeviceError(
            f"{source}: the flash fired but no colour grating is visible "
            f"({100 * pattern:.1f}% coloured pixels, need >= {100 * PATTERN_MIN_FRACTION:.0f}%); "
            "check the projector, its sync cable and that it points at the scene"
        )
    return stats


def _next_index(out_dir: Path) -> int:
    used = [int(m.group(1)) for p in out_dir.iterdir() if (m := _SHOT_RE.match(p.name))]
    return max(used) + 1 if used else 0


def _write_shot(png: Path, side: Path, image: NDArray[np.uint8], meta: dict[str, Any]) -> None:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[:, :, ::-1]))
    if not ok:
        raise DeviceError(f"{png}: PNG encoding failed")
    text = json.dumps(meta, indent=2, sort_keys=False) + "\n"
    # JSON moves into place last: a shot is complete when its JSON exists.
    with atomic_path(side) as tmp_json, atomic_path(png) as tmp_png:
        tmp_png.write_bytes(buf.tobytes())
        tmp_json.write_text(text, encoding="utf-8")


@dataclass(frozen=True)
class CaptureOptions:
    """How :func:`capture_shots` fires and checks each shot (``prism3d capture`` flags)."""

    count: int = 1
    """Number of shots (``--count``; a UAV sequence)."""
    interval_s: float = 0.0
    """Time between shot starts, s (``--interval``); 0 = as fast as possible."""
    pattern_id: int = 1
    """Grating pattern, 0 = plain white flash, 1..15."""
    flash: bool = True
    """Fire the flash; False = ambient exposure only, no grating check."""
    expected_size: tuple[int, int] | None = None
    """Sensor ``(width, height)`` of the calibration (``StereoRig.split.sensor_size``)."""
    shutter_us: int = DEFAULT_SHUTTER_US
    """Shutter time sent with ``FIRE``, us."""
    flash_us: int = DEFAULT_FLASH_US
    """Flash duration sent with ``FIRE``, us."""
    flash_delay_us: int = DEFAULT_FLASH_DELAY_US
    """Flash delay after the shutter opens, us."""
    trigger_timeout: float = 1.0
    """Per-try reply timeout of the trigger, s."""
    grab_timeout: float = 5.0
    """Time allowed for the camera to deliver each frame, s."""

    def __post_init__(self) -> None:
        c = self.count
        if isinstance(c, bool) or not isinstance(c, int) or c < 1:
            raise InputError(f"count: expected an integer >= 1, got {c!r}")
        object.__setattr__(self, "interval_s", check_positive(self.interval_s, "interval_s", strict=False))
        check_in_range(check_positive(self.grab_timeout, "grab_timeout"), "grab_timeout", 0.0, 3600.0)
        p = self.pattern_id
        if isinstance(p, bool) or not isinstance(p, int) or not 0 <= p <= 15:
            raise InputError(f"pattern_id: expected an integer in [0, 15], got {p!r}")
        e = self.expected_size
        if e is not None and (len(tuple(e)) != 2 or min(int(v) for v in e) <= 0):
            raise InputError(f"expected_size: expected (width, height) > 0, got {e!r}")

    @property
    def timing(self) -> dict[str, int]:
        """``shutter_us``, ``flash_us``, ``flash_delay_us`` as sent (flash ones 0 without flash)."""
        return {"shutter_us": self.shutter_us, "flash_us": self.flash_us if self.flash else 0,
                "flash_delay_us": self.flash_delay_us if self.flash else 0}


def capture_shots(
    trigger_port: str,
    source: str | CameraSource,
    out_dir: str | Path,
    options: CaptureOptions | None = None,
    *,
    progress: Callable[[int, int], object] | None = None,
    resolver: TargetResolver | None = None,
) -> list[Path]:
    """Capture shots: arm, fire, grab, check, save ``shot_NNN.png/.json``.

    ``trigger_port``: port or pyserial URL; ``source``: ``folder:PATH``,
    ``opencv:INDEX_OR_URL``, ``virtual[:TARGET]`` or a source object (opened here,
    closed by its owner); ``out_dir``: created, numbering continues after existing
    shots; ``options``: None = ``CaptureOptions()``; ``progress(done, count)`` after
    each saved shot; ``resolver`` names virtual targets. Returns the PNG paths in order.
    InputError for bad arguments or a wrong frame size; DeviceError for trigger or
    camera failures and bad frames (earlier shots stay, the failing one leaves no file).
    """
    opts = CaptureOptions() if options is None else options
    if not isinstance(opts, CaptureOptions):
        raise InputError(f"options: expected a CaptureOptions or None, got {type(opts).__name__}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: output path exists and is not a folder")
    cam: CameraSource = open_source(source, resolver=resolver) if isinstance(source, str) else source
    owns_source = isinstance(source, str)
    saved: list[Path] = []
    created = not out.exists()
    cam.open()
    try:
        with TriggerClient(trigger_port, timeout=opts.trigger_timeout) as trig:
            device = asdict(trig.identify())
            first = _next_index(out) if out.is_dir() else 0  # the folder appears with the first shot
            t_start = time.monotonic()
            for k in range(opts.count):
                wait = t_start + k * opts.interval_s - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                png = _capture_one(trig, cam, out, first + k, opts, {"port": trigger_port, "device": device})
                saved.append(png)
                log.info("saved %s", png)
                if progress is not None:
                    progress(k + 1, opts.count)
    except BaseException:
        # shots taken stay (each is whole); a run that saved none leaves no empty folder
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    finally:
        if owns_source:
            cam.close()
    return saved


def _capture_one(
    trig: TriggerClient,
    cam: CameraSource,
    out: Path,
    index: int,
    opts: CaptureOptions,
    trigger: dict[str, Any],
) -> Path:
    """One shot: prepare, arm, fire, grab, check, then write the PNG and its side-car."""
    timing = opts.timing
    cam.prepare(opts.pattern_id)
    trig.arm(opts.pattern_id)
    t_iso = datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    report = trig.fire(flash_delay_us=timing["flash_delay_us"], flash_us=timing["flash_us"],
                       shutter_us=timing["shutter_us"])
    image = cam.grab(opts.grab_timeout, flash_fired=report.flash_fired)
    stats = check_frame(
        image,
        expected_size=opts.expected_size,
        pattern_visible=report.flash_fired and opts.pattern_id != 0,
        source=cam.spec,
    )
    meta = {
        "schema_version": SHOT_SCHEMA_VERSION,
        "index": index,
        "time_utc": t_iso,
        "pattern_id": opts.pattern_id,
        "flash": report.flash_fired,
        "timing": timing,
        "trigger": {**trigger, **report.to_dict()},
        "source": cam.info(),
        "image": stats,
    }
    png = out / f"shot_{index:03d}.png"
    out.mkdir(parents=True, exist_ok=True)
    _write_shot(png, png.with_suffix(".json"), image, meta)
    return png
