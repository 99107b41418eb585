"""Detection scores, one scorer for images and maps: probability of detection against
false positives per image or frame (FPPI), as JPL's OT-MACH work reports detection, with
identification among the hits (MSTAR-style). Both walk the detections best first through
``_match_best_first``, each target taken at most once; they differ only in how a
detection finds its target (a box or 3D radius in an image; a radius on the map for a
survey, :func:`score_detections`) and in what a confuser is (a false positive in an image
scene; neither hit nor miss on a map, where it is only an uncounted target).

Image scenes follow the scene contract (docs/atr.md "Scene scoring"): a truth
``{"targets": [{"class", "confuser", "box_rc": [r0, c0, r1, c1], "xyz_mm"?, ...}]}`` and
detections ``{"detections": [{"row", "col", "class", "score", "xyz_mm"?, ...}]}``.

A detection hits a target when its pixel lies in the target's box, or its 3D position is
within the target's ``radius_mm`` of the target's ``xyz_mm`` (both given). Detections are
matched greedily in descending score, each target at most once; a detection on a confuser
(a vehicle or crate not in the bank) or on nothing, or a second one on a matched target, is
a false positive. A target marked ``difficult`` (mostly hidden) is neither counted nor
missed, and detections on it are ignored (PASCAL VOC's rule). Every threshold is a prefix
of that order, so one matching serves the whole Pd-FPPI curve.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from prism3d.atr.scene import SceneDetection
from prism3d.capture.rig import StereoRig
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_paths
from prism3d.io.images import check_image_size

__all__ = ["FPPI_POINTS", "FppiPoint", "MapDetection", "MapTarget", "Match", "PdCurve", "SceneEvaluation", "SceneScore",
           "check_scene_folders", "match_map_detections", "plot_fppi", "plot_scene", "read_scene_truth",
           "score_detections", "score_scenes", "write_scene_results"]

#: FPPI operating points reported (Pd and identification accuracy at each).
FPPI_POINTS = (0.1, 1.0)


@dataclass(frozen=True)
class Match:
    """What one detection (``index`` into the list given) turned out to be: ``hit`` (a
    counted target, ``target``), ``confuser`` (an uncounted target, scored as a false
    positive), ``fp``, or ``ignored`` (on a difficult target, or an uncounted one where
    confusers are not false positives); ``class_right`` for a hit."""

    index: int
    score: float
    kind: str
    target: int | None
    class_right: bool


@dataclass(frozen=True)
class PdCurve:
    """Pd-FPPI curve at each distinct detection score, descending: ``threshold``, ``pd``,
    ``fppi`` and ``id_accuracy`` (identification among the hits), one value each."""

    threshold: list[float]
    pd: list[float]
    fppi: list[float]
    id_accuracy: list[float]


@dataclass(frozen=True)
class FppiPoint:
    """The curve at an operating point: the best ``pd`` with at most that many false
    positives per image, its ``id_accuracy``, its ``threshold`` (None: not reached), and
    ``confusers_called``, the share of confusers with a detection at or above it."""

    pd: float
    id_accuracy: float
    threshold: float | None
    confusers_called: float


@dataclass(frozen=True)
class SceneScore:
    """:func:`score_scenes`' result: image, target (bank classes, not confusers) and
    confuser counts, the curve, the operating points of :data:`FPPI_POINTS` (keyed
    ``"0.1"``, ``"1"``) and the highest Pd at any threshold. ``to_json`` / ``from_json``:
    the results file's keys."""

    n_images: int
    n_targets: int
    n_confusers: int
    curve: PdCurve
    at_fppi: dict[str, FppiPoint]
    pd_max: float

    def to_json(self) -> dict[str, Any]:
        return {"n_images": self.n_images, "n_targets": self.n_targets, "n_confusers": self.n_confusers,
                "curve": asdict(self.curve), "at_fppi": {k: asdict(v) for k, v in self.at_fppi.items()},
                "pd_max": self.pd_max}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> SceneScore:
        try:
            return cls(int(doc["n_images"]), int(doc["n_targets"]), int(doc["n_confusers"]), PdCurve(**doc["curve"]),
                       {k: FppiPoint(**v) for k, v in doc["at_fppi"].items()}, float(doc["pd_max"]))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(f"scene scores: not a scores document ({type(exc).__name__}: {exc})") from None


