"""Built-in procedural targets: tanks, jets, ships and trucks with camouflage paint.

Built on the fly from closed, outward-oriented primitives (overlapping parts, simply
concatenated), as :class:`~prism3d.capture.mesh.SceneMesh` in millimetres, object
frame x forward, y left, z up, origin at the footprint centre on the ground; kit,
full or any scale. Frame, scales and mesh structure: docs/targets.md.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.checks import check_positive
from prism3d.datasets.models._primitives import (
    Part,
    both_sides,
    box,
    cylinder,
    ellipse,
    hull_plan,
    loft,
    prism,
    rotate_x,
    taper,
    wheel,
)
from prism3d.capture.camouflage import CLASS_PALETTES, camouflage_field, plain_paint
from prism3d.datasets.models._civilian import CIVILIAN_VARIANTS, body_colour, paint_for
from prism3d.errors import InputError
from prism3d.io.ply import write_ply

__all__ = ["builtin_classes", "builtin_target", "export_builtin_target", "list_builtin_targets"]

# ---------------------------------------------------------------------------------
# Variant registry (filled by the @_variant builders below, in listing order)
# ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Variant:
    """A built-in target variant (full-size geometry recipe plus kit scale)."""

    target_class: str
    variant: str
    model_scale: Fraction
    build: Callable[[], list[Part]]
    patch_full_mm: float
    """Camouflage patch diameter on the full-size target, millimetres."""
    features: dict = field(default_factory=dict)
    description: str = ""
    group: str = "military"
    """``military`` (camouflaged, kit scales) or ``civilian`` (body colour, glass, tyres)."""
    zones: dict | None = None
    """Civilian paint zones (metres, builder frame): glass boxes, wheels, trim."""


_CLASSES = ("tank", "jet", "ship", "truck", "car", "van", "bus")
#: Groups of built-in targets: the camouflaged military set (what ``builtin`` names) and
#: the civilian vehicles.
GROUPS = ("military", "civilian")

_VARIANTS: dict[str, _Variant] = {}


def _variant(
    target_class: str, variant: str, model_scale: Fraction, patch_full_mm: float,
    features: dict, description: str,
) -> Callable[[Callable[[], list[Part]]], Callable[[], list[Part]]]:
    """Register the decorated builder as built-in target ``<target_class>_<variant>``."""

    def register(build: Callable[[], list[Part]]) -> Callable[[], list[Part]]:
        _VARIANTS[f"{target_class}_{variant}"] = _Variant(
            target_class, variant, model_scale, build, patch_full_mm, features, description
        )
        return build

    return register


# ---------------------------------------------------------------------------------
# Tanks
# ---------------------------------------------------------------------------------


def _track_profile(x_rear: float, x_front: float, height: float) -> list[tuple[float, float]]:
    """Side profile (x, z) of a track run: flat on the ground, sloped ends."""
    return [
        (x_rear + 0.55, 0.0),
        (x_front - 0.6, 0.0),
        (x_front, 0.55 * height),
        (x_front - 0.15, height),
        (x_rear + 0.1, height),
        (x_rear, 0.5 * height),
    ]


def _tracks(x_rear: float, x_front: float, height: float, y_in: float, y_out: float) -> list[Part]:
    return both_sides(prism(_track_profile(x_rear, x_front, height), 1, y_in, y_out))


def _road_wheels(xs: Sequence[float], radius: float, y_in: float, y_out: float) -> list[Part]:
    parts: list[Part] = []
    for x in xs:
        parts += both_sides(cylinder((x, y_in, radius + 0.05), (x, y_out, radius + 0.05), radius))
    return parts


@_variant(
    "tank", "t1", Fraction(1, 48), 1200.0,
    {"turret": "amidships wedge", "gun": "long", "road_wheels": "skirted"},
    "Modern main battle tank: low hull, side skirts, wedge turret amidships, long gun.",
)
def _build_tank_t1() -> list[Part]:
    parts = _tracks(-3.6, 3.7, 1.0, 1.1, 1.75)
    parts += both_sides(box((-3.55, 1.75, 0.40), (3.55, 1.83, 1.05)))  # side skirts
    parts.append(box((-3.5, -1.1, 0.42), (3.5, 1.1, 1.0)))  # lower hull
    hull = [(-3.75, 0.95), (3.7, 0.95), (4.0, 1.2), (2.9, 1.7), (-3.6, 1.75), (-3.8, 1.4)]
    parts.append(prism(hull, 1, -1.83, 1.83))
    turret_lo = [(-2.3, -1.6), (1.0, -1.7), (2.3, -0.7), (2.3, 0.7), (1.0, 1.7), (-2.3, 1.6)]
    turret_hi = [(-2.2, -1.45), (0.9, -1.55), (1.9, -0.55), (1.9, 0.55), (0.9, 1.55), (-2.2, 1.45)]
    parts.append(taper(turret_lo, turret_hi, 2, 1.7, 2.45))
    parts.append(box((2.1, -0.4, 1.85), (2.7, 0.4, 2.35)))  # mantlet
    parts.append(cylinder((2.6, 0.0, 2.1), (7.9, 0.0, 2.1), 0.09))  # barrel
    parts.append(cylinder((3.8, 0.0, 2.1), (5.6, 0.0, 2.1), 0.13))  # thermal sleeve
    parts.append(cylinder((-0.6, -0.75, 2.4), (-0.6, -0.75, 2.75), 0.38))  # commander cupola
    parts.append(box((-1.5, 0.4, 2.4), (-0.8, 1.0, 2.6)))  # loader hatch
    parts += both_sides(box((0.9, 1.45, 2.0), (1.3, 1.75, 2.3)))  # smoke launchers
    return parts


@_variant(
    "tank", "t2", Fraction(1, 35), 1000.0,
    {"turret": "forward round", "gun": "short", "road_wheels": 5},
    ("Second-world-war medium tank: tall sloped hull, visible road wheels, round turret "
     "set forward, short gun."),
)
def _build_tank_t2() -> list[Part]:
    parts = _tracks(-2.9, 3.0, 0.95, 0.95, 1.45)
    parts += _road_wheels([-2.0, -1.0, 0.0, 1.0, 2.0], 0.38, 0.9, 1.52)
    parts.append(box((-2.7, -0.95, 0.45), (2.8, 0.95, 1.0)))  # lower hull
    hull = [(-2.95, 0.9), (2.9, 0.9), (3.15, 1.1), (2.1, 1.75), (-2.7, 1.75), (-3.0, 1.3)]
    parts.append(prism(hull, 1, -1.5, 1.5))
    c = (0.55, 0.0)
    ring_lo = ellipse((c[0], c[1], 1.75), 2, 1.1, 1.0)
    ring_hi = ellipse((c[0] - 0.1, c[1], 2.55), 2, 0.85, 0.8)
    parts.append(loft([ring_lo, ring_hi]))  # cast turret
    parts.append(cylinder((1.5, 0.0, 2.1), (1.9, 0.0, 2.1), 0.3))  # mantlet
    parts.append(cylinder((1.8, 0.0, 2.1), (4.3, 0.0, 2.1), 0.08))  # short gun
    parts.append(cylinder((0.2, 0.45, 2.5), (0.2, 0.45, 2.8), 0.32))  # cupola
    parts.append(box((-2.9, -1.2, 1.75), (-1.9, 1.2, 1.95)))  # engine deck grille
    return parts


@_variant(
    "tank", "t3", Fraction(1, 35), 1200.0,
    {"turret": "rear casemate", "gun": "very long", "road_wheels": 6},
    ("Tank destroyer: six visible road wheels, large fixed casemate at the rear, very long "
     "gun with a muzzle brake."),
)
def _build_tank_t3() -> list[Part]:
    parts = _tracks(-3.4, 3.3, 1.0, 1.05, 1.6)
    parts += _road_wheels([-2.45, -1.5, -0.55, 0.4, 1.35, 2.3], 0.36, 1.0, 1.68)
    parts.append(box((-3.2, -1.05, 0.45), (3.2, 1.05, 1.0)))
    hull = [(-3.45, 0.95), (3.3, 0.95), (3.55, 1.15), (2.7, 1.5), (-3.3, 1.5)]
    parts.append(prism(hull, 1, -1.65, 1.65))
    casemate = [(-3.3, 1.5), (0.6, 1.5), (-0.2, 2.7), (-3.1, 2.7)]
    parts.append(prism(casemate, 1, -1.45, 1.45))
    parts.append(box((0.0, -0.45, 1.8), (0.45, 0.45, 2.4)))  # gun mantlet
    parts.append(cylinder((0.3, 0.0, 2.1), (4.9, 0.0, 2.1), 0.1))  # gun
    parts.append(cylinder((4.9, 0.0, 2.1), (5.35, 0.0, 2.1), 0.17))  # muzzle brake
    parts.append(cylinder((-1.8, 0.7, 2.7), (-1.8, 0.7, 2.95), 0.3))  # hatch ring
    parts += both_sides(cylinder((-3.5, 1.0, 1.3), (-3.5, 1.4, 1.3), 0.2))  # rear stowage
    return parts


# ---------------------------------------------------------------------------------
# Jets
# ---------------------------------------------------------------------------------


def _fuselage(stations: Sequence[tuple[float, float, float, float]], nose_x: float) -> Part:
    """Fuselage lofted through elliptic stations (x, y-radius, z-radius, z-centre),
    listed nose to tail, with a pointed nose at ``nose_x``."""
    rings = [ellipse((x, 0.0, zc), 0, ry, rz) for x, ry, rz, zc in stations]
    zc0 = stations[0][3]
    return loft(rings, start_apex=(nose_x * 1000.0, 0.0, zc0 * 1000.0))


def _canopy(
    x_front: float, x_rear: float, z_base: float, half_width: float, height: float
) -> Part:
    xs = np.linspace(x_front, x_rear, 5)[1:-1]
    shape = [0.8, 1.0, 0.7]
    rings = [
        ellipse((x, 0.0, z_base), 0, half_width * s, height * s, n=12) for x, s in zip(xs, shape)
    ]
    return loft(
        rings,
        start_apex=(x_front * 1000.0, 0.0, z_base * 1000.0),
        end_apex=(x_rear * 1000.0, 0.0, z_base * 1000.0),
    )


@_variant(
    "jet", "j1", Fraction(1, 72), 2500.0,
    {"wing": "swept trapezoid", "tail": "single fin", "engine_count": 1},
    ("Single-engine fighter: 40-degree swept trapezoid wing, single fin, conventional "
     "tailplane, ventral intake."),
)
def _build_jet_j1() -> list[Part]:
    stations = [
        (6.6, 0.3, 0.3, 1.6),
        (4.6, 0.6, 0.62, 1.6),
        (2.0, 0.75, 0.82, 1.6),
        (-3.0, 0.75, 0.82, 1.6),
        (-6.4, 0.55, 0.6, 1.6),
        (-7.4, 0.48, 0.48, 1.6),
    ]
    parts = [_fuselage(stations, 7.6)]
    parts.append(_canopy(5.0, 1.6, 2.05, 0.42, 0.6))
    parts.append(box((-1.2, -0.55, 0.62), (3.1, 0.55, 1.3)))  # ventral intake
    wing = [(2.0, 0.0), (-1.6, 4.75), (-3.0, 4.75), (-3.3, 0.0), (-3.0, -4.75), (-1.6, -4.75)]
    parts.append(prism(wing, 2, 1.4, 1.6))
    tail = [(-5.0, 0.0), (-6.6, 2.8), (-7.5, 2.8), (-7.4, 0.0), (-7.5, -2.8), (-6.6, -2.8)]
    parts.append(prism(tail, 2, 1.5, 1.62))
    fin = [(-4.6, 2.2), (-7.3, 2.2), (-7.6, 4.9), (-6.6, 4.9)]
    parts.append(prism(fin, 1, -0.08, 0.08))
    parts.append(cylinder((-7.4, 0.0, 1.6), (-7.9, 0.0, 1.6), 0.45, 0.4))  # nozzle
    return parts


@_variant(
    "jet", "j2", Fraction(1, 72), 2500.0,
    {"wing": "swept trapezoid", "tail": "twin canted fins", "engine_count": 2},
    ("Heavy twin-engine fighter: blended centre body, two engine nacelles, 45-degree swept "
     "wing, twin canted fins, tailplane."),
)
def _build_jet_j2() -> list[Part]:
    stations = [
        (8.5, 0.35, 0.35, 2.0),
        (6.5, 0.62, 0.66, 2.0),
        (4.0, 0.8, 0.85, 2.0),
        (2.0, 0.85, 0.85, 2.0),
    ]
    parts = [_fuselage(stations, 9.6)]
    parts.append(_canopy(6.6, 2.8, 2.5, 0.45, 0.65))
    body = [(3.0, -1.0), (1.0, -1.9), (-8.0, -1.9), (-8.0, 1.9), (1.0, 1.9), (3.0, 1.0)]
    parts.append(prism(body, 2, 1.5, 2.3))
    for y in (-1.15, 1.15):
        parts.append(cylinder((2.6, y, 1.55), (-9.0, y, 1.55), 0.65))  # nacelle
        parts.append(cylinder((-9.0, y, 1.55), (-9.6, y, 1.55), 0.6, 0.5))  # nozzle
        sign = np.sign(y)
        intake = [(0.6 * sign, 0.9), (1.7 * sign, 0.9), (1.7 * sign, 1.9), (0.6 * sign, 1.9)]
        parts.append(prism(intake, 0, 1.0, 4.6))
    wing = [(1.0, -1.5), (-4.6, -6.75), (-6.2, -6.75), (-6.8, -1.5),
            (-6.8, 1.5), (-6.2, 6.75), (-4.6, 6.75), (1.0, 1.5)]
    parts.append(prism(wing, 2, 1.75, 1.95))
    tail = [(-6.7, -1.6), (-8.6, -4.3), (-9.8, -4.3), (-9.6, -1.6),
            (-9.6, 1.6), (-9.8, 4.3), (-8.6, 4.3), (-6.7, 1.6)]
    parts.append(prism(tail, 2, 1.6, 1.75))
    fin = [(-6.2, 2.1), (-9.2, 2.1), (-9.5, 5.6), (-8.3, 5.6)]
    for y, cant in ((1.6, -0.26), (-1.6, 0.26)):
        part = prism(fin, 1, y - 0.08, y + 0.08)
        parts.append(rotate_x(part, cant, (0.0, y, 2.1)))
    return parts


@_variant(
    "jet", "j3", Fraction(1, 72), 2500.0,
    {"wing": "clipped delta + canards", "tail": "single fin", "engine_count": 1},
    ("Delta-wing canard fighter: clipped delta wing, close-coupled canards, tall fin, no "
     "tailplane, single engine."),
)
def _build_jet_j3() -> list[Part]:
    stations = [
        (6.3, 0.28, 0.3, 1.5),
        (4.3, 0.58, 0.62, 1.5),
        (1.5, 0.72, 0.8, 1.5),
        (-4.5, 0.72, 0.8, 1.5),
        (-6.9, 0.5, 0.55, 1.5),
    ]
    parts = [_fuselage(stations, 7.7)]
    parts.append(_canopy(4.9, 1.7, 1.95, 0.4, 0.55))
    for sign in (-1.0, 1.0):  # side intakes
        y0, y1 = 0.55 * sign, 1.25 * sign
        intake = [(y0, 0.85), (y1, 0.85), (y1, 1.75), (y0, 1.75)]
        parts.append(prism(intake, 0, -1.0, 3.0))
    wing = [(1.2, 0.0), (-5.8, 5.45), (-6.8, 5.45), (-6.8, -5.45), (-5.8, -5.45)]
    parts.append(prism(wing, 2, 1.15, 1.35))
    canard = [(3.9, 0.0), (2.7, 2.3), (2.2, 2.3), (2.3, 0.0), (2.2, -2.3), (2.7, -2.3)]
    parts.append(prism(canard, 2, 1.85, 1.95))
    fin = [(-3.6, 2.0), (-7.2, 2.0), (-7.4, 5.3), (-6.3, 5.3)]
    parts.append(prism(fin, 1, -0.08, 0.08))
    parts.append(cylinder((-6.9, 0.0, 1.5), (-7.6, 0.0, 1.5), 0.45, 0.4))
    return parts


# ---------------------------------------------------------------------------------
# Ships (waterline models: flat bottom at the waterline, z = 0)
# ---------------------------------------------------------------------------------


def _ship_hull(
    length_wl: float, length_deck: float, beam_wl: float, beam_deck: float, freeboard: float,
    bow_frac: float = 0.22, stern_frac: float = 0.85,
) -> Part:
    wl = hull_plan(length_wl, beam_wl, length_wl / 2 - bow_frac * length_wl, stern_frac)
    shift = (length_deck - length_wl) / 2.0 * 0.6
    deck = hull_plan(
        length_deck, beam_deck, length_deck / 2 - bow_frac * length_deck + shift, stern_frac,
        x_center=shift,
    )
    return taper(wl, deck, 2, 0.0, freeboard)


def _gun_turret(
    x: float, z: float, facing: float, radius: float = 3.2, barrel: float = 7.0
) -> list[Part]:
    lo = ellipse((x, 0.0, z), 2, radius, radius * 0.85, n=12)
    hi = ellipse((x - 0.5 * facing, 0.0, z + 2.8), 2, radius * 0.7, radius * 0.6, n=12)
    x0 = x + facing * radius * 0.6
    return [
        loft([lo, hi]),
        cylinder((x0, 0.0, z + 1.3), (x0 + facing * barrel, 0.0, z + 1.3), 0.3),
    ]


@_variant(
    "ship", "s1", Fraction(1, 700), 9000.0,
    {"type": "destroyer", "superstructure": "midships", "masts": 1},
    ("Destroyer: flared hull, forward superstructure with bridge and lattice-free pole "
     "mast, one raked funnel, gun turrets fore and aft, hangar aft."),
)
def _build_ship_s1() -> list[Part]:
    parts = [_ship_hull(146.0, 154.0, 16.5, 18.0, 8.0)]
    parts.append(box((18.0, -7.0, 8.0), (44.0, 7.0, 15.0)))  # forward superstructure
    bridge = [(30.0, 15.0), (46.0, 15.0), (44.0, 20.0), (30.0, 20.0)]
    parts.append(prism(bridge, 1, -6.5, 6.5))
    parts.append(cylinder((33.0, 0.0, 20.0), (33.0, 0.0, 38.0), 0.7, 0.45))  # mast
    parts.append(box((32.6, -5.0, 32.0), (33.4, 5.0, 32.8)))  # yardarm
    parts.append(box((-30.0, -7.0, 8.0), (18.0, 7.0, 13.5)))  # aft superstructure
    funnel = [
        ellipse((2.0, 0.0, 13.0), 2, 4.5, 2.8, n=16),
        ellipse((-1.0, 0.0, 24.0), 2, 3.6, 2.3, n=16),
    ]
    parts.append(loft(funnel))
    parts.append(box((-44.0, -6.5, 8.0), (-30.0, 6.5, 14.0)))  # hangar
    parts += _gun_turret(55.0, 8.0, 1.0)
    parts += _gun_turret(-56.0, 8.0, -1.0)
    parts.append(box((46.0, -3.0, 8.0), (50.0, 3.0, 9.5)))  # missile cells
    return parts


@_variant(
    "ship", "s2", Fraction(1, 700), 12000.0,
    {"type": "container ship", "superstructure": "aft", "masts": 1},
    ("Container ship: long hull with aft accommodation block and funnel, container bays "
     "stacked to different heights, forecastle mast."),
)
def _build_ship_s2() -> list[Part]:
    parts = [_ship_hull(174.0, 180.0, 29.0, 30.0, 14.0, bow_frac=0.18, stern_frac=0.8)]
    parts.append(box((-80.0, -12.5, 14.0), (-66.0, 12.5, 40.0)))  # accommodation
    parts.append(box((-73.0, -15.0, 36.0), (-66.0, 15.0, 40.0)))  # bridge wings
    parts.append(box((-87.0, -3.5, 14.0), (-80.0, 3.5, 44.0)))  # funnel
    tiers = [3, 4, 5, 5, 4, 5, 4, 3, 3, 2]
    for i, n_tiers in enumerate(tiers):
        x0 = -62.0 + 13.5 * i
        parts.append(box((x0, -12.5, 14.0), (x0 + 12.5, 12.5, 14.0 + 2.6 * n_tiers)))
    parts.append(box((78.0, -9.0, 14.0), (86.0, 9.0, 16.5)))  # forecastle deck house
    parts.append(cylinder((82.0, 0.0, 16.5), (82.0, 0.0, 28.0), 0.6))  # fore mast
    return parts


@_variant(
    "ship", "s3", Fraction(1, 1200), 15000.0,
    {"type": "aircraft carrier", "superstructure": "starboard island", "masts": 1},
    ("Aircraft carrier: hull under a wide angled flight deck, starboard island with "
     "bridge, funnel and mast, parked aircraft."),
)
def _build_ship_s3() -> list[Part]:
    parts = [_ship_hull(285.0, 300.0, 38.0, 40.0, 17.0, bow_frac=0.15, stern_frac=0.9)]
    deck = [(-150.0, -20.0), (100.0, -20.0), (152.0, -11.0), (152.0, 11.0),
            (80.0, 22.0), (-40.0, 36.0), (-150.0, 30.0)]
    parts.append(prism(deck, 2, 17.0, 20.0))
    parts.append(box((-22.0, -19.5, 20.0), (14.0, -12.0, 35.0)))  # island
    parts.append(box((-6.0, -19.0, 35.0), (12.0, -12.5, 41.0)))  # bridge
    parts.append(box((-20.0, -18.5, 35.0), (-9.0, -13.0, 44.0)))  # funnel
    parts.append(cylinder((3.0, -15.5, 41.0), (3.0, -15.5, 60.0), 1.0, 0.6))  # mast
    for i, x in enumerate([-120.0, -100.0, -80.0, 60.0]):
        y = 10.0 if i < 3 else -6.0
        parts.append(box((x, y - 6.0, 20.0), (x + 16.0, y + 6.0, 24.5)))  # parked aircraft
    return parts


# ---------------------------------------------------------------------------------
# Trucks
# ---------------------------------------------------------------------------------


def _wheel_pairs(xs: Sequence[float], radius: float, y_in: float, y_out: float) -> list[Part]:
    parts: list[Part] = []
    for x in xs:
        parts += both_sides(wheel(x, y_in, y_out, radius))
    return parts


@_variant(
    "truck", "k1", Fraction(1, 35), 900.0,
    {"cab": "cab over engine", "cargo": "canvas cover", "axles": 3},
    "Six-wheel-drive cargo truck, cab over engine, canvas-covered cargo bed.",
)
def _build_truck_k1() -> list[Part]:
    parts = _wheel_pairs([2.9, -1.6, -3.0], 0.55, 0.8, 1.22)
    parts.append(box((-3.9, -0.5, 0.85), (3.7, 0.5, 1.2)))  # chassis frame
    cab = [(2.3, 1.05), (4.0, 1.05), (4.05, 2.0), (3.8, 3.0), (2.3, 3.0)]
    parts.append(prism(cab, 1, -1.2, 1.2))
    parts.append(box((3.95, -1.25, 0.75), (4.15, 1.25, 1.05)))  # bumper
    parts.append(box((-4.0, -1.25, 1.2), (2.1, 1.25, 1.7)))  # cargo bed
    arch = [(-1.25, 1.7), (1.25, 1.7), (1.25, 2.7), (0.9, 3.15), (-0.9, 3.15), (-1.25, 2.7)]
    parts.append(prism(arch, 0, -4.0, 2.0))  # canvas cover
    parts.append(cylinder((0.4, -0.95, 0.95), (1.6, -0.95, 0.95), 0.3))  # fuel tank
    return parts


@_variant(
    "truck", "k2", Fraction(1, 35), 900.0,
    {"cab": "bonneted", "cargo": "open drop-side bed", "axles": 2},
    "Four-wheel bonneted utility truck: long engine hood, open drop-side bed.",
)
def _build_truck_k2() -> list[Part]:
    parts = _wheel_pairs([2.6, -2.2], 0.55, 0.78, 1.18)
    parts.append(box((-3.5, -0.5, 0.8), (3.3, 0.5, 1.15)))  # chassis frame
    hood = [(1.9, 1.0), (3.55, 1.0), (3.55, 1.8), (1.9, 2.0)]
    parts.append(prism(hood, 1, -0.8, 0.8))
    parts += both_sides(box((1.9, 0.8, 1.0), (3.4, 1.2, 1.35)))  # front fenders
    cab = [(0.4, 1.05), (2.0, 1.05), (2.0, 2.0), (1.7, 2.75), (0.4, 2.75)]
    parts.append(prism(cab, 1, -1.15, 1.15))
    parts.append(box((-3.5, -1.2, 1.15), (0.3, 1.2, 1.35)))  # bed floor
    parts += both_sides(box((-3.5, 1.12, 1.35), (0.3, 1.2, 1.95)))  # drop sides
    parts.append(box((-3.5, -1.12, 1.35), (-3.42, 1.12, 1.95)))  # tailgate
    parts.append(box((0.22, -1.12, 1.35), (0.3, 1.12, 2.2)))  # headboard
    parts.append(box((3.5, -1.15, 0.7), (3.7, 1.15, 1.0)))  # bumper
    return parts


@_variant(
    "truck", "k3", Fraction(1, 35), 900.0,
    {"cab": "cab over engine", "cargo": "fuel tank", "axles": 3},
    ("Six-wheel fuel tanker: cab over engine, elliptic tank with domed ends and top "
     "walkway."),
)
def _build_truck_k3() -> list[Part]:
    parts = _wheel_pairs([3.4, -1.7, -3.1], 0.55, 0.8, 1.22)
    parts.append(box((-4.4, -0.5, 0.85), (4.2, 0.5, 1.2)))
    cab = [(2.8, 1.05), (4.5, 1.05), (4.55, 2.0), (4.3, 3.0), (2.8, 3.0)]
    parts.append(prism(cab, 1, -1.2, 1.2))
    parts.append(box((4.45, -1.25, 0.75), (4.65, 1.25, 1.05)))
    rings = [
        ellipse((-4.45, 0.0, 2.1), 0, 0.85, 0.6),
        ellipse((-4.3, 0.0, 2.1), 0, 1.2, 0.9),
        ellipse((2.4, 0.0, 2.1), 0, 1.2, 0.9),
        ellipse((2.55, 0.0, 2.1), 0, 0.85, 0.6),
    ]
    parts.append(loft(rings))  # tank with domed ends
    parts.append(box((-4.0, -0.35, 2.95), (2.2, 0.35, 3.1)))  # walkway
    parts.append(box((-4.4, -1.1, 1.1), (2.6, 1.1, 1.35)))  # tank cradle
    return parts


# ---------------------------------------------------------------------------------
# Civilian vehicles (datasets/models/_civilian.py), registered after the military set
# ---------------------------------------------------------------------------------


def _register_civilian() -> None:
    for spec in CIVILIAN_VARIANTS:
        def build(spec=spec) -> list[Part]:
            return spec.build()[0]

        _VARIANTS[f"{spec.target_class}_{spec.variant}"] = _Variant(
            spec.target_class, spec.variant, Fraction(*spec.model_scale), build, 0.0, dict(spec.features),
            spec.description, "civilian", spec.build()[1])


_register_civilian()

# ---------------------------------------------------------------------------------
# Registry and public API
# ---------------------------------------------------------------------------------


_GEOMETRY_CACHE: dict[str, tuple[NDArray[np.float64], NDArray[np.int64], int]] = {}
_SHIFTS: dict[str, NDArray[np.float64]] = {}  # builder frame -> normalised frame, mm


def list_builtin_targets(group: str = "all") -> list[str]:
    """Names of the built-in targets, in a stable order (group, class, then variant).

    Parameters
    ----------
    group : {"all", "military", "civilian"}
        ``military``: the camouflaged tanks, jets, ships and trucks (what the target spec
        ``builtin`` means); ``civilian``: cars, vans, buses and trucks in body colours.

    Returns
    -------
    list of str
        ``["tank_t1", ..., "truck_k3", "car_sedan", ..., "truck_kei"]`` for ``all``.
    """
    if group not in ("all", *GROUPS):
        raise InputError(f"group: expected all, {', '.join(GROUPS)}; got {group!r}")
    return [n for n, v in _VARIANTS.items() if group in ("all", v.group)]


def builtin_classes(group: str = "all") -> list[str]:
    """Target classes of the built-in targets of ``group`` (:func:`list_builtin_targets`),
    in a stable order: ``tank jet ship truck car van bus`` for ``all``."""
    names = list_builtin_targets(group)
    return [c for c in _CLASSES if any(_VARIANTS[n].target_class == c for n in names)]


def builtin_targets_of_class(cls: str) -> list[str]:
    """Built-in target names of class ``cls`` (both groups: ``truck`` is the military
    trucks and the civilian box truck, pickup and kei truck); empty for an unknown class."""
    return [n for n, v in _VARIANTS.items() if v.target_class == cls]


def _full_size_geometry(name: str) -> tuple[NDArray[np.float64], NDArray[np.int64], int]:
    """Full-size vertices (mm, normalised object frame), faces and part count."""
    cached = _GEOMETRY_CACHE.get(name)
    if cached is None:
        parts = _VARIANTS[name].build()
        offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
        vertices = np.vstack([v for v, _ in parts])
        faces = np.vstack([f + o for (_, f), o in zip(parts, offsets)])
        lo = vertices.min(axis=0)
        hi = vertices.max(axis=0)
        shift = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])
        vertices = vertices - shift
        vertices.setflags(write=False)
        faces.setflags(write=False)
        cached = (vertices, faces, len(parts))
        _GEOMETRY_CACHE[name] = cached
        _SHIFTS[name] = shift
    return cached


def _scale_ratio(scale: float | str, model_scale: Fraction) -> float:
    if isinstance(scale, str):
        if scale == "model":
            return float(model_scale)
        if scale == "full":
            return 1.0
        raise InputError(f"scale: expected 'model', 'full' or a positive number, got {scale!r}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.integer, np.floating)):
        raise InputError(f"scale: expected 'model', 'full' or a positive number, got {scale!r}")
    ratio = float(scale)
    if not np.isfinite(ratio) or ratio <= 0:
        raise InputError(f"scale: expected a finite ratio to full size > 0, got {scale!r}")
    return ratio


def _check_name_and_seed(name: str, seed: int) -> None:
    if name not in _VARIANTS:
        raise InputError(
            f"unknown built-in target {name!r}; valid names: {', '.join(_VARIANTS)}"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed: expected a non-negative integer, got {seed!r}")


def _paint(name: str, patch_mm: float, camouflage: bool, seed: int, palette: str | None, ratio: float = 1.0):
    """Albedo field: the camouflage of ``name`` or its plain base coat; a civilian
    vehicle's body colour (drawn from ``seed``), glass and tyres."""
    spec = _VARIANTS[name]
    if spec.group == "civilian":
        if palette is not None:
            raise InputError(f"palette: {name} is a civilian vehicle painted in a body colour; give no palette")
        _full_size_geometry(name)
        sx, _, sz = _SHIFTS[name]
        zones = dict(spec.zones or {})
        zones["glass"] = [(a - sx / 1e3, b - sx / 1e3, c - sz / 1e3, d - sz / 1e3) for a, b, c, d in zones["glass"]]
        zones["trim"] = [(a - sx / 1e3, b - sx / 1e3, c - sz / 1e3, d - sz / 1e3) for a, b, c, d in zones["trim"]]
        zones["wheels"] = [(x - sx / 1e3, r) for x, r in zones["wheels"]]
        return paint_for(zones, body_colour(seed, list(_VARIANTS).index(name))[1]).scaled(ratio)
    if not camouflage:
        return plain_paint(spec.target_class, palette=palette)
    # Mix the variant index into the seed so two targets never share a pattern.
    variant_index = list(_VARIANTS).index(name)
    return camouflage_field(
        spec.target_class,
        patch_size_mm=patch_mm,
        seed=int(seed) * len(_VARIANTS) + variant_index,
        palette=palette,
    )


