"""Ground control points of a survey: OpenDroneMap's ``gcp_list.txt`` read and checked, the
points taken into the survey's local frame, and the check report (``gcp_check.json``).

The file: a first line naming the coordinate system (``EPSG:<code>``, a PROJ string, WKT on
one line, or ODM's ``WGS84 UTM <zone><N|S>``), then one line per observation: ``x y z
pixel_x pixel_y image [name [...]]`` (x y in the CRS's axis order as ODM reads them:
easting northing, or longitude latitude for a geographic CRS; heights in metres above the
WGS84 ellipsoid, as the survey's are; pixels from the centre of the top-left pixel, as
OpenSfM reads them). Lines starting with ``#`` and blank lines are skipped.

Control points are held where the map puts them in the survey's bundle adjustment
(:mod:`~prism3d.reconstruct.survey.sfm`); check points (``--gcp-check``) are kept out of
it and only measured: each point is triangulated afresh from its pixels through the final
poses and compared with its map coordinates, in the file's own CRS, with no alignment.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyproj
from numpy.typing import NDArray

from prism3d.errors import InputError
from prism3d.geo import enu_to_wgs84, wgs84_to_enu
from prism3d.reconstruct.survey._sfm_worker import MIN_SPREAD
from prism3d.reconstruct.survey.sfm import ControlPoint

__all__ = ["GcpFile", "GcpPoint", "check_points_report", "gps_only_accuracy", "read_gcp_file", "survey_control"]

#: The fewest points a file must hold, and the fewest control points an adjustment takes.
MIN_POINTS = 3
_WGS84 = pyproj.CRS.from_epsg(4326)
#: ODM's short CRS form.
_ODM_UTM = re.compile(r"^\s*WGS\s*84\s+UTM\s+(\d{1,2})\s*([NS])\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class GcpPoint:
    """One named point: its coordinates in the file's CRS and its pixels ``(image, x, y)``."""

    name: str
    xyz: tuple[float, float, float]
    observations: tuple[tuple[str, float, float], ...]


@dataclass(frozen=True)
class GcpFile:
    """A read ``gcp_list.txt``: its CRS (as written and as PROJ reads it) and its points in file order."""

    path: Path
    crs_text: str
    crs: pyproj.CRS
    points: tuple[GcpPoint, ...]

    def to_lla(self, xyz: NDArray) -> NDArray[np.float64]:
        """(n, 3) file coordinates -> (latitude, longitude, ellipsoidal height)."""
        P = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        lon, lat = _transformer(self.crs, _WGS84).transform(P[:, 0], P[:, 1])
        return np.stack([lat, lon, P[:, 2]], axis=1)

    def from_lla(self, lla: NDArray) -> NDArray[np.float64]:
        """The inverse of :meth:`to_lla`."""
        A = np.atleast_2d(np.asarray(lla, dtype=np.float64))
        x, y = _transformer(_WGS84, self.crs).transform(A[:, 1], A[:, 0])
        return np.stack([x, y, A[:, 2]], axis=1)


@lru_cache(maxsize=16)
def _transformer(src: pyproj.CRS, dst: pyproj.CRS) -> pyproj.Transformer:
    """PROJ's transformation between two CRSs, x y in (easting, northing) / (lon, lat) order."""
    return pyproj.Transformer.from_crs(src, dst, always_xy=True)


def _parse_crs(text: str, where: str) -> pyproj.CRS:
    m = _ODM_UTM.match(text)
    spec = f"EPSG:{(32600 if m.group(2).upper() == 'N' else 32700) + int(m.group(1))}" if m else text.strip()
    try:
        crs = pyproj.CRS.from_user_input(spec)
    except pyproj.exceptions.CRSError:
        raise InputError(f"{where}: line 1: {text.strip()[:60]!r} is not a coordinate system PROJ knows "
                         "(expected e.g. EPSG:32654, WGS84 UTM 54N or a PROJ string)") from None
    if crs.is_projected:
        units = {a.unit_name for a in crs.axis_info[:2]}
        if units != {"metre"}:
            raise InputError(f"{where}: {crs.name} has axes in {', '.join(sorted(units))}; give a CRS in metres "
                             "or degrees")
    elif not crs.is_geographic:
        raise InputError(f"{where}: {crs.name} is neither projected nor geographic")
    return crs


