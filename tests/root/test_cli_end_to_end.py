"""Every CLI command on a tiny fixture, in tmp_path (OpenSfM's test_run_all);
:data:`COMMANDS` is checked against the parser.

A quarter-size paper rig (648x486 sensor, f = 1277 px) keeps it fast.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
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


@pytest.fixture(scope="module")
def stereo(plate, tmp_path_factory) -> Path:
    """rectify -> match -> reconstruct on the plate shot; the outputs other commands read."""
    out = tmp_path_factory.mktemp("stereo")
    r = prism3d("rectify", plate / "shot.png", "--calib", plate / "rig.yaml", "-o", out / "rect")
    assert r.returncode == 0, r.stderr
    # the plate at 1250 mm has disparity f*B/z ~ 202 px on this rig
    r = prism3d("match", out / "rect" / "left.png", out / "rect" / "right.png",
                "-o", out / "d.pfm", "--min-disp", "170", "--num-disp", "64", "--sparse")
    assert r.returncode == 0, r.stderr
    r = prism3d("reconstruct", plate / "shot.png", "--calib", plate / "rig.yaml", "-o", out / "scan.ply",
                "--disparity-out", out / "disp.pfm", "--depth-out", out / "depth.tiff",
                "--mesh", out / "mesh.ply")
    assert r.returncode == 0, r.stderr
    return out


def test_rectify_match_reconstruct_flatness(plate, stereo):
    assert (stereo / "rect" / "left.png").exists()
    from prism3d.io.pfm import read_pfm

    d = read_pfm(stereo / "d.pfm")
    with np.load(plate / "truth.npz", allow_pickle=False) as t:
        truth = t["disparity_rect"]
    both = np.isfinite(d) & np.isfinite(truth)
    assert both.sum() > 0.8 * np.isfinite(truth).sum()  # the plate is matched
    assert np.median(np.abs(d[both] - truth[both])) < 0.1  # ~202 px, sub-pixel accurate
    for f in ("scan.ply", "disp.pfm", "depth.tiff", "mesh.ply"):
        assert (stereo / f).exists(), f
    from prism3d.io.hashes import sha256_file
    from prism3d.io.ply import read_ply

    header = read_ply(stereo / "scan.ply").comments  # the scan says what it came from
    assert f"shot_sha256 {sha256_file(plate / 'shot.png')}" in header
    assert f"calibration_sha256 {sha256_file(plate / 'rig.yaml')}" in header
    r = prism3d("flatness", stereo / "scan.ply", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert set(rep["regions"]) == {"upper_left", "upper_right", "centre", "lower_left", "lower_right"}
    # smoke test on a 4x coarser rig (6.2 mm per px of disparity, pattern aliased at 1x
    # sampling); the paper-rig accuracy is asserted by the Table I tests
    assert rep["mean_rms_mm"] < 0.3 * rep["resolution_mm_per_px"]


def test_triangulate_matches_reconstruct(plate, stereo, tmp_path):
    """The matcher's disparity -> cloud: the plate at its simulated distance."""
    from prism3d.io.ply import read_ply

    r = prism3d("triangulate", stereo / "d.pfm", "--calib", plate / "rig.yaml", "--left",
                stereo / "rect" / "left.png", "-o", tmp_path / "cloud.ply")
    assert r.returncode == 0, r.stderr
    pts = read_ply(tmp_path / "cloud.ply").points
    scan = read_ply(stereo / "scan.ply").points
    assert len(pts) > 0.5 * len(scan)
    assert np.median(pts[:, 2]) == pytest.approx(np.median(scan[:, 2]), abs=5.0)


def test_convert_calib_reads_a_middlebury_file(tmp_path):
    (tmp_path / "calib.txt").write_text(
        "cam0=[1000 0 320; 0 1000 240; 0 0 1]\ncam1=[1000 0 330; 0 1000 240; 0 0 1]\n"
        "doffs=10\nbaseline=120.5\nwidth=640\nheight=480\nndisp=128\n")
    r = prism3d("convert-calib", tmp_path / "calib.txt", "-o", tmp_path / "c.yaml")
    assert r.returncode == 0, r.stderr
    from prism3d.capture.rig import StereoRig

    rig = StereoRig.load(tmp_path / "c.yaml")
    assert rig.baseline_mm == pytest.approx(120.5)
    assert rig.left.K[0, 0] == pytest.approx(1000.0) and rig.right.K[0, 2] == pytest.approx(330.0)


