"""The discriminative stage of whole-scene detection: what an object in a scene is, from
the correlation filters' responses, its 3D size and its range.

The paper's filters answer "which class does this look most like"; they were never shown
a negative, so a sibling vehicle or a crate looks like its nearest class. A
:class:`SceneRecogniser` holds banks (one per channel, e.g. shape and depth) over the
targets *and* the classes to refuse (the other built-in vehicles, crates, fuel tanks), and
a multinomial logistic regression (scikit-learn, weights kept as arrays) over, per object
standing on the ground: each class's best peak-to-correlation energy in each bank, how
much better the best target class does than the best refused class, the object's length,
width and height and their log-ratio to each target class's, its pixel area against the
area the class would cover at its range, and the range. It is trained on objects found
in simulated scenes with exact truth (:mod:`prism3d.datasets.jobs.mining`): the targets' own
pieces are positives, everything else (clutter, ground noise, siblings, crates) negative.
Method and figures: docs/atr.md "Learning what is not a target".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.bank import FilterBank, spectrum_metrics
from prism3d.atr.scene import (
    DetectOptions,
    SceneChannels,
    SceneDetection,
    bank_scale,
    chip_channel,
    class_size,
    project,
)
from prism3d.errors import InputError
from prism3d.io.model_file import read_model_npz, write_model_npz

__all__ = ["NONE", "RECOGNISER_SCHEMA_VERSION", "SceneRecogniser", "Verifier", "detect_objects",
           "filter_features", "object_features", "object_gate", "n_size_features", "size_features", "train_prefilter", "train_verifier"]

RECOGNISER_SCHEMA_VERSION = 1
#: The verifier's label for "not a target".
NONE = "none"
#: An object is looked at when it has this many pixels, stands this high and is this long
#: (mm): below, stereo noise and grass tufts; every target of the field scenes passes.
MIN_OBJECT_PX, MIN_OBJECT_HEIGHT_MM, MIN_OBJECT_LENGTH_MM = 40, 400.0, 1000.0


@dataclass(frozen=True)
class Verifier:
    """Standardisation (``mean``, ``scale``) and a multinomial logistic regression
    (``coef`` (K, D), ``intercept`` (K,)) over ``classes`` (targets, then ``none``)."""

    classes: tuple[str, ...]
    mean: NDArray[np.float64]
    scale: NDArray[np.float64]
    coef: NDArray[np.float64]
    intercept: NDArray[np.float64]

    def proba(self, X: NDArray) -> NDArray[np.float64]:
        """Class probabilities (n, K) of feature rows (n, D)."""
        z = ((np.atleast_2d(X) - self.mean) / self.scale) @ self.coef.T + self.intercept
        z -= z.max(axis=1, keepdims=True)
        p = np.exp(z)
        return p / p.sum(axis=1, keepdims=True)


def train_verifier(X: NDArray, y: Sequence[str], targets: Sequence[str], *, C: float = 0.1) -> Verifier:
    """Fit the verifier on feature rows and labels (a target class or :data:`NONE`)."""
    from sklearn.linear_model import LogisticRegression

    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(list(y))
    present = sorted(set(y) - {NONE})
    if NONE not in set(y) or not present:
        raise InputError(f"verifier: needs targets and negatives to learn from (labels seen: {sorted(set(y))})")
    mean, scale = X.mean(axis=0), X.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    lr = LogisticRegression(C=C, max_iter=5000)
    lr.fit((X - mean) / scale, y)
    classes = [c for c in targets] + [NONE]
    coef = np.zeros((len(classes), X.shape[1]))
    icpt = np.full(len(classes), -50.0)  # a target never seen in training is never called
    fitted = list(lr.classes_)
    if len(fitted) == 2:  # binary: sklearn keeps one row, for fitted[1]
        coef[classes.index(fitted[1])] = lr.coef_[0]
        icpt[classes.index(fitted[1])] = lr.intercept_[0]
        icpt[classes.index(fitted[0])] = 0.0
    else:
        for k, c in enumerate(fitted):
            coef[classes.index(c)] = lr.coef_[k]
            icpt[classes.index(c)] = lr.intercept_[k]
    return Verifier(tuple(classes), mean, scale, coef, icpt)


#: The prefilter keeps all but this share of the training positives.
PREFILTER_LOSS = 0.005


def train_prefilter(Xs: NDArray, y: Sequence[str]) -> tuple[Verifier, float]:
    """The cascade's first stage on the size features and its threshold: the score that
    keeps all but :data:`PREFILTER_LOSS` of the training positives."""
    lab = ["target" if v != NONE else NONE for v in y]
    pf = train_verifier(Xs, lab, ["target"], C=1.0)
    p = pf.proba(np.asarray(Xs, dtype=np.float64))[:, 0]
    pos = p[np.asarray(lab) == "target"]
    return pf, float(np.quantile(pos, PREFILTER_LOSS)) if len(pos) else 0.0


def object_gate(scene: SceneChannels, lab: int) -> bool:
    """Whether an object is big enough to be looked at (:data:`MIN_OBJECT_PX` ...)."""
    L, _, H = scene.object_dims_mm[lab]
    return bool(scene.object_npx[lab] >= MIN_OBJECT_PX and H >= MIN_OBJECT_HEIGHT_MM and L >= MIN_OBJECT_LENGTH_MM
                and np.isfinite(scene.object_xyz_mm[lab]).all())


def _pce_per_class(bank: FilterBank, scene: SceneChannels, r: float, c: float, z: float) -> NDArray[np.float64]:
    """Each class's best PCE for a chip cut at that class's scale about (r, c)."""
    ppm = bank_scale(bank)
    f = float(scene.K[0, 0])
    S = int(bank.size)
    out = np.full(len(bank.classes), 1e-4)
    for ci, cls in enumerate(bank.classes):
        s = ppm[cls] * z / f
        if S / s > 4 * max(scene.range_mm.shape):
            continue
        x = chip_channel(bank, scene, r, c, s, f)
        ks = np.flatnonzero(bank.filter_class == ci)
        m = spectrum_metrics(np.fft.fft2(x, axes=(-2, -1)), bank.freqs[ks])[bank.metric][0]
        out[ci] = max(float(np.max(m)), 1e-4)
    return out


def size_features(banks: Sequence[FilterBank], targets: Sequence[str], scene: SceneChannels, lab: int
                  ) -> NDArray[np.float64]:
    """The cheap part of an object's features: its size and area against each target
    class's, its range (module docstring)."""
    z = float(scene.object_xyz_mm[lab][2])
    feats: list[float] = []
    L, W, H = (max(float(v), 100.0) for v in scene.object_dims_mm[lab])
    ext = class_size(banks[0].metadata, "class_extent_mm", list(targets))
    f = float(scene.K[0, 0])
    for t in targets:
        e = ext[t]
        cl, cw, ch = max(e[0], e[1]), min(e[0], e[1]), e[2]
        expected_px = cl * ch * (f / z) ** 2 * 0.6
        feats += [abs(math.log(L / cl)), abs(math.log(H / ch)), math.log(W / cw),
                  math.log(max(float(scene.object_npx[lab]), 1.0) / expected_px)]
    feats += [math.log(L), math.log(W), math.log(H), math.log(z), math.log(max(float(scene.object_npx[lab]), 1.0))]
    return np.asarray(feats, dtype=np.float64)


