"""Trained model files, told apart by the ``kind`` in their JSON metadata: filter banks
(``bank``), scene recognisers (``scene_recogniser``: banks and a verifier), HOG + SVM
models (``hog_svm``) and aerial recognisers (``aerial_recogniser``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from prism3d.atr.aerial import AerialModel
from prism3d.atr.bank import FilterBank
from prism3d.atr.scene import bank_scale
from prism3d.atr.verifier import SceneRecogniser
from prism3d.errors import InputError

__all__ = ["load_aerial_model", "load_scene_model", "model_kind"]

#: Suffixes of trained model files.
MODEL_SUFFIXES = (".npz",)


def model_kind(path: str | Path) -> str | None:
    """``bank``, ``scene_recogniser``, ``hog_svm`` or ``aerial_recogniser`` for a prism3d
    model file, None for anything else (a mesh, a name, a damaged file)."""
    p = Path(path)
    if p.suffix.lower() not in MODEL_SUFFIXES or not p.is_file():
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            if "meta_json" not in z.files:
                return None
            meta = json.loads(bytes(z["meta_json"]).decode("utf-8"))
    except Exception:  # noqa: BLE001 - zip/numpy/json raise many types on a damaged file
        return None
    if not isinstance(meta, dict):
        return None
    return str(meta.get("kind", "bank"))


def load_scene_model(path: str | Path) -> Any:
    """A model that ``detect`` can search a ground-level scene with: a filter bank (with the
    scale facts scenes need) or a scene recogniser; an aerial model or anything else is
    refused with what to give instead."""
    kind = model_kind(path)
    if kind == "scene_recogniser":
        model = SceneRecogniser.load(path)
        for b in model.banks:
            bank_scale(b)
        return model
    if kind == "aerial_recogniser":
        raise InputError(f"{path}: an aerial recogniser (for surveys: survey-detect); detect needs a bank or a scene "
                         "recogniser ('prism3d bank train')")
    if kind not in (None, "bank"):
        raise InputError(f"{path}: a {kind} model; detect needs a bank or a scene recogniser ('prism3d bank train')")
    bank = FilterBank.load(path)
    bank_scale(bank)
    return bank


def load_aerial_model(path: str | Path) -> AerialModel:
    """An aerial recogniser (:class:`~prism3d.atr.aerial.AerialModel`); a ground-level model is
    refused with what to give instead."""
    kind = model_kind(path)
    if kind != "aerial_recogniser":
        raise InputError(f"{path}: {'not a prism3d model' if kind is None else 'a ' + kind + ' model'}, trained for "
                         "ground-level shots; survey-detect needs an aerial recogniser ('prism3d bank train --view nadir')")
    return AerialModel.load(path)
