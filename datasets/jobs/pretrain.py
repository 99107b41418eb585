"""``python -m prism3d.datasets.jobs.pretrain``: train the default aerial recogniser (``survey-detect``'s
car, van, truck and bus) into the recogniser cache once per install, so that the first
``survey-detect`` does not wait for it (``make setup`` runs this; a few minutes on 2 cores).
A model already cached is kept."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from prism3d.atr.survey_detect import DEFAULT_CLASSES
from prism3d.datasets.jobs.recognisers import aerial_recogniser, cache_dir
from prism3d.datasets.database.resolve import resolve_targets

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Train (or find) the default aerial recogniser; prints one line."""
    p = argparse.ArgumentParser(prog="python -m prism3d.datasets.jobs.pretrain", description=__doc__)
    p.add_argument("-q", "--quiet", action="store_true")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    model, info = aerial_recogniser(resolve_targets(list(DEFAULT_CLASSES), scale="full"))
    if not a.quiet:
        how = "already cached" if info["cached"] else f"trained in {time.perf_counter() - t0:.0f} s"
        print(f"prism3d pretrain: aerial recogniser of {', '.join(model.classes)} {how} ({info['path'] or cache_dir()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
