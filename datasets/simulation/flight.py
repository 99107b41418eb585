"""Virtual nadir drone surveys with exact ground truth (``prism3d simulate flight``): the
test bench of the UAV survey mode (issue 30: one moving camera, neighbouring frames form
stereo pairs).

World: local east-north-up about ``origin_lla``, metres (the renderer works in mm: world
mm = ENU m x 1000). Gentle hills (a mesh of the height field) carry grass and soil
textured from a few GSD upward and 6 m gravel roads (level across, following the hills);
buildings, trees, bushes and rocks as clutter; full-size ground vehicles (built-in tanks
and trucks, camouflage seeds no bank trains on) and confusers (crates, fuel tanks) stand
on open ground, tilted to the slope; the sun casts shadows. One pinhole camera flies a
lawnmower pattern looking straight down, the flight direction at the image's top (-y of
the OpenCV camera), with attitude and altitude jitter; the GPS positions are noisy.

Folder (all or nothing): ``IMG_0000.JPG`` ... (EXIF focal length and GPS),
``geoinfo.txt`` (senseFly), ``camera.yaml`` (OpenCV calibration-sample FileStorage:
``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``),
``truth.json``, ``truth.npz`` (true DSM, bare ground, object ids),
``depth/IMG_0000.npz`` ... (``depth_m`` z-depth float32 NaN = no hit, ``object_id`` int16)
and, with ``gcp``, ``gcp_list.txt`` (painted ground control points in OpenDroneMap's
format: :mod:`~prism3d.datasets.simulation.flight_gcp`).

What stands where and how the camera flies is planned first, from the seed alone
(:mod:`~prism3d.datasets.simulation.flight_plan`); this module renders the plan and writes it.
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.camera_effects import CameraEffects
from prism3d.capture.render import RaycastRenderer, SensorNoise, camera_rays, gaussian_blur, quantize
from prism3d.capture.rig import CameraModel
from prism3d.capture.simulate import ShotOptions, apply_view_optics, gloss_table, render_view, write_npz
from prism3d.datasets.simulation.field import distant_sun
from prism3d.datasets.simulation.flight_ground import on_road
from prism3d.datasets.simulation.flight_gcp import GCP_FILE, gcp_list_text, map_crs, observe_markers, to_map
from prism3d.datasets.simulation.flight_placing import corners_enu
from prism3d.datasets.simulation.flight_plan import (
    ATTITUDE_CONVENTION,
    FLIGHT_SCHEMA_VERSION,
    FULLY_VISIBLE_FRACTION,
    FlightOptions,
    FlightPlan,
    GEOID_UNDULATION_M,
    JPEG_QUALITY,
    SENSOR_WIDTH_MM,
    frames_seeing,
    nadir_camera_rotation,
    plan_flight,
)
from prism3d.errors import InputError
from prism3d.geo import enu_to_wgs84
from prism3d.io.atomic import atomic_write_text, staged_folder
from prism3d.io.opencv_yaml import write_filestorage

__all__ = ["FLIGHT_SCHEMA_VERSION", "FlightOptions", "FlightPlan", "nadir_camera_rotation", "plan_flight",
           "simulate_flight"]

#: Sky light and sun, as the shot simulator's ambient and flash levels.
_AMBIENT, _SUN = 0.35, 0.85


# -- rendering and truth ------------------------------------------------------------------
def _frame_image(renderer: Any, plan: FlightPlan, k: int, projector: Any, shot: Any, gloss: Any,
                 effects: Any) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.int32]]:
    """One frame as the camera records it (optics, PSF, noise, quantised; JPEG is the file),
    and its true z-depth (mm) and renderer object ids."""
    T_mm = plan.T_enu_cam[k].copy()
    T_mm[:3, 3] *= 1000.0
    img, truth = render_view(renderer, plan.camera, T_mm, projector, shot, gloss)
    apply_view_optics(img, plan.camera, effects, "left")
    img = gaussian_blur(img, effects.psf_sigma_px)
    if shot.noise:
        img = quantize(SensorNoise().apply(img, np.random.default_rng([shot.seed, 32, k])))
    else:
        img = quantize(img * 255.0)
    return img, truth["depth_mm"], truth["object_id"]


def _truth_ids(plan: FlightPlan, k: int, depth_m: NDArray, oid: NDArray, xn: NDArray, yn: NDArray) -> NDArray[np.int16]:
    """Renderer ids as truth ids (0 ground, 1 road, object i >= 1 -> i + 1; -1 none)."""
    ids = np.where(oid >= 1, oid + 1, oid).astype(np.int16)
    g = np.flatnonzero(oid.ravel() == 0)
    T = plan.T_enu_cam[k]
    d = depth_m.ravel()[g].astype(np.float64)
    pc = np.stack([xn.ravel()[g] * d, yn.ravel()[g] * d, d], axis=1)
    x = T[0, 3] + pc @ T[0, :3]
    y = T[1, 3] + pc @ T[1, :3]
    ids.ravel()[g[on_road(plan.roads, x, y)]] = 1
    return ids


def _visibility(plan: FlightPlan, k: int, ids: NDArray[np.int16], solo: list[Any], out: list[dict]) -> None:
    """Per target in frame ``k``: the visible fraction of its silhouette (its own render
    through a window of the camera, exact: distortion acts on normalised coordinates)."""
    cam = plan.camera
    w, h = cam.size
    T_mm = plan.T_enu_cam[k].copy()
    T_mm[:3, 3] *= 1000.0
    for t, (mesh, T_obj) in enumerate(plan.objects[1:len(plan.records) + 1]):
        corners = corners_enu(mesh, T_obj)
        if not frames_seeing(cam, [plan.T_enu_cam[k]], corners):
            continue
        uv = cam.project((corners - plan.T_enu_cam[k][:3, 3]) @ plan.T_enu_cam[k][:3, :3])
        u0, v0 = (max(0, int(math.floor(a)) - 4) for a in uv.min(axis=0))
        u1, v1 = min(w - 1, int(math.ceil(uv[:, 0].max())) + 4), min(h - 1, int(math.ceil(uv[:, 1].max())) + 4)
        K = cam.K.copy()
        K[0, 2] -= u0
        K[1, 2] -= v0
        win = CameraModel(K, cam.dist, (u1 - u0 + 1, v1 - v0 + 1))
        sil = np.zeros((v1 - v0 + 1) * (u1 - u0 + 1), dtype=bool)
        sil[solo[t].trace_camera(win, T_mm).index] = True
        seen = ids[v0:v1 + 1, u0:u1 + 1].ravel() == t + 2
        frac = float((seen & sil).sum() / max(int(sil.sum()), 1))
        out[t]["visible_fraction"][str(k)] = round(frac, 4)


def _true_dsm(renderer: Any, plan: FlightPlan) -> dict[str, NDArray]:
    """Highest surface (vertical rays from above), bare ground and truth ids at the DSM cell centres."""
    g = plan.dsm
    H, W, cell = g["height"], g["width"], g["cell_m"]
    top = 1000.0 * max(float(corners_enu(m, T)[:, 2].max()) for m, T in plan.objects) + 1000.0  # mm
    dsm = np.empty((H, W), dtype=np.float32)
    ground = np.empty((H, W), dtype=np.float32)
    oid = np.empty((H, W), dtype=np.int16)
    xs = g["west"] + (np.arange(W) + 0.5) * cell
    rows = max(1, (1 << 20) // W)
    down = np.tile([0.0, 0.0, -1.0], (rows * W, 1))
    for r0 in range(0, H, rows):
        r1 = min(H, r0 + rows)
        X, Y = np.meshgrid(xs, g["north"] - (np.arange(r0, r1) + 0.5) * cell)
        o = np.stack([X.ravel() * 1000.0, Y.ravel() * 1000.0, np.full(X.size, top)], axis=1)
        hits = renderer.cast(o, down[: X.size], normalized=True)
        dsm[r0:r1] = np.where(hits.hit, (top - hits.t) / 1000.0, np.nan).reshape(X.shape)
        ground[r0:r1] = plan.land.height_at(X, Y)
        ids = np.where(hits.object_id >= 1, hits.object_id + 1, hits.object_id).reshape(X.shape)
        ids[(ids == 0) & on_road(plan.roads, X, Y)] = 1
        oid[r0:r1] = ids
    return {"dsm": dsm, "ground": ground, "object_id": oid}


def _exif(plan: FlightPlan, k: int, lla: NDArray) -> bytes:
    """EXIF of frame ``k``: camera, focal length (mm, and the sensor's pixels per cm) and GPS."""
    from PIL import Image
    from PIL.ExifTags import GPS, IFD, Base

    cam = plan.camera
    ex = Image.Exif()
    ex[Base.Make], ex[Base.Model] = "prism3d", "virtual survey camera"
    e = ex.get_ifd(IFD.Exif)
    e[Base.FocalLength] = cam.fx * SENSOR_WIDTH_MM / cam.width
    e[Base.FocalPlaneXResolution] = e[Base.FocalPlaneYResolution] = cam.width / (SENSOR_WIDTH_MM / 10.0)
    e[Base.FocalPlaneResolutionUnit] = 3
    e[Base.ExifImageWidth], e[Base.ExifImageHeight] = cam.size
    gp = ex.get_ifd(IFD.GPSInfo)
    lat, lon, alt = (float(v) for v in lla)

    def dms(a: float) -> tuple[float, float, float]:
        a = abs(a)
        return (float(int(a)), float(int(a * 60.0) % 60), (a * 3600.0) % 60.0)

    gp[GPS.GPSLatitudeRef], gp[GPS.GPSLatitude] = ("N" if lat >= 0 else "S"), dms(lat)
    gp[GPS.GPSLongitudeRef], gp[GPS.GPSLongitude] = ("E" if lon >= 0 else "W"), dms(lon)
    gp[GPS.GPSAltitudeRef], gp[GPS.GPSAltitude] = (0 if alt >= 0 else 1), abs(alt)
    gp[GPS.GPSImgDirectionRef], gp[GPS.GPSImgDirection] = "T", float(plan.attitude_deg[k, 0])
    return ex.tobytes()


def _jpeg(img: NDArray[np.uint8], exif: bytes) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, "JPEG", quality=JPEG_QUALITY, exif=exif)
    return buf.getvalue()


