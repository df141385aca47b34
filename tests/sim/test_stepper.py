"""The closed loop as a stepper (sim/stepper.py): reset/step from outside gives run_batch's
answers, external plans give the policies' answers, a seed gives the same episode, and a
scenario that ends stops while the others go on.

run_batch is itself a driver of the stepper, so in one process the two must agree bit for bit
(tests/sim/test_batch.py holds run_batch to run_scenario, tests/sim/test_golden.py run_scenario to its
references); here the logs are compared exactly.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from bad_policies import DriftLeft, blind_cruise
from fixtures_golden import GOLDEN_COLUMNS, compare_with_reference

from safeil_sumo import api
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.roads.catalogue import resolve_net
from safeil_sumo.roads.road import load_road
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim.batch import run_batch
from safeil_sumo.sim.leaders import constant, piecewise
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.recorded_ego import RecordedPath
from safeil_sumo.sim.stepper import ClosedLoop

# every test here runs SUMO (tests/conftest.py: the sumo marker)
pytestmark = pytest.mark.sumo

pytest.importorskip("libsumo")

WALL_KEYS = ("wall_time_s", "steps_per_s")
PLAN_EVERY = 10  # physics steps per decision step at LoopConfig's defaults (10 Hz, 0.01 s)
# the logged features of a decision: planner features 0-5 (lane lines), 7, 8 (the radar's)
LOGGED_FEATURES = ["c0l", "c1l", "c2l", "c0r", "c1r", "c2r", "v_lead_sensed", "d_lead_sensed"]


@pytest.fixture(scope="module")
def road():
    return load_road(resolve_net("curved500"))


def _noisy(road, name="noisy"):
    """Every sensor noise on, a braking and re-accelerating leader."""
    sc = safety_scenario(road, 3, master_seed=7)
    return replace(
        sc, name=name, max_time_s=8.0, ego_lateral_offset_m=0.3, ego_heading_offset_rad=0.01,
        leader=piecewise([0.0, 2.0, 4.0, 6.0], [28.0, 28.0, 22.0, 30.0]),
        sensors=replace(sc.sensors, radar_noise_m=0.3, radar_speed_noise_mps=0.2,
                        lane_noise_c0_m=0.02, lane_noise_c1=0.002, quantization_m=0.05))


def _mixed(road):
    """Every way to end, at different steps: completed, off road, collision, timeouts."""
    analytic = AnalyticPlanner()
    return [
        (replace(safety_scenario(road, 0), name="clean"), analytic),
        (Scenario("drift", road, constant(30.0), 30.0, 50.0, seed=1), DriftLeft()),
        (Scenario("crash", road, constant(10.0), 30.0, 20.0, seed=2), blind_cruise()),
        (_noisy(road), analytic),
        (Scenario("free", road, None, 25.0, 50.0, seed=4, max_time_s=4.0), AnalyticPlanner()),
    ]


def _drive(sim: ClosedLoop, scenarios, pols, plan=None, **reset_kw):
    """Step ``sim`` to the end; ``plan(obs) -> plans`` (None: the bound policies plan).
    Returns the rollouts and, per step, (observation, events)."""
    obs = sim.reset(scenarios, pols, **reset_kw)
    trace = [(obs, None)]
    while obs.running.any():
        obs, events = sim.step(None if plan is None else plan(obs))
        trace.append((obs, events))
    with pytest.raises(RuntimeError, match="ended"):
        sim.step()
    return [sim.rollout(i) for i in range(len(scenarios))], trace


def _assert_identical(got, want, skip=()):
    for g, w in zip(got, want, strict=True):
        pd.testing.assert_frame_equal(g.log, w.log, check_exact=True)
        for key in set(w.summary) - set(WALL_KEYS) - set(skip):
            a, b = g.summary[key], w.summary[key]
            assert a == b or (pd.isna(a) and pd.isna(b)), (w.summary["scenario"], key, a, b)


def test_stepping_to_the_end_equals_run_batch(road):
    """reset/step/rollout from outside give run_batch's logs and summaries, and the
    observations and events agree with the logs: each decision's features are the ones
    logged for its steps, each step's flags are its rows', each end is where the log ends."""
    cases = _mixed(road)
    scenarios, pols = [sc for sc, _ in cases], [p for _, p in cases]
    loop = LoopConfig(max_time_s=60.0)
    batch = run_batch(scenarios, pols, loop)
    assert [r.summary["end_reason"] for r in batch] == [
        "completed", "off_road", "collision", "timeout", "timeout"]
    with ClosedLoop(loop) as sim:
        stepped, trace = _drive(sim, scenarios, pols)
    _assert_identical(stepped, batch)

    logs = [r.log for r in stepped]
    for j, (obs, events) in enumerate(trace):
        k = j * PLAN_EVERY  # the physics step at which this observation's decision is made
        for i, log in enumerate(logs):
            if events is not None and events.sub_steps[i]:  # the rows of this step
                rows = log.iloc[k - PLAN_EVERY:k - PLAN_EVERY + events.sub_steps[i]]
                for flag in ("lane_departure", "ttc_flag", "collision"):
                    assert getattr(events, flag)[i] == rows[flag].any(), (i, j, flag)
                last = rows.iloc[-1]
                for col in ("t", "x", "y", "yaw", "v", "s", "d", "gap", "ttc", "leader_v",
                            "path_fraction", "collision"):
                    assert getattr(obs, col)[i] == last[col] or (
                        np.isnan(last[col]) and np.isnan(getattr(obs, col)[i])), (i, j, col)
            if obs.running[i]:  # the features the next plan gets are those logged for it
                np.testing.assert_array_equal(
                    obs.features[i, [0, 1, 2, 3, 4, 5, 7, 8]], log.iloc[k][LOGGED_FEATURES])
                if k:  # the ego's speed at the decision
                    assert obs.features[i, 6] == pytest.approx(log.iloc[k - 1]["v"])
        if events is not None:
            for i in np.flatnonzero(events.ended):  # it ended in this step, where its log ends
                assert events.end_reason[i] == stepped[i].summary["end_reason"]
                assert len(logs[i]) == k - PLAN_EVERY + events.sub_steps[i]
    steps_taken = sum(ev.sub_steps for _, ev in trace[1:])
    assert steps_taken.tolist() == [len(log) for log in logs]
    assert sum(ev.terminated for _, ev in trace[1:]).tolist() == [0, 1, 1, 0, 0]
    assert sum(ev.truncated for _, ev in trace[1:]).tolist() == [1, 0, 0, 1, 1]
    assert not trace[-1][0].running.any()


def test_external_plans_equal_the_policies_plans(road):
    """Plans fed to step() (made by the same planners from the observations, grouped as the
    stepper groups them) give the logs of letting the bound policies plan; the rows of ended
    scenarios are ignored (NaN here). Without bound policies, the plans' horizon is given."""
    cases = _mixed(road)
    cases[0] = (cases[0][0], planner_registry.load("safeil"))  # an MLP among the analytic planners
    scenarios, pols = [sc for sc, _ in cases], [p for _, p in cases]
    loop = LoopConfig(max_time_s=12.0)

    def plan(obs):
        plans = np.full((len(pols), 3, 2), np.nan)
        for policy in {id(p): p for p in pols}.values():
            rows = obs.running & np.array([p is policy for p in pols])
            if rows.any():
                plans[rows] = np.asarray(policy.plan(obs.features[rows])).reshape(-1, 3, 2)
        return plans

    with ClosedLoop(loop) as sim:
        own, _ = _drive(sim, scenarios, pols)
        given, _ = _drive(sim, scenarios, pols, plan)
        unbound, _ = _drive(sim, scenarios, None, lambda obs: plan(obs).reshape(-1, 6),
                            horizon_s=5.0)
        with pytest.raises(ValueError, match="without a policy"):
            sim.reset(scenarios, None)
        obs = sim.reset(scenarios, None, horizon_s=5.0)
        with pytest.raises(ValueError, match="needs its plans"):
            sim.step()
        with pytest.raises(ValueError, match=r"plans must be \(5, 3, 2\)"):
            sim.step(np.zeros((4, 3, 2)))
        # refused plans leave the run as it was
        obs, _ = sim.step(plan(obs))
        assert obs.running.all() and obs.t.tolist() == pytest.approx([0.1] * 5)
    _assert_identical(given, own)
    _assert_identical(unbound, own, skip=("policy",))
    assert {r.summary["policy"] for r in unbound} == {"external"}


