"""The survey's pieces against exact synthetic truth: georeferencing a model onto GPS
positions (off a line, on a line, without GPS) and fusing pairs' height tiles."""

from __future__ import annotations

import numpy as np
import pytest

from prism3d.errors import InputError
from prism3d.reconstruct.survey.run import SurveyOptions, _dense_scale, _tile_bounds, fuse_tiles, georeference
from prism3d.reconstruct.survey.model import PairTile


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    import cv2

    v = np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(deg)
    return cv2.Rodrigues(v)[0]


def _scene(rng: np.random.Generator, lines: int = 2):
    """Camera centres of a lawnmower at 100 m over a ground (ENU) and ground points."""
    xs = np.arange(6) * 30.0
    C = np.concatenate([np.c_[xs, np.full(6, 60.0 * k), np.full(6, 100.0)] for k in range(lines)])
    P = np.c_[rng.uniform(-50, 200, 3000), rng.uniform(-40, 100, 3000), rng.normal(0, 0.2, 3000)]
    return C, P


@pytest.mark.parametrize("lines", [2, 1])
def test_georeference_recovers_the_similarity(lines: int) -> None:
    rng = np.random.default_rng(1)
    C, P = _scene(rng, lines)
    s, R = 0.037, _rot([0.3, -0.5, 0.8], 71.0)  # enu = s R model + t
    t = np.array([12.0, -7.0, 3.0])
    to_model = lambda X: (X - t) @ R / s  # noqa: E731
    gps = C + rng.normal(0, 0.05, C.shape)
    g = georeference(to_model(C), gps, to_model(P))
    # the cameras come back within GPS noise and the ground comes back level
    assert np.sqrt(np.mean(np.sum((g.apply(to_model(C)) - C) ** 2, axis=1))) < 0.12
    assert g.s == pytest.approx(s, rel=0.01)
    Pe = g.apply(to_model(P))
    assert np.abs(Pe[:, 2]).mean() < 0.4
    assert ("similarity" in g.method) == (lines == 2)


def test_georeference_without_gps_levels_the_model() -> None:
    rng = np.random.default_rng(2)
    C, P = _scene(rng)
    R = _rot([1, 2, 3], 40.0)
    g = georeference(C @ R.T, None, P @ R.T)
    assert g.residual_rms_m is None and "unknown" in g.method
    Pe = g.apply(P @ R.T)
    assert np.std(Pe[:, 2]) < 0.3  # level: the ground is flat in z
    assert np.allclose(g.apply((C @ R.T)[:1])[0, :2], 0.0, atol=1e-9)  # camera 1 above the origin
    assert np.abs(np.median(Pe[:, 2])) < 0.05  # the ground at height 0
    assert g.apply(C @ R.T)[:, 2].min() > 90.0  # cameras above the ground


def test_georeference_refuses_frames_that_do_not_move() -> None:
    rng = np.random.default_rng(3)
    C, P = _scene(rng, 1)
    with pytest.raises(InputError, match="same position"):
        georeference(C[:2], np.zeros((2, 3)), P)


def _tile(z: np.ndarray, west: float, north: float, cell: float) -> PairTile:
    return PairTile(west, north, cell, z.astype(np.float32), np.ones(z.shape, np.int32),
                    np.full(z.shape + (3,), 100, np.uint8))


def test_fusion_keeps_agreement_and_drops_contradiction() -> None:
    cell = 0.1
    a = np.full((20, 30), 5.0)
    b = np.full((20, 30), 5.02)
    c = np.full((20, 30), 5.01)
    c[5, 5] = 9.0  # one pair's blunder among three: outvoted
    b[:, 25:] = np.nan
    c[:, 25:] = np.nan
    a[10, 10], b[10, 10], c[10, 10] = 1.0, 3.0, 7.0  # three pairs that all disagree: no height
    f = fuse_tiles([_tile(a, 0.0, 2.0, cell), _tile(b, 0.0, 2.0, cell), _tile(c, 0.0, 2.0, cell)],
                   [0.01, 0.01, 0.01], band_rows=7)
    assert f.dsm.shape == (20, 30)
    assert f.dsm[5, 5] == pytest.approx(5.01, abs=1e-5)  # the blunder left out of the mean
    assert f.dsm[0, 0] == pytest.approx((5.0 + 5.02 + 5.01) / 3, abs=1e-5)
    assert np.isnan(f.dsm[10, 10])
    assert f.dsm[3, 27] == pytest.approx(5.0)  # seen by one pair only: kept
    assert f.agree[0, 0] == 3 and f.seen[3, 27] == 1


