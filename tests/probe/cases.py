"""The bad-input probe's case list (issue 27; the survey and ATR commands added by issue 40),
reproducible from its description.

Per command and per input argument: missing, empty, a directory, garbage bytes, a
truncated valid file, wrong shape, NaN/inf values, absurd sizes (headers claiming
60000x60000 pixels or 300 M points, a zipped 20000^2 array: a decompression bomb),
negative/zero numbers; per output: an existing folder, an existing file, a parent that
is a regular file, a read-only place, a missing parent folder, a suffix that does not
match the format, two outputs naming one file.

:func:`build_fixtures` writes the valid inputs and the bad files once (~40 s, ~25 s of it the
survey and ATR inputs of issue 40: a flight, its survey, a tiny aerial recogniser);
:func:`cases` turns them into :class:`Case` rows. A case runs in a fresh, empty work
folder (its cwd): relative paths in ``argv`` are outputs there, ``{fx}`` is the
fixture folder (never written: the runners check it), ``{trigger}`` a running
simulated trigger controller. ``setup`` lists what is put in the work folder first.

Read-only places: we run as root, so ``chmod`` does not stop a write. The read-only
output is a path under ``/sys`` (sysfs refuses new names even to root: EPERM/EACCES),
and separately a path whose parent is a regular file (ENOTDIR).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import re
import shutil
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np

#: A path sysfs refuses to create, even for root (our "read-only folder").
READ_ONLY_DIR = "/sys/prism3d_probe_read_only"

#: What a case may exit with: "2" a refusal; "0or2" a correct result or a refusal;
#: "0or1or2" also the documented exit 1 (``db verify`` listing problems, a render or
#: features job with a failed unit, ``demo`` with a failed stage).
EXPECT_CODES = {"2": (2,), "0or2": (0, 2), "0or1or2": (0, 1, 2)}


@dataclasses.dataclass(frozen=True)
class Case:
    id: str
    argv: tuple[str, ...]
    expect: str = "2"
    outputs: tuple[str, ...] = ()
    protect: tuple[str, ...] = ()
    #: (relative path, "mkdir" | "file" | "copy:FIXTURE_RELPATH") made before the run
    setup: tuple[tuple[str, str], ...] = ()
    #: "shared_data" (skipped when absent) or "trigger" (needs a simulated controller)
    needs: str | None = None

    def resolve(self, fx: Path | str, trigger: str = "", data: Path | str | None = None) -> list[str]:
        """``argv`` with ``{fx}``, ``{trigger}`` and ``{data}`` (../shared/data) filled in."""
        data = str(data or shared_data_dir() or "/nonexistent_shared_data")
        return [a.replace("{fx}", str(fx)).replace("{trigger}", trigger).replace("{data}", data) for a in self.argv]


# --------------------------------------------------------------------------- helpers
def shared_data_dir() -> Path | None:
    env = os.environ.get("PRISM3D_TEST_DATA")
    for c in ([Path(env)] if env else []) + [Path(__file__).resolve().parents[2].parent / "shared" / "data"]:
        if c.is_dir():
            return c
    return None


def prepare_work(case: Case, work: Path, fx: Path) -> None:
    """Make ``case.setup`` in the (empty) work folder."""
    for rel, spec in case.setup:
        p = work / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        if spec == "mkdir":
            p.mkdir(parents=True, exist_ok=True)
            (p / "keep.txt").write_text("an existing file that must survive\n")
        elif spec == "file":
            p.write_text("an existing file\n")
        elif spec.startswith("copy:"):
            src = fx / spec[5:]
            if src.is_dir():
                shutil.copytree(src, p, symlinks=True)
            else:
                shutil.copy2(src, p)
        else:  # pragma: no cover - a mistake in this file
            raise ValueError(spec)


def snapshot(root: Path, *, hashes: bool = True) -> dict[str, str]:
    """Relative path -> content hash (files), "dir" (folders), "link" (symlinks)."""
    out: dict[str, str] = {}
    if not root.exists():
        return out
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        for n in dirnames:
            out[str((d / n).relative_to(root))] = "dir"
        for n in filenames:
            p = d / n
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif hashes:
                out[rel] = file_hash(p)
            else:
                st = p.stat()
                out[rel] = f"{st.st_size}:{st.st_mtime_ns}"
    return out


def file_hash(p: Path) -> str:
    h = hashlib.sha1()
    with open(p, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def diff_snapshots(before: dict[str, str], after: dict[str, str]) -> list[str]:
    new = sorted(set(after) - set(before))
    gone = sorted(set(before) - set(after))
    changed = sorted(k for k in set(before) & set(after) if before[k] != after[k])
    return [f"new {k}" for k in new] + [f"removed {k}" for k in gone] + [f"changed {k}" for k in changed]


# --------------------------------------------------------------------------- fixtures
def outcome_problems(case: Case, rc: int | str, lines: list[str], work: Path, before: dict[str, str],
                     fx: Path, fx_before: dict[str, str], protect: dict[str, str]) -> list[str]:
    """What is wrong with one run of ``case`` (both runners judge alike): the exit code,
    exactly one ``prism3d ...`` stderr line on exit 2, the work folder unchanged after a
    failure, the fixtures and the ``protect`` files (name -> hash) untouched."""
    problems = []
    if rc not in EXPECT_CODES[case.expect]:
        problems.append(f"exit {rc} (expected {case.expect})")
    if rc == 2 and (len(lines) != 1 or not lines[0].startswith(("prism3d ", "prism3d:"))):  # "prism3d:" global options
        problems.append(f"exit 2 with {len(lines)} stderr lines: {lines[:3]}")
    if rc != 0:
        changes = diff_snapshots(before, snapshot(work))
        if changes:
            problems.append(f"exit {rc} but the work folder changed: {changes[:5]}")
    fx_changes = diff_snapshots(fx_before, snapshot(fx, hashes=False))
    if fx_changes:
        problems.append(f"the input fixtures changed: {fx_changes[:5]}")
    for p, h in protect.items():
        if not (work / p).is_file() or file_hash(work / p) != h:
            problems.append(f"protected file {p} changed or removed")
    return problems


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png_claiming(w: int, h: int) -> bytes:
    """A PNG whose header claims w x h RGB pixels, with a few bytes of data."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
            + _png_chunk(b"IDAT", zlib.compress(b"\0" * 64)) + _png_chunk(b"IEND", b""))


def _npz_bomb(path: Path, key: str = "a", n: int = 20000, dtype: str = "<f4") -> None:
    """A zipped n x n array of zeros: ~1.6 GB inflated from a few MB."""
    header = {"descr": dtype, "fortran_order": False, "shape": (n, n)}
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    row = b"\0" * (n * np.dtype(dtype).itemsize)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
            f.write(buf.getvalue())
            for _ in range(n):
                f.write(row)


def _replace_matrix(yaml_text: str, name: str, rows: int, cols: int, data: str) -> str:
    """Swap matrix ``name`` of an OpenCV FileStorage text for another."""
    lines = yaml_text.splitlines(keepends=True)
    out, skip = [], False
    for line in lines:
        if line.startswith(f"{name}:"):
            out.append(f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {data} ]\n")
            skip = True
            continue
        if skip:
            if line.startswith(" ") or not line.strip():
                continue
            skip = False
        out.append(line)
    return "".join(out)


