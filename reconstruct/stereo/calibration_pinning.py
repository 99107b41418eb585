"""Does a calibration's set of shots pin the rig well enough for matching? Each
parameter's uncertainty (the bundle's covariance) is carried through the rectification
geometry to a row offset and a disparity error at the working distance, against what the
matcher needs (ROW_OFFSET_NEED_PX, DISPARITY_NEED_PX); the warnings say which shots to add.
Logged under the calibration's logger (``prism3d.reconstruct.stereo.calibrate``), as before.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import CameraModel, PrismSplit, StereoRig, compute_rectification
from prism3d.geometry import make_transform, matrix_from_rotvec
from prism3d.reconstruct.stereo._bundle import (
    CAM_PARAM_NAMES,
    N_CAM,
    BundleProblem,
    BundleResult,
)

__all__ = ["DISPARITY_NEED_PX", "ROW_OFFSET_NEED_PX", "Pinning", "camera_from_vector", "check_pinning", "pose_matrix", "rig_param_names"]

log = logging.getLogger("prism3d.reconstruct.stereo.calibrate")


def pose_matrix(rvec: NDArray, tvec: NDArray) -> NDArray[np.float64]:
    return make_transform(matrix_from_rotvec(np.asarray(rvec, dtype=np.float64).ravel()), tvec)


def camera_from_vector(p: NDArray, size: tuple[int, int]) -> CameraModel:
    fx, fy, cx, cy, s = p[:5]
    K = np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return CameraModel(K, p[5:10], size)


#: Largest row offset (px) the calibration may leave between the rectified views: the
#: matcher searches along one row, and its finest sub-pixel precision is 1/10 px (paper).
ROW_OFFSET_NEED_PX = 0.1
#: Largest disparity error (px) the calibration may add: half that finest precision, so
#: that the depth error z^2 / (f B) * dd (eq. 16) stays below the matching noise.
DISPARITY_NEED_PX = 0.05
# Each parameter's need follows from these two through the rectification geometry
# (_stereo_errors), evaluated by check_pinning: no per-parameter constants.
#: Board tilts to ask for: f and the principal point improve with the angle between board
#: and image plane up to ~45 deg, where foreshortening starts to spoil the corners
#: (Zhang 2000, sec. 5.1); 20-40 deg keeps clear of both ends.
_TILT_ADVICE_DEG = (20, 40)
#: Image points per axis and view on which the needs are checked (edges included).
_CHECK_GRID = 9
_REGIONS = (
    ("upper-left corner", "top edge", "upper-right corner"),
    ("left edge", "centre", "right edge"),
    ("lower-left corner", "bottom edge", "lower-right corner"),
)
#: Parameter groups of the advice: label, members, and the tilt axis that separates
#: each member from the board's distance and turn (a tilt about the vertical axis
#: foreshortens along x, so it pins fx and cx; about the horizontal axis, fy and cy).
_GROUPS: tuple[tuple[str, tuple[str, ...], dict[str, str]], ...] = (
    ("principal point", ("cx", "cy"), {"cx": "vertical", "cy": "horizontal"}),
    ("focal length", ("fx", "fy"), {"fx": "vertical", "fy": "horizontal"}),
    ("skew", ("skew",), {}),
    ("distortion", ("k1", "k2", "k3", "p1", "p2"), {}),
    ("rig rotation", ("rx", "ry", "rz"), {}),
    ("rig translation", ("baseline", "tx", "ty", "tz"), {}),
)
_RIG_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
_N_RIG = 2 * N_CAM + 6  # bundle parameters of the rig: both cameras, then R, T
#: Sensitivity steps: a hundredth of a parameter's std (well inside the linear range), or
#: a relative 1e-6 for a parameter without variance.
_DIFF_STEP_SIGMA = 1e-2
_DIFF_STEP_REL = 1e-6
#: Fewer common pixel pairs than this at the working distance: nothing to check.
_MIN_CHECK_PAIRS = 3


@dataclass(frozen=True)
class Pinning:
    """What :func:`check_pinning` found (fields of :class:`Calibration`)."""

    warnings: tuple[str, ...] = ()
    needs: dict[str, float] = field(default_factory=dict)
    precision: dict[str, float] = field(default_factory=dict)


def rig_param_names() -> list[str]:
    """Keys of :attr:`Calibration.std` for the first ``2 * N_CAM + 6`` bundle parameters."""
    return [f"{n}_{cam}" for cam in ("left", "right") for n in CAM_PARAM_NAMES] + list(_RIG_NAMES)


def _rig_from_vector(p: NDArray, size: tuple[int, int], split: PrismSplit) -> StereoRig:
    T = pose_matrix(p[2 * N_CAM : 2 * N_CAM + 3], p[2 * N_CAM + 3 : 2 * N_CAM + 6])
    left = camera_from_vector(p[:N_CAM], size)
    return StereoRig(left, camera_from_vector(p[N_CAM : 2 * N_CAM], size), T, split)


def _check_pixels(rig: StereoRig, depth_mm: float) -> tuple[NDArray, NDArray]:
    """Pixel pairs ``(uv_left, uv_right)`` of scene points ``depth_mm`` in front of the
    left camera (its z), on a grid over each view, where both views see them."""
    R, t = rig.R, rig.T
    c_right = -R.T @ t  # right camera centre, left frame
    pairs: list[tuple[NDArray, NDArray]] = []
    for from_left, cam, other in ((True, rig.left, rig.right), (False, rig.right, rig.left)):
        w, h = cam.size
        u, v = np.meshgrid(np.linspace(0, w - 1, _CHECK_GRID), np.linspace(0, h - 1, _CHECK_GRID))
        uv = np.stack([u.ravel(), v.ravel()], axis=1)
        rays = cam.pixel_rays(uv)
        if from_left:
            uvo = other.project((rays / rays[:, 2:3] * depth_mm) @ R.T + t)
        else:
            d = rays @ R  # the right camera's rays in the left frame
            with np.errstate(divide="ignore", invalid="ignore"):
                uvo = other.project(c_right + ((depth_mm - c_right[2]) / d[:, 2])[:, None] * d)
        ow, oh = other.size
        with np.errstate(invalid="ignore"):
            ok = (uvo[:, 0] >= 0) & (uvo[:, 1] >= 0) & (uvo[:, 0] <= ow - 1) & (uvo[:, 1] <= oh - 1)
        pairs.append((uv[ok], uvo[ok]) if from_left else (uvo[ok], uv[ok]))
    return np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])


def _stereo_errors(
    p: NDArray, size: tuple[int, int], split: PrismSplit, uv_l: NDArray, uv_r: NDArray, f0: float, b0: float
) -> NDArray[np.float64]:
    """Rectified row offsets, then disparities, of fixed pixel pairs under the rig
    parameters ``p`` (px at focal length ``f0``). The disparity is scaled to the
    baseline ``b0``, so that a baseline error shows as the disparity error that makes
    the same depth error."""
    rig = _rig_from_vector(p, size, split)
    rect = compute_rectification(rig)
    a = rig.left.pixel_rays(uv_l) @ rect.R1.T
    b = rig.right.pixel_rays(uv_r) @ rect.R2.T
    a = a[:, :2] / a[:, 2:3]
    b = b[:, :2] / b[:, 2:3]
    return np.concatenate([f0 * (a[:, 1] - b[:, 1]), f0 * b0 / rig.baseline_mm * (a[:, 0] - b[:, 0])])


def _regions_without_corners(points: Sequence[NDArray | None], size: tuple[int, int]) -> list[str]:
    """The 3x3 image regions (named) with a part -- a cell of a 6x6 grid, a sixth of the
    image each way -- that no corner reaches."""
    w, h = size
    seen = np.zeros((6, 6), bool)
    for pts in points:
        if pts is not None:
            col = np.clip((pts[:, 0] + 0.5) * 6 // w, 0, 5).astype(int)
            row = np.clip((pts[:, 1] + 0.5) * 6 // h, 0, 5).astype(int)
            seen[row, col] = True
    return [_REGIONS[r][c] for r in range(3) for c in range(3)
            if not seen[2 * r : 2 * r + 2, 2 * c : 2 * c + 2].all()]


def _join(items: Sequence[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _with_unit(name: str, value: float) -> str:
    """A parameter's value with its unit (the rig rotation in degrees)."""
    base = name.split("_")[0]
    if base in ("rx", "ry", "rz"):
        return f"{math.degrees(value):.2g} deg"
    if base in ("tx", "ty", "tz", "baseline"):
        return f"{value:.2g} mm"
    if base in ("fx", "fy", "cx", "cy", "skew"):
        return f"{value:.2g} px"
    return f"{value:.2g}"


