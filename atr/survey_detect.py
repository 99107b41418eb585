"""Targets from the air: vehicles found in a survey's normalised DSM (height above the
ground) and identified by their shape seen from above.

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
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError

__all__ = ["NadirTemplate", "find_vehicles", "nadir_templates", "score_detections", "write_geojson"]

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
    from prism3d.capture.render import RaycastRenderer

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


def find_vehicles(ndsm: NDArray, cell_m: float, templates: Sequence[NadirTemplate], *, west: float = 0.0,
                  north: float = 0.0, min_height_m: float = 0.8, play_cells: int = 2) -> list[dict[str, Any]]:
    """Candidates standing out of ``ndsm`` (H, W) m by ``min_height_m`` (NaN: no data; row 0 north, cell
    (r, c) centred at ``west + (c + .5) cell``, ``north - (r + .5) cell``), each with its
    map position, heading of its long axis (deg clockwise from north), length, width,
    height, the best-fitting class and template and ``score`` (their height-shape
    correlation; -1 when no class fits its size), best first."""
    import cv2

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
        xm = west + (float(cx) + 0.5) * cell_m
        ym = north - (float(cy) + 0.5) * cell_m
        heading = (90.0 + theta) % 180.0  # image angle (x right, y down) -> compass, mod 180
        out.append({"x": xm, "y": ym, "heading_deg": round(heading, 1), "length_m": round(L, 2),
                    "width_m": round(Wd, 2), "height_m": round(hgt, 2), "area_m2": round(area, 2),
                    "class": best.cls if best else None, "template": best.name if best else None,
                    "score": round(score, 4)})
    out.sort(key=lambda d: -d["score"])
    return out


def score_detections(dets: Sequence[dict], targets: Sequence[dict], n_frames: int) -> dict[str, Any]:
    """Pd against false positives per frame over the score threshold: a detection is a
    hit when within half the target's length of a not yet found target's centre
    (``targets``: ``x``, ``y``, ``length_m``, ``counted``; uncounted targets, e.g.
    confusers, are neither hits nor misses), else a false positive."""
    tx = np.array([[t["x"], t["y"]] for t in targets]) if targets else np.zeros((0, 2))
    counted = np.array([bool(t.get("counted", True)) for t in targets], bool)
    radius = np.array([max(0.5 * t["length_m"], 2.0) for t in targets])
    found = np.zeros(len(targets), bool)
    curve = []
    tp = fp = 0
    for d in sorted(dets, key=lambda d: -d["score"]):
        if d["score"] <= -1:
            break
        dist = np.hypot(tx[:, 0] - d["x"], tx[:, 1] - d["y"]) if len(tx) else np.zeros(0)
        hit = np.flatnonzero((dist <= radius) & ~found)
        if len(hit):
            k = hit[np.argmin(dist[hit])]
            found[k] = True
            if counted[k]:
                tp += 1
        elif not (len(dist) and np.any((dist <= radius) & ~counted)):
            fp += 1
        curve.append((d["score"], tp, fp))
    n_t = int(counted.sum())

    def pd_at(fppf: float) -> float:
        best = 0
        for _, t, f in curve:
            if f / max(n_frames, 1) <= fppf:
                best = max(best, t)
        return best / max(n_t, 1)

    return {"n_targets": n_t, "n_frames": n_frames, "pd_at_0.1_fppf": pd_at(0.1), "pd_at_1_fppf": pd_at(1.0),
            "curve": [{"score": s, "tp": t, "fp": f} for s, t, f in curve]}


def write_geojson(path: str | Path, dets: Sequence[dict], *, origin_lla: Sequence[float] | None) -> None:
    """Detections as a GeoJSON FeatureCollection: WGS84 longitude/latitude points (RFC
    7946) when ``origin_lla`` georeferences the local frame, else local coordinates with
    a note that the scale is unknown."""
    from prism3d.io.atomic import atomic_write_text

    feats = []
    for d in dets:
        if origin_lla is not None:
            from prism3d.capture.geotag import enu_to_wgs84

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


#: The built-in ground vehicles searched by default.
DEFAULT_VEHICLES = ("tank_t1", "tank_t2", "tank_t3", "truck_k1", "truck_k2", "truck_k3")


def ndsm_ground(survey_dir: Path) -> NDArray[np.float32]:
    """The survey's ground heights (``ground.tif``, else DSM minus nDSM)."""
    from prism3d.io.geo import read_geotiff

    if (survey_dir / "ground.tif").is_file():
        return read_geotiff(survey_dir / "ground.tif")[0]
    return read_geotiff(survey_dir / "dsm.tif")[0] - read_geotiff(survey_dir / "ndsm.tif")[0]


def detect_in_survey(survey_dir: str | Path, out_path: str | Path, items: Sequence[tuple[str, Any]], *,
                     min_height_m: float = 0.8) -> dict[str, Any]:
    """Find the targets ``items`` (``(name, SceneMesh)`` at full size, mm; the CLI gives
    the built-in ground vehicles by default) in a survey folder's nDSM and write them to
    ``out_path`` as GeoJSON, best first. A survey without GPS is refused: its sizes are
    in unknown units."""
    import time

    from prism3d.io.geo import read_geotiff

    t0 = time.perf_counter()
    d = Path(survey_dir)
    for f in ("poses.json", "ndsm.tif"):
        if not (d / f).is_file():
            raise InputError(f"{d}: no {f}; give a folder written by 'prism3d survey'")
    try:
        doc = json.loads((d / "poses.json").read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"{d / 'poses.json'}: unreadable ({exc})") from None
    if doc.get("scale") != "gps":
        raise InputError(f"{d}: the survey's scale is unknown (no GPS); vehicle sizes cannot be compared")
    if not items:
        raise InputError("detect: no targets to look for")
    ndsm, meta = read_geotiff(d / "ndsm.tif")
    cell = float(meta["gsd"])
    tpls = nadir_templates(list(items), cell)
    dets = find_vehicles(ndsm, cell, tpls, west=float(meta["west"]), north=float(meta["north"]),
                         min_height_m=min_height_m)
    if (d / "dsm.tif").is_file():  # each detection's ground height: a point, not a column, in the local frame
        ground = ndsm_ground(d)
        fallback = float(np.nanmedian(ground)) if np.isfinite(ground).any() else 0.0
        k = max(2, int(round(3.0 / cell)))  # the ground within 3 m (the centre cell may be a hole)
        for x in dets:
            r = int((float(meta["north"]) - x["y"]) / cell)
            c = int((x["x"] - float(meta["west"])) / cell)
            win = ground[max(r - k, 0):r + k + 1, max(c - k, 0):c + k + 1]
            z = float(np.nanmedian(win)) if win.size and np.isfinite(win).any() else fallback
            x["z"] = round(z, 3)
    write_geojson(out_path, dets, origin_lla=doc.get("origin_lla"))
    return {"n_detections": len(dets), "n_scored": sum(x["score"] > -1 for x in dets), "cell": cell,
            "seconds": time.perf_counter() - t0}
