"""The scene simulator: one flash shot through the virtual prism rig, with ground truth.

Image model (per view pixel, linear, values in [0, 1])::

    illumination = ambient + flash * max(0, n . l) * visible * pattern_rgb / falloff
    image        = clip(albedo * illumination, 0, 1)   -> blur -> noise -> uint8

That is the ideal camera (``effects=None`` or ``CameraEffects.ideal()``). By default
a :class:`~prism3d.capture.camera_effects.CameraEffects` adds what a real prism shot
has: a Blinn-Phong flash highlight ``gloss * (n . h)^shininess * flash-light`` per
material (view-dependent: ``h`` bisects the directions to the view's camera centre
and to the flash), no per-ray clip (the sensor saturates), a gain and colour cast on
the right view, vignetting about each view's principal point, a lens PSF, then after
noise and quantisation a JPEG round trip of the sensor image (order and values: see
that module).

* ``n`` is the unit surface normal, ``l`` the unit direction from the surface point to
  the projector centre; ``visible`` is 1 when the segment to the projector is free
  (cast shadows, tested by ray casting), ``pattern_rgb`` the projector colour that
  lands on the point (bilinear in the pattern image, 0 outside the projector's
  frustum; 1 everywhere inside it for a white flash), and
  ``falloff = (distance / Projector.ref_distance_mm) ** 2`` (inverse-square law,
  1 at the reference distance). ``ambient`` is a uniform, shadowless light.
* The truth ``shading_<view>`` is the same illumination with the pattern taken as
  white (a scalar per pixel), ``illumination_<view>`` the RGB one. The truth maps
  are diffuse-only and free of camera effects (no highlight, gain, vignetting, blur
  or JPEG). With the ideal camera, a white flash, supersample 1 and no noise,
  ``image / 255 == albedo * shading`` up to quantisation.
* Each view is rendered through its virtual camera (lens distortion exact) with
  ``supersample x supersample`` rays per pixel box-averaged (colour only); the
  truth maps come from one ray through each exact output pixel centre (depth is
  never averaged across edges). The two views are then put on the sensor with
  :meth:`PrismSplit.join` (mirror flips applied), and sensor noise is added.

Speed: a full 2592x1944 shot with the pattern and 2x2 supersampling takes a few
seconds on 2 cores (``benchmarks/bench_simulate.py``). Only hit pixels are carried
(compact arrays); the supersampled colour rays are streamed in bands of whole output
rows and each band is lit, shaded and box-averaged at once; lighting, pattern
sampling, shadow rays, truth maps and noise are parallel numba kernels; the
rectified-disparity view casts depth-only rays. Camera rays are cached per camera
model on the renderer, so later shots of a sequence skip the distortion inversion.

Contract of :func:`simulate_to_folder` (``prism3d simulate plate|calib|scene OUT``):
see its docstring.
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
from prism3d.capture.camera_effects import CameraEffects, jpeg_roundtrip
from prism3d.capture.camouflage import CamouflageField
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.pattern import stripe_pattern
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
    TextureAlbedo,
    calibration_board_poses,
    chessboard,
    chessboard_corners,
    flat_plate,
    translation,
    turntable_poses,
)

from prism3d.checks import check_array, check_choice, check_in_range, check_positive
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path, atomic_write_text

__all__ = [
    "TRUTH_SCHEMA_VERSION",
    "Projector",
    "Shot",
    "simulate_shot",
    "simulate_to_folder",
    "working_distance_mm",
    "write_ply",
]

#: Version of the truth ``.npz`` / ``poses.json`` layout.
TRUTH_SCHEMA_VERSION = 1

ProgressFn = Callable[[int, int, str], None]


# -- projector -------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Projector:
    """A pinhole flash projector.

    Parameters
    ----------
    K : (3, 3) float64
        Projector intrinsics (OpenCV pixel-centre convention) for the pattern image.
    size : (int, int)
        Pattern ``(width, height)`` in projector pixels.
    pattern : (H, W, 3) uint8, optional
        RGB image the projector casts; ``None`` = a uniform white flash.
    T_rig_proj : (4, 4) float64
        Projector pose in the rig frame (OpenCV frame). Default identity: the rig
        origin (midway between the two views), looking along rig z.
    ref_distance_mm : float
        Distance at which the inverse-square falloff factor is 1.
    """

    K: NDArray[np.float64]
    size: tuple[int, int]
    pattern: NDArray[np.uint8] | None = None
    T_rig_proj: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    ref_distance_mm: float = 1250.0

    def __post_init__(self) -> None:
        cam = CameraModel(self.K, np.zeros(5), self.size)  # validates K and size
        object.__setattr__(self, "K", cam.K)
        object.__setattr__(self, "size", cam.size)
        if self.pattern is not None:
            p = check_array(self.pattern, "pattern", ndim=3, dtype_kind="u")
            w, h = cam.size
            if p.shape != (h, w, 3) or p.dtype != np.uint8:
                raise InputError(
                    f"pattern: expected ({h}, {w}, 3) uint8 for a {w}x{h} projector, "
                    f"got {p.shape} {p.dtype}"
                )
            object.__setattr__(self, "pattern", np.ascontiguousarray(p))
        T = check_array(self.T_rig_proj, "T_rig_proj", shape=(4, 4)).astype(np.float64)
        if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise InputError("T_rig_proj: rotation part is not a rotation")
        object.__setattr__(self, "T_rig_proj", T)
        check_positive(self.ref_distance_mm, "ref_distance_mm")

    @classmethod
    def for_rig(
        cls,
        rig: StereoRig,
        *,
        pattern: bool | NDArray[np.uint8] = True,
        size: tuple[int, int] = (1024, 1280),
        field_width_mm: float | None = None,
        period_px: int = 8,
        seed: int | None = None,
    ) -> Projector:
        """A projector at the rig origin whose field covers the views at the working
        distance with margin (default width: 1.4x a view's field width).

        ``pattern``: True = De Bruijn colour stripes (:func:`stripe_pattern`),
        False = white flash, or an explicit ``(H, W, 3) uint8`` image.
        """
        wd = working_distance_mm(rig)
        if field_width_mm is None:
            field_width_mm = 1.4 * rig.left.width / rig.left.fx * wd
        fw = check_positive(field_width_mm, "field_width_mm")
        if isinstance(pattern, np.ndarray):
            pat: NDArray[np.uint8] | None = pattern
            h, w = pattern.shape[:2]
        else:
            w, h = int(size[0]), int(size[1])
            pat = stripe_pattern(w, h, period_px=period_px, seed=seed) if pattern else None
        f = w * wd / fw
        K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(K, (w, h), pat, np.eye(4), wd)

    @property
    def position_rig(self) -> NDArray[np.float64]:
        """Projector centre ``(3,)`` in the rig frame, mm."""
        return self.T_rig_proj[:3, 3].copy()

    def light_at(self, points_rig: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(rgb (N, 3), white (N,))`` the projector casts on rig-frame points.

        ``white`` is 1 inside the frustum and 0 outside; ``rgb`` is the bilinearly
        sampled pattern (``white`` repeated for a white flash).
        """
        P = np.ascontiguousarray(check_array(points_rig, "points_rig", shape=(None, 3)), dtype=np.float64)
        _, rgb, white, _ = self._light(P, np.zeros_like(P), 1.0)
        return rgb, white.astype(np.float64)

    def _pattern01(self) -> NDArray[np.float64]:
        """The pattern as float64 in [0, 1] (cached; a 1x1 dummy for a white flash)."""
        cached = self.__dict__.get("_pattern01_cache")
        if cached is None:
            if self.pattern is None:
                cached = np.zeros((1, 1, 3))
            else:
                cached = self.pattern.astype(np.float64) / 255.0
            object.__setattr__(self, "_pattern01_cache", cached)
        return cached

    def _light(
        self, P: NDArray[np.float64], N: NDArray[np.float64], flash: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_]]:
        """``(k, rgb, white, lit)`` at rig-frame points ``P`` with unit normals ``N``.

        ``k (N,) = flash * max(0, n . l) * (ref / distance)^2`` before the shadow
        test, ``rgb (N, 3)`` the projector colour (0 outside the frustum), ``white``
        inside the frustum, ``lit`` = inside and facing the projector (the points
        that need a shadow ray). One parallel numba pass (``light_hits``).
        """
        from prism3d.capture._render_kernels import light_hits

        m = len(P)
        k = np.empty(m)
        rgb = np.empty((m, 3))
        white = np.empty(m, dtype=bool)
        lit = np.empty(m, dtype=bool)
        T_proj_rig = np.linalg.inv(self.T_rig_proj)
        w, h = self.size
        light_hits(
            np.ascontiguousarray(P), np.ascontiguousarray(N), self.position_rig,
            np.ascontiguousarray(T_proj_rig[:3, :3]), T_proj_rig[:3, 3].copy(), self.K, w, h,
            self._pattern01(), self.pattern is not None, float(self.ref_distance_mm), float(flash),
            k, rgb, white, lit,
        )
        return k, rgb, white, lit


