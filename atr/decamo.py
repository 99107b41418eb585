"""Camouflage removal with depth: paint (albedo), shading, the bare shape relit, and the
"false shadows" paint paints on. Model ``I = a S(n)``: piecewise-constant paint ``a``
(k-means) times 2nd-order SH irradiance [1]_ of the depth normals [2]_ [3]_ (Huber
IRLS), alternated; details and history in docs/decamo.md.

References
----------
.. [1] Ramamoorthi, Hanrahan, "An efficient representation for irradiance environment maps", SIGGRAPH 2001.
.. [2] Chen, Koltun, "A simple model for intrinsic image decomposition with depth cues", ICCV 2013.
.. [3] Barron, Malik, "Shape, illumination, and reflectance from shading", TPAMI 37(8), 2015.
.. [4] Grosse et al., "Ground truth dataset and baseline evaluations for intrinsic image algorithms", ICCV 2009.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.atr.geometry import as_camera, depth_to_points, normals_from_depth
from prism3d.capture.rig import CameraModel, StereoRig
from prism3d.checks import (
    check_array,
    check_choice,
    check_in_range,
    check_positive,
    check_same_shape,
)
from prism3d.errors import InputError
from prism3d.grids import nearest_valid
from prism3d.io.atomic import staged_folder
from prism3d.io.images import read_depth, read_image, split_npz_spec, write_depth, write_image
from prism3d.reconstruct.stereo.pipeline import reconstruct_shot

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

MAX_PAINTS = 12  # camouflage schemes use 2-5 colours; more clusters only split noise
MIN_SURFACE_PX = 20  # fewer pixels cannot pin down 9 SH coefficients robustly
SATURATED = 0.98  # clipped pixels do not follow I = a S: left out of the light fit
BLACK = 2.0 / 255.0  # below 2 grey levels the image carries no shading
SHADING_FLOOR = 0.02  # of the 99th pct: I / S stays finite where the fit predicts no light
RATIO_FLOOR = 1e-4  # keeps log(I / S) finite on black pixels
CHROMA_FULL_GREY = 0.1  # grey level above which a pixel's chromaticity is fully trusted
CHROMA_MIN_CONF = 0.1  # weight of chromaticity on the darkest pixels (noisy there)
CHROMA_WEIGHT = 5.0  # chromaticity vs log intensity in k-means: paints differ in hue
SHADING_PCT = 99  # shading is normalised so this percentile over the surface is 1
DARK_REF_PCT = 95  # "dark" is a fraction of this percentile (robust to highlights)
SHAPE_AMBIENT = 0.15  # shape image = 0.15 + 0.85 max(0, n.l): unlit faces stay visible
SHAPE_DIFFUSE = 0.85  # the lit part of the shape image (ambient + diffuse = 1)
HUBER_K = 1.345  # Huber's constant: 95 % efficiency on Gaussian residuals
MAD_TO_SIGMA = 1.4826  # median absolute deviation -> Gaussian sigma
IRLS_ITERS = 15  # Huber IRLS converges in < 10 steps on our shots
KMEANS_ITERS = 30  # Lloyd steps (stops earlier when the centres settle)
KMEANS_MAX_FIT = 20000  # k-means is fitted on a fixed-seed subsample of this size


@dataclass(frozen=True)
class DecamoResult:
    """Result of :func:`decamouflage`; NaN (labels -1, shape 0) off the surface."""

    albedo: NDArray[np.float32]
    """(H, W, 3) piecewise-constant paint, linear, common scale with ``shading``."""
    shading: NDArray[np.float32]
    """(H, W) fitted irradiance ``S(n)``, 99th percentile over the surface = 1."""
    shape: NDArray[np.float32]
    """(H, W) surface relit with uniform albedo under :data:`CANONICAL_LIGHT_CAM`, [0, 1]."""
    false_shadow: NDArray[np.bool_]
    """(H, W) dark in the image, not dark in the shading, on a dark paint."""
    normals: NDArray[np.float32]
    """(H, W, 3) camera-frame unit normals used."""
    labels: NDArray[np.int16]
    """(H, W) paint cluster of each pixel, clusters ordered dark to bright."""
    palette: NDArray[np.float32]
    """(k, 3) paint colours, dark to bright."""
    light_coeffs: NDArray[np.float64]
    """(9,) SH coefficients ``c`` (order of :func:`sh_basis`), scale of ``shading``."""
    mask: NDArray[np.bool_]
    """(H, W) surface pixels used."""


def sh_basis(normals: NDArray) -> NDArray[np.float64]:
    """Real spherical harmonics up to order 2 at unit normals ``(N, 3)`` -> ``(N, 9)``.

    Order ``Y00, Y1-1 (y), Y10 (z), Y11 (x), Y2-2 (xy), Y2-1 (yz), Y20, Y21 (xz),
    Y22``, normalised as in Ramamoorthi & Hanrahan 2001, eq. 3.
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


