"""The paper's accuracy test (Table I, eq. 9-16): least-squares planes ``z = a x + b y
+ c`` in five regions of a scanned flat plate, their residual RMS, and the rig's depth
resolution ``z^2 / (f B)`` per pixel of disparity beside it."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_in_range
from prism3d.errors import InputError, ReconstructionError
from prism3d.io.ply import read_ply

__all__ = ["REGIONS", "FlatnessReport", "PlaneFit", "fit_plane", "flatness_of_ply", "flatness_test", "ransac_plane"]

#: Region names and centres as fractions of the plate's extent (x right, y down).
REGIONS: dict[str, tuple[float, float]] = {
    "upper_left": (0.2, 0.2),
    "upper_right": (0.8, 0.2),
    "centre": (0.5, 0.5),
    "lower_left": (0.2, 0.8),
    "lower_right": (0.8, 0.8),
}


#: The plate's extent: these percentiles of the points (stray points do not count).
_EXTENT_PERCENTILES = (1, 99)


@dataclass(frozen=True)
class PlaneFit:
    """Least-squares plane ``z = a x + b y + c`` and its residuals (mm)."""

    a: float
    b: float
    c: float
    rms_mm: float
    """RMS of the z residuals (eq. 14)."""
    rms_orthogonal_mm: float
    """RMS of the distances to the plane."""
    max_abs_mm: float
    n_points: int


def ransac_plane(sample: NDArray, tol: float | NDArray, rng: np.random.Generator, *, iterations: int = 300,
                 accept=None) -> tuple[NDArray[np.float64], float, int]:
    """The dominant plane ``n . p + d = 0`` of ``sample`` (n, 3) by RANSAC on point
    triples (``tol``: inlier distance, scalar or per point; ``accept(n)``: a test a
    candidate normal must pass; normals oriented so ``d >= 0``), refitted by least
    squares to its inliers. Returns ``(n, d, inlier count of the RANSAC winner)``;
    ``(None, 0.0, -1)`` when no candidate passes."""
    best, best_n = None, -1
    for _ in range(iterations):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n)
        if nn < 1e-9:
            continue
        n /= nn
        d = -float(n @ a)
        if d < 0:
            n, d = -n, -d
        if accept is not None and not accept(n):
            continue
        cnt = int(np.sum(np.abs(sample @ n + d) < tol))
        if cnt > best_n:
            best, best_n = (n, d), cnt
    if best is None:
        return None, 0.0, -1
    n, d = best
    q = sample[np.abs(sample @ n + d) < tol]
    c = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - c, full_matrices=False)
    n2 = vt[2] * (1 if vt[2] @ n > 0 else -1)
    return n2, -float(n2 @ c), best_n


def fit_plane(points: NDArray) -> PlaneFit:
    """Fit ``z = a x + b y + c`` to ``(N, 3)`` points by least squares (the paper's eq. 9-14)."""
    p = check_array(points, "points", shape=(None, 3), dtype_kind="fiu").astype(np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 3:
        raise ReconstructionError(f"plane fit needs at least 3 points, got {len(p)}")
    centre = p.mean(axis=0)
    q = p - centre  # centring keeps the normal equations well conditioned
    A = np.c_[q[:, 0], q[:, 1], np.ones(len(q))]
    sol, *_ = np.linalg.lstsq(A, q[:, 2], rcond=None)
    a, b, c0 = sol
    c = c0 + centre[2] - a * centre[0] - b * centre[1]
    res = q[:, 2] - A @ sol
    rms = float(np.sqrt(np.mean(res**2)))
    return PlaneFit(float(a), float(b), float(c), rms, rms / float(np.sqrt(1 + a * a + b * b)),
                    float(np.max(np.abs(res))), len(p))


@dataclass(frozen=True)
class FlatnessReport:
    """Table I for one scan."""

    regions: dict[str, PlaneFit]
    whole: PlaneFit
    mean_depth_mm: float
    region_size_mm: tuple[float, float]
    resolution_mm_per_px: float | None
    """eq. 16 at the mean depth, when focal length and baseline are known."""

    @property
    def mean_rms_mm(self) -> float:
        return float(np.mean([r.rms_mm for r in self.regions.values()]))

    def to_dict(self) -> dict:
        return {
            "regions": {k: asdict(v) for k, v in self.regions.items()},
            "whole": asdict(self.whole),
            "mean_rms_mm": self.mean_rms_mm,
            "mean_depth_mm": self.mean_depth_mm,
            "region_size_mm": list(self.region_size_mm),
            "resolution_mm_per_px": self.resolution_mm_per_px,
        }

    def table(self) -> str:
        lines = [f"{'region':<12} {'points':>8} {'RMS (mm)':>9} {'max (mm)':>9}"]
        for k, r in self.regions.items():
            lines.append(f"{k:<12} {r.n_points:>8d} {r.rms_mm:>9.4f} {r.max_abs_mm:>9.4f}")
        lines.append(f"{'mean':<12} {'':>8} {self.mean_rms_mm:>9.4f}")
        lines.append(f"whole plate: {self.whole.n_points} points, RMS {self.whole.rms_mm:.4f} mm; "
                     f"mean depth {self.mean_depth_mm:.1f} mm")
        if self.resolution_mm_per_px is not None:
            lines.append(f"depth resolution (eq. 16): {self.resolution_mm_per_px:.3f} mm per pixel of disparity")
        return "\n".join(lines)


def flatness_test(
    points: NDArray,
    *,
    region_fraction: float = 0.2,
    focal_px: float | None = None,
    baseline_mm: float | None = None,
    min_points: int = 50,
) -> FlatnessReport:
    """Table I: plane fits in squares of ``region_fraction`` of the plate's extent (the
    points' 1st-99th percentile box in x, y) around the centres in :data:`REGIONS`.

    Raises
    ------
    ReconstructionError
        A region holds fewer than ``min_points`` points (the scan does not cover the plate).
    """
    p = check_array(points, "points", shape=(None, 3), dtype_kind="fiu").astype(np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    check_in_range(region_fraction, "region_fraction", 0.01, 0.5)
    for name, v in (("focal_px", focal_px), ("baseline_mm", baseline_mm)):
        if v is not None and not (np.isfinite(v) and v > 0):
            raise InputError(f"{name}: expected a finite number > 0, got {v!r}")
    if len(p) < 5 * min_points:
        raise ReconstructionError(f"too few points for the flatness test: {len(p)}")
    x0, x1 = np.percentile(p[:, 0], list(_EXTENT_PERCENTILES))
    y0, y1 = np.percentile(p[:, 1], list(_EXTENT_PERCENTILES))
    hx = 0.5 * region_fraction * (x1 - x0)
    hy = 0.5 * region_fraction * (y1 - y0)
    regions = {}
    for name, (fx, fy) in REGIONS.items():
        cx, cy = x0 + fx * (x1 - x0), y0 + fy * (y1 - y0)
        sel = (np.abs(p[:, 0] - cx) <= hx) & (np.abs(p[:, 1] - cy) <= hy)
        if sel.sum() < min_points:
            raise ReconstructionError(
                f"region {name} holds {int(sel.sum())} points (< {min_points}): the scan does not cover the plate"
            )
        regions[name] = fit_plane(p[sel])
    whole = fit_plane(p)
    zbar = float(np.mean(p[:, 2]))
    res = None
    if focal_px is not None and baseline_mm is not None:
        res = zbar**2 / (float(focal_px) * float(baseline_mm))
    return FlatnessReport(regions, whole, zbar, (2 * hx, 2 * hy), res)


def flatness_of_ply(path: str | Path, **kwargs: float) -> FlatnessReport:
    """Run :func:`flatness_test` on a PLY scan; reads ``focal_px``/``baseline_mm``
    from the scan's comments (written by ``prism3d reconstruct``) when not given."""
    ply = read_ply(path)
    meta = {}
    for c in ply.comments:
        key, _, val = c.partition(" ")
        if key in ("focal_px", "baseline_mm"):
            try:
                meta[key] = float(val)
            except ValueError as exc:
                raise InputError(f"{path}: malformed comment {c!r}") from exc
    for k, v in meta.items():
        kwargs.setdefault(k, v)
    return flatness_test(ply.points, **kwargs)
