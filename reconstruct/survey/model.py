"""The drone survey's options and the values its stages hand on: the georeference, the fused
surface, the folder's file list and schema.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d.errors import InputError
from prism3d.geo import parse_crs

__all__ = ["TwoViewPose", "DISPARITY_SIGMA_PX", "FusedSurface", "Georef", "PairRequest", "PairResult", "PairTile", "SURVEY_FILES",
           "SURVEY_SCHEMA_VERSION", "SurveyOptions", "SurveyState"]


SURVEY_SCHEMA_VERSION = 1


#: Files every survey writes (``survey -o OUT``), besides ``colmap/`` and ``depth/``.
SURVEY_FILES = ("poses.json", "cloud.ply", "cloud.las", "dsm.tif", "ndsm.tif", "ground.tif", "ortho.tif",
                "ortho_quality.tif", "survey.png")


#: Disparity noise assumed for a pair's height tolerance, px at the matched scale.
DISPARITY_SIGMA_PX = 0.25


@dataclass(frozen=True)
class TwoViewPose:
    """``R``, ``t`` map camera-1 coordinates to camera 2 (x2 = R x1 + t, ``t`` unit
    length); ``baseline_cam1`` is camera 2's centre in camera 1's frame (unit);
    ``pts1``/``pts2`` the inlier matches (pixels), ``n_matches`` before the geometric
    check, ``inlier_rms_px`` the Sampson distance RMS of the inliers."""

    R: NDArray[np.float64]
    t: NDArray[np.float64]
    pts1: NDArray[np.float64]
    pts2: NDArray[np.float64]
    n_matches: int
    inlier_rms_px: float

    @property
    def baseline_cam1(self) -> NDArray[np.float64]:
        c = -self.R.T @ self.t
        return c / np.linalg.norm(c)

    @property
    def n_inliers(self) -> int:
        return len(self.pts1)


@dataclass(frozen=True)
class SurveyOptions:
    """How a survey is computed (``prism3d survey`` options)."""

    max_image_size: int = 2000
    """Features for the poses on frames downscaled to this side (keypoints stay full-res)."""
    dense_max_pixels: float = 3.2e6
    """Frames are matched at the largest scale (1, 1/2, 1/3...) keeping them under this
    many pixels: dense matching dominates the time and its memory grows with the area."""
    pair_steps: tuple[int, ...] = (1, 2)
    """Pairs: each frame with the next (1) and the next-but-one (2, twice the baseline)."""
    cross_pairs: bool = True
    """Also pair each frame with the frame further along the sequence that shares most of
    its view (the neighbouring flight line): the strips' ends and edges are seen only so."""
    cell_m: float | None = None
    """DSM cell, m (model units without GPS); None: twice the matched frames' ground sample distance."""
    ortho_gsd_m: float | None = None
    """Orthophoto cell, m; None: the photographs' own ground sample distance (the median
    camera height above the ground over the focal length), finer than the DSM's cell."""
    min_shared_points: int = 30
    """A pair needs this many sparse points seen by both frames, else it is skipped (no overlap)."""
    min_base_to_height: float = 0.03
    """A pair whose baseline is below this fraction of its depth is skipped (too short)."""
    refine_intrinsics: str = "auto"
    """What the bundle adjustment refines: "focal+distortion" (f, k1, k2), "none", or
    "auto": none when the start is a calibration file, f, k1 and k2 from EXIF. Nadir
    frames over gentle relief hardly tell the focal length from the flying height (the
    image scale gives only their ratio), so a calibrated camera is best left as it is."""
    refine_principal_point: bool = False
    """Free the principal point in the bundle adjustment (poorly fixed by few nadir frames)."""
    matcher: str = "ours"
    """The dense matcher: ours, or "sgbm" (OpenCV's, the benchmarks' anchor)."""
    matching: str = "auto"
    """Which frames' features are matched for the poses: "auto" (all pairs up to 40 frames;
    above, each frame with its 20 nearest by GPS position, or the next 6 in flight order
    without GPS), "exhaustive", "spatial" or "sequential" (:class:`~.sfm.SfmOptions`)."""
    crs: str | None = None
    """The products' coordinate system: "utm" (the site's UTM zone; the default with GPS),
    "enu" (the local east-north-up frame at the first frame), or "EPSG:<code>" of a
    projected CRS in metres. Heights stay above the WGS84 ellipsoid. Without GPS the
    products have no CRS and asking for one is an error."""
    laz: bool = False
    """Write the point cloud compressed (cloud.laz) instead of cloud.las."""
    cloud_spacing_m: float | None = None
    """Thin the point cloud to one point per cube of this side, m; None: every matched pixel
    (each DSM cell from its best pair; :mod:`~prism3d.reconstruct.survey.cloud`)."""
    lk_window: int = 9
    """Our matcher's sub-pixel (Lucas-Kanade) window, px, with 3 iterations: nadir pairs
    see ground that is flat at the window's scale, and a wider window than the stereo
    default (5) averages more noise (docs/uav.md: on the simulator the DSM's median error
    0.26 -> 0.19 GSD; the real pair's open ground 7.3 -> 5.3 cm rough)."""

    gps_prior: bool = True
    """With GPS: the positions are soft constraints in the bundle adjustment (each with
    ``gps_accuracy``), the model adjusted in the local frame; off: a similarity onto the
    positions after the adjustment, as before (docs/uav.md)."""
    gps_accuracy: tuple[float, float] | None = None
    """The positions' standard deviation (horizontal, vertical), m; None: estimated from
    their residuals after a first adjustment that assumes a consumer drone's 1 m / 2 m."""
    gcp_file: str | None = None
    """Ground control points, OpenDroneMap's ``gcp_list.txt`` (:mod:`~prism3d.reconstruct.survey.gcp`)."""
    gcp_check: tuple[str, ...] = ()
    """Names in ``gcp_file`` (each may be a comma-separated list) kept out of the adjustment
    and only measured, in ``gcp_check.json``: check points (all of them: the GPS-only
    survey's absolute error is measured)."""

    def __post_init__(self) -> None:
        if isinstance(self.max_image_size, bool) or not 320 <= int(self.max_image_size) <= 20000:
            raise InputError(f"max_image_size: expected 320-20000 px, got {self.max_image_size!r}")
        if not (math.isfinite(self.dense_max_pixels) and self.dense_max_pixels >= 1e4):
            raise InputError(f"dense_max_pixels: expected >= 10000, got {self.dense_max_pixels!r}")
        steps = tuple(int(s) for s in self.pair_steps)
        if not steps or any(s < 1 or s > 10 for s in steps) or len(set(steps)) != len(steps):
            raise InputError(f"pair_steps: expected distinct steps in 1-10, got {self.pair_steps!r}")
        object.__setattr__(self, "pair_steps", steps)
        if self.cell_m is not None and not (math.isfinite(self.cell_m) and 0 < self.cell_m <= MAX_CELL_M):
            raise InputError(f"cell: expected a DSM cell size > 0 and <= {MAX_CELL_M:g} m, got {self.cell_m!r}")
        if self.cloud_spacing_m is not None and not (math.isfinite(self.cloud_spacing_m)
                                                     and 0 < self.cloud_spacing_m <= MAX_CELL_M):
            raise InputError(f"cloud_spacing: expected a spacing > 0 and <= {MAX_CELL_M:g} m, got {self.cloud_spacing_m!r}")
        if self.ortho_gsd_m is not None and not (math.isfinite(self.ortho_gsd_m) and 0 < self.ortho_gsd_m <= MAX_CELL_M):
            raise InputError(f"ortho-gsd: expected an orthophoto cell > 0 and <= {MAX_CELL_M:g} m, "
                             f"got {self.ortho_gsd_m!r}")
        if isinstance(self.lk_window, bool) or int(self.lk_window) != self.lk_window or self.lk_window < 3 \
                or self.lk_window % 2 == 0:
            raise InputError(f"lk_window: expected an odd integer >= 3, got {self.lk_window!r}")
        object.__setattr__(self, "crs", parse_crs(self.crs))
        if self.matching not in ("auto", "exhaustive", "spatial", "sequential"):
            raise InputError(f"matching: expected auto, exhaustive, spatial or sequential, got {self.matching!r}")
        if self.matcher not in ("ours", "sgbm"):
            raise InputError(f"matcher: expected ours or sgbm, got {self.matcher!r}")
        if not isinstance(self.gps_prior, bool):
            raise InputError(f"gps_prior: expected True or False, got {self.gps_prior!r}")
        if self.gps_accuracy is not None:
            acc = tuple(self.gps_accuracy) if isinstance(self.gps_accuracy, (tuple, list)) else (self.gps_accuracy,)
            if len(acc) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                        and 0.005 <= v <= 1000.0 for v in acc):
                raise InputError(f"gps_accuracy: expected (horizontal, vertical) in 0.005-1000 m, "
                                 f"got {self.gps_accuracy!r}")
            object.__setattr__(self, "gps_accuracy", (float(acc[0]), float(acc[1])))
        names = (self.gcp_check,) if isinstance(self.gcp_check, str) else self.gcp_check
        object.__setattr__(self, "gcp_check", tuple(c for a in names for c in str(a).split(",") if c))
        if self.gcp_check and self.gcp_file is None:
            raise InputError("gcp_check: check points need a control point file (gcp_file)")
        if self.refine_intrinsics not in ("auto", "focal+distortion", "none"):
            raise InputError(f"refine_intrinsics: expected auto, focal+distortion or none, got {self.refine_intrinsics!r}")


