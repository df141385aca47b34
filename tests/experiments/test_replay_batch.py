"""Batched replays (``replay_all(batch=)``): many windows side by side in one libsumo
simulation give the records of one simulation per run (``batch=1``).

Synthetic drives of tests/experiments/test_replay.py: arcs turning left and right, of other lengths and
world frames (each window its own replay net), a maneuver without a leader (its window fails
in preparation; the others go on), and the ``recorded`` pseudo-planner (kinematic: it stays on
``run_scenario``) beside the learned and analytic planners.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from fixtures_data import arc_drive

from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.experiments.task_engine import even_units

pytest.importorskip("libsumo")

POLICIES = ["analytic", "bc", "idm", "recorded"]
RTOL = 1e-9


def _maneuvers() -> pd.DataFrame:
    return pd.concat([
        arc_drive(21.0).assign(maneuver_id="a#0"),
        arc_drive(12.0, heading0=-2.0, origin=(6.0e5, 4.9e6)).assign(maneuver_id="b#0"),
        arc_drive(11.0, heading0=1.2).assign(maneuver_id="nolead#0", lead_x=np.nan),
    ], ignore_index=True)


def _same(a, b, where: str = "") -> None:
    """Equal records: floats to RTOL relative, everything else exactly."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float) and not (math.isnan(a) or math.isnan(b)):
        assert a == pytest.approx(b, rel=RTOL, abs=1e-12), where
    else:
        assert a == b, where


@pytest.mark.sumo
def test_batched_windows_give_the_records_of_one_simulation_per_run(tmp_path):
    maneuvers = _maneuvers()
    wins = ra.windows(maneuvers, "sliding", duration_s=10.0, stride_s=5.0)
    assert [(w.maneuver_id, w.start_s) for w in wins] == [
        ("a#0", 0.0), ("a#0", 5.0), ("a#0", 10.0), ("b#0", 0.0), ("nolead#0", 0.0)]
    assert [len(u) for u in even_units(wins, 8)] == [5]  # all five in one simulation
    one = ra.replay_all(maneuvers, wins, POLICIES, tmp_path / "one", workers=1, batch=1,
                        progress=False)
    many = ra.replay_all(maneuvers, wins, POLICIES, tmp_path / "many", workers=1, batch=8,
                         progress=False)
    assert [r["status"] for r in one] == ["ok"] * 4 + ["failed"]
    assert "without a leader" in one[-1]["error"]
    assert [m["policy"] for m in one[0]["metrics"]] == POLICIES
    assert all(m["end_reason"] == "timeout" for r in one[:4] for m in r["metrics"])
    _same(many, one)
    # one file per window, as without batches: a resumed batch reruns only what is missing
    files = sorted((tmp_path / "many" / "tasks").iterdir())
    assert len(files) == len(wins)
    stamps = {p.name: p.stat().st_mtime_ns for p in files}
    files[1].unlink()
    again = ra.replay_all(maneuvers, wins, POLICIES, tmp_path / "many", workers=1, batch=8,
                          progress=False)
    _same(again, one)
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "many" / "tasks").iterdir()
            if p.name != files[1].name} == {k: v for k, v in stamps.items()
                                            if k != files[1].name}
    assert json.loads(files[1].read_text())["task_id"] == wins[1].task_id


def test_even_units_are_even_and_feed_every_worker():
    wins = list(range(140))
    assert [len(u) for u in even_units(wins, 64, 2)] == [35] * 4
    assert [len(u) for u in even_units(wins, 64, 1)] == [47, 47, 46]
    assert [len(u) for u in even_units(wins[:5], 64, 2)] == [3, 2]
    assert even_units(wins[:3], 1, 2) == [(0,), (1,), (2,)]
    assert [w for u in even_units(wins, 16, 2) for w in u] == wins
    assert even_units([], 8, 2) == []
    with pytest.raises(ValueError, match="batch size"):
        even_units(wins, 0)
