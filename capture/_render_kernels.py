"""Numba kernels behind :mod:`prism3d.capture.render` and the scene simulator
(private; inputs validated by the wrappers, contiguous, float64 unless stated).
Pipeline order: docs/capture.md ("Renderers").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def grid_rays(
    K: np.ndarray,
    dist: np.ndarray,
    width: int,
    row0: int,
    R: np.ndarray,
    out: np.ndarray,
    out_z: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out[r, u] = R @ ray_cam(u, row0 + r)``, ``out_z[r, u] = ray_cam[2]``: unit rays
    through the distorted pixel centres (Newton inversion to 1e-15 as
    ``CameraModel.undistort_normalized``, warm-started from the left neighbour).
    """
    fx = K[0, 0]
    s = K[0, 1]
    cx = K[0, 2]
    fy = K[1, 1]
    cy = K[1, 2]
    k1 = dist[0]
    k2 = dist[1]
    p1 = dist[2]
    p2 = dist[3]
    k3 = dist[4]
    has_dist = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    for r in prange(out.shape[0]):
        v = row0 + r
        yd = (v - cy) / fy
        x = 0.0
        y = 0.0
        xd_prev = 0.0
        for u in range(width):
            xd = (u - cx - s * yd) / fx
            if u == 0 or not has_dist:
                x = xd
                y = yd
            else:
                x = x + (xd - xd_prev)
            xd_prev = xd
            if has_dist:
                for _ in range(30):
                    r2 = x * x + y * y
                    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
                    fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
                    fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
                    j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
                    j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
                    j21 = j12
                    j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
                    det = j11 * j22 - j12 * j21
                    dx = (j22 * fx_ - j12 * fy_) / det
                    dy = (-j21 * fx_ + j11 * fy_) / det
                    x -= dx
                    y -= dy
                    if abs(dx) < 1e-15 and abs(dy) < 1e-15:
                        break
            n = 1.0 / np.sqrt(x * x + y * y + 1.0)
            cx_ = x * n
            cy_ = y * n
            out[r, u, 0] = R[0, 0] * cx_ + R[0, 1] * cy_ + R[0, 2] * n
            out[r, u, 1] = R[1, 0] * cx_ + R[1, 1] * cy_ + R[1, 2] * n
            out[r, u, 2] = R[2, 0] * cx_ + R[2, 1] * cy_ + R[2, 2] * n
            out_z[r, u] = n


