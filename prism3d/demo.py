"""``prism3d demo OUT_DIR``: the whole pipeline on built-in data, and its report.

The demo is a list of stages; each runs one capability on built-in data, writes its
artefacts under ``OUT_DIR`` and returns a :class:`~prism3d.report.Section`. A stage
that fails is reported in the page (with its error) and the demo exits non-zero, so a
broken install is visible rather than hidden.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from prism3d.atr.bank import FilterBank, train_bank
from prism3d.atr.chips import ChipSpec, load_mesh_file
from prism3d.atr.decamo import decamouflage
from prism3d.atr.detect import detect_shot
from prism3d.atr.evaluate import (
    EVAL_CHIP_SPEC,
    evaluate_bank,
    heldout_seed,
    plot_confusion,
    plot_per_aspect,
    plot_roc,
)
from prism3d.atr.features import model_features, scan_features
from prism3d.atr.scene import SceneDetection
from prism3d.atr.scene_eval import plot_scene, score_scenes
from prism3d.atr.survey_detect import DEFAULT_CLASSES, detect_in_survey
from prism3d.browser import check_page, find_chromium
from prism3d.capture.rig import StereoRig, paper_rig
from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
from prism3d.datasets.database import db as dbm
from prism3d.datasets.simulation.field import FieldOptions, simulate_field
from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight
from prism3d.datasets.database.ingest import add_builtin, add_meshes
from prism3d.datasets.jobs.database_jobs import run_features_job, run_render_job
from prism3d.datasets.jobs.recognisers import aerial_recogniser
from prism3d.datasets.database.resolve import resolve_targets
from prism3d.datasets.models.scanned import compare_scan_banks, scan_builtin_target
from prism3d.datasets.evaluation.survey_eval import evaluate_survey
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets
from prism3d.errors import InputError
from prism3d.geometry import rotation_angle_deg
from prism3d.io.atomic import atomic_path, atomic_write_text
from prism3d.io.images import read_image
from prism3d.io.ply import write_ply
from prism3d.progress import ProgressFn, null_progress
from prism3d.reconstruct.stereo.calibrate import CalibrationOptions, calibrate_stereo
from prism3d.reconstruct.stereo.flatness import REGIONS, flatness_test
from prism3d.reconstruct.stereo.meshing import smooth_depth, smoothing_resolution_mm
from prism3d.reconstruct.stereo.pipeline import ReconstructOptions, reconstruct_shot
from prism3d.reconstruct.stereo.rectify import rectify_shot
from prism3d.reconstruct.scan.stitch import StitchOptions, stitch_scans
from prism3d.reconstruct.scan.stitch_options import STITCH_MIN_CONFIDENCE
from prism3d.reconstruct.survey.run import run_survey
from prism3d.report import Report, Section, figure_png, image_png, point_cloud_viewer

__all__ = ["DemoContext", "run_demo", "STAGES"]

log = logging.getLogger(__name__)


@dataclass
class DemoContext:
    """State shared between demo stages (artefacts of earlier stages)."""

    out_dir: Path
    seed: int = 0
    fast: bool = False
    results: dict[str, Any] = field(default_factory=dict)

    def path(self, *parts: str) -> Path:
        p = self.out_dir.joinpath(*parts)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p


def _stage_environment(ctx: DemoContext) -> Section:
    """Check that every heavy dependency imports and the headless renderer works."""
    import importlib

    s = Section("Installation check")
    rows = []
    for mod in ("numpy", "scipy", "cv2", "open3d", "pyrender", "OpenGL", "skimage", "sklearn",
                "pandas", "pyarrow", "serial", "numba", "trimesh", "dask", "distributed"):
        m = importlib.import_module(mod)
        rows.append([mod, getattr(m, "__version__", getattr(m, "VERSION", "?"))])
    s.table("Libraries", ["module", "version"], rows)
    import numba

    s.paragraphs.append(
        f"OpenGL platform: <code>{os.environ.get('PYOPENGL_PLATFORM')}</code>; numba threading "
        f"layer: <code>{numba.config.THREADING_LAYER}</code>; CPU cores: {os.cpu_count()}."
    )
    return s


def depth_figure(depth_mm: Any, title: str) -> bytes:
    """A colour-mapped depth image (mm) with a colour bar, as PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(5, 4.2))
    d = np.asarray(depth_mm, dtype=np.float32)
    finite = d[np.isfinite(d)]
    lo, hi = (np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0))
    im = ax.imshow(np.ma.masked_invalid(d), cmap="viridis", vmin=lo, vmax=hi)
    ax.set_title(title)
    ax.axis("off")
    fig.colorbar(im, ax=ax, label="depth (mm)")
    return figure_png(fig)


