"""Chessboard corner detection with a canonical, view-consistent corner order.

Detectors (:data:`DETECTORS`): ``"xjunction"`` (default: ``"classic"`` refined by
:func:`refine_xjunction`), ``"classic"`` (``cv2.findChessboardCorners`` + ``cornerSubPix``),
``"sb"`` (``cv2.findChessboardCornersSB``); accuracies in docs/calibration.md. Corner 0
is the grid corner from which rows run along +x and columns along +y in the image; where
that is ambiguous, :func:`grid_symmetries` lists the alternatives.

References
----------
.. [1] A. Geiger, F. Moosmann, O. Car, B. Schuster, "Automatic camera and range sensor
   calibration using a single shot", ICRA 2012 (sector-based corner ideas).
.. [2] P. Duda, "Accurate detection and localization of checkerboard corners for
   calibration", BMVC 2018 (``findChessboardCornersSB``).
.. [3] S. Placht et al., "ROCHADE: Robust Checkerboard Advanced Detection for Camera
   Calibration", ECCV 2014 (sub-pixel refinement by fitting the grey levels).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import PrismSplit
from prism3d.checks import check_array, check_choice, check_file
from prism3d.errors import InputError
from prism3d.io.images import check_image_size, decode_image

__all__ = [
    "DETECTORS",
    "CornerDetection",
    "board_object_points",
    "canonical_order",
    "detect_corners",
    "detect_square_grid",
    "detect_views",
    "grid_symmetries",
    "load_image",
    "refine_xjunction",
    "to_gray",
    "to_gray_float",
]

log = logging.getLogger(__name__)

#: Available detector names.
DETECTORS = ("xjunction", "classic", "sb")
#: Default cornerSubPix half-window as a fraction of the board's square size in
#: pixels (the best measured, docs/calibration.md); ``window=None`` uses it.
WINDOW_FRACTION = 0.2
DEFAULT_WINDOW: int | None = None
#: X-junction fit window radius as a fraction of the corner spacing (``"xjunction"``).
XJ_RADIUS_FRACTION = 0.6
#: Largest X-junction fit window radius, pixels.
XJ_MAX_RADIUS = 32.0
#: OpenCV's detectors fail on views smaller than this (px).
_MIN_IMAGE_PX = 16
#: Views larger than this are searched for the board in an area-averaged copy of this
#: size (OpenCV's search slows and grows with the pixel count; the corners are refined
#: at full resolution). The paper's 5 MP sensor gives 2.5 MP views.
DETECT_MAX_PIXELS = 8_000_000
#: cornerSubPix stops after this many iterations or a move below this (px).
_SUBPIX_MAX_ITER = 100
_SUBPIX_EPS = 1e-4


def _subpix_criteria() -> tuple[int, int, float]:
    import cv2

    return (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, _SUBPIX_MAX_ITER, _SUBPIX_EPS)


@dataclass(frozen=True, eq=False)
class CornerDetection:
    """What was found in one view (``"left"``/``"right"``) of one image (path or
    ``"<array i>"``): whether the full board was, the corner count, the mean edge width in
    px (``cv2.estimateChessboardSharpness``, NaN when not found) and the ``(N, 2)`` float64
    corners in canonical order, or None."""

    source: str
    view: str
    found: bool
    n_corners: int
    sharpness: float
    corners: NDArray[np.float64] | None


def board_object_points(board: tuple[int, int], square_mm: float) -> NDArray[np.float64]:
    """Board-frame corner positions ``(N, 3)`` mm, row-major, ``z = 0``.

    ``board = (cols, rows)`` inner corners as in OpenCV's ``patternSize``; corner
    ``i = r * cols + c`` sits at ``(c * square_mm, r * square_mm, 0)``.
    """
    cols, rows = _check_board(board)
    c, r = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    return np.stack([c.ravel(), r.ravel(), np.zeros(cols * rows)], axis=1) * float(square_mm)


def _check_board(board: Sequence[int]) -> tuple[int, int]:
    try:
        cols, rows = (int(b) for b in board)
    except (TypeError, ValueError) as exc:
        raise InputError(f"board: expected (cols, rows) inner corners, got {board!r}") from exc
    if cols < 2 or rows < 2:
        raise InputError(f"board: expected at least 2x2 inner corners, got {cols}x{rows}")
    return cols, rows


def grid_symmetries(board: tuple[int, int]) -> list[NDArray[np.intp]]:
    """Index permutations mapping a detected corner list onto the grid's symmetric orders.

    ``corners[perm]`` is the same grid read in another order: 4 orders for a
    rectangular board (identity, rows reversed, columns reversed, both), 8 for a
    square one (also transposed).
    """
    cols, rows = _check_board(board)
    G = np.arange(cols * rows).reshape(rows, cols)
    grids = [G, G[::-1, :], G[:, ::-1], G[::-1, ::-1]]
    if cols == rows:
        grids += [g.T for g in grids]
    return [np.ascontiguousarray(g).ravel() for g in grids]


def _order_score(corners: NDArray[np.float64], board: tuple[int, int]) -> float:
    cols, rows = board
    g = corners.reshape(rows, cols, 2)
    d_row = (g[:, -1] - g[:, 0]).mean(axis=0)
    d_col = (g[-1, :] - g[0, :]).mean(axis=0)
    d_row = d_row / max(float(np.linalg.norm(d_row)), 1e-12)
    d_col = d_col / max(float(np.linalg.norm(d_col)), 1e-12)
    # tiny tie-breakers keep the choice deterministic at exactly 45/90 degrees
    return float(d_row[0] + d_col[1] + 1e-6 * (d_row[1] - d_col[0]))


def canonical_order(corners: NDArray, board: tuple[int, int]) -> NDArray[np.float64]:
    """Reorder ``(N, 2)`` corners in any of the grid's symmetric orders so rows run along
    +x and columns along +y; ``board`` = ``(cols, rows)`` inner corners."""
    cols, rows = _check_board(board)
    c = check_array(corners, "corners", dtype_kind="fiu").reshape(-1, 2).astype(np.float64)
    if c.shape[0] != cols * rows:
        raise InputError(
            f"corners: expected {cols * rows} corners for a {cols}x{rows} board, got {c.shape[0]}"
        )
    best = max(grid_symmetries((cols, rows)), key=lambda p: _order_score(c[p], (cols, rows)))
    return c[best]


def to_gray(image: NDArray) -> NDArray[np.uint8]:
    """Grey uint8 ``(H, W)`` from an RGB/grey uint8 or float [0, 1] image."""
    import cv2

    img = check_array(image, "image", ndim=(2, 3))
    if img.dtype.kind == "f":
        img = np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(f"image: expected uint8 or float in [0, 1], got {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] == 1:
            return np.ascontiguousarray(img[:, :, 0])
        if img.shape[2] not in (3, 4):
            raise InputError(f"image: expected 1, 3 or 4 channels, got {img.shape[2]}")
        # OpenCV takes a row-strided view (a prism view is a column slice) without a copy
        src = img if img.shape[2] == 3 else np.ascontiguousarray(img[:, :, :3])
        return cv2.cvtColor(src, cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)


def to_gray_float(image: NDArray) -> NDArray[np.float64]:
    """Grey float64 ``(H, W)`` on the 0-255 scale, without rounding to 8 bits.

    RGB is weighted like ``cv2.COLOR_RGB2GRAY`` (0.299, 0.587, 0.114); float input in
    [0, 1] is scaled by 255. Sub-pixel refinement works on this, so that the grey
    conversion adds no quantisation to the (8-bit, noisy) image.
    """
    img = check_array(image, "image", ndim=(2, 3))
    if img.dtype.kind not in "fu":
        raise InputError(f"image: expected uint8 or float in [0, 1], got {img.dtype}")
    a = np.nan_to_num(img.astype(np.float64))
    if img.dtype.kind == "f":
        a = a * 255.0
    if a.ndim == 3:
        if a.shape[2] == 1:
            return np.ascontiguousarray(a[:, :, 0])
        if a.shape[2] not in (3, 4):
            raise InputError(f"image: expected 1, 3 or 4 channels, got {a.shape[2]}")
        a = a[:, :, :3] @ np.array([0.299, 0.587, 0.114])
    return np.ascontiguousarray(a)


def _grid_directions(
    corners: NDArray[np.float64], board: tuple[int, int]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per corner: unit row and column directions and the distance to the nearest
    grid neighbour (pixels), from the detected grid (OpenCV's row-major order)."""
    cols, rows = board
    g = corners.reshape(rows, cols, 2)

    def central(axis: int) -> NDArray[np.float64]:
        d = np.diff(g, axis=axis)
        pad = [(0, 0)] * 3
        pad[axis] = (1, 0)
        before = np.pad(d, pad, mode="edge")
        pad[axis] = (0, 1)
        after = np.pad(d, pad, mode="edge")
        return 0.5 * (before + after)

    def nearest(axis: int) -> NDArray[np.float64]:
        d = np.linalg.norm(np.diff(g, axis=axis), axis=2)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        a = np.pad(d, pad, mode="constant", constant_values=np.inf)
        pad[axis] = (0, 1)
        b = np.pad(d, pad, mode="constant", constant_values=np.inf)
        return np.minimum(a, b)

    d_row, d_col = central(1).reshape(-1, 2), central(0).reshape(-1, 2)
    d_row = d_row / np.maximum(np.linalg.norm(d_row, axis=1, keepdims=True), 1e-12)
    d_col = d_col / np.maximum(np.linalg.norm(d_col, axis=1, keepdims=True), 1e-12)
    spacing = np.minimum(nearest(1), nearest(0)).ravel()
    return d_row, d_col, spacing