def n_size_features(n_targets: int) -> int:
    """How many :func:`size_features` an object has (4 per target class, 5 shared)."""
    return 4 * n_targets + 5


def filter_features(banks: Sequence[FilterBank], targets: Sequence[str], scene: SceneChannels, lab: int
                    ) -> NDArray[np.float64]:
    """The filters' part: each class's best log PCE in each bank and the best target
    class's margin over the best refused class."""
    r, c = scene.object_rc[lab]
    z = float(scene.object_xyz_mm[lab][2])
    feats: list[float] = []
    tgt = [banks[0].classes.index(t) for t in targets]
    rej = [i for i in range(len(banks[0].classes)) if i not in tgt]
    for b in banks:
        lp = np.log(_pce_per_class(b, scene, r, c, z))
        feats += list(lp)
        feats.append(float(lp[tgt].max() - (lp[rej].max() if rej else lp[tgt].min())))
    return np.asarray(feats, dtype=np.float64)


def object_features(banks: Sequence[FilterBank], targets: Sequence[str], scene: SceneChannels, lab: int
                    ) -> NDArray[np.float64]:
    """The verifier's features of object ``lab``: :func:`size_features` then
    :func:`filter_features` (module docstring)."""
    return np.concatenate([size_features(banks, targets, scene, lab), filter_features(banks, targets, scene, lab)])