def _stage_simulate(ctx: DemoContext) -> Section:
    """The virtual prism rig: one flash shot of a camouflaged target, with ground truth."""
    import numpy as np

    s = Section("Virtual prism rig: a simulated flash shot and its ground truth")
    out = ctx.path("simulate")
    target = builtin_target("tank_t1", seed=ctx.seed)
    summary = simulate_to_folder("scene", out, SimulateOptions(views=1, seed=ctx.seed,
                                                               supersample=1 if ctx.fast else 2),
                                 target=target)

    shot = read_image(out / "shot_00.png")
    with np.load(out / "truth_00.npz", allow_pickle=False) as t:
        depth = t["depth_left_mm"]
        mask = t["mask_left"]
    s.paragraphs.append(
        "One camera, a prism adapter putting two views side by side on one 2592x1944 sensor "
        "(f = 5107 px, baseline 197.9 mm, converging at 1250 mm), a flash projector casting a "
        f"De Bruijn colour grating onto a camouflaged 1:35 tank model ({target.metadata['length_mm']:.0f} x "
        f"{target.metadata['width_mm']:.0f} x {target.metadata['height_mm']:.0f} mm). "
        f"Rendered in {summary['seconds']:.1f} s with exact per-pixel ground truth."
    )
    s.figure("sensor image: the two views side by side", image_png(shot))
    s.figure("ground-truth depth, left view", depth_figure(depth, "true depth (left view)"))
    s.table("Ground truth (left view)", ["quantity", "value"], [
        ["pixels on target", int(mask.sum())],
        ["depth min (mm)", float(np.nanmin(depth))],
        ["depth max (mm)", float(np.nanmax(depth))],
    ])
    s.link("shot_00.png", "simulate/shot_00.png")
    s.link("rig.yaml", "simulate/rig.yaml")
    s.link("truth_00.npz", "simulate/truth_00.npz")
    s.link("target.ply", "simulate/target.ply")
    return s


#: The demo's calibration board (inner corners) and square size.
DEMO_BOARD = (19, 13)
DEMO_SQUARE_MM = 12.0


def demo_rig(ctx: DemoContext) -> Any:
    """The rig the demo simulates: the paper's, or a quarter-size one with ``--fast``."""
    if ctx.fast:
        return paper_rig(sensor_size=(1296, 972), focal_px=5107.0 / 2)
    return paper_rig()


def _stage_calibration(ctx: DemoContext) -> Section:
    """Simulated chessboard shots -> calibration by bundle adjustment; recovered vs true."""

    s = Section(f"Calibration: 5 simulated chessboard shots ({DEMO_BOARD[0]}x{DEMO_BOARD[1]} corners, "
                f"{DEMO_SQUARE_MM:g} mm squares), bundle adjustment")
    true = demo_rig(ctx)
    out = ctx.path("calibration")
    # A 19 x 13 board of 12 mm squares: at this focal length the principal point is
    # pinned by the number of corners (std ~0.3 px with 5 poses; ~0.6 px for 9 x 6).
    simulate_to_folder("calib", out, SimulateOptions(seed=ctx.seed, supersample=2, board=DEMO_BOARD,
                                                       square_mm=DEMO_SQUARE_MM), rig=true)
    shots = sorted(out.glob("calib_*.png"))
    options = CalibrationOptions(board=DEMO_BOARD, square_mm=DEMO_SQUARE_MM, tangential=False)
    cal = calibrate_stereo(shots, options=options)
    cal.save(ctx.path("calib.yaml"))
    ctx.results["calibration"] = cal
    ctx.results["true_rig"] = true
    est = cal.rig
    rows = []
    for name, a, b in (("left", true.left, est.left), ("right", true.right, est.right)):
        rows += [
            [f"{name} fx (px)", a.fx, b.fx, 100 * (b.fx - a.fx) / a.fx, "0.1 %"],
            [f"{name} fy (px)", a.fy, b.fy, 100 * (b.fy - a.fy) / a.fy, "0.1 %"],
            [f"{name} cx (px)", a.cx, b.cx, b.cx - a.cx, "1 px"],
            [f"{name} cy (px)", a.cy, b.cy, b.cy - a.cy, "1 px"],
            [f"{name} k1", a.dist[0], b.dist[0], b.dist[0] - a.dist[0], "0.005"],
            [f"{name} k2", a.dist[1], b.dist[1], b.dist[1] - a.dist[1], ""],
        ]
    rows.append(["baseline (mm)", true.baseline_mm, est.baseline_mm,
                 100 * (est.baseline_mm - true.baseline_mm) / true.baseline_mm, "0.1 %"])
    dR = est.R @ true.R.T
    rows.append(["rig rotation error (deg)", 0.0, rotation_angle_deg(dR), rotation_angle_deg(dR), "0.02 deg"])
    s.table("Recovered vs true parameters (error: % for fx, fy, baseline; absolute otherwise)",
            ["parameter", "true", "recovered", "error", "target"], rows)
    s.table("Quality", ["figure", "value"], [
        ["RMS reprojection error (px)", cal.rms_px],
        ["left / right RMS (px)", f"{cal.rms_left_px:.4f} / {cal.rms_right_px:.4f}"],
        ["rectification residual: vertical disparity RMS of corners (px)", cal.rectification_rms_px],
        ["views used", cal.n_views],
    ])

    s.figure("one of the chessboard shots", image_png(read_image(shots[0])))
    s.link("calib.yaml", "calib.yaml")
    return s


