"""A driver's style in a closed-loop task: the standstill distance and a style that changes
during a run (``PlannerRef.style_changes``, ``ScheduledStyle``), in task ids, batches, the
Python API and the loop itself (real libsumo for the closed loop)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from safeil_sumo import api
from safeil_sumo.experiments import sweep_executor as se
from safeil_sumo.planners import idm
from safeil_sumo.planners import registry as reg
from safeil_sumo.planners.registry import PlannerRef, PolicyError, ScheduledStyle
from safeil_sumo.planners.safety_filter import SafetyFiltered
from safeil_sumo.scenarios.spec import ScenarioSpec, Task


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


# ------------------------------------------------------------------ the schedule as data


def test_a_schedule_round_trips_through_json_and_is_part_of_the_task_id():
    changes = ((20.0, 2.5, 8.0), (40.0, 1.2, None))
    task = Task(ScenarioSpec(net="straight"), PlannerRef("idm", time_gap_s=1.0,
                                                         style_changes=changes))
    data = task.to_json()
    assert data["style_changes"] == [[20.0, 2.5, 8.0], [40.0, 1.2, None]]
    back = Task.from_json(json.loads(json.dumps(data)))
    assert back == task and se.task_id(back) == se.task_id(task)
    # pairs (no standstill distance) and ints are the same schedule, normalised
    assert PlannerRef("idm", style_changes=[[20, 2.5, 8], (40, 1.2)]).style_changes == changes
    other = Task(ScenarioSpec(net="straight"), PlannerRef("idm", time_gap_s=1.0,
                                                          style_changes=changes[:1]))
    plain = Task(ScenarioSpec(net="straight"), PlannerRef("idm", time_gap_s=1.0))
    assert len({se.task_id(t) for t in (task, other, plain)}) == 3
    assert len({se.batch_key(t) for t in (task, other, plain)}) == 3  # never one batch
    assert se.spec_fields(task)["style_changes"] == '[[20.0, 2.5, 8.0], [40.0, 1.2, null]]'


def test_a_task_without_a_schedule_keeps_its_id():
    """Ids computed before style changes existed (commit 011dff3): cached records still match."""
    assert "style_changes" not in Task().to_json()
    assert se.task_id(Task()) == "curved500_analytic-00000-529d6846b2bc"
    assert se.task_id(Task(ScenarioSpec(net="straight", index=3), PlannerRef(
        "analytic", True))) == "straight_analytic_f-00003-78f4383cff2d"


@pytest.mark.parametrize(("changes", "match"), [
    ([(10.0, 2.0), (5.0, 1.0)], "increasing time"),
    ([(10.0, 2.0), (10.0, 1.0)], "increasing time"),
    ([(-1.0, 2.0)], ">= 0 s"),
    ([(float("nan"), 2.0)], ">= 0 s"),
    ([(1.0, 0.0)], r"\(0, 10\] s"),
    ([(1.0, 12.0)], r"\(0, 10\] s"),
    ([(1.0, 2.0, float("inf"))], "finite"),
    ([(1.0,)], "t_s, time_gap_s"),
    ([(1.0, 2.0, 3.0, 4.0)], "t_s, time_gap_s"),
    ([("a", 2.0)], "numbers"),
    ("10 2", "sequence"),
    (5.0, "sequence"),
])
def test_a_malformed_schedule_is_refused_in_one_line(changes, match):
    with pytest.raises(ValueError, match=match) as err:
        PlannerRef("idm", style_changes=changes)
    assert "\n" not in str(err.value)


def test_only_a_planner_with_a_time_gap_setting_takes_a_schedule(tmp_path):
    """Refused at load, before any simulation (these tests are not marked sumo: a SUMO start
    would fail them), also by the Python API and for a change the planner refuses."""
    for name in ("analytic", "safeil_paper", "bc"):
        with pytest.raises(PolicyError, match="no time-gap setting"):
            PlannerRef(name, style_changes=[(5.0, 2.0)]).load()
    with pytest.raises(PolicyError, match="no time-gap setting"):
        api.run("straight", "analytic", scenarios=1, style_changes=[(5.0, 2.0)])
    with pytest.raises(PolicyError, match="no time-gap setting"):
        api.run("straight", reg.load("analytic"), scenarios=1, style_changes=[(5.0, 2.0)])
    with pytest.raises(PolicyError, match="no time-gap setting"):
        api.sweep("analytic", tmp_path / "sweep", scenarios=1, nets=("straight",),
                  style_changes=[(5.0, 2.0)])
    assert not (tmp_path / "sweep").exists()
    # the IDM's s0 must stay inside its calibration bounds: refused at load, not mid-run
    with pytest.raises(PolicyError, match="standstill distance must be in"):
        PlannerRef("idm", style_changes=[(5.0, 2.0, 0.5), (9.0, 2.0, 20.0)]).load()
    with pytest.raises(ValueError, match="needs a time gap"):
        api.run("straight", "idm", scenarios=1, standstill_m=2.0)


# ------------------------------------------------------------------ the schedule in time


def test_the_idm_takes_each_change_at_the_first_decision_at_or_after_its_time():
    base = reg.load("idm")
    t0, s0 = base.params.time_gap_s, base.params.s0_m
    planner = PlannerRef("idm", style_changes=[(1.0, 2.0, 3.0), (2.0, 1.2, None)]).load()
    assert isinstance(planner, ScheduledStyle) and planner.name == "idm"

    def style():
        return planner.planner.params.time_gap_s, planner.planner.params.s0_m

    planner.at_time(0.0)
    assert style() == (t0, s0)
    planner.at_time(0.9)
    assert style() == (t0, s0)
    planner.at_time(1.0 - 1e-12)  # 100 steps of 0.01 s may land an ulp short of 1.0
    assert style() == (2.0, 3.0)
    planner.at_time(2.5)
    assert style() == (1.2, 3.0)  # None: the IDM keeps its s0, as with_time_gap(T) does
    features = np.array([0, 0, 0, 0, 0, 0, 20.0, 18.0, 30.0])
    want = idm.IDMPlanner(idm.IDMParams(**{**vars(base.params), "time_gap_s": 1.2,
                                           "s0_m": 3.0})).plan(features)
    np.testing.assert_array_equal(planner.plan(features), want)
    filtered = PlannerRef("idm", True, style_changes=planner.changes).load()
    filtered.at_time(2.0)  # the filter plans with the IDM of the new setting
    np.testing.assert_array_equal(filtered.plan(features), SafetyFiltered(idm.IDMPlanner(
        idm.IDMParams(**{**vars(base.params), "time_gap_s": 1.2, "s0_m": 3.0}))).plan(features))
    planner.at_time(0.0)  # run again: from the style it was built with
    assert style() == (t0, s0)
    planner.at_time(5.0)  # both changes due at one decision: the last one holds
    assert style() == (1.2, 3.0)


def test_a_checkpoints_style_follows_the_schedule_and_its_filter_counts(tmp_path):
    ref = PlannerRef("safeil", safety_filter=True, time_gap_s=1.0, standstill_m=2.0,
                     style_changes=[(10.0, 2.5, 2.0), (20.0, 1.8, None)])
    planner = ref.load()
    assert planner.name == "safeil+filter"
    features = np.array([0.5, 0.0, 0.0, -3.0, 0.0, 0.0, 20.0, 20.0, 40.0])
    reference = reg.load("safeil")  # the same checkpoint, set by hand
    for t, style in ((0.0, (1.0, 2.0)), (10.0, (2.5, 2.0)), (20.0, (1.8, None))):
        planner.at_time(t)
        reg.with_time_gap(reference, *style)
        assert planner.planner.style == reference.style
        np.testing.assert_array_equal(planner.plan(features),
                                      SafetyFiltered(reference).plan(features))
    assert planner.calls == 3 and planner.interventions <= 3
    planner.at_time(0.0)
    assert planner.planner.style == {"time_gap_s": 1.0, "standstill_m": 2.0}


def test_a_stateful_style_is_never_shared_between_tasks():
    """A batch shares a stateless planner (one cache per process); a task with style changes
    gets its own, and moving its time moves no one else's style."""
    plain = PlannerRef("safeil", time_gap_s=1.0, standstill_m=2.0)
    sched = PlannerRef("safeil", time_gap_s=1.0, standstill_m=2.0,
                       style_changes=[(10.0, 2.5, 2.0)])
    se._SHARED_POLICIES.clear()
    try:
        shared = se._load_policy(plain, shared=True)
        a = se._load_policy(sched, shared=True)
        b = se._load_policy(sched, shared=True)
        assert isinstance(a, ScheduledStyle) and isinstance(b, ScheduledStyle)
        assert len({id(shared), id(a.planner), id(b.planner)}) == 3
        a.at_time(10.0)
        assert a.planner.style == {"time_gap_s": 2.5, "standstill_m": 2.0}
        assert b.planner.style == shared.style == {"time_gap_s": 1.0, "standstill_m": 2.0}
        assert se._load_policy(plain, shared=True) is shared
    finally:
        se._SHARED_POLICIES.clear()