@dataclass(frozen=True)
class SceneEvaluation:
    """``prism3d bank eval-scenes``' result: the ``score`` and what produced it (the
    ``bank`` file, its ``channel`` (channels joined by commas) and ``classes``, the
    ``seconds`` and ``workers`` of the run, and ``scenes``: each scene's folder, timings
    and detections as ``detect`` writes them). ``to_json``: the score's keys and these."""

    score: SceneScore
    bank: str
    channel: str
    classes: list[str]
    seconds: float
    workers: int | None
    scenes: list[dict[str, Any]]

    def to_json(self) -> dict[str, Any]:
        return {**self.score.to_json(), "bank": self.bank, "channel": self.channel, "classes": self.classes,
                "seconds": self.seconds, "workers": self.workers, "scenes": self.scenes}


def _match_best_first(dets: Sequence[dict], targets: Sequence[dict],
                     find: Callable[[dict, list[bool]], tuple[int | None, bool]], *,
                     confusers_are_fp: bool) -> list[Match]:
    """Walk ``dets`` (each with ``score`` and ``class``) in descending score; ``find(det,
    taken)`` gives the free target it falls on (or None) and whether it lies near an
    uncounted target. Targets carry ``counted`` (default True) and ``difficult`` (default
    False): a difficult target is never taken and its detections are ignored (PASCAL VOC's
    rule); an uncounted one is taken once, as a confuser or ignored."""
    out = []
    taken = [False] * len(targets)
    for i in sorted(range(len(dets)), key=lambda i: -dets[i]["score"]):
        d = dets[i]
        j, near_uncounted = find(d, taken)
        if j is None:
            kind = "ignored" if near_uncounted else "fp"
            out.append(Match(i, float(d["score"]), kind, None, False))
            continue
        t = targets[j]
        if t.get("difficult", False):
            out.append(Match(i, float(d["score"]), "ignored", j, False))
            continue
        taken[j] = True
        if not t.get("counted", True):
            out.append(Match(i, float(d["score"]), "confuser" if confusers_are_fp else "ignored", j, False))
        else:
            out.append(Match(i, float(d["score"]), "hit", j, d.get("class") is not None and d.get("class") == t.get("class")))
    return out


def score_scenes(scenes: Sequence[tuple[dict, dict]]) -> SceneScore:
    """Score ``[(detections_doc, truth_doc), ...]`` (one pair per image; the documents as
    ``detect --json`` and ``simulate field`` write them, module docstring): Pd,
    identification and confusers called against false positives per image."""
    if not isinstance(scenes, Sequence) or isinstance(scenes, (str, bytes)) or not scenes:
        raise InputError("scenes: expected a non-empty list of (detections, truth) pairs")
    events = []  # (score, kind, correct_id): kind "hit", "fp", "confuser"
    n_targets = n_confusers = 0
    for k, pair in enumerate(scenes):
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
            raise InputError(f"scenes[{k}]: expected a (detections, truth) pair")
        dets, targets = _detections(pair[0], k), _targets(pair[1], k)
        n_targets += sum(not t["confuser"] and not t["difficult"] for t in targets)
        n_confusers += sum(t["confuser"] and not t["difficult"] for t in targets)
        for m in _match_best_first(dets, targets, lambda d, taken: (_match(d, targets, taken), False),
                                  confusers_are_fp=True):
            if m.kind != "ignored":  # a difficult target: neither found nor missed, nor a false alarm
                events.append((m.score, m.kind, m.class_right))
    n_images = len(scenes)
    events.sort(key=lambda e: -e[0])
    th, pd, fppi, ida = _curve(events, n_targets, n_images)
    at = {}
    for x in FPPI_POINTS:
        ok = [i for i, f in enumerate(fppi) if f <= x]
        if ok:
            i = max(ok, key=lambda i: (pd[i], -i))
            called = sum(e[1] == "confuser" and e[0] >= th[i] for e in events)
            at[f"{x:g}"] = FppiPoint(pd[i], ida[i], th[i], called / n_confusers if n_confusers else float("nan"))
        else:
            at[f"{x:g}"] = FppiPoint(0.0, float("nan"), None, 0.0 if n_confusers else float("nan"))
    return SceneScore(n_images, n_targets, n_confusers, PdCurve(th, pd, fppi, ida), at, pd[-1] if pd else 0.0)


