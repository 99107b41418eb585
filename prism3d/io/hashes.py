"""File hashes that tie outputs to their inputs (scans to shots and calibrations, models
to the scans and poses they were stitched from)."""

from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["sha256_file", "sha256_files"]


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sha256_files(paths: list[str | Path]) -> str:
    """One hex SHA-256 of several files: of one file, its own hash; of more, the hash of
    their hashes joined by spaces (order matters: left before right)."""
    hs = [sha256_file(p) for p in paths]
    return hs[0] if len(hs) == 1 else hashlib.sha256(" ".join(hs).encode()).hexdigest()