def test_reset_with_a_seed_repeats_the_episode(road):
    """reset(seed=s) twice: identical observations and events at every step (noisy sensors:
    every draw is seeded); scenario i gets seed s + i; another seed draws other noise."""
    scenarios = [_noisy(road, "a"), replace(_noisy(road, "b"), initial_gap_m=30.0)]
    loop = LoopConfig(max_time_s=3.0)
    planner = AnalyticPlanner()

    def episode(seed):
        with ClosedLoop(loop) as sim:
            rollouts, trace = _drive(sim, scenarios, planner, seed=seed)
        return rollouts, trace

    first, again, other = episode(5), episode(5), episode(6)
    assert len(first[1]) == len(again[1]) == 31  # reset + 30 decision steps
    for (o1, e1), (o2, e2) in zip(first[1], again[1], strict=True):
        for field in o1.__dataclass_fields__:
            np.testing.assert_array_equal(getattr(o1, field), getattr(o2, field), err_msg=field)
        if e1 is not None:
            for field in e1.__dataclass_fields__:
                np.testing.assert_array_equal(getattr(e1, field), getattr(e2, field))
    _assert_identical(again[0], first[0])
    assert [r.summary["seed"] for r in first[0]] == [5, 6]
    assert not np.array_equal(first[1][0][0].features, other[1][0][0].features)


