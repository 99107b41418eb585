"""Targets from the air: vehicles found in a survey's orthophoto and normalised DSM.

:func:`detect_in_survey` reads a survey folder onto the aerial recogniser's grid (the
orthophoto at the photographs' own GSD and the nDSM resampled to it), runs the recogniser
(:class:`~prism3d.atr.aerial.AerialModel`) over the surveyed area that could hold a
vehicle (cells standing out of the ground or without a height, and their surroundings) and
writes one GeoJSON Feature per vehicle in WGS84. The earlier nDSM-only method (below, the
baseline of the benchmarks) is kept as it was:

Each object standing out of the nDSM (connected cells above ``min_height_m``) is
measured (length and width of its minimum-area rectangle, height) and compared with
nadir height templates: the class meshes (CAD or scanned) ray-cast from straight above
at the survey's cell size, length along x. The candidate's height chip is turned onto
its long axis and correlated with each template in both directions (normalised
cross-correlation over the template's window, a few cells of play); the score is the
best correlation of a class whose size fits. Detections go out as GeoJSON in WGS84
(RFC 7946) when the survey is georeferenced. Method and figures: docs/uav.md.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyproj
from numpy.typing import NDArray

from prism3d.atr.aerial import DEFAULT_THRESHOLD, VehicleDetection
from prism3d.capture.render import RaycastRenderer
from prism3d.checks import check_outputs_not_inputs
from prism3d.errors import InputError
from prism3d.geo import MapFrame, enu_to_wgs84
from prism3d.io.atomic import atomic_paths, atomic_write_text
from prism3d.reconstruct.survey.model import METRIC_SCALES
from prism3d.io.geo import read_geotiff

__all__ = ["NadirTemplate", "SurveyScene", "TemplateCandidate", "check_survey_request", "detect_in_survey", "draw_survey_detections", "find_vehicles",
           "load_survey_scene", "nadir_templates", "write_geojson"]

#: A class fits a candidate when the candidate's length, width and height are within
#: these factors of the class's (occlusion, trees and the DSM's smoothing shrink or grow them).
SIZE_TOLERANCE = (0.65, 1.35)


@dataclass(frozen=True)
class NadirTemplate:
    """A class seen from straight above: ``heights`` (h, w) m above its base at ``cell``
    m per cell, length along x (columns), centred; its bounding ``length``/``width``/
    ``height`` in m."""

    name: str
    cls: str
    heights: NDArray[np.float32]
    cell: float
    length: float
    width: float
    height: float


def nadir_templates(items: Sequence[tuple[str, Any]], cell_m: float, *, units_per_m: float = 1000.0
                    ) -> list[NadirTemplate]:
    """Top-down height templates of ``(name, SceneMesh)`` items (vertices in mm, z up,
    as the target library and database keep them) at ``cell_m``; each mesh's long axis
    is turned onto x first."""
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise InputError(f"cell: expected > 0 m, got {cell_m}")
    out = []
    for name, mesh in items:
        V = np.asarray(mesh.vertices, dtype=np.float64) / units_per_m
        xy = V[:, :2] - V[:, :2].mean(axis=0)
        evals, evecs = np.linalg.eigh(np.cov(xy.T))
        ax = evecs[:, int(np.argmax(evals))]
        a = math.atan2(ax[1], ax[0])
        T = np.eye(4)
        T[:2, :2] = [[math.cos(-a), -math.sin(-a)], [math.sin(-a), math.cos(-a)]]
        Vr = V @ T[:3, :3].T
        lo, hi = Vr.min(axis=0), Vr.max(axis=0)
        ctr = (lo + hi) / 2.0
        T[:3, 3] = -np.array([ctr[0], ctr[1], lo[2]])
        T[:3, 3] *= units_per_m
        r = RaycastRenderer([(mesh, T)])
        half = (hi - lo)[:2] / 2.0 + 2 * cell_m
        nx, ny = int(math.ceil(2 * half[0] / cell_m)) | 1, int(math.ceil(2 * half[1] / cell_m)) | 1
        xs = (np.arange(nx) - nx // 2) * cell_m
        ys = (ny // 2 - np.arange(ny)) * cell_m  # row 0 north (+y), as a DSM
        X, Y = np.meshgrid(xs, ys)
        top = (hi[2] - lo[2] + 1.0) * units_per_m
        o = np.c_[X.ravel() * units_per_m, Y.ravel() * units_per_m, np.full(X.size, top)]
        d = np.tile([0.0, 0.0, -1.0], (X.size, 1))
        hits = r.cast(o, d, normalized=True)
        h = np.where(np.isfinite(hits.t), (top - hits.t) / units_per_m, 0.0).reshape(ny, nx)
        ext = hi - lo
        out.append(NadirTemplate(name, str(mesh.metadata.get("class", name)), h.astype(np.float32), float(cell_m),
                                 float(ext[0]), float(ext[1]), float(ext[2])))
    return out


def _ncc(a: NDArray, b: NDArray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else -1.0


def _best_match(chip: NDArray, tpl: NDArray, play: int) -> float:
    """Best NCC of ``tpl`` against ``chip`` (larger by ``play`` cells on each side),
    over shifts and both directions along the long axis."""
    th, tw = tpl.shape
    best = -1.0
    for t in (tpl, tpl[::-1, ::-1]):
        for dy in range(2 * play + 1):
            for dx in range(2 * play + 1):
                w = chip[dy:dy + th, dx:dx + tw]
                if w.shape == t.shape:
                    best = max(best, _ncc(w, t))
    return best


@dataclass(frozen=True)
class TemplateCandidate:
    """An object standing out of an nDSM, as :func:`find_vehicles` measures it: map
    position ``x``, ``y`` (m), heading of its long axis (deg clockwise from north, mod 180),
    length, width, height (m) and area (m^2), the best-fitting class and template (None:
    no class fits its size) and ``score``, their height-shape correlation (-1: none fits)."""

    x: float
    y: float
    heading_deg: float
    length_m: float
    width_m: float
    height_m: float
    area_m2: float
    class_name: str | None
    template: str | None
    score: float

    def to_record(self) -> dict[str, Any]:
        """The candidate as a :func:`write_geojson` record (``class`` for ``class_name``)."""
        return {"x": self.x, "y": self.y, "heading_deg": self.heading_deg, "length_m": self.length_m,
                "width_m": self.width_m, "height_m": self.height_m, "area_m2": self.area_m2,
                "class": self.class_name, "template": self.template, "score": self.score}


def find_vehicles(ndsm: NDArray, cell_m: float, templates: Sequence[NadirTemplate], *, west: float = 0.0,
                  north: float = 0.0, min_height_m: float = 0.8, play_cells: int = 2) -> list[TemplateCandidate]:
    """Candidates standing out of ``ndsm`` (H, W) m by ``min_height_m`` (NaN: no data; row 0
    north, cell (r, c) centred at ``west + (c + .5) cell``, ``north - (r + .5) cell``),
    matched with the nadir height ``templates`` that fit their size, best first (the
    detector survey-detect used before the aerial recogniser; kept as a benchmark's anchor)."""
    if not templates:
        raise InputError("detect: no class templates")
    z = np.asarray(ndsm, dtype=np.float32)
    if z.ndim != 2:
        raise InputError(f"nDSM: expected (H, W), got {z.shape}")
    zf = np.where(np.isfinite(z), z, 0.0).astype(np.float32)
    # hysteresis: an object is the connected cells above half the threshold holding one
    # above it, so a truck's cab and body stay one object over the chassis between them
    # (gaps narrower than ~0.6 m closed: a cab and its load box are one vehicle)
    gap = np.ones((2 * max(1, int(round(0.3 / cell_m))) + 1,) * 2, np.uint8)
    low = cv2.morphologyEx((zf > 0.5 * min_height_m).astype(np.uint8), cv2.MORPH_CLOSE, gap)
    low = cv2.morphologyEx(low, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, lab, stats, cents = cv2.connectedComponentsWithStats(low, connectivity=8)
    tall = np.zeros(n, bool)
    tall[np.unique(lab[(zf > min_height_m) & (low > 0)])] = True
    lmin = SIZE_TOLERANCE[0] * min(min(t.width for t in templates), min(t.length for t in templates))
    amax = max(t.length * t.width for t in templates) * SIZE_TOLERANCE[1] ** 2 * 1.5
    out = []
    H, W = z.shape
    for k in range(1, n):
        if not tall[k]:
            continue
        area = stats[k, cv2.CC_STAT_AREA] * cell_m**2
        if area < lmin * lmin or area > amax:
            continue
        x0, y0, bw, bh = (int(stats[k, i]) for i in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH,
                                                     cv2.CC_STAT_HEIGHT))
        rr, cc = np.nonzero(lab[y0:y0 + bh, x0:x0 + bw] == k)
        pts = np.c_[cc + x0, rr + y0].astype(np.float32)
        (cx, cy), (a, b), ang = cv2.minAreaRect(pts)
        L, Wd = max(a, b) * cell_m + cell_m, min(a, b) * cell_m + cell_m
        # the long axis's angle in image coordinates (x right, y down)
        theta = ang if a >= b else ang + 90.0
        hgt = float(np.percentile(zf[rr + y0, cc + x0], 98))
        fits = [t for t in templates
                if SIZE_TOLERANCE[0] * t.length <= L <= SIZE_TOLERANCE[1] * t.length
                and SIZE_TOLERANCE[0] * t.width <= Wd <= SIZE_TOLERANCE[1] * max(t.width, 0.5 * t.length)
                and SIZE_TOLERANCE[0] * t.height <= hgt <= SIZE_TOLERANCE[1] * t.height]
        score, best = _match_templates(zf, lab, k, cx, cy, theta, fits, play_cells)
        xm = west + (float(cx) + 0.5) * cell_m
        ym = north - (float(cy) + 0.5) * cell_m
        heading = (90.0 + theta) % 180.0  # image angle (x right, y down) -> compass, mod 180
        out.append(TemplateCandidate(xm, ym, round(heading, 1), round(L, 2), round(Wd, 2), round(hgt, 2),
                                     round(area, 2), best.cls if best else None, best.name if best else None,
                                     round(score, 4)))
    out.sort(key=lambda d: -d.score)
    return out


def _match_templates(zf: NDArray, lab: NDArray, k: int, cx: float, cy: float, theta: float,
                     fits: Sequence[NadirTemplate], play_cells: int) -> tuple[float, NadirTemplate | None]:
    """Best correlation of object ``k``'s height chip (at ``cx, cy``, turned by ``theta`` onto its
    long axis) with the templates that fit its size, and that template (-1, None: none fit)."""
    score, best = -1.0, None
    if fits:
        side = int(max(max(t.heights.shape) for t in fits) * 1.5) + 2 * play_cells + 4
        M = cv2.getRotationMatrix2D((float(cx), float(cy)), float(theta), 1.0)
        M[:, 2] += np.array([side / 2.0 - cx, side / 2.0 - cy])
        own = np.where(lab == k, zf, np.minimum(zf, 0.3)).astype(np.float32)  # neighbours flattened
        chip = cv2.warpAffine(own, M, (side, side), flags=cv2.INTER_LINEAR, borderValue=0.0)
        for t in fits:
            th, tw = t.heights.shape
            r0 = side // 2 - th // 2 - play_cells
            c0 = side // 2 - tw // 2 - play_cells
            s = _best_match(chip[r0:r0 + th + 2 * play_cells, c0:c0 + tw + 2 * play_cells], t.heights, play_cells)
            if s > score:
                score, best = s, t
    return score, best


def write_geojson(path: str | Path, dets: Sequence[dict], *, origin_lla: Sequence[float] | None) -> None:
    """Detections as a GeoJSON FeatureCollection: WGS84 longitude/latitude points (RFC
    7946) when ``origin_lla`` georeferences the local frame, else local coordinates with
    a note that the scale is unknown."""
    feats = []
    for d in dets:
        if origin_lla is not None:
            z = d.get("z")
            lat, lon, _ = enu_to_wgs84(np.array([[d["x"], d["y"], 0.0 if z is None else z]]),
                                       np.asarray(origin_lla, float))[0]
            coords = [round(float(lon), 9), round(float(lat), 9)]
        else:
            coords = [d["x"], d["y"]]
        props = {k: v for k, v in d.items()}
        props["x_local"], props["y_local"] = props.pop("x"), props.pop("y")
        if "z" in props:
            props["z_local"] = props.pop("z")
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": coords}, "properties": props})
    doc: dict[str, Any] = {"type": "FeatureCollection", "features": feats}
    if origin_lla is None:
        doc["prism3d"] = {"coordinates": "local survey frame, scale unknown (no GPS)"}
    else:
        doc["prism3d"] = {"local_frame_origin_lla": [float(v) for v in origin_lla]}
    atomic_write_text(path, json.dumps(doc, indent=1))




#: The survey-detect default target classes.
DEFAULT_CLASSES = ("car", "van", "truck", "bus")
#: Around every cell that could belong to a vehicle (standing 0.4 m out of the ground, or
#: without a height inside the coverage), the search reaches this far, m.
ROI_MARGIN_M = 3.0
#: The largest survey area read onto the recogniser's grid, pixels (memory: about 20 bytes
#: a pixel while searching).
MAX_GRID_PIXELS = 120_000_000


@dataclass(frozen=True)
class SurveyScene:
    """A survey on the recogniser's grid: ``grey`` (H, W) float32 [0, 1] (NaN outside the
    orthophoto's coverage), ``rgb`` (H, W, 3) uint8, ``ndsm`` (H, W) float32 (NaN: no
    height), ``ground`` (H, W) float32 (NaN where unknown), ``roi`` (H, W) bool, the
    north-west corner and ``gsd``; ``origin_lla`` (None without GPS)."""

    grey: NDArray[np.float32]
    rgb: NDArray[np.uint8]
    ndsm: NDArray[np.float32]
    ground: NDArray[np.float32]
    roi: NDArray[np.bool_]
    west: float
    north: float
    gsd: float
    origin_lla: tuple[float, float, float] | None
    frame: MapFrame | None = None
    """The map grid's ties to WGS84 and the survey's local frame (None without GPS)."""


def _read_checked(path: Path, what: str) -> tuple[NDArray, dict]:

    if not path.is_file():
        raise InputError(f"{path.parent}: no {path.name}; give a folder written by 'prism3d survey'")
    try:
        return read_geotiff(path)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - rasterio raises its own types for a bad file
        raise InputError(f"{path}: not a readable GeoTIFF {what} ({type(exc).__name__}: {exc})") from None


def load_survey_scene(survey_dir: str | Path, gsd: float, *, appearance: bool = True, height: bool = True
                      ) -> SurveyScene:
    """A survey folder's orthophoto and nDSM on one grid of ``gsd`` m over the nDSM's
    extent (the orthophoto area-averaged or interpolated onto it, the nDSM nearest-cell)."""
    d = Path(survey_dir)
    nd, mn = _read_checked(d / "ndsm.tif", "nDSM")
    if nd.ndim != 2 or not np.issubdtype(nd.dtype, np.floating):
        raise InputError(f"{d / 'ndsm.tif'}: expected one float band of heights, got shape {nd.shape} {nd.dtype}")
    gr, mg = (_read_checked(d / "ground.tif", "ground") if (d / "ground.tif").is_file() else (None, None))
    o, mo = _read_checked(d / "ortho.tif", "orthophoto")
    if o.ndim != 3 or o.shape[2] < 3 or o.dtype != np.uint8:
        raise InputError(f"{d / 'ortho.tif'}: expected an RGB(A) 8-bit orthophoto, got shape {o.shape} {o.dtype}")
    if (mo["crs_wkt"] or "") != (mn["crs_wkt"] or ""):
        raise InputError(f"{d / 'ortho.tif'}: in another coordinate system than ndsm.tif; both must come from one survey")
    frame, lla = _survey_frame(d, mn["crs_wkt"])
    if gr is not None and (gr.shape != nd.shape or mg["west"] != mn["west"] or mg["north"] != mn["north"]):
        raise InputError(f"{d / 'ground.tif'}: not on ndsm.tif's grid; both must come from one survey")
    west, north, cell = float(mn["west"]), float(mn["north"]), float(mn["gsd"])
    # the grid over the surveyed cells only (a survey's lattice holds every pair's tile; most
    # of it may be empty), a few metres around
    rows, cols = np.flatnonzero(np.isfinite(nd).any(axis=1)), np.flatnonzero(np.isfinite(nd).any(axis=0))
    if not len(rows):
        raise InputError(f"{d / 'ndsm.tif'}: holds no height at all")
    pad = int(round(ROI_MARGIN_M / cell))
    r0, r1 = max(0, rows[0] - pad), min(nd.shape[0], rows[-1] + pad + 1)
    c0, c1 = max(0, cols[0] - pad), min(nd.shape[1], cols[-1] + pad + 1)
    nd = nd[r0:r1, c0:c1]
    gr = None if gr is None else gr[r0:r1, c0:c1]
    west, north = west + c0 * cell, north - r0 * cell
    W, H = int(round(nd.shape[1] * cell / gsd)), int(round(nd.shape[0] * cell / gsd))
    oe, os_ = mo["west"] + o.shape[1] * mo["gsd"], mo["north"] - o.shape[0] * mo["gsd"]
    ne, ns = west + nd.shape[1] * cell, north - nd.shape[0] * cell
    if min(oe, ne) - max(mo["west"], west) <= 0 or min(mo["north"], north) - max(os_, ns) <= 0:
        raise InputError(f"{d / 'ortho.tif'}: does not overlap ndsm.tif; both must come from one survey")
    if W * H > MAX_GRID_PIXELS:
        raise InputError(f"{d}: {nd.shape[1] * cell:.0f} x {nd.shape[0] * cell:.0f} m at {gsd} m is {W * H:,} "
                         f"pixels, more than {MAX_GRID_PIXELS:,}; survey a smaller area")
    X = (west + (np.arange(W) + 0.5) * gsd).astype(np.float64)
    Y = (north - (np.arange(H) + 0.5) * gsd).astype(np.float64)
    rgb, grey, covered = _ortho_on_grid(o, mo, X, Y, gsd)
    nx = ((X - west) / cell - 0.5).astype(np.float32)
    ny = ((north - Y) / cell - 0.5).astype(np.float32)
    z = _remap_rows(nd.astype(np.float32), nx, ny, cv2.INTER_NEAREST, nan=True)
    g = np.full(z.shape, np.nan, np.float32) if gr is None else _remap_rows(gr.astype(np.float32), nx, ny,
                                                                         cv2.INTER_NEAREST, nan=True)
    if not appearance:
        grey = np.where(np.isfinite(grey), np.nan, np.nan).astype(np.float32)
    if not height:
        z = np.full(z.shape, np.nan, np.float32)
    stand = np.nan_to_num(z, nan=0.0) > 0.4
    hole = ~np.isfinite(z) & covered if height else covered
    k = max(1, int(round(ROI_MARGIN_M / gsd)))
    roi = cv2.dilate((stand | hole).astype(np.uint8), np.ones((3, 3), np.uint8), iterations=k) > 0
    roi &= covered if appearance else np.isfinite(z) | ~stand
    return SurveyScene(grey.astype(np.float32), rgb, z, g, roi, west, north, gsd, lla, frame)


def _survey_frame(d: Path, crs_wkt: str | None) -> tuple[MapFrame | None, tuple[float, float, float] | None]:
    """The survey's map frame and origin from its poses.json, the rasters' CRS checked
    against it (a raster of another survey or reprojected by hand is refused)."""
    doc = json.loads((d / "poses.json").read_text()) if (d / "poses.json").is_file() else {}
    frame = MapFrame.from_record(doc) if isinstance(doc, dict) else None
    if frame is not None and not _same_crs(crs_wkt, frame.crs_wkt):
        raise InputError(f"{d / 'ndsm.tif'}: not in the survey's coordinate system ({frame.name}); "
                         "both must come from one survey")
    return frame, None if frame is None else frame.origin_lla


def _same_crs(wkt: str | None, ref: str) -> bool:
    """Whether a raster's CRS is the survey's (PROJ's equivalence, not the text)."""
    if not wkt:
        return False
    try:
        return bool(pyproj.CRS.from_user_input(wkt).equals(pyproj.CRS.from_user_input(ref), ignore_axis_order=True))
    except pyproj.exceptions.CRSError:
        return False


def _ortho_on_grid(o: NDArray, mo: dict, X: NDArray, Y: NDArray, gsd: float
                   ) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.bool_]]:
    """The orthophoto ``o`` (metadata ``mo``) at the grid's cell centres ``X``, ``Y``: area-averaged
    to about the grid first when finer, then sampled. RGB, grey (NaN uncovered), covered cells."""
    f = float(mo["gsd"]) / gsd
    src = o[..., :4] if o.shape[2] >= 4 else np.dstack([o, np.full(o.shape[:2], 255, np.uint8)])
    s = 1.0
    if f < 0.8:
        src = cv2.resize(src, (max(1, int(round(o.shape[1] * f))), max(1, int(round(o.shape[0] * f)))),
                         interpolation=cv2.INTER_AREA)
        s = o.shape[1] / src.shape[1]
    mx = ((X - mo["west"]) / (mo["gsd"] * s) - 0.5).astype(np.float32)
    my = ((mo["north"] - Y) / (mo["gsd"] * s) - 0.5).astype(np.float32)
    rgba = _remap_rows(src, mx, my, cv2.INTER_LINEAR)
    covered = rgba[..., 3] >= 128
    rgb = np.ascontiguousarray(rgba[..., :3])
    grey = (rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)) / 255.0
    grey[~covered] = np.nan
    return rgb, grey, covered