def _table1_run(ctx: DemoContext, rig: Any, out: Any, *, pattern: bool) -> Any:
    simulate_to_folder("plate", out, SimulateOptions(pattern=pattern, camouflage=False, seed=ctx.seed,
                                                       supersample=1 if ctx.fast else 2), rig=ctx.results["true_rig"])
    shot = read_image(out / "shot.png")
    res = {}
    for label, sigma in (("unsmoothed", 0.0), ("smoothed", 2.0)):
        rec = reconstruct_shot(shot, rig, ReconstructOptions(smooth_sigma_px=sigma))
        res[label] = (flatness_test(rec.scan.points, focal_px=rec.rect.focal_px,
                                    baseline_mm=rec.rect.baseline_mm), rec)
    return res


def _stage_table1(ctx: DemoContext) -> Section:
    """The paper's accuracy test (Table I) on a simulated flat plate."""
    s = Section("Accuracy test (the paper's Table I): flat 30x30 cm plate at 1250 mm")
    if "calibration" not in ctx.results:
        ctx.results["true_rig"] = demo_rig(ctx)
    true = ctx.results["true_rig"]
    cal = ctx.results.get("calibration")
    runs = {}
    runs["calibrated rig, grating on"] = _table1_run(ctx, cal.rig if cal else true, ctx.path("plate"), pattern=True)
    runs["true rig, grating on"] = _table1_run(ctx, true, ctx.path("plate"), pattern=True)
    runs["calibrated rig, no grating"] = _table1_run(ctx, cal.rig if cal else true, ctx.path("plate_nopattern"),
                                                     pattern=False)
    header = ["region"] + [f"{k}: {m} (mm)" for k in runs for m in ("unsmoothed", "smoothed")]
    rows = []
    paper = {"unsmoothed": 0.14, "smoothed": 0.10}
    for region in REGIONS:
        rows.append([region] + [runs[k][m][0].regions[region].rms_mm for k in runs for m in ("unsmoothed", "smoothed")])
    rows.append(["mean"] + [runs[k][m][0].mean_rms_mm for k in runs for m in ("unsmoothed", "smoothed")])
    rows.append(["paper (mean)"] + [paper[m] for _ in runs for m in ("unsmoothed", "smoothed")])
    s.table("RMS residual of the plane fit z = ax + by + c in each region (eq. 9-15)", header, rows)
    first = runs["calibrated rig, grating on"]["unsmoothed"]
    rep, rec = first
    s.paragraphs.append(
        f"Depth resolution at {rep.mean_depth_mm:.0f} mm (eq. 16): {rep.resolution_mm_per_px:.3f} mm per pixel "
        f"of disparity; the RMS above corresponds to {rep.mean_rms_mm / rep.resolution_mm_per_px:.3f} px. "
        f"Smoothing (Gaussian sigma 2 px, edge-preserving) costs "
        f"{smoothing_resolution_mm(2.0, rep.mean_depth_mm, rec.rect.focal_px):.2f} mm of lateral resolution (FWHM). "
        f"Matching took {rec.timings_s.get('match', 0):.1f} s for {rec.rect.size[0]}x{rec.rect.size[1]} rectified "
        f"pixels, disparities {rec.min_disp}..{rec.min_disp + rec.num_disp - 1}."
    )
    ctx.results["table1"] = {k: {m: v[m][0].to_dict() for m in v} for k, v in runs.items()}
    s.figure("plate depth (calibrated rig, grating on, unsmoothed)", depth_figure(rec.depth_mm, "plate depth"))
    return s


