"""Viewing poses for training and test chips: grids, view-sphere samplings, tables.

An OpenCV camera (x right, y down, z forward) on a sphere around the target's
bounding-box centre, object frame x forward, y left, z up (mm): ``az_deg`` from +x,
counter-clockwise from above; ``el_deg`` above the x-y plane; ``range_mm`` from the
centre; ``roll_deg`` about the optical axis (positive turns the scene clockwise).
Details: docs/atr.md "Viewing poses".
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError

__all__ = [
    "POSE_COLUMNS",
    "ChipPose",
    "camera_T_obj_cam",
    "directions_to_az_el",
    "fibonacci_directions",
    "grid_directions",
    "icosphere_directions",
    "make_poses",
    "parse_range",
    "poses_table",
]

#: Columns of :func:`poses_table` (then ``T_cam_obj_00`` ... ``T_cam_obj_33``).
POSE_COLUMNS = ("az_deg", "el_deg", "range_mm", "roll_deg", "fx", "fy", "cx", "cy")


@dataclass(frozen=True)
class ChipPose:
    """One chip's viewpoint and camera: ``az_deg``, ``el_deg`` (degrees, module
    docstring), ``range_mm`` (> 0), ``roll_deg``, pinhole ``K`` (3, 3) and ``T_cam_obj``
    (4, 4), object -> OpenCV camera frame.
    """

    az_deg: float
    el_deg: float
    range_mm: float
    roll_deg: float
    K: NDArray[np.float64]
    T_cam_obj: NDArray[np.float64]

    def __post_init__(self) -> None:
        K = check_array(self.K, "K", shape=(3, 3), dtype_kind="fiu").astype(np.float64)
        T = check_array(self.T_cam_obj, "T_cam_obj", shape=(4, 4), dtype_kind="fiu").astype(
            np.float64
        )
        if not (math.isfinite(self.range_mm) and self.range_mm > 0):
            raise InputError(f"range_mm: expected a positive finite distance, got {self.range_mm}")
        K.setflags(write=False)
        T.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_cam_obj", T)

    @property
    def T_obj_cam(self) -> NDArray[np.float64]:
        """Camera pose in the object frame (``T_world_cam`` for a renderer whose world
        is the object frame)."""
        return np.linalg.inv(self.T_cam_obj)

    def row(self) -> dict[str, float]:
        """The pose as one flat table row (:data:`POSE_COLUMNS` + 16 ``T_cam_obj_ij``)."""
        r = {
            "az_deg": float(self.az_deg),
            "el_deg": float(self.el_deg),
            "range_mm": float(self.range_mm),
            "roll_deg": float(self.roll_deg),
            "fx": float(self.K[0, 0]),
            "fy": float(self.K[1, 1]),
            "cx": float(self.K[0, 2]),
            "cy": float(self.K[1, 2]),
        }
        for i in range(4):
            for j in range(4):
                r[f"T_cam_obj_{i}{j}"] = float(self.T_cam_obj[i, j])
        return r

    @classmethod
    def from_row(cls, row: dict) -> ChipPose:
        """Inverse of :meth:`row` (a dict or a pandas row)."""
        try:
            K = np.array(
                [[row["fx"], 0.0, row["cx"]], [0.0, row["fy"], row["cy"]], [0.0, 0.0, 1.0]]
            )
            T = np.array(
                [[row[f"T_cam_obj_{i}{j}"] for j in range(4)] for i in range(4)], dtype=np.float64
            )
            return cls(
                float(row["az_deg"]),
                float(row["el_deg"]),
                float(row["range_mm"]),
                float(row["roll_deg"]),
                K,
                T,
            )
        except KeyError as exc:
            raise InputError(f"pose row: missing column {exc.args[0]!r}") from None


#: Most values a range spec may give (a typo such as ``0:360:1e-7`` would be billions of poses).
MAX_RANGE_VALUES = 100_000


def parse_range(spec: str | float | Sequence[float]) -> list[float]:
    """Parse ``"A0:A1:STEP"``, ``"v1,v2,..."`` or numbers into a list of floats.

    ``"A0:A1:STEP"`` is end-exclusive (``"0:360:10"`` stops at 350), but includes an end
    reached exactly that is not a full turn (``"10:60:25"`` -> 10, 35, 60).
    """
    if isinstance(spec, (int, float, np.integer, np.floating)) and not isinstance(spec, bool):
        return _finite([float(spec)], spec)
    if not isinstance(spec, str):
        try:
            vals = [float(v) for v in spec]
        except (TypeError, ValueError):
            raise InputError(
                f"range spec: expected 'A0:A1:STEP', 'v1,v2' or numbers, got {spec!r}"
            ) from None
        if not vals:
            raise InputError("range spec: empty list")
        return _finite(vals, spec)
    text = spec.strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3:
                raise ValueError
            a0, a1, step = parts
            if not step > 0:
                raise InputError(f"range spec {spec!r}: STEP must be > 0, got {step}")
            _finite(parts, spec)
            n = math.floor((a1 - a0) / step + 1e-9)
            if n > MAX_RANGE_VALUES:  # n + 1 values before a full turn's end is dropped
                raise InputError(f"range spec {spec!r}: {n + 1} values, more than {MAX_RANGE_VALUES}; "
                                 "use a larger STEP")
            vals = [a0 + i * step for i in range(max(n, 0) + 1)]
            if vals and (
                vals[-1] > a1 + 1e-9
                or (abs(vals[-1] - a1) < 1e-9 and abs((a1 - a0) - 360.0) < 1e-9)
            ):
                vals = vals[:-1]
            if len(vals) > MAX_RANGE_VALUES:
                raise InputError(f"range spec {spec!r}: {len(vals)} values, more than {MAX_RANGE_VALUES}; "
                                 "use a larger STEP")
        else:
            vals = [float(p) for p in text.split(",") if p.strip()]
    except InputError:
        raise
    except ValueError:
        raise InputError(
            f"range spec: expected 'A0:A1:STEP' or 'v1,v2,...', got {spec!r}"
        ) from None
    if not vals:
        raise InputError(f"range spec {spec!r}: no values")
    return [round(v, 9) for v in _finite(vals, spec)]


def _finite(vals: list[float], spec: Any) -> list[float]:
    if not all(math.isfinite(v) for v in vals):
        raise InputError(f"range spec {spec!r}: values must be finite numbers")
    return vals


def grid_directions(
    azimuths_deg: Iterable[float], elevations_deg: Iterable[float]
) -> NDArray[np.float64]:
    """``(N, 2)`` (az, el) degrees of a full grid, elevation-major then azimuth."""
    az = [float(a) for a in azimuths_deg]
    el = [float(e) for e in elevations_deg]
    if not az or not el:
        raise InputError("grid_directions: need at least one azimuth and one elevation")
    return np.array([(a, e) for e in el for a in az], dtype=np.float64).reshape(-1, 2)


def directions_to_az_el(dirs: NDArray) -> NDArray[np.float64]:
    """Unit vectors ``(N, 3)`` (object frame, centre -> camera) to ``(N, 2)`` (az, el) deg,
    azimuth in [0, 360)."""
    d = check_array(dirs, "dirs", shape=(None, 3), dtype_kind="f")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    az = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0
    el = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
    return np.stack([az, el], axis=1)


def fibonacci_directions(
    n: int, *, min_el_deg: float = -90.0, max_el_deg: float = 90.0
) -> NDArray[np.float64]:
    """Near-uniform ``(n, 2)`` (az, el) degrees on the golden-angle spiral, equally
    spaced in ``sin(el)`` (Gonzalez, Mathematical Geosciences 42, 2010).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n: expected a positive integer, got {n!r}")
    if not -90.0 <= min_el_deg < max_el_deg <= 90.0:
        raise InputError(
            f"elevation limits: expected -90 <= min < max <= 90, got {min_el_deg}, {max_el_deg}"
        )
    s0, s1 = math.sin(math.radians(min_el_deg)), math.sin(math.radians(max_el_deg))
    i = np.arange(n, dtype=np.float64)
    s = s0 + (i + 0.5) / n * (s1 - s0)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    az = np.degrees(i * golden) % 360.0
    el = np.degrees(np.arcsin(s))
    return np.stack([az, el], axis=1)


