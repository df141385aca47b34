"""A driver's style in a closed-loop task: the standstill distance and a style that changes
during a run (``PlannerRef.style_changes``), in task ids, batches and the loop itself."""

from __future__ import annotations

import pytest

from safeil_sumo.experiments import sweep_executor as se
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import Task


def test_a_standstill_distance_is_part_of_the_task():
    """Two tasks that differ only in s0 have different ids and never share a batch's planner."""
    with_s0 = Task(planner=PlannerRef("idm", time_gap_s=2.0, standstill_m=3.0))
    without = Task(planner=PlannerRef("idm", time_gap_s=2.0))
    assert with_s0.to_json()["standstill_m"] == 3.0
    assert "standstill_m" not in without.to_json()
    assert se.task_id(with_s0) != se.task_id(without)
    assert Task.from_json(with_s0.to_json()) == with_s0
    assert Task.of(policy="idm", time_gap_s=2.0, standstill_m=3.0) == with_s0
    se._SHARED_POLICIES.clear()
    try:
        a = se._load_policy(with_s0.planner, shared=True)
        b = se._load_policy(without.planner, shared=True)
    finally:
        se._SHARED_POLICIES.clear()
    assert a.params.s0_m == 3.0 and b.params.s0_m != 3.0
