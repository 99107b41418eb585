"""The object frame of a scanned model, chosen from the data (docs/stitching.md, "Object frame").

``z`` up: the turntable's axis when the views came from one, else the normal of the
support plane the object stands on; ``x`` forward: an axis of the smallest rectangle around the footprint
when it is also a mirror axis (box-like hulls), else the footprint's mirror axis (swept
wings), else the rectangle's; of it and the axis across, the longer (the longest
horizontal extent); ``y = z x x``; origin:
the footprint's centre on the support (the lowest surface point along ``z``). Footprint and
extents are measured on the points near the surface fitted to them, each extreme point
projected on the plane of its neighbourhood (reconstruct/scan/surface.py; the scan
features' boxes use the same), not on the noisiest points. Which end of ``x`` is the front cannot be told from
shape alone (measured: the end where the points tail off is the front on 8 of 21
Quaternius CAD vehicles and 9 of the 12 built-in targets): unless the scan that faced the front is named, the choice is stated as a guess
(``forward_ambiguous``), not hidden.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError, ReconstructionError
from prism3d.geometry import rotvec_from_matrix
from prism3d.reconstruct.scan.registration import point_spacing
from prism3d.reconstruct.scan.surface import surface_extents, surface_points

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
#: Grid of the footprint's area (cells along its longer side), closed over gaps of this
#: many cells (sparse or unseen patches) and with its holes filled.
FOOTPRINT_CELLS = 400
FOOTPRINT_CLOSE_CELLS = 5
#: Mirror-axis search: candidate angles every MIRROR_STEP_DEG, refined to
#: MIRROR_FINE_DEG; the axis may pass up to MIRROR_SHIFT_CELLS from the footprint's
#: centroid (an unevenly scanned side moves the centroid).
MIRROR_STEP_DEG = 1.0
MIRROR_FINE_DEG = 0.02
MIRROR_SHIFT_CELLS = 4.0
#: A footprint is mirror-symmetric when its reflection about the best axis lies, on
#: average, at most this share of the typical (median-angle) misfit from it.
MIRROR_MAX_RATIO = 0.6
#: The smallest rectangle's axes are preferred when one reflects the footprint within this
#: many cells (mean) of the best mirror axis: exact on box-like hulls, whose small
#: asymmetric fittings can tilt the best mirror line (ship_s3: 1.6 deg); a swept planform
#: (jets) has no such rectangle axis (misfit 3-5 cells against 0.3-2).
RECT_MIRROR_TOL_CELLS = 0.5
#: Footprint cells reflected per trial axis (an even subsample of them).
MIRROR_SAMPLES = 20000
#: A front view must look at the object within this angle of its long axis (horizontally).
FRONT_VIEW_MAX_DEG = 60.0


@dataclass(frozen=True)
class ObjectFrame:
    """Where a model stands: ``T_object_model`` (4, 4) maps model coordinates (mm) into the
    object frame; ``up_from`` ``"turntable"`` or ``"support plane"``; ``extent_mm`` (3,)
    length, width, height along x, y, z; ``forward_ambiguous`` True when front and back
    could be swapped; ``front_view`` the scan that set the front (None: a guess); ``notes``
    what else a user should know."""

    T_object_model: NDArray[np.float64]
    up_from: str
    extent_mm: NDArray[np.float64]
    forward_ambiguous: bool
    notes: list[str] = field(default_factory=list)
    front_view: int | None = None

    def to_dict(self) -> dict:
        return {"T_object_model": self.T_object_model.tolist(), "up_from": self.up_from,
                "extent_mm": [float(v) for v in self.extent_mm],
                "forward_ambiguous": bool(self.forward_ambiguous), "front_view": self.front_view,
                "notes": list(self.notes)}


def object_frame(points: NDArray, T_model_scan: Sequence[NDArray] | None = None, *,
                 front_view: int | None = None, normals: NDArray | None = None) -> ObjectFrame:
    """The object frame of a model's ``points`` (N, 3) mm given the poses of the scans it was
    stitched from (``T_model_scan``, camera frames in OpenCV convention; None: one scan in
    the model frame). ``front_view``: the index of the scan that looked at the object's
    front (x then points at that camera); without it front and back are a stated guess
    (``forward_ambiguous``). ``normals`` (N, 3): the points' outward normals (default:
    estimated, facing the scans' sensors). ReconstructionError when neither a turntable
    nor a support plane gives the up direction (the message names what is missing)."""
    P, N = _finite_points(points, normals)
    poses = [np.eye(4)] if not T_model_scan else [np.asarray(T, np.float64) for T in T_model_scan]
    if front_view is not None and (isinstance(front_view, bool) or not isinstance(front_view, (int, np.integer))
                                   or not 0 <= front_view < len(poses)):
        raise InputError(f"front_view: expected a scan index in [0, {len(poses) - 1}], got {front_view!r}")
    upright = _upright(poses)
    notes: list[str] = []
    up = _turntable_up(poses, upright)
    plane = None
    if up is not None:
        up_from = "turntable"
    else:
        up, plane, tol = _support_up(P, upright)
        up_from = "support plane"
        above = P @ up > plane + tol  # the support itself is no part of the object
        P, N = P[above], None if N is None else N[above]
        if len(P) < 100:
            raise ReconstructionError("object frame: almost nothing stands on the support plane")
    P = surface_points(P, N, viewpoints=[T[:3, 3] for T in poses])[0]
    e1, e2 = _basis(up)
    uv = np.stack([P @ e1, P @ e2], axis=1)
    x2, symmetric = _footprint_axis(uv)
    if not symmetric:
        notes.append("the footprint has no mirror symmetry; x is the long side of the smallest "
                     "rectangle around it")
    x = x2[0] * e1 + x2[1] * e2
    y0 = np.cross(up, x)
    lo3, hi3 = surface_extents(P, np.stack([x, y0, up]))
    if hi3[1] - lo3[1] > hi3[0] - lo3[0]:  # x is the longer horizontal extent
        x, y0 = y0, -x
        lo3, hi3 = np.array([lo3[1], -hi3[0], lo3[2]]), np.array([hi3[1], -lo3[0], hi3[2]])
        x2 = np.array([x @ e1, x @ e2])
    lo = float(lo3[2]) if plane is None else float(plane)
    hi = float(hi3[2])
    cx, cy = (lo3[:2] + hi3[:2]) / 2
    centre_xyz = cx * x + cy * y0
    centre = np.array([centre_xyz @ e1, centre_xyz @ e2])
    length, width = float(hi3[0] - lo3[0]), float(hi3[1] - lo3[1])
    origin = centre[0] * e1 + centre[1] * e2 + lo * up
    x, ambiguous = _orient_front(x, up, origin, poses, front_view, uv, centre, x2, notes)
    y = np.cross(up, x)
    R = np.stack([x, y, up])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ origin
    return ObjectFrame(T, up_from, np.array([length, width, hi - lo]), ambiguous, notes,
                       None if front_view is None else int(front_view))


def _finite_points(points: NDArray, normals: NDArray | None) -> tuple[NDArray, NDArray | None]:
    """The finite points (and their normals), at least 100 of them."""
    P = check_array(points, "points", shape=(None, 3), dtype_kind="fiu").astype(np.float64)
    ok = np.all(np.isfinite(P), axis=1)
    N = None
    if normals is not None:
        N = check_array(normals, "normals", shape=(len(P), 3), dtype_kind="fiu").astype(np.float64)
        ok &= np.all(np.isfinite(N), axis=1)
        N = N[ok]
    P = P[ok]
    if len(P) < 100:
        raise ReconstructionError(f"object frame: {len(P)} points are too few to find the object's frame")
    return P, N


def _orient_front(x: NDArray, up: NDArray, origin: NDArray, poses: list[NDArray], front_view: int | None,
                  uv: NDArray, centre: NDArray, x2: NDArray, notes: list[str]) -> tuple[NDArray, bool]:
    """``x`` turned toward the ``front_view`` camera or, without one, toward the points'
    heavier tail (a guess, added to ``notes``); and whether front and back are ambiguous."""
    if front_view is not None:
        look = poses[front_view][:3, 3] - origin  # from the object to that camera
        look -= (look @ up) * up
        ang = float(np.degrees(np.arccos(np.clip(abs(look @ x) / max(np.linalg.norm(look), 1e-300), 0, 1))))
        if ang > FRONT_VIEW_MAX_DEG:
            raise InputError(f"front_view: scan {front_view} looks at a side of the object ({ang:.0f} deg from "
                             f"its long axis, over {FRONT_VIEW_MAX_DEG:g}); give the scan that faced its front")
        if look @ x < 0:
            x = -x
        ambiguous = False
    else:
        # shape alone does not tell front from back: the points' heavier tail, a stated guess
        # (right on 8 of 21 Quaternius vehicles, docs/stitching.md)
        if _skewness((uv - centre) @ x2) < 0:
            x = -x
        ambiguous = True
        notes.append("which end is the front was not given (front_view / --front-view): x points to the "
                     "end where the points tail off, a guess; front and back may be swapped")
    return x, ambiguous


def _upright(poses: list[NDArray]) -> NDArray[np.float64]:
    """The cameras' mean image-up direction (-y of OpenCV cameras) in the model frame: a
    camera on a tripod or a drone's gimbal is upright, which fixes the sign of up."""
    u = np.sum([-T[:3, 1] for T in poses], axis=0)
    return u / max(np.linalg.norm(u), 1e-300)