def working_distance_mm(rig: StereoRig, default: float = 1250.0) -> float:
    """Depth (rig z) where the left optical axis crosses the rig's y-z plane
    (the convergence distance of a symmetric rig); ``default`` for parallel views."""
    c = rig.T_rig_left[:3, 3]
    z_axis = rig.T_rig_left[:3, 2]
    if abs(z_axis[0]) < 1e-9:
        return float(default)
    s = -c[0] / z_axis[0]
    p = c + s * z_axis
    return float(p[2]) if s > 0 and p[2] > 0 else float(default)


# -- one shot --------------------------------------------------------------------------
@dataclass(eq=False)
class Shot:
    """A simulated flash shot.

    Attributes
    ----------
    sensor_image : (H_s, W_s, 3) uint8
        RGB side-by-side image as the camera records it (views joined by the prism
        split, mirror flips applied).
    truth : dict[str, ndarray]
        Ground truth (see :func:`simulate_shot`).
    rectification : Rectification
        The rectification ``disparity_rect`` refers to.
    effects : CameraEffects or None
        The camera effects applied (None = the ideal camera).
    """

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
    """``(k, rgb, white)`` at the hits: flash factor AFTER the shadow test (0 in
    shadow), projector colour and frustum flag (rig frame = world)."""
    k, rgb, white, lit = projector._light(hits.points, hits.normals, flash)
    li = np.flatnonzero(lit)
    if len(li):
        vis = renderer._visible(hits.points, projector.position_rig, 1e-3, li)
        k[li[~vis]] = 0.0
    k[~lit] = 0.0
    return k, rgb, white


