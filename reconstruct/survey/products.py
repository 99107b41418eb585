"""What a survey writes from its fused surface: DSM, ground, nDSM, true orthophoto
(GeoTIFF), cloud (PLY, LAS), poses.json and the overview figure; the frames' overlap.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError
from prism3d.geo import MapFrame
from prism3d.io.atomic import atomic_path, atomic_write_text
from prism3d.io.geo import write_geotiff, write_las
from prism3d.io.ply import write_ply
from prism3d.reconstruct.survey.cloud import DenseCloud, cells_of, dense_cloud
from prism3d.reconstruct.survey.dsm import MAX_CELLS, normalised_dsm
from prism3d.reconstruct.survey.mapgrid import Grid, GridWarp, map_grid, resample
from prism3d.reconstruct.survey.model import (
    SURVEY_SCHEMA_VERSION,
    FusedSurface,
    SurveyState,
)
from prism3d.reconstruct.survey.ortho import MAX_ORTHO_CELLS, true_orthophoto

__all__ = ["draw_survey", "footprint", "overlap_coverage", "overlap_mask", "write_products"]


#: Points of the cloud at most this high above the ground surface are ASPRS class 2
#: (ground), the rest 1 (unclassified): the ground filter's own base tolerance.
GROUND_CLASS_M = 0.3


def write_products(stage: Path, fused: FusedSurface, st: SurveyState,
                   progress: Callable[[int, int, str], None] | None = None) -> dict[str, Any]:
    """Every product of a survey into the staging folder ``stage`` (the caller moves it in
    place whole): GeoTIFFs and the LAS/LAZ cloud on the map grid of ``--crs`` (UTM by
    default; model units and no CRS without GPS), cloud.ply in the local frame, the
    figure and poses.json, whose summary it returns."""
    frame = MapFrame.for_site(st.options.crs, st.origin)
    if progress:
        progress(0, 1, "DSM, ground, nDSM")
    ground, ndsm, ortho, grids = _write_rasters(stage, fused, st, frame, progress)
    if progress:
        progress(0, 1, "cloud")
    cloud = _write_clouds(stage, fused, ground, frame, st, progress)
    doc = _poses_doc(stage, fused, st, ground, ortho, frame, grids)
    doc["cloud"] = {"points": int(len(cloud.xyz)), "source": cloud.source, "spacing": cloud.spacing,
                    "pairs_used": cloud.pairs_used}
    atomic_write_text(stage / "poses.json", json.dumps(doc, indent=1))
    draw_survey(stage / "survey.png", fused, ndsm, st.T_enu, st.scaled)
    n_ok = sum(r.ok for r in st.pairs)
    return {"n_frames": len(st.paths), "n_registered": int(sum(st.sfm.registered)),
            "reprojection_rms_px": float(st.sfm.reprojection_rms_px), "scale": doc["scale"],
            "pairs_ok": n_ok, "pairs_skipped": len(st.pairs) - n_ok, "cell": fused.cell,
            "dsm_cells": int(np.isfinite(fused.dsm).sum()), "overlap_filled_fraction": doc["dsm"]["overlap_filled_fraction"],
            "crs": None if frame is None else frame.name}


def _write_rasters(stage: Path, fused: FusedSurface, st: SurveyState, frame: MapFrame | None,
                   progress: Callable[[int, int, str], None] | None) -> tuple[NDArray, NDArray, Any, dict[str, Grid]]:
    """dsm, ground, ndsm, ortho and ortho_quality GeoTIFFs on the map grid; returns ground
    and nDSM on the survey's ENU grid, the orthophoto and the map grids written."""
    scaled = frame is not None
    tags = {"SCALE": st.scale, "SOFTWARE": "prism3d survey",
            "HEIGHTS": "metres above the WGS84 ellipsoid" if scaled else "model units, frame levelled on the ground",
            "VERTICAL_DATUM": "WGS84 ellipsoid" if scaled else "none"}
    cell = fused.cell
    ground, ndsm = normalised_dsm(fused.dsm * (1000.0 if scaled else 1.0), cell * (1000.0 if scaled else 1.0))
    if scaled:
        ground, ndsm = ground / 1000.0, ndsm / 1000.0
    enu = Grid(fused.west, fused.north, cell, fused.dsm.shape)
    K, dist = np.asarray(st.sfm.K, dtype=np.float64), np.asarray(st.sfm.dist, dtype=np.float64)
    frames = [(str(st.paths[k]), st.T_enu[k]) for k in sorted(st.T_enu)]
    if frame is None or frame.local:
        dsm_m, ground_m, ndsm_m, mg, on_map = fused.dsm, ground, ndsm, enu, None
    else:
        z0 = float(np.nanmedian(ground)) if np.isfinite(ground).any() else 0.0
        mg = map_grid(frame, enu, cell, z0, max_cells=MAX_CELLS)
        warp = GridWarp(frame, mg, z0)
        dh = warp.height_offset(0, mg.shape[0], 0, mg.shape[1]).astype(np.float32)
        dsm_m = resample(fused.dsm, enu, warp, mode="linear") + dh
        ground_m = resample(ground, enu, warp, mode="linear") + dh
        ndsm_m = dsm_m - ground_m

        def on_map(g: float) -> tuple[tuple[float, float, int, int], Any]:
            og = map_grid(frame, enu, g, z0, max_cells=MAX_ORTHO_CELLS)
            ow = GridWarp(frame, og, z0)
            return (og.west, og.north, og.shape[0], og.shape[1]), ow.enu_xy
    crs = None if frame is None else frame.crs_wkt
    units = "metre" if scaled else None
    common = dict(west=mg.west, north=mg.north, gsd=mg.cell, crs_wkt=crs, tags=tags, units=units)
    write_geotiff(stage / "dsm.tif", dsm_m, nodata=float("nan"), band_names=["height"], **common)
    write_geotiff(stage / "ground.tif", ground_m.astype(np.float32), nodata=float("nan"), band_names=["ground"], **common)
    write_geotiff(stage / "ndsm.tif", ndsm_m.astype(np.float32), nodata=float("nan"),
                  band_names=["height above ground"], **common)
    ortho = true_orthophoto(fused.dsm, fused.west, fused.north, cell, frames, K, dist, tuple(st.sfm.size),
                            gsd=st.options.ortho_gsd_m, on_map=on_map, progress=progress)
    ocommon = dict(common, west=ortho.west, north=ortho.north, gsd=ortho.gsd, units=None)
    write_geotiff(stage / "ortho.tif", ortho.rgba, **ocommon)
    write_geotiff(stage / "ortho_quality.tif", ortho.quality, nodata=0, band_names=[
        "1 measured surface, 2 interpolated surface, 3 unseen, colour carried in"], **ocommon)
    og = Grid(ortho.west, ortho.north, ortho.gsd, ortho.rgba.shape[:2])
    return ground, ndsm, ortho, {"dsm": mg, "ortho": og}


