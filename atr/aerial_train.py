"""Training the aerial recogniser (:class:`~prism3d.atr.aerial.AerialModel`) on composed
scenes (:mod:`prism3d.atr.aerial_scenes`): rendered models at every heading, under every
sun, side by side in car parks and among clutter, with exact truth.

1. Targets are gathered into window groups of similar length (the longest at most 1.35
   times the shortest): a window fits its vehicles with 0.5 m to spare each way.
2. Windows are cut from training patches at the headings of the grid: positives centred
   on a group's vehicles turned within half a heading step; negatives anywhere else,
   drawn at random, half a vehicle off a vehicle (the windows between two parked cars),
   and on vehicles at other headings. A group with fewer vehicles than the best-stocked
   one sees each of its vehicles again at more headings (the ratio of the two, less one,
   at most ``positive_views``), jittered within half a step, and each vehicle that is not
   a target once at its own heading, as a negative (benchmarks/RESULTS.md: 35 bus windows
   against 521 for a car window left half the buses unfound; more truck views without the
   tanks at their heading called a camouflaged tank a truck).
3. One logistic regression per group (balanced classes, L2), then rounds of hard
   negatives: the best-scoring false windows of fresh patches are added and the group
   refitted (Felzenszwalb et al.'s data mining).
4. A multinomial logistic namer per group among its classes, on the positives.
5. Calibration: the whole detector runs on held-out patches; each detection is a
   vehicle or not (within 1.2 m of a target's centre, axis within 20 deg); Platt's
   sigmoid on the raw score, per group, turns scores into the share of detections that
   are vehicles.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from numpy.typing import NDArray
from sklearn.linear_model import LogisticRegression

from prism3d.atr.aerial import AerialGroup, AerialModel, correlate_cells, window_features
from prism3d.atr.aerial_features import CHANNEL_SETS, cell_features, rotate_scene
from prism3d.atr.aerial_scenes import AerialPatch, PatchSpec, compose_patch
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.nadir import NadirSprite, render_nadir
from prism3d.errors import InputError

__all__ = ["AerialTrainOptions", "train_aerial", "window_groups"]

#: A group's longest member is at most this many times its shortest.
GROUP_LENGTH_RATIO = 1.35
#: Room around a group's largest vehicle inside its window, m each way.
WINDOW_MARGIN_M = 0.5
#: A detection within this distance (m) of a target's centre, axis within MATCH_DEG, is a vehicle.
MATCH_M, MATCH_DEG = 1.2, 20.0


@dataclass(frozen=True)
class AerialTrainOptions:
    """How an aerial recogniser is trained (one place per default)."""

    channels: str = "both"
    """Input: ``both`` (appearance and height), ``appearance`` (orthophoto only) or
    ``height`` (nDSM only)."""
    gsd_m: float = 0.06
    """Working grid, m per pixel (scenes are resampled to it)."""
    cell_px: int = 8
    """Feature cell side, px (0.48 m at the default grid)."""
    angle_step_deg: float = 15.0
    """Heading step of the search, deg (a cell's orientation bins are 20 deg wide)."""
    patches: int = 80
    """Training patches (36 m squares) for the first fit."""
    mining_patches: int = 24
    """Fresh patches per round of hard negatives."""
    mining_rounds: int = 3
    """Rounds of hard negatives."""
    calibration_patches: int = 24
    """Held-out patches for the calibration."""
    random_negatives: int = 40
    """Random negative windows per patch and heading."""
    positive_views: int = 12
    """At most this many more views of each vehicle of a group with fewer vehicles than the
    best-stocked one (module docstring; 0: none)."""
    regularisation_c: float = 0.05
    """Inverse L2 strength of the logistic regressions."""
    seed: int = 0
    """Seeds the patches (and so the whole training)."""
    patch: PatchSpec = field(default_factory=PatchSpec)
    """The training scenes."""

    def __post_init__(self) -> None:
        if self.channels not in CHANNEL_SETS:
            raise InputError(f"channels: expected one of {', '.join(CHANNEL_SETS)}, got {self.channels!r}")
        for name in ("patches", "mining_patches", "calibration_patches", "random_negatives"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or not 1 <= v <= 100_000:
                raise InputError(f"{name}: expected a positive integer, got {v!r}")
        if isinstance(self.positive_views, bool) or int(self.positive_views) != self.positive_views \
                or not 0 <= self.positive_views <= 20:
            raise InputError(f"positive_views: expected 0-20, got {self.positive_views!r}")
        if isinstance(self.mining_rounds, bool) or not 0 <= int(self.mining_rounds) <= 10:
            raise InputError(f"mining_rounds: expected 0-10, got {self.mining_rounds!r}")
        if not (0.01 <= self.gsd_m <= 0.5):
            raise InputError(f"gsd_m: expected 0.01-0.5 m, got {self.gsd_m!r}")
        if not (1.0 <= self.angle_step_deg <= 45.0):
            raise InputError(f"angle_step_deg: expected 1-45 deg, got {self.angle_step_deg!r}")


def window_groups(items: Sequence[tuple[str, NadirSprite]]) -> list[list[tuple[str, NadirSprite]]]:
    """Targets gathered by length, shortest first, each group's longest at most
    :data:`GROUP_LENGTH_RATIO` times its shortest."""
    out: list[list[tuple[str, NadirSprite]]] = []
    for cls, sp in sorted(items, key=lambda t: t[1].length_m):
        if out and sp.length_m <= GROUP_LENGTH_RATIO * out[-1][0][1].length_m:
            out[-1].append((cls, sp))
        else:
            out.append([(cls, sp)])
    return out


def _window_cells(group: Sequence[tuple[str, NadirSprite]], cell_m: float) -> tuple[int, int]:
    L = max(sp.length_m for _, sp in group) + 2 * WINDOW_MARGIN_M
    W = max(sp.width_m for _, sp in group) + 2 * WINDOW_MARGIN_M
    return (int(math.ceil(W / cell_m)) | 1, int(math.ceil(L / cell_m)) | 1)


def _angle_diff(a: float, b: float) -> float:
    """Smallest difference between two axes (mod pi), rad."""
    d = abs(a - b) % math.pi
    return min(d, math.pi - d)


@dataclass
class _Samples:
    X: list[NDArray] = field(default_factory=list)
    y: list[int] = field(default_factory=list)
    cls: list[str] = field(default_factory=list)


def _patch_views(patch: AerialPatch, o: AerialTrainOptions, angles: Sequence[float]):
    """(angle, cell features, vehicles' and others' cell positions) per heading."""
    grey = patch.rgb.mean(axis=2)
    for ang in angles:
        g, z, M = rotate_scene(grey, patch.ndsm, ang, 0)
        F = cell_features(g, z, o.cell_px, o.channels)

        def cell_of(r: float, c: float, M: NDArray = M) -> tuple[int, int]:
            x, y = M @ np.array([c, r, 1.0])
            return int(y // o.cell_px), int(x // o.cell_px)

        yield ang, F, cell_of


def _cut(patches: Sequence[AerialPatch], groups: list, cells: list[tuple[int, int]], o: AerialTrainOptions,
         rng: np.random.Generator) -> list[_Samples]:
    """Positive and negative windows of every group from ``patches`` (module docstring)."""
    step = math.radians(o.angle_step_deg)
    grid = np.arange(0.0, math.pi, step)
    names = [{sp.name for _, sp in g} for g in groups]
    out = [_Samples() for _ in groups]
    stock = [sum(v["visible"] >= 0.6 and v["name"] in nm for p in patches for v in p.vehicles) for nm in names]
    extra = [min(o.positive_views, max(0, int(round(max(stock) / n)) - 1)) if n else 0 for n in stock]
    for p in patches:
        vis = [v for v in p.vehicles if v["visible"] >= 0.6]
        _add_views(p, vis, names, cells, extra, o, rng, out)
        angs = {float(grid[int(round((v["heading_rad"] % math.pi) / step)) % len(grid)]) for v in vis}
        # across the vehicles too: a row of cars side by side lies along that heading (a bus's look)
        angs |= {float(grid[int(round(((a + math.pi / 2) % math.pi) / step)) % len(grid)]) for a in list(angs)}
        angs |= {float(a) for a in rng.choice(grid, size=2, replace=False)}
        for ang, F, cell_of in _patch_views(p, o, sorted(angs)):
            hc, wc = F.shape[:2]
            for gi, (grp, wcells) in enumerate(zip(groups, cells)):
                pos = [(v, cell_of(v["row"], v["col"])) for v in vis
                       if v["name"] in names[gi] and _angle_diff(v["heading_rad"], ang) <= step / 2]
                taken = {ij for _, ij in pos}
                s = out[gi]
                for v, (i, j) in pos:
                    # nose to +x: a vehicle facing the other way is seen turned half round
                    x = window_features(F, i, j, wcells, turned=math.cos(v["heading_rad"] - ang) < 0)
                    if x is not None:
                        s.X.append(x)
                        s.y.append(1)
                        s.cls.append(v["cls"])
                near = set()
                for i, j in taken:
                    near |= {(i + a, j + b) for a in (-1, 0, 1) for b in (-1, 0, 1)}
                negs = [(int(i), int(j)) for i, j in zip(rng.integers(0, hc, o.random_negatives),
                                                         rng.integers(0, wc, o.random_negatives))]
                for v in p.vehicles + p.clutter:  # beside, between and on things at this heading
                    i, j = cell_of(v["row"], v["col"])
                    half_l = v["length_m"] / 2.0 / (o.gsd_m * o.cell_px)
                    half_w = (v["width_m"] / 2.0 + 0.4) / (o.gsd_m * o.cell_px)
                    for a, b in ((0, 1), (0, -1), (1, 0), (-1, 0), (0, 0)):
                        negs.append((int(round(i + a * 2 * half_w * rng.uniform(0.5, 1.0))),
                                     int(round(j + b * 2 * half_l * rng.uniform(0.4, 1.0)))))
                    for b in (1, -1):  # a little off along the vehicle: its centre must be found to a metre
                        negs.append((i, int(round(j + b * max(2.5, 2 * half_l * rng.uniform(0.15, 0.4))))))
                for i, j in negs:
                    if (i, j) in near:
                        continue
                    x = window_features(F, i, j, wcells)
                    if x is not None:
                        s.X.append(x)
                        s.y.append(0)
                        s.cls.append("")
    return out


def _add_views(p: AerialPatch, vis: Sequence[dict], names: list[set], cells: list[tuple[int, int]], extra: list[int],
               o: AerialTrainOptions, rng: np.random.Generator, out: list[_Samples]) -> None:
    """Each group's ``extra`` more views of its visible vehicles (positives) and, for such a
    group, one view of each vehicle that is not a target at its own heading (a negative:
    the cut's headings are the targets', so a tank is rarely seen at its own)."""
    sibs = [v for v in p.clutter if v["kind"].startswith("vehicle:")]
    for gi, wcells in enumerate(cells):
        for v in vis if extra[gi] else []:
            if v["name"] in names[gi]:
                for x in _more_views(p, v, wcells, extra[gi], o, rng):
                    out[gi].X.append(x)
                    out[gi].y.append(1)
                    out[gi].cls.append(v["cls"])
        for v in sibs if extra[gi] else []:
            for x in _more_views(p, v, wcells, 1, o, rng):
                out[gi].X.append(x)
                out[gi].y.append(0)
                out[gi].cls.append("")


def _more_views(p: AerialPatch, v: dict, wcells: tuple[int, int], n: int, o: AerialTrainOptions,
                rng: np.random.Generator) -> list[NDArray]:
    """``n`` more windows of vehicle ``v`` (a positive, or a non-target's negative): the
    patch around it turned to its heading plus a jitter within half a heading step (so
    its cells fall differently too)."""
    step = math.radians(o.angle_step_deg)
    cell_m = o.gsd_m * o.cell_px
    # the window's half diagonal and the 3 cells the features look around, px
    reach = int(math.ceil((math.hypot(*wcells) / 2 + 4) * cell_m / o.gsd_m))
    r0, c0 = max(0, int(v["row"]) - reach), max(0, int(v["col"]) - reach)
    r1, c1 = min(p.ndsm.shape[0], int(v["row"]) + reach + 1), min(p.ndsm.shape[1], int(v["col"]) + reach + 1)
    grey = p.rgb[r0:r1, c0:c1].mean(axis=2)
    out = []
    for _ in range(n):
        ang = float(v["heading_rad"] % math.pi + rng.uniform(-step / 2, step / 2))
        g, z, M = rotate_scene(grey, p.ndsm[r0:r1, c0:c1], ang, 0)
        F = cell_features(g, z, o.cell_px, o.channels)
        x, y = M @ np.array([v["col"] - c0, v["row"] - r0, 1.0])
        w = window_features(F, int(y // o.cell_px), int(x // o.cell_px), wcells,
                            turned=math.cos(v["heading_rad"] - ang) < 0)
        if w is not None:
            out.append(w)
    return out


def _fit(s: _Samples, o: AerialTrainOptions) -> tuple[NDArray, float]:
    X = np.asarray(s.X, dtype=np.float32)
    y = np.asarray(s.y)
    if y.sum() < 5 or (1 - y).sum() < 5:
        raise InputError(f"aerial training: too few windows to learn from ({int(y.sum())} positive, "
                         f"{int((1 - y).sum())} negative); give more patches")
    lr = LogisticRegression(C=o.regularisation_c, class_weight="balanced", max_iter=2000)
    lr.fit(X, y)
    return lr.coef_[0].astype(np.float32), float(lr.intercept_[0])


def _namer(s: _Samples, classes: list[str], o: AerialTrainOptions) -> tuple[NDArray, NDArray]:
    if len(classes) == 1:
        return np.zeros((1, 1), np.float32), np.zeros(1, np.float32)
    X = np.asarray([x for x, y in zip(s.X, s.y) if y == 1], dtype=np.float32)
    lab = [c for c, y in zip(s.cls, s.y) if y == 1]
    lr = LogisticRegression(C=o.regularisation_c * 10, max_iter=5000)
    lr.fit(X, lab)
    coef = np.zeros((len(classes), X.shape[1]), np.float32)
    bias = np.full(len(classes), -50.0, np.float32)  # a class never seen is never named
    if len(lr.classes_) == 2:
        a, b = list(lr.classes_)
        coef[classes.index(b)] = lr.coef_[0]
        bias[classes.index(b)] = lr.intercept_[0]
        bias[classes.index(a)] = 0.0
    else:
        for k, c in enumerate(lr.classes_):
            coef[classes.index(c)] = lr.coef_[k]
            bias[classes.index(c)] = lr.intercept_[k]
    return coef, bias


def _mine(model: AerialModel, patches: Sequence[AerialPatch], groups: list, cells: list, o: AerialTrainOptions,
          samples: list[_Samples], per_patch: int = 60) -> int:
    """Add each group's best-scoring false windows of ``patches`` as negatives."""
    step = math.radians(o.angle_step_deg)
    grid = np.arange(0.0, math.pi, step)
    names = [{sp.name for _, sp in g} for g in groups]
    added = 0
    for p in patches:
        for gi, grp in enumerate(model.groups):
            found = []
            for ang, F, cell_of in _patch_views(p, o, grid):
                fwd = correlate_cells(F, grp.weights)
                back = correlate_cells(F, grp.weights[::-1, ::-1])
                turned = back > fwd
                raw = np.maximum(fwd, back) + grp.bias
                ok = {cell_of(v["row"], v["col"]) for v in p.vehicles
                      if v["name"] in names[gi] and _angle_diff(v["heading_rad"], ang) <= step}
                near = set()
                for i, j in ok:
                    near |= {(i + a, j + b) for a in (-2, -1, 0, 1, 2) for b in (-2, -1, 0, 1, 2)}
                idx = np.argsort(raw, axis=None)[::-1][: per_patch * 4]
                for flat in idx:
                    i, j = divmod(int(flat), raw.shape[1])
                    if raw[i, j] < -1.0:
                        break
                    if (i, j) in near:
                        continue
                    x = window_features(F, i, j, cells[gi], turned=bool(turned[i, j]))
                    if x is not None:
                        found.append((float(raw[i, j]), x))
            found.sort(key=lambda t: -t[0])
            for _, x in found[:per_patch]:
                samples[gi].X.append(x)
                samples[gi].y.append(0)
                samples[gi].cls.append("")
                added += 1
    return added


def _calibrate(model: AerialModel, patches: Sequence[AerialPatch]) -> list[tuple[float, float]]:
    """Platt's (a, b) per group from the detections on held-out ``patches``."""
    raws: list[list[tuple[float, int]]] = [[] for _ in model.groups]
    for p in patches:
        dets = model.detect(p.rgb.mean(axis=2), p.ndsm)
        used = set()
        for d in dets:
            hit = None
            for k, v in enumerate(p.vehicles):
                if k in used or v["visible"] < 0.5:
                    continue
                dist = math.hypot(d.row - v["row"], d.col - v["col"]) * model.gsd_m
                if dist <= MATCH_M and _angle_diff(d.heading_rad, v["heading_rad"]) <= math.radians(MATCH_DEG):
                    hit = k
                    break
            if hit is not None:
                used.add(hit)
            raws[d.group].append((d.raw, int(hit is not None)))
    out = []
    for r in raws:
        y = np.array([t[1] for t in r])
        if len(r) < 10 or y.sum() < 3 or (1 - y).sum() < 3:
            out.append((1.0, 0.0))
            continue
        lr = LogisticRegression(C=100.0).fit(np.array([[t[0]] for t in r]), y)
        out.append((float(lr.coef_[0, 0]), float(lr.intercept_[0])))
    return out


def _sprites(items: Sequence[tuple[str, SceneMesh]], gsd: float) -> list[tuple[str, NadirSprite]]:
    return [(cls, render_nadir(m, gsd)) for cls, m in items]


def train_aerial(targets: Sequence[tuple[str, SceneMesh]], negatives: Sequence[tuple[str, SceneMesh]],
                 options: AerialTrainOptions | None = None, *,
                 progress: Callable[[int, int, str], None] | None = None) -> AerialModel:
    """Train an aerial recogniser of ``targets`` (``(class, SceneMesh)`` full size, mm, z
    up; several meshes may share a class) against ``negatives`` (``(kind, SceneMesh)``:
    ``vehicle:<class>`` for vehicles that are not targets, else clutter) (module docstring)."""
    o = AerialTrainOptions() if options is None else options
    if not targets:
        raise InputError("aerial training: no targets")
    t0 = time.perf_counter()
    spec = PatchSpec(**{**asdict(o.patch), "gsd_m": o.gsd_m})
    if o.channels == "height":  # a patch without an nDSM shows a height-only window nothing to learn from
        spec = PatchSpec(**{**asdict(spec), "missing_dsm_share": 0.0})
    tsp = _sprites(targets, o.gsd_m)
    nsp = _sprites(negatives, o.gsd_m)
    groups = window_groups(tsp)
    cell_m = o.gsd_m * o.cell_px
    cells = [_window_cells(g, cell_m) for g in groups]
    rng = np.random.default_rng([o.seed, 37])
    total = o.patches + o.mining_rounds * o.mining_patches + o.calibration_patches
    done = 0

    def patches(n: int, label: str) -> list[AerialPatch]:
        nonlocal done
        out = []
        for _ in range(n):
            out.append(compose_patch(rng, tsp, nsp, spec))
            done += 1
            if progress:
                progress(done, total, label)
        return out

    samples = _cut(patches(o.patches, "training patches"), groups, cells, o, rng)
    model = _assemble(groups, cells, samples, o, None, {})
    for _ in range(o.mining_rounds):
        _mine(model, patches(o.mining_patches, "hard negatives"), groups, cells, o, samples)
        model = _assemble(groups, cells, samples, o, None, {})
    platt = _calibrate(model, patches(o.calibration_patches, "calibration"))
    meta = {"targets": [[c, m.name] for c, m in targets], "negatives": [[k, m.name] for k, m in negatives],
            "options": {k: v for k, v in asdict(o).items() if k != "patch"}, "patch": asdict(o.patch),
            "windows": [{"classes": sorted({c for c, _ in g}), "names": [sp.name for _, sp in g], "cells": list(c)}
                        for g, c in zip(groups, cells)],
            "samples": [{"positive": int(sum(s.y)), "negative": int(len(s.y) - sum(s.y))} for s in samples],
            "seconds": round(time.perf_counter() - t0, 1)}
    return _assemble(groups, cells, samples, o, platt, meta)


def _assemble(groups: list, cells: list, samples: list[_Samples], o: AerialTrainOptions,
              platt: list | None, meta: dict) -> AerialModel:
    out = []
    for gi, (grp, wc) in enumerate(zip(groups, cells)):
        classes = sorted({c for c, _ in grp})
        w, b = _fit(samples[gi], o)
        coef, bias = _namer(samples[gi], classes, o)
        F = len(CHANNEL_SETS[o.channels])
        dims = {}
        for c in classes:
            sps = [sp for cc, sp in grp if cc == c]
            dims[c] = (float(np.median([s.length_m for s in sps])), float(np.median([s.width_m for s in sps])),
                       float(np.median([s.height_m for s in sps])))
        out.append(AerialGroup(tuple(classes), tuple(sp.name for _, sp in grp), wc, w.reshape(wc[0], wc[1], F), b,
                               (1.0, 0.0) if platt is None else platt[gi], coef, bias, dims))
    return AerialModel(o.gsd_m, o.cell_px, o.channels, o.angle_step_deg, tuple(out), meta)
