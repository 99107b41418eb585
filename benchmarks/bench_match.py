"""Benchmark: prism3d.reconstruct.match_stereo vs OpenCV StereoSGBM (3-way).

Run::

    .venv/bin/python benchmarks/bench_match.py [--quick] [--out benchmarks/RESULTS_match.md]

Prints a Markdown section (and writes it to ``--out``):

* accuracy (bad-1, bad-2, average error, density; holes count as bad) and speed on
  every ground-truthed pair in ``../shared/data/stereo``, both matchers in the same
  run, 2 threads each (``cv2.setNumThreads(2)``; numba uses the 2 cores);
* a synthetic pair at the paper's geometry (rectified 2130 x 1976 views, disparity
  700..950 px, 272 levels from 688): speed ratio, accuracy against the known
  disparity, and peak memory of each matcher in a fresh subprocess (VmHWM);
* numba compile cost: first call in a fresh process with an empty cache, and with the
  on-disk cache filled;
* the sub-pixel shift sweep (RMS, bias, correlation with the fractional part).

Times are the minimum of ``--repeat`` runs after a warm-up call. Wall times on a
shared machine are noisy; benchmarks print, they never assert.
"""

from __future__ import annotations

import argparse
import json
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

from prism3d.reconstruct.stereo.stereo_eval import load_benchmark_pair
from prism3d.reconstruct.stereo.match import match_stereo, match_stereo_full
from prism3d.reconstruct.stereo.stereo_eval import score_disparity

from prism3d.io.atomic import atomic_write_text

HERE = Path(__file__).resolve().parent
DATA = HERE.parents[0].parent / "shared" / "data"
SCENES = ["tsukuba", "venus", "teddy", "cones", "aloe", "playground", "terrace", "kitti"]


def _data_dir() -> Path | None:
    env = os.environ.get("PRISM3D_TEST_DATA")
    for c in ([Path(env)] if env else []) + [DATA]:
        if c.is_dir():
            return c
    return None


def load_scene(root: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(left RGB, right RGB, gt disparity (0 = unknown), evaluation mask or None)."""
    return load_benchmark_pair(root, name)


def sgbm(left: np.ndarray, right: np.ndarray, min_disp: int, num_disp: int) -> np.ndarray:
    """OpenCV SGBM-3WAY with the settings of the brief; invalid -> NaN."""
    n16 = int(math.ceil(num_disp / 16) * 16)
    m = cv2.StereoSGBM_create(
        minDisparity=min_disp, numDisparities=n16, blockSize=5, P1=8 * 25, P2=32 * 25,
        uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    lb = left[:, :, ::-1].copy() if left.ndim == 3 else left
    rb = right[:, :, ::-1].copy() if right.ndim == 3 else right
    d = m.compute(lb, rb).astype(np.float32) / 16
    d[d < min_disp] = np.nan
    return d


def _best_time(fn, repeat: int) -> tuple[float, object]:
    out = fn()  # warm-up
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def paper_pair(h: int = 1976, w: int = 2130, dmin: float = 700.0, dmax: float = 950.0,
               seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour band-limited texture on a slanted relief, right view warped by the known
    disparity (cubic interpolation). Columns x < 1000 of the left view have no
    counterpart (as in the real rig, where the object fills the overlap)."""
    rng = np.random.default_rng(seed)
    tex = np.empty((h, w, 3), np.float32)
    for c in range(3):
        n = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.5)
        tex[:, :, c] = n / n.std()
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def disp(xl: np.ndarray, y: np.ndarray) -> np.ndarray:
        bump = np.exp(-(((xl - 0.7 * w) / (0.15 * w)) ** 2 + ((y - 0.5 * h) / (0.2 * h)) ** 2))
        return dmin + (dmax - dmin) * (0.5 * xl / w + 0.3 * y / h + 0.2 * bump)

    xl = xx + dmin
    for _ in range(30):
        xl = xx + disp(xl, yy)
    right = cv2.remap(tex, xl.astype(np.float32), yy.astype(np.float32), cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REFLECT)

    def u8(a: np.ndarray) -> np.ndarray:
        return np.clip(a * 40 + 128, 0, 255).astype(np.uint8)

    gt = disp(xx, yy).astype(np.float32)
    gt[:, :1000] = 0.0
    return u8(tex), u8(right), gt


