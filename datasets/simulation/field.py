"""Field scenes: several full-size camouflaged targets, confusers and clutter on rolling
terrain under the sun, shot through a prism rig scaled for the range, with exact truth.

The test bench of whole-scene ATR (``prism3d simulate field``, docs/atr.md "Field
scenes"). World frame: x right, y away from the rig, z up, origin on the ground below
the rig. Bank-class targets stand on the land zone (ranges ``land_range_m``); a class
too large for it (a full-size ship) floats on the water zone beyond (``water_range_m``).
Confusers are the built-in vehicles not among ``classes`` and vehicle-size crates and
fuel tanks; clutter is rocks, bushes, trees and buildings. Every target is painted with
a camouflage seed no bank trains on.

Batches of scenes (``simulate field OUT --count N``) and their evaluation with a bank
(``bank eval-scenes``) run as independent units in this process or on Dask, through the
database jobs' runner (:func:`prism3d.datasets.jobs.database_jobs.run_tasks`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.detect import detect_shot
from prism3d.atr.models import load_scene_model
from prism3d.atr.scene_eval import SceneEvaluation, check_scene_folders, score_scenes, write_scene_results
from prism3d.capture.camera_effects import CameraEffects
from prism3d.capture.camouflage import CamouflageField
from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.render import RaycastRenderer
from prism3d.capture.rig import StereoRig, look_at, paper_rig
from prism3d.capture.scenes import value_noise
from prism3d.capture.simulate import Projector, ShotOptions, effects_entries, simulate_shot
from prism3d.checks import check_outputs_not_inputs, check_seed
from prism3d.datasets.models._primitives import Part, box, cylinder, ellipse, loft, prism
from prism3d.datasets.database.resolve import resolve_model
from prism3d.datasets.runner import RunOptions, run_tasks
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_write_text, check_outputs, staged_folder
from prism3d.io.images import read_image, write_image

__all__ = [
    "FIELD_SCHEMA_VERSION", "FieldOptions", "FieldScene", "detect_scene_folder", "eval_scene_folders", "plan_field",
    "scene_folder_name", "simulate_field", "simulate_field_batch",
]

FIELD_SCHEMA_VERSION = 1
#: Camouflage seeds of scene targets start here: no bank is trained on them.
SCENE_CAMO_SEED_BASE = 10_000
#: Targets whose visible fraction is below this are "difficult" (scored as neither hit nor miss).
DIFFICULT_VISIBLE_FRACTION = 0.5
#: Bank classes with a full-size footprint radius above this (mm) go on the water zone.
LAND_MAX_RADIUS_MM = 20_000.0
#: Default confusers: the built-in vehicles a default bank does not hold, and two shapes.
SHAPE_CONFUSERS = ("crate", "fuel_tank")


@dataclass(frozen=True)
class FieldOptions:
    """What ``simulate field`` places and how the rig sees it."""

    targets: int | None = None
    """Bank-class targets per scene (None: 3-6, drawn)."""
    classes: tuple[str, ...] = ("tank_t1", "jet_j1", "ship_s1", "truck_k1")
    """Built-in targets the scene's bank knows (the default bank of the checks)."""
    confusers: int | None = None
    """Confusers per scene (None: 1-3, drawn): built-ins not in ``classes``, crates, fuel tanks."""
    clutter: int = 30
    """Rocks, bushes, trees and buildings."""
    land_range_m: tuple[float, float] = (45.0, 75.0)
    """Ranges (horizontal, from below the rig) of land targets, m: from 20 m up they are
    seen 15-24 deg from above, around the 20 deg a default bank is trained at."""
    water_range_m: tuple[float, float] = (260.0, 380.0)
    """Ranges of water-borne targets (full-size ships), m."""
    camera_height_m: float = 20.0
    """Height of the rig above the ground, m."""
    depression_deg: float = 18.0
    """Angle of the rig's optical axis below the horizon (aimed at the middle of the land zone)."""
    baseline_mm: float = 4000.0
    """Stereo baseline: the paper's 4 m example for 20 m and beyond."""
    focal_px: float = 2000.0
    """Focal length of the views, px (36 x 52 deg per portrait view)."""
    sensor_size: tuple[int, int] = (2592, 1944)
    """Sensor (width, height) px: the paper's 5 MP, split into two portrait views."""
    supersample: int = 1
    """Colour rays per pixel along each axis (2 smooths edges at 4x the time)."""
    noise: bool = True
    """Sensor noise (the real-camera effects are always on)."""
    seed: int = 0
    """Seeds the layout, the paints, the sun and the noise."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "seed", check_seed(self.seed))
        for name, lo, hi in (("targets", 1, 12), ("confusers", 0, 12)):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or int(v) != v or not lo <= int(v) <= hi):
                raise InputError(f"{name}: expected an integer in [{lo}, {hi}], got {v!r}")
        if isinstance(self.clutter, bool) or int(self.clutter) != self.clutter or not 0 <= self.clutter <= 500:
            raise InputError(f"clutter: expected an integer in [0, 500], got {self.clutter!r}")
        object.__setattr__(self, "classes", tuple(self.classes))
        known = list_builtin_targets()
        if not self.classes:
            raise InputError("classes: expected at least one built-in target name")
        for c in self.classes:
            if c not in known and "=" not in c:  # FILE=CLASS:UNITS:UP:FORWARD: checked when the scene is planned
                raise InputError(f"classes: unknown built-in target {c!r}; valid: {', '.join(known)} "
                                 "(or a mesh file FILE=CLASS:UNITS:UP:FORWARD at full size)")
        for name in ("land_range_m", "water_range_m"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 5.0 <= lo < hi <= 5000.0):
                raise InputError(f"{name}: expected 5 <= near < far <= 5000 m, got {(lo, hi)}")
        if not 1.0 <= self.camera_height_m <= 500.0:
            raise InputError(f"camera_height_m: expected 1-500 m, got {self.camera_height_m}")
        if not 2.0 <= self.depression_deg <= 60.0:
            raise InputError(f"depression_deg: expected 2-60 deg, got {self.depression_deg}")
        if not (self.baseline_mm > 0 and self.focal_px > 0):
            raise InputError("baseline_mm and focal_px must be > 0")
        if int(self.supersample) != self.supersample or not 1 <= self.supersample <= 4:
            raise InputError(f"supersample: expected 1-4, got {self.supersample!r}")


# -- albedo ----------------------------------------------------------------------------
@dataclass(frozen=True)
class GroundAlbedo:
    """Grass and soil mottled by two octaves of value noise; water beyond ``water_y_mm``."""

    seed: int = 0
    water_y_mm: float = 200_000.0

    def __call__(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        a = value_noise(p, 9000.0, self.seed)
        b = value_noise(p, 1800.0, self.seed + 1)
        t = np.clip(0.7 * a + 0.3 * b, 0.0, 1.0)[:, None]
        grass = np.array([0.30, 0.38, 0.18])
        soil = np.array([0.46, 0.39, 0.27])
        out = (1.0 - t) * grass + t * soil
        fine = 0.5 * value_noise(p, 400.0, self.seed + 2) + 0.3 * value_noise(p, 140.0, self.seed + 4) \
            + 0.2 * value_noise(p, 60.0, self.seed + 5)  # tufts and blades: texture for stereo
        out *= (0.6 + 0.8 * fine)[:, None]
        wet = p[:, 1] > self.water_y_mm
        out[wet] = np.array([0.10, 0.13, 0.16]) * (0.9 + 0.2 * value_noise(p[wet], 3000.0, self.seed + 3))[:, None]
        return np.clip(out, 0.0, 1.0)


# -- geometry --------------------------------------------------------------------------
@dataclass(frozen=True)
class Terrain:
    """Rolling ground: a few long plane waves (amplitude ``amp_mm``), flat water beyond
    ``water_y_mm`` (heights taper to 0 over the last 40 m of land)."""

    waves: tuple[tuple[float, float, float, float], ...]  # (kx, ky, phase, amplitude) per mm
    water_y_mm: float

    def height(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        h = np.zeros(np.broadcast(x, y).shape)
        for kx, ky, ph, a in self.waves:
            h += a * np.sin(kx * x + ky * y + ph)
        taper = np.clip((self.water_y_mm - y) / 40_000.0, 0.0, 1.0)
        return h * taper - 400.0 * (y > self.water_y_mm)

    def mesh(self, half_width_at: Callable[[float], float], y0: float, y1: float, seed: int) -> SceneMesh:
        """A grid widening with distance (columns fixed, rows denser near the rig)."""
        nu, nv = 241, 181
        ys = y0 * (y1 / y0) ** (np.arange(nv) / (nv - 1.0))
        u = np.linspace(-1.0, 1.0, nu)
        X = u[None, :] * np.array([half_width_at(y) for y in ys])[:, None]
        Y = np.broadcast_to(ys[:, None], X.shape)
        Z = self.height(X, Y)
        V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        i = np.arange(nv - 1)[:, None] * nu + np.arange(nu - 1)[None, :]
        i = i.ravel()
        F = np.concatenate([np.stack([i, i + 1, i + nu + 1], 1), np.stack([i, i + nu + 1, i + nu], 1)])
        return SceneMesh(V, F, None, GroundAlbedo(seed, self.water_y_mm), "ground", {"material": "lambertian"})


def _join(parts: Sequence[Part]) -> tuple[NDArray, NDArray]:
    off = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    return np.vstack([v for v, _ in parts]), np.vstack([f + o for (_, f), o in zip(parts, off)])


def _ellipsoid(c: Sequence[float], r: Sequence[float], n: int = 12) -> Part:
    """Closed ellipsoid (metres in, mm out) as a loft of rings with apexes."""
    rings = []
    for t in np.linspace(-1.0, 1.0, 9)[1:-1]:
        s = math.sqrt(1.0 - t * t)
        rings.append(ellipse((c[0], c[1], c[2] + r[2] * t), 2, r[0] * s, r[1] * s, n))
    return loft(rings, start_apex=np.array([c[0], c[1], c[2] - r[2]]) * 1000.0,
                end_apex=np.array([c[0], c[1], c[2] + r[2]]) * 1000.0)


def _prop(kind: str, rng: np.random.Generator) -> tuple[list[Part], tuple[float, float, float], str]:
    """Parts (metres, base at z = 0), colour and name of one clutter or confuser shape."""
    if kind == "rock":
        r = rng.uniform(0.3, 1.0)
        return [_ellipsoid((0, 0, 0.35 * r), (r, r * rng.uniform(0.6, 1.0), 0.6 * r), 8)], (0.45, 0.43, 0.40), "rock"
    if kind == "bush":
        r = rng.uniform(0.6, 1.6)
        return [_ellipsoid((0, 0, 0.7 * r), (r, r * rng.uniform(0.7, 1.0), 0.8 * r), 10)], (0.16, 0.24, 0.10), "bush"
    if kind == "tree":
        h = rng.uniform(5.0, 9.0)
        rc = rng.uniform(1.5, 2.8)
        parts = [cylinder((0, 0, 0), (0, 0, h * 0.5), 0.2, 0.15, 8),
                 _ellipsoid((0, 0, h - rc), (rc, rc, rc * 1.1), 12)]
        return parts, (0.14, 0.22, 0.09), "tree"
    if kind == "building":
        L, W, H = rng.uniform(8, 16), rng.uniform(6, 10), rng.uniform(3, 6)
        roof = prism([(-W / 2, H), (W / 2, H), (0, H + 0.35 * W)], 0, -L / 2, L / 2)
        return [box((-L / 2, -W / 2, 0), (L / 2, W / 2, H)), roof], (0.55, 0.50, 0.45), "building"
    if kind == "crate":
        L, W, H = rng.uniform(6.0, 9.0), rng.uniform(2.4, 3.2), rng.uniform(2.4, 3.2)
        return [box((-L / 2, -W / 2, 0), (L / 2, W / 2, H))], (0.30, 0.32, 0.20), "crate"
    if kind == "fuel_tank":
        L, r = rng.uniform(7.0, 10.0), rng.uniform(1.2, 1.6)
        return [cylinder((-L / 2, 0, r), (L / 2, 0, r), r, n=16),
                box((-L / 2 + 0.5, -r * 0.6, 0), (L / 2 - 0.5, r * 0.6, 0.4))], (0.28, 0.30, 0.22), "fuel_tank"
    raise InputError(f"unknown prop kind {kind!r}")


def prop_mesh(kind: str, rng: np.random.Generator, seed: int) -> SceneMesh:
    parts, rgb, name = _prop(kind, rng)
    V, F = _join(parts)
    if kind in SHAPE_CONFUSERS:  # painted like the targets, so paint alone gives nothing away
        paint = CamouflageField.from_palette("woodland", patch_size_mm=1500.0, seed=seed)
        return SceneMesh(V, F, None, paint, name, {"material": "painted_metal"})
    jitter = np.clip(np.asarray(rgb) * rng.uniform(0.85, 1.15), 0, 1)
    return SceneMesh(V, F, None, UniformAlbedo(tuple(float(c) for c in jitter)), name, {"material": "lambertian"})


def replace_metadata(mesh: SceneMesh, cls: str) -> SceneMesh:
    """The mesh with its class recorded in its metadata (truth records read it there)."""
    return SceneMesh(mesh.vertices, mesh.faces, mesh.vertex_albedo, mesh.albedo_field, mesh.name,
                     {**mesh.metadata, "class": cls})


def _pose(x: float, y: float, z: float, heading_deg: float) -> NDArray[np.float64]:
    a = math.radians(heading_deg)
    T = np.eye(4)
    T[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = (x, y, z)
    return T


# -- the plan --------------------------------------------------------------------------
@dataclass(eq=False)
class FieldScene:
    """A planned field scene: rig, its pose, objects (world frame), sun, truth records."""

    rig: StereoRig
    T_world_rig: NDArray[np.float64]
    objects: list[tuple[SceneMesh, NDArray[np.float64]]]  # (mesh, T_world_obj)
    records: list[dict[str, Any]]  # one per target/confuser: name, class, confuser, object index...
    sun_dir_world: NDArray[np.float64]
    options: FieldOptions
    meta: dict[str, Any] = field(default_factory=dict)


def _field_rig(o: FieldOptions) -> tuple[StereoRig, NDArray[np.float64]]:
    """The scaled prism rig (converging at the mid land range) and ``T_world_rig``."""
    h = o.camera_height_m * 1000.0
    dep = math.radians(o.depression_deg)
    wd = h / math.sin(dep)
    rig = paper_rig(working_distance_mm=wd, baseline_mm=o.baseline_mm, focal_px=o.focal_px,
                    sensor_size=tuple(int(v) for v in o.sensor_size), dist=(-0.02, 0.01, 0.0, 0.0, 0.0))
    eye = np.array([0.0, 0.0, h])
    target = np.array([0.0, h / math.tan(dep), 0.0])
    return rig, look_at(eye, target, up=(0.0, 0.0, 1.0))


def _in_view(rig: StereoRig, T_world_rig: NDArray, pts_world: NDArray, margin_px: float = 20.0) -> bool:
    """All points project inside both views (with a margin), in front of the cameras."""
    for cam, T_rig_cam in ((rig.left, rig.T_rig_left), (rig.right, rig.T_rig_right)):
        T = np.linalg.inv(T_world_rig @ T_rig_cam)
        pc = pts_world @ T[:3, :3].T + T[:3, 3]
        if np.any(pc[:, 2] <= 1000.0):
            return False
        uv = cam.project(pc)
        w, h = cam.size
        if not (np.all(uv[:, 0] >= margin_px) and np.all(uv[:, 0] <= w - 1 - margin_px)
                and np.all(uv[:, 1] >= margin_px) and np.all(uv[:, 1] <= h - 1 - margin_px)):
            return False
    return True


def _terrain_waves(rng: np.random.Generator) -> tuple[tuple[float, float, float, float], ...]:
    """The rolling terrain's three ground swells ``(kx, ky, phase, amplitude mm)``, drawn
    from ``rng``."""
    return tuple((float(math.cos(t) * k), float(math.sin(t) * k), float(rng.uniform(0, 2 * math.pi)), float(a))
                 for t, k, a in zip(rng.uniform(0, math.pi, 3),
                                    2 * math.pi / (rng.uniform(35, 90, 3) * 1000.0), (600.0, 350.0, 200.0)))


def _place(mesh: SceneMesh, zone: tuple[float, float], rng: np.random.Generator, terrain: Terrain,
           view: tuple[StereoRig, NDArray[np.float64], float], taken: list[tuple[float, float, float]],
           spacing: float = 1.5, tries: int = 200, in_view: bool = True) -> NDArray | None:
    """``T_world_obj`` of a free spot for ``mesh`` (range in ``zone`` m, bearing within ``view``'s
    half fov, sunk into the terrain, whole in both views if ``in_view``), added to ``taken``; or None."""
    rig, T_world_rig, half_fov = view
    lo, hi = mesh.bounds
    rad = float(np.hypot(*(hi[:2] - lo[:2])) / 2.0)
    for _ in range(tries):
        rng_m = rng.uniform(*zone) * 1000.0
        bearing = rng.uniform(-half_fov, half_fov)
        x, y = rng_m * math.sin(bearing), rng_m * math.cos(bearing)
        if any(math.hypot(x - a, y - b) < spacing * (rad + r) for a, b, r in taken):
            continue
        head = float(rng.uniform(0.0, 360.0))
        T = _pose(x, y, 0.0, head)
        fp = np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], lo[1]], [hi[0], hi[1]], [0, 0]])
        fw = fp @ T[:2, :2].T + T[:2, 3]
        T[2, 3] = float(np.min(terrain.height(fw[:, 0], fw[:, 1]))) - 30.0
        if in_view:
            corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
            if not _in_view(rig, T_world_rig, corners @ T[:3, :3].T + T[:3, 3]):
                continue
        taken.append((x, y, rad))
        return T
    return None


def _pick_objects(o: FieldOptions, rng: np.random.Generator) -> list[tuple[str, bool]]:
    """``(name, confuser)`` of the scene's targets (drawn from ``o.classes``), then of its
    confusers (other military built-ins, not ships, and the shape confusers)."""
    n_t = int(rng.integers(3, 7)) if o.targets is None else int(o.targets)
    n_c = int(rng.integers(1, 4)) if o.confusers is None else int(o.confusers)
    picks = [(str(rng.choice(list(o.classes))), False) for _ in range(n_t)]
    others = [n for n in list_builtin_targets("military") if n not in o.classes and not n.startswith("ship")]
    pool = others + list(SHAPE_CONFUSERS)
    picks += [(str(rng.choice(pool)), True) for _ in range(n_c)]
    return picks


def _object_mesh(name: str, rng: np.random.Generator, seed_k: int) -> SceneMesh:
    """Full-size mesh of a picked target or confuser: a shape confuser (drawn from ``rng``),
    a user's mesh file spec or a built-in, painted with camouflage seed ``seed_k``."""
    if name in SHAPE_CONFUSERS:
        return prop_mesh(name, rng, seed_k)
    if "=" in name:  # a user's mesh file, full size, its class in the spec
        cls, mesh = resolve_model(name, scale="full")
        return replace_metadata(mesh, cls)
    return builtin_target(name, scale="full", seed=seed_k)


