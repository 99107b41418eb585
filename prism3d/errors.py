"""The prism3d exception family.

Library code raises these and never prints or exits; the command line maps any
:class:`Prism3dError` to one line on stderr and exit code 2. Anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

__all__ = [
    "Prism3dError",
    "InputError",
    "CalibrationError",
    "ReconstructionError",
    "DeviceError",
    "DatasetError",
]


class Prism3dError(Exception):
    """Base class of every error prism3d raises on purpose (a user-facing problem)."""


class InputError(Prism3dError, ValueError):
    """A file, array or parameter given by the user is missing, malformed or out of range."""


class CalibrationError(Prism3dError):
    """Calibration could not be done or is unusable (no board found, too few views...)."""


class ReconstructionError(Prism3dError):
    """Matching, triangulation, stitching or meshing failed on otherwise valid input."""


class DeviceError(Prism3dError):
    """A device (trigger controller, camera) did not answer, answered wrongly, or vanished."""


class DatasetError(Prism3dError):
    """A target database is malformed, inconsistent, or a job on it failed."""
