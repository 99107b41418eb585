"""Multi-view stitching: 8 turntable views of the built-in tank, with and without a
turntable hint, against the issue's targets (0.05 deg, 0.1 mm RMS surface motion,
0.3 mm fused RMS); files, failure detection, bad input. The slow tests use the
scene simulator's full-resolution views."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from prism3d.errors import InputError, ReconstructionError
from prism3d.geometry import rotation_angle_deg
from prism3d.reconstruct.scan.stitch import StitchOptions, stitch_scans, stitch_to_files
from prism3d.reconstruct.scan.stitch_options import STITCH_MIN_CONFIDENCE


def _rz(deg):
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


def _raycast_views(W=720, H=540, f=3000.0, views=8, step_deg=45.0, noise_mm=0.15, dropout=0.1, seed=7,
                   target="tank_t1", max_incidence_deg=90.0):
    """Views of a built-in target (default tank_t1) on a turntable (raycast, ~0.4 mm spacing, Gaussian noise
    along the ray, random dropouts, no surface seen at more than ``max_incidence_deg`` from its normal):
    scans in each camera frame + true T_world_cam."""
    o3d = pytest.importorskip("open3d")
    from prism3d.capture.rig import look_at
    from prism3d.datasets.models.targets import builtin_target

    tank = builtin_target(target)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.t.geometry.TriangleMesh(
            o3d.core.Tensor(tank.vertices.astype(np.float32)), o3d.core.Tensor(tank.faces.astype(np.int32))
        )
    )
    u, v = np.meshgrid(np.arange(W) - (W - 1) / 2, np.arange(H) - (H - 1) / 2)
    rays_cam = np.stack([u / f, v / f, np.ones_like(u)], -1).reshape(-1, 3)
    rays_cam /= np.linalg.norm(rays_cam, axis=1, keepdims=True)
    T0 = look_at([0.0, -1200.0, 380.0], [0.0, 0.0, 20.0], up=[0.0, 0.0, 1.0])
    rng = np.random.default_rng(seed)
    scans, poses = [], []
    for k in range(views):
        T = _rz(step_deg * k) @ T0
        d_world = rays_cam @ T[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T[:3, 3], d_world.shape), d_world], 1).astype(np.float32)
        cast = scene.cast_rays(o3d.core.Tensor(rays))
        hit = cast["t_hit"].numpy()
        ok = np.isfinite(hit) & (rng.random(len(hit)) > dropout)
        if max_incidence_deg < 90.0:
            cos_inc = np.abs(np.sum(cast["primitive_normals"].numpy() * d_world, axis=1))
            ok &= cos_inc > np.cos(np.radians(max_incidence_deg))
        t = hit[ok] + rng.normal(0, noise_mm, ok.sum())
        pts = rays_cam[ok] * t[:, None]
        col = np.tile(np.array([[90, 110, 60]], np.uint8), (len(pts), 1))
        scans.append((pts, col, None))
        poses.append(T)
    return scans, poses, tank.vertices, tank.faces


@pytest.fixture(scope="module")
def tank_views():
    return _raycast_views()


def _rotation_errors(res, poses):
    """Per view: rotation error (deg) of the recovered pose against the truth."""
    T0_inv = np.linalg.inv(poses[0])
    return [rotation_angle_deg(np.linalg.inv(T0_inv @ P) @ T) for P, T in zip(poses, res.T_model_scan, strict=True)]


def _pose_errors(res, poses, V):
    """Per view: rotation error (deg) and RMS motion (mm) of the true surface."""
    T0_inv = np.linalg.inv(poses[0])
    out = []
    for k, T in enumerate(res.T_model_scan):
        true = T0_inv @ poses[k]
        assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
        Vk = V @ np.linalg.inv(poses[k])[:3, :3].T + np.linalg.inv(poses[k])[:3, 3]
        diff = (Vk @ T[:3, :3].T + T[:3, 3]) - (Vk @ true[:3, :3].T + true[:3, 3])
        out.append((rotation_angle_deg(np.linalg.inv(true) @ T), float(np.sqrt(np.mean(np.sum(diff**2, 1))))))
    return out


def _fused_rms(res, poses, V, F):
    import open3d as o3d

    T0_inv = np.linalg.inv(poses[0])
    V0 = V @ T0_inv[:3, :3].T + T0_inv[:3, 3]
    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.t.geometry.TriangleMesh(o3d.core.Tensor(V0.astype(np.float32)),
                                                 o3d.core.Tensor(F.astype(np.int32))))
    d = sc.compute_distance(o3d.core.Tensor(res.points.astype(np.float32))).numpy()
    return float(np.sqrt(np.mean(d**2)))


def _check(res, poses, V, F):
    """The issue's targets: every view within 0.05 deg, the true surface moved by at
    most 0.1 mm RMS, the fused cloud within 0.3 mm RMS of the true mesh."""
    errs = _pose_errors(res, poses, V)
    assert max(a for a, _ in errs) <= 0.05, errs
    assert max(b for _, b in errs) <= 0.1, errs
    assert _fused_rms(res, poses, V, F) <= 0.3


def _check_pairs(res, scans, poses, max_points):
    """Every registered pair is reported; at the recovered poses each fits as well as at
    the true poses (the known answer, measured the same way on the same registration
    copies); its residual off the surface is the scans' own noise."""
    from prism3d.reconstruct.scan.registration import ScanPyramid, evaluate_pyramids
    from prism3d.reconstruct.scan.stitch import _PAIR_SAMPLE, _registration_copy

    pairs = res.diagnostics["pairs"]
    n = len(scans)
    assert [(p["i"], p["j"]) for p in pairs if p["kind"] == "odometry"] == [(k, k + 1) for k in range(n - 1)]
    assert {(p["i"], p["j"]) for p in pairs} == {(e["target"], e["source"]) for e in res.diagnostics["edges"]}
    spacing, rsp = res.diagnostics["spacing"], res.diagnostics["registration_voxel"]
    pyr = [ScanPyramid(_registration_copy(s[0], spacing, max_points)[0], rsp) for s in scans]
    for p in pairs:
        i, j = p["i"], p["j"]
        assert p["max_correspondence_distance"] == pytest.approx(2.0 * rsp)
        assert 0 < p["fitness"] <= 1 and 0 < p["final_fitness"] <= 1
        assert p["check"] == [], p
        truth = evaluate_pyramids(pyr[j], pyr[i], np.linalg.inv(poses[i]) @ poses[j],
                                  max_distance=2.0 * rsp, sample=_PAIR_SAMPLE)
        got = (p["final_fitness"], p["final_inlier_rmse"], p["final_plane_sigma"])
        np.testing.assert_allclose(got, truth, rtol=0.03, atol=0.002, err_msg=str(p))
        assert 0.7 < p["final_plane_sigma"] / p["noise_sigma"] < 1.3, p
    return pairs


