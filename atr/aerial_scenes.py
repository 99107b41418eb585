"""Aerial training scenes composed from nadir sprites: what a survey's orthophoto and
normalised DSM show of vehicles, with exact truth.

A patch is a square of ground seen from straight above at the detector's working ground
sample distance: a paved car park (rows of bays, painted lines, vehicles side by side,
trees overhanging the edge rows, people, poles), a street (lanes and their markings,
crossings, vehicles queued or spread along the lanes, pavements beside) or open ground
(grass, soil, gravel; vehicles and clutter scattered). Every object is a sprite of its mesh
(:func:`prism3d.capture.nadir.render_nadir`) turned to its heading, composited by height,
lit by a sun of random elevation and azimuth with the shadows the height field casts,
then seen through a camera (blur, gain, colour cast, noise; optionally metered and
sRGB-encoded as a JPEG is, else linear as our flights render). The normalised DSM a survey
would give is emulated from the exact heights: gridded at a DSM cell, smoothed, noisy,
with holes where the image has no texture to match (shadows, dark paint, uniform asphalt)
and a few at random. Why these choices and what they bought: docs/atr.md "Vehicles from
the air".
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.capture.nadir import NadirSprite
from prism3d.capture.paints import draw_body_paint
from prism3d.capture.scenes import value_noise
from prism3d.errors import InputError

__all__ = ["AerialPatch", "PatchSpec", "compose_patch"]


@dataclass(frozen=True)
class PatchSpec:
    """How training patches are made (one place per default)."""

    gsd_m: float = 0.06
    """Working ground sample distance, m per pixel (the detector's grid)."""
    size_m: float = 36.0
    """Side of a patch, m."""
    carpark_share: float = 0.65
    """Share of patches that are car parks."""
    road_share: float = 0.0
    """Share of patches that are streets: lanes, their markings and crossings, vehicles
    queued or spread along them, pavements beside (the rest open ground). Off by default:
    streets raise recall on real street photographs but cost the simulated car parks and
    the field flight's tanks (docs/atr.md "Streets and the camera curve")."""
    dsm_cell_m: tuple[float, float] = (0.10, 0.24)
    """Range of the emulated DSM's cell, m."""
    dsm_noise_m: tuple[float, float] = (0.03, 0.15)
    """Range of the emulated DSM's height noise, m."""
    hole_share: tuple[float, float] = (0.0, 0.6)
    """Range of the share of bright textureless cells (smooth asphalt, concrete slabs)
    left without a height, as stereo leaves them."""
    dark_hole_share: tuple[float, float] = (0.0, 1.0)
    """The same for dark cells (shadow, dark paint): up to all of them (a black roof is
    often wholly missing from a survey's nDSM; a bright slab between paving joints is not)."""
    missing_dsm_share: float = 0.1
    """Share of patches whose DSM is missing altogether (appearance only)."""
    repaint: float = 0.7
    """Share of target vehicles in car parks repainted in a body colour drawn as in car
    parks (the sprite's commonest colour is taken for its body); vehicles of other classes
    half as often, so a camouflaged tank is refused mostly as what it is."""
    repaint_open: float = 0.3
    """The same share on open ground, where vehicles are more often seen in their own
    paint (a camouflaged truck on grass is still a truck)."""
    tone_share: float = 0.0
    """Share of patches seen as a real camera's JPEG shows them: metered so the scene's
    median lands at 10-25 % of full scale, then sRGB-encoded (dark asphalt comes out mid
    grey). The rest stay linear, as the simulator's own flights render. Off by default
    (same measurements as ``road_share``)."""


@dataclass(frozen=True)
class AerialPatch:
    """A training patch: ``rgb`` (H, W, 3) float32 [0, 1], ``ndsm`` (H, W) float32 m
    (NaN: no height), ``gsd`` m, ``vehicles`` (truth: ``row``, ``col``, ``heading_rad``
    (object +x from the image's +x towards -rows, i.e. counter-clockwise seen from above),
    ``cls``, ``name``, ``length_m``, ``width_m``, ``height_m``, ``visible``) and
    ``clutter`` (``row``, ``col``, ``kind``)."""

    rgb: NDArray[np.float32]
    ndsm: NDArray[np.float32]
    gsd: float
    vehicles: list[dict] = field(default_factory=list)
    clutter: list[dict] = field(default_factory=list)


# -- ground ------------------------------------------------------------------------------
def _noise(shape: tuple[int, int], gsd: float, cell_m: float, seed: int) -> NDArray[np.float64]:
    """Smooth value noise in [0, 1] over an image grid (cells of ``cell_m``)."""
    h, w = shape
    step = max(1, int(cell_m / gsd / 4))  # evaluate on a coarser grid, then resize
    ys, xs = np.arange(0, h + step, step), np.arange(0, w + step, step)
    X, Y = np.meshgrid(xs * gsd * 1000.0, ys * gsd * 1000.0)
    v = value_noise(np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1), cell_m * 1000.0, seed)
    v = v.reshape(len(ys), len(xs)).astype(np.float32)
    return cv2.resize(v, (len(xs) * step, len(ys) * step), interpolation=cv2.INTER_LINEAR)[:h, :w]


