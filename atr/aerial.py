"""The aerial recogniser: vehicles found and named in an orthophoto and its normalised DSM.

Targets are gathered into window groups of similar length (a car window, a bus window...).
Each group has one linear detector over the cells of a window laid along the vehicle
(:mod:`prism3d.atr.aerial_features`: appearance gradients and contrast, height above the
ground and its holes) and a linear namer among its classes. The scene is turned through
headings ``angle_step_deg`` apart; at each, every group's window is correlated with the
cell grid (a window's score is the sum of its cells' weighted features, so all positions
cost one filter per feature). Local maxima become candidates; a calibrated score (Platt's
sigmoid on held-out training scenes) ranks them; each vehicle keeps its best candidate
(non-maximum suppression on the footprints), so vehicles side by side in a row stay one
detection each. Training: :mod:`prism3d.atr.aerial_train`; method and figures: docs/atr.md
"Vehicles from the air".
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.atr.aerial_features import CHANNEL_SETS, cell_features, rotate_scene
from prism3d.errors import InputError
from prism3d.io.model_file import read_model_npz, write_model_npz

__all__ = ["AERIAL_SCHEMA_VERSION", "DEFAULT_THRESHOLD", "AerialGroup", "AerialModel", "VehicleDetection",
           "correlate_cells", "window_features"]

AERIAL_SCHEMA_VERSION = 1
#: Calibrated score at or above which a candidate is reported as a vehicle (the share of
#: held-out training detections at that score that were vehicles).
DEFAULT_THRESHOLD = 0.5
#: Candidates below this calibrated score are dropped before suppression.
CANDIDATE_FLOOR = 0.02
#: A window with more than this share of its area outside the orthophoto is not judged:
#: training never showed the edge of a survey's coverage (on a real target-free survey, a
#: tree beside a no-data hole scored 0.999 as a truck), and a vehicle half outside cannot
#: be named.
MAX_OUTSIDE_SHARE = 0.2
#: Heights more than this (m) above the tallest target class stand for no target (trees,
#: buildings): a window with more than TALL_SHARE of its area that tall is not judged (a
#: linear window reads "taller" as "more like a truck"; an 11 m tree cut by a no-data hole
#: scored 0.999 as one on a real target-free survey).
TALL_MARGIN_M, TALL_SHARE = 1.0, 0.25


@dataclass(frozen=True)
class VehicleDetection:
    """A vehicle found from the air (or, from :meth:`AerialModel.candidates`, a candidate),
    in pixels of the grid searched."""

    row: float
    """Pixel row of the centre."""
    col: float
    """Pixel column of the centre."""
    heading_rad: float
    """Direction of the nose, counter-clockwise from the grid's +column axis (east)."""
    group: int
    """Index of the model's group (of similar-sized classes) that found it."""
    raw: float
    """The group's uncalibrated window score."""
    score: float
    """Calibrated score: the share of held-out detections at this score that were vehicles."""
    class_name: str
    """The class it is called."""
    class_p: tuple[float, ...]
    """The group's probability of each of its classes."""
    length_m: float | None = None
    """Footprint length, m (the named class's median; None on a candidate)."""
    width_m: float | None = None
    """Footprint width, m."""
    corners_rc: tuple[tuple[float, float], ...] | None = None
    """The footprint's four corners as (row, col) pixels."""