def _gloss_table(
    renderer: RaycastRenderer, effects: CameraEffects
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(ks, shininess)`` ``(n_objects,)`` of the scene's meshes (``metadata["material"]``)."""
    ks = np.zeros(renderer.n_objects)
    shin = np.ones(renderer.n_objects)
    if effects.specular:
        for i, mesh in enumerate(renderer._meshes):
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
    """Shade hits into ``img`` rows ``pix``: the ideal clipped diffuse colour when
    ``spec`` is None, else diffuse + highlight (``spec``: the view's output-pixel
    weight map; ray ``first + pix`` of a ``ss``-times supersampled camera with
    ``row_len`` rays per row), unclipped above."""
    from prism3d.capture._render_kernels import shade_colour, shade_colour_specular

    if spec is None:
        shade_colour(pix, alb, k, rgb, ambient, img)
    else:
        shade_colour_specular(pix, alb, k, rgb, spec, first, row_len, ss, width, ambient, img)


def _render_view(
    renderer: RaycastRenderer,
    cam: CameraModel,
    T_rig_cam: NDArray,
    projector: Projector,
    ambient: float,
    flash: float,
    background: float,
    supersample: int,
    gloss: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.float64], dict[str, NDArray]]:
    """Clean colour image ``(H, W, 3)`` and the truth maps of one view.

    ``gloss`` None: the ideal image in [0, 1]. Else ``(ks, shininess)`` per object:
    the flash highlight seen from this view's camera centre is added and values are
    not clipped above (the truth maps stay diffuse-only either way). The highlight
    weight ``ks (n . h)^s`` is evaluated on each output pixel's centre ray (the truth
    pass) and multiplies the flash light of every supersampled ray of that pixel:
    the lobe spans hundreds of pixels, and the transcendental maths then costs one
    evaluation per pixel instead of ``supersample^2``.
    """
    from prism3d.capture._render_kernels import box_mean, scatter_truth, specular_weight

    w, h = cam.size
    n = h * w
    # truth: one exact ray per output pixel centre, streamed in bands of rows
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
    spec = None if gloss is None else np.zeros(n)
    img1 = np.full((n, 3), float(background)) if supersample == 1 else np.zeros((0, 3))

    def truth_band(s: int, e: int, hb: CameraHits) -> None:
        if len(hb.index) == 0:
            return
        alb = renderer._albedo(hb.object_id, hb.face_id, hb.bary_uv, hb.points, np.float32)
        k, rgb, white = _illumination(renderer, hb, projector, flash)
        if spec is not None and gloss is not None and gloss[0].max() > 0:
            specular_weight(
                hb.index, hb.points, hb.normals, hb.object_id, eye, src, gloss[0], gloss[1], spec
            )
        scatter_truth(
            hb.index, hb.t, hb.z_cam, alb, k, rgb, white, hb.normals, R, hb.object_id, ambient,
            depth, mask, albedo, shading, illum, normals, object_id,
        )
        if supersample == 1:
            _shade(hb.index, alb, k, rgb, ambient, img1, spec, 0, w, 1, w)

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
    if supersample == 1:
        return img1.reshape(h, w, 3), truth
    # colour: supersampled rays streamed in bands of whole output rows, each band
    # shaded and box-averaged at once (memory stays ~one band)
    ss = supersample
    cs = cam.scaled(ss)
    ws = cs.size[0]
    img = np.empty((h, w, 3))
    band_img = np.empty((0, 3), dtype=np.float32)

    def shade_band(s: int, e: int, hb: CameraHits) -> None:
        nonlocal band_img
        if len(band_img) < e - s:
            band_img = np.empty((e - s, 3), dtype=np.float32)
        b = band_img[: e - s]
        b.fill(background)
        if len(hb.index):
            alb_s = renderer._albedo(hb.object_id, hb.face_id, hb.bary_uv, hb.points, np.float32)
            k_s, rgb_s, _ = _illumination(renderer, hb, projector, flash)
            _shade(hb.index - s, alb_s, k_s, rgb_s, ambient, b, spec, s, ws, ss, w)
        r0 = s // ws // ss
        r1 = e // ws // ss
        box_mean(b.reshape(-1, ws, 3), ss, img[r0:r1])

    renderer.stream_camera(cs, T_rig_cam, shade_band, rows_multiple=ss)
    return img, truth