def _geoinfo(plan: FlightPlan, names: list[str], lla: NDArray) -> str:
    """senseFly's position table: noisy GPS (WGS84), true attitude (deg)."""
    lines = ["#Rev: sensefly/geoinfo/2",
             "\t".join(["fileName", "latitude", "longitude", "altitude_amsl", "altitude_wgs84", "heading", "pitch",
                        "roll"])]
    for name, (lat, lon, h), (hd, pt, rl) in zip(names, lla, plan.attitude_deg):
        vals = [lat, lon, h - GEOID_UNDULATION_M, h, hd, pt, rl]
        lines.append(name + "\t" + "".join(f"{v:.10f}\t" for v in vals))
    return "\n".join(lines) + "\n"


def _truth_doc(o: FlightOptions, plan: FlightPlan, names: list[str], targets: list[dict], effects: Any) -> dict:
    cam = plan.camera
    frames = [{"image": n, "T_enu_cam": T.tolist(), "gps_enu": [float(v) for v in g], "line": int(li),
               "heading_deg": float(a[0]), "pitch_deg": float(a[1]), "roll_deg": float(a[2])}
              for n, T, g, li, a in zip(names, plan.T_enu_cam, plan.gps_enu, plan.line, plan.attitude_deg)]
    return {
        "schema_version": FLIGHT_SCHEMA_VERSION, "units": "m",
        "world_frame": "local east-north-up at origin_lla (ellipsoidal height), metres",
        "camera_frame": "OpenCV: x right, y down, z forward (down for a level nadir camera)",
        "attitude_convention": ATTITUDE_CONVENTION,
        "origin_lla": list(o.origin_lla), "geoid_undulation_m": GEOID_UNDULATION_M,
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(o).items()},
        "gsd_m": plan.gsd_m, "mean_ground_m": plan.mean_ground_m,
        "K": cam.K.tolist(), "dist": cam.dist.tolist(), "size": list(cam.size),
        "camera_effects": effects.to_dict(), "frames": frames,
        "sun_dir_enu": plan.sun_dir_enu.tolist(),
        "sun_elevation_deg": plan.meta["sun_elevation_deg"], "sun_azimuth_deg": plan.meta["sun_azimuth_deg"],
        "terrain": {"waves_per_m": plan.meta["waves_per_m"], "spacing_m": plan.meta["spacing_m"],
                    "bounds_m": list(plan.land.bounds), "texture_scale": plan.meta["texture_scale"]},
        **({"carpark": plan.meta["carpark"]} if "carpark" in plan.meta else {}),
        "roads": [{"x0_m": r.x0, "y0_m": r.y0, "direction_deg": math.degrees(math.atan2(r.ux, r.uy)) % 360.0,
                   "width_m": r.width} for r in plan.roads],
        "objects": plan.kinds, "targets": targets,
        "dsm": {"file": "truth.npz", **plan.dsm,
                "layout": "row 0 = north edge; cell (r, c) centre = (west + (c + 0.5) cell, north - (r + 0.5) cell)"},
    }


