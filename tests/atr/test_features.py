"""Tests of prism3d.atr.features and prism3d.atr.geometry (sizes, invariances, files)."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from scipy.spatial import cKDTree
from prism3d.atr.features import (
    FEATURE_INFO,
    FEATURES_SCHEMA_VERSION,
    features_table,
    features_to_parquet,
    model_features,
    scan_features,
    view_features,
)
from prism3d.atr.geometry import depth_to_points, gravity_box, normals_from_depth, up_rotation
from prism3d.capture.render import RaycastRenderer
from prism3d.reconstruct.scan.surface import surface_points
from prism3d.capture.rig import CameraModel, look_at
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets

from prism3d.errors import InputError
from prism3d.io.ply import write_ply


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _close(a: dict, b: dict, keys, tol: float = 0.02, atol: float = 1e-3) -> list[str]:
    return [k for k in keys if not abs(a[k] - b[k]) <= tol * abs(a[k]) + atol]


@pytest.mark.parametrize("name", list_builtin_targets())
def test_model_sizes_match_builtin_metadata(name: str) -> None:
    m = builtin_target(name)
    f = model_features(m.vertices, m.faces, up="z")
    for k in ("length_mm", "width_mm", "height_mm"):
        assert f[k] == pytest.approx(m.metadata[k], rel=0.01), k
    assert f["obb_major_mm"] >= f["obb_middle_mm"] >= f["obb_minor_mm"] > 0
    assert f["volume_mm3"] > 0 and f["surface_area_mm2"] > 0
    assert set(f) == {k for k, v in FEATURE_INFO.items() if {"model", "scan"} & set(v["source"])}


@pytest.mark.parametrize("name", ["tank_t1", "jet_j2", "ship_s3"])
def test_model_features_invariant_to_rotation_about_vertical_and_scale(name: str) -> None:
    m = builtin_target(name)
    f0 = model_features(m.vertices, m.faces, up="z")
    f1 = model_features(m.vertices @ _rz(37.0).T + [50.0, -20.0, 7.0], m.faces, up="z")
    # the same model stored Y-up (glTF style)
    f2 = model_features(m.vertices @ np.linalg.inv(up_rotation("y")).T, m.faces, up="y")
    fs = model_features(2.0 * m.vertices, m.faces, up="z")
    plain = [k for k, v in FEATURE_INFO.items() if "rotation_about_vertical" in v["invariant_to"]
             and "model" in v["source"] and not k.startswith("fpfh")]
    assert _close(f0, f1, plain) == []
    assert _close(f0, f2, plain) == []
    fp0 = np.array([f0[f"fpfh_{i:02d}"] for i in range(33)])
    fp1 = np.array([f1[f"fpfh_{i:02d}"] for i in range(33)])
    assert np.abs(fp0 - fp1).sum() / fp0.sum() < 0.02  # FPFH bins are discrete: compare as a histogram
    scale_inv = [k for k, v in FEATURE_INFO.items() if "scale" in v["invariant_to"]
                 and "model" in v["source"] and not k.startswith("fpfh")]
    assert _close(f0, fs, scale_inv) == []
    for k in ("length_mm", "width_mm", "height_mm"):
        assert fs[k] == pytest.approx(2 * f0[k], rel=1e-9)
    assert fs["volume_mm3"] == pytest.approx(8 * f0["volume_mm3"], rel=1e-9)


def test_gravity_box_known_box() -> None:
    rng = np.random.default_rng(1)
    p = rng.uniform([-50, -10, 0], [50, 10, 30], size=(2000, 3))
    p = np.vstack([p, [[-50, -10, 0], [50, 10, 30]]]) @ _rz(20).T
    b = gravity_box(p)
    assert (b.length_mm, b.width_mm, b.height_mm) == pytest.approx((100, 20, 30), rel=2e-3)


def test_normals_from_depth_plane_known_answer() -> None:
    K = np.array([[500.0, 0, 31.5], [0, 500.0, 23.5], [0, 0, 1]])
    n_true = np.array([0.3, -0.2, -1.0])
    n_true /= np.linalg.norm(n_true)
    # plane n . p = -1000 ; depth along rays
    cam = CameraModel(K, np.zeros(5), (64, 48))
    rays = cam.pixel_grid_rays()
    t = -1000.0 / (rays @ n_true)
    depth = (rays[..., 2] * t).astype(np.float32)
    n = normals_from_depth(depth, K)
    assert np.allclose(n.reshape(-1, 3), n_true, atol=1e-3)
    P = depth_to_points(depth, K)
    assert np.allclose(P @ n_true, -1000.0, atol=0.05)


def _scan_of(mesh, n_views: int = 6, noise_mm: float = 0.15):
    """Stand-in scan: back-projected truth depth of several views, with noise."""
    cam = CameraModel(np.array([[1200.0, 0, 159.5], [0, 1200.0, 159.5], [0, 0, 1]]), np.zeros(5), (320, 320))
    r = RaycastRenderer([(mesh, np.eye(4))])
    rng = np.random.default_rng(0)
    c = np.array([0.0, 0.0, mesh.metadata["height_mm"] / 2])
    pts = []
    for i in range(n_views):
        az = 2 * np.pi * i / n_views
        eye = c + 1250.0 * np.array([np.cos(az) * np.cos(0.5), np.sin(az) * np.cos(0.5), np.sin(0.5)])
        T = look_at(eye, c, up=np.array([0.0, 0.0, -1.0]))
        res = r.render(cam, T)
        d = res.depth_mm + rng.normal(0, noise_mm, res.depth_mm.shape).astype(np.float32)
        P = depth_to_points(d, cam)[np.isfinite(d)]
        pts.append(P @ T[:3, :3].T + T[:3, 3])
    return np.vstack(pts)


@pytest.mark.parametrize("name", ["tank_t2", "truck_k1"])
def test_scan_sizes_within_2_percent(name: str) -> None:
    m = builtin_target(name)
    P = _scan_of(m)
    f = scan_features(P, up="z")
    for k in ("length_mm", "width_mm", "height_mm"):
        assert f[k] == pytest.approx(m.metadata[k], rel=0.02), (k, f[k], m.metadata[k])
    assert f["volume_is_hull"] == 1.0 and np.isnan(f["surface_area_mm2"])


def _open_box_cloud(L: float, W: float, H: float, step: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points on the 4 sides and the top of an L x W x H box (no bottom, as a
    turntable model has), with outward normals."""
    P, N = [], []
    xs, ys, zs = (np.arange(-a / 2, a / 2 + 1e-9, step) for a in (L, W, H))
    for sgn in (-1, 1):
        u, v = np.meshgrid(ys, zs)
        P.append(np.c_[np.full(u.size, sgn * L / 2), u.ravel(), v.ravel() + H / 2])
        N.append(np.tile([sgn, 0.0, 0.0], (u.size, 1)))
        u, v = np.meshgrid(xs, zs)
        P.append(np.c_[u.ravel(), np.full(u.size, sgn * W / 2), v.ravel() + H / 2])
        N.append(np.tile([0.0, sgn, 0.0], (u.size, 1)))
    u, v = np.meshgrid(xs, ys)
    P.append(np.c_[u.ravel(), v.ravel(), np.full(u.size, H)])
    N.append(np.tile([0.0, 0.0, 1.0], (u.size, 1)))
    P, N = np.vstack(P), np.vstack(N)
    return P + rng.normal(0, 0.1 * step, P.shape), N


