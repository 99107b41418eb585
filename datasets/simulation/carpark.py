"""Car parks for ``prism3d simulate flight --scene carpark``: a level paved lot with painted
bays, rows of parked civilian vehicles (body colours drawn as in real car parks, black and
white included), long bays for buses and box trucks, trees along the edges whose crowns
overhang the first row, people in the aisles and light poles.

Lot frame: ``a`` along the rows (bays side by side), ``b`` across them; a row is 5 m deep,
an aisle 6.5 m, a car bay 2.5 m wide, a long bay 3.5 x 12 m. World: ENU metres (meshes in
mm). Used by :mod:`prism3d.datasets.simulation.flight`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.scenes import value_noise
from prism3d.datasets.models._primitives import box, cylinder, ellipse, loft
from prism3d.datasets.simulation.field import prop_mesh
from prism3d.datasets.models.targets import builtin_target

__all__ = ["BAY_WIDTH_M", "Lot", "lot_albedo", "lot_clutter", "park_vehicles", "person_mesh", "plan_lot", "pole_mesh"]

BAY_WIDTH_M, BAY_DEPTH_M, AISLE_M = 2.5, 5.0, 6.5
LONG_BAY_WIDTH_M, LONG_BAY_DEPTH_M = 3.5, 12.0
LINE_HALF_WIDTH_M = 0.06
#: Vehicles of a car bay and their shares (kei cars and trucks as in a Japanese car park).
CAR_BAY_MIX = (("car_sedan", 0.20), ("car_hatchback", 0.20), ("car_suv", 0.18), ("car_kei", 0.22),
               ("van_panel", 0.08), ("truck_pickup", 0.05), ("truck_kei", 0.07))
LONG_BAY_MIX = (("bus_city", 0.5), ("truck_box", 0.5))


@dataclass(frozen=True)
class Lot:
    """A paved lot: centre ``(cx, cy)`` and row direction ``(ux, uy)`` (ENU m), half sizes
    along and across the rows, its level ``z`` (m), painted lines ``(a0, b0, a1, b1)`` in
    the lot frame, the surface (``asphalt`` or ``concrete``) and its paint seed."""

    cx: float
    cy: float
    ux: float
    uy: float
    half_a: float
    half_b: float
    z: float
    lines: tuple[tuple[float, float, float, float], ...]
    surface: str
    seed: int

    def to_lot(self, x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
        dx, dy = np.asarray(x, dtype=np.float64) - self.cx, np.asarray(y, dtype=np.float64) - self.cy
        return dx * self.ux + dy * self.uy, -dx * self.uy + dy * self.ux

    def to_world(self, a: float, b: float) -> tuple[float, float]:
        return self.cx + a * self.ux - b * self.uy, self.cy + a * self.uy + b * self.ux

    def inside(self, x: NDArray, y: NDArray, margin: float = 0.0) -> NDArray[np.bool_]:
        a, b = self.to_lot(x, y)
        return (np.abs(a) <= self.half_a + margin) & (np.abs(b) <= self.half_b + margin)

    def level_weight(self, x: NDArray, y: NDArray, blend: float = 4.0) -> NDArray[np.float64]:
        """1 on the lot, falling smoothly to 0 ``blend`` m outside it."""
        a, b = self.to_lot(x, y)
        d = np.maximum(np.abs(a) - self.half_a, np.abs(b) - self.half_b)
        s = np.clip(d / blend, 0.0, 1.0)
        return 1.0 - s * s * (3.0 - 2.0 * s)

    def on_line(self, a: NDArray, b: NDArray) -> NDArray[np.bool_]:
        out = np.zeros(np.shape(a), dtype=bool)
        for a0, b0, a1, b1 in self.lines:
            if a0 == a1:
                out |= (np.abs(a - a0) <= LINE_HALF_WIDTH_M) & (b >= min(b0, b1)) & (b <= max(b0, b1))
            else:
                out |= (np.abs(b - b0) <= LINE_HALF_WIDTH_M) & (a >= min(a0, a1)) & (a <= max(a0, a1))
        return out


@dataclass(frozen=True)
class Bay:
    """A parking bay: its centre in the lot frame, the way a vehicle in it faces (+1: +b),
    its kind (``car`` or ``long``)."""

    a: float
    b: float
    facing: int
    kind: str


def plan_lot(rng: np.random.Generator, centre: tuple[float, float], direction_rad: float, z: float,
             span_a: float, span_b: float, seed: int) -> tuple[Lot, list[Bay]]:
    """A lot fitting in ``span_a`` x ``span_b`` m (rows along ``direction_rad``, from east
    counter-clockwise): double rows of car bays, and a row of long bays when there is room."""
    n_a = max(4, int((span_a - 2.0) // BAY_WIDTH_M))
    width_a = n_a * BAY_WIDTH_M
    # across: row | aisle | row row | aisle | row ... then an aisle and long bays if room
    double = [("row+", BAY_DEPTH_M), ("aisle", AISLE_M), ("row-", BAY_DEPTH_M)]
    tail = [("aisle", AISLE_M), ("long", LONG_BAY_DEPTH_M)]  # buses and box trucks, when there is room
    bands: list[tuple[str, float]] = list(double)
    room = span_b - 2.0 - sum(w for _, w in bands)
    want_long = room >= sum(w for _, w in tail)
    while room - sum(w for _, w in double) - (sum(w for _, w in tail) if want_long else 0.0) >= 0 \
            and len(bands) < 9:
        bands += double
        room -= sum(w for _, w in double)
    if want_long:
        bands += tail
    total_b = sum(w for _, w in bands)
    half_a, half_b = width_a / 2.0 + 1.0, total_b / 2.0 + 1.0
    bays: list[Bay] = []
    lines: list[tuple[float, float, float, float]] = []
    b0 = -total_b / 2.0
    for kind, w in bands:
        if kind.startswith("row"):
            facing = 1 if kind == "row+" else -1  # the vehicle's nose towards the aisle beside it
            for i in range(n_a + 1):
                a = -width_a / 2.0 + i * BAY_WIDTH_M
                lines.append((a, b0, a, b0 + w))
            for i in range(n_a):
                bays.append(Bay(-width_a / 2.0 + (i + 0.5) * BAY_WIDTH_M, b0 + w / 2.0, facing, "car"))
        elif kind == "long":
            n_long = int(width_a // LONG_BAY_WIDTH_M)
            a_start = -n_long * LONG_BAY_WIDTH_M / 2.0
            for i in range(n_long + 1):
                lines.append((a_start + i * LONG_BAY_WIDTH_M, b0, a_start + i * LONG_BAY_WIDTH_M, b0 + w))
            for i in range(n_long):
                bays.append(Bay(a_start + (i + 0.5) * LONG_BAY_WIDTH_M, b0 + w / 2.0, -1, "long"))
        b0 += w
    surface = "asphalt" if rng.uniform() < 0.75 else "concrete"
    lot = Lot(float(centre[0]), float(centre[1]), math.cos(direction_rad), math.sin(direction_rad), half_a, half_b,
              float(z), tuple(lines), surface, int(seed))
    return lot, bays


def lot_albedo(lot: Lot, p_mm: NDArray[np.float64], scale: float) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Which points (mm, world) lie on the lot and their albedo there: asphalt (dark,
    mottled, oil stains) or concrete (light, slab joints), white painted lines. Noise
    cells are ``scale`` times larger than at full resolution (none finer than the camera
    resolves)."""
    x, y = p_mm[:, 0] / 1000.0, p_mm[:, 1] / 1000.0
    on = lot.inside(x, y)
    out = np.zeros((len(p_mm), 3))
    idx = np.flatnonzero(on)
    if not len(idx):
        return on, out
    q = p_mm[idx]
    n = 0.5 * value_noise(q, 2500.0, lot.seed + 21) + 0.3 * value_noise(q, 400.0 * scale, lot.seed + 22) \
        + 0.2 * value_noise(q, 90.0 * scale, lot.seed + 23)
    if lot.surface == "asphalt":
        base = np.array([0.14, 0.14, 0.15])[None, :] * (0.65 + 0.7 * n)[:, None]
        stain = value_noise(q, 1200.0, lot.seed + 24) > 0.78
        base[stain] *= 0.7
    else:
        base = np.array([0.42, 0.41, 0.38])[None, :] * (0.8 + 0.4 * n)[:, None]
    a, b = lot.to_lot(x[idx], y[idx])
    paint = lot.on_line(a, b)
    base[paint] = np.array([0.78, 0.78, 0.74])
    out[idx] = np.clip(base, 0.0, 1.0)
    return on, out


