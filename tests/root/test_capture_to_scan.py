"""A full capture round trip through the CLI: simulated trigger controller on a real
pty, the virtual prism rig as the camera, then reconstruction of the captured shot."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from prism3d.capture.rig import paper_rig
from prism3d.capture.trigger_sim import TriggerSimulator


def test_capture_then_reconstruct(tmp_path):
    paper_rig().save(tmp_path / "rig.yaml")
    with TriggerSimulator() as sim:
        r = subprocess.run([sys.executable, "-m", "prism3d.cli", "--quiet", "capture", "--trigger", sim.port,
                            "--camera", "virtual", "-o", str(tmp_path / "shots"), "--calib",
                            str(tmp_path / "rig.yaml"), "--grab-timeout", "120"],
                           capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    shot = tmp_path / "shots" / "shot_000.png"
    assert shot.exists() and (tmp_path / "shots" / "shot_000.json").exists()
    r = subprocess.run([sys.executable, "-m", "prism3d.cli", "--quiet", "reconstruct", str(shot), "--calib",
                        str(tmp_path / "rig.yaml"), "-o", str(tmp_path / "scan.ply")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    from prism3d.io.ply import read_ply

    pts = read_ply(tmp_path / "scan.ply").points
    assert len(pts) > 100_000
    assert abs(np.median(pts[:, 2]) - 1250) < 15  # the plate at the working distance
