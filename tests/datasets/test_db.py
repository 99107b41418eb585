"""Target database folder: init/open, ingest, duplicates, concurrency, bad input."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from prism3d.datasets.database.db import (
    TABLE_SCHEMA_VERSION,
    check_add_request,
    init_db,
    open_db,
    read_table,
    verify_db,
)
from prism3d.datasets.database.ingest import add_builtin, add_meshes

from prism3d.errors import DatasetError, InputError


def _box_obj(path: Path, size: tuple[float, float, float], shift: float = 0.0) -> Path:
    """An axis-aligned box as OBJ (z up), extents ``size``."""
    lx, ly, lz = size
    v = (
        np.array([[x, y, z] for x in (0, lx) for y in (0, ly) for z in (0, lz)], dtype=float)
        + shift
    )
    f = [
        (0, 1, 3),
        (0, 3, 2),
        (4, 6, 7),
        (4, 7, 5),
        (0, 4, 5),
        (0, 5, 1),
        (2, 3, 7),
        (2, 7, 6),
        (0, 2, 6),
        (0, 6, 4),
        (1, 5, 7),
        (1, 7, 3),
    ]
    lines = [f"v {a} {b} {c}" for a, b, c in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")
    return path


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


def test_init_open_and_empty_tables(tmp_path: Path) -> None:
    db = init_db(tmp_path / "db")
    assert (tmp_path / "db" / "db.yaml").is_file()
    assert open_db(tmp_path / "db").meta["units"] == "mm"
    assert len(db.targets()) == 0
    assert db.jobs() == []
    assert verify_db(db) == []
    # an empty targets table is readable without prism3d
    assert len(pd.read_parquet(tmp_path / "db" / "targets.parquet")) == 0
    with pytest.raises(DatasetError, match="already a prism3d database"):
        init_db(tmp_path / "db")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(DatasetError, match="not an empty folder"):
        init_db(tmp_path / "full")
    with pytest.raises(DatasetError, match="not a prism3d database"):
        open_db(tmp_path / "full")


def test_add_meshes_units_scale_and_duplicates(tmp_path: Path) -> None:
    db = init_db(tmp_path / "db")
    f = _box_obj(tmp_path / "box.obj", (4.0, 2.0, 1.0))
    rep = add_meshes(db, [f], target_class="truck", units="cm", up="z")
    assert rep.added == ["box"]
    t = db.targets()
    r = t.iloc[0]
    assert r["class"] == "truck" and r["units"] == "cm" and r["scale_to_mm"] == 10.0
    np.testing.assert_allclose([r["length_mm"], r["width_mm"], r["height_mm"]], [40, 20, 10])
    assert r["n_faces"] == 12 and r["schema_version"] == TABLE_SCHEMA_VERSION
    assert r["source_sha256"] == hashlib.sha256(f.read_bytes()).hexdigest()
    # the normalised model is a mm, z-up PLY with vertex colours
    from prism3d.io.ply import read_ply

    ply = read_ply(tmp_path / "db" / r["model_file"])
    assert "units mm" in ply.comments and ply.colors is not None
    np.testing.assert_allclose(np.ptp(ply.points, axis=0), [40, 20, 10], atol=1e-4)
    assert ply.points[:, 2].min() == pytest.approx(0.0)
    # duplicate content (same bytes, another name): skipped, or an error with strict
    dup = tmp_path / "copy.obj"
    dup.write_bytes(f.read_bytes())
    rep = add_meshes(db, [dup], target_class="truck", units="cm", up="z")
    assert rep.added == [] and "already in the database as box" in rep.skipped[0]
    before = _snapshot(tmp_path / "db")
    with pytest.raises(DatasetError, match="duplicate"):
        add_meshes(db, [dup], target_class="truck", units="cm", up="z", strict=True)
    assert _snapshot(tmp_path / "db") == before
    # same name, other content: a new id
    (tmp_path / "sub").mkdir()
    g = _box_obj(tmp_path / "sub" / "box.obj", (1.0, 1.0, 1.0))
    rep = add_meshes(db, [g], target_class="truck", units="m", up="z", length_mm=500.0)
    assert rep.added == ["box_2"]
    r2 = db.targets().set_index("target_id").loc["box_2"]
    assert r2["length_mm"] == pytest.approx(500.0) and r2["scale_to_mm"] == pytest.approx(500.0)


def test_add_a_mesh_with_a_non_ascii_name(tmp_path: Path) -> None:
    """The file name goes into the model's (ASCII) PLY header as an escape; the id is a
    safe name, the table keeps the name as given."""
    from prism3d.io.ply import read_ply

    db = init_db(tmp_path / "db")
    f = _box_obj(tmp_path / "üß中 tank.obj", (4.0, 2.0, 1.0))
    rep = add_meshes(db, [f], target_class="tank", units="mm", up="z")
    r = db.targets().iloc[0]
    assert rep.added == [r["target_id"]] and r["target_id"].isascii() and r["name"] == "üß中 tank"
    ply = read_ply(tmp_path / "db" / r["model_file"])
    assert any("\\xfc\\xdf\\u4e2d tank.obj" in c for c in ply.comments), ply.comments
    assert verify_db(db) == []


def test_up_axis_y_and_sidecar(tmp_path: Path) -> None:
    db = init_db(tmp_path / "db")
    f = _box_obj(tmp_path / "tall.obj", (4.0, 3.0, 1.0))  # file y (3) is up
    (tmp_path / "tall.obj.units.yaml").write_text("units: mm\nup: y\n")
    add_meshes(db, [f], target_class="ship")
    r = db.targets().iloc[0]
    assert (r["units"], r["up"]) == ("mm", "y")
    np.testing.assert_allclose([r["length_mm"], r["width_mm"], r["height_mm"]], [4, 1, 3])
    with pytest.raises(DatasetError, match="declares units 'mm'"):
        add_meshes(db, [f], target_class="ship", units="m")


def test_check_add_request() -> None:
    assert check_add_request([], [], None) == "builtin"  # --builtin without names: all
    assert check_add_request([], ["tank_t1"], None) == "builtin"
    assert check_add_request(["a.obj"], None, "tank") == "meshes"
    with pytest.raises(InputError, match="not both"):
        check_add_request(["a.obj"], [], None)
    with pytest.raises(InputError, match="give mesh files"):
        check_add_request([], None, "tank")
    with pytest.raises(InputError, match="--class"):
        check_add_request(["a.obj"], None, None)


def test_add_builtin(tmp_path: Path) -> None:
    db = init_db(tmp_path / "db")
    rep = add_builtin(db, ["tank_t1", "ship_s1"])
    assert rep.added == ["tank_t1", "ship_s1"]
    t = db.targets().set_index("target_id")
    assert t.loc["tank_t1", "class"] == "tank" and t.loc["ship_s1", "class"] == "ship"
    assert t.loc["tank_t1", "source_kind"] == "builtin"
    assert 150 <= t.loc["tank_t1", "length_mm"] <= 280
    # the duplicate key is the generated model's hash
    sha = hashlib.sha256(
        (tmp_path / "db" / t.loc["tank_t1", "model_file"]).read_bytes()
    ).hexdigest()
    assert t.loc["tank_t1", "source_sha256"] == sha
    rep = add_builtin(db, ["tank_t1"])
    assert rep.added == [] and len(rep.skipped) == 1
    with pytest.raises(DatasetError, match="unknown built-in target 'tank_zz'"):
        add_builtin(db, ["tank_zz"])
    assert verify_db(db) == []


@pytest.mark.parametrize(
    "kwargs, content, match",
    [
        ({"units": "furlong", "up": "z"}, None, "units: expected one of"),
        ({"up": "z"}, None, "units unknown"),
        ({"units": "mm"}, None, "up axis unknown"),
        ({"units": "mm", "up": "x"}, None, "up: expected one of"),
        ({"units": "mm", "up": "z"}, "this is not a mesh\n\x00\x01garbage", "cannot load mesh"),
        ({"units": "mm", "up": "z", "length_mm": -3.0}, None, r"length_mm: expected a length in \(0, 1e\+06\]"),
        ({"units": "mm", "up": "z", "length_mm": 1e300}, None, r"length_mm: expected a length in \(0, 1e\+06\]"),
        ({"units": "mm", "up": "z", "yaw_deg": float("inf")}, None, "yaw_deg: expected a finite angle"),
    ],
)
def test_bad_input_changes_nothing(
    tmp_path: Path, kwargs: dict, content: str | None, match: str
) -> None:
    db = init_db(tmp_path / "db")
    add_builtin(db, ["truck_k1"])
    good = _box_obj(tmp_path / "good.obj", (2.0, 1.0, 1.0))
    bad = tmp_path / "bad.obj"
    if content is None:
        _box_obj(bad, (3.0, 1.0, 1.0))
    else:
        bad.write_text(content)
    before = _snapshot(tmp_path / "db")
    with pytest.raises(DatasetError, match=match):
        add_meshes(db, [good, bad], target_class="truck", **kwargs)
    assert _snapshot(tmp_path / "db") == before


def test_bad_paths_and_names(tmp_path: Path) -> None:
    db = init_db(tmp_path / "db")
    with pytest.raises(DatasetError, match="file not found"):
        add_meshes(db, [tmp_path / "nope.obj"], target_class="tank", units="mm", up="z")
    (tmp_path / "x.fbx").write_text("x")
    with pytest.raises(DatasetError, match="unsupported mesh format"):
        add_meshes(db, [tmp_path / "x.fbx"], target_class="tank", units="mm", up="z")
    with pytest.raises(DatasetError, match="not a valid name"):
        add_meshes(db, [tmp_path / "x.fbx"], target_class="../evil", units="mm", up="z")
    with pytest.raises(DatasetError, match="no mesh files"):
        add_meshes(db, [], target_class="tank")
    # a point cloud (PLY without faces) is not a target model
    from prism3d.io.ply import write_ply

    write_ply(
        tmp_path / "scan.ply", np.random.default_rng(0).normal(size=(50, 3)), comments=["units mm"]
    )
    with pytest.raises(DatasetError, match="cannot load mesh"):
        add_meshes(db, [tmp_path / "scan.ply"], target_class="tank")


def test_prism3d_ply_declares_units(tmp_path: Path) -> None:
    """A PLY written by prism3d (``units mm`` comment) needs no --units/--up."""
    from prism3d.io.ply import write_ply

    v = np.array([[0, 0, 0], [10, 0, 0], [0, 20, 0], [0, 0, 5]], dtype=float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    write_ply(tmp_path / "model.ply", v, faces=f, comments=["units mm"])
    db = init_db(tmp_path / "db")
    add_meshes(db, [tmp_path / "model.ply"], target_class="tank")
    r = db.targets().iloc[0]
    assert (r["units"], r["up"]) == ("mm", "z") and r["height_mm"] == pytest.approx(5.0)
    with pytest.raises(DatasetError, match="declares units 'mm'"):
        add_meshes(db, [tmp_path / "model.ply"], target_class="tank", units="cm")


def test_unknown_schema_versions_rejected(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    db = init_db(tmp_path / "db")
    add_builtin(db, ["jet_j1"])
    tf = tmp_path / "db" / "targets.parquet"
    table = pq.read_table(tf)
    meta = dict(table.schema.metadata)
    meta[b"prism3d_schema_version"] = b"99"
    pq.write_table(table.replace_schema_metadata(meta), tf)
    before = _snapshot(tmp_path / "db")
    with pytest.raises(DatasetError, match="unknown schema_version 99"):
        db.targets()
    with pytest.raises(DatasetError, match="unknown schema_version 99"):
        add_builtin(db, ["jet_j2"])
    assert any("unknown schema_version 99" in p for p in verify_db(db))
    assert _snapshot(tmp_path / "db") == before
    y = tmp_path / "db" / "db.yaml"
    y.write_text(y.read_text().replace("schema_version: 1", "schema_version: 7"))
    with pytest.raises(DatasetError, match="unknown schema_version 7"):
        open_db(tmp_path / "db")
    y.write_text(y.read_text() + "colour: blue\n")
    with pytest.raises(DatasetError, match="unknown keys"):
        open_db(tmp_path / "db")
    with pytest.raises(DatasetError, match="not a readable Parquet"):
        (tmp_path / "junk.parquet").write_text("junk")
        read_table(tmp_path / "junk.parquet")


def _add_worker(db_path: str, files: list[str]) -> None:
    from prism3d.datasets.database.ingest import add_meshes as add

    import prism3d  # noqa: F401

    for f in files:  # one call per file: many lock/replace cycles interleave
        add(db_path, [f], target_class="truck", units="mm", up="z")


def test_concurrent_add_two_processes(tmp_path: Path) -> None:
    from prism3d._env import spawn_context

    db = init_db(tmp_path / "db")
    files = [str(_box_obj(tmp_path / f"b{i}.obj", (2.0 + i, 1.0, 1.0))) for i in range(8)]
    ctx = spawn_context()
    procs = [ctx.Process(target=_add_worker, args=(str(db.path), files[k::2])) for k in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]
    t = db.targets()
    assert sorted(t["target_id"]) == sorted(Path(f).stem for f in files)
    assert t["source_sha256"].is_unique
    assert verify_db(db) == []


@pytest.mark.realdata
def test_quaternius_vehicles_policy(shared_data: Path, tmp_path: Path) -> None:
    from prism3d.datasets.database.ingest import KIT_SCALE, QUATERNIUS_VEHICLES, add_quaternius_vehicles

    folder = shared_data / "meshes" / "quaternius_vehicles_cc0"
    if not folder.is_dir():
        pytest.skip("quaternius meshes not in the shared data")
    db = init_db(tmp_path / "db")
    names = ["tank_1", "car_suv", "ship_boat", "airplane_military_1"]
    rep = add_quaternius_vehicles(db, folder, names=names)
    assert rep.added == names
    t = db.targets().set_index("target_id")
    assert list(t["class"]) == ["tank", "vehicle", "ship", "jet"]
    for n in names:
        cls, up, _, length_m = QUATERNIUS_VEHICLES[n]
        r = t.loc[n]
        assert r["up"] == up and r["units"] == "m"
        assert max(r["length_mm"], r["width_mm"]) == pytest.approx(length_m * 1000 * KIT_SCALE[cls])
        assert r["height_mm"] < max(r["length_mm"], r["width_mm"])  # the up axis is right
    # ground vehicles and ships: the long axis is x after the yaw
    assert all(
        t.loc[n, "length_mm"] > t.loc[n, "width_mm"] for n in ("tank_1", "car_suv", "ship_boat")
    )
    assert add_quaternius_vehicles(db, folder, names=["tank_1"]).added == []


def test_verify_finds_a_bad_job_yaml_and_duplicate_rows(tmp_path) -> None:
    """Damage verify used to miss: an invalid job.yaml, a manifest row repeated."""
    import shutil

    from prism3d.atr.chips import ChipSpec
    from prism3d.datasets.database.ingest import add_builtin
    from prism3d.datasets.jobs.database_jobs import run_render_job

    db = init_db(tmp_path / "db")
    add_builtin(db, ["tank_t1"])
    assert run_render_job(db, "j", azimuth="0:90:90", elevation=10, chip_spec=ChipSpec(size=16)).ok
    assert verify_db(db) == []
    mdir = db.job_dir("j") / "manifest"
    part = sorted(mdir.glob("part-*.parquet"))[0]
    shutil.copy(part, mdir / "part-copy-000000.parquet")
    assert any("duplicate manifest rows" in p for p in verify_db(db))
    (mdir / "part-copy-000000.parquet").unlink()
    (db.job_dir("j") / "job.yaml").write_text("- just\n- a list\n")
    assert any("not a render job spec" in p for p in verify_db(db))
    (db.job_dir("j") / "job.yaml").write_bytes(b"\xff\xfe: [\n")
    assert verify_db(db) and all("Traceback" not in p for p in verify_db(db))


def test_a_stitched_scan_becomes_a_target_without_flags(tmp_path: Path) -> None:
    """stitch --frame object --mesh, then db add MESH --class tank: units and up from the
    PLY header, source_kind scan, provenance with the poses' and scans' hashes, coverage
    of a turntable ring seen from 17 deg above (the underside unobserved)."""
    from prism3d.cli import main
    from prism3d.io.ply import write_ply
    from tests.reconstruct.test_stitch import _raycast_views

    scans, _, _, _ = _raycast_views(views=8, W=360, H=270, f=1500.0)
    paths = []
    for k, (p, c, _) in enumerate(scans):
        paths.append(tmp_path / "scan" / f"s{k}.ply")
        paths[-1].parent.mkdir(exist_ok=True)
        write_ply(paths[-1], p, colors=c,  # the hashes `prism3d reconstruct` writes
                  comments=["prism3d scan", f"shot_sha256 {k:064x}", "calibration_sha256 " + "c" * 64])
    model, mesh = tmp_path / "scan" / "model.ply", tmp_path / "scan" / "mesh.ply"
    assert main(["--quiet", "stitch", *map(str, paths), "-o", str(model), "--mesh", str(mesh),
                 "--turntable-step", "45", "--frame", "object"]) == 0
    db = init_db(tmp_path / "db")
    add_meshes(db, [mesh], target_class="tank")  # no units, no up: the header says mm, z up
    r = db.targets().iloc[0]
    assert r["source_kind"] == "scan" and (r["units"], r["up"]) == ("mm", "z")
    assert "poses.json sha256" in r["provenance"] and "scan files not found" not in r["provenance"]
    assert 0.4 < r["coverage"] < 0.9, r["coverage"]  # a ring of views: not the whole sphere
    assert "nothing seen below" in r["provenance"]
    assert "shots sha256 " in r["provenance"] and "calibration sha256 " + "c" * 64 in r["provenance"]
    assert 200 < r["length_mm"] < 290  # tank_t1, 243.8 mm long
    assert verify_db(db) == []
