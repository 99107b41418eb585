"""Pairwise rigid registration of point clouds: global (FPFH + RANSAC) and ICP.

Everything here is rigid (rotation + translation: no scale, no reflection; every
returned rotation has ``det(R) = +1``) and deterministic (the RANSAC stage is our
own, driven by a seeded :class:`numpy.random.Generator`; Open3D computes normals,
FPFH descriptors and the ICP steps, which are deterministic).

Scales derive from the data: :func:`point_spacing` (median nearest-neighbour
distance) sets the ICP voxel and correspondence distances, and the global stage
picks the voxel that leaves a few thousand points, so clouds in metres and in
millimetres both work without tuning.

Open3D objects never leave this module's public functions.

References
----------
.. [1] R. B. Rusu, N. Blodow, M. Beetz, "Fast Point Feature Histograms (FPFH) for
   3D registration", ICRA 2009.
.. [2] M. A. Fischler, R. C. Bolles, "Random sample consensus", Comm. ACM 24(6),
   1981.
.. [3] Y. Chen, G. Medioni, "Object modelling by registration of multiple range
   images", Image and Vision Computing 10(3), 1992 (point-to-plane ICP).
.. [4] W. Kabsch, "A solution for the best rotation to relate two sets of
   vectors", Acta Cryst. A32, 1976.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from prism3d.checks import check_array, check_choice, check_positive
from prism3d.errors import InputError, ReconstructionError

__all__ = [
    "RegistrationResult",
    "ScanFeatures",
    "ScanPyramid",
    "evaluate_pyramids",
    "global_register",
    "icp_pyramids",
    "match_features",
    "match_features_candidates",
    "point_spacing",
    "refine_icp",
    "register_pair",
    "rigid_fit",
    "rotation_angle_deg",
    "surface_noise",
    "turntable_motion",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of registering a source cloud onto a target cloud.

    Attributes
    ----------
    T_target_source : (4, 4) float64
        Rigid transform mapping source points into the target frame.
    fitness : float
        Fraction of (down-sampled) source points with a target point within the
        final correspondence distance.
    inlier_rmse : float
        RMS distance of those correspondences (cloud units).
    information : (6, 6) float64
        Information matrix of the alignment (Open3D convention, rotation first),
        used to weight pose-graph edges.
    max_distance : float
        Correspondence distance of the final ICP level.
    """

    T_target_source: NDArray[np.float64]
    fitness: float
    inlier_rmse: float
    information: NDArray[np.float64]
    max_distance: float


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
    """Median nearest-neighbour distance of a cloud (its sampling step).

    Parameters
    ----------
    points : (N, 3) float
        At least 2 points.
    sample : int
        Number of query points (a seeded random subset when N is larger).
    seed : int

    Returns
    -------
    float
        Spacing in the cloud's units (> 0).
    """
    pts = _check_points(points, "points", min_points=2)
    tree = cKDTree(pts)
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


def rotation_angle_deg(T: NDArray) -> float:
    """Rotation angle of a 4x4 (or 3x3) transform, degrees in [0, 180]."""
    R = np.asarray(T)[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def rigid_fit(src: NDArray, dst: NDArray, weights: NDArray | None = None) -> NDArray[np.float64]:
    """Least-squares rigid transform (Kabsch) with ``det(R) = +1``.

    Parameters
    ----------
    src, dst : (N, 3) float
        Corresponding points, N >= 3.
    weights : (N,) float, optional

    Returns
    -------
    T_dst_src : (4, 4) float64
        Minimises ``sum w |R src + t - dst|^2`` over rotations (no reflection).
    """
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
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3.0 * voxel, max_nn=30))
        vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
        down.orient_normals_towards_camera_location(vp)
    else:
        n = np.asarray(down.normals)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        down.normals = o3d.utility.Vector3dVector(n / np.maximum(norm, 1e-12))
    return down


