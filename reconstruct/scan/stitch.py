"""Stitching of multi-view scans into one 360-degree model (:func:`stitch_scans`): odometry
edges, loop closures, a pose graph with a line process [1]_, joint refinement, fusion. The
model frame is the first scan's. Stages and measurements: ``docs/stitching.md``.

References
----------
.. [1] S. Choi, Q.-Y. Zhou, V. Koltun, "Robust reconstruction of indoor scenes", CVPR 2015.
.. [2] R. Kuemmerle et al., "g2o: A general framework for graph optimization", ICRA 2011.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_choice
from prism3d.errors import InputError, ReconstructionError
from prism3d.geometry import invert_transform, rotation_angle_deg, rotvec_from_matrix
from prism3d.io.atomic import atomic_paths, atomic_write_text, output_lock
from prism3d.io.pcd import read_pcd
from prism3d.io.ply import read_ply, write_ply
from prism3d.progress import ProgressFn
from prism3d.reconstruct.scan.fusion import fuse_clouds, mesh_is_closed, poisson_mesh
from prism3d.reconstruct.scan.multiview import (
    fit_turntable,
    overlapping_pairs,
    refine_multiview,
    refine_turntable,
)
from prism3d.reconstruct.scan.object_frame import object_frame
from prism3d.reconstruct.scan.registration import (
    RegistrationResult,
    ScanFeatures,
    ScanPyramid,
    evaluate_pyramids,
    global_voxel,
    icp_pyramids,
    match_features_candidates,
    point_spacing,
    surface_noise,
    turntable_motion,
)
from prism3d.reconstruct.scan.stitch_options import (
    StitchOptions,
    StitchResult,
)

__all__ = ["StitchOptions", "StitchResult", "load_cloud", "stitch_scans", "stitch_to_files"]

log = logging.getLogger(__name__)

#: Version of the ``poses.json`` written by :func:`stitch_to_files`.
POSES_SCHEMA_VERSION = 1

Cloud = tuple[NDArray, NDArray | None, NDArray | None]
Pair = tuple[int, int]

#: A registered pair is marked for checking when less than this fraction of its source
#: overlaps the target, pairwise or in the finished model ...
PAIR_CHECK_MIN_FITNESS = 0.3
#: ... or when its plane_sigma exceeds this multiple of the scans' own noise (correct
#: pairs measure 0.8-1.3x).
PAIR_CHECK_NOISE_RATIO = 3.0
# Source points per pair measurement: sampling error of the fitness <= 0.006, ~6 ms a pair.
_PAIR_SAMPLE = 8000
# Largest displacement, as a fraction of the object's radius, by which two pairs' motions
# may differ and still count as the same motion (0.1 allows < 5.7 deg).
_MOTION_AGREEMENT = 0.1
# Fewest finite points a scan needs (below this no normal or feature is meaningful).
_MIN_SCAN_POINTS = 30
# The feature voxel leaves about this many points of the first scan: FPFH + RANSAC on a
# few thousand points is fast and still finds the match.
_FEATURE_POINTS = 3000
# Global candidates are ranked after ICP down to this scale (cheap, enough to tell a wrong
# alignment), and the best is then refined from the next level down.
_RANK_LAST_SCALE = 4.0
_BEST_FIRST_SCALE = 2.0
# ICP from a predicted motion (turntable step, a neighbour's motion) starts at this scale:
# the prediction is within a few point spacings.
_PREDICTED_FIRST_SCALE = 4.0
# Loop closures are registered on this level only: the joint refinement puts every pose on
# the full clouds afterwards (the finest level cost a third of the time for noise-level gains).
_LOOP_SCALE = 2.0
# A neighbour's motion replaces a global match that passes min_fitness only when it fits
# clearly better (by this much fitness).
_BETTER_FIT_MARGIN = 0.05
# A neighbour's motion this close (registration voxels, at the scan's radius) to a pair's own
# starts ICP inside the pair's own basin: half the first level's search distance
# (_PREDICTED_FIRST_SCALE voxels, searched within twice that).
_REFIT_SKIP_VOXELS = 4.0
# Inliers lie within the correspondence distance, so an RMSE above this multiple of it
# means a broken registration.
_MAX_RMSE_RATIO = 1.5
# Pose graph: correspondence distance in registration voxels; edge pruning and loop-closure
# preference are Open3D's defaults.
_GRAPH_DISTANCE_VOXELS = 3.0
_GRAPH_EDGE_PRUNE = 0.25
_GRAPH_LOOP_PREFERENCE = 1.0
# An edge disagreeing with the optimised poses by more than this many registration voxels
# (largest point displacement) did not close its loop.
_MAX_RESIDUAL_VOXELS = 20.0
# Free poses look like a turntable when every view turned by more than _TT_MIN_TURN_DEG has
# its axis within _TT_AXIS_TOL_DEG of the common one and its translation within
# _TT_CENTRE_VOXELS registration voxels of a pure rotation about it.
_TT_MIN_TURN_DEG = 10.0
_TT_AXIS_TOL_DEG = 1.0
_TT_CENTRE_VOXELS = 5.0
# |det(R) - 1| above this is not a rotation.
_RIGID_DET_TOL = 1e-6
# A lever below 1/this of the median is reported as "over 100x" rather than a ratio.
_LEVER_FACTOR_CAP = 100.0




def load_cloud(path: str | Path, *, min_confidence: float = 0.0) -> Cloud:
    """Read a ``.ply`` or ``.pcd`` scan: ``(points, colors, normals)``, keeping the points whose
    ``confidence`` (when the file has one) reaches ``min_confidence``. InputError names the file."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".ply":
        d = read_ply(p)
        pts, col, nrm = d.points, d.colors, d.normals
        conf = d.extra.get("confidence")
        if min_confidence > 0 and conf is not None:
            keep = np.asarray(conf) >= min_confidence
            pts = pts[keep]
            col = None if col is None else col[keep]
            nrm = None if nrm is None else nrm[keep]
    elif suffix == ".pcd":
        d2 = read_pcd(p)
        pts, col, nrm = d2.points, d2.colors, d2.normals
    else:
        raise InputError(f"{p}: unknown point-cloud format {suffix!r} (expected .ply or .pcd)")
    if len(pts) == 0:
        raise InputError(f"{p}: the scan has no points")
    return np.asarray(pts, dtype=np.float64), col, nrm


