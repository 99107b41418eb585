"""Camera effects of the virtual rig (prism3d.capture.camera_effects), each measured
against its definition on flat targets, and the ideal camera against the simulator
as it was before effects existed."""

from __future__ import annotations

import dataclasses
import hashlib

import cv2
import numpy as np
import pytest
from prism3d.capture.camera_effects import (
    MATERIALS,
    CameraEffects,
    Gloss,
    jpeg_roundtrip,
    vignetting_factor,
)
from prism3d.capture.rig import CameraModel, StereoRig, paper_rig
from prism3d.capture.scenes import TextureAlbedo, chessboard, flat_plate, rotation_about, translation
from prism3d.capture.simulate import Projector, ShotOptions, SimulateOptions, simulate_shot, simulate_to_folder

import prism3d  # noqa: F401  (sets the environment)
from prism3d.errors import InputError


def quarter_rig(**kw):
    return paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4, **kw)


def eighth_rig(**kw):
    return paper_rig(sensor_size=(324, 244), focal_px=5107.0 / 8, **kw)


def only(**kw) -> CameraEffects:
    """The ideal camera with just the named effects switched on."""
    return dataclasses.replace(CameraEffects.ideal(), **kw)


def grey_wall(grey: float = 0.5):
    """A matte grey plate filling both views of the small rigs (1250 mm away)."""
    return [(flat_plate(900, 900, albedo=(grey, grey, grey), material="lambertian"), translation(0, 0, 1250))]


def views(rig, shot):
    left, right = rig.split.split(shot.sensor_image)
    return left.astype(np.float64), right.astype(np.float64)


# -- the ideal camera ------------------------------------------------------------------
def _digest(shot) -> tuple[str, str]:
    """(sensor image + every truth array, sensor image alone), sha256 prefixes."""
    h = hashlib.sha256()
    h.update(shot.sensor_image.tobytes())
    for k in sorted(shot.truth):
        a = np.ascontiguousarray(shot.truth[k])
        h.update(k.encode())
        h.update(str(a.dtype).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:32], hashlib.sha256(shot.sensor_image.tobytes()).hexdigest()[:32]


def _reference_scene():
    rig = eighth_rig()
    plate = flat_plate(300, 300, albedo=TextureAlbedo(seed=2))
    occ = flat_plate(40, 40, albedo=(0.8, 0.6, 0.4), name="occluder")
    objs = [
        (plate, translation(0, 0, 1250) @ rotation_about((0, 1, 0), np.radians(15))),
        (occ, translation(20, -10, 900)),
    ]
    return rig, objs, Projector.for_rig(rig, pattern=True, seed=3)


#: Digests of two shots of ``_reference_scene`` made by the simulator before camera
#: effects existed (commit 3f62f27, this machine: numba kernels, Open3D casting),
#: with the arguments below and no ``effects`` argument: the old code path itself,
#: not a re-implementation. Any change to the ideal image or the truth shows here.
_OLD_DIGESTS = {
    "pattern_ss2_noise_blur": ("99da2ad9ab56cf0f4f103b110acb64b3", "53288d754ce39bcfdf3a67ce0c80f2dc"),
    "white_ss1": ("4eae50eac01503c50ee4f57394da71ac", "3d84fd814bc2211e5146af2f72ceb623"),
}


@pytest.mark.parametrize("effects", [None, CameraEffects.ideal()], ids=["None", "ideal"])
def test_ideal_camera_is_bit_identical_to_the_simulator_before_effects(effects):
    rig, objs, proj = _reference_scene()
    a = simulate_shot(rig, objs, ShotOptions(supersample=2, noise=True, blur_sigma=0.8, seed=7, effects=effects), projector=proj)
    b = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False, seed=1, effects=effects))
    assert _digest(a) == _OLD_DIGESTS["pattern_ss2_noise_blur"]
    assert _digest(b) == _OLD_DIGESTS["white_ss1"]


def test_default_effects_change_the_image_but_not_the_truth():
    rig, objs, proj = _reference_scene()
    ideal = simulate_shot(rig, objs, ShotOptions(supersample=2, seed=7, effects=None), projector=proj)
    real = simulate_shot(rig, objs, ShotOptions(supersample=2, seed=7), projector=proj)  # default: effects on
    assert real.effects == CameraEffects() and ideal.effects is None
    assert not np.array_equal(real.sensor_image, ideal.sensor_image)
    assert sorted(real.truth) == sorted(ideal.truth)
    for k in ideal.truth:  # truth stays diffuse-only and effect-free
        assert np.array_equal(real.truth[k], ideal.truth[k], equal_nan=ideal.truth[k].dtype.kind == "f"), k
    # seeded: same seed, same image; another seed, another noise draw
    again = simulate_shot(rig, objs, ShotOptions(supersample=2, seed=7), projector=proj)
    other = simulate_shot(rig, objs, ShotOptions(supersample=2, seed=8), projector=proj)
    assert np.array_equal(real.sensor_image, again.sensor_image)
    assert not np.array_equal(real.sensor_image, other.sensor_image)