def plan_field(options: FieldOptions | None = None) -> FieldScene:
    """Draw a field scene: layout, paints and sun from ``options.seed`` (no rendering)."""
    o = FieldOptions() if options is None else options
    rng = np.random.default_rng(o.seed)
    rig, T_world_rig = _field_rig(o)
    wy = 0.5 * (o.land_range_m[1] + o.water_range_m[0]) * 1000.0
    waves = _terrain_waves(rng)
    terrain = Terrain(waves, wy)
    half_fov = math.atan(rig.left.width / 2.0 / rig.left.fx) + 0.1
    ground = terrain.mesh(lambda y: y * math.tan(half_fov) + 25_000.0, 4000.0, o.water_range_m[1] * 1600.0, o.seed)
    objects: list[tuple[SceneMesh, NDArray]] = [(ground, np.eye(4))]
    records: list[dict[str, Any]] = []
    taken: list[tuple[float, float, float]] = []  # (x, y, radius) mm of placed footprints
    view = (rig, T_world_rig, half_fov)
    for k, (name, confuser) in enumerate(_pick_objects(o, rng)):
        seed_k = SCENE_CAMO_SEED_BASE + o.seed * 16 + k
        mesh = _object_mesh(name, rng, seed_k)
        lo, hi = mesh.bounds
        water = float(np.hypot(*(hi[:2] - lo[:2])) / 2.0) > LAND_MAX_RADIUS_MM
        T = _place(mesh, o.water_range_m if water else o.land_range_m, rng, terrain, view, taken, spacing=1.3)
        if T is None:
            continue
        if water:
            T[2, 3] = -0.12 * (hi[2] - lo[2])  # draught: the hull sits in the water
        records.append({"name": name, "class": str(mesh.metadata.get("class", name)), "confuser": bool(confuser),
                        "object_index": len(objects), "heading_deg": float(np.degrees(math.atan2(T[1, 0], T[0, 0]))) % 360.0,
                        "zone": "water" if water else "land", "camouflage_seed": seed_k})
        objects.append((mesh, T))
    kinds = rng.choice(["rock", "bush", "tree", "building"], size=int(o.clutter), p=[0.35, 0.35, 0.2, 0.1])
    for j, kind in enumerate(kinds):
        mesh = prop_mesh(str(kind), rng, o.seed * 1000 + j)
        T = _place(mesh, (o.land_range_m[0] * 0.8, o.land_range_m[1] * 1.6), rng, terrain, view, taken,
                   spacing=1.1, tries=30, in_view=False)
        if T is not None:
            objects.append((mesh, T))
    el = math.radians(rng.uniform(35.0, 65.0))
    az = rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    meta = {"terrain_waves": [list(w) for w in waves], "water_y_mm": wy}
    return FieldScene(rig, T_world_rig, objects, records, sun, o, meta)