def test_a_scenario_that_ends_stops_while_the_others_go_on(road):
    """A collision a few decision steps in: events say which scenario ended and why, in the
    step it happened (part way through the step's physics steps); its observation is sensed
    at its end state, and afterwards it takes no step and its observation stays as it ended,
    while the other one drives on."""
    crash = Scenario("crash", road, constant(10.0), 30.0, 20.0, seed=0)
    clean = replace(safety_scenario(road, 1), max_time_s=5.0)
    with ClosedLoop(LoopConfig()) as sim:
        obs = sim.reset([crash, clean], blind_cruise())
        assert obs.running.tolist() == [True, True] and obs.t.tolist() == [0.0, 0.0]
        assert obs.gap[0] == pytest.approx(20.0, abs=0.5) and obs.ttc[0] == pytest.approx(1.0,
                                                                                         abs=0.1)
        steps = 0
        while obs.running[0]:
            obs, events = sim.step()
            steps += 1
            assert steps < 50
        assert events.ended.tolist() == [True, False]
        assert events.end_reason.tolist() == ["collision", ""]
        assert events.terminated.tolist() == [True, False] and not events.truncated.any()
        assert events.collision[0] and obs.collision[0] and obs.running.tolist() == [False, True]
        assert 0 < events.sub_steps[0] <= PLAN_EVERY and events.sub_steps[1] == PLAN_EVERY
        ended_at = obs
        # its final observation is sensed at its end state (the speed feature is its speed
        # there), the running one's at the next decision
        assert ended_at.features[0, 6] == ended_at.v[0]
        assert ended_at.features[1, 6] == ended_at.v[1]
        obs, events = sim.step()
        assert events.sub_steps.tolist() == [0, PLAN_EVERY] and not events.ended.any()
        assert events.end_reason.tolist() == ["collision", ""]
        for field in ("t", "x", "s", "gap", "features"):
            np.testing.assert_array_equal(getattr(obs, field)[0], getattr(ended_at, field)[0])
        assert obs.t[1] == pytest.approx(ended_at.t[1] + PLAN_EVERY * 0.01)
        while obs.running.any():
            obs, events = sim.step()
        assert sim.end_reasons == ["collision", "timeout"]
        crashed, drove = sim.rollout(0), sim.rollout(1)
    assert crashed.summary["end_reason"] == "collision"
    assert len(crashed.log) == round(crashed.log["t"].iloc[-1] / 0.01) < 200
    assert len(drove.log) == 500


class _FailingSumo:
    """The real SUMO API whose simulation step fails after ``steps`` steps."""

    def __init__(self, api, steps: int) -> None:
        self._api, self._left = api, steps
        self.vehicle, self.route = api.vehicle, api.route
        outer = self

        class Simulation:
            def step(self, *args):
                outer._left -= 1
                if outer._left < 0:
                    raise RuntimeError("simulated SUMO crash")
                return api.simulation.step(*args)

            def getCollidingVehiclesIDList(self):
                return api.simulation.getCollidingVehiclesIDList()

        self.simulation = Simulation()

    def close(self) -> None:
        self._api.close()