_CHILD = r"""
import json, sys, time
import numpy as np, cv2
sys.path.insert(0, {here!r})
import bench_match as b


def hwm_mb():
    # VmHWM: peak RSS of this process image (ru_maxrss would include the parent's
    # peak, which Linux carries across fork + exec)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


cv2.setNumThreads(2)
with np.load({pair!r}, allow_pickle=False) as z:
    L, R = z["left"], z["right"]
base = hwm_mb()
t = time.perf_counter()
if {which!r} == "ours":
    d = b.match_stereo(L, R, min_disp=688, num_disp=272)
else:
    d = b.sgbm(L, R, 688, 272)
dt = time.perf_counter() - t
peak = hwm_mb()
print(json.dumps({{"peak_mb": peak, "inputs_mb": base, "first_call_s": dt}}))
"""


def _child(which: str, pair: Path) -> dict:
    code = _CHILD.format(here=str(HERE), which=which, pair=str(pair))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


_COMPILE = r"""
import time
t0 = time.perf_counter()
import numpy as np
from prism3d.reconstruct.stereo.match import MatchOptions, match_stereo
rng = np.random.default_rng(0)
L = (rng.random((40, 80)) * 255).astype(np.uint8)
R = np.roll(L, -4, axis=1)
t1 = time.perf_counter()
match_stereo(L, R, min_disp=0, num_disp=8)
t2 = time.perf_counter()
match_stereo(L, R, min_disp=0, num_disp=8, options=MatchOptions(coarse_to_fine=True))
t3 = time.perf_counter()
print(t1 - t0, t2 - t1, t3 - t2)
"""


def compile_cost() -> tuple[list[float], list[float]]:
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, NUMBA_CACHE_DIR=tmp)
        runs = []
        for _ in range(2):
            r = subprocess.run([sys.executable, "-c", _COMPILE], capture_output=True, text=True,
                               env=env, check=True)
            runs.append([float(v) for v in r.stdout.split()])
    return runs[0], runs[1]


