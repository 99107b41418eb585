"""Chessboard calibration of one camera or a (prism) stereo rig, refined by our own
bundle adjustment: corners -> Zhang's closed form per camera -> right-view corner
order fixed by the stereo geometry -> joint bundle adjustment -> a check that the shots
pin the rig for stereo matching (docs/calibration.md).

References
----------
.. [1] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11),
   1330-1334 (2000).
.. [2] J.-Y. Bouguet, "Camera Calibration Toolbox for Matlab" (skew off by default).
.. [3] B. Triggs et al., "Bundle Adjustment -- A Modern Synthesis", LNCS 1883 (2000).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import PrismSplit, StereoRig, compute_rectification
from prism3d.checks import check_array, check_choice
from prism3d.errors import CalibrationError, InputError
from prism3d.geometry import rotation_angle_deg
from prism3d.reconstruct.stereo._bundle import (
    CAM_PARAM_NAMES,
    N_CAM,
    BundleProblem,
    BundleResult,
    rodrigues_inv,
    solve_bundle,
)
from prism3d.reconstruct.stereo.calibration_model import (
    Calibration,
    CameraCalibration,
    check_square,
)
from prism3d.reconstruct.stereo.calibration_pinning import (
    camera_from_vector,
    check_pinning,
    pose_matrix,
    rig_param_names,
)
from prism3d.reconstruct.stereo.corners import (
    DEFAULT_WINDOW,
    DETECTORS,
    CornerDetection,
    board_object_points,
    detect_views,
    grid_symmetries,
)

__all__ = [
    "Calibration",
    "CalibrationOptions",
    "CameraCalibration",
    "calibrate_camera",
    "calibrate_stereo",
    "calibrate_stereo_points",
    "calibrate_to_file",
    "parse_board",
    "rectification_residual",
]

log = logging.getLogger(__name__)

#: Minimum number of board views seen by both cameras.
MIN_VIEWS = 3
#: A view is an outlier when its RMS exceeds this multiple of the median view RMS.
OUTLIER_FACTOR = 3.0
#: Two board-to-board poses agree (same corner order) within this rotation (deg) and this
#: fraction of the translation: a wrong order is off by >= 90 deg or a board width.
_POSE_AGREE_DEG = 3.0
_POSE_AGREE_REL = 0.1


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _pose_vec(T: NDArray) -> NDArray[np.float64]:
    return np.concatenate([rodrigues_inv(T[:3, :3]), T[:3, 3]])


def _zhang_init(
    obj: list[NDArray],
    img: list[NDArray],
    size: tuple[int, int],
    *,
    tangential: bool,
    k3: bool,
    who: str,
) -> tuple[NDArray, NDArray, list[NDArray]]:
    """Zhang's closed form + OpenCV's refinement: K, dist(5), T_cam_board per view."""
    import cv2

    flags = 0
    if not k3:
        flags |= cv2.CALIB_FIX_K3
    if not tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    try:
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [o.astype(np.float32) for o in obj],
            [i.astype(np.float32).reshape(-1, 1, 2) for i in img],
            tuple(int(s) for s in size),
            None,
            None,
            flags=flags,
        )
    except cv2.error as exc:
        raise CalibrationError(
            f"{who}: initial calibration failed ({str(exc).strip().splitlines()[-1]})"
        ) from exc
    poses = [pose_matrix(r, t) for r, t in zip(rvecs, tvecs, strict=True)]
    d = np.zeros(5)
    d[: min(5, dist.size)] = dist.ravel()[:5]
    return K, d, poses


def _solve_pnp(obj: NDArray, img: NDArray, K: NDArray, dist: NDArray) -> NDArray[np.float64]:
    import cv2

    ok, rvec, tvec = cv2.solvePnP(
        obj.astype(np.float64), img.astype(np.float64), K, dist, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok:  # pragma: no cover - a planar grid with valid intrinsics always solves
        raise CalibrationError("solvePnP failed on a detected board")
    return pose_matrix(rvec, tvec)


def _mean_pose(Ts: Sequence[NDArray]) -> NDArray[np.float64]:
    Rm = np.mean([T[:3, :3] for T in Ts], axis=0)
    U, _, Vt = np.linalg.svd(Rm)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = np.median([T[:3, 3] for T in Ts], axis=0)
    return out


def _pose_close(A: NDArray, B: NDArray) -> bool:
    ang = rotation_angle_deg(A[:3, :3] @ B[:3, :3].T)
    dt = np.linalg.norm(A[:3, 3] - B[:3, 3])
    return ang < _POSE_AGREE_DEG and dt < _POSE_AGREE_REL * max(np.linalg.norm(B[:3, 3]), 1e-9)


def _free_mask_cam(*, skew: bool, tangential: bool, k3: bool) -> NDArray[np.bool_]:
    return np.array([True, True, True, True, skew, True, True, tangential, tangential, k3])


def _cam_vector(K: NDArray, dist: NDArray) -> NDArray[np.float64]:
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1], *np.asarray(dist).ravel()[:5]])


def _rms(r: NDArray) -> float:
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if r.size else float("nan")


def _check_points(points: Sequence[NDArray], name: str, ncols: int) -> list[NDArray[np.float64]]:
    out = []
    for i, p in enumerate(points):
        a = check_array(p, f"{name}[{i}]", dtype_kind="fiu").astype(np.float64)
        if a.ndim == 3 and a.shape[1] == 1:  # OpenCV's (N, 1, k) layout
            a = a[:, 0]
        if a.ndim != 2 or a.shape[1] != ncols or a.shape[0] < 4:
            raise InputError(
                f"{name}[{i}]: expected (N >= 4, {ncols}) points, got shape {np.shape(p)}"
            )
        if not np.all(np.isfinite(a)):
            raise InputError(f"{name}[{i}]: expected finite values, found NaN or inf")
        out.append(a)
    return out


def _one_opencv_thread(fn: Callable) -> Callable:
    """Run ``fn`` with OpenCV limited to one thread (restored afterwards), so that a
    calibration repeats to the last bit (docs/calibration.md)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        import cv2

        n = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            return fn(*args, **kwargs)
        finally:
            cv2.setNumThreads(n)

    return wrapper


