"""Pairwise rigid registration of point clouds: global (FPFH [1]_ + RANSAC [2]_) and ICP [3]_,
rigid (``det(R) = +1``) and deterministic (seeded RANSAC), scaled by :func:`point_spacing`.
Open3D objects never leave the public functions. Notes: ``docs/stitching.md``.

References
----------
.. [1] R. B. Rusu, N. Blodow, M. Beetz, "Fast Point Feature Histograms (FPFH)", ICRA 2009.
.. [2] M. A. Fischler, R. C. Bolles, "Random sample consensus", Comm. ACM 24(6), 1981.
.. [3] Y. Chen, G. Medioni, "Object modelling by registration of multiple range images", 1992.
.. [4] W. Kabsch, "A solution for the best rotation ...", Acta Cryst. A32, 1976.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from prism3d.checks import check_array, check_choice, check_positive
from prism3d.errors import InputError, ReconstructionError
from prism3d.geometry import invert_transform, rotation_about, rotation_angle_deg, rotvec_from_matrix
from prism3d.reconstruct.scan.neighbours import query_tree

__all__ = [
    "RegistrationResult",
    "ScanFeatures",
    "ScanPyramid",
    "evaluate_pyramids",
    "global_register",
    "global_voxel",
    "icp_pyramids",
    "match_features",
    "match_features_candidates",
    "point_spacing",
    "refine_icp",
    "register_pair",
    "rigid_fit",
    "surface_noise",
    "turntable_motion",
]

log = logging.getLogger(__name__)

# RANSAC: fewer mutual FPFH matches than this and all one-way matches are used instead.
_MIN_MUTUAL_MATCHES = 30
# Hypotheses are drawn and scored in batches of this many (vectorised Kabsch).
_RANSAC_BATCH = 1000
# Edge-length test: a sampled triple's edges agree within this ratio (rigid motions keep
# distances) and are longer than _MIN_EDGE_VOXELS feature voxels (short edges fix no rotation).
_EDGE_RATIO = 0.9
_MIN_EDGE_VOXELS = 2.0
# A match is an inlier within this many feature voxels of its target.
_INLIER_VOXELS = 1.5
# Stop when a clean sample has been drawn with this failure chance (99.99 % confidence),
# after at least _MIN_BATCHES batches.
_RANSAC_FAILURE = 1e-4
_MIN_BATCHES = 4
# Each batch keeps this many times max_candidates of its best hypotheses for the pool.
_POOL_PER_CANDIDATE = 4
# Inlier refits of a candidate (converges in 2-3).
_REFITS = 3
# Candidates are distinct when they differ by more than this rotation or these feature voxels.
_DISTINCT_DEG = 10.0
_DISTINCT_VOXELS = 10.0
# ICP skips a coarse level with fewer points than this (or a quarter of the cloud): a handful
# of points only misleads it.
_MIN_LEVEL_POINTS = 1500
# ICP convergence: relative change of fitness and RMSE.
_ICP_RELATIVE = 1e-6
# Feature stage radii, in feature voxels: normals and the FPFH descriptor.
_NORMAL_VOXELS = 3.0
_FPFH_VOXELS = 5.0


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of registering a source cloud onto a target cloud."""

    T_target_source: NDArray[np.float64]
    """(4, 4) float64 rigid transform mapping source points into the target frame."""
    fitness: float
    """Fraction of (down-sampled) source points with a target point within ``max_distance``."""
    inlier_rmse: float
    """RMS distance of those correspondences (cloud units)."""
    information: NDArray[np.float64]
    """(6, 6) float64 information matrix (Open3D convention, rotation first) for pose graphs."""
    max_distance: float
    """Correspondence distance of the final ICP level."""


def _o3d():
    import open3d as o3d

    return o3d


