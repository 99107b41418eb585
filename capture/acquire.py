"""One-shot (or sequence) capture: arm, fire, grab, check, save atomically.

Each shot is ``shot_NNN.png`` (the full sensor image, RGB) plus a side-car
``shot_NNN.json`` (schema below). Both files appear together or not at all: they are
written to temporary files and moved into place only after every check passed; the
JSON is moved last, so a PNG with its JSON is a complete shot.

Side-car schema (``schema_version`` 1)::

    {"schema_version": 1, "index": 0, "time_utc": "2024-...Z",
     "pattern_id": 1, "flash": true,
     "timing": {"shutter_us": 8000, "flash_us": 2000, "flash_delay_us": 500},
     "trigger": {"port": "/dev/pts/5", "device": {...ID...}, "shot": 1,
                 "t_shutter_us": ..., "t_flash_us": ..., "flash_fired": true},
     "source": {...CameraSource.info()...},
     "image": {"width": W, "height": H, "mean": .., "saturated_fraction": ..,
               "pattern_fraction": ..}}
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable
from dataclasses import asdict
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
from prism3d.checks import check_positive
from prism3d.errors import DeviceError, InputError
from prism3d.io.atomic import atomic_path

__all__ = ["capture_shots", "check_frame", "SHOT_SCHEMA_VERSION"]

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
    """Check a captured frame; return its statistics.

    Parameters
    ----------
    image : (H, W, 3) uint8
        RGB frame.
    expected_size : (int, int), optional
        Sensor ``(width, height)`` from the calibration.
    pattern_visible : bool
        Require the colour grating to be visible (flash fired with a pattern):
        at least :data:`PATTERN_MIN_FRACTION` of the pixels must have a chroma
        ``max(R, G, B) - min(R, G, B) >= PATTERN_CHROMA``.
    source : str
        Name used in messages.

    Returns
    -------
    dict
        ``width, height, mean, saturated_fraction, pattern_fraction``.

    Raises
    ------
    InputError
        Wrong size for the calibration.
    DeviceError
        Black frame, saturated frame, or no grating although the flash fired.
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


def capture_shots(
    trigger_port: str,
    source: str | CameraSource,
    out_dir: str | Path,
    *,
    count: int = 1,
    interval_s: float = 0.0,
    pattern_id: int = 1,
    flash: bool = True,
    expected_size: tuple[int, int] | None = None,
    progress: Callable[[int, int], object] | None = None,
    shutter_us: int = DEFAULT_SHUTTER_US,
    flash_us: int = DEFAULT_FLASH_US,
    flash_delay_us: int = DEFAULT_FLASH_DELAY_US,
    trigger_timeout: float = 1.0,
    grab_timeout: float = 5.0,
    resolver: TargetResolver | None = None,
) -> list[Path]:
    """Capture ``count`` shots: arm, fire, grab, check, save ``shot_NNN.png/.json``.

    Parameters
    ----------
    trigger_port : str
        Trigger controller port or pyserial URL.
    source : str or CameraSource
        ``folder:PATH``, ``opencv:INDEX_OR_URL``, ``virtual[:TARGET]`` or a source
        object (opened here, closed by its owner).
    out_dir : path
        Output folder (created). Numbering continues after existing shots.
    count : int
        Number of shots (``--count``; a UAV sequence).
    interval_s : float
        Time between shot starts (``--interval``); 0 = as fast as possible.
    pattern_id : int
        Grating pattern (0 = plain white flash, 1..15).
    flash : bool
        Fire the flash (False: ambient exposure only; no grating check).
    expected_size : (int, int), optional
        Sensor ``(width, height)`` of the calibration (``StereoRig.split.sensor_size``).
    progress : callable, optional
        ``progress(done, count)`` after each saved shot.
    shutter_us, flash_us, flash_delay_us : int
        Exposure timing sent with ``FIRE``.
    trigger_timeout : float
        Per-try reply timeout of the trigger (seconds).
    grab_timeout : float
        Time allowed for the camera to deliver each frame (seconds).
    resolver : TargetResolver, optional
        Virtual target resolver (CLI-supplied).

    Returns
    -------
    list of Path
        The PNG paths, in order.

    Raises
    ------
    InputError
        Bad arguments, unknown source, frame size not matching ``expected_size``.
    DeviceError
        Trigger or camera failure, black/saturated frame, missing grating. Shots
        saved before the failure stay; the failing shot leaves no file.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise InputError(f"count: expected an integer >= 1, got {count!r}")
    interval = check_positive(interval_s, "interval_s", strict=False)
    check_positive(grab_timeout, "grab_timeout")
    if isinstance(pattern_id, bool) or not isinstance(pattern_id, int) or not 0 <= pattern_id <= 15:
        raise InputError(f"pattern_id: expected an integer in [0, 15], got {pattern_id!r}")
    if expected_size is not None:
        if len(tuple(expected_size)) != 2 or min(int(v) for v in expected_size) <= 0:
            raise InputError(f"expected_size: expected (width, height) > 0, got {expected_size!r}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: output path exists and is not a folder")
    cam: CameraSource = open_source(source, resolver=resolver) if isinstance(source, str) else source
    owns_source = isinstance(source, str)
    fl_us = flash_us if flash else 0
    fl_delay = flash_delay_us if flash else 0
    saved: list[Path] = []
    cam.open()
    try:
        with TriggerClient(trigger_port, timeout=trigger_timeout) as trig:
            device = asdict(trig.identify())
            out.mkdir(parents=True, exist_ok=True)
            first = _next_index(out)
            t_start = time.monotonic()
            for k in range(count):
                wait = t_start + k * interval - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                index = first + k
                cam.prepare(pattern_id)
                trig.arm(pattern_id)
                t_iso = datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
                report = trig.fire(flash_delay_us=fl_delay, flash_us=fl_us, shutter_us=shutter_us)
                image = cam.grab(grab_timeout, flash_fired=report.flash_fired)
                stats = check_frame(
                    image,
                    expected_size=expected_size,
                    pattern_visible=report.flash_fired and pattern_id != 0,
                    source=cam.spec,
                )
                meta = {
                    "schema_version": SHOT_SCHEMA_VERSION,
                    "index": index,
                    "time_utc": t_iso,
                    "pattern_id": pattern_id,
                    "flash": report.flash_fired,
                    "timing": {"shutter_us": shutter_us, "flash_us": fl_us,
                               "flash_delay_us": fl_delay},
                    "trigger": {"port": trigger_port, "device": device, **report.to_dict()},
                    "source": cam.info(),
                    "image": stats,
                }
                png = out / f"shot_{index:03d}.png"
                _write_shot(png, png.with_suffix(".json"), image, meta)
                saved.append(png)
                log.info("saved %s", png)
                if progress is not None:
                    progress(k + 1, count)
    finally:
        if owns_source:
            cam.close()
    return saved
