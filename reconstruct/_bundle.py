"""Bundle adjustment for chessboard calibration (private).

One problem covers a single camera or a stereo pair: every camera's intrinsics and
distortion, the rig's relative pose (stereo) and every board pose are refined jointly
by :func:`scipy.optimize.least_squares` with a sparse Jacobian pattern.

Parameter layout (the *full* vector; a boolean mask selects the free entries)::

    [cam 0: fx fy cx cy skew k1 k2 p1 p2 k3]        10
    [cam 1: the same]                               10   (stereo only)
    [rig: rvec(3) t(3)]  x_right = R x_left + t      6   (stereo only)
    [view v: rvec(3) t(3)]  x_left = R_v X + t_v     6 per view

Residuals are reprojection errors in pixels, two rows (u, v) per observation. The
Jacobian is dense (a few hundred columns at most) and computed by central differences
over column groups that exploit its sparsity: each residual depends on one camera,
the rig pose (right camera only) and one board pose, so the j-th pose parameter of
all views is perturbed in one evaluation (about 30 evaluations per Jacobian).

References
----------
.. [1] B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle Adjustment -- A
   Modern Synthesis", Vision Algorithms: Theory and Practice, LNCS 1883 (2000).
.. [2] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11)
   (2000): the maximum-likelihood refinement of section 3.2.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

__all__ = [
    "CAM_PARAM_NAMES",
    "N_CAM",
    "BundleProblem",
    "BundleResult",
    "rodrigues",
    "rodrigues_inv",
    "solve_bundle",
]

CAM_PARAM_NAMES = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")
N_CAM = len(CAM_PARAM_NAMES)


def rodrigues(rvec: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices ``(V, 3, 3)`` from rotation vectors ``(V, 3)`` (vectorised)."""
    r = np.asarray(rvec, dtype=np.float64).reshape(-1, 3)
    theta2 = np.einsum("ij,ij->i", r, r)
    theta = np.sqrt(theta2)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = np.zeros((r.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -r[:, 2], r[:, 1]
    K[:, 1, 0], K[:, 1, 2] = r[:, 2], -r[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -r[:, 1], r[:, 0]
    return np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)


def rodrigues_inv(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vector ``(3,)`` of one rotation matrix (via OpenCV)."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64).reshape(3, 3))
    return rvec.ravel()


@dataclass
class BundleProblem:
    """Observations and the starting point of a calibration bundle adjustment.

    Attributes
    ----------
    object_points : (M, 3) float64
        Board points (board frame, board units) of every observation.
    image_points : (M, 2) float64
        Their detected pixels.
    cam_index : (M,) int
        0 = left (or the single camera), 1 = right.
    view_index : (M,) int
        Board pose index of every observation.
    x0 : (P,) float64
        Full parameter vector (layout in the module docstring).
    free : (P,) bool
        Which parameters are optimised.
    n_cams : int
        1 or 2.
    n_views : int
        Number of board poses.
    """

    object_points: NDArray[np.float64]
    image_points: NDArray[np.float64]
    cam_index: NDArray[np.intp]
    view_index: NDArray[np.intp]
    x0: NDArray[np.float64]
    free: NDArray[np.bool_]
    n_cams: int
    n_views: int

    @property
    def rig_offset(self) -> int:
        return N_CAM * self.n_cams

    @property
    def view_offset(self) -> int:
        return N_CAM * self.n_cams + (6 if self.n_cams == 2 else 0)

    def param_names(self) -> list[str]:
        """Names of the full parameter vector, e.g. ``fx1``, ``rig_t0``, ``view3_r1``."""
        names = []
        for c in range(self.n_cams):
            names += [f"{n}{c + 1}" for n in CAM_PARAM_NAMES]
        if self.n_cams == 2:
            names += [f"rig_r{i}" for i in range(3)] + [f"rig_t{i}" for i in range(3)]
        for v in range(self.n_views):
            names += [f"view{v}_r{i}" for i in range(3)] + [f"view{v}_t{i}" for i in range(3)]
        return names

    def project(self, full: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pixels ``(M, 2)`` of every observation for the full parameter vector."""
        vo = self.view_offset
        views = full[vo : vo + 6 * self.n_views].reshape(self.n_views, 6)
        Rv = rodrigues(views[:, :3])
        vi = self.view_index
        X = np.einsum("mij,mj->mi", Rv[vi], self.object_points) + views[vi, 3:]
        if self.n_cams == 2:
            ro = self.rig_offset
            Rr = rodrigues(full[ro : ro + 3])[0]
            tr = full[ro + 3 : ro + 6]
            right = self.cam_index == 1
            X[right] = X[right] @ Rr.T + tr
        cams = full[: N_CAM * self.n_cams].reshape(self.n_cams, N_CAM)[self.cam_index]
        fx, fy, cx, cy, s, k1, k2, p1, p2, k3 = cams.T
        x = X[:, 0] / X[:, 2]
        y = X[:, 1] / X[:, 2]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=1)

    def residuals_full(self, full: NDArray[np.float64]) -> NDArray[np.float64]:
        return (self.project(full) - self.image_points).ravel()

    def expand(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        full = self.x0.copy()
        full[self.free] = x
        return full

    def _groups(self) -> list[NDArray[np.intp]]:
        """Free-parameter column groups that touch disjoint residual rows.

        Camera and rig parameters affect many rows (one column per group); the j-th
        pose parameter of every view can be perturbed at once, since each residual
        row depends on one view only.
        """
        free_idx = np.full(self.x0.size, -1)
        free_idx[self.free] = np.arange(int(self.free.sum()))
        groups = []
        for j in range(self.view_offset):
            if self.free[j]:
                groups.append(np.array([j]))
        vo = self.view_offset
        for j in range(6):
            cols = vo + 6 * np.arange(self.n_views) + j
            cols = cols[self.free[cols]]
            if cols.size:
                groups.append(cols)
        return groups

    def jacobian(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Dense Jacobian ``(2M, n_free)`` of the residuals by grouped central differences."""
        full = self.expand(x)
        free_pos = np.full(full.size, -1)
        free_pos[self.free] = np.arange(x.size)
        J = np.zeros((2 * self.object_points.shape[0], x.size))
        vo = self.view_offset
        # rows touched by each view's pose
        row_view = np.repeat(self.view_index, 2)
        for cols in self._groups():
            h = 1e-6 * np.maximum(1.0, np.abs(full[cols]))
            fp = full.copy()
            fm = full.copy()
            fp[cols] += h
            fm[cols] -= h
            d = self.residuals_full(fp) - self.residuals_full(fm)
            if cols.size == 1 and cols[0] < vo:
                J[:, free_pos[cols[0]]] = d / (2.0 * h[0])
            else:
                views = (cols - vo) // 6
                hv = np.zeros(self.n_views)
                hv[views] = h
                colv = np.full(self.n_views, -1)
                colv[views] = free_pos[cols]
                rows = np.flatnonzero(colv[row_view] >= 0)
                J[rows, colv[row_view[rows]]] = d[rows] / (2.0 * hv[row_view[rows]])
        return J


@dataclass
class BundleResult:
    """Refined parameters and their quality.

    Attributes
    ----------
    params : (P,) float64
        Full refined parameter vector.
    residuals : (M, 2) float64
        Final reprojection errors, pixels.
    std : (P,) float64
        Standard deviation of every parameter (0 for fixed ones), from
        ``sigma^2 (J^T J)^-1`` with ``sigma^2 = |r|^2 / (2M - n_free)``.
    names : list of str
        Parameter names (see :meth:`BundleProblem.param_names`).
    success : bool
        The solver's convergence flag.
    """

    params: NDArray[np.float64]
    residuals: NDArray[np.float64]
    std: NDArray[np.float64]
    names: list[str]
    success: bool


def solve_bundle(
    problem: BundleProblem, *, loss: str = "soft_l1", f_scale: float = 1.0, max_nfev: int = 200
) -> BundleResult:
    """Refine ``problem`` with a robust pass, then a linear-loss pass for the statistics.

    The robust pass (``loss`` with ``f_scale`` pixels) limits the pull of a few bad
    corners; the final pass with the plain squared loss gives the maximum-likelihood
    estimate under Gaussian corner noise and the Jacobian for the covariance.
    """

    def fun(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return problem.residuals_full(problem.expand(x))

    with _single_blas_thread():
        return _solve(problem, fun, loss=loss, f_scale=f_scale, max_nfev=max_nfev)


def _single_blas_thread() -> contextlib.AbstractContextManager:
    """Limit BLAS to one thread: the matrices are small, and on a busy 2-core machine
    threaded SVDs of a ~1000 x 100 Jacobian were measured 17x slower than serial."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def _solve(
    problem: BundleProblem, fun: Callable, *, loss: str, f_scale: float, max_nfev: int
) -> BundleResult:
    opts: dict = {"jac": problem.jacobian, "x_scale": "jac", "method": "trf", "tr_solver": "exact"}
    x = problem.x0[problem.free].copy()
    if loss != "linear":
        res = least_squares(
            fun,
            x,
            loss=loss,
            f_scale=f_scale,
            max_nfev=max_nfev,
            xtol=1e-10,
            ftol=1e-10,
            gtol=1e-10,
            **opts,
        )
        x = res.x
    res = least_squares(fun, x, max_nfev=max_nfev, xtol=1e-12, ftol=1e-12, gtol=1e-12, **opts)
    full = problem.expand(res.x)
    r = res.fun
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    dof = max(r.size - res.x.size, 1)
    sigma2 = float(r @ r) / dof
    JtJ = J.T @ J
    # scale columns for a well-conditioned inverse
    d = np.sqrt(np.maximum(np.diag(JtJ), 1e-300))
    cov = np.linalg.pinv(JtJ / np.outer(d, d)) / np.outer(d, d) * sigma2
    std = np.zeros(full.size)
    std[problem.free] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return BundleResult(
        params=full,
        residuals=r.reshape(-1, 2),
        std=std,
        names=problem.param_names(),
        success=bool(res.success),
    )
