"""The closed loop, written once: N scenarios in ONE SUMO simulation, stepped from outside.

:class:`ClosedLoop` is the project's one closed loop (docs/architecture.md, "The closed loop"):
``reset(scenarios, policies)`` starts one SUMO simulation with the scenarios and returns the
first :class:`Observation`; ``step(plans)`` is one decision step, one planning period
(``1 / LoopConfig.plan_rate_hz``): the plans (given, or made by the bound policies from the
features of the observation) are tracked for the period's physics sub-steps (``step_s``), and
the next :class:`Observation` comes back with the step's :class:`Events`; ``step(controls=...)``
holds acceleration and steering commands over the period instead (no plan or tracker).
``restart(i, scenario)`` starts an ended scenario again on its copy of the track while the
others run (N > 1; each scenario counts its time, leader commands, log rows and time limit from
its own start step ``k0``). Every other loop is a driver of it: :func:`.runner.run_scenario` (N = 1, to the end), :func:`.batch.run_batch` (N, to
the end, each rollout as it ends), the replays, Gymnasium envs, closed-loop training rollouts,
falsification and the synthetic-drive recorder (:func:`safeil_sumo.data.recorder.record_drive`).

It is composed per scenario of a leader provider (:mod:`.providers`: a scripted or recorded
speed profile on a SUMO vehicle of its own, or whichever of SUMO's traffic leads) and an ego
driver (:class:`PlanAndTrack`: the policy's plan tracked by the controller on our vehicle
plant; :class:`Kinematic`: moved to a recorded pose every step, ``pose_at``, with no plan,
tracker or plant; :class:`SelfDriven`: an ego that enters SUMO itself and gives its pose every
step, :class:`SelfDrivenEgo`, the synthetic-drive recorder's), and of the stages every scenario shares: the sensors (camera, radar), the
monitors and the SUMO seam (:mod:`.sumo_setup`, :mod:`.sumo_api`).

Each sub-step is the stage sequence drive (track -> plant) -> move in SUMO -> step -> monitor,
called ONCE for all running scenarios; sensing and planning happen once per decision step. The
loop's body is written against an array namespace (:mod:`.xp`): at N = 1 it runs on Python
floats (:data:`.xp.FLOATS`: the stages' scalar paths, about 5x faster than numpy on one
number), at N > 1 on arrays ``(n,)`` of the running scenarios (:data:`.xp.ARRAYS`). What is
per scenario by nature stays per scenario: the camera and radar (each scenario's own road and
noise generator), the walks along each lane, SUMO's per-vehicle commands and reads. A scenario
that ends (end of path, collision, off road, a flag with ``stop_on_flag``, its time limit) is
sensed once more at its end state (its final observation) and leaves SUMO at that sub-step;
the others go on.

SUMO's names: N = 1 runs on the scenario's own net with the vehicles ``ego`` and ``leader``
(what SSM output, sumo-gui and the traffic's route files name); N > 1 puts every scenario on
its own renamed copy of its track (:mod:`.batch_net`: ``ego_i``, ``c{i}_...``, each copy
shifted along x by its ``dx``).

Randomness: each scenario keeps its own ``np.random.Generator(scenario.seed)`` for the sensor
noise; SUMO's ``--seed`` is the first scenario's and the loop draws nothing from SUMO (speed mode
0, every speed commanded; traffic draws from SUMO, N = 1). ``reset(seed=s)`` gives scenario
``i`` the seed ``s + i`` (Gymnasium's vector envs seed their sub-envs so).

Scope: every scenario and ego of the project. Traffic, sumo-gui and SSM output run at N = 1
(they name the original net's edges and the vehicle ``ego``); a run's egos are all planned or
all kinematic.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, Protocol, Self, TypeAlias, TypeVar, cast

import numpy as np

from safeil_sumo.core.features import planner_features
from safeil_sumo.core.geometry import Polyline, PolylineStack, yaw_to_sumo_angle
from safeil_sumo.core.policy import Policy
from safeil_sumo.sim import brake_guard as grd
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.batch_net import mixed_batch_net, prefixed
from safeil_sumo.sim.loop_types import GUI_SCREENSHOT_AT_S, LoopConfig, Rollout, Scenario
from safeil_sumo.sim.providers import NO_LEADER, LeaderPose, ScriptedLeader, TrafficLeader
from safeil_sumo.sim.rollout_log import _Log, finish
from safeil_sumo.sim.sumo_setup import (
    EGO_ID,
    GUI_VIEW_WIDTH_M,
    LEADER_ID,
    ApiFactory,
    default_factory,
    footprints_overlap,
    initial_state,
    insert_vehicles,
    lane_placeable,
    max_steps,
    place_ego,
    start_positions,
    sumo_args,
    sumo_lane_position,
    xy_placement_is_unambiguous,
)
from safeil_sumo.sim.xp import ARRAYS, FLOATS, BoolOrArray, FloatOrArray, Namespace

# empty space [m] between neighbouring copies of the track: beyond moveToXY's lane search
# radius, so each ego's search sees its own copy only (coincident copies made every moveToXY
# search all N copies: 0.2x the scalar loop at N = 32, measured)
SPACING_M = 1000.0
EXTERNAL = "external"  # the policy name in the summary of a scenario planned from outside
# end reasons of Events.terminated (the episode's own end) and Events.truncated (a limit)
TERMINAL_REASONS = ("collision", "off_road", "flag")
LIMIT_REASONS = ("completed", "timeout", "recording_end")
_COL = {name: i for i, name in enumerate(_Log.COLUMNS)}
_LOGGED_FEATURES = [0, 1, 2, 3, 4, 5, 7, 8]  # c0l..c2r, v_lead, d_lead: the features logged
# the log's columns in an Observation: floats, then flags
_OBS_FLOATS = np.array([_COL[c] for c in ("t", "x", "y", "yaw", "v", "s", "d", "gap", "ttc",
                                           "leader_v", "path_fraction")])
_OBS_FLAGS = np.array([_COL[c] for c in ("lane_departure", "ttc_flag", "collision")])
# the end reasons of a sub-step, in the order they are checked (_watch's end conditions)
_END_REASONS = ("completed", "collision", "off_road", "flag", "timeout")

Pose: TypeAlias = tuple[float, float, float, float]  # front bumper x, y [m], yaw [rad], v [m/s]
# a kinematic ego's recorded pose at t [s] (the recorded pseudo-planner's pose_at)
PoseAt: TypeAlias = Callable[[float], Pose]


class TimedPolicy(Protocol):
    """A planner that changes with its scenario's time (a driver's style that changes during
    the run, :class:`safeil_sumo.planners.registry.ScheduledStyle`): :class:`PlanAndTrack`
    tells it the time of each decision it plans for, before it plans (scenarios that share
    one must be at the same time)."""

    def at_time(self, t_s: float) -> None: ...


class SelfDrivenEgo(Protocol):
    """An ego that drives itself (the synthetic-drive recorder's, :mod:`safeil_sumo.data.recorder`):
    it enters SUMO itself, instead of the loop's insertion and placement (``enter(api,
    ego_id)``, before the loop's first SUMO step), and every physics step, after SUMO's last
    step, it may read SUMO and says where it is at ``t`` [s] (``drive(api, t)``: its front
    bumper ``x, y`` [m], heading [rad], speed [m/s]); ``pose_at(0.0)``: its initial pose. The
    loop moves it there in SUMO (its front bumper exactly as given), steps, monitors and logs
    it; no plan, tracker or plant (NaN commands in the log). It runs alone (N = 1, no scripted
    leader or traffic of the loop's) and drives on through a collision (the log's
    ``collision`` column counts its steps)."""

    @property
    def name(self) -> str: ...

    @property
    def horizon(self) -> float: ...

    def pose_at(self, t: float) -> Pose: ...

    def enter(self, api: sumo_api.SumoApi, ego_id: str) -> None: ...

    def drive(self, api: sumo_api.SumoApi, t: float) -> Pose: ...

    def plan(self, features: np.ndarray) -> np.ndarray:
        """A :class:`~safeil_sumo.core.policy.Policy`'s (``reset`` takes policies); never called."""
        ...
# (s, d, heading, segment) of points on each row's ego lane centre, walked from their segments:
# floats and an int at N = 1 (Polyline.project_near), arrays else (project_near_many)
Project: TypeAlias = Callable[..., tuple[Any, Any, Any, Any]]
Rows: TypeAlias = Sequence[int] | np.ndarray  # row indices of the running scenarios
Controls: TypeAlias = tuple[FloatOrArray, FloatOrArray]  # held acceleration, steering commands
# what a driver's move gives the log: steering, acceleration commands, the guard's deceleration
Commands: TypeAlias = tuple[FloatOrArray, FloatOrArray, FloatOrArray]
# what a sub-step's drive gives the rest of it: t, steer_cmd, accel_cmd, the guard's
# deceleration, v, front_x, front_y, s, d, heading and hit
Moved: TypeAlias = tuple[FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray,
                         FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray,
                         BoolOrArray]


class StageClock:
    """Wall time [s] per stage of a stepped run, summed over its steps (pass one to
    :class:`ClosedLoop` or :func:`.batch.run_batch`; the bench reports it per ego-step).
    ``outside``: the time outside the stages, SUMO's start in ``reset`` and the driver's own
    work between steps."""

    STAGES = ("sense", "plan", "track", "plant", "project", "sumo_move", "sumo_step",
              "sumo_read", "monitor", "outside")

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(self.STAGES, 0.0)
        self.ego_steps = 0
        self._t = time.perf_counter()

    def lap(self, stage: str) -> None:
        """Book the time since the last lap to ``stage``."""
        now = time.perf_counter()
        self.seconds[stage] += now - self._t
        self._t = now

    def us_per_ego_step(self) -> dict[str, float]:
        return {k: 1e6 * v / max(self.ego_steps, 1) for k, v in self.seconds.items()}


