"""GPS positions and focal lengths of photographs: position tables and EXIF on the real
drone frames."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.capture.geotag import exif_focal_px, exif_geotag, read_position_table
from prism3d.errors import InputError
from prism3d.geo import wgs84_to_enu

AERIAL = "aerial/snowpeak_internal_only"


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
