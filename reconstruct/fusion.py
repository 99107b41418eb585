"""Fusion of registered scans: one de-duplicated, noise-averaged cloud and a
watertight mesh.

The fused cloud averages all points (and colours) falling in one voxel of the
data's point spacing, so overlapping scans neither duplicate nor thicken the
surface, and sensor noise averages down. Normals are re-estimated on the fused
cloud and oriented toward the averaged viewing direction of the points that made
each voxel (every scan is assumed to be in its sensor frame before registration,
sensor at the origin). The mesh is a screened Poisson surface.

References
----------
.. [1] M. Kazhdan, H. Hoppe, "Screened Poisson surface reconstruction", ACM
   Transactions on Graphics 32(3), 2013.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_in_range, check_positive
from prism3d.errors import InputError, ReconstructionError

__all__ = ["fuse_clouds", "poisson_mesh"]

log = logging.getLogger(__name__)


def _o3d():
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def fuse_clouds(
    points: list[NDArray],
    T_model_scan: list[NDArray],
    *,
    voxel: float,
    colors: list[NDArray | None] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None, NDArray[np.float32]]:
    """Merge registered scans into one voxel-averaged cloud with normals.

    Parameters
    ----------
    points : list of (N_k, 3) float
        Each scan in its own sensor frame (sensor at the origin).
    T_model_scan : list of (4, 4) float
        Registration of each scan into the model frame.
    voxel : float
        Averaging voxel (the data's point spacing is a good choice), cloud units.
    colors : list of (N_k, 3) uint8 or None, optional
        Colours are fused only when every scan has them.

    Returns
    -------
    points : (M, 3) float64
        Model frame.
    colors : (M, 3) uint8 or None
    normals : (M, 3) float32
        Unit normals facing the sensors that saw each point.
    """
    o3d = _o3d()
    check_positive(voxel, "voxel")
    if len(points) != len(T_model_scan) or not points:
        raise InputError(f"points/T_model_scan: expected equal non-zero lengths, got {len(points)} and {len(T_model_scan)}")
    use_col = colors is not None and all(c is not None for c in colors)
    all_p, all_v, all_c = [], [], []
    for k, (p, T) in enumerate(zip(points, T_model_scan, strict=True)):
        P = np.asarray(check_array(p, f"points[{k}]", shape=(None, 3), dtype_kind="fiu"), dtype=np.float64)
        T = np.asarray(T, dtype=np.float64)
        pm = P @ T[:3, :3].T + T[:3, 3]
        view = T[:3, 3][None, :] - pm
        view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-300)
        all_p.append(pm)
        all_v.append(view)
        if use_col:
            all_c.append(np.asarray(colors[k], dtype=np.float64) / 255.0)  # type: ignore[index]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(all_p)))
    pc.normals = o3d.utility.Vector3dVector(np.concatenate(all_v))
    if use_col:
        pc.colors = o3d.utility.Vector3dVector(np.concatenate(all_c))
    down = pc.voxel_down_sample(voxel)
    if len(down.points) < 3:
        raise ReconstructionError("fusion: fewer than 3 points remain after voxel averaging")
    view = np.asarray(down.normals).copy()
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3.0 * voxel, max_nn=30))
    nrm = np.asarray(down.normals).copy()
    flip = np.sum(nrm * view, axis=1) < 0
    nrm[flip] *= -1
    out_p = np.asarray(down.points, dtype=np.float64).copy()
    out_c = None
    if use_col:
        out_c = np.clip(np.round(np.asarray(down.colors) * 255.0), 0, 255).astype(np.uint8)
    return out_p, out_c, nrm.astype(np.float32)


def poisson_mesh(
    points: NDArray,
    normals: NDArray,
    *,
    colors: NDArray | None = None,
    spacing: float,
    depth: int | None = None,
    trim_quantile: float = 0.0,
    smooth_iterations: int = 0,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.uint8] | None]:
    """Screened Poisson surface of an oriented cloud.

    Parameters
    ----------
    points : (N, 3) float
    normals : (N, 3) float
        Oriented unit normals (outward).
    colors : (N, 3) uint8, optional
        Interpolated to the mesh vertices.
    spacing : float
        Point spacing; the default octree depth makes cells about 2 spacings wide
        (depth clipped to [5, 10]).
    depth : int, optional
        Octree depth.
    trim_quantile : float in [0, 1)
        Remove vertices whose Poisson sample density is in this lowest quantile
        (surface invented far from data). ``0`` keeps the surface closed
        (watertight); trimming opens holes where data was missing.
    smooth_iterations : int
        Taubin smoothing passes (volume-preserving), 0 = none.

    Returns
    -------
    vertices : (V, 3) float64
    faces : (F, 3) int64
    colors : (V, 3) uint8 or None

    References
    ----------
    .. [1] Kazhdan and Hoppe, 2013.
    """
    o3d = _o3d()
    P = np.asarray(check_array(points, "points", shape=(None, 3), dtype_kind="fiu"), dtype=np.float64)
    N = np.asarray(check_array(normals, "normals", shape=(len(P), 3), dtype_kind="f"), dtype=np.float64)
    check_positive(spacing, "spacing")
    check_in_range(trim_quantile, "trim_quantile", 0.0, 0.999)
    if len(P) < 10:
        raise ReconstructionError(f"poisson mesh: expected at least 10 points, got {len(P)}")
    if depth is None:
        extent = float(np.max(P.max(axis=0) - P.min(axis=0)))
        depth = int(np.clip(np.ceil(np.log2(max(extent * 1.1 / (2.0 * spacing), 2.0))), 5, 10))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pc.normals = o3d.utility.Vector3dVector(N)
    if colors is not None:
        C = check_array(colors, "colors", shape=(len(P), 3), dtype_kind="u")
        pc.colors = o3d.utility.Vector3dVector(np.asarray(C, dtype=np.float64) / 255.0)
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=int(depth), linear_fit=False)
    if trim_quantile > 0:
        d = np.asarray(dens)
        mesh.remove_vertices_by_mask(d < np.quantile(d, trim_quantile))
    if smooth_iterations > 0:
        mesh = mesh.filter_smooth_taubin(number_of_iterations=int(smooth_iterations))
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    V = np.asarray(mesh.vertices, dtype=np.float64).copy()
    F = np.asarray(mesh.triangles, dtype=np.int64).copy()
    if len(F) == 0:
        raise ReconstructionError("poisson mesh: the surface is empty")
    VC = None
    if colors is not None and mesh.has_vertex_colors():
        VC = np.clip(np.round(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
    return V, F, VC