@dataclass(frozen=True)
class MapDetection:
    """A detection on a map (metres, one frame with the targets')."""

    x: float
    y: float
    score: float
    """Higher is surer; -1 or below: not a detection (no class fits)."""
    class_name: str | None = None
    """The class it is called (None: none)."""


@dataclass(frozen=True)
class MapTarget:
    """A true object on a map (metres)."""

    x: float
    y: float
    length_m: float
    """Its length: half of it (at least 2 m) is the default hit radius."""
    counted: bool = True
    """False for a confuser: neither found nor missed, and a detection near it is no false positive."""
    class_name: str | None = None
    """Its class."""


def match_map_detections(dets: Sequence[MapDetection], targets: Sequence[MapTarget], *,
                         radius_m: float | None = None) -> list[Match]:
    """The map rules of :func:`score_detections`, one :class:`Match` per detection scoring
    above -1 (``index`` into ``dets``), best first."""
    tx = np.array([[t.x, t.y] for t in targets]) if targets else np.zeros((0, 2))
    counted = np.array([bool(t.counted) for t in targets], bool)
    radius = np.array([radius_m if radius_m is not None else max(0.5 * t.length_m, 2.0) for t in targets])

    def find(d: dict, taken: list[bool]) -> tuple[int | None, bool]:
        dist = np.hypot(tx[:, 0] - d["x"], tx[:, 1] - d["y"]) if len(tx) else np.zeros(0)
        hit = np.flatnonzero((dist <= radius) & ~np.asarray(taken, bool))
        if len(hit):
            return int(hit[np.argmin(dist[hit])]), False
        return None, bool(len(dist) and np.any((dist <= radius) & ~counted))

    live = [i for i, d in enumerate(dets) if d.score > -1]
    docs = [{"x": dets[i].x, "y": dets[i].y, "score": dets[i].score, "class": dets[i].class_name} for i in live]
    ms = _match_best_first(docs, [{"counted": t.counted, "class": t.class_name} for t in targets], find,
                           confusers_are_fp=False)
    return [Match(live[m.index], m.score, m.kind, m.target, m.class_right) for m in ms]