#: Model constants of the X-junction fit: erf argument scale and d erf / dx factor.
_K_ERF = 1.0 / math.sqrt(2.0)
_K_DER = 2.0 / math.sqrt(math.pi)
#: Smallest fit window radius, px: fewer pixels leave the 9 model parameters unpinned.
_XJ_MIN_RADIUS = 2.0
#: Ridge on the linear start solve, keeping a blank window's 4x4 system regular.
_XJ_LINEAR_RIDGE = 1e-9
#: Levenberg-Marquardt damping: start, factor on success and on failure, give-up level.
_LM_LAMBDA0 = 1e-3
_LM_DOWN = 0.3
_LM_UP = 10.0
_LM_LAMBDA_MAX = 1e8
_LM_DIAG_FLOOR = 1e-12  # keeps the damping of a parameter without gradient non-zero
#: A corner has converged when its step is below this, px.
_XJ_STEP_TOL = 1e-5
#: Smallest blur width (px) during the fit: a narrower edge is below pixel sampling.
_XJ_MIN_BLUR = 0.2
#: Fit accepted only when the corner moved less than this fraction of the corner spacing
#: (a larger move means the fit locked on another corner) ...
_XJ_MAX_MOVE = 0.25
#: ... and the contrast |A| (grey levels) exceeds this (else there is no corner).
_XJ_MIN_CONTRAST = 1.0


