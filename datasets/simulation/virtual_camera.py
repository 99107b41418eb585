"""Targets for the ``virtual[:TARGET]`` camera source of ``prism3d capture``: the CLI
hands :func:`resolve_virtual_target` to the source, as capture cannot import this layer."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from prism3d.capture.rig import StereoRig, paper_rig
from prism3d.capture.scenes import flat_plate, translation, turntable_poses
from prism3d.capture.simulate import Projector, ShotOptions, simulate_shot, working_distance_mm
from prism3d.capture.sources import RenderFn
from prism3d.datasets.models.targets import builtin_target, list_builtin_targets
from prism3d.errors import InputError

__all__ = ["resolve_virtual_target", "VIRTUAL_TARGETS"]

#: Names accepted after ``virtual:`` besides the built-in targets.
VIRTUAL_TARGETS = ("plate",)


def resolve_virtual_target(
    name: str, *, rig: StereoRig | None = None, supersample: int = 1
) -> RenderFn:
    """A render function ``(flash_fired, pattern_id, shot_index) -> (H, W, 3) uint8``: one
    flash photograph through ``rig`` (default the paper's), the grating only when the
    flash fired. ``name``: ``plate`` (30 x 30 cm at the working distance) or a built-in
    target on the turntable (shot ``k`` turned by 45 k deg); ``supersample``: anti-aliasing.
    """
    rig = rig or paper_rig()
    wd = working_distance_mm(rig)
    if name == "plate":
        objects_for = lambda k: [(flat_plate(300.0, 300.0), translation(0.0, 0.0, wd))]  # noqa: E731
    elif name in list_builtin_targets():
        mesh = builtin_target(name)
        centre = (0.0, 0.0, float(mesh.extent_mm[2]) / 2.0)

        def objects_for(k: int) -> list:
            T_world_rig = turntable_poses(1, 45.0, distance_mm=wd, start_deg=45.0 * k, target=centre)[0]
            return [(mesh, np.linalg.inv(T_world_rig))]
    else:
        valid = ", ".join(VIRTUAL_TARGETS + tuple(list_builtin_targets()))
        raise InputError(f"virtual:{name}: unknown target; valid targets: {valid}")

    projectors: dict[int, Projector] = {}

    def render(flash_fired: bool, pattern_id: int, shot_index: int) -> NDArray[np.uint8]:
        if flash_fired:
            if pattern_id not in projectors:
                projectors[pattern_id] = Projector.for_rig(rig, pattern=pattern_id != 0, seed=pattern_id or None)
            shot = simulate_shot(rig, objects_for(shot_index), ShotOptions(supersample=supersample, seed=shot_index),
                                 projector=projectors[pattern_id])
        else:  # ambient light only
            shot = simulate_shot(rig, objects_for(shot_index), ShotOptions(flash=0.0, supersample=supersample, seed=shot_index),
                                 projector=None)
        return shot.sensor_image

    return render
