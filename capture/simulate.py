"""The scene simulator: one flash shot through the virtual prism rig, with ground truth.

Image model, speed notes and the folder contract: docs/capture.md ("The scene
simulator"). The truth maps are diffuse-only and free of camera effects.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture._render_kernels import (
    box_mean,
    gain_vignetting,
    scatter_truth,
    shade_colour,
    shade_colour_specular,
    specular_weight,
)
from prism3d.capture.camera_effects import CameraEffects, jpeg_roundtrip
from prism3d.capture.camouflage import CamouflageField
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.projector import (
    Projector,
    working_distance_mm,
)
from prism3d.capture.render import (
    CameraHits,
    RaycastRenderer,
    SensorNoise,
    gaussian_blur,
    quantize,
)
from prism3d.capture.rig import (
    CameraModel,
    Rectification,
    StereoRig,
    compute_rectification,
    paper_rig,
)
from prism3d.capture.scenes import (
    BoardPoseOptions,
    TextureAlbedo,
    calibration_board_poses,
    chessboard,
    chessboard_corners,
    flat_plate,
    translation,
    turntable_poses,
)
from prism3d.checks import check_choice, check_in_range, check_positive, check_seed
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path, atomic_write_text, staged_folder
from prism3d.io.images import write_image
from prism3d.io.ply import write_ply

__all__ = [
    "TRUTH_SCHEMA_VERSION",
    "Projector",
    "Shot",
    "ShotOptions",
    "SimulateOptions",
    "simulate_shot",
    "simulate_to_folder",
    "working_distance_mm",
    "effects_entries",
]

#: Version of the truth ``.npz`` / ``poses.json`` layout.
TRUTH_SCHEMA_VERSION = 1

ProgressFn = Callable[[int, int, str], None]

#: Shadow rays start this far (mm) along the ray, so a surface does not shadow itself.
SHADOW_EPS_MM = 1e-3
#: Side of the accuracy-test plate, mm (the paper's Table I: a 30 x 30 cm plate).
PLATE_SIZE_MM = 300.0
#: Camouflage patch size on the plate, mm (a few patches per view field).
PLATE_CAMO_PATCH_MM = 60.0
#: A scene target's camouflage: about this many patches along its longest side ...
TARGET_CAMO_PATCHES = 6
#: ... but patches no smaller than this, mm (small targets stay legibly painted).
MIN_TARGET_CAMO_PATCH_MM = 10.0
#: Shots per kind when ``views`` is None: 1 plate, 5 board poses (paper: 3-5), 8 turntable views.
DEFAULT_VIEWS = {"plate": 1, "calib": 5, "scene": 8}
#: Shot k of a folder is seeded ``seed * SHOT_SEED_STRIDE + k``: distinct, reproducible.
SHOT_SEED_STRIDE = 1000


# -- options ---------------------------------------------------------------------------
#: Largest extra optical blur, px: beyond it a view is a smear (and OpenCV's kernel
#: size overflows near 1e9).
MAX_BLUR_SIGMA_PX = 100.0
#: Most shots in one simulated folder: a turntable has 8, a calibration set 10-50.
MAX_VIEWS = 1000
#: Most inner corners along a simulated board's side (OpenCV's boards: 5-20).
MAX_BOARD_CORNERS = 100
#: Largest simulated board square, mm (a 100 m square is no board).
MAX_SQUARE_MM = 1e5


def _check_blur(value: float) -> float:
    return check_in_range(value, "blur_sigma", 0.0, MAX_BLUR_SIGMA_PX)


@dataclass(frozen=True)
class ShotOptions:
    """How one flash shot is lit, sampled and recorded (image model: docs/capture.md)."""

    ambient: float = 0.25
    """Uniform shadowless light level, in [0, 10]."""
    flash: float = 0.75
    """Flash strength at the projector's reference distance, in [0, 10]."""
    supersample: int = 2
    """Colour rays per pixel along each axis, box-averaged, in [1, 8] (2 smooths edges)."""
    noise: bool | SensorNoise = True
    """Sensor noise: True = ``SensorNoise()``, False = none, or a ``SensorNoise``."""
    blur_sigma: float = 0.0
    """Extra Gaussian blur of each view, px, before noise (``hypot`` with the effects' PSF)."""
    seed: int = 0
    """Seed of the noise generator: same seed, same image."""
    background: float = 0.0
    """Image value where no surface is hit, in [0, 1] (0 = black)."""
    effects: CameraEffects | None = field(default_factory=CameraEffects)
    """Real-camera effects (on by default); None or ``CameraEffects.ideal()`` = the ideal camera."""

    def __post_init__(self) -> None:
        setv = object.__setattr__
        setv(self, "ambient", check_in_range(self.ambient, "ambient", 0.0, 10.0))
        setv(self, "flash", check_in_range(self.flash, "flash", 0.0, 10.0))
        setv(self, "background", check_in_range(self.background, "background", 0.0, 1.0))
        ss = int(self.supersample)
        if ss != self.supersample or ss < 1 or ss > 8:
            raise InputError(f"supersample: expected an integer in [1, 8], got {self.supersample!r}")
        setv(self, "supersample", ss)
        setv(self, "blur_sigma", _check_blur(self.blur_sigma))
        setv(self, "seed", check_seed(self.seed))
        if not (self.noise is None or isinstance(self.noise, (bool, SensorNoise))):
            raise InputError(f"noise: expected a bool or SensorNoise, got {type(self.noise).__name__}")
        _check_effects(self.effects)

    @property
    def noise_model(self) -> SensorNoise | None:
        """The sensor noise model, None for a noise-free shot."""
        if self.noise is True:
            return SensorNoise()
        return self.noise if isinstance(self.noise, SensorNoise) else None

    @property
    def real_effects(self) -> CameraEffects | None:
        """The camera effects, None when they are all neutral (the ideal camera)."""
        return None if self.effects is None or self.effects.is_ideal else self.effects