def test_scan_box_from_surface_ignores_error_tails() -> None:
    """A scan's depth errors have long tails, and min/max picks them: 0.3 % of the
    points of a 200 x 70 x 90 mm box pushed 1-1.5 mm outwards along their normals
    (as the stereo scans' worst points are) widen the box of the points by ~4 %
    (2-3 mm on 70); the box of the points near their fitted surface stays within 1 %."""
    rng = np.random.default_rng(2)
    L, W, H = 200.0, 70.0, 90.0
    P, N = _open_box_cloud(L, W, H, 0.3, rng)
    tail = rng.random(len(P)) < 0.003
    P[tail] += N[tail] * rng.uniform(1.0, 1.5, (tail.sum(), 1))
    fp = scan_features(P, N, up="z", box="points")
    fs = scan_features(P, N, up="z", box="surface")
    assert fp["width_mm"] > 1.03 * W  # what min/max does with the tails
    for k, v in (("length_mm", L), ("width_mm", W), ("height_mm", H)):
        assert fs[k] == pytest.approx(v, rel=0.01), (k, fs[k], v)
    assert scan_features(P, N, up="z")["width_mm"] == fs["width_mm"]  # auto: normals given -> surface
    kept, sorted_ = surface_points(P, N)
    assert sorted_ and len(kept) > 0.95 * len(P)  # the surface keeps the bulk ...
    assert np.mean(cKDTree(kept).query(P[tail])[0] == 0) < 0.05  # ... and drops the tails
    # a sparse cloud (fewer than 200 spacings across): auto keeps the points' box
    Ps, Ns = _open_box_cloud(L, W, H, 5.0, rng)
    assert scan_features(Ps, Ns, up="z")["width_mm"] == scan_features(Ps, Ns, up="z", box="points")["width_mm"]
    with pytest.raises(InputError, match="normals"):
        scan_features(P, None, up="z", box="surface")
    with pytest.raises(InputError, match="box"):
        scan_features(P, N, up="z", box="hull")


