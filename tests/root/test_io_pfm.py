from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.io.pfm import read_pfm, write_pfm


@pytest.mark.parametrize("little", [True, False])
@pytest.mark.parametrize("shape", [(7, 5), (4, 6, 3)])
def test_round_trip(tmp_path, little, shape):
    rng = np.random.default_rng(1)
    a = rng.normal(size=shape).astype(np.float32)
    a.flat[3] = np.inf
    a.flat[4] = np.nan
    write_pfm(tmp_path / "a.pfm", a, little_endian=little)
    b = read_pfm(tmp_path / "a.pfm")
    assert b.dtype == np.float32 and b.shape == shape
    np.testing.assert_array_equal(b, a)


def test_rows_are_stored_bottom_up(tmp_path):
    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    write_pfm(tmp_path / "a.pfm", a)
    raw = (tmp_path / "a.pfm").read_bytes()
    body = np.frombuffer(raw[-24:], "<f4").reshape(2, 3)
    np.testing.assert_array_equal(body, a[::-1])
    assert raw.startswith(b"Pf\n3 2\n-1.0\n")


def test_big_endian_file_by_hand(tmp_path):
    a = np.array([[1.5, -2.0]], dtype=">f4")
    (tmp_path / "b.pfm").write_bytes(b"Pf\n2 1\n1.0\n" + a.tobytes())
    np.testing.assert_array_equal(read_pfm(tmp_path / "b.pfm"), [[1.5, -2.0]])


@pytest.mark.parametrize(
    "content, match",
    [
        (b"P6\n2 2\n255\n" + bytes(12), "not a PFM"),
        (b"Pf\nx y\n-1\n", "malformed PFM header"),
        (b"Pf\n4 4\n-1.0\n" + bytes(10), "truncated"),
        (b"Pf\n0 4\n-1.0\n", "implausible"),
        (b"Pf\n99999999 99999999\n-1.0\n", "implausible"),
        (b"Pf\n1 1\n0\n" + bytes(4), "non-zero"),
        (b"", "not a PFM"),
    ],
)
def test_malformed(tmp_path, content, match):
    p = tmp_path / "bad.pfm"
    p.write_bytes(content)
    with pytest.raises(InputError, match=match):
        read_pfm(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_pfm(tmp_path / "nope.pfm")


def test_write_rejects_bad_shape(tmp_path):
    with pytest.raises(InputError, match="1 or 3 channels"):
        write_pfm(tmp_path / "x.pfm", np.zeros((2, 2, 2), np.float32))
    assert not (tmp_path / "x.pfm").exists()


@pytest.mark.realdata
@pytest.mark.parametrize("scene", ["playground", "terrace"])
def test_eth3d_ground_truth_matches_opencv(shared_data, scene):
    """Our reader reproduces ETH3D's disp0.pfm exactly as OpenCV decodes it."""
    import cv2

    path = shared_data / "stereo" / "eth3d_two_view" / scene / "disp0.pfm"
    ours = read_pfm(path)
    ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert ref is not None and ours.shape == ref.shape
    np.testing.assert_array_equal(ours, ref)  # inf = unknown kept as inf
    # sanity: the image is top-down (the first left-image rows are sky/unknown or valid,
    # and the known disparities are in a plausible range)
    finite = ours[np.isfinite(ours)]
    assert 0.2 < finite.size / ours.size < 0.9
    assert 0 < finite.min() and finite.max() < 100


def _warp_correlation(disp, im0, im1):
    ys, xs = np.nonzero(np.isfinite(disp))
    xr = np.round(xs - disp[ys, xs]).astype(int)
    keep = (xr >= 0) & (xr < im1.shape[1])
    return np.corrcoef(im1[ys[keep], xr[keep]], im0[ys[keep], xs[keep]])[0, 1]


@pytest.mark.realdata
@pytest.mark.parametrize("scene", ["playground", "terrace"])
def test_eth3d_orientation_is_right(shared_data, scene):
    """Independent check of row order: the GT disparity maps left pixels onto the same
    scene points in the right image (correlation ~0.99); rows read upside down would not."""
    import cv2

    d = shared_data / "stereo" / "eth3d_two_view" / scene
    disp = read_pfm(d / "disp0.pfm")
    im0 = cv2.imread(str(d / "im0.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
    im1 = cv2.imread(str(d / "im1.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)
    good = _warp_correlation(disp, im0, im1)
    flipped = _warp_correlation(disp[::-1], im0, im1)
    assert good > 0.98
    assert good - flipped > 0.03