# --------------------------------------------------------------------------------------
# single camera
# --------------------------------------------------------------------------------------
@_one_opencv_thread
def calibrate_camera(
    object_points_list: Sequence[NDArray],
    image_points_list: Sequence[NDArray],
    image_size: tuple[int, int],
    *,
    skew: bool = False,
    tangential: bool = True,
    k3: bool = False,
) -> CameraCalibration:
    """Calibrate one camera from planar-target correspondences (Zhang + bundle adjustment).

    ``object_points_list``: per view ``(N_i, 3)`` target points (z = 0, any unit);
    ``image_points_list``: their pixels ``(N_i, 2)``; ``image_size`` ``(width, height)``.
    ``skew`` (off, as Bouguet recommends), ``tangential`` (p1 p2), ``k3``: free
    parameters. Raises CalibrationError with fewer than ``MIN_VIEWS`` views.
    """
    obj = _check_points(object_points_list, "object_points_list", 3)
    img = _check_points(image_points_list, "image_points_list", 2)
    if len(obj) != len(img):
        raise InputError(
            f"object_points_list and image_points_list must have the same length, got {len(obj)} and {len(img)}"
        )
    for i, (o, p) in enumerate(zip(obj, img, strict=True)):
        if o.shape[0] != p.shape[0]:
            raise InputError(f"view {i}: {o.shape[0]} object points but {p.shape[0]} image points")
    if len(obj) < MIN_VIEWS:
        raise CalibrationError(f"calibration needs at least {MIN_VIEWS} views, got {len(obj)}")
    size = (int(image_size[0]), int(image_size[1]))
    if size[0] <= 0 or size[1] <= 0:
        raise InputError(f"image_size: expected positive (width, height), got {image_size}")
    K, d, poses = _zhang_init(obj, img, size, tangential=tangential, k3=k3, who="camera")
    V = len(obj)
    x0 = np.concatenate([_cam_vector(K, d)] + [_pose_vec(T) for T in poses])
    free = np.concatenate(
        [_free_mask_cam(skew=skew, tangential=tangential, k3=k3), np.ones(6 * V, bool)]
    )
    prob = BundleProblem(
        object_points=np.concatenate(obj),
        image_points=np.concatenate(img),
        cam_index=np.zeros(sum(o.shape[0] for o in obj), dtype=np.intp),
        view_index=np.concatenate(
            [np.full(o.shape[0], i, dtype=np.intp) for i, o in enumerate(obj)]
        ),
        x0=x0,
        free=free,
        n_cams=1,
        n_views=V,
    )
    res = solve_bundle(prob)
    cam = camera_from_vector(res.params[:N_CAM], size)
    per_view = np.array([_rms(res.residuals[prob.view_index == v]) for v in range(V)])
    views = res.params[N_CAM:].reshape(V, 6)
    return CameraCalibration(
        camera=cam,
        rms_px=_rms(res.residuals),
        per_view_rms_px=per_view,
        std={n: float(s) for n, s in zip(CAM_PARAM_NAMES, res.std[:N_CAM], strict=True)},
        T_cam_board=np.stack([pose_matrix(v[:3], v[3:]) for v in views]),
    )


