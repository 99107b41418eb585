"""Numba kernels of the semi-global stereo matcher (private; see :mod:`.match`).

Every kernel works on a *per-pixel disparity window*: pixel ``(y, x)`` searches the
``K`` disparities ``dlo[y, x] + k`` for ``k = 0 .. K-1``. A full search is the special
case ``dlo == min_disp`` everywhere and ``K == num_disp``; the coarse-to-fine path
gives every pixel a narrow window around the upsampled coarse disparity. Costs are
stored compactly as ``(H, W, K)`` uint8 (matching cost) and uint16 (aggregated cost).

Speed: census codes are planar ``(C, H, W)`` uint32 (5x5 windows) and the right
view's rows are stored mirrored, so the candidates of one left pixel are contiguous
and the Hamming loop over ``k`` vectorises (SIMD popcount); SGM path buffers are
uint16 so the recursion runs 16-32 lanes wide.

References
----------
.. [1] R. Zabih and J. Woodfill, "Non-parametric local transforms for computing
   visual correspondence", ECCV 1994 (census transform).
.. [2] H. Hirschmüller, "Stereo processing by semiglobal matching and mutual
   information", IEEE TPAMI 30(2), 2008 (SGM, left-right check, adaptive P2).
.. [3] M. Rothermel, K. Wenzel, D. Fritsch, N. Haala, "SURE: Photogrammetric surface
   reconstruction from imagery", LC3D Workshop 2012 (tSGM: per-pixel search ranges
   from a coarser pyramid level).
.. [4] M. Shimizu and M. Okutomi, "Sub-pixel estimation error cancellation on
   area-based matching", IJCV 63(3), 2005 (pixel-locking of parabola fits); the
   equiangular (symmetric V) fit follows their analysis.
.. [5] B. D. Lucas and T. Kanade, "An iterative image registration technique with an
   application to stereo vision", IJCAI 1981 (1-D iterative warping refinement).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

INF16 = 0x3FFF  # "no such disparity" in uint16 path costs; sums of 8 stay < 65535


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
def census_transform(padded, ry, rx, reverse, out):
    """Census transform with a ``(2ry+1) x (2rx+1)`` window, every channel.

    padded : (C, H + 2ry, W + 2rx) float32, channel planes with replicated borders;
    out : (C, H, W) uint32 or uint64, bit set when the neighbour is darker than the
    centre (at most 64 comparisons, centre excluded). With ``reverse`` every row is
    stored mirrored (``out[c, y, W - 1 - x]``): the right view's layout in
    :func:`matching_cost`, where the candidates of one left pixel are then contiguous.
    """
    nc, h, w = out.shape
    one = out.dtype.type(1)
    zero = out.dtype.type(0)
    for y in prange(h):
        bits = np.empty(w, out.dtype)
        for c in range(nc):
            centre = padded[c, y + ry, rx:rx + w]
            bits[:] = zero
            for dy in range(-ry, ry + 1):
                for dx in range(-rx, rx + 1):
                    if dy == 0 and dx == 0:
                        continue
                    nb = padded[c, y + ry + dy, rx + dx:rx + dx + w]
                    for x in range(w):
                        bits[x] = (bits[x] << one) | (one if nb[x] < centre[x] else zero)
            if reverse:
                for x in range(w):
                    out[c, y, w - 1 - x] = bits[x]
            else:
                for x in range(w):
                    out[c, y, x] = bits[x]


@njit(cache=True, nogil=True, parallel=True)
def matching_cost(census_l, census_rr, feat_l, feat_rr, ad_scale, ad_clip, dlo, k_levels,
                  oob_cost, out):
    """Census Hamming distance summed over channels plus a truncated absolute
    difference of per-pixel features.

    census_l : (C, H, W) uint32/uint64 left census; census_rr : the right census with
    mirrored rows (``census_transform(..., reverse=True)``); feat_l, feat_rr : (F, H, W)
    uint8 features, the right one mirrored likewise (F may be 0). The AD term of a
    summed absolute feature difference ``a`` is ``floor(ad_scale * min(a, ad_clip) +
    0.5)``. dlo : (H, W) int32; out : (H, W, K) uint8, ``out[y, x, k]`` = cost of
    disparity ``dlo[y, x] + k`` saturated at 255; ``oob_cost`` where the right pixel
    ``x - d`` falls outside the image.

    With mirrored right rows, the right pixel ``x - dlo - k`` of candidate ``k`` sits
    at index ``W - 1 - x + dlo + k``: consecutive candidates are consecutive in
    memory, so the loops over ``k`` vectorise (SIMD popcount).
    """
    nc, h, w = census_l.shape
    nf = feat_l.shape[0]
    clip = np.float32(ad_clip)
    scale = np.float32(ad_scale)
    half = np.float32(0.5)
    for y in prange(h):
        acc = np.empty(k_levels, np.int32)
        adb = np.empty(k_levels, np.int32)
        for x in range(w):
            d0 = dlo[y, x]
            o = out[y, x]
            # candidates with 0 <= x - d0 - k < w
            k_lo = max(0, x - d0 - (w - 1))
            k_hi = min(k_levels, x - d0 + 1)
            if k_hi <= k_lo:
                o[:] = oob_cost
                continue
            n = k_hi - k_lo
            j0 = w - 1 - x + d0 + k_lo
            a = acc[:n]
            cl = census_l[0, y, x]
            cr = census_rr[0, y, j0:j0 + n]
            for k in range(n):
                a[k] = np.int32(_popcount(cl ^ cr[k]))
            for c in range(1, nc):
                cl = census_l[c, y, x]
                cr = census_rr[c, y, j0:j0 + n]
                for k in range(n):
                    a[k] += np.int32(_popcount(cl ^ cr[k]))
            if nf > 0:
                v = adb[:n]
                fl = np.int32(feat_l[0, y, x])
                fr = feat_rr[0, y, j0:j0 + n]
                for k in range(n):
                    v[k] = abs(fl - np.int32(fr[k]))
                for f in range(1, nf):
                    fl = np.int32(feat_l[f, y, x])
                    fr = feat_rr[f, y, j0:j0 + n]
                    for k in range(n):
                        v[k] += abs(fl - np.int32(fr[k]))
                for k in range(n):
                    a[k] += np.int32(min(np.float32(v[k]), clip) * scale + half)
            for k in range(k_lo):
                o[k] = oob_cost
            for k in range(n):
                o[k_lo + k] = np.uint8(min(a[k], 255))
            for k in range(k_hi, k_levels):
                o[k] = oob_cost


# ------------------------------------------------------------------- SGM aggregation


@njit(cache=True, nogil=True, inline="always")
def _p2_eff(p1, p2, ia, ib, gamma):
    g = abs(ia - ib)
    v = p1 + (p2 - p1) / (1.0 + g / gamma)
    return np.int32(v) if v > p1 + 1 else np.int32(p1 + 1)


@njit(cache=True, nogil=True, inline="always")
def _step(costf, coff, lp, minprev, shift, lc, aggf, k_levels, p1, p2):
    """One SGM recursion on flat arrays, summed into the aggregated costs.

    ``L[k] = C[k] + min(Lq[j], Lq[j-1] + P1, Lq[j+1] + P1, min Lq + P2) - min Lq`` with
    ``j = k + shift`` (shift = dlo_p - dlo_q, clamped to +-k_levels). Path buffers
    ``lp`` (previous pixel) and ``lc`` (current pixel, distinct uint16 arrays so the
    loop vectorises; values stay below ``INF16 + P1``) hold ``3 * k_levels + 2`` values: level ``k`` sits at
    ``k_levels + 1 + k`` and every other entry stays ``INF16``, so the shifted read
    needs no branch. ``costf[coff + k]`` is the matching cost and
    ``aggf[coff + k]`` the sum over paths. Returns min_k L[k].
    """
    if shift > k_levels:
        shift = k_levels
    elif shift < -k_levels:
        shift = -k_levels
    src = k_levels + 1 + shift
    dst = k_levels + 1
    # slices + simple uint16 loops: LLVM vectorises these (32 lanes with AVX-512)
    a = lp[src - 1:src + k_levels + 1]
    c = costf[coff:coff + k_levels]
    o = lc[dst:dst + k_levels]
    g = aggf[coff:coff + k_levels]
    big = np.uint16(minprev + p2)
    p1u = np.uint16(p1)
    mp = np.uint16(minprev)
    for k in range(k_levels):
        v = min(min(a[k + 1], np.uint16(a[k] + p1u)), min(np.uint16(a[k + 2] + p1u), big))
        r = np.uint16(np.uint16(np.uint16(c[k]) + v) - mp)
        o[k] = r
        g[k] = np.uint16(g[k] + r)
    mn = np.uint16(INF16)
    for k in range(k_levels):
        mn = min(mn, o[k])
    return np.int32(mn)


@njit(cache=True, nogil=True, inline="always")
def _start(costf, coff, lc, aggf, k_levels):
    """First pixel of a scanline: L = C."""
    dst = k_levels + 1
    mn = np.int32(INF16)
    for k in range(k_levels):
        c = np.int32(costf[coff + k])
        lc[dst + k] = np.uint16(c)
        aggf[coff + k] += np.uint16(c)
        mn = min(mn, c)
    return mn


@njit(cache=True, nogil=True, parallel=True)
def aggregate_path(cost, dlo, guide, p1, p2, gamma, dy, dx, agg):
    """Add one horizontal or diagonal SGM path direction ``(dy, dx)`` into ``agg``.

    cost : (H, W, K) uint8; agg : (H, W, K) uint16 (C-contiguous). The image is cut
    into independent scanlines that start where the previous pixel ``p - (dy, dx)``
    would leave the image; scanlines run in parallel (no two of one direction share a
    pixel, so the in-place sum is race free).
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
        if s < n_row:
            y = np.int64(y_row)
            x = np.int64(s)
        else:
            x = np.int64(x_col)
            y = np.int64(s - n_row + y_first)
        lp = np.full(stride, np.uint16(INF16), np.uint16)
        lc = np.full(stride, np.uint16(INF16), np.uint16)
        mn = _start(costf, (y * w + x) * kl, lc, aggf, kl)
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
            mn = _step(costf, (y * w + x) * kl, lp, mn, shift, lc, aggf, kl, p1, p2e)


