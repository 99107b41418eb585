"""The survey mode end to end (``prism3d survey``): a simulated flight (12 frames on two
lines, 70 % forward overlap) against its exact truth, the real drone pair, and the
refusals. The issue's figures at full size (12 MP from 100 m) are in docs/uav.md and
benchmarks/RESULTS.md; this flight is 800 x 600 px from 40 m (GSD 7 cm, DSM cells of
14 cm as at 12 MP from 100 m), checked against the same criteria in GSD except where
its coarser features set the limit (rotations)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from prism3d.cli import main
from prism3d.datasets.evaluation.survey_eval import evaluate_survey

SIZE = (800, 600)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight

    d = tmp_path_factory.mktemp("flight") / "f"
    simulate_flight(d, FlightOptions(size=SIZE, altitude_m=40.0, seed=5, targets=6))
    return d


@pytest.fixture(scope="module")
def survey(flight: Path, tmp_path_factory) -> Path:
    """The survey on one thread: COLMAP's multi-threaded mapping places frames a little
    differently run to run (measured: one run in three added a 0.66 "car" on this flight),
    and the tests below score exact outcomes; one thread is bit-reproducible."""
    out = tmp_path_factory.mktemp("survey") / "s"
    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PRISM3D_NUM_THREADS", "1")
        rc = main(["-q", "survey", *frames, "--calib", str(flight / "camera.yaml"), "--gps", str(flight / "geoinfo.txt"),
                   "-o", str(out)])
    assert rc == 0
    return out


def test_survey_writes_the_contract(survey: Path, flight: Path) -> None:
    import laspy

    from prism3d.geo import MapFrame, utm_epsg

    from prism3d.io.geo import read_geotiff
    from prism3d.io.ply import read_ply

    doc = json.loads((survey / "poses.json").read_text())
    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))
    assert [f["image"] for f in doc["frames"]] == frames  # paths as given
    T = np.array(doc["frames"][3]["T_enu_cam"])
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert T[2, 2] < -0.99  # a nadir camera: its z (forward) points down
    assert doc["scale"] == "gps" and 0 < doc["reprojection_rms_px"] < 0.5
    assert doc["camera"]["refined"] == []  # a calibration file is kept as it is
    frame = MapFrame.from_record(doc)
    assert frame.epsg == utm_epsg(*doc["origin_lla"][:2]) and doc["map_frame"]["epsg"] == frame.epsg
    ply = read_ply(survey / "cloud.ply")  # the local frame of poses.json
    las = laspy.read(survey / "cloud.las")  # the map frame
    assert len(las.x) == len(ply.points) > 10_000
    np.testing.assert_allclose(np.c_[las.x, las.y, las.z], frame.enu_to_map(ply.points), atol=0.0006)
    assert las.header.parse_crs().to_epsg() == frame.epsg
    assert set(np.unique(las.classification)) == {1, 2}
    assert ply.colors is not None
    dsm, meta = read_geotiff(survey / "dsm.tif")
    ndsm, _ = read_geotiff(survey / "ndsm.tif")
    ground, _ = read_geotiff(survey / "ground.tif")
    ortho, om = read_geotiff(survey / "ortho.tif")
    assert dsm.shape == ndsm.shape and ortho.shape[2] == 4
    np.testing.assert_allclose(ndsm, dsm - ground, atol=1e-4)
    # the orthophoto at the photographs' own GSD (finer than the DSM cell), over the same ground
    assert om["gsd"] == pytest.approx(0.07, rel=0.15) and om["gsd"] < meta["gsd"]
    assert om["west"] == pytest.approx(meta["west"], abs=meta["gsd"]) and om["north"] == pytest.approx(
        meta["north"], abs=meta["gsd"])
    assert ortho.shape[1] * om["gsd"] == pytest.approx(dsm.shape[1] * meta["gsd"], abs=2 * meta["gsd"])
    assert ortho.shape[0] * om["gsd"] == pytest.approx(dsm.shape[0] * meta["gsd"], abs=2 * meta["gsd"])
    assert meta["tags"]["SCALE"] == "gps" and meta["tags"]["VERTICAL_DATUM"] == "WGS84 ellipsoid"
    truth = json.loads((flight / "truth.json").read_text())
    assert om["gsd"] == pytest.approx(truth["gsd_m"], rel=0.10)
    # the cloud at the matching's density (several points per DSM cell), each point as close
    # to the true open ground as the fused DSM, and on the DSM up to the pairs' noise
    ev = evaluate_survey(survey, flight)
    assert doc["cloud"]["source"] == "matched pixels" and doc["cloud"]["points"] == len(ply.points)
    assert len(ply.points) > 3 * doc["dsm"]["filled_cells"]
    assert ev["cloud"]["open_ground_median_abs_error_m"] < 1.5 * ev["dsm"]["median_abs_error_m"]
    assert ev["cloud"]["open_ground_class_2_fraction"] >= 0.9
    q = frame.enu_to_map(ply.points)
    c = np.floor((q[:, 0] - meta["west"]) / meta["gsd"]).astype(int)
    r = np.floor((meta["north"] - q[:, 1]) / meta["gsd"]).astype(int)
    e = np.abs(dsm[r, c] - q[:, 2])
    e = e[np.isfinite(e)]
    assert len(e) > 0.95 * len(q) and np.median(e) < 0.05 and np.percentile(e, 90) < 0.3
    model = survey / "colmap"
    assert {"cameras.txt", "images.txt", "points3D.txt"} <= {p.name for p in model.iterdir()}
    pairs = doc["dense"]["pairs"]
    assert all(p["status"] == "ok" for p in pairs) and len(pairs) >= 21
    for p in pairs:
        assert (survey / p["depth_map"]).is_file()
    assert (survey / "survey.png").stat().st_size > 10_000


def test_survey_against_the_flight_truth(survey: Path, flight: Path) -> None:
    """Poses after a similarity alignment, the DSM on open ground, the overlapped area
    filled, the cloud's ground class, against exact truth: positions within 0.5 GSD; rotations within 0.05 deg
    (a pixel is 0.067 deg at 800 px; 12 MP: 0.003 deg against the issue's 0.02); the
    DSM within the issue's bounds (median <= 0.5 GSD, RMS <= 1 GSD), >= 95 % of the
    overlap filled; vehicles' heights in the nDSM within 10 % (12 MP: 7 of 8 within 5 %)."""
    from prism3d.datasets.evaluation.survey_eval import evaluate_survey

    r = evaluate_survey(survey, flight)
    assert r["frames_placed"] == 12
    assert r["position_error_gsd"]["max"] <= 0.5
    assert r["rotation_error_deg"]["max"] < 0.05
    assert r["dsm"]["median_abs_error_gsd"] <= 0.5
    assert r["dsm"]["rms_error_gsd"] <= 1.0
    assert r["dsm"]["overlap_filled_fraction"] >= 0.95
    v = r["vehicles"]
    assert v["measured"] == v["n"] >= 5
    cl = r["cloud"]  # the LAS classes: ground is class 2, vehicles are not
    assert cl["open_ground_points"] > 10_000 and cl["open_ground_class_2_fraction"] >= 0.9
    assert cl["vehicle_points"] > 500 and cl["vehicle_not_ground_fraction"] >= 0.9
    assert v["max_relative_height_error"] < 0.10
    doc = json.loads((survey / "poses.json").read_text())
    assert doc["dsm"]["overlap_filled_fraction"] >= 0.95  # the survey's own estimate agrees


def test_survey_detect_on_the_survey(survey: Path, flight: Path, tmp_path: Path) -> None:
    """survey-detect's defaults (car, van, truck, bus) on this field flight: a WGS84
    FeatureCollection at the site in which what is called a vehicle is one of its military
    trucks, called a truck, and nothing else is (its tanks are no class of the defaults).
    How many of its camouflaged trucks at 7 cm GSD are found is no claim of the car-park
    recogniser; Pd is scored on car parks in tests/atr/test_carpark_survey.py."""
    from prism3d.datasets.evaluation.survey_eval import evaluate_survey

    out = tmp_path / "d.geojson"
    assert main(["-q", "survey-detect", str(survey), "-o", str(out)]) == 0
    gj = json.loads(out.read_text())
    assert gj["type"] == "FeatureCollection" and sorted(gj["prism3d"]["classes"]) == ["bus", "car", "truck", "van"]
    truth = json.loads((flight / "truth.json").read_text())
    for f in gj["features"]:
        lon, lat = f["geometry"]["coordinates"]
        assert abs(lat - truth["origin_lla"][0]) < 0.01 and abs(lon - truth["origin_lla"][1]) < 0.01
        assert f["properties"]["score"] >= 0.5 and f["properties"]["footprint"]["type"] == "Polygon"
    n = len(truth["targets"])
    trucks = sum(t["class"] == "truck" for t in truth["targets"])
    at = evaluate_survey(survey, flight, detections=out, radius_m=1.6, threshold=0.5)["detection"]["at_threshold"]
    assert trucks >= 2 and 1 <= round(at["pd"] * n) <= trucks, at
    assert at["class_accuracy"] == 1.0 and at["fp_per_frame"] <= 0.1, at


def test_survey_with_dask_workers_agrees_with_the_survey_in_process(survey: Path, flight: Path, tmp_path: Path) -> None:
    """Three frames with the dense pairs on 2 local Dask workers, on the in-process
    survey's lattice: the same ground shape. The two are placed by different GPS fits
    (three frames on one line are levelled on their ground; twelve on two lines take a
    similarity), so their difference is a plane within GPS noise, removed first."""
    from prism3d.io.geo import read_geotiff

    ref, meta = read_geotiff(survey / "dsm.tif")
    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))[:3]
    out = tmp_path / "s"
    assert main(["-q", "survey", *frames, "--calib", str(flight / "camera.yaml"), "--gps", str(flight / "geoinfo.txt"),
                 "--workers", "2", "--no-cross-pairs", "--cell", str(meta["gsd"]), "-o", str(out)]) == 0
    d, m = read_geotiff(out / "dsm.tif")
    r0 = int(round((meta["north"] - m["north"]) / meta["gsd"]))
    c0 = int(round((m["west"] - meta["west"]) / meta["gsd"]))
    win = ref[r0:r0 + d.shape[0], c0:c0 + d.shape[1]]
    both = np.isfinite(win) & np.isfinite(d[:win.shape[0], :win.shape[1]])
    assert both.sum() > 0.5 * np.isfinite(d).sum()
    gsd = json.loads((flight / "truth.json").read_text())["gsd_m"]
    rr, cc = np.nonzero(both)
    diff = (win - d[:win.shape[0], :win.shape[1]])[both].astype(np.float64)
    A = np.c_[rr, cc, np.ones(len(rr))]
    plane, *_ = np.linalg.lstsq(A, diff, rcond=None)
    assert np.median(np.abs(diff - A @ plane)) < 0.5 * gsd
    assert np.abs(plane[:2]).max() * d.shape[0] < 2.0  # tilts within GPS noise over the area (m)


