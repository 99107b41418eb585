"""Undistort + rectify the two views of a calibrated (prism) stereo rig.

Remap tables from :func:`prism3d.capture.rig.compute_rectification` (equal principal
points: ``d = x_left - x_right = f B / z``), applied to a pair or a side-by-side shot.

References: Fusiello, Trucco, Verri, "A compact algorithm for rectification of stereo
pairs", Machine Vision and Applications 12, 2000.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.calib_formats import load_stereo_calibration
from prism3d.capture.rig import CameraModel, Rectification, StereoRig, compute_rectification
from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.io.atomic import staged_folder
from prism3d.io.images import read_image, write_image
from prism3d.io.opencv_yaml import write_filestorage

__all__ = [
    "RectifyMaps",
    "rectify_maps",
    "rectify_pair",
    "rectify_shot",
    "rectify_to_folder",
    "save_rectification",
]


@dataclass(frozen=True, eq=False)
class RectifyMaps:
    """Remap tables of both views (``cv2.remap`` inputs) implementing ``rect``.

    ``left_x, left_y, right_x, right_y``: (H, W) float32 source pixel of each rectified
    pixel; with ``fixed_point`` (OpenCV, 1/32 px) the x arrays are ``CV_16SC2`` (H, W, 2)
    int16 maps and the y arrays (H, W) uint16 interpolation tables.
    """

    rect: Rectification
    left_x: NDArray
    left_y: NDArray
    right_x: NDArray
    right_y: NDArray
    fixed_point: bool = False

    def remap(
        self, left: NDArray, right: NDArray, *, interpolation: int | str | None = None
    ) -> tuple[NDArray, NDArray]:
        """Rectify a pair of ``(h, w[, C])`` views into ``rect.size`` images (unmapped = 0).

        ``interpolation``: an OpenCV flag (default linear; the input's dtype) or "bspline":
        exact cubic B-spline, float32 clipped to the input's range, for sub-pixel work
        (OpenCV's kernels shift edges differently in each view: docs/matching.md).
        """
        import cv2

        if isinstance(interpolation, str):
            if interpolation != "bspline":
                raise InputError(f"interpolation: expected an OpenCV flag or 'bspline', got {interpolation!r}")
            if self.fixed_point:
                raise InputError("interpolation='bspline' needs float maps (rectify_maps(fixed_point=False))")
            return self._remap_bspline(left, "left", self.left_x, self.left_y), self._remap_bspline(
                right, "right", self.right_x, self.right_y
            )
        interp = cv2.INTER_LINEAR if interpolation is None else int(interpolation)
        out = []
        for name, img, mx, my in (
            ("left", left, self.left_x, self.left_y),
            ("right", right, self.right_x, self.right_y),
        ):
            a = check_array(img, name, ndim=(2, 3))
            if a.dtype == np.float64:
                a = a.astype(np.float32)
            out.append(
                cv2.remap(
                    np.ascontiguousarray(a),
                    mx,
                    my,
                    interp,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0,
                )
            )
        return out[0], out[1]

    @staticmethod
    def _remap_bspline(img: NDArray, name: str, mx: NDArray, my: NDArray) -> NDArray[np.float32]:
        from ._match_kernels import bspline_rows
        from ._rectify_kernels import bspline_remap

        a = check_array(img, name, ndim=(2, 3), dtype_kind="uif", min_size=1)
        chans = a[..., None] if a.ndim == 2 else a
        h, w, nc = chans.shape
        coef = np.empty((nc, h, w), np.float32)
        tmp = np.empty((w, h), np.float32)
        for c in range(nc):
            ch = np.ascontiguousarray(chans[..., c], dtype=np.float32)
            bspline_rows(ch, coef[c])
            bspline_rows(np.ascontiguousarray(coef[c].T), tmp)  # then along the columns
            coef[c] = tmp.T
        out = np.empty(mx.shape + (nc,), np.float32)
        bspline_remap(coef, np.ascontiguousarray(mx, dtype=np.float32), np.ascontiguousarray(my, dtype=np.float32),
                      float(np.min(chans)), float(np.max(chans)), out)
        return out[..., 0] if a.ndim == 2 else out


def _map_for(
    cam: CameraModel, R: NDArray, P: NDArray, size: tuple[int, int]
) -> tuple[NDArray, NDArray]:
    """Float32 map of one view. OpenCV's initUndistortRectifyMap ignores skew, so a
    camera with skew is mapped with our own exact projection."""
    import cv2

    w, h = size
    if cam.skew == 0.0:
        mx, my = cv2.initUndistortRectifyMap(
            cam.K, cam.dist, np.asarray(R), np.asarray(P)[:, :3], (w, h), cv2.CV_32FC1
        )
        return mx, my
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    Pi = np.linalg.inv(np.asarray(P)[:, :3])
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1) @ Pi.T
    pts = rays @ np.asarray(R)  # rectified frame -> camera frame (R^T applied row-wise)
    uv = cam.project(pts)
    uv[~np.isfinite(uv)] = -1e6
    return (uv[:, 0].reshape(h, w).astype(np.float32), uv[:, 1].reshape(h, w).astype(np.float32))


def rectify_maps(rig: StereoRig, rect: Rectification, *, fixed_point: bool = False) -> RectifyMaps:
    """Remap tables taking each view of ``rig`` to its rectified image under ``rect``
    (``fixed_point``: OpenCV ``CV_16SC2`` maps).
    """
    import cv2

    if not isinstance(rig, StereoRig):
        raise InputError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    if not isinstance(rect, Rectification):
        raise InputError(f"rect: expected a Rectification, got {type(rect).__name__}")
    lx, ly = _map_for(rig.left, rect.R1, rect.P1, rect.size)
    rx, ry = _map_for(rig.right, rect.R2, rect.P2, rect.size)
    if fixed_point:
        lx, ly = cv2.convertMaps(lx, ly, cv2.CV_16SC2)
        rx, ry = cv2.convertMaps(rx, ry, cv2.CV_16SC2)
    return RectifyMaps(rect, lx, ly, rx, ry, bool(fixed_point))


def rectify_pair(
    left: NDArray,
    right: NDArray,
    rig: StereoRig,
    *,
    alpha: float = 1.0,
    size: tuple[int, int] | None = None,
) -> tuple[NDArray, NDArray, Rectification]:
    """Undistort and rectify two views ``(h, w[, C])`` uint8/float32 (``rig.split.split``
    output, each ``rig.left.size``); ``alpha``, ``size`` as in
    :func:`~prism3d.capture.rig.compute_rectification`.

    Returns ``(left_rect, right_rect, rect)``: (H, W[, C]) images of the input dtype whose
    corresponding points share a row, and the Rectification.
    """
    la = check_array(left, "left", ndim=(2, 3))
    ra = check_array(right, "right", ndim=(2, 3))
    for name, a, cam in (("left", la, rig.left), ("right", ra, rig.right)):
        if (a.shape[1], a.shape[0]) != cam.size:
            raise InputError(
                f"{name}: expected a {cam.size[0]}x{cam.size[1]} view for this rig, got {a.shape[1]}x{a.shape[0]}"
            )
    rect = compute_rectification(rig, alpha=alpha, size=size)
    maps = rectify_maps(rig, rect)
    lr, rr = maps.remap(la, ra)
    return lr, rr, rect


def rectify_shot(
    shot_image: NDArray, rig: StereoRig, *, alpha: float = 1.0, size: tuple[int, int] | None = None
) -> tuple[NDArray, NDArray, Rectification]:
    """Split a side-by-side sensor image with ``rig.split`` and rectify both views
    (returns as :func:`rectify_pair`).
    """
    left, right = rig.split.split(shot_image)
    return rectify_pair(left, right, rig, alpha=alpha, size=size)


def save_rectification(path: str | Path, rect: Rectification, rig: StereoRig | None = None) -> None:
    """Write ``R1 R2 P1 P2 Q`` and ``image_size`` as FileStorage YAML (atomic), with
    the calibration (``K1 D1 K2 D2 R T``) when ``rig`` is given.
    """
    values: dict = {
        "schema_version": 1,
        **rect.to_filestorage(),
        "focal_px": rect.focal_px,
        "baseline_mm": rect.baseline_mm,
    }
    if rig is not None:
        values.update(
            {
                "K1": rig.left.K,
                "D1": rig.left.dist,
                "K2": rig.right.K,
                "D2": rig.right.dist,
                "R": rig.R,
                "T": rig.T,
                "image_size": np.array(rig.left.size, dtype=np.int32),
            }
        )
    write_filestorage(path, values)


def _write_png(path: Path, image: NDArray) -> None:
    """A rectified view (uint8, or float in [0, 1]) as PNG, atomically."""
    img = image
    if img.dtype.kind == "f":
        img = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    write_image(path, img)


def rectify_to_folder(
    shot_path: str | Path | None,
    calib_paths: str | Path | list[str | Path],
    out_dir: str | Path,
    *,
    left_path: str | Path | None = None,
    right_path: str | Path | None = None,
    alpha: float = 1.0,
    image_size: tuple[int, int] | None = None,
) -> dict[str, Path]:
    """``prism3d rectify``: rectify a side-by-side shot (or ``left_path``/``right_path``)
    with a calibration file, write ``left.png``, ``right.png``, ``rectification.yaml``
    into ``out_dir`` together (temporary names, then moved); returns their paths by key.

    Raises InputError for missing or unreadable files or views that do not fit the
    calibration.
    """
    two_files = left_path is not None or right_path is not None
    if two_files == (shot_path is not None) or (two_files and (left_path is None or right_path is None)):
        raise InputError("give either a side-by-side SHOT or both --left and --right view files")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: output folder exists and is not a folder")
    rig = load_stereo_calibration(calib_paths,
                                  image_size=image_size).rig
    # the readers name their file; what follows is about the views against the calibration
    views = (read_image(left_path), read_image(right_path)) if two_files else (read_image(shot_path),)  # type: ignore[arg-type]
    try:
        if two_files:
            la, ra = views
            if la.shape != ra.shape:
                raise InputError(f"the views are {la.shape[1]}x{la.shape[0]} and {ra.shape[1]}x{ra.shape[0]}; "
                                 "they must have the same size")
            left, right, rect = rectify_pair(la, ra, rig, alpha=alpha)
        else:
            left, right, rect = rectify_shot(views[0], rig, alpha=alpha)
    except InputError as exc:
        src = f"{left_path}, {right_path}" if two_files else str(shot_path)
        calib = ", ".join(map(str, calib_paths)) if isinstance(calib_paths, (list, tuple)) else str(calib_paths)
        raise InputError(f"{src}: {exc} (calibration {calib})") from exc
    paths = {
        "left": out / "left.png",
        "right": out / "right.png",
        "rectification": out / "rectification.yaml",
    }
    with staged_folder(out) as stage:  # all three appear together, or none (and no folder)
        _write_png(stage / "left.png", left)
        _write_png(stage / "right.png", right)
        save_rectification(stage / "rectification.yaml", rect, rig)
    return paths
