"""DSM, orthophoto and normalised DSM from points, against the surface they were drawn
from; LAS and GeoTIFF written and read back with their coordinate system."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.reconstruct.survey.dsm import grid_points, normalised_dsm

VEHICLE = (10.0, 5.0, 4.5, 2.0, 1.8)  # centre x, y, length, width, height (m)


def _surface(x, y):
    return 100.0 + 0.04 * x + 0.02 * y + 0.3 * np.sin(x / 9.0)


def _scene(rng, n=400_000):
    x = rng.uniform(-30, 30, n)
    y = rng.uniform(-20, 20, n)
    z = _surface(x, y)
    cx, cy, L, W, H = VEHICLE
    on = (np.abs(x - cx) < L / 2) & (np.abs(y - cy) < W / 2)
    z = np.where(on, _surface(x, y) + H, z)
    rgb = np.where(on[:, None], [200, 30, 30], [40, 120, 40]).astype(np.uint8)
    return np.c_[x, y, z], rgb, on


def test_dsm_follows_the_surface_and_the_vehicle_stands_out():
    rng = np.random.default_rng(0)
    xyz, rgb, on = _scene(rng)
    g = grid_points(xyz, rgb, 0.25)
    H, W = g.dsm.shape
    ext = xyz.max(axis=0) - xyz.min(axis=0)
    assert (H, W) == (int(ext[1] // 0.25) + 1, int(ext[0] // 0.25) + 1)  # the points' extent
    assert g.west == xyz[:, 0].min() and g.north == xyz[:, 1].max()
    rows, cols = np.mgrid[0:H, 0:W]
    cx = g.west + (cols + 0.5) * g.gsd
    cy = g.north - (rows + 0.5) * g.gsd
    truth = _surface(cx, cy)
    vx, vy, L, Wd, Ht = VEHICLE
    inside = (np.abs(cx - vx) < L / 2 - 0.3) & (np.abs(cy - vy) < Wd / 2 - 0.3)
    edge = (np.abs(cx - vx) < L / 2 + 0.3) & (np.abs(cy - vy) < Wd / 2 + 0.3)
    full = np.isfinite(g.dsm) & ~edge
    assert full.mean() > 0.9
    err = g.dsm[full] - truth[full]
    assert np.median(np.abs(err)) < 0.01 and np.sqrt(np.mean(err ** 2)) < 0.02  # 0.25 m cells, 10 cm slopes
    ground, ndsm = normalised_dsm(g.dsm * 1000.0, g.gsd * 1000.0)
    assert np.nanmedian(np.abs(ndsm[full])) < 50  # mm: open ground is at 0
    assert abs(np.nanmedian(ndsm[inside]) / 1000.0 / Ht - 1) < 0.05  # the 5 % on heights
    assert (g.ortho[inside][:, :3] == [200, 30, 30]).all() and (g.ortho[g.count == 0][:, 3] == 0).all()


def test_bad_input():
    with pytest.raises(InputError, match="cell size"):
        grid_points(np.zeros((5, 3)), None, 0.0)
    with pytest.raises(InputError, match="none finite"):
        grid_points(np.full((5, 3), np.nan), None, 1.0)
    with pytest.raises(InputError, match="budget"):
        grid_points(np.array([[0, 0, 0], [1e6, 1e6, 0]], dtype=float), None, 0.01)
    with pytest.raises(InputError, match="colours"):
        grid_points(np.zeros((5, 3)), np.zeros((4, 3)), 1.0)


def test_las_and_geotiff_round_trip_with_their_crs(tmp_path):
    import laspy

    from prism3d.geo import local_enu_crs_wkt
    from prism3d.io.geo import read_geotiff, write_geotiff, write_las

    rng = np.random.default_rng(1)
    xyz, rgb, _ = _scene(rng, 20_000)
    wkt = local_enu_crs_wkt(37.5434422, 139.0427824)
    write_las(tmp_path / "cloud.las", xyz, rgb, crs_wkt=wkt)
    las = laspy.read(tmp_path / "cloud.las")
    back = np.c_[las.x, las.y, las.z]
    assert np.abs(back - xyz).max() <= 0.0005 + 1e-9
    assert (np.c_[las.red, las.green, las.blue] // 257 == rgb).all()
    assert las.header.version.minor == 4 and las.header.global_encoding.wkt
    assert any("Orthographic" in str(getattr(v, "string", "")) or "ortho" in str(getattr(v, "string", "")).lower()
               for v in las.header.vlrs)
    crs = las.header.parse_crs()  # laspy through pyproj, as PDAL and QGIS read it
    assert crs is not None and crs.is_projected and crs.axis_info[0].unit_name == "metre"
    assert crs.coordinate_operation.method_name.lower().startswith("orthographic")
    g = grid_points(xyz, rgb, 0.5)
    write_geotiff(tmp_path / "dsm.tif", g.dsm, west=g.west, north=g.north, gsd=g.gsd, crs_wkt=wkt, nodata=np.nan)
    write_geotiff(tmp_path / "ortho.tif", g.ortho, west=g.west, north=g.north, gsd=g.gsd, crs_wkt=wkt)
    dsm, meta = read_geotiff(tmp_path / "dsm.tif")
    np.testing.assert_array_equal(dsm, g.dsm)
    assert meta["west"] == g.west and meta["north"] == g.north and meta["gsd"] == g.gsd
    assert "Orthographic" in meta["crs_wkt"]
    ortho, _ = read_geotiff(tmp_path / "ortho.tif")
    np.testing.assert_array_equal(ortho, g.ortho)
    with pytest.raises(InputError, match="raster"):
        write_geotiff(tmp_path / "bad.tif", np.zeros((0, 3)), west=0, north=0, gsd=1, crs_wkt=None)
    assert not (tmp_path / "bad.tif").exists()


def test_unscaled_products_say_so(tmp_path):
    """Without GPS a survey's rasters and cloud carry no CRS and say their scale is unknown."""
    import laspy

    from prism3d.io.geo import read_geotiff, write_geotiff, write_las

    write_geotiff(tmp_path / "dsm.tif", np.ones((4, 5), np.float32), west=0, north=0, gsd=0.1, crs_wkt=None,
                  tags={"SCALE": "unknown"})
    a, meta = read_geotiff(tmp_path / "dsm.tif")
    assert meta["crs_wkt"] is None and meta["tags"]["SCALE"] == "unknown"
    write_las(tmp_path / "c.las", np.zeros((3, 3)), system_identifier="prism3d survey: scale unknown")
    las = laspy.read(tmp_path / "c.las")
    assert las.header.system_identifier == "prism3d survey: scale unknown"
    with pytest.raises(InputError, match="32 characters"):
        write_las(tmp_path / "d.las", np.zeros((3, 3)), system_identifier="x" * 33)
    assert not (tmp_path / "d.las").exists()
