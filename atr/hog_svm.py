"""HOG + linear SVM baseline: the detector/classifier the filter banks are compared with.

A :class:`HogSvm` holds one linear one-vs-rest SVM per class on the histogram-of-
oriented-gradients vector (Dalal and Triggs [1]_) of an ``S x S`` window. It trains on
exactly the chips a :class:`~prism3d.atr.bank.FilterBank` trains on
(:func:`~prism3d.atr.bank.render_class_chips`, same poses, paint and noise) and with no
augmentation, so that a comparison of the two measures the classifiers, not the data.
Windows are scored in "channel units" (:func:`chip_units`): the depth relief of
:func:`~prism3d.atr.bank.depth_relief`, raw grey intensity or shape, background 0.

Negatives of class ``c`` are the other classes' chips plus generated background
windows (seeded): the chips shifted by a third to three quarters of a chip (a window
grazing a target must score low, since a scene detector slides over every position),
blank windows and smooth random textures (low-pass noise; clutter for intensity).

:meth:`HogSvm.dense_scores` scores every cell-aligned window of a scene from one HOG
of the whole scene: a window's blocks are a sub-grid of the scene's block grid, so its
decision value is the correlation of each class's weight tensor with that grid.

References
----------
.. [1] Dalal, Triggs, "Histograms of oriented gradients for human detection", CVPR 2005.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.bank import (
    BANK_CHIP_SPEC,
    check_targets,
    class_scale_facts,
    depth_relief,
    render_class_chips,
)
from prism3d.atr.chips import ChipSpec, as_chip_spec
from prism3d.atr.poses import parse_range
from prism3d.capture.mesh import SceneMesh
from prism3d.checks import check_array, check_choice, check_file, check_positive, check_seed
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path
from prism3d.io.images import check_npy_header

__all__ = ["HOG_CHANNELS", "HOG_SVM_SCHEMA_VERSION", "HogParams", "HogSvm", "chip_units"]

HOG_SVM_SCHEMA_VERSION = 1
#: Channels a HOG + SVM model scores (the mask has no texture worth a gradient histogram).
HOG_CHANNELS = ("intensity", "depth", "shape")
#: SVM regularisation. The training set is small (tens of chips per class) against a
#: 1764-value feature and separable, so C sets the margin. On azimuths between the training
#: ones (4 built-in targets, 30 deg grid) C = 1 fits each view (depth 0.96 correct, 88 % of
#: chips above 0 for their class, against 1.00 and 96 % at 0.1) and C = 0.01 under-fits
#: intensity (0.92 against 0.94; 0.965 against 0.993 on the 10 deg grid).
DEFAULT_C = 0.1
#: Generated background windows per training chip: shifted chips, textures; blank windows
#: are all alike (one HOG vector, all zeros), so a tenth of a chip each suffices.
_SHIFTED_PER_CHIP, _TEXTURE_PER_CHIP, _BLANK_PER_CHIP = 1.0, 1.0, 0.1
#: Shift of the grazing negatives, in chip sides.
_SHIFT_MIN, _SHIFT_MAX = 1.0 / 3.0, 0.75
#: Gaussian width (px) range of the texture negatives' low-pass filter.
_TEXTURE_SIGMA_PX = (1.5, 8.0)
_MAX_ITER = 20000
_NOT_FINITE = "expected finite values (channel units, see chip_units), found NaN or inf"


def chip_units(
    images: NDArray, channel: str, fx: NDArray | float | None = None
) -> NDArray[np.float64]:
    """Chips ``(N, S, S)`` as rendered -> the units a :class:`HogSvm` scores.

    ``depth`` (mm, NaN = no surface) becomes :func:`~prism3d.atr.bank.depth_relief` in
    [0, 1] and needs ``fx`` (chip focal length, px, one or one per chip); ``intensity``
    and ``shape`` stay in [0, 1] with NaN set to 0 (background).
    """
    check_choice(channel, "channel", HOG_CHANNELS)
    x = check_array(images, "images", ndim=3, dtype_kind="fiub").astype(np.float64)
    if channel == "depth":
        if fx is None:
            raise InputError("chip_units: depth chips need fx (the chip focal length, px)")
        return depth_relief(x, fx)
    return np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


@dataclass(frozen=True)
class HogParams:
    """HOG settings of a window, as :func:`skimage.feature.hog` takes them; the defaults
    suit 64-px chips: 8 x 8 cells (7 x 7 blocks, 1764 values)."""

    orientations: int = 9
    """Gradient orientation bins."""
    pixels_per_cell: tuple[int, int] = (8, 8)
    """Cell side, px (square cells)."""
    cells_per_block: tuple[int, int] = (2, 2)
    """Cells per normalisation block (rows, columns)."""
    block_norm: str = "L2-Hys"
    """Block normalisation: L1, L1-sqrt, L2 or L2-Hys."""

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "orientations", int(self.orientations))
            object.__setattr__(self, "pixels_per_cell", tuple(int(v) for v in self.pixels_per_cell))
            object.__setattr__(self, "cells_per_block", tuple(int(v) for v in self.cells_per_block))
        except (TypeError, ValueError) as exc:
            raise InputError(f"hog: malformed settings {self!r} ({exc})") from None
        check_choice(self.block_norm, "hog block_norm", ("L1", "L1-sqrt", "L2", "L2-Hys"))
        ppc, cpb = self.pixels_per_cell, self.cells_per_block
        if len(ppc) != 2 or ppc[0] != ppc[1] or ppc[0] < 1:
            raise InputError(f"hog pixels_per_cell: expected square cells [p, p] with p >= 1, got {list(ppc)}")
        if len(cpb) != 2 or min(cpb) < 1:
            raise InputError(f"hog cells_per_block: expected [r, c] with r, c >= 1, got {list(cpb)}")
        if self.orientations < 1:
            raise InputError(f"hog orientations: expected >= 1, got {self.orientations}")

    @classmethod
    def from_json(cls, doc: object) -> HogParams:
        """The settings a model file holds (:meth:`to_json`); InputError when malformed."""
        if not isinstance(doc, dict):
            raise InputError(f"hog: expected a dict of HOG settings, got {type(doc).__name__}")
        known = {f.name for f in fields(cls)}
        extra = set(doc) - known
        if extra:
            raise InputError(f"hog: unknown settings {sorted(extra)}; expected {sorted(known)}")
        return cls(**doc)

    def to_json(self) -> dict[str, int | str | list[int]]:
        """The settings as JSON (tuples as lists)."""
        return {"orientations": self.orientations, "pixels_per_cell": list(self.pixels_per_cell),
                "cells_per_block": list(self.cells_per_block), "block_norm": self.block_norm}


def _block_grid(size: int, hog: HogParams) -> tuple[int, int, int]:
    """Blocks per window side (rows, cols) and values per block for an ``S x S`` window."""
    p = hog.pixels_per_cell[0]
    br, bc = hog.cells_per_block
    nr, nc = size // p - br + 1, size // p - bc + 1
    return nr, nc, br * bc * hog.orientations


def _hog(image: NDArray[np.float64], hog: HogParams, *, vector: bool) -> NDArray[np.float64]:
    from skimage.feature import hog as sk_hog

    return sk_hog(
        image,
        orientations=hog.orientations,
        pixels_per_cell=hog.pixels_per_cell,
        cells_per_block=hog.cells_per_block,
        block_norm=hog.block_norm,
        feature_vector=vector,
        channel_axis=None,
    )


@dataclass(eq=False)
class HogSvm:
    """One linear SVM per class on the HOG vector of an ``S x S`` window.

    ``weights`` ``(C, D)`` and ``bias`` ``(C,)``: class ``c``'s decision value of HOG
    vector ``h`` is ``weights[c] @ h + bias[c]`` (> 0: class ``c``, < 0: not ``c``);
    ``hog``: HOG settings (``orientations``, ``pixels_per_cell``, ``cells_per_block``,
    ``block_norm``); ``metadata``: training settings (JSON).
    """

    classes: list[str]
    channel: str
    size: int
    weights: NDArray[np.float64]
    bias: NDArray[np.float64]
    hog: HogParams = HogParams()
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_choice(self.channel, "channel", HOG_CHANNELS)
        self.classes = [str(c) for c in self.classes]
        if len(self.classes) < 2 or len(set(self.classes)) != len(self.classes):
            raise InputError(f"classes: expected at least 2 distinct classes, got {self.classes}")
        if not isinstance(self.hog, HogParams):
            raise InputError(f"hog: expected HogParams, got {type(self.hog).__name__}")
        self.size = int(self.size)
        nr, nc, per = _block_grid(self.size, self.hog)
        if nr < 1 or nc < 1:
            raise InputError(
                f"size: a {self.size}-px window holds no HOG block of "
                f"{list(self.hog.cells_per_block)} "
                f"cells of {self.hog.pixels_per_cell[0]} px"
            )
        n = len(self.classes)
        w = check_array(self.weights, "weights", shape=(n, nr * nc * per), dtype_kind="fiu")
        self.weights = w.astype(np.float64)
        self.bias = check_array(self.bias, "bias", shape=(n,), dtype_kind="fiu").astype(np.float64)
        if not (np.all(np.isfinite(self.weights)) and np.all(np.isfinite(self.bias))):
            raise InputError("HogSvm: weights or bias hold NaN or infinite values")

    # -- training -------------------------------------------------------------------
    @classmethod
    def train(
        cls,
        targets: Sequence[tuple[str, SceneMesh]],
        *,
        channel: str = "depth",
        azimuth: str | Sequence[float] = "0:360:10",
        elevation: str | Sequence[float] = "20",
        range_mm: str | float | Sequence[float] | None = None,
        chip_spec: ChipSpec | None = None,
        seed: int = 0,
        C: float = DEFAULT_C,
        hog: HogParams | None = None,
    ) -> HogSvm:
        """Train on ``[(class_name, SceneMesh), ...]`` (>= 2 classes) at the bank's chips.

        ``channel``, ``azimuth``, ``elevation``, ``range_mm`` and ``chip_spec`` (None =
        :data:`~prism3d.atr.bank.BANK_CHIP_SPEC`) are as in
        :func:`~prism3d.atr.bank.train_bank`; ``seed`` draws the background negatives
        and seeds the SVM solver; ``C``: SVM regularisation (:data:`DEFAULT_C`);
        ``hog``: HOG settings (None: :class:`HogParams`' defaults).
        """
        t0 = time.perf_counter()
        check_choice(channel, "channel", HOG_CHANNELS)
        seed = check_seed(seed)
        C = check_positive(C, "C")
        hog = HogParams() if hog is None else hog
        spec = as_chip_spec(chip_spec, BANK_CHIP_SPEC)
        items = check_targets(targets)
        S = int(spec.size)
        classes = _training_classes(items, S, hog)
        az_train = parse_range(azimuth)
        X, labels, _, _, rng_mm, fx = render_class_chips(
            items, channel=channel, azimuth=az_train, elevation=elevation, range_mm=range_mm,
            chip_spec=spec,
        )
        pos = chip_units(X, channel, fx)
        neg, n_kind = _background_windows(pos, np.random.default_rng(seed))
        feats = _features(np.concatenate([pos, neg]), hog)
        lab = np.concatenate([[classes.index(c) for c in labels], np.full(len(neg), -1)])
        weights, bias = _fit_one_vs_rest(feats, lab, len(classes), C=C, seed=seed)
        meta = {
            "channel": channel,
            "azimuth": [float(a) for a in az_train],
            "elevation": [float(e) for e in parse_range(elevation)],
            "range_mm": None if range_mm is None else [float(r) for r in parse_range(range_mm)],
            "targets": [[c, m.name] for c, m in items],
            **_chip_facts(spec),
            "seed": seed,
            "C": C,
            "hog": hog.to_json(),
            "augmentation": None,
            **_fit_facts(feats @ weights.T + bias, lab, len(pos), n_kind, classes),
            "train_seconds": round(time.perf_counter() - t0, 3),
            **class_scale_facts(items, labels, fx, rng_mm),
        }
        return cls(classes, channel, S, weights, bias, hog, meta)

    # -- scoring --------------------------------------------------------------------
    def score_windows(self, windows: NDArray) -> NDArray[np.float64]:
        """Decision values ``(N, C)`` of windows ``(N, S, S)`` in channel units."""
        x = self._check_windows(windows)
        if len(x) == 0:
            return np.zeros((0, len(self.classes)))
        return _features(x, self.hog) @ self.weights.T + self.bias

    def predict(self, windows: NDArray) -> list[str]:
        """The best-scoring class of each window ``(N, S, S)`` (channel units)."""
        return [self.classes[i] for i in np.argmax(self.score_windows(windows), axis=1)]

    def dense_scores(self, image: NDArray) -> tuple[NDArray[np.float64], int, int, int]:
        """Decision values of every cell-aligned ``S x S`` window of an image.

        ``image`` ``(h, w)`` in channel units, the target at chip scale. Returns
        ``(scores (C, h', w'), row0, col0, stride)``: ``scores[c, i, j]`` is class ``c``'s
        value for the window centred at ``(row0 + i*stride, col0 + j*stride)`` (top-left
        ``(i*stride, j*stride)``; ``stride`` = HOG cell side). One HOG of the whole image;
        a window's value equals :meth:`score_windows` of the cut-out window when the
        image's gradient across the window's edge is 0 on its outermost pixel ring (HOG
        gives a cut-out window 0 gradient there), e.g. blank background around a chip;
        otherwise it differs a little (smooth random texture: by up to 0.09 against a
        score spread of 0.45). An image smaller than ``S`` gives a ``(C, 0, 0)`` array.
        """
        g = check_array(image, "image", ndim=2, dtype_kind="fiub").astype(np.float64)
        if not np.all(np.isfinite(g)):
            raise InputError(f"image: {_NOT_FINITE}")
        S, n_cls = self.size, len(self.classes)
        p = self.hog.pixels_per_cell[0]
        h, w = g.shape
        if h < S or w < S:
            return np.zeros((n_cls, 0, 0)), S // 2, S // 2, p
        nr, nc, per = _block_grid(S, self.hog)
        grid = _hog(g, self.hog, vector=False)
        grid = grid.reshape(grid.shape[0], grid.shape[1], per)
        n_i = min((h - S) // p + 1, grid.shape[0] - nr + 1)
        n_j = min((w - S) // p + 1, grid.shape[1] - nc + 1)
        wt = self.weights.reshape(n_cls, nr, nc, per)
        out = np.zeros((n_i, n_j, n_cls))
        for a in range(nr):  # one matrix product per block offset, over all windows at once
            for b in range(nc):
                out += grid[a : a + n_i, b : b + n_j] @ wt[:, a, b].T
        out += self.bias
        return np.ascontiguousarray(out.transpose(2, 0, 1)), S // 2, S // 2, p

    def _check_windows(self, windows: NDArray) -> NDArray[np.float64]:
        x = check_array(windows, "windows", ndim=3, dtype_kind="fiub")
        if x.shape[1:] != (self.size, self.size):
            raise InputError(
                f"windows: expected (N, {self.size}, {self.size}) windows, got {x.shape}"
            )
        x = x.astype(np.float64)
        if not np.all(np.isfinite(x)):
            raise InputError(f"windows: {_NOT_FINITE}")
        return x

    # -- persistence ----------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the model as ``.npz`` (no pickle, JSON metadata) atomically; returns the path."""
        p = Path(path)
        if p.suffix.lower() != ".npz":
            raise InputError(f"{p}: expected a .npz file name")
        if p.is_dir():
            raise InputError(f"{p}: is a directory; give an output file name")
        meta = {
            "schema_version": HOG_SVM_SCHEMA_VERSION,
            "kind": "hog_svm",
            "classes": list(self.classes),
            "channel": self.channel,
            "size": int(self.size),
            "hog": self.hog.to_json(),
            "metadata": self.metadata,
        }
        try:
            blob = json.dumps(meta, allow_nan=True).encode("utf-8")
        except (TypeError, ValueError) as exc:
            raise InputError(f"{p}: metadata is not JSON-serialisable ({exc})") from None
        with atomic_path(p) as tmp, open(tmp, "wb") as fh:
            np.savez(
                fh,
                meta_json=np.frombuffer(blob, dtype=np.uint8),
                weights=self.weights.astype(np.float64),
                bias=self.bias.astype(np.float64),
            )
        return p

    @classmethod
    def load(cls, path: str | Path) -> HogSvm:
        """Read a model written by :meth:`save`; InputError for anything else."""
        p = check_file(path, "HOG + SVM model")
        try:  # our own handle: np.load leaves a file it fails to parse open
            with open(p, "rb") as fh, np.load(fh, allow_pickle=False) as z:
                meta = json.loads(bytes(z["meta_json"].astype(np.uint8)).decode("utf-8"))
                for k in ("weights", "bias"):
                    with z.zip.open(f"{k}.npy") as member:
                        check_npy_header(member, f"{p}:{k}")
                arrays = {k: z[k] for k in ("weights", "bias")}
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - zip/numpy/json raise many types on a corrupt file
            why = exc or type(exc).__name__
            raise InputError(f"{p}: not a prism3d HOG + SVM model ({why})") from None
        if not isinstance(meta, dict) or meta.get("kind") != "hog_svm":
            raise InputError(f"{p}: not a prism3d HOG + SVM model (no hog_svm header)")
        ver = meta.get("schema_version")
        if ver != HOG_SVM_SCHEMA_VERSION:
            raise InputError(
                f"{p}: unknown HOG + SVM schema_version {ver!r} "
                f"(this prism3d reads {HOG_SVM_SCHEMA_VERSION})"
            )
        try:
            return cls(
                list(meta["classes"]),
                meta["channel"],
                int(meta["size"]),
                arrays["weights"],
                arrays["bias"],
                HogParams.from_json(meta["hog"]),
                dict(meta.get("metadata", {})),
            )
        except InputError as exc:
            raise InputError(f"{p}: not a valid HOG + SVM model ({exc})") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{p}: not a valid HOG + SVM model (bad or missing {exc})") from None


def _features(windows: NDArray[np.float64], hog: HogParams) -> NDArray[np.float64]:
    """HOG vectors ``(N, D)`` of windows ``(N, S, S)``."""
    return np.stack([_hog(w, hog, vector=True) for w in windows]).astype(np.float64)


def _training_classes(items: list[tuple[str, SceneMesh]], S: int, hog: HogParams) -> list[str]:
    """The classes of ``items`` in first-seen order; InputError unless there are at least 2
    and an ``S``-px chip holds one HOG block."""
    classes = list(dict.fromkeys(c for c, _ in items))
    if len(classes) < 2:
        raise InputError(f"targets: a HOG + SVM model needs at least 2 classes, got {classes}")
    if min(_block_grid(S, hog)[:2]) < 1:
        raise InputError(f"chip_spec.size: {S} px is too small for one HOG block ({hog})")
    return classes


def _chip_facts(spec: ChipSpec) -> dict:
    """The training chips' settings, for the model's metadata."""
    return {
        "chip_size": int(spec.size),
        "framing": spec.framing,
        "camouflage": bool(spec.camouflage),
        "noise_sigma": float(spec.noise_sigma),
        "depth_noise_mm": float(spec.depth_noise_mm),
        "chip_seed": int(spec.seed),
    }


def _fit_facts(
    dec: NDArray[np.float64], lab: NDArray, npos: int, n_kind: dict[str, int], classes: list[str]
) -> dict:
    """Training-set counts, accuracy and background rejection for the model's metadata, from
    the decision values ``dec`` ``(N, C)`` of the positives (first ``npos``) and negatives."""
    train_acc = float(np.mean(np.argmax(dec[:npos], axis=1) == lab[:npos]))
    neg = dec[npos:]
    rejection = float(np.mean(np.max(neg, axis=1) < 0.0)) if len(neg) else float("nan")
    counts = {c: int(np.sum(lab == i)) for i, c in enumerate(classes)}
    return {
        "n_positives": counts,
        "n_negatives": {c: int(len(lab) - n) for c, n in counts.items()},
        "n_background": n_kind,
        "training_accuracy": train_acc,
        "training_background_rejection": rejection,
    }


def _background_windows(
    pos: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], dict[str, int]]:
    """Generic negatives from the chips ``(N, S, S)``: shifted chips, blanks, textures."""
    from scipy.ndimage import gaussian_filter

    n, S, _ = pos.shape
    n_shift = int(round(_SHIFTED_PER_CHIP * n))
    n_tex = int(round(_TEXTURE_PER_CHIP * n))
    n_blank = max(1, int(round(_BLANK_PER_CHIP * n)))
    shifted = np.zeros((n_shift, S, S))
    src = rng.permutation(np.resize(np.arange(n), n_shift))
    mag = rng.uniform(_SHIFT_MIN * S, _SHIFT_MAX * S, n_shift)
    ang = rng.uniform(0.0, 2.0 * np.pi, n_shift)
    for k in range(n_shift):
        dr, dc = int(round(mag[k] * np.sin(ang[k]))), int(round(mag[k] * np.cos(ang[k])))
        shifted[k] = _shift_zero(pos[src[k]], dr, dc)
    tex = np.empty((n_tex, S, S))
    sig = rng.uniform(*_TEXTURE_SIGMA_PX, n_tex)
    for k in range(n_tex):
        t = gaussian_filter(rng.standard_normal((S, S)), sig[k], mode="wrap")
        lo, hi = t.min(), t.max()
        tex[k] = (t - lo) / max(hi - lo, 1e-12)
    neg = np.concatenate([shifted, np.zeros((n_blank, S, S)), tex])
    return neg, {"shifted": n_shift, "blank": n_blank, "texture": n_tex}


def _shift_zero(img: NDArray[np.float64], dr: int, dc: int) -> NDArray[np.float64]:
    """``img`` moved by ``(dr, dc)`` px, uncovered pixels 0 (background)."""
    out = np.zeros_like(img)
    h, w = img.shape
    if abs(dr) >= h or abs(dc) >= w:
        return out
    out[max(dr, 0) : h + min(dr, 0), max(dc, 0) : w + min(dc, 0)] = img[
        max(-dr, 0) : h + min(-dr, 0), max(-dc, 0) : w + min(-dc, 0)
    ]
    return out


def _fit_one_vs_rest(
    feats: NDArray[np.float64], lab: NDArray, n_classes: int, *, C: float, seed: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One balanced linear SVM per class (label ``-1``: background, negative for all)."""
    from sklearn.svm import LinearSVC

    weights = np.empty((n_classes, feats.shape[1]))
    bias = np.empty(n_classes)
    for ci in range(n_classes):
        svm = LinearSVC(
            C=C, class_weight="balanced", dual="auto", random_state=seed, max_iter=_MAX_ITER
        )
        svm.fit(feats, (lab == ci).astype(np.int64))
        weights[ci] = svm.coef_[0]
        bias[ci] = svm.intercept_[0]
    return weights, bias
