"""Progress display for long work: a tqdm bar on a terminal, silent otherwise.

Library functions take an optional ``progress`` callable ``(done, total, label)``;
the CLI passes one made here. Nothing is shown when stderr is not a TTY or when
``--quiet`` was given.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

__all__ = ["ProgressFn", "make_progress", "null_progress"]

ProgressFn = Callable[[int, int, str], None]


def null_progress(done: int, total: int, label: str = "") -> None:
    """A progress callback that shows nothing."""


class _Bar:
    def __init__(self, desc: str) -> None:
        self.desc = desc
        self.bar: Any = None

    def __call__(self, done: int, total: int, label: str = "") -> None:
        from tqdm import tqdm

        if self.bar is None or self.bar.total != total:
            if self.bar is not None:
                self.bar.close()
            self.bar = tqdm(total=total, desc=self.desc, unit="step", leave=False, file=sys.stderr,
                            dynamic_ncols=True)
        self.bar.n = done
        if label:
            self.bar.set_postfix_str(label, refresh=False)
        self.bar.refresh()
        if done >= total:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def make_progress(desc: str, *, quiet: bool = False) -> ProgressFn:
    """A progress callback for the CLI: a bar on a TTY, else silent."""
    if quiet or not sys.stderr.isatty():
        return null_progress
    return _Bar(desc)
