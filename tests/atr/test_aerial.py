"""The aerial recogniser: composed training patches with exact truth, per-cell features that
follow a heading, a small recogniser trained and searched on patches it never saw
(vehicles side by side found one by one, at their heading), and its file."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prism3d.atr.aerial import AerialModel
from prism3d.atr.aerial_features import cell_features, feature_names, rotate_scene
from prism3d.atr.aerial_scenes import PatchSpec, compose_patch
from prism3d.atr.aerial_train import (
    GROUP_LENGTH_RATIO,
    AerialTrainOptions,
    _cut,
    _window_cells,
    train_aerial,
    window_groups,
)
from prism3d.capture.nadir import render_nadir
from prism3d.datasets.models.targets import builtin_target
from prism3d.datasets.simulation.carpark import person_mesh
from prism3d.datasets.simulation.field import prop_mesh
from prism3d.errors import InputError

GSD = 0.08
OPTIONS = AerialTrainOptions(gsd_m=GSD, cell_px=6, patches=10, mining_rounds=1, mining_patches=4,
                             calibration_patches=6, random_negatives=30, seed=3,
                             patch=PatchSpec(size_m=32.0, missing_dsm_share=0.0))


def _items():
    rng = np.random.default_rng(0)
    targets = [("car", builtin_target(n, scale="full")) for n in ("car_sedan", "car_kei", "car_suv")]
    targets.append(("bus", builtin_target("bus_city", scale="full")))
    negatives = [("tree", prop_mesh("tree", rng, 1)), ("bush", prop_mesh("bush", rng, 2)),
                 ("person", person_mesh(rng)), ("vehicle:tank", builtin_target("tank_t2", scale="full"))]
    return targets, negatives


@pytest.fixture(scope="module")
def model() -> AerialModel:
    return train_aerial(*_items(), OPTIONS)


def test_patches_hold_their_truth() -> None:
    targets, negatives = _items()
    tsp = [(c, render_nadir(m, GSD)) for c, m in targets]
    nsp = [(c, render_nadir(m, GSD)) for c, m in negatives]
    p = compose_patch(np.random.default_rng(5), tsp, nsp, PatchSpec(gsd_m=GSD, size_m=32.0, carpark_share=1.0,
                                                                   missing_dsm_share=0.0, hole_share=(0.0, 0.0),
                                                                   dark_hole_share=(0.0, 0.0)))
    n = p.rgb.shape[0]
    assert p.rgb.shape == (n, n, 3) and n == 400 and p.vehicles
    checked = 0
    for v in p.vehicles:
        r, c = int(round(v["row"])), int(round(v["col"]))
        if v["visible"] > 0.9 and 5 < r < n - 5 and 5 < c < n - 5:
            # a vehicle stands its height over its centre (the roof, give or take the DSM's cell;
            # the emulated DSM's random blobs may leave some of it without a height)
            around = p.ndsm[r - 2:r + 3, c - 2:c + 3]
            if np.isfinite(around).any():
                checked += 1
                assert np.nanmax(around) > 0.6 * v["height_m"]
    assert checked >= len(p.vehicles) // 2
    assert {v["cls"] for v in p.vehicles} <= {"car", "bus"}


def test_a_street_patch_holds_vehicles_in_its_lanes() -> None:
    """Streets: every vehicle lies along the one street direction (either way), none of
    them is an aircraft, the lanes' markings are painted, and each vehicle's footprint
    overlaps no other's."""
    targets, negatives = _items()
    negatives = negatives + [("vehicle:jet", builtin_target("jet_j1", scale="full"))]
    tsp = [(c, render_nadir(m, GSD)) for c, m in targets]
    nsp = [(c, render_nadir(m, GSD)) for c, m in negatives]
    spec = PatchSpec(gsd_m=GSD, size_m=32.0, carpark_share=0.0, road_share=1.0, missing_dsm_share=0.0)
    for seed in range(4):
        p = compose_patch(np.random.default_rng(seed), tsp, nsp, spec)
        others = [o for o in p.clutter if o["kind"].startswith("vehicle:")]
        assert all(o["kind"] == "vehicle:tank" for o in others)  # a jet's wings span more than a lane
        along = [v["heading_rad"] % math.pi for v in p.vehicles] + [o["heading_rad"] % math.pi for o in others]
        assert len(along) >= 2
        ref = along[0]
        assert all(min(abs(a - ref), math.pi - abs(a - ref)) < math.radians(10.0) for a in along)
        cars = p.vehicles + others
        for i, a in enumerate(cars):  # queued, never stacked: centres at least a width apart
            for b in cars[i + 1:]:
                assert math.hypot(a["row"] - b["row"], a["col"] - b["col"]) * GSD > 1.4


