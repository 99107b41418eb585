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
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.camera_effects import CameraEffects
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.render import (
    RaycastRenderer,
    SensorNoise,
    camera_rays,
    gaussian_blur,
    quantize,
)
from prism3d.capture.rig import CameraModel
from prism3d.capture.simulate import (
    ShotOptions,
    apply_view_optics,
    gloss_table,
    render_view,
    write_npz,
)
from prism3d.checks import check_seed
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets
from prism3d.datasets.simulation.carpark import Lot, lot_clutter, park_vehicles, plan_lot
from prism3d.datasets.simulation.field import (
    SCENE_CAMO_SEED_BASE,
    SHAPE_CONFUSERS,
    Terrain,
    distant_sun,
    prop_mesh,
)
from prism3d.datasets.simulation.flight_ground import (
    ROAD_WIDTH_M,
    HeightField,
    Land,
    Road,
    SurveyGroundAlbedo,
    on_road,
)
from prism3d.datasets.simulation.flight_gcp import (
    GCP_FILE,
    gcp_list_text,
    map_crs,
    marker_side_m,
    merged_markers,
    observe_markers,
    place_markers,
    to_map,
)
from prism3d.datasets.simulation.flight_placing import Placer, corners_enu
from prism3d.errors import InputError
from prism3d.geo import enu_to_wgs84
from prism3d.io.atomic import atomic_write_text, staged_folder
from prism3d.io.opencv_yaml import write_filestorage

__all__ = ["FLIGHT_SCHEMA_VERSION", "FlightOptions", "FlightPlan", "nadir_camera_rotation", "plan_flight",
           "simulate_flight"]

FLIGHT_SCHEMA_VERSION = 1
#: Geoid height at the default site (EGM96, 37.5 N 139.0 E), m: altitude_amsl = altitude_wgs84 - this.
GEOID_UNDULATION_M = 39.7
#: Most true-DSM cells (about 10 bytes each): an automatic cell is coarsened to stay under it.
MAX_DSM_CELLS = 60_000_000
#: Most terrain mesh vertices: the grid spacing grows beyond 1 m to stay under it.
MAX_TERRAIN_VERTICES = 1_500_000
#: Most clutter objects in a flight (a long or high flight gets no more).
MAX_CLUTTER = 3000
#: Sensor width, mm (a 1/2.3-inch type), for the EXIF focal length in mm.
SENSOR_WIDTH_MM = 6.17
#: Built-in target classes that drive on the ground.
GROUND_VEHICLE_CLASSES = ("tank", "truck")
SCENES = ("field", "carpark")
#: A target counts as fully visible in a frame from this visible fraction of its silhouette.
FULLY_VISIBLE_FRACTION = 0.98
JPEG_QUALITY = 92
_AMBIENT, _SUN = 0.35, 0.85
#: NED -> ENU, and the nadir camera in the body frame (x forward, y right, z down).
_R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_R_BODY_CAM = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
ATTITUDE_CONVENTION = ("R_enu_cam = R_enu_ned Rz(heading) Ry(pitch) Rx(roll) R_body_cam; body x forward, "
                       "y right, z down; camera x right, y backward (image down), z down; heading clockwise "
                       "from north")


def _check_int(v: Any, name: str, lo: int, hi: int) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= int(v) <= hi:
        raise InputError(f"{name}: expected an integer in [{lo}, {hi}], got {v!r}")


def _check_num(v: Any, name: str, lo: float, hi: float, *, open_lo: bool = False, open_hi: bool = False) -> None:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number, got {v!r}") from None
    ok = math.isfinite(x) and (x > lo if open_lo else x >= lo) and (x < hi if open_hi else x <= hi)
    if not ok:
        raise InputError(f"{name}: expected a value in {'(' if open_lo else '['}{lo}, {hi}{')' if open_hi else ']'}, "
                         f"got {v!r}")


