"""Process environment for the heavy libraries, set in one place.

Imported by ``prism3d/__init__.py`` so it runs before any subpackage can import
OpenGL, pyrender, numba or a process pool. Values the user already set win.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import multiprocessing.context

#: OpenGL platform for headless pyrender: ``osmesa`` (default, software) or ``egl``.
OPENGL_PLATFORMS = ("osmesa", "egl")


def configured_threads() -> int:
    """Threads a parallel stage may use: ``PRISM3D_NUM_THREADS`` (0 or unset = the stage
    decides: all cores for Open3D's ray casting and COLMAP; job runners set 1 per worker)."""
    try:
        return max(0, int(os.environ.get("PRISM3D_NUM_THREADS", "0")))
    except ValueError:
        return 0


def configure_environment() -> None:
    """Set ``PYOPENGL_PLATFORM``, ``NUMBA_THREADING_LAYER`` and the thread pools' idle
    policy (OpenMP, OpenBLAS) unless already set."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
    # OpenMP threads sleep between parallel regions instead of spinning: with many
    # short numba kernels on a shared 2-core machine, spinning made each launch cost
    # 5-10 ms (measured); sleeping costs microseconds.
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    # OpenBLAS's idle threads spin 2^n cycles (n = OPENBLAS_THREAD_TIMEOUT, 4..30, default
    # 28: about 0.1 s) after each call, taking the cores from the numba kernels that run
    # next: the matcher's small gain-fit products made its kernels up to 5x slower
    # (measured, docs/performance.md). 4 is the shortest spin; it must be set before
    # numpy loads OpenBLAS, which importing prism3d first does.
    os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")
    # numba reads the variable once, when it is first imported; if something (a test
    # runner, a notebook) imported it before us, set its config directly.
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.THREADING_LAYER = os.environ["NUMBA_THREADING_LAYER"]
    # numba's on-disk cache lives beside the package unless the user chose a place;
    # an installed (read-only) package falls back to numba's own user cache.


def spawn_context() -> multiprocessing.context.SpawnContext:
    """The multiprocessing context every process pool in prism3d uses.

    ``fork`` after an OpenMP (numba) or OpenGL call can hang the child, so pools
    always ``spawn``.
    """
    import multiprocessing  # not at module level: ~5-25 ms that most commands never need

    return multiprocessing.get_context("spawn")


# --- import hooks ----------------------------------------------------------------------------
class ImportHook:
    """A one-shot ``sys.meta_path`` entry that runs ``after(module)`` once the module
    ``name`` has been imported, whenever (and if ever) something imports it. Nothing is
    imported on its behalf. Use :func:`on_import`; :meth:`remove` takes the hook out if
    it has not fired.
    """

    def __init__(self, name: str, after: Callable[[Any], None]) -> None:
        self.name = name
        self.after = after

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> Any:
        if fullname != self.name:
            return None
        from importlib.machinery import SourceFileLoader, SourcelessFileLoader
        from importlib.util import find_spec

        self.remove()  # one shot; the other finders locate the real module
        spec = find_spec(fullname)
        loader = getattr(spec, "loader", None)
        # a per-spec loader object (source or byte-code file) only: never patch a shared one
        if not isinstance(loader, (SourceFileLoader, SourcelessFileLoader)):
            return spec
        exec_module, after = loader.exec_module, self.after

        def exec_then_after(module: Any) -> None:
            exec_module(module)
            after(module)

        loader.exec_module = exec_then_after
        return spec

    def remove(self) -> None:
        """Take the hook out of ``sys.meta_path`` (no-op once it has fired)."""
        if self in sys.meta_path:
            sys.meta_path.remove(self)


def on_import(name: str, *, after: Callable[[Any], None]) -> ImportHook:
    """Run ``after(module)`` once ``name`` is first imported (see :class:`ImportHook`);
    ``name`` must not be imported yet."""
    hook = ImportHook(name, after)
    sys.meta_path.insert(0, hook)
    return hook
