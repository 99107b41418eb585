"""The geo module: ENU against known geodesy, round trips, UTM zones against PROJ's own
projection, and refusals."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest

from prism3d.errors import InputError
from prism3d.geo import enu_to_wgs84, local_enu_crs_wkt, utm_epsg, wgs84_to_enu


def test_enu_against_known_geodesy():
    o = np.array([37.5, 139.0, 100.0])
    # a point straight up is pure "up"; north and east steps by the ellipsoid's radii
    up = wgs84_to_enu([37.5, 139.0, 350.0], o)[0]
    assert np.allclose(up, [0, 0, 250.0], atol=1e-6)
    lat = np.radians(37.5)
    e2 = 6.69437999014e-3
    m = 6378137.0 * (1 - e2) / (1 - e2 * np.sin(lat) ** 2) ** 1.5  # meridian radius
    n = 6378137.0 / np.sqrt(1 - e2 * np.sin(lat) ** 2)  # prime vertical radius
    d = 1e-4  # degrees: curvature over ~10 m is far below a millimetre
    north = wgs84_to_enu([37.5 + d, 139.0, 100.0], o)[0]
    east = wgs84_to_enu([37.5, 139.0 + d, 100.0], o)[0]
    assert abs(north[1] - np.radians(d) * (m + 100.0)) < 1e-3 and abs(north[0]) < 1e-6
    assert abs(east[0] - np.radians(d) * (n + 100.0) * np.cos(lat)) < 1e-3
    # a parallel curves poleward in the tangent plane by x^2 tan(lat) / 2N (4.7 um here)
    assert east[1] == pytest.approx(east[0] ** 2 * np.tan(lat) / (2 * n), rel=0.01)


def test_enu_round_trip():
    rng = np.random.default_rng(0)
    o = np.array([-33.9, 151.2, 40.0])
    enu = rng.uniform(-5000, 5000, (50, 3))
    back = wgs84_to_enu(enu_to_wgs84(enu, o), o)
    assert np.abs(back - enu).max() < 1e-6


def test_bad_positions_are_refused():
    with pytest.raises(InputError, match="latitude"):
        wgs84_to_enu([[95.0, 0.0, 0.0]], [0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="finite"):
        wgs84_to_enu([[np.nan, 0.0, 0.0]], [0.0, 0.0, 0.0])


@pytest.mark.parametrize("lat, lon, code", [
    (37.5434, 139.0428, 32654),  # the shared aerial site
    (-33.9, 18.4, 32734),  # southern hemisphere
    (0.0, -0.1, 32630),  # the equator belongs to the north
    (51.5, 359.9, 32630),  # longitudes past 180 wrap
    (60.5, 5.3, 32632),  # south-west Norway: zone 32 widened west
    (78.0, 8.0, 32631), (78.0, 15.0, 32633), (78.0, 25.0, 32635), (78.0, 40.0, 32637),  # Svalbard
    (10.0, 179.99, 32660),
])
def test_utm_zone_of_a_site(lat, lon, code):
    assert utm_epsg(lat, lon) == code
    # the site is near its zone's central meridian band: PROJ's UTM keeps the scale near 1
    crs = pyproj.CRS.from_epsg(code)
    assert crs.name.startswith("WGS 84 / UTM zone")
    x, _ = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(((lon + 180) % 360) - 180, lat)
    assert 100_000 < x < 900_000


def test_beyond_utm_and_bad_sites_are_refused():
    with pytest.raises(InputError, match="beyond UTM"):
        utm_epsg(85.0, 10.0)
    with pytest.raises(InputError, match="latitude"):
        utm_epsg(91.0, 10.0)
    with pytest.raises(InputError, match="out of range"):
        local_enu_crs_wkt(95.0, 0.0)
    with pytest.raises(InputError, match="finite"):
        enu_to_wgs84([[np.inf, 0.0, 0.0]], [0.0, 0.0, 0.0])


def test_map_frame_against_transverse_mercator_facts():
    """UTM from the site's ENU frame: a round trip to 1e-6 m; the grid's north turned from
    true north by the meridian convergence (tan(dlon) sin(lat), spherical, to 0.01 deg);
    map distances the ENU distances times UTM's scale (0.9996 on the central meridian,
    growing as 1 + x^2 / 2R^2 away from it), heights the ellipsoidal heights."""
    from prism3d.geo import MapFrame

    o = (35.0, 139.5, 0.0)  # zone 54 (central meridian 141 E)
    f = MapFrame.for_site(None, np.array(o))
    assert f.epsg == 32654 and not f.local
    rng = np.random.default_rng(0)
    P = rng.uniform([-2000, -2000, 0], [2000, 2000, 300], (200, 3))
    Q = f.enu_to_map(P)
    np.testing.assert_allclose(f.map_to_enu(Q), P, atol=1e-6)
    lla = f.map_to_lla(Q)
    np.testing.assert_allclose(lla, enu_to_wgs84(P, np.array(o)), atol=1e-9)
    gamma = np.degrees(np.arctan(np.tan(np.radians(139.5 - 141.0)) * np.sin(np.radians(35.0))))
    assert float(f.grid_north_deg(Q[:1])[0]) == pytest.approx(gamma, abs=0.01)
    a, b = np.array([[0.0, 0.0, 0.0]]), np.array([[1000.0, 0.0, 0.0]])
    d_map = np.linalg.norm(f.enu_to_map(b)[0, :2] - f.enu_to_map(a)[0, :2])
    x = f.enu_to_map(a)[0, 0] - 500000.0
    k = 0.9996 * (1 + x**2 / (2 * 6371000.0**2))
    assert d_map == pytest.approx(1000.0 * k, rel=2e-5)
    # a point 1 km away on the tangent plane lies 7.8 cm above the ellipsoid
    assert f.enu_to_map([[1000.0, 0.0, 0.0]])[0, 2] == pytest.approx(1000.0**2 / (2 * 6371000.0), rel=0.01)
    # the local frame is the identity
    loc = MapFrame.for_site("enu", np.array(o))
    assert loc.local and np.array_equal(loc.enu_to_map(P), P) and "Orthographic" in loc.crs_wkt


@pytest.mark.parametrize("spec,msg", [("EPSG:4326", "not a projected CRS"), ("EPSG:2000000", "PROJ knows"),
                                      ("utm33", "expected utm"), ("EPSG:", "expected utm"),
                                      ("EPSG:2249", "US survey foot")])
def test_bad_crs_requests_are_refused(spec, msg):
    from prism3d.geo import parse_crs

    with pytest.raises(InputError, match=msg):
        parse_crs(spec)


def test_crs_without_gps_is_refused_and_the_default_is_utm():
    from prism3d.geo import MapFrame

    with pytest.raises(InputError, match="no GPS"):
        MapFrame.for_site("utm", None)
    assert MapFrame.for_site(None, None) is None
    assert MapFrame.for_site("EPSG:3857", np.array([35.0, 139.5, 0.0])).epsg == 3857
    assert MapFrame.for_site(None, np.array([-33.9, 18.4, 0.0])).epsg == 32734
    assert MapFrame.for_site(None, np.array([85.0, 10.0, 0.0])).local  # beyond UTM: the local frame


def test_a_damaged_map_frame_record_is_a_one_line_error():
    """poses.json edited by hand or damaged: a text origin, an EPSG code PROJ does not
    know, a geographic one: InputError, not a ValueError or CRSError from below."""
    from prism3d.geo import MapFrame

    with pytest.raises(InputError, match="origin_lla: expected"):
        MapFrame.from_record({"origin_lla": "37.5 139.0"})
    for code, said in ((999999, "not a coordinate system PROJ knows"), (4326, "not a projected CRS")):
        with pytest.raises(InputError, match=said):
            MapFrame.from_record({"origin_lla": [37.5, 139.0, 10.0], "map_frame": {"epsg": code}})
    assert MapFrame.from_record({"origin_lla": [37.5, 139.0, 10.0], "map_frame": {"epsg": 32654}}).epsg == 32654


def test_a_raster_beyond_the_pixel_budget_is_refused_on_its_header(tmp_path, monkeypatch):
    from prism3d.io.geo import read_geotiff, write_geotiff

    p = tmp_path / "r.tif"
    write_geotiff(p, np.zeros((100, 100), np.float32), west=5e5, north=4e6, gsd=1.0,
                  crs_wkt=pyproj.CRS.from_epsg(32654).to_wkt("WKT1_GDAL"))
    assert read_geotiff(p)[0].shape == (100, 100)
    monkeypatch.setenv("PRISM3D_MAX_PIXELS", "1000")
    with pytest.raises(InputError, match="100x100 = 10,000 pixels, more than the 1,000 pixels limit"):
        read_geotiff(p)