@dataclass(frozen=True, eq=False)
class _XJWindows:
    """The pixels around every corner: coordinates ``(N, M)``, offsets from the rounded
    corner, in-window weights (0 outside the radius or the image) and grey levels."""

    px: NDArray[np.float64]
    py: NDArray[np.float64]
    rel_x: NDArray[np.float64]
    rel_y: NDArray[np.float64]
    wgt: NDArray[np.float64]
    img: NDArray[np.float64]


def _xj_windows(g: NDArray[np.float64], c0: NDArray[np.float64], radius: NDArray[np.float64]) -> _XJWindows:
    H, W = g.shape
    ri = int(np.ceil(radius.max()))
    oy, ox = np.mgrid[-ri : ri + 1, -ri : ri + 1]
    ox, oy = ox.ravel().astype(np.float64), oy.ravel().astype(np.float64)
    base = np.rint(c0)
    px = base[:, :1] + ox[None]  # (N, M) pixel coordinates
    py = base[:, 1:] + oy[None]
    inside = (px >= 0) & (px <= W - 1) & (py >= 0) & (py <= H - 1)
    wgt = (((px - c0[:, :1]) ** 2 + (py - c0[:, 1:]) ** 2 <= radius[:, None] ** 2) & inside).astype(
        np.float64
    )
    img = g[np.clip(py, 0, H - 1).astype(np.intp), np.clip(px, 0, W - 1).astype(np.intp)]
    return _XJWindows(px, py, px - base[:, :1], py - base[:, 1:], wgt, img)


