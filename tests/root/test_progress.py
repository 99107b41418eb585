"""Progress off a terminal: silent, or one line as each stage starts; nothing with quiet."""

from __future__ import annotations

from prism3d.progress import make_progress, null_progress


def test_stage_lines_off_a_terminal(capsys) -> None:
    p = make_progress("survey", stage_lines=True)  # pytest's stderr is not a terminal
    for k in range(3):
        p(k, 3, f"poses: step {k}")
    p(0, 12, "dense pairs: frames 0-1")
    p(5, 12, "dense pairs: frames 4-6")
    p(0, 1, "fusion: 11 depth maps")
    p(1, 1, "no stage in this label")
    assert capsys.readouterr().err.splitlines() == [
        "survey: poses (3 steps)...", "survey: dense pairs (12 steps)...", "survey: fusion (1 step)..."]


def test_quiet_and_plain_progress_say_nothing(capsys) -> None:
    assert make_progress("survey", quiet=True, stage_lines=True) is null_progress
    assert make_progress("survey") is null_progress  # not a terminal, no stage lines asked
    make_progress("survey", stage_lines=True)(0, 1, "poses: x")
    assert capsys.readouterr().err.count("\n") == 1
