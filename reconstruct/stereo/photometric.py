"""Photometric equalisation of a stereo pair: the right view's gain field.

The views of a real rig differ in exposure, colour balance and vignetting: smooth
multiplicative fields per channel that census ignores but the colour-difference
cost and Lucas-Kanade do not (docs/matching.md). :func:`fit_gain_field` samples the
log ratio ``log L(x, y) - log R(x - d, y)`` at matched pixels and fits a low-order
2-D polynomial by IRLS (Tukey's biweight on a MAD scale); ``right * field`` then
has the left view's exposure.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.reconstruct.stereo import _photometric_kernels as _k

__all__ = ["GainField", "fit_gain_field"]

#: Samples closer than this to black or white (8-bit levels) are not used: the ratio
#: of clipped or noise-dominated values says nothing about the gain.
_DARK, _BRIGHT = 12.0, 243.0
#: Fewest samples per polynomial term; fewer samples lower the degree.
_SAMPLES_PER_TERM = 30
#: Most samples used (an even subset of the matched pixels): ~1300 per term at degree 4.
_MAX_SAMPLES = 20000
#: Tukey's biweight constant (95 % efficiency for Gaussian residuals).
_TUKEY_C = 4.685
#: Spacing (px) of the grid the field is evaluated on before bilinear interpolation.
_GRID = 8
#: A field within this of 1 everywhere changes no 8-bit value by more than ~0.5 level:
#: applying it is skipped.
_NEGLIGIBLE = 0.002
#: Highest polynomial degree accepted (a higher one over-fits the smooth field).
_MAX_DEGREE = 6
#: Ridge on the shape terms, per sample: keeps the fit tame where samples are sparse.
_RIDGE_PER_SAMPLE = 1e-4
#: Iteratively re-weighted least-squares passes (the weights settle within a few).
_IRLS_ITERS = 6
#: MAD -> standard deviation for Gaussian residuals.
_MAD_TO_SIGMA = 1.4826
#: Floor of the robust scale (log-gain units) so that a perfect fit does not divide by 0.
_MIN_SCALE = 1e-4


@dataclass(frozen=True)
class GainField:
    """A per-channel multiplicative field ``exp(poly(x, y))`` over an image.

    ``coef`` (C, T) float64: coefficients of the terms ``x^i y^j``, ``i + j <= degree``,
    in coordinates normalised to [-1, 1] over ``size`` = image ``(width, height)``.
    """

    coef: NDArray[np.float64]
    degree: int
    size: tuple[int, int]

    @classmethod
    def identity(cls, channels: int, size: tuple[int, int]) -> GainField:
        """The field that changes nothing."""
        return cls(np.zeros((channels, 1)), 0, (int(size[0]), int(size[1])))

    @property
    def is_identity(self) -> bool:
        """No change at all (the field :meth:`identity` returns)."""
        return not np.any(self.coef)

    def evaluate(self, rows: slice | None = None) -> NDArray[np.float32]:
        """The gain (H, W, C) float32 (or rows ``rows`` of it), evaluated every ``_GRID`` px
        and interpolated bilinearly (linear to ~1e-5 over that step).
        """
        w, h = self.size
        r0, r1, _ = (rows if rows is not None else slice(None)).indices(h)
        nrows = max(r1 - r0, 0)
        nc = self.coef.shape[0]
        if not nrows:
            return np.empty((0, w, nc), np.float32)
        gx = np.arange(0.0, w - 1.0 + _GRID, _GRID)
        gy = np.arange(float(r0), r0 + nrows - 1.0 + _GRID, _GRID)
        xn, yn = _normalised(gx, w), _normalised(gy, h)
        acc = np.zeros((len(gy), len(gx), nc))
        for c, coef in enumerate(self.coef):
            for t, (i, j) in enumerate(_terms(self.degree)):
                if coef[t] != 0.0:
                    acc[..., c] += coef[t] * np.outer(yn**j, xn**i)
        # output pixel (x, y) reads the grid at (x / _GRID, y / _GRID); every channel
        # in one warp
        M = np.array([[1.0 / _GRID, 0.0, 0.0], [0.0, 1.0 / _GRID, 0.0]])
        out = cv2.warpAffine(np.exp(acc).astype(np.float32), M, (w, nrows),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(nrows, w, nc)

    def apply(self, image: NDArray, *, row0: int = 0) -> NDArray:
        """``image * gain`` in the image's own dtype (uint8 rounded and saturated);
        ``image`` holds rows ``row0..`` of the field's grid."""
        img = np.asarray(image)
        if self.negligible():
            return img
        g = self.evaluate(slice(row0, row0 + img.shape[0]))
        g = g if img.ndim == 3 else g[..., 0]
        if img.dtype == np.uint8:  # the float product rounded half to even and saturated
            return cv2.multiply(img, g, dtype=cv2.CV_8U).reshape(img.shape)
        return (img.astype(np.float32) * g).astype(img.dtype)

    def gains_on_grid(self, n: int = 5) -> NDArray[np.float64]:
        """``(C, n, n)`` gains on an ``n x n`` grid spanning the image (corners included),
        for reports and for telling a negligible field."""
        t = np.linspace(-1.0, 1.0, n)
        yy, xx = np.meshgrid(t, t, indexing="ij")
        A = np.stack([xx.ravel() ** i * yy.ravel() ** j for i, j in _terms(self.degree)], axis=1)
        return np.exp(self.coef @ A.T).reshape(-1, n, n)

    def negligible(self, tol: float = _NEGLIGIBLE) -> bool:
        """True when the gain stays within ``tol`` of 1 everywhere on a 5 x 5 grid."""
        return bool(np.all(np.abs(self.gains_on_grid() - 1.0) <= tol))


