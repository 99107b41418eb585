"""The object frame of a scanned model, chosen from the data (docs/stitching.md, "Object frame").

``z`` up: the turntable's axis when the views came from one, else the normal of the
support plane the object stands on; ``x`` forward: the long side of the smallest
rectangle around the footprint (the longest horizontal extent); ``y = z x x``; origin:
the footprint's centre on the support (the lowest surface point along ``z``). Which end
of ``x`` is the front cannot be told from shape alone for a symmetric object: the choice
is stated (``forward_ambiguous``), not hidden.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import ReconstructionError

__all__ = ["ObjectFrame", "object_frame"]

#: A set of poses is a turntable's when at least this many views turned by more than
#: MIN_TURN_DEG about axes within AXIS_TOL_DEG of their mean.
MIN_TURNTABLE_VIEWS = 3
MIN_TURN_DEG = 5.0
AXIS_TOL_DEG = 5.0
#: The support plane: the plane (RANSAC, inliers within this many point spacings) under
#: most of the points whose normal is within SUPPORT_TILT_DEG of the cameras' upright.
SUPPORT_INLIER_SPACINGS = 2.0
SUPPORT_TILT_DEG = 30.0
#: ... holding at least this share of the points, with at most BELOW_SHARE of the rest
#: beneath it.
SUPPORT_MIN_SHARE = 0.05
BELOW_SHARE = 0.02
#: The lowest point is taken at this quantile of the heights (a stray point below the
#: object does not move the origin; its thin extremities are kept: no trimming above).
TRIM_QUANTILE = 0.001
#: Grid of the footprint's area, cells along its longer side.
FOOTPRINT_CELLS = 200
#: |skewness| of the points along x below which front and back are a coin toss.
AMBIGUOUS_SKEW = 0.15


@dataclass(frozen=True)
class ObjectFrame:
    """Where a model stands: ``T_object_model`` (4, 4) maps model coordinates (mm) into the
    object frame; ``up_from`` ``"turntable"`` or ``"support plane"``; ``extent_mm`` (3,)
    length, width, height along x, y, z; ``forward_ambiguous`` True when front and back
    could be swapped; ``notes`` what else a user should know."""

    T_object_model: NDArray[np.float64]
    up_from: str
    extent_mm: NDArray[np.float64]
    forward_ambiguous: bool
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"T_object_model": self.T_object_model.tolist(), "up_from": self.up_from,
                "extent_mm": [float(v) for v in self.extent_mm],
                "forward_ambiguous": bool(self.forward_ambiguous), "notes": list(self.notes)}


def object_frame(points: NDArray, T_model_scan: Sequence[NDArray] | None = None) -> ObjectFrame:
    """The object frame of a model's ``points`` (N, 3) mm given the poses of the scans it was
    stitched from (``T_model_scan``, camera frames in OpenCV convention; None: one scan in
    the model frame). ReconstructionError when neither a turntable nor a support plane
    gives the up direction (the message names what is missing)."""
    P = check_array(points, "points", shape=(None, 3), dtype_kind="fiu").astype(np.float64)
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 100:
        raise ReconstructionError(f"object frame: {len(P)} points are too few to find the object's frame")
    poses = [np.eye(4)] if not T_model_scan else [np.asarray(T, np.float64) for T in T_model_scan]
    upright = _upright(poses)
    notes: list[str] = []
    up = _turntable_up(poses, upright)
    if up is not None:
        up_from = "turntable"
        heights = P @ up
        lo = float(np.quantile(heights, TRIM_QUANTILE))
    else:
        up, lo, tol = _support_up(P, upright)
        up_from = "support plane"
        P = P[P @ up > lo + tol]  # the support itself is no part of the object
        heights = P @ up
    hi = float(heights.max())
    e1, e2 = _basis(up)
    uv = np.stack([P @ e1, P @ e2], axis=1)
    centre, x2, (length, width) = _footprint(uv)
    x = x2[0] * e1 + x2[1] * e2
    skew = _skewness((uv - centre) @ x2)
    if skew < 0:  # the heavier tail forward (a stated convention, not a truth)
        x = -x
    ambiguous = abs(skew) < AMBIGUOUS_SKEW
    if ambiguous:
        notes.append(f"front and back cannot be told apart from the shape (skewness {abs(skew):.2f} "
                     f"< {AMBIGUOUS_SKEW}); x may point backwards")
    y = np.cross(up, x)
    origin = centre[0] * e1 + centre[1] * e2 + lo * up
    R = np.stack([x, y, up])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ origin
    return ObjectFrame(T, up_from, np.array([length, width, hi - lo]), ambiguous, notes)


def _upright(poses: list[NDArray]) -> NDArray[np.float64]:
    """The cameras' mean image-up direction (-y of OpenCV cameras) in the model frame: a
    camera on a tripod or a drone's gimbal is upright, which fixes the sign of up."""
    u = np.sum([-T[:3, 1] for T in poses], axis=0)
    return u / max(np.linalg.norm(u), 1e-300)


