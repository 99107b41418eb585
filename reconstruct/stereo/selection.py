"""Which pixels of a matched pair become points, and how sure each one is, by rules
stated against the shot itself (its noise, black level, disparity map); the rules and
their reasons: docs/reconstruction.md."""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError

from . import _selection_kernels as _k

__all__ = [
    "REASONS",
    "Coverage",
    "confidence_from_std",
    "estimate_noise",
    "enclosed",
    "fill_from_planes",
    "isolated_matches",
    "near",
    "occlusions",
    "surrounded",
    "std_from_confidence",
    "texture_energy",
    "textured",
    "unlit",
]

#: Why a pixel gave no point, in the order the checks apply.
REASONS = ("outside depth range", "too far to measure", "no texture", "silhouette", "occluded", "inconsistent",
           "isolated match", "low confidence",
           "unmatched")

#: Immerkaer's operator responds to noise of std sigma with std 6 sigma; a median
#: absolute response is 0.6745 std of a Gaussian.
_IMMERKAER_GAIN = 0.6745 * 6.0
#: Noise blocks (px): small enough that some are smooth, large enough for a median.
_NOISE_BLOCK = 16
#: The smoothest tenth of the blocks estimates the noise (texture only adds).
_NOISE_PERCENTILE = 10.0
#: The 8-bit quantisation step's own noise, 1 / sqrt(12) levels.
_MIN_NOISE = 0.29
#: Blocks wholly inside the mask needed before the mask is used.
_MIN_NOISE_BLOCKS = 4
#: Percentiles of the brightest channel taken as the shot's black level and top.
_BLACK_PERCENTILE, _TOP_PERCENTILE = 0.5, 99.5
#: Fill windows are made of square cells of about radius / 6 px (at most 13 x 13 cells).
_CELLS_PER_RADIUS = 6


def estimate_noise(image: NDArray, mask: NDArray | None = None) -> float:
    """Noise std (8-bit levels) of the image: 10th percentile over 16x16 blocks (inside
    ``mask``) of Immerkaer's operator's median absolute response.

    References
    ----------
    .. [1] J. Immerkaer, "Fast noise variance estimation", CVIU 64(2), 1996.
    """
    img = check_array(image, "image", ndim=(2, 3), min_size=9).astype(np.float32)
    chans = [img] if img.ndim == 2 else [img[..., c] for c in range(img.shape[2])]
    kern = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    resp = sum(np.abs(cv2.filter2D(np.ascontiguousarray(c), -1, kern, borderType=cv2.BORDER_REFLECT))
               for c in chans) / len(chans)
    h, w = resp.shape
    b = _NOISE_BLOCK
    hb, wb = h // b, w // b
    if hb == 0 or wb == 0:
        est = float(np.median(resp)) / _IMMERKAER_GAIN
        return max(est, _MIN_NOISE)
    blocks = resp[: hb * b, : wb * b].reshape(hb, b, wb, b).transpose(0, 2, 1, 3).reshape(hb * wb, b * b)
    if mask is not None:
        m = check_array(mask, "mask", shape=(h, w)).astype(bool)
        keep = m[: hb * b, : wb * b].reshape(hb, b, wb, b).transpose(0, 2, 1, 3).reshape(hb * wb, -1).all(axis=1)
        if keep.sum() >= _MIN_NOISE_BLOCKS:
            blocks = blocks[keep]
    per_block = np.median(blocks, axis=1) / _IMMERKAER_GAIN
    return max(float(np.percentile(per_block, _NOISE_PERCENTILE)), _MIN_NOISE)


