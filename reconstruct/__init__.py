"""prism3d.reconstruct: three pipelines in three sub-packages, each importing only those
before it (tests/root/test_layers.py):

* ``stereo``: one prism shot to a scan: calibration, rectification, the matcher and its
  refinement, triangulation, meshing, the flatness (accuracy) test;
* ``scan``: scans to models: registration, ICP stitching, the object frame, fusion;
* ``survey``: drone frames to georeferenced products: poses (pycolmap), dense pairs with
  the stereo matcher, fusion, DSM, true orthophoto.

The names below load lazily, on first use."""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "Calibration": "stereo.calibrate",
    "calibrate_stereo": "stereo.calibrate",
    "calibrate_camera": "stereo.calibrate",
    "rectify_pair": "stereo.rectify",
    "rectify_shot": "stereo.rectify",
    "rectify_maps": "stereo.rectify",
    "match_stereo": "stereo.match",
    "match_stereo_full": "stereo.match",
    "match_files": "stereo.match",
    "StereoResult": "stereo.match",
    "score_disparity": "stereo.stereo_eval",
    "reconstruct_shot": "stereo.pipeline",
    "reconstruct_pair": "stereo.pipeline",
    "ReconstructOptions": "stereo.pipeline",
    "triangulate": "stereo.triangulate",
    "fit_plane": "stereo.flatness",
    "flatness_test": "stereo.flatness",
}

__all__ = sorted(_LAZY)  # noqa: PLE0605 - the lazily imported names, kept in one place


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'prism3d.reconstruct' has no attribute {name!r}")
    return getattr(importlib.import_module(f"prism3d.reconstruct.{mod}"), name)
