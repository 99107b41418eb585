"""The OpenCV two-view pose the survey's poses are checked against (tests only): SIFT
features, ratio-test matches, the essential matrix by MAGSAC, the pose it implies
(cheirality), refined on its inliers by least squares of the Sampson distances. The
translation comes back as a unit vector: two views fix the direction of the motion,
not its length (GPS gives that).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.reconstruct.survey.model import TwoViewPose


def _grey8(img: NDArray, name: str) -> NDArray[np.uint8]:
    a = check_array(img, name)
    if a.ndim == 3:
        a = a[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    if a.ndim != 2:
        raise InputError(f"{name}: expected a grey or colour image, got shape {a.shape}")
    if a.dtype != np.uint8:
        a = np.clip(a, 0, 255).astype(np.uint8)
    return a


def _sampson(E_or_F: NDArray, x1: NDArray, x2: NDArray) -> NDArray[np.float64]:
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    Fx1 = h1 @ E_or_F.T
    Ftx2 = h2 @ E_or_F
    num = np.sum(h2 * Fx1, axis=1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / np.maximum(den, 1e-18)


def relative_pose(img1: NDArray, img2: NDArray, K: NDArray, *, max_features: int = 8000,
                  ratio: float = 0.8, threshold_px: float = 1.0, seed: int = 0) -> TwoViewPose:
    """The pose of view 2 relative to view 1 (same camera, intrinsics ``K``, images
    without distortion or with little), from SIFT matches passing Lowe's ratio test
    (``ratio``), MAGSAC on the essential matrix (``threshold_px``), cheirality, and a
    last essential matrix fitted to the inliers. Refused with one line when the views
    share too little (fewer than 30 inliers)."""
    g1, g2 = _grey8(img1, "image 1"), _grey8(img2, "image 2")
    K = check_array(K, "K", shape=(3, 3)).astype(np.float64)
    if not (0 < ratio < 1 and threshold_px > 0 and max_features >= 100):
        raise InputError("relative_pose: expected 0 < ratio < 1, threshold_px > 0, max_features >= 100")
    cv2.setRNGSeed(seed)
    sift = cv2.SIFT_create(nfeatures=int(max_features))
    k1, d1 = sift.detectAndCompute(g1, None)
    k2, d2 = sift.detectAndCompute(g2, None)
    if d1 is None or d2 is None or len(k1) < 30 or len(k2) < 30:
        raise InputError("relative_pose: too few features in the images (textureless or too small?)")
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < 30:
        raise InputError(f"relative_pose: only {len(good)} matches pass the ratio test; do the views overlap?")
    p1 = np.array([k1[m.queryIdx].pt for m in good], dtype=np.float64)
    p2 = np.array([k2[m.trainIdx].pt for m in good], dtype=np.float64)
    return pose_from_matches(p1, p2, K, threshold_px=threshold_px, seed=seed)


def pose_from_matches(p1: NDArray, p2: NDArray, K: NDArray, *, threshold_px: float = 1.0,
                      seed: int = 0) -> TwoViewPose:
    """The relative pose from matched pixels ``p1`` <-> ``p2`` (n, 2): MAGSAC on the
    essential matrix (``threshold_px``), cheirality, then an essential matrix fitted to
    all the inliers (kept when it explains 95 % of them)."""
    p1 = check_array(p1, "p1", ndim=2).astype(np.float64)
    p2 = check_array(p2, "p2", ndim=2).astype(np.float64)
    K = check_array(K, "K", shape=(3, 3)).astype(np.float64)
    if p1.shape != p2.shape or p1.shape[1] != 2:
        raise InputError(f"matches: expected two (n, 2) arrays of the same n, got {p1.shape} and {p2.shape}")
    if len(p1) < 30:
        raise InputError(f"relative_pose: only {len(p1)} matches; do the views overlap?")
    cv2.setRNGSeed(seed)
    E, mask = cv2.findEssentialMat(p1, p2, K, method=cv2.USAC_MAGSAC, prob=0.9999, threshold=threshold_px)
    if E is None or E.shape != (3, 3):
        raise InputError("relative_pose: no essential matrix fits the matches")
    inl = mask.ravel().astype(bool)
    _, R, t, pose_mask = cv2.recoverPose(E, p1[inl], p2[inl], K)
    keep = pose_mask.ravel() > 0
    q1, q2 = p1[inl][keep], p2[inl][keep]
    if len(q1) < 30:
        raise InputError(f"relative_pose: only {len(q1)} matches fit one motion; do the views overlap?")
    R, t = _refine(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).ravel(), q1, q2, K)
    rms = float(np.sqrt(np.mean(_sampson(_fundamental(R, t, K), q1, q2))))
    return TwoViewPose(R=R, t=t, pts1=q1, pts2=q2, n_matches=len(p1), inlier_rms_px=rms)


def _fundamental(R: NDArray, t: NDArray, K: NDArray) -> NDArray[np.float64]:
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    return Kinv.T @ (tx @ R) @ Kinv


def _refine(R: NDArray, t: NDArray, q1: NDArray, q2: NDArray, K: NDArray
            ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least squares of the inliers' Sampson distances over the rotation (a rotation
    vector about ``R``) and the direction of ``t`` (two angles on its tangent plane), with
    a Huber loss at 1 px: the maximum-likelihood pose the essential matrix only
    approximates."""
    t = t / np.linalg.norm(t)
    a = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(t, a)

    def unpack(x: NDArray) -> tuple[NDArray, NDArray]:
        dR = cv2.Rodrigues(x[:3])[0]
        tt = t + x[3] * a + x[4] * b
        return dR @ R, tt / np.linalg.norm(tt)

    def resid(x: NDArray) -> NDArray:
        Rx, tx = unpack(x)
        return np.sqrt(_sampson(_fundamental(Rx, tx, K), q1, q2))

    sol = least_squares(resid, np.zeros(5), loss="huber", f_scale=1.0, x_scale=1e-3)
    return unpack(sol.x)
