"""The numba camouflage kernel is bit-identical to the numpy reference (`_noise`)."""

from __future__ import annotations

import numpy as np
import pytest
from prism3d.capture import camouflage as camo
from prism3d.capture.camouflage import CamouflageField

import prism3d  # noqa: F401  (sets the environment)


def reference_labels(field: CamouflageField, pts: np.ndarray) -> np.ndarray:
    """The numpy path: `_noise` in 8192-point chunks, then the thresholds."""
    out = np.zeros(len(pts), dtype=np.uint8)
    for s in range(0, len(pts), camo._CHUNK):
        noise = camo._noise(
            np.asarray(pts[s : s + camo._CHUNK], dtype=np.float64),
            field.patch_size_mm, field._tables, field._rotations, field._offsets,
        )
        lab = np.zeros(len(noise), dtype=np.uint8)
        for k in range(noise.shape[1]):
            lab[noise[:, k] > field._thresholds[k]] = k + 1
        out[s : s + camo._CHUNK] = lab
    return out


@pytest.mark.parametrize(
    ("palette", "seed", "octaves", "patch"),
    [("woodland", 0, 2, 60.0), ("desert", 3, 1, 7.5), ("naval", 11, 4, 300.0), ("air", 5, 3, 20.0)],
)
def test_kernel_labels_are_bit_identical(monkeypatch, palette, seed, octaves, patch):
    field = CamouflageField.from_palette(palette, patch_size_mm=patch, seed=seed, octaves=octaves)
    rng = np.random.default_rng(seed)
    pts = np.concatenate(
        [
            rng.uniform(-2000, 2000, (40_000, 3)),
            np.c_[rng.uniform(-150, 150, (40_000, 2)), np.zeros(40_000)],  # a plate
            -rng.uniform(0, 1e4, (1000, 3)),  # negative lattice cells
        ]
    )
    ref = reference_labels(field, pts)
    np.testing.assert_array_equal(field.labels(pts), ref)
    monkeypatch.setattr(camo, "_KERNEL_CHUNK", 1000)  # chunk boundaries change nothing
    np.testing.assert_array_equal(field.labels(pts), ref)
    np.testing.assert_array_equal(field(pts[:5000]), np.array(field.colors)[ref[:5000]])