@njit(cache=True, nogil=True, parallel=True)
def aggregate_vertical(cost, dlo, guide, p1, p2, gamma, dy, block, agg):
    """Add the vertical SGM path (``dy = +1`` top-down, ``-1`` bottom-up) into ``agg``.

    Columns are processed in blocks of ``block`` adjacent columns that walk the rows
    together (contiguous memory per step); blocks run in parallel.
    """
    h, w, kl = cost.shape
    costf = cost.reshape(-1)
    aggf = agg.reshape(-1)
    nb = (w + block - 1) // block
    stride = 3 * kl + 2
    for b in prange(nb):
        x0 = b * block
        x1 = min(w, x0 + block)
        nbx = x1 - x0
        lp = np.full(nbx * stride, np.uint16(INF16), np.uint16)
        lc = np.full(nbx * stride, np.uint16(INF16), np.uint16)
        mins = np.empty(nbx, np.int32)
        y = 0 if dy > 0 else h - 1
        for i in range(nbx):
            mins[i] = _start(costf, (y * w + x0 + i) * kl, lc[i * stride:(i + 1) * stride],
                             aggf, kl)
        for _ in range(h - 1):
            yq = y
            y += dy
            lp, lc = lc, lp
            for i in range(nbx):
                x = x0 + i
                p2e = _p2_eff(p1, p2, guide[y, x], guide[yq, x], gamma)
                shift = dlo[y, x] - dlo[yq, x]
                o = i * stride
                mins[i] = _step(costf, (y * w + x) * kl, lp[o:o + stride], mins[i], shift,
                                lc[o:o + stride], aggf, kl, p1, p2e)