# --------------------------------------------------------------------------------------
# stereo
# --------------------------------------------------------------------------------------
def rectification_residual(
    rig: StereoRig, left_points: Sequence[NDArray], right_points: Sequence[NDArray]
) -> float:
    """RMS vertical disparity (px) of corresponding points after rectifying ``rig``.

    Each point is undistorted exactly, rotated by ``R1`` / ``R2`` of
    :func:`~prism3d.capture.rig.compute_rectification` and projected with ``P1`` / ``P2``.
    """
    rect = compute_rectification(rig)
    dy = []
    for pl, pr in zip(left_points, right_points, strict=True):
        ys = []
        for cam, Rr, P, pts in (
            (rig.left, rect.R1, rect.P1, pl),
            (rig.right, rect.R2, rect.P2, pr),
        ):
            rays = cam.pixel_rays(np.asarray(pts, dtype=np.float64)) @ Rr.T
            ys.append(P[1, 1] * rays[:, 1] / rays[:, 2] + P[1, 2])
        dy.append(ys[0] - ys[1])
    if not dy:
        return float("nan")
    d = np.concatenate(dy)
    return float(np.sqrt(np.mean(d * d)))


def _rig_frame(T_right_left: NDArray) -> NDArray[np.float64]:
    """``T_rig_left``: origin midway between the centres, x to the right camera,
    z along the mean optical axis, y down."""
    R = T_right_left[:3, :3]
    c_right = -R.T @ T_right_left[:3, 3]
    x = c_right / np.linalg.norm(c_right)
    z = np.array([0.0, 0.0, 1.0]) + R.T @ np.array([0.0, 0.0, 1.0])
    z = z - x * (x @ z)
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    T_left_rig = np.eye(4)
    T_left_rig[:3, 0], T_left_rig[:3, 1], T_left_rig[:3, 2], T_left_rig[:3, 3] = (
        x,
        y,
        z,
        c_right / 2.0,
    )
    return np.linalg.inv(T_left_rig)


# --------------------------------------------------------------------------------------
# stereo calibration: the stages
# --------------------------------------------------------------------------------------
def _view_points(
    left_points: Sequence[NDArray | None], right_points: Sequence[NDArray | None], board: tuple[int, int],
    square_mm: float,
) -> tuple[NDArray[np.float64], list[NDArray | None], list[NDArray | None]]:
    """The board's object points ``(n, 3)`` and per camera every view's ``(n, 2)`` float64
    corners or None, checked."""
    if len(left_points) != len(right_points):
        raise InputError(
            f"left_points and right_points must have the same length, got {len(left_points)} and {len(right_points)}"
        )
    obj = board_object_points(board, square_mm)
    n = obj.shape[0]
    L: list[NDArray | None] = []
    Rt: list[NDArray | None] = []
    for side, pts, out in (("left", left_points, L), ("right", right_points, Rt)):
        for i, p in enumerate(pts):
            if p is None:
                out.append(None)
                continue
            a = check_array(p, f"{side}_points[{i}]", dtype_kind="fiu").astype(np.float64).reshape(-1, 2)
            if a.shape[0] != n:
                raise InputError(
                    f"{side}_points[{i}]: expected {n} corners for a {board[0]}x{board[1]} board, got {a.shape[0]}"
                )
            out.append(a)
    return obj, L, Rt