def _write_clouds(stage: Path, fused: FusedSurface, ground: NDArray, frame: MapFrame | None, st: SurveyState,
                  progress: Callable[[int, int, str], None] | None) -> DenseCloud:
    """cloud.ply (local frame) and cloud.las / cloud.laz (map frame) at the matching's density
    (:func:`~prism3d.reconstruct.survey.cloud.dense_cloud`), with colour; in the LAS, ASPRS
    class 2 (ground) within :data:`GROUND_CLASS_M` of the ground surface, else 1
    (unclassified; all of them without GPS)."""
    o = st.options
    cloud = dense_cloud(st.pairs, st.T_enu, [str(p) for p in st.paths], np.asarray(st.sfm.K, dtype=np.float64),
                        np.asarray(st.sfm.dist, dtype=np.float64), st.factor, fused, spacing=o.cloud_spacing_m,
                        progress=progress)
    xyz, col, cell = cloud.xyz, cloud.rgb, fused.cell
    scaled = frame is not None
    what = f"one point per {cell:g} cell" if cloud.source == "dsm cells" else \
        "every matched pixel" if cloud.spacing is None else f"one point per {cloud.spacing:.3g} cube"
    write_ply(stage / "cloud.ply", xyz, colors=col, double=True,
              comments=[f"prism3d survey: dense cloud, {what}",
                        "frame: local east-north-up, metres (poses.json)" if scaled else "frame: model, scale unknown"])
    cls = np.ones(len(xyz), dtype=np.uint8)
    if scaled:  # without GPS there is no metre to measure the tolerance in: all unclassified
        rr, cc = cells_of(fused, xyz)
        rr, cc = np.clip(rr, 0, fused.dsm.shape[0] - 1), np.clip(cc, 0, fused.dsm.shape[1] - 1)
        above = xyz[:, 2] - ground[rr, cc]
        cls[np.isfinite(above) & (above <= GROUND_CLASS_M)] = 2
    pts = xyz if frame is None else frame.enu_to_map(xyz)
    write_las(stage / ("cloud.laz" if o.laz else "cloud.las"), pts, col, crs_wkt=None if frame is None else frame.crs_wkt,
              scale_m=min(0.001, cell / 100.0), classification=cls,
              system_identifier="prism3d survey" if scaled else "prism3d survey: scale unknown")
    return cloud