# ----------------------------------------------------------------- winner take all


@njit(cache=True, nogil=True, parallel=True)
def select_disparity(agg, dlo, uniqueness, disp, best_cost, conf):
    """Winner-take-all with equiangular sub-pixel fit and uniqueness test.

    disp : (H, W) float32 out, NaN where the uniqueness test fails;
    best_cost : (H, W) int32 out; conf : (H, W) float32 out in [0, 1] (relative gap
    between the best cost and the best cost outside +-1 of the winner).
    """
    h, w, kl = agg.shape
    big = np.uint16(0xFFFF)
    for y in prange(h):
        for x in range(w):
            row = agg[y, x]
            # vectorised min, then its first index, then the best outside +-1
            m = big
            for k in range(kl):
                m = min(m, row[k])
            b = 0
            while row[b] != m:
                b += 1
            bc = np.int32(m)
            s1 = big
            for k in range(b - 1):
                s1 = min(s1, row[k])
            for k in range(b + 2, kl):
                s1 = min(s1, row[k])
            second = np.int32(1 << 30) if (b < 2 and b + 2 >= kl) else np.int32(s1)
            best_cost[y, x] = bc
            if second >= (1 << 30):
                g = 1.0
            else:
                g = (second - bc) / max(second, 1)
            conf[y, x] = g
            if g * 100.0 < uniqueness:
                disp[y, x] = np.nan
                continue
            off = 0.0
            if 0 < b < kl - 1:
                cm = np.float64(agg[y, x, b - 1])
                cp = np.float64(agg[y, x, b + 1])
                c0 = np.float64(bc)
                den = max(cm, cp) - c0
                if den > 0:
                    off = 0.5 * (cm - cp) / den
            disp[y, x] = np.float32(dlo[y, x] + b + off)


