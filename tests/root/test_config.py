from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from prism3d.config import config_from_dict, load_config, save_config
from prism3d.errors import InputError


@dataclass(frozen=True)
class Inner:
    p1: float = 8.0
    """Small-change penalty."""


@dataclass(frozen=True)
class Opts:
    num_disp: int = 64
    """Disparity levels."""
    mode: Literal["fast", "full"] = "full"
    size: tuple[int, int] = (640, 480)
    inner: Inner = field(default_factory=Inner)
    name: str | None = None


def test_round_trip(tmp_path):
    o = Opts(num_disp=128, mode="fast", size=(10, 20), inner=Inner(4.0), name="x")
    save_config(tmp_path / "c.yaml", o)
    assert load_config(tmp_path / "c.yaml", Opts) == o


def test_defaults_and_int_to_float():
    o = config_from_dict(Opts, {"inner": {"p1": 3}})
    assert o.inner.p1 == 3.0 and isinstance(o.inner.p1, float) and o.num_disp == 64


@pytest.mark.parametrize(
    "data, match",
    [
        ({"num_dsp": 3}, r"unknown key\(s\) 'num_dsp'; valid keys: inner, mode, name, num_disp, size"),
        ({"inner": {"p2": 1}}, r"config.inner: unknown key\(s\) 'p2'"),
        ({"num_disp": "64"}, "config.num_disp: expected an integer"),
        ({"num_disp": True}, "expected an integer"),
        ({"mode": "slow"}, "expected one of 'fast', 'full'"),
        ({"size": [1, 2, 3]}, "expected 2 values"),
        ({"inner": 5}, "expected a mapping"),
        ({"name": 5}, "expected a string"),
    ],
)
def test_errors(data, match):
    with pytest.raises(InputError, match=match):
        config_from_dict(Opts, data)


def test_bad_yaml(tmp_path):
    (tmp_path / "c.yaml").write_text("num_disp: [1,\n")
    with pytest.raises(InputError, match="not valid YAML"):
        load_config(tmp_path / "c.yaml", Opts)
    (tmp_path / "d.yaml").write_text("!!python/object:os.system {}\n")
    with pytest.raises(InputError, match="not valid YAML"):
        load_config(tmp_path / "d.yaml", Opts)


def _options_classes():
    from prism3d.atr.chips import ChipSpec
    from prism3d.capture.acquire import CaptureOptions
    from prism3d.capture.scenes import BoardPoseOptions
    from prism3d.capture.simulate import ShotOptions, SimulateOptions
    from prism3d.datasets.jobs.database_jobs import RunOptions
    from prism3d.reconstruct.stereo.calibrate import CalibrationOptions
    from prism3d.reconstruct.stereo.match_options import MatchOptions
    from prism3d.reconstruct.stereo.pipeline import ReconstructOptions
    from prism3d.reconstruct.scan.stitch import StitchOptions

    return [ChipSpec, CaptureOptions, BoardPoseOptions, ShotOptions, SimulateOptions, CalibrationOptions,
            MatchOptions, ReconstructOptions, StitchOptions, RunOptions]


@pytest.mark.parametrize("cls", _options_classes(), ids=lambda c: c.__name__)
def test_every_options_object_round_trips_through_yaml(tmp_path, cls):
    """The stage options can live in a YAML file (defaults written, read back equal);
    a typo in a key is an error naming it."""
    import dataclasses

    opts = cls()
    save_config(tmp_path / "o.yaml", opts)
    assert load_config(tmp_path / "o.yaml", cls) == opts
    first = dataclasses.fields(cls)[0].name
    with pytest.raises(InputError, match=f"{first}x"):
        config_from_dict(cls, {f"{first}x": 1})