def test_eight_views_with_turntable_hint(tank_views):
    from prism3d.reconstruct.scan.fusion import mesh_is_closed

    scans, poses, V, F = tank_views
    calls = []
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, mesh=True, mesh_depth=7,
                                            max_registration_points=20000), progress=lambda d, t, s: calls.append(d))
    _check(res, poses, V, F)
    assert res.mesh_faces is not None and len(res.mesh_faces) > 1000
    assert mesh_is_closed(res.mesh_faces) and res.diagnostics["mesh_closed"]
    assert res.colors is not None and res.mesh_colors is not None
    kinds = {(e["target"], e["source"]): e["kind"] for e in res.diagnostics["edges"]}
    assert kinds[(0, 7)] == "loop"  # 360 deg loop closure found
    assert calls and calls[-1] == max(calls)
    # Every pair's fit, pairwise and in the model. Measured: overlap 0.53-0.94 (odometry)
    # and 0.37-0.82 (loops), inlier RMSE 0.38-0.61 mm (the sampling: 0.67 mm registration
    # voxel), off the surface 0.081-0.112 mm, 0.83-1.06x the scans' own noise (0.15 mm along
    # the rays, voxel-averaged), unchanged by the global refinement to within 0.01 mm.
    pairs = _check_pairs(res, scans, poses, 20000)
    assert len(pairs) == 16
    for p in pairs:
        assert p["final_plane_sigma"] < np.sqrt(2) * 0.15  # two raw scans' noise, unaveraged
        assert abs(p["final_fitness"] - p["fitness"]) < 0.01


def test_the_step_motion_is_found_past_pairs_that_match_a_mirror_image(tank_views, monkeypatch):
    """A symmetric body can match its own mirror image in the first pairs (car_suv, seed 0:
    pairs 0-3 turned 173, 33 and 62 deg): the step motion comes from the first pair that
    turns by the step, however late, and the stitch is as right as without the bad pairs."""
    from prism3d.reconstruct.scan import stitch as st

    scans, poses, V, F = tank_views
    real, bad = st._global_pair, []

    def mirrored_first(prep, opts, i, j):
        r = real(prep, opts, i, j)
        if i < 4:  # as if the first four pairs matched a mirror image: no turn by the step
            bad.append(i)
            return replace(r, T_target_source=np.eye(4))
        return r

    monkeypatch.setattr(st, "_global_pair", mirrored_first)
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, mesh=False, max_registration_points=20000))
    assert bad[:4] == [0, 1, 2, 3]
    _check(res, poses, V, F)
    assert any("turntable motion came from scan 4-scan 5" in w for w in res.diagnostics["warnings"]), \
        res.diagnostics["warnings"]


@pytest.mark.slow  # make test-all: a variant of a fast test's behaviour (suite time)
def test_eight_views_in_metres_without_hint(tank_views):
    """The same scans in metres: every scale (voxels, ICP distances, thresholds)
    follows the point spacing, so the targets hold at 1/1000 of the size."""
    scans, poses, V, F = tank_views
    metres = [(p / 1000.0, c, n) for p, c, n in scans]
    res = stitch_scans(metres, StitchOptions(mesh=False, max_registration_points=20000))
    poses_m = []
    for T in poses:
        T = T.copy()
        T[:3, 3] /= 1000.0
        poses_m.append(T)
    errs = _pose_errors(res, poses_m, V / 1000.0)
    assert max(a for a, _ in errs) <= 0.05, errs
    assert max(b for _, b in errs) <= 0.1e-3, errs
    assert _fused_rms(res, poses_m, V / 1000.0, F) <= 0.3e-3
    assert res.diagnostics["warnings"] == []


def _rig_set():
    """8 views at 45 deg of tank_t1 rendered once by the scene simulator (slow;
    cached in $PRISM3D_STITCH_SET or /tmp/prism3d_stitch_tank8)."""
    import os
    from pathlib import Path

    folder = Path(os.environ.get("PRISM3D_STITCH_SET", "/tmp/prism3d_stitch_tank8"))
    if not (folder / "poses.json").exists():
        from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
        from prism3d.datasets.models.targets import builtin_target

        simulate_to_folder("scene", folder, SimulateOptions(views=8, seed=1, supersample=1), target=builtin_target("tank_t1"))
    return folder


