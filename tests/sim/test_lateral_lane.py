"""``LoopConfig.lateral = "lane"`` (``replay --lateral lane``): the instrument mode for
longitudinal-only evaluation. After every physics step the ego is put on its lane centre at the
station its own motion reached; the planner, PID and plant still drive the longitudinal part.

Real libsumo runs on a small generated track: 120 m straight, then a left bend of R = 50 m (the
ZalaZone handling course's), driven at 15 m/s behind a braking leader by a planner whose lateral
plan goes straight ahead (the analytic planner's longitudinal plan, y = 0): it leaves its lane
in the bend; with the mode on it stays on the lane, and its longitudinal log equals the normal
run's wherever the normal run is still on its lane.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.roads.network import build_network
from safeil_sumo.roads.road import load_road
from safeil_sumo.roads.track import TrackSpec
from safeil_sumo.sim.batch import run_batch
from safeil_sumo.sim.leaders import piecewise
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.stepper import on_lane_pose
from safeil_sumo.sim.xp import ARRAYS

STRAIGHT_M = 120.0  # [m] of the run-in the ego drives before the bend


class StraightAhead:
    """The analytic planner's longitudinal plan with a lateral plan straight ahead (y = 0 in
    the ego frame): it cannot follow a bend."""

    name = "straight_ahead"

    def __init__(self) -> None:
        self.inner = AnalyticPlanner()
        self.horizon = self.inner.horizon

    def plan(self, features):
        cp = np.array(self.inner.plan(features), dtype=float)
        cp[..., 1] = 0.0
        return cp


@pytest.fixture(scope="module")
def bend(tmp_path_factory):
    spec = TrackSpec(name="bend50", radius_m=50.0, arc_length_m=120.0, run_in_m=200.0,
                     run_out_m=300.0)
    road = load_road(build_network(spec, tmp_path_factory.mktemp("bend50")))
    # the test path starts on the run-in, STRAIGHT_M before the bend
    return replace(road, path_start_s=road.path_start_s - STRAIGHT_M)


def _scenario(road) -> Scenario:
    leader = piecewise([0.0, 3.0, 6.0, 20.0], [15.0, 15.0, 11.0, 11.0])
    return Scenario("bend50", road, leader, ego_speed_mps=15.0, initial_gap_m=30.0,
                    max_time_s=14.0)


def test_on_lane_pose_hand_computed():
    # lane heading +x, front bumper 0.5 m left of it at x = 10: onto (10, 0), heading 0
    x, y, yaw = on_lane_pose(10.0, 0.5, 0.5, 0.0, 2.0)
    assert (x, y, yaw) == pytest.approx((8.0, 0.0, 0.0), abs=1e-12)
    # lane heading north (+y) through x = 0; front bumper 0.3 m to its right (d = -0.3)
    x, y, yaw = on_lane_pose(0.3, 5.0, -0.3, math.pi / 2, 2.0)
    assert (x, y, yaw) == pytest.approx((0.0, 3.0, math.pi / 2), abs=1e-12)
    # arrays (the N > 1 loop)
    xs, ys, _ = on_lane_pose(np.array([10.0, 0.3]), np.array([0.5, 5.0]), np.array([0.5, -0.3]),
                             np.array([0.0, math.pi / 2]), 2.0, ARRAYS)
    np.testing.assert_allclose(xs, [8.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(ys, [0.0, 3.0], atol=1e-12)


def test_bad_lateral_mode_is_refused():
    with pytest.raises(ValueError, match="lateral"):
        LoopConfig(lateral="road")


@pytest.mark.sumo
def test_lane_mode_keeps_a_planner_that_leaves_the_bend_on_its_lane(bend):
    scenario = _scenario(bend)
    free = run_scenario(scenario, StraightAhead(), LoopConfig()).log
    lane = run_scenario(scenario, StraightAhead(), LoopConfig(lateral="lane")).log

    # the normal run leaves its lane in the bend (entered after ~8 s at ~13-15 m/s)
    departed = free["lane_departure"].to_numpy() > 0
    assert departed.any()
    t_dep = float(free["t"].to_numpy()[np.argmax(departed)])
    assert 7.0 < t_dep < 11.0
    # with the mode on: on the lane centre to round-off, heading along it, no flag, to the end
    assert not (lane["lane_departure"] > 0).any()
    assert lane["d"].abs().max() < 1e-6
    assert len(lane) == round(14.0 / 0.01)
    assert lane["s"].iloc[-1] > bend.path_start_s + STRAIGHT_M + 40.0  # well into the bend

    # the longitudinal log equals the normal run's while the normal run is on its lane: to
    # round-off on the straight (measured 1e-13); in the bend before it departs within what its
    # drift outwards makes by itself (measured: 0.87 m out, its station on the centre lags by
    # 0.10 m, d / R of the arc; speed 0.017 m/s, acceleration command 0.07 m/s^2)
    n_dep = int(np.argmax(departed))
    on_straight = free["s"].to_numpy() < bend.path_start_s + STRAIGHT_M
    for col, straight_tol, bend_tol in (("s", 1e-9, 0.15), ("v", 1e-9, 0.03),
                                        ("gap", 1e-9, 0.15), ("accel_cmd", 1e-9, 0.1)):
        a, b = free[col].to_numpy()[:n_dep], lane[col].to_numpy()[:n_dep]
        np.testing.assert_allclose(a[on_straight[:n_dep]], b[on_straight[:n_dep]], rtol=0,
                                   atol=straight_tol, err_msg=col)
        np.testing.assert_allclose(a, b, rtol=0, atol=bend_tol, err_msg=col)
    # and the leader's braking was followed (the longitudinal part is still the planner's)
    assert lane["v"].iloc[-1] < 12.5


@pytest.mark.sumo
def test_lane_mode_in_a_batch_equals_one_scenario(bend):
    """The N > 1 loop (arrays) puts its egos on their lanes as the N = 1 loop does."""
    scenario = _scenario(bend)
    loop = LoopConfig(lateral="lane")
    one = run_scenario(scenario, StraightAhead(), loop).log
    two = run_batch([scenario, replace(scenario, name="bend50_b")], StraightAhead(), loop)
    for rollout in two:
        got = rollout.log
        assert len(got) == len(one)
        for col in ("s", "d", "v", "gap", "accel_cmd"):
            np.testing.assert_allclose(got[col].to_numpy(), one[col].to_numpy(), rtol=0,
                                       atol=1e-7, err_msg=col)


def test_replay_cli_takes_the_lateral_mode():
    from safeil_sumo.replay import parse_args

    assert parse_args([]).lateral == "free"
    assert parse_args(["--lateral", "lane"]).lateral == "lane"
    with pytest.raises(SystemExit) as exc:
        parse_args(["--lateral", "road"])
    assert exc.value.code == 2
