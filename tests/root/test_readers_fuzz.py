"""Every reader of a user's file raises only prism3d's error family, whatever the bytes:
the known bad inputs of a probe (truncated, empty, duplicate PLY properties, a 2x2 K1,
a header-only FileStorage, a non-integer schema_version, a cut-short bank...), then
random mutations of valid files (hypothesis, bounded)."""

from __future__ import annotations

import io
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prism3d.errors import Prism3dError

#: Mutated files per reader: 40 in the suite; ``PRISM3D_FUZZ_EXAMPLES=500`` gives the
#: 5000-file run of docs/hardening.md (10 readers).
FUZZ_EXAMPLES = int(os.environ.get("PRISM3D_FUZZ_EXAMPLES", "40"))


def _readers() -> dict[str, tuple[str, Callable[[Path], object]]]:
    from prism3d.atr.bank import FilterBank
    from prism3d.atr.features import read_units_sidecar
    from prism3d.capture.calib_formats import load_stereo_calibration
    from prism3d.capture.rig import StereoRig
    from prism3d.io.images import read_depth, read_image
    from prism3d.io.pcd import read_pcd
    from prism3d.io.pfm import read_pfm
    from prism3d.io.ply import read_ply

    return {
        "ply": (".ply", read_ply), "pcd": (".pcd", read_pcd), "pfm": (".pfm", read_pfm),
        "rig": (".yaml", StereoRig.load), "calib": (".yaml", load_stereo_calibration),
        "calib_txt": (".txt", load_stereo_calibration), "bank": (".npz", FilterBank.load),
        "depth_npz": (".npz", read_depth),
        "units": (".units.yaml", lambda p: read_units_sidecar(Path(str(p).removesuffix(".units.yaml")))), "image": (".png", read_image),
    }


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict[str, bytes]:
    """Valid files of each format, the seeds of the mutations."""
    from prism3d.capture.rig import paper_rig
    from prism3d.io.images import write_image
    from prism3d.io.pfm import write_pfm
    from prism3d.io.ply import write_ply

    d = tmp_path_factory.mktemp("valid")
    rng = np.random.default_rng(0)
    paper_rig().save(d / "rig.yaml")
    write_ply(d / "c.ply", rng.random((20, 3)), colors=np.zeros((20, 3), np.uint8), normals=rng.random((20, 3)))
    write_pfm(d / "d.pfm", rng.random((6, 7)).astype(np.float32))
    write_image(d / "i.png", rng.integers(0, 255, (9, 11, 3), dtype=np.uint8))
    buf = io.BytesIO()
    np.savez(buf, meta_json=np.frombuffer(b'{"schema_version": 1}', np.uint8), freqs=np.zeros((1, 4, 3)))
    dbuf = io.BytesIO()
    np.savez_compressed(dbuf, depth=rng.random((5, 6)).astype(np.float32))
    pcd = (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\n"
           b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n")
    return {"ply": (d / "c.ply").read_bytes(), "pcd": pcd, "pfm": (d / "d.pfm").read_bytes(),
            "rig": (d / "rig.yaml").read_bytes(), "calib": (d / "rig.yaml").read_bytes(),
            "calib_txt": b"cam0=[1000 0 320; 0 1000 240; 0 0 1]\ncam1=[1000 0 330; 0 1000 240; 0 0 1]\n"
                         b"doffs=10\nbaseline=120\nwidth=640\nheight=480\n",
            "bank": buf.getvalue(), "depth_npz": dbuf.getvalue(), "units": b"units: mm\nup: z\n", "image": (d / "i.png").read_bytes()}


def _probe_cases(valid: dict[str, bytes], reader: str) -> dict[str, bytes]:
    good = valid[reader]
    rig = valid["rig"]
    return {
        "empty": b"", "garbage": b"\x00\xff garbage \x80\x81\n", "not utf-8": b"\xff\xfe\xfa\n",
        "half": good[: len(good) // 2], "header-only FileStorage": b"%YAML:1.0\n---\n",
        "malformed map": b"%YAML:1.0\n---\nK1: [1, 2\n",
        "2x2 K1": rig.replace(b"rows: 3\n   cols: 3\n   dt: d\n   data: [", b"rows: 2\n   cols: 2\n   dt: d\n   data: [", 1),
        "schema_version abc": rig.replace(b"schema_version: 1", b"schema_version: abc"),
        "flip_left 7": rig.replace(b"flip_left: 0", b"flip_left: 7"),
        "duplicate PLY property": valid["ply"].replace(b"property float y", b"property float x", 1),
        "uchar 300": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                     b"property float z\nproperty uchar red\nend_header\n1 2 3 300\n",
        "PFM claiming 60000^2": b"Pf\n60000 60000\n-1\n" + b"\0" * 64,
    }


@pytest.mark.parametrize("reader", sorted(_readers()))
def test_known_bad_inputs_raise_our_errors(reader, valid, tmp_path):
    ext, read = _readers()[reader]
    for name, data in _probe_cases(valid, reader).items():
        p = tmp_path / f"case{ext}"
        p.write_bytes(data)
        try:
            read(p)
        except Prism3dError:
            pass
        except Exception as exc:  # noqa: BLE001 - the finding is the exception type itself
            pytest.fail(f"{reader} on {name!r}: {type(exc).__name__}: {exc}")


@st.composite
def _mutation(draw, seed: bytes) -> bytes:
    data = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "cut", "insert", "delete"]))
        i = draw(st.integers(0, max(len(data) - 1, 0)))
        if kind == "flip" and data:
            data[i] = draw(st.integers(0, 255))
        elif kind == "cut":
            data = data[:i]
        elif kind == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif data:
            del data[i : i + draw(st.integers(1, 16))]
    return bytes(data)


@pytest.mark.parametrize("reader", sorted(_readers()))
def test_mutated_files_raise_our_errors(reader, valid, tmp_path):
    ext, read = _readers()[reader]

    @settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True,
              suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
    @given(_mutation(valid[reader]))
    def check(data: bytes) -> None:
        p = tmp_path / f"m{ext}"
        p.write_bytes(data)
        try:
            read(p)
        except Prism3dError:
            pass

    check()
