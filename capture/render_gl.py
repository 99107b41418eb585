"""OpenGL (pyrender, headless OSMesa) backend of the renderer -- fast chip rendering.

The only place where the OpenCV camera frame becomes the OpenGL one:
``T_world_gl = T_world_cam @ diag(1, -1, -1, 1)``. Pinhole cameras without skew
only (InputError otherwise); depth from the 24-bit z-buffer, normals as 8-bit
colours (accuracy: docs/capture.md). Importing ``prism3d`` sets ``PYOPENGL_PLATFORM``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.capture.render import RenderResult, check_objects, check_pose
from prism3d.capture.rig import CameraModel
from prism3d.errors import InputError

__all__ = ["PyrenderRenderer"]

#: OpenCV camera frame -> OpenGL camera frame (the one flip in prism3d).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


class PyrenderRenderer:
    """Rasterising renderer: shaded RGB, albedo, depth, mask, object ids, normals.

    ``objects``: (SceneMesh, ``T_world_obj``) pairs (vertex colours from
    ``vertex_colors()``); ``light_intensity`` of a headlight and ``ambient`` light for
    ``rgb``; ``znear, zfar`` clip planes, mm. One ``OffscreenRenderer`` per image size is
    reused; :meth:`close` (or ``with``) frees the GL context.
    """

    def __init__(
        self,
        objects: Sequence[tuple[SceneMesh, NDArray]],
        *,
        light_intensity: float = 3.0,
        ambient: float = 0.3,
        znear: float = 10.0,
        zfar: float = 100_000.0,
    ) -> None:
        import pyrender
        import trimesh

        items = check_objects(objects)
        if not 0 < znear < zfar:
            raise InputError(f"znear, zfar: expected 0 < znear < zfar, got {znear}, {zfar}")
        self._znear = float(znear)
        self._zfar = float(zfar)
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[ambient] * 3)
        self._nodes = []
        self._normal_scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0] * 3)
        self._normal_meshes = []
        for mesh, T in items:
            # unshared vertices so every triangle is flat-coloured by its own vertices
            tri = mesh.vertices[mesh.faces].reshape(-1, 3)
            colors = mesh.vertex_colors()[mesh.faces].reshape(-1, 3)
            faces = np.arange(len(tri)).reshape(-1, 3)
            tm = trimesh.Trimesh(
                tri, faces, vertex_colors=np.clip(np.rint(colors * 255), 0, 255).astype(np.uint8), process=False
            )
            self._nodes.append(self._scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False), pose=T))
            self._normal_meshes.append((tri, faces, T))
        self._light = pyrender.DirectionalLight(color=np.ones(3), intensity=float(light_intensity))
        self._light_node = self._scene.add(self._light, pose=np.eye(4))
        self._cam_node = None
        self._renderers: dict[tuple[int, int], object] = {}

    def close(self) -> None:
        """Release the OpenGL contexts."""
        for r in self._renderers.values():
            r.delete()  # type: ignore[attr-defined]
        self._renderers.clear()

    def __enter__(self) -> PyrenderRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _renderer(self, size: tuple[int, int]):
        import pyrender

        r = self._renderers.get(size)
        if r is None:
            r = pyrender.OffscreenRenderer(size[0], size[1])
            self._renderers[size] = r
        return r

    def render(self, camera: CameraModel, T_world_cam: NDArray) -> RenderResult:
        """Render ``camera`` at ``T_world_cam`` (OpenCV frame); see the module notes."""
        import pyrender

        if not isinstance(camera, CameraModel):
            raise InputError(f"camera: expected a CameraModel, got {type(camera).__name__}")
        if camera.has_distortion:
            raise InputError(
                "PyrenderRenderer: the camera has lens distortion, which OpenGL cannot "
                "render; use RaycastRenderer or a camera with dist = 0"
            )
        if camera.skew != 0:
            raise InputError("PyrenderRenderer: pyrender's IntrinsicsCamera has no skew; got skew != 0")
        T = check_pose(T_world_cam, "T_world_cam")
        w, h = camera.size
        # pyrender puts pixel centres at i + 0.5; OpenCV at i: shift the principal point
        cam = pyrender.IntrinsicsCamera(
            camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, znear=self._znear, zfar=self._zfar
        )
        T_world_gl = T @ _CV_TO_GL
        r = self._renderer((w, h))
        flags = pyrender.RenderFlags
        cam_node = self._scene.add(cam, pose=T_world_gl)
        self._scene.set_pose(self._light_node, T_world_gl)
        try:
            rgb, depth = r.render(self._scene, flags=flags.NONE)
            albedo, _ = r.render(self._scene, flags=flags.FLAT)
            if len(self._nodes) > 1:
                seg_map = {n: (i + 1, 0, 0) for i, n in enumerate(self._nodes)}
                seg, _ = r.render(self._scene, flags=flags.SEG, seg_node_map=seg_map)
                obj = seg[..., 0].astype(np.int32) - 1
            else:
                obj = np.where(depth > 0, 0, -1).astype(np.int32)
        finally:
            self._scene.remove_node(cam_node)
        mask = depth > 0
        depth_mm = np.where(mask, depth, np.nan).astype(np.float32)
        # back-project: exact pinhole (no skew, no distortion)
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        z = depth_mm.astype(np.float64)
        pc = np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=-1)
        pw = pc @ T[:3, :3].T + T[:3, 3]
        normals = self._normals(r, camera, T, mask)
        obj[~mask] = -1
        return RenderResult(
            depth_mm=depth_mm,
            normals_cam=normals,
            points_world=pw,
            albedo=(albedo.astype(np.float32) / 255.0) * mask[..., None],
            mask=mask,
            object_id=obj,
            face_id=np.full((h, w), -1, dtype=np.int64),
            rgb=np.ascontiguousarray(rgb[..., :3]),
        )

    def _normals(self, r, camera: CameraModel, T: NDArray, mask: NDArray) -> NDArray[np.float32]:
        """Camera-frame flat normals, rendered as colours (n + 1) / 2 (FLAT pass)."""
        import pyrender
        import trimesh

        R_cam_world = T[:3, :3].T
        scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0] * 3)
        for tri, faces, T_obj in self._normal_meshes:
            tw = tri @ T_obj[:3, :3].T + T_obj[:3, 3]
            t3 = tw.reshape(-1, 3, 3)
            n = np.cross(t3[:, 1] - t3[:, 0], t3[:, 2] - t3[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            centres = t3.mean(axis=1) - T[:3, 3]
            flip = np.einsum("ij,ij->i", n, centres) > 0  # face the camera
            n[flip] *= -1
            nc = n @ R_cam_world.T
            col = np.repeat(np.clip(np.rint((nc + 1) * 127.5), 0, 255), 3, axis=0).astype(np.uint8)
            tm = trimesh.Trimesh(tw, faces, vertex_colors=col, process=False)
            scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False))
        cam = pyrender.IntrinsicsCamera(
            camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5, znear=self._znear, zfar=self._zfar
        )
        scene.add(cam, pose=T @ _CV_TO_GL)
        col, _ = r.render(scene, flags=pyrender.RenderFlags.FLAT)
        n = col[..., :3].astype(np.float32) / 127.5 - 1.0
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        n[~mask] = np.nan
        return n.astype(np.float32)