def _no_lap(stage: str) -> None:
    pass


@dataclass(frozen=True)
class Observation:
    """The N scenarios after ``reset`` or a ``step``; row ``i`` is scenario ``i``. A scenario
    that has ended keeps the values of its last sub-step (its features: sensed at that end
    state). Positions are the original track's (a copy's shift taken off)."""

    t: np.ndarray  # (N,) simulation time of the row's state [s]
    features: np.ndarray  # (N, 9) the planner's features (safeil_sumo.core.features) for the next plan
    x: np.ndarray  # (N,) ego centre of gravity [m]
    y: np.ndarray  # (N,) [m]
    yaw: np.ndarray  # (N,) ego heading [rad]
    v: np.ndarray  # (N,) ego speed [m/s]
    s: np.ndarray  # (N,) front bumper's arc length along the ego lane [m]
    d: np.ndarray  # (N,) front bumper's lateral offset from the lane centre, left + [m]
    gap: np.ndarray  # (N,) bumper-to-bumper gap to the leader along the lane [m]; inf: none
    ttc: np.ndarray  # (N,) time to collision [s]; inf: not closing or no leader
    leader_v: np.ndarray  # (N,) the leader's true speed [m/s]; NaN: none
    path_fraction: np.ndarray  # (N,) share of the test path completed [-]
    lane_departure: np.ndarray  # (N,) bool: the footprint is out of its lane (+ margin)
    ttc_flag: np.ndarray  # (N,) bool: ttc <= the scenario's threshold
    collision: np.ndarray  # (N,) bool: SUMO's collision or footprint overlap with the leader
    running: np.ndarray  # (N,) bool: not ended (step goes on with it)


@dataclass(frozen=True)
class Events:
    """What happened during one decision step, per scenario ``(N,)``."""

    ended: np.ndarray  # (N,) bool: ended during this step
    end_reason: np.ndarray  # (N,) str: why each ended scenario ended ("" while running):
    # completed (end of path), collision, off_road, flag (stop_on_flag), timeout (time limit),
    # recording_end (the time limit where a recorded leader's profile ends)
    lane_departure: np.ndarray  # (N,) bool: flagged at any sub-step of this step
    ttc_flag: np.ndarray  # (N,) bool: flagged at any sub-step of this step
    collision: np.ndarray  # (N,) bool: at any sub-step of this step
    sub_steps: np.ndarray  # (N,) int: physics steps taken in this step (0 once ended)

    @property
    def terminated(self) -> np.ndarray:
        """(N,) bool: ended in this step by its own doing (TERMINAL_REASONS)."""
        return self.ended & np.isin(self.end_reason, TERMINAL_REASONS)

    @property
    def truncated(self) -> np.ndarray:
        """(N,) bool: ended in this step at a limit, the path's end or the time (LIMIT_REASONS)."""
        return self.ended & np.isin(self.end_reason, LIMIT_REASONS)


class _Scenario:
    """What is per scenario in a run: its road, noise, camera, leader provider and log.
    ``copies``: the run puts every scenario on its own renamed copy of its track (N > 1).
    ``generation``: how often scenario ``i``'s copy has been restarted (:meth:`ClosedLoop.restart`,
    N > 1): a restarted scenario's vehicles and routes get new SUMO ids (``ego_i.generation``)."""

    def __init__(self, i: int, scenario: Scenario, policy: Policy | None, horizon: float,
                 loop: LoopConfig, vehicle: veh.VehicleParams, dx: float, log_width: int,
                 copies: bool, generation: int = 0) -> None:
        self.i, self.scenario, self.policy, self.horizon = i, scenario, policy, horizon
        self.generation = generation
        self.k0 = 0  # the loop's physics step at which this scenario's step 0 runs (restarts)
        self.rename = partial(prefixed, i) if copies else str  # SUMO id -> its id in this run
        # this scenario's vehicle and route ids end so
        self.tag = "" if not copies else f"_{i}" if generation == 0 else f"_{i}.{generation}"
        self.ego = f"ego{self.tag}" if copies else EGO_ID
        self.leader_id = f"leader{self.tag}" if copies else LEADER_ID
        self.dx = dx  # x offset [m] of this scenario's copy of the track in SUMO
        road = self.road = scenario.road
        self.lane = road.lanes[road.ego_lane]
        self.centre = self.lane.centre
        self.rng = np.random.default_rng(scenario.seed)
        self.n_max = max_steps(scenario, loop)
        self.s_ego0, self.s_lead0 = start_positions(scenario, vehicle)
        self.camera = sen.LaneCamera(road, scenario.sensors, self.s_ego0)
        # a policy with pose_at(t) (the recorded pseudo-planner) is a kinematic ego
        pose_at: PoseAt | None = getattr(policy, "pose_at", None)
        self.pose_at = pose_at
        # a kinematic ego with drive(api, t) drives itself (SelfDrivenEgo, SelfDriven)
        self.self_driven = (cast(SelfDrivenEgo, policy)
                            if getattr(policy, "drive", None) is not None else None)
        self.state0 = (initial_state(scenario, vehicle) if pose_at is None
                       else veh.state_from_front_bumper(*pose_at(0.0), vehicle))
        self.lead: ScriptedLeader | TrafficLeader | None = (
            TrafficLeader(scenario, self.ego) if scenario.traffic is not None
            else ScriptedLeader(scenario, vehicle, self.leader_id, self.n_max, loop.step_s, dx)
            if scenario.leader is not None else None)
        self.end_reason, self.error = "", ""
        # the log, row k = step k: a list of rows at N = 1 (an append per step: the row, or the
        # array of its kept columns), else an array filled row by row; None: freed
        self.rows: list[list[float] | np.ndarray] | np.ndarray | None = (
            [] if not copies else np.empty((self.n_max, log_width)))
        self.steps = 0  # rows filled
        # the ego route's SUMO lane ids (sumo_lane_position's) -> their ids in this run
        self.lane_ids = {p.lane_id: self.rename(p.lane_id) for p in road.ego_pieces}

    def add(self, api: sumo_api.SumoApi, vehicle: veh.VehicleParams) -> None:
        """Insert the ego (and the scripted leader, or the traffic) on this scenario's track;
        place the ego; a self-driven ego enters SUMO itself."""
        if self.self_driven is not None:
            self.self_driven.enter(api, self.ego)
            return
        road = self.road
        ego_k, ego_lane, ego_pos, lead_scale = insert_vehicles(
            api, self.scenario, vehicle, self.ego, self.leader_id, self.rename, self.tag)
        ego_edge = self.rename(road.route_edges[ego_k])
        if self.lead is not None:
            self.lead.start(api, lead_scale, ego_edge, float(ego_pos))
        front = veh.front_bumper(self.state0, vehicle)
        if xy_placement_is_unambiguous(road, front, self.s_ego0):
            place_ego(api, self.state0, vehicle, self.ego, self.dx, ego_edge, int(ego_lane))
        else:  # a closed course's other lap is nearer: keep the insertion on the ego's station
            api.vehicle.setSpeed(self.ego, veh.speed(self.state0))


def _horizon(policy: Policy | None, horizon_s: float | None) -> float:
    """The plans' horizon [s]: ``horizon_s``, else the policy's."""
    if horizon_s is not None:
        return horizon_s
    assert policy is not None, "reset and restart refuse neither a policy nor horizon_s"
    return policy.horizon


def _leader_rear(sc: _Scenario) -> tuple[tuple[float, float] | None, float]:
    """The scenario's leader as last read: its rear ``(x, y)`` [m] and true speed [m/s]
    (``None, 0.0``: no leader)."""
    lead = sc.lead
    pose: LeaderPose | None = lead.leader if lead is not None else None
    if lead is None or pose is None:
        return None, 0.0
    return pose[0], lead.v


def _kinematic_state(pose: Pose, vehicle: veh.VehicleParams) -> veh.PlantState:
    """The loop's state tuple of an ego at front bumper ``pose[:2]``, heading ``pose[2]``,
    speed ``pose[3]``."""
    s = veh.state_from_front_bumper(*pose, vehicle)
    return (s.x, s.y, s.yaw, s.vx, s.vy, s.yaw_rate, s.steer, s.drive_force)


def check_scope(scenarios: Sequence[Scenario], policies: Sequence[Policy | None],
                loop: LoopConfig) -> None:
    """Refuse what the loop does not run: kinematic and planned egos in one run; traffic,
    sumo-gui or SSM output with more than one scenario; a self-driven ego with others, a
    scripted leader or traffic."""
    kinematic = [getattr(p, "pose_at", None) is not None for p in policies]
    if any(kinematic) and not all(kinematic):
        raise ValueError("a run's egos are all kinematic (pose_at) or all planned: run the "
                         "kinematic ones apart")
    if any(getattr(p, "drive", None) is not None for p in policies) and (
            len(scenarios) > 1 or any(sc.leader is not None or sc.traffic is not None
                                      for sc in scenarios)):
        raise ValueError("a self-driven ego (drive) runs alone: one scenario, no scripted "
                         "leader or traffic of the loop's")
    if len(scenarios) > 1:
        if loop.gui or loop.ssm_file is not None:
            raise ValueError("sumo-gui and SSM output follow the vehicle 'ego' of ONE scenario: "
                             "run them one by one (N = 1), or headless without SSM output")
        if any(sc.traffic is not None for sc in scenarios):
            raise ValueError("traffic runs one scenario at a time (N = 1): its route files "
                             "name the original net's edges")


def _front_bumper(st: veh.PlantState, d_front: float, xp: Namespace
                  ) -> tuple[FloatOrArray, FloatOrArray]:
    """The front bumper ``(x, y)`` [m] of plant states ``st`` (centre of gravity, yaw)."""
    x, y, yaw = st[:3]
    return x + d_front * xp.cos(yaw), y + d_front * xp.sin(yaw)