def build_fixtures(root: Path) -> dict[str, Path]:
    """Write the valid inputs and the bad files under ``root`` (~40 s); return named paths."""
    import warnings

    from prism3d.capture.rig import paper_rig
    from prism3d.cli import main
    from prism3d.io.images import write_image
    from prism3d.io.pfm import write_pfm
    from prism3d.io.ply import write_ply

    root.mkdir(parents=True, exist_ok=True)

    def run(*args: object) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rc = main(["--quiet", *map(str, args)])
        if rc != 0:
            raise RuntimeError(f"fixture command failed: {args}")

    paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4).save(root / "rig.yaml")
    run("simulate", "plate", root / "plate", "--rig", root / "rig.yaml", "--supersample", "1")
    run("simulate", "calib", root / "cal", "--rig", root / "rig.yaml", "--supersample", "1", "--views", "3")
    run("rectify", root / "plate/shot.png", "--calib", root / "rig.yaml", "-o", root / "rect")
    run("reconstruct", root / "plate/shot.png", "--calib", root / "rig.yaml", "-o", root / "scan.ply")
    with np.load(root / "plate/truth.npz") as t:
        disp = t["disparity_rect"].astype(np.float32)
        depth = t["depth_left_mm"].astype(np.float32)
    write_pfm(root / "disp.pfm", disp)
    np.save(root / "depth.npy", depth)
    run("bank", "train", "--targets", "tank_t1", "jet_j1", "-o", root / "bank.npz", "--azimuth", "0:360:90",
        "--elevation", "20:20:1", "--size", "32", "--no-camouflage", "--scenes", "0")
    run("db", "init", root / "db")
    run("db", "add", root / "db", "--builtin", "tank_t1")
    run("db", "render", root / "db", "--job", "j", "--azimuth", "0:90:90", "--elevation", "20:20:1",
        "--range", "3000", "--size", "32")
    # two small overlapping patches for stitch (a known motion)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-100.0, 100.0, (1500, 2))
    z = 600.0 + 15.0 * np.sin(xy[:, 0] / 17.0) * np.cos(xy[:, 1] / 23.0)
    P = np.c_[xy, z]
    N = np.tile([0.0, 0.0, -1.0], (len(P), 1))
    write_ply(root / "a.ply", P, normals=N)
    c, s = np.cos(np.radians(3.0)), np.sin(np.radians(3.0))
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    write_ply(root / "b.ply", P @ R.T + [4.0, -2.0, 3.0], normals=N @ R.T)
    (root / "box.obj").write_text(
        "v 0 0 0\nv 1000 0 0\nv 1000 500 0\nv 0 500 0\nv 0 0 300\nv 1000 0 300\nv 1000 500 300\nv 0 500 300\n"
        "f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n")
    (root / "calib.txt").write_text(
        "cam0=[1000 0 320; 0 1000 240; 0 0 1]\ncam1=[1000 0 330; 0 1000 240; 0 0 1]\n"
        "doffs=10\nbaseline=120.5\nwidth=640\nheight=480\nndisp=128\n")
    (root / "cloud.pcd").write_bytes(
        b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 4\nHEIGHT 1\n"
        b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n0 0 600\n100 0 600\n0 100 610\n100 100 620\n")

    bad = root / "bad"
    bad.mkdir()
    valid = {"png": root / "plate/shot.png", "yaml": root / "rig.yaml", "txt": root / "calib.txt",
             "pfm": root / "disp.pfm", "ply": root / "scan.ply", "pcd": root / "cloud.pcd",
             "obj": root / "box.obj", "npz": root / "bank.npz", "npy": root / "depth.npy"}
    _generic_bad_files(bad, valid)
    (bad / "garbage.tiff").write_bytes(b"II*\x00garbage")
    # images
    write_image(bad / "grey10.png", np.full((10, 10), 128, np.uint8))
    write_image(bad / "rgb_1x1.png", np.zeros((1, 1, 3), np.uint8))
    write_image(bad / "half_shot.png", np.full((486, 324, 3), 90, np.uint8))
    (bad / "claims_60000.png").write_bytes(_png_claiming(60000, 60000))
    (bad / "claims_1x1e9.png").write_bytes(_png_claiming(1, 1_000_000_000))
    # a real, decodable 20000 x 20000 grey PNG (400 MP, ~400 KB): a decompression bomb
    raw = zlib.compressobj(9)
    line = b"\0" + b"\0" * 20000
    body = b"".join(raw.compress(line) for _ in range(20000)) + raw.flush()
    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 0, 0, 0, 0)
    (bad / "bomb_20000.png").write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
                                         + _png_chunk(b"IDAT", body) + _png_chunk(b"IEND", b""))
    # calibration YAML
    rig = (root / "rig.yaml").read_text()
    k = "1276.75, 0., 161.5, 0., 1276.75, 242.5, 0., 0., 1."
    (bad / "k1_2x2.yaml").write_text(_replace_matrix(rig, "K1", 2, 2, "1276.75, 0., 0., 1276.75"))
    (bad / "k1_nan.yaml").write_text(_replace_matrix(rig, "K1", 3, 3, k.replace("1276.75", ".nan", 1)))
    (bad / "k1_inf.yaml").write_text(_replace_matrix(rig, "K1", 3, 3, k.replace("1276.75", ".inf", 1)))
    (bad / "k1_negative.yaml").write_text(_replace_matrix(rig, "K1", 3, 3, k.replace("1276.75", "-1276.75")))
    (bad / "k1_zero.yaml").write_text(_replace_matrix(rig, "K1", 3, 3, k.replace("1276.75", "0.")))
    (bad / "t_nan.yaml").write_text(_replace_matrix(rig, "T", 3, 1, ".nan, 0., 15.6"))
    (bad / "t_zero.yaml").write_text(_replace_matrix(rig, "T", 3, 1, "0., 0., 0."))
    (bad / "t_1e300.yaml").write_text(_replace_matrix(rig, "T", 3, 1, "-1e300, 0., 15.6"))
    (bad / "d1_huge.yaml").write_text(_replace_matrix(rig, "D1", 5, 1, "1e6, 0., 0., 0., 0."))
    (bad / "r_not_rotation.yaml").write_text(_replace_matrix(rig, "R", 3, 3, "2., 0., 0., 0., 2., 0., 0., 0., 2."))
    (bad / "sensor_60000.yaml").write_text(rig.replace("data: [ 648, 486 ]", "data: [ 60000, 60000 ]"))
    (bad / "sensor_zero.yaml").write_text(rig.replace("data: [ 648, 486 ]", "data: [ 0, 0 ]"))
    (bad / "schema_99.yaml").write_text(rig.replace("schema_version: 1", "schema_version: 99"))
    (bad / "header_only.yaml").write_text("%YAML:1.0\n---\n")
    (bad / "no_k2.yaml").write_text(_replace_matrix(rig, "K2", 3, 3, k).replace("K2:", "K9:"))
    # Middlebury calib.txt
    txt = (root / "calib.txt").read_text()
    (bad / "calib_nan.txt").write_text(txt.replace("baseline=120.5", "baseline=nan"))
    (bad / "calib_inf_focal.txt").write_text(txt.replace("cam0=[1000", "cam0=[inf"))
    (bad / "calib_neg_width.txt").write_text(txt.replace("width=640", "width=-640"))
    (bad / "calib_60000.txt").write_text(txt.replace("width=640", "width=60000").replace("height=480", "height=60000"))
    (bad / "calib_no_cam1.txt").write_text("\n".join(ln for ln in txt.splitlines() if not ln.startswith("cam1")))
    # PFM
    write_pfm(bad / "pfm_10x10.pfm", np.ones((10, 10), np.float32))
    write_pfm(bad / "pfm_nan.pfm", np.full_like(disp, np.nan))
    write_pfm(bad / "pfm_inf.pfm", np.full_like(disp, np.inf))
    write_pfm(bad / "pfm_negative.pfm", -np.abs(np.nan_to_num(disp, nan=1.0)))
    write_pfm(bad / "pfm_tiny_disp.pfm", np.full_like(disp, 1e-30))
    (bad / "pfm_claims_60000.pfm").write_bytes(b"Pf\n60000 60000\n-1\n" + b"\0" * 64)
    (bad / "pfm_negative_size.pfm").write_bytes(b"Pf\n-5 -5\n-1\n" + b"\0" * 64)
    # PLY scans
    (bad / "ply_no_vertices.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                              b"property float y\nproperty float z\nend_header\n")
    (bad / "ply_nan.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                      b"property float y\nproperty float z\nend_header\nnan nan nan\nnan 1 2\n1 nan 3\n")
    (bad / "ply_inf.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                      b"property float y\nproperty float z\nend_header\ninf 0 0\n0 -inf 0\n0 0 inf\n")
    (bad / "ply_one_point.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                            b"property float y\nproperty float z\nend_header\n1 2 3\n")
    (bad / "ply_claims_1e9.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
                                             b"property float x\nproperty float y\nproperty float z\nend_header\n"
                                             + b"\0" * 120)
    (bad / "ply_dup_property.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                               b"property float x\nproperty float z\nend_header\n1 2 3\n")
    (bad / "ply_coords_1e30.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                                              b"property float y\nproperty float z\nend_header\n"
                                              b"0 0 0\n1e30 0 0\n0 1e30 0\n0 0 1e30\n")
    # PCD
    hdr = b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
    (bad / "pcd_claims_300M.pcd").write_bytes(hdr + b"WIDTH 300000000\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
                                             b"POINTS 300000000\nDATA binary\n" + b"\0" * 48)
    (bad / "pcd_nan.pcd").write_bytes(hdr + b"WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n"
                                      b"nan nan nan\nnan nan nan\nnan nan nan\n")
    (bad / "pcd_lzf_lies.pcd").write_bytes(hdr + b"WIDTH 100000000\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
                                           b"POINTS 100000000\nDATA binary_compressed\n"
                                           + struct.pack("<II", 16, 1_200_000_000) + b"\0" * 16)
    # OBJ meshes
    (bad / "obj_no_faces.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    (bad / "obj_nan.obj").write_text("v nan 0 0\nv 1 nan 0\nv 0 1 nan\nf 1 2 3\n")
    (bad / "obj_inf.obj").write_text("v inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (bad / "obj_bad_index.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 999999\n")
    (bad / "obj_degenerate.obj").write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
    (bad / "obj_1e30.obj").write_text("v 0 0 0\nv 1e30 0 0\nv 0 1e30 0\nv 0 0 1e30\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    # NPZ / NPY
    _npz_bomb(bad / "bomb_20000.npz")
    _npz_bomb(bad / "bomb_depth.npz", key="depth_left_mm")
    np.save(bad / "depth_10x10.npy", np.ones((10, 10), np.float32))
    np.save(bad / "depth_nan.npy", np.full_like(depth, np.nan))
    np.save(bad / "depth_inf.npy", np.full_like(depth, np.inf))
    np.save(bad / "depth_negative.npy", -np.ones_like(depth))
    np.save(bad / "depth_3d.npy", np.ones((4, 4, 4), np.float32))
    np.save(bad / "depth_object.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with open(bad / "npy_claims_60000.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (60000, 60000)})
        f.write(b"\0" * 64)
    with np.load(root / "bank.npz", allow_pickle=False) as b:
        arrays = {k: b[k] for k in b.files}
    nanb = {k: (np.full_like(v, np.nan) if v.dtype.kind in "fc" and v.size > 16 else v) for k, v in arrays.items()}
    np.savez(bad / "bank_nan.npz", **nanb)
    np.savez(bad / "bank_no_meta.npz", **{k: v for k, v in arrays.items() if "meta" not in k})
    np.savez(bad / "npz_wrong_keys.npz", x=np.zeros(3))
    # database: a folder that is not one, a db with a garbage targets table
    (bad / "not_a_db").mkdir()
    (bad / "not_a_db" / "notes.txt").write_text("hello\n")
    shutil.copytree(root / "db", bad / "db_garbage_targets", symlinks=True)
    (bad / "db_garbage_targets" / "targets.parquet").write_bytes(b"\x00garbage")
    shutil.copytree(root / "db", bad / "db_garbage_yaml", symlinks=True)
    (bad / "db_garbage_yaml" / "db.yaml").write_text("schema_version: [unclosed\n")
    # misc
    (bad / "blocker").write_text("a regular file where a folder is expected\n")
    _build_survey_fixtures(root, run)
    return {"root": root}


def _generic_bad_files(bad: Path, valid: dict[str, Path]) -> None:
    """empty, dir, garbage and truncated (the first half of a valid one) files per suffix."""
    for ext, src in valid.items():
        (bad / f"empty.{ext}").write_bytes(b"")
        (bad / f"dir.{ext}").mkdir()
        (bad / f"garbage.{ext}").write_bytes(b"\x00\xff garbage \x80\x81\n" * 7)
        data = src.read_bytes()
        (bad / f"truncated.{ext}").write_bytes(data[: len(data) // 2])


# ------------------------------------------------------------ survey and ATR fixtures (issue 40)
#: the fixture flight's frames (6 of 480 x 360 px from 40 m on two lines); cases use the first three
FLIGHT_FRAMES = tuple(f"IMG_{k:04d}.JPG" for k in range(6))
_GARBAGE = b"\x00\xff garbage \x80\x81\n" * 7


def _with_camera(text: str, w: int, h: int, k: str | None = None, dist: str | None = None) -> str:
    """The flight's camera.yaml stating another image size, camera matrix or distortion."""
    out = re.sub(r"(?m)^image_width: .*$", f"image_width: {w}", text)
    out = re.sub(r"(?m)^image_height: .*$", f"image_height: {h}", out)
    if k is not None:
        out = _replace_matrix(out, "camera_matrix", 3, 3, k)
    if dist is not None:
        out = _replace_matrix(out, "distortion_coefficients", 5, 1, dist)
    return out


def _sparse_geotiff(path: Path, n: int, bands: int, dtype: str, meta: dict) -> None:
    """An n x n GeoTIFF of ``bands`` whose tiles are all absent (a few hundred bytes that
    read back as n * n * bands values: a decompression bomb) on ``meta``'s origin and CRS."""
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=bands, dtype=dtype, tiled=True,
                       blockxsize=512, blockysize=512, compress="deflate", sparse_ok=True,
                       crs=meta["crs_wkt"], transform=from_origin(meta["west"], meta["north"], meta["gsd"],
                                                                  meta["gsd"])):
        pass


def _folder_variant(bad: Path, src: Path, name: str, names: tuple[str, ...], changes: dict) -> None:
    """``bad/name``: the files ``names`` of ``src``, with ``changes`` (file -> None: left
    out, "dir": a folder, bytes/str: its content, a Path: copied from, a callable: writes it)."""
    d = bad / name
    d.mkdir()
    for n in names:
        v = changes.get(n, src / n)
        if v is None:
            continue
        if isinstance(v, str) and v == "dir":
            (d / n).mkdir()
        elif isinstance(v, bytes):
            (d / n).write_bytes(v)
        elif isinstance(v, str):
            (d / n).write_text(v)
        elif isinstance(v, Path):
            shutil.copy2(v, d / n)
        else:
            v(d / n)


def _build_survey_fixtures(root: Path, run) -> None:
    """The drone-survey and ATR inputs: a small flight and its survey (~12 s), a tiny aerial
    recogniser (~9 s), an intensity-channel bank, a scene folder made of the plate shot,
    a short video, and their bad variants."""
    import json
    import warnings

    import cv2
    import pyproj

    from prism3d.io.geo import read_geotiff, write_geotiff
    from prism3d.io.images import write_image

    bad = root / "bad"
    flight, survey = root / "flight", root / "survey"
    run("simulate", "flight", flight, "--frames", "6", "--size", "480x360", "--altitude", "40", "--no-depth",
        "--seed", "2")
    run("survey", *[flight / n for n in FLIGHT_FRAMES], "--calib", flight / "camera.yaml", "--gps",
        flight / "geoinfo.txt", "-o", survey)
    run("bank", "train", "--targets", "tank_t1", "jet_j1", "-o", root / "bank_intensity.npz", "--azimuth",
        "0:360:90", "--elevation", "20:20:1", "--size", "32", "--no-camouflage", "--scenes", "0", "--channel",
        "intensity")
    with warnings.catch_warnings():  # a tiny aerial recogniser: 2 patches, no mining rounds
        warnings.simplefilter("ignore")
        from prism3d.atr.aerial_train import AerialTrainOptions, train_aerial
        from prism3d.datasets.database.resolve import resolve_targets
        from prism3d.datasets.jobs.recognisers import aerial_negatives

        train_aerial(resolve_targets(["car"], scale="full"), aerial_negatives(["car"])[:3], AerialTrainOptions(
            patches=2, mining_patches=1, mining_rounds=0, calibration_patches=1, random_negatives=2,
            positive_views=0)).save(root / "aerial.npz")

    # frames: without EXIF (no GPS, no focal length), a short video, the left view of the plate
    (root / "nogps").mkdir()
    imgs = [cv2.imread(str(flight / n)) for n in FLIGHT_FRAMES[:3]]
    for n, img in zip(FLIGHT_FRAMES, imgs):
        cv2.imwrite(str(root / "nogps" / n), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    for name, frames in (("flight.avi", imgs), ("bad/one_frame.avi", imgs[:1])):
        vw = cv2.VideoWriter(str(root / name), cv2.VideoWriter_fourcc(*"MJPG"), 1.0, (480, 360))
        for img in frames:
            vw.write(img)
        vw.release()
    shot = cv2.imread(str(root / "plate/shot.png"))
    cv2.imwrite(str(root / "plate_left.png"), shot[:, : shot.shape[1] // 2])

    # a scene folder as 'simulate field' writes one, from the plate shot (detect takes ~1 s)
    target = {"instance": 0, "class": "tank", "name": "tank_t1", "confuser": False, "box_rc": [150, 60, 330, 260],
              "xyz_mm": [0.0, 0.0, 1250.0], "radius_mm": 150.0, "range_mm": 1250.0, "heading_deg": 30.0,
              "zone": "land", "visible_fraction": 1.0, "difficult": False, "object_index": 1}
    confuser = {**target, "instance": 1, "class": "crate", "name": "crate", "confuser": True,
                "box_rc": [20, 20, 90, 120], "object_index": 2}
    truth = {"schema_version": 1, "units": "mm", "camera": "left view of the prism rig, OpenCV frame",
             "options": {"targets": 1, "confusers": 1, "classes": ["tank_t1", "jet_j1"], "seed": 0},
             "T_world_rig": np.eye(4).tolist(), "n_objects": 2, "targets": [target, confuser]}
    scene = root / "scene"
    scene.mkdir()
    shutil.copy2(root / "plate/shot.png", scene / "shot.png")
    shutil.copy2(root / "rig.yaml", scene / "rig.yaml")
    (scene / "truth.json").write_text(json.dumps(truth, indent=1))

    _generic_bad_files(bad, {"jpg": flight / FLIGHT_FRAMES[0], "csv": flight / "geoinfo.txt",
                             "tif": survey / "ndsm.tif", "json": survey / "poses.json", "avi": root / "flight.avi"})
    # the generic truncated.csv is a tab table cut in half; a comma-separated one as well
    rows = [ln.rstrip("\t").split("\t") for ln in (flight / "geoinfo.txt").read_text().splitlines()[1:]]
    head, body = rows[0], rows[1:]

    def table(rs: list[list[str]], header: list[str] | None = None) -> str:
        return "#Rev: sensefly/geoinfo/2\n" + "\n".join("\t".join(r) for r in [header or head, *rs]) + "\n"

    def col(r: list[str], i: int, v: str) -> list[str]:
        return r[:i] + [v] + r[i + 1:]

    (bad / "gps_comma.csv").write_text("fileName,latitude,longitude,altitude\n" + "".join(
        f"{r[0]},{r[1]},{r[2]},{r[4]}\n" for r in body))
    (bad / "gps_nan.txt").write_text(table([col(body[0], 1, "nan"), *body[1:]]))
    (bad / "gps_inf.txt").write_text(table([col(body[0], 2, "inf"), *body[1:]]))
    (bad / "gps_lat_91.txt").write_text(table([col(body[0], 1, "91.0"), *body[1:]]))
    (bad / "gps_no_altitude.txt").write_text(table([r[:3] + r[5:] for r in body], head[:3] + head[5:]))
    (bad / "gps_other_names.txt").write_text(table([col(r, 0, r[0].replace("IMG_", "DSC_")) for r in body]))
    (bad / "gps_duplicate_row.txt").write_text(table([body[0], *body]))
    (bad / "gps_same_position.txt").write_text(table([[r[0], *body[0][1:]] for r in body]))
    (bad / "gps_1000km_apart.txt").write_text(table([col(r, 1, f"{float(r[1]) + 9.0 * k:.10f}")
                                                     for k, r in enumerate(body)]))
    (bad / "gps_altitude_1e12.txt").write_text(table([col(col(r, 3, "1e12"), 4, "1e12") for r in body]))
    (bad / "gps_altitude_negative.txt").write_text(table([col(col(r, 3, "-1e6"), 4, "-1e6") for r in body]))
    (bad / "gps_header_only.txt").write_text(table([]))
    (bad / "gps_missing_frames.txt").write_text(table(body[3:]))
    (bad / "gps_no_names.txt").write_text(table([col(r, 0, "") for r in body]))
    (bad / "gps_latin1.txt").write_bytes(table(body).replace("IMG_0000", "IMG_\xe9000").encode("latin-1"))

    # camera calibrations of the survey (the flight's camera.yaml changed)
    cam = (flight / "camera.yaml").read_text()
    f = re.search(r"data: \[ ([0-9.e+-]+),", cam).group(1)
    kk = f"{f}, 0., 239.5, 0., {f}, 179.5, 0., 0., 1."
    cams = {"nan": _with_camera(cam, 480, 360, kk.replace(f, ".nan", 1)),
            "inf": _with_camera(cam, 480, 360, kk.replace(f, ".inf", 1)),
            "negative_focal": _with_camera(cam, 480, 360, kk.replace(f, "-" + f)),
            "zero_focal": _with_camera(cam, 480, 360, kk.replace(f, "0.")),
            "focal_1e300": _with_camera(cam, 480, 360, kk.replace(f, "1e300")),
            "dist_1e6": _with_camera(cam, 480, 360, None, "1e6, 0., 0., 0., 0."),
            "dist_nan": _with_camera(cam, 480, 360, None, ".nan, 0., 0., 0., 0."),
            "centre_1e6": _with_camera(cam, 480, 360, kk.replace("239.5", "1e6")),
            "other_size": _with_camera(cam, 4000, 3000),
            "size_zero": _with_camera(cam, 0, 0),
            "size_negative": _with_camera(cam, -480, -360),
            "k_2x2": _replace_matrix(cam, "camera_matrix", 2, 2, f"{f}, 0., 0., {f}"),
            "no_camera_matrix": cam.replace("camera_matrix:", "not_a_matrix:"),
            "no_size": re.sub(r"(?m)^image_(width|height): .*\n", "", cam),
            "truncated": cam[: len(cam) // 2],
            # for the frames that are not photographs: a camera of their size
            "10x10": _with_camera(cam, 10, 10, "7., 0., 4.5, 0., 7., 4.5, 0., 0., 1."),
            "1x1": _with_camera(cam, 1, 1, "1., 0., 0., 0., 1., 0., 0., 0., 1."),
            "60000x60000": _with_camera(cam, 60000, 60000, "42000., 0., 29999.5, 0., 42000., 29999.5, 0., 0., 1."),
            "20000x20000": _with_camera(cam, 20000, 20000, "14000., 0., 9999.5, 0., 14000., 9999.5, 0., 0., 1.")}
    for kind, text in cams.items():
        (bad / f"cam_{kind}.yaml").write_text(text)

    # frames that are not the flight's photographs
    write_image(bad / "IMG_small.JPG", cv2.resize(imgs[1], (240, 180))[..., ::-1])
    shutil.copy2(flight / FLIGHT_FRAMES[0], bad / "IMG_0000_copy.JPG")
    rng = np.random.default_rng(7)
    pairs = {"grey10": [np.full((10, 10), 128, np.uint8)] * 2, "1x1": [np.zeros((1, 1, 3), np.uint8)] * 2,
             "uniform_grey": [np.full((360, 480, 3), 128, np.uint8)] * 2,
             "noise": [rng.integers(0, 256, (360, 480, 3), dtype=np.uint8) for _ in range(2)]}
    for kind, images in pairs.items():
        (bad / f"pair_{kind}").mkdir()
        for n, img in zip("ab", images):
            write_image(bad / f"pair_{kind}" / f"{n}.{'jpg' if img.shape[0] > 10 else 'png'}", img)
    for kind, src in (("claims_60000", bad / "claims_60000.png"), ("bomb_20000", bad / "bomb_20000.png")):
        (bad / f"pair_{kind}").mkdir()
        for n in "ab":
            shutil.copy2(src, bad / f"pair_{kind}" / f"{n}.png")
    (bad / "pair_truncated").mkdir()
    for n in FLIGHT_FRAMES[:2]:
        data = (flight / n).read_bytes()
        (bad / "pair_truncated" / n).write_bytes(data[: len(data) // 2])
    (bad / "empty_frames").mkdir()
    (bad / "one_frame").mkdir()
    shutil.copy2(flight / FLIGHT_FRAMES[0], bad / "one_frame" / FLIGHT_FRAMES[0])
    (bad / "vehicles.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [139.0427, 37.5435]},
         "properties": {"class": "car", "score": 0.9}}]}))

    # survey folders, each with one product changed (what survey-detect reads)
    sv_files = ("poses.json", "ndsm.tif", "ground.tif", "ortho.tif")
    doc = json.loads((survey / "poses.json").read_text())
    nd, mn = read_geotiff(survey / "ndsm.tif")
    gr, mg = read_geotiff(survey / "ground.tif")
    orth, mo = read_geotiff(survey / "ortho.tif")
    utm33 = pyproj.CRS.from_epsg(32633).to_wkt("WKT1_GDAL")

    def tif(a: np.ndarray, meta: dict, **over):
        m = {**meta, **over}
        return lambda p: write_geotiff(p, a, west=m["west"], north=m["north"], gsd=m["gsd"], crs_wkt=m["crs_wkt"],
                                       nodata=m["nodata"] if np.asarray(a).dtype.kind == "f" else None)

    def poses(**over) -> str:
        return json.dumps({**doc, **over}, indent=1)

    def half(p: Path) -> bytes:
        data = p.read_bytes()
        return data[: len(data) // 2]

    variants = {
        "poses_empty": {"poses.json": b""}, "poses_garbage": {"poses.json": _GARBAGE},
        "poses_truncated": {"poses.json": half(survey / "poses.json")}, "poses_list": {"poses.json": "[]"},
        "poses_no_keys": {"poses.json": "{}"}, "poses_is_dir": {"poses.json": "dir"},
        "poses_scale_unknown": {"poses.json": poses(scale="unknown", origin_lla=None)},
        "poses_origin_nan": {"poses.json": poses(origin_lla=[float("nan")] * 3)},
        "poses_origin_out_of_range": {"poses.json": poses(origin_lla=[123.0, 500.0, 0.0])},
        "poses_origin_short": {"poses.json": poses(origin_lla=[37.5])},
        "poses_origin_string": {"poses.json": poses(origin_lla="37.5 139.0")},
        "poses_origin_1e400": {"poses.json": poses(origin_lla=[37.5, 139.0, 0.0]).replace(
            '"origin_lla": [\n  37.5,', '"origin_lla": [\n  1e400,')},
        "poses_epsg_string": {"poses.json": poses(map_frame={**doc["map_frame"], "epsg": "EPSG:32654"})},
        "poses_epsg_4326": {"poses.json": poses(map_frame={**doc["map_frame"], "epsg": 4326})},
        "poses_epsg_999999": {"poses.json": poses(map_frame={**doc["map_frame"], "epsg": 999999})},
        "poses_epsg_other_zone": {"poses.json": poses(map_frame={**doc["map_frame"], "epsg": 32633})},
        "poses_map_frame_list": {"poses.json": poses(map_frame=[32654])},
        "poses_deep_nesting": {"poses.json": "[" * 200000 + "]" * 200000},
        "no_ndsm": {"ndsm.tif": None}, "ndsm_empty": {"ndsm.tif": b""}, "ndsm_garbage": {"ndsm.tif": _GARBAGE},
        "ndsm_truncated": {"ndsm.tif": half(survey / "ndsm.tif")}, "ndsm_is_dir": {"ndsm.tif": "dir"},
        "ndsm_is_the_ortho": {"ndsm.tif": survey / "ortho.tif"},
        "ndsm_all_nan": {"ndsm.tif": tif(np.full_like(nd, np.nan), mn)},
        "ndsm_inf": {"ndsm.tif": tif(np.where(np.isfinite(nd), np.inf, nd).astype(np.float32), mn)},
        "ndsm_1e30": {"ndsm.tif": tif(np.where(np.isfinite(nd), 1e30, nd).astype(np.float32), mn)},
        "ndsm_int16": {"ndsm.tif": tif(np.nan_to_num(nd).astype(np.int16), mn)},
        "ndsm_two_bands": {"ndsm.tif": tif(np.dstack([nd, nd]), mn)},
        "ndsm_other_grid": {"ndsm.tif": tif(nd, mn, west=mn["west"] + 10000.0)},
        "ndsm_no_crs": {"ndsm.tif": tif(nd, mn, crs_wkt=None)},
        "ndsm_cell_100m": {"ndsm.tif": tif(nd, mn, gsd=100.0), "ground.tif": tif(gr, mg, gsd=100.0)},
        "ndsm_bomb_20000": {"ndsm.tif": lambda p: _sparse_geotiff(p, 20000, 1, "float32", mn)},
        "ndsm_claims_60000": {"ndsm.tif": lambda p: _sparse_geotiff(p, 60000, 1, "float32", mn)},
        "no_ortho": {"ortho.tif": None}, "ortho_empty": {"ortho.tif": b""}, "ortho_garbage": {"ortho.tif": _GARBAGE},
        "ortho_truncated": {"ortho.tif": half(survey / "ortho.tif")},
        "ortho_is_the_ndsm": {"ortho.tif": survey / "ndsm.tif"},
        "ortho_grey": {"ortho.tif": tif(orth[..., 0].copy(), mo)},
        "ortho_other_grid": {"ortho.tif": tif(orth, mo, west=mo["west"] - 10000.0)},
        "ortho_other_crs": {"ortho.tif": tif(orth, mo, crs_wkt=utm33)},
        "ortho_half_gsd": {"ortho.tif": tif(np.ascontiguousarray(orth[::2, ::2]), mo, gsd=2 * mo["gsd"])},
        "ortho_bomb_20000": {"ortho.tif": lambda p: _sparse_geotiff(p, 20000, 3, "uint8", mo)},
        "no_ground": {"ground.tif": None}, "ground_garbage": {"ground.tif": _GARBAGE},
        "ground_other_grid": {"ground.tif": tif(np.ascontiguousarray(gr[10:]), mg, north=mg["north"] - 10 * mg["gsd"])},
        "only_poses": {"ndsm.tif": None, "ground.tif": None, "ortho.tif": None},
    }
    for kind, changes in variants.items():
        _folder_variant(bad, survey, f"survey_{kind}", sv_files, changes)
    (bad / "survey_empty").mkdir()

    # scene folders for bank eval-scenes
    sc_files = ("shot.png", "rig.yaml", "truth.json")

    def truth_with(**over) -> str:
        return json.dumps({**truth, **over}, indent=1)

    def one_target(**over) -> str:
        return truth_with(targets=[{**target, **over}])

    no_class = {k: v for k, v in target.items() if k != "class"}
    scenes = {
        "no_shot": {"shot.png": None}, "no_rig": {"rig.yaml": None}, "no_truth": {"truth.json": None},
        "shot_is_dir": {"shot.png": "dir"}, "shot_garbage": {"shot.png": _GARBAGE},
        "shot_grey10": {"shot.png": bad / "grey10.png"}, "shot_half_size": {"shot.png": bad / "half_shot.png"},
        "shot_claims_60000": {"shot.png": bad / "claims_60000.png"},
        "shot_bomb_20000": {"shot.png": bad / "bomb_20000.png"},
        "rig_garbage": {"rig.yaml": _GARBAGE}, "rig_k1_nan": {"rig.yaml": bad / "k1_nan.yaml"},
        "rig_sensor_60000": {"rig.yaml": bad / "sensor_60000.yaml"},
        "rig_is_a_camera_yaml": {"rig.yaml": flight / "camera.yaml"},
        "truth_empty": {"truth.json": b""}, "truth_garbage": {"truth.json": _GARBAGE},
        "truth_truncated": {"truth.json": truth_with()[: len(truth_with()) // 2]},
        "truth_list": {"truth.json": "[]"}, "truth_no_keys": {"truth.json": "{}"},
        "truth_targets_dict": {"truth.json": truth_with(targets={})},
        "truth_target_string": {"truth.json": truth_with(targets=["tank"])},
        "truth_target_no_class": {"truth.json": truth_with(targets=[no_class])},
        "truth_box_nan": {"truth.json": one_target(box_rc=[float("nan"), 0, 10, 10])},
        "truth_box_short": {"truth.json": one_target(box_rc=[1, 2])},
        "truth_box_reversed": {"truth.json": one_target(box_rc=[300, 260, 150, 60])},
        "truth_box_strings": {"truth.json": one_target(box_rc=["a", "b", "c", "d"])},
        "truth_box_1e300": {"truth.json": one_target(box_rc=[-1e300, -1e300, 1e300, 1e300])},
        "truth_xyz_nan": {"truth.json": one_target(xyz_mm=[float("nan")] * 3)},
        "truth_radius_negative": {"truth.json": one_target(radius_mm=-150.0)},
        "truth_no_targets_at_all": {"truth.json": truth_with(targets=[])},
        "truth_deep_nesting": {"truth.json": "[" * 200000 + "]" * 200000},
    }
    for kind, changes in scenes.items():
        _folder_variant(bad, scene, f"scene_{kind}", sc_files, changes)

    # aerial recognisers that are damaged or lie about themselves
    with np.load(root / "aerial.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays.pop("meta_json")).decode())

    def aerial(name: str, m: dict, arr: dict) -> None:
        np.savez(bad / name, meta_json=np.frombuffer(json.dumps(m).encode(), np.uint8), **arr)

    aerial("aerial_nan.npz", meta, {k: np.full_like(v, np.nan) for k, v in arrays.items()})
    aerial("aerial_schema_99.npz", {**meta, "schema_version": 99}, arrays)
    aerial("aerial_no_groups.npz", {**meta, "groups": []}, arrays)
    aerial("aerial_gsd_zero.npz", {**meta, "gsd_m": 0.0}, arrays)
    aerial("aerial_gsd_1e-6.npz", {**meta, "gsd_m": 1e-6}, arrays)
    aerial("aerial_channels_unknown.npz", {**meta, "channels": "x-ray"}, arrays)
    aerial("aerial_weights_wrong_shape.npz", meta, {k: (np.zeros(3, np.float32) if k.endswith("_weights") else v)
                                                    for k, v in arrays.items()})
    aerial("aerial_missing_arrays.npz", meta, {})


# --------------------------------------------------------------------------- case builders
_GENERIC = ("missing", "empty", "directory", "garbage", "truncated")

#: format -> {kind: bad file under {fx}/bad (or a path)}
_EXTRA: dict[str, dict[str, str]] = {
    "png": {"grey_10x10": "grey10.png", "rgb_1x1": "rgb_1x1.png", "half_shot": "half_shot.png",
            "claims_60000x60000": "claims_60000.png", "claims_1x1e9": "claims_1x1e9.png",
            "bomb_20000x20000": "bomb_20000.png", "tiff_garbage": "garbage.tiff"},
    "yaml": {"k1_2x2": "k1_2x2.yaml", "k1_nan": "k1_nan.yaml", "k1_inf": "k1_inf.yaml",
             "k1_negative": "k1_negative.yaml", "k1_zero": "k1_zero.yaml", "t_nan": "t_nan.yaml",
             "t_zero": "t_zero.yaml", "t_1e300": "t_1e300.yaml", "d1_huge": "d1_huge.yaml",
             "r_not_rotation": "r_not_rotation.yaml", "sensor_60000": "sensor_60000.yaml",
             "sensor_zero": "sensor_zero.yaml", "schema_99": "schema_99.yaml",
             "header_only": "header_only.yaml", "no_k2": "no_k2.yaml", "calib_txt_nan": "calib_nan.txt",
             "calib_txt_inf_focal": "calib_inf_focal.txt", "calib_txt_neg_width": "calib_neg_width.txt",
             "calib_txt_60000": "calib_60000.txt", "calib_txt_no_cam1": "calib_no_cam1.txt",
             "txt_garbage": "garbage.txt"},
    "pfm": {"wrong_size_10x10": "pfm_10x10.pfm", "nan": "pfm_nan.pfm", "inf": "pfm_inf.pfm",
            "negative": "pfm_negative.pfm", "tiny_1e-30": "pfm_tiny_disp.pfm",
            "claims_60000x60000": "pfm_claims_60000.pfm", "negative_size": "pfm_negative_size.pfm"},
    "ply": {"no_vertices": "ply_no_vertices.ply", "nan": "ply_nan.ply", "inf": "ply_inf.ply",
            "one_point": "ply_one_point.ply", "claims_1e9": "ply_claims_1e9.ply",
            "dup_property": "ply_dup_property.ply", "coords_1e30": "ply_coords_1e30.ply",
            "pcd_claims_300M": "pcd_claims_300M.pcd", "pcd_nan": "pcd_nan.pcd",
            "pcd_lzf_lies": "pcd_lzf_lies.pcd", "pcd_truncated": "truncated.pcd"},
    "obj": {"no_faces": "obj_no_faces.obj", "nan": "obj_nan.obj", "inf": "obj_inf.obj",
            "bad_index": "obj_bad_index.obj", "degenerate": "obj_degenerate.obj", "coords_1e30": "obj_1e30.obj",
            "ply_no_vertices": "ply_no_vertices.ply", "ply_claims_1e9": "ply_claims_1e9.ply"},
    "npz": {"bomb_20000x20000": "bomb_20000.npz", "nan_filters": "bank_nan.npz", "no_meta": "bank_no_meta.npz",
            "wrong_keys": "npz_wrong_keys.npz", "object_npy": "depth_object.npy"},
    "depth": {"wrong_shape_10x10": "depth_10x10.npy", "nan": "depth_nan.npy", "inf": "depth_inf.npy",
              "negative": "depth_negative.npy", "3d": "depth_3d.npy", "object_npy": "depth_object.npy",
              "npy_claims_60000": "npy_claims_60000.npy", "npz_bomb": "bomb_depth.npz:depth_left_mm",
              "npz_missing_key": "{fx}/plate/truth.npz:nokey", "npz_no_key": "{fx}/plate/truth.npz",
              "pfm_garbage": "garbage.pfm", "pfm_10x10": "pfm_10x10.pfm", "tiff_garbage": "garbage.tiff"},
}
_PHOTO_EXTRA = {k: _EXTRA["png"][k] for k in ("grey_10x10", "rgb_1x1", "claims_60000x60000", "claims_1x1e9",
                                                "bomb_20000x20000", "tiff_garbage")}
_EXTRA.update({
    # survey frames
    "jpg": {**_PHOTO_EXTRA, "other_size": "IMG_small.JPG", "ply_scan": "{fx}/scan.ply", "geojson": "vehicles.geojson",
            "geotiff_ortho": "{fx}/survey/ortho.tif", "video_garbage": "garbage.avi",
            "prism_shot": "{fx}/plate/shot.png"},
    # a survey's GPS position table
    "gps": {"nan": "gps_nan.txt", "inf": "gps_inf.txt", "lat_91": "gps_lat_91.txt",
            "no_altitude": "gps_no_altitude.txt", "other_names": "gps_other_names.txt",
            "duplicate_row": "gps_duplicate_row.txt", "same_position": "gps_same_position.txt",
            "1000km_apart": "gps_1000km_apart.txt", "altitude_1e12": "gps_altitude_1e12.txt",
            "altitude_negative": "gps_altitude_negative.txt", "header_only": "gps_header_only.txt",
            "missing_frames": "gps_missing_frames.txt", "no_names": "gps_no_names.txt", "latin1": "gps_latin1.txt",
            "comma_separated": "gps_comma.csv", "poses_json": "{fx}/survey/poses.json",
            "geojson": "vehicles.geojson", "jpeg": "{fx}/flight/IMG_0000.JPG", "middlebury_calib": "{fx}/calib.txt"},
    # a survey camera's calibration
    "cam": {**{k: f"cam_{k}.yaml" for k in ("nan", "inf", "negative_focal", "zero_focal", "focal_1e300", "dist_1e6",
                                            "dist_nan", "centre_1e6", "other_size", "size_zero", "size_negative",
                                            "k_2x2", "no_camera_matrix", "no_size")},
            "camera_truncated": "cam_truncated.yaml", "stereo_rig": "{fx}/rig.yaml",
            "middlebury_calib": "{fx}/calib.txt", "poses_json": "{fx}/survey/poses.json"},
    "avi": {"one_frame": "one_frame.avi", "a_png_instead": "{fx}/plate/shot.png"},
    # survey-detect's aerial recogniser
    "aerial": {**_EXTRA["npz"], **{k: f"aerial_{k}.npz" for k in (
        "nan", "schema_99", "no_groups", "gsd_zero", "gsd_1e-6", "channels_unknown", "weights_wrong_shape",
        "missing_arrays")}, "ground_bank": "{fx}/bank.npz", "ground_bank_intensity": "{fx}/bank_intensity.npz"},
})
_EXT = {"png": "png", "yaml": "yaml", "pfm": "pfm", "ply": "ply", "obj": "obj", "npz": "npz", "depth": "npy",
        "jpg": "jpg", "gps": "csv", "cam": "yaml", "avi": "avi", "aerial": "npz"}


def bad_files(fmt: str) -> dict[str, str]:
    """kind -> argument for a bad file of format ``fmt``."""
    ext = _EXT[fmt]
    out = {"missing": f"missing_input.{ext}", "empty": f"{{fx}}/bad/empty.{ext}",
           "directory": f"{{fx}}/bad/dir.{ext}", "garbage": f"{{fx}}/bad/garbage.{ext}",
           "truncated": f"{{fx}}/bad/truncated.{ext}"}
    for kind, name in _EXTRA[fmt].items():
        out[kind] = name if name.startswith("{fx}") else f"{{fx}}/bad/{name}"
    return out


def _sub(argv: list[str], i: int, value: str) -> tuple[str, ...]:
    a = list(argv)
    a[i] = value
    return tuple(a)


def _flag(argv: list[str], flag: str, value: str | None) -> tuple[str, ...]:
    """Set ``flag`` to ``value`` (replacing it if present; a bare flag when value is None)."""
    a = list(argv)
    if flag in a:
        i = a.index(flag)
        if value is None:
            return tuple(a)
        a[i + 1] = value
        return tuple(a)
    return tuple(a + [flag] + ([] if value is None else [value]))


class _Builder:
    def __init__(self) -> None:
        self.cases: list[Case] = []

    def add(self, id: str, argv, expect: str = "2", outputs=(), protect=(), setup=(), needs=None) -> None:
        self.cases.append(Case(id, tuple(argv), expect, tuple(outputs), tuple(protect), tuple(setup), needs))

    def files(self, prefix: str, base: list[str], i: int, fmt: str, outputs, *, ok: set[str] = frozenset(),
              only: set[str] | None = None, setup=()) -> None:
        """Every bad file of ``fmt`` at argv position ``i``; kinds in ``ok`` may succeed."""
        for kind, path in bad_files(fmt).items():
            if only is not None and kind not in only:
                continue
            self.add(f"{prefix}/{kind}", _sub(base, i, path), "0or2" if kind in ok else "2", outputs, setup=setup)

    def numbers(self, prefix: str, base: list[str], flag: str, values: dict[str, str], outputs, *,
                ok: set[str] = frozenset(), setup=()) -> None:
        for name, v in values.items():
            self.add(f"{prefix}/{flag}/{name}", _flag(base, flag, v), "0or2" if name in ok else "2", outputs,
                     setup=setup)

    def out_file(self, prefix: str, base: list[str], i: int, outputs, *, ext: str | None, setup=(),
                 exists_ok: bool = True) -> None:
        """An output file at argv position ``i``: the file-system cases."""
        name = Path(base[i]).name
        others = [o for o in outputs if o != base[i]]
        self.add(f"{prefix}/is_existing_dir", _sub(base, i, "taken"), "2", others + ["taken"],
                 protect=["taken/keep.txt"], setup=[*setup, ("taken", "mkdir")])
        self.add(f"{prefix}/exists", base, "0or2" if exists_ok else "2", outputs, setup=[*setup, (base[i], "file")])
        self.add(f"{prefix}/parent_is_file", _sub(base, i, f"blocker/{name}"), "2", others,
                 protect=["blocker"], setup=[*setup, ("blocker", "file")])
        self.add(f"{prefix}/read_only", _sub(base, i, f"{READ_ONLY_DIR}/{name}"), "2", others, setup=setup)
        self.add(f"{prefix}/missing_parent", _sub(base, i, f"new/sub/{name}"), "0or2",
                 others + [f"new/sub/{name}"], setup=setup)
        if ext is not None:
            self.add(f"{prefix}/wrong_suffix", _sub(base, i, f"{Path(name).stem}.{ext}"), "2",
                     others + [f"{Path(name).stem}.{ext}"], setup=setup)

    def out_dir(self, prefix: str, base: list[str], i: int, outputs, *, setup=(), nonempty_ok: bool = True) -> None:
        """An output folder at argv position ``i``."""
        name = Path(base[i]).name
        self.add(f"{prefix}/is_existing_file", base, "2", [], protect=[base[i]], setup=[*setup, (base[i], "file")])
        self.add(f"{prefix}/exists_nonempty", base, "0or2" if nonempty_ok else "2", [],
                 protect=[f"{base[i]}/keep.txt"], setup=[*setup, (base[i], "mkdir")])
        self.add(f"{prefix}/parent_is_file", _sub(base, i, f"blocker/{name}"), "2", [], protect=["blocker"],
                 setup=[*setup, ("blocker", "file")])
        self.add(f"{prefix}/read_only", _sub(base, i, f"{READ_ONLY_DIR}/{name}"), "2", [], setup=setup)
        self.add(f"{prefix}/missing_parent", _sub(base, i, f"new/sub/{name}"), "0or2", [f"new/sub/{name}"],
                 setup=setup)


NAN_INF = {"nan": "nan", "inf": "inf", "-inf": "-inf"}
RANGE_SPECS = {"nan": "nan", "inf": "inf", "step_1e-7": "0:360:1e-7", "step_0": "0:360:0",
               "step_negative": "0:360:-10", "reversed": "360:0:10", "garbage": "a:b:c",
               "huge_span": "-1e308:1e308:1", "empty": ""}


def _survey_and_atr_cases(b: _Builder, F: str) -> None:
    """Issue 40: survey, survey-detect, detect, simulate flight|field, bank eval-scenes."""
    ZERO_NEG = {"zero": "0", "negative": "-1"}
    fr = [f"{F}/flight/{n}" for n in FLIGHT_FRAMES[:3]]
    cam = f"{F}/flight/camera.yaml"
    BOX = f"{F}/box.obj"
    #: target specs refused before any training: unknown names and mesh files that cannot be read as given
    bad_specs = {"unknown_name": "no_such_target", "path_like": "../../etc/passwd", "empty_string": "",
                 "mesh_without_units": BOX, "mesh_bad_units": f"{BOX}=car:furlong", "mesh_bad_up": f"{BOX}=car:mm:q",
                 "mesh_bad_forward": f"{BOX}=car:mm:z:w", "mesh_forward_is_up": f"{BOX}=car:mm:z:z",
                 "mesh_five_fields": f"{BOX}=car:mm:z:x:extra", "mesh_empty_class": f"{BOX}=",
                 "mesh_missing_file": "nope.obj=car:mm:z:x", "mesh_garbage": f"{F}/bad/garbage.obj=car:mm:z:x",
                 "mesh_nan": f"{F}/bad/obj_nan.obj=car:mm:z:x",
                 "mesh_no_faces": f"{F}/bad/obj_no_faces.obj=car:mm:z:x",
                 "mesh_degenerate": f"{F}/bad/obj_degenerate.obj=car:mm:z:x",
                 "mesh_ply_claims_1e9": f"{F}/bad/ply_claims_1e9.ply=car:mm:z:x",
                 "mesh_is_a_directory": f"{F}/bad/dir.obj=car:mm:z:x"}
    bad_dbs = {"missing": "nope_db", "file": f"{F}/bad/garbage.yaml", "not_a_db": f"{F}/bad/not_a_db",
               "garbage_targets": f"{F}/bad/db_garbage_targets", "garbage_db_yaml": f"{F}/bad/db_garbage_yaml"}
    LENGTHS = {**NAN_INF, "zero": "0", "negative": "-100", "huge": "1e300"}
    CHOICES = {"--units": "furlong", "--up": "w", "--forward": "q"}

    # survey --------------------------------------------------------------------------
    outs = ["sv"]
    base = ["survey", *fr, "--calib", cam, "-o", "sv"]
    b.files("survey/IMAGE_OR_VIDEO[1]", base, 2, "jpg", outs)
    # frames that are not photographs, two alike (so they agree in size) with a camera of that size
    for kind, names, calib in (("grey_10x10", "a.png b.png", "cam_10x10"), ("rgb_1x1", "a.png b.png", "cam_1x1"),
                               ("claims_60000", "a.png b.png", "cam_60000x60000"),
                               ("bomb_20000", "a.png b.png", "cam_20000x20000"),
                               ("uniform_grey", "a.jpg b.jpg", None), ("noise", "a.jpg b.jpg", None),
                               ("truncated", " ".join(FLIGHT_FRAMES[:2]), None)):
        folder = {"grey_10x10": "grey10", "rgb_1x1": "1x1"}.get(kind, kind)
        b.add(f"survey/IMAGE_OR_VIDEO/two_{kind}", ["survey", *[f"{F}/bad/pair_{folder}/{n}" for n in names.split()],
                                                    "--calib", f"{F}/bad/{calib}.yaml" if calib else cam, "-o", "sv"],
              "2", outs)
    b.add("survey/IMAGE_OR_VIDEO/one_frame", ["survey", fr[0], "--calib", cam, "-o", "sv"], "2", outs)
    b.add("survey/IMAGE_OR_VIDEO/none", ["survey", "--calib", cam, "-o", "sv"], "2", outs)
    b.add("survey/IMAGE_OR_VIDEO/a_folder", ["survey", f"{F}/flight", "--calib", cam, "-o", "sv"], "2", outs)
    b.add("survey/IMAGE_OR_VIDEO/folder_of_0", ["survey", f"{F}/bad/empty_frames", "--calib", cam, "-o", "sv"], "2",
          outs)
    b.add("survey/IMAGE_OR_VIDEO/folder_of_1", ["survey", f"{F}/bad/one_frame", "--calib", cam, "-o", "sv"], "2",
          outs)
    b.add("survey/IMAGE_OR_VIDEO/folder_and_frames", ["survey", f"{F}/bad/one_frame", *fr, "--calib", cam, "-o",
                                                      "sv"], "2", outs)
    b.add("survey/IMAGE_OR_VIDEO/same_frame_twice", ["survey", fr[0], fr[0], fr[1], "--calib", cam, "-o", "sv"],
          "2", outs)
    b.add("survey/IMAGE_OR_VIDEO/same_photo_two_names", ["survey", fr[0], f"{F}/bad/IMG_0000_copy.JPG", fr[1],
                                                         "--calib", cam, "-o", "sv"], "0or2", outs)
    b.add("survey/IMAGE_OR_VIDEO/out_of_order", ["survey", fr[2], fr[0], fr[1], "--calib", cam, "-o", "sv"], "0or2",
          outs)
    b.add("survey/--calib/not_given_no_exif", ["survey", *[f"{F}/nogps/{n}" for n in FLIGHT_FRAMES[:3]], "-o", "sv"],
          "2", outs)
    vbase = ["survey", f"{F}/flight.avi", "--calib", cam, "-o", "sv"]
    b.files("survey/VIDEO", vbase, 1, "avi", outs)
    b.add("survey/VIDEO/and_frames", ["survey", f"{F}/flight.avi", *fr, "--calib", cam, "-o", "sv"], "2", outs)
    b.add("survey/VIDEO/two_videos", ["survey", f"{F}/flight.avi", f"{F}/flight.avi", "--calib", cam, "-o", "sv"],
          "2", outs)
    b.add("survey/VIDEO/with_--gps_of_the_frames", vbase + ["--gps", f"{F}/flight/geoinfo.txt"], "2", outs)
    b.add("survey/VIDEO/with_--resume", vbase + ["--resume"], "0or2", outs)
    b.numbers("survey", vbase, "--video-step", {**NAN_INF, **ZERO_NEG, "huge": "1e9", "tiny": "1e-9"}, outs,
              ok={"tiny"})
    b.add("survey/--video-step/nan_with_frames", base + ["--video-step", "nan"], "0or2", outs)
    b.files("survey/--calib", base, base.index("--calib") + 1, "cam", outs, ok={"no_size"})
    gbase = base + ["--gps", f"{F}/flight/geoinfo.txt"]
    b.files("survey/--gps", gbase, gbase.index("--gps") + 1, "gps", outs,
            ok={"comma_separated", "1000km_apart", "altitude_1e12", "altitude_negative"})
    b.numbers("survey", base, "--crs", {"EPSG:4326_geographic": "EPSG:4326", "EPSG:999999": "EPSG:999999",
                                        "foo": "foo", "empty": "", "EPSG:": "EPSG:", "EPSG:-1": "EPSG:-1",
                                        "EPSG:4978_geocentric": "EPSG:4978", "EPSG:2227_us_feet": "EPSG:2227",
                                        "EPSG:huge": "EPSG:99999999999999999999", "EPSG:3857": "EPSG:3857",
                                        "EPSG:2056_other_continent": "EPSG:2056",
                                        "EPSG:32633_other_zone": "EPSG:32633"}, outs,
              ok={"EPSG:3857", "EPSG:2056_other_continent", "EPSG:32633_other_zone"})
    nogps = ["survey", *[f"{F}/nogps/{n}" for n in FLIGHT_FRAMES[:3]], "--calib", cam, "-o", "sv"]
    for v in ("utm", "enu", "EPSG:32654"):
        b.add(f"survey/--crs/{v}_without_gps", nogps + ["--crs", v], "2", outs)
    CELLS = {**NAN_INF, **ZERO_NEG, "tiny": "1e-9", "0.1mm": "1e-4", "huge": "1e300", "1000km": "1e6"}
    b.numbers("survey", base, "--cell", CELLS, outs, ok={"huge", "1000km"})
    b.numbers("survey", base, "--ortho-gsd", CELLS, outs, ok={"huge", "1000km"})
    b.numbers("survey", base, "--cloud-spacing", {k: v for k, v in CELLS.items() if k not in ("tiny", "0.1mm")}, outs)
    b.numbers("survey", base, "--pair-steps", {**ZERO_NEG, "11": "11", "huge": "99999999999999999999",
                                               "garbage": "a"}, outs)
    b.add("survey/--pair-steps/duplicate", base + ["--pair-steps", "1", "1"], "2", outs)
    b.numbers("survey", base, "--max-image-size", {**ZERO_NEG, "319": "319", "20001": "20001",
                                                   "huge": "99999999999999999999"}, outs)
    b.numbers("survey", base, "--dense-max-pixels", {**NAN_INF, **ZERO_NEG, "9999": "9999", "huge": "1e300"}, outs,
              ok={"huge"})
    b.numbers("survey", base, "--workers", {"negative": "-1", "more_than_the_machine": "10000"}, outs)
    b.numbers("survey", base, "--scheduler", {"garbage": "not a url", "unreachable": "tcp://127.0.0.1:1"}, outs)
    b.numbers("survey", base, "--matching", {"unknown": "nearest"}, outs)
    b.numbers("survey", base, "--refine", {"unknown": "everything"}, outs)
    for name, v in {"tiny": "1000", "zero": "0", "negative": "-5"}.items():
        b.add(f"survey/--max-pixels/{name}", ["--max-pixels", v, *base], "2", outs)
    b.out_dir("survey/-o", base, base.index("sv"), outs, nonempty_ok=False)
    b.add("survey/-o/is_a_frame", _sub(base, base.index("sv"), fr[0]), "2")
    b.add("survey/-o/is_the_frames_folder", _sub(base, base.index("sv"), f"{F}/flight"), "2")
    b.add("survey/-o/resume_leftover_is_a_file", base, "0or2", outs, setup=[(".sv.resume", "file")])
    b.add("survey/--resume/leftover_is_garbage", base + ["--resume"], "0or2", outs,
          setup=[(".sv.resume", "mkdir"), (".sv.resume/manifest.json", "file")])

    # survey-detect -------------------------------------------------------------------
    outs = ["v.geojson"]
    base = ["survey-detect", f"{F}/survey", "--targets", f"{F}/aerial.npz", "-o", "v.geojson"]
    surveys = {"missing": "no_such_survey", "empty_dir": f"{F}/bad/survey_empty",
               "geojson_file": f"{F}/bad/vehicles.geojson", "ply_file": f"{F}/scan.ply",
               "geotiff_file": f"{F}/survey/ndsm.tif", "garbage_file": f"{F}/bad/garbage.json",
               "frames_folder": f"{F}/flight", "scene_folder": f"{F}/scene"}
    surveys.update({k: f"{F}/bad/survey_{k}" for k in (
        "poses_empty", "poses_garbage", "poses_truncated", "poses_list", "poses_no_keys", "poses_is_dir",
        "poses_scale_unknown", "poses_origin_nan", "poses_origin_out_of_range", "poses_origin_short",
        "poses_origin_string", "poses_origin_1e400", "poses_epsg_string", "poses_epsg_4326", "poses_epsg_999999",
        "poses_epsg_other_zone", "poses_map_frame_list", "poses_deep_nesting", "no_ndsm", "ndsm_empty",
        "ndsm_garbage", "ndsm_truncated", "ndsm_is_dir", "ndsm_is_the_ortho", "ndsm_all_nan", "ndsm_inf",
        "ndsm_1e30", "ndsm_int16", "ndsm_two_bands", "ndsm_other_grid", "ndsm_no_crs", "ndsm_cell_100m",
        "ndsm_bomb_20000", "ndsm_claims_60000", "no_ortho", "ortho_empty", "ortho_garbage", "ortho_truncated",
        "ortho_is_the_ndsm", "ortho_grey", "ortho_other_grid", "ortho_other_crs", "ortho_half_gsd",
        "ortho_bomb_20000", "no_ground", "ground_garbage", "ground_other_grid", "only_poses")})
    for kind, path in surveys.items():
        b.add(f"survey-detect/SURVEY_DIR/{kind}", _sub(base, 1, path),
              "0or2" if kind in ("no_ground", "ortho_half_gsd", "ndsm_inf", "ndsm_1e30") else "2", outs)
    b.add("survey-detect/SURVEY_DIR/missing_training_first", ["survey-detect", "no_such_survey", "--no-cache", "-o",
                                                              "v.geojson"], "2", outs)
    b.files("survey-detect/--targets", base, 3, "aerial", outs)
    for kind, spec in bad_specs.items():
        b.add(f"survey-detect/--targets/{kind}", _sub(base, 3, spec), "2", outs)
    b.add("survey-detect/--targets/model_and_a_class", base[:4] + ["car"] + base[4:], "2", outs)
    b.add("survey-detect/--targets/mesh_too_small_for_aerial", _sub(base, 3, f"{BOX}=car:mm:z:x")
          + ("--length-mm", "100"), "2", outs)
    for kind, db in bad_dbs.items():
        b.add(f"survey-detect/--db/{kind}", [a for a in base if a not in ("--targets", f"{F}/aerial.npz")]
              + ["--db", db], "2", outs)
    b.add("survey-detect/--db/and_--targets", base + ["--db", f"{F}/db"], "2", outs)
    for flag, v in CHOICES.items():
        b.add(f"survey-detect/{flag}/unknown", _sub(base, 3, BOX) + (flag, v), "2", outs)
    b.numbers("survey-detect", list(_sub(base, 3, f"{BOX}=car")), "--length-mm", LENGTHS, outs)
    b.numbers("survey-detect", base, "--threshold", {**NAN_INF, "negative": "-0.1", "over_1": "1.5",
                                                     "huge": "1e300", "zero": "0", "one": "1"}, outs,
              ok={"zero", "one"})
    b.out_file("survey-detect/-o", base, 5, outs, ext="csv")
    sv = [("sv", "copy:survey")]
    b.add("survey-detect/-o/the_surveys_poses.json", _sub(_sub(base, 1, "sv"), 5, "sv/poses.json"), "2",
          protect=["sv/poses.json"], setup=sv)
    b.add("survey-detect/-o/the_surveys_ortho.tif", _sub(_sub(base, 1, "sv"), 5, "sv/ortho.tif"), "2",
          protect=["sv/ortho.tif"], setup=sv)
    b.add("survey-detect/--draw/the_surveys_survey.png", _sub(base, 1, "sv") + ("--draw", "sv/survey.png"), "2",
          outs, protect=["sv/survey.png"], setup=sv)
    b.add("survey-detect/--draw/wrong_suffix", base + ["--draw", "d.jpg"], "2", outs + ["d.jpg"])
    b.add("survey-detect/--draw/same_as_-o", base + ["--draw", "v.geojson"], "2", outs)
    b.add("survey-detect/--draw/is_existing_dir", base + ["--draw", "taken.png"], "2", outs,
          protect=["taken.png/keep.txt"], setup=[("taken.png", "mkdir")])
    b.add("survey-detect/--draw/parent_is_file", base + ["--draw", "blocker/d.png"], "2", outs,
          protect=["blocker"], setup=[("blocker", "file")])
    b.add("survey-detect/--draw/read_only", base + ["--draw", f"{READ_ONLY_DIR}/d.png"], "2", outs)
    b.add("survey-detect/--draw/missing_parent", base + ["--draw", "new/sub/d.png"], "0or2", outs + ["new/sub/d.png"])

    # detect --------------------------------------------------------------------------
    outs = ["det.json"]
    base = ["detect", f"{F}/plate/shot.png", "--calib", f"{F}/rig.yaml", "--bank", f"{F}/bank.npz", "-o", "det.json"]
    ibase = ["detect", "--image", f"{F}/plate_left.png", "--depth", f"{F}/depth.npy", "--fx", "1276.75", "--bank",
             f"{F}/bank.npz", "-o", "det.json"]
    tbase = [a for a in base if a not in ("--bank", f"{F}/bank.npz")] + ["--targets", "tank_t1"]
    b.files("detect/SHOT", base, 1, "png", outs)
    b.files("detect/--calib", base, 3, "yaml", outs)
    b.files("detect/--bank", base, 5, "npz", outs)
    b.add("detect/--bank/aerial_recogniser", _sub(base, 5, f"{F}/aerial.npz"), "2", outs)
    b.add("detect/--bank/aerial_nan", _sub(base, 5, f"{F}/bad/aerial_nan.npz"), "2", outs)
    b.add("detect/--bank/other_channel", _sub(base, 5, f"{F}/bank_intensity.npz"), "0or2", outs)
    b.add("detect/--bank/a_survey_folder", _sub(base, 5, f"{F}/survey"), "2", outs)
    b.files("detect/--image", ibase, 2, "png", outs, ok={"half_shot"})  # the left view's size: the depth map's
    b.files("detect/--depth", ibase, 4, "depth", outs)
    b.numbers("detect", ibase, "--fx", {**NAN_INF, **ZERO_NEG, "huge": "1e300", "tiny": "1e-300"}, outs,
              ok={"huge", "tiny"})
    b.numbers("detect", base, "--depth-range", {"nan": "nan:nan", "inf": "1:inf", "zero": "0:0",
                                                "reversed": "2:1", "negative": "-5:-1", "huge": "0.001:1e12",
                                                "garbage": "a:b", "one_value": "1", "empty": ""}, outs,
              ok={"inf", "huge"})
    b.add("detect/SHOT+--image", base + ["--image", f"{F}/plate_left.png"], "2", outs)
    b.add("detect/SHOT/none", [a for a in base if a != f"{F}/plate/shot.png"], "2", outs)
    b.add("detect/SHOT/without_--calib", [a for a in base if a not in ("--calib", f"{F}/rig.yaml")], "2", outs)
    b.add("detect/SHOT/with_--depth", base + ["--depth", f"{F}/depth.npy"], "2", outs)
    b.add("detect/SHOT/with_--fx", base + ["--fx", "1000"], "0or2", outs)
    b.add("detect/--image/without_--depth", [a for a in ibase if a not in ("--depth", f"{F}/depth.npy")], "2", outs)
    b.add("detect/--image/without_--fx", [a for a in ibase if a not in ("--fx", "1276.75")], "2", outs)
    b.add("detect/--image/with_--calib", ibase + ["--calib", f"{F}/rig.yaml"], "0or2", outs)
    b.add("detect/--bank+--targets", base + ["--targets", "tank_t1"], "2", outs)
    b.add("detect/--bank+--db", base + ["--db", f"{F}/db"], "2", outs)
    b.add("detect/SHOT/missing_training_first", _sub(tbase, 1, "missing_input.png"), "2", outs)
    for kind, spec in bad_specs.items():
        b.add(f"detect/--targets/{kind}", _sub(tbase, len(tbase) - 1, spec), "2", outs)
    b.add("detect/--targets/a_model_alone", _sub(tbase, len(tbase) - 1, f"{F}/bank.npz"), "0or2", outs)
    b.add("detect/--targets/a_model_and_a_name", list(tbase) + [f"{F}/bank.npz"], "2", outs)
    b.add("detect/--targets/aerial_model", _sub(tbase, len(tbase) - 1, f"{F}/aerial.npz"), "2", outs)
    for kind, db in bad_dbs.items():
        b.add(f"detect/--db/{kind}", tbase[:-2] + ["--db", db], "2", outs)
    for flag, v in CHOICES.items():
        b.add(f"detect/{flag}/unknown", _sub(tbase, len(tbase) - 1, BOX) + (flag, v), "2", outs)
    b.numbers("detect", list(_sub(tbase, len(tbase) - 1, f"{BOX}=tank")), "--length-mm", LENGTHS, outs)
    b.out_file("detect/-o", base, 7, outs, ext="txt")
    b.add("detect/--draw/wrong_suffix", base + ["--draw", "d.jpg"], "2", outs + ["d.jpg"])
    b.add("detect/--draw/same_as_-o", base + ["--draw", "det.json"], "2", outs)
    b.add("detect/--draw/is_existing_dir", base + ["--draw", "taken.png"], "2", outs,
          protect=["taken.png/keep.txt"], setup=[("taken.png", "mkdir")])
    b.add("detect/--draw/parent_is_file", base + ["--draw", "blocker/d.png"], "2", outs, protect=["blocker"],
          setup=[("blocker", "file")])
    b.add("detect/--draw/read_only", base + ["--draw", f"{READ_ONLY_DIR}/d.png"], "2", outs)
    b.add("detect/--draw/missing_parent", base + ["--draw", "new/sub/d.png"], "0or2", outs + ["new/sub/d.png"])
    b.add("detect/--draw/is_the_input_shot", ["detect", "shot.png", *base[2:], "--draw", "shot.png"], "2", outs,
          protect=["shot.png"], setup=[("shot.png", "copy:plate/shot.png")])
    for name, v in {"tiny": "1000", "zero": "0"}.items():
        b.add(f"detect/--max-pixels/{name}", ["--max-pixels", v, *base], "2", outs)

    # simulate flight -----------------------------------------------------------------
    outs = ["fl"]
    base = ["simulate", "flight", "fl", "--frames", "2", "--lines", "1", "--size", "160x120", "--no-depth"]
    p = "simulate-flight"
    b.out_dir(f"{p}/OUT_DIR", base, 2, outs, nonempty_ok=False)
    b.numbers(p, base, "--frames", {**ZERO_NEG, "one": "1", "1001": "1001", "huge": "1000000000",
                                    "int_overflow": str(2**70)}, outs)
    b.add(f"{p}/--frames/not_a_multiple_of_--lines", _flag(_flag(base, "--lines", "2"), "--frames", "3"), "2", outs)
    b.numbers(p, base, "--lines", {**ZERO_NEG, "101": "101", "more_than_frames": "2"}, outs)
    b.numbers(p, base, "--altitude", {**NAN_INF, **ZERO_NEG, "1m": "1", "1001": "1001", "huge": "1e300"}, outs)
    b.numbers(p, base, "--overlap", {**NAN_INF, **ZERO_NEG, "one": "1", "over_1": "1.5"}, outs)
    b.numbers(p, base, "--side-overlap", {**NAN_INF, "negative": "-0.1", "one": "1", "over_1": "1.5"}, outs)
    b.numbers(p, base, "--size", {"0x0": "0x0", "1x1": "1x1", "63x63": "63x63", "60000x60000": "60000x60000",
                                  "12001x100": "12001x100", "garbage": "axb", "negative": "-160x120", "empty": "",
                                  "three_numbers": "160x120x3", "fraction": "160.5x120",
                                  "int_overflow": "99999999999999999999x120"}, outs)
    b.numbers(p, base, "--heading", {**NAN_INF, "over_360": "361", "huge": "1e300", "negative": "-90"}, outs,
              ok={"negative"})
    b.numbers(p, base, "--seed", {"negative": "-1", "huge": str(2**70)}, outs, ok={"negative", "huge"})
    b.numbers(p, base, "--supersample", {**ZERO_NEG, "5": "5", "huge": "100000"}, outs)
    b.numbers(p, base, "--targets", {"negative": "-1", "41": "41", "huge": "1000000000"}, outs)
    b.add(f"{p}/--targets/carpark_201", base + ["--scene", "carpark", "--targets", "201"], "2", outs)
    b.numbers(p, base, "--confusers", {"negative": "-1", "21": "21"}, outs)
    b.numbers(p, base, "--scene", {"unknown": "moon"}, outs)

    # simulate field ------------------------------------------------------------------
    outs = ["fs"]
    base = ["simulate", "field", "fs", "--targets", "1", "--confusers", "0", "--no-noise"]
    p = "simulate-field"
    b.out_dir(f"{p}/OUT_DIR", base, 2, outs, nonempty_ok=False)
    b.numbers(p, base, "--targets", {**ZERO_NEG, "13": "13", "huge": "1000000000"}, outs)
    b.numbers(p, base, "--confusers", {"negative": "-1", "13": "13"}, outs)
    b.numbers(p, base, "--seed", {"negative": "-1", "huge": str(2**70)}, outs, ok={"negative", "huge"})
    b.numbers(p, base, "--supersample", {**ZERO_NEG, "5": "5", "huge": "100000"}, outs)
    for kind, spec in {k: bad_specs[k] for k in ("unknown_name", "path_like", "empty_string", "mesh_without_units",
                                                 "mesh_bad_units", "mesh_bad_up", "mesh_bad_forward",
                                                 "mesh_missing_file", "mesh_garbage", "mesh_nan",
                                                 "mesh_degenerate")}.items():
        b.add(f"{p}/--classes/{kind}", base + ["--classes", spec.replace("=car", "=tank")], "2", outs)
    count = base + ["--count", "1"]
    b.numbers(p, base, "--count", {**ZERO_NEG, "huge": "100001"}, outs)
    b.add(f"{p}/--workers/without_--count", base + ["--workers", "2"], "2", outs)
    b.numbers(p, count, "--workers", {"negative": "-1", "more_than_the_machine": "10000"}, outs)
    b.add(f"{p}/--scheduler/without_--count", base + ["--scheduler", "tcp://127.0.0.1:1"], "2", outs)
    b.numbers(p, count, "--scheduler", {"garbage": "not a url", "unreachable": "tcp://127.0.0.1:1"}, outs)
    b.add(f"{p}/--count/batch.json_of_other_options", count, "2", protect=["fs/batch.json"],
          setup=[("fs", "mkdir"), ("fs/batch.json", "file")])
    b.add(f"{p}/--count/incomplete_scene", count, "2", protect=["fs/scene_0000/keep.txt"],
          setup=[("fs/scene_0000", "mkdir")])
    b.add(f"{p}/--count/OUT_DIR_is_existing_file", count, "2", protect=["fs"], setup=[("fs", "file")])

    # bank eval-scenes ----------------------------------------------------------------
    outs = ["res.json", "res_fppi.png"]
    base = ["bank", "eval-scenes", f"{F}/bank.npz", f"{F}/scene", "--json", "res.json"]
    p = "bank-eval-scenes"
    b.files(f"{p}/MODEL_NPZ", base, 2, "npz", outs)
    for kind, path in {"aerial_recogniser": f"{F}/aerial.npz", "aerial_nan": f"{F}/bad/aerial_nan.npz",
                       "a_scene_folder": f"{F}/scene", "truth_npz_of_a_flight": f"{F}/flight/truth.npz"}.items():
        b.add(f"{p}/MODEL_NPZ/{kind}", _sub(base, 2, path), "2", outs)
    b.add(f"{p}/MODEL_NPZ/other_channel", _sub(base, 2, f"{F}/bank_intensity.npz"), "0or2", outs)
    b.add(f"{p}/MODEL_NPZ/not_given", ["bank", "eval-scenes"], "2")
    scenes = {"missing": "no_such_scene", "a_file": f"{F}/scene/shot.png", "empty_dir": f"{F}/bad/survey_empty",
              "survey_folder": f"{F}/survey", "frames_folder": f"{F}/flight"}
    scenes.update({k: f"{F}/bad/scene_{k}" for k in (
        "no_shot", "no_rig", "no_truth", "shot_is_dir", "shot_garbage", "shot_grey10", "shot_half_size",
        "shot_claims_60000", "shot_bomb_20000", "rig_garbage", "rig_k1_nan", "rig_sensor_60000",
        "rig_is_a_camera_yaml", "truth_empty", "truth_garbage", "truth_truncated", "truth_list", "truth_no_keys",
        "truth_targets_dict", "truth_target_string", "truth_target_no_class", "truth_box_nan", "truth_box_short",
        "truth_box_reversed", "truth_box_strings", "truth_box_1e300", "truth_xyz_nan", "truth_radius_negative",
        "truth_no_targets_at_all", "truth_deep_nesting")})
    for kind, path in scenes.items():
        b.add(f"{p}/SCENE_DIR/{kind}", _sub(base, 3, path),
              "0or2" if kind in ("truth_box_1e300", "truth_no_targets_at_all") else "2", outs)
    b.add(f"{p}/SCENE_DIR/one_good_one_bad", base[:4] + [f"{F}/bad/scene_truth_garbage"] + base[4:], "2", outs)
    b.add(f"{p}/SCENE_DIR/twice", base[:4] + [f"{F}/scene"] + base[4:], "0or2", outs)
    b.add(f"{p}/SCENE_DIR/none", base[:3] + base[4:], "2", outs)
    b.out_file(f"{p}/--json", base, 5, outs, ext="txt")
    b.add(f"{p}/--json/plot_name_is_existing_dir", base, "2", protect=["res_fppi.png/keep.txt"],
          setup=[("res_fppi.png", "mkdir")])
    b.add(f"{p}/--json/plot_name_exists", base, "0or2", setup=[("res_fppi.png", "file")])
    b.add(f"{p}/--json/is_the_scenes_truth", _sub(_sub(base, 3, "sc"), 5, "sc/truth.json"), "2",
          protect=["sc/truth.json"], setup=[("sc", "copy:scene")])
    b.add(f"{p}/-o/given", base + ["-o", "x.npz"], "2", outs + ["x.npz"])
    b.numbers(p, base, "--workers", {"negative": "-1", "more_than_the_machine": "10000"}, outs)
    b.numbers(p, base, "--scheduler", {"garbage": "not a url", "unreachable": "tcp://127.0.0.1:1"}, outs)
    # options of the other actions, given to eval-scenes
    b.numbers(p, base, "--noise", {"nan": "nan"}, outs, ok={"nan"})
    b.numbers(p, base, "--size", {"zero": "0"}, outs, ok={"zero"})
    b.numbers(p, base, "--scenes", {"negative": "-1"}, outs, ok={"negative"})


def cases(fx: Path | str | None = None) -> list[Case]:
    """The probe's cases (``fx`` is unused: paths carry the ``{fx}`` placeholder)."""
    b = _Builder()
    F = "{fx}"

    # demo ----------------------------------------------------------------------------
    base = ["demo", "demo_out", "--fast", "--only", "environment"]
    b.out_dir("demo/OUT_DIR", base, 1, ["demo_out"])
    b.add("demo/--only/unknown_stage", _flag(base, "--only", "no_such_stage"), "2")
    b.add("demo/--seed/negative", _flag(base, "--seed", "-1"), "0or1or2", ["demo_out"])

    # simulate ------------------------------------------------------------------------
    for kind in ("plate", "calib", "scene"):
        base = ["simulate", kind, "sim", "--rig", f"{F}/rig.yaml", "--supersample", "1", "--views", "1"]
        p = f"simulate-{kind}"
        b.files(f"{p}/--rig", base, 4, "yaml", ["sim"], ok=set())
        if kind == "plate":
            b.out_dir(f"{p}/OUT_DIR", base, 2, ["sim"])
        b.numbers(p, base, "--views", {"zero": "0", "negative": "-1", "huge": "1000000000"}, ["sim"])
        b.numbers(p, base, "--supersample", {"zero": "0", "negative": "-2", "huge": "100000"}, ["sim"])
        b.numbers(p, base, "--seed", {"negative": "-1", "huge": str(2**70)}, ["sim"], ok={"negative", "huge"})
        b.numbers(p, base, "--jpeg-quality", {"negative": "-5", "over_100": "1000"}, ["sim"])
        if kind != "calib":
            b.numbers(p, base, "--blur", {**NAN_INF, "negative": "-1", "huge": "1e9"}, ["sim"])
        if kind == "calib":
            b.numbers(p, base, "--square", {**NAN_INF, "zero": "0", "negative": "-3", "huge": "1e300"}, ["sim"])
            b.numbers(p, base, "--board", {"0x0": "0x0", "1x1": "1x1", "1000x1000": "1000x1000",
                                           "garbage": "axb", "negative": "-9x6"}, ["sim"])
        if kind == "scene":
            b.numbers(p, base, "--target", {"unknown": "no_such_target", "path_like": "../../etc/passwd",
                                            "empty": ""}, ["sim"])

    # calibrate -----------------------------------------------------------------------
    cal = [f"{F}/cal/calib_00.png", f"{F}/cal/calib_01.png", f"{F}/cal/calib_02.png"]
    base = ["calibrate", *cal, "-o", "c.yaml", "--no-tangential"]
    b.files("calibrate/IMAGES", base, 1, "png", ["c.yaml"])
    b.add("calibrate/IMAGES/only_one", ["calibrate", cal[0], "-o", "c.yaml"], "2", ["c.yaml"])
    b.add("calibrate/IMAGES/plate_shot_no_board", ["calibrate", f"{F}/plate/shot.png", cal[1], "-o", "c.yaml"],
          "2", ["c.yaml"])
    b.add("calibrate/--pairs/odd_count", _flag(base, "--pairs", None), "2", ["c.yaml"])
    b.numbers("calibrate", base, "--board", {"0x0": "0x0", "1000x1000": "1000x1000", "garbage": "axb",
                                              "wrong_board": "7x5"}, ["c.yaml"])
    b.numbers("calibrate", base, "--square", {**NAN_INF, "zero": "0", "negative": "-25", "huge": "1e300"}, ["c.yaml"])
    b.out_file("calibrate/-o", base, base.index("c.yaml"), ["c.yaml"], ext="png")

    # convert-calib -------------------------------------------------------------------
    base = ["convert-calib", f"{F}/calib.txt", "-o", "c.yaml"]
    b.files("convert-calib/CALIB", base, 1, "yaml", ["c.yaml"], ok=set())
    b.add("convert-calib/CALIB/three_files", ["convert-calib", f"{F}/calib.txt", f"{F}/calib.txt",
                                               f"{F}/calib.txt", "-o", "c.yaml"], "2", ["c.yaml"])
    b.numbers("convert-calib", base, "--image-size", {"0x0": "0x0", "60000x60000": "60000x60000",
                                                      "garbage": "axb", "negative": "-640x480"}, ["c.yaml"],
              ok={"60000x60000"})
    b.out_file("convert-calib/-o", base, 3, ["c.yaml"], ext="json")
    b.add("convert-calib/-o/same_as_input", ["convert-calib", "calib.txt", "-o", "calib.txt"], "0or2", [],
          setup=[("calib.txt", "copy:calib.txt")])

    # rectify -------------------------------------------------------------------------
    base = ["rectify", f"{F}/plate/shot.png", "--calib", f"{F}/rig.yaml", "-o", "rect"]
    b.files("rectify/SHOT", base, 1, "png", ["rect"])
    b.files("rectify/--calib", base, 3, "yaml", ["rect"])
    b.add("rectify/SHOT+--left", base + ["--left", f"{F}/rect/left.png", "--right", f"{F}/rect/right.png"], "2")
    b.numbers("rectify", base, "--alpha", {**NAN_INF, "negative": "-1", "huge": "1e9"}, ["rect"])
    b.numbers("rectify", base, "--image-size", {"0x0": "0x0", "60000x60000": "60000x60000"}, ["rect"])
    b.out_dir("rectify/-o", base, 5, ["rect"])

    # match ---------------------------------------------------------------------------
    base = ["match", f"{F}/rect/left.png", f"{F}/rect/right.png", "-o", "d.pfm", "--num-disp", "64",
            "--min-disp", "170", "--sparse"]
    b.files("match/LEFT", base, 1, "png", ["d.pfm"])
    b.files("match/RIGHT", base, 2, "png", ["d.pfm"])
    b.add("match/RIGHT/half_size_of_left", _sub(base, 2, f"{F}/bad/grey10.png"), "2", ["d.pfm"])
    b.numbers("match", base, "--num-disp", {"zero": "0", "negative": "-64", "100000": "100000",
                                            "huge": "2000000000"}, ["d.pfm"], ok={"100000", "huge"})  # clipped to the image
    b.numbers("match", base, "--min-disp", {"negative_huge": "-100000", "huge": "100000",
                                            "int_overflow": str(2**40)}, ["d.pfm"])
    b.out_file("match/-o", base, 4, ["d.pfm"], ext="png")
    b.add("match/--valid-out/same_as_-o", base + ["--valid-out", "d.pfm"], "2", ["d.pfm"])
    b.add("match/--valid-out/wrong_suffix", base + ["--valid-out", "v.pfm"], "2", ["d.pfm", "v.pfm"])
    b.add("match/--valid-out/parent_is_file", base + ["--valid-out", "blocker/v.png"], "2", ["d.pfm"],
          setup=[("blocker", "file")])
    b.add("match/--valid-out/read_only", base + ["--valid-out", f"{READ_ONLY_DIR}/v.png"], "2", ["d.pfm"])

    # reconstruct ---------------------------------------------------------------------
    base = ["reconstruct", f"{F}/plate/shot.png", "--calib", f"{F}/rig.yaml", "-o", "scan.ply"]
    outs = ["scan.ply"]
    b.files("reconstruct/SHOT", base, 1, "png", outs)
    b.files("reconstruct/--calib", base, 3, "yaml", outs)
    lr = ["reconstruct", "--left", f"{F}/rect/left.png", "--right", f"{F}/rect/right.png", "--calib",
          f"{F}/calib.txt", "-o", "scan.ply"]
    b.files("reconstruct/--left", lr, 2, "png", outs, only={"missing", "empty", "garbage", "grey_10x10",
                                                            "claims_60000x60000", "bomb_20000x20000"})
    b.add("reconstruct/--left/without_--right", ["reconstruct", "--left", f"{F}/rect/left.png", "--calib",
                                                  f"{F}/rig.yaml", "-o", "scan.ply"], "2", outs)
    b.add("reconstruct/--calib/three_files", base[:4] + [f"{F}/rig.yaml", f"{F}/rig.yaml"] + base[4:], "2", outs)
    b.numbers("reconstruct", base, "--depth-range", {"nan": "nan:nan", "inf": "1000:inf", "zero": "0:0",
                                                      "reversed": "2000:1000", "negative": "-5:-1",
                                                      "huge": "1:1e12", "garbage": "a:b", "one_value": "1000"},
              outs, ok={"inf", "huge"})
    b.numbers("reconstruct", base, "--num-disp", {"zero": "0", "negative": "-5", "huge": "100000"}, outs,
              ok={"huge"})
    b.numbers("reconstruct", base, "--min-disp", {"negative_huge": "-100000", "huge": "100000"}, outs)
    b.numbers("reconstruct", base, "--min-confidence", {**NAN_INF, "negative": "-1", "over_1": "2"}, outs)
    b.numbers("reconstruct", base, "--smooth", {**NAN_INF, "negative": "-1", "huge": "1e9"}, outs)
    b.out_file("reconstruct/-o", base, 5, outs, ext="pcd")
    full = base + ["--disparity-out", "d.pfm", "--depth-out", "z.tiff", "--mesh", "m.ply"]
    fouts = ["scan.ply", "d.pfm", "z.tiff", "m.ply"]
    for flag, other, ext in (("--disparity-out", "d.pfm", "png"), ("--depth-out", "z.tiff", "png"),
                             ("--mesh", "m.ply", "obj")):
        i = full.index(flag) + 1
        b.add(f"reconstruct/{flag}/same_as_-o", _sub(full, i, "scan.ply"), "2", fouts)
        b.add(f"reconstruct/{flag}/wrong_suffix", _sub(full, i, f"x.{ext}"), "2", fouts + [f"x.{ext}"])
        b.add(f"reconstruct/{flag}/parent_is_file", _sub(full, i, "blocker/x" + Path(other).suffix), "2", fouts,
              setup=[("blocker", "file")])
        b.add(f"reconstruct/{flag}/read_only", _sub(full, i, f"{READ_ONLY_DIR}/{other}"), "2", fouts)
        b.add(f"reconstruct/{flag}/is_existing_dir", _sub(full, i, "taken"), "2", fouts,
              protect=["taken/keep.txt"], setup=[("taken", "mkdir")])
    b.add("reconstruct/--depth-out/same_as_--mesh", _sub(full, full.index("--depth-out") + 1, "m.ply"), "2", fouts)

    # triangulate ---------------------------------------------------------------------
    base = ["triangulate", f"{F}/disp.pfm", "--calib", f"{F}/rig.yaml", "--left", f"{F}/rect/left.png",
            "-o", "cloud.ply"]
    outs = ["cloud.ply"]
    b.files("triangulate/DISP_PFM", base, 1, "pfm", outs, ok={"inf", "nan", "negative", "tiny_1e-30"})
    b.files("triangulate/--calib", base, 3, "yaml", outs)
    b.files("triangulate/--left", base, 5, "png", outs, ok={"half_shot"})  # the left view as shot
    b.numbers("triangulate", base, "--max-depth", {**NAN_INF, "zero": "0", "negative": "-1"}, outs, ok={"inf"})
    b.numbers("triangulate", base, "--image-size", {"0x0": "0x0", "60000x60000": "60000x60000"}, outs,
              ok={"60000x60000"})
    b.out_file("triangulate/-o", base, 7, outs, ext="pcd")

    # flatness ------------------------------------------------------------------------
    base = ["flatness", f"{F}/scan.ply"]
    b.files("flatness/SCAN_PLY", base, 1, "ply", [])
    b.numbers("flatness", base, "--region", {**NAN_INF, "zero": "0", "negative": "-0.2", "over_1": "2"}, [])
    b.numbers("flatness", base, "--focal", {**NAN_INF, "zero": "0", "negative": "-5"}, [])
    b.numbers("flatness", base, "--baseline", {**NAN_INF, "zero": "0", "negative": "-5"}, [])

    # stitch --------------------------------------------------------------------------
    base = ["stitch", f"{F}/a.ply", f"{F}/b.ply", "-o", "model.ply"]
    outs = ["model.ply", "poses.json"]
    b.files("stitch/SCANS[0]", base, 1, "ply", outs)
    b.files("stitch/SCANS[1]", base, 2, "ply", outs, only={"missing", "garbage", "no_vertices", "nan", "one_point"})
    b.add("stitch/SCANS/only_one", ["stitch", f"{F}/a.ply", "-o", "model.ply"], "2", outs)
    b.numbers("stitch", base, "--voxel", {**NAN_INF, "zero": "0", "negative": "-1", "tiny": "1e-9",
                                          "huge": "1e300"}, outs, ok={"huge"})
    b.numbers("stitch", base, "--turntable-step", {**NAN_INF, "huge": "1e300"}, outs, ok={"huge"})
    b.numbers("stitch", base, "--min-confidence", {**NAN_INF, "negative": "-1", "over_1": "2"}, outs)
    b.numbers("stitch", base + ["--mesh", "mesh.ply"], "--smooth", {"negative": "-1", "huge": "1000000000"},
              outs + ["mesh.ply"])
    b.out_file("stitch/-o", base, 4, outs, ext="pcd")
    b.add("stitch/-o/poses.json_exists", base, "0or2", outs, setup=[("poses.json", "file")])
    b.add("stitch/--mesh/same_as_-o", base + ["--mesh", "model.ply"], "2", outs)
    b.add("stitch/--mesh/named_poses.json", base + ["--mesh", "poses.json"], "2", outs)
    b.add("stitch/--mesh/wrong_suffix", base + ["--mesh", "mesh.obj"], "2", outs + ["mesh.obj"])
    b.add("stitch/--mesh/read_only", base + ["--mesh", f"{READ_ONLY_DIR}/mesh.ply"], "2", outs)
    b.numbers("stitch", base + ["--frame", "object"], "--front-view",
              {"negative": "-1", "past_the_scans": "2", "huge": "1000000000000", "not_int": "1.5"}, outs)
    b.add("stitch/--front-view/without_object_frame", base + ["--front-view", "0"], "2", outs)

    # decamo --------------------------------------------------------------------------
    base = ["decamo", f"{F}/plate/shot.png", f"{F}/plate/truth.npz:depth_left_mm", "-o", "dc", "--calib",
            f"{F}/rig.yaml"]
    b.files("decamo/IMAGE", base, 1, "png", ["dc"], ok={"half_shot"})  # one view, with --calib
    b.files("decamo/DEPTH", base, 2, "depth", ["dc"])
    b.files("decamo/--calib", base, base.index("--calib") + 1, "yaml", ["dc"])
    nocal = base[:4] + ["--focal", "1276.75"]
    b.numbers("decamo", nocal, "--focal", {**NAN_INF, "zero": "0", "negative": "-5"}, ["dc"])
    b.add("decamo/--focal+--calib", base + ["--focal", "1000"], "2", ["dc"])
    b.add("decamo/no_depth_no_calib", ["decamo", f"{F}/plate/shot.png", "-o", "dc"], "2", ["dc"])
    b.out_dir("decamo/-o", base, 4, ["dc"])

    # features ------------------------------------------------------------------------
    base = ["features", f"{F}/box.obj", "--units", "mm", "--up", "z", "-o", "f.parquet"]
    b.files("features/MODEL", base, 1, "obj", ["f.parquet"], ok={"coords_1e30"})
    b.files("features/SCAN", base, 1, "ply", ["f.parquet"])
    b.add("features/MODEL/no_units", ["features", f"{F}/box.obj", "-o", "f.parquet"], "2", ["f.parquet"])
    b.out_file("features/-o", base, 7, ["f.parquet"], ext="csv")

    # render --------------------------------------------------------------------------
    base = ["render", "tank_t1", "-o", "chips", "--azimuth", "0:90:90", "--elevation", "20:20:1",
            "--range", "3000", "--size", "32"]
    meshbase = _sub(base, 1, f"{F}/box.obj") + ("--units", "mm")
    b.files("render/MODEL", list(meshbase), 1, "obj", ["chips"], ok={"coords_1e30"})
    b.add("render/MODEL/unknown_name", _sub(base, 1, "no_such_target"), "2", ["chips"])
    b.numbers("render", list(meshbase) + ["--up", "z"], "--length-mm",
              {**NAN_INF, "zero": "0", "negative": "-5", "huge": "1e300"}, ["chips"])
    b.add("render/--length-mm/builtin_target", base + ["--length-mm", "100"], "2", ["chips"])
    b.add("render/MODEL/path_like_name", _sub(base, 1, "../../x"), "2", ["chips"])
    b.numbers("render", base, "--azimuth", RANGE_SPECS, ["chips"])
    b.numbers("render", base, "--elevation", {**RANGE_SPECS, "over_90": "100:120:10"}, ["chips"],
              ok={"over_90"})
    b.numbers("render", base, "--range", {"nan": "nan", "inf": "inf", "zero": "0", "negative": "-3000",
                                          "huge": "1e300", "garbage": "a,b", "empty": "", "many": ",".join(
                                              ["3000"] * 4000)}, ["chips"], ok={"many"})
    b.numbers("render", base, "--size", {"zero": "0", "negative": "-32", "60000": "60000"}, ["chips"])
    b.numbers("render", base, "--noise", {**NAN_INF, "negative": "-1", "huge": "1e9"}, ["chips"])
    rng = _flag(list(base), "--framing", "range")
    b.numbers("render", list(rng), "--pixels-per-m", {**NAN_INF, "zero": "0", "negative": "-5", "huge": "1e9"},
              ["chips"])
    b.out_dir("render/-o", base, 3, ["chips"])

    # bank ----------------------------------------------------------------------------
    base = ["bank", "train", "--targets", "tank_t1", "jet_j1", "-o", "bank.npz", "--azimuth", "0:360:90",
            "--elevation", "20:20:1", "--size", "32", "--no-camouflage", "--scenes", "0"]
    outs = ["bank.npz"]
    b.add("bank-train/--targets/unknown", _sub(base, 3, "no_such_target"), "2", outs)
    for kind, path in bad_files("obj").items():
        b.add(f"bank-train/--targets/mesh_{kind}", _sub(base, 3, f"{path}=tank") + ("--units", "mm", "--up", "z"),
              "0or2" if kind == "coords_1e30" else "2", outs)
    b.add("bank-train/--targets/one_class", ["bank", "train", "--targets", "tank_t1", *base[5:]], "2", outs)
    b.numbers("bank-train", base, "--azimuth", RANGE_SPECS, outs)
    b.numbers("bank-train", base, "--elevation", {k: RANGE_SPECS[k] for k in ("nan", "step_0", "garbage")}, outs)
    b.numbers("bank-train", base, "--size", {"zero": "0", "negative": "-1", "60000": "60000"}, outs)
    b.numbers("bank-train", base, "--bin-deg", {**NAN_INF, "zero": "0", "negative": "-10", "huge": "1e9"}, outs,
              ok={"huge"})
    b.out_file("bank-train/-o", base, 6, outs, ext="npy")
    b.add("bank-train/-o/missing", [a for a in base if a not in ("-o", "bank.npz")], "2")
    base = ["bank", "eval", f"{F}/bank.npz", "--targets", "tank_t1", "jet_j1", "--azimuth", "45:315:90",
            "--elevation", "20:20:1", "--json", "res.json"]
    outs = ["res.json"]
    b.files("bank-eval/BANK_NPZ", base, 2, "npz", outs)
    b.add("bank-eval/BANK_NPZ/not_given", [a for a in base if a != f"{F}/bank.npz"], "2", outs)
    b.add("bank-eval/-o/given", base + ["-o", "x.npz"], "2", outs + ["x.npz"])
    b.add("bank-eval/--targets/unknown", _sub(base, 4, "no_such_target"), "2", outs)
    b.numbers("bank-eval", base, "--noise", {**NAN_INF, "negative": "-1", "huge": "1e9"}, outs)
    b.numbers("bank-eval", base, "--azimuth", {k: RANGE_SPECS[k] for k in ("nan", "step_1e-7", "garbage")}, outs)
    b.out_file("bank-eval/--json", base, base.index("res.json"), outs, ext="txt")

    # db ------------------------------------------------------------------------------
    db_setup = [("db", "copy:db")]
    dbs = {"missing": "nope_db", "empty_dir": "{w_empty}", "file": f"{F}/bad/garbage.yaml",
           "not_a_db": f"{F}/bad/not_a_db", "garbage_targets": "db_gt", "garbage_db_yaml": "db_gy"}
    dbset = {"empty_dir": [("empty_db", "mkdir")], "garbage_targets": [("db_gt", "copy:bad/db_garbage_targets")],
             "garbage_db_yaml": [("db_gy", "copy:bad/db_garbage_yaml")]}

    def db_path(kind: str) -> str:
        return "empty_db" if kind == "empty_dir" else dbs[kind]

    b.add("db-init/DB/exists_nonempty", ["db", "init", "x"], "2", [], protect=["x/keep.txt"], setup=[("x", "mkdir")])
    b.add("db-init/DB/existing_db", ["db", "init", "db"], "2", [], setup=db_setup)
    b.add("db-init/DB/is_existing_file", ["db", "init", "x"], "2", [], protect=["x"], setup=[("x", "file")])
    b.add("db-init/DB/parent_is_file", ["db", "init", "blocker/db"], "2", [], setup=[("blocker", "file")])
    b.add("db-init/DB/read_only", ["db", "init", f"{READ_ONLY_DIR}/db"], "2", [])
    b.add("db-init/DB/missing_parent", ["db", "init", "new/sub/db"], "0or2", ["new/sub/db"])
    for action, extra, expect in (("add", ["--builtin", "jet_j1"], "2"),
                                  ("render", ["--job", "k", "--azimuth", "0:90:90", "--elevation", "20:20:1",
                                              "--range", "3000", "--size", "32"], "2"),
                                  ("features", ["--job", "j"], "2"), ("info", [], "2"), ("verify", [], "0or1or2")):
        for kind in dbs:
            b.add(f"db-{action}/DB/{kind}", ["db", action, db_path(kind), *extra], expect if kind != "missing"
                  else "2", setup=dbset.get(kind, ()))
    base = ["db", "add", "db", f"{F}/box.obj", "--class", "truck", "--units", "mm", "--up", "z"]
    b.files("db-add/MESH", base, 3, "obj", [], ok={"coords_1e30"}, setup=db_setup)
    b.add("db-add/MESH/no_class", [a for a in base if a not in ("--class", "truck")], "2", setup=db_setup)
    b.add("db-add/MESH/no_units", base[:6], "2", setup=db_setup)
    b.add("db-add/--builtin/unknown", ["db", "add", "db", "--builtin", "no_such_target"], "2", setup=db_setup)
    b.add("db-add/--builtin/and_meshes", ["db", "add", "db", f"{F}/box.obj", "--builtin", "jet_j1"], "2",
          setup=db_setup)
    b.add("db-add/--class/path_like", _flag(base, "--class", "../../evil"), "2", setup=db_setup)
    b.add("db-add/--class/empty", _flag(base, "--class", ""), "2", setup=db_setup)
    b.numbers("db-add", base, "--length-mm", {**NAN_INF, "zero": "0", "negative": "-100", "huge": "1e300"}, [],
              setup=db_setup)
    b.numbers("db-add", base, "--yaw", {**NAN_INF, "huge": "1e300"}, [], ok={"huge"}, setup=db_setup)
    base = ["db", "render", "db", "--job", "k", "--azimuth", "0:90:90", "--elevation", "20:20:1", "--range",
            "3000", "--size", "32"]
    b.numbers("db-render", base, "--job", {"path_like": "../../evil", "empty": "", "slash": "a/b",
                                            "dotdot": ".."}, [], setup=db_setup)
    b.numbers("db-render", base, "--azimuth", RANGE_SPECS, [], setup=db_setup)
    b.numbers("db-render", base, "--range", {"nan": "nan", "zero": "0", "negative": "-1", "garbage": "x"}, [],
              setup=db_setup)
    b.numbers("db-render", base, "--size", {"zero": "0", "negative": "-1", "60000": "60000"}, [], setup=db_setup)
    b.numbers("db-render", base, "--workers", {"negative": "-1", "more_than_the_machine": "10000"}, [],
              setup=db_setup)
    b.numbers("db-render", base, "--scheduler", {"garbage": "not a url", "unreachable": "tcp://127.0.0.1:1"}, [],
              setup=db_setup)
    b.numbers("db-render", base, "--targets", {"unknown": "no_such_id", "path_like": "../../x"}, [],
              setup=db_setup)
    b.numbers("db-render", base, "--classes", {"unknown": "no_such_class"}, [], setup=db_setup)
    b.add("db-render/--job/same_job_other_spec", _flag(_flag(base, "--job", "j"), "--size", "48"), "2", setup=db_setup)
    b.numbers("db-features", ["db", "features", "db", "--job", "j"], "--job",
              {"unknown": "nope", "path_like": "../../evil", "empty": ""}, [], setup=db_setup)

    # trigger / capture ----------------------------------------------------------------
    ports = {"missing": "/dev/prism3d_no_such_port", "regular_file": f"{F}/bad/garbage.yaml",
             "directory": f"{F}/bad/dir.yaml", "empty": "", "garbage_url": "nope://x",
             "refused_socket": "socket://127.0.0.1:1"}
    for action in ("ping", "status", "fire"):
        for kind, port in ports.items():
            b.add(f"trigger-{action}/PORT/{kind}", ["trigger", action, port, "--timeout", "0.5"], "2")
    b.add("trigger-ping/PORT/not_given", ["trigger", "ping"], "2")
    for name, v in {**NAN_INF, "zero": "0", "negative": "-1", "huge": "1e300"}.items():
        b.add(f"trigger-ping/--timeout/{name}", ["trigger", "ping", "{trigger}", "--timeout", v],
              "0or2" if name in ("inf", "huge") else "2", needs="trigger")
    for flag in ("--pattern", "--flash-delay-us", "--flash-us", "--shutter-us"):
        for name, v in {"negative": "-1", "huge": "999999999999"}.items():
            b.add(f"trigger-fire/{flag}/{name}", ["trigger", "fire", "{trigger}", flag, v, "--timeout", "2"], "2",
                  needs="trigger")
    b.add("trigger-simulate/--link/existing_file", ["trigger", "simulate", "--link", "port"], "2",
          protect=["port"], setup=[("port", "file")])
    b.add("trigger-simulate/--link/existing_dir", ["trigger", "simulate", "--link", "port"], "2",
          protect=["port/keep.txt"], setup=[("port", "mkdir")])
    b.add("trigger-simulate/--link/parent_is_file", ["trigger", "simulate", "--link", "blocker/port"], "2",
          setup=[("blocker", "file")])
    b.add("trigger-simulate/--link/read_only", ["trigger", "simulate", "--link", f"{READ_ONLY_DIR}/port"], "2")
    b.add("trigger-simulate/PORT/given", ["trigger", "simulate", "/dev/x", "--link", "blocker/port"], "2",
          setup=[("blocker", "file")])

    base = ["capture", "--trigger", "{trigger}", "--camera", f"folder:{F}/cal", "-o", "shots", "--timeout", "2",
            "--grab-timeout", "2"]
    for kind, port in ports.items():
        b.add(f"capture/--trigger/{kind}", _sub(base, 2, port), "2")
    T = "trigger"
    for kind, cam in {"unknown_kind": "nope:x", "empty": "", "folder_missing": "folder:/nonexistent_prism3d",
                      "folder_is_file": f"folder:{F}/bad/garbage.png", "folder_empty": "folder:emptycam",
                      "folder_garbage_images": f"folder:{F}/bad", "opencv_bad_index": "opencv:99",
                      "virtual_unknown": "virtual:no_such_target"}.items():
        b.add(f"capture/--camera/{kind}", _sub(base, 4, cam), "2", ["shots"], needs=T,
              setup=[("emptycam", "mkdir")] if kind == "folder_empty" else ())
    b.numbers("capture", base, "--count", {"zero": "0", "negative": "-1"}, ["shots"])
    b.numbers("capture", base, "--interval", {**NAN_INF, "negative": "-1"}, ["shots"])
    b.numbers("capture", base, "--timeout", {"nan": "nan", "zero": "0", "negative": "-1"}, ["shots"])
    b.numbers("capture", base, "--grab-timeout", {"nan": "nan", "zero": "0", "negative": "-1"}, ["shots"])
    b.numbers("capture", base, "--pattern", {"negative": "-1", "huge": "999999999999"}, ["shots"])
    for kind, path in bad_files("yaml").items():
        if kind in ("missing", "empty", "garbage", "k1_2x2", "sensor_60000", "sensor_zero"):
            b.add(f"capture/--calib/{kind}", list(base) + ["--calib", path], "2", ["shots"])
    b.add("capture/--calib/size_mismatch", list(base) + ["--calib", f"{F}/rig.yaml", "--camera",
                                                          f"folder:{F}/rect"], "2", ["shots"])
    b.add("capture/-o/is_existing_file", base, "2", protect=["shots"], setup=[("shots", "file")])
    b.add("capture/-o/parent_is_file", _sub(base, 6, "blocker/shots"), "2", setup=[("blocker", "file")])
    b.add("capture/-o/read_only", _sub(base, 6, f"{READ_ONLY_DIR}/shots"), "2")
    b.add("capture/-o/exists_nonempty", base, "0or2", protect=["shots/keep.txt"], setup=[("shots", "mkdir")])

    _survey_and_atr_cases(b, F)

    # real data (../shared/data; skipped when absent) ----------------------------------
    D, S = "{data}", "shared_data"
    eth = f"{D}/stereo/eth3d_two_view/playground"
    tsu = f"{D}/stereo/middlebury_2001_2003/tsukuba"
    b.add("real/match/--num-disp/100000_tsukuba", ["match", f"{tsu}/im3.png", f"{tsu}/im4.png", "-o", "d.pfm",
                                                   "--num-disp", "100000"], "0or2", ["d.pfm"], needs=S)
    b.add("real/match/RIGHT/other_size", ["match", f"{tsu}/im3.png", f"{eth}/im1.png", "-o", "d.pfm",
                                          "--num-disp", "16"], "2", ["d.pfm"], needs=S)
    b.add("real/triangulate/--left/wrong_size", ["triangulate", f"{eth}/disp0.pfm", "--calib", f"{eth}/calib.txt",
                                                 "--left", f"{F}/bad/grey10.png", "-o", "c.ply"], "2", ["c.ply"],
          needs=S)
    b.add("real/triangulate/--calib/prism_rig_for_eth3d", ["triangulate", f"{eth}/disp0.pfm", "--calib",
                                                           f"{F}/rig.yaml", "--left", f"{eth}/im0.png", "-o",
                                                           "c.ply"], "2", ["c.ply"], needs=S)
    b.add("real/reconstruct/--left/tsukuba_with_eth3d_calib", ["reconstruct", "--left", f"{tsu}/im3.png", "--right",
                                                               f"{tsu}/im4.png", "--calib", f"{eth}/calib.txt",
                                                               "-o", "s.ply"], "2", ["s.ply"], needs=S)
    b.add("real/features/SCAN/organised_pcd_wrong_suffix", [
        "features", f"{D}/pointclouds/pcl/table_scene_mug_stereo_textured.pcd", "--units", "m", "--up", "y",
        "-o", "f.csv"], "2", ["f.csv"], needs=S)
    b.add("real/stitch/SCANS/pcd_and_garbage", ["stitch", f"{D}/pointclouds/pcl/bun0.pcd", f"{F}/bad/garbage.ply",
                                                "-o", "m.ply"], "2", ["m.ply", "poses.json"], needs=S)

    # the {trigger} placeholder means a running simulated controller
    out = []
    for c in b.cases:
        if any("{trigger}" in a for a in c.argv) and c.needs is None:
            c = dataclasses.replace(c, needs="trigger")
        out.append(c)
    ids = [c.id for c in out]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:  # pragma: no cover - a mistake in this file
        raise ValueError(f"duplicate case ids: {sorted(dup)}")
    return out


def command_of(case_id: str) -> str:
    return case_id.split("/", 1)[0]