def _irls(A: NDArray, b: NDArray, *, iters: int = IRLS_ITERS, huber_k: float = HUBER_K) -> NDArray[np.float64]:
    """Huber-weighted IRLS for ``A x ≈ b``, residual scale from the MAD at each step."""
    w = np.ones(len(b))
    x = np.zeros(A.shape[1])
    reg = 1e-9 * np.eye(A.shape[1])
    for _ in range(iters):
        Aw = A * w[:, None]
        x = np.linalg.solve(A.T @ Aw + reg * max(1.0, float(np.trace(A.T @ Aw))), Aw.T @ b)
        r = b - A @ x
        sigma = MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))) + 1e-9
        a = np.abs(r) / (huber_k * sigma)
        w = np.where(a <= 1.0, 1.0, 1.0 / np.maximum(a, 1e-12))
    return x


def _kmeans_pp_seeds(Xf: NDArray, k: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """k-means++ initial centres."""
    centres = [Xf[rng.integers(len(Xf))]]
    d2 = np.sum((Xf - centres[0]) ** 2, axis=1)
    for _ in range(1, k):
        tot = d2.sum()
        idx = int(rng.integers(len(Xf))) if tot <= 0 else int(rng.choice(len(Xf), p=d2 / tot))
        centres.append(Xf[idx])
        d2 = np.minimum(d2, np.sum((Xf - Xf[idx]) ** 2, axis=1))
    return np.array(centres, dtype=np.float64)


def _kmeans(X: NDArray, k: int, *, seed: int = 0, iters: int = KMEANS_ITERS,
            max_fit: int = KMEANS_MAX_FIT) -> tuple[NDArray, NDArray]:
    """Deterministic k-means on ``(N, D)`` fitted on <= ``max_fit`` points; (labels, centres)."""
    rng = np.random.default_rng(seed)
    Xf = X if len(X) <= max_fit else X[rng.choice(len(X), max_fit, replace=False)]
    k = min(k, len(Xf))
    C = _kmeans_pp_seeds(Xf, k, rng)
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
    ok = np.all(np.isfinite(normals), axis=-1)
    need = region & ~ok
    if not need.any() or not ok.any():
        return normals
    _, (ii, jj) = nearest_valid(~ok)
    out = normals.copy()
    out[need] = normals[ii[need], jj[need]]
    return out


def _check_inputs(image: NDArray, depth_mm: NDArray, n_paints: int, iterations: int, falloff: str,
                  gamma: float, dark_fraction: float) -> tuple[NDArray, NDArray, int]:
    """Validated ``(image float64 in [0, 1], depth float64, number of paints)``."""
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
    if k != n_paints or not 1 <= k <= MAX_PAINTS:
        raise InputError(f"n_paints: expected an integer in [1, {MAX_PAINTS}], got {n_paints!r}")
    if int(iterations) != iterations or iterations < 1:
        raise InputError(f"iterations: expected a positive integer, got {iterations!r}")
    check_choice(falloff, "falloff", ("none", "camera"))
    check_positive(gamma, "gamma")
    check_in_range(dark_fraction, "dark_fraction", 0.0, 1.0)
    return img, d, k


def _surface_normals(d: NDArray, cam: CameraModel, mask: NDArray | None) -> tuple[NDArray, NDArray]:
    """``(surface (H, W) bool, normals (H, W, 3) float64)``: finite depth inside ``mask``
    whose normal is known or filled from the nearest neighbour."""
    surface = np.isfinite(d) & (d > 0)
    if mask is not None:
        m = check_array(mask, "mask", ndim=2)
        check_same_shape(m, d, ("mask", "depth_mm"))
        surface &= m.astype(bool)
    normals = _fill_nearest(normals_from_depth(d, cam).astype(np.float64), surface)
    surface &= np.all(np.isfinite(normals), axis=-1)
    n_valid = int(surface.sum())
    if n_valid < MIN_SURFACE_PX:
        raise InputError(f"only {n_valid} surface pixels with valid depth; need at least {MIN_SURFACE_PX}")
    return surface, normals


def _light_basis(normals: NDArray, d: NDArray, cam: CameraModel, surface: NDArray, falloff: str) -> NDArray:
    """SH basis ``(M, 9)`` of the surface pixels, times the flash's 1/r^2 (relative to the
    median range) when ``falloff == "camera"``."""
    B = sh_basis(normals[surface])
    if falloff == "camera":
        r = np.linalg.norm(depth_to_points(d, cam)[surface], axis=1)
        B = B * (np.median(r) / r)[:, None] ** 2
    return B


def _cluster_paints(I: NDArray, s: NDArray, grey: NDArray, k: int, seed: int) -> tuple[NDArray, NDArray]:
    """k-means of ``I / s`` in (log intensity, chromaticity): (labels, per-paint median ratio)."""
    ratio = np.maximum(I / s[:, None], RATIO_FLOOR)
    rg = ratio.mean(axis=1)
    chroma = ratio[:, :2] / ratio.sum(axis=1, keepdims=True)
    conf = np.clip(grey / CHROMA_FULL_GREY, CHROMA_MIN_CONF, 1.0)[:, None]
    X = np.column_stack([np.log(rg), CHROMA_WEIGHT * conf * chroma])
    lab, _ = _kmeans(X, k, seed=seed)
    kk = int(lab.max()) + 1
    C = np.array([np.median(ratio[lab == j], axis=0) if np.any(lab == j) else np.ones(3) for j in range(kk)])
    return lab, C


def _alternate(I: NDArray, grey: NDArray, B: NDArray, fit: NDArray, k: int, iterations: int,
               seed: int) -> tuple[NDArray, NDArray, NDArray]:
    """Alternate the light fit and the paint clustering: (labels, palette, grey albedo)."""
    a_grey = np.ones(len(grey))
    lab = np.zeros(len(grey), dtype=np.int64)
    C = np.ones((1, 3))
    for _ in range(int(iterations)):
        c = _irls(B[fit] * a_grey[fit, None], grey[fit])
        s = B @ c
        s = np.maximum(s, SHADING_FLOOR * max(float(np.percentile(s, SHADING_PCT)), 1e-9))
        lab, C = _cluster_paints(I, s, grey, k, seed)
        a_grey = C.mean(axis=1)[lab]
    return lab, C, a_grey


def _final_light(B: NDArray, grey: NDArray, fit: NDArray, a_grey: NDArray, lab: NDArray,
                 C: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Light of the final albedo, scaled so shading's 99th pct is 1, paints sorted dark to
    bright: ``(c, s, labels, palette)``."""
    c = _irls(B[fit] * a_grey[fit, None], grey[fit])
    s = B @ c
    scale = float(np.percentile(s, SHADING_PCT))
    if not np.isfinite(scale) or scale <= 0:
        raise InputError("could not fit a light: the image is black on the surface")
    c = c / scale
    s = s / scale
    C = C * scale
    order = np.argsort(C.mean(axis=1))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return c, s, rank[lab], C[order]


def _false_shadow(grey: NDArray, s: NDArray, lab: NDArray, C: NDArray, dark_fraction: float) -> NDArray:
    """Per surface pixel: dark image, not dark shading, dark paint."""
    dark_img = grey <= dark_fraction * np.percentile(grey, DARK_REF_PCT)
    dark_shd = s <= dark_fraction * np.percentile(s, DARK_REF_PCT)
    pg = C.mean(axis=1)
    dark_paint = (pg <= dark_fraction * pg.max())[lab]
    return dark_img & ~dark_shd & dark_paint


def _on_image(surface: NDArray, values: NDArray, fill: float, dtype: type, channels: int = 0) -> NDArray:
    """Scatter per-surface-pixel ``values`` into an (H, W[, channels]) image filled with ``fill``."""
    out = np.full(surface.shape + ((channels,) if channels else ()), fill, dtype=dtype)
    out[surface] = values
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

    ``image`` (H, W, 3) uint8 or float in [0, 1]; ``depth_mm`` (H, W) float, NaN = no
    surface; ``K`` (3, 3) or CameraModel (its distortion is inverted for the normals);
    ``mask`` (H, W) bool restricts the surface. ``n_paints`` flat paints (1-12);
    ``iterations`` light-fit / clustering alternations; ``falloff`` "camera" (flash at
    the camera, 1/r^2) or "none"; the image is linearised as ``I ** gamma``;
    ``dark_fraction`` sets ``false_shadow`` (docs/decamo.md); ``seed`` of the k-means.
    Raises InputError on mismatched sizes, no valid depth, < 20 surface pixels, bad options.
    """
    img, d, k = _check_inputs(image, depth_mm, n_paints, iterations, falloff, gamma, dark_fraction)
    h, w = d.shape
    cam = as_camera(K, (w, h))
    if gamma != 1.0:
        img = np.clip(img, 0.0, 1.0) ** float(gamma)
    surface, normals = _surface_normals(d, cam, mask)
    I = img[surface]  # (M, 3)
    grey = I.mean(axis=1)
    B = _light_basis(normals, d, cam, surface, falloff)
    fit = (I.max(axis=1) < SATURATED) & (grey > BLACK)
    if fit.sum() < MIN_SURFACE_PX:
        fit = np.ones_like(grey, dtype=bool)
    lab, C, a_grey = _alternate(I, grey, B, fit, k, iterations, seed)
    c, s, lab, C = _final_light(B, grey, fit, a_grey, lab, C)
    shape = SHAPE_AMBIENT + SHAPE_DIFFUSE * np.maximum(0.0, normals[surface] @ CANONICAL_LIGHT_CAM)
    return DecamoResult(
        albedo=_on_image(surface, C[lab], np.nan, np.float32, 3),
        shading=_on_image(surface, s, np.nan, np.float32),
        shape=_on_image(surface, shape, 0.0, np.float32),
        false_shadow=_on_image(surface, _false_shadow(grey, s, lab, C, dark_fraction), False, bool),
        normals=_on_image(surface, normals[surface], np.nan, np.float32, 3),
        labels=_on_image(surface, lab, -1, np.int16),
        palette=C.astype(np.float32),
        light_coeffs=c,
        mask=surface,
    )


def lmse(estimate: NDArray, truth: NDArray, mask: NDArray, *, window: int = 20) -> float:
    """Local mean squared error of Grosse et al. 2009 [4]_: 0 perfect, 1 as bad as zero.

    Windows of ``window`` px every ``window // 2`` px, the estimate scaled per window by
    its least-squares factor; ``(H, W, C)`` inputs are averaged over channels.
    ``estimate, truth`` (H, W) or (H, W, C) float; ``mask`` (H, W) bool.
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
def _write_outputs(res: DecamoResult, out_dir: Path, extra: dict[str, Any]) -> dict[str, Any]:
    import tifffile

    alb = np.nan_to_num(res.albedo, nan=0.0)
    alb_u8 = (np.clip(alb / max(float(alb.max()), 1e-9), 0, 1) * 255 + 0.5).astype(np.uint8)
    names = {"albedo": "albedo.png", "shading": "shading.tiff", "shape": "shape.png",
             "false_shadow": "false_shadow.png", "light": "light.json"}
    info = {
        "schema_version": 1,
        "sh_coeffs": [float(v) for v in res.light_coeffs],
        "palette_linear": res.palette.astype(float).tolist(),
        "surface_pixels": int(res.mask.sum()),
        "false_shadow_pixels": int(res.false_shadow.sum()),
        **extra,
    }
    with staged_folder(out_dir) as stage:  # all five files, or none
        write_image(stage / names["albedo"], alb_u8)
        tifffile.imwrite(str(stage / names["shading"]), res.shading.astype(np.float32))
        write_image(stage / names["shape"], (np.clip(res.shape, 0, 1) * 255 + 0.5).astype(np.uint8))
        write_image(stage / names["false_shadow"], res.false_shadow)
        (stage / names["light"]).write_text(json.dumps(info, indent=2))
    return {**{k: str(out_dir / v) for k, v in names.items()}, **info}


def _view_camera(image: NDArray, depth_spec: str | Path, depth_shape: tuple[int, int],
                 calib: str | Path | None, focal_px: float | None,
                 view: str) -> tuple[NDArray, NDArray | CameraModel, str]:
    """``(image of the view, intrinsics, description)`` from ``calib``, ``focal_px`` or a
    ``rig.yaml`` beside the depth file; a side-by-side sensor image is split."""
    h, w = depth_shape
    if calib is None and focal_px is None:
        beside = split_npz_spec(depth_spec)[0].parent / "rig.yaml"
        if not beside.is_file():
            raise InputError(
                f"{depth_spec}: no intrinsics: pass --calib rig.yaml (the rig calibration) or "
                f"--focal PX (focal length in pixels, principal point at the image centre); "
                f"no rig.yaml was found beside the depth file"
            )
        calib = beside
    if calib is None:
        f = check_positive(focal_px, "focal_px")
        cam = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        return image, cam, f"focal {f} px"

    rig = StereoRig.load(calib)
    sw, sh = rig.split.sensor_size
    if image.shape[:2] == (sh, sw) and (sw, sh) != (w, h):
        left, right = rig.split.split(image)
        image = left if view == "left" else right
    return image, (rig.left if view == "left" else rig.right), f"calib {calib} ({view})"


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

    Writes ``albedo.png``, ``shading.tiff``, ``shape.png``, ``false_shadow.png`` and
    ``light.json`` atomically; returns their paths and the ``light.json`` content.
    ``image_path``: one view, or the side-by-side sensor image with ``calib``;
    ``depth_spec``: that view's depth, mm (``.tiff .npy .pfm`` or ``file.npz:key``).
    Intrinsics: the ``view`` camera of ``calib``, else ``focal_px`` (principal point at
    the centre), else ``rig.yaml`` beside the depth. ``options`` go to :func:`decamouflage`.
    """
    check_choice(view, "view", ("left", "right"))
    if calib is not None and focal_px is not None:
        raise InputError("give either --calib or --focal, not both")
    image = read_image(image_path)
    depth = read_depth(depth_spec)
    h, w = depth.shape
    image, cam, source = _view_camera(image, depth_spec, (h, w), calib, focal_px, view)
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
    """Decamouflage the rectified left view of a side-by-side shot, depth reconstructed
    with default options; outputs as :func:`decamo_to_folder` plus ``depth_rect.tiff``
    (mm). ``options`` go to :func:`decamouflage`."""
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
