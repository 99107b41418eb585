"""Disruptive camouflage paint as a procedural albedo field.

A :class:`CamouflageField` maps 3-D object-frame points (mm) to one of a few flat
paint colours with hard boundaries; the darkest colour of each built-in palette is
a near-black "false shadow", which the 3-D pipeline removes. Each colour after the
base coat is a layer of patches where a rotated fractal value-noise field exceeds a
threshold calibrated to the requested area fractions; defined in 3-D, the patches
wrap over edges without UV mapping. Construction details, periodicity and the numba
labeller: docs/capture.md ("Camouflage").

References
----------
.. [1] K. Perlin, "An image synthesizer", SIGGRAPH 1985 (lattice noise and its
   fractal sums).
.. [2] D. S. Ebert, F. K. Musgrave, D. Peachey, K. Perlin, S. Worley, *Texturing and
   Modeling: A Procedural Approach*, 3rd ed., Morgan Kaufmann, 2003, ch. 2 (value
   noise) and ch. 16 (fractional Brownian motion).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from prism3d.capture._scene_kernels import camouflage_labels
from prism3d.capture.mesh import UniformAlbedo
from prism3d.checks import check_array, check_choice, check_in_range, check_positive
from prism3d.errors import InputError

__all__ = [
    "PALETTES",
    "CLASS_PALETTES",
    "Palette",
    "CamouflageField",
    "camouflage_field",
    "plain_paint",
]

_LATTICE = 32  # lattice period (cells) per axis; power of two for cheap wrapping
_MASK = _LATTICE - 1
_CHUNK = 1 << 13  # points per chunk: keeps the (8, layers, chunk) temporaries in L2 cache
_CALIBRATION_POINTS = 1 << 17
_KERNEL_CHUNK = 1 << 20  # points per numba call: bounds the (octaves, 3, chunk) temporary


@dataclass(frozen=True)
class Palette:
    """A paint scheme: ``colors`` (linear albedo (r, g, b) in [0, 1], the first the
    base coat, later ones patch layers) and the area ``fractions`` they cover (sum 1).
    """

    colors: tuple[tuple[float, float, float], ...]
    fractions: tuple[float, ...]


PALETTES: dict[str, Palette] = {
    # NATO-style three/four-tone woodland: olive base, brown, black (shadow-like), tan.
    "woodland": Palette(
        colors=((0.22, 0.28, 0.13), (0.30, 0.21, 0.12), (0.05, 0.05, 0.04), (0.55, 0.50, 0.34)),
        fractions=(0.40, 0.27, 0.18, 0.15),
    ),
    # Desert: sand base, light brown, dark brown, black.
    "desert": Palette(
        colors=((0.70, 0.60, 0.42), (0.52, 0.40, 0.25), (0.26, 0.18, 0.11), (0.05, 0.05, 0.04)),
        fractions=(0.45, 0.25, 0.17, 0.13),
    ),
    # Naval: haze grey base, light grey, dark grey, near-black.
    "naval": Palette(
        colors=((0.50, 0.52, 0.55), (0.76, 0.78, 0.80), (0.27, 0.29, 0.32), (0.06, 0.07, 0.09)),
        fractions=(0.45, 0.20, 0.20, 0.15),
    ),
    # Tactical aircraft: medium grey base, dark green, black-green.
    "air": Palette(
        colors=((0.45, 0.47, 0.46), (0.20, 0.26, 0.18), (0.06, 0.07, 0.06)),
        fractions=(0.45, 0.35, 0.20),
    ),
}
"""Built-in palettes by name."""

CLASS_PALETTES: dict[str, str] = {
    "tank": "woodland",
    "truck": "woodland",
    "jet": "air",
    "ship": "naval",
}
"""Default palette name of each built-in target class."""


def _check_palette(colors: NDArray[np.float64], fractions: NDArray[np.float64]) -> None:
    if len(colors) < 2 or len(colors) > 8:
        raise InputError(f"colors: expected 2 to 8 paint colours, got {len(colors)}")
    if colors.min() < 0.0 or colors.max() > 1.0:
        raise InputError("colors: expected albedo values in [0, 1]")
    if fractions.shape != (len(colors),):
        raise InputError(
            f"fractions: expected {len(colors)} values (one per colour), got {fractions.shape[0]}"
        )
    if fractions.min() <= 0.0 or abs(fractions.sum() - 1.0) > 1e-6:
        raise InputError(
            f"fractions: expected positive values summing to 1, got {tuple(fractions.tolist())}"
        )


def _random_rotation(rng: np.random.Generator) -> NDArray[np.float64]:
    """A uniformly random 3x3 rotation (unit quaternion from a Gaussian)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _noise(
    points: NDArray[np.float64],
    patch_size_mm: float,
    tables: NDArray[np.float32],
    rotations: NDArray[np.float64],
    offsets: NDArray[np.float64],
) -> NDArray[np.float32]:
    """Fractal value noise ``(n, layers)`` float32 at points ``(n, 3)`` (one chunk)."""
    n = len(points)
    out = np.zeros((tables.shape[2], n), dtype=np.float32)
    amp = np.float32(1.0)
    for o in range(len(rotations)):
        freq = (2.0**o) / patch_size_mm
        q = (rotations[o] * freq) @ points.T  # (3, n) lattice coordinates
        q += offsets[o][:, None]
        qi = np.floor(q)
        q -= qi
        f = q.astype(np.float32)
        u = f * f * (np.float32(3.0) - np.float32(2.0) * f)  # smoothstep fade
        i = qi.astype(np.int64)
        i &= _MASK
        base = i[0] * (_LATTICE * _LATTICE)
        base += i[1] * _LATTICE
        base += i[2]
        # One gather fetches all 8 cell corners (corner index = 4 dz + 2 dy + dx),
        # transposed to (8, layers, n) so the blends below run on contiguous rows.
        c = np.take(tables, base, axis=0).reshape(n, -1).T.copy()
        c = c.reshape(8, -1, n)
        ux, uy, uz = u[0], u[1], u[2]
        # trilinear blend with faded weights: along z, then y, then x
        lo = c[:4]  # dz = 0; (4, layers, n), corner = 2 dy + dx
        hi = c[4:]
        hi -= lo
        hi *= uz
        lo += hi
        v0 = lo[:2]  # dy = 0; (2, layers, n), index dx
        v1 = lo[2:]
        v1 -= v0
        v1 *= uy
        v0 += v1
        v = v0[1] - v0[0]
        v *= ux
        v += v0[0]  # (layers, n)
        v *= amp
        out += v
        amp *= np.float32(0.5)
    return out.T