@dataclass(frozen=True)
class FlightOptions:
    """What ``simulate flight`` flies over and how its camera sees it."""

    frames: int = 12
    """Photographs in all, split evenly between the lines (at least 2 a line)."""
    lines: int = 2
    """Parallel flight lines, every other one flown the opposite way."""
    altitude_m: float = 100.0
    """Flying height above the terrain's mean, m (10-1000)."""
    overlap: float = 0.70
    """Forward overlap of consecutive frames of a line on the mean ground, in (0, 0.95)."""
    side_overlap: float = 0.60
    """Overlap of neighbouring lines, in [0, 0.95)."""
    size: tuple[int, int] = (4000, 3000)
    """Image (width, height) px; the flight direction is the image's up."""
    hfov_deg: float = 70.0
    """Horizontal field of view, deg."""
    dist: tuple[float, float, float, float, float] = (-0.02, 0.01, 0.0, 0.0, 0.0)
    """Lens distortion (k1, k2, p1, p2, k3), OpenCV's model."""
    heading_deg: float | None = None
    """Flight direction of the first line, deg clockwise from north (None: drawn)."""
    scene: str = "field"
    """``field``: camouflaged military vehicles on open ground among rocks, bushes, trees and
    buildings; ``carpark``: a paved car park of parked civilian vehicles in rows (cars of
    every body colour, vans, pickups, kei trucks, buses and box trucks in long bays), trees
    overhanging the edge rows, people and light poles (datasets/simulation/carpark.py)."""
    targets: int | None = None
    """Ground vehicles (None: field 5-10, drawn; carpark 70-95 % of the car bays)."""
    confusers: int | None = None
    """Crates and fuel tanks (None: field 0-3, drawn; carpark none)."""
    clutter_per_ha: float = 20.0
    """Rocks, bushes, trees and buildings per hectare of terrain."""
    attitude_sigma_deg: tuple[float, float, float] = (1.0, 1.0, 2.0)
    """Attitude jitter (roll, pitch, yaw), deg."""
    altitude_sigma_m: float = 0.5
    """Altitude jitter, m."""
    gps_sigma_m: tuple[float, float] = (0.3, 0.6)
    """GPS noise (horizontal, per axis; vertical), m."""
    origin_lla: tuple[float, float, float] = (37.5435, 139.0426, 150.0)
    """Site origin (latitude, longitude deg; ellipsoidal height m): ENU (0, 0, 0)."""
    dsm_cell_m: float | None = None
    """True-DSM cell, m (None: twice the nominal GSD to the cm, coarser past MAX_DSM_CELLS)."""
    depth: bool = True
    """Write each frame's true depth and object ids (depth/IMG_xxxx.npz)."""
    supersample: int = 1
    """Colour rays per pixel along each axis (2 smooths edges at 4x the time)."""
    noise: bool = True
    """Sensor noise (the other camera effects are always on)."""
    gcp: int = 0
    """Ground control points: painted chequer boards spread over the block, each inside two
    frames or more, written to ``gcp_list.txt`` (0: none; at most 50)."""
    gcp_pixel_sigma: float = 0.5
    """Noise of the control points' pixels in ``gcp_list.txt`` (px per axis, the clicking)."""
    seed: int = 0
    """Seeds the terrain, layout, paints, sun, flight jitter, GPS and noise."""

    def __post_init__(self) -> None:
        setv = object.__setattr__
        setv(self, "seed", check_seed(self.seed))
        _check_int(self.frames, "frames", 2, 1000)
        _check_int(self.lines, "lines", 1, 100)
        if self.frames % self.lines or self.frames // self.lines < 2:
            raise InputError(f"frames: expected a multiple of lines ({self.lines}) with at least 2 frames a line, "
                             f"got {self.frames}")
        _check_num(self.altitude_m, "altitude_m", 10.0, 1000.0)
        _check_num(self.overlap, "overlap", 0.0, 0.95, open_lo=True, open_hi=True)
        _check_num(self.side_overlap, "side_overlap", 0.0, 0.95, open_hi=True)
        if len(self.size) != 2 or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in self.size):
            raise InputError(f"size: expected (width, height) integer px, got {self.size!r}")
        w, h = (int(v) for v in self.size)
        if not (64 <= w <= 12000 and 64 <= h <= 12000 and w * h <= 80_000_000):
            raise InputError(f"size: expected 64-12000 px a side and at most 80 MP, got {w}x{h}")
        setv(self, "size", (w, h))
        _check_num(self.hfov_deg, "hfov_deg", 20.0, 120.0)
        if len(self.dist) != 5:
            raise InputError(f"dist: expected 5 coefficients (k1, k2, p1, p2, k3), got {self.dist!r}")
        for d in self.dist:
            _check_num(d, "dist", -1.0, 1.0, open_lo=True, open_hi=True)
        if self.heading_deg is not None:
            _check_num(self.heading_deg, "heading_deg", -360.0, 360.0)
        if self.scene not in SCENES:
            raise InputError(f"scene: expected one of {', '.join(SCENES)}, got {self.scene!r}")
        for name, hi in (("targets", 40 if self.scene == "field" else 200), ("confusers", 20)):
            if getattr(self, name) is not None:
                _check_int(getattr(self, name), name, 0, hi)
        _check_num(self.clutter_per_ha, "clutter_per_ha", 0.0, 200.0)
        for name, n, hi in (("attitude_sigma_deg", 3, 10.0), ("gps_sigma_m", 2, 100.0)):
            v = getattr(self, name)
            if len(v) != n:
                raise InputError(f"{name}: expected {n} values, got {v!r}")
            for x in v:
                _check_num(x, name, 0.0, hi)
        _check_num(self.altitude_sigma_m, "altitude_sigma_m", 0.0, 50.0)
        if len(self.origin_lla) != 3:
            raise InputError(f"origin_lla: expected (latitude, longitude, height), got {self.origin_lla!r}")
        lat, lon, hgt = self.origin_lla
        _check_num(lat, "origin_lla latitude", -85.0, 85.0)
        _check_num(lon, "origin_lla longitude", -180.0, 180.0)
        _check_num(hgt, "origin_lla height", -1000.0, 10000.0)
        if self.dsm_cell_m is not None:
            _check_num(self.dsm_cell_m, "dsm_cell_m", 0.005, 100.0)
        _check_int(self.supersample, "supersample", 1, 4)
        _check_int(self.gcp, "gcp", 0, 50)
        _check_num(self.gcp_pixel_sigma, "gcp_pixel_sigma", 0.0, 20.0)


