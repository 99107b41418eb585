"""Pairwise registration: Kabsch, turntable projection, FPFH+RANSAC, ICP; real data."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.reconstruct.scan.registration import (
    global_register,
    point_spacing,
    refine_icp,
    register_pair,
    rigid_fit,
    turntable_motion,
)

from prism3d.errors import InputError
from prism3d.geometry import rotation_angle_deg

BUNNY_REF = np.array(
    [
        [0.8806, 0.0365, -0.4724, 0.03453],
        [-0.02354, 0.9992, 0.03326, -0.001519],
        [0.4732, -0.01817, 0.8808, 0.04116],
        [0, 0, 0, 1],
    ]
)


def _rot(axis, deg):
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(deg)
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _pose(axis, deg, t):
    T = np.eye(4)
    T[:3, :3] = _rot(axis, deg)
    T[:3, 3] = t
    return T


def _apply(T, p):
    return p @ T[:3, :3].T + T[:3, 3]


def _surface(n=6000, seed=0):
    """A bumpy closed-ish surface patch with enough structure for features (mm)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-60, 60, n)
    v = rng.uniform(-40, 40, n)
    z = 15 * np.sin(u / 15) * np.cos(v / 12) + 8 * np.exp(-((u - 20) ** 2 + v**2) / 200) + 300
    return np.stack([u, v, z], axis=1)


def test_rigid_fit_known_answer_and_no_reflection():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(50, 3))
    T = _pose([1, 2, 3], 37, [5, -2, 1])
    np.testing.assert_allclose(rigid_fit(a, _apply(T, a)), T, atol=1e-10)
    # A mirrored target must still give a proper rotation.
    R = rigid_fit(a, a * [-1, 1, 1])
    assert np.linalg.det(R[:3, :3]) == pytest.approx(1.0)


def test_point_spacing_adapts_to_units():
    g = np.stack(np.meshgrid(np.arange(30.0), np.arange(30.0)), -1).reshape(-1, 2)
    p = np.c_[g, np.zeros(len(g))]
    assert point_spacing(p) == pytest.approx(1.0)
    assert point_spacing(p / 1000) == pytest.approx(1e-3)
    with pytest.raises(InputError, match="coincide"):
        point_spacing(np.zeros((5, 3)))
    with pytest.raises(InputError, match="at least 2"):
        point_spacing(np.zeros((1, 3)))


def test_turntable_motion_projects_onto_exact_step():
    c = np.array([10.0, -5.0, 1200.0])
    R = _rot([0.1, -1, 0.2], 45.3)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (np.eye(3) - R) @ c + 0.2 * np.array([0.1, -1, 0.2])  # small screw part
    A = turntable_motion(T, 45.0)
    assert rotation_angle_deg(A) == pytest.approx(45.0)
    # The projected motion keeps the axis point fixed.
    np.testing.assert_allclose(_apply(A, c[None])[0], c, atol=1.0)
    assert turntable_motion(T, 20.0) is None


def test_global_then_icp_recovers_pose_and_is_deterministic():
    src = _surface()
    T_true = _pose([0.3, 1, 0.2], 25, [8, -3, 12])
    dst = _apply(T_true, _surface(seed=1))
    T1, _, _ = global_register(src, dst, seed=3)
    T2, _, _ = global_register(src, dst, seed=3)
    np.testing.assert_array_equal(T1, T2)
    assert rotation_angle_deg(np.linalg.inv(T_true) @ T1) < 5
    r = refine_icp(src, dst, T1)
    assert rotation_angle_deg(np.linalg.inv(T_true) @ r.T_target_source) < 0.1
    np.testing.assert_allclose(r.T_target_source[:3, 3], T_true[:3, 3], atol=0.5)
    assert np.linalg.det(r.T_target_source[:3, :3]) == pytest.approx(1.0)
    assert r.fitness > 0.9 and r.information.shape == (6, 6)


def test_errors():
    p = _surface(200)
    with pytest.raises(InputError, match="expected shape"):
        refine_icp(p[:, :2], p, np.eye(4))
    with pytest.raises(InputError, match="non-finite"):
        register_pair(np.vstack([p, [[np.nan, 0, 0]]]), p)
    with pytest.raises(InputError, match="at least 10 points"):
        global_register(p[:5], p)
    with pytest.raises(InputError, match="T_init"):
        refine_icp(p, p, np.eye(3))
    with pytest.raises(InputError, match="method"):
        refine_icp(p, p, np.eye(4), method="magic")
    with pytest.raises(InputError, match="lengths differ"):
        refine_icp(p, p, np.eye(4), scales=(2.0, 1.0), max_iterations=(10,))


