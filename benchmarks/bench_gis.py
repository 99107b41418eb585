"""Survey products as a GIS user reads them (issue 39): a simulated flight and the real
drone pair surveyed with the defaults (UTM) and, as the anchor in the same run, in the
local frame (``--crs enu``); each product read back through rasterio, rio-cogeo's
validator and laspy + pyproj, and the simulated one scored against its exact truth.

    python benchmarks/bench_gis.py [--work DIR] [--json OUT]

Prints one table; records nothing by itself (the figures go to RESULTS.md by hand).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("PRISM3D_NUM_THREADS", "1")  # COLMAP on one thread: reproducible surveys

from prism3d.cli import main  # noqa: E402
from prism3d.datasets.evaluation.survey_eval import evaluate_survey  # noqa: E402
from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight  # noqa: E402

HERE = Path(__file__).resolve().parent
REAL_DIR = HERE.parents[1] / "shared" / "data" / "aerial" / "snowpeak_internal_only"
REAL_GSD_M = 117.0 / 3210.0  # ground ~117 m below, f = 3210 px (docs/uav.md)


def read_back(survey: Path) -> dict:
    """What GDAL / PDAL users see: EPSG codes, alpha, nodata, units, COG validity, the
    orthophoto's pixel, holes inside its coverage, the cloud's CRS and classes."""
    import laspy
    import rasterio
    from rio_cogeo.cogeo import cog_validate
    from scipy import ndimage

    out: dict = {"rasters": {}}
    for name in ("dsm.tif", "ground.tif", "ndsm.tif", "ortho.tif", "ortho_quality.tif"):
        with rasterio.open(survey / name) as src:
            rec = {"epsg": src.crs.to_epsg() if src.crs else None, "nodata": src.nodata,
                   "alpha": src.colorinterp[-1] == rasterio.enums.ColorInterp.alpha, "units": src.units[0],
                   "overviews": src.overviews(1), "res_m": src.res[0], "cog_valid": cog_validate(str(survey / name),
                                                                                               quiet=True)[0]}
            if name == "ortho.tif":
                a = src.read(4) > 0
                inside = ndimage.binary_fill_holes(a)
                rec["nodata_inside_coverage"] = float((inside & ~a).sum() / max(1, inside.sum()))
        out["rasters"][name] = rec
    cloud = next(p for p in (survey / "cloud.las", survey / "cloud.laz") if p.is_file())
    las = laspy.read(cloud)
    crs = las.header.parse_crs()
    out["cloud"] = {"epsg": crs.to_epsg() if crs else None, "points": int(len(las.x)),
                    "classes": {int(k): int(v) for k, v in zip(*np.unique(las.classification, return_counts=True))}}
    return out


def survey(frames: list[Path], out: Path, *extra: str) -> float:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    rc = main(["-q", "survey", *map(str, frames), *extra, "-o", str(out)])
    if rc != 0:
        raise SystemExit(f"survey of {frames[0].parent} failed ({rc})")
    return time.perf_counter() - t0


def cloud_row(name: str, r: dict) -> str:
    """The cloud beside its anchor, the DSM of the same survey: points per filled DSM cell
    and, on the simulator, the open ground's median |height error| of each."""
    pts, cells = r["read_back"]["cloud"]["points"], r["dsm_filled_cells"]
    ce = f"{r['cloud']['open_ground_median_abs_error_m'] * 100:.2f}" if "cloud" in r else "-"
    de = f"{r['dsm']['median_abs_error_m'] * 100:.2f}" if "dsm" in r else "-"
    ppm = f"{r['cloud']['points_per_m2']:.0f}" if "cloud" in r else "-"
    return f"| {name} | {pts:,} | {cells:,} | {pts / cells:.2f} | {ppm} | {ce} | {de} |"


