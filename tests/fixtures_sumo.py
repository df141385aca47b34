"""A fake SUMO API for the closed loop's seam (``api_factory``): no libsumo needed to test the
loop's logic. The ``fake_sumo`` fixture (tests/conftest.py) gives a :class:`FakeSumoFactory`."""

from __future__ import annotations

from safeil_sumo.sim.sumo_setup import LEADER_ID


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


class FakeSumoFactory:
    """An ``api_factory``: each call (a SUMO start with its ``args``) makes a :class:`FakeSumo`
    with ``kwargs``, kept in ``made``."""

    def __init__(self, **kwargs):
        self.kwargs = kwargs
        self.made: list[FakeSumo] = []

    def __call__(self, args):
        self.made.append(FakeSumo(args, **self.kwargs))
        return self.made[-1]
