"""prism3d.datasets: built-in targets, the target database and its jobs."""

from prism3d.capture.camouflage import CamouflageField, camouflage_field, plain_paint
from prism3d.datasets.models.targets import (
    builtin_classes,
    builtin_target,
    export_builtin_target,
    list_builtin_targets,
)

__all__ = [
    "CamouflageField",
    "camouflage_field",
    "plain_paint",
    "builtin_classes",
    "builtin_target",
    "export_builtin_target",
    "list_builtin_targets",
]
