"""Bundle adjustment for chessboard calibration (private): one camera or a stereo
pair, every board pose and (stereo) the rig pose refined jointly by
:func:`scipy.optimize.least_squares`, on reprojection errors (px). Full vector::

    [cam 0: fx fy cx cy skew k1 k2 p1 p2 k3]        10
    [cam 1: the same]                               10   (stereo only)
    [rig: rvec(3) t(3)]  x_right = R x_left + t      6   (stereo only)
    [view v: rvec(3) t(3)]  x_left = R_v X + t_v     6 per view

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

from prism3d.geometry import matrix_from_rotvec

__all__ = [
    "CAM_PARAM_NAMES",
    "N_CAM",
    "BundleProblem",
    "BundleResult",
    "rodrigues_inv",
    "solve_bundle",
]

CAM_PARAM_NAMES = ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")
N_CAM = len(CAM_PARAM_NAMES)
#: Central-difference step, relative to max(1, |parameter|): near the square root of the
#: float64 precision that balances truncation against rounding.
_DIFF_STEP = 1e-6
#: Solver tolerances of the robust pass and of the final least-squares pass.
_ROBUST_TOL = 1e-10
_FINAL_TOL = 1e-12


def rodrigues_inv(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vector ``(3,)`` of one rotation matrix (via OpenCV)."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64).reshape(3, 3))
    return rvec.ravel()


@dataclass
class BundleProblem:
    """Observations and the starting point of a calibration bundle adjustment: board
    points ``(M, 3)`` (board units), their pixels ``(M, 2)``, camera (0 left or single,
    1 right) and board pose index ``(M,)`` of each, the full start vector ``x0 (P,)``
    (module docstring) and its ``free (P,)`` mask."""

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
        Rv = matrix_from_rotvec(views[:, :3])
        vi = self.view_index
        X = np.einsum("mij,mj->mi", Rv[vi], self.object_points) + views[vi, 3:]
        if self.n_cams == 2:
            ro = self.rig_offset
            Rr = matrix_from_rotvec(full[ro : ro + 3])
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
        """Free-parameter column groups touching disjoint residual rows: one per camera or
        rig parameter; the j-th pose parameter of all views together (a row sees one view)."""
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
            h = _DIFF_STEP * np.maximum(1.0, np.abs(full[cols]))
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
    """Refined full vector ``(P,)``, reprojection errors ``(M, 2)`` px, standard deviations
    ``(P,)`` from ``sigma^2 (J^T J)^-1`` (0 when fixed), names, the solver's success flag."""

    params: NDArray[np.float64]
    residuals: NDArray[np.float64]
    std: NDArray[np.float64]
    names: list[str]
    success: bool


def solve_bundle(
    problem: BundleProblem, *, loss: str = "soft_l1", f_scale: float = 1.0, max_nfev: int = 200
) -> BundleResult:
    """Refine ``problem``: a robust pass (``loss``, ``f_scale`` px) against a few bad
    corners, then plain least squares for the estimate and its covariance."""

    def fun(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return problem.residuals_full(problem.expand(x))

    with _single_blas_thread():
        return _solve(problem, fun, loss=loss, f_scale=f_scale, max_nfev=max_nfev)


def _single_blas_thread() -> contextlib.AbstractContextManager:
    """Limit BLAS to one thread: the matrices are small (docs/calibration.md)."""
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
            xtol=_ROBUST_TOL,
            ftol=_ROBUST_TOL,
            gtol=_ROBUST_TOL,
            **opts,
        )
        x = res.x
    res = least_squares(fun, x, max_nfev=max_nfev, xtol=_FINAL_TOL, ftol=_FINAL_TOL, gtol=_FINAL_TOL, **opts)
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
