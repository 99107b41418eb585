"""What a survey starts from: the frames (or a video's), their GPS positions (a table or
EXIF) and the starting camera (a calibration file, else EXIF).
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.capture.calib_formats import load_camera_calibration
from prism3d.capture.geotag import exif_focal_px, exif_geotag, read_position_table
from prism3d.capture.rig import CameraModel
from prism3d.errors import InputError
from prism3d.io.images import check_image_size, read_image

__all__ = ["VIDEO_SUFFIXES", "check_frames", "gps_positions", "load_frame", "starting_camera", "video_frames"]


def _image_sizes(paths: Sequence[Path]) -> list[tuple[int, int]]:
    from PIL import Image, UnidentifiedImageError

    sizes = []
    for p in paths:
        if p.is_dir():
            raise InputError(f"{p}: is a folder; give the frames themselves (e.g. {p}/*.JPG)")
        if not p.is_file():
            raise InputError(f"{p}: image not found")
        check_image_size(p)  # a header declaring more than the decode budget is refused here
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(p) as im:
                    sizes.append(im.size)
        except Image.DecompressionBombError as exc:  # within our budget, beyond Pillow's own limit
            n = re.search(r"\((\d+) pixels\)", str(exc))
            raise InputError(f"{p}: the image declares {n.group(1) if n else 'too many'} pixels; "
                             "Pillow will not open it") from None
        except (UnidentifiedImageError, OSError) as exc:
            raise InputError(f"{p}: not an image this tool can read ({exc})") from None
    return sizes


#: Inputs read as videos (frames taken every ``video_step_s``).
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v")


def video_frames(video: str | Path, folder: Path, *, step_s: float = 1.0, max_frames: int = 500) -> list[Path]:
    """Frames of a video every ``step_s`` seconds (by its frame rate; every frame when it
    states none) written as JPEGs into ``folder``: the survey's frames. A video without
    two readable frames is refused."""
    v = Path(video)
    if not v.is_file():
        raise InputError(f"{v}: video not found")
    if not (math.isfinite(step_s) and step_s > 0):
        raise InputError(f"video step: expected seconds > 0, got {step_s}")
    cap = cv2.VideoCapture(str(v))
    try:
        if not cap.isOpened():
            raise InputError(f"{v}: cannot open as a video (unknown container or codec)")
        fps = cap.get(cv2.CAP_PROP_FPS)
        every = max(1, int(round(step_s * fps))) if fps and math.isfinite(fps) and fps > 0 else 1
        folder.mkdir(parents=True, exist_ok=True)
        out, k = [], 0
        while len(out) < max_frames:
            ok, img = cap.read()
            if not ok:
                break
            if k % every == 0:
                p = folder / f"{v.stem}_{k:06d}.jpg"
                if not cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 95]):
                    raise InputError(f"{p}: cannot write the frame")
                out.append(p)
            k += 1
    finally:
        cap.release()
    if len(out) < 2:
        raise InputError(f"{v}: {len(out)} frame(s) read every {step_s:g} s; a survey needs at least 2")
    return out


def check_frames(images: Sequence[str | Path]) -> tuple[list[Path], tuple[int, int]]:
    """The frames as paths and their common (width, height); one-line errors for fewer
    than two frames, a missing or unreadable one, a repeated one, or different sizes."""
    paths = [Path(p) for p in images]
    for p in paths:
        if p.is_dir():
            raise InputError(f"{p}: is a folder; give the frames themselves (e.g. {p}/*.JPG)")
    if len(paths) < 2:
        raise InputError(f"survey: {len(paths)} frame(s) given; a survey needs at least 2 overlapping frames")
    names = [p.name for p in paths]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"survey: frames named {', '.join(dup[:3])} more than once; names identify frames")
    sizes = _image_sizes(paths)
    for p, s in zip(paths[1:], sizes[1:]):
        if s != sizes[0]:
            raise InputError(f"survey: frames of different sizes: {paths[0].name} is {sizes[0][0]}x{sizes[0][1]}, "
                             f"{p.name} is {s[0]}x{s[1]}; one camera at one setting is needed")
    return paths, sizes[0]


def gps_positions(paths: Sequence[Path], gps_table: str | Path | None) -> tuple[list[Any] | None, str]:
    """GeoTags per frame from a position table (every frame must be in it, and every
    image the table names must exist), else from EXIF when every frame has it."""
    if gps_table is not None:
        folders = {p.resolve().parent for p in paths}
        table = read_position_table(gps_table, images_dir=folders.pop() if len(folders) == 1 else None)
        if len({p.parent for p in paths}) > 1:
            given = {p.name for p in paths}
            absent = [n for n in table if n not in given]
            if absent:
                raise InputError(f"{gps_table}: names {len(absent)} image(s) not among the frames: "
                                 f"{', '.join(absent[:5])}")
        missing = [p.name for p in paths if p.name not in table]
        if missing:
            raise InputError(f"{gps_table}: no position for {', '.join(missing[:5])}"
                             + (" ..." if len(missing) > 5 else ""))
        return [table[p.name] for p in paths], f"table {Path(gps_table).name}"
    tags = [exif_geotag(p) for p in paths]
    if all(t is not None for t in tags):
        return tags, "EXIF"
    return None, "none"


def starting_camera(paths: Sequence[Path], size: tuple[int, int], calib: str | Path | None):
    """The starting calibration: a camera YAML, else the EXIF focal length."""
    if calib is not None:
        return load_camera_calibration(calib, image_size=size), "calibration file"
    f = exif_focal_px(paths[0])
    if f is None:
        raise InputError("survey: no starting calibration: give --calib or frames whose EXIF has the focal "
                         "length and focal-plane resolution")
    w, h = size
    K = np.array([[f, 0, (w - 1) / 2.0], [0, f, (h - 1) / 2.0], [0, 0, 1.0]])
    return CameraModel(K, np.zeros(5), size), "EXIF focal length"


def load_frame(path: str, K: NDArray, dist: NDArray, factor: int) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """A frame undistorted onto ``K`` and area-downscaled by ``factor``: the image and its K
    (what dense matching sees, and what the dense cloud takes its colours from)."""
    img = read_image(path)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = np.ascontiguousarray(img[..., :3])
    if np.any(np.asarray(dist) != 0):
        img = cv2.undistort(img, K, np.asarray(dist, dtype=np.float64))
    Ks = np.asarray(K, dtype=np.float64).copy()
    if factor > 1:
        h, w = img.shape[:2]
        img = cv2.resize(img, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
        Ks[:2] /= factor
        Ks[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
        Ks[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return img, Ks
