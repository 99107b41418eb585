"""Execute every notebook in notebooks/ headless (nbclient, kernel python3, 120 s per cell)."""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=120, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors
    figures = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
               if "image/png" in o.get("data", {})]
    if path.stem == "recognition_evaluation":  # its chips, confusion matrices, ROC... drawn inline
        assert len(figures) >= 5, len(figures)
    if path.stem == "scanned_targets":  # matrices side by side, mask IoU, two ROCs
        assert len(figures) >= 4, len(figures)
    if path.stem == "scene_detection":  # the recorded Pd-FPPI curves and the live scene
        assert len(figures) >= 2, len(figures)