def _pair_entries(stage: Path, fused: FusedSurface, st: SurveyState, ground: NDArray) -> tuple[list[dict], float]:
    """poses.json's pair entries (each ok pair's depth map written to depth/) and the
    share of the frames' overlap the DSM fills."""
    depth_dir = stage / "depth"
    depth_dir.mkdir()
    per_pair, overlap_filled = overlap_coverage([(r.i, r.j) for r in st.pairs], st.T_enu, np.asarray(st.sfm.K, dtype=np.float64),
                                                st.sfm.size, float(np.nanmedian(ground)), fused)
    pairs = []
    for r in st.pairs:
        entry = r.record()
        entry["frames"] = [st.shown[r.i], st.shown[r.j]]
        if (r.i, r.j) in per_pair:
            entry["overlap_filled_fraction"] = per_pair[(r.i, r.j)]
        if r.ok:
            name = f"{st.paths[r.i].stem}__{st.paths[r.j].stem}.npz"
            np.savez_compressed(depth_dir / name, depth=r.depth, K=np.asarray(r.K_depth), T_enu_cam=st.T_enu[r.i])
            entry["depth_map"] = f"depth/{name}"
        pairs.append(entry)
    return pairs, overlap_filled


def _frame_entries(st: SurveyState) -> list[dict]:
    """poses.json's frame entries: image, COLMAP name, pose, GPS position and residual."""
    frames = []
    for k in range(len(st.paths)):
        fr: dict[str, Any] = {"image": st.shown[k], "colmap_name": st.sfm.model_names[k],
                              "registered": bool(st.sfm.registered[k]),
                              "T_enu_cam": st.T_enu[k].tolist() if k in st.T_enu else None}
        if st.gps_enu is not None:
            fr["gps_enu"] = [float(v) for v in st.gps_enu[k]]
            if k in st.T_enu:
                fr["gps_residual_m"] = float(np.linalg.norm(st.T_enu[k][:3, 3] - st.gps_enu[k]))
        frames.append(fr)
    return frames


