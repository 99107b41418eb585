from __future__ import annotations

import numpy as np
import pytest

from prism3d.capture.rig import compute_rectification, paper_rig
from prism3d.errors import InputError, ReconstructionError
from prism3d.reconstruct.stereo.flatness import fit_plane, flatness_of_ply, flatness_test
from prism3d.reconstruct.stereo.meshing import mesh_from_grid, smooth_depth, smoothing_resolution_mm
from prism3d.reconstruct.stereo.triangulate import (
    depth_resolution_mm,
    depth_to_points,
    grid_normals,
    triangulate,
)


@pytest.fixture(scope="module")
def rect():
    return compute_rectification(paper_rig(), size=(320, 300))


def _plane_disparity(rect, n_rect, d0):
    """Exact disparity of the plane n . X = d0 (rectified-left frame) on the pixel grid."""
    w, h = rect.size
    f, cx, cy = rect.P1[0, 0], rect.P1[0, 2], rect.P1[1, 2]
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    ray = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], axis=2)
    z = d0 / (ray @ n_rect)
    return (f * rect.baseline_mm / z).astype(np.float32), z


def test_disparity_round_trip_to_known_points(rect):
    rig = paper_rig()
    n = np.array([0.1, -0.05, 1.0])
    disp, z = _plane_disparity(rect, n / np.linalg.norm(n), 1250.0)
    img = np.zeros(disp.shape + (3,), np.uint8)
    scan = triangulate(disp, np.ones_like(disp, bool), rect, img)
    assert len(scan) > 0.95 * disp.size
    # points are in the left camera frame: map to rectified frame and check the plane
    x_rect = scan.points.astype(np.float64) @ rect.R1.T
    np.testing.assert_allclose(x_rect @ (n / np.linalg.norm(n)), 1250.0, atol=2e-3)
    # and they project to their pixels through the ORIGINAL left camera + the rectified camera
    r, c = scan.pixels[:, 0], scan.pixels[:, 1]
    uv = x_rect @ rect.P1[:, :3].T
    np.testing.assert_allclose(uv[:, 0] / uv[:, 2], c, atol=1e-3)
    np.testing.assert_allclose(uv[:, 1] / uv[:, 2], r, atol=1e-3)
    # normals: unit, facing the camera, equal to the plane normal (in left frame)
    n_left = rect.R1.T @ (n / np.linalg.norm(n))
    cosang = np.abs(scan.normals.astype(np.float64) @ n_left)
    assert np.median(cosang) > 0.99999
    assert np.all(np.sum(scan.normals * scan.points, axis=1) < 0)
    assert rig.left.size != rect.size  # the rectified grid is its own grid


def test_invalid_and_nonpositive_disparities_are_dropped(rect):
    disp, _ = _plane_disparity(rect, np.array([0, 0, 1.0]), 1250.0)
    valid = np.ones_like(disp, bool)
    valid[:, :50] = False
    disp[100:110] = np.nan
    disp[200:205] = -3
    scan = triangulate(disp, valid, rect, np.zeros(disp.shape, np.uint8))
    assert scan.pixels[:, 1].min() >= 50
    assert not np.any((scan.pixels[:, 0] >= 100) & (scan.pixels[:, 0] < 110))
    with pytest.raises(ReconstructionError, match="empty scan"):
        triangulate(disp, np.zeros_like(valid), rect, np.zeros(disp.shape, np.uint8))
    with pytest.raises(InputError, match="same shape"):
        triangulate(disp, valid[:-1], rect, np.zeros(disp.shape, np.uint8))
    with pytest.raises(InputError, match="rectification is"):
        triangulate(disp[:-1], valid[:-1], rect, np.zeros(disp[:-1].shape, np.uint8))


def test_depth_resolution_eq16():
    assert depth_resolution_mm(1250.0, 5107.0, 197.9) == pytest.approx(1.546, abs=5e-4)


