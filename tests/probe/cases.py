"""The bad-input probe's case list (issue 27), reproducible from its description.

Per command and per input argument: missing, empty, a directory, garbage bytes, a
truncated valid file, wrong shape, NaN/inf values, absurd sizes (headers claiming
60000x60000 pixels or 300 M points, a zipped 20000^2 array: a decompression bomb),
negative/zero numbers; per output: an existing folder, an existing file, a parent that
is a regular file, a read-only place, a missing parent folder, a suffix that does not
match the format, two outputs naming one file.

:func:`build_fixtures` writes the valid inputs and the bad files once (< 20 s);
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
    if rc == 2 and (len(lines) != 1 or not lines[0].startswith("prism3d ")):
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
    """Write the valid inputs and the bad files under ``root`` (~10 s); return named paths."""
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
    for ext, src in valid.items():
        (bad / f"empty.{ext}").write_bytes(b"")
        (bad / f"dir.{ext}").mkdir()
        (bad / f"garbage.{ext}").write_bytes(b"\x00\xff garbage \x80\x81\n" * 7)
        data = src.read_bytes()
        (bad / f"truncated.{ext}").write_bytes(data[: len(data) // 2])
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
    return {"root": root}


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
_EXT = {"png": "png", "yaml": "yaml", "pfm": "pfm", "ply": "ply", "obj": "obj", "npz": "npz", "depth": "npy"}


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