def _pick(rng: np.random.Generator, mix: tuple[tuple[str, float], ...]) -> str:
    names = [n for n, _ in mix]
    p = np.array([w for _, w in mix])
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def park_vehicles(rng: np.random.Generator, lot: Lot, bays: list[Bay], count: int | None,
                  seed_base: int) -> list[tuple[SceneMesh, NDArray[np.float64], dict[str, Any]]]:
    """Vehicles in ``count`` bays (None: 70-95 % of the car bays and half the long bays),
    each centred in its bay to within 0.2 m and 3 deg, one in five parked the other way
    round; returns ``(mesh, T_world_obj (mm), record)``."""
    car = [i for i, bb in enumerate(bays) if bb.kind == "car"]
    long = [i for i, bb in enumerate(bays) if bb.kind == "long"]
    if count is None:
        chosen = list(rng.choice(car, size=int(round(rng.uniform(0.70, 0.95) * len(car))), replace=False))
        if long:
            chosen += list(rng.choice(long, size=max(1, len(long) // 2), replace=False))
    else:
        pool = car + long
        chosen = list(rng.choice(pool, size=min(int(count), len(pool)), replace=False))
    out = []
    for k, i in enumerate(sorted(int(c) for c in chosen)):
        bay = bays[i]
        name = _pick(rng, LONG_BAY_MIX if bay.kind == "long" else CAR_BAY_MIX)
        seed = seed_base + k
        mesh = builtin_target(name, scale="full", seed=seed)
        depth = LONG_BAY_DEPTH_M if bay.kind == "long" else BAY_DEPTH_M
        length = float(mesh.extent_mm[0]) / 1000.0
        facing = bay.facing * (-1 if rng.uniform() < 0.2 else 1)
        # nose towards the aisle: the body pulled to the bay's aisle end, a little slack
        slack = max(0.0, (depth - length) / 2.0 - 0.3)
        b = bay.b + bay.facing * rng.uniform(0.0, slack) + rng.normal(0.0, 0.08)
        a = bay.a + rng.normal(0.0, 0.12)
        # forward = facing x the lot's b axis, (-uy, ux) in ENU; as an angle from east
        ang = math.atan2(facing * lot.ux, -facing * lot.uy) + math.radians(rng.normal(0.0, 2.0))
        x, y = lot.to_world(a, b)
        T = np.eye(4)
        T[:3, :3] = [[math.cos(ang), -math.sin(ang), 0.0], [math.sin(ang), math.cos(ang), 0.0], [0.0, 0.0, 1.0]]
        T[:3, 3] = (x * 1000.0, y * 1000.0, lot.z * 1000.0 - 20.0)
        out.append((mesh, T, {"name": name, "class": str(mesh.metadata["class"]), "confuser": False,
                              "paint": mesh.metadata.get("paint"), "paint_seed": seed}))
    return out


def person_mesh(rng: np.random.Generator) -> SceneMesh:
    """A standing person, 1.55-1.85 m: legs, torso, head (metres in, mm out)."""
    h = rng.uniform(1.55, 1.85)
    legs = box((-0.12, -0.18, 0.0), (0.12, 0.18, 0.47 * h))
    torso = box((-0.13, -0.23, 0.47 * h), (0.13, 0.23, 0.82 * h))
    rings = [ellipse((0.0, 0.0, 0.82 * h + 0.02 + 0.2 * t * h / 1.7), 2, 0.1 * s, 0.09 * s, 10)
             for t, s in ((0.1, 0.6), (0.35, 1.0), (0.65, 1.0), (0.9, 0.6))]
    head = loft(rings)
    parts = [legs, torso, head]
    V = np.vstack([v for v, _ in parts])
    off = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    F = np.vstack([f + o for (_, f), o in zip(parts, off)])
    rgb = tuple(float(c) for c in np.clip(rng.uniform(0.05, 0.8, 3), 0, 1))
    return SceneMesh(V, F, None, UniformAlbedo(rgb), "person", {"material": "lambertian"})


def pole_mesh() -> SceneMesh:
    """A car-park light pole: an 8 m mast with a 1.2 m arm and lamp."""
    parts = [cylinder((0, 0, 0), (0, 0, 8.0), 0.09, 0.07, 8), box((0.0, -0.05, 7.85), (1.2, 0.05, 7.95)),
             box((0.9, -0.2, 7.7), (1.35, 0.2, 7.9))]
    V = np.vstack([v for v, _ in parts])
    off = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    F = np.vstack([f + o for (_, f), o in zip(parts, off)])
    return SceneMesh(V, F, None, UniformAlbedo((0.45, 0.46, 0.47)), "pole", {"material": "lambertian"})


def lot_clutter(rng: np.random.Generator, lot: Lot, vehicles_ab: NDArray, seed: int
                ) -> list[tuple[SceneMesh, NDArray[np.float64], tuple[float, float, float]]]:
    """Trees just outside the lot's long edges (crowns overhanging the first rows), people
    in the aisles clear of the vehicles (``vehicles_ab`` (n, 2) lot frame), light poles
    at the row ends; ``(mesh, T_world_obj (mm), (a, b, radius m))`` each."""
    out = []

    def put(mesh: SceneMesh, a: float, b: float, rad: float, turn: float = 0.0) -> None:
        x, y = lot.to_world(a, b)
        T = np.eye(4)
        T[:3, :3] = [[math.cos(turn), -math.sin(turn), 0.0], [math.sin(turn), math.cos(turn), 0.0], [0, 0, 1.0]]
        T[:3, 3] = (x * 1000.0, y * 1000.0, lot.z * 1000.0 - 30.0)
        out.append((mesh, T, (a, b, rad)))

    for side in (-1, 1):
        a = -lot.half_a + rng.uniform(2.0, 6.0)
        while a < lot.half_a - 2.0:
            if rng.uniform() < 0.6:
                put(prop_mesh("tree", rng, seed + len(out)), a, side * (lot.half_b + rng.uniform(0.3, 1.5)), 2.5)
            a += rng.uniform(6.0, 11.0)
    n_people = int(rng.integers(5, 13))
    tries = 0
    while n_people and tries < 400:
        tries += 1
        a, b = rng.uniform(-lot.half_a + 1, lot.half_a - 1), rng.uniform(-lot.half_b + 1, lot.half_b - 1)
        if len(vehicles_ab) and np.min(np.hypot(vehicles_ab[:, 0] - a, vehicles_ab[:, 1] - b)) < 3.2:
            continue
        put(person_mesh(rng), a, b, 0.4, rng.uniform(0, 2 * math.pi))
        n_people -= 1
    for sa in (-1, 1):
        for sb in (-1, 1):
            if rng.uniform() < 0.7:
                put(pole_mesh(), sa * (lot.half_a + 0.5), sb * (lot.half_b - rng.uniform(2.0, 8.0)), 0.3,
                    0.0 if sa < 0 else math.pi)
    return out