def assert_gis_products(survey: Path) -> int:
    """Read back as GDAL and PDAL users would (rasterio, rio-cogeo, laspy + pyproj): an
    EPSG code on every raster and the cloud, nodata or alpha set, valid Cloud-Optimised
    GeoTIFFs with overviews, heights in metres, no hole inside the orthophoto's coverage.
    Returns the EPSG code."""
    import laspy
    import rasterio
    from rio_cogeo.cogeo import cog_validate
    from scipy import ndimage

    doc = json.loads((survey / "poses.json").read_text())
    epsg = doc["map_frame"]["epsg"]
    for name in ("dsm.tif", "ground.tif", "ndsm.tif", "ortho.tif", "ortho_quality.tif"):
        ok, errors, _ = cog_validate(str(survey / name), quiet=True)
        assert ok, (name, errors)
        with rasterio.open(survey / name) as src:
            assert src.crs.to_epsg() == epsg, name
            assert src.overviews(1), name
            if name == "ortho.tif":
                assert src.colorinterp[3] == rasterio.enums.ColorInterp.alpha
                alpha = src.read(4) > 0
            else:
                assert src.nodata is not None, name
            if name in ("dsm.tif", "ground.tif", "ndsm.tif"):
                assert src.units[0] == "metre" and np.isnan(src.nodata)
    assert alpha.mean() > 0.3 and (ndimage.binary_fill_holes(alpha) == alpha).all()
    assert laspy.read(survey / "cloud.las").header.parse_crs().to_epsg() == epsg
    return epsg


