"""Formats GIS tools open: LAS 1.4 / LAZ point clouds with colour and classes (laspy,
lazrs) and Cloud-Optimised GeoTIFF rasters (rasterio, GDAL), both with their coordinate
system, written atomically.

The coordinate systems they carry come from :mod:`prism3d.geo`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.io.images import max_pixels, pixel_count
from prism3d.io.atomic import atomic_path

__all__ = ["read_geotiff", "write_geotiff", "write_las"]


def write_las(path: str | Path, xyz: NDArray, rgb: NDArray | None = None, *, crs_wkt: str | None = None,
              scale_m: float = 0.001, system_identifier: str | None = None,
              classification: NDArray | None = None) -> None:
    """LAS 1.4 (point format 7: xyz, 16-bit RGB) at ``scale_m`` resolution, the CRS as
    an OGC WKT record; ``rgb`` uint8 (n, 3) or None (grey); ``classification`` (n,) ASPRS
    classes (0 never classified by default); ``system_identifier`` (at most 32
    characters) says how the points were made (e.g. that their scale is unknown). A
    ``.laz`` path is compressed (LASzip through laspy's lazrs backend)."""
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
    span = (p.max(axis=0) - header.offsets) / scale_m if len(p) else np.zeros(3)
    if (span > 2**31 - 1).any():
        raise InputError(f"points: span {span.max() * scale_m:.3g} m does not fit LAS integers at "
                         f"{scale_m:g} m resolution")
    las = laspy.LasData(header)
    las.x, las.y, las.z = p[:, 0], p[:, 1], p[:, 2]
    if classification is not None:
        k = np.asarray(classification)
        if k.shape != (len(p),) or (k < 0).any() or (k > 255).any():
            raise InputError(f"classification: expected ({len(p)},) classes 0-255, got shape {k.shape}")
        las.classification = k.astype(np.uint8)
    if rgb is not None:
        c16 = np.asarray(rgb, dtype=np.uint16) * 257
        las.red, las.green, las.blue = c16[:, 0], c16[:, 1], c16[:, 2]
    with atomic_path(path) as tmp:
        las.write(str(tmp), do_compress=Path(path).suffix.lower() == ".laz")


def write_geotiff(path: str | Path, raster: NDArray, *, west: float, north: float, gsd: float,
                  crs_wkt: str | None, nodata: float | None = None, band_names: list[str] | None = None,
                  tags: dict[str, str] | None = None, units: str | None = None) -> None:
    """A Cloud-Optimised GeoTIFF of a (H, W) or (H, W, bands) raster whose row 0 is the
    north edge: pixel (0, 0)'s top-left corner at (``west``, ``north``), square pixels of
    ``gsd`` (m); 512 px tiles, deflate, overviews halving down to one tile (averaged; a
    single integer band holds categories and takes the nearest); uint8 with 3 or 4 bands
    is an RGB(A) image, its 4th band marked alpha; ``units`` the bands' unit (``metre``);
    ``tags`` are written as GDAL metadata (e.g. ``SCALE=unknown``). GDAL's COG driver
    only copies a finished file, so the raster is written plain first beside the target."""
    import rasterio
    import rasterio.shutil
    from rasterio.enums import ColorInterp
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
                   transform=from_origin(west, north, gsd, gsd), **({"crs": crs_wkt} if crs_wkt else {}))
    if nodata is not None:
        profile["nodata"] = nodata
    rgb = a.dtype == np.uint8 and nb in (3, 4)
    if rgb:
        profile["photometric"] = "RGB"
        if nb == 4:
            profile["alpha"] = "YES"
    with atomic_path(path) as tmp:
        plain = tmp.with_name(tmp.name + ".plain.tif")
        try:
            with rasterio.open(plain, "w", **profile) as dst:
                dst.write(np.moveaxis(a, 2, 0))
                if tags:
                    dst.update_tags(**{str(k): str(v) for k, v in tags.items()})
                for k, name in enumerate(band_names or [], start=1):
                    dst.set_band_description(k, name)
                if units:
                    dst.units = [units] * nb
                if rgb and nb == 4:
                    dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]
            rasterio.shutil.copy(plain, tmp, driver="COG", COMPRESS="DEFLATE", BLOCKSIZE="512",
                                 OVERVIEWS="AUTO", RESAMPLING="NEAREST" if nb == 1 and a.dtype.kind in "iub"
                                 else "AVERAGE", BIGTIFF="IF_SAFER",
                                 PREDICTOR="YES" if a.dtype.kind == "f" else "NO")
        finally:
            plain.unlink(missing_ok=True)


def read_geotiff(path: str | Path) -> tuple[NDArray, dict]:
    """A GeoTIFF's bands (H, W[, bands]) and ``{"west", "north", "gsd", "crs_wkt",
    "nodata", "tags"}``."""
    import rasterio

    with rasterio.open(path) as src:
        n = int(src.width) * int(src.height)
        if n > max_pixels():  # checked on the header, before a band is decoded
            raise InputError(f"{path}: the raster declares {src.width}x{src.height} = {pixel_count(n)}, more than "
                             f"the {pixel_count(max_pixels())} limit (--max-pixels or PRISM3D_MAX_PIXELS raises it)")
        a = np.moveaxis(src.read(), 0, 2)
        t = src.transform
        meta = {"west": t.c, "north": t.f, "gsd": t.a, "crs_wkt": src.crs.to_wkt() if src.crs else None,
                "nodata": src.nodata, "tags": dict(src.tags())}
    return (a[..., 0] if a.shape[2] == 1 else a), meta