def _metadata(name: str, vertices: NDArray, ratio: float, n_parts: int, camouflage: bool, seed: int,
              palette: str | None) -> dict:
    spec = _VARIANTS[name]
    extent = vertices.max(axis=0) - vertices.min(axis=0)
    if spec.group == "civilian":
        palette_name, camouflage = "none", False
    else:
        palette_name = CLASS_PALETTES[spec.target_class] if palette is None else palette
    return {
        "class": spec.target_class,
        "variant": spec.variant,
        "name": name,
        "model_scale": float(spec.model_scale),
        "model_scale_label": f"{spec.model_scale.numerator}:{spec.model_scale.denominator}",
        "scale": ratio,
        "length_mm": float(extent[0]),
        "width_mm": float(extent[1]),
        "height_mm": float(extent[2]),
        "full_length_mm": float(extent[0] / ratio),
        "provenance": "builtin procedural",
        "description": spec.description,
        "features": dict(spec.features),
        "parts": n_parts,
        "camouflage": palette_name if camouflage else "none",
        "patch_size_mm": spec.patch_full_mm * ratio,
        "seed": int(seed),
        "group": spec.group,
        **({"paint": body_colour(seed, list(_VARIANTS).index(name))[0]} if spec.group == "civilian" else {}),
    }


def builtin_target(
    name: str,
    *,
    scale: float | str = "model",
    camouflage: bool = True,
    seed: int = 0,
    palette: str | None = None,
) -> SceneMesh:
    """Build a built-in procedural target (frame and scales: docs/targets.md).

    Parameters
    ----------
    name : str
        One of :func:`list_builtin_targets` (e.g. ``"tank_t1"``).
    scale : {"model", "full"} or float
        The kit scale (model 150-280 mm long), real size, or a ratio to full size.
    camouflage : bool
        Disruptive camouflage paint, else the plain base coat.
    seed : int
        Camouflage pattern seed (>= 0); the geometry does not depend on it.
    palette : str, optional
        Overrides the class's palette (:data:`~prism3d.capture.camouflage.PALETTES`).

    Returns
    -------
    SceneMesh
        Vertices ``(N, 3)`` float64 mm, object frame (x forward, y left, z up, origin at
        the footprint centre on the ground), ``albedo_field``, and ``metadata``
        (class, variant, sizes ``length_mm width_mm height_mm`` = extents along x, y, z,
        scales, description, camouflage, ``patch_size_mm``, seed).

    Raises
    ------
    InputError
        Unknown ``name`` (the message lists valid names), bad ``scale``, ``seed``, ``palette``.
    """
    _check_name_and_seed(name, seed)
    spec = _VARIANTS[name]
    ratio = _scale_ratio(scale, spec.model_scale)
    full_vertices, faces, n_parts = _full_size_geometry(name)
    vertices = full_vertices * ratio
    albedo = _paint(name, spec.patch_full_mm * ratio, camouflage, seed, palette, ratio)
    return SceneMesh(
        vertices=vertices,
        faces=np.array(faces),
        albedo_field=albedo,
        name=name,
        metadata=_metadata(name, vertices, ratio, n_parts, camouflage, seed, palette),
    )


