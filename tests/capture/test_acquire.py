"""capture_shots against the trigger simulator on a real pty, with virtual/folder sources."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from prism3d.capture.acquire import CaptureOptions, check_frame, capture_shots
from prism3d.capture.sources import VirtualSource
from prism3d.capture.trigger_sim import TriggerSimulator
from prism3d.errors import DeviceError, InputError

SIZE = (128, 64)


@pytest.fixture
def sim() -> Iterator[TriggerSimulator]:
    with TriggerSimulator() as s:
        yield s


def _files(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir()) if d.exists() else []


def test_round_trip_virtual(sim: TriggerSimulator, tmp_path: Path) -> None:
    out = tmp_path / "shots"
    done: list[tuple[int, int]] = []
    paths = capture_shots(
        sim.port, VirtualSource(sensor_size=SIZE), out,
        CaptureOptions(count=2, interval_s=0.05, pattern_id=2, expected_size=SIZE, trigger_timeout=0.3),
        progress=lambda k, n: done.append((k, n)),
    )
    assert [p.name for p in paths] == ["shot_000.png", "shot_001.png"]
    assert _files(out) == ["shot_000.json", "shot_000.png", "shot_001.json", "shot_001.png"]
    assert done == [(1, 2), (2, 2)]
    img = cv2.imread(str(paths[0]), cv2.IMREAD_COLOR)
    assert img.shape == (64, 128, 3)
    meta = json.loads(paths[1].with_suffix(".json").read_text())
    assert meta["schema_version"] == 1 and meta["index"] == 1 and meta["pattern_id"] == 2
    assert meta["flash"] is True and meta["trigger"]["shot"] == 2
    assert meta["trigger"]["device"]["model"] == "PRISM3D-TRIG"
    assert meta["trigger"]["t_flash_us"] - meta["trigger"]["t_shutter_us"] == meta["timing"]["flash_delay_us"]
    assert meta["source"]["kind"] == "virtual" and meta["image"]["width"] == 128
    assert meta["image"]["pattern_fraction"] > 0.5
    assert meta["time_utc"].endswith("Z")
    # Numbering continues; no flash = no grating check, ambient exposure.
    more = capture_shots(sim.port, VirtualSource(sensor_size=SIZE), out, CaptureOptions(flash=False, trigger_timeout=0.3))
    assert more[0].name == "shot_002.png"
    meta = json.loads(more[0].with_suffix(".json").read_text())
    assert meta["flash"] is False and meta["trigger"]["t_flash_us"] is None


def test_round_trip_folder_spec(sim: TriggerSimulator, tmp_path: Path) -> None:
    drop = tmp_path / "tether"
    drop.mkdir()
    frame = VirtualSource(sensor_size=SIZE)
    frame.prepare(1)
    rgb = frame.grab(1.0, flash_fired=True)

    def camera() -> None:
        time.sleep(0.3)
        cv2.imwrite(str(drop / "IMG_0001.png"), rgb[:, :, ::-1])

    th = threading.Thread(target=camera, daemon=True)
    th.start()
    paths = capture_shots(sim.port, f"folder:{drop}", tmp_path / "out", CaptureOptions(grab_timeout=3.0, trigger_timeout=0.3))
    th.join(2)
    saved = cv2.imread(str(paths[0]), cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(saved, rgb)
    meta = json.loads(paths[0].with_suffix(".json").read_text())
    assert meta["source"]["file"].endswith("IMG_0001.png")


def _render(value: int | None):
    def render(flash: bool, pattern: int, i: int) -> np.ndarray:
        if value is None:  # grey: lit but colourless, i.e. grating missing
            return np.full((64, 128, 3), 120, np.uint8)
        return np.full((64, 128, 3), value, np.uint8)
    return render


@pytest.mark.parametrize(
    ("value", "kwargs", "error", "match"),
    [
        (0, {}, DeviceError, r"frame is black \(mean level 0.0/255\)"),
        (255, {}, DeviceError, r"frame is saturated \(100% of pixels"),
        (None, {}, DeviceError, "the flash fired but no colour grating is visible"),
        (120, {"expected_size": (2592, 1944)}, InputError, "frame is 128x64 but the calibration expects a 2592x1944"),
    ],
)
def test_failed_checks_leave_no_files(
    sim: TriggerSimulator, tmp_path: Path, value: int | None, kwargs: dict, error: type, match: str
) -> None:
    out = tmp_path / "o"
    with pytest.raises(error, match=match):
        capture_shots(sim.port, VirtualSource(render=_render(value)), out, CaptureOptions(trigger_timeout=0.3, **kwargs))
    assert _files(out) == []


@pytest.mark.parametrize("fault", ["silence", "garbage", "slow", "disconnect"])
def test_trigger_faults_leave_no_files(tmp_path: Path, fault: str) -> None:
    out = tmp_path / "o"
    with TriggerSimulator(fault, slow_s=1.5) as s:
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match=r"no reply|no valid reply|port vanished"):
            capture_shots(s.port, VirtualSource(sensor_size=SIZE), out, CaptureOptions(trigger_timeout=0.2))
        assert time.monotonic() - t0 < 0.2 * 3 + 0.6
    assert _files(out) == []


def test_drop_fault_recovers(tmp_path: Path) -> None:
    with TriggerSimulator("drop") as s:
        paths = capture_shots(s.port, VirtualSource(sensor_size=SIZE), tmp_path, CaptureOptions(trigger_timeout=0.2))
    assert len(paths) == 1 and paths[0].with_suffix(".json").exists()


def test_camera_timeout_leaves_no_files(sim: TriggerSimulator, tmp_path: Path) -> None:
    drop = tmp_path / "tether"
    drop.mkdir()
    out = tmp_path / "o"
    with pytest.raises(DeviceError, match="no new complete image within 0.2 s"):
        capture_shots(sim.port, f"folder:{drop}", out, CaptureOptions(grab_timeout=0.2, trigger_timeout=0.3))
    assert _files(out) == []


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"count": 0}, "count"),
        ({"interval_s": -1}, "interval_s"),
        ({"pattern_id": 16}, "pattern_id"),
        ({"expected_size": (0, 5)}, "expected_size"),
        ({"grab_timeout": 0}, "grab_timeout"),
    ],
)
def test_argument_errors(tmp_path: Path, kwargs: dict, match: str) -> None:
    with pytest.raises(InputError, match=match):
        capture_shots("loop://", "virtual", tmp_path, CaptureOptions(**kwargs))


def test_out_dir_is_a_file(tmp_path: Path) -> None:
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        capture_shots("loop://", "virtual", f)
    with pytest.raises(InputError, match="options: expected a CaptureOptions"):
        capture_shots("loop://", "virtual", tmp_path, {"count": 2})  # type: ignore[arg-type]


def test_capture_options_timing_without_flash() -> None:
    assert CaptureOptions(flash=False).timing == {"shutter_us": CaptureOptions().shutter_us, "flash_us": 0,
                                                  "flash_delay_us": 0}


def test_check_frame_stats_and_shape() -> None:
    img = np.zeros((4, 4, 3), np.uint8)
    img[..., 0] = 200
    img[..., 1:] = 40
    st = check_frame(img, pattern_visible=True)
    assert st["pattern_fraction"] == 1.0 and st["width"] == 4
    with pytest.raises(DeviceError, match=r"expected an \(H, W, 3\) uint8 frame"):
        check_frame(np.zeros((4, 4), np.uint8))
