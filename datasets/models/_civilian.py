"""Civilian built-in vehicles (private): cars, vans, buses and trucks at true size.

Each variant is a recipe of closed parts (:mod:`prism3d.datasets.models._primitives`) built
already in the normalised object frame (x forward, y left, z up, metres in, mm out;
footprint centred on the origin, wheels on z = 0) plus the zones of its paint: the body
colour, dark glass over the cabin between the belt line and the roof, black tyres.
Sizes are those of common production vehicles of each kind (a kei car is 3.4 x 1.48 m
by Japanese law; the rest are typical catalogue figures), so a vehicle seen by a real
camera has the size its class predicts. :mod:`prism3d.datasets.models.targets` registers them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.paints import draw_body_paint
from prism3d.datasets.models._primitives import Part, box, both_sides, loft, wheel

__all__ = ["CIVILIAN_VARIANTS", "CivilianSpec", "VehiclePaint", "body_colour", "paint_for"]

GLASS = (0.05, 0.06, 0.07)
TYRE = (0.03, 0.03, 0.03)
TRIM = (0.10, 0.10, 0.10)


def body_colour(seed: int, index: int) -> tuple[str, tuple[float, float, float]]:
    """The body paint of variant ``index`` for ``seed``: drawn with the shares of
    :data:`~prism3d.capture.paints.BODY_PAINTS` (deterministic)."""
    return draw_body_paint(np.random.default_rng([int(seed), int(index), 7]))


@dataclass(frozen=True)
class VehiclePaint:
    """Albedo of a civilian vehicle at object-frame points (mm): tyres where within a
    wheel's disc and outside ``tyre_y_mm``; glass where inside one of ``glass`` boxes
    (x0, x1, z0, z1, mm); ``trim`` boxes (bumpers, bed floors); the body colour elsewhere."""

    body: tuple[float, float, float]
    glass: tuple[tuple[float, float, float, float], ...]
    wheels: tuple[tuple[float, float], ...]  # (x, radius) mm, centre at z = radius
    tyre_y_mm: float
    trim: tuple[tuple[float, float, float, float], ...] = ()

    def __call__(self, points_obj: NDArray[np.float64]) -> NDArray[np.float64]:
        p = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
        out = np.empty((len(p), 3))
        out[:] = self.body
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        for x0, x1, z0, z1 in self.trim:
            out[(x >= x0) & (x <= x1) & (z >= z0) & (z <= z1)] = TRIM
        for x0, x1, z0, z1 in self.glass:
            out[(x >= x0) & (x <= x1) & (z >= z0) & (z <= z1)] = GLASS
        side = np.abs(y) >= self.tyre_y_mm
        for wx, r in self.wheels:
            out[side & ((x - wx) ** 2 + (z - r) ** 2 <= (r * 1.02) ** 2)] = TYRE
        return out

    def scaled(self, ratio: float) -> VehiclePaint:
        """The same paint on the model scaled by ``ratio``."""
        return VehiclePaint(self.body, tuple(tuple(v * ratio for v in g) for g in self.glass),
                            tuple((x * ratio, r * ratio) for x, r in self.wheels), self.tyre_y_mm * ratio,
                            tuple(tuple(v * ratio for v in g) for g in self.trim))


@dataclass(frozen=True)
class CivilianSpec:
    """A civilian variant: class, name, description, its parts and its paint zones
    (full size, mm; body colour left to :class:`VehiclePaint`)."""

    target_class: str
    variant: str
    description: str
    features: dict
    model_scale: tuple[int, int]
    build: Callable[[], tuple[list[Part], dict]]


def _section(x: float, wb: float, wt: float, z0: float, z1: float, r: float, n: int = 3) -> NDArray[np.float64]:
    """A cross-section ring at ``x`` (metres in, mm out): a trapezoid from half-width
    ``wb`` at ``z0`` to ``wt`` at ``z1``, its four corners rounded by ``r`` (``n`` points
    each), counter-clockwise seen from +x."""
    r = min(r, 0.45 * (z1 - z0), 0.45 * min(wb, wt))
    corners = [((wb - r, z0 + r), -np.pi / 2, 0.0), ((wt - r, z1 - r), 0.0, np.pi / 2),
               ((-wt + r, z1 - r), np.pi / 2, np.pi), ((-wb + r, z0 + r), np.pi, 1.5 * np.pi)]
    pts = []
    for (cy, cz), a0, a1 in corners:
        for t in np.linspace(a0, a1, n):
            pts.append((x, cy + r * np.cos(t), cz + r * np.sin(t)))
    return np.array(pts) * 1000.0


def _body(stations: Sequence[tuple[float, float, float, float, float]], r: float) -> Part:
    """A lofted body through stations ``(x, half_width_bottom, half_width_top, z0, z1)``."""
    return loft([_section(x, wb, wt, z0, z1, r) for x, wb, wt, z0, z1 in stations])


def _wheels(xs: Sequence[float], radius: float, half_track_out: float, width: float = 0.2) -> list[Part]:
    parts: list[Part] = []
    for x in xs:
        parts += both_sides(wheel(x, half_track_out - width, half_track_out, radius))
    return parts


def _car(length: float, width: float, lower: list, cabin: list, wheel_x: Sequence[float], r: float,
         belt: float, roof: float) -> tuple[list[Part], dict]:
    """Lower body + greenhouse + wheels; glass between the belt line and just below the
    roof over the greenhouse's length."""
    parts = [_body(lower, 0.12), _body(cabin, 0.08)]
    parts += _wheels(wheel_x, r, width / 2.0 - 0.03)
    xs = [s[0] for s in cabin]
    zones = {"glass": [(min(xs) - 0.05, max(xs) + 0.05, belt + 0.03, roof - 0.05)],
             "wheels": [(x, r) for x in wheel_x], "tyre_y": width / 2.0 - 0.25, "trim": []}
    return parts, zones


