"""One renderer interface for the virtual rig and for ATR chip rendering.

A render takes a list of ``(SceneMesh, T_world_obj)`` and a camera
(:class:`~prism3d.capture.rig.CameraModel` + ``T_world_cam``) and returns a
:class:`RenderResult` of per-pixel maps.

Backends
--------
:class:`RaycastRenderer`
    Exact geometry. Rays go through the DISTORTED pixel centres
    (``CameraModel.pixel_rays``, exact inversion of the distortion model), are cast
    in float32 by Open3D's ``RaycastingScene`` to find the hit triangle, and the hit
    is then recomputed in float64 (Moller-Trumbore on the hit triangle), so a plane
    at depth z renders depth z to ~1e-9 mm and every pixel sees exactly what
    ``CameraModel.project`` predicts. Build once, render many cameras.
:class:`~prism3d.capture._pyrender_backend.PyrenderRenderer`
    Fast OpenGL (OSMesa) rasterisation for chips: RGB, depth, mask; pinhole only.

Also here: :func:`box_downsample` (supersampling), :class:`SensorNoise` (shot +
read noise), :func:`gaussian_blur`, :func:`quantize`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.capture.rig import CameraModel
from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError

__all__ = [
    "RenderResult",
    "RayHits",
    "RaycastRenderer",
    "PyrenderRenderer",
    "camera_rays",
    "box_downsample",
    "SensorNoise",
    "gaussian_blur",
    "quantize",
]

#: Rays per Open3D call (bounds temporary memory to a few hundred MB).
_CHUNK = 1 << 20


@dataclass(eq=False)
class RenderResult:
    """Per-pixel output of a render, ``(H, W)`` = the camera's ``(height, width)``.

    Attributes
    ----------
    depth_mm : (H, W) float32
        Depth along the camera z axis, mm; NaN where no surface.
    normals_cam : (H, W, 3) float32
        Unit surface normals in the OpenCV camera frame, turned to face the camera;
        NaN where no surface.
    points_world : (H, W, 3) float64
        Hit points in the world frame, mm; NaN where no surface.
    albedo : (H, W, 3) float32
        Surface albedo in [0, 1] (``SceneMesh.albedo_at``); 0 where no surface.
    mask : (H, W) bool
        True where a surface was hit.
    object_id : (H, W) int32
        Index of the object (order of the objects list) hit, -1 for none.
    face_id : (H, W) int64
        Triangle index within that object's mesh, -1 for none.
    rgb : (H, W, 3) uint8 or None
        Shaded colour image (pyrender backend only).
    """

    depth_mm: NDArray[np.float32]
    normals_cam: NDArray[np.float32]
    points_world: NDArray[np.float64]
    albedo: NDArray[np.float32]
    mask: NDArray[np.bool_]
    object_id: NDArray[np.int32]
    face_id: NDArray[np.int64]
    rgb: NDArray[np.uint8] | None = None


@dataclass(eq=False)
class RayHits:
    """Float64-refined ray hits for ``N`` rays (see :meth:`RaycastRenderer.cast`).

    Attributes
    ----------
    t : (N,) float64
        Distance along the (unit) ray, mm; inf for a miss.
    object_id : (N,) int32
        Object index, -1 for a miss.
    face_id : (N,) int64
        Triangle index within the object, -1 for a miss.
    bary_uv : (N, 2) float64
        Barycentric (u, v), Open3D convention ``p = (1-u-v) a + u b + v c``.
    points : (N, 3) float64
        Hit points (world), NaN for a miss.
    normals : (N, 3) float64
        Unit geometric normals (world) facing against the ray, NaN for a miss.
    """

    t: NDArray[np.float64]
    object_id: NDArray[np.int32]
    face_id: NDArray[np.int64]
    bary_uv: NDArray[np.float64]
    points: NDArray[np.float64]
    normals: NDArray[np.float64]

    @property
    def hit(self) -> NDArray[np.bool_]:
        return self.object_id >= 0


def _check_pose(T: NDArray, name: str) -> NDArray[np.float64]:
    T = check_array(T, name, shape=(4, 4), dtype_kind="fiu").astype(np.float64)
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"{name}: expected a finite rigid 4x4 transform")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise InputError(f"{name}: rotation part is not a proper rotation")
    return T


def _check_objects(objects: Sequence[tuple[SceneMesh, NDArray]]) -> list[tuple[SceneMesh, NDArray[np.float64]]]:
    try:
        items = list(objects)
    except TypeError as exc:
        raise InputError("objects: expected a list of (SceneMesh, T_world_obj) pairs") from exc
    if not items:
        raise InputError("objects: the scene is empty (expected at least one (SceneMesh, T_world_obj))")
    out = []
    for i, item in enumerate(items):
        if not (isinstance(item, tuple | list) and len(item) == 2 and isinstance(item[0], SceneMesh)):
            raise InputError(f"objects[{i}]: expected a (SceneMesh, T_world_obj) pair, got {type(item).__name__}")
        out.append((item[0], _check_pose(item[1], f"objects[{i}] pose")))
    return out


class RaycastRenderer:
    """Exact ray-casting renderer (Open3D ``RaycastingScene`` + float64 refinement).

    Parameters
    ----------
    objects : sequence of (SceneMesh, (4, 4) float64)
        Meshes and their poses ``T_world_obj``. The scene is built once; render as
        many cameras as needed.

    Notes
    -----
    Open3D intersects in float32, which only decides *which* triangle a ray hits;
    distances, barycentric coordinates, points and normals are recomputed in float64
    on that triangle (Moller-Trumbore). A ray that float32 puts a hair beside a
    triangle edge may pick the neighbouring triangle: on a continuous surface that
    gives the same point. Normals are the flat (geometric) triangle normals.

    References
    ----------
    .. [1] T. Moller, B. Trumbore, "Fast, minimum storage ray-triangle intersection",
       Journal of Graphics Tools 2 (1997).
    """

    def __init__(self, objects: Sequence[tuple[SceneMesh, NDArray]]) -> None:
        import open3d as o3d

        items = _check_objects(objects)
        self._meshes = [m for m, _ in items]
        self._poses = [T for _, T in items]
        self._poses_inv = [np.linalg.inv(T) for T in self._poses]
        self._scene = o3d.t.geometry.RaycastingScene()
        a_list, e1_list, e2_list, n_list = [], [], [], []
        offsets = [0]
        gid_to_obj = {}
        for i, (mesh, T) in enumerate(items):
            v = mesh.vertices @ T[:3, :3].T + T[:3, 3]
            tri = v[mesh.faces]
            e1 = tri[:, 1] - tri[:, 0]
            e2 = tri[:, 2] - tri[:, 0]
            n = np.cross(e1, e2)
            nn = np.linalg.norm(n, axis=1, keepdims=True)
            with np.errstate(invalid="ignore", divide="ignore"):
                n = n / nn
            a_list.append(tri[:, 0])
            e1_list.append(e1)
            e2_list.append(e2)
            n_list.append(n)
            gid = self._scene.add_triangles(
                o3d.core.Tensor(v.astype(np.float32)),
                o3d.core.Tensor(mesh.faces.astype(np.uint32)),
            )
            gid_to_obj[int(gid)] = i
            offsets.append(offsets[-1] + len(mesh.faces))
        self._gid_map = np.full(max(gid_to_obj) + 2, -1, dtype=np.int32)
        for g, i in gid_to_obj.items():
            self._gid_map[g] = i
        self._a = np.concatenate(a_list)
        self._e1 = np.concatenate(e1_list)
        self._e2 = np.concatenate(e2_list)
        self._n = np.concatenate(n_list)
        self._offsets = np.asarray(offsets, dtype=np.int64)

    @property
    def n_objects(self) -> int:
        return len(self._meshes)

    # -- rays -------------------------------------------------------------------------
    def cast(self, origins: NDArray, directions: NDArray, *, normalized: bool = False) -> RayHits:
        """Intersect rays with the scene, refined in float64.

        Parameters
        ----------
        origins : (N, 3) or (3,) float64
            Ray origins (world, mm); one origin is broadcast to all rays.
        directions : (N, 3) float64
            Ray directions (world); normalised internally (unless ``normalized``
            says they already are), so ``t`` is a distance.
        """
        d = check_array(directions, "directions", shape=(None, 3), dtype_kind="f").astype(np.float64)
        o = np.asarray(origins, dtype=np.float64)
        shared = o.shape == (3,)
        if not shared and o.shape != d.shape:
            raise InputError(f"origins: expected shape (3,) or {d.shape}, got {o.shape}")
        n = len(d)
        t = np.full(n, np.inf)
        obj = np.full(n, -1, dtype=np.int32)
        face = np.full(n, -1, dtype=np.int64)
        uv = np.zeros((n, 2))
        pts = np.full((n, 3), np.nan)
        nrm = np.full((n, 3), np.nan)
        for s in range(0, n, _CHUNK):
            e = min(n, s + _CHUNK)
            oc = o.reshape(1, 3) if shared else o[s:e]
            dc = d[s:e] if normalized else d[s:e] / np.linalg.norm(d[s:e], axis=1, keepdims=True)
            self._cast_chunk(oc, dc, t[s:e], obj[s:e], face[s:e], uv[s:e], pts[s:e], nrm[s:e])
        return RayHits(t, obj, face, uv, pts, nrm)

    def _cast_chunk(self, o, d, t_out, obj_out, face_out, uv_out, pts_out, nrm_out) -> None:
        import open3d as o3d

        from prism3d.capture._render_kernels import refine_hits

        rays = np.empty((len(d), 6), dtype=np.float32)
        rays[:, :3] = o
        rays[:, 3:] = d
        ans = self._scene.cast_rays(o3d.core.Tensor(rays), nthreads=0)
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        t32 = ans["t_hit"].numpy()
        hit = (gid != np.iinfo(np.uint32).max) & np.isfinite(t32)
        if not np.any(hit):
            return
        idx = np.nonzero(hit)[0]
        objs = self._gid_map[np.minimum(gid[idx], len(self._gid_map) - 1)]
        prim = ans["primitive_ids"].numpy()[idx].astype(np.int64)
        gface = self._offsets[objs] + prim
        m = len(idx)
        tt = np.empty(m)
        uvv = np.empty((m, 2))
        pp = np.empty((m, 3))
        nn = np.empty((m, 3))
        oo = np.ascontiguousarray(o if len(o) == 1 else o[idx])
        refine_hits(
            oo,
            np.ascontiguousarray(d[idx]),
            gface,
            self._a,
            self._e1,
            self._e2,
            self._n,
            t32[idx].astype(np.float64),
            ans["primitive_uvs"].numpy()[idx].astype(np.float64),
            tt,
            uvv,
            pp,
            nn,
        )
        t_out[idx] = tt
        obj_out[idx] = objs
        face_out[idx] = prim
        uv_out[idx] = uvv
        pts_out[idx] = pp
        nrm_out[idx] = nn

    def albedo(self, hits: RayHits) -> NDArray[np.float64]:
        """Albedo ``(N, 3)`` float64 at the hits (0 for misses), via ``SceneMesh.albedo_at``."""
        out = np.zeros((len(hits.t), 3))
        for i, mesh in enumerate(self._meshes):
            sel = np.nonzero(hits.object_id == i)[0]
            if len(sel) == 0:
                continue
            Ti = self._poses_inv[i]
            p_obj = hits.points[sel] @ Ti[:3, :3].T + Ti[:3, 3]
            out[sel] = mesh.albedo_at(p_obj, hits.face_id[sel], hits.bary_uv[sel])
        return out

    def visible_from(
        self, points_world: NDArray, source_world: NDArray, *, tol_mm: float = 1e-3
    ) -> NDArray[np.bool_]:
        """True where the segment from ``source_world`` to a point is unobstructed.

        A ray is cast from the source towards each point; the point is visible when
        the first hit lies no nearer than the point itself (minus
        ``tol_mm + 1e-7 * distance``). Points that are NaN give False.
        """
        p = check_array(points_world, "points_world", shape=(None, 3)).astype(np.float64)
        src = check_array(source_world, "source_world", shape=(3,)).astype(np.float64)
        out = np.zeros(len(p), dtype=bool)
        ok = np.all(np.isfinite(p), axis=1)
        if not np.any(ok):
            return out
        d = p[ok] - src
        dist = np.linalg.norm(d, axis=1)
        good = dist > 0
        hits = self.cast(src, np.where(good[:, None], d, np.array([0.0, 0.0, 1.0])))
        vis = hits.t >= dist - (float(tol_mm) + 1e-7 * dist)
        out[np.nonzero(ok)[0]] = vis & good
        return out

    # -- cameras ----------------------------------------------------------------------
    def render(
        self,
        camera: CameraModel,
        T_world_cam: NDArray,
        *,
        with_albedo: bool = True,
    ) -> RenderResult:
        """Render ``camera`` at pose ``T_world_cam`` (OpenCV frame).

        Rays pass through every distorted pixel centre, so distortion is exact.
        ``with_albedo=False`` skips the albedo evaluation (the map is then zeros).
        """
        if not isinstance(camera, CameraModel):
            raise InputError(f"camera: expected a CameraModel, got {type(camera).__name__}")
        T = _check_pose(T_world_cam, "T_world_cam")
        w, h = camera.size
        rays, z_cam = camera_rays(camera, T[:3, :3])
        hits = self.cast(T[:3, 3], rays.reshape(-1, 3), normalized=True)
        return self._result(hits, z_cam.reshape(-1), T, (h, w), with_albedo)

    def _result(self, hits: RayHits, z_cam, T, hw, with_albedo) -> RenderResult:
        h, w = hw
        m = hits.hit
        depth = hits.t * z_cam  # inf * z for misses, replaced below
        depth[~m] = np.nan
        normals_cam = hits.normals @ T[:3, :3]  # R^T n for each row
        alb = self.albedo(hits) if with_albedo else np.zeros((len(m), 3))
        return RenderResult(
            depth_mm=depth.astype(np.float32).reshape(h, w),
            normals_cam=normals_cam.astype(np.float32).reshape(h, w, 3),
            points_world=hits.points.reshape(h, w, 3),
            albedo=alb.astype(np.float32).reshape(h, w, 3),
            mask=m.reshape(h, w),
            object_id=hits.object_id.reshape(h, w),
            face_id=hits.face_id.reshape(h, w),
        )


def camera_rays(
    camera: CameraModel, R_world_cam: NDArray | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit rays through every distorted pixel centre.

    Returns ``(rays, z_cam)``: ``rays`` ``(H, W, 3)`` float64 in the world frame
    (``R_world_cam @ ray_cam``; camera frame when ``R_world_cam`` is None) and
    ``z_cam`` ``(H, W)``, the rays' camera-frame z component (depth = t * z_cam).
    Same rays as ``camera.pixel_grid_rays()`` (exact Newton inversion of the
    distortion model), computed by a parallel numba kernel.
    """
    from prism3d.capture._render_kernels import grid_rays

    R = np.eye(3) if R_world_cam is None else np.asarray(R_world_cam, dtype=np.float64)
    w, h = camera.size
    out = np.empty((h, w, 3), dtype=np.float64)
    out_z = np.empty((h, w), dtype=np.float64)
    grid_rays(
        np.ascontiguousarray(camera.K), np.ascontiguousarray(camera.dist), w, h,
        np.ascontiguousarray(R), out, out_z,
    )
    return out, out_z