def _surface_patch(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A bumpy 200 x 200 mm patch 600 mm in front of the camera, with normals to -z."""
    xy = rng.uniform(-100.0, 100.0, (n, 2))
    z = 600.0 + 15.0 * np.sin(xy[:, 0] / 17.0) * np.cos(xy[:, 1] / 23.0)
    gx = 15.0 / 17.0 * np.cos(xy[:, 0] / 17.0) * np.cos(xy[:, 1] / 23.0)
    gy = -15.0 / 23.0 * np.sin(xy[:, 0] / 17.0) * np.sin(xy[:, 1] / 23.0)
    N = np.c_[gx, gy, -np.ones(n)]
    return np.c_[xy, z], N / np.linalg.norm(N, axis=1, keepdims=True)


def test_stitch_recovers_a_known_motion(tmp_path):
    from prism3d.geometry import make_transform, rotation_about, rotation_angle_deg, transform_points
    from prism3d.io.ply import write_ply

    rng = np.random.default_rng(3)
    P, N = _surface_patch(30000, rng)
    T = make_transform(rotation_about([0.2, 1.0, 0.1], np.radians(4.0)), [6.0, -3.0, 4.0])
    write_ply(tmp_path / "a.ply", P, normals=N)
    write_ply(tmp_path / "b.ply", transform_points(T, P), normals=N @ T[:3, :3].T)
    r = prism3d("stitch", tmp_path / "a.ply", tmp_path / "b.ply", "-o", tmp_path / "model.ply")
    assert r.returncode == 0, r.stderr
    poses = json.loads((tmp_path / "poses.json").read_text())
    Ts = [np.asarray(p["T_model_scan"], dtype=float) for p in poses["scans"]]
    T_ab = np.linalg.inv(Ts[0]) @ Ts[1]  # scan b's points into scan a's frame: inverse of T
    assert rotation_angle_deg(T_ab @ T) < 0.05
    assert np.linalg.norm((T_ab @ T)[:3, 3]) < 0.2
    assert (tmp_path / "model.ply").exists()


def test_decamo_on_a_reconstructed_shot(plate, tmp_path):
    r = prism3d("decamo", plate / "shot.png", "--calib", plate / "rig.yaml", "-o", tmp_path / "dc")
    assert r.returncode == 0, r.stderr
    from prism3d.io.images import read_image

    albedo = read_image(tmp_path / "dc" / "albedo.png")
    assert albedo.ndim == 3 and albedo.std() > 0
    assert (tmp_path / "dc" / "shape.png").exists() and (tmp_path / "dc" / "false_shadow.png").exists()


def test_features_of_a_scan(stereo, tmp_path):
    import pandas as pd

    r = prism3d("features", stereo / "scan.ply", "--units", "mm", "--up", "y", "--box", "points",
                "-o", tmp_path / "f.parquet")
    assert r.returncode == 0, r.stderr
    df = pd.read_parquet(tmp_path / "f.parquet")
    assert len(df) == 1
    # the simulated plate is 240 mm wide in this rig's field (length is its longer side)
    assert df["length_mm"].iloc[0] > 100.0


def test_render_a_builtin_target(tmp_path):
    import pandas as pd

    r = prism3d("render", "tank_t1", "-o", tmp_path / "chips", "--azimuth", "0:90:45", "--elevation", "20:20:1",
                "--range", "3000", "--size", "32", "--format", "npz")
    assert r.returncode == 0, r.stderr
    manifest = next((tmp_path / "chips").glob("*.parquet"))
    assert len(pd.read_parquet(manifest)) == 3  # azimuths 0, 45, 90 (end included) at one elevation and range


def test_bank_train_and_eval(tmp_path):
    r = prism3d("bank", "train", "--scenes", "0", "--targets", "tank_t1", "jet_j1", "-o", tmp_path / "bank.npz",
                "--azimuth", "0:360:45", "--elevation", "20:20:1", "--size", "32", "--no-camouflage")
    assert r.returncode == 0, r.stderr
    r = prism3d("bank", "eval", tmp_path / "bank.npz", "--targets", "tank_t1", "jet_j1",
                "--azimuth", "0:360:45", "--elevation", "20:20:1", "--json", tmp_path / "res.json")
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "res.json").read_text())
    assert res["pcc"] > 0.5  # two very different classes


def test_db_init_add_render_features_info_verify(tmp_path):
    db = tmp_path / "db"
    for args in (["init", db], ["add", db, "--builtin", "tank_t1", "jet_j1"],
                 ["render", db, "--job", "j", "--azimuth", "0:90:90", "--elevation", "20:20:1",
                  "--range", "3000", "--size", "32"],
                 ["features", db, "--job", "j"], ["verify", db]):
        r = prism3d("db", *args)
        assert r.returncode == 0, (args, r.stderr)
    r = prism3d("db", "info", db, "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["targets"] == 2 and info["targets_per_class"] == {"tank": 1, "jet": 1}
    assert set(info["jobs"]) == {"j"}


def test_trigger_simulate_then_ping_status_fire(tmp_path):
    with subprocess.Popen([sys.executable, "-m", "prism3d.cli", "trigger", "simulate"],
                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True) as proc:
        try:
            port = proc.stdout.readline().strip()
            assert port.startswith("/dev/"), port
            for action in ("ping", "status", "fire"):
                r = prism3d("trigger", action, port, "--timeout", "5")
                assert r.returncode == 0, (action, r.stderr)
        finally:
            proc.terminate()
            proc.wait(timeout=30)


def test_capture_with_the_virtual_camera(tmp_path):
    """The virtual camera is the paper's rig (tests/root/test_capture_to_scan.py also
    reconstructs its shot)."""
    from prism3d.capture.trigger_sim import TriggerSimulator

    with TriggerSimulator() as sim:
        r = prism3d("capture", "--trigger", sim.port, "--camera", "virtual", "-o", tmp_path / "shots",
                    "--grab-timeout", "120")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "shots" / "shot_000.png").exists() and (tmp_path / "shots" / "shot_000.json").exists()


def test_demo_one_stage(tmp_path):
    r = prism3d("demo", tmp_path / "demo", "--fast", "--only", "environment")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "demo" / "report.html").exists()


#: every command of `prism3d --help` and the test that runs it
COMMANDS = {
    "demo": "test_demo_one_stage",
    "simulate": "test_simulate_writes_the_contract",
    "calibrate": "test_calibrate_from_simulated_shots",
    "convert-calib": "test_convert_calib_reads_a_middlebury_file",
    "rectify": "test_rectify_match_reconstruct_flatness",
    "match": "test_rectify_match_reconstruct_flatness",
    "reconstruct": "test_rectify_match_reconstruct_flatness",
    "triangulate": "test_triangulate_matches_reconstruct",
    "flatness": "test_rectify_match_reconstruct_flatness",
    "stitch": "test_stitch_recovers_a_known_motion",
    "decamo": "test_decamo_on_a_reconstructed_shot",
    "features": "test_features_of_a_scan",
    "render": "test_render_a_builtin_target",
    "bank": "test_bank_train_and_eval",
    "detect": "test_detect_on_an_image_and_depth_map",
    "db": "test_db_init_add_render_features_info_verify",
    "trigger": "test_trigger_simulate_then_ping_status_fire",
    "capture": "test_capture_with_the_virtual_camera",
    "survey": "test_simulate_flight_survey_and_survey_detect",
    "survey-detect": "test_simulate_flight_survey_and_survey_detect",
}


def test_simulate_flight_survey_and_survey_detect(tmp_path):
    """A small flight (6 frames on two lines, 480 x 360 px) surveyed with its GPS table
    and calibration, then searched for vehicles: the products and a WGS84 GeoJSON."""
    r = prism3d("simulate", "flight", tmp_path / "f", "--frames", "6", "--size", "480x360", "--altitude", "40",
                "--no-depth", "--seed", "2")
    assert r.returncode == 0, r.stderr
    frames = sorted((tmp_path / "f").glob("IMG_*.JPG"))
    assert len(frames) == 6
    r = prism3d("survey", *frames, "--calib", tmp_path / "f" / "camera.yaml", "--gps", tmp_path / "f" / "geoinfo.txt",
                "-o", tmp_path / "s")
    assert r.returncode == 0, r.stderr
    for name in ("poses.json", "cloud.ply", "cloud.las", "dsm.tif", "ndsm.tif", "ortho.tif"):
        assert (tmp_path / "s" / name).is_file(), name
    assert json.loads((tmp_path / "s" / "poses.json").read_text())["scale"] == "gps"
    r = prism3d("survey-detect", tmp_path / "s", "-o", tmp_path / "d.geojson")
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "d.geojson").read_text())["type"] == "FeatureCollection"


def test_every_command_has_an_end_to_end_test():
    """A new command without a run here fails: the list is checked against the parser."""
    from prism3d.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(COMMANDS) == set(sub.choices)
    for name in COMMANDS.values():
        assert callable(globals().get(name)), name


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
        (["render", "tank_t1", "-o", "chips", "--size", "60000"], "4096 px"),
        (["features", "nope.ply", "-o", "f.csv"], r"f.csv: .*Parquet"),
        (["render", "tank_t1", "-o", "chips", "--azimuth", "nan"], "finite"),
        (["render", "tank_t1", "-o", "chips", "--azimuth", "0:360:1e-7"], "use a larger STEP"),
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


def test_absurd_numbers_on_real_outputs_are_one_line(stereo, tmp_path):
    """Numbers that used to give a wrong result or a traceback: a non-positive focal
    length in the flatness test, a voxel far below the points' spacing in stitch."""
    r = prism3d("flatness", stereo / "scan.ply", "--focal", "-5")
    assert r.returncode == 2 and "focal_px: expected a finite number > 0" in r.stderr
    r = prism3d("stitch", stereo / "scan.ply", stereo / "scan.ply", "-o", tmp_path / "m.ply", "--voxel", "1e-9")
    assert r.returncode == 2 and "too small for scans" in r.stderr and "Traceback" not in r.stderr
    r = prism3d("stitch", stereo / "scan.ply", stereo / "scan.ply", "-o", tmp_path / "m.pcd")
    assert r.returncode == 2 and "m.pcd: the model and mesh are written as PLY" in r.stderr
    assert list(tmp_path.iterdir()) == []