# -- rendering and truth ----------------------------------------------------------------
def _sun_projector(scene: FieldScene) -> Any:
    """The sun as a distant white projector aimed at the field (shadows come free)."""
    centre = np.array([0.0, np.mean(scene.options.land_range_m) * 1000.0, 0.0])
    return distant_sun(scene.sun_dir_world, centre, scene.options.water_range_m[1] * 1000.0,
                        np.linalg.inv(scene.T_world_rig))


def distant_sun(sun_dir_world: NDArray, centre_world: NDArray, radius_mm: float,
                 T_rig_world: NDArray | None = None) -> Any:
    """A white projector 10 km from ``centre_world`` (mm) along ``sun_dir_world``, lighting
    a disc of ``radius_mm`` there with margin; its pose in the rig frame (world by default)."""
    dist = 1.0e7
    sun = np.asarray(sun_dir_world, dtype=np.float64)
    centre = np.asarray(centre_world, dtype=np.float64)
    pos = centre + dist * sun
    T_world_proj = look_at(pos, centre, up=(0.0, 0.0, 1.0) if abs(sun[2]) < 0.99 else (0, 1, 0))
    T_rig_proj = T_world_proj if T_rig_world is None else np.asarray(T_rig_world) @ T_world_proj
    w = h = 512
    f = w * dist / (2.5 * radius_mm)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return Projector(K, (w, h), None, T_rig_proj, dist)


