"""Camera sources: folder (new complete file), OpenCV, virtual, and the spec factory."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from prism3d.capture.sources import (
    CameraSource,
    FolderSource,
    OpenCVSource,
    VirtualSource,
    open_source,
    synthetic_plate_render,
    to_rgb8,
)
from prism3d.errors import DeviceError, InputError


def _rgb(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _png_bytes(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", rgb[:, :, ::-1])
    assert ok
    return buf.tobytes()


def test_open_source_forms(tmp_path: Path) -> None:
    assert isinstance(open_source(f"folder:{tmp_path}"), FolderSource)
    src = open_source("opencv:0")
    assert isinstance(src, OpenCVSource) and src.target == 0
    assert open_source("opencv:rtsp://cam/stream").target == "rtsp://cam/stream"
    v = open_source("virtual")
    assert isinstance(v, VirtualSource) and v.spec == "virtual"
    assert open_source("virtual:tank").spec == "virtual:tank"
    for s in (FolderSource(tmp_path), OpenCVSource(0), VirtualSource()):
        assert isinstance(s, CameraSource)


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("webcam:0", r"unknown kind 'webcam'; valid forms: folder:PATH, opencv:INDEX_OR_URL, virtual\[:TARGET\]"),
        ("folder", "folder needs a path"),
        ("opencv:", "opencv needs an index or URL"),
    ],
)
def test_open_source_errors(spec: str, match: str) -> None:
    with pytest.raises(InputError, match=match):
        open_source(spec)


def test_to_rgb8_conversions() -> None:
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 0] = 10  # blue
    assert to_rgb8(bgr)[0, 0].tolist() == [0, 0, 10]
    assert to_rgb8(np.full((2, 2), 7, np.uint8)).shape == (2, 2, 3)
    assert to_rgb8(np.full((2, 2, 4), 300 * 256 // 300, np.uint16)).dtype == np.uint8
    with pytest.raises(DeviceError, match="expected 8- or 16-bit"):
        to_rgb8(np.zeros((2, 2), np.float32))
    with pytest.raises(DeviceError, match="grey or colour"):
        to_rgb8(np.zeros((2, 2, 2), np.uint8))


def test_folder_waits_for_new_complete_file(tmp_path: Path) -> None:
    old = _rgb(seed=1)
    (tmp_path / "old.png").write_bytes(_png_bytes(old))
    (tmp_path / "notes.txt").write_text("ignored")
    new = _rgb(seed=2)
    data = _png_bytes(new)
    src = FolderSource(tmp_path, poll_s=0.02)
    src.open()
    src.prepare(1)

    def camera() -> None:  # a tethered camera writing the file in two parts
        time.sleep(0.1)
        with open(tmp_path / "IMG_0001.png", "wb") as fh:
            fh.write(data[: len(data) // 2])
            fh.flush()
            time.sleep(0.15)
            fh.write(data[len(data) // 2 :])

    th = threading.Thread(target=camera, daemon=True)
    th.start()
    got = src.grab(3.0)
    th.join(2)
    np.testing.assert_array_equal(got, new)
    assert src.info()["file"].endswith("IMG_0001.png")
    # The same file is not delivered twice.
    with pytest.raises(DeviceError, match=r"no new complete image within 0.1 s"):
        src.grab(0.1)


def test_folder_refuses_a_truncated_jpeg_until_it_is_complete(tmp_path: Path) -> None:
    """libjpeg decodes a truncated JPEG (the missing rows grey), so a file caught
    mid-write must wait for its end marker, and then be delivered whole."""
    rgb = _rgb(h=96, w=128, seed=3)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    data = buf.tobytes()
    src = FolderSource(tmp_path, poll_s=0.02)
    src.prepare(0)
    (tmp_path / "IMG_0002.jpg").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(DeviceError, match=r"never decoded: \['IMG_0002.jpg'\]"):
        src.grab(0.2)
    with open(tmp_path / "IMG_0002.jpg", "ab") as fh:
        fh.write(data[len(data) * 2 // 3 :])
    got = src.grab(2.0)
    want = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(got, want)


def test_folder_does_not_deliver_a_touched_file_again(tmp_path: Path) -> None:
    """A delivered file whose time stamp changes but whose bytes do not is the same
    frame; rewritten with new bytes, it is a new one."""
    src = FolderSource(tmp_path, poll_s=0.02)
    src.prepare(0)
    first, second = _rgb(seed=4), _rgb(seed=5)
    (tmp_path / "IMG_0003.png").write_bytes(_png_bytes(first))
    np.testing.assert_array_equal(src.grab(2.0), first)
    st = (tmp_path / "IMG_0003.png").stat()
    os.utime(tmp_path / "IMG_0003.png", ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))
    with pytest.raises(DeviceError, match=r"no new complete image within 0.2 s"):
        src.grab(0.2)
    (tmp_path / "IMG_0003.png").write_bytes(_png_bytes(second))
    np.testing.assert_array_equal(src.grab(2.0), second)


def test_folder_timeout_and_undecodable(tmp_path: Path) -> None:
    src = FolderSource(tmp_path, poll_s=0.02)
    src.prepare(0)
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg at all")
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match=r"within 0.2 s \(1 file\(s\) never decoded: \['broken.jpg'\]\)"):
        src.grab(0.2)
    assert time.monotonic() - t0 < 1.0


def test_folder_missing(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match="folder not found"):
        FolderSource(tmp_path / "nope").open()


def test_opencv_cannot_open(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match=r"opencv:.*cannot open the camera"):
        OpenCVSource(str(tmp_path / "missing.avi")).open()


def test_opencv_reads_image_sequence(tmp_path: Path) -> None:
    frames = [_rgb(seed=s) for s in range(3)]
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"f_{i:03d}.png"), f[:, :, ::-1])
    src = open_source(f"opencv:{tmp_path / 'f_%03d.png'}")
    src.open()
    try:
        src.prepare(1)
        np.testing.assert_array_equal(src.grab(2.0), frames[0])
        np.testing.assert_array_equal(src.grab(2.0), frames[1])
        assert src.info()["kind"] == "opencv"
        src.grab(2.0)
        with pytest.raises(DeviceError, match="returned no frame"):
            src.grab(2.0)
    finally:
        src.close()
    with pytest.raises(DeviceError, match="not open"):
        src._read(0.1)


def test_virtual_grating_only_with_flash() -> None:
    src = VirtualSource(sensor_size=(128, 64))
    src.prepare(2)
    dark = src.grab(1.0, flash_fired=False)
    lit = src.grab(1.0, flash_fired=True)
    assert dark.shape == lit.shape == (64, 128, 3) and lit.dtype == np.uint8
    chroma = lambda im: (im.max(2).astype(int) - im.min(2)).mean()  # noqa: E731
    assert chroma(dark) < 5 < 40 < chroma(lit)
    assert lit.mean() > 2 * dark.mean()
    src.prepare(0)  # plain white flash: bright, colourless
    white = src.grab(1.0, flash_fired=True)
    assert chroma(white) < 5 and white.mean() > 2 * dark.mean()
    assert src.info() == {"spec": "virtual", "kind": "virtual", "target": "plate"}


def test_virtual_views_are_shifted_by_disparity() -> None:
    render = synthetic_plate_render((256, 64), disparity_px=12, seed=3)
    img = render(True, 1, 0).astype(float)
    left, right = img[:, :128], img[:, 128:]
    errs = [np.abs(left[:, d:] - right[:, : 128 - d]).mean() for d in range(0, 20)]
    assert int(np.argmin(errs)) == 12


def test_virtual_resolver_and_errors() -> None:
    calls: list[str] = []

    def resolver(name: str):
        calls.append(name)
        return lambda flash, pattern, i: np.full((8, 8, 3), 100 if flash else 10, np.uint8)

    src = open_source("virtual:tank", resolver=resolver)
    src.prepare(1)
    assert src.grab(1.0, flash_fired=True)[0, 0, 0] == 100 and calls == ["tank"]
    with pytest.raises(InputError, match="no target resolver available"):
        VirtualSource("tank").open()
    bad = VirtualSource(render=lambda f, p, i: np.zeros((4, 4), np.float32))
    with pytest.raises(DeviceError, match=r"renderer returned float32 \(4, 4\)"):
        bad.grab(1.0)
    with pytest.raises(InputError, match="sensor_size"):
        synthetic_plate_render((15, 64))