def _remap_rows(img: NDArray, mx: NDArray, my: NDArray, interp: int, *, nan: bool = False) -> NDArray:
    """``img`` sampled at every (mx[c], my[r]) of a separable grid, in bands of rows
    (OpenCV's maps hold at most 32767 a side)."""
    H, W = len(my), len(mx)
    out = np.empty((H, W) + img.shape[2:], dtype=img.dtype)
    border = float("nan") if nan else 0
    for c0 in range(0, W, 30000):
        xs = mx[c0:c0 + 30000]
        for r0 in range(0, H, 4096):
            ys = my[r0:r0 + 4096]
            MX, MY = np.meshgrid(xs, ys)
            out[r0:r0 + len(ys), c0:c0 + len(xs)] = cv2.remap(img, MX, MY, interp, borderMode=cv2.BORDER_CONSTANT,
                                                              borderValue=border)
    return out


def _compass_deg(heading_rad: float, grid_north_deg: float = 0.0) -> float:
    """A heading counter-clockwise from the grid's +x (east) as a compass bearing of the
    long axis from true north, degrees in [0, 180) (front and back are not told apart);
    ``grid_north_deg`` the bearing of the grid's +y (the meridian convergence)."""
    b = round((90.0 - math.degrees(heading_rad) + grid_north_deg) % 180.0, 1)
    return 0.0 if b >= 180.0 else b


