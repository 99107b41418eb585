"""The virtual drone survey (``simulate flight``): files in the formats the survey mode
reads, GPS and overlap as asked, and the truth exact and consistent across frames, the
DSM and the terrain; bad input refused before anything is written."""

from __future__ import annotations

import json

import numpy as np
import pytest

from prism3d.errors import InputError

SMALL = dict(frames=6, lines=2, size=(640, 480), targets=4, confusers=1, seed=5)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight

    out = tmp_path_factory.mktemp("flight") / "survey"
    opts = FlightOptions(**SMALL)
    summary = simulate_flight(out, opts)
    truth = json.loads((out / "truth.json").read_text())
    with np.load(out / "truth.npz") as z:
        grid = {k: z[k] for k in z.files}
    return out, opts, summary, truth, grid


def _depth(out, k):
    with np.load(out / "depth" / f"IMG_{k:04d}.npz") as z:
        return z["depth_m"], z["object_id"]


def _camera(truth):
    from prism3d.capture.rig import CameraModel

    return CameraModel(np.array(truth["K"]), np.array(truth["dist"]), tuple(truth["size"]))


def _back_project(truth, k, uv, depth):
    """World points (ENU m) of pixels ``uv`` at z-depths ``depth`` in frame ``k``."""
    cam = _camera(truth)
    T = np.array(truth["frames"][k]["T_enu_cam"])
    rays = cam.pixel_rays(uv)
    pc = rays / rays[:, 2:3] * depth[:, None]
    return pc @ T[:3, :3].T + T[:3, 3]


def _project(truth, k, pts):
    """Pixels and camera z of world points in frame ``k``."""
    T = np.array(truth["frames"][k]["T_enu_cam"])
    pc = (pts - T[:3, 3]) @ T[:3, :3]
    return _camera(truth).project(pc), pc[:, 2]


def _ground_samples(out, truth, k, step=7):
    """Pixels of frame ``k`` on open ground or road (every ``step``-th) and their depths."""
    depth, ids = _depth(out, k)
    v, u = np.mgrid[3:depth.shape[0] - 3:step, 3:depth.shape[1] - 3:step]
    u, v = u.ravel(), v.ravel()
    keep = ids[v, u] <= 1
    keep &= ids[v, u] >= 0
    return np.stack([u[keep], v[keep]], axis=1).astype(np.float64), depth[v[keep], u[keep]].astype(np.float64)


def _bilinear(img, uv):
    """Bilinear samples of ``img`` at pixels ``uv`` (pixel centres at integers)."""
    u0 = np.floor(uv[:, 0]).astype(int)
    v0 = np.floor(uv[:, 1]).astype(int)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    return ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u0 + 1]
            + (1 - fu) * fv * img[v0 + 1, u0] + fu * fv * img[v0 + 1, u0 + 1])


