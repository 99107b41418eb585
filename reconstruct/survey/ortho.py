"""A true orthophoto at the photographs' own ground sample distance.

Every ground cell is coloured from the frame that sees it most directly (the smallest
horizontal distance from the camera centre, i.e. the least off-nadir ray) among the frames
in which it is not hidden, found through the DSM. The DSM's holes inside the covered
area (dark cars, shadows, uniform asphalt) are filled by interpolation first, so the
mosaic has no holes inside its coverage; a quality raster says which cells stood on a
measured surface (1) and which on an interpolated one (2); 0 is outside the coverage. A
pocket inside the coverage that no photograph sees (a gap between neighbouring frames'
footprints) is coloured from around it and marked 3.

Occlusion: each frame gets a z-buffer of the filled DSM at roughly the DSM's cell; a cell
is hidden in a frame when it lies farther than the z-buffer there by more than
``OCCLUSION_TOLERANCE_CELLS`` DSM cells (plus 1 % of the range).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from prism3d.capture.rig import CameraModel
from prism3d.errors import InputError
from prism3d.io.images import read_image

__all__ = ["Orthophoto", "fill_dsm", "photo_gsd", "true_orthophoto"]

#: Cells of the orthophoto processed at once (rows and columns of a tile).
TILE = 1024
#: How much farther than a frame's z-buffer a cell may lie and still be seen, in DSM cells.
OCCLUSION_TOLERANCE_CELLS = 3.0
#: The most orthophoto cells made (2 GB of RGBA): a finer GSD over a larger area is refused.
MAX_ORTHO_CELLS = 500_000_000


#: ENU (x, y) of the centres of an orthophoto's cells ``[r0, r1) x [c0, c1)``.
CellCentres = Callable[[int, int, int, int], tuple[NDArray, NDArray]]


@dataclass(frozen=True)
class Orthophoto:
    """``rgba`` (H, W, 4) uint8 (alpha 0 outside the coverage), ``quality`` (H, W) uint8
    (0 outside, 1 measured surface, 2 interpolated surface, 3 colour carried in: no
    photograph sees the cell), north-west corner, ``gsd``
    (m), and which frame coloured how many cells."""

    rgba: NDArray[np.uint8]
    quality: NDArray[np.uint8]
    west: float
    north: float
    gsd: float
    cells_per_frame: dict[int, int]


def fill_dsm(dsm: NDArray) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The DSM with its holes inside the coverage filled (OpenCV's fast-marching inpaint),
    and the coverage: measured cells and every hole they enclose."""
    d = np.asarray(dsm, dtype=np.float32)
    valid = np.isfinite(d)
    if not valid.any():
        raise InputError("orthophoto: the DSM has no height at all")
    coverage = ndimage.binary_fill_holes(ndimage.binary_closing(valid, iterations=2)) | valid
    holes = coverage & ~valid
    if not holes.any():
        return np.where(valid, d, np.nan).astype(np.float32), coverage
    base = float(np.nanmedian(d))
    src = np.where(valid, d - base, 0.0).astype(np.float32)
    filled = cv2.inpaint(src, holes.astype(np.uint8), 3, cv2.INPAINT_TELEA) + base
    return np.where(coverage, filled, np.nan).astype(np.float32), coverage


def photo_gsd(T_enu_cam: Sequence[NDArray], fx: float, ground_z: float) -> float:
    """The photographs' ground sample distance: the median camera height above
    ``ground_z`` over the focal length (m per pixel at full resolution)."""
    h = [float(T[2, 3]) - ground_z for T in T_enu_cam]
    h = [v for v in h if v > 0]
    if not h:
        raise InputError("orthophoto: no camera is above the ground")
    return float(np.median(h)) / float(fx)


def _zbuffer(cam: CameraModel, T_cam_enu: NDArray, P: NDArray, step: float) -> tuple[NDArray[np.float32], float]:
    """Nearest depth of the points ``P`` (n, 3) in a grid of ``step`` px over the image."""
    pc = P @ T_cam_enu[:3, :3].T + T_cam_enu[:3, 3]
    z = pc[:, 2]
    ok = z > 0
    uv = cam.project(pc[ok])
    w, h = cam.size
    W, H = int(math.ceil(w / step)) + 1, int(math.ceil(h / step)) + 1
    c = np.floor(uv[:, 0] / step + 0.5).astype(np.int64)
    r = np.floor(uv[:, 1] / step + 0.5).astype(np.int64)
    inside = (c >= 0) & (c < W) & (r >= 0) & (r < H)
    zb = np.full(H * W, np.inf, dtype=np.float64)
    np.minimum.at(zb, r[inside] * W + c[inside], z[ok][inside])
    zb = zb.reshape(H, W)
    # cells a point did not land in take their neighbours' nearest depth
    zb = np.minimum(zb, ndimage.minimum_filter(zb, size=3, mode="nearest"))
    return zb.astype(np.float32), step