def _write_gcps(stage: Path, plan: FlightPlan, o: FlightOptions, names: list[str], seen: list[dict[int, Any]]
                ) -> dict[str, Any]:
    """``gcp_list.txt`` (clicked pixels) and the control points' truth for ``truth.json``:
    per point its ENU and map coordinates and its true pixel in each frame that sees it."""
    epsg = map_crs(np.asarray(o.origin_lla))
    enu = np.array([g["enu"] for g in plan.gcps])
    xyz = to_map(enu, np.asarray(o.origin_lla), epsg)
    gnames = [g["name"] for g in plan.gcps]
    atomic_write_text(stage / GCP_FILE, gcp_list_text(epsg, gnames, xyz, seen, names))
    points = [{"name": n, "enu": [round(float(v), 4) for v in enu[g]], "map": [round(float(v), 3) for v in xyz[g]],
               "pixels": {names[k]: [round(v, 3) for v in seen[k][g][0]] for k in range(len(names)) if g in seen[k]}}
              for g, n in enumerate(gnames)]
    return {"file": GCP_FILE, "crs": f"EPSG:{epsg}", "heights": "WGS84 ellipsoidal, m",
            "pixel_convention": "(0, 0) the centre of the top-left pixel", "pixel_sigma": o.gcp_pixel_sigma,
            "marker": f"{plan.meta['gcp_side_m']} m square board, 2 x 2 black and white chequer; the point is "
                      "its top's centre", "points": points}