@dataclass(frozen=True)
class SimulateOptions:
    """What ``prism3d simulate plate|calib|scene`` renders (folder contract: docs/capture.md)."""

    pattern: bool | None = None
    """Project the grating; None = on for plate and scene, off for calib (stripes defeat corners)."""
    camouflage: bool = True
    """Plate: woodland camouflage (else grey speckle); scene: paint targets that have no albedo."""
    views: int | None = None
    """Number of shots; None = 1 plate, 5 board poses, 8 turntable views (45 deg steps)."""
    seed: int = 0
    """Seeds poses, textures, the pattern order and the noise: same seed, same files."""
    noise: bool = True
    """Sensor noise on/off."""
    supersample: int = 2
    """Colour supersampling factor (see ``ShotOptions.supersample``)."""
    compress: bool = True
    """Deflate the truth ``.npz`` (~60x smaller for ~0.3 s more per 5 MP shot)."""
    board: tuple[int, int] = (9, 6)
    """calib: inner corners (cols, rows); a denser board pins the principal point better."""
    square_mm: float = 25.0
    """calib: chessboard square size, mm."""
    blur_sigma: float = 0.0
    """Extra Gaussian optical blur of each view, px (``hypot`` with the effects' PSF)."""
    effects: CameraEffects | None = field(default_factory=CameraEffects)
    """Real-camera effects; None or ``CameraEffects.ideal()`` = the ideal camera."""

    def __post_init__(self) -> None:
        _check_effects(self.effects)
        v = self.views
        if v is not None and (int(v) != v or not 1 <= int(v) <= MAX_VIEWS):
            raise InputError(f"views: expected an integer in [1, {MAX_VIEWS}], got {v!r}")
        b = self.board
        if len(b) != 2 or any(int(x) != x or not 2 <= int(x) <= MAX_BOARD_CORNERS for x in b):
            raise InputError(f"board: expected (cols, rows) inner corners in [2, {MAX_BOARD_CORNERS}], got {b!r}")
        object.__setattr__(self, "square_mm", check_in_range(check_positive(self.square_mm, "square_mm"),
                                                             "square_mm", 0.0, MAX_SQUARE_MM))
        object.__setattr__(self, "blur_sigma", _check_blur(self.blur_sigma))
        object.__setattr__(self, "seed", check_seed(self.seed))
        self.shot_options(0)  # validates supersample and noise now, not after the first file

    def shot_options(self, seed: int) -> ShotOptions:
        """The options of one shot of the folder, noise seeded by ``seed``."""
        return ShotOptions(supersample=self.supersample, noise=self.noise, blur_sigma=self.blur_sigma,
                           seed=seed, effects=self.effects)