def simulate_shot(
    rig: StereoRig,
    objects: Sequence[tuple[SceneMesh, NDArray]],
    *,
    projector: Projector | None = None,
    ambient: float = 0.25,
    flash: float = 0.75,
    supersample: int = 2,
    noise: bool | SensorNoise = True,
    blur_sigma: float = 0.0,
    seed: int = 0,
    rectification: Rectification | None = None,
    background: float = 0.0,
    renderer: RaycastRenderer | None = None,
    effects: CameraEffects | None = CameraEffects(),  # noqa: B008  (frozen, immutable)
) -> Shot:
    """Simulate one flash photograph through the prism rig, with exact ground truth.

    Parameters
    ----------
    rig : StereoRig
        The virtual rig (e.g. :func:`~prism3d.capture.rig.paper_rig`).
    objects : sequence of (SceneMesh, (4, 4) float64)
        Meshes and their poses ``T_rig_obj`` in the rig frame.
    projector : Projector, optional
        The flash. Default: a white flash at the rig origin
        (``Projector.for_rig(rig, pattern=False)``).
    ambient, flash : float
        Ambient light level and flash strength (see the module docstring).
    supersample : int
        Rays per pixel along each axis for the colour image (box-averaged).
    noise : bool or SensorNoise
        Sensor noise (True = ``SensorNoise()``), seeded by ``seed``.
    blur_sigma : float
        Gaussian blur of each view (pixels), applied before noise (combined with
        the effects' lens PSF as ``hypot(blur_sigma, effects.psf_sigma_px)``).
    seed : int
        Seed of the noise generator; same seed, same image.
    rectification : Rectification, optional
        Grid of ``disparity_rect``; default ``compute_rectification(rig)``.
    background : float
        Image value where no surface is hit (0 = black).
    renderer : RaycastRenderer, optional
        A renderer already built for ``objects`` (in the rig frame), to reuse.
    effects : CameraEffects or None
        Real-camera effects (:class:`~prism3d.capture.camera_effects.CameraEffects`):
        on by default with plausible values (right view 0.88x with a colour cast,
        0.5-stop vignetting, 0.7 px PSF, JPEG quality 92, painted-metal gloss).
        None or ``CameraEffects.ideal()`` = the ideal camera (bit-identical to
        the simulator before effects existed). Deterministic: same seed, same image.

    Returns
    -------
    Shot
        ``truth`` holds, for ``<v>`` in ``left``/``right`` (view pixels after split
        and un-flip): ``depth_<v>_mm`` (H, W) float32 NaN = no surface, ``mask_<v>``
        bool, ``albedo_<v>`` (H, W, 3) float32, ``shading_<v>`` (H, W) float32,
        ``illumination_<v>`` (H, W, 3) float32, ``normals_<v>`` (H, W, 3) float32
        (camera frame, facing the camera), ``object_id_<v>`` int32; plus
        ``disparity_rect`` (rectified-left grid, float32, NaN = no surface),
        ``depth_rect_mm``, ``R1 R2 P1 P2 Q``, ``T_rig_left``, ``T_right_left``,
        ``projector_T_rig_proj``. The truth maps are diffuse-only (no highlight)
        and free of camera effects.
    """
    if not isinstance(rig, StereoRig):
        raise InputError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    a = check_in_range(ambient, "ambient", 0.0, 10.0)
    fl = check_in_range(flash, "flash", 0.0, 10.0)
    bg = check_in_range(background, "background", 0.0, 1.0)
    ss = int(supersample)
    if ss != supersample or ss < 1 or ss > 8:
        raise InputError(f"supersample: expected an integer in [1, 8], got {supersample!r}")
    blur = check_positive(blur_sigma, "blur_sigma", strict=False)
    if projector is None:
        projector = Projector.for_rig(rig, pattern=False)
    elif not isinstance(projector, Projector):
        raise InputError(f"projector: expected a Projector or None, got {type(projector).__name__}")
    if noise is True:
        noise_model: SensorNoise | None = SensorNoise()
    elif noise is False or noise is None:
        noise_model = None
    elif isinstance(noise, SensorNoise):
        noise_model = noise
    else:
        raise InputError(f"noise: expected a bool or SensorNoise, got {type(noise).__name__}")
    if effects is not None and not isinstance(effects, CameraEffects):
        raise InputError(f"effects: expected a CameraEffects or None, got {type(effects).__name__}")
    fx = None if effects is None or effects.is_ideal else effects
    if renderer is None:
        renderer = RaycastRenderer(objects)
    rect = rectification if rectification is not None else compute_rectification(rig)
    gloss = None if fx is None else _gloss_table(renderer, fx)

    truth: dict[str, NDArray] = {}
    views = []
    for name, cam, T in (("left", rig.left, rig.T_rig_left), ("right", rig.right, rig.T_rig_right)):
        img, t = _render_view(renderer, cam, T, projector, a, fl, bg, ss, gloss)
        sigma = blur
        if fx is not None:
            _apply_view_optics(img, cam, fx, name)
            sigma = float(np.hypot(blur, fx.psf_sigma_px))
        if sigma > 0:
            img = gaussian_blur(img, sigma)
        views.append(img)
        truth[f"depth_{name}_mm"] = t["depth_mm"]
        for key in ("mask", "albedo", "shading", "illumination", "normals", "object_id"):
            truth[f"{key}_{name}"] = t[key]

    # true disparity on the rectified-left grid
    R1_4 = np.eye(4)
    R1_4[:3, :3] = rect.R1
    T_rig_rect = rig.T_rig_left @ np.linalg.inv(R1_4)
    rw, rhh = rect.camera.size
    disp = np.full(rw * rhh, np.nan, dtype=np.float32)
    depth_rect = np.full(rw * rhh, np.nan, dtype=np.float32)
    fb = rect.focal_px * rect.baseline_mm

    def rect_band(s: int, e: int, hb: CameraHits) -> None:  # depth only: no albedo, no light
        z = hb.t * hb.z_cam
        depth_rect[hb.index] = z
        with np.errstate(divide="ignore", invalid="ignore"):
            disp[hb.index] = fb / z

    renderer.stream_camera(rect.camera, T_rig_rect, rect_band)
    truth["disparity_rect"] = disp.reshape(rhh, rw)
    truth["depth_rect_mm"] = depth_rect.reshape(rhh, rw)
    for k in ("R1", "R2", "P1", "P2", "Q"):
        truth[k] = np.asarray(getattr(rect, k), dtype=np.float64)
    truth["T_rig_left"] = rig.T_rig_left.copy()
    truth["T_right_left"] = rig.T_right_left.copy()
    truth["projector_T_rig_proj"] = projector.T_rig_proj.copy()

    sensor = rig.split.join(views[0], views[1], fill=0.0)
    if noise_model is not None:
        rng = np.random.default_rng(seed)
        sensor_u8 = quantize(noise_model.apply(sensor, rng))
    else:
        sensor_u8 = quantize(sensor * 255.0)
    if fx is not None and fx.jpeg_quality is not None:
        sensor_u8 = jpeg_roundtrip(sensor_u8, fx.jpeg_quality)
    return Shot(sensor_u8, truth, rect, effects)


