"""Which features and how much mining the field-scene verifier needs: variants trained on
one mined set, scored on issue 29's 20 field scenes in the same run.

Retraining alone moves Pd at 0.1 FPPI by a few points (the matcher's threads and the
banks' training are not bit-exact), so variants are compared on *one* mining run: the
scenes are mined once with every candidate channel's filter responses in the rows, and each
variant's recogniser is its banks plus a verifier fitted on its columns (and its scenes).

    python benchmarks/bench_verifier_features.py mine --scenes 64 --rows /tmp/vf/rows.npz
    python benchmarks/bench_verifier_features.py eval --rows /tmp/vf/rows.npz --work /tmp/field/scenes

``mine`` keeps the banks beside the rows (``banks_*.npz``); ``eval`` generates and
reconstructs the 20 scored scenes (seeds 100-119) once into ``--work`` (kept as ``rec.npz``)
and writes ``benchmarks/results/verifier_features.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prism3d.atr.bank import BANK_CHIP_SPEC
from prism3d.atr.detect import detect_scene, in_left_view, scene_channels
from prism3d.atr.scene_eval import score_scenes
from prism3d.atr.verifier import SceneRecogniser, n_size_features
from prism3d.capture.rig import StereoRig
from prism3d.datasets.database.resolve import resolve_targets
from prism3d.datasets.jobs.database_jobs import RunOptions
from prism3d.datasets.jobs.mining import MinedRows, MiningOptions, fit_recogniser, mine_rows, recogniser_banks
from prism3d.datasets.simulation.field import FieldOptions, simulate_field
from prism3d.io.images import read_image
from prism3d.reconstruct.stereo.pipeline import ReconstructOptions, convergence_distance_mm, reconstruct_shot

CLASSES = ["tank_t1", "jet_j1", "ship_s1", "truck_k1"]
CHANNELS = ("shape", "depth", "intensity")


def mine(a: argparse.Namespace) -> None:
    """Banks in every candidate channel, then the mining scenes' rows with all their responses."""
    t0 = time.perf_counter()
    o = MiningOptions(scenes=a.scenes, channels=CHANNELS, chip_spec=BANK_CHIP_SPEC)
    banks, classes, _ = recogniser_banks(resolve_targets(CLASSES), options=o)
    a.rows.parent.mkdir(parents=True, exist_ok=True)
    placeholder = fit_recogniser(banks, classes, MinedRows(np.zeros((2, n_size_features(len(classes)) + len(banks)
                                                                      * (len(banks[0].classes) + 1))),
                                                           [classes[0], "none"], []))
    placeholder.save(a.rows.with_name("banks_" + a.rows.stem + ".npz"))
    mined = mine_rows(banks, classes, CLASSES, options=o, run=RunOptions(workers=a.workers),
                      progress=lambda i, n, what: print(f"{i}/{n} {what}", flush=True))
    np.savez(a.rows, X=mined.X, y=np.array(mined.y), per_scene=json.dumps(mined.per_scene),
             seconds=time.perf_counter() - t0)
    print(f"mined {len(mined.y)} rows from {a.scenes} scenes in {time.perf_counter() - t0:.0f} s")


def _columns(n_targets: int, n_classes: int, channels: tuple[str, ...]) -> np.ndarray:
    """The row columns of the size features and of ``channels``' responses."""
    n_size, per = n_size_features(n_targets), n_classes + 1
    cols = list(range(n_size))
    for ch in channels:
        k = CHANNELS.index(ch)
        cols += list(range(n_size + k * per, n_size + (k + 1) * per))
    return np.asarray(cols)


def _variant(all_banks: SceneRecogniser, z, channels: tuple[str, ...], scenes: int, C: float) -> SceneRecogniser:
    """The recogniser of ``channels`` with its verifier fitted on the first ``scenes`` mined scenes."""
    per_scene = json.loads(str(z["per_scene"]))
    n_rows = sum(s["positive"] + s["negative"] for s in per_scene[:scenes])
    banks = tuple(b for b in all_banks.banks if b.channel in channels)
    order = tuple(b.channel for b in banks)
    cols = _columns(len(all_banks.targets), len(banks[0].classes), order)
    X, y = z["X"][:n_rows][:, cols], [str(v) for v in z["y"][:n_rows]]
    return fit_recogniser(banks, all_banks.targets, MinedRows(X, y, per_scene[:scenes]), C=C)


