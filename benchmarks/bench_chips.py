"""Chip rendering speed: depth+mask and full (intensity, depth, mask, shape) chips per
second at 128x128, raycast vs pyrender backends, on one built-in target.

Run: ``.venv/bin/python benchmarks/bench_chips.py`` (prints a Markdown section).
"""

from __future__ import annotations

import os
import platform
import time

import prism3d  # noqa: F401  (environment first)


def _rate(fn, n: int) -> float:
    fn(4)  # warm-up (numba compile, GL context)
    t = time.perf_counter()
    fn(n)
    return n / (time.perf_counter() - t)


def main() -> str:
    import numpy as np
    from prism3d.atr.chips import CHANNELS, ChipSpec, chip_poses, render_chips
    from prism3d.datasets.models.targets import builtin_target

    mesh = builtin_target("tank_t1")
    poses = chip_poses(mesh, list(np.arange(0, 360, 2.5)), [20.0], 1000.0, size=128)  # 144 poses
    rows = []
    for backend in ("raycast", "pyrender"):
        for label, ch in (("depth+mask", ("depth", "mask")), ("intensity+depth+mask+shape", None)):
            spec = ChipSpec(size=128, backend=backend, channels=CHANNELS if ch is None else ch)

            def run(n, spec=spec):
                render_chips(mesh, poses[:n], chip_spec=spec)

            rows.append((backend, label, _rate(run, len(poses))))
    lines = [
        "## Chip rendering (benchmarks/bench_chips.py)",
        "",
        (
            f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}; tank_t1 (448 faces), 128x128 chips, 144 poses."
        ),
        "",
        "| backend | channels | chips/s |",
        "|---|---|---|",
    ]
    lines += [f"| {b} | {c} | {r:.0f} |" for b, c, r in rows]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(main())
