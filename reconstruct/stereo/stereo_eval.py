"""Score a disparity map against ground truth (Middlebury-style error rates).

A pixel is *scored* where the ground truth is known (finite and > 0, or ``gt_valid``)
and inside ``mask``; a scored pixel without an estimate counts as bad in the dense
rates, the ``*_valid`` rates use only pixels with one.

References: Scharstein, Szeliski, "A taxonomy and evaluation of dense two-frame stereo
correspondence algorithms", IJCV 47, 2002.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_positive, check_same_shape
from prism3d.errors import InputError
from prism3d.io.images import read_image
from prism3d.io.pfm import read_pfm

__all__ = ["DisparityScore", "score_disparity", "sky_mask"]


@dataclass(frozen=True)
class DisparityScore:
    """Error rates of one disparity map (fractions 0..1, errors in px).

    ``bad1``/``bad2``: scored pixels with ``|d - gt|`` above the thresholds or no
    estimate; ``*_valid``: the same over pixels with an estimate; ``avg_err``,
    ``rms_err`` over those; ``density``: share with an estimate; ``n_scored``.
    """

    bad1: float
    bad2: float
    bad1_valid: float
    bad2_valid: float
    avg_err: float
    rms_err: float
    density: float
    n_scored: int

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (for JSON / tables)."""
        return asdict(self)


def score_disparity(
    disparity: NDArray[Any],
    gt: NDArray[Any],
    *,
    mask: NDArray[Any] | None = None,
    gt_valid: NDArray[Any] | None = None,
    negative_invalid: bool = False,
    thresholds: tuple[float, float] = (1.0, 2.0),
) -> DisparityScore:
    """Score ``disparity`` (H, W) px (NaN/inf = no estimate) against ``gt`` (H, W) px.

    ``gt`` non-finite or <= 0 is unknown unless ``gt_valid`` is given; ``mask`` limits
    the region; ``negative_invalid`` treats negative estimates as missing (OpenCV);
    ``thresholds`` of bad1, bad2. Raises InputError for unequal or non-2-D shapes or
    when no pixel is scored.
    """
    d = check_array(disparity, "disparity", ndim=2, dtype_kind="fiu").astype(np.float64)
    g = check_array(gt, "gt", ndim=2, dtype_kind="fiu").astype(np.float64)
    check_same_shape(d, g, ("disparity", "gt"))
    t1 = check_positive(thresholds[0], "thresholds[0]")
    t2 = check_positive(thresholds[1], "thresholds[1]")
    if gt_valid is None:
        known = np.isfinite(g) & (g > 0)
    else:
        gv = check_array(gt_valid, "gt_valid", ndim=2, dtype_kind="b")
        check_same_shape(gv, g, ("gt_valid", "gt"))
        known = gv & np.isfinite(g)
    if mask is not None:
        m = check_array(mask, "mask", ndim=2, dtype_kind="b")
        check_same_shape(m, g, ("mask", "gt"))
        known &= m
    n = int(known.sum())
    if n == 0:
        raise InputError("gt: no pixel to score (ground truth unknown everywhere in the mask)")
    has = np.isfinite(d)
    if negative_invalid:
        has &= d >= 0
    has_s = has & known
    err = np.abs(d[has_s] - g[has_s])
    nv = max(int(has_s.sum()), 1)
    bad1_v = int((err > t1).sum())
    bad2_v = int((err > t2).sum())
    missing = n - int(has_s.sum())
    return DisparityScore(
        bad1=(bad1_v + missing) / n,
        bad2=(bad2_v + missing) / n,
        bad1_valid=bad1_v / nv,
        bad2_valid=bad2_v / nv,
        avg_err=float(err.mean()) if err.size else float("nan"),
        rms_err=float(np.sqrt(np.mean(err**2))) if err.size else float("nan"),
        density=int(has_s.sum()) / n,
        n_scored=n,
    )


#: The ground-truthed real stereo pairs of the shared test data (see its README).
BENCHMARK_SCENES = ("tsukuba", "venus", "teddy", "cones", "aloe", "playground", "terrace", "kitti")


def load_benchmark_pair(data_root: str | Path, name: str) -> tuple[NDArray, NDArray, NDArray[np.float32], NDArray | None]:
    """``(left RGB, right RGB, gt disparity (0 = unknown), non-occluded mask or None)``
    of the pair ``name`` under ``data_root/stereo`` (Middlebury's scaled PNG, ETH3D's
    PFM with inf, KITTI's PNG x 256 decoded).
    """
    import cv2

    if name not in BENCHMARK_SCENES:
        raise InputError(f"unknown benchmark scene {name!r}; valid: {', '.join(BENCHMARK_SCENES)}")
    st = Path(data_root) / "stereo"
    mask = None

    def grey(path: Path, flags: int = cv2.IMREAD_GRAYSCALE) -> NDArray:
        img = cv2.imread(str(path), flags)
        if img is None:
            raise InputError(f"{path}: cannot read the ground truth")
        return img

    if name in ("tsukuba", "venus", "teddy", "cones"):
        files = {"tsukuba": ("im3.png", "im4.png", 16), "venus": ("im2.ppm", "im6.ppm", 8),
                 "teddy": ("im2.png", "im6.png", 4), "cones": ("im2.png", "im6.png", 4)}
        a, b, scale = files[name]
        d = st / "middlebury_2001_2003" / name
        left, right = read_image(d / a), read_image(d / b)
        gt = grey(d / "groundtruth.png") / float(scale)
        mask = grey(d / "nonocc.png") == 255
    elif name == "aloe":
        d = st / "middlebury_2006_aloe"
        left, right = read_image(d / "aloeL.jpg"), read_image(d / "aloeR.jpg")
        gt = grey(d / "aloeGT.png").astype(np.float64)
    elif name in ("playground", "terrace"):
        d = st / "eth3d_two_view" / name
        left, right = read_image(d / "im0.png"), read_image(d / "im1.png")
        gt = read_pfm(d / "disp0.pfm").astype(np.float64)
        gt[~np.isfinite(gt)] = 0.0
    else:
        d = st / "kitti2015_sample"
        left, right = read_image(d / "image_2_000046_10.png"), read_image(d / "image_3_000046_10.png")
        gt = grey(d / "disp_occ_0_000046_10.png", cv2.IMREAD_UNCHANGED) / 256.0
    return left, right, gt.astype(np.float32), mask


def sky_mask(image_rgb: NDArray) -> NDArray[np.bool_]:
    """A street scene's clear sky told by colour alone, for scoring what a matcher says
    there: blue above red (by 30) and green (by 5) and bright (> 120), smooth (Gaussian-
    blurred Sobel magnitude < 25 levels), 4-connected to the top row, eroded by 2 px so
    that no edge pixel counts. On KITTI 000046_10: 82,852 pixels in rows 0-155."""
    import cv2

    im = check_array(image_rgb, "image", ndim=3).astype(np.float32)
    r, g, b = im[..., 0], im[..., 1], im[..., 2]
    grey = cv2.cvtColor(np.clip(im, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)
    grad = cv2.GaussianBlur(np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1)), (0, 0), 2)
    blue = (b > r + 30) & (b > g + 5) & (b > 120) & (grad < 25)
    _, lab = cv2.connectedComponents(blue.astype(np.uint8), connectivity=4)
    sky = np.isin(lab, np.unique(lab[0][blue[0]])) & blue
    return cv2.erode(sky.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
