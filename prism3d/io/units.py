"""Units and up axis that a mesh or cloud file declares in its PLY header comments."""

from __future__ import annotations

import math
import re
from collections.abc import Iterable

__all__ = ["FORWARD_AXES", "declared_forward", "declared_units", "forward_yaw_deg"]

# "units mm" (prism3d's scans and DB models) or "units mm; frame ..." (built-in exports).
_UNITS = re.compile(r"\s*units\s+(\w+)\s*;?.*")
# "up z" as prism3d writes it; a ";"-separated tail is allowed as for units.
_UP = re.compile(r"\s*up\s+(-?[xyz])\s*(?:;.*)?")
# "forward x" on its own, or "frame x forward, ..." as prism3d's exports and DB models write it
_FORWARD = re.compile(r"\s*forward\s+(-?[xyz])\s*(?:;.*)?")
_FRAME_FORWARD = re.compile(r".*\bframe\s+(-?[xyz])\s+forward\b.*")
#: Axes a file's forward (the vehicle's nose) may lie along.
FORWARD_AXES = ("x", "-x", "y", "-y", "z", "-z")


def declared_units(comments: Iterable[str]) -> tuple[str | None, str | None]:
    """``(units, up)`` from PLY comments (``PlyData.comments``); None where not declared.

    The first ``units WORD`` and ``up AXIS`` comments win; values are not validated.
    """
    units = up = None
    for c in comments:
        if units is None and (m := _UNITS.fullmatch(c)):
            units = m.group(1)
        elif up is None and (m := _UP.fullmatch(c)):
            up = m.group(1)
    return units, up


def declared_forward(comments: Iterable[str]) -> str | None:
    """The forward axis PLY comments declare (``forward x`` or ``frame x forward``), or None."""
    for c in comments:
        if (m := _FORWARD.fullmatch(c)) or (m := _FRAME_FORWARD.fullmatch(c)):
            return m.group(1)
    return None


def forward_yaw_deg(forward: str, up: str) -> float:
    """The turn about up (deg, counter-clockwise seen from above) that puts a file's
    ``forward`` axis on +x once its ``up`` axis is turned to z (y-up files: (x, y, z) ->
    (x, -z, y)). Raises ValueError when forward is not horizontal (along up)."""
    if forward not in FORWARD_AXES:
        raise ValueError(f"forward: expected one of {', '.join(FORWARD_AXES)}, got {forward!r}")
    sign = -1.0 if forward.startswith("-") else 1.0
    axis = forward[-1]
    v = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}[axis]
    v = tuple(sign * c for c in v)
    if up == "y":
        v = (v[0], -v[2], v[1])
    if abs(v[2]) > 0.5:
        raise ValueError(f"forward {forward} lies along the up axis ({up}); give a horizontal axis")
    return -math.degrees(math.atan2(v[1], v[0]))
