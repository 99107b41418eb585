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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from prism3d._env import configured_threads
from prism3d.atr.bank import GRADIENT_SIGMA_PX, spectrum_metrics
from prism3d.atr.models import load_scene_model
from prism3d.atr.scene import (
    DetectOptions,
    SceneChannels,
    SceneDetection,
    bank_scale,
    chip_channel,
    class_size,
    object_xyz,
    project,
    scene_channels,
)
from prism3d.atr.verifier import SceneRecogniser, detect_objects
from prism3d.capture.rig import StereoRig
from prism3d.checks import check_outputs_not_inputs
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_paths
from prism3d.io.images import read_depth, read_image, split_npz_spec
from prism3d.reconstruct.stereo.pipeline import (
    ReconstructOptions,
    convergence_distance_mm,
    reconstruct_shot,
)

__all__ = [
    "DetectOptions", "SceneChannels", "SceneInput", "SceneSource", "bank_scale", "detect_scene", "detect_scene_hog", "detect_shot",
    "detect_to_file", "draw_detections", "in_left_view", "read_scene_source", "scene_channels",
]


def _peaks(score: NDArray, size: int) -> tuple[NDArray, NDArray]:
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



def _finish(cands: list, scene: SceneChannels, classes: Sequence[str], ppm: dict[str, float], S: int,
            extent: dict, gate: bool, o: DetectOptions, aspect: Any, radius: dict[str, float]
            ) -> list[SceneDetection]:
    """Greedy non-maximum suppression (half a chip, at the smaller of two detections'
    scales), the 3D size gate, one detection per object placed at the object's median
    point, none within a found target's radius (``radius``: class -> mm, full size; the
    smaller of the two classes'), and the detection records, best first."""
    f = float(scene.K[0, 0])
    H, W = scene.range_mm.shape
    cands = sorted(cands, key=lambda t: -t[0])
    out: list[SceneDetection] = []
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
        xyz = object_xyz(scene, ri, cj)
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
                r, c = project(scene.K, p)
            taken.add(lab)
        kept.append((r, c, rad))
        out.append(SceneDetection(float(r), float(c), classes[ci], float(score), aspect(k), z,
                                  None if xyz is None else tuple(xyz)))
        if len(out) >= o.max_detections:
            break
    return out


def detect_scene(bank: Any, scene: SceneChannels, options: DetectOptions | None = None) -> list[SceneDetection]:
    """Detections of ``bank`` in a prepared scene, best first (module docstring); pixels
    of the scene grid, points in the scene's camera frame."""

    if isinstance(bank, SceneRecogniser):
        return detect_objects(bank, scene, options)
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
    extent = class_size(bank.metadata, "class_extent_mm", bank.classes)
    cands.sort(key=lambda t: -t[0])
    cands = cands[: o.verify_top]
    if need_figure:  # every object the 3D found is a candidate too, at its centroid
        cands = [(np.inf, float(r), float(c), 0, 0) for r, c in scene.object_rc[1:]] + cands
    if o.verify and cands:
        cands = _verify(bank, scene, cands, ppm, f, extent)
    return _finish(cands, scene, bank.classes, ppm, S, extent, need_figure, o,
                   lambda k: float(bank.filter_az_deg[k]), class_size(bank.metadata, "class_radius_mm", bank.classes))


def detect_scene_hog(model: Any, scene: SceneChannels, options: DetectOptions | None = None) -> list[SceneDetection]:
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
    extent = class_size(model.metadata, "class_extent_mm", model.classes)
    return _finish(cands, scene, model.classes, ppm, S, extent, need_figure, o, lambda k: float("nan"),
                   class_size(model.metadata, "class_radius_mm", model.classes))


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



def _verify(bank: Any, scene: SceneChannels, cands: list, ppm: dict[str, float], f: float,
            extent: dict) -> list:
    """Score candidates as chips are scored in training: a chip at each class's scale
    centred on the candidate, prepared like a training chip (:func:`~prism3d.atr.scene.chip_channel`),
    correlated with all that class's filters (whole planes: shift-invariant); among the
    classes whose size fits the object under the candidate, the best by the bank's metric
    wins and its value is the score."""
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
            x = chip_channel(bank, scene, r, c, sc, f)
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
    return configured_threads() or max(1, min(4, os.cpu_count() or 1))