def unlit(image: NDArray, noise: float, textured_mask: NDArray, *, k_sigma: float = 5.0,
          spill: float = 0.04, min_share: float = 0.1) -> NDArray[np.bool_]:
    """Unlit background ``(H, W)`` bool: connected dark regions (within ``k_sigma`` noise
    or ``spill`` of the range above the black level) holding untextured pixels, when
    they cover ``min_share`` of the image (a flash shot against the dark)."""
    img = check_array(image, "image", ndim=(2, 3))
    v = (img.max(axis=2) if img.ndim == 3 else img).astype(np.float32)
    t = check_array(textured_mask, "textured_mask", shape=v.shape).astype(bool)
    floor, top = (float(p) for p in np.percentile(v, [_BLACK_PERCENTILE, _TOP_PERCENTILE]))
    dark = v <= floor + max(float(k_sigma) * float(noise), float(spill) * (top - floor))
    n, labels = cv2.connectedComponents(dark.astype(np.uint8), connectivity=8)
    floor_region = np.zeros(n, bool)
    floor_region[np.unique(labels[dark & ~t])] = True
    floor_region[0] = False
    out = floor_region[labels] & dark
    return out if out.mean() >= float(min_share) else np.zeros_like(out)


def near(mask: NDArray, radius: int) -> NDArray[np.bool_]:
    """Pixels within ``radius`` px (chessboard distance) of a ``mask`` pixel, excluding
    the mask itself."""
    m = check_array(mask, "mask", ndim=2).astype(np.uint8)
    size = 2 * int(radius) + 1
    return cv2.dilate(m, np.ones((size, size), np.uint8)).astype(bool) & ~m.astype(bool)


#: Side (px) of the neighbourhood whose matches vote on a pixel's (:func:`isolated_matches`):
#: about a thousand pixels, so that the vote is a region's and not one window's.
ISOLATION_WINDOW_PX = 31
#: A match is kept where at least this share of its peers matched too.
ISOLATION_MIN_SHARE = 0.5
#: Texture levels (log-spaced between the 1st and 99th percentiles) that rank the peers.
_ISOLATION_LEVELS = 12


