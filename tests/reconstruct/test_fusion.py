"""Fusion: voxel-averaged cloud with outward normals, closed Poisson mesh, closedness test."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.reconstruct.scan.fusion import fuse_clouds, mesh_is_closed, poisson_mesh

from prism3d.errors import InputError, ReconstructionError

TETRA = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def _sphere(n=6000, r=50.0, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * r, q


def test_mesh_is_closed_known_answers():
    assert mesh_is_closed(TETRA)
    assert not mesh_is_closed(TETRA[:3])  # a missing face leaves boundary edges
    flipped = TETRA.copy()
    flipped[0] = flipped[0, ::-1]
    assert not mesh_is_closed(flipped)  # inconsistent orientation
    assert not mesh_is_closed(np.zeros((0, 3), int))
    with pytest.raises(InputError, match="faces"):
        mesh_is_closed(np.zeros((4, 2), int))


def test_fuse_two_views_of_a_sphere_averages_and_orients_outward():
    p, n = _sphere(20000)
    rng = np.random.default_rng(1)
    T0 = np.eye(4)
    T0[:3, 3] = [0, 0, -200.0]  # sensor 0 below the sphere, looking up (+z)
    T1 = np.eye(4)
    T1[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]  # sensor 1 on +x, looking along -x
    T1[:3, 3] = [200.0, 0, 0]
    scans = []
    for T in (T0, T1):
        seen = np.sum((T[:3, 3] - p) * n, axis=1) > 0.3 * np.linalg.norm(T[:3, 3] - p, axis=1)
        pw = p[seen] + rng.normal(0, 0.2, (seen.sum(), 3))
        scans.append((pw - T[:3, 3]) @ T[:3, :3])  # into the sensor frame
    s0, s1 = scans
    pts, col, nrm = fuse_clouds([s0, s1], [T0, T1], voxel=2.0)
    assert col is None and len(pts) < len(s0) + len(s1)
    r = np.linalg.norm(pts, axis=1)
    assert abs(np.median(r) - 50.0) < 0.2
    outward = np.sum(nrm * pts / r[:, None], axis=1)
    assert np.mean(outward > 0.9) > 0.98
    with pytest.raises(InputError, match="equal non-zero lengths"):
        fuse_clouds([s0], [T0, T1], voxel=1.0)


def test_poisson_mesh_is_closed_and_trimming_opens_it():
    p, n = _sphere()
    col = np.full((len(p), 3), 200, np.uint8)
    V, F, C = poisson_mesh(p, n, colors=col, spacing=1.5)
    assert mesh_is_closed(F) and C is not None and C.shape == V.shape
    assert abs(np.median(np.linalg.norm(V, axis=1)) - 50.0) < 0.5
    half = p[:, 2] > 0  # only the upper half observed: trimming removes the guessed lower half
    _, F2, _ = poisson_mesh(p[half], n[half], spacing=1.5, trim_quantile=0.3)
    assert not mesh_is_closed(F2)
    with pytest.raises(ReconstructionError, match="at least 10 points"):
        poisson_mesh(p[:5], n[:5], spacing=1.0)
    with pytest.raises(InputError, match="trim_quantile"):
        poisson_mesh(p, n, spacing=1.0, trim_quantile=1.5)


def test_min_views_keeps_only_points_another_scan_confirms():
    rng = np.random.default_rng(0)
    x, y = np.meshgrid(np.arange(0, 50, 0.5), np.arange(0, 20, 0.5))
    plane = np.c_[x.ravel(), y.ravel(), np.full(x.size, 100.0)]
    a = plane[plane[:, 0] < 30] + rng.normal(0, 0.02, (int((plane[:, 0] < 30).sum()), 3))
    b = plane[plane[:, 0] >= 20] + rng.normal(0, 0.02, (int((plane[:, 0] >= 20).sum()), 3))
    ghost = np.array([[25.0, 10.0, 97.0]])  # an artefact 3 mm off the surface, in scan a only
    a = np.vstack([a, ghost])
    I = [np.eye(4), np.eye(4)]
    p1, _, _ = fuse_clouds([a, b], I, voxel=0.5)
    p2, _, _ = fuse_clouds([a, b], I, voxel=0.5, min_views=2)
    assert np.min(np.abs(p1[:, 2] - 97.0)) < 0.1  # kept by default
    assert np.all(np.abs(p2[:, 2] - 100.0) < 0.2)  # the ghost is gone...
    # ...and so is what one scan saw alone (beyond the 1 mm support distance)
    assert 18.5 < p2[:, 0].min() and p2[:, 0].max() < 31.5
    assert p1[:, 0].min() < 1.0 and p1[:, 0].max() > 49.0
    with pytest.raises(InputError, match="min_views"):
        fuse_clouds([a, b], I, voxel=0.5, min_views=3)
