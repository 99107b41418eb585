"""Benchmark: `prism3d reconstruct` through the command line on every ground-truthed real
pair in ../shared/data/stereo, against OpenCV StereoSGBM-3WAY on the same pair.

Run::

    .venv/bin/python benchmarks/bench_realpairs.py [--quick] [--out FILE.md] [--perturb]

Two routes per pair, each a fresh `prism3d` process, as a user would run them:

* **shot**: the pair packed side by side into one "shot" PNG with an ordinary-stereo
  calibration YAML (K1 D1 K2 D2 R T image_size, identity rotation; the pair's own
  focal length, baseline and principal points where it has a calib.txt);
* **files**: `--left L --right R --calib C` with the pair's own calib.txt where it has
  one (ETH3D), else the same YAML.

No disparity range is given: prism3d estimates it from the images. Every output point is
projected back into the left image with the calibration (``d = f B / z - doffs``) and
compared with the ground truth (Middlebury: non-occluded pixels; others: every pixel
with ground truth). Density = share of ground-truth pixels that got a point; bad-2 dense
counts the pixels without a point as bad; bad-2 on covered pixels uses only those with
a point. SGBM (blockSize 5, P1 8*25, P2 32*25, uniqueness 10, speckle 100/2, 3-way, the
ground truth's maximum as its range: an advantage ours does not get) is scored the
same way on its valid pixels.

``--perturb`` adds the photometric robustness test: each Middlebury pair with its right
view 30 % darker, a colour cast (gains 0.8 / 1.0 / 1.2), 40 % vignetting at the corners
and JPEG quality 85, against the untouched pair (shot route); also the same without
the JPEG step, and with the JPEG step on both views. Benchmarks print; they never
assert.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import prism3d  # noqa: F401,I001  (first: the thread pools' idle policy, before numpy loads OpenBLAS)
import cv2
import numpy as np

from prism3d.io.atomic import atomic_write_text
from prism3d.io.ply import read_ply
from prism3d.reconstruct.stereo.stereo_eval import BENCHMARK_SCENES, load_benchmark_pair, score_disparity

HERE = Path(__file__).resolve().parent
PRISM3D = Path(sys.executable).parent / "prism3d"
MIDDLEBURY = ("tsukuba", "venus", "teddy", "cones", "aloe")
CALIB_TXT = {"playground": "eth3d_two_view/playground/calib.txt",
             "terrace": "eth3d_two_view/terrace/calib.txt"}


def _data_dir() -> Path | None:
    env = os.environ.get("PRISM3D_TEST_DATA")
    for c in ([Path(env)] if env else []) + [HERE.parents[1] / "shared" / "data"]:
        if c.is_dir():
            return c
    return None


def sgbm(left: np.ndarray, right: np.ndarray, num_disp: int) -> np.ndarray:
    """OpenCV SGBM-3WAY with the brief's settings; invalid -> NaN."""
    m = cv2.StereoSGBM_create(minDisparity=0, numDisparities=int(math.ceil(num_disp / 16) * 16), blockSize=5,
                              P1=8 * 25, P2=32 * 25, uniquenessRatio=10, speckleWindowSize=100,
                              speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    d = m.compute(left[:, :, ::-1].copy(), right[:, :, ::-1].copy()).astype(np.float32) / 16
    d[d < 0] = np.nan
    return d


def perturb_right(img: np.ndarray, *, jpeg: int | None = 85) -> np.ndarray:
    """The issue's photometric test: 30 % darker, cast (0.8, 1.0, 1.2), 40 % corner
    vignetting (``1 - 0.4 r^2``, r = 1 at the corners), then JPEG at ``jpeg``."""
    h, w = img.shape[:2]
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((x - (w - 1) / 2) ** 2 + (y - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    out = img.astype(np.float32) * 0.7 * (1 - 0.4 * r2)[..., None] * np.array([0.8, 1.0, 1.2], np.float32)
    out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out if jpeg is None else jpeg_roundtrip(out, jpeg)


def jpeg_roundtrip(img: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1].copy()


def _calib(name: str, root: Path, w: int, h: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(K1, K2, baseline mm): the pair's own calib.txt where it has one, else a made-up
    but consistent rig (f = 1000 px, B = 100 mm, centred principal point)."""
    if name in CALIB_TXT:
        from prism3d.capture.calib_formats import load_stereo_calibration

        rig = load_stereo_calibration(root / "stereo" / CALIB_TXT[name]).rig
        return rig.left.K, rig.right.K, rig.baseline_mm
    K = np.array([[1000.0, 0, (w - 1) / 2], [0, 1000.0, (h - 1) / 2], [0, 0, 1]])
    return K, K.copy(), 100.0


def _write_yaml(path: Path, K1: np.ndarray, K2: np.ndarray, B: float, w: int, h: int) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in (("K1", K1), ("D1", np.zeros((5, 1))), ("K2", K2), ("D2", np.zeros((5, 1))),
                 ("R", np.eye(3)), ("T", np.array([[-B], [0.0], [0.0]])),
                 ("image_size", np.array([[w], [h]], np.int32))):
        fs.write(k, v)
    fs.release()


def _points_to_disparity(ply: Path, K1: np.ndarray, K2: np.ndarray, B: float, shape: tuple[int, int]
                         ) -> np.ndarray:
    pts = read_ply(ply).points.astype(np.float64)
    z = pts[:, 2]
    u = np.rint(K1[0, 0] * pts[:, 0] / z + K1[0, 2]).astype(np.int64)
    v = np.rint(K1[1, 1] * pts[:, 1] / z + K1[1, 2]).astype(np.int64)
    d = K1[0, 0] * B / z - (K2[0, 2] - K1[0, 2])
    out = np.full(shape, np.nan, np.float32)
    ok = (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    out[v[ok], u[ok]] = d[ok]
    return out


def _run(args: list[str]) -> float:
    t = time.perf_counter()
    proc = subprocess.run([str(PRISM3D), "-q", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"prism3d {' '.join(args)} failed: {proc.stderr.strip()}")
    return time.perf_counter() - t


def _reconstruct(route: str, name: str, left: np.ndarray, right: np.ndarray, root: Path, tmp: Path
                 ) -> tuple[np.ndarray, float]:
    h, w = left.shape[:2]
    K1, K2, B = _calib(name, root, w, h)
    yaml = tmp / f"{name}.yaml"
    _write_yaml(yaml, K1, K2, B, w, h)
    out = tmp / f"{name}_{route}.ply"
    if route == "shot":
        shot = tmp / f"{name}_shot.png"
        cv2.imwrite(str(shot), np.concatenate([left, right], axis=1)[:, :, ::-1])
        secs = _run(["reconstruct", str(shot), "--calib", str(yaml), "-o", str(out)])
    else:
        lp, rp = tmp / f"{name}_l.png", tmp / f"{name}_r.png"
        cv2.imwrite(str(lp), left[:, :, ::-1])
        cv2.imwrite(str(rp), right[:, :, ::-1])
        calib = root / "stereo" / CALIB_TXT[name] if name in CALIB_TXT else yaml
        secs = _run(["reconstruct", "--left", str(lp), "--right", str(rp), "--calib", str(calib), "-o", str(out)])
    return _points_to_disparity(out, K1, K2, B, (h, w)), secs


def accuracy_table(root: Path, scenes: list[str]) -> list[str]:
    lines = ["| pair | route | density | bad-2 dense | bad-2 covered | SGBM density | SGBM bad-2 dense | "
             "SGBM bad-2 covered | bad-2 ratio | s (fresh process) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    with tempfile.TemporaryDirectory() as td:
        for name in scenes:
            left, right, gt, mask = load_benchmark_pair(root, name)
            ss = score_disparity(sgbm(left, right, int(math.ceil(float(gt.max()) + 1))), gt, mask=mask)
            for route in ("shot", "files"):
                d, secs = _reconstruct(route, name, left, right, root, Path(td))
                so = score_disparity(d, gt, mask=mask)
                lines.append(f"| {name} | {route}{' (calib.txt)' if route == 'files' and name in CALIB_TXT else ''}"
                             f" | {so.density:.3f} | {so.bad2:.3f} | {so.bad2_valid:.3f} | {ss.density:.3f} | "
                             f"{ss.bad2:.3f} | {ss.bad2_valid:.3f} | {so.bad2 / ss.bad2:.2f} | {secs:.2f} |")
                print(lines[-1], flush=True)
    return lines


def perturbation_table(root: Path, scenes: list[str]) -> list[str]:
    lines = ["| pair | case | density | bad-2 dense | density / untouched | bad-2 / untouched | "
             "SGBM bad-2 / untouched |", "|---|---|---:|---:|---:|---:|---:|"]
    cases = {"right: dark+cast+vignetting": lambda l, r: (l, perturb_right(r, jpeg=None)),
             "right: JPEG 85": lambda l, r: (l, jpeg_roundtrip(r, 85)),
             "right: all four": lambda l, r: (l, perturb_right(r)),
             "right: all four, left JPEG 85 too": lambda l, r: (jpeg_roundtrip(l, 85), perturb_right(r))}
    with tempfile.TemporaryDirectory() as td:
        for name in scenes:
            left, right, gt, mask = load_benchmark_pair(root, name)
            nd = int(math.ceil(float(gt.max()) + 1))
            d0, _ = _reconstruct("shot", name, left, right, root, Path(td))
            s0 = score_disparity(d0, gt, mask=mask)
            g0 = score_disparity(sgbm(left, right, nd), gt, mask=mask)
            lines.append(f"| {name} | untouched | {s0.density:.3f} | {s0.bad2:.3f} | 1 | 1 | 1 |")
            print(lines[-1], flush=True)
            for case, fn in cases.items():
                lp, rp = fn(left, right)
                d, _ = _reconstruct("shot", name, lp, rp, root, Path(td))
                s = score_disparity(d, gt, mask=mask)
                g = score_disparity(sgbm(lp, rp, nd), gt, mask=mask)
                lines.append(f"| {name} | {case} | {s.density:.3f} | {s.bad2:.3f} | {s.density / s0.density:.3f} | "
                             f"{s.bad2 / s0.bad2:.2f} | {g.bad2 / g0.bad2:.2f} |")
                print(lines[-1], flush=True)
    return lines


def prism_table(cache: Path) -> list[str]:
    """The photometric test on simulated 5 MP prism shots (ideal camera): the right half
    of the sensor 30 % darker, cast, vignetted about the right view's principal point,
    and the whole sensor image JPEG 85 (or not), reconstructed like any shot; density
    and bad-2 against the true rectified disparity (pixels with truth count; no point =
    bad)."""
    from prism3d.capture.camera_effects import CameraEffects
    from prism3d.capture.rig import StereoRig
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
    from prism3d.datasets.models.targets import builtin_target
    from prism3d.io.images import read_image
    from prism3d.reconstruct.stereo.pipeline import reconstruct_shot

    lines = ["| shot | case | density | bad-2 dense | bad-1 dense | density / untouched | bad-2 / untouched |",
             "|---|---|---:|---:|---:|---:|---:|"]
    scenes = {"plate": dict(kind="plate", pattern=True, camouflage=False),
              "tank view 1": dict(kind="scene", target=builtin_target("tank_t1", seed=0), views=2)}
    for name, kw in scenes.items():
        folder = cache / name.replace(" ", "_")
        if not (folder / "rig.yaml").exists():
            kind = kw.pop("kind")
            simulate_to_folder(kind, folder, SimulateOptions(effects=CameraEffects.ideal(),
                               **{k: v for k, v in kw.items() if k != "target"}), target=kw.get("target"))
        rig = StereoRig.load(folder / "rig.yaml")
        shot_file = folder / ("shot.png" if (folder / "shot.png").exists() else "shot_01.png")
        truth = np.load(folder / ("truth.npz" if shot_file.name == "shot.png" else "truth_01.npz"))["disparity_rect"]
        shot = read_image(shot_file)
        x, y, w, h = rig.split.roi_right
        cx, cy = rig.right.cx, rig.right.cy

        def perturbed(jpeg: int | None) -> np.ndarray:
            out = shot.astype(np.float32)
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
            r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / max(cx ** 2 + cy ** 2, (w - cx) ** 2 + (h - cy) ** 2)
            gain = 0.7 * (1 - 0.4 * r2)[..., None] * np.array([0.8, 1.0, 1.2], np.float32)
            out[y:y + h, x:x + w] *= gain
            out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
            return out if jpeg is None else jpeg_roundtrip(out, jpeg)

        known = np.isfinite(truth)
        base = None
        for case, img in (("untouched", shot), ("right half: dark+cast+vignetting", perturbed(None)),
                          ("... and the sensor image JPEG 85", perturbed(85))):
            rec = reconstruct_shot(img, rig)
            e = np.abs(rec.disparity - truth)[known]
            dens = float(np.isfinite(e).mean())
            bad2 = float(np.mean(~(e <= 2)))
            bad1 = float(np.mean(~(e <= 1)))
            base = base or (dens, bad2)
            lines.append(f"| {name} | {case} | {dens:.3f} | {bad2:.4f} | {bad1:.4f} | {dens / base[0]:.3f} | "
                         f"{bad2 / base[1]:.2f} |")
            print(lines[-1], flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tsukuba, playground and kitti only")
    ap.add_argument("--perturb", action="store_true", help="also the photometric robustness table")
    ap.add_argument("--prism", action="store_true", help="also the photometric test on simulated prism shots")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/prism3d_realpairs"), help="simulated shots")
    ap.add_argument("--out", type=Path, help="also write the Markdown here")
    a = ap.parse_args()
    root = _data_dir()
    if root is None:
        print("real data not found (set PRISM3D_TEST_DATA or place ../shared/data): real pairs skipped")
    scenes = [] if root is None else ["tsukuba", "playground", "kitti"] if a.quick else list(BENCHMARK_SCENES)
    load = os.getloadavg()[0]
    lines = ["## Real pairs through `prism3d reconstruct` (CLI) vs SGBM-3WAY", "",
             f"{time.strftime('%Y-%m-%d')}; 1-min load average at start {load:.1f} on {os.cpu_count()} cores. "
             "Range estimated by prism3d from the images; SGBM given the ground truth's maximum.", ""]
    if scenes:
        lines += accuracy_table(root, scenes)
    if a.perturb and scenes:
        lines += ["", "### Photometric robustness (shot route)", ""]
        lines += perturbation_table(root, [s for s in scenes if s in MIDDLEBURY])
    if a.prism:
        lines += ["", "### Photometric robustness, simulated 5 MP prism shots (ideal camera)", ""]
        lines += prism_table(a.cache)
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        atomic_write_text(a.out, text)


if __name__ == "__main__":
    main()
