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


Stage = Callable[[DemoContext], Section]

#: The demo's stages, in order. Capabilities append theirs here.
STAGES: list[tuple[str, Stage]] = [
    ("environment", _stage_environment),
    ("simulate", _stage_simulate),
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
