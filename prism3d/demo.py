"""``prism3d demo OUT_DIR``: the whole pipeline on built-in data, and its report.

The demo is a list of stages; each runs one capability on built-in data, writes its
artefacts under ``OUT_DIR`` and returns a :class:`~prism3d.report.Section`. A stage
that fails is reported in the page (with its error) and the demo exits non-zero, so a
broken install is visible rather than hidden.
"""

from __future__ import annotations

import logging
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from prism3d.progress import ProgressFn, null_progress
from prism3d.report import Report, Section

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
    import os

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

    from prism3d.report import figure_png

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

    from prism3d.capture.simulate import simulate_to_folder
    from prism3d.datasets.targets import builtin_target
    from prism3d.report import image_png

    s = Section("Virtual prism rig: a simulated flash shot and its ground truth")
    out = ctx.path("simulate")
    target = builtin_target("tank_t1", seed=ctx.seed)
    summary = simulate_to_folder("scene", out, target=target, views=1, seed=ctx.seed,
                                 supersample=1 if ctx.fast else 2)
    from prism3d.io.images import read_image

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


def demo_rig(ctx: DemoContext) -> Any:
    """The rig the demo simulates: the paper's, or a quarter-size one with ``--fast``."""
    from prism3d.capture.rig import paper_rig

    if ctx.fast:
        return paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4)
    return paper_rig()


def _stage_calibration(ctx: DemoContext) -> Section:
    """Simulated chessboard shots -> calibration by bundle adjustment; recovered vs true."""

    from prism3d.capture.rig import rotation_angle_deg
    from prism3d.capture.simulate import simulate_to_folder
    from prism3d.reconstruct.calibrate import calibrate_stereo

    s = Section("Calibration: 5 simulated chessboard shots, bundle adjustment")
    true = demo_rig(ctx)
    out = ctx.path("calibration")
    simulate_to_folder("calib", out, rig=true, seed=ctx.seed, supersample=1 if ctx.fast else 2)
    shots = sorted(out.glob("calib_*.png"))
    cal = calibrate_stereo(shots, board=(9, 6), square_mm=25.0, tangential=False)
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
    from prism3d.io.images import read_image
    from prism3d.report import image_png

    s.figure("one of the chessboard shots", image_png(read_image(shots[0])))
    s.link("calib.yaml", "calib.yaml")
    return s


def _table1_run(ctx: DemoContext, rig: Any, out: Any, *, pattern: bool) -> Any:
    from prism3d.capture.simulate import simulate_to_folder
    from prism3d.io.images import read_image
    from prism3d.reconstruct.flatness import flatness_test
    from prism3d.reconstruct.pipeline import reconstruct_shot

    simulate_to_folder("plate", out, rig=ctx.results["true_rig"], pattern=pattern, camouflage=False,
                       seed=ctx.seed, supersample=1 if ctx.fast else 2)
    shot = read_image(out / "shot.png")
    res = {}
    for label, sigma in (("unsmoothed", 0.0), ("smoothed", 2.0)):
        rec = reconstruct_shot(shot, rig, smooth_sigma_px=sigma)
        res[label] = (flatness_test(rec.scan.points, focal_px=rec.rect.focal_px,
                                    baseline_mm=rec.rect.baseline_mm), rec)
    return res


def _stage_table1(ctx: DemoContext) -> Section:
    """The paper's accuracy test (Table I) on a simulated flat plate."""
    from prism3d.reconstruct.flatness import REGIONS
    from prism3d.reconstruct.meshing import smoothing_resolution_mm

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


Stage = Callable[[DemoContext], Section]

#: The demo's stages, in order. Capabilities append theirs here.
STAGES: list[tuple[str, Stage]] = [
    ("environment", _stage_environment),
    ("simulate", _stage_simulate),
    ("calibration", _stage_calibration),
    ("table1", _stage_table1),
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
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ctx = DemoContext(out, seed=seed, fast=fast)
    report = Report("prism3d demo: one flash photograph to a metric 3D model, and ATR on top")
    stages = [(n, f) for n, f in STAGES if only is None or n in only]
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
    return out / "report.html", failed
