"""Nearest-neighbour queries of a scipy ``cKDTree`` spread over a thread pool kept for the
process.

scipy's ``workers=-1`` starts new Python threads on every call. The stitcher makes
thousands of queries of ~10k points (two per view pair and Gauss-Newton step), and on 2
shared cores each thread start cost about a millisecond (measured; docs/performance.md).
The tree releases the GIL while it searches, so the same chunks queried from threads that
already exist run in parallel with no start cost, and give the same answers.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from numpy.typing import NDArray

from prism3d._env import configured_threads

__all__ = ["query_tree"]

#: Fewest points a chunk gets: below this a chunk's hand-off costs more than it saves.
MIN_CHUNK = 2000

_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def _threads() -> int:
    """Threads a query may use: ``PRISM3D_NUM_THREADS`` when set (a job worker's 1), else
    the cores this process may run on."""
    n = configured_threads()
    if n:
        return n
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _executor(threads: int) -> ThreadPoolExecutor:
    """The process's pool, grown to ``threads`` when it has fewer."""
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < threads:
            _pool, _pool_size = ThreadPoolExecutor(threads, thread_name_prefix="prism3d-kdtree"), threads
        return _pool


def query_tree(tree: Any, points: NDArray, *, k: int = 1,
               distance_upper_bound: float = np.inf) -> tuple[NDArray, NDArray]:
    """``tree.query(points, k=k, distance_upper_bound=...)`` (distances, indices; misses are
    ``inf`` and ``tree.n``), the points split into one chunk per thread."""
    pts = np.asarray(points)
    threads = min(_threads(), len(pts) // MIN_CHUNK)
    if threads < 2:
        return tree.query(pts, k=k, distance_upper_bound=distance_upper_bound)
    pool = _executor(threads)
    futures = [pool.submit(tree.query, part, k, 0.0, 2.0, distance_upper_bound)
               for part in np.array_split(pts, threads)]
    parts = [f.result() for f in futures]
    return np.concatenate([d for d, _ in parts]), np.concatenate([i for _, i in parts])