def _xj_model(p: NDArray[np.float64], sel: NDArray[np.intp], win: _XJWindows) -> tuple[NDArray, NDArray]:
    """Model grey levels ``(n, M)`` and Jacobian ``(n, M, 9)`` of the corners ``sel`` with
    parameters ``p (n, 9)``: x y, edge normal angles, blur, mean, contrast, shading."""
    from scipy.special import erf

    u = win.px[sel] - p[:, 0:1]
    v = win.py[sel] - p[:, 1:2]
    c1, s1 = np.cos(p[:, 2:3]), np.sin(p[:, 2:3])
    c2, s2 = np.cos(p[:, 3:4]), np.sin(p[:, 3:4])
    sig = p[:, 4:5]
    a1 = (c1 * u + s1 * v) * (_K_ERF / sig)
    a2 = (c2 * u + s2 * v) * (_K_ERF / sig)
    e1, e2 = erf(a1), erf(a2)
    g1 = _K_DER * np.exp(-a1 * a1) * (_K_ERF / sig)
    g2 = _K_DER * np.exp(-a2 * a2) * (_K_ERF / sig)
    A = p[:, 6:7]
    f = p[:, 5:6] + A * e1 * e2 + p[:, 7:8] * win.rel_x[sel] + p[:, 8:9] * win.rel_y[sel]
    J = np.empty(u.shape + (9,))
    J[..., 0] = -A * (g1 * c1 * e2 + e1 * g2 * c2)
    J[..., 1] = -A * (g1 * s1 * e2 + e1 * g2 * s2)
    J[..., 2] = A * g1 * (-s1 * u + c1 * v) * e2
    J[..., 3] = A * e1 * g2 * (-s2 * u + c2 * v)
    J[..., 4] = -A * (e1 * g2 * a2 + g1 * a1 * e2) / (_K_ERF / sig) / sig
    J[..., 5] = 1.0
    J[..., 6] = e1 * e2
    J[..., 7] = win.rel_x[sel]
    J[..., 8] = win.rel_y[sel]
    return f, J


def _xj_start(c0: NDArray, d_row: NDArray, d_col: NDArray, win: _XJWindows) -> NDArray[np.float64]:
    """Start: edges along the grid lines, 1 px blur, the linear terms by least squares."""
    n1 = np.arctan2(d_row[:, 0], -d_row[:, 1])  # normal of the edge along the row
    n2 = np.arctan2(d_col[:, 0], -d_col[:, 1])
    p = np.zeros((c0.shape[0], 9))
    p[:, 0:2], p[:, 2], p[:, 3], p[:, 4] = c0, n1, n2, 1.0
    _, J = _xj_model(p, np.arange(c0.shape[0]), win)
    lin = J[..., 5:9] * win.wgt[..., None]
    lhs = np.einsum("nmi,nmj->nij", lin, J[..., 5:9]) + _XJ_LINEAR_RIDGE * np.eye(4)
    p[:, 5:9] = np.linalg.solve(lhs, np.einsum("nmi,nm->ni", lin, win.img)[..., None])[..., 0]
    return p


def _xj_levenberg_marquardt(p: NDArray[np.float64], win: _XJWindows, max_iter: int) -> NDArray[np.float64]:
    """Levenberg-Marquardt on all corners at once, each with its own damping (``p`` updated)."""
    wgt, img = win.wgt, win.img
    f, J = _xj_model(p, np.arange(p.shape[0]), win)
    r = (f - img) * wgt
    cost = np.einsum("nm,nm->n", r, r)
    lam = np.full(p.shape[0], _LM_LAMBDA0)
    active = np.ones(p.shape[0], dtype=bool)
    for _ in range(int(max_iter)):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        Jw = J[idx] * wgt[idx, :, None]
        JtJ = np.einsum("nmi,nmj->nij", Jw, J[idx])
        grad = np.einsum("nmi,nm->ni", Jw, r[idx])
        diag = np.einsum("nii->ni", JtJ) + _LM_DIAG_FLOOR
        lhs = JtJ + (lam[idx, None] * diag)[:, :, None] * np.eye(9)[None]
        try:
            step = -np.linalg.solve(lhs, grad[..., None])[..., 0]
        except np.linalg.LinAlgError:  # pragma: no cover - damped systems are regular
            break
        trial = p[idx] + step
        trial[:, 4] = np.maximum(trial[:, 4], _XJ_MIN_BLUR)
        ft, Jt = _xj_model(trial, idx, win)
        rt = (ft - img[idx]) * wgt[idx]
        ct = np.einsum("nm,nm->n", rt, rt)
        better = ct < cost[idx]
        acc = idx[better]
        p[acc], f[acc], J[acc] = trial[better], ft[better], Jt[better]
        r[acc], cost[acc] = rt[better], ct[better]
        lam[acc] *= _LM_DOWN
        lam[idx[~better]] *= _LM_UP
        small = np.max(np.abs(step[:, :2]), axis=1) < _XJ_STEP_TOL
        active[idx[(better & small) | (lam[idx] > _LM_LAMBDA_MAX)]] = False
    return p


