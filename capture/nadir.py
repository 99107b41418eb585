"""A mesh seen from straight above, orthographically: the sprite of aerial training scenes.

One vertical ray per sub-pixel gives the surface's albedo, normal and height; a top-down
orthographic view turns by any angle about the vertical exactly by turning the image (and
the normals' horizontal part), and is relit under any sun from its normals, so one render
per mesh serves every heading and light (:mod:`prism3d.atr.aerial_scenes`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.mesh import SceneMesh
from prism3d.capture.render import RaycastRenderer
from prism3d.errors import InputError

__all__ = ["NadirSprite", "render_nadir"]

#: The most sprite pixels rendered at once (a 100 m object at 2 cm is 25 MP).
MAX_SPRITE_PIXELS = 16_000_000


@dataclass(frozen=True)
class NadirSprite:
    """An orthographic top-down view: ``albedo`` (h, w, 3) float32 in [0, 1] (premultiplied
    by ``alpha``), ``normal`` (h, w, 3) float32 unit normals (object frame: x, y
    horizontal, z up; (0, 0, 1) off the object), ``height`` (h, w) float32 m above the
    mesh's lowest point (0 off it), ``alpha`` (h, w) float32 coverage in [0, 1]; ``gsd``
    m per pixel; the object's +x along the columns, +y up the rows (row 0 at the largest
    y); the mesh's bounding-box centre at the image centre."""

    albedo: NDArray[np.float32]
    normal: NDArray[np.float32]
    height: NDArray[np.float32]
    alpha: NDArray[np.float32]
    gsd: float
    name: str
    length_m: float
    width_m: float
    height_m: float


def render_nadir(mesh: SceneMesh, gsd_m: float, *, margin_m: float = 0.3, supersample: int = 2) -> NadirSprite:
    """Render ``mesh`` (mm, z up) straight down at ``gsd_m`` metres per pixel with
    ``supersample`` x ``supersample`` rays per pixel, ``margin_m`` of empty border."""
    if not (math.isfinite(gsd_m) and gsd_m > 0):
        raise InputError(f"gsd: expected > 0 m, got {gsd_m}")
    if int(supersample) != supersample or not 1 <= supersample <= 4:
        raise InputError(f"supersample: expected 1-4, got {supersample!r}")
    lo, hi = mesh.bounds / 1000.0
    ctr = (lo + hi) / 2.0
    half = (hi - lo)[:2] / 2.0 + margin_m
    w, h = 2 * int(math.ceil(half[0] / gsd_m)) + 1, 2 * int(math.ceil(half[1] / gsd_m)) + 1
    s = int(supersample)
    if w * h * s * s > MAX_SPRITE_PIXELS:
        raise InputError(f"{mesh.name}: a {w} x {h} px sprite at {gsd_m} m is too large; give a coarser gsd")
    sub = gsd_m / s
    xs = ctr[0] + (np.arange(w * s) - (w * s - 1) / 2.0) * sub
    ys = ctr[1] - (np.arange(h * s) - (h * s - 1) / 2.0) * sub
    X, Y = np.meshgrid(xs, ys)
    top = (hi[2] + 1.0) * 1000.0
    o = np.stack([X.ravel() * 1000.0, Y.ravel() * 1000.0, np.full(X.size, top)], axis=1)
    d = np.zeros_like(o)
    d[:, 2] = -1.0
    r = RaycastRenderer([(mesh, np.eye(4))])
    hits = r.cast(o, d, normalized=True)
    hit = hits.hit.reshape(h * s, w * s)
    alb = r.albedo(hits)  # 0 for misses
    nrm = np.zeros((h * s * w * s, 3))
    nrm[:, 2] = 1.0
    nrm[hits.hit] = hits.normals[hits.hit]
    hgt = np.where(hits.hit, (top - hits.t) / 1000.0 - lo[2], 0.0)

    def pool(a: NDArray, k: int) -> NDArray:
        return a.reshape(h, s, w, s, *a.shape[2:]).mean(axis=(1, 3))

    alpha = pool(hit.astype(np.float64), 2)
    albedo = pool(alb.reshape(h * s, w * s, 3), 3)
    normal = pool(nrm.reshape(h * s, w * s, 3), 3)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-9)
    height = hgt.reshape(h * s, w * s).reshape(h, s, w, s).max(axis=(1, 3))
    ext = hi - lo
    return NadirSprite(albedo.astype(np.float32), normal.astype(np.float32), height.astype(np.float32),
                       alpha.astype(np.float32), float(gsd_m), mesh.name, float(ext[0]), float(ext[1]), float(ext[2]))
