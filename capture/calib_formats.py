"""Read the stereo calibration files people already have into a :class:`StereoRig`.

Formats, detected from the content (:data:`SOURCE_FORMATS`): ``prism3d`` and ``opencv``
FileStorage YAML/XML (``K1 D1 K2 D2 R T``, or ``stereo_calib``'s ``intrinsics.yml`` +
``extrinsics.yml``), ``middlebury`` (2014 / ETH3D ``calib.txt``), ``kitti``
(``calib_cam_to_cam.txt`` or ``calib.txt``) and ``ros`` (``camera_info`` YAML, left +
right). Rigs are in mm (ROS and KITTI metres converted; OpenCV files taken as mm).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import CameraModel, PrismSplit, StereoRig
from prism3d.errors import InputError
from prism3d.io.opencv_yaml import read_filestorage

__all__ = [
    "StereoCalibration",
    "load_camera_calibration",
    "load_stereo_calibration",
    "convert_calibration",
    "read_opencv_calibration",
    "read_middlebury_calib",
    "read_kitti_calib",
    "read_ros_camera_info",
    "SOURCE_FORMATS",
]

#: Values of :attr:`StereoCalibration.source_format`.
SOURCE_FORMATS = ("prism3d", "opencv", "middlebury", "kitti", "ros")

_UNDERSTOOD = (
    "understood: prism3d/OpenCV FileStorage YAML or XML (K1 D1 K2 D2 R T, or M1 D1 M2 D2 "
    "+ R T), Middlebury/ETH3D calib.txt, KITTI calib_cam_to_cam.txt or calib.txt, "
    "ROS camera_info YAML (left + right)"
)

PathLike = str | os.PathLike[str]
Size = tuple[int, int]
_T = TypeVar("_T")


@dataclass(frozen=True)
class StereoCalibration:
    """A stereo calibration read from a file: the ``rig`` (views side by side unless a
    prism3d file says otherwise), its ``source_format``, the ``(min_disp, num_disp)`` the
    file states (Middlebury ``ndisp`` -> ``(0, ndisp)``) or None, Middlebury/ETH3D ``doffs``
    (``z = f * B / (d + doffs)``) or None, and ``notes`` on the conversion."""

    rig: StereoRig
    source_format: str
    disparity_range: tuple[int, int] | None = None
    doffs: float | None = None
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.rig, StereoRig):
            raise InputError(f"rig: expected a StereoRig, got {type(self.rig).__name__}")
        if self.source_format not in SOURCE_FORMATS:
            raise InputError(
                f"source_format: expected one of {', '.join(SOURCE_FORMATS)}; "
                f"got {self.source_format!r}"
            )
        if self.disparity_range is not None:
            try:
                lo, n = (int(v) for v in self.disparity_range)
            except (TypeError, ValueError) as exc:
                raise InputError(
                    f"disparity_range: expected (min_disp, num_disp), got {self.disparity_range!r}"
                ) from exc
            if n <= 0:
                raise InputError(f"disparity_range: num_disp must be > 0, got {n}")
            object.__setattr__(self, "disparity_range", (lo, n))
        if self.doffs is not None:
            object.__setattr__(self, "doffs", float(self.doffs))
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))


# -- dispatcher and conversion ---------------------------------------------------------
def load_stereo_calibration(
    paths: PathLike | Sequence[PathLike],
    *,
    image_size: Size | None = None,
    kitti_cameras: tuple[int, int] = (2, 3),
) -> StereoCalibration:
    """Read one stereo calibration given as one or two files (OpenCV intrinsics +
    extrinsics or ROS left + right, either order), whatever its format.

    ``image_size``: ``(width, height)`` of each image, required when the file states none
    and checked when it does; ``kitti_cameras``: KITTI (left, right) indices (default the
    colour pair). Raises InputError for missing, unreadable or inconsistent files.
    """
    ps = _as_paths(paths)
    kinds = [_detect(p, _read_text(p)) for p in ps]
    if len(ps) == 1:
        if kinds[0] == "filestorage":
            return read_opencv_calibration(ps, image_size=image_size)
        if kinds[0] == "middlebury":
            return read_middlebury_calib(ps[0], image_size=image_size)
        if kinds[0] == "kitti":
            return read_kitti_calib(ps[0], cameras=kitti_cameras, image_size=image_size)
        return read_ros_camera_info(ps, image_size=image_size)
    if kinds[0] == kinds[1] == "filestorage":
        return read_opencv_calibration(ps, image_size=image_size)
    if kinds[0] == kinds[1] == "ros":
        return read_ros_camera_info(ps, image_size=image_size)
    raise InputError(
        f"{ps[0]} ({kinds[0]}) and {ps[1]} ({kinds[1]}): two files must be OpenCV "
        f"intrinsics + extrinsics or ROS left + right camera_info; give other formats alone"
    )


def convert_calibration(
    paths: PathLike | Sequence[PathLike],
    out_path: PathLike,
    *,
    image_size: Size | None = None,
    kitti_cameras: tuple[int, int] = (2, 3),
) -> StereoCalibration:
    """Read a calibration (see :func:`load_stereo_calibration`) and write it as prism3d's
    FileStorage YAML at ``out_path``, atomically; nothing is written on failure.

    Besides the rig the file keeps ``converted_from``, ``disparity_range`` and ``doffs``
    when known; :func:`load_stereo_calibration` reads them back.
    """
    out = Path(out_path)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"{out}: the converted calibration must be a .yaml or .yml file")
    if out.is_dir():
        raise InputError(f"{out}: is a directory; give the output file name")
    for p in _as_paths(paths):
        same = out.exists() and p.exists() and os.path.samefile(out, p)
        if same or out.resolve() == p.resolve():
            raise InputError(f"{out}: is also the input file; choose another output path")
    cal = load_stereo_calibration(paths, image_size=image_size, kitti_cameras=kitti_cameras)
    extra: dict[str, Any] = {}
    if cal.source_format != "prism3d":
        extra["converted_from"] = cal.source_format
    if cal.disparity_range is not None:
        extra["disparity_range"] = np.array(cal.disparity_range, dtype=np.int32)
    if cal.doffs is not None:
        extra["doffs"] = float(cal.doffs)
    cal.rig.save(out, extra=extra)
    return cal


# -- OpenCV / prism3d FileStorage ------------------------------------------------------
def read_opencv_calibration(
    paths: PathLike | Sequence[PathLike], *, image_size: Size | None = None
) -> StereoCalibration:
    """Read prism3d or OpenCV FileStorage YAML/XML: ``K1 D1 K2 D2 R T`` in one file, or
    ``M1 D1 M2 D2`` + ``R T`` in one file or in two files (intrinsics, extrinsics; any order).
    """
    ps = _as_paths(paths)
    values: dict[str, Any] = {}
    owner: dict[str, Path] = {}
    for p in ps:
        if _detect(p, _read_text(p)) != "filestorage":
            raise InputError(f"{p}: not an OpenCV FileStorage file ('%YAML' or '<?xml' header)")
        for key, value in read_filestorage(p).items():
            if key in values:
                raise InputError(
                    f"{p}: entry {key!r} is also in {owner[key]}; give files that do not overlap"
                )
            values[key], owner[key] = value, p
    src = " + ".join(str(p) for p in ps)
    names = set(values)
    k1, k2 = ("K1", "K2") if {"K1", "K2"} <= names else ("M1", "M2")
    has_intrinsics = {k1, "D1", k2, "D2"} <= names
    if not (has_intrinsics and {"R", "T"} <= names):
        if has_intrinsics:
            why = f"holds intrinsics only ({k1} D1 {k2} D2); also give the extrinsics file (R T)"
        elif {"R", "T"} <= names:
            why = "holds extrinsics only (R T); also give the intrinsics file (M1 D1 M2 D2)"
        elif "camera_matrix" in names:
            why = "is a single-camera calibration (camera_matrix); need M1 D1 M2 D2 and R T"
        else:
            found = ", ".join(sorted(names)) or "nothing"
            why = f"has no stereo calibration entries (found {found}); {_UNDERSTOOD}"
        raise InputError(f"{src}: {why}")

    fmt = "prism3d" if "schema_version" in names else "opencv"
    fs = dict(values, K1=values[k1], K2=values[k2])
    size = _resolve_size(_filestorage_size(values, src), image_size, src)
    if "roi_left" not in fs or "sensor_size" not in fs:
        fs["image_size"] = size
    rig = _wrap(src, lambda: StereoRig.from_filestorage(fs, source=src))

    notes: list[str] = []
    if fmt == "opencv":
        notes.append("T taken as millimetres (OpenCV files carry no unit): the board squares "
                     "must have been given in mm")
        if rig.baseline_mm < 5.0:
            notes.append(f"baseline {rig.baseline_mm:.4g} is implausibly small for millimetres: "
                         f"calibrated in metres or board squares? rescale T")
    ignored = [k for k in ("R1", "R2", "P1", "P2", "Q") if k in names]
    if ignored:
        notes.append(f"{' '.join(ignored)} ignored: prism3d computes its own rectification")
    if "converted_from" in values:
        notes.append(f"converted by prism3d from a {values['converted_from']} calibration")
    disp = doffs = None
    if "disparity_range" in values:
        d = _floats(src, "disparity_range", values["disparity_range"], 2)
        disp = (int(d[0]), int(d[1]))
    if "doffs" in values:
        doffs = float(_floats(src, "doffs", values["doffs"], 1)[0])
    return _result(src, rig, fmt, disp, doffs, notes)


def _filestorage_size(values: dict[str, Any], src: str) -> Size | None:
    for keys in (("image_size",), ("imageSize",), ("image_width", "image_height")):
        if all(k in values for k in keys):
            a = np.concatenate([_floats(src, k, values[k], None) for k in keys])
            if a.size != 2:
                raise InputError(f"{src}: {'/'.join(keys)} must hold (width, height), "
                                 f"got {a.size} values")
            return int(round(a[0])), int(round(a[1]))
    if "roi_left" in values:
        a = _floats(src, "roi_left", values["roi_left"], 4)
        return int(a[2]), int(a[3])
    return None


def _floats(src: str, name: str, value: Any, n: int | None) -> NDArray[np.float64]:
    try:
        a = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise InputError(f"{src}: {name}: expected numbers, got {str(value)[:40]!r}") from None
    if n is not None and a.size != n:
        raise InputError(f"{src}: {name}: expected {n} values, got {a.size}")
    return a


# -- Middlebury 2014 / ETH3D -----------------------------------------------------------
_MB_KNOWN = {"cam0", "cam1", "doffs", "baseline", "width", "height", "ndisp", "isint",
             "vmin", "vmax", "dyavg", "dymax"}


def read_middlebury_calib(path: PathLike, *, image_size: Size | None = None) -> StereoCalibration:
    """Read a Middlebury 2014 / ETH3D ``calib.txt``.

    The images are already rectified: K1 = cam0, K2 = cam1, no distortion, R = I,
    T = (-baseline, 0, 0) mm. A disparity ``d`` of the images as given satisfies
    ``d = f * B / z - doffs``; ``disparity_range`` is ``(0, ndisp)``.
    """
    p = Path(path)
    entries = _key_values(p, _read_text(p), "=")
    missing = [k for k in ("cam0", "cam1", "baseline") if k not in entries]
    if missing:
        raise InputError(f"{p}: missing {', '.join(missing)}; a Middlebury/ETH3D calib.txt "
                         f"needs cam0, cam1, baseline, width, height")
    K0, K1 = (_mb_matrix(p, k, entries[k]) for k in ("cam0", "cam1"))
    baseline = _number(p, "baseline", entries["baseline"])
    if baseline <= 0:
        raise InputError(f"{p}: baseline must be > 0 (mm), got {entries['baseline']}")
    size = None
    if "width" in entries or "height" in entries:
        if not ("width" in entries and "height" in entries):
            raise InputError(f"{p}: gives only one of width and height; give both")
        size = (_integer(p, "width", entries["width"]), _integer(p, "height", entries["height"]))
    size = _resolve_size(size, image_size, p)

    notes = ["calib.txt describes rectified images: distortion zero, R = identity"]
    offset = float(K1[0, 2] - K0[0, 2])
    if "doffs" in entries:
        doffs = _number(p, "doffs", entries["doffs"])
        if abs(doffs - offset) > 1e-6 * max(1.0, abs(doffs)):
            notes.append(f"doffs {doffs:g} differs from cam1 cx - cam0 cx = {offset:g}; "
                         f"the cameras' cx are used")
    else:
        doffs = offset
        notes.append(f"no doffs entry: taken as cam1 cx - cam0 cx = {doffs:g}")
    notes.append(f"disparity of the images as given is f*B/z - doffs; after prism3d's "
                 f"rectification it is f*B/z (left view shifted by doffs = {doffs:g} px)")
    disp = (0, _integer(p, "ndisp", entries["ndisp"])) if "ndisp" in entries else None
    if "vmin" in entries and "vmax" in entries:
        vmin, vmax = _number(p, "vmin", entries["vmin"]), _number(p, "vmax", entries["vmax"])
        if disp is None:
            disp = (math.floor(vmin), math.ceil(vmax) - math.floor(vmin) + 1)
            notes.append("disparity_range from vmin/vmax (meant for colour-coding; no ndisp)")
        else:
            notes.append(f"vmin/vmax {vmin:g}/{vmax:g} are for colour-coding only (Middlebury: "
                         f"not for matching); disparity_range uses ndisp")
    if "dymax" in entries and _number(p, "dymax", entries["dymax"]) > 0:
        notes.append(f"residual vertical disparity up to {entries['dymax']} px (dymax)")
    unknown = sorted(set(entries) - _MB_KNOWN)
    if unknown:
        notes.append(f"ignored unknown entries: {', '.join(unknown)}")
    T = np.eye(4)
    T[0, 3] = -baseline
    rig = _make_rig(p, K0, np.zeros(5), K1, np.zeros(5), T, size)
    return _result(p, rig, "middlebury", disp, doffs, notes)


def _mb_matrix(p: Path, name: str, text: str) -> NDArray[np.float64]:
    body = text.strip()
    form = "'[fx 0 cx; 0 fy cy; 0 0 1]'"
    if not (body.startswith("[") and body.endswith("]")):
        raise InputError(f"{p}: {name}: expected a matrix {form}, got {text[:40]!r}")
    rows = [r.replace(",", " ").split() for r in body[1:-1].split(";")]
    if len(rows) != 3 or any(len(r) != 3 for r in rows):
        count = sum(len(r) for r in rows)
        raise InputError(f"{p}: {name}: expected a 3x3 matrix {form}, got {count} values")
    return np.array([[_number(p, name, v) for v in r] for r in rows])


# -- KITTI -----------------------------------------------------------------------------
def read_kitti_calib(
    path: PathLike, *, cameras: tuple[int, int] = (2, 3), image_size: Size | None = None
) -> StereoCalibration:
    """Read KITTI ``calib_cam_to_cam.txt`` (``P_rect_0x``, ``S_rect_0x``) or the
    odometry/object ``calib.txt`` (``P0`` .. ``P3``; it has no image size: pass ``image_size``).

    The rectified projections are used (the benchmark images are rectified): K from
    ``P[:, :3]``, no distortion, R = I, baseline from ``P[0, 3] / P[0, 0]`` (m -> mm).
    """
    p = Path(path)
    entries = _key_values(p, _read_text(p), ":")
    try:
        left, right = (int(c) for c in cameras)
    except (TypeError, ValueError) as exc:
        raise InputError(f"kitti_cameras: expected (left, right) indices, got {cameras!r}") from exc
    if not (0 <= left <= 3 and 0 <= right <= 3) or left == right:
        raise InputError(f"kitti_cameras: expected two different indices in 0..3, got {cameras!r}")
    rect = any(k.startswith("P_rect_") for k in entries)
    what = "calib_cam_to_cam.txt" if rect else "calib.txt"
    names = [f"P_rect_{i:02d}" if rect else f"P{i}" for i in (left, right)]
    P = []
    for name in names:
        if name not in entries:
            raise InputError(f"{p}: missing {name}; a KITTI {what} with cameras {left} and "
                             f"{right} needs it")
        values = [_number(p, name, v) for v in _split_values(p, name, entries[name], 12)]
        P.append(_check_projection(p, name, np.array(values).reshape(3, 4)))
    baseline = 1000.0 * (P[0][0, 3] / P[0][0, 0] - P[1][0, 3] / P[1][0, 0])
    if baseline <= 0:
        raise InputError(f"{p}: camera {right} is not to the right of camera {left} (baseline "
                         f"{baseline:.1f} mm); choose kitti_cameras=(left, right)")
    size = None
    if rect:
        sizes = []
        for i in (left, right):
            key = f"S_rect_{i:02d}"
            if key not in entries:
                raise InputError(f"{p}: missing {key}; a KITTI {what} needs the rectified size")
            sizes.append(tuple(_integer(p, key, v) for v in _split_values(p, key, entries[key], 2)))
        if sizes[0] != sizes[1]:
            raise InputError(f"{p}: S_rect_{left:02d} {sizes[0]} and S_rect_{right:02d} "
                             f"{sizes[1]} differ")
        size = sizes[0]
    size = _resolve_size(size, image_size, p)
    notes = [f"KITTI rectified projections {names[0]}/{names[1]} used (rectified images): "
             f"distortion zero, R = identity; metres converted to mm"]
    centre = [1000.0 * np.linalg.solve(Pi[:, :3], Pi[:, 3]) for Pi in P]
    dy, dz = centre[1][1:] - centre[0][1:]
    if max(abs(dy), abs(dz)) > 1.0:
        notes.append(f"the projections also differ by (dy, dz) = ({dy:.2f}, {dz:.2f}) mm off "
                     f"the baseline; ignored, as KITTI's tools do")
    T = np.eye(4)
    T[0, 3] = -baseline
    rig = _make_rig(p, P[0][:, :3], np.zeros(5), P[1][:, :3], np.zeros(5), T, size)
    return _result(p, rig, "kitti", None, None, notes)


def _check_projection(where: str | Path, name: str, P: NDArray[np.float64]) -> NDArray[np.float64]:
    if P[0, 0] <= 0 or P[1, 1] <= 0 or P[1, 0] != 0 or np.any(P[2, :3] != (0, 0, 1)):
        raise InputError(f"{where}: {name} is not a rectified projection "
                         f"[fx 0 cx tx; 0 fy cy ty; 0 0 1 tz]")
    return P


# -- one camera ------------------------------------------------------------------------
def load_camera_calibration(path: PathLike, *, image_size: Size | None = None) -> CameraModel:
    """One camera's intrinsics (a survey camera's starting calibration): OpenCV's
    calibration output (FileStorage ``camera_matrix`` ``distortion_coefficients``
    ``image_width`` ``image_height``, or ``K``/``D``), or a ROS ``camera_info`` YAML.
    ``image_size`` ``(width, height)`` is required when the file states none and
    checked when it does."""
    p = Path(path)
    text = _read_text(p)
    try:
        kind = _detect(p, text)
    except InputError:
        raise InputError(f"{p}: not a camera calibration prism3d knows; understood: OpenCV FileStorage YAML/XML "
                         "(camera_matrix, distortion_coefficients, image_width, image_height) or a ROS "
                         "camera_info YAML") from None
    if kind == "filestorage":
        doc = read_filestorage(p)
        K = next((doc[k] for k in ("camera_matrix", "K", "M", "cameraMatrix") if k in doc), None)
        D = next((doc[k] for k in ("distortion_coefficients", "D", "dist_coeffs", "distCoeffs") if k in doc),
                 np.zeros(5))
        if K is None:
            raise InputError(f"{p}: no camera_matrix (or K) entry; a single camera's calibration needs one")
        w, h = doc.get("image_width"), doc.get("image_height")
        size = None if w is None or h is None else (_integer(str(p), "image_width", w),
                                                   _integer(str(p), "image_height", h))
        where = str(p)
    elif kind == "ros":
        doc = _ros_doc(p)
        if "camera_matrix" not in doc:
            raise InputError(f"{p}: holds a stereo pair; give one camera's camera_info")
        where = str(p)
        missing = [k for k in ("image_width", "image_height") if k not in doc]
        if missing:
            raise InputError(f"{p}: missing {', '.join(missing)}")
        size = (_integer(where, "image_width", doc["image_width"]), _integer(where, "image_height", doc["image_height"]))
        K = _ros_matrix(where, doc, "camera_matrix", (3, 3))
        node = doc.get("distortion_coefficients")
        D = np.zeros(5)
        if node is not None and not (isinstance(node, dict) and node.get("data") == []):
            D = _ros_matrix(where, doc, "distortion_coefficients", None).ravel()
    else:
        raise InputError(f"{p}: a {kind} file describes a stereo pair; give one camera's OpenCV or ROS "
                         "calibration (camera_matrix, distortion_coefficients, image_width, image_height)")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise InputError(f"{where}: camera_matrix must be 3x3, got {K.shape}")
    if size is None:
        if image_size is None:
            raise InputError(f"{where}: states no image size (image_width, image_height); give the frames' size")
        size = (int(image_size[0]), int(image_size[1]))
    elif image_size is not None and tuple(int(v) for v in image_size) != size:
        raise InputError(f"{where}: calibrated for {size[0]}x{size[1]} px, the frames are "
                         f"{int(image_size[0])}x{int(image_size[1])}")
    return CameraModel(K, np.asarray(D, dtype=np.float64).ravel(), size)


# -- ROS camera_info -------------------------------------------------------------------
def read_ros_camera_info(
    paths: PathLike | Sequence[PathLike], *, image_size: Size | None = None
) -> StereoCalibration:
    """Read ROS ``camera_info`` YAML: a left and a right file (either order), or one
    file with ``left:`` and ``right:`` mappings.

    With rectifying rotations ``R_l``, ``R_r`` (``rectification_matrix``) and the
    rectified translation ``t = P_r[:, :3]^-1 P_r[:, 3]`` (metres; ``-B`` along x for a
    horizontal pair), ``R = R_r^T R_l`` and ``T = 1000 R_r^T t`` mm; the right camera
    centre in the left frame is ``R_l^T (B, 0, 0)``.
    """
    ps = _as_paths(paths)
    docs = [(p, _ros_doc(p)) for p in ps]
    if len(ps) == 1:
        p, doc = docs[0]
        if not {"left", "right"} <= set(doc):
            raise InputError(f"{p}: holds one camera; give the left and the right camera_info")
        cams = [_ros_camera(f"{p} (left)", doc["left"]), _ros_camera(f"{p} (right)", doc["right"])]
    else:
        for p, doc in docs:
            if "camera_matrix" not in doc:
                raise InputError(f"{p}: not a single camera_info file; give one left and one "
                                 f"right file")
        cams = [_ros_camera(str(p), doc) for p, doc in docs]
    src = " + ".join(str(p) for p in ps)
    notes = ["ROS translations are metres: converted to mm"]
    ref = [not np.any(np.abs(c["P"][:, 3]) > 1e-12 * c["P"][0, 0]) for c in cams]
    if ref[0] and ref[1]:
        raise InputError(f"{src}: both cameras have P[0,3] == 0 (two left cameras?); give the "
                         f"left and the right camera")
    if not (ref[0] or ref[1]):
        raise InputError(f"{src}: neither camera is the reference (left) one with P[0,3] == 0")
    if ref[1]:
        cams.reverse()
        notes.append("files given as (right, left): swapped")
    cl, cr = cams
    if cl["size"] != cr["size"]:
        raise InputError(f"{src}: image sizes differ ({cl['where']}: {cl['size']}, "
                         f"{cr['where']}: {cr['size']})")
    t = np.linalg.solve(cr["P"][:, :3], cr["P"][:, 3]) - np.linalg.solve(cl["P"][:, :3],
                                                                         cl["P"][:, 3])
    T = np.eye(4)
    T[:3, :3] = cr["R"].T @ cl["R"]
    T[:3, 3] = 1000.0 * (cr["R"].T @ t)
    size = _resolve_size(cl["size"], image_size, src)
    rig = _make_rig(src, cl["K"], cl["D"], cr["K"], cr["D"], T, size)
    return _result(src, rig, "ros", None, None, notes)


def _ros_doc(p: Path) -> dict[str, Any]:
    doc = _yaml_mapping(_read_text(p))
    if doc is None or not ("camera_matrix" in doc or {"left", "right"} <= set(doc)):
        raise InputError(f"{p}: not a ROS camera_info YAML (no camera_matrix)")
    return doc


def _ros_camera(where: str, doc: Any) -> dict[str, Any]:
    if not isinstance(doc, dict):
        raise InputError(f"{where}: expected a camera_info mapping")
    required = ("image_width", "image_height", "camera_matrix", "projection_matrix")
    missing = [k for k in required if k not in doc]
    if missing:
        raise InputError(f"{where}: missing {', '.join(missing)}")
    size = (_integer(where, "image_width", doc["image_width"]),
            _integer(where, "image_height", doc["image_height"]))
    model = str(doc.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "rational_polynomial"):
        raise InputError(f"{where}: distortion_model {model!r} is not supported "
                         f"(plumb_bob or rational_polynomial)")
    D = np.zeros(5)
    node = doc.get("distortion_coefficients")
    if node is not None and not (isinstance(node, dict) and node.get("data") == []):
        D = _ros_matrix(where, doc, "distortion_coefficients", None).ravel()
    R = np.eye(3)
    if "rectification_matrix" in doc:
        R = _ros_matrix(where, doc, "rectification_matrix", (3, 3))
    P = _ros_matrix(where, doc, "projection_matrix", (3, 4))
    return {"where": where, "size": size, "K": _ros_matrix(where, doc, "camera_matrix", (3, 3)),
            "D": D, "R": _nearest_rotation(where, R),
            "P": _check_projection(where, "projection_matrix", P)}


def _ros_matrix(
    where: str, doc: dict[str, Any], key: str, shape: tuple[int, int] | None
) -> NDArray[np.float64]:
    node = doc[key]
    if not isinstance(node, dict) or not isinstance(node.get("data"), list):
        raise InputError(f"{where}: {key}: expected a mapping with rows, cols and a data list")
    data = node["data"]
    rows, cols = (_integer(where, f"{key}.{k}", node.get(k, 0)) for k in ("rows", "cols"))
    if shape is not None and (rows, cols) != shape:
        raise InputError(f"{where}: {key}: expected {shape[0]}x{shape[1]}, got {rows}x{cols}")
    if len(data) != rows * cols:
        raise InputError(f"{where}: {key}: expected {rows * cols} values ({rows}x{cols}), "
                         f"got {len(data)}")
    return np.array([_number(where, key, v) for v in data]).reshape(rows, cols)


def _nearest_rotation(where: str, R: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation nearest ``R`` (files print a few digits); refuse non-rotations."""
    U, _, Vt = np.linalg.svd(R)
    Q = U @ Vt
    if np.linalg.det(Q) < 0 or np.max(np.abs(Q - R)) > 1e-3:
        raise InputError(f"{where}: rectification_matrix is not a rotation")
    return Q