@njit(cache=True, nogil=True, parallel=True)
def right_disparity(agg, dlo, disp_r):
    """Winner-take-all of the right view from the same cost volume (integer, float32)."""
    h, w, kl = agg.shape
    for y in prange(h):
        best = np.full(w, np.int32(1 << 30), np.int32)
        for x in range(w):
            d0 = dlo[y, x]
            for k in range(kl):
                xr = x - d0 - k
                if 0 <= xr < w:
                    c = np.int32(agg[y, x, k])
                    if c < best[xr]:
                        best[xr] = c
                        disp_r[y, xr] = d0 + k
        for xr in range(w):
            if best[xr] >= (1 << 30):
                disp_r[y, xr] = np.nan


@njit(cache=True, nogil=True, parallel=True)
def lr_check(disp, disp_r, max_diff):
    """Invalidate (NaN) left disparities that disagree with the right view."""
    h, w = disp.shape
    for y in prange(h):
        for x in range(w):
            d = disp[y, x]
            if np.isnan(d):
                continue
            xr = int(np.floor(x - d + 0.5))
            if xr < 0 or xr >= w:
                disp[y, x] = np.nan
                continue
            dr = disp_r[y, xr]
            if np.isnan(dr) or abs(dr - d) > max_diff:
                disp[y, x] = np.nan


# ------------------------------------------------------------------------ speckles