def test_ideal_flags():
    assert CameraEffects.ideal().is_ideal and not CameraEffects().is_ideal
    # gloss with every coefficient 0 adds nothing: still the ideal camera
    flat = only(specular=True, materials=(("lambertian", Gloss(0.0, 1.0)),), default_material="lambertian")
    assert flat.is_ideal and not flat.has_gloss
    for kw in ({"exposure_right": 0.9}, {"colour_gain_right": (1.0, 1.0, 1.01)}, {"vignetting_stops": 0.1},
               {"psf_sigma_px": 0.5}, {"jpeg_quality": 95}, {"specular": True}):
        assert not only(**kw).is_ideal, kw


# -- the two halves: exposure and colour -----------------------------------------------
def test_right_view_gain_equals_the_exposure_and_colour_cast():
    rig = eighth_rig()
    objs = grey_wall(0.5)
    ideal = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=True, seed=2, effects=None))
    fx = only(exposure_right=0.88, colour_gain_right=(0.95, 1.0, 1.05))
    shot = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=True, seed=2, effects=fx))
    l0, r0 = views(rig, ideal)
    l1, r1 = views(rig, shot)
    assert np.array_equal(l0, l1)  # the left view is the reference
    m = shot.truth["mask_right"]
    assert m.all()
    ratio = r1[m].mean(axis=0) / r0[m].mean(axis=0)
    # 39 528 pixels at ~90 DN with ~1.7 DN noise: the mean ratio is known to ~1e-4
    assert ratio == pytest.approx(0.88 * np.array([0.95, 1.0, 1.05]), abs=2e-3)
    assert np.allclose(fx.view_gain("right"), 0.88 * np.array([0.95, 1.0, 1.05]))
    assert np.array_equal(CameraEffects().view_gain("left"), np.ones(3))


def test_default_right_view_is_darker_and_bluer():
    rig = eighth_rig()
    shot = simulate_shot(rig, grey_wall(0.5), ShotOptions(supersample=1, noise=False, effects=dataclasses.replace(CameraEffects(), jpeg_quality=None, vignetting_stops=0.0)))
    left, right = views(rig, shot)
    ratio = right.reshape(-1, 3).mean(0) / left.reshape(-1, 3).mean(0)  # symmetric rig and scene
    assert ratio == pytest.approx(0.88 * np.array([0.96, 1.0, 1.04]), abs=3e-3)


# -- vignetting ------------------------------------------------------------------------
def test_vignetting_falls_to_the_stated_corner_attenuation_about_the_principal_point():
    base = eighth_rig()
    w, h = base.left.size
    # shift the left principal point: vignetting must follow the optical centre
    K = base.left.K.copy()
    K[0, 2] += 25.0
    K[1, 2] -= 15.0
    rig = StereoRig(CameraModel(K, base.left.dist, (w, h)), base.right, base.T_right_left, base.split, base.T_rig_left)
    objs = grey_wall(0.7)
    ideal = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False, effects=None))
    shot = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False, effects=only(vignetting_stops=0.5)))
    for view, cam in ((0, rig.left), (1, rig.right)):
        dn = views(rig, ideal)[view]
        ratio = views(rig, shot)[view] / dn
        cx, cy = cam.K[0, 2], cam.K[1, 2]
        expected = vignetting_factor(cam.size, (cx, cy), 0.5)[..., None]
        # exact up to the uint8 rounding of both images (~165-180 DN here)
        assert np.all(np.abs(ratio - expected) <= (0.5 + 0.5 * expected) / dn + 1e-12)
        # the farthest corner from the principal point gets exactly 2^-0.5
        corners = [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1)]
        r, c = max(corners, key=lambda rc: (rc[1] - cx) ** 2 + (rc[0] - cy) ** 2)
        assert expected[r, c] == pytest.approx(2**-0.5, abs=1e-12)
        assert ratio[r, c].mean() == pytest.approx(2**-0.5, abs=0.006)
        centre = ratio[int(round(cy)), int(round(cx))]
        assert centre == pytest.approx(np.ones(3), abs=0.006)
    assert CameraEffects().vignetting_stops == 0.5