def _truth_scans(folder, stride=1, noise_mm=0.15, dropout=0.1, seed=0):
    """Scans back-projected from the simulator's true left depth (every pixel, as a
    reconstruction gives), with noise along the ray and dropouts."""
    from prism3d.capture.rig import StereoRig
    from prism3d.io.ply import read_ply

    rig = StereoRig.load(folder / "rig.yaml")
    rays = rig.left.pixel_grid_rays()[::stride, ::stride]
    views = json.loads((folder / "poses.json").read_text())["views"]
    rng = np.random.default_rng(seed)
    scans, poses = [], []
    for v in views:
        t = np.load(folder / v["truth"], allow_pickle=False)
        z = t["depth_left_mm"][::stride, ::stride]
        m = np.isfinite(z)
        r = rays[m]
        p = r / r[:, 2:3] * z[m][:, None] + r * rng.normal(0, noise_mm, m.sum())[:, None]
        col = (np.clip(t["albedo_left"][::stride, ::stride][m], 0, 1) * 255).astype(np.uint8)
        keep = rng.random(len(p)) >= dropout
        scans.append((p[keep], col[keep], None))
        poses.append(np.array(v["T_world_cam"]))
    target = read_ply(folder / "target.ply")
    return scans, poses, target.points, target.faces


@pytest.mark.slow
@pytest.mark.parametrize("hint", [45.0, None])
def test_virtual_rig_eight_views_full_density(hint):
    folder = _rig_set()
    scans, poses, V, F = _truth_scans(folder)
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=hint, mesh=False))
    _check(res, poses, V, F)


@pytest.mark.slow
@pytest.mark.parametrize("hint", [45.0, None])
def test_ship_stereo_coverage_with_true_depth(tmp_path, hint):
    """ship_s3's end-on view stitches 0.23 deg off from stereo scans rendered with 1 ray
    per pixel (README, "Known gap"). Keep the stereo scans' pixels -- the coverage the matcher gives,
    a third of the end-on view missing -- but give each the true depth plus 0.1 mm
    noise along the ray: the issue's targets hold (measured 0.018 deg, 0.023 mm
    surface motion), so the stitching copes with that coverage and the gap is the
    stereo depth."""
    from prism3d.capture.rig import StereoRig
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
    from prism3d.datasets.models.targets import builtin_target
    from prism3d.io.images import read_image
    from prism3d.io.ply import read_ply
    from prism3d.reconstruct.stereo.pipeline import ReconstructOptions, reconstruct_shot

    folder = tmp_path / "ship"
    # the ideal camera, as when the gap was measured: with the real-camera effects the
    # matcher keeps more of the end-on view (its lever ratio 0.27, not weakly held)
    simulate_to_folder("scene", folder, SimulateOptions(views=8, seed=0, supersample=1, effects=None),
                       target=builtin_target("ship_s3", seed=0))
    rig = StereoRig.load(folder / "rig.yaml")
    views = json.loads((folder / "poses.json").read_text())["views"]
    rng = np.random.default_rng(0)
    scans, poses = [], []
    for v in views:
        scan = reconstruct_shot(read_image(folder / v["image"]), rig, ReconstructOptions(min_confidence=STITCH_MIN_CONFIDENCE)).scan
        t = np.load(folder / v["truth"], allow_pickle=False)
        z_true = t["depth_rect_mm"][scan.pixels[:, 0], scan.pixels[:, 1]].astype(np.float64)
        ok = np.isfinite(z_true)
        q = scan.points[ok].astype(np.float64) @ t["R1"].T  # rectified-left frame
        q *= (z_true[ok] / q[:, 2])[:, None]
        q += q / np.linalg.norm(q, axis=1, keepdims=True) * rng.normal(0, 0.1, ok.sum())[:, None]
        scans.append((q @ t["R1"], None, None))
        poses.append(np.array(v["T_world_cam"]))
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=hint, mesh=False))
    target = read_ply(folder / "target.ply")
    _check(res, poses, target.points, target.faces)
    # with the stereo scans' coverage the end-on view is held by its transom alone
    # and is named as weakly held; with true depth its pose is right all the same
    assert _lever_warnings(res) == ["scan 6"], res.diagnostics["warnings"]
    assert len(res.diagnostics["warnings"]) == 1, res.diagnostics["warnings"]


@pytest.mark.slow
def test_ship_stereo_scans_stitch_within_the_targets(tmp_path):
    """The whole chain on a target that failed before the refinement got B-spline
    views: ship_s2 simulated (1 ray per pixel), every view reconstructed with the
    defaults, stitched with and without the hint. Measured 0.026 deg, 0.062 mm surface
    motion, 0.161 mm fused (on bilinear views 0.109 deg, 0.170 mm)."""
    from prism3d.capture.rig import StereoRig
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
    from prism3d.datasets.models.targets import builtin_target
    from prism3d.io.images import read_image
    from prism3d.io.ply import read_ply
    from prism3d.reconstruct.stereo.pipeline import ReconstructOptions, reconstruct_shot

    folder = tmp_path / "ship"
    simulate_to_folder("scene", folder, SimulateOptions(views=8, seed=0, supersample=1), target=builtin_target("ship_s2", seed=0))
    rig = StereoRig.load(folder / "rig.yaml")
    views = json.loads((folder / "poses.json").read_text())["views"]
    scans = [reconstruct_shot(read_image(folder / v["image"]), rig, ReconstructOptions(min_confidence=STITCH_MIN_CONFIDENCE)).scan
             for v in views]
    poses = [np.array(v["T_world_cam"]) for v in views]
    target = read_ply(folder / "target.ply")
    for hint in (45.0, None):
        res = stitch_scans([(s.points, s.colors, s.normals) for s in scans],
                           StitchOptions(turntable_step_deg=hint, mesh=False))
        _check(res, poses, target.points, target.faces)
        assert res.diagnostics["warnings"] == []