_SURFACES = {  # base albedo and the spread of its mottling
    "asphalt": ((0.13, 0.13, 0.14), 0.35),
    "asphalt_light": ((0.24, 0.24, 0.25), 0.25),
    "concrete": ((0.45, 0.44, 0.41), 0.2),
    "grass": ((0.22, 0.32, 0.12), 0.35),
    "dry_grass": ((0.40, 0.38, 0.22), 0.3),
    "gravel": ((0.38, 0.35, 0.31), 0.3),
    "soil": ((0.38, 0.30, 0.21), 0.3),
}


def _surface(rng: np.random.Generator, kind: str, shape: tuple[int, int], gsd: float) -> NDArray[np.float32]:
    base, spread = _SURFACES[kind]
    s = int(rng.integers(1 << 30))
    n = 0.5 * _noise(shape, gsd, rng.uniform(2.0, 6.0), s) + 0.3 * _noise(shape, gsd, 0.5, s + 1) \
        + 0.2 * rng.random(shape).astype(np.float32)
    tint = np.asarray(base) * rng.uniform(0.8, 1.2) * rng.uniform(0.93, 1.07, 3)
    return (tint[None, None, :] * (1.0 - spread + 2.0 * spread * n)[..., None]).astype(np.float32)


def _joints(rng: np.random.Generator, albedo: NDArray, gsd: float) -> None:
    """Paving: a grid of darker joints 1-3 m apart at a random angle, in place."""
    n = albedo.shape[0]
    step = rng.uniform(1.0, 3.0) / gsd
    ang = rng.uniform(0, math.pi)
    segs = []
    for k in range(-int(2 * n / step), int(2 * n / step)):
        for a in (ang, ang + math.pi / 2):
            c, s_ = math.cos(a), math.sin(a)
            o = np.array([n / 2, n / 2]) + k * step * np.array([-s_, c])
            segs.append((o[1] - 2 * n * s_, o[0] - 2 * n * c, o[1] + 2 * n * s_, o[0] + 2 * n * c))
    _paint_lines(albedo, segs, max(1.0, 0.03 / gsd), (albedo.mean(axis=(0, 1)) * 0.55).astype(np.float32))


def _decoys(rng: np.random.Generator, albedo: NDArray, gsd: float, count: int) -> NDArray[np.bool_]:
    """Flat, car-sized painted rectangles (patched asphalt, stains, markings, covers), some
    with bands across like a windscreen's: appearance without height. Returns their mask."""
    n = albedo.shape[0]
    mask = np.zeros((n, n), np.uint8)
    for _ in range(count):
        L, W = rng.uniform(3.0, 6.0) / gsd, rng.uniform(1.4, 2.4) / gsd
        r, c, a = rng.uniform(0, n), rng.uniform(0, n), rng.uniform(0, 180)
        box = cv2.boxPoints(((c, r), (L, W), a)).astype(np.int32)
        one = np.zeros((n, n), np.uint8)
        cv2.fillPoly(one, [box], 1)
        colour = rng.uniform(0.03, 0.85) * rng.uniform(0.9, 1.1, 3)
        albedo[one > 0] = colour
        if rng.uniform() < 0.5:  # bands across it, as a windscreen and rear window look
            for f in (0.3, -0.3):
                ca, sa = math.cos(math.radians(a)), math.sin(math.radians(a))
                cx, cy = c + f * L * ca, r + f * L * sa
                band = cv2.boxPoints(((cx, cy), (0.12 * L, W * 0.9), a)).astype(np.int32)
                cv2.fillPoly(albedo, [band], tuple(float(v) for v in np.asarray(colour) * 0.3))
        mask |= one
    return mask > 0