class PlanAndTrack:
    """The ego driver of planned egos: each decision's plans are prepared for tracking; every
    physics step the controller tracks them and our vehicle plant integrates the commands. A
    decision may give the commands instead (``step(controls=...)``): they are held over the
    period, with no plan or tracker (the plant's actuators and limits still apply)."""

    def __init__(self, loop: ClosedLoop) -> None:
        self.vehicle, self.controller, self.dt = loop.vehicle, loop.controller, loop.loop.step_s
        self.plant = veh.Plant.of(loop.vehicle, loop.loop.step_s)
        self.lap = loop._sub_lap
        self.guard, self.period = loop.loop.brake_guard, loop._plan_every * loop.loop.step_s
        self.full_brake_mps2 = loop.vehicle.max_brake_decel_mps2
        self.on_lane = loop.loop.lateral == "lane"  # LoopConfig.lateral: put on the lane centre
        self.d_front = loop.vehicle.cog_to_front_bumper_m  # [m]

    def front(self, live: _Live, xp: Namespace) -> tuple[FloatOrArray, FloatOrArray]:
        """The front bumper [m] after this step's move."""
        return _front_bumper(live.st, self.d_front, xp)

    def plan(self, live: _Live, given: np.ndarray | None, t: FloatOrArray, xp: Namespace,
             controls: Controls | None = None) -> None:
        """The plans of the decision at ``t`` [s] (each scenario's own time: a float at N = 1,
        ``(n,)`` else) (``given`` ``(n, 3, 2)``, or the policies'); or, with ``controls``
        (acceleration, steering: floats at N = 1, columns ``(n,)`` else), no plan."""
        live.controls = controls
        n = len(live.runs)
        guard = self.guard
        if guard is not None:
            self._watch_leader(live, guard, xp)
        if controls is not None:  # the commands are held: no plan, its log columns NaN
            live.target = None
            live.t_plan = xp.full(n, t)
            live.plan_log = (xp.full(n, t), *_block(xp, n, 9))
            return
        fx, fy = live.front
        yaw = live.st[2]
        if given is None:
            for timed, rows_of in live.c.timed:  # told the decision's time first
                timed.at_time(_decision_time(t, rows_of, xp))
        if xp is FLOATS:
            if given is not None:
                cp = given[0]
            else:
                policy = live.runs[0].policy
                assert policy is not None, "_checked_plans refuses steps without plans or policy"
                cp = policy.plan(live.features)
            live.target = ctl.make_target(cp, _scalar(live.c.horizon),
                                          (_scalar(fx), _scalar(fy), _scalar(yaw)))
            live.plan_log = (t, fx, fy, yaw, *np.asarray(cp, float).reshape(6).tolist())
        else:
            cps = given
            if cps is None:
                cps = np.empty((n, 3, 2))
                for policy, rows_of in live.c.planners:  # one call per planner object
                    assert policy is not None, "_checked_plans refuses steps without plans or policy"
                    cps[rows_of] = np.asarray(policy.plan(live.features[rows_of]),
                                              float).reshape(-1, 3, 2)
            live.target = ctl.make_targets(cps, _array(live.c.horizon), _array(fx), _array(fy),
                                           _array(yaw))
            live.plan_log = (np.full(n, t), fx, fy, yaw, *cps.reshape(n, 6).T)
        live.t_plan = xp.full(n, t)

    def _watch_leader(self, live: _Live, guard: grd.BrakeGuard, xp: Namespace) -> None:
        """The brake guard's view at a decision: the leader's acceleration estimate and the
        deceleration demand held over the period (:mod:`.brake_guard`)."""
        f = live.features
        v_ego: FloatOrArray
        v_lead: FloatOrArray
        gap: FloatOrArray
        if xp is FLOATS:
            v_ego, v_lead, gap = float(f[6]), float(f[7]), float(f[8])
        else:
            v_ego, v_lead, gap = f[:, 6], f[:, 7], f[:, 8]
        a_prev, v_lead_prev, gap_prev, v_ego_prev = live.guard_memory
        a_lead = grd.leader_accel(a_prev, v_lead_prev, gap_prev, v_ego_prev, v_lead, gap,
                                  self.period, guard, xp)
        live.guard_memory = (a_lead, v_lead, gap, v_ego)
        live.guard_demand = grd.guard_decel(gap, v_ego, v_lead, a_lead, guard, xp)

    def move(self, live: _Live, t: FloatOrArray, xp: Namespace) -> Commands:
        """Track the plans (under the brake guard) and step the plant; the steering and
        acceleration commands and the guard's deceleration where it overrode (else 0; NaN
        without a guard or with held commands)."""
        vehicle = self.vehicle
        x, y, yaw, vx, vy, yaw_rate = live.st[:6]
        # plan() made a target or holds the commands: one of the two
        target, controls = live.target, live.controls
        if target is not None:
            steer_cmd, accel_cmd, live.integral, live.prev_error = ctl.track_values(
                target, t - live.t_plan, x, y, yaw, vx, vy, yaw_rate, vehicle,
                live.integral, live.prev_error, self.controller, self.dt, xp)
            if self.guard is not None:  # brake harder where the situation needs it
                demand = live.guard_demand
                override = (demand > 0.0) & (demand > -accel_cmd)
                guarded = xp.where(override, demand, 0.0)
                # full braking if need be: the vehicle's limit, not the tracker's
                accel_cmd = xp.where(override, xp.maximum(-demand, -self.full_brake_mps2),
                                     accel_cmd)
            else:
                guarded = live.c.nans
        elif controls is not None:  # commands from outside, held over the period
            accel_cmd, steer_cmd = controls
            guarded = live.c.nans
        else:
            raise RuntimeError("nothing to track: each step plans (or holds commands) first")
        throttle, brake = veh.pedals_from_accel_vx(accel_cmd, vx, vehicle, xp)
        if self.lap is not None:
            self.lap("track")
        live.st = self.plant.step(live.st, steer_cmd, throttle, brake, xp)
        if self.on_lane:
            live.st = self._on_lane_centre(live, xp)
        return steer_cmd, accel_cmd, guarded

    def _on_lane_centre(self, live: _Live, xp: Namespace) -> veh.PlantState:
        """``LoopConfig.lateral = "lane"``: the plant's new state with its pose put on the ego
        lane centre (:func:`on_lane_pose`) at the station its front bumper reached; the speeds,
        yaw rate, steering and drive force as the plant left them."""
        x, y, yaw, vx, vy, yaw_rate, steer, drive = live.st
        d_front = self.vehicle.cog_to_front_bumper_m
        fx, fy = x + d_front * xp.cos(yaw), y + d_front * xp.sin(yaw)
        _, d, heading, live.ego_seg = live.c.project(fx, fy, live.ego_seg)
        x, y, yaw = on_lane_pose(fx, fy, d, heading, d_front, xp)
        return x, y, yaw, vx, vy, yaw_rate, steer, drive


class Kinematic:
    """The ego driver of kinematic egos (the recorded pseudo-planner): every step each ego is
    moved to its pose ``pose_at(t)``; no plan, tracker or plant (NaN commands in the log)."""

    def __init__(self, loop: ClosedLoop) -> None:
        self.vehicle, self.dt = loop.vehicle, loop.loop.step_s
        self.d_front = loop.vehicle.cog_to_front_bumper_m  # [m]

    def front(self, live: _Live, xp: Namespace) -> tuple[FloatOrArray, FloatOrArray]:
        """The front bumper [m] after this step's move."""
        return _front_bumper(live.st, self.d_front, xp)

    def plan(self, live: _Live, given: np.ndarray | None, t: FloatOrArray, xp: Namespace,
             controls: Controls | None = None) -> None:
        pass  # nothing is planned (nor held): the log's plan columns stay NaN

    def move(self, live: _Live, t: FloatOrArray, xp: Namespace) -> Commands:
        states = []
        for r, tj in zip(live.runs, xp.rows(t + self.dt), strict=True):
            assert r.pose_at is not None, "a run's egos are all kinematic or none (check_scope)"
            states.append(_kinematic_state(r.pose_at(tj), self.vehicle))
        live.st = tuple(xp.from_rows(col) for col in zip(*states, strict=True))
        nans = live.c.nans
        return nans, nans, nans


class SelfDriven:
    """The ego driver of a self-driven ego (:class:`SelfDrivenEgo`, N = 1): every step it is
    asked where it is (``drive(api, t)``, after SUMO's last step); its front bumper is kept as
    given (``_Live.front_now``: no round trip through the centre of gravity); no plan, tracker
    or plant (NaN commands in the log)."""

    def __init__(self, loop: ClosedLoop) -> None:
        self.loop, self.vehicle, self.dt = loop, loop.vehicle, loop.loop.step_s

    def plan(self, live: _Live, given: np.ndarray | None, t: FloatOrArray, xp: Namespace,
             controls: Controls | None = None) -> None:
        pass  # nothing is planned (nor held): the log's plan columns stay NaN

    def front(self, live: _Live, xp: Namespace) -> tuple[FloatOrArray, FloatOrArray]:
        """Its front bumper as it gave it."""
        return live.front_now

    def move(self, live: _Live, t: FloatOrArray, xp: Namespace) -> Commands:
        api, ego = self.loop._api, live.runs[0].self_driven
        assert api is not None and ego is not None, "a self-driven ego runs alone, in SUMO"
        pose = ego.drive(api, _scalar(t) + self.dt)
        live.st = _kinematic_state(pose, self.vehicle)
        live.front_now = pose[0], pose[1]
        nans = live.c.nans
        return nans, nans, nans


