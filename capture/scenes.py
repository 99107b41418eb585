"""Test scenes for the virtual rig: textured plate, chessboard, turntable poses.

Materials: ``metadata["material"]`` names a key of
:data:`prism3d.capture.camera_effects.MATERIALS` (default ``painted_metal``; the
chessboard is ``matte_paper``). Flat objects use OpenCV-like frames (mm, x right, y down,
front side facing -z), so ``T_rig_obj = translation(0, 0, z)`` faces the rig. The
turntable world frame is z-up, its axis the world z axis.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d import geometry
from prism3d.capture._scene_kernels import value_noise as _kernel
from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.rig import StereoRig, look_at
from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError
from prism3d.geometry import make_transform

__all__ = [
    "TextureAlbedo",
    "ChessboardAlbedo",
    "value_noise",
    "grid_sheet",
    "flat_plate",
    "chessboard",
    "chessboard_corners",
    "from_trimesh",
    "translation",
    "rotation_about",
    "place_at",
    "turntable_poses",
    "calibration_board_poses",
    "BoardPoseOptions",
]

def value_noise(points: NDArray[np.float64], cell_mm: float, seed: int = 0) -> NDArray[np.float64]:
    """Smooth 3-D value noise in [0, 1] at ``points`` ``(N, 3)`` mm: hashed lattice
    values (spacing ``cell_mm``, ``seed``) blended with the quintic fade curve.

    References
    ----------
    .. [1] K. Perlin, "Improving noise", SIGGRAPH 2002 (the quintic fade curve).
    """
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    cell = check_positive(cell_mm, "cell_mm")
    out = np.empty(len(p))
    _kernel(p, 1.0 / cell, np.uint64(int(seed) & 0xFFFFFFFF), out)
    return out


@dataclass(frozen=True)
class TextureAlbedo:
    """A mild grey speckle texture (two octaves of value noise) around ``base``.

    Gives unstructured-light (passive) stereo something to match when the projector
    is off, while staying close to a uniform grey plate.
    """

    seed: int = 0
    cell_mm: float = 2.0
    base: float = 0.6
    amplitude: float = 0.2

    def __call__(self, points_obj: NDArray[np.float64]) -> NDArray[np.float64]:
        n = 0.65 * value_noise(points_obj, self.cell_mm, self.seed) + 0.35 * value_noise(
            points_obj, self.cell_mm * 0.5, self.seed + 1
        )
        g = np.clip(self.base + self.amplitude * (2.0 * n - 1.0), 0.0, 1.0)
        return np.repeat(g[:, None], 3, axis=1)


@dataclass(frozen=True)
class ChessboardAlbedo:
    """Exact chessboard albedo in the board plane (object frame of :func:`chessboard`).

    Inner corner ``(i, j)`` sits at ``(i * square_mm, j * square_mm, 0)``; the square
    containing the origin's upper-left neighbour ``(-s..0, -s..0)`` is black; outside
    the ``(cols + 1) x (rows + 1)`` squares the board is white (the margin).
    """

    cols: int = 9
    rows: int = 6
    square_mm: float = 25.0
    black: float = 0.05
    white: float = 0.95

    def __call__(self, points_obj: NDArray[np.float64]) -> NDArray[np.float64]:
        p = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3)
        a = np.floor(p[:, 0] / self.square_mm).astype(np.int64) + 1
        b = np.floor(p[:, 1] / self.square_mm).astype(np.int64) + 1
        inside = (a >= 0) & (a <= self.cols) & (b >= 0) & (b <= self.rows)
        is_black = inside & ((a + b) % 2 == 0)
        g = np.where(is_black, self.black, self.white)
        return np.repeat(g[:, None], 3, axis=1)


def grid_sheet(
    x0: float, x1: float, y0: float, y1: float, nx: int, ny: int
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """A flat rectangle in z = 0 split into ``nx x ny`` cells (2 triangles each).

    Triangles are counter-clockwise seen from -z (the front side faces -z).
    """
    nx = max(1, int(nx))
    ny = max(1, int(ny))
    xs = np.linspace(x0, x1, nx + 1)
    ys = np.linspace(y0, y1, ny + 1)
    X, Y = np.meshgrid(xs, ys)
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
    a = idx[:-1, :-1].ravel()
    b = idx[:-1, 1:].ravel()
    c = idx[1:, :-1].ravel()
    d = idx[1:, 1:].ravel()
    # a top-left, b top-right, c bottom-left, d bottom-right (y down): the winding
    # (a, c, b) has normal (c - a) x (b - a) = -z, i.e. counter-clockwise from -z.
    F = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return V, F.astype(np.int64)


def flat_plate(
    width_mm: float = 300.0,
    height_mm: float = 300.0,
    *,
    albedo: object | None = None,
    cell_mm: float = 5.0,
    name: str = "plate",
    material: str | None = None,
) -> SceneMesh:
    """A flat plate centred on its origin in z = 0, front side facing -z, of
    ``width_mm x height_mm``. ``albedo``: a field (points -> (N, 3)) or one RGB colour;
    default a mild grey speckle (:class:`TextureAlbedo`) for passive matching. ``cell_mm``:
    triangle size (per-vertex colours in pyrender). ``material``: ``metadata["material"]``."""
    w = check_positive(width_mm, "width_mm")
    h = check_positive(height_mm, "height_mm")
    cell = check_positive(cell_mm, "cell_mm")
    V, F = grid_sheet(-w / 2, w / 2, -h / 2, h / 2, math.ceil(w / cell), math.ceil(h / cell))
    if albedo is None:
        field = TextureAlbedo()
    elif callable(albedo):
        field = albedo
    else:
        rgb = check_array(albedo, "albedo", shape=(3,), dtype_kind="fiu").astype(np.float64)
        if rgb.min() < 0 or rgb.max() > 1:
            raise InputError(f"albedo: RGB values must lie in [0, 1], got {tuple(rgb)}")
        field = UniformAlbedo(tuple(float(v) for v in rgb))
    metadata: dict[str, object] = {"width_mm": w, "height_mm": h}
    if material is not None:
        if not isinstance(material, str) or not material:
            raise InputError(f"material: expected a material class name, got {material!r}")
        metadata["material"] = material
    return SceneMesh(V, F, albedo_field=field, name=name, metadata=metadata)


def chessboard(
    cols: int = 9,
    rows: int = 6,
    square_mm: float = 25.0,
    margin_squares: float = 1.0,
    *,
    name: str = "chessboard",
) -> SceneMesh:
    """A chessboard with ``cols x rows`` INNER corners (OpenCV; 9 x 6 = 10 x 7 squares):
    origin at the first inner corner, x along the columns, y along the rows, printed side
    facing -z, a white margin of ``margin_squares``; exact albedo, ``matte_paper``."""
    cols = int(cols)
    rows = int(rows)
    if cols < 2 or rows < 2:
        raise InputError(f"chessboard: need at least 2x2 inner corners, got {cols}x{rows}")
    s = check_positive(square_mm, "square_mm")
    m = check_positive(margin_squares, "margin_squares", strict=False)
    x0, x1 = -s * (1 + m), s * (cols + m)
    y0, y1 = -s * (1 + m), s * (rows + m)
    V, F = grid_sheet(x0, x1, y0, y1, math.ceil((x1 - x0) / s) * 2, math.ceil((y1 - y0) / s) * 2)
    return SceneMesh(
        V,
        F,
        albedo_field=ChessboardAlbedo(cols, rows, s),
        name=name,
        metadata={
            "cols": cols, "rows": rows, "square_mm": s, "margin_squares": m, "material": "matte_paper",
        },
    )


def chessboard_corners(cols: int = 9, rows: int = 6, square_mm: float = 25.0) -> NDArray[np.float64]:
    """Inner corners ``(cols * rows, 3)`` float64 in the :func:`chessboard` frame, row by
    row (``cv2.findChessboardCorners`` order for an unrotated board; docs/calibration.md)."""
    s = check_positive(square_mm, "square_mm")
    j, i = np.mgrid[0 : int(rows), 0 : int(cols)]
    return np.stack([i.ravel() * s, j.ravel() * s, np.zeros(i.size)], axis=1)


def from_trimesh(mesh: object, *, name: str = "mesh", scale_to_mm: float = 1.0, albedo: object | None = None) -> SceneMesh:
    """Convert a ``trimesh.Trimesh`` to a :class:`SceneMesh` (vertex colours kept)."""
    V = np.asarray(mesh.vertices, dtype=np.float64) * float(scale_to_mm)  # type: ignore[attr-defined]
    F = np.asarray(mesh.faces, dtype=np.int64)  # type: ignore[attr-defined]
    va = None
    vis = getattr(mesh, "visual", None)
    if albedo is None and vis is not None and getattr(vis, "kind", None) == "vertex":
        va = np.asarray(vis.vertex_colors, dtype=np.float64)[:, :3] / 255.0
    return SceneMesh(V, F, vertex_albedo=va, albedo_field=albedo, name=name)  # type: ignore[arg-type]


def translation(x: float, y: float, z: float) -> NDArray[np.float64]:
    """4x4 translation."""
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def rotation_about(axis: Sequence[float], angle_rad: float) -> NDArray[np.float64]:
    """4x4 rotation by ``angle_rad`` about ``axis`` (non-zero) through the origin."""
    return make_transform(geometry.rotation_about(axis, angle_rad))


def place_at(mesh: SceneMesh, distance_mm: float, *, R: NDArray | None = None) -> NDArray[np.float64]:
    """``T_rig_obj`` putting the mesh's bounding-box centre at ``(0, 0, distance_mm)``
    in the rig frame, after rotating it by ``R`` (3x3, default identity)."""
    d = check_positive(distance_mm, "distance_mm")
    Rm = np.eye(3) if R is None else check_array(R, "R", shape=(3, 3)).astype(np.float64)
    centre = mesh.bounds.mean(axis=0)
    T = np.eye(4)
    T[:3, :3] = Rm
    T[:3, 3] = np.array([0.0, 0.0, d]) - Rm @ centre
    return T


def turntable_poses(
    n_views: int = 8,
    step_deg: float = 45.0,
    *,
    distance_mm: float = 1250.0,
    elevation_deg: float = 15.0,
    start_deg: float = 0.0,
    target: Sequence[float] = (0.0, 0.0, 0.0),
) -> list[NDArray[np.float64]]:
    """Rig poses ``T_world_rig`` around a turntable (world z up): view ``k`` from azimuth
    ``start_deg + k * step_deg`` (from the world -y axis), raised by ``elevation_deg``,
    ``distance_mm`` from ``target``."""
    n = int(n_views)
    if n < 1:
        raise InputError(f"n_views: expected >= 1, got {n_views}")
    d = check_positive(distance_mm, "distance_mm")
    tgt = np.asarray(target, dtype=np.float64)
    el = math.radians(float(elevation_deg))
    if abs(el) >= math.pi / 2:
        raise InputError(f"elevation_deg: expected within (-90, 90), got {elevation_deg}")
    poses = []
    for k in range(n):
        az = math.radians(float(start_deg) + k * float(step_deg))
        direction = np.array(
            [math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)]
        )
        eye = tgt + d * direction
        poses.append(look_at(eye, tgt, up=np.array([0.0, 0.0, 1.0])))
    return poses


def _board_outline(cols: int, rows: int, s: float, margin: float) -> NDArray[np.float64]:
    x0, x1 = -s * (1 + margin), s * (cols + margin)
    y0, y1 = -s * (1 + margin), s * (rows + margin)
    return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)


@dataclass(frozen=True)
class BoardPoseOptions:
    """How :func:`calibration_board_poses` varies the chessboard (defaults: the paper rig's
    working range; tilts as docs/calibration.md recommends)."""

    cols: int = 9
    """Inner corners per row."""
    rows: int = 6
    """Inner corners per column."""
    square_mm: float = 25.0
    """Square size, mm."""
    margin_squares: float = 1.0
    """White margin around the squares, in squares (must stay inside the views too)."""
    distance_range_mm: tuple[float, float] = (1100.0, 1400.0)
    """Board centre depth range, mm: around the paper rig's 1250 mm working distance."""
    tilt_range_deg: tuple[float, float] = (20.0, 40.0)
    """Tilt range about an in-plane axis, deg: tilts pin f and the principal point, until
    foreshortening spoils the corners near 45 deg (Zhang 2000)."""
    edge_px: float = 20.0
    """Room kept between the board outline and each view's border, px."""
    seed: int = 0
    """Random seed of the poses."""
    max_tries: int = 20000
    """Random poses tried before giving up (the board is too large for the views)."""

    def __post_init__(self) -> None:
        if int(self.cols) < 2 or int(self.rows) < 2:
            raise InputError(f"cols, rows: expected at least 2x2 inner corners, got {self.cols}x{self.rows}")
        check_positive(self.square_mm, "square_mm")
        check_positive(self.margin_squares, "margin_squares", strict=False)
        check_positive(self.edge_px, "edge_px", strict=False)
        for name in ("distance_range_mm", "tilt_range_deg"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not lo <= hi:
                raise InputError(f"{name}: expected (low, high) with low <= high, got {getattr(self, name)}")
        check_positive(self.distance_range_mm[0], "distance_range_mm")
        if int(self.max_tries) < 1:
            raise InputError(f"max_tries: expected >= 1, got {self.max_tries}")


#: Random pose spread: jitter of the tilt axis direction (rad) about its even spread,
#: in-plane turn about portrait orientation (deg), lateral offset as a fraction of the
#: half field (x, y) -- enough variety for the calibration, with the board kept in view.
_AXIS_JITTER_RAD = 0.2
_SPIN_JITTER_DEG = 15.0
_OFFSET_FRACTION = (0.3, 0.5)


def _random_board_pose(
    rng: np.random.Generator, k: int, n: int, rig: StereoRig, o: BoardPoseOptions, centre: NDArray
) -> NDArray[np.float64]:
    """Pose ``k`` of ``n``: tilt axes spread evenly over the poses, portrait orientation."""
    tilt = math.radians(rng.uniform(*o.tilt_range_deg))
    axis_angle = math.pi * (k / n) + rng.uniform(-_AXIS_JITTER_RAD, _AXIS_JITTER_RAD)
    axis = np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0])
    spin = math.radians(90.0 + rng.uniform(-_SPIN_JITTER_DEG, _SPIN_JITTER_DEG))
    z = rng.uniform(*o.distance_range_mm)
    half_field = 0.5 * rig.left.width / rig.left.fx * z
    x = rng.uniform(-_OFFSET_FRACTION[0], _OFFSET_FRACTION[0]) * half_field
    y = rng.uniform(-_OFFSET_FRACTION[1], _OFFSET_FRACTION[1]) * half_field * rig.left.height / rig.left.width
    R = rotation_about(axis, tilt) @ rotation_about((0, 0, 1), spin)
    return translation(x, y, z) @ R @ translation(*(-centre))