def _check_points(points: NDArray, name: str, min_points: int = 10) -> NDArray[np.float64]:
    pts = check_array(points, name, shape=(None, 3), dtype_kind="fiu")
    pts = np.asarray(pts, dtype=np.float64)
    if len(pts) < min_points:
        raise InputError(f"{name}: expected at least {min_points} points, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise InputError(f"{name}: contains non-finite coordinates")
    return pts


def point_spacing(points: NDArray, *, sample: int = 4000, seed: int = 0) -> float:
    """Median nearest-neighbour distance (> 0, cloud units) of ``points`` (N >= 2, 3), measured
    on a seeded subset of ``sample`` query points."""
    pts = _check_points(points, "points", min_points=2)
    tree = cKDTree(pts, balanced_tree=False)  # built a third faster; queries as fast, answers the same
    if len(pts) > sample:
        q = pts[np.random.default_rng(seed).choice(len(pts), sample, replace=False)]
    else:
        q = pts
    d, _ = tree.query(q, k=2)
    nn = d[:, 1]
    nn = nn[nn > 0]
    if len(nn) == 0:
        raise InputError("points: all points coincide; cannot measure a point spacing")
    return float(np.median(nn))


def rigid_fit(src: NDArray, dst: NDArray, weights: NDArray | None = None) -> NDArray[np.float64]:
    """Weighted least-squares ``T_dst_src`` (4, 4) of corresponding (N >= 3, 3) points (Kabsch
    [4]_), ``det(R) = +1``."""
    a = np.asarray(src, dtype=np.float64)
    b = np.asarray(dst, dtype=np.float64)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ca = w @ a
    cb = w @ b
    H = (a - ca).T @ ((b - cb) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T


def _batched_kabsch(a: NDArray, b: NDArray) -> tuple[NDArray, NDArray]:
    """Rigid fits for a batch: a, b (B, 3, 3) -> R (B, 3, 3), t (B, 3)."""
    ca = a.mean(axis=1, keepdims=True)
    cb = b.mean(axis=1, keepdims=True)
    H = np.einsum("bki,bkj->bij", a - ca, b - cb)
    U, _, Vt = np.linalg.svd(H)
    V = np.transpose(Vt, (0, 2, 1))
    Ut = np.transpose(U, (0, 2, 1))
    d = np.sign(np.linalg.det(V @ Ut))
    d[d == 0] = 1.0
    V[:, :, 2] *= d[:, None]
    R = V @ Ut
    t = cb[:, 0, :] - np.einsum("bij,bj->bi", R, ca[:, 0, :])
    return R, t


def _make_cloud(points: NDArray, normals: NDArray | None = None):
    o3d = _o3d()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return pc


def _prepare(points: NDArray, voxel: float, *, normals: NDArray | None = None, viewpoint: NDArray | None = None):
    """Voxel-down-sample and give oriented normals (toward ``viewpoint``)."""
    o3d = _o3d()
    pc = _make_cloud(points, normals)
    down = pc.voxel_down_sample(voxel) if voxel > 0 else pc
    if not down.has_normals():
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=_NORMAL_VOXELS * voxel, max_nn=30))
        vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
        down.orient_normals_towards_camera_location(vp)
    else:
        n = np.asarray(down.normals)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        down.normals = o3d.utility.Vector3dVector(n / np.maximum(norm, 1e-12))
    return down


# The feature voxel search starts at this many spacings, takes at most _VOXEL_TRIES steps and
# accepts up to _VOXEL_SLACK times the wanted points (the count falls ~ 1 / voxel^2).
_VOXEL_START = 2.0
_VOXEL_TRIES = 4
_VOXEL_SLACK = 1.3


def global_voxel(points: NDArray, spacing: float, target_points: int) -> float:
    """Feature voxel (cloud units) leaving about ``target_points`` of ``points`` (N, 3)."""
    pc = _make_cloud(points)
    v = max(spacing * _VOXEL_START, 1e-12)
    for _ in range(_VOXEL_TRIES):
        n = len(pc.voxel_down_sample(v).points)
        if n <= target_points * _VOXEL_SLACK:
            break
        v *= np.sqrt(n / target_points)
    return float(v)