def test_the_folder_holds_what_the_survey_mode_reads(flight):
    import cv2

    from prism3d.capture.geotag import exif_focal_px, exif_geotag, read_position_table
    from prism3d.geo import wgs84_to_enu

    out, opts, summary, truth, _ = flight
    names = [f"IMG_{k:04d}.JPG" for k in range(6)]
    assert sorted(summary["files"]) == sorted(
        names + [f"depth/{n[:-4]}.npz" for n in names] + ["camera.yaml", "geoinfo.txt", "truth.json", "truth.npz"])
    assert summary["n_frames"] == 6 and summary["n_targets"] == 4
    lines = (out / "geoinfo.txt").read_text().splitlines()
    assert lines[0] == "#Rev: sensefly/geoinfo/2"
    assert lines[1].split("\t") == ["fileName", "latitude", "longitude", "altitude_amsl", "altitude_wgs84", "heading",
                                    "pitch", "roll"]
    assert all(ln.endswith("\t") and ln.count("\t") == 8 for ln in lines[2:])
    table = read_position_table(out / "geoinfo.txt", images_dir=out)
    assert list(table) == names
    lla = np.array([[table[n].lat_deg, table[n].lon_deg, table[n].alt_m] for n in names])
    enu = wgs84_to_enu(lla, np.array(truth["origin_lla"]))
    np.testing.assert_allclose(enu, [f["gps_enu"] for f in truth["frames"]], atol=1e-3)
    np.testing.assert_allclose([table[n].heading_deg for n in names], [f["heading_deg"] for f in truth["frames"]],
                               atol=1e-6)
    tag = exif_geotag(out / names[0])
    assert tag.lat_deg == pytest.approx(table[names[0]].lat_deg, abs=1e-7)
    assert tag.alt_m == pytest.approx(table[names[0]].alt_m, abs=1e-3)
    assert exif_focal_px(out / names[0]) == pytest.approx(truth["K"][0][0], rel=1e-4)
    img = cv2.imread(str(out / names[0]))  # BGR
    assert img.shape == (480, 640, 3)
    assert img[..., 1].mean() > img[..., 0].mean() + 10  # grass: green over blue, so RGB was written as RGB
    fs = cv2.FileStorage(str(out / "camera.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), truth["K"])
    np.testing.assert_allclose(fs.getNode("distortion_coefficients").mat().ravel(), truth["dist"])
    assert int(fs.getNode("image_width").real()) == 640 and int(fs.getNode("image_height").real()) == 480
    fs.release()
    assert truth["schema_version"] == 1 and truth["units"] == "m"


def test_the_camera_looks_down_and_flies_along_the_image_up_axis(flight):
    _, opts, _, truth, grid = flight
    frames = truth["frames"]
    assert [f["line"] for f in frames] == [0, 0, 0, 1, 1, 1]
    for a, b in ((0, 1), (1, 2), (3, 4), (4, 5)):
        Ta, Tb = np.array(frames[a]["T_enu_cam"]), np.array(frames[b]["T_enu_cam"])
        assert Ta[2, 2] < -0.99  # optical axis down
        move = (Tb[:3, 3] - Ta[:3, 3])[:2]
        up = -Ta[:2, 1]  # the image's up axis on the ground
        assert move @ up / np.linalg.norm(move) / np.linalg.norm(up) > 0.98
    c = [np.array(f["T_enu_cam"])[:3, 3] for f in frames]
    assert np.dot(c[1] - c[0], c[4] - c[3]) < 0  # the second line flown the other way
    ground = np.nanmean(grid["ground"])
    assert np.mean([p[2] for p in c]) - ground == pytest.approx(opts.altitude_m, abs=2.0)


def test_gps_is_the_true_position_plus_noise_of_the_stated_size(flight):
    _, opts, _, truth, _ = flight
    err = np.array([np.array(f["gps_enu"]) - np.array(f["T_enu_cam"])[:3, 3] for f in truth["frames"]])
    sh, sv = opts.gps_sigma_m
    assert np.all(np.abs(err[:, :2]) < 4.5 * sh) and np.all(np.abs(err[:, 2]) < 4.5 * sv)
    assert np.any(np.abs(err) > 0.01)  # noisy, not the truth


def test_neighbouring_frames_overlap_as_asked(flight):
    out, opts, _, truth, _ = flight

    def shared(a, b):
        uv, d = _ground_samples(out, truth, a)
        q, z = _project(truth, b, _back_project(truth, a, uv, d))
        inside = (z > 0) & (q[:, 0] >= -0.5) & (q[:, 0] <= 639.5) & (q[:, 1] >= -0.5) & (q[:, 1] <= 479.5)
        return inside.mean()

    # attitude jitter (1-2 deg at 100 m) and the hills move each pair's overlap by a few %
    forward = [shared(a, b) for a, b in ((0, 1), (1, 2), (3, 4), (4, 5))]
    assert np.mean(forward) == pytest.approx(opts.overlap, abs=0.04)
    assert np.all(np.abs(np.array(forward) - opts.overlap) < 0.1)
    side = [shared(a, b) for a, b in ((0, 5), (1, 4), (2, 3))]  # the frames abreast on the two lines
    assert np.mean(side) == pytest.approx(opts.side_overlap, abs=0.06)


def test_depth_lands_on_the_terrain_and_the_dsm(flight):
    from prism3d.datasets.simulation.flight import plan_flight

    out, opts, _, truth, grid = flight
    land = plan_flight(opts).land  # the same seed plans the same terrain
    cell, west, north = float(grid["cell_m"]), float(grid["west"]), float(grid["north"])
    for k in (0, 4):
        uv, d = _ground_samples(out, truth, k)
        p = _back_project(truth, k, uv, d)
        assert np.abs(p[:, 2] - land.height_at(p[:, 0], p[:, 1])).max() < 1e-4  # exact: 0.1 mm
        # the DSM between the four cell centres around the point, where all four are open ground
        cu, cv = (p[:, 0] - west) / cell - 0.5, (north - p[:, 1]) / cell - 0.5
        c0, r0 = np.floor(cu).astype(int), np.floor(cv).astype(int)
        ok = (c0 >= 0) & (r0 >= 0) & (c0 < grid["dsm"].shape[1] - 1) & (r0 < grid["dsm"].shape[0] - 1)
        c0, r0, cu, cv, p = c0[ok], r0[ok], cu[ok], cv[ok], p[ok]
        oid = grid["object_id"]
        ground = (oid[r0, c0] <= 1) & (oid[r0 + 1, c0] <= 1) & (oid[r0, c0 + 1] <= 1) & (oid[r0 + 1, c0 + 1] <= 1)
        assert ground.mean() > 0.8
        z = _bilinear(grid["dsm"].astype(np.float64), np.stack([cu, cv], axis=1)[ground])
        dz = np.abs(z - p[ground, 2])
        assert np.median(dz) < 0.0005 and np.percentile(dz, 99) < 0.01  # bilinear across the mesh's kinks
    on_ground = grid["object_id"] <= 1
    assert np.abs(grid["dsm"][on_ground] - grid["ground"][on_ground]).max() < 1e-4
    assert np.all(grid["dsm"] >= grid["ground"] - 0.2)  # objects stand on the ground, never under it


def test_frames_agree_with_each_other_through_their_depth(flight):
    out, _, _, truth, _ = flight
    for a, b in ((0, 1), (4, 3), (1, 4)):
        uv, d = _ground_samples(out, truth, a, step=5)
        q, z = _project(truth, b, _back_project(truth, a, uv, d))
        inside = (q[:, 0] >= 0) & (q[:, 0] < 638) & (q[:, 1] >= 0) & (q[:, 1] < 478)
        q, z = q[inside], z[inside]
        depth_b, ids_b = _depth(out, b)
        u0, v0 = np.floor(q[:, 0]).astype(int), np.floor(q[:, 1]).astype(int)
        open_b = np.ones(len(q), dtype=bool)
        for dv in (0, 1):
            for du in (0, 1):
                ids = ids_b[v0 + dv, u0 + du]
                open_b &= (ids >= 0) & (ids <= 1)
        dz = np.abs(_bilinear(depth_b.astype(np.float64), q[open_b]) - z[open_b])
        assert open_b.sum() > 1000
        assert np.median(dz) < 0.0005 and np.percentile(dz, 95) < 0.002  # float32 depth, bilinear


def test_targets_stand_on_the_ground_inside_the_dsm_with_their_heights(flight):
    out, _, _, truth, grid = flight
    cell, west, north = float(grid["cell_m"]), float(grid["west"]), float(grid["north"])
    h, w = grid["dsm"].shape
    ndsm = grid["dsm"] - grid["ground"]
    objects = {o["id"]: o for o in truth["objects"]}
    assert objects[0]["kind"] == "ground" and objects[1]["kind"] == "road"
    assert (grid["object_id"] == 1).any()  # roads cross the area
    seen = 0
    for t in truth["targets"]:
        assert objects[t["id"]]["kind"] == ("confuser" if t["confuser"] else "target")
        assert t["class"] in ("tank", "truck", "crate", "fuel_tank")
        x, y, z = t["xyz_enu"]
        c, r = int((x - west) / cell), int((north - y) / cell)
        assert 0 <= r < h and 0 <= c < w
        at = np.array([[(x - west) / cell - 0.5, (north - y) / cell - 0.5]])
        g = _bilinear(grid["ground"].astype(np.float64), at)
        assert -0.25 < z - g[0] < 0.01  # standing: the base touches the ground, never floats
        assert grid["object_id"][r, c] == t["id"]
        mine = grid["object_id"] == t["id"]
        # the highest point: a tank's turret roof is not at its footprint centre
        assert float(ndsm[mine].max()) == pytest.approx(t["height_m"], rel=0.10)
        # a tank's gun is thin; cells on the outline (0.44 m here) add up to ~20 %
        assert 0.5 < mine.sum() * cell**2 / (t["length_m"] * t["width_m"]) < 1.3
        for k in t["frames"]:
            assert t["visible_fraction"][str(k)] >= 0.98
            assert (_depth(out, k)[1] == t["id"]).any()
        seen += len(t["frames"]) >= 2
    assert seen >= len(truth["targets"]) // 2


def test_bad_options_are_refused_and_nothing_is_written(tmp_path):
    from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight

    for kw, msg in (({"frames": 1}, "frames"), ({"lines": 0}, "lines"), ({"frames": 7, "lines": 2}, "multiple"),
                    ({"frames": 4, "lines": 4}, "at least 2"), ({"overlap": 0.95}, "overlap"),
                    ({"overlap": 0.0}, "overlap"), ({"side_overlap": 1.0}, "side_overlap"),
                    ({"altitude_m": 5.0}, "altitude_m"), ({"altitude_m": 2000.0}, "altitude_m"),
                    ({"size": (32, 24)}, "size"), ({"size": (12001, 9000)}, "size"), ({"size": (640.5, 480)}, "size"),
                    ({"targets": -1}, "targets"), ({"seed": -1}, "seed"), ({"dist": (0.1, 0.0)}, "dist"),
                    ({"gps_sigma_m": (0.3,)}, "gps_sigma_m")):
        with pytest.raises(InputError, match=msg):
            FlightOptions(**kw)
    out = tmp_path / "out"
    with pytest.raises(InputError, match="coarser cell"):
        simulate_flight(out, FlightOptions(**{**SMALL, "dsm_cell_m": 0.005, "altitude_m": 1000.0}))
    assert not out.exists()
    (out / "keep").mkdir(parents=True)
    with pytest.raises(InputError, match="not empty"):
        simulate_flight(out, FlightOptions(**SMALL))
    assert [p.name for p in out.iterdir()] == ["keep"]
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        simulate_flight(f, FlightOptions(**SMALL))
    assert f.read_text() == "x"
    with pytest.raises(InputError, match="options"):
        simulate_flight(tmp_path / "o2", {"frames": 4})


def test_the_cli_flies_a_survey_and_refuses_bad_options(tmp_path, capsys):
    from prism3d.cli import main

    out = tmp_path / "fl"
    assert main(["-q", "simulate", "flight", str(out), "--frames", "4", "--lines", "1", "--size", "320x240",
                 "--targets", "2", "--confusers", "0", "--seed", "3", "--no-noise", "--no-depth",
                 "--overlap", "0.6", "--altitude", "80"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["IMG_0000.JPG", "IMG_0001.JPG", "IMG_0002.JPG", "IMG_0003.JPG",
                                                     "camera.yaml", "geoinfo.txt", "truth.json", "truth.npz"]
    doc = json.loads((out / "truth.json").read_text())
    assert doc["options"]["overlap"] == 0.6 and doc["options"]["size"] == [320, 240] and len(doc["targets"]) == 2
    for args, msg in ((["--overlap", "0.99"], "overlap"), (["--size", "big"], "--size"), (["--frames", "5"], "frames"),
                      (["--count", "2"], "unrecognized arguments: --count"), (["--jpeg-quality", "500"], "unrecognized")):
        bad = tmp_path / "bad"
        try:
            rc = main(["-q", "simulate", "flight", str(bad), "--size", "320x240", *args])
        except SystemExit as exc:  # argparse refuses an option flights do not have
            rc = exc.code
        assert rc == 2
        assert msg in capsys.readouterr().err
        assert not bad.exists()