def detect_in_survey(survey_dir: str | Path, out_path: str | Path, model: Any, *,
                     threshold: float | None = None, all_candidates: bool = False,
                     draw: str | Path | None = None) -> dict[str, Any]:
    """Vehicles of ``model`` (:class:`~prism3d.atr.aerial.AerialModel`) in a survey folder,
    written to ``out_path`` as GeoJSON (one Feature per vehicle, best first; those scoring
    at least ``threshold``, default the model's calibrated 0.5, unless ``all_candidates``)
    and drawn on the orthophoto to ``draw`` (PNG). A survey without GPS is refused (its
    sizes are in unknown units)."""
    t0 = time.perf_counter()
    d, out = Path(survey_dir), Path(out_path)
    th = check_survey_request(d, out, threshold=threshold, draw=draw)
    scene = load_survey_scene(d, model.gsd_m, appearance=model.channels != "height",
                              height=model.channels != "appearance")
    t1 = time.perf_counter()
    dets = model.detect(scene.grey, scene.ndsm, roi=scene.roi)
    t2 = time.perf_counter()
    kept = [x for x in dets if all_candidates or x.score >= th]
    feats = [_feature(x, scene) for x in kept]

    with atomic_paths(*([out] if draw is None else [out, Path(draw)])) as tmps:  # both files or neither
        _write_feature_collection(tmps[0], feats, scene, th, all_candidates, model)
        if draw is not None:
            draw_survey_detections(tmps[1], scene, kept, th)
    counts: dict[str, int] = {}
    for x in kept:
        if x.score >= th:
            counts[x.class_name] = counts.get(x.class_name, 0) + 1
    return {"n_vehicles": sum(counts.values()), "by_class": counts, "n_written": len(kept),
            "threshold": th, "seconds": {"read": round(t1 - t0, 2), "detect": round(t2 - t1, 2),
                                         "total": round(time.perf_counter() - t0, 2)}}