def global_register(
    source: NDArray,
    target: NDArray,
    *,
    voxel: float | None = None,
    target_points: int = 3000,
    max_hypotheses: int = 40000,
    seed: int = 0,
    viewpoint_source: NDArray | None = None,
    viewpoint_target: NDArray | None = None,
) -> tuple[NDArray[np.float64], float, float]:
    """Coarse alignment without a guess (FPFH [1]_ + RANSAC [2]_ over ``max_hypotheses`` triples)
    of ``source`` onto ``target`` (N, 3): ``T_target_source`` (4, 4), the consistent fraction
    of feature matches, and the feature voxel (default: leaving ``target_points`` points)."""
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    if voxel is None:
        voxel = global_voxel(src, point_spacing(src), target_points)
    check_positive(voxel, "voxel")
    fs = ScanFeatures(src, voxel, viewpoint=viewpoint_source)
    fd = ScanFeatures(dst, voxel, viewpoint=viewpoint_target)
    T, frac = match_features(fs, fd, max_hypotheses=max_hypotheses, seed=seed)
    return T, frac, float(voxel)


class ScanFeatures:
    """FPFH descriptors of ``points`` (N, 3) down-sampled at ``voxel``, computed once per scan:
    ``points`` (M, 3), ``features`` (M, 33), ``voxel``; ``viewpoint`` orients the normals."""

    def __init__(self, points: NDArray, voxel: float, *, viewpoint: NDArray | None = None) -> None:
        o3d = _o3d()
        pts = _check_points(points, "points")
        check_positive(voxel, "voxel")
        down = _prepare(pts, voxel, viewpoint=viewpoint)
        if len(down.points) < 10:
            raise ReconstructionError("global registration: too few points after down-sampling")
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=_FPFH_VOXELS * voxel, max_nn=100)
        self.features = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(down, param).data).T.copy()
        self.points = np.asarray(down.points, dtype=np.float64).copy()
        self.voxel = float(voxel)
        self._tree = cKDTree(self.features)


def match_features(
    source: ScanFeatures,
    target: ScanFeatures,
    *,
    max_hypotheses: int = 40000,
    seed: int = 0,
) -> tuple[NDArray[np.float64], float]:
    """The best RANSAC alignment ``(T_target_source, inlier_fraction)`` of
    :func:`match_features_candidates`."""
    return match_features_candidates(source, target, max_hypotheses=max_hypotheses, seed=seed,
                                      max_candidates=1)[0]


def _feature_matches(source: ScanFeatures, target: ScanFeatures) -> tuple[NDArray, NDArray]:
    """Matched points ``a`` (source) and ``b`` (target), mutual nearest descriptors when enough."""
    fs = source.features
    _, s2d = target._tree.query(fs, k=1)
    _, d2s = source._tree.query(target.features, k=1)
    mutual = d2s[s2d] == np.arange(len(fs))
    si = np.nonzero(mutual)[0]
    if len(si) < _MIN_MUTUAL_MATCHES:
        si = np.arange(len(fs))
    a = source.points[si]
    b = target.points[s2d[si]]
    if len(a) < 3:
        raise ReconstructionError("global registration: fewer than 3 feature matches")
    return a, b


def _sample_triples(a: NDArray, b: NDArray, voxel: float, rng: np.random.Generator) -> tuple[NDArray, NDArray]:
    """Up to a batch of match triples passing the edge-length test."""
    idx = rng.integers(0, len(a), size=(_RANSAC_BATCH * 3, 3))
    A = a[idx]
    B = b[idx]
    la = np.linalg.norm(A - np.roll(A, 1, axis=1), axis=2)
    lb = np.linalg.norm(B - np.roll(B, 1, axis=1), axis=2)
    ok = (np.minimum(la, lb) > _EDGE_RATIO * np.maximum(la, lb)).all(axis=1) & (la.min(axis=1) > _MIN_EDGE_VOXELS * voxel)
    return A[ok][:_RANSAC_BATCH], B[ok][:_RANSAC_BATCH]