#: ``poses.json`` ``scale`` of a survey in metres: placed by its GPS, or (no GPS) by its
#: ground control points; "unknown" otherwise.
METRIC_SCALES = ("gps", "control points")
#: Largest DSM or orthophoto cell, m: a kilometre cell maps no drone survey (a larger value
#: is a unit mistake; the products' grids would be one cell, or overflow).
MAX_CELL_M = 1000.0


@dataclass(frozen=True)
class Georef:
    """``x_enu = s R x_model + t``; ``method`` says how it was found, ``residual_rms_m``
    the camera centres' RMS distance to their GPS positions after it (None without GPS)."""

    s: float
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    method: str
    residual_rms_m: float | None

    def apply(self, P: NDArray) -> NDArray[np.float64]:
        return self.s * np.asarray(P, dtype=np.float64) @ self.R.T + self.t

    def pose(self, cam_from_model: NDArray) -> NDArray[np.float64]:
        """``T_enu_cam`` (4, 4) of a camera given ``cam_from_model`` (4, 4)."""
        T = np.linalg.inv(np.asarray(cam_from_model, dtype=np.float64))  # model <- cam
        out = np.eye(4)
        out[:3, :3] = self.R @ T[:3, :3]
        out[:3, 3] = self.apply(T[:3, 3])
        return out


