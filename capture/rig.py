"""The prism stereo rig: one sensor, two virtual cameras.

A prism/mirror adapter in front of one camera puts two views side by side on the
sensor. Each view behaves as a separate (virtual) pinhole camera with its own
intrinsics and lens distortion; the pair is an ordinary stereo rig.

Conventions (see DESIGN.md): OpenCV camera frame (x right, y down, z forward),
pixel (0, 0) is the centre of the top-left pixel, millimetres, transforms named
``T_<to>_<from>``. ``StereoRig.R`` / ``StereoRig.T`` follow ``cv2.stereoCalibrate``:
``x_right = R @ x_left + T``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array
from prism3d.errors import InputError
from prism3d.io.images import max_pixels, pixel_count
from prism3d.io.opencv_yaml import read_filestorage, write_filestorage

__all__ = [
    "CameraModel",
    "PrismSplit",
    "StereoRig",
    "Rectification",
    "paper_rig",
    "scaled_rig",
    "compute_rectification",
    "look_at",
    "SCHEMA_VERSION",
]

#: Version of the rig/calibration YAML layout written by :meth:`StereoRig.save`.
SCHEMA_VERSION = 1


#: Largest |coefficient| of (k1, k2, p1, p2, k3) accepted: real lenses, even wide-angle
#: ones, stay within tens; 1e30 in a file is a corrupt or mistyped calibration.
MAX_DISTORTION = 1e3
#: Largest |entry| of K, px: a 10 m lens on 0.1 um pixels; 1e300 is a corrupt file.
MAX_K_PX = 1e8
#: Largest distance between the cameras or from rig to camera, mm (100 km): beyond any
#: stereo pair, survey pairs included; 1e300 is a corrupt file.
MAX_TRANSLATION_MM = 1e8


def _frozen_array(a: NDArray, dtype: Any = np.float64) -> NDArray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _check_pixels(w: int, h: int) -> None:
    """A camera or sensor whose images would not fit the decode budget is refused where it
    is declared, before anything is rendered or read at that size."""
    if w * h > max_pixels():
        raise InputError(f"size: {w}x{h} is {pixel_count(w * h)}, more than the {pixel_count(max_pixels())} "
                         "limit (--max-pixels or PRISM3D_MAX_PIXELS raises it)")


@dataclass(frozen=True, eq=False)
class CameraModel:
    """A pinhole camera with skew and OpenCV lens distortion: ``K`` (3, 3)
    ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` px (eq. 2 of the paper), ``dist`` (5,)
    ``(k1, k2, p1, p2, k3)`` in OpenCV's model (shorter input zero-padded), ``size``
    ``(width, height)`` px."""

    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    size: tuple[int, int]

    def __post_init__(self) -> None:
        K = check_array(self.K, "K", shape=(3, 3), dtype_kind="fiu").astype(np.float64)
        if not np.all(np.isfinite(K)):
            raise InputError("K: expected finite values")
        if np.any(np.abs(K) > MAX_K_PX):
            raise InputError(f"K: entries above {MAX_K_PX:g} px describe no camera, got {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"K: focal lengths must be > 0, got fx={K[0, 0]}, fy={K[1, 1]}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise InputError("K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
        d = check_array(self.dist, "dist", dtype_kind="fiu").astype(np.float64).ravel()
        if d.size > 5:
            if np.any(d[5:] != 0):
                raise InputError(
                    f"dist: only (k1, k2, p1, p2, k3) are supported, got {d.size} coefficients"
                )
            d = d[:5]
        d = np.concatenate([d, np.zeros(5 - d.size)])
        if not np.all(np.isfinite(d)):
            raise InputError("dist: expected finite values")
        if np.any(np.abs(d) > MAX_DISTORTION):
            raise InputError(f"dist: coefficients of magnitude above {MAX_DISTORTION:g} describe no lens, got {d.tolist()}")
        try:
            w, h = (int(v) for v in self.size)
        except (TypeError, ValueError) as exc:
            raise InputError(f"size: expected (width, height), got {self.size!r}") from exc
        if w <= 0 or h <= 0:
            raise InputError(f"size: width and height must be > 0, got {(w, h)}")
        _check_pixels(w, h)
        object.__setattr__(self, "K", _frozen_array(K))
        object.__setattr__(self, "dist", _frozen_array(d))
        object.__setattr__(self, "size", (w, h))

    # -- convenience -------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def skew(self) -> float:
        return float(self.K[0, 1])

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        return (
            self.size == other.size
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.dist, other.dist)
        )

    def __hash__(self) -> int:
        return hash((self.size, self.K.tobytes(), self.dist.tobytes()))

    def with_size(self, size: tuple[int, int]) -> CameraModel:
        """The same camera with another image size (K unchanged)."""
        return CameraModel(self.K, self.dist, size)

    def scaled(self, factor: float) -> CameraModel:
        """The camera sampled ``factor`` times more densely (supersampling).

        With the pixel-centre convention, pixel ``u`` maps to ``(u + 0.5) * f - 0.5``.
        """
        K = self.K.copy()
        K[0, 0] *= factor
        K[0, 1] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        w, h = self.size
        return CameraModel(K, self.dist, (int(round(w * factor)), int(round(h * factor))))

    # -- geometry ----------------------------------------------------------------------
    def distort_normalized(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Apply the distortion model to normalised coordinates ``(N, 2)``."""
        k1, k2, p1, p2, k3 = self.dist
        x = xy[..., 0]
        y = xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort_normalized(
        self, xy_d: NDArray[np.float64], *, iterations: int = 30
    ) -> NDArray[np.float64]:
        """Invert :meth:`distort_normalized` by Newton iterations (to ~1e-14)."""
        if not self.has_distortion:
            return np.array(xy_d, dtype=np.float64, copy=True)
        k1, k2, p1, p2, k3 = self.dist
        xd = xy_d[..., 0]
        yd = xy_d[..., 1]
        x = xd.copy()
        y = yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            fx_ = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
            fy_ = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
            # Jacobian of the forward model
            j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            dx = (j22 * fx_ - j12 * fy_) / det
            dy = (-j21 * fx_ + j11 * fy_) / det
            x = x - dx
            y = y - dy
            if np.max(np.abs(dx), initial=0.0) < 1e-15 and np.max(np.abs(dy), initial=0.0) < 1e-15:
                break
        return np.stack([x, y], axis=-1)

    def project(self, points_cam: NDArray[np.float64]) -> NDArray[np.float64]:
        """Project camera-frame points ``(N, 3)`` mm to distorted pixels ``(N, 2)``.

        Points at or behind the camera (z <= 0) give NaN.
        """
        p = check_array(points_cam, "points_cam", shape=(None, 3)).astype(np.float64)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        xyd = self.distort_normalized(xy)
        u = self.K[0, 0] * xyd[:, 0] + self.K[0, 1] * xyd[:, 1] + self.K[0, 2]
        v = self.K[1, 1] * xyd[:, 1] + self.K[1, 2]
        return np.stack([u, v], axis=-1)

    def pixel_rays(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unit ray directions ``(N, 3)`` in the camera frame through distorted pixels."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        y_d = (uv[:, 1] - self.K[1, 2]) / self.K[1, 1]
        x_d = (uv[:, 0] - self.K[0, 2] - self.K[0, 1] * y_d) / self.K[0, 0]
        xy = self.undistort_normalized(np.stack([x_d, y_d], axis=-1))
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def pixel_grid_rays(self) -> NDArray[np.float64]:
        """Rays ``(H, W, 3)`` through every pixel centre of the image."""
        w, h = self.size
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        return self.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(h, w, 3)


@dataclass(frozen=True)
class PrismSplit:
    """Where the two views sit on the sensor: full ``sensor_size`` ``(width, height)``,
    each view's ``roi`` ``(x, y, w, h)`` px, and whether the adapter mirrors a view
    left-right (:meth:`split` un-flips it)."""

    sensor_size: tuple[int, int]
    roi_left: tuple[int, int, int, int]
    roi_right: tuple[int, int, int, int]
    flip_left: bool = False
    flip_right: bool = False

    def __post_init__(self) -> None:
        try:
            sw, sh = (int(v) for v in self.sensor_size)
            rl = tuple(int(v) for v in self.roi_left)
            rr = tuple(int(v) for v in self.roi_right)
        except (TypeError, ValueError) as exc:
            raise InputError(f"PrismSplit: sizes and ROIs must be integers ({exc})") from exc
        if sw <= 0 or sh <= 0:
            raise InputError(f"sensor_size: expected positive (width, height), got {(sw, sh)}")
        _check_pixels(sw, sh)
        for name, roi in (("roi_left", rl), ("roi_right", rr)):
            if len(roi) != 4:
                raise InputError(f"{name}: expected (x, y, w, h), got {roi}")
            x, y, w, h = roi
            if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > sw or y + h > sh:
                raise InputError(
                    f"{name}: {roi} lies outside the {sw}x{sh} sensor or is empty"
                )
        if rl[2:] != rr[2:]:
            raise InputError(f"roi_left and roi_right must have the same size, got {rl[2:]} and {rr[2:]}")
        object.__setattr__(self, "sensor_size", (sw, sh))
        object.__setattr__(self, "roi_left", rl)
        object.__setattr__(self, "roi_right", rr)
        object.__setattr__(self, "flip_left", bool(self.flip_left))
        object.__setattr__(self, "flip_right", bool(self.flip_right))

    @classmethod
    def side_by_side(
        cls, sensor_size: tuple[int, int], *, flip_left: bool = False, flip_right: bool = False
    ) -> PrismSplit:
        """The usual layout: left half and right half of the sensor."""
        sw, sh = (int(v) for v in sensor_size)
        if sw % 2:
            raise InputError(f"sensor width must be even for a half split, got {sw}")
        half = sw // 2
        return cls((sw, sh), (0, 0, half, sh), (half, 0, half, sh), flip_left, flip_right)

    @property
    def view_size(self) -> tuple[int, int]:
        """``(width, height)`` of each view."""
        return (self.roi_left[2], self.roi_left[3])

    def split(self, image: NDArray) -> tuple[NDArray, NDArray]:
        """Cut a sensor image ``(H, W[, C])`` into (left, right) views, un-flipped (copies)."""
        img = check_array(image, "image", ndim=(2, 3))
        sw, sh = self.sensor_size
        if img.shape[1] != sw or img.shape[0] != sh:
            raise InputError(
                f"image: expected a {sw}x{sh} sensor image for this prism split, "
                f"got {img.shape[1]}x{img.shape[0]}"
            )
        out = []
        for roi, flip in ((self.roi_left, self.flip_left), (self.roi_right, self.flip_right)):
            x, y, w, h = roi
            view = img[y : y + h, x : x + w]
            if flip:
                view = view[:, ::-1]
            out.append(np.ascontiguousarray(view))
        return out[0], out[1]

    def join(self, left: NDArray, right: NDArray, *, fill: int | float = 0) -> NDArray:
        """Compose a sensor image from two views (inverse of :meth:`split`)."""
        left = check_array(left, "left", ndim=(2, 3))
        right = check_array(right, "right", ndim=(2, 3))
        w, h = self.view_size
        for name, v in (("left", left), ("right", right)):
            if v.shape[:2] != (h, w):
                raise InputError(f"{name}: expected a {w}x{h} view, got {v.shape[1]}x{v.shape[0]}")
        if left.shape != right.shape or left.dtype != right.dtype:
            raise InputError("left and right views must have the same shape and dtype")
        sw, sh = self.sensor_size
        out = np.full((sh, sw) + left.shape[2:], fill, dtype=left.dtype)
        for roi, flip, v in ((self.roi_left, self.flip_left, left), (self.roi_right, self.flip_right, right)):
            x, y, ww, hh = roi
            out[y : y + hh, x : x + ww] = v[:, ::-1] if flip else v
        return out


def look_at(eye: NDArray, target: NDArray, up: NDArray = (0.0, -1.0, 0.0)) -> NDArray[np.float64]:
    """``T_world_cam`` of an OpenCV camera at ``eye`` looking at ``target``.

    ``up`` is the world direction that should appear up in the image (image y points
    down, so the camera's -y axis is aligned with it as far as possible).
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    z = target - eye  # the optical axis
    nz = np.linalg.norm(z)
    if nz == 0:
        raise InputError("look_at: eye and target coincide")
    z /= nz
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-12:
        raise InputError("look_at: viewing direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Two virtual cameras on one sensor: ``left``, ``right`` (view pixels, after split
    and un-flip), ``T_right_left`` (mm), the ``split``, and ``T_rig_left``, the left camera's
    pose in the rig frame (origin midway between the centres, z along the mean viewing
    direction; identity when unknown, e.g. after calibration)."""

    left: CameraModel
    right: CameraModel
    T_right_left: NDArray[np.float64]
    split: PrismSplit
    T_rig_left: NDArray[np.float64] = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        for name in ("T_right_left", "T_rig_left"):
            T = check_array(getattr(self, name), name, shape=(4, 4), dtype_kind="fiu").astype(np.float64)
            R = T[:3, :3]
            if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
                raise InputError(f"{name}: expected a finite rigid 4x4 transform")
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise InputError(f"{name}: rotation part is not a proper rotation (det {np.linalg.det(R):.3f})")
            if np.linalg.norm(T[:3, 3]) > MAX_TRANSLATION_MM:
                raise InputError(f"{name}: a translation of {np.linalg.norm(T[:3, 3]):.3g} mm is beyond any "
                                 f"rig (at most {MAX_TRANSLATION_MM:g} mm); check the units")
            object.__setattr__(self, name, _frozen_array(T))
        if self.left.size != self.split.view_size or self.right.size != self.split.view_size:
            raise InputError(
                f"camera sizes {self.left.size}, {self.right.size} do not match the "
                f"prism split's view size {self.split.view_size}"
            )
        if np.linalg.norm(self.T_right_left[:3, 3]) <= 0:
            raise InputError("T_right_left: baseline must be > 0")

    @property
    def R(self) -> NDArray[np.float64]:
        """Rotation of ``cv2.stereoCalibrate``: ``x_right = R @ x_left + T``."""
        return self.T_right_left[:3, :3].copy()

    @property
    def T(self) -> NDArray[np.float64]:
        """Translation ``(3,)`` mm of ``cv2.stereoCalibrate``."""
        return self.T_right_left[:3, 3].copy()

    @property
    def baseline_mm(self) -> float:
        """Distance between the two camera centres, mm."""
        return float(np.linalg.norm(self.T_right_left[:3, 3]))

    @property
    def T_left_right(self) -> NDArray[np.float64]:
        return np.linalg.inv(self.T_right_left)

    @property
    def T_rig_right(self) -> NDArray[np.float64]:
        return self.T_rig_left @ self.T_left_right

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, StereoRig):
            return NotImplemented
        return (
            self.left == other.left
            and self.right == other.right
            and self.split == other.split
            and np.array_equal(self.T_right_left, other.T_right_left)
            and np.array_equal(self.T_rig_left, other.T_rig_left)
        )

    __hash__ = None  # type: ignore[assignment]

    # -- file I/O ----------------------------------------------------------------------
    def to_filestorage(self) -> dict[str, Any]:
        """The FileStorage entries of this rig (OpenCV stereoCalibrate names), and the
        default rectification in ``cv2.stereoRectify``'s names (``R1 R2 P1 P2 Q`` and
        ``rectified_size``): ``cv2.initUndistortRectifyMap(K1, D1, R1, P1, rectified_size,
        ...)`` alone gives the maps prism3d rectifies with. Written for other tools; a rig
        is read from ``K1 D1 K2 D2 R T`` and the split only."""
        s = self.split
        return {
            "schema_version": SCHEMA_VERSION,
            "image_size": np.array(self.split.view_size, dtype=np.int32),
            "K1": self.left.K,
            "D1": self.left.dist,
            "K2": self.right.K,
            "D2": self.right.dist,
            "R": self.R,
            "T": self.T,
            "sensor_size": np.array(s.sensor_size, dtype=np.int32),
            "roi_left": np.array(s.roi_left, dtype=np.int32),
            "roi_right": np.array(s.roi_right, dtype=np.int32),
            "flip_left": int(s.flip_left),
            "flip_right": int(s.flip_right),
            "T_rig_left": self.T_rig_left,
            **compute_rectification(self).to_filestorage(),
        }

    @classmethod
    def from_filestorage(cls, values: dict[str, Any], *, source: str = "calibration") -> StereoRig:
        """Build a rig from FileStorage entries (see :meth:`to_filestorage`).

        ``K1 D1 K2 D2 R T`` are required. Without the split entries the views are
        taken to be two separate images of ``image_size`` (an ordinary stereo rig)
        laid side by side.
        """
        version = _int_entry(values, "schema_version", SCHEMA_VERSION, source)
        if version > SCHEMA_VERSION:
            raise InputError(
                f"{source}: schema_version {version} is newer than this prism3d understands "
                f"({SCHEMA_VERSION}); upgrade prism3d"
            )
        missing = [k for k in ("K1", "D1", "K2", "D2", "R", "T") if k not in values]
        if missing:
            raise InputError(f"{source}: missing {', '.join(missing)}")

        def vec(name: str, n: int) -> tuple[int, ...]:
            a = np.asarray(values[name]).ravel()
            if a.size != n:
                raise InputError(f"{source}: {name} must have {n} values, got {a.size}")
            return tuple(int(round(float(v))) for v in a)

        try:
            T = np.eye(4)
            T[:3, :3] = np.asarray(values["R"], dtype=np.float64).reshape(3, 3)
            T[:3, 3] = np.asarray(values["T"], dtype=np.float64).ravel()[:3]
        except ValueError as exc:
            raise InputError(f"{source}: R must be 3x3 and T 3x1 ({exc})") from exc
        if "image_size" in values:
            view = vec("image_size", 2)
        elif "roi_left" in values:
            view = vec("roi_left", 4)[2:]
        else:
            raise InputError(f"{source}: missing image_size")
        if "roi_left" in values and "roi_right" in values and "sensor_size" in values:
            split = PrismSplit(
                vec("sensor_size", 2),
                vec("roi_left", 4),  # type: ignore[arg-type]
                vec("roi_right", 4),  # type: ignore[arg-type]
                _flag_entry(values, "flip_left", source),
                _flag_entry(values, "flip_right", source),
            )
        else:
            split = PrismSplit.side_by_side((2 * view[0], view[1]))
        try:
            T_rig_left = np.asarray(values.get("T_rig_left", np.eye(4)), dtype=np.float64).reshape(4, 4)
            left = CameraModel(np.asarray(values["K1"]).reshape(3, 3), np.asarray(values["D1"]).ravel(), view)
            right = CameraModel(np.asarray(values["K2"]).reshape(3, 3), np.asarray(values["D2"]).ravel(), view)
        except (ValueError, TypeError) as exc:  # a 2x2 K, a text where a matrix belongs...
            raise InputError(f"{source}: K1, K2 must be 3x3, D1, D2 distortion vectors, T_rig_left "
                             f"4x4 ({exc})") from None
        return cls(left, right, T, split, T_rig_left)

    def save(self, path: str | Path, extra: dict[str, Any] | None = None) -> None:
        """Write the rig as OpenCV FileStorage YAML (atomically), plus ``extra`` entries."""
        values = self.to_filestorage()
        if extra:
            values.update(extra)
        write_filestorage(path, values)

    @classmethod
    def load(cls, path: str | Path) -> StereoRig:
        """Read a rig (or calibration) YAML written by prism3d or by OpenCV tools."""
        return cls.from_filestorage(read_filestorage(path), source=str(path))


def _int_entry(values: dict[str, Any], name: str, default: int, source: str) -> int:
    try:
        return int(values.get(name, default))
    except (TypeError, ValueError):
        raise InputError(f"{source}: {name} must be an integer, got {values.get(name)!r}") from None


def _flag_entry(values: dict[str, Any], name: str, source: str) -> bool:
    v = _int_entry(values, name, 0, source)
    if v not in (0, 1):
        raise InputError(f"{source}: {name} must be 0 or 1, got {v}")
    return bool(v)


def paper_rig(
    *,
    working_distance_mm: float = 1250.0,
    baseline_mm: float = 197.9,
    focal_px: float = 5107.0,
    sensor_size: tuple[int, int] = (2592, 1944),
    dist: tuple[float, ...] = (-0.06, 0.12, 0.0, 0.0, 0.0),
    skew: float = 0.0,
    flip_left: bool = False,
    flip_right: bool = False,
) -> StereoRig:
    """The paper's rig: a 5 MP sensor split into two 1296x1944 views, f = 5107 px,
    baseline 197.9 mm, both views converging ``working_distance_mm`` in front, mild radial
    distortion. Rig frame: origin midway between the centres, x to the right camera, z to
    the convergence point, y down.

    References
    ----------
    .. [1] "A high-resolution and high-speed 3D imaging system and its application on
       ATR" (the system this package implements): section on the prism adapter.
    """
    split = PrismSplit.side_by_side(sensor_size, flip_left=flip_left, flip_right=flip_right)
    w, h = split.view_size
    K = np.array([[focal_px, skew, (w - 1) / 2.0], [0.0, focal_px, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    cam = CameraModel(K, np.asarray(dist, dtype=np.float64), (w, h))
    target = np.array([0.0, 0.0, float(working_distance_mm)])
    T_rig_left = look_at(np.array([-baseline_mm / 2.0, 0.0, 0.0]), target)
    T_rig_right = look_at(np.array([baseline_mm / 2.0, 0.0, 0.0]), target)
    T_right_left = np.linalg.inv(T_rig_right) @ T_rig_left
    return StereoRig(cam, cam, T_right_left, split, T_rig_left)


def scaled_rig(range_mm: float, baseline_mm: float, **kwargs: Any) -> StereoRig:
    """The paper's design scaled to another range (e.g. 20 m range, 4 m baseline).

    The focal length is kept (same sensor and lens class); only geometry changes.
    """
    if range_mm <= 0 or baseline_mm <= 0:
        raise InputError(f"range_mm and baseline_mm must be > 0, got {range_mm}, {baseline_mm}")
    return paper_rig(working_distance_mm=range_mm, baseline_mm=baseline_mm, **kwargs)


@dataclass(frozen=True, eq=False)
class Rectification:
    """Rectifying rotations ``R1, R2`` (3, 3) (camera -> rectified frame),
    projections ``P1, P2`` (3, 4) with equal principal points and ``P2[0, 3] = -f * B`` (so
    ``d = f * B / z``), disparity-to-depth ``Q`` (4, 4) and the rectified ``size``
    (as ``cv2.stereoRectify``)."""

    R1: NDArray[np.float64]
    R2: NDArray[np.float64]
    P1: NDArray[np.float64]
    P2: NDArray[np.float64]
    Q: NDArray[np.float64]
    size: tuple[int, int]

    def __post_init__(self) -> None:
        for name, shape in (("R1", (3, 3)), ("R2", (3, 3)), ("P1", (3, 4)), ("P2", (3, 4)), ("Q", (4, 4))):
            object.__setattr__(self, name, _frozen_array(check_array(getattr(self, name), name, shape=shape)))
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))

    def to_filestorage(self) -> dict[str, Any]:
        """``R1 R2 P1 P2 Q rectified_size``: ``cv2.stereoRectify``'s names, as FileStorage entries."""
        return {"R1": self.R1, "R2": self.R2, "P1": self.P1, "P2": self.P2, "Q": self.Q,
                "rectified_size": np.array(self.size, dtype=np.int32)}

    @property
    def focal_px(self) -> float:
        return float(self.P1[0, 0])

    @property
    def baseline_mm(self) -> float:
        return float(-self.P2[0, 3] / self.P2[0, 0])

    @property
    def camera(self) -> CameraModel:
        """The rectified left camera (no distortion)."""
        return CameraModel(self.P1[:, :3], np.zeros(5), self.size)

    def disparity_to_depth(self, disparity: NDArray) -> NDArray[np.float32]:
        """Depth (mm, rectified left frame z) from disparity; NaN stays NaN."""
        d = np.asarray(disparity, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.focal_px * self.baseline_mm / d
        z[~(d > 0)] = np.nan
        return z.astype(np.float32)


#: Samples per image edge when tracing a view's footprint in the rectified frame: the
#: distorted edges are smooth, so 64 points trace them to far below a pixel.
_FOOTPRINT_SAMPLES = 64
#: Rounding allowance (px) on the output size: an exact identity rig keeps its own size.
_SIZE_ROUNDING_PX = 1e-6


def _rectifying_rotations(rig: StereoRig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``R1``, ``R2``: x along the baseline, z along the mean optical axis (Fusiello)."""
    R = rig.R
    t = rig.T
    # camera centres in the left frame
    c_right = -R.T @ t
    x_axis = c_right / np.linalg.norm(c_right)
    z_mean = np.array([0.0, 0.0, 1.0]) + R.T @ np.array([0.0, 0.0, 1.0])
    z_axis = z_mean - x_axis * (x_axis @ z_mean)
    z_axis /= np.linalg.norm(z_axis)
    y_axis = np.cross(z_axis, x_axis)
    R1 = np.stack([x_axis, y_axis, z_axis])  # rows: rect axes in left frame -> x_rect = R1 x_left
    return R1, R1 @ R.T  # x_rect(right-centred) = R1 R^T x_right


def _footprint(cam: CameraModel, Rr: NDArray) -> tuple[float, ...]:
    """A view's outer and inner extent ``(x0, x1, y0, y1)`` in normalised rectified coordinates."""
    w, h = cam.size
    n = _FOOTPRINT_SAMPLES
    us = np.linspace(0, w - 1, n)
    vs = np.linspace(0, h - 1, n)
    edges = {
        "top": np.stack([us, np.zeros(n)], 1),
        "bottom": np.stack([us, np.full(n, h - 1.0)], 1),
        "left": np.stack([np.zeros(n), vs], 1),
        "right": np.stack([np.full(n, w - 1.0), vs], 1),
    }
    proj = {}
    for k, uv in edges.items():
        rays = cam.pixel_rays(uv) @ Rr.T
        proj[k] = rays[:, :2] / rays[:, 2:3]
    outer = (
        min(p[:, 0].min() for p in proj.values()),
        max(p[:, 0].max() for p in proj.values()),
        min(p[:, 1].min() for p in proj.values()),
        max(p[:, 1].max() for p in proj.values()),
    )
    inner = (
        proj["left"][:, 0].max(),
        proj["right"][:, 0].min(),
        proj["top"][:, 1].max(),
        proj["bottom"][:, 1].min(),
    )
    return (*outer, *inner)


def _rectified_window(
    rig: StereoRig, R1: NDArray, R2: NDArray, a: float
) -> tuple[float, float, float, float]:
    """Union of the views' columns and their common rows, ``(x0, x1, y0, y1)``, between the
    inner (``a = 0``) and outer (``a = 1``) footprints."""
    xs0, xs1, ys0, ys1 = [], [], [], []
    for cam, Rr in ((rig.left, R1), (rig.right, R2)):
        ox0, ox1, oy0, oy1, ix0, ix1, iy0, iy1 = _footprint(cam, Rr)
        xs0.append(a * ox0 + (1 - a) * ix0)
        xs1.append(a * ox1 + (1 - a) * ix1)
        ys0.append(a * oy0 + (1 - a) * iy0)
        ys1.append(a * oy1 + (1 - a) * iy1)
    x0, x1 = min(xs0), max(xs1)  # union of columns
    y0, y1 = max(ys0), min(ys1)  # common rows
    if not (x1 > x0 and y1 > y0):
        raise InputError("the two views share no rows after rectification: check R and T")
    return x0, x1, y0, y1


def _fit_window(
    f: float, window: tuple[float, float, float, float], size: tuple[int, int] | None
) -> tuple[float, float, float, int, int]:
    """Focal length, principal point and output size that hold ``window``."""
    x0, x1, y0, y1 = window
    if size is not None:
        w_out, h_out = int(size[0]), int(size[1])
        if w_out <= 0 or h_out <= 0:
            raise InputError(f"size: expected positive (width, height), got {size}")
        f *= min((w_out - 1) / (f * (x1 - x0)), (h_out - 1) / (f * (y1 - y0)))
        cx = (w_out - 1) / 2.0 - f * (x0 + x1) / 2.0
        cy = (h_out - 1) / 2.0 - f * (y0 + y1) / 2.0
    else:
        w_out = int(math.ceil(f * (x1 - x0) - _SIZE_ROUNDING_PX)) + 1
        h_out = int(math.ceil(f * (y1 - y0) - _SIZE_ROUNDING_PX)) + 1
        cx = -f * x0
        cy = -f * y0
    return f, cx, cy, w_out, h_out


def compute_rectification(
    rig: StereoRig,
    *,
    alpha: float = 1.0,
    size: tuple[int, int] | None = None,
    focal_px: float | None = None,
) -> Rectification:
    """Rectify ``rig``: both views rotated to a common frame whose x axis is the
    baseline, with equal principal points, so rectified depth ``z`` has disparity
    ``d = f * B / z``. The output spans the union of both views' columns and their
    common rows.

    ``alpha`` in [0, 1]: 0 crops each view to its inner rectangle, 1 keeps every source
    pixel. ``size``: output ``(width, height)``, the focal length scaled to fit.
    ``focal_px``: rectified focal length before any fit; default the mean fy.

    References
    ----------
    .. [1] A. Fusiello, E. Trucco, A. Verri, "A compact algorithm for rectification of
       stereo pairs", Machine Vision and Applications 12 (2000).
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"alpha: expected a value in [0, 1], got {alpha}")
    R1, R2 = _rectifying_rotations(rig)
    f = float(focal_px) if focal_px is not None else 0.5 * (rig.left.fy + rig.right.fy)
    if not f > 0:
        raise InputError(f"focal_px: expected > 0, got {focal_px}")
    window = _rectified_window(rig, R1, R2, float(alpha))
    f, cx, cy, w_out, h_out = _fit_window(f, window, size)
    B = rig.baseline_mm
    P1 = np.array([[f, 0.0, cx, 0.0], [0.0, f, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    P2 = P1.copy()
    P2[0, 3] = -f * B
    Q = np.array(
        [[1.0, 0.0, 0.0, -cx], [0.0, 1.0, 0.0, -cy], [0.0, 0.0, 0.0, f], [0.0, 0.0, 1.0 / B, 0.0]]
    )
    return Rectification(R1, R2, P1, P2, Q, (w_out, h_out))
