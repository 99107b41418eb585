"""The ``prism3d`` command line.

Each command parses its arguments and calls one library function. Start-up is lazy:
heavy libraries are imported inside the handlers, so ``prism3d --help`` is instant.

Exit codes: 0 success; 2 a user mistake (a :class:`~prism3d.errors.Prism3dError`,
printed as one line on stderr, no partial output); 130 interrupted. Anything else is
a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import os
import re
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from prism3d import __version__
from prism3d.errors import DatasetError, InputError, Prism3dError
from prism3d.options_cli import field_option, given_fields

Handler = Callable[[argparse.Namespace], int | None]

#: Choices shared by several commands (``--units``, ``--up``, ``--channels``).
_UNITS = ("mm", "cm", "m", "in")
_UP_AXES = ("y", "z")
_CHANNELS = ("intensity", "depth", "mask", "shape")


class _Parser(argparse.ArgumentParser):
    """argparse with our exit code 2 and one-line messages."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def _progress(args: argparse.Namespace, desc: str, *, stage_lines: bool = False) -> Any:
    from prism3d.progress import make_progress

    return make_progress(desc, quiet=getattr(args, "quiet", False), stage_lines=stage_lines)


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        print(text)


def _global_options(p: argparse.ArgumentParser, *, top: bool) -> None:
    """-q, -v and --max-pixels: before the command with their defaults, and accepted after
    it too (there without a default, so a command's parser never undoes what was given
    before it)."""
    d: dict[str, Any] = {} if top else {"default": argparse.SUPPRESS}
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summaries", **d)
    p.add_argument("-v", "--verbose", action="count", help="more logging (-vv for debug)",
                   **(d or {"default": 0}))
    p.add_argument("--max-pixels", type=int, metavar="N",
                   help="largest image or array decoded, pixels (default 100 MP; or PRISM3D_MAX_PIXELS)", **d)


def _command(
    sub: Any, name: str, run: Handler, *, help: str, description: str
) -> argparse.ArgumentParser:
    """Add the subcommand ``name``, run by ``run(args)``."""
    p = sub.add_parser(name, help=help, description=description)
    _global_options(p, top=False)
    p.set_defaults(func=run)
    return p


def _output_option(p: argparse.ArgumentParser, metavar: str) -> None:
    p.add_argument("-o", "--output", required=True, type=Path, metavar=metavar)


# --- demo -------------------------------------------------------------------------------
def _cmd_demo(args: argparse.Namespace) -> int:
    from prism3d.demo import run_demo

    report, failed = run_demo(args.out_dir, seed=args.seed, fast=args.fast,
                              progress=_progress(args, "demo"), only=args.only)
    _say(args, f"report: {report}")
    if failed:
        print(f"prism3d demo: stages failed: {', '.join(failed)} (see {report})", file=sys.stderr)
        return 1
    return 0


def _add_demo(sub: Any) -> None:
    p = _command(sub, "demo", _cmd_demo,
                 help="run the whole pipeline on built-in data and write report.html",
                 description="Run every stage of prism3d on built-in data (simulated shots, "
                 "calibration, reconstruction, ATR) and write OUT_DIR/report.html.")
    p.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    p.add_argument("--seed", type=int, default=0, help="random seed for simulated data (default 0)")
    p.add_argument("--fast", action="store_true", help="smaller images, fewer views, two scanned targets instead of four (for tests)")
    p.add_argument("--only", nargs="+", metavar="STAGE", help="run only these stages")


# --- trigger / capture --------------------------------------------------------------------
def _cmd_trigger(args: argparse.Namespace) -> int:
    if args.action == "simulate":
        from prism3d.capture.trigger_sim import simulate_main

        return simulate_main(args.fault, link=args.link)
    from prism3d.capture import trigger

    if args.port is None:
        raise InputError(f"trigger {args.action}: give the controller's PORT (a device path or pyserial URL)")
    if args.action == "ping":
        result = trigger.trigger_ping(args.port, timeout=args.timeout)
    elif args.action == "status":
        result = trigger.trigger_status(args.port, timeout=args.timeout)
    else:
        result = trigger.trigger_fire(args.port, pattern_id=args.pattern, flash_delay_us=args.flash_delay_us,
                                      flash_us=args.flash_us, shutter_us=args.shutter_us, timeout=args.timeout)
    _print_json(result)
    return 0


def _add_trigger(sub: Any) -> None:
    p = _command(sub, "trigger", _cmd_trigger,
                 help="flash+shutter controller over a serial line (simulate|ping|status|fire)",
                 description="Talk to the flash/shutter trigger controller (protocol: "
                 "docs/trigger-protocol.md). 'simulate' serves a simulated controller on a "
                 "pseudo-terminal and prints its path first.")
    p.add_argument("action", choices=["simulate", "ping", "status", "fire"])
    p.add_argument("port", nargs="?", metavar="PORT", help="device path or pyserial URL (not for simulate)")
    p.add_argument("--timeout", type=float, default=1.0, help="seconds to wait for each reply (default 1)")
    p.add_argument("--fault", choices=["silence", "garbage", "drop", "disconnect", "slow"],
                   help="simulate: inject this fault")
    p.add_argument("--link", type=Path, help="simulate: keep this symlink pointing at the pty")
    p.add_argument("--pattern", type=int, default=1, help="fire: grating pattern id (0 = plain flash)")
    p.add_argument("--flash-delay-us", type=int, default=500)
    p.add_argument("--flash-us", type=int, default=2000)
    p.add_argument("--shutter-us", type=int, default=8000)


def _virtual_resolver(name: str) -> Any:
    from prism3d.datasets.simulation.virtual_camera import resolve_virtual_target

    return resolve_virtual_target(name)


# --- simulate ------------------------------------------------------------------------------
def _simulated_common(args: argparse.Namespace) -> dict[str, Any]:
    """The seed, noise and (when given) supersampling every simulated kind shares."""
    common = {"seed": args.seed, "noise": args.noise}
    if args.supersample is not None:
        common["supersample"] = args.supersample
    return common


def _cmd_simulate_flight(args: argparse.Namespace) -> int:
    from prism3d.datasets.simulation.flight import FlightOptions, simulate_flight

    fo = FlightOptions(**_simulated_common(args), **given_fields(args, _FLIGHT_OPTIONS))
    summary = simulate_flight(args.out_dir, fo, progress=_progress(args, "simulate flight"))
    _say(args, f"wrote a {summary['n_frames']}-frame flight over {fo.scene} ({summary['n_targets']} vehicles, "
               f"GSD {100 * summary['gsd_m']:.1f} cm) to {args.out_dir} in {summary['seconds']:.1f} s")
    return 0


def _cmd_simulate_field(args: argparse.Namespace) -> int:
    from prism3d.datasets.simulation.field import FieldOptions, simulate_field

    fo = FieldOptions(**_simulated_common(args), **given_fields(args, _FIELD_OPTIONS))
    if args.count is not None:
        from prism3d.datasets.runner import RunOptions
        from prism3d.datasets.simulation.field import simulate_field_batch

        report = simulate_field_batch(args.out_dir, args.count, fo, RunOptions(
            workers=args.workers, scheduler=args.scheduler, progress=_progress(args, "simulate field")))
        _say(args, report.summary())
        if not report.ok:
            print(f"prism3d: {report.failure_line()}", file=sys.stderr)
        return report.exit_code
    if args.workers or args.scheduler:
        raise InputError("simulate field: --workers and --scheduler go with --count (a batch of scenes)")
    summary = simulate_field(args.out_dir, fo, progress=_progress(args, "simulate field"))
    _say(args, f"wrote a field scene ({summary['n_targets']} targets, {summary['n_confusers']} confusers) "
               f"to {args.out_dir} in {summary['seconds']:.1f} s")
    return 0


def _cmd_simulate_rig(args: argparse.Namespace) -> int:
    """``simulate plate|calib|scene``: shots through the virtual prism rig."""
    import dataclasses

    from prism3d.capture.camera_effects import CameraEffects
    from prism3d.capture.simulate import SimulateOptions, simulate_to_folder
    from prism3d.reconstruct.stereo.calibrate import parse_board

    rig = None
    if args.rig is not None:
        from prism3d.capture.rig import StereoRig

        rig = StereoRig.load(args.rig)
    camouflage = getattr(args, "camouflage", None)
    if camouflage is None:
        camouflage = args.kind == "scene"
    target = None
    if args.kind == "scene":
        from prism3d.datasets.models.targets import builtin_target

        target = builtin_target(args.target, camouflage=camouflage, seed=args.seed)
    effects = CameraEffects.ideal() if args.ideal_camera else CameraEffects()
    if args.jpeg_quality is not None:
        effects = dataclasses.replace(effects, jpeg_quality=args.jpeg_quality or None)
    board = parse_board(getattr(args, "board", "9x6"))
    summary = simulate_to_folder(args.kind, args.out_dir, SimulateOptions(
        pattern=args.pattern, camouflage=camouflage, views=args.views, seed=args.seed, noise=args.noise,
        supersample=2 if args.supersample is None else args.supersample, compress=args.compress, board=board,
        square_mm=getattr(args, "square", 25.0), blur_sigma=args.blur, effects=effects,
    ), rig=rig, target=target, progress=_progress(args, f"simulate {args.kind}"))
    _say(args, f"wrote {summary['n_shots']} shot(s) and ground truth to {args.out_dir} "
               f"in {summary['seconds']:.1f} s")
    return 0


def _simulate_common(q: argparse.ArgumentParser, *, supersample: str) -> None:
    """The options every ``simulate`` kind takes."""
    q.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--noise", dest="noise", action="store_true", default=True, help="sensor noise (default)")
    q.add_argument("--no-noise", dest="noise", action="store_false")
    q.add_argument("--supersample", type=int, default=None, help=f"anti-aliasing factor (default {supersample})")