def _turntable_up(poses: list[NDArray], upright: NDArray) -> NDArray[np.float64] | None:
    """The turntable axis, pointing the cameras' upright way; None when the poses do not
    share one rotation axis."""
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


def _footprint_axis(uv: NDArray) -> tuple[NDArray[np.float64], bool]:
    """A unit direction (2,) of the footprint's main horizontal axis and whether it is a
    mirror axis. The footprint: the points' cells on a FOOTPRINT_CELLS grid, closed and
    filled (how densely a side was scanned does not weigh). The mirror axis: the line
    about which the reflected footprint lies closest to itself (mean distance, cells).
    An axis of the smallest rectangle around the footprint that mirrors it about as well
    (RECT_MIRROR_TOL_CELLS) wins; without any mirror axis, the rectangle's long side."""
    import cv2

    span = float(np.ptp(uv, axis=0).max())
    cell = max(span / FOOTPRINT_CELLS, 1e-9)
    pad = FOOTPRINT_CLOSE_CELLS + 2
    ij = np.floor((uv - uv.min(axis=0)) / cell).astype(np.int64) + pad
    shape = tuple(int(v) for v in ij.max(axis=0) + pad + 1)
    img = np.zeros(shape, np.uint8)
    img[ij[:, 0], ij[:, 1]] = 1
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (FOOTPRINT_CLOSE_CELLS, FOOTPRINT_CLOSE_CELLS))
    img = cv2.morphologyEx(img, cv2.MORPH_CLOSE, k)
    outside = img.copy()
    cv2.floodFill(outside, np.zeros((shape[0] + 2, shape[1] + 2), np.uint8), (0, 0), 1)
    img |= 1 - outside  # holes (an unseen patch inside the outline) are footprint too
    occ = np.argwhere(img > 0).astype(np.float64) + 0.5
    dist = cv2.distanceTransform((1 - img).astype(np.uint8), cv2.DIST_L2, 5)
    c = occ.mean(axis=0)
    X = (occ - c)[:: max(1, len(occ) // MIRROR_SAMPLES)]
    hi_idx = np.array(shape) - 1

    def misfit(th: float, shift_step: float = 0.5) -> float:
        d = np.array([np.cos(th), np.sin(th)])
        n = np.array([-d[1], d[0]])
        s = X @ n
        best = np.inf
        for t in np.arange(-MIRROR_SHIFT_CELLS, MIRROR_SHIFT_CELLS + 1e-9, shift_step):
            q = np.clip(np.floor(c + X - 2 * (s - t)[:, None] * n).astype(np.int64), 0, hi_idx)
            best = min(best, float(np.mean(np.minimum(dist[q[:, 0], q[:, 1]], 10.0))))
        return best

    angles = np.radians(np.arange(0.0, 180.0, MIRROR_STEP_DEG))
    scores = np.array([misfit(a, 2.0) for a in angles])  # coarse offsets, then fine near the best
    th = float(angles[int(np.argmin(scores))])
    step = np.radians(MIRROR_STEP_DEG)
    best = np.inf
    while step > np.radians(MIRROR_FINE_DEG):
        step /= 5.0
        cand = th + step * np.arange(-5, 6)
        fits = [misfit(a) for a in cand]
        th, best = float(cand[int(np.argmin(fits))]), float(min(fits))
    (_, _), (w, h), ang = cv2.minAreaRect(occ.astype(np.float32))
    a = np.radians(ang) + (0.0 if w >= h else np.pi / 2)  # the rectangle's long side
    rect_fit, rect = min((misfit(r), r) for r in (a, a + np.pi / 2))
    if rect_fit <= best + RECT_MIRROR_TOL_CELLS:  # a box-like hull: the rectangle is exact
        return np.array([np.cos(rect), np.sin(rect)]), True
    if best <= MIRROR_MAX_RATIO * float(np.median(scores)):
        return np.array([np.cos(th), np.sin(th)]), True
    return np.array([np.cos(a), np.sin(a)]), False


def _skewness(s: NDArray) -> float:
    s = s - s.mean()
    sd = s.std()
    return float(np.mean(s**3) / sd**3) if sd > 0 else 0.0