def refine_xjunction(
    gray: NDArray,
    corners: NDArray,
    board: tuple[int, int],
    *,
    radius_fraction: float = XJ_RADIUS_FRACTION,
    max_radius: float = XJ_MAX_RADIUS,
    max_iter: int = 40,
) -> NDArray[np.float64]:
    """Refine chessboard corners ``(N, 2)`` (OpenCV grid order) by fitting a blurred
    X-junction to the float grey levels ``gray`` (:func:`to_gray_float`): within
    ``radius_fraction`` x the corner spacing (<= ``max_radius`` px), ``I(p) = m + A erf(n1.(p
    - c) / (sqrt(2) s)) erf(n2.(p - c) / (sqrt(2) s)) + g.(p - p0)`` by Levenberg-Marquardt.
    Corners whose fit fails keep their input position.

    References
    ----------
    .. [1] S. Placht et al., "ROCHADE: Robust Checkerboard Advanced Detection for Camera
       Calibration", ECCV 2014 (saddle-point refinement of smoothed corners).
    .. [2] D. Chen, G. Zhang, "A new sub-pixel detector for X-corners in camera
       calibration targets", WSCG 2005.
    """
    cols, rows = _check_board(board)
    g = check_array(gray, "gray", ndim=2, dtype_kind="fu").astype(np.float64)
    c0 = check_array(corners, "corners", dtype_kind="fiu").reshape(-1, 2).astype(np.float64)
    if c0.shape[0] != cols * rows:
        raise InputError(
            f"corners: expected {cols * rows} corners for a {cols}x{rows} board, got {c0.shape[0]}"
        )
    d_row, d_col, spacing = _grid_directions(c0, (cols, rows))
    radius = np.clip(float(radius_fraction) * spacing, _XJ_MIN_RADIUS, max(float(max_radius), _XJ_MIN_RADIUS))
    win = _xj_windows(g, c0, radius)
    p = _xj_levenberg_marquardt(_xj_start(c0, d_row, d_col, win), win, max_iter)
    moved = np.linalg.norm(p[:, :2] - c0, axis=1)
    ok = (
        np.all(np.isfinite(p), axis=1)
        & (moved < _XJ_MAX_MOVE * spacing)
        & (p[:, 4] < radius)
        & (np.abs(p[:, 6]) > _XJ_MIN_CONTRAST)
    )
    if not ok.all():
        log.debug("x-junction fit failed for %d of %d corners", int((~ok).sum()), ok.size)
    return np.where(ok[:, None], p[:, :2], c0)


def load_image(path: str | Path) -> NDArray[np.uint8]:
    """Read an image file as RGB uint8 ``(H, W, 3)`` (grey files become 3 channels)."""
    import cv2

    p = check_file(path, "image")
    check_image_size(p)  # the pixel budget, from the header, before decoding
    data = np.fromfile(p, dtype=np.uint8)
    img = decode_image(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise InputError(f"{p}: not a readable image (expected PNG, JPEG, TIFF, ...)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB, dst=img)  # in place: one copy of a large image


def detect_corners(
    image: NDArray,
    board: tuple[int, int] = (9, 6),
    *,
    method: str = "xjunction",
    window: int | None = DEFAULT_WINDOW,
) -> NDArray[np.float64] | None:
    """A chessboard's inner corners ``(N, 2)`` float64 to sub-pixel accuracy, in canonical
    order, or None when the full board is not found.

    ``image``: one view ``(H, W[, 3])`` uint8 or float; ``board``: ``(cols, rows)`` inner
    corners (OpenCV ``patternSize``); ``method``: one of :data:`DETECTORS`; ``window``:
    ``cornerSubPix`` half-window, px (default ``WINDOW_FRACTION`` x the square size),
    always clipped to below half a square.
    """
    import cv2

    cols, rows = _check_board(board)
    check_choice(method, "method", DETECTORS)
    if window is not None and int(window) < 1:
        raise InputError(f"window: expected a half-window >= 1 pixel, got {window}")
    gray = to_gray(image)
    if min(gray.shape) < _MIN_IMAGE_PX:
        return None
    try:
        return _detect(gray, cols, rows, method, None if window is None else int(window), image)
    except cv2.error as exc:
        log.debug("OpenCV detector failed: %s", exc)
        return None


def _detection_copy(gray: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], float]:
    """The view the board is searched in and its scale: the view itself up to
    :data:`DETECT_MAX_PIXELS`, else an area-averaged copy of that size (corners are then
    refined at full resolution), so a huge image costs neither minutes nor gigabytes."""
    import cv2

    n = gray.shape[0] * gray.shape[1]
    if n <= DETECT_MAX_PIXELS:
        return gray, 1.0
    s = float(np.sqrt(DETECT_MAX_PIXELS / n))
    return cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_AREA), s