def test_flatness_known_noise(rect):
    rng = np.random.default_rng(0)
    n = np.array([0.08, 0.02, 1.0])
    n /= np.linalg.norm(n)
    _, z = _plane_disparity(rect, n, 1250.0)
    pts = depth_to_points(z + rng.normal(0, 0.1, z.shape), rect).reshape(-1, 3)
    rep = flatness_test(pts, focal_px=rect.focal_px, baseline_mm=rect.baseline_mm)
    assert set(rep.regions) == {"upper_left", "upper_right", "centre", "lower_left", "lower_right"}
    for r in rep.regions.values():
        # z residual of noise added along the rectified z (~ along camera z): ~0.1 mm
        assert 0.085 < r.rms_mm < 0.115
        assert r.n_points > 500
    exact = flatness_test(depth_to_points(z, rect).reshape(-1, 3))
    assert exact.mean_rms_mm < 1e-3
    assert rep.resolution_mm_per_px == pytest.approx(
        rep.mean_depth_mm**2 / (rect.focal_px * rect.baseline_mm))
    assert "upper_left" in rep.table() and rep.to_dict()["mean_rms_mm"] == pytest.approx(rep.mean_rms_mm)


def test_fit_plane_exact():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-100, 100, (200, 2))
    z = 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 1000
    f = fit_plane(np.c_[xy, z])
    assert (f.a, f.b, f.c) == pytest.approx((0.3, -0.2, 1000))
    assert f.rms_mm < 1e-9
    with pytest.raises(ReconstructionError, match="at least 3"):
        fit_plane(np.zeros((2, 3)))


def test_flatness_requires_coverage():
    pts = np.c_[np.random.default_rng(2).uniform(0, 1, (1000, 2)), np.zeros(1000)]
    pts[:, 0] = np.where(pts[:, 0] < 0.5, pts[:, 0] * 0.1, pts[:, 0])  # empty left part
    with pytest.raises(ReconstructionError, match="does not cover"):
        flatness_test(pts)


def test_flatness_of_ply_reads_rig_from_comments(tmp_path, rect):
    from prism3d.io.ply import write_ply

    _, z = _plane_disparity(rect, np.array([0, 0, 1.0]), 1250.0)
    pts = depth_to_points(z, rect).reshape(-1, 3)
    write_ply(tmp_path / "s.ply", pts, comments=["focal_px 5107", "baseline_mm 197.9"])
    rep = flatness_of_ply(tmp_path / "s.ply")
    assert rep.resolution_mm_per_px == pytest.approx(rep.mean_depth_mm**2 / (5107 * 197.9))
    assert 1.5 < rep.resolution_mm_per_px < 1.6


def test_mesh_does_not_bridge_depth_jumps(rect):
    w, h = rect.size
    z = np.full((h, w), 1250.0)
    z[:, w // 2:] = 1400.0  # a step: an occlusion edge
    pts = depth_to_points(z, rect, frame="rectified")
    valid = np.ones((h, w), bool)
    valid[10, 10] = False
    verts, faces = mesh_from_grid(pts, valid, focal_px=rect.focal_px)
    assert len(verts) == h * w - 1
    zf = verts[faces][:, :, 2]
    assert np.all(zf.max(1) - zf.min(1) < 1.0)  # no triangle spans the step
    # every cell away from the step has its two triangles; the hole removes the 6 around it
    expected = 2 * (h - 1) * (w - 2) - 6
    assert len(faces) == expected
    # counter-clockwise seen from the camera: normals point to -z
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    assert np.all(np.cross(b - a, c - a)[:, 2] < 0)


def test_smoothing_reduces_noise_keeps_edges(rect):
    rng = np.random.default_rng(3)
    w, h = rect.size
    z = np.full((h, w), 1250.0)
    z[:, w // 2:] = 1300.0
    noisy = (z + rng.normal(0, 0.2, z.shape)).astype(np.float32)
    noisy[50:60, 50:60] = np.nan
    sm = smooth_depth(noisy, sigma_px=2.0, focal_px=5107.0, baseline_mm=197.9)  # 15 mm jump limit
    inner = np.s_[20:-20, 20:w // 2 - 20]
    assert np.nanstd(sm[inner] - z[inner]) < 0.5 * np.nanstd(noisy[inner] - z[inner])
    assert np.all(np.isnan(sm[50:60, 50:60]))
    edge = np.s_[:, w // 2 - 2:w // 2 + 2]
    assert np.nanmax(np.abs(sm[edge] - z[edge])) < 1.5  # the 50 mm step is not blurred
    with pytest.raises(InputError, match="sigma_px"):
        smooth_depth(noisy, sigma_px=0)
    assert smoothing_resolution_mm(2.0, 1250, 5107) == pytest.approx(2.355 * 2 * 1250 / 5107, rel=1e-3)


def test_grid_normals_shape_checks():
    with pytest.raises(InputError, match="same shape"):
        grid_normals(np.zeros((4, 4, 3)), np.ones((3, 4), bool))
