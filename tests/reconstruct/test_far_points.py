"""Two-camera pairs searched down to disparity 0 (infinity): what cannot be told from
infinity is dropped and counted, on KITTI's real street scene and on a synthetic pair with
a wall at a known distance in front of an empty sky."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from prism3d.cli import main
from prism3d.io.ply import read_ply

#: KITTI's rectified colour cameras, devkit calibration of the 2011_09_26 drives (P_rect_02,
#: P_rect_03 as calib_cam_to_cam.txt gives them).
KITTI_CALIB = ("S_rect_02: 1242 375\n"
               "P_rect_02: 721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884\n"
               "S_rect_03: 1242 375\n"
               "P_rect_03: 721.5377 0 609.5593 -339.5242 0 721.5377 172.854 2.199936 0 0 1 0.002729905\n")


@pytest.mark.realdata
def test_kitti_keeps_no_point_beyond_what_its_disparities_can_tell(shared_data: Path, tmp_path: Path, capsys) -> None:
    """Before: points up to 14,000 km (9 % beyond 100 m). Now every point within the range
    the calibration and the matcher's precision give (f B / 3 median stds, about 590 m),
    the drop counted in the summary, and the crossing car still at its 11-15 m."""
    from prism3d.reconstruct.stereo.pipeline import FAR_SIGMAS

    k = shared_data / "stereo/kitti2015_sample"
    cal = tmp_path / "calib_cam_to_cam.txt"
    cal.write_text(KITTI_CALIB)
    out = tmp_path / "scan.ply"
    assert main(["reconstruct", "--left", str(k / "image_2_000046_10.png"), "--right", str(k / "image_3_000046_10.png"),
                 "--calib", str(cal), "-o", str(out), "--depth-out", str(tmp_path / "d.npy")]) == 0
    said = capsys.readouterr().out
    assert "too far to measure" in said
    ply = read_ply(out)
    z = ply.points[:, 2]
    std = np.asarray(ply.extra["disparity_std"])
    est = np.asarray(ply.extra["measured"]) == 0  # every point says whether it was matched
    assert 0.1 < est.mean() < 0.4
    fb = 721.5377 * 537.2  # f (px) x baseline (mm)
    assert (fb / z >= FAR_SIGMAS * std - 1e-3).all()  # each point 3 of its stds from infinity
    assert z.max() < 1_000_000 and (z > 100_000).mean() < 0.09
    depth = np.load(tmp_path / "d.npy")
    car = depth[185:262, 615:835]
    assert 11_000 < np.nanmedian(car) < 15_000
    # The sky (sky-blue, smooth pixels joined to the top row): 20.5 % of it had a depth
    # (5 % matched by chance in its faint gradient, 15 % extended from the tree tops);
    # measured 3.6 % after the isolation and enclosure rules.
    assert np.isfinite(depth[_sky_mask(k / "image_2_000046_10.png")]).mean() < 0.05


def _sky_mask(path: Path) -> np.ndarray:
    from prism3d.io.images import read_image
    from prism3d.reconstruct.stereo.stereo_eval import sky_mask

    sky = sky_mask(read_image(path))
    assert sky.sum() > 50_000  # the mask found the sky
    return sky


def test_a_far_background_is_dropped_and_the_wall_stays(tmp_path: Path) -> None:
    """A textured wall at 4 m (15 px) over the lower half, a textured background 600 m away
    (0.1 px) over the upper half: the wall at 4 m; the background, which no disparity
    search can tell from infinity at this precision, gives no point (it came back at
    hundreds of metres to kilometres before)."""
    import cv2

    W, H, F, B = 640, 480, 500.0, 120.0
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.random((H, W + 40)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 30, 220, cv2.NORM_MINMAX)

    def shifted(d: float) -> np.ndarray:  # the texture moved d px left, sub-pixel
        return cv2.warpAffine(tex, np.float32([[1, 0, -d], [0, 1, 0]]), (W + 40, H), flags=cv2.INTER_CUBIC)

    left, right = tex[:, 20:20 + W].copy(), np.empty((H, W), np.float32)
    right[H // 2:] = shifted(F * B / 4000.0)[H // 2:, 20:20 + W]
    right[:H // 2] = shifted(F * B / 600_000.0)[:H // 2, 20:20 + W]
    for name, img in (("l.png", left), ("r.png", right)):
        noisy = img + rng.normal(0, 0.5, img.shape)
        cv2.imwrite(str(tmp_path / name), np.clip(noisy, 0, 255).astype(np.uint8))
    cx, cy = (W - 1) / 2, (H - 1) / 2
    (tmp_path / "calib.txt").write_text(
        f"cam0=[{F} 0 {cx}; 0 {F} {cy}; 0 0 1]\ncam1=[{F} 0 {cx}; 0 {F} {cy}; 0 0 1]\n"
        f"doffs=0\nbaseline={B}\nwidth={W}\nheight={H}\n")
    out = tmp_path / "s.ply"
    assert main(["-q", "reconstruct", "--left", str(tmp_path / "l.png"), "--right", str(tmp_path / "r.png"),
                 "--calib", str(tmp_path / "calib.txt"), "--min-disp", "0", "--num-disp", "32", "-o", str(out)]) == 0
    ply = read_ply(out)
    z = ply.points[:, 2]
    wall = np.abs(z - 4000.0) < 100.0
    assert wall.sum() > 0.8 * (W - 40) * H / 2 and abs(float(np.median(z[wall])) - 4000.0) < 20.0
    assert z.max() < 100_000.0, np.sort(z)[-5:]