@njit(cache=True, nogil=True, parallel=True)
def cull_rays(
    o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray, keep: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``keep[i]`` = ray ``o + t d`` (t >= 0) meets the scene's padded box ``[lo, hi]`` (slab test)."""
    stride = 0 if o.shape[0] == 1 else 1
    for i in prange(d.shape[0]):
        j = i * stride
        t0 = 0.0
        t1 = np.inf
        ok = True
        for a in range(3):
            oa = o[j, a]
            da = d[i, a]
            if da == 0.0:
                if oa < lo[a] or oa > hi[a]:
                    ok = False
            else:
                inv = 1.0 / da
                ta = (lo[a] - oa) * inv
                tb = (hi[a] - oa) * inv
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
        keep[i] = ok and t0 <= t1


@njit(cache=True, nogil=True, parallel=True)
def pack_rays_sel(
    o: np.ndarray, d: np.ndarray, sel: np.ndarray, rays: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``rays[q] = (o, d[sel[q]])`` in float32 (``o`` one row or one per ray)."""
    stride = 0 if o.shape[0] == 1 else 1
    for q in prange(sel.shape[0]):
        i = sel[q]
        j = i * stride
        rays[q, 0] = o[j, 0]
        rays[q, 1] = o[j, 1]
        rays[q, 2] = o[j, 2]
        rays[q, 3] = d[i, 0]
        rays[q, 4] = d[i, 1]
        rays[q, 5] = d[i, 2]


@njit(cache=True, nogil=True, inline="always")  # inlined: no call cost in the kernel
def _row3(a: np.ndarray, i: int) -> tuple:  # pragma: no cover - compiled
    """``(a[i, 0], a[i, 1], a[i, 2])``."""
    return a[i, 0], a[i, 1], a[i, 2]


@njit(cache=True, nogil=True, inline="always")  # inlined: no call cost in the kernel
def _moller_trumbore(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
    A: np.ndarray, E1: np.ndarray, E2: np.ndarray, f: int,
) -> tuple:  # pragma: no cover - compiled
    """``(ok, u, v, t)`` of the ray ``o + t d`` on triangle ``f`` in float64;
    ``ok`` False for a degenerate (zero or non-finite determinant) triangle."""
    e1x, e1y, e1z = _row3(E1, f)
    e2x, e2y, e2z = _row3(E2, f)
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    tx = ox - A[f, 0]
    ty = oy - A[f, 1]
    tz = oz - A[f, 2]
    qx = ty * e1z - tz * e1y
    qy = tz * e1x - tx * e1z
    qz = tx * e1y - ty * e1x
    if det != 0.0 and np.isfinite(det):
        inv = 1.0 / det
        u = (tx * px + ty * py + tz * pz) * inv
        v = (dx * qx + dy * qy + dz * qz) * inv
        t = (e2x * qx + e2y * qy + e2z * qz) * inv
        return True, u, v, t
    return False, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True, inline="always")  # inlined: no call cost in the kernel
def _store_facing_normal(
    N: np.ndarray, f: int, dx: float, dy: float, dz: float, n_out: np.ndarray, j: int
) -> None:  # pragma: no cover - compiled
    """``n_out[j]`` = the unit normal of face ``f``, flipped to face the ray ``d``."""
    nx, ny, nz = _row3(N, f)
    if nx * dx + ny * dy + nz * dz > 0.0:
        nx = -nx
        ny = -ny
        nz = -nz
    n_out[j, 0] = nx
    n_out[j, 1] = ny
    n_out[j, 2] = nz


@njit(cache=True, nogil=True, parallel=True)
def refine_compact(
    o: np.ndarray,
    d: np.ndarray,
    rid: np.ndarray,
    idx: np.ndarray,
    gid: np.ndarray,
    prim: np.ndarray,
    t32: np.ndarray,
    uv32: np.ndarray,
    gid_map: np.ndarray,
    offsets: np.ndarray,
    A: np.ndarray,
    E1: np.ndarray,
    E2: np.ndarray,
    N: np.ndarray,
    first: int,
    index_out: np.ndarray,
    obj_out: np.ndarray,
    face_out: np.ndarray,
    t_out: np.ndarray,
    uv_out: np.ndarray,
    p_out: np.ndarray,
    n_out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Compact Open3D's hits ``idx`` (row ``q = idx[j]`` traced chunk ray ``rid[q]``,
    global ``first + rid[q]``) into output row ``j``, refined in float64 by
    Moller-Trumbore (the float32 answer only for a degenerate triangle).
    """
    last = gid_map.shape[0] - 1
    stride = 0 if o.shape[0] == 1 else 1
    for j in prange(idx.shape[0]):
        q = idx[j]
        i = rid[q]
        ob = gid_map[min(np.int64(gid[q]), last)]
        fl = np.int64(prim[q])
        f = offsets[ob] + fl
        index_out[j] = first + i
        obj_out[j] = ob
        face_out[j] = fl
        ox, oy, oz = _row3(o, i * stride)
        dx, dy, dz = _row3(d, i)
        ok, u, v, t = _moller_trumbore(ox, oy, oz, dx, dy, dz, A, E1, E2, f)
        if not ok:
            u = np.float64(uv32[q, 0])
            v = np.float64(uv32[q, 1])
            t = np.float64(t32[q])
        t_out[j] = t
        uv_out[j, 0] = u
        uv_out[j, 1] = v
        p_out[j, 0] = ox + t * dx
        p_out[j, 1] = oy + t * dy
        p_out[j, 2] = oz + t * dz
        _store_facing_normal(N, f, dx, dy, dz, n_out, j)


@njit(cache=True, nogil=True, inline="always")  # inlined: no call cost in the kernel
def _project_to_pattern(
    px: float, py: float, pz: float, R_pr: np.ndarray, t_pr: np.ndarray,
    fx: float, s: float, cx: float, fy: float, cy: float, pw: int, ph: int,
) -> tuple:  # pragma: no cover - compiled
    """``(inside, u, v)``: the rig point's projector pixel and whether it lies in
    the pattern (pixel-centre convention, half-pixel border)."""
    qx = R_pr[0, 0] * px + R_pr[0, 1] * py + R_pr[0, 2] * pz + t_pr[0]
    qy = R_pr[1, 0] * px + R_pr[1, 1] * py + R_pr[1, 2] * pz + t_pr[1]
    qz = R_pr[2, 0] * px + R_pr[2, 1] * py + R_pr[2, 2] * pz + t_pr[2]
    inside = False
    u = 0.0
    v = 0.0
    if qz > 0.0:
        u = fx * qx / qz + s * qy / qz + cx
        v = fy * qy / qz + cy
        inside = u >= -0.5 and u <= pw - 0.5 and v >= -0.5 and v <= ph - 0.5
    return inside, u, v


@njit(cache=True, nogil=True, inline="always")  # inlined: no call cost in the kernel
def _store_bilinear(
    pattern: np.ndarray, u: float, v: float, pw: int, ph: int, rgb_out: np.ndarray, i: int
) -> None:  # pragma: no cover - compiled
    """``rgb_out[i]`` = the pattern bilinearly sampled at ``(u, v)`` (clamped to the edges)."""
    uu = min(max(u, 0.0), pw - 1.0)
    vv = min(max(v, 0.0), ph - 1.0)
    u0 = min(np.int64(np.floor(uu)), pw - 2) if pw > 1 else 0
    v0 = min(np.int64(np.floor(vv)), ph - 2) if ph > 1 else 0
    fu = uu - u0
    fv = vv - v0
    u1 = min(u0 + 1, pw - 1)
    v1 = min(v0 + 1, ph - 1)
    w00 = (1 - fu) * (1 - fv)
    w10 = fu * (1 - fv)
    w01 = (1 - fu) * fv
    w11 = fu * fv
    for c in range(3):
        rgb_out[i, c] = (
            w00 * pattern[v0, u0, c]
            + w10 * pattern[v0, u1, c]
            + w01 * pattern[v1, u0, c]
            + w11 * pattern[v1, u1, c]
        )


@njit(cache=True, nogil=True, parallel=True)
def light_hits(
    P: np.ndarray,
    N: np.ndarray,
    src: np.ndarray,
    R_pr: np.ndarray,
    t_pr: np.ndarray,
    Kp: np.ndarray,
    pw: int,
    ph: int,
    pattern: np.ndarray,
    has_pattern: bool,
    ref_mm: float,
    flash: float,
    k_out: np.ndarray,
    rgb_out: np.ndarray,
    white_out: np.ndarray,
    lit_out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Flash light at points before the shadow test: ``k = flash * max(0, n . l) *
    (ref_mm / |S - P|)^2``, projector colour ``rgb`` (bilinear; white without pattern;
    0 outside), ``white`` (inside the frustum), ``lit`` (inside and ``n . l > 0``).
    """
    fx = Kp[0, 0]
    s = Kp[0, 1]
    cx = Kp[0, 2]
    fy = Kp[1, 1]
    cy = Kp[1, 2]
    for i in prange(P.shape[0]):
        px, py, pz = _row3(P, i)
        lx = src[0] - px
        ly = src[1] - py
        lz = src[2] - pz
        dist = np.sqrt(lx * lx + ly * ly + lz * lz)
        ndotl = (N[i, 0] * lx + N[i, 1] * ly + N[i, 2] * lz) / dist
        if not ndotl > 0.0:
            ndotl = 0.0
        k_out[i] = flash * ndotl * (ref_mm / dist) ** 2
        inside, u, v = _project_to_pattern(px, py, pz, R_pr, t_pr, fx, s, cx, fy, cy, pw, ph)
        white_out[i] = inside
        lit_out[i] = inside and ndotl > 0.0
        if not inside:
            rgb_out[i, 0] = 0.0
            rgb_out[i, 1] = 0.0
            rgb_out[i, 2] = 0.0
        elif not has_pattern:
            rgb_out[i, 0] = 1.0
            rgb_out[i, 1] = 1.0
            rgb_out[i, 2] = 1.0
        else:
            _store_bilinear(pattern, u, v, pw, ph, rgb_out, i)


@njit(cache=True, nogil=True, parallel=True)
def shade_colour(
    pix: np.ndarray,
    albedo: np.ndarray,
    k: np.ndarray,
    rgb: np.ndarray,
    ambient: float,
    img: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``img[pix[i]] = clip(albedo_i * (ambient + k_i * rgb_i), 0, 1)`` (``k`` after the shadow test)."""
    for i in prange(pix.shape[0]):
        p = pix[i]
        for c in range(3):
            x = albedo[i, c] * (ambient + k[i] * rgb[i, c])
            img[p, c] = min(max(x, 0.0), 1.0)


@njit(cache=True, nogil=True, parallel=True)
def box_mean(img: np.ndarray, f: int, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[r, c] = mean of img[r*f:(r+1)*f, c*f:(c+1)*f]`` (float64 sums)."""
    H = out.shape[0]
    W = out.shape[1]
    C = out.shape[2]
    inv = 1.0 / (f * f)
    for r in prange(H):
        for c in range(W):
            for ch in range(C):
                acc = 0.0
                for a in range(f):
                    for b in range(f):
                        acc += img[r * f + a, c * f + b, ch]
                out[r, c, ch] = acc * inv


@njit(cache=True, nogil=True, parallel=True)
def rotate_rays(
    d_cam: np.ndarray, R: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``out[i] = R @ d_cam[i]`` for ``(N, 3)`` rays."""
    for i in prange(d_cam.shape[0]):
        x, y, z = _row3(d_cam, i)
        out[i, 0] = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
        out[i, 1] = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
        out[i, 2] = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z


@njit(cache=True, nogil=True, parallel=True)
def pack_segments(
    P: np.ndarray, sel: np.ndarray, src: np.ndarray, rays: np.ndarray, dist: np.ndarray
) -> float:  # pragma: no cover - compiled
    """Float32 rays ``src -> P[sel[j]]`` with the point at parameter 1; ``dist[j] =
    |P - src|`` (-1 for a non-finite point or zero length); returns the largest distance.
    """
    n = sel.shape[0]
    for j in prange(n):
        i = sel[j]
        dx = P[i, 0] - src[0]
        dy = P[i, 1] - src[1]
        dz = P[i, 2] - src[2]
        dd = np.sqrt(dx * dx + dy * dy + dz * dz)
        rays[j, 0] = src[0]
        rays[j, 1] = src[1]
        rays[j, 2] = src[2]
        if np.isfinite(dd) and dd > 0.0:
            dist[j] = dd
            rays[j, 3] = dx
            rays[j, 4] = dy
            rays[j, 5] = dz
        else:
            dist[j] = -1.0
            rays[j, 3] = 0.0
            rays[j, 4] = 0.0
            rays[j, 5] = 1.0
    m = 0.0
    for j in range(n):
        m = max(m, dist[j])
    return m


@njit(cache=True, nogil=True, parallel=True)
def scatter_truth(
    index: np.ndarray,
    t: np.ndarray,
    zc: np.ndarray,
    alb: np.ndarray,
    k: np.ndarray,
    rgb: np.ndarray,
    white: np.ndarray,
    normals: np.ndarray,
    R: np.ndarray,
    obj: np.ndarray,
    ambient: float,
    depth: np.ndarray,
    mask: np.ndarray,
    albedo: np.ndarray,
    shading: np.ndarray,
    illum: np.ndarray,
    normals_cam: np.ndarray,
    object_id: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Write the flat float32 truth maps of hit pixels ``index``: ``depth = t * zc``,
    ``shading = ambient + k * white``, ``illum = ambient + k * rgb``, ``normals_cam = R^T n``.
    """
    for j in prange(index.shape[0]):
        p = index[j]
        depth[p] = t[j] * zc[j]
        mask[p] = True
        kj = k[j]
        shading[p] = ambient + kj * (1.0 if white[j] else 0.0)
        for c in range(3):
            albedo[p, c] = alb[j, c]
            illum[p, c] = ambient + kj * rgb[j, c]
            normals_cam[p, c] = R[0, c] * normals[j, 0] + R[1, c] * normals[j, 1] + R[2, c] * normals[j, 2]
        object_id[p] = obj[j]


@njit(cache=True, nogil=True, inline="always")
def _mix64(z: np.uint64) -> np.uint64:  # pragma: no cover - compiled
    """splitmix64 finaliser (Steele, Lea, Flood 2014)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True, nogil=True, inline="always")
def _uniform(state: np.uint64) -> tuple[np.uint64, float]:  # pragma: no cover - compiled
    """Next ``(state, u)`` of a splitmix64 stream, ``u`` uniform in (0, 1)."""
    state = state + np.uint64(0x9E3779B97F4A7C15)
    return state, (float(_mix64(state) >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@njit(cache=True, nogil=True)
def _poisson(lam: float, state: np.uint64) -> tuple[np.uint64, float]:  # pragma: no cover
    """One Poisson(``lam``) variate: multiplication method below 10, else PTRS."""
    if not lam > 0.0:  # also NaN
        return state, 0.0
    if lam < 10.0:
        limit = np.exp(-lam)
        k = 0
        state, p = _uniform(state)
        while p > limit:
            k += 1
            state, u = _uniform(state)
            p *= u
        return state, float(k)
    # transformed rejection with squeeze (Hormann 1993, algorithm PTRS)
    slam = np.sqrt(lam)
    loglam = np.log(lam)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    alpha = 1.1239 + 1.1328 / (b - 3.4)
    v_r = 0.9277 - 3.6224 / (b - 2.0)
    while True:
        state, u = _uniform(state)
        state, v = _uniform(state)
        u -= 0.5
        us = 0.5 - abs(u)
        k = np.floor((2.0 * a / us + b) * u + lam + 0.43)
        if us >= 0.07 and v <= v_r:
            return state, k
        if k < 0.0 or (us < 0.013 and v > us):
            continue
        if np.log(v * alpha / (a / (us * us) + b)) <= -lam + k * loglam - math.lgamma(k + 1.0):
            return state, k


@njit(cache=True, nogil=True, parallel=True)
def sensor_noise(
    x: np.ndarray, gain: float, read_dn: float, key: np.uint64, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``out[i] = Poisson(255 clip(x[i], 0, 1) gain) / gain + N(0, read_dn)`` in DN;
    element ``i`` draws from its own splitmix64 stream keyed by ``(key, i)`` (thread-independent).
    """
    two_pi = 2.0 * np.pi
    for i in prange(x.shape[0]):
        state = _mix64(key ^ _mix64(np.uint64(i) + np.uint64(0x632BE59BD9B4E019)))
        xi = min(max(x[i], 0.0), 1.0) * 255.0
        state, e = _poisson(xi * gain, state)
        val = e / gain
        if read_dn > 0.0:
            state, u1 = _uniform(state)
            state, u2 = _uniform(state)
            val += read_dn * np.sqrt(-2.0 * np.log(u1)) * np.cos(two_pi * u2)
        out[i] = val


@njit(cache=True, nogil=True, parallel=True)
def on_plane(
    P: np.ndarray, sel: np.ndarray, nrm: np.ndarray, c: float, tol: float, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """``out[j] = |n . P[sel[j]] - c| <= tol`` (False for NaN)."""
    for j in prange(sel.shape[0]):
        i = sel[j]
        out[j] = abs(P[i, 0] * nrm[0] + P[i, 1] * nrm[1] + P[i, 2] * nrm[2] - c) <= tol


@njit(cache=True, nogil=True, parallel=True)
def quantize_u8(x: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out = uint8(clip(rint(x), 0, 255))`` (round half to even, NaN -> 0)."""
    for i in prange(x.shape[0]):
        v = np.rint(x[i])
        if not v > 0.0:  # also NaN
            out[i] = 0
        elif v >= 255.0:
            out[i] = 255
        else:
            out[i] = np.uint8(v)


@njit(cache=True, nogil=True, parallel=True)
def specular_weight(
    index: np.ndarray,
    P: np.ndarray,
    N: np.ndarray,
    obj: np.ndarray,
    eye: np.ndarray,
    src: np.ndarray,
    ks: np.ndarray,
    shininess: np.ndarray,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``out[index[i]] = ks[o] * max(0, n . h)^shininess[o]`` (``o = obj[i]``), ``h`` the
    bisector of the directions from ``P[i]`` to ``eye`` and to ``src``.
    """
    for i in prange(P.shape[0]):
        o = obj[i]
        c = ks[o]
        w = 0.0
        if c > 0.0:
            vx = eye[0] - P[i, 0]
            vy = eye[1] - P[i, 1]
            vz = eye[2] - P[i, 2]
            lx = src[0] - P[i, 0]
            ly = src[1] - P[i, 1]
            lz = src[2] - P[i, 2]
            nv2 = vx * vx + vy * vy + vz * vz
            nl2 = lx * lx + ly * ly + lz * lz
            if nv2 > 0.0 and nl2 > 0.0:
                iv = 1.0 / np.sqrt(nv2)
                il = 1.0 / np.sqrt(nl2)
                hx = vx * iv + lx * il
                hy = vy * iv + ly * il
                hz = vz * iv + lz * il
                d = N[i, 0] * hx + N[i, 1] * hy + N[i, 2] * hz
                h2 = hx * hx + hy * hy + hz * hz
                if d > 0.0 and h2 > 0.0:
                    # (n . h / |h|)^s = exp(s/2 log(d^2 / |h|^2))
                    w = c * math.exp(0.5 * shininess[o] * math.log(min(d * d / h2, 1.0)))
        out[index[i]] = w


@njit(cache=True, nogil=True, parallel=True)
def shade_colour_specular(
    pix: np.ndarray,
    albedo: np.ndarray,
    k: np.ndarray,
    rgb: np.ndarray,
    spec: np.ndarray,
    first: int,
    row_len: int,
    ss: int,
    width: int,
    ambient: float,
    img: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``img[pix[i]] = max(0, albedo_i (ambient + k_i rgb_i) + spec[q] k_i rgb_i)``,
    unclipped above; ray ``first + pix[i]`` of an ``ss``-supersampled camera
    (``row_len`` per row) lies in output pixel ``q = (r // ss) * width + c // ss``.
    """
    inv_len = 1.0 / row_len
    inv_ss = 1.0 / ss
    for i in prange(pix.shape[0]):
        p = pix[i]
        g = first + p
        if ss == 1:
            q = g
        else:
            # integer divisions by multiplication: (x + 0.5) / n is >= 0.5 / n away
            # from an integer, far more than the float64 rounding error
            r = np.int64((g + 0.5) * inv_len)
            c = g - r * row_len
            q = np.int64((r + 0.5) * inv_ss) * width + np.int64((c + 0.5) * inv_ss)
        s = spec[q]
        for c in range(3):
            x = albedo[i, c] * (ambient + k[i] * rgb[i, c]) + s * k[i] * rgb[i, c]
            img[p, c] = max(x, 0.0)


@njit(cache=True, nogil=True, parallel=True)
def gain_vignetting(
    img: np.ndarray, gain: np.ndarray, cx: float, cy: float, a: float, inv_rc2: float
) -> None:  # pragma: no cover - compiled
    """In place ``img[r, c, ch] *= gain[ch] * (1 - a ((c - cx)^2 + (r - cy)^2) inv_rc2)``."""
    H = img.shape[0]
    W = img.shape[1]
    for r in prange(H):
        dy2 = (r - cy) * (r - cy)
        for c in range(W):
            f = 1.0 - a * ((c - cx) * (c - cx) + dy2) * inv_rc2
            for ch in range(img.shape[2]):
                img[r, c, ch] *= gain[ch] * f
