"""Correlation filter banks: one OT-MACH filter per target class and azimuth bin.

:func:`train_bank` renders each class at the training poses, bins the chips by azimuth
and trains one filter per (class, bin), with ``(alpha, beta, gamma)`` chosen on
held-out views; :class:`FilterBank` classifies chips by the best peak metric and
detects targets in scenes; banks are saved as ``.npz`` without pickle. Parameter
search and chip preprocessing: docs/atr.md "Filter banks".

References
----------
.. [1] Johnson, Edens, Lu, Chao, "Optimization of OT-MACH filter generation for
   target recognition", Proc. SPIE 7340 (2009).
.. [2] Kumar, Mahalanobis, Juday, *Correlation Pattern Recognition*, CUP (2005).
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.chips import (
    ChipSet,
    ChipSpec,
    as_chip_spec,
    bounding_sphere,
    render_chips,
    spec_poses,
)
from prism3d.atr.filters import PSR_EXCLUDE, PSR_WINDOW, otmach_from_moments, peak_metrics
from prism3d.atr.poses import parse_range
from prism3d.capture.mesh import SceneMesh
from prism3d.checks import check_array, check_choice, check_file
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path
from prism3d.io.images import check_npy_header

__all__ = [
    "BANK_CHIP_SPEC",
    "BANK_SCHEMA_VERSION",
    "BankOptions",
    "DEFAULT_PARAM_GRID",
    "Detection",
    "FilterBank",
    "INTENSITY_PREP",
    "INTENSITY_PREPS",
    "check_bank_command",
    "check_targets",
    "class_scale_facts",
    "depth_relief",
    "prepare_chips",
    "render_class_chips",
    "train_bank",
    "spectrum_metrics",
]

log = logging.getLogger(__name__)

BANK_SCHEMA_VERSION = 1
FILTER_CHANNELS = ("intensity", "depth", "shape", "mask")
#: (alpha, beta, gamma) candidates of the automatic OT-MACH search (ratios matter only).
DEFAULT_PARAM_GRID: tuple[tuple[float, float, float], ...] = (
    (1.0, 1.0, 1.0),
    (1.0, 0.1, 1.0),
    (0.1, 1.0, 1.0),
    (1.0, 1.0, 0.1),
    (0.0, 0.1, 1.0),
    (0.0, 1.0, 0.0),
)
#: Peak metrics a bank can score with.
METRICS = ("pce", "psr", "peak")
#: Default training chips: 64 px resolve the targets' aspects and keep a bank small.
BANK_CHIP_SPEC = ChipSpec(size=64)
#: How intensity chips enter the filters. A bank trained on targets over a black
#: background and shown the same target over a brighter one sees its silhouette's contrast
#: flip sign (target-vs-clutter ROC AUC 0.48 with noise clutter, 0.00-0.05 across
#: backgrounds): ``"gradient"`` correlates the gradient magnitude, the same either way
#: (docs/atr.md "Intensity"). ``"raw"``: banks saved before it (no ``intensity_prep``).
INTENSITY_PREPS = ("gradient", "raw")
INTENSITY_PREP = "gradient"
#: Gaussian scale of the gradient (px at the chip size).
GRADIENT_SIGMA_PX = 1.0
#: Seed stride between classes (a prime): no two classes share lighting/noise draws.
_CLASS_SEED_STRIDE = 1009
#: Seed offset of the held-out views: their noise differs from the training chips'.
_HELDOUT_SEED_OFFSET = 7


def check_targets(targets: Sequence[tuple[str, SceneMesh]]) -> list[tuple[str, SceneMesh]]:
    """Validate a ``[(class_name, SceneMesh), ...]`` list (non-empty, >= 2 classes for a bank)."""
    try:
        items = [(str(c), m) for c, m in targets]
    except (TypeError, ValueError):
        raise InputError("targets: expected a list of (class_name, SceneMesh) pairs") from None
    if not items:
        raise InputError("targets: empty list; expected (class_name, SceneMesh) pairs")
    for c, m in items:
        if not isinstance(m, SceneMesh):
            raise InputError(
                f"targets: item for class {c!r} is a {type(m).__name__}, expected SceneMesh"
            )
        if not c:
            raise InputError("targets: empty class name")
    return items


def check_bank_command(action: str, *, output: str | Path | None, bank: str | Path | None,
                       results: str | Path | None = None) -> None:
    """Check a ``bank train`` (needs ``output``, ``.npz``) or ``bank eval`` (needs
    ``bank``; ``results`` JSON optional) request, outputs included, before any work."""
    check_choice(action, "action", ("train", "eval", "eval-scenes"))
    if action == "train" and output is None:
        raise InputError("bank train: give -o BANK.npz")
    if action != "train" and bank is None:
        raise InputError(f"bank {action}: give the bank file (bank {action} BANK.npz ...)")
    if action != "train" and output is not None:
        raise InputError("bank eval writes no bank: -o is for bank train (results go to --json FILE)")
    if action == "train" and results is not None:
        raise InputError("bank train: --json is for bank eval")
    if action == "train" and bank is not None:
        raise InputError(f"bank train: unexpected argument {bank}; the bank is written to -o")
    for path, suffix in ((output, ".npz"), (results, ".json")):
        if path is None:
            continue
        p = Path(path)
        if p.suffix.lower() != suffix:
            raise InputError(f"{p}: expected a {suffix} file name")
        if p.is_dir():
            raise InputError(f"{p}: is a directory; give an output file name")
        if bank is not None and p.resolve() == Path(bank).resolve():
            raise InputError(f"{p}: is the bank being read; give another output name")


def prepare_chips(
    images: NDArray, channel: str, fx: NDArray | float | None = None, *,
    intensity_prep: str = INTENSITY_PREP,
) -> NDArray[np.float64]:
    """Chips ``(N, S, S)`` -> zero-mean, unit-energy filter inputs (module docstring).

    ``fx`` (focal length per chip, px) is required for ``depth``. ``intensity_prep``:
    ``"gradient"`` (intensity chips become their gradient magnitude: which side of the
    silhouette is brighter no longer matters) or ``"raw"`` (banks saved before it).
    """
    check_choice(channel, "channel", FILTER_CHANNELS)
    check_choice(intensity_prep, "intensity_prep", INTENSITY_PREPS)
    x = check_array(images, "images", ndim=3, dtype_kind="fiub").astype(np.float64)
    n, h, w = x.shape
    if channel == "depth":
        if fx is None:
            raise InputError("prepare_chips: depth chips need fx (the chip focal length, px)")
        x = depth_relief(x, fx)
    else:
        x = np.nan_to_num(x, nan=0.0)
        if channel == "intensity" and intensity_prep == "gradient":
            from scipy.ndimage import gaussian_filter

            s = (0.0, GRADIENT_SIGMA_PX, GRADIENT_SIGMA_PX)  # never across chips
            x = np.hypot(gaussian_filter(x, s, order=(0, 1, 0)), gaussian_filter(x, s, order=(0, 0, 1)))
    x = x - x.mean(axis=(1, 2), keepdims=True)
    e = np.sqrt(np.sum(x**2, axis=(1, 2), keepdims=True))
    return x / np.maximum(e, 1e-12)


def depth_relief(images: NDArray, fx: NDArray | float) -> NDArray[np.float64]:
    """Depth chips ``(N, S, S)`` mm -> relief in [0, 1]: 1 at the near side of the chip's
    depth slab, 0 at its far side and where there is no surface. The slab is centred on
    the median depth of the chip's central quarter and is as deep as the chip is wide at
    that depth (``fx`` px per chip), so relief does not depend on range."""
    x = check_array(images, "images", ndim=3, dtype_kind="fiub").astype(np.float64)
    n, h, w = x.shape
    f = np.broadcast_to(np.asarray(fx, dtype=np.float64), (n,))
    out = np.zeros_like(x)
    q0, q1 = h // 2 - h // 8, h // 2 + h // 8 + 1
    for i in range(n):
        centre = x[i, q0:q1, q0:q1]
        fin = centre[np.isfinite(centre)]
        if fin.size == 0:
            fin = x[i][np.isfinite(x[i])]
        if fin.size == 0:
            continue
        zc = float(np.median(fin))
        half = (w / 2.0) * zc / f[i]
        rel = (zc + half - x[i]) / (2 * half)
        out[i] = np.clip(np.nan_to_num(rel, nan=0.0), 0.0, 1.0)
    return out


@dataclass(eq=False)
class Detection:
    """One detection in a scene: target centre pixel, class, aspect and PSR."""

    row: int
    col: int
    target_class: str
    aspect_deg: float
    psr: float


@dataclass(frozen=True)
class BankOptions:
    """How a bank is trained: chips rendered at every azimuth x elevation, one filter per
    class and aspect bin, with the OT-MACH weights searched or given."""

    azimuth: str = "0:360:10"
    """Training azimuths, degrees (A0:A1:STEP or a list)."""
    elevation: str = "20"
    """Training elevations, degrees (E0:E1:STEP or a list)."""
    bin_deg: float = 10.0
    """Aspect bin width, degrees (360 / bin_deg an integer)."""
    params: str | tuple[float, float, float] = "auto"
    """OT-MACH weights (alpha, beta, gamma), or "auto": searched on held-out views."""

    def changed(self) -> dict[str, str | float]:
        """The fields that differ from the defaults, by name (what a cache key needs)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) != f.default}

    def train_kwargs(self) -> dict[str, str | float | tuple[float, float, float]]:
        """The options as :func:`train_bank` keywords."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(eq=False)
class FilterBank:
    """One correlation filter per (class, azimuth bin).

    ``freqs`` (K, S, S) complex128 filters, ``filter_class`` (K,) index into ``classes``,
    ``filter_az_deg`` (K,) bin centres, ``params`` (K, 3) OT-MACH weights, ``metadata``
    (training settings, JSON), ``metric`` (pce, psr or peak) deciding classification.
    """

    classes: list[str]
    channel: str
    size: int
    bin_deg: float
    freqs: NDArray[np.complex128]
    filter_class: NDArray[np.int64]
    filter_az_deg: NDArray[np.float64]
    params: NDArray[np.float64]
    metadata: dict = field(default_factory=dict)
    metric: str = "pce"

    def __post_init__(self) -> None:
        check_choice(self.channel, "channel", FILTER_CHANNELS)
        check_choice(self.metric, "metric", METRICS)
        check_choice(self.intensity_prep, "intensity_prep", INTENSITY_PREPS)
        k = len(self.freqs)
        if (
            self.freqs.shape != (k, self.size, self.size)
            or len(self.filter_class) != k
            or len(self.filter_az_deg) != k
        ):
            raise InputError("FilterBank: inconsistent filter arrays")

    def __len__(self) -> int:
        return len(self.freqs)

    @property
    def intensity_prep(self) -> str:
        """How this bank's intensity chips were prepared (``INTENSITY_PREPS``); banks saved
        before the choice existed were trained on raw intensity."""
        return str(self.metadata.get("intensity_prep", "raw"))

    # -- responses ----------------------------------------------------------------
    def _inputs(self, chips: ChipSet | NDArray, fx: NDArray | float | None) -> NDArray[np.float64]:
        if isinstance(chips, ChipSet):
            if self.channel not in chips.channels:
                raise InputError(
                    f"chips: the bank needs channel {self.channel!r}; have {sorted(chips.channels)}"
                )
            imgs = chips[self.channel]
            fx = np.array([p.K[0, 0] for p in chips.poses])
        else:
            imgs = chips
        x = check_array(imgs, "chips", ndim=3)
        if x.shape[1:] != (self.size, self.size):
            raise InputError(f"chips: expected (N, {self.size}, {self.size}) chips, got {x.shape}")
        return prepare_chips(x, self.channel, fx, intensity_prep=self.intensity_prep)

    def responses(
        self, chips: ChipSet | NDArray, fx: NDArray | float | None = None
    ) -> dict[str, NDArray]:
        """Peak metrics ``(N, K)`` (``psr``, ``pce``, ``peak``, ``row``, ``col``) of every
        chip against every filter."""
        x = self._inputs(chips, fx)
        spectra = np.fft.fft2(x, axes=(-2, -1))
        return spectrum_metrics(spectra, self.freqs)

    def classify(self, chips: ChipSet | NDArray, fx: NDArray | float | None = None):  # -> DataFrame
        """Classify chips by the best score (``self.metric``) over all filters.

        Returns
        -------
        pandas.DataFrame
            One row per chip: ``pred_class``, ``pred_az_deg`` (winning bin centre),
            ``score`` (winning metric value), ``psr`` and ``pce`` of the winning
            filter, and ``score_<class>`` / ``psr_<class>`` (best per class).
        """
        import pandas as pd

        r = self.responses(chips, fx)
        sc = r[self.metric]
        best = np.argmax(sc, axis=1)
        n = len(sc)
        out = {
            "pred_class": [self.classes[self.filter_class[b]] for b in best],
            "pred_az_deg": self.filter_az_deg[best],
            "score": sc[np.arange(n), best],
            "psr": r["psr"][np.arange(n), best],
            "pce": r["pce"][np.arange(n), best],
        }
        for ci, c in enumerate(self.classes):
            sel = self.filter_class == ci
            out[f"score_{c}"] = sc[:, sel].max(axis=1)
            out[f"psr_{c}"] = r["psr"][:, sel].max(axis=1)
        return pd.DataFrame(out)

    def detect(
        self,
        scene: NDArray,
        *,
        fx: float | None = None,
        threshold: float = 8.0,
        max_detections: int = 10,
        min_distance: int | None = None,
    ) -> list[Detection]:
        """Detect targets in a larger ``(H, W)`` scene image of the bank's channel.

        The scene is prepared like a chip (``depth`` needs ``fx``), each filter is
        correlated over the whole scene (zero-padded to the scene size), and peaks of
        the per-pixel best PSR-normalised response are taken greedily with
        non-maximum suppression (``min_distance``, default half a chip) while their
        PSR (:func:`~prism3d.atr.filters.peak_metrics` window) is >= ``threshold``.
        ``row, col`` is the estimated target centre (chip centre) in the scene.
        """
        g = check_array(scene, "scene", ndim=2)
        H, W = g.shape
        S = self.size
        if H < S or W < S:
            raise InputError(
                f"scene: expected at least {S}x{S} pixels (the chip size), got {H}x{W}"
            )
        x = prepare_chips(g[None], self.channel, fx, intensity_prep=self.intensity_prep)[0]
        planes, z = _scene_planes(x, self.freqs, S)
        best_k = np.argmax(z, axis=0)
        best = np.max(z, axis=0)
        md = S // 2 if min_distance is None else int(min_distance)
        out: list[Detection] = []
        work = best.copy()
        for _ in range(int(max_detections) * 4):
            if len(out) >= max_detections:
                break
            idx = int(np.argmax(work))
            r, c = divmod(idx, W)
            if not np.isfinite(work[r, c]):
                break
            k = int(best_k[r, c])
            plane = np.roll(planes[k], (-r, -c), axis=(0, 1))
            psr_v = float(_psr_at_origin(plane))
            work[max(0, r - md) : r + md + 1, max(0, c - md) : c + md + 1] = -np.inf
            if psr_v < threshold:
                if best[r, c] < 0:
                    break
                continue
            out.append(
                Detection(
                    int((r + S // 2) % H),
                    int((c + S // 2) % W),
                    self.classes[self.filter_class[k]],
                    float(self.filter_az_deg[k]),
                    psr_v,
                )
            )
        return out

    # -- persistence --------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the bank as ``.npz`` (no pickle) atomically; returns the path."""
        meta = {
            "schema_version": BANK_SCHEMA_VERSION,
            "classes": list(self.classes),
            "channel": self.channel,
            "size": int(self.size),
            "bin_deg": float(self.bin_deg),
            "metric": self.metric,
            "metadata": self.metadata,
        }
        p = Path(path)
        with atomic_path(p) as tmp, open(tmp, "wb") as fh:
            np.savez(
                fh,
                meta_json=np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8),
                freqs=self.freqs.astype(np.complex128),
                filter_class=self.filter_class.astype(np.int64),
                filter_az_deg=self.filter_az_deg.astype(np.float64),
                params=self.params.astype(np.float64),
            )
        return p

    @classmethod
    def load(cls, path: str | Path) -> FilterBank:
        """Read a bank written by :meth:`save`; rejects unknown schema versions."""
        p = check_file(path, "filter bank")
        names = ("freqs", "filter_class", "filter_az_deg", "params")
        try:  # our own handle: np.load leaves a file it fails to parse open
            with open(p, "rb") as fh, np.load(fh, allow_pickle=False) as z:
                meta = json.loads(bytes(z["meta_json"].astype(np.uint8)).decode("utf-8"))
                for k in names:  # declared sizes, before decompressing
                    with z.zip.open(f"{k}.npy") as member:
                        check_npy_header(member, f"{p}:{k}")
                arrays = {k: z[k] for k in names}
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - zip/numpy/json raise many types on a corrupt file
            raise InputError(f"{p}: not a prism3d filter bank ({exc or type(exc).__name__})") from None
        ver = meta.get("schema_version") if isinstance(meta, dict) else None
        if ver != BANK_SCHEMA_VERSION:
            raise InputError(
                f"{p}: unknown filter bank schema_version {ver!r} (this prism3d reads {BANK_SCHEMA_VERSION})"
            )
        if arrays["freqs"].dtype.kind not in "fc" or not np.all(np.isfinite(arrays["freqs"])):
            raise InputError(f"{p}: the bank's filters hold NaN or infinite values; retrain it")
        try:
            return cls(
                list(meta["classes"]),
                meta["channel"],
                int(meta["size"]),
                float(meta["bin_deg"]),
                arrays["freqs"],
                arrays["filter_class"],
                arrays["filter_az_deg"],
                arrays["params"],
                dict(meta.get("metadata", {})),
                str(meta.get("metric", "pce")),
            )
        except InputError as exc:
            raise InputError(f"{p}: not a valid prism3d filter bank ({exc})") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{p}: not a valid prism3d filter bank (bad or missing {exc})") from None


