"""prism3d.capture: the rig (prism split, virtual cameras), the grating pattern, the
flash/shutter trigger, camera sources, and the virtual rig (renderer + scene
simulator with exact ground truth)."""

from prism3d.capture.rig import (
    CameraModel,
    PrismSplit,
    Rectification,
    StereoRig,
    compute_rectification,
    look_at,
    paper_rig,
    scaled_rig,
)

__all__ = [
    "CameraModel",
    "PrismSplit",
    "StereoRig",
    "Rectification",
    "compute_rectification",
    "look_at",
    "paper_rig",
    "scaled_rig",
]
