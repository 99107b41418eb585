"""Numba kernels of the semi-global stereo matcher (private; see :mod:`.match`).

Pixel ``(y, x)`` searches the ``K`` disparities ``dlo[y, x] + k``, ``k = 0 .. K-1``
(a full search: ``dlo == min_disp``). Costs are (H, W, K) uint8 (matching) and uint16
(aggregated), K padded to whole 16-level vectors; census codes are planar (C, H, W)
with the right view's rows mirrored, so a pixel's candidates are contiguous. Hot
loops use the 16-lane vectors of :mod:`._simd`. Layout and why: docs/matching.md.

References: Zabih & Woodfill, ECCV 1994 (census); Hirschmüller, TPAMI 2008 (SGM);
Rothermel et al., LC3D 2012 (tSGM); Shimizu & Okutomi, IJCV 2005 (sub-pixel);
Lucas & Kanade, IJCAI 1981.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from ._simd import (
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
    v16_lane,
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
    v16_slide,
    v16_store,
    v16_store_u8,
    v16_sub,
    v16_to_f32,
    v16_to_u16,
    v16_xor,
    v16_zero,
)

INF16 = 0x3FFF  # "no such disparity" in uint16 path costs; sums of 8 stay < 65535

# numba's on-disk cache is keyed by the hash of *this* file only, yet the kernels inline
# the intrinsics of _simd.py: its hash is recorded here, so that editing _simd.py (and
# updating this line, which a test demands) recompiles the kernels
_SIMD_SHA256 = "80f5ba262b22a4ae80826b8cb8f9e3df1d95bd9da286e7d40a9e26a74fd9a7aa"


@intrinsic
def _popcount(typingctx, x):  # pragma: no cover - compiled by numba
    """LLVM ``ctpop`` on an unsigned integer (POPCNT; vectorised as VPOPCNT/PSHUFB)."""
    if not isinstance(x, types.Integer):
        return None
    sig = x(x)

    def codegen(context, builder, signature, args):
        ity = ir.IntType(x.bitwidth)
        fnty = ir.FunctionType(ity, [ity])
        fn = cgutils.get_or_insert_function(builder.module, fnty, f"llvm.ctpop.i{x.bitwidth}")
        return builder.call(fn, args)

    return sig, codegen


# --------------------------------------------------------------------------- census


@njit(cache=True, nogil=True, parallel=True)
def matching_cost(census_l, census_rr, feat_l, feat_rr, ad_scale, ad_clip, dlo, k_levels,
                  oob_cost, out):
    """out (H, W, K) uint8: census Hamming distance over channels + truncated feature
    difference ``floor(ad_scale * min(a, ad_clip) + 0.5)`` of disparity ``dlo + k``,
    saturated at 255; ``oob_cost`` outside the right view. census (C, H, W) uint32/64,
    feat (F, H, W) uint8 (F may be 0); the right ones with mirrored rows.
    """
    h, w = census_l.shape[1:]
    clip = np.float32(ad_clip)
    scale = np.float32(ad_scale)
    nc = census_l.shape[0]
    nf = feat_l.shape[0]
    for y in prange(h):
        acc = np.empty(k_levels, np.uint16)
        adb = np.empty(k_levels, np.uint16)
        # the usual colour case (3 census channels, 3 features) with the row views
        # made once per row and the channels unrolled (per-pixel views cost ~25 %)
        rgb = nc == 3 and nf == 3
        r0 = census_rr[0, y]
        r1 = census_rr[min(1, nc - 1), y]
        r2 = census_rr[min(2, nc - 1), y]
        q0 = feat_rr[0, y] if nf > 0 else adb.view(np.uint8)
        q1 = feat_rr[min(1, nf - 1), y] if nf > 0 else q0
        q2 = feat_rr[min(2, nf - 1), y] if nf > 0 else q0
        orow = out[y].reshape(-1)
        z = v16_zero(acc)  # a uint16 zero vector
        half = v16_broadcast(v16_to_f32(z), 0.5)
        vsat = v16_broadcast(half, 255.0)
        vclip = v16_broadcast(half, clip)
        vscale = v16_broadcast(half, scale)
        u255 = v16_broadcast(z, 255)
        for x in range(w):
            d0 = dlo[y, x]
            o = out[y, x]
            # candidates with 0 <= x - d0 - k < w
            k_lo = max(0, x - d0 - (w - 1))
            k_hi = min(k_levels, x - d0 + 1)
            if k_hi <= k_lo:
                o[:] = oob_cost
                continue
            # whole 16-candidate vectors first, then the scalar remainder
            jb = w - 1 - x + d0
            if rgb:
                k_v = _cost16_rgb(census_l, feat_l, r0, r1, r2, q0, q1, q2, y, x, jb, k_lo,
                                  k_hi, orow, x * k_levels, z, half, vsat, vclip, vscale, u255)
            else:
                k_v = _cost16(census_l, census_rr, feat_l, feat_rr, scale, clip, y, x, jb,
                              k_lo, k_hi, o)
            if k_v < k_hi:
                _cost_scalar(census_l, census_rr, feat_l, feat_rr, scale, clip, y, x, jb,
                             k_v, k_hi, acc, adb, o)
            for k in range(k_lo):
                o[k] = oob_cost
            for k in range(k_hi, k_levels):
                o[k] = oob_cost


@njit(cache=True, nogil=True, inline="always")
def _cost16_rgb(census_l, feat_l, r0, r1, r2, q0, q1, q2, y, x, jb, k_v, k_hi, orow, ob, z,
                half, vsat, vclip, vscale, u255):
    """:func:`_cost16` for 3 channels and 3 features on the right rows ``r*``, ``q*``."""
    c0 = census_l[0, y, x]
    c1 = census_l[1, y, x]
    c2 = census_l[2, y, x]
    p0 = v16_broadcast(z, feat_l[0, y, x])
    p1 = v16_broadcast(z, feat_l[1, y, x])
    p2 = v16_broadcast(z, feat_l[2, y, x])
    while k_v + 16 <= k_hi:
        j = jb + k_v
        e0 = v16_load(r0, j)
        e1 = v16_load(r1, j)
        e2 = v16_load(r2, j)
        a = v16_add(v16_add(v16_narrow(v16_popcount(v16_xor(e0, v16_broadcast(e0, c0)))),
                            v16_narrow(v16_popcount(v16_xor(e1, v16_broadcast(e1, c1))))),
                    v16_narrow(v16_popcount(v16_xor(e2, v16_broadcast(e2, c2)))))
        g0 = v16_load_u8(q0, j)
        g1 = v16_load_u8(q1, j)
        g2 = v16_load_u8(q2, j)
        v = v16_add(v16_add(v16_sub(v16_max(p0, g0), v16_min(p0, g0)),
                            v16_sub(v16_max(p1, g1), v16_min(p1, g1))),
                    v16_sub(v16_max(p2, g2), v16_min(p2, g2)))
        t = v16_to_u16(v16_min(v16_add(v16_mul(v16_min(v16_to_f32(v), vclip),
                                               vscale), half), vsat))
        v16_store_u8(orow, ob + k_v, v16_min(v16_add(a, t), u255))
        k_v += 16
    return k_v


@njit(cache=True, nogil=True, inline="always")
def _cost16(census_l, census_rr, feat_l, feat_rr, scale, clip, y, x, jb, k_lo, k_hi, o):
    """Costs of candidates ``k_lo ..`` in whole 16-lane vectors (right pixel ``jb + k``);
    returns the first candidate left for the scalar loop.
    """
    nc = census_l.shape[0]
    nf = feat_l.shape[0]
    k = k_lo
    if k + 16 > k_hi:
        return k
    z = v16_load_u8(o, 0)
    half = v16_broadcast(v16_to_f32(z), 0.5)
    vsat = v16_broadcast(half, 255.0)
    vclip = v16_broadcast(half, clip)
    vscale = v16_broadcast(half, scale)
    u255 = v16_broadcast(z, 255)
    while k + 16 <= k_hi:
        j = jb + k
        a = v16_broadcast(z, 0)
        for c in range(nc):
            r = v16_load(census_rr[c, y], j)
            d = v16_xor(r, v16_broadcast(r, census_l[c, y, x]))
            a = v16_add(a, v16_narrow(v16_popcount(d)))
        if nf > 0:
            v = v16_broadcast(z, 0)
            for f in range(nf):
                q = v16_load_u8(feat_rr[f, y], j)
                p = v16_broadcast(z, feat_l[f, y, x])
                v = v16_add(v, v16_sub(v16_max(p, q), v16_min(p, q)))
            t = v16_to_u16(v16_min(v16_add(v16_mul(v16_min(v16_to_f32(v), vclip), vscale),
                                           half), vsat))
            a = v16_add(a, t)
        v16_store_u8(o, k, v16_min(a, u255))
        k += 16
    return k


@njit(cache=True, nogil=True, inline="always")
def _cost_scalar(census_l, census_rr, feat_l, feat_rr, scale, clip, y, x, jb, k0, k_hi,
                 acc, adb, o):
    """Costs of candidates ``k0 .. k_hi - 1``, one at a time (see :func:`_cost16`)."""
    nc = census_l.shape[0]
    nf = feat_l.shape[0]
    half = np.float32(0.5)
    sat = np.float32(255.0)
    u255 = np.uint16(255)
    n = k_hi - k0
    j0 = jb + k0
    a = acc[:n]
    c0 = census_l[0, y, x]
    r0 = census_rr[0, y, j0:j0 + n]
    for k in range(n):
        a[k] = np.uint16(_popcount(c0 ^ r0[k]))
    for c in range(1, nc):
        cc = census_l[c, y, x]
        rc = census_rr[c, y, j0:j0 + n]
        for k in range(n):
            a[k] = np.uint16(a[k] + np.uint16(_popcount(cc ^ rc[k])))
    ob = o[k0:k_hi]
    if nf > 0:
        v = adb[:n]
        for k in range(n):
            v[k] = 0
        for f in range(nf):
            pf = feat_l[f, y, x]
            qf = feat_rr[f, y, j0:j0 + n]
            for k in range(n):
                v[k] = np.uint16(v[k] + np.uint16(np.uint8(max(pf, qf[k]) - min(pf, qf[k]))))
        for k in range(n):
            t = np.uint16(min(min(np.float32(v[k]), clip) * scale + half, sat))
            ob[k] = np.uint8(min(np.uint16(a[k] + t), u255))
    else:
        for k in range(n):
            ob[k] = np.uint8(min(a[k], u255))


# ------------------------------------------------------------------- SGM aggregation


@njit(cache=True, nogil=True, inline="always")
def _p2_eff(p1, p2, ia, ib, gamma):
    g = abs(ia - ib)
    v = p1 + (p2 - p1) / (1.0 + g / gamma)
    return np.int32(v) if v > p1 + 1 else np.int32(p1 + 1)


@njit(cache=True, nogil=True, inline="always")
def _step(costf, coff, lp, minprev, shift, lc, aggf, kl, p1, p2, pad, k_levels):
    """One SGM recursion on flat arrays, summed into ``aggf``; returns min_k L[k].

    ``L[k] = C[k] + min(Lq[j], Lq[j-1] + P1, Lq[j+1] + P1, min Lq + P2) - min Lq``,
    ``j = k + shift``; the path buffers hold level ``k`` at ``kl + 1 + k``, INF16
    elsewhere (branch-free shifted reads); padded levels stay INF16.
    """
    shift = _clamp_shift(shift, k_levels)
    src = kl + 1 + shift
    dst = kl + 1
    # slices + simple uint16 loops: LLVM vectorises these (32 lanes with AVX-512)
    a = lp[src - 1:src + kl + 1]
    c = costf[coff:coff + kl]
    o = lc[dst:dst + kl]
    g = aggf[coff:coff + kl]
    big = np.uint16(minprev + p2)
    p1u = np.uint16(p1)
    mp = np.uint16(minprev)
    for k in range(kl):
        v = min(min(a[k + 1], np.uint16(a[k] + p1u)), min(np.uint16(a[k + 2] + p1u), big))
        r = max(np.uint16(np.uint16(np.uint16(c[k]) + v) - mp), pad[k])
        o[k] = r
        g[k] = np.uint16(g[k] + r)
    mn = np.uint16(INF16)
    for k in range(kl):
        mn = min(mn, o[k])
    return np.int32(mn)


@njit(cache=True, nogil=True, inline="always")
def _start(costf, coff, lc, aggf, kl, pad):
    """First pixel of a scanline: L = C (padding held at INF16)."""
    dst = kl + 1
    mn = np.int32(INF16)
    for k in range(kl):
        c = np.int32(max(np.uint16(costf[coff + k]), pad[k]))
        lc[dst + k] = np.uint16(c)
        aggf[coff + k] += np.uint16(c)
        mn = min(mn, c)
    return mn


@njit(cache=True, nogil=True, parallel=True)
def aggregate_path(cost, dlo, guide, p1, p2, gamma, dy, dx, k_levels, agg):
    """Add the SGM path direction ``(dy, dx)`` into ``agg`` (H, W, Kp) uint16 from
    ``cost`` (H, W, Kp) uint8; independent scanlines run in parallel (race free).
    """
    h, w, kl = cost.shape
    costf = cost.reshape(-1)
    aggf = agg.reshape(-1)
    n_row = w if dy != 0 else 0
    n_col = (h - (1 if dy != 0 else 0)) if dx != 0 else 0
    y_row = 0 if dy > 0 else h - 1
    x_col = 0 if dx > 0 else w - 1
    y_first = 1 if dy > 0 else 0
    stride = 3 * kl + 2
    for s in prange(n_row + n_col):
        pad = _padding(kl, k_levels)
        if s < n_row:
            y = np.int64(y_row)
            x = np.int64(s)
        else:
            x = np.int64(x_col)
            y = np.int64(s - n_row + y_first)
        lp = np.full(stride, np.uint16(INF16), np.uint16)
        lc = np.full(stride, np.uint16(INF16), np.uint16)
        mn = _start(costf, (y * w + x) * kl, lc, aggf, kl, pad)
        while True:
            yq = y
            xq = x
            y += dy
            x += dx
            if y < 0 or y >= h or x < 0 or x >= w:
                break
            p2e = _p2_eff(p1, p2, guide[y, x], guide[yq, xq], gamma)
            shift = dlo[y, x] - dlo[yq, xq]
            lp, lc = lc, lp
            mn = _step(costf, (y * w + x) * kl, lp, mn, shift, lc, aggf, kl, p1, p2e, pad,
                       k_levels)


@njit(cache=True, nogil=True, parallel=True)
def _speckle_runs(disp, max_diff, run, parent, size):
    """``run[y, x]``: flat index of the start of (y, x)'s horizontal run (-1 for
    NaN); run starts get ``parent[r] = r`` and ``size[r]`` = length. Rows in parallel.
    """
    h, w = disp.shape
    for y in prange(h):
        start = -1
        prev = np.float32(0.0)
        for x in range(w):
            d = disp[y, x]
            if np.isnan(d):
                run[y, x] = -1
                start = -1
                continue
            if start < 0 or abs(d - prev) > max_diff:
                start = y * w + x
                parent[start] = start
                size[start] = 0
            run[y, x] = start
            size[start] += 1
            prev = d


@njit(cache=True, nogil=True, inline="always")
def _uf_root(parent, a):
    """Union-find root of ``a`` (path halving)."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@njit(cache=True, nogil=True, parallel=True)