def test_match_rejects_bad_num_disp(plate, tmp_path):
    r = prism3d("match", plate / "shot.png", plate / "shot.png", "-o", tmp_path / "d.pfm", "--num-disp", "0")
    assert r.returncode == 2 and "num_disp" in r.stderr
    assert not (tmp_path / "d.pfm").exists()


def test_output_under_a_file_is_one_line_exit_2(plate, stereo, tmp_path):
    """The file system refusing an output (here: a folder that is a file) is a user
    error like any other: one line naming the path, exit 2, no traceback, nothing written."""
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    for args in (["features", stereo / "scan.ply", "--units", "mm", "--up", "y", "-o", blocker / "f.parquet"],
                 ["reconstruct", plate / "shot.png", "--calib", plate / "rig.yaml", "-o", blocker / "s.ply"]):
        r = prism3d(*args)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "not_a_dir" in lines[0] and "Traceback" not in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["not_a_dir"]


def test_calibrate_refuses_the_same_image_twice(tmp_path, plate):
    """The same shot given three times returned a 312.8 mm baseline (true 197.9)."""
    import shutil

    shutil.copy(plate / "shot.png", tmp_path / "copy.png")
    r = prism3d("calibrate", plate / "shot.png", tmp_path / "copy.png", "-o", tmp_path / "c.yaml")
    assert r.returncode == 2 and "the same image as" in r.stderr and "give each board pose once" in r.stderr
    assert not (tmp_path / "c.yaml").exists()