class _Frames:
    """Full-resolution frames read on first use, the most recent few kept."""

    def __init__(self, paths: Sequence[str], keep: int = 3) -> None:
        self.paths, self.keep = list(paths), keep
        self.cache: dict[int, NDArray[np.uint8]] = {}

    def get(self, k: int) -> NDArray[np.uint8]:
        if k not in self.cache:
            if len(self.cache) >= self.keep:
                self.cache.pop(next(iter(self.cache)))
            img = read_image(self.paths[k])
            self.cache[k] = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
        return self.cache[k]


def _sample(img: NDArray[np.uint8], x: NDArray, y: NDArray) -> NDArray[np.uint8]:
    """Bilinear samples (n, 3) of ``img`` at (x, y): OpenCV's remap on the points laid out
    as rows of 1024 (its maps are limited to 32767 a side)."""
    n = len(x)
    w = 1024
    rows = -(-n // w)
    mx = np.zeros(rows * w, dtype=np.float32)
    my = np.zeros(rows * w, dtype=np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(img, mx.reshape(rows, w), my.reshape(rows, w), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * w, -1)[:n]


def true_orthophoto(dsm: NDArray, west: float, north: float, cell: float, frames: Sequence[tuple[str, NDArray]],
                    K: NDArray, dist: NDArray, size: tuple[int, int], *, gsd: float | None = None,
                    on_map: Callable[[float], tuple[tuple[float, float, int, int], CellCentres]] | None = None,
                    progress: Callable[[int, int, str], None] | None = None) -> Orthophoto:
    """The orthophoto over a DSM (row 0 north; cell (r, c) centred at ``west + (c + .5)
    cell``, ``north - (r + .5) cell``; NaN holes) from ``frames`` (image path,
    ``T_enu_cam``) of one camera (``K``, ``dist`` OpenCV, full-resolution ``size``) at
    ``gsd`` (default :func:`photo_gsd`). The DSM and poses are in the local ENU frame;
    the orthophoto is on the DSM's own grid, or with ``on_map`` (given the GSD: the map
    grid's west, north, rows, columns and the ENU centres of its cells) on a map grid."""
    filled, coverage = fill_dsm(dsm)
    measured = np.isfinite(np.asarray(dsm, dtype=np.float32))
    # occlusion and the surface each cell stands on from the 3 x 3 median: isolated
    # mismatched cells would hide the roofs around them
    filled = np.where(coverage, ndimage.median_filter(np.nan_to_num(filled, nan=float(np.nanmedian(filled))), size=3),
                      np.nan).astype(np.float32)
    cam = CameraModel(np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64), tuple(size))
    T_cam = [np.linalg.inv(np.asarray(T, dtype=np.float64)) for _, T in frames]
    ground_z = float(np.nanmedian(filled))
    g = photo_gsd([np.asarray(T) for _, T in frames], cam.fx, ground_z) if gsd is None else float(gsd)
    if not (math.isfinite(g) and g > 0):
        raise InputError(f"ortho GSD: expected > 0 m, got {g}")
    H0, W0 = filled.shape
    Wo, Ho = max(1, int(round(W0 * cell / g))), max(1, int(round(H0 * cell / g)))
    if Wo * Ho > MAX_ORTHO_CELLS:
        raise InputError(f"ortho GSD: {g:.4g} m over {W0 * cell:.0f} x {H0 * cell:.0f} m is {Wo * Ho:,} cells, "
                         f"more than {MAX_ORTHO_CELLS:,}; give a coarser --ortho-gsd")
    ow, on = float(west), float(north)
    if on_map is None:
        def centres(r0: int, r1: int, c0: int, c1: int) -> tuple[NDArray, NDArray]:
            X, Y = np.meshgrid(west + (np.arange(c0, c1) + 0.5) * g, north - (np.arange(r0, r1) + 0.5) * g)
            return X, Y
    else:
        (ow, on, Ho, Wo), centres = on_map(g)
    rr, cc = np.nonzero(coverage)
    P = np.c_[west + (cc + 0.5) * cell, north - (rr + 0.5) * cell, filled[rr, cc]]
    zstep = max(1.0, cell / g)  # one z-buffer cell per DSM cell, in frame pixels
    boxes = _frame_boxes(cam, [np.asarray(T, dtype=np.float64) for _, T in frames], float(np.nanmin(filled)),
                         float(np.nanmax(filled)), 2.0 * cell)
    zbufs = [_zbuffer(cam, Tc, P[_rows_in(rr, cc, box, west, north, cell)], zstep) for Tc, box in zip(T_cam, boxes)]
    cam_xy = np.array([np.asarray(T, dtype=np.float64)[:3, 3] for _, T in frames])
    imgs = _Frames([p for p, _ in frames])
    rgba = np.zeros((Ho, Wo, 4), dtype=np.uint8)
    quality = np.zeros((Ho, Wo), dtype=np.uint8)
    used: dict[int, int] = {}
    tiles = [(r0, c0) for r0 in range(0, Ho, TILE) for c0 in range(0, Wo, TILE)]
    for t, (r0, c0) in enumerate(tiles):
        r1, c1 = min(Ho, r0 + TILE), min(Wo, c0 + TILE)
        X, Y = centres(r0, r1, c0, c1)
        seeing = [k for k, b in enumerate(boxes) if b is None or not (
            X.max() < b[0] or X.min() > b[1] or Y.max() < b[2] or Y.min() > b[3])]
        _ortho_tile(r0, c0, r1, c1, X, Y, west, north, cell, filled, coverage,
                    measured, cam, T_cam, zbufs, cam_xy, imgs, rgba, quality, used, seeing)
        if progress:
            progress(t + 1, len(tiles), "orthophoto")
    _fill_pockets(rgba, quality)
    return Orthophoto(rgba, quality, ow, on, g, used)


#: Margin around an unseen pocket the colour is carried in from, orthophoto cells.
POCKET_MARGIN = 4


def _fill_pockets(rgba: NDArray[np.uint8], quality: NDArray[np.uint8]) -> None:
    """Cells inside the coverage that no photograph sees (a gap between the footprints of
    neighbouring frames, enclosed by cells they do see) coloured from around them
    (OpenCV's fast-marching inpaint), in place; ``quality`` 3 marks them."""
    seen = rgba[..., 3] > 0
    pockets = ndimage.binary_fill_holes(seen) & ~seen
    if not pockets.any():
        return
    lab, n = ndimage.label(pockets)
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        r0, r1 = max(0, sl[0].start - POCKET_MARGIN), min(rgba.shape[0], sl[0].stop + POCKET_MARGIN)
        c0, c1 = max(0, sl[1].start - POCKET_MARGIN), min(rgba.shape[1], sl[1].stop + POCKET_MARGIN)
        m = lab[r0:r1, c0:c1] == k
        rgb = np.ascontiguousarray(rgba[r0:r1, c0:c1, :3])
        rgba[r0:r1, c0:c1, :3] = np.where(m[..., None], cv2.inpaint(rgb, m.astype(np.uint8), 3, cv2.INPAINT_TELEA), rgb)
        rgba[r0:r1, c0:c1, 3][m] = 255
        quality[r0:r1, c0:c1][m] = 3


def _frame_boxes(cam: CameraModel, T_enu_cam: Sequence[NDArray], zmin: float, zmax: float, margin: float
                 ) -> list[tuple[float, float, float, float] | None]:
    """Per frame, an ENU box (x0, x1, y0, y1) holding every ground point between heights
    ``zmin`` and ``zmax`` the frame can see: its border's rays meet both planes (the
    pyramid's sections between lie inside), widened by 10 % and ``margin``; None when a
    ray does not reach them (an oblique frame: no bound). Tiles and z-buffers then look at
    the frames that can see them only, so the orthophoto's cost grows with the area, not
    with the area times the frames."""
    w, h = cam.size
    t = np.linspace(0.0, 1.0, 9)
    border = np.r_[np.c_[t * (w - 1), 0 * t], np.c_[t * (w - 1), 0 * t + (h - 1)], np.c_[0 * t, t * (h - 1)],
                   np.c_[0 * t + (w - 1), t * (h - 1)]]
    rays = cam.pixel_rays(border)
    out: list[tuple[float, float, float, float] | None] = []
    for T in T_enu_cam:
        d = rays @ np.asarray(T)[:3, :3].T
        C = np.asarray(T)[:3, 3]
        pts = []
        for z in (zmin, zmax):
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (z - C[2]) / d[:, 2]
            if not np.isfinite(s).all() or (s <= 0).any():
                pts = []
                break
            pts.append(C + s[:, None] * d)
        if not pts:
            out.append(None)
            continue
        p = np.vstack(pts)
        (x0, y0), (x1, y1) = p[:, :2].min(axis=0), p[:, :2].max(axis=0)
        pad = margin + 0.1 * max(x1 - x0, y1 - y0)
        out.append((float(x0 - pad), float(x1 + pad), float(y0 - pad), float(y1 + pad)))
    return out


def _rows_in(rr: NDArray, cc: NDArray, box: tuple[float, float, float, float] | None, west: float, north: float,
             cell: float) -> NDArray | slice:
    """Which of the coverage cells (``rr``, ``cc`` in row-major order) lie in ``box``."""
    if box is None:
        return slice(None)
    r0 = int(np.searchsorted(rr, int(np.floor((north - box[3]) / cell)), side="left"))
    r1 = int(np.searchsorted(rr, int(np.ceil((north - box[2]) / cell)), side="right"))
    c = cc[r0:r1]
    keep = (c >= np.floor((box[0] - west) / cell)) & (c <= np.ceil((box[1] - west) / cell))
    return r0 + np.flatnonzero(keep)


def _ortho_tile(r0: int, c0: int, r1: int, c1: int, X: NDArray, Y: NDArray, west: float, north: float, cell: float,
                filled: NDArray, coverage: NDArray, measured: NDArray, cam: CameraModel, T_cam: list[NDArray],
                zbufs: list, centres: NDArray, imgs: _Frames, rgba: NDArray, quality: NDArray,
                used: dict[int, int], seeing: list[int]) -> None:
    """Colour one tile of the orthophoto in place (module docstring); ``X``, ``Y`` the ENU
    centres of its cells; ``seeing`` the frames that may see it."""
    # DSM coordinates of these cells (fractional; cell centres at integer + 0.5)
    fc = ((X - west) / cell - 0.5).astype(np.float32)
    fr = ((north - Y) / cell - 0.5).astype(np.float32)
    Z = cv2.remap(np.nan_to_num(filled, nan=0.0), fc, fr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ci = np.clip(np.round(fc).astype(np.int64), 0, filled.shape[1] - 1)
    ri = np.clip(np.round(fr).astype(np.int64), 0, filled.shape[0] - 1)
    cov = coverage[ri, ci]
    if not cov.any():
        return
    P = np.stack([X[cov], Y[cov], Z[cov].astype(np.float64)], axis=1)
    n = len(P)
    best = np.full(n, -1, dtype=np.int64)
    best_d = np.full(n, np.inf)
    near = np.full(n, -1, dtype=np.int64)  # the most direct frame holding the cell, seen or not
    near_d = np.full(n, np.inf)
    uv_all: dict[int, NDArray] = {}
    for k in seeing:
        Tc = T_cam[k]
        pc = P @ Tc[:3, :3].T + Tc[:3, 3]
        z = pc[:, 2]
        uv = np.full((n, 2), np.nan)
        front = z > 0
        uv[front] = cam.project(pc[front])
        w, h = cam.size
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        zb, step = zbufs[k]
        zr = np.clip(np.floor(uv[inside, 1] / step + 0.5).astype(np.int64), 0, zb.shape[0] - 1)
        zc = np.clip(np.floor(uv[inside, 0] / step + 0.5).astype(np.int64), 0, zb.shape[1] - 1)
        seen = np.zeros(n, dtype=bool)
        seen[inside] = z[inside] <= zb[zr, zc] + OCCLUSION_TOLERANCE_CELLS * cell + 0.01 * z[inside]
        d = np.hypot(P[:, 0] - centres[k, 0], P[:, 1] - centres[k, 1])
        better = seen & (d < best_d)
        best[better], best_d[better] = k, d[better]
        closer = inside & (d < near_d)
        near[closer], near_d[closer] = k, d[closer]
        uv_all[k] = uv
    # hidden in every frame (a spike of the DSM in front of it): the most direct frame anyway
    best = np.where(best >= 0, best, near)
    out = np.zeros((n, 4), dtype=np.uint8)
    for k in np.unique(best[best >= 0]):
        sel = np.flatnonzero(best == k)
        uv = uv_all[int(k)][sel]
        img = imgs.get(int(k))
        u0, v0 = (max(0, int(math.floor(a)) - 1) for a in uv.min(axis=0))
        u1, v1 = int(math.ceil(uv[:, 0].max())) + 2, int(math.ceil(uv[:, 1].max())) + 2
        crop = img[v0:v1, u0:u1]
        out[sel, :3] = _sample(crop, uv[:, 0] - u0, uv[:, 1] - v0)
        out[sel, 3] = 255
        used[int(k)] = used.get(int(k), 0) + len(sel)
    tile = np.zeros((r1 - r0, c1 - c0, 4), dtype=np.uint8)
    tile[cov] = out
    rgba[r0:r1, c0:c1] = tile
    q = np.where(measured[ri, ci], 1, 2).astype(np.uint8)
    quality[r0:r1, c0:c1] = np.where(cov & (tile[..., 3] > 0), q, 0)
