"""Two frames of one moving camera as a stereo pair: rectified from their relative pose
(the motion becomes the x axis, both views share one orientation and focal length),
matched with our matcher, and back-projected into camera 1's frame, scaled by a known
baseline (GPS) or left in baseline units. The survey mode's dense step for one pair
(docs/uav.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.reconstruct.stereo.match import match_stereo_full
from prism3d.reconstruct.survey.model import TwoViewPose

__all__ = ["PAIR_MATCHERS", "PairCloud", "RectifiedPair", "pair_cloud", "rectify_from_pose"]


@dataclass(frozen=True)
class RectifiedPair:
    """``left``/``right`` rectified images (camera 1 is the left one), their coverage
    masks, the homographies from each original image (``H1``, ``H2``), the rectified
    intrinsics ``K`` and ``R_rect`` (rectified frame from camera 1's)."""

    left: NDArray
    right: NDArray
    mask_left: NDArray[np.bool_]
    mask_right: NDArray[np.bool_]
    H1: NDArray[np.float64]
    H2: NDArray[np.float64]
    K: NDArray[np.float64]
    R_rect: NDArray[np.float64]


def rectify_from_pose(img1: NDArray, img2: NDArray, K: NDArray, pose: TwoViewPose) -> RectifiedPair:
    """Rectify two views of one camera (intrinsics ``K``) whose relative pose is
    ``pose``: the new x axis is the motion from camera 1 to camera 2, the new z the mean
    of the two optical axes made orthogonal to it (Fusiello's construction); the canvas
    holds both warped images. Refused when the motion is mostly along the view (forward
    motion: epipoles inside the image)."""
    import cv2

    a, b = check_array(img1, "image 1"), check_array(img2, "image 2")
    if a.shape != b.shape:
        raise InputError(f"images: {a.shape} and {b.shape} differ; a pair needs frames of one size")
    K = check_array(K, "K", shape=(3, 3)).astype(np.float64)
    h, w = a.shape[:2]
    ex = pose.baseline_cam1
    z2 = pose.R.T @ np.array([0.0, 0.0, 1.0])
    zm = np.array([0.0, 0.0, 1.0]) + z2
    if abs(float(ex @ zm / np.linalg.norm(zm))) > 0.7:  # within 45 deg of the view: forward motion
        raise InputError("pair: the camera moved along its view (forward motion); it cannot be rectified as a stereo pair")
    ey = np.cross(zm, ex)
    ey /= np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    Rr = np.stack([ex, ey, ez])
    Kinv = np.linalg.inv(K)
    H1 = K @ Rr @ Kinv
    H2 = K @ Rr @ pose.R.T @ Kinv
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1.0]]).T
    pts = np.hstack([H1 @ corners, H2 @ corners])
    pts = pts[:2] / pts[2]
    x0, y0 = np.floor(pts.min(axis=1))
    x1, y1 = np.ceil(pts.max(axis=1))
    W, H = int(x1 - x0) + 1, int(y1 - y0) + 1
    if W * H > 16 * w * h:
        raise InputError("pair: the rectified views would be more than 16x the frame (too oblique a motion)")
    T = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1.0]])
    H1, H2 = T @ H1, T @ H2
    ones = np.full((h, w), 255, np.uint8)
    left = cv2.warpPerspective(a, H1, (W, H), flags=cv2.INTER_LINEAR)
    right = cv2.warpPerspective(b, H2, (W, H), flags=cv2.INTER_LINEAR)
    m1 = cv2.warpPerspective(ones, H1, (W, H), flags=cv2.INTER_NEAREST) > 0
    m2 = cv2.warpPerspective(ones, H2, (W, H), flags=cv2.INTER_NEAREST) > 0
    Kr = K.copy()
    Kr[0, 2] -= x0
    Kr[1, 2] -= y0
    return RectifiedPair(left, right, m1, m2, H1, H2, Kr, Rr)