def check_survey_request(survey_dir: str | Path, out_path: str | Path, *, threshold: float | None = None,
                         draw: str | Path | None = None) -> float:
    """What :func:`detect_in_survey` is asked, checked before a recogniser is loaded or
    trained (minutes): the output names (``.geojson``/``.json``, a ``.png`` drawing, none
    of them one of the survey's own files), the survey folder (a folder with a readable
    ``poses.json`` of a GPS-scaled survey, ``ndsm.tif`` and ``ortho.tif``) and the
    threshold. Returns the threshold to use. The rasters' contents are read by
    :func:`load_survey_scene`."""
    d, out = Path(survey_dir), Path(out_path)
    if out.suffix.lower() not in (".geojson", ".json"):
        raise InputError(f"{out}: expected a .geojson (or .json) file name for the vehicles")
    if draw is not None and Path(draw).suffix.lower() != ".png":
        raise InputError(f"{draw}: expected a .png file name for the drawing")
    for f in (out, Path(draw) if draw is not None else None):
        if f is not None and f.resolve().parent == d.resolve() and f.name in _SURVEY_NAMES:
            raise InputError(f"{f}: would overwrite the survey's own {f.name}; write the vehicles elsewhere")
    check_outputs_not_inputs([out, draw], [d / n for n in sorted(_SURVEY_NAMES)])  # links to them too
    if not d.exists():
        raise InputError(f"{d}: no such survey folder; give a folder written by 'prism3d survey'")
    if not d.is_dir():
        raise InputError(f"{d}: not a folder; give a folder written by 'prism3d survey'")
    if not (d / "poses.json").is_file():
        raise InputError(f"{d}: no poses.json; give a folder written by 'prism3d survey'")
    try:
        doc = json.loads((d / "poses.json").read_text())
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: nesting deeper than the parser goes
        raise InputError(f"{d / 'poses.json'}: unreadable ({type(exc).__name__}: {exc})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{d / 'poses.json'}: expected a JSON object, got {type(doc).__name__}")
    if doc.get("scale") not in METRIC_SCALES or doc.get("origin_lla") is None:
        raise InputError(f"{d}: the survey's scale is unknown (no GPS); vehicle sizes cannot be compared")
    for name in ("ndsm.tif", "ortho.tif"):
        if not (d / name).is_file():
            raise InputError(f"{d}: no {name}; give a folder written by 'prism3d survey'")
    th = DEFAULT_THRESHOLD if threshold is None else float(threshold)
    if not (math.isfinite(th) and 0.0 <= th <= 1.0):
        raise InputError(f"threshold: expected a score in [0, 1], got {threshold!r}")
    return th


