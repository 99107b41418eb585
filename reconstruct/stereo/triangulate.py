"""Disparity -> metric depth (``z = f B / d``) -> coloured point cloud with normals (a
*scan*, in the left camera frame, mm), with its organised grid for meshing."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.calib_formats import load_stereo_calibration
from prism3d.capture.rig import Rectification, StereoRig, compute_rectification
from prism3d.checks import check_array, check_same_shape
from prism3d.errors import InputError, ReconstructionError
from prism3d.geometry import backproject
from prism3d.io.images import read_image
from prism3d.io.pfm import read_pfm
from prism3d.io.ply import write_ply
from prism3d.reconstruct.stereo.rectify import rectify_maps
from prism3d.reconstruct.stereo.selection import confidence_from_std

__all__ = [
    "Scan",
    "depth_resolution_mm",
    "depth_to_points",
    "disparity_to_depth",
    "disparity_to_rectified",
    "grid_normals",
    "scan_from_depth",
    "triangulate",
    "triangulate_to_file",
]


def depth_resolution_mm(z_mm: float | NDArray, focal_px: float, baseline_mm: float) -> float | NDArray:
    """Depth change (mm) per pixel of disparity, ``|dz/dd| = z^2 / (f B)`` (the paper's eq. 16)."""
    return np.asarray(z_mm, dtype=np.float64) ** 2 / (float(focal_px) * float(baseline_mm))


def disparity_to_depth(disparity: NDArray, rect: Rectification) -> NDArray[np.float32]:
    """Depth ``(H, W)`` float32 mm along the rectified-left z axis; NaN where ``d <= 0`` or NaN."""
    d = check_array(disparity, "disparity", ndim=2, dtype_kind="f")
    return rect.disparity_to_depth(d)


def depth_to_points(depth_mm: NDArray, rect: Rectification, *, frame: str = "left") -> NDArray[np.float32]:
    """Organised points ``(H, W, 3)`` float32 mm from a rectified-left depth map, in the
    ``"left"`` camera frame (the frame of scans) or the ``"rectified"``-left frame."""
    z = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="f").astype(np.float64)
    P = rect.P1
    f, cx, cy = P[0, 0], P[0, 2], P[1, 2]
    pts = backproject(z, f, f, cx, cy)
    if frame == "left":
        pts = pts @ rect.R1  # x_left = R1^T x_rect  <=>  row-vector form x_rect @ R1
    elif frame != "rectified":
        raise InputError(f"frame: expected 'left' or 'rectified', got {frame!r}")
    return pts.astype(np.float32)


def grid_normals(points: NDArray, valid: NDArray) -> NDArray[np.float32]:
    """Unit normals ``(H, W, 3)`` of an organised point grid, facing the camera at the
    origin: central differences, one-sided at gaps; NaN where none can be formed."""
    from ._mesh_kernels import grid_normals as _grid_normals_kernel

    p = check_array(points, "points", ndim=3)
    m = check_array(valid, "valid", ndim=2).astype(bool)
    check_same_shape(p, m, ("points", "valid"), dims=2)
    if p.shape[2] != 3:
        raise InputError(f"points: expected (H, W, 3), got shape {p.shape}")
    p64 = np.ascontiguousarray(p, dtype=np.float64)
    m = np.ascontiguousarray(m & np.isfinite(p64).all(axis=2))
    out = np.empty(p.shape, np.float32)
    _grid_normals_kernel(p64, m, out)
    return out


@dataclass
class Scan:
    """One view's reconstruction: points ``(N, 3)`` float32 (left camera frame, mm) with
    colours, unit normals facing the camera, ``confidence`` (chance the disparity is
    within 1 px of the truth), ``pixels`` ``(row, col)`` on the rectified-left grid of
    ``grid_shape``, its ``depth_mm`` (NaN where no point) and ``disparity_std`` (px)."""

    points: NDArray[np.float32]
    colors: NDArray[np.uint8]
    normals: NDArray[np.float32]
    confidence: NDArray[np.float32]
    pixels: NDArray[np.int32]
    grid_shape: tuple[int, int]
    depth_mm: NDArray[np.float32]
    disparity_std: NDArray[np.float32] | None = None
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    def grid(self) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """The organised ``(H, W, 3)`` point grid (NaN where no point) and its mask."""
        h, w = self.grid_shape
        g = np.full((h, w, 3), np.nan, dtype=np.float32)
        m = np.zeros((h, w), dtype=bool)
        g[self.pixels[:, 0], self.pixels[:, 1]] = self.points
        m[self.pixels[:, 0], self.pixels[:, 1]] = True
        return g, m

    def point_properties(self) -> dict[str, NDArray[np.float32]]:
        """Per-point PLY scalars: ``confidence``, and where known ``disparity_std`` (px)
        and ``depth_std`` (mm, ``z^2 / (f B)`` times the disparity std)."""
        out = {"confidence": self.confidence}
        if self.disparity_std is not None:
            out["disparity_std"] = self.disparity_std.astype(np.float32)
            f, b = self.meta.get("focal_px"), self.meta.get("baseline_mm")
            if f and b:
                z = self.points[:, 2].astype(np.float64)  # left-camera z: within R1 of the rectified z
                out["depth_std"] = (self.disparity_std * z * z / (float(f) * float(b))).astype(np.float32)
        return out

    def save(self, path: str | Path, *, faces: NDArray | None = None) -> None:
        """Write a binary PLY (points, colours, normals, per-point scalars[, faces]) atomically."""
        write_ply(path, self.points, colors=self.colors, normals=self.normals, faces=faces,
                  extra=self.point_properties(),
                  comments=["prism3d scan", "units mm", "frame left camera (OpenCV axes)"])


