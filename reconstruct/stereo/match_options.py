"""Options of the stereo matcher, importable without numba (the pipeline's options hold
them; :mod:`prism3d.config` reads them from YAML)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from prism3d.checks import check_choice, check_int
from prism3d.errors import InputError

__all__ = ["MatchOptions"]

#: 3 channels x 8 paths x p2 must stay within the uint16 path sums' headroom.
_P2_LIMIT = 40000


@dataclass(frozen=True)
class MatchOptions:
    """Options of :func:`match_stereo_full` (why these defaults: docs/matching.md)."""

    coarse_to_fine: bool | None = None
    """Force (True) or forbid (False) coarse-to-fine; None: above C2F_AUTO_CELLS cells."""
    census_window: tuple[int, int] = (5, 5)
    """Census window (rows, cols), odd sizes >= 3, at most 64 comparisons."""
    p1: int = 10
    """SGM penalty per colour channel for a 1-level disparity change."""
    p2: int = 120
    """SGM penalty per colour channel for larger changes (> p1, <= 1600)."""
    p2_gamma: float = 20.0
    """Intensity step (grey levels) at which the adaptive P2 is halved."""
    paths: int = 4
    """Aggregation paths, 4 or 8."""
    uniqueness: float = 5.0
    """Minimum margin (percent) between the best cost and the best outside +-1 level."""
    lr_max_diff: float = 1.0
    """Maximum left-right disagreement (px)."""
    speckle_size: int | None = None
    """Valid regions smaller than this (px) are dropped; None: 100 px at 450x375, scaled by area."""
    speckle_range: float = 2.0
    """Disparity step (px) that separates speckle regions."""
    subpixel: str = "lk"
    """Sub-pixel: "lk" (equiangular fit, then Lucas-Kanade) or "equiangular" (fit alone)."""
    lk_window: int = 5
    """Odd side (px) of the square Lucas-Kanade window."""
    lk_iters: int = 1
    """Maximum Gauss-Newton iterations (one suffices from the equiangular start)."""
    fine_window: int | None = None
    """Levels searched per pixel coarse-to-fine (>= 3); None: 2 * (scale + 4) + 1, or more."""
    ad_weight: float = 1.0
    """Weight (>= 0) of the colour-difference term added to the census cost; 0: census only."""
    ad_trunc: float = 15.0
    """Truncation (> 0, grey levels per channel) of the colour-difference term."""
    ad_mode: str = "intensity"
    """What the colour-difference term compares: "intensity" (after equalisation) or "gradient"."""
    equalize: bool = True
    """Bring the right view's exposure, colour balance and vignetting to the left's first."""

    def __post_init__(self) -> None:
        check_choice(self.paths, "paths", (4, 8))
        check_choice(self.subpixel, "subpixel", ("lk", "equiangular"))
        check_choice(self.ad_mode, "ad_mode", ("intensity", "gradient"))
        if not (np.isfinite(self.ad_weight) and self.ad_weight >= 0):
            raise InputError(f"ad_weight: expected a finite number >= 0, got {self.ad_weight!r}")
        if not (np.isfinite(self.ad_trunc) and self.ad_trunc > 0):
            raise InputError(f"ad_trunc: expected a finite number > 0, got {self.ad_trunc!r}")
        if self.fine_window is not None and check_int(self.fine_window, "fine_window") < 3:
            raise InputError(f"fine_window: expected an integer >= 3, got {self.fine_window}")
        _check_census_window(self.census_window)
        if check_int(self.lk_window, "lk_window") < 3 or self.lk_window % 2 == 0:
            raise InputError(f"lk_window: expected an odd integer >= 3, got {self.lk_window}")
        for nm, v in (("p1", self.p1), ("p2", self.p2)):
            if check_int(v, nm) <= 0:
                raise InputError(f"{nm}: expected an integer > 0, got {v}")
        if self.p2 <= self.p1:
            raise InputError(f"p2: expected p2 > p1, got p1={self.p1}, p2={self.p2}")
        if self.p2 * 3 * 8 > _P2_LIMIT:
            raise InputError(f"p2: expected at most 1600, got {self.p2}")


def _check_census_window(cw: Any) -> None:
    if (
        len(cw) != 2
        or any(check_int(c, "census_window") % 2 == 0 or c < 3 for c in cw)
        or cw[0] * cw[1] - 1 > 64
    ):
        raise InputError(
            f"census_window: expected two odd sizes >= 3 with rows*cols <= 65, got {cw!r}")
