"""Process environment for the heavy libraries, set in one place.

Imported by ``prism3d/__init__.py`` so it runs before any subpackage can import
OpenGL, pyrender, numba or a process pool. Values the user already set win.
"""

from __future__ import annotations

import multiprocessing
import os
import sys

#: OpenGL platform for headless pyrender: ``osmesa`` (default, software) or ``egl``.
OPENGL_PLATFORMS = ("osmesa", "egl")


def configure_environment() -> None:
    """Set ``PYOPENGL_PLATFORM`` and ``NUMBA_THREADING_LAYER`` unless already set."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
    # OpenMP threads sleep between parallel regions instead of spinning: with many
    # short numba kernels on a shared 2-core machine, spinning made each launch cost
    # 5-10 ms (measured); sleeping costs microseconds.
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
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
    return multiprocessing.get_context("spawn")