def triangulate(
    disparity: NDArray,
    valid: NDArray,
    rect: Rectification,
    image: NDArray,
    *,
    disparity_std: NDArray | None = None,
    min_confidence: float = 0.0,
) -> Scan:
    """A :class:`Scan` of the ``valid`` pixels of a rectified-left disparity ``(H, W)``
    float32 (NaN = invalid) with colours from the rectified left ``image``; points whose
    confidence (from ``disparity_std``, px) is below ``min_confidence`` are dropped."""
    d = check_array(disparity, "disparity", ndim=2, dtype_kind="f")
    m = check_array(valid, "valid", ndim=2).astype(bool)
    img = check_array(image, "image", ndim=(2, 3))
    check_same_shape(d, m, ("disparity", "valid"))
    check_same_shape(d, img, ("disparity", "image"), dims=2)
    if (d.shape[1], d.shape[0]) != rect.size:
        raise InputError(
            f"disparity is {d.shape[1]}x{d.shape[0]} but the rectification is {rect.size[0]}x{rect.size[1]}"
        )
    sd = None if disparity_std is None else check_array(disparity_std, "disparity_std", shape=d.shape)
    m = m & np.isfinite(d) & (d > 0)
    if sd is not None and min_confidence > 0:
        m &= ~(confidence_from_std(sd) < min_confidence) | ~np.isfinite(sd)
    depth = np.where(m, rect.disparity_to_depth(d), np.nan).astype(np.float32)
    return scan_from_depth(depth, rect, img, sd)


def scan_from_depth(
    depth_mm: NDArray, rect: Rectification, image: NDArray, disparity_std: NDArray | None = None
) -> Scan:
    """A :class:`Scan` from a rectified-left depth map (mm, NaN = no point), its image and
    ``disparity_std`` (px; NaN or absent: confidence 1). A point without neighbours
    gets the normal along its ray."""
    depth = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="f").astype(np.float32)
    img = check_array(image, "image", ndim=(2, 3))
    check_same_shape(depth, img, ("depth_mm", "image"), dims=2)
    if disparity_std is None:
        sd = np.full(depth.shape, np.nan, np.float32)
    else:
        sd = check_array(disparity_std, "disparity_std", shape=depth.shape).astype(np.float32)
    m = np.isfinite(depth)
    if not m.any():
        raise ReconstructionError("no valid disparities to triangulate (empty scan): is the disparity range right?")
    grid = depth_to_points(depth, rect, frame="left")
    normals = grid_normals(grid, m)
    lone = m & ~np.all(np.isfinite(normals), axis=2)
    if lone.any():
        p = grid[lone].astype(np.float64)
        normals[lone] = (-p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)
    rows, cols = np.nonzero(m)
    rgb = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
    if rgb.dtype != np.uint8:
        rgb = np.clip(np.round(rgb * 255.0 if rgb.dtype.kind == "f" else rgb), 0, 255).astype(np.uint8)
    std = sd[rows, cols]
    conf = np.where(np.isfinite(std), confidence_from_std(std), np.float32(1.0)).astype(np.float32)
    return Scan(
        points=grid[rows, cols],
        colors=rgb[rows, cols],
        normals=normals[rows, cols],
        confidence=conf,
        pixels=np.stack([rows, cols], axis=1).astype(np.int32),
        grid_shape=depth.shape,
        depth_mm=depth,
        disparity_std=std,
    )


