"""Formats GIS tools open: LAS 1.4 point clouds with colour (laspy) and GeoTIFF rasters
(rasterio, GDAL), both with their coordinate system, written atomically.

The coordinate systems they carry come from :mod:`prism3d.geo`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path

__all__ = ["read_geotiff", "write_geotiff", "write_las"]


def write_las(path: str | Path, xyz: NDArray, rgb: NDArray | None = None, *, crs_wkt: str | None = None,
              scale_m: float = 0.001, system_identifier: str | None = None) -> None:
    """LAS 1.4 (point format 7: xyz, 16-bit RGB) at ``scale_m`` resolution, the CRS as
    an OGC WKT record; ``rgb`` uint8 (n, 3) or None (grey); ``system_identifier`` (at
    most 32 characters) says how the points were made (e.g. that their scale is unknown)."""
    import laspy

    p = check_array(xyz, "points", ndim=2).astype(np.float64)
    if p.shape[1] != 3 or not np.isfinite(p).all():
        raise InputError(f"points: expected finite (n, 3) coordinates, got shape {p.shape}")
    if rgb is not None:
        c = check_array(rgb, "colours", ndim=2)
        if c.shape != p.shape:
            raise InputError(f"colours: expected {p.shape}, got {c.shape}")
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales = np.full(3, scale_m)
    header.offsets = np.floor(p.min(axis=0)) if len(p) else np.zeros(3)
    header.generating_software = "prism3d"
    if system_identifier is not None:
        if len(system_identifier) > 32:
            raise InputError(f"system_identifier: at most 32 characters, got {len(system_identifier)}")
        header.system_identifier = system_identifier
    if crs_wkt is not None:
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(crs_wkt))
        header.global_encoding.wkt = True
    las = laspy.LasData(header)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    if rgb is not None:
        c16 = np.asarray(rgb, dtype=np.uint16) * 257
        las.red, las.green, las.blue = c16[:, 0], c16[:, 1], c16[:, 2]
    with atomic_path(path) as tmp:
        las.write(str(tmp))


def write_geotiff(path: str | Path, raster: NDArray, *, west: float, north: float, gsd: float,
                  crs_wkt: str | None, nodata: float | None = None, band_names: list[str] | None = None,
                  tags: dict[str, str] | None = None) -> None:
    """A GeoTIFF of a (H, W) or (H, W, bands) raster whose row 0 is the north edge:
    pixel (0, 0)'s top-left corner at (``west``, ``north``), square pixels of ``gsd``
    (m); deflate-compressed, tiled; uint8 with 3 or 4 bands is an RGB(A) image;
    ``tags`` are written as GDAL metadata (e.g. ``SCALE=unknown``)."""
    import rasterio
    from rasterio.transform import from_origin

    a = np.asarray(raster)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError(f"raster: expected (H, W) or (H, W, bands), got shape {np.shape(raster)}")
    if not (np.isfinite(gsd) and gsd > 0 and np.isfinite(west) and np.isfinite(north)):
        raise InputError("raster: the origin must be finite and the pixel size > 0")
    h, w, nb = a.shape
    profile = dict(driver="GTiff", height=h, width=w, count=nb, dtype=a.dtype.name,
                   transform=from_origin(west, north, gsd, gsd), compress="deflate",
                   tiled=w >= 256 and h >= 256, **({"crs": crs_wkt} if crs_wkt else {}))
    if nodata is not None:
        profile["nodata"] = nodata
    if a.dtype == np.uint8 and nb in (3, 4):
        profile["photometric"] = "RGB"
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(np.moveaxis(a, 2, 0))
            if tags:
                dst.update_tags(**{str(k): str(v) for k, v in tags.items()})
            for k, name in enumerate(band_names or [], start=1):
                dst.set_band_description(k, name)
            if a.dtype == np.uint8 and nb == 4:
                from rasterio.enums import ColorInterp

                dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]


def read_geotiff(path: str | Path) -> tuple[NDArray, dict]:
    """A GeoTIFF's bands (H, W[, bands]) and ``{"west", "north", "gsd", "crs_wkt",
    "nodata", "tags"}``."""
    import rasterio

    with rasterio.open(path) as src:
        a = np.moveaxis(src.read(), 0, 2)
        t = src.transform
        meta = {"west": t.c, "north": t.f, "gsd": t.a, "crs_wkt": src.crs.to_wkt() if src.crs else None,
                "nodata": src.nodata, "tags": dict(src.tags())}
    return (a[..., 0] if a.shape[2] == 1 else a), meta
