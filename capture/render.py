"""One renderer interface for the virtual rig and for ATR chip rendering.

A render takes ``(SceneMesh, T_world_obj)`` pairs and a camera (``CameraModel`` +
``T_world_cam``) and returns a :class:`RenderResult` of per-pixel maps. Backends:
:class:`RaycastRenderer` (exact geometry, distortion exact, float64 hits) and
:class:`~prism3d.capture.render_gl.PyrenderRenderer` (OpenGL rasterisation for chips, pinhole only). How and how
fast: docs/capture.md ("Renderers").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast as _narrow

import numpy as np
from numpy.typing import NDArray

from prism3d._env import configured_threads
from prism3d.capture._render_kernels import (
    cull_rays,
    grid_rays,
    on_plane,
    pack_rays_sel,
    pack_segments,
    quantize_u8,
    refine_compact,
    rotate_rays,
    sensor_noise,
)
from prism3d.capture.camouflage import CamouflageField
from prism3d.capture.mesh import SceneMesh
from prism3d.capture.rig import CameraModel
from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError

__all__ = [
    "CameraHits",
    "RayHits",
    "RaycastRenderer",
    "RenderResult",
    "SensorNoise",
    "box_downsample",
    "camera_rays",
    "check_objects",
    "check_pose",
    "configured_threads",
    "gaussian_blur",
    "quantize",
]

#: Rays per Open3D call (bounds temporary memory to a few hundred MB).
_CHUNK = 1 << 20
#: Camera models whose pixel rays a renderer keeps (a shot uses 1x, supersampled and
#: rectified cameras; ~32 bytes per pixel each).
_RAY_CACHE_SIZE = 3
#: Gaussian kernel half-width in sigmas: the weight beyond 3.5 sigma is < 0.05 %.
GAUSS_RADIUS_SIGMAS = 3.5
#: A point within this distance of a planar scene's plane counts as on it (mm).
_PLANE_TOL_MM = 1e-6


@dataclass(eq=False)
class RenderResult:
    """Per-pixel maps of a render, ``(H, W)`` = the camera's ``(height, width)``:
    ``depth_mm`` (H, W) float32 along camera z, NaN = no surface; ``normals_cam``
    (H, W, 3) float32, OpenCV camera frame, facing the camera, NaN = none;
    ``points_world`` (H, W, 3) float64 mm, NaN = none; ``albedo`` (H, W, 3) float32
    in [0, 1], 0 = none; ``mask`` (H, W) bool; ``object_id`` (H, W) int32 (-1 = none);
    ``face_id`` (H, W) int64 (-1 = none); ``rgb`` (H, W, 3) uint8 (pyrender only).
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
    """Float64-refined hits of ``N`` rays (:meth:`RaycastRenderer.cast`): ``t`` (N,) mm
    (inf = miss), ``object_id`` (N,) int32 and ``face_id`` (N,) int64 (-1 = miss),
    ``bary_uv`` (N, 2) (Open3D: ``p = (1-u-v) a + u b + v c``), ``points`` and unit
    ``normals`` (N, 3) world frame, normals facing against the ray (NaN = miss).
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


def check_pose(T: NDArray, name: str) -> NDArray[np.float64]:
    """``T`` as a (4, 4) float64 rigid transform, or InputError naming ``name``."""
    T = check_array(T, name, shape=(4, 4), dtype_kind="fiu").astype(np.float64)
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"{name}: expected a finite rigid 4x4 transform")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise InputError(f"{name}: rotation part is not a proper rotation")
    return T


def check_objects(objects: Sequence[tuple[SceneMesh, NDArray]]) -> list[tuple[SceneMesh, NDArray[np.float64]]]:
    """A non-empty scene as a list of (SceneMesh, (4, 4) float64 pose), or InputError."""
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
        out.append((item[0], check_pose(item[1], f"objects[{i}] pose")))
    return out


class RaycastRenderer:
    """Exact ray-casting renderer (Open3D ``RaycastingScene`` + float64 refinement) of
    ``objects``: (SceneMesh, ``T_world_obj`` (4, 4)) pairs; build once, render many
    cameras, one renderer per thread (cached buffers). Float32 casting picks the
    triangle; hits are recomputed in float64 on it (docs/capture.md).

    References
    ----------
    .. [1] T. Moller, B. Trumbore, "Fast, minimum storage ray-triangle intersection",
       Journal of Graphics Tools 2 (1997).
    """

    def __init__(self, objects: Sequence[tuple[SceneMesh, NDArray]]) -> None:
        import open3d as o3d

        items = check_objects(objects)
        self._meshes = [m for m, _ in items]
        self._poses = [T for _, T in items]
        self._poses_inv = [np.linalg.inv(T) for T in self._poses]
        self._scene = o3d.t.geometry.RaycastingScene()
        a_list, e1_list, e2_list, n_list, v_list = [], [], [], [], []
        offsets = [0]
        gid_to_obj = {}
        for i, (mesh, T) in enumerate(items):
            v = mesh.vertices @ T[:3, :3].T + T[:3, 3]
            v_list.append(v)
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
        self._ray_cache: dict[tuple, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
        # padded scene bounding box: rays that miss it are never cast (the pad covers
        # Open3D's float32 copy of the vertices with a wide margin)
        allv = np.concatenate(v_list)
        pad = 1e-3 + 1e-5 * float(np.abs(allv).max())
        self._box_lo = allv.min(axis=0) - pad
        self._box_hi = allv.max(axis=0) + pad
        self._plane = _scene_plane(allv)
        # reused float32 Open3D ray buffer (a renderer is not meant for concurrent use)
        self._rays_buf = np.empty((0, 6), dtype=np.float32)

    @property
    def n_objects(self) -> int:
        return len(self._meshes)

    # -- rays -------------------------------------------------------------------------
    def cast(self, origins: NDArray, directions: NDArray, *, normalized: bool = False) -> RayHits:
        """Intersect rays with the scene, refined in float64.

        ``origins`` (N, 3) or (3,) world mm (one origin is broadcast); ``directions``
        (N, 3), normalised here unless ``normalized``, so ``t`` is a distance.
        """
        d = check_array(directions, "directions", shape=(None, 3), dtype_kind="f").astype(np.float64)
        o = np.asarray(origins, dtype=np.float64)
        shared = o.shape == (3,)
        if not shared and o.shape != d.shape:
            raise InputError(f"origins: expected shape (3,) or {d.shape}, got {o.shape}")
        if not normalized:
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
        n = len(d)
        hits = self._trace(o.reshape(1, 3) if shared else o, d)
        t = np.full(n, np.inf)
        obj = np.full(n, -1, dtype=np.int32)
        face = np.full(n, -1, dtype=np.int64)
        uv = np.zeros((n, 2))
        pts = np.full((n, 3), np.nan)
        nrm = np.full((n, 3), np.nan)
        i = hits.index
        t[i] = hits.t
        obj[i] = hits.object_id
        face[i] = hits.face_id
        uv[i] = hits.bary_uv
        pts[i] = hits.points
        nrm[i] = hits.normals
        return RayHits(t, obj, face, uv, pts, nrm)

    def _trace(
        self, o: NDArray[np.float64], d: NDArray[np.float64], z: NDArray[np.float64] | None = None
    ) -> _Hits:
        """Hits only (compact) of unit rays ``d`` ``(N, 3)`` from ``o`` ``(1, 3)`` or ``(N, 3)``.

        With ``z`` ``(N,)`` given, the returned ``extra`` holds ``z`` at the hits.
        """
        d = np.ascontiguousarray(d, dtype=np.float64)

        def band(s: int, e: int) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
            return d[s:e], (None if z is None else z[s:e])

        hits = self._trace_bands(np.ascontiguousarray(o, dtype=np.float64), len(d), _CHUNK, band)
        return _narrow(_Hits, hits)  # accumulate mode always returns the hits

    def _scratch_rays(self, n: int) -> NDArray[np.float32]:
        """A reused ``(n, 6)`` float32 Open3D ray buffer (n <= _CHUNK)."""
        if len(self._rays_buf) < n:
            self._rays_buf = np.empty((n, 6), dtype=np.float32)
        return self._rays_buf[:n]

    def _trace_bands(
        self,
        o: NDArray[np.float64],
        n: int,
        chunk: int,
        band: Callable[[int, int], tuple[NDArray[np.float64], NDArray[np.float64] | None]],
        consume: Callable[[int, int, _Hits], None] | None = None,
    ) -> _Hits | None:
        """Cast ``n`` rays made ``chunk`` at a time by ``band(start, end)`` ->
        ``(unit directions, optional per-ray extra)``: all hits, compact; or, with
        ``consume(start, end, hits)``, one call per chunk in reused buffers (returns None).
        """
        import open3d as o3d

        keep = np.empty(min(n, chunk), dtype=np.bool_)
        # accumulate: outputs sized for the worst case (every ray hits); pages never
        # written cost nothing, the result is a view [:m]. stream: one chunk's worth.
        size = n if consume is None else min(n, chunk)
        bufs = _hit_buffers(size)
        extra: NDArray[np.float64] | None = None
        m = 0
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            if consume is not None:
                m = 0
            dc, zc = band(s, e)
            oc = o if len(o) == 1 else o[s:e]
            kc = keep[: e - s]
            cull_rays(oc, dc, self._box_lo, self._box_hi, kc)
            rid = np.flatnonzero(kc)
            k = 0
            if len(rid):
                r = self._scratch_rays(len(rid))
                pack_rays_sel(oc, dc, rid, r)
                ans = self._scene.cast_rays(o3d.core.Tensor.from_numpy(r), nthreads=configured_threads())
                gid = ans["geometry_ids"].numpy()
                t32 = ans["t_hit"].numpy()
                idx = np.flatnonzero((gid != np.iinfo(np.uint32).max) & np.isfinite(t32))
                k = len(idx)
            if k:
                refine_compact(
                    oc, dc, rid, idx, gid, ans["primitive_ids"].numpy(), t32, ans["primitive_uvs"].numpy(),
                    self._gid_map, self._offsets, self._a, self._e1, self._e2, self._n, s,
                    *(b[m : m + k] for b in bufs),
                )
                if zc is not None:
                    if extra is None:
                        extra = np.empty(size)
                    extra[m : m + k] = zc[rid[idx]]
            m += k
            if consume is not None:
                consume(s, e, _first_hits(bufs, extra, m))
        if consume is not None:
            return None
        return _first_hits(bufs, extra, m)

    def albedo(self, hits: RayHits | CameraHits, dtype: type = np.float64) -> NDArray:
        """Albedo ``(N, 3)`` (``dtype``) at the hits (0 for misses), via ``SceneMesh.albedo_at``."""
        return self._albedo(hits.object_id, hits.face_id, hits.bary_uv, hits.points, dtype)

    def _albedo(
        self,
        obj: NDArray[np.int32],
        face: NDArray[np.int64],
        uv: NDArray[np.float64],
        points: NDArray[np.float64],
        dtype: type = np.float64,
    ) -> NDArray:
        """Albedo ``(M, 3)`` (``dtype``) at world points on the objects ``obj`` (0 for -1).

        Same values as ``SceneMesh.albedo_at``; a :class:`CamouflageField` (the
        common case) is evaluated through its labels and palette directly.
        """
        m = len(obj)
        whole = len(self._meshes) == 1 and m > 0 and int(obj.min()) == 0
        out = np.empty((m, 3), dtype=dtype) if whole else np.zeros((m, 3), dtype=dtype)
        for i, mesh in enumerate(self._meshes):
            if whole:
                sel: NDArray | slice = slice(None)
            else:
                sel = np.flatnonzero(obj == i)
                if len(sel) == 0:
                    continue
            Ti = self._poses_inv[i]
            p_obj = points[sel]
            if not np.array_equal(Ti[:3, :3], np.eye(3)):
                p_obj = p_obj @ Ti[:3, :3].T
            if np.any(Ti[:3, 3] != 0):
                p_obj = p_obj + Ti[:3, 3]
            field = mesh.albedo_field
            if isinstance(field, CamouflageField):
                # palette colours are validated in [0, 1]: albedo_at's clip is a no-op
                out[sel] = np.take(field._colors.astype(dtype), field.labels(p_obj), axis=0)
            else:
                out[sel] = mesh.albedo_at(p_obj, face[sel], uv[sel])
        return out

    @property
    def meshes(self) -> tuple[SceneMesh, ...]:
        """The scene's meshes, in object-id order."""
        return tuple(self._meshes)

    def visible_from(
        self, points_world: NDArray, source_world: NDArray, *, tol_mm: float = 1e-3,
        subset: NDArray | None = None,
    ) -> NDArray[np.bool_]:
        """True where the segment from ``source_world`` to a point is unobstructed (for
        the points ``points_world[subset]`` when ``subset``, an index array, is given).

        The first hit from the source must lie no nearer than the point (minus
        ``tol_mm + 1e-7 * distance``); NaN points give False. A float32 any-hit pass;
        only segments it reports blocked are re-decided in float64; a one-plane scene
        needs no rays (docs/capture.md).
        """
        p = check_array(points_world, "points_world", shape=(None, 3))
        src = check_array(source_world, "source_world", shape=(3,)).astype(np.float64)
        return self._visible(p, src, float(tol_mm), subset)

    def _visible(
        self,
        p: NDArray[np.float64],
        src: NDArray[np.float64],
        tol: float,
        sel: NDArray[np.int64] | None = None,
    ) -> NDArray[np.bool_]:
        """:meth:`visible_from` of the points ``p[sel]`` (all of ``p`` when ``sel`` is None)."""
        import open3d as o3d

        p = np.ascontiguousarray(p, dtype=np.float64)
        src = np.ascontiguousarray(src, dtype=np.float64)
        sel = np.arange(len(p)) if sel is None else np.ascontiguousarray(sel, dtype=np.int64)
        if self._plane is not None:
            # the whole scene lies in one plane and the source is off it: a segment
            # from the source to a point of that plane meets the plane (hence the
            # scene) only at the point itself, so such a point is visible; exactly
            # what the rays would say, without casting them
            nrm, c = self._plane
            if abs(float(src @ nrm) - c) > _PLANE_TOL_MM:
                on = np.empty(len(sel), dtype=bool)
                on_plane(p, sel, nrm, c, _PLANE_TOL_MM, on)
                if np.any(on):
                    out = np.ones(len(sel), dtype=bool)
                    rest = np.flatnonzero(~on)
                    if len(rest):
                        out[rest] = self._visible(p, src, tol, sel[rest])
                    return out
        n = len(sel)
        dist = np.empty(n)
        blocked = np.zeros(n, dtype=bool)
        for s in range(0, n, _CHUNK):
            e = min(n, s + _CHUNK)
            r = self._scratch_rays(e - s)
            dmax = pack_segments(p, sel[s:e], src, r, dist[s:e])
            if dmax <= 0.0:
                continue
            # blocked (float64 rule) <=> first hit t < dist * (1 - e_i), with
            # e_i = tol / dist_i + 1e-7 >= e_min: any hit at parameter < 1 - e_min / 2
            # flags all of them (and perhaps a near-self hit, cleared below)
            e_min = tol / dmax + 1e-7
            occ = self._scene.test_occlusions(
                o3d.core.Tensor.from_numpy(r), tnear=0.0, tfar=1.0 - 0.5 * e_min, nthreads=configured_threads()
            )
            blocked[s:e] = occ.numpy()
        good = dist > 0.0
        vis = good & ~blocked
        cand = np.flatnonzero(good & blocked)
        if len(cand):
            pc = p[sel[cand]]
            dd = dist[cand]
            hits = self._trace(src.reshape(1, 3), (pc - src) / dd[:, None])
            t = np.full(len(cand), np.inf)
            t[hits.index] = hits.t
            vis[cand] = t >= dd - (tol + 1e-7 * dd)
        return vis

    # -- cameras ----------------------------------------------------------------------
    def render(
        self,
        camera: CameraModel,
        T_world_cam: NDArray,
        *,
        with_albedo: bool = True,
    ) -> RenderResult:
        """Render ``camera`` at pose ``T_world_cam`` (OpenCV frame), rays through the
        distorted pixel centres; ``with_albedo=False`` leaves the albedo map zero.
        """
        if not isinstance(camera, CameraModel):
            raise InputError(f"camera: expected a CameraModel, got {type(camera).__name__}")
        T = check_pose(T_world_cam, "T_world_cam")
        w, h = camera.size
        hits = self.trace_camera(camera, T)
        n = h * w
        i = hits.index
        depth = np.full(n, np.nan, dtype=np.float32)
        depth[i] = hits.t * hits.z_cam
        normals_cam = np.full((n, 3), np.nan, dtype=np.float32)
        normals_cam[i] = hits.normals @ T[:3, :3]  # R^T n for each row
        pts = np.full((n, 3), np.nan)
        pts[i] = hits.points
        alb = np.zeros((n, 3), dtype=np.float32)
        if with_albedo:
            alb[i] = self._albedo(hits.object_id, hits.face_id, hits.bary_uv, hits.points)
        mask = np.zeros(n, dtype=bool)
        mask[i] = True
        obj = np.full(n, -1, dtype=np.int32)
        obj[i] = hits.object_id
        face = np.full(n, -1, dtype=np.int64)
        face[i] = hits.face_id
        return RenderResult(
            depth_mm=depth.reshape(h, w),
            normals_cam=normals_cam.reshape(h, w, 3),
            points_world=pts.reshape(h, w, 3),
            albedo=alb.reshape(h, w, 3),
            mask=mask.reshape(h, w),
            object_id=obj.reshape(h, w),
            face_id=face.reshape(h, w),
        )

    def _camera_frame_rays(self, camera: CameraModel) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Camera-frame unit rays ``(H*W, 3)`` and their z ``(H*W,)``, cached per
        intrinsics (K, distortion, size) on this renderer: the Newton inversion of
        the distortion is paid once per camera model, not once per render (the two
        views of a symmetric rig share one entry)."""
        key = (camera.K.tobytes(), camera.dist.tobytes(), tuple(camera.size))
        hit = self._ray_cache.pop(key, None)
        if hit is None:
            w, h = camera.size
            d = np.empty((h, w, 3))
            z = np.empty((h, w))
            grid_rays(
                np.ascontiguousarray(camera.K), np.ascontiguousarray(camera.dist), w, 0, np.eye(3), d, z
            )
            hit = (d.reshape(-1, 3), z.reshape(-1))
            for a in hit:
                a.setflags(write=False)
            while len(self._ray_cache) >= _RAY_CACHE_SIZE:
                self._ray_cache.pop(next(iter(self._ray_cache)))
        self._ray_cache[key] = hit  # most recently used last
        return hit

    def trace_camera(self, camera: CameraModel, T_world_cam: NDArray[np.float64]) -> CameraHits:
        """All hits of a camera's pixel rays, compact (hit pixels only);
        ``T_world_cam`` is not re-checked.
        """
        hits: list[CameraHits] = []
        self._camera_bands(camera, T_world_cam, None, 1, hits)
        return hits[0]

    def stream_camera(
        self,
        camera: CameraModel,
        T_world_cam: NDArray[np.float64],
        consume: Callable[[int, int, CameraHits], None],
        *,
        rows_multiple: int = 1,
    ) -> None:
        """Cast a camera's pixel rays in bands of whole rows (a multiple of
        ``rows_multiple``, ~1 M rays), calling ``consume(first_pixel, end_pixel, hits)``
        per band with buffers the next band overwrites.
        """
        self._camera_bands(camera, T_world_cam, consume, rows_multiple, [])

    def _camera_bands(
        self,
        camera: CameraModel,
        T_world_cam: NDArray[np.float64],
        consume: Callable[[int, int, CameraHits], None] | None,
        rows_multiple: int,
        out: list[CameraHits],
    ) -> None:
        w, h = camera.size
        T = np.asarray(T_world_cam, dtype=np.float64)
        R = np.ascontiguousarray(T[:3, :3])
        o = T[:3, 3].reshape(1, 3).copy()
        rays_cam, z_cam = self._camera_frame_rays(camera)
        rm = max(1, int(rows_multiple))
        rows = max(rm, (_CHUNK // w) // rm * rm)
        d = np.empty((min(rows, h) * w, 3))

        def band(s: int, e: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
            rotate_rays(rays_cam[s:e], R, d[: e - s])
            return d[: e - s], z_cam[s:e]

        def wrap(hits: _Hits) -> CameraHits:
            zc = hits.extra if hits.extra is not None else np.zeros(0)
            return CameraHits(
                hits.index, hits.object_id, hits.face_id, hits.t, hits.bary_uv, hits.points,
                hits.normals, zc, (h, w),
            )

        if consume is not None:
            self._trace_bands(o, h * w, rows * w, band, lambda s, e, hb: consume(s, e, wrap(hb)))
        else:
            out.append(wrap(_narrow(_Hits, self._trace_bands(o, h * w, rows * w, band))))


def _scene_plane(v: NDArray[np.float64]) -> tuple[NDArray[np.float64], float] | None:
    """``(unit normal, offset)`` of the plane ``n . x = c`` holding every scene vertex
    ``v`` (world frame) within ``_PLANE_TOL_MM / 10``, or None (not planar)."""
    if len(v) < 3:
        return None
    centre = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - centre, full_matrices=False)
    nrm = vt[2]
    c = float(centre @ nrm)
    if float(np.abs(v @ nrm - c).max()) > 0.1 * _PLANE_TOL_MM:
        return None
    return nrm, c


@dataclass(eq=False)
class _CompactHits:
    """Compact hits: ``index`` (M,) of the hit rays, then per-hit fields."""

    index: NDArray[np.int64]
    object_id: NDArray[np.int32]
    face_id: NDArray[np.int64]
    t: NDArray[np.float64]
    bary_uv: NDArray[np.float64]
    points: NDArray[np.float64]
    normals: NDArray[np.float64]


@dataclass(eq=False)
class _Hits(_CompactHits):
    """Compact hits and ``extra`` (M,), the traced rays' extra values at the hits."""

    extra: NDArray[np.float64] | None = None