def subpixel_sweep() -> dict[str, float]:
    h, w = 48, 160
    rng = np.random.default_rng(1)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    spec = np.fft.fft2(rng.standard_normal((h, w))) * np.exp(
        -2 * (np.pi * 1.2) ** 2 * (fx**2 + fy**2))
    left = np.real(np.fft.ifft2(spec))
    lo, hi = left.min(), left.max()
    left8 = np.rint((left - lo) / (hi - lo) * 255).astype(np.uint8)
    errs, fr, bias = [], [], []
    for f in np.round(np.arange(0.0, 1.0001, 0.05), 2):
        right = np.real(np.fft.ifft2(spec * np.exp(2j * np.pi * fx * (8 + f))))
        right8 = np.clip(np.rint((right - lo) / (hi - lo) * 255), 0, 255).astype(np.uint8)
        d = match_stereo(left8, right8, min_disp=0, num_disp=24)
        e = (d[8:-8, 24:-8] - (8 + f)).ravel()
        errs.append(e)
        fr.append(np.full(e.shape, f))
        bias.append(float(np.median(e)))
    e = np.concatenate(errs)
    f = np.concatenate(fr)
    est = np.mod(e + 8 + f, 1.0)
    hist = np.histogram(est, bins=10, range=(0, 1))[0] / est.size
    return {"rms": float(np.sqrt(np.mean(e**2))), "max_abs_bias": max(abs(b) for b in bias),
            "corr": float(np.corrcoef(e, f)[0, 1]), "hist_max": float(hist.max()),
            "hist_min": float(hist.min())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one repeat, skip the compile test")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=HERE / "RESULTS_match.md")
    args = ap.parse_args(argv)
    repeat = 1 if args.quick else args.repeat
    cv2.setNumThreads(2)
    lines = ["## Stereo matcher (`prism3d.reconstruct.match_stereo`) vs OpenCV StereoSGBM-3WAY", ""]
    lines.append("SGBM: blockSize 5, P1 8*25, P2 32*25, uniquenessRatio 10, speckle 100/2, "
                 "MODE_SGBM_3WAY, numDisparities = GT max rounded up to 16; its invalid pixels "
                 "count as bad. Ours: defaults, dense output. 2 threads each; times = min of "
                 f"{repeat} after warm-up.")
    lines.append("")
    lines.append(f"Load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; "
                 f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')}; "
                 f"OPENBLAS_THREAD_TIMEOUT={os.environ.get('OPENBLAS_THREAD_TIMEOUT', '(unset)')}; numba "
                 f"threading layer {os.environ.get('NUMBA_THREADING_LAYER', '(default)')}.")
    lines.append("")
    root = _data_dir()
    if root is not None:
        lines += ["| scene | size | levels | ours bad-1 | ours bad-2 | ours avg | SGBM bad-1 | "
                  "SGBM bad-2 | SGBM avg | SGBM density | bad-2 ratio | ours s | SGBM s | time ratio |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for name in SCENES:
            left, right, gt, mask = load_scene(root, name)
            nd = int(math.ceil(float(gt.max()) + 1))
            t_o, d_o = _best_time(lambda: match_stereo(left, right, min_disp=0, num_disp=nd),
                                  repeat)
            t_s, d_s = _best_time(lambda: sgbm(left, right, 0, nd), repeat)
            so = score_disparity(d_o, gt, mask=mask)
            ss = score_disparity(d_s, gt, mask=mask)
            lines.append(
                f"| {name} | {left.shape[1]}x{left.shape[0]} | {nd} | {so.bad1:.3f} | "
                f"{so.bad2:.3f} | {so.avg_err:.2f} | {ss.bad1:.3f} | {ss.bad2:.3f} | "
                f"{ss.avg_err:.2f} | {ss.density:.2f} | {so.bad2 / ss.bad2:.2f} | {t_o:.3f} | "
                f"{t_s:.3f} | {t_o / t_s:.2f} |")
            print(lines[-1], flush=True)
        lines.append("")
    else:
        lines += ["(real data not found: accuracy table skipped)", ""]

    left, right, gt = paper_pair()
    t_o, res = _best_time(lambda: match_stereo_full(left, right, min_disp=688, num_disp=272),
                          repeat)
    t_s, d_s = _best_time(lambda: sgbm(left, right, 688, 272), repeat)
    so = score_disparity(res.disparity, gt)
    ss = score_disparity(d_s, gt)
    lines += [
        "### Paper geometry (synthetic, 2130x1976 rectified views, disparity 700-950, "
        "272 levels from 688)", "",
        f"- ours (coarse-to-fine = {res.coarse_to_fine}): {t_o:.2f} s; SGBM-3WAY: {t_s:.2f} s; "
        f"ratio ours/SGBM = {t_o / t_s:.2f}",
        f"- accuracy on the overlap: ours bad-1 {so.bad1:.4f}, RMS {so.rms_err:.3f} px, "
        f"avg {so.avg_err:.3f} px; SGBM bad-1 {ss.bad1:.4f}, RMS {ss.rms_err:.3f} px, "
        f"avg {ss.avg_err:.3f} px, density {ss.density:.4f}",
    ]
    print("\n".join(lines[-2:]), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        pair = Path(tmp) / "pair.npz"
        np.savez(pair, left=left, right=right)
        mo = _child("ours", pair)
        ms = _child("sgbm", pair)
    lines.append(
        f"- peak RSS of a fresh process that loads the pair and matches it once "
        f"(VmHWM; {mo['inputs_mb']:.0f} MB before matching: interpreter, libraries, "
        f"inputs): ours {mo['peak_mb']:.0f} MB, SGBM {ms['peak_mb']:.0f} MB; first call "
        f"(kernels from the on-disk cache) ours {mo['first_call_s']:.2f} s, "
        f"SGBM {ms['first_call_s']:.2f} s")
    print(lines[-1], flush=True)
    lines.append("")
    if not args.quick:
        cold, warm = compile_cost()
        lines += [
            "### numba compile cost (fresh process, tiny pair)", "",
            f"- empty cache: import {cold[0]:.2f} s, first full-search call {cold[1]:.2f} s, "
            f"first coarse-to-fine call {cold[2]:.2f} s",
            f"- cache filled (`cache=True`): import {warm[0]:.2f} s, first call {warm[1]:.2f} s, "
            f"first coarse-to-fine call {warm[2]:.2f} s", ""]
        print("\n".join(lines[-4:]), flush=True)
    sw = subpixel_sweep()
    lines += [
        "### Sub-pixel shift sweep (band-limited texture, d = 8.00..9.00 step 0.05, exact "
        "Fourier shift, uint8)", "",
        f"- RMS {sw['rms']:.4f} px; max |median bias| over the 21 shifts {sw['max_abs_bias']:.4f} px; "
        f"corr(error, fractional part) {sw['corr']:+.3f}; histogram of estimated fractional "
        f"parts (10 bins) min {sw['hist_min']:.3f} / max {sw['hist_max']:.3f} (flat = 0.100)", ""]
    print("\n".join(lines[-3:]), flush=True)
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