def _speckle_mark(disp, run, parent, size, max_size):
    """NaN every pixel whose region has fewer than ``max_size`` pixels."""
    h, w = disp.shape
    for y in prange(h):
        for x in range(w):
            r = run[y, x]
            if r >= 0 and size[parent[r]] < max_size:
                disp[y, x] = np.nan


@njit(cache=True, nogil=True)
def remove_speckles(disp, max_size, max_diff):
    """NaN the 4-connected regions (neighbours within ``max_diff``) smaller than
    ``max_size`` px: union-find over row runs, sizes summed at the roots.
    """
    h, w = disp.shape
    run = np.empty((h, w), np.int32)
    parent = np.empty(h * w, np.int32)
    size = np.empty(h * w, np.int32)
    _speckle_runs(disp, max_diff, run, parent, size)
    for y in range(1, h):
        la = -1
        lb = -1
        for x in range(w):
            a = run[y, x]
            b = run[y - 1, x]
            if a < 0 or b < 0 or (a == la and b == lb):
                continue
            if abs(disp[y, x] - disp[y - 1, x]) > max_diff:
                continue
            la = a
            lb = b
            ra = _uf_root(parent, a)
            rb = _uf_root(parent, b)
            if ra == rb:
                continue
            if size[ra] < size[rb]:
                ra, rb = rb, ra
            parent[rb] = ra  # union by size
            size[ra] += size[rb]
    for y in range(h):
        for x in range(w):
            r = y * w + x
            if run[y, x] == r:
                parent[r] = _uf_root(parent, r)
    _speckle_mark(disp, run, parent, size, max_size)