def test_detect_on_an_image_and_depth_map(tmp_path):
    """`detect --image --depth --fx` on a small field scene's left view and true depth:
    detections in the contract; a depth map of another size is one line, exit 2."""
    import json

    import numpy as np

    from prism3d.capture.rig import StereoRig
    from prism3d.datasets.simulation.field import FieldOptions, simulate_field
    from prism3d.io.images import read_image, write_image

    scene = tmp_path / "field"
    simulate_field(scene, FieldOptions(seed=5, targets=2, confusers=0, clutter=5, sensor_size=(720, 540),
                                       focal_px=600.0))
    rig = StereoRig.load(scene / "rig.yaml")
    left = rig.split.split(read_image(scene / "shot.png"))[0]
    write_image(tmp_path / "left.png", left)
    r = prism3d("bank", "train", "--scenes", "0", "--targets", "tank_t1", "truck_k1", "--azimuth", "0:360:60", "--bin-deg", "60",
                "--channel", "depth", "-o", tmp_path / "b.npz")
    assert r.returncode == 0, r.stderr
    r = prism3d("detect", "--image", tmp_path / "left.png", "--depth", f"{scene / 'truth.npz'}:depth_left_mm",
                "--fx", rig.left.fx, "--bank", tmp_path / "b.npz", "-o", tmp_path / "det.json")
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "det.json").read_text())
    scores = [d["score"] for d in doc["detections"]]
    assert scores == sorted(scores, reverse=True)
    assert all(d["class"] in ("tank", "truck") for d in doc["detections"])
    np.save(tmp_path / "small.npy", np.ones((10, 10), dtype=np.float32))
    r = prism3d("detect", "--image", tmp_path / "left.png", "--depth", tmp_path / "small.npy", "--fx", "600",
                "--bank", tmp_path / "b.npz", "-o", tmp_path / "det2.json")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "det2.json").exists()