def _residual(T_a: NDArray, T_b: NDArray, radius: float, centre: NDArray | None = None) -> tuple[float, float]:
    """Rotation (deg) and largest displacement of a point within ``radius`` of ``centre``
    between two transforms (about the cloud, not the sensor)."""
    D = invert_transform(T_a) @ T_b
    ang = rotation_angle_deg(D)
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    disp = float(np.linalg.norm(D[:3, :3] @ c + D[:3, 3] - c) + np.radians(ang) * radius)
    return ang, disp


def _validate_clouds(clouds: Sequence, min_confidence: float = 0.0) -> tuple[list[Cloud], list[str]]:
    if isinstance(clouds, (str, Path)) or not isinstance(clouds, Sequence):
        raise InputError(f"clouds: expected a list of scans or paths, got {type(clouds).__name__}")
    if len(clouds) < 2:
        raise InputError(f"clouds: stitching needs at least 2 scans, got {len(clouds)}")
    out: list[Cloud] = []
    names: list[str] = []
    for k, c in enumerate(clouds):
        if isinstance(c, (str, Path)):
            name = str(c)
            pts, col, nrm = load_cloud(c, min_confidence=min_confidence)
        else:
            name = f"scan {k}"
            if not isinstance(c, (tuple, list)) or len(c) != 3:
                raise InputError(f"clouds[{k}]: expected (points, colors or None, normals or None) or a path")
            pts, col, nrm = c
        P = np.asarray(check_array(pts, f"{name} points", shape=(None, 3), dtype_kind="fiu"), dtype=np.float64)
        finite = np.isfinite(P).all(axis=1)
        if finite.sum() < _MIN_SCAN_POINTS:
            raise InputError(f"{name}: expected at least {_MIN_SCAN_POINTS} finite points, got {int(finite.sum())}")
        C = None
        if col is not None:
            C = check_array(col, f"{name} colors", shape=(len(P), 3), dtype_kind="fu")
            if C.dtype.kind == "f":
                C = np.clip(np.round(C * 255.0), 0, 255)
            C = np.asarray(C, dtype=np.uint8)[finite]
        N = None
        if nrm is not None:
            N = np.asarray(check_array(nrm, f"{name} normals", shape=(len(P), 3), dtype_kind="f"))[finite]
        out.append((P[finite], C, N))
        names.append(name)
    return out, names


def _registration_copy(points: NDArray, spacing: float, max_points: int) -> tuple[NDArray, float]:
    """Down-sample a scan for registration to at most ~``max_points`` points."""
    import open3d as o3d

    if len(points) <= max_points:
        return points, spacing
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    v = spacing * np.sqrt(len(points) / max_points)
    down = np.asarray(pc.voxel_down_sample(v).points)
    return down, float(v)


class _Run:
    """Progress ticks, failed checks (raise or warn) and the warnings of one run."""

    def __init__(self, n: int, on_failure: str, progress: ProgressFn | None) -> None:
        self.total = 2 * n + 3
        self.step = 0
        self.on_failure = on_failure
        self.progress = progress
        self.warnings: list[str] = []
        self.seconds: dict[str, float] = {}
        self.assumed: set[int] = set()
        """Odometry pairs ``k, k+1`` placed by the given turntable step (nothing registered them)."""

    def tick(self, label: str) -> None:
        self.step += 1
        if self.progress is not None:
            self.progress(min(self.step, self.total), self.total, label)

    def warn(self, msg: str) -> None:
        log.warning(msg)
        self.warnings.append(msg)

    def fail(self, msg: str) -> None:
        if self.on_failure == "raise":
            raise ReconstructionError(msg)
        self.warn(msg)


@dataclass
class _Prepared:
    """The scans and what every stage derives from them once."""

    scans: list[Cloud]
    names: list[str]
    spacing: float  # fusion voxel (median point spacing unless given)
    rsp: float  # registration voxel (the coarsest registration copy's spacing)
    reg_pts: list[NDArray]
    centres: list[NDArray]
    radius: float  # 95th percentile distance of a registration point from its centroid
    pyramids: list[ScanPyramid]
    feat_voxel: float
    features: dict[int, ScanFeatures] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.scans)

    def feats(self, k: int) -> ScanFeatures:
        if k not in self.features:
            self.features[k] = ScanFeatures(self.reg_pts[k], self.feat_voxel)
        return self.features[k]

    def icp(self, i: int, j: int, init: NDArray, first_scale: float | None = None,
            last_scale: float | None = None) -> RegistrationResult:
        """Register scan j onto scan i (T_i_j)."""
        return icp_pyramids(self.pyramids[j], self.pyramids[i], init, first_scale=first_scale, last_scale=last_scale)