# -- the lens PSF ----------------------------------------------------------------------
def _step_albedo(points):
    g = np.where(np.asarray(points)[:, 0] < 0.0, 0.15, 0.85)
    return np.repeat(g[:, None], 3, axis=1)


def _edge_width_sq(view, rows):
    """Second moment (px^2) of the line spread across the vertical edge, per row, mean."""
    out = []
    for r in rows:
        esf = view[r, :, 1]
        lsf = np.diff(esf)
        c = int(np.argmax(np.abs(lsf)))
        win = lsf[c - 7 : c + 8]
        x = np.arange(len(win))
        mu = (win * x).sum() / win.sum()
        out.append((win * (x - mu) ** 2).sum() / win.sum())
    return float(np.mean(out))


def test_psf_blurs_by_its_sigma_and_folds_with_blur_sigma():
    rig = quarter_rig()
    objs = [(flat_plate(900, 900, albedo=_step_albedo, material="lambertian"), translation(0, 0, 1250))]
    kw = dict(supersample=4, noise=False)
    ideal = simulate_shot(rig, objs, ShotOptions(effects=None, **kw))
    psf = simulate_shot(rig, objs, ShotOptions(effects=only(psf_sigma_px=1.0), **kw))
    rows = range(200, 290, 6)
    var0 = _edge_width_sq(views(rig, ideal)[0], rows)
    var1 = _edge_width_sq(views(rig, psf)[0], rows)
    # variances add: PSF sigma^2 = 1 px^2 on top of the box-integrated pixel
    assert var1 - var0 == pytest.approx(1.0, abs=0.1)
    # the PSF is the same Gaussian as blur_sigma, and the two combine in quadrature
    same = simulate_shot(rig, objs, ShotOptions(effects=None, blur_sigma=1.0, **kw))
    assert np.array_equal(psf.sensor_image, same.sensor_image)
    both = simulate_shot(rig, objs, ShotOptions(effects=only(psf_sigma_px=0.6), blur_sigma=0.8, **kw))
    assert np.abs(both.sensor_image.astype(int) - same.sensor_image.astype(int)).max() <= 1


# -- JPEG ------------------------------------------------------------------------------
def test_jpeg_round_trip_of_the_sensor_image():
    rig = quarter_rig()
    objs = [(flat_plate(900, 900, albedo=TextureAlbedo(seed=1)), translation(0, 0, 1250))]
    raw = simulate_shot(rig, objs, ShotOptions(supersample=1, seed=4, effects=None))
    jpg = simulate_shot(rig, objs, ShotOptions(supersample=1, seed=4, effects=only(jpeg_quality=92)))
    assert jpg.sensor_image.shape == raw.sensor_image.shape == (486, 648, 3)
    assert jpg.sensor_image.dtype == np.uint8
    assert np.array_equal(jpg.sensor_image, jpeg_roundtrip(raw.sensor_image, 92))
    # by hand: OpenCV encode + decode, BGR at the I/O boundary
    ok, buf = cv2.imencode(".jpg", raw.sensor_image[:, :, ::-1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 92])
    assert ok and np.array_equal(jpg.sensor_image, cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1])
    diff = np.abs(jpg.sensor_image.astype(float) - raw.sensor_image)
    mse = float((diff**2).mean())
    psnr = 10 * np.log10(255.0**2 / mse)
    # quality 92 on a noisy speckled grey plate: ~2 DN, ~38 dB (measured 2.1 DN,
    # 38.2 dB; at full resolution 1.6 DN, 41 dB; with the colour grating, whose
    # chroma the 4:2:0 subsampling smears, 2.4 DN, 36.6 dB)
    assert 1.0 < diff.mean() < 3.5 and 34.0 < psnr < 43.0
    worse = jpeg_roundtrip(raw.sensor_image, 50)
    assert np.abs(worse.astype(float) - raw.sensor_image).mean() > diff.mean()


# -- specular highlights ---------------------------------------------------------------
def _mirror_point_pixel(cam, T_rig_cam, z_plane, light):
    """Pixel where a plane z = z_plane (normal along rig z) reflects ``light`` into the camera."""
    eye = T_rig_cam[:3, 3]
    eye_m = eye.copy()
    eye_m[2] = 2 * z_plane - eye[2]  # the camera's mirror image behind the plane
    s = (z_plane - light[2]) / (eye_m[2] - light[2])
    p = light + s * (eye_m - light)
    T_cam_rig = np.linalg.inv(T_rig_cam)
    return cam.project((T_cam_rig[:3, :3] @ p + T_cam_rig[:3, 3])[None])[0], p