# -- geometry ----------------------------------------------------------------------------
def nadir_camera_rotation(heading_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0) -> NDArray[np.float64]:
    """``R_enu_cam`` (3, 3) of the survey camera at an attitude (deg; :data:`ATTITUDE_CONVENTION`):
    level, it looks straight down with the heading at the image's top."""
    y, p, r = (math.radians(float(a)) for a in (heading_deg, pitch_deg, roll_deg))
    Rz = np.array([[math.cos(y), -math.sin(y), 0.0], [math.sin(y), math.cos(y), 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[math.cos(p), 0.0, math.sin(p)], [0.0, 1.0, 0.0], [-math.sin(p), 0.0, math.cos(p)]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(r), -math.sin(r)], [0.0, math.sin(r), math.cos(r)]])
    return _R_ENU_NED @ Rz @ Ry @ Rx @ _R_BODY_CAM


# -- the plan -----------------------------------------------------------------------------
@dataclass(eq=False)
class FlightPlan:
    """A planned flight, nothing rendered: camera, true poses (ENU m, OpenCV camera frame),
    attitudes, noisy GPS, the terrain, the objects (world mm) and the truth records."""

    camera: CameraModel
    T_enu_cam: list[NDArray[np.float64]]
    line: list[int]
    attitude_deg: NDArray[np.float64]  # (n, 3) heading, pitch, roll
    gps_enu: NDArray[np.float64]  # (n, 3)
    land: Land
    roads: tuple[Road, ...]
    objects: list[tuple[SceneMesh, NDArray[np.float64]]]  # (mesh, T_world_obj) mm; 0 = the ground
    kinds: list[dict[str, Any]]  # truth ids: 0 ground, 1 road, renderer object i >= 1 -> i + 1
    records: list[dict[str, Any]]  # targets and confusers
    sun_dir_enu: NDArray[np.float64]
    dsm: dict[str, Any]
    gsd_m: float
    mean_ground_m: float
    meta: dict[str, Any] = field(default_factory=dict)
    gcps: list[dict[str, Any]] = field(default_factory=list)  # name, enu (marker top centre), object id


