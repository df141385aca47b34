"""The runner over a fake SUMO API: the seam is real (no libsumo needed for the loop's logic)."""

import math

import numpy as np
import pytest
from fixtures_sumo import FakeSumoFactory

from safeil_sumo.core.geometry import yaw_to_sumo_angle
from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.sim.leaders import constant
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.sumo_setup import EGO_ID, LEADER_ID


def run_fake(road, factory: FakeSumoFactory, placement="xy"):

    sc = Scenario("fake", road, constant(28.0), 30.0, 50.0, seed=3)
    # the fake moves the ego where moveToXY puts it (it has no lane coordinates for moveTo)
    rollout = run_scenario(sc, AnalyticPlanner(),
                           LoopConfig(max_time_s=60.0, ego_placement=placement),
                           api_factory=factory)
    return rollout, factory.made[0]


def test_runner_drives_the_seam(straight_road, fake_sumo):
    rollout, fake = run_fake(straight_road, fake_sumo)
    s = rollout.summary
    assert s["end_reason"] == "completed" and s["completed"]
    assert fake.closed
    # SUMO's own control switched off on both vehicles
    for vid in (EGO_ID, LEADER_ID):
        assert ("setSpeedMode", vid, 0) in fake.calls
        assert ("setLaneChangeMode", vid, 0) in fake.calls
    moves = [c for c in fake.calls if c[0] == "moveToXY"]
    # one moveToXY per step (plus the initial placement), keepRoute=2, SUMO navigation angle
    assert len(moves) == len(rollout.log) + 1
    last = rollout.log.iloc[-1]
    _, vid, x, y, angle, keep = moves[-1]
    assert (vid, keep) == (EGO_ID, 2)
    assert (x, y) == (pytest.approx(last["front_x"]), pytest.approx(last["front_y"]))
    assert angle == pytest.approx(yaw_to_sumo_angle(last["yaw"]))
    # the analytic planner settles on the leader's speed at its time gap
    assert last["v"] == pytest.approx(28.0, abs=0.3)
    assert last["gap"] == pytest.approx(5.0 + 1.5 * 28.0, abs=2.0)
    assert "--collision.action" in fake.args and "--time-to-teleport" in fake.args


def test_sumo_failure_mid_run_keeps_the_log(straight_road, fake_sumo):
    fake_sumo.kwargs["fail_at_step"] = 200
    rollout, fake = run_fake(straight_road, fake_sumo)
    assert rollout.summary["end_reason"] == "error"
    assert "simulated SUMO crash" in rollout.summary["error"]
    assert len(rollout.log) == 199 and fake.closed
    assert math.isfinite(rollout.log["x"].iloc[-1]) and np.all(np.isfinite(rollout.log["t"]))


def test_an_error_before_the_loop_ends_the_run_with_its_reason(straight_road, fake_sumo):
    """A seam without moveTo under the lane placement: the run ends with the error, SUMO
    closed (not a crash of the runner)."""
    rollout, fake = run_fake(straight_road, fake_sumo, placement="lane")
    assert rollout.summary["end_reason"] == "error"
    assert "moveTo" in rollout.summary["error"] and fake.closed
    assert rollout.summary["leaders_met"] == 0


def test_lane_placeable_on_floats_and_arrays():
    """Inside the lane (``|d| <= half width``, the boundary included, NaN outside) and the step
    short of the route's end: a Python bool at N = 1, the same flags on arrays."""
    from safeil_sumo.sim.sumo_setup import lane_placeable

    half, end, advance = 1.75, 100.0, 1.0
    cases = [(0.0, 50.0, True), (1.75, 50.0, True), (-1.75, 50.0, True), (1.76, 50.0, False),
             (-1.76, 50.0, False), (math.nan, 50.0, False), (0.0, 98.9, True),
             (0.0, 99.0, False)]
    for d, s, expected in cases:
        assert lane_placeable(d, s, advance, half, end) is expected, (d, s)
    d, s, expected = (np.array(column) for column in zip(*cases, strict=True))
    flags = lane_placeable(d, s, np.full(len(d), advance), np.full(len(d), half), end)
    assert flags.tolist() == expected.tolist()