def _scored_scenes(work: Path, n: int) -> list[Path]:
    """The scored scenes (seeds 100...), simulated and reconstructed once."""
    folders = []
    for k in range(n):
        d = work / f"scene_{100 + k:04d}"
        if not (d / "truth.json").is_file():
            simulate_field(d, FieldOptions(seed=100 + k))
        if not (d / "rec.npz").is_file():
            rig = StereoRig.load(d / "rig.yaml")
            wd = convergence_distance_mm(rig)
            rec = reconstruct_shot(read_image(d / "shot.png"), rig, ReconstructOptions(depth_range_mm=(0.3 * wd, 10 * wd)))
            grey = rec.left_rect.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
            np.savez(d / "rec.npz", grey=grey, depth=rec.depth_mm, K=np.asarray(rec.rect.P1)[:, :3], R1=rec.rect.R1)
        folders.append(d)
    return folders


def _score(model: SceneRecogniser, folders: list[Path]) -> dict:
    """Pd / identification / confusers of ``model`` on the scored scenes, as bench_field_scenes."""
    pairs, ts = [], []
    for d in folders:
        rig = StereoRig.load(d / "rig.yaml")
        truth = json.loads((d / "truth.json").read_text())
        z = np.load(d / "rec.npz")
        sc = scene_channels(z["grey"] / 255.0, z["depth"], z["K"])
        t = time.perf_counter()
        dets = detect_scene(model, sc)
        ts.append(time.perf_counter() - t)
        dets = in_left_view(dets, z["K"], z["R1"], rig)  # rectified grid -> left view, as detect_shot does
        pairs.append(({"detections": [dt.to_json() for dt in dets]}, truth))
    r = score_scenes(pairs).to_json()  # the results document, with this run's figures added
    r["detect_s_median"] = float(np.median(ts))
    return r


def evaluate(a: argparse.Namespace) -> None:
    """Every variant on the scored scenes, printed and written as JSON."""
    z = np.load(a.rows)
    all_banks = SceneRecogniser.load(a.rows.with_name("banks_" + a.rows.stem + ".npz"))
    n_mined = len(json.loads(str(z["per_scene"])))
    folders = _scored_scenes(a.work, a.n)
    variants = [(ch, s) for s in sorted({min(40, n_mined), n_mined})
                for ch in (("shape", "depth"), ("shape", "depth", "intensity"), ("depth", "intensity"))]
    out = {"mined_scenes": n_mined, "rows": int(len(z["y"])), "mining_s": float(z["seconds"]), "variants": {}}
    for channels, scenes in variants:
        name = f"{'+'.join(channels)} / {scenes} scenes"
        r = _score(_variant(all_banks, z, channels, scenes, a.C), folders)
        out["variants"][name] = r
        _say(name, r)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1, default=float))


def _say(name: str, r: dict) -> None:
    """One line of a variant's scores."""
    v1, v10 = r["at_fppi"]["0.1"], r["at_fppi"]["1"]
    fit = f" | fit {r['fit_s']:.1f} s" if "fit_s" in r else ""
    print(f"{name:36s} Pd@0.1 {v1['pd']:.3f} id {v1['id_accuracy']:.3f} conf {v1['confusers_called']:.3f} | "
          f"Pd@1 {v10['pd']:.3f}{fit} | {r['detect_s_median']:.2f} s/shot", flush=True)


class _Wrapped:
    """A scikit-learn classifier on some feature columns, as the verifier (``classes``, ``proba``)."""

    def __init__(self, clf, cols: np.ndarray, classes: tuple[str, ...]) -> None:
        self.clf, self.cols, self.classes = clf, cols, classes

    def proba(self, X: np.ndarray) -> np.ndarray:
        P = self.clf.predict_proba(np.atleast_2d(X)[:, self.cols])
        out = np.zeros((P.shape[0], len(self.classes)))
        for k, c in enumerate(self.clf.classes_):
            out[:, self.classes.index(str(c))] = P[:, k]
        return out


class _Mean:
    """The mean of several classifiers' probabilities (an ensemble)."""

    def __init__(self, members: list) -> None:
        self.members = members

    def fit(self, X: np.ndarray, y: np.ndarray) -> _Mean:
        for m in self.members:
            m.fit(X, y)
        self.classes_ = self.members[0].classes_
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        return np.mean([m.predict_proba(X) for m in self.members], axis=0)