def test_a_camera_curve_lifts_dark_ground_to_mid_grey() -> None:
    """A patch seen as a JPEG shows it is metered and sRGB-encoded: its median grey sits
    near the middle of the scale, where the linear patch's dark asphalt sits near black."""
    targets, negatives = _items()
    tsp = [(c, render_nadir(m, GSD)) for c, m in targets]
    nsp = [(c, render_nadir(m, GSD)) for c, m in negatives]
    med = {}
    for tone in (0.0, 1.0):
        spec = PatchSpec(gsd_m=GSD, size_m=32.0, carpark_share=1.0, tone_share=tone, missing_dsm_share=0.0)
        med[tone] = [float(np.median(compose_patch(np.random.default_rng(s), tsp, nsp, spec).rgb.mean(axis=2)))
                     for s in range(6)]
    # metering puts the median at 10-25 % of full scale before the curve: 0.35-0.54 after it
    assert all(0.3 < m < 0.6 for m in med[1.0]), med
    assert np.median(med[0.0]) < 0.3, med


def test_features_turn_with_the_scene() -> None:
    rng = np.random.default_rng(1)
    grey = np.zeros((240, 240), np.float32)
    grey[100:140, 60:180] = 1.0  # a bright bar along x
    z = np.zeros_like(grey)
    z[100:140, 60:180] = 1.5
    along = cell_features(*rotate_scene(grey, z, 0.0)[:2], 8)
    across = cell_features(*rotate_scene(grey, z, math.pi / 2)[:2], 8)
    names = feature_names("both")
    hog = [names.index(f"hog{k}") for k in range(9)]
    # the bar's long edges are horizontal when it lies along x: the vertical-gradient bin (90 deg) leads
    assert np.argmax(along[..., hog].sum(axis=(0, 1))) == 4
    assert np.argmax(across[..., hog].sum(axis=(0, 1))) in (0, 8)
    assert along[..., names.index("h_max")].max() == pytest.approx(0.75)  # 1.5 m / 2
    del rng


