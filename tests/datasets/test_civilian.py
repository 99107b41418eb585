"""Civilian built-in vehicles, the one target list (classes, forward axes, databases) and the
simulated car park: known sizes, paints and layouts."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from prism3d.datasets.models.targets import builtin_classes, builtin_target, builtin_targets_of_class, list_builtin_targets
from prism3d.datasets.database.resolve import resolve_targets
from prism3d.errors import InputError, Prism3dError

#: Catalogue sizes (length, width, height m) the civilian built-ins are built to.
SIZES = {"car_sedan": (4.70, 1.80, 1.45), "car_hatchback": (4.05, 1.75, 1.48), "car_suv": (4.65, 1.86, 1.72),
         "car_kei": (3.39, 1.47, 1.75), "van_panel": (4.90, 1.70, 1.98), "bus_city": (10.5, 2.49, 3.2),
         "truck_box": (7.6, 2.3, 3.3), "truck_pickup": (5.3, 1.84, 1.8), "truck_kei": (3.39, 1.47, 1.8)}


def test_groups_and_classes() -> None:
    mil, civ = list_builtin_targets("military"), list_builtin_targets("civilian")
    assert len(mil) == 12 and set(civ) == set(SIZES)
    assert list_builtin_targets() == mil + civ
    assert builtin_classes("civilian") == ["truck", "car", "van", "bus"]
    assert set(builtin_targets_of_class("truck")) == {"truck_k1", "truck_k2", "truck_k3", "truck_box", "truck_pickup",
                                                        "truck_kei"}
    with pytest.raises(InputError, match="group"):
        list_builtin_targets("boats")


@pytest.mark.parametrize("name", sorted(SIZES))
def test_true_size_frame_and_kit_scale(name: str) -> None:
    m = builtin_target(name, scale="full")
    L, W, H = SIZES[name]
    assert m.extent_mm / 1000.0 == pytest.approx([L, W, H], abs=0.06)
    lo, hi = m.bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-6)  # on the ground
    assert (lo[0] + hi[0]) / 2 == pytest.approx(0.0, abs=1e-6) and (lo[1] + hi[1]) / 2 == pytest.approx(0.0, abs=1e-6)
    kit = builtin_target(name)
    assert 120.0 <= kit.extent_mm[0] <= 300.0  # a kit fits the rig's field
    assert m.metadata["group"] == "civilian" and m.metadata["camouflage"] == "none"


def test_paint_body_glass_and_tyres() -> None:
    m = builtin_target("car_sedan", scale="full", seed=0)
    paint = m.albedo_field
    body = paint(np.array([[0.0, 0.0, 1450.0]]))[0]  # the roof's middle
    glass = paint(np.array([[1100.0, 0.0, 1150.0]]))[0]  # the windscreen
    tyre = paint(np.array([[1400.0, 880.0, 200.0]]))[0]  # the front wheel's side
    assert np.allclose(glass, (0.05, 0.06, 0.07)) and np.allclose(tyre, (0.03, 0.03, 0.03))
    assert not np.allclose(body, glass)
    colours = collections.Counter(builtin_target("car_sedan", scale="full", seed=s).metadata["paint"]
                                  for s in range(60))
    assert colours["white"] > colours["red"] and colours["black"] >= 3 and len(colours) >= 6


def test_class_names_expand_to_their_built_ins() -> None:
    got = resolve_targets(["car", "bus", "tank_t1"])
    assert [c for c, _ in got] == ["car"] * 4 + ["bus", "tank"]
    assert [m.name for c, m in got if c == "car"] == builtin_targets_of_class("car")
    assert len(resolve_targets(["civilian"])) == 9 and len(resolve_targets(["builtin"])) == 12


def test_forward_axis_turns_the_nose_onto_x(tmp_path) -> None:
    import trimesh

    box = trimesh.creation.box(extents=(1.0, 4.0, 1.5))  # long along y: its nose is +y
    box.apply_translation((0, 0.5, 0.75))
    f = tmp_path / "long_y.ply"
    box.export(f)
    (cls, m), = resolve_targets([f"{f}=car:m:z:y"])
    assert cls == "car" and m.extent_mm[:2] == pytest.approx([4000.0, 1000.0], abs=1e-6)
    (_, m2), = resolve_targets([f"{f}=car:m:z:-y"])
    assert m2.extent_mm[:2] == pytest.approx([4000.0, 1000.0], abs=1e-6)
    # +y onto +x is a quarter turn clockwise seen from above; -y the other way
    assert m.metadata["yaw_deg"] == pytest.approx(-90.0) and m2.metadata["yaw_deg"] == pytest.approx(90.0)
    with pytest.raises(Prism3dError, match="forward axis unknown"):
        resolve_targets([f"{f}=car:m:z"])
    with pytest.raises(Prism3dError, match="along the up axis"):
        resolve_targets([f"{f}=car:m:z:z"])
    with pytest.raises(InputError, match="expected FILE"):
        resolve_targets([f"{f}=car:m:z:y:extra"])


def test_unknown_class_or_name_is_refused() -> None:
    with pytest.raises(InputError, match="neither a mesh file, a built-in target nor a class"):
        resolve_targets(["tractor"])


def test_carpark_plan_rows_of_vehicles() -> None:
    from prism3d.datasets.simulation.flight import FlightOptions, plan_flight

    for seed in (0, 1):
        plan = plan_flight(FlightOptions(scene="carpark", frames=3, lines=1, altitude_m=60.0, size=(2304, 1728),
                                         seed=seed))
        recs = plan.records
        assert len(recs) >= 30
        classes = collections.Counter(r["class"] for r in recs)
        assert classes["car"] > sum(v for k, v in classes.items() if k != "car")
        assert {r["paint"] for r in recs} >= {"white", "black", "silver"}
        xy = np.array([T[:2, 3] / 1000.0 for _, T in plan.objects[1:len(recs) + 1]])
        d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) + np.eye(len(xy)) * 1e9
        assert 1.5 < d.min(axis=1).min() and np.median(d.min(axis=1)) < 3.0  # side by side in 2.5 m bays
        assert plan.meta["carpark"]["painted_lines"] > 20
    with pytest.raises(InputError, match="scene"):
        FlightOptions(scene="harbour")
