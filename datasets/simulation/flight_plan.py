"""The plan of a virtual drone survey (:mod:`~prism3d.datasets.simulation.flight`): the
options, the site (terrain, roads, a car park), the camera's path and attitude, the GPS
noise, and what stands where (targets, confusers, clutter, ground control markers), drawn
from one seed before anything is rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.capture.rig import CameraModel
from prism3d.checks import check_seed
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets
from prism3d.datasets.simulation.carpark import Lot, lot_clutter, park_vehicles, plan_lot
from prism3d.datasets.simulation.field import SCENE_CAMO_SEED_BASE, SHAPE_CONFUSERS, Terrain, prop_mesh
from prism3d.datasets.simulation.flight_ground import (
    ROAD_WIDTH_M,
    HeightField,
    Land,
    Road,
    SurveyGroundAlbedo,
)
from prism3d.datasets.simulation.flight_gcp import marker_side_m, merged_markers, place_markers
from prism3d.datasets.simulation.flight_placing import Placer, corners_enu
from prism3d.errors import InputError

__all__ = ["FLIGHT_SCHEMA_VERSION", "FlightOptions", "FlightPlan", "frames_seeing", "nadir_camera_rotation",
           "plan_flight"]

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


def frames_seeing(cam: CameraModel, poses: list[NDArray], pts_enu: NDArray, margin_px: float = 2.0) -> list[int]:
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
            return len(frames_seeing(cam, poses, corners_enu(mesh, T_mm))) >= 2

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
        if len(frames_seeing(cam, poses, corners_enu(mesh, T))) < 2:
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