def _poses_doc(stage: Path, fused: FusedSurface, st: SurveyState, ground: NDArray, ortho: Any,
               frame: MapFrame | None, grids: dict[str, Grid]) -> dict[str, Any]:
    """The survey's record (poses.json; docs/formats.md)."""
    pairs, overlap_filled = _pair_entries(stage, fused, st, ground)
    sfm, o, shown = st.sfm, st.options, st.shown
    return {
        "schema_version": SURVEY_SCHEMA_VERSION,
        "frames": _frame_entries(st),
        "reprojection_rms_px": float(sfm.reprojection_rms_px),
        "n_observations": int(sfm.n_observations),
        "n_sparse_points": int(len(sfm.points)),
        "scale": st.scale,
        "units": "m" if st.scaled else "model units (scale unknown)",
        "frame": ("local east-north-up at the origin (x east, y north, z up; heights above the WGS84 "
                  "ellipsoid); T_enu_cam maps OpenCV camera coordinates (x right, y down, z forward)")
        if st.scaled else "the model levelled on its ground (z up), camera 1 above the origin; scale unknown",
        "origin_lla": None if st.origin is None else [float(v) for v in st.origin],
        "crs_wkt": None if frame is None else frame.crs_wkt,
        "map_frame": None if frame is None else frame.record(),
        "gps_source": st.gps_source,
        "georeference": {"method": st.geo.method, "scale": st.geo.s, "residual_rms_m": st.geo.residual_rms_m,
                         "adjustment": getattr(sfm, "georeferencing", {})},
        "camera": {"model": {"RADIAL": "RADIAL (f, cx, cy, k1, k2)", "OPENCV": "OPENCV (fx, fy, cx, cy, k1, k2, p1, p2)"}
                   .get(getattr(sfm, "camera_model", "RADIAL"), str(getattr(sfm, "camera_model", "RADIAL"))),
                   "choice": getattr(sfm, "camera_choice", {}), "start": st.calib_source, "refined": st.refined,
                   "self_calibration": getattr(sfm, "self_calibration", {}),
                   "K": np.asarray(sfm.K).tolist(), "dist": np.asarray(sfm.dist).tolist(), "size": list(sfm.size)},
        "dense": {"downscale": st.factor, "pair_steps": list(o.pair_steps), "pairs": pairs},
        "ortho": {"gsd": ortho.gsd, "shape": list(ortho.rgba.shape[:2]), "west": ortho.west, "north": ortho.north,
                  "cells_per_frame": {shown[k]: v for k, v in sorted(ortho.cells_per_frame.items())},
                  "interpolated_surface_fraction": float((ortho.quality == 2).sum() / max(1, (ortho.quality > 0).sum())),
                  "unseen_fraction": float((ortho.quality == 3).sum() / max(1, (ortho.quality > 0).sum()))},
        "dsm": {"cell": fused.cell, "west": grids["dsm"].west, "north": grids["dsm"].north,
                "shape": list(grids["dsm"].shape),
                "local_grid": {"west": fused.west, "north": fused.north, "shape": list(fused.dsm.shape)},
                "filled_cells": int(np.isfinite(fused.dsm).sum()), "cells_seen_by_2_or_more_pairs": int((fused.seen >= 2).sum()),
                "overlap_filled_fraction": overlap_filled},
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(o).items()},
    }


def overlap_coverage(pairs: Sequence[tuple[int, int]], T_enu: dict[int, NDArray], K: NDArray, size: tuple[int, int],
                     ground_z: float, fused: FusedSurface) -> tuple[dict[tuple[int, int], float], float]:
    """The share of each pair of frames' ground overlap (the two frames' footprints on the plane
    ``z = ground_z`` intersected) holding a fused height, and of the union of those
    overlaps; on the DSM's lattice widened to hold every footprint whole."""
    cell = fused.cell
    finite = np.isfinite(fused.dsm)
    quads = {(i, j): [footprint(T_enu[i], K, size, ground_z), footprint(T_enu[j], K, size, ground_z)]
             for i, j in pairs if i in T_enu and j in T_enu}
    if not quads:
        return {}, 0.0
    allq = np.concatenate([np.concatenate(q) for q in quads.values()])
    pad_w = max(0, int(math.ceil((fused.west - allq[:, 0].min()) / cell)))
    pad_n = max(0, int(math.ceil((allq[:, 1].max() - fused.north) / cell)))
    H0, W0 = finite.shape
    Hc = max(H0 + pad_n, int(math.ceil((fused.north + pad_n * cell - allq[:, 1].min()) / cell)))
    Wc = max(W0 + pad_w, int(math.ceil((allq[:, 0].max() - fused.west + pad_w * cell) / cell)))
    if Hc * Wc > 800_000_000:
        raise InputError("survey: the frames' footprints are far larger than the DSM; poses or GPS are wrong")
    filled = np.zeros((Hc, Wc), bool)
    filled[pad_n:pad_n + H0, pad_w:pad_w + W0] = finite
    union = np.zeros((Hc, Wc), bool)
    per_pair = {}
    for key, q in quads.items():
        m = overlap_mask(q, (Hc, Wc), fused.west - pad_w * cell, fused.north + pad_n * cell, cell)
        union |= m
        per_pair[key] = round(float(filled[m].mean()) if m.any() else 0.0, 4)
    return per_pair, round(float(filled[union].mean()) if union.any() else 0.0, 4)