def cloud_figure(points: Any, colors: Any, title: str, *, max_points: int = 30000) -> bytes:
    """Three orthographic views of a coloured point cloud (matplotlib), PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    p = np.asarray(points, dtype=np.float64)
    c = None if colors is None else np.asarray(colors, dtype=np.float64) / 255.0
    if len(p) > max_points:
        idx = np.random.default_rng(0).choice(len(p), max_points, replace=False)
        p = p[idx]
        c = None if c is None else c[idx]
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    for ax, (i, j, name) in zip(axes, ((0, 1, "x-y"), (0, 2, "x-z"), (1, 2, "y-z")), strict=True):
        ax.scatter(p[:, i], p[:, j], s=0.3, c=c if c is not None else "k", linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(f"{title}: {name} (mm)")
    return figure_png(fig)


def _scan_views(ctx: DemoContext, out: Path, rig: Any, n: int) -> list[tuple[Any, Any, Any]]:
    """Reconstruct the ``n`` simulated turntable shots in ``out`` at the stitcher's
    confidence (what `prism3d stitch` keeps from scan files) and save them."""
    import numpy as np

    scans = []
    for k in range(n):
        rec = reconstruct_shot(read_image(out / f"shot_{k:02d}.png"), rig,
                               ReconstructOptions(min_confidence=STITCH_MIN_CONFIDENCE))
        sc = rec.scan
        scans.append((sc.points.astype(np.float64), sc.colors, sc.normals))
        write_ply(ctx.path("scans", f"scan_{k:02d}.ply"), sc.points, colors=sc.colors, normals=sc.normals,
                  comments=["prism3d scan", "units mm", "frame left camera (OpenCV axes)"])
        if k == 0:
            ctx.results["view0"] = rec
    return scans


def _size_rows(res: Any, T_w0: Any, target: Any) -> list[list[Any]]:
    """Gravity-aligned size of the stitched model (turntable frame, z up) against the
    true mesh: the box of the fitted surface and the box of every point."""
    P_w, N_w = res.points @ T_w0[:3, :3].T + T_w0[:3, 3], res.normals @ T_w0[:3, :3].T
    f_scan = scan_features(P_w, N_w, up="z", box="surface")
    f_pts = scan_features(P_w, N_w, up="z", box="points")
    f_true = model_features(target.vertices, target.faces, up="z")
    return [[k[:-3], f_true[k], f_scan[k], 100 * (f_scan[k] / f_true[k] - 1), f_pts[k],
             100 * (f_pts[k] / f_true[k] - 1)] for k in ("length_mm", "width_mm", "height_mm")]


def _stage_model360(ctx: DemoContext) -> Section:
    """8 turntable shots of a camouflaged target -> 8 scans -> stitched 360-degree model."""
    import json

    import numpy as np

    s = Section("360-degree model: 8 shots on a turntable, reconstructed and stitched")
    true = ctx.results.get("true_rig") or demo_rig(ctx)
    cal = ctx.results.get("calibration")
    out = ctx.path("scene")
    target = builtin_target("tank_t1", seed=ctx.seed)
    simulate_to_folder("scene", out, SimulateOptions(views=8, seed=ctx.seed, supersample=1), rig=true,
                       target=target)
    # the scanned-targets stage shoots tank_t1 with these very settings: it reuses the shots
    ctx.results["turntable_shots"] = ("tank_t1", true, out)
    poses = json.loads((out / "poses.json").read_text())
    T_world_cam = [np.asarray(v["T_world_cam"], dtype=np.float64) for v in poses["views"]]
    scans = _scan_views(ctx, out, cal.rig if cal is not None else true, 8)
    res = stitch_scans(scans, StitchOptions(turntable_step_deg=45.0, on_failure="warn"))
    for w in res.diagnostics.get("warnings", []):
        s.paragraphs.append(f"<b>Warning:</b> {w}")
    write_ply(ctx.path("model.ply"), res.points, colors=res.colors, normals=res.normals,
              comments=["prism3d model", "units mm", "frame: left camera of view 0"])
    if res.mesh_vertices is not None:
        write_ply(ctx.path("model_mesh.ply"), res.mesh_vertices, faces=res.mesh_faces, colors=res.mesh_colors,
                  comments=["prism3d model mesh", "units mm", "frame: left camera of view 0"])
    rows = []
    T0 = np.linalg.inv(T_world_cam[0])
    for k in range(8):
        dT = np.linalg.inv(T0 @ T_world_cam[k]) @ res.T_model_scan[k]
        rows.append([k, len(scans[k][0]), rotation_angle_deg(dT), float(np.linalg.norm(dT[:3, 3]))])
    s.table("Recovered view poses vs truth (the rig as calibrated above)",
            ["view", "points", "rotation error (deg)", "translation error (mm)"], rows)
    s.table("Gravity-aligned size of the stitched model vs the true mesh (box of the fitted surface near the "
            "points, as `prism3d features` gives by default; the box of every point beside it)",
            ["dimension", "true (mm)", "from the scans (mm)", "error (%)", "every point (mm)", "error (%)"],
            _size_rows(res, T_world_cam[0], target))
    s.paragraphs.append(
        f"Target: camouflaged 1:35 tank model ({target.metadata['length_mm']:.0f} mm long). Fused model: "
        f"{len(res.points)} points" + (f", mesh {len(res.mesh_faces)} triangles" if res.mesh_faces is not None else "")
        + ". Stitching: turntable prior (45 deg), multi-scale point-to-plane ICP, pose graph with loop closure, joint "
        "multi-view refinement"
        + (", then all views constrained to one turntable axis (axis and angles fitted)"
           if "turntable" in res.diagnostics.get("multiview", {}) else "")
        + "; the fused cloud keeps the points two scans agree on."
    )
    ctx.results["model"] = res
    s.raw_html.append(point_cloud_viewer(res.points, res.colors))
    s.figure("stitched model", cloud_figure(res.points, res.colors, "model"))
    s.link("model.ply", "model.ply")
    if res.mesh_vertices is not None:
        s.link("model_mesh.ply", "model_mesh.ply")
    s.link("poses (truth)", "scene/poses.json")
    return s


def _stage_decamo(ctx: DemoContext) -> Section:
    """Camouflage removal on one reconstructed view."""
    import numpy as np

    s = Section("Camouflage removal on one view (depth from the reconstruction)")
    rec = ctx.results.get("view0")
    if rec is None:
        raise RuntimeError("the 360-degree model stage must run first")
    # the grating colours the light, so the texture comes from a second, white-flash
    # exposure of the same view; the depth is the grating shot's reconstruction
    true = ctx.results.get("true_rig") or demo_rig(ctx)
    cal = ctx.results.get("calibration")
    out = ctx.path("decamo")
    simulate_to_folder("scene", out, SimulateOptions(views=1, pattern=False, seed=ctx.seed, supersample=1),
                       rig=true, target=builtin_target("tank_t1", seed=ctx.seed))
    left, _, _ = rectify_shot(read_image(out / "shot_00.png"), cal.rig if cal is not None else true)

    # normals need a smooth surface: per-pixel depth noise (~0.2 mm at 0.25 mm pixel
    # spacing) would make them useless
    depth = smooth_depth(rec.depth_mm, sigma_px=4.0, focal_px=rec.rect.focal_px, baseline_mm=rec.rect.baseline_mm)
    res = decamouflage(left, depth, rec.rect.camera)
    m = np.isfinite(rec.depth_mm)
    rows, cols = np.nonzero(m)
    r0, r1 = max(rows.min() - 20, 0), min(rows.max() + 20, m.shape[0])
    c0, c1 = max(cols.min() - 20, 0), min(cols.max() + 20, m.shape[1])
    crop = np.s_[r0:r1, c0:c1]

    def to8(a: Any) -> Any:
        a = np.nan_to_num(np.asarray(a, dtype=np.float64))
        hi = np.percentile(a[m[crop]] if a.ndim == 2 else a[m[crop]].ravel(), 99.5) or 1.0
        return np.clip(a / hi * 255.0, 0, 255).astype(np.uint8)

    s.figure("camouflaged view (white flash, rectified left)", image_png(left[crop], max_side=420))
    s.figure("albedo (the paint)", image_png(to8(res.albedo[crop]), max_side=420))
    s.figure("shading", image_png(to8(res.shading[crop]), max_side=420))
    s.figure("shape image: true 3D profile, false shadows gone", image_png(to8(res.shape[crop]), max_side=420))
    s.figure("false-shadow mask", image_png((res.false_shadow[crop] * 255).astype(np.uint8), max_side=420))
    s.paragraphs.append(
        "Lighting: 2nd-order spherical harmonics fitted robustly to the image over the normals of the "
        "reconstructed depth; paint: a few flat colours (k-means) alternated with the lighting fit."
    )
    return s


def _stage_features(ctx: DemoContext) -> Section:
    """Size/profile/surface features of the built-in targets -> Parquet."""
    import pandas as pd

    s = Section("ATR features of the built-in targets")
    rows = []
    for name in list_builtin_targets():
        t = builtin_target(name, camouflage=False)
        f = model_features(t.vertices, t.faces, up="z")
        rows.append({"target": name, "class": t.metadata["class"], **f})
    df = pd.DataFrame(rows)
    with atomic_path(ctx.path("features.parquet")) as tmp:
        df.to_parquet(tmp, index=False)
    show = [c for c in ("length_mm", "width_mm", "height_mm", "volume_mm3", "area_mm2") if c in df.columns]
    s.table("Gravity-aligned size (mm) and more (all columns in features.parquet)",
            ["target", "class"] + show, df[["target", "class"] + show].values.tolist())
    s.link("features.parquet", "features.parquet")
    return s


def _stage_database(ctx: DemoContext) -> Section:
    """A small target database of the built-in targets, one render job and its features."""
    s = Section("Target database: built-in targets, a render job and a features job")
    path = ctx.path("targets_db")
    if not (path / "db.yaml").exists():
        dbm.init_db(path)
    add_builtin(path)
    job = run_render_job(path, "demo", azimuth="0:360:30" if ctx.fast else "0:360:15", elevation="15:45:15",
                         chip_spec=ChipSpec(size=64))
    feats = run_features_job(path, "demo")
    db = dbm.open_db(path)
    t = db.targets()
    cols = [c for c in ("target_id", "class", "name", "length_mm", "width_mm", "height_mm") if c in t.columns]
    s.table("targets (targets.parquet)", cols, t[cols].values.tolist())
    man = db.renders("demo")
    s.paragraphs.append(
        f"Render job 'demo': {len(man)} chips ({job.summary()}); features job: {feats.summary()}. "
        "The folder is plain Parquet + NPZ + YAML (datasets/FORMAT.md): pandas, pyarrow and DuckDB read it "
        "without prism3d. Problems found by verify: "
        f"{len(dbm.verify_db(path))}."
    )
    s.link("targets_db/", "targets_db/db.yaml")
    return s


def _stage_bank(ctx: DemoContext) -> Section:
    """Correlation filter banks trained on renders, evaluated on unseen poses."""
    from dataclasses import replace

    s = Section("Recognition: OT-MACH correlation filter banks on rendered chips")
    names = ["tank_t1", "jet_j1", "ship_s1", "truck_k1"]
    train = resolve_targets(names, seed=ctx.seed)
    test = resolve_targets(names, seed=heldout_seed(ctx.seed))  # a different camouflage pattern
    step = "0:360:30" if ctx.fast else "0:360:15"
    rows = []
    results = {}
    for channel in ("depth", "shape", "intensity"):
        bank = train_bank(train, channel=channel, azimuth=step, elevation="15:35:20", bin_deg=30 if ctx.fast else 15,
                          chip_spec=ChipSpec(size=64))
        bank.save(ctx.path("banks", f"bank_{channel}.npz"))
        res = evaluate_bank(bank, test, chip_spec=replace(EVAL_CHIP_SPEC, noise_sigma=0.03, clutter="noise"),
                            out_json=ctx.path("banks", f"results_{channel}.json"))
        results[channel] = res
        rows.append([channel, 100 * res.pcc, res.roc.get("auc", float("nan"))])
    s.table("Probability of correct classification on unseen azimuths (new camouflage, noise, clutter)",
            ["chip channel", "Pcc (%)", "ROC AUC (targets vs clutter)"], rows)
    best = results["depth"]
    s.figure("confusion (depth chips)", figure_png(plot_confusion(best)))
    s.figure("accuracy per aspect (depth chips)", figure_png(plot_per_aspect(best)))
    s.figure("ROC (depth chips)", figure_png(plot_roc(best)))
    s.paragraphs.append(
        "Training: chips rendered from the 3D models at every azimuth step; test: azimuths half-way between, "
        "a different camouflage pattern, sensor noise and clutter. Intensity chips learn the paint, so a new "
        "camouflage hurts them; depth and shape-image (decamouflaged) chips do not."
    )
    for ch in ("depth", "shape", "intensity"):
        s.link(f"results_{ch}.json", f"banks/results_{ch}.json")
    return s


#: The targets the demo scans; ``--fast`` scans the first and the last (two classes; the
#: tank's shots are the 360-degree stage's), which halves the demo's longest stage.
SCANNED_TARGETS = ("tank_t1", "jet_j1", "ship_s1", "truck_k1")


def _stage_scanned_bank(ctx: DemoContext) -> Section:
    """Built-in targets scanned on the turntable -> a database of scans -> a bank trained
    on the scans, evaluated on renders of the true meshes beside a bank trained on them."""
    import numpy as np

    names = [SCANNED_TARGETS[0], SCANNED_TARGETS[-1]] if ctx.fast else list(SCANNED_TARGETS)
    s = Section(f"Scanned targets train the bank: {len(names)} targets scanned on the turntable, banks from scans "
                "vs true meshes")
    true_rig = ctx.results.get("true_rig") or demo_rig(ctx)
    cal = ctx.results.get("calibration")
    path = ctx.path("scanned", "targets_db")
    shutil.rmtree(path, ignore_errors=True)  # a rerun into the same folder must not add the scans twice
    dbm.init_db(path)
    notes = {}
    for n in names:
        _reuse_turntable_shots(ctx, n, true_rig, ctx.path("scanned", n, "shots"))
        st = scan_builtin_target(n, ctx.path("scanned", n), seed=ctx.seed, rig=true_rig,
                                 calib_rig=cal.rig if cal is not None else None)
        notes[n] = st.notes
        add_meshes(path, [st.mesh], target_class=str(builtin_target(n).metadata["class"]))
    db = dbm.open_db(path)
    t = db.targets()
    t = t[t["source_kind"] == "scan"]
    cols = ["target_id", "class", "length_mm", "width_mm", "height_mm", "coverage"]
    s.table("The scans in a target database (source_kind scan; provenance: poses, scans, shots and calibration "
            "by sha256)", cols, t[cols].values.tolist())
    scanned = [(str(r["class"]), load_mesh_file(path / r["model_file"], name=str(r["target_id"])))
               for _, r in t.iterrows()]
    true = [(str(builtin_target(n).metadata["class"]), builtin_target(n, seed=ctx.seed)) for n in names]
    test = [(c, builtin_target(n, seed=heldout_seed(ctx.seed))) for (c, _), n in zip(true, names, strict=True)]
    step = "0:360:30" if ctx.fast else "0:360:15"
    res = compare_scan_banks(scanned, true, test, azimuth=step, bin_deg=30 if ctx.fast else 15, seed=ctx.seed)
    s.table("Pcc on renders of the TRUE meshes at unseen azimuths (new camouflage, noise 0.03, clutter)",
            ["chip channel", "bank from scans (%)", "bank from true meshes (%)", "difference (points)"],
            [[ch, 100 * r.scan.pcc, 100 * r.mesh.pcc, r.difference_points] for ch, r in res.items()])
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.5))
    plot_confusion(res["depth"].scan, ax=axes[0], title="depth, scans")
    plot_confusion(res["depth"].mesh, ax=axes[1], title="depth, true meshes")
    s.figure("confusion matrices, depth chips: bank from scans (left), from the true meshes (right)",
             figure_png(fig))
    for n in names:
        if notes[n]:
            s.paragraphs.append(f"<b>{n}:</b> " + "; ".join(notes[n]))
    s.paragraphs.append(
        "Each target: 8 shots through the simulated prism rig on a turntable, each reconstructed, stitched with the "
        "turntable step into a mesh in its object frame (z up from the turntable axis, x along the longest "
        "horizontal extent and towards the shot that faced the front, origin on the support) kept within 2 point spacings of the data and coloured by the shots, then added to "
        "the database without flags. Banks are trained on the database's scans and on the true meshes (the paint "
        f"the scanner saw), both tested on the true meshes in a new paint. The scanned meshes have "
        f"{np.mean([len(m.vertices) for _, m in scanned]):.0f} vertices on average."
    )
    s.link("targets_db/", "scanned/targets_db/db.yaml")
    return s


def _reuse_turntable_shots(ctx: DemoContext, name: str, rig: Any, dest: Path) -> None:
    """Link the 360-degree stage's shots into ``dest`` when they are the ones the scan of
    ``name`` would simulate (same target, rig object and seed; 8 views, no supersampling):
    the simulation is deterministic, so the files are the same bytes (15 s saved)."""
    done = ctx.results.get("turntable_shots")
    if done is None or done[0] != name or done[1] is not rig or dest.exists():
        return

    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:  # another file system: a copy
            shutil.copy2(src, dst)

    shutil.copytree(done[2], dest, copy_function=link)


Stage = Callable[[DemoContext], Section]

#: The demo's stages, in order. Capabilities append theirs here.

#: Detections drawn on the demo's field scene: the best few (the scene's own score list
#: goes on far below; `bank eval-scenes` sweeps the threshold over many scenes).
DEMO_SCENE_DRAWN = 8


def _stage_scene(ctx: DemoContext) -> Section:
    """A whole field scene: camouflaged full-size targets among confusers and clutter,
    reconstructed, and the shape bank's detections drawn against the truth."""
    import json

    s = Section("Whole-scene ATR: camouflaged targets found in a field shot (shape channel)")
    folder = ctx.path("field")
    if not (folder / "truth.json").is_file():
        simulate_field(folder, FieldOptions(seed=ctx.seed + 100))
    bank_path = ctx.path("banks", "bank_shape.npz")
    if bank_path.is_file():
        bank = FilterBank.load(bank_path)
    else:  # the bank stage did not run: the same bank, trained here
        names = ["tank_t1", "jet_j1", "ship_s1", "truck_k1"]
        bank = train_bank(resolve_targets(names, seed=ctx.seed), channel="shape", azimuth="0:360:30",
                          elevation="15:35:20", bin_deg=30, chip_spec=ChipSpec(size=64))
    rig = StereoRig.load(folder / "rig.yaml")
    shot = read_image(folder / "shot.png")
    truth = json.loads((folder / "truth.json").read_text())
    dets, times = detect_shot(bank, shot, rig)
    doc = {"channel": bank.channel, "timings_s": times, "detections": [d.to_json() for d in dets]}
    atomic_write_text(ctx.path("field", "detections.json"), json.dumps(doc, indent=1))
    res = score_scenes([(doc, truth)])
    left = rig.split.split(shot)[0]
    s.figure("left view: true targets (green), confusers (orange), the best detections (red, rank, class, score)",
             figure_png(plot_scene(left, truth, dets, top=DEMO_SCENE_DRAWN,
                                   title=f"{len(dets)} detections; the best {DEMO_SCENE_DRAWN} drawn")))
    rows = []
    for t in truth["targets"]:
        hit = next((k for k, d in enumerate(dets) if _on_target(d, t)), None)
        rows.append([t["class"] + (" (confuser)" if t["confuser"] else ""), t["range_mm"] / 1000.0,
                     t["visible_fraction"], "-" if hit is None else hit + 1,
                     "-" if hit is None else dets[hit].class_name])
    s.table("Truth and the first detection on each target (rank in the score list, class called)",
            ["target", "range (m)", "visible fraction", "rank", "called"], rows)
    s.table("Time per stage (s)", ["reconstruction", "ground and objects", "detection"],
            [[times["reconstruct_s"], times["channels_s"], times["detect_s"]]])
    s.paragraphs.append(
        f"Highest Pd on this scene {res.pd_max:.2f} ({res.n_targets} counted targets). One scene says "
        "little: benchmarks/RESULTS.md 'Whole-scene ATR on field scenes' gives Pd against false positives per "
        "image over 20 scenes, and 'prism3d bank eval-scenes' measures it on yours.")
    s.link("detections.json", "field/detections.json")
    return s