def _check_effects(effects: object) -> None:
    if effects is not None and not isinstance(effects, CameraEffects):
        raise InputError(f"effects: expected a CameraEffects or None, got {type(effects).__name__}")


# -- projector -------------------------------------------------------------------------


# -- one shot --------------------------------------------------------------------------
@dataclass(eq=False)
class Shot:
    """A simulated flash shot: ``sensor_image`` (H_s, W_s, 3) uint8 as the camera
    records it (views joined, mirror flips applied), ``truth`` (see
    :func:`simulate_shot`), the ``rectification`` of ``disparity_rect`` and the
    camera ``effects`` applied (None = ideal)."""

    sensor_image: NDArray[np.uint8]
    truth: dict[str, NDArray]
    rectification: Rectification
    effects: CameraEffects | None = None


def _illumination(
    renderer: RaycastRenderer,
    hits: CameraHits,
    projector: Projector,
    flash: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """``(k, rgb, white)`` at the hits: flash factor after the shadow test (0 in
    shadow), projector colour and frustum flag (rig frame = world)."""
    k, rgb, white, lit = projector._light(hits.points, hits.normals, flash)
    li = np.flatnonzero(lit)
    if len(li):
        vis = renderer.visible_from(hits.points, projector.position_rig, tol_mm=SHADOW_EPS_MM, subset=li)
        k[li[~vis]] = 0.0
    k[~lit] = 0.0
    return k, rgb, white


def gloss_table(
    renderer: RaycastRenderer, effects: CameraEffects
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(ks, shininess)`` ``(n_objects,)`` of the scene's meshes (``metadata["material"]``)."""
    ks = np.zeros(renderer.n_objects)
    shin = np.ones(renderer.n_objects)
    if effects.specular:
        for i, mesh in enumerate(renderer.meshes):
            g = effects.gloss(mesh.metadata.get("material"))
            ks[i], shin[i] = g.coefficient, g.shininess
    return ks, shin


def _shade(
    pix: NDArray[np.int64],
    alb: NDArray,
    k: NDArray[np.float64],
    rgb: NDArray[np.float64],
    ambient: float,
    img: NDArray,
    spec: NDArray[np.float64] | None,
    first: int = 0,
    row_len: int = 1,
    ss: int = 1,
    width: int = 1,
) -> None:
    """Shade hits into ``img`` rows ``pix``: clipped diffuse when ``spec`` is None,
    else diffuse + highlight (``spec``: per output pixel; ray ``first + pix`` of an
    ``ss``-supersampled camera with ``row_len`` rays per row), unclipped."""
    if spec is None:
        shade_colour(pix, alb, k, rgb, ambient, img)
    else:
        shade_colour_specular(pix, alb, k, rgb, spec, first, row_len, ss, width, ambient, img)


_TRUTH_KEYS = ("mask", "albedo", "shading", "illumination", "normals", "object_id")


def render_view(
    renderer: RaycastRenderer,
    cam: CameraModel,
    T_rig_cam: NDArray,
    projector: Projector,
    opts: ShotOptions,
    gloss: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.float64], dict[str, NDArray]]:
    """Clean colour image ``(H, W, 3)`` and truth maps of one view; ``gloss`` None:
    ideal, in [0, 1]; else ``(ks, shininess)`` per object: highlight added, unclipped.
    """
    spec = None if gloss is None else np.zeros(cam.size[0] * cam.size[1])
    img1, truth = _truth_pass(renderer, cam, T_rig_cam, projector, opts, gloss, spec)
    if img1 is not None:
        return img1, truth
    return _colour_pass(renderer, cam, T_rig_cam, projector, opts, spec), truth


def _truth_pass(
    renderer: RaycastRenderer,
    cam: CameraModel,
    T_rig_cam: NDArray,
    projector: Projector,
    opts: ShotOptions,
    gloss: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
    spec: NDArray[np.float64] | None,
) -> tuple[NDArray[np.float64] | None, dict[str, NDArray]]:
    """One exact ray per output pixel centre, streamed in bands of rows: the truth
    maps, the highlight weights ``spec`` (filled in place) and, at supersample 1,
    the colour image (else None)."""
    w, h = cam.size
    n = h * w
    depth = np.full(n, np.nan, dtype=np.float32)
    mask = np.zeros(n, dtype=bool)
    albedo = np.zeros((n, 3), dtype=np.float32)
    shading = np.full(n, np.nan, dtype=np.float32)
    illum = np.full((n, 3), np.nan, dtype=np.float32)
    normals = np.full((n, 3), np.nan, dtype=np.float32)
    object_id = np.full(n, -1, dtype=np.int32)
    R = np.ascontiguousarray(T_rig_cam[:3, :3])
    eye = np.ascontiguousarray(T_rig_cam[:3, 3], dtype=np.float64)
    src = projector.position_rig
    one_ray = opts.supersample == 1
    img1 = np.full((n, 3), float(opts.background)) if one_ray else np.zeros((0, 3))

    def truth_band(s: int, e: int, hb: CameraHits) -> None:
        if len(hb.index) == 0:
            return
        alb = renderer.albedo(hb, np.float32)
        k, rgb, white = _illumination(renderer, hb, projector, opts.flash)
        if spec is not None and gloss is not None and gloss[0].max() > 0:
            specular_weight(
                hb.index, hb.points, hb.normals, hb.object_id, eye, src, gloss[0], gloss[1], spec
            )
        scatter_truth(
            hb.index, hb.t, hb.z_cam, alb, k, rgb, white, hb.normals, R, hb.object_id, opts.ambient,
            depth, mask, albedo, shading, illum, normals, object_id,
        )
        if one_ray:
            _shade(hb.index, alb, k, rgb, opts.ambient, img1, spec, 0, w, 1, w)

    renderer.stream_camera(cam, T_rig_cam, truth_band)
    truth = {
        "depth_mm": depth.reshape(h, w),
        "mask": mask.reshape(h, w),
        "albedo": albedo.reshape(h, w, 3),
        "shading": shading.reshape(h, w),
        "illumination": illum.reshape(h, w, 3),
        "normals": normals.reshape(h, w, 3),
        "object_id": object_id.reshape(h, w),
    }
    return (img1.reshape(h, w, 3) if one_ray else None), truth


def _colour_pass(
    renderer: RaycastRenderer,
    cam: CameraModel,
    T_rig_cam: NDArray,
    projector: Projector,
    opts: ShotOptions,
    spec: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """The supersampled colour image: rays streamed in bands of whole output rows,
    each band shaded and box-averaged at once (memory stays ~one band)."""
    w, h = cam.size
    ss = opts.supersample
    cs = cam.scaled(ss)
    ws = cs.size[0]
    img = np.empty((h, w, 3))
    band_img = np.empty((0, 3), dtype=np.float32)

    def shade_band(s: int, e: int, hb: CameraHits) -> None:
        nonlocal band_img
        if len(band_img) < e - s:
            band_img = np.empty((e - s, 3), dtype=np.float32)
        b = band_img[: e - s]
        b.fill(opts.background)
        if len(hb.index):
            alb_s = renderer.albedo(hb, np.float32)
            k_s, rgb_s, _ = _illumination(renderer, hb, projector, opts.flash)
            _shade(hb.index - s, alb_s, k_s, rgb_s, opts.ambient, b, spec, s, ws, ss, w)
        r0 = s // ws // ss
        r1 = e // ws // ss
        box_mean(b.reshape(-1, ws, 3), ss, img[r0:r1])

    renderer.stream_camera(cs, T_rig_cam, shade_band, rows_multiple=ss)
    return img


def simulate_shot(
    rig: StereoRig,
    objects: Sequence[tuple[SceneMesh, NDArray]],
    options: ShotOptions | None = None,
    *,
    projector: Projector | None = None,
    rectification: Rectification | None = None,
    renderer: RaycastRenderer | None = None,
) -> Shot:
    """Simulate one flash photograph through the prism rig, with exact ground truth.

    ``objects``: (SceneMesh, ``T_rig_obj`` (4, 4)) pairs; ``options`` None =
    ``ShotOptions()``; ``projector`` default a white flash at the rig origin;
    ``rectification`` (grid of ``disparity_rect``) default ``compute_rectification(rig)``;
    ``renderer``: one already built for ``objects``, to reuse.

    ``Shot.truth`` per view ``<v>`` (left/right, view pixels): ``depth_<v>_mm`` (H, W)
    float32 NaN = no surface, ``mask_<v>`` bool, ``albedo_<v>`` (H, W, 3) float32,
    ``shading_<v>`` (H, W) float32, ``illumination_<v>`` (H, W, 3) float32,
    ``normals_<v>`` (H, W, 3) float32 (camera frame), ``object_id_<v>`` int32; plus
    ``disparity_rect``, ``depth_rect_mm`` (rectified-left grid), ``R1 R2 P1 P2 Q``,
    ``T_rig_left``, ``T_right_left``, ``projector_T_rig_proj``.
    """
    if not isinstance(rig, StereoRig):
        raise InputError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    opts = ShotOptions() if options is None else options
    if not isinstance(opts, ShotOptions):
        raise InputError(f"options: expected a ShotOptions or None, got {type(opts).__name__}")
    if projector is None:
        projector = Projector.for_rig(rig, pattern=False)
    elif not isinstance(projector, Projector):
        raise InputError(f"projector: expected a Projector or None, got {type(projector).__name__}")
    if renderer is None:
        renderer = RaycastRenderer(objects)
    rect = rectification if rectification is not None else compute_rectification(rig)
    views, truth = _render_views(renderer, rig, projector, opts)
    truth.update(_rectified_truth(renderer, rig, rect))
    truth["projector_T_rig_proj"] = projector.T_rig_proj.copy()
    return Shot(_sensor_image(rig, views, opts), truth, rect, opts.effects)


def _render_views(
    renderer: RaycastRenderer, rig: StereoRig, projector: Projector, opts: ShotOptions
) -> tuple[list[NDArray[np.float64]], dict[str, NDArray]]:
    """Both views, each with its optics (gain, vignetting, blur) applied, and their truth."""
    fx = opts.real_effects
    gloss = None if fx is None else gloss_table(renderer, fx)
    truth: dict[str, NDArray] = {}
    views = []
    for name, cam, T in (("left", rig.left, rig.T_rig_left), ("right", rig.right, rig.T_rig_right)):
        img, t = render_view(renderer, cam, T, projector, opts, gloss)
        sigma = opts.blur_sigma
        if fx is not None:
            apply_view_optics(img, cam, fx, name)
            sigma = float(np.hypot(opts.blur_sigma, fx.psf_sigma_px))
        if sigma > 0:
            img = gaussian_blur(img, sigma)
        views.append(img)
        truth[f"depth_{name}_mm"] = t["depth_mm"]
        for key in _TRUTH_KEYS:
            truth[f"{key}_{name}"] = t[key]
    return views, truth


def _rectified_truth(renderer: RaycastRenderer, rig: StereoRig, rect: Rectification) -> dict[str, NDArray]:
    """True disparity and depth on the rectified-left grid (depth-only rays), the
    rectification matrices and the rig poses."""
    R1_4 = np.eye(4)
    R1_4[:3, :3] = rect.R1
    T_rig_rect = rig.T_rig_left @ np.linalg.inv(R1_4)
    rw, rhh = rect.camera.size
    disp = np.full(rw * rhh, np.nan, dtype=np.float32)
    depth_rect = np.full(rw * rhh, np.nan, dtype=np.float32)
    fb = rect.focal_px * rect.baseline_mm

    def rect_band(s: int, e: int, hb: CameraHits) -> None:
        z = hb.t * hb.z_cam
        depth_rect[hb.index] = z
        with np.errstate(divide="ignore", invalid="ignore"):
            disp[hb.index] = fb / z

    renderer.stream_camera(rect.camera, T_rig_rect, rect_band)
    truth: dict[str, NDArray] = {"disparity_rect": disp.reshape(rhh, rw),
                                 "depth_rect_mm": depth_rect.reshape(rhh, rw)}
    for k in ("R1", "R2", "P1", "P2", "Q"):
        truth[k] = np.asarray(getattr(rect, k), dtype=np.float64)
    truth["T_rig_left"] = rig.T_rig_left.copy()
    truth["T_right_left"] = rig.T_right_left.copy()
    return truth


def _sensor_image(rig: StereoRig, views: list[NDArray[np.float64]], opts: ShotOptions) -> NDArray[np.uint8]:
    """Join the views on the sensor, add noise, quantise, then the JPEG round trip."""
    sensor = rig.split.join(views[0], views[1], fill=0.0)
    noise_model = opts.noise_model
    if noise_model is not None:
        rng = np.random.default_rng(opts.seed)
        sensor_u8 = quantize(noise_model.apply(sensor, rng))
    else:
        sensor_u8 = quantize(sensor * 255.0)
    fx = opts.real_effects
    if fx is not None and fx.jpeg_quality is not None:
        sensor_u8 = jpeg_roundtrip(sensor_u8, fx.jpeg_quality)
    return sensor_u8


def apply_view_optics(
    img: NDArray[np.float64], cam: CameraModel, fx: CameraEffects, view: str
) -> None:
    """In place: the view's RGB gain and vignetting about its principal point."""
    gain = fx.view_gain(view)
    cx, cy = float(cam.K[0, 2]), float(cam.K[1, 2])
    a, inv_rc2 = fx.vignetting_coefficients(cam.size, (cx, cy))
    if a > 0 or np.any(gain != 1.0):
        gain_vignetting(img, gain, cx, cy, a, inv_rc2)


# -- files -----------------------------------------------------------------------------
def write_npz(path: Path, arrays: dict[str, NDArray], *, compress: bool) -> None:
    """Write arrays as ``.npz`` atomically; ``compress``: deflate level 1 (sizes and
    times: docs/capture.md)."""
    import zipfile

    if not compress:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        return
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, a in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(a), allow_pickle=False)


def _write_target_ply(path: Path, mesh: SceneMesh) -> None:
    """The true target mesh as PLY: float64 xyz in mm, RGB, ``units mm``, ``up z``
    (the turntable frame), so ``prism3d features`` reads it as it is."""
    write_ply(path, mesh.vertices, colors=mesh.vertex_colors(), faces=mesh.faces, double=True,
              comments=[f"prism3d true target mesh ({mesh.name})", "units mm", "up z"])


def _has_own_albedo(mesh: SceneMesh) -> bool:
    return mesh.albedo_field is not None or mesh.vertex_albedo is not None


#: One planned shot: (png name, truth npz name, objects with rig-frame poses, extra truth).
_PlannedShot = tuple[str, str, list[tuple[SceneMesh, NDArray]], dict[str, NDArray]]


def _check_rig_target(kind: str, rig: StereoRig | None, target: SceneMesh | None) -> StereoRig:
    """The rig (None = :func:`paper_rig`), checked, and for ``scene`` the target mesh checked."""
    if rig is None:
        rig = paper_rig()
    if not isinstance(rig, StereoRig):
        raise InputError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    if kind == "scene":
        if target is None:
            raise InputError("simulate scene: a target mesh is required (target=SceneMesh)")
        if not isinstance(target, SceneMesh):
            raise InputError(f"target: expected a SceneMesh, got {type(target).__name__}")
    return rig


def simulate_to_folder(
    kind: str,
    out_dir: str | Path,
    options: SimulateOptions | None = None,
    *,
    rig: StereoRig | None = None,
    target: SceneMesh | None = None,
    progress: ProgressFn | None = None,
) -> dict[str, Any]:
    """Simulate shots and write them with their ground truth (``prism3d simulate``).

    ``kind``: ``plate`` (the 300 x 300 mm accuracy-test plate at the working distance),
    ``calib`` (a chessboard in varied poses) or ``scene`` (``target``, world = turntable
    frame z up, on a turntable); files per kind: docs/capture.md ("Simulated folders").
    ``out_dir`` is created; ``options`` None = ``SimulateOptions()``; ``rig`` default
    :func:`paper_rig`; ``progress(done, total, label)`` after each shot.

    Returns ``kind``, ``out_dir``, ``files`` (names written), ``n_shots``, ``pattern``,
    ``camera_effects`` (``CameraEffects.to_dict()``, None = ideal), ``seconds``.
    """
    check_choice(kind, "kind", ("plate", "calib", "scene"))
    opts = SimulateOptions() if options is None else options
    if not isinstance(opts, SimulateOptions):
        raise InputError(f"options: expected a SimulateOptions or None, got {type(opts).__name__}")
    t0 = time.perf_counter()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    rig = _check_rig_target(kind, rig, target)
    use_pattern = (kind != "calib") if opts.pattern is None else bool(opts.pattern)
    projector = Projector.for_rig(rig, pattern=use_pattern, seed=opts.seed if opts.seed else None)
    files: list[str] = []
    n = DEFAULT_VIEWS[kind] if opts.views is None else int(opts.views)
    with staged_folder(out) as stage:  # every file appears at the end, or none (disk full...)
        if kind == "plate":
            shots = _plan_plate(rig, n, opts)
        elif kind == "calib":
            shots = _plan_calib(rig, n, opts)
        else:
            shots = _plan_scene(rig, target, n, opts, stage)  # type: ignore[arg-type]  # validated above
            files += ["target.ply", "poses.json"]
        sim_entries = effects_entries(opts.effects, float(opts.blur_sigma))
        rig.save(stage / "rig.yaml", extra={"simulated": 1, **sim_entries})
        files.append("rig.yaml")
        files += _write_shots(stage, rig, shots, projector, opts, progress)
    return {
        "kind": kind,
        "out_dir": str(out),
        "files": sorted(files),
        "n_shots": len(shots),
        "pattern": use_pattern,
        "camera_effects": None if opts.effects is None or opts.effects.is_ideal else opts.effects.to_dict(),
        "seconds": time.perf_counter() - t0,
    }


def _plan_plate(rig: StereoRig, n: int, opts: SimulateOptions) -> list[_PlannedShot]:
    """The accuracy-test plate facing the rig at the working distance, ``n`` shots
    (a fresh noise seed each)."""
    albedo = (
        CamouflageField.from_palette("woodland", patch_size_mm=PLATE_CAMO_PATCH_MM, seed=opts.seed)
        if opts.camouflage
        else TextureAlbedo(seed=opts.seed)
    )
    plate = flat_plate(PLATE_SIZE_MM, PLATE_SIZE_MM, albedo=albedo)
    objs = [(plate, translation(0.0, 0.0, working_distance_mm(rig)))]
    shots: list[_PlannedShot] = []
    for k in range(n):
        stem = ("shot", "truth") if n == 1 else (f"shot_{k:02d}", f"truth_{k:02d}")
        shots.append((stem[0] + ".png", stem[1] + ".npz", objs, {"T_rig_plate": objs[0][1]}))
    return shots


def _plan_calib(rig: StereoRig, n: int, opts: SimulateOptions) -> list[_PlannedShot]:
    """A chessboard in ``n`` seeded poses with its true corners in both views."""
    cols, rows = (int(b) for b in opts.board)
    square_mm = opts.square_mm
    board_mesh = chessboard(cols, rows, square_mm)
    corners = chessboard_corners(cols, rows, square_mm)
    poses = calibration_board_poses(
        rig, n, options=BoardPoseOptions(cols=cols, rows=rows, square_mm=square_mm, seed=opts.seed)
    )
    shots: list[_PlannedShot] = []
    for k, T_rig_board in enumerate(poses):
        extra: dict[str, NDArray] = {"T_rig_board": T_rig_board}
        views = (("left", rig.left, rig.T_rig_left), ("right", rig.right, rig.T_rig_right))
        for name, cam, T_rig_cam in views:
            T_cam_board = np.linalg.inv(T_rig_cam) @ T_rig_board
            pc = corners @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
            extra[f"corners_{name}"] = _visible_corners(cam, pc)
            extra[f"T_{name}_board"] = T_cam_board
        extra["board_corners_mm"] = corners
        extra["board_inner_corners"] = np.array([cols, rows], dtype=np.int32)
        extra["board_square_mm"] = np.array(float(square_mm))
        shots.append((f"calib_{k:02d}.png", f"truth_{k:02d}.npz", [(board_mesh, T_rig_board)], extra))
    return shots


def _visible_corners(cam: CameraModel, pc: NDArray[np.float64]) -> NDArray[np.float64]:
    """True distorted pixels ``(N, 2)`` of camera-frame points, NaN outside the view."""
    uv = cam.project(pc)
    w, h = cam.size
    outside = ~((uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5))
    uv[outside] = np.nan
    return uv


def _plan_scene(
    rig: StereoRig, target: SceneMesh, n: int, opts: SimulateOptions, out: Path
) -> list[_PlannedShot]:
    """``target`` on a turntable in ``n`` views; writes ``target.ply`` and ``poses.json``."""
    tgt = target
    if opts.camouflage and not _has_own_albedo(tgt):
        patch = max(MIN_TARGET_CAMO_PATCH_MM, float(tgt.extent_mm.max()) / TARGET_CAMO_PATCHES)
        camo = CamouflageField.from_palette("woodland", patch_size_mm=patch, seed=opts.seed)
        tgt = SceneMesh(tgt.vertices, tgt.faces, None, camo, tgt.name, dict(tgt.metadata))
    poses = turntable_poses(n, 360.0 / n, distance_mm=working_distance_mm(rig))
    shots: list[_PlannedShot] = []
    records = []
    for k, T_world_rig in enumerate(poses):
        T_world_cam = T_world_rig @ rig.T_rig_left
        extra = {"T_world_rig": T_world_rig, "T_world_cam": T_world_cam}
        shots.append((f"shot_{k:02d}.png", f"truth_{k:02d}.npz", [(tgt, np.linalg.inv(T_world_rig))], extra))
        records.append({"index": k, "image": f"shot_{k:02d}.png", "truth": f"truth_{k:02d}.npz",
                        "T_world_cam": T_world_cam.tolist(), "T_world_rig": T_world_rig.tolist()})
    _write_target_ply(out / "target.ply", tgt)
    doc = {
        "schema_version": TRUTH_SCHEMA_VERSION,
        "units": "mm",
        "world_frame": "turntable: origin on the axis, z up",
        "camera": "left virtual camera, OpenCV frame (x right, y down, z forward)",
        "T_rig_left": rig.T_rig_left.tolist(),
        "T_world_rig": [v["T_world_rig"] for v in records],
        "views": records,
    }
    atomic_write_text(out / "poses.json", json.dumps(doc, indent=1))
    return shots


def _write_shots(
    out: Path,
    rig: StereoRig,
    shots: list[_PlannedShot],
    projector: Projector,
    opts: SimulateOptions,
    progress: ProgressFn | None,
) -> list[str]:
    """Render and write each planned shot (PNG + truth npz); one renderer per object list."""
    rect = compute_rectification(rig)
    files: list[str] = []
    cached: dict[int, RaycastRenderer] = {}
    for k, (png, npz, objs, extra) in enumerate(shots):
        key = id(objs)
        if key not in cached:
            cached.clear()
            cached[key] = RaycastRenderer(objs)
        shot_opts = opts.shot_options(opts.seed * SHOT_SEED_STRIDE + k)
        shot = simulate_shot(rig, objs, shot_opts, projector=projector, rectification=rect, renderer=cached[key])
        truth = dict(shot.truth)
        truth.update({k2: np.asarray(v) for k2, v in extra.items()})
        truth["schema_version"] = np.array(TRUTH_SCHEMA_VERSION)
        write_image(out / png, shot.sensor_image)  # encoded in memory: a full disk is an OSError
        write_npz(out / npz, truth, compress=opts.compress)
        files += [png, npz]
        if progress is not None:
            progress(k + 1, len(shots), png)
    return files


def effects_entries(effects: CameraEffects | None, blur_sigma: float) -> dict[str, Any]:
    """The camera effects of a simulated folder as flat ``rig.yaml`` ``sim_*`` entries
    (list: docs/capture.md)."""
    out: dict[str, Any] = {"sim_ideal_camera": 1, "sim_blur_sigma_px": float(blur_sigma)}
    if effects is None or effects.is_ideal:
        return out
    out.update(
        sim_ideal_camera=0,
        sim_exposure_right=effects.exposure_right,
        sim_colour_gain_right=np.asarray(effects.colour_gain_right, dtype=np.float64),
        sim_vignetting_stops=effects.vignetting_stops,
        sim_psf_sigma_px=effects.psf_sigma_px,
        sim_jpeg_quality=int(effects.jpeg_quality or 0),
        sim_specular=int(effects.specular),
        sim_default_material=effects.default_material,
    )
    for name, g in effects.materials:
        key = "sim_gloss_" + "".join(c if c.isalnum() else "_" for c in name)
        out[key] = np.array([g.coefficient, g.shininess])
    return out
