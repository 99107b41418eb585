"""Target database and its jobs: ingest, a several-thousand-chip render job, features,
read-back with pandas/DuckDB, 1 vs 2 Dask workers, worker memory over ~10k chips.

Run: ``.venv/bin/python benchmarks/bench_db.py [WORK_DIR]`` (prints a Markdown section;
WORK_DIR defaults to a temporary folder, deleted afterwards). Uses the built-in
targets plus, when present, the Quaternius CC0 vehicles of the shared test data.
"""

from __future__ import annotations

import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import prism3d  # noqa: F401  (environment first)

REPO = Path(__file__).resolve().parents[1]


def _shared_data() -> Path | None:
    env = os.environ.get("PRISM3D_TEST_DATA")
    for c in ([Path(env)] if env else []) + [REPO.parent / "shared" / "data"]:
        if c.is_dir():
            return c
    return None


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _rss_table(db, job: str) -> tuple[str, float]:
    from prism3d.datasets.jobs.database_jobs import unit_stats

    st = unit_stats(db, job)
    lines = []
    worst = 0.0
    for pid, g in st.groupby("pid"):
        first, last, peak = g["rss_mb"].iloc[0], g["rss_mb"].iloc[-1], g["rss_mb"].max()
        n10 = max(1, len(g) // 10)
        early = g["rss_mb"].iloc[:n10].mean()
        late = g["rss_mb"].iloc[-n10:].mean()
        worst = max(worst, late - early)
        lines.append(
            f"| {pid} | {len(g)} | {int(g['chips'].sum())} | {first:.0f} | {peak:.0f} | {last:.0f} | "
            f"{early:.0f} -> {late:.0f} |"
        )
    return "\n".join(lines), worst


def main(work: Path) -> str:
    import duckdb
    import pandas as pd
    from prism3d.datasets.database.db import init_db, verify_db
    from prism3d.datasets.database.ingest import add_builtin, add_quaternius_vehicles
    from prism3d.atr.chips import ChipSpec
    from prism3d.datasets.jobs.database_jobs import RunOptions, run_features_job, run_render_job

    out: list[str] = ["## Target database and jobs (benchmarks/bench_db.py)", ""]
    out.append(
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
        f"load average at start {_load()} (shared machine)."
    )
    out.append("")
    db = init_db(work / "db")
    t = time.perf_counter()
    add_builtin(db)
    t_b = time.perf_counter() - t
    data = _shared_data()
    n_q = 0
    t_q = 0.0
    if data is not None and (data / "meshes" / "quaternius_vehicles_cc0").is_dir():
        t = time.perf_counter()
        n_q = len(add_quaternius_vehicles(db, data / "meshes" / "quaternius_vehicles_cc0").added)
        t_q = time.perf_counter() - t
    targets = db.targets()
    out.append(
        f"Ingest: 12 built-ins in {t_b:.1f} s, {n_q} Quaternius GLB meshes in {t_q:.1f} s; "
        f"classes {targets['class'].value_counts().sort_index().to_dict()}."
    )
    out.append("")

    # -- the several-thousand-chip job, 2 workers -----------------------------------
    kw = {"azimuth": "0:360:5", "elevation": "10,30,50", "chip_spec": ChipSpec(size=64), "chips_per_unit": 108}
    rep = run_render_job(db, "main", run=RunOptions(workers=2), **kw)
    n_main = len(db.renders("main"))
    out.append(
        f"Render job `main`: {len(targets)} targets x 216 poses, 64x64, 4 channels: {n_main} chips, "
        f"{rep.total_units} units, 2 workers: {rep.seconds:.1f} s ({n_main / rep.seconds:.0f} chips/s), "
        f"failed units {len(rep.failed)}."
    )
    frep = run_features_job(db, "main", run=RunOptions(workers=2))
    out.append(
        f"Features job: {frep.total_units} units (view features of every chip + model features) "
        f"in {frep.seconds:.1f} s, failed {len(frep.failed)}."
    )
    t = time.perf_counter()
    m = pd.read_parquet(db.path / "renders" / "main" / "manifest")
    t_pd = time.perf_counter() - t
    t = time.perf_counter()
    q = duckdb.sql(
        f"SELECT class, count(*) AS n FROM '{db.path}/renders/main/manifest/*.parquet' GROUP BY class ORDER BY class"
    ).fetchall()
    nf = duckdb.sql(f"SELECT count(*) FROM '{db.path}/features/main/*.parquet'").fetchall()[0][0]
    t_dd = time.perf_counter() - t
    out.append(
        f"Read back: pandas {len(m)} manifest rows in {t_pd * 1e3:.0f} ms; DuckDB per class {dict(q)} and "
        f"{nf} feature rows in {t_dd * 1e3:.0f} ms."
    )
    t = time.perf_counter()
    problems = verify_db(db)
    out.append(
        f"`verify`: {len(problems)} problems, {time.perf_counter() - t:.1f} s (hashes every chip)."
    )
    out.append("")

    # -- 1 vs 2 workers ---------------------------------------------------------------
    sub = {
        "azimuth": "0:360:5",
        "elevation": "20,40",
        "chip_spec": ChipSpec(size=64),
        "chips_per_unit": 72,
        "classes": ["tank", "jet", "ship", "truck"],
    }
    times = {}
    loads = {}
    for w in (1, 2):
        loads[w] = _load()
        r = run_render_job(db, f"speed{w}", run=RunOptions(workers=w), **sub)
        times[w] = r.seconds
    n_sub = len(db.renders("speed1"))
    out.append("| workers | chips | seconds | chips/s | load avg (1/5/15 min) before |")
    out.append("|---|---|---|---|---|")
    for w in (1, 2):
        out.append(f"| {w} | {n_sub} | {times[w]:.1f} | {n_sub / times[w]:.0f} | {loads[w]} |")
    out.append("")
    out.append(
        f"Speed-up 2 vs 1 worker: **{times[1] / times[2]:.2f}x** (includes ~1-5 s cluster start and "
        "per-worker imports)."
    )
    out.append("")

    # -- memory over ~10k chips -------------------------------------------------------
    mem = {
        "azimuth": "0:360:2",
        "elevation": "5,20,35,50",
        "chip_spec": ChipSpec(size=64, channels=("intensity", "depth", "mask")),
        "chips_per_unit": 120,
        "targets": list(targets["target_id"][:14]),
    }
    r = run_render_job(db, "memory", run=RunOptions(workers=1), **mem)
    n_mem = len(db.renders("memory"))
    table, growth = _rss_table(db, "memory")
    out.append(
        f"Worker memory, job `memory` ({n_mem} chips, 1 worker, {r.total_units} units, {r.seconds:.0f} s; "
        "RSS sampled at the end of every unit inside the worker, MiB):"
    )
    out.append("")
    out.append(
        "| worker pid | units | chips | first | peak | last | mean of first 10% -> last 10% of units |"
    )
    out.append("|---|---|---|---|---|---|---|")
    out.append(table)
    out.append("")
    out.append(f"Growth (last 10% vs first 10% of units): {growth:+.0f} MiB.")
    return "\n".join(out)


if __name__ == "__main__":
    if len(sys.argv) > 1:
        w = Path(sys.argv[1])
        w.mkdir(parents=True, exist_ok=True)
        print(main(w))
    else:
        d = Path(tempfile.mkdtemp(prefix="bench_db_"))
        try:
            print(main(d))
        finally:
            shutil.rmtree(d, ignore_errors=True)
