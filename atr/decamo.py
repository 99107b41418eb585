"""Camouflage removal with depth: separate paint (albedo) from shading, relight the
bare 3-D shape, and flag the "false shadows" that disruptive paint paints on.

Model
-----
Per surface pixel ``p`` with unit normal ``n_p`` (from the depth map and the
intrinsics) the linear image is ``I_p = a_p * S(n_p)`` where ``a_p`` (RGB) is the
paint and ``S`` the irradiance of a distant, shadowless environment, written as a
2nd-order spherical-harmonic expansion ``S(n) = sum_i c_i Y_i(n)`` (9 coefficients;
Ramamoorthi & Hanrahan [1] showed that this captures Lambertian irradiance to a few
per cent). Depth supplies the normals, so shading is a function of geometry only
(the key idea of depth-aided intrinsic images, Chen & Koltun [2]; SIRFS [3] jointly
infers shape, too). Camouflage paint is a few flat colours, so ``a_p`` is
piecewise constant over a few clusters. :func:`decamouflage` alternates

1. a robust (Huber IRLS) least-squares fit of ``c`` to ``I_grey ≈ a_grey(label) * S(n)``;
2. k-means clustering of ``I / S`` in (log intensity, chromaticity) into ``k`` paints,
   each paint's albedo being the per-channel median of ``I / S`` over its pixels.

The first fit assumes a uniform albedo and relies on the Huber weights to discount
the paint patches. Shading and albedo are defined up to a common scale: shading is
normalised so that its 99th percentile over the surface is 1.

Outputs: ``albedo`` (the piecewise-constant paint), ``shading`` (the fitted SH
irradiance), ``shape`` (the surface relit with a uniform albedo under a canonical
light from the upper left: the true 3-D profile without false shadows) and
``false_shadow`` (dark in the image but not dark in the shading).

References
----------
.. [1] R. Ramamoorthi and P. Hanrahan, "An efficient representation for irradiance
   environment maps", SIGGRAPH 2001.
.. [2] Q. Chen and V. Koltun, "A simple model for intrinsic image decomposition with
   depth cues", ICCV 2013.
.. [3] J. T. Barron and J. Malik, "Shape, illumination, and reflectance from
   shading", IEEE TPAMI 37(8), 2015.
.. [4] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman, "Ground truth
   dataset and baseline evaluations for intrinsic image algorithms", ICCV 2009
   (the LMSE error measure, :func:`lmse`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from prism3d.atr.geometry import as_camera, depth_to_points, normals_from_depth
from prism3d.capture.rig import CameraModel

from prism3d.checks import check_array, check_choice, check_in_range, check_positive, check_same_shape
from prism3d.errors import InputError

__all__ = [
    "CANONICAL_LIGHT_CAM",
    "DecamoResult",
    "decamo_from_shot",
    "decamo_to_folder",
    "decamouflage",
    "lmse",
    "sh_basis",
]

#: Unit direction (camera frame, towards the light) of the canonical light of the
#: shape image: from the upper left, in front of the object.
CANONICAL_LIGHT_CAM = np.array([-0.45, -0.6, -1.0]) / np.linalg.norm([-0.45, -0.6, -1.0])


@dataclass(frozen=True)
class DecamoResult:
    """Result of :func:`decamouflage`.

    Attributes
    ----------
    albedo : (H, W, 3) float32
        Piecewise-constant paint colour (linear, arbitrary common scale with
        ``shading``); NaN off the surface.
    shading : (H, W) float32
        Fitted irradiance ``S(n)``; 99th percentile over the surface = 1; NaN off
        the surface.
    shape : (H, W) float32
        The surface relit with uniform albedo under :data:`CANONICAL_LIGHT_CAM`
        (``0.15 + 0.85 max(0, n . l)``), in [0, 1]; 0 off the surface.
    false_shadow : (H, W) bool
        Dark in the image but not dark in the shading, on a dark paint (paint that
        mimics shadow); see ``dark_fraction`` of :func:`decamouflage`.
    normals : (H, W, 3) float32
        Camera-frame unit normals used (NaN off the surface).
    labels : (H, W) int16
        Paint cluster of each pixel (-1 off the surface), clusters ordered from
        dark to bright.
    palette : (k, 3) float32
        The paint colours, dark to bright.
    light_coeffs : (9,) float64
        SH irradiance coefficients ``c`` (order of :func:`sh_basis`), same scale
        as ``shading``.
    mask : (H, W) bool
        Pixels on the surface that were used.
    """

    albedo: NDArray[np.float32]
    shading: NDArray[np.float32]
    shape: NDArray[np.float32]
    false_shadow: NDArray[np.bool_]
    normals: NDArray[np.float32]
    labels: NDArray[np.int16]
    palette: NDArray[np.float32]
    light_coeffs: NDArray[np.float64]
    mask: NDArray[np.bool_]


def sh_basis(normals: NDArray) -> NDArray[np.float64]:
    """Real spherical harmonics up to order 2 at unit normals.

    Parameters
    ----------
    normals : (N, 3) float
        Unit vectors ``(x, y, z)``.

    Returns
    -------
    (N, 9) float64
        ``Y00, Y1-1 (y), Y10 (z), Y11 (x), Y2-2 (xy), Y2-1 (yz), Y20 (3z^2-1),
        Y21 (xz), Y22 (x^2-y^2)`` with the normalisation constants of [1]_.

    References
    ----------
    .. [1] R. Ramamoorthi and P. Hanrahan, "An efficient representation for
       irradiance environment maps", SIGGRAPH 2001, eq. 3.
    """
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    return np.stack(
        [
            np.full_like(x, 0.282095),
            0.488603 * y,
            0.488603 * z,
            0.488603 * x,
            1.092548 * x * y,
            1.092548 * y * z,
            0.315392 * (3.0 * z * z - 1.0),
            1.092548 * x * z,
            0.546274 * (x * x - y * y),
        ],
        axis=1,
    )


def _irls(A: NDArray, b: NDArray, *, iters: int = 15, huber_k: float = 1.345) -> NDArray[np.float64]:
    """Huber-weighted iteratively reweighted least squares ``A x ≈ b``; the residual
    scale is re-estimated each step from the median absolute deviation."""
    w = np.ones(len(b))
    x = np.zeros(A.shape[1])
    reg = 1e-9 * np.eye(A.shape[1])
    for _ in range(iters):
        Aw = A * w[:, None]
        x = np.linalg.solve(A.T @ Aw + reg * max(1.0, float(np.trace(A.T @ Aw))), Aw.T @ b)
        r = b - A @ x
        sigma = 1.4826 * np.median(np.abs(r - np.median(r))) + 1e-9
        a = np.abs(r) / (huber_k * sigma)
        w = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    return x


def _kmeans(X: NDArray, k: int, *, seed: int = 0, iters: int = 30, max_fit: int = 20000) -> tuple[NDArray, NDArray]:
    """Deterministic k-means (k-means++ seeding) on ``(N, D)``; returns (labels, centres).
    Fitted on at most ``max_fit`` points (fixed-seed subsample), then all points are
    assigned."""
    rng = np.random.default_rng(seed)
    Xf = X if len(X) <= max_fit else X[rng.choice(len(X), max_fit, replace=False)]
    k = min(k, len(Xf))
    centres = [Xf[rng.integers(len(Xf))]]
    d2 = np.sum((Xf - centres[0]) ** 2, axis=1)
    for _ in range(1, k):
        tot = d2.sum()
        idx = int(rng.integers(len(Xf))) if tot <= 0 else int(rng.choice(len(Xf), p=d2 / tot))
        centres.append(Xf[idx])
        d2 = np.minimum(d2, np.sum((Xf - Xf[idx]) ** 2, axis=1))
    C = np.array(centres, dtype=np.float64)
    for _ in range(iters):
        lab = np.argmin(((Xf[:, None, :] - C[None]) ** 2).sum(-1), axis=1)
        newC = np.array([Xf[lab == j].mean(axis=0) if np.any(lab == j) else C[j] for j in range(k)])
        if np.allclose(newC, C, atol=1e-9):
            break
        C = newC
    lab_all = np.argmin(((X[:, None, :] - C[None]) ** 2).sum(-1), axis=1)
    return lab_all, C


def _to_float_image(image: NDArray) -> NDArray[np.float64]:
    img = check_array(image, "image", ndim=3, dtype_kind="fiu")
    if img.shape[2] != 3:
        raise InputError(f"image: expected (H, W, 3) RGB, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img.astype(np.float64) / 255.0
    if img.dtype.kind in "iu":
        raise InputError(f"image: expected uint8 or float in [0, 1], got {img.dtype}")
    f = img.astype(np.float64)
    if np.nanmax(f, initial=0.0) > 1.0 + 1e-6 or np.nanmin(f, initial=0.0) < -1e-6:
        raise InputError("image: float images must be in [0, 1]")
    return f


def _fill_nearest(normals: NDArray, region: NDArray) -> NDArray:
    """Fill NaN normals inside ``region`` with the nearest finite normal."""
    from scipy.ndimage import distance_transform_edt

    ok = np.all(np.isfinite(normals), axis=-1)
    need = region & ~ok
    if not need.any() or not ok.any():
        return normals
    _, (ii, jj) = distance_transform_edt(~ok, return_indices=True)
    out = normals.copy()
    out[need] = normals[ii[need], jj[need]]
    return out


def decamouflage(
    image: NDArray,
    depth_mm: NDArray,
    K: NDArray | CameraModel,
    *,
    mask: NDArray | None = None,
    n_paints: int = 4,
    iterations: int = 6,
    falloff: str = "camera",
    gamma: float = 1.0,
    dark_fraction: float = 0.3,
    seed: int = 0,
) -> DecamoResult:
    """Remove camouflage paint using depth: albedo, shading, shape image, false shadows.

    Parameters
    ----------
    image : (H, W, 3) uint8 or float in [0, 1]
        RGB image of the view the depth map belongs to.
    depth_mm : (H, W) float
        Depth along the camera z axis, mm; NaN = no surface.
    K : (3, 3) array or CameraModel
        Intrinsics of that view (a CameraModel's lens distortion is inverted exactly
        when computing normals; a bare K means an undistorted image).
    mask : (H, W) bool, optional
        Restrict to these pixels (e.g. the target); default: every finite depth.
    n_paints : int
        Number of flat paint colours (clusters), 1-12.
    iterations : int
        Alternations of lighting fit and albedo clustering.
    falloff : {"camera", "none"}
        ``"camera"`` (default, the rig's flash): the light is near the camera centre
        and its irradiance falls off as ``1 / r^2`` (``r`` = distance to the
        camera), multiplied into the SH shading. ``"none"``: distant light only.
    gamma : float
        The image is linearised as ``I ** gamma`` (1 = already linear, 2.2 ≈ sRGB).
    dark_fraction : float
        For ``false_shadow``: the image grey level is at most this fraction of its
        95th percentile over the surface, the shading is above this fraction of its
        95th percentile, and the pixel's paint is at most this fraction of the
        brightest paint.
    seed : int
        Seed of the k-means initialisation (the result is deterministic).

    Returns
    -------
    DecamoResult

    Raises
    ------
    InputError
        Image and depth sizes differ, no valid depth (all NaN), too few surface
        pixels, bad options.

    References
    ----------
    See the module docstring: Ramamoorthi & Hanrahan 2001 (SH irradiance), Chen &
    Koltun 2013 (depth cues for intrinsic images), Barron & Malik (SIRFS).
    """
    img = _to_float_image(image)
    d = check_array(depth_mm, "depth_mm", ndim=2, dtype_kind="fiu").astype(np.float64)
    if img.shape[:2] != d.shape:
        raise InputError(
            f"image and depth_mm must have the same size, got image {img.shape[1]}x{img.shape[0]} "
            f"and depth {d.shape[1]}x{d.shape[0]}"
        )
    if not np.any(np.isfinite(d)):
        raise InputError("depth_mm: no valid depth (all NaN): nothing to decamouflage")
    k = int(n_paints)
    if k != n_paints or not 1 <= k <= 12:
        raise InputError(f"n_paints: expected an integer in [1, 12], got {n_paints!r}")
    if int(iterations) != iterations or iterations < 1:
        raise InputError(f"iterations: expected a positive integer, got {iterations!r}")
    check_choice(falloff, "falloff", ("none", "camera"))
    check_positive(gamma, "gamma")
    check_in_range(dark_fraction, "dark_fraction", 0.0, 1.0)
    h, w = d.shape
    cam = as_camera(K, (w, h))
    surface = np.isfinite(d) & (d > 0)
    if mask is not None:
        m = check_array(mask, "mask", ndim=2)
        check_same_shape(m, d, ("mask", "depth_mm"))
        surface &= m.astype(bool)
    if gamma != 1.0:
        img = np.clip(img, 0.0, 1.0) ** float(gamma)

    normals = normals_from_depth(d, cam)
    normals = _fill_nearest(normals.astype(np.float64), surface)
    surface &= np.all(np.isfinite(normals), axis=-1)
    n_valid = int(surface.sum())
    if n_valid < 20:
        raise InputError(f"only {n_valid} surface pixels with valid depth; need at least 20")

    I = img[surface]  # (M, 3)
    grey = I.mean(axis=1)
    B = sh_basis(normals[surface])
    if falloff == "camera":
        r = np.linalg.norm(depth_to_points(d, cam)[surface], axis=1)
        B = B * (np.median(r) / r)[:, None] ** 2
    # pixels that inform the light fit: not saturated, not black
    fit = (I.max(axis=1) < 0.98) & (grey > 2.0 / 255.0)
    if fit.sum() < 20:
        fit = np.ones_like(grey, dtype=bool)

    a_grey = np.ones(len(grey))
    lab = np.zeros(len(grey), dtype=np.int64)
    C = np.ones((1, 3))
    c = np.zeros(9)
    for _ in range(int(iterations)):
        c = _irls(B[fit] * a_grey[fit, None], grey[fit])
        s = B @ c
        s_floor = 0.02 * max(float(np.percentile(s, 99)), 1e-9)
        s = np.maximum(s, s_floor)
        ratio = np.maximum(I / s[:, None], 1e-4)
        rg = ratio.mean(axis=1)
        chroma = ratio[:, :2] / ratio.sum(axis=1, keepdims=True)
        conf = np.clip(grey / 0.1, 0.1, 1.0)[:, None]  # dark pixels: noisy chromaticity
        X = np.column_stack([np.log(rg), 5.0 * conf * chroma])
        lab, _ = _kmeans(X, k, seed=seed)
        kk = int(lab.max()) + 1
        C = np.array(
            [np.median(ratio[lab == j], axis=0) if np.any(lab == j) else np.ones(3) for j in range(kk)]
        )
        a_grey = C.mean(axis=1)[lab]
    # final light with the final albedo, then fix the scale (99th pct of shading = 1)
    c = _irls(B[fit] * a_grey[fit, None], grey[fit])
    s = B @ c
    scale = float(np.percentile(s, 99))
    if not np.isfinite(scale) or scale <= 0:
        raise InputError("could not fit a light: the image is black on the surface")
    c = c / scale
    s = s / scale
    C = C * scale
    order = np.argsort(C.mean(axis=1))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    lab = rank[lab]
    C = C[order]

    albedo = np.full((h, w, 3), np.nan, dtype=np.float32)
    albedo[surface] = C[lab]
    shading = np.full((h, w), np.nan, dtype=np.float32)
    shading[surface] = s
    labels = np.full((h, w), -1, dtype=np.int16)
    labels[surface] = lab
    n_out = np.full((h, w, 3), np.nan, dtype=np.float32)
    n_out[surface] = normals[surface]
    shape = np.zeros((h, w), dtype=np.float32)
    shape[surface] = 0.15 + 0.85 * np.maximum(0.0, normals[surface] @ CANONICAL_LIGHT_CAM)
    dark_img = grey <= dark_fraction * np.percentile(grey, 95)
    dark_shd = s <= dark_fraction * np.percentile(s, 95)
    pg = C.mean(axis=1)
    dark_paint = (pg <= dark_fraction * pg.max())[lab]
    fs = np.zeros((h, w), dtype=bool)
    fs[surface] = dark_img & ~dark_shd & dark_paint
    return DecamoResult(albedo, shading, shape, fs, n_out, labels, C.astype(np.float32), c, surface)


def lmse(estimate: NDArray, truth: NDArray, mask: NDArray, *, window: int = 20) -> float:
    """Local mean squared error of Grosse et al. [1]_ (scale-invariant per window).

    Windows of ``window`` pixels every ``window // 2`` pixels; in each, the estimate
    is scaled by the least-squares factor before the squared error is summed over
    the masked pixels. The total is divided by the same sum with a zero estimate, so
    0 is perfect and 1 is as bad as predicting zero. Multi-channel inputs are
    compared channel by channel and averaged.

    Parameters
    ----------
    estimate, truth : (H, W) or (H, W, C) float
    mask : (H, W) bool

    References
    ----------
    .. [1] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman, "Ground truth
       dataset and baseline evaluations for intrinsic image algorithms", ICCV 2009.
    """
    e = np.asarray(estimate, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if e.shape != t.shape or e.shape[:2] != m.shape:
        raise InputError(f"lmse: shapes differ: estimate {e.shape}, truth {t.shape}, mask {m.shape}")
    if e.ndim == 3:
        return float(np.mean([lmse(e[..., i], t[..., i], m, window=window) for i in range(e.shape[2])]))
    m = m & np.isfinite(e) & np.isfinite(t)
    h, w = m.shape
    step = max(1, window // 2)
    num = 0.0
    den = 0.0
    for i in range(0, max(1, h - window + 1), step):
        for j in range(0, max(1, w - window + 1), step):
            mm = m[i : i + window, j : j + window]
            if not mm.any():
                continue
            ee = e[i : i + window, j : j + window][mm]
            tt = t[i : i + window, j : j + window][mm]
            ssq = float(ee @ ee)
            alpha = float(ee @ tt) / ssq if ssq > 0 else 0.0
            num += float(np.sum((tt - alpha * ee) ** 2))
            den += float(tt @ tt)
    return num / den if den > 0 else 0.0


# -- files -----------------------------------------------------------------------------
def _camera_from_calib(calib: str | Path, view: str) -> CameraModel:
    from prism3d.capture.rig import StereoRig

    rig = StereoRig.load(calib)
    return rig.left if view == "left" else rig.right


def _write_outputs(res: DecamoResult, out_dir: Path, extra: dict[str, Any]) -> dict[str, Any]:
    import tifffile

    from prism3d.io.atomic import atomic_path, atomic_write_text
    from prism3d.io.images import write_image

    out_dir.mkdir(parents=True, exist_ok=True)
    alb = np.nan_to_num(res.albedo, nan=0.0)
    alb_u8 = (np.clip(alb / max(float(alb.max()), 1e-9), 0, 1) * 255 + 0.5).astype(np.uint8)
    paths = {
        "albedo": out_dir / "albedo.png",
        "shading": out_dir / "shading.tiff",
        "shape": out_dir / "shape.png",
        "false_shadow": out_dir / "false_shadow.png",
        "light": out_dir / "light.json",
    }
    write_image(paths["albedo"], alb_u8)
    with atomic_path(paths["shading"]) as tmp:
        tifffile.imwrite(str(tmp), res.shading.astype(np.float32))
    write_image(paths["shape"], (np.clip(res.shape, 0, 1) * 255 + 0.5).astype(np.uint8))
    write_image(paths["false_shadow"], res.false_shadow)
    info = {
        "schema_version": 1,
        "sh_coeffs": [float(v) for v in res.light_coeffs],
        "palette_linear": res.palette.astype(float).tolist(),
        "surface_pixels": int(res.mask.sum()),
        "false_shadow_pixels": int(res.false_shadow.sum()),
        **extra,
    }
    atomic_write_text(paths["light"], json.dumps(info, indent=2))
    return {**{k: str(v) for k, v in paths.items()}, **info}


def decamo_to_folder(
    image_path: str | Path,
    depth_spec: str | Path,
    out_dir: str | Path,
    *,
    calib: str | Path | None = None,
    focal_px: float | None = None,
    view: str = "left",
    **options: Any,
) -> dict[str, Any]:
    """``prism3d decamo IMAGE DEPTH -o OUT_DIR [--calib rig.yaml | --focal PX] [--view left|right]``.

    Writes ``albedo.png`` (paint, scaled to the brightest paint), ``shading.tiff``
    (float32), ``shape.png``, ``false_shadow.png`` and ``light.json`` (SH
    coefficients, palette) atomically into ``out_dir``.

    Parameters
    ----------
    image_path : path
        RGB image of one view; a full side-by-side sensor image is accepted with
        ``calib`` (the ``view`` half is cut out with the prism split).
    depth_spec : str or path
        Depth map of that view, mm: ``.tiff``, ``.npy``, ``.pfm`` or ``file.npz:key``.
    calib : path, optional
        Rig calibration YAML; the ``view`` camera gives the intrinsics (its lens
        distortion is handled exactly for the normals).
    focal_px : float, optional
        Focal length in pixels, principal point at the image centre (no distortion).
    view : {"left", "right"}
        Which camera of ``calib``.
    options
        Passed to :func:`decamouflage`.

    Intrinsics come from ``calib``, else ``focal_px``, else ``rig.yaml`` beside the
    depth file; with none of these an InputError says what to pass.

    Returns
    -------
    dict
        Output paths and the ``light.json`` content.
    """
    from prism3d.io.images import read_depth, read_image, split_npz_spec

    check_choice(view, "view", ("left", "right"))
    if calib is not None and focal_px is not None:
        raise InputError("give either --calib or --focal, not both")
    image = read_image(image_path)
    depth = read_depth(depth_spec)
    h, w = depth.shape
    source = ""
    cam: NDArray | CameraModel
    if calib is None and focal_px is None:
        beside = split_npz_spec(depth_spec)[0].parent / "rig.yaml"
        if beside.is_file():
            calib = beside
        else:
            raise InputError(
                f"{depth_spec}: no intrinsics: pass --calib rig.yaml (the rig calibration) or "
                f"--focal PX (focal length in pixels, principal point at the image centre); "
                f"no rig.yaml was found beside the depth file"
            )
    if calib is not None:
        from prism3d.capture.rig import StereoRig

        rig = StereoRig.load(calib)
        cam = rig.left if view == "left" else rig.right
        sw, sh = rig.split.sensor_size
        if image.shape[:2] == (sh, sw) and (sw, sh) != (w, h):
            left, right = rig.split.split(image)
            image = left if view == "left" else right
        source = f"calib {calib} ({view})"
    else:
        f = check_positive(focal_px, "focal_px")
        cam = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        source = f"focal {f} px"
    if image.shape[:2] != depth.shape:
        raise InputError(
            f"{image_path} is {image.shape[1]}x{image.shape[0]} but the depth map {depth_spec} is "
            f"{w}x{h}: they must be the same view"
        )
    res = decamouflage(image, depth, cam, **options)
    return _write_outputs(res, Path(out_dir), {"intrinsics": source, "image": str(image_path),
                                                "depth": str(depth_spec)})


def decamo_from_shot(
    shot_path: str | Path,
    calib_path: str | Path,
    out_dir: str | Path,
    **options: Any,
) -> dict[str, Any]:
    """Decamouflage straight from a side-by-side shot and its calibration.

    Reconstructs depth with :func:`prism3d.reconstruct.pipeline.reconstruct_shot`
    (default options) and decamouflages the rectified left view (pinhole camera of
    the rectification). Outputs as :func:`decamo_to_folder`; also writes
    ``depth_rect.tiff`` (the reconstructed depth, mm).

    Parameters
    ----------
    shot_path : path
        Side-by-side sensor image.
    calib_path : path
        Rig calibration YAML.
    out_dir : path
        Output folder.
    options
        Passed to :func:`decamouflage`.
    """
    from prism3d.capture.rig import StereoRig
    from prism3d.reconstruct.pipeline import reconstruct_shot

    from prism3d.io.images import read_image, write_depth

    shot = read_image(shot_path)
    rig = StereoRig.load(calib_path)
    rec = reconstruct_shot(shot, rig)
    depth = np.asarray(rec.depth_mm, dtype=np.float32)
    left = np.asarray(rec.left_rect)
    if left.ndim == 2:
        left = np.repeat(left[:, :, None], 3, axis=2)
    res = decamouflage(left, depth, rec.rect.camera, **options)
    out = Path(out_dir)
    out_info = _write_outputs(res, out, {"intrinsics": f"rectified left of {calib_path}",
                                         "image": str(shot_path), "depth": "reconstructed"})
    write_depth(out / "depth_rect.tiff", depth)
    out_info["depth"] = str(out / "depth_rect.tiff")
    return out_info