def _camera(o: FlightOptions) -> CameraModel:
    w, h = o.size
    f = (w / 2.0) / math.tan(math.radians(o.hfov_deg) / 2.0)
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraModel(K, np.asarray(o.dist, dtype=np.float64), (w, h))


def _layout(o: FlightOptions, cam: CameraModel,
            psi: float) -> tuple[NDArray, list[int], list[float], tuple[float, float]]:
    """Nominal camera centres ``(n, 2)`` (ENU m, pattern centred on the origin), line of
    each frame, course (deg) and the footprint (along, across) on the mean ground, m."""
    along = cam.height * o.altitude_m / cam.fx
    across = cam.width * o.altitude_m / cam.fx
    step, spacing = (1.0 - o.overlap) * along, (1.0 - o.side_overlap) * across
    fwd = np.array([math.sin(psi), math.cos(psi)])
    right = np.array([math.cos(psi), -math.sin(psi)])
    n = o.frames // o.lines
    xy, lines, course = [], [], []
    for li in range(o.lines):
        c = (li - (o.lines - 1) / 2.0) * spacing
        for j in (range(n) if li % 2 == 0 else reversed(range(n))):
            xy.append((j - (n - 1) / 2.0) * step * fwd + c * right)
            lines.append(li)
            course.append(math.degrees(psi) % 360.0 if li % 2 == 0 else (math.degrees(psi) + 180.0) % 360.0)
    return np.array(xy), lines, course, (along, across)


def _carpark_site(rng: np.random.Generator, centres: NDArray, foot: tuple[float, float], psi: float,
                  hills: Terrain, seed: int) -> tuple[Lot, list, tuple[Road, ...]]:
    """A car park in the middle frame's footprint (rows along or across the flight, 10 deg
    of play) and two roads skirting it (one along its rows, one across)."""
    along = math.pi / 2.0 - psi  # the flight direction, from east counter-clockwise
    turn = float(rng.choice([0.0, math.pi / 2.0])) + math.radians(rng.uniform(-10.0, 10.0))
    d = along + turn
    span_a, span_b = (foot[0], foot[1]) if abs(math.cos(turn)) > 0.5 else (foot[1], foot[0])
    c = centres.mean(axis=0) + rng.uniform(-0.03, 0.03, 2) * np.array(foot)
    z = float(hills.height(np.array([c[0]]), np.array([c[1]]))[0])
    lot, bays = plan_lot(rng, (float(c[0]), float(c[1])), d, z, 0.75 * span_a, 0.75 * span_b, seed)
    ua, ub = np.array([math.cos(d), math.sin(d)]), np.array([-math.sin(d), math.cos(d)])
    p1 = c - ub * (lot.half_b + 2.0 + ROAD_WIDTH_M / 2.0)
    p2 = c + ua * (lot.half_a + 2.0 + ROAD_WIDTH_M / 2.0)
    roads = (Road(float(p1[0]), float(p1[1]), float(ua[0]), float(ua[1])),
             Road(float(p2[0]), float(p2[1]), float(ub[0]), float(ub[1])))
    return lot, bays, roads