def _chip(mesh, dist: float, yaw: float = 30.0, size: int = 128, f: float = 600.0):
    cam = CameraModel(np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]]), np.zeros(5), (size, size))
    R = _rz(yaw)
    T_world_obj = np.eye(4)
    T_world_obj[:3, :3] = R
    c = np.array([0.0, 0.0, mesh.metadata["height_mm"] / 2])
    eye = c + dist * np.array([0.0, -np.cos(0.4), np.sin(0.4)])
    T = look_at(eye, c, up=np.array([0.0, 0.0, -1.0]))
    res = RaycastRenderer([(mesh, T_world_obj)]).render(cam, T)
    return res.depth_mm, res.mask, cam


@pytest.mark.parametrize("name", ["tank_t1", "jet_j1", "truck_k2"])
def test_view_features_range_and_scale_invariance(name: str) -> None:
    m = builtin_target(name)
    d1, m1, cam = _chip(m, 1250.0)
    d2, m2, _ = _chip(m, 1700.0)  # farther: physical sizes must not change
    d3, m3, cam3 = _chip(m, 1250.0, f=420.0)  # 0.7x apparent size
    f1 = view_features(d1, m1, cam.K)
    f2 = view_features(d2, m2, cam)
    f3 = view_features(d3, m3, cam3)
    assert f1["range_mm"] == pytest.approx(1250.0, rel=0.05)
    assert f1["pixels_per_m"] == pytest.approx(600.0 * 1000 / f1["range_mm"])
    assert f1["pixels_on_target_px"] == m1.sum()
    for k in ("silhouette_area_mm2", "silhouette_width_mm", "silhouette_height_mm"):
        assert f2[k] == pytest.approx(f1[k], rel=0.05), k  # perspective changes a little
    claimed = [k for k, v in FEATURE_INFO.items() if "view" in v["source"]
               and ("scale" in v["invariant_to"] or "range" in v["invariant_to"])]
    assert len(claimed) >= 8
    assert _close(f1, f3, claimed, tol=0.02, atol=0.005) == []
    t0 = time.perf_counter()
    for _ in range(20):
        view_features(d1, m1, cam.K)
    print(f"view_features per 128x128 chip: {(time.perf_counter() - t0) / 20 * 1e3:.2f} ms")


def test_view_features_errors() -> None:
    K = np.eye(3)
    with pytest.raises(InputError, match="no target pixel"):
        view_features(np.full((8, 8), np.nan, np.float32), None, K)
    with pytest.raises(InputError, match="same shape"):
        view_features(np.ones((8, 8), np.float32), np.ones((4, 4), bool), K)