def _apply_view_optics(
    img: NDArray[np.float64], cam: CameraModel, fx: CameraEffects, view: str
) -> None:
    """In place: the view's RGB gain and vignetting about its principal point."""
    from prism3d.capture._render_kernels import gain_vignetting

    gain = fx.view_gain(view)
    cx, cy = float(cam.K[0, 2]), float(cam.K[1, 2])
    a, inv_rc2 = fx.vignetting_coefficients(cam.size, (cx, cy))
    if a > 0 or np.any(gain != 1.0):
        gain_vignetting(img, gain, cx, cy, a, inv_rc2)


# -- files -----------------------------------------------------------------------------
def _write_png(path: Path, rgb: NDArray[np.uint8]) -> None:
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[:, :, ::-1])):
            raise InputError(f"{path}: could not write the PNG")


def _write_npz(path: Path, arrays: dict[str, NDArray], *, compress: bool) -> None:
    """Write arrays as ``.npz`` (readable by ``np.load``), atomically.

    ``compress``: deflate at level 1. A 5 MP scene shot's truth is ~94 % NaN
    background: 281 MB plain, 4.8 MB at level 1 (0.6 s in memory, against 0.3 s
    plain), 3.8 MB at ``np.savez_compressed``'s level 6 (1.2 s)."""
    import zipfile

    if not compress:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        return
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, a in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(a), allow_pickle=False)


