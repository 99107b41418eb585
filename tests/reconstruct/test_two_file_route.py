"""The two-file route on real data: OpenCV's stereo chessboard set (9x6 inner corners,
25 mm squares, 13 pairs) calibrated with ``prism3d calibrate --pairs``, then pair 03
reconstructed with ``prism3d reconstruct --left --right``; the board's points must be
flat, where the calibration puts the board, and their corners 25 mm apart.

The figures the bounds come from (benchmarks/bench_two_file_route.py, which also runs
OpenCV StereoSGBM on the same calibration): calibration RMS 0.170 px, baseline 83.18 mm.
Pair 03's board (PnP with K1 D1) lies 242-317 mm away, tilted 19 deg; the rectified focal
length is 535.7 px, so fB = 44 560 px mm and a disparity error dd gives a depth error
dz = z^2 / (f B) dd = 1.75 mm per px at the median z (2.26 mm/px at the far corner).
Measured (prism3d / SGBM on the same pixels): every board pixel covered (100 % / 94 %);
plane RMS 1.76 / 1.61 mm, 3-robust-sigma trimmed 1.50 / 1.39 mm, on the squares' edges
0.65 / 0.75 mm; corner spacing 24.99 +- 0.12 / 25.01 +- 0.19 mm; extent 199.8 x 125.0 mm;
board plane 0.2 mm and 0.4 deg from the PnP plane.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from prism3d.cli import main
from prism3d.io.ply import read_ply

pytestmark = pytest.mark.realdata

SET = "calibration/opencv_stereo_9x6"
IDS = ("01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14")
BOARD = (9, 6)
SQUARE_MM = 25.0


# --- the board in the left image and the figures of a cloud on it -------------------------
def _board(left_path: Path, K: np.ndarray, D: np.ndarray) -> dict:
    """Inner corners (6, 9, 2), the board mask (hull of the corners eroded 4 px, so the
    white border does not count), edge pixels, and the PnP board plane (point, normal)."""
    img = cv2.imread(str(left_path))
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    ok, c = cv2.findChessboardCornersSB(grey, BOARD, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    assert ok, f"{left_path}: chessboard not found by OpenCV"
    corners = c.reshape(BOARD[1], BOARD[0], 2).astype(np.float64)
    mask = np.zeros(grey.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.rint(cv2.convexHull(corners.reshape(-1, 2).astype(np.float32))).astype(np.int32), 1)
    mask = cv2.erode(mask, np.ones((9, 9), np.uint8)).astype(bool)
    g = cv2.GaussianBlur(grey.astype(np.float32), (3, 3), 0)
    edges = mask & (np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)) >= 100.0)
    obj = np.zeros((BOARD[1] * BOARD[0], 3))
    obj[:, :2] = np.mgrid[0:BOARD[0], 0:BOARD[1]].T.reshape(-1, 2) * SQUARE_MM
    _, rvec, tvec = cv2.solvePnP(obj, corners.reshape(-1, 2), K, D)
    Rb = cv2.Rodrigues(rvec)[0]
    return {"corners": corners, "mask": mask, "edges": edges, "pnp_point": tvec.ravel(), "pnp_normal": Rb[:, 2]}


def _fit_plane(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = p.mean(0)
    return c, np.linalg.svd(p - c, full_matrices=False)[2][2]


def _fit_plane_trimmed(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refit on the points within 3 robust sigmas (1.4826 MAD) until the set is stable."""
    z = p[:, 2]
    keep = np.abs(z - np.median(z)) <= 3 * 1.4826 * np.median(np.abs(z - np.median(z))) + 1e-9
    for _ in range(50):
        c, n = _fit_plane(p[keep])
        r = (p - c) @ n
        new = np.abs(r) <= 3 * 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        if np.array_equal(new, keep):
            break
        keep = new
    return c, n, keep


def _spacing(P: np.ndarray) -> tuple[float, float, float, float]:
    """Mean and std of the neighbour distances of a (6, 9, 3) corner grid, its mean row
    length (8 squares) and column length (5 squares)."""
    d = np.concatenate([np.linalg.norm(P[:, 1:] - P[:, :-1], axis=-1).ravel(),
                        np.linalg.norm(P[1:] - P[:-1], axis=-1).ravel()])
    return (float(d.mean()), float(d.std()), float(np.linalg.norm(P[:, -1] - P[:, 0], axis=-1).mean()),
            float(np.linalg.norm(P[-1] - P[0], axis=-1).mean()))


