"""1 vs 2 Dask workers on the same render job (issue 10: >= 1.6x expected on 2 cores).

Each worker is pinned to one core (NUMBA_NUM_THREADS=1, PRISM3D_NUM_THREADS=1 for
Open3D, OMP_NUM_THREADS=1), so N workers use N cores. The job: the 12 built-in
targets x 72 azimuths x 8 elevations at 96x96 (6912 chips, 48 units); cluster start-up
is included in the times. Prints a Markdown section.

Run: ``.venv/bin/python benchmarks/bench_workers.py``
"""

from __future__ import annotations

import os
import tempfile
import time

import prism3d  # noqa: F401  (environment first)


def main() -> None:
    from prism3d.datasets.database import db as dbm
    from prism3d.datasets.database.ingest import add_builtin
    from prism3d.atr.chips import ChipSpec
    from prism3d.datasets.jobs.database_jobs import RunOptions, run_render_job

    d = tempfile.mkdtemp(prefix="prism3d-bench-workers-")
    dbm.init_db(d)
    add_builtin(d)
    kw = dict(azimuth="0:360:5", elevation="10:80:10", chip_spec=ChipSpec(size=96), chips_per_unit=144)
    run_render_job(d, "warm", run=RunOptions(workers=1), azimuth="0:360:90", elevation="20",
                   chip_spec=ChipSpec(size=32))  # caches
    rows = []
    times = {}
    for w in (1, 2):
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        rep = run_render_job(d, f"w{w}", run=RunOptions(workers=w), **kw)
        dt = time.perf_counter() - t0
        times[w] = dt
        n = len(dbm.open_db(d).renders(f"w{w}"))
        rows.append(f"| {w} | {n} | {dt:.1f} | {n / dt:.0f} | {load:.2f} | {rep.failed and len(rep.failed) or 0} |")
    print("## Render job: 1 vs 2 Dask workers\n")
    print("| workers | chips | seconds (incl. cluster start) | chips/s | load before | failed units |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    print(f"\nspeed-up 2 vs 1 workers: {times[1] / times[2]:.2f}x")


if __name__ == "__main__":
    main()