def in_left_view(dets: Sequence[SceneDetection], K: NDArray, R1: NDArray, rig: Any) -> list[SceneDetection]:
    """Detections on a rectified left grid (camera matrix ``K``, rectifying rotation
    ``R1``) moved to the left view's pixels and camera frame, as the simulator's truth is."""
    R1 = np.asarray(R1, dtype=np.float64)
    out = []
    for dt in dets:
        if dt.xyz_mm is None:
            # no depth: map the ray only (rectified pixel -> left view pixel at unit depth)
            y = (dt.row - K[1, 2]) / K[1, 1]
            p = R1.T @ np.array([(dt.col - K[0, 2]) / K[0, 0], y, 1.0])
            xyz = None
        else:
            p = R1.T @ np.asarray(dt.xyz_mm)
            xyz = (float(p[0]), float(p[1]), float(p[2]))
        uv = rig.left.project(p[None])[0]
        out.append(replace(dt, row=float(uv[1]), col=float(uv[0]), xyz_mm=xyz))
    return out


def detect_shot(bank: Any, shot: NDArray, rig: Any, *, depth_range_mm: tuple[float, float] | None = None,
                options: DetectOptions | None = None) -> tuple[list[SceneDetection], dict[str, float]]:
    """Reconstruct a prism shot, then detect; rows, cols in the LEFT VIEW's pixels and
    ``xyz_mm`` in the left camera frame (as the simulator's truth). Returns the
    detections and timings (s)."""
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
    return in_left_view(dets, K, rec.rect.R1, rig), {"reconstruct_s": t1 - t0, "channels_s": t2 - t1, "detect_s": t3 - t2}


@dataclass(frozen=True)
class SceneSource:
    """What ``detect`` searches: a prism ``shot`` with its ``calib`` (rig or calibration
    YAML), or an ``image`` with its ``depth`` map (mm) and focal length ``fx`` (px)."""

    shot: str | Path | None = None
    calib: str | Path | None = None
    image: str | Path | None = None
    depth: str | Path | None = None
    fx: float | None = None


@dataclass(frozen=True)
class SceneInput:
    """A :class:`SceneSource` read and checked by :func:`read_scene_source`: the shot (with
    its ``rig``) or the image (with its ``depth`` map, mm), ready to search."""

    source: SceneSource
    image: NDArray
    rig: StereoRig | None = None
    depth: NDArray | None = None


def read_scene_source(source: SceneSource, *, output: str | Path, draw: str | Path | None = None,
                      models: Sequence[str | Path] = (),
                      depth_range_mm: tuple[float, float] | None = None) -> SceneInput:
    """Every input of ``detect`` read and checked, and its outputs (``output`` JSON,
    ``draw`` PNG) checked against them, so that a bad input is refused before a recogniser
    is loaded or trained (minutes): the shot and its calibration (the shot's size must be
    the rig's sensor; without ``depth_range_mm`` the views must converge), or the image,
    its depth map of the image's size and a focal length > 0. ``models`` (model files
    read) count as inputs too: no output may replace any of them."""
    shot, calib, image, depth, fx = source.shot, source.calib, source.image, source.depth, source.fx
    out = Path(output)
    if out.suffix.lower() != ".json":
        raise InputError(f"{out}: expected a .json file name for the detections")
    if draw is not None and Path(draw).suffix.lower() != ".png":
        raise InputError(f"{draw}: expected a .png file name for the drawing")
    if (shot is None) == (image is None):
        raise InputError("detect: give a shot (with --calib) or --image with --depth, not both")
    depth_file = None if depth is None else split_npz_spec(depth)[0]
    check_outputs_not_inputs([out, draw], [shot, calib, image, depth_file, *models])
    if shot is not None:
        if calib is None:
            raise InputError("detect: a shot needs --calib (the rig or calibration YAML)")
        if depth is not None:
            raise InputError("detect: --depth goes with --image, not with a shot")
        rig = StereoRig.load(calib)
        if depth_range_mm is None and convergence_distance_mm(rig) is None:
            raise InputError("detect: the rig's views do not converge; give --depth-range NEAR:FAR (m)")
        img = read_image(shot)
        if getattr(rig, "split", None) is not None:
            sw, sh = rig.split.sensor_size
            if img.shape[1] != sw or img.shape[0] != sh:
                raise InputError(f"{shot}: {img.shape[1]}x{img.shape[0]} px, the rig {calib} has a {sw}x{sh} "
                                 "sensor; give the shot this calibration was made for")
        return SceneInput(source, img, rig=rig)
    if depth is None:
        raise InputError("detect: --image needs --depth (a depth map in mm: .npy, .tiff or .pfm)")
    if fx is None:
        raise InputError("detect: --image needs --fx (the focal length in pixels)")
    if not (math.isfinite(fx) and fx > 0):
        raise InputError(f"detect: --fx must be a focal length > 0 px, got {fx}")
    img = read_image(image)
    dmap = read_depth(depth)
    if dmap.shape[:2] != img.shape[:2]:
        raise InputError(f"{depth}: {dmap.shape[1]}x{dmap.shape[0]} px, the image is "
                         f"{img.shape[1]}x{img.shape[0]}; give a depth map of the image's size")
    return SceneInput(source, img, depth=dmap)