def test_specular_highlight_sits_at_the_mirror_point_of_each_view():
    rig = quarter_rig()
    z = 1250.0
    objs = [(flat_plate(300, 300, albedo=(0.4, 0.4, 0.4), material="test_gloss"), translation(0, 0, z))]
    gloss = Gloss(0.5, 5000.0)  # a compact lobe: half width ~1 deg, ~20 px here
    fx = only(specular=True, materials=(("test_gloss", gloss),), default_material="test_gloss")
    shot = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False, effects=fx))
    ideal = simulate_shot(rig, objs, ShotOptions(supersample=1, noise=False, effects=None))
    light = np.zeros(3)  # the default white flash sits at the rig origin
    plate_x = []
    for i, (name, cam, T) in enumerate((("left", rig.left, rig.T_rig_left), ("right", rig.right, rig.T_rig_right))):
        view = views(rig, shot)[i] / 255.0
        t = shot.truth
        k = t[f"shading_{name}"] - 0.25  # flash light, white flash, no shadows here
        weight = (view - t[f"albedo_{name}"] * t[f"shading_{name}"][..., None])[..., 1] / k
        expected_uv, p = _mirror_point_pixel(cam, T, z, light)
        plate_x.append(p[0])
        peak = np.nanmax(weight)
        assert peak == pytest.approx(gloss.coefficient, rel=0.01)
        sel = weight > 0.5 * peak
        vv, uu = np.nonzero(sel)
        w = weight[sel]
        centroid = np.array([(uu * w).sum() / w.sum(), (vv * w).sum() / w.sum()])
        assert np.linalg.norm(centroid - expected_uv) < 0.1, (name, centroid, expected_uv)  # measured 0.012
        # half width on the plate ~ z * arccos(0.5^(1/s)) -> pixels
        hw_px = z * np.arccos(0.5 ** (1 / gloss.shininess)) * cam.fx / z
        assert np.sqrt(sel.sum() / np.pi) == pytest.approx(hw_px, rel=0.02)
        # the truth stays diffuse: same albedo and shading as the ideal camera's
        assert np.array_equal(t[f"albedo_{name}"], ideal.truth[f"albedo_{name}"])
        assert np.array_equal(t[f"shading_{name}"], ideal.truth[f"shading_{name}"], equal_nan=True)
    # view-dependent: the flash midway between the cameras, at their height, puts each
    # view's highlight halfway to its camera: 99 mm apart on the plate
    assert plate_x[0] == pytest.approx(rig.T_rig_left[0, 3] / 2, abs=1e-9)
    assert plate_x[1] == pytest.approx(rig.T_rig_right[0, 3] / 2, abs=1e-9)


def test_material_classes_set_the_gloss():
    rig = eighth_rig()
    kw = dict(supersample=1, noise=False)
    fx = dataclasses.replace(CameraEffects.ideal(), specular=True)
    matte = simulate_shot(rig, grey_wall(0.5), ShotOptions(effects=fx, **kw))
    assert np.array_equal(matte.sensor_image, simulate_shot(rig, grey_wall(0.5), ShotOptions(effects=None, **kw)).sensor_image)
    metal = [(flat_plate(900, 900, albedo=(0.5, 0.5, 0.5)), translation(0, 0, 1250))]  # no class: painted metal
    shiny = simulate_shot(rig, metal, ShotOptions(effects=fx, **kw))
    gain = views(rig, shiny)[0].max() / views(rig, matte)[0].max()
    g = MATERIALS["painted_metal"]
    # brightest pixel ~ at the mirror point, ~1.25 m away, flash 0.75, ambient 0.25:
    # (albedo (ambient + flash) + ks flash) / (albedo (ambient + flash)), 1.09 for 6 % gloss
    assert gain == pytest.approx(1 + g.coefficient * 0.75 / (0.5 * 1.0), abs=0.01)
    assert chessboard().metadata["material"] == "matte_paper"
    with pytest.raises(InputError, match="material 'velvet': unknown class"):
        simulate_shot(rig, [(flat_plate(material="velvet"), translation(0, 0, 1250))], ShotOptions(effects=fx, **kw))