class _Recorder:
    """A planner that records what the loop asks of it, in order."""

    def __init__(self, planner):
        self.planner, self.name, self.horizon = planner, planner.name, planner.horizon
        self.calls: list[tuple[str, float]] = []

    def at_time(self, t_s: float) -> None:
        self.calls.append(("at_time", t_s))

    def plan(self, features):
        self.calls.append(("plan", float(np.asarray(features)[..., 6].flat[0])))
        return self.planner.plan(features)


def test_the_loop_tells_the_planner_each_decisions_time_before_it_plans(straight_road,
                                                                         fake_sumo):
    from safeil_sumo.sim.leaders import constant
    from safeil_sumo.sim.loop_types import LoopConfig, Scenario
    from safeil_sumo.sim.runner import run_scenario

    rec = _Recorder(reg.load("analytic"))
    sc = Scenario("fake", straight_road, constant(28.0), 30.0, 50.0, seed=3)
    run_scenario(sc, rec, LoopConfig(max_time_s=1.0, ego_placement="xy"), api_factory=fake_sumo)
    kinds = [k for k, _ in rec.calls]
    assert kinds == ["at_time", "plan"] * (len(kinds) // 2) and len(kinds) == 20
    times = [t for k, t in rec.calls if k == "at_time"]
    np.testing.assert_allclose(times, 0.1 * np.arange(10), rtol=0, atol=1e-9)


def test_scenarios_at_different_times_cannot_share_a_changing_planner():
    from safeil_sumo.sim.stepper import _decision_time
    from safeil_sumo.sim.xp import ARRAYS, FLOATS

    assert _decision_time(np.array([3.0, 1.0, 3.0]), np.array([0, 2]), ARRAYS) == 3.0
    assert _decision_time(2.5, slice(None), FLOATS) == 2.5
    with pytest.raises(ValueError, match="give each scenario its own"):
        _decision_time(np.array([3.0, 1.0]), slice(None), ARRAYS)


# ------------------------------------------------------------------ in SUMO

SPEED_MPS = 10.0  # [m/s] the leader's constant speed and the ego's start
S0_M = 2.0  # [m] both styles' standstill distance
CHANGE_S = 50.0  # [s]
END_S = 110.0  # [s] the straight track's 1.2 km test path lasts ~117 s at 10 m/s
STRAIGHT = {"leader_speed_range_mps": (SPEED_MPS, SPEED_MPS), "ego_speed_mps": SPEED_MPS}


def _settled_time_gap(log, t0: float, t1: float) -> float:
    """The mean time gap [s] (bumper gap / ego speed) over ``t0 <= t < t1`` [s]."""
    m = (log["t"] >= t0) & (log["t"] < t1)
    return float((log["gap"][m] / log["v"][m]).mean())


@pytest.mark.sumo
@pytest.mark.parametrize(("policy", "first", "second"), [
    ("safeil", 1.0, 2.5),  # the checkpoint drops back
    ("idm", 2.5, 1.0),  # the IDM closes up
])
def test_a_style_that_changes_mid_run_settles_at_each_styles_gap(policy, first, second):
    """Real libsumo, straight track, a leader at a constant 10 m/s, the ego starting on the
    first style's line: the steady time gap is (s0 + T v) / v = T + s0 / v, so 1.0 s and
    2.5 s with s0 = 2 m are 1.2 s and 2.7 s. Settled (the mean over the 10 s before the
    change at 50 s, and over the run's last 10 s) at each within 0.3 s, moved by > 1 s."""
    pytest.importorskip("libsumo")
    result = api.run("straight", policy, scenarios=1, time_gap_s=first, standstill_m=S0_M,
                     style_changes=[(CHANGE_S, second, S0_M)], max_time_s=END_S,
                     initial_gap_m=S0_M + first * SPEED_MPS, **STRAIGHT)
    log = result.log
    assert result.summary["end_reason"].iloc[0] == "timeout" and not result.summary[
        "flag"].iloc[0]
    before = _settled_time_gap(log, CHANGE_S - 10.0, CHANGE_S)
    after = _settled_time_gap(log, END_S - 10.0, END_S)
    print(f"{policy}: settled time gap {before:.3f} s before, {after:.3f} s after")
    assert before == pytest.approx(first + S0_M / SPEED_MPS, abs=0.3)
    assert after == pytest.approx(second + S0_M / SPEED_MPS, abs=0.3)
    assert (after - before) * np.sign(second - first) > 1.0
    if policy == "safeil":  # the change comes at the decision at 50 s, not one before
        plain = api.run("straight", policy, scenarios=1, time_gap_s=first,
                        standstill_m=S0_M, max_time_s=CHANGE_S + 0.15,
                        initial_gap_m=S0_M + first * SPEED_MPS, **STRAIGHT).log
        cp = ["cp1_x", "cp2_x", "cp3_x"]
        early = plain["plan_t"] < CHANGE_S - 1e-6
        np.testing.assert_array_equal(log.loc[:len(plain) - 1][early][cp], plain[early][cp])
        at = (plain["plan_t"] - CHANGE_S).abs() < 1e-6
        assert at.any() and (log.loc[:len(plain) - 1][at]["cp3_x"] != plain[at]["cp3_x"]).all()


@pytest.mark.sumo
def test_a_batched_sweep_changes_every_tasks_style(tmp_path):
    """Real libsumo, ``api.sweep`` with two tasks in one simulation (batch 2): each task's own
    scheduled planner closes up from 2.7 s (2.5 s + 2 m / 10 m/s) to near 1.2 s after the change
    at 30 s; the two identical tasks give the same records (to round-off)."""
    pytest.importorskip("libsumo")
    summary = api.sweep("safeil", tmp_path, scenarios=2, nets=("straight",), batch=2,
                        time_gap_s=2.5, standstill_m=S0_M, style_changes=[(30.0, 1.0, S0_M)],
                        initial_gap_m=S0_M + 2.5 * SPEED_MPS, max_time_s=70.0, **STRAIGHT)
    assert list(summary["status"]) == ["ok", "ok"]
    assert list(summary["style_changes"]) == ["[[30.0, 1.0, 2.0]]"] * 2
    gaps = summary["resp_min_time_gap_s"]
    print(f"batched: min time gap {list(gaps)} s")
    # (the copies of the track lie 1 km apart in x: equal to round-off)
    assert gaps.iloc[0] == pytest.approx(gaps.iloc[1], abs=1e-9) and gaps.iloc[0] < 1.5