#: Voxels across the scans' extent beyond which a voxel grid cannot be indexed (Open3D
#: refuses; a voxel near the point spacing gives ~1e3-1e4).
_MAX_VOXELS_ACROSS = 1e8


def _prepare_scans(scans: list[Cloud], names: list[str], opts: StitchOptions) -> _Prepared:
    """Point spacing, registration copies, object centre and radius, pyramids."""
    spacings = [point_spacing(s[0], seed=opts.seed) for s in scans]
    spacing = float(np.median(spacings)) if opts.voxel is None else float(opts.voxel)
    extent = max(float(np.ptp(s[0], axis=0).max()) for s in scans)
    if extent / spacing > _MAX_VOXELS_ACROSS:
        raise InputError(f"voxel: {spacing:g} is too small for scans {extent:g} across "
                         f"(more than {_MAX_VOXELS_ACROSS:g} voxels); give a voxel near the point spacing")
    reg_pts, reg_sp = [], []
    for s in scans:
        p, v = _registration_copy(s[0], spacing, opts.max_registration_points)
        reg_pts.append(p)
        reg_sp.append(v)
    rsp = float(max(reg_sp))
    centres = [p.mean(axis=0) for p in reg_pts]
    radius = float(max(np.percentile(np.linalg.norm(p - c, axis=1), 95) for p, c in zip(reg_pts, centres, strict=True)))
    pyramids = [ScanPyramid(p, rsp) for p in reg_pts]
    feat_voxel = global_voxel(reg_pts[0], rsp, _FEATURE_POINTS)
    return _Prepared(scans, names, spacing, rsp, reg_pts, centres, radius, pyramids, feat_voxel)


def _global_pair(prep: _Prepared, opts: StitchOptions, i: int, j: int) -> RegistrationResult:
    """Several distinct RANSAC alignments, each refined coarsely by ICP; the best fitting one
    refined fully (the one with most feature matches can be wrong on boxy objects)."""
    try:
        cands = match_features_candidates(prep.feats(j), prep.feats(i), seed=opts.seed,
                                          max_candidates=opts.global_candidates)
    except ReconstructionError as exc:
        raise ReconstructionError(
            f"views {prep.names[i]} and {prep.names[j]} do not overlap: {exc} (are they consecutive views of one "
            "object?)"
        ) from exc
    if len(cands) == 1:
        return prep.icp(i, j, cands[0][0])
    coarse = [prep.icp(i, j, T, last_scale=_RANK_LAST_SCALE) for T, _ in cands]
    best = max(range(len(coarse)), key=lambda k: (round(coarse[k].fitness, 3), -coarse[k].inlier_rmse))
    return prep.icp(i, j, coarse[best].T_target_source, first_scale=_BEST_FIRST_SCALE)


def _find_turntable_motion(prep: _Prepared, opts: StitchOptions, run: _Run,
                           results: dict[Pair, RegistrationResult]) -> NDArray | None:
    """The exact step motion ``A`` from the first consecutive pair whose global match turns
    by the step: a symmetric body (a car seen from the side) can match its own mirror image
    in the first pairs (car_suv, seed 0: 173, 33 and 62 deg for the first three, 45 +- 0.5
    for the rest)."""
    n, step = prep.n, float(opts.turntable_step_deg)
    for k in range(n - 1):
        r = _global_pair(prep, opts, k, k + 1)
        cand = turntable_motion(r.T_target_source, step)
        if cand is not None and r.fitness >= opts.min_fitness:
            results[(k, k + 1)] = r
            if k > 0:  # the earlier pairs matched at other angles: the axis rests on one pair
                run.warn(f"the turntable motion came from {prep.names[k]}-{prep.names[k + 1]}: the {k} pair(s) before "
                         "matched at other angles (a symmetric object?); check the poses against the scans")
            return cand
        log.info("turntable axis from views %d-%d rejected (fitness %.3f)", k, k + 1, r.fitness)
    run.fail(
        f"could not find the turntable motion of {opts.turntable_step_deg} deg between "
        f"{prep.names[0]} .. {prep.names[n - 1]}: global registration found no "
        "rotation of that size"
    )
    return None


def _odometry(prep: _Prepared, opts: StitchOptions, run: _Run) -> tuple[dict[Pair, RegistrationResult], set[int],
                                                                        NDArray | None]:
    """Edges ``k+1 -> k``, the odometry pairs corroborated by a known or neighbouring motion
    (held to min_turntable_fitness), and the turntable motion."""
    results: dict[Pair, RegistrationResult] = {}
    corroborated: set[int] = set()
    A = _find_turntable_motion(prep, opts, run, results) if opts.turntable_step_deg is not None else None
    for k in range(prep.n - 1):
        r = results.get((k, k + 1))
        at_step = None
        if r is None and A is not None:
            r = at_step = prep.icp(k, k + 1, A, first_scale=_PREDICTED_FIRST_SCALE)
            if r.fitness < opts.min_turntable_fitness:
                r = None
            else:
                corroborated.add(k)
        if r is None:
            r = _global_pair(prep, opts, k, k + 1)
            if at_step is not None and r.fitness < opts.min_fitness:
                r = _assume_step(prep, run, k, A, at_step, r)
                corroborated.add(k)
        results[(k, k + 1)] = r
        run.tick(f"odometry {k}-{k + 1}")
    if A is None and prep.n > 2:
        _refit_from_neighbours(prep, opts, results)
        _corroborate_by_neighbours(prep, opts, results, corroborated)
        _yield_to_agreeing_neighbours(prep, opts, run, results, corroborated)
    _check_odometry(prep, opts, run, results, corroborated)
    return results, corroborated, A


