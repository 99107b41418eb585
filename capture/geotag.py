"""Where and with what a photograph was taken: GPS from a position table (senseFly's
``geoinfo.txt`` and any tab/comma table with the same columns) or from the JPEG's EXIF,
the focal length in pixels from EXIF, and WGS84 positions in a local east-north-up
frame in metres. The survey mode (docs/uav.md) builds on these.

ENU is exact: geodetic -> Earth-centred (ECEF) on the WGS84 ellipsoid, then rotated into
the tangent frame at the origin (east, north, up); heights are ellipsoidal, as GPS
gives them (EXIF GPSAltitude of drone cameras is ellipsoidal too; a table's
``altitude_wgs84`` column is preferred over ``altitude_amsl`` for the same reason).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError

__all__ = ["GeoTag", "WGS84_A", "WGS84_F", "enu_to_wgs84", "exif_focal_px", "exif_geotag", "read_position_table",
           "wgs84_to_enu"]

#: WGS84 semi-major axis (m) and flattening.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
_E2 = WGS84_F * (2.0 - WGS84_F)


@dataclass(frozen=True)
class GeoTag:
    """One photograph's position (degrees, metres above the WGS84 ellipsoid) and, when
    the source has them, its attitude (degrees: heading clockwise from north, pitch,
    roll)."""

    name: str
    lat_deg: float
    lon_deg: float
    alt_m: float
    heading_deg: float | None = None
    pitch_deg: float | None = None
    roll_deg: float | None = None


def _ecef(lla: NDArray[np.float64]) -> NDArray[np.float64]:
    lat, lon, h = np.radians(lla[:, 0]), np.radians(lla[:, 1]), lla[:, 2]
    n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - _E2) + h) * np.sin(lat)], axis=1)


def _enu_rotation(lat0: float, lon0: float) -> NDArray[np.float64]:
    """Rows: east, north, up at (lat0, lon0) in ECEF."""
    la, lo = math.radians(lat0), math.radians(lon0)
    return np.array([[-math.sin(lo), math.cos(lo), 0.0],
                     [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
                     [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]])


def _check_lla(lla: NDArray, what: str) -> NDArray[np.float64]:
    a = np.asarray(lla, dtype=np.float64)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
        raise InputError(f"{what}: expected finite (latitude, longitude, height) rows, got shape {np.shape(lla)}")
    if (np.abs(a[:, 0]) > 90).any() or (np.abs(a[:, 1]) > 360).any():
        raise InputError(f"{what}: latitude must be within +-90 deg and longitude within +-360 deg")
    return a


def wgs84_to_enu(lla: NDArray, origin: NDArray) -> NDArray[np.float64]:
    """``(n, 3)`` east, north, up (m) of WGS84 ``(lat, lon, h)`` rows (degrees, metres
    above the ellipsoid) in the tangent frame at ``origin`` (lat, lon, h)."""
    a = _check_lla(lla, "positions")
    o = _check_lla(origin, "origin")[0]
    return (_ecef(a) - _ecef(o[None])[0]) @ _enu_rotation(o[0], o[1]).T


def enu_to_wgs84(enu: NDArray, origin: NDArray) -> NDArray[np.float64]:
    """The inverse of :func:`wgs84_to_enu` (Bowring's latitude, iterated to < 1e-12 rad)."""
    o = _check_lla(origin, "origin")[0]
    e = np.atleast_2d(np.asarray(enu, dtype=np.float64))
    xyz = _ecef(o[None])[0] + e @ _enu_rotation(o[0], o[1])
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - _E2))
    for _ in range(10):
        n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        new = np.arctan2(z, p * (1.0 - _E2 * n / (n + h)))
        if np.max(np.abs(new - lat)) < 1e-12:
            lat = new
            break
        lat = new
    n = WGS84_A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    h = p / np.cos(lat) - n
    return np.stack([np.degrees(lat), np.degrees(lon), h], axis=1)


#: Column names a position table may use, first match wins.
_COLUMNS = {
    "name": ("filename", "file", "image", "name"),
    "lat": ("latitude", "lat"),
    "lon": ("longitude", "lon", "lng"),
    "alt": ("altitude_wgs84", "altitude_ellipsoid", "altitude", "alt", "altitude_amsl", "height"),
    "heading": ("heading", "yaw"),
    "pitch": ("pitch",),
    "roll": ("roll",),
}