def _global_voxel(points: NDArray, spacing: float, target_points: int) -> float:
    pc = _make_cloud(points)
    v = max(spacing * 2.0, 1e-12)
    for _ in range(4):
        n = len(pc.voxel_down_sample(v).points)
        if n <= target_points * 1.3:
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
    """Coarse rigid alignment without an initial guess (FPFH + RANSAC).

    Parameters
    ----------
    source, target : (N, 3) float
        The clouds, any unit.
    voxel : float, optional
        Down-sampling voxel of the feature stage; default: the size leaving about
        ``target_points`` points of the source.
    target_points : int
    max_hypotheses : int
        RANSAC samples (3 mutual feature matches each, pre-filtered by an
        edge-length test).
    seed : int
        Seed of the sampler: the same inputs and seed give the same result.
    viewpoint_source, viewpoint_target : (3,) float, optional
        Sensor positions used to orient estimated normals (default the origin,
        i.e. each scan in its own camera frame).

    Returns
    -------
    T_target_source : (4, 4) float64
    inlier_fraction : float
        Fraction of feature matches consistent with the result.
    voxel : float
        The feature voxel used.

    References
    ----------
    .. [1] Rusu et al., ICRA 2009 (FPFH). .. [2] Fischler and Bolles, 1981.
    """
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    if voxel is None:
        voxel = _global_voxel(src, point_spacing(src), target_points)
    check_positive(voxel, "voxel")
    fs = ScanFeatures(src, voxel, viewpoint=viewpoint_source)
    fd = ScanFeatures(dst, voxel, viewpoint=viewpoint_target)
    T, frac = match_features(fs, fd, max_hypotheses=max_hypotheses, seed=seed)
    return T, frac, float(voxel)


class ScanFeatures:
    """FPFH descriptors of a cloud voxel-down-sampled at ``voxel`` (computed once
    per scan, matched against any number of other scans by :func:`match_features`).

    Parameters
    ----------
    points : (N, 3) float
    voxel : float
        Feature voxel (cloud units); normals use a ``3 * voxel`` radius and the
        descriptor a ``5 * voxel`` radius.
    viewpoint : (3,) float, optional
        Sensor position orienting normals (default the origin).

    Attributes
    ----------
    points : (M, 3) float64
    features : (M, 33) float64
    voxel : float
    """

    def __init__(self, points: NDArray, voxel: float, *, viewpoint: NDArray | None = None) -> None:
        o3d = _o3d()
        pts = _check_points(points, "points")
        check_positive(voxel, "voxel")
        down = _prepare(pts, voxel, viewpoint=viewpoint)
        if len(down.points) < 10:
            raise ReconstructionError("global registration: too few points after down-sampling")
        param = o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
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
    """RANSAC over mutual FPFH matches: coarse ``T_target_source``.

    Hypotheses are 3 matches passing an edge-length test (rigid motions keep
    distances); the one with most matches within ``1.5 * voxel`` wins and is
    refitted on its inliers. Deterministic for a given ``seed``. See
    :func:`match_features_candidates` for the runners-up.

    Returns
    -------
    T_target_source : (4, 4) float64
    inlier_fraction : float

    References
    ----------
    .. [1] Rusu et al., ICRA 2009. .. [2] Fischler and Bolles, 1981.
    """
    return match_features_candidates(source, target, max_hypotheses=max_hypotheses, seed=seed,
                                      max_candidates=1)[0]