def _on_target(d: SceneDetection, t: dict) -> bool:
    """Whether a detection falls in a true target's box (the scoring's image rule)."""
    r0, c0, r1, c1 = t["box_rc"]
    return r0 <= d.row <= r1 and c0 <= d.col <= c1

def _stage_survey(ctx: DemoContext) -> Section:
    """The UAV mode: a simulated drone flight over a car park surveyed into a DSM, a true
    orthophoto and an nDSM, scored against its truth, and the vehicles found and named."""
    import glob
    import json

    s = Section("UAV mode: a drone survey of a car park from one moving camera (simulated flight)")
    flight = ctx.path("flight")
    if not (flight / "truth.json").is_file():
        simulate_flight(flight, FlightOptions(scene="carpark", size=(800, 600) if ctx.fast else (1152, 864),
                                              altitude_m=35.0, frames=6, seed=ctx.seed + 5))
    out = ctx.path("survey")
    if not (out / "poses.json").is_file():
        run_survey(sorted(glob.glob(str(flight / "IMG_*.JPG"))), out, calib=flight / "camera.yaml",
                   gps_table=flight / "geoinfo.txt")
    det = ctx.path("survey", "vehicles.geojson")
    model, info = aerial_recogniser(resolve_targets(list(DEFAULT_CLASSES), scale="full"))
    found = detect_in_survey(out, det, model, draw=ctx.path("survey", "vehicles.png"))
    r = evaluate_survey(out, flight, detections=det, radius_m=1.6, threshold=0.5)
    doc = json.loads((out / "poses.json").read_text())
    s.paragraphs.append(
        f"{len(doc['frames'])} frames on two flight lines (from 35 m, GSD {r['gsd_m'] * 100:.1f} cm) over a car park: "
        "rows of parked cars of every body colour, vans, pickups, kei trucks, buses and box trucks, trees over the "
        "edge rows, people and light poles, with noisy GPS. 'prism3d survey' found the poses (pycolmap), adjusted "
        "them with the GPS positions as constraints, matched neighbouring frames (our matcher), fused the heights and made a true orthophoto at the "
        "photographs' ground sample distance; 'prism3d survey-detect' found and named the vehicles from the "
        "orthophoto's appearance and the nDSM's height with a recogniser trained on our procedural vehicles "
        f"rendered from above ({'cached' if info['cached'] else 'trained now'}). Figures at size: docs/atr.md.")
    s.figure("the orthophoto with the vehicles found (red: class and score)",
             _png_thumbnail(ctx.path("survey", "vehicles.png")))
    s.figure("orthophoto, DSM and normalised DSM (cameras in cyan)", (out / "survey.png").read_bytes())
    d, det_s = r["dsm"], r["detection"]
    at = det_s["at_threshold"]
    s.table("Against the flight's exact truth (after a similarity alignment of the camera centres)",
            ["quantity", "value", "the issue asks"],
            [["camera positions, max (GSD)", r["position_error_gsd"]["max"], "<= 0.5"],
             ["DSM on open ground, median |error| (GSD)", d["median_abs_error_gsd"], "<= 0.5"],
             ["overlapped area filled", d["overlap_filled_fraction"], ">= 0.95"],
             ["vehicles found at score 0.5 (within 1.6 m)", f"{at['pd']:.2f} of {det_s['n_targets']}", ">= 0.95"],
             ["false positives at score 0.5", at["false_positives"], "<= 0.1 a frame"],
             ["class right among those found", at["class_accuracy"], ">= 0.9"]])
    s.table("vehicles by class, as written", ["class", "vehicles"], sorted(found["by_class"].items()))
    s.table("Time per stage (s)", list(doc["seconds"]), [list(doc["seconds"].values())])
    for name in ("dsm.tif", "ortho.tif", "ndsm.tif", "cloud.las", "poses.json", "vehicles.geojson"):
        s.link(name, f"survey/{name}")
    return s


