"""Whole-scene detection: a filter bank slid over a shot (or an image + depth map), each
class's filters scaled by the range at every pixel, so one bank serves all ranges.

Method (docs/atr.md "Detection in scenes"):

1. Ground: a plane fitted to the scene's points (RANSAC), then the local ground under
   every point (low percentile per 2 m cell, a progressive morphological filter); a
   pixel is *figure* where it stands ``min_height_mm`` above it, grown down to
   ``low_height_mm`` (hysteresis).
   Figure pixels group into connected objects.
2. Channel images in the bank's units: ``depth`` -> each object's relief about its median
   depth, exactly as a training chip's (background 0); ``shape`` -> the shading of the
   depth map's normals under the canonical chip light on figure pixels (the camouflage's
   paint is gone); ``intensity`` -> the grey image itself (2D only: no help from depth).
3. Candidates: for 3D channels every object's centroid (``band_scan`` adds range-band
   peaks); for intensity, range bands (ratio ``band_ratio``): in band ``Z`` each class's
   channel image is resampled so a target at ``Z`` has its training chip's size (the
   bank records chip pixels per mm per class) and correlated with every filter of the
   class, scored by the local PCE.
4. Verification: at each candidate, a chip at each size-fitting class's scale prepared as
   training chips are, scored by the bank's metric over all the class's filters.
5. Suppression: best first, one detection per object, none within a found target's 3D
   radius; 3D detections are placed at their object's median 3D point.

Every detection has its pixel, its 3D point, class, aspect (the winning filter's
azimuth bin), ``score`` (the bank's chip metric, PCE by default) and ``range_mm``.
Every verified candidate is kept (scoring sweeps the threshold over them).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.reconstruct.dsm import progressive_ground
from prism3d.reconstruct.flatness import ransac_plane

__all__ = [
    "DetectOptions", "SceneChannels", "bank_scale", "detect_scene", "detect_scene_hog", "detect_shot",
    "detect_to_file", "scene_channels",
]

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
            from prism3d.atr.geometry import normals_from_depth

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


def scene_channels(grey: NDArray, depth_mm: NDArray, K: NDArray, options: DetectOptions | None = None,
                   *, seed: int = 0) -> SceneChannels:
    """Ground, figure objects, ranges and normals of an image + depth map (module docstring)."""
    import cv2
    from scipy import ndimage

    from prism3d.atr.geometry import depth_to_points

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
    ds = d.copy()
    k = int(o.depth_smooth_px) | 1
    if k > 1:  # median of the valid neighbours: a NaN-aware smoothing by filling then masking
        fill = np.where(np.isfinite(d), d, 0).astype(np.float32)
        ds = cv2.medianBlur(fill, min(k, 5)) if k <= 5 else ndimage.median_filter(fill, size=k)
        ds = np.where(np.isfinite(d), ds, np.nan).astype(np.float32)
        ds = np.where(np.abs(ds - d) > 0.05 * np.nan_to_num(d, nan=1.0), d, ds)
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
    low = np.full(na * nb, np.inf)
    # the 10th percentile per cell: the value at 10 % of each cell's heights sorted (every
    # other pixel each way: a 2 m cell holds plenty, and the sort is 4x shorter)
    sub = np.zeros_like(valid)
    sub[::2, ::2] = True
    sub &= valid
    hv, fv = height[sub], flat[sub]
    order = np.lexsort((hv, fv))  # by cell, then height
    hv, fv = hv[order], fv[order]
    first = np.flatnonzero(np.r_[True, fv[1:] != fv[:-1]])
    counts = np.diff(np.r_[first, len(fv)])
    low[fv[first]] = hv[first + counts // 10]
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
    return SceneChannels(g, d, K, rng_map, hag, figure, labels.astype(np.int32), xyz, n, dims, centres, ds)


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
    import cv2

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
    from scipy import ndimage

    bad = ~np.isfinite(d)
    if not bad.any():
        return d.astype(np.float32)
    small = d[::step, ::step]
    sbad = ~np.isfinite(small)
    dist, (ri, ci) = ndimage.distance_transform_edt(sbad, return_indices=True)
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


def _peaks(score: NDArray, size: int) -> tuple[NDArray, NDArray]:
    from scipy import ndimage

    mx = ndimage.maximum_filter(score, size=size, mode="constant", cval=-np.inf)
    r, c = np.nonzero((score == mx) & np.isfinite(score))
    return r, c


#: A window whose values vary less than this (std, channel units) holds nothing to match.
_MIN_WINDOW_STD = 0.02


def _correlate(img: NDArray[np.float32], spat: NDArray[np.float32], ks: NDArray, S: int
               ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
    """Best local peak-to-correlation energy over filters ``ks`` at every pixel of ``img``
    (zero outside) and the winning filter. The local PCE at ``p`` is ``c(p)^2`` over the
    mean of ``c^2`` in the S x S window about ``p`` (signed: negative peaks score < 0), the
    chip-level PCE of a chip centred at ``p``; flat windows (nothing to match) are -inf."""
    import cv2

    h, w = img.shape
    pad = S // 2
    big = cv2.copyMakeBorder(img, pad, S - pad - 1, pad, S - pad - 1, cv2.BORDER_CONSTANT, value=0)
    m = cv2.boxFilter(big, cv2.CV_32F, (S, S), anchor=(0, 0), normalize=True, borderType=cv2.BORDER_CONSTANT)
    m2 = cv2.boxFilter(big * big, cv2.CV_32F, (S, S), anchor=(0, 0), normalize=True, borderType=cv2.BORDER_CONSTANT)
    flat = (m2 - m * m)[:h, :w] < _MIN_WINDOW_STD**2
    best = np.full((h, w), -np.inf, dtype=np.float32)
    arg = np.zeros((h, w), dtype=np.int32)
    for k in ks:
        c = cv2.matchTemplate(big, spat[k], cv2.TM_CCORR)[:h, :w]
        e = cv2.boxFilter(c * c, cv2.CV_32F, (S, S), normalize=True, borderType=cv2.BORDER_CONSTANT)
        r = c * np.abs(c) / np.maximum(e, 1e-30)
        upd = r > best
        best[upd] = r[upd]
        arg[upd] = k
    best[flat | ~np.isfinite(best)] = -np.inf
    return best, arg


def _band_scan(scene: SceneChannels, classes: Sequence[str], ppm: dict[str, float], S: int,
               images: dict[str, NDArray], need_figure: bool, o: DetectOptions,
               score_fn: Any) -> list[tuple[float, float, float, int, int]]:
    """Slide over range bands: for each class and band, the class's channel image around
    the band's pixels resampled to chip scale at the band's range, scored by
    ``score_fn(class_index, small) -> (score (h, w) per window centre, winner (h, w))``;
    peaks whose pixel's range is in the band become ``(score, row, col, winner, class)``."""
    import cv2

    f = float(scene.K[0, 0])
    rmap = scene.range_mm
    fin = np.isfinite(rmap)
    if not fin.any():
        return []
    zlo, zhi = float(np.nanmin(rmap)), float(np.nanmax(rmap))
    nb = max(1, int(math.ceil(math.log(zhi / zlo) / math.log(o.band_ratio))))
    edges = zlo * o.band_ratio ** np.arange(nb + 1)
    H, W = rmap.shape
    band_of = np.full(rmap.shape, -1, dtype=np.int32)
    band_of[fin] = np.clip(np.floor(np.log(rmap[fin] / zlo) / math.log(o.band_ratio)), 0, nb - 1).astype(np.int32)
    where = band_of if not need_figure else np.where(scene.figure, band_of, -1)
    boxes = {}
    for b in range(nb):  # each band's pixel rows and columns, once
        sel = where == b
        rows_any, cols_any = np.flatnonzero(sel.any(axis=1)), np.flatnonzero(sel.any(axis=0))
        if len(rows_any):
            boxes[b] = (rows_any[0], rows_any[-1], cols_any[0], cols_any[-1])
    cands: list[tuple[float, float, float, int, int]] = []
    for ci, cls in enumerate(classes):
        img = images[cls]
        for b, (ra, rb, ca, cb) in boxes.items():
            z = math.sqrt(edges[b] * edges[b + 1])
            s = ppm[cls] * z / f  # resampling factor: scene px -> chip px at this range
            reach = int(math.ceil(S / s))  # a chip's width in scene pixels
            if reach > max(H, W):  # a target of this class this near cannot be in view
                continue
            r0, r1 = max(0, ra - reach), min(H, rb + reach + 1)
            c0, c1 = max(0, ca - reach), min(W, cb + reach + 1)
            crop = img[r0:r1, c0:c1]
            hs, ws = max(1, int(round(crop.shape[0] * s))), max(1, int(round(crop.shape[1] * s)))
            sx, sy = ws / crop.shape[1], hs / crop.shape[0]
            small = cv2.resize(crop, (ws, hs), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
            best, arg = score_fn(ci, small.astype(np.float32))
            # window centred at small pixel (i, j) <-> scene pixel (r0 + (i + .5) / sy - .5, ...)
            rows = np.clip((r0 + (np.arange(hs) + 0.5) / sy - 0.5).round().astype(int), 0, H - 1)
            cols = np.clip((c0 + (np.arange(ws) + 0.5) / sx - 0.5).round().astype(int), 0, W - 1)
            best[(band_of[np.ix_(rows, cols)] != b)] = -np.inf
            best[best < o.min_score] = -np.inf
            pr, pc = _peaks(best, max(3, S // 4))
            for i, j in zip(pr, pc):
                cands.append((float(best[i, j]), r0 + (i + 0.5) / sy - 0.5, c0 + (j + 0.5) / sx - 0.5,
                              int(arg[i, j]), ci))
    return cands


def _full_size(meta: dict, key: str, classes: Sequence[str]) -> dict[str, Any]:
    """A per-class size the bank records (``class_extent_mm``: x, y, z; ``class_radius_mm``)
    at full size (divided by the class's ``class_full_scale``); classes without it absent."""
    full = meta.get("class_full_scale", {})
    vals = meta.get(key) or {}
    return {c: np.asarray(vals[c], dtype=np.float64) / float(full.get(c, 1.0) or 1.0)
            for c in classes if c in vals}


def _finish(cands: list, scene: SceneChannels, classes: Sequence[str], ppm: dict[str, float], S: int,
            extent: dict, gate: bool, o: DetectOptions, aspect: Any, radius: dict[str, float]) -> list[dict]:
    """Greedy non-maximum suppression (half a chip, at the smaller of two detections'
    scales), the 3D size gate, one detection per object placed at the object's median
    point, none within a found target's radius (``radius``: class -> mm, full size; the
    smaller of the two classes'), and the detection records, best first."""
    f = float(scene.K[0, 0])
    H, W = scene.range_mm.shape
    cands = sorted(cands, key=lambda t: -t[0])
    out: list[dict] = []
    kept: list[tuple[float, float, float]] = []
    kept_xyz: list[tuple[NDArray, float]] = []
    taken: set[int] = set()
    for score, r, c, k, ci in cands:
        ri, cj = int(round(min(max(r, 0), H - 1))), int(round(min(max(c, 0), W - 1)))
        z = float(scene.range_mm[ri, cj])
        if not math.isfinite(z):
            continue
        sc = ppm[classes[ci]] * z / f
        rad = o.nms_fraction * (S / 2.0) / sc
        if any(math.hypot(r - a, c - b2) < min(rad, rr) for a, b2, rr in kept):
            continue
        xyz = _xyz(scene, ri, cj)
        if gate:
            lab = _object_under(scene, ri, cj, NEAR_CHIP_PX / sc)
            if lab in taken or not _size_fits(scene, ri, cj, extent.get(classes[ci]), NEAR_CHIP_PX / sc):
                continue  # one detection per object; and the object must fit the class
            if np.isfinite(scene.object_xyz_mm[lab]).all():
                # the object, not the window, locates the target (a window peak may sit
                # on its shadow or beside it)
                p = scene.object_xyz_mm[lab]
                rad3 = float(radius[classes[ci]]) if classes[ci] in radius else None
                if rad3 and any(np.linalg.norm(p - q) < min(rad3, rq) for q, rq in kept_xyz):
                    continue  # a part of a target already found (objects split at depth steps)
                kept_xyz.append((p, rad3 or 0.0))
                xyz = [float(v) for v in p]
                r, c = _project(scene.K, p)
            taken.add(lab)
        kept.append((r, c, rad))
        out.append({"row": float(r), "col": float(c), "class": classes[ci],
                    "aspect_deg": aspect(k), "score": float(score),
                    "range_mm": z, "xyz_mm": xyz})
        if len(out) >= o.max_detections:
            break
    return out


def detect_scene(bank: Any, scene: SceneChannels, options: DetectOptions | None = None) -> list[dict]:
    """Detections of ``bank`` in a prepared scene, best first (module docstring): dicts
    with ``row``, ``col`` (pixels of the scene grid), ``class``, ``aspect_deg``,
    ``score``, ``range_mm``, ``xyz_mm`` (scene camera frame; None without depth there)."""
    import cv2

    from prism3d.atr.bank import GRADIENT_SIGMA_PX

    o = DetectOptions() if options is None else options
    ppm = bank_scale(bank)
    S = int(bank.size)
    spat = np.fft.ifft2(bank.freqs, axes=(-2, -1)).real.astype(np.float32)
    f = float(scene.K[0, 0])
    need_figure = bank.channel != "intensity"  # 3D channels are 0 off the objects
    filters = [np.flatnonzero(bank.filter_class == ci) for ci in range(len(bank.classes))]

    def score_fn(ci: int, small: NDArray[np.float32]) -> tuple[NDArray, NDArray]:
        if bank.channel == "intensity" and bank.intensity_prep == "gradient":
            gx = cv2.GaussianBlur(cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=1), (0, 0), GRADIENT_SIGMA_PX)
            gy = cv2.GaussianBlur(cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=1), (0, 0), GRADIENT_SIGMA_PX)
            small = np.hypot(gx, gy)
        return _correlate(small, spat, filters[ci], S)

    cands: list = []
    if not need_figure or o.band_scan or not o.verify:
        shared = None if bank.channel == "depth" else scene.channel(bank.channel)
        images = {c: shared if shared is not None else scene.channel("depth", half_depth_mm=(S / 2.0) / ppm[c])
                  for c in bank.classes}
        cands = _band_scan(scene, bank.classes, ppm, S, images, need_figure, o, score_fn)
    extent = _full_size(bank.metadata, "class_extent_mm", bank.classes)
    cands.sort(key=lambda t: -t[0])
    cands = cands[: o.verify_top]
    if need_figure:  # every object the 3D found is a candidate too, at its centroid
        cands = [(np.inf, float(r), float(c), 0, 0) for r, c in scene.object_rc[1:]] + cands
    if o.verify and cands:
        cands = _verify(bank, scene, cands, ppm, f, extent)
    return _finish(cands, scene, bank.classes, ppm, S, extent, need_figure, o,
                   lambda k: float(bank.filter_az_deg[k]), _full_size(bank.metadata, "class_radius_mm", bank.classes))


def detect_scene_hog(model: Any, scene: SceneChannels, options: DetectOptions | None = None) -> list[dict]:
    """The HOG + linear SVM baseline (:class:`~prism3d.atr.hog_svm.HogSvm`) slid over the
    same range bands, channel images, 3D gates and suppression as :func:`detect_scene`;
    the score is the SVM's decision value (aspect unknown: NaN)."""
    o = DetectOptions() if options is None else options
    ppm = bank_scale(model)
    S = int(model.size)
    need_figure = model.channel != "intensity"
    shared = None if model.channel == "depth" else scene.channel(model.channel)
    images = {c: shared if shared is not None else scene.channel("depth", half_depth_mm=(S / 2.0) / ppm[c])
              for c in model.classes}
    def score_fn(ci: int, small: NDArray[np.float32]) -> tuple[NDArray, NDArray]:
        sc, r0, c0, stride = model.dense_scores(small)
        best = np.full(small.shape, -np.inf, dtype=np.float32)
        if sc.size:
            best[r0: r0 + stride * sc.shape[1]: stride, c0: c0 + stride * sc.shape[2]: stride] = sc[ci]
        return best, np.zeros(small.shape, dtype=np.int32)

    o2 = DetectOptions(**{**o.__dict__, "min_score": -np.inf})  # SVM values are signed
    cands = _band_scan(scene, model.classes, ppm, S, images, need_figure, o2, score_fn)
    extent = _full_size(model.metadata, "class_extent_mm", model.classes)
    return _finish(cands, scene, model.classes, ppm, S, extent, need_figure, o, lambda k: float("nan"),
                   _full_size(model.metadata, "class_radius_mm", model.classes))


#: An object under a detection may be this much smaller (occlusion, the hidden far side,
#: end-on views) or larger (objects touching) than the class's length and height, with a
#: fixed allowance for the depth noise of far objects (mm).
LENGTH_RATIO_RANGE = (0.3, 1.3)
HEIGHT_RATIO_RANGE = (0.4, 1.3)
SIZE_ALLOWANCE_MM = 500.0
#: A 3D-channel detection must sit on an object or within this many chip pixels of one.
NEAR_CHIP_PX = 4.0


def _object_under(scene: SceneChannels, r: int, c: int, near_px: float) -> int:
    """The object (label) under a pixel, or the commonest within ``near_px``; 0 = none."""
    h = max(1, int(near_px))
    win = scene.labels[max(0, r - h): r + h + 1, max(0, c - h): c + h + 1]
    labs = win[win > 0]
    return int(np.bincount(labs).argmax()) if labs.size else 0


def _size_fits(scene: SceneChannels, r: int, c: int, extent_mm: Sequence[float] | None, near_px: float) -> bool:
    """Whether the object under (or within ``near_px`` of) a detection could be a target
    of the class: its length and height against the class's (``extent_mm`` x, y, z at
    full size; None: any object will do)."""
    lab = _object_under(scene, r, c, near_px)
    if lab == 0:
        return False
    if extent_mm is None:
        return True
    length, _, height = scene.object_dims_mm[lab]
    cl = max(extent_mm[0], extent_mm[1])
    ch = extent_mm[2]
    e = SIZE_ALLOWANCE_MM
    return (LENGTH_RATIO_RANGE[0] * cl - e <= length <= LENGTH_RATIO_RANGE[1] * cl + e
            and HEIGHT_RATIO_RANGE[0] * ch - e <= height <= HEIGHT_RATIO_RANGE[1] * ch + e)


def _chip_at(img: NDArray[np.float32], r: float, c: float, s: float, S: int) -> NDArray[np.float32]:
    """The S x S chip centred at scene pixel (r, c) at resampling factor ``s`` (chip px
    per scene px): the part inside the scene area-averaged to chip scale (to half a chip
    pixel), zero outside; an (H, W, k) image gives an (S, S, k) chip."""
    import cv2

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


def _chip_channel(bank: Any, scene: SceneChannels, r: float, c: float, s: float, f: float) -> NDArray:
    """A candidate's chip in the bank's channel, prepared as the training chips were: depth
    relief about the chip centre's median depth (``depth_relief``), or the shading of the
    chip-scale depth's normals under the chip light (``shape``), or the grey image; objects
    outside the chip's depth slab (in front of or behind the target) are background."""
    from prism3d.atr.bank import depth_relief, prepare_chips
    from prism3d.atr.geometry import normals_from_depth

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


def _verify(bank: Any, scene: SceneChannels, cands: list, ppm: dict[str, float], f: float,
            extent: dict) -> list:
    """Score candidates as chips are scored in training: a chip at each class's scale
    centred on the candidate, prepared like a training chip (:func:`_chip_channel`),
    correlated with all that class's filters (whole planes: shift-invariant); among the
    classes whose size fits the object under the candidate, the best by the bank's metric
    wins and its value is the score."""
    from concurrent.futures import ThreadPoolExecutor

    from prism3d.atr.bank import spectrum_metrics

    S = int(bank.size)
    ks_of = [np.flatnonzero(bank.filter_class == ci) for ci in range(len(bank.classes))]

    def one(cand: tuple) -> tuple | None:
        _, r, c, _, _ = cand
        ri = int(round(min(max(r, 0), scene.range_mm.shape[0] - 1)))
        cj = int(round(min(max(c, 0), scene.range_mm.shape[1] - 1)))
        z = float(scene.range_mm[ri, cj])
        if not math.isfinite(z):
            return None
        best = (-np.inf, 0, 0)
        for ci, cls in enumerate(bank.classes):
            sc = ppm[cls] * z / f
            if S / sc > max(scene.range_mm.shape) or (
                    bank.channel != "intensity" and not _size_fits(scene, ri, cj, extent.get(cls), NEAR_CHIP_PX / sc)):
                continue  # a target of this class could not be here: the 3D says so
            x = _chip_channel(bank, scene, r, c, sc, f)
            ks = ks_of[ci]
            m = spectrum_metrics(np.fft.fft2(x, axes=(-2, -1)), bank.freqs[ks])[bank.metric][0]
            j = int(np.argmax(m))
            if m[j] > best[0]:
                best = (float(m[j]), int(ks[j]), ci)
        return (best[0], r, c, best[1], best[2]) if np.isfinite(best[0]) else None

    # candidates are independent; OpenCV's resampling and the FFTs release the GIL
    with ThreadPoolExecutor(max_workers=_verify_threads()) as pool:
        return [v for v in pool.map(one, cands) if v is not None]


def _verify_threads() -> int:
    """Threads verifying candidates: ``PRISM3D_NUM_THREADS`` (unset: the cores, at most
    4: the work per chip is small; job runners set 1 per worker)."""
    from prism3d.capture.render import configured_threads

    return configured_threads() or max(1, min(4, os.cpu_count() or 1))


def _project(K: NDArray, p: NDArray) -> tuple[float, float]:
    """Pixel (row, col) of a camera-frame point."""
    u = K @ p
    return float(u[1] / u[2]), float(u[0] / u[2])


def _xyz(scene: SceneChannels, r: int, c: int) -> list[float] | None:
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


def detect_shot(bank: Any, shot: NDArray, rig: Any, *, depth_range_mm: tuple[float, float] | None = None,
                options: DetectOptions | None = None) -> tuple[list[dict], dict[str, float]]:
    """Reconstruct a prism shot, then detect; rows, cols in the LEFT VIEW's pixels and
    ``xyz_mm`` in the left camera frame (as the simulator's truth). Returns the
    detections and timings (s)."""
    from prism3d.reconstruct.pipeline import ReconstructOptions, convergence_distance_mm, reconstruct_shot

    t0 = time.perf_counter()
    if depth_range_mm is None:
        wd = convergence_distance_mm(rig)
        if wd is None:
            raise InputError("detect: the rig's views do not converge; give --depth-range NEAR:FAR (m)")
        depth_range_mm = (0.3 * wd, 10.0 * wd)
    rec = reconstruct_shot(shot, rig, ReconstructOptions(depth_range_mm=depth_range_mm))
    t1 = time.perf_counter()
    grey = rec.left_rect.astype(np.float32)
    if grey.ndim == 3:
        grey = grey @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    K = np.asarray(rec.rect.P1, dtype=np.float64)[:, :3]
    sc = scene_channels(grey / 255.0, rec.depth_mm, K, options)
    t2 = time.perf_counter()
    dets = detect_scene(bank, sc, options)
    t3 = time.perf_counter()
    R1 = np.asarray(rec.rect.R1, dtype=np.float64)
    for dt in dets:
        if dt["xyz_mm"] is None:
            # no depth: map the ray only (rectified pixel -> left view pixel at unit depth)
            y = (dt["row"] - K[1, 2]) / K[1, 1]
            p = R1.T @ np.array([(dt["col"] - K[0, 2]) / K[0, 0], y, 1.0])
        else:
            p = R1.T @ np.asarray(dt["xyz_mm"])
            dt["xyz_mm"] = [float(v) for v in p]
        uv = rig.left.project(p[None])[0]
        dt["col"], dt["row"] = float(uv[0]), float(uv[1])
    return dets, {"reconstruct_s": t1 - t0, "channels_s": t2 - t1, "detect_s": t3 - t2}


def detect_to_file(bank_path: str | Path, output: str | Path, *, shot: str | Path | None = None,
                   calib: str | Path | None = None, image: str | Path | None = None,
                   depth: str | Path | None = None, fx: float | None = None,
                   depth_range_mm: tuple[float, float] | None = None,
                   options: DetectOptions | None = None) -> dict[str, Any]:
    """``prism3d detect``: a shot + calibration, or an image + depth map (+ focal), to a
    detections JSON written atomically. Everything is checked before work starts."""
    from prism3d.atr.bank import FilterBank
    from prism3d.io.atomic import atomic_write_text
    from prism3d.io.images import read_image

    out = Path(output)
    if out.suffix.lower() != ".json":
        raise InputError(f"{out}: expected a .json file name for the detections")
    if (shot is None) == (image is None):
        raise InputError("detect: give a shot (with --calib) or --image with --depth, not both")
    bank = FilterBank.load(bank_path)
    bank_scale(bank)
    if shot is not None:
        if calib is None:
            raise InputError("detect: a shot needs --calib (the rig or calibration YAML)")
        if depth is not None:
            raise InputError("detect: --depth goes with --image, not with a shot")
        from prism3d.capture.rig import StereoRig

        rig = StereoRig.load(calib)
        img = read_image(shot)
        dets, times = detect_shot(bank, img, rig, depth_range_mm=depth_range_mm, options=options)
        source = {"shot": str(shot), "calib": str(calib), "frame": "left view pixels, left camera (mm)"}
    else:
        if depth is None:
            raise InputError("detect: --image needs --depth (a depth map in mm: .npy, .tiff or .pfm)")
        from prism3d.io.images import read_depth

        img = read_image(image)
        dmap = read_depth(depth)
        if dmap.shape[:2] != img.shape[:2]:
            raise InputError(f"{depth}: {dmap.shape[1]}x{dmap.shape[0]} px, the image is "
                             f"{img.shape[1]}x{img.shape[0]}; give a depth map of the image's size")
        h, w = img.shape[:2]
        if fx is None:
            raise InputError("detect: --image needs --fx (the focal length in pixels)")
        K = np.array([[fx, 0, (w - 1) / 2.0], [0, fx, (h - 1) / 2.0], [0, 0, 1.0]])
        grey = img.astype(np.float32)
        if grey.ndim == 3:
            grey = grey[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        t0 = time.perf_counter()
        sc = scene_channels(grey / (255.0 if img.dtype == np.uint8 else 1.0), dmap, K, options)
        t1 = time.perf_counter()
        dets = detect_scene(bank, sc, options)
        times = {"channels_s": t1 - t0, "detect_s": time.perf_counter() - t1}
        source = {"image": str(image), "depth": str(depth), "fx": float(fx), "frame": "image pixels, camera (mm)"}
    doc = {"schema_version": 1, "bank": str(bank_path), "channel": bank.channel, "classes": bank.classes,
           **source, "timings_s": times, "detections": dets}
    atomic_write_text(out, json.dumps(doc, indent=1))
    return doc