def _target_records(plan: FlightPlan) -> list[dict[str, Any]]:
    out = []
    for t, ((mesh, T), rec) in enumerate(zip(plan.objects[1:], plan.records)):
        lo, hi = mesh.bounds
        base = T[:3, :3] @ np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]) + T[:3, 3]
        T_m = T.copy()
        T_m[:3, 3] /= 1000.0
        corners = np.array([[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]], [hi[0], hi[1], lo[2]], [lo[0], hi[1], lo[2]]])
        foot = (corners @ T[:3, :3].T + T[:3, 3])[:, :2] / 1000.0
        out.append({"instance": t, "id": t + 2, **rec, "xyz_enu": [float(v) for v in base / 1000.0],
                    "footprint_enu": [[round(float(a), 4), round(float(b), 4)] for a, b in foot],
                    "heading_deg": math.degrees(math.atan2(T[0, 0], T[1, 0])) % 360.0,
                    "tilt_deg": math.degrees(math.acos(min(1.0, T[2, 2]))),
                    "length_m": float(hi[0] - lo[0]) / 1000.0, "width_m": float(hi[1] - lo[1]) / 1000.0,
                    "height_m": float(hi[2] - lo[2]) / 1000.0, "T_enu_obj": T_m.tolist(),
                    "frames": [], "visible_fraction": {}})
    return out


def _fly(stage: Path, plan: FlightPlan, o: FlightOptions, names: list[str], lla: NDArray, targets: list[dict],
         renderer: Any, progress: Callable[[int, int, str], None] | None) -> list[dict[int, Any]]:
    """Render the frames in turn; a second thread labels and writes each (JPEG, depth)
    while the next renders, one frame behind, so at most two frames are in memory.
    Returns per frame the control points it sees (:func:`observe_markers`)."""
    from concurrent.futures import Future, ThreadPoolExecutor

    effects = CameraEffects()
    shot = ShotOptions(ambient=_AMBIENT, flash=_SUN, supersample=o.supersample, noise=o.noise, seed=o.seed,
                       effects=effects)
    x0, x1, y0, y1 = plan.land.bounds
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, plan.mean_ground_m]) * 1000.0
    projector = distant_sun(plan.sun_dir_enu, centre, 500.0 * math.hypot(x1 - x0, y1 - y0))
    gloss = gloss_table(renderer, effects)
    rays, zc = camera_rays(plan.camera)
    xn, yn = (rays[..., 0] / zc).astype(np.float32), (rays[..., 1] / zc).astype(np.float32)
    del rays, zc
    solo = [RaycastRenderer([obj]) for obj in plan.objects[1:len(targets) + 1]]
    if o.depth:
        (stage / "depth").mkdir()
    seen: list[dict[int, Any]] = [{} for _ in names]
    gcp_enu = np.array([g["enu"] for g in plan.gcps]).reshape(-1, 3)

    def finish(k: int, img: NDArray, depth_mm: NDArray, oid: NDArray) -> None:
        name = names[k]
        (stage / name).write_bytes(_jpeg(img, _exif(plan, k, lla[k])))
        depth_m = depth_mm / np.float32(1000.0)
        ids = _truth_ids(plan, k, depth_m, oid, xn, yn)
        _visibility(plan, k, ids, solo, targets)
        if plan.gcps:
            seen[k] = observe_markers(plan.camera, plan.T_enu_cam[k], gcp_enu, ids, plan.gcps[0]["id"],
                                      np.random.default_rng([o.seed, 35, k]), o.gcp_pixel_sigma)
        if o.depth:
            write_npz(stage / "depth" / f"{name[:-4]}.npz", {"depth_m": depth_m, "object_id": ids}, compress=True)

    pending: Future | None = None
    with ThreadPoolExecutor(max_workers=1) as pool:
        for k, name in enumerate(names):
            frame = _frame_image(renderer, plan, k, projector, shot, gloss, effects)
            if pending is not None:
                pending.result()
            pending = pool.submit(finish, k, *frame)
            del frame
            if progress and k:
                progress(k, len(names) + 1, names[k - 1])
        if pending is not None:
            pending.result()
    return seen