def _init_cameras(
    obj: NDArray, points: tuple[list, list], size: tuple[int, int], *, tangential: bool, k3: bool
) -> list[tuple[NDArray, NDArray, dict[int, NDArray]]]:
    """Zhang's initialisation of each camera: ``(K, dist, {view: T_cam_board})``."""
    init = []
    for name, pts in zip(("left", "right"), points, strict=True):
        idx = [i for i in range(len(pts)) if pts[i] is not None]
        K, d, poses = _zhang_init(
            [obj] * len(idx), [pts[i] for i in idx], size, tangential=tangential, k3=k3, who=f"{name} camera"
        )
        init.append((K, d, dict(zip(idx, poses, strict=True))))
    return init


def _fix_corner_order(
    obj: NDArray, board: tuple[int, int], both: list[int], Rt: list, P1: dict, right: tuple, srcs: list[str]
) -> tuple[list[int], dict[int, NDArray]]:
    """Re-order each right view whose corners disagree with the stereo geometry the views
    agree on most (updating ``Rt`` and the right poses ``right[2]`` in place), dropping
    it when no grid symmetry fits. Returns the views kept and ``T_right_left`` per view."""
    K2, D2, P2 = right
    rel = {i: P2[i] @ np.linalg.inv(P1[i]) for i in both}
    support = {i: sum(_pose_close(rel[j], rel[i]) for j in both) for i in both}
    ref = rel[max(both, key=lambda i: support[i])]
    perms = grid_symmetries(board)
    dropped: list[int] = []
    for i in both:
        if _pose_close(rel[i], ref):
            continue
        best = None
        for p in perms[1:]:
            T = _solve_pnp(obj, Rt[i][p], K2, D2)
            cand = T @ np.linalg.inv(P1[i])
            if _pose_close(cand, ref):
                best = (p, T, cand)
                break
        if best is None:
            log.warning("%s: the two views disagree with the rig geometry; right view dropped", srcs[i])
            Rt[i] = None
            dropped.append(i)
        else:
            log.info("%s: right-view corner order corrected by the stereo geometry", srcs[i])
            Rt[i] = Rt[i][best[0]]
            P2[i], rel[i] = best[1], best[2]
    return [i for i in both if i not in dropped], rel


def _reported_detections(
    detections: Sequence[CornerDetection], Rt: list, V: int
) -> tuple[CornerDetection, ...]:
    """The detection report with the corrected right-view corner order."""
    dets = list(detections)
    if len(dets) == 2 * V:
        for i in range(V):
            d = dets[2 * i + 1]
            if Rt[i] is not None and d.corners is not None and not np.array_equal(d.corners, Rt[i]):
                dets[2 * i + 1] = dataclasses.replace(d, corners=Rt[i].copy())
    return tuple(dets)


def _stereo_problem(
    obj: NDArray, L: list, Rt: list, used: list[int], init: list, T_rl0: NDArray, cam_free: NDArray[np.bool_]
) -> BundleProblem:
    """The joint bundle problem of both cameras, the rig pose and the ``used`` board poses."""
    (K1, D1, P1), (K2, D2, P2) = init
    N = obj.shape[0]
    views = [P1[i] if L[i] is not None else np.linalg.inv(T_rl0) @ P2[i] for i in used]
    x0 = np.concatenate(
        [_cam_vector(K1, D1), _cam_vector(K2, D2), _pose_vec(T_rl0)] + [_pose_vec(T) for T in views]
    )
    free = np.concatenate([cam_free, cam_free, np.ones(6 + 6 * len(used), bool)])
    objs, imgs, cams, vidx = [], [], [], []
    for k, i in enumerate(used):
        for c, pts in ((0, L[i]), (1, Rt[i])):
            if pts is not None:
                objs.append(obj)
                imgs.append(pts)
                cams.append(np.full(N, c, dtype=np.intp))
                vidx.append(np.full(N, k, dtype=np.intp))
    return BundleProblem(
        object_points=np.concatenate(objs),
        image_points=np.concatenate(imgs),
        cam_index=np.concatenate(cams),
        view_index=np.concatenate(vidx),
        x0=x0,
        free=free,
        n_cams=2,
        n_views=len(used),
    )


