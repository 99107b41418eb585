"""Tests of prism3d.reconstruct.stereo.match (census + SGM stereo matcher)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from prism3d.reconstruct.stereo.stereo_eval import load_benchmark_pair
import pytest
from prism3d.reconstruct.stereo.match import (MatchOptions, StereoResult, match_files, match_stereo,
                                       match_stereo_full)
from prism3d.reconstruct.stereo.stereo_eval import score_disparity

from prism3d.errors import InputError, ReconstructionError

# ----------------------------------------------------------------------------- helpers


def _spectrum(h: int, w: int, sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Spectrum of a periodic band-limited random texture (Gaussian low-pass)."""
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    spec = np.fft.fft2(rng.standard_normal((h, w)))
    return spec * np.exp(-2 * (np.pi * sigma) ** 2 * (fx**2 + fy**2)), fx


def _shifted(spec: np.ndarray, fx: np.ndarray, d: float) -> np.ndarray:
    """The texture sampled at x + d (exact Fourier shift): a right view at disparity d."""
    return np.real(np.fft.ifft2(spec * np.exp(2j * np.pi * fx * d)))


def _pair(h: int, w: int, d: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    spec, fx = _spectrum(h, w, 1.2, seed)
    left = np.real(np.fft.ifft2(spec))
    lo, hi = left.min(), left.max()

    def u8(a: np.ndarray) -> np.ndarray:
        return np.clip(np.rint((a - lo) / (hi - lo) * 255), 0, 255).astype(np.uint8)

    return u8(left), u8(_shifted(spec, fx, d))


# ------------------------------------------------------------------------- known answers


def test_integer_shift_known_answer() -> None:
    left, right = _pair(48, 128, 7.0)
    res = match_stereo_full(left, right, min_disp=0, num_disp=16)
    assert isinstance(res, StereoResult)
    inner = res.disparity[6:-6, 20:-6]
    assert np.abs(inner - 7.0).max() < 0.05
    assert res.disparity.dtype == np.float32 and res.disparity.shape == (48, 128)
    assert res.valid.dtype == np.bool_ and res.valid[6:-6, 20:-6].mean() > 0.99
    assert np.isfinite(res.disparity).all()
    assert np.isnan(res.raw[~res.valid]).all()
    assert np.array_equal(res.raw[res.valid], res.disparity[res.valid])
    assert res.confidence.dtype == np.float32
    assert (res.confidence >= 0).all() and (res.confidence <= 1).all()
    assert (res.confidence[~res.valid] == 0).all()
    assert not res.coarse_to_fine
    dense = match_stereo(left, right, min_disp=0, num_disp=16)
    assert np.array_equal(dense, res.disparity)


def test_reused_scratch_changes_nothing() -> None:
    """Scratch volumes are kept between calls (per thread): results must not depend
    on what ran before -- other sizes, other ranges, colour vs grey, coarse-to-fine --
    nor on another thread matching at the same time; returned arrays are never the
    scratch."""
    import threading

    a_l, a_r = _pair(48, 128, 7.0, seed=1)
    b_l, b_r = _pair(40, 96, 3.0, seed=2)
    first = match_stereo_full(a_l, a_r, min_disp=0, num_disp=16)
    keep = {k: getattr(first, k).copy() for k in ("disparity", "valid", "confidence", "raw")}
    match_stereo_full(b_l, b_r, min_disp=-4, num_disp=40)
    match_stereo_full(np.dstack([a_l, a_r, a_l]), np.dstack([a_r, a_l, a_r]), min_disp=0,
                      num_disp=16)
    match_stereo_full(a_l, a_r, min_disp=0, num_disp=16, options=MatchOptions(coarse_to_fine=True))
    again = match_stereo_full(a_l, a_r, min_disp=0, num_disp=16)
    for k, v in keep.items():
        assert np.array_equal(getattr(first, k), v, equal_nan=True), k  # not overwritten
        assert np.array_equal(getattr(again, k), v, equal_nan=True), k
    results: list = []

    def work() -> None:
        for _ in range(3):
            results.append(match_stereo_full(a_l, a_r, min_disp=0, num_disp=16).raw)

    threads = [threading.Thread(target=work) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 6
    for r in results:
        assert np.array_equal(r, keep["raw"], equal_nan=True)


def test_census_only_and_gradient_features() -> None:
    """Without the AD term (ad_weight=0: no feature planes) and with gradient
    features the matcher still finds a known shift, on colour and grey pairs."""
    pairs = [_pair(48, 128, 7.0, seed=s) for s in (4, 5, 6)]  # one texture per channel
    colour = (np.dstack([p[0] for p in pairs]), np.dstack([p[1] for p in pairs]))
    for lv, rv in (pairs[0], colour):
        for kw in ({"ad_weight": 0.0}, {"ad_mode": "gradient"}):
            res = match_stereo_full(lv, rv, min_disp=0, num_disp=20, options=MatchOptions(**kw))
            inner = res.disparity[6:-6, 24:-6]
            assert np.abs(inner - 7.0).max() < 0.1, kw


def test_negative_disparity_and_float_input() -> None:
    left, right = _pair(40, 96, -3.0, seed=3)
    d = match_stereo(left.astype(np.float32) / 255, right.astype(np.float32) / 255,
                     min_disp=-8, num_disp=12)
    assert np.median(np.abs(d[6:-6, 6:-12] + 3.0)) < 0.02


def test_grey_rgb_equivalence_and_colour_used() -> None:
    left, right = _pair(40, 96, 5.0, seed=4)
    grey = match_stereo(left, right, min_disp=0, num_disp=12)
    rgb = match_stereo(np.dstack([left] * 3), np.dstack([right] * 3), min_disp=0, num_disp=12)
    np.testing.assert_array_equal(grey, rgb)  # identical channels are treated as grey
    # colour-only texture: the luminance is flat, only hue varies
    lr, rr = _pair(40, 96, 5.0, seed=5)
    lg, rg = _pair(40, 96, 5.0, seed=6)
    lcol = np.dstack([lr, lg, 255 - ((lr.astype(int) + lg) // 2)]).astype(np.uint8)
    rcol = np.dstack([rr, rg, 255 - ((rr.astype(int) + rg) // 2)]).astype(np.uint8)
    d = match_stereo(lcol, rcol, min_disp=0, num_disp=12)
    assert np.median(np.abs(d[6:-6, 16:-6] - 5.0)) < 0.05


def test_subpixel_sweep_no_pixel_locking() -> None:
    """Band-limited texture shifted by 8.00 .. 9.00 px in 0.05 steps (exact Fourier
    shift): RMS <= 0.05 px, no bias toward integers, flat error vs fractional part."""
    h, w = 48, 160
    spec, fx = _spectrum(h, w, 1.2, 1)
    left = np.real(np.fft.ifft2(spec))
    lo, hi = left.min(), left.max()
    left8 = np.rint((left - lo) / (hi - lo) * 255).astype(np.uint8)
    fracs = np.round(np.arange(0.0, 1.0001, 0.05), 2)
    errs, fr, bias = [], [], []
    for f in fracs:
        right = np.clip(np.rint((_shifted(spec, fx, 8 + f) - lo) / (hi - lo) * 255), 0, 255)
        d = match_stereo(left8, right.astype(np.uint8), min_disp=0, num_disp=24)
        e = (d[8:-8, 24:-8] - (8 + f)).ravel()
        errs.append(e)
        fr.append(np.full(e.shape, f))
        bias.append(float(np.median(e)))
    e = np.concatenate(errs)
    f = np.concatenate(fr)
    rms = float(np.sqrt(np.mean(e**2)))
    assert rms <= 0.05, rms
    assert max(abs(b) for b in bias) < 0.01, bias  # no pull toward (or away from) integers
    assert abs(np.corrcoef(e, f)[0, 1]) < 0.3
    # the fractional parts of the estimates spread evenly (no pile-up at 0)
    est_frac = np.mod(np.concatenate(errs) + 8 + f, 1.0)
    hist = np.histogram(est_frac, bins=10, range=(0, 1))[0] / est_frac.size
    assert hist.max() < 0.2


def _relief_pair(h: int, w: int, dmin: float, dmax: float) -> tuple[np.ndarray, ...]:
    """Slanted plane + bump: left = texture, right warped by the known disparity."""
    rng = np.random.default_rng(9)
    tex = cv2.GaussianBlur(rng.standard_normal((h, w + int(dmax) + 8)).astype(np.float32),
                           (0, 0), 1.3)
    tex = np.clip(tex / tex.std() * 45 + 128, 0, 255).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)

    def disp(xl: np.ndarray, y: np.ndarray) -> np.ndarray:
        bump = np.exp(-(((xl - 0.6 * w) / (0.15 * w)) ** 2 + ((y - 0.5 * h) / (0.25 * h)) ** 2))
        return dmin + (dmax - dmin) * (0.5 * xl / w + 0.3 * y / h + 0.2 * bump)

    xl = xx + dmin
    for _ in range(40):
        xl = xx + disp(xl, yy)
    left = tex[:, :w]
    right = cv2.remap(tex, xl.astype(np.float32), yy.astype(np.float32), cv2.INTER_CUBIC)
    return left.astype(np.uint8), right.astype(np.uint8), disp(xx, yy).astype(np.float32)


def test_coarse_to_fine_large_offset() -> None:
    left, right, gt = _relief_pair(160, 520, 140.0, 190.0)
    res = match_stereo_full(left, right, min_disp=136, num_disp=64,
                            options=MatchOptions(coarse_to_fine=True))
    assert res.coarse_to_fine
    region = (slice(8, -8), slice(200, -8))  # left part has no counterpart in the right view
    e = (res.disparity - gt)[region]
    assert np.mean(np.abs(e) > 1.0) < 0.01
    assert float(np.sqrt(np.mean(e**2))) < 0.15
    full = match_stereo_full(left, right, min_disp=136, num_disp=64,
                             options=MatchOptions(coarse_to_fine=False))
    assert not full.coarse_to_fine
    assert np.mean(np.abs(full.disparity - res.disparity)[region] > 0.5) < 0.01


# ---------------------------------------------------------------------------- bad input


def test_bad_input() -> None:
    a = np.zeros((20, 30), np.uint8)
    with pytest.raises(InputError, match="left and right must have the same shape"):
        match_stereo(a, np.zeros((20, 31), np.uint8), min_disp=0, num_disp=8)
    with pytest.raises(InputError, match="num_disp: expected an integer > 0, got 0"):
        match_stereo(a, a, min_disp=0, num_disp=0)
    with pytest.raises(InputError, match="num_disp: expected an integer > 0, got -5"):
        match_stereo(a, a, min_disp=0, num_disp=-5)
    with pytest.raises(InputError, match="num_disp: expected an integer, got 8.0"):
        match_stereo(a, a, min_disp=0, num_disp=8.0)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="min_disp: expected an integer, got 1.5"):
        match_stereo(a, a, min_disp=1.5, num_disp=8)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="min_disp: expected an integer, got True"):
        match_stereo(a, a, min_disp=True, num_disp=8)
    with pytest.raises(InputError, match="left: expected uint8 or float image, got uint16"):
        match_stereo(a.astype(np.uint16), a, min_disp=0, num_disp=8)
    with pytest.raises(InputError, match="right: expected dtype kind"):
        match_stereo(a, a.astype(np.int16), min_disp=0, num_disp=8)
    with pytest.raises(InputError, match="left: expected 2 or 3 dimensions"):
        match_stereo(np.zeros(30, np.uint8), np.zeros(30, np.uint8), min_disp=0, num_disp=8)
    with pytest.raises(InputError, match=r"left: expected \(H, W\) or \(H, W, 3\)"):
        match_stereo(np.zeros((20, 30, 4), np.uint8), a, min_disp=0, num_disp=8)
    with pytest.raises(InputError, match="right: expected finite values"):
        match_stereo(a / 255.0, np.full((20, 30), np.nan), min_disp=0, num_disp=8)
    with pytest.raises(InputError, match="options: expected a MatchOptions, got dict"):
        match_stereo(a, a, min_disp=0, num_disp=8, options={"paths": 4})  # type: ignore[arg-type]


def test_match_options_validation() -> None:
    """MatchOptions checks its fields when built (same messages as the old keywords)."""
    with pytest.raises(InputError, match="paths: expected one of 4, 8"):
        MatchOptions(paths=6)
    with pytest.raises(InputError, match="subpixel: expected one of"):
        MatchOptions(subpixel="parabola")
    with pytest.raises(InputError, match="ad_mode: expected one of"):
        MatchOptions(ad_mode="mi")
    with pytest.raises(InputError, match="census_window"):
        MatchOptions(census_window=(4, 5))
    with pytest.raises(InputError, match="census_window"):
        MatchOptions(census_window=(9, 9))
    with pytest.raises(InputError, match="lk_window"):
        MatchOptions(lk_window=4)
    with pytest.raises(InputError, match="p2: expected p2 > p1"):
        MatchOptions(p1=10, p2=10)
    with pytest.raises(InputError, match="p1: expected an integer > 0"):
        MatchOptions(p1=0)
    with pytest.raises(InputError, match="p2: expected at most"):
        MatchOptions(p2=5000)
    with pytest.raises(InputError, match="ad_weight"):
        MatchOptions(ad_weight=-1.0)
    with pytest.raises(InputError, match="fine_window"):
        MatchOptions(fine_window=2)
    with pytest.raises(InputError, match="ad_trunc: expected a finite number > 0"):
        MatchOptions(ad_trunc=0.0)
    with pytest.raises(InputError, match="fine_window: expected an integer, got 3.0"):
        MatchOptions(fine_window=3.0)  # type: ignore[arg-type]
    assert MatchOptions(p1=8, p2=100).p2 == 100 and MatchOptions().speckle_size is None


def test_match_files_writes_pfm(tmp_path: Path) -> None:
    from prism3d.io.images import write_image
    from prism3d.io.pfm import read_pfm

    left, right = _pair(40, 96, 6.0, seed=7)
    write_image(tmp_path / "l.png", left)
    write_image(tmp_path / "r.png", right)
    res = match_files(tmp_path / "l.png", tmp_path / "r.png", tmp_path / "d.pfm", num_disp=12)
    np.testing.assert_array_equal(read_pfm(tmp_path / "d.pfm"), res.disparity)
    write_image(tmp_path / "small.png", left[:, :90])
    with pytest.raises(InputError, match="must have the same size"):
        match_files(tmp_path / "l.png", tmp_path / "small.png", tmp_path / "x.pfm", num_disp=12)
    with pytest.raises(InputError, match="not found"):
        match_files(tmp_path / "nope.png", tmp_path / "r.png", tmp_path / "x.pfm", num_disp=12)
    assert not (tmp_path / "x.pfm").exists()


def test_nothing_matchable_raises() -> None:
    left, right = _pair(20, 40, 3.0)
    # every candidate lies outside the right view: refused before any cost is computed
    with pytest.raises(InputError, match=r"range 100..107 lies outside what a 40 px wide image"):
        match_stereo(left, right, min_disp=100, num_disp=8)
    # no pixel left after the checks (the assembly of an all-invalid raw disparity)
    from prism3d.reconstruct.stereo import match as m

    nan = np.full((20, 40), np.nan, np.float32)
    with pytest.raises(ReconstructionError, match="no pixel passed the consistency checks"):
        m._assemble(nan, np.zeros_like(nan), False, False, None, 0, 7)


def test_a_range_wider_than_the_image_is_clipped_to_it() -> None:
    """--num-disp 125 million on a 40 px image searches the 40 px that can match (no
    gigabytes of cost volume) and gives what the in-image range gives."""
    left, right = _pair(20, 40, 3.0)
    np.testing.assert_array_equal(match_stereo(left, right, min_disp=0, num_disp=125_000_016),
                                  match_stereo(left, right, min_disp=0, num_disp=40))


# ------------------------------------------------------------- real data vs OpenCV SGBM

_SCENES = ["tsukuba", "venus", "teddy", "cones", "aloe", "playground", "terrace", "kitti"]


def _load_scene(root: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(left RGB, right RGB, gt disparity (0 = unknown), evaluation mask or None)."""
    return load_benchmark_pair(root, name)


def _sgbm(left: np.ndarray, right: np.ndarray, num_disp: int) -> np.ndarray:
    n16 = int(math.ceil(num_disp / 16) * 16)
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=n16, blockSize=5, P1=8 * 25, P2=32 * 25,
        uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    d = sgbm.compute(left[:, :, ::-1].copy(), right[:, :, ::-1].copy()).astype(np.float32) / 16
    d[d < 0] = np.nan  # OpenCV's invalid marker counts as bad
    return d


@pytest.mark.realdata
@pytest.mark.parametrize("scene", _SCENES)
def test_beats_opencv_sgbm(shared_data: Path, scene: str) -> None:
    """Dense bad-2.0 at most 0.7x that of OpenCV SGBM-3WAY (holes count as bad)."""
    left, right, gt, mask = _load_scene(shared_data, scene)
    num_disp = math.ceil(float(gt.max()) + 1)
    ours = match_stereo(left, right, min_disp=0, num_disp=num_disp)
    ref = _sgbm(left, right, num_disp)
    s_ours = score_disparity(ours, gt, mask=mask)
    s_ref = score_disparity(ref, gt, mask=mask)
    assert s_ours.density == 1.0
    assert s_ours.bad2 <= 0.7 * s_ref.bad2, (scene, s_ours.bad2, s_ref.bad2)


# ------------------------------------------------------------------ kernel known answers


@pytest.mark.parametrize("kl,radius,nc,scale,clip", [
    (7, 2, 3, 1.0, 45.0), (16, 2, 3, 1.0, 45.0), (37, 2, 3, 0.7, 30.0), (33, 3, 3, 1.0, 45.0),
    (21, 2, 1, 2.3, 15.0)])
def test_matching_cost_kernel_matches_brute_force(kl: int, radius: int, nc: int, scale: float,
                                                  clip: float) -> None:
    """Mirrored-row cost kernel == direct census Hamming + truncated AD, including
    per-pixel windows (coarse-to-fine layout) and out-of-image candidates; whole
    16-candidate vectors and the scalar remainder, 32- and 64-bit census codes."""
    from prism3d.reconstruct.stereo import _match_kernels as k
    from prism3d.reconstruct.stereo.match import _census

    rng = np.random.default_rng(11 + kl)
    h, w = 9, 61
    left = rng.integers(0, 256, (h, w, nc)).astype(np.float32)
    right = rng.integers(0, 256, (h, w, nc)).astype(np.float32)
    cl = _census(left, radius, radius, False)
    cr = _census(right, radius, radius, True)
    assert cl.dtype == (np.uint32 if radius == 2 else np.uint64) and cl.shape == (nc, h, w)
    np.testing.assert_array_equal(cr[:, :, ::-1], _census(right, radius, radius, False))
    fl = np.ascontiguousarray(np.moveaxis(left.astype(np.uint8), 2, 0))
    fr_plain = np.moveaxis(right.astype(np.uint8), 2, 0)
    fr = np.ascontiguousarray(fr_plain[:, :, ::-1])
    dlo = rng.integers(-3, 18, (h, w)).astype(np.int32)
    out = np.empty((h, w, kl), np.uint8)
    k.matching_cost(cl, cr, fl, fr, scale, clip, dlo, kl, np.uint8(36), out)
    in_image = (np.arange(w)[None, :, None] - dlo[:, :, None] - np.arange(kl)) >= 0
    assert in_image.all(axis=2).sum() > 10  # some pixels with every candidate inside
    crp = cr[:, :, ::-1]
    for y in range(h):
        for x in range(w):
            for kk in range(kl):
                xr = x - dlo[y, x] - kk
                if not 0 <= xr < w:
                    assert out[y, x, kk] == 36
                    continue
                ham = sum((int(cl[c, y, x]) ^ int(crp[c, y, xr])).bit_count() for c in range(nc))
                ad = int(np.abs(fl[:, y, x].astype(int) - fr_plain[:, y, xr].astype(int)).sum())
                t = np.minimum(np.float32(ad), np.float32(clip)) * np.float32(scale)
                t = int(min(t + np.float32(0.5), np.float32(255.0)))
                assert out[y, x, kk] == min(255, ham + t), (y, x, kk)


def _speckles_reference(disp: np.ndarray, max_size: int, max_diff: float) -> np.ndarray:
    """Plain Python flood fill: NaN every 4-connected region (neighbours within
    max_diff) smaller than max_size."""
    h, w = disp.shape
    out = disp.copy()
    seen = np.zeros((h, w), bool)
    for y0 in range(h):
        for x0 in range(w):
            if seen[y0, x0] or np.isnan(disp[y0, x0]):
                continue
            seen[y0, x0] = True
            stack, comp = [(y0, x0)], []
            while stack:
                y, x = stack.pop()
                comp.append((y, x))
                for yy, xx in ((y + 1, x), (y - 1, x), (y, x + 1), (y, x - 1)):
                    if 0 <= yy < h and 0 <= xx < w and not seen[yy, xx] and not np.isnan(disp[yy, xx]) \
                            and abs(disp[yy, xx] - disp[y, x]) <= max_diff:
                        seen[yy, xx] = True
                        stack.append((yy, xx))
            if len(comp) < max_size:
                for y, x in comp:
                    out[y, x] = np.nan
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_speckle_removal_matches_flood_fill(seed: int) -> None:
    """Union-find over row runs == a plain flood fill (tall thin regions, regions of
    exactly max_size, NaN gaps, plateaus joined only through one pixel pair)."""
    from prism3d.reconstruct.stereo import _match_kernels as K

    rng = np.random.default_rng(seed)
    h, w = 61, 47
    disp = np.round(rng.uniform(0, 6, (h, w)) / 1.5) * 1.5  # plateaus of equal values
    disp[rng.random((h, w)) < 0.15] = np.nan
    disp[5:60, 20] = 50.0  # a 1-px wide column crossing every stripe: 55 pixels
    disp[5:60, 19] = np.nan
    disp[5:60, 21] = np.nan
    disp[40:51, 30] = 80.0  # a U: two arms that meet only in its bottom row (27 px)
    disp[40:51, 36] = 80.0
    disp[50, 30:37] = 80.0
    disp = disp.astype(np.float32)
    for max_size in (4, 12, 27, 28, 55, 56):
        ref = _speckles_reference(disp, max_size, 1.0)
        got = disp.copy()
        K.remove_speckles(got, max_size, np.float64(1.0))
        assert np.array_equal(np.isnan(got), np.isnan(ref)), max_size
        kept = ~np.isnan(got)
        assert np.array_equal(got[kept], disp[kept])


def test_median_network_and_window_median() -> None:
    """The 3x3 median network selects the median of every 0/1 input (0-1 principle:
    then of any input) and of random values; the window median with NaN neighbours
    (slow path) and at the border matches numpy."""
    import itertools

    from prism3d.reconstruct.stereo import _match_kernels as K

    for bits in itertools.product([0.0, 1.0], repeat=9):
        assert K._median9(*bits) == sorted(bits)[4], bits
    rng = np.random.default_rng(9)
    for _ in range(500):
        a = rng.integers(0, 4, 9).astype(np.float32)
        assert K._median9(*a) == np.median(a)
    filled = rng.uniform(0, 20, (6, 7)).astype(np.float32)
    filled[2, 3] = np.nan
    raw = np.full_like(filled, np.nan)  # every pixel invalid: every output a median
    out = np.empty_like(filled)
    valid = np.empty(filled.shape, bool)
    conf = np.empty_like(filled)
    K.median_fill_final(filled, raw, np.zeros_like(filled), 1, out, valid, conf)
    pad = np.pad(filled, 1, mode="edge")
    for y in range(6):
        for x in range(7):
            win = pad[y:y + 3, x:x + 3]
            win = win[~np.isnan(win)]
            assert out[y, x] == np.sort(win)[len(win) // 2], (y, x)
    assert not valid.any() and (conf == 0).all()