@pytest.mark.parametrize("sig, code, word", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_a_signal_mid_run_leaves_nothing_behind(tmp_path, monkeypatch, capsys, sig, code, word):
    """SIGTERM unwinds like Ctrl-C: a command signalled while it writes its staged outputs
    says so in one line, exits 143 (130 for SIGINT), and leaves no output, staging folder
    or lock; the caller's own SIGTERM handler is back afterwards."""
    import os

    import prism3d.cli as cli
    from prism3d.io.atomic import staged_folder

    work = tmp_path / "w"
    work.mkdir()
    seen = []

    def writes_then_is_signalled(args):
        with staged_folder(work / "f") as stage:
            (stage / "half.bin").write_bytes(b"x" * 1000)
            seen.append(sorted(p.name for p in work.iterdir()))
            os.kill(os.getpid(), sig)
            time.sleep(5)  # the handler interrupts this
        return 0

    monkeypatch.setattr(cli, "_cmd_simulate_field", writes_then_is_signalled)
    before = signal.getsignal(signal.SIGTERM)
    old_int = signal.signal(signal.SIGINT, signal.default_int_handler)  # as an interactive run has it
    try:
        rc = cli.main(["simulate", "field", str(work / "f")])
    finally:
        signal.signal(signal.SIGINT, old_int)
    err = capsys.readouterr().err.strip().splitlines()
    assert seen and any(n.endswith(".tmp") for n in seen[0]) and ".f.lock" in seen[0]  # it was writing
    assert rc == code and err[-1].endswith(word) and "Traceback" not in "\n".join(err)
    assert list(work.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before


def test_two_writers_of_one_output_folder(tmp_path):
    """A command into a folder another process is writing is refused with one line and
    touches nothing; the writer's output then appears whole."""
    out = tmp_path / "f"
    go = tmp_path / "go"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import pathlib, sys, time\n"
        "from prism3d.io.atomic import staged_folder\n"
        f"with staged_folder({str(out)!r}) as st:\n"
        "    (st / 'a.txt').write_text('first')\n"
        f"    while not pathlib.Path({str(go)!r}).exists():\n"
        "        time.sleep(0.05)\n")])
    lock = tmp_path / ".f.lock"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not lock.exists():
        time.sleep(0.05)
    second = subprocess.run([sys.executable, "-m", "prism3d.cli", "-q", "simulate", "field", str(out)],
                            capture_output=True, text=True, timeout=300)
    go.write_text("")
    assert holder.wait(timeout=60) == 0
    assert second.returncode == 2 and "is writing it" in second.stderr, second.stderr
    assert len(second.stderr.strip().splitlines()) == 1
    assert [p.name for p in out.iterdir()] == ["a.txt"] and (out / "a.txt").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f", "go"]


def test_sigterm_after_the_outputs_are_in_place_keeps_the_exit_code(tmp_path):
    """A SIGTERM while the interpreter tears down (up to a second with numba and Dask
    loaded), after ``main`` returned: the process ends with ``main``'s code, not killed by
    the signal (a caller would take the finished outputs for lost)."""
    script = ("import os, signal, sys, time\n"
              "sys.argv = ['prism3d']\n"  # prints the help and returns 2
              "from prism3d.cli import run\n"
              "run()\n"
              "os.kill(os.getpid(), signal.SIGTERM)\n"
              "time.sleep(5)\n"
              "sys.exit(9)\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, (r.returncode, r.stderr)
