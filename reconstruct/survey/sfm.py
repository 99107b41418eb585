"""Camera poses of a drone survey (many photographs from one moving camera) by COLMAP's
structure from motion: SIFT features, matching, incremental mapping and bundle adjustment
that refines the focal length and radial distortion, through pycolmap, in a child
process. The survey mode's pose step (docs/uav.md); OpenCV's two-view geometry
(tests/reconstruct/two_view_anchor.py) is its anchor.

Why a child process: COLMAP logs to stderr at the file-descriptor level (the child's goes
to ``colmap.log``), a crash must not take the caller down, and a timeout must be
enforceable. Why these settings (measured on pycolmap 4.2.1, docs/uav.md): one RADIAL
camera (f, cx, cy, k1, k2) shared by all frames and started from a calibration we give
(COLMAP's EXIF guess is wrong on resized copies); the principal point fixed by default
(two nadir views moved it by 213 px when free); two-view tracks kept (else two frames
triangulate nothing).

Pixel conventions: COLMAP puts (0, 0) at the top-left corner of the image, prism3d at the
centre of the top-left pixel; the conversion (0.5 px) happens here, both ways, and
everything this module returns is in prism3d's convention, at full resolution.

References
----------
.. [1] J. L. Schoenberger and J.-M. Frahm, "Structure-from-Motion Revisited", CVPR 2016.
.. [2] S. Umeyama, "Least-squares estimation of transformation parameters between two
   point patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d._env import configured_threads
from prism3d.capture.rig import CameraModel
from prism3d.checks import check_array, check_choice, check_int, check_positive
from prism3d.errors import InputError, ReconstructionError
from prism3d.io.atomic import atomic_write_text
from prism3d.io.images import check_image_size
from prism3d.reconstruct.survey import _sfm_worker

__all__ = ["ControlPoint", "SfmOptions", "SfmResult", "map_frames", "similarity_align"]

log = logging.getLogger(__name__)

#: "auto" matching is exhaustive up to this many images, sequential above.
EXHAUSTIVE_MAX_IMAGES = 40
#: The GPS accuracy (horizontal, vertical; m) a first adjustment assumes when it is estimated:
#: a consumer drone's GNSS.
GPS_START_ACCURACY = (1.0, 2.0)
#: The file that marks a work folder as made by :func:`map_frames`.
WORK_MARK = ".prism3d-sfm"
#: What :func:`map_frames` writes in its work folder (removed before a rerun there).
_OWNED = ("database.db", "database.db-wal", "database.db-shm", "images", "model", "sparse",
          "request.json", "result.npz", "result.json", "colmap.log")
_STAGES = ("features", "matching", "mapping", "camera model", "georeferencing")
_WORKER_SCHEMA = 1
_WORKER_MODULE = _sfm_worker.__name__  # run as its own process (python -m)


@dataclass(frozen=True)
class ControlPoint:
    """A ground control point: its name, its position (local ENU m) and its pixels
    ``(frame index, x, y)`` in prism3d's convention (the frames of :func:`map_frames`)."""

    name: str
    enu: tuple[float, float, float]
    observations: tuple[tuple[int, float, float], ...]