def score_detections(dets: Sequence[MapDetection], targets: Sequence[MapTarget], n_frames: int, *,
                     radius_m: float | None = None, threshold: float | None = None) -> dict[str, Any]:
    """Map detections against map targets: Pd against false positives per
    frame over the score threshold. A detection is a hit when within ``radius_m`` (default:
    half the target's length, at least 2 m) of a target's centre not yet found, the nearest
    first; uncounted targets (confusers) are neither hits nor misses, and a detection near
    one is not a false positive; scores <= -1 (no class fits) are not detections. With
    ``threshold``: Pd, false positives and the share of hits whose class is the
    target's at that score too. ``curve``: one entry per detection, best first."""
    counted = np.array([bool(t.counted) for t in targets], bool)
    curve = []
    tp = fp = right = 0
    for m in match_map_detections(dets, targets, radius_m=radius_m):
        tp += m.kind == "hit"
        fp += m.kind == "fp"
        right += m.class_right
        curve.append((m.score, tp, fp, right))
    n_t = int(counted.sum())

    def pd_at(fppf: float) -> tuple[float, float | None]:
        best = (0, 0)
        for _, t, f, rgt in curve:
            if f / max(n_frames, 1) <= fppf and t > best[0]:
                best = (t, rgt)
        return best[0] / max(n_t, 1), (best[1] / best[0] if best[0] else None)

    out: dict[str, Any] = {"n_targets": n_t, "n_frames": n_frames}
    for x in FPPI_POINTS:
        pd, acc = pd_at(x)
        out[f"pd_at_{x:g}_fppf"], out[f"class_accuracy_at_{x:g}_fppf"] = pd, acc
    if threshold is not None:
        at = [c for c in curve if c[0] >= threshold]
        t, f, rgt = (at[-1][1], at[-1][2], at[-1][3]) if at else (0, 0, 0)
        out["at_threshold"] = {"threshold": threshold, "pd": t / max(n_t, 1), "false_positives": f,
                               "fp_per_frame": f / max(n_frames, 1), "class_accuracy": rgt / t if t else None}
    out["curve"] = [{"score": sc, "tp": t, "fp": f, "class_right": rgt} for sc, t, f, rgt in curve]
    return out


def _curve(events: list[tuple[float, str, bool]], n_targets: int, n_images: int
           ) -> tuple[list[float], list[float], list[float], list[float]]:
    """Threshold, Pd, FPPI and identification accuracy at each distinct score of ``events``
    (``(score, kind, correct_id)``, in descending score)."""
    th, pd, fppi, ida = [], [], [], []
    hits = fps = correct = 0
    for i, (score, kind, ok) in enumerate(events):
        hits += kind == "hit"
        fps += kind != "hit"
        correct += kind == "hit" and ok
        if i + 1 < len(events) and events[i + 1][0] == score:
            continue  # equal scores pass a threshold together
        th.append(float(score))
        pd.append(hits / n_targets if n_targets else float("nan"))
        fppi.append(fps / n_images)
        ida.append(correct / hits if hits else float("nan"))
    return th, pd, fppi, ida


