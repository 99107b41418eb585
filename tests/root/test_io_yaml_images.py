from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.io.images import read_depth, read_image, write_depth, write_image
from prism3d.io.opencv_yaml import read_filestorage, write_filestorage


def test_filestorage_round_trip_and_opencv_reads_it(tmp_path):
    import cv2

    K = np.array([[5107.0, 0.1, 647.5], [0, 5106.0, 971.5], [0, 0, 1]])
    vals = {"K1": K, "D1": np.array([-0.06, 0.12, 0, 0, 0]), "rms_px": 0.123,
            "n_views": 5, "board": "9x6", "image_size": np.array([1296, 1944])}
    write_filestorage(tmp_path / "c.yaml", vals)
    fs = cv2.FileStorage(str(tmp_path / "c.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("K1").mat(), K)
    assert fs.getNode("rms_px").real() == pytest.approx(0.123)
    fs.release()
    back = read_filestorage(tmp_path / "c.yaml")
    np.testing.assert_array_equal(back["K1"], K)
    np.testing.assert_array_equal(back["D1"].ravel(), vals["D1"])
    assert back["n_views"] == 5 and back["board"] == "9x6"
    np.testing.assert_array_equal(back["image_size"].ravel(), [1296, 1944])


@pytest.mark.parametrize(
    "content, match",
    [
        ("K1: [1, 2]\n", "not an OpenCV FileStorage"),
        ("%YAML:1.0\n---\nK1: !!opencv-matrix\n   rows: 3\n   cols: [\n", "malformed|could not open"),
    ],
)
def test_filestorage_malformed(tmp_path, content, match):
    p = tmp_path / "bad.yaml"
    p.write_text(content)
    with pytest.raises(InputError, match=match):
        read_filestorage(p)


@pytest.mark.parametrize("ext", ["yaml", "xml", "json"])
def test_filestorage_reads_what_opencv_reads(tmp_path, ext):
    """Our parser gives what cv2.FileStorage's nodes give, for each flavour OpenCV
    writes: numbers, strings, matrices (multi-channel, int), 1-D nd-matrices, NaN, inf."""
    import cv2

    vals = {"a": 1, "b": 2.5, "c": "hello world", "e": np.eye(3), "f": np.arange(6).reshape(2, 3),
            "h": -1e-30, "i": float("nan"), "l": float("inf"), "n": np.array([np.nan, -np.inf, 1.5])}
    write_filestorage(tmp_path / f"w.{ext}", vals)
    fs = cv2.FileStorage(str(tmp_path / "nd.yml"), cv2.FILE_STORAGE_WRITE)  # OpenCV's own 1-D and 3-channel
    fs.write("d", np.arange(5.0))
    fs.write("x", np.arange(24.0).reshape(2, 3, 4))
    fs.release()
    back = read_filestorage(tmp_path / f"w.{ext}")
    assert (back["a"], back["b"], back["c"], back["h"]) == (1, 2.5, "hello world", -1e-30)
    assert np.isnan(back["i"]) and back["l"] == np.inf
    np.testing.assert_array_equal(back["e"], np.eye(3))
    assert back["f"].dtype == np.int32 and back["f"].tolist() == [[0, 1, 2], [3, 4, 5]]
    np.testing.assert_array_equal(back["n"].ravel(), vals["n"])
    nd = read_filestorage(tmp_path / "nd.yml")
    assert nd["d"].shape == (5,) and nd["x"].shape == (2, 3, 4)
    np.testing.assert_array_equal(nd["x"], np.arange(24.0).reshape(2, 3, 4))


def test_filestorage_matrix_that_overflows_opencv(tmp_path):
    """A matrix whose rows x cols disagree with its data: OpenCV 5.0's reader overflows
    its heap on it (malloc aborts the process, found by fuzzing); ours says so."""
    write_filestorage(tmp_path / "c.yaml", {"T": np.array([1.0, 2.0, 3.0])})
    p = tmp_path / "c.yaml"
    p.write_text(p.read_text().replace("cols: 1", "dols: 1"))
    with pytest.raises(InputError, match="'cols' must be a whole number"):
        read_filestorage(p)
    p.write_text(p.read_text().replace("dols: 1", "cols: 2"))
    with pytest.raises(InputError, match="3 numbers for 3x2x1"):
        read_filestorage(p)


def test_filestorage_missing_key(tmp_path):
    write_filestorage(tmp_path / "c.yaml", {"a": 1})
    with pytest.raises(InputError, match="missing entry 'K1'"):
        read_filestorage(tmp_path / "c.yaml", keys=["K1"])


def test_filestorage_bad_suffix(tmp_path):
    with pytest.raises(InputError, match="must end in"):
        write_filestorage(tmp_path / "c.txt", {"a": 1})


def test_image_round_trip_rgb_order(tmp_path):
    import cv2

    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 200  # red
    write_image(tmp_path / "a.png", img)
    assert cv2.imread(str(tmp_path / "a.png"))[0, 0].tolist() == [0, 0, 200]  # BGR on disk
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), img)
    assert read_image(tmp_path / "a.png", grey=True).shape == (4, 5)