# -- the record of a simulated folder --------------------------------------------------
def test_simulate_to_folder_records_the_effects(tmp_path):
    rig = eighth_rig()
    s = simulate_to_folder("plate", tmp_path / "real", SimulateOptions(supersample=1), rig=rig)
    assert s["camera_effects"] == CameraEffects().to_dict()
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["rig.yaml", "shot.png", "truth.npz"]
    fs = cv2.FileStorage(str(tmp_path / "real" / "rig.yaml"), cv2.FILE_STORAGE_READ)
    try:
        assert fs.getNode("sim_ideal_camera").real() == 0
        assert fs.getNode("sim_exposure_right").real() == pytest.approx(0.88)
        assert np.allclose(fs.getNode("sim_colour_gain_right").mat().ravel(), [0.96, 1.0, 1.04])
        assert fs.getNode("sim_vignetting_stops").real() == pytest.approx(0.5)
        assert fs.getNode("sim_psf_sigma_px").real() == pytest.approx(0.7)
        assert fs.getNode("sim_jpeg_quality").real() == 92
        assert fs.getNode("sim_default_material").string() == "painted_metal"
        assert np.allclose(fs.getNode("sim_gloss_painted_metal").mat().ravel(), [0.06, 200.0])
    finally:
        fs.release()
    assert StereoRig.load(tmp_path / "real" / "rig.yaml").left.size == rig.left.size
    s = simulate_to_folder("plate", tmp_path / "ideal", SimulateOptions(supersample=1, effects=None), rig=rig)
    assert s["camera_effects"] is None
    fs = cv2.FileStorage(str(tmp_path / "ideal" / "rig.yaml"), cv2.FILE_STORAGE_READ)
    try:
        assert fs.getNode("sim_ideal_camera").real() == 1 and fs.getNode("sim_exposure_right").empty()
    finally:
        fs.release()
    with pytest.raises(InputError, match="effects: expected a CameraEffects"):
        simulate_to_folder("plate", tmp_path / "x", SimulateOptions(effects="on"), rig=rig)  # type: ignore[arg-type]


# -- values and errors -----------------------------------------------------------------
def test_to_dict_round_trip():
    fx = CameraEffects(exposure_right=0.8, jpeg_quality=None, materials={"a": Gloss(0.1, 50.0)}, default_material="a")
    assert CameraEffects.from_dict(fx.to_dict()) == fx
    assert CameraEffects.from_dict({}) == CameraEffects()
    assert fx.gloss(None) == Gloss(0.1, 50.0) == fx.gloss("a")


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"exposure_right": 0.0}, "exposure_right"),
        ({"exposure_right": float("nan")}, "exposure_right"),
        ({"colour_gain_right": (1.0, 1.0)}, "colour_gain_right"),
        ({"colour_gain_right": (1.0, 1.0, 9.0)}, "colour_gain_right"),
        ({"vignetting_stops": -0.1}, "vignetting_stops"),
        ({"psf_sigma_px": -1.0}, "psf_sigma_px"),
        ({"jpeg_quality": 0}, "jpeg_quality"),
        ({"jpeg_quality": 101}, "jpeg_quality"),
        ({"jpeg_quality": 90.5}, "jpeg_quality"),
        ({"jpeg_quality": True}, "jpeg_quality"),
        ({"materials": (("a", Gloss(0.1, 2.0)), ("a", Gloss(0.1, 2.0))), "default_material": "a"}, "duplicate"),
        ({"materials": (("a", (0.1, 2.0)),), "default_material": "a"}, r"materials\['a'\]: expected a Gloss"),
        ({"materials": (1, 2)}, "materials: expected"),
        ({"default_material": "velvet"}, "default_material"),
    ],
)
def test_effects_validation(kw, match):
    with pytest.raises(InputError, match=match):
        CameraEffects(**kw)


def test_other_errors():
    with pytest.raises(InputError, match="gloss coefficient"):
        Gloss(1.5, 10.0)
    with pytest.raises(InputError, match="gloss shininess"):
        Gloss(0.1, 0.5)
    with pytest.raises(InputError, match="unknown keys gamma"):
        CameraEffects.from_dict({"gamma": 2.2})
    with pytest.raises(InputError, match="materials must map"):
        CameraEffects.from_dict({"materials": {"a": [0.1]}})
    with pytest.raises(InputError, match="material 'x': unknown class"):
        CameraEffects().gloss("x")
    with pytest.raises(InputError, match="view: expected"):
        CameraEffects().view_gain("middle")
    with pytest.raises(InputError, match=r"image: expected \(H, W, 3\) uint8"):
        jpeg_roundtrip(np.zeros((4, 4, 3), np.uint16), 90)
    with pytest.raises(InputError, match="quality"):
        jpeg_roundtrip(np.zeros((4, 4, 3), np.uint8), 0)
    with pytest.raises(InputError, match="effects: expected a CameraEffects"):
        simulate_shot(eighth_rig(), grey_wall(), ShotOptions(effects="on"))  # type: ignore[arg-type]
    with pytest.raises(InputError, match="material: expected"):
        flat_plate(material="")