@pytest.mark.realdata
def test_bunny_bun0_to_bun4_matches_pcl_reference(shared_data):
    """bun0 -> bun4 (metres, ~400 points each) without a start guess.

    PCL's reference is classic point-to-point ICP (max distance 0.05 m, i.e. every
    point of bun0 takes part, overlap or not). From our global registration that
    estimator reproduces it; our default robust point-to-plane ICP (only the
    overlap, Tukey-weighted) converges ~6.5 deg away, where Open3D's generalized
    ICP -- an independent estimator -- also lands: on these sparse partial scans the
    two objectives have different minima, so the default is checked against both.
    """
    o3d = pytest.importorskip("open3d")
    from prism3d.io.pcd import read_pcd

    a = read_pcd(shared_data / "pointclouds/pcl/bun0.pcd").points
    b = read_pcd(shared_data / "pointclouds/pcl/bun4.pcd").points
    T_glob, _, _ = global_register(a, b, seed=0)  # no start guess
    assert rotation_angle_deg(np.linalg.inv(BUNNY_REF) @ T_glob) < 10
    r = refine_icp(a, b, T_glob, method="point_to_point", spacing=0.025, scales=(1.0,), max_iterations=(50,))
    err_deg = rotation_angle_deg(np.linalg.inv(BUNNY_REF) @ r.T_target_source)
    err_mm = 1000 * np.linalg.norm(r.T_target_source[:3, 3] - BUNNY_REF[:3, 3])
    assert err_deg < 1.0 and err_mm < 2.0, (err_deg, err_mm)
    # The default pipeline (global + robust multi-scale point-to-plane ICP).
    d = register_pair(a, b)
    reg = o3d.pipelines.registration
    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a))
    pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b))
    for pc in (pa, pb):
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.02, max_nn=30))
    g = reg.registration_generalized_icp(pa, pb, 0.012, BUNNY_REF, reg.TransformationEstimationForGeneralizedICP(),
                                         reg.ICPConvergenceCriteria(1e-9, 1e-9, 100))
    T_g = np.asarray(g.transformation)
    assert rotation_angle_deg(np.linalg.inv(T_g) @ d.T_target_source) < 1.0
    assert 1000 * np.linalg.norm(d.T_target_source[:3, 3] - T_g[:3, 3]) < 2.0
    assert rotation_angle_deg(np.linalg.inv(BUNNY_REF) @ d.T_target_source) < 8.0
    # An independent reference: the Stanford repository's own alignment of the
    # full-resolution scans (bun.conf: bun045 -> bun000, quaternion x y z w
    # 0.00548449 -0.294635 -0.0038555 0.955586, a 34.3 deg turn about y). The PCD
    # files are not in the PLY files' frames, so only the rotation is comparable:
    # ours is within 1 deg of it (measured 0.52), PCL's reference is 6 deg short.
    from scipy.spatial.transform import Rotation

    R_stanford = Rotation.from_quat([0.00548449, -0.294635, -0.0038555, 0.955586]).as_matrix()
    assert rotation_angle_deg(R_stanford.T @ d.T_target_source[:3, :3]) < 1.0
    assert rotation_angle_deg(R_stanford.T @ BUNNY_REF[:3, :3]) > 5.0
    # ...and ours explains the data better: more of bun0 lands on bun4
    from scipy.spatial import cKDTree

    tree = cKDTree(b)

    def close_fraction(T):
        return float(np.mean(tree.query(a @ T[:3, :3].T + T[:3, 3])[0] < 0.003))

    assert close_fraction(d.T_target_source) > close_fraction(BUNNY_REF) + 0.1


@pytest.mark.realdata
def test_open3d_fragments_perturbed_poses_recovered(shared_data):
    from prism3d.io.pcd import read_pcd

    a = read_pcd(shared_data / "pointclouds/open3d_fragments/cloud_bin_0_down.pcd")
    b = read_pcd(shared_data / "pointclouds/open3d_fragments/cloud_bin_1_down.pcd")
    for k, T in enumerate([_pose([0, 0, 1], 30, [0.1, -0.2, 0.05]), _pose([1, 1, 0], -50, [0.3, 0.0, -0.1])]):
        moved = _apply(T, b.points)  # truth: T_bmoved_b = T, fragments aligned => T_a_bmoved = inv(T)
        r = register_pair(moved, a.points, seed=k)
        err = np.linalg.inv(np.linalg.inv(T)) @ r.T_target_source
        assert rotation_angle_deg(err) < 1.0
        spacing = point_spacing(a.points)  # ~3 cm: a sparse, real RGB-D fragment
        assert np.linalg.norm((r.T_target_source @ T)[:3, 3]) < 0.5 * spacing