_SURVEY_NAMES = {"poses.json", "cloud.ply", "cloud.las", "cloud.laz", "dsm.tif", "ndsm.tif", "ground.tif", "ortho.tif",
                 "ortho_quality.tif", "survey.png"}


def _feature(x: VehicleDetection, scene: SurveyScene) -> dict[str, Any]:
    """One detection as a GeoJSON Feature: a WGS84 point at its centre, its footprint a
    WGS84 polygon, local metres kept beside."""
    g = scene.gsd
    r, c = x.row, x.col
    ri, ci = int(min(max(round(r), 0), scene.ground.shape[0] - 1)), int(min(max(round(c), 0), scene.ground.shape[1] - 1))
    k = max(1, int(round(2.0 / g)))
    win = scene.ground[max(ri - k, 0):ri + k + 1, max(ci - k, 0):ci + k + 1]
    z = float(np.nanmedian(win)) if np.isfinite(win).any() else float(np.nanmedian(scene.ground)) \
        if np.isfinite(scene.ground).any() else 0.0
    pts = [(scene.west + (c + 0.5) * g, scene.north - (r + 0.5) * g)]
    pts += [(scene.west + (cc + 0.5) * g, scene.north - (rr + 0.5) * g) for rr, cc in x.corners_rc]
    frame = scene.frame if scene.frame is not None else MapFrame(tuple(scene.origin_lla))
    q = np.array([[px, py, z] for px, py in pts])
    lla = frame.map_to_lla(q)
    local = frame.map_to_enu(q[:1])[0]
    lonlat = [[round(float(b), 9), round(float(a), 9)] for a, b, _ in lla]
    ring = lonlat[1:] + [lonlat[1]]
    heading = _compass_deg(x.heading_rad, float(frame.grid_north_deg(q[:1])[0]))
    props = {"class": x.class_name, "score": round(float(x.score), 4), "heading_deg": heading,
             "footprint": {"type": "Polygon", "coordinates": [ring]},
             "length_m": round(float(x.length_m), 2), "width_m": round(float(x.width_m), 2),
             "x_local": round(float(local[0]), 3), "y_local": round(float(local[1]), 3),
             "z_local": round(float(local[2]), 3)}
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": lonlat[0]}, "properties": props}


