"""Units and up axis that a mesh or cloud file declares in its PLY header comments."""

from __future__ import annotations

import re
from collections.abc import Iterable

__all__ = ["declared_units"]

# "units mm" (prism3d's scans and DB models) or "units mm; frame ..." (built-in exports).
_UNITS = re.compile(r"\s*units\s+(\w+)\s*;?.*")
# "up z" as prism3d writes it; a ";"-separated tail is allowed as for units.
_UP = re.compile(r"\s*up\s+(-?[xyz])\s*(?:;.*)?")


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
