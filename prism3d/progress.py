"""Progress display for long work: a tqdm bar on a terminal, silent otherwise.

Library functions take an optional ``progress`` callable ``(done, total, label)``;
the CLI passes one made here; labels ``"stage: detail"`` name the stage of a long
command (a bar per stage). Nothing is shown with ``--quiet``, nor when stderr is not a
TTY, except, for commands of stages, one line as each stage starts. :func:`compile_notice` tells the user when numba kernels
have to be compiled (a cold cache) instead of leaving a silent wait.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from prism3d._env import on_import

__all__ = ["COMPILE_NOTICE", "ProgressFn", "compile_notice", "make_progress", "null_progress"]

ProgressFn = Callable[[int, int, str], None]


def null_progress(done: int, total: int, label: str = "") -> None:
    """A progress callback that shows nothing."""


def _stage(label: str) -> str:
    """The stage of a ``"stage: detail"`` label ("" for a label without one)."""
    return label.split(":", 1)[0].strip() if ":" in label else ""


class _Bar:
    """A tqdm bar, a new one (named after it) for each stage of ``"stage: detail"`` labels."""

    def __init__(self, desc: str) -> None:
        self.desc = desc
        self.bar: Any = None
        self.stage = ""

    def __call__(self, done: int, total: int, label: str = "") -> None:
        from tqdm import tqdm

        stage = _stage(label)
        if self.bar is None or self.bar.total != total or stage != self.stage:
            if self.bar is not None:
                self.bar.close()
            self.stage = stage
            self.bar = tqdm(total=total, desc=f"{self.desc} {stage}".strip(), unit="step", leave=False,
                            file=sys.stderr, dynamic_ncols=True)
        if stage:
            label = label.split(":", 1)[1].strip()
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


class _StageLines:
    """One line on stderr as each stage of ``"stage: detail"`` labels starts (a log, a batch
    job: where a long run is, without a bar's control characters)."""

    def __init__(self, desc: str) -> None:
        self.desc = desc
        self.stage = ""

    def __call__(self, done: int, total: int, label: str = "") -> None:
        stage = _stage(label)
        if stage and stage != self.stage:
            self.stage = stage
            try:
                print(f"{self.desc}: {stage} ({total} step{'s' if total != 1 else ''})...", file=sys.stderr,
                      flush=True)
            except (OSError, ValueError):  # a closed or broken stderr must not break the command
                pass


def make_progress(desc: str, *, quiet: bool = False, stage_lines: bool = False) -> ProgressFn:
    """A progress callback for the CLI: a bar on a TTY (one per stage); elsewhere silent,
    or with ``stage_lines`` one line as each stage starts."""
    if quiet:
        return null_progress
    if not sys.stderr.isatty():
        return _StageLines(desc) if stage_lines else null_progress
    return _Bar(desc)


#: The one line shown when a kernel has to be compiled at run time.
COMPILE_NOTICE = (
    "prism3d: compiling numeric kernels for first use (about 1-2 minutes, once; "
    "'python -m prism3d._precompile' does it ahead)..."
)
_noticed = False


def _notice_once(stream: Any) -> None:
    global _noticed
    if _noticed:
        return
    _noticed = True
    try:
        print(COMPILE_NOTICE, file=stream, flush=True)
    except (OSError, ValueError):  # a closed or broken stderr must not break the command
        pass


def _compile_listener(stream: Any) -> Any:
    """A numba event listener that prints :data:`COMPILE_NOTICE` once when a prism3d
    kernel starts compiling (not when it loads from numba's on-disk cache)."""
    from numba.core import event

    class _Listener(event.Listener):
        def on_start(self, ev: Any) -> None:
            fn = getattr(ev.data.get("dispatcher"), "py_func", None)
            if getattr(fn, "__module__", "").startswith("prism3d."):
                _notice_once(stream)

        def on_end(self, ev: Any) -> None:
            pass

    return _Listener()


@contextmanager
def compile_notice(*, quiet: bool = False, stream: Any = None) -> Iterator[None]:
    """Inside the block, print :data:`COMPILE_NOTICE` on stderr (once per process) when
    a numba kernel has to be compiled, so a cold cache is not a silent minute-long
    wait.

    For the CLI only (library code never prints). Costs nothing when the kernels load
    from the cache, and does not import numba: when numba is not imported yet, the
    listener is registered right after its import, if the command imports it at all.
    The line goes to stderr whether or not it is a terminal (a notebook's ``!prism3d``
    or a CI log stalls just the same; stdout stays clean for parsers); ``quiet``
    silences it.
    """
    if quiet:
        yield
        return
    out = sys.stderr if stream is None else stream
    state: dict[str, Any] = {}

    def register() -> None:
        from numba.core import event

        state["listener"] = _compile_listener(out)
        event.register("numba:compile", state["listener"])

    hook = None
    if "numba" in sys.modules:
        register()
    else:
        hook = on_import("numba", after=lambda module: register())
    try:
        yield
    finally:
        if hook is not None:
            hook.remove()
        if "listener" in state:
            from numba.core import event

            event.unregister("numba:compile", state["listener"])
