"""Scanned targets as training targets: chips of a stitched object-frame mesh match the
true mesh's (nothing leaks through the unseen underside at the training elevations), and a
bank trained on scans classifies renders of the true meshes like a bank trained on them."""

from __future__ import annotations

import numpy as np
import pytest

from tests.reconstruct.test_stitch import _raycast_views


def _scanned_mesh(name, folder):
    """A raycast turntable scan of ``name`` stitched --frame object with the mesh kept
    within 2 spacings of the data: the mesh as a SceneMesh (mm, z up, scanned colours)."""
    from prism3d.atr.chips import load_mesh_file
    from prism3d.io.ply import write_ply
    from prism3d.reconstruct.scan.stitch import StitchOptions, stitch_to_files

    scans, _, _, _ = _raycast_views(target=name, W=480, H=360, f=2000.0)
    paths = []
    for k, (p, c, _) in enumerate(scans):
        paths.append(folder / f"s{k}.ply")
        write_ply(paths[-1], p, colors=c)
    stitch_to_files(paths, folder / "model.ply", StitchOptions(turntable_step_deg=45.0, mesh_max_spacings=2.0),
                    mesh_out=folder / "mesh.ply", frame="object")
    return load_mesh_file(folder / "mesh.ply", name=f"{name}_scan")


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    return {n: _scanned_mesh(n, tmp_path_factory.mktemp(n)) for n in ("tank_t1", "truck_k1")}


def test_scanned_chips_match_the_true_mesh(scanned):
    from prism3d.atr.chips import ChipSpec, render_chips, spec_poses
    from prism3d.datasets.models.targets import builtin_target

    spec = ChipSpec(size=64, channels=("mask", "depth"), camouflage=False)
    for name, scan in scanned.items():
        true = builtin_target(name)
        a = render_chips(scan, spec_poses(scan, "0:360:45", "20", None, spec), chip_spec=spec)
        b = render_chips(true, spec_poses(true, "0:360:45", "20", None, spec), chip_spec=spec)
        ma, mb = a["mask"] > 0, b["mask"] > 0
        iou = (ma & mb).sum(axis=(1, 2)) / (ma | mb).sum(axis=(1, 2))
        assert iou.min() > 0.93, (name, iou)
        # no background through a hole: where the scan's chip sees a surface, so does the truth's
        assert (ma & ~mb).sum() < 0.03 * ma.sum(), name
        assert np.all(np.isfinite(a["depth"][ma])), name
        # the mesh keeps the colours the scans saw (the raycast scans' paint: 90, 110, 60)
        np.testing.assert_allclose(np.median(scan.vertex_albedo, axis=0), np.array([90, 110, 60]) / 255, atol=2 / 255)


def test_bank_from_scans_classifies_the_true_meshes(scanned):
    """Depth banks (2 classes, 30-deg bins): from scans vs from the true meshes, tested on
    the true meshes in a new paint with noise and clutter at unseen azimuths."""
    from prism3d.datasets.models.scanned import compare_scan_banks
    from prism3d.datasets.models.targets import builtin_target

    true = [("tank", builtin_target("tank_t1")), ("truck", builtin_target("truck_k1"))]
    test = [("tank", builtin_target("tank_t1", seed=17)), ("truck", builtin_target("truck_k1", seed=17))]
    res = compare_scan_banks([("tank", scanned["tank_t1"]), ("truck", scanned["truck_k1"])], true, test,
                             channels=("depth",), azimuth="0:360:30", bin_deg=30)
    r = res["depth"]
    assert r.mesh.pcc > 0.9
    assert abs(r.difference_points) <= 5.0, r.difference_points
    with pytest.raises(Exception, match="same classes"):
        compare_scan_banks([("tank", scanned["tank_t1"])], true, test)
