"""Shared pytest fixtures.

Real third-party data lives outside the project (``../shared/data`` relative to the
repository root, or wherever ``PRISM3D_TEST_DATA`` points). Tests that need it take
the ``shared_data`` fixture, which skips (never fails) when the data is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import prism3d  # noqa: F401  (sets the process environment before numba/OpenGL load)

REPO_ROOT = Path(__file__).resolve().parents[1]


def _shared_data_dir() -> Path | None:
    env = os.environ.get("PRISM3D_TEST_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(REPO_ROOT.parent / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to the real test data folder, or skip the test when it is absent."""
    d = _shared_data_dir()
    if d is None:
        pytest.skip("real test data not found (set PRISM3D_TEST_DATA or place ../shared/data)")
    return d


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


#: Modules that take minutes, run first: `make test` spreads modules over two processes
#: (pytest-xdist, --dist loadfile), and a long module scheduled last would run alone.
_HEAVY_FIRST = ("test_demo_report.py", "test_survey.py", "test_scanned.py", "test_stitch.py", "test_object_frame.py",
                "test_capture_to_scan.py", "test_features.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(_HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order