EDGES_PER_PATCH = 3.0  # export: default longest edge = patch / 3, so vertex paint shows the pattern
SUBDIVIDE_MAX_ITER = 12  # trimesh subdivision passes; each halves the edges (4096x shorter at most)


def export_builtin_target(
    name: str,
    out_path: str | Path,
    *,
    scale: float | str = "model",
    camouflage: bool = True,
    seed: int = 0,
    palette: str | None = None,
    max_edge_mm: float | None = None,
) -> Path:
    """Write a built-in target as a binary PLY mesh with vertex colours, atomically.

    The paint is sampled at the vertices after splitting faces to edges of at most
    ``max_edge_mm`` (default a third of the patch size): for viewers and exchange; the
    renderer should use :func:`builtin_target` (exact procedural paint). ``scale``,
    ``camouflage``, ``seed``, ``palette`` as for :func:`builtin_target`. Returns
    ``out_path`` (a ``.ply`` in an existing folder, else InputError).
    """
    import trimesh  # lazy: only needed for the export

    path = Path(out_path)
    if path.suffix.lower() != ".ply":
        raise InputError(f"{path}: expected a .ply output file, got suffix {path.suffix!r}")
    if not path.parent.is_dir():
        raise InputError(f"{path}: output folder {path.parent} does not exist")
    mesh = builtin_target(name, scale=scale, camouflage=camouflage, seed=seed, palette=palette)
    vertices, faces = mesh.vertices, mesh.faces
    if camouflage:
        edge = (
            mesh.metadata["patch_size_mm"] / EDGES_PER_PATCH
            if max_edge_mm is None
            else check_positive(max_edge_mm, "max_edge_mm")
        )
        vertices, faces = trimesh.remesh.subdivide_to_size(
            vertices, faces, max_edge=edge, max_iter=SUBDIVIDE_MAX_ITER
        )
        merged = trimesh.Trimesh(vertices, faces, process=True)
        vertices = np.asarray(merged.vertices, dtype=np.float64)
        faces = np.asarray(merged.faces, dtype=np.int64)
    colors = np.clip(np.asarray(mesh.albedo_field(vertices)), 0.0, 1.0)
    md = mesh.metadata
    comments = [
        f"prism3d builtin target {name} ({md['class']} {md['variant']})",
        f"units mm; frame x forward, y left, z up; scale {md['scale']:.9g} of full size",
        f"length_mm {md['length_mm']:.4f} width_mm {md['width_mm']:.4f}"
        f" height_mm {md['height_mm']:.4f}",
        f"camouflage {md['camouflage']} seed {md['seed']}",
    ]
    write_ply(path, vertices, colors=colors, faces=faces, comments=comments)
    return path