def detect_to_file(model: Any, output: str | Path, source: SceneSource | SceneInput, *,
                   depth_range_mm: tuple[float, float] | None = None, options: DetectOptions | None = None,
                   draw: str | Path | None = None, source_name: str | None = None) -> dict[str, Any]:
    """``prism3d detect``: a shot + calibration, or an image + depth map (+ focal), to a
    detections JSON (and a drawing, PNG) written atomically and together; ``model`` is a
    bank or a scene recogniser (or the path of one); ``source`` as given, or already read
    by :func:`read_scene_source`. Everything is checked before work starts."""
    out = Path(output)
    if isinstance(source, SceneSource):
        source = read_scene_source(source, output=out, draw=draw, depth_range_mm=depth_range_mm,
                                   models=[model] if isinstance(model, (str, Path)) else [])
    else:  # read before the model was trained or loaded: its outputs are checked as those were
        if out.suffix.lower() != ".json":
            raise InputError(f"{out}: expected a .json file name for the detections")
        if draw is not None and Path(draw).suffix.lower() != ".png":
            raise InputError(f"{draw}: expected a .png file name for the drawing")
    if isinstance(model, (str, Path)):
        source_name = source_name or str(model)
        model = load_scene_model(model)
    src, img = source.source, source.image
    if source.rig is not None:
        rig = source.rig
        dets, times = detect_shot(model, img, rig, depth_range_mm=depth_range_mm, options=options)
        where = {"shot": str(src.shot), "calib": str(src.calib), "frame": "left view pixels, left camera (mm)"}
        view = rig.split.split(img)[0] if getattr(rig, "split", None) is not None else img
    else:
        dmap, fx = source.depth, float(src.fx)
        h, w = img.shape[:2]
        K = np.array([[fx, 0, (w - 1) / 2.0], [0, fx, (h - 1) / 2.0], [0, 0, 1.0]])
        grey = img.astype(np.float32)
        if grey.ndim == 3:
            grey = grey[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        t0 = time.perf_counter()
        sc = scene_channels(grey / (255.0 if img.dtype == np.uint8 else 1.0), dmap, K, options)
        t1 = time.perf_counter()
        dets = detect_scene(model, sc, options)
        times = {"channels_s": t1 - t0, "detect_s": time.perf_counter() - t1}
        where = {"image": str(src.image), "depth": str(src.depth), "fx": fx, "frame": "image pixels, camera (mm)"}
        view = img
    channel = ",".join(model.channels) if isinstance(model, SceneRecogniser) else model.channel
    doc = {"schema_version": 1, "model": source_name, "channel": channel, "classes": list(model.classes),
           **where, "timings_s": times, "detections": [d.to_json() for d in dets]}
    with atomic_paths(*([out] if draw is None else [out, Path(draw)])) as tmps:
        tmps[0].write_text(json.dumps(doc, indent=1))
        if draw is not None:
            draw_detections(tmps[1], view, dets)
    return doc


#: Detections drawn by :func:`draw_detections`.
DRAW_TOP = 12


def draw_detections(path: str | Path, image: NDArray, dets: Sequence[SceneDetection], *, top: int = DRAW_TOP
                    ) -> None:
    """The image with its best ``top`` detections marked (a ring at each, class and score),
    as PNG at ``path``; the best in red, the rest in orange."""
    img = np.ascontiguousarray(np.asarray(image)[..., :3][..., ::-1] if np.asarray(image).ndim == 3
                               else np.repeat(np.asarray(image)[..., None], 3, axis=2)).astype(np.uint8)
    h, w = img.shape[:2]
    s = max(1, int(round(max(h, w) / 1000)))
    for k, d in enumerate(sorted(dets, key=lambda x: -x.score)[:top]):
        col = (40, 40, 230) if k == 0 else (40, 150, 240)
        r, c = int(round(d.row)), int(round(d.col))
        cv2.circle(img, (c, r), 18 * s, col, 2 * s, cv2.LINE_AA)
        cv2.putText(img, f"{k + 1} {d.class_name} {d.score:.2f}", (c + 20 * s, r), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5 * s, col, s, cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise InputError(f"{path}: could not write the drawing")