def simulate_flight(out_dir: str | Path, options: FlightOptions | None = None, *,
                    progress: Callable[[int, int, str], None] | None = None) -> dict[str, Any]:
    """Fly the survey of ``options`` and write its photographs and truth into ``out_dir``
    (new or empty), all or nothing (files: the module docstring). ``progress(done, total,
    label)`` after each frame and after the true DSM.

    ``truth.json`` ``targets``: ``instance``, ``id`` (in ``objects`` and the id maps),
    ``name``, ``class``, ``confuser``, ``xyz_enu`` (base footprint centre on the ground),
    ``heading_deg`` (forward, clockwise from north), ``tilt_deg``, ``length_m width_m
    height_m`` (bounding box), ``T_enu_obj``, ``visible_fraction`` per frame wholly in view
    and ``frames`` where it is fully visible. Returns ``out_dir``, ``n_frames``,
    ``n_targets``, ``gsd_m``, ``seconds``, ``files``.
    """
    o = FlightOptions() if options is None else options
    if not isinstance(o, FlightOptions):
        raise InputError(f"options: expected a FlightOptions or None, got {type(o).__name__}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise InputError(f"{out}: folder is not empty; give a new folder for the flight")
    t0 = time.perf_counter()
    plan = plan_flight(o)
    n = len(plan.T_enu_cam)
    names = [f"IMG_{k:04d}.JPG" for k in range(n)]
    lla = enu_to_wgs84(plan.gps_enu, np.asarray(o.origin_lla))
    targets = _target_records(plan)
    renderer = RaycastRenderer(plan.objects)
    with staged_folder(out) as stage:
        seen = _fly(stage, plan, o, names, lla, targets, renderer, progress)
        if progress:
            progress(n, n + 1, "true DSM")
        truth = _true_dsm(renderer, plan)
        g = plan.dsm
        write_npz(stage / "truth.npz", {**truth, "west": np.float64(g["west"]), "north": np.float64(g["north"]),
                                         "cell_m": np.float64(g["cell_m"]),
                                         "schema_version": np.int64(FLIGHT_SCHEMA_VERSION)}, compress=True)
        for t in targets:
            t["frames"] = [int(k) for k, f in t["visible_fraction"].items() if f >= FULLY_VISIBLE_FRACTION]
        atomic_write_text(stage / "geoinfo.txt", _geoinfo(plan, names, lla))
        cam = plan.camera
        write_filestorage(stage / "camera.yaml", {
            "image_width": cam.width, "image_height": cam.height, "camera_matrix": cam.K,
            "distortion_coefficients": cam.dist, "schema_version": FLIGHT_SCHEMA_VERSION, "simulated": 1})
        doc = _truth_doc(o, plan, names, targets, CameraEffects())
        if plan.gcps:
            doc["gcps"] = _write_gcps(stage, plan, o, names, seen)
        atomic_write_text(stage / "truth.json", json.dumps(doc, indent=1))
        files = sorted(p.relative_to(stage).as_posix() for p in stage.rglob("*") if p.is_file())
    if progress:
        progress(n + 1, n + 1, "written")
    return {"out_dir": str(out), "n_frames": n, "n_targets": sum(not t["confuser"] for t in targets),
            "n_confusers": sum(t["confuser"] for t in targets), "gsd_m": plan.gsd_m,
            "seconds": time.perf_counter() - t0, "files": files}
