"""Every CLI command on a tiny fixture, in tmp_path (OpenSfM's test_run_all).

A quarter-size paper rig (648x486 sensor, f = 1277 px) keeps it fast.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prism3d.capture.rig import paper_rig


def prism3d(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "prism3d.cli", "--quiet", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def small_rig(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("rig")
    paper_rig(sensor_size=(648, 486), focal_px=5107.0 / 4).save(d / "rig.yaml")
    return d / "rig.yaml"


@pytest.fixture(scope="module")
def plate(tmp_path_factory, small_rig) -> Path:
    out = tmp_path_factory.mktemp("plate")
    r = prism3d("simulate", "plate", out, "--rig", small_rig, "--supersample", "1")
    assert r.returncode == 0, r.stderr
    return out


def test_simulate_writes_the_contract(plate):
    import cv2

    assert (plate / "shot.png").exists() and (plate / "rig.yaml").exists()
    with np.load(plate / "truth.npz", allow_pickle=False) as t:
        for k in ("depth_left_mm", "depth_right_mm", "mask_left", "albedo_left", "shading_left"):
            assert k in t.files, k
        assert t["depth_left_mm"].dtype == np.float32
    fs = cv2.FileStorage(str(plate / "rig.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("K1").mat().shape == (3, 3)
    fs.release()


def test_rectify_match_reconstruct_flatness(plate, tmp_path):
    r = prism3d("rectify", plate / "shot.png", "--calib", plate / "rig.yaml", "-o", tmp_path / "rect")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "rect" / "left.png").exists()
    # the plate at 1250 mm has disparity f*B/z ~ 202 px on this rig
    r = prism3d("match", tmp_path / "rect" / "left.png", tmp_path / "rect" / "right.png",
                "-o", tmp_path / "d.pfm", "--min-disp", "170", "--num-disp", "64", "--sparse")
    assert r.returncode == 0, r.stderr
    from prism3d.io.pfm import read_pfm

    d = read_pfm(tmp_path / "d.pfm")
    with np.load(plate / "truth.npz", allow_pickle=False) as t:
        truth = t["disparity_rect"]
    both = np.isfinite(d) & np.isfinite(truth)
    assert both.sum() > 0.8 * np.isfinite(truth).sum()  # the plate is matched
    assert np.median(np.abs(d[both] - truth[both])) < 0.1  # ~202 px, sub-pixel accurate
    r = prism3d("reconstruct", plate / "shot.png", "--calib", plate / "rig.yaml", "-o", tmp_path / "scan.ply",
                "--disparity-out", tmp_path / "disp.pfm", "--depth-out", tmp_path / "depth.tiff",
                "--mesh", tmp_path / "mesh.ply")
    assert r.returncode == 0, r.stderr
    for f in ("scan.ply", "disp.pfm", "depth.tiff", "mesh.ply"):
        assert (tmp_path / f).exists(), f
    r = prism3d("flatness", tmp_path / "scan.ply", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert set(rep["regions"]) == {"upper_left", "upper_right", "centre", "lower_left", "lower_right"}
    # smoke test on a 4x coarser rig (6.2 mm per px of disparity, pattern aliased at 1x
    # sampling); the paper-rig accuracy is asserted by the Table I tests
    assert rep["mean_rms_mm"] < 0.3 * rep["resolution_mm_per_px"]


def test_calibrate_from_simulated_shots(tmp_path, small_rig):
    r = prism3d("simulate", "calib", tmp_path / "cal", "--rig", small_rig, "--supersample", "1")
    assert r.returncode == 0, r.stderr
    shots = sorted((tmp_path / "cal").glob("calib_*.png"))
    r = prism3d("calibrate", *shots, "-o", tmp_path / "calib.yaml", "--no-tangential")
    assert r.returncode == 0, r.stderr
    from prism3d.capture.rig import StereoRig

    rig = StereoRig.load(tmp_path / "calib.yaml")
    assert rig.baseline_mm == pytest.approx(197.9, rel=0.01)


def test_simulate_blur_option(tmp_path, small_rig):
    from prism3d.io.images import read_image

    sharp = []
    for blur in ("0", "1.5"):
        out = tmp_path / f"b{blur}"
        r = prism3d("simulate", "plate", out, "--rig", small_rig, "--supersample", "1", "--no-noise",
                    "--blur", blur)
        assert r.returncode == 0, r.stderr
        img = read_image(out / "shot.png").astype(float)
        sharp.append(np.mean(np.abs(np.diff(img, axis=1))))
    assert sharp[1] < 0.7 * sharp[0]  # the lens PSF smooths the stripes' edges


def test_simulate_calib_board_option(tmp_path, small_rig):
    r = prism3d("simulate", "calib", tmp_path, "--rig", small_rig, "--supersample", "1", "--views", "1",
                "--board", "12x8", "--square", "15")
    assert r.returncode == 0, r.stderr
    t = np.load(tmp_path / "truth_00.npz")
    assert t["corners_left"].shape == (96, 2) and np.isfinite(t["corners_left"]).all()
    assert t["board_inner_corners"].tolist() == [12, 8] and float(t["board_square_mm"]) == 15.0
    # adjacent true corners are one square apart on the board
    np.testing.assert_allclose(np.diff(t["board_corners_mm"][:2, 0]), [15.0])


@pytest.mark.parametrize(
    "args, match",
    [
        (["reconstruct", "nope.png", "--calib", "nope.yaml", "-o", "x.ply"], "not found"),
        (["match", "a.png", "b.png", "-o", "d.pfm", "--num-disp", "16"], "not found"),
        (["flatness", "nope.ply"], "not found"),
        (["calibrate", "nope.png", "-o", "c.yaml"], "not found|no such"),
        (["simulate", "scene", "out", "--target", "nope"], "unknown built-in target"),
        (["simulate", "calib", "out", "--board", "9"], "--board"),
        (["simulate", "calib", "out", "--square", "-3"], "square"),
        (["simulate", "plate", "out", "--blur", "-1"], "blur"),
        (["rectify", "nope.png", "--calib", "nope.yaml", "-o", "out"], "not found"),
    ],
)
def test_bad_input_exit_2_one_line(tmp_path, args, match):
    r = subprocess.run([sys.executable, "-m", "prism3d.cli", *args], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0]
    import re

    assert re.search(match, lines[0], re.I), lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written


def test_reconstruct_rejects_wrong_shot_size(plate, tmp_path):
    from prism3d.io.images import write_image

    write_image(tmp_path / "small.png", np.zeros((100, 200, 3), np.uint8))
    r = prism3d("reconstruct", tmp_path / "small.png", "--calib", plate / "rig.yaml", "-o", tmp_path / "s.ply")
    assert r.returncode == 2 and "sensor" in r.stderr
    assert not (tmp_path / "s.ply").exists()


def test_match_rejects_bad_num_disp(plate, tmp_path):
    r = prism3d("match", plate / "shot.png", plate / "shot.png", "-o", tmp_path / "d.pfm", "--num-disp", "0")
    assert r.returncode == 2 and "num_disp" in r.stderr
    assert not (tmp_path / "d.pfm").exists()