def _turntable_up(poses: list[NDArray], upright: NDArray) -> NDArray[np.float64] | None:
    """The turntable axis, pointing the cameras' upright way; None when the poses do not
    share one rotation axis."""
    from prism3d.geometry import rotvec_from_matrix

    rv = [rotvec_from_matrix(T[:3, :3] @ np.linalg.inv(poses[0][:3, :3])) for T in poses[1:]]
    turned = [v for v in rv if np.degrees(np.linalg.norm(v)) > MIN_TURN_DEG]
    if len(turned) < MIN_TURNTABLE_VIEWS - 1:
        return None
    ref = max(turned, key=np.linalg.norm)
    axes = [v / np.linalg.norm(v) * (1.0 if v @ ref >= 0 else -1.0) for v in turned]
    mean = np.sum([a * np.linalg.norm(v) for a, v in zip(axes, turned, strict=True)], axis=0)
    mean /= np.linalg.norm(mean)
    if max(np.degrees(np.arccos(np.clip(a @ mean, -1.0, 1.0))) for a in axes) > AXIS_TOL_DEG:
        return None
    return mean if mean @ upright >= 0 else -mean


def _support_up(P: NDArray, upright: NDArray) -> tuple[NDArray[np.float64], float, float]:
    """The normal (upright side) and height of the plane the object stands on, and the
    inlier distance (points within it of the plane belong to the support)."""
    import open3d as o3d

    from prism3d.reconstruct.registration import point_spacing

    spacing = point_spacing(P)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    o3d.utility.random.seed(0)  # the same planes every run
    rest = pc
    for _ in range(4):  # the largest planes first; the support is the lowest upright one
        if len(rest.points) < 100:
            break
        plane, idx = rest.segment_plane(SUPPORT_INLIER_SPACINGS * spacing, 3, 500)
        n = np.asarray(plane[:3], np.float64)
        n /= np.linalg.norm(n)
        d = float(plane[3]) / np.linalg.norm(plane[:3])
        if n @ upright < 0:
            n, d = -n, -d
        tilt = np.degrees(np.arccos(np.clip(n @ upright, -1.0, 1.0)))
        h = P @ n + d  # signed height above the plane
        if (len(idx) >= SUPPORT_MIN_SHARE * len(P) and tilt <= SUPPORT_TILT_DEG
                and np.mean(h < -SUPPORT_INLIER_SPACINGS * spacing) <= BELOW_SHARE):
            return n, -d, SUPPORT_INLIER_SPACINGS * spacing
        rest = rest.select_by_index(idx, invert=True)
    raise ReconstructionError(
        "object frame: the views do not come from a turntable (no common rotation axis) and no "
        "support plane was found under the object; scan it standing on a visible flat surface, "
        "or on a turntable"
    )


def _basis(u: NDArray) -> tuple[NDArray, NDArray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def _footprint(uv: NDArray) -> tuple[NDArray, NDArray, tuple[float, float]]:
    """Centre (2,), long direction (2,) and (length, width) of the footprint: the long
    direction is the major axis of the footprint's area (the points binned on a
    FOOTPRINT_CELLS grid, so that how densely a side was scanned does not weigh), the
    extents are those of the points along it and across."""
    span = np.ptp(uv, axis=0).max()
    cell = max(span / FOOTPRINT_CELLS, 1e-9)
    occ = np.unique(np.floor(uv / cell).astype(np.int64), axis=0).astype(np.float64) * cell
    cov = np.cov((occ - occ.mean(axis=0)).T)
    w, v = np.linalg.eigh(cov)
    d = v[:, int(np.argmax(w))]
    axes = np.stack([d, [-d[1], d[0]]], axis=1)
    q = uv @ axes
    lo, hi = q.min(axis=0), q.max(axis=0)
    centre = axes @ ((lo + hi) / 2)
    return centre, d, (float(hi[0] - lo[0]), float(hi[1] - lo[1]))


def _skewness(s: NDArray) -> float:
    s = s - s.mean()
    sd = s.std()
    return float(np.mean(s**3) / sd**3) if sd > 0 else 0.0
