"""Fusion of registered scans: one de-duplicated, noise-averaged cloud (points and
colours averaged per voxel; normals re-estimated and turned toward the sensors that saw
each voxel) and a watertight screened Poisson mesh.

References
----------
.. [1] M. Kazhdan, H. Hoppe, "Screened Poisson surface reconstruction", ACM
   Transactions on Graphics 32(3), 2013.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_in_range, check_positive
from prism3d.errors import InputError, ReconstructionError
from prism3d.grids import voxel_mean
from prism3d.reconstruct.scan.neighbours import query_tree

__all__ = ["fuse_clouds", "mesh_is_closed", "poisson_mesh"]

log = logging.getLogger(__name__)


def _o3d():
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


#: Default distance within which another scan's surface confirms a point, in voxels.
_SUPPORT_VOXELS = 2.0
#: Normals are estimated once per voxel of this many fusion voxels (smooth and cheap).
_NORMAL_CELL_VOXELS = 2.0
#: PCA neighbourhood of the cell normals, in cells, and its neighbour cap.
_NORMAL_RADIUS_CELLS = 3.0
_NORMAL_MAX_NN = 24
#: The Poisson octree spans the cloud's extent times this (margin around the data).
_OCTREE_MARGIN = 1.1
#: Default octree cell, in point spacings.
_CELL_SPACINGS = 2.0
#: Default octree depths allowed: depth 9 costs ~4x more than 8.
_DEPTH_RANGE = (5, 8)
#: An averaged normal shorter than this had opposite normals cancel (a thin wall).
_MIN_NORMAL_LENGTH = 0.5


def _to_model_frame(points: list[NDArray], T_model_scan: list[NDArray], colors: list[NDArray | None] | None,
                    use_col: bool) -> tuple[list[NDArray], list[NDArray], list[NDArray]]:
    """Each scan's points in the model frame, their unit directions toward the sensor,
    and their colours in [0, 1]."""
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
    return all_p, all_v, all_c


def _keep_supported(all_p: list[NDArray], all_v: list[NDArray], all_c: list[NDArray], tau: float,
                    use_col: bool) -> None:
    """Drop (in place) the points no other scan's surface passes within ``tau`` of. The
    other scans are asked nearest first (by their centroids): they support most points, so
    the farther ones are asked about the few left (the kept set is the same in any order)."""
    from scipy.spatial import cKDTree

    trees = [cKDTree(q, balanced_tree=False) for q in all_p]  # faster to build, the same answers
    centres = np.array([q.mean(axis=0) if len(q) else np.full(3, np.inf) for q in all_p])
    for k in range(len(all_p)):
        ok = np.zeros(len(all_p[k]), bool)
        for j in np.argsort(np.linalg.norm(centres - centres[k], axis=1), kind="stable"):
            if j != k:
                todo = ~ok
                if not todo.any():
                    break
                dd, _ = query_tree(trees[j], all_p[k][todo], distance_upper_bound=tau)
                ok[np.flatnonzero(todo)[np.isfinite(dd)]] = True
        all_p[k], all_v[k] = all_p[k][ok], all_v[k][ok]
        if use_col:
            all_c[k] = all_c[k][ok]


def fuse_clouds(
    points: list[NDArray],
    T_model_scan: list[NDArray],
    *,
    voxel: float,
    colors: list[NDArray | None] | None = None,
    min_views: int = 1,
    support_distance: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None, NDArray[np.float32]]:
    """Merge scans ``(N_k, 3)`` (each in its sensor frame) registered by ``T_model_scan``
    (4, 4) into one cloud averaged per ``voxel`` (about the point spacing): points
    ``(M, 3)`` float64 in the model frame, colours ``(M, 3)`` uint8 (when every scan has
    them) and unit normals ``(M, 3)`` float32 facing the sensors. ``min_views=2`` keeps
    only points another scan passes within ``support_distance`` (default 2 voxels) of."""
    check_positive(voxel, "voxel")
    if len(points) != len(T_model_scan) or not points:
        raise InputError(f"points/T_model_scan: expected equal non-zero lengths, got {len(points)} and {len(T_model_scan)}")
    use_col = colors is not None and all(c is not None for c in colors)
    if min_views not in (1, 2):
        raise InputError(f"min_views: expected 1 or 2, got {min_views!r}")
    all_p, all_v, all_c = _to_model_frame(points, T_model_scan, colors, use_col)
    if min_views == 2 and len(all_p) > 1:
        tau = _SUPPORT_VOXELS * voxel if support_distance is None else \
            float(check_positive(support_distance, "support_distance"))
        _keep_supported(all_p, all_v, all_c, tau, use_col)
    out_p, (view, mean_c), _ = voxel_mean(np.concatenate(all_p), voxel, np.concatenate(all_v),
                                          np.concatenate(all_c) if use_col else None)
    if len(out_p) < 3:
        raise ReconstructionError("fusion: fewer than 3 points remain after voxel averaging")
    nrm = _cell_normals(out_p, _NORMAL_CELL_VOXELS * voxel)
    flip = np.sum(nrm * view, axis=1) < 0
    nrm[flip] *= -1
    out_c = None
    if mean_c is not None:
        out_c = np.clip(np.round(mean_c * 255.0), 0, 255).astype(np.uint8)
    return out_p, out_c, nrm.astype(np.float32)


def _cell_normals(points: NDArray, cell: float) -> NDArray[np.float64]:
    """Unoriented normals: PCA normals of the cloud averaged per ``cell`` voxel, given to
    every point of the voxel (several times cheaper than per point, as smooth)."""
    o3d = _o3d()
    centres, _, inv = voxel_mean(points, cell, origin=points.min(axis=0))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centres))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=_NORMAL_RADIUS_CELLS * cell,
                                                             max_nn=_NORMAL_MAX_NN))
    return np.asarray(pc.normals, dtype=np.float64)[inv]


def _oriented_cloud(o3d: Any, P: NDArray, N: NDArray, colors: NDArray | None, cell: float | None) -> Any:
    """An Open3D cloud of the points with usable normals (and colours); with ``cell``, points
    much denser than the octree cells (they only cost time) averaged to half a cell first,
    and averaged normals that cancelled (both sides of a thin wall) dropped."""
    good = np.isfinite(N).all(axis=1) & (np.linalg.norm(N, axis=1) > _MIN_NORMAL_LENGTH)
    P, N = P[good], N[good]
    C = None
    if colors is not None:
        C = np.asarray(check_array(colors, "colors", shape=(len(good), 3), dtype_kind="u"), dtype=np.float64)[good]
        C /= 255.0
    if cell is not None:
        P, (N, C), _ = voxel_mean(P, cell / 2.0, N, C)
        ln = np.linalg.norm(N, axis=1)
        ok = ln > _MIN_NORMAL_LENGTH
        P, N, C = P[ok], N[ok] / ln[ok, None], None if C is None else C[ok]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pc.normals = o3d.utility.Vector3dVector(N)
    if C is not None:
        pc.colors = o3d.utility.Vector3dVector(C)
    return pc


def _finish_mesh(mesh: Any, dens: Any, trim_quantile: float, smooth_iterations: int, with_colors: bool
                 ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.uint8] | None]:
    """Trim low-density vertices, smooth, clean up; as arrays."""
    if trim_quantile > 0:
        d = np.asarray(dens)
        mesh.remove_vertices_by_mask(d < np.quantile(d, trim_quantile))
    if smooth_iterations > 0:
        mesh = mesh.filter_smooth_taubin(number_of_iterations=int(smooth_iterations))
    if trim_quantile > 0 or smooth_iterations > 0:
        mesh.remove_degenerate_triangles()  # (on an untrimmed surface this could open it)
    mesh.remove_unreferenced_vertices()
    V = np.asarray(mesh.vertices, dtype=np.float64).copy()
    F = np.asarray(mesh.triangles, dtype=np.int64).copy()
    if len(F) == 0:
        raise ReconstructionError("poisson mesh: the surface is empty")
    VC = None
    if with_colors and mesh.has_vertex_colors():
        VC = np.clip(np.round(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
    return V, F, VC


def poisson_mesh(
    points: NDArray,
    normals: NDArray,
    *,
    colors: NDArray | None = None,
    spacing: float,
    depth: int | None = None,
    trim_quantile: float = 0.0,
    smooth_iterations: int = 0,
    max_distance: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.uint8] | None]:
    """Screened Poisson surface (Kazhdan and Hoppe, 2013) of points and outward unit
    normals ``(N, 3)``: vertices ``(V, 3)`` float64, faces ``(F, 3)`` int64, colours
    ``(V, 3)`` uint8 or None. ``spacing``: the point spacing (default octree cells of 2
    spacings). ``trim_quantile``: drop vertices of the lowest Poisson density (0 keeps
    the surface closed, guessed where no scan saw it). ``smooth_iterations``: Taubin.
    ``max_distance``: drop the surface farther than this from every input point (the
    closed surface balloons where nothing was seen: under a model, around thin wings)."""
    o3d = _o3d()
    P = np.asarray(check_array(points, "points", shape=(None, 3), dtype_kind="fiu"), dtype=np.float64)
    N = np.asarray(check_array(normals, "normals", shape=(len(P), 3), dtype_kind="f"), dtype=np.float64)
    check_positive(spacing, "spacing")
    check_in_range(trim_quantile, "trim_quantile", 0.0, 0.999)
    if len(P) < 10:
        raise ReconstructionError(f"poisson mesh: expected at least 10 points, got {len(P)}")
    extent = float(np.max(P.max(axis=0) - P.min(axis=0)))
    if depth is None:
        depth = int(np.clip(np.ceil(np.log2(max(extent * _OCTREE_MARGIN / (_CELL_SPACINGS * spacing), 2.0))),
                            *_DEPTH_RANGE))
    check_in_range(depth, "depth", 1, 12)
    cell = extent * _OCTREE_MARGIN / 2.0**depth
    pc = _oriented_cloud(o3d, P, N, colors, cell if cell / 2.0 > spacing else None)
    # One thread: the multi-threaded solver's sums vary in the last digits from run
    # to run, and features computed from the surface must repeat exactly (~6 % slower).
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=int(depth), linear_fit=False,
                                                                           n_threads=1)
    V, F, C = _finish_mesh(mesh, dens, trim_quantile, smooth_iterations, colors is not None)
    if max_distance is None:
        return V, F, C
    return _trim_far(V, F, C, P, check_positive(max_distance, "max_distance"))


def _trim_far(V: NDArray, F: NDArray, C: NDArray | None, P: NDArray, d: float
              ) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.uint8] | None]:
    """The mesh without its vertices farther than ``d`` from the points ``P`` (and the faces
    that used them), reindexed."""
    from scipy.spatial import cKDTree

    near = query_tree(cKDTree(P), V, distance_upper_bound=d)[0] <= d
    F = F[near[F].all(axis=1)]
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    index = np.cumsum(used) - 1
    return V[used], index[F].astype(np.int64), None if C is None else C[used]


def mesh_is_closed(faces: NDArray) -> bool:
    """Whether a triangle mesh ``(F, 3)`` int is watertight: every undirected edge
    belongs to exactly two faces, traversed in opposite directions."""
    F = np.asarray(check_array(faces, "faces", shape=(None, 3), dtype_kind="iu"), dtype=np.int64)
    if len(F) == 0:
        return False
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    m = int(e.max()) + 1
    directed = e[:, 0] * m + e[:, 1]
    if len(np.unique(directed)) != len(directed):
        return False  # an edge used twice in one direction: non-manifold or flipped faces
    undirected = np.minimum(e[:, 0], e[:, 1]) * m + np.maximum(e[:, 0], e[:, 1])
    _, counts = np.unique(undirected, return_counts=True)
    return bool(np.all(counts == 2))
