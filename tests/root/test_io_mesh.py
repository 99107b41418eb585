from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.io.mesh import UNITS_MM, read_mesh


def test_round_trip_formats(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 3.0, 4.0))
    for ext in ("obj", "ply", "stl", "off", "glb"):
        f = tmp_path / f"b.{ext}"
        box.export(f)
        m = read_mesh(f)
        np.testing.assert_allclose(m.vertices.max(0) - m.vertices.min(0), (2, 3, 4), atol=1e-6)
        assert m.faces.shape[1] == 3 and len(m.faces) >= 12


def test_scene_transforms_are_applied(tmp_path):
    import trimesh

    a = trimesh.creation.box(extents=(1, 1, 1))
    sc = trimesh.Scene()
    T = np.eye(4)
    T[:3, 3] = (10, 0, 0)
    sc.add_geometry(a, transform=np.eye(4))
    sc.add_geometry(a.copy(), transform=T)
    sc.export(tmp_path / "s.glb")
    m = read_mesh(tmp_path / "s.glb")
    np.testing.assert_allclose(m.vertices[:, 0].max(), 10.5, atol=1e-6)


def test_units_table():
    assert UNITS_MM == {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


def test_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_mesh(tmp_path / "none.obj")
    (tmp_path / "x.xyz").write_text("1 2 3")
    with pytest.raises(InputError, match="unsupported mesh format"):
        read_mesh(tmp_path / "x.xyz")
    (tmp_path / "e.obj").write_text("v 0 0 0\n")
    with pytest.raises(InputError, match="no triangles|cannot read"):
        read_mesh(tmp_path / "e.obj")
    (tmp_path / "c.glb").write_bytes(b"glTF garbage")
    with pytest.raises(InputError, match="cannot read|no triangles"):
        read_mesh(tmp_path / "c.glb")


@pytest.mark.realdata
def test_real_mesh_colours_and_formats_agree(shared_data):
    m = read_mesh(shared_data / "meshes" / "quaternius_vehicles_cc0" / "obj" / "tank_1.obj")
    assert len(m.faces) > 100
    assert m.vertex_colors is not None and m.vertex_colors.std(axis=0).max() > 0.01  # material (Kd) colours
    g = read_mesh(shared_data / "meshes" / "quaternius_vehicles_cc0" / "glb" / "tank_1.glb")
    np.testing.assert_allclose(g.vertices.max(0) - g.vertices.min(0), m.vertices.max(0) - m.vertices.min(0),
                               rtol=1e-3)  # the same model in both formats


@pytest.mark.realdata
def test_glb_keeps_its_base_colours_like_the_obj(shared_data):
    """Quaternius GLBs carry their paint as baseColorFactor beside the specular-glossiness
    extension, which trimesh reads as white: every model with both files gives the OBJ's
    paint (area-weighted mean RGB within 2 of 255)."""
    root = shared_data / "meshes" / "quaternius_vehicles_cc0"
    pairs = [(g, root / "obj" / (g.stem + ".obj")) for g in sorted((root / "glb").glob("*.glb"))]
    pairs = [(g, o) for g, o in pairs if o.exists()]
    assert pairs
    def paint(m):  # the area-weighted mean colour (vertex counts differ between the formats)
        v, f = m.vertices, m.faces
        area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        return (m.vertex_colors[f].mean(axis=1) * area[:, None]).sum(0) / area.sum()

    compared = 0
    for glb, obj in pairs:
        g, o = read_mesh(glb), read_mesh(obj)
        assert (g.vertex_colors is None) == (o.vertex_colors is None), glb.name  # textured: none in both
        if g.vertex_colors is None:
            continue
        compared += 1
        diff = np.abs(paint(g) - paint(o)) * 255
        assert diff.max() < 2.0, (glb.name, diff)
    assert compared >= len(pairs) // 2, compared


def test_vertex_colours_of_ply_and_off_files_are_read(tmp_path):
    """A coloured PLY (a stitched scan's mesh, an exported built-in target; colours per
    vertex or per face) keeps its colours (they read as 0.7 grey before: trimesh's per-vertex colour
    visuals have no texture conversion)."""
    import trimesh

    from prism3d.datasets.models.targets import builtin_target, export_builtin_target

    export_builtin_target("tank_t1", tmp_path / "t.ply")
    d = read_mesh(tmp_path / "t.ply")
    true = builtin_target("tank_t1").vertex_colors()
    assert d.vertex_colors is not None
    assert np.abs(np.median(d.vertex_colors, axis=0) - np.median(true, axis=0)).max() < 1.5 / 255
    box = trimesh.creation.box([1, 1, 1])
    box.visual = trimesh.visual.ColorVisuals(box, face_colors=[200, 10, 10, 255])
    box.export(tmp_path / "b.ply")  # colours per face
    d = read_mesh(tmp_path / "b.ply")
    np.testing.assert_allclose(d.vertex_colors.mean(axis=0), np.array([200, 10, 10]) / 255, atol=1 / 255)