# --------------------------------------------------------------- sub-pixel refinement


@njit(cache=True, nogil=True, parallel=True)
def bspline_rows(img, out):
    """Cubic B-spline coefficients of every row of ``img`` into ``out`` (H, W) float32,
    mirror boundaries (recursive prefilter, pole ``sqrt(3) - 2``; Unser 1999).
    """
    h, w = img.shape
    z = np.sqrt(3.0) - 2.0
    horizon = min(w, 24)
    for y in prange(h):
        cp = np.empty(w, np.float64)
        acc = 0.0
        zk = 1.0
        for k in range(horizon):
            acc += zk * img[y, k]
            zk *= z
        cp[0] = acc
        for k in range(1, w):
            cp[k] = img[y, k] + z * cp[k - 1]
        cm = (z / (z * z - 1.0)) * (cp[w - 1] + z * cp[w - 2]) if w > 1 else cp[0]
        out[y, w - 1] = 6.0 * cm
        for k in range(w - 2, -1, -1):
            cm = z * (cm - cp[k])
            out[y, k] = 6.0 * cm


@njit(cache=True, nogil=True, parallel=True)
def fill_holes(disp, out):
    """Every NaN takes the smaller (background) of the nearest valid disparities left
    and right on its row; rows without any stay NaN (:func:`fill_columns`).
    """
    h, w = disp.shape
    for y in prange(h):
        last = np.nan
        leftv = np.empty(w, np.float32)
        for x in range(w):
            if not np.isnan(disp[y, x]):
                last = disp[y, x]
            leftv[x] = last
        last = np.nan
        for x in range(w - 1, -1, -1):
            d = disp[y, x]
            if not np.isnan(d):
                last = d
                out[y, x] = d
                continue
            a = leftv[x]
            if np.isnan(a):
                out[y, x] = last
            elif np.isnan(last):
                out[y, x] = a
            else:
                out[y, x] = min(a, last)


@njit(cache=True, nogil=True)
def fill_columns(out):
    """Fill rows left all-NaN by :func:`fill_holes` from the nearest filled row."""
    h, w = out.shape
    good = np.zeros(h, np.bool_)
    for y in range(h):
        good[y] = not np.isnan(out[y, 0])
    for y in range(h):
        if good[y]:
            continue
        best = -1
        for r in range(1, h):
            if y - r >= 0 and good[y - r]:
                best = y - r
                break
            if y + r < h and good[y + r]:
                best = y + r
                break
        if best >= 0:
            for x in range(w):
                out[y, x] = out[best, x]


@njit(cache=True, nogil=True, inline="always")
def _median9(a0, a1, a2, a3, a4, a5, a6, a7, a8):  # pragma: no cover - compiled
    """Median of nine values (3x3 selection network, 19 compare-exchanges)."""
    a1, a2 = min(a1, a2), max(a1, a2)
    a4, a5 = min(a4, a5), max(a4, a5)
    a7, a8 = min(a7, a8), max(a7, a8)
    a0, a1 = min(a0, a1), max(a0, a1)
    a3, a4 = min(a3, a4), max(a3, a4)
    a6, a7 = min(a6, a7), max(a6, a7)
    a1, a2 = min(a1, a2), max(a1, a2)
    a4, a5 = min(a4, a5), max(a4, a5)
    a7, a8 = min(a7, a8), max(a7, a8)
    a0, a3 = min(a0, a3), max(a0, a3)
    a5, a8 = min(a5, a8), max(a5, a8)
    a4, a7 = min(a4, a7), max(a4, a7)
    a3, a6 = min(a3, a6), max(a3, a6)
    a1, a4 = min(a1, a4), max(a1, a4)
    a2, a5 = min(a2, a5), max(a2, a5)
    a4, a7 = min(a4, a7), max(a4, a7)
    a4, a2 = min(a4, a2), max(a4, a2)
    a6, a4 = min(a6, a4), max(a6, a4)
    a4, a2 = min(a4, a2), max(a4, a2)
    return a4


