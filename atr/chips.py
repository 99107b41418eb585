"""Training and test chips: a target mesh rendered at many poses.

:func:`render_chips` renders one :class:`~prism3d.capture.mesh.SceneMesh` at a list of
poses on the shared renderer (:mod:`prism3d.capture.render`) and returns a
:class:`ChipSet` of ``(N, size, size)`` arrays per channel plus the pose table:

``intensity`` (float32, [0, 1])
    albedo (grey) x (ambient + (1 - ambient) * max(0, n . l)) under a directional
    light ``l`` (camera frame), optionally jittered per chip; camouflage paint on or
    off (off: one uniform grey, the mean paint luminance).
``depth`` (float32 mm, NaN = no surface)
    true camera z of the surface seen through each pixel CENTRE (one exact ray per
    pixel, no anti-aliasing, hence no "flying pixels" at silhouettes).
``mask`` (bool)
    pixels that see the target (not the clutter).
``shape`` (float32, [0, 1])
    the "shape image": uniform albedo 1 relit by the canonical light (the same for
    every chip, no jitter) -- what camouflage removal recovers.

Framing: ``"fit"`` scales every chip so the target's bounding sphere fills
``fill`` of the chip (range-invariant); ``"range"`` keeps one focal length
(``pixels_per_m`` pixels per metre of target at 1 m range), so the target's
apparent size follows its range.

Clutter: ``"ground"`` puts the target on a large textured ground plane (it shows in
intensity, depth and shape, like real terrain); ``"noise"`` fills the intensity
background with a smooth random texture. Both are deterministic given ``seed``.
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

from prism3d.io.mesh import UNITS_MM
from prism3d.checks import check_array, check_choice
from prism3d.errors import InputError

__all__ = [
    "CHANNELS",
    "CHIP_SCHEMA_VERSION",
    "ChipSet",
    "TerrainAlbedo",
    "chip_poses",
    "load_mesh_file",
    "render_chips",
    "render_to_folder",
]

log = logging.getLogger(__name__)

CHANNELS = ("intensity", "depth", "mask", "shape")
CHIP_SCHEMA_VERSION = 1
#: Canonical light, camera frame (towards the light): upper left, in front.
DEFAULT_LIGHT = (-0.35, -0.55, -1.0)
_LUMA = np.array([0.299, 0.587, 0.114])
#: Chips per renderer call (amortises per-call overhead; ~16k rays per 128^2 chip).
_BATCH = 16


@dataclass(eq=False)
class ChipSet:
    """Chips of one target at ``N`` poses.

    Attributes
    ----------
    channels : dict of str -> (N, S, S) array
        ``intensity`` / ``shape`` float32 [0, 1], ``depth`` float32 mm (NaN = no
        surface), ``mask`` bool, for the channels requested.
    poses : list of ChipPose
        One per chip, in order.
    target : str
        The mesh name.
    table : pandas.DataFrame
        :func:`~prism3d.atr.poses.poses_table` plus ``target``, ``light_x/y/z``
        (camera-frame light direction used for ``intensity``) and ``chip``
        (index).
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
    """Procedural terrain texture (an albedo field): a sum of random plane waves.

    ``scale_mm`` is the largest texture wavelength; 4 octaves halve it each time.
    Deterministic in ``seed``; values in [0.1, 0.8], greenish-brown.
    """

    scale_mm: float
    seed: int = 0

    def __call__(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        rng = np.random.default_rng(self.seed + 7919)
        p = np.asarray(points, dtype=np.float64)[:, :2]
        g = np.zeros(len(p))
        amp = 1.0
        for octave in range(4):
            k = 2.0 * math.pi / (self.scale_mm / 2.0**octave)
            for _ in range(3):
                th = rng.uniform(0, 2 * math.pi)
                ph = rng.uniform(0, 2 * math.pi)
                g += amp * np.sin(k * (p[:, 0] * math.cos(th) + p[:, 1] * math.sin(th)) + ph)
            amp *= 0.6
        g = 0.45 + 0.18 * g / 1.5
        g = np.clip(g, 0.1, 0.8)
        return np.stack([0.9 * g, g, 0.7 * g], axis=1)


def _bounding_sphere(mesh: SceneMesh) -> tuple[NDArray[np.float64], float]:
    c = mesh.bounds.mean(axis=0)
    r = float(np.max(np.linalg.norm(mesh.vertices - c, axis=1)))
    return c, r


def _check_size(size: int) -> int:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 8:
        raise InputError(f"size: expected an integer chip size >= 8 pixels, got {size!r}")
    return int(size)


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

    Parameters
    ----------
    azimuths_deg, elevations_deg, ranges_mm, rolls_deg : str, float or sequence
        Grids (``"0:360:10"``, ``"10,40"``, numbers; :func:`~prism3d.atr.poses.parse_range`).
    size : int
        Chip side, pixels (>= 8). The principal point is the chip centre
        ``((size-1)/2, (size-1)/2)``.
    framing : {"fit", "range"}
        ``"fit"``: focal length so the bounding sphere spans ``fill`` of the chip at
        every range. ``"range"``: one focal length ``pixels_per_m`` (pixels per metre
        of target at 1 m range; default: the "fit" focal at the nearest range).
    directions_deg : (N, 2) float, optional
        (az, el) list replacing the az x el grid (e.g. a Fibonacci sampling).

    Returns
    -------
    list of ChipPose
        Range-major, then elevation, azimuth, roll.
    """
    size = _check_size(size)
    check_choice(framing, "framing", ("fit", "range"))
    if not 0 < fill <= 1:
        raise InputError(f"fill: expected a fraction in (0, 1], got {fill}")
    c, r = _bounding_sphere(mesh)
    if directions_deg is None:
        az = parse_range(azimuths_deg)
        el = parse_range(elevations_deg)
        dirs = [(a, e) for e in el for a in az]
    else:
        dirs = [tuple(d) for d in check_array(directions_deg, "directions_deg", shape=(None, 2))]
    ranges = parse_range(ranges_mm)
    rolls = parse_range(rolls_deg)
    for R in ranges:
        if not R > 1.05 * r:
            raise InputError(
                f"ranges_mm: range {R} mm puts the camera inside {mesh.name}'s bounding sphere "
                f"(radius {r:.1f} mm); use ranges > {1.05 * r:.1f} mm"
            )

    def fit_focal(R: float) -> float:
        return fill * (size / 2.0) * math.sqrt(R * R - r * r) / r

    if framing == "range":
        if pixels_per_m is None:
            f_range = fit_focal(min(ranges))
        else:
            if not (math.isfinite(pixels_per_m) and pixels_per_m > 0):
                raise InputError(f"pixels_per_m: expected a positive number, got {pixels_per_m}")
            f_range = float(pixels_per_m)
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


def _ground_mesh(mesh: SceneMesh, seed: int) -> SceneMesh:
    """A square ground plane under ``mesh`` (object z up), 30x its size, textured."""
    b = mesh.bounds
    c = b.mean(axis=0)
    half = 15.0 * float(np.max(b[1, :2] - b[0, :2]))
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
    scale = 0.6 * float(np.max(b[1] - b[0]))
    return SceneMesh(v, f, albedo_field=TerrainAlbedo(scale, seed), name="ground")


def _smooth_noise(rng: np.random.Generator, n: int, size: int) -> NDArray[np.float32]:
    """``(n, size, size)`` smooth random textures in [0.05, 0.85] (low-pass white noise)."""
    w = rng.standard_normal((n, size, size))
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.fftfreq(size)[None, :]
    lp = np.exp(-(fx**2 + fy**2) / (2 * 0.06**2))
    g = np.fft.ifft2(np.fft.fft2(w) * lp).real
    g /= g.std(axis=(1, 2), keepdims=True) + 1e-12
    return np.clip(0.45 + 0.15 * g, 0.05, 0.85).astype(np.float32)


def _light_dirs(
    light: Sequence[float], variation_deg: float, n: int, rng: np.random.Generator
) -> NDArray:
    l0 = np.asarray(light, dtype=np.float64).reshape(3)
    nl = np.linalg.norm(l0)
    if not nl > 0:
        raise InputError(f"light: expected a non-zero direction, got {tuple(light)}")
    l0 = l0 / nl
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


def render_chips(
    mesh: SceneMesh,
    poses: Sequence[ChipPose] | None = None,
    *,
    azimuth: str | float | Sequence[float] = "0:360:30",
    elevation: str | float | Sequence[float] = 20.0,
    range_mm: str | float | Sequence[float] | None = None,
    size: int = 128,
    framing: str = "fit",
    pixels_per_m: float | None = None,
    channels: Sequence[str] = CHANNELS,
    camouflage: bool = True,
    light: Sequence[float] = DEFAULT_LIGHT,
    ambient: float = 0.25,
    lighting_variation: float = 0.0,
    clutter: str | None = None,
    noise_sigma: float = 0.0,
    depth_noise_mm: float = 0.0,
    seed: int = 0,
    backend: str = "raycast",
) -> ChipSet:
    """Render ``mesh`` at ``poses`` into chips.

    Parameters
    ----------
    mesh : SceneMesh
        The target (object frame, mm).
    poses : sequence of ChipPose, optional
        Exact poses (their ``K`` and ``T_cam_obj`` are used as given; ``size`` must
        match). Default: :func:`chip_poses` of ``azimuth`` x ``elevation`` x
        ``range_mm`` (default range: 4 bounding-sphere radii) with ``framing``.
    size : int
        Chip side in pixels (>= 8).
    channels : sequence of {"intensity", "depth", "mask", "shape"}
        Which arrays to return.
    camouflage : bool
        Use the mesh's paint (True) or one uniform grey (False) for ``intensity``.
    light : (3,) float
        Direction towards the light, camera frame (OpenCV: -y is up, -z towards the
        camera). Also the canonical light of ``shape``.
    ambient : float
        Ambient fraction in [0, 1).
    lighting_variation : float
        Standard deviation (degrees) of a random tilt of the light per chip
        (``intensity`` only).
    clutter : {None, "ground", "noise"}
        Background (module docstring).
    noise_sigma : float
        Additive Gaussian noise (std, [0, 1] units) on ``intensity`` and ``shape``.
    depth_noise_mm : float
        Additive Gaussian noise (std, mm) on ``depth`` surface pixels.
    seed : int
        Seed of lighting jitter, clutter and noise (deterministic).
    backend : {"raycast", "pyrender"}
        ``raycast``: exact per-pixel-centre rays (:class:`RaycastRenderer`).
        ``pyrender``: OpenGL rasterisation (z-buffer depth, paint sampled at the
        vertices; no "ground" clutter).

    Returns
    -------
    ChipSet

    Raises
    ------
    InputError
        Not a SceneMesh, a bad size/channel/framing/backend/clutter, bad noise or
        ambient values, an unusable range.
    """
    if not isinstance(mesh, SceneMesh):
        raise InputError(f"mesh: expected a SceneMesh, got {type(mesh).__name__}")
    size = _check_size(size)
    chans = tuple(channels)
    if not chans:
        raise InputError("channels: expected at least one of " + ", ".join(CHANNELS))
    for ch in chans:
        check_choice(ch, "channels", CHANNELS)
    check_choice(backend, "backend", ("raycast", "pyrender"))
    check_choice(clutter, "clutter", (None, "ground", "noise"))
    if not 0 <= ambient < 1:
        raise InputError(f"ambient: expected a value in [0, 1), got {ambient}")
    for v, nm in (
        (noise_sigma, "noise_sigma"),
        (depth_noise_mm, "depth_noise_mm"),
        (lighting_variation, "lighting_variation"),
    ):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"{nm}: expected a finite value >= 0, got {v}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed: expected a non-negative integer, got {seed!r}")
    if poses is None:
        if range_mm is None:
            range_mm = 4.0 * _bounding_sphere(mesh)[1]
        poses = chip_poses(
            mesh,
            azimuth,
            elevation,
            range_mm,
            size=size,
            framing=framing,
            pixels_per_m=pixels_per_m,
        )
    poses = list(poses)
    if not poses:
        raise InputError("poses: expected at least one pose")
    for p in poses:
        if not isinstance(p, ChipPose):
            raise InputError(f"poses: expected ChipPose items, got {type(p).__name__}")
    if backend == "pyrender" and clutter == "ground":
        raise InputError("clutter='ground' needs backend='raycast'")
    rng = np.random.default_rng(seed)
    n = len(poses)
    lights = _light_dirs(light, lighting_variation, n, rng)
    canon = lights[0] if lighting_variation <= 0 else _light_dirs(light, 0.0, 1, rng)[0]
    want_int = "intensity" in chans
    want_shape = "shape" in chans
    need_normals = want_int or want_shape
    depth = np.full((n, size, size), np.nan, dtype=np.float32)
    mask = np.zeros((n, size, size), dtype=bool)
    inten = np.zeros((n, size, size), dtype=np.float32) if want_int else None
    shape = np.zeros((n, size, size), dtype=np.float32) if want_shape else None
    grey = None if camouflage else _paint_grey(mesh)
    if backend == "raycast":
        _render_raycast(
            mesh,
            poses,
            size,
            clutter,
            seed,
            need_normals,
            want_int,
            grey,
            lights,
            canon,
            ambient,
            depth,
            mask,
            inten,
            shape,
        )
    else:
        _render_pyrender(
            mesh,
            poses,
            size,
            need_normals,
            want_int,
            grey,
            lights,
            canon,
            ambient,
            depth,
            mask,
            inten,
            shape,
        )
    if clutter == "noise" and want_int:
        bg = _smooth_noise(rng, n, size)
        inten[~mask] = bg[~mask]
    if noise_sigma > 0:
        if want_int:
            inten += rng.normal(0.0, noise_sigma, inten.shape).astype(np.float32)
            np.clip(inten, 0.0, 1.0, out=inten)
        if want_shape:
            shape += rng.normal(0.0, noise_sigma, shape.shape).astype(np.float32)
            np.clip(shape, 0.0, 1.0, out=shape)
    if depth_noise_mm > 0:
        fin = np.isfinite(depth)
        depth[fin] += rng.normal(0.0, depth_noise_mm, int(fin.sum())).astype(np.float32)
    out: dict[str, NDArray] = {}
    for ch in chans:
        out[ch] = {"intensity": inten, "depth": depth, "mask": mask, "shape": shape}[ch]
    table = poses_table(poses)
    table.insert(0, "chip", np.arange(n))
    table.insert(1, "target", mesh.name)
    table["light_x"], table["light_y"], table["light_z"] = lights[:, 0], lights[:, 1], lights[:, 2]
    return ChipSet(out, poses, mesh.name, table)


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


def _render_raycast(
    mesh: SceneMesh,
    poses: list[ChipPose],
    size: int,
    clutter: str | None,
    seed: int,
    need_normals: bool,
    want_int: bool,
    grey: float | None,
    lights: NDArray[np.float64],
    canon: NDArray[np.float64],
    ambient: float,
    depth: NDArray[np.float32],
    mask: NDArray[np.bool_],
    inten: NDArray[np.float32] | None,
    shape: NDArray[np.float32] | None,
) -> None:
    from prism3d.capture.render import RaycastRenderer

    objects = [(mesh, np.eye(4))]
    if clutter == "ground":
        objects.append((_ground_mesh(mesh, seed), np.eye(4)))
    renderer = RaycastRenderer(objects)
    npx = size * size
    ray_cache: dict[bytes, tuple[NDArray, NDArray]] = {}
    for b0 in range(0, len(poses), _BATCH):
        batch = poses[b0 : b0 + _BATCH]
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
        hits = renderer.cast(origins, dirs, normalized=True)
        hit = hits.object_id >= 0
        d_all = np.where(hit, hits.t * zc, np.nan).reshape(nb, size, size)
        depth[b0 : b0 + nb] = d_all
        mask[b0 : b0 + nb] = (hits.object_id == 0).reshape(nb, size, size)
        if not need_normals:
            continue
        alb = None
        if want_int:
            a = renderer.albedo(hits) @ _LUMA
            if grey is not None:
                a[hits.object_id == 0] = grey
            alb = a.reshape(nb, npx)
        nw = hits.normals.reshape(nb, npx, 3)
        hb = hit.reshape(nb, npx)
        for j in range(nb):
            nc = np.nan_to_num(nw[j] @ Rs[j])  # R^T n per row: camera-frame normals
            if want_int:
                inten[b0 + j] = np.where(
                    hb[j], alb[j] * _shade(nc, lights[b0 + j], ambient), 0.0
                ).reshape(size, size)
            if shape is not None:
                shape[b0 + j] = np.where(hb[j], _shade(nc, canon, ambient), 0.0).reshape(size, size)


def _render_pyrender(
    mesh: SceneMesh,
    poses: list[ChipPose],
    size: int,
    need_normals: bool,
    want_int: bool,
    grey: float | None,
    lights: NDArray[np.float64],
    canon: NDArray[np.float64],
    ambient: float,
    depth: NDArray[np.float32],
    mask: NDArray[np.bool_],
    inten: NDArray[np.float32] | None,
    shape: NDArray[np.float32] | None,
) -> None:
    from prism3d.capture.render import PyrenderRenderer
    from prism3d.capture.rig import CameraModel

    with PyrenderRenderer([(mesh, np.eye(4))]) as renderer:
        for i, p in enumerate(poses):
            cam = CameraModel(p.K, np.zeros(5), (size, size))
            res = renderer.render(cam, p.T_obj_cam)
            depth[i] = res.depth_mm
            mask[i] = res.mask
            if need_normals:
                nc = np.nan_to_num(res.normals_cam.reshape(-1, 3).astype(np.float64))
                m = res.mask.reshape(-1)
                if want_int:
                    a = (
                        (res.albedo.reshape(-1, 3) @ _LUMA)
                        if grey is None
                        else np.full(m.shape, grey)
                    )
                    inten[i] = np.where(m, a * _shade(nc, lights[i], ambient), 0.0).reshape(
                        size, size
                    )
                if shape is not None:
                    shape[i] = np.where(m, _shade(nc, canon, ambient), 0.0).reshape(size, size)


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

    Parameters
    ----------
    units : {"mm", "cm", "m", "in"}
        Units of the file's coordinates.
    up : {"y", "z"}
        The file's up axis; ``"y"`` (glTF convention) is rotated to the prism3d
        object frame's z-up (``(x, y, z) -> (x, -z, y)``... i.e. +90 deg about x).
    length_mm : float, optional
        Rescale so the longest horizontal extent is this long (for files in
        arbitrary units).
    yaw_deg : float
        Rotation about the (new) up axis, counter-clockwise seen from above, to put
        the model's nose on +x (e.g. 90 for a Y-up file whose nose is on +z).
    name : str, optional
        Default: the file stem.

    Returns
    -------
    SceneMesh
        Vertices in mm, object frame z up, origin at the footprint centre on the
        ground (bounding-box centre in x, y; minimum z = 0); vertex albedo from the
        file's face/vertex colours (material colours), grey when there are none.
    """
    from prism3d.io.mesh import read_mesh

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
        metadata={"source": str(p), "units": units, "up": up, "yaw_deg": float(yaw_deg)},
    )


