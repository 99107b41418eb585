"""The synchronised flash projector of the virtual rig: where it sits on the rig, what its
colour-coded grating casts on the scene, and the working distance it is focused at.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from prism3d.capture._render_kernels import light_hits
from prism3d.capture.pattern import stripe_pattern
from prism3d.capture.rig import CameraModel, StereoRig
from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError

__all__ = ["DEFAULT_WORKING_DISTANCE_MM", "PROJECTOR_FIELD_MARGIN", "Projector", "working_distance_mm"]

#: Paper rig working distance, mm; also the fallback for parallel views.
DEFAULT_WORKING_DISTANCE_MM = 1250.0
#: Projector field width / one view's field width: covers both views with margin.
PROJECTOR_FIELD_MARGIN = 1.4


@dataclass(frozen=True, eq=False)
class Projector:
    """A pinhole flash projector: ``K`` (3, 3) intrinsics of the pattern image, ``size``
    ``(width, height)`` px, ``pattern`` (H, W, 3) uint8 cast (None = white flash),
    ``T_rig_proj`` (4, 4) pose (default identity: rig origin, along rig z) and
    ``ref_distance_mm`` where the inverse-square falloff is 1.
    """

    K: NDArray[np.float64]
    size: tuple[int, int]
    pattern: NDArray[np.uint8] | None = None
    T_rig_proj: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))
    ref_distance_mm: float = DEFAULT_WORKING_DISTANCE_MM

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
        """A projector at the rig origin covering the views at the working distance
        (default field width ``PROJECTOR_FIELD_MARGIN`` x a view's). ``pattern``:
        True = De Bruijn stripes, False = white flash, or an ``(H, W, 3) uint8`` image."""
        wd = working_distance_mm(rig)
        if field_width_mm is None:
            field_width_mm = PROJECTOR_FIELD_MARGIN * rig.left.width / rig.left.fx * wd
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
        """``(rgb (N, 3), white (N,))`` cast on rig-frame points: the bilinear pattern
        colour, and 1 inside the frustum / 0 outside."""
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
        """``(k, rgb, white, lit)`` at rig-frame points with unit normals, before the
        shadow test (one parallel pass of ``light_hits``)."""
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


def working_distance_mm(rig: StereoRig, default: float = DEFAULT_WORKING_DISTANCE_MM) -> float:
    """Rig depth where the left optical axis crosses the rig's y-z plane (convergence
    distance of a symmetric rig), mm; ``default`` for parallel views."""
    c = rig.T_rig_left[:3, 3]
    z_axis = rig.T_rig_left[:3, 2]
    if abs(z_axis[0]) < 1e-9:
        return float(default)
    s = -c[0] / z_axis[0]
    p = c + s * z_axis
    return float(p[2]) if s > 0 and p[2] > 0 else float(default)
