"""Triangle meshes with albedo, as the renderer and the simulator consume them:
vertices in mm in the object frame, faces, and albedo in [0, 1] per vertex or as a
procedural field evaluated at any 3-D point (exact at every pixel).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError

__all__ = ["AlbedoField", "MovedAlbedo", "SceneMesh", "UniformAlbedo"]


class AlbedoField(Protocol):
    """Anything mapping object-frame points ``(N, 3)`` mm to albedo ``(N, 3)`` in [0, 1]."""

    def __call__(self, points_obj: NDArray[np.float64]) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class UniformAlbedo:
    """One colour everywhere."""

    rgb: tuple[float, float, float] = (0.7, 0.7, 0.7)

    def __call__(self, points_obj: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.broadcast_to(np.asarray(self.rgb, dtype=np.float64), (len(points_obj), 3)).copy()


@dataclass(frozen=True, eq=False)
class MovedAlbedo:
    """An albedo field carried along by a rigid motion (picklable, unlike a closure);
    ``T_obj_new`` maps the moved mesh's frame back to the field's frame.
    """

    field: AlbedoField
    T_obj_new: NDArray[np.float64]

    def __call__(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        T = self.T_obj_new
        return self.field(np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3])


@dataclass(frozen=True, eq=False)
class SceneMesh:
    """A triangle mesh in millimetres with albedo: ``vertices`` (N, 3) object frame,
    ``faces`` (M, 3) counter-clockwise from outside, ``vertex_albedo`` (N, 3) in [0, 1]
    (barycentric), ``albedo_field`` (wins; neither = uniform 0.7 grey), ``name``.
    """

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    vertex_albedo: NDArray[np.float64] | None = None
    albedo_field: AlbedoField | Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None
    name: str = "mesh"
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = check_array(self.vertices, f"{self.name}.vertices", shape=(None, 3), dtype_kind="fiu")
        f = check_array(self.faces, f"{self.name}.faces", shape=(None, 3), dtype_kind="iu")
        if len(v) == 0 or len(f) == 0:
            raise InputError(f"{self.name}: empty mesh (no vertices or no faces)")
        if not np.all(np.isfinite(v)):
            raise InputError(f"{self.name}: vertices contain NaN or inf")
        if f.min() < 0 or f.max() >= len(v):
            raise InputError(f"{self.name}: face indices out of range [0, {len(v)})")
        object.__setattr__(self, "vertices", np.ascontiguousarray(v, dtype=np.float64))
        object.__setattr__(self, "faces", np.ascontiguousarray(f, dtype=np.int64))
        if self.vertex_albedo is not None:
            a = check_array(self.vertex_albedo, f"{self.name}.vertex_albedo", shape=(len(v), 3))
            a = a.astype(np.float64)
            if a.max(initial=0) > 1.0 + 1e-9 or a.min(initial=0) < 0:
                raise InputError(f"{self.name}: vertex_albedo must lie in [0, 1]")
            object.__setattr__(self, "vertex_albedo", np.ascontiguousarray(a))

    @property
    def bounds(self) -> NDArray[np.float64]:
        """``(2, 3)`` min and max corner, mm."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    @property
    def extent_mm(self) -> NDArray[np.float64]:
        """Axis-aligned size ``(3,)`` mm."""
        b = self.bounds
        return b[1] - b[0]

    def albedo_at(
        self, points_obj: NDArray[np.float64], face_ids: NDArray[np.int64], bary_uv: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Albedo ``(N, 3)`` at surface points from faces and barycentric (u, v)
        (Open3D: point = (1-u-v) a + u b + v c).
        """
        if self.albedo_field is not None:
            out = np.asarray(self.albedo_field(points_obj), dtype=np.float64)
            return np.clip(out, 0.0, 1.0)
        if self.vertex_albedo is not None:
            tri = self.faces[face_ids]
            u = bary_uv[:, 0:1]
            w = bary_uv[:, 1:2]
            a = self.vertex_albedo
            return (1 - u - w) * a[tri[:, 0]] + u * a[tri[:, 1]] + w * a[tri[:, 2]]
        return np.full((len(points_obj), 3), 0.7)

    def transformed(self, T_new_obj: NDArray[np.float64], name: str | None = None) -> SceneMesh:
        """The mesh with vertices mapped by a 4x4 transform (albedo field follows it)."""
        T = check_array(T_new_obj, "T_new_obj", shape=(4, 4)).astype(np.float64)
        v = self.vertices @ T[:3, :3].T + T[:3, 3]
        fieldf = self.albedo_field
        if fieldf is not None:
            fieldf = MovedAlbedo(fieldf, np.linalg.inv(T))
        return SceneMesh(v, self.faces, self.vertex_albedo, fieldf, name or self.name, dict(self.metadata))

    def vertex_colors(self) -> NDArray[np.float64]:
        """Albedo at every vertex ``(N, 3)`` (for viewers, PLY export, pyrender)."""
        if self.albedo_field is not None:
            return np.clip(np.asarray(self.albedo_field(self.vertices), dtype=np.float64), 0, 1)
        if self.vertex_albedo is not None:
            return self.vertex_albedo.copy()
        return np.full((len(self.vertices), 3), 0.7)