def _terrain(rng: np.random.Generator, centres: NDArray, foot: tuple[float, float],
             psi: float, scene: str = "field", seed: int = 0
             ) -> tuple[Land, tuple[Road, ...], dict[str, Any]]:
    """The hills and two roads (one along the lines, one across) over the flown area and a
    margin; a car park scene levels a lot in the middle (``meta["lot"]``, ``meta["bays"]``)."""
    half = 0.5 * math.hypot(*foot) + 0.15 * max(foot) + 10.0
    x0, x1 = centres[:, 0].min() - half, centres[:, 0].max() + half
    y0, y1 = centres[:, 1].min() - half, centres[:, 1].max() + half
    d = max(1.0, math.ceil(10.0 * math.sqrt((x1 - x0) * (y1 - y0) / MAX_TERRAIN_VERTICES)) / 10.0)
    waves = tuple((float(math.cos(t) * 2 * math.pi / lam), float(math.sin(t) * 2 * math.pi / lam),
                   float(rng.uniform(0, 2 * math.pi)), float(a))
                  for t, lam, a in zip(rng.uniform(0, math.pi, 3),
                                       (rng.uniform(120, 200), rng.uniform(70, 120), rng.uniform(50, 80)),
                                       (1.5, 0.8, 0.3)))
    span = np.ptp(centres, axis=0) + foot[0]
    roads = []
    for turn, spread in ((rng.uniform(-20, 20), 0.3), (90.0 + rng.uniform(-30, 30), 0.3)):
        a = psi + math.radians(turn)
        off = rng.uniform(-spread, spread, 2) * span
        roads.append(Road(float(off[0]), float(off[1]), math.sin(a), math.cos(a)))
    meta: dict[str, Any] = {}
    lots: tuple[Lot, ...] = ()
    if scene == "carpark":
        lot, bays, roads_t = _carpark_site(rng, centres, foot, psi, Terrain(waves, math.inf), seed)
        roads, lots = list(roads_t), (lot,)
        meta.update(lot=lot, bays=bays)
    hf = HeightField(Terrain(waves, math.inf), tuple(roads), lots)
    nx, ny = int(math.ceil((x1 - x0) / d)) + 1, int(math.ceil((y1 - y0) / d)) + 1
    X, Y = np.meshgrid(x0 + d * np.arange(nx), y0 + d * np.arange(ny))
    land = Land(float(x0), float(y0), d, hf(X, Y))
    return land, tuple(roads), {"waves_per_m": [list(w) for w in waves], "spacing_m": d, **meta}


def _poses(o: FlightOptions, rng: np.random.Generator, centres: NDArray, course: list[float],
           z_mean: float) -> tuple[list[NDArray], NDArray, NDArray]:
    """True ``T_enu_cam`` (jittered attitude and altitude), attitudes (heading, pitch, roll)
    deg and GPS positions (noisy), ENU m."""
    sr, sp, sy = o.attitude_sigma_deg
    sh, sv = o.gps_sigma_m
    poses, att, gps = [], [], []
    for (x, y), c in zip(centres, course):
        roll, pitch, yaw = rng.normal(0.0, 1.0, 3) * (sr, sp, sy)
        head = (c + yaw) % 360.0
        T = np.eye(4)
        T[:3, :3] = nadir_camera_rotation(head, pitch, roll)
        T[:3, 3] = (x, y, z_mean + o.altitude_m + rng.normal(0.0, o.altitude_sigma_m))
        poses.append(T)
        att.append((head, pitch, roll))
        gps.append(T[:3, 3] + rng.normal(0.0, 1.0, 3) * (sh, sh, sv))
    return poses, np.array(att), np.array(gps)