def _hit_buffers(size: int) -> tuple[NDArray, ...]:
    """Uninitialised outputs for ``size`` hits, in :class:`_CompactHits` field order: ray
    index, object id, face id, ``t``, barycentric uv, points, normals."""
    return (
        np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int32), np.empty(size, dtype=np.int64),
        np.empty(size), np.empty((size, 2)), np.empty((size, 3)), np.empty((size, 3)),
    )


def _first_hits(bufs: tuple[NDArray, ...], extra: NDArray[np.float64] | None, m: int) -> _Hits:
    """The first ``m`` hits of :func:`_hit_buffers` outputs and ``extra`` (views, no copies)."""
    return _Hits(*(b[:m] for b in bufs), None if extra is None else extra[:m])


@dataclass(eq=False)
class CameraHits(_CompactHits):
    """The hit pixels of a camera render (:meth:`RaycastRenderer.trace_camera`):
    ``index`` (M,) int64 flat pixel ``v * W + u``, increasing; ``object_id``,
    ``face_id``, ``t`` (M,) mm along the unit ray, ``bary_uv`` (M, 2), ``points`` and
    unit ``normals`` (M, 3) world frame (facing the camera), ``z_cam`` (M,) camera z
    of the unit ray (depth = ``t * z_cam``), ``shape`` ``(H, W)``.
    """

    z_cam: NDArray[np.float64]
    shape: tuple[int, int]