def test_an_error_ends_the_running_scenarios_and_bad_input_is_refused(road):
    """A SUMO failure in a step ends every running scenario with "error" (the ended keep
    their reasons), closes SUMO and is raised; run_batch turns it into rollouts. Bad input is
    refused before SUMO starts."""
    crash = Scenario("crash", road, constant(10.0), 30.0, 20.0, seed=0)
    clean = replace(safety_scenario(road, 1), max_time_s=5.0)

    def factory(args):
        return _FailingSumo(sumo_api.start(args), 300)

    sim = ClosedLoop(LoopConfig(), api_factory=factory)
    with pytest.raises(RuntimeError, match="no scenario is running"):
        sim.step()
    sim.reset([crash, clean], blind_cruise())
    with pytest.raises(RuntimeError, match="simulated SUMO crash"):
        while True:
            sim.step()
    assert sim.end_reasons == ["collision", "error"]
    assert sim.rollout(1).summary["error"] == "RuntimeError: simulated SUMO crash"
    assert len(sim.rollout(1).log) == 299
    with pytest.raises(RuntimeError, match="ended"):
        sim.step()
    rollouts = run_batch([crash, clean], blind_cruise(), api_factory=factory)
    assert [r.summary["end_reason"] for r in rollouts] == ["collision", "error"]

    with pytest.raises(ValueError, match="policies"):
        sim.reset([crash, clean], [blind_cruise()])
    with pytest.raises(ValueError, match="no scenarios"):
        sim.reset([], blind_cruise())
    # sumo-gui, SSM output and traffic name the original net and the vehicle "ego": N = 1
    for config in (LoopConfig(gui=True, backend="traci"), LoopConfig(ssm_file=Path("ssm.xml"))):
        with pytest.raises(ValueError, match="one by one"):
            ClosedLoop(config).reset([crash, clean], blind_cruise())
    traffic = api.scenario("n74", 0, 0, from_km=4.0, to_km=5.0, traffic="light")
    with pytest.raises(ValueError, match="traffic runs one scenario at a time"):
        sim.reset([traffic, traffic], blind_cruise())
    with pytest.raises(ValueError, match="unknown log column"):
        ClosedLoop(log_columns=("t", "speed"))


def _first(scenarios, policy):
    """Scenario 0's rollout, run from a reset of ``scenarios`` until it ends."""
    with ClosedLoop() as loop:
        loop.reset(scenarios, policy)
        while not loop.end_reasons[0]:
            loop.step()
        return loop.rollout(0)


def test_restart_runs_a_scenario_as_it_runs_alone(road):
    """A scenario restarted on an ended one's copy (a vector env's autoreset), while the other
    scenario runs on, gives the log it gives from a reset with that other one, bit for bit (the
    same arrays loop), and the log it gives alone (N = 1: the floats loop, libm's cos/sin
    against numpy's) within the golden tolerances (tests/sim/test_golden.py); a running scenario,
    another net, another kind of ego and a closed SUMO are refused."""
    analytic = AnalyticPlanner()
    short = replace(safety_scenario(road, 0), max_time_s=1.0)
    long_ = replace(safety_scenario(road, 1), max_time_s=4.0)
    again = replace(_noisy(road, "again"), max_time_s=2.0)
    with ClosedLoop() as loop:
        loop.reset([short, long_], analytic)
        with pytest.raises(ValueError, match="running"):
            loop.restart(1, again, analytic)
        while not loop.end_reasons[0]:
            obs, _ = loop.step()
        with pytest.raises(ValueError, match="all kinematic"):
            loop.restart(0, again, RecordedPath(np.array([0.0, 1.0]), np.array(
                [[0.0, 0.0], [30.0, 0.0]]), np.zeros(2), np.full(2, 30.0)))
        loop.restart(0, again, analytic)
        obs, events = loop.step()
        assert obs.running.all() and obs.t[0] == 0.0 and not events.ended.any()
        assert events.sub_steps[0] == 0 and events.sub_steps[1] == PLAN_EVERY
        while obs.running[0]:
            obs, _ = loop.step()
        got = loop.rollout(0)
        other = replace(again, road=load_road(resolve_net("straight")))
        while obs.running.any():
            obs, _ = loop.step()
        with pytest.raises(RuntimeError, match="call reset"):
            loop.restart(0, other, analytic)
    pd.testing.assert_frame_equal(got.log, _first([again, long_], analytic).log,
                                  check_exact=True)
    alone = _first([again], analytic)
    reference = {c: alone.log[c].to_numpy(dtype=np.float64) for c in GOLDEN_COLUMNS}
    reference |= {"rows": len(alone.log), "end_reason": alone.summary["end_reason"]}
    assert compare_with_reference(got.log, got.summary["end_reason"], reference) == []
    with ClosedLoop() as loop:
        loop.reset([short, long_], analytic)
        while not loop.end_reasons[0]:
            loop.step()
        with pytest.raises(ValueError, match="same net|stay on that net"):
            loop.restart(0, other, analytic)


