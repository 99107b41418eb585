"""Known-answer tests of the scene simulator (prism3d.capture.simulate)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from prism3d.capture.camera_effects import CameraEffects
from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.rig import compute_rectification, paper_rig
from prism3d.capture.scenes import (
    chessboard,
    chessboard_corners,
    flat_plate,
    from_trimesh,
    rotation_about,
    translation,
)
from prism3d.capture.simulate import (
    Projector,
    ShotOptions,
    SimulateOptions,
    simulate_shot,
    simulate_to_folder,
    working_distance_mm,
)

import prism3d  # noqa: F401  (sets the environment)
from prism3d.errors import InputError


def quarter_rig(**kw):
    return paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4, **kw)


def eighth_rig(**kw):
    return paper_rig(sensor_size=(324, 244), focal_px=5107.0 / 8, **kw)


def plane_depth(cam, T_rig_cam, z_plane):
    """Analytic depth map of the plane rig-z = z_plane seen by cam."""
    rays = cam.pixel_grid_rays().reshape(-1, 3)
    d = rays @ T_rig_cam[:3, :3].T
    c = T_rig_cam[:3, 3]
    t = (z_plane - c[2]) / d[:, 2]
    return (t * rays[:, 2]).reshape(cam.height, cam.width), (c + t[:, None] * d).reshape(cam.height, cam.width, 3)


@pytest.fixture(scope="module")
def plate_shot():
    rig = quarter_rig()
    plate = flat_plate(300, 300)
    # the ideal camera: these are known-answer tests of the image model itself
    shot = simulate_shot(rig, [(plate, translation(0, 0, 1250))], ShotOptions(supersample=1, noise=False, effects=None))
    return rig, shot


def test_plate_depth_and_disparity_exact(plate_shot):
    rig, shot = plate_shot
    t = shot.truth
    for name, cam, T in (("left", rig.left, rig.T_rig_left), ("right", rig.right, rig.T_rig_right)):
        depth = t[f"depth_{name}_mm"]
        true_depth, pts = plane_depth(cam, T, 1250.0)
        inside = (np.abs(pts[..., 0]) < 149.9) & (np.abs(pts[..., 1]) < 149.9)
        m = t[f"mask_{name}"]
        assert m[inside].all()
        assert not m[(np.abs(pts[..., 0]) > 150.1) | (np.abs(pts[..., 1]) > 150.1)].any()
        err = np.abs(depth[inside].astype(np.float64) - true_depth[inside])
        assert err.max() < 1e-3  # float32 storage: ~6e-5 mm at 1250 mm
    rect = shot.rectification
    d = t["disparity_rect"]
    valid = np.isfinite(d)
    assert valid.mean() > 0.3
    expected = rect.focal_px * rect.baseline_mm / 1250.0
    assert abs(expected - 808.0 / 4) < 1.0
    assert np.abs(d[valid] - expected).max() < 1e-3
    assert np.allclose(t["R1"], rect.R1) and np.allclose(t["P2"], rect.P2)


def test_shading_albedo_consistency_white_flash(plate_shot):
    rig, shot = plate_shot
    left, right = rig.split.split(shot.sensor_image)
    for name, view in (("left", left), ("right", right)):
        m = shot.truth[f"mask_{name}"]
        pred = shot.truth[f"albedo_{name}"] * shot.truth[f"shading_{name}"][..., None]
        err = np.abs(view.astype(np.float64) / 255.0 - np.clip(pred, 0, 1))[m]
        assert err.max() <= 0.5 / 255 + 1e-6
        # white flash: illumination equals shading in every channel
        ill = shot.truth[f"illumination_{name}"][m]
        assert np.allclose(ill, shot.truth[f"shading_{name}"][m][:, None], atol=1e-6)
        assert np.allclose(np.linalg.norm(shot.truth[f"normals_{name}"][m], axis=-1), 1, atol=1e-5)
        assert (shot.truth[f"normals_{name}"][m][:, 2] < 0).all()  # facing the camera


def test_supersampled_noisy_shot_is_deterministic_and_close():
    rig = eighth_rig()
    objs = [(flat_plate(300, 300, albedo=(0.5, 0.5, 0.5)), translation(0, 0, 1250))]
    a = simulate_shot(rig, objs, ShotOptions(supersample=2, noise=True, seed=3, effects=None))
    b = simulate_shot(rig, objs, ShotOptions(supersample=2, noise=True, seed=3, effects=None))
    c = simulate_shot(rig, objs, ShotOptions(supersample=2, noise=True, seed=4, effects=None))
    assert np.array_equal(a.sensor_image, b.sensor_image)
    assert not np.array_equal(a.sensor_image, c.sensor_image)
    left, _ = rig.split.split(a.sensor_image)
    m = a.truth["mask_left"]
    inner = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    pred = 255 * 0.5 * a.truth["shading_left"][inner]
    resid = left[inner].mean(axis=1) - pred
    assert abs(resid.mean()) < 0.3
    assert 0.5 < resid.std() < 3.0  # shot + read noise, averaged over 3 channels


def test_pattern_colours_follow_the_projector():
    rig = eighth_rig()
    proj = Projector.for_rig(rig, pattern=True)
    objs = [(flat_plate(300, 300, albedo=(1.0, 1.0, 1.0)), translation(0, 0, 1250))]
    shot = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False), projector=proj)
    t = shot.truth
    m = t["mask_left"]
    ill = t["illumination_left"][m]
    # a saturated colour pattern: some channels at ambient only, some lit
    assert ill.min() == pytest.approx(0.25, abs=1e-6)
    assert ill.max() > 0.9
    assert np.all(ill <= t["shading_left"][m][:, None] + 1e-6)


def test_shadow_of_an_occluder_is_where_geometry_says():
    rig = eighth_rig()
    plate = flat_plate(300, 300, albedo=(0.8, 0.8, 0.8))
    occ = flat_plate(40, 40, albedo=(0.8, 0.8, 0.8), name="occluder")
    T_occ = translation(20, -10, 900)
    shot = simulate_shot(rig, [(plate, translation(0, 0, 1250)), (occ, T_occ)], ShotOptions(supersample=1, noise=False))
    t = shot.truth
    _, pts = plane_depth(rig.left, rig.T_rig_left, 1250.0)
    on_plate = t["object_id_left"] == 0
    # segment from the projector (rig origin) to a plate point crosses z=900 at s=900/1250
    q = pts * (900.0 / 1250.0)
    in_shadow = (np.abs(q[..., 0] - 20) < 20) & (np.abs(q[..., 1] + 10) < 20)
    margin = (np.abs(q[..., 0] - 20) > 20.3) | (np.abs(q[..., 1] + 10) > 20.3)
    shade = t["shading_left"]
    sel = on_plate & in_shadow
    assert sel.sum() > 20
    assert np.allclose(shade[sel], 0.25, atol=1e-6)  # ambient only
    lit = on_plate & ~in_shadow & margin
    assert (shade[lit] > 0.9).all()
    assert (t["object_id_left"] == 1).sum() > 20  # the occluder itself is seen


def test_calib_truth_corners_match_projectpoints_and_detector():
    rig = quarter_rig()
    board = chessboard(9, 6, 25.0)
    corners = chessboard_corners(9, 6, 25.0)
    T_rig_board = (
        translation(-100, -60, 1250)
        @ rotation_about((0, 1, 0), np.radians(10))
        @ rotation_about((0, 0, 1), np.radians(10))
    )
    shot = simulate_shot(rig, [(board, T_rig_board)], ShotOptions(supersample=4, noise=False))
    left, _ = rig.split.split(shot.sensor_image)
    T_left_board = np.linalg.inv(rig.T_rig_left) @ T_rig_board
    rvec, _ = cv2.Rodrigues(T_left_board[:3, :3])
    uv_cv, _ = cv2.projectPoints(corners, rvec, T_left_board[:3, 3], rig.left.K, rig.left.dist)
    uv_cv = uv_cv.reshape(-1, 2)
    pc = corners @ T_left_board[:3, :3].T + T_left_board[:3, 3]
    assert np.abs(rig.left.project(pc) - uv_cv).max() < 1e-6
    grey = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    # classic detector: same order as chessboard_corners
    ok, found = cv2.findChessboardCorners(grey, (9, 6))
    assert ok
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    found = cv2.cornerSubPix(grey, found, (5, 5), (-1, -1), crit).reshape(-1, 2)
    err = np.linalg.norm(found - uv_cv, axis=1)
    assert err.mean() < 0.1 and err.max() < 0.2
    # sector-based detector: reversed order on this board, ~0.03 px
    ok, found = cv2.findChessboardCornersSB(grey, (9, 6), flags=cv2.CALIB_CB_ACCURACY)
    assert ok
    err = np.linalg.norm(found.reshape(-1, 2)[::-1] - uv_cv, axis=1)
    assert err.mean() < 0.1 and err.max() < 0.2


def test_mirror_flip_split_recovers_views():
    rig = eighth_rig(flip_right=True)
    objs = [(flat_plate(300, 300), translation(0, 0, 1250))]
    # every effect but JPEG acts per view; JPEG's 8x8 blocks sit on the sensor layout
    fx = CameraEffects(jpeg_quality=None)
    a = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False, effects=fx))
    b = simulate_shot(eighth_rig(), objs, ShotOptions(supersample=1, noise=False, effects=fx))
    la, ra = rig.split.split(a.sensor_image)
    lb, rb = eighth_rig().split.split(b.sensor_image)
    assert np.array_equal(la, lb) and np.array_equal(ra, rb)
    w = rig.split.view_size[0]
    assert np.array_equal(a.sensor_image[:, w:], rb[:, ::-1])


def test_working_distance_of_paper_rig():
    assert working_distance_mm(paper_rig()) == pytest.approx(1250.0, abs=1e-6)
    assert working_distance_mm(paper_rig(working_distance_mm=2000)) == pytest.approx(2000.0, abs=1e-6)


def test_simulate_shot_errors():
    rig = eighth_rig()
    objs = [(flat_plate(), translation(0, 0, 1250))]
    with pytest.raises(InputError, match="rig: expected a StereoRig"):
        simulate_shot("rig", objs)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="supersample"):
        simulate_shot(rig, objs, ShotOptions(supersample=0))
    with pytest.raises(InputError, match="ambient"):
        simulate_shot(rig, objs, ShotOptions(ambient=-1))
    with pytest.raises(InputError, match="blur_sigma"):
        simulate_shot(rig, objs, ShotOptions(blur_sigma=-1))
    with pytest.raises(InputError, match="projector"):
        simulate_shot(rig, objs, projector="x")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="noise"):
        simulate_shot(rig, objs, ShotOptions(noise="loud"))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="scene is empty"):
        simulate_shot(rig, [])
    with pytest.raises(InputError, match="pattern: expected"):
        Projector(np.diag([100.0, 100.0, 1.0]), (64, 32), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(InputError, match="focal"):
        Projector(np.diag([-100.0, 100.0, 1.0]), (64, 32))


# -- the CLI contract ------------------------------------------------------------------
def _read_fs(path):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return {k: fs.getNode(k).mat() for k in ("K1", "D1", "K2", "D2", "R", "T")}
    finally:
        fs.release()


def test_simulate_to_folder_plate_contract(tmp_path):
    rig = eighth_rig()
    calls = []
    summary = simulate_to_folder(
        "plate", tmp_path / "plate", SimulateOptions(supersample=1), rig=rig, progress=lambda *a: calls.append(a)
    )
    out = tmp_path / "plate"
    assert sorted(p.name for p in out.iterdir()) == ["rig.yaml", "shot.png", "truth.npz"]
    assert summary["files"] == ["rig.yaml", "shot.png", "truth.npz"] and summary["pattern"] is True
    assert calls == [(1, 1, "shot.png")]
    fs = _read_fs(out / "rig.yaml")
    assert np.allclose(fs["K1"], rig.left.K) and np.allclose(fs["T"].ravel(), rig.T)
    img = cv2.imread(str(out / "shot.png"))
    assert img.shape == (244, 324, 3)
    with np.load(out / "truth.npz", allow_pickle=False) as z:
        for k in ("depth_left_mm", "depth_right_mm", "disparity_rect", "shading_left", "albedo_left"):
            assert z[k].dtype == np.float32
        assert z["mask_left"].dtype == bool and z["albedo_left"].shape == (244, 162, 3)
        assert z["normals_right"].shape == (244, 162, 3)
        for k in ("R1", "R2", "P1", "P2"):
            assert k in z
        assert np.nanmax(np.abs(z["depth_left_mm"])) < 1300


def test_truth_npz_is_deflated_by_default_and_equal_to_plain(tmp_path):
    """Truth is mostly NaN background: the default file is deflated (a 5 MP scene
    shot 281 -> 4.8 MB) and holds exactly what the plain file holds."""
    import zipfile

    rig = eighth_rig()
    simulate_to_folder("plate", tmp_path / "z", SimulateOptions(supersample=1), rig=rig)
    simulate_to_folder("plate", tmp_path / "p", SimulateOptions(supersample=1, compress=False), rig=rig)
    z_path, p_path = tmp_path / "z" / "truth.npz", tmp_path / "p" / "truth.npz"
    with zipfile.ZipFile(z_path) as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_DEFLATED}
    with zipfile.ZipFile(p_path) as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
    assert z_path.stat().st_size < 0.5 * p_path.stat().st_size
    with np.load(z_path, allow_pickle=False) as a, np.load(p_path, allow_pickle=False) as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k
    assert not [p.name for p in (tmp_path / "z").iterdir() if p.name.startswith(".")]  # no temp files left


def test_simulate_to_folder_calib_contract_and_determinism(tmp_path):
    rig = eighth_rig()
    s1 = simulate_to_folder("calib", tmp_path / "a", SimulateOptions(views=2, supersample=1, seed=5), rig=rig)
    s2 = simulate_to_folder("calib", tmp_path / "b", SimulateOptions(views=2, supersample=1, seed=5), rig=rig)
    names = ["calib_00.png", "calib_01.png", "rig.yaml", "truth_00.npz", "truth_01.npz"]
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == names
    assert s1["files"] == names == s2["files"] and s1["pattern"] is False
    for n in ("calib_00.png", "calib_01.png"):
        assert (tmp_path / "a" / n).read_bytes() == (tmp_path / "b" / n).read_bytes()
    with np.load(tmp_path / "a" / "truth_01.npz", allow_pickle=False) as z:
        cl = z["corners_left"]
        assert cl.shape == (54, 2) and cl.dtype == np.float64 and np.isfinite(cl).all()
        T = z["T_left_board"]
        rvec, _ = cv2.Rodrigues(T[:3, :3])
        uv, _ = cv2.projectPoints(chessboard_corners(), rvec, T[:3, 3], rig.left.K, rig.left.dist)
        assert np.abs(uv.reshape(-1, 2) - cl).max() < 1e-6
        # tilted by 20-40 degrees against the rig axis, 1100-1400 mm away
        T_rig_board = z["T_rig_board"]
        assert np.allclose(rig.T_rig_left @ T, T_rig_board)
        tilt = np.degrees(np.arccos(abs(T_rig_board[2, 2])))
        assert 20 - 1e-9 <= tilt <= 40 + 1e-9
        centre = T_rig_board[:3, :3] @ np.array([100.0, 62.5, 0]) + T_rig_board[:3, 3]
        assert 1100 - 1e-6 <= centre[2] <= 1400 + 1e-6


def test_simulate_to_folder_scene_contract(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    rig = eighth_rig()
    target = from_trimesh(trimesh.creation.box(extents=(150.0, 100.0, 80.0)), name="box")
    s = simulate_to_folder("scene", tmp_path, SimulateOptions(views=2, supersample=1, noise=False), rig=rig,
                           target=target)
    names = ["poses.json", "rig.yaml", "shot_00.png", "shot_01.png", "target.ply", "truth_00.npz", "truth_01.npz"]
    assert sorted(p.name for p in tmp_path.iterdir()) == names == s["files"]
    doc = json.loads((tmp_path / "poses.json").read_text())
    assert len(doc["views"]) == 2 and len(doc["T_world_rig"]) == 2
    T_world_cam = np.array(doc["views"][1]["T_world_cam"])
    assert T_world_cam.shape == (4, 4)
    mesh = trimesh.load(tmp_path / "target.ply", process=False)
    assert np.allclose(mesh.vertices, target.vertices) and len(mesh.faces) == len(target.faces)
    from prism3d.atr.features import features_table
    from prism3d.io.ply import read_ply

    ply = read_ply(tmp_path / "target.ply")
    assert "units mm" in ply.comments and "up z" in ply.comments
    assert np.array_equal(ply.points, target.vertices)  # float64, exact
    table = features_table([tmp_path / "target.ply"], up="z")  # no --units: the file declares mm
    assert table["kind"].tolist() == ["mesh"] and table["units_in"].tolist() == ["mm"]
    with np.load(tmp_path / "truth_01.npz", allow_pickle=False) as z:
        depth = z["depth_left_mm"]
        m = z["mask_left"]
        assert m.sum() > 100
        # back-project the true depth into the world: the points lie on the box surface
        rays = rig.left.pixel_grid_rays()[m]
        p_cam = rays / rays[:, 2:3] * depth[m][:, None].astype(np.float64)
        p_world = p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        half = np.array([75.0, 50.0, 40.0])
        dist_to_surface = np.min(np.abs(np.abs(p_world) - half), axis=1)
        assert np.all(np.abs(p_world) <= half + 0.01) and dist_to_surface.max() < 0.01


def test_simulate_to_folder_errors(tmp_path):
    with pytest.raises(InputError, match="kind"):
        simulate_to_folder("teapot", tmp_path)
    with pytest.raises(InputError, match="target mesh is required"):
        simulate_to_folder("scene", tmp_path, rig=eighth_rig())
    with pytest.raises(InputError, match="views"):
        simulate_to_folder("plate", tmp_path, SimulateOptions(views=0), rig=eighth_rig())
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        simulate_to_folder("plate", f)
    with pytest.raises(InputError, match="target: expected a SceneMesh"):
        simulate_to_folder("scene", tmp_path, rig=eighth_rig(), target="box")  # type: ignore[arg-type]
    assert not any(p.suffix == ".png" for p in tmp_path.iterdir())
    with pytest.raises(InputError, match="options: expected a SimulateOptions"):
        simulate_to_folder("plate", tmp_path, ShotOptions())  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"views": 1.5}, r"views: expected an integer in \[1, 1000\]"),
        ({"views": 10**9}, r"views: expected an integer in \[1, 1000\]"),
        ({"board": (1000, 1000)}, r"board: expected \(cols, rows\) inner corners in \[2, 100\]"),
        ({"blur_sigma": 1e9}, r"blur_sigma: expected a value in \[0.0, 100.0\]"),
        ({"seed": -1}, r"seed: expected an integer in \[0, 2\*\*63\)"),
        ({"board": (1, 6)}, r"board: expected \(cols, rows\)"),
        ({"board": (9, 6, 2)}, r"board: expected \(cols, rows\)"),
        ({"square_mm": 0}, "square_mm"),
        ({"blur_sigma": -1}, "blur_sigma"),
        ({"effects": "on"}, "effects: expected a CameraEffects"),
        ({"supersample": 9}, "supersample"),
        ({"noise": "loud"}, "noise"),
    ],
)
def test_simulate_options_validation(kwargs, match):
    with pytest.raises(InputError, match=match):
        SimulateOptions(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"flash": 11}, "flash"),
        ({"background": 2}, "background"),
        ({"supersample": 1.5}, "supersample"),
        ({"effects": 1}, "effects: expected a CameraEffects"),
    ],
)
def test_shot_options_validation(kwargs, match):
    with pytest.raises(InputError, match=match):
        ShotOptions(**kwargs)
    o = ShotOptions(noise=False, effects=CameraEffects.ideal())
    assert o.noise_model is None and o.real_effects is None and ShotOptions().real_effects == CameraEffects()


def test_simulate_shot_rejects_other_options():
    with pytest.raises(InputError, match="options: expected a ShotOptions"):
        simulate_shot(eighth_rig(), [(flat_plate(), translation(0, 0, 1250))], SimulateOptions())  # type: ignore[arg-type]


def test_uniform_albedo_mesh_roundtrip():
    m = SceneMesh(np.eye(3), np.array([[0, 1, 2]]), albedo_field=UniformAlbedo((0.2, 0.3, 0.4)))
    assert np.allclose(m.vertex_colors(), [0.2, 0.3, 0.4])
    assert compute_rectification(eighth_rig()).size[0] > 0


# -- fast paths ------------------------------------------------------------------------
def test_streamed_supersampled_shot_does_not_depend_on_band_size(monkeypatch):
    from prism3d.capture import render as render_mod

    rig = eighth_rig()
    proj = Projector.for_rig(rig, pattern=True)
    plate = flat_plate(300, 300)  # speckle texture albedo
    occ = flat_plate(40, 40, albedo=(0.8, 0.8, 0.8), name="occluder")
    objs = [(plate, translation(0, 0, 1250)), (occ, translation(20, -10, 900))]
    a = simulate_shot(rig, objs, ShotOptions(supersample=2, noise=False), projector=proj)
    monkeypatch.setattr(render_mod, "_CHUNK", 4 * 324 + 7)  # many small bands
    b = simulate_shot(rig, objs, ShotOptions(supersample=2, noise=False), projector=proj)
    assert np.array_equal(a.sensor_image, b.sensor_image)
    for k, v in a.truth.items():
        np.testing.assert_array_equal(v, b.truth[k], err_msg=k)


def test_projector_light_at_is_bilinear_in_the_pattern():
    pat = np.zeros((4, 6, 3), np.uint8)
    pat[..., 0] = np.arange(6) * 40  # red ramps along u
    pat[..., 1] = (np.arange(4) * 60)[:, None]  # green along v
    pat[..., 2] = 255
    proj = Projector(np.array([[10.0, 0, 2.5], [0, 10.0, 1.5], [0, 0, 1]]), (6, 4), pat, ref_distance_mm=100.0)
    # projector pixel (u, v) = 10 * (x, y) / z + (2.5, 1.5)
    pts = np.array([[0.0, 0.0, 100.0], [13.0, -7.0, 100.0], [0.0, 0.0, -100.0], [100.0, 0, 100.0], [-30.0, -20.0, 100.0]])
    rgb, white = proj.light_at(pts)
    assert white.tolist() == [1.0, 1.0, 0.0, 0.0, 1.0]
    u = 10 * pts[:, 0] / 100 + 2.5
    v = 10 * pts[:, 1] / 100 + 1.5
    for i in (0, 1):
        assert rgb[i, 0] == pytest.approx(40 * u[i] / 255, abs=1e-12)
        assert rgb[i, 1] == pytest.approx(60 * v[i] / 255, abs=1e-12)
        assert rgb[i, 2] == pytest.approx(1.0, abs=1e-12)
    assert np.array_equal(rgb[2:4], np.zeros((2, 3)))
    assert rgb[4, 0] == 0.0 and rgb[4, 1] == 0.0  # edge at (-0.5, -0.5): clamped to pixel (0, 0)
    flash = Projector(proj.K, (6, 4))
    rgb_w, white_w = flash.light_at(pts)
    assert np.array_equal(rgb_w, np.repeat(white_w[:, None], 3, axis=1))
