"""Where and with what a photograph was taken: GPS from a position table (senseFly's
``geoinfo.txt`` and any tab/comma table with the same columns) or from the JPEG's EXIF,
and the focal length in pixels from EXIF. The survey mode (docs/uav.md) builds on these;
positions go to a local frame through :mod:`prism3d.geo`.

Heights are ellipsoidal, as GPS gives them (EXIF GPSAltitude of drone cameras is
ellipsoidal too; a table's ``altitude_wgs84`` column is preferred over ``altitude_amsl``
for the same reason).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError

__all__ = ["GeoTag", "exif_focal_px", "exif_geotag", "read_position_table"]

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
