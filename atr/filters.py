"""Correlation filters (MACE, UMACE, MACH, OT-MACH) and correlation-peak metrics.

All filters are designed in the 2-D frequency domain (numpy FFT) from ``N``
training images ``x_i`` of shape ``(H, W)``; ``X_i = fft2(x_i)``, ``d = H * W``.
A filter is the complex array ``F`` ``(H, W)``; the correlation plane of an image
``g`` is ``c = ifft2(fft2(g) * conj(F))`` (real part), i.e.
``c[s] = sum_x g(x + s) f(x)`` with circular wrap: a target shifted by ``s`` moves
the peak from ``(0, 0)`` to ``s``. :func:`correlate` returns the plane with the
zero shift at the centre ``(H // 2, W // 2)`` (``np.fft.fftshift``).

Designs (diagonal matrices stored as ``(H, W)`` arrays):

* MACE: ``F = d D^-1 X (X^+ D^-1 X)^-1 u`` with ``D`` the average power spectrum
  ``mean |X_i|^2`` and ``u = 1``: every training image correlates to exactly 1 at
  the origin while the plane energy is minimal (sharp peaks).
* UMACE: ``F = D^-1 m`` with ``m = mean X_i`` (no constraint, no matrix inverse).
* MACH: ``F = S^-1 m`` with the average similarity measure
  ``S = mean |X_i - m|^2`` (peak-height variation across the class is minimal).
* OT-MACH: ``F = m / (alpha C + beta D + gamma S)`` with white-noise ``C = 1``
  (scaled to the mean of ``D``) -- the optimal trade-off of noise tolerance (C),
  peak sharpness (D) and distortion tolerance (S). ``(0, 1, 0)`` is UMACE,
  ``(0, 0, 1)`` is MACH, ``(1, 0, 0)`` is the matched filter of the class mean.

A tiny ``eps`` (relative to the mean of the denominator) keeps divisions finite; it
does not change the MACE constraints (they hold for any positive diagonal ``D``).

References
----------
.. [1] A. Mahalanobis, B. V. K. Vijaya Kumar, D. Casasent, "Minimum average
   correlation energy filters", Applied Optics 26(17), 3633-3640 (1987).
.. [2] A. Mahalanobis, B. V. K. Vijaya Kumar, S. Song, S. R. F. Sims, J. F.
   Epperson, "Unconstrained correlation filters", Applied Optics 33(17),
   3751-3759 (1994) (UMACE, MACH).
.. [3] Ph. Refregier, "Filter design for optical pattern recognition:
   multicriteria optimization approach", Optics Letters 15(15), 854-856 (1990).
.. [4] B. V. K. Vijaya Kumar, A. Mahalanobis, R. D. Juday, *Correlation Pattern
   Recognition*, Cambridge University Press (2005).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError

__all__ = [
    "PSR_EXCLUDE",
    "PSR_WINDOW",
    "CorrelationFilter",
    "correlate",
    "correlate_many",
    "mace_filter",
    "mach_filter",
    "otmach_filter",
    "otmach_from_moments",
    "peak_metrics",
    "psr",
    "umace_filter",
]

#: PSR sidelobe window side (pixels) centred on the peak ...
PSR_WINDOW = 20
#: ... excluding this central square (pixels).
PSR_EXCLUDE = 5
_EPS = 1e-9


@dataclass(frozen=True, eq=False)
class CorrelationFilter:
    """A frequency-domain correlation filter.

    Attributes
    ----------
    freq : (H, W) complex128
        The filter ``F`` (module docstring).
    kind : str
        ``"mace"``, ``"umace"``, ``"mach"`` or ``"otmach"``.
    params : tuple of float
        ``(alpha, beta, gamma)`` for OT-MACH (and the equivalent for UMACE/MACH).
    """

    freq: NDArray[np.complex128]
    kind: str
    params: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.freq.shape)  # type: ignore[return-value]

    def correlate(self, image: NDArray) -> NDArray[np.float64]:
        """Centred correlation plane ``(H, W)`` of ``image`` (see :func:`correlate`)."""
        return correlate(self, image)

    def spatial(self) -> NDArray[np.float64]:
        """The filter as an ``(H, W)`` image (origin at ``[0, 0]``)."""
        return np.fft.ifft2(self.freq).real


def _stack(images: NDArray, name: str = "images") -> NDArray[np.float64]:
    x = check_array(images, name, ndim=3, dtype_kind="fiub")
    if x.shape[0] < 1 or x.shape[1] < 1 or x.shape[2] < 1:
        raise InputError(f"{name}: expected (N, H, W) with N, H, W >= 1, got {x.shape}")
    x = x.astype(np.float64)
    if not np.all(np.isfinite(x)):
        raise InputError(f"{name}: contains NaN or inf (replace invalid pixels first, e.g. by 0)")
    return x


def _spectra(images: NDArray) -> NDArray[np.complex128]:
    return np.fft.fft2(_stack(images), axes=(-2, -1))


def _reg(a: NDArray[np.float64]) -> NDArray[np.float64]:
    return a + _EPS * max(float(a.mean()), 1e-300)


def mace_filter(images: NDArray) -> CorrelationFilter:
    """MACE filter of ``(N, H, W)`` training images: correlation peak 1 at the origin
    for each of them, minimum average correlation-plane energy.

    Raises
    ------
    InputError
        Bad array, NaN, or linearly dependent training images (singular ``X^+ D^-1 X``).
    """
    X = _spectra(images)
    n = X.shape[0]
    d = X.shape[1] * X.shape[2]
    D = _reg(np.mean(np.abs(X) ** 2, axis=0))
    Xf = X.reshape(n, -1)  # rows = x_i^T
    Dinv = 1.0 / D.reshape(-1)
    A = (Xf.conj() * Dinv) @ Xf.T  # A[i, j] = X_i^+ D^-1 X_j
    try:
        coef = np.linalg.solve(A, np.ones(n, dtype=np.complex128))
    except np.linalg.LinAlgError:
        raise InputError(
            "mace_filter: training images are linearly dependent (singular matrix)"
        ) from None
    if not np.all(np.isfinite(coef)):
        raise InputError("mace_filter: training images are linearly dependent (singular matrix)")
    F = d * Dinv * (coef @ Xf)
    return CorrelationFilter(F.reshape(X.shape[1:]), "mace")


def _moments(images: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    X = _spectra(images)
    m = X.mean(axis=0)
    D = np.mean(np.abs(X) ** 2, axis=0)
    S = np.mean(np.abs(X - m) ** 2, axis=0)
    return m, D, S


def otmach_from_moments(
    m: NDArray, D: NDArray, S: NDArray, alpha: float, beta: float, gamma: float
) -> CorrelationFilter:
    """OT-MACH from precomputed spectral moments (mean ``m``, power ``D``, similarity ``S``)."""
    for v, nm in ((alpha, "alpha"), (beta, "beta"), (gamma, "gamma")):
        if not (math.isfinite(v) and v >= 0):
            raise InputError(f"{nm}: expected a finite value >= 0, got {v}")
    if alpha + beta + gamma <= 0:
        raise InputError("otmach: alpha + beta + gamma must be > 0")
    C = float(D.mean())  # white noise with the power of the training set
    den = _reg(alpha * C + beta * D + gamma * S)
    return CorrelationFilter(m / den, "otmach", (float(alpha), float(beta), float(gamma)))


def otmach_filter(images: NDArray, alpha: float, beta: float, gamma: float) -> CorrelationFilter:
    """Optimal trade-off MACH filter ``F = m / (alpha C + beta D + gamma S)``.

    ``C`` is white noise scaled to the mean power of the training spectra, so the
    three weights are comparable. Scaling all three weights by ``k`` scales ``F``
    by ``1/k`` (peak metrics such as PSR are unchanged).
    """
    m, D, S = _moments(images)
    return otmach_from_moments(m, D, S, alpha, beta, gamma)


def umace_filter(images: NDArray) -> CorrelationFilter:
    """Unconstrained MACE: ``F = D^-1 m``."""
    m, D, _ = _moments(images)
    return CorrelationFilter(m / _reg(D), "umace", (0.0, 1.0, 0.0))


def mach_filter(images: NDArray) -> CorrelationFilter:
    """MACH: ``F = S^-1 m`` (needs >= 2 distinct training images)."""
    m, _, S = _moments(images)
    if not np.any(S > 0):
        raise InputError("mach_filter: needs at least two different training images (S = 0)")
    return CorrelationFilter(m / _reg(S), "mach", (0.0, 0.0, 1.0))


def correlate(filt: CorrelationFilter, image: NDArray) -> NDArray[np.float64]:
    """Correlation plane ``(H, W)`` float64 of one image, zero shift at ``(H//2, W//2)``.

    A target shifted by ``(dr, dc)`` (circularly) puts the peak at
    ``(H//2 + dr, W//2 + dc)``.
    """
    g = check_array(image, "image", ndim=2, dtype_kind="fiub").astype(np.float64)
    if g.shape != filt.freq.shape:
        raise InputError(f"image: expected shape {filt.freq.shape} (the filter's), got {g.shape}")
    c = np.fft.ifft2(np.fft.fft2(g) * np.conj(filt.freq)).real
    return np.fft.fftshift(c)


def correlate_many(freqs: NDArray, spectra: NDArray) -> NDArray[np.float64]:
    """Centred planes ``(N, K, H, W)`` of ``N`` image spectra against ``K`` filters."""
    c = np.fft.ifft2(spectra[:, None] * np.conj(freqs)[None], axes=(-2, -1)).real
    return np.fft.fftshift(c, axes=(-2, -1))


def peak_metrics(
    planes: NDArray, *, window: int = PSR_WINDOW, exclude: int = PSR_EXCLUDE
) -> dict[str, NDArray[np.float64]]:
    """Peak height, location, PSR and PCE of correlation planes.

    Parameters
    ----------
    planes : (..., H, W) float
        Correlation planes (any leading shape).
    window, exclude : int
        PSR sidelobe region: the ``window x window`` square centred on the peak
        (circular wrap at the borders) minus the central ``exclude x exclude``
        square. Defaults: 20x20 minus 5x5.

    Returns
    -------
    dict
        ``peak`` (max value), ``row``, ``col`` (its index), ``psr`` =
        ``(peak - mean(sidelobe)) / std(sidelobe)``, ``pce`` =
        ``peak^2 / sum(c^2)`` (peak-to-correlation energy, plane energy over all
        pixels), each of the leading shape.

    References
    ----------
    .. [1] B. V. K. Vijaya Kumar, A. Mahalanobis, R. D. Juday, *Correlation Pattern
       Recognition* (2005), ch. 5 (PSR, PCE).
    """
    c = np.asarray(planes, dtype=np.float64)
    if c.ndim < 2:
        raise InputError(f"planes: expected (..., H, W), got shape {c.shape}")
    H, W = c.shape[-2:]
    if not (isinstance(window, int) and isinstance(exclude, int) and 0 < exclude < window):
        raise InputError(
            f"window, exclude: expected integers 0 < exclude < window, got {window}, {exclude}"
        )
    if window > min(H, W):
        raise InputError(f"window: {window} exceeds the plane size {H}x{W}")
    lead = c.shape[:-2]
    flat = c.reshape(-1, H, W)
    idx = np.argmax(flat.reshape(len(flat), -1), axis=1)
    r, q = np.divmod(idx, W)
    peak = flat.reshape(len(flat), -1)[np.arange(len(flat)), idx]
    off = np.arange(window) - window // 2
    rr = (r[:, None] + off[None]) % H
    cc = (q[:, None] + off[None]) % W
    win = flat[np.arange(len(flat))[:, None, None], rr[:, :, None], cc[:, None, :]]
    keep = np.ones((window, window), dtype=bool)
    e0 = window // 2 - exclude // 2
    keep[e0 : e0 + exclude, e0 : e0 + exclude] = False
    side = win[:, keep]
    mu = side.mean(axis=1)
    sd = side.std(axis=1)
    psr_v = (peak - mu) / np.maximum(sd, 1e-300)
    energy = np.sum(flat**2, axis=(1, 2))
    pce = peak**2 / np.maximum(energy, 1e-300)
    return {
        "peak": peak.reshape(lead),
        "row": r.reshape(lead),
        "col": q.reshape(lead),
        "psr": psr_v.reshape(lead),
        "pce": pce.reshape(lead),
    }


def psr(plane: NDArray, *, window: int = PSR_WINDOW, exclude: int = PSR_EXCLUDE) -> float:
    """Peak-to-sidelobe ratio of one plane (see :func:`peak_metrics`)."""
    return float(peak_metrics(np.asarray(plane)[None], window=window, exclude=exclude)["psr"][0])
