"""Training and test chips: a target mesh rendered at many poses.

:func:`render_chips` renders a :class:`~prism3d.capture.mesh.SceneMesh` at a list of
poses on the shared renderer and returns a :class:`ChipSet` of ``(N, size, size)``
channels: ``intensity`` (float32 [0, 1], Lambert + ambient under a camera-frame light,
camouflage paint or one uniform grey), ``depth`` (float32 mm, NaN = no surface, one
exact ray per pixel centre), ``mask`` (bool, target pixels) and ``shape`` (float32
[0, 1], albedo 1 under the canonical light). Every chip setting is one
:class:`ChipSpec`. Framing, clutter and lighting models: docs/atr.md.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.poses import ChipPose, camera_T_obj_cam, parse_range, poses_table
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.render import RaycastRenderer
from prism3d.capture.render_gl import PyrenderRenderer
from prism3d.capture.rig import CameraModel
from prism3d.checks import check_array, check_choice
from prism3d.errors import InputError
from prism3d.io.atomic import staged_folder
from prism3d.io.mesh import UNITS_MM, read_mesh

__all__ = [
    "CHANNELS",
    "CHIP_SCHEMA_VERSION",
    "ChipSet",
    "ChipSpec",
    "TerrainAlbedo",
    "as_chip_spec",
    "bounding_sphere",
    "check_ranges",
    "chip_poses",
    "default_range_mm",
    "ground_mesh",
    "load_mesh_file",
    "render_chips",
    "render_to_folder",
    "spec_poses",
]

log = logging.getLogger(__name__)

CHANNELS = ("intensity", "depth", "mask", "shape")
CHIP_SCHEMA_VERSION = 1
#: Canonical light, camera frame (towards the light): upper left, in front.
DEFAULT_LIGHT = (-0.35, -0.55, -1.0)
_LUMA = np.array([0.299, 0.587, 0.114])
#: Chips per renderer call (amortises per-call overhead; ~16k rays per 128^2 chip).
_BATCH = 16
#: Default camera range, in bounding-sphere radii: the whole target in view, little background.
DEFAULT_RANGE_RADII = 4.0
#: A range must exceed the bounding radius by 5 %: the camera stays outside the target.
_MIN_RANGE_RADII = 1.05
#: Terrain texture: octaves, plane waves per octave, amplitude decay per octave (1/f-like).
_TERRAIN_OCTAVES, _TERRAIN_WAVES, _TERRAIN_DECAY = 4, 3, 0.6
#: Seed offset of the terrain texture, so it never repeats the camouflage pattern's draws.
_TERRAIN_SEED_OFFSET = 7919
#: Ground plane half-width in target extents: its edge never shows in a chip.
_GROUND_HALF_EXTENTS = 15.0
#: Terrain wavelength, in target extents: patches about the target's size.
_GROUND_TEXTURE_EXTENTS = 0.6
#: Gaussian low-pass width (cycles/pixel) of the "noise" background: blobs ~ 1/6 of a chip.
_NOISE_CUTOFF = 0.06


@dataclass(frozen=True)
class ChipSpec:
    """How chips are rendered: size, framing, channels, paint, light, clutter, noise.

    One place for the chip settings shared by :func:`render_chips`,
    :func:`render_to_folder`, the filter banks, evaluation and database render jobs.
    """

    size: int = 128
    """Chip side, pixels (>= 8); the principal point is the chip centre."""
    framing: str = "fit"
    """``"fit"``: the bounding sphere fills the chip at every range; ``"range"``: one focal."""
    pixels_per_m: float | None = None
    """``"range"`` framing: pixels per metre at 1 m (default: the "fit" focal at the nearest range)."""
    channels: tuple[str, ...] = CHANNELS
    """Channels to return, among intensity, depth, mask, shape."""
    camouflage: bool = True
    """Intensity with the mesh's paint (True) or one uniform grey, its mean luminance (False)."""
    light: tuple[float, float, float] = DEFAULT_LIGHT
    """Direction towards the light, camera frame (OpenCV); also the canonical light of shape."""
    ambient: float = 0.25
    """Ambient fraction in [0, 1): shadowed sides stay visible, as under daylight."""
    lighting_variation: float = 0.0
    """Std (deg) of a random tilt of the light per chip (intensity only)."""
    clutter: str | None = None
    """Background: None, ``"ground"`` (textured terrain plane) or ``"noise"`` (smooth texture)."""
    noise_sigma: float = 0.0
    """Additive Gaussian noise std on intensity and shape ([0, 1] units)."""
    depth_noise_mm: float = 0.0
    """Additive Gaussian noise std on depth surface pixels, mm."""
    seed: int = 0
    """Seed of lighting jitter, clutter and noise (rendering is deterministic)."""
    backend: str = "raycast"
    """``"raycast"`` (exact per-pixel rays) or ``"pyrender"`` (OpenGL; no ground clutter)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", _check_size(self.size))
        chans = tuple(self.channels)
        if not chans:
            raise InputError("channels: expected at least one of " + ", ".join(CHANNELS))
        for ch in chans:
            check_choice(ch, "channels", CHANNELS)
        object.__setattr__(self, "channels", chans)
        check_choice(self.framing, "framing", ("fit", "range"))
        check_choice(self.backend, "backend", ("raycast", "pyrender"))
        check_choice(self.clutter, "clutter", (None, "ground", "noise"))
        if not 0 <= self.ambient < 1:
            raise InputError(f"ambient: expected a value in [0, 1), got {self.ambient}")
        for nm, hi in (("noise_sigma", MAX_NOISE_SIGMA), ("depth_noise_mm", MAX_DEPTH_NOISE_MM),
                       ("lighting_variation", 180.0)):
            v = getattr(self, nm)
            if not (math.isfinite(v) and 0 <= v <= hi):
                raise InputError(f"{nm}: expected a value in [0, {hi:g}], got {v}")
        s = self.seed
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0:
            raise InputError(f"seed: expected a non-negative integer, got {s!r}")
        object.__setattr__(self, "seed", int(s))
        light = tuple(float(v) for v in np.asarray(self.light, dtype=np.float64).reshape(3))
        if not np.linalg.norm(light) > 0:
            raise InputError(f"light: expected a non-zero direction, got {tuple(self.light)}")
        object.__setattr__(self, "light", light)
        if self.pixels_per_m is not None:
            object.__setattr__(self, "pixels_per_m", _check_pixels_per_m(self.pixels_per_m))
        if self.backend == "pyrender" and self.clutter == "ground":
            raise InputError("clutter='ground' needs backend='raycast'")


@dataclass(eq=False)
class ChipSet:
    """Chips of one target at ``N`` poses.

    ``channels``: name -> ``(N, S, S)`` array; ``poses``: one :class:`ChipPose` per
    chip; ``table``: :func:`~prism3d.atr.poses.poses_table` plus ``chip``, ``target``
    and the camera-frame light ``light_x/y/z``.
    """

    channels: dict[str, NDArray]
    poses: list[ChipPose]
    target: str
    table: object = field(repr=False)

    @property
    def size(self) -> int:
        return int(next(iter(self.channels.values())).shape[-1])

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, name: str) -> NDArray:
        if name not in self.channels:
            raise InputError(f"ChipSet: no channel {name!r}; have {sorted(self.channels)}")
        return self.channels[name]


@dataclass(frozen=True, eq=False)
class TerrainAlbedo:
    """Procedural terrain albedo, a sum of random plane waves in [0.1, 0.8], greenish-brown.

    ``scale_mm`` is the largest wavelength (each octave halves it); deterministic in ``seed``.
    """

    scale_mm: float
    seed: int = 0

    def __call__(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        rng = np.random.default_rng(self.seed + _TERRAIN_SEED_OFFSET)
        p = np.asarray(points, dtype=np.float64)[:, :2]
        g = np.zeros(len(p))
        amp = 1.0
        for octave in range(_TERRAIN_OCTAVES):
            k = 2.0 * math.pi / (self.scale_mm / 2.0**octave)
            for _ in range(_TERRAIN_WAVES):
                th = rng.uniform(0, 2 * math.pi)
                ph = rng.uniform(0, 2 * math.pi)
                g += amp * np.sin(k * (p[:, 0] * math.cos(th) + p[:, 1] * math.sin(th)) + ph)
            amp *= _TERRAIN_DECAY
        g = 0.45 + 0.18 * g / 1.5
        g = np.clip(g, 0.1, 0.8)
        return np.stack([0.9 * g, g, 0.7 * g], axis=1)


def as_chip_spec(chip_spec: ChipSpec | None, default: ChipSpec | None = None) -> ChipSpec:
    """``chip_spec``, or ``default`` (``ChipSpec()``) when None; InputError for another type."""
    if chip_spec is None:
        return ChipSpec() if default is None else default
    if not isinstance(chip_spec, ChipSpec):
        raise InputError(f"chip_spec: expected a ChipSpec, got {type(chip_spec).__name__}")
    return chip_spec


def bounding_sphere(mesh: SceneMesh) -> tuple[NDArray[np.float64], float]:
    """Centre ``(3,)`` (bounding-box centre, mm) and radius (mm) enclosing ``mesh``."""
    c = mesh.bounds.mean(axis=0)
    r = float(np.max(np.linalg.norm(mesh.vertices - c, axis=1)))
    return c, r


def default_range_mm(mesh: SceneMesh) -> float:
    """The default camera range of ``mesh``: :data:`DEFAULT_RANGE_RADII` bounding radii, mm."""
    return DEFAULT_RANGE_RADII * bounding_sphere(mesh)[1]


#: Largest chip side (px): correlation filters are trained on tens to hundreds of pixels;
#: 4096 is far beyond any use, and one such chip with every channel is ~200 MB.
MAX_CHIP_SIZE = 4096
#: Farthest camera, mm: 100 km, beyond any sensor's range (1e300 is a typo).
MAX_RANGE_MM = 1e8
#: Largest "range" framing focal, px per metre at 1 m: a 10 m telephoto on 1 um pixels.
MAX_PIXELS_PER_M = 1e7
#: Intensity noise std is in [0, 1] units: 10 is ten times the whole range (pure noise).
MAX_NOISE_SIGMA = 10.0
#: Depth noise std, mm: 100 m hides any target.
MAX_DEPTH_NOISE_MM = 1e5
#: Memory the chips of one render_chips call may take (all channels, every pose); larger
#: sets are rendered in parts (a database job splits them into units).
CHIP_MEMORY_BUDGET = 1 << 30
#: Bytes per chip pixel in the render buffers: depth + intensity + shape float32, mask.
_BYTES_PER_CHIP_PIXEL = 13


def _check_size(size: int) -> int:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 8:
        raise InputError(f"size: expected an integer chip size >= 8 pixels, got {size!r}")
    if size > MAX_CHIP_SIZE:
        raise InputError(f"size: {size} px is more than the {MAX_CHIP_SIZE} px a chip may be")
    return int(size)


def _check_chip_memory(n: int, size: int) -> None:
    need = n * size * size * _BYTES_PER_CHIP_PIXEL
    if need > CHIP_MEMORY_BUDGET:
        raise InputError(f"{n} chips of {size}x{size} px need {need / 2**30:.1f} GiB, more than the "
                         f"{CHIP_MEMORY_BUDGET / 2**30:.0f} GiB budget of one call; render fewer poses at "
                         "once (prism3d db render splits a job into units)")


def check_ranges(ranges_mm: str | float | Sequence[float]) -> list[float]:
    """Camera ranges (a :func:`~prism3d.atr.poses.parse_range` spec), each in
    (0, :data:`MAX_RANGE_MM`]; checked before a job writes anything."""
    ranges = parse_range(ranges_mm)
    for R in ranges:
        if not 0 < R <= MAX_RANGE_MM:
            raise InputError(f"ranges_mm: expected ranges in (0, {MAX_RANGE_MM:g}] mm, got {R:g}")
    return ranges


def _check_pixels_per_m(value: float) -> float:
    if not (math.isfinite(value) and 0 < value <= MAX_PIXELS_PER_M):
        raise InputError(f"pixels_per_m: expected a number in (0, {MAX_PIXELS_PER_M:g}], got {value}")
    return float(value)


def chip_poses(
    mesh: SceneMesh,
    azimuths_deg: str | float | Sequence[float],
    elevations_deg: str | float | Sequence[float],
    ranges_mm: str | float | Sequence[float],
    *,
    rolls_deg: str | float | Sequence[float] = 0.0,
    size: int = 128,
    framing: str = "fit",
    pixels_per_m: float | None = None,
    fill: float = 0.9,
    directions_deg: NDArray | None = None,
) -> list[ChipPose]:
    """Framed chip poses of ``mesh`` looking at its bounding-box centre.

    Grids as :func:`~prism3d.atr.poses.parse_range` (``"0:360:10"``, ``"10,40"``);
    ``directions_deg`` (N, 2) (az, el) replaces the az x el grid. ``framing``,
    ``pixels_per_m``: :class:`ChipSpec`; ``fill``: fraction of the chip the bounding
    sphere spans under "fit". Returns range-major, then elevation, azimuth, roll.
    """
    size = _check_size(size)
    check_choice(framing, "framing", ("fit", "range"))
    if not 0 < fill <= 1:
        raise InputError(f"fill: expected a fraction in (0, 1], got {fill}")
    c, r = bounding_sphere(mesh)
    if directions_deg is None:
        az = parse_range(azimuths_deg)
        el = parse_range(elevations_deg)
        dirs = [(a, e) for e in el for a in az]
    else:
        dirs = [tuple(d) for d in check_array(directions_deg, "directions_deg", shape=(None, 2))]
    ranges = check_ranges(ranges_mm)
    rolls = parse_range(rolls_deg)
    for R in ranges:
        if not R > _MIN_RANGE_RADII * r:
            raise InputError(
                f"ranges_mm: range {R} mm puts the camera inside {mesh.name}'s bounding sphere "
                f"(radius {r:.1f} mm); use ranges > {_MIN_RANGE_RADII * r:.1f} mm"
            )

    def fit_focal(R: float) -> float:
        return fill * (size / 2.0) * math.sqrt(R * R - r * r) / r

    if framing == "range":
        if pixels_per_m is None:
            f_range = fit_focal(min(ranges))
        else:
            f_range = _check_pixels_per_m(pixels_per_m)
    c0 = (size - 1) / 2.0
    out = []
    for R in ranges:
        f = fit_focal(R) if framing == "fit" else f_range
        K = np.array([[f, 0.0, c0], [0.0, f, c0], [0.0, 0.0, 1.0]])
        for a, e in dirs:
            for roll in rolls:
                T_obj_cam = camera_T_obj_cam(a, e, R, roll, c)
                out.append(
                    ChipPose(float(a), float(e), float(R), float(roll), K, np.linalg.inv(T_obj_cam))
                )
    return out


def spec_poses(
    mesh: SceneMesh,
    azimuth: str | float | Sequence[float],
    elevation: str | float | Sequence[float],
    range_mm: str | float | Sequence[float] | None,
    chip_spec: ChipSpec,
) -> list[ChipPose]:
    """:func:`chip_poses` with the size and framing of ``chip_spec``; range None = default."""
    if range_mm is None:
        range_mm = default_range_mm(mesh)
    return chip_poses(
        mesh,
        azimuth,
        elevation,
        range_mm,
        size=chip_spec.size,
        framing=chip_spec.framing,
        pixels_per_m=chip_spec.pixels_per_m,
    )


def ground_mesh(mesh: SceneMesh, seed: int) -> SceneMesh:
    """A square textured ground plane under ``mesh`` (object z up), 30x its size."""
    b = mesh.bounds
    c = b.mean(axis=0)
    half = _GROUND_HALF_EXTENTS * float(np.max(b[1, :2] - b[0, :2]))
    z = b[0, 2] - 1e-3 * max(float(np.max(b[1] - b[0])), 1.0)
    v = np.array(
        [
            [c[0] - half, c[1] - half, z],
            [c[0] + half, c[1] - half, z],
            [c[0] + half, c[1] + half, z],
            [c[0] - half, c[1] + half, z],
        ]
    )
    f = np.array([[0, 1, 2], [0, 2, 3]])
    scale = _GROUND_TEXTURE_EXTENTS * float(np.max(b[1] - b[0]))
    return SceneMesh(v, f, albedo_field=TerrainAlbedo(scale, seed), name="ground")


def _smooth_noise(rng: np.random.Generator, n: int, size: int) -> NDArray[np.float32]:
    """``(n, size, size)`` smooth random textures in [0.05, 0.85] (low-pass white noise)."""
    w = rng.standard_normal((n, size, size))
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.fftfreq(size)[None, :]
    lp = np.exp(-(fx**2 + fy**2) / (2 * _NOISE_CUTOFF**2))
    g = np.fft.ifft2(np.fft.fft2(w) * lp).real
    g /= g.std(axis=(1, 2), keepdims=True) + 1e-12
    return np.clip(0.45 + 0.15 * g, 0.05, 0.85).astype(np.float32)


def _light_dirs(
    light: Sequence[float], variation_deg: float, n: int, rng: np.random.Generator
) -> NDArray:
    l0 = np.asarray(light, dtype=np.float64).reshape(3)
    l0 = l0 / np.linalg.norm(l0)
    if variation_deg <= 0:
        return np.tile(l0, (n, 1))
    # random rotation by a Gaussian angle about a random axis perpendicular to l0
    out = np.empty((n, 3))
    for i in range(n):
        ax = np.cross(l0, rng.standard_normal(3))
        ax /= np.linalg.norm(ax)
        ang = math.radians(variation_deg) * rng.standard_normal()
        out[i] = l0 * math.cos(ang) + np.cross(ax, l0) * math.sin(ang)
    return out


def _paint_grey(mesh: SceneMesh) -> float:
    return float(np.mean(mesh.vertex_colors() @ _LUMA))


@dataclass(eq=False)
class _Buffers:
    """Output arrays ``(N, S, S)`` filled in place by the renderers."""

    depth: NDArray[np.float32]
    mask: NDArray[np.bool_]
    intensity: NDArray[np.float32] | None
    shape: NDArray[np.float32] | None

    @classmethod
    def allocate(cls, n: int, size: int, chans: Sequence[str]) -> _Buffers:
        def maybe(ch: str) -> NDArray[np.float32] | None:
            return np.zeros((n, size, size), dtype=np.float32) if ch in chans else None

        return cls(
            np.full((n, size, size), np.nan, dtype=np.float32),
            np.zeros((n, size, size), dtype=bool),
            maybe("intensity"),
            maybe("shape"),
        )

    @property
    def need_normals(self) -> bool:
        return self.intensity is not None or self.shape is not None


@dataclass(frozen=True, eq=False)
class _Shading:
    """Paint and lights of one render: ``grey`` replaces the paint when not None (once)."""

    grey: float | None
    lights: NDArray[np.float64]
    canon: NDArray[np.float64]
    ambient: float


def render_chips(
    mesh: SceneMesh,
    poses: Sequence[ChipPose] | None = None,
    *,
    azimuth: str | float | Sequence[float] = "0:360:30",
    elevation: str | float | Sequence[float] = 20.0,
    range_mm: str | float | Sequence[float] | None = None,
    chip_spec: ChipSpec | None = None,
) -> ChipSet:
    """Render ``mesh`` (object frame, mm) into chips.

    ``poses`` are used as given (``K``, ``T_cam_obj``; their size must match
    ``chip_spec.size``); default: :func:`chip_poses` of ``azimuth`` x ``elevation`` x
    ``range_mm`` (default range :func:`default_range_mm`). ``chip_spec``: the chip
    settings (None = ``ChipSpec()``). Raises :class:`InputError` for a non-SceneMesh,
    bad poses or an unusable range.
    """
    spec = as_chip_spec(chip_spec)
    if not isinstance(mesh, SceneMesh):
        raise InputError(f"mesh: expected a SceneMesh, got {type(mesh).__name__}")
    if poses is None:
        poses = spec_poses(mesh, azimuth, elevation, range_mm, spec)
    poses = _check_poses(poses)
    _check_chip_memory(len(poses), spec.size)
    rng = np.random.default_rng(spec.seed)
    n = len(poses)
    lights = _light_dirs(spec.light, spec.lighting_variation, n, rng)
    canon = lights[0] if spec.lighting_variation <= 0 else _light_dirs(spec.light, 0.0, 1, rng)[0]
    shading = _Shading(None if spec.camouflage else _paint_grey(mesh), lights, canon, spec.ambient)
    buf = _Buffers.allocate(n, spec.size, spec.channels)
    if spec.backend == "raycast":
        _render_raycast(mesh, poses, spec, shading, buf)
    else:
        _render_pyrender(mesh, poses, spec.size, shading, buf)
    _add_clutter_and_noise(buf, spec, rng)
    arrays = {"intensity": buf.intensity, "depth": buf.depth, "mask": buf.mask, "shape": buf.shape}
    table = poses_table(poses)
    table.insert(0, "chip", np.arange(n))
    table.insert(1, "target", mesh.name)
    table["light_x"], table["light_y"], table["light_z"] = lights[:, 0], lights[:, 1], lights[:, 2]
    return ChipSet({ch: arrays[ch] for ch in spec.channels}, poses, mesh.name, table)


def _check_poses(poses: Sequence[ChipPose]) -> list[ChipPose]:
    poses = list(poses)
    if not poses:
        raise InputError("poses: expected at least one pose")
    for p in poses:
        if not isinstance(p, ChipPose):
            raise InputError(f"poses: expected ChipPose items, got {type(p).__name__}")
    return poses


def _add_clutter_and_noise(buf: _Buffers, spec: ChipSpec, rng: np.random.Generator) -> None:
    """Noise background, then sensor noise, in this order of random draws (reproducible)."""
    n, size = buf.depth.shape[:2]
    if spec.clutter == "noise" and buf.intensity is not None:
        bg = _smooth_noise(rng, n, size)
        buf.intensity[~buf.mask] = bg[~buf.mask]
    if spec.noise_sigma > 0:
        for img in (buf.intensity, buf.shape):
            if img is not None:
                img += rng.normal(0.0, spec.noise_sigma, img.shape).astype(np.float32)
                np.clip(img, 0.0, 1.0, out=img)
    if spec.depth_noise_mm > 0:
        fin = np.isfinite(buf.depth)
        buf.depth[fin] += rng.normal(0.0, spec.depth_noise_mm, int(fin.sum())).astype(np.float32)


def _pixel_rays(
    K: NDArray[np.float64], size: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pinhole camera-frame unit rays ``(S*S, 3)`` and their z ``(S*S,)``."""
    u, v = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
    d = np.stack(
        [(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1
    ).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, d[:, 2].copy()


def _shade(n_cam: NDArray, l_cam: NDArray, ambient: float) -> NDArray[np.float64]:
    return ambient + (1.0 - ambient) * np.clip(n_cam @ l_cam, 0.0, None)


def _batch_rays(
    batch: Sequence[ChipPose], size: int, ray_cache: dict[bytes, tuple[NDArray, NDArray]]
) -> tuple[NDArray, NDArray, NDArray, list[NDArray]]:
    """Object-frame ray origins, directions ``(B*S*S, 3)``, camera z per ray, rotations."""
    npx = size * size
    nb = len(batch)
    origins = np.empty((nb * npx, 3))
    dirs = np.empty((nb * npx, 3))
    zc = np.empty(nb * npx)
    Rs = []
    for j, p in enumerate(batch):
        key = p.K.tobytes() + bytes([size % 256, size // 256])
        if key not in ray_cache:
            ray_cache[key] = _pixel_rays(p.K, size)
        rc, z = ray_cache[key]
        T = p.T_obj_cam
        sl = slice(j * npx, (j + 1) * npx)
        origins[sl] = T[:3, 3]
        dirs[sl] = rc @ T[:3, :3].T
        zc[sl] = z
        Rs.append(T[:3, :3])
    return origins, dirs, zc, Rs


def _render_raycast(
    mesh: SceneMesh, poses: list[ChipPose], spec: ChipSpec, sh: _Shading, buf: _Buffers
) -> None:
    size = spec.size
    objects = [(mesh, np.eye(4))]
    if spec.clutter == "ground":
        objects.append((ground_mesh(mesh, spec.seed), np.eye(4)))
    renderer = RaycastRenderer(objects)
    npx = size * size
    ray_cache: dict[bytes, tuple[NDArray, NDArray]] = {}
    for b0 in range(0, len(poses), _BATCH):
        batch = poses[b0 : b0 + _BATCH]
        nb = len(batch)
        origins, dirs, zc, Rs = _batch_rays(batch, size, ray_cache)
        hits = renderer.cast(origins, dirs, normalized=True)
        hit = hits.object_id >= 0
        buf.depth[b0 : b0 + nb] = np.where(hit, hits.t * zc, np.nan).reshape(nb, size, size)
        buf.mask[b0 : b0 + nb] = (hits.object_id == 0).reshape(nb, size, size)
        if not buf.need_normals:
            continue
        alb = None
        if buf.intensity is not None:
            a = renderer.albedo(hits) @ _LUMA
            if sh.grey is not None:
                a[hits.object_id == 0] = sh.grey
            alb = a.reshape(nb, npx)
        nw = hits.normals.reshape(nb, npx, 3)
        hb = hit.reshape(nb, npx)
        for j in range(nb):
            nc = np.nan_to_num(nw[j] @ Rs[j])  # R^T n per row: camera-frame normals
            if buf.intensity is not None:
                buf.intensity[b0 + j] = np.where(
                    hb[j], alb[j] * _shade(nc, sh.lights[b0 + j], sh.ambient), 0.0
                ).reshape(size, size)
            if buf.shape is not None:
                buf.shape[b0 + j] = np.where(
                    hb[j], _shade(nc, sh.canon, sh.ambient), 0.0
                ).reshape(size, size)


def _render_pyrender(
    mesh: SceneMesh, poses: list[ChipPose], size: int, sh: _Shading, buf: _Buffers
) -> None:
    with PyrenderRenderer([(mesh, np.eye(4))]) as renderer:
        for i, p in enumerate(poses):
            cam = CameraModel(p.K, np.zeros(5), (size, size))
            res = renderer.render(cam, p.T_obj_cam)
            buf.depth[i] = res.depth_mm
            buf.mask[i] = res.mask
            if not buf.need_normals:
                continue
            nc = np.nan_to_num(res.normals_cam.reshape(-1, 3).astype(np.float64))
            m = res.mask.reshape(-1)
            if buf.intensity is not None:
                a = (
                    (res.albedo.reshape(-1, 3) @ _LUMA)
                    if sh.grey is None
                    else np.full(m.shape, sh.grey)
                )
                buf.intensity[i] = np.where(
                    m, a * _shade(nc, sh.lights[i], sh.ambient), 0.0
                ).reshape(size, size)
            if buf.shape is not None:
                buf.shape[i] = np.where(m, _shade(nc, sh.canon, sh.ambient), 0.0).reshape(size, size)


# -- mesh files and the render command ------------------------------------------------------


def load_mesh_file(
    path: str | Path,
    *,
    units: str = "mm",
    up: str = "z",
    length_mm: float | None = None,
    yaw_deg: float = 0.0,
    name: str | None = None,
) -> SceneMesh:
    """Load a mesh file (GLB, OBJ, PLY, OFF, STL...) with trimesh as a :class:`SceneMesh`.

    ``units`` of the file's coordinates; ``up`` its up axis (``"y"``, glTF, is turned
    +90 deg about x to z-up); ``length_mm`` rescales the longest horizontal extent;
    ``yaw_deg`` turns about up (counter-clockwise from above) to put the nose on +x.
    Returns vertices in mm, z up, origin at the footprint centre on the ground, vertex
    albedo from the file's colours (grey when none).
    """
    check_choice(units, "units", tuple(UNITS_MM))
    check_choice(up, "up", ("y", "z"))
    data = read_mesh(path)
    p = Path(path)
    v = data.vertices * UNITS_MM[units]
    if up == "y":
        v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)
    if yaw_deg:
        a = math.radians(yaw_deg)
        Rz = np.array(
            [[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]]
        )
        v = v @ Rz.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    if length_mm is not None:
        if not (math.isfinite(length_mm) and length_mm > 0):
            raise InputError(f"length_mm: expected a positive length, got {length_mm}")
        ext = float(np.max(hi[:2] - lo[:2]))
        if not ext > 0:
            raise InputError(f"{p}: degenerate mesh (zero horizontal extent)")
        v = v * (length_mm / ext)
    return SceneMesh(
        v,
        data.faces,
        vertex_albedo=data.vertex_colors if data.vertex_colors is not None else np.full((len(v), 3), 0.7),
        name=name or p.stem,
        metadata={"source": str(p), "units": units, "up": up, "yaw_deg": float(yaw_deg), "length_mm": length_mm},
    )


def render_to_folder(
    mesh: SceneMesh | str | Path,
    out_dir: str | Path,
    *,
    azimuth: str | Sequence[float] = "0:360:10",
    elevation: str | Sequence[float] = "10:60:25",
    range_mm: str | Sequence[float] | float | None = None,
    chip_spec: ChipSpec | None = None,
    units: str = "mm",
    up: str = "z",
    fmt: str = "npz",
) -> Path:
    """Render chips of a mesh (or mesh file, in ``units`` with ``up``) into a folder.

    ``fmt="npz"``: ``chips_<channel>.npz`` (one ``(N, S, S)`` array ``chips`` each);
    ``fmt="png"``: ``<channel>/chip_00000.png`` (8-bit; mask 0/255) and
    ``depth/chip_00000.tiff`` (float32 mm). Then ``manifest.parquet``: one row per chip
    (poses table, light, file names, size, framing, schema_version). The files appear
    together or not at all. Returns the manifest path.
    """
    spec = as_chip_spec(chip_spec)
    check_choice(fmt, "fmt", ("npz", "png"))
    if not isinstance(mesh, SceneMesh):
        mesh = load_mesh_file(mesh, units=units, up=up)
    chips = render_chips(
        mesh, None, azimuth=azimuth, elevation=elevation, range_mm=range_mm, chip_spec=spec
    )
    table = chips.table.copy()
    write = _write_npz_channel if fmt == "npz" else _write_image_channel
    with staged_folder(out_dir) as stage:  # the chips and their manifest together, or nothing
        for ch, arr in chips.channels.items():
            table[f"file_{ch}"] = write(stage, ch, arr)
        table["size"] = spec.size
        table["framing"] = spec.framing
        table["schema_version"] = CHIP_SCHEMA_VERSION
        table.to_parquet(stage / "manifest.parquet", index=False)
    return Path(out_dir) / "manifest.parquet"


def _write_npz_channel(out: Path, ch: str, arr: NDArray) -> list[str]:
    """``chips_<ch>.npz`` in the staging folder ``out`` (made atomic as a whole); returns
    the per-chip references ``file#index``."""
    fn = f"chips_{ch}.npz"
    with open(out / fn, "wb") as fh:
        np.savez_compressed(fh, chips=arr)
    return [f"{fn}#{i}" for i in range(len(arr))]


def _write_image_channel(out: Path, ch: str, arr: NDArray) -> list[str]:
    """One PNG (depth: float32 TIFF) per chip under ``<ch>/`` of the staging folder
    ``out``; returns the file names."""
    import cv2

    (out / ch).mkdir(exist_ok=True)
    names = []
    for i, img in enumerate(arr):
        if ch == "depth":
            fn = f"{ch}/chip_{i:05d}.tiff"
            ok, buf = cv2.imencode(".tiff", img.astype(np.float32))
        else:
            fn = f"{ch}/chip_{i:05d}.png"
            u8 = (
                (img.astype(np.uint8) * 255)
                if ch == "mask"
                else np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)
            )
            ok, buf = cv2.imencode(".png", u8)
        if not ok:
            raise InputError(f"{out / fn}: image encoding failed")
        (out / fn).write_bytes(buf.tobytes())
        names.append(fn)
    return names