@dataclass(frozen=True)
class PairCloud:
    """Points (n, 3) in camera 1's frame (units of ``baseline``), their colours (n, 3)
    uint8, the rectified pair, the disparity search range used, and ``valid_fraction``:
    the share of the two views' overlap (left pixels whose match at the median disparity
    falls in the right view) with a valid depth."""

    points: NDArray[np.float64]
    colours: NDArray[np.uint8]
    rect: RectifiedPair
    disparity_range: tuple[int, int]
    valid_fraction: float


#: Matchers a pair can be matched with: ours, or OpenCV's SGBM (the benchmarks' anchor).
PAIR_MATCHERS = ("ours", "sgbm")


def _sgbm(left: NDArray, right: NDArray, lo: int, n: int) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """OpenCV StereoSGBM (3-way, 5 px blocks, its usual penalties) over ``lo .. lo + n``
    (widened to a multiple of 16): disparity and validity."""
    import cv2

    n16 = int(np.ceil(n / 16.0)) * 16
    ch = 1 if left.ndim == 2 else left.shape[2]
    sg = cv2.StereoSGBM_create(minDisparity=int(lo), numDisparities=n16, blockSize=5, P1=8 * ch * 25,
                               P2=32 * ch * 25, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                               mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    d = sg.compute(left, right).astype(np.float32) / 16.0
    return d, d >= lo


def pair_cloud(img1: NDArray, img2: NDArray, K: NDArray, pose: TwoViewPose, *, baseline: float = 1.0,
               margin_px: int = 8, options=None, matcher: str = "ours") -> PairCloud:
    """Dense points of a pair: :func:`rectify_from_pose`, the disparity range from the pose's
    inlier matches (0.5-99.5 %, widened by ``margin_px``), our matcher (or ``matcher=
    "sgbm"``: OpenCV's, for comparison), triangulation in the rectified frame, then
    rotated back into camera 1's frame and scaled so the cameras are ``baseline`` apart."""
    import cv2

    if not (np.isfinite(baseline) and baseline > 0):
        raise InputError(f"baseline: expected a length > 0, got {baseline}")
    rp = rectify_from_pose(img1, img2, K, pose)
    q1 = cv2.perspectiveTransform(pose.pts1[None], rp.H1)[0]
    q2 = cv2.perspectiveTransform(pose.pts2[None], rp.H2)[0]
    dx = q1[:, 0] - q2[:, 0]
    lo = int(np.floor(np.percentile(dx, 0.5))) - margin_px
    hi = int(np.ceil(np.percentile(dx, 99.5))) + margin_px
    if hi <= max(lo, 0) + 1:
        raise InputError("pair: the views barely move against each other (too short a baseline for depth)")
    if matcher not in PAIR_MATCHERS:
        raise InputError(f"matcher: expected one of {', '.join(PAIR_MATCHERS)}, got {matcher!r}")
    if matcher == "sgbm":
        disp, ok = _sgbm(rp.left, rp.right, lo, hi - lo)
    else:
        res = match_stereo_full(rp.left, rp.right, min_disp=lo, num_disp=hi - lo, options=options)
        disp, ok = res.disparity, res.valid
    # the overlap: left pixels whose match (at the typical disparity) lies in the right view
    shift = int(round(float(np.median(dx))))
    seen = np.zeros_like(rp.mask_right)
    if 0 <= shift < seen.shape[1]:
        seen[:, shift:] = rp.mask_right[:, : seen.shape[1] - shift]
    elif -seen.shape[1] < shift < 0:
        seen[:, :shift] = rp.mask_right[:, -shift:]
    both = rp.mask_left & seen
    valid = ok & both & (disp > 0)
    rows, cols = np.nonzero(valid)
    d = disp[rows, cols].astype(np.float64)
    f, cx, cy = rp.K[0, 0], rp.K[0, 2], rp.K[1, 2]
    Z = f * baseline / d
    P_rect = np.c_[(cols - cx) * Z / f, (rows - cy) * Z / f, Z]
    P = P_rect @ rp.R_rect  # rectified -> camera 1: R_rect^T p, row-wise
    img = rp.left if rp.left.ndim == 3 else np.repeat(rp.left[..., None], 3, axis=2)
    return PairCloud(P, img[rows, cols, :3].astype(np.uint8), rp, (lo, hi),
                     float(valid.sum() / max(int(both.sum()), 1)))
