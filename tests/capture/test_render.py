"""Known-answer tests of the renderers (prism3d.capture.render)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.render import (
    RaycastRenderer,
    SensorNoise,
    box_downsample,
    camera_rays,
    gaussian_blur,
    quantize,
)
from prism3d.capture.rig import CameraModel, PrismSplit, look_at, paper_rig
from prism3d.capture.scenes import flat_plate, rotation_about, translation

import prism3d  # noqa: F401  (sets PYOPENGL_PLATFORM before any OpenGL import)
from prism3d.errors import InputError


def small_camera(dist=(-0.06, 0.12, 0.001, -0.002, 0.01), skew=0.0):
    K = np.array([[640.0, skew, 81.3], [0.0, 645.0, 60.7], [0.0, 0.0, 1.0]])
    return CameraModel(K, np.array(dist), (160, 120))


@pytest.fixture(scope="module")
def plate_renderer():
    return RaycastRenderer([(flat_plate(600, 600, albedo=(0.3, 0.5, 0.7)), translation(0, 0, 1250))])


def test_camera_rays_match_pixel_grid_rays():
    cam = small_camera()
    rays, z = camera_rays(cam)
    assert np.abs(rays - cam.pixel_grid_rays()).max() < 1e-12
    assert np.allclose(z, rays[..., 2])
    R = rotation_about((1, 2, 3), 0.4)[:3, :3]
    rays_w, z_w = camera_rays(cam, R)
    assert np.allclose(rays_w, rays @ R.T, atol=1e-14) and np.allclose(z_w, z)


def test_fronto_plate_depth_is_exact(plate_renderer):
    cam = small_camera()
    res = plate_renderer.render(cam, np.eye(4))
    assert res.mask.all()
    assert np.abs(res.depth_mm.astype(np.float64) - 1250.0).max() < 1e-4
    assert np.allclose(res.normals_cam, [0, 0, -1])
    assert np.allclose(res.albedo, [0.3, 0.5, 0.7], atol=1e-6)
    assert (res.object_id == 0).all() and res.face_id.min() >= 0
    assert np.abs(res.points_world[..., 2] - 1250.0).max() < 1e-9


def test_hit_points_project_back_to_pixel_centres(plate_renderer):
    """A rendered pixel sees exactly the point CameraModel.project / cv2.projectPoints
    put on that pixel, with distortion and a tilted camera."""
    cam = small_camera()
    T_world_cam = look_at(np.array([150.0, -80.0, 0.0]), np.array([0.0, 20.0, 1250.0]))
    res = plate_renderer.render(cam, T_world_cam)
    assert res.mask.mean() > 0.9
    T_cam_world = np.linalg.inv(T_world_cam)
    pw = res.points_world[res.mask]
    pc = pw @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    rvec, _ = cv2.Rodrigues(np.eye(3))
    uv_cv, _ = cv2.projectPoints(pc, rvec, np.zeros(3), cam.K, cam.dist)
    v, u = np.nonzero(res.mask)
    err = np.abs(uv_cv.reshape(-1, 2) - np.stack([u, v], 1))
    assert err.max() < 1e-6
    assert np.allclose(res.depth_mm[res.mask], pc[:, 2], rtol=1e-7)
    # the tilted plane's depth follows exactly from the ray geometry
    assert np.abs(pw[:, 2] - 1250.0).max() < 1e-9


def test_occlusion_object_ids_and_visibility():
    plate = flat_plate(300, 300)
    small = flat_plate(50, 50, name="small")
    r = RaycastRenderer([(plate, translation(0, 0, 1250)), (small, translation(0, 0, 1000))])
    assert r.n_objects == 2
    cam = small_camera(dist=())
    res = r.render(cam, np.eye(4))
    c = res.object_id[60, 81]
    assert c == 1 and res.depth_mm[60, 81] == pytest.approx(1000.0, abs=1e-4)
    assert res.object_id[10, 10] == 0
    pts = np.array([[0.0, 0.0, 1250.0], [140.0, 0.0, 1250.0], [np.nan, 0, 0]])
    vis = r.visible_from(pts, np.zeros(3))  # (0, 0) is behind the small plate
    assert vis.tolist() == [False, True, False]
    hits = r.cast(np.zeros(3), np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 0.0]]))
    assert hits.hit.tolist() == [True, False]
    assert hits.t[0] == pytest.approx(1000.0, abs=1e-9) and np.isinf(hits.t[1])


def test_misses_are_nan():
    r = RaycastRenderer([(flat_plate(10, 10), translation(0, 0, 1250))])
    res = r.render(small_camera(), np.eye(4))
    assert 0 < res.mask.sum() < res.mask.size
    assert np.isnan(res.depth_mm[~res.mask]).all() and np.isnan(res.normals_cam[~res.mask]).all()
    assert (res.object_id[~res.mask] == -1).all() and (res.albedo[~res.mask] == 0).all()


def test_vertex_albedo_is_interpolated():
    V = np.array([[-100.0, -100, 0], [100, -100, 0], [-100, 100, 0]])
    mesh = SceneMesh(V, np.array([[0, 2, 1]]), vertex_albedo=np.eye(3))
    r = RaycastRenderer([(mesh, translation(0, 0, 500))])
    h = r.cast(np.zeros(3), np.array([[0.0, 0.0, 1.0]]))
    alb = r.albedo(h)
    # point (0, 0): barycentric weights 0 / 0.5 / 0.5 for vertices 0, 1, 2
    assert np.allclose(alb[0], [0.0, 0.5, 0.5])


def test_supersampling_box_average():
    # the centre of output pixel (u, v) is the mean of its 3x3 sub-pixel centres
    img = np.arange(36, dtype=np.float64).reshape(6, 6)
    out = box_downsample(img, 3)
    assert out.shape == (2, 2) and out[0, 0] == img[:3, :3].mean()
    assert box_downsample(img, 1) is not img
    with pytest.raises(InputError, match="multiple"):
        box_downsample(np.zeros((5, 6)), 3)
    with pytest.raises(InputError, match="integer"):
        box_downsample(img, 1.5)  # type: ignore[arg-type]


def test_sensor_noise_statistics_and_determinism():
    img = np.full((200, 200, 3), 0.5)
    model = SensorNoise(gain_e_per_dn=20.0, read_noise_dn=2.0)
    a = model.apply(img, np.random.default_rng(1))
    b = model.apply(img, np.random.default_rng(1))
    assert np.array_equal(a, b)
    assert a.mean() == pytest.approx(127.5, abs=0.1)
    assert a.var() == pytest.approx(127.5 / 20.0 + 4.0, rel=0.05)
    q = quantize(np.array([-3.0, 0.4, 254.6, 300.0]))
    assert q.dtype == np.uint8 and q.tolist() == [0, 0, 255, 255]
    with pytest.raises(InputError, match="gain_e_per_dn"):
        SensorNoise(gain_e_per_dn=0)
    with pytest.raises(InputError, match="read_noise_dn"):
        SensorNoise(read_noise_dn=-1)


def test_gaussian_blur():
    img = np.zeros((21, 21), np.float32)
    img[10, 10] = 1.0
    out = gaussian_blur(img, 1.5)
    assert out.sum() == pytest.approx(1.0, abs=1e-5) and out[10, 10] < 0.2
    assert gaussian_blur(img, 0) is img
    with pytest.raises(InputError, match="sigma_px"):
        gaussian_blur(img, -1)


def test_renderer_errors(plate_renderer):
    with pytest.raises(InputError, match="scene is empty"):
        RaycastRenderer([])
    with pytest.raises(InputError, match="SceneMesh, T_world_obj"):
        RaycastRenderer([("plate", np.eye(4))])
    with pytest.raises(InputError, match="pose"):
        RaycastRenderer([(flat_plate(), np.zeros((4, 4)))])
    with pytest.raises(InputError, match="rotation"):
        RaycastRenderer([(flat_plate(), np.diag([1.0, 1.0, -1.0, 1.0]))])
    with pytest.raises(InputError, match="camera: expected a CameraModel"):
        plate_renderer.render("cam", np.eye(4))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="T_world_cam"):
        plate_renderer.render(small_camera(), np.eye(3))
    with pytest.raises(InputError, match="origins"):
        plate_renderer.cast(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(InputError, match="directions"):
        plate_renderer.cast(np.zeros(3), np.ones((3, 2)))


# -- rig parameters the simulator relies on ------------------------------------------
def test_bad_rig_parameters_raise():
    with pytest.raises(InputError, match="focal lengths must be > 0"):
        CameraModel(np.array([[-5107.0, 0, 648], [0, 5107, 972], [0, 0, 1]]), np.zeros(5), (1296, 1944))
    with pytest.raises(InputError, match="outside the 2592x1944 sensor"):
        PrismSplit((2592, 1944), (0, 0, 1296, 1944), (1300, 0, 1296, 1944))
    with pytest.raises(InputError, match="focal lengths must be > 0"):
        paper_rig(focal_px=-10.0)


def test_split_then_join_is_lossless():
    rng = np.random.default_rng(0)
    for flips in ((False, False), (True, False), (False, True), (True, True)):
        split = PrismSplit.side_by_side((64, 32), flip_left=flips[0], flip_right=flips[1])
        img = rng.integers(0, 256, (32, 64, 3), dtype=np.uint8)
        left, right = split.split(img)
        assert np.array_equal(split.join(left, right), img)


# -- pyrender backend -------------------------------------------------------------------
@pytest.fixture(scope="module")
def pyrender_plate():
    pytest.importorskip("pyrender")
    from prism3d.capture.render_gl import PyrenderRenderer

    objs = [(flat_plate(300, 300, albedo=(0.5, 0.5, 0.5)), translation(0, 0, 1250))]
    try:
        r = PyrenderRenderer(objs)
    except Exception as exc:  # pragma: no cover - no OpenGL on this machine
        pytest.skip(f"pyrender unavailable: {exc}")
    yield r, objs
    r.close()


def test_pyrender_matches_raycaster(pyrender_plate):
    r, objs = pyrender_plate
    cam = small_camera(dist=())
    T = look_at(np.array([100.0, -50.0, 0.0]), np.array([0.0, 0.0, 1250.0]))
    res = r.render(cam, T)
    ref = RaycastRenderer(objs).render(cam, T)
    assert res.rgb is not None and res.rgb.dtype == np.uint8 and res.rgb.shape == (120, 160, 3)
    both = res.mask & ref.mask
    assert both.sum() > 0.95 * ref.mask.sum()
    # mask boundary agrees to a pixel; depth to the z-buffer precision
    assert (res.mask != ref.mask).sum() <= 2 * (ref.mask.shape[0] + ref.mask.shape[1])
    assert np.abs(res.depth_mm[both] - ref.depth_mm[both]).max() < 0.5
    assert np.allclose(res.albedo[both], 0.5, atol=1 / 255)
    assert np.abs(res.normals_cam[both] - ref.normals_cam[both]).max() < 0.02
    assert (res.object_id[both] == 0).all() and (res.object_id[~res.mask] == -1).all()


def test_pyrender_rejects_distortion_and_skew(pyrender_plate):
    r, _ = pyrender_plate
    with pytest.raises(InputError, match="distortion"):
        r.render(small_camera(), np.eye(4))
    with pytest.raises(InputError, match="skew"):
        r.render(small_camera(dist=(), skew=1.0), np.eye(4))


# -- fast paths (streaming, ray cache, culling, planar shadows, counter-based noise) ----
def _tilted_plate_scene():
    T = translation(30, -20, 1250) @ rotation_about((1, 1, 0), 0.5)
    return RaycastRenderer([(flat_plate(400, 300, albedo=(0.3, 0.5, 0.7)), T)])


def test_stream_camera_bands_match_trace_camera(monkeypatch):
    from prism3d.capture import render as render_mod

    r = _tilted_plate_scene()
    cam = small_camera()
    T = look_at(np.array([40.0, -30.0, 0.0]), np.array([0.0, 0.0, 1250.0]))
    whole = r.trace_camera(cam, T)
    monkeypatch.setattr(render_mod, "_CHUNK", 7 * cam.width + 5)  # bands of 6 rows
    bands = []

    def consume(s, e, hb):
        assert e - s == min(6 * cam.width, cam.width * cam.height - s)
        assert np.all((hb.index >= s) & (hb.index < e))
        bands.append([a.copy() for a in (hb.index, hb.t, hb.points, hb.normals, hb.z_cam, hb.face_id)])

    r.stream_camera(cam, T, consume, rows_multiple=2)
    got = [np.concatenate(x) for x in zip(*bands, strict=True)]
    ref = (whole.index, whole.t, whole.points, whole.normals, whole.z_cam, whole.face_id)
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a, b)
    # the compact hits are the render's maps
    res = r.render(cam, T)
    assert np.array_equal(np.flatnonzero(res.mask), whole.index)
    np.testing.assert_array_equal(res.depth_mm.reshape(-1)[whole.index], (whole.t * whole.z_cam).astype(np.float32))


def test_camera_rays_are_cached_per_camera_model():
    r = _tilted_plate_scene()
    cam = small_camera()
    r.render(cam, np.eye(4))
    r.render(cam, look_at(np.zeros(3), np.array([10.0, 0.0, 1250.0])))
    assert len(r._ray_cache) == 1
    d, z = next(iter(r._ray_cache.values()))
    rays, zc = camera_rays(cam)
    assert np.array_equal(d, rays.reshape(-1, 3)) and np.array_equal(z, zc.reshape(-1))
    for k in range(2, 5):
        r.render(cam.scaled(k), np.eye(4))
    assert len(r._ray_cache) == 3  # bounded


def test_bounding_box_cull_changes_nothing():
    r = _tilted_plate_scene()
    rng = np.random.default_rng(5)
    d = np.c_[rng.uniform(-0.3, 0.3, (20000, 2)), np.ones(20000)]
    o = rng.uniform(-50, 50, (20000, 3))
    a = r.cast(o, d)
    assert 0.1 < a.hit.mean() < 0.9
    r._box_lo = np.full(3, -np.inf)
    r._box_hi = np.full(3, np.inf)
    b = r.cast(o, d)
    for f in ("t", "object_id", "face_id", "bary_uv", "points", "normals"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_planar_scene_shadow_shortcut_matches_rays():
    r = _tilted_plate_scene()
    assert r._plane is not None
    res = r.render(small_camera(), np.eye(4))
    on = res.points_world[res.mask]
    nrm, c = r._plane
    behind = on[:50] + 5.0 * nrm * np.sign(c)  # 5 mm beyond the plate, seen through it
    pts = np.concatenate([on, behind, [[np.nan, 0.0, 0.0]]])
    src = np.array([20.0, 10.0, 0.0])
    fast = r.visible_from(pts, src)
    r._plane = None  # force the ray test
    slow = r.visible_from(pts, src)
    np.testing.assert_array_equal(fast, slow)
    assert fast[: len(on)].all() and not fast[len(on) :].any()
    two = RaycastRenderer([(flat_plate(300, 300), translation(0, 0, 1250)), (flat_plate(50, 50), translation(0, 0, 1000))])
    assert two._plane is None


def test_sensor_noise_low_light_and_thread_independence():
    import numba

    model = SensorNoise(gain_e_per_dn=1.0, read_noise_dn=0.0)
    img = np.full((300, 300, 3), 3.0 / 255.0)  # 3 electrons: the small-mean sampler
    e = model.apply(img, np.random.default_rng(2))
    assert np.array_equal(e, np.round(e))
    assert e.mean() == pytest.approx(3.0, abs=0.03) and e.var() == pytest.approx(3.0, rel=0.05)
    assert model.apply(np.zeros((4, 4)), np.random.default_rng(0)).max() == 0.0
    big = np.random.default_rng(0).uniform(0, 1, (64, 64, 3))
    full = SensorNoise().apply(big, np.random.default_rng(9))
    n = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = SensorNoise().apply(big, np.random.default_rng(9))
    finally:
        numba.set_num_threads(n)
    assert np.array_equal(full, one)