# -- shared helpers --------------------------------------------------------------------
def _as_paths(paths: PathLike | Sequence[PathLike]) -> list[Path]:
    if isinstance(paths, str | os.PathLike):
        return [Path(paths)]
    try:
        ps = [Path(p) for p in paths]
    except TypeError as exc:
        raise InputError(f"calibration: expected one or two file paths, got {paths!r}") from exc
    if not 1 <= len(ps) <= 2:
        raise InputError(f"calibration: expected one or two files, got {len(ps)}")
    return ps


def _read_text(p: Path) -> str:
    if not p.exists():
        raise InputError(f"{p}: calibration file not found; check the path")
    if not p.is_file():
        raise InputError(f"{p}: is a directory or special file; give the calibration file")
    data = p.read_bytes()
    if not data.strip():
        raise InputError(f"{p}: file is empty; give a stereo calibration file")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not a text file (invalid UTF-8 at byte {exc.start}); "
                         f"{_UNDERSTOOD}") from exc


def _detect(p: Path, text: str) -> str:
    """'filestorage', 'middlebury', 'kitti' or 'ros', from the content."""
    head = text.lstrip()[:32]
    if head.startswith(("<?xml", "<opencv_storage", "%YAML:")) or (
        head.startswith("%YAML") and "!!opencv-matrix" in text  # OpenCV 5 writes '%YAML 1.2'
    ):
        return "filestorage"
    if re.search(r"^\s*cam0\s*=", text, re.M):
        return "middlebury"
    if re.search(r"^\s*(P_rect_0\d|P[0-3])\s*:", text, re.M):
        return "kitti"
    doc = _yaml_mapping(text)
    if doc is not None and ("camera_matrix" in doc or {"left", "right"} <= set(doc)):
        return "ros"
    if head.startswith("%YAML"):
        return "filestorage"
    raise InputError(f"{p}: not a stereo calibration format prism3d knows; {_UNDERSTOOD}")