def on_lane_pose(fx: FloatOrArray, fy: FloatOrArray, d: FloatOrArray, heading: FloatOrArray,
                 d_front: float, xp: Namespace = FLOATS
                 ) -> tuple[FloatOrArray, FloatOrArray, FloatOrArray]:
    """``(x, y, yaw)`` of the centre of gravity of an ego whose front bumper ``fx, fy`` [m],
    ``d`` [m] left of a lane centre heading ``heading`` [rad] there, is moved onto the centre:
    the front bumper at the foot point, heading along the lane (``d_front`` [m]: centre of
    gravity to front bumper)."""
    cos_h, sin_h = xp.cos(heading), xp.sin(heading)
    foot_x, foot_y = fx + d * sin_h, fy - d * cos_h
    return foot_x - d_front * cos_h, foot_y - d_front * sin_h, heading


def _decision_time(t: FloatOrArray, rows_of: np.ndarray | slice, xp: Namespace) -> float:
    """The one time [s] of the scenarios ``rows_of`` at a decision (``t``: each running
    scenario's); ``ValueError`` when a planner that changes in time is shared by scenarios at
    different times."""
    if xp is FLOATS:
        return _scalar(t)
    times = np.asarray(t)[rows_of]
    if times.min() != times.max():
        raise ValueError("a planner whose style changes in time (at_time) plans for scenarios "
                         f"at different times ({times.min():g} s to {times.max():g} s): give "
                         "each scenario its own")
    return float(times.flat[0])


def _scalar(value: FloatOrArray) -> float:
    """A per-scenario value of the N = 1 loop (FLOATS): a float, not an array."""
    assert not isinstance(value, np.ndarray), "the one-scenario loop runs on floats"
    return value


def _array(value: FloatOrArray) -> np.ndarray:
    """A per-scenario value of the N > 1 loop (ARRAYS): an array ``(n,)``."""
    assert isinstance(value, np.ndarray), "the loop of N > 1 scenarios runs on arrays"
    return value


def _block(xp: Namespace, n: int, k: int) -> tuple[FloatOrArray, ...]:
    """``k`` NaN log columns: floats at N = 1, arrays ``(n,)`` else."""
    return (xp.full(n, math.nan),) * k


class _Live:
    """The loop's state over the running scenarios, in the run's namespace ``xp``: row ``j``
    of every value is ``runs[j]``, scenario ``idx[j]`` of the reset."""

    def __init__(self, runs: list[_Scenario], xp: Namespace) -> None:
        n = len(runs)
        self.runs, self.xp = runs, xp
        self.idx = np.arange(n)
        self.st: veh.PlantState = tuple(  # the plant's state
            xp.from_rows([float(v) for v in col]) for col in zip(*(
                (r.state0.x, r.state0.y, r.state0.yaw, r.state0.vx, r.state0.vy,
                 r.state0.yaw_rate, r.state0.steer, r.state0.drive_force) for r in runs),
                strict=True))
        # PID memory
        self.integral: FloatOrArray = xp.full(n, 0.0)
        self.prev_error: FloatOrArray = xp.full(n, math.nan)
        # the brake guard's: leader acceleration, leader speed, gap, ego speed at the last
        # decision; its deceleration demand over the period [m/s^2]
        self.guard_memory = grd.no_history(n, xp)
        self.guard_demand: FloatOrArray = xp.full(n, 0.0)
        self.t_plan: FloatOrArray = xp.full(n, 0.0)  # when the tracked plans were made [s]
        self.features = np.full((n, 9) if xp is ARRAYS else 9, np.nan)  # the last decision's
        # front bumper then [m]
        self.front: tuple[FloatOrArray, FloatOrArray] = (xp.full(n, math.nan),
                                                         xp.full(n, math.nan))
        # a self-driven ego's front bumper after its move, as it gave it [m]
        self.front_now: tuple[FloatOrArray, FloatOrArray] = self.front
        # log columns: c0l..c2r, v_lead, d_lead as logged; the plan being tracked (time, pose,
        # control points)
        self.feature_log, self.plan_log = _block(xp, n, 8), _block(xp, n, 10)
        self.target: ctl.TrackingTarget | ctl.BatchTarget | None = None
        # the held commands (acceleration, steering) of step(controls=...), or None
        self.controls: Controls | None = None
        self.c = _Fixed.of(runs, xp)
        # each row's segment of its ego lane centre under the front bumper, under the leader's
        # rear (ints at N = 1)
        self.ego_seg: FloatOrArray = xp.from_rows([r.centre.segment_index(r.s_ego0)
                                                   for r in runs])
        # the leader's walk starts at its front; among traffic at the ego's (no leader yet)
        self.lead_seg: FloatOrArray = xp.from_rows([r.centre.segment_index(
            r.s_ego0 if isinstance(r.lead, TrafficLeader) else r.s_lead0) for r in runs])
        self.clear_flags()

    def clear_flags(self) -> None:
        """A new decision step: no flag, no sub-step yet."""
        false = self.c.no_flags
        self.departed = self.ttc_flag = self.collision = false
        self.sub_steps = 0

    @property
    def at(self) -> np.ndarray | slice:
        """The rows in the reset's per-scenario arrays: ``idx``, or at N = 1 the one row as a
        slice (cheaper to write)."""
        return slice(None) if self.xp is FLOATS else self.idx

    def flush(self, ev: Events) -> None:
        """The decision step's flags and sub-steps so far into ``ev``."""
        at = self.at
        ev.lane_departure[at], ev.ttc_flag[at] = self.departed, self.ttc_flag
        ev.collision[at], ev.sub_steps[at] = self.collision, self.sub_steps

    def take(self, keep: Rows) -> None:
        """Keep the rows ``keep`` (indices) only: the others have ended (rows remain of
        several scenarios only: N > 1, arrays)."""
        if not len(keep):
            self.runs, self.idx = [], self.idx[:0]
            return
        keep = np.asarray(keep)

        def cols(values: tuple[FloatOrArray, ...]) -> Any:  # the tuple's length, as given
            return tuple(_array(col)[keep] for col in values)

        self.runs = [self.runs[j] for j in keep]
        self.idx = self.idx[keep]
        self.c = _Fixed.of(self.runs, self.xp)
        self.st = cols(self.st)
        self.integral, self.prev_error = cols((self.integral, self.prev_error))
        self.guard_memory = cols(self.guard_memory)
        self.guard_demand, self.t_plan = cols((self.guard_demand, self.t_plan))
        self.features = self.features[keep]
        self.front = cols(self.front)
        self.ego_seg, self.lead_seg = cols((self.ego_seg, self.lead_seg))
        self.feature_log = cols(self.feature_log)
        self.plan_log = cols(self.plan_log)
        target = self.target
        if target is not None:
            assert isinstance(target, ctl.BatchTarget), "N > 1 scenarios track a BatchTarget"
            target = target.take(keep)
        self.target = target
        self.controls = cols(self.controls) if self.controls is not None else None
        self.departed, self.ttc_flag, self.collision = cols(
            (self.departed, self.ttc_flag, self.collision))

    def join(self, other: _Live) -> None:
        """Add ``other``'s rows (restarted scenarios, after a step: the next decision plans
        anew), then order every row by its scenario index (N > 1: arrays)."""
        cat = np.concatenate

        def cols(a: tuple[FloatOrArray, ...], b: tuple[FloatOrArray, ...]) -> Any:
            return tuple(cat([x, y]) for x, y in zip(a, b, strict=True))

        self.runs = self.runs + other.runs
        self.idx = cat([self.idx, other.idx])
        self.st = cols(self.st, other.st)
        self.integral = cat([self.integral, other.integral])
        self.prev_error = cat([self.prev_error, other.prev_error])
        self.guard_memory = cols(self.guard_memory, other.guard_memory)
        self.guard_demand = cat([self.guard_demand, other.guard_demand])
        self.t_plan, self.features = (cat([self.t_plan, other.t_plan]),
                                      cat([self.features, other.features]))
        self.front = cols(self.front, other.front)
        self.ego_seg, self.lead_seg = (cat([self.ego_seg, other.ego_seg]),
                                       cat([self.lead_seg, other.lead_seg]))
        self.feature_log = cols(self.feature_log, other.feature_log)
        self.plan_log = cols(self.plan_log, other.plan_log)
        self.departed, self.ttc_flag, self.collision = cols(
            (self.departed, self.ttc_flag, self.collision),
            (other.departed, other.ttc_flag, other.collision))
        self.target, self.controls = None, None
        self.take(np.argsort(self.idx, kind="stable"))