def _rig_covariance(prob: BundleProblem, res: BundleResult) -> tuple[NDArray, NDArray[np.intp], list[str]]:
    """Covariance of the free rig parameters (both cameras, ``R``, ``T``) from the bundle
    Jacobian, their indices in the full vector, and their :attr:`Calibration.std` names."""
    x = res.params[prob.free]
    J = prob.jacobian(x)
    r = res.residuals.ravel()
    sigma2 = float(r @ r) / max(r.size - x.size, 1)
    JtJ = J.T @ J
    s = np.sqrt(np.maximum(np.diag(JtJ), 1e-300))  # column scaling for a well-conditioned inverse
    cov = np.linalg.pinv(JtJ / np.outer(s, s)) / np.outer(s, s) * sigma2
    cols = np.flatnonzero(prob.free[:_N_RIG])  # free rig parameters, full indices
    at = np.cumsum(prob.free) - 1  # full index -> free index
    return cov[np.ix_(at[cols], at[cols])], cols, [rig_param_names()[j] for j in cols]


def _stereo_gradients(
    rig: StereoRig, p0: NDArray, cols: NDArray[np.intp], C: NDArray, uv: tuple[NDArray, NDArray], f0: float
) -> NDArray[np.float64]:
    """Central-difference derivatives ``(2 M, k)`` of the row offsets and disparities of the
    pixel pairs ``uv`` by each free rig parameter (steps of a hundredth of its std)."""
    G = np.empty((2 * len(uv[0]), len(cols)))
    for k, j in enumerate(cols):
        step = np.zeros(_N_RIG)
        if C[k, k] > 0:
            step[j] = _DIFF_STEP_SIGMA * math.sqrt(C[k, k])
        else:
            step[j] = _DIFF_STEP_REL * max(1.0, abs(p0[j]))
        args = (rig.left.size, rig.split, uv[0], uv[1], f0, rig.baseline_mm)
        G[:, k] = (_stereo_errors(p0 + step, *args) - _stereo_errors(p0 - step, *args)) / (2.0 * step[j])
    return G