def render_to_folder(
    mesh: SceneMesh | str | Path,
    out_dir: str | Path,
    *,
    azimuth: str | Sequence[float] = "0:360:10",
    elevation: str | Sequence[float] = "10:60:25",
    range_mm: str | Sequence[float] | float | None = None,
    size: int = 128,
    framing: str = "fit",
    pixels_per_m: float | None = None,
    channels: Sequence[str] = CHANNELS,
    units: str = "mm",
    up: str = "z",
    fmt: str = "npz",
    camouflage: bool = True,
    clutter: str | None = None,
    noise_sigma: float = 0.0,
    seed: int = 0,
    backend: str = "raycast",
) -> Path:
    """Render chips of a mesh (or mesh file) into a folder with a Parquet manifest.

    Writes (each file atomically):

    * ``fmt="npz"``: ``chips_<channel>.npz`` holding one ``(N, S, S)`` array
      ``chips`` per channel;
    * ``fmt="png"``: ``<channel>/chip_00000.png`` (intensity/shape 8-bit, mask 0/255)
      and ``depth/chip_00000.tiff`` (float32 mm, NaN = no surface);
    * ``manifest.parquet``: one row per chip, every pose and camera field
      (:func:`~prism3d.atr.poses.poses_table`), ``target``, ``chip``, the light, the
      file names, ``size``, ``framing`` and ``schema_version``.

    Returns
    -------
    Path
        The manifest path.
    """
    from prism3d.io.atomic import atomic_path

    check_choice(fmt, "fmt", ("npz", "png"))
    if not isinstance(mesh, SceneMesh):
        mesh = load_mesh_file(mesh, units=units, up=up)
    chips = render_chips(
        mesh,
        None,
        azimuth=azimuth,
        elevation=elevation,
        range_mm=range_mm,
        size=size,
        framing=framing,
        pixels_per_m=pixels_per_m,
        channels=channels,
        camouflage=camouflage,
        clutter=clutter,
        noise_sigma=noise_sigma,
        seed=seed,
        backend=backend,
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = chips.table.copy()
    for ch, arr in chips.channels.items():
        if fmt == "npz":
            fn = f"chips_{ch}.npz"
            with atomic_path(out / fn) as tmp, open(tmp, "wb") as fh:
                np.savez_compressed(fh, chips=arr)
            table[f"file_{ch}"] = [f"{fn}#{i}" for i in range(len(chips))]
        else:
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
                with atomic_path(out / fn) as tmp:
                    tmp.write_bytes(buf.tobytes())
                names.append(fn)
            table[f"file_{ch}"] = names
    table["size"] = size
    table["framing"] = framing
    table["schema_version"] = CHIP_SCHEMA_VERSION
    manifest = out / "manifest.parquet"
    with atomic_path(manifest) as tmp:
        table.to_parquet(tmp, index=False)
    return manifest