def _target_truth(scene: FieldScene, objs: list[tuple[SceneMesh, NDArray]],
                  oid: NDArray) -> list[dict[str, Any]]:
    """``truth.json`` ``targets`` records (see :func:`simulate_field`) of the scene's targets and
    confusers, from the rendered left-view object ids ``oid`` and ``objs`` in the rig frame."""
    rig = scene.rig
    T_left_rig = np.linalg.inv(rig.T_rig_left)
    targets = []
    for k, rec in enumerate(scene.records):
        mesh, T_rig_obj = objs[rec["object_index"]]
        vis = oid == rec["object_index"]
        alone = _silhouette(mesh, T_rig_obj, rig)
        frac = float(vis.sum() / max(alone.sum(), 1))
        T_left_obj = T_left_rig @ T_rig_obj
        c_obj = mesh.bounds.mean(axis=0)
        xyz = T_left_obj[:3, :3] @ c_obj + T_left_obj[:3, 3]
        rr, cc = np.nonzero(vis if vis.any() else alone)
        box_rc = [int(rr.min()), int(cc.min()), int(rr.max()), int(cc.max())] if len(rr) else [0, 0, -1, -1]
        targets.append({
            "instance": k, "class": rec["class"], "name": rec["name"], "confuser": rec["confuser"], "box_rc": box_rc,
            "xyz_mm": [float(v) for v in xyz], "radius_mm": float(np.max(np.linalg.norm(mesh.vertices - c_obj, axis=1))),
            "range_mm": float(np.linalg.norm(xyz)), "heading_deg": rec["heading_deg"], "zone": rec["zone"],
            "visible_fraction": round(frac, 4), "difficult": bool(frac < DIFFICULT_VISIBLE_FRACTION),
            "camouflage_seed": rec["camouflage_seed"], "object_index": rec["object_index"],
        })
    return targets