class ClosedLoop:
    """N scenarios side by side in one SUMO simulation, one decision step at a time.

    ``loop``, ``vehicle``, ``controller``: as for ``run_scenario`` (sumo-gui and SSM output
    with one scenario). ``api_factory``: SUMO options -> the SUMO API (default: libsumo/traci
    per ``loop.backend``, sumo-gui per ``loop.gui``). ``log_columns``: the per-step log keeps
    only these columns of ``_Log.COLUMNS`` (None: all). ``net_dir``: where the net of N > 1
    scenarios is written (default: the shared cache of :mod:`.batch_net`). ``clock``: filled
    with the time per stage.

    SUMO runs from ``reset`` until every scenario has ended or :meth:`close` (also a context
    manager). libsumo runs one simulation per process: one ClosedLoop at a time per process.
    Planners run in the caller's thread settings; :func:`.batch.run_batch` limits BLAS to one
    thread around its steps (a sweep runs a worker per core).
    """

    def __init__(self, loop: LoopConfig = LoopConfig(),
                 vehicle: veh.VehicleParams = veh.VehicleParams(),
                 controller: ctl.ControllerParams = ctl.ControllerParams(),
                 api_factory: ApiFactory | None = None, *,
                 log_columns: Sequence[str] | None = None, net_dir: Path | None = None,
                 clock: StageClock | None = None) -> None:
        columns = tuple(log_columns) if log_columns is not None else _Log.COLUMNS
        unknown = sorted(set(columns) - set(_Log.COLUMNS))
        if unknown:
            raise ValueError(f"unknown log column(s) {unknown}; the log has "
                             f"{', '.join(_Log.COLUMNS)}")
        self.loop, self.vehicle, self.controller = loop, vehicle, controller
        self.api_factory = api_factory or default_factory(loop)
        self.net_dir, self.clock = net_dir, clock
        self.columns = columns
        self._col_idx = (None if columns == _Log.COLUMNS
                         else np.array([_Log.COLUMNS.index(c) for c in columns]))
        self._lap = clock.lap if clock is not None else _no_lap
        self._sub_lap = clock.lap if clock is not None else None  # every physics step's
        self._d_front = vehicle.cog_to_front_bumper_m  # [m]
        # a leader's rear this close [m] ahead of the ego's front is checked for footprint overlap
        self._near = 2.0 * vehicle.length_m
        self._dt = loop.step_s
        self._offroad_m, self._stop_on_flag = loop.offroad_stop_m, loop.stop_on_flag
        self._plan_every = max(round(1.0 / (loop.plan_rate_hz * loop.step_s)), 1)
        # sumo-gui shows the true pose: always moveToXY there
        self._on_lane = loop.ego_placement == "lane" and not loop.gui
        self._shot_k = (round(GUI_SCREENSHOT_AT_S / loop.step_s)
                        if loop.gui_screenshot is not None else -1)  # the screenshot's step
        self._xp = FLOATS  # the run's namespace: FLOATS at N = 1, ARRAYS else
        self._driver: PlanAndTrack | Kinematic | SelfDriven = PlanAndTrack(self)
        self._self_driven = False  # the run's ego drives itself (SelfDriven)
        self._api: sumo_api.SumoApi | None = None
        self._runs: list[_Scenario] = []  # every scenario of the last reset, in order
        self._live: _Live | None = None  # the running ones; None: nothing to step
        self._k = 0  # the next physics step
        self._last = np.empty((0, len(_Log.COLUMNS)))  # (N, 44) each scenario's latest row
        self._features = np.empty((0, 9))  # (N, 9) each scenario's latest features
        self._running = np.empty(0, dtype=bool)  # (N,)
        self._pending: list[_Scenario] = []  # restarted scenarios, started by the next step
        self.sumo_started_s = math.nan  # time.perf_counter() when the last reset started SUMO

    # -- the public loop ----------------------------------------------------------------------

    def reset(self, scenarios: Sequence[Scenario],
              policies: Policy | Sequence[Policy | None] | None = None,
              seed: int | None = None, horizon_s: float | None = None) -> Observation:
        """Start SUMO with ``scenarios`` at their initial states; the first observation.

        ``policies``: one planner for all, one per scenario, or None (then every ``step`` gets
        its plans); scenarios sharing a planner object are planned in one call; a policy with
        ``pose_at(t)`` is a kinematic ego (all or none of a run's). ``seed``: None keeps each
        scenario's seed, else scenario ``i`` gets ``seed + i``. ``horizon_s`` [s]: the plans'
        horizon (default: each policy's ``horizon``; needed without policies).
        Bad input raises ``ValueError`` before SUMO starts, as does SUMO failing to start; an
        error after it ends every scenario with ``end_reason="error"``, closes SUMO and is
        raised.
        """
        self.close()
        self._runs, self._live, self._pending = [], None, []
        scenarios = list(scenarios)
        if not scenarios:
            raise ValueError("no scenarios to reset")
        if seed is not None:
            scenarios = [replace(sc, seed=int(seed) + i) for i, sc in enumerate(scenarios)]
        pols = _policy_list(policies, len(scenarios))
        check_scope(scenarios, pols, self.loop)
        if horizon_s is None and any(p is None for p in pols):
            raise ValueError("reset without a policy needs horizon_s, the plans' horizon [s]")
        copies = len(scenarios) > 1
        args = sumo_args(scenarios[0], self.loop)
        shifts = [0.0]
        if copies:
            net, shifts = mixed_batch_net([sc.road.net_path for sc in scenarios], SPACING_M,
                                          self.net_dir)
            args[args.index("-n") + 1] = str(net)
        runs = [_Scenario(i, sc, p, _horizon(p, horizon_s), self.loop, self.vehicle, dx,
                          len(self.columns), copies)
                for i, (sc, p, dx) in enumerate(zip(scenarios, pols, shifts, strict=True))]
        self._xp = ARRAYS if copies else FLOATS
        self._self_driven = runs[0].self_driven is not None
        self._driver = (SelfDriven(self) if self._self_driven
                        else Kinematic(self) if runs[0].pose_at is not None
                        else PlanAndTrack(self))
        self._api = api = self.api_factory(args)
        self.sumo_started_s = time.perf_counter()
        self._runs, self._k = runs, 0
        n = len(runs)
        self._last = np.full((n, len(_Log.COLUMNS)), np.nan)
        self._features = np.full((n, 9), np.nan)
        self._running = np.ones(n, dtype=bool)
        try:
            live = self._start(api, runs)
        except Exception as exc:
            self._fail(exc)
            raise
        self._live = live
        return self._observation()

    def step(self, plans: np.ndarray | None = None,
             controls: np.ndarray | None = None) -> tuple[Observation, Events]:
        """One decision step: plan, then the planning period's physics sub-steps.

        ``plans`` ``(N, 3, 2)`` (or ``(N, 6)``) [m]: each scenario's three free B-spline control
        points in its ego frame at this decision (rows of ended scenarios are ignored, as are
        all of kinematic egos); None: the bound policies plan from the observation's features.
        ``controls`` ``(N, 2)`` instead: each ego's acceleration [m/s^2] and road-wheel steering
        angle [rad] commands, held over the period with no plan or tracker (the plant's
        actuators and limits still apply; ignored for kinematic egos). Scenarios queued by
        :meth:`restart` start during the step (see there). Returns the observation after the
        step and what happened in it. An error ends every running scenario with
        ``end_reason="error"``, closes SUMO and is raised.
        """
        n_all = len(self._runs)
        ev = Events(np.zeros(n_all, bool), np.array([r.end_reason for r in self._runs], object),
                    np.zeros(n_all, bool), np.zeros(n_all, bool), np.zeros(n_all, bool),
                    np.zeros(n_all, int))
        self._advance(plans, controls, ev)
        return self._observation(), ev

    def advance(self, plans: np.ndarray | None = None,
                controls: np.ndarray | None = None) -> np.ndarray:
        """:meth:`step` for drivers that read only which scenarios still run
        (:func:`.runner.run_scenario`, :func:`.batch.run_batch`): the same decision step, without
        building its :class:`Observation` and :class:`Events`. Returns ``running`` ``(N,)`` bool
        after the step (a copy)."""
        self._advance(plans, controls, None)
        return self._running.copy()

    def _advance(self, plans: np.ndarray | None, controls: np.ndarray | None,
                 ev: Events | None) -> None:
        """The decision step of :meth:`step` (``ev``: filled with what happened; None: not
        kept)."""
        live, api = self._live, self._api
        if live is None:
            raise RuntimeError("no scenario is running: call reset first" if not self._runs
                               else "every scenario has ended: call reset")
        assert api is not None, "SUMO runs while a scenario does (close ends both)"
        self._lap("outside")
        if plans is not None and controls is not None:
            raise ValueError("step takes plans or controls, not both")
        # bad plans or controls are refused; the run goes on
        held = self._checked_controls(live, controls)
        given = self._checked_plans(live, plans) if held is None else None
        pending, self._pending = self._pending, []
        try:
            # each scenario's own time (a restarted one's starts at its k0)
            self._driver.plan(live, given, (self._k - live.c.k0) * self._dt, self._xp, held)
            self._lap("plan")
            live.clear_flags()
            last = False
            for sub in range(self._plan_every):
                if self.clock is not None:
                    self.clock.ego_steps += len(live.runs)
                last = sub == self._plan_every - 1
                if last and pending:  # inserted by this step's last SUMO step, as in reset
                    for r in pending:
                        r.add(api, self.vehicle)
                self._sub_step(live, api, self._k, last, ev)
                self._k += 1
                if not live.runs:
                    break
            if live.runs and ev is not None:
                live.flush(ev)
            if pending:
                live = self._start_restarted(live, api, pending, inserted=last)
            if live.runs:
                self._sense(live)
            else:  # every scenario has ended: SUMO is no longer needed
                self._live = None
                self._close_api()
        except Exception as exc:
            self._fail(exc)
            raise

    def restart(self, i: int, scenario: Scenario, policy: Policy | None = None,
                horizon_s: float | None = None) -> None:
        """Queue ``scenario`` to start again on scenario ``i``'s copy of the track, which has
        ended, while the others run on (a vector env's autoreset; N > 1: one scenario's end
        ends the run). It starts during the next :meth:`step`: its vehicles enter SUMO at that
        step's last SUMO step (as ``reset`` inserts them before its one SUMO step), so the
        observation after that step has its initial state, sensed as ``reset`` senses it, and
        its first decision is the step after (it is not stepped in the step that starts it).
        Its time and log start at 0. Its road must be on the same net as scenario ``i``'s (the
        copy is of that net), its ego planned or kinematic as the run's. ``ValueError`` for a
        running scenario, another net or another kind of ego; ``RuntimeError`` when SUMO has
        closed (every scenario had ended: call ``reset``)."""
        if self._live is None or self._api is None:
            raise RuntimeError("every scenario has ended and SUMO is closed: call reset")
        if not 0 <= i < len(self._runs):
            raise ValueError(f"no scenario {i}: the reset had {len(self._runs)}")
        old = self._runs[i]
        if self._running[i] or any(r.i == i for r in self._pending):
            raise ValueError(f"scenario {i} is running (or already restarting): only an ended "
                             "scenario restarts")
        if Path(scenario.road.net_path) != Path(old.road.net_path):
            raise ValueError(f"scenario {i} runs on a copy of {old.road.net_path}; a restart "
                             f"must stay on that net, got {scenario.road.net_path}")
        check_scope([scenario], [policy], self.loop)
        if scenario.traffic is not None:
            raise ValueError("traffic runs one scenario at a time (N = 1): it does not restart")
        if getattr(policy, "drive", None) is not None:
            raise ValueError("a self-driven ego runs alone (N = 1): it does not restart")
        if (getattr(policy, "pose_at", None) is not None) != isinstance(self._driver, Kinematic):
            raise ValueError("a run's egos are all kinematic (pose_at) or all planned: a restart "
                             "keeps the run's kind")
        if horizon_s is None and policy is None:
            raise ValueError("a restart without a policy needs horizon_s, the plans' horizon [s]")
        self._runs[i] = r = _Scenario(
            i, scenario, policy, _horizon(policy, horizon_s), self.loop, self.vehicle, old.dx,
            len(self.columns), True, old.generation + 1)
        self._pending.append(r)

    def _start_restarted(self, live: _Live, api: sumo_api.SumoApi, pending: list[_Scenario],
                         inserted: bool) -> _Live:
        """The restarted scenarios after their insertion (done now with one SUMO step when
        every other scenario ended before the step's last one): read the leaders, look at the
        start and join the running ones; they are sensed with them. Returns the loop's rows."""
        if not inserted:
            for r in pending:
                r.add(api, self.vehicle)
            api.simulation.step()
            self._k += 1
        for r in pending:
            r.k0 = self._k
            if r.lead is not None:
                r.lead.read(api)
        new = _Live(pending, self._xp)
        new.idx = np.array([r.i for r in pending])
        self._look_at_start(new)
        self._running[new.idx] = True
        if live.runs:
            live.join(new)
            return live
        self._live = new  # every other scenario has ended: the restarted ones are the loop's
        return new

    def rollout(self, i: int, wall_s: float = math.nan) -> Rollout:
        """Scenario ``i``'s log so far and its summary (``wall_s`` [s]: its share of the wall
        time, for the summary's rates)."""
        r = self._runs[i]
        if r.rows is None:
            raise ValueError(f"the log of scenario {i} has been freed")
        data = (np.array(r.rows, dtype=float).reshape(-1, len(self.columns))
                if isinstance(r.rows, list) else r.rows[:r.steps].copy())
        log = _Log.to_frame(data, self.columns)
        name = r.policy.name if r.policy is not None else EXTERNAL
        traffic = r.lead if isinstance(r.lead, TrafficLeader) else None
        return finish(r.scenario, log, r.end_reason or "running", r.error, wall_s, name,
                      len(traffic.met) if traffic else 0, traffic.cut_ins if traffic else 0)

    def free_log(self, i: int) -> None:
        """Drop scenario ``i``'s log buffer (a sweep keeps only the running scenarios' logs)."""
        self._runs[i].rows = None

    @property
    def started(self) -> bool:
        """Whether the last ``reset`` got as far as starting SUMO (its scenarios have state)."""
        return bool(self._runs)

    @property
    def steps(self) -> np.ndarray:
        """(N,) int: physics steps logged per scenario since the reset."""
        return np.array([r.steps for r in self._runs], dtype=int)

    @property
    def end_reasons(self) -> list[str]:
        """Each scenario's end reason ("" while running; "error" after a failure)."""
        return [r.end_reason for r in self._runs]

    def close(self) -> None:
        """End SUMO (the scenarios' logs stay readable until the next reset)."""
        self._live = None
        self._close_api()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the stages ---------------------------------------------------------------------------

    def _start(self, api: sumo_api.SumoApi, runs: list[_Scenario]) -> _Live:
        """Insert every scenario, take SUMO's first step, read the leaders, look at the
        initial states and sense them."""
        for r in runs:
            r.add(api, self.vehicle)
        api.simulation.step()
        if self.loop.gui:  # the ego exists only after the first step
            sumo_api.track_in_gui(api, runs[0].ego, GUI_VIEW_WIDTH_M)
        for r in runs:
            if r.lead is not None:
                r.lead.read(api)
        live = _Live(runs, self._xp)
        self._lap("outside")
        self._look_at_start(live)
        self._sense(live)
        return live

    def _sense(self, live: _Live, rows: Rows | None = None) -> None:
        """Camera and radar of the running scenarios (or of their ``rows``) at their current
        state: the features of the next decision (or, for ended rows, the final ones)."""
        st: tuple[FloatOrArray, ...]
        if rows is None or len(rows) == len(live.runs):
            runs, st, idx = live.runs, live.st, live.at
        else:  # some of several scenarios (N > 1: arrays)
            runs = [live.runs[j] for j in rows]
            st = tuple(_array(col)[rows] for col in live.st)
            idx = live.idx[rows]
        feats, feature_log, front = self._features_at(runs, st)
        self._features[idx] = feats
        if rows is None:
            live.features, live.feature_log, live.front = feats, feature_log, front
        self._lap("sense")

    def _features_at(self, runs: list[_Scenario], st: tuple[FloatOrArray, ...]
                     ) -> tuple[np.ndarray, tuple[FloatOrArray, ...],
                                tuple[FloatOrArray, FloatOrArray]]:
        """The planner's features of ``runs`` at states ``st``: ``(features (n, 9) or (9,),
        their logged columns, the front bumpers (x, y))``."""
        xp = self._xp
        x, y, yaw, vx, vy = st[:5]
        v = xp.hypot(vx, vy)
        d_front = self._d_front
        fx_, fy_ = x + d_front * xp.cos(yaw), y + d_front * xp.sin(yaw)
        lefts: list[np.ndarray] | np.ndarray
        rights: list[np.ndarray] | np.ndarray
        if xp is FLOATS:  # the camera: one scenario's lines, its own noise
            r = runs[0]
            left, right, _ = r.camera.lane_lines(np.array((fx_, fy_)), _scalar(yaw), r.rng)
            lefts, rights = [left], [right]
        else:  # each scenario's lines, sampled per line and fitted all at once, then its noise
            lefts, rights = _camera_fits(runs, fx_, fy_, _array(yaw))
            for j, r in enumerate(runs):
                sen.add_lane_noise(lefts[j], rights[j], r.scenario.sensors, r.rng)
        leads: list[tuple[float, float]] = []  # per row: the leader's features v_lead, d_lead
        for r, left, right, (fx, fy, yj, vj) in zip(runs, lefts, rights,
                                                    xp.each(fx_, fy_, yaw, v), strict=True):
            rear, v_true = _leader_rear(r)
            radar = sen.radar_leader(np.array((fx, fy)), yj, rear, v_true, left, right,
                                     r.scenario.sensors, r.rng)
            leads.append(sen.leader_features(radar, vj, r.scenario.sensors))
        v_lead, d_lead = xp.from_each(leads)
        feats = planner_features(xp.from_rows(lefts), xp.from_rows(rights), v, v_lead, d_lead)
        if xp is FLOATS:
            f = feats.tolist()
            feature_log = (*f[:6], f[7], f[8])
        else:
            feature_log = tuple(feats[:, _LOGGED_FEATURES].T)
        return feats, feature_log, (fx_, fy_)

    def _checked_plans(self, live: _Live, plans: np.ndarray | None) -> np.ndarray | None:
        """The running scenarios' rows ``(n, 3, 2)`` of ``plans`` (None: their policies
        plan); ``ValueError`` for plans of the wrong size or a missing policy."""
        if plans is None:
            if live.c.unplanned:
                raise ValueError("a scenario without a policy needs its plans: step(plans)")
            return None
        given = np.asarray(plans, dtype=float)
        if given.size != 6 * len(self._runs):
            raise ValueError(f"plans must be ({len(self._runs)}, 3, 2) control points [m], got "
                             f"shape {given.shape}")
        return given.reshape(len(self._runs), 3, 2)[live.idx]

    def _checked_controls(self, live: _Live, controls: np.ndarray | None
                          ) -> tuple[FloatOrArray, FloatOrArray] | None:
        """The running scenarios' commands ``(acceleration, steering)`` of ``controls`` (floats
        at N = 1, columns ``(n,)`` else), or None; ``ValueError`` for a wrong shape or a value
        that is not finite."""
        if controls is None:
            return None
        given = np.asarray(controls, dtype=float)
        if given.shape != (len(self._runs), 2):
            raise ValueError(f"controls must be ({len(self._runs)}, 2): acceleration [m/s^2] "
                             f"and steering angle [rad], got shape {given.shape}")
        rows = given[live.idx]
        if not np.isfinite(rows).all():
            raise ValueError("controls must be finite")
        if self._xp is FLOATS:
            accel, steer = rows[0].tolist()
            return accel, steer
        return rows[:, 0].copy(), rows[:, 1].copy()

    def _sub_step(self, live: _Live, api: sumo_api.SumoApi, k: int, last: bool,
                  ev: Events | None) -> None:
        """Physics step ``k`` of every running scenario: drive (:meth:`_drive`), then on the
        state at ``t + dt``: read the leaders, check footprints, run the monitors, log the step
        (the full row: ``(n, 44)``, 44 floats at N = 1), end the scenarios that end."""
        t, steer_cmd, accel_cmd, guarded, v, front_x, front_y, s, d, heading, hit = self._drive(
            live, api, k)
        c, st, xp, lap = live.c, live.st, self._xp, self._sub_lap
        # each leader's rear x, y [m] and true speed [m/s] (NaN: none; the true speed of a
        # leader that needs_location comes once it is located)
        lead_x, lead_y, v_lead = xp.from_each([r.lead.read(api) if r.lead is not None
                                               else NO_LEADER for r in live.runs])
        if c.any_traffic:  # a leader met after none: its walk starts at the ego's segment
            from_ego = xp.from_rows([isinstance(r.lead, TrafficLeader) and r.lead.from_ego
                                     for r in live.runs])
            live.lead_seg = xp.where(from_ego, live.ego_seg, live.lead_seg)
        if lap is not None:
            lap("sumo_read")
        has_lead = xp.isfinite(lead_x)  # NaN: no leader
        s_rear, _, _, live.lead_seg = _project(c.project, xp, lead_x, lead_y, live.lead_seg)
        gap = xp.where(has_lead, s_rear - s, math.inf)
        yaw = st[2]
        fix = xp.nonzero(has_lead & ((gap < self._near) | c.located))
        if len(fix):
            v_lead, hit = self._locate_leaders(live, fix, s_rear, gap, v_lead, hit,
                                               (front_x, front_y), yaw)
        if lap is not None:
            lap("project")

        d_min, d_max, departed, ttc, ttc_flag, fraction = _monitors(
            c, self.vehicle, yaw, heading, s, d, v, gap, v_lead, has_lead, xp)
        lead_no = (xp.from_rows([r.lead.no if r.lead is not None and r.lead.leader is not None
                                 else math.nan for r in live.runs])
                   if c.any_traffic else xp.where(has_lead, 0.0, math.nan))
        rows: Any = [  # the log's columns (_Log.COLUMNS): floats at N = 1, arrays (n,) else
            t + self._dt, st[0], st[1], yaw, v, st[4], st[5], st[6], front_x, front_y,
            steer_cmd, accel_cmd, s, d, d_min, d_max, *live.feature_log, lead_x, lead_y, v_lead,
            gap, ttc, departed, ttc_flag, hit, fraction, *live.plan_log, lead_no, guarded,
        ]
        if xp is FLOATS:  # one scenario: a list append per step
            run = live.runs[0]
            log = run.rows
            assert isinstance(log, list), "a running scenario's log is kept (a list at N = 1)"
            log.append(rows if self._col_idx is None else np.asarray(rows)[self._col_idx])
            run.steps = k + 1
        else:  # each scenario's own step (a restarted one's starts at its k0)
            rows = np.array(rows).T
            logged = rows if self._col_idx is None else rows[:, self._col_idx]
            for r, row in zip(live.runs, logged, strict=True):
                log = r.rows
                assert isinstance(log, np.ndarray), "a running scenario's log is kept"
                log[k - r.k0] = row
                r.steps = k - r.k0 + 1

        if ev is not None:  # the decision step's flags (only Events reads them)
            live.departed = live.departed | departed
            live.ttc_flag = live.ttc_flag | ttc_flag
            live.collision = live.collision | hit
            live.sub_steps += 1
        # the end conditions of _END_REASONS, in order (a self-driven ego drives on through a
        # collision: its log counts it)
        ends = (s >= c.path_end, c.no_flags if self._self_driven else hit,
                xp.abs(d) > c.half_width + self._offroad_m,
                (departed | ttc_flag) & self._stop_on_flag, k + 1 - c.k0 >= c.n_max)
        ended = ends[0] | ends[1] | ends[2] | ends[3] | ends[4]
        any_ended = xp.any(ended)
        if last or any_ended:  # the observation: each scenario's latest row
            self._last[live.at] = rows
        if any_ended:  # why: the first end condition met
            self._end(live, api, ended, xp.select(ends, _END_REASONS, ""), ev)
        if lap is not None:
            lap("monitor")

    def _drive(self, live: _Live, api: sumo_api.SumoApi, k: int) -> Moved:
        """Drive the egos (track and plant, or their recorded poses), find each front bumper on
        its lane, move the egos and command the leaders in SUMO, step SUMO."""
        c, dt, lap, xp = live.c, self._dt, self._sub_lap, self._xp
        t = (k - c.k0) * dt  # each scenario's own time (a restarted one's starts at its k0)
        steer_cmd, accel_cmd, guarded = self._driver.move(live, t, xp)
        yaw, vx, vy = live.st[2:5]
        v = xp.hypot(vx, vy)
        front_x, front_y = self._driver.front(live, xp)
        if lap is not None:
            lap("plant")

        # where each front bumper is on its lane, then SUMO: move, command the leaders, step
        s, d, heading, live.ego_seg = c.project(front_x, front_y, live.ego_seg)
        if lap is not None:
            lap("project")
        # moveTo on the lane where placeable (ego_placement "lane" only), else moveToXY
        inside = (lane_placeable(d, s, v * dt, c.half_width, c.route_end) if self._on_lane
                  else c.no_flags)
        vehicle = api.vehicle
        for r, (fx, fy, vj, sj, yj, on_lane) in zip(
                live.runs, xp.each(front_x, front_y, v, s, yaw, inside), strict=True):
            if on_lane:
                lane, pos = sumo_lane_position(r.road, sj, vj * dt)
                vehicle.moveTo(r.ego, r.lane_ids[lane], pos)
            else:
                vehicle.moveToXY(r.ego, "", -1, fx + r.dx, fy, yaw_to_sumo_angle(yj), 2)
            vehicle.setSpeed(r.ego, vj)
            if r.lead is not None:
                r.lead.command(api, k - r.k0)
        if lap is not None:
            lap("sumo_move")
        if k == self._shot_k and (shot := self.loop.gui_screenshot) is not None:
            sumo_api.gui_screenshot(api, shot)  # sumo-gui saves it during this step
        api.simulation.step()
        colliding = api.simulation.getCollidingVehiclesIDList()
        if colliding:  # SUMO's collisions (few steps have any)
            ids = set(colliding)
            hit = xp.from_rows([r.ego in ids for r in live.runs])
        else:
            hit = c.no_flags
        if lap is not None:
            lap("sumo_step")
        return t, steer_cmd, accel_cmd, guarded, v, front_x, front_y, s, d, heading, hit

    def _locate_leaders(self, live: _Live, rows: Rows, s_rear: FloatOrArray, gap: FloatOrArray,
                        v_lead: FloatOrArray, hit: BoolOrArray,
                        front: tuple[FloatOrArray, FloatOrArray], yaw: FloatOrArray,
                        count: bool = True) -> tuple[FloatOrArray, BoolOrArray]:
        """The leaders of ``rows`` (each with a leader) located on the ego lane (their true
        speeds, and for traffic the leaders met) and, where close, checked for footprint
        overlap with the ego (unless already colliding). Returns ``v_lead, hit``."""
        xp, vehicle = self._xp, self.vehicle
        near = self._near
        srl, gl, vll, hl = xp.rows(s_rear), xp.rows(gap), xp.rows(v_lead), xp.rows(hit)
        fxl, fyl, yl = xp.rows(front[0]), xp.rows(front[1]), xp.rows(yaw)
        for j in rows:
            lead = live.runs[j].lead
            pose = lead.leader if lead is not None else None
            assert lead is not None and pose is not None, "rows with a leader are located"
            if lead.needs_location:
                vll[j] = lead.located(srl[j], gl[j], count)
            if gl[j] < near and not hl[j]:
                hl[j] = footprints_overlap((fxl[j], fyl[j]), yl[j], vehicle, pose, lead.length,
                                           lead.width)
        return xp.from_rows(vll), xp.from_rows(hl)

    def _end(self, live: _Live, api: sumo_api.SumoApi, ended: BoolOrArray, reason: Any,
             ev: Events | None) -> None:
        """The scenarios ``ended`` (rows) are sensed once more (their final observation) and
        leave SUMO and the loop (into ``ev``, unless None)."""
        xp = self._xp
        rows = xp.nonzero(ended)
        self._sense(live, rows)
        if ev is not None:
            live.flush(ev)
        reasons = xp.rows(reason)
        for j in rows:
            r = live.runs[j]
            r.end_reason = str(reasons[j])
            if r.end_reason == "timeout":  # or the end of its recorded leader
                r.end_reason = r.scenario.time_limit_reason
            if ev is not None:
                ev.ended[r.i], ev.end_reason[r.i] = True, r.end_reason
            self._running[r.i] = False
            for vid in (r.ego, *(r.lead.vehicle_ids() if r.lead is not None else ())):
                with suppress(Exception):  # it may have left the network already
                    api.vehicle.remove(vid)
        live.take(xp.nonzero(reason == ""))

    def _look_at_start(self, live: _Live) -> None:
        """The monitors' view of the initial states, for reset's observation (footprint
        overlap as the collision; traffic's leader located; nothing else the loop keeps is
        changed)."""
        c, vehicle, xp = live.c, self.vehicle, self._xp
        n = len(live.runs)
        x, y, yaw, vx, vy = live.st[:5]
        v = xp.hypot(vx, vy)
        d_front = self._d_front
        front_x, front_y = x + d_front * xp.cos(yaw), y + d_front * xp.sin(yaw)
        s, d, heading, _ = c.project(front_x, front_y, live.ego_seg)
        lx, ly, lv = [], [], []
        for r in live.runs:
            rear, v_true = _leader_rear(r)
            lx.append(math.nan if rear is None else rear[0])
            ly.append(math.nan if rear is None else rear[1])
            lv.append(math.nan if rear is None else v_true)
        lead_x, lead_y, v_lead = xp.from_rows(lx), xp.from_rows(ly), xp.from_rows(lv)
        has_lead = xp.isfinite(lead_x)
        s_rear, _, _, seg = _project(c.project, xp, lead_x, lead_y, live.lead_seg)
        if c.any_traffic:  # traffic's walk goes on from here
            live.lead_seg = xp.where(c.traffic, seg, live.lead_seg)
        gap = xp.where(has_lead, s_rear - s, math.inf)
        hit = xp.from_rows([False] * n)
        fix = xp.nonzero(has_lead & ((gap < self._near) | c.traffic))
        if len(fix):
            v_lead, hit = self._locate_leaders(live, fix, s_rear, gap, v_lead, hit,
                                               (front_x, front_y), yaw,
                                               count=False)
        _, _, departed, ttc, ttc_flag, fraction = _monitors(
            c, vehicle, yaw, heading, s, d, v, gap, v_lead, has_lead, xp)
        for name, values in (("t", 0.0), ("x", x), ("y", y), ("yaw", yaw), ("v", v), ("s", s),
                             ("d", d), ("gap", gap), ("ttc", ttc), ("leader_v", v_lead),
                             ("path_fraction", fraction), ("lane_departure", departed),
                             ("ttc_flag", ttc_flag), ("collision", hit)):
            self._last[live.idx, _COL[name]] = values

    def _observation(self) -> Observation:
        # copies: take makes new arrays (columns, floats), each field a row of one of them
        last = self._last.T
        t, x, y, yaw, v, s, d, gap, ttc, leader_v, fraction = last.take(_OBS_FLOATS, axis=0)
        departed, ttc_flag, collision = last.take(_OBS_FLAGS, axis=0).astype(bool)
        return Observation(t, self._features.copy(), x, y, yaw, v, s, d, gap, ttc, leader_v,
                           fraction, departed, ttc_flag, collision, self._running.copy())

    def _fail(self, exc: Exception) -> None:
        """Every scenario still running ends with the error; SUMO is closed."""
        for r in self._runs:
            if not r.end_reason:
                r.end_reason, r.error = "error", f"{type(exc).__name__}: {exc}"
        self._running[:] = False
        self.close()

    def _close_api(self) -> None:
        api, self._api = self._api, None
        if api is not None:
            with suppress(Exception):  # already gone: nothing left to end
                api.close()


