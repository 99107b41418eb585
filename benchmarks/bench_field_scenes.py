"""Whole-scene ATR on simulated field scenes: Pd vs false positives per image per channel.

Generates ``--n`` field scenes (``prism3d simulate field``, seeds ``--seed0``...), trains
the scene recogniser of ``bank train``'s defaults on the four default classes (filters over
the targets and what to refuse, a verifier mined from simulated scenes; ``--recogniser
PATH`` takes one already trained), and, beside it, one plain bank per channel (``bank train
--scenes 0``, the filters alone: today's bank before the recogniser),
reconstructs each shot once and runs every bank on it, then scores with
:func:`prism3d.atr.scene_eval.score_scenes`. Prints Pd / identification / confusers at
0.1 and 1 FPPI, detection time per shot (reconstruction excluded) and scenes per minute;
writes ``benchmarks/results/field_scenes.json`` (with each run's Pd-FPPI curve).

``--true-depth`` adds the best 3D bank on the simulator's exact depth (the recogniser's
own limit, stereo taken out); ``--rate N`` generates N more scenes as a batch job in this
process and on 2 Dask workers (scenes per minute, 1 vs 2 workers).

    python benchmarks/bench_field_scenes.py --n 20 --work /tmp/field_bench --true-depth --rate 4
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prism3d.atr.bank import BANK_CHIP_SPEC, train_bank
from prism3d.atr.detect import detect_scene, detect_scene_hog, in_left_view, scene_channels
from prism3d.atr.hog_svm import HogSvm
from prism3d.atr.scene_eval import score_scenes
from prism3d.atr.verifier import SceneRecogniser
from prism3d.capture.rig import StereoRig
from prism3d.datasets.simulation.field import FieldOptions, simulate_field, simulate_field_batch
from prism3d.datasets.jobs.database_jobs import RunOptions
from prism3d.datasets.jobs.mining import MiningOptions, train_scene_recogniser
from prism3d.datasets.database.resolve import resolve_targets
from prism3d.io.images import read_image
from prism3d.reconstruct.stereo.pipeline import (
    ReconstructOptions,
    convergence_distance_mm,
    reconstruct_shot,
)

CLASSES = ["tank_t1", "jet_j1", "ship_s1", "truck_k1"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--work", type=Path, default=Path("/tmp/field_bench"))
    ap.add_argument("--channels", nargs="+", default=["depth", "shape", "intensity"])
    ap.add_argument("--no-hog", action="store_true", help="skip the HOG + SVM baseline")
    ap.add_argument("--true-depth", action="store_true", help="also the shape bank on the exact depth")
    ap.add_argument("--rate", type=int, default=0, metavar="N",
                    help="generate N scenes as a batch job, in-process and on 2 Dask workers")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "field_scenes.json")
    ap.add_argument("--recogniser", type=Path, help="a trained recogniser (default: train one with the defaults)")
    ap.add_argument("--workers", type=int, default=2, help="mining scenes' Dask workers when training")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    folders, made = [], 0
    for k in range(a.n):
        d = a.work / f"scene_{a.seed0 + k:04d}"
        if not (d / "truth.json").is_file():
            simulate_field(d, FieldOptions(seed=a.seed0 + k))
            made += 1
        folders.append(d)
    gen_s = time.perf_counter() - t0
    targets = resolve_targets(CLASSES)
    t_rec = time.perf_counter()
    if a.recogniser is not None:
        recogniser = SceneRecogniser.load(a.recogniser)
    else:
        recogniser = train_scene_recogniser(targets, CLASSES, options=MiningOptions(chip_spec=BANK_CHIP_SPEC),
                                            run=RunOptions(workers=a.workers))
    t_rec = time.perf_counter() - t_rec
    banks = {c: train_bank(targets, channel=c, chip_spec=BANK_CHIP_SPEC) for c in a.channels}
    hogs = {} if a.no_hog else {c: HogSvm.train(targets, channel=c, chip_spec=BANK_CHIP_SPEC) for c in a.channels}
    runs = [("shape+depth", "recogniser", recogniser)] + [(c, "bank", b) for c, b in banks.items()] \
        + [(c, "hog", m) for c, m in hogs.items()]
    best3d = "shape" if "shape" in banks else next((c for c in banks if c != "intensity"), None)
    if a.true_depth and best3d is not None:
        runs.append((best3d, "bank-true-depth", banks[best3d]))
    pairs = {(c, k): [] for c, k, _ in runs}
    det_s = {(c, k): [] for c, k, _ in runs}
    rec_s, ch_s = [], []
    for d in folders:
        rig = StereoRig.load(d / "rig.yaml")
        truth = json.loads((d / "truth.json").read_text())
        t1 = time.perf_counter()
        cache = d / "rec.npz"  # the reconstruction, kept beside the scene in the work folder
        if not cache.is_file():
            wd = convergence_distance_mm(rig)
            rec = reconstruct_shot(read_image(d / "shot.png"), rig,
                                   ReconstructOptions(depth_range_mm=(0.3 * wd, 10 * wd)))
            grey = rec.left_rect.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
            np.savez(cache, grey=grey, depth=rec.depth_mm, K=np.asarray(rec.rect.P1)[:, :3], R1=rec.rect.R1)
            rec_s.append(time.perf_counter() - t1)
        z = np.load(cache)
        t2 = time.perf_counter()
        sc = scene_channels(z["grey"] / 255.0, z["depth"], z["K"])
        t3 = time.perf_counter()
        ch_s.append(t3 - t2)
        R1 = np.asarray(z["R1"])
        sc_true = _true_scene(d, rig) if any(k == "bank-true-depth" for _, k, _ in runs) else None
        for c, kind, model in runs:
            t4 = time.perf_counter()
            if kind == "bank-true-depth":
                dets = detect_scene(model, sc_true)  # already in the left view
            else:
                dets = detect_scene(model, sc) if kind in ("bank", "recogniser") else detect_scene_hog(model, sc)
            det_s[(c, kind)].append(time.perf_counter() - t4)
            if kind != "bank-true-depth":  # rectified grid -> left view, as detect_shot does
                dets = in_left_view(dets, z["K"], R1, rig)
            pairs[(c, kind)].append(({"detections": [dt.to_json() for dt in dets]}, truth))
        print(d.name, f"channels {t3 - t2:.1f} s", flush=True)
    out = {"n_scenes": a.n, "generated": made, "generation_s": gen_s, "recogniser_train_s": round(t_rec, 1),
           "recogniser": recogniser.metadata.get("mining", {}),
           "scenes_per_minute": 60 * made / gen_s if made else None,
           "reconstruct_s_median": float(np.median(rec_s)) if rec_s else None,
           "channels_s_median": float(np.median(ch_s)), "runs": {}}
    for (c, kind), pr in pairs.items():
        r = score_scenes(pr).to_json()  # the results document, with this run's figures added
        r["detect_s_median"] = float(np.median(det_s[(c, kind)]))
        out["runs"][f"{kind}:{c}"] = r
        for x, v in r["at_fppi"].items():
            print(f"{kind:4s} {c:9s} at {x:>3s} FPPI: Pd {v['pd']:.3f}  id {v['id_accuracy']}  "
                  f"confusers called {v['confusers_called']:.3f}")
        print(f"{kind:4s} {c:9s} Pd max {r['pd_max']:.3f}; detect {r['detect_s_median']:.2f} s/shot "
              f"(+ channels {out['channels_s_median']:.2f} s)")
    if a.rate:
        out["batch_rate"] = _batch_rate(a.work / "rate", a.seed0 + 10_000, a.rate)
        print("batch generation, scenes/min:", out["batch_rate"])
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1, default=float))
    if made:
        print("generation:", f"{out['scenes_per_minute']:.1f} scenes/min")


def _true_scene(d: Path, rig: StereoRig):
    """The scene's channels from the simulator's exact left-view depth and the left view."""
    z = np.load(d / "truth.npz")
    left = rig.split.split(read_image(d / "shot.png"))[0].astype(np.float32)
    grey = left @ np.array([0.299, 0.587, 0.114], dtype=np.float32) if left.ndim == 3 else left
    depth = z["depth_left_mm"].astype(np.float32)
    depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
    return scene_channels(grey / 255.0, depth, rig.left.K)


def _batch_rate(root: Path, seed: int, n: int) -> dict:
    """Scenes per minute of ``simulate field --count n`` in this process and on 2 workers."""
    import shutil

    rates = {}
    for workers in (0, 2):
        folder = root / f"workers_{workers}"
        shutil.rmtree(folder, ignore_errors=True)
        rep = simulate_field_batch(folder, n, FieldOptions(seed=seed), RunOptions(workers=workers))
        rates[f"workers_{workers}"] = round(60.0 * rep.done_units / rep.seconds, 2)
    return rates


if __name__ == "__main__":
    main()