def test_products_are_what_gis_tools_expect(survey: Path) -> None:
    assert assert_gis_products(survey) == 32654  # the simulated site, 139.04 E: UTM zone 54 N


def test_crs_choices_and_refusals(flight: Path, tmp_path: Path, capsys) -> None:
    """--crs enu keeps the local frame (the orthographic WKT at the origin), --laz writes a
    LASzip cloud, and off a terminal the survey says each stage as it starts; an unknown
    CRS, a geographic one, and a CRS asked of frames without GPS are one line and exit 2
    with nothing written."""
    import cv2
    import laspy
    import rasterio

    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))[:3]
    base = [*frames, "--calib", str(flight / "camera.yaml"), "--gps", str(flight / "geoinfo.txt"),
            "--pair-steps", "1", "--no-cross-pairs", "--ortho-gsd", "0.2"]
    capsys.readouterr()
    assert main(["survey", *base, "--crs", "enu", "--laz", "-o", str(tmp_path / "e")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [ln.split(" (")[0] for ln in err if ln.startswith("survey: ")] == [
        "survey: poses", "survey: dense pairs", "survey: fusion", "survey: products"]
    with rasterio.open(tmp_path / "e" / "dsm.tif") as src:
        assert src.crs.to_epsg() is None and "Orthographic" in src.crs.to_wkt()
    assert not (tmp_path / "e" / "cloud.las").exists()
    las = laspy.read(tmp_path / "e" / "cloud.laz")
    assert len(las.x) > 1000 and "Orthographic" in las.header.parse_crs().to_wkt()
    for bad in ("EPSG:4326", "EPSG:99999999", "mercator"):
        assert main(["-q", "survey", *base, "--crs", bad, "-o", str(tmp_path / "b")]) == 2
        assert not (tmp_path / "b").exists()
    plain = []
    for p in frames:  # re-encoded: no EXIF GPS
        q = tmp_path / Path(p).name
        cv2.imwrite(str(q), cv2.imread(p))
        plain.append(str(q))
    assert main(["-q", "survey", *plain, "--calib", str(flight / "camera.yaml"), "--crs", "utm",
                 "-o", str(tmp_path / "n")]) == 2
    assert not (tmp_path / "n").exists()


def test_without_gps_the_scale_is_unknown_everywhere(flight: Path, tmp_path: Path) -> None:
    """Frames without EXIF GPS and no table: the model levelled, its scale unknown."""
    import cv2
    import laspy

    from prism3d.io.geo import read_geotiff

    frames = []
    for p in sorted(flight.glob("IMG_*.JPG"))[:3]:  # re-encoded: no EXIF
        frames.append(str(tmp_path / p.name))
        cv2.imwrite(frames[-1], cv2.imread(str(p)), [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = tmp_path / "s"
    assert main(["-q", "survey", *frames, "--calib", str(flight / "camera.yaml"), "--no-cross-pairs",
                 "-o", str(out)]) == 0
    doc = json.loads((out / "poses.json").read_text())
    assert doc["scale"] == "unknown" and doc["origin_lla"] is None and "unknown" in doc["units"]
    _, meta = read_geotiff(out / "dsm.tif")
    assert meta["crs_wkt"] is None and meta["tags"]["SCALE"] == "unknown"
    assert "unknown" in laspy.read(out / "cloud.las").header.system_identifier
    assert main(["-q", "survey-detect", str(out), "-o", str(tmp_path / "d.geojson")]) == 2
    assert not (tmp_path / "d.geojson").exists()


@pytest.mark.parametrize("case", ["one_frame", "sizes", "missing_in_table", "no_overlap", "not_empty"])
def test_bad_input_is_one_line_exit_2_and_nothing_written(case: str, flight: Path, tmp_path: Path, capsys) -> None:
    import cv2

    frames = sorted(flight.glob("IMG_*.JPG"))
    args = [str(frames[0]), str(frames[1])]
    extra = ["--calib", str(flight / "camera.yaml")]
    out = tmp_path / "out"
    if case == "one_frame":
        args = args[:1]
    elif case == "sizes":
        small = tmp_path / "IMG_small.JPG"
        cv2.imwrite(str(small), cv2.resize(cv2.imread(str(frames[1])), (400, 300)))
        args = [str(frames[0]), str(small)]
    elif case == "missing_in_table":
        d = tmp_path / "frames"
        d.mkdir()
        for f in frames[:2]:
            shutil.copy(f, d / f.name)
        shutil.copy(flight / "geoinfo.txt", d / "geoinfo.txt")  # names 12 frames, 2 are here
        args = [str(d / frames[0].name), str(d / frames[1].name)]
        extra += ["--gps", str(d / "geoinfo.txt")]
    elif case == "no_overlap":
        rng = np.random.default_rng(0)
        noise = tmp_path / "IMG_noise.JPG"
        cv2.imwrite(str(noise), (rng.random((SIZE[1], SIZE[0], 3)) * 255).astype(np.uint8))
        args = [str(frames[0]), str(noise)]
    elif case == "not_empty":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
    capsys.readouterr()
    rc = main(["survey", *args, *extra, "-o", str(out)])
    # the stage lines the survey had said before it failed (no overlap is found in the
    # poses stage), then the error: one line
    err = "\n".join(ln for ln in capsys.readouterr().err.strip().splitlines() if not ln.startswith("survey: "))
    assert rc == 2
    assert len(err.splitlines()) == 1 and err.startswith("prism3d survey: error:")
    want = {"one_frame": "at least 2", "sizes": "different sizes", "missing_in_table": "not in",
            "no_overlap": "could not be placed", "not_empty": "not an empty folder"}[case]
    assert want in err
    if case == "not_empty":
        assert [p.name for p in out.iterdir()] == ["keep.txt"]
    else:
        assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]  # no staging left behind


@pytest.mark.realdata
def test_real_drone_pair(shared_data: Path, tmp_path: Path) -> None:
    """IMG_2188 -> IMG_2189 (real nadir frames, EXIF focal, geoinfo.txt GPS):
    reprojection RMS <= 0.5 px over >= 1000 tracks; a DSM over >= 80 % of the pair's
    overlap; open ground flat to a few GSD; the poses' baseline equal to the GPS one."""
    from prism3d.capture.geotag import read_position_table
    from prism3d.datasets.evaluation.survey_eval import ground_roughness
    from prism3d.geo import wgs84_to_enu
    from prism3d.io.geo import read_geotiff

    d = shared_data / "aerial/snowpeak_internal_only"
    out = tmp_path / "s"
    assert main(["-q", "survey", str(d / "IMG_2188.JPG"), str(d / "IMG_2189.JPG"), "--gps", str(d / "geoinfo.txt"),
                 "-o", str(out)]) == 0
    doc = json.loads((out / "poses.json").read_text())
    assert doc["reprojection_rms_px"] <= 0.5 and doc["n_sparse_points"] >= 1000
    assert doc["camera"]["refined"] == ["f", "k1", "k2"]
    # the camera model compared on held-back matches: RADIAL kept (a free principal point does
    # not help; OPENCV's fit has non-square pixels, fx / fy 0.86, and is refused)
    ch = doc["camera"]["choice"]
    assert ch["chosen"] == "RADIAL" and len(ch["candidates"]) == 3 and ch["held_back_points"] >= 200
    assert all(c["held_out_rms_px"] < 1.0 for c in ch["candidates"])
    assert doc["dsm"]["overlap_filled_fraction"] >= 0.8
    tags = read_position_table(d / "geoinfo.txt")
    a, b = tags["IMG_2188.JPG"], tags["IMG_2189.JPG"]
    gps = float(np.linalg.norm(wgs84_to_enu([[b.lat_deg, b.lon_deg, b.alt_m]], [a.lat_deg, a.lon_deg, a.alt_m])))
    T = [np.array(f["T_enu_cam"]) for f in doc["frames"]]
    assert np.linalg.norm(T[1][:3, 3] - T[0][:3, 3]) == pytest.approx(gps, abs=0.05)
    dsm, meta = read_geotiff(out / "dsm.tif")
    ndsm, _ = read_geotiff(out / "ndsm.tif")
    gsd = 117.0 / 3210.0  # the frames' ground sample distance at full size, m
    rough = ground_roughness(dsm, ndsm, meta["gsd"])
    assert rough["patches"] > 100 and rough["median_rms_m"] < 3 * gsd
    assert assert_gis_products(out) == 32654  # Japan, 138.5 E: UTM zone 54 N
    _, om = read_geotiff(out / "ortho_quality.tif")
    assert om["gsd"] == pytest.approx(gsd, rel=0.10)  # the photographs' own GSD


def test_a_video_is_sampled_into_frames(flight: Path, tmp_path: Path) -> None:
    """One video in: its frames every --video-step seconds into OUT/frames/, surveyed
    (no GPS in a video: the scale is unknown)."""
    import cv2

    frames = sorted(flight.glob("IMG_*.JPG"))[:4]
    video = tmp_path / "flight.avi"
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 2.0, SIZE)
    for f in frames:  # 2 fps, each frame twice: one a second
        img = cv2.imread(str(f))
        vw.write(img)
        vw.write(img)
    vw.release()
    out = tmp_path / "s"
    assert main(["-q", "survey", str(video), "--calib", str(flight / "camera.yaml"), "--no-cross-pairs",
                 "-o", str(out)]) == 0
    doc = json.loads((out / "poses.json").read_text())
    assert len(doc["frames"]) == 4 and doc["scale"] == "unknown"
    for f in doc["frames"]:
        assert Path(f["image"]).parent == out / "frames" and Path(f["image"]).is_file()
    assert main(["-q", "survey", str(video), str(frames[0]), "-o", str(tmp_path / "t")]) == 2


def test_a_killed_survey_resumes_with_identical_products(survey: Path, flight: Path, tmp_path: Path) -> None:
    """kill -9 in the dense stage (two pairs finished), then the same command with
    --resume: it keeps the poses and the finished pairs, finishes, leaves no staging or
    resume folder, and its products equal those of the uninterrupted survey (one thread:
    bit-reproducible) to the bit."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from prism3d.io.geo import read_geotiff

    frames = sorted(str(p) for p in flight.glob("IMG_*.JPG"))
    out = tmp_path / "s"
    cmd = [sys.executable, "-m", "prism3d.cli", "-q", "survey", *frames, "--calib", str(flight / "camera.yaml"),
           "--gps", str(flight / "geoinfo.txt"), "-o", str(out)]
    env = dict(os.environ, PRISM3D_NUM_THREADS="1")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    pairs = tmp_path / ".s.resume" / "pairs"
    t0 = time.monotonic()
    def finished() -> int:  # pathlib's glob also matches the hidden temporary file of a pair being written
        return sum(not p.name.startswith(".") for p in pairs.glob("*.npz"))

    while finished() < 2 and proc.poll() is None and time.monotonic() - t0 < 300:
        time.sleep(0.05)
    assert proc.poll() is None, "the survey ended before two pairs were done"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not out.exists()
    r = subprocess.run([*cmd, "--resume"], env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "poses.json").read_text())
    assert doc["resumed"]["poses"] and doc["resumed"]["pairs_reused"] >= 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]  # no lock, staging or resume folder left
    for name in ("dsm.tif", "ndsm.tif", "ortho.tif"):
        a, _ = read_geotiff(survey / name)
        b, _ = read_geotiff(out / name)
        np.testing.assert_array_equal(a, b)
    # without --resume, leftovers of another run are removed and the survey starts again
    (tmp_path / ".t.resume" / "pairs").mkdir(parents=True)
    (tmp_path / ".t.resume" / "pairs" / "0_1.npz").write_bytes(b"stale")
    assert main(["-q", "survey", *frames[:3], "--calib", str(flight / "camera.yaml"), "--gps",
                 str(flight / "geoinfo.txt"), "--pair-steps", "1", "--no-cross-pairs", "-o", str(tmp_path / "t")]) == 0
    assert not (tmp_path / ".t.resume").exists()