def simulate_field(out_dir: str | Path, options: FieldOptions | None = None, *,
                   progress: Callable[[int, int, str], None] | None = None) -> dict[str, Any]:
    """Render a field scene and write ``shot.png``, ``rig.yaml``, ``truth.json`` and
    ``truth.npz`` (left-view depth and object ids) into ``out_dir``, all or nothing.

    ``truth.json`` ``targets``: one record per target and confuser: ``class``,
    ``confuser``, ``box_rc`` ``[r0, c0, r1, c1]`` (left view, visible pixels, inclusive),
    ``xyz_mm`` (bounding-box centre, left camera frame), ``radius_mm`` (bounding radius),
    ``range_mm``, ``heading_deg``, ``visible_fraction``, ``difficult`` (visible fraction
    below :data:`DIFFICULT_VISIBLE_FRACTION`), ``instance``, ``name`` (built-in target or
    shape), ``object_index`` (its id in ``truth.npz`` ``object_id_left``; 0 is the ground).
    """
    o = FieldOptions() if options is None else options
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise InputError(f"{out}: folder is not empty; give a new folder for the field scene")
    t0 = time.perf_counter()
    scene = plan_field(o)
    if progress:
        progress(0, 3, "planned")
    T_rig_world = np.linalg.inv(scene.T_world_rig)
    objs = [(m, T_rig_world @ T) for m, T in scene.objects]
    renderer = RaycastRenderer(objs)
    shot = simulate_shot(scene.rig, objs, ShotOptions(ambient=0.35, flash=0.85, supersample=o.supersample,
                                                      noise=o.noise, seed=o.seed, effects=CameraEffects()),
                         projector=_sun_projector(scene), renderer=renderer)
    if progress:
        progress(1, 3, "rendered")
    rig = scene.rig
    oid = shot.truth["object_id_left"]
    targets = _target_truth(scene, objs, oid)
    doc = {
        "schema_version": FIELD_SCHEMA_VERSION, "units": "mm",
        "camera": "left view of the prism rig, OpenCV frame; box_rc in left-view pixels",
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(o).items()},
        "sun_dir_world": [float(v) for v in scene.sun_dir_world],
        "T_world_rig": scene.T_world_rig.tolist(),
        "n_objects": len(objs), "targets": targets,
    }
    with staged_folder(out) as stage:
        write_image(stage / "shot.png", shot.sensor_image)
        rig.save(stage / "rig.yaml", extra={"simulated": 1, **effects_entries(CameraEffects(), 0.0)})
        np.savez_compressed(stage / "truth.npz", depth_left_mm=shot.truth["depth_left_mm"],
                            object_id_left=oid.astype(np.int16))
        atomic_write_text(stage / "truth.json", json.dumps(doc, indent=1))
    if progress:
        progress(3, 3, "written")
    return {"out_dir": str(out), "n_targets": sum(not t["confuser"] for t in targets),
            "n_confusers": sum(t["confuser"] for t in targets), "seconds": time.perf_counter() - t0,
            "files": ["rig.yaml", "shot.png", "truth.json", "truth.npz"]}


