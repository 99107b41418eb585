"""Per-cell features of an aerial scene at one heading: what the aerial recogniser's linear
windows read.

The scene (grey appearance and normalised DSM on one grid) is turned so that vehicles at
the heading under test lie along the image's columns, then cut into square cells. Each
cell holds:

* 9 gradient-orientation bins (unsigned, 20 deg each) of the appearance's logarithm, each
  weighted by the gradient's magnitude and normalised by the gradient energy of the 3 x 3
  cells around (Dalal and Triggs [1]_; one normalisation instead of four overlapping
  blocks, as in Felzenszwalb et al. [2]_): edges and stripes whatever their contrast sign,
  so a white car and a black one look alike. The logarithm makes an edge's strength its
  brightness ratio, not its difference: a black car's outline on dark asphalt and its
  windscreen count as much as a white car's (the offset keeps sensor noise in deep
  shadow from counting as edges);
* the cell's contrast: its mean grey's distance from the median of the 7 x 7 cells
  around, and its grey spread;
* the height above the ground: the cell's mean and highest nDSM value (m, clipped to
  0-6) and its share of cells without a height (stereo leaves dark paint and shadows
  empty: a hole is a fact, not zero).

References
----------
.. [1] N. Dalal, B. Triggs, "Histograms of oriented gradients for human detection", CVPR 2005.
.. [2] P. Felzenszwalb, R. Girshick, D. McAllester, D. Ramanan, "Object detection with
   discriminatively trained part-based models", IEEE TPAMI 32(9), 2010.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["CHANNEL_SETS", "N_BINS", "cell_features", "feature_names", "rotate_scene"]

N_BINS = 9
_APPEARANCE = [f"hog{k}" for k in range(N_BINS)] + ["contrast", "spread"]
_HEIGHT = ["h_mean", "h_max", "h_missing"]
#: Which per-cell features each input set reads.
CHANNEL_SETS = {"both": _APPEARANCE + _HEIGHT, "appearance": _APPEARANCE, "height": _HEIGHT}
MAX_HEIGHT_M = 6.0
#: Added to the grey level (0-1) before its logarithm: about 13 of 255 grey levels, above
#: the sensor noise in shadow.
LOG_OFFSET = 0.05


def feature_names(channels: str) -> list[str]:
    """The per-cell feature names of a channel set (``both``, ``appearance``, ``height``)."""
    return list(CHANNEL_SETS[channels])


def rotate_scene(grey: NDArray, ndsm: NDArray, angle_rad: float, pad: int = 0
                 ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float64]]:
    """The scene turned so that a vehicle heading ``angle_rad`` (counter-clockwise from the
    image's +x, seen from above) lies along +x; the canvas grows to hold it all (+``pad``
    px a side). Returns grey, nDSM (NaN kept; NaN outside) and the 2 x 3 map from
    original (x, y) pixels to turned ones."""
    h, w = grey.shape
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    # turning the scene clockwise on screen by angle (y down) undoes a counter-clockwise heading
    W = int(math.ceil(abs(w * c) + abs(h * s))) + 2 * pad
    H = int(math.ceil(abs(w * s) + abs(h * c))) + 2 * pad
    M = np.array([[c, -s, 0.0], [s, c, 0.0]])
    M[:, 2] = np.array([(W - 1) / 2.0, (H - 1) / 2.0]) - M[:, :2] @ np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    g = cv2.warpAffine(grey.astype(np.float32), M, (W, H), flags=cv2.INTER_LINEAR, borderValue=float("nan"))
    missing = (~np.isfinite(ndsm)).astype(np.float32)
    z = cv2.warpAffine(np.nan_to_num(ndsm, nan=0.0).astype(np.float32), M, (W, H), flags=cv2.INTER_LINEAR,
                       borderValue=0.0)
    m = cv2.warpAffine(missing, M, (W, H), flags=cv2.INTER_LINEAR, borderValue=1.0)
    z[m > 0.5] = np.nan
    return g, z, M


def _cell_mean(a: NDArray[np.float32], hc: int, wc: int, k: int) -> NDArray[np.float32]:
    """Mean of each k x k cell (the image cropped to whole cells)."""
    return cv2.resize(a[: hc * k, : wc * k], (wc, hc), interpolation=cv2.INTER_AREA)


#: the orientation bin of each tenth of a degree over 0-360, folded to 0-180 (unsigned)
_BIN_OF = np.minimum((np.mod(np.arange(3601) / 10.0, 180.0) * N_BINS / 180.0).astype(np.uint8), N_BINS - 1)


def _orientation_bins(ang: NDArray[np.float32]) -> NDArray[np.uint8]:
    """Unsigned orientation bin (0..N_BINS-1) of each gradient angle (rad, 0-2 pi): the
    angle in tenths of a degree looked up in a table (the bins' edges, 20 deg apart, fall on
    whole tenths): no floating-point modulo over the image."""
    t = (ang * np.float32(1800.0 / math.pi)).astype(np.int16)
    return _BIN_OF.take(t, mode="clip")


def cell_features(grey: NDArray, ndsm: NDArray, cell_px: int, channels: str = "both") -> NDArray[np.float32]:
    """Per-cell features (Hc, Wc, F) of a grey image (NaN outside the scene) and its nDSM
    on the same grid (module docstring); F as :func:`feature_names` of ``channels``."""
    g = np.asarray(grey, dtype=np.float32)
    H, W = g.shape
    k = int(cell_px)
    hc, wc = H // k, W // k
    out = []
    outside = ~np.isfinite(g)
    if channels in ("both", "appearance"):
        inside = g[::4, ::4][np.isfinite(g[::4, ::4])]  # a sixteenth of the pixels: the same median
        fill = float(np.median(inside)) if inside.size else 0.0
        gf = np.where(outside, fill, g).astype(np.float32)
        lg = np.log(gf + np.float32(LOG_OFFSET))
        gx = cv2.Sobel(lg, cv2.CV_32F, 1, 0, ksize=1)
        gy = cv2.Sobel(lg, cv2.CV_32F, 0, 1, ksize=1)
        mag, ang = cv2.cartToPolar(gx, gy)
        # the coverage's edge is no edge of the scene: nothing within a pixel of it counts
        mag[cv2.dilate(outside.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0] = 0.0
        b = _orientation_bins(ang)
        hist = np.empty((hc, wc, N_BINS), dtype=np.float32)
        tmp = np.empty_like(mag)
        for j in range(N_BINS):
            np.multiply(mag, b == j, out=tmp)
            hist[..., j] = _cell_mean(tmp, hc, wc, k)
        hist *= k * k
        energy = cv2.boxFilter((hist * hist).sum(axis=2), -1, (3, 3), normalize=False, borderType=cv2.BORDER_REFLECT)
        hog = np.minimum(hist / np.sqrt(energy[..., None] / 9.0 + 1e-4), 0.6) / 0.6
        mean = _cell_mean(gf, hc, wc, k)
        spread = np.sqrt(np.maximum(_cell_mean(gf * gf, hc, wc, k) - mean * mean, 0.0))
        local = cv2.medianBlur(np.clip(mean * 255, 0, 255).astype(np.uint8), 7).astype(np.float32) / 255.0
        out += [hog, np.abs(mean - local)[..., None] * 4.0, spread[..., None] * 8.0]
    if channels in ("both", "height"):
        z = np.asarray(ndsm, dtype=np.float32)
        fin = np.isfinite(z)
        zc = np.nan_to_num(z, nan=0.0)  # a copy
        np.clip(zc, 0.0, MAX_HEIGHT_M, out=zc)
        share = _cell_mean(fin.astype(np.float32), hc, wc, k)
        hmean = _cell_mean(zc, hc, wc, k) / np.maximum(share, 1.0 / (k * k))
        hmax = zc[: hc * k, : wc * k].reshape(hc, k, wc, k).max(axis=(1, 3))
        out += [hmean[..., None] / 2.0, hmax[..., None] / 2.0, (1.0 - share)[..., None]]
    f = np.concatenate(out, axis=2).astype(np.float32)
    if channels in ("both", "appearance"):
        f[_cell_mean(outside.astype(np.float32), hc, wc, k) > 0.5] = 0.0
    return f