def _terms(degree: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def _normalised(v: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    return v / max(n - 1, 1) * 2.0 - 1.0


def fit_gain_field(
    left: NDArray,
    right: NDArray,
    disparity: NDArray,
    valid: NDArray,
    *,
    scale: float = 1.0,
    size: tuple[int, int] | None = None,
    max_degree: int = 4,
) -> GainField:
    """The gain that maps the right view's values onto the left's (``right * field``).

    left, right: (h, w[, C]) uint8 views, possibly downsampled, of ``disparity`` (h, w)
    (``x_left - x_right``, used at ``valid``). ``scale``: full-resolution pixels per
    pixel here; ``size``: the full-resolution ``(width, height)`` the field is defined
    on (default ``(w, h) * scale``). ``max_degree`` (<= 6; 4 holds cos^4 vignetting)
    drops with fewer than ``_SAMPLES_PER_TERM`` samples per term. Identity when too
    few samples.
    """
    L = check_array(left, "left", ndim=(2, 3)).astype(np.float32)
    R = check_array(right, "right", ndim=(2, 3)).astype(np.float32)
    if L.shape != R.shape:
        raise InputError(f"left {L.shape} and right {R.shape} must have the same shape")
    L = L[..., None] if L.ndim == 2 else L
    R = R[..., None] if R.ndim == 2 else R
    h, w, nc = L.shape
    d = check_array(disparity, "disparity", shape=(h, w), dtype_kind="f")
    m = check_array(valid, "valid", shape=(h, w)).astype(bool) & np.isfinite(d)
    if not (isinstance(max_degree, int) and 0 <= max_degree <= _MAX_DEGREE):
        raise InputError(f"max_degree: expected an integer in [0, 6], got {max_degree!r}")
    full = (int(round(w * scale)), int(round(h * scale))) if size is None else (int(size[0]), int(size[1]))
    lv, rv, ys, xr = _samples(L, R, d, m)
    n = len(ys)
    degree = max_degree
    while degree > 0 and n < _SAMPLES_PER_TERM * len(_terms(degree)):
        degree -= 1
    if n < _SAMPLES_PER_TERM:
        return GainField.identity(nc, full)
    g = np.log(lv.astype(np.float64)) - np.log(rv.astype(np.float64))
    # sample positions on the full-resolution grid of the right view, normalised
    xn = _normalised((xr + 0.5) * scale - 0.5, full[0])
    yn = _normalised((ys + 0.5) * scale - 0.5, full[1])
    return GainField(_irls(xn, yn, g, degree), degree, full)


def _samples(L: NDArray[np.float32], R: NDArray[np.float32], d: NDArray, m: NDArray[np.bool_]
             ) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Left and right values (N, C), rows and right-view columns of the usable matches."""
    h, w, _ = L.shape
    ys, xs = np.nonzero(m)
    if len(ys) > _MAX_SAMPLES:  # an even subset: a few thousand samples pin 15 terms
        step = -(-len(ys) // _MAX_SAMPLES)
        ys, xs = ys[::step], xs[::step]
    xr = xs - d[ys, xs].astype(np.float64)
    inside = (xr >= 0) & (xr <= w - 1)
    ys, xs, xr = ys[inside], xs[inside], xr[inside]
    x0 = np.floor(xr).astype(np.intp)
    x1 = np.minimum(x0 + 1, w - 1)
    t = (xr - x0)[:, None].astype(np.float32)
    rv = R[ys, x0] * (1 - t) + R[ys, x1] * t
    lv = L[ys, xs]
    usable = np.all((lv > _DARK) & (lv < _BRIGHT) & (rv > _DARK) & (rv < _BRIGHT), axis=1)
    return lv[usable], rv[usable], ys[usable], xr[usable]


def _irls(xn: NDArray[np.float64], yn: NDArray[np.float64], g: NDArray[np.float64], degree: int
          ) -> NDArray[np.float64]:
    """Coefficients (C, T) of ``g[:, c] ~ sum_t beta[c, t] x^i y^j`` by Tukey-biweight IRLS on
    a MAD scale, every channel at once.

    The weighted normal matrix of a polynomial basis holds only the weighted moments
    ``sum w x^p y^q`` (``p + q <= 2 degree``): one product of the moments' basis with the
    channels' weights per pass gives every channel's matrix (45 moments against 15 x 15
    products at degree 4), instead of weighting the design matrix per channel.
    """
    terms = _terms(degree)
    moments = _terms(2 * degree)
    n, nc = g.shape
    px, py = np.ones((2 * degree + 1, n)), np.ones((2 * degree + 1, n))
    for p in range(1, 2 * degree + 1):
        np.multiply(px[p - 1], xn, out=px[p])
        np.multiply(py[p - 1], yn, out=py[p])
    basis = np.empty((len(moments), n))  # (M, N)
    for k, (p, q) in enumerate(moments):
        np.multiply(px[p], py[q], out=basis[k])
    at = {m: k for k, m in enumerate(moments)}
    design = basis[[at[t] for t in terms]]  # (T, N)
    pick = np.array([[at[(a[0] + b[0], a[1] + b[1])] for b in terms] for a in terms])
    ridge = np.diag(np.r_[0.0, np.full(len(terms) - 1, _RIDGE_PER_SAMPLE * n)])
    wgt = np.ones((n, nc))
    beta = np.zeros((nc, len(terms)))
    for _ in range(_IRLS_ITERS):
        mom = (basis @ wgt).T  # (C, M)
        rhs = (design @ (wgt * g)).T  # (C, T)
        for c in range(nc):
            beta[c] = np.linalg.solve(mom[c][pick] + ridge, rhs[c])
        _k.tukey_weights(g - design.T @ beta.T, _TUKEY_C, _MAD_TO_SIGMA, _MIN_SCALE, wgt)
    return beta