def _already_rectified(rig: StereoRig) -> bool:
    """True for a rig whose views are rectified as given (Middlebury/ETH3D/KITTI
    calibrations): no rotation, baseline along x, no distortion, equal fx, fy, cy."""
    L, R = rig.left, rig.right
    t = rig.T
    return (np.allclose(rig.R, np.eye(3), atol=1e-9) and abs(t[1]) < 1e-6 * abs(t[0])
            and abs(t[2]) < 1e-6 * abs(t[0]) and not L.has_distortion and not R.has_distortion
            and np.isclose(L.fx, R.fx) and np.isclose(L.fy, R.fy) and np.isclose(L.cy, R.cy)
            and L.skew == 0 and R.skew == 0)


def disparity_to_rectified(disparity: NDArray, rig: StereoRig, rect: Rectification
                           ) -> NDArray[np.float32]:
    """A disparity map on ``rect``'s rectified-left grid: as is, or from an already-rectified
    pair's left view (Middlebury) shifted: ``d_rect = d + cx_right - cx_left``."""
    d = check_array(disparity, "disparity", ndim=2, dtype_kind="f").astype(np.float32)
    w, h = rect.size
    if d.shape == (h, w):
        return d
    vw, vh = rig.left.size
    if d.shape == (vh, vw) and _already_rectified(rig):
        f = rect.focal_px
        if np.isclose(f, rig.left.fx):
            sx = rect.P1[0, 2] - rig.left.cx
            sy = rect.P1[1, 2] - rig.left.cy
            if abs(sx - round(sx)) < 1e-6 and abs(sy - round(sy)) < 1e-6:
                ix, iy = int(round(sx)), int(round(sy))
                out = np.full((h, w), np.nan, np.float32)
                ys, xs = slice(max(iy, 0), min(iy + vh, h)), slice(max(ix, 0), min(ix + vw, w))
                src = d[ys.start - iy:ys.stop - iy, xs.start - ix:xs.stop - ix]
                out[ys, xs] = src + np.float32(rig.right.cx - rig.left.cx)
                return out
    raise InputError(
        f"disparity is {d.shape[1]}x{d.shape[0]} but the calibration's rectified left view is {w}x{h} "
        f"(views {vw}x{vh}): give a disparity computed on this calibration's rectified pair "
        "(prism3d rectify / match / reconstruct --disparity-out)")


def triangulate_to_file(
    disparity_path: str | Path,
    calib_paths: str | Path | list[str | Path],
    left_path: str | Path,
    out_ply: str | Path,
    *,
    alpha: float = 1.0,
    image_size: tuple[int, int] | None = None,
    max_depth_mm: float | None = None,
) -> Scan:
    """What ``prism3d triangulate`` calls: a disparity PFM (see :func:`disparity_to_rectified`)
    and the (rectified or original) left view to a coloured cloud PLY, like OpenCV's
    ``reprojectImageTo3D``; points beyond ``max_depth_mm`` are dropped."""
    out = Path(out_ply)
    if out.suffix.lower() != ".ply":
        raise InputError(f"{out}: the cloud is written as .ply")
    if out.is_dir():
        raise InputError(f"{out}: is a directory; give an output file name")
    rig = load_stereo_calibration(calib_paths,
                                  image_size=image_size).rig
    rect = compute_rectification(rig, alpha=alpha)
    try:
        d = disparity_to_rectified(read_pfm(disparity_path), rig, rect)
    except InputError as exc:
        raise InputError(f"{disparity_path}: {exc}") from exc
    img = read_image(left_path)
    w, h = rect.size
    if img.shape[:2] == (h, w):
        colours = img
    elif (img.shape[1], img.shape[0]) == rig.left.size:
        maps = rectify_maps(rig, rect)
        colours = maps.remap(img, img)[0]
    else:
        raise InputError(f"{left_path}: image is {img.shape[1]}x{img.shape[0]}; expected the rectified left "
                         f"view ({w}x{h}) or the left view ({rig.left.size[0]}x{rig.left.size[1]})")
    valid = np.isfinite(d) & (d > 0)
    if max_depth_mm is not None:
        if not (np.isfinite(max_depth_mm) and max_depth_mm > 0):
            raise InputError(f"max_depth_mm: expected a number > 0, got {max_depth_mm!r}")
        with np.errstate(divide="ignore"):
            valid &= rect.focal_px * rect.baseline_mm / np.where(valid, d, 1.0) <= max_depth_mm
    if not valid.any():
        raise InputError(f"{disparity_path}: no positive finite disparity to triangulate")
    scan = triangulate(np.where(valid, d, np.nan).astype(np.float32), valid, rect, colours)
    scan.meta.update(focal_px=rect.focal_px, baseline_mm=rect.baseline_mm)

    write_ply(out, scan.points, colors=scan.colors, normals=scan.normals,
              comments=["prism3d cloud from a disparity map", "units mm", "frame left camera (OpenCV axes)",
                        f"focal_px {rect.focal_px}", f"baseline_mm {rect.baseline_mm}"])
    return scan