def _needs(
    G: NDArray, C: NDArray, names: list[str], T: NDArray, m: int
) -> tuple[dict[str, float], dict[str, float]]:
    """Standard deviation and need of each parameter (and of the baseline ``|T|``), the need
    from the effective sensitivity ``cov(q, p) / var(p)`` of the ``m`` row offsets and the
    disparities ``q``."""
    GC = G @ C
    std = {n: math.sqrt(C[k, k]) for k, n in enumerate(names) if C[k, k] > 0}
    g_eff = {n: GC[:, k] / C[k, k] for k, n in enumerate(names) if C[k, k] > 0}
    if {"tx", "ty", "tz"} <= set(names):
        u = np.zeros(len(names))
        u[[names.index(n) for n in ("tx", "ty", "tz")]] = T / float(np.linalg.norm(T))
        if (var_b := float(u @ C @ u)) > 0:
            std["baseline"], g_eff["baseline"] = math.sqrt(var_b), GC @ u / var_b
    needs = {
        n: min(ROW_OFFSET_NEED_PX / max(float(np.abs(g[:m]).max()), 1e-300),
               DISPARITY_NEED_PX / max(float(np.abs(g[m:]).max()), 1e-300))
        for n, g in g_eff.items()
    }
    return std, needs


def _precision_warning(n_views: int, pr: dict[str, float]) -> list[str]:
    """The line saying the rows or disparities are not pinned at the working distance."""
    row_px, disp_px = pr["row_offset_px"], pr["disparity_px"]
    parts = []
    if row_px > ROW_OFFSET_NEED_PX:
        parts.append(f"rectified rows may be {row_px:.2f} px apart (needs <= {ROW_OFFSET_NEED_PX:g} px)")
    if disp_px > DISPARITY_NEED_PX:
        parts.append(f"disparities off by {disp_px:.2f} px = {pr['depth_mm']:.2f} mm of depth "
                     f"(needs <= {DISPARITY_NEED_PX:g} px)")
    if not parts:
        return []
    return [f"the {n_views} shots do not pin the rig to what stereo matching needs at "
            f"the working distance ({pr['working_distance_mm']:.0f} mm): {' and '.join(parts)} "
            "(1 sigma, worst image point)"]


