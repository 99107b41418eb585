from __future__ import annotations

import os

import numpy as np
import pytest

import prism3d
from prism3d.checks import (
    check_array,
    check_choice,
    check_file,
    check_finite,
    check_in_range,
    check_outputs_not_inputs,
    check_positive,
    check_same_shape,
)
from prism3d.errors import (
    CalibrationError,
    DatasetError,
    DeviceError,
    InputError,
    Prism3dError,
    ReconstructionError,
)
from prism3d.io.atomic import atomic_open, atomic_path, atomic_write_text


def test_error_family():
    for cls in (InputError, CalibrationError, ReconstructionError, DeviceError, DatasetError):
        assert issubclass(cls, Prism3dError)
    assert issubclass(InputError, ValueError)
    assert prism3d.InputError is InputError


def test_atomic_write_success_and_failure(tmp_path):
    p = tmp_path / "out.txt"
    atomic_write_text(p, "old")
    with pytest.raises(RuntimeError):
        with atomic_open(p, "w") as fh:
            fh.write("half of the new")
            raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert [f.name for f in tmp_path.iterdir()] == ["out.txt"]  # no temp left behind
    atomic_write_text(p, "new")
    assert p.read_text() == "new"
    assert oct(p.stat().st_mode & 0o777) != oct(0o600) or os.umask(0o022) == 0o077


def test_atomic_path_keeps_suffix(tmp_path):
    with atomic_path(tmp_path / "sub" / "x.png") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path / "sub"
        tmp.write_bytes(b"1")
    assert (tmp_path / "sub" / "x.png").read_bytes() == b"1"


def test_check_array_messages():
    a = check_array([[1, 2, 3]], "pts", shape=(None, 3))
    assert a.shape == (1, 3)
    with pytest.raises(InputError, match=r"pts: expected shape \(\*, 3\), got \(2, 2\)"):
        check_array(np.zeros((2, 2)), "pts", shape=(None, 3))
    with pytest.raises(InputError, match="expected 2 or 3 dimensions, got 1"):
        check_array(np.zeros(3), "img", ndim=(2, 3))
    with pytest.raises(InputError, match="dtype kind"):
        check_array(np.zeros(3, bool), "x", dtype_kind="f")
    with pytest.raises(InputError, match="at least 4 elements"):
        check_array(np.zeros(3), "x", min_size=4)
    with pytest.raises(CalibrationError, match="x: expected"):
        check_array(np.zeros(3), "x", ndim=2, error=CalibrationError)


def test_scalar_checks(tmp_path):
    assert check_positive(2, "n") == 2.0
    with pytest.raises(InputError, match="n: expected a finite number > 0, got -1"):
        check_positive(-1, "n")
    with pytest.raises(InputError, match="expected a number"):
        check_positive("abc", "n")
    assert check_positive(0, "n", strict=False) == 0
    with pytest.raises(InputError, match=r"in \[0, 1\]"):
        check_in_range(2, "alpha", 0, 1)
    with pytest.raises(InputError, match="expected one of a, b"):
        check_choice("c", "mode", ["a", "b"])
    with pytest.raises(InputError, match="NaN or inf"):
        check_finite(np.array([1, np.nan]), "x")
    with pytest.raises(InputError, match="same shape"):
        check_same_shape(np.zeros((2, 3)), np.zeros((3, 2)), ("left", "right"))
    with pytest.raises(InputError, match="not found"):
        check_file(tmp_path / "nope")
    with pytest.raises(InputError, match="directory"):
        check_file(tmp_path)


def test_staged_folder_all_or_nothing(tmp_path):
    """A command's outputs appear together: a failure half-way leaves the folder as it
    was (absent, or with its old files untouched); success moves them all in."""
    from prism3d.io.atomic import staged_folder

    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with staged_folder(out) as stage:
            (stage / "a.txt").write_text("a")
            raise RuntimeError("disk full, say")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no folder, no leftovers
    with staged_folder(out) as stage:
        (stage / "a.txt").write_text("a")
        (stage / "sub").mkdir()
        (stage / "sub" / "b.txt").write_text("b")
    assert (out / "a.txt").read_text() == "a" and (out / "sub" / "b.txt").read_text() == "b"
    with pytest.raises(RuntimeError):
        with staged_folder(out) as stage:
            (stage / "a.txt").write_text("new")
            raise RuntimeError
    assert (out / "a.txt").read_text() == "a"  # the old output kept
    with staged_folder(out) as stage:
        (stage / "a.txt").write_text("new")
    assert (out / "a.txt").read_text() == "new" and (out / "sub" / "b.txt").read_text() == "b"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_an_output_folder_has_one_writer(tmp_path):
    """A second writer of a folder being written is refused with one line and changes
    nothing; the lock goes with the first writer."""
    from prism3d.io.atomic import staged_folder

    out = tmp_path / "out"
    with staged_folder(out) as stage:
        (stage / "a.txt").write_text("first")
        with pytest.raises(InputError, match="another prism3d process .* is writing it"):
            with staged_folder(out) as other:
                (other / "a.txt").write_text("second")
    assert (out / "a.txt").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no lock, no staging folder left


def test_a_dead_writers_lock_and_staging_are_taken_over(tmp_path):
    """A lock left by a process that died (kill -9) is taken over, and the staging folder
    it had started is removed."""
    import json
    import socket
    import subprocess
    import sys

    from prism3d.io.atomic import staged_folder

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    pid = int(dead.stdout)  # that process has exited
    out = tmp_path / "out"
    left = tmp_path / ".out.abc123.tmp"
    left.mkdir()
    (left / "half.bin").write_bytes(b"x")
    (tmp_path / ".out.lock").write_text(json.dumps({"host": socket.gethostname(), "pid": pid,
                                                     "stages": [str(left)]}))
    with staged_folder(out) as stage:
        (stage / "a.txt").write_text("a")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_an_output_may_not_replace_an_input(tmp_path):
    """An output that is an input (by name, through a symlink or a hard link) or lies in
    an input folder is refused; other outputs, and missing or None paths, pass."""
    shot = tmp_path / "shot.png"
    shot.write_bytes(b"x")
    scene = tmp_path / "scene"
    scene.mkdir()
    (tmp_path / "link.png").symlink_to(shot)
    os.link(shot, tmp_path / "hard.png")
    for out in (shot, tmp_path / "link.png", tmp_path / "hard.png", tmp_path / "." / "shot.png"):
        with pytest.raises(InputError, match="is also an input"):
            check_outputs_not_inputs([out], [shot])
    for out in (scene / "truth.json", scene / "new" / "r.json", scene):
        with pytest.raises(InputError, match="lies in the input folder"):
            check_outputs_not_inputs([out], input_folders=[scene])
    check_outputs_not_inputs([tmp_path / "det.json", None], [shot, None, tmp_path / "missing.npz"],
                             input_folders=[scene, tmp_path / "no_such_folder"])
    check_outputs_not_inputs([tmp_path / "scene_results.json"], input_folders=[scene])  # a sibling, not inside
