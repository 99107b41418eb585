"""Benchmark: filter banks trained on SCANNED models vs on the true meshes (issue 28).

Run::

    .venv/bin/python benchmarks/bench_scan_bank.py [--targets tank_t1 jet_j1 ship_s1 truck_k1 | all]
        [--cache DIR] [--json OUT.json]

Each target is scanned as a user scans it (``prism3d.datasets.models.scanned.scan_builtin_target``):
8 turntable shots through the simulated prism rig with the real camera effects, each
reconstructed (``reconstruct``), stitched with the turntable step into a mesh in the
object frame kept within 2 point spacings of the data, coloured by the shots. Per channel
(depth, shape, intensity) two banks are trained at azimuths 0:360:10, elevation 20: on the
scanned meshes (their scanned paint), and on the true meshes (the paint the scanner saw).
Both are evaluated on renders of the TRUE meshes at the azimuths between, with a new
camouflage, noise 0.03 and noise clutter. Prints Pcc per channel and the difference, the
mask IoU of scanned vs true chips, the scans' notes; ``--json`` keeps everything (the
scanned-targets notebook draws it). Scans are cached in ``--cache`` and reused.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def mask_iou(a, b) -> float:
    """Mean mask IoU of two meshes' chips at 8 azimuths, elevation 20."""
    from prism3d.atr.chips import ChipSpec, render_chips, spec_poses

    spec = ChipSpec(size=64, channels=("mask",), camouflage=False)
    ca = render_chips(a, spec_poses(a, "0:360:45", "20", None, spec), chip_spec=spec).channels["mask"] > 0
    cb = render_chips(b, spec_poses(b, "0:360:45", "20", None, spec), chip_spec=spec).channels["mask"] > 0
    return float(np.mean([(x & y).sum() / max((x | y).sum(), 1) for x, y in zip(ca, cb, strict=True)]))


def main() -> None:
    from prism3d.atr.chips import load_mesh_file
    from prism3d.datasets.models.scanned import compare_scan_banks, scan_builtin_target
    from prism3d.datasets.models.targets import builtin_target, list_builtin_targets

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", nargs="+", default=["tank_t1", "jet_j1", "ship_s1", "truck_k1"])
    ap.add_argument("--channels", nargs="+", default=["depth", "shape", "intensity"])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/prism3d_scan_bank"))
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    names = list_builtin_targets() if a.targets == ["all"] else a.targets
    t0 = time.perf_counter()
    scans, notes = {}, {}
    for n in names:
        st = scan_builtin_target(n, a.cache / n)
        scans[n] = load_mesh_file(st.mesh, name=f"{n}_scan")
        notes[n] = st.notes
        print(f"scanned {n}: {len(scans[n].vertices)} vertices, {time.perf_counter() - t0:.0f} s", flush=True)
    t_scan = time.perf_counter() - t0
    true = {n: builtin_target(n, seed=0) for n in names}  # the paint the scanner saw
    cls = {n: str(true[n].metadata["class"]) for n in names}
    ious = {n: mask_iou(scans[n], true[n]) for n in names}
    print("\n| target | mask IoU scan vs true (8 azimuths, el 20) | notes |\n|---|---:|---|")
    for n in names:
        print(f"| {n} | {ious[n]:.3f} | {'; '.join(notes[n])[:160]} |")
    test = [(cls[n], builtin_target(n, camouflage=True, seed=17)) for n in names]
    t1 = time.perf_counter()
    res = compare_scan_banks([(cls[n], scans[n]) for n in names], [(cls[n], true[n]) for n in names], test,
                             channels=a.channels)
    print(f"\n{len(names)} targets ({', '.join(names)}), scanned in {t_scan:.0f} s, banks in "
          f"{time.perf_counter() - t1:.0f} s")
    print("\n| channel | Pcc, bank from scans | Pcc, bank from true meshes | difference (points) | "
          "ROC AUC scans / meshes |\n|---|---:|---:|---:|---|")
    for ch, r in res.items():
        print(f"| {ch} | {100 * r.scan.pcc:.1f} % | {100 * r.mesh.pcc:.1f} % | "
              f"{r.difference_points:+.1f} | {r.scan.roc['auc']:.3f} / {r.mesh.roc['auc']:.3f} |")
    if a.json is not None:
        doc = {"targets": names, "mask_iou": ious, "notes": notes,
               "channels": {ch: r.to_json() for ch, r in res.items()}}
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(doc, indent=1))
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