def test_a_black_car_beside_a_painted_line_keeps_its_edges() -> None:
    """Grey levels from the survey simulator: asphalt 0.14, a painted line 0.8, a body
    0.04 (black) or 0.8 (white). Next to the line, the car's long edge (gradient across,
    90 deg bin) must hold at least half as much of its cell's normalised histogram for
    the black car as for the white one: an edge counts by its brightness ratio (by the
    grey levels' difference, the line would leave the black car's edge a fifth)."""
    names = feature_names("appearance")
    share = {}
    for body in (0.04, 0.8):
        grey = np.full((160, 160), 0.14, np.float32)
        grey[64:96, 16:144] = body  # the car, along x; its top edge at row 64
        grey[56:59, 16:144] = 0.8  # a bay line along it, in the cell above
        f = cell_features(grey, np.full_like(grey, np.nan), 8, "appearance")
        cell = f[64 // 8, 10]  # the cell holding the car's top edge (row 64 starts it)
        share[body] = cell[names.index("hog4")]
    assert share[0.04] >= 0.5 * share[0.8], share


def test_groups_by_length() -> None:
    targets, _ = _items()
    groups = window_groups([(c, render_nadir(m, 0.2)) for c, m in targets])
    lengths = [[sp.length_m for _, sp in g] for g in groups]
    assert sum(map(len, lengths)) == len(targets)
    for i, ls in enumerate(lengths):
        assert max(ls) <= GROUP_LENGTH_RATIO * min(ls) + 1e-9  # a window fits each of its vehicles
        if i:  # shortest first; the next group starts where the last could not stretch
            assert min(ls) > GROUP_LENGTH_RATIO * min(lengths[i - 1])
    assert {c for c, _ in groups[-1]} == {"bus"} and all("bus" not in {c for c, _ in g} for g in groups[:-1])


def test_a_scarce_group_sees_its_vehicles_at_more_headings() -> None:
    """A rare long vehicle gets more positive windows, each centred on it (its roof height
    in the window's middle), while the well-stocked cars keep theirs."""
    targets, negatives = _items()
    tsp = [(c, render_nadir(m, GSD)) for c, m in targets]
    nsp = [(c, render_nadir(m, GSD)) for c, m in negatives]
    spec = PatchSpec(gsd_m=GSD, size_m=32.0, carpark_share=1.0, missing_dsm_share=0.0, hole_share=(0.0, 0.0),
                     dark_hole_share=(0.0, 0.0))
    patches = [compose_patch(np.random.default_rng(40 + k), tsp, nsp, spec) for k in range(4)]
    groups = window_groups(tsp)
    cells = [_window_cells(g, GSD * OPTIONS.cell_px) for g in groups]
    counts = {}
    for views in (0, 4):
        o = AerialTrainOptions(**{**OPTIONS.__dict__, "positive_views": views})
        samples = _cut(patches, groups, cells, o, np.random.default_rng(0))
        # the share of the bus windows with its roof in their middle cell (a bus cut by the
        # patch's edge may show none), the same for the first views and the extra ones
        names = feature_names(o.channels)
        mids = [np.asarray(x).reshape(cells[-1][0], cells[-1][1], len(names))[
            cells[-1][0] // 2, cells[-1][1] // 2, names.index("h_max")] * 2.0  # stored as m / 2
            for x, y in zip(samples[-1].X, samples[-1].y) if y]
        counts[views] = [int(sum(s.y)) for s in samples] + [float(np.mean(np.array(mids) > 0.5 * 3.2))]
    assert counts[0][-2] >= 2, counts  # the patches hold buses
    assert counts[4][-2] >= 4 * counts[0][-2], counts
    assert counts[4][-1] >= counts[0][-1] - 0.05 and counts[4][-1] >= 0.7, counts
    best = int(np.argmax(counts[0][:-1]))
    assert counts[4][best] == counts[0][best], counts


def test_finds_each_vehicle_of_a_row_at_its_heading(model: AerialModel) -> None:
    targets, negatives = _items()
    tsp = [(c, render_nadir(m, GSD)) for c, m in targets]
    nsp = [(c, render_nadir(m, GSD)) for c, m in negatives]
    found = total = fp = right = 0
    inner = lambda r, c: 40 < r < 360 and 40 < c < 360
    for seed in (101, 102, 103, 104, 105):
        p = compose_patch(np.random.default_rng(seed), tsp, nsp, PatchSpec(gsd_m=GSD, size_m=32.0,
                                                                           missing_dsm_share=0.0))
        dets = [d for d in model.detect(p.rgb.mean(axis=2), p.ndsm) if d.score >= 0.5]
        used = set()
        for d in dets:
            best = None
            for k, v in enumerate(p.vehicles):
                if k not in used and math.hypot(d.row - v["row"], d.col - v["col"]) * GSD <= 1.2:
                    best = k
                    break
            if best is None:
                fp += inner(d.row, d.col)
                continue
            used.add(best)
            v = p.vehicles[best]
            dh = abs(d.heading_rad - v["heading_rad"]) % math.pi
            assert min(dh, math.pi - dh) <= math.radians(20.0)
            right += inner(v["row"], v["col"]) and v["visible"] >= 0.8 and d.class_name == v["cls"]
        vis = {k for k, v in enumerate(p.vehicles) if v["visible"] >= 0.8 and inner(v["row"], v["col"])}
        total += len(vis)
        found += len(vis & used)
    assert total >= 30, total
    assert found / total >= 0.8 and fp <= 0.2 * total and right >= 0.9 * found, (found, total, fp, right)


def test_model_file_round_trip_and_refusals(model: AerialModel, tmp_path) -> None:
    p = model.save(tmp_path / "m.npz")
    back = AerialModel.load(p)
    assert back.classes == model.classes and back.channels == "both"
    rng = np.random.default_rng(0)
    g = rng.uniform(0, 1, (300, 300)).astype(np.float32)
    z = np.zeros_like(g)
    a, b = model.candidates(g, z), back.candidates(g, z)
    assert [round(x.raw, 4) for x in a] == [round(x.raw, 4) for x in b]
    with pytest.raises(InputError, match="one \\(H, W\\) shape"):
        model.detect(g, z[:10])
    (tmp_path / "x.npz").write_bytes(b"not a model")
    with pytest.raises(InputError, match="not a prism3d model"):
        AerialModel.load(tmp_path / "x.npz")
    with pytest.raises(InputError, match="channels"):
        AerialTrainOptions(channels="sound")


# -- survey-detect on a survey folder made from a composed patch ----------------------------
ORIGIN = (36.0, 140.0, 100.0)


def _survey(tmp_path, *, crs: str | None = "local", ortho_shift: float = 0.0):
    """A survey folder holding a composed car park: the patch's orthophoto (at its GSD) and
    nDSM (at 0.16 m cells), a flat ground, poses.json with the origin."""
    import json

    import cv2

    from prism3d.geo import local_enu_crs_wkt
    from prism3d.io.geo import write_geotiff

    targets, negatives = _items()
    tsp = [(c, render_nadir(m, GSD)) for c, m in targets]
    nsp = [(c, render_nadir(m, GSD)) for c, m in negatives]
    p = compose_patch(np.random.default_rng(104), tsp, nsp, PatchSpec(gsd_m=GSD, size_m=32.0, missing_dsm_share=0.0,
                                                                       carpark_share=1.0))
    d = tmp_path / "survey"
    d.mkdir()
    wkt = local_enu_crs_wkt(ORIGIN[0], ORIGIN[1]) if crs == "local" else crs
    west, north = 100.0, 200.0
    n = p.rgb.shape[0]
    rgba = np.dstack([np.clip(p.rgb * 255, 0, 255).astype(np.uint8), np.full((n, n), 255, np.uint8)])
    write_geotiff(d / "ortho.tif", rgba, west=west + ortho_shift, north=north, gsd=GSD, crs_wkt=wkt)
    k = 2
    nd = cv2.resize(np.nan_to_num(p.ndsm, nan=0.0), (n // k, n // k), interpolation=cv2.INTER_NEAREST)
    write_geotiff(d / "ndsm.tif", nd.astype(np.float32), west=west, north=north, gsd=GSD * k,
                  crs_wkt=local_enu_crs_wkt(ORIGIN[0], ORIGIN[1]), nodata=float("nan"))
    write_geotiff(d / "ground.tif", np.zeros_like(nd, np.float32), west=west, north=north, gsd=GSD * k,
                  crs_wkt=local_enu_crs_wkt(ORIGIN[0], ORIGIN[1]), nodata=float("nan"))
    (d / "poses.json").write_text(json.dumps({"scale": "gps", "origin_lla": list(ORIGIN)}))
    truth = [(west + (v["col"] + 0.5) * GSD, north - (v["row"] + 0.5) * GSD, v) for v in p.vehicles
             if v["visible"] >= 0.8]
    return d, truth


def test_survey_detect_writes_vehicles_in_wgs84(model: AerialModel, tmp_path) -> None:
    import json

    from prism3d.atr.survey_detect import detect_in_survey
    from prism3d.geo import wgs84_to_enu

    d, truth = _survey(tmp_path)
    out, png = tmp_path / "v.geojson", tmp_path / "v.png"
    s = detect_in_survey(d, out, model, draw=png)
    assert out.is_file() and png.is_file() and s["n_vehicles"] > 0
    gj = json.loads(out.read_text())
    assert gj["type"] == "FeatureCollection" and len(gj["features"]) == s["n_written"]
    close = 0
    for f in gj["features"]:
        p = f["properties"]
        assert f["geometry"]["type"] == "Point" and p["score"] >= 0.5 and p["class"] in ("car", "bus")
        assert 0.0 <= p["heading_deg"] < 180.0
        ring = p["footprint"]["coordinates"][0]
        assert p["footprint"]["type"] == "Polygon" and len(ring) == 5 and ring[0] == ring[-1]
        lon, lat = f["geometry"]["coordinates"]
        e, nn, _ = wgs84_to_enu(np.array([[lat, lon, 0.0]]), np.array(ORIGIN))[0]
        assert e == pytest.approx(p["x_local"], abs=0.01) and nn == pytest.approx(p["y_local"], abs=0.01)
        close += min(math.hypot(e - x, nn - y) for x, y, _ in truth) <= 1.6
    assert close >= 0.8 * len(gj["features"])
    every = tmp_path / "all.geojson"
    s2 = detect_in_survey(d, every, model, all_candidates=True)
    assert s2["n_written"] >= s["n_written"]


@pytest.mark.parametrize("case", ["overwrite", "other_crs", "apart", "png_ndsm", "no_gps", "threshold"])
def test_survey_detect_bad_input_writes_nothing(model: AerialModel, tmp_path, case: str) -> None:
    import json

    from prism3d.atr.survey_detect import detect_in_survey

    d, _ = _survey(tmp_path, crs="EPSG:4326" if case == "other_crs" else "local",
                   ortho_shift=500.0 if case == "apart" else 0.0)
    out = d / "poses.json" if case == "overwrite" else tmp_path / "v.geojson"
    before = out.read_bytes() if out.exists() else None
    if case == "png_ndsm":
        (d / "ndsm.tif").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    if case == "no_gps":
        (d / "poses.json").write_text(json.dumps({"scale": "unknown", "origin_lla": None}))
    kw = {"threshold": float("nan")} if case == "threshold" else {}
    match = {"overwrite": "overwrite the survey", "other_crs": "another coordinate system", "apart": "does not overlap",
             "png_ndsm": "not a readable GeoTIFF", "no_gps": "scale is unknown", "threshold": "threshold"}[case]
    with pytest.raises(InputError, match=match):
        detect_in_survey(d, out, model, **kw)
    assert (out.read_bytes() if out.exists() else None) == before


def test_cli_refuses_unknown_classes_and_models_of_the_other_view(model: AerialModel, tmp_path, capsys) -> None:
    from prism3d.atr.bank import train_bank
    from prism3d.cli import main
    from prism3d.datasets.database.resolve import resolve_targets

    d, _ = _survey(tmp_path)
    aerial = model.save(tmp_path / "aerial.npz")
    bank = train_bank(resolve_targets(["tank_t1", "truck_k1"]), channel="depth", azimuth="0:360:90", bin_deg=90.0,
                      params=(1.0, 0.0, 0.0)).save(tmp_path / "bank.npz")
    out = tmp_path / "v.geojson"
    for args, msg in ((["--targets", "tractor"], "neither a mesh file"),
                      (["--targets", str(bank)], "trained for ground-level shots"),
                      (["--targets", str(aerial), "car"], "stands alone")):
        capsys.readouterr()
        assert main(["-q", "survey-detect", str(d), *args, "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1
        assert not out.exists()
    img, dep = tmp_path / "i.png", tmp_path / "d.npy"
    import cv2

    cv2.imwrite(str(img), np.zeros((40, 60, 3), np.uint8))
    np.save(dep, np.full((40, 60), 5000.0, np.float32))
    assert main(["-q", "detect", "--image", str(img), "--depth", str(dep), "--fx", "50", "--bank", str(aerial),
                 "-o", str(tmp_path / "d.json")]) == 2
    assert "aerial recogniser" in capsys.readouterr().err
    assert main(["-q", "survey-detect", str(d), "--targets", str(aerial), "-o", str(out), "--draw",
                 str(tmp_path / "v.png")]) == 0
    assert out.is_file() and (tmp_path / "v.png").is_file()


# -- a model file's contents are checked when it is read ---------------------------------------
def _tiny_model() -> AerialModel:
    """A hand-made model (no training): a one-class group and a two-class group with a namer."""
    from prism3d.atr.aerial import AerialGroup

    F = len(feature_names("both"))
    rng = np.random.default_rng(0)
    g0 = AerialGroup(("car",), ("car_kei",), (3, 5), rng.normal(size=(3, 5, F)).astype(np.float32), -1.0,
                     (1.0, 0.0), np.zeros((1, 1), np.float32), np.zeros(1, np.float32), {"car": (3.7, 1.6, 1.6)})
    g1 = AerialGroup(("bus", "truck"), ("bus_city", "truck_k1"), (3, 7), rng.normal(size=(3, 7, F)).astype(np.float32),
                     -2.0, (2.0, -1.0), rng.normal(size=(2, 3 * 7 * F)).astype(np.float32), np.zeros(2, np.float32),
                     {"bus": (11.0, 2.5, 3.2), "truck": (7.5, 2.4, 3.0)})
    return AerialModel(0.06, 8, "both", 15.0, (g0, g1))


def _rewrite(src, dst, meta_change=None, arrays_change=None) -> None:
    """``src``'s model file written to ``dst`` with its metadata and arrays changed (a
    damaged or hand-edited file)."""
    import json

    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays.pop("meta_json")).decode())
    if meta_change:
        meta_change(meta)
    if arrays_change:
        arrays = arrays_change(arrays)
    np.savez(dst, meta_json=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)


def _set(**kv):
    return lambda m: m.update(kv)


def _set_group(i, **kv):
    return lambda m: m["groups"][i].update(kv)


DAMAGED = {
    "nan_weights": (None, lambda a: {**a, "g0_weights": np.full_like(a["g0_weights"], np.nan)}, "g0_weights: holds NaN"),
    "inf_namer": (None, lambda a: {**a, "g1_class_coef": np.full_like(a["g1_class_coef"], np.inf)}, "g1_class_coef"),
    "gsd_zero": (_set(gsd_m=0.0), None, "gsd_m"),
    "gsd_1e-6": (_set(gsd_m=1e-6), None, "gsd_m"),
    "gsd_string": (_set(gsd_m="0.06"), None, "gsd_m"),
    "cell_px_zero": (_set(cell_px=0), None, "cell_px"),
    "angle_step_zero": (_set(angle_step_deg=0.0), None, "angle_step_deg"),
    "channels_unknown": (_set(channels="x-ray"), None, "channels"),
    "no_groups": (_set(groups=[]), None, "groups"),
    "groups_not_a_list": (_set(groups="g"), None, "groups"),
    "weights_wrong_shape": (None, lambda a: {**a, "g0_weights": np.zeros(3, np.float32)}, r"g0_weights: expected \(3, 5, 14\)"),
    "namer_wrong_shape": (None, lambda a: {**a, "g1_class_coef": np.zeros((2, 10), np.float32)}, "g1_class_coef"),
    "missing_arrays": (None, lambda a: {}, "no array g0_weights"),
    "even_cells": (_set_group(0, cells=[4, 5]), None, "cells"),
    "dims_of_a_class_missing": (_set_group(1, dims={"bus": [11.0, 2.5, 3.2]}), None, "dims"),
    "platt_nan": (_set_group(0, platt=[float("nan"), 0.0]), None, "platt"),
    "bias_null": (_set_group(0, bias=None), None, "bias"),
    "classes_empty": (_set_group(0, classes=[]), None, "classes"),
}


def test_a_sound_model_file_reads_back_whole(tmp_path) -> None:
    m = _tiny_model()
    back = AerialModel.load(m.save(tmp_path / "m.npz"))
    assert back.classes == ["car", "bus", "truck"] and back.gsd_m == 0.06 and back.cell_px == 8
    for a, b in zip(m.groups, back.groups):
        assert np.array_equal(a.weights, b.weights) and np.array_equal(a.class_coef, b.class_coef)
        assert a.cells == b.cells and a.platt == b.platt and a.dims == b.dims


@pytest.mark.parametrize("case", sorted(DAMAGED))
def test_a_damaged_model_file_is_refused_when_read(tmp_path, case: str) -> None:
    """NaN weights once gave exit 0 with no vehicles, gsd 0 a ZeroDivisionError, weights of
    the wrong shape an IndexError and missing arrays a KeyError: each is now one InputError
    naming the file and what is wrong."""
    meta_change, arrays_change, match = DAMAGED[case]
    src = _tiny_model().save(tmp_path / "m.npz")
    bad = tmp_path / f"{case}.npz"
    _rewrite(src, bad, meta_change, arrays_change)
    with pytest.raises(InputError, match=match) as exc:
        AerialModel.load(bad)
    assert str(bad) in str(exc.value) and "train it again" in str(exc.value)


def _flat_survey(tmp_path, *, ndsm_value: float = 0.0):
    """A tiny survey folder (20 x 20 m): a grey orthophoto, an nDSM of ``ndsm_value``
    everywhere (NaN: no height at all), poses.json with GPS."""
    import json

    from prism3d.geo import local_enu_crs_wkt
    from prism3d.io.geo import write_geotiff

    d = tmp_path / "flat_survey"
    d.mkdir()
    wkt = local_enu_crs_wkt(ORIGIN[0], ORIGIN[1])
    write_geotiff(d / "ortho.tif", np.full((250, 250, 4), 120, np.uint8), west=0.0, north=20.0, gsd=0.08, crs_wkt=wkt)
    write_geotiff(d / "ndsm.tif", np.full((125, 125), ndsm_value, np.float32), west=0.0, north=20.0, gsd=0.16,
                  crs_wkt=wkt, nodata=float("nan"))
    (d / "poses.json").write_text(json.dumps({"scale": "gps", "origin_lla": list(ORIGIN)}))
    return d


def test_cli_survey_detect_refuses_a_damaged_model_file(tmp_path, capsys) -> None:
    from prism3d.cli import main

    d = _flat_survey(tmp_path)
    bad = tmp_path / "nan.npz"
    _rewrite(_tiny_model().save(tmp_path / "m.npz"), bad, None, lambda a: {k: np.full_like(v, np.nan) for k, v in a.items()})
    out = tmp_path / "v.geojson"
    assert main(["-q", "survey-detect", str(d), "--targets", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds NaN" in err[0] and str(bad) in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("case", ["missing_folder", "a_file", "no_ndsm", "no_height_at_all"])
def test_cli_survey_detect_refuses_a_bad_survey_before_training(tmp_path, monkeypatch, capsys, case: str) -> None:
    """A missing or broken survey is refused before the aerial recogniser is trained (that
    took minutes before the survey folder was even looked at)."""
    import prism3d.datasets.jobs.recognisers as recognisers
    from prism3d.cli import main

    def no_training(*a, **k):
        raise AssertionError("trained before the survey was checked")

    monkeypatch.setattr(recognisers, "train_aerial", no_training)
    d = {"missing_folder": tmp_path / "no_such_survey", "a_file": tmp_path / "v.txt"}.get(case)
    if case == "a_file":
        d.write_text("x")
    if d is None:
        d = _flat_survey(tmp_path, ndsm_value=float("nan") if case == "no_height_at_all" else 0.0)
    if case == "no_ndsm":
        (d / "ndsm.tif").unlink()
    match = {"missing_folder": "no such survey folder", "a_file": "not a folder", "no_ndsm": "no ndsm.tif",
             "no_height_at_all": "holds no height"}[case]
    out = tmp_path / "v.geojson"
    assert main(["-q", "survey-detect", str(d), "--targets", "car", "--no-cache", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err
    assert not out.exists()