def _paint_lines(albedo: NDArray, segments: Sequence[tuple[float, float, float, float]], width_px: float,
                 colour: NDArray) -> None:
    """Draw painted line segments (row, col endpoints) onto ``albedo`` in place."""
    mask = np.zeros(albedo.shape[:2], dtype=np.uint8)
    t = max(1, int(round(width_px)))
    for r0, c0, r1, c1 in segments:
        cv2.line(mask, (int(round(c0 * 16)), int(round(r0 * 16))), (int(round(c1 * 16)), int(round(r1 * 16))), 255,
                 t, cv2.LINE_AA, 4)
    a = (mask.astype(np.float32) / 255.0)[..., None]
    albedo *= 1.0 - a
    albedo += a * colour


# -- placing sprites ---------------------------------------------------------------------
@dataclass
class _Canvas:
    albedo: NDArray[np.float32]
    normal: NDArray[np.float32]
    height: NDArray[np.float32]
    owner: NDArray[np.int32]  # -1 ground, else the object's index


def _repaint(sp: NadirSprite, rng: np.random.Generator) -> NadirSprite:
    """The sprite with its body (the pixels within 0.04 of its commonest albedo) in a new
    body paint, shading kept (each pixel scaled as the old colour was)."""
    a = sp.alpha > 0.5
    if a.sum() < 10:
        return sp
    alb = sp.albedo / np.maximum(sp.alpha, 1e-6)[..., None]
    q = np.round(alb[a] * 25).astype(np.int64)
    key = q[:, 0] * 676 + q[:, 1] * 26 + q[:, 2]
    mode = np.bincount(key).argmax()
    body = np.array([mode // 676, (mode // 26) % 26, mode % 26]) / 25.0
    near = a & (np.abs(alb - body).max(axis=-1) <= 0.04 + 1.0 / 25)
    _, paint = draw_body_paint(rng)
    new = alb.copy()
    new[near] = np.clip(np.asarray(paint) * (alb[near] + 0.02) / (body + 0.02), 0.0, 1.0)
    return NadirSprite(new.astype(np.float32) * sp.alpha[..., None], sp.normal, sp.height, sp.alpha, sp.gsd, sp.name,
                       sp.length_m, sp.width_m, sp.height_m)


def _place(cv: _Canvas, sp: NDArray | NadirSprite, row: float, col: float, heading: float, base: float,
           index: int) -> None:
    """Composite a sprite turned by ``heading`` (rad, counter-clockwise seen from above)
    centred at (row, col), standing on ``base`` m; taller surfaces win."""
    h, w = sp.alpha.shape
    H, W = cv.height.shape
    diag = int(math.ceil(math.hypot(h, w))) + 2
    c, s = math.cos(heading), math.sin(heading)
    # image coordinates: x = col, y = row (down); a counter-clockwise turn seen from above is
    # clockwise in (x, y-down) terms
    M = np.array([[c, s, 0.0], [-s, c, 0.0]])
    M[:, 2] = np.array([diag / 2.0, diag / 2.0]) - M[:, :2] @ np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    warp = lambda a: cv2.warpAffine(a, M, (diag, diag), flags=cv2.INTER_LINEAR, borderValue=0.0)
    alpha = warp(sp.alpha)
    if not (alpha > 0.5).any():
        return
    hgt = warp(sp.height) + base
    alb = warp(sp.albedo)
    nrm = warp(sp.normal)
    nx, ny = nrm[..., 0].copy(), nrm[..., 1].copy()
    nrm[..., 0], nrm[..., 1] = c * nx - s * ny, s * nx + c * ny
    r0, c0 = int(round(row - diag / 2.0)), int(round(col - diag / 2.0))
    a0, b0 = max(0, -r0), max(0, -c0)
    a1, b1 = min(diag, H - r0), min(diag, W - c0)
    if a1 <= a0 or b1 <= b0:
        return
    sl = (slice(r0 + a0, r0 + a1), slice(c0 + b0, c0 + b1))
    al = alpha[a0:a1, b0:b1]
    take = (al > 0.5) & (hgt[a0:a1, b0:b1] >= cv.height[sl])
    cv.albedo[sl][take] = (alb[a0:a1, b0:b1] / np.maximum(al, 1e-6)[..., None])[take]  # un-premultiplied
    n = nrm[a0:a1, b0:b1]
    cv.normal[sl][take] = n[take] / np.maximum(np.linalg.norm(n[take], axis=-1, keepdims=True), 1e-6)
    cv.height[sl][take] = hgt[a0:a1, b0:b1][take]
    cv.owner[sl][take] = index


def _shadow(height: NDArray[np.float32], gsd: float, sun_az: float, sun_el: float) -> NDArray[np.float32]:
    """1 lit, 0 in the shadow the height field casts under a sun at azimuth ``sun_az``
    (rad, counter-clockwise from the image's +x seen from above) and elevation ``sun_el``;
    marched on a grid twice as coarse, softened by a pixel."""
    k = 2
    hs = cv2.resize(height, (height.shape[1] // k, height.shape[0] // k), interpolation=cv2.INTER_AREA)
    top = float(hs.max())
    if top <= 0.05:
        return np.ones_like(height)
    tan_el = math.tan(sun_el)
    step = 1.0
    n = int(math.ceil(top / tan_el / (gsd * k) / step)) + 1
    dx, dy = math.cos(sun_az), -math.sin(sun_az)  # towards the sun, in (col, row)
    lit = np.ones(hs.shape, dtype=bool)
    H, W = hs.shape
    for i in range(1, n + 1):
        ox, oy = int(round(i * step * dx)), int(round(i * step * dy))
        if abs(ox) >= W or abs(oy) >= H:
            break
        shifted = np.zeros_like(hs)
        shifted[max(0, -oy):H - max(0, oy), max(0, -ox):W - max(0, ox)] = \
            hs[max(0, oy):H - max(0, -oy), max(0, ox):W - max(0, -ox)]
        lit &= ~(shifted > hs + i * step * gsd * k * tan_el + 0.05)
    out = cv2.resize(lit.astype(np.float32), (height.shape[1], height.shape[0]), interpolation=cv2.INTER_LINEAR)
    return cv2.GaussianBlur(out, (0, 0), 1.0)


# -- layouts -----------------------------------------------------------------------------
def _carpark_layout(rng: np.random.Generator, n: int, gsd: float, targets: Sequence, vehicles_neg: Sequence
                    ) -> tuple[list[tuple], list[tuple[float, float, float, float]], float]:
    """Rows of 2.5 x 5 m bays at a random angle: ``(sprite, row, col, heading, kind, cls)``
    per parked vehicle, the painted segments, and the rows' angle."""
    ang = rng.uniform(0, math.pi)
    ua = np.array([math.cos(ang), -math.sin(ang)])  # along the rows, (col, row)
    ub = np.array([math.sin(ang), math.cos(ang)])  # across
    bay_w, bay_d, aisle = rng.uniform(2.3, 2.7) / gsd, rng.uniform(4.8, 5.5) / gsd, rng.uniform(5.5, 7.5) / gsd
    ctr = np.array([n / 2.0, n / 2.0]) + rng.uniform(-0.1, 0.1, 2) * n
    pool = [(s, "target", c) for c, s in targets] + [(s, "negative", c) for c, s in vehicles_neg]
    weights = np.array([3.0 if k == "target" else 1.0 for _, k, _ in pool])
    placed, lines = [], []
    occupancy = rng.uniform(0.5, 1.0)
    span = 1.6 * n
    b = -span / 2.0
    while b < span / 2.0:
        for facing, row_b in ((1, b), (-1, b + bay_d)):
            nb = int(span // bay_w)
            for i in range(nb + 1):
                a = -span / 2.0 + i * bay_w
                p0 = ctr + ua * a + ub * row_b
                p1 = p0 + ub * bay_d * (1 if facing > 0 else 1)
                lines.append((p0[1], p0[0], p1[1], p1[0]))
            for i in range(nb):
                if rng.uniform() > occupancy:
                    continue
                sp, kind, cls = pool[int(rng.choice(len(pool), p=weights / weights.sum()))]
                if sp.length_m > 1.25 * bay_d * gsd + 1.0:
                    continue  # a bus does not fit a car bay
                a = -span / 2.0 + (i + 0.5) * bay_w + rng.normal(0, 0.12 / gsd)
                bb = row_b + bay_d / 2.0 + rng.normal(0, 0.15 / gsd)
                p = ctr + ua * a + ub * bb
                hd = ang + (math.pi / 2 if facing > 0 else -math.pi / 2) + rng.normal(0, math.radians(2.0))
                if rng.uniform() < 0.2:
                    hd += math.pi
                placed.append((sp, p[1], p[0], hd, kind, cls))
        b += 2 * bay_d + aisle
    # 0-2 long vehicles along an aisle (buses, box trucks, parked lengthwise)
    longs = [q for q in pool if q[0].length_m > 6.0]
    for _ in range(int(rng.integers(1, 5)) if longs else 0):
        # a class, then one of its vehicles; three times in four a target's (buses are few in
        # a car park, and a window learns from each one)
        mine = [q for q in longs if q[1] == "target"]
        src = mine if mine and rng.uniform() < 0.75 else longs
        long_classes = sorted({c for _, _, c in src})
        c_pick = long_classes[int(rng.integers(len(long_classes)))]
        of = [q for q in src if q[2] == c_pick]
        sp, kind, cls = of[int(rng.integers(len(of)))]
        a = rng.uniform(-0.4, 0.4) * n
        p = ctr + ua * a + ub * (2 * bay_d + aisle / 2.0 - span / 2.0 + rng.integers(0, 3) * (2 * bay_d + aisle))
        placed = [q for q in placed if math.hypot(q[1] - p[1], q[2] - p[0]) > (sp.length_m / 2 + 2.0) / gsd]
        placed.append((sp, p[1], p[0], ang + rng.normal(0, 0.03) + (math.pi if rng.uniform() < 0.5 else 0.0),
                       kind, cls))
    return placed, lines, ang


def _road_layout(rng: np.random.Generator, albedo: NDArray, gsd: float, targets: Sequence, vehicles_neg: Sequence
                 ) -> list[tuple]:
    """A street across the patch at a random angle, drawn into ``albedo`` in place: 2-5
    lanes of 3.0-3.7 m with their markings (dashed lanes, a solid or double yellow
    divider, edge lines, now and then a zebra crossing and its stop lines), kerbs and
    pavements beside. Vehicles drive or queue along the lanes, each lane one way.
    Returns ``(sprite, row, col, heading, kind, cls)`` per vehicle."""
    n = albedo.shape[0]
    ang = rng.uniform(0, math.pi)
    ua = np.array([math.cos(ang), -math.sin(ang)])  # along the street, (col, row)
    ub = np.array([math.sin(ang), math.cos(ang)])  # across
    ctr = np.array([n / 2.0, n / 2.0]) + ub * rng.uniform(-0.2, 0.2) * n
    lanes, lane_w = int(rng.integers(2, 6)), rng.uniform(3.0, 3.7) / gsd
    half = lanes * lane_w / 2.0
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float32)
    _street_sides(rng, albedo, (cols - ctr[0]) * ub[0] + (rows - ctr[1]) * ub[1], half, gsd)

    def seg(a0: float, a1: float, t: float) -> tuple[float, float, float, float]:
        p0, p1 = ctr + ua * a0 + ub * t, ctr + ua * a1 + ub * t
        return (p0[1], p0[0], p1[1], p1[0])

    mid = _street_markings(rng, albedo, seg, lanes, lane_w, gsd)
    pool = [(s, "target", c) for c, s in targets] + [(s, "negative", c) for c, s in vehicles_neg]
    pool = [q for q in pool if q[0].width_m <= 0.95 * lane_w * gsd] or pool[:1]  # no aircraft in a lane
    weights = np.array([3.0 if k == "target" else 1.0 for _, k, _ in pool])
    placed = []
    for i in range(lanes):
        forward = i >= mid  # mid < 0 on a one-way street
        queue = rng.uniform() < 0.4
        a = -0.8 * n + rng.uniform(0, 10.0) / gsd
        while a < 0.8 * n:
            sp, kind, cls = pool[int(rng.choice(len(pool), p=weights / weights.sum()))]
            a += sp.length_m / 2.0 / gsd
            p = ctr + ua * a + ub * (-half + (i + 0.5) * lane_w + rng.normal(0, 0.25 / gsd))
            hd = ang + (0.0 if forward else math.pi) + rng.normal(0, math.radians(2.0))
            placed.append((sp, p[1], p[0], hd, kind, cls))
            a += sp.length_m / 2.0 / gsd + (rng.uniform(0.8, 2.5) if queue else rng.exponential(12.0) + 2.0) / gsd
    return placed


def _street_sides(rng: np.random.Generator, albedo: NDArray, across: NDArray, half: float, gsd: float) -> None:
    """Pavements of 2-4.5 m (paving with joints) beyond the carriageway's ``half`` width
    (px; ``across`` is each pixel's signed distance from its axis), verges beyond, kerbs."""
    n = albedo.shape[0]
    walk = rng.uniform(2.0, 4.5) / gsd
    pave = _surface(rng, str(rng.choice(["concrete", "asphalt_light"])), (n, n), gsd)
    _joints(rng, pave, gsd)
    side = (np.abs(across) > half) & (np.abs(across) <= half + walk)
    albedo[side] = pave[side]
    verge = np.abs(across) > half + walk
    albedo[verge] = _surface(rng, str(rng.choice(["grass", "dry_grass", "concrete", "soil"])), (n, n), gsd)[verge]
    kerb = np.abs(np.abs(across) - half) < max(1.0, 0.15 / gsd)
    albedo[kerb] *= rng.uniform(0.6, 1.4)


def _street_markings(rng: np.random.Generator, albedo: NDArray, seg: Callable, lanes: int, lane_w: float,
                     gsd: float) -> int:
    """The carriageway's paint (``seg(a0, a1, t)``: a segment along the street from ``a0``
    to ``a1`` at ``t`` across, px). Returns the index of the lane the divider stands
    before (-1: one way)."""
    n = albedo.shape[0]
    half = lanes * lane_w / 2.0
    white = np.array([0.8, 0.8, 0.76], np.float32) * rng.uniform(0.7, 1.05)
    yellow = np.array([0.75, 0.62, 0.12], np.float32) * rng.uniform(0.7, 1.05)
    mid = lanes // 2 if rng.uniform() < 0.7 else -1
    dash, gap, phase = rng.uniform(2.0, 3.5) / gsd, rng.uniform(4.0, 9.0) / gsd, rng.uniform(0, 10.0) / gsd
    for i in range(1, lanes):
        t = -half + i * lane_w
        if i == mid:
            div = [seg(-n, n, t + d) for d in ((-0.12 / gsd, 0.12 / gsd) if rng.uniform() < 0.5 else (0.0,))]
            _paint_lines(albedo, div, 0.12 / gsd, yellow if rng.uniform() < 0.6 else white)
        else:
            a = np.arange(-n - phase, n, dash + gap)
            _paint_lines(albedo, [seg(a0, a0 + dash, t) for a0 in a], 0.12 / gsd, white)
    if rng.uniform() < 0.6:
        _paint_lines(albedo, [seg(-n, n, -half + 0.3 / gsd), seg(-n, n, half - 0.3 / gsd)], 0.12 / gsd, white)
    if rng.uniform() < 0.4:  # a zebra crossing: stripes along the street, across its width, stop lines
        at, w = rng.uniform(-0.3, 0.3) * n, rng.uniform(2.5, 4.0) / gsd
        step = rng.uniform(1.0, 1.4) / gsd
        _paint_lines(albedo, [seg(at - w / 2, at + w / 2, t) for t in np.arange(-half + step / 2, half, step)],
                     step / 2, white)
        stops = []
        for sgn in (-1, 1):
            a0 = at + sgn * (w / 2 + 1.0 / gsd)
            r0, c0, _, _ = seg(a0, a0, -half)
            r1, c1, _, _ = seg(a0, a0, half)
            stops.append((r0, c0, r1, c1))
        _paint_lines(albedo, stops, 0.3 / gsd, white)
    return mid


def _scatter_layout(rng: np.random.Generator, n: int, gsd: float, targets: Sequence, vehicles_neg: Sequence,
                    count: int) -> list[tuple]:
    pool = [(s, "target", c) for c, s in targets] + [(s, "negative", c) for c, s in vehicles_neg]
    out, taken = [], []
    for _ in range(count):
        sp, kind, cls = pool[int(rng.integers(len(pool)))]
        for _try in range(30):
            r, c = rng.uniform(0.05, 0.95, 2) * n
            rad = (sp.length_m / 2 + 1.0) / gsd
            if all(math.hypot(r - a, c - b) > rad + rb for a, b, rb in taken):
                taken.append((r, c, rad))
                out.append((sp, r, c, rng.uniform(0, 2 * math.pi), kind, cls))
                break
    return out


# -- the patch ---------------------------------------------------------------------------
def compose_patch(rng: np.random.Generator, targets: Sequence[tuple[str, NadirSprite]],
                  negatives: Sequence[tuple[str, NadirSprite]], spec: PatchSpec | None = None) -> AerialPatch:
    """One training patch (module docstring): ``targets`` are ``(class, sprite)`` of the
    vehicles to find, ``negatives`` ``(kind, sprite)`` of everything else (other vehicles:
    kind ``vehicle:<class>``; trees, bushes, people, poles, rocks, buildings...)."""
    o = PatchSpec() if spec is None else spec
    if not targets:
        raise InputError("aerial scenes: no targets to place")
    g = o.gsd_m
    n = int(round(o.size_m / g))
    neg_veh = [(k.split(":", 1)[1], s) for k, s in negatives if k.startswith("vehicle:")]
    props = [(k, s) for k, s in negatives if not k.startswith("vehicle:")]
    u = rng.uniform()
    carpark, road = u < o.carpark_share, o.carpark_share <= u < o.carpark_share + o.road_share
    albedo, decoy = _ground(rng, carpark or road, n, g)
    if carpark:
        objs, lines, _ = _carpark_layout(rng, n, g, targets, neg_veh)
        colour = np.array([0.8, 0.8, 0.76]) if rng.uniform() < 0.8 else np.array([0.75, 0.62, 0.12])
        _paint_lines(albedo, lines, rng.uniform(0.1, 0.15) / g, colour.astype(np.float32))
    elif road:
        objs = _road_layout(rng, albedo, g, targets, neg_veh)
    else:
        objs = _scatter_layout(rng, n, g, targets, neg_veh, int(rng.integers(3, 9)))
    clutter = _clutter(rng, n, g, objs, props)
    canvas = _Canvas(albedo, np.dstack([np.zeros((n, n, 2), np.float32), np.ones((n, n, 1), np.float32)]),
                     np.zeros((n, n), np.float32), np.full((n, n), -1, np.int32))
    share = o.repaint if carpark or road else o.repaint_open
    objs = [(_repaint(sp, rng) if rng.uniform() < share * (1.0 if kind == "target" else 0.5) else sp, r, c, hd,
             kind, cls) for sp, r, c, hd, kind, cls in objs]
    everything = objs + clutter
    for i, (sp, r, c, hd, _, _) in enumerate(everything):
        _place(canvas, sp, r, c, hd, 0.0, i)
    tone = bool(o.tone_share > 0 and rng.uniform() < o.tone_share)
    rgb = _camera(rng, _sunlit(rng, canvas, g), g, tone=tone)
    # stereo's holes follow the light the sensor got, not the JPEG's curve
    linear = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4) if tone else rgb
    ndsm = _emulate_ndsm(rng, canvas.height, linear, g, o, keep=decoy & (canvas.owner < 0))
    vehicles = []
    for i, (sp, r, c, hd, kind, cls) in enumerate(objs):
        if kind != "target" or not (0 <= r < n and 0 <= c < n):
            continue
        vis = float((canvas.owner == i).sum()) / max(1.0, float((sp.alpha > 0.5).sum()))
        vehicles.append({"row": float(r), "col": float(c), "heading_rad": float(hd % (2 * math.pi)), "cls": cls,
                         "name": sp.name, "length_m": sp.length_m, "width_m": sp.width_m, "height_m": sp.height_m,
                         "visible": round(min(1.0, vis), 3)})
    others = [{"row": float(r), "col": float(c), "kind": (f"vehicle:{cls}" if kind == "negative" else cls),
               "heading_rad": float(hd), "length_m": sp.length_m, "width_m": sp.width_m}
              for sp, r, c, hd, kind, cls in everything if kind != "target" and 0 <= r < n and 0 <= c < n]
    return AerialPatch(rgb.astype(np.float32), ndsm, g, vehicles, others)


def _ground(rng: np.random.Generator, carpark: bool, n: int, g: float) -> tuple[NDArray[np.float32], NDArray]:
    """The bare ground's albedo (a car park's paving, or open ground), with joints and
    painted decoys (whose mask is returned)."""
    if carpark:
        surface = str(rng.choice(["asphalt", "asphalt", "asphalt_light", "concrete", "gravel"]))
    else:
        surface = str(rng.choice(["grass", "dry_grass", "soil", "gravel", "grass"]))
    albedo = _surface(rng, surface, (n, n), g)
    if surface in ("concrete", "asphalt_light", "gravel") and rng.uniform() < 0.6:
        _joints(rng, albedo, g)
    return albedo, _decoys(rng, albedo, g, int(rng.integers(0, 7)))


def _clutter(rng: np.random.Generator, n: int, g: float, objs: Sequence[tuple], props: Sequence) -> list[tuple]:
    """Clutter placed among the vehicles ``objs``: trees anywhere (crowns overhang
    vehicles), buildings and the small things clear of everything placed."""
    trees = [(k, s) for k, s in props if s.height_m > 3.0]
    small = [(k, s) for k, s in props if s.height_m <= 3.0]
    clutter = []
    taken = [(r, c, (sp.length_m / 2 + 0.3) / g) for sp, r, c, *_ in objs]
    for kinds, count in ((trees, int(rng.integers(1, 6))), (small, int(rng.integers(3, 14)))):
        for _ in range(count if kinds else 0):
            k, sp = kinds[int(rng.integers(len(kinds)))]
            for _try in range(20):
                r, c = rng.uniform(0, 1, 2) * n
                rad = (max(sp.length_m, sp.width_m) / 2 + 0.3) / g
                if sp.height_m > 3.0 and k != "building" or all(math.hypot(r - a, c - b) > rad + rb
                                                                 for a, b, rb in taken):
                    taken.append((r, c, rad))
                    clutter.append((sp, r, c, rng.uniform(0, 2 * math.pi), "clutter", k))
                    break
    return clutter


def _sunlit(rng: np.random.Generator, canvas: _Canvas, g: float) -> NDArray[np.float32]:
    """The canvas lit by a random sun (its shadows cast) and the sky's ambient light."""
    sun_el, sun_az = math.radians(rng.uniform(25.0, 70.0)), rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(sun_el) * math.cos(sun_az), math.cos(sun_el) * math.sin(sun_az), math.sin(sun_el)])
    lit = _shadow(canvas.height, g, sun_az, sun_el)
    ambient = rng.uniform(0.2, 0.45)
    shade = ambient + (1.0 - ambient) * np.clip(canvas.normal @ sun.astype(np.float32), 0.0, 1.0) * lit
    return canvas.albedo * shade[..., None]


def _camera(rng: np.random.Generator, rgb: NDArray, gsd: float, *, tone: bool = False) -> NDArray[np.float32]:
    """Exposure, colour cast, a lens blur of 0.4-1.2 px, sensor noise and 8-bit steps;
    with ``tone``, metering and the sRGB curve a camera's JPEG applies (IEC 61966-2-1)."""
    out = rgb * rng.uniform(0.75, 1.35) * rng.uniform(0.92, 1.08, 3)[None, None, :]
    if tone:
        out = out * (rng.uniform(0.10, 0.25) / max(float(np.median(out.mean(axis=2))), 1e-3))
    out = cv2.GaussianBlur(out.astype(np.float32), (0, 0), rng.uniform(0.4, 1.2))
    out = out + rng.normal(0.0, rng.uniform(0.003, 0.015), out.shape).astype(np.float32)
    out = np.clip(out, 0.0, 1.0)
    if tone:
        out = np.where(out <= 0.0031308, 12.92 * out, 1.055 * out ** (1.0 / 2.4) - 0.055)
    else:
        out = out ** rng.uniform(0.85, 1.15)
    return (np.round(out * 255.0) / 255.0).astype(np.float32)


def _emulate_ndsm(rng: np.random.Generator, height: NDArray, rgb: NDArray, gsd: float, o: PatchSpec,
                  keep: NDArray | None = None) -> NDArray[np.float32]:
    """The normalised DSM a survey would give of this patch (module docstring)."""
    n = height.shape[0]
    if rng.uniform() < o.missing_dsm_share:
        return np.full(height.shape, np.nan, dtype=np.float32)
    cell = rng.uniform(*o.dsm_cell_m)
    k = max(1, int(round(cell / gsd)))
    m = n // k
    hb = height[: m * k, : m * k].reshape(m, k, m, k)
    dsm = np.median(hb, axis=(1, 3)).astype(np.float32)
    if rng.uniform() < 0.5:  # stereo fattens objects by about a matching window
        dsm = np.maximum(dsm, cv2.dilate(dsm, np.ones((3, 3), np.uint8))) if rng.uniform() < 0.5 else dsm
        dsm = cv2.GaussianBlur(dsm, (0, 0), rng.uniform(0.4, 1.0))
    dsm = dsm + rng.normal(0.0, rng.uniform(*o.dsm_noise_m), dsm.shape).astype(np.float32)
    dsm = dsm + (rng.uniform(-0.15, 0.15) * (_noise((m, m), cell, 15.0, int(rng.integers(1 << 30))) - 0.5))
    grey = rgb[: m * k, : m * k].mean(axis=2).reshape(m, k, m, k)
    texture = grey.std(axis=(1, 3))
    mean = grey.mean(axis=(1, 3))
    dark = mean < rng.uniform(0.02, 0.07)
    flat = (texture < rng.uniform(0.002, 0.012)) & ~dark
    u = rng.uniform(size=dark.shape)
    drop = (dark & (u < rng.uniform(*o.dark_hole_share))) | (flat & (u < rng.uniform(*o.hole_share)))
    drop = cv2.morphologyEx(drop.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    blobs = _noise((m, m), cell, rng.uniform(1.0, 4.0), int(rng.integers(1 << 30))) > rng.uniform(0.8, 0.98)
    if keep is not None:  # painted decoys keep their (flat) height: appearance without height
        kb = keep[: m * k, : m * k].reshape(m, k, m, k).any(axis=(1, 3))
        drop &= ~kb
        blobs &= ~kb
    dsm[drop | blobs] = np.nan
    up = cv2.resize(dsm, (m * k, m * k), interpolation=cv2.INTER_NEAREST)
    out = np.full(height.shape, np.nan, dtype=np.float32)
    out[: m * k, : m * k] = up
    return out
