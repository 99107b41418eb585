"""The ``prism3d`` command line.

Each command parses its arguments and calls one library function. Start-up is lazy:
heavy libraries are imported inside the handlers, so ``prism3d --help`` is instant.

Exit codes: 0 success; 2 a user mistake (a :class:`~prism3d.errors.Prism3dError`,
printed as one line on stderr, no partial output); 130 interrupted. Anything else is
a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from prism3d import __version__
from prism3d.errors import InputError, Prism3dError

Handler = Callable[[argparse.Namespace], int | None]


class _Parser(argparse.ArgumentParser):
    """argparse with our exit code 2 and one-line messages."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


def _progress(args: argparse.Namespace, desc: str) -> Any:
    from prism3d.progress import make_progress

    return make_progress(desc, quiet=getattr(args, "quiet", False))


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        print(text)


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
    p = sub.add_parser("demo", help="run the whole pipeline on built-in data and write report.html",
                       description="Run every stage of prism3d on built-in data (simulated shots, "
                       "calibration, reconstruction, ATR) and write OUT_DIR/report.html.")
    p.add_argument("out_dir", type=Path, metavar="OUT_DIR")
    p.add_argument("--seed", type=int, default=0, help="random seed for simulated data (default 0)")
    p.add_argument("--fast", action="store_true", help="smaller images and fewer views (for tests)")
    p.add_argument("--only", nargs="+", metavar="STAGE", help="run only these stages")
    p.set_defaults(func=_cmd_demo)


# --- registry ---------------------------------------------------------------------------
_COMMANDS: list[Callable[[Any], None]] = [
    _add_demo,
]


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="prism3d",
        description="One flash photograph through a prism stereo adapter -> a calibrated, "
        "metric 3D model; ATR datasets and features on that 3D core.",
        epilog="Run 'prism3d COMMAND --help' for a command's options. Lengths are millimetres, "
        "angles degrees. Docs: README.md.",
    )
    parser.add_argument("--version", action="version", version=f"prism3d {__version__}")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars or summaries")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``prism3d`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        rc = args.func(args)
    except Prism3dError as exc:
        msg = " ".join(str(exc).split())  # one line
        print(f"prism3d {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"prism3d {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


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
    sys.exit(main())
