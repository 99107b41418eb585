"""Benchmark: filter banks trained on SCANNED models vs on the true meshes (issue 28).

Run::

    .venv/bin/python benchmarks/bench_scan_bank.py [--targets tank_t1 jet_j1 ship_s1 truck_k1]

Each target is scanned on the virtual turntable (8 views at 45 deg, raycast depth with
0.15 mm noise along the rays and 10 % dropouts: the scans ``tests/reconstruct/
test_stitch.py`` stitches; not yet the stereo reconstructions with the camera effects),
stitched with ``--frame object`` into a Poisson mesh kept within 2 point spacings of the
data (``--mesh-max-distance 2``: the closed surface balloons under the model and around
thin wings), painted one grey (a scan's own paint
is not carried here). Two banks per channel (depth, shape, intensity) are trained at
azimuths 0:360:10, elevation 20: on the scanned meshes, and on the true meshes with the
same plain paint. Both are evaluated on renders of the TRUE meshes at azimuths between
the training ones, with a new camouflage, noise 0.03 and clutter. Prints Pcc per channel,
the ratio, and the mask IoU of scanned vs true chips at the training poses.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def scanned_mesh(name: str, work: Path):
    """``name`` scanned, stitched in the object frame and meshed; a SceneMesh in mm, z up."""
    from prism3d.capture.mesh import SceneMesh
    from prism3d.io.ply import read_ply, write_ply
    from prism3d.reconstruct.stitch import StitchOptions, stitch_to_files
    from tests.reconstruct.test_stitch import _raycast_views

    scans, _, _, _ = _raycast_views(target=name)
    paths = []
    for k, (p, c, _) in enumerate(scans):
        paths.append(work / name / f"s{k}.ply")
        paths[-1].parent.mkdir(parents=True, exist_ok=True)
        write_ply(paths[-1], p, colors=c)
    stitch_to_files(paths, work / name / "model.ply", StitchOptions(turntable_step_deg=45.0, mesh_max_spacings=2.0),
                    mesh_out=work / name / "mesh.ply", frame="object")
    m = read_ply(work / name / "mesh.ply")
    return SceneMesh(m.points, m.faces, vertex_albedo=np.full((len(m.points), 3), 0.45), name=f"{name}_scan")


def plain(mesh):
    from prism3d.capture.mesh import SceneMesh

    return SceneMesh(mesh.vertices, mesh.faces, vertex_albedo=np.full((len(mesh.vertices), 3), 0.45),
                     name=mesh.name)


def mask_iou(a, b) -> float:
    from prism3d.atr.chips import ChipSpec, render_chips, spec_poses

    spec = ChipSpec(size=64, channels=("mask",), camouflage=False)
    ious = []
    for m_a, m_b in ((a, b),):
        pa = spec_poses(m_a, "0:360:45", "20", None, spec)
        pb = spec_poses(m_b, "0:360:45", "20", None, spec)
        ca = render_chips(m_a, pa, chip_spec=spec).channels["mask"] > 0
        cb = render_chips(m_b, pb, chip_spec=spec).channels["mask"] > 0
        ious += [float((x & y).sum() / max((x | y).sum(), 1)) for x, y in zip(ca, cb, strict=True)]
    return float(np.mean(ious))


def main() -> None:
    from dataclasses import replace

    from prism3d.atr.bank import BANK_CHIP_SPEC, train_bank
    from prism3d.atr.evaluate import EVAL_CHIP_SPEC, evaluate_bank
    from prism3d.datasets.targets import builtin_target

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", nargs="+", default=["tank_t1", "jet_j1", "ship_s1", "truck_k1"])
    ap.add_argument("--channels", nargs="+", default=["depth", "shape", "intensity"])
    a = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        scans = {n: scanned_mesh(n, Path(d)) for n in a.targets}
    true = {n: builtin_target(n) for n in a.targets}
    cls = {n: str(true[n].metadata["class"]) for n in a.targets}
    print(f"scanned {len(a.targets)} targets in {time.perf_counter() - t0:.0f} s")
    print("\n| target | mask IoU scan vs true (8 azimuths, el 20) |\n|---|---:|")
    for n in a.targets:
        print(f"| {n} | {mask_iou(scans[n], plain(true[n])):.3f} |")
    test = [(cls[n], builtin_target(n, camouflage=True, seed=17)) for n in a.targets]
    spec_eval = replace(EVAL_CHIP_SPEC, noise_sigma=0.03, clutter="noise")
    print("\n| channel | Pcc, bank from scans | Pcc, bank from true meshes | difference (points) |\n|---|---:|---:|---:|")
    for ch in a.channels:
        pcc = []
        for src in (scans, {n: plain(true[n]) for n in a.targets}):
            bank = train_bank([(cls[n], src[n]) for n in a.targets], channel=ch, azimuth="0:360:10",
                              elevation="20", chip_spec=replace(BANK_CHIP_SPEC, camouflage=False))
            pcc.append(evaluate_bank(bank, test, chip_spec=spec_eval)["pcc"])
        print(f"| {ch} | {100 * pcc[0]:.1f} % | {100 * pcc[1]:.1f} % | {100 * (pcc[0] - pcc[1]):+.1f} |")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