def _find(gray: NDArray[np.uint8], cols: int, rows: int, method: str) -> NDArray | None:
    """OpenCV's board search: ``(N, 1, 2)`` float32 corners or None."""
    import cv2

    if method == "sb":
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=flags)
        return corners if ok else None
    base = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    for flags in (base, base | cv2.CALIB_CB_FILTER_QUADS):
        ok, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
        if ok:
            return corners
    # the sector-based detector finds some boards the classic one misses
    ok, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
    return corners if ok else None


def _detect(
    gray: NDArray[np.uint8],
    cols: int,
    rows: int,
    method: str,
    window: int | None,
    image: NDArray,
) -> NDArray[np.float64] | None:
    import cv2

    small, scale = _detection_copy(gray)
    corners = _find(small, cols, rows, method)
    if corners is None or corners.reshape(-1, 2).shape[0] != cols * rows:
        return None
    if scale != 1.0:  # back to full-resolution pixel centres
        corners = ((corners.astype(np.float64) + 0.5) / scale - 0.5).astype(np.float32)
    if method != "sb" or scale != 1.0:
        c = corners.reshape(rows, cols, 2)
        sq = min(
            float(np.median(np.linalg.norm(np.diff(c, axis=1), axis=2))),
            float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=2))),
        )
        want = WINDOW_FRACTION * sq if window is None else window
        w = max(1, min(round(want), int(sq / 2) - 1))
        corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (w, w), (-1, -1), _subpix_criteria())
        if method == "xjunction":
            corners = _refine_xjunction_in(image, corners.reshape(-1, 2), (cols, rows), scale != 1.0)
    return canonical_order(corners.reshape(-1, 2).astype(np.float64), (cols, rows))


def _refine_xjunction_in(image: NDArray, corners: NDArray, board: tuple[int, int], crop: bool
                         ) -> NDArray[np.float64]:
    """:func:`refine_xjunction` on the float grey of ``image``; with ``crop``, of the
    board's bounding box only (plus the fit radius), which a huge view needs."""
    if not crop:
        return refine_xjunction(to_gray_float(image), corners, board)
    h, w = image.shape[:2]
    m = int(np.ceil(XJ_MAX_RADIUS)) + 2
    x0 = max(0, int(np.floor(corners[:, 0].min())) - m)
    y0 = max(0, int(np.floor(corners[:, 1].min())) - m)
    x1 = min(w, int(np.ceil(corners[:, 0].max())) + m + 1)
    y1 = min(h, int(np.ceil(corners[:, 1].max())) + m + 1)
    off = np.array([x0, y0], dtype=np.float64)
    fine = refine_xjunction(to_gray_float(image[y0:y1, x0:x1]), corners.astype(np.float64) - off, board)
    return fine + off


def _sharpness(gray: NDArray[np.uint8], board: tuple[int, int], corners: NDArray) -> float:
    import cv2

    try:
        stats, _ = cv2.estimateChessboardSharpness(
            gray, board, corners.astype(np.float32).reshape(-1, 1, 2)
        )
        return float(stats[0])
    except cv2.error:  # pragma: no cover - OpenCV refuses odd geometries
        return float("nan")


def _shot_views(img: NDArray, name: str, split: object | None) -> list[tuple[NDArray, str]]:
    """The (left, right) views of a side-by-side shot (default split: the two halves)."""
    check_array(img, name, ndim=(2, 3))
    sp = split
    if sp is None:
        h, w = img.shape[:2]
        if w % 2:
            raise InputError(f"{name}: width {w} is odd; give a PrismSplit for this sensor")
        sp = PrismSplit.side_by_side((w, h))
    if not isinstance(sp, PrismSplit):
        raise InputError(f"split: expected a PrismSplit, got {type(sp).__name__}")
    try:
        lv, rv = sp.split(img)
    except InputError as exc:
        raise InputError(f"{name}: {exc}") from exc
    return [(lv, name), (rv, name)]


