"""A scene prepared for whole-scene detection: the ground under an image + depth map, the
objects standing on it (connected, measured, placed in 3D) and chips cut from it at any
class's scale, prepared as training chips are (docs/atr.md "Detection in scenes", steps
1 and 3). :mod:`prism3d.atr.detect` searches it; :mod:`prism3d.atr.verifier` judges its
objects.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from prism3d.atr.bank import depth_relief, prepare_chips
from prism3d.atr.geometry import depth_to_points, normals_from_depth
from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.grids import cell_quantile, nearest_valid
from prism3d.reconstruct.stereo.flatness import ransac_plane
from prism3d.reconstruct.survey.dsm import progressive_ground

__all__ = ["DetectOptions", "SceneChannels", "SceneDetection", "bank_scale", "chip_channel", "class_size", "object_xyz", "project",
           "scene_channels"]

#: Chip light and ambient of the shape channel (atr/chips.py ``ChipSpec`` defaults).
_CANON_LIGHT = np.array((-0.35, -0.55, -1.0)) / np.linalg.norm((-0.35, -0.55, -1.0))
_CHIP_AMBIENT = 0.25


@dataclass(frozen=True)
class DetectOptions:
    """How :func:`detect_scene` searches (why each default: docs/atr.md)."""

    band_ratio: float = 1.25
    """Ratio of consecutive range bands: a candidate's chip is at most 12 % off its size
    (verification then cuts the chip at the candidate's own range)."""
    min_height_mm: float = 400.0
    """Height above the local ground from which a point seeds an object."""
    low_height_mm: float = 150.0
    """Height down to which an object grows from its seeds (wheels, tracks, skids)."""
    ground_cell_mm: float = 2000.0
    """Cell of the local ground estimate."""
    min_score: float = 0.05
    """Lowest local PCE of a range-band peak kept as a candidate (band scan only; verified
    detections are all kept, so the scoring can sweep the threshold)."""
    max_detections: int = 100
    """Most detections per image (best first)."""
    nms_fraction: float = 0.5
    """Non-maximum suppression radius, as a fraction of the chip's width at the detection."""
    depth_smooth_px: int = 5
    """Median filter (px) of the depth before normals and ranges."""
    verify: bool = True
    """Score the best candidates again as training chips are scored (chip-level metric)."""
    verify_top: int = 200
    """Candidates verified per image (the rest are dropped)."""
    band_scan: bool = False
    """3D channels: also slide every filter over range bands for candidates, besides each
    object's centroid. Off: on 20 field scenes it added 0.00 Pd at 0.1 FPPI and 0.01 at
    1 FPPI for twice the time, since detections are placed on their objects anyway. The
    intensity channel (no objects) and ``verify=False`` always scan."""

    def __post_init__(self) -> None:
        if not (1.01 <= self.band_ratio <= 2.0):
            raise InputError(f"band_ratio: expected a value in [1.01, 2], got {self.band_ratio}")
        for name in ("min_height_mm", "low_height_mm", "ground_cell_mm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{name}: expected a positive length, got {v}")
        if not 0 < self.nms_fraction <= 2:
            raise InputError(f"nms_fraction: expected a value in (0, 2], got {self.nms_fraction}")
        if int(self.max_detections) != self.max_detections or self.max_detections < 1:
            raise InputError(f"max_detections: expected a positive integer, got {self.max_detections}")


@dataclass(frozen=True)
class SceneDetection:
    """One detection in a scene, best-first lists of which :func:`detect_scene` returns and
    ``detections.json`` holds (:meth:`to_json`; the class under the key ``class``)."""

    row: float
    """Pixel row of the detection (the object's median point where there is one)."""
    col: float
    """Pixel column."""
    class_name: str
    """The class it is called."""
    score: float
    """Higher is surer: a filter's peak metric, or a recogniser's 1 - P(none)."""
    aspect_deg: float = math.nan
    """Azimuth of the filter that matched (NaN from a recogniser)."""
    range_mm: float | None = None
    """Depth at the detection, mm."""
    xyz_mm: tuple[float, float, float] | None = None
    """Its 3D point in the camera frame, mm (None: no depth there)."""
    p_classes: dict[str, float] | None = None
    """A recogniser's probability of each class (and of none)."""

    def to_json(self) -> dict[str, Any]:
        """The record as ``detections.json`` holds it."""
        doc: dict[str, Any] = {"row": self.row, "col": self.col, "class": self.class_name,
                               "aspect_deg": self.aspect_deg, "score": self.score, "range_mm": self.range_mm,
                               "xyz_mm": None if self.xyz_mm is None else list(self.xyz_mm)}
        if self.p_classes is not None:
            doc["p_classes"] = dict(self.p_classes)
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> SceneDetection:
        """A record of ``detections.json`` (:meth:`to_json`)."""
        try:
            xyz = doc.get("xyz_mm")
            return cls(float(doc["row"]), float(doc["col"]), str(doc["class"]), float(doc["score"]),
                       float(doc.get("aspect_deg", math.nan)), doc.get("range_mm"),
                       None if xyz is None else (float(xyz[0]), float(xyz[1]), float(xyz[2])), doc.get("p_classes"))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"detection: malformed record {doc!r} ({exc})") from None


