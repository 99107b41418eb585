"""Stitching of multi-view scans into one 360-degree model.

Pipeline (:func:`stitch_scans`):

1. Load the scans (arrays, PLY or PCD); measure the point spacing (median
   nearest-neighbour distance), from which every distance parameter derives.
2. Odometry edges ``k+1 -> k``. With a known turntable step: the step's motion is
   a rotation by exactly ``step`` about a fixed but unknown axis, so it is the
   same rigid motion ``A`` for every consecutive pair. ``A`` is measured once by a
   global registration (FPFH + RANSAC) + ICP of the first pair that gives a
   rotation within 8 deg of the step, projected onto an exact step rotation
   (:func:`~prism3d.reconstruct.registration.turntable_motion`), and then used as
   the initial guess of every pair (``A^j`` for views ``j`` steps apart).
   Without a hint each consecutive pair is registered globally, then checked
   against its neighbours' motions (views taken in a sequence usually move
   alike): a neighbour's motion that fits clearly better replaces a match, one
   that agrees with a neighbour's lets it pass with less overlap, and one that
   moves unlike both neighbours, which agree, gives way to their common motion.
   Every edge is refined by multi-scale point-to-plane ICP with Tukey's robust
   loss. Registration works on copies voxel-down-sampled to about
   ``max_registration_points`` points; each copy is prepared once (voxel levels
   with normals, FPFH features) and shared by all its edges.
3. Loop-closure edges between non-adjacent views whose (predicted) viewing
   directions differ by at most 100 deg -- including last -> first of a 360
   sequence -- refined by ICP at the finest level from the chained odometry and
   kept when their fitness passes; each edge carries its information matrix.
4. A pose graph over all views, optimised globally (Levenberg-Marquardt with a
   line process that discounts wrong loop closures).
5. Failure detection: an odometry edge with too little overlap (fitness), a large
   inlier RMSE, or a large residual after the optimisation (the loop does not
   close) raises :class:`~prism3d.errors.ReconstructionError` naming the views
   (or logs a warning with ``on_failure="warn"``).
6. Joint refinement of all poses (:mod:`prism3d.reconstruct.multiview`) over every
   pair of views whose surfaces overlap at the pose graph's poses
   (:func:`~prism3d.reconstruct.multiview.overlapping_pairs`), then, for a
   turntable sequence, with all views constrained to one rotation axis.
7. Every registered pair's overlap and residuals, pairwise and re-measured at the
   final poses (``diagnostics["pairs"]``), with the pairs worth checking marked.
8. Fusion (:mod:`prism3d.reconstruct.fusion`): voxel-averaged coloured cloud and
   an optional watertight Poisson mesh.

The model frame is the first scan's frame.

References
----------
.. [1] S. Choi, Q.-Y. Zhou, V. Koltun, "Robust reconstruction of indoor scenes",
   CVPR 2015 (pose graph with line process).
.. [2] R. Kuemmerle et al., "g2o: A general framework for graph optimization",
   ICRA 2011.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_choice, check_in_range, check_positive
from prism3d.errors import InputError, ReconstructionError
from prism3d.io.atomic import atomic_path, atomic_write_text
from prism3d.progress import ProgressFn
from prism3d.reconstruct.fusion import fuse_clouds, mesh_is_closed, poisson_mesh
from prism3d.reconstruct.registration import (
    ScanFeatures,
    ScanPyramid,
    _global_voxel,
    evaluate_pyramids,
    icp_pyramids,
    match_features_candidates,
    point_spacing,
    rotation_angle_deg,
    surface_noise,
    turntable_motion,
)

__all__ = ["StitchResult", "load_cloud", "stitch_scans", "stitch_to_files"]

log = logging.getLogger(__name__)

#: Version of the ``poses.json`` written by :func:`stitch_to_files`.
POSES_SCHEMA_VERSION = 1

Cloud = tuple[NDArray, NDArray | None, NDArray | None]


@dataclass
class StitchResult:
    """A stitched model.

    Attributes
    ----------
    T_model_scan : list of (4, 4) float64
        Per input scan, the transform mapping its points into the model frame
        (= the first scan's frame; ``T_model_scan[0]`` is the identity).
    points : (N, 3) float64
        Fused, voxel-averaged model cloud (input units).
    colors : (N, 3) uint8 or None
        Present when every scan had colours.
    normals : (N, 3) float32
        Outward unit normals.
    mesh_vertices : (V, 3) float64 or None
    mesh_faces : (F, 3) int64 or None
    mesh_colors : (V, 3) uint8 or None
    diagnostics : dict
        ``spacing``, ``registration_voxel``, ``edges`` (list of dicts: ``source``,
        ``target``, ``kind`` odometry/loop, ``fitness``, ``inlier_rmse``,
        ``residual_deg``, ``residual`` (largest displacement of a source point within
        the cloud radius, input units),
        ``kept``), ``pairs`` (list of dicts, one per registered pair, odometry pairs in
        order then loop closures: ``i``, ``j`` (scan j registered onto scan i),
        ``kind``, ``kept`` (an edge of the optimised pose graph), ``fitness`` (the
        fraction of scan j's registration points with a point of scan i within
        ``max_correspondence_distance``), ``inlier_rmse`` (their RMS distance, input
        units), ``plane_sigma`` (the spread of their distances from scan i's surface,
        robust to edge pairs), each of the pairwise registration, the same three at the
        final poses as ``final_fitness``, ``final_inlier_rmse``, ``final_plane_sigma``,
        all on the finest registration level at ``max_correspondence_distance``;
        ``noise_sigma`` (the ``plane_sigma`` the two scans' own noise gives a correct
        alignment) and ``check`` (reasons to look at the pair: overlap below
        ``PAIR_CHECK_MIN_FITNESS``, a ``plane_sigma`` above ``PAIR_CHECK_NOISE_RATIO``
        times ``noise_sigma``; empty when none)),
        ``multiview`` (iterations, rms, max_change_deg, correspondences, pairs -- the
        number of overlapping view pairs refined jointly; empty when off),
        ``rotation_levers`` (per view, how firmly its
        correspondences in the last joint refinement fix its angle about the
        turntable axis, or its weakest rotation, as a length in input units; see
        ``min_rotation_lever_ratio``; empty without ``multiview``),
        ``mesh_closed`` (every mesh edge shared by exactly two faces;
        None without a mesh), ``warnings`` (list of str) and ``seconds`` per
        stage.
    """

    T_model_scan: list[NDArray[np.float64]]
    points: NDArray[np.float64]
    colors: NDArray[np.uint8] | None
    normals: NDArray[np.float32]
    mesh_vertices: NDArray[np.float64] | None = None
    mesh_faces: NDArray[np.int64] | None = None
    mesh_colors: NDArray[np.uint8] | None = None
    diagnostics: dict[str, Any] = field(default_factory=dict)


#: Scan files that carry a per-point ``confidence`` (prism3d's scans: the chance the
#: point's disparity is within 1 px, from its predicted std) are registered and fused on
#: the points at or above this (std <= 0.61 px). Points estimated from their neighbours
#: (occlusions, untextured holes) carry errors of a pixel or more that pull the
#: registration: worst view pose on tank_t1 / tank_t2, real camera effects, 0.068 /
#: 0.142 deg with every point, 0.039 / 0.095 at 0.9 (docs/reconstruction.md).
STITCH_MIN_CONFIDENCE = 0.9


def load_cloud(path: str | Path, *, min_confidence: float = 0.0) -> Cloud:
    """Read a scan from ``.ply`` or ``.pcd``: ``(points, colors, normals)``, keeping the
    points whose ``confidence`` property (when the file has one) reaches
    ``min_confidence``.

    Raises
    ------
    InputError
        Missing/unreadable file, unknown suffix, or no points; the message names
        the file.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".ply":
        from prism3d.io.ply import read_ply

        d = read_ply(p)
        pts, col, nrm = d.points, d.colors, d.normals
        conf = d.extra.get("confidence")
        if min_confidence > 0 and conf is not None:
            keep = np.asarray(conf) >= min_confidence
            pts = pts[keep]
            col = None if col is None else col[keep]
            nrm = None if nrm is None else nrm[keep]
    elif suffix == ".pcd":
        from prism3d.io.pcd import read_pcd

        d2 = read_pcd(p)
        pts, col, nrm = d2.points, d2.colors, d2.normals
    else:
        raise InputError(f"{p}: unknown point-cloud format {suffix!r} (expected .ply or .pcd)")
    if len(pts) == 0:
        raise InputError(f"{p}: the scan has no points")
    return np.asarray(pts, dtype=np.float64), col, nrm


# Largest displacement of a scan point, as a fraction of the object's radius, by
# which a pair's motion may differ from its neighbour's and still count as the same
# motion (the constant-motion check of stitch_scans); 0.1 allows < 5.7 deg.
_MOTION_AGREEMENT = 0.1


def _rigid_inverse(T: NDArray) -> NDArray[np.float64]:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _residual(T_a: NDArray, T_b: NDArray, radius: float, centre: NDArray | None = None) -> tuple[float, float]:
    """Rotation angle (deg) and largest displacement of a point within ``radius`` of
    ``centre`` (the source cloud's centroid; default the origin) between two transforms.

    Measured about the cloud, not the sensor: a scan 1.25 m from its camera would
    otherwise turn a 0.5 deg disagreement into an 11 mm "displacement"."""
    D = _rigid_inverse(T_a) @ T_b
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
        if finite.sum() < 30:
            raise InputError(f"{name}: expected at least 30 finite points, got {int(finite.sum())}")
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


#: A registered pair is marked for checking when less than this fraction of its source
#: scan's points overlap the target, pairwise or in the finished model ...
PAIR_CHECK_MIN_FITNESS = 0.3
#: ... or when its residual off the surface (plane_sigma) exceeds this multiple of what
#: the two scans' own noise gives a correct alignment (correct pairs measure 0.8-1.3x).
PAIR_CHECK_NOISE_RATIO = 3.0
#: Source points per pair measurement (the same seeded subset at both poses): the fitness
#: carries a sampling error of at most 0.006 (1 sigma), and a pair costs ~6 ms instead of
#: ~35 ms for all ~33k points of a tank scan.
_PAIR_SAMPLE = 8000


def _pair_report(
    results: dict[tuple[int, int], Any],
    kept: set[tuple[int, int]],
    T_model: list[NDArray],
    pyramids: list[ScanPyramid],
) -> list[dict[str, Any]]:
    """Per registered pair ``(i, j)`` (scan j registered onto scan i): its fit at the
    pairwise registration and at the final poses, both on the finest level at the finest
    ICP correspondence distance (comparable between pairs; loop closures were registered
    on a coarser level), the residual the scans' own noise gives, and the reasons to
    check the pair. Odometry pairs in order, then loop closures."""
    dist = 2.0 * pyramids[0].spacing  # icp_pyramids' correspondence distance on the finest level
    noise = [surface_noise(p) for p in pyramids]
    out: list[dict[str, Any]] = []
    for (i, j), r in sorted(results.items(), key=lambda kv: (kv[0][1] != kv[0][0] + 1, kv[0])):
        pairwise, final = (
            evaluate_pyramids(pyramids[j], pyramids[i], T, max_distance=dist, sample=_PAIR_SAMPLE)
            for T in (r.T_target_source, _rigid_inverse(T_model[i]) @ T_model[j])
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


def _looks_like_turntable(T_model: list[NDArray], voxel: float) -> bool:
    """Do poses (first view the identity) share one rotation axis? Every view turned
    by more than 10 deg has its axis within 1 deg of the common one and its
    translation within ``5 * voxel`` of a pure rotation about it."""
    from prism3d.reconstruct.multiview import _rotvec, fit_turntable

    if len(T_model) < 3:
        return False
    u, p, _ = fit_turntable(T_model)
    for T in T_model[1:]:
        rv = _rotvec(T[:3, :3])
        ang = float(np.linalg.norm(rv))
        if ang > np.radians(10.0) and abs(float(rv @ u)) / ang < np.cos(np.radians(1.0)):
            return False
        R = T[:3, :3]
        if np.linalg.norm((np.eye(3) - R) @ p - T[:3, 3]) > 5.0 * voxel:
            return False
    return True


def stitch_scans(
    clouds: Sequence[Cloud | str | Path],
    *,
    turntable_step_deg: float | None = None,
    voxel: float | None = None,
    mesh: bool = True,
    mesh_depth: int | None = None,
    mesh_trim_quantile: float = 0.0,
    smooth_iterations: int = 0,
    min_fitness: float = 0.2,
    min_turntable_fitness: float = 0.1,
    max_residual_deg: float = 1.0,
    max_registration_points: int = 30000,
    loop_max_angle_deg: float = 100.0,
    multiview: bool = True,
    turntable_constraint: str = "auto",
    max_turntable_rms_ratio: float = 1.25,
    global_candidates: int = 5,
    fusion_min_views: int = 2,
    min_rotation_lever_ratio: float = 0.2,
    min_confidence: float = STITCH_MIN_CONFIDENCE,
    on_failure: str = "raise",
    seed: int = 0,
    progress: ProgressFn | None = None,
) -> StitchResult:
    """Register scans of one object taken from several views and fuse them.

    Parameters
    ----------
    clouds : list of (points, colors, normals) or of paths
        Each scan in its own sensor frame (the sensor at the origin, e.g. a
        prism3d scan in its left-camera frame): ``points (N, 3)`` float, any unit
        (millimetres or metres), ``colors (N, 3)`` uint8 or float in [0, 1] or
        None, ``normals (N, 3)`` or None. Paths: ``.ply`` or ``.pcd``. Scans are
        in acquisition order (consecutive scans overlap).
    turntable_step_deg : float, optional
        Known rotation between consecutive views (a turntable). Used to predict
        every relative pose and to reject wrong global matches.
    voxel : float, optional
        Fusion voxel and base ICP distance scale, cloud units. Default: the
        median point spacing of the scans.
    mesh : bool
        Also build a Poisson mesh.
    mesh_depth : int, optional
        Poisson octree depth (default from extent / spacing).
    mesh_trim_quantile : float
        Density-quantile trimming of the mesh. 0 (default) keeps it closed
        (watertight) but invents a smooth surface where no scan looked; > 0 removes
        that guess and opens holes there (see
        :func:`~prism3d.reconstruct.fusion.poisson_mesh`).
    smooth_iterations : int
        Taubin smoothing passes on the mesh.
    min_fitness : float
        Smallest acceptable overlap fraction of an odometry edge found by global
        registration; loop-closure edges below it are skipped. Global registration
        can match a symmetric object's opposite sides: a tank's views 180 deg apart
        align (wrongly) at fitness 0.12.
    min_turntable_fitness : float
        The same for an odometry edge that ICP converged to from the known turntable
        motion, or (without a hint) whose motion agrees with a neighbouring pair's
        motion that fits at ``min_fitness`` or better: with the motion known or
        corroborated, a small overlap is not a sign of a wrong match. On
        reconstructed scans of the twelve built-in targets (8 views, 45 deg)
        consecutive views overlap down to 0.165 (a ship or a truck end-on, then
        oblique).
    max_residual_deg : float
        Largest rotation residual of an edge after the pose-graph optimisation.
    max_registration_points : int
        Scans are voxel-down-sampled to about this size for registration
        (fusion uses every point).
    loop_max_angle_deg : float
        Non-adjacent views are tried as loop closures when their predicted
        relative rotation is at most this.
    global_candidates : int
        Distinct global-registration alignments tried per pair (each refined
        coarsely by ICP, the best fitting kept).
    fusion_min_views : {1, 2}
        2 (default, with 3 or more scans): the fused cloud keeps only points that
        another scan confirms (:func:`~prism3d.reconstruct.fusion.fuse_clouds`),
        dropping view-dependent stereo artefacts; 1 keeps every point.
    min_rotation_lever_ratio : float
        With 3 or more views and ``multiview``, a warning names every view whose
        rotation lever (``levers`` of
        :func:`~prism3d.reconstruct.multiview.refine_turntable`: how firmly its
        correspondences fix its angle about the turntable axis, or its weakest
        rotation when the poses are free) is below this fraction of the median
        view's. Such a view's pose follows the depth errors of a few surfaces: a
        built-in ship seen end-on, held by its 35 mm transom alone, has
        0.16-0.18 of the median on stereo scans (7 renderings and camouflage
        seeds) and was turned 0.04-0.23 deg by their errors, where the other
        views stay within 0.05; every other view of the twelve built-in targets
        has 0.25 or more. 0 turns the check off. The levers are in
        ``diagnostics["rotation_levers"]``.
    multiview : bool
        After the pose graph, refine all poses jointly against all their overlaps
        (:func:`~prism3d.reconstruct.multiview.refine_multiview`): on stereo scans
        with view-dependent errors this takes the worst pose from 0.47 deg to
        0.05-0.07 deg of the truth (four targets), on truth-depth scans from 0.053
        to 0.018 deg.
    turntable_constraint : {"auto", "on", "off"}
        Finish (after ``multiview``) with the views constrained to one turntable
        axis (:func:`~prism3d.reconstruct.multiview.refine_turntable`: the axis and
        one angle per view instead of 6 free parameters per view). The free
        refinement's remaining errors on stereo scans are tilts of the views about
        horizontal axes, which a turntable cannot make. ``"auto"``: when
        ``turntable_step_deg`` is given, or when the free poses already share one
        rotation axis (every view's axis within 1 deg of the common one, and each
        view's translation within 5 registration voxels of a pure rotation about
        it); ``"on"``: always (with 3 or more views); ``"off"``: never. Only with
        ``multiview``. The step's angle is only a starting value: every view's
        angle is estimated.
    max_turntable_rms_ratio : float
        The constrained poses are kept only if their point-to-plane RMS is at most
        this times the free poses' RMS; otherwise the views are taken not to share
        one axis (the object was moved between shots) and a warning says so.
    min_confidence : float in [0, 1]
        Scan files with a per-point ``confidence`` (prism3d scans) are registered and
        fused on the points at or above it (:data:`STITCH_MIN_CONFIDENCE`); arrays
        passed directly are used whole.
    on_failure : {"raise", "warn"}
        Failed checks raise :class:`ReconstructionError` or log warnings (also
        listed in ``diagnostics["warnings"]``).
    seed : int
        Seed of the global registration (results are deterministic).
    progress : callable(done, total, label), optional

    Returns
    -------
    StitchResult

    Raises
    ------
    InputError
        Fewer than 2 scans, empty scans, unreadable files, bad parameters.
    ReconstructionError
        Scans that cannot be registered (no overlap, loop does not close),
        naming the views.
    """
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    check_choice(on_failure, "on_failure", ("raise", "warn"))
    check_choice(turntable_constraint, "turntable_constraint", ("auto", "on", "off"))
    check_positive(max_turntable_rms_ratio, "max_turntable_rms_ratio")
    check_positive(min_fitness, "min_fitness")
    check_positive(min_turntable_fitness, "min_turntable_fitness")
    check_positive(max_residual_deg, "max_residual_deg")
    if not (np.isfinite(min_rotation_lever_ratio) and 0 <= min_rotation_lever_ratio < 1):
        raise InputError(f"min_rotation_lever_ratio: expected a number in [0, 1), got {min_rotation_lever_ratio}")
    if turntable_step_deg is not None:
        check_positive(abs(float(turntable_step_deg)), "turntable_step_deg")
        if abs(float(turntable_step_deg)) >= 180:
            raise InputError(f"turntable_step_deg: expected |step| < 180, got {turntable_step_deg}")
    t_start = time.perf_counter()
    seconds: dict[str, float] = {}
    check_in_range(min_confidence, "min_confidence", 0.0, 1.0)
    scans, names = _validate_clouds(clouds, min_confidence)
    n = len(scans)
    n_pairs_est = 2 * n
    total_steps = n_pairs_est + 3
    step_i = 0

    def tick(label: str) -> None:
        nonlocal step_i
        step_i += 1
        if progress is not None:
            progress(min(step_i, total_steps), total_steps, label)

    warnings_: list[str] = []

    def fail(msg: str) -> None:
        if on_failure == "raise":
            raise ReconstructionError(msg)
        log.warning(msg)
        warnings_.append(msg)

    t0 = time.perf_counter()
    spacings = [point_spacing(s[0], seed=seed) for s in scans]
    spacing = float(np.median(spacings)) if voxel is None else float(check_positive(voxel, "voxel"))
    reg_pts = []
    reg_sp = []
    for s in scans:
        p, v = _registration_copy(s[0], spacing, max_registration_points)
        reg_pts.append(p)
        reg_sp.append(v)
    rsp = float(max(reg_sp))
    centres = [p.mean(axis=0) for p in reg_pts]
    radius = float(max(np.percentile(np.linalg.norm(p - c, axis=1), 95) for p, c in zip(reg_pts, centres, strict=True)))
    # Every scan is prepared once (voxel levels + normals, FPFH features on demand)
    # and reused by all the edges it takes part in.
    pyramids = [ScanPyramid(p, rsp) for p in reg_pts]
    feat_voxel = _global_voxel(reg_pts[0], rsp, 3000)
    features: dict[int, ScanFeatures] = {}

    def feats(k: int) -> ScanFeatures:
        if k not in features:
            features[k] = ScanFeatures(reg_pts[k], feat_voxel)
        return features[k]

    seconds["prepare"] = time.perf_counter() - t0

    # --- odometry edges ---------------------------------------------------
    t0 = time.perf_counter()
    edges: list[dict[str, Any]] = []
    results: dict[tuple[int, int], Any] = {}

    def icp(i: int, j: int, init: NDArray, first_scale: float | None = None,
            last_scale: float | None = None):
        """Register scan j onto scan i (T_i_j)."""
        return icp_pyramids(pyramids[j], pyramids[i], init, first_scale=first_scale, last_scale=last_scale)

    def global_pair(i: int, j: int):
        # Several distinct RANSAC alignments, each refined coarsely by ICP; the best
        # fitting one is refined fully. (The alignment with the most feature matches
        # can be wrong on symmetric, boxy objects: a truck seen end-on matched 90
        # deg off at fitness 0.36 when the right alignment fits 0.70.)
        try:
            cands = match_features_candidates(feats(j), feats(i), seed=seed, max_candidates=global_candidates)
        except ReconstructionError as exc:
            raise ReconstructionError(
                f"views {names[i]} and {names[j]} do not overlap: {exc} (are they consecutive views of one "
                "object?)"
            ) from exc
        if len(cands) == 1:
            return icp(i, j, cands[0][0])
        coarse = [icp(i, j, T, last_scale=4.0) for T, _ in cands]
        best = max(range(len(coarse)), key=lambda k: (round(coarse[k].fitness, 3), -coarse[k].inlier_rmse))
        return icp(i, j, coarse[best].T_target_source, first_scale=2.0)

    A: NDArray | None = None
    # odometry edges ICP found from the known turntable motion, or (no hint) whose
    # motion a neighbouring pair corroborates: held to min_turntable_fitness
    corroborated: set[int] = set()
    if turntable_step_deg is not None:
        for k in range(min(n - 1, 3)):
            r = global_pair(k, k + 1)
            cand = turntable_motion(r.T_target_source, float(turntable_step_deg))
            if cand is not None and r.fitness >= min_fitness:
                A = cand
                results[(k, k + 1)] = r
                break
            log.info("turntable axis from views %d-%d rejected (fitness %.3f)", k, k + 1, r.fitness)
        if A is None:
            fail(
                f"could not find the turntable motion of {turntable_step_deg} deg between "
                f"{names[0]} .. {names[min(n - 1, 3)]}: global registration found no rotation "
                "of that size"
            )
    for k in range(n - 1):
        r = results.get((k, k + 1))
        if r is None and A is not None:
            r = icp(k, k + 1, A, first_scale=4.0)
            if r.fitness < min_turntable_fitness:
                r = None
            else:
                corroborated.add(k)
        if r is None:
            r = global_pair(k, k + 1)
        results[(k, k + 1)] = r
        tick(f"odometry {k}-{k + 1}")
    if A is None and n > 2:

        def same_motion(T_a: NDArray, T_b: NDArray, k: int) -> bool:
            """Do two pairs' motions agree on scan k+1's points (within
            _MOTION_AGREEMENT of the object's radius)?"""
            return _residual(T_a, T_b, radius, centres[k + 1])[1] <= _MOTION_AGREEMENT * radius

        # Constant-motion check (no turntable hint): views taken in a sequence
        # usually move alike, so each pair is also tried from its neighbours'
        # motions. A clearly better fit (+0.05) replaces a global match that went
        # wrong (e.g. a boxy object's end-on view matched to the wrong face); a
        # global match that fails min_fitness anyway is replaced by any better fit.
        for k in range(n - 1):
            cur = results[(k, k + 1)]
            for m in (k - 1, k + 1):
                if not (0 <= m < n - 1):
                    continue
                r = icp(k, k + 1, results[(m, m + 1)].T_target_source, first_scale=4.0)
                margin = 0.05 if cur.fitness >= min_fitness else 0.0
                if r.fitness > cur.fitness + margin:
                    log.info("views %s-%s: the neighbours' motion fits better (%.3f > %.3f)",
                             names[k], names[k + 1], r.fitness, cur.fitness)
                    cur = r
            results[(k, k + 1)] = cur
        # A pair whose motion agrees with a neighbouring pair's well-fitting motion
        # (no point of the scan moved by more than _MOTION_AGREEMENT of the object's
        # radius between the two) is corroborated by it, like an edge found from a
        # turntable step, and is held to min_turntable_fitness: a truck's end-on
        # view and the oblique one after it overlap at fitness 0.18 (their global
        # match, 0.15, was 36 deg off). The loop-closure checks below still apply.
        for k in range(n - 1):
            T_k = results[(k, k + 1)].T_target_source
            for m in (k - 1, k + 1):
                if (0 <= m < n - 1 and results[(m, m + 1)].fitness >= min_fitness
                        and same_motion(results[(m, m + 1)].T_target_source, T_k, k)):
                    corroborated.add(k)
        # A pair whose match agrees with neither neighbour, while the two neighbours
        # (each fitting at min_fitness or better) agree with each other, is
        # registered again from their common motion. If that fit reaches
        # min_turntable_fitness and keeps the common motion, it replaces the match
        # even at a lower fitness: a jet seen tail-on (stereo scans) matched the
        # next view at 0.253 with the views after it turned 90 deg about a
        # horizontal axis, while the true motion fits 0.208.
        for k in range(1, n - 2):
            if k in corroborated:
                continue
            before, after = results[(k - 1, k)], results[(k + 1, k + 2)]
            if min(before.fitness, after.fitness) < min_fitness:
                continue
            if not same_motion(before.T_target_source, after.T_target_source, k):
                continue
            r = icp(k, k + 1, before.T_target_source, first_scale=4.0)
            if r.fitness >= min_turntable_fitness and same_motion(before.T_target_source, r.T_target_source, k):
                log.info("views %s-%s: their match (fitness %.3f) disagrees with both neighbours, which move "
                         "alike; using that common motion (fitness %.3f)",
                         names[k], names[k + 1], results[(k, k + 1)].fitness, r.fitness)
                results[(k, k + 1)] = r
                corroborated.add(k)
            else:
                msg = (f"views {names[k]} and {names[k + 1]} move unlike the pairs on either side, which "
                       "move alike: an uneven step, or a wrong match (check the poses from "
                       f"{names[k + 1]} on)")
                log.warning(msg)
                warnings_.append(msg)
    for k in range(n - 1):
        r = results[(k, k + 1)]
        if r.fitness < (min_turntable_fitness if k in corroborated else min_fitness):
            fail(
                f"views {names[k]} and {names[k + 1]} do not overlap enough to register "
                f"(fitness {r.fitness:.3f} < {min_turntable_fitness if k in corroborated else min_fitness}); "
                "are they consecutive views of one object?"
            )
        if r.inlier_rmse > 1.5 * r.max_distance:
            fail(f"views {names[k]} and {names[k + 1]}: registration residual too large ({r.inlier_rmse:.3g})")
    seconds["odometry"] = time.perf_counter() - t0

    # chained initial poses
    T_model = [np.eye(4)]
    for k in range(n - 1):
        T_model.append(T_model[-1] @ results[(k, k + 1)].T_target_source)

    # --- loop closures ----------------------------------------------------
    t0 = time.perf_counter()
    for i in range(n):
        for j in range(i + 2, n):
            init = _rigid_inverse(T_model[i]) @ T_model[j]
            if rotation_angle_deg(init) > loop_max_angle_deg:
                continue
            # the scale-2 level only: the joint refinements below put every pose on
            # the full clouds. The full-resolution level here cost ~10 s of a 30 s
            # budget; without it the final worst poses moved by -0.004..+0.007 deg
            # (6 stereo targets and the demo: noise at that level), truth-depth
            # scans 0.0069 -> 0.0070 deg
            r = icp(i, j, init, first_scale=2.0, last_scale=2.0)
            if r.fitness >= min_fitness and r.inlier_rmse <= 1.5 * r.max_distance:
                results[(i, j)] = r
            else:
                log.info("loop closure %s-%s skipped (fitness %.3f)", names[i], names[j], r.fitness)
            tick(f"loop {i}-{j}")
    seconds["loop_closures"] = time.perf_counter() - t0

    # --- pose graph -------------------------------------------------------
    t0 = time.perf_counter()
    graph = reg.PoseGraph()
    for T in T_model:
        graph.nodes.append(reg.PoseGraphNode(T))
    for (i, j), r in sorted(results.items()):
        graph.edges.append(
            reg.PoseGraphEdge(j, i, r.T_target_source, r.information, uncertain=(j != i + 1))
        )
    if len(results) > n - 1:
        option = reg.GlobalOptimizationOption(
            max_correspondence_distance=3.0 * rsp,
            edge_prune_threshold=0.25,
            preference_loop_closure=1.0,
            reference_node=0,
        )
        reg.global_optimization(
            graph,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    T0_inv = _rigid_inverse(np.asarray(graph.nodes[0].pose))
    T_model = [T0_inv @ np.asarray(nd.pose, dtype=np.float64) for nd in graph.nodes]
    kept_pairs = {(e.target_node_id, e.source_node_id) for e in graph.edges}
    kept_pairs_ij = {(min(i, j), max(i, j)) for i, j in kept_pairs}
    for (i, j), r in sorted(results.items()):
        rel = _rigid_inverse(T_model[i]) @ T_model[j]
        ang, disp = _residual(rel, r.T_target_source, radius, centres[j])
        kind = "odometry" if j == i + 1 else "loop"
        edges.append(
            {"source": j, "target": i, "kind": kind, "fitness": r.fitness, "inlier_rmse": r.inlier_rmse,
             "residual_deg": ang, "residual": disp, "kept": (i, j) in kept_pairs}
        )
        if kind == "odometry" and (ang > max_residual_deg or disp > 20.0 * rsp):
            fail(
                f"views {names[i]} and {names[j]}: the pose graph disagrees with their pairwise "
                f"registration by {ang:.2f} deg / {disp:.3g} (loop does not close; a wrong match?)"
            )
        elif kind == "loop" and (ang > max_residual_deg or disp > 20.0 * rsp):
            log.warning("loop closure %s-%s inconsistent (%.2f deg); discounted", names[i], names[j], ang)
    seconds["pose_graph"] = time.perf_counter() - t0
    tick("pose graph")

    # --- joint multi-view refinement ----------------------------------------
    mv_info: dict[str, float] = {}
    if multiview:
        from prism3d.reconstruct.multiview import overlapping_pairs, refine_multiview

        t0 = time.perf_counter()
        fine = [pyr._levels[-1] for pyr in pyramids]
        fine_p = [np.asarray(pc.points) for pc in fine]
        fine_n = [np.asarray(pc.normals) for pc in fine]
        # every overlapping pair, not only the pose graph's accepted edges
        mv_pairs = sorted(kept_pairs_ij | set(overlapping_pairs(fine_p, fine_n, T_model, spacing=rsp)))
        T_model, mv_info = refine_multiview(fine_p, fine_n, T_model, mv_pairs, spacing=rsp)
        mv_info = {**mv_info, "pairs": float(len(mv_pairs))}
        seconds["multiview"] = time.perf_counter() - t0
        log.info("multi-view refinement: %d iterations, rms %.3g, largest change %.3f deg",
                 mv_info["iterations"], mv_info["rms"], mv_info["max_change_deg"])
        use_tt = turntable_constraint == "on" or (
            turntable_constraint == "auto" and (turntable_step_deg is not None or _looks_like_turntable(T_model, rsp))
        )
        if use_tt and n >= 3:
            from prism3d.reconstruct.multiview import refine_turntable

            t0 = time.perf_counter()
            T_tt, tt_info = refine_turntable(fine_p, fine_n, T_model, mv_pairs, spacing=rsp)
            seconds["turntable"] = time.perf_counter() - t0
            if tt_info["rms"] <= max_turntable_rms_ratio * tt_info["rms_input"]:
                T_model = T_tt
                mv_info = {**mv_info, "turntable": tt_info}
                log.info("turntable refinement: rms %.3g (free poses %.3g), largest change %.3f deg",
                         tt_info["rms"], tt_info["rms_input"], tt_info["max_change_deg"])
            else:
                msg = (f"the views do not fit one turntable axis (point-to-plane rms {tt_info['rms']:.3g} "
                       f"against {tt_info['rms_input']:.3g} with free poses): was the object moved "
                       "between shots? keeping the free poses")
                warnings_.append(msg)
                log.warning(msg)
    for T in T_model:
        if abs(np.linalg.det(T[:3, :3]) - 1.0) > 1e-6:
            raise ReconstructionError("stitching produced a non-rigid pose")

    # --- weakly held views ----------------------------------------------------
    levers = np.asarray(mv_info["turntable"]["levers"] if "turntable" in mv_info
                        else mv_info.get("levers", np.zeros(0)), dtype=np.float64)
    if n >= 3 and len(levers) == n and min_rotation_lever_ratio > 0:
        med = float(np.median(levers))
        about = "its angle about the turntable axis" if "turntable" in mv_info else "its rotation"
        for k in range(n):
            if med > 0 and levers[k] < min_rotation_lever_ratio * med:
                factor = f"~{med / levers[k]:.0f}x" if levers[k] * 100.0 >= med else "over 100x"
                msg = (f"view {names[k]}: {about} rests on little of what it sees (rotation lever "
                       f"{levers[k]:.3g}, {levers[k] / med:.2f} of the median view's {med:.3g}): depth errors "
                       f"across those surfaces turn it {factor} more than a typical "
                       "view, so its pose is the least certain (a narrow object seen end-on? turn the object "
                       "so that no view is end-on)")
                log.warning(msg)
                warnings_.append(msg)

    # --- every registered pair's fit, pairwise and in the finished model -------
    t0 = time.perf_counter()
    pairs = _pair_report(results, kept_pairs_ij, T_model, pyramids)
    seconds["pairs"] = time.perf_counter() - t0

    # --- fusion -----------------------------------------------------------
    t0 = time.perf_counter()
    pts, col, nrm = fuse_clouds(
        [s[0] for s in scans], T_model, voxel=spacing, colors=[s[1] for s in scans],
        min_views=2 if (fusion_min_views == 2 and n >= 3) else 1,
    )
    seconds["fusion"] = time.perf_counter() - t0
    tick("fusion")
    mv = mf = mc = None
    mesh_closed = None
    if mesh:
        t0 = time.perf_counter()
        mv, mf, mc = poisson_mesh(
            pts, nrm, colors=col, spacing=spacing, depth=mesh_depth,
            trim_quantile=mesh_trim_quantile, smooth_iterations=smooth_iterations,
        )
        seconds["mesh"] = time.perf_counter() - t0
        mesh_closed = mesh_is_closed(mf)
        if not mesh_closed and mesh_trim_quantile == 0:
            log.warning("the Poisson mesh is not closed")
    tick("mesh")
    seconds["total"] = time.perf_counter() - t_start
    diag = dict(  # noqa: C408
        spacing=spacing,
        registration_voxel=rsp,
        turntable_motion=None if A is None else A.tolist(),
        mesh_closed=mesh_closed,
        edges=edges,
        pairs=pairs,
        multiview=mv_info,
        rotation_levers=[float(v) for v in levers],
        warnings=warnings_,
        seconds=seconds,
        names=names,
    )
    return StitchResult(T_model, pts, col, nrm, mv, mf, mc, diag)


def stitch_to_files(
    scan_paths: Sequence[str | Path],
    out_model_ply: str | Path,
    *,
    mesh_out: str | Path | None = None,
    turntable_step_deg: float | None = None,
    progress: ProgressFn | None = None,
    **options: Any,
) -> StitchResult:
    """Stitch scan files and write the model (the ``prism3d stitch`` command).

    Writes ``out_model_ply`` (fused cloud with colours and normals), ``mesh_out``
    when given (Poisson mesh with vertex colours), and ``poses.json`` beside the
    model: ``{"schema_version": 1, "model": <model file name>, "scans": [{"path":
    <input path as given>, "T_model_scan": 4x4 list}, ...], "pairs": [...]}`` with
    ``pairs`` as in ``StitchResult.diagnostics`` (every registered pair's fit). All files
    appear together or not at all.

    Parameters
    ----------
    scan_paths : list of path
        ``.ply`` / ``.pcd`` scans in acquisition order.
    out_model_ply : path
    mesh_out : path, optional
    turntable_step_deg : float, optional
    progress : callable(done, total, label), optional
    **options
        Passed to :func:`stitch_scans`.

    Returns
    -------
    StitchResult
    """
    from prism3d.io.ply import write_ply

    if isinstance(scan_paths, (str, Path)):
        raise InputError("scan_paths: expected a list of scan files")
    paths = [str(p) for p in scan_paths]
    for p in paths:
        if not Path(p).is_file():
            raise InputError(f"{p}: scan file not found")
    res = stitch_scans(
        paths, turntable_step_deg=turntable_step_deg, mesh=mesh_out is not None,
        progress=progress, **options,
    )
    out = Path(out_model_ply)
    doc = {
        "schema_version": POSES_SCHEMA_VERSION,
        "model": out.name,
        "scans": [{"path": p, "T_model_scan": T.tolist()} for p, T in zip(paths, res.T_model_scan, strict=True)],
        "pairs": res.diagnostics["pairs"],
    }
    with contextlib.ExitStack() as stack:
        tmp_model = stack.enter_context(atomic_path(out))
        tmp_poses = stack.enter_context(atomic_path(out.parent / "poses.json"))
        tmp_mesh = stack.enter_context(atomic_path(mesh_out)) if mesh_out is not None else None
        write_ply(tmp_model, res.points, colors=res.colors, normals=res.normals,
                  comments=["prism3d stitch: fused model, frame of the first scan"])
        atomic_write_text(tmp_poses, json.dumps(doc, indent=1))
        if tmp_mesh is not None:
            write_ply(tmp_mesh, res.mesh_vertices, faces=res.mesh_faces, colors=res.mesh_colors,
                      comments=["prism3d stitch: Poisson mesh"])
    return res