def match_features_candidates(
    source: ScanFeatures,
    target: ScanFeatures,
    *,
    max_hypotheses: int = 40000,
    seed: int = 0,
    max_candidates: int = 5,
) -> list[tuple[NDArray[np.float64], float]]:
    """The best *distinct* RANSAC alignments, most feature inliers first.

    On objects with repeated or symmetric parts (a box-shaped truck seen end-on),
    the alignment with the most FPFH inliers can be wrong while the right one is
    a close runner-up; refining a few distinct candidates by ICP and keeping the
    best-fitting one (as :func:`~prism3d.reconstruct.stitch.stitch_scans` does)
    recovers it. Candidates differ by more than 10 deg or 10 feature voxels.

    Returns
    -------
    list of (T_target_source (4, 4) float64, inlier_fraction)
        At least one, at most ``max_candidates``.
    """
    voxel = max(source.voxel, target.voxel)
    ps, pd = source.points, target.points
    fs, fd = source.features, target.features
    _, s2d = target._tree.query(fs, k=1)
    _, d2s = source._tree.query(fd, k=1)
    mutual = d2s[s2d] == np.arange(len(fs))
    si = np.nonzero(mutual)[0]
    if len(si) < 30:
        si = np.arange(len(fs))
    a = ps[si]
    b = pd[s2d[si]]
    nc = len(a)
    if nc < 3:
        raise ReconstructionError("global registration: fewer than 3 feature matches")
    rng = np.random.default_rng(seed)
    thr = 1.5 * voxel
    best_count = -1
    pool_R: list[NDArray] = []
    pool_t: list[NDArray] = []
    pool_c: list[NDArray] = []
    batch = 1000
    keep_per_batch = 4 * max(1, int(max_candidates))
    done = 0
    while done < max_hypotheses:
        idx = rng.integers(0, nc, size=(batch * 3, 3))
        A = a[idx]
        B = b[idx]
        # Edge-length (tuple) test: rigid motions preserve pairwise distances.
        la = np.linalg.norm(A - np.roll(A, 1, axis=1), axis=2)
        lb = np.linalg.norm(B - np.roll(B, 1, axis=1), axis=2)
        ok = (np.minimum(la, lb) > 0.9 * np.maximum(la, lb)).all(axis=1) & (la.min(axis=1) > 2 * voxel)
        A = A[ok][:batch]
        B = B[ok][:batch]
        done += batch
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
        # Standard RANSAC stopping rule (99.99 % confidence of one clean sample),
        # counted in sampled triples; deterministic because it depends on counts only.
        w = best_count / nc
        if w > 0 and done >= 4 * batch:
            need = np.log(1e-4) / np.log(max(1e-12, 1.0 - min(w, 0.999) ** 3))
            if done >= need:
                break
    if best_count < 3:
        raise ReconstructionError("global registration: RANSAC found no consistent feature matches")
    Rs = np.concatenate(pool_R)
    ts = np.concatenate(pool_t)
    cs = np.concatenate(pool_c)
    order = np.argsort(-cs, kind="stable")
    out: list[tuple[NDArray[np.float64], float]] = []
    chosen: list[NDArray] = []
    for k in order:
        if cs[k] < 3 or len(out) >= max_candidates:
            break
        T = np.eye(4)
        T[:3, :3] = Rs[k]
        T[:3, 3] = ts[k]
        for _ in range(3):
            r = np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1)
            inl = r < thr
            if inl.sum() < 3:
                break
            T = rigid_fit(a[inl], b[inl])
        if any(
            rotation_angle_deg(_rigid_inv(C) @ T) < 10.0 and np.linalg.norm(C[:3, 3] - T[:3, 3]) < 10 * voxel
            for C in chosen
        ):
            continue
        chosen.append(T)
        r = np.linalg.norm(a @ T[:3, :3].T + T[:3, 3] - b, axis=1)
        out.append((T, float((r < thr).mean())))
    return out


def _rigid_inv(T: NDArray) -> NDArray[np.float64]:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