def test_stitch_to_files_writes_model_mesh_and_poses(tank_views, tmp_path):
    from prism3d.io.ply import read_ply, write_ply

    scans = tank_views[0]
    paths = []
    for k in (0, 1, 2):
        p = tmp_path / f"scan_{k}.ply"
        write_ply(p, scans[k][0], colors=scans[k][1])
        paths.append(p)
    res = stitch_to_files(paths, tmp_path / "out" / "model.ply",
                          StitchOptions(turntable_step_deg=45.0, mesh_depth=6, max_registration_points=8000),
                          mesh_out=tmp_path / "out" / "mesh.ply")
    model = read_ply(tmp_path / "out" / "model.ply")
    mesh = read_ply(tmp_path / "out" / "mesh.ply")
    assert len(model.points) == len(res.points) and mesh.faces is not None
    doc = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert doc["schema_version"] == 1 and [s["path"] for s in doc["scans"]] == [str(p) for p in paths]
    np.testing.assert_allclose(np.array(doc["scans"][2]["T_model_scan"]), res.T_model_scan[2])
    # every registered pair's fit, as in the diagnostics
    assert doc["pairs"] == res.diagnostics["pairs"]
    assert [(p["i"], p["j"]) for p in doc["pairs"]][:2] == [(0, 1), (1, 2)]
    assert set(doc["pairs"][0]) == {
        "i", "j", "kind", "kept", "max_correspondence_distance", "fitness", "inlier_rmse", "plane_sigma",
        "final_fitness", "final_inlier_rmse", "final_plane_sigma", "noise_sigma", "check"}
    # A second writer of the same model (another stitch still running) is refused up front
    # and changes nothing; the lock goes with the first.
    from prism3d.io.atomic import output_lock

    before = (tmp_path / "out" / "model.ply").read_bytes()
    with output_lock(tmp_path / "out" / "model.ply"):
        with pytest.raises(InputError, match="another prism3d process"):
            stitch_to_files(paths, tmp_path / "out" / "model.ply", StitchOptions(turntable_step_deg=45.0))
    assert (tmp_path / "out" / "model.ply").read_bytes() == before
    assert sorted(q.name for q in (tmp_path / "out").iterdir()) == ["mesh.ply", "model.ply", "poses.json"]
    # Nothing written on error.
    with pytest.raises(InputError, match="missing.ply"):
        stitch_to_files([paths[0], tmp_path / "missing.ply"], tmp_path / "o2" / "model.ply")
    assert not (tmp_path / "o2").exists() or not any((tmp_path / "o2").iterdir())


def test_pcd_and_ply_inputs_mixed(tank_views, tmp_path):
    """Scans given as PCD (ASCII and binary, written by Open3D) and PLY files, mixed,
    stitch to the same targets, and poses.json maps each input path."""
    import open3d as o3d

    from prism3d.io.ply import write_ply

    scans, poses, V, F = tank_views
    paths = []
    for k, (pts, col, _) in enumerate(scans):
        if k % 3 == 2:
            p = tmp_path / f"scan_{k}.ply"
            write_ply(p, pts, colors=col)
        else:
            p = tmp_path / f"scan_{k}.pcd"
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pc.colors = o3d.utility.Vector3dVector(col / 255.0)
            assert o3d.io.write_point_cloud(str(p), pc, write_ascii=(k % 3 == 0))
        paths.append(p)
    res = stitch_to_files(paths, tmp_path / "out" / "model.ply",
                          StitchOptions(turntable_step_deg=45.0, max_registration_points=20000))
    _check(res, poses, V, F)
    doc = json.loads((tmp_path / "out" / "poses.json").read_text())
    assert [s["path"] for s in doc["scans"]] == [str(p) for p in paths]
    np.testing.assert_allclose(np.array(doc["scans"][4]["T_model_scan"]), res.T_model_scan[4])