def _stereo_quality(
    prob: BundleProblem, res: BundleResult
) -> tuple[NDArray[np.float64], tuple[int, ...], dict[str, float]]:
    """Per-view RMS ``(V, 2)``, outlier views and the named standard deviations."""
    r = res.residuals
    per_view = np.full((prob.n_views, 2), np.nan)
    for k in range(prob.n_views):
        for c in (0, 1):
            m = (prob.view_index == k) & (prob.cam_index == c)
            if m.any():
                per_view[k, c] = _rms(r[m])
    view_rms = np.array([_rms(r[prob.view_index == k]) for k in range(prob.n_views)])
    med = float(np.median(view_rms))
    outliers = tuple(int(k) for k in np.flatnonzero(view_rms > OUTLIER_FACTOR * med))
    std = {n: float(res.std[j]) for j, n in enumerate(rig_param_names())}
    return per_view, outliers, std


def _calibrated_rig(p: NDArray, size: tuple[int, int], split: PrismSplit | None) -> StereoRig:
    """The rig of the solved bundle vector ``p`` (default split: two views side by side)."""
    T_rl = pose_matrix(p[2 * N_CAM : 2 * N_CAM + 3], p[2 * N_CAM + 3 : 2 * N_CAM + 6])
    if split is None:
        split = PrismSplit.side_by_side((2 * size[0], size[1]))
    try:
        left_cam = camera_from_vector(p[:N_CAM], size)
        right_cam = camera_from_vector(p[N_CAM : 2 * N_CAM], size)
        return StereoRig(left_cam, right_cam, T_rl, split, _rig_frame(T_rl))
    except InputError as exc:
        raise CalibrationError(f"calibration produced an invalid rig ({exc})") from exc


def _stereo_start(
    obj: NDArray, board: tuple[int, int], L: list[NDArray | None], Rt: list[NDArray | None],
    size: tuple[int, int], srcs: list[str], *, tangential: bool, k3: bool,
) -> tuple[list[int], list[tuple[NDArray, NDArray, dict[int, NDArray]]], NDArray[np.float64]]:
    """The shots with consistent boards in both views (right-view order fixed in ``Rt``), each
    camera's initialisation and the mean ``T_right_left``; CalibrationError when too few."""
    both = [i for i in range(len(L)) if L[i] is not None and Rt[i] is not None]
    if len(both) < MIN_VIEWS:
        raise CalibrationError(
            f"calibration needs the board in both views of at least {MIN_VIEWS} shots, got {len(both)}"
        )
    init = _init_cameras(obj, (L, Rt), size, tangential=tangential, k3=k3)
    both, rel = _fix_corner_order(obj, board, both, Rt, init[0][2], init[1], srcs)
    if len(both) < MIN_VIEWS:
        raise CalibrationError(
            f"only {len(both)} shots have consistent boards in both views; need {MIN_VIEWS}"
        )
    return both, init, _mean_pose([rel[i] for i in both])