def isolated_matches(valid: NDArray, matchable: NDArray, energy: NDArray, *,
                     window: int = ISOLATION_WINDOW_PX, min_share: float = ISOLATION_MIN_SHARE
                     ) -> NDArray[np.bool_]:
    """Valid matches whose peers mostly failed: among the ``matchable`` pixels of the
    ``window`` square around a match with at least its texture ``energy``
    (:func:`texture_energy`), fewer than ``min_share`` passed the matcher's checks. Where
    faint texture (sky, haze, a smooth gradient) defeats the matcher almost everywhere,
    the few matches that survive are chance agreements; a chessboard's edges, among
    failed flat squares, are judged by the other edges."""
    v = check_array(valid, "valid", ndim=2).astype(bool)
    m = check_array(matchable, "matchable", shape=v.shape).astype(bool)
    e = check_array(energy, "energy", shape=v.shape)
    out = np.zeros(v.shape, bool)
    if not (v & m).any():
        return out
    log_e = np.log2(np.maximum(e, 1e-12, dtype=np.float32))
    lo, hi = np.percentile(log_e[m], [1.0, 99.0])
    level = np.clip(np.digitize(log_e, np.linspace(lo, hi, _ISOLATION_LEVELS + 1)) - 1, 0, _ISOLATION_LEVELS - 1)
    k = (int(window), int(window))
    for i in range(_ISOLATION_LEVELS):
        here = v & (level == i)
        if not here.any():
            continue
        peers = m & (level >= i)
        ok = cv2.boxFilter((v & peers).astype(np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        n = cv2.boxFilter(peers.astype(np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
        out |= here & (ok < float(min_share) * np.maximum(n, 1.0))
    return out


def surrounded(mask: NDArray, radius: int) -> NDArray[np.bool_]:
    """Pixels with a ``mask`` pixel within ``radius`` px straight above, below, left and
    right: inside a surface's outline, where interpolation holds, rather than beside
    it (above a tree crown is sky as often as tree)."""
    m = check_array(mask, "mask", ndim=2).astype(bool)
    r = int(radius)

    def reach_from_before(a: NDArray[np.bool_]) -> NDArray[np.bool_]:
        cols = np.arange(a.shape[1], dtype=np.int64)
        last = np.maximum.accumulate(np.where(a, cols[None, :], -(r + 1) - a.shape[1]), axis=1)
        return cols[None, :] - last <= r

    return (reach_from_before(m) & reach_from_before(m[:, ::-1])[:, ::-1]
            & reach_from_before(m.T).T & reach_from_before(m.T[:, ::-1])[:, ::-1].T)


def enclosed(region: NDArray, outside: NDArray) -> NDArray[np.bool_]:
    """Pixels of ``region`` whose connected component (8-connected) touches neither an
    ``outside`` pixel nor the image border: holes in a surface, not the space beside
    one."""
    r = check_array(region, "region", ndim=2).astype(np.uint8)
    o = check_array(outside, "outside", shape=r.shape).astype(bool)
    n, labels = cv2.connectedComponents(r, connectivity=8)
    if n <= 1:
        return np.zeros(r.shape, bool)
    bad = np.zeros(n, bool)
    touch = cv2.dilate(o.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    bad[np.unique(labels[touch])] = True
    border = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    bad[np.unique(border)] = True
    bad[0] = True
    return ~bad[labels] & r.astype(bool)


def texture_energy(image: NDArray, *, window: tuple[int, int] = (7, 19)) -> NDArray[np.float32]:
    """Horizontal-gradient energy summed over the colour channels and the ``window``
    (rows, cols) around each pixel: what a horizontal match has to hold on to."""
    img = check_array(image, "image", ndim=(2, 3)).astype(np.float32)
    img = img[..., None] if img.ndim == 2 else img
    energy = np.zeros(img.shape[:2], np.float32)
    for c in range(img.shape[2]):
        g = cv2.Sobel(np.ascontiguousarray(img[..., c]), cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
        energy += g * g
    wy, wx = int(window[0]), int(window[1])
    return cv2.boxFilter(energy, -1, (wx, wy), normalize=True, borderType=cv2.BORDER_REFLECT) * (wy * wx)


def textured(image: NDArray, noise: float, *, window: tuple[int, int] = (7, 19),
             k_sigma: float = 3.0) -> NDArray[np.bool_]:
    """Pixels whose ``window`` (rows, cols) holds more horizontal-gradient energy than
    noise alone would: ``n sigma^2 / 2`` over ``n`` samples, exceeded by ``k_sigma``
    relative spreads ``sqrt(3 / n)``."""
    img = check_array(image, "image", ndim=(2, 3))
    n = int(window[0]) * int(window[1]) * (1 if img.ndim == 2 else img.shape[2])
    floor = n * float(noise) ** 2 / 2.0
    return texture_energy(img, window=window) > floor * (1.0 + float(k_sigma) * np.sqrt(3.0 / n))


def occlusions(disparity: NDArray, *, margin: float = 1.0) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """``(occluded, outside)`` masks of a dense left-view disparity map: ``outside``, the
    match lies left of the right view; ``occluded``, a pixel nearer by more than
    ``margin`` px further right on the row lands on or left of the same column."""
    d = check_array(disparity, "disparity", ndim=2, dtype_kind="f").astype(np.float32)
    occ = np.empty(d.shape, np.bool_)
    out = np.empty(d.shape, np.bool_)
    _k.occlusions(np.ascontiguousarray(d), occ, out, float(margin))
    return occ, out


def fill_from_planes(
    disparity: NDArray,
    known: NDArray,
    targets: NDArray,
    *,
    radii: tuple[int, ...] = (8, 24),
    sides: tuple[str, ...] = ("centre",),
    min_fraction: float = 0.25,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Predict ``targets`` from local planes through the ``known`` disparities: per
    window (each of ``radii``; centred or reaching to the ``"left"``/``"right"`` only)
    with ``min_fraction`` known, the plane's prediction of smallest variance wins.
    Returns the estimate and its std (px), ``(H, W)`` float32, NaN where none served."""
    d = check_array(disparity, "disparity", ndim=2, dtype_kind="f")
    k = check_array(known, "known", shape=d.shape).astype(bool) & np.isfinite(d)
    t = check_array(targets, "targets", shape=d.shape).astype(bool)
    if not (0.0 < min_fraction <= 1.0):
        raise InputError(f"min_fraction: expected a value in (0, 1], got {min_fraction!r}")
    codes = {"centre": 0, "left": -1, "right": 1}
    for name in sides:
        if name not in codes:
            raise InputError(f"sides: expected 'centre', 'left' or 'right', got {name!r}")
    est_img = np.full(d.shape, np.nan, np.float32)
    std_img = np.full(d.shape, np.nan, np.float32)
    ys, xs = np.nonzero(t)
    if len(ys) == 0 or not k.any():
        return est_img, std_img
    ref = float(np.median(d[k]))
    dk = np.ascontiguousarray(np.where(k, d, 0.0), dtype=np.float64)
    km = np.ascontiguousarray(k)
    est = np.full(len(ys), np.nan)
    var = np.full(len(ys), np.inf)
    ys32, xs32 = ys.astype(np.int64), xs.astype(np.int64)
    for r in radii:
        s = max(1, int(r) // _CELLS_PER_RADIUS)
        kc = max(1, int(round(r / s)))
        cells = np.empty((10, -(-d.shape[0] // s), -(-d.shape[1] // s)))
        _k.cell_sums(dk, km, s, ref, cells)
        for name in sides:
            cols = (2 * kc + 1) if codes[name] == 0 else (kc + 1)
            min_n = float(min_fraction) * (2 * kc + 1) * cols * s * s
            _k.plane_predict(ys32, xs32, cells, s, kc, codes[name], min_n, est, var)
    ok = np.isfinite(var)
    est_img[ys[ok], xs[ok]] = (est[ok] + ref).astype(np.float32)
    std_img[ys[ok], xs[ok]] = np.sqrt(var[ok]).astype(np.float32)
    return est_img, std_img


def confidence_from_std(std: NDArray) -> NDArray[np.float32]:
    """The chance that a disparity is within 1 px of the truth (the bad-1 rule) if its
    error is Gaussian with standard deviation ``std`` px: ``erf(1 / (sqrt(2) std))``."""
    from scipy.special import erf

    s = np.asarray(std, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = erf(1.0 / (np.sqrt(2.0) * s))
    return np.where(np.isfinite(s) & (s >= 0), c, 0.0).astype(np.float32)


def std_from_confidence(confidence: float) -> float:
    """The largest disparity std (px) whose :func:`confidence_from_std` reaches
    ``confidence`` (in (0, 1))."""
    from scipy.special import erfinv

    c = float(confidence)
    if not (0.0 < c < 1.0):
        raise InputError(f"confidence: expected a value in (0, 1), got {confidence!r}")
    return float(1.0 / (np.sqrt(2.0) * erfinv(c)))


@dataclass
class Coverage:
    """Pixel counts of a view: ``considered`` (covered by the left view), ``measured``,
    ``estimated`` (filled from planes), and ``dropped`` per each of :data:`REASONS`."""

    considered: int
    measured: int
    estimated: int
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def kept(self) -> int:
        return self.measured + self.estimated

    def shares(self) -> dict[str, float]:
        """Each category as a share of ``considered``."""
        n = max(self.considered, 1)
        out = {"kept": self.kept / n, "measured": self.measured / n, "estimated": self.estimated / n}
        out.update({k: v / n for k, v in self.dropped.items()})
        return out

    def summary(self) -> str:
        """One line: the share kept and why the rest was dropped."""
        s = self.shares()
        parts = [f"{s[k]:.1%} {k}" for k in REASONS if self.dropped.get(k, 0) > 0]
        tail = f"; dropped: {', '.join(parts)}" if parts else ""
        return (f"kept {s['kept']:.1%} of {self.considered} pixels ({s['measured']:.1%} measured, "
                f"{s['estimated']:.1%} estimated from their neighbours){tail}")

    def as_dict(self) -> dict[str, object]:
        return {"considered": self.considered, "measured": self.measured, "estimated": self.estimated,
                "kept": self.kept, "dropped": dict(self.dropped)}