@dataclass(frozen=True)
class SfmOptions:
    """Options of :func:`map_frames`."""

    max_image_size: int = 2000
    """SIFT runs on frames downscaled to this longest side (px, >= 100); keypoints come back
    in full-resolution pixels. Full 4608 px frames cost 41 s and 4.4 GB each."""
    max_features: int = 8192
    """Most SIFT features per frame (>= 100)."""
    matching: str = "auto"
    """Which pairs are matched: "exhaustive" (all), "sequential" (each frame with the next
    ``sequential_overlap`` in input order), "spatial" (each frame with its
    ``spatial_neighbours`` nearest by GPS position: a lawnmower block's neighbours on the
    next line too, at a cost linear in the frames) or "auto" (exhaustive up to 40 frames,
    above: spatial with positions, else sequential)."""
    spatial_neighbours: int = 20
    """Frames nearest by position that spatial matching pairs each frame with (>= 1)."""
    sequential_overlap: int = 6
    """Frames after each frame that sequential matching pairs it with (>= 1)."""
    refine_focal: bool = True
    """Bundle adjustment refines the focal length."""
    refine_principal_point: bool = False
    """Bundle adjustment refines the principal point (only with many frames and lines)."""
    refine_distortion: bool = True
    """Bundle adjustment refines k1 and k2 (COLMAP's RADIAL model)."""
    choose_camera: bool = True
    """When the focal length and distortion are refined: compare RADIAL, RADIAL with a free
    principal point and OPENCV (k1 k2 p1 p2) on held-back matches and keep the simplest
    that fits (docs/uav.md); else RADIAL as mapped."""
    threads: int = 0
    """Threads for COLMAP (>= 0); 0: ``configured_threads()`` (PRISM3D_NUM_THREADS), and
    when that is 0 too, all cores."""
    timeout_s: float = 3600.0
    """Wall time (s, > 0) after which the child process is killed."""

    def __post_init__(self) -> None:
        if check_int(self.max_image_size, "max_image_size") < 100:
            raise InputError(f"max_image_size: expected an integer >= 100, got {self.max_image_size}")
        if check_int(self.max_features, "max_features") < 100:
            raise InputError(f"max_features: expected an integer >= 100, got {self.max_features}")
        check_choice(self.matching, "matching", ("auto", "exhaustive", "sequential", "spatial"))
        if check_int(self.spatial_neighbours, "spatial_neighbours") < 1:
            raise InputError(f"spatial_neighbours: expected an integer >= 1, got {self.spatial_neighbours}")
        if check_int(self.sequential_overlap, "sequential_overlap") < 1:
            raise InputError(f"sequential_overlap: expected an integer >= 1, got {self.sequential_overlap}")
        for name in ("refine_focal", "refine_principal_point", "refine_distortion", "choose_camera"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        if check_int(self.threads, "threads") < 0:
            raise InputError(f"threads: expected an integer >= 0, got {self.threads}")
        check_positive(self.timeout_s, "timeout_s")


@dataclass(frozen=True, eq=False)
class SfmResult:
    """Poses and structure of the largest model COLMAP found, per input frame.

    The model frame is COLMAP's (arbitrary position, orientation and scale); cameras use
    the OpenCV convention (x right, y down, z forward) and prism3d's pixel convention.
    """

    names: list[str]
    """Every input image path as given, in input order."""
    registered: list[bool]
    """Per name: placed in the model."""
    cam_from_world: list[NDArray[np.float64] | None]
    """Per name: (4, 4) float64 ``T_cam_world`` (model frame to camera), None if unregistered."""
    K: NDArray[np.float64]
    """(3, 3) refined intrinsics at full resolution (fx = fy with RADIAL)."""
    dist: NDArray[np.float64]
    """(5,) OpenCV distortion (k1, k2, p1, p2, 0); p1 = p2 = 0 with RADIAL."""
    size: tuple[int, int]
    """(width, height) of the frames, px."""
    points: NDArray[np.float64]
    """(N, 3) triangulated points, model frame."""
    colors: NDArray[np.uint8]
    """(N, 3) their RGB colours."""
    track_length: NDArray[np.int64]
    """(N,) frames that see each point."""
    reprojection_rms_px: float
    """RMS of the reprojection error's length over every observation (full-resolution px),
    computed here from the model with ``K``, ``dist`` and the poses."""
    n_observations: int
    """Observations (a point seen in a frame) in the model."""
    model_dir: Path
    """The model in COLMAP's text format (cameras, images, points3D, rigs, frames); its image
    names are the staged names (``model_names``) under ``work_dir/images``."""
    seconds: dict[str, float]
    """Wall time per stage: features, matching, mapping; and total (with process start)."""
    log_path: Path
    """COLMAP's log."""
    model_names: list[str] = field(default_factory=list)
    """Per name: the frame's name in the COLMAP database and model."""
    model_sizes: list[int] = field(default_factory=list)
    """Registered frames of every model COLMAP found, largest (the one returned) first."""
    camera_model: str = "RADIAL"
    """COLMAP's camera model of the result: RADIAL (f, cx, cy, k1, k2) or OPENCV (fx, fy,
    cx, cy, k1, k2, p1, p2)."""
    camera_choice: dict = field(default_factory=dict)
    """How the camera model was chosen: the candidates' held-back RMS, or why none was compared."""
    frame: str = "model"
    """``model`` (COLMAP's arbitrary frame) or ``enu``: the poses and points are already in
    the local east-north-up frame of the control points or GPS positions given
    (``georeferencing`` says how)."""
    georeferencing: dict = field(default_factory=dict)
    """How the model was moved into ENU and adjusted there (control points, GPS priors)."""
    self_calibration: dict = field(default_factory=dict)
    """When the focal length was refined: its formal uncertainty, how the flying height
    trades against it, the block's geometry and whether the block ``determined`` it."""

    @property
    def camera(self) -> CameraModel:
        """The refined calibration as a :class:`~prism3d.capture.rig.CameraModel`."""
        return CameraModel(K=self.K, dist=self.dist, size=self.size)

    @property
    def n_registered(self) -> int:
        return int(sum(self.registered))

    @property
    def unregistered(self) -> list[str]:
        """Input names of the frames not in the model."""
        return [n for n, r in zip(self.names, self.registered) if not r]


def similarity_align(src: NDArray, dst: NDArray, *, scale: bool = True
                     ) -> tuple[float, NDArray[np.float64], NDArray[np.float64]]:
    """The similarity (``s``, ``R``, ``t``) that best maps ``src`` onto ``dst`` in least
    squares, ``dst ~ s R src + t`` (Umeyama [2]_; a proper rotation, never a reflection);
    ``scale=False`` fixes ``s = 1`` (rigid).

    Parameters
    ----------
    src, dst : (N, 3) float64
        Corresponding points, N >= 3, not all on one line (the rotation about that line
        would be undetermined).

    Returns
    -------
    s : float
    R : (3, 3) float64
    t : (3,) float64
    """
    a = check_array(src, "src", shape=(None, 3), dtype_kind="fiu").astype(np.float64)
    b = check_array(dst, "dst", shape=(None, 3), dtype_kind="fiu").astype(np.float64)
    if a.shape != b.shape:
        raise InputError(f"similarity_align: src and dst must have the same shape, got {a.shape} and {b.shape}")
    if len(a) < 3:
        raise InputError(f"similarity_align: expected at least 3 point pairs, got {len(a)}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise InputError("similarity_align: expected finite coordinates")
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    ac, bc = a - ma, b - mb
    sv = np.linalg.svd(ac, compute_uv=False)
    if sv[0] <= 0 or sv[1] <= 1e-9 * sv[0]:
        raise InputError("similarity_align: the source points are all on one line (or one point); "
                         "the rotation is undetermined")
    s, R, t = _sfm_worker.umeyama(np, a, b)
    if not scale:
        s, t = 1.0, mb - R @ ma
    return s, R, t


def map_frames(images: Sequence[str | Path], work_dir: str | Path, *, camera: CameraModel | None = None,
               focal_px: float | None = None, options: SfmOptions | None = None,
               progress: Callable[[int, int, str], None] | None = None,
               positions: NDArray | None = None, gps_accuracy: tuple[float, float] | str | None = None,
               control: Sequence[ControlPoint] = ()) -> SfmResult:
    """Poses of ``images`` (two or more frames of one camera and size, in flight order) by
    COLMAP's incremental structure from motion, run in a child process in ``work_dir``: a
    new or empty folder, or one an earlier call made (``.prism3d-sfm``; a rerun replaces
    its database, staged frames, ``request.json``, ``colmap.log``, results and ``model/``).

    ``camera``: the starting calibration (RADIAL from f = (fx + fy) / 2, the principal
    point, k1 and k2); else ``focal_px`` (EXIF), principal point at the centre.
    ``positions`` (n, 3): each frame's GPS position, metres in a local frame: spatial
    matching pairs frames by it; with ``gps_accuracy`` ((horizontal, vertical) m, or
    "estimate": from the residuals after a first adjustment at :data:`GPS_START_ACCURACY`)
    the model is adjusted in that frame with the positions as soft constraints (COLMAP's
    pose priors). ``control``: ground control points (local ENU) with their pixels; three
    or more seen twice are held fixed in that adjustment. Either returns the model in the
    local frame (``frame == "enu"``). ``progress(done, 5, stage)`` as each stage starts.

    Returns the largest model (frames outside it are unregistered). Raises
    :class:`InputError` for fewer than two frames, a missing, unreadable or odd-sized frame,
    a bad starting calibration or work folder, or fewer than two frames placed; and
    :class:`ReconstructionError` when the child crashed, failed or ran past the timeout.
    """
    opts = SfmOptions() if options is None else options
    if not isinstance(opts, SfmOptions):
        raise InputError(f"options: expected SfmOptions, got {type(opts).__name__}")
    t_start = time.perf_counter()
    paths = _check_images(images)
    size = _frame_size(paths)
    params = _starting_params(camera, focal_px, size)
    gps = None if gps_accuracy is None or positions is None else _gps_prior(gps_accuracy)
    wd = _prepare_work_dir(work_dir, paths)
    staged = _stage_images(paths, wd / "images")
    request = _worker_request(opts, wd, images, paths, staged, params, _checked_positions(positions, len(paths)))
    request["gps_prior"] = gps
    request["gcps"] = [{"name": c.name, "enu": [float(v) for v in c.enu],
                        "obs": [[staged[k], float(x) + 0.5, float(y) + 0.5] for k, x, y in c.observations]}
                       for c in control]  # COLMAP's pixels: (0, 0) the top-left corner
    atomic_write_text(wd / "request.json", json.dumps(request, indent=1))
    log_path = wd / "colmap.log"
    _run_worker(wd, log_path, opts.timeout_s, progress)
    return _read_result(wd, [str(p) for p in images], staged, size, log_path, time.perf_counter() - t_start)


def _gps_prior(gps_accuracy: tuple[float, float] | str) -> dict:
    """The request's GPS prior: the accuracy given, or the start of its estimate."""
    est = isinstance(gps_accuracy, str)
    if est and gps_accuracy != "estimate":
        raise InputError(f"gps_accuracy: expected (horizontal, vertical) metres or 'estimate', got {gps_accuracy!r}")
    h, v = (check_positive(a, "gps_accuracy") for a in (GPS_START_ACCURACY if est else gps_accuracy))
    return {"sigma_h": float(h), "sigma_v": float(v), "estimate": est}


def _checked_positions(positions: NDArray | None, n: int) -> NDArray[np.float64] | None:
    if positions is None:
        return None
    p = np.asarray(positions, dtype=np.float64)
    if p.shape != (n, 3) or not np.isfinite(p).all():
        raise InputError(f"positions: expected {n} finite (x, y, z) rows, got shape {p.shape}")
    return p


def _worker_request(opts: SfmOptions, wd: Path, images: Sequence[str | Path], paths: list[Path],
                    staged: list[str], params: list[float], positions: NDArray | None = None) -> dict:
    """The child's JSON request: where things go, the starting calibration, the frames'
    positions, and the options with "auto" matching and 0 threads resolved."""
    threads = opts.threads
    if threads == 0:
        threads = configured_threads() or -1  # COLMAP: -1 = all cores
    matching = opts.matching
    if matching == "auto":
        matching = ("exhaustive" if len(paths) <= EXHAUSTIVE_MAX_IMAGES
                    else "spatial" if positions is not None else "sequential")
    if matching == "spatial" and positions is None:
        raise InputError("matching: spatial matching needs the frames' positions (GPS)")
    return {
        "schema_version": _WORKER_SCHEMA,
        "work_dir": str(wd),
        "database": str(wd / "database.db"),
        "image_dir": str(wd / "images"),
        "image_names": staged,
        "inputs": [str(p) for p in images],
        "camera_params": params,
        "max_image_size": opts.max_image_size,
        "max_features": opts.max_features,
        "matching": matching,
        "sequential_overlap": opts.sequential_overlap,
        "spatial_neighbours": opts.spatial_neighbours,
        "positions": None if positions is None else positions.tolist(),
        "refine_focal": opts.refine_focal,
        "refine_principal_point": opts.refine_principal_point,
        "refine_distortion": opts.refine_distortion,
        "choose_camera": bool(opts.choose_camera and opts.refine_focal and opts.refine_distortion),
        "threads": threads,
        "model_dir": str(wd / "model"),
        "result_npz": str(wd / "result.npz"),
        "result_json": str(wd / "result.json"),
    }


# --- checks ---------------------------------------------------------------------------------
def _check_images(images: Sequence[str | Path]) -> list[Path]:
    if isinstance(images, (str, Path)) or not isinstance(images, Sequence):
        raise InputError("images: expected a list of image paths")
    if len(images) < 2:
        raise InputError(f"images: structure from motion needs at least 2 frames, got {len(images)}")
    paths = [Path(p) for p in images]
    seen: dict[Path, Path] = {}
    for p in paths:
        if not p.exists():
            raise InputError(f"{p}: image not found; check the path")
        if not p.is_file():
            raise InputError(f"{p}: expected an image file, found a directory or special file")
        r = p.resolve()
        if r in seen:
            raise InputError(f"{p}: given twice (also as {seen[r]}); give each frame once")
        seen[r] = p
    return paths


def _frame_size(paths: list[Path]) -> tuple[int, int]:
    """The frames' common (width, height), read from their headers."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    sizes = []
    for p in paths:
        check_image_size(p)  # the project's pixel budget (PRISM3D_MAX_PIXELS)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(p) as im:
                    sizes.append((int(im.size[0]), int(im.size[1])))
        except Image.DecompressionBombError as exc:
            raise InputError(f"{p}: {exc}") from None
        except (UnidentifiedImageError, OSError, ValueError) as exc:
            raise InputError(f"{p}: cannot read the image ({exc.__class__.__name__}); is it a JPEG/PNG/TIFF?") from exc
    for p, s in zip(paths[1:], sizes[1:]):
        if s != sizes[0]:
            raise InputError(f"images: {paths[0]} is {sizes[0][0]}x{sizes[0][1]} but {p} is {s[0]}x{s[1]}; "
                             "all frames must come from one camera at one size")
    return sizes[0]


def _starting_params(camera: CameraModel | None, focal_px: float | None, size: tuple[int, int]) -> list[float]:
    """COLMAP RADIAL parameters (f, cx, cy, k1, k2), COLMAP's pixel convention."""
    w, h = size
    if camera is not None:
        if not isinstance(camera, CameraModel):
            raise InputError(f"camera: expected a CameraModel, got {type(camera).__name__}")
        if tuple(camera.size) != (w, h):
            raise InputError(f"camera: the calibration is for {camera.size[0]}x{camera.size[1]} px but the "
                             f"frames are {w}x{h} px; calibrate at the frames' size")
        K, d = camera.K, camera.dist
        if K[0, 1] != 0 or np.any(d[2:] != 0):
            log.info("RADIAL start: skew and p1, p2, k3 of the calibration are dropped")
        return [float(K[0, 0] + K[1, 1]) / 2.0, float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5, float(d[0]), float(d[1])]
    if focal_px is None:
        raise InputError("no starting calibration: give --calib or images with EXIF focal length")
    f = check_positive(focal_px, "focal_px")
    return [f, w / 2.0, h / 2.0, 0.0, 0.0]


def _prepare_work_dir(work_dir: str | Path, paths: list[Path]) -> Path:
    """A new or empty folder, or one marked as ours (then cleared of what we wrote)."""
    wd = Path(work_dir).absolute()
    for p in paths:
        if p.absolute().is_relative_to(wd) or p.resolve().is_relative_to(wd.resolve()):
            raise InputError(f"{p}: the frames must not lie inside work_dir {wd}; copy them elsewhere first")
    if wd.exists() and not wd.is_dir():
        raise InputError(f"{wd}: exists and is not a folder; give a new or empty folder as work_dir")
    if wd.is_dir() and any(wd.iterdir()):
        if not (wd / WORK_MARK).is_file():
            raise InputError(f"{wd}: folder is not empty and was not made by map_frames; "
                             "give a new or empty folder as work_dir")
        for name in _OWNED:
            p = wd / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
        for p in wd.glob("result.*.tmp*"):
            p.unlink()
    wd.mkdir(parents=True, exist_ok=True)
    atomic_write_text(wd / WORK_MARK, "made by prism3d.reconstruct.survey.sfm.map_frames; a rerun here replaces its files\n")
    return wd


def _stage_images(paths: list[Path], folder: Path) -> list[str]:
    """Links to the frames under one folder, named ``NNNN_<name>`` so that COLMAP (which
    orders and keys images by name) sees them in input order and frames of the same name
    from different folders stay apart."""
    folder.mkdir()
    width = max(4, len(str(len(paths) - 1)))
    names = []
    for i, p in enumerate(paths):
        name = f"{i:0{width}d}_{p.name}"
        target = folder / name
        try:
            os.symlink(p.resolve(), target)
        except OSError:
            shutil.copyfile(p, target)
        names.append(name)
    return names


# --- the child process ------------------------------------------------------------------------
def _run_worker(wd: Path, log_path: Path, timeout_s: float,
                progress: Callable[[int, int, str], None] | None) -> None:
    """Run the worker on ``wd/request.json``; stage lines from its stdout drive ``progress``."""
    import selectors

    cmd = [sys.executable, "-m", _WORKER_MODULE, str(wd / "request.json")]
    deadline = time.monotonic() + timeout_s
    with open(log_path, "wb") as logf:
        # COLMAP's glog writes to stderr (our log) only, not to log files of its own in $TMPDIR
        env = {**os.environ, "GLOG_logtostderr": "1"}
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=logf, cwd=wd, env=env)
        try:
            fd = proc.stdout.fileno()  # type: ignore[union-attr]  # stdout=PIPE
            sel = selectors.DefaultSelector()
            sel.register(fd, selectors.EVENT_READ)
            buf = b""
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise subprocess.TimeoutExpired(cmd, timeout_s)
                if not sel.select(timeout=min(left, 1.0)):
                    continue
                chunk = os.read(fd, 4096)
                if not chunk:
                    break
                buf += chunk
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    _on_stage(line.decode(errors="replace").strip(), progress)
            sel.close()
            rc = proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            raise ReconstructionError(f"COLMAP did not finish within {timeout_s:g} s (SfmOptions.timeout_s); "
                                      f"see {log_path}") from None
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
    if rc != 0:
        raise ReconstructionError(f"COLMAP failed (exit code {rc}): {_last_line(log_path)}; see {log_path}")


def _on_stage(line: str, progress: Callable[[int, int, str], None] | None) -> None:
    if not line.startswith("stage "):
        return
    name = line[6:]
    log.debug("sfm stage %s", name)
    if progress is None:
        return
    if name in _STAGES:
        progress(_STAGES.index(name), len(_STAGES), name)
    elif name == "done":
        progress(len(_STAGES), len(_STAGES), "done")


def _last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "no log"
    return lines[-1][:300] if lines else "empty log"


# --- results ----------------------------------------------------------------------------------
def _read_result(wd: Path, names: list[str], staged: list[str], size: tuple[int, int], log_path: Path,
                 total_s: float) -> SfmResult:
    try:
        info = json.loads((wd / "result.json").read_text())
    except (OSError, ValueError) as exc:
        raise ReconstructionError(f"COLMAP left no readable result.json: {_last_line(log_path)}; "
                                  f"see {log_path}") from exc
    by_staged = {s: i for i, s in enumerate(staged)}
    if info.get("unreadable"):
        bad = names[by_staged[info["unreadable"][0]]]
        raise InputError(f"{bad}: COLMAP could not read the image (see {log_path}); is it a valid image file?")
    n = len(names)
    if not info.get("model_sizes") or info["model_sizes"][0] < 2:
        raise _not_placed(n, n, info, log_path)
    with np.load(wd / "result.npz", allow_pickle=False) as z:
        arr = {k: z[k] for k in z.files}
    reg_idx = [by_staged[str(s)] for s in arr["reg_names"]]
    if len(reg_idx) < 2:
        raise _not_placed(n - len(reg_idx), n, info, log_path)
    registered = [False] * n
    poses: list[NDArray[np.float64] | None] = [None] * n
    for k, i in enumerate(reg_idx):
        T = np.eye(4)
        T[:3] = arr["cam_from_world"][k]
        registered[i], poses[i] = True, T
    model = str(arr["camera_model"]) if "camera_model" in arr else "RADIAL"
    K, dist = _intrinsics(model, arr["camera_params"])
    if tuple(int(v) for v in arr["camera_size"]) != tuple(size):
        raise ReconstructionError(f"COLMAP's camera is {tuple(arr['camera_size'])} px, the frames {size}")
    obs_xy = arr["obs_xy"] - 0.5
    err = _reprojection_errors(K, dist, arr["cam_from_world"][arr["obs_image"]], arr["points"][arr["obs_point"]],
                               obs_xy)
    rms = float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")
    seconds = {k: float(v) for k, v in info["seconds"].items()}
    seconds["total"] = float(total_s)
    unreg = [i for i in range(n) if not registered[i]]
    if unreg:
        log.warning("%d of %d frames not placed: %s", len(unreg), n,
                    "; ".join(f"{names[i]} ({_why_not_placed(staged[i], info, by_staged, names)})" for i in unreg))
    return SfmResult(
        names=names, registered=registered, cam_from_world=poses, K=K, dist=dist, size=(int(size[0]), int(size[1])),
        points=arr["points"], colors=arr["colors"], track_length=arr["track_length"],
        reprojection_rms_px=rms, n_observations=int(len(err)), model_dir=wd / "model", seconds=seconds,
        log_path=log_path, model_names=list(staged), model_sizes=[int(v) for v in info["model_sizes"]],
        camera_model=model, camera_choice=dict(info.get("camera_choice") or {}),
        frame=str((info.get("georeferencing") or {}).get("frame", "model")),
        georeferencing=dict(info.get("georeferencing") or {}),
        self_calibration=dict(info.get("self_calibration") or {}))


def _intrinsics(model: str, params: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """OpenCV ``K`` and ``dist`` (prism3d's pixel convention) of COLMAP camera parameters."""
    v = [float(x) for x in params]
    if model == "RADIAL":
        f, cx, cy, k1, k2 = v
        fx = fy = f
        p1 = p2 = 0.0
    elif model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = v
    else:
        raise ReconstructionError(f"COLMAP returned a {model} camera; expected RADIAL or OPENCV")
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, np.array([k1, k2, p1, p2, 0.0])


#: Fewer SIFT features than this in a frame: too blurred, dark or plain to match.
FEW_FEATURES = 200


def _why_not_placed(staged_name: str, info: dict, by_staged: dict[str, int], names: Sequence[str]) -> str:
    """Why COLMAP left a frame out, from its worker's counts: too few features, no frame
    verified with it, or the frames it matched and their inlier counts."""
    k = int((info.get("keypoints") or {}).get(staged_name, 0))
    if k < FEW_FEATURES:
        return f"only {k} features: blurred, dark or plain?"
    partners = (info.get("pair_inliers") or {}).get(staged_name) or {}
    if not partners:
        return f"{k} features, but no frame shares enough of them: no overlap?"
    best = sorted(partners.items(), key=lambda kv: -kv[1])[:3]
    said = ", ".join(f"{names[by_staged[o]] if o in by_staged else o} ({m} inliers)" for o, m in best)
    return f"matched {said}, but could not be placed from them: too few inliers or too little parallax?"


def _not_placed(k: int, n: int, info: dict, log_path: Path) -> InputError:
    """The "no overlap" error, saying whether any frames matched at all."""
    pairs = info.get("verified_pairs") or {}
    if not pairs:
        why = "no two frames share enough features"
    else:
        why = (f"{sum(pairs.values())} pair(s) match, but no model could start from them: "
               "too little camera motion between the frames?")
    return InputError(f"{k} of {n} frames could not be placed: do they overlap? ({why}; see {log_path})")


def _reprojection_errors(K: NDArray, dist: NDArray, T: NDArray, X: NDArray, xy: NDArray) -> NDArray[np.float64]:
    """Length of each observation's reprojection error (px): ``X`` (M, 3) model points
    through ``T`` (M, 3, 4) cam_from_world and the camera (k1, k2, p1, p2 of ``dist``),
    against ``xy`` (M, 2)."""
    Xc = np.einsum("mij,mj->mi", T[:, :, :3], X) + T[:, :, 3]
    u, v = Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]
    r2 = u * u + v * v
    radial = 1.0 + dist[0] * r2 + dist[1] * r2 * r2
    p1, p2 = (float(dist[2]), float(dist[3])) if len(dist) >= 4 else (0.0, 0.0)
    ud = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
    vd = v * radial + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
    px = K[0, 0] * ud + K[0, 2]
    py = K[1, 1] * vd + K[1, 2]
    return np.hypot(px - xy[:, 0], py - xy[:, 1])
