"""The surface a scan's size is measured on: one estimator for the object frame's extents
and the scan features' boxes (docs/stitching.md, "Object frame"; docs/features.md).

The extremes of stereo points are the depth noise's: a fraction of a per cent of a side's
points lie 1-3 mm outside it, so a box around the points is too wide by twice that, and a
footprint traced from them is tilted by their spurs. The screened Poisson surface of the
oriented points follows the bulk of the points: :func:`surface_points` keeps the points
within NEAR_CELLS spacings (one octree cell) of it, and :func:`surface_extents` reads a
box's sides from them, each extreme point projected on the plane of its neighbourhood
(measured on 18 stitched stereo scans against the truth: docs/stitching.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from prism3d.errors import InputError
from prism3d.reconstruct.scan.fusion import poisson_mesh
from prism3d.reconstruct.scan.neighbours import query_tree

__all__ = ["DENSE_SPACINGS", "cloud_spacing", "surface_extents", "surface_points"]

#: The surface is fitted only to clouds at least this many point spacings across (its
#: cells are ~2 spacings; on a sparse cloud it is no better than the points and bulges
#: by up to 2 spacings beyond them).
DENSE_SPACINGS = 200.0
#: Surface vertices within this many spacings (one octree cell) of a point are kept.
NEAR_CELLS = 2.0
#: Fewer supported surface vertices give no meaningful box.
MIN_POINTS = 10
#: The median spacing is taken over at most ~this many points.
SPACING_SUBSAMPLE = 20000
#: Normals estimated for a cloud given without them: PCA of this many neighbours.
NORMAL_NEIGHBOURS = 20
#: Extreme points are projected on the plane of their neighbourhood before extents are
#: taken (moving least squares): points within EXTREME_BAND_SPACINGS of an extreme,
#: neighbourhoods of MLS_NEIGHBOURS points of a 1-in-MLS_STRIDE subsample (about 9 point
#: spacings across, far wider than the noise); at most MLS_CANDIDATES of them (an even
#: subsample).
EXTREME_BAND_SPACINGS = 10.0
MLS_NEIGHBOURS = 64
MLS_STRIDE = 4
MLS_CANDIDATES = 100_000


def cloud_spacing(points: NDArray, tree: cKDTree | None = None) -> float:
    """Median nearest-neighbour distance of (up to ~SPACING_SUBSAMPLE of) the points."""
    tree = cKDTree(points) if tree is None else tree
    return float(np.median(tree.query(points[:: max(1, len(points) // SPACING_SUBSAMPLE)], k=2)[0][:, 1]))


def surface_points(points: NDArray, normals: NDArray | None = None, *,
                   viewpoints: Sequence[NDArray] | None = None, sparse: bool = False
                   ) -> tuple[NDArray[np.float64], bool]:
    """The points a size is measured on, and whether the surface sorted them: for a dense
    cloud (>= DENSE_SPACINGS spacings across; any cloud with ``sparse``) the points
    within NEAR_CELLS spacings of their screened Poisson surface (the depth noise's tails
    dropped), else every point. Without ``normals`` they are estimated and turned toward
    the nearest of ``viewpoints`` (the sensors' centres, (3,) each); with neither, every
    point."""
    P = np.asarray(points, dtype=np.float64)
    spacing = cloud_spacing(P)
    if not spacing > 0:
        raise InputError("points: no point spacing (all points coincide?)")
    if not sparse and float(np.ptp(P, axis=0).max()) < DENSE_SPACINGS * spacing:
        return P, False
    if normals is None:
        if not viewpoints:
            return P, False
        normals = _normals_facing(P, np.asarray(viewpoints, dtype=np.float64).reshape(-1, 3))
    V, F, _ = poisson_mesh(P, np.asarray(normals, dtype=np.float64), spacing=spacing)
    keep = _distance_to_mesh(P, V, F) <= NEAR_CELLS * spacing
    if keep.sum() < MIN_POINTS:
        raise InputError("points: the fitted surface does not follow the points (are the normals oriented?)")
    return P[keep], True


def surface_extents(points: NDArray, R: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lowest and highest surface coordinates (3,) of ``points`` along the rows of ``R``:
    the points within EXTREME_BAND_SPACINGS of each extreme, projected on the plane of
    their neighbourhood (moving least squares), then their extremes."""
    Q = np.asarray(points, dtype=np.float64) @ np.asarray(R, dtype=np.float64).T
    spacing = cloud_spacing(Q)
    band = EXTREME_BAND_SPACINGS * spacing
    near = np.zeros(len(Q), bool)
    for a in range(Q.shape[1]):
        near |= (Q[:, a] < Q[:, a].min() + band) | (Q[:, a] > Q[:, a].max() - band)
    idx = np.flatnonzero(near)
    idx = idx[:: max(1, len(idx) // MLS_CANDIDATES)]
    sub = Q[::MLS_STRIDE] if len(Q) >= MLS_STRIDE * MLS_NEIGHBOURS else Q
    k = min(MLS_NEIGHBOURS, len(sub))
    tree = cKDTree(sub)
    lo, hi = np.full(Q.shape[1], np.inf), np.full(Q.shape[1], -np.inf)
    for s in range(0, len(idx), 4096):  # (4096, k, 3) at a time
        q = Q[idx[s : s + 4096]]
        _, nb = query_tree(tree, q, k=k)
        N = sub[nb]
        cen = N.mean(axis=1)
        D = N - cen[:, None]
        n = np.linalg.eigh(np.einsum("mki,mkj->mij", D, D))[1][:, :, 0]
        # a point moves onto its plane by at most NEAR_CELLS spacings (the noise a kept
        # point may have): where the neighbourhood is no plane (a sharp edge), no further
        off = np.clip(np.sum((q - cen) * n, axis=1), -NEAR_CELLS * spacing, NEAR_CELLS * spacing)
        proj = q - off[:, None] * n
        lo, hi = np.minimum(lo, proj.min(axis=0)), np.maximum(hi, proj.max(axis=0))
    return lo, hi


def _distance_to_mesh(P: NDArray, V: NDArray, F: NDArray) -> NDArray[np.float64]:
    """Each point's distance to the nearest triangle of a mesh (Open3D's raycasting scene,
    float32 about the mesh's centre, not a far origin)."""
    import open3d as o3d

    centre = V.mean(axis=0)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(V - centre, dtype=np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(F, dtype=np.int32))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    query = o3d.core.Tensor(np.ascontiguousarray(P - centre, dtype=np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def _normals_facing(P: NDArray, viewpoints: NDArray) -> NDArray[np.float64]:
    """PCA normals of NORMAL_NEIGHBOURS neighbours, each turned toward its nearest viewpoint."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
    N = np.asarray(pc.normals).copy()
    nearest = query_tree(cKDTree(viewpoints), P)[1]
    flip = np.sum(N * (viewpoints[nearest] - P), axis=1) < 0
    N[flip] *= -1
    return N