def _frames_seeing(cam: CameraModel, poses: list[NDArray], pts_enu: NDArray, margin_px: float = 2.0) -> list[int]:
    """Frames whose image holds all the points (ENU m), with a margin."""
    w, h = cam.size
    out = []
    for k, T in enumerate(poses):
        pc = (pts_enu - T[:3, 3]) @ T[:3, :3]
        if np.any(pc[:, 2] <= 0.0):
            continue
        uv = cam.project(pc)
        if np.all((uv >= margin_px) & (uv <= np.array([w - 1.0, h - 1.0]) - margin_px)):
            out.append(k)
    return out


def _dsm_grid(o: FlightOptions, cam: CameraModel, poses: list[NDArray], z_mean: float, gsd: float) -> dict[str, Any]:
    """The true-DSM grid over the union of the frames' footprints on the mean ground."""
    w, h = cam.size
    rays = cam.pixel_rays(np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]]))
    pts = []
    for T in poses:
        d = rays @ T[:3, :3].T
        pts.append(T[:3, 3] + d * ((z_mean - T[2, 3]) / d[:, 2])[:, None])
    p = np.concatenate(pts)
    (xa, ya), (xb, yb) = p[:, :2].min(axis=0), p[:, :2].max(axis=0)
    area = (xb - xa) * (yb - ya)
    if o.dsm_cell_m is None:
        cell = max(round(2.0 * gsd, 2), 0.01, math.ceil(100.0 * math.sqrt(area / MAX_DSM_CELLS)) / 100.0)
    else:
        cell = float(o.dsm_cell_m)
    west, north = round(math.floor(xa / cell) * cell, 6), round(math.ceil(yb / cell) * cell, 6)
    width, height = int(math.ceil((xb - west) / cell)), int(math.ceil((north - ya) / cell))
    if width * height > MAX_DSM_CELLS:
        raise InputError(f"dsm_cell_m: a {cell} m grid over the {xb - xa:.0f} x {yb - ya:.0f} m footprint has "
                         f"{width * height:,} cells, more than {MAX_DSM_CELLS:,}; give a coarser cell")
    return {"west": west, "north": north, "cell_m": cell, "width": width, "height": height,
            "east": round(west + width * cell, 6), "south": round(north - height * cell, 6)}


def _place_targets(o: FlightOptions, rng: np.random.Generator, placer: Placer, cam: CameraModel,
                   poses: list[NDArray], dsm: dict[str, Any]) -> tuple[list, list[dict[str, Any]]]:
    """Ground vehicles and confusers inside the DSM area, each wholly in at least two frames."""
    vehicles = [n for n in list_builtin_targets("military") if n.split("_")[0] in GROUND_VEHICLE_CLASSES]
    n_t = int(rng.integers(5, 11)) if o.targets is None else int(o.targets)
    n_c = int(rng.integers(0, 4)) if o.confusers is None else int(o.confusers)
    picks = [(str(rng.choice(vehicles)), False) for _ in range(n_t)]
    picks += [(str(rng.choice(list(SHAPE_CONFUSERS))), True) for _ in range(n_c)]
    zone = (dsm["west"] + 5.0, dsm["east"] - 5.0, dsm["south"] + 5.0, dsm["north"] - 5.0)
    placed, records = [], []
    for k, (name, confuser) in enumerate(picks):
        seed_k = SCENE_CAMO_SEED_BASE + o.seed * 64 + k
        mesh = prop_mesh(name, rng, seed_k) if name in SHAPE_CONFUSERS else builtin_target(name, scale="full",
                                                                                              seed=seed_k)

        def seen_twice(T: NDArray, mesh: SceneMesh = mesh) -> bool:
            T_mm = T.copy()
            T_mm[:3, 3] *= 1000.0
            return len(_frames_seeing(cam, poses, corners_enu(mesh, T_mm))) >= 2

        T = placer.place(mesh, zone, spacing=1.3, tries=300, tilt=True, accept=seen_twice)
        if T is None:
            raise InputError(f"targets: no room for {len(picks)} targets and confusers on the open ground of "
                             f"this flight (placed {k}); fly more frames or ask for fewer")
        placed.append((mesh, T))
        records.append({"name": name, "class": str(mesh.metadata.get("class", name)), "confuser": confuser,
                        "camouflage_seed": seed_k})
    return placed, records