def _assume_step(prep: _Prepared, run: _Run, k: int, A: NDArray, at_step: RegistrationResult,
                 matched: RegistrationResult) -> RegistrationResult:
    """The fallback of a pair that neither the turntable step nor a global match registers
    (too little shared surface: a thin wing seen edge-on): the given step motion ``A``
    itself, weighted by the little overlap it has, so the pose graph and the joint
    turntable refinement place the view; said in the warnings and the edge's ``fallback``."""
    run.warn(f"views {prep.names[k]} and {prep.names[k + 1]} share too little to register (fitness "
             f"{max(at_step.fitness, matched.fitness):.3f}); placed by the given turntable step")
    run.assumed.add(k)
    return RegistrationResult(np.array(A, dtype=np.float64), at_step.fitness, at_step.inlier_rmse,
                              at_step.information, at_step.max_distance)


def _same_motion(prep: _Prepared, T_a: NDArray, T_b: NDArray, k: int) -> bool:
    """Do two pairs' motions agree on scan k+1's points (within _MOTION_AGREEMENT of the radius)?"""
    return _residual(T_a, T_b, prep.radius, prep.centres[k + 1])[1] <= _MOTION_AGREEMENT * prep.radius


def _refit_from_neighbours(prep: _Prepared, opts: StitchOptions, results: dict[Pair, RegistrationResult]) -> None:
    """Each pair is also registered from its neighbours' motions; a clearly better fit replaces
    its global match (any better fit, when the match fails min_fitness). A neighbour's motion
    within _REFIT_SKIP_VOXELS of the pair's own is not tried: ICP from there lands where the
    pair already is (on a turntable every pair moves alike, so none is registered twice)."""
    n = prep.n
    for k in range(n - 1):
        cur = results[(k, k + 1)]
        for m in (k - 1, k + 1):
            if not (0 <= m < n - 1):
                continue
            near = _residual(cur.T_target_source, results[(m, m + 1)].T_target_source, prep.radius,
                             prep.centres[k + 1])[1]
            if near <= _REFIT_SKIP_VOXELS * prep.rsp:
                continue
            r = prep.icp(k, k + 1, results[(m, m + 1)].T_target_source, first_scale=_PREDICTED_FIRST_SCALE)
            margin = _BETTER_FIT_MARGIN if cur.fitness >= opts.min_fitness else 0.0
            if r.fitness > cur.fitness + margin:
                log.info("views %s-%s: the neighbours' motion fits better (%.3f > %.3f)",
                         prep.names[k], prep.names[k + 1], r.fitness, cur.fitness)
                cur = r
        results[(k, k + 1)] = cur


def _corroborate_by_neighbours(prep: _Prepared, opts: StitchOptions, results: dict[Pair, RegistrationResult],
                               corroborated: set[int]) -> None:
    """A pair moving like a neighbouring pair that fits at min_fitness is corroborated by it."""
    n = prep.n
    for k in range(n - 1):
        T_k = results[(k, k + 1)].T_target_source
        for m in (k - 1, k + 1):
            if (0 <= m < n - 1 and results[(m, m + 1)].fitness >= opts.min_fitness
                    and _same_motion(prep, results[(m, m + 1)].T_target_source, T_k, k)):
                corroborated.add(k)


def _yield_to_agreeing_neighbours(prep: _Prepared, opts: StitchOptions, run: _Run,
                                  results: dict[Pair, RegistrationResult], corroborated: set[int]) -> None:
    """A pair moving unlike both neighbours, which move alike (each at min_fitness), is
    registered again from their common motion and takes it if that fits and holds."""
    names = prep.names
    for k in range(1, prep.n - 2):
        if k in corroborated:
            continue
        before, after = results[(k - 1, k)], results[(k + 1, k + 2)]
        if min(before.fitness, after.fitness) < opts.min_fitness:
            continue
        if not _same_motion(prep, before.T_target_source, after.T_target_source, k):
            continue
        r = prep.icp(k, k + 1, before.T_target_source, first_scale=_PREDICTED_FIRST_SCALE)
        if r.fitness >= opts.min_turntable_fitness and _same_motion(prep, before.T_target_source,
                                                                    r.T_target_source, k):
            log.info("views %s-%s: their match (fitness %.3f) disagrees with both neighbours, which move "
                     "alike; using that common motion (fitness %.3f)",
                     names[k], names[k + 1], results[(k, k + 1)].fitness, r.fitness)
            results[(k, k + 1)] = r
            corroborated.add(k)
        else:
            run.warn(f"views {names[k]} and {names[k + 1]} move unlike the pairs on either side, which "
                     "move alike: an uneven step, or a wrong match (check the poses from "
                     f"{names[k + 1]} on)")