def test_cli_bad_input_exits_2_and_writes_nothing(tank_views, tmp_path, capsys):
    """`prism3d stitch`: fewer than 2 scans, a missing, unreadable or empty file and
    two scans that do not overlap each end with one line on stderr and exit 2, and
    leave the output folder empty (no model, no poses.json, no temporary files)."""
    from prism3d.cli import main
    from prism3d.io.ply import write_ply

    scans = tank_views[0]
    good = tmp_path / "a.ply"
    write_ply(good, scans[0][0])
    far = tmp_path / "far.ply"
    write_ply(far, scans[4][0] + [5000.0, 0, 0])
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"this is not a point cloud\n")
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    # two unrelated shapes: RANSAC finds no consistent feature matches at all
    rng = np.random.default_rng(1)
    u = rng.normal(size=(20000, 3))
    sphere = tmp_path / "sphere.ply"
    write_ply(sphere, 50.0 * u / np.linalg.norm(u, axis=1, keepdims=True))
    g = rng.uniform(-50.0, 50.0, size=(20000, 2))
    plane = tmp_path / "plane.ply"
    write_ply(plane, np.c_[g, 0.2 * np.sin(g[:, 0] / 5.0)])
    cases = [
        ([good], "at least 2 scans"),
        ([good, tmp_path / "missing.ply"], "missing.ply"),
        ([good, garbage], "garbage.ply"),
        ([good, empty], "empty.ply"),
        ([good, far], "do not overlap"),
        ([sphere, plane], "plane.ply do not overlap"),
    ]
    for k, (inputs, message) in enumerate(cases):
        out = tmp_path / f"out{k}"
        out.mkdir()
        capsys.readouterr()
        code = main(["stitch", *map(str, inputs), "-o", str(out / "model.ply"), "--mesh", str(out / "mesh.ply")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2, (inputs, err)
        assert len(err) == 1 and message in err[0], err
        assert list(out.iterdir()) == [], list(out.iterdir())


def test_a_wrong_scan_is_marked_in_the_pair_report(tank_views):
    """View 3 of five replaced by the same view of another target (truck_k1) and stitched
    with on_failure="warn": the pairs that hold it are marked. Without a hint, 2-3
    overlaps 0.16 and sits 19x the scans' noise off the surface; 3-4 matched wrongly with
    0.59 overlap, but 10x off the surface (measured). The pairs among the tank's own
    views fit at their noise (0.88-1.3x) and are not marked."""
    scans = list(tank_views[0][:5])
    scans[3] = _raycast_views(target="truck_k1", views=4)[0][3]
    res = stitch_scans(scans, StitchOptions(mesh=False, max_registration_points=8000, on_failure="warn"))
    marks = {(p["i"], p["j"]): p["check"] for p in res.diagnostics["pairs"]}
    assert set(marks) == {(0, 1), (1, 2), (2, 3), (3, 4), (0, 2)}
    assert marks[(0, 1)] == marks[(1, 2)] == marks[(0, 2)] == []
    assert marks[(2, 3)][0].startswith("overlap 0.1") and "off the surface by" in marks[(2, 3)][1]
    (only,) = marks[(3, 4)]
    assert only.startswith("off the surface by") and only.endswith("x the scans' noise")
    assert float(only.split("by ")[1].split("x")[0]) > 5


def test_evaluate_pyramids_reproduces_icp_and_checks_input(tank_views):
    """At the ICP's own result, evaluate_pyramids gives the ICP's fitness and inlier RMSE
    (the known answer: the same correspondences); a seeded subset is reproducible; the
    two scans' residual off the surface matches their noise; bad input is refused."""
    from prism3d.reconstruct.scan.registration import (
        ScanPyramid,
        evaluate_pyramids,
        icp_pyramids,
        point_spacing,
        surface_noise,
    )

    scans, poses = tank_views[0], tank_views[1]
    a, b = scans[0][0][::3], scans[1][0][::3]
    sp = 1.5 * point_spacing(a)
    pa, pb = ScanPyramid(a, sp), ScanPyramid(b, sp)
    r = icp_pyramids(pb, pa, np.linalg.inv(poses[0]) @ poses[1], first_scale=2.0)
    fit, rmse, sigma = evaluate_pyramids(pb, pa, r.T_target_source, max_distance=r.max_distance)
    assert fit == pytest.approx(r.fitness, abs=1e-4) and rmse == pytest.approx(r.inlier_rmse, rel=1e-4)
    assert 0.7 < sigma / np.hypot(surface_noise(pa), surface_noise(pb)) < 1.3
    sub = evaluate_pyramids(pb, pa, r.T_target_source, max_distance=r.max_distance, sample=2000)
    assert sub == evaluate_pyramids(pb, pa, r.T_target_source, max_distance=r.max_distance, sample=2000)
    assert abs(sub[0] - fit) < 0.03
    far = r.T_target_source.copy()
    far[0, 3] += 1e4
    assert evaluate_pyramids(pb, pa, far, max_distance=r.max_distance) == (0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="different scales or spacing"):
        evaluate_pyramids(pb, ScanPyramid(a, 2 * sp), r.T_target_source, max_distance=1.0)
    with pytest.raises(InputError, match="scale: expected one of"):
        evaluate_pyramids(pb, pa, r.T_target_source, max_distance=1.0, scale=3.0)
    with pytest.raises(InputError, match="scale: expected one of"):
        surface_noise(pa, scale=3.0)
    with pytest.raises(InputError, match="max_distance"):
        evaluate_pyramids(pb, pa, r.T_target_source, max_distance=0.0)
    with pytest.raises(InputError, match="sample"):
        evaluate_pyramids(pb, pa, r.T_target_source, max_distance=1.0, sample=0)
    with pytest.raises(InputError, match="T_target_source"):
        evaluate_pyramids(pb, pa, np.eye(3), max_distance=1.0)


def test_cli_prints_each_pair(monkeypatch, capsys, tmp_path):
    """`prism3d stitch` prints one line per registered pair, pairwise -> in the model,
    with the reasons to check it; --quiet prints nothing."""
    import prism3d.reconstruct.scan.stitch as st
    from prism3d.cli import main
    from prism3d.reconstruct.scan.stitch import StitchResult

    def pair(i, j, check, kept=True):
        return {"i": i, "j": j, "kind": "odometry" if j == i + 1 else "loop", "kept": kept,
                "max_correspondence_distance": 1.35, "fitness": 0.88, "inlier_rmse": 0.393,
                "plane_sigma": 0.107, "final_fitness": 0.87, "final_inlier_rmse": 0.394,
                "final_plane_sigma": 0.108, "noise_sigma": 0.109, "check": check}

    pairs = [pair(0, 1, []), pair(1, 2, ["overlap 0.12 < 0.3", "off the surface by 9.2x the scans' noise"]),
             pair(0, 2, [], kept=False)]
    res = StitchResult([np.eye(4)] * 3, np.zeros((1, 3)), None, np.zeros((1, 3), np.float32),
                       diagnostics={"pairs": pairs})
    monkeypatch.setattr(st, "stitch_to_files", lambda *a, **k: res)
    argv = ["stitch", "a.ply", "b.ply", "c.ply", "-o", str(tmp_path / "model.ply")]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2] == ("pair 0-1: overlap 0.88 -> 0.87, inlier RMSE 0.393 -> 0.394 mm (max dist 1.35 mm), "
                        "off the surface 0.107 -> 0.108 mm (noise 0.109 mm)")
    assert lines[3].startswith("pair 1-2: ") and lines[3].endswith(
        "  <- check: overlap 0.12 < 0.3; off the surface by 9.2x the scans' noise")
    assert lines[4].startswith("pair 0-2 (loop, discounted): ") and "<- check" not in lines[4]
    assert len(lines) == 5
    assert main(["--quiet", *argv]) == 0
    assert capsys.readouterr().out == ""


def test_non_overlapping_scans_raise_naming_views(tank_views):
    scans = tank_views[0]
    far = (scans[4][0] + [5000.0, 0, 0], None, None)  # a different place entirely
    with pytest.raises(ReconstructionError, match="scan 0 and scan 1"):
        stitch_scans([scans[0], far], StitchOptions(mesh=False, max_registration_points=8000))


def test_turntable_motion_accepts_small_overlap(tank_views):
    """An odometry edge ICP reached from the known turntable motion may overlap
    little (a thin jet side-on then tail-on: 0.19 on reconstructed scans); the same
    overlap from global registration, where a symmetric object's opposite sides
    match wrongly at ~0.12, still fails. Scan 2 carries 5 far-away copies of itself,
    so only ~1/6 of its points can overlap scan 1."""
    scans, poses = tank_views[0], tank_views[1]
    p2 = scans[2][0]
    padded = np.concatenate([p2] + [p2 + [8000.0 * (i + 1), 0, 0] for i in range(5)])
    three = [scans[0], scans[1], (padded, None, None)]
    for hint in (45.0, None):
        # without a hint the pair 1-2 moves like the well-fitting pair 0-1, which
        # corroborates its small overlap as a known motion would
        res = stitch_scans(three, StitchOptions(turntable_step_deg=hint, mesh=False,
                                                max_registration_points=30000))
        fit = {(e["source"], e["target"]): e["fitness"] for e in res.diagnostics["edges"]}
        assert 0.1 <= fit[(2, 1)] < 0.2, fit
        assert res.diagnostics["warnings"] == []
        err = _rotation_errors(res, poses[:3])
        assert max(err) < 0.05, (hint, err)
    # the pair alone: nothing corroborates the small overlap
    with pytest.raises(ReconstructionError, match="scan 0 and scan 1"):
        stitch_scans(three[1:], StitchOptions(turntable_step_deg=None, mesh=False,
                                              max_registration_points=30000))
    # a pair that moves unlike its neighbour (90 deg after 45 deg, overlap 0.09-0.12)
    # is not corroborated by it
    p3 = scans[3][0]
    uneven = [scans[0], scans[1], (np.concatenate([p3, p3 + [8000.0, 0, 0]]), None, None)]
    with pytest.raises(ReconstructionError, match="scan 1 and scan 2"):
        stitch_scans(uneven, StitchOptions(turntable_step_deg=None, mesh=False,
                                           max_registration_points=30000))


def test_a_pair_nothing_registers_is_placed_by_the_given_step(tank_views):
    """With the turntable step given, a pair that shares too little for ICP from the step
    (fitness < 0.1) or a global match (< 0.2) is placed by the step motion itself, said in
    the warnings and the edge's ``fallback``; the poses stay right (the step is the truth
    here). Without the step the same scans are refused, naming the views."""
    scans, poses = tank_views[0], tank_views[1]
    p2 = scans[2][0]
    padded = np.concatenate([p2] + [p2 + [8000.0 * (i + 1), 0, 0] for i in range(15)])  # 1/16 can overlap
    three = [scans[0], scans[1], (padded, None, None)]
    res = stitch_scans(three, StitchOptions(turntable_step_deg=45.0, mesh=False, max_registration_points=30000))
    edge = {(e["source"], e["target"]): e for e in res.diagnostics["edges"]}
    assert edge[(2, 1)]["fallback"] == "turntable step" and edge[(2, 1)]["fitness"] < 0.1
    assert edge[(1, 0)]["fallback"] is None
    assert any("placed by the given turntable step" in w for w in res.diagnostics["warnings"])
    err = _rotation_errors(res, poses[:3])
    assert max(err[:2]) < 0.05, err  # the registered views: stitching's own bound
    # The placed view is as right as the turntable axis, here from the one registered pair's
    # match: 0.026 deg off the true axis, so a 45 deg step about it lands 0.054 deg off (2 sin
    # 22.5 deg x the axis error) and the view 0.059 deg (measured on two machines: 0.059,
    # and under 0.05 on another). Bound: twice the registered views' 0.05.
    assert err[2] < 0.1, err
    with pytest.raises(ReconstructionError, match="scan 1 and scan 2"):
        stitch_scans(three, StitchOptions(turntable_step_deg=None, mesh=False, max_registration_points=30000))


def test_turntable_constraint_auto_and_rejected(tank_views):
    """Without a hint the poses are recognised as one turntable's and constrained to
    it (poses, surface and fused cloud within stitching's bounds); when the object is
    tilted 2 deg between shots 3 and 4, the hinted run finds the views off one axis, says
    so, and keeps the free poses (which are right)."""
    scans, poses, V, F = tank_views
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=None, mesh=False, max_registration_points=20000))
    assert "turntable" in res.diagnostics["multiview"]
    _check(res, poses, V, F)
    assert res.mesh_vertices is None and res.diagnostics["turntable_motion"] is None
    # object tilted about a horizontal axis through it: views 4-7 see M x
    M = np.eye(4)
    a = np.radians(2.0)
    M[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
    M[:3, 3] = np.array([0, 0, 20.0]) - M[:3, :3] @ np.array([0, 0, 20.0])
    moved, truth = [], []
    for k, (s, T) in enumerate(zip(scans, poses, strict=True)):
        if k < 4:
            moved.append(s)
            truth.append(T)
            continue
        S = np.linalg.inv(T) @ M @ T
        moved.append((s[0] @ S[:3, :3].T + S[:3, 3], s[1], s[2]))
        truth.append(np.linalg.inv(M) @ T)
    res = stitch_scans(moved, StitchOptions(turntable_step_deg=45.0, mesh=False, on_failure="warn"))
    assert any("turntable axis" in w for w in res.diagnostics["warnings"]), res.diagnostics["warnings"]
    assert "turntable" not in res.diagnostics["multiview"]
    assert max(e for e, _ in _pose_errors(res, truth, V)) < 0.05


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
        StitchOptions(on_failure="ignore")
    with pytest.raises(InputError, match="turntable_step_deg"):
        StitchOptions(turntable_step_deg=200)



@pytest.mark.parametrize("field, value, message", [
    ("on_failure", "ignore", "on_failure"),
    ("turntable_constraint", "always", "turntable_constraint"),
    ("max_turntable_rms_ratio", 0.0, "max_turntable_rms_ratio"),
    ("min_fitness", -0.1, "min_fitness"),
    ("min_turntable_fitness", 0.0, "min_turntable_fitness"),
    ("max_residual_deg", 0.0, "max_residual_deg"),
    ("min_rotation_lever_ratio", 1.0, "min_rotation_lever_ratio"),
    ("turntable_step_deg", -180.0, "turntable_step_deg"),
    ("turntable_step_deg", 0.0, "turntable_step_deg"),
    ("min_confidence", 1.5, "min_confidence"),
    ("voxel", 0.0, "voxel"),
])
def test_stitch_options_validation(field, value, message):
    """Every option check fires when the options are made, naming the option."""
    with pytest.raises(InputError, match=message):
        StitchOptions(**{field: value})
    assert StitchOptions().min_confidence == STITCH_MIN_CONFIDENCE

@pytest.mark.slow  # make test-all: a variant of a fast test's behaviour (suite time)
def test_small_overlap_without_hint_is_corroborated_by_neighbours():
    """Stereo loses surfaces seen at grazing incidence, so reconstructed end-on views
    overlap their neighbours little (truck_k3: 0.18). Raycast views of truck_k3 that
    drop surfaces seen beyond 50 deg overlap at 0.15-0.20 on two pairs, below
    min_fitness; each moves like a neighbouring well-fitting pair, which corroborates
    it, and every pose is found without a hint (measured 0.020 deg)."""
    scans, poses, _, _ = _raycast_views(target="truck_k3", max_incidence_deg=50.0)
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=None, mesh=False))
    odometry = [e["fitness"] for e in res.diagnostics["edges"] if e["kind"] == "odometry"]
    assert min(odometry) < 0.2, odometry  # the case the corroboration is for
    err = _rotation_errors(res, poses)
    assert max(err) < 0.05, err
    assert res.diagnostics["warnings"] == []