def _sedan() -> tuple[list[Part], dict]:
    lower = [(-2.35, 0.80, 0.78, 0.28, 0.86), (-2.2, 0.88, 0.86, 0.18, 0.96), (-1.2, 0.90, 0.88, 0.18, 0.98),
             (1.3, 0.90, 0.88, 0.18, 0.93), (2.2, 0.86, 0.82, 0.20, 0.80), (2.35, 0.76, 0.70, 0.30, 0.70)]
    cabin = [(-1.40, 0.80, 0.78, 0.90, 1.00), (-0.75, 0.80, 0.66, 0.90, 1.43), (0.50, 0.80, 0.66, 0.90, 1.45),
             (1.35, 0.80, 0.78, 0.90, 0.99)]
    return _car(4.70, 1.80, lower, cabin, (1.40, -1.40), 0.32, 0.97, 1.45)


def _hatchback() -> tuple[list[Part], dict]:
    lower = [(-2.02, 0.82, 0.80, 0.26, 0.90), (-1.9, 0.86, 0.84, 0.18, 0.96), (1.2, 0.86, 0.84, 0.18, 0.90),
             (1.9, 0.80, 0.76, 0.22, 0.76), (2.02, 0.72, 0.66, 0.32, 0.68)]
    cabin = [(-1.98, 0.80, 0.74, 0.88, 1.00), (-1.75, 0.80, 0.66, 0.88, 1.44), (0.40, 0.80, 0.66, 0.88, 1.48),
             (1.22, 0.80, 0.76, 0.88, 0.97)]
    return _car(4.05, 1.75, lower, cabin, (1.27, -1.27), 0.31, 0.96, 1.48)


def _suv() -> tuple[list[Part], dict]:
    lower = [(-2.32, 0.88, 0.86, 0.32, 1.02), (-2.2, 0.92, 0.90, 0.25, 1.08), (1.4, 0.92, 0.90, 0.25, 1.06),
             (2.15, 0.88, 0.84, 0.28, 0.92), (2.32, 0.80, 0.74, 0.38, 0.84)]
    cabin = [(-2.25, 0.86, 0.80, 1.00, 1.12), (-2.05, 0.86, 0.74, 1.00, 1.68), (0.60, 0.86, 0.74, 1.00, 1.72),
             (1.45, 0.86, 0.82, 1.00, 1.10)]
    return _car(4.65, 1.86, lower, cabin, (1.38, -1.38), 0.37, 1.08, 1.72)


def _kei() -> tuple[list[Part], dict]:
    lower = [(-1.695, 0.70, 0.69, 0.24, 0.92), (-1.6, 0.735, 0.73, 0.16, 0.94), (1.35, 0.735, 0.73, 0.16, 0.92),
             (1.62, 0.72, 0.70, 0.20, 0.82), (1.695, 0.66, 0.62, 0.30, 0.74)]
    cabin = [(-1.68, 0.72, 0.70, 0.86, 0.98), (-1.62, 0.72, 0.66, 0.86, 1.72), (0.75, 0.72, 0.66, 0.86, 1.75),
             (1.45, 0.72, 0.70, 0.86, 0.94)]
    return _car(3.39, 1.47, lower, cabin, (1.25, -1.25), 0.29, 0.94, 1.75)