def _ransac_pool(a: NDArray, b: NDArray, voxel: float, max_hypotheses: int, seed: int,
                 max_candidates: int) -> tuple[NDArray, NDArray, NDArray]:
    """Each batch's best hypotheses ``(R, t, inlier counts)``, sampled until the standard
    stopping rule (counted in triples; deterministic: it depends on counts only)."""
    rng = np.random.default_rng(seed)
    thr = _INLIER_VOXELS * voxel
    nc = len(a)
    best_count = -1
    pool_R, pool_t, pool_c = [], [], []
    keep_per_batch = _POOL_PER_CANDIDATE * max(1, int(max_candidates))
    done = 0
    while done < max_hypotheses:
        A, B = _sample_triples(a, b, voxel, rng)
        done += _RANSAC_BATCH
        if len(A) == 0:
            continue
        R, t = _batched_kabsch(A, B)
        moved = np.einsum("bij,nj->bni", R, a) + t[:, None, :]
        counts = (np.sum((moved - b[None]) ** 2, axis=2) < thr * thr).sum(axis=1)
        top = np.argsort(-counts, kind="stable")[:keep_per_batch]
        pool_R.append(R[top])
        pool_t.append(t[top])
        pool_c.append(counts[top])
        best_count = max(best_count, int(counts[top[0]]))
        w = best_count / nc
        if w > 0 and done >= _MIN_BATCHES * _RANSAC_BATCH:
            need = np.log(_RANSAC_FAILURE) / np.log(max(1e-12, 1.0 - min(w, 0.999) ** 3))
            if done >= need:
                break
    if best_count < 3:
        raise ReconstructionError("global registration: RANSAC found no consistent feature matches")
    return np.concatenate(pool_R), np.concatenate(pool_t), np.concatenate(pool_c)


def match_features_candidates(
    source: ScanFeatures,
    target: ScanFeatures,
    *,
    max_hypotheses: int = 40000,
    seed: int = 0,
    max_candidates: int = 5,
) -> list[tuple[NDArray[np.float64], float]]:
    """The best *distinct* RANSAC alignments over FPFH matches, most inliers first: 1 to
    ``max_candidates`` of ``(T_target_source (4, 4), inlier_fraction)``. On symmetric objects the
    best can be wrong and a runner-up right; candidates differ by > 10 deg or 10 voxels."""
    voxel = max(source.voxel, target.voxel)
    a, b = _feature_matches(source, target)
    Rs, ts, cs = _ransac_pool(a, b, voxel, max_hypotheses, seed, max_candidates)
    thr = _INLIER_VOXELS * voxel
    out: list[tuple[NDArray[np.float64], float]] = []
    chosen: list[NDArray] = []
    for k in np.argsort(-cs, kind="stable"):
        if cs[k] < 3 or len(out) >= max_candidates:
            break
        T = _refit_inliers(a, b, Rs[k], ts[k], thr)
        if any(
            rotation_angle_deg(invert_transform(C) @ T) < _DISTINCT_DEG
            and np.linalg.norm(C[:3, 3] - T[:3, 3]) < _DISTINCT_VOXELS * voxel
            for C in chosen
        ):
            continue
        chosen.append(T)
        r = np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1)
        out.append((T, float((r < thr).mean())))
    return out