def _scene_planes(
    x: NDArray[np.float64], freqs: NDArray[np.complex128], S: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Correlation planes ``(K, H, W)`` of a prepared scene with every filter (zero-padded
    to the scene size; shift s at [s]) and the planes standardised to compare filters."""
    H, W = x.shape
    G = np.fft.fft2(x)
    spat = np.fft.ifft2(freqs, axes=(-2, -1)).real
    pad = np.zeros((len(freqs), H, W))
    pad[:, :S, :S] = spat
    Fp = np.fft.fft2(pad, axes=(-2, -1))
    planes = np.fft.ifft2(G[None] * np.conj(Fp), axes=(-2, -1)).real
    # normalise each plane by its own sidelobe statistics (global std) to compare filters
    z = (planes - planes.mean(axis=(1, 2), keepdims=True)) / np.maximum(
        planes.std(axis=(1, 2), keepdims=True), 1e-300
    )
    return planes, z


def _psr_at_origin(plane: NDArray) -> float:
    """PSR of the value at ``[0, 0]`` of a plane (window wraps around)."""
    c = np.fft.fftshift(plane)
    h, w = c.shape
    r0, c0 = h // 2, w // 2
    half = PSR_WINDOW // 2
    win = np.take(
        np.take(c, np.arange(r0 - half, r0 + half) % h, axis=0),
        np.arange(c0 - half, c0 + half) % w,
        axis=1,
    )
    keep = np.ones_like(win, dtype=bool)
    e0 = half - PSR_EXCLUDE // 2
    keep[e0 : e0 + PSR_EXCLUDE, e0 : e0 + PSR_EXCLUDE] = False
    side = win[keep]
    return (c[r0, c0] - side.mean()) / max(side.std(), 1e-300)


def spectrum_metrics(spectra: NDArray, freqs: NDArray, chunk: int = 8) -> dict[str, NDArray]:
    """Peak metrics ``(N, K)`` of spectra ``(N, S, S)`` against filters ``(K, S, S)``."""
    n, k = len(spectra), len(freqs)
    out = {m: np.empty((n, k)) for m in ("peak", "psr", "pce", "row", "col")}
    import scipy.fft

    W = spectra.shape[-1]
    sp = spectra[..., : W // 2 + 1].astype(np.complex64)
    fr = np.conj(freqs[..., : W // 2 + 1]).astype(np.complex64)
    for s in range(0, n, chunk):
        # the planes are real (real images, Hermitian filters): half spectra suffice
        planes = scipy.fft.irfft2(
            sp[s : s + chunk, None] * fr[None], s=spectra.shape[-2:], axes=(-2, -1), workers=-1
        )
        planes = np.fft.fftshift(planes, axes=(-2, -1))
        m = peak_metrics(planes)
        for key, arr in out.items():
            arr[s : s + chunk] = m[key]
    return out


def _az_bin(az_deg: NDArray, bin_deg: float) -> NDArray[np.int64]:
    nb = round(360.0 / bin_deg)
    return (
        np.floor(((np.asarray(az_deg) % 360.0) + bin_deg / 2.0) / bin_deg).astype(np.int64)
    ) % nb


def render_class_chips(
    targets: Sequence[tuple[str, SceneMesh]],
    *,
    channel: str,
    azimuth: str | Sequence[float],
    elevation: str | Sequence[float],
    range_mm: str | float | Sequence[float] | None = None,
    chip_spec: ChipSpec | None = None,
) -> tuple[NDArray, list[str], NDArray, NDArray, NDArray, NDArray]:
    """Chips of all targets: ``(images (N,S,S), labels, az_deg, el_deg, range_mm, fx)``.

    ``range_mm`` None: :func:`~prism3d.atr.chips.default_range_mm` of each mesh;
    ``chip_spec`` (None = :data:`BANK_CHIP_SPEC`): its channels are replaced by
    ``(channel, "mask")`` and target ``i`` renders with seed ``seed + 1009 i``.
    """
    spec = as_chip_spec(chip_spec, BANK_CHIP_SPEC)
    items = check_targets(targets)
    imgs, labels, az, el, rng_, fx = [], [], [], [], [], []
    for i, (cls, mesh) in enumerate(items):
        poses = spec_poses(mesh, azimuth, elevation, range_mm, spec)
        cspec = replace(spec, channels=(channel, "mask"), seed=spec.seed + _CLASS_SEED_STRIDE * i)
        cs = render_chips(mesh, poses, chip_spec=cspec)
        imgs.append(cs[channel])
        labels += [cls] * len(cs)
        az.append([p.az_deg for p in cs.poses])
        el.append([p.el_deg for p in cs.poses])
        rng_.append([p.range_mm for p in cs.poses])
        fx.append([p.K[0, 0] for p in cs.poses])
    return (
        np.concatenate(imgs),
        labels,
        np.concatenate(az),
        np.concatenate(el),
        np.concatenate(rng_),
        np.concatenate(fx),
    )


def _check_bank_args(
    items: list[tuple[str, SceneMesh]], channel: str, metric: str, bin_deg: float, params
) -> list[str]:
    """Validate :func:`train_bank`'s arguments; returns the classes in first-seen order."""
    check_choice(channel, "channel", FILTER_CHANNELS)
    check_choice(metric, "metric", METRICS)
    if not (isinstance(bin_deg, (int, float)) and 0 < bin_deg <= 360):
        raise InputError(f"bin_deg: expected a width in (0, 360], got {bin_deg!r}")
    nbins = 360.0 / bin_deg
    if abs(nbins - round(nbins)) > 1e-9:
        raise InputError(f"bin_deg: 360 / bin_deg must be an integer, got bin_deg={bin_deg}")
    classes = sorted({c for c, _ in items}, key=[c for c, _ in items].index)
    if len(classes) < 2:
        raise InputError(f"targets: a bank needs at least 2 classes, got {classes}")
    if params != "auto" and len(tuple(params)) != 3:
        raise InputError(f"params: expected 'auto' or (alpha, beta, gamma), got {params!r}")
    return classes


def _group_moments(
    spectra: NDArray, lab: NDArray, bins: NDArray, n_classes: int, nbins: int
) -> tuple[list[tuple[int, int]], list[tuple[NDArray, NDArray, NDArray]]]:
    """Non-empty (class, bin) groups and their OT-MACH spectral moments (mean, ASD, ASM)."""
    groups = [
        (ci, b)
        for ci in range(n_classes)
        for b in range(nbins)
        if np.any((lab == ci) & (bins == b))
    ]
    moments = []
    for ci, b in groups:
        sel = spectra[(lab == ci) & (bins == b)]
        m = sel.mean(axis=0)
        moments.append(
            (m, np.mean(np.abs(sel) ** 2, axis=0), np.mean(np.abs(sel - m) ** 2, axis=0))
        )
    return groups, moments


def _search_params(
    moments: list, groups: list[tuple[int, int]], heldout: tuple[NDArray, NDArray, NDArray],
    nbins: int, metric: str,
) -> tuple[tuple[float, float, float], int]:
    """Best ``(alpha, beta, gamma)`` of :data:`DEFAULT_PARAM_GRID` on held-out views.

    ``heldout`` = (spectra, class index, azimuth bin). Each view competes among the
    filters of its bin and the two neighbours; key = (correct views, mean median margin).
    Returns the triple and its number of correct views.
    """
    spec_v, labv, binv = heldout
    gcls = np.array([g[0] for g in groups])
    gbin = np.array([g[1] for g in groups])
    best = (-np.inf, -np.inf)
    best_prm = tuple(DEFAULT_PARAM_GRID[0])
    for prm in DEFAULT_PARAM_GRID:
        freqs = np.stack([otmach_from_moments(*mo, *prm).freq for mo in moments])
        correct, margins = 0, []
        for b in range(nbins):
            vs = np.flatnonzero(binv == b)
            fs = np.flatnonzero(
                (gbin == b) | (gbin == (b + 1) % nbins) | (gbin == (b - 1) % nbins)
            )
            if vs.size == 0 or fs.size == 0:
                continue
            v = spectrum_metrics(spec_v[vs], freqs[fs])[metric]
            own = gcls[fs][None, :] == labv[vs][:, None]
            s_in = np.where(own, v, -np.inf).max(axis=1)
            s_out = np.where(~own, v, -np.inf).max(axis=1)
            correct += int(np.sum(s_in > s_out))
            margins.append(np.median(s_in - s_out))
        key = (correct, float(np.mean(margins)) if margins else -np.inf)
        if key > best:
            best, best_prm = key, tuple(float(x) for x in prm)
    return best_prm, best[0]


def _heldout_views(
    items, classes, channel, az_train, elevation, range_mm, bin_deg, spec
) -> tuple[NDArray, NDArray, NDArray]:
    """Spectra, class index and bin of views half a training step away in azimuth."""
    step = float(np.median(np.diff(sorted(az_train)))) if len(az_train) > 1 else bin_deg
    az_val = [a + step / 2.0 for a in az_train]
    Xv, lv, azv, _, _, fxv = render_class_chips(
        items,
        channel=channel,
        azimuth=az_val,
        elevation=elevation,
        range_mm=range_mm,
        chip_spec=replace(spec, seed=spec.seed + _HELDOUT_SEED_OFFSET),
    )
    labv = np.array([classes.index(c) for c in lv])
    spec_v = np.fft.fft2(prepare_chips(Xv, channel, fxv), axes=(-2, -1))
    return spec_v, labv, _az_bin(azv, bin_deg)


def class_scale_facts(
    items: Sequence[tuple[str, SceneMesh]], labels: Sequence[str], fx: NDArray, range_mm: NDArray,
) -> dict[str, dict]:
    """What a scene detector needs to put each class's chips at the right scale:
    ``chip_px_per_mm`` (median chip focal / range over the class's training chips: chip
    pixels per mm at the target), ``class_radius_mm`` (bounding radius of its mesh) and
    ``class_full_scale`` (the mesh's ratio to full size: a built-in kit model's
    ``metadata["scale"]``, 1 for a mesh taken as it is), ``class_extent_mm`` (the mesh's
    x, y, z extents, z up)."""
    lab = np.asarray(labels)
    ratio = np.asarray(fx, dtype=np.float64) / np.asarray(range_mm, dtype=np.float64)
    out: dict[str, dict] = {"chip_px_per_mm": {}, "class_radius_mm": {}, "class_full_scale": {},
                            "class_extent_mm": {}}
    for cls, mesh in items:
        if cls in out["chip_px_per_mm"]:
            continue
        out["chip_px_per_mm"][cls] = float(np.median(ratio[lab == cls]))
        out["class_radius_mm"][cls] = float(bounding_sphere(mesh)[1])
        out["class_full_scale"][cls] = float(mesh.metadata.get("scale", 1.0) or 1.0)
        out["class_extent_mm"][cls] = [float(v) for v in mesh.extent_mm]
    return out


def _bank_metadata(
    items: list[tuple[str, SceneMesh]], labels: list[str], fx: NDArray, rng: NDArray, *,
    az_train: NDArray, elevation, range_mm, spec: ChipSpec, params, sep: float, chosen: NDArray,
) -> dict:
    """A trained bank's metadata: training poses and chips, the (alpha, beta, gamma) chosen
    and their held-out accuracy ``sep``, the PSR window, each class's scale."""
    return {
        "azimuth": [float(a) for a in az_train],
        "elevation": [float(e) for e in parse_range(elevation)],
        "range_mm": None if range_mm is None else [float(r) for r in parse_range(range_mm)],
        "framing": spec.framing,
        "camouflage": bool(spec.camouflage),
        "noise_sigma": float(spec.noise_sigma),
        "depth_noise_mm": float(spec.depth_noise_mm),
        "params": "auto" if params == "auto" else list(params),
        "targets": [[c, m.name] for c, m in items],
        "heldout_accuracy": None if not math.isfinite(float(sep)) else float(sep),
        "chosen_params": [float(v) for v in chosen],
        "psr_window": PSR_WINDOW,
        "psr_exclude": PSR_EXCLUDE,
        "intensity_prep": INTENSITY_PREP,
        **class_scale_facts(items, labels, fx, rng),
    }


def train_bank(
    targets: Sequence[tuple[str, SceneMesh]],
    *,
    channel: str = "depth",
    azimuth: str | Sequence[float] = BankOptions.azimuth,
    elevation: str | Sequence[float] = BankOptions.elevation,
    range_mm: str | float | Sequence[float] | None = None,
    bin_deg: float = BankOptions.bin_deg,
    metric: str = "pce",
    params: str | tuple[float, float, float] = BankOptions.params,
    chip_spec: ChipSpec | None = None,
) -> FilterBank:
    """Train an OT-MACH filter bank from ``[(class_name, SceneMesh), ...]`` (>= 2 classes).

    ``channel``: chip channel of the filters; ``azimuth``/``elevation``: training grid;
    ``bin_deg``: azimuth bin width (``360 / bin_deg`` an integer); ``metric``: peak
    metric of classification and of the search; ``params``: fixed ``(alpha, beta,
    gamma)`` or ``"auto"`` (search on held-out views, module docstring);
    ``chip_spec``: training chips (None = :data:`BANK_CHIP_SPEC`).
    """
    spec = as_chip_spec(chip_spec, BANK_CHIP_SPEC)
    items = check_targets(targets)
    classes = _check_bank_args(items, channel, metric, bin_deg, params)
    nbins = round(360.0 / bin_deg)
    az_train = parse_range(azimuth)
    X, labels, az, _, rng, fx = render_class_chips(
        items, channel=channel, azimuth=az_train, elevation=elevation, range_mm=range_mm,
        chip_spec=spec,
    )
    lab = np.array([classes.index(c) for c in labels])
    spectra = np.fft.fft2(prepare_chips(X, channel, fx), axes=(-2, -1))
    groups, moments = _group_moments(spectra, lab, _az_bin(az, bin_deg), len(classes), nbins)
    if params == "auto":
        heldout = _heldout_views(
            items, classes, channel, az_train, elevation, range_mm, bin_deg, spec
        )
        prm, n_correct = _search_params(moments, groups, heldout, nbins, metric)
        sep = n_correct / max(len(heldout[1]), 1)
    else:
        prm = tuple(float(v) for v in params)
        sep = float("nan")
    freqs = np.stack([otmach_from_moments(*mo, *prm).freq for mo in moments])
    chosen = np.tile(np.asarray(prm), (len(groups), 1))
    fclass = np.array([g[0] for g in groups], dtype=np.int64)
    meta = _bank_metadata(items, labels, fx, rng, az_train=az_train, elevation=elevation,
                          range_mm=range_mm, spec=spec, params=params, sep=sep, chosen=chosen[0])
    return FilterBank(
        classes,
        channel,
        int(spec.size),
        float(bin_deg),
        freqs,
        fclass,
        np.array([g[1] * bin_deg for g in groups], dtype=np.float64),
        chosen,
        meta,
        metric,
    )