def _van() -> tuple[list[Part], dict]:
    """A one-box panel van: glass only over the cab."""
    lower = [(-2.45, 0.84, 0.84, 0.24, 1.06), (1.9, 0.85, 0.85, 0.22, 1.06), (2.35, 0.83, 0.80, 0.26, 0.98),
             (2.45, 0.78, 0.74, 0.34, 0.90)]
    cabin = [(-2.44, 0.84, 0.80, 1.00, 1.95), (1.70, 0.84, 0.80, 1.00, 1.98), (2.28, 0.83, 0.80, 1.00, 1.10)]
    parts = [_body(lower, 0.10), _body(cabin, 0.08)]
    parts += _wheels((1.55, -1.05), 0.33, 0.82)
    zones = {"glass": [(0.95, 2.40, 1.09, 1.92)], "wheels": [(1.55, 0.33), (-1.05, 0.33)], "tyre_y": 0.6,
             "trim": []}
    return parts, zones


def _bus() -> tuple[list[Part], dict]:
    """A 10.5 m city bus: a window band all round, an air-conditioning unit on the roof."""
    body = [(-5.25, 1.18, 1.16, 0.32, 2.98), (-5.1, 1.245, 1.22, 0.30, 3.00), (5.1, 1.245, 1.22, 0.30, 3.00),
            (5.25, 1.18, 1.14, 0.32, 2.96)]
    parts = [_body(body, 0.18), box((-2.4, -0.8, 2.95), (0.3, 0.8, 3.2))]
    parts += _wheels((3.1, -2.4), 0.50, 1.20, 0.28)
    zones = {"glass": [(-5.3, 5.3, 1.05, 2.70)], "wheels": [(3.1, 0.5), (-2.4, 0.5)], "tyre_y": 0.85,
             "trim": [(-2.41, 0.31, 2.96, 3.21)]}
    return parts, zones


def _box_truck() -> tuple[list[Part], dict]:
    """A 7.6 m box truck: cab over engine in front, a tall cargo box behind."""
    cab_lower = [(1.55, 1.10, 1.10, 0.45, 1.40), (3.7, 1.12, 1.12, 0.45, 1.40), (3.8, 1.05, 1.02, 0.50, 1.30)]
    cab = [(1.60, 1.08, 1.00, 1.30, 2.55), (3.55, 1.08, 1.00, 1.30, 2.55), (3.78, 1.06, 1.00, 1.30, 1.45)]
    parts = [_body(cab_lower, 0.10), _body(cab, 0.10), box((-3.8, -0.5, 0.55), (1.6, 0.5, 0.85))]
    parts.append(box((-3.8, -1.15, 0.85), (1.45, 1.15, 3.30)))  # cargo box
    parts += _wheels((2.85, -1.9), 0.45, 1.13, 0.25)
    zones = {"glass": [(1.6, 3.85, 1.45, 2.45)], "wheels": [(2.85, 0.45), (-1.9, 0.45)], "tyre_y": 0.85,
             "trim": [(-3.8, 1.6, 0.5, 0.86)]}
    return parts, zones


def _pickup() -> tuple[list[Part], dict]:
    """A 5.3 m pickup: bonnet and crew cab, an open bed behind (floor and walls)."""
    lower = [(0.0, 0.92, 0.90, 0.30, 1.05), (1.9, 0.92, 0.90, 0.30, 1.02), (2.55, 0.88, 0.84, 0.32, 0.92),
             (2.65, 0.80, 0.74, 0.40, 0.86)]
    cabin = [(0.02, 0.88, 0.80, 0.98, 1.78), (1.05, 0.88, 0.78, 0.98, 1.80), (1.75, 0.88, 0.84, 0.98, 1.05)]
    parts = [_body(lower, 0.10), _body(cabin, 0.08)]
    parts.append(box((-2.65, -0.90, 0.55), (0.02, 0.90, 0.75)))  # bed floor
    parts += both_sides(box((-2.65, 0.82, 0.55), (0.02, 0.92, 1.05)))  # bed sides
    parts.append(box((-2.65, -0.90, 0.55), (-2.55, 0.90, 1.02)))  # tailgate
    parts += _wheels((1.6, -1.6), 0.38, 0.90, 0.24)
    zones = {"glass": [(0.0, 1.80, 1.08, 1.75)], "wheels": [(1.6, 0.38), (-1.6, 0.38)], "tyre_y": 0.62,
             "trim": [(-2.56, 0.0, 0.55, 0.78)]}
    return parts, zones