@_one_opencv_thread
def calibrate_stereo_points(
    left_points: Sequence[NDArray | None],
    right_points: Sequence[NDArray | None],
    image_size: tuple[int, int],
    *,
    board: tuple[int, int] = (9, 6),
    square_mm: float = 25.0,
    split: PrismSplit | None = None,
    skew: bool = False,
    tangential: bool = True,
    k3: bool = False,
    sources: Sequence[str] | None = None,
    detections: Sequence[CornerDetection] = (),
) -> Calibration:
    """Calibrate a stereo rig from chessboard corners already detected.

    ``left_points``, ``right_points``: per view ``(N, 2)`` corners in
    :func:`~prism3d.reconstruct.stereo.corners.board_object_points` order, or None where that
    camera missed the board; ``image_size`` ``(width, height)`` of each view; ``board`` to
    ``k3`` as :class:`CalibrationOptions`; ``sources`` a name per view; ``detections``
    ``(left, right)`` per view, flattened, carried into the report (right-view order
    corrected). Raises CalibrationError with fewer than ``MIN_VIEWS`` views in both cameras.
    """
    check_square(square_mm)
    obj, L, Rt = _view_points(left_points, right_points, board, square_mm)
    size = (int(image_size[0]), int(image_size[1]))
    V = len(L)
    srcs = list(sources) if sources is not None else [f"view {i}" for i in range(V)]
    both, init, T_rl0 = _stereo_start(obj, board, L, Rt, size, srcs, tangential=tangential, k3=k3)
    dets = _reported_detections(detections, Rt, V)

    used = [i for i in range(V) if L[i] is not None or Rt[i] is not None]
    cam_free = _free_mask_cam(skew=skew, tangential=tangential, k3=k3)
    prob = _stereo_problem(obj, L, Rt, used, init, T_rl0, cam_free)
    res = solve_bundle(prob)
    rig = _calibrated_rig(res.params, size, split)
    per_view, outliers, std = _stereo_quality(prob, res)
    r = res.residuals
    pinning = check_pinning(prob, res, rig, obj, [L[i] for i in used], [Rt[i] for i in used])
    return Calibration(
        rig=rig,
        rms_px=_rms(r),
        rms_left_px=_rms(r[prob.cam_index == 0]),
        rms_right_px=_rms(r[prob.cam_index == 1]),
        per_view_rms_px=per_view,
        std=std,
        rectification_rms_px=rectification_residual(rig, [L[i] for i in both], [Rt[i] for i in both]),
        n_views=len(used),
        board=(int(board[0]), int(board[1])),
        square_mm=float(square_mm),
        flags={"skew": bool(skew), "tangential": bool(tangential), "k3": bool(k3)},
        outlier_views=outliers,
        sources=tuple(srcs[i] for i in used),
        detections=dets,
        precision=pinning.precision,
        needs=pinning.needs,
        warnings=pinning.warnings,
    )


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of :func:`calibrate_stereo` (the ``prism3d calibrate`` flags)."""

    board: tuple[int, int] = (9, 6)
    """Inner corners ``(cols, rows)`` of the chessboard (OpenCV ``patternSize``)."""
    square_mm: float = 25.0
    """Square size, mm; sets the unit of ``T``."""
    pairs: bool = False
    """Images are separate views alternating left, right (an ordinary rig), not prism shots."""
    split: PrismSplit | None = None
    """Where the views sit on the sensor; None: the left and right halves."""
    skew: bool = False
    """Estimate the skew ``K[0, 1]``; off, as Bouguet recommends (square pixels)."""
    tangential: bool = True
    """Estimate p1 p2; on, since real adapters decentre the lenses (docs/calibration.md)."""
    k3: bool = False
    """Estimate k3; off, since board shots rarely reach the image corners that pin it."""
    method: str = "xjunction"
    """Corner detector (:data:`~prism3d.reconstruct.stereo.corners.DETECTORS`); the X-junction fit is
    the most accurate measured (docs/calibration.md)."""
    window: int | None = DEFAULT_WINDOW
    """``cornerSubPix`` half-window, px; None: a fraction of the square size."""

    def __post_init__(self) -> None:
        check_square(self.square_mm)
        check_choice(self.method, "method", DETECTORS)
        if self.window is not None and int(self.window) < 1:
            raise InputError(f"window: expected a half-window >= 1 pixel, got {self.window}")
        if self.split is not None and not isinstance(self.split, PrismSplit):
            raise InputError(f"split: expected a PrismSplit, got {type(self.split).__name__}")


def _check_boards_found(dets: list[tuple[CornerDetection, CornerDetection]], bx: int, by: int) -> None:
    """Raise when no image, or some image, shows the board in neither view."""
    if not any(d.found for pair in dets for d in pair):
        raise CalibrationError(
            f"no {bx}x{by} chessboard found in any image; check the board size "
            "(inner corners, e.g. 9x6) and the images"
        )
    empty = [
        pair[0].source if pair[0].source == pair[1].source else f"{pair[0].source} / {pair[1].source}"
        for pair in dets
        if not (pair[0].found or pair[1].found)
    ]
    if empty:
        raise CalibrationError(
            f"no {bx}x{by} chessboard found in {', '.join(empty)}; remove the image(s) or check --board"
        )


@_one_opencv_thread
def calibrate_stereo(
    images: Sequence[str | Path | NDArray],
    *,
    options: CalibrationOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Calibration:
    """Calibrate a prism (or ordinary) stereo rig from chessboard images (``prism3d
    calibrate``): side-by-side shots, or with ``options.pairs`` separate views alternating
    left, right (paths or ``(H, W[, 3])`` uint8). ``options``: None for the defaults;
    ``progress(done, total)`` after each image. Raises CalibrationError for an image with
    the board in neither view (named), no board at all, fewer than ``MIN_VIEWS`` shots;
    InputError for unreadable files or mixed sizes. Accuracy: docs/calibration.md."""
    o = CalibrationOptions() if options is None else options
    if not isinstance(o, CalibrationOptions):
        raise InputError(f"options: expected CalibrationOptions, got {type(o).__name__}")
    dets, view_size = detect_views(
        images, board=o.board, pairs=o.pairs, split=o.split, method=o.method, window=o.window,
        progress=progress,
    )
    bx, by = int(o.board[0]), int(o.board[1])
    _check_boards_found(dets, bx, by)
    sources = [
        p[0].source if p[0].source == p[1].source else f"{p[0].source} + {Path(p[1].source).name}"
        for p in dets
    ]
    return calibrate_stereo_points(
        [p[0].corners for p in dets],
        [p[1].corners for p in dets],
        view_size,
        board=(bx, by),
        square_mm=o.square_mm,
        split=o.split,
        skew=o.skew,
        tangential=o.tangential,
        k3=o.k3,
        sources=sources,
        detections=tuple(d for pair in dets for d in pair),
    )


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` -> ``(9, 6)`` (inner corners per row x per column), for the CLI."""
    parts = str(text).lower().replace("*", "x").split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError as exc:
        raise InputError(
            f"--board: expected COLSxROWS inner corners such as 9x6, got {text!r}"
        ) from exc
    if cols < 2 or rows < 2:
        raise InputError(f"--board: expected at least 2x2 inner corners, got {text!r}")
    return cols, rows


