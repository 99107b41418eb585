"""Render and feature jobs: units, resume, SIGKILL safety, failures, readers."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from prism3d.datasets.database.db import JobStatus, init_db, open_db, verify_db
from prism3d.datasets.database.ingest import add_builtin
from prism3d.atr.chips import ChipSpec
from prism3d.datasets.jobs.database_jobs import (
    RenderSpec,
    RunOptions,
    database_info,
    job_status,
    plan_units,
    run_features_job,
    run_render_job,
    unit_stats,
    write_npz_deterministic,
)

from prism3d.errors import DatasetError

JOB = {
    "azimuth": "0:360:30",
    "elevation": "10,40",
    "chip_spec": ChipSpec(size=32),
    "chips_per_unit": 10,
}  # 24 poses -> 3 units


@pytest.fixture(scope="module")
def small_db(tmp_path_factory: pytest.TempPathFactory):
    """Two built-in targets, a finished 48-chip render job 'j' and its features."""
    db = init_db(tmp_path_factory.mktemp("jobs") / "db")
    add_builtin(db, ["tank_t1", "jet_j1"])
    rep = run_render_job(db, "j", **JOB)
    assert rep.ok and rep.done_units == 6
    feat = run_features_job(db, "j")
    assert feat.ok, feat.summary()
    return db


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def test_render_spec_from_and_into_chip_spec() -> None:
    chip = ChipSpec(size=48, channels=("depth", "mask"), camouflage=False, clutter="noise", seed=3)
    spec = RenderSpec.create("a", ["t"], chip, 7, azimuth="0:360:90", range_mm=900)
    assert spec.chip_spec == chip and spec.range_mm == "900" and spec.elevation == "20"
    assert spec.chips_per_unit == 7
    # the defaults live in ChipSpec: a default job stores the ChipSpec defaults
    assert RenderSpec(name="b", targets=("t",)).chip_spec == ChipSpec()


def test_plan_units_and_spec_checks() -> None:
    spec = RenderSpec(
        name="a", targets=("t1", "t2"), azimuth="0:360:10", elevation="10,30,50", chips_per_unit=50
    )
    units = plan_units(spec)
    assert spec.n_poses == 108
    assert [(u.target_id, u.start, u.stop) for u in units[:3]] == [
        ("t1", 0, 50),
        ("t1", 50, 100),
        ("t1", 100, 108),
    ]
    assert len(units) == 6 and len({u.unit_id for u in units}) == 6
    assert RenderSpec.from_dict(spec.to_dict()).spec_hash == spec.spec_hash
    with pytest.raises(DatasetError, match="unknown keys"):
        RenderSpec.from_dict({**spec.to_dict(), "colour": 1})
    with pytest.raises(DatasetError, match="channels: expected"):
        RenderSpec(name="a", targets=("t",), channels=("depth", "rgb"))
    with pytest.raises(DatasetError, match="size: expected"):
        RenderSpec(name="a", targets=("t",), size=4)
    with pytest.raises(DatasetError, match="azimuth"):
        RenderSpec(name="a", targets=("t",), azimuth="0:x:1")
    with pytest.raises(DatasetError, match="no targets"):
        RenderSpec(name="a", targets=())
    with pytest.raises(DatasetError, match="not a valid name"):
        RenderSpec(name="../a", targets=("t",))


def test_deterministic_npz(tmp_path: Path) -> None:
    a = {"depth": np.arange(12, dtype=np.float32).reshape(3, 4), "mask": np.eye(3, dtype=bool)}
    s1 = write_npz_deterministic(tmp_path / "a.npz", a)
    time.sleep(1.1)
    s2 = write_npz_deterministic(tmp_path / "b.npz", a)
    assert s1 == s2 == hashlib.sha256((tmp_path / "a.npz").read_bytes()).hexdigest()
    with np.load(tmp_path / "a.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["depth"], a["depth"])
        assert z["mask"].dtype == bool


def test_manifest_and_chips(small_db) -> None:
    db = small_db
    m = db.renders("j")
    assert len(m) == 48 and not m.duplicated(["target_id", "chip_index"]).any()
    for col in [
        "target_id",
        "class",
        "az_deg",
        "el_deg",
        "range_mm",
        "roll_deg",
        "fx",
        "fy",
        "cx",
        "cy",
        "T_cam_obj_00",
        "T_cam_obj_33",
        "chip_file",
        "channels",
        "sha256",
        "schema_version",
    ]:
        assert col in m.columns
    assert set(m["class"]) == {"tank", "jet"}
    assert sorted(m["az_deg"].unique()) == list(range(0, 360, 30))
    # the manifest pose reproduces the chip: the target's bbox centre projects to the chip centre
    r = m.iloc[5]
    T = np.array([[r[f"T_cam_obj_{i}{j}"] for j in range(4)] for i in range(4)])
    X, meta = db.load_chips("j", targets=[r["target_id"]], channel="depth")
    assert X.shape == (24, 32, 32) and X.dtype == np.float32
    d = X[int(r["chip_index"])]
    assert np.isfinite(d).any() and np.nanmin(d) < r["range_mm"] < np.nanmax(d) + 1e3
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    mask, _ = db.load_chips("j", channel="mask")
    assert mask.dtype == bool and mask.shape == (48, 32, 32)
    assert mask.reshape(48, -1).any(axis=1).all()
    # known answer: the camera looks at the target's bounding-box centre
    from prism3d.datasets import builtin_target

    c = builtin_target(r["target_id"]).bounds.mean(axis=0)
    p = T[:3, :3] @ c + T[:3, 3]
    assert p[0] * r["fx"] / p[2] + r["cx"] == pytest.approx(15.5, abs=1e-6)
    assert p[1] * r["fy"] / p[2] + r["cy"] == pytest.approx(15.5, abs=1e-6)
    assert np.linalg.norm(p) == pytest.approx(r["range_mm"])
    np.testing.assert_array_equal(np.isfinite(db.load_chips("j", channel="depth")[0]), mask)
    inten, meta = db.load_chips(
        "j", classes=["jet"], az_range=(0, 90), el_range=(30, 50), channel="intensity"
    )
    assert len(meta) == 4 and set(meta["el_deg"]) == {40.0} and inten.dtype == np.float32
    assert 0 <= inten.min() and inten.max() <= 1
    batches = list(db.iter_batches("j", 20, channel="depth"))
    assert [len(b[1]) for b in batches] == [20, 20, 8]
    with pytest.raises(DatasetError, match="batch_size"):
        next(db.iter_batches("j", 0))
    with pytest.raises(DatasetError, match="no render job 'nope'"):
        db.renders("nope")


def test_readable_without_prism3d(small_db) -> None:
    import duckdb
    import pyarrow.dataset as ds

    root = small_db.path
    glob = str(root / "renders" / "j" / "manifest" / "*.parquet")
    n_duck = duckdb.sql(f"SELECT count(*) FROM '{glob}'").fetchall()[0][0]
    per_class = dict(duckdb.sql(f"SELECT class, count(*) FROM '{glob}' GROUP BY class").fetchall())
    pa_rows = (
        ds.dataset(str(root / "renders" / "j" / "manifest"), format="parquet").to_table().num_rows
    )
    pd_rows = len(pd.read_parquet(root / "renders" / "j" / "manifest"))
    assert n_duck == pa_rows == pd_rows == 48 and per_class == {"tank": 24, "jet": 24}
    feats = duckdb.sql(f"SELECT count(*) FROM '{root}/features/j/*.parquet'").fetchall()[0][0]
    assert feats == 48
    t = pd.read_parquet(root / "targets.parquet")
    assert list(t["target_id"]) == ["tank_t1", "jet_j1"]
    # a chip file is a plain npz
    rel = pd.read_parquet(root / "renders" / "j" / "manifest")["chip_file"].iloc[0]
    with np.load(root / rel, allow_pickle=False) as z:
        assert set(z.files) == {"intensity", "depth", "mask", "shape"}


def test_features(small_db) -> None:
    f = small_db.features("j")
    assert len(f) == 48 and {"target_id", "class", "chip_index", "az_deg"} <= set(f.columns)
    assert f.select_dtypes("number").shape[1] > 10
    mf = small_db.features("models")
    assert sorted(mf["target_id"]) == ["jet_j1", "tank_t1"]
    again = run_features_job(small_db, "j")
    assert again.done_units == 0 and again.skipped_units == again.total_units == 8


def test_export_split(small_db, tmp_path: Path) -> None:
    out = small_db.export_split(
        "j", tmp_path / "split.npz", channels=("depth", "mask"), el_range=(10, 10)
    )
    with np.load(out, allow_pickle=False) as z:
        assert z["depth"].shape == (24, 32, 32) and z["mask"].dtype == bool
        assert list(z["classes"]) == ["jet", "tank"]
        assert np.bincount(z["labels"]).tolist() == [12, 12]
        assert set(z["el_deg"]) == {10.0}
    with pytest.raises(DatasetError, match="no chips"):
        small_db.export_split("j", tmp_path / "none.npz", classes=["ship"])


def test_info_and_stats(small_db) -> None:
    assert small_db.info().jobs == {"j": None}  # the folder alone: names only
    info = database_info(small_db)
    assert info.targets == 2 and info.targets_per_class == {"jet": 1, "tank": 1}
    assert info.jobs["j"] == JobStatus(units=6, done_units=6, chips=48, features=True)
    assert info.to_json()["jobs"]["j"] == {"units": 6, "done_units": 6, "chips": 48, "features": True}
    assert info.text().splitlines()[-1] == "  j: 6/6 units done, 48 chips, features yes"
    st = unit_stats(small_db, "j")
    assert len(st) == 6 and (st["rss_mb"] > 0).all() and st["chips"].sum() == 48


def test_rerun_resumes_and_spec_mismatch(small_db) -> None:
    before = _snapshot(small_db.path)
    rep = run_render_job(small_db, "j", **JOB)
    assert rep.ok and rep.done_units == 0 and rep.skipped_units == 6
    assert _snapshot(small_db.path) == before
    with pytest.raises(DatasetError, match="exists with a different spec"):
        run_render_job(small_db, "j", **{**JOB, "chip_spec": ChipSpec(size=40)})
    with pytest.raises(DatasetError, match="unknown target ids"):
        run_render_job(small_db, "k", targets=["nope"], **JOB)
    with pytest.raises(DatasetError, match="workers"):
        run_render_job(small_db, "k", run=RunOptions(workers=-1), **JOB)
    with pytest.raises(DatasetError, match="scheduler"):
        run_render_job(small_db, "k", run=RunOptions(scheduler="localhost"), **JOB)
    with pytest.raises(DatasetError, match="retries"):
        RunOptions(retries=-1)
    with pytest.raises(DatasetError, match="leave noise_sigma at"):
        run_render_job(small_db, "k", **{**JOB, "chip_spec": ChipSpec(size=32, noise_sigma=0.1)})
    assert _snapshot(small_db.path) == before


def test_verify_flags_problems(small_db, tmp_path: Path) -> None:
    import shutil

    import pyarrow.parquet as pq

    assert verify_db(small_db) == []
    root = tmp_path / "copy"
    shutil.copytree(small_db.path, root)
    db = open_db(root)
    m = db.renders("j")
    (root / m["chip_file"].iloc[0]).write_bytes(b"tampered")
    (root / m["chip_file"].iloc[1]).unlink()
    (root / "renders" / "j" / "chips" / "tank_t1" / "999999.npz").write_bytes(b"orphan")
    probs = verify_db(db)
    assert any("sha256 mismatch" in p for p in probs)
    assert any("missing" in p for p in probs)
    assert any("orphan chip" in p for p in probs)
    # a manifest path escaping the DB folder: rejected by readers, flagged by verify
    for bad in ("../x.npz", "/etc/passwd"):
        part = min((root / "renders" / "j" / "manifest").glob("part-jet*.parquet"))
        t = pq.read_table(part)
        df = t.to_pandas()
        df.loc[0, "chip_file"] = bad
        import pyarrow as pa

        pq.write_table(
            pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(
                t.schema.metadata
            ),
            part,
        )
        snap = _snapshot(root)
        with pytest.raises(DatasetError, match="escapes the database folder"):
            db.load_chips("j", targets=["jet_j1"])
        assert any("escapes the database folder" in p for p in verify_db(db))
        assert _snapshot(root) == snap


def test_failing_unit_is_reported_others_finish(tmp_path: Path) -> None:
    db = init_db(tmp_path / "db")
    add_builtin(db, ["truck_k1"])
    from prism3d.datasets.database.ingest import add_meshes

    box = tmp_path / "box.obj"
    box.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    add_meshes(db, [box], target_class="truck", units="cm", up="z")
    (db.path / "models" / "box.ply").write_bytes(b"ply\ncorrupted")
    rep = run_render_job(
        db,
        "f",
        azimuth="0:360:90",
        elevation="20",
        chip_spec=ChipSpec(size=16),
        chips_per_unit=2,
        run=RunOptions(retries=1),
    )
    assert not rep.ok and rep.exit_code == 1
    assert rep.done_units == 2 and len(rep.failed) == 2
    assert all("target box poses" in f["what"] for f in rep.failed)
    assert "FAILED box-000000 (target box poses 0..1)" in rep.summary()
    assert job_status(db, "f").done_units == 2


_KILL_SCRIPT = """
import sys
import prism3d
from prism3d.atr.chips import ChipSpec
from prism3d.datasets.jobs.database_jobs import run_render_job
run_render_job(sys.argv[1], "k", azimuth="0:360:5", elevation="10,30", chip_spec=ChipSpec(size=48),
               chips_per_unit=8)