@dataclass(eq=False)
class SceneChannels:
    """A scene prepared for detection: ``grey`` (H, W) [0, 1], ``depth_mm`` (H, W) NaN =
    none, ``K`` (3, 3), ``range_mm`` (H, W) smoothed and filled depth (NaN where nothing
    is near), ``height_mm`` above the local ground, ``figure`` mask, ``labels`` (objects,
    0 = none), per label ``object_xyz_mm`` (median 3D point, camera frame; its z is
    ``object_depth_mm``), ``object_dims_mm`` (length, width, height: the smallest
    footprint rectangle of its points and its 98th height percentile) and ``object_rc``
    (pixel centroid), ``up`` (the ground's normal, camera frame),
    ``smooth_depth_mm`` (the median-filtered depth; ``normals`` are computed from it on
    first use)."""

    grey: NDArray[np.float32]
    depth_mm: NDArray[np.float32]
    K: NDArray[np.float64]
    range_mm: NDArray[np.float32]
    height_mm: NDArray[np.float32]
    figure: NDArray[np.bool_]
    labels: NDArray[np.int32]
    object_xyz_mm: NDArray[np.float64]
    up: NDArray[np.float64]
    object_dims_mm: NDArray[np.float64]
    object_rc: NDArray[np.float64]
    smooth_depth_mm: NDArray[np.float32] | None = None
    object_npx: NDArray[np.int64] | None = None
    """Pixels per label (0: the background)."""
    _normals: NDArray[np.float32] | None = None
    _object_depth: NDArray[np.float32] | None = None

    @property
    def object_depth_mm(self) -> NDArray[np.float64]:
        """Each object's median depth (its median point's z; 0 for the background)."""
        return np.nan_to_num(self.object_xyz_mm[:, 2], nan=0.0)

    @property
    def normals(self) -> NDArray[np.float32]:
        """Camera-frame unit normals (H, W, 3) of the smoothed depth (computed once)."""
        if self._normals is None:
            self._normals = normals_from_depth(self.smooth_depth_mm, self.K)
        return self._normals

    def object_depth(self) -> NDArray[np.float32]:
        """(H, W, 2) float32: depth in metres on objects (0 elsewhere), the object mask (once)."""
        if self._object_depth is None:
            d = np.where(self.figure, np.nan_to_num(self.depth_mm, nan=0.0) * 1e-3, 0.0)
            m = self.figure & np.isfinite(self.depth_mm)
            self._object_depth = np.stack([d, m], axis=-1).astype(np.float32)
        return self._object_depth

    def channel(self, name: str, half_depth_mm: float | None = None) -> NDArray[np.float32]:
        """The scene in a bank channel's units (module docstring); ``depth`` needs the
        chip's half width at the target, mm (the relief slab's half depth)."""
        if name == "intensity":
            return self.grey
        if name == "shape":
            n = np.nan_to_num(self.normals.astype(np.float64))
            s = _CHIP_AMBIENT + (1 - _CHIP_AMBIENT) * np.clip(n @ _CANON_LIGHT, 0.0, None)
            return np.where(self.figure, s, 0.0).astype(np.float32)
        if name == "depth":
            if half_depth_mm is None:
                raise InputError("depth channel: the relief needs the chip's half width (mm)")
            zc = self.object_depth_mm[self.labels]
            rel = (zc + half_depth_mm - self.depth_mm) / (2.0 * half_depth_mm)
            rel = np.where(self.figure & np.isfinite(rel), np.clip(rel, 0.0, 1.0), 0.0)
            return rel.astype(np.float32)
        raise InputError(f"channel: expected intensity, depth or shape, got {name!r}")