def _check_odometry(prep: _Prepared, opts: StitchOptions, run: _Run, results: dict[Pair, RegistrationResult],
                    corroborated: set[int]) -> None:
    """Every odometry edge overlaps enough and fits within its correspondence distance."""
    names = prep.names
    for k in range(prep.n - 1):
        r = results[(k, k + 1)]
        least = opts.min_turntable_fitness if k in corroborated else opts.min_fitness
        if r.fitness < least and k not in run.assumed:
            run.fail(
                f"views {names[k]} and {names[k + 1]} do not overlap enough to register "
                f"(fitness {r.fitness:.3f} < {least}); are they consecutive views of one object?"
            )
        if r.inlier_rmse > _MAX_RMSE_RATIO * r.max_distance:
            run.fail(f"views {names[k]} and {names[k + 1]}: registration residual too large ({r.inlier_rmse:.3g})")


def _chain_poses(results: dict[Pair, RegistrationResult], n: int) -> list[NDArray]:
    """Initial poses: the odometry edges chained from the first view."""
    T_model = [np.eye(4)]
    for k in range(n - 1):
        T_model.append(T_model[-1] @ results[(k, k + 1)].T_target_source)
    return T_model


def _loop_closures(prep: _Prepared, opts: StitchOptions, run: _Run, results: dict[Pair, RegistrationResult],
                   T_model: list[NDArray]) -> None:
    """Non-adjacent views within loop_max_angle_deg, refined from the chained poses, kept when they fit."""
    for i in range(prep.n):
        for j in range(i + 2, prep.n):
            init = invert_transform(T_model[i]) @ T_model[j]
            if rotation_angle_deg(init) > opts.loop_max_angle_deg:
                continue
            r = prep.icp(i, j, init, first_scale=_LOOP_SCALE, last_scale=_LOOP_SCALE)
            if r.fitness >= opts.min_fitness and r.inlier_rmse <= _MAX_RMSE_RATIO * r.max_distance:
                results[(i, j)] = r
            else:
                log.info("loop closure %s-%s skipped (fitness %.3f)", prep.names[i], prep.names[j], r.fitness)
            run.tick(f"loop {i}-{j}")


def _optimise_pose_graph(prep: _Prepared, results: dict[Pair, RegistrationResult],
                         T_model: list[NDArray]) -> tuple[list[NDArray], set[Pair]]:
    """Levenberg-Marquardt over the pose graph (loop closures uncertain, line process [1]_);
    the poses with the first view the identity, and the kept edges ``(target, source)``."""
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    for T in T_model:
        graph.nodes.append(reg.PoseGraphNode(T))
    for (i, j), r in sorted(results.items()):
        graph.edges.append(reg.PoseGraphEdge(j, i, r.T_target_source, r.information, uncertain=(j != i + 1)))
    if len(results) > prep.n - 1:
        option = reg.GlobalOptimizationOption(
            max_correspondence_distance=_GRAPH_DISTANCE_VOXELS * prep.rsp,
            edge_prune_threshold=_GRAPH_EDGE_PRUNE,
            preference_loop_closure=_GRAPH_LOOP_PREFERENCE,
            reference_node=0,
        )
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    T0_inv = invert_transform(np.asarray(graph.nodes[0].pose))
    T_out = [T0_inv @ np.asarray(nd.pose, dtype=np.float64) for nd in graph.nodes]
    return T_out, {(e.target_node_id, e.source_node_id) for e in graph.edges}


def _edge_report(prep: _Prepared, opts: StitchOptions, run: _Run, results: dict[Pair, RegistrationResult],
                 T_model: list[NDArray], kept_pairs: set[Pair]) -> list[dict[str, Any]]:
    """Each edge's residual against the optimised poses; an odometry edge off by too much fails."""
    edges = []
    for (i, j), r in sorted(results.items()):
        rel = invert_transform(T_model[i]) @ T_model[j]
        ang, disp = _residual(rel, r.T_target_source, prep.radius, prep.centres[j])
        kind = "odometry" if j == i + 1 else "loop"
        edges.append({"source": j, "target": i, "kind": kind, "fitness": r.fitness, "inlier_rmse": r.inlier_rmse,
                      "residual_deg": ang, "residual": disp, "kept": (i, j) in kept_pairs,
                      "fallback": "turntable step" if kind == "odometry" and i in run.assumed else None})
        off = ang > opts.max_residual_deg or disp > _MAX_RESIDUAL_VOXELS * prep.rsp
        if kind == "odometry" and off:
            run.fail(
                f"views {prep.names[i]} and {prep.names[j]}: the pose graph disagrees with their pairwise "
                f"registration by {ang:.2f} deg / {disp:.3g} (loop does not close; a wrong match?)"
            )
        elif kind == "loop" and off:
            log.warning("loop closure %s-%s inconsistent (%.2f deg); discounted", prep.names[i], prep.names[j], ang)
    return edges


def _looks_like_turntable(T_model: list[NDArray], voxel: float) -> bool:
    """Do poses (first view the identity) share one rotation axis (see _TT_* above)?"""
    if len(T_model) < 3:
        return False
    u, p, _ = fit_turntable(T_model)
    for T in T_model[1:]:
        rv = rotvec_from_matrix(T[:3, :3])
        ang = float(np.linalg.norm(rv))
        if ang > np.radians(_TT_MIN_TURN_DEG) and abs(float(rv @ u)) / ang < np.cos(np.radians(_TT_AXIS_TOL_DEG)):
            return False
        R = T[:3, :3]
        if np.linalg.norm((np.eye(3) - R) @ p - T[:3, 3]) > _TT_CENTRE_VOXELS * voxel:
            return False
    return True