"""


def test_sigkill_then_resume_equals_uninterrupted(tmp_path: Path) -> None:
    """A job SIGKILLed half-way and resumed gives the manifest of an uninterrupted run."""
    dbs = []
    for nm in ("killed", "clean"):
        db = init_db(tmp_path / nm)
        add_builtin(db, ["tank_t2", "ship_s2"])
        dbs.append(db)
    killed, clean = dbs
    mdir = killed.path / "renders" / "k" / "manifest"
    proc = subprocess.Popen(
        [sys.executable, "-c", _KILL_SCRIPT, str(killed.path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    t0 = time.time()
    try:
        while time.time() - t0 < 120:
            if mdir.is_dir() and len(list(mdir.glob("part-*.parquet"))) >= 2:
                break
            if proc.poll() is not None:
                break
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        _, err = proc.communicate()
    n_parts = len(list(mdir.glob("part-*.parquet")))
    total = 2 * 144 // 8
    assert proc.returncode == -signal.SIGKILL, err.decode()[-2000:]
    assert 0 < n_parts < total
    assert job_status(killed, "k").done_units == n_parts
    rep = run_render_job(
        killed, "k", azimuth="0:360:5", elevation="10,30", chip_spec=ChipSpec(size=48), chips_per_unit=8
    )
    assert rep.ok and rep.skipped_units == n_parts and rep.done_units == total - n_parts
    rep2 = run_render_job(
        clean, "k", azimuth="0:360:5", elevation="10,30", chip_spec=ChipSpec(size=48), chips_per_unit=8
    )
    assert rep2.ok and rep2.done_units == total
    a, b = killed.renders("k"), clean.renders("k")
    assert len(a) == 288 and not a.duplicated(["target_id", "chip_index"]).any()
    pd.testing.assert_frame_equal(a, b)
    assert verify_db(killed) == [] and verify_db(clean) == []
    chips_a = sorted(p.relative_to(killed.path) for p in (killed.path / "renders").rglob("*.npz"))
    assert len(chips_a) == 288


@pytest.mark.slow
def test_dask_local_cluster(small_db, tmp_path: Path, monkeypatch) -> None:
    """Two spawn workers give the same manifest as the in-process run, and the caller's
    environment is left as it was (the nannies set the workers' variables in it)."""
    import distributed

    clusters = []

    class Recorded(distributed.LocalCluster):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            clusters.append((self.scheduler_address, self.dashboard_link))

    monkeypatch.setattr(distributed, "LocalCluster", Recorded)
    tmp = tmp_path / "tmpdir"
    tmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)  # read TMPDIR again
    env = dict(os.environ)
    rep = run_render_job(small_db, "jd", run=RunOptions(workers=2), **JOB)
    assert dict(os.environ) == env
    assert list(tmp.iterdir()) == []  # the workers' scratch space went with the run
    # reachable from this machine only: scheduler and dashboard on the loopback address
    (addr, dash), = clusters
    assert addr.startswith("tcp://127.0.0.1:") and dash.startswith("http://127.0.0.1:"), (addr, dash)
    assert rep.ok and rep.done_units == 6
    assert len({s["pid"] for s in rep.stats}) >= 1 and all(
        s["pid"] != os.getpid() for s in rep.stats
    )
    a = small_db.renders("jd").drop(columns=["chip_file"])
    b = small_db.renders("j").drop(columns=["chip_file"])
    pd.testing.assert_frame_equal(a, b)