def test_restart_when_the_others_end_during_the_step(road):
    """The other scenario ends part way through the step that starts a restarted one: the
    restarted one is inserted with a SUMO step of its own after it and runs on alone (its log
    still the one a reset gives it, bit for bit)."""
    analytic = AnalyticPlanner()
    short = replace(safety_scenario(road, 0), max_time_s=1.2)
    long_ = replace(safety_scenario(road, 1), max_time_s=1.25)  # ends 5 steps into a decision
    again = replace(_noisy(road, "again"), max_time_s=1.0)
    with ClosedLoop() as loop:
        loop.reset([short, long_], analytic)
        while not loop.end_reasons[0]:
            loop.step()
        loop.restart(0, again, analytic)
        obs, events = loop.step()
        assert obs.running.tolist() == [True, False] and obs.t[0] == 0.0
        assert events.sub_steps.tolist() == [0, 5] and events.end_reason.tolist() == ["",
                                                                                      "timeout"]
        while obs.running.any():
            obs, _ = loop.step()
        got = loop.rollout(0).log
    pd.testing.assert_frame_equal(got, _first([again, long_], analytic).log, check_exact=True)


def test_controls_drive_the_plant_without_a_plan(road):
    """step(controls=...) holds acceleration and steering commands over the period: logged as
    given, the ego brakes; bad shapes and NaN are refused, plans and controls together too."""
    sc = replace(safety_scenario(road, 0), max_time_s=3.0)
    with ClosedLoop() as loop:
        obs = loop.reset([sc], horizon_s=3.0)
        v0 = obs.v[0]
        for _ in range(10):
            obs, _ = loop.step(controls=np.array([[-3.0, 0.0]]))
        log = loop.rollout(0).log
        assert (log["accel_cmd"] == -3.0).all() and (log["steer_cmd"] == 0.0).all()
        assert obs.v[0] < v0 - 2.0
        for bad in (np.zeros((1, 3)), np.array([[np.nan, 0.0]])):
            with pytest.raises(ValueError, match="controls"):
                loop.step(controls=bad)
        with pytest.raises(ValueError, match="not both"):
            loop.step(np.zeros((1, 3, 2)), controls=np.zeros((1, 2)))


class _SelfDriven:
    """A self-driven ego (the synthetic-drive recorder's kind): never started here."""

    name, horizon = "self", 3.0

    def pose_at(self, t):
        return 0.0, 0.0, 0.0, 0.0

    def enter(self, api, ego_id):
        raise AssertionError("refused before SUMO starts")

    def drive(self, api, t):
        raise AssertionError("refused before SUMO starts")

    def plan(self, features):
        raise AssertionError("never planned")


def test_a_self_driven_ego_runs_alone(road):
    """A self-driven ego (``enter``, ``drive``: it enters SUMO itself) runs alone: with another
    scenario or a scripted leader of the loop's it is refused before SUMO starts."""
    alone = Scenario("alone", road, None, 25.0, seed=0)
    led = Scenario("led", road, constant(30.0), 30.0, 50.0, seed=0)
    for scenarios in ([alone, alone], [led]):
        with pytest.raises(ValueError, match="runs alone"):
            ClosedLoop().reset(scenarios, [_SelfDriven()] * len(scenarios))
