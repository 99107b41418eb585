"""One moving camera's two frames as a stereo pair: rectified from the relative pose and
matched with our matcher; exact on a synthetic textured ground seen from two known
poses, and on the real drone pair (rectification, coverage)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.reconstruct.stereo.flatness import ransac_plane
from prism3d.reconstruct.survey.model import TwoViewPose
from prism3d.reconstruct.survey.pair import pair_cloud, rectify_from_pose

F, W, H = 700.0, 640, 480
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def _rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _ground_views(depth: float, c2: np.ndarray, R: np.ndarray, seed: int = 0):
    """Two views of a textured plane Z = ``depth`` (camera 1's frame) from camera 1 and
    from camera 2 (centre ``c2`` in camera 1's frame, x2 = R x1 + t)."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (1200, 1200)).astype(np.float32), (0, 0), 1.2)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    scale = 1200 / (2.2 * depth * W / F)  # texture px per unit on the ground

    def view(Rc: np.ndarray, centre: np.ndarray) -> np.ndarray:
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        d = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones_like(u)], axis=-1) @ Rc  # rays in cam1: R^T d
        s = (depth - centre[2]) / d[..., 2]
        X = centre[0] + s * d[..., 0]
        Y = centre[1] + s * d[..., 1]
        mx = (X * scale + 600).astype(np.float32)
        my = (Y * scale + 600).astype(np.float32)
        g = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
        return np.clip(g, 0, 255).astype(np.uint8)

    return view(np.eye(3), np.zeros(3)), view(R, c2)


def _pose(R: np.ndarray, c2: np.ndarray, depth: float) -> TwoViewPose:
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-30, 30, 200), rng.uniform(-20, 20, 200), np.full(200, depth)]
    t = -R @ c2
    x1 = X @ K.T
    x2 = (X @ R.T + t) @ K.T
    return TwoViewPose(R=R, t=t / np.linalg.norm(t), pts1=x1[:, :2] / x1[:, 2:], pts2=x2[:, :2] / x2[:, 2:],
                       n_matches=200, inlier_rms_px=0.0)


def test_pair_of_a_moving_camera_gives_the_true_ground():
    """A nadir camera moves 30 m along its image's -y and turns 5 deg over ground 100 m
    below: the pair rectifies, and the points lie on the true plane (depth within 0.3 %,
    flat to 0.1 % of the range), over most of the overlap."""
    depth, c2, R = 100.0, np.array([0.0, -30.0, 0.0]), _rz(5.0)
    v1, v2 = _ground_views(depth, c2, R)
    pose = _pose(R, c2, depth)
    pc = pair_cloud(v1, v2, K, pose, baseline=30.0)
    z = pc.points[:, 2]
    assert abs(np.median(z) / depth - 1) < 0.003
    assert np.percentile(np.abs(z - depth), 90) < 0.001 * depth
    assert pc.valid_fraction > 0.9
    import cv2

    r1 = cv2.perspectiveTransform(pose.pts1[None], pc.rect.H1)[0]  # matched points share rows
    r2 = cv2.perspectiveTransform(pose.pts2[None], pc.rect.H2)[0]
    assert np.abs(r1[:, 1] - r2[:, 1]).max() < 1e-6


def test_forward_motion_and_bad_pairs_are_refused():
    R = np.eye(3)
    fwd = TwoViewPose(R=R, t=np.array([0.0, 0.0, -1.0]), pts1=np.zeros((30, 2)), pts2=np.zeros((30, 2)),
                      n_matches=30, inlier_rms_px=0.0)
    img = np.zeros((H, W), np.uint8)
    with pytest.raises(InputError, match="forward motion"):
        rectify_from_pose(img, img, K, fwd)
    with pytest.raises(InputError, match="one size"):
        rectify_from_pose(img, np.zeros((H, W + 2), np.uint8), K, fwd)
    with pytest.raises(InputError, match="baseline"):
        pair_cloud(img, img, K, fwd, baseline=0.0)


