"""Joint multi-view ICP: refine all view poses together against all their overlaps.

Pairwise registration followed by a pose graph treats each pair's result as a
measurement; when the scans carry view-dependent errors (a stereo scan's depth
noise, a partial overlap), each pair's optimum is biased a little differently and
the pose graph can only distribute the disagreement. Here every view is instead
moved so that, *simultaneously*, its points lie on the surfaces of every view it
overlaps (point-to-plane, Tukey-weighted), with all poses as unknowns (the first
view fixed). This is the simultaneous registration of Bergevin et al. [1]_ and
Pulli [2]_, solved by Gauss-Newton on a ``6 (n - 1)`` parameter system with
correspondences re-found at every iteration.

Measured on 8 matcher-reconstructed turntable views of a camouflaged tank (paper
rig, grating on): the pose graph's view poses 0.04-0.47 deg from the truth, after
this step 0.01-0.05 deg -- the same as when it is started from the true poses (on
four targets, 0.05-0.07 deg at worst: the scans' own depth errors are the limit).
On scans of the true depth with 0.15 mm noise: 0.053 -> 0.018 deg.

References
----------
.. [1] R. Bergevin, M. Soucy, H. Gagnon, D. Laurendeau, "Towards a general
   multi-view registration technique", IEEE TPAMI 18(5), 1996.
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

__all__ = ["refine_multiview"]

log = logging.getLogger(__name__)


def _expmap(w: NDArray[np.float64]) -> NDArray[np.float64]:
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(th) * K + (1.0 - np.cos(th)) * (K @ K)


def refine_multiview(
    points: Sequence[NDArray],
    normals: Sequence[NDArray],
    T_model_scan: Sequence[NDArray],
    pairs: Sequence[tuple[int, int]],
    *,
    spacing: float,
    max_iterations: int = 12,
    tolerance_deg: float = 2e-4,
    min_normal_cos: float = 0.7,
    max_query_points: int = 10000,
) -> tuple[list[NDArray[np.float64]], dict[str, float]]:
    """Refine all view poses jointly (the first view stays fixed).

    Parameters
    ----------
    points, normals : list of (N_k, 3) float
        Each view's (down-sampled) points and unit normals in its own frame.
    T_model_scan : list of (4, 4) float
        Initial poses (e.g. from a pose graph), accurate to about ``spacing``.
    pairs : list of (i, j)
        Views that overlap; each pair contributes both ways (points of i on the
        surface of j and of j on i).
    spacing : float
        Point spacing of the clouds: Tukey's constant is ``spacing``,
        correspondences are searched within ``3 * spacing``.
    max_iterations : int
        Gauss-Newton iterations (correspondences re-found at each).
    tolerance_deg : float
        Stop when no view rotates by more than this in an iteration.
    min_normal_cos : float
        Correspondences whose normals disagree more than this are dropped.
    max_query_points : int
        Each view's points are matched against the others' full clouds through an
        evenly strided subset of at most this many (the estimate needs thousands of
        correspondences, not hundreds of thousands).

    Returns
    -------
    poses : list of (4, 4) float64
        Refined ``T_model_scan``.
    info : dict
        ``iterations``, ``rms`` (weighted point-to-plane RMS at the end, cloud
        units), ``max_change_deg`` (largest rotation of a view from its initial
        pose), ``correspondences``.

    Raises
    ------
    InputError
        Inconsistent inputs.
    ReconstructionError
        Too few correspondences to fix a view.
    """
    n = len(points)
    if n < 2 or len(normals) != n or len(T_model_scan) != n:
        raise InputError("refine_multiview: need >= 2 views with points, normals and a pose each")
    check_positive(spacing, "spacing")
    P = [np.asarray(check_array(p, f"points[{k}]", ndim=2, dtype_kind="f"), dtype=np.float64)
         for k, p in enumerate(points)]
    N = [np.asarray(check_array(v, f"normals[{k}]", shape=P[k].shape, dtype_kind="f"), dtype=np.float64)
         for k, v in enumerate(normals)]
    T = [np.array(check_array(t, f"T_model_scan[{k}]", shape=(4, 4), dtype_kind="f"), dtype=np.float64)
         for k, t in enumerate(T_model_scan)]
    pairs = sorted({(min(i, j), max(i, j)) for i, j in pairs if i != j})
    if not pairs or any(not (0 <= i < n and 0 <= j < n) for i, j in pairs):
        raise InputError(f"refine_multiview: pairs must index the {n} views, got {pairs!r}")
    trees = [cKDTree(p) for p in P]
    stride = [max(1, -(-len(p) // int(max_query_points))) for p in P]
    Q = [p[::st] for p, st in zip(P, stride, strict=True)]
    QN = [v[::st] for v, st in zip(N, stride, strict=True)]
    k_tukey = float(spacing)
    dist = 3.0 * k_tukey
    # perturbations about the centroid keep rotation and translation decoupled
    c = np.mean([t[:3, :3] @ p.mean(axis=0) + t[:3, 3] for p, t in zip(P, T, strict=True)], axis=0)
    T_init = [t.copy() for t in T]
    it = 0
    rms = float("nan")
    n_corr = 0
    for it in range(1, int(max_iterations) + 1):
        H = np.zeros((6 * n, 6 * n))
        g = np.zeros(6 * n)
        cost = wsum = 0.0
        n_corr = 0
        for i, j in pairs:
            for a, b in ((i, j), (j, i)):
                M = np.linalg.solve(T[b], T[a])  # a's frame -> b's frame
                pa = Q[a] @ M[:3, :3].T + M[:3, 3]
                dd, idx = trees[b].query(pa, distance_upper_bound=dist, workers=-1)
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
                if keep.sum() < 6:
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
        Hr = H[6:, 6:]
        if np.min(np.abs(np.diag(Hr))) <= 0:
            raise ReconstructionError(
                "multi-view refinement: a view has no correspondences with its neighbours"
            )
        x = np.r_[np.zeros(6), -np.linalg.solve(Hr + 1e-9 * np.trace(Hr) / len(Hr) * np.eye(len(Hr)), g[6:])]
        # the initial poses are close (pose graph): a step larger than ~1 deg is a
        # weakly constrained direction (a smooth, symmetric surface sliding), damp it
        big = np.max(np.linalg.norm(x.reshape(n, 6)[:, :3], axis=1))
        if big > np.radians(1.0):
            x *= np.radians(1.0) / big
        rms = float(np.sqrt(cost / max(wsum, 1e-12)))
        step = 0.0
        for k in range(1, n):
            w_, t_ = x[6 * k: 6 * k + 3], x[6 * k + 3: 6 * k + 6]
            E = np.eye(4)
            E[:3, :3] = _expmap(w_)
            E[:3, 3] = t_ + c - E[:3, :3] @ c  # rotate about the centroid, then shift
            T[k] = E @ T[k]
            step = max(step, float(np.degrees(np.linalg.norm(w_))))
        log.debug("multi-view ICP iteration %d: rms %.4g, largest rotation step %.2e deg", it, rms, step)
        if step < tolerance_deg:
            break
    change = max(
        float(np.degrees(np.arccos(np.clip((np.trace(T[k][:3, :3].T @ T_init[k][:3, :3]) - 1) / 2, -1, 1))))
        for k in range(n)
    )
    return T, {"iterations": float(it), "rms": rms, "max_change_deg": change, "correspondences": float(n_corr)}
