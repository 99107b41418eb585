"""Resume an interrupted survey: the finished work kept beside the output folder.

While a survey runs, its poses (the SfM result and COLMAP model) and each finished dense
pair are written, each atomically, into ``.OUT.resume/`` beside ``OUT``, under a
fingerprint of what decides them (the frames' names, sizes and modification times, the GPS
table's and calibration's bytes, the options, prism3d's version). A rerun of the same
command with ``--resume`` after an interruption (Ctrl-C, SIGTERM, kill -9, a lost machine)
reuses them: the poses as they were (so the kept pairs stay consistent with them) and every
finished pair; the rest is computed. The folder goes once the survey's outputs are in
place, and at once when the survey fails on its input (nothing there is worth keeping).
Without ``--resume``, a folder left by an earlier run is removed and the survey starts
again. Arrays are stored as ``.npz`` without pickles and the rest as JSON.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from prism3d import __version__
from prism3d.errors import InputError
from prism3d.io.atomic import atomic_path, atomic_write_text
from prism3d.reconstruct.survey.model import PairResult, PairTile, SurveyOptions
from prism3d.reconstruct.survey.sfm import SfmResult

__all__ = ["ResumeFolder", "load_pair", "resume_dir", "save_pair"]

RESUME_SCHEMA_VERSION = 1
#: Options that only shape the products written from the poses and pairs: a rerun that
#: changes them still resumes (the products are always made again).
PRODUCT_ONLY_OPTIONS = ("crs", "laz", "cloud_spacing_m", "ortho_gsd_m")


def resume_dir(out: Path) -> Path:
    """Where a survey into ``out`` keeps its finished work."""
    return out.parent / f".{out.name}.resume"


def _fingerprint(images: list[Path], gps_table: Path | None, calib: Path | None, options: SurveyOptions) -> str:
    h = hashlib.sha256()
    h.update(f"prism3d {__version__} resume {RESUME_SCHEMA_VERSION}\n".encode())
    for p in images:
        st = p.stat()
        h.update(f"{p.resolve()} {st.st_size} {st.st_mtime_ns}\n".encode())
    for f in (gps_table, calib, options.gcp_file):
        h.update(b"-" if f is None else Path(f).read_bytes())
    kept = {k: v for k, v in asdict(options).items() if k not in PRODUCT_ONLY_OPTIONS}
    h.update(json.dumps(kept, sort_keys=True, default=str).encode())
    return h.hexdigest()


def save_pair(r: PairResult, path: str | Path) -> None:
    """One pair's result, atomically (``.npz``: its arrays and its record as JSON)."""
    arrays: dict[str, Any] = {"record": np.array(json.dumps(r.record()))}
    if r.tile is not None:
        t = r.tile
        arrays.update(tile_west=np.float64(t.west), tile_north=np.float64(t.north), tile_cell=np.float64(t.cell),
                      tile_dsm=t.dsm, tile_count=t.count, tile_rgb=t.rgb)
    if r.depth is not None:
        arrays["depth"] = r.depth
    if r.K_depth is not None:
        arrays["K_depth"] = r.K_depth
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def load_pair(path: str | Path) -> PairResult | None:
    """A pair written by :func:`save_pair`, or None when it is unreadable (recomputed)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            rec = json.loads(str(z["record"]))
            r = PairResult(**rec)
            if "tile_dsm" in z.files:
                r.tile = PairTile(float(z["tile_west"]), float(z["tile_north"]), float(z["tile_cell"]),
                                  z["tile_dsm"], z["tile_count"], z["tile_rgb"])
            r.depth = z["depth"] if "depth" in z.files else None
            r.K_depth = z["K_depth"] if "K_depth" in z.files else None
            return r
    except (OSError, ValueError, KeyError, TypeError):
        return None


class ResumeFolder:
    """``.OUT.resume/`` of one survey (module docstring): ``sfm`` and ``pairs`` kept there."""

    def __init__(self, out: Path, images: list[Path], gps_table: Path | None, calib: Path | None,
                 options: SurveyOptions, *, resume: bool) -> None:
        self.dir = resume_dir(out)
        if self.dir.exists() and not self.dir.is_dir():
            raise InputError(f"{self.dir}: exists and is not a folder (the survey keeps its resume data there); "
                             "move it away")
        fp = _fingerprint(images, gps_table, calib, options)
        old = self.dir / "fingerprint.json"
        same = False
        if resume and old.is_file():
            try:
                same = json.loads(old.read_text()).get("fingerprint") == fp
            except (OSError, ValueError):
                same = False
        if self.dir.exists() and not same:
            shutil.rmtree(self.dir)
        self.resumed = same
        (self.dir / "pairs").mkdir(parents=True, exist_ok=True)
        if not same:
            atomic_write_text(old, json.dumps({"fingerprint": fp, "schema_version": RESUME_SCHEMA_VERSION}))

    def pair_path(self, i: int, j: int) -> Path:
        return self.dir / "pairs" / f"{i}_{j}.npz"

    def finished_pair(self, i: int, j: int) -> PairResult | None:
        p = self.pair_path(i, j)
        return load_pair(p) if self.resumed and p.is_file() else None

    def save_sfm(self, sfm: SfmResult) -> None:
        """The poses: arrays in ``sfm.npz``, the rest in ``sfm.json``, the COLMAP model copied."""
        d = self.dir / "sfm"
        shutil.rmtree(d, ignore_errors=True)
        shutil.copytree(sfm.model_dir, d / "model")
        reg = [T is not None for T in sfm.cam_from_world]
        poses = np.array([T if T is not None else np.full((4, 4), np.nan) for T in sfm.cam_from_world])
        with atomic_path(d / "sfm.npz") as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, cam_from_world=poses, K=sfm.K, dist=sfm.dist, points=sfm.points, colors=sfm.colors,
                         track_length=sfm.track_length)
        meta = {"names": sfm.names, "registered": reg, "size": list(sfm.size), "reprojection_rms_px": sfm.reprojection_rms_px,
                "n_observations": sfm.n_observations, "seconds": sfm.seconds, "model_names": sfm.model_names,
                "model_sizes": sfm.model_sizes, "camera_model": sfm.camera_model, "camera_choice": sfm.camera_choice,
                "frame": sfm.frame, "georeferencing": sfm.georeferencing, "self_calibration": sfm.self_calibration}
        atomic_write_text(d / "sfm.json", json.dumps(meta))  # last: its presence says the poses are whole

    def load_sfm(self, log_path: Path) -> SfmResult | None:
        d = self.dir / "sfm"
        if not self.resumed or not (d / "sfm.json").is_file():
            return None
        try:
            meta = json.loads((d / "sfm.json").read_text())
            with np.load(d / "sfm.npz", allow_pickle=False) as z:
                a = {k: z[k] for k in z.files}
        except (OSError, ValueError, KeyError):
            return None
        poses = [a["cam_from_world"][k] if ok else None for k, ok in enumerate(meta["registered"])]
        return SfmResult(names=meta["names"], registered=meta["registered"], cam_from_world=poses, K=a["K"],
                         dist=a["dist"], size=tuple(meta["size"]), points=a["points"], colors=a["colors"],
                         track_length=a["track_length"], reprojection_rms_px=meta["reprojection_rms_px"],
                         n_observations=meta["n_observations"], model_dir=d / "model",
                         seconds=dict(meta["seconds"]), log_path=log_path, model_names=meta["model_names"],
                         model_sizes=meta["model_sizes"], camera_model=meta["camera_model"],
                         camera_choice=meta["camera_choice"], frame=meta.get("frame", "model"),
                         georeferencing=meta.get("georeferencing", {}),
                         self_calibration=meta.get("self_calibration", {}))

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