def _policy_list(policies: Policy | Sequence[Policy | None] | None, n: int
                 ) -> list[Policy | None]:
    """One policy (or None) per scenario."""
    if policies is None or isinstance(policies, Policy):
        return [policies] * n
    out = list(policies)
    if len(out) != n:
        raise ValueError(f"{n} scenarios but {len(out)} policies")
    return out


def _project(project: Project, xp: Namespace, x: FloatOrArray, y: FloatOrArray,
             seg: FloatOrArray) -> tuple[Any, Any, Any, Any]:
    """``s, d, heading, segment`` of points ``x, y`` each on its ego lane centre (``project``:
    :attr:`_Fixed.project`), walked from ``seg``; a NaN point gives NaN and keeps its segment
    (the arrays' walk does so itself)."""
    if xp is FLOATS and math.isnan(x):
        return math.nan, math.nan, math.nan, seg
    return project(x, y, seg)


def _monitors(c: _Fixed, vehicle: veh.VehicleParams, yaw: FloatOrArray, heading: FloatOrArray,
              s: FloatOrArray, d: FloatOrArray, v: FloatOrArray, gap: FloatOrArray,
              v_lead: FloatOrArray, has_lead: BoolOrArray, xp: Namespace
              ) -> tuple[FloatOrArray, FloatOrArray, BoolOrArray, FloatOrArray, BoolOrArray,
                         FloatOrArray]:
    """The monitors: ``d_min, d_max`` [m] (the footprint's lateral extent), lane departure,
    TTC [s], TTC flag, path completed [-]."""
    heading_err = (yaw - heading + math.pi) % (2.0 * math.pi) - math.pi
    d_min, d_max = mon.footprint_offset_range(d, heading_err, vehicle.length_m, vehicle.width_m,
                                              xp)
    departed = mon.lane_departure(d_min, d_max, c.lane_width, c.margin, xp)
    ttc = xp.where(has_lead, mon.time_to_collision(gap, v, v_lead, xp), math.inf)
    ttc_flag = ttc <= c.ttc_threshold
    fraction = mon.path_completed(s, c.path_start, c.path_end, xp)
    return d_min, d_max, departed, ttc, ttc_flag, fraction


