"""The README's Python example runs as printed, on a small simulated plate shot."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import numpy as np

from prism3d.capture.rig import paper_rig
from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
from prism3d.io.ply import read_ply

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_python_example(tmp_path: Path) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S)
    assert len(blocks) == 1
    rig = paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4)
    simulate_to_folder("plate", tmp_path / "sim", SimulateOptions(supersample=1), rig=rig)
    shutil.copy(tmp_path / "sim" / "shot.png", tmp_path / "shot.png")
    shutil.copy(tmp_path / "sim" / "rig.yaml", tmp_path / "calib.yaml")
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        scope: dict = {}
        exec(compile(blocks[0], "README.md", "exec"), scope)
    finally:
        os.chdir(cwd)
    ply = read_ply(tmp_path / "scan.ply")
    assert len(ply.points) == len(scope["points"]) > 1000
    assert "confidence" in ply.extra and np.all(ply.extra["confidence"] >= 0.5)
    assert abs(np.median(ply.points[:, 2]) - 1250.0) < 15.0  # the plate at the working distance