def _joint_refinement(prep: _Prepared, opts: StitchOptions, run: _Run, T_model: list[NDArray],
                      kept_pairs_ij: set[Pair]) -> tuple[list[NDArray], dict[str, Any]]:
    """All poses refined jointly over every overlapping pair, then on one turntable axis."""
    t0 = time.perf_counter()
    fine_p = [p for p, _ in (pyr.finest() for pyr in prep.pyramids)]
    fine_n = [v for _, v in (pyr.finest() for pyr in prep.pyramids)]
    # every overlapping pair, not only the pose graph's accepted edges
    pairs = sorted(kept_pairs_ij | set(overlapping_pairs(fine_p, fine_n, T_model, spacing=prep.rsp)))
    T_model, info = refine_multiview(fine_p, fine_n, T_model, pairs, spacing=prep.rsp)
    info = {**info, "pairs": float(len(pairs))}
    run.seconds["multiview"] = time.perf_counter() - t0
    log.info("multi-view refinement: %d iterations, rms %.3g, largest change %.3f deg",
             info["iterations"], info["rms"], info["max_change_deg"])
    use_tt = opts.turntable_constraint == "on" or (
        opts.turntable_constraint == "auto"
        and (opts.turntable_step_deg is not None or _looks_like_turntable(T_model, prep.rsp))
    )
    if use_tt and prep.n >= 3:
        T_model, info = _refine_on_turntable(opts, run, fine_p, fine_n, T_model, pairs, prep.rsp, info)
    return T_model, info


def _refine_on_turntable(opts: StitchOptions, run: _Run, fine_p: list[NDArray], fine_n: list[NDArray],
                         T_free: list[NDArray], pairs: list[Pair], rsp: float,
                         info: dict[str, Any]) -> tuple[list[NDArray], dict[str, Any]]:
    """Turntable-constrained poses, kept when their RMS stays near the free poses'."""
    t0 = time.perf_counter()
    T_tt, tt_info = refine_turntable(fine_p, fine_n, T_free, pairs, spacing=rsp)
    run.seconds["turntable"] = time.perf_counter() - t0
    if tt_info["rms"] <= opts.max_turntable_rms_ratio * tt_info["rms_input"]:
        log.info("turntable refinement: rms %.3g (free poses %.3g), largest change %.3f deg",
                 tt_info["rms"], tt_info["rms_input"], tt_info["max_change_deg"])
        return T_tt, {**info, "turntable": tt_info}
    msg = (f"the views do not fit one turntable axis (point-to-plane rms {tt_info['rms']:.3g} "
           f"against {tt_info['rms_input']:.3g} with free poses): was the object moved "
           "between shots? keeping the free poses")
    run.warnings.append(msg)
    log.warning(msg)
    return T_free, info


def _lever_warnings(opts: StitchOptions, run: _Run, names: list[str], mv_info: dict[str, Any]) -> NDArray:
    """Per view, its rotation lever; a warning names each view held far below the median."""
    levers = np.asarray(mv_info["turntable"]["levers"] if "turntable" in mv_info
                        else mv_info.get("levers", np.zeros(0)), dtype=np.float64)
    n = len(names)
    if not (n >= 3 and len(levers) == n and opts.min_rotation_lever_ratio > 0):
        return levers
    med = float(np.median(levers))
    about = "its angle about the turntable axis" if "turntable" in mv_info else "its rotation"
    for k in range(n):
        if med > 0 and levers[k] < opts.min_rotation_lever_ratio * med:
            factor = f"~{med / levers[k]:.0f}x" if levers[k] * _LEVER_FACTOR_CAP >= med else "over 100x"
            run.warn(f"view {names[k]}: {about} rests on little of what it sees (rotation lever "
                     f"{levers[k]:.3g}, {levers[k] / med:.2f} of the median view's {med:.3g}): depth errors "
                     f"across those surfaces turn it {factor} more than a typical "
                     "view, so its pose is the least certain (a narrow object seen end-on? turn the object "
                     "so that no view is end-on)")
    return levers


def _pair_report(results: dict[Pair, Any], kept: set[Pair], T_model: list[NDArray],
                 pyramids: list[ScanPyramid]) -> list[dict[str, Any]]:
    """Per registered pair ``(i, j)`` (j onto i; odometry in order, then loops): its fit pairwise
    and at the final poses on the finest level, the scans' own noise, and reasons to check it."""
    dist = 2.0 * pyramids[0].spacing  # icp_pyramids' correspondence distance on the finest level
    noise = [surface_noise(p) for p in pyramids]
    out: list[dict[str, Any]] = []
    for (i, j), r in sorted(results.items(), key=lambda kv: (kv[0][1] != kv[0][0] + 1, kv[0])):
        pairwise, final = (
            evaluate_pyramids(pyramids[j], pyramids[i], T, max_distance=dist, sample=_PAIR_SAMPLE)
            for T in (r.T_target_source, invert_transform(T_model[i]) @ T_model[j])
        )
        p: dict[str, Any] = {"i": i, "j": j, "kind": "odometry" if j == i + 1 else "loop",
                             "kept": (i, j) in kept, "max_correspondence_distance": dist}
        for prefix, (fit, rmse, sigma) in (("", pairwise), ("final_", final)):
            p.update({f"{prefix}fitness": fit, f"{prefix}inlier_rmse": rmse, f"{prefix}plane_sigma": sigma})
        p["noise_sigma"] = float(np.hypot(noise[i], noise[j]))
        p["check"] = []
        low = min(p["fitness"], p["final_fitness"])
        if low < PAIR_CHECK_MIN_FITNESS:
            p["check"].append(f"overlap {low:.2f} < {PAIR_CHECK_MIN_FITNESS:g}")
        high = max(p["plane_sigma"], p["final_plane_sigma"])
        if high > PAIR_CHECK_NOISE_RATIO * p["noise_sigma"]:
            p["check"].append(f"off the surface by {high / p['noise_sigma']:.1f}x the scans' noise")
        out.append(p)
    return out