def main_(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, help="scratch folder (default: a temporary one, removed)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args(argv)
    work = a.work or Path(tempfile.mkdtemp(prefix="bench_gis."))
    res: dict = {}
    try:
        flight = work / "flight"
        if not flight.is_dir():
            simulate_flight(flight, FlightOptions(size=(1152, 864), altitude_m=40.0, seed=7, targets=8))
        frames = sorted(flight.glob("IMG_*.JPG"))
        sim = ["--calib", str(flight / "camera.yaml"), "--gps", str(flight / "geoinfo.txt")]
        truth_gsd = json.loads((flight / "truth.json").read_text())["gsd_m"]
        for crs in ("utm", "enu"):
            s = survey(frames, work / f"sim_{crs}", *sim, "--crs", crs)
            ev = evaluate_survey(work / f"sim_{crs}", flight)
            res[f"sim_{crs}"] = {"seconds": round(s, 1), "photo_gsd_m": truth_gsd, "read_back": read_back(work / f"sim_{crs}"),
                                 "dsm": ev["dsm"], "cloud": ev["cloud"], "position_error_gsd": ev["position_error_gsd"],
                                 "vehicle_height_max_error": ev["vehicles"]["max_relative_height_error"],
                                 "dsm_filled_cells": json.loads((work / f"sim_{crs}" / "poses.json").read_text())[
                                     "dsm"]["filled_cells"]}
        if all((REAL_DIR / n).is_file() for n in ("IMG_2188.JPG", "IMG_2189.JPG", "geoinfo.txt")):
            real = [REAL_DIR / "IMG_2188.JPG", REAL_DIR / "IMG_2189.JPG"]
            for crs in ("utm", "enu"):
                s = survey(real, work / f"real_{crs}", "--gps", str(REAL_DIR / "geoinfo.txt"), "--crs", crs)
                doc = json.loads((work / f"real_{crs}" / "poses.json").read_text())
                res[f"real_{crs}"] = {"seconds": round(s, 1), "photo_gsd_m": REAL_GSD_M,
                                      "reprojection_rms_px": doc["reprojection_rms_px"],
                                      "camera": doc["camera"]["model"], "read_back": read_back(work / f"real_{crs}"),
                                      "dsm_filled_cells": doc["dsm"]["filled_cells"]}
        else:
            print(f"real pair skipped: {REAL_DIR} is absent", file=sys.stderr)
    finally:
        if a.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print("| survey | EPSG (rasters / cloud) | COG valid | alpha / nodata | ortho px / photo GSD | nodata inside coverage "
          "| DSM median err (GSD) | open ground class 2 | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k, r in res.items():
        rb = r["read_back"]
        eps = sorted({str(v["epsg"]) for v in rb["rasters"].values()})
        cog = all(v["cog_valid"] for v in rb["rasters"].values())
        an = rb["rasters"]["ortho.tif"]["alpha"] and all(np.isnan(rb["rasters"][n]["nodata"])
                                                          for n in ("dsm.tif", "ground.tif", "ndsm.tif"))
        ratio = rb["rasters"]["ortho.tif"]["res_m"] / r["photo_gsd_m"]
        dsm = f"{r['dsm']['median_abs_error_gsd']:.3f}" if "dsm" in r else "-"
        g = f"{r['cloud']['open_ground_class_2_fraction']:.4f}" if "cloud" in r else "-"
        print(f"| {k} | {'/'.join(eps)} / {rb['cloud']['epsg']} | {cog} | {an} | {ratio:.3f} | "
              f"{rb['rasters']['ortho.tif']['nodata_inside_coverage']:.4%} | {dsm} | {g} | {r['seconds']} |")
    print("\n| survey | cloud points | DSM cells (anchor) | points / cell | points / m2 | cloud open-ground "
          "error cm | DSM open-ground error cm |")
    print("|---|---|---|---|---|---|---|")
    for k, r in res.items():
        print(cloud_row(k, r))
    if a.json:
        a.json.write_text(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main_())
