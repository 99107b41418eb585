"""Known-answer tests for the built-in procedural targets (prism3d.datasets.models.targets)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import trimesh

from prism3d.capture.mesh import SceneMesh, UniformAlbedo
from prism3d.capture.camouflage import CLASS_PALETTES, PALETTES, CamouflageField
from prism3d.datasets.models.targets import builtin_classes, builtin_target, list_builtin_targets
from prism3d.errors import InputError

NAMES = list_builtin_targets("military")


@pytest.fixture(scope="module")
def targets() -> dict[str, SceneMesh]:
    return {name: builtin_target(name) for name in NAMES}


def _surface_points(mesh: SceneMesh, n: int = 20000) -> np.ndarray:
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    pts, _ = trimesh.sample.sample_surface(tm, n, seed=0)
    return np.asarray(pts, dtype=np.float64)


def test_names_and_classes_are_stable() -> None:
    assert builtin_classes("military") == ["tank", "jet", "ship", "truck"]
    assert NAMES[:3] == ["tank_t1", "tank_t2", "tank_t3"]
    assert len(NAMES) == len(set(NAMES)) == 12
    assert list_builtin_targets("military") == NAMES  # stable order, fresh list
    for cls in builtin_classes("military"):
        assert sum(n.startswith(cls + "_") for n in NAMES) >= 3


def test_metadata_and_sizes(targets: dict[str, SceneMesh]) -> None:
    for name, m in targets.items():
        md = m.metadata
        cls, variant = name.split("_")
        assert md["class"] == cls and md["variant"] == variant and md["name"] == name
        assert md["provenance"] == "builtin procedural"
        assert md["scale"] == pytest.approx(md["model_scale"])
        ext = m.extent_mm
        np.testing.assert_allclose([md["length_mm"], md["width_mm"], md["height_mm"]], ext)
        # documented range: 150-280 mm long, fits a 300 x 300 mm field
        assert 150.0 <= md["length_mm"] <= 280.0, name
        assert md["width_mm"] <= 280.0 and md["height_mm"] <= 280.0, name
        # object frame: footprint centred on the origin, lowest point on the ground
        lo, hi = m.bounds
        np.testing.assert_allclose(lo[:2], -hi[:2], atol=1e-9)
        assert lo[2] == pytest.approx(0.0, abs=1e-9)
        assert md["full_length_mm"] == pytest.approx(md["length_mm"] / md["model_scale"])
        assert md["camouflage"] == CLASS_PALETTES[cls]
        assert md["description"] and md["features"]


def test_real_sizes_are_plausible(targets: dict[str, SceneMesh]) -> None:
    full_m = {n: m.metadata["full_length_mm"] / 1000 for n, m in targets.items()}
    ranges = {"tank": (6, 12.5), "jet": (14, 22), "ship": (140, 320), "truck": (6, 10)}
    for name, length in full_m.items():
        lo, hi = ranges[name.split("_")[0]]
        assert lo <= length <= hi, (name, length)


def test_meshes_are_closed_oriented_and_clean(targets: dict[str, SceneMesh]) -> None:
    for name, m in targets.items():
        assert len(m.vertices) < 50_000
        tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
        assert tm.is_watertight, name
        assert tm.is_winding_consistent, name
        assert tm.area_faces.min() > 1e-3, name  # no degenerate faces (mm^2)
        parts = tm.split(only_watertight=False)
        assert len(parts) == m.metadata["parts"], name
        # every closed part has outward normals: positive enclosed volume
        assert min(p.volume for p in parts) > 0, name


def test_geometry_deterministic_and_seed_changes_only_paint() -> None:
    a = builtin_target("jet_j2", seed=3)
    b = builtin_target("jet_j2", seed=3)
    c = builtin_target("jet_j2", seed=4)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.vertices, c.vertices)
    np.testing.assert_array_equal(a.faces, c.faces)
    pts = _surface_points(a, 5000)
    np.testing.assert_array_equal(a.albedo_field(pts), b.albedo_field(pts))
    changed = np.any(a.albedo_field(pts) != c.albedo_field(pts), axis=1).mean()
    assert changed > 0.2
    np.testing.assert_array_equal(a.vertex_colors(), b.vertex_colors())


def test_variants_differ(targets: dict[str, SceneMesh]) -> None:
    for cls in builtin_classes("military"):
        names = [n for n in NAMES if n.startswith(cls + "_")]
        for p, q in itertools.combinations(names, 2):
            ep, eq = targets[p].extent_mm, targets[q].extent_mm
            # proportions differ by more than 3 % somewhere, or the part structure differs
            prop = np.abs(ep / ep[0] - eq / eq[0]).max()
            assert prop > 0.03 or targets[p].metadata["parts"] != targets[q].metadata["parts"]
            assert targets[p].metadata["features"] != targets[q].metadata["features"]
            assert len(targets[p].vertices) != len(targets[q].vertices) or prop > 0.03


def test_camouflage_takes_exactly_palette_colours(targets: dict[str, SceneMesh]) -> None:
    for name, m in targets.items():
        field = m.albedo_field
        assert isinstance(field, CamouflageField)
        palette = np.array(PALETTES[m.metadata["camouflage"]].colors)
        pts = _surface_points(m)
        alb = field(pts)
        colours, counts = np.unique(alb, axis=0, return_counts=True)
        # piecewise constant: every value is exactly one of the palette colours
        assert all(any(np.array_equal(c, p) for p in palette) for c in colours), name
        frac = counts / counts.sum()
        assert len(colours) == len(palette), name
        assert frac.min() > 0.03, (name, frac)
        # dark (shadow-like) patches exist and cover a real share of the surface
        lum = alb @ np.array([0.2126, 0.7152, 0.0722])
        assert (lum < 0.1).mean() > 0.05, name


def test_camouflage_off_gives_uniform_base_coat() -> None:
    m = builtin_target("tank_t2", camouflage=False)
    assert isinstance(m.albedo_field, UniformAlbedo)
    alb = m.albedo_at(_surface_points(m, 2000), np.zeros(2000, dtype=np.int64), np.zeros((2000, 2)))
    base = np.array(PALETTES["woodland"].colors[0])
    np.testing.assert_array_equal(alb, np.broadcast_to(base, alb.shape))
    assert m.metadata["camouflage"] == "none"
    ship = builtin_target("ship_s1", camouflage=False, palette="desert")
    np.testing.assert_array_equal(ship.vertex_colors()[0], PALETTES["desert"].colors[0])


def test_scale_full_and_numeric(targets: dict[str, SceneMesh]) -> None:
    for name in ("tank_t1", "ship_s3", "truck_k2"):
        model = targets[name]
        full = builtin_target(name, scale="full")
        s = model.metadata["model_scale"]
        np.testing.assert_allclose(full.extent_mm, model.extent_mm / s, rtol=1e-9)
        np.testing.assert_allclose(full.vertices, model.vertices / s, rtol=1e-9, atol=1e-6)
        assert full.metadata["scale"] == 1.0
        assert full.metadata["length_mm"] == pytest.approx(model.metadata["full_length_mm"])
        same = builtin_target(name, scale=s)
        np.testing.assert_array_equal(same.vertices, model.vertices)
    half = builtin_target("jet_j1", scale=0.5)
    full_length = targets["jet_j1"].metadata["full_length_mm"]
    np.testing.assert_allclose(half.metadata["length_mm"], full_length / 2)
    # full-size tank is 7-12 m long
    assert 7000 < builtin_target("tank_t3", scale="full").metadata["length_mm"] < 12000


def test_camouflage_pattern_scales_with_the_model(targets: dict[str, SceneMesh]) -> None:
    model = targets["tank_t3"]
    full = builtin_target("tank_t3", scale="full")
    s = model.metadata["model_scale"]
    pts = _surface_points(model, 5000)
    agree = (model.albedo_field.labels(pts) == full.albedo_field.labels(pts / s)).mean()
    assert agree > 0.999
    assert full.metadata["patch_size_mm"] == pytest.approx(model.metadata["patch_size_mm"] / s)


def test_targets_do_not_share_a_pattern() -> None:
    a = builtin_target("truck_k1").albedo_field
    b = builtin_target("truck_k3").albedo_field
    pts = np.random.default_rng(0).uniform(-100, 100, (5000, 3))
    assert (a.labels(pts) != b.labels(pts)).mean() > 0.2


def test_palette_override() -> None:
    m = builtin_target("tank_t1", palette="desert")
    assert m.metadata["camouflage"] == "desert"
    assert m.albedo_field.colors == PALETTES["desert"].colors


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"name": "tank_x9"}, r"unknown built-in target 'tank_x9'; valid names: tank_t1, tank_t2"),
        ({"name": "tank_t1", "scale": "huge"}, r"scale: expected 'model', 'full' or a positive"),
        ({"name": "tank_t1", "scale": -1.0}, r"scale: expected a finite ratio to full size > 0"),
        ({"name": "tank_t1", "scale": float("nan")}, r"scale: expected a finite ratio"),
        ({"name": "tank_t1", "scale": True}, r"scale: expected 'model', 'full' or a positive"),
        ({"name": "tank_t1", "scale": [1.0]}, r"scale: expected 'model', 'full' or a positive"),
        ({"name": "tank_t1", "seed": -1}, r"seed: expected a non-negative integer"),
        ({"name": "tank_t1", "seed": 1.5}, r"seed: expected a non-negative integer"),
        ({"name": "tank_t1", "palette": "pink"}, r"palette: expected one of woodland"),
        ({"name": "tank_t1", "palette": "pink", "camouflage": False}, r"palette: expected one of"),
    ],
)
def test_builtin_target_errors(kwargs: dict, match: str) -> None:
    name = kwargs.pop("name")
    with pytest.raises(InputError, match=match):
        builtin_target(name, **kwargs)


def test_export_builtin_target_ply(tmp_path) -> None:
    from prism3d.datasets.models.targets import export_builtin_target
    from prism3d.io.ply import read_ply

    out = export_builtin_target("truck_k2", tmp_path / "k2.ply", seed=1)
    assert out == tmp_path / "k2.ply"
    ply = read_ply(out)
    ref = builtin_target("truck_k2", seed=1)
    np.testing.assert_allclose(ply.points.max(0) - ply.points.min(0), ref.extent_mm, atol=1e-3)
    assert ply.faces is not None and len(ply.faces) > len(ref.faces)  # split for the paint
    palette = np.round(np.array(PALETTES["woodland"].colors) * 255).astype(np.uint8)
    assert set(map(tuple, ply.colors)) <= set(map(tuple, palette))
    assert any("truck_k2" in c for c in ply.comments)
    plain = read_ply(export_builtin_target("truck_k2", tmp_path / "p.ply", camouflage=False))
    assert len(plain.faces) == len(ref.faces) and len(np.unique(plain.colors, axis=0)) == 1


def test_export_errors(tmp_path) -> None:
    from prism3d.datasets.models.targets import export_builtin_target

    with pytest.raises(InputError, match=r"expected a \.ply output file, got suffix '\.obj'"):
        export_builtin_target("tank_t1", tmp_path / "t.obj")
    with pytest.raises(InputError, match=r"output folder .* does not exist"):
        export_builtin_target("tank_t1", tmp_path / "missing" / "t.ply")
    with pytest.raises(InputError, match=r"max_edge_mm: expected a finite number > 0"):
        export_builtin_target("tank_t1", tmp_path / "t.ply", max_edge_mm=0)
    with pytest.raises(InputError, match=r"unknown built-in target"):
        export_builtin_target("nope", tmp_path / "t.ply")
    assert not any(tmp_path.iterdir())  # no partial output


@pytest.mark.realdata
def test_mixed_up_axes_in_one_bank_command(shared_data, tmp_path):
    """Quaternius' tanks are y up, its cars z up: per-target FILE=CLASS:UNITS:UP specs
    stand each upright (height the smallest extent) and one `bank train` takes both."""
    from prism3d.cli import main
    from prism3d.datasets.database.resolve import resolve_targets

    glb = shared_data / "meshes" / "quaternius_vehicles_cc0" / "glb"
    specs = [f"{glb / 'tank_1.glb'}=tank:m:y:z", f"{glb / 'car_normal_1.glb'}=vehicle:m:z:y"]
    for cls, mesh in resolve_targets(specs):
        ext = mesh.extent_mm
        assert ext[2] < min(ext[0], ext[1]), (cls, ext)  # upright: lower than long or wide
    out = tmp_path / "b.npz"
    assert main(["--quiet", "bank", "train", "--scenes", "0", "--targets", *specs, "-o", str(out), "--azimuth", "0:360:90",
                 "--elevation", "20:20:1", "--size", "32", "--no-camouflage"]) == 0
    with pytest.raises(Exception, match="FILE\\[=CLASS"):
        resolve_targets([f"{glb / 'tank_1.glb'}=tank:m:y:z:extra"])


def test_size_warning_by_class():
    """A length implausible for the class in its stated units is named; kits to full size pass."""
    from prism3d.datasets.database.ingest import size_warning

    assert size_warning("a.off", "aircraft", 357_000.0, "m") is not None  # a 357 m biplane
    assert "357 m long with units 'm'" in size_warning("a.off", "aircraft", 357_000.0, "m")
    assert size_warning("t.obj", "tank", 7500.0, "mm") is None  # full size
    assert size_warning("t.obj", "tank", 215.0, "mm") is None  # a 1:35 kit
    assert size_warning("t.obj", "tank", 2.0, "mm") is not None  # smaller than any kit
    assert size_warning("x.obj", "robot", 1e9, "mm") is None  # a class without a known size


@pytest.mark.realdata
def test_modelnet_airplane_in_metres_is_flagged(shared_data, caplog):
    from prism3d.datasets.database.resolve import resolve_targets

    f = shared_data / "meshes" / "modelnet_airplane" / "airplane_0001.off"
    with caplog.at_level("WARNING"):
        resolve_targets([f"{f}=aircraft:m:z:x"])
    assert "implausible for the class 'aircraft'" in caplog.text


def test_length_mm_rescales_mesh_files_whatever_their_units(tmp_path, capsys):
    """--length-mm on render and bank: an OFF file in arbitrary units (ModelNet's) becomes
    a target of the stated length without --units; built-in targets refuse it; without
    it the undeclared units are an error (never guessed)."""
    from prism3d.cli import main
    from prism3d.datasets.database.resolve import resolve_targets

    box = trimesh.creation.box([3.0, 1.0, 0.8])
    box.apply_translation([0, 0, 0.4])
    f = tmp_path / "crate_1.off"
    box.export(f)
    [(cls, mesh)] = resolve_targets([f"{f}=tank::z:x"], length_mm=215.0)
    assert cls == "tank" and mesh.extent_mm[0] == pytest.approx(215.0, rel=1e-6)
    assert mesh.extent_mm[2] == pytest.approx(215.0 * 0.8 / 3.0, rel=1e-6)
    assert main(["--quiet", "render", str(f), "-o", str(tmp_path / "chips"), "--up", "z", "--forward", "x",
                 "--length-mm", "215",
                 "--azimuth", "0:360:180", "--elevation", "20:20:1", "--size", "32"]) == 0
    import pandas as pd

    man = pd.read_parquet(next((tmp_path / "chips").glob("*.parquet")))
    assert len(man) == 2
    assert main(["--quiet", "bank", "train", "--scenes", "0", "--targets", f"{f}=tank", "tank_t1=other", "--up", "z",
                 "--forward", "x",
                 "--length-mm", "215", "-o", str(tmp_path / "b.npz"), "--azimuth", "0:360:90",
                 "--elevation", "20:20:1", "--size", "32"]) == 0
    capsys.readouterr()
    assert main(["--quiet", "render", str(f), "-o", str(tmp_path / "c2"), "--up", "z", "--forward", "x"]) == 2
    assert "units unknown" in capsys.readouterr().err
    assert main(["--quiet", "render", "tank_t1", "-o", str(tmp_path / "c3"), "--length-mm", "100"]) == 2
    assert "built-in target" in capsys.readouterr().err
    assert not (tmp_path / "c2").exists() and not (tmp_path / "c3").exists()
    with pytest.raises(Exception, match="length_mm"):
        resolve_targets([f"{f}=tank::z:x"], length_mm=-1.0)