def _park(o: FlightOptions, rng: np.random.Generator, placer: Placer, cam: CameraModel, poses: list[NDArray],
          lot: Lot, bays: list) -> tuple[list, list[dict[str, Any]], list]:
    """The car park's vehicles (those wholly in two frames or more), its trees, people and
    poles (merged per kind, as :func:`_place_clutter` does); the lot kept clear of other clutter."""
    parked = park_vehicles(rng, lot, bays, o.targets, SCENE_CAMO_SEED_BASE + o.seed * 512)
    targets, records, ab = [], [], []
    for mesh, T, rec in parked:
        if len(_frames_seeing(cam, poses, corners_enu(mesh, T))) < 2:
            continue
        targets.append((mesh, T))
        records.append(rec)
        ab.append(lot.to_lot(T[0, 3] / 1000.0, T[1, 3] / 1000.0))
    if not targets:
        raise InputError("carpark: no parked vehicle is wholly in two frames; fly more overlap or lower")
    placer.taken = np.vstack([placer.taken, [lot.cx, lot.cy, math.hypot(lot.half_a, lot.half_b) + 2.0]])
    parts: dict[str, list[tuple[NDArray, NDArray, NDArray]]] = {}
    for mesh, T, _ in lot_clutter(rng, lot, np.array(ab, dtype=np.float64).reshape(-1, 2), o.seed * 100_000 + 50_000):
        rgb = mesh.albedo_field(np.zeros((1, 3)))[0]
        parts.setdefault(mesh.name, []).append((mesh.vertices @ T[:3, :3].T + T[:3, 3], mesh.faces, rgb))
    return targets, records, _merge_kinds(parts, ("tree", "person", "pole"))


def _merge_kinds(parts: dict[str, list[tuple[NDArray, NDArray, NDArray]]], order: tuple[str, ...]) -> list:
    """One world-frame mesh per kind of clutter (in ``order``), each instance in its own colour."""
    out = []
    for kind in [k for k in order if k in parts]:
        off = np.cumsum([0] + [len(v) for v, _, _ in parts[kind][:-1]])
        V = np.vstack([v for v, _, _ in parts[kind]])
        F = np.vstack([f + k for (_, f, _), k in zip(parts[kind], off)])
        A = np.vstack([np.tile(c, (len(v), 1)) for v, _, c in parts[kind]])
        out.append((SceneMesh(V, F, A, None, kind, {"material": "lambertian", "count": len(parts[kind])}),
                    np.eye(4)))
    return out


def _place_clutter(o: FlightOptions, rng: np.random.Generator, placer: Placer) -> list:
    """Rocks, bushes, trees and buildings, merged into one mesh per kind (world frame, each
    instance in its own colour): a renderer of a few meshes shades faster than of hundreds."""
    x0, x1, y0, y1 = placer.land.bounds
    n = min(MAX_CLUTTER, int(round(o.clutter_per_ha * (x1 - x0) * (y1 - y0) / 1e4)))
    kinds = rng.choice(["rock", "bush", "tree", "building"], size=n, p=[0.35, 0.35, 0.2, 0.1])
    parts: dict[str, list[tuple[NDArray, NDArray, NDArray]]] = {}
    for j, kind in enumerate(kinds):
        mesh = prop_mesh(str(kind), rng, o.seed * 100_000 + j)
        T = placer.place(mesh, (x0 + 12.0, x1 - 12.0, y0 + 12.0, y1 - 12.0), spacing=1.1, tries=30, tilt=False)
        if T is not None:
            rgb = mesh.albedo_field(np.zeros((1, 3)))[0]
            parts.setdefault(str(kind), []).append((mesh.vertices @ T[:3, :3].T + T[:3, 3], mesh.faces, rgb))
    return _merge_kinds(parts, ("building", "tree", "bush", "rock"))