@functools.lru_cache(maxsize=8)
def _lattice_state(
    seed: int, octaves: int, fractions: tuple[float, ...]
) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float64], NDArray[np.float32]]:
    """Random lattice, octave rotations and offsets, and calibrated thresholds, in
    lattice units: cached per (seed, octaves, fractions).
    """
    layers = len(fractions) - 1
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5EED_CA40]))
    lattice = rng.uniform(-1.0, 1.0, size=(_LATTICE, _LATTICE, _LATTICE, layers))
    # Corner table: entry (x, y, z) holds the 8 lattice values of the cell whose
    # low corner is (x, y, z) (periodic), corner index 4 dz + 2 dy + dx.
    corners = [
        np.roll(lattice, (-dx, -dy, -dz), axis=(0, 1, 2))
        for dz in (0, 1)
        for dy in (0, 1)
        for dx in (0, 1)
    ]
    tables = np.ascontiguousarray(
        np.stack(corners, axis=3).reshape(_LATTICE**3, 8, layers), dtype=np.float32
    )
    rotations = np.stack([_random_rotation(rng) for _ in range(octaves)])
    offsets = rng.uniform(0.0, _LATTICE, size=(octaves, 3))

    # Per-layer coverage p_k so that the final fraction of colour k, after the
    # later layers are painted over it, is fractions[k]:
    # f_k = p_k * prod_{j>k} (1 - p_j), solved from the top layer down.
    p = np.zeros(layers)
    remaining = 1.0
    for k in range(layers, 0, -1):
        p[k - 1] = fractions[k] / remaining
        remaining *= 1.0 - p[k - 1]
    # Threshold = (1 - p_k) quantile of each layer's noise, measured on a
    # deterministic sample spanning one full lattice period.
    sample = np.random.default_rng(12345).uniform(0.0, _LATTICE, size=(_CALIBRATION_POINTS, 3))
    noise = np.concatenate(
        [
            _noise(sample[i : i + _CHUNK], 1.0, tables, rotations, offsets)
            for i in range(0, _CALIBRATION_POINTS, _CHUNK)
        ]
    )
    thresholds = np.array(
        [np.quantile(noise[:, k], 1.0 - p[k]) for k in range(layers)], dtype=np.float32
    )
    for arr in (tables, rotations, offsets, thresholds):
        arr.setflags(write=False)
    return tables, rotations, offsets, thresholds