def __getattr__(name: str) -> object:
    # PyrenderRenderer lives in its own module (OpenGL imports are heavy); import lazily.
    if name == "PyrenderRenderer":
        from prism3d.capture._pyrender_backend import PyrenderRenderer

        return PyrenderRenderer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# -- image formation helpers -----------------------------------------------------------
def box_downsample(image: NDArray, factor: int) -> NDArray[np.float64]:
    """Average non-overlapping ``factor x factor`` blocks of ``(H*f, W*f[, C])``.

    With the pixel-centre convention of :meth:`CameraModel.scaled`, block ``(r, c)``
    covers exactly output pixel ``(r, c)``.
    """
    f = int(factor)
    if f < 1 or f != factor:
        raise InputError(f"factor: expected an integer >= 1, got {factor}")
    img = check_array(image, "image", ndim=(2, 3))
    if f == 1:
        return img.astype(np.float64)
    H, W = img.shape[:2]
    if H % f or W % f:
        raise InputError(f"image: size {W}x{H} is not a multiple of the factor {f}")
    shp = (H // f, f, W // f, f) + img.shape[2:]
    return img.reshape(shp).mean(axis=(1, 3), dtype=np.float64)


def gaussian_blur(image: NDArray, sigma_px: float) -> NDArray:
    """Gaussian blur (optics / defocus) with standard deviation ``sigma_px``; 0 = none."""
    import cv2

    s = check_positive(sigma_px, "sigma_px", strict=False)
    if s == 0:
        return image
    img = np.asarray(image)
    k = 2 * int(np.ceil(3.5 * s)) + 1
    return cv2.GaussianBlur(img, (k, k), sigmaX=s, sigmaY=s, borderType=cv2.BORDER_REFLECT)


@dataclass(frozen=True)
class SensorNoise:
    """A simple sensor model: photon shot noise + Gaussian read noise, in DN.

    A signal of ``x`` DN (0-255 scale) collects ``x * gain_e_per_dn`` electrons, which
    are Poisson-distributed; read noise adds ``N(0, read_noise_dn)``.

    Attributes
    ----------
    gain_e_per_dn : float
        Electrons per digital number (full scale 255 DN = ``255 * gain`` electrons).
        Larger = less shot noise. Default 40 (full well ~10 000 e-).
    read_noise_dn : float
        Standard deviation of the read noise, DN.
    """

    gain_e_per_dn: float = 40.0
    read_noise_dn: float = 1.0

    def __post_init__(self) -> None:
        check_positive(self.gain_e_per_dn, "gain_e_per_dn")
        check_positive(self.read_noise_dn, "read_noise_dn", strict=False)

    def apply(self, image01: NDArray, rng: np.random.Generator) -> NDArray[np.float64]:
        """Noisy image in DN (float64, unclipped) from a clean image in [0, 1]."""
        x = np.clip(np.asarray(image01, dtype=np.float64), 0.0, 1.0) * 255.0
        electrons = rng.poisson(x * self.gain_e_per_dn)
        out = electrons / self.gain_e_per_dn
        if self.read_noise_dn > 0:
            out = out + rng.normal(0.0, self.read_noise_dn, size=x.shape)
        return out


def quantize(image_dn: NDArray) -> NDArray[np.uint8]:
    """Round DN values to uint8 with clipping to [0, 255]."""
    return np.clip(np.rint(np.asarray(image_dn, dtype=np.float64)), 0, 255).astype(np.uint8)