def _write_feature_collection(out: Path, feats: list[dict], scene: SurveyScene, th: float, all_candidates: bool,
                              model: Any) -> None:
    doc = {"type": "FeatureCollection", "features": feats,
           "prism3d": {"local_frame_origin_lla": [float(v) for v in scene.origin_lla], "threshold": th,
                       "all_candidates": bool(all_candidates), "classes": model.classes,
                       "channels": model.channels, "score": "calibrated: the share of the recogniser's held-out "
                       "training detections at this score that were vehicles",
                       "heading_deg": "compass bearing of the long axis, 0-180 (front and back not told apart)"}}
    out.write_text(json.dumps(doc, indent=1))


def draw_survey_detections(path: str | Path, scene: SurveyScene, dets: Sequence[VehicleDetection],
                           threshold: float) -> None:
    """The orthophoto with each detection's footprint (vehicles at or above ``threshold``
    in red with class and score; candidates below in thin blue), as PNG at ``path``."""
    img = np.ascontiguousarray(scene.rgb[..., ::-1])
    f = max(1, int(round(0.25 / max(scene.gsd, 1e-6) / 4)))
    for x in sorted(dets, key=lambda t: t.score):
        ok = x.score >= threshold
        col = (40, 40, 230) if ok else (230, 140, 40)
        poly = np.round(np.array(x.corners_rc)[:, ::-1]).astype(np.int32)
        cv2.polylines(img, [poly], True, col, 2 if ok else 1, cv2.LINE_AA)
        if ok:
            cv2.putText(img, f"{x.class_name} {x.score:.2f}", (int(poly[:, 0].min()), int(poly[:, 1].min()) - 3),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4 * f, col, 1, cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise InputError(f"{path}: could not write the drawing")
