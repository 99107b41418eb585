"""Reconstruction defaults the CLI help shows (no heavy imports: ``--help`` stays instant)."""

from __future__ import annotations

__all__ = ["DEFAULT_MIN_CONFIDENCE"]

#: Default of ``min_confidence``: drop a pixel only when its estimate has less than a
#: 5 % chance of being within 1 px of the truth (predicted std above ~16 px): the
#: surface is kept, and estimates its surroundings contradict are dropped. 0.5 keeps
#: the points more likely right than not (std <= 1.48 px); see docs/reconstruction.md.
DEFAULT_MIN_CONFIDENCE = 0.05