def _refit_inliers(a: NDArray, b: NDArray, R: NDArray, t: NDArray, thr: float) -> NDArray[np.float64]:
    """A hypothesis refitted (Kabsch) on its inliers, a few times."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    for _ in range(_REFITS):
        r = np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1)
        inl = r < thr
        if inl.sum() < 3:
            break
        T = rigid_fit(a[inl], b[inl])
    return T


class ScanPyramid:
    """A cloud prepared once for many :func:`icp_pyramids` calls: level ``i`` voxel-averaged at
    ``scales[i] * spacing`` (coarse to fine, ending at 1: the points as given) with oriented
    normals (``normals`` used at the finest level when given, else estimated and oriented
    toward ``viewpoint``, default the origin)."""

    def __init__(
        self,
        points: NDArray,
        spacing: float,
        *,
        scales: tuple[float, ...] = (8.0, 4.0, 2.0, 1.0),
        normals: NDArray | None = None,
        viewpoint: NDArray | None = None,
    ) -> None:
        o3d = _o3d()
        pts = _check_points(points, "points")
        check_positive(spacing, "spacing")
        scales = tuple(float(s) for s in scales)
        if not scales or scales[-1] > 1:
            scales = scales + (1.0,)
        vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
        full = _make_cloud(pts, normals)
        self.spacing = float(spacing)
        self.scales = scales
        self.n_points = len(pts)
        self._levels = []
        for sc in scales:
            v = sc * spacing
            pc = full.voxel_down_sample(v) if sc > 1 else o3d.geometry.PointCloud(full)
            if sc <= 1 and normals is not None:
                n = np.asarray(pc.normals)
                pc.normals = o3d.utility.Vector3dVector(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12))
            else:
                pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3.0 * max(v, spacing), max_nn=20))
                pc.orient_normals_towards_camera_location(vp)
            self._levels.append(pc)
        self._trees: dict[int, cKDTree] = {}

    def finest(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Points and unit normals (M, 3) of the finest level."""
        return np.asarray(self._levels[-1].points), np.asarray(self._levels[-1].normals)

    def _level(self, scale: float) -> int:
        """Index of the level at ``scale`` (levels at or below 1 are the same)."""
        found = [i for i, sc in enumerate(self.scales) if max(sc, 1.0) == max(float(scale), 1.0)]
        if not found:
            raise InputError(f"scale: expected one of the pyramid's scales {self.scales}, got {scale}")
        return found[-1]

    def _level_arrays(self, i: int) -> tuple[NDArray[np.float64], NDArray[np.float64], cKDTree]:
        """Points, normals and a KD-tree (built once) of level ``i``."""
        if i not in self._trees:
            self._trees[i] = cKDTree(np.asarray(self._levels[i].points))
        return np.asarray(self._levels[i].points), np.asarray(self._levels[i].normals), self._trees[i]


def _icp_levels(source: ScanPyramid, first_scale: float | None, last_scale: float | None,
                max_iterations: int | tuple[int, ...]) -> list[tuple[int, int]]:
    """``(level, iterations)`` pairs from ``first_scale`` down to ``last_scale``."""
    levels = [i for i, sc in enumerate(source.scales)
              if (first_scale is None or sc <= first_scale) and (last_scale is None or sc >= last_scale)]
    if not levels:
        levels = [len(source.scales) - 1]
    its = (max_iterations,) * len(levels) if isinstance(max_iterations, int) else tuple(max_iterations)
    if len(its) != len(levels):
        raise InputError(f"max_iterations: expected {len(levels)} values (one per level), got {len(its)}")
    return list(zip(levels, its, strict=True))


def icp_pyramids(
    source: ScanPyramid,
    target: ScanPyramid,
    T_init: NDArray,
    *,
    first_scale: float | None = None,
    last_scale: float | None = None,
    max_iterations: int | tuple[int, ...] = 30,
    method: str = "point_to_plane",
) -> RegistrationResult:
    """Multi-scale rigid ICP [3]_ from ``T_init`` (4, 4) ``T_target_source``, between pyramids
    of the same scales and spacing, over the levels from ``first_scale`` to ``last_scale``
    (``max_iterations`` per level). Each level matches within ``2 v`` and weights by Tukey's
    biweight ``k = v`` (``v = max(scale, 1) * spacing``); ``method`` point_to_plane or
    point_to_point."""
    reg = _o3d().pipelines.registration
    check_choice(method, "method", ("point_to_plane", "point_to_point"))
    if source.scales != target.scales or source.spacing != target.spacing:
        raise InputError("source/target pyramids: built with different scales or spacing")
    T = np.asarray(check_array(T_init, "T_init", shape=(4, 4), dtype_kind="fiu"), dtype=np.float64)
    levels = _icp_levels(source, first_scale, last_scale, max_iterations)
    dist = 2.0 * source.spacing
    res = d_l = None
    for i, it in levels:
        s_l, d_l = source._levels[i], target._levels[i]
        if i != levels[-1][0] and min(len(s_l.points), len(d_l.points)) < min(_MIN_LEVEL_POINTS,
                                                                              source.n_points // 4):
            continue
        v = max(source.scales[i], 1.0) * source.spacing
        dist = 2.0 * v
        if method == "point_to_plane":
            est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=v))
        else:
            est = reg.TransformationEstimationPointToPoint(False)
        crit = reg.ICPConvergenceCriteria(relative_fitness=_ICP_RELATIVE, relative_rmse=_ICP_RELATIVE,
                                          max_iteration=int(it))
        res = reg.registration_icp(s_l, d_l, dist, T, est, crit)
        T = np.asarray(res.transformation, dtype=np.float64).copy()
    if res is None:
        raise ReconstructionError("ICP: no usable level")
    if np.linalg.det(T[:3, :3]) <= 0:  # cannot happen with a rigid estimator; never return one
        raise ReconstructionError("ICP returned a non-rotation")
    # registration_icp evaluates its result at the returned transform
    corr = np.asarray(res.correspondence_set)
    info = _information(np.asarray(d_l.points)[corr[:, 1]] if len(corr) else np.zeros((0, 3)))
    return RegistrationResult(T, float(res.fitness), float(res.inlier_rmse), info, float(dist))


