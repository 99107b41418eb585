"""Tests of the 16-lane vector intrinsics (prism3d.reconstruct.stereo._simd) against numpy,
and of the SGM kernels' vector paths against a plain-Python SGM."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from prism3d.reconstruct.stereo import _match_kernels as K
from prism3d.reconstruct.stereo._simd import (
    v8f_acc64,
    v8f_broadcast,
    v8f_fma,
    v8f_load,
    v8f_zero,
    v16_add,
    v16_broadcast,
    v16_fill_bits,
    v16_fill_range,
    v16_keys,
    v16_load,
    v16_load_num,
    v16_load_u8,
    v16_lt,
    v16_max,
    v16_min,
    v16_mul,
    v16_narrow,
    v16_popcount,
    v16_reduce_min,
    v16_reverse,
    v16_store,
    v16_store_u8,
    v16_sub,
    v16_to_f32,
    v16_to_u16,
    v16_xor,
    v16_zero,
)


@njit(cache=False)
def _integer_ops(a, b, c32, d32, c64, u8, out16, out32, out8, scal):
    va = v16_load(a, 1)  # unaligned
    vb = v16_load(b, 0)
    v16_store(out16, 0, v16_add(va, vb))
    v16_store(out16, 16, v16_sub(va, vb))
    v16_store(out16, 32, v16_mul(va, vb))
    v16_store(out16, 48, v16_xor(va, vb))
    v16_store(out16, 64, v16_min(va, vb))
    v16_store(out16, 80, v16_max(va, vb))
    v16_store(out16, 96, v16_broadcast(va, 70000))  # truncates like astype
    v16_store(out16, 112, v16_load_u8(u8, 3))
    v16_store(out16, 128, v16_narrow(v16_popcount(v16_xor(v16_load(c32, 0),
                                                          v16_load(d32, 0)))))
    v16_store(out16, 144, v16_narrow(v16_popcount(v16_load(c64, 0))))
    v16_store(out16, 160, v16_fill_range(va, 3, 5, 7))
    v16_store(out16, 176, v16_fill_range(va, -4, 1, 9))
    v16_store(out16, 192, v16_fill_range(va, 14, 40, 9))
    v16_store(out16, 208, v16_fill_range(va, 9, 2, 9))  # empty range
    v16_store(out16, 224, v16_fill_bits(va, 0b1000000000000101, 3))
    v16_store(out32, 0, v16_keys(va, 100))
    v16_store(out32, 16, v16_min(v16_load(c32, 0), v16_load(d32, 0)))
    v16_store_u8(out8, 0, v16_add(va, vb))
    scal[0] = v16_reduce_min(va)
    scal[1] = v16_reduce_min(v16_load(c32, 0))


@njit(cache=False)
def _float_ops(x, y, out, out16):
    vx = v16_load(x, 0)
    vy = v16_load(y, 0)
    v16_store(out, 0, v16_add(vx, vy))
    v16_store(out, 16, v16_sub(vx, vy))
    v16_store(out, 32, v16_mul(vx, vy))
    v16_store(out, 48, v16_min(vx, vy))
    v16_store(out, 64, v16_max(vx, vy))
    v16_store(out, 80, v16_broadcast(vx, 0.1))  # float64 -> float32 like astype
    u = v16_load(out16, 0)
    v16_store(out, 96, v16_to_f32(u))
    v16_store(out16, 16, v16_to_u16(v16_add(v16_min(vx, v16_broadcast(vx, 300.0)),
                                            v16_broadcast(vx, 0.5))))


def test_integer_intrinsics_match_numpy() -> None:
    rng = np.random.default_rng(3)
    a = rng.integers(0, 65536, 17).astype(np.uint16)
    b = rng.integers(0, 65536, 16).astype(np.uint16)
    c32 = rng.integers(0, 2**32, 16, dtype=np.uint64).astype(np.uint32)
    d32 = rng.integers(0, 2**32, 16, dtype=np.uint64).astype(np.uint32)
    c64 = rng.integers(0, 2**63, 16, dtype=np.uint64) * np.uint64(2) + np.uint64(1)
    u8 = rng.integers(0, 256, 20).astype(np.uint8)
    out16 = np.zeros(240, np.uint16)
    out32 = np.zeros(32, np.uint32)
    out8 = np.zeros(16, np.uint8)
    scal = np.zeros(2, np.uint64)
    _integer_ops(a, b, c32, d32, c64, u8, out16, out32, out8, scal)
    va = a[1:17]
    with np.errstate(over="ignore"):
        np.testing.assert_array_equal(out16[0:16], va + b)
        np.testing.assert_array_equal(out16[16:32], va - b)
        np.testing.assert_array_equal(out16[32:48], va * b)
    np.testing.assert_array_equal(out16[48:64], va ^ b)
    np.testing.assert_array_equal(out16[64:80], np.minimum(va, b))
    np.testing.assert_array_equal(out16[80:96], np.maximum(va, b))
    np.testing.assert_array_equal(out16[96:112], np.full(16, 70000 % 65536))
    np.testing.assert_array_equal(out16[112:128], u8[3:19])
    pc = [(int(p) ^ int(q)).bit_count() for p, q in zip(c32, d32)]
    np.testing.assert_array_equal(out16[128:144], pc)
    np.testing.assert_array_equal(out16[144:160], [int(v).bit_count() for v in c64])
    lanes = np.arange(16)
    np.testing.assert_array_equal(out16[160:176], np.where((lanes >= 3) & (lanes <= 5), 7, va))
    np.testing.assert_array_equal(out16[176:192], np.where(lanes <= 1, 9, va))
    np.testing.assert_array_equal(out16[192:208], np.where(lanes >= 14, 9, va))
    np.testing.assert_array_equal(out16[208:224], va)
    np.testing.assert_array_equal(out16[224:240], np.where(np.isin(lanes, [0, 2, 15]), 3, va))
    np.testing.assert_array_equal(out32[:16], (va.astype(np.uint32) << 16) | (100 + lanes))
    np.testing.assert_array_equal(out32[16:], np.minimum(c32, d32))
    with np.errstate(over="ignore"):
        np.testing.assert_array_equal(out8, (va + b).astype(np.uint8))
    assert scal[0] == va.min() and scal[1] == c32.min()


def test_float_intrinsics_match_numpy_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    x = rng.uniform(-1000, 1000, 16).astype(np.float32)
    x[:4] = [0.0, 299.5, 300.0, 1e-7]
    y = rng.uniform(-1000, 1000, 16).astype(np.float32)
    out = np.zeros(112, np.float32)
    out16 = np.zeros(32, np.uint16)
    out16[:16] = rng.integers(0, 65536, 16)
    _float_ops(x, y, out, out16)
    np.testing.assert_array_equal(out[0:16], x + y)
    np.testing.assert_array_equal(out[16:32], x - y)
    np.testing.assert_array_equal(out[32:48], x * y)
    np.testing.assert_array_equal(out[48:64], np.minimum(x, y))
    np.testing.assert_array_equal(out[64:80], np.maximum(x, y))
    np.testing.assert_array_equal(out[80:96], np.full(16, np.float32(0.1)))
    np.testing.assert_array_equal(out[96:112], out16[:16].astype(np.float32))
    # to_u16 is defined for lanes in [0, 65536): compare there
    want = np.minimum(x, np.float32(300.0)) + np.float32(0.5)
    ok = want >= 0
    assert ok.sum() >= 6
    np.testing.assert_array_equal(out16[16:][ok], want[ok].astype(np.uint16))


@njit(cache=False)
def _compare_ops(u8, f32, out32, out64):
    a = v16_load_num(u8, 0)  # uint8 -> 16-bit lanes
    b = v16_load_num(u8, 16)
    z32 = v16_zero(out32)
    v16_store(out32, 0, v16_lt(a, b, z32))
    v16_store(out32, 16, v16_reverse(v16_load(out32, 0)))
    v16_store(out32, 32, v16_add(z32, v16_broadcast(z32, 0)))
    fa = v16_load_num(f32, 0)
    fb = v16_load_num(f32, 16)
    v16_store(out64, 0, v16_lt(fa, fb, v16_zero(out64)))


def test_compare_reverse_zero_intrinsics() -> None:
    rng = np.random.default_rng(5)
    u8 = rng.integers(0, 256, 32).astype(np.uint8)
    u8[16:20] = u8[0:4]  # equal lanes compare False
    f32 = rng.uniform(-5, 5, 32).astype(np.float32)
    f32[16] = np.nan  # NaN compares False (ordered), like the scalar "<"
    f32[17] = f32[1]
    out32 = np.ones(48, np.uint32)
    out64 = np.ones(16, np.uint64)
    _compare_ops(u8, f32, out32, out64)
    want = (u8[:16] < u8[16:]).astype(np.uint32)
    np.testing.assert_array_equal(out32[:16], want)
    np.testing.assert_array_equal(out32[16:32], want[::-1])
    np.testing.assert_array_equal(out32[32:], 0)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(out64, (f32[:16] < f32[16:]).astype(np.uint64))


@njit(cache=False)
def _float8_ops(q, lrow, acc):
    f = v8f_zero()
    for u in range(5):
        f = v8f_fma(v8f_broadcast(lrow[u]), v8f_load(q, 1 + u), f)
    v8f_acc64(acc, 0, f, 1.0)
    v8f_acc64(acc, 8, f, -1.0)


@njit(cache=False, fastmath={"contract"})
def _float8_scalar(q, lrow, acc):
    """The same sums one lane at a time, as the scalar kernel computed them (fused
    multiply-adds where the CPU has them)."""
    for m in range(8):
        f = np.float32(0.0)
        for u in range(5):
            f += lrow[u] * q[1 + u + m]
        acc[m] += 1.0 * np.float64(f)
        acc[8 + m] += -1.0 * np.float64(f)


def test_float8_intrinsics_match_scalar_sums() -> None:
    """Eight sums of products as vector lanes == the scalar loop they replaced, bit
    for bit, accumulated in float64."""
    rng = np.random.default_rng(6)
    q = rng.uniform(-3, 3, 16).astype(np.float32)
    lrow = rng.uniform(-3, 3, 5).astype(np.float32)
    start = rng.uniform(-1, 1, 16)
    acc = start.copy()
    ref = start.copy()
    _float8_ops(q, lrow, acc)
    _float8_scalar(q, lrow, ref)
    np.testing.assert_array_equal(acc, ref)
    exact = np.array([sum(float(lrow[u]) * float(q[1 + u + m]) for u in range(5))
                      for m in range(8)])
    np.testing.assert_allclose(acc[:8] - start[:8], exact, rtol=0, atol=1e-5)
    np.testing.assert_allclose(acc[8:] - start[8:], -exact, rtol=0, atol=1e-5)


def test_three_lane_masks() -> None:
    """_three_lanes(s): bits of the lanes s, s+1, s+2 inside 0..15, for any s."""
    for s0 in range(-6, 22):
        want = sum(1 << i for i in (s0, s0 + 1, s0 + 2) if 0 <= i < 16)
        assert K._three_lanes(s0) == want, s0


def _census_reference(img: np.ndarray, ry: int, rx: int) -> np.ndarray:
    """Plain census: bit set when the neighbour (borders replicated) is darker than
    the centre, neighbours in row-major order, the first in the highest bit."""
    h, w, nc = img.shape
    out = np.zeros((nc, h, w), np.uint64)
    for dy in range(-ry, ry + 1):
        for dx in range(-rx, rx + 1):
            if dy == 0 and dx == 0:
                continue
            ys = np.clip(np.arange(h) + dy, 0, h - 1)
            xs = np.clip(np.arange(w) + dx, 0, w - 1)
            nbr = img[ys][:, xs]
            bit = (nbr < img).astype(np.uint64)
            out = (out << np.uint64(1)) | np.moveaxis(bit, 2, 0)
    return out


@pytest.mark.parametrize("dtype,ry,rx,w", [(np.uint8, 2, 2, 45), (np.float32, 2, 2, 37),
                                           (np.uint8, 3, 3, 40), (np.uint8, 1, 4, 16),
                                           (np.float32, 2, 1, 3), (np.uint8, 2, 2, 1),
                                           (np.uint8, 2, 2, 20), (np.uint8, 2, 2, 36)])
def test_census_kernel_matches_reference(dtype, ry: int, rx: int, w: int) -> None:
    """16-pixel vector chunks, the remainder and the clamped borders, mirrored rows,
    32- and 64-bit codes, uint8 and float images (equal values set no bit)."""
    rng = np.random.default_rng(w)
    h, nc = 7, 3
    img = rng.integers(0, 6, (h, w, nc)).astype(dtype)  # many equal neighbours
    nbits = (2 * ry + 1) * (2 * rx + 1) - 1
    ctype = np.uint32 if nbits <= 32 else np.uint64
    ref = _census_reference(img, ry, rx)
    for reverse in (False, True):
        out = np.empty((nc, h, w), ctype)
        K.census_hwc(img, ry, rx, reverse, out)
        got = out[:, :, ::-1] if reverse else out
        np.testing.assert_array_equal(got.astype(np.uint64), ref)


# ------------------------------------------------- SGM kernels against plain Python


def _p2(p1: int, p2: int, gamma: float, ga: float, gb: float) -> int:
    v = p1 + (p2 - p1) / (1.0 + abs(float(ga) - float(gb)) / gamma)
    return int(np.uint16(max(v, p1 + 1)))


def _path(cost, dlo, guide, p1, p2, gamma, k_levels, pixels):
    """One SGM path over ``pixels`` (a list of (y, x)) with uint16 semantics."""
    kp = cost.shape[2]
    inf = K.INF16
    pad = np.array([0 if k < k_levels else inf for k in range(kp)])
    out = {}
    prev = None
    for y, x in pixels:
        c = cost[y, x].astype(np.int64)
        if prev is None:
            cur = np.maximum(c, pad)
        else:
            (yq, xq), lq = prev
            mp = int(lq.min())
            big = (mp + _p2(p1, p2, gamma, guide[y, x], guide[yq, xq])) % 65536
            sh = int(np.clip(dlo[y, x] - dlo[yq, xq], -k_levels, k_levels))

            def at(j: int, lq: np.ndarray = lq) -> int:
                return int(lq[j]) if 0 <= j < kp else inf

            cur = np.empty(kp, np.int64)
            for k in range(kp):
                j = k + sh
                v = min(at(j), (at(j - 1) + p1) % 65536, (at(j + 1) + p1) % 65536, big)
                cur[k] = max(((c[k] + v) % 65536 - mp) % 65536, pad[k])
        out[(y, x)] = cur
        prev = ((y, x), cur)
    return out


def _sgm_reference(cost, dlo, guide, p1, p2, gamma, k_levels, paths=4):
    h, w, kp = cost.shape
    agg = np.zeros((h, w, kp), np.int64)
    dirs = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    if paths == 8:
        dirs += [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    lines = []
    for dy, dx in dirs:  # every scanline starts where its predecessor leaves the image
        for y0 in range(h):
            for x0 in range(w):
                if 0 <= y0 - dy < h and 0 <= x0 - dx < w:
                    continue
                line, y, x = [], y0, x0
                while 0 <= y < h and 0 <= x < w:
                    line.append((y, x))
                    y, x = y + dy, x + dx
                lines.append(line)
    for line in lines:
        for (y, x), lv in _path(cost, dlo, guide, p1, p2, gamma, k_levels, line).items():
            agg[y, x] += lv
    return agg % 65536


def _wta_reference(agg, dlo, k_levels, uniqueness):
    h, w, _ = agg.shape
    disp = np.full((h, w), np.nan, np.float32)
    conf = np.zeros((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            row = agg[y, x, :k_levels].astype(np.int64)
            b = int(np.argmin(row))
            m = int(row[b])
            rest = [int(row[k]) for k in range(k_levels) if not b - 1 <= k <= b + 1]
            g = 1.0 if not rest else (min(rest) - m) / max(min(rest), 1)
            conf[y, x] = g
            if g * 100.0 < uniqueness:
                continue
            off = 0.0
            if 0 < b < k_levels - 1:
                cm, cp = float(row[b - 1]), float(row[b + 1])
                den = max(cm, cp) - m
                if den > 0:
                    off = 0.5 * (cm - cp) / den
            disp[y, x] = np.float32(dlo[y, x] + b + off)
    return disp, conf


@pytest.mark.parametrize("kp,k_levels,paths,jump", [
    (16, 16, 4, 2), (16, 13, 4, 2), (32, 21, 4, 2), (17, 15, 4, 2), (48, 40, 4, 2),
    (16, 13, 4, 20), (16, 13, 8, 20), (32, 32, 8, 2), (13, 13, 8, 15)])
def test_sgm_kernels_match_plain_python(kp: int, k_levels: int, paths: int, jump: int) -> None:
    """4- and 8-path SGM + winner-take-all of the kernels (16-lane vectors when ``kp``
    is a multiple of 16, scalar loops otherwise) == a plain-Python SGM, with padded
    levels and per-pixel windows (coarse-to-fine shifts, also beyond the window)."""
    rng = np.random.default_rng(kp * 100 + k_levels + paths + jump)
    h, w = 7, 19
    cost = rng.integers(0, 90, (h, w, kp)).astype(np.uint8)
    # a smooth valley so that the winners are unique and the fits interior
    cost[:, :, : k_levels] //= 2
    cost[:, :, 5] = rng.integers(0, 4, (h, w))
    dlo = (30 + rng.integers(-jump, jump + 1, (h, w))).astype(np.int32)
    guide = rng.uniform(0, 255, (h, w)).astype(np.float32)
    p1, p2, gamma = 24, 300, 20.0
    agg = np.empty((h, w, kp), np.uint16)
    K.sgm_horizontal(cost, dlo, guide, np.int32(p1), np.int32(p2), gamma, k_levels, agg)
    if paths == 8:
        for dy, dx in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            K.aggregate_path(cost, dlo, guide, np.int32(p1), np.int32(p2), gamma, dy, dx,
                             k_levels, agg)
    disp = np.empty((h, w), np.float32)
    conf = np.empty((h, w), np.float32)
    K.sgm_vertical_wta(cost, dlo, guide, np.int32(p1), np.int32(p2), gamma, k_levels, 16, 5.0,
                       agg, disp, conf)
    ref = _sgm_reference(cost, dlo, guide, p1, p2, gamma, k_levels, paths)
    np.testing.assert_array_equal(agg[:, :, :k_levels], ref[:, :, :k_levels])
    rd, rc = _wta_reference(ref, dlo, k_levels, 5.0)
    np.testing.assert_allclose(conf, rc, rtol=1e-6)
    np.testing.assert_array_equal(np.isnan(disp), np.isnan(rd))
    np.testing.assert_allclose(disp, rd, rtol=0, atol=1e-5)
    assert np.isfinite(disp).mean() > 0.3


def _lr_reference(agg, dlo, k_levels, max_diff, disp):
    """Right-view winner-take-all (smallest cost, then smallest disparity) and the
    left-right check, plainly."""
    h, w, _ = agg.shape
    out = disp.copy()
    for y in range(h):
        best = {}
        for x in range(w):
            for k in range(k_levels):
                xr = x - int(dlo[y, x]) - k
                if 0 <= xr < w:
                    cand = (int(agg[y, x, k]), int(dlo[y, x]) + k)
                    best[xr] = min(best.get(xr, cand), cand)
        for x in range(w):
            d = out[y, x]
            if np.isnan(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if xr not in best or abs(np.float32(best[xr][1]) - d) > max_diff:
                out[y, x] = np.nan
    return out


@pytest.mark.parametrize("kp,k_levels,varying", [(16, 16, False), (32, 21, False),
                                                  (64, 64, False), (48, 40, False),
                                                  (80, 67, False), (32, 32, True),
                                                  (17, 15, False)])
def test_left_right_check_matches_plain_python(kp: int, k_levels: int, varying: bool) -> None:
    """The right-view keys slid through registers (one window start per row, 16..64
    levels in whole vectors) or kept per pixel (other widths, per-pixel windows) ==
    a plain right-view winner-take-all; ties go to the smaller disparity."""
    rng = np.random.default_rng(kp + k_levels + varying)
    h, w = 5, 90
    if varying:
        dlo = rng.integers(-3, 6, (h, w)).astype(np.int32)
    else:
        dlo = np.full((h, w), 7, np.int32)
        dlo[1] = -5  # rows with other starts, negative too
    # a per-row true disparity: mostly consistent views, with ties (coarse costs)
    dt = (dlo.min(axis=1) + rng.integers(2, k_levels - 2, h))[:, None, None]
    lev = dlo[:, :, None] + np.arange(kp)
    agg = (np.abs(lev - dt) // 2 + rng.integers(0, 3, (h, w, kp))).astype(np.uint16)
    agg[:, :, k_levels:] = 4 * K.INF16
    disp = (dt[:, :, 0] + rng.uniform(-0.6, 0.6, (h, w))).astype(np.float32)
    wrong = rng.random((h, w)) < 0.2
    disp[wrong] += rng.integers(-8, 9, wrong.sum()).astype(np.float32)
    disp[rng.random((h, w)) < 0.1] = np.nan
    ref = _lr_reference(agg, dlo, k_levels, 1.0, disp)
    got = disp.copy()
    K.right_lr_check(agg, dlo, k_levels, 1.0, got)
    np.testing.assert_array_equal(got, ref)
    assert 0.05 < np.isnan(got).mean() < 0.95


def test_kernels_record_the_intrinsics_they_were_compiled_with() -> None:
    """numba caches the kernels by the hash of _match_kernels.py alone; the hash of
    _simd.py recorded there must be current, or cached kernels could be stale."""
    import hashlib
    from pathlib import Path

    from prism3d.reconstruct.stereo import _simd

    digest = hashlib.sha256(Path(_simd.__file__).read_bytes()).hexdigest()
    assert digest == K._SIMD_SHA256, (
        "reconstruct/stereo/_simd.py changed: set _SIMD_SHA256 in reconstruct/stereo/_match_kernels.py "
        f"to {digest!r} (so that numba recompiles the kernels)")
