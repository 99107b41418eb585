"""Where the matcher's time goes, per stage and per pair, beside OpenCV SGBM-3WAY on the same
pair in the same run (issue 41's breakdown; docs/performance.md).

Each stage of :func:`prism3d.reconstruct.match_stereo` is a numba kernel or a short Python
step; this script wraps them with wall-clock timers for the measured calls only (the product
code is not changed), warms every pair once (numba compiles, scratch buffers are kept), then
takes the median of ``--repeat`` calls. Stages nest (the equalisation runs a coarse match, the
coarse-to-fine path a full match at 1/scale): a kernel's time is counted in the kernel's row,
and ``_equalize`` / ``_match_c2f`` rows show only what is outside their kernels.

    python benchmarks/profile_matcher.py --data ../shared/data --repeat 3
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import prism3d  # noqa: F401,I001  (first: the thread pools' idle policy, before numpy loads OpenBLAS)
import numpy as np

from prism3d.reconstruct.stereo import _match_kernels as kernels
from prism3d.reconstruct.stereo import match as match_module
from prism3d.reconstruct.stereo.match import match_stereo
from prism3d.reconstruct.stereo.stereo_eval import BENCHMARK_SCENES, load_benchmark_pair

sys.path.insert(0, str(Path(__file__).parent))
from bench_realpairs import sgbm  # noqa: E402  (SGBM-3WAY with the real-pair benchmark's settings)

#: (module, attribute, row name): what is timed. Kernels are looked up through ``match``'s
#: own ``_k`` reference, so wrapping the kernel module's attribute reaches every call.
STAGES = (
    (match_module, "_check_pair", "input checks"),
    (match_module, "_census", "census transform"),
    (match_module, "_features", "AD features"),
    (kernels, "sgm_horizontal", "cost + horizontal paths"),
    (kernels, "aggregate_path", "diagonal paths"),
    (kernels, "sgm_vertical_wta", "vertical paths + WTA"),
    (kernels, "right_lr_check", "LR check"),
    (kernels, "remove_speckles", "speckle filter"),
    (match_module, "_refine_lk", "LK sub-pixel"),
    (match_module, "fit_gain_field", "gain field fit"),
    (match_module, "_downsample", "pyramid"),
    (match_module, "_assemble", "fill + assemble"),
)


class _Timers:
    """Wall seconds per row while ``on``; calls nested inside another timed call are
    subtracted from it, so the rows add up to the whole."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.on = False
        self._stack: list[list[float]] = []

    def wrap(self, fn, name: str):
        @functools.wraps(fn)
        def timed(*a, **k):
            if not self.on:
                return fn(*a, **k)
            self._stack.append([0.0])
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                inner = self._stack.pop()[0]
                self.seconds[name] += dt - inner
                if self._stack:
                    self._stack[-1][0] += dt
        return timed


def install(timers: _Timers) -> None:
    """Wrap every stage; a stage renamed in the matcher fails here rather than going untimed."""
    for mod, attr, name in STAGES:
        setattr(mod, attr, timers.wrap(getattr(mod, attr), name))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scenes", nargs="+", default=list(BENCHMARK_SCENES))
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "profile_matcher.json")
    a = ap.parse_args()
    timers = _Timers()
    install(timers)
    out = {}
    for name in a.scenes:
        try:
            left, right, gt, _ = load_benchmark_pair(a.data, name)
        except (FileNotFoundError, OSError) as exc:
            print(f"{name}: skipped ({exc})")
            continue
        nd = int(np.ceil(float(gt.max()) + 1))
        match_stereo(left, right, min_disp=0, num_disp=nd)  # warm: compile, keep scratch
        sgbm(left, right, nd)
        calls = []
        for _ in range(a.repeat):
            timers.seconds.clear()
            timers.on = True
            t0 = time.perf_counter()
            match_stereo(left, right, min_disp=0, num_disp=nd)
            total = time.perf_counter() - t0
            timers.on = False
            calls.append((total, dict(timers.seconds)))
        ts = []
        for _ in range(a.repeat):
            t0 = time.perf_counter()
            sgbm(left, right, nd)
            ts.append(time.perf_counter() - t0)
        calls.sort(key=lambda c: c[0])
        total, stages = calls[len(calls) // 2]
        stages["other (Python between stages)"] = total - sum(stages.values())
        t_sgbm = float(np.median(ts))
        out[name] = {"size": [int(left.shape[1]), int(left.shape[0])], "num_disp": nd, "ours_s": total,
                     "sgbm_s": t_sgbm, "ratio": total / t_sgbm, "stages_s": stages}
        print(f"{name} {left.shape[1]}x{left.shape[0]} d{nd}: ours {1000 * total:.1f} ms, SGBM {1000 * t_sgbm:.1f} ms, "
              f"{total / t_sgbm:.2f}x")
        for k, v in sorted(stages.items(), key=lambda kv: -kv[1]):
            if v >= 0.0005:
                print(f"    {k:32s} {1000 * v:8.1f} ms  {100 * v / total:5.1f} %")
    if out:
        s_o = sum(v["ours_s"] for v in out.values())
        s_s = sum(v["sgbm_s"] for v in out.values())
        print(f"summed: ours {s_o:.3f} s, SGBM {s_s:.3f} s, {s_o / s_s:.2f}x")
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