def write_ply(path: str | Path, mesh: SceneMesh) -> None:
    """Write a mesh as binary little-endian PLY (double xyz mm, uchar RGB), atomically."""
    V = mesh.vertices
    F = mesh.faces
    C = np.clip(np.rint(mesh.vertex_colors() * 255.0), 0, 255).astype(np.uint8)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment prism3d true target mesh, millimetres ({mesh.name})\n"
        f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vdt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    va = np.empty(len(V), dtype=vdt)
    va["x"], va["y"], va["z"] = V[:, 0], V[:, 1], V[:, 2]
    va["r"], va["g"], va["b"] = C[:, 0], C[:, 1], C[:, 2]
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    fa = np.empty(len(F), dtype=fdt)
    fa["n"] = 3
    fa["i"] = F.astype(np.int32)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(va.tobytes())
        fh.write(fa.tobytes())


def _has_own_albedo(mesh: SceneMesh) -> bool:
    return mesh.albedo_field is not None or mesh.vertex_albedo is not None


def simulate_to_folder(
    kind: str,
    out_dir: str | Path,
    *,
    rig: StereoRig | None = None,
    target: SceneMesh | None = None,
    pattern: bool | None = None,
    camouflage: bool = True,
    views: int | None = None,
    seed: int = 0,
    noise: bool = True,
    supersample: int = 2,
    progress: ProgressFn | None = None,
    compress: bool = True,
    board: tuple[int, int] = (9, 6),
    square_mm: float = 25.0,
    blur_sigma: float = 0.0,
    effects: CameraEffects | None = CameraEffects(),  # noqa: B008  (frozen, immutable)
) -> dict[str, Any]:
    """Simulate shots and write them with their ground truth (``prism3d simulate``).

    Parameters
    ----------
    kind : {"plate", "calib", "scene"}
        ``plate``: the paper's accuracy test, a flat 300 x 300 mm plate facing the
        rig (perpendicular to rig z) at the working distance (1250 mm for the paper
        rig); writes ``shot.png`` + ``truth.npz`` (``shot_00.png``... when
        ``views`` > 1: the same plate, a fresh noise seed per shot).
        ``calib``: a chessboard (``board`` inner corners, default 9 x 6, ``square_mm``
        squares, default 25 mm) in ``views``
        (default 5) varied poses (tilts 20-40 deg, 1100-1400 mm, seeded, whole board
        in both views); writes ``calib_00.png``... + ``truth_00.npz``... with
        ``corners_left``/``corners_right`` ((cols*rows, 2) float64 true distorted pixels,
        NaN outside the view) and ``T_left_board``, ``T_rig_board``.
        ``scene``: ``target`` on a turntable, ``views`` (default 8) views at
        ``360 / views`` degree steps (45 deg for 8); writes ``shot_00.png``... +
        ``truth_00.npz``..., ``target.ply`` (the true mesh, mm, world = turntable
        frame, z up) and ``poses.json`` (per view ``T_world_cam`` of the left
        virtual camera and ``T_world_rig``, 4x4 lists).
        Every kind writes ``rig.yaml`` (:meth:`StereoRig.save`) with ``simulated: 1``
        and the camera effects used as ``sim_*`` entries (:func:`_effects_entries`).
    out_dir : path
        Output folder (created).
    rig : StereoRig, optional
        Default :func:`paper_rig`.
    target : SceneMesh, optional
        The object of ``scene`` (required there), world frame = turntable frame.
    pattern : bool, optional
        Project the colour grating. Default: on for plate and scene, off (white
        flash) for calib -- stripes over a chessboard defeat corner detection.
    camouflage : bool
        Plate: woodland camouflage albedo (else a mild grey speckle texture). Scene:
        paint a camouflage albedo on a target that has no albedo of its own.
    views : int, optional
        Number of shots (see ``kind``).
    seed : int
        Seeds poses, textures, the pattern order and the noise: same seed, same files.
    noise : bool
        Sensor noise on/off.
    supersample : int
        Colour supersampling factor.
    progress : callable(done, total, label), optional
        Called after each shot.
    compress : bool
        Write the truth ``.npz`` deflated (default; ~60x smaller, a 5 MP shot's
        truth 4.8 MB instead of 281 MB, for ~0.3 s more per shot). False writes
        it plain.
    board : (cols, rows)
        ``calib``: inner corners of the chessboard. A denser board pins the
        principal point better: with 5 poses at the paper rig's focal length its
        standard deviation is ~0.6 px for 9 x 6 corners, ~0.3 px for 19 x 13.
    square_mm : float
        ``calib``: square size, mm.
    blur_sigma : float
        Extra Gaussian optical blur of each view, pixels, combined with the
        effects' PSF (``hypot``); 0 (default) adds none.
    effects : CameraEffects or None
        Real-camera effects (default on, see :func:`simulate_shot`); None or
        ``CameraEffects.ideal()`` = the ideal camera. The PNGs then hold the
        JPEG-decoded pixels (lossless copies of what the camera's JPEG decodes to).

    Returns
    -------
    dict
        ``kind``, ``out_dir``, ``files`` (names written), ``n_shots``, ``pattern``,
        ``camera_effects`` (``CameraEffects.to_dict()``, None for the ideal
        camera), ``seconds``.
    """
    check_choice(kind, "kind", ("plate", "calib", "scene"))
    if effects is not None and not isinstance(effects, CameraEffects):
        raise InputError(f"effects: expected a CameraEffects or None, got {type(effects).__name__}")
    t0 = time.perf_counter()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if rig is None:
        rig = paper_rig()
    if not isinstance(rig, StereoRig):
        raise InputError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    if views is not None and (int(views) != views or int(views) < 1):
        raise InputError(f"views: expected a positive integer, got {views!r}")
    if kind == "calib":
        if len(board) != 2 or any(int(b) != b or int(b) < 2 for b in board):
            raise InputError(f"board: expected (cols, rows) inner corners >= 2, got {board!r}")
        square_mm = check_positive(square_mm, "square_mm")
    if kind == "scene":
        if target is None:
            raise InputError("simulate scene: a target mesh is required (target=SceneMesh)")
        if not isinstance(target, SceneMesh):
            raise InputError(f"target: expected a SceneMesh, got {type(target).__name__}")
    use_pattern = (kind != "calib") if pattern is None else bool(pattern)
    wd = working_distance_mm(rig)
    projector = Projector.for_rig(rig, pattern=use_pattern, seed=seed if seed else None)
    rect = compute_rectification(rig)
    files: list[str] = []
    common = dict(
        projector=projector, supersample=supersample, noise=noise, rectification=rect,
        blur_sigma=check_positive(blur_sigma, "blur_sigma", strict=False), effects=effects,
    )
    out.mkdir(parents=True, exist_ok=True)
    shots: list[tuple[str, str, list[tuple[SceneMesh, NDArray]], dict[str, NDArray]]] = []

    if kind == "plate":
        albedo = (
            CamouflageField.from_palette("woodland", patch_size_mm=60.0, seed=seed)
            if camouflage
            else TextureAlbedo(seed=seed)
        )
        plate = flat_plate(300.0, 300.0, albedo=albedo)
        objs = [(plate, translation(0.0, 0.0, wd))]
        n = 1 if views is None else int(views)
        for k in range(n):
            stem = ("shot", "truth") if n == 1 else (f"shot_{k:02d}", f"truth_{k:02d}")
            extra = {"T_rig_plate": objs[0][1]}
            shots.append((stem[0] + ".png", stem[1] + ".npz", objs, extra))
    elif kind == "calib":
        cols, rows = (int(b) for b in board)
        board_mesh = chessboard(cols, rows, square_mm)
        corners = chessboard_corners(cols, rows, square_mm)
        n = 5 if views is None else int(views)
        poses = calibration_board_poses(rig, n, cols=cols, rows=rows, square_mm=square_mm, seed=seed)
        for k, T_rig_board in enumerate(poses):
            extra: dict[str, NDArray] = {"T_rig_board": T_rig_board}
            for name, cam, T_rig_cam in (
                ("left", rig.left, rig.T_rig_left),
                ("right", rig.right, rig.T_rig_right),
            ):
                T_cam_board = np.linalg.inv(T_rig_cam) @ T_rig_board
                pc = corners @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
                uv = cam.project(pc)
                w, h = cam.size
                outside = ~(
                    (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
                )
                uv[outside] = np.nan
                extra[f"corners_{name}"] = uv
                extra[f"T_{name}_board"] = T_cam_board
            extra["board_corners_mm"] = corners
            extra["board_inner_corners"] = np.array([cols, rows], dtype=np.int32)
            extra["board_square_mm"] = np.array(float(square_mm))
            shots.append((f"calib_{k:02d}.png", f"truth_{k:02d}.npz", [(board_mesh, T_rig_board)], extra))
    else:
        tgt: SceneMesh = target  # type: ignore[assignment]  # validated above
        if camouflage and not _has_own_albedo(tgt):
            camo = CamouflageField.from_palette("woodland", patch_size_mm=max(10.0, float(tgt.extent_mm.max()) / 6), seed=seed)
            tgt = SceneMesh(tgt.vertices, tgt.faces, None, camo, tgt.name, dict(tgt.metadata))
        n = 8 if views is None else int(views)
        poses = turntable_poses(n, 360.0 / n, distance_mm=wd)
        view_records = []
        for k, T_world_rig in enumerate(poses):
            T_rig_world = np.linalg.inv(T_world_rig)
            T_world_cam = T_world_rig @ rig.T_rig_left
            extra = {"T_world_rig": T_world_rig, "T_world_cam": T_world_cam}
            shots.append((f"shot_{k:02d}.png", f"truth_{k:02d}.npz", [(tgt, T_rig_world)], extra))
            view_records.append(
                {
                    "index": k,
                    "image": f"shot_{k:02d}.png",
                    "truth": f"truth_{k:02d}.npz",
                    "T_world_cam": T_world_cam.tolist(),
                    "T_world_rig": T_world_rig.tolist(),
                }
            )
        write_ply(out / "target.ply", tgt)
        files.append("target.ply")
        doc = {
            "schema_version": TRUTH_SCHEMA_VERSION,
            "units": "mm",
            "world_frame": "turntable: origin on the axis, z up",
            "camera": "left virtual camera, OpenCV frame (x right, y down, z forward)",
            "T_rig_left": rig.T_rig_left.tolist(),
            "T_world_rig": [v["T_world_rig"] for v in view_records],
            "views": view_records,
        }
        atomic_write_text(out / "poses.json", json.dumps(doc, indent=1))
        files.append("poses.json")

    sim_entries = _effects_entries(effects, float(common["blur_sigma"]))  # type: ignore[arg-type]
    rig.save(out / "rig.yaml", extra={"simulated": 1, **sim_entries})
    files.append("rig.yaml")
    total = len(shots)
    cached: dict[int, RaycastRenderer] = {}
    for k, (png, npz, objs, extra) in enumerate(shots):
        key = id(objs)
        if key not in cached:
            cached.clear()
            cached[key] = RaycastRenderer(objs)
        shot = simulate_shot(rig, objs, seed=seed * 1000 + k, renderer=cached[key], **common)  # type: ignore[arg-type]
        truth = dict(shot.truth)
        truth.update({k2: np.asarray(v) for k2, v in extra.items()})
        truth["schema_version"] = np.array(TRUTH_SCHEMA_VERSION)
        _write_png(out / png, shot.sensor_image)
        _write_npz(out / npz, truth, compress=compress)
        files += [png, npz]
        if progress is not None:
            progress(k + 1, total, png)
    return {
        "kind": kind,
        "out_dir": str(out),
        "files": sorted(files),
        "n_shots": total,
        "pattern": use_pattern,
        "camera_effects": None if effects is None or effects.is_ideal else effects.to_dict(),
        "seconds": time.perf_counter() - t0,
    }


def _effects_entries(effects: CameraEffects | None, blur_sigma: float) -> dict[str, Any]:
    """The camera effects of a simulated folder as flat ``rig.yaml`` entries.

    ``sim_ideal_camera`` (1 = no effects; then nothing else but the blur),
    ``sim_blur_sigma_px``, ``sim_exposure_right``, ``sim_colour_gain_right`` (R, G, B),
    ``sim_vignetting_stops``, ``sim_psf_sigma_px``, ``sim_jpeg_quality`` (0 = none),
    ``sim_specular``, ``sim_default_material`` and ``sim_gloss_<class>``
    (coefficient, shininess) per material class.
    """
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