def _fuse(prep: _Prepared, opts: StitchOptions, run: _Run, T_model: list[NDArray]) -> tuple[Any, ...]:
    """Fused cloud ``(points, colors, normals)`` and the optional mesh ``(V, F, colors, closed)``."""
    t0 = time.perf_counter()
    scans, n = prep.scans, prep.n
    pts, col, nrm = fuse_clouds(
        [s[0] for s in scans], T_model, voxel=prep.spacing, colors=[s[1] for s in scans],
        min_views=2 if (opts.fusion_min_views == 2 and n >= 3) else 1,
    )
    run.seconds["fusion"] = time.perf_counter() - t0
    run.tick("fusion")
    mv = mf = mc = None
    mesh_closed = None
    if opts.mesh:
        t0 = time.perf_counter()
        mv, mf, mc = poisson_mesh(pts, nrm, colors=col, spacing=prep.spacing, depth=opts.mesh_depth,
                                  trim_quantile=opts.mesh_trim_quantile, smooth_iterations=opts.smooth_iterations,
                                  max_distance=None if opts.mesh_max_spacings is None
                                  else opts.mesh_max_spacings * prep.spacing)
        run.seconds["mesh"] = time.perf_counter() - t0
        mesh_closed = mesh_is_closed(mf)
        if not mesh_closed and opts.mesh_trim_quantile == 0 and opts.mesh_max_spacings is None:
            log.warning("the Poisson mesh is not closed")
    run.tick("mesh")
    return pts, col, nrm, mv, mf, mc, mesh_closed