def _finite(v: object, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{what}: expected a finite number, got {v!r}")
    return float(v)


def _xyz(v: object, what: str) -> np.ndarray | None:
    if v is None:
        return None
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise InputError(f"{what}: expected [x, y, z] or null, got {v!r}")
    return np.array([_finite(c, what) for c in v])


def _items(doc: object, key: str, k: int | None, fields: str, what: str) -> list[tuple[str, dict]]:
    """``doc[key]`` of scene ``k`` (None: a file of its own, named by the caller): (name for
    messages, item) pairs, each an object with a string ``class``."""
    if not isinstance(doc, dict) or not isinstance(doc.get(key), list):
        raise InputError(f"{'' if k is None else f'scenes[{k}]: '}{what}: expected {{\"{key}\": [...]}}")
    out = []
    for i, item in enumerate(doc[key]):
        w = f"{'' if k is None else f'scenes[{k}].'}{key}[{i}]"
        if not isinstance(item, dict) or not isinstance(item.get("class"), str):
            raise InputError(f"{w}: expected an object with {fields}")
        out.append((w, item))
    return out


def _detections(doc: object, k: int) -> list[dict]:
    return [{"row": _finite(d.get("row"), f"{w}.row"), "col": _finite(d.get("col"), f"{w}.col"),
             "class": d["class"], "score": _finite(d.get("score"), f"{w}.score"),
             "xyz": _xyz(d.get("xyz_mm"), f"{w}.xyz_mm")}
            for w, d in _items(doc, "detections", k, "row, col, class, score", "detections")]


def _targets(doc: object, k: int | None) -> list[dict]:
    """A truth document's targets, each checked (box inside out, finite numbers, a 3D
    radius > 0: a negative one would silently never match)."""
    out = []
    for w, t in _items(doc, "targets", k, "class, confuser, box_rc", "truth"):
        box = t.get("box_rc")
        if not isinstance(box, (list, tuple)) or len(box) != 4:
            raise InputError(f"{w}.box_rc: expected [r0, c0, r1, c1], got {box!r}")
        r0, c0, r1, c1 = (_finite(v, f"{w}.box_rc") for v in box)
        if r1 < r0 or c1 < c0:
            raise InputError(f"{w}.box_rc: expected r0 <= r1 and c0 <= c1, got {box!r}")
        radius = t.get("radius_mm")
        if radius is not None and _finite(radius, f"{w}.radius_mm") <= 0:
            raise InputError(f"{w}.radius_mm: expected a radius > 0 mm, got {radius!r}")
        conf = bool(t.get("confuser", False))
        out.append({"class": t["class"], "confuser": conf, "counted": not conf, "box": (r0, c0, r1, c1),
                    "difficult": bool(t.get("difficult", False)),
                    "xyz": _xyz(t.get("xyz_mm"), f"{w}.xyz_mm"),
                    "radius": None if radius is None else _finite(radius, f"{w}.radius_mm")})
    return out


def _match(d: dict, targets: list[dict], taken: list[bool]) -> int | None:
    """The free target the detection falls on (nearest box centre first), or None."""
    best, best_d = None, math.inf
    for j, t in enumerate(targets):
        if taken[j]:
            continue
        r0, c0, r1, c1 = t["box"]
        inside = r0 <= d["row"] <= r1 and c0 <= d["col"] <= c1
        near = (d["xyz"] is not None and t["xyz"] is not None and t["radius"] is not None
                and float(np.linalg.norm(d["xyz"] - t["xyz"])) <= t["radius"])
        if inside or near:
            dist = math.hypot(d["row"] - (r0 + r1) / 2, d["col"] - (c0 + c1) / 2)
            if dist < best_d:
                best, best_d = j, dist
    return best


def read_scene_truth(path: Any) -> dict:
    """A scene's ``truth.json``, parsed and its targets checked as scoring will read them;
    InputError naming the file otherwise (a nesting deeper than the JSON parser goes
    included)."""
    import json
    from pathlib import Path

    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: not readable ({exc})") from None
    except (ValueError, RecursionError) as exc:
        raise InputError(f"{p}: not valid JSON ({type(exc).__name__}: {exc})") from None
    try:
        _targets(doc, None)
    except InputError as exc:
        raise InputError(f"{p}: {exc}") from None
    return doc


def _in_message(exc: Exception, path: Any) -> str:
    """An error's message naming ``path`` once (loaders name their file; some do not)."""
    text = str(exc)
    return text if str(path) in text else f"{path}: {text}"


def check_scene_folders(scenes: Sequence[str]) -> list:
    """Scene folders (``shot.png``, ``rig.yaml``, ``truth.json`` each), every one checked
    before any detection: the shot's header readable and within the pixel budget, the rig
    loading and its sensor the shot's size, the truth valid (:func:`read_scene_truth`).
    A broken scene is one error naming it, not a failed unit after the others' work.
    Returns ``(folder, truth)`` pairs."""
    import warnings
    from pathlib import Path

    from PIL import Image

    if not scenes:
        raise InputError("eval-scenes: no scenes given (folders written by 'prism3d simulate field')")
    out = []
    for s in scenes:
        p = Path(s)
        if not p.is_dir():
            raise InputError(f"{p}: not a folder (expected a scene from 'prism3d simulate field')")
        for name in ("shot.png", "rig.yaml", "truth.json"):
            if not (p / name).is_file():
                raise InputError(f"{p}: has no {name} (expected a scene from 'prism3d simulate field')")
        shot = p / "shot.png"
        check_image_size(shot)  # a header claiming more than the budget (a decompression bomb)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(shot) as im:
                    w, h = im.size
        except Exception as exc:  # noqa: BLE001 - Pillow raises many types for a damaged file
            raise InputError(f"{shot}: not a readable image ({type(exc).__name__})") from None
        try:
            rig = StereoRig.load(p / "rig.yaml")
        except InputError as exc:
            raise InputError(_in_message(exc, p / "rig.yaml")) from None
        sw, sh = rig.split.sensor_size
        if (w, h) != (sw, sh):
            raise InputError(f"{shot}: {w}x{h} px, but its rig.yaml has a {sw}x{sh} sensor; the scene's "
                             "files do not belong together")
        out.append((p, read_scene_truth(p / "truth.json")))
    return out


def plot_fppi(*results: SceneScore | SceneEvaluation, labels: Sequence[str] | None = None):  # -> matplotlib Figure
    """Pd (and identification among hits, dashed) against false positives per image, one
    curve per :class:`SceneScore` or :class:`SceneEvaluation` (labelled by its channel
    unless ``labels``), FPPI on a log axis with 0.1 and 1 marked."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6))
    for k, res in enumerate(results):
        cv = res.score.curve if isinstance(res, SceneEvaluation) else res.curve
        lab = labels[k] if labels else (res.channel if isinstance(res, SceneEvaluation) else f"run {k + 1}")
        x = np.maximum(np.asarray(cv.fppi, dtype=float), 1e-3)
        line, = ax.step(x, cv.pd, where="post", label=f"{lab}: Pd")
        ax.step(x, cv.id_accuracy, where="post", ls="--", lw=0.8, color=line.get_color(),
                label=f"{lab}: identified")
    for v in FPPI_POINTS:
        ax.axvline(v, color="0.7", lw=0.6)
    ax.set_xscale("log")
    ax.set_xlim(1e-3, 20)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("false positives per image")
    ax.set_ylabel("Pd / identification")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig


def plot_scene(image: Any, truth: dict | None, detections: Sequence[SceneDetection], *, top: int = 8,
               title: str | None = None):  # -> matplotlib Figure
    """An image (the left view) with the true targets' boxes (green; confusers orange;
    dashed: difficult) when ``truth`` is given, and the ``top`` best detections (a cross,
    rank, class, score)."""
    import matplotlib.pyplot as plt

    img = np.asarray(image)
    h, w = img.shape[:2]
    fig, ax = plt.subplots(figsize=(6.4, 6.4 * h / w + 0.4))
    ax.imshow(img, cmap="gray" if img.ndim == 2 else None)
    for t in (truth or {}).get("targets", []):
        r0, c0, r1, c1 = t["box_rc"]
        col = "orange" if t.get("confuser") else "lime"
        ax.add_patch(plt.Rectangle((c0, r0), c1 - c0, r1 - r0, fill=False, ec=col, lw=1.2,
                                   ls="--" if t.get("difficult") else "-"))
        ax.text(c0, r1 + 0.012 * h, t["class"] + (" (confuser)" if t.get("confuser") else ""), color=col,
                fontsize=6, va="top")
    for k, d in enumerate(list(detections)[:top]):
        ax.plot(d.col, d.row, "+", color="red", ms=10, mew=1.5)
        ax.text(d.col + 0.01 * w, d.row - 0.01 * h, f"{k + 1}. {d.class_name} {d.score:.3f}", color="red",
                fontsize=6)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    return fig


def write_scene_results(res: SceneScore | SceneEvaluation, path) -> None:
    """The results JSON (``res.to_json()``) and its Pd-FPPI plot (``<stem>_fppi.png``),
    renamed together."""
    import json
    from pathlib import Path

    import matplotlib.pyplot as plt

    fig = plot_fppi(res)
    try:
        with atomic_paths(path, Path(f"{path.with_suffix('')}_fppi.png")) as tmp:
            tmp[0].write_text(json.dumps(res.to_json(), indent=1, default=float), encoding="utf-8")
            fig.savefig(tmp[1], format="png", dpi=80)
    finally:
        plt.close(fig)
