"""Test scenes for the virtual rig: textured plate, chessboard, turntable poses.

Materials: a mesh may name its material class in ``metadata["material"]`` (a key
of :data:`prism3d.capture.camera_effects.MATERIALS`), which sets its flash gloss
when camera effects are on; a mesh without one is ``painted_metal``. The chessboard
is ``matte_paper``.

Frames (see DESIGN.md): millimetres, OpenCV-like object frames for flat objects
(x right, y down, the visible *front* side faces -z, i.e. towards a camera that looks
along +z). A plate placed with ``T_rig_obj = translation(0, 0, z)`` faces the rig.

The turntable (scene) world frame is z-up: the turntable axis is the world z axis
through the origin, the rig circles around it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.rig import StereoRig, look_at
from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError

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
]

def value_noise(points: NDArray[np.float64], cell_mm: float, seed: int = 0) -> NDArray[np.float64]:
    """Smooth 3-D value noise in [0, 1] at ``points`` ``(N, 3)`` mm.

    Pseudo-random values (a splitmix64 hash of the lattice coordinates and ``seed``)
    on an integer lattice of spacing ``cell_mm``, blended trilinearly with the
    quintic fade curve (C2-continuous). Exact and deterministic at any point.

    References
    ----------
    .. [1] K. Perlin, "Improving noise", SIGGRAPH 2002 (the quintic fade curve).
    """
    from prism3d.capture._scene_kernels import value_noise as _kernel

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
    """A flat plate centred on its origin in the plane z = 0, front side facing -z.

    Parameters
    ----------
    width_mm, height_mm : float
        Size along x and y.
    albedo : callable or (3,) tuple, optional
        An albedo field (points_obj -> (N, 3)) or one RGB colour. Default: a mild grey
        speckle :class:`TextureAlbedo` (so passive matching works without a pattern).
    cell_mm : float
        Triangle size (fine enough for per-vertex colours in the pyrender backend;
        the ray caster is exact with any subdivision).
    material : str, optional
        Material class (``metadata["material"]``, e.g. ``"lambertian"``); None
        leaves it unset (the camera effects' default, painted metal).
    """
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
    """A chessboard with ``cols x rows`` INNER corners (OpenCV convention).

    9 x 6 inner corners = 10 x 7 squares. The object frame has its origin at the first
    inner corner, x along the columns, y along the rows, the board in z = 0 with the
    printed side facing -z. The albedo (:class:`ChessboardAlbedo`) is exact per point:
    black 0.05, white 0.95, white margin of ``margin_squares`` squares all round;
    material ``matte_paper`` (a print on matte stock: a faint, broad flash sheen).
    """
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
    """Inner corners ``(cols * rows, 3)`` float64 in the :func:`chessboard` frame.

    Row by row (y), left to right (x) within a row -- the order
    ``cv2.findChessboardCorners`` returns for an unrotated board seen from the front
    (measured; ``cv2.findChessboardCornersSB`` returns the same corners in reverse
    order for this board, since 10 x 7 squares are not 180-degree symmetric).
    """
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
    """4x4 rotation by ``angle_rad`` about a unit ``axis`` through the origin (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if n == 0:
        raise InputError("rotation_about: axis must be non-zero")
    a = a / n
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * K @ K
    return T


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
    """Rig poses ``T_world_rig`` around a turntable (world z up, axis through origin).

    View ``k`` sees the target from azimuth ``start_deg + k * step_deg`` (about +z,
    measured from the world -y axis), raised by ``elevation_deg``, with the rig's
    z axis pointing at ``target`` from ``distance_mm`` away. Equivalent to turning
    the target by ``-k * step_deg`` in front of a fixed rig.
    """
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


def calibration_board_poses(
    rig: StereoRig,
    n: int = 5,
    *,
    cols: int = 9,
    rows: int = 6,
    square_mm: float = 25.0,
    margin_squares: float = 1.0,
    distance_range_mm: tuple[float, float] = (1100.0, 1400.0),
    tilt_range_deg: tuple[float, float] = (20.0, 40.0),
    edge_px: float = 20.0,
    seed: int = 0,
    max_tries: int = 20000,
) -> list[NDArray[np.float64]]:
    """Varied, well-conditioned chessboard poses ``T_rig_board`` seen by both views.

    Each pose tilts the board by an angle in ``tilt_range_deg`` about an in-plane axis
    (the axes' directions spread evenly over the poses), turns it in-plane around
    portrait orientation, and places it at a depth in ``distance_range_mm`` with a
    lateral offset; a pose is kept only when the whole board (with its white margin)
    projects inside both views with ``edge_px`` to spare.
    """
    n = int(n)
    if n < 1:
        raise InputError(f"n: expected >= 1, got {n}")
    rng = np.random.default_rng(seed)
    outline = _board_outline(cols, rows, square_mm, margin_squares)
    centre = outline.mean(axis=0)
    poses: list[NDArray[np.float64]] = []
    tries = 0
    T_left_rig = np.linalg.inv(rig.T_rig_left)
    T_right_rig = np.linalg.inv(rig.T_rig_right)
    while len(poses) < n:
        tries += 1
        if tries > max_tries:
            raise InputError(
                f"could not place {n} chessboards inside both views (placed {len(poses)}); "
                "the board is too large for this rig's field of view"
            )
        k = len(poses)
        tilt = math.radians(rng.uniform(*tilt_range_deg))
        axis_angle = math.pi * (k / n) + rng.uniform(-0.2, 0.2)
        axis = np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0])
        spin = math.radians(90.0 + rng.uniform(-15.0, 15.0))
        z = rng.uniform(*distance_range_mm)
        half_field = 0.5 * rig.left.width / rig.left.fx * z
        x = rng.uniform(-0.3, 0.3) * half_field
        y = rng.uniform(-0.5, 0.5) * half_field * rig.left.height / rig.left.width
        R = rotation_about(axis, tilt) @ rotation_about((0, 0, 1), spin)
        T = translation(x, y, z) @ R @ translation(*(-centre))
        pts = outline @ T[:3, :3].T + T[:3, 3]
        ok = True
        for T_cam_rig, cam in ((T_left_rig, rig.left), (T_right_rig, rig.right)):
            pc = pts @ T_cam_rig[:3, :3].T + T_cam_rig[:3, 3]
            uv = cam.project(pc)
            w, h = cam.size
            if not (
                np.all(np.isfinite(uv))
                and uv[:, 0].min() >= edge_px
                and uv[:, 1].min() >= edge_px
                and uv[:, 0].max() <= w - 1 - edge_px
                and uv[:, 1].max() <= h - 1 - edge_px
            ):
                ok = False
                break
        if ok:
            poses.append(T)
    return poses