def camera_rays(
    camera: CameraModel, R_world_cam: NDArray | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(rays (H, W, 3), z_cam (H, W))``: unit rays through every distorted pixel
    centre, in the world frame (``R_world_cam @ ray_cam``; camera frame when None),
    and their camera z (depth = t * z_cam). Same as ``camera.pixel_grid_rays()``.
    """
    R = np.eye(3) if R_world_cam is None else np.asarray(R_world_cam, dtype=np.float64)
    w, h = camera.size
    out = np.empty((h, w, 3), dtype=np.float64)
    out_z = np.empty((h, w), dtype=np.float64)
    grid_rays(
        np.ascontiguousarray(camera.K), np.ascontiguousarray(camera.dist), w, 0,
        np.ascontiguousarray(R), out, out_z,
    )
    return out, out_z


# -- image formation helpers -----------------------------------------------------------
def box_downsample(image: NDArray, factor: int) -> NDArray[np.float64]:
    """Average non-overlapping ``factor x factor`` blocks of ``(H*f, W*f[, C])``;
    block ``(r, c)`` is output pixel ``(r, c)`` (pixel centres as ``CameraModel.scaled``).
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
    k = 2 * int(np.ceil(GAUSS_RADIUS_SIGMAS * s)) + 1
    return cv2.GaussianBlur(img, (k, k), sigmaX=s, sigmaY=s, borderType=cv2.BORDER_REFLECT)


@dataclass(frozen=True)
class SensorNoise:
    """Photon shot noise + Gaussian read noise, in DN (0-255 scale): ``x`` DN
    collects ``x * gain_e_per_dn`` Poisson electrons; read noise ``N(0, read_noise_dn)``.
    Default gain 40 e-/DN (full well ~10 000 e-).
    """

    gain_e_per_dn: float = 40.0
    read_noise_dn: float = 1.0

    def __post_init__(self) -> None:
        check_positive(self.gain_e_per_dn, "gain_e_per_dn")
        check_positive(self.read_noise_dn, "read_noise_dn", strict=False)

    def apply(self, image01: NDArray, rng: np.random.Generator) -> NDArray[np.float64]:
        """Noisy image in DN (float64, unclipped) from a clean image in [0, 1], one
        counter-based stream per value keyed from ``rng`` (thread-count independent).

        References
        ----------
        .. [1] W. Hormann, "The transformed rejection method for generating Poisson
           random variables", Insurance: Mathematics and Economics 12 (1993).
        .. [2] G. L. Steele, D. Lea, C. H. Flood, "Fast splittable pseudorandom
           number generators", OOPSLA 2014 (splitmix64).
        """
        x = np.asarray(image01, dtype=np.float64)
        flat = np.ascontiguousarray(x).reshape(-1)
        key = np.uint64(int(rng.integers(0, 2**63, dtype=np.int64)))
        out = np.empty(flat.shape)
        sensor_noise(flat, float(self.gain_e_per_dn), float(self.read_noise_dn), key, out)
        return out.reshape(x.shape)


def quantize(image_dn: NDArray) -> NDArray[np.uint8]:
    """Round DN values to uint8 (half to even, as ``np.rint``) with clipping to [0, 255]."""
    x = np.asarray(image_dn, dtype=np.float64)
    out = np.empty(x.shape, dtype=np.uint8)
    quantize_u8(np.ascontiguousarray(x).reshape(-1), out.reshape(-1))
    return out
