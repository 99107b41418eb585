"""Tests of prism3d.atr.chips: exact depth, shading, framing, clutter, files."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from prism3d.atr.chips import ChipSpec, chip_poses, load_mesh_file, render_chips, render_to_folder
from prism3d.capture.mesh import SceneMesh, UniformAlbedo

from prism3d.errors import InputError


@pytest.fixture(scope="module")
def builtin_tank() -> SceneMesh:
    from prism3d.datasets.models.targets import builtin_target

    return builtin_target("tank_t1")


def _cube(half: float = 50.0) -> SceneMesh:
    v = np.array(
        [[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)], float
    )
    f = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return SceneMesh(v, f, albedo_field=UniformAlbedo((0.5, 0.5, 0.5)), name="cube")


def test_depth_exact_no_flying_pixels():
    cube = _cube()
    poses = chip_poses(cube, [0.0], [0.0], [1000.0], size=33, framing="range", pixels_per_m=300.0)
    cs = render_chips(cube, poses, chip_spec=ChipSpec(size=33))
    d = cs["depth"][0]
    m = cs["mask"][0]
    assert d[16, 16] == pytest.approx(950.0, abs=1e-6)
    # every surface pixel is on the front face (z = 950 exactly): no edge mixing
    np.testing.assert_allclose(d[m], 950.0, atol=1e-6)
    assert np.all(np.isnan(d[~m]))
    # analytic silhouette: pixel centres with |u - 16| <= f * 50 / 950
    half_px = 300.0 * 50 / 950
    u = np.abs(np.arange(33) - 16.0)
    expect = (u[:, None] < half_px) & (u[None, :] < half_px)
    np.testing.assert_array_equal(m, expect)


def test_shape_and_intensity_lambertian():
    cube = _cube()
    cs = render_chips(
        cube,
        azimuth=[30.0],
        elevation=20.0,
        range_mm=800.0,
        chip_spec=ChipSpec(size=48, camouflage=False, ambient=0.2),
    )
    m = cs["mask"][0]
    ratio = cs["intensity"][0][m] / cs["shape"][0][m]
    np.testing.assert_allclose(ratio, 0.5, rtol=1e-5)  # uniform grey paint 0.5
    assert cs["shape"][0][m].min() >= 0.2 - 1e-6
    assert len(np.unique(np.round(cs["shape"][0][m], 4))) >= 2  # different faces, different shading
    assert cs.table.shape[0] == 1 and "light_x" in cs.table


def test_framing_fit_vs_range(builtin_tank):
    fit = render_chips(
        builtin_tank,
        azimuth=[90.0],
        elevation=10.0,
        range_mm=[1000.0, 2000.0],
        chip_spec=ChipSpec(size=48, framing="fit", channels=("mask",)),
    )
    rng = render_chips(
        builtin_tank,
        azimuth=[90.0],
        elevation=10.0,
        range_mm=[1000.0, 2000.0],
        chip_spec=ChipSpec(size=48, framing="range", channels=("mask",)),
    )
    a_fit = fit["mask"].sum(axis=(1, 2))
    a_rng = rng["mask"].sum(axis=(1, 2))
    assert abs(a_fit[0] - a_fit[1]) / a_fit[0] < 0.05  # range-invariant
    assert a_rng[1] / a_rng[0] == pytest.approx(0.25, rel=0.15)  # area ~ 1/range^2


def test_clutter_noise_determinism(builtin_tank):
    kw = {
        "azimuth": "0:360:120",
        "elevation": 25.0,
        "chip_spec": ChipSpec(
            size=48, clutter="ground", noise_sigma=0.05, lighting_variation=10.0, seed=4
        ),
    }
    a = render_chips(builtin_tank, **kw)
    b = render_chips(builtin_tank, **kw)
    for ch in ("intensity", "depth", "mask", "shape"):
        np.testing.assert_array_equal(a[ch], b[ch])
    assert (
        np.isfinite(a["depth"]).mean() > a["mask"].mean() + 0.3
    )  # the ground fills the background
    n = render_chips(
        builtin_tank,
        azimuth=[0.0],
        elevation=20.0,
        chip_spec=ChipSpec(size=48, clutter="noise", channels=("intensity", "mask")),
    )
    assert n["intensity"][0][~n["mask"][0]].std() > 0.01
    c = render_chips(
        builtin_tank,
        azimuth=[0.0],
        elevation=20.0,
        chip_spec=ChipSpec(size=48, seed=1, noise_sigma=0.0, channels=("intensity",), camouflage=True),
    )
    d = render_chips(
        builtin_tank,
        azimuth=[0.0],
        elevation=20.0,
        chip_spec=ChipSpec(size=48, seed=1, noise_sigma=0.0, channels=("intensity",), camouflage=False),
    )
    assert not np.array_equal(c["intensity"], d["intensity"])


def test_pyrender_backend_matches_raycast(builtin_tank):
    pytest.importorskip("pyrender")
    kw = {"azimuth": [45.0], "elevation": 20.0}
    spec = ChipSpec(size=48, channels=("depth", "mask"))
    a = render_chips(builtin_tank, chip_spec=spec, **kw)
    b = render_chips(builtin_tank, chip_spec=replace(spec, backend="pyrender"), **kw)
    both = a["mask"][0] & b["mask"][0]
    assert (a["mask"][0] != b["mask"][0]).mean() < 0.02
    assert np.median(np.abs(a["depth"][0][both] - b["depth"][0][both])) < 0.5


def test_render_errors(builtin_tank):
    with pytest.raises(InputError, match="inside"):
        render_chips(builtin_tank, range_mm=10.0, chip_spec=ChipSpec(size=32))
    with pytest.raises(InputError, match="SceneMesh"):
        render_chips("tank", chip_spec=ChipSpec(size=32))
    with pytest.raises(InputError, match="chip_spec: expected a ChipSpec"):
        render_chips(builtin_tank, chip_spec={"size": 32})
    with pytest.raises(InputError, match="empty mesh"):
        SceneMesh(np.zeros((0, 3)), np.zeros((0, 3), int))


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"size": 0}, "chip size"),
        ({"size": 8.5}, "chip size"),
        ({"channels": ("colour",)}, "channels"),
        ({"channels": ()}, "at least one"),
        ({"framing": "zoom"}, "framing"),
        ({"backend": "vulkan"}, "backend"),
        ({"clutter": "forest"}, "clutter"),
        ({"ambient": 1.0}, "ambient"),
        ({"noise_sigma": -1}, "noise_sigma"),
        ({"depth_noise_mm": float("nan")}, "depth_noise_mm"),
        ({"lighting_variation": -0.1}, "lighting_variation"),
        ({"seed": -1}, "seed"),
        ({"seed": True}, "seed"),
        ({"light": (0.0, 0.0, 0.0)}, "non-zero direction"),
        ({"backend": "pyrender", "clutter": "ground"}, "needs backend='raycast'"),
    ],
)
def test_chip_spec_validation(fields, match):
    with pytest.raises(InputError, match=match):
        ChipSpec(**fields)


def test_chip_spec_normalises_and_is_frozen():
    spec = ChipSpec(size=np.int64(32), channels=["depth"], light=[0, 0, -2])
    assert spec.size == 32 and type(spec.size) is int
    assert spec.channels == ("depth",) and spec.light == (0.0, 0.0, -2.0)
    with pytest.raises(AttributeError):
        spec.size = 64  # type: ignore[misc]


def test_camouflage_off_is_applied_once(tmp_path):
    """Camouflage off = one grey, the mean luminance of the target's own (camouflage) paint.

    Greying must happen once, at rendering: the CLI renders the painted target and lets
    ChipSpec.camouflage decide. Painting the target plain first and greying it again
    gives the base coat's luminance instead (a different grey), which this catches.
    """
    from prism3d.atr.chips import _LUMA
    from prism3d.cli import main
    from prism3d.datasets.models.targets import builtin_target

    camo = builtin_target("tank_t1", seed=0)
    plain = builtin_target("tank_t1", camouflage=False)
    grey_camo = float(np.mean(camo.vertex_colors() @ _LUMA))
    grey_plain = float(np.mean(plain.vertex_colors() @ _LUMA))
    assert abs(grey_camo - grey_plain) > 1e-3  # distinguishable at rtol 1e-5 below
    spec = ChipSpec(size=32, camouflage=False, channels=("intensity", "shape", "mask"))
    cs = render_chips(camo, azimuth=[30.0], elevation=20.0, chip_spec=spec)
    m = cs["mask"][0]
    ratio = cs["intensity"][0][m] / cs["shape"][0][m]
    np.testing.assert_allclose(ratio, grey_camo, rtol=1e-5)
    # the CLI path: `prism3d render tank_t1 --no-camouflage` gives the same chips
    out = tmp_path / "cli"
    argv = ["--quiet", "render", "tank_t1", "-o", str(out), "--azimuth", "30", "--elevation", "20",
            "--size", "32", "--no-camouflage", "--channels", "intensity", "shape", "mask"]
    assert main(argv) == 0
    with np.load(out / "chips_intensity.npz") as z:
        np.testing.assert_array_equal(z["chips"], cs["intensity"])


def test_render_to_folder_and_mesh_file(tmp_path, builtin_tank):
    import trimesh

    man = render_to_folder(
        builtin_tank, tmp_path / "npz", azimuth="0:360:90", elevation="10", chip_spec=ChipSpec(size=32)
    )
    df = pd.read_parquet(man)
    assert len(df) == 4 and {"az_deg", "fx", "T_cam_obj_23", "schema_version", "file_depth"} <= set(
        df.columns
    )
    with np.load(tmp_path / "npz" / "chips_depth.npz", allow_pickle=False) as z:
        assert z["chips"].shape == (4, 32, 32)
    man = render_to_folder(
        builtin_tank,
        tmp_path / "png",
        azimuth="0:360:180",
        elevation="10",
        chip_spec=ChipSpec(size=32),
        fmt="png",
    )
    df = pd.read_parquet(man)
    assert (tmp_path / "png" / df["file_depth"][0]).exists() and (
        tmp_path / "png" / df["file_intensity"][1]
    ).exists()
    # a Y-up OBJ in metres: 2 m long along x, 0.5 m tall along y
    box = trimesh.creation.box(extents=(2.0, 0.5, 1.0))
    box.export(tmp_path / "box.obj")
    m = load_mesh_file(tmp_path / "box.obj", units="m", up="y")
    np.testing.assert_allclose(m.extent_mm, [2000.0, 1000.0, 500.0], atol=1e-6)
    assert m.bounds[0, 2] == pytest.approx(0.0)
    m2 = load_mesh_file(tmp_path / "box.obj", length_mm=200.0)
    assert m2.extent_mm.max() == pytest.approx(200.0)
    with pytest.raises(InputError, match="box2.obj"):
        load_mesh_file(tmp_path / "box2.obj")
    with pytest.raises(InputError, match="units"):
        load_mesh_file(tmp_path / "box.obj", units="furlong")


def test_absurd_chip_requests_are_refused_before_allocating(builtin_tank):
    """``render --size 60000`` or a billion-chip grid ran out of memory; now one line."""
    with pytest.raises(InputError, match="60000 px is more than the 4096 px"):
        ChipSpec(size=60000)
    with pytest.raises(InputError, match=r"32760 chips of 256x256 px need 26.0 GiB, more than the 1 GiB"):
        render_chips(builtin_tank, azimuth="0:360:1", elevation="0:90:1", chip_spec=ChipSpec(size=256))


def test_render_to_folder_writes_all_or_nothing(builtin_tank, tmp_path, monkeypatch):
    """A failure after the chips were written (here: the manifest) leaves no chips behind."""
    import pandas as pd

    def fail(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(pd.DataFrame, "to_parquet", fail)
    with pytest.raises(OSError):
        render_to_folder(builtin_tank, tmp_path / "chips", azimuth="0:90:45", elevation=20,
                         chip_spec=ChipSpec(size=16))
    assert list(tmp_path.iterdir()) == []