def test_resume_keeps_job_targets(tmp_path: Path) -> None:
    """A target added after a job was created is not silently added to it on resume."""
    db = init_db(tmp_path / "db")
    add_builtin(db, ["truck_k1"])
    kw = {"azimuth": "0,180", "elevation": "20", "chip_spec": ChipSpec(size=16)}
    assert run_render_job(db, "r", **kw).done_units == 1
    add_builtin(db, ["truck_k2"])
    rep = run_render_job(db, "r", **kw)
    assert rep.total_units == 1 and rep.skipped_units == 1
    assert run_render_job(db, "r2", **kw).total_units == 2  # a new job sees both


def test_cli_db_render_and_features_quiet(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`--quiet` silences the summaries of `db render` and `db features` (exit codes kept)."""
    from prism3d.cli import main

    db = init_db(tmp_path / "db")
    add_builtin(db, ["truck_k1"])
    capsys.readouterr()
    render = ["db", "render", str(db.path), "--job", "q", "--azimuth", "0,180", "--size", "16"]
    assert main(["--quiet", *render]) == 0
    assert main(["--quiet", "db", "features", str(db.path), "--job", "q"]) == 0
    assert capsys.readouterr().out == ""
    assert main(render) == 0  # resumed: the summary is printed without --quiet
    assert "job q: 1/1 units done" in capsys.readouterr().out


def test_tampered_target_id_writes_nothing_outside(tmp_path: Path) -> None:
    """A target id is a folder name: one that climbs out of the database (a hand-edited
    targets.parquet) is refused when read, and the job writes nothing anywhere."""
    from prism3d.datasets.database.db import read_table, write_table

    db = init_db(tmp_path / "db")
    add_builtin(db, ["tank_t1"])
    t = read_table(db.targets_file).drop(columns=["schema_version"])
    t.loc[0, "target_id"] = "../../../../elsewhere/x"
    write_table(t, db.targets_file, kind="targets")
    before = sorted(p for p in tmp_path.rglob("*"))
    with pytest.raises(DatasetError, match="target_id.*not a valid name"):
        run_render_job(db, "j", **JOB)
    assert sorted(p for p in tmp_path.rglob("*")) == before
    assert verify_db(db)  # and verify reports it


def test_symlinked_chip_folder_is_refused(tmp_path: Path) -> None:
    """A chips/<target> folder that is a link to elsewhere is not written through."""
    db = init_db(tmp_path / "db")
    add_builtin(db, ["tank_t1"])
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    chips = db.path / "renders" / "j" / "chips"
    chips.mkdir(parents=True)
    (chips / "tank_t1").symlink_to(outside, target_is_directory=True)
    rep = run_render_job(db, "j", **JOB)
    assert not rep.ok and all("escapes the database folder" in f["error"] for f in rep.failed)
    assert list(outside.iterdir()) == []


def test_unreachable_scheduler_fails_fast_writing_nothing(tmp_path: Path) -> None:
    """A scheduler nobody listens on: the job fails within seconds, before job.yaml."""
    import socket

    db = init_db(tmp_path / "db")
    add_builtin(db, ["tank_t1"])
    with socket.socket() as s:  # a port that was free a moment ago, now closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    before = sorted(tmp_path.rglob("*"))
    t0 = time.time()
    with pytest.raises(DatasetError, match=f"scheduler tcp://127.0.0.1:{port}: cannot connect"):
        run_render_job(db, "j", run=RunOptions(scheduler=f"tcp://127.0.0.1:{port}"), **JOB)
    assert time.time() - t0 < 60  # not the 30 s of Dask's own connect timeout per try, repeated
    assert sorted(tmp_path.rglob("*")) == before



def test_resume_removes_a_killed_writers_temp_part_and_refuses_a_second_run(tmp_path: Path) -> None:
    """A kill during a manifest write leaves a hidden temp part (0 bytes): it never
    matches ``*.parquet`` (DuckDB's glob in FORMAT.md), the next run removes it and
    verify is clean; a second run of a job already running is refused."""
    import fcntl

    db = init_db(tmp_path / "db")
    add_builtin(db, ["tank_t1"])
    kw = dict(JOB, azimuth="0:90:90", elevation=10)
    assert run_render_job(db, "j", **kw).ok
    mdir = db.job_dir("j") / "manifest"
    dead = mdir / ".part-tank_t1-000000.x1y2.tmp"
    dead.write_bytes(b"")
    parts = list(mdir.glob("*.parquet"))
    assert parts and dead not in parts
    assert any("leftover temporary file" in p for p in verify_db(db))
    rep = run_render_job(db, "j", **kw)
    assert rep.ok and rep.done_units == 0 and not dead.exists()
    assert verify_db(db) == []
    fd = os.open(db.job_dir("j") / ".lock", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as a running job holds it
        with pytest.raises(DatasetError, match="another process is running it"):
            run_render_job(db, "j", **kw)
    finally:
        os.close(fd)


def test_more_local_workers_than_the_machine_holds_is_refused_up_front(tmp_path) -> None:
    from prism3d.cli import main
    from prism3d.datasets.runner import max_local_workers

    cap = max_local_workers()
    assert cap >= 1
    RunOptions(workers=cap)  # the most it holds is fine
    RunOptions(workers=10_000, scheduler="tcp://127.0.0.1:1")  # an existing cluster decides for itself
    with pytest.raises(DatasetError, match="more than this machine holds"):
        RunOptions(workers=cap + 1)
    out = tmp_path / "fields"
    assert main(["--quiet", "simulate", "field", str(out), "--count", "2", "--workers", "10000"]) == 2
    assert not out.exists()