def read_position_table(path: str | Path, *, images_dir: str | Path | None = None) -> dict[str, GeoTag]:
    """Positions per image name from a tab- or comma-separated table with a header line
    (``#`` lines are comments): ``fileName latitude longitude altitude_wgs84 ...`` as
    senseFly's ``geoinfo.txt``, or the same with the usual short names. With
    ``images_dir`` every named image must exist there (a table naming missing files is
    refused, naming them)."""
    p = Path(path)
    try:
        lines = [ln.rstrip("\r\n") for ln in p.read_text(encoding="utf-8", errors="strict").splitlines()]
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read the position table ({exc})") from None
    rows = [ln for ln in lines if ln.strip() and not ln.lstrip().startswith("#")]
    if len(rows) < 2:
        raise InputError(f"{p}: expected a header line and at least one position")
    sep = "\t" if "\t" in rows[0] else ","
    header = [h.strip().lower() for h in rows[0].split(sep)]
    col: dict[str, int] = {}
    for key, names in _COLUMNS.items():
        for n in names:
            if n in header:
                col[key] = header.index(n)
                break
    missing = [k for k in ("name", "lat", "lon", "alt") if k not in col]
    if missing:
        raise InputError(f"{p}: no column for {', '.join(missing)} (header: {' '.join(header)})")
    out: dict[str, GeoTag] = {}
    for k, ln in enumerate(rows[1:], start=2):
        f = [v.strip() for v in ln.split(sep)]

        def num(key: str, f: list[str] = f, k: int = k) -> float | None:
            if key not in col:
                return None
            try:
                v = float(f[col[key]])
            except (IndexError, ValueError):
                raise InputError(f"{p}: row {k}: {key} is not a number") from None
            if not math.isfinite(v):
                raise InputError(f"{p}: row {k}: {key} is not finite")
            return v

        name = f[col["name"]] if col["name"] < len(f) else ""
        if not name:
            raise InputError(f"{p}: row {k}: no image name")
        lat, lon, alt = num("lat"), num("lon"), num("alt")
        if not (-90 <= lat <= 90 and -360 <= lon <= 360):
            raise InputError(f"{p}: row {k}: latitude {lat} / longitude {lon} out of range")
        if name in out:
            raise InputError(f"{p}: {name} appears twice")
        out[name] = GeoTag(name, lat, lon, alt, num("heading"), num("pitch"), num("roll"))
    if images_dir is not None:
        d = Path(images_dir)
        absent = [n for n in out if not (d / n).is_file()]
        if absent:
            raise InputError(f"{p}: names {len(absent)} image(s) not in {d}: {', '.join(absent[:5])}"
                             + (" ..." if len(absent) > 5 else ""))
    return out


def _exif(path: Path):  # -> PIL.Image.Exif
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.getexif(), im.size
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"{path}: cannot read the image's metadata ({exc})") from None


def exif_geotag(path: str | Path) -> GeoTag | None:
    """The GPS position in a JPEG's EXIF (None when it has none). The altitude is taken
    as given (drone cameras write ellipsoidal heights); a GPSAltitudeRef of 1 (below
    sea level) negates it."""
    from PIL.ExifTags import GPS, IFD

    p = Path(path)
    exif, _ = _exif(p)
    g = exif.get_ifd(IFD.GPSInfo)
    if not g or GPS.GPSLatitude not in g or GPS.GPSLongitude not in g:
        return None

    def deg(v, ref: str | None) -> float:
        d, m, s = (float(x) for x in v)
        sign = -1.0 if ref in ("S", "W") else 1.0
        return sign * (d + m / 60.0 + s / 3600.0)

    lat = deg(g[GPS.GPSLatitude], g.get(GPS.GPSLatitudeRef))
    lon = deg(g[GPS.GPSLongitude], g.get(GPS.GPSLongitudeRef))
    alt = float(g.get(GPS.GPSAltitude, 0.0))
    if g.get(GPS.GPSAltitudeRef) in (1, b"\x01"):
        alt = -alt
    track = g.get(GPS.GPSTrack)
    return GeoTag(p.name, lat, lon, alt, None if track is None else float(track))


def exif_focal_px(path: str | Path) -> float | None:
    """Focal length in pixels of the image as stored: FocalLength (mm) times
    FocalPlaneXResolution (pixels per inch or cm of the sensor at the size EXIF states),
    scaled to the file's actual width; None when EXIF lacks either."""
    from PIL.ExifTags import IFD, Base

    p = Path(path)
    exif, (w, _) = _exif(p)
    e = exif.get_ifd(IFD.Exif)
    f_mm = e.get(Base.FocalLength)
    res = e.get(Base.FocalPlaneXResolution)
    if f_mm is None or res is None or float(res) <= 0:
        return None
    mm_per_unit = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}.get(int(e.get(Base.FocalPlaneResolutionUnit, 2)))
    if mm_per_unit is None:  # 1: no absolute unit
        return None
    per_mm = float(res) / mm_per_unit
    exif_w = e.get(Base.ExifImageWidth) or w
    return float(f_mm) * per_mm * (w / float(exif_w))
