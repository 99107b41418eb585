"""Multi-view stitching: 8 turntable views of the built-in tank, with and without a
turntable hint; files, determinism of outputs, failure detection, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from prism3d.errors import InputError, ReconstructionError
from prism3d.reconstruct.registration import rotation_angle_deg
from prism3d.reconstruct.stitch import stitch_scans, stitch_to_files


def _rz(deg):
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


@pytest.fixture(scope="module")
def tank_views():
    """8 views at 45 deg of tank_t1 (raycast, ~1 mm spacing, 0.1 mm noise along the
    ray, 10 % dropouts): scans in each left-camera frame + true T_world_cam."""
    o3d = pytest.importorskip("open3d")
    from prism3d.capture.rig import look_at
    from prism3d.datasets.targets import builtin_target

    tank = builtin_target("tank_t1")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.t.geometry.TriangleMesh(
            o3d.core.Tensor(tank.vertices.astype(np.float32)), o3d.core.Tensor(tank.faces.astype(np.int32))
        )
    )
    W, H, f = 360, 270, 1300.0
    u, v = np.meshgrid(np.arange(W) - (W - 1) / 2, np.arange(H) - (H - 1) / 2)
    rays_cam = np.stack([u / f, v / f, np.ones_like(u)], -1).reshape(-1, 3)
    rays_cam /= np.linalg.norm(rays_cam, axis=1, keepdims=True)
    T0 = look_at([0.0, -1200.0, 380.0], [0.0, 0.0, 20.0], up=[0.0, 0.0, 1.0])
    rng = np.random.default_rng(7)
    scans, poses = [], []
    for k in range(8):
        T = _rz(45.0 * k) @ T0
        d_world = rays_cam @ T[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T[:3, 3], d_world.shape), d_world], 1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        ok = np.isfinite(hit) & (rng.random(len(hit)) > 0.1)
        t = hit[ok] + rng.normal(0, 0.1, ok.sum())
        pts = rays_cam[ok] * t[:, None]
        col = np.tile(np.array([[90, 110, 60]], np.uint8), (len(pts), 1))
        scans.append((pts, col, None))
        poses.append(T)
    return scans, poses, tank


def _check(res, poses, tank, max_deg, max_rms_mm, max_fused_rms_mm):
    import open3d as o3d

    T0_inv = np.linalg.inv(poses[0])
    for k, T in enumerate(res.T_model_scan):
        true = T0_inv @ poses[k]
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        assert rotation_angle_deg(np.linalg.inv(true) @ T) < max_deg, k
        Vk = tank.vertices @ np.linalg.inv(poses[k])[:3, :3].T + np.linalg.inv(poses[k])[:3, 3]
        diff = (Vk @ T[:3, :3].T + T[:3, 3]) - (Vk @ true[:3, :3].T + true[:3, 3])
        assert np.sqrt(np.mean(np.sum(diff**2, 1))) < max_rms_mm, k
    V0 = tank.vertices @ T0_inv[:3, :3].T + T0_inv[:3, 3]
    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.t.geometry.TriangleMesh(o3d.core.Tensor(V0.astype(np.float32)),
                                                 o3d.core.Tensor(tank.faces.astype(np.int32))))
    d = sc.compute_distance(o3d.core.Tensor(res.points.astype(np.float32))).numpy()
    assert np.sqrt(np.mean(d**2)) < max_fused_rms_mm


def test_eight_views_with_turntable_hint(tank_views, tmp_path):
    scans, poses, tank = tank_views
    calls = []
    res = stitch_scans(scans, turntable_step_deg=45.0, mesh=True, progress=lambda d, t, s: calls.append(d))
    _check(res, poses, tank, max_deg=0.1, max_rms_mm=0.5, max_fused_rms_mm=0.4)
    assert res.mesh_faces is not None and len(res.mesh_faces) > 1000
    assert res.colors is not None and res.mesh_colors is not None
    kinds = {(e["target"], e["source"]): e["kind"] for e in res.diagnostics["edges"]}
    assert kinds[(0, 7)] == "loop"  # 360 deg loop closure found
    assert calls and calls[-1] == max(calls)


@pytest.mark.slow
def test_eight_views_without_hint(tank_views):
    scans, poses, tank = tank_views
    res = stitch_scans(scans, mesh=False)
    _check(res, poses, tank, max_deg=0.1, max_rms_mm=0.5, max_fused_rms_mm=0.4)
    assert res.mesh_vertices is None


def test_stitch_to_files_writes_model_mesh_and_poses(tank_views, tmp_path):
    from prism3d.io.ply import read_ply, write_ply

    scans, _, _ = tank_views
    paths = []
    for k in (0, 1, 2):
        p = tmp_path / f"scan_{k}.ply"
        write_ply(p, scans[k][0], colors=scans[k][1])
        paths.append(p)
    res = stitch_to_files(paths, tmp_path / "out" / "model.ply", mesh_out=tmp_path / "out" / "mesh.ply",
                          turntable_step_deg=45.0)
    model = read_ply(tmp_path / "out" / "model.ply")
    mesh = read_ply(tmp_path / "out" / "mesh.ply")
    assert len(model.points) == len(res.points) and mesh.faces is not None
    doc = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert doc["schema_version"] == 1 and [s["path"] for s in doc["scans"]] == [str(p) for p in paths]
    np.testing.assert_allclose(np.array(doc["scans"][2]["T_model_scan"]), res.T_model_scan[2])
    # Nothing written on error.
    with pytest.raises(InputError, match="missing.ply"):
        stitch_to_files([paths[0], tmp_path / "missing.ply"], tmp_path / "o2" / "model.ply")
    assert not (tmp_path / "o2").exists() or not any((tmp_path / "o2").iterdir())


def test_non_overlapping_scans_raise_naming_views(tank_views):
    scans, _, _ = tank_views
    far = (scans[4][0] + [5000.0, 0, 0], None, None)  # a different place entirely
    with pytest.raises(ReconstructionError, match="scan 0 and scan 1"):
        stitch_scans([scans[0], far], mesh=False)


def test_bad_input():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(100, 3))
    with pytest.raises(InputError, match="at least 2 scans"):
        stitch_scans([(p, None, None)])
    with pytest.raises(InputError, match="scan 1: expected at least 30"):
        stitch_scans([(p, None, None), (p[:5], None, None)])
    with pytest.raises(InputError, match="unknown point-cloud format"):
        stitch_scans(["a.xyz", "b.xyz"])
    with pytest.raises(InputError, match="on_failure"):
        stitch_scans([(p, None, None), (p, None, None)], on_failure="ignore")
    with pytest.raises(InputError, match="turntable_step_deg"):
        stitch_scans([(p, None, None), (p, None, None)], turntable_step_deg=200)