@dataclass(frozen=True)
class FusedSurface:
    """The fused DSM (H, W) float32 (NaN: no consistent height), its colour (H, W, 3)
    uint8, per-cell number of agreeing pairs and of pairs seen, north-west corner, cell."""

    dsm: NDArray[np.float32]
    rgb: NDArray[np.uint8]
    agree: NDArray[np.uint8]
    seen: NDArray[np.uint8]
    west: float
    north: float
    cell: float


@dataclass(frozen=True)
class PairRequest:
    """One dense pair to match (:func:`~prism3d.reconstruct.survey.run.dense_pair`): frames
    ``i`` and ``j`` (their paths and ``T_enu_cam`` poses, 4 x 4), the camera ``K`` and
    ``dist`` shared by the flight, the matching ``factor`` (1, 2, 3...: frames downscaled
    by it), the sparse ENU points both see (``shared``, N x 3), the survey's lattice
    ``cell`` and the options that decide whether the pair is skipped and how it is matched.
    Picklable: the jobs' runner ships it to worker processes or a Dask cluster."""

    i: int
    j: int
    path_i: str
    path_j: str
    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    factor: int
    T_enu_cam_i: NDArray[np.float64]
    T_enu_cam_j: NDArray[np.float64]
    shared: NDArray[np.float64]
    cell: float
    min_shared: int = 30
    min_base_to_height: float = 0.03
    matcher: str = "ours"
    lk_window: int = 5
    save_to: str | None = None
    """Where the finished pair is also written (the survey's resume folder), or nowhere."""


@dataclass(frozen=True)
class PairTile:
    """A pair's heights on the survey's lattice: north-west corner and ``cell`` (m), the
    per-cell median height ``dsm`` (NaN: none), point ``count`` and mean colour ``rgb``."""

    west: float
    north: float
    cell: float
    dsm: NDArray[np.float32]
    count: NDArray[np.int32]
    rgb: NDArray


@dataclass
class PairResult:
    """What one dense pair gave: ``status`` "ok" or "skipped" with a ``reason``; the
    figures measured on the way (None until measured); when ok, its ``tile``, camera i's
    ``depth`` map (m, NaN: none) and that map's intrinsics ``K_depth``."""

    i: int
    j: int
    status: str = "skipped"
    reason: str | None = None
    baseline: float | None = None
    depth_median: float | None = None
    n_points: int | None = None
    valid_fraction: float | None = None
    disparity_range: list[float] | None = None
    sigma_z: float | None = None
    seconds: float | None = None
    tile: PairTile | None = None
    depth: NDArray[np.float32] | None = None
    K_depth: NDArray[np.float64] | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def record(self) -> dict[str, Any]:
        """The pair's entry in poses.json: the figures measured (tile and depth map aside)."""
        out: dict[str, Any] = {"i": self.i, "j": self.j, "status": self.status, "reason": self.reason}
        for k in ("baseline", "depth_median", "n_points", "valid_fraction", "disparity_range", "sigma_z", "seconds"):
            v = getattr(self, k)
            if v is not None:
                out[k] = v
        return out


@dataclass(frozen=True)
class SurveyState:
    """What a survey knows when it writes its products: the frames (``paths``, and how the
    products name them, ``shown``), the SfM model ``sfm``, its georeference ``geo`` and
    ``T_enu_cam`` per placed frame, the dense ``pairs``, the ENU ``origin`` (lat, lon, 0;
    None without GPS) and the frames' GPS positions in ENU, where the GPS and the starting
    camera came from, the intrinsics the adjustment ``refined``, the matching ``factor``
    and the ``options``."""

    paths: list[Path]
    shown: list[str]
    sfm: Any
    geo: Georef
    T_enu: dict[int, NDArray[np.float64]]
    pairs: list[PairResult]
    origin: NDArray[np.float64] | None
    gps_enu: NDArray[np.float64] | None
    gps_source: str
    calib_source: str
    refined: list[str] = field(default_factory=list)
    factor: int = 1
    options: SurveyOptions = field(default_factory=SurveyOptions)

    @property
    def scaled(self) -> bool:
        """Metres in a local ENU frame (GPS or control points), or model units."""
        return self.origin is not None

    @property
    def scale(self) -> str:
        """What placed the survey in metres (:data:`METRIC_SCALES`), or "unknown"."""
        return "gps" if self.gps_enu is not None else "control points" if self.origin is not None else "unknown"