def _ground_plane(P: NDArray, valid: NDArray, rng: np.random.Generator) -> tuple[NDArray, float]:
    """Dominant plane ``(n, d)`` (n . p + d = height, camera above: d > 0) by RANSAC on
    a sample, tolerance growing with depth (stereo error grows as Z^2)."""
    pts = P[valid]
    if len(pts) < 100:
        raise InputError("scene: fewer than 100 pixels with depth; nothing to find a ground in")
    sample = pts[rng.choice(len(pts), size=min(len(pts), 20000), replace=False)]
    z = sample[:, 2]
    tol = 150.0 + 2e-6 * z * z
    # the ground is below the camera: its normal has a -y (up) part
    n, d, count = ransac_plane(sample, tol, rng, accept=lambda n: abs(n[1]) >= 0.3)
    if n is None or count < 0.2 * len(sample):
        raise InputError("scene: no ground plane found under the camera (is this a ground-level view?)")
    return n, d


def _smooth_depth(d: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    """``d`` median-filtered over ``size`` px (made odd; 1: unchanged) among its valid pixels
    (NaN stays NaN); where the median moves a depth by more than 5 %, the depth is kept."""
    ds = d.copy()
    k = int(size) | 1
    if k > 1:  # median of the valid neighbours: a NaN-aware smoothing by filling then masking
        fill = np.where(np.isfinite(d), d, 0).astype(np.float32)
        ds = cv2.medianBlur(fill, min(k, 5)) if k <= 5 else ndimage.median_filter(fill, size=k)
        ds = np.where(np.isfinite(d), ds, np.nan).astype(np.float32)
        ds = np.where(np.abs(ds - d) > 0.05 * np.nan_to_num(d, nan=1.0), d, ds)
    return ds


def _cell_low(height: NDArray, flat: NDArray, valid: NDArray, n_cells: int) -> NDArray[np.float64]:
    """The 10th-percentile height of each ground cell (``flat``: each pixel's cell index; inf
    where no valid pixel of a cell is sampled), the raw input of the local ground."""
    # the 10th percentile per cell: the value at 10 % of each cell's heights sorted (every
    # other pixel each way: a 2 m cell holds plenty, and the sort is 4x shorter)
    sub = np.zeros_like(valid)
    sub[::2, ::2] = True
    sub &= valid
    return cell_quantile(height[sub], flat[sub], n_cells, 0.1, empty=np.inf, of_count=True)


def scene_channels(grey: NDArray, depth_mm: NDArray, K: NDArray, options: DetectOptions | None = None,
                   *, seed: int = 0) -> SceneChannels:
    """Ground, figure objects, ranges and normals of an image + depth map (module docstring)."""
    o = DetectOptions() if options is None else options
    g = check_array(grey, "image", ndim=2).astype(np.float32)
    d = check_array(depth_mm, "depth", ndim=2).astype(np.float32)
    if g.shape != d.shape:
        raise InputError(f"depth: {d.shape[1]}x{d.shape[0]} px, the image is {g.shape[1]}x{g.shape[0]}; "
                         "give a depth map of the image's size")
    K = check_array(K, "K", shape=(3, 3)).astype(np.float64)
    if g.max(initial=0) > 1.0:
        g = g / 255.0
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32)
    fin = np.isfinite(d)
    if fin.sum() >= 100:  # sky and points at near-zero disparity: no ground, no object there
        far = FAR_RATIO * float(np.median(d[fin]))
        d[fin & (d > far)] = np.nan
    ds = _smooth_depth(d, o.depth_smooth_px)
    valid = np.isfinite(ds)
    P = depth_to_points(ds, K)
    n, dd = _ground_plane(P, valid, np.random.default_rng(seed))
    height = np.where(valid, P @ n + dd, np.nan)
    # local ground: low percentile per cell of the plane, opened over the window
    e1 = np.cross(n, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    a = np.where(valid, P @ e1, 0.0)
    b = np.where(valid, P @ e2, 0.0)
    cell = o.ground_cell_mm
    ia = np.floor((a - a[valid].min()) / cell).astype(np.int64)
    ib = np.floor((b - b[valid].min()) / cell).astype(np.int64)
    na, nb = int(ia[valid].max()) + 1, int(ib[valid].max()) + 1
    if na * nb > 4_000_000:
        raise InputError(f"scene: spans {na * cell / 1000:.0f} x {nb * cell / 1000:.0f} m; "
                         "too large for a ground grid (is the depth in mm?)")
    flat = ia * nb + ib
    low = _cell_low(height, flat, valid, na * nb)
    ground_grid = progressive_ground(low.reshape(na, nb), cell)
    ground = ground_grid.reshape(-1)[flat]
    hag = np.where(valid, height - ground, np.nan).astype(np.float32)
    # hysteresis: objects are seeded where they stand min_height_mm high and grow down to
    # low_height_mm, so wheels and tracks stay on the vehicle (training chips have them)
    # (a short way: GROW_MM at the objects' typical depth, not along the whole ground)
    hh = np.nan_to_num(hag, nan=0.0)
    seed = ndimage.binary_opening(hh > o.min_height_mm, iterations=1)
    zs = ds[seed & valid]
    steps = int(np.clip(round(GROW_MM * K[1, 1] / float(np.median(zs))), 1, 40)) if zs.size else 1
    figure = ndimage.binary_dilation(seed, iterations=steps, mask=hh > o.low_height_mm) | seed
    # objects one behind the other touch in the image: cut them apart at depth steps
    labels, nlab = ndimage.label(figure & ~_depth_steps(ds), structure=np.ones((3, 3)))
    dims, xyz, centres = _object_dims(labels, nlab, valid & figure, a, b, hag, P)
    rng_map = _fill_nearest(ds)
    npx = np.bincount(labels.ravel(), minlength=nlab + 1).astype(np.int64)
    return SceneChannels(g, d, K, rng_map, hag, figure, labels.astype(np.int32), xyz, n, dims, centres, ds, npx)


#: Depths beyond this many times the scene's median depth are dropped before the ground is
#: found: a stereo pair's sky and textureless distance come back kilometres away (KITTI: up
#: to 14 km, against a median of 15 m), where nothing can be measured or recognised.
FAR_RATIO = 25.0
#: A depth step between neighbouring pixels larger than this share of the depth (and
#: than DEPTH_STEP_MM) separates two objects.
DEPTH_STEP_RATIO = 0.02
DEPTH_STEP_MM = 800.0


def _depth_steps(d: NDArray) -> NDArray[np.bool_]:
    """Pixels on the near or far side of a depth discontinuity (either axis)."""
    z = np.nan_to_num(d, nan=0.0)
    lim = np.maximum(DEPTH_STEP_RATIO * z, DEPTH_STEP_MM)
    out = np.zeros(d.shape, dtype=bool)
    dx = np.abs(np.diff(z, axis=1)) > np.minimum(lim[:, 1:], lim[:, :-1])
    dy = np.abs(np.diff(z, axis=0)) > np.minimum(lim[1:], lim[:-1])
    out[:, 1:] |= dx
    out[:, :-1] |= dx
    out[1:] |= dy
    out[:-1] |= dy
    return out & np.isfinite(d)


#: How far below its seeds an object may grow (wheels, tracks, skids), mm.
GROW_MM = 600.0


def _object_dims(labels: NDArray, nlab: int, sel: NDArray, a: NDArray, b: NDArray, hag: NDArray,
                 P: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per object, in one pass over its points (sorted by label once): ``(nlab + 1, 3)``
    length, width (smallest rectangle around the footprint, 1-99 % of the points) and
    height (98th percentile above the ground), mm; ``(nlab + 1, 3)`` its median 3D point
    (camera frame, NaN for an object without points); ``(nlab + 1, 2)`` its pixel centroid."""
    out = np.zeros((nlab + 1, 3))
    xyz = np.full((nlab + 1, 3), np.nan)
    rc = np.zeros((nlab + 1, 2))
    if not nlab:
        return out, xyz, rc
    rows, cols = np.nonzero(sel)
    lv = labels[rows, cols]
    order = np.argsort(lv, kind="stable")
    lv, rows, cols = lv[order], rows[order], cols[order]
    pa, pb, ph, pp = a[rows, cols], b[rows, cols], hag[rows, cols], P[rows, cols]
    bounds = np.searchsorted(lv, np.arange(1, nlab + 2))
    for k in range(nlab):
        s0, s1 = bounds[k], bounds[k + 1]
        if s1 > s0:
            xyz[k + 1] = np.median(pp[s0:s1], axis=0)
            rc[k + 1] = rows[s0:s1].mean(), cols[s0:s1].mean()
        if s1 - s0 < 5:
            continue
        xy = np.stack([pa[s0:s1], pb[s0:s1]], axis=1)
        if len(xy) > 4000:
            xy = xy[:: len(xy) // 4000 + 1]
        c = np.median(xy, axis=0)
        rad = np.linalg.norm(xy - c, axis=1)
        xy = xy[rad <= np.percentile(rad, 99)]
        (_, _), (w, h), _ = cv2.minAreaRect(xy.astype(np.float32))
        out[k + 1] = (max(w, h), min(w, h), float(np.percentile(ph[s0:s1], 98)))
    return out, xyz, rc


def _fill_nearest(d: NDArray, step: int = 4) -> NDArray[np.float32]:
    """Depth with holes filled from the nearest valid pixel (the range of a window centred
    on a hole), found on a grid ``step`` px apart (a range sets a filter's scale; it need
    not be exact); valid pixels keep their own depth; far from any depth (> 64 px) NaN."""
    bad = ~np.isfinite(d)
    if not bad.any():
        return d.astype(np.float32)
    small = d[::step, ::step]
    sbad = ~np.isfinite(small)
    dist, (ri, ci) = nearest_valid(sbad)
    filled = small[ri, ci]
    filled[dist * step > 64] = np.nan
    up = np.repeat(np.repeat(filled, step, axis=0), step, axis=1)[: d.shape[0], : d.shape[1]]
    return np.where(bad, up, d).astype(np.float32)


def bank_scale(bank: Any) -> dict[str, float]:
    """Chip pixels per mm at a full-size target, per class (the bank's records)."""
    meta = bank.metadata
    ppm = meta.get("chip_px_per_mm")
    if not isinstance(ppm, dict) or set(ppm) < set(bank.classes):
        raise InputError("bank: it does not record its chips' scale (chip_px_per_mm); "
                         "train it again with this prism3d (bank train) to detect in scenes")
    full = meta.get("class_full_scale", {})
    return {c: float(ppm[c]) * float(full.get(c, 1.0)) for c in bank.classes}



def class_size(meta: dict, key: str, classes: Sequence[str]) -> dict[str, Any]:
    """A per-class size the bank records (``class_extent_mm``: x, y, z; ``class_radius_mm``)
    at full size (divided by the class's ``class_full_scale``); classes without it absent."""
    full = meta.get("class_full_scale", {})
    vals = meta.get(key) or {}
    return {c: np.asarray(vals[c], dtype=np.float64) / float(full.get(c, 1.0) or 1.0)
            for c in classes if c in vals}



def _chip_at(img: NDArray[np.float32], r: float, c: float, s: float, S: int) -> NDArray[np.float32]:
    """The S x S chip centred at scene pixel (r, c) at resampling factor ``s`` (chip px
    per scene px): the part inside the scene area-averaged to chip scale (to half a chip
    pixel), zero outside; an (H, W, k) image gives an (S, S, k) chip."""
    half = 0.5 * S / s
    H, W = img.shape[:2]
    a0, a1 = max(int(math.floor(r - half)), 0), min(int(math.ceil(r + half)), H)
    b0, b1 = max(int(math.floor(c - half)), 0), min(int(math.ceil(c + half)), W)
    chip = np.zeros((S, S) + img.shape[2:], dtype=np.float32)
    if a1 <= a0 or b1 <= b0:
        return chip
    hs, ws = max(1, int(round((a1 - a0) * s))), max(1, int(round((b1 - b0) * s)))
    part = cv2.resize(img[a0:a1, b0:b1], (ws, hs), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    part = part.reshape((hs, ws) + img.shape[2:])
    i0 = int(round((a0 - (r - half)) * s))
    j0 = int(round((b0 - (c - half)) * s))
    d0, d1 = max(i0, 0), min(S, i0 + hs)
    e0, e1 = max(j0, 0), min(S, j0 + ws)
    if d1 > d0 and e1 > e0:
        chip[d0:d1, e0:e1] = part[d0 - i0 : d1 - i0, e0 - j0 : e1 - j0]
    return chip


def _depth_chip_at(scene: SceneChannels, r: float, c: float, s: float, S: int) -> NDArray[np.float32]:
    """Object depth (mm; NaN off the objects) as an S x S chip at chip scale: depth and
    object share area-averaged separately, depth kept where objects cover half a pixel."""
    dm = scene.object_depth()  # depth (m: float32 sums stay exact enough) and share, one resize
    both = _chip_at(dm, r, c, s, S)
    num, den = both[..., 0], both[..., 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den > 0.5, 1e3 * num / den, np.nan)
    return out.astype(np.float32)


def chip_channel(bank: Any, scene: SceneChannels, r: float, c: float, s: float, f: float) -> NDArray:
    """A candidate's chip in the bank's channel, prepared as the training chips were: depth
    relief about the chip centre's median depth (``depth_relief``), or the shading of the
    chip-scale depth's normals under the chip light (``shape``), or the grey image; objects
    outside the chip's depth slab (in front of or behind the target) are background."""
    S = int(bank.size)
    if bank.channel == "intensity":
        return prepare_chips(_chip_at(scene.grey, r, c, s, S)[None], "intensity",
                             intensity_prep=bank.intensity_prep)
    dz = _depth_chip_at(scene, r, c, s, S)
    fx = f * s
    rel = depth_relief(dz[None], fx)[0]
    q0, q1 = S // 2 - S // 8, S // 2 + S // 8 + 1
    cen = dz[q0:q1, q0:q1]
    fin = cen[np.isfinite(cen)]
    if fin.size == 0:
        fin = dz[np.isfinite(dz)]
    if fin.size == 0:
        return prepare_chips(np.zeros((1, S, S)), "shape")
    zc = float(np.median(fin))
    half = (S / 2.0) * zc / fx
    inside = np.isfinite(dz) & (np.abs(dz - zc) <= half)
    if bank.channel == "depth":
        x = np.where(inside, rel, 0.0)
    else:
        K = np.array([[fx, 0, (S - 1) / 2.0], [0, fx, (S - 1) / 2.0], [0, 0, 1.0]])
        n = np.nan_to_num(normals_from_depth(np.where(inside, dz, np.nan), K).astype(np.float64))
        x = np.where(inside, _CHIP_AMBIENT + (1 - _CHIP_AMBIENT) * np.clip(n @ _CANON_LIGHT, 0.0, None), 0.0)
    return prepare_chips(x[None], "shape")  # zero mean, unit energy



def project(K: NDArray, p: NDArray) -> tuple[float, float]:
    """Pixel (row, col) of a camera-frame point."""
    u = K @ p
    return float(u[1] / u[2]), float(u[0] / u[2])


def object_xyz(scene: SceneChannels, r: int, c: int) -> list[float] | None:
    """The 3D point of a detection: its object's median depth when it sits on one, else
    the filled range, along the pixel's ray (scene camera frame, mm)."""
    lab = int(scene.labels[r, c])
    z = float(scene.object_depth_mm[lab]) if lab else float(scene.range_mm[r, c])
    if not math.isfinite(z):
        return None
    K = scene.K
    y = (r - K[1, 2]) / K[1, 1]
    x = (c - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return [x * z, y * z, z]


