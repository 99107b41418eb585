"""prism3d.reconstruct: calibration, rectification, stereo matching, triangulation,
meshing, ICP stitching and the accuracy test (names below load lazily, on first use)."""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "Calibration": "calibrate",
    "calibrate_stereo": "calibrate",
    "calibrate_camera": "calibrate",
    "rectify_pair": "rectify",
    "rectify_shot": "rectify",
    "rectify_maps": "rectify",
    "match_stereo": "match",
    "match_stereo_full": "match",
    "match_files": "match",
    "StereoResult": "match",
    "score_disparity": "stereo_eval",
    "reconstruct_shot": "pipeline",
    "reconstruct_pair": "pipeline",
    "ReconstructOptions": "pipeline",
    "triangulate": "triangulate",
    "fit_plane": "flatness",
    "flatness_test": "flatness",
}

__all__ = sorted(_LAZY)  # noqa: PLE0605 - the lazily imported names, kept in one place


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'prism3d.reconstruct' has no attribute {name!r}")
    return getattr(importlib.import_module(f"prism3d.reconstruct.{mod}"), name)