@dataclass(frozen=True, eq=False)
class CamouflageField:
    """Piecewise-constant multi-colour camouflage, a callable albedo field.

    ``colors``: 2 to 8 flat (r, g, b) in [0, 1], the first the base coat; ``fractions``:
    area per colour (sum 1); ``patch_size_mm``: patch diameter in the evaluation frame;
    ``seed``: same seed, same pattern bit for bit; ``octaves`` 1-4 (more = raggeder
    edges); ``name`` for metadata. Called on ``(N, 3)`` mm points it returns ``(N, 3)``
    float64 albedo; :meth:`labels` the colour index.
    """

    colors: tuple[tuple[float, float, float], ...]
    fractions: tuple[float, ...]
    patch_size_mm: float = 30.0
    seed: int = 0
    octaves: int = 2
    name: str = "custom"
    _colors: NDArray[np.float64] = field(init=False, repr=False)
    _tables: NDArray[np.float32] = field(init=False, repr=False)
    _rotations: NDArray[np.float64] = field(init=False, repr=False)
    _offsets: NDArray[np.float64] = field(init=False, repr=False)
    _thresholds: NDArray[np.float32] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        colors = check_array(self.colors, "colors", shape=(None, 3), dtype_kind="fiu").astype(
            np.float64
        )
        fractions = check_array(self.fractions, "fractions", ndim=1, dtype_kind="fiu").astype(
            np.float64
        )
        _check_palette(colors, fractions)
        check_positive(self.patch_size_mm, "patch_size_mm")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise InputError(f"seed: expected a non-negative integer, got {self.seed!r}")
        if not isinstance(self.octaves, (int, np.integer)):
            raise InputError(f"octaves: expected an integer in [1, 4], got {self.octaves!r}")
        check_in_range(self.octaves, "octaves", 1, 4)
        object.__setattr__(self, "colors", tuple(tuple(map(float, c)) for c in colors))
        object.__setattr__(self, "fractions", tuple(map(float, fractions)))
        object.__setattr__(self, "patch_size_mm", float(self.patch_size_mm))
        object.__setattr__(self, "_colors", colors)

        tables, rotations, offsets, thresholds = _lattice_state(
            int(self.seed), int(self.octaves), tuple(map(float, fractions))
        )
        object.__setattr__(self, "_tables", tables)
        object.__setattr__(self, "_rotations", rotations)
        object.__setattr__(self, "_offsets", offsets)
        object.__setattr__(self, "_thresholds", thresholds)

    def __reduce__(self) -> tuple:
        # Rebuild from the parameters (the cached lattice makes this cheap): keeps
        # process-pool payloads small instead of shipping the 3 MB lattice table.
        args = (self.colors, self.fractions, self.patch_size_mm, self.seed, self.octaves, self.name)
        return (type(self), args)

    @classmethod
    def from_palette(
        cls, palette: str, *, patch_size_mm: float = 30.0, seed: int = 0, octaves: int = 2
    ) -> CamouflageField:
        """A field using one of the built-in :data:`PALETTES` by name."""
        check_choice(palette, "palette", PALETTES)
        pal = PALETTES[palette]
        return cls(pal.colors, pal.fractions, patch_size_mm, seed, octaves, palette)

    # -- evaluation -------------------------------------------------------------------

    def labels(self, points_obj: NDArray[np.float64]) -> NDArray[np.uint8]:
        """``(N,) uint8`` paint colour index (0 = base coat) of ``(N, 3)`` object-frame
        points in mm.
        """
        pts = check_array(points_obj, "points_obj", shape=(None, 3), dtype_kind="fiu")
        out = np.zeros(len(pts), dtype=np.uint8)
        octaves = len(self._rotations)
        qbuf = np.empty(octaves * 3 * min(len(pts), _KERNEL_CHUNK))
        for start in range(0, len(pts), _KERNEL_CHUNK):
            chunk = np.asarray(pts[start : start + _KERNEL_CHUNK], dtype=np.float64)
            # the matrix products are numpy's (same rounding as `_noise`); the
            # per-point loops run in a numba kernel that repeats `_noise` exactly.
            # Big chunks: handing the cores between BLAS and numba threads is slow.
            q = qbuf[: octaves * 3 * len(chunk)].reshape(octaves, 3, len(chunk))
            for o in range(octaves):
                np.matmul(self._rotations[o] * ((2.0**o) / self.patch_size_mm), chunk.T, out=q[o])
            camouflage_labels(
                q, self._offsets, self._tables, self._thresholds, out[start : start + _KERNEL_CHUNK]
            )
        return out

    def __call__(self, points_obj: NDArray[np.float64]) -> NDArray[np.float64]:
        """Albedo ``(N, 3)`` float64 in [0, 1] at object-frame points ``(N, 3)`` mm."""
        return np.take(self._colors, self.labels(points_obj), axis=0)

    @property
    def dark_index(self) -> int:
        """Index of the darkest colour (the shadow-mimicking patches)."""
        lum = self._colors @ np.array([0.2126, 0.7152, 0.0722])
        return int(np.argmin(lum))


def camouflage_field(
    target_class: str, *, patch_size_mm: float, seed: int = 0, palette: str | None = None
) -> CamouflageField:
    """The default camouflage of a built-in ``target_class`` (a key of
    :data:`CLASS_PALETTES`), patch diameter ``patch_size_mm`` in the model frame,
    ``seed``, optional ``palette`` override (a key of :data:`PALETTES`).
    """
    check_choice(target_class, "target_class", CLASS_PALETTES)
    name = CLASS_PALETTES[target_class] if palette is None else palette
    return CamouflageField.from_palette(name, patch_size_mm=patch_size_mm, seed=seed)


def plain_paint(target_class: str, *, palette: str | None = None) -> UniformAlbedo:
    """A :class:`UniformAlbedo` of the base (first) colour of ``target_class``'s
    palette (or ``palette``): paint without camouflage patches.
    """
    check_choice(target_class, "target_class", CLASS_PALETTES)
    name = CLASS_PALETTES[target_class] if palette is None else palette
    check_choice(name, "palette", PALETTES)
    return UniformAlbedo(PALETTES[name].colors[0])