def test_image_errors(tmp_path):
    (tmp_path / "x.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="cannot decode"):
        read_image(tmp_path / "x.png")
    with pytest.raises(InputError, match="not found"):
        read_image(tmp_path / "missing.png")
    with pytest.raises(InputError, match="uint8"):
        write_image(tmp_path / "y.png", np.zeros((2, 2), np.float32))
    with pytest.raises(InputError, match="extension"):
        write_image(tmp_path / "y.xyz", np.zeros((2, 2), np.uint8))


@pytest.mark.parametrize("suffix", [".tiff", ".npy", ".npz"])
def test_depth_round_trip(tmp_path, suffix):
    d = np.random.default_rng(0).uniform(1000, 1500, (6, 7)).astype(np.float32)
    d[2, 3] = np.nan
    write_depth(tmp_path / f"d{suffix}", d)
    spec = tmp_path / f"d{suffix}"
    back = read_depth(f"{spec}:depth_mm" if suffix == ".npz" else spec)
    np.testing.assert_array_equal(back, d)


def test_depth_npz_keys(tmp_path):
    np.savez(tmp_path / "t.npz", depth_left_mm=np.ones((2, 2), np.float32), other=np.zeros(3))
    assert read_depth(f"{tmp_path / 't.npz'}:depth_left_mm").shape == (2, 2)
    with pytest.raises(InputError, match="holds 2 arrays"):
        read_depth(tmp_path / "t.npz")
    with pytest.raises(InputError, match="no array 'nope'"):
        read_depth(f"{tmp_path / 't.npz'}:nope")
    with pytest.raises(InputError, match="2-D numeric"):
        read_depth(f"{tmp_path / 't.npz'}:other")
    (tmp_path / "bad.npy").write_bytes(b"garbage")
    with pytest.raises(InputError, match="cannot read depth"):
        read_depth(tmp_path / "bad.npy")
    with pytest.raises(InputError, match="unsupported depth format"):
        read_depth(_touch(tmp_path / "d.jpg"))


def _touch(p):
    p.write_bytes(b"x")
    return p


def _png_header(w: int, h: int) -> bytes:
    """A PNG whose header declares w x h RGB pixels, with almost no data (a bomb's shape)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def test_image_claiming_60000_squared_is_refused_from_its_header(tmp_path, monkeypatch):
    import resource

    p = tmp_path / "bomb.png"
    p.write_bytes(_png_header(60000, 60000))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match=r"bomb.png: the image declares 3,600 MP, more than the 100 MP limit"):
        read_image(p)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000  # KB: nothing decoded
    monkeypatch.setenv("PRISM3D_MAX_PIXELS", "1000")
    small = tmp_path / "small.png"
    write_image(small, np.zeros((40, 40, 3), np.uint8))
    with pytest.raises(InputError, match=r"small.png: 40x40 is 1,600 pixels, more than the 1,000 pixels limit"):
        read_image(small)
    monkeypatch.setenv("PRISM3D_MAX_PIXELS", "2000")
    assert read_image(small).shape == (40, 40, 3)


def test_depth_npz_declaring_gigabytes_is_refused_before_decompressing(tmp_path):
    """A 20000^2 float32 zero map compresses to ~1.5 MB; ``decamo`` took 3.2 GB to load
    it. The array's header is read first."""
    import resource
    import zipfile

    header = {"descr": "<f4", "fortran_order": False, "shape": (20000, 20000)}
    buf = __import__("io").BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    p = tmp_path / "bomb.npz"
    with zipfile.ZipFile(p, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("depth.npy", buf.getvalue() + b"\0" * 4096)  # the header is all that is read
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match=r"bomb.npz:depth: the array declares 400 MP, more than the 100 MP limit"):
        read_depth(f"{p}:depth")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000  # KB
    np.save(tmp_path / "ok.npy", np.ones((4, 5), np.float32))
    assert read_depth(tmp_path / "ok.npy").shape == (4, 5)