@dataclass(frozen=True)
class AerialGroup:
    """One window group: its target ``classes`` and member ``names``, the window
    ``cells`` (rows across the vehicle, columns along it; both odd), the detector's
    ``weights`` (rows, cols, F) and ``bias``, the calibration ``platt`` (a, b): score =
    sigmoid(a raw + b), the namer ``class_coef`` (n_classes, rows * cols * F) and
    ``class_bias``, and each class's median ``dims`` (length, width, height m)."""

    classes: tuple[str, ...]
    names: tuple[str, ...]
    cells: tuple[int, int]
    weights: NDArray[np.float32]
    bias: float
    platt: tuple[float, float]
    class_coef: NDArray[np.float32]
    class_bias: NDArray[np.float32]
    dims: dict[str, tuple[float, float, float]]

    def name(self, x: NDArray) -> tuple[str, NDArray[np.float64]]:
        """The class of a window's flattened features, seen the way round the detector
        matched it (the namer learnt vehicles nose to +x), and the namer's probabilities."""
        if len(self.classes) == 1:
            return self.classes[0], np.ones(1)
        z = self.class_coef.astype(np.float64) @ x.astype(np.float64) + self.class_bias
        p = np.exp(z - z.max())
        p /= p.sum()
        return self.classes[int(np.argmax(p))], p


