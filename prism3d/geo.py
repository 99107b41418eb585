"""Where things are on the Earth, in one place: WGS84 positions to and from a site's local
east-north-up frame, the UTM zone of a site, and the coordinate systems written into our
GIS products. Geodesy is PROJ's (pyproj): geodetic -> Earth-centred (ECEF) on the WGS84
ellipsoid -> the topocentric frame at the origin, exact to well under a millimetre;
heights are ellipsoidal, as GPS gives them (docs/uav.md).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pyproj
from numpy.typing import NDArray

from prism3d.errors import InputError

__all__ = ["check_lla", "enu_to_wgs84", "local_enu_crs_wkt", "utm_epsg", "wgs84_to_enu"]


def check_lla(lla: NDArray, what: str) -> NDArray[np.float64]:
    """``(n, 3)`` float64 (latitude, longitude, height) rows, or a one-line error."""
    a = np.asarray(lla, dtype=np.float64)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
        raise InputError(f"{what}: expected finite (latitude, longitude, height) rows, got shape {np.shape(lla)}")
    if (np.abs(a[:, 0]) > 90).any() or (np.abs(a[:, 1]) > 360).any():
        raise InputError(f"{what}: latitude must be within +-90 deg and longitude within +-360 deg")
    return a


@lru_cache(maxsize=64)
def _topocentric(lat0: float, lon0: float, h0: float) -> pyproj.Transformer:
    """(lat, lon, h) in degrees and metres -> (east, north, up) at the origin, metres."""
    return pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +proj=axisswap +order=2,1 +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        f"+step +proj=cart +ellps=WGS84 +step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} "
        f"+h_0={h0!r}")


def wgs84_to_enu(lla: NDArray, origin: NDArray) -> NDArray[np.float64]:
    """``(n, 3)`` east, north, up (m) of WGS84 ``(lat, lon, h)`` rows (degrees, metres
    above the ellipsoid) in the tangent frame at ``origin`` (lat, lon, h)."""
    a = check_lla(lla, "positions")
    o = check_lla(origin, "origin")[0]
    e, n, u = _topocentric(float(o[0]), float(o[1]), float(o[2])).transform(a[:, 0], a[:, 1], a[:, 2])
    return np.stack([e, n, u], axis=1).astype(np.float64)


def enu_to_wgs84(enu: NDArray, origin: NDArray) -> NDArray[np.float64]:
    """The inverse of :func:`wgs84_to_enu`: ``(n, 3)`` latitude, longitude (degrees) and
    ellipsoidal height (m)."""
    o = check_lla(origin, "origin")[0]
    e = np.atleast_2d(np.asarray(enu, dtype=np.float64))
    if e.ndim != 2 or e.shape[1] != 3 or not np.isfinite(e).all():
        raise InputError(f"positions: expected finite (east, north, up) rows, got shape {np.shape(enu)}")
    lat, lon, h = _topocentric(float(o[0]), float(o[1]), float(o[2])).transform(
        e[:, 0], e[:, 1], e[:, 2], direction=pyproj.enums.TransformDirection.INVERSE)
    return np.stack([lat, lon, h], axis=1).astype(np.float64)


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """The EPSG code of the WGS84 UTM zone holding (lat, lon): 6-degree zones from 180 W,
    with the grid's exceptions (zone 32 widened over south-west Norway, 56-64 N; zones 31,
    33, 35 and 37 over Svalbard, 72-84 N); beyond UTM's 84 N / 80 S, a one-line error."""
    a = check_lla([lat_deg, lon_deg, 0.0], "site")[0]
    lat, lon = float(a[0]), ((float(a[1]) + 180.0) % 360.0) - 180.0
    if not -80.0 <= lat <= 84.0:
        raise InputError(f"site: latitude {lat:.4f} deg is beyond UTM (80 S to 84 N); use the local frame")
    zone = min(int((lon + 180.0) // 6.0) + 1, 60)
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif lat >= 72.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return (32600 if lat >= 0.0 else 32700) + zone


def local_enu_crs_wkt(lat0_deg: float, lon0_deg: float) -> str:
    """OGC WKT of the orthographic projection at (lat0, lon0) on WGS84, metres: the GIS
    stand-in for a local east-north-up frame there (within 2 cm of true ENU at 500 m)."""
    from rasterio.crs import CRS

    if not (-90 <= lat0_deg <= 90 and -180 <= lon0_deg <= 360):
        raise InputError(f"origin: latitude {lat0_deg} / longitude {lon0_deg} out of range")
    return CRS.from_proj4(f"+proj=ortho +lat_0={lat0_deg:.10f} +lon_0={lon0_deg:.10f} +x_0=0 +y_0=0 "
                          "+ellps=WGS84 +units=m +no_defs").to_wkt()
