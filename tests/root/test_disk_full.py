"""Disk full: every writing command (trigger and flatness write no file), its outputs on a 2 MiB tmpfs filled to the brim (or
to a little free space, so some files fit and the next does not), exits 2 with one line,
leaves nothing half-written and no new file, and keeps an earlier output byte for byte.

Needs permission to mount a tmpfs (root); skipped otherwise.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from prism3d.cli import main

SIZE = "2m"


@pytest.fixture(scope="module")
def mnt(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("tmpfs")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={SIZE}", "tmpfs", str(d)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    yield d
    subprocess.run(["umount", "-l", str(d)], capture_output=True)


@pytest.fixture(scope="module")
def trigger() -> str:
    from prism3d.capture.trigger_sim import TriggerSimulator

    with TriggerSimulator() as sim:
        yield sim.port


def _cli(*args) -> int:
    return main(["--quiet", *map(str, args)])


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Valid inputs on the ordinary disk: a small rig's plate shot, its rectified pair,
    disparity, scan, two scans to stitch, a bank and a database with a render job."""
    from prism3d.capture.rig import paper_rig
    from prism3d.geometry import make_transform, rotation_about, transform_points
    from prism3d.io.ply import read_ply, write_ply

    d = tmp_path_factory.mktemp("inputs")
    paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4).save(d / "rig.yaml")
    assert _cli("simulate", "plate", d / "plate", "--rig", d / "rig.yaml", "--supersample", "1") == 0
    assert _cli("rectify", d / "plate" / "shot.png", "--calib", d / "rig.yaml", "-o", d / "rect") == 0
    assert _cli("match", d / "rect" / "left.png", d / "rect" / "right.png", "-o", d / "d.pfm",
                "--min-disp", "170", "--num-disp", "64") == 0
    assert _cli("reconstruct", d / "plate" / "shot.png", "--calib", d / "rig.yaml", "-o", d / "scan.ply") == 0
    P = read_ply(d / "scan.ply").points[::20]
    write_ply(d / "a.ply", P)
    T = make_transform(rotation_about([0.0, 1.0, 0.0], np.radians(2.0)), [3.0, 0.0, 0.0])
    write_ply(d / "b.ply", transform_points(T, P))
    assert _cli("bank", "train", "--scenes", "0", "--targets", "tank_t1", "jet_j1", "-o", d / "bank.npz", "--azimuth",
                "0:360:90", "--elevation", "20:20:1", "--size", "32", "--no-camouflage") == 0
    assert _cli("simulate", "calib", d / "cal", "--rig", d / "rig.yaml", "--supersample", "1", "--views", "4") == 0
    assert _cli("db", "init", d / "db") == 0
    assert _cli("db", "add", d / "db", "--builtin", "jet_j1") == 0
    assert _cli("db", "render", d / "db", "--job", "j", "--azimuth", "0:90:90", "--elevation", "20:20:1",
                "--range", "3000", "--size", "32") == 0
    return {"d": d, "rig": d / "rig.yaml", "shot": d / "plate" / "shot.png"}