def test_mesh_errors() -> None:
    with pytest.raises(InputError, match="empty mesh"):
        model_features(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    with pytest.raises(InputError, match="indices"):
        model_features(np.eye(3), np.array([[0, 1, 5]]))
    with pytest.raises(InputError, match="up"):
        model_features(np.eye(3), np.array([[0, 1, 2]]), up="w")
    with pytest.raises(InputError, match="at least 10"):
        scan_features(np.zeros((3, 3)))


def _write_tank_ply(path, units_comment: bool):
    m = builtin_target("tank_t1")
    write_ply(path, m.vertices / 1000.0 if not units_comment else m.vertices, faces=m.faces,
              comments=["units mm"] if units_comment else None)
    return m


def test_features_table_units_up_and_parquet(tmp_path) -> None:
    m = _write_tank_ply(tmp_path / "tank_m.ply", units_comment=False)  # metres, no declaration
    _write_tank_ply(tmp_path / "tank_mm.ply", units_comment=True)
    with pytest.raises(InputError, match="pass --units"):
        features_table([tmp_path / "tank_m.ply"], up="z")
    with pytest.raises(InputError, match="declares units 'mm'"):
        features_table([tmp_path / "tank_mm.ply"], units="m", up="z")
    with pytest.raises(InputError, match="no up axis"):
        features_table([tmp_path / "tank_mm.ply"])
    (tmp_path / "tank_m.ply.units.yaml").write_text("units: m\nup: z\n")
    df = features_to_parquet([tmp_path / "tank_m.ply", tmp_path / "tank_mm.ply"], tmp_path / "f.parquet", up="z")
    assert list(df["kind"]) == ["mesh", "mesh"] and list(df["units_in"]) == ["m", "mm"]
    assert df["length_mm"].to_numpy() == pytest.approx(m.metadata["length_mm"], rel=1e-6)
    back = pd.read_parquet(tmp_path / "f.parquet")
    assert (back["schema_version"] == FEATURES_SCHEMA_VERSION).all()
    meta = pq.read_schema(tmp_path / "f.parquet").metadata
    assert meta[b"prism3d_features_schema_version"] == str(FEATURES_SCHEMA_VERSION).encode()
    (tmp_path / "tank_m.ply.units.yaml").write_text("units: m\nfoo: 1\n")
    with pytest.raises(InputError, match="unknown keys"):
        features_table([tmp_path / "tank_m.ply"], up="z")
    (tmp_path / "x.xyz2").write_text("1 2 3\n")
    with pytest.raises(InputError, match="unsupported format"):
        features_table([tmp_path / "x.xyz2"], units="mm", up="z")
    with pytest.raises(InputError, match="not found"):
        features_table([tmp_path / "missing.obj"], units="mm", up="z")
    # a scan (PLY without faces) with declared units
    write_ply(tmp_path / "scan.ply", _scan_of(builtin_target("tank_t2"), n_views=3), comments=["units mm"])
    df2 = features_table([tmp_path / "scan.ply"], up="z")
    assert df2["kind"][0] == "scan"


def test_features_reads_the_units_of_an_exported_builtin(tmp_path) -> None:
    """``units mm; frame ...`` (export_builtin_target) declares mm, as for ``prism3d db add``."""
    from prism3d.datasets.models.targets import export_builtin_target

    p = export_builtin_target("truck_k2", tmp_path / "k2.ply", camouflage=False)
    with pytest.raises(InputError, match="declares units 'mm'"):
        features_table([p], units="m", up="z")
    df = features_table([p], up="z")
    assert list(df["units_in"]) == ["mm"]
    assert df["length_mm"][0] == pytest.approx(builtin_target("truck_k2").metadata["length_mm"], rel=0.02)


def test_real_meshes_mixed_units_and_up(shared_data, tmp_path) -> None:
    d = shared_data / "meshes"
    bunny = tmp_path / "stanford-bunny.obj"
    shutil.copy(d / "classic" / "stanford-bunny.obj", bunny)
    (tmp_path / "stanford-bunny.obj.units.yaml").write_text("units: m\nup: y\n")
    files = [d / "quaternius_vehicles_cc0" / "glb" / "tank_1.glb",
             d / "quaternius_vehicles_cc0" / "obj" / "airplane_military_1.obj",
             d / "modelnet_airplane" / "airplane_0001.off"]
    df = features_table(files, units="mm", up="y")  # arbitrary units: declared explicitly as mm
    assert len(df) == 3 and df[["length_mm", "width_mm", "height_mm"]].notna().all().all()
    dfb = features_table([bunny], up="y")  # sidecar wins for the bunny (metres, Y-up)
    # the bunny is ~0.16 m: 150-160 mm long, taller than ~100 mm
    assert 120 < dfb["length_mm"][0] < 200 and dfb["height_mm"][0] > 100
    assert dfb["units_in"][0] == "m"
