"""What a calibration gives: each camera's intrinsics and errors (:class:`CameraCalibration`)
and the stereo rig with its per-view errors, uncertainties and warnings
(:class:`Calibration`), written as OpenCV FileStorage YAML.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import CameraModel, StereoRig
from prism3d.checks import check_positive
from prism3d.errors import InputError
from prism3d.geometry import rotation_angle_deg
from prism3d.io.opencv_yaml import read_filestorage
from prism3d.reconstruct.stereo._bundle import (
    CAM_PARAM_NAMES,
)
from prism3d.reconstruct.stereo.calibration_pinning import (
    DISPARITY_NEED_PX,
    ROW_OFFSET_NEED_PX,
)
from prism3d.reconstruct.stereo.corners import (
    CornerDetection,
)

__all__ = ["MAX_SQUARE_MM", "Calibration", "CameraCalibration", "check_square"]


#: Largest chessboard square, mm: a 100 m square is no calibration board (and 1e300
#: overflows the float32 corner arithmetic).
MAX_SQUARE_MM = 1e5


def check_square(square_mm: float) -> float:
    v = check_positive(square_mm, "square_mm")
    if v > MAX_SQUARE_MM:
        raise InputError(f"square_mm: expected at most {MAX_SQUARE_MM:g} mm, got {square_mm!r}")
    return v


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Result of :func:`calibrate_camera`: the camera, RMS reprojection error (px,
    ``sqrt(mean(du^2 + dv^2))`` as ``cv2.calibrateCamera``) overall and per view ``(V,)``,
    standard deviation per parameter name (0 when fixed), ``T_cam_board (V, 4, 4)``."""

    camera: CameraModel
    rms_px: float
    per_view_rms_px: NDArray[np.float64]
    std: dict[str, float]
    T_cam_board: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibrated stereo rig and its quality figures.

    RMS reprojection errors are px (``per_view_rms_px`` ``(V, 2)``, NaN where a camera
    missed the board); ``std`` holds ``fx_left ... k3_right``, ``rx ry rz`` (rad) and
    ``tx ty tz`` (mm); ``outlier_views`` exceed ``OUTLIER_FACTOR`` x the median view RMS.
    ``precision`` (working distance, 1-sigma rectified row offset and disparity px at the
    worst image point, depth mm), ``needs`` (per parameter, the std that alone reaches
    ``ROW_OFFSET_NEED_PX`` / ``DISPARITY_NEED_PX``) and ``warnings`` come from the pinning
    check; they are empty for loaded files and not stored in the YAML.
    """

    rig: StereoRig
    rms_px: float = float("nan")
    rms_left_px: float = float("nan")
    rms_right_px: float = float("nan")
    per_view_rms_px: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    std: dict[str, float] = field(default_factory=dict)
    rectification_rms_px: float = float("nan")
    n_views: int = 0
    board: tuple[int, int] = (0, 0)
    square_mm: float = float("nan")
    flags: dict[str, bool] = field(default_factory=dict)
    outlier_views: tuple[int, ...] = ()
    sources: tuple[str, ...] = ()
    detections: tuple[CornerDetection, ...] = ()
    precision: dict[str, float] = field(default_factory=dict)
    needs: dict[str, float] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.rig, StereoRig):
            raise InputError(f"rig: expected a StereoRig, got {type(self.rig).__name__}")
        pv = np.asarray(self.per_view_rms_px, dtype=np.float64)
        if pv.ndim != 2 or pv.shape[1] != 2:
            raise InputError(f"per_view_rms_px: expected shape (V, 2), got {pv.shape}")
        object.__setattr__(self, "per_view_rms_px", pv)
        object.__setattr__(self, "board", (int(self.board[0]), int(self.board[1])))
        object.__setattr__(self, "outlier_views", tuple(int(v) for v in self.outlier_views))

    # -- file I/O ----------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Write OpenCV FileStorage YAML: ``K1 D1 K2 D2 R T``, the RMS figures and the
        standard deviations ``std_K1 std_D1 std_K2 std_D2 std_om`` (rad) ``std_T`` (mm)."""
        extra: dict[str, Any] = {
            "rms_px": float(self.rms_px),
            "rms_left_px": float(self.rms_left_px),
            "rms_right_px": float(self.rms_right_px),
            "rectification_rms_px": float(self.rectification_rms_px),
            "n_views": int(self.n_views),
        }
        if self.board != (0, 0):
            extra["board"] = np.array(self.board, dtype=np.int32)
            extra["square_mm"] = float(self.square_mm)
        if self.per_view_rms_px.size:
            extra["per_view_rms_px"] = np.asarray(self.per_view_rms_px, dtype=np.float64)
        if self.outlier_views:
            extra["outlier_views"] = np.array(self.outlier_views, dtype=np.int32)
        for k in ("skew", "tangential", "k3"):
            if k in self.flags:
                extra[f"calib_{k}"] = int(bool(self.flags[k]))
        if self.std:
            for cam, tag in (("left", "1"), ("right", "2")):
                extra[f"std_K{tag}"] = np.array(
                    [self.std.get(f"{n}_{cam}", 0.0) for n in CAM_PARAM_NAMES[:5]]
                )
                extra[f"std_D{tag}"] = np.array(
                    [self.std.get(f"{n}_{cam}", 0.0) for n in CAM_PARAM_NAMES[5:]]
                )
            extra["std_om"] = np.array([self.std.get(n, 0.0) for n in ("rx", "ry", "rz")])
            extra["std_T"] = np.array([self.std.get(n, 0.0) for n in ("tx", "ty", "tz")])
        self.rig.save(path, extra=extra)

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration YAML; a plain ``rig.yaml`` (no quality figures) also loads."""
        values = read_filestorage(path)
        rig = StereoRig.from_filestorage(values, source=str(path))

        def num(key: str) -> float:
            v = values.get(key)
            return float(np.asarray(v).ravel()[0]) if v is not None else float("nan")

        std: dict[str, float] = {}
        if "std_K1" in values:
            for cam, tag in (("left", "1"), ("right", "2")):
                k = np.asarray(values.get(f"std_K{tag}", np.zeros(5))).ravel()
                d = np.asarray(values.get(f"std_D{tag}", np.zeros(5))).ravel()
                for n, v in zip(CAM_PARAM_NAMES, np.concatenate([k, d]), strict=False):
                    std[f"{n}_{cam}"] = float(v)
            for names, key in ((("rx", "ry", "rz"), "std_om"), (("tx", "ty", "tz"), "std_T")):
                vals = np.asarray(values.get(key, np.zeros(3))).ravel()
                std.update({n: float(v) for n, v in zip(names, vals, strict=False)})
        pv = values.get("per_view_rms_px")
        board = values.get("board")
        return cls(
            rig=rig,
            rms_px=num("rms_px"),
            rms_left_px=num("rms_left_px"),
            rms_right_px=num("rms_right_px"),
            per_view_rms_px=np.zeros((0, 2))
            if pv is None
            else np.asarray(pv, dtype=np.float64).reshape(-1, 2),
            std=std,
            rectification_rms_px=num("rectification_rms_px"),
            n_views=int(num("n_views")) if "n_views" in values else 0,
            board=(0, 0) if board is None else tuple(int(b) for b in np.asarray(board).ravel()[:2]),
            square_mm=num("square_mm"),
            flags={
                k: bool(int(num(f"calib_{k}")))
                for k in ("skew", "tangential", "k3")
                if f"calib_{k}" in values
            },
            outlier_views=tuple(
                int(v) for v in np.asarray(values.get("outlier_views", [])).ravel()
            ),
        )

    def summary(self) -> str:
        """A printable multi-line report (what the CLI shows)."""
        rig = self.rig
        lines = [
            (
                f"views: {self.n_views}   board: {self.board[0]}x{self.board[1]}, "
                f"{self.square_mm:g} mm squares"
            ),
            (
                f"RMS reprojection error: {self.rms_px:.4f} px "
                f"(left {self.rms_left_px:.4f}, right {self.rms_right_px:.4f})"
            ),
            f"rectification residual (vertical disparity RMS): {self.rectification_rms_px:.4f} px",
        ]
        if self.precision:
            pr = self.precision
            lines.append(
                f"precision at the working distance ({pr['working_distance_mm']:.0f} mm, 1 sigma, worst image "
                f"point): rectified rows ±{pr['row_offset_px']:.3f} px (needs <= {ROW_OFFSET_NEED_PX:g}), "
                f"disparity ±{pr['disparity_px']:.3f} px = ±{pr['depth_mm']:.3f} mm of depth "
                f"(needs <= {DISPARITY_NEED_PX:g})"
            )
        for cam, name in ((rig.left, "left"), (rig.right, "right")):
            s = self.std
            lines.append(
                f"{name:5s}: fx {cam.fx:.2f} ±{s.get(f'fx_{name}', 0):.2f}  fy {cam.fy:.2f} "
                f"±{s.get(f'fy_{name}', 0):.2f}  cx {cam.cx:.2f} ±{s.get(f'cx_{name}', 0):.2f}  "
                f"cy {cam.cy:.2f} ±{s.get(f'cy_{name}', 0):.2f}  skew {cam.skew:.3f}"
            )
            d = cam.dist
            lines.append(
                f"       k1 {d[0]:.5f} ±{s.get(f'k1_{name}', 0):.5f}  k2 {d[1]:.5f} "
                f"±{s.get(f'k2_{name}', 0):.5f}  p1 {d[2]:.6f}  p2 {d[3]:.6f}  k3 {d[4]:.5f}"
            )
        t = rig.T
        lines.append(
            f"baseline {rig.baseline_mm:.3f} mm  T = ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) mm "
            f"±({self.std.get('tx', 0):.3f}, {self.std.get('ty', 0):.3f}, {self.std.get('tz', 0):.3f})"
            f"  rotation {rotation_angle_deg(rig.R):.4f} deg"
        )
        if self.per_view_rms_px.size:
            lines.append("per-view RMS (left, right) px:")
            for i, (a, b) in enumerate(self.per_view_rms_px):
                src = self.sources[i] if i < len(self.sources) else f"view {i}"
                flag = "  <-- outlier" if i in self.outlier_views else ""
                lines.append(f"  {i:3d} {a:8.4f} {b:8.4f}  {src}{flag}")
        missing = [d for d in self.detections if not d.found]
        for d in missing:
            lines.append(f"board not found: {d.source} ({d.view} view)")
        return "\n".join(lines)