@njit(cache=True, nogil=True)
def remove_speckles(disp, max_size, max_diff):
    """Set to NaN 4-connected regions (neighbours differing <= max_diff) smaller than
    ``max_size`` pixels."""
    h, w = disp.shape
    label = np.zeros((h, w), np.int32)
    stack = np.empty(h * w, np.int32)
    members = np.empty(h * w, np.int32)
    cur = 0
    for y0 in range(h):
        for x0 in range(w):
            if label[y0, x0] != 0 or np.isnan(disp[y0, x0]):
                continue
            cur += 1
            label[y0, x0] = cur
            top = 0
            stack[top] = y0 * w + x0
            top = 1
            n = 0
            while top > 0:
                top -= 1
                p = stack[top]
                members[n] = p
                n += 1
                y = p // w
                x = p - y * w
                d = disp[y, x]
                for nb in range(4):
                    yy = y + (1 if nb == 0 else (-1 if nb == 1 else 0))
                    xx = x + (1 if nb == 2 else (-1 if nb == 3 else 0))
                    if yy < 0 or yy >= h or xx < 0 or xx >= w:
                        continue
                    if label[yy, xx] != 0:
                        continue
                    dn = disp[yy, xx]
                    if np.isnan(dn) or abs(dn - d) > max_diff:
                        continue
                    label[yy, xx] = cur
                    stack[top] = yy * w + xx
                    top += 1
            if n < max_size:
                for i in range(n):
                    p = members[i]
                    disp[p // w, p % w] = np.nan


# --------------------------------------------------------------- sub-pixel refinement


@njit(cache=True, nogil=True, parallel=True)
def bspline_rows(img, out):
    """Cubic B-spline interpolation coefficients of every row (mirror boundaries).

    img, out : (H, W) float32. Causal + anti-causal recursive prefilter with pole
    ``z = sqrt(3) - 2`` (Unser 1999, "Splines: a perfect fit for signal and image
    processing", IEEE SPM 16(6)); ``out`` sampled with the cubic B-spline kernel
    reproduces ``img`` at integer positions.
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


@njit(cache=True, nogil=True, parallel=True, fastmath=True, error_model="numpy")
def refine_lk(left, right_coef, disp, wy, wx, iters, max_step):
    """Refine valid disparities by 1-D Gauss-Newton (Lucas-Kanade) warping.

    left : (H, W) float32 band-passed grey left view; right_coef : (H, W) float32 cubic
    B-spline coefficients of the band-passed right view (:func:`bspline_rows`);
    disp : (H, W) float32 in/out. Minimises ``sum_window (L(y, x) - R(y, x - d))^2``
    over ``d``; ``R`` and its derivative are sampled with the cubic B-spline, whose
    near-flat frequency response keeps the estimate free of pixel-locking. The
    fractional shift is the same for the whole window, so the kernel weights are
    computed once per iteration. Keeps the input when the solution moves farther
    than ``max_step`` from it or the window has no horizontal texture.
    """
    h, w = disp.shape
    sixth = np.float32(1.0 / 6.0)
    one = np.float32(1.0)
    for y in prange(h):
        for x in range(w):
            d_in = disp[y, x]
            if np.isnan(d_in):
                continue
            if y - wy < 0 or y + wy >= h or x - wx < 0 or x + wx >= w:
                continue
            d = np.float64(d_in)
            ok = True
            for _ in range(iters):
                xs = x - d
                x0 = int(np.floor(xs))
                if x0 - wx - 1 < 0 or x0 + wx + 2 >= w:
                    ok = False
                    break
                t = np.float32(xs - x0)
                omt = one - t
                t2 = t * t
                a0 = omt * omt * omt * sixth
                a1 = (np.float32(3.0) * t2 * t - np.float32(6.0) * t2 + np.float32(4.0)) * sixth
                a2 = (np.float32(-3.0) * t2 * t + np.float32(3.0) * t2 + np.float32(3.0) * t
                      + one) * sixth
                a3 = t2 * t * sixth
                g0 = np.float32(-0.5) * omt * omt
                g1 = np.float32(1.5) * t2 - np.float32(2.0) * t
                g2 = np.float32(-1.5) * t2 + t + np.float32(0.5)
                g3 = np.float32(0.5) * t2
                num = np.float32(0.0)
                den = np.float32(0.0)
                for v in range(y - wy, y + wy + 1):
                    # rolling 4-tap window over the row: one load per sample
                    q0 = right_coef[v, x0 - wx - 1]
                    q1 = right_coef[v, x0 - wx]
                    q2 = right_coef[v, x0 - wx + 1]
                    for u in range(-wx, wx + 1):
                        q3 = right_coef[v, x0 + u + 2]
                        val = a0 * q0 + a1 * q1 + a2 * q2 + a3 * q3
                        g = g0 * q0 + g1 * q1 + g2 * q2 + g3 * q3
                        # r(d) = L - R(x - d); dr/dd = +R'(x - d)
                        r = left[v, x + u] - val
                        num += r * g
                        den += g * g
                        q0 = q1
                        q1 = q2
                        q2 = q3
                if den <= 1e-6:
                    ok = False
                    break
                step = -np.float64(num) / np.float64(den)
                d += step
                if abs(d - d_in) > max_step:
                    ok = False
                    break
                if abs(step) < 2e-3:
                    break
            if ok:
                disp[y, x] = np.float32(d)


# --------------------------------------------------------------------- hole filling


@njit(cache=True, nogil=True, parallel=True)
def fill_holes(disp, out):
    """Dense fill: every NaN takes the smaller (farther, background) of the nearest
    valid disparities to its left and right on the same row; a row without any valid
    pixel stays NaN (filled vertically afterwards by :func:`fill_columns`)."""
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
                out[y, x] = filled[y, x]
            else:
                for i in range(1, m):
                    v = buf[i]
                    j = i - 1
                    while j >= 0 and buf[j] > v:
                        buf[j + 1] = buf[j]
                        j -= 1
                    buf[j + 1] = v
                out[y, x] = buf[m // 2]


# --------------------------------------------------------------- coarse-to-fine ranges


@njit(cache=True, nogil=True, parallel=True)
def fine_ranges(coarse, scale, radius, k_levels, dmin, dmax, dlo):
    """Per-pixel search windows for the full-resolution pass.

    coarse : (h, w) float32 dense disparity of the coarse level (in coarse pixels);
    dlo : (H, W) int32 out, the first disparity of each pixel's ``k_levels`` window,
    chosen to cover ``[min, max]`` of the upsampled 3x3 coarse neighbourhood widened
    by ``radius`` when that fits, else centred on the pixel's own coarse value;
    always inside ``[dmin, dmax - k_levels + 1]``.
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