def _png_thumbnail(path: Path, width: int = 1400) -> bytes:
    """A PNG at most ``width`` px wide (the report stays small)."""
    import cv2

    img = cv2.imread(str(path))
    if img.shape[1] > width:
        img = cv2.resize(img, (width, int(img.shape[0] * width / img.shape[1])), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


STAGES: list[tuple[str, Stage]] = [
    ("environment", _stage_environment),
    ("simulate", _stage_simulate),
    ("calibration", _stage_calibration),
    ("table1", _stage_table1),
    ("model360", _stage_model360),
    ("decamo", _stage_decamo),
    ("features", _stage_features),
    ("database", _stage_database),
    ("bank", _stage_bank),
    ("scanned_bank", _stage_scanned_bank),
    ("scene", _stage_scene),
    ("survey", _stage_survey),
]


def run_demo(
    out_dir: str | Path,
    *,
    seed: int = 0,
    fast: bool = False,
    progress: ProgressFn = null_progress,
    only: list[str] | None = None,
) -> tuple[Path, list[str]]:
    """Run the demo stages into ``out_dir`` and write ``out_dir/report.html``.

    Returns
    -------
    report_path : Path
    failed : list of str
        Names of stages that raised (their traceback is in the report).
    """
    names = [n for n, _ in STAGES]
    unknown = [n for n in (only or []) if n not in names]
    if unknown:
        raise InputError(f"--only: unknown stage(s) {', '.join(unknown)}; the stages are {', '.join(names)}")
    out = Path(out_dir)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _run_stages(out, [(n, f) for n, f in STAGES if only is None or n in only], seed, fast,
                           progress)
    except BaseException:
        # the report grows stage by stage (an interrupted demo keeps what it did), but a
        # run that could write nothing leaves no empty folder behind
        if created and not any(out.iterdir()):
            out.rmdir()
        raise


def _run_stages(out: Path, stages: list, seed: int, fast: bool, progress: ProgressFn
                ) -> tuple[Path, list[str]]:
    """Run ``stages`` into ``out``, writing ``report.html`` after each one."""
    ctx = DemoContext(out, seed=seed, fast=fast)
    report = Report("prism3d demo: one flash photograph to a metric 3D model, and ATR on top")
    failed: list[str] = []
    for i, (name, fn) in enumerate(stages):
        progress(i, len(stages), name)
        t0 = time.perf_counter()
        try:
            section = fn(ctx)
        except Exception as exc:  # a stage failure must show in the report
            log.exception("demo stage %s failed", name)
            failed.append(name)
            section = Section(f"{name}: FAILED")
            section.raw_html.append(
                "<pre>" + traceback.format_exception_only(type(exc), exc)[-1].strip() + "</pre>"
            )
        section.seconds = time.perf_counter() - t0
        report.add(section)
        # write after every stage so an interrupted demo still leaves a report
        report.write(out / "report.html")
    progress(len(stages), len(stages), "done")
    _screenshot(out)
    return out / "report.html", failed


def _screenshot(out: Path) -> None:
    """Save ``report_screenshot.png`` when a headless Chromium is available."""
    if find_chromium() is None:
        log.info("no Chromium: skipping the report screenshot")
        return
    try:
        check = check_page(out / "report.html", screenshot=out / "report_screenshot.png", height=3000)
    except Exception as exc:  # a screenshot is a nicety; never fail the demo for it
        log.warning("report screenshot failed: %s", exc)
        return
    for line in check.console_errors:
        log.warning("report console error: %s", line)
