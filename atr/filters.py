"""Correlation filters (MACE, UMACE, MACH, OT-MACH) and correlation-peak metrics.

Filters are ``(H, W)`` complex arrays designed in the 2-D frequency domain from
``(N, H, W)`` training images; the correlation plane of ``g`` is
``ifft2(fft2(g) * conj(F))`` (a target shifted by ``s`` moves the peak to ``s``).
Designs and conventions: docs/atr.md "Correlation filters".

References
----------
.. [1] Mahalanobis, Kumar, Casasent, Applied Optics 26(17), 3633 (1987) (MACE).
.. [2] Mahalanobis et al., Applied Optics 33(17), 3751 (1994) (UMACE, MACH).
.. [3] Refregier, Optics Letters 15(15), 854 (1990) (optimal trade-off).
.. [4] Kumar, Mahalanobis, Juday, *Correlation Pattern Recognition*, CUP (2005).
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
    """A frequency-domain filter: ``freq`` (H, W) complex128, ``kind`` (mace, umace,
    mach, otmach) and OT-MACH ``params`` (alpha, beta, gamma).
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
    """MACE filter of ``(N, H, W)`` images: peak 1 at the origin for each, minimum
    average plane energy. InputError for linearly dependent images.
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
    """OT-MACH filter ``F = m / (alpha C + beta D + gamma S)`` (white noise ``C``
    scaled to the mean power, so the weights are comparable; only their ratios matter).
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
    """Peak height, location, PSR and PCE of ``(..., H, W)`` correlation planes.

    Returns a dict of leading-shape arrays: ``peak``, ``row``, ``col``, ``psr`` =
    ``(peak - mean(sidelobe)) / std(sidelobe)`` over the ``window`` square around the peak
    (wrapping) minus the central ``exclude`` square, and ``pce`` = ``peak^2 / sum(c^2)``
    (Kumar et al. 2005, ch. 5).
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