@dataclass(frozen=True)
class AerialModel:
    """A trained aerial recogniser (module docstring): ``gsd_m`` of its working grid,
    ``cell_px``, ``channels`` (``both``, ``appearance`` or ``height``), ``angle_step_deg``
    and its ``groups``; ``metadata`` records how it was trained."""

    gsd_m: float
    cell_px: int
    channels: str
    angle_step_deg: float
    groups: tuple[AerialGroup, ...]
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.channels not in CHANNEL_SETS:
            raise InputError(f"aerial model: channels must be one of {', '.join(CHANNEL_SETS)}, got {self.channels!r}")
        if not self.groups:
            raise InputError("aerial model: no window groups")

    @property
    def classes(self) -> list[str]:
        out: list[str] = []
        for g in self.groups:
            out += [c for c in g.classes if c not in out]
        return out

    @property
    def cell_m(self) -> float:
        return self.gsd_m * self.cell_px

    # -- detection -------------------------------------------------------------------------
    def candidates(self, grey: NDArray, ndsm: NDArray, *, roi: NDArray | None = None,
                   angles_rad: Sequence[float] | None = None) -> list[VehicleDetection]:
        """Every local maximum of every group's score over the headings, before
        suppression (no footprint yet), in pixels of the input grid. ``grey`` and
        ``ndsm`` (H, W) share this model's ``gsd_m`` grid (``ndsm`` NaN = no height; all NaN
        for an appearance-only search); ``roi`` (H, W) bool limits where centres may fall."""
        g = np.asarray(grey, dtype=np.float32)
        z = np.asarray(ndsm, dtype=np.float32)
        if g.ndim != 2 or z.shape != g.shape:
            raise InputError(f"aerial scene: expected a grey image and an nDSM of one (H, W) shape, got "
                             f"{g.shape} and {z.shape}")
        if roi is not None and np.asarray(roi).shape != g.shape:
            raise InputError(f"aerial scene: the search area is {np.shape(roi)}, the image {g.shape}")
        if angles_rad is None:
            angles_rad = np.arange(0.0, math.pi, math.radians(self.angle_step_deg))
        if roi is None:
            return self._candidates(g, z, None, angles_rad)
        # the search area's parts, each cut out with a window's reach around it
        reach = int(self.cell_px * (max(max(gr.cells) for gr in self.groups) // 2 + 2))
        out: list[VehicleDetection] = []
        for r0, c0, r1, c1 in _boxes(np.asarray(roi, dtype=bool), reach):
            for d in self._candidates(g[r0:r1, c0:c1], z[r0:r1, c0:c1], np.asarray(roi)[r0:r1, c0:c1], angles_rad):
                out.append(replace(d, row=d.row + r0, col=d.col + c0))
        return out

    def _candidates(self, g: NDArray, z: NDArray, roi: NDArray | None, angles_rad: Sequence[float]
                    ) -> list[VehicleDetection]:
        """The headings on a pool of threads (one per core, at most two: each holds a turned
        copy of the scene; OpenCV and numpy's large operations release the GIL), gathered
        in heading order."""
        workers = max(1, min(2, os.cpu_count() or 1, len(angles_rad)))
        if workers == 1:
            return [d for ang in angles_rad for d in self._at_heading(g, z, roi, float(ang))]
        with ThreadPoolExecutor(max_workers=workers) as pool:
            parts = list(pool.map(lambda a: self._at_heading(g, z, roi, float(a)), angles_rad))
        return [d for part in parts for d in part]

    def _at_heading(self, g: NDArray, z: NDArray, roi: NDArray | None, ang: float) -> list[VehicleDetection]:
        k = self.cell_px
        pad = k * (max(max(gr.cells) for gr in self.groups) // 2 + 2)
        out: list[VehicleDetection] = []
        gr_img, z_img, M = rotate_scene(g, z, float(ang), pad)
        F = cell_features(gr_img, z_img, k, self.channels)
        hc, wc = F.shape[:2]
        if self.channels != "height":
            # each cell's share outside the orthophoto (an area mean over whole cells)
            off = cv2.resize(np.isnan(gr_img[: hc * k, : wc * k]).astype(np.float32), (wc, hc),
                             interpolation=cv2.INTER_AREA)
        if self.channels != "appearance":
            limit = max(d[2] for gr in self.groups for d in gr.dims.values()) + TALL_MARGIN_M
            tall = cv2.resize((z_img[: hc * k, : wc * k] > limit).astype(np.float32), (wc, hc),
                              interpolation=cv2.INTER_AREA)
        roi_r = None
        if roi is not None:
            rr = cv2.warpAffine(roi.astype(np.uint8), M, (gr_img.shape[1], gr_img.shape[0]), flags=cv2.INTER_NEAREST)
            roi_r = rr[: hc * k, : wc * k].reshape(hc, k, wc, k).max(axis=(1, 3)) > 0
        Minv = cv2.invertAffineTransform(M)
        for gi, grp in enumerate(self.groups):
            # the window learnt nose to +x, and turned half round (nose to -x); the better wins
            fwd = correlate_cells(F, grp.weights)
            back = correlate_cells(F, grp.weights[::-1, ::-1])
            turned = back > fwd
            raw = np.maximum(fwd, back) + grp.bias
            p = _sigmoid(grp.platt[0] * raw + grp.platt[1])
            keep = (p >= CANDIDATE_FLOOR) & (raw == cv2.dilate(raw, np.ones((3, 3), np.uint8)))
            if roi_r is not None:
                keep &= roi_r
            if self.channels != "height":
                keep &= cv2.blur(off, (grp.cells[1], grp.cells[0]), borderType=cv2.BORDER_CONSTANT) <= MAX_OUTSIDE_SHARE
            if self.channels != "appearance":
                keep &= cv2.blur(tall, (grp.cells[1], grp.cells[0]), borderType=cv2.BORDER_CONSTANT) <= TALL_SHARE
            rows, cols = np.nonzero(keep)
            for i, j in zip(rows, cols):
                x = window_features(F, i, j, grp.cells, turned=bool(turned[i, j]))
                if x is None:
                    continue
                # named the way round the detector matched it: each class's best of both ways
                # round was tried, and lost 2 points of class (RESULTS.md, dark cars)
                cls, cp = grp.name(x)
                xr, yr = (j + 0.5) * k - 0.5, (i + 0.5) * k - 0.5
                xo, yo = Minv @ np.array([xr, yr, 1.0])
                head = (float(ang) + (math.pi if turned[i, j] else 0.0)) % (2 * math.pi)
                out.append(VehicleDetection(float(yo), float(xo), head, gi, float(raw[i, j]), float(p[i, j]), cls,
                                            tuple(round(float(v), 4) for v in cp)))
        return out

    def detect(self, grey: NDArray, ndsm: NDArray, *, roi: NDArray | None = None,
               min_score: float = CANDIDATE_FLOOR) -> list[VehicleDetection]:
        """Detections best first (:meth:`candidates`, then one per vehicle), each with its
        footprint (the named class's median size)."""
        cands = sorted(self.candidates(grey, ndsm, roi=roi), key=lambda d: -d.score)
        kept: list[VehicleDetection] = []
        for d in cands:
            if d.score < min_score:
                break
            L, W, _ = self.groups[d.group].dims[d.class_name]
            if any(_overlaps(d, L, W, q, self.gsd_m) for q in kept):
                continue
            corners = tuple((float(r), float(c)) for r, c in _corners(d, L, W, self.gsd_m))
            kept.append(replace(d, length_m=L, width_m=W, corners_rc=corners))
        return kept

    # -- files -----------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the model as ``.npz`` (no pickle; JSON metadata) atomically."""
        p = Path(path)
        if p.suffix.lower() != ".npz":
            raise InputError(f"{p}: expected a .npz file name for the model")
        if p.is_dir():
            raise InputError(f"{p}: is a folder; give an output file name")
        meta = {"schema_version": AERIAL_SCHEMA_VERSION, "kind": "aerial_recogniser", "gsd_m": self.gsd_m,
                "cell_px": self.cell_px, "channels": self.channels, "angle_step_deg": self.angle_step_deg,
                "groups": [{"classes": list(g.classes), "names": list(g.names), "cells": list(g.cells),
                            "bias": g.bias, "platt": list(g.platt), "dims": {c: list(v) for c, v in g.dims.items()}}
                           for g in self.groups],
                "metadata": self.metadata}
        arrays = {}
        for i, g in enumerate(self.groups):
            arrays[f"g{i}_weights"] = g.weights.astype(np.float32)
            arrays[f"g{i}_class_coef"] = g.class_coef.astype(np.float32)
            arrays[f"g{i}_class_bias"] = g.class_bias.astype(np.float32)
        return write_model_npz(p, meta, arrays)

    @classmethod
    def load(cls, path: str | Path) -> AerialModel:
        """Read a model written by :meth:`save`; a file of another kind or version, or one
        whose contents are damaged or inconsistent (:func:`_model_from_file`), is refused."""
        p = Path(path)
        meta, arr = read_model_npz(p, "model")
        if not isinstance(meta, dict) or meta.get("kind") != "aerial_recogniser":
            kind = meta.get("kind", "unknown") if isinstance(meta, dict) else "unknown"
            raise InputError(f"{p}: a {kind} model, not an aerial recogniser "
                             "(train one with 'prism3d bank train --view nadir')")
        if meta.get("schema_version") != AERIAL_SCHEMA_VERSION:
            raise InputError(f"{p}: aerial model schema {meta.get('schema_version')}, this prism3d reads "
                             f"{AERIAL_SCHEMA_VERSION}; train it again")
        try:
            return _model_from_file(meta, arr)
        except InputError as exc:
            raise InputError(f"{p}: not a valid aerial recogniser ({exc}); train it again") from None


#: What a loaded model's grid may be (the training options' ranges, :mod:`prism3d.atr.aerial_train`).
_GSD_RANGE_M, _ANGLE_STEP_RANGE_DEG, _MAX_CELL_PX, _MAX_WINDOW_CELLS = (0.01, 0.5), (1.0, 45.0), 64, 255


def _model_from_file(meta: dict, arr: dict[str, NDArray]) -> AerialModel:
    """The model of a file's metadata and arrays, every field checked: the grid (``gsd_m``,
    ``cell_px``, ``angle_step_deg`` within the training ranges; ``channels`` known) and
    each group (:func:`_group_from_file`). A file edited by hand or damaged would otherwise
    divide by zero, index out of range or report NaN scores as no vehicles."""
    gsd = _number(meta.get("gsd_m"), "gsd_m", *_GSD_RANGE_M)
    cell_px = meta.get("cell_px")
    if isinstance(cell_px, bool) or not isinstance(cell_px, int) or not 1 <= cell_px <= _MAX_CELL_PX:
        raise InputError(f"cell_px: expected an integer in [1, {_MAX_CELL_PX}], got {cell_px!r}")
    channels = meta.get("channels")
    if channels not in CHANNEL_SETS:
        raise InputError(f"channels: expected one of {', '.join(CHANNEL_SETS)}, got {channels!r}")
    step = _number(meta.get("angle_step_deg"), "angle_step_deg", *_ANGLE_STEP_RANGE_DEG)
    gms = meta.get("groups")
    if not isinstance(gms, list) or not gms:
        raise InputError(f"groups: expected a non-empty list of window groups, got {gms!r}")
    groups = tuple(_group_from_file(i, gm, arr, len(CHANNEL_SETS[channels])) for i, gm in enumerate(gms))
    md = meta.get("metadata", {})
    return AerialModel(gsd, cell_px, channels, step, groups, dict(md) if isinstance(md, dict) else {})


def _group_from_file(i: int, gm: object, arr: dict[str, NDArray], n_feat: int) -> AerialGroup:
    """Window group ``i`` of a model file: its classes and names, window cells (two odd
    sizes), finite bias, Platt pair and class sizes, and its arrays present, finite and
    of the shapes the window and the ``n_feat`` features per cell imply."""
    w = f"groups[{i}]"
    if not isinstance(gm, dict):
        raise InputError(f"{w}: expected an object, got {type(gm).__name__}")
    classes, names = _names(gm.get("classes"), f"{w}.classes"), _names(gm.get("names"), f"{w}.names")
    cells = gm.get("cells")
    if (not isinstance(cells, list) or len(cells) != 2
            or not all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= _MAX_WINDOW_CELLS
                       and c % 2 == 1 for c in cells)):
        raise InputError(f"{w}.cells: expected [rows, cols], odd, 1-{_MAX_WINDOW_CELLS}, got {cells!r}")
    platt = gm.get("platt")
    if not isinstance(platt, list) or len(platt) != 2:
        raise InputError(f"{w}.platt: expected [a, b], got {platt!r}")
    dims_in = gm.get("dims")
    if not isinstance(dims_in, dict) or set(dims_in) != set(classes):
        raise InputError(f"{w}.dims: expected the sizes of {', '.join(classes)}, got {dims_in!r}")
    dims = {}
    for c, v in dims_in.items():
        if not isinstance(v, list) or len(v) != 3:
            raise InputError(f"{w}.dims.{c}: expected [length, width, height] m, got {v!r}")
        dims[c] = tuple(_number(x, f"{w}.dims.{c}", 0.01, 1000.0) for x in v)
    n_cls = len(classes)
    want = {"weights": (cells[0], cells[1], n_feat),
            "class_coef": (1, 1) if n_cls == 1 else (n_cls, cells[0] * cells[1] * n_feat), "class_bias": (n_cls,)}
    got = {}
    for key, shape in want.items():
        name = f"g{i}_{key}"
        if name not in arr:
            raise InputError(f"no array {name}")
        a = arr[name]
        if a.dtype.kind not in "fiu" or a.shape != shape:
            raise InputError(f"{name}: expected {shape} numbers, got {a.shape} {a.dtype}")
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name}: holds NaN or infinite values")
        got[key] = a.astype(np.float32)
    return AerialGroup(classes, names, (cells[0], cells[1]), got["weights"], _number(gm.get("bias"), f"{w}.bias"),
                       (_number(platt[0], f"{w}.platt"), _number(platt[1], f"{w}.platt")),
                       got["class_coef"], got["class_bias"], dims)


def _number(v: object, what: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    """``v`` as a float, if it is a finite JSON number in [lo, hi]."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        rng = "" if (lo, hi) == (-math.inf, math.inf) else f" in [{lo:g}, {hi:g}]"
        raise InputError(f"{what}: expected a finite number{rng}, got {v!r}")
    return float(v)


def _names(v: object, what: str) -> tuple[str, ...]:
    """``v`` as a tuple of names, if it is a non-empty JSON list of non-empty strings."""
    if not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v):
        raise InputError(f"{what}: expected a non-empty list of names, got {v!r}")
    return tuple(v)


def _boxes(roi: NDArray[np.bool_], reach: int) -> list[tuple[int, int, int, int]]:
    """Bounding boxes (r0, c0, r1, c1) of the search area's connected parts grown by
    ``reach`` px, overlapping boxes merged."""
    n, _, stats, _ = cv2.connectedComponentsWithStats(roi.astype(np.uint8), connectivity=8)
    H, W = roi.shape
    boxes = [[max(0, int(stats[i, cv2.CC_STAT_TOP]) - reach), max(0, int(stats[i, cv2.CC_STAT_LEFT]) - reach),
              min(H, int(stats[i, cv2.CC_STAT_TOP] + stats[i, cv2.CC_STAT_HEIGHT]) + reach),
              min(W, int(stats[i, cv2.CC_STAT_LEFT] + stats[i, cv2.CC_STAT_WIDTH]) + reach)] for i in range(1, n)]
    merged = True
    while merged:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    boxes.pop(j)
                    merged = True
                    break
            if merged:
                break
    return [tuple(b) for b in boxes]


def _sigmoid(x: NDArray) -> NDArray[np.float64]:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -50, 50)))


def correlate_cells(F: NDArray[np.float32], Wt: NDArray[np.float32]) -> NDArray[np.float32]:
    """Sum over features of each feature plane correlated with its window weights, the
    window centred on each cell (zero outside)."""
    out = np.zeros(F.shape[:2], dtype=np.float32)
    for f in range(F.shape[2]):
        out += cv2.filter2D(F[..., f], cv2.CV_32F, Wt[..., f], borderType=cv2.BORDER_CONSTANT)
    return out


def window_features(F: NDArray, i: int, j: int, cells: tuple[int, int], *, turned: bool = False
                    ) -> NDArray[np.float32] | None:
    """The flattened cell features of the window centred on cell (i, j), ``turned`` half
    round (a vehicle nose to -x seen as nose to +x: unsigned gradient bins are the same
    under a half turn); None when it does not fit in the grid."""
    hr, hc = cells[0] // 2, cells[1] // 2
    if i - hr < 0 or j - hc < 0 or i + hr >= F.shape[0] or j + hc >= F.shape[1]:
        return None
    w = F[i - hr:i + hr + 1, j - hc:j + hc + 1]
    return (w[::-1, ::-1] if turned else w).reshape(-1)


def _corners(d: VehicleDetection, L: float, W: float, gsd: float) -> NDArray[np.float64]:
    """A detection's footprint corners (4, 2) as (row, col) pixels."""
    a = d.heading_rad
    u = np.array([-math.sin(a), math.cos(a)])  # along the vehicle, (row, col): +x is col, up is -row
    v = np.array([-math.cos(a), -math.sin(a)])  # across
    c = np.array([d.row, d.col])
    hl, hw = L / 2.0 / gsd, W / 2.0 / gsd
    return np.array([c + u * hl + v * hw, c - u * hl + v * hw, c - u * hl - v * hw, c + u * hl - v * hw])


def _overlaps(d: VehicleDetection, L: float, W: float, q: VehicleDetection, gsd: float) -> bool:
    """Whether ``d``'s centre falls in the inner 80 % x 70 % of ``q``'s footprint or
    ``q``'s in ``d``'s (a second look at the same vehicle), or they are within 0.8 m."""
    dist = math.hypot(d.row - q.row, d.col - q.col) * gsd
    if dist < 0.8:
        return True
    for a, b, la, wa in ((d, q, q.length_m, q.width_m), (q, d, L, W)):
        ang = b.heading_rad
        dr, dc = a.row - b.row, a.col - b.col
        along = (dc * math.cos(ang) - dr * math.sin(ang)) * gsd
        across = (-dc * math.sin(ang) - dr * math.cos(ang)) * gsd
        if abs(along) <= 0.4 * la and abs(across) <= 0.35 * wa:
            return True
    return False
