"""The runner over a fake SUMO API: the seam is real (no libsumo needed for the loop's logic)."""

import math

import numpy as np
import pytest

from safeil_sumo.analytic import AnalyticPlanner
from safeil_sumo.geometry import yaw_to_sumo_angle
from safeil_sumo.sim.leaders import constant
from safeil_sumo.sim.runner import EGO_ID, LEADER_ID, LoopConfig, Scenario, run_scenario


# FakeSumo's route, vehicle and simulation domains: each changes the state of its FakeSumo
class _FakeRoute:
    def __init__(self, fake):
        self.fake = fake

    def add(self, route_id, edges):
        self.fake.calls.append(("route.add", route_id, tuple(edges)))


class _FakeVehicle:
    def __init__(self, fake):
        self.fake = fake

    def add(self, veh_id, route_id, depart="now", departLane="0", departPos="0",
            departSpeed="0"):
        self.fake.cars[veh_id] = {"x": float(departPos), "y": 0.0, "angle": 90.0,
                                  "speed": float(departSpeed)}

    def moveToXY(self, veh_id, edge, lane, x, y, angle=90.0, keepRoute=1):
        self.fake.calls.append(("moveToXY", veh_id, x, y, angle, keepRoute))
        self.fake.cars[veh_id].update(x=x, y=y, angle=angle)

    def setSpeed(self, veh_id, v):
        self.fake.cars[veh_id]["speed"] = v

    def setSpeedMode(self, veh_id, mode):
        self.fake.calls.append(("setSpeedMode", veh_id, mode))

    def setLaneChangeMode(self, veh_id, mode):
        self.fake.calls.append(("setLaneChangeMode", veh_id, mode))

    def setLength(self, veh_id, length):
        pass

    def setWidth(self, veh_id, width):
        pass

    def getPosition(self, veh_id):
        return self.fake.cars[veh_id]["x"], self.fake.cars[veh_id]["y"]

    def getAngle(self, veh_id):
        return self.fake.cars[veh_id]["angle"]

    def getSpeed(self, veh_id):
        return self.fake.cars[veh_id]["speed"]

    def getIDList(self):
        return list(self.fake.cars)


class _FakeSimulation:
    def __init__(self, fake):
        self.fake = fake

    def step(self, t=0.0):
        self.fake.time += self.fake.dt
        self.fake.steps += 1
        if self.fake.fail_at_step is not None and self.fake.steps > self.fake.fail_at_step:
            raise RuntimeError("simulated SUMO crash")
        leader = self.fake.cars.get(LEADER_ID)
        if leader is not None:
            leader["x"] += leader["speed"] * self.fake.dt

    def getTime(self):
        return self.fake.time

    def getCollidingVehiclesIDList(self):
        return []


class FakeSumo:
    """Vehicles on a straight road along +x: the leader moves at its set speed; the ego is
    wherever moveToXY puts it. Records the calls the runner makes."""

    def __init__(self, args, fail_at_step=None):
        self.args = list(args)
        self.fail_at_step = fail_at_step
        self.time = 0.0
        self.steps = 0
        self.dt = float(self.args[self.args.index("--step-length") + 1])
        self.cars = {}
        self.calls = []
        self.closed = False
        self.route = _FakeRoute(self)
        self.vehicle = _FakeVehicle(self)
        self.simulation = _FakeSimulation(self)

    def close(self):
        self.closed = True


def run_fake(road, placement="xy", **kw):
    made = []

    def factory(args):
        made.append(FakeSumo(args, **kw))
        return made[0]

    sc = Scenario("fake", road, constant(28.0), 30.0, 50.0, seed=3)
    # the fake moves the ego where moveToXY puts it (it has no lane coordinates for moveTo)
    rollout = run_scenario(sc, AnalyticPlanner(),
                           LoopConfig(max_time_s=60.0, ego_placement=placement),
                           api_factory=factory)
    return rollout, made[0]


def test_runner_drives_the_seam(straight_road):
    rollout, fake = run_fake(straight_road)
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


def test_sumo_failure_mid_run_keeps_the_log(straight_road):
    rollout, fake = run_fake(straight_road, fail_at_step=200)
    assert rollout.summary["end_reason"] == "error"
    assert "simulated SUMO crash" in rollout.summary["error"]
    assert len(rollout.log) == 199 and fake.closed
    assert math.isfinite(rollout.log["x"].iloc[-1]) and np.all(np.isfinite(rollout.log["t"]))


def test_an_error_before_the_loop_ends_the_run_with_its_reason(straight_road):
    """A seam without moveTo under the lane placement: the run ends with the error, SUMO
    closed (not a crash of the runner)."""
    rollout, fake = run_fake(straight_road, placement="lane")
    assert rollout.summary["end_reason"] == "error"
    assert "moveTo" in rollout.summary["error"] and fake.closed
    assert rollout.summary["leaders_met"] == 0


def test_lane_placeable_on_floats_and_arrays():
    """Inside the lane (``|d| <= half width``, the boundary included, NaN outside) and the step
    short of the route's end: a Python bool at N = 1, the same flags on arrays."""
    from safeil_sumo.sim.runner import lane_placeable

    half, end, advance = 1.75, 100.0, 1.0
    cases = [(0.0, 50.0, True), (1.75, 50.0, True), (-1.75, 50.0, True), (1.76, 50.0, False),
             (-1.76, 50.0, False), (math.nan, 50.0, False), (0.0, 98.9, True),
             (0.0, 99.0, False)]
    for d, s, expected in cases:
        assert lane_placeable(d, s, advance, half, end) is expected, (d, s)
    d, s, expected = (np.array(column) for column in zip(*cases, strict=True))
    flags = lane_placeable(d, s, np.full(len(d), advance), np.full(len(d), half), end)
    assert flags.tolist() == expected.tolist()