@njit(cache=True, nogil=True, inline="always")
def _window_median(filled, y, x, r, buf):  # pragma: no cover - compiled
    """Median of the non-NaN ``filled`` values in the (2r+1)^2 window at (y, x),
    else ``filled[y, x]``; ``buf`` is scratch.
    """
    h, w = filled.shape
    if r == 1 and 0 < y < h - 1 and 0 < x < w - 1:
        a0 = filled[y - 1, x - 1]
        a1 = filled[y - 1, x]
        a2 = filled[y - 1, x + 1]
        a3 = filled[y, x - 1]
        a4 = filled[y, x]
        a5 = filled[y, x + 1]
        a6 = filled[y + 1, x - 1]
        a7 = filled[y + 1, x]
        a8 = filled[y + 1, x + 1]
        s = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7 + a8
        if not np.isnan(s) and not np.isinf(s):
            return _median9(a0, a1, a2, a3, a4, a5, a6, a7, a8)
    m = 0
    for dy in range(-r, r + 1):
        yy = min(max(y + dy, 0), h - 1)
        for dx in range(-r, r + 1):
            xx = min(max(x + dx, 0), w - 1)
            v = filled[yy, xx]
            if not np.isnan(v):
                buf[m] = v
                m += 1
    if m == 0:
        return filled[y, x]
    for i in range(1, m):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v
    return buf[m // 2]


@njit(cache=True, nogil=True, parallel=True)
def median_filled(filled, valid, r, out):
    """Median of the ``(2r+1)^2`` neighbourhood of ``filled`` at non-valid pixels."""
    h, w = filled.shape
    n = (2 * r + 1) * (2 * r + 1)
    for y in prange(h):
        buf = np.empty(n, np.float32)
        for x in range(w):
            if valid[y, x]:
                out[y, x] = filled[y, x]
                continue
            out[y, x] = _window_median(filled, y, x, r, buf)


# --------------------------------------------------------------- coarse-to-fine ranges


@njit(cache=True, nogil=True, parallel=True)
def fine_ranges(coarse, scale, radius, k_levels, dmin, dmax, dlo):
    """dlo (H, W) int32: first level of each pixel's ``k_levels`` window, covering the
    upsampled 3x3 ``coarse`` (h, w) float32 neighbourhood +- ``radius`` when it fits,
    else centred on the pixel's coarse value; within ``[dmin, dmax - k_levels + 1]``.
    """
    hc, wc = coarse.shape
    h, w = dlo.shape
    hi_lim = dmax - k_levels + 1
    for y in prange(h):
        yc = min(max(int((y + 0.5) / scale - 0.5 + 0.5), 0), hc - 1)
        for x in range(w):
            xc = min(max(int((x + 0.5) / scale - 0.5 + 0.5), 0), wc - 1)
            lo = 1e30
            hi = -1e30
            for dy in range(-1, 2):
                yy = min(max(yc + dy, 0), hc - 1)
                for dx in range(-1, 2):
                    xx = min(max(xc + dx, 0), wc - 1)
                    v = coarse[yy, xx]
                    if not np.isnan(v):
                        lo = min(lo, v)
                        hi = max(hi, v)
            c = coarse[yc, xc]
            if np.isnan(c):
                if lo > hi:
                    s = dmin
                    dlo[y, x] = max(min(s, hi_lim), dmin)
                    continue
                c = 0.5 * (lo + hi)
            flo = int(np.floor(lo * scale)) - radius
            fhi = int(np.ceil(hi * scale)) + radius
            if fhi - flo + 1 <= k_levels:
                s = (flo + fhi - k_levels + 1) // 2
            else:
                s = int(np.floor(c * scale + 0.5)) - k_levels // 2
            dlo[y, x] = max(min(s, hi_lim), dmin)


# =========================================================================== fast path
#
# Kernels of the current pipeline (see :func:`.match._match_level`). Compared with the
# generic kernels above they (a) read the interleaved ``(H, W, C)`` image directly,
# (b) fuse passes so that a call needs few parallel launches (each costs a thread
# wake-up with OMP_WAIT_POLICY=passive), (c) keep the per-pixel work of the
# sequential SGM recursions small (P2 of a pixel pair computed once for both
# directions, vectorised, outside the recursion), and (d) refine sub-pixel
# disparities from window sums that do not depend on the fractional shift.


@njit(cache=True, nogil=True)
def channels_equal(img):
    """True when every channel of the ``(H, W, C)`` image equals the first (early exit)."""
    h, w, nc = img.shape
    for y in range(h):
        for x in range(w):
            v = img[y, x, 0]
            for c in range(1, nc):
                if img[y, x, c] != v:
                    return False
    return True


@njit(cache=True, nogil=True, parallel=True)
def census_hwc(img, ry, rx, reverse, out):
    """Census codes out (C, H, W) uint32/uint64 of an (H, W, C) uint8/float32 image:
    bit set when the neighbour is darker (row-major, centre skipped), borders
    replicated, rows mirrored with ``reverse``.
    """
    h, w, nc = img.shape
    one = out.dtype.type(1)
    zero = out.dtype.type(0)
    planes = np.empty((nc, h, w), img.dtype)
    for y in prange(h):
        for c in range(nc):  # channel outermost: contiguous (vectorised) stores
            for x in range(w):
                planes[c, y, x] = img[y, x, c]
    pf = planes.reshape(-1)
    of = out.reshape(-1)
    for y in prange(h):
        for c in range(nc):
            crow = (c * h + y) * w
            # interior: 16 pixels at a time, their codes kept in one vector register
            # (one shift-add per neighbour); flat indices, no per-row views
            x = rx
            while x + 16 <= w - rx or (rx < x < w - rx and w - 2 * rx >= 16):
                if x + 16 > w - rx:
                    x = w - rx - 16  # the last block overlaps the one before
                cv = v16_load_num(pf, crow + x)
                acc = v16_zero(of)
                for dy in range(-ry, ry + 1):
                    nrow = (c * h + min(max(y + dy, 0), h - 1)) * w
                    for dx in range(-rx, rx + 1):
                        if dy == 0 and dx == 0:
                            continue
                        acc = v16_add(v16_add(acc, acc),
                                      v16_lt(v16_load_num(pf, nrow + x + dx), cv, acc))
                if reverse:
                    v16_store(of, crow + w - 16 - x, v16_reverse(acc))
                else:
                    v16_store(of, crow + x, acc)
                x += 16
            # borders (coordinates clamped) and the interior remainder, pixel by pixel
            x_done = min(x, w)
            for i in range(min(rx, w) + (w - x_done)):
                xs = i if i < min(rx, w) else x_done + i - min(rx, w)
                cval = pf[crow + xs]
                b = zero
                for dy in range(-ry, ry + 1):
                    nrow = (c * h + min(max(y + dy, 0), h - 1)) * w
                    for dx in range(-rx, rx + 1):
                        if dy == 0 and dx == 0:
                            continue
                        xx = min(max(xs + dx, 0), w - 1)
                        b = (b << one) | (one if pf[nrow + xx] < cval else zero)
                of[crow + (w - 1 - xs if reverse else xs)] = b


@njit(cache=True, nogil=True, parallel=True)
def features_hwc(left, right, gain, offset, reverse, feat_l, feat_r):
    """Planar uint8 AD features: ``sat(rint(left))`` and ``sat(rint(max(right * gain
    + offset, 0)))`` per channel (float32, as cv2.convertScaleAbs), right rows mirrored
    with ``reverse``.
    """
    h, w, nc = left.shape
    for y in prange(h):
        for c in range(nc):
            g = np.float32(gain[c])
            o = np.float32(offset[c])
            for x in range(w):
                v = np.float32(left[y, x, c])
                feat_l[c, y, x] = np.uint8(min(max(np.rint(v), np.float32(0.0)), np.float32(255.0)))
            # the reversed store is its own loop: a branch inside kept it scalar
            if reverse:
                for x in range(w):
                    v = max(np.float32(right[y, x, c]) * g + o, np.float32(0.0))
                    feat_r[c, y, w - 1 - x] = np.uint8(min(np.rint(v), np.float32(255.0)))
            else:
                for x in range(w):
                    v = max(np.float32(right[y, x, c]) * g + o, np.float32(0.0))
                    feat_r[c, y, x] = np.uint8(min(np.rint(v), np.float32(255.0)))


@njit(cache=True, nogil=True, parallel=True)
def grey_hwc(img, out):
    """(H, W) float32 channel mean of an ``(H, W, C)`` image."""
    h, w, nc = img.shape
    inv = np.float32(1.0 / nc)
    for y in prange(h):
        if nc == 3:  # the usual case, unrolled so that the loop over x vectorises
            for x in range(w):
                s = (np.float32(img[y, x, 0]) + np.float32(img[y, x, 1])) + np.float32(img[y, x, 2])
                out[y, x] = s * inv
            continue
        for x in range(w):
            s = np.float32(0.0)
            for c in range(nc):
                s += np.float32(img[y, x, c])
            out[y, x] = s * inv


@njit(cache=True, nogil=True, inline="always")
def _p2_row(p1, p2, gamma, ga, gb, out):
    """out[i] = adaptive P2 of the pixel pair (ga[i], gb[i]) (vectorised)."""
    fp1 = np.float64(p1)
    dp = np.float64(p2 - p1)
    lo = np.float64(p1 + 1)
    for i in range(out.shape[0]):
        v = fp1 + dp / (1.0 + np.float64(abs(ga[i] - gb[i])) / gamma)
        out[i] = np.uint16(max(v, lo))


@njit(cache=True, nogil=True, inline="always")
def _sgm_step(costf, co, buf, src, dst, aggf, kp, p1u, big, mp, pad, assign):
    """One SGM recursion (:func:`_step`) of the pixel at flat offset ``co``: reads the
    previous path costs at ``buf[src - 1 .. src + kp]``, writes ``buf[dst ..]``,
    assigns or adds into ``aggf``; returns the new min. Whole 16-level vectors when
    ``kp % 16 == 0``, else one fused loop.
    """
    kv = kp - kp % 16
    m = np.uint16(INF16)
    if kv > 0:
        z = v16_load(pad, 0)
        vp1 = v16_broadcast(z, p1u)
        vbig = v16_broadcast(z, big)
        vmp = v16_broadcast(z, mp)
        mv = v16_broadcast(z, INF16)
        for kb in range(0, kv, 16):
            a0 = v16_load(buf, src - 1 + kb)
            a1 = v16_load(buf, src + kb)
            a2 = v16_load(buf, src + 1 + kb)
            v = v16_min(v16_min(a1, v16_add(a0, vp1)), v16_min(v16_add(a2, vp1), vbig))
            c = v16_max(v16_sub(v16_add(v16_load_u8(costf, co + kb), v), vmp),
                        v16_load(pad, kb))
            v16_store(buf, dst + kb, c)
            if assign:
                v16_store(aggf, co + kb, c)
            else:
                v16_store(aggf, co + kb, v16_add(v16_load(aggf, co + kb), c))
            mv = v16_min(mv, c)
        m = v16_reduce_min(mv)
    for k in range(kv, kp):  # levels past the whole vectors (8 paths: unpadded)
        v = min(min(buf[src + k], np.uint16(buf[src - 1 + k] + p1u)),
                min(np.uint16(buf[src + 1 + k] + p1u), big))
        c = max(np.uint16(np.uint16(np.uint16(costf[co + k]) + v) - mp), pad[k])
        buf[dst + k] = c
        aggf[co + k] = c if assign else np.uint16(aggf[co + k] + c)
        m = min(m, c)
    return m


@njit(cache=True, nogil=True, inline="always")
def _sgm_start(costf, co, buf, dst, aggf, kp, pad, assign):
    """First pixel of a path: ``L = C`` into ``buf[dst..]`` and ``aggf[co..]``; returns
    its minimum.
    """
    m = np.uint16(INF16)
    for k in range(kp):
        c = max(np.uint16(costf[co + k]), pad[k])
        buf[dst + k] = c
        aggf[co + k] = c if assign else np.uint16(aggf[co + k] + c)
        m = min(m, c)
    return m


@njit(cache=True, nogil=True, inline="always")
def _clamp_shift(shift, k_levels):
    """Window offset between neighbours clamped to +-k_levels as in :func:`_step`."""
    if shift > k_levels:
        return k_levels
    if shift < -k_levels:
        return -k_levels
    return shift


@njit(cache=True, nogil=True, inline="always")
def _sgm_layout(cost, agg, p1):
    """``h, w, kp``, ``cost`` and ``agg`` flat, the size ``st`` of a pixel's slot in the
    path buffers and the offset ``dst`` of its costs in the slot (room for a shift of
    +-kp and the +-1 levels), and P1 as uint16."""
    h, w, kp = cost.shape
    return h, w, kp, cost.reshape(-1), agg.reshape(-1), 3 * kp + 2, kp + 1, np.uint16(p1)


@njit(cache=True, nogil=True, inline="always")
def _padding(kp, k_levels):
    """(kp,) uint16: 0 for searched levels, INF16 for the padding past ``k_levels``."""
    pad = np.zeros(kp, np.uint16)
    for k in range(k_levels, kp):
        pad[k] = np.uint16(INF16)
    return pad


@njit(cache=True, nogil=True, parallel=True)
def sgm_horizontal(cost, dlo, guide, p1, p2, gamma, k_levels, agg):
    """Left-to-right plus right-to-left SGM paths *assigned* to ``agg`` (H, W, Kp)
    uint16 from ``cost`` (H, W, Kp) uint8; both directions of a row in one loop.
    """
    h, w, kp, costf, aggf, st, dst, p1u = _sgm_layout(cost, agg, p1)
    for y in prange(h):
        pad = _padding(kp, k_levels)
        p2r = np.empty(w, np.uint16)  # p2r[x]: pair (x - 1, x)
        p2r[0] = 0
        _p2_row(p1, p2, gamma, guide[y, 1:], guide[y, :w - 1], p2r[1:])
        ba = np.full(2 * st, np.uint16(INF16), np.uint16)
        bb = np.full(2 * st, np.uint16(INF16), np.uint16)
        row = y * w * kp
        dl = dlo[y]
        ma = _sgm_start(costf, row, ba, dst, aggf, kp, pad, True)
        mb = _sgm_start(costf, row + (w - 1) * kp, bb, dst, aggf, kp, pad,
                        2 * (w - 1) > w - 1)
        cur = 0
        for xa in range(1, w):
            xb = w - 1 - xa
            prev = cur
            cur = st - cur
            sa = _clamp_shift(dl[xa] - dl[xa - 1], k_levels)
            ma = _sgm_step(costf, row + xa * kp, ba, prev + dst + sa, cur + dst, aggf, kp, p1u,
                           np.uint16(ma + p2r[xa]), ma, pad, 2 * xa <= w - 1)
            sb = _clamp_shift(dl[xb] - dl[xb + 1], k_levels)
            mb = _sgm_step(costf, row + xb * kp, bb, prev + dst + sb, cur + dst, aggf, kp, p1u,
                           np.uint16(mb + p2r[xb + 1]), mb, pad, 2 * xb > w - 1)


@njit(cache=True, nogil=True, inline="always")
def _three_lanes(s):
    """Bit mask of the lanes ``s, s + 1, s + 2`` that lie in 0..15 (``s`` any int)."""
    if s >= 16 or s <= -3:
        return 0
    return (7 << s) & 0xFFFF if s >= 0 else 7 >> -s


@njit(cache=True, nogil=True, inline="always")
def _wta(aggf, o, kp, k_levels, d0, uniqueness, disp, conf, y, x):
    """Winner-take-all of one pixel: best level, uniqueness, confidence, equiangular fit."""
    kl = k_levels
    big = np.uint16(0xFFFF)
    if kp % 16 == 0:
        # 16-lane vectors; the first pass takes the minimum of keys cost << 16 |
        # level (the first best level, no branches), the second the best cost outside
        # +-1 level of the winner. Padding levels need no mask: each path holds them
        # at INF16, so their sum (4 or 8 * INF16: 65532, or 65528 after the uint16
        # wrap) exceeds any real sum (at most 8 paths of 255 + P2 <= 5255 each)
        z = v16_load(aggf, o)
        km = v16_keys(z, 0)
        for kb in range(16, kp, 16):
            km = v16_min(km, v16_keys(v16_load(aggf, o + kb), kb))
        key = v16_reduce_min(km)
        m = np.uint16(key >> np.uint32(16))
        b = np.int64(key & np.uint32(0xFFFF))
        sv = v16_fill_bits(z, _three_lanes(b - 1), big)
        for kb in range(16, kp, 16):
            sv = v16_min(sv, v16_fill_bits(v16_load(aggf, o + kb), _three_lanes(b - 1 - kb), big))
        s1 = v16_reduce_min(sv)
    else:
        # minimum and its first level in one vectorisable pass: keys (cost << 16) | level
        # (over a view of the row: with flat indices LLVM left these loops scalar)
        row = aggf[o:o + kp]
        kmin = np.uint32(0xFFFFFFFF)
        for k in range(kl):
            kmin = min(kmin, (np.uint32(row[k]) << np.uint32(16)) | np.uint32(k))
        m = np.uint16(kmin >> np.uint32(16))
        b = np.int64(kmin & np.uint32(0xFFFF))
        # best cost outside +-1 level of the winner (a select, also vectorisable)
        s1 = big
        for k in range(kl):
            s1 = min(s1, row[k] if (k < b - 1 or k > b + 1) else big)
    bc = np.int32(m)
    if b < 2 and b + 2 >= kl:
        g = 1.0
    else:
        second = np.int32(s1)
        g = (second - bc) / max(second, 1)
    conf[y, x] = g
    if g * 100.0 < uniqueness:
        disp[y, x] = np.nan
        return
    off = 0.0
    if 0 < b < kl - 1:
        cm = np.float64(aggf[o + b - 1])
        cp = np.float64(aggf[o + b + 1])
        c0 = np.float64(bc)
        den = max(cm, cp) - c0
        if den > 0:
            off = 0.5 * (cm - cp) / den
    disp[y, x] = np.float32(d0 + b + off)


@njit(cache=True, nogil=True, parallel=True)
def sgm_vertical_wta(cost, dlo, guide, p1, p2, gamma, k_levels, block, uniqueness, agg,
                     disp, conf):
    """Bottom-up then top-down SGM paths added into ``agg``, then winner-take-all into
    ``disp``, ``conf`` (H, W) float32 while the final costs are in cache; columns in
    blocks of ``block``.
    """
    h, w, kp, costf, aggf, st, dst, p1u = _sgm_layout(cost, agg, p1)
    nb = (w + block - 1) // block
    for bi in prange(nb):
        x0 = bi * block
        x1 = min(w, x0 + block)
        nbx = x1 - x0
        pad = _padding(kp, k_levels)
        half = nbx * st  # previous / current path costs alternate between the halves
        buf = np.full(2 * half, np.uint16(INF16), np.uint16)
        mins = np.empty(nbx, np.uint16)
        p2c = np.empty(nbx, np.uint16)
        for direction in range(2):
            dy = -1 if direction == 0 else 1
            y = h - 1 if dy < 0 else 0
            cur = 0
            for i in range(nbx):
                mins[i] = _sgm_start(costf, (y * w + x0 + i) * kp, buf, i * st + dst, aggf, kp,
                                     pad, False)
            if dy > 0:
                for i in range(nbx):
                    _wta(aggf, (y * w + x0 + i) * kp, kp, k_levels, dlo[y, x0 + i], uniqueness,
                         disp, conf, y, x0 + i)
            for _ in range(h - 1):
                yq = y
                y += dy
                prev = cur
                cur = half - cur
                _p2_row(p1, p2, gamma, guide[y, x0:x1], guide[yq, x0:x1], p2c)
                dl = dlo[y]
                dq = dlo[yq]
                for i in range(nbx):
                    x = x0 + i
                    o = i * st
                    sh = _clamp_shift(dl[x] - dq[x], k_levels)
                    mp = mins[i]
                    mins[i] = _sgm_step(costf, (y * w + x) * kp, buf, prev + o + dst + sh,
                                        cur + o + dst, aggf, kp, p1u, np.uint16(mp + p2c[i]),
                                        mp, pad, False)
                if dy > 0:
                    for i in range(nbx):
                        _wta(aggf, (y * w + x0 + i) * kp, kp, k_levels, dlo[y, x0 + i],
                             uniqueness, disp, conf, y, x0 + i)


@njit(cache=True, nogil=True, inline="always")
def _lr_row_sliding(aggf, y, w, kp, d0, dbase, k_levels, key):
    """Right-view keys of row ``y`` for a full search with ``kp`` 16..64: the window
    ``key[jb .. jb + kp - 1]`` slides one pixel a step, kept in vector registers.
    """
    none = np.uint32(0xFFFFFFFF)
    nonev = v16_broadcast(v16_zero(key), none)
    nv = kp // 16
    r0 = nonev
    r1 = nonev
    r2 = nonev
    r3 = nonev
    off = d0 - dbase
    for x in range(w):
        jb = w - 1 - x + d0
        if x > 0:
            top = r0 if nv == 1 else (r1 if nv == 2 else (r2 if nv == 3 else r3))
            j = jb + kp  # the right pixel leaving the window
            if 0 <= j < w:
                key[j] = v16_lane(top, 15)
            r3 = v16_slide(r3, r2)
            r2 = v16_slide(r2, r1)
            r1 = v16_slide(r1, r0)
            r0 = v16_slide(r0, nonev)
        k_lo = max(0, x - d0 - (w - 1))
        k_hi = min(k_levels, x - d0 + 1)
        if k_hi <= k_lo:
            continue
        base = (y * w + x) * kp
        for vi in range(nv):
            kb = 16 * vi
            kv = v16_keys(v16_load(aggf, base + kb), off + kb)
            kv = v16_fill_range(v16_fill_range(kv, -1, k_lo - kb - 1, none), k_hi - kb, 16, none)
            if vi == 0:
                r0 = v16_min(r0, kv)
            elif vi == 1:
                r1 = v16_min(r1, kv)
            elif vi == 2:
                r2 = v16_min(r2, kv)
            else:
                r3 = v16_min(r3, kv)
    for vi in range(nv):
        r = r0 if vi == 0 else (r1 if vi == 1 else (r2 if vi == 2 else r3))
        for i in range(16):
            j = d0 + 16 * vi + i  # the window of the last pixel starts at d0
            if 0 <= j < w:
                key[j] = v16_lane(r, i)


@njit(cache=True, nogil=True, parallel=True)
def right_lr_check(agg, dlo, k_levels, max_diff, disp):
    """Left-right check of ``disp`` in place: each right pixel's winner from the same
    volume (min of keys ``(cost << 16) | (d - min dlo)``, smallest d on ties); NaN
    where the disparities differ by more than ``max_diff``.
    """
    h, w, kp = agg.shape
    aggf = agg.reshape(-1)
    none = np.uint32(0xFFFFFFFF)
    low = np.uint32(0xFFFF)
    if np.int64(dlo.max()) - np.int64(dlo.min()) + k_levels > 0xFFFF:
        raise ValueError("right_lr_check: the disparity range exceeds 65535 levels")
    for y in prange(h):
        dbase = dlo[y, 0]
        dtop = dlo[y, 0]
        for x in range(1, w):
            dbase = min(dbase, dlo[y, x])
            dtop = max(dtop, dlo[y, x])
        key = np.full(w, none, np.uint32)
        if dtop == dbase and kp % 16 == 0 and kp <= 64:
            _lr_row_sliding(aggf, y, w, kp, dbase, dbase, k_levels, key)
        else:
            kk = np.arange(kp).astype(np.uint32)
            for x in range(w):
                d0 = dlo[y, x]
                k_lo = max(0, x - d0 - (w - 1))
                k_hi = min(k_levels, x - d0 + 1)
                if k_hi <= k_lo:
                    continue
                n = k_hi - k_lo
                j0 = w - 1 - x + d0 + k_lo
                kb = key[j0:j0 + n]
                av = agg[y, x, k_lo:k_hi]
                kv = kk[k_lo:k_hi]
                off = np.uint32(d0 - dbase)
                for i in range(n):
                    kb[i] = min(kb[i], (np.uint32(av[i]) << np.uint32(16)) | (kv[i] + off))
        for x in range(w):
            d = disp[y, x]
            if np.isnan(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if xr < 0 or xr >= w:
                disp[y, x] = np.nan
                continue
            kr = key[w - 1 - xr]
            if kr == none or abs(np.float32(dbase + np.int64(kr & low)) - d) > max_diff:
                disp[y, x] = np.nan


@njit(cache=True, nogil=True, inline="always")
def _lk_row_products(lrow, qrow, x, xb, wx, sign, esf):
    """esf[8x + m] += sign * sum_u L(x + u) q(xb - 2 + m + u), m = 0..5, |u| <= wx,
    for one window row (six 8-lane fused multiply-adds; lanes 6, 7 unused).
    """
    q0 = xb - 1 - wx
    l0 = x - wx
    f = v8f_zero()
    for u in range(2 * wx + 1):
        f = v8f_fma(v8f_broadcast(lrow[l0 + u]), v8f_load(qrow, q0 + u), f)
    v8f_acc64(esf, 8 * x, f, sign)


@njit(cache=True, nogil=True, inline="always")
def _gram_row(qpad, v, w, sign, cs):
    """cs[dl, p] += sign * q(v, p) q(v, p + dl), lags dl = 0..3."""
    q = qpad[v, 1:w + 1]
    for dl in range(4):
        c = cs[dl]
        for p in range(w - dl):
            c[p] += sign * (np.float64(q[p]) * np.float64(q[p + dl]))


_NO_RUN = -(1 << 30)  # xb_run of a column without running P sums


@njit(cache=True, nogil=True, inline="always")
def _row_any_valid(disp, y, w):
    for x in range(w):
        if not np.isnan(disp[y, x]):
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _gram_box_sums(cs, sm, w, wx):
    """sm[dl, p] = sum of cs[dl, p - wx .. p + wx] (lags dl = 0..3) along the row: four
    independent running sums in one loop, so that their add chains overlap."""
    nu = 2 * wx + 1
    a0 = a1 = a2 = a3 = 0.0
    for u in range(nu - 1):
        a0 += cs[0, u]
        a1 += cs[1, u]
        a2 += cs[2, u]
        a3 += cs[3, u]
    p_end = w - wx - 3  # every lag has p < w - wx - dl
    for p in range(wx, p_end):
        a0 += cs[0, p + wx]
        a1 += cs[1, p + wx]
        a2 += cs[2, p + wx]
        a3 += cs[3, p + wx]
        sm[0, p] = a0
        sm[1, p] = a1
        sm[2, p] = a2
        sm[3, p] = a3
        a0 -= cs[0, p - wx]
        a1 -= cs[1, p - wx]
        a2 -= cs[2, p - wx]
        a3 -= cs[3, p - wx]
    for p in range(max(wx, p_end), w - wx):  # the lags' last few columns
        a0 += cs[0, p + wx]
        sm[0, p] = a0
        a0 -= cs[0, p - wx]
        if p < w - wx - 1:
            a1 += cs[1, p + wx]
            sm[1, p] = a1
            a1 -= cs[1, p - wx]
        if p < w - wx - 2:
            a2 += cs[2, p + wx]
            sm[2, p] = a2
            a2 -= cs[2, p - wx]


@njit(cache=True, nogil=True, inline="always")
def _lk_start_row(left, qpad, disp, y, w, wx, wy, esf, xb_run, state, dcur):
    """Row ``y``'s P sums ``esf[8x + m] = sum_window L(v, x + u) q(v, xb - 2 + m + u)``,
    slid down from the row above when its integer part ``xb`` is the same, else summed
    afresh; ``state`` 1 and ``dcur`` = disparity where a pixel can be refined."""
    state[:] = 0
    l_in = left[y + wy]
    q_in = qpad[y + wy]
    l_out = left[max(y - wy - 1, 0)]
    q_out = qpad[max(y - wy - 1, 0)]
    for x in range(w):
        if x < wx or x >= w - wx:
            continue
        d_in = disp[y, x]
        if np.isnan(d_in):
            xb_run[x] = _NO_RUN
            continue
        d = np.float64(d_in)
        xb = int(np.floor(x - d))
        if xb - wx - 1 < 0 or xb + wx + 2 >= w:
            xb_run[x] = _NO_RUN
            continue
        if xb_run[x] == xb:
            _lk_row_products(l_in, q_in, x, xb, wx, 1.0, esf)
            _lk_row_products(l_out, q_out, x, xb, wx, -1.0, esf)
        else:
            for m in range(8):
                esf[8 * x + m] = 0.0
            for v in range(y - wy, y + wy + 1):
                _lk_row_products(left[v], qpad[v], x, xb, wx, 1.0, esf)
            xb_run[x] = xb
        state[x] = 1
        dcur[x] = d


@njit(cache=True, nogil=True, inline="always")
def _bspline_weights(t, sixth, one):
    """Cubic B-spline weights a0..a3 (value) and g0..g3 (derivative) at fraction t.
    ``sixth`` and ``one`` come from outside the parallel loop: as constants LLVM's
    fast-math would refold the products (results 1 ulp apart)."""
    omt = one - t
    t2 = t * t
    a0 = np.float64(omt * omt * omt * sixth)
    a1 = np.float64((np.float32(3.0) * t2 * t - np.float32(6.0) * t2 + np.float32(4.0)) * sixth)
    a2 = np.float64((np.float32(-3.0) * t2 * t + np.float32(3.0) * t2 + np.float32(3.0) * t
                     + one) * sixth)
    a3 = np.float64(t2 * t * sixth)
    g0 = np.float64(np.float32(-0.5) * omt * omt)
    g1 = np.float64(np.float32(1.5) * t2 - np.float32(2.0) * t)
    g2 = np.float64(np.float32(-1.5) * t2 + t + np.float32(0.5))
    g3 = np.float64(np.float32(0.5) * t2)
    return a0, a1, a2, a3, g0, g1, g2, g3


@njit(cache=True, nogil=True, inline="always")
def _gn_num_den(esf, s0, s1, s2, s3, e0, x0, t, sixth, one):
    """Gauss-Newton ``sum r g`` and ``sum g^2`` at integer part x0, fraction t."""
    pp0 = esf[e0]
    pp1 = esf[e0 + 1]
    pp2 = esf[e0 + 2]
    pp3 = esf[e0 + 3]
    m00 = s0[x0 - 1]
    m11 = s0[x0]
    m22 = s0[x0 + 1]
    m33 = s0[x0 + 2]
    m01 = s1[x0 - 1]
    m12 = s1[x0]
    m23 = s1[x0 + 1]
    m02 = s2[x0 - 1]
    m13 = s2[x0]
    m03 = s3[x0 - 1]
    a0, a1, a2, a3, g0, g1, g2, g3 = _bspline_weights(t, sixth, one)
    mg0 = m00 * g0 + m01 * g1 + m02 * g2 + m03 * g3
    mg1 = m01 * g0 + m11 * g1 + m12 * g2 + m13 * g3
    mg2 = m02 * g0 + m12 * g1 + m22 * g2 + m23 * g3
    mg3 = m03 * g0 + m13 * g1 + m23 * g2 + m33 * g3
    den = g0 * mg0 + g1 * mg1 + g2 * mg2 + g3 * mg3
    num = (g0 * pp0 + g1 * pp1 + g2 * pp2 + g3 * pp3
           - (a0 * mg0 + a1 * mg1 + a2 * mg2 + a3 * mg3))
    return num, den


@njit(cache=True, nogil=True, inline="always")
def _lk_iterate_row(disp, y, w, wx, iters, max_step, esf, sm, xb_run, state, dcur, sixth, one):
    """Gauss-Newton steps, one sweep of the row per iteration (independent pixels: their
    dependency chains overlap). state: 0 idle, 1 iterating, 2 converged, 3 failed."""
    s0 = sm[0]
    s1 = sm[1]
    s2 = sm[2]
    s3 = sm[3]
    for _ in range(iters):
        for x in range(wx, w - wx):
            if state[x] != 1:
                continue
            d = dcur[x]
            xs = x - d
            x0 = int(np.floor(xs))
            if x0 - wx - 1 < 0 or x0 + wx + 2 >= w:
                state[x] = 3
                continue
            e0 = 8 * x + 1 + (0 if x0 == xb_run[x] else (-1 if x0 < xb_run[x] else 1))
            num, den = _gn_num_den(esf, s0, s1, s2, s3, e0, x0, np.float32(xs - x0), sixth, one)
            if den <= _MIN_GRAM:
                state[x] = 3
                continue
            step = -num / den
            d += step
            dcur[x] = d
            if abs(d - np.float64(disp[y, x])) > max_step:
                state[x] = 3
            elif abs(step) < _LK_CONVERGED:
                state[x] = 2


_MIN_GRAM = 1e-6  # sum g^2 below this: no texture to refine on
_LK_CONVERGED = 2e-3  # px: a smaller step ends the iterations

# fast-math without "nnan"/"ninf": LLVM may otherwise fold the NaN tests away (measured:
# every invalid pixel then ran the whole iteration on a NaN disparity)
_FAST_FINITE = {"nsz", "arcp", "contract", "reassoc"}


@njit(cache=True, nogil=True, parallel=True, fastmath=_FAST_FINITE, error_model="numpy")
def refine_lk_gram(left, right_coef_pad, disp, wy, wx, iters, max_step, n_stripes):
    """1-D Lucas-Kanade refinement of ``disp`` (H, W) float32 in place, from window sums.

    right_coef_pad (H, W + 4) float32: the right view's B-spline coefficients in
    columns 1..W, the rest zero. A Gauss-Newton step needs ``g.P - a^T M g`` and
    ``g^T M g`` (``P_j = sum L q_j``, Gram ``M_jk = sum q_j q_k``), which depend only on
    the integer part of ``x - d``: O(1) per iteration (docs/matching.md).
    """
    h, w = disp.shape
    sixth = np.float32(1.0 / 6.0)
    one = np.float32(1.0)
    y_lo = wy
    y_hi = h - wy  # rows y_lo .. y_hi - 1 have a full window
    n_rows = y_hi - y_lo
    if n_rows <= 0:
        return
    ns = max(1, min(n_stripes, n_rows))
    for si in prange(ns):
        ya = y_lo + (si * n_rows) // ns
        yb = y_lo + ((si + 1) * n_rows) // ns
        cs = np.zeros((4, w), np.float64)
        sm = np.zeros((4, w), np.float64)
        esf = np.zeros(8 * w, np.float64)  # running P sums per column (6 of 8 used)
        xb_run = np.full(w, _NO_RUN, np.int64)  # their integer part, or none
        state = np.zeros(w, np.uint8)
        dcur = np.zeros(w, np.float64)
        for v in range(ya - wy, ya + wy + 1):
            _gram_row(right_coef_pad, v, w, 1.0, cs)
        for y in range(ya, yb):
            if y > ya:
                _gram_row(right_coef_pad, y + wy, w, 1.0, cs)
                _gram_row(right_coef_pad, y - wy - 1, w, -1.0, cs)
            if not _row_any_valid(disp, y, w):
                for x in range(w):
                    xb_run[x] = _NO_RUN
                continue
            _gram_box_sums(cs, sm, w, wx)
            _lk_start_row(left, right_coef_pad, disp, y, w, wx, wy, esf, xb_run, state, dcur)
            _lk_iterate_row(disp, y, w, wx, iters, max_step, esf, sm, xb_run, state, dcur,
                            sixth, one)
            for x in range(wx, w - wx):
                if state[x] == 1 or state[x] == 2:
                    disp[y, x] = np.float32(dcur[x])


@njit(cache=True, nogil=True, parallel=True)
def median_fill_final(filled, raw, conf, r, out, valid, conf_out):
    """:func:`median_filled` with the validity taken from ``raw`` (not NaN), plus the
    result's ``valid`` mask and ``conf_out = clip(conf, 0, 1)`` where valid, else 0."""
    h, w = filled.shape
    n = (2 * r + 1) * (2 * r + 1)
    for y in prange(h):
        buf = np.empty(n, np.float32)
        for x in range(w):
            ok = not np.isnan(raw[y, x])
            valid[y, x] = ok
            if ok:
                conf_out[y, x] = min(max(conf[y, x], np.float32(0.0)), np.float32(1.0))
                out[y, x] = filled[y, x]
                continue
            conf_out[y, x] = 0.0
            out[y, x] = _window_median(filled, y, x, r, buf)
