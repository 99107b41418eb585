"""Joint multi-view ICP: every view moved so that its points lie on the surfaces of every
view it overlaps (point-to-plane, Tukey-weighted, Gauss-Newton, the first view fixed), free
or on one turntable axis. Measurements: ``docs/stitching.md``.

References
----------
.. [1] R. Bergevin et al., "Towards a general multi-view registration technique", TPAMI 1996.
.. [2] K. Pulli, "Multiview registration for large data sets", 3DIM 1999.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError, ReconstructionError
from prism3d.geometry import rotation_angle_deg, rotvec_from_matrix
from prism3d.reconstruct.scan.neighbours import query_tree

__all__ = ["fit_turntable", "overlapping_pairs", "refine_multiview", "refine_turntable"]

log = logging.getLogger(__name__)

# Correspondences are searched within this many spacings (Tukey's constant is one spacing).
_SEARCH_SPACINGS = 3.0
# A view pair direction with fewer weighted correspondences than this adds nothing (6 unknowns).
_MIN_CORRESPONDENCES = 6
# The initial poses are close (pose graph): a step turning a view by more than this is a
# weakly constrained direction (a smooth, symmetric surface sliding), so it is scaled down.
_MAX_STEP_DEG = 1.0
# Levenberg damping of the normal equations, relative to their mean diagonal.
_DAMPING = 1e-9
#: Default stop: a Gauss-Newton step turning no view by more than this (degrees). The
#: steps stop shrinking at 2-3e-4 deg (the correspondences' and weights' jitter), so a
#: finer stop only repeats iterations; 1e-3 deg is 50x below the stitcher's 0.05-deg pose
#: bound (docs/performance.md, "Stitching: voxel means, fewer repeated registrations").
TOLERANCE_DEG = 1e-3
# Step of the numerical Jacobian of the view twists in the turntable parameters (rad, units).
_JACOBIAN_STEP = 1e-6


def _expmap(w: NDArray[np.float64]) -> NDArray[np.float64]:
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


class _Problem:
    """Points, normals, trees and the point-to-plane normal equations shared by the
    free and the turntable-constrained refinements."""

    def __init__(self, points: Sequence[NDArray], normals: Sequence[NDArray], T_model_scan: Sequence[NDArray],
                 pairs: Sequence[tuple[int, int]], spacing: float, min_normal_cos: float,
                 max_query_points: int, name: str) -> None:
        n = len(points)
        if n < 2 or len(normals) != n or len(T_model_scan) != n:
            raise InputError(f"{name}: need >= 2 views with points, normals and a pose each")
        check_positive(spacing, "spacing")
        self.P = [np.asarray(check_array(p, f"points[{k}]", ndim=2, dtype_kind="f"), dtype=np.float64)
                  for k, p in enumerate(points)]
        self.N = [np.asarray(check_array(v, f"normals[{k}]", shape=self.P[k].shape, dtype_kind="f"),
                             dtype=np.float64) for k, v in enumerate(normals)]
        self.T0 = [np.array(check_array(t, f"T_model_scan[{k}]", shape=(4, 4), dtype_kind="f"), dtype=np.float64)
                   for k, t in enumerate(T_model_scan)]
        prs = sorted({(min(i, j), max(i, j)) for i, j in pairs if i != j})
        if not prs or any(not (0 <= i < n and 0 <= j < n) for i, j in prs):
            raise InputError(f"{name}: pairs must index the {n} views, got {pairs!r}")
        self.n, self.pairs = n, prs
        self.trees = [cKDTree(p) for p in self.P]
        stride = [max(1, -(-len(p) // int(max_query_points))) for p in self.P]
        self.Q = [p[::st] for p, st in zip(self.P, stride, strict=True)]
        self.QN = [v[::st] for v, st in zip(self.N, stride, strict=True)]
        self.k_tukey = float(spacing)
        self.dist = _SEARCH_SPACINGS * self.k_tukey
        self.min_normal_cos = float(min_normal_cos)
        # perturbations about the centroid keep rotation and translation decoupled
        self.c = np.mean([t[:3, :3] @ p.mean(axis=0) + t[:3, 3] for p, t in zip(self.P, self.T0, strict=True)],
                         axis=0)
    def normal_equations(self, T: Sequence[NDArray]) -> tuple[NDArray, NDArray, float, float, int]:
        """Gauss-Newton system ``H x = -g`` in the left twists (about the centroid) of
        all views, with the weighted squared residual, the weight sum and the
        number of correspondences."""
        n, P, N, Q, QN, trees, c = self.n, self.P, self.N, self.Q, self.QN, self.trees, self.c
        k_tukey, dist, min_normal_cos, pairs = self.k_tukey, self.dist, self.min_normal_cos, self.pairs
        H = np.zeros((6 * n, 6 * n))
        g = np.zeros(6 * n)
        cost = wsum = 0.0
        n_corr = 0
        for i, j in pairs:
            for a, b in ((i, j), (j, i)):
                M = np.linalg.solve(T[b], T[a])  # a's frame -> b's frame
                pa = Q[a] @ M[:3, :3].T + M[:3, 3]
                dd, idx = query_tree(trees[b], pa, distance_upper_bound=dist)
                ok = np.isfinite(dd)
                if not ok.any():
                    continue
                pa = pa[ok]
                qb = P[b][idx[ok]]
                nb = N[b][idx[ok]]
                na = QN[a][ok] @ M[:3, :3].T
                ok = np.einsum("ij,ij->i", na, nb) > min_normal_cos
                pa, qb, nb = pa[ok], qb[ok], nb[ok]
                r = np.einsum("ij,ij->i", nb, pa - qb)
                w = np.where(np.abs(r) < k_tukey, (1.0 - (r / k_tukey) ** 2) ** 2, 0.0)
                keep = w > 0
                if keep.sum() < _MIN_CORRESPONDENCES:
                    continue
                pa, qb, nb, r, w = pa[keep], qb[keep], nb[keep], r[keep], w[keep]
                # to the model frame, centred
                Rb, tb = T[b][:3, :3], T[b][:3, 3]
                pm = pa @ Rb.T + tb - c
                qm = qb @ Rb.T + tb - c
                nm = nb @ Rb.T
                Ja = np.hstack([np.cross(pm, nm), nm])
                Jb = -np.hstack([np.cross(qm, nm), nm])
                for u, Ju in ((a, Ja), (b, Jb)):
                    Jw = Ju * w[:, None]
                    g[6 * u: 6 * u + 6] += Jw.T @ r
                    for v, Jv in ((a, Ja), (b, Jb)):
                        H[6 * u: 6 * u + 6, 6 * v: 6 * v + 6] += Jw.T @ Jv
                cost += float(np.sum(w * r * r))
                wsum += float(np.sum(w))
                n_corr += len(r)
        return H, g, cost, wsum, n_corr


def _view_levers(H: NDArray, n: int, twist: NDArray | None = None) -> list[float]:
    """Per view, ``sqrt(info / W)`` from its 6x6 block of ``H`` (``W`` the weight sum, ``info``
    that of ``twist``, else of the weakest rotation): how firmly it is held, as a length."""
    out = []
    for k in range(n):
        B = H[6 * k: 6 * k + 6, 6 * k: 6 * k + 6]
        W = float(np.trace(B[3:, 3:]))
        if W <= 0:
            out.append(0.0)
            continue
        if twist is not None:
            info = float(twist @ B @ twist)
        else:
            Btt = B[3:, 3:] + 1e-12 * W * np.eye(3)
            S = B[:3, :3] - B[:3, 3:] @ np.linalg.solve(Btt, B[3:, :3])
            info = float(np.linalg.eigvalsh(0.5 * (S + S.T))[0])
        out.append(float(np.sqrt(max(info, 0.0) / W)))
    return out


def overlapping_pairs(
    points: Sequence[NDArray],
    normals: Sequence[NDArray],
    T_model_scan: Sequence[NDArray],
    *,
    spacing: float,
    min_fraction: float = 0.02,
    sample: int = 2000,
    min_normal_cos: float = 0.7,
) -> list[tuple[int, int]]:
    """Every pair ``(i, j)``, ``i < j``, of views whose surfaces overlap at the given poses: in
    either direction at least ``min_fraction`` of a strided ``sample`` of one view's points has
    a point of the other within ``3 * spacing`` whose normal agrees (cosine above
    ``min_normal_cos``), the refinements' correspondence test."""
    n = len(points)
    if len(normals) != n or len(T_model_scan) != n:
        raise InputError("overlapping_pairs: need points, normals and a pose for every view")
    check_positive(spacing, "spacing")
    P = [np.asarray(p, dtype=np.float64) for p in points]
    N = [np.asarray(v, dtype=np.float64) for v in normals]
    T = [np.asarray(t, dtype=np.float64) for t in T_model_scan]
    trees = [cKDTree(p) if len(p) else None for p in P]
    dist = _SEARCH_SPACINGS * float(spacing)
    out = []
    for i in range(n):
        for j in range(i + 1, n):
            frac = 0.0
            for a, b in ((i, j), (j, i)):
                tree = trees[b]
                if tree is None or len(P[a]) == 0:
                    continue
                st = max(1, -(-len(P[a]) // int(sample)))
                M = np.linalg.solve(T[b], T[a])
                q = P[a][::st] @ M[:3, :3].T + M[:3, 3]
                d, idx = query_tree(tree, q, distance_upper_bound=dist)
                hit = np.isfinite(d)
                if hit.any():
                    na = N[a][::st][hit] @ M[:3, :3].T
                    ok = np.einsum("ij,ij->i", na, N[b][idx[hit]]) > min_normal_cos
                    frac = max(frac, float(ok.sum()) / len(q))
            if frac >= min_fraction:
                out.append((i, j))
    return out


def _max_rotation_deg(A: Sequence[NDArray], B: Sequence[NDArray]) -> float:
    """Largest rotation between corresponding poses, degrees."""
    return max(rotation_angle_deg(a[:3, :3].T @ b[:3, :3]) for a, b in zip(A, B, strict=True))


def _apply_twist(T: NDArray, x6: NDArray, c: NDArray) -> NDArray:
    """``E T`` with ``E`` the rotation ``x6[:3]`` about ``c`` followed by the shift ``x6[3:]``."""
    E = np.eye(4)
    E[:3, :3] = _expmap(x6[:3])
    E[:3, 3] = x6[3:] + c - E[:3, :3] @ c
    return E @ T


def _rms(cost: float, wsum: float) -> float:
    return float(np.sqrt(cost / max(wsum, 1e-12)))


def _damped_solve(Hr: NDArray, g: NDArray, what: str) -> NDArray:
    """``-Hr^-1 g`` with a tiny Levenberg damping; a view without correspondences fails."""
    if np.min(np.abs(np.diag(Hr))) <= 0:
        raise ReconstructionError(f"{what}: a view has no correspondences with its neighbours")
    m = len(Hr)
    return -np.linalg.solve(Hr + _DAMPING * np.trace(Hr) / m * np.eye(m), g)


def _largest_turn(x: NDArray, views: int) -> float:
    """Largest rotation (rad) among ``views`` stacked 6-vectors."""
    return float(np.max(np.linalg.norm(x.reshape(views, 6)[:, :3], axis=1)))


def refine_multiview(
    points: Sequence[NDArray],
    normals: Sequence[NDArray],
    T_model_scan: Sequence[NDArray],
    pairs: Sequence[tuple[int, int]],
    *,
    spacing: float,
    max_iterations: int = 12,
    tolerance_deg: float = TOLERANCE_DEG,
    min_normal_cos: float = 0.7,
    max_query_points: int = 10000,
) -> tuple[list[NDArray[np.float64]], dict[str, float]]:
    """Refine all poses ``T_model_scan`` (4, 4), accurate to about ``spacing``, jointly (the
    first view fixed) over the overlapping ``pairs`` of views with ``points``, ``normals``
    (N_k, 3) in their own frames. Tukey's constant is ``spacing``; correspondences within
    ``3 * spacing``, normals' cosine above ``min_normal_cos``, from ``max_query_points`` per
    view; stops after ``max_iterations`` or a step below ``tolerance_deg``. Returns the poses
    and ``info``: ``iterations``, ``rms``, ``max_change_deg``, ``correspondences``, ``levers``."""
    prob = _Problem(points, normals, T_model_scan, pairs, spacing, min_normal_cos, max_query_points,
                    "refine_multiview")
    n, c = prob.n, prob.c
    T = [t.copy() for t in prob.T0]
    T_init = [t.copy() for t in T]
    it = 0
    rms = float("nan")
    n_corr = 0
    H = np.zeros((6 * n, 6 * n))
    for it in range(1, int(max_iterations) + 1):
        H, g, cost, wsum, n_corr = prob.normal_equations(T)
        x = np.r_[np.zeros(6), _damped_solve(H[6:, 6:], g[6:], "multi-view refinement")]
        big = _largest_turn(x, n)
        if big > np.radians(_MAX_STEP_DEG):
            x *= np.radians(_MAX_STEP_DEG) / big
        rms = _rms(cost, wsum)
        step = 0.0
        for k in range(1, n):
            T[k] = _apply_twist(T[k], x[6 * k: 6 * k + 6], c)
            step = max(step, float(np.degrees(np.linalg.norm(x[6 * k: 6 * k + 3]))))
        log.debug("multi-view ICP iteration %d: rms %.4g, largest rotation step %.2e deg", it, rms, step)
        if step < tolerance_deg:
            break
    change = _max_rotation_deg(T, T_init)
    # the last iteration's system (the poses moved by < tolerance_deg since, or by its step)
    return T, {"iterations": float(it), "rms": rms, "max_change_deg": change, "correspondences": float(n_corr),
               "levers": _view_levers(H, n)}
def _basis(u: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two unit vectors completing ``u`` to a right-handed orthonormal basis."""
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def _turntable_pose(u: NDArray, p: NDArray, theta: float) -> NDArray[np.float64]:
    """Rotation by ``theta`` about the line through ``p`` with direction ``u``."""
    T = np.eye(4)
    T[:3, :3] = _expmap(u * theta)
    T[:3, 3] = p - T[:3, :3] @ p
    return T


def fit_turntable(T_model_scan: Sequence[NDArray]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The turntable closest to poses whose first is the identity: axis direction ``u`` (the
    angle-weighted mean axis), a point ``p`` on it (least squares ``(I - R_k) p = t_k``,
    nearest the origin) and each view's angle about ``u``."""
    rv = [rotvec_from_matrix(np.asarray(T, float)[:3, :3]) for T in T_model_scan[1:]]
    ref = max(rv, key=np.linalg.norm)
    u = np.sum([v if v @ ref >= 0 else -v for v in rv], axis=0)
    u /= max(np.linalg.norm(u), 1e-300)
    e1, _ = _basis(u)
    theta = [0.0]
    for T in T_model_scan[1:]:
        Re1 = np.asarray(T, float)[:3, :3] @ e1
        theta.append(float(np.arctan2(u @ np.cross(e1, Re1), e1 @ Re1)))
    A = np.vstack([np.eye(3) - _expmap(u * th) for th in theta[1:]])
    b = np.concatenate([np.asarray(T, float)[:3, 3] for T in T_model_scan[1:]])
    p, *_ = np.linalg.lstsq(A, b, rcond=None)
    p = p - (p @ u) * u
    return u, p, np.asarray(theta)


def _turntable_poses(u: NDArray, p: NDArray, theta: NDArray) -> list[NDArray[np.float64]]:
    """Poses of all views (the first the identity) on the axis ``(u, p)`` at angles ``theta``."""
    return [np.eye(4)] + [_turntable_pose(u, p, float(t)) for t in theta[1:]]


def _perturb_turntable(delta: NDArray, u: NDArray, p: NDArray, theta: NDArray,
                       n: int) -> tuple[NDArray, NDArray, NDArray]:
    """Turntable moved by ``delta``: ``n - 1`` angles, then two axis tilts and two axis shifts."""
    e1, e2 = _basis(u)
    un = u + delta[n - 1] * e1 + delta[n] * e2
    un /= np.linalg.norm(un)
    pn = p + delta[n + 1] * e1 + delta[n + 2] * e2
    thn = theta.copy()
    thn[1:] += delta[: n - 1]
    return un, pn - (pn @ un) * un, thn


def _twist(E: NDArray, c: NDArray) -> NDArray:
    """Left twist (6,) about ``c`` of a small motion ``E``."""
    return np.r_[rotvec_from_matrix(E[:3, :3]), E[:3, 3] - c + E[:3, :3] @ c]


def _turntable_jacobian(u: NDArray, p: NDArray, theta: NDArray, T: list[NDArray], c: NDArray) -> NDArray:
    """``d(view twists) / d(turntable parameters)``, (6 (n - 1), n + 3), numerically."""
    n = len(T)
    m = (n - 1) + 4
    h = _JACOBIAN_STEP
    J = np.zeros((6 * (n - 1), m))
    for j in range(m):
        d = np.zeros(m)
        d[j] = h
        Tp = _turntable_poses(*_perturb_turntable(d, u, p, theta, n))
        for k in range(1, n):
            J[6 * (k - 1): 6 * k, j] = _twist(Tp[k] @ np.linalg.inv(T[k]), c) / h
    return J


def refine_turntable(
    points: Sequence[NDArray],
    normals: Sequence[NDArray],
    T_model_scan: Sequence[NDArray],
    pairs: Sequence[tuple[int, int]],
    *,
    spacing: float,
    max_iterations: int = 12,
    tolerance_deg: float = TOLERANCE_DEG,
    min_normal_cos: float = 0.7,
    max_query_points: int = 10000,
) -> tuple[list[NDArray[np.float64]], dict[str, float]]:
    """Joint multi-view ICP with every view on one turntable axis (the first view the model
    frame, its pose the identity): the axis (4 parameters) and one angle per view, fitted to
    :func:`refine_multiview`'s residuals by Gauss-Newton through the numerical Jacobian of the
    view twists. Parameters and returns as :func:`refine_multiview`; ``info`` also holds
    ``rms_input`` (at the input poses: a much larger ``rms`` says the views do not share an
    axis), ``axis``, ``axis_point``, ``angles_deg`` and ``levers`` (about the axis)."""
    prob = _Problem(points, normals, T_model_scan, pairs, spacing, min_normal_cos, max_query_points,
                    "refine_turntable")
    n, c = prob.n, prob.c
    T_in = prob.T0
    if not np.allclose(T_in[0], np.eye(4), atol=1e-9):
        raise InputError("refine_turntable: the first view's pose must be the identity (the model frame)")
    u, p, theta = fit_turntable(T_in)
    _, _, cost0, wsum0, _ = prob.normal_equations(T_in)
    T = _turntable_poses(u, p, theta)
    it = 0
    for it in range(1, int(max_iterations) + 1):
        H, g, cost, wsum, n_corr = prob.normal_equations(T)
        J = _turntable_jacobian(u, p, theta, T, c)
        delta = _damped_solve(J.T @ H[6:, 6:] @ J, J.T @ g[6:], "turntable refinement")
        x = J @ delta
        big = _largest_turn(x, n - 1)
        if big > np.radians(_MAX_STEP_DEG):
            delta *= np.radians(_MAX_STEP_DEG) / big
            x = J @ delta
        u, p, theta = _perturb_turntable(delta, u, p, theta, n)
        T = _turntable_poses(u, p, theta)
        step = float(np.degrees(_largest_turn(x, n - 1)))
        log.debug("turntable ICP iteration %d: rms %.4g, largest rotation step %.2e deg", it, _rms(cost, wsum), step)
        if step < tolerance_deg:
            break
    H, g, cost, wsum, n_corr = prob.normal_equations(T)
    return T, {"iterations": float(it), "rms": _rms(cost, wsum), "rms_input": _rms(cost0, wsum0),
               "max_change_deg": _max_rotation_deg(T, T_in), "correspondences": float(n_corr), "axis": u.tolist(),
               "axis_point": p.tolist(), "angles_deg": np.degrees(theta).tolist(),
               "levers": _view_levers(H, n, np.r_[u, np.cross(u, c - p)])}