def surface_noise(pyramid: ScanPyramid, *, scale: float = 1.0, sample: int = 3000, seed: int = 0) -> float:
    """Noise sigma (cloud units) of a prepared cloud's surface along its normals, on the level
    at ``scale``: the robust spread of (a seeded ``sample`` of) its points' distances from the
    tangent plane at their nearest neighbour, over sqrt(2); 0 without neighbours. Two aligned
    scans have a ``plane_sigma`` of about ``hypot(s1, s2)``."""
    x, n, tree = pyramid._level_arrays(pyramid._level(scale))
    q = np.random.default_rng(seed).choice(len(x), min(int(sample), len(x)), replace=False)
    d, idx = tree.query(x[q], k=2, distance_upper_bound=2.0 * max(float(scale), 1.0) * pyramid.spacing)
    ok = np.isfinite(d[:, 1])
    if not ok.any():
        return 0.0
    nb = idx[ok, 1]
    r = np.einsum("ij,ij->i", x[q[ok]] - x[nb], n[nb])
    return float(1.4826 * np.median(np.abs(r)) / np.sqrt(2.0))


def evaluate_pyramids(
    source: ScanPyramid,
    target: ScanPyramid,
    T_target_source: NDArray,
    *,
    max_distance: float,
    scale: float = 1.0,
    sample: int | None = None,
    seed: int = 0,
) -> tuple[float, float, float]:
    """``(fitness, inlier_rmse, plane_sigma)`` of two prepared clouds at ``T_target_source`` (no
    ICP step) within ``max_distance``, on the level at ``scale`` and a seeded ``sample`` of
    source points; ``plane_sigma`` is ``1.4826 * median(|d|)`` of the distances from the
    target's tangent planes (the surfaces' separation)."""
    if source.scales != target.scales or source.spacing != target.spacing:
        raise InputError("source/target pyramids: built with different scales or spacing")
    T = np.asarray(check_array(T_target_source, "T_target_source", shape=(4, 4), dtype_kind="fiu"),
                   dtype=np.float64)
    check_positive(max_distance, "max_distance")
    level = source._level(scale)
    x = np.asarray(source._levels[level].points)
    if sample is not None and check_positive(sample, "sample") < len(x):
        x = x[np.sort(np.random.default_rng(seed).choice(len(x), int(sample), replace=False))]
    y = x @ T[:3, :3].T + T[:3, 3]
    q, n, tree = target._level_arrays(level)
    d, j = query_tree(tree, y, distance_upper_bound=float(max_distance))
    ok = np.isfinite(d)
    if not ok.any():
        return 0.0, 0.0, 0.0
    r = np.einsum("ij,ij->i", y[ok] - q[j[ok]], n[j[ok]])
    return float(ok.mean()), float(np.sqrt(np.mean(d[ok] ** 2))), float(1.4826 * np.median(np.abs(r)))


