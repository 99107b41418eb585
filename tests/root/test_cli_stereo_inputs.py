"""Ordinary stereo rigs through the command line: reconstruct / rectify --left --right with
the calibration files people have, triangulate, convert-calib; and every bad input is one
line on stderr, exit code 2, nothing written."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from prism3d.cli import main
from prism3d.io.ply import read_ply

F, B, CX, CY = 400.0, 60.0, 95.5, 71.5
W, H = 192, 144


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.empty((h, w, 3), np.float32)
    for c in range(3):
        t = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.2)
        out[..., c] = 128 + 45 * t / t.std()
    return np.clip(out, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A rectified pair of a fronto-parallel textured plane at 1200 mm (disparity f B / z
    = 20 px) with a Middlebury calib.txt, a KITTI calib_cam_to_cam.txt and a ROS pair."""
    d = tmp_path_factory.mktemp("pair")
    disp = F * B / 1200.0
    scene = _texture(H, W + 40, 3)
    left = scene[:, 20:20 + W]
    right = scene[:, 20 + int(disp):20 + int(disp) + W]
    cv2.imwrite(str(d / "im0.png"), left[:, :, ::-1])
    cv2.imwrite(str(d / "im1.png"), right[:, :, ::-1])
    (d / "calib.txt").write_text(
        f"cam0=[{F} 0 {CX}; 0 {F} {CY}; 0 0 1]\ncam1=[{F} 0 {CX}; 0 {F} {CY}; 0 0 1]\n"
        f"doffs=0\nbaseline={B}\nwidth={W}\nheight={H}\nndisp=64\n")
    p2 = f"{F} 0 {CX} 0 0 {F} {CY} 0 0 0 1 0"
    p3 = f"{F} 0 {CX} {-F * B / 1000.0} 0 {F} {CY} 0 0 0 1 0"
    (d / "calib_cam_to_cam.txt").write_text(
        f"S_rect_02: {W} {H}\nP_rect_02: {p2}\nS_rect_03: {W} {H}\nP_rect_03: {p3}\n")
    for side, tx in (("left", 0.0), ("right", -F * B / 1000.0)):
        (d / f"{side}.yaml").write_text(
            f"image_width: {W}\nimage_height: {H}\ncamera_name: {side}\n"
            f"camera_matrix: {{rows: 3, cols: 3, data: [{F}, 0, {CX}, 0, {F}, {CY}, 0, 0, 1]}}\n"
            "distortion_model: plumb_bob\ndistortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n"
            "rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\n"
            f"projection_matrix: {{rows: 3, cols: 4, data: [{F}, 0, {CX}, {tx}, 0, {F}, {CY}, 0, 0, 0, 1, 0]}}\n")
    return {"dir": d, "disp": disp}


@pytest.mark.parametrize("calib", [["calib.txt"], ["calib_cam_to_cam.txt"], ["left.yaml", "right.yaml"]])
def test_two_file_reconstruct_with_each_format(pair: dict, tmp_path: Path, calib: list[str]) -> None:
    """The plane at 1200 mm comes back at 1200 mm from every calibration format."""
    d = pair["dir"]
    out = tmp_path / "scan.ply"
    rc = main(["-q", "reconstruct", "--left", str(d / "im0.png"), "--right", str(d / "im1.png"),
               "--calib", *[str(d / c) for c in calib], "-o", str(out), "--disparity-out", str(tmp_path / "d.pfm")])
    assert rc == 0
    ply = read_ply(out)
    z = ply.points[:, 2]
    assert len(z) > 0.8 * (W - 40) * (H - 20)
    assert abs(float(np.median(z)) - 1200.0) < 2.0
    assert {"confidence", "disparity_std", "depth_std"} <= set(ply.extra)


def test_triangulate_a_disparity_on_the_left_image_grid(pair: dict, tmp_path: Path) -> None:
    """A disparity map of the images as given (constant 20 px) with the pair's calib.txt:
    every pixel at f B / d = 1200 mm, like OpenCV's reprojectImageTo3D."""
    from prism3d.io.pfm import write_pfm

    d = pair["dir"]
    disp = np.full((H, W), pair["disp"], np.float32)
    disp[:5] = np.inf  # unknown
    write_pfm(tmp_path / "d.pfm", disp)
    out = tmp_path / "cloud.ply"
    assert main(["-q", "triangulate", str(tmp_path / "d.pfm"), "--calib", str(d / "calib.txt"),
                 "--left", str(d / "im0.png"), "-o", str(out)]) == 0
    pts = read_ply(out).points
    assert len(pts) == (H - 5) * W
    np.testing.assert_allclose(pts[:, 2], 1200.0, rtol=1e-5)
    # a pixel's ray: x = (u - cx) z / f
    assert abs(float(pts[:, 0].min()) - (0 - CX) * 1200.0 / F) < 1e-2