def _silhouette(mesh: SceneMesh, T_rig_obj: NDArray, rig: StereoRig) -> NDArray[np.bool_]:
    """Pixels of the left view the object would cover with nothing in front of it."""
    r = RaycastRenderer([(mesh, T_rig_obj)])
    w, h = rig.left.size
    mask = np.zeros(w * h, dtype=bool)

    def band(s: int, e: int, hb: Any) -> None:
        mask[hb.index] = True

    r.stream_camera(rig.left, rig.T_rig_left, band)
    return mask.reshape(h, w)


#: Files a complete field scene folder holds (``simulate_field`` writes them together).
SCENE_FILES = ("rig.yaml", "shot.png", "truth.json", "truth.npz")


def scene_folder_name(seed: int) -> str:
    """The folder of the scene with ``seed`` in a batch: ``scene_0042``."""
    return f"scene_{seed:04d}"


def _field_unit(out_dir: str, options: dict[str, Any]) -> dict[str, Any]:
    """One batch unit (a Dask task): the scene of ``options`` into ``out_dir``."""
    opts = FieldOptions(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in options.items()})
    return simulate_field(out_dir, opts)


def simulate_field_batch(out_dir: str | Path, count: int, options: FieldOptions | None = None,
                         run: Any = None) -> Any:
    """``count`` field scenes with seeds ``options.seed``, ``+1``... into
    ``out_dir/scene_<seed>`` as independent units, in this process or on Dask
    (``run``: :class:`~prism3d.datasets.jobs.database_jobs.RunOptions`). Each scene appears whole or not
    at all, so a rerun resumes: complete scene folders are kept and counted as skipped;
    ``batch.json`` (seeds, options, seconds, scenes per minute) is rewritten at the end.
    Returns the :class:`~prism3d.datasets.jobs.database_jobs.JobReport`."""
    o = FieldOptions() if options is None else options
    if isinstance(count, bool) or int(count) != count or not 1 <= int(count) <= 100_000:
        raise InputError(f"count: expected an integer in [1, 100000], got {count!r}")
    run = RunOptions() if run is None else run
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    seeds = [o.seed + k for k in range(int(count))]
    opts_doc = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(o).items()}
    old = out / "batch.json"
    if old.is_file():  # a resumed batch must not mix scenes made with other options
        try:
            before = json.loads(old.read_text()).get("options", {})
        except (OSError, ValueError, RecursionError, AttributeError):  # unreadable, or not a batch's object
            before = None
        if before != opts_doc:
            raise InputError(f"{out}: holds a batch made with other options ({old}); give a new folder")
    tasks, done = [], 0
    for s in seeds:
        d = out / scene_folder_name(s)
        if d.is_dir() and all((d / f).is_file() for f in SCENE_FILES):
            done += 1
            continue
        if d.exists():
            raise InputError(f"{d}: exists but is not a complete field scene; remove it and run again")
        tasks.append((d.name, "field scene", _field_unit, (str(d), asdict(replace(o, seed=s)))))
    report = run_tasks("field", tasks, run)
    report.total_units, report.skipped_units = len(seeds), done
    made = [st for st in report.stats if st]
    busy = sum(st["seconds"] for st in made)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "batch.json", json.dumps({
        "scenes": [scene_folder_name(s) for s in seeds], "seeds": seeds,
        "options": opts_doc,
        "made_now": len(made), "resumed": done, "failed": report.failed,
        "wall_seconds": round(report.seconds, 2), "scene_seconds": round(busy, 2),
        "scenes_per_minute": round(60.0 * len(made) / report.seconds, 2) if made and report.seconds > 0 else None,
        "workers": run.workers, "scheduler": run.scheduler,
    }, indent=1))
    return report