def _simulate_rig_options(q: argparse.ArgumentParser, *, views: str, camouflage: bool) -> None:
    """The options of shots through the virtual prism rig (plate, calib, scene)."""
    q.add_argument("--rig", type=Path, help="rig/calibration YAML to simulate (default: the paper's rig)")
    q.add_argument("--pattern", dest="pattern", action="store_true", default=None,
                   help="project the colour grating (default: on for plate/scene, off for calib)")
    q.add_argument("--no-pattern", dest="pattern", action="store_false", help="white flash only")
    if camouflage:
        q.add_argument("--camouflage", dest="camouflage", action="store_true", default=None,
                       help="camouflage paint (default: on for scene targets, off for the plate)")
        q.add_argument("--no-camouflage", dest="camouflage", action="store_false")
    q.add_argument("--views", type=int, help=f"number of shots (default {views})")
    q.add_argument("--compress", action=argparse.BooleanOptionalAction, default=True,
                   help="deflate the truth .npz files (default; --no-compress writes them plain, ~60x larger)")
    q.add_argument("--blur", type=float, default=0.0, metavar="PX",
                   help="extra Gaussian blur of each view, pixels (default 0: the camera's own PSF only)")
    q.add_argument("--ideal-camera", action="store_true",
                   help="the ideal camera: no exposure or colour difference between the views, no "
                   "vignetting, lens PSF, gloss or JPEG (default: real-camera effects on)")
    q.add_argument("--jpeg-quality", type=int, default=None, metavar="Q",
                   help="JPEG quality of the simulated camera, 1-100 (default 92; 0 = none)")


def _add_simulate(sub: Any) -> None:
    p = _command(sub, "simulate", lambda args: 2,
                 help="virtual rig shots and scenes with exact ground truth (plate|calib|scene|field|flight)",
                 description="Simulate with exact ground truth; each kind has its own options "
                 "('prism3d simulate KIND --help'). Shots through the virtual prism rig write shot PNG(s), "
                 "rig.yaml (OpenCV FileStorage) and truth.npz (depth_left_mm, depth_right_mm, mask, albedo, "
                 "shading, true rectified disparity...).")
    ksub = p.add_subparsers(dest="kind", metavar="KIND", required=True, parser_class=_Parser)

    def kind(name: str, run: Handler, help: str, supersample: str) -> argparse.ArgumentParser:
        q = _command(ksub, name, run, help=help, description=help[0].upper() + help[1:] + ".")
        q.set_defaults(kind=name)
        _simulate_common(q, supersample=supersample)
        return q

    q = kind("plate", _cmd_simulate_rig, "the paper's 30x30 cm plate at 1250 mm, grating on", "2")
    _simulate_rig_options(q, views="1", camouflage=True)
    q = kind("calib", _cmd_simulate_rig, "chessboard shots for calibration (5 views of 9x6 inner corners, 25 mm)",
             "2")
    _simulate_rig_options(q, views="5", camouflage=False)
    q.add_argument("--board", default="9x6",
                   help="chessboard inner corners COLSxROWS (default 9x6; 19x13 pins the principal point about "
                   "twice as well)")
    q.add_argument("--square", type=float, default=25.0, help="square size, mm (default 25)")
    q = kind("scene", _cmd_simulate_rig, "a built-in target on a turntable, 8 views at 45 deg (also target.ply "
             "and poses.json)", "2")
    _simulate_rig_options(q, views="8", camouflage=True)
    q.add_argument("--target", default="tank_t1", help="built-in target name (default tank_t1)")
    q = kind("field", _cmd_simulate_field, "full-size camouflaged targets, confusers and clutter on terrain under "
             "the sun, through a 4 m baseline rig (shot.png, rig.yaml, truth.json, truth.npz)", "1")
    opt = functools.partial(field_option, q, _FIELD_OPTIONS)
    opt("targets", "--targets", type=int)
    opt("confusers", "--confusers", type=int)
    opt("classes", "--classes", nargs="+", metavar="NAME")
    q.add_argument("--count", type=int, help="a batch of this many scenes, seeds SEED, SEED+1... in "
                   "OUT_DIR/scene_<seed> (a rerun resumes; batch.json has the scenes per minute)")
    q.add_argument("--workers", type=int, default=0, help="with --count: local Dask workers (0 = in this process)")
    q.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="with --count: an existing Dask scheduler")
    q = kind("flight", _cmd_simulate_flight, "a nadir drone survey (lawnmower lines, 12 MP) over hills, roads, "
             "clutter and ground vehicles (IMG_0000.JPG..., geoinfo.txt, camera.yaml, truth.json, truth.npz "
             "with the true DSM, depth/); lengths in metres", "1")
    opt = functools.partial(field_option, q, _FLIGHT_OPTIONS)
    opt("targets", "--targets", type=int)
    opt("confusers", "--confusers", type=int)
    opt("frames", "--frames", type=int)
    opt("lines", "--lines", type=int)
    opt("scene", "--scene", choices=["field", "carpark"])
    opt("altitude_m", "--altitude", type=float, metavar="M")
    opt("overlap", "--overlap", type=float, metavar="F")
    opt("side_overlap", "--side-overlap", type=float, metavar="F")
    opt("size", "--size", type=_size_wxh, metavar="WxH")
    opt("heading_deg", "--heading", type=float, metavar="DEG")
    opt("depth", "--depth", action=argparse.BooleanOptionalAction)
    opt("gcp", "--gcp", type=int, metavar="N")
    opt("gcp_pixel_sigma", "--gcp-pixel-sigma", type=float, metavar="PX")


#: The field scene simulator's options dataclass: its fields give `simulate field` its
#: defaults and help.
_FIELD_OPTIONS = ("prism3d.datasets.simulation.field", "FieldOptions")
#: The drone flight simulator's options dataclass: its fields give `simulate flight` its
#: defaults and help.
_FLIGHT_OPTIONS = ("prism3d.datasets.simulation.flight_plan", "FlightOptions")