def _yaml_mapping(text: str) -> dict[str, Any] | None:
    import yaml

    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    return doc if isinstance(doc, dict) else None


def _key_values(p: Path, text: str, sep: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        key, found, value = s.partition(sep)
        key = key.strip()
        if not found or not key:
            raise InputError(f"{p}: line {lineno}: expected 'name{sep}value', got {s[:40]!r}")
        if key in out:
            raise InputError(f"{p}: line {lineno}: {key} is given twice")
        out[key] = value.strip()
    return out


def _split_values(p: Path, name: str, text: str, n: int) -> list[str]:
    vals = text.split()
    if len(vals) != n:
        raise InputError(f"{p}: {name}: expected {n} values, got {len(vals)}")
    return vals


def _number(where: str | Path, name: str, value: Any) -> float:
    try:
        if isinstance(value, bool):
            raise ValueError
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {name}: expected a number, got {str(value)[:40]!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: {name}: expected a finite number, got {value!r}")
    return v


def _integer(where: str | Path, name: str, value: Any) -> int:
    v = _number(where, name, value)
    if v != round(v) or v <= 0:
        raise InputError(f"{where}: {name}: expected a positive integer, got {value!r}")
    return int(round(v))


def _resolve_size(file_size: Size | None, image_size: Size | None, where: str | Path) -> Size:
    """The file's image size, else ``image_size``; both given must agree."""
    if image_size is None:
        if file_size is None:
            raise InputError(f"{where}: the file does not state the image size; pass it "
                             f"(image_size=(width, height), or --image-size WxH)")
        return file_size
    try:
        w, h = (int(v) for v in image_size)
    except (TypeError, ValueError) as exc:
        raise InputError(f"image_size: expected (width, height), got {image_size!r}") from exc
    if w <= 0 or h <= 0:
        raise InputError(f"image_size: width and height must be > 0, got {(w, h)}")
    if file_size is not None and tuple(file_size) != (w, h):
        raise InputError(f"{where}: the file gives {file_size[0]}x{file_size[1]} images but "
                         f"image_size is {w}x{h}; drop or fix image_size")
    return w, h


def _wrap(where: str | Path, build: Callable[[], _T]) -> _T:
    """Call ``build()``; put the file name in front of an InputError that lacks it."""
    try:
        return build()
    except InputError as exc:
        if str(exc).startswith(str(where)):
            raise
        raise InputError(f"{where}: {exc}") from exc


def _make_rig(where: str | Path, K1: NDArray, D1: NDArray, K2: NDArray, D2: NDArray,
              T: NDArray, size: Size) -> StereoRig:
    def build() -> StereoRig:
        split = PrismSplit.side_by_side((2 * size[0], size[1]))
        return StereoRig(CameraModel(K1, D1, size), CameraModel(K2, D2, size), T, split)

    return _wrap(where, build)


def _result(where: str | Path, rig: StereoRig, fmt: str, disp: tuple[int, int] | None,
            doffs: float | None, notes: list[str]) -> StereoCalibration:
    return _wrap(where, lambda: StereoCalibration(rig, fmt, disp, doffs, tuple(notes)))
