"""Options drawn from the options dataclasses: the CLI reads each field's default and help
from the source without importing the module, and what it reads is what the dataclass
holds; a command given no option builds the dataclass's defaults, and each flag lands on
its field."""

from __future__ import annotations

import dataclasses

import pytest

from prism3d.atr.bank import BankOptions
from prism3d.atr.chips import ChipSpec
from prism3d.atr.scene import DetectOptions
from prism3d.cli import (
    _BANK_OPTIONS,
    _CHIP_SPEC,
    _DETECT_OPTIONS,
    _RENDER_SPEC,
    _FIELD_OPTIONS,
    _FLIGHT_OPTIONS,
    _RECONSTRUCT_OPTIONS,
    _STITCH_OPTIONS,
    _SURVEY_OPTIONS,
    build_parser,
)
from prism3d.datasets.simulation.field import FieldOptions
from prism3d.datasets.simulation.flight import FlightOptions
from prism3d.options_cli import _fields, given_fields
from prism3d.options_cli import _NOT_LITERAL
from prism3d.reconstruct.scan.stitch_options import StitchOptions
from prism3d.reconstruct.stereo.pipeline import ReconstructOptions
from prism3d.reconstruct.survey.model import SurveyOptions


@pytest.mark.parametrize(("where", "cls"), [(_SURVEY_OPTIONS, SurveyOptions), (_STITCH_OPTIONS, StitchOptions),
                                           (_FLIGHT_OPTIONS, FlightOptions), (_FIELD_OPTIONS, FieldOptions),
                                           (_RECONSTRUCT_OPTIONS, ReconstructOptions), (_BANK_OPTIONS, BankOptions),
                                           (_CHIP_SPEC, ChipSpec), (_DETECT_OPTIONS, DetectOptions)])
def test_defaults_read_from_the_source_are_the_dataclass_defaults(where, cls):
    real = {f.name: f.default for f in dataclasses.fields(cls)}
    read = _fields(where)
    assert set(read) == set(real)
    for name, (default, doc) in read.items():
        assert default == real[name] or (default is _NOT_LITERAL and real[name] is dataclasses.MISSING), name
        assert doc, f"{name} has no docstring"
    assert _fields(_SURVEY_OPTIONS)["pair_steps"][0] == (1, 2)
    assert _fields(_STITCH_OPTIONS)["min_confidence"][0] == 0.9  # a module constant


def _stitch_options(*argv: str) -> StitchOptions:
    args = build_parser().parse_args(["stitch", "a.ply", "b.ply", "-o", "m.ply", *argv])
    return StitchOptions(**given_fields(args, _STITCH_OPTIONS))


def test_stitch_flags_land_on_their_fields():
    assert _stitch_options() == StitchOptions()
    assert _stitch_options("--turntable-step", "45", "--voxel", "0.5", "--smooth", "3", "--min-confidence", "0.5",
                           "--mesh-max-distance", "2") == StitchOptions(
        turntable_step_deg=45.0, voxel=0.5, smooth_iterations=3, min_confidence=0.5, mesh_max_spacings=2.0)


def _survey_options(*argv: str) -> SurveyOptions:
    args = build_parser().parse_args(["survey", "a.jpg", "b.jpg", "-o", "out", *argv])
    return SurveyOptions(**given_fields(args, _SURVEY_OPTIONS))


def test_survey_without_options_is_the_dataclass_default():
    assert _survey_options() == SurveyOptions()


def test_survey_flags_land_on_their_fields():
    o = _survey_options("--cell", "0.5", "--ortho-gsd", "0.04", "--crs", "enu", "--laz", "--cloud-spacing", "0.2",
                        "--matching", "sequential", "--pair-steps", "1", "3", "--no-cross-pairs",
                        "--max-image-size", "1500", "--dense-max-pixels", "2e6", "--refine", "none",
                        "--refine-principal-point", "--gcp", "g.txt", "--gcp-check", "a,b", "c",
                        "--gps-accuracy", "0.5", "--no-gps-prior")
    assert o == SurveyOptions(cell_m=0.5, ortho_gsd_m=0.04, crs="enu", laz=True, cloud_spacing_m=0.2,
                              matching="sequential", pair_steps=(1, 3), cross_pairs=False, max_image_size=1500,
                              dense_max_pixels=2e6, refine_intrinsics="none", refine_principal_point=True,
                              gcp_file="g.txt", gcp_check=("a", "b", "c"), gps_accuracy=(0.5, 1.0),
                              gps_prior=False)