class ScanPyramid:
    """A cloud prepared for repeated ICP: voxel levels with oriented normals.

    Built once per scan (down-sampling and normal estimation dominate the cost of
    a well-initialised ICP), then used as source or target of any number of
    :func:`icp_pyramids` calls. Level ``i`` is the cloud voxel-averaged at
    ``scales[i] * spacing`` (``scales[i] <= 1``: the points as given).

    Parameters
    ----------
    points : (N, 3) float
    spacing : float
        Point spacing of ``points`` (cloud units).
    scales : tuple of float
        Coarse to fine; a final ``1.0`` is appended when missing.
    normals : (N, 3) float, optional
        Used at the finest level instead of estimated normals.
    viewpoint : (3,) float, optional
        Sensor position orienting estimated normals (default the origin).
    """

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

    def level_sizes(self) -> list[int]:
        """Number of points per level, coarse to fine."""
        return [len(pc.points) for pc in self._levels]

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
    """Multi-scale rigid ICP between two prepared clouds.

    At each level (coarse to fine, starting at ``first_scale``) correspondences
    are searched within ``2 * max(scale, 1) * spacing`` and weighted by Tukey's
    biweight (``k = max(scale, 1) * spacing``), which discounts boundary and
    non-overlap pairs; the point-to-plane step is solved by Gauss-Newton.

    Parameters
    ----------
    source, target : ScanPyramid
        Built with the same ``scales`` and ``spacing``.
    T_init : (4, 4) float
        Initial ``T_target_source``.
    first_scale : float, optional
        Skip the levels coarser than this (a good ``T_init`` needs only the fine
        levels).
    last_scale : float, optional
        Stop after the level at this scale (a cheap coarse evaluation, e.g. to
        rank several initial guesses).
    max_iterations : int or tuple of int
        Per level.
    method : {"point_to_plane", "point_to_point"}

    Returns
    -------
    RegistrationResult

    References
    ----------
    .. [3] Chen and Medioni, 1992.
    """
    o3d = _o3d()
    reg = o3d.pipelines.registration
    check_choice(method, "method", ("point_to_plane", "point_to_point"))
    if source.scales != target.scales or source.spacing != target.spacing:
        raise InputError("source/target pyramids: built with different scales or spacing")
    T = np.asarray(check_array(T_init, "T_init", shape=(4, 4), dtype_kind="fiu"), dtype=np.float64)
    spacing = source.spacing
    levels = [i for i, sc in enumerate(source.scales)
              if (first_scale is None or sc <= first_scale) and (last_scale is None or sc >= last_scale)]
    if not levels:
        levels = [len(source.scales) - 1]
    its = (max_iterations,) * len(levels) if isinstance(max_iterations, int) else tuple(max_iterations)
    if len(its) != len(levels):
        raise InputError(f"max_iterations: expected {len(levels)} values (one per level), got {len(its)}")
    dist = 2.0 * spacing
    s_l = d_l = None
    ran = False
    for i, it in zip(levels, its, strict=True):
        sc = source.scales[i]
        s_l, d_l = source._levels[i], target._levels[i]
        last = i == levels[-1]
        if not last and min(len(s_l.points), len(d_l.points)) < min(1500, source.n_points // 4):
            continue  # too coarse for this cloud: a handful of points only misleads ICP
        v = max(sc, 1.0) * spacing
        dist = 2.0 * v
        if method == "point_to_plane":
            est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=v))
        else:
            est = reg.TransformationEstimationPointToPoint(False)
        res = reg.registration_icp(
            s_l, d_l, dist, T, est,
            reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=int(it)),
        )
        T = np.asarray(res.transformation, dtype=np.float64).copy()
        ran = True
    if not ran or s_l is None:
        raise ReconstructionError("ICP: no usable level")
    if np.linalg.det(T[:3, :3]) <= 0:  # cannot happen with a rigid estimator; never return one
        raise ReconstructionError("ICP returned a non-rotation")
    # registration_icp evaluates its result (fitness, RMSE, correspondences) at
    # the returned transform.
    corr = np.asarray(res.correspondence_set)
    info = _information(np.asarray(d_l.points)[corr[:, 1]] if len(corr) else np.zeros((0, 3)))
    return RegistrationResult(T, float(res.fitness), float(res.inlier_rmse), info, float(dist))


def surface_noise(pyramid: ScanPyramid, *, scale: float = 1.0, sample: int = 3000, seed: int = 0) -> float:
    """Noise of a prepared cloud's surface along its normals.

    Two independent samples of one surface with noise ``sigma`` along the normal lie
    ``sqrt(2) * sigma`` apart along it; within one scan, a point and its nearest
    neighbour are such a pair. So ``sigma`` is the spread (``1.4826 * median(|d|)``, like
    ``plane_sigma`` of :func:`evaluate_pyramids`) of (a seeded sample of) the level's
    points' distances from the tangent plane at their nearest neighbour within the
    level's correspondence distance, over ``sqrt(2)``. Two correctly aligned scans with
    noises ``s1`` and ``s2`` have a ``plane_sigma`` of about ``hypot(s1, s2)``.

    Parameters
    ----------
    pyramid : ScanPyramid
    scale : float
        Level, one of the pyramid's ``scales`` (1: the finest).
    sample : int
        Number of query points (all when the level is smaller).
    seed : int

    Returns
    -------
    float
        Cloud units; 0 when no point has a neighbour within reach.
    """
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
    """Overlap and residuals of two prepared clouds at a given alignment (no ICP step).

    Measures what :func:`icp_pyramids` reports for its result at any transform, e.g.
    a pair at the poses of a global optimisation. The point-to-point RMSE of correctly
    aligned scans is dominated by their sampling (the nearest target point lies up to
    half a voxel away sideways) and is bounded by ``max_distance``, so it barely grows
    with a misalignment; the spread along the target's normals is the surfaces'
    separation: their noise when aligned (:func:`surface_noise`), more when not.

    Parameters
    ----------
    source, target : ScanPyramid
        Built with the same ``scales`` and ``spacing``.
    T_target_source : (4, 4) float
    max_distance : float
        Correspondence distance (cloud units).
    scale : float
        Level to measure on, one of the pyramids' ``scales`` (1: the finest, where
        :func:`icp_pyramids` ends unless given ``last_scale``).
    sample : int, optional
        Measure on this many of the source level's points (a seeded random subset,
        the same for every call with the same source and ``seed``); default all.
    seed : int

    Returns
    -------
    fitness : float
        Fraction of the source level's points with a target point within
        ``max_distance`` (Open3D's ``fitness``; as :func:`icp_pyramids` reports).
    inlier_rmse : float
        RMS distance of those correspondences (cloud units; Open3D's ``inlier_rmse``,
        0 when there are none).
    plane_sigma : float
        ``1.4826 * median(|d|)`` of the same source points' distances ``d`` from their
        target points' tangent planes (cloud units; 0 when there are none).
    """
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
    d, j = tree.query(y, distance_upper_bound=float(max_distance))
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
    """Multi-scale point-to-plane ICP (rigid).

    Level ``i`` down-samples both clouds at ``scales[i] * spacing`` and matches
    within ``2 * max(scales[i], 1) * spacing``, with Tukey's robust loss
    (``k = max(scales[i], 1) * spacing``). See :class:`ScanPyramid` and
    :func:`icp_pyramids` to prepare each cloud once for many registrations.

    Parameters
    ----------
    source, target : (N, 3) float
    T_init : (4, 4) float
        Initial ``T_target_source``.
    spacing : float, optional
        Point spacing; default :func:`point_spacing` of the source.
    scales : tuple of float
        Voxel sizes in units of ``spacing``, coarse to fine (``<= 1``: no
        down-sampling at the last level).
    max_iterations : tuple of int
        Per level.
    source_normals, target_normals : (N, 3) float, optional
        Used instead of estimated normals where given.
    viewpoint_target : (3,) float, optional
        Sensor position orienting estimated target normals.
    method : {"point_to_plane", "point_to_point"}
        ``point_to_point`` (plain least squares, no robust loss) reproduces the
        classic ICP of PCL; the default is more accurate on dense scans.

    Returns
    -------
    RegistrationResult

    References
    ----------
    .. [3] Chen and Medioni, 1992.
    """
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