def plan_flight(options: FlightOptions | None = None) -> FlightPlan:
    """Draw a flight from ``options.seed``: terrain, roads, flight, objects, sun (no rendering)."""
    o = FlightOptions() if options is None else options
    rng = np.random.default_rng([o.seed, 30])
    cam = _camera(o)
    psi = math.radians(rng.uniform(0.0, 360.0) if o.heading_deg is None else float(o.heading_deg))
    centres, lines, course, foot = _layout(o, cam, psi)
    land, roads, meta = _terrain(rng, centres, foot, psi, o.scene, o.seed)
    lot = meta.pop("lot", None)
    bays = meta.pop("bays", None)
    z_mean = float(land.z.mean())
    poses, att, gps = _poses(o, np.random.default_rng([o.seed, 31]), centres, course, z_mean)
    gsd = o.altitude_m / cam.fx
    dsm = _dsm_grid(o, cam, poses, z_mean, gsd)
    scale = max(1.0, 2.5 * gsd * 1000.0 / 60.0)  # GroundAlbedo's finest cell is 60 mm
    ground = land.mesh(SurveyGroundAlbedo(o.seed, scale, roads, () if lot is None else (lot,)))
    placer = Placer(rng, land, roads)
    if lot is None:
        targets, records = _place_targets(o, rng, placer, cam, poses, dsm)
        clutter = _place_clutter(o, rng, placer)
    else:
        targets, records, clutter = _park(o, rng, placer, cam, poses, lot, bays)
        clutter += _place_clutter(o, rng, placer)
        meta["carpark"] = {"centre_enu": [lot.cx, lot.cy, lot.z], "rows_direction_deg":
                           math.degrees(math.atan2(lot.ux, lot.uy)) % 360.0, "size_m": [2 * lot.half_a, 2 * lot.half_b],
                           "surface": lot.surface, "bays": len(bays), "painted_lines": len(lot.lines)}
    objects = [(ground, np.eye(4))] + targets + clutter
    gcps: list[dict[str, Any]] = []
    if o.gcp:  # last, on their own draws: the rest of the flight is the same with or without them
        side = marker_side_m(gsd)
        zone = (dsm["west"] + 5.0, dsm["east"] - 5.0, dsm["south"] + 5.0, dsm["north"] - 5.0)
        placed = place_markers(o.gcp, np.random.default_rng([o.seed, 34]), placer, cam, poses, zone, side, 20.0)
        objects.append((merged_markers(placed, side), np.eye(4)))
        gcps = [{"name": f"gcp{k + 1:02d}", "enu": [float(v) for v in top], "id": len(objects)}
                for k, (_, top) in enumerate(placed)]
        meta["gcp_side_m"] = side
    kinds: list[dict[str, Any]] = [{"id": 0, "kind": "ground"}, {"id": 1, "kind": "road"}]
    for i, (mesh, _) in enumerate(objects[1:], start=1):
        if i <= len(records):
            rec = records[i - 1]
            kinds.append({"id": i + 1, "kind": "confuser" if rec["confuser"] else "target",
                          "name": rec["name"], "instance": i - 1})
        else:
            kinds.append({"id": i + 1, "kind": mesh.name, "count": mesh.metadata["count"]})
    el, az = math.radians(rng.uniform(35.0, 65.0)), rng.uniform(0.0, 2.0 * math.pi)
    sun = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    meta.update(heading_deg=math.degrees(psi) % 360.0, footprint_m=list(foot), texture_scale=scale,
                sun_elevation_deg=math.degrees(el), sun_azimuth_deg=math.degrees(az))
    return FlightPlan(cam, poses, lines, att, gps, land, roads, objects, kinds, records, sun, dsm, gsd, z_mean, meta,
                      gcps)


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
        if not _frames_seeing(cam, [plan.T_enu_cam[k]], corners):
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
