"""How scans are stitched into one model (:class:`StitchOptions`, one place per default)
and what stitching returns (:class:`StitchResult`); the method: docs/stitching.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_choice, check_in_range, check_int, check_positive
from prism3d.errors import InputError

__all__ = ["MAX_MESH_DEPTH", "MAX_SMOOTH_ITERATIONS", "STITCH_MIN_CONFIDENCE", "StitchOptions", "StitchResult"]

#: Scan files with a per-point ``confidence`` are registered and fused on the points at or
#: above this (disparity std <= 0.61 px): interpolated points pull the registration
#: (measurements in docs/stitching.md).
STITCH_MIN_CONFIDENCE = 0.9
#: Most Taubin passes on a mesh: a few tens already round it; more is a typo.
MAX_SMOOTH_ITERATIONS = 1000
#: Deepest Poisson octree: depth 14 is 16384^3 cells, beyond any scan this rig takes.
MAX_MESH_DEPTH = 14


@dataclass(frozen=True)
class StitchOptions:
    """Options of :func:`stitch_scans` (why each default: ``docs/stitching.md``)."""

    turntable_step_deg: float | None = None
    """Known rotation between consecutive views, degrees (|step| < 180); predicts every pair."""
    voxel: float | None = None
    """Fusion voxel and base distance scale, scan units; default the median point spacing."""
    mesh: bool = True
    """Also build a Poisson mesh."""
    mesh_depth: int | None = None
    """Poisson octree depth; default from extent / spacing."""
    mesh_trim_quantile: float = 0.0
    """Density-quantile trimming of the mesh; 0 keeps it closed (watertight)."""
    mesh_max_spacings: float | None = None
    """Drop the mesh farther than this many point spacings from the fused points (None:
    keep the closed surface, guessed where nothing was seen; a scanned training target
    wants 2: docs/stitching.md, "Object frame")."""
    smooth_iterations: int = 0
    """Taubin smoothing passes on the mesh."""
    min_fitness: float = 0.2
    """Least overlap of a globally registered odometry edge (a tank's opposite sides fit 0.12)."""
    min_turntable_fitness: float = 0.1
    """Least overlap of an edge whose motion is predicted or corroborated (true pairs: >= 0.165)."""
    max_residual_deg: float = 1.0
    """Largest rotation residual of an odometry edge after the pose graph, degrees."""
    max_registration_points: int = 30000
    """Scans are voxel-down-sampled to about this many points for registration."""
    loop_max_angle_deg: float = 100.0
    """Non-adjacent views whose predicted relative rotation is at most this are loop closures."""
    multiview: bool = True
    """Refine all poses jointly against all their overlaps after the pose graph."""
    turntable_constraint: str = "auto"
    """{"auto", "on", "off"}: end with all views on one axis (auto: a step, or one shared axis)."""
    max_turntable_rms_ratio: float = 1.25
    """Turntable poses are kept if their RMS is at most this times the free poses' RMS."""
    global_candidates: int = 5
    """Distinct global alignments tried per pair, each refined coarsely by ICP."""
    fusion_min_views: int = 2
    """{1, 2}: 2 (with >= 3 scans) keeps only fused points another scan confirms."""
    min_rotation_lever_ratio: float = 0.2
    """In [0, 1): warn about views whose rotation lever is below this fraction of the median (0: off)."""
    min_confidence: float = STITCH_MIN_CONFIDENCE
    """In [0, 1]: points of scan files kept at or above this ``confidence``."""
    on_failure: str = "raise"
    """{"raise", "warn"}: failed checks raise ReconstructionError or log warnings."""
    seed: int = 0
    """Seed of the global registration (results are deterministic)."""

    def __post_init__(self) -> None:
        check_choice(self.on_failure, "on_failure", ("raise", "warn"))
        check_choice(self.turntable_constraint, "turntable_constraint", ("auto", "on", "off"))
        check_positive(self.max_turntable_rms_ratio, "max_turntable_rms_ratio")
        check_positive(self.min_fitness, "min_fitness")
        check_positive(self.min_turntable_fitness, "min_turntable_fitness")
        check_positive(self.max_residual_deg, "max_residual_deg")
        ratio = self.min_rotation_lever_ratio
        if not (np.isfinite(ratio) and 0 <= ratio < 1):
            raise InputError(f"min_rotation_lever_ratio: expected a number in [0, 1), got {ratio}")
        step = self.turntable_step_deg
        if step is not None:
            check_positive(abs(float(step)), "turntable_step_deg")
            if abs(float(step)) >= 180:
                raise InputError(f"turntable_step_deg: expected |step| < 180, got {step}")
        check_in_range(self.min_confidence, "min_confidence", 0.0, 1.0)
        if self.voxel is not None:
            check_positive(self.voxel, "voxel")
        it = check_int(self.smooth_iterations, "smooth_iterations")
        if not 0 <= it <= MAX_SMOOTH_ITERATIONS:
            raise InputError(f"smooth_iterations: expected 0 to {MAX_SMOOTH_ITERATIONS}, got {it}")
        if self.mesh_depth is not None and not 1 <= check_int(self.mesh_depth, "mesh_depth") <= MAX_MESH_DEPTH:
            raise InputError(f"mesh_depth: expected 1 to {MAX_MESH_DEPTH}, got {self.mesh_depth}")
        check_in_range(self.mesh_trim_quantile, "mesh_trim_quantile", 0.0, 0.99)
        if self.mesh_max_spacings is not None:
            check_in_range(self.mesh_max_spacings, "mesh_max_spacings", 0.5, 1000.0)


@dataclass
class StitchResult:
    """A stitched model: ``T_model_scan`` (4, 4) per scan into the first scan's frame, the fused
    cloud ``points`` (N, 3), ``colors`` (N, 3) uint8 or None, ``normals`` (N, 3) float32, the
    mesh or None, and ``diagnostics`` (keys in ``docs/stitching.md``)."""

    T_model_scan: list[NDArray[np.float64]]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8] | None
    normals: NDArray[np.float32]
    mesh_vertices: NDArray[np.float64] | None = None
    mesh_faces: NDArray[np.int64] | None = None
    mesh_colors: NDArray[np.uint8] | None = None
    diagnostics: dict[str, Any] = field(default_factory=dict)