def test_fusion_places_offset_tiles_on_one_lattice() -> None:
    cell = 0.5
    a = np.arange(12, dtype=float).reshape(3, 4)
    f = fuse_tiles([_tile(a, 10.0, 20.0, cell), _tile(a + 100, 11.0, 19.0, cell)], [0.1, 0.1])
    assert (f.west, f.north) == (10.0, 20.0)
    assert f.dsm.shape == (5, 6)
    assert f.dsm[0, 0] == 0.0 and f.dsm[2, 4] == 102.0 and f.dsm[4, 5] == 111.0  # tile 2: 2 cells east, 2 south
    assert np.isnan(f.dsm[2, 3])  # both pairs there, 90 apart: contradiction


def test_fusion_needs_a_tile() -> None:
    with pytest.raises(InputError, match="no pair"):
        fuse_tiles([], [])


def test_tile_bounds_sit_on_the_lattice_and_hold_the_points() -> None:
    rng = np.random.default_rng(4)
    P = np.c_[rng.uniform(3.3, 9.7, 500), rng.uniform(-4.2, 2.9, 500), np.zeros(500)]
    from prism3d.reconstruct.survey.dsm import grid_points

    w, s, e, n = _tile_bounds(P, 0.25)
    assert w / 0.25 == pytest.approx(round(w / 0.25)) and n / 0.25 == pytest.approx(round(n / 0.25), abs=1e-6)
    g = grid_points(P, None, 0.25, bounds=(w, s, e, n))
    assert g.count.sum() == len(P)


def test_dense_scale_and_options() -> None:
    assert _dense_scale((4000, 3000), 3.2e6) == 2
    assert _dense_scale((1600, 1200), 3.2e6) == 1
    assert _dense_scale((4608, 3456), 3.2e6) == 3
    with pytest.raises(InputError, match="pair_steps"):
        SurveyOptions(pair_steps=(1, 1))
    with pytest.raises(InputError, match="cell"):
        SurveyOptions(cell_m=0.0)


def test_frames_whose_headers_declare_too_many_pixels_are_refused_before_decoding(tmp_path) -> None:
    """A PNG header claiming 60000 x 60000 pixels (Pillow's own bomb error before) and a
    folder given as a frame are one-line errors naming the file."""
    import struct
    import zlib

    from prism3d.reconstruct.survey.inputs import check_frames

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    big = tmp_path / "big.png"
    big.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0))
                    + chunk(b"IEND", b""))
    import cv2

    ok = tmp_path / "ok.png"
    cv2.imwrite(str(ok), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(InputError, match="big.png: the image declares 3,600 MP, more than the 100 MP limit"):
        check_frames([ok, big])
    with pytest.raises(InputError, match="is a folder"):
        check_frames([tmp_path])


def test_a_cell_beyond_a_kilometre_is_refused() -> None:
    for name in ("cell_m", "ortho_gsd_m", "cloud_spacing_m"):
        with pytest.raises(InputError, match="<= 1000 m"):
            SurveyOptions(**{name: 1e300})
    assert SurveyOptions(cell_m=1000.0).cell_m == 1000.0


def test_a_resume_leftover_that_is_a_file_is_refused(tmp_path) -> None:
    from prism3d.reconstruct.survey.resume import ResumeFolder, resume_dir

    out = tmp_path / "s"
    resume_dir(out).write_text("not a folder")
    with pytest.raises(InputError, match="exists and is not a folder"):
        ResumeFolder(out, [], None, None, SurveyOptions(), resume=True)


def test_resume_ignores_what_only_shapes_the_products(tmp_path) -> None:
    """A rerun that only changes the products' CRS, format, cloud spacing or orthophoto GSD
    keeps the poses and pairs; one that changes the DSM cell does not."""
    from prism3d.reconstruct.survey.resume import _fingerprint

    img = tmp_path / "a.jpg"
    img.write_bytes(b"x")
    base = _fingerprint([img], None, None, SurveyOptions())
    for change in ({"crs": "enu"}, {"laz": True}, {"cloud_spacing_m": 0.1}, {"ortho_gsd_m": 0.05}):
        assert _fingerprint([img], None, None, SurveyOptions(**change)) == base, change
    assert _fingerprint([img], None, None, SurveyOptions(cell_m=0.3)) != base