def _group_warnings(
    flagged: list[str], std: dict[str, float], needs: dict[str, float], rots: NDArray, dists: NDArray,
    corners_advice: str,
) -> list[str]:
    """One line per parameter group with a parameter looser than its need, with advice."""
    normals = rots[:, :, 2] * np.where(rots[:, 2, 2] < 0, -1.0, 1.0)[:, None]  # facing away
    tilt = {"vertical": np.degrees(np.arctan2(normals[:, 0], normals[:, 2])),
            "horizontal": np.degrees(np.arctan2(normals[:, 1], normals[:, 2]))}

    def tilt_advice(axis: str) -> str:
        lo, hi = tilt[axis].min(), tilt[axis].max()
        return (f"add shots tilted {_TILT_ADVICE_DEG[0]}-{_TILT_ADVICE_DEG[1]} deg about the {axis} axis, "
                f"both ways (now {lo:+.0f}..{hi:+.0f} deg)")

    out = []
    for label, members, tilt_axis in _GROUPS:
        hit = [n for n in flagged if n.split("_")[0] in members]
        if not hit:
            continue
        items = ", ".join(
            f"{n.replace('_', ' ')} ±{_with_unit(n, std[n])} (needs <= {_with_unit(n, needs[n])})" for n in hit)
        axes = sorted({tilt_axis[n.split("_")[0]] for n in hit if n.split("_")[0] in tilt_axis}, reverse=True)
        advice = [tilt_advice(a) for a in axes] or [corners_advice]
        if label.startswith("rig"):
            lo, hi = dists[:, 2].min(), dists[:, 2].max()
            advice.append(f"place boards nearer and farther (now {lo:.0f}-{hi:.0f} mm)")
        out.append(f"{label}: {items}: {'; '.join(advice)}")
    return out


def check_pinning(
    prob: BundleProblem,
    res: BundleResult,
    rig: StereoRig,
    board_points: NDArray,
    left_points: Sequence[NDArray | None],
    right_points: Sequence[NDArray | None],
) -> Pinning:
    """Compare the calibration's precision with what stereo matching needs.

    The rig parameters' covariance is propagated to the rectified row offsets and
    disparities of pixel pairs over both views at the boards' median distance; each
    parameter's need follows from its effective sensitivity ``cov(q, p) / var(p)``, since
    the parameters are strongly correlated (docs/calibration.md).
    """
    C, cols, names = _rig_covariance(prob, res)
    views = res.params[prob.view_offset :].reshape(prob.n_views, 6)
    rots = matrix_from_rotvec(views[:, :3])
    dists = rots @ board_points.mean(axis=0) + views[:, 3:]
    depth = float(np.median(dists[:, 2]))
    uv_l, uv_r = _check_pixels(rig, depth)
    if len(uv_l) < _MIN_CHECK_PAIRS:
        log.info("calibration precision not checked: the views share too few pixels at %.0f mm", depth)
        return Pinning()
    f0, b0 = (rig.left.fy + rig.right.fy) / 2.0, rig.baseline_mm
    G = _stereo_gradients(rig, res.params[:_N_RIG], cols, C, (uv_l, uv_r), f0)
    m = len(uv_l)
    std_q = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", G, C, G), 0.0))
    row_px, disp_px = float(std_q[:m].max()), float(std_q[m:].max())
    precision = {"working_distance_mm": depth, "row_offset_px": row_px, "disparity_px": disp_px,
                 "depth_mm": disp_px * depth**2 / (f0 * b0)}
    std, needs = _needs(G, C, names, rig.T, m)

    # what the board poses lack: tilts about the camera's axes, corners in the image
    holes = [f"the {_join(regions)} of the {side} view"
             for side, pts in (("left", left_points), ("right", right_points))
             if (regions := _regions_without_corners(pts, rig.left.size))]
    corners_advice = ("add shots with corners in the image regions that have none" if holes
                      else "add shots with the board reaching into the image corners")
    flagged = [n for n in [*names, "baseline"] if n in needs and std[n] > needs[n]]
    warnings = _precision_warning(prob.n_views, precision)
    warnings += _group_warnings(flagged, std, needs, rots, dists, corners_advice)
    if warnings and not flagged:  # jointly, not singly, too loose
        warnings[0] += f"; {corners_advice}"
    if warnings and holes:
        warnings.append(f"image regions without corners: {'; '.join(holes)}")
    for w in warnings:
        log.warning("%s", w, extra={"prism3d_calibration_warning": True})
    return Pinning(tuple(warnings), needs, precision)


