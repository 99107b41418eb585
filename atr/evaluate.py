"""Recognition evaluation: Pcc, confusion, per-aspect / per-range accuracy, ROC, PSR
distributions, plots, and a feature-based baseline classifier.

:func:`evaluate_bank` classifies test chips at unseen poses and scores target chips
against clutter-only chips (ROC definitions: docs/atr.md "Evaluation").
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.bank import FilterBank, check_targets, render_class_chips
from prism3d.atr.chips import (
    ChipSpec,
    as_chip_spec,
    bounding_sphere,
    ground_mesh,
    render_chips,
    spec_poses,
)
from prism3d.atr.features import view_features
from prism3d.atr.poses import parse_range
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_paths

__all__ = [
    "BankEvaluation",
    "EVAL_CHIP_SPEC",
    "HELDOUT_SEED_OFFSET",
    "accuracy_by",
    "confusion_matrix",
    "evaluate_bank",
    "feature_baseline",
    "format_results",
    "heldout_seed",
    "pcc",
    "plot_confusion",
    "plot_per_aspect",
    "plot_psr_histograms",
    "plot_roc",
    "roc_curve",
]

log = logging.getLogger(__name__)

#: Test seed = training seed + 1: a camouflage pattern and noise the bank never saw.
HELDOUT_SEED_OFFSET = 1
#: Seed stride between targets' clutter-only chips (distinct from the class stride 1009).
_CLUTTER_SEED_STRIDE = 31


def _labels(values: Sequence[str], classes: Sequence[str], name: str) -> NDArray[np.int64]:
    idx = {c: i for i, c in enumerate(classes)}
    out = []
    for v in values:
        if v not in idx:
            raise InputError(f"{name}: unknown class {v!r}; the bank's classes are {list(classes)}")
        out.append(idx[v])
    return np.asarray(out, dtype=np.int64)


def pcc(true: Sequence[str], pred: Sequence[str]) -> float:
    """Probability of correct classification (fraction of equal labels)."""
    t, p = list(true), list(pred)
    if len(t) != len(p) or not t:
        raise InputError(
            f"pcc: expected two equal, non-empty label lists, got {len(t)} and {len(p)}"
        )
    return float(np.mean([a == b for a, b in zip(t, p, strict=True)]))


def confusion_matrix(
    true: Sequence[str], pred: Sequence[str], classes: Sequence[str]
) -> NDArray[np.int64]:
    """``(C, C)`` counts, row = true class, column = predicted class."""
    t = _labels(true, classes, "true labels")
    p = _labels(pred, classes, "predicted labels")
    if len(t) != len(p):
        raise InputError(f"confusion_matrix: {len(t)} true vs {len(p)} predicted labels")
    m = np.zeros((len(classes), len(classes)), dtype=np.int64)
    np.add.at(m, (t, p), 1)
    return m


def accuracy_by(
    values: NDArray, correct: NDArray, bin_width: float | None = None
) -> dict[float, float]:
    """Accuracy per value (or per bin of ``bin_width``, keyed by bin centre)."""
    v = np.asarray(values, dtype=np.float64)
    c = np.asarray(correct, dtype=bool)
    if bin_width is not None:
        v = np.round(v / bin_width) * bin_width
    return {float(k): float(c[v == k].mean()) for k in np.unique(v)}


def roc_curve(target_scores: NDArray, clutter_scores: NDArray) -> dict[str, list[float]]:
    """Pd vs Pfa over every threshold; also the area under the curve.

    Returns
    -------
    dict
        ``thresholds`` (descending), ``pd``, ``pfa`` (same length), ``auc``.
    """
    t = np.asarray(target_scores, dtype=np.float64).ravel()
    c = np.asarray(clutter_scores, dtype=np.float64).ravel()
    if t.size == 0 or c.size == 0:
        raise InputError("roc_curve: need at least one target and one clutter score")
    th = np.unique(np.concatenate([t, c]))[::-1]
    pd_ = np.array([np.mean(t >= x) for x in th])
    pfa = np.array([np.mean(c >= x) for x in th])
    x = np.concatenate([[0.0], pfa, [1.0]])
    y = np.concatenate([[0.0], pd_, [1.0]])
    auc = float(np.sum(np.diff(x) * (y[1:] + y[:-1]) / 2))
    return {"thresholds": th.tolist(), "pd": pd_.tolist(), "pfa": pfa.tolist(), "auc": auc}


def heldout_seed(seed: int) -> int:
    """Seed of the test targets and chips for a bank trained with ``seed``.

    Test targets wear a camouflage pattern (and chips get noise draws) the bank never
    saw: ``seed + HELDOUT_SEED_OFFSET``.
    """
    return int(seed) + HELDOUT_SEED_OFFSET


#: Default test chips: the library's chip defaults with the held-out seed of seed 0.
EVAL_CHIP_SPEC = ChipSpec(seed=heldout_seed(0))


def relief_noise_mm(targets: Sequence[tuple[str, object]], sigma: float) -> float:
    """The depth noise (mm) that is the same share of a chip's depth relief as ``sigma``
    is of the intensity range: a fit-framed chip spans about 2 r / 0.9 of a target of
    bounding radius r, and its relief maps that depth range onto [0, 1]; the median over
    ``targets``. ``bank eval --noise`` perturbs both channels so, not intensity alone."""
    if not targets or sigma <= 0:
        return 0.0
    radii = [bounding_sphere(m)[1] for _, m in targets]
    return float(sigma * 2.0 * np.median(radii) / 0.9)


@dataclass(frozen=True)
class BankEvaluation:
    """A bank scored on rendered test chips (:func:`evaluate_bank`); :meth:`to_json` is the
    results file ``bank eval --json`` writes, :meth:`from_json` reads one back."""

    classes: list[str]
    """The bank's classes, in the order of the confusion matrix."""
    channel: str
    """The chip channel of the bank."""
    metric: str
    """The peak metric that decides the class."""
    pcc: float
    """Probability of correct classification over the test chips."""
    confusion: list[list[int]]
    """Counts, rows = true class, columns = called class."""
    per_class: dict[str, float]
    """Accuracy per true class."""
    per_aspect: dict[str, float]
    """Accuracy per azimuth bin of the bank (key: the bin's centre, degrees)."""
    per_elevation: dict[str, float]
    """Accuracy per elevation (key: degrees)."""
    per_range: dict[str, float]
    """Accuracy per range (key: mm)."""
    roc: dict[str, Any]
    """Targets against clutter-only chips: ``thresholds``, ``pd``, ``pfa`` lists and ``auc``."""
    pd_at_pfa: dict[str, float]
    """Best Pd with Pfa at most 1, 5 and 10 % (keys "0.01", "0.05", "0.1")."""
    scores_target: list[float]
    """The best class score of each target chip."""
    scores_clutter: list[float]
    """The best class score of each clutter-only chip."""
    psr_target: list[float]
    """The best PSR of each target chip."""
    psr_clutter: list[float]
    """The best PSR of each clutter-only chip."""
    n_chips: int
    """Target chips scored."""
    conditions: dict[str, Any]
    """The test conditions: paint, noise, clutter, lighting, seed, azimuths."""

    def to_json(self) -> dict[str, Any]:
        """The results as JSON, keys in field order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_json(cls, doc: object) -> BankEvaluation:
        """Results written by :meth:`to_json` (e.g. a ``bank eval --json`` file)."""
        if not isinstance(doc, dict):
            raise InputError(f"bank evaluation: expected a JSON object, got {type(doc).__name__}")
        missing = [f.name for f in fields(cls) if f.name not in doc]
        if missing:
            raise InputError(f"bank evaluation: missing {', '.join(missing)} (not a 'bank eval --json' results file?)")
        return cls(**{f.name: doc[f.name] for f in fields(cls)})


def evaluate_bank(
    bank: FilterBank,
    targets: Sequence[tuple[str, object]],
    *,
    azimuth: str | Sequence[float] | None = None,
    elevation: str | Sequence[float] | None = None,
    range_mm: str | float | Sequence[float] | None = None,
    chip_spec: ChipSpec | None = None,
    out_json: str | Path | None = None,
) -> BankEvaluation:
    """Evaluate a bank on rendered test chips (module docstring).

    ``targets``: ``[(class, SceneMesh)]``, classes among ``bank.classes``. Default
    azimuths: the training ones shifted by a quarter step; default elevations and
    ranges: the training ones. ``chip_spec``: test conditions (None =
    :data:`EVAL_CHIP_SPEC`); its size and framing are replaced by the bank's.
    ``out_json``: also write ``<stem>_chips.parquet`` and the plots beside it.
    """
    if not isinstance(bank, FilterBank):
        raise InputError(f"bank: expected a FilterBank, got {type(bank).__name__}")
    items = _check_eval_targets(bank, targets)
    azimuth, elevation, range_mm = _test_grid(bank, azimuth, elevation, range_mm)
    spec = replace(
        as_chip_spec(chip_spec, EVAL_CHIP_SPEC),
        size=bank.size,
        framing=bank.metadata.get("framing", "fit"),
    )
    X, labels, az, el, rng_, fx = render_class_chips(
        items, channel=bank.channel, azimuth=azimuth, elevation=elevation, range_mm=range_mm,
        chip_spec=spec,
    )
    df, correct = _classify_test_chips(bank, X, fx, labels, az, el, rng_)
    cl_scores, cl_psr = _clutter_scores(bank, items, azimuth, elevation, range_mm, spec)
    cls_scores = np.array([df[f"score_{c}"].to_numpy() for c in bank.classes]).max(axis=0)
    roc = roc_curve(cls_scores, cl_scores)
    res = BankEvaluation(
        classes=list(bank.classes),
        channel=bank.channel,
        metric=bank.metric,
        pcc=float(correct.mean()),
        confusion=confusion_matrix(labels, df["pred_class"].tolist(), bank.classes).tolist(),
        **_accuracy_by_condition(bank, labels, correct, az, el, rng_),
        roc=roc,
        pd_at_pfa=_pd_at_pfa(roc),
        scores_target=cls_scores.tolist(),
        scores_clutter=cl_scores.tolist(),
        psr_target=df["psr"].tolist(),
        psr_clutter=cl_psr.tolist(),
        n_chips=len(df),
        conditions=_conditions(spec, azimuth),
    )
    if out_json is not None:
        _write_results(res, df, Path(out_json))
    return res


def _classify_test_chips(
    bank: FilterBank, X: NDArray, fx: NDArray, labels: list[str], az: NDArray, el: NDArray,
    rng_: NDArray,
) -> tuple[Any, NDArray[np.bool_]]:
    """The bank's classification of the test chips (a DataFrame, one row per chip, with its
    true class, pose and ``correct``) and that ``correct`` column."""
    df = bank.classify(X, fx)
    df.insert(0, "true_class", labels)
    df["az_deg"], df["el_deg"], df["range_mm"] = az, el, rng_
    correct = df["true_class"].to_numpy() == df["pred_class"].to_numpy()
    df["correct"] = correct
    return df, correct


def _accuracy_by_condition(
    bank: FilterBank, labels: list[str], correct: NDArray, az: NDArray, el: NDArray, rng_: NDArray
) -> dict[str, dict]:
    """Accuracy per true class, azimuth bin (the bank's), elevation and range, keyed as in
    :func:`evaluate_bank`'s results."""
    return {
        "per_class": {
            c: float(correct[np.array(labels) == c].mean()) for c in bank.classes if c in labels
        },
        "per_aspect": {
            f"{k:g}": v
            for k, v in accuracy_by(np.asarray(az) % 360.0, correct, bank.bin_deg).items()
        },
        "per_elevation": {f"{k:g}": v for k, v in accuracy_by(el, correct).items()},
        "per_range": {f"{k:g}": v for k, v in accuracy_by(rng_, correct).items()},
    }


def format_results(res: BankEvaluation) -> str:
    """Pcc and the confusion matrix of an :func:`evaluate_bank` result, as text lines."""
    lines = [f"Pcc {100 * res.pcc:.1f}% over {len(res.classes)} classes ({', '.join(res.classes)})"]
    for c, row in zip(res.classes, res.confusion, strict=True):
        lines.append(f"  {c:<10} " + " ".join(f"{v:5d}" for v in row))
    return "\n".join(lines)


def _check_eval_targets(bank: FilterBank, targets) -> list[tuple[str, object]]:
    items = check_targets(targets)
    for c, m in items:
        if c not in bank.classes:
            raise InputError(
                f"targets: unknown class {c!r} for target {m.name!r}; the bank's classes are {bank.classes}"
            )
    return items


def _test_grid(bank: FilterBank, azimuth, elevation, range_mm) -> tuple[list[float], object, object]:
    """Test azimuths (default: a quarter training step past them), elevations, ranges."""
    md = bank.metadata
    if azimuth is None:
        tr = md.get("azimuth") or [0.0]
        step = float(np.median(np.diff(sorted(tr)))) if len(tr) > 1 else bank.bin_deg
        azimuth = [a + step / 4.0 for a in tr]
    if elevation is None:
        elevation = md.get("elevation") or [20.0]
    if range_mm is None and md.get("range_mm"):
        range_mm = md["range_mm"]
    return parse_range(azimuth), elevation, range_mm


def _clutter_scores(
    bank: FilterBank, items, azimuth, elevation, range_mm, spec: ChipSpec
) -> tuple[NDArray, NDArray]:
    """Best score and PSR of clutter-only chips (ground, or noise background) per pose."""
    scores, psr = [], []
    for i, (_, mesh) in enumerate(items):
        poses = spec_poses(mesh, azimuth, elevation, range_mm, spec)
        cspec = replace(
            spec,
            channels=(bank.channel,),
            clutter="noise" if spec.clutter == "noise" else None,
            seed=spec.seed + _CLUTTER_SEED_STRIDE * i,
        )
        r = bank.responses(render_chips(ground_mesh(mesh, spec.seed + i), poses, chip_spec=cspec))
        scores.append(r[bank.metric].max(axis=1))
        psr.append(r["psr"].max(axis=1))
    return np.concatenate(scores), np.concatenate(psr)


def _pd_at_pfa(roc: dict) -> dict[str, float]:
    """Best Pd with Pfa <= 1 %, 5 %, 10 % (keys ``"0.01"``...)."""
    out = {}
    for lim in (0.01, 0.05, 0.1):
        ok = [p for p, f in zip(roc["pd"], roc["pfa"], strict=True) if f <= lim]
        out[str(lim)] = float(max(ok)) if ok else 0.0
    return out


def _conditions(spec: ChipSpec, azimuth: list[float]) -> dict:
    return {
        "camouflage": bool(spec.camouflage),
        "noise_sigma": float(spec.noise_sigma),
        "depth_noise_mm": float(spec.depth_noise_mm),
        "clutter": spec.clutter,
        "lighting_variation": float(spec.lighting_variation),
        "seed": int(spec.seed),
        "azimuth": [float(a) for a in azimuth],
    }


def _write_results(res: BankEvaluation, df, path: Path) -> None:
    """The results JSON, the chip table and the four plots: written under temp names,
    renamed together only when all of them were written (a failure leaves none)."""
    plt = _plt()
    stem = path.with_suffix("")
    figs = {"confusion": plot_confusion(res), "aspect": plot_per_aspect(res),
            "roc": plot_roc(res), "psr": plot_psr_histograms(res)}
    names = [path, Path(f"{stem}_chips.parquet"), *(Path(f"{stem}_{n}.png") for n in figs)]
    try:
        with atomic_paths(*names) as tmp:
            tmp[0].write_text(json.dumps(res.to_json(), indent=1), encoding="utf-8")
            df.to_parquet(tmp[1], index=False)
            for t, fig in zip(tmp[2:], figs.values(), strict=True):
                fig.savefig(t, format="png", dpi=80)
    finally:
        for fig in figs.values():
            plt.close(fig)


def _plt():
    # no backend forced: headless, matplotlib picks Agg itself; in a notebook the figures
    # stay inline (forcing Agg here silenced them)
    import matplotlib.pyplot as plt

    return plt


def plot_confusion(res: BankEvaluation, *, ax=None, title: str | None = None):  # -> matplotlib Figure
    """Confusion matrix (row-normalised colours, counts printed); into ``ax`` when given
    (matrices side by side), with ``title`` before the Pcc."""
    plt = _plt()
    m = np.asarray(res.confusion, dtype=float)
    cls = res.classes
    if ax is None:
        fig, ax = plt.subplots(figsize=(4, 3.5))
    else:
        fig = ax.figure
    norm = m / np.maximum(m.sum(axis=1, keepdims=True), 1)
    ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    for i in range(len(cls)):
        for j in range(len(cls)):
            ax.text(
                j,
                i,
                f"{int(m[i, j])}",
                ha="center",
                va="center",
                color="k" if norm[i, j] < 0.6 else "w",
            )
    ax.set_xticks(range(len(cls)), cls)
    ax.set_yticks(range(len(cls)), cls)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(f"{title or res.channel}: Pcc = {100 * res.pcc:.1f}%")
    fig.tight_layout()
    return fig


def plot_per_aspect(res: BankEvaluation):  # -> matplotlib Figure
    """Accuracy per azimuth bin on a polar plot (0 deg = nose-on)."""
    plt = _plt()
    az = np.array([float(k) for k in res.per_aspect])
    acc = np.array(list(res.per_aspect.values()))
    order = np.argsort(az)
    fig = plt.figure(figsize=(4, 4))
    ax = fig.add_subplot(projection="polar")
    a = np.radians(np.append(az[order], az[order][0]))
    ax.plot(a, np.append(acc[order], acc[order][0]), "o-")
    ax.set_ylim(0, 1.05)
    ax.set_title(f"{res.channel}: accuracy per aspect")
    return fig


def plot_roc(res: BankEvaluation):  # -> matplotlib Figure
    """Pd vs Pfa (target chips vs clutter-only chips)."""
    plt = _plt()
    r = res.roc
    fig, ax = plt.subplots(figsize=(4, 3.5))
    ax.plot([0] + r["pfa"] + [1], [0] + r["pd"] + [1], "-")
    ax.set_xlabel("Pfa (false alarms per clutter chip)")
    ax.set_ylabel("Pd")
    ax.set_xscale("symlog", linthresh=0.01)
    ax.set_title(f"ROC, AUC = {r['auc']:.3f}")
    fig.tight_layout()
    return fig


def plot_psr_histograms(res: BankEvaluation):  # -> matplotlib Figure
    """Histograms of the best PSR: target chips vs clutter chips."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4, 3.5))
    t = np.asarray(res.psr_target)
    c = np.asarray(res.psr_clutter)
    bins = np.linspace(min(t.min(), c.min()), max(t.max(), c.max()), 30)
    ax.hist(t, bins, alpha=0.6, label="targets")
    ax.hist(c, bins, alpha=0.6, label="clutter")
    ax.set_xlabel("best PSR")
    ax.legend()
    fig.tight_layout()
    return fig


def feature_baseline(
    targets: Sequence[tuple[str, object]],
    *,
    feature_fn: Callable[[NDArray, NDArray, NDArray], dict[str, float]] | None = None,
    train_azimuth: str | Sequence[float] = "0:360:10",
    test_azimuth: str | Sequence[float] | None = None,
    elevation: str | Sequence[float] = "20",
    size: int = 64,
    camouflage: bool = True,
    depth_noise_mm: float = 0.0,
    seed: int = 0,
) -> dict:
    """Feature-based baseline: a RandomForest (``random_state=0``) on view features.

    ``feature_fn(depth_mm, mask, K) -> dict[str, float]`` computes the features of
    one depth view (default: :func:`prism3d.atr.features.view_features`). Training
    and test views are depth chips at ``range``-true framing (sizes are features).

    Returns
    -------
    dict
        ``pcc``, ``confusion``, ``classes``, ``feature_names``.
    """
    from sklearn.ensemble import RandomForestClassifier

    items = check_targets(targets)
    if feature_fn is None:
        feature_fn = view_features
    classes = sorted({c for c, _ in items}, key=[c for c, _ in items].index)
    tr = parse_range(train_azimuth)
    if test_azimuth is None:
        step = float(np.median(np.diff(sorted(tr)))) if len(tr) > 1 else 10.0
        test_azimuth = [a + step / 4.0 for a in tr]
    views = {"elevation": elevation, "size": size, "camouflage": camouflage,
             "depth_noise_mm": depth_noise_mm}
    Xtr, ytr, names = _feature_table(items, feature_fn, tr, seed, **views)
    Xte, yte, _ = _feature_table(items, feature_fn, parse_range(test_azimuth), seed + 100, **views)
    Xtr = np.nan_to_num(Xtr)
    Xte = np.nan_to_num(Xte)
    clf = RandomForestClassifier(n_estimators=200, random_state=0, n_jobs=1).fit(Xtr, ytr)
    pred = clf.predict(Xte).tolist()
    return {
        "pcc": pcc(yte, pred),
        "confusion": confusion_matrix(yte, pred, classes).tolist(),
        "classes": classes,
        "feature_names": names,
    }


def _feature_table(
    items: list[tuple[str, object]],
    feature_fn: Callable[[NDArray, NDArray, NDArray], dict[str, float]],
    az: NDArray,
    seed: int,
    *,
    elevation: str | Sequence[float],
    size: int,
    camouflage: bool,
    depth_noise_mm: float,
) -> tuple[NDArray[np.float64], list[str], list[str]]:
    """Features of every target's depth views at azimuths ``az`` (``range`` framing, target
    ``i`` seeded ``seed + i``): the table ``(N, F)``, its class labels and column names."""
    rows, labs = [], []
    for i, (c, mesh) in enumerate(items):
        spec = ChipSpec(
            size=size,
            framing="range",
            channels=("depth", "mask"),
            camouflage=camouflage,
            depth_noise_mm=depth_noise_mm,
            seed=seed + i,
        )
        cs = render_chips(mesh, None, azimuth=az, elevation=elevation, chip_spec=spec)
        for j, p in enumerate(cs.poses):
            rows.append(feature_fn(cs["depth"][j], cs["mask"][j], p.K))
            labs.append(c)
    names = sorted(rows[0])
    return np.array([[float(r.get(n, np.nan)) for n in names] for r in rows]), labs, names