def _detect_view(img: NDArray, name: str, view: str, board: tuple[int, int], method: str,
                 window: int | None) -> CornerDetection:
    corners = detect_corners(img, board, method=method, window=window)
    sharp = float("nan") if corners is None else _sharpness(to_gray(img), tuple(board), corners)
    log.debug("%s (%s): found=%s", name, view, corners is not None)
    return CornerDetection(
        source=name,
        view=view,
        found=corners is not None,
        n_corners=0 if corners is None else int(corners.shape[0]),
        sharpness=sharp,
        corners=corners,
    )


def _shot_items(images: Sequence[str | Path | NDArray], pairs: bool) -> list[str | Path | NDArray]:
    """The images as a list: at least one, and an even count in pairs mode."""
    items = list(images)
    if not items:
        raise InputError("images: expected at least one image, got none")
    if pairs and len(items) % 2:
        raise InputError(
            f"images: pairs mode expects left, right, left, right..., got an odd count ({len(items)})"
        )
    return items


def detect_views(
    images: Sequence[str | Path | NDArray],
    *,
    board: tuple[int, int] = (9, 6),
    pairs: bool = False,
    split: object | None = None,
    method: str = "xjunction",
    window: int | None = DEFAULT_WINDOW,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[tuple[CornerDetection, CornerDetection]], tuple[int, int]]:
    """Detect the board in both views of every shot.

    ``images``: side-by-side prism shots (cut by ``split``, a PrismSplit; default the two
    halves) or, with ``pairs``, separate views alternating left, right (OpenCV's
    ``stereo_calib.xml`` order); ``method``, ``window`` as :func:`detect_corners`;
    ``progress(done, total)`` after each shot. Returns one ``(left, right)`` detection
    per shot and the view size ``(width, height)``. Raises InputError for unreadable
    files, an odd count in pairs mode, or mixed view sizes.
    """
    _check_board(board)
    items = _shot_items(images, pairs)
    names = [str(it) if isinstance(it, str | Path) else f"<array {i}>" for i, it in enumerate(items)]

    def get(i: int) -> NDArray:
        it = items[i]
        return load_image(it) if isinstance(it, str | Path) else np.asarray(it)

    out: list[tuple[CornerDetection, CornerDetection]] = []
    view_size: tuple[int, int] | None = None
    first_name = ""
    n_shots = len(items) // 2 if pairs else len(items)
    for s in range(n_shots):
        if pairs:  # one view in memory at a time
            views = ((get(k), names[k]) for k in (2 * s, 2 * s + 1))
        else:
            views = iter(_shot_views(get(s), names[s], split))
        pair = []
        for view in ("left", "right"):
            img, name = next(views)
            check_array(img, name, ndim=(2, 3))
            size = (int(img.shape[1]), int(img.shape[0]))
            if view_size is None:
                view_size, first_name = size, name
            elif size != view_size:
                raise InputError(
                    f"{name}: view size {size[0]}x{size[1]} differs from {first_name} "
                    f"({view_size[0]}x{view_size[1]}); all images must have the same size"
                )
            pair.append(_detect_view(img, name, view, board, method, window))
            del img
        out.append((pair[0], pair[1]))
        if progress is not None:
            progress(s + 1, n_shots)
    if view_size is None:  # pragma: no cover - n_shots >= 1 always sets it
        raise InputError("images: nothing to detect")
    return out, view_size


#: Square-grid target: contours smaller than this (px^2) are noise, not squares.
_MIN_QUAD_AREA = 16
#: Polygon approximation tolerance, fraction of the perimeter: keeps a blurred square's
#: 4 corners while merging the pixel steps of its edges.
_QUAD_APPROX = 0.08
_HULL_APPROX = 0.05
#: A square's area may differ from the median of the largest ones by this factor either
#: way (perspective), and no more (text, specks, the page border).
_QUAD_AREA_RATIO = (0.3, 3.0)
#: Where a square's corners sit around its centre in grid units (squares half a cell wide).
_SQUARE_CORNER_OFFSETS = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) * 0.5