def stitch_scans(
    clouds: Sequence[Cloud | str | Path],
    options: StitchOptions | None = None,
    *,
    progress: ProgressFn | None = None,
) -> StitchResult:
    """Register scans of one object from several views and fuse them.

    ``clouds``: scans in acquisition order, each in its sensor frame, as ``(points (N, 3) any
    unit, colors (N, 3) uint8 / float in [0, 1] or None, normals (N, 3) or None)`` or
    ``.ply`` / ``.pcd`` paths; ``options`` None for the defaults; ``progress(done, total,
    label)``. Raises InputError on bad input and ReconstructionError (naming the views) on
    scans that cannot be registered.
    """
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    opts = StitchOptions() if options is None else options
    t_start = time.perf_counter()
    scans, names = _validate_clouds(clouds, opts.min_confidence)
    run = _Run(len(scans), opts.on_failure, progress)
    t0 = time.perf_counter()
    prep = _prepare_scans(scans, names, opts)
    run.seconds["prepare"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    results, _, A = _odometry(prep, opts, run)
    run.seconds["odometry"] = time.perf_counter() - t0
    T_model = _chain_poses(results, prep.n)
    t0 = time.perf_counter()
    _loop_closures(prep, opts, run, results, T_model)
    run.seconds["loop_closures"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    T_model, kept_pairs = _optimise_pose_graph(prep, results, T_model)
    edges = _edge_report(prep, opts, run, results, T_model, kept_pairs)
    run.seconds["pose_graph"] = time.perf_counter() - t0
    run.tick("pose graph")
    kept_pairs_ij = {(min(i, j), max(i, j)) for i, j in kept_pairs}
    mv_info: dict[str, Any] = {}
    if opts.multiview:
        T_model, mv_info = _joint_refinement(prep, opts, run, T_model, kept_pairs_ij)
    for T in T_model:
        if abs(np.linalg.det(T[:3, :3]) - 1.0) > _RIGID_DET_TOL:
            raise ReconstructionError("stitching produced a non-rigid pose")
    levers = _lever_warnings(opts, run, names, mv_info)
    t0 = time.perf_counter()
    pairs = _pair_report(results, kept_pairs_ij, T_model, prep.pyramids)
    run.seconds["pairs"] = time.perf_counter() - t0
    pts, col, nrm, mv, mf, mc, mesh_closed = _fuse(prep, opts, run, T_model)
    run.seconds["total"] = time.perf_counter() - t_start
    diag = {"spacing": prep.spacing, "registration_voxel": prep.rsp,
            "turntable_motion": None if A is None else A.tolist(), "mesh_closed": mesh_closed, "edges": edges,
            "pairs": pairs, "multiview": mv_info, "rotation_levers": [float(v) for v in levers],
            "warnings": run.warnings, "seconds": run.seconds, "names": names}
    return StitchResult(T_model, pts, col, nrm, mv, mf, mc, diag)


def _checked_file_args(scan_paths: Sequence[str | Path], out_model_ply: str | Path,
                       mesh_out: str | Path | None, frame: str, front_view: int | None) -> list[str]:
    """The scan paths as strings, once the files, output names, frame and front view are
    checked: a bad argument fails before any stitching."""
    if isinstance(scan_paths, (str, Path)):
        raise InputError("scan_paths: expected a list of scan files")
    paths = [str(p) for p in scan_paths]
    for p in paths:
        if not Path(p).is_file():
            raise InputError(f"{p}: scan file not found")
    outs = [Path(out_model_ply)] + ([Path(mesh_out)] if mesh_out is not None else [])
    for o in outs:
        if o.suffix.lower() != ".ply":
            raise InputError(f"{o}: the model and mesh are written as PLY; name them .ply")
        if o.is_dir():
            raise InputError(f"{o}: is a folder; give an output file name")
    if len(outs) == 2 and outs[0].resolve() == outs[1].resolve():
        raise InputError("the model and the mesh name the same file; give each its own path")
    check_choice(frame, "frame", ("scan", "object"))
    if front_view is not None and frame != "object":
        raise InputError("front_view: only with the object frame (--frame object)")
    if front_view is not None and not (isinstance(front_view, int) and 0 <= front_view < len(paths)):
        raise InputError(f"front_view: expected a scan index in [0, {len(paths) - 1}], got {front_view!r}")
    return paths


def stitch_to_files(
    scan_paths: Sequence[str | Path],
    out_model_ply: str | Path,
    options: StitchOptions | None = None,
    *,
    mesh_out: str | Path | None = None,
    progress: ProgressFn | None = None,
    frame: str = "scan",
    front_view: int | None = None,
) -> StitchResult:
    """Stitch ``.ply`` / ``.pcd`` scan files (the ``prism3d stitch`` command) and write, all or
    none: ``out_model_ply`` (fused cloud), ``mesh_out`` when given (``options.mesh`` follows it)
    and ``poses.json`` beside the model (``schema_version``, ``model``, ``scans`` with ``path``
    and ``T_model_scan``, ``pairs`` as in the diagnostics, ``fallbacks``: pairs placed by the
    given turntable step, and the ``warnings``). ``frame`` ``"scan"``: the model in
    the first scan's camera frame; ``"object"``: in the object frame
    (:func:`~prism3d.reconstruct.scan.object_frame.object_frame`: z up, x forward, origin on the
    support; PLY header ``up z``), with ``object_frame`` (``T_object_model`` ...) in
    poses.json; ``T_model_scan`` stays in the first scan's frame. ``front_view``: the scan
    (index) that faced the object's front, which sets x's sign (else a stated guess)."""
    paths = _checked_file_args(scan_paths, out_model_ply, mesh_out, frame, front_view)
    opts = dataclasses.replace(StitchOptions() if options is None else options, mesh=mesh_out is not None)
    out = Path(out_model_ply)
    out.parent.mkdir(parents=True, exist_ok=True)
    with output_lock(out):  # a second stitch into the same model is refused, not raced
        return _stitch_and_write(paths, opts, out, mesh_out, progress, frame, front_view)


def _stitch_and_write(paths: list[str], opts: StitchOptions, out: Path, mesh_out: str | Path | None,
                      progress: ProgressFn | None, frame: str, front_view: int | None) -> StitchResult:
    res = stitch_scans(paths, opts, progress=progress)
    doc = {
        "schema_version": POSES_SCHEMA_VERSION,
        "model": out.name,
        "scans": [{"path": p, "T_model_scan": T.tolist()} for p, T in zip(paths, res.T_model_scan, strict=True)],
        "pairs": res.diagnostics["pairs"],
        "fallbacks": [{"views": [e["target"], e["source"]], "placed_by": e["fallback"], "fitness": e["fitness"]}
                      for e in res.diagnostics["edges"] if e.get("fallback")],
        "warnings": list(res.diagnostics["warnings"]),
    }
    T_out, where = np.eye(4), ["frame of the first scan"]
    if frame == "object":
        of = object_frame(res.points, res.T_model_scan, front_view=front_view,  # before anything is written
                          normals=res.normals)
        T_out, doc["object_frame"] = of.T_object_model, of.to_dict()
        where = [f"object frame: z up (from the {of.up_from}), x forward, origin on the support", "up z"]
        res.diagnostics["object_frame"] = of.to_dict()
    R, t = T_out[:3, :3], T_out[:3, 3]
    names = [out, out.parent / "poses.json"] + ([Path(mesh_out)] if mesh_out is not None else [])
    with atomic_paths(*names) as tmp:  # all of them, or none
        tmp_model, tmp_poses = tmp[0], tmp[1]
        tmp_mesh = tmp[2] if mesh_out is not None else None
        write_ply(tmp_model, res.points @ R.T + t, colors=res.colors,
                  normals=None if res.normals is None else res.normals @ R.T.astype(np.float32),
                  comments=["prism3d stitch: fused model", "units mm", *where])
        atomic_write_text(tmp_poses, json.dumps(doc, indent=1))
        if tmp_mesh is not None:
            write_ply(tmp_mesh, res.mesh_vertices @ R.T + t, faces=res.mesh_faces, colors=res.mesh_colors,
                      comments=["prism3d stitch: Poisson mesh", "units mm", *where])
    return res
