"""The concurrency and kill probe (``benchmarks/probe_concurrency.py``, issue 40) on its
smallest inputs: one race per command and a survey killed at two points with SIGKILL
and SIGTERM. Slow (two to three minutes on two cores: some twenty CLI runs); the full
measurement is the script itself.

What it holds the commands to: a survey, a stitch or a render job raced against itself
refuses one writer with one line and gives the same output as a run alone; a killed
survey leaves no process behind, SIGTERM exits 143 with one line, and the next run (with
or without ``--resume``) ends with the same products and nothing beside them.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _probe():
    spec = importlib.util.spec_from_file_location("probe_concurrency", ROOT / "benchmarks" / "probe_concurrency.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_races_and_kills_on_the_smallest_inputs(tmp_path: Path) -> None:
    probe = _probe()
    inp = probe.build_inputs(tmp_path, small=True)
    res = probe.probe_concurrency(inp, tmp_path, 1, say=lambda _: None)
    assert set(res) == {"survey", "stitch", "db render"}
    for name, entry in res.items():
        assert entry["reference_rc"] == [0, 0], (name, entry["reference_err"])
        assert entry["alone_twice"]["different"] == {}, name
        (race,) = entry["races"]
        assert race.same_content and not race.leftovers, (name, race.problems)
        assert race.outcome == "one refused", (name, race.problems)
    kills = probe.probe_kills(inp, tmp_path, 2, say=lambda _: None)
    assert kills["reference_rc"] == 0
    assert [(k.point, k.signal) for k in kills["kills"]] == [(0, "SIGKILL"), (0, "SIGTERM"), (1, "SIGKILL"),
                                                             (1, "SIGTERM")]
    for k in kills["kills"]:
        assert not k.problems, (k.point, k.signal, k.stage, k.problems)
        assert k.same_content and not k.leftovers and not k.orphans
    interrupted = [k for k in kills["kills"] if k.stage != "finished before the kill"]  # a busy machine: rarely all
    assert {k.signal for k in interrupted} == {"SIGKILL", "SIGTERM"}
    assert all(k.rerun_rc == 0 for k in interrupted)
    assert "| SIGTERM |" in "\n".join(probe.report_kills(kills, 2))