def _size_wxh(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` in pixels."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if m is None:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels (e.g. 4000x3000), got {text!r}")
    return (int(m.group(1)), int(m.group(2)))


def _cmd_capture(args: argparse.Namespace) -> int:
    from prism3d.capture.acquire import CaptureOptions, capture_shots

    expected = None
    if args.calib is not None:
        from prism3d.capture.rig import StereoRig

        expected = StereoRig.load(args.calib).split.sensor_size
    camera = args.camera
    if camera == "virtual":  # the physically simulated paper rig, not a stand-in
        camera = "virtual:plate"
    paths = capture_shots(args.trigger, camera, args.output, CaptureOptions(
        count=args.count, interval_s=args.interval, pattern_id=args.pattern, flash=not args.no_flash,
        expected_size=expected, trigger_timeout=args.timeout, grab_timeout=args.grab_timeout,
    ), progress=_progress(args, "capture"), resolver=_virtual_resolver)
    for p in paths:
        _say(args, str(p))
    return 0


def _add_capture(sub: Any) -> None:
    p = _command(sub, "capture", _cmd_capture,
                 help="one-shot (or sequence) capture: arm, fire, grab, check, save",
                 description="Arm the trigger controller, fire the flash and shutter, grab the frame "
                 "from the camera source, check it and save shot_NNN.png + shot_NNN.json atomically.")
    p.add_argument("--trigger", required=True, metavar="PORT", help="trigger controller port or pyserial URL")
    p.add_argument("--camera", required=True, metavar="SOURCE",
                   help="folder:PATH | opencv:INDEX_OR_URL | virtual[:TARGET]")
    _output_option(p, "DIR")
    p.add_argument("--count", type=int, default=1, help="number of shots (default 1)")
    p.add_argument("--interval", type=float, default=0.0, metavar="S", help="seconds between shots")
    p.add_argument("--pattern", type=int, default=1, help="grating pattern id (0 = plain flash)")
    p.add_argument("--no-flash", action="store_true", help="do not fire the flash projector")
    p.add_argument("--calib", type=Path, help="calibration YAML: check the frame size against it")
    p.add_argument("--timeout", type=float, default=1.0, help="trigger reply timeout, seconds")
    p.add_argument("--grab-timeout", type=float, default=5.0, help="camera frame timeout, seconds")


# --- calibrate / rectify -------------------------------------------------------------------
def _cmd_calibrate(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.stereo.calibrate import calibrate_to_file

    # The calibration's warnings are printed below, even with --quiet (they say the file may
    # be unfit for use, which a script must hear too); logging must not print them twice.
    def not_printed_below(record: logging.LogRecord) -> bool:
        return not getattr(record, "prism3d_calibration_warning", False)

    lib_log = logging.getLogger("prism3d.reconstruct.stereo.calibrate")
    lib_log.addFilter(not_printed_below)
    try:
        cal = calibrate_to_file(args.images, args.output, board=args.board, square_mm=args.square,
                                pairs=args.pairs, skew=args.skew, tangential=not args.no_tangential,
                                progress=_progress(args, "calibrate"))
    finally:
        lib_log.removeFilter(not_printed_below)
    _say(args, cal.summary())
    _say(args, f"wrote {args.output}")
    for w in cal.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0


def _add_calibrate(sub: Any) -> None:
    p = _command(sub, "calibrate", _cmd_calibrate,
                 help="chessboard calibration of the prism rig (bundle adjustment)",
                 description="Detect chessboard corners in each view of side-by-side prism shots "
                 "(or in separate left/right images with --pairs), estimate both cameras "
                 "(K, k1 k2 [p1 p2]), the rig's R T and every board pose by bundle adjustment, "
                 "and write an OpenCV FileStorage YAML with the quality figures.")
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGES",
                   help="prism shots; with --pairs: left1 right1 left2 right2 ...")
    _output_option(p, "CALIB_YAML")
    p.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    p.add_argument("--square", type=float, default=25.0, metavar="MM", help="square size, mm (default 25)")
    p.add_argument("--pairs", action="store_true", help="IMAGES alternate left, right (ordinary stereo rig)")
    p.add_argument("--skew", action="store_true", help="estimate the skew (off by default, as Bouguet advises)")
    p.add_argument("--no-tangential", action="store_true", help="radial k1 k2 only (the paper's model)")


def _cmd_rectify(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.stereo.rectify import rectify_to_folder

    _check_views(args)
    files = rectify_to_folder(args.shot, list(args.calib), args.output, left_path=args.left,
                              right_path=args.right, alpha=args.alpha,
                              image_size=_parse_size(args.image_size))
    for f in files.values():
        _say(args, f"wrote {f}")
    return 0


def _add_rectify(sub: Any) -> None:
    p = _command(sub, "rectify", _cmd_rectify,
                 help="rectify the two views of a prism shot (or a stereo pair)",
                 description="Split a side-by-side shot into its two views (or take --left/--right "
                 "files), undistort and rectify them (equal principal points: disparity = f*B/z), "
                 "write left.png, right.png and rectification.yaml (R1 R2 P1 P2 Q).")
    _shot_options(p)
    _output_option(p, "OUT_DIR")
    p.add_argument("--alpha", type=float, default=1.0,
                   help="0 = crop to valid pixels, 1 = keep every source pixel (default)")


# --- match / reconstruct / flatness -------------------------------------------------------
def _cmd_match(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.stereo.match import match_files

    if args.output.suffix.lower() != ".pfm":
        raise InputError(f"{args.output}: disparity is written as PFM (.pfm)")
    res = match_files(args.left, args.right, args.output, num_disp=args.num_disp,
                      min_disp=args.min_disp, dense=args.dense, valid_out=args.valid_out)
    _say(args, f"wrote {args.output} ({100.0 * res.valid.mean():.1f}% confident pixels)")
    return 0


def _add_match(sub: Any) -> None:
    p = _command(sub, "match", _cmd_match,
                 help="dense stereo matching of a rectified pair -> disparity PFM",
                 description="Census + semi-global matching with sub-pixel refinement, left-right "
                 "check and hole filling. Writes d = x_left - x_right (float32 PFM).")
    p.add_argument("left", type=Path, metavar="LEFT")
    p.add_argument("right", type=Path, metavar="RIGHT")
    _output_option(p, "DISP_PFM")
    p.add_argument("--num-disp", required=True, type=int, metavar="N", help="number of disparity levels")
    p.add_argument("--min-disp", type=int, default=0, metavar="M", help="smallest disparity (default 0)")
    p.add_argument("--sparse", dest="dense", action="store_false",
                   help="write NaN where the match is not confident (default: dense, holes filled)")
    p.add_argument("--valid-out", type=Path, metavar="PNG", help="also write the confidence mask")


def _calib_options(p: argparse.ArgumentParser, *, required: bool = True) -> None:
    p.add_argument("--calib", required=required, type=Path, nargs="+", metavar="CALIB",
                   help="calibration: prism3d/OpenCV YAML, Middlebury/ETH3D calib.txt, KITTI "
                   "calib_cam_to_cam.txt, or two files (ROS left + right camera_info; OpenCV "
                   "intrinsics + extrinsics)")
    p.add_argument("--image-size", metavar="WxH", help="each view's size, for calibration files that "
                   "do not state it")


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--image-size: expected WIDTHxHEIGHT, e.g. 1242x375, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise InputError(f"--image-size: width and height must be > 0, got {text!r}")
    return w, h


def _shot_options(p: argparse.ArgumentParser) -> None:
    """SHOT or --left/--right (checked by :func:`_check_views`), and the calibration."""
    p.add_argument("shot", type=Path, nargs="?", metavar="SHOT", help="side-by-side sensor image")
    p.add_argument("--left", type=Path, metavar="LEFT", help="left view file (ordinary stereo rig)")
    p.add_argument("--right", type=Path, metavar="RIGHT", help="right view file")
    _calib_options(p)


def _check_views(args: argparse.Namespace) -> None:
    if args.shot is not None and (args.left is not None or args.right is not None):
        raise InputError("give a side-by-side SHOT or --left/--right view files, not both")
    if args.shot is None and (args.left is None or args.right is None):
        raise InputError("give a side-by-side SHOT, or both --left and --right view files")


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.stereo.pipeline import ReconstructOptions, reconstruct_to_files

    _check_views(args)
    options = ReconstructOptions(**given_fields(args, _RECONSTRUCT_OPTIONS))
    rec = reconstruct_to_files(args.shot, list(args.calib), args.output, left_path=args.left,
                               right_path=args.right, disparity_out=args.disparity_out,
                               depth_out=args.depth_out, mesh_out=args.mesh,
                               image_size=_parse_size(args.image_size), options=options,
                               progress=_progress(args, "reconstruct"))
    if args.json:
        _print_json({"output": str(args.output), "points": len(rec.scan), "min_disp": rec.min_disp,
                     "num_disp": rec.num_disp, "noise": rec.noise, "coverage": rec.coverage.as_dict(),
                     "shares": rec.coverage.shares(), "timings_s": rec.timings_s})
        return 0
    t = rec.timings_s
    _say(args, f"wrote {args.output}: {len(rec.scan)} points (disparity {rec.min_disp}..{rec.min_disp + rec.num_disp - 1}; "
               + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()) + ")")
    _say(args, rec.coverage.summary())
    return 0


#: The shot reconstruction's options dataclass: its fields give `reconstruct` its defaults and help.
_RECONSTRUCT_OPTIONS = ("prism3d.reconstruct.stereo.pipeline", "ReconstructOptions")


def _near_far_mm(text: str) -> tuple[float, float]:
    """``NEAR:FAR`` in mm."""
    try:
        lo, hi = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NEAR:FAR in mm, got {text!r}") from None
    return lo, hi


def _add_reconstruct(sub: Any) -> None:
    p = _command(sub, "reconstruct", _cmd_reconstruct,
                 help="one prism shot (or a stereo pair) -> metric scan PLY",
                 description="Rectify the two views of a side-by-side shot (or of --left/--right "
                 "files), match them, refine, and triangulate into a coloured point cloud with "
                 "normals (millimetres, left camera frame). Each point carries its confidence "
                 "(the chance its disparity is within 1 px of the truth), disparity_std (px) "
                 "and depth_std (mm). Prints the share of pixels kept and why the rest were "
                 "dropped.")
    _shot_options(p)
    _output_option(p, "SCAN_PLY")
    p.add_argument("--disparity-out", type=Path, metavar="PFM",
                   help="disparity of the kept pixels (rectified-left grid, inf elsewhere)")
    p.add_argument("--depth-out", type=Path, metavar="TIFF|NPY|NPZ", help="depth in mm (rectified-left grid)")
    p.add_argument("--mesh", type=Path, metavar="PLY", help="also write a mesh of the organised scan")
    opt = functools.partial(field_option, p, _RECONSTRUCT_OPTIONS)
    opt("depth_range_mm", "--depth-range", type=_near_far_mm, metavar="NEAR:FAR")
    opt("min_disp", "--min-disp", type=int)
    opt("num_disp", "--num-disp", type=int)
    opt("min_confidence", "--min-confidence", type=float, metavar="C")
    opt("smooth_sigma_px", "--smooth", type=float, metavar="SIGMA_PX")
    p.add_argument("--json", action="store_true", help="print the result (coverage, timings) as JSON")


def _cmd_triangulate(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.stereo.triangulate import triangulate_to_file

    scan = triangulate_to_file(args.disparity, list(args.calib), args.left, args.output,
                               image_size=_parse_size(args.image_size), max_depth_mm=args.max_depth)
    _say(args, f"wrote {args.output}: {len(scan)} points")
    return 0


def _add_triangulate(sub: Any) -> None:
    p = _command(sub, "triangulate", _cmd_triangulate,
                 help="disparity map -> coloured point cloud (like reprojectImageTo3D)",
                 description="Turn a disparity map (PFM; NaN, inf or <= 0 = no value) into a coloured "
                 "point cloud with normals, millimetres, left camera frame. The disparity is on the "
                 "calibration's rectified-left grid (as prism3d rectify/match write it), or on the "
                 "left image as given for an already-rectified pair (Middlebury/ETH3D calib.txt).")
    p.add_argument("disparity", type=Path, metavar="DISP_PFM")
    _calib_options(p)
    p.add_argument("--left", required=True, type=Path, metavar="LEFT",
                   help="colours: the rectified left view, or the left view as shot")
    _output_option(p, "CLOUD_PLY")
    p.add_argument("--max-depth", type=float, metavar="MM", help="drop points further than this")


def _cmd_convert_calib(args: argparse.Namespace) -> int:
    from prism3d.capture.calib_formats import convert_calibration

    cal = convert_calibration(list(args.calib), args.output, image_size=_parse_size(args.image_size))
    _say(args, f"wrote {args.output} (from {cal.source_format}: baseline {cal.rig.baseline_mm:.3f} mm, "
               f"views {cal.rig.left.size[0]}x{cal.rig.left.size[1]})")
    for note in cal.notes:
        _say(args, f"note: {note}")
    return 0


def _add_convert_calib(sub: Any) -> None:
    p = _command(sub, "convert-calib", _cmd_convert_calib,
                 help="another tool's stereo calibration -> prism3d calibration YAML",
                 description="Read a stereo calibration in any format prism3d understands "
                 "(Middlebury/ETH3D calib.txt, KITTI calib_cam_to_cam.txt, ROS camera_info "
                 "left + right, OpenCV stereo YAML) and write prism3d's OpenCV FileStorage YAML.")
    p.add_argument("calib", type=Path, nargs="+", metavar="CALIB", help="one file, or two (ROS left right; "
                   "OpenCV intrinsics extrinsics)")
    _output_option(p, "CALIB_YAML")
    p.add_argument("--image-size", metavar="WxH", help="each view's size, when the file does not state it")


def _cmd_flatness(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.stereo.flatness import flatness_of_ply

    kw = {}
    if args.focal is not None:
        kw["focal_px"] = args.focal
    if args.baseline is not None:
        kw["baseline_mm"] = args.baseline
    rep = flatness_of_ply(args.scan, region_fraction=args.region, **kw)
    if args.json:
        _print_json(rep.to_dict())
    else:
        print(rep.table())
    return 0


def _add_flatness(sub: Any) -> None:
    p = _command(sub, "flatness", _cmd_flatness,
                 help="the paper's plane-fit accuracy test (Table I) on a plate scan",
                 description="Fit z = ax + by + c by least squares in 5 regions of a flat-plate scan "
                 "(upper left, upper right, centre, lower left, lower right; eq. 9-13) and report "
                 "the RMS residual (eq. 14-15) and the depth resolution z^2/(fB) (eq. 16).")
    p.add_argument("scan", type=Path, metavar="SCAN_PLY")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--region", type=float, default=0.2, help="region side as a fraction of the plate (0.2)")
    p.add_argument("--focal", type=float, help="focal length, px (default: from the scan's header)")
    p.add_argument("--baseline", type=float, help="baseline, mm (default: from the scan's header)")


# --- stitch --------------------------------------------------------------------------------
def _cmd_stitch(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.scan.stitch import StitchOptions, stitch_to_files

    if len(args.scans) < 2:
        raise InputError("stitch needs at least 2 scans")
    opts = StitchOptions(mesh=args.mesh is not None, **given_fields(args, _STITCH_OPTIONS))  # no mesh asked: none built
    res = stitch_to_files(args.scans, args.output, opts, mesh_out=args.mesh, progress=_progress(args, "stitch"),
                          frame=args.frame, front_view=args.front_view)
    _say(args, f"wrote {args.output} ({len(res.points)} points) and {args.output.parent / 'poses.json'}"
               + (f", mesh {args.mesh}" if args.mesh else ""))
    of = res.diagnostics.get("object_frame")
    if of:
        L, W, H = of["extent_mm"]
        _say(args, f"object frame: up from the {of['up_from']}; {L:.1f} x {W:.1f} x {H:.1f} mm (L x W x H)"
                   + ("; front and back may be swapped" if of["forward_ambiguous"] else ""))
    pairs = res.diagnostics.get("pairs", [])
    if pairs:
        _say(args, "registered pairs (pairwise -> in the model; off the surface: spread along the normals, "
                   "vs the scans' own noise):")
    for p in pairs:
        kind = "" if p["kind"] == "odometry" else " (loop" + ("" if p["kept"] else ", discounted") + ")"
        _say(args, f"pair {p['i']}-{p['j']}{kind}: overlap {p['fitness']:.2f} -> {p['final_fitness']:.2f}, "
                   f"inlier RMSE {p['inlier_rmse']:.3g} -> {p['final_inlier_rmse']:.3g} mm "
                   f"(max dist {p['max_correspondence_distance']:.3g} mm), off the surface "
                   f"{p['plane_sigma']:.3g} -> {p['final_plane_sigma']:.3g} mm "
                   f"(noise {p['noise_sigma']:.3g} mm)"
                   + (f"  <- check: {'; '.join(p['check'])}" if p["check"] else ""))
    return 0


#: The stitcher's options dataclass: its fields give `prism3d stitch` its defaults and help.
_STITCH_OPTIONS = ("prism3d.reconstruct.scan.stitch_options", "StitchOptions")


def _add_stitch(sub: Any) -> None:
    p = _command(sub, "stitch", _cmd_stitch,
                 help="register and fuse scans of several views into one 360-degree model",
                 description="Register the scans pairwise (turntable prior or deterministic global "
                 "registration, then multi-scale ICP), optimise a pose graph with loop closure, fuse "
                 "the points and optionally mesh them (screened Poisson). Writes poses.json beside the "
                 "model: T_model_scan for each input.")
    p.add_argument("scans", nargs="+", type=Path, metavar="SCANS", help="PLY or PCD scans in acquisition order")
    _output_option(p, "MODEL_PLY")
    p.add_argument("--mesh", type=Path, metavar="MESH_PLY", help="also write a watertight mesh")
    opt = functools.partial(field_option, p, _STITCH_OPTIONS)
    opt("turntable_step_deg", "--turntable-step", type=float, metavar="DEG")
    opt("voxel", "--voxel", type=float)
    opt("smooth_iterations", "--smooth", type=int, metavar="N")
    opt("min_confidence", "--min-confidence", type=float, metavar="C")
    opt("mesh_max_spacings", "--mesh-max-distance", type=float, metavar="SPACINGS")
    p.add_argument("--frame", choices=["scan", "object"], default="scan",
                   help="scan: the first scan's camera frame (default); object: z up (turntable axis or "
                   "support plane), x along the longest horizontal extent, origin on the support")
    p.add_argument("--front-view", type=int, metavar="K",
                   help="with --frame object: scan K (0 = the first given) faced the object's front, so x "
                   "points at it (without it front and back are a stated guess)")


# --- ATR: decamo / features ------------------------------------------------------------------
def _cmd_decamo(args: argparse.Namespace) -> int:
    from prism3d.atr import decamo

    if args.depth is None:
        if args.calib is None:
            raise InputError("decamo: give DEPTH, or a shot with --calib to reconstruct the depth first")
        out = decamo.decamo_from_shot(args.image, args.calib, args.output)
    else:
        out = decamo.decamo_to_folder(args.image, args.depth, args.output, calib=args.calib,
                                      focal_px=args.focal, view=args.view)
    _say(args, f"wrote albedo.png, shading.tiff, shape.png, false_shadow.png to {args.output}")
    del out
    return 0


def _add_decamo(sub: Any) -> None:
    p = _command(sub, "decamo", _cmd_decamo,
                 help="remove camouflage using depth: albedo, shading, shape image, false shadows",
                 description="Estimate the lighting (2nd-order spherical harmonics) from the image and "
                 "the surface normals of its depth map, separate shading from the piecewise-constant "
                 "paint, and write albedo.png, shading.tiff (float32), shape.png (the surface relit "
                 "with uniform albedo: the true 3D profile) and false_shadow.png. Without DEPTH, IMAGE "
                 "is a prism shot reconstructed with --calib first.")
    p.add_argument("image", type=Path, metavar="IMAGE")
    p.add_argument("depth", nargs="?", metavar="DEPTH",
                   help="depth map in mm: .tiff, .npy, .pfm or FILE.npz:KEY (e.g. truth.npz:depth_left_mm)")
    _output_option(p, "OUT_DIR")
    p.add_argument("--calib", type=Path, help="calibration/rig YAML giving the camera intrinsics")
    p.add_argument("--focal", type=float, metavar="PX", help="focal length in px (principal point at the centre)")
    p.add_argument("--view", choices=["left", "right"], default="left", help="which camera of --calib")


def _cmd_features(args: argparse.Namespace) -> int:
    from prism3d.atr.features import features_to_parquet

    _check_out_not_dir(args.output)
    df = features_to_parquet(args.inputs, args.output, units=args.units, up=args.up, box=args.box,
                             progress=_progress(args, "features"))
    _say(args, f"wrote {args.output}: {len(df)} rows x {df.shape[1]} columns")
    return 0


def _add_features(sub: Any) -> None:
    p = _command(sub, "features", _cmd_features,
                 help="size, profile, range and surface features -> Parquet",
                 description="One row of named, unit-bearing features per model or scan (meshes: OBJ, "
                 "PLY, GLB, OFF, STL; scans: PLY, PCD). Units and up axis are never guessed: give "
                 "--units/--up, or a FILE.units.yaml sidecar. Columns are documented in docs/features.md.")
    p.add_argument("inputs", nargs="+", type=Path, metavar="MODEL_OR_SCAN")
    _output_option(p, "FEATURES_PARQUET")
    p.add_argument("--units", choices=_UNITS, help="units of files that do not declare them")
    p.add_argument("--up", choices=_UP_AXES, help="up axis of files that do not declare it")
    p.add_argument("--box", choices=["auto", "surface", "points"], default="auto",
                   help="scans: boxes of the fitted surface near the data (needs normals) or of every point; "
                   "auto (default): surface when the scan has normals and is dense (>= 200 point spacings across)")


# --- ATR: render / bank ---------------------------------------------------------------------
def _cmd_render(args: argparse.Namespace) -> int:
    from prism3d.atr.chips import ChipSpec, render_to_folder
    from prism3d.datasets.database.resolve import resolve_model

    spec = ChipSpec(**given_fields(args, _CHIP_SPEC))  # its seed paints a built-in target too
    if Path(args.model).is_file():
        model: Any = resolve_model(args.model, units=args.units, up=args.up, forward=args.forward,
                                   seed=spec.seed, length_mm=args.length_mm)[1]  # flags, sidecar, PLY header; rescaled
    else:
        if args.length_mm is not None:
            raise InputError(f"--length-mm: {args.model} is a built-in target (its length is fixed); "
                             "the flag rescales mesh files")
        model = resolve_model(args.model, seed=spec.seed)[1]  # painted; ChipSpec.camouflage decides
    manifest = render_to_folder(model, args.output, azimuth=args.azimuth, elevation=args.elevation,
                                range_mm=args.range, chip_spec=spec, fmt=args.format)
    _say(args, f"wrote chips and {manifest}")
    return 0


#: The chip settings: `render --size --framing --channels --no-camouflage --clutter --noise --seed --backend`.
_CHIP_SPEC = ("prism3d.atr.chips", "ChipSpec")


def _add_render(sub: Any) -> None:
    p = _command(sub, "render", _cmd_render,
                 help="render a model at many poses into training chips + manifest",
                 description="Render MODEL (a mesh file or a built-in target name) at every azimuth x "
                 "elevation x range into chips (intensity, depth mm, mask, shape image) and a Parquet "
                 "manifest holding every pose and camera field.")
    p.add_argument("model", metavar="MODEL", help="mesh file (OBJ/PLY/GLB/OFF/STL) or built-in target name")
    _output_option(p, "DIR")
    p.add_argument("--azimuth", default="0:360:10", metavar="A0:A1:STEP", help="degrees (default 0:360:10)")
    p.add_argument("--elevation", default="10:60:25", metavar="E0:E1:STEP", help="degrees (default 10:60:25)")
    p.add_argument("--range", metavar="R1,R2,...", help="camera distances, mm (default: 4 bounding radii)")
    chip = functools.partial(field_option, p, _CHIP_SPEC)
    chip("size", "--size", type=int, metavar="PX")
    chip("framing", "--framing", choices=["fit", "range"])
    chip("pixels_per_m", "--pixels-per-m", type=float, metavar="PX")
    chip("channels", "--channels", nargs="+", choices=_CHANNELS, metavar="CHANNEL")
    p.add_argument("--units", choices=_UNITS, help="units of a mesh file")
    p.add_argument("--up", choices=_UP_AXES, help="up axis of a mesh file that does not declare it")
    p.add_argument("--forward", choices=["x", "-x", "y", "-y", "z", "-z"],
                   help="the axis a mesh file's nose points along, where it does not declare it")
    p.add_argument("--length-mm", type=float, metavar="MM",
                   help="rescale a mesh file to this length (longest horizontal extent); its units then do not matter")
    p.add_argument("--format", choices=["npz", "png"], default="npz", help="chip files (default npz)")
    chip("camouflage", "--no-camouflage", action="store_false", note="given: one uniform grey")
    chip("clutter", "--clutter", choices=["ground", "noise"])
    chip("noise_sigma", "--noise", type=float, metavar="SIGMA")
    chip("seed", "--seed", type=int, note="also the seed of a built-in target's paint")
    chip("backend", "--backend", choices=["raycast", "pyrender"])


def _cmd_bank(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from prism3d.atr.bank import check_bank_command

    check_bank_command(args.action, output=args.output, bank=args.bank,
                       results=args.json)
    _finish_targets(args)
    if args.action == "eval-scenes":
        from prism3d.datasets.simulation.field import eval_scene_folders
        from prism3d.datasets.runner import RunOptions

        res = eval_scene_folders(args.bank, args.scenes, out_json=args.json, run=RunOptions(
            workers=args.workers, scheduler=args.scheduler, progress=_progress(args, "bank eval-scenes")))
        sc = res.score
        for x, v in sc.at_fppi.items():
            _say(args, f"at {x} false positives per image: Pd {v.pd:.3f}, identification "
                       f"{v.id_accuracy:.3f}, confusers called {v.confusers_called:.3f}")
        _say(args, f"{sc.n_images} scenes, {sc.n_targets} targets, {sc.n_confusers} confusers; "
                   f"highest Pd {sc.pd_max:.3f}")
        return 0
    if args.scenes:
        raise InputError(f"bank {args.action}: unexpected arguments {' '.join(args.scenes)}")
    if args.action == "train":
        return _bank_train(args)
    if args.workers or args.scheduler:
        raise InputError("bank eval: --workers and --scheduler are for train and eval-scenes")
    from prism3d.atr.evaluate import EVAL_CHIP_SPEC, evaluate_bank, format_results, heldout_seed, relief_noise_mm
    from prism3d.atr.models import load_scene_model, model_kind
    from prism3d.atr.verifier import SceneRecogniser

    if model_kind(args.bank) == "aerial_recogniser":
        raise InputError(f"{args.bank}: an aerial recogniser; bank eval scores ground-level banks (score an aerial "
                         "one with survey-detect on a simulated flight: benchmarks/bench_carpark.py)")
    model = load_scene_model(args.bank)
    bank = model.banks[0] if isinstance(model, SceneRecogniser) else model
    args.seed = heldout_seed(args.seed)
    targets = _targets_for(args)
    if isinstance(model, SceneRecogniser):  # a refused built-in is scored as the class of its own it is in the bank
        targets = [(m.name if m.name in bank.classes and c not in bank.classes else c, m) for c, m in targets]
    spec = replace(EVAL_CHIP_SPEC, camouflage=args.camouflage, noise_sigma=args.noise,
                   depth_noise_mm=relief_noise_mm(targets, args.noise), clutter="noise" if args.clutter else None)
    scored = given_fields(args, _BANK_OPTIONS)
    res = evaluate_bank(bank, targets, azimuth=scored.get("azimuth"), elevation=scored.get("elevation"), chip_spec=spec,
                        out_json=args.json)
    _say(args, format_results(res))
    return 0


def _bank_train(args: argparse.Namespace) -> int:
    """``bank train``: filters alone (``--scenes 0``), a scene recogniser (filters over the
    targets and what to refuse, a verifier mined from simulated scenes) or, ``--view nadir``,
    an aerial recogniser."""
    from dataclasses import replace

    from prism3d.atr.bank import BANK_CHIP_SPEC, BankOptions, train_bank
    from prism3d.datasets.runner import RunOptions, check_scheduler
    from prism3d.datasets.jobs.mining import DEFAULT_SCENES, MiningOptions
    from prism3d.datasets.jobs.recognisers import aerial_recogniser, scene_recogniser

    given = given_fields(args, _BANK_OPTIONS)
    if args.view == "nadir":
        if given or args.scenes_n is not None or args.channel is not None:
            raise InputError("bank train --view nadir: the aerial recogniser takes no --azimuth, --elevation, "
                             "--bin-deg, --scenes or --channel")
        model, _ = aerial_recogniser(_targets_for(args, scale="full"), cache=False,
                                     progress=_progress(args, "bank train (aerial)"))
        model.save(args.output)
        _say(args, f"wrote {args.output}: aerial recogniser of {', '.join(model.classes)}")
        return 0
    targets = _targets_for(args)
    spec = replace(BANK_CHIP_SPEC, size=args.size, camouflage=args.camouflage)
    scenes = DEFAULT_SCENES if args.scenes_n is None else args.scenes_n
    how = BankOptions(**given)
    if scenes == 0:
        bank = train_bank(targets, channel=args.channel or "depth", chip_spec=spec, **how.train_kwargs())
        bank.save(args.output)
        _say(args, f"wrote {args.output}: {len(bank.classes)} classes, channel {bank.channel} (filters only)")
        return 0
    if args.channel is not None:
        raise InputError("bank train: --channel is for the filters alone (--scenes 0); a recogniser uses --channels")
    run = RunOptions(workers=args.workers, scheduler=args.scheduler)
    check_scheduler(args.scheduler)  # reached before the banks are trained, not only when mining starts
    mining = MiningOptions(scenes=scenes, channels=tuple(args.channels), chip_spec=spec, bank=how)
    model, _ = scene_recogniser(targets, mining, run=run, cache=False, progress=_progress(args, "bank train"))
    model.save(args.output)
    rows = model.metadata["mining"]["rows"]
    _say(args, f"wrote {args.output}: recogniser of {', '.join(model.targets)} refusing "
               f"{len(model.banks[0].classes) - len(model.targets)} classes; channels {', '.join(model.channels)}; "
               f"verifier from {scenes} scenes ({rows['positive']} target and {rows['negative']} other objects)")
    return 0


#: A bank's training views: `bank train --azimuth --elevation --bin-deg`.
_BANK_OPTIONS = ("prism3d.atr.bank", "BankOptions")


def _add_bank(sub: Any) -> None:
    p = _command(sub, "bank", _cmd_bank,
                 help="train a recogniser on rendered models (and simulated scenes); evaluate it",
                 description="train: OT-MACH filters (one per class and aspect bin, parameters chosen on held-out "
                 "views) over the targets and over what to refuse (the other built-in vehicles, crates, fuel "
                 "tanks), in the shape and depth channels, and a verifier on their responses, the objects' 3D size "
                 "and range, mined from --scenes simulated field scenes (--scenes 0: the filters alone, the paper's "
                 "bank); --view nadir: an aerial recogniser for survey-detect. eval: classify unseen poses and report "
                 "Pcc, confusion, per-aspect accuracy and ROC; eval-scenes: detect in scene folders, Pd vs false "
                 "positives per image. Method: docs/atr.md.")
    p.add_argument("action", choices=["train", "eval", "eval-scenes"])
    p.add_argument("bank", nargs="?", type=Path, metavar="MODEL_NPZ", help="eval, eval-scenes: the model file")
    p.add_argument("scenes", nargs="*", metavar="SCENE_DIR",
                   help="eval-scenes: scene folders from 'prism3d simulate field' (detect, then Pd vs FPPI)")
    _add_target_options(p, ["builtin"])
    p.add_argument("-o", "--output", type=Path, metavar="MODEL_NPZ", help="train: output model")
    p.add_argument("--view", choices=["ground", "nadir"], default="ground",
                   help="train: ground-level shots (default) or a survey's orthophoto and nDSM (nadir)")
    p.add_argument("--scenes", dest="scenes_n", type=int, default=None, metavar="N",
                   help="train: simulated field scenes the verifier is mined from (default 40; 0: filters alone)")
    p.add_argument("--channels", nargs="+", default=["shape", "depth"], choices=["intensity", "depth", "shape"],
                   help="train: a recogniser's filter channels (default shape depth)")
    p.add_argument("--channel", choices=["intensity", "depth", "shape"], default=None,
                   help="train --scenes 0: the filters' channel (default depth)")
    grid = functools.partial(field_option, p, _BANK_OPTIONS)
    grid("azimuth", "--azimuth", metavar="A0:A1:STEP",
         note="eval: the azimuths scored (default: half-way between the training azimuths)")
    grid("elevation", "--elevation", metavar="E0:E1:STEP", note="eval: the elevations scored (default: the same)")
    grid("bin_deg", "--bin-deg", type=float, metavar="DEG")
    p.add_argument("--size", type=int, default=64, help="chip side, px (default 64)")
    p.add_argument("--camouflage", dest="camouflage", action="store_true", default=True)
    p.add_argument("--no-camouflage", dest="camouflage", action="store_false")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="eval: noise std, as a share of the intensity range and of the depth relief")
    p.add_argument("--clutter", action="store_true", help="eval: clutter backgrounds and clutter-only chips")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, metavar="RESULTS_JSON",
                   help="eval, eval-scenes: write results (+ plots beside it)")
    p.add_argument("--workers", type=int, default=0,
                   help="train (mining scenes), eval-scenes: local Dask workers, one scene each (0 = in this process)")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="train, eval-scenes: an existing Dask scheduler")


# --- detect ----------------------------------------------------------------------------------
def _parse_depth_range(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        a, b = (float(v) for v in text.split(":"))
    except ValueError:
        raise InputError(f"--depth-range: expected NEAR:FAR in metres, got {text!r}") from None
    if not (0 < a < b):
        raise InputError(f"--depth-range: expected 0 < NEAR < FAR, got {text!r}")
    return a * 1000.0, b * 1000.0


def _cmd_detect(args: argparse.Namespace) -> int:
    from prism3d.atr.detect import DetectOptions, SceneSource, detect_to_file, read_scene_source
    from prism3d.atr.models import load_scene_model, model_kind

    _finish_targets(args)
    if args.bank is not None and (args.targets_given or args.db is not None):
        raise InputError("detect: give --bank (a trained model) or --targets/--db, not both")
    depth_range = _parse_depth_range(args.depth_range)
    # every input read before a recogniser is loaded or trained (minutes)
    src = read_scene_source(SceneSource(shot=args.shot, calib=args.calib, image=args.image, depth=args.depth,
                                        fx=args.fx), output=args.output, draw=args.draw, depth_range_mm=depth_range,
                            models=([args.bank] if args.bank is not None else [])
                            + [t for t in args.targets if model_kind(t) is not None])
    if args.bank is not None:
        model, how = load_scene_model(args.bank), str(args.bank)
    elif len(args.targets) == 1 and model_kind(args.targets[0]) is not None:
        model, how = load_scene_model(args.targets[0]), args.targets[0]
    else:
        from prism3d.atr.bank import BANK_CHIP_SPEC
        from prism3d.datasets.jobs.mining import MiningOptions
        from prism3d.datasets.jobs.recognisers import scene_recogniser

        model, info = scene_recogniser(_targets_for(args), MiningOptions(chip_spec=BANK_CHIP_SPEC),
                                       cache=not args.no_cache, progress=_progress(args, "training the recogniser"))
        how = "cached recogniser" if info["cached"] else "recogniser trained now"
    doc = detect_to_file(model, args.output, src, depth_range_mm=depth_range, draw=args.draw, source_name=how,
                         options=DetectOptions(**given_fields(args, _DETECT_OPTIONS)))
    t = doc["timings_s"]
    _say(args, f"wrote {args.output}: {len(doc['detections'])} detections ({how}; "
               + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in t.items()) + ")")
    return 0


#: How detect searches a scene: `detect --min-height --ground-cell --max-detections --band-scan`.
_DETECT_OPTIONS = ("prism3d.atr.scene", "DetectOptions")


def _add_detect(sub: Any) -> None:
    p = _command(sub, "detect", _cmd_detect,
                 help="find and identify targets in a whole shot (or image + depth map)",
                 description="Reconstruct the shot, find the ground and the objects standing on it, then judge "
                 "each object with a recogniser (filter responses over the targets and what to refuse, 3D size, "
                 "range; 'bank train') or slide a bank's filters over the scene. Writes detections (pixel, 3D "
                 "point, class, score), best first: threshold them, or score them with 'bank eval-scenes'. "
                 "Method: docs/atr.md.")
    p.add_argument("shot", nargs="?", type=Path, metavar="SHOT", help="prism shot (with --calib)")
    p.add_argument("--calib", type=Path, help="rig or calibration YAML of the shot")
    p.add_argument("--bank", type=Path, help="a trained bank or recogniser (.npz from 'bank train')")
    _add_target_options(p, ["builtin"])
    p.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--no-cache", action="store_true", help="with --targets: train again, and do not keep it")
    p.add_argument("--image", type=Path, help="instead of a shot: an image ...")
    p.add_argument("--depth", type=Path, help="... with its depth map in mm (.npy, .tiff, .pfm, .npz[:key])")
    p.add_argument("--fx", type=float, help="focal length of --image, px")
    p.add_argument("--depth-range", metavar="NEAR:FAR",
                   help="shot: depths searched, metres (default 0.3x to 10x the rig's convergence distance)")
    p.add_argument("--draw", type=Path, metavar="PNG", help="also draw the detections on the image")
    search = functools.partial(field_option, p, _DETECT_OPTIONS)
    search("min_height_mm", "--min-height", type=float, metavar="MM")
    search("ground_cell_mm", "--ground-cell", type=float, metavar="MM")
    search("max_detections", "--max-detections", type=int, metavar="N")
    search("band_scan", "--band-scan", action="store_true")
    _output_option(p, "DETECTIONS_JSON")


# --- the survey mode ------------------------------------------------------------------------
def _cmd_survey(args: argparse.Namespace) -> int:
    from prism3d.reconstruct.survey.run import SurveyOptions, run_survey

    opts = SurveyOptions(**given_fields(args, _SURVEY_OPTIONS))
    run_pairs = None
    if args.workers or args.scheduler:
        from prism3d.datasets.runner import RunOptions, run_survey_pairs

        run = RunOptions(workers=args.workers, scheduler=args.scheduler, retries=0)

        def run_pairs(reqs: list, progress: Any) -> list:
            return run_survey_pairs(reqs, run, progress)
    s = run_survey(args.images, args.output, calib=args.calib, gps_table=args.gps, options=opts,
                   progress=_progress(args, "survey", stage_lines=True), run_pairs=run_pairs, video_step_s=args.video_step,
                   resume=args.resume)
    unit = "m" if s["scale"] != "unknown" else "units (scale unknown: no GPS)"
    r = s["resumed"]
    if r["poses"] or r["pairs_reused"]:
        _say(args, f"survey: resumed: poses {'kept' if r['poses'] else 'computed'}, {r['pairs_reused']} pairs kept, "
                   f"{r['pairs_matched']} matched")
    if "gcp_check" in s:
        _say(args, "survey: " + s["gcp_check"])
    _say(args, f"survey: {s['n_registered']}/{s['n_frames']} frames placed, reprojection RMS "
               f"{s['reprojection_rms_px']:.2f} px; {s['pairs_ok']} pairs matched, {s['pairs_skipped']} skipped; "
               f"DSM of {s['dsm_cells']:,} cells of {s['cell']:g} {unit}; {s['seconds']['total']:.0f} s -> {args.output}")
    return 0


def _gps_accuracy(text: str) -> tuple[float, float]:
    """``--gps-accuracy H[,V]`` (m; V defaults to 2 H) as (horizontal, vertical)."""
    try:
        v = [float(a) for a in text.split(",")]
    except ValueError:
        v = []
    if len(v) not in (1, 2):
        raise argparse.ArgumentTypeError(f"expected H or H,V in metres, got {text!r}")
    return (v[0], v[1] if len(v) == 2 else 2.0 * v[0])


#: The survey's options dataclass: its fields give `prism3d survey` its defaults and help.
_SURVEY_OPTIONS = ("prism3d.reconstruct.survey.model", "SurveyOptions")


def _add_survey(sub: Any) -> None:
    p = _command(sub, "survey", _cmd_survey,
                 help="drone survey: frames of one moving camera -> poses, point cloud, DSM, orthophoto",
                 description="The UAV mode: camera poses and intrinsics from the frames (pycolmap's "
                 "incremental mapping with bundle adjustment), put in metres in a local east-north-up "
                 "frame by the GPS (--gps table or EXIF; without either the scale is unknown and every "
                 "output says so); each frame matched with the next and the next-but-one by our stereo "
                 "matcher, the pairs' heights fused with a consistency check. Writes OUT/poses.json, "
                 "cloud.ply (local frame), cloud.las (or .laz; ASPRS ground class), dsm.tif, ground.tif, ndsm.tif, "
                 "ortho.tif (a true orthophoto at the photographs' own ground sample distance), ortho_quality.tif "
                 "(Cloud-Optimised GeoTIFFs in the site's UTM zone by default, heights above the WGS84 ellipsoid), "
                 "survey.png, depth/ and colmap/ (a COLMAP text model). Method: docs/uav.md.")
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGE_OR_VIDEO",
                   help="frames in flight order, or one video (.mp4 .mov .avi .mkv .m4v)")
    p.add_argument("--video-step", type=float, default=1.0, metavar="S",
                   help="a video's frames are taken every S seconds into OUT/frames/ (default 1)")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="OUT_DIR", help="new folder for the survey")
    p.add_argument("--calib", type=Path, help="starting calibration of the camera (OpenCV/ROS YAML; "
                   "default: the EXIF focal length, principal point at the centre)")
    p.add_argument("--gps", type=Path, metavar="TABLE", help="positions table (senseFly geoinfo.txt or CSV "
                   "with fileName, latitude, longitude, altitude; default: the frames' EXIF GPS)")
    opt = functools.partial(field_option, p, _SURVEY_OPTIONS)
    opt("cell_m", "--cell", type=float, metavar="M")
    opt("ortho_gsd_m", "--ortho-gsd", type=float, metavar="M")
    opt("crs", "--crs", metavar="utm|enu|EPSG:CODE")
    opt("laz", "--laz", action="store_true")
    opt("cloud_spacing_m", "--cloud-spacing", type=float, metavar="M")
    opt("matching", "--matching", choices=["auto", "exhaustive", "spatial", "sequential"])
    p.add_argument("--resume", action="store_true",
                   help="reuse the poses and finished pairs an interrupted run of this same command kept "
                   "(in .OUT.resume beside OUT; frames, not a video); without it such leftovers are removed")
    opt("pair_steps", "--pair-steps", type=int, nargs="+", metavar="K")
    opt("cross_pairs", "--cross-pairs", action=argparse.BooleanOptionalAction)
    opt("max_image_size", "--max-image-size", type=int, metavar="PX")
    opt("dense_max_pixels", "--dense-max-pixels", type=float, metavar="N")
    opt("refine_intrinsics", "--refine", choices=["auto", "focal+distortion", "none"])
    opt("refine_principal_point", "--refine-principal-point", action="store_true")
    opt("gcp_file", "--gcp", metavar="GCP_LIST")
    opt("gcp_check", "--gcp-check", nargs="+", metavar="NAME")
    opt("gps_accuracy", "--gps-accuracy", type=_gps_accuracy, metavar="H[,V]")
    opt("gps_prior", "--gps-prior", action=argparse.BooleanOptionalAction)
    p.add_argument("--workers", type=int, default=0, help="dense pairs on a local Dask cluster of W processes")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="dense pairs on an existing Dask scheduler")


def _targets_for(args: argparse.Namespace, *, scale: str = "model") -> list:
    """The command's target list: ``--db`` or ``--targets`` specs (the datasets.database.resolve rules)."""
    from prism3d.datasets.database.resolve import resolve_db_targets, resolve_targets

    if getattr(args, "db", None) is not None:
        if args.targets_given:
            raise InputError("give --targets or --db, not both")
        return resolve_db_targets(args.db, scale=scale)
    return resolve_targets(args.targets, units=args.units, up=args.up, forward=args.forward, seed=args.seed,
                           length_mm=args.length_mm, scale=scale)


def _add_target_options(p: argparse.ArgumentParser, default: list[str], *, db: bool = True) -> None:
    """The one target list of bank, detect and survey-detect (datasets/database/resolve.py)."""
    p.add_argument("--targets", nargs="+", default=None, metavar="SPEC",
                   help="built-in names (tank_t1, car_kei), classes (car van truck bus tank jet ship), 'builtin' "
                   "(the military set), 'civilian', or mesh files FILE[=CLASS[:UNITS[:UP[:FORWARD]]]] "
                   f"(default: {' '.join(default)})")
    if db:
        p.add_argument("--db", type=Path, metavar="DB", help="the targets of a target database instead")
    p.add_argument("--units", choices=_UNITS, help="units of mesh files that do not declare them")
    p.add_argument("--up", choices=_UP_AXES, help="up axis of mesh files that do not declare it")
    p.add_argument("--forward", choices=["x", "-x", "y", "-y", "z", "-z"],
                   help="the axis a mesh file's nose points along, where it does not declare it")
    p.add_argument("--length-mm", type=float, metavar="MM",
                   help="rescale every mesh file to this length (longest horizontal extent); units then do not matter")
    p.set_defaults(target_default=list(default))


def _finish_targets(args: argparse.Namespace) -> None:
    args.targets_given = args.targets is not None
    if args.targets is None:
        args.targets = list(args.target_default)


def _cmd_survey_detect(args: argparse.Namespace) -> int:
    from prism3d.atr.aerial import AerialModel
    from prism3d.atr.survey_detect import check_survey_request, detect_in_survey, load_survey_scene
    from prism3d.datasets.jobs.recognisers import aerial_recogniser
    from prism3d.atr.models import model_kind

    _finish_targets(args)
    # the survey and outputs first: loading or training a recogniser must not precede a refusal
    check_survey_request(args.survey, args.output, threshold=args.threshold, draw=args.draw)
    models = [t for t in args.targets if model_kind(t) is not None]
    if models:
        if len(args.targets) != 1 or args.db is not None:
            raise InputError("--targets: a trained model file stands alone (it names its own classes)")
        kind = model_kind(models[0])
        if kind != "aerial_recogniser":
            raise InputError(f"{models[0]}: a {kind} model, trained for ground-level shots; survey-detect needs an "
                             "aerial recogniser ('prism3d bank train --view nadir')")
        model, how = AerialModel.load(models[0]), "model file"
    else:
        targets = _targets_for(args, scale="full")

        def read_survey(options: Any) -> None:  # its contents, at the grid the model will have
            load_survey_scene(args.survey, options.gsd_m, appearance=options.channels != "height",
                              height=options.channels != "appearance")

        model, info = aerial_recogniser(targets, cache=not args.no_cache, before_training=read_survey,
                                        progress=_progress(args, "training the aerial recogniser"))
        how = "cached" if info["cached"] else "trained now" + (f", cached in {info['path']}" if info["path"] else "")
    s = detect_in_survey(args.survey, args.output, model, threshold=args.threshold,
                         all_candidates=args.all_candidates, draw=args.draw)
    by = ", ".join(f"{c} {n}" for c, n in sorted(s["by_class"].items())) or "none"
    _say(args, f"wrote {args.output}: {s['n_vehicles']} vehicles ({by}) at score >= {s['threshold']:.2f}"
               + (f", {s['n_written']} candidates in all" if args.all_candidates else "")
               + f"; recogniser {how}; {s['seconds']['total']:.1f} s")
    return 0


def _add_survey_detect(sub: Any) -> None:
    p = _command(sub, "survey-detect", _cmd_survey_detect,
                 help="find and name vehicles in a survey (orthophoto + nDSM) -> GeoJSON in WGS84",
                 description="Vehicles in a survey folder: the orthophoto's appearance and the nDSM's height "
                 "read by a recogniser trained on the targets' models rendered from above at every heading, in car "
                 "parks and among clutter (trained once per target list, then cached). One GeoJSON Feature per "
                 "vehicle: a WGS84 point with properties class, score (calibrated), heading_deg (long axis, "
                 "0-180), footprint (a polygon), sizes and local x/y/z. Method: docs/atr.md.")
    p.add_argument("survey", type=Path, metavar="SURVEY_DIR", help="a folder written by 'prism3d survey'")
    _add_target_options(p, ["car", "van", "truck", "bus"])
    p.add_argument("--seed", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--threshold", type=float, default=None, metavar="P",
                   help="report vehicles scoring at least P (default 0.5: half of the recogniser's held-out "
                   "detections at that score were vehicles)")
    p.add_argument("--all-candidates", action="store_true", help="write every candidate, best first, with its score")
    p.add_argument("--draw", type=Path, metavar="PNG", help="also draw the detections on the orthophoto")
    p.add_argument("--no-cache", action="store_true", help="train the recogniser again, and do not keep it")
    _output_option(p, "VEHICLES_GEOJSON")


# --- datasets: the target database ---------------------------------------------------------
def _cmd_db(args: argparse.Namespace) -> int:
    from prism3d.datasets.database import db as dbm

    a = args.db_action
    if a == "init":
        dbm.init_db(args.db)
        _say(args, f"created target database {args.db}")
        return 0
    if a == "add":
        from prism3d.datasets.database import ingest

        if dbm.check_add_request(args.meshes, args.builtin, args.target_class) == "builtin":
            rep = ingest.add_builtin(args.db, args.builtin or None, strict=args.strict)
        else:
            yaw = args.yaw
            if args.forward is not None:  # the nose's axis, turned onto +x (datasets/database/resolve.py's rule)
                from prism3d.io.units import forward_yaw_deg

                try:
                    yaw += forward_yaw_deg(args.forward, args.up or "z")
                except ValueError as exc:
                    raise InputError(f"--forward: {exc}") from None
            rep = ingest.add_meshes(args.db, args.meshes, target_class=args.target_class, units=args.units,
                                    up=args.up, length_mm=args.length_mm, yaw_deg=yaw, strict=args.strict)
        _say(args, rep.summary())
        return 0
    if a == "render":
        from prism3d.atr.chips import ChipSpec
        from prism3d.datasets.jobs.database_jobs import RunOptions, run_render_job

        spec = ChipSpec(**given_fields(args, _CHIP_SPEC))
        run = RunOptions(workers=args.workers, scheduler=args.scheduler, progress=_progress(args, "render"))
        rep = run_render_job(args.db, args.job, **given_fields(args, _RENDER_SPEC), range_mm=args.range,
                             chip_spec=spec, targets=args.targets, classes=args.classes, run=run)
        return _job_result(args, rep)
    if a == "features":
        from prism3d.datasets.jobs.database_jobs import RunOptions, run_features_job

        run = RunOptions(workers=args.workers, scheduler=args.scheduler, progress=_progress(args, "features"))
        rep = run_features_job(args.db, args.job, run=run)
        return _job_result(args, rep)
    if a == "info":
        from prism3d.datasets.jobs.database_jobs import database_info

        info = database_info(dbm.open_db(args.db))
        print(json.dumps(info.to_json(), indent=2, sort_keys=True) if args.json else info.text())
        return 0
    problems = dbm.verify_db(args.db)
    for p in problems:
        print(p)
    _say(args, "verify: OK" if not problems else f"verify: {len(problems)} problem(s)")
    return 1 if problems else 0


def _job_result(args: argparse.Namespace, rep: Any) -> int:
    """Print a job's summary; a job with failed units is an error (exit 2, one line)."""
    _say(args, rep.summary())
    if not rep.ok:
        raise DatasetError(rep.failure_line())
    return 0


#: A render job's grid: `db render --azimuth --elevation` (its chips: `_CHIP_SPEC`).
_RENDER_SPEC = ("prism3d.datasets.jobs.database_jobs", "RenderSpec")


def _add_db(sub: Any) -> None:
    p = _command(sub, "db", _cmd_db,
                 help="the target database: init, add, render, features, info, verify",
                 description="A target database is a folder (format: datasets/FORMAT.md) readable by "
                 "pandas, pyarrow and DuckDB: targets, normalised models, render jobs (chips + Parquet "
                 "manifests), feature tables. Jobs are split into units, resume where they stopped and "
                 "run in-process or on a Dask cluster.")
    dsub = p.add_subparsers(dest="db_action", metavar="ACTION", required=True, parser_class=_Parser)

    def action(name: str, help: str, description: str) -> argparse.ArgumentParser:
        q = dsub.add_parser(name, help=help, description=description)
        _global_options(q, top=False)
        q.add_argument("db", type=Path, metavar="DB")
        return q

    action("init", "create an empty database", "Create an empty target database.")
    q = action("add", "add mesh files (with --class) or the built-in targets",
               "Add targets. Mesh files need --class, and --units/--up unless a "
               "FILE.units.yaml sidecar declares them (never guessed). Duplicates (same content hash) "
               "are skipped (--strict: an error).")
    q.add_argument("meshes", nargs="*", type=Path, metavar="MESH")
    q.add_argument("--builtin", nargs="*", metavar="NAME",
                   help="add built-in targets by name (no names: the 12 military ones; the civilian: car_sedan ...)")
    q.add_argument("--class", dest="target_class", metavar="C", help="class of the mesh files")
    q.add_argument("--forward", choices=["x", "-x", "y", "-y", "z", "-z"],
                   help="the files' axis their nose points along (turned onto +x, as FORWARD in target specs)")
    q.add_argument("--units", choices=_UNITS)
    q.add_argument("--up", choices=_UP_AXES)
    q.add_argument("--length-mm", type=float, help="rescale each mesh to this length, mm")
    q.add_argument("--yaw", type=float, default=0.0, metavar="DEG", help="turn about up so x is forward")
    q.add_argument("--strict", action="store_true", help="a duplicate is an error")
    q = action("render", "render job: chips of every target at every pose (resumable)",
               "Render every target at azimuth x elevation x range into chips and "
               "manifest parts. Re-running resumes; --workers N uses a local Dask cluster, "
               "--scheduler an existing one.")
    q.add_argument("--job", required=True, metavar="NAME")
    job = functools.partial(field_option, q, _RENDER_SPEC)
    job("azimuth", "--azimuth", metavar="A0:A1:STEP")
    job("elevation", "--elevation", metavar="E0:E1:STEP")
    q.add_argument("--range", metavar="R1,R2,...", help="camera distances, mm")
    chip = functools.partial(field_option, q, _CHIP_SPEC)
    chip("size", "--size", type=int, metavar="PX")
    chip("channels", "--channels", nargs="+", choices=_CHANNELS, metavar="CHANNEL")
    q.add_argument("--targets", nargs="+", metavar="ID", help="only these target ids")
    q.add_argument("--classes", nargs="+", metavar="C", help="only these classes")
    chip("framing", "--framing", choices=["fit", "range"])
    chip("camouflage", "--no-camouflage", action="store_false", note="given: one uniform grey")
    chip("seed", "--seed", type=int, note="the job's seed: each unit derives its own")
    q.add_argument("--workers", type=int, default=0, help="local Dask workers (0 = in this process)")
    q.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="an existing Dask scheduler")
    q = action("features", "features job over a render job's chips and the models",
               "Compute view features of every chip of a render job (and model features "
               "of every target) into Parquet parts; resumable like render.")
    q.add_argument("--job", required=True, metavar="NAME")
    q.add_argument("--workers", type=int, default=0)
    q.add_argument("--scheduler", metavar="tcp://HOST:PORT")
    q = action("info", "counts per table, class and job", "Summarise the database.")
    q.add_argument("--json", action="store_true")
    action("verify", "check files, hashes, paths and schema versions",
           "Every manifest row has its files, hashes match, no path escapes the "
           "database folder, schema versions are known. Exit 1 listing problems.")


# --- registry ---------------------------------------------------------------------------
_COMMANDS: list[Callable[[Any], None]] = [
    _add_demo,
    _add_simulate,
    _add_calibrate,
    _add_convert_calib,
    _add_rectify,
    _add_match,
    _add_reconstruct,
    _add_triangulate,
    _add_flatness,
    _add_stitch,
    _add_decamo,
    _add_features,
    _add_render,
    _add_bank,
    _add_detect,
    _add_survey,
    _add_survey_detect,
    _add_db,
    _add_trigger,
    _add_capture,
]


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="prism3d",
        description="One flash photograph through a prism stereo adapter -> a calibrated, "
        "metric 3D model; ATR datasets and features on that 3D core.",
        epilog="Run 'prism3d COMMAND --help' for a command's options. Lengths: millimetres in the "
        "prism stereo core, metres in the drone survey (survey, survey-detect, simulate flight); "
        "angles degrees. Docs: README.md, docs/cli.md.",
    )
    parser.add_argument("--version", action="version", version=f"prism3d {__version__}")
    _global_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in _COMMANDS:
        add(sub)
    return parser


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that staging folders, locks and child processes are
    cleaned up on the way out (the default SIGTERM kills without unwinding)."""


def _on_sigterm(signum: int, frame: Any) -> None:
    raise _Terminated()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``prism3d`` console script."""
    old_term = None
    if threading.current_thread() is threading.main_thread():
        old_term = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return _main(argv)
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def run() -> int:
    """The console script: :func:`main`, then the interpreter's teardown (up to a second
    with numba and Dask loaded) with SIGTERM ending the process with ``main``'s exit
    code: its outputs are in place by then, and a signal death would report them lost."""
    rc = main()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: os._exit(rc))
    return rc


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if args.max_pixels is not None and args.max_pixels <= 0:
        parser.error(f"--max-pixels: expected a number of pixels > 0, got {args.max_pixels}")
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    levels = _quiet_other_libraries(level, verbose=args.verbose > 0)
    before = os.environ.get("PRISM3D_MAX_PIXELS")
    if args.max_pixels is not None:
        os.environ["PRISM3D_MAX_PIXELS"] = str(args.max_pixels)  # read where images are decoded
    try:
        return _run(args)
    finally:  # main() called in-process leaves the environment and logging as it found them
        if before is None:
            os.environ.pop("PRISM3D_MAX_PIXELS", None)
        else:
            os.environ["PRISM3D_MAX_PIXELS"] = before
        for name, lvl in levels.items():
            logging.getLogger(name).setLevel(lvl)


#: Commands whose -o names a folder (the others write a file).
_FOLDER_OUTPUT = {"rectify", "decamo", "render", "capture", "survey"}
#: Arguments that name an output file when they hold a path.
_FILE_OUTPUT_ARGS = ("output", "mesh", "depth_out", "disparity_out", "valid_out", "json", "link", "draw")


def _check_command_outputs(args: argparse.Namespace) -> None:
    """Every output a command names, checked before it starts work (atomic.check_outputs)."""
    from prism3d.io.atomic import check_outputs

    files, folders = [], []
    for name in _FILE_OUTPUT_ARGS:
        v = getattr(args, name, None)
        if isinstance(v, Path):
            (folders if name == "output" and args.command in _FOLDER_OUTPUT else files).append(v)
    if isinstance(getattr(args, "out_dir", None), Path):
        folders.append(args.out_dir)
    if args.command == "db" and getattr(args, "db_action", None) == "init":
        folders.append(args.db)
    if args.command == "stitch" and isinstance(args.output, Path):
        files.append(args.output.parent / "poses.json")
    check_outputs(files, folders)


def _run(args: argparse.Namespace) -> int:
    """Run the chosen command; a Prism3dError or a file-system refusal is one line, exit 2."""
    from prism3d.progress import compile_notice

    try:
        _check_command_outputs(args)
        with compile_notice(quiet=args.quiet):  # one stderr line if kernels must compile
            rc = args.func(args)
    except Prism3dError as exc:
        msg = " ".join(str(exc).split())  # one line
        print(f"prism3d {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        term = isinstance(exc, _Terminated)
        print(f"prism3d {args.command}: {'terminated' if term else 'interrupted'}", file=sys.stderr)
        return 143 if term else 130
    except BrokenPipeError:  # output piped into e.g. `head`: not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the file system said no: read-only, not a folder, disk full...
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"prism3d {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    return int(rc or 0)


def _quiet_other_libraries(level: int, *, verbose: bool) -> dict[str, int]:
    """prism3d's own records at ``level``; other libraries' warnings (numpy, Pillow,
    tifffile, Python ``warnings``, OpenCV's own log) only with -v: set on the loggers,
    so it holds whatever handlers a host (a notebook, a test runner) installed. Returns
    the levels it replaced, for :func:`main` to put back."""
    logging.captureWarnings(True)  # warnings.warn -> the "py.warnings" logger
    root, ours = logging.getLogger(), logging.getLogger("prism3d")
    old = {"": root.level, "prism3d": ours.level}
    ours.setLevel(level)
    root.setLevel(level if verbose else logging.ERROR)
    if not verbose and "OPENCV_LOG_LEVEL" not in os.environ:  # "[ WARN:0] can't open camera"
        os.environ["OPENCV_LOG_LEVEL"] = "ERROR"  # read when cv2 loads
        cv2 = sys.modules.get("cv2")
        if cv2 is not None:
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    if not verbose:  # FFmpeg's own lines ("[mjpeg @ 0x...] overread 8") on a damaged video:
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # the survey says what failed
    return old


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, sort_keys=True, default=_json_default))


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _check_out_not_dir(path: Path) -> None:
    if path.is_dir():
        raise InputError(f"{path}: is a directory; give an output file name")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run())