@pytest.mark.parametrize("target", ["truck_k1", pytest.param("jet_j2", marks=pytest.mark.slow),
                                    pytest.param("ship_s2", marks=pytest.mark.slow)])
def test_other_targets_without_hint(target):
    """No turntable hint on a boxy truck (its end-on views have faces that match the
    wrong way), a jet and a ship (the paper's object: long and narrow, so the turn of
    an end-on view rests on its stern and a few walls): global registration with
    several candidates and the neighbours' motion finds every pose (measured 0.018,
    0.007 and 0.012 deg)."""
    scans, poses, _, _ = _raycast_views(target=target)
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=None, mesh=False))
    err = _rotation_errors(res, poses)
    assert max(err) < 0.05, err
    assert res.diagnostics["warnings"] == []


def _lever_warnings(res) -> list[str]:
    """The views the stitch names as weakly held by their rotation levers."""
    return [w.split(":")[0].removeprefix("view ") for w in res.diagnostics["warnings"] if "rotation lever" in w]


@pytest.mark.slow  # make test-all: a variant of a fast test's behaviour (suite time)
def test_rotation_lever_check(tank_views):
    """Every view's lever is reported; the tank's views hold their turn well (its
    end-on views have 0.32-0.43 of the median on stereo scans, 0.42-0.50 here), so
    nothing is flagged; a threshold above the three weakest flags exactly those, 0
    turns the check off, and a ratio outside [0, 1) is refused."""
    scans, _, _, _ = tank_views
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, mesh=False))
    lev = np.asarray(res.diagnostics["rotation_levers"])
    assert lev.shape == (len(scans),) and np.all(lev > 0)
    assert _lever_warnings(res) == []
    ratio = lev / np.median(lev)
    cut = float(np.sort(ratio)[2]) + 1e-3  # the three weakest views
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, mesh=False,
                                            min_rotation_lever_ratio=cut))
    assert sorted(_lever_warnings(res)) == sorted(f"scan {k}" for k in np.argsort(ratio)[:3])
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, mesh=False,
                                            min_rotation_lever_ratio=0))
    assert _lever_warnings(res) == []
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(InputError, match="min_rotation_lever_ratio"):
            StitchOptions(turntable_step_deg=45.0, mesh=False, min_rotation_lever_ratio=bad)