def _camera_fits(live: list[_Scenario], x: np.ndarray, y: np.ndarray, yaw: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The camera's left and right line fits ``(n, 4)`` (before noise) of every scenario: the
    lines each camera sees, then one sampling and one stacked fit per (line, camera setting)."""
    fits = np.empty((2 * len(live), 4))  # row 2j: scenario j's left line, 2j + 1: its right
    xl, yl = x.tolist(), y.tolist()
    # -> (line, camera, rows, arc lengths)
    groups: dict[tuple[int, float, int, float, float],
                 tuple[Polyline, sen.SensorConfig, list[int], list[float]]] = {}
    for j, r in enumerate(live):
        lane, s_left, s_right = r.camera.lane_stations(xl[j], yl[j])
        config = r.scenario.sensors
        for row, line, s0 in ((2 * j, lane.left_boundary, s_left),
                              (2 * j + 1, lane.right_boundary, s_right)):
            key = (id(line), config.view_range_m, config.view_samples,  # what sampling reads
                   config.max_view_turn_rad, config.min_view_range_m)
            g = groups.setdefault(key, (line, config, [], []))
            g[2].append(row)
            g[3].append(s0)
    # sampled per group, fitted in one stacked fit per number of samples (scenarios on many
    # roads have many groups; a fit is per point set, the same alone or stacked)
    points: dict[int, list[tuple[list[int], np.ndarray, np.ndarray]]] = {}
    for line, config, rows, stations in groups.values():
        cars = np.array(rows) // 2
        px, py = sen.ego_points_many(line, np.array(stations), x[cars], y[cars], yaw[cars],
                                     config)
        points.setdefault(px.shape[1], []).append((rows, px, py))
    for parts in points.values():
        if len(parts) == 1:
            rows, px, py = parts[0]
        else:
            rows = [row for part in parts for row in part[0]]
            px, py = np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])
        fits[rows] = sen.polyfit3_batch(px, py)
    return fits[0::2], fits[1::2]


_T = TypeVar("_T")
_K = TypeVar("_K")


def _groups(items: list[_T], key: Callable[[_T], _K]) -> list[tuple[_K, np.ndarray | slice]]:
    """``(object, rows)`` for each distinct ``key(item)`` object (compared by identity: lanes
    and planners need not hash), in order; one group's rows are ``slice(None)``."""
    groups: dict[int, tuple[_K, list[int]]] = {}
    for j, item in enumerate(items):
        obj = key(item)
        groups.setdefault(id(obj), (obj, []))[1].append(j)
    if len(groups) == 1:
        return [(next(iter(groups.values()))[0], slice(None))]
    return [(obj, np.array(rows)) for obj, rows in groups.values()]


@dataclass(frozen=True)
class _Fixed:
    """What stays fixed during a run, over the running scenarios (rebuilt when one ends):
    floats at N = 1, arrays ``(n,)`` else."""

    lane_width: FloatOrArray  # (n,) [m]
    half_width: FloatOrArray  # (n,) half the lane width [m]
    margin: FloatOrArray  # (n,) lane monitor tolerance [m]
    ttc_threshold: FloatOrArray  # (n,) [s]
    path_start: FloatOrArray  # (n,) [m]
    path_end: FloatOrArray  # (n,) [m]
    route_end: FloatOrArray  # (n,) the end of SUMO's route along the ego lane [m]
    n_max: FloatOrArray  # (n,) steps
    horizon: FloatOrArray  # (n,) plan horizon [s]
    located: BoolOrArray  # (n,) bool: the leader is located on the ego lane every step
    traffic: BoolOrArray  # (n,) bool: the leader is SUMO's traffic
    any_traffic: bool
    no_flags: BoolOrArray  # (n,) bool: False in every row (not written to)
    nans: FloatOrArray  # (n,) NaN in every row (not written to)
    planners: list[tuple[Policy | None, np.ndarray | slice]]  # (planner, rows): a call each
    timed: list[tuple[TimedPolicy, np.ndarray | slice]]  # the planners with at_time, their rows
    unplanned: bool  # a row has no policy: step needs its plans
    # (x, y, segment) -> s, d, heading, segment on each row's ego lane centre: the one polyline,
    # or several (scenarios on different roads) walked at once on their stack (NaN points give
    # NaN and keep their segment; no NaN at N = 1)
    project: Project
    k0: FloatOrArray  # (n,) int: the loop's physics step of each scenario's step 0 (restarts)

    @staticmethod
    def of(live: list[_Scenario], xp: Namespace) -> _Fixed:
        def col(get: Callable[[_Scenario], object]) -> Any:
            return xp.from_rows([get(r) for r in live])

        traffic = [isinstance(r.lead, TrafficLeader) for r in live]
        project: Project = (live[0].centre.project_near if xp is FLOATS
                            else _lanes(live).project_near_many)
        lane_width = col(lambda r: r.lane.width)
        planners = _groups(live, lambda r: r.policy)
        return _Fixed(
            lane_width=lane_width, half_width=0.5 * lane_width,
            margin=col(lambda r: r.scenario.monitors.lane_margin_m),
            ttc_threshold=col(lambda r: r.scenario.monitors.ttc_threshold_s),
            path_start=col(lambda r: r.road.path_start_s),
            path_end=col(lambda r: r.road.path_end_s),
            route_end=col(lambda r: r.road.ego_pieces[-1].s1),
            n_max=col(lambda r: r.n_max), horizon=col(lambda r: r.horizon),
            located=col(lambda r: r.lead is not None and r.lead.needs_location),
            traffic=xp.from_rows(traffic), any_traffic=any(traffic),
            no_flags=xp.from_rows([False] * len(live)), nans=xp.full(len(live), math.nan),
            planners=planners,
            timed=[(cast(TimedPolicy, policy), rows) for policy, rows in planners
                   if getattr(policy, "at_time", None) is not None],
            unplanned=any(policy is None for policy, _ in planners), project=project,
            k0=col(lambda r: r.k0))


def _lanes(live: list[_Scenario]) -> Polyline | PolylineStack:
    """What projects each running scenario's points on its own ego lane centre."""
    groups = _groups(live, lambda r: r.centre)
    if len(groups) == 1:
        return groups[0][0]
    line_of = np.empty(len(live), dtype=int)
    for k, (_, rows) in enumerate(groups):
        line_of[rows] = k
    return PolylineStack([line for line, _ in groups], line_of)