def _information(q: NDArray) -> NDArray[np.float64]:
    """Information matrix of point correspondences at target points ``q`` (M, 3):
    ``sum J^T J`` with ``J = [[q]_x^T | I]`` (rotation first, Open3D's convention)."""
    J = np.zeros((len(q), 3, 6))
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    J[:, 0, 1], J[:, 0, 2] = z, -y
    J[:, 1, 0], J[:, 1, 2] = -z, x
    J[:, 2, 0], J[:, 2, 1] = y, -x
    J[:, 0, 3] = J[:, 1, 4] = J[:, 2, 5] = 1.0
    return np.einsum("mki,mkj->ij", J, J)


def refine_icp(
    source: NDArray,
    target: NDArray,
    T_init: NDArray,
    *,
    spacing: float | None = None,
    scales: tuple[float, ...] = (8.0, 4.0, 2.0, 1.0),
    max_iterations: tuple[int, ...] = (30, 30, 30, 40),
    source_normals: NDArray | None = None,
    target_normals: NDArray | None = None,
    viewpoint_target: NDArray | None = None,
    method: str = "point_to_plane",
) -> RegistrationResult:
    """Multi-scale rigid ICP [3]_ of ``source`` onto ``target`` (N, 3) from ``T_init``: both
    clouds as :class:`ScanPyramid` at ``scales`` of ``spacing`` (default :func:`point_spacing`
    of the source), then :func:`icp_pyramids`. ``point_to_point`` (no robust loss) is PCL's
    classic ICP; the default is more accurate on dense scans."""
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    check_array(T_init, "T_init", shape=(4, 4), dtype_kind="fiu")
    if spacing is None:
        spacing = point_spacing(src)
    check_positive(spacing, "spacing")
    check_choice(method, "method", ("point_to_plane", "point_to_point"))
    if len(scales) != len(max_iterations):
        raise InputError(f"scales and max_iterations: lengths differ ({len(scales)} vs {len(max_iterations)})")
    scales = tuple(scales)
    max_iterations = tuple(max_iterations)
    if scales[-1] > 1:
        scales, max_iterations = scales + (1.0,), max_iterations + (max_iterations[-1],)
    ps = ScanPyramid(src, spacing, scales=scales, normals=source_normals)
    pd = ScanPyramid(dst, spacing, scales=scales, normals=target_normals, viewpoint=viewpoint_target)
    return icp_pyramids(ps, pd, T_init, max_iterations=max_iterations, method=method)


def turntable_motion(T: NDArray, step_deg: float, *, tolerance_deg: float = 8.0) -> NDArray[np.float64] | None:
    """Project a measured view-to-view motion ``T`` (4, 4) onto an exact turntable step: its
    rotation axis, the angle exactly ``+-step_deg`` (sign of the measurement) and the axis
    position fitted to ``t = (I - R) c`` without ``t``'s along-axis part. None when ``T``'s
    angle is off ``|step_deg|`` by more than ``tolerance_deg``."""
    T = np.asarray(T, dtype=np.float64)
    rv = rotvec_from_matrix(T[:3, :3])
    ang = np.linalg.norm(rv)
    step = abs(np.radians(step_deg))
    if ang < 1e-9 or abs(np.degrees(ang - step)) > tolerance_deg:
        return None
    u = rv / ang
    R = rotation_about(u, step)
    t = T[:3, 3]
    t_perp = t - (t @ u) * u
    # axis point from the measured rotation (exact for a pure rotation), rebuilt at the step
    c, *_ = np.linalg.lstsq(np.eye(3) - T[:3, :3], t_perp, rcond=None)
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = (np.eye(3) - R) @ c
    return out


def register_pair(
    source: NDArray,
    target: NDArray,
    *,
    init: NDArray | None = None,
    spacing: float | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """Register ``source`` onto ``target`` (N, 3, each in its sensor frame): global registration
    (unless ``init`` is given) then :func:`refine_icp`."""
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    if spacing is None:
        spacing = point_spacing(src)
    if init is None:
        init, _, _ = global_register(src, dst, seed=seed)
    return refine_icp(src, dst, init, spacing=spacing)
