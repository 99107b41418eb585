from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.io.ply import read_ply, write_ply


def _cloud(n=50, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * 100
    cols = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    return pts, cols, nrm


def test_round_trip_full(tmp_path):
    pts, cols, nrm = _cloud()
    faces = np.array([[0, 1, 2], [2, 3, 4]])
    conf = np.linspace(0, 1, len(pts)).astype(np.float32)
    write_ply(tmp_path / "m.ply", pts, colors=cols, normals=nrm, faces=faces,
              extra={"confidence": conf}, comments=["units mm"], double=True)
    d = read_ply(tmp_path / "m.ply")
    np.testing.assert_array_equal(d.points, pts)
    np.testing.assert_array_equal(d.colors, cols)
    np.testing.assert_array_equal(d.normals, nrm)
    np.testing.assert_array_equal(d.faces, faces)
    np.testing.assert_array_equal(d.extra["confidence"], conf)
    assert d.comments == ["units mm"]


def test_comments_stay_one_ascii_line(tmp_path):
    """A comment cannot break the header: line breaks become spaces, non-ASCII escapes."""
    pts, _, _ = _cloud()
    write_ply(tmp_path / "c.ply", pts, comments=["source ü.obj\nend_header", "units mm"], double=True)
    d = read_ply(tmp_path / "c.ply")
    np.testing.assert_array_equal(d.points, pts)
    assert d.comments == ["source \\xfc.obj end_header", "units mm"]


def test_float32_default_and_float_colours(tmp_path):
    pts, _, _ = _cloud()
    write_ply(tmp_path / "p.ply", pts, colors=np.full((len(pts), 3), 0.5))
    d = read_ply(tmp_path / "p.ply")
    np.testing.assert_allclose(d.points, pts.astype(np.float32))
    assert np.all(d.colors == 128)
    assert d.faces is None and d.normals is None


def test_open3d_reads_ours_and_we_read_open3d(tmp_path):
    import open3d as o3d

    pts, cols, nrm = _cloud()
    write_ply(tmp_path / "ours.ply", pts, colors=cols, normals=nrm)
    pc = o3d.io.read_point_cloud(str(tmp_path / "ours.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), pts, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(np.asarray(pc.colors) * 255, cols, atol=0.51)
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    for ascii_ in (False, True):
        o3d.io.write_triangle_mesh(str(tmp_path / "box.ply"), mesh, write_ascii=ascii_)
        d = read_ply(tmp_path / "box.ply")
        np.testing.assert_allclose(d.points, np.asarray(mesh.vertices), atol=1e-6)
        np.testing.assert_array_equal(d.faces, np.asarray(mesh.triangles))


def test_ascii_and_big_endian_and_quads(tmp_path):
    txt = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    (tmp_path / "q.ply").write_text(txt)
    d = read_ply(tmp_path / "q.ply")
    np.testing.assert_array_equal(d.faces, [[0, 1, 2], [0, 2, 3]])
    hdr = (b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\n"
           b"property double y\nproperty double z\nend_header\n")
    body = np.array([1, 2, 3, 4, 5, 6], ">f8").tobytes()
    (tmp_path / "be.ply").write_bytes(hdr + body)
    np.testing.assert_array_equal(read_ply(tmp_path / "be.ply").points, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    "content, match",
    [
        (b"hello", "not a PLY"),
        (b"ply\nelement vertex 1\nproperty float x\nend_header\n", "no format"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\n"
         b"property float z\nend_header\n" + bytes(20), "truncated"),
        (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
         b"end_header\n1 2 3\n", "truncated"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n", "x, y, z"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quux x\nend_header\n", "malformed property"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
         b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n",
         "out of range"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\nend_header\n", "malformed element"),
    ],
)
def test_malformed(tmp_path, content, match):
    p = tmp_path / "bad.ply"
    p.write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_ply(p)


def test_write_validation(tmp_path):
    with pytest.raises(InputError, match="points"):
        write_ply(tmp_path / "a.ply", np.zeros((3, 2)))
    with pytest.raises(InputError, match="faces"):
        write_ply(tmp_path / "a.ply", np.zeros((3, 3)), faces=np.array([[0, 1, 5]]))
    assert not (tmp_path / "a.ply").exists()
