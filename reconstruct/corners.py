"""Chessboard corner detection with a canonical, view-consistent corner order.

Corners are found in each view of a side-by-side prism shot (cut with a
:class:`~prism3d.capture.rig.PrismSplit`) or in separate left/right images.
Two OpenCV detectors are available:

``"classic"`` (default)
    ``cv2.findChessboardCorners`` (falling back to ``FILTER_QUADS`` and to the
    sector-based detector for finding only) followed by ``cv2.cornerSubPix`` with a
    search window of half-size ``window`` pixels (``winSize=(window, window)``, a
    ``2 window + 1`` square); by default the half-window is 0.2 x the board's square
    size in pixels (7 px for 35 px squares), clipped to below half a square.
``"sb"``
    ``cv2.findChessboardCornersSB`` (sector-based, with ``CALIB_CB_ACCURACY``).

Measured (``benchmarks/bench_calibrate.py``, numbers from one run):

* Virtual paper rig (``prism3d simulate calib``, 5 shots, 10 views, squares ~80 px),
  RMS corner error against the true corners: classic half-window 3: 0.142 px,
  5: 0.110, 7: 0.094, 11: 0.083, 0.2 x square (~16): 0.076 px; SB: 0.145 px and it
  missed 7 of the 10 views.
* OpenCV's real 9x6 stereo set (13 pairs, 640x480, squares 31-45 px), RMS after our
  adjustment with k1 k2, each camera alone (left / right): classic 3: 0.240 / 0.297,
  5: 0.204 / 0.212, 7: 0.191 / 0.194, 11: 0.418 / 0.461, 0.2 x square: 0.189 / 0.195;
  SB: 0.254 / 0.247. (0.25 x square broke down on the right camera, 0.226.)

The square-proportional window is the default: best on the virtual rig and on the
real set. ``cv2.stereoCalibrate`` on the same corners gives the same joint RMS as our
adjustment (0.2085 px).

Corner order: OpenCV may return the grid in any of its symmetric orders (reversed
for a board turned by 180 degrees; for square boards also transposed). We
canonicalise: corner 0 is the grid corner from which rows run along +x and
columns along +y in the image (first corner nearest the image top-left for an
upright board), the same rule in both views. Where the rule is ambiguous (board
near 45 or 90 degrees), :func:`grid_symmetries` lists the alternatives and the
calibration resolves the order between views by the stereo geometry.

References
----------
.. [1] A. Geiger, F. Moosmann, O. Car, B. Schuster, "Automatic camera and range sensor
   calibration using a single shot", ICRA 2012 (sector-based corner ideas).
.. [2] P. Duda, "Accurate detection and localization of checkerboard corners for
   calibration", BMVC 2018 (``findChessboardCornersSB``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_choice, check_file
from prism3d.errors import InputError

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
    "to_gray",
]

log = logging.getLogger(__name__)

#: Available detector names.
DETECTORS = ("classic", "sb")
#: Default cornerSubPix half-window as a fraction of the board's square size in
#: pixels (see the module docstring for the numbers); ``window=None`` uses it.
WINDOW_FRACTION = 0.2
DEFAULT_WINDOW: int | None = None


@dataclass(frozen=True, eq=False)
class CornerDetection:
    """What was found in one view of one image.

    Attributes
    ----------
    source : str
        Image path (or ``"<array i>"`` for in-memory images).
    view : str
        ``"left"`` or ``"right"``.
    found : bool
        Whether the full board was found.
    n_corners : int
        Number of corners returned (``board[0] * board[1]`` when found, else 0).
    sharpness : float
        Mean edge width around the corners in pixels
        (``cv2.estimateChessboardSharpness``; lower is sharper; NaN when not found).
    corners : (N, 2) float64 or None
        Sub-pixel corners in canonical order, view-image pixels.
    """

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
    """Reorder a detected grid so rows run along +x and columns along +y.

    Parameters
    ----------
    corners : (N, 2) float
        Corners in any of the grid's symmetric orders (OpenCV output).
    board : (cols, rows)
        Inner-corner counts.

    Returns
    -------
    (N, 2) float64
        The same corners in canonical order.
    """
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
        return cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)


def load_image(path: str | Path) -> NDArray[np.uint8]:
    """Read an image file as RGB uint8 ``(H, W, 3)`` (grey files become 3 channels)."""
    import cv2

    p = check_file(path, "image")
    data = np.fromfile(p, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise InputError(f"{p}: not a readable image (expected PNG, JPEG, TIFF, ...)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def detect_corners(
    image: NDArray,
    board: tuple[int, int] = (9, 6),
    *,
    method: str = "classic",
    window: int | None = DEFAULT_WINDOW,
) -> NDArray[np.float64] | None:
    """Find a chessboard's inner corners to sub-pixel accuracy.

    Parameters
    ----------
    image : (H, W[, 3]) uint8 or float32
        One view (RGB or grey).
    board : (cols, rows)
        Inner corners per row and per column (OpenCV ``patternSize``).
    method : {"classic", "sb"}
        Detector (see the module docstring for measured accuracy).
    window : int, optional
        ``cornerSubPix`` half-window for ``"classic"``; default 0.2 x the square size
        in pixels. Always clipped to below half a square.

    Returns
    -------
    (N, 2) float64 or None
        Corners in canonical order, or None when the full board is not found.
    """
    import cv2

    cols, rows = _check_board(board)
    check_choice(method, "method", DETECTORS)
    if window is not None and int(window) < 1:
        raise InputError(f"window: expected a half-window >= 1 pixel, got {window}")
    gray = to_gray(image)
    if min(gray.shape) < 16:  # OpenCV's detectors fail on tiny images
        return None
    try:
        return _detect(gray, cols, rows, method, None if window is None else int(window))
    except cv2.error as exc:
        log.debug("OpenCV detector failed: %s", exc)
        return None


def _detect(
    gray: NDArray[np.uint8], cols: int, rows: int, method: str, window: int | None
) -> NDArray[np.float64] | None:
    import cv2

    if method == "sb":
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=flags)
    else:
        ok, corners = False, None
        base = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        for flags in (base, base | cv2.CALIB_CB_FILTER_QUADS):
            ok, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
            if ok:
                break
        if not ok:  # the sector-based detector finds some boards the classic one misses
            ok, corners = cv2.findChessboardCornersSB(
                gray, (cols, rows), flags=cv2.CALIB_CB_NORMALIZE_IMAGE
            )
        if ok:
            c = corners.reshape(rows, cols, 2)
            sq = min(
                float(np.median(np.linalg.norm(np.diff(c, axis=1), axis=2))),
                float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=2))),
            )
            want = WINDOW_FRACTION * sq if window is None else window
            w = max(1, min(round(want), int(sq / 2) - 1))
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
            corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (w, w), (-1, -1), crit)
    if not ok or corners is None or corners.reshape(-1, 2).shape[0] != cols * rows:
        return None
    return canonical_order(corners.reshape(-1, 2).astype(np.float64), (cols, rows))


def _sharpness(gray: NDArray[np.uint8], board: tuple[int, int], corners: NDArray) -> float:
    import cv2

    try:
        stats, _ = cv2.estimateChessboardSharpness(
            gray, board, corners.astype(np.float32).reshape(-1, 1, 2)
        )
        return float(stats[0])
    except cv2.error:  # pragma: no cover - OpenCV refuses odd geometries
        return float("nan")


def detect_views(
    images: Sequence[str | Path | NDArray],
    *,
    board: tuple[int, int] = (9, 6),
    pairs: bool = False,
    split: object | None = None,
    method: str = "classic",
    window: int | None = DEFAULT_WINDOW,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[tuple[CornerDetection, CornerDetection]], tuple[int, int]]:
    """Detect the board in both views of every shot.

    Parameters
    ----------
    images : sequence of paths or (H, W[, 3]) arrays
        Side-by-side prism shots, or (``pairs=True``) separate images alternating
        left, right, left, right... (OpenCV's ``stereo_calib.xml`` order).
    board : (cols, rows)
        Inner corners.
    pairs : bool
        Separate left/right images instead of side-by-side shots.
    split : PrismSplit, optional
        Where the views sit on the sensor (shots only); default: left and right halves.
    method, window
        See :func:`detect_corners`.
    progress : callable(done, total), optional
        Called after each image.

    Returns
    -------
    detections : list of (left, right) CornerDetection
        One pair per shot.
    view_size : (int, int)
        ``(width, height)`` of each view.

    Raises
    ------
    InputError
        Unreadable files, an odd number of images in pairs mode, mixed image sizes.
    """
    from prism3d.capture.rig import PrismSplit

    _check_board(board)
    items = list(images)
    if not items:
        raise InputError("images: expected at least one image, got none")
    if pairs and len(items) % 2:
        raise InputError(
            f"images: pairs mode expects left, right, left, right..., got an odd count ({len(items)})"
        )
    names = [
        str(it) if isinstance(it, str | Path) else f"<array {i}>" for i, it in enumerate(items)
    ]

    def get(i: int) -> NDArray:
        it = items[i]
        return load_image(it) if isinstance(it, str | Path) else np.asarray(it)

    out: list[tuple[CornerDetection, CornerDetection]] = []
    view_size: tuple[int, int] | None = None
    first_name = ""
    n_shots = len(items) // 2 if pairs else len(items)
    for s in range(n_shots):
        if pairs:
            views = [(get(2 * s), names[2 * s]), (get(2 * s + 1), names[2 * s + 1])]
        else:
            img = get(s)
            check_array(img, names[s], ndim=(2, 3))
            sp = split
            if sp is None:
                h, w = img.shape[:2]
                if w % 2:
                    raise InputError(
                        f"{names[s]}: width {w} is odd; give a PrismSplit for this sensor"
                    )
                sp = PrismSplit.side_by_side((w, h))
            if not isinstance(sp, PrismSplit):
                raise InputError(f"split: expected a PrismSplit, got {type(sp).__name__}")
            try:
                lv, rv = sp.split(img)
            except InputError as exc:
                raise InputError(f"{names[s]}: {exc}") from exc
            views = [(lv, names[s]), (rv, names[s])]
        pair = []
        for (img, name), view in zip(views, ("left", "right"), strict=True):
            check_array(img, name, ndim=(2, 3))
            size = (int(img.shape[1]), int(img.shape[0]))
            if view_size is None:
                view_size, first_name = size, name
            elif size != view_size:
                raise InputError(
                    f"{name}: view size {size[0]}x{size[1]} differs from {first_name} "
                    f"({view_size[0]}x{view_size[1]}); all images must have the same size"
                )
            corners = detect_corners(img, board, method=method, window=window)
            sharp = (
                float("nan") if corners is None else _sharpness(to_gray(img), tuple(board), corners)
            )
            pair.append(
                CornerDetection(
                    source=name,
                    view=view,
                    found=corners is not None,
                    n_corners=0 if corners is None else int(corners.shape[0]),
                    sharpness=sharp,
                    corners=corners,
                )
            )
            log.debug("%s (%s): found=%s", name, view, corners is not None)
        out.append((pair[0], pair[1]))
        if progress is not None:
            progress(s + 1, n_shots)
    if view_size is None:  # pragma: no cover - n_shots >= 1 always sets it
        raise InputError("images: nothing to detect")
    return out, view_size


def detect_square_grid(
    image: NDArray,
    grid: tuple[int, int] = (8, 8),
    *,
    window: int = 5,
) -> NDArray[np.float64] | None:
    """Corners of a target made of separate dark squares (Zhang's calibration pattern).

    Threshold (Otsu) -> contours -> convex quadrilaterals of similar area -> the
    ``cols x rows`` squares ordered by a homography fitted to their centres ->
    ``cv2.cornerSubPix`` on every square corner.

    Parameters
    ----------
    image : (H, W[, 3]) uint8
        The view.
    grid : (cols, rows)
        Squares per row and per column.
    window : int
        ``cornerSubPix`` half-window (keep it below half the gap between squares).
        On Zhang's five images (squares ~30 px, gaps ~23 px), calibrating from these
        corners gives alpha 831.43, beta 831.79, k1 -0.2299, RMS 0.41 px with 5
        (2: 831.25 / RMS 0.51; 4: 831.66 / 0.42; 6: 831.38 / 0.40), against Zhang's
        832.50, 832.53, -0.2286 from his own corners (RMS 0.34); our corners differ
        from his by 0.25-0.33 px RMS.

    Returns
    -------
    (4 * cols * rows, 2) float64 or None
        Square by square, rows from the image top, squares left to right, and for each
        square its corners top-left, top-right, bottom-right, bottom-left (the target
        is assumed roughly upright: no more than 45 degrees of in-plane rotation).
        None when the grid is not found.

    References
    ----------
    .. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11)
       (2000): the pattern of separate squares used there.
    """
    import cv2

    cols, rows = _check_board(grid)
    gray = to_gray(image)
    n = cols * rows
    _, bw = cv2.threshold(
        cv2.GaussianBlur(gray, (3, 3), 0), 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU
    )
    contours, _ = cv2.findContours(bw, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    quads = []
    for c in contours:
        area = cv2.contourArea(c)
        if area < 16:
            continue
        approx = cv2.approxPolyDP(c, 0.08 * cv2.arcLength(c, True), True)
        if len(approx) == 4 and cv2.isContourConvex(approx):
            quads.append((area, approx.reshape(4, 2).astype(np.float64)))
    if len(quads) < n:
        return None
    areas = np.array([a for a, _ in quads])
    med = np.median(np.sort(areas)[-n:])
    keep = [q for a, q in quads if 0.3 * med < a < 3.0 * med]
    if len(keep) != n:
        return None
    centres = np.array([q.mean(axis=0) for q in keep])
    hull = cv2.convexHull(centres.astype(np.float32)).reshape(-1, 2)
    box = cv2.approxPolyDP(hull, 0.05 * cv2.arcLength(hull, True), True).reshape(-1, 2)
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
    dist = np.linalg.norm(pred[:, None] - centres[None], axis=2)
    match = np.argmin(dist, axis=1)
    if len(set(match.tolist())) != n:
        return None
    H, _ = cv2.findHomography(g, centres[match])  # refine with all centres
    out = np.zeros((n, 4, 2))
    offs = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) * 0.5
    for k in range(n):
        quad = keep[match[k]]
        # order the quad's corners like the grid directions (TL, TR, BR, BL)
        want = cv2.perspectiveTransform((g[k] + offs)[None], H)[0]
        idx = np.argmin(np.linalg.norm(want[:, None] - quad[None], axis=2), axis=1)
        if len(set(idx.tolist())) != 4:
            return None
        out[k] = quad[idx]
    pts = out.reshape(-1, 1, 2).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    w = max(1, int(window))
    pts = cv2.cornerSubPix(gray, pts, (w, w), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(np.float64)