def test_rectify_two_files_and_convert_calib(pair: dict, tmp_path: Path) -> None:
    d = pair["dir"]
    assert main(["-q", "rectify", "--left", str(d / "im0.png"), "--right", str(d / "im1.png"),
                 "--calib", str(d / "calib.txt"), "-o", str(tmp_path / "rect")]) == 0
    assert sorted(p.name for p in (tmp_path / "rect").iterdir()) == ["left.png", "rectification.yaml", "right.png"]
    assert main(["-q", "convert-calib", str(d / "left.yaml"), str(d / "right.yaml"), "-o",
                 str(tmp_path / "c.yaml")]) == 0
    from prism3d.capture.rig import StereoRig

    rig = StereoRig.load(tmp_path / "c.yaml")
    assert rig.baseline_mm == pytest.approx(B) and rig.left.size == (W, H)


def _bad(args: list[str], capsys: pytest.CaptureFixture, match: str, out: Path) -> None:
    rc = main(args)
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and match in err, err
    assert not out.exists() and not list(out.parent.glob(f".{out.stem}*"))


@pytest.mark.parametrize("text, match", [
    (f"cam0=[{F} 0 {CX}; 0 {F} {CY}; 0 0 1]\nbaseline={B}\nwidth={W}\nheight={H}\n", "missing cam1"),
    (f"cam0=[{F} 0 {CX}; 0 {F} {CY}; 0 0 1]\ncam1=[{F} 0 {CX}; 0 {F} {CY}; 0 0 1]\nwidth={W}\nheight={H}\n",
     "missing baseline"),
    (f"cam0=[{F} 0 {CX}; 0 {F} {CY}]\ncam1=[{F} 0 {CX}; 0 {F} {CY}; 0 0 1]\nbaseline={B}\nwidth={W}\nheight={H}\n",
     "3x3"),
])
def test_bad_calib_txt(pair: dict, tmp_path: Path, capsys: pytest.CaptureFixture, text: str, match: str) -> None:
    d = pair["dir"]
    (tmp_path / "calib.txt").write_text(text)
    out = tmp_path / "scan.ply"
    _bad(["-q", "reconstruct", "--left", str(d / "im0.png"), "--right", str(d / "im1.png"), "--calib",
          str(tmp_path / "calib.txt"), "-o", str(out)], capsys, match, out)


def test_bad_kitti_and_ros_files(pair: dict, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    d = pair["dir"]
    kitti = tmp_path / "calib_cam_to_cam.txt"
    kitti.write_text((d / "calib_cam_to_cam.txt").read_text().replace("P_rect_03", "P_rect_99"))
    out = tmp_path / "scan.ply"
    args = ["-q", "reconstruct", "--left", str(d / "im0.png"), "--right", str(d / "im1.png"), "-o", str(out)]
    _bad([*args, "--calib", str(kitti)], capsys, "missing P_rect_03", out)
    ros = tmp_path / "right.yaml"
    ros.write_text((d / "right.yaml").read_text().replace("projection_matrix", "projection"))
    _bad([*args, "--calib", str(d / "left.yaml"), str(ros)], capsys, "projection_matrix", out)


def test_views_of_different_sizes_and_a_wrong_disparity(pair: dict, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    d = pair["dir"]
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), cv2.imread(str(d / "im1.png"))[:100, :150])
    out = tmp_path / "scan.ply"
    _bad(["-q", "reconstruct", "--left", str(d / "im0.png"), "--right", str(small), "--calib",
          str(d / "calib.txt"), "-o", str(out)], capsys, "same size", out)
    rect = tmp_path / "rect"
    _bad(["-q", "rectify", "--left", str(d / "im0.png"), "--right", str(small), "--calib",
          str(d / "calib.txt"), "-o", str(rect)], capsys, "same size", rect / "left.png")
    from prism3d.io.pfm import write_pfm

    write_pfm(tmp_path / "d.pfm", np.full((H - 10, W), 20.0, np.float32))
    cloud = tmp_path / "cloud.ply"
    _bad(["-q", "triangulate", str(tmp_path / "d.pfm"), "--calib", str(d / "calib.txt"), "--left",
          str(d / "im0.png"), "-o", str(cloud)], capsys, "disparity is", cloud)
    # a shot and --left together, and neither
    _bad(["-q", "reconstruct", str(d / "im0.png"), "--left", str(d / "im0.png"), "--calib",
          str(d / "calib.txt"), "-o", str(out)], capsys, "not both", out)
    _bad(["-q", "reconstruct", "--calib", str(d / "calib.txt"), "-o", str(out)], capsys, "both --left and --right",
         out)