def _check_distinct_files(images: Sequence[str | Path]) -> None:
    """InputError when two image files have the same content: one board pose counted
    twice weights it double and skews the fit (the same shot three times gave a
    312.8 mm baseline for a 197.9 mm rig)."""
    import hashlib

    seen: dict[str, str] = {}
    for img in images:
        p = Path(img)
        if not p.is_file():
            continue  # the reader names a missing file
        h = hashlib.sha256(p.read_bytes()).hexdigest()
        if h in seen:
            raise InputError(f"{p}: the same image as {seen[h]}; give each board pose once")
        seen[h] = str(p)


def calibrate_to_file(
    images: Sequence[str | Path],
    out_path: str | Path,
    *,
    board: tuple[int, int] | str = (9, 6),
    square_mm: float = 25.0,
    pairs: bool = False,
    skew: bool = False,
    tangential: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> Calibration:
    """``prism3d calibrate IMAGES... -o calib.yaml --board 9x6 --square 25 [--pairs]
    [--skew] [--no-tangential]``: calibrate and write the YAML (atomically; nothing is
    written when calibration fails). Returns the calibration (print ``summary()``)."""
    out = Path(out_path)
    if out.suffix.lower() not in (".yaml", ".yml", ".xml", ".json"):
        raise InputError(f"{out}: calibration files must end in .yaml, .yml, .xml or .json")
    if out.is_dir():
        raise InputError(f"{out}: is a folder; give a file name such as calib.yaml")
    b = parse_board(board) if isinstance(board, str) else board
    options = CalibrationOptions(board=b, square_mm=square_mm, pairs=pairs, skew=skew, tangential=tangential)
    _check_distinct_files(images)
    cal = calibrate_stereo(images, options=options, progress=progress)
    cal.save(out)
    return cal