def _cases(i: dict[str, Path], m: Path) -> dict[str, tuple[list, Path]]:
    """name -> (argv, the output it writes: a file or a folder)."""
    d = i["d"]
    render = ["--azimuth", "0:90:45", "--elevation", "20:20:1", "--range", "3000", "--size", "32"]
    return {
        "simulate": (["simulate", "plate", m / "sim", "--rig", i["rig"], "--supersample", "1"], m / "sim"),
        "convert-calib": (["convert-calib", i["rig"], "-o", m / "c.yaml"], m / "c.yaml"),
        "rectify": (["rectify", i["shot"], "--calib", i["rig"], "-o", m / "rect"], m / "rect"),
        "match": (["match", d / "rect" / "left.png", d / "rect" / "right.png", "-o", m / "d.pfm",
                   "--min-disp", "170", "--num-disp", "64"], m / "d.pfm"),
        "reconstruct": (["reconstruct", i["shot"], "--calib", i["rig"], "-o", m / "scan.ply",
                         "--mesh", m / "mesh.ply", "--depth-out", m / "depth.tiff"], m / "scan.ply"),
        "triangulate": (["triangulate", d / "d.pfm", "--calib", i["rig"], "--left", d / "rect" / "left.png",
                         "-o", m / "cloud.ply"], m / "cloud.ply"),
        "stitch": (["stitch", d / "a.ply", d / "b.ply", "-o", m / "model.ply"], m / "model.ply"),
        "decamo": (["decamo", i["shot"], "--calib", i["rig"], "-o", m / "dc"], m / "dc"),
        "features": (["features", d / "scan.ply", "--units", "mm", "--up", "y", "-o", m / "f.parquet"],
                     m / "f.parquet"),
        "render": (["render", "tank_t1", "-o", m / "chips", "--format", "npz", *render], m / "chips"),
        "bank-train": (["bank", "train", "--scenes", "0", "--targets", "tank_t1", "-o", m / "bank.npz", "--azimuth", "0:360:90",
                        "--elevation", "20:20:1", "--size", "32", "--no-camouflage"], m / "bank.npz"),
        "bank-eval": (["bank", "eval", d / "bank.npz", "--targets", "tank_t1", "jet_j1", "--azimuth",
                       "0:360:90", "--elevation", "20:20:1", "--json", m / "res.json"], m / "res.json"),
        "calibrate": (["calibrate", *sorted((d / "cal").glob("calib_*.png")), "--board", "9x6", "-o",
                       m / "c.yaml"], m / "c.yaml"),
        "capture": (["capture", "--trigger", "{trigger}", "--camera", f"folder:{d / 'cal'}", "-o", m / "shots",
                     "--count", "2"], m / "shots"),
        "demo": (["demo", m / "demo", "--fast", "--only", "environment"], m / "demo"),
        "db-init": (["db", "init", m / "newdb"], m / "newdb"),
        "db-add": (["db", "add", m / "db", "--builtin", "tank_t1", "truck_k1"], m / "db"),
        "db-render": (["db", "render", m / "db", "--job", "k", *render], m / "db"),
        "db-features": (["db", "features", m / "db", "--job", "j"], m / "db"),
    }


def _snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir")
            for p in sorted(root.rglob("*"))}


def _fill(m: Path, free: int) -> None:
    """Fill the tmpfs, then give back ``free`` bytes."""
    import os

    fd = os.open(m / "filler", os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        for block in (65536, 4096, 1):
            try:
                while os.write(fd, b"\0" * block):
                    pass
            except OSError:
                pass
    finally:
        os.close(fd)
    if free:
        size = (m / "filler").stat().st_size
        with open(m / "filler", "r+b") as fh:
            fh.truncate(max(0, size - free))


@pytest.mark.parametrize("free", [0, 200_000])
@pytest.mark.parametrize("earlier", [False, True], ids=["new", "earlier-output"])
@pytest.mark.parametrize("name", ["simulate", "calibrate", "convert-calib", "rectify", "match", "reconstruct",
                                  "triangulate", "stitch", "decamo", "features", "render", "bank-train",
                                  "bank-eval", "capture", "demo", "db-init", "db-add", "db-render",
                                  "db-features"])
def test_disk_full(mnt, inputs, trigger, name, earlier, free, capsys):
    for p in list(mnt.iterdir()):
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    argv, out = _cases(inputs, mnt)[name]
    argv = [str(a).replace("{trigger}", trigger) for a in argv]
    if name.startswith("db-") and name != "db-init":
        shutil.copytree(inputs["d"] / "db", out)
    elif earlier:  # an earlier output where this run writes: it must survive
        if out.suffix:
            out.write_bytes(b"an earlier output\n")
        else:
            out.mkdir()
            (out / "earlier.txt").write_text("an earlier output\n")
    _fill(mnt, free)
    before = _snapshot(mnt)
    capsys.readouterr()
    rc = _cli(*argv)
    err = capsys.readouterr().err.strip().splitlines()
    after = _snapshot(mnt)
    (mnt / "filler").unlink()
    if rc == 0:  # it fitted in the space given (a small output and some free space)
        assert free > 0 and out.exists(), (name, err)
        return
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("prism3d "), err
    if name in ("db-render", "db-features"):  # resumable jobs keep their whole finished parts
        from prism3d.datasets.database.db import verify_db

        assert set(before) <= set(after)
        assert verify_db(out, check_hashes=True) == []
        return
    assert after == before
