"""Meshes from organised scans (neighbouring pixels give triangles without a search;
none bridges a depth jump), and edge-preserving depth smoothing."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_positive, check_same_shape
from prism3d.reconstruct.stereo._mesh_kernels import range_limited_gaussian

__all__ = ["mesh_from_grid", "smooth_depth", "smoothing_resolution_mm"]

#: Default depth jump smoothing does not cross, in pixels of disparity (15 mm at the
#: paper's 1250 mm): well above the noise, well below an occlusion's step.
_JUMP_DISPARITY_PX = 10.0
#: Without the rig's focal length and baseline: this share of the depth.
_JUMP_DEPTH_SHARE = 0.01
#: Gaussian kernel half-width, in sigmas.
_KERNEL_SIGMAS = 3


def mesh_from_grid(
    points: NDArray, valid: NDArray, *, focal_px: float, max_slope: float = 6.0
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Triangulate an organised point grid ``(H, W, 3)`` (camera frame) at its ``valid``
    pixels, dropping edges whose ``|dz|`` exceeds ``max_slope`` times their footprint
    ``z / focal_px`` (6 ~ 80 degrees of slant): vertices ``(N, 3)`` float32 (row-major)
    and faces ``(M, 3)`` int64 facing the camera."""
    p = check_array(points, "points", ndim=3)
    m = check_array(valid, "valid", ndim=2).astype(bool)
    check_same_shape(p, m, ("points", "valid"), dims=2)
    f = check_positive(focal_px, "focal_px")
    check_positive(max_slope, "max_slope")
    m = m & np.all(np.isfinite(p), axis=2)
    h, w = m.shape
    index = np.full((h, w), -1, dtype=np.int64)
    index[m] = np.arange(int(m.sum()))
    z = np.where(m, p[..., 2], np.nan).astype(np.float64)

    def edge_ok(za: NDArray, zb: NDArray) -> NDArray[np.bool_]:
        footprint = 0.5 * (za + zb) / f
        with np.errstate(invalid="ignore"):
            return np.abs(za - zb) <= max_slope * footprint

    z00, z01, z10, z11 = z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]
    i00, i01, i10, i11 = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    e_right = edge_ok(z00, z01)
    e_down = edge_ok(z00, z10)
    e_diag = edge_ok(z01, z10)
    e_right_b = edge_ok(z10, z11)
    e_down_r = edge_ok(z01, z11)
    # triangle A: (00, 10, 01); triangle B: (01, 10, 11) -- counter-clockwise seen from the camera
    ta = (i00 >= 0) & (i10 >= 0) & (i01 >= 0) & e_right & e_down & e_diag
    tb = (i01 >= 0) & (i10 >= 0) & (i11 >= 0) & e_diag & e_right_b & e_down_r
    faces = np.concatenate([
        np.stack([i00[ta], i10[ta], i01[ta]], axis=1),
        np.stack([i01[tb], i10[tb], i11[tb]], axis=1),
    ])
    return p[m].astype(np.float32), faces.astype(np.int64)


def smooth_depth(
    depth_mm: NDArray,
    *,
    sigma_px: float = 1.5,
    jump_mm: float | None = None,
    focal_px: float | None = None,
    baseline_mm: float | None = None,
) -> NDArray[np.float32]:
    """Edge-preserving Gaussian smoothing of a depth map (mm, NaN = hole) over neighbours
    within ``jump_mm`` (default 10 px of disparity with ``focal_px`` and ``baseline_mm``,
    else 1 % of the depth); resolution lost: :func:`smoothing_resolution_mm`."""
    d = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="f").astype(np.float64)
    s = check_positive(sigma_px, "sigma_px")
    r = int(np.ceil(_KERNEL_SIGMAS * s))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * (x / s) ** 2)
    weights = np.outer(g, g)
    if jump_mm is not None:
        jump = np.full_like(d, check_positive(jump_mm, "jump_mm"))
    elif focal_px is not None and baseline_mm is not None:
        jump = _JUMP_DISPARITY_PX * d**2 / (check_positive(focal_px, "focal_px") * check_positive(baseline_mm, "baseline_mm"))
    else:
        jump = _JUMP_DEPTH_SHARE * d
    jump = np.where(np.isfinite(jump), jump, 0.0)
    out = np.empty_like(d)
    range_limited_gaussian(np.ascontiguousarray(d), weights, np.ascontiguousarray(jump), out)
    return out.astype(np.float32)


def smoothing_resolution_mm(sigma_px: float, z_mm: float, focal_px: float) -> float:
    """Lateral resolution lost to :func:`smooth_depth`: the kernel FWHM at depth z, mm."""
    return float(2.0 * np.sqrt(2.0 * np.log(2.0)) * sigma_px * z_mm / focal_px)