def _inside_both_views(rig: StereoRig, pts_rig: NDArray, edge_px: float) -> bool:
    for T_rig_cam, cam in ((rig.T_rig_left, rig.left), (rig.T_rig_right, rig.right)):
        T_cam_rig = np.linalg.inv(T_rig_cam)
        uv = cam.project(pts_rig @ T_cam_rig[:3, :3].T + T_cam_rig[:3, 3])
        w, h = cam.size
        if not (
            np.all(np.isfinite(uv))
            and uv[:, 0].min() >= edge_px
            and uv[:, 1].min() >= edge_px
            and uv[:, 0].max() <= w - 1 - edge_px
            and uv[:, 1].max() <= h - 1 - edge_px
        ):
            return False
    return True


def calibration_board_poses(
    rig: StereoRig, n: int = 5, *, options: BoardPoseOptions | None = None
) -> list[NDArray[np.float64]]:
    """Varied, well-conditioned chessboard poses ``T_rig_board`` ``(4, 4)`` seen by both views.

    Each pose tilts the board about an in-plane axis, turns it in-plane around portrait
    orientation and places it in the depth range with a lateral offset; a pose is kept
    only when the whole board (with its margin) projects inside both views.
    """
    o = BoardPoseOptions() if options is None else options
    if not isinstance(o, BoardPoseOptions):
        raise InputError(f"options: expected BoardPoseOptions, got {type(o).__name__}")
    n = int(n)
    if n < 1:
        raise InputError(f"n: expected >= 1, got {n}")
    rng = np.random.default_rng(o.seed)
    outline = _board_outline(o.cols, o.rows, o.square_mm, o.margin_squares)
    centre = outline.mean(axis=0)
    poses: list[NDArray[np.float64]] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > o.max_tries:
            raise InputError(
                f"could not place {n} chessboards inside both views (placed {len(poses)}); "
                "the board is too large for this rig's field of view"
            )
        T = _random_board_pose(rng, len(poses), n, rig, o, centre)
        if _inside_both_views(rig, outline @ T[:3, :3].T + T[:3, 3], o.edge_px):
            poses.append(T)
    return poses