def _kei_truck() -> tuple[list[Part], dict]:
    """A kei truck (3.4 x 1.48 m): a short cab over the front wheels, a flat bed with low
    drop sides."""
    cab_lower = [(0.90, 0.73, 0.73, 0.30, 0.95), (1.62, 0.73, 0.72, 0.28, 0.95), (1.695, 0.70, 0.68, 0.32, 0.88)]
    cab = [(0.92, 0.72, 0.66, 0.90, 1.78), (1.30, 0.72, 0.66, 0.90, 1.80), (1.68, 0.72, 0.70, 0.90, 0.98)]
    parts = [_body(cab_lower, 0.08), _body(cab, 0.06), box((-1.695, -0.3, 0.35), (0.9, 0.3, 0.62))]
    parts.append(box((-1.695, -0.735, 0.62), (0.88, 0.735, 0.70)))  # bed floor
    parts += both_sides(box((-1.695, 0.70, 0.70), (0.88, 0.735, 0.98)))  # drop sides
    parts.append(box((-1.695, -0.735, 0.70), (-1.66, 0.735, 0.98)))  # tailgate
    parts.append(box((0.84, -0.70, 0.70), (0.90, 0.70, 1.70)))  # cab guard
    parts += _wheels((1.2, -0.95), 0.28, 0.70, 0.17)
    zones = {"glass": [(1.25, 1.72, 0.98, 1.74)], "wheels": [(1.2, 0.28), (-0.95, 0.28)], "tyre_y": 0.5,
             "trim": []}
    return parts, zones


CIVILIAN_VARIANTS: tuple[CivilianSpec, ...] = (
    CivilianSpec("car", "sedan", "Three-box saloon car, 4.7 x 1.8 x 1.45 m.",
                 {"body": "three-box", "doors": 4}, (1, 24), _sedan),
    CivilianSpec("car", "hatchback", "Two-box hatchback, 4.05 x 1.75 x 1.48 m.",
                 {"body": "two-box", "doors": 5}, (1, 24), _hatchback),
    CivilianSpec("car", "suv", "Sport utility vehicle, 4.65 x 1.86 x 1.72 m, tall two-box.",
                 {"body": "two-box tall", "doors": 5}, (1, 24), _suv),
    CivilianSpec("car", "kei", "Japanese kei car (tall wagon), 3.39 x 1.47 x 1.75 m.",
                 {"body": "one-and-a-half box", "doors": 5}, (1, 24), _kei),
    CivilianSpec("van", "panel", "Cab-over panel van, 4.9 x 1.7 x 1.98 m, windows only at the cab.",
                 {"body": "one-box", "glass": "cab only"}, (1, 24), _van),
    CivilianSpec("bus", "city", "City bus, 10.5 x 2.49 x 3.2 m with its roof unit.",
                 {"axles": 2, "roof": "air conditioning unit"}, (1, 48), _bus),
    CivilianSpec("truck", "box", "Box truck, 7.6 x 2.3 x 3.3 m: cab over engine, cargo box.",
                 {"cab": "cab over engine", "cargo": "box"}, (1, 35), _box_truck),
    CivilianSpec("truck", "pickup", "Crew-cab pickup, 5.3 x 1.84 x 1.8 m, open bed.",
                 {"cab": "bonneted crew cab", "cargo": "open bed"}, (1, 24), _pickup),
    CivilianSpec("truck", "kei", "Kei truck, 3.39 x 1.47 x 1.8 m: short cab, flat bed with drop sides.",
                 {"cab": "cab over engine", "cargo": "drop-side flat bed"}, (1, 24), _kei_truck),
)


def paint_for(zones: dict, body: tuple[float, float, float]) -> VehiclePaint:
    """The :class:`VehiclePaint` of a variant's zones (metres) in mm, with ``body``."""
    mm = 1000.0
    return VehiclePaint(tuple(body), tuple(tuple(v * mm for v in g) for g in zones["glass"]),
                        tuple((x * mm, r * mm) for x, r in zones["wheels"]), zones["tyre_y"] * mm,
                        tuple(tuple(v * mm for v in g) for g in zones["trim"]))