@pytest.mark.realdata
def test_real_drone_pair_rectifies_and_covers_its_overlap(shared_data):
    """IMG_2188 -> IMG_2189 at 1600 px: after rectification the pose's inlier matches
    share rows (median 0.2 px), our matcher gives depth over 80 % of the pair's overlap
    (measured 91 %), and the DSM at 0.2 m fills 80 % of the pair's footprint (93 %)."""
    import cv2

    from prism3d.capture.geotag import exif_focal_px, read_position_table
    from prism3d.geo import wgs84_to_enu
    from tests.reconstruct.two_view_anchor import relative_pose

    d = shared_data / "aerial/snowpeak_internal_only"
    s = 1600 / 4608
    a, b = (cv2.resize(cv2.imread(str(d / n)), None, fx=s, fy=s, interpolation=cv2.INTER_AREA)[..., ::-1].copy()
            for n in ("IMG_2188.JPG", "IMG_2189.JPG"))
    h, w = a.shape[:2]
    f = exif_focal_px(d / "IMG_2188.JPG") * s
    Kr = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    pose = relative_pose(a, b, Kr)
    tags = read_position_table(d / "geoinfo.txt")
    A, B = tags["IMG_2188.JPG"], tags["IMG_2189.JPG"]
    base = float(np.linalg.norm(wgs84_to_enu([[B.lat_deg, B.lon_deg, B.alt_m]], [A.lat_deg, A.lon_deg, A.alt_m])))
    pc = pair_cloud(a, b, Kr, pose, baseline=base)
    r1 = cv2.perspectiveTransform(pose.pts1[None], pc.rect.H1)[0]
    r2 = cv2.perspectiveTransform(pose.pts2[None], pc.rect.H2)[0]
    assert np.median(np.abs(r1[:, 1] - r2[:, 1])) < 0.5
    assert pc.valid_fraction > 0.8
    assert 80.0 < np.median(pc.points[:, 2]) < 140.0  # a survey flight's height (GPS-scaled), m
    # levelled on the ground, turned onto the GPS track: a DSM over the pair's footprint
    from prism3d.reconstruct.survey.dsm import grid_points
    c2 = wgs84_to_enu([[B.lat_deg, B.lon_deg, B.alt_m]], [A.lat_deg, A.lon_deg, A.alt_m])[0]
    _, pts = enu_from_pair(pc.points, pose.baseline_cam1, np.zeros(3), c2)
    g = grid_points(pts, pc.colours, 0.2)
    hull = cv2.convexHull(((pts[::100, :2] - [g.west, g.north]) * [1, -1] / g.gsd).astype(np.float32))
    inside = np.zeros(g.dsm.shape, np.uint8)
    cv2.fillConvexPoly(inside, hull.astype(np.int32), 1)
    assert np.isfinite(g.dsm)[inside > 0].mean() > 0.8  # measured 0.93


def test_enu_from_a_pair_levels_the_ground_and_follows_the_track():
    """The synthetic pair with the GPS track heading north-east:
    the ground comes out level (heights within 0.1 % of the range), at the right height
    below camera 1, and camera 2 lands on its GPS position (horizontally exact; the
    vertical as good as the levelling)."""
    depth, c2, R = 100.0, np.array([0.0, -30.0, 0.0]), _rz(5.0)
    v1, v2 = _ground_views(depth, c2, R)
    pc = pair_cloud(v1, v2, K, _pose(R, c2, depth), baseline=30.0)
    c1e = np.array([10.0, 20.0, 150.0])
    track = np.array([30.0 / math.sqrt(2), 30.0 / math.sqrt(2), 0.0])
    Renu, pts = enu_from_pair(pc.points, np.array([0.0, -1.0, 0.0]), c1e, c1e + track)
    assert np.percentile(np.abs(pts[:, 2] - (150.0 - depth)), 90) < 0.1
    c2e = Renu @ c2 + c1e
    assert np.allclose(c2e[:2], (c1e + track)[:2], atol=1e-6)  # the heading is the track's
    assert abs(c2e[2] - c1e[2]) < 0.05  # up is estimated from the ground: 0.1 deg over 30 m
    with pytest.raises(InputError, match="horizontally"):
        enu_from_pair(pc.points, np.array([0.0, -1.0, 0.0]), c1e, c1e + [0, 0, 5.0])


def enu_from_pair(points_cam1: NDArray, baseline_cam1: NDArray, c1_enu: NDArray, c2_enu: NDArray
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera 1's orientation in a local east-north-up frame from a pair alone (the
    survey levels and georeferences all its frames at once; this is the two-frame case): up is the
    normal of the dominant plane of the points (the ground, robustly fitted; a nadir
    survey's assumption), and the turn about up puts the pair's baseline along the GPS
    track ``c1_enu`` -> ``c2_enu``. Returns ``R_enu_cam1`` and the points in ENU (metres,
    camera 1 at ``c1_enu``). Two frames cannot do better: with three or more, a
    similarity fitted to all the GPS positions replaces the plane assumption."""
    P = check_array(points_cam1, "points", ndim=2).astype(np.float64)
    if len(P) < 100:
        raise InputError("pair: fewer than 100 points; no ground to level on")
    c1 = np.asarray(c1_enu, dtype=np.float64)
    c2 = np.asarray(c2_enu, dtype=np.float64)
    track = c2 - c1
    if np.hypot(track[0], track[1]) < 1e-3:
        raise InputError("pair: the GPS positions do not move horizontally; no heading to align to")
    rng = np.random.default_rng(0)
    sample = P[rng.choice(len(P), size=min(len(P), 20000), replace=False)]
    up, _, _ = ransac_plane(sample, 0.01 * float(np.median(sample[:, 2])), rng)  # 1 % of the range
    if up @ np.median(P, axis=0) > 0:  # up points from the ground towards the camera
        up = -up
    b = np.asarray(baseline_cam1, dtype=np.float64)
    bh = b - (b @ up) * up
    th = np.array([track[0], track[1], 0.0])
    bh /= np.linalg.norm(bh)
    th /= np.linalg.norm(th)
    # R maps camera-1 axes to ENU: up -> z, the baseline's horizontal part -> the track's
    src = np.stack([bh, np.cross(up, bh), up], axis=1)
    dst = np.stack([th, np.cross([0.0, 0.0, 1.0], th), [0.0, 0.0, 1.0]], axis=1)
    R = dst @ src.T
    return R, P @ R.T + c1
