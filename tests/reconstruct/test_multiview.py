"""Joint multi-view ICP: poses perturbed from the truth come back, all at once."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.reconstruct.scan.multiview import (
    fit_turntable,
    overlapping_pairs,
    refine_multiview,
    refine_turntable,
    _view_levers,
)
from prism3d.geometry import rotation_angle_deg

from prism3d.errors import InputError


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _views():
    """8 turntable views of tank_t1 (ray cast, 0.15 mm noise, dropouts; see
    test_stitch), each in its camera frame, with normals and the true poses."""
    o3d = pytest.importorskip("open3d")
    from .test_stitch import _raycast_views

    scans, poses, _, _ = _raycast_views()
    pts, nrm = [], []
    for s in scans:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s[0])).voxel_down_sample(1.0)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3.0, max_nn=30))
        pc.orient_normals_towards_camera_location(np.zeros(3))
        pts.append(np.asarray(pc.points))
        nrm.append(np.asarray(pc.normals))
    T0 = np.linalg.inv(poses[0])
    return pts, nrm, [T0 @ T for T in poses]


def _perturb(T, deg, mm, rng, centre):
    """Turn by ``deg`` about ``centre`` (the object, as a pose graph's error is) and
    shift by ``mm``."""
    E = np.eye(4)
    E[:3, :3] = _rot(rng.normal(size=3), deg)
    E[:3, 3] = centre - E[:3, :3] @ centre + rng.normal(size=3) * mm / np.sqrt(3)
    return E @ T


def test_recovers_perturbed_turntable_poses_jointly() -> None:
    scans, normals, truth = _views()
    rng = np.random.default_rng(3)
    centre = scans[0].mean(axis=0)
    init = [truth[0]] + [_perturb(T, 0.4, 0.5, rng, centre) for T in truth[1:]]
    pairs = [(k, (k + 1) % 8) for k in range(8)] + [(k, (k + 2) % 8) for k in range(8)]
    T, info = refine_multiview(scans, normals, init, pairs, spacing=1.0)
    err = [rotation_angle_deg(np.linalg.inv(t) @ e) for t, e in zip(truth, T, strict=True)]
    assert max(err) < 0.02, err
    assert max(abs(np.linalg.det(t[:3, :3]) - 1) for t in T) < 1e-9
    np.testing.assert_array_equal(T[0], init[0])  # the first view is the frame
    assert info["max_change_deg"] > 0.2 and info["rms"] < 0.3 and info["correspondences"] > 1e4


def _turntable(u, p, deg):
    T = np.eye(4)
    T[:3, :3] = _rot(u, deg)
    T[:3, 3] = np.asarray(p, float) - T[:3, :3] @ np.asarray(p, float)
    return T


def test_fit_turntable_recovers_axis_point_and_angles() -> None:
    """Exact turntable poses, angles up to 180 deg and unequal steps."""
    u = np.array([0.02, -0.966, -0.258])
    u /= np.linalg.norm(u)
    p = np.array([30.0, -5.0, 1250.0])
    angles = [0.0, 44.0, 91.0, 135.5, 180.0, -134.0, -90.0, -45.0]
    poses = [_turntable(u, p, a) for a in angles]
    uu, pp, th = fit_turntable(poses)
    assert abs(abs(uu @ u) - 1) < 1e-12
    sign = np.sign(uu @ u)
    np.testing.assert_allclose(np.degrees(th) * sign, angles, atol=1e-9)
    # the fitted axis point lies on the true axis
    d = pp - p
    assert np.linalg.norm(d - (d @ u) * u) < 1e-6


def test_refine_turntable_removes_tilts() -> None:
    """Views tilted 0.3 deg about horizontal axes and shifted 0.3 mm: the
    turntable-constrained refinement puts every view back on one axis; the free
    refinement from the same start is compared beside it."""
    scans, normals, truth = _views()
    rng = np.random.default_rng(5)
    centre = scans[0].mean(axis=0)
    init = [truth[0]] + [_perturb(T, 0.3, 0.3, rng, centre) for T in truth[1:]]
    pairs = [(k, (k + 1) % 8) for k in range(8)] + [(k, (k + 2) % 8) for k in range(8)]
    T, info = refine_turntable(scans, normals, init, pairs, spacing=1.0)
    err = [rotation_angle_deg(np.linalg.inv(t) @ e) for t, e in zip(truth, T, strict=True)]
    assert max(err) < 0.02, err
    # the axis is the true one (the truth's own turntable fit, in view 0's frame)
    u_true, _, th_true = fit_turntable(truth)
    assert np.degrees(np.arccos(min(1.0, abs(float(np.array(info["axis"]) @ u_true))))) < 0.01
    sign = np.sign(float(np.array(info["axis"]) @ u_true))
    dth = (np.array(info["angles_deg"]) * sign - np.degrees(th_true) + 180.0) % 360.0 - 180.0
    assert np.abs(dth).max() < 0.02, dth
    assert info["rms"] <= info["rms_input"] and len(info["angles_deg"]) == 8
    np.testing.assert_array_equal(T[0], np.eye(4))
    with pytest.raises(InputError, match="identity"):
        refine_turntable(scans, normals, [init[1]] + init[1:], pairs, spacing=1.0)


def test_bad_input() -> None:
    scans, normals, truth = _views()
    with pytest.raises(InputError, match="pairs"):
        refine_multiview(scans, normals, truth, [(0, 9)], spacing=1.0)
    with pytest.raises(InputError, match=">= 2 views"):
        refine_multiview(scans[:1], normals[:1], truth[:1], [(0, 0)], spacing=1.0)
    with pytest.raises(InputError):
        refine_multiview(scans, normals[:2], truth, [(0, 1)], spacing=1.0)
    with pytest.raises(InputError, match="spacing"):
        refine_multiview(scans, normals, truth, [(0, 1)], spacing=0.0)


def test_overlapping_pairs_finds_the_views_that_share_surface() -> None:
    """8 turntable views of a tank: neighbours overlap, and so do views 90 deg apart
    (the top and the ends); a copy of view 0 moved 1 m away overlaps nothing, and
    the test is the refinements' own (3 spacings, normals agreeing)."""
    scans, normals, truth = _views()
    pairs = overlapping_pairs(scans, normals, truth, spacing=1.0)
    assert all((k, k + 1) in pairs for k in range(7)) and (0, 7) in pairs
    assert {(0, 2), (1, 3), (2, 4)} <= set(pairs)
    assert all(i < j for i, j in pairs)
    far = np.eye(4)
    far[:3, 3] = [1000.0, 0.0, 0.0]
    pairs = overlapping_pairs(scans[:2] + scans[:1], normals[:2] + normals[:1], truth[:2] + [far @ truth[0]],
                              spacing=1.0)
    assert pairs == [(0, 1)]
    # the same surface with its normals flipped (the other side of a thin wall) is no overlap
    assert overlapping_pairs([scans[0], scans[0]], [normals[0], -normals[0]], [truth[0], truth[0]],
                             spacing=1.0) == []
    with pytest.raises(InputError, match="pose for every view"):
        overlapping_pairs(scans, normals, truth[:3], spacing=1.0)
    with pytest.raises(InputError, match="spacing"):
        overlapping_pairs(scans, normals, truth, spacing=0.0)


def _face(rng, centre, normal, e1, e2, w, h, n=20000):
    a = rng.uniform(-w / 2, w / 2, n)
    b = rng.uniform(-h / 2, h / 2, n)
    P = np.asarray(centre, float) + a[:, None] * np.asarray(e1, float) + b[:, None] * np.asarray(e2, float)
    return P, np.tile(np.asarray(normal, float), (n, 1))


def _block(P, N, c):
    J = np.hstack([np.cross(P - c, N), N])
    H = np.zeros((12, 12))
    H[6:, 6:] = J.T @ J  # view 1's block; view 0 sees nothing
    return H


def test_view_levers_match_the_geometry() -> None:
    """A face of width w facing a turntable axis squarely holds the angle with lever
    w / sqrt(12), at any distance from the axis; a deck (normals along the axis) as
    large again halves the information per weight; a side wall (normal across the
    axis) holds it by its points' distances from the axis along the wall; free
    poses report the weakest rotation (a lone face can spin about its normal: 0)."""
    rng = np.random.default_rng(3)
    w, u, a = 35.0, np.array([0.0, 0.0, 1.0]), np.zeros(3)
    face, fn = _face(rng, [-125.0, 0.0, 20.0], [-1, 0, 0], [0, 1, 0], [0, 0, 1], w, 30.0)
    deck, dn = _face(rng, [-60.0, 0.0, 35.0], [0, 0, 1], [1, 0, 0], [0, 1, 0], 130.0, w)
    side, sn = _face(rng, [-62.5, w / 2, 20.0], [0, 1, 0], [1, 0, 0], [0, 0, 1], 125.0, 30.0)
    c = np.array([-40.0, 5.0, 10.0])  # the refinement's centroid: anywhere

    def lever(P, N, free=False):
        twist = None if free else np.r_[u, np.cross(u, c - a)]
        lv = _view_levers(_block(P, N, c), 2, twist)
        assert lv[0] == 0.0
        return lv[1]

    assert lever(face, fn) == pytest.approx(w / np.sqrt(12), rel=0.02)
    assert lever(np.vstack([face, deck]), np.vstack([fn, dn])) == pytest.approx(w / np.sqrt(24), rel=0.02)
    assert lever(side, sn) == pytest.approx(np.sqrt(np.mean(side[:, 0] ** 2)), rel=0.02)
    assert lever(face, fn, free=True) == pytest.approx(0.0, abs=1e-6)
    top, tn = _face(rng, [0.0, 0.0, 15.0], [0, 0, 1], [1, 0, 0], [0, 1, 0], 30.0, 30.0)
    front, frn = _face(rng, [0.0, -15.0, 0.0], [0, -1, 0], [1, 0, 0], [0, 0, 1], 30.0, 30.0)
    right, rn = _face(rng, [15.0, 0.0, 0.0], [1, 0, 0], [0, 1, 0], [0, 0, 1], 30.0, 30.0)
    assert 3.0 < lever(np.vstack([top, front, right]), np.vstack([tn, frn, rn]), free=True) < 30.0


def test_refinements_report_levers() -> None:
    """On the tank's 8 views the end-on views (2 and 6: front and back plates, the
    hull's width) hold their angle about the axis least firmly, the side views most."""
    scans, normals, truth = _views()
    pairs = [(k, (k + 1) % 8) for k in range(8)] + [(k, (k + 2) % 8) for k in range(8)]
    _, info = refine_turntable(scans, normals, truth, pairs, spacing=1.0)
    lev = np.asarray(info["levers"])
    assert lev.shape == (8,) and np.all(lev > 0)
    assert set(np.argsort(lev)[:2]) == {2, 6}, lev
    assert lev[[2, 6]].max() < 0.6 * np.median(lev)
    _, info = refine_multiview(scans, normals, truth, pairs, spacing=1.0)
    assert len(info["levers"]) == 8 and min(info["levers"]) > 0