def _dark_quads(gray: NDArray[np.uint8], n: int) -> list[NDArray[np.float64]] | None:
    """The ``n`` dark convex quadrilaterals of similar area (Otsu threshold), or None."""
    import cv2

    _, bw = cv2.threshold(
        cv2.GaussianBlur(gray, (3, 3), 0), 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU
    )
    contours, _ = cv2.findContours(bw, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    quads = []
    for c in contours:
        area = cv2.contourArea(c)
        if area < _MIN_QUAD_AREA:
            continue
        approx = cv2.approxPolyDP(c, _QUAD_APPROX * cv2.arcLength(c, True), True)
        if len(approx) == 4 and cv2.isContourConvex(approx):
            quads.append((area, approx.reshape(4, 2).astype(np.float64)))
    if len(quads) < n:
        return None
    areas = np.array([a for a, _ in quads])
    med = np.median(np.sort(areas)[-n:])
    keep = [q for a, q in quads if _QUAD_AREA_RATIO[0] * med < a < _QUAD_AREA_RATIO[1] * med]
    return keep if len(keep) == n else None


def _grid_match(
    centres: NDArray[np.float64], cols: int, rows: int
) -> tuple[NDArray[np.intp], NDArray[np.float64], NDArray[np.float64]] | None:
    """Square index per grid cell (row-major), the cells' grid coordinates and the
    grid-to-image homography refined on all centres; None when ambiguous."""
    import cv2

    hull = cv2.convexHull(centres.astype(np.float32)).reshape(-1, 2)
    box = cv2.approxPolyDP(hull, _HULL_APPROX * cv2.arcLength(hull, True), True).reshape(-1, 2)
    if box.shape[0] != 4:
        return None
    # image corners of the grid: top-left, top-right, bottom-right, bottom-left
    s = box.sum(axis=1)
    d = box[:, 0] - box[:, 1]
    img_corners = np.array(
        [box[np.argmin(s)], box[np.argmax(d)], box[np.argmax(s)], box[np.argmin(d)]]
    )
    grid_corners = np.array(
        [[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], dtype=np.float64
    )
    H, _ = cv2.findHomography(grid_corners, img_corners.astype(np.float64))
    if H is None:
        return None
    gc, gr = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    g = np.stack([gc.ravel(), gr.ravel()], axis=1)
    pred = cv2.perspectiveTransform(g[None], H)[0]
    match = np.argmin(np.linalg.norm(pred[:, None] - centres[None], axis=2), axis=1)
    if len(set(match.tolist())) != cols * rows:
        return None
    H, _ = cv2.findHomography(g, centres[match])  # refine with all centres
    return match, g, H


def detect_square_grid(
    image: NDArray,
    grid: tuple[int, int] = (8, 8),
    *,
    window: int = 5,
) -> NDArray[np.float64] | None:
    """Corners ``(4 * cols * rows, 2)`` float64 of a target of separate dark squares
    (Zhang's pattern, ``grid = (cols, rows)``), square by square from the image top, each
    TL, TR, BR, BL (target within 45 deg of upright), refined by ``cornerSubPix`` with
    half-window ``window`` (below half the gap); None when not found.

    References
    ----------
    .. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11)
       (2000): the pattern of separate squares used there.
    """
    import cv2

    cols, rows = _check_board(grid)
    gray = to_gray(image)
    n = cols * rows
    keep = _dark_quads(gray, n)
    if keep is None:
        return None
    centres = np.array([q.mean(axis=0) for q in keep])
    found = _grid_match(centres, cols, rows)
    if found is None:
        return None
    match, g, H = found
    out = np.zeros((n, 4, 2))
    for k in range(n):
        quad = keep[match[k]]
        # order the quad's corners like the grid directions (TL, TR, BR, BL)
        want = cv2.perspectiveTransform((g[k] + _SQUARE_CORNER_OFFSETS)[None], H)[0]
        idx = np.argmin(np.linalg.norm(want[:, None] - quad[None], axis=2), axis=1)
        if len(set(idx.tolist())) != 4:
            return None
        out[k] = quad[idx]
    pts = out.reshape(-1, 1, 2).astype(np.float32)
    w = max(1, int(window))
    pts = cv2.cornerSubPix(gray, pts, (w, w), (-1, -1), _subpix_criteria())
    return pts.reshape(-1, 2).astype(np.float64)