def _models(seed: int) -> dict:
    """The classifiers compared on the same rows (scaled inputs where they need it)."""
    from sklearn.ensemble import HistGradientBoostingClassifier, RandomForestClassifier
    from sklearn.linear_model import LogisticRegression
    from sklearn.neural_network import MLPClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    return {
        "logistic C=0.1 (default)": make_pipeline(StandardScaler(), LogisticRegression(C=0.1, max_iter=5000)),
        "logistic C=1": make_pipeline(StandardScaler(), LogisticRegression(C=1.0, max_iter=5000)),
        "logistic C=0.1 balanced": make_pipeline(StandardScaler(), LogisticRegression(C=0.1, max_iter=5000,
                                                                                      class_weight="balanced")),
        "gradient boosting": HistGradientBoostingClassifier(max_iter=300, learning_rate=0.05, random_state=seed),
        "gradient boosting, shallow": HistGradientBoostingClassifier(max_iter=200, learning_rate=0.05, max_depth=3,
                                                                     l2_regularization=1.0, random_state=seed),
        "gradient boosting, leaves 8": HistGradientBoostingClassifier(max_iter=400, learning_rate=0.03,
                                                                      max_leaf_nodes=8, min_samples_leaf=10,
                                                                      random_state=seed),
        "logistic + gradient boosting": _Mean([
            make_pipeline(StandardScaler(), LogisticRegression(C=0.1, max_iter=5000)),
            HistGradientBoostingClassifier(max_iter=300, learning_rate=0.05, random_state=seed)]),
        "random forest": RandomForestClassifier(n_estimators=400, min_samples_leaf=2, n_jobs=2, random_state=seed),
        "MLP 32": make_pipeline(StandardScaler(), MLPClassifier((32,), alpha=1e-2, max_iter=2000, random_state=seed)),
        "MLP 64-32": make_pipeline(StandardScaler(), MLPClassifier((64, 32), alpha=1e-2, max_iter=2000,
                                                                   random_state=seed)),
    }


def compare_models(a: argparse.Namespace) -> None:
    """Classifiers on the same mined rows and features (channels ``--channels``), scored alike."""
    z = np.load(a.rows)
    all_banks = SceneRecogniser.load(a.rows.with_name("banks_" + a.rows.stem + ".npz"))
    folders = _scored_scenes(a.work, a.n)
    base = _variant(all_banks, z, tuple(a.channels), 10_000, 0.1)  # banks, prefilter and LR of these channels
    cols = _columns(len(all_banks.targets), len(base.banks[0].classes), tuple(b.channel for b in base.banks))
    X, y = z["X"][:, cols], np.array([str(v) for v in z["y"]])
    classes = base.verifier.classes
    out = {"channels": list(a.channels), "rows": int(len(y)), "models": {}}
    for name, clf in _models(0).items():
        if a.only and not any(k in name for k in a.only):
            continue
        t = time.perf_counter()
        clf.fit(X, y)
        fit_s = time.perf_counter() - t
        model = SceneRecogniser(base.banks, base.targets, base.verifier, {}, base.prefilter, base.prefilter_threshold)
        object.__setattr__(model, "verifier", _Wrapped(clf, np.arange(X.shape[1]), classes))
        r = _score(model, folders)
        r["fit_s"] = fit_s
        out["models"][name] = r
        _say(name, r)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1, default=float))


def main() -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("mine")
    m.add_argument("--scenes", type=int, default=64)
    m.add_argument("--rows", type=Path, required=True)
    m.add_argument("--workers", type=int, default=2)
    e = sub.add_parser("eval")
    e.add_argument("--rows", type=Path, required=True)
    e.add_argument("--work", type=Path, default=Path("/tmp/field_bench"))
    e.add_argument("--n", type=int, default=20)
    e.add_argument("--C", type=float, default=0.1)
    e.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "verifier_features.json")
    c = sub.add_parser("models")
    c.add_argument("--rows", type=Path, required=True)
    c.add_argument("--work", type=Path, default=Path("/tmp/field_bench"))
    c.add_argument("--n", type=int, default=20)
    c.add_argument("--channels", nargs="+", default=["shape", "depth"])
    c.add_argument("--only", nargs="*", help="models whose name holds one of these")
    c.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "verifier_models.json")
    a = ap.parse_args()
    {"mine": mine, "eval": evaluate, "models": compare_models}[a.cmd](a)


if __name__ == "__main__":
    main()