# -- evaluation jobs ---------------------------------------------------------------


def detect_scene_folder(bank_path: str, scene: str) -> dict:
    """One unit of ``eval-scenes`` (a Dask task): the bank's detections in one scene folder
    (``scene``, ``detections``, ``timings_s``)."""
    p = Path(scene)
    dets, times = detect_shot(load_scene_model(bank_path), read_image(p / "shot.png"), StereoRig.load(p / "rig.yaml"))
    return {"scene": str(p), "timings_s": times, "detections": [d.to_json() for d in dets]}


def eval_scene_folders(bank_path, scenes: Sequence[str], *, out_json=None, progress=None,
                       run=None) -> SceneEvaluation:
    """``prism3d bank eval-scenes``: detect with the bank in every scene folder and score
    (:func:`~prism3d.atr.scene_eval.score_scenes`); scenes are independent units run in
    this process or on Dask (``run``: :class:`~prism3d.datasets.jobs.database_jobs.RunOptions`; its
    progress wins over ``progress``); results (with each scene's detections and timings) go to ``out_json``
    atomically when given. A scene that fails stops the evaluation (a score over fewer
    scenes would not be the score asked for)."""
    if out_json is not None and Path(out_json).suffix.lower() != ".json":
        raise InputError(f"{out_json}: expected a .json file name for the results")
    if out_json is not None:  # neither the results nor their plot may replace the model or land in a scene
        outs = [Path(out_json), Path(f"{Path(out_json).with_suffix('')}_fppi.png")]
        check_outputs_not_inputs(outs, [bank_path], input_folders=scenes)
        check_outputs(outs)  # the plot's name too: a folder there fails now, not after the detections
    checked = check_scene_folders(scenes)  # every scene whole, before any detection
    folders, truths = [p for p, _ in checked], [t for _, t in checked]
    bank = load_scene_model(bank_path)
    run = RunOptions() if run is None else run
    if run.progress is None and progress is not None:
        run = replace(run, progress=progress)
    t0 = time.perf_counter()
    tasks = [(p.name, "detect", detect_scene_folder, (str(bank_path), str(p))) for p in folders]
    report = run_tasks("eval-scenes", tasks, replace(run, retries=0))
    if report.failed:
        f = report.failed[0]
        raise InputError(f"eval-scenes: {len(report.failed)} of {len(folders)} scenes failed "
                         f"(first: {f['unit']}: {f['error']}); nothing written")
    by_scene = {r["scene"]: r for r in report.stats}
    per_scene = [by_scene[str(p)] for p in folders]
    pairs = [({"detections": r["detections"]}, truth) for r, truth in zip(per_scene, truths)]
    res = SceneEvaluation(score_scenes(pairs), str(bank_path),
                          ",".join(getattr(bank, "channels", [getattr(bank, "channel", "")])), list(bank.classes),
                          time.perf_counter() - t0, run.workers, per_scene)
    if out_json is not None:
        write_scene_results(res, Path(out_json))
    return res
