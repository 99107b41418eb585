"""Colour-coded gratings for the flash projector (RGB ``uint8``): vertical stripes,
neighbours differ and every ``window`` stripes occur once along x.

References
----------
.. [1] H. Fredricksen, J. Maiorana, "Necklaces of beads in k colors and k-ary de Bruijn
   sequences", Discrete Mathematics 23 (1978).
.. [2] J. Salvi, J. Pages, J. Batlle, "Pattern codification strategies in structured
   light systems", Pattern Recognition 37 (2004) -- De Bruijn colour stripe coding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from prism3d.checks import check_array, check_positive
from prism3d.errors import InputError
from prism3d.io.images import write_image

__all__ = [
    "DEFAULT_COLORS",
    "de_bruijn",
    "stripe_sequence",
    "stripe_ids",
    "stripe_pattern",
    "grid_pattern",
    "check_window_unique",
    "save_pattern_png",
]

#: Six saturated projector colours (RGB uint8): red, green, blue, cyan, magenta, yellow.
DEFAULT_COLORS: NDArray[np.uint8] = np.array(
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [0, 255, 255], [255, 0, 255], [255, 255, 0]],
    dtype=np.uint8,
)
DEFAULT_COLORS.setflags(write=False)


def de_bruijn(k: int, n: int) -> NDArray[np.int64]:
    """The lexicographically least De Bruijn sequence B(k, n): ``(k**n,) int64`` in
    ``[0, k)`` where every length-``n`` word occurs once cyclically (Fredricksen and
    Maiorana: Lyndon words whose length divides ``n``, in order).
    """
    k = int(k)
    n = int(n)
    if k < 2:
        raise InputError(f"de_bruijn: k (alphabet size) must be >= 2, got {k}")
    if n < 1:
        raise InputError(f"de_bruijn: n (word length) must be >= 1, got {n}")
    if k**n > 50_000_000:
        raise InputError(f"de_bruijn: k**n = {k**n} is too long a sequence")
    seq: list[int] = []
    w = [0]
    while w:
        if n % len(w) == 0:
            seq.extend(w)
        m = len(w)
        while len(w) < n:  # repeat the Lyndon word to length n
            w.append(w[len(w) - m])
        while w and w[-1] == k - 1:  # drop trailing maximal symbols
            w.pop()
        if w:
            w[-1] += 1
    return np.asarray(seq, dtype=np.int64)


def _eulerian_stripe_sequence(k: int, window: int, rng: np.random.Generator | None) -> list[int]:
    """Longest colour sequence with no equal neighbours and unique ``window``-runs:
    an Eulerian circuit (Hierholzer) of the graph of valid runs.
    """
    if window == 1:
        order = list(range(k))
        if rng is not None:
            rng.shuffle(order)
        return order
    m = window - 1
    # enumerate nodes: tuples of length m with no equal neighbours
    nodes: list[tuple[int, ...]] = [(c,) for c in range(k)]
    for _ in range(m - 1):
        nodes = [t + (c,) for t in nodes for c in range(k) if c != t[-1]]
    out: dict[tuple[int, ...], list[int]] = {}
    for t in nodes:
        succ = [c for c in range(k) if c != t[-1]]
        if rng is not None:
            rng.shuffle(succ)
        else:
            succ.reverse()  # pop() from the end takes the smallest colour first
        out[t] = succ
    start = nodes[0]
    stack: list[tuple[int, ...]] = [start]
    circuit: list[tuple[int, ...]] = []
    while stack:
        v = stack[-1]
        if out[v]:
            c = out[v].pop()
            stack.append(v[1:] + (c,))
        else:
            circuit.append(stack.pop())
    circuit.reverse()
    # circuit is a closed walk of nodes; the colour sequence is the first node then
    # the last symbol of every following node.
    # Every window of the result is a distinct edge; the first ``len - m`` symbols
    # also form a cyclic sequence with unique cyclic windows.
    return list(circuit[0]) + [v[-1] for v in circuit[1:]]


def stripe_sequence(
    n_stripes: int, *, n_colors: int = len(DEFAULT_COLORS), window: int = 3, seed: int | None = None
) -> NDArray[np.int64]:
    """``(n_stripes,) int64`` colour indices (of ``n_colors`` >= 3): neighbours differ,
    ``window``-runs unique; ``seed`` randomises deterministically (None = canonical).
    """
    n_stripes = int(n_stripes)
    n_colors = int(n_colors)
    window = int(window)
    if n_colors < 3:
        raise InputError(f"n_colors: need at least 3 colours, got {n_colors}")
    if window < 1:
        raise InputError(f"window: expected >= 1, got {window}")
    if n_stripes < 1:
        raise InputError(f"n_stripes: expected >= 1, got {n_stripes}")
    capacity = n_colors * (n_colors - 1) ** (window - 1) + window - 1 if window > 1 else n_colors
    if n_stripes > capacity:
        raise InputError(
            f"{n_stripes} stripes requested but {n_colors} colours with window {window} give "
            f"at most {capacity} uniquely coded stripes; increase the period, the window or "
            "the number of colours"
        )
    rng = None if seed is None else np.random.default_rng(seed)
    seq = _eulerian_stripe_sequence(n_colors, window, rng)
    return np.asarray(seq[:n_stripes], dtype=np.int64)


def _check_colors(colors: NDArray) -> NDArray[np.uint8]:
    c = check_array(colors, "colors", shape=(None, 3), dtype_kind="iuf")
    if len(c) < 3:
        raise InputError(f"colors: need at least 3 colours, got {len(c)}")
    if c.min() < 0 or c.max() > 255:
        raise InputError("colors: RGB values must lie in [0, 255]")
    c8 = c.astype(np.uint8)
    if len(np.unique(c8, axis=0)) != len(c8):
        raise InputError("colors: colours must be distinct")
    return c8


def stripe_ids(
    width: int,
    *,
    period_px: int = 8,
    n_colors: int = len(DEFAULT_COLORS),
    window: int = 3,
    seed: int | None = None,
) -> NDArray[np.int64]:
    """Colour index of every pattern column ``(width,)`` for :func:`stripe_pattern`."""
    width = int(width)
    if width < 1:
        raise InputError(f"width: expected >= 1, got {width}")
    period = int(check_positive(period_px, "period_px"))
    if period != period_px:
        raise InputError(f"period_px: expected an integer, got {period_px!r}")
    n = -(-width // period)
    seq = stripe_sequence(n, n_colors=n_colors, window=window, seed=seed)
    return np.repeat(seq, period)[:width]


def stripe_pattern(
    width: int,
    height: int,
    *,
    period_px: int = 8,
    colors: NDArray = DEFAULT_COLORS,
    window: int = 3,
    seed: int | None = None,
) -> NDArray[np.uint8]:
    """``(height, width, 3) uint8`` vertical De Bruijn stripes ``period_px`` wide
    from the ``colors`` (K, 3) table, every ``window`` stripes unique along x; ``seed``
    randomises the order deterministically.
    """
    c = _check_colors(colors)
    height = int(height)
    if height < 1:
        raise InputError(f"height: expected >= 1, got {height}")
    ids = stripe_ids(width, period_px=period_px, n_colors=len(c), window=window, seed=seed)
    row = c[ids]
    return np.ascontiguousarray(np.broadcast_to(row, (height,) + row.shape))


def grid_pattern(
    width: int,
    height: int,
    *,
    period_px: int = 8,
    colors: NDArray = DEFAULT_COLORS,
    window: int = 3,
    line_px: int = 1,
    row_shift: int = 1,
    seed: int | None = None,
) -> NDArray[np.uint8]:
    """``(height, width, 3) uint8`` colour grid: cell ``(r, c)`` takes
    ``seq[c + r * row_shift]`` of a stripe sequence, between black grid lines (corners in 2-D).
    """
    c = _check_colors(colors)
    width = int(width)
    height = int(height)
    if width < 1 or height < 1:
        raise InputError(f"width and height must be >= 1, got {(width, height)}")
    period = int(period_px)
    if period < 2:
        raise InputError(f"period_px: expected >= 2 for a grid, got {period_px}")
    line_px = int(line_px)
    if not 0 <= line_px < period:
        raise InputError(f"line_px: expected 0 <= line_px < period_px, got {line_px}")
    row_shift = int(row_shift)
    if row_shift < 0:
        raise InputError(f"row_shift: expected >= 0, got {row_shift}")
    n_cols = -(-width // period)
    n_colors = len(c)
    capacity = n_colors * (n_colors - 1) ** (window - 1) if window > 1 else n_colors
    if n_cols > capacity:
        raise InputError(
            f"{n_cols} grid columns requested but {n_colors} colours with window {window} "
            f"code at most {capacity}; increase the period, the window or the colours"
        )
    # the cyclic part of the Eulerian sequence: cyclic windows are unique too
    cyc = stripe_sequence(capacity + window - 1, n_colors=n_colors, window=window, seed=seed)
    cyc = cyc[:capacity]
    cols = np.arange(width) // period
    rows = np.arange(height) // period
    idx = cyc[(cols[None, :] + rows[:, None] * row_shift) % capacity]
    out = c[idx]
    if line_px:
        out[(np.arange(height) % period) < line_px, :] = 0
        out[:, (np.arange(width) % period) < line_px] = 0
    return np.ascontiguousarray(out)


def check_window_unique(ids: NDArray, window: int) -> bool:
    """True when neighbours of the per-stripe ``ids`` (N,) differ and every
    ``window``-run occurs once.
    """
    a = check_array(ids, "ids", ndim=1, dtype_kind="iu")
    window = int(window)
    if window < 1:
        raise InputError(f"window: expected >= 1, got {window}")
    if len(a) >= 2 and np.any(a[1:] == a[:-1]):
        return False
    if len(a) < window:
        return True
    runs = np.lib.stride_tricks.sliding_window_view(a, window)
    return len(np.unique(runs, axis=0)) == len(runs)


def save_pattern_png(path: str | Path, pattern: NDArray) -> None:
    """Write an RGB ``(H, W, 3) uint8`` pattern as PNG, atomically."""
    p = check_array(pattern, "pattern", ndim=(2, 3), dtype_kind="u")
    if p.dtype != np.uint8:
        raise InputError(f"pattern: expected uint8, got {p.dtype}")
    if p.ndim == 3 and p.shape[2] != 3:
        raise InputError(f"pattern: expected 3 channels (RGB), got {p.shape[2]}")
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"{path}: pattern files must end in .png")
    write_image(path, p)
