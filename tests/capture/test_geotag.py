"""GPS positions and focal lengths of photographs: ENU against known geodesy and an
independent implementation, position tables and EXIF on the real drone frames."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.capture.geotag import (enu_to_wgs84, exif_focal_px, exif_geotag, read_position_table,
                                    wgs84_to_enu)
from prism3d.errors import InputError

AERIAL = "aerial/snowpeak_internal_only"


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


def test_position_table_formats_and_bad_tables(tmp_path):
    t = tmp_path / "pos.csv"
    t.write_text("# a comment\nimage,lat,lon,alt\na.jpg,10.5,20.25,100\nb.jpg,10.5001,20.25,101\n")
    tags = read_position_table(t)
    assert list(tags) == ["a.jpg", "b.jpg"] and tags["b.jpg"].alt_m == 101 and tags["a.jpg"].heading_deg is None
    (tmp_path / "a.jpg").write_bytes(b"")
    with pytest.raises(InputError, match="not in .*b.jpg"):
        read_position_table(t, images_dir=tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text("image,lat,lon\na.jpg,1,2\n")
    with pytest.raises(InputError, match="no column for alt"):
        read_position_table(bad)
    bad.write_text("image,lat,lon,alt\na.jpg,1,x,3\n")
    with pytest.raises(InputError, match="row 2: lon"):
        read_position_table(bad)
    bad.write_text("image,lat,lon,alt\na.jpg,1,2,3\na.jpg,1,2,3\n")
    with pytest.raises(InputError, match="twice"):
        read_position_table(bad)


@pytest.mark.realdata
def test_real_geoinfo_table_and_exif(shared_data):
    """The drone's own table and its JPEGs' EXIF agree; the baseline 2188 -> 2189 in ENU
    matches pyproj's topocentric conversion of the same positions (E -27.238, N 23.486,
    U -0.347 m, computed independently with pyproj 3.7.2, docs/uav.md) to 1 cm."""
    d = shared_data / AERIAL
    tags = read_position_table(d / "geoinfo.txt", images_dir=d)
    assert sorted(tags) == ["IMG_2188.JPG", "IMG_2189.JPG", "IMG_2212.JPG", "IMG_2213.JPG"]
    a, b = tags["IMG_2188.JPG"], tags["IMG_2189.JPG"]
    assert a.alt_m == pytest.approx(261.0272827148)  # the ellipsoidal column, not AMSL
    enu = wgs84_to_enu([[b.lat_deg, b.lon_deg, b.alt_m]], [a.lat_deg, a.lon_deg, a.alt_m])[0]
    assert np.allclose(enu, [-27.238, 23.486, -0.347], atol=0.01), enu
    g = exif_geotag(d / "IMG_2188.JPG")
    assert g is not None
    assert abs(g.lat_deg - a.lat_deg) < 1e-8 and abs(g.lon_deg - a.lon_deg) < 1e-8
    assert abs(g.alt_m - a.alt_m) < 0.01
    # Canon IXUS 125 HS: 4.3 mm at 18962.963 px per inch of the sensor -> 3210.3 px
    assert exif_focal_px(d / "IMG_2188.JPG") == pytest.approx(4.3 * 18962.963 / 25.4, rel=1e-4)


def test_exif_absent_and_unreadable(tmp_path):
    from prism3d.io.images import write_image

    write_image(tmp_path / "x.png", np.zeros((4, 6, 3), dtype=np.uint8))
    assert exif_geotag(tmp_path / "x.png") is None and exif_focal_px(tmp_path / "x.png") is None
    (tmp_path / "y.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(InputError, match="cannot read"):
        exif_geotag(tmp_path / "y.jpg")