def _rotvec(R: NDArray) -> NDArray[np.float64]:
    angle = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.pi - angle < 1e-6:
        # Near 180 deg: axis from the symmetric part.
        M = (R + np.eye(3)) / 2.0
        ax = M[np.argmax(np.diag(M))]
        return ax / np.linalg.norm(ax) * angle
    return w / (2.0 * np.sin(angle)) * angle


def _rotation(axis: NDArray, angle_rad: float) -> NDArray[np.float64]:
    u = np.asarray(axis, dtype=np.float64)
    u = u / np.linalg.norm(u)
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K


def turntable_motion(T: NDArray, step_deg: float, *, tolerance_deg: float = 8.0) -> NDArray[np.float64] | None:
    """Project a measured view-to-view motion onto an exact turntable step.

    A turntable step is a pure rotation by ``step_deg`` about a fixed axis (no
    translation along it). From a measured ``T`` (e.g. a global registration of two
    consecutive scans) take the rotation axis direction, set the angle to exactly
    ``+-step_deg`` (sign of the measurement) and the axis position to the least-
    squares fit of ``t = (I - R) c`` with ``t``'s along-axis part removed.

    Parameters
    ----------
    T : (4, 4) float
    step_deg : float
        The known step, degrees (its sign is taken from ``T``).
    tolerance_deg : float
        ``None`` is returned when ``T``'s angle differs from ``|step_deg|`` by more.

    Returns
    -------
    (4, 4) float64 or None
    """
    T = np.asarray(T, dtype=np.float64)
    rv = _rotvec(T[:3, :3])
    ang = np.linalg.norm(rv)
    step = abs(np.radians(step_deg))
    if ang < 1e-9 or abs(np.degrees(ang - step)) > tolerance_deg:
        return None
    u = rv / ang
    R = _rotation(u, step)
    t = T[:3, 3]
    t_perp = t - (t @ u) * u
    # Axis point from the measured rotation (exact for a pure rotation), then
    # re-built with the exact step angle.
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
    """Register ``source`` onto ``target``: global registration (unless ``init``
    is given) followed by multi-scale point-to-plane ICP.

    Parameters
    ----------
    source, target : (N, 3) float
        Clouds in any unit; each in its sensor frame (normals are oriented toward
        the origin).
    init : (4, 4) float, optional
        Initial ``T_target_source``; skips the global stage.
    spacing : float, optional
        Default: :func:`point_spacing` of the source.
    seed : int

    Returns
    -------
    RegistrationResult
    """
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    if spacing is None:
        spacing = point_spacing(src)
    if init is None:
        init, _, _ = global_register(src, dst, seed=seed)
    return refine_icp(src, dst, init, spacing=spacing)