def _measure(points: np.ndarray, K: np.ndarray, D: np.ndarray, board: dict) -> dict:
    mask, corners = board["mask"], board["corners"]
    h, w = mask.shape
    uv = cv2.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)[0].reshape(-1, 2)
    ui, vi = np.rint(uv).astype(np.int64).T
    inb = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    on, on_edge = np.zeros(len(points), bool), np.zeros(len(points), bool)
    on[inb], on_edge[inb] = mask[vi[inb], ui[inb]], board["edges"][vi[inb], ui[inb]]
    bp = points[on]
    hit = np.zeros(mask.shape, np.uint8)
    hit[vi[on], ui[on]] = 1
    out = {"n": len(bp), "board_px": int(mask.sum()),
           # a point within 1 px: the points sit on the rectified grid, not on these pixels
           "share": float((cv2.dilate(hit, np.ones((3, 3), np.uint8)).astype(bool) & mask).sum() / mask.sum())}
    if len(bp) < 100:
        return out
    c, n = _fit_plane(bp)
    out["rms"] = float(np.sqrt(np.mean(((bp - c) @ n) ** 2)))
    c, n, keep = _fit_plane_trimmed(bp)
    out["rms_trim"] = float(np.sqrt(np.mean(((bp[keep] - c) @ n) ** 2)))
    out["kept_trim"] = float(keep.mean())
    ep = points[on_edge]
    ce, ne, ke = _fit_plane_trimmed(ep)
    out["rms_edge"] = float(np.sqrt(np.mean(((ep[ke] - ce) @ ne) ** 2)))
    out["pnp_offset"] = float(np.median((bp - board["pnp_point"]) @ board["pnp_normal"]))
    out["pnp_tilt_deg"] = math.degrees(math.acos(min(1.0, abs(float(n @ board["pnp_normal"])))))
    # looked-up corners: the mean of the points projecting within 1.5 px of each corner
    P = np.full(corners.shape[:2] + (3,), np.nan)
    for i, j in np.ndindex(*corners.shape[:2]):
        near = np.sum((uv[inb] - corners[i, j]) ** 2, 1) <= 1.5 ** 2
        if near.any():
            P[i, j] = points[inb][near].mean(0)
    out["corners_found"] = int(np.isfinite(P[..., 0]).sum())
    out["lookup"] = _spacing(P)
    # ray-plane corners: each corner's ray through K1 D1 cut with the trimmed plane
    xy = cv2.undistortPoints(corners.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    out["ray_plane"] = _spacing((rays * ((c @ n) / (rays @ n))[:, None]).reshape(P.shape))
    return out


# --- the route through the CLI -----------------------------------------------------------
@pytest.fixture(scope="module")
def route(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    folder = shared_data / SET
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    tmp = tmp_path_factory.mktemp("two_file_route")
    calib = tmp / "calib.yaml"
    images = [str(folder / f"{side}{i}.jpg") for i in IDS for side in ("left", "right")]
    rc = main(["-q", "calibrate", "--pairs", *images, "-o", str(calib), "--board", "9x6", "--square", "25"])
    assert rc == 0
    fs = cv2.FileStorage(str(calib), cv2.FILE_STORAGE_READ)
    cal = {k: fs.getNode(k).mat() for k in ("K1", "D1", "T")}
    cal["rms_px"] = fs.getNode("rms_px").real()
    fs.release()
    return {"folder": folder, "tmp": tmp, "calib": calib, **cal}


def _reconstruct(route: dict, pair: str, out: Path, *extra: str) -> tuple[int, list[warnings.WarningMessage]]:
    """`prism3d reconstruct --left --right` in-process; numpy warnings are recorded, not
    raised (pytest turns warnings into errors, which would abort the command)."""
    folder = route["folder"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(["-q", "reconstruct", "--left", str(folder / f"left{pair}.jpg"), "--right",
                   str(folder / f"right{pair}.jpg"), "--calib", str(route["calib"]), "-o", str(out), *extra])
    return rc, list(caught)


@pytest.fixture(scope="module")
def scan03(route: dict) -> dict:
    ply = route["tmp"] / "scan03.ply"
    rc, caught = _reconstruct(route, "03", ply)  # no range given: prism3d finds it
    assert rc == 0
    K, D = route["K1"], route["D1"].ravel()
    board = _board(route["folder"] / "left03.jpg", K, D)
    return {"m": _measure(read_ply(ply).points, K, D, board), "warnings": caught}


def test_calibrate_pairs_on_opencv_set(route: dict) -> None:
    # Measured 0.170 px (OpenCV's own left-only reference: 0.39 px); baseline 83.18 mm.
    assert route["rms_px"] < 0.3
    assert 80.0 < float(np.linalg.norm(route["T"])) < 86.0


def test_board_points_exist_and_are_flat(scan03: dict) -> None:
    m = scan03["m"]
    # Measured: 100 % of the 75 519 board pixels have a point within 1 px (SGBM: 94 %),
    # 81 033 points on them (the rectified grid is ~1:1 with the image).
    assert m["share"] >= 0.95, m
    assert m["n"] >= 0.8 * m["board_px"], m
    # Precision from the geometry: dz = z^2 / (f B) dd = 1.75 mm/px at the median z
    # (279 mm), 2.26 mm/px at the far corner (317 mm). On the squares' edges (the only
    # board pixels with texture) a 1/4-1/3 px matcher gives 0.45-0.75 mm: measured
    # 0.65 mm (SGBM 0.75). Bound 1.0 mm = 0.57 px at the median depth.
    assert m["rms_edge"] < 1.0, m
    # Inside a square there is nothing to match; every method interpolates from the
    # edges (SGBM on the same pixels: 1.61 plain, 1.39 trimmed). Measured 1.76 / 1.50 mm;
    # bounds 3.0 / 2.5 mm (1.7 / 1.4 px at the median depth): a wrong-range or
    # unrefined scan is 10x off.
    assert m["rms"] < 3.0, m
    assert m["rms_trim"] < 2.5 and m["kept_trim"] > 0.9, m
    # Where the calibration says the board is: the calibrate command itself predicts
    # +-1.4 mm of depth (1 sigma, worst image point) from its parameters' uncertainty
    # at 310 mm. Measured -0.21 mm and 0.38 deg; bounds 2 mm and 1.5 deg.
    assert abs(m["pnp_offset"]) < 2.0, m
    assert m["pnp_tilt_deg"] < 1.5, m


def test_corner_spacing_is_25_mm(scan03: dict) -> None:
    m = scan03["m"]
    # A depth bias dz scales lateral distances by dz / z: the +-1.4 mm predicted above is
    # 0.5 % at 280 mm = 0.13 mm on 25 mm, 1 mm on 200 mm. Measured (looked-up from the
    # points / ray through K1 D1 cut with the plane): 24.99 +- 0.12 / 24.99 +- 0.10 mm,
    # rows 199.8 / 199.7 mm, columns 125.0 / 125.1 mm. Bounds: mean 25 +- 0.25 mm (1 %),
    # std < 0.4 mm (a looked-up corner averages ~7 points of ~1 mm depth noise, each
    # moving it sideways by x/z of that), rows 200 +- 1.5 mm, columns 125 +- 1.0 mm.
    assert m["corners_found"] == 54, m
    for name in ("lookup", "ray_plane"):
        mean, std, row, col = m[name]
        assert abs(mean - SQUARE_MM) < 0.25, (name, m[name])
        assert std < 0.4, (name, m[name])
        assert abs(row - 8 * SQUARE_MM) < 1.5, (name, m[name])
        assert abs(col - 5 * SQUARE_MM) < 1.0, (name, m[name])


def test_reconstruct_emits_no_numpy_warnings(scan03: dict) -> None:
    assert [str(w.message) for w in scan03["warnings"] if issubclass(w.category, RuntimeWarning)] == []


def test_right_view_of_another_size_is_refused(route: dict, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    right = cv2.imread(str(route["folder"] / "right03.jpg"))
    cropped = tmp_path / "right03_cropped.png"
    cv2.imwrite(str(cropped), right[:400, :600])
    out = tmp_path / "scan.ply"
    capsys.readouterr()
    rc = main(["-q", "reconstruct", "--left", str(route["folder"] / "left03.jpg"), "--right", str(cropped),
               "--calib", str(route["calib"]), "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "right03_cropped.png" in lines[0] and "600x400" in lines[0] and "640x480" in lines[0], err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["right03_cropped.png"]  # no partial output


def test_no_point_beyond_the_computed_range(route: dict, scan03: dict) -> None:
    """The search reached disparity 0 (no range given): the scan records the range its
    precision can tell from infinity (f B / 3 median stds) and keeps nothing beyond it."""
    ply = read_ply(route["tmp"] / "scan03.ply")
    meta = dict(c.split(" ", 1) for c in ply.comments if " " in c)
    assert meta["min_disp"] == "0"
    assert ply.points[:, 2].max() <= float(meta["max_range_mm"])
