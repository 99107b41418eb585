"""prism3d: one flash photograph through a prism stereo adapter -> a metric 3D model,
and an ATR dataset and feature toolkit built on that 3D core.

Layers (imports go left to right only)::

    prism3d.capture <- prism3d.reconstruct <- prism3d.atr <- prism3d.datasets

Importing ``prism3d`` is cheap: it only sets the process environment
(see :mod:`prism3d._env`) and exposes the version and the error family.
"""

from __future__ import annotations

from prism3d._env import configure_environment as _configure_environment

_configure_environment()

from prism3d import errors  # noqa: E402
from prism3d.errors import (  # noqa: E402
    CalibrationError,
    DatasetError,
    DeviceError,
    InputError,
    Prism3dError,
    ReconstructionError,
)

__version__ = "0.1.0"

__all__ = ["__version__"]
__all__ += errors.__all__
