"""Where things are on the Earth, in one place: WGS84 positions to and from a site's local
east-north-up frame, the UTM zone of a site, and the coordinate systems written into our
GIS products. Geodesy is PROJ's (pyproj): geodetic -> Earth-centred (ECEF) on the WGS84
ellipsoid -> the topocentric frame at the origin, exact to well under a millimetre;
heights are ellipsoidal, as GPS gives them (docs/uav.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyproj
from numpy.typing import NDArray

from prism3d.errors import InputError

__all__ = ["CRS_CHOICES", "MapFrame", "check_lla", "enu_to_wgs84", "local_enu_crs_wkt", "parse_crs", "utm_epsg",
           "wgs84_to_enu"]


def check_lla(lla: NDArray, what: str) -> NDArray[np.float64]:
    """``(n, 3)`` float64 (latitude, longitude, height) rows, or a one-line error."""
    try:
        a = np.asarray(lla, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected (latitude, longitude, height) numbers, got {str(lla)[:60]!r}") from None
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


#: What ``--crs`` accepts beside ``EPSG:<code>``: the site's UTM zone, or the local frame.
CRS_CHOICES = ("utm", "enu")


def parse_crs(spec: str | None) -> str | None:
    """A product CRS request checked: None (the default: UTM with GPS), ``"utm"``,
    ``"enu"`` or ``"EPSG:<code>"`` of a projected CRS in metres; else a one-line error."""
    if spec is None:
        return None
    s = str(spec).strip()
    if s.lower() in CRS_CHOICES:
        return s.lower()
    if not s.upper().startswith("EPSG:") or not s[5:].isdigit():
        raise InputError(f"crs: expected utm, enu or EPSG:<code>, got {spec!r}")
    try:
        crs = pyproj.CRS.from_epsg(int(s[5:]))
    except pyproj.exceptions.CRSError:
        raise InputError(f"crs: {s} is not a coordinate system PROJ knows") from None
    if not crs.is_projected:
        raise InputError(f"crs: {s} ({crs.name}) is not a projected CRS; products need map metres (e.g. UTM)")
    units = {a.unit_name for a in crs.axis_info[:2]}
    if units != {"metre"}:
        raise InputError(f"crs: {s} ({crs.name}) has axes in {', '.join(sorted(units))}; products need metres")
    return f"EPSG:{int(s[5:])}"


@lru_cache(maxsize=16)
def _lonlat_to_map(epsg: int) -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(4326, epsg, always_xy=True)


@dataclass(frozen=True)
class MapFrame:
    """The grid a survey's products lie on and its ties to the survey's local ENU frame
    (origin ``origin_lla``): ``epsg`` a projected CRS (x east, y north in metres; heights
    ellipsoidal, as GPS gives them), or None for the local frame itself (the products'
    CRS then the orthographic projection at the origin). Conversions are PROJ's, exact
    (heights included: a point's ENU ``up`` becomes its height above the ellipsoid)."""

    origin_lla: tuple[float, float, float]
    epsg: int | None = None

    @classmethod
    def for_site(cls, spec: str | None, origin_lla: NDArray | None) -> MapFrame | None:
        """The frame a ``--crs`` request gives at a site (None: a survey without GPS, whose
        products carry no CRS; asking for one then is an error)."""
        s = parse_crs(spec)
        if origin_lla is None:
            if s is not None:
                raise InputError(f"crs: {spec} asked for, but the frames have no GPS; the products have no "
                                 "geographic frame (leave out --crs)")
            return None
        o = check_lla(origin_lla, "origin")[0]
        origin = (float(o[0]), float(o[1]), float(o[2]))
        if s == "enu" or (s is None and not -80.0 <= origin[0] <= 84.0):  # the poles: no UTM
            return cls(origin)
        if s is None or s == "utm":
            return cls(origin, utm_epsg(origin[0], origin[1]))
        return cls(origin, int(s[5:]))

    @classmethod
    def from_record(cls, doc: dict) -> MapFrame | None:
        """The frame a survey's poses.json records (``origin_lla`` and ``map_frame``);
        surveys written before the record are in the local frame."""
        lla = doc.get("origin_lla")
        if lla is None:
            return None
        rec = doc.get("map_frame") or {}
        epsg = rec.get("epsg") if isinstance(rec, dict) else None
        if epsg is not None and (isinstance(epsg, bool) or not isinstance(epsg, int)):
            raise InputError(f"map_frame: epsg must be an integer, got {epsg!r}")
        o = check_lla(lla, "origin_lla")[0]
        if epsg is not None:
            try:
                parse_crs(f"EPSG:{epsg}")
            except InputError as exc:
                raise InputError(f"map_frame: {exc}") from None
        return cls((float(o[0]), float(o[1]), float(o[2])), epsg)

    @property
    def local(self) -> bool:
        return self.epsg is None

    @property
    def crs_wkt(self) -> str:
        """The products' CRS as OGC WKT 1 (what GeoTIFF and LAS 1.4 readers take)."""
        if self.epsg is None:
            return local_enu_crs_wkt(self.origin_lla[0], self.origin_lla[1])
        return pyproj.CRS.from_epsg(self.epsg).to_wkt("WKT1_GDAL")

    @property
    def name(self) -> str:
        if self.epsg is None:
            return "local east-north-up frame at the origin"
        return f"EPSG:{self.epsg} ({pyproj.CRS.from_epsg(self.epsg).name})"

    def record(self) -> dict:
        """poses.json's ``map_frame`` entry."""
        return {"epsg": self.epsg, "name": self.name, "heights": "metres above the WGS84 ellipsoid",
                "units": "metre"}

    def enu_to_map(self, P: NDArray) -> NDArray[np.float64]:
        """``(n, 3)`` ENU points -> map (x, y, ellipsoidal height)."""
        p = np.atleast_2d(np.asarray(P, dtype=np.float64))
        if self.epsg is None:
            return p.copy()
        lla = enu_to_wgs84(p, np.asarray(self.origin_lla))
        x, y = _lonlat_to_map(self.epsg).transform(lla[:, 1], lla[:, 0])
        return np.stack([x, y, lla[:, 2]], axis=1)

    def map_to_lla(self, Q: NDArray) -> NDArray[np.float64]:
        """``(n, 3)`` map (x, y, height) -> WGS84 (latitude, longitude, height)."""
        q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
        if q.ndim != 2 or q.shape[1] != 3 or not np.isfinite(q).all():
            raise InputError(f"map positions: expected finite (x, y, height) rows, got shape {np.shape(Q)}")
        if self.epsg is None:
            return enu_to_wgs84(q, np.asarray(self.origin_lla))
        lon, lat = _lonlat_to_map(self.epsg).transform(q[:, 0], q[:, 1], direction=pyproj.enums.TransformDirection.INVERSE)
        return np.stack([lat, lon, q[:, 2]], axis=1)

    def map_to_enu(self, Q: NDArray) -> NDArray[np.float64]:
        """``(n, 3)`` map (x, y, ellipsoidal height) -> ENU points."""
        q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
        if self.epsg is None:
            return q.copy()
        return wgs84_to_enu(self.map_to_lla(q), np.asarray(self.origin_lla))

    def grid_north_deg(self, Q: NDArray) -> NDArray[np.float64]:
        """At map points ``(n, 2+)``: the compass bearing (deg, clockwise from true north)
        of the grid's +y axis (the meridian convergence; 0 in the local frame)."""
        q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
        a = np.c_[q[:, :2], np.zeros(len(q))]
        b = a + [0.0, 1.0, 0.0]
        e = self.map_to_enu(a)
        f = self.map_to_enu(b)
        d = f - e
        return np.degrees(np.arctan2(d[:, 0], d[:, 1]))
