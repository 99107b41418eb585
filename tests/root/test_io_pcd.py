"""PCD reader: ascii, binary, binary_compressed (LZF), against real PCL/Open3D files."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.io._pcd_kernels import lzf_decompress
from prism3d.io.pcd import read_pcd


def _header(fields="x y z", size="4 4 4", typ="F F F", count="1 1 1", n=3, data="ascii"):
    return (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {typ}\nCOUNT {count}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode()


def _lzf_literals(raw: bytes) -> bytes:
    out = bytearray()
    for i in range(0, len(raw), 32):
        chunk = raw[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def test_ascii_with_packed_rgb_and_nan(tmp_path):
    rgb = struct.unpack("<f", struct.pack("<I", (10 << 16) | (20 << 8) | 30))[0]
    body = f"1 2 3 {rgb!r}\nnan nan nan {rgb!r}\n4 5 6 {rgb!r}\n"
    p = tmp_path / "a.pcd"
    p.write_bytes(_header("x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1") + body.encode())
    d = read_pcd(p)
    np.testing.assert_allclose(d.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(d.colors, [[10, 20, 30], [10, 20, 30]])
    assert d.n_dropped == 1


def test_binary_and_compressed_roundtrip(tmp_path):
    pts = np.array([[1.5, -2.0, 3.0], [0.25, 0.5, 0.75], [7, 8, 9]], dtype="<f4")
    rgba = np.array([0xFF010203, 0xFF040506, 0xFF070809], dtype="<u4")
    rec = np.empty(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["rgba"] = pts[:, 0], pts[:, 1], pts[:, 2], rgba
    hdr = dict(fields="x y z rgba", size="4 4 4 4", typ="F F F U", count="1 1 1 1")
    pb = tmp_path / "b.pcd"
    pb.write_bytes(_header(**hdr, data="binary") + rec.tobytes())
    soa = b"".join(rec[f].tobytes() for f in ("x", "y", "z", "rgba"))
    comp = _lzf_literals(soa)
    pc = tmp_path / "c.pcd"
    pc.write_bytes(_header(**hdr, data="binary_compressed") + struct.pack("<II", len(comp), len(soa)) + comp)
    for p in (pb, pc):
        d = read_pcd(p)
        np.testing.assert_array_equal(d.points, pts.astype(np.float64))
        np.testing.assert_array_equal(d.colors, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def test_lzf_back_reference():
    # "abc" literal, then a back reference of length 6 at distance 3 -> "abcabcabc".
    src = np.frombuffer(bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2]), dtype=np.uint8)
    out, n = lzf_decompress(src, 9)
    assert n == 9 and out.tobytes() == b"abcabcabc"
    bad = np.frombuffer(bytes([(1 << 5) | 0, 5]), dtype=np.uint8)
    assert lzf_decompress(bad, 10)[1] == -1


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"hello\n", "not a PCD file"),
        (_header(fields="rgba", size="4", typ="U", count="1"), "no 'x' field"),
        (_header(data="weird"), "unknown PCD DATA mode"),
        (_header(data="binary") + b"\0" * 10, "truncated"),
        (_header() + b"1 2 3\n", "ascii PCD has 3 values"),
        (_header(size="4 4", typ="F F F"), "lengths differ"),
        (_header(typ="X F F"), "unsupported PCD field"),
        (_header(data="binary_compressed") + struct.pack("<II", 4, 36) + b"\xff\xff\xff\xff", "corrupt LZF"),
        (_header(data="binary_compressed") + struct.pack("<II", 4, 12), "holds 12 bytes"),
    ],
)
def test_errors(tmp_path, content, match):
    p = tmp_path / "bad.pcd"
    p.write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_pcd(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="nope.pcd"):
        read_pcd(tmp_path / "nope.pcd")


@pytest.mark.parametrize(
    ("name", "n", "has_color", "has_normals"),
    [
        ("pcl/bun0.pcd", 397, False, True),
        ("pcl/bun4.pcd", 361, False, False),
        ("pcl/car6.pcd", 10031, False, False),
        ("pcl/milk.pcd", 13704, False, False),
        ("pcl/table_scene_mug_stereo_textured.pcd", 209280, True, False),
        ("open3d_fragments/cloud_bin_0_down.pcd", 3903, True, True),
    ],
)
def test_real_files_match_open3d(shared_data, name, n, has_color, has_normals):
    o3d = pytest.importorskip("open3d")
    path = shared_data / "pointclouds" / name
    d = read_pcd(path)
    assert d.points.shape == (n, 3)
    assert (d.colors is not None) == has_color and (d.normals is not None) == has_normals
    ref = o3d.io.read_point_cloud(str(path), remove_nan_points=True, remove_infinite_points=True)
    np.testing.assert_allclose(d.points, np.asarray(ref.points), atol=1e-6)
    if has_color:
        np.testing.assert_allclose(d.colors / 255.0, np.asarray(ref.colors), atol=1e-6)
    if name.startswith("pcl/table"):
        assert d.n_dropped == 640 * 480 - n and d.height == 480


def test_compressed_pcd_claiming_gigabytes_is_refused_before_allocating(tmp_path):
    """A 100-byte binary_compressed PCD whose header claims 300 M points (3.6 GB)."""
    import resource
    import struct

    n = 300_000_000
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
              f"WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary_compressed\n").encode()
    p = tmp_path / "bomb.pcd"
    p.write_bytes(header + struct.pack("<II", 16, n * 12) + b"\x00" * 16)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match="more than LZF can expand to"):
        read_pcd(p)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000  # KB