def read_gcp_file(path: str | Path) -> GcpFile:
    """``path`` read and checked (module docstring); a one-line :class:`InputError` for an
    unreadable file, an unknown CRS, a malformed line, a name given two positions, or fewer
    than :data:`MIN_POINTS` points."""
    p = Path(path)
    where = str(p)
    try:
        lines = p.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{where}: cannot read the control points ({exc.__class__.__name__})") from None
    body = [(k + 1, ln) for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise InputError(f"{where}: empty; expected a CRS line, then x y z pixel_x pixel_y image name lines")
    crs = _parse_crs(body[0][1], where)
    pos: dict[str, tuple[float, float, float]] = {}
    obs: dict[str, list[tuple[str, float, float]]] = {}
    for k, ln in body[1:]:
        f = ln.split()
        if len(f) < 6:
            raise InputError(f"{where}: line {k}: expected x y z pixel_x pixel_y image [name], got {ln.strip()[:60]!r}")
        try:
            v = [float(a) for a in f[:5]]
        except ValueError:
            raise InputError(f"{where}: line {k}: expected five numbers then an image name, got "
                             f"{ln.strip()[:60]!r}") from None
        if not all(math.isfinite(a) for a in v):
            raise InputError(f"{where}: line {k}: coordinates must be finite numbers")
        if v[3] < -0.5 or v[4] < -0.5:
            raise InputError(f"{where}: line {k}: pixel ({v[3]}, {v[4]}) lies outside any image")
        name = f[6] if len(f) > 6 else f"{v[0]:.3f}_{v[1]:.3f}_{v[2]:.3f}"
        xyz = (v[0], v[1], v[2])
        if name in pos and max(abs(a - b) for a, b in zip(pos[name], xyz)) > 1e-6:
            raise InputError(f"{where}: line {k}: point {name} is given two positions")
        pos[name] = xyz
        obs.setdefault(name, []).append((Path(f[5]).name, v[3], v[4]))
    if len(pos) < MIN_POINTS:
        raise InputError(f"{where}: {len(pos)} control point(s); at least {MIN_POINTS} are needed")
    gf = GcpFile(p, body[0][1].strip(), crs, tuple(GcpPoint(n, pos[n], tuple(obs[n])) for n in pos))
    lla = gf.to_lla(np.array([pt.xyz for pt in gf.points]))
    if not np.isfinite(lla).all() or (np.abs(lla[:, 0]) > 90).any():
        raise InputError(f"{where}: coordinates outside {crs.name}'s valid area (x y in the CRS's order?)")
    return gf


def survey_control(gf: GcpFile, frame_names: Sequence[str], origin_lla: NDArray | None,
                   check: Sequence[str] = ()) -> tuple[list[ControlPoint], list[ControlPoint]]:
    """The file's points in the survey's local ENU frame (``origin_lla``) with their pixels
    by frame index: (control, check). Errors: no origin (neither GPS nor control points), an
    image not among the frames,
    a ``check`` name not in the file, or 1-2 control points left (0 checks only)."""
    where = str(gf.path)
    if origin_lla is None:
        raise InputError(f"{where}: only check points and no GPS: nothing places the survey (give control points "
                         "or the frames' GPS)")
    index = {Path(n).name: k for k, n in enumerate(frame_names)}
    missing = sorted({im for pt in gf.points for im, _, _ in pt.observations if im not in index})
    if missing:
        raise InputError(f"{where}: {len(missing)} image(s) not in the survey: {', '.join(missing[:3])}"
                         f"{' ...' if len(missing) > 3 else ''}")
    names = {pt.name for pt in gf.points}
    unknown = [c for c in check if c not in names]
    if unknown:
        raise InputError(f"--gcp-check: {', '.join(unknown[:3])} not in {where} (its points: "
                         f"{', '.join(sorted(names)[:6])}{' ...' if len(names) > 6 else ''})")
    n_control = len(names) - len(set(check))
    if 0 < n_control < MIN_POINTS:
        raise InputError(f"{where}: {n_control} control point(s) left beside the check points; at least "
                         f"{MIN_POINTS} are needed (or make all of them check points)")
    enu = wgs84_to_enu(gf.to_lla(np.array([pt.xyz for pt in gf.points])), np.asarray(origin_lla, dtype=np.float64))
    control, checks = [], []
    for pt, e in zip(gf.points, enu):
        cp = ControlPoint(pt.name, (float(e[0]), float(e[1]), float(e[2])),
                          tuple((index[im], x, y) for im, x, y in pt.observations))
        (checks if pt.name in check else control).append(cp)
    return control, checks


def gps_only_accuracy(C: NDArray, ground: NDArray, sigma_h: float, sigma_v: float) -> dict[str, Any]:
    """The 1-sigma absolute error of a block that rests on its GPS alone (no control
    points): a least-squares fit of n positions of accuracy (``sigma_h`` per axis,
    ``sigma_v``) leaves a shift of sigma / sqrt(n) and a tilt about each horizontal
    principal axis of the positions of sigma_v / (sqrt(n) x their spread across it); that
    tilt moves the ground at its farthest from the positions' centroid (``ground``:
    sparse points, ENU). A block of one or two lines is narrow across: its roll is the
    weak part."""
    C = np.asarray(C, dtype=np.float64)
    n = len(C)
    m = C[:, :2].mean(axis=0)
    evals, evecs = np.linalg.eigh(np.cov((C[:, :2] - m).T, bias=True))
    G = np.asarray(ground, dtype=np.float64)[:, :2] - m
    out: dict[str, Any] = {
        "control": "none: position, scale and tilt rest on the GPS", "gps_accuracy_m": [sigma_h, sigma_v],
        "horizontal_m": round(sigma_h / math.sqrt(n), 3), "vertical_m": round(sigma_v / math.sqrt(n), 3),
        "measured": False, "how_to_measure": "give check points (--gcp FILE --gcp-check NAMES)"}
    spread = np.sqrt(np.maximum(evals, 0.0))
    if n < 3 or spread[0] <= MIN_SPREAD * spread[1]:  # the roll about the line: from the ground, not the GPS
        out.update(tilt_deg=None, vertical_at_edges_m=None,
                   tilt="the positions lie on one line: the roll about it comes from the ground's plane")
        return out
    tilt = [sigma_v / (math.sqrt(n) * sd) for sd in spread]
    reach = [float(np.abs(G @ evecs[:, k]).max()) if len(G) else 0.0 for k in range(2)]
    edge = math.sqrt((sigma_v / math.sqrt(n)) ** 2 + sum((t * r) ** 2 for t, r in zip(tilt, reach)))
    out.update(tilt_deg=round(math.degrees(max(tilt)), 3), vertical_at_edges_m=round(edge, 3))
    return out


def _triangulate(obs: Sequence[tuple[int, float, float]], T_enu: dict[int, NDArray], K: NDArray, dist: NDArray
                 ) -> tuple[NDArray[np.float64] | None, int]:
    """A point (ENU) from its pixels in placed frames (undistorted, linear least squares,
    then two Gauss-Newton steps on the reprojection error); None with fewer than two."""
    use = [(k, x, y) for k, x, y in obs if k in T_enu]
    if len(use) < 2:
        return None, len(use)
    uv = np.array([[x, y] for _, x, y in use], dtype=np.float64)
    n = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    Ms = [np.linalg.inv(T_enu[k])[:3] for k, _, _ in use]
    rows = []
    for M, (a, b) in zip(Ms, n):
        rows += [a * M[2] - M[0], b * M[2] - M[1]]
    vt = np.linalg.svd(np.asarray(rows))[2]
    if abs(vt[-1][3]) < 1e-12:
        return None, len(use)
    X = vt[-1][:3] / vt[-1][3]
    for _ in range(2):  # minimise the normalised reprojection error (the linear one weights by depth)
        J, r = [], []
        for M, (a, b) in zip(Ms, n):
            p = M[:, :3] @ X + M[:, 3]
            r += [p[0] / p[2] - a, p[1] / p[2] - b]
            J += [(M[0, :3] - p[0] / p[2] * M[2, :3]) / p[2], (M[1, :3] - p[1] / p[2] * M[2, :3]) / p[2]]
        X = X - np.linalg.lstsq(np.asarray(J), np.asarray(r), rcond=None)[0]
    return X, len(use)


def check_points_report(gf: GcpFile, control: Sequence[ControlPoint], checks: Sequence[ControlPoint],
                        T_enu: dict[int, NDArray], K: NDArray, dist: NDArray, origin_lla: NDArray,
                        gsd_m: float, adjusted: str) -> dict[str, Any]:
    """``gcp_check.json``: each point triangulated from the final poses and compared with
    its map coordinates in the file's CRS (no alignment): residual per point (dx, dy, dz,
    m: the CRS's axes, or east, north, up for a geographic CRS; horizontal, vertical), and
    the RMS per role, in m and in GSD."""
    given = {pt.name: np.array(pt.xyz) for pt in gf.points}
    rows = []
    for role, pts in (("control", control), ("check", checks)):
        for cp in pts:
            X, views = _triangulate(cp.observations, T_enu, K, dist)
            row: dict[str, Any] = {"name": cp.name, "role": role, "views": views}
            if X is None:
                row["why"] = "seen in fewer than two placed frames"
            else:
                got = gf.from_lla(enu_to_wgs84(X[None], origin_lla))[0]
                # metres: map units of a projected CRS; a geographic CRS's degrees measured in ENU
                d = X - np.asarray(cp.enu) if gf.crs.is_geographic else got - given[cp.name]
                row.update(estimated=[round(float(v), 4) for v in got], dx_m=round(float(d[0]), 4),
                           dy_m=round(float(d[1]), 4), dz_m=round(float(d[2]), 4),
                           horizontal_m=round(float(math.hypot(d[0], d[1])), 4), vertical_m=round(abs(float(d[2])), 4))
            rows.append(row)
    out: dict[str, Any] = {"crs": gf.crs_text, "crs_name": gf.crs.name, "adjusted_with": adjusted,
                           "gsd_m": round(float(gsd_m), 5), "points": rows,
                           "method": "each point triangulated from its pixels through the survey's final poses "
                                     "(undistorted; least squares on the reprojection error), compared with its "
                                     "coordinates in the file's CRS, no alignment"}
    for role in ("control", "check"):
        done = [r for r in rows if r["role"] == role and "dx_m" in r]
        if done:
            h = math.sqrt(sum(r["horizontal_m"] ** 2 for r in done) / len(done))
            v = math.sqrt(sum(r["dz_m"] ** 2 for r in done) / len(done))
            out[role] = {"points": len(done), "rms_horizontal_m": round(h, 4), "rms_vertical_m": round(v, 4),
                         "rms_horizontal_gsd": round(h / gsd_m, 3), "rms_vertical_gsd": round(v / gsd_m, 3)}
    return out
