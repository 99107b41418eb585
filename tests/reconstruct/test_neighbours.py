"""Tree queries spread over the thread pool give exactly what one ``cKDTree.query`` gives."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from prism3d.reconstruct.scan import neighbours
from prism3d.reconstruct.scan.neighbours import MIN_CHUNK, query_tree


@pytest.mark.parametrize("k", [1, 3])
@pytest.mark.parametrize("n", [0, 5, MIN_CHUNK * 2 - 1, MIN_CHUNK * 5 + 7])
def test_same_answers_as_one_query(k, n, monkeypatch):
    monkeypatch.setenv("PRISM3D_NUM_THREADS", "3")  # three chunks whatever the machine
    rng = np.random.default_rng(n + k)
    tree = cKDTree(rng.uniform(0, 1, (20000, 3)))
    q = rng.uniform(-0.1, 1.1, (n, 3))
    for bound in (np.inf, 0.02):
        d, i = query_tree(tree, q, k=k, distance_upper_bound=bound)
        d0, i0 = tree.query(q, k=k, distance_upper_bound=bound)
        assert d.shape == d0.shape and i.shape == i0.shape
        np.testing.assert_array_equal(d, d0)
        np.testing.assert_array_equal(i, i0)  # misses: inf and tree.n, as scipy gives
        if bound < np.inf and n:
            assert np.isinf(d).any()


def test_one_thread_when_a_job_worker_asks(monkeypatch):
    """A job worker (PRISM3D_NUM_THREADS=1) queries in its own thread, no pool."""
    monkeypatch.setenv("PRISM3D_NUM_THREADS", "1")
    monkeypatch.setattr(neighbours, "_executor", lambda threads: pytest.fail("pool used"))
    tree = cKDTree(np.random.default_rng(0).uniform(0, 1, (1000, 3)))
    d, _ = query_tree(tree, np.zeros((MIN_CHUNK * 4, 3)))
    assert d.shape == (MIN_CHUNK * 4,)
