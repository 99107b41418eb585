"""Vehicle body paints as they occur in car parks: the colours (linear albedo) and their
shares, white, black and silver first (survey reports of new-car colours put these three at
about two thirds). Shared by the civilian built-in vehicles and the aerial training scenes.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BODY_PAINTS", "draw_body_paint"]

BODY_PAINTS: dict[str, tuple[tuple[float, float, float], float]] = {
    "white": ((0.80, 0.80, 0.78), 0.28),
    "black": ((0.035, 0.035, 0.04), 0.18),
    "silver": ((0.55, 0.56, 0.57), 0.15),
    "grey": ((0.28, 0.29, 0.30), 0.08),
    "pearl": ((0.74, 0.72, 0.67), 0.06),
    "red": ((0.50, 0.06, 0.05), 0.05),
    "blue": ((0.10, 0.20, 0.50), 0.05),
    "navy": ((0.05, 0.07, 0.18), 0.04),
    "beige": ((0.45, 0.37, 0.26), 0.04),
    "green": ((0.08, 0.20, 0.10), 0.02),
    "yellow": ((0.75, 0.60, 0.10), 0.02),
    "sky": ((0.40, 0.55, 0.70), 0.03),
}


def draw_body_paint(rng: np.random.Generator) -> tuple[str, tuple[float, float, float]]:
    """One body paint drawn with the shares of :data:`BODY_PAINTS`."""
    names = list(BODY_PAINTS)
    p = np.array([BODY_PAINTS[n][1] for n in names])
    k = int(rng.choice(len(names), p=p / p.sum()))
    return names[k], BODY_PAINTS[names[k]][0]
