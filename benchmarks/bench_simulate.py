"""Time a full-resolution simulated plate shot and print a Markdown section.

The shot: :func:`~prism3d.capture.rig.paper_rig` (2592x1944 sensor, two 1296x1944
views), a 300 x 300 mm plate with woodland camouflage albedo at 1250 mm, the colour
grating projector on, ``supersample`` x ``supersample`` rays per pixel (default 2),
sensor noise on. The output (title, machine, breakdown table, total, rays/s) is
meant to be pasted into ``benchmarks/RESULTS.md``.

Run: ``.venv/bin/python benchmarks/bench_simulate.py [--supersample 2] [--repeat 1]``
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from prism3d.capture import _render_kernels
from prism3d.capture import simulate as simulate_mod
from prism3d.capture.camouflage import CamouflageField
from prism3d.capture.render import RaycastRenderer, SensorNoise
from prism3d.capture.rig import paper_rig
from prism3d.capture.scenes import flat_plate, translation
from prism3d.capture.simulate import Projector, ShotOptions, simulate_shot

import prism3d  # noqa: F401  (environment first)

#: (attribute owner, attribute name, row label) of the timed stages, in table order.
STAGES: list[tuple[Any, str, str]] = [
    (RaycastRenderer, "trace_camera", "camera rays: generate, cast, refine (float64)"),
    (RaycastRenderer, "stream_camera", "camera rays: generate, cast, refine (float64)"),
    (RaycastRenderer, "_visible", "shadow rays (any-hit + exact re-cast of blocked)"),
    (RaycastRenderer, "_albedo", "albedo field (camouflage kernel)"),
    (Projector, "_light", "projector light: pattern bilinear, n.l, falloff"),
    (_render_kernels, "shade_colour", "colour = albedo x illumination"),
    (_render_kernels, "box_mean", "supersample box average"),
    (SensorNoise, "apply", "sensor noise (Poisson + read)"),
    (simulate_mod, "quantize", "quantise to uint8"),
]


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument(
        "--occluder", action="store_true",
        help="add a 60 x 60 mm plate at 900 mm: the scene is no longer planar, so every "
        "lit pixel casts a shadow ray (the plate alone needs none)",
    )
    args = ap.parse_args()

    timings: dict[str, float] = {}
    cpu: dict[str, float] = {}
    rays = {"camera": 0, "shadow": 0, "shadow_cast": 0}

    stack: list[list[float]] = []  # per active stage: [child wall, child cpu]

    def timed(label: str, fn: Callable) -> Callable:
        # exclusive times: a stage called inside another (albedo inside the streamed
        # camera pass) is charged to itself only
        def wrapper(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            c = time.process_time()
            stack.append([0.0, 0.0])
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - t
                dc = time.process_time() - c
                child = stack.pop()
                timings[label] = timings.get(label, 0.0) + dt - child[0]
                cpu[label] = cpu.get(label, 0.0) + dc - child[1]
                if stack:
                    stack[-1][0] += dt
                    stack[-1][1] += dc

        return wrapper

    originals = [(owner, name, getattr(owner, name)) for owner, name, _ in STAGES]
    for owner, name, label in STAGES:
        setattr(owner, name, timed(label, getattr(owner, name)))
    trace_camera = RaycastRenderer.trace_camera
    stream_camera = RaycastRenderer.stream_camera
    visible = RaycastRenderer._visible

    def counting_trace(self, camera, T):  # type: ignore[no-untyped-def]
        rays["camera"] += camera.width * camera.height
        return trace_camera(self, camera, T)

    def counting_stream(self, camera, T, consume, **kw):  # type: ignore[no-untyped-def]
        rays["camera"] += camera.width * camera.height
        return stream_camera(self, camera, T, consume, **kw)

    def counting_visible(self, p, src, tol, sel=None):  # type: ignore[no-untyped-def]
        rays["shadow"] += len(p) if sel is None else len(sel)
        return visible(self, p, src, tol, sel)

    RaycastRenderer.trace_camera = counting_trace  # type: ignore[method-assign]
    RaycastRenderer._visible = counting_visible  # type: ignore[method-assign]
    RaycastRenderer.stream_camera = counting_stream  # type: ignore[method-assign]
    pack_segments = _render_kernels.pack_segments

    def counting_pack(P, sel, *a):  # type: ignore[no-untyped-def]
        rays["shadow_cast"] += len(sel)
        return pack_segments(P, sel, *a)

    _render_kernels.pack_segments = counting_pack

    rig = paper_rig()
    projector = Projector.for_rig(rig, pattern=True)
    camo = CamouflageField.from_palette("woodland", patch_size_mm=60.0)
    objs = [(flat_plate(300, 300, albedo=camo), translation(0, 0, 1250))]
    if args.occluder:
        objs.append((flat_plate(60, 60, albedo=(0.8, 0.8, 0.8), name="occluder"), translation(30, -20, 900)))
    # warm-up (numba compile / cache load) on a tiny rig
    small = paper_rig(sensor_size=(324, 244), focal_px=5107 / 8)
    simulate_shot(small, objs, ShotOptions(supersample=args.supersample), projector=Projector.for_rig(small))
    runs = []
    for k in range(args.repeat + 1):
        # a fresh renderer per cold shot (scene build, ~0.1 s, excluded); the last
        # shot reuses the renderer of the one before, as a shot sequence does
        if k < args.repeat:
            renderer = RaycastRenderer(objs)
        timings.clear()
        cpu.clear()
        rays.update(camera=0, shadow=0, shadow_cast=0)
        t0 = time.perf_counter()
        c0 = time.process_time()
        shot = simulate_shot(rig, objs, ShotOptions(supersample=args.supersample, noise=True, seed=0), projector=projector,
                             renderer=renderer)
        runs.append(
            (time.perf_counter() - t0, dict(timings), dict(rays), time.process_time() - c0, dict(cpu))
        )
    for owner, name, fn in originals:
        setattr(owner, name, fn)
    _render_kernels.pack_segments = pack_segments
    warm = runs.pop()
    total, best, nrays, total_cpu, best_cpu = min(runs, key=lambda r: r[0])

    h, w = shot.sensor_image.shape[:2]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        f"## Simulated shot: {w}x{h} sensor, pattern on, {args.supersample}x{args.supersample} supersampling",
        "",
        (
            f"Machine: {_cpu_name()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"numpy {np.__version__}; 1-min load average at the end {load:.1f}. "
            f"Best of {args.repeat} cold shot(s) (fresh renderer: camera rays computed)."
        ),
        "",
        "Scene: `paper_rig()`, 300 x 300 mm plate at 1250 mm, woodland camouflage albedo, "
        + ("plus a 60 x 60 mm occluder at 900 mm (shadow rays for every lit pixel), " if args.occluder
           else "alone (planar: no shadow rays needed), ")
        + "colour grating projector, sensor noise; both views + truth maps at pixel centres + "
        "rectified-disparity truth view. Wall seconds depend on the load of the machine; CPU "
        "seconds (summed over threads) much less.",
        "",
        "| stage | wall s | CPU s (all threads) |",
        "|---|---:|---:|",
    ]
    acc_wall = acc_cpu = 0.0
    for label in dict.fromkeys(label for _, _, label in STAGES):  # unique, in order
        v = best.get(label, 0.0)
        c = best_cpu.get(label, 0.0)
        acc_wall += v
        acc_cpu += c
        lines.append(f"| {label} | {v:.2f} | {c:.2f} |")
    lines.append(
        "| other (truth maps, split/join, rectified disparity) | "
        f"{total - acc_wall:.2f} | {total_cpu - acc_cpu:.2f} |"
    )
    lines.append(f"| **total** | **{total:.2f}** | {total_cpu:.2f} |")
    n_all = nrays["camera"] + nrays["shadow_cast"]
    lines += [
        "",
        (
            f"Rays: {nrays['camera'] / 1e6:.1f} M camera + {nrays['shadow_cast'] / 1e6:.1f} M shadow "
            f"rays cast (for {nrays['shadow'] / 1e6:.1f} M shadow tests) = {n_all / 1e6:.1f} M; "
            f"{n_all / total / 1e6:.1f} M rays/s end to end (whole shot), "
            f"{nrays['camera'] / best.get(STAGES[0][2], np.nan) / 1e6:.1f} M camera rays/s in the "
            "ray stage."
        ),
        "",
        (
            "Next shot with the same renderer (camera rays cached, as in a shot sequence): "
            f"{warm[0]:.2f} s wall, {warm[3]:.2f} s CPU."
        ),
    ]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