def test_rotation_lever_warning_for_an_unheld_view(tank_views, monkeypatch):
    """A view whose correspondences do not hold its turn at all (lever 0) is named,
    and the warning gives a bounded factor, not a division by zero."""
    import prism3d.reconstruct.scan.multiview as mv
    import prism3d.reconstruct.scan.stitch as st

    scans, _, _, _ = tank_views
    real = mv.refine_turntable

    def zero_lever(*args, **kwargs):
        T, info = real(*args, **kwargs)
        info["levers"] = np.array(info["levers"], dtype=np.float64)
        info["levers"][3] = 0.0
        return T, info

    monkeypatch.setattr(st, "refine_turntable", zero_lever)  # stitch holds its own reference
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, mesh=False))
    assert _lever_warnings(res) == ["scan 3"]
    (msg,) = [w for w in res.diagnostics["warnings"] if "rotation lever" in w]
    assert "rotation lever 0," in msg and "over 100x more" in msg, msg


def test_match_against_both_agreeing_neighbours_yields_to_their_motion(tank_views, monkeypatch, caplog):
    """Without a hint, a pair's match that fits better but moves unlike both of its
    neighbours (which move alike) gives way to their common motion when that still
    fits at min_turntable_fitness. Stereo scans of a jet seen tail-on did this: the
    match fit 0.253 with the views after it turned 90 deg, the true motion 0.208, and
    no loop closure registered to expose it. Here views 2-3 are offered a match 90 deg
    off whose fit is raised above the true one's."""
    import dataclasses
    import logging

    import prism3d.reconstruct.scan.stitch as st

    scans, poses, V, F = tank_views
    T_true = np.linalg.inv(poses[2]) @ poses[3]  # T_target_source of views 2 <- 3
    c = scans[3][0].mean(axis=0)
    flip = np.eye(4)
    flip[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # 90 deg about x, through the centroid
    flip[:3, 3] = c - flip[:3, :3] @ c
    T_wrong = T_true @ flip

    index = {}

    class Tagged(st.ScanPyramid):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            index[id(self)] = len(index)

    calls = []
    real_candidates = st.match_features_candidates

    def candidates(src, tgt, **k):
        calls.append(1)
        out = real_candidates(src, tgt, **k)
        return [(T_wrong, 1 << 20)] + out if len(calls) == 3 else out  # the third pair, 2-3

    real_icp = st.icp_pyramids

    def icp(source, target, T_init, **k):
        r = real_icp(source, target, T_init, **k)
        if (index[id(target)], index[id(source)]) == (2, 3) and rotation_angle_deg(
                np.linalg.inv(T_true) @ r.T_target_source) > 10.0:
            r = dataclasses.replace(r, fitness=0.9)
        return r

    monkeypatch.setattr(st, "ScanPyramid", Tagged)
    monkeypatch.setattr(st, "match_features_candidates", candidates)
    monkeypatch.setattr(st, "icp_pyramids", icp)
    with caplog.at_level(logging.INFO, logger="prism3d.reconstruct.scan.stitch"):
        res = stitch_scans(scans, StitchOptions(mesh=False, max_registration_points=20000))
    assert any("disagrees with both neighbours" in m for m in caplog.messages)  # the case was made
    _check(res, poses, V, F)
    assert res.diagnostics["warnings"] == []


def test_uneven_step_between_agreeing_neighbours_is_kept_and_flagged(tank_views):
    """A view left out of a 45 deg sequence makes one 90 deg step between pairs that
    move alike. The neighbours' common motion does not fit it, so its own match
    stays (every pose right), and a warning names the pair."""
    scans, poses, _, _ = tank_views
    keep = [0, 1, 2, 4, 5, 6, 7]
    res = stitch_scans([scans[k] for k in keep],
                       StitchOptions(mesh=False, max_registration_points=20000, on_failure="raise"))
    err = _rotation_errors(res, [poses[k] for k in keep])
    assert max(err) < 0.05, err
    assert len(res.diagnostics["warnings"]) == 1
    assert "scan 2 and scan 3 move unlike the pairs on either side" in res.diagnostics["warnings"][0]