#: Golden ratio: the icosahedron's vertices are the cyclic permutations of (0, +-1, +-phi).
_PHI = (1.0 + math.sqrt(5.0)) / 2.0
_ICO_VERTICES = np.array(
    [
        [-1, _PHI, 0],
        [1, _PHI, 0],
        [-1, -_PHI, 0],
        [1, -_PHI, 0],
        [0, -1, _PHI],
        [0, 1, _PHI],
        [0, -1, -_PHI],
        [0, 1, -_PHI],
        [_PHI, 0, -1],
        [_PHI, 0, 1],
        [-_PHI, 0, -1],
        [-_PHI, 0, 1],
    ],
    dtype=np.float64,
)
#: The icosahedron's 20 faces (vertex indices, counter-clockwise from outside).
_ICO_FACES = np.array(
    [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ],
    dtype=np.int64,
)


def _icosahedron() -> tuple[list[NDArray[np.float64]], NDArray[np.int64]]:
    """Unit vertices (list, grown by :func:`_subdivide`) and faces of the icosahedron."""
    v = _ICO_VERTICES
    return list(v / np.linalg.norm(v, axis=1, keepdims=True)), _ICO_FACES


def _subdivide(verts: list[NDArray[np.float64]], f: NDArray[np.int64]) -> NDArray[np.int64]:
    """Split every triangle into four; new edge midpoints go on the unit sphere (appended)."""
    cache: dict[tuple[int, int], int] = {}

    def mid(a: int, b: int) -> int:
        key = (min(a, b), max(a, b))
        if key not in cache:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            cache[key] = len(verts) - 1
        return cache[key]

    nf = []
    for a, b, c in f:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        nf += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    return np.asarray(nf, dtype=np.int64)