@dataclass(eq=False)
class SceneRecogniser:
    """Banks over the same classes (targets and refused classes), the ``targets`` they
    report and the :class:`Verifier` (module docstring)."""

    banks: tuple[FilterBank, ...]
    targets: tuple[str, ...]
    verifier: Verifier
    metadata: dict = field(default_factory=dict)
    prefilter: Verifier | None = None
    """A cascade's first stage on :func:`size_features` only (``target`` or ``none``): the
    filters are correlated only with objects it gives at least ``prefilter_threshold``."""
    prefilter_threshold: float = 0.0

    def __post_init__(self) -> None:
        if not self.banks:
            raise InputError("recogniser: no filter banks")
        for b in self.banks[1:]:
            if list(b.classes) != list(self.banks[0].classes):
                raise InputError("recogniser: its banks must share their classes")
        missing = [t for t in self.targets if t not in self.banks[0].classes]
        if missing:
            raise InputError(f"recogniser: targets {missing} have no filters")

    @property
    def classes(self) -> list[str]:
        return list(self.targets)

    @property
    def channels(self) -> list[str]:
        return [b.channel for b in self.banks]

    def save(self, path: str | Path) -> Path:
        """Write as ``.npz`` (no pickle; JSON metadata) atomically."""
        p = Path(path)
        if p.suffix.lower() != ".npz":
            raise InputError(f"{p}: expected a .npz file name for the recogniser")
        meta = {"schema_version": RECOGNISER_SCHEMA_VERSION, "kind": "scene_recogniser", "targets": list(self.targets),
                "verifier_classes": list(self.verifier.classes), "metadata": self.metadata,
                "prefilter_threshold": self.prefilter_threshold,
                "prefilter_classes": None if self.prefilter is None else list(self.prefilter.classes),
                "banks": [{"classes": list(b.classes), "channel": b.channel, "size": int(b.size),
                           "bin_deg": float(b.bin_deg), "metric": b.metric, "metadata": b.metadata}
                          for b in self.banks]}
        arrays = {"verifier_mean": self.verifier.mean, "verifier_scale": self.verifier.scale,
                  "verifier_coef": self.verifier.coef, "verifier_intercept": self.verifier.intercept}
        if self.prefilter is not None:
            arrays.update({f"prefilter_{k}": getattr(self.prefilter, k) for k in ("mean", "scale", "coef", "intercept")})
        for i, b in enumerate(self.banks):
            arrays.update({f"b{i}_freqs": b.freqs.astype(np.complex128), f"b{i}_filter_class": b.filter_class,
                           f"b{i}_filter_az_deg": b.filter_az_deg, f"b{i}_params": b.params})
        return write_model_npz(p, meta, arrays)

    @classmethod
    def load(cls, path: str | Path) -> SceneRecogniser:
        """Read a recogniser written by :meth:`save`; another kind or version is refused."""
        p = Path(path)
        meta, arr = read_model_npz(p, "recogniser")
        if not isinstance(meta, dict) or meta.get("kind") != "scene_recogniser":
            raise InputError(f"{p}: not a scene recogniser")
        if meta.get("schema_version") != RECOGNISER_SCHEMA_VERSION:
            raise InputError(f"{p}: recogniser schema {meta.get('schema_version')}, this prism3d reads "
                             f"{RECOGNISER_SCHEMA_VERSION}; train it again")
        try:
            banks = tuple(FilterBank(list(bm["classes"]), bm["channel"], int(bm["size"]), float(bm["bin_deg"]),
                                     arr[f"b{i}_freqs"], arr[f"b{i}_filter_class"], arr[f"b{i}_filter_az_deg"],
                                     arr[f"b{i}_params"], dict(bm["metadata"]), str(bm["metric"]))
                          for i, bm in enumerate(meta["banks"]))
            v = Verifier(tuple(meta["verifier_classes"]), arr["verifier_mean"], arr["verifier_scale"],
                         arr["verifier_coef"], arr["verifier_intercept"])
            pf = None
            if meta.get("prefilter_classes"):
                pf = Verifier(tuple(meta["prefilter_classes"]), arr["prefilter_mean"], arr["prefilter_scale"],
                              arr["prefilter_coef"], arr["prefilter_intercept"])
            return cls(banks, tuple(meta["targets"]), v, dict(meta.get("metadata", {})), pf,
                       float(meta.get("prefilter_threshold", 0.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{p}: not a valid recogniser (bad or missing {exc})") from None


def detect_objects(model: SceneRecogniser, scene: SceneChannels, options: DetectOptions | None = None
                   ) -> list[SceneDetection]:
    """Detections of a recogniser in a prepared scene, best first: every object passing
    :func:`object_gate` scored by the verifier (``score`` = 1 - P(none), ``class_name`` = the
    likeliest target class, ``p_classes``), placed at its median 3D point; an object within
    a better detection's class radius is a piece of it and dropped."""
    o = DetectOptions() if options is None else options
    labs = [lab for lab in range(1, len(scene.object_dims_mm)) if object_gate(scene, lab)]
    if not labs:
        return []
    Xs = np.array([size_features(model.banks, model.targets, scene, lab) for lab in labs])
    if model.prefilter is not None:
        keep = model.prefilter.proba(Xs)[:, 0] >= model.prefilter_threshold
        labs, Xs = [lab for lab, k in zip(labs, keep) if k], Xs[keep]
        if not labs:
            return []
    X = np.hstack([Xs, np.array([filter_features(model.banks, model.targets, scene, lab) for lab in labs])])
    P = model.verifier.proba(X)
    k_none = model.verifier.classes.index(NONE)
    radius = class_size(model.banks[0].metadata, "class_radius_mm", list(model.targets))
    order = np.argsort(-(1.0 - P[:, k_none]))
    out: list[SceneDetection] = []
    kept: list[tuple[NDArray, float]] = []
    for i in order:
        lab = labs[int(i)]
        pt = np.asarray(scene.object_xyz_mm[lab], dtype=np.float64)
        pv = P[i].copy()
        pv[k_none] = -1.0
        cls = model.verifier.classes[int(np.argmax(pv))]
        rad = float(np.max(radius[cls])) if cls in radius else 0.0
        if any(np.linalg.norm(pt - q) < min(rad, rq) for q, rq in kept):
            continue
        kept.append((pt, rad))
        r, c = project(scene.K, pt)
        out.append(SceneDetection(float(r), float(c), cls, float(1.0 - P[i, k_none]), float("nan"), float(pt[2]),
                                  (float(pt[0]), float(pt[1]), float(pt[2])),
                                  {c2: round(float(p), 4) for c2, p in zip(model.verifier.classes, P[i])}))
        if len(out) >= o.max_detections:
            break
    return out