def footprint(T_enu_cam: NDArray, K: NDArray, size: tuple[int, int], ground_z: float) -> NDArray[np.float64]:
    """The frame's corners (4, 2) on the horizontal plane ``z = ground_z`` (east, north)."""
    w, h = size
    uv = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float64)
    rays = np.c_[(uv - [K[0, 2], K[1, 2]]) / [K[0, 0], K[1, 1]], np.ones(4)] @ T_enu_cam[:3, :3].T
    c = T_enu_cam[:3, 3]
    if np.any(rays[:, 2] >= 0):
        raise InputError("survey: a frame's corner looks above the horizon; not a nadir survey")
    s = (ground_z - c[2]) / rays[:, 2]
    return c[:2] + s[:, None] * rays[:, :2]


def overlap_mask(quads: Sequence[NDArray], shape: tuple[int, int], west: float, north: float,
                 cell: float) -> NDArray[np.bool_]:
    """Cells of a (H, W) grid inside the intersection of convex ground quads (n, 4, 2)."""
    poly = np.asarray(quads[0], dtype=np.float32)
    for q in quads[1:]:
        area, inter = cv2.intersectConvexConvex(poly, np.asarray(q, dtype=np.float32))
        if area <= 0 or inter is None:
            return np.zeros(shape, bool)
        poly = inter.reshape(-1, 2)
    px = np.c_[(poly[:, 0] - west) / cell - 0.5, (north - poly[:, 1]) / cell - 0.5]
    m = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(m, np.round(px * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def draw_survey(path: Path, fused: FusedSurface, ndsm: NDArray, T_enu: dict[int, NDArray], scaled: bool) -> None:
    """The orthophoto, the DSM (hill-shaded) and the nDSM side by side, cameras marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    unit = "m" if scaled else "units"
    H, W = fused.dsm.shape
    ext = (fused.west, fused.west + W * fused.cell, fused.north - H * fused.cell, fused.north)
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), constrained_layout=True)
    rgba = np.dstack([fused.rgb, np.where(np.isfinite(fused.dsm), 255, 0).astype(np.uint8)])
    axes[0].imshow(rgba, extent=ext)
    axes[0].set_title("orthophoto")
    d = np.where(np.isfinite(fused.dsm), fused.dsm, np.nanmedian(fused.dsm))
    gy, gx = np.gradient(d, fused.cell)
    shade = np.clip(0.5 + 0.5 * (-gx - gy) / np.sqrt(1 + gx**2 + gy**2), 0, 1)
    lo, hi = (np.nanpercentile(fused.dsm, [1, 99]) if np.isfinite(fused.dsm).any() else (0.0, 1.0))
    im = axes[1].imshow(np.where(np.isfinite(fused.dsm), fused.dsm, np.nan), extent=ext, cmap="terrain",
                        vmin=lo, vmax=max(hi, lo + 1e-6))
    axes[1].imshow(np.where(np.isfinite(fused.dsm), shade, np.nan), extent=ext, cmap="gray", alpha=0.35)
    fig.colorbar(im, ax=axes[1], shrink=0.8, label=f"height ({unit})")
    axes[1].set_title("DSM")
    lim = float(np.nanpercentile(ndsm, 99.5)) if np.isfinite(ndsm).any() else 1.0
    im2 = axes[2].imshow(ndsm, extent=ext, cmap="magma", vmin=0, vmax=max(lim, 1e-6))
    fig.colorbar(im2, ax=axes[2], shrink=0.8, label=f"above ground ({unit})")
    axes[2].set_title("normalised DSM")
    C = np.array([T[:3, 3] for T in T_enu.values()])
    for ax in axes:
        ax.plot(C[:, 0], C[:, 1], "c.-", ms=6, lw=0.8)
        ax.set_xlabel(f"east ({unit})")
    axes[0].set_ylabel(f"north ({unit})")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