def icosphere_directions(
    subdivisions: int = 1, *, min_el_deg: float = -90.0
) -> NDArray[np.float64]:
    """``(N, 2)`` (az, el) degrees at the vertices of an icosahedron subdivided
    ``subdivisions`` times (10 * 4**k + 2), above ``min_el_deg``, sorted by el then az.
    """
    if (
        isinstance(subdivisions, bool)
        or not isinstance(subdivisions, (int, np.integer))
        or not 0 <= subdivisions <= 6
    ):
        raise InputError(f"subdivisions: expected an integer in [0, 6], got {subdivisions!r}")
    verts, f = _icosahedron()
    for _ in range(int(subdivisions)):
        f = _subdivide(verts, f)
    ae = directions_to_az_el(np.asarray(verts))
    ae = np.round(ae, 9) % np.array([360.0, 1e9])
    ae = ae[ae[:, 1] >= min_el_deg - 1e-9]
    order = np.lexsort((ae[:, 0], ae[:, 1]))
    return ae[order]


def camera_T_obj_cam(
    az_deg: float,
    el_deg: float,
    range_mm: float,
    roll_deg: float = 0.0,
    center_obj: NDArray | Sequence[float] = (0.0, 0.0, 0.0),
) -> NDArray[np.float64]:
    """``T_obj_cam`` of a camera at (az, el, range) around ``center_obj`` looking at it.

    Object +z appears up in the image. At |el| = 90 deg (looking along z) the
    horizontal direction pointing away from the azimuth, ``-(cos az, sin az, 0)``,
    appears up instead, so the pose stays defined. Roll then turns the camera about
    its optical axis.
    """
    c = np.asarray(center_obj, dtype=np.float64).reshape(3)
    a, e = math.radians(az_deg), math.radians(el_deg)
    d = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    eye = c + range_mm * d
    z = -d
    up = np.array([0.0, 0.0, 1.0])
    if abs(d[2]) > 1.0 - 1e-9:
        up = np.array([-math.cos(a), -math.sin(a), 0.0]) * np.sign(d[2])
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = math.radians(roll_deg)
    cr, sr = math.cos(r), math.sin(r)
    # rotate the camera's x, y axes about z by -roll (scene turns clockwise by +roll)
    x2 = cr * x - sr * y
    y2 = sr * x + cr * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x2, y2, z, eye
    return T


def make_poses(
    directions_deg: NDArray | Sequence[tuple[float, float]],
    ranges_mm: Sequence[float] | float,
    *,
    K: NDArray | None = None,
    size: int = 128,
    focal_px: float | None = None,
    rolls_deg: Sequence[float] | float = 0.0,
    center_obj: NDArray | Sequence[float] = (0.0, 0.0, 0.0),
) -> list[ChipPose]:
    """All (az, el) directions x ranges x rolls as :class:`ChipPose`, range-major.

    ``K`` default: focal ``focal_px`` (default ``size``), principal point at the chip
    centre; ``center_obj``: the point looked at, object frame mm.
    """
    dirs = check_array(
        np.asarray(directions_deg, dtype=np.float64).reshape(-1, 2),
        "directions_deg",
        shape=(None, 2),
        min_size=2,
    )
    ranges = parse_range(ranges_mm)
    rolls = parse_range(rolls_deg)
    for r in ranges:
        if not (math.isfinite(r) and r > 0):
            raise InputError(f"ranges_mm: expected positive distances, got {r}")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise InputError(f"size: expected a positive integer chip size, got {size!r}")
    if K is None:
        f = float(size if focal_px is None else focal_px)
        c0 = (size - 1) / 2.0
        K = np.array([[f, 0.0, c0], [0.0, f, c0], [0.0, 0.0, 1.0]])
    out = []
    for rng in ranges:
        for az, el in dirs:
            for roll in rolls:
                T_obj_cam = camera_T_obj_cam(az, el, rng, roll, center_obj)
                out.append(
                    ChipPose(
                        float(az), float(el), float(rng), float(roll), K, np.linalg.inv(T_obj_cam)
                    )
                )
    return out


def poses_table(poses: Sequence[ChipPose]):  # -> pandas.DataFrame
    """Poses as a pandas DataFrame, one row per pose.

    Columns: ``az_deg, el_deg, range_mm, roll_deg, fx, fy, cx, cy`` and the 16
    entries ``T_cam_obj_ij`` (row ``i``, column ``j``) of the 4x4 transform.
    """
    import pandas as pd

    cols = list(POSE_COLUMNS) + [f"T_cam_obj_{i}{j}" for i in range(4) for j in range(4)]
    return pd.DataFrame([p.row() for p in poses], columns=cols)