def test_the_help_is_the_field_docstring(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["survey", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "Pairs: each frame with the next (1)" in out and "twice the baseline). (default: 1 2)" in out
    assert ":mod:" not in out and "``" not in out


def test_a_bad_gps_accuracy_is_one_line(capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["survey", "a.jpg", "-o", "out", "--gps-accuracy", "1,2,3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--gps-accuracy" in err[0] and "H or H,V" in err[0]


def _flight_options(*argv: str) -> FlightOptions:
    args = build_parser().parse_args(["simulate", "flight", "out", *argv])
    assert args.supersample is None  # the simulator's own default
    return FlightOptions(seed=args.seed, noise=args.noise, **given_fields(args, _FLIGHT_OPTIONS))


def test_simulate_flight_flags_land_on_their_fields():
    assert _flight_options() == FlightOptions()
    assert _flight_options("--targets", "3", "--confusers", "1", "--frames", "8", "--lines", "1", "--scene", "carpark",
                           "--altitude", "60", "--overlap", "0.8", "--side-overlap", "0.5", "--size", "800x600",
                           "--heading", "30", "--no-depth", "--gcp", "5", "--gcp-pixel-sigma", "0.2", "--seed", "4",
                           "--no-noise") == FlightOptions(
        targets=3, confusers=1, frames=8, lines=1, scene="carpark", altitude_m=60.0, overlap=0.8, side_overlap=0.5,
        size=(800, 600), heading_deg=30.0, depth=False, gcp=5, gcp_pixel_sigma=0.2, seed=4, noise=False)


def test_simulate_field_flags_land_on_their_fields():
    def field(*argv: str) -> FieldOptions:
        args = build_parser().parse_args(["simulate", "field", "out", *argv])
        return FieldOptions(seed=args.seed, noise=args.noise, **given_fields(args, _FIELD_OPTIONS))

    assert field() == FieldOptions()
    assert field("--targets", "4", "--confusers", "2", "--classes", "tank_t1", "truck_k1") == FieldOptions(
        targets=4, confusers=2, classes=("tank_t1", "truck_k1"))


def test_reconstruct_flags_land_on_their_fields():
    def rec(*argv: str) -> ReconstructOptions:
        args = build_parser().parse_args(["reconstruct", "shot.png", "--calib", "rig.yaml", "-o", "s.ply", *argv])
        return ReconstructOptions(**given_fields(args, _RECONSTRUCT_OPTIONS))

    assert rec() == ReconstructOptions()
    assert rec("--depth-range", "900:1600", "--min-confidence", "0.5", "--smooth", "1.5") == ReconstructOptions(
        depth_range_mm=(900.0, 1600.0), min_confidence=0.5, smooth_sigma_px=1.5)
    assert rec("--min-disp", "100", "--num-disp", "64") == ReconstructOptions(min_disp=100, num_disp=64)


def test_bank_flags_land_on_their_fields_and_eval_keeps_its_own_default():
    parse = build_parser().parse_args
    assert BankOptions(**given_fields(parse(["bank", "train", "-o", "m.npz"]), _BANK_OPTIONS)) == BankOptions()
    args = parse(["bank", "train", "-o", "m.npz", "--azimuth", "0:360:30", "--elevation", "15:35:20",
                  "--bin-deg", "30"])
    assert BankOptions(**given_fields(args, _BANK_OPTIONS)) == BankOptions(azimuth="0:360:30", elevation="15:35:20",
                                                                            bin_deg=30.0)
    # eval scores between the training azimuths unless told: no flag, no value
    assert given_fields(parse(["bank", "eval", "m.npz"]), _BANK_OPTIONS) == {}


def test_render_flags_land_on_the_chip_spec():
    parse = build_parser().parse_args
    assert ChipSpec(**given_fields(parse(["render", "tank_t1", "-o", "out"]), _CHIP_SPEC)) == ChipSpec()
    args = parse(["render", "tank_t1", "-o", "out", "--size", "64", "--framing", "range", "--pixels-per-m", "40",
                  "--channels", "depth", "mask", "--no-camouflage", "--clutter", "noise", "--noise", "0.02",
                  "--seed", "3", "--backend", "pyrender"])
    assert ChipSpec(**given_fields(args, _CHIP_SPEC)) == ChipSpec(
        size=64, framing="range", pixels_per_m=40.0, channels=("depth", "mask"), camouflage=False, clutter="noise",
        noise_sigma=0.02, seed=3, backend="pyrender")


def test_detect_flags_land_on_the_detect_options():
    parse = build_parser().parse_args
    base = ["detect", "--image", "a.png", "--depth", "d.npy", "--fx", "500", "--bank", "b.npz", "-o", "d.json"]
    assert DetectOptions(**given_fields(parse(base), _DETECT_OPTIONS)) == DetectOptions()
    args = parse([*base, "--min-height", "300", "--ground-cell", "1500", "--max-detections", "5", "--band-scan"])
    assert DetectOptions(**given_fields(args, _DETECT_OPTIONS)) == DetectOptions(
        min_height_mm=300.0, ground_cell_mm=1500.0, max_detections=5, band_scan=True)


def test_db_render_flags_land_on_the_job_and_chip_fields():
    parse = build_parser().parse_args
    args = parse(["db", "render", "db", "--job", "j"])
    assert given_fields(args, _RENDER_SPEC) == {} and ChipSpec(**given_fields(args, _CHIP_SPEC)) == ChipSpec()
    args = parse(["db", "render", "db", "--job", "j", "--azimuth", "0:90:90", "--elevation", "20:20:1", "--size", "32",
                  "--channels", "depth", "--framing", "range", "--no-camouflage", "--seed", "4"])
    assert given_fields(args, _RENDER_SPEC) == {"azimuth": "0:90:90", "elevation": "20:20:1"}
    assert ChipSpec(**given_fields(args, _CHIP_SPEC)) == ChipSpec(size=32, channels=("depth",), framing="range",
                                                                   camouflage=False, seed=4)
