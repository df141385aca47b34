"""The closed loop as a stepper: N scenarios in ONE SUMO simulation, stepped from outside.

:class:`ClosedLoop` is the loop of docs/architecture.md ("Where the closed loop is going"),
opened up: ``reset(scenarios, policies)`` starts one SUMO simulation with every scenario on its
own renamed copy of its track (:mod:`.batch_net`, each copy shifted along x by its ``dx``) and
returns the first :class:`Observation`; ``step(plans)`` is one decision step, one planning period
(``1 / LoopConfig.plan_rate_hz``): the plans (given, or made by the bound policies from the
features of the observation) are tracked for the period's physics sub-steps (``step_s``), and
the next :class:`Observation` comes back with the step's :class:`Events`. Gymnasium envs,
closed-loop training rollouts and falsification call it; :func:`.batch.run_batch` is a driver
that steps until every scenario has ended and builds the rollouts.

Each sub-step is the stage sequence of :func:`.runner.run_scenario`, track -> plant -> move in
SUMO -> step -> monitor, called ONCE for all running scenarios on arrays ``(n,)`` (the same stage
functions, with the array namespace :data:`.xp.ARRAYS`); sensing and planning happen once per
decision step on features ``(n, 9)``. What is per scenario by nature stays per scenario: the
camera and radar (each scenario's own road and noise generator), the walks along each lane,
SUMO's per-vehicle commands and reads. A scenario that ends (end of path, collision, off road,
a flag with ``stop_on_flag``, its time limit) leaves SUMO at that sub-step; the others go on.

Randomness: each scenario keeps its own ``np.random.Generator(scenario.seed)`` for the sensor
noise; SUMO's ``--seed`` is the first scenario's and the loop draws nothing from SUMO (speed mode
0, every speed commanded). ``reset(seed=s)`` gives scenario ``i`` the seed ``s + i`` (Gymnasium's
vector envs seed their sub-envs so).

Scope (step 3a): scripted leaders (or none) and plan-and-track egos, headless, no SSM output.
Traffic, sumo-gui, SSM output and kinematic (``pose_at``) egos run on ``run_scenario`` (step 3b
folds them in: docs/architecture.md).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Self

import numpy as np

from safeil_sumo.features import planner_features
from safeil_sumo.geometry import Polyline, PolylineStack, yaw_to_sumo_angle
from safeil_sumo.policy import Policy
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.batch_net import mixed_batch_net, prefixed
from safeil_sumo.sim.loop_types import LoopConfig, Rollout, Scenario
from safeil_sumo.sim.runner import (
    ApiFactory,
    _default_factory,
    _Log,
    _read_leader,
    finish,
    footprints_overlap,
    initial_state,
    insert_vehicles,
    lane_placeable,
    leader_speeds,
    max_steps,
    place_ego,
    start_positions,
    sumo_args,
    sumo_lane_position,
    xy_placement_is_unambiguous,
)
from safeil_sumo.sim.xp import ARRAYS

# empty space [m] between neighbouring copies of the track: beyond moveToXY's lane search
# radius, so each ego's search sees its own copy only (coincident copies made every moveToXY
# search all N copies: 0.2x the scalar loop at N = 32, measured)
SPACING_M = 1000.0
EXTERNAL = "external"  # the policy name in the summary of a scenario planned from outside
# end reasons of Events.terminated (the episode's own end) and Events.truncated (a limit)
TERMINAL_REASONS = ("collision", "off_road", "flag")
LIMIT_REASONS = ("completed", "timeout")
_COL = {name: i for i, name in enumerate(_Log.COLUMNS)}


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
    that has ended keeps the values of its last sub-step (its features: those of its last
    decision). Positions are the original track's (a copy's shift taken off)."""

    t: np.ndarray  # (N,) simulation time of the row's state [s]
    features: np.ndarray  # (N, 9) the planner's features (safeil_sumo.features) for the next plan
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
    # completed (end of path), collision, off_road, flag (stop_on_flag), timeout (time limit)
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
    """What is per scenario in a run: its road, noise, camera, leader and log."""

    def __init__(self, i: int, scenario: Scenario, policy: Policy | None, horizon: float,
                 loop: LoopConfig, vehicle: veh.VehicleParams, dx: float, log_width: int,
                 generation: int = 0) -> None:
        self.i, self.scenario, self.policy, self.horizon = i, scenario, policy, horizon
        # a restarted scenario's vehicles and routes get new SUMO ids (".<generation>")
        self.tag = f"_{i}" if generation == 0 else f"_{i}.{generation}"
        self.ego, self.leader_id = f"ego{self.tag}", f"leader{self.tag}"
        self.generation = generation
        self.k0 = 0  # the loop's physics step at which this scenario's step 0 runs
        self.dx = dx  # x offset [m] of this scenario's copy of the track in SUMO
        road = self.road = scenario.road
        self.lane = road.lanes[road.ego_lane]
        self.centre = self.lane.centre
        self.multi_piece = len(road.ego_pieces) > 1
        self.rng = np.random.default_rng(scenario.seed)
        self.n_max = max_steps(scenario, loop)
        self.s_ego0, self.s_lead0 = start_positions(scenario, vehicle)
        self.camera = sen.LaneCamera(road, scenario.sensors, self.s_ego0)
        self.state0 = initial_state(scenario, vehicle)
        self.has_leader = scenario.leader is not None
        self.lead_speeds = leader_speeds(scenario, self.n_max, loop.step_s)
        self.lead_scale = 1.0
        self.lead_cmd = math.nan  # the leader's last speed command to SUMO [m/s]
        self.leader = None  # (rear_xy, v_sumo, yaw, front_xy) as read after the last step
        self.lead_v = 0.0
        self.end_reason, self.error = "", ""
        self.rows = np.empty((self.n_max, log_width))  # the log, row k = step k; None: freed
        self.steps = 0  # rows filled
        self.lane_ids: dict[str, str] = {}  # SUMO lane id -> its id in this copy

    def add(self, api: sumo_api.SumoApi, vehicle: veh.VehicleParams) -> None:
        """Insert the ego and leader on this scenario's copy of the track; place the ego."""
        road, i = self.road, self.i
        ego_k, ego_lane, _, self.lead_scale = insert_vehicles(
            api, self.scenario, vehicle, self.ego, self.leader_id, partial(prefixed, i), self.tag)
        front = veh.front_bumper(self.state0, vehicle)
        if xy_placement_is_unambiguous(road, front, self.s_ego0):
            place_ego(api, self.state0, vehicle, self.ego, self.dx,
                      prefixed(i, road.route_edges[ego_k]), int(ego_lane))
        else:  # a closed course's other lap is nearer: keep the insertion on the ego's station
            api.vehicle.setSpeed(self.ego, veh.speed(self.state0))

    def read_leader(self, api: sumo_api.SumoApi, vehicle: veh.VehicleParams) -> None:
        """The leader after a step, in the original track's coordinates."""
        lead = _read_leader(api, vehicle, self.leader_id)
        if lead is not None and self.dx:
            (rx, ry), v, yaw, (fx, fy) = lead
            lead = (rx - self.dx, ry), v, yaw, (fx - self.dx, fy)
        self.leader = lead


def _lane_position(sc: _Scenario, s: float, advance_m: float) -> tuple[str, float]:
    """:func:`.runner.sumo_lane_position` on the scenario's copy of the track."""
    lane, pos = sumo_lane_position(sc.road, s, advance_m)
    copy = sc.lane_ids.get(lane)
    if copy is None:
        copy = sc.lane_ids[lane] = prefixed(sc.i, lane)
    return copy, pos


def check_scope(scenarios: Sequence[Scenario], policies: Sequence[Policy | None],
                loop: LoopConfig) -> None:
    """Refuse what the stepper does not run yet (step 3b): kinematic egos, sumo-gui, SSM
    output, traffic."""
    if any(getattr(p, "pose_at", None) is not None for p in policies):
        raise ValueError("the batched loop does not run kinematic (pose_at) egos: use "
                         "run_scenario")
    if loop.gui or loop.ssm_file is not None:
        raise ValueError("the batched loop runs headless without SSM output: use run_scenario")
    if any(sc.traffic is not None for sc in scenarios):
        raise ValueError("the batched loop runs scripted leaders only (no traffic): use "
                         "run_scenario")


class _Live:
    """The loop's state over the running scenarios: row ``j`` of every array is ``runs[j]``,
    scenario ``idx[j]`` of the reset."""

    def __init__(self, runs: list[_Scenario]) -> None:
        n = len(runs)
        self.runs = runs
        self.idx = np.arange(n)
        self.st = tuple(np.array(col, dtype=float) for col in zip(*(
            (r.state0.x, r.state0.y, r.state0.yaw, r.state0.vx, r.state0.vy, r.state0.yaw_rate,
             r.state0.steer, r.state0.drive_force) for r in runs)))  # the plant's state, (n,) each
        self.integral, self.prev_error = np.zeros(n), np.full(n, np.nan)  # PID memory
        self.t_plan = np.zeros(n)  # when the tracked plans were made [s]
        self.features = np.full((n, 9), np.nan)  # the last decision's features
        self.front = (np.full(n, np.nan), np.full(n, np.nan))  # front bumper then [m]
        self.feature_log = np.full((n, 8), np.nan)  # c0l..c2r, v_lead, d_lead as logged
        self.plan_log = np.full((n, 10), np.nan)  # the plan being tracked: time, pose, points
        self.target: ctl.BatchTarget | None = None
        self.controls: np.ndarray | None = None  # (n, 2) given accel, steer commands, or None
        self.c = _Fixed.of(runs)
        self.ego_seg = np.array([r.centre.segment_index(r.s_ego0) for r in runs])
        self.lead_seg = np.array([r.centre.segment_index(r.s_lead0) for r in runs])

    def take(self, keep: np.ndarray) -> None:
        """Keep the rows ``keep`` (indices) only: the others have ended."""
        self.runs = [self.runs[j] for j in keep]
        self.idx = self.idx[keep]
        self.c = _Fixed.of(self.runs) if self.runs else self.c
        self.st = tuple(col[keep] for col in self.st)
        self.integral, self.prev_error = self.integral[keep], self.prev_error[keep]
        self.t_plan, self.features = self.t_plan[keep], self.features[keep]
        self.front = (self.front[0][keep], self.front[1][keep])
        self.ego_seg, self.lead_seg = self.ego_seg[keep], self.lead_seg[keep]
        self.feature_log, self.plan_log = self.feature_log[keep], self.plan_log[keep]
        self.target = self.target.take(keep) if self.target is not None else None
        self.controls = self.controls[keep] if self.controls is not None else None

    def join(self, other: _Live) -> None:
        """Add ``other``'s rows (restarted scenarios, between two steps: no plan is being
        tracked), then order every row by its scenario index."""
        cat = np.concatenate
        self.runs = self.runs + other.runs
        self.idx = cat([self.idx, other.idx])
        self.st = tuple(cat([a, b]) for a, b in zip(self.st, other.st))
        self.integral = cat([self.integral, other.integral])
        self.prev_error = cat([self.prev_error, other.prev_error])
        self.t_plan, self.features = cat([self.t_plan, other.t_plan]), cat([self.features,
                                                                             other.features])
        self.front = (cat([self.front[0], other.front[0]]), cat([self.front[1], other.front[1]]))
        self.ego_seg, self.lead_seg = cat([self.ego_seg, other.ego_seg]), cat([self.lead_seg,
                                                                               other.lead_seg])
        self.feature_log = cat([self.feature_log, other.feature_log])
        self.plan_log = cat([self.plan_log, other.plan_log])
        self.target, self.controls = None, None
        self.take(np.argsort(self.idx, kind="stable"))


class ClosedLoop:
    """N scenarios side by side in one SUMO simulation, one decision step at a time.

    ``loop``, ``vehicle``, ``controller``: as for ``run_scenario`` (``loop`` headless, no SSM
    output). ``api_factory``: SUMO options -> the SUMO API (default: libsumo/traci per
    ``loop.backend``). ``log_columns``: the per-step log keeps only these columns of
    ``runner._Log.COLUMNS`` (None: all). ``net_dir``: where the run's net is written (default:
    the shared cache of :mod:`.batch_net`). ``clock``: filled with the time per stage.

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
        check_scope([], [], loop)
        columns = tuple(log_columns) if log_columns is not None else _Log.COLUMNS
        unknown = sorted(set(columns) - set(_Log.COLUMNS))
        if unknown:
            raise ValueError(f"unknown log column(s) {unknown}; the log has "
                             f"{', '.join(_Log.COLUMNS)}")
        self.loop, self.vehicle, self.controller = loop, vehicle, controller
        self.api_factory = api_factory or _default_factory(loop)
        self.net_dir, self.clock = net_dir, clock
        self.columns = columns
        self._col_idx = (None if columns == _Log.COLUMNS
                         else np.array([_Log.COLUMNS.index(c) for c in columns]))
        self._lap = clock.lap if clock is not None else _no_lap
        self._dt = loop.step_s
        self._plan_every = max(round(1.0 / (loop.plan_rate_hz * loop.step_s)), 1)
        self._plant = veh.Plant.of(vehicle, loop.step_s)
        self._api: sumo_api.SumoApi | None = None
        self._runs: list[_Scenario] = []  # every scenario of the last reset, in order
        self._live: _Live | None = None  # the running ones; None: nothing to step
        self._k = 0  # the next physics step
        self._last = np.empty((0, len(_Log.COLUMNS)))  # (N, 44) each scenario's latest row
        self._features = np.empty((0, 9))  # (N, 9) each scenario's latest features
        self._running = np.empty(0, dtype=bool)  # (N,)
        self._pending: list[_Scenario] = []  # restarted scenarios, started by the next step

    # -- the public loop ----------------------------------------------------------------------

    def reset(self, scenarios: Sequence[Scenario],
              policies: Policy | Sequence[Policy | None] | None = None,
              seed: int | None = None, horizon_s: float | None = None) -> Observation:
        """Start SUMO with ``scenarios`` at their initial states; the first observation.

        ``policies``: one planner for all, one per scenario, or None (then every ``step`` gets
        its plans); scenarios sharing a planner object are planned in one call. ``seed``: None
        keeps each scenario's seed, else scenario ``i`` gets ``seed + i``. ``horizon_s`` [s]: the
        plans' horizon (default: each policy's ``horizon``; needed without policies).
        Bad input raises ``ValueError`` before SUMO starts; an error after it ends every
        scenario with ``end_reason="error"``, closes SUMO and is raised.
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
        net, shifts = mixed_batch_net([sc.road.net_path for sc in scenarios], SPACING_M,
                                      self.net_dir)
        runs = [_Scenario(i, sc, p, horizon_s if horizon_s is not None else p.horizon,
                          self.loop, self.vehicle, dx, len(self.columns))
                for i, (sc, p, dx) in enumerate(zip(scenarios, pols, shifts))]
        args = sumo_args(scenarios[0], self.loop)
        args[args.index("-n") + 1] = str(net)
        self._api = self.api_factory(args)
        self._runs, self._k = runs, 0
        n = len(runs)
        self._last = np.full((n, len(_Log.COLUMNS)), np.nan)
        self._features = np.full((n, 9), np.nan)
        self._running = np.ones(n, dtype=bool)
        try:
            for r in runs:
                r.add(self._api, self.vehicle)
            self._api.simulation.step()
            for r in runs:
                if r.has_leader:
                    r.read_leader(self._api, self.vehicle)
                    r.lead_v = r.leader[1] / r.lead_scale if r.leader is not None else 0.0
            live = _Live(runs)
            self._lap("outside")
            self._look_at_start(live)
            self._sense(live)
        except Exception as exc:
            self._fail(exc)
            raise
        self._live = live
        return self._observation()

    def step(self, plans: np.ndarray | None = None,
             controls: np.ndarray | None = None) -> tuple[Observation, Events]:
        """One decision step: plan, then the planning period's physics sub-steps.

        ``plans`` ``(N, 3, 2)`` (or ``(N, 6)``) [m]: each scenario's three free B-spline control
        points in its ego frame at this decision (rows of ended scenarios are ignored); None:
        the bound policies plan from the observation's features. ``controls`` ``(N, 2)``
        instead: each ego's acceleration [m/s^2] and road-wheel steering angle [rad] commands,
        held over the period with no plan or tracker (the plant's actuators and limits still
        apply). Scenarios queued by :meth:`restart` start during the step (see there). Returns
        the observation after the step and what happened in it. An error ends every running
        scenario with ``end_reason="error"``, closes SUMO and is raised.
        """
        live = self._live
        if live is None:
            raise RuntimeError("no scenario is running: call reset first" if not self._runs
                               else "every scenario has ended: call reset")
        self._lap("outside")
        if plans is not None and controls is not None:
            raise ValueError("step takes plans or controls, not both")
        held = self._checked_controls(live, controls)
        # bad plans are refused; the run goes on
        given = self._checked_plans(live, plans) if held is None else None
        n_all = len(self._runs)
        ev = Events(np.zeros(n_all, bool), np.array([r.end_reason for r in self._runs], object),
                    np.zeros(n_all, bool), np.zeros(n_all, bool), np.zeros(n_all, bool),
                    np.zeros(n_all, int))
        pending, self._pending = self._pending, []
        try:
            self._plan(live, given, held)
            for sub in range(self._plan_every):
                if self.clock is not None:
                    self.clock.ego_steps += len(live.runs)
                last = sub == self._plan_every - 1
                if last and pending:  # inserted by this step's last SUMO step, as in reset
                    for r in pending:
                        r.add(self._api, self.vehicle)
                self._sub_step(live, self._k, last, ev)
                self._k += 1
                if not live.runs:
                    break
            if pending:
                self._start_restarted(live, pending, inserted=sub == self._plan_every - 1)
            if live.runs:
                self._sense(live)
            else:  # every scenario has ended: SUMO is no longer needed
                self._live = None
                self._close_api()
        except Exception as exc:
            self._fail(exc)
            raise
        return self._observation(), ev

    def restart(self, i: int, scenario: Scenario, policy: Policy | None = None,
                horizon_s: float | None = None) -> None:
        """Queue ``scenario`` to start again on scenario ``i``'s copy of the track, which has
        ended, while the others run on (a vector env's autoreset). It starts during the next
        :meth:`step`: its vehicles enter SUMO at that step's last SUMO step (as ``reset``
        inserts them before its one SUMO step), so the observation after that step has its
        initial state, sensed as ``reset`` senses it, and its first decision is the step after
        (it is not stepped in the step that starts it). Its time and log start at 0. Its road
        must be on the same net as scenario ``i``'s (the copy is of that net). ``ValueError``
        for a running scenario or another net; ``RuntimeError`` when SUMO has closed (every
        scenario had ended: call ``reset``)."""
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
        if horizon_s is None and policy is None:
            raise ValueError("a restart without a policy needs horizon_s, the plans' horizon [s]")
        self._runs[i] = r = _Scenario(
            i, scenario, policy, horizon_s if horizon_s is not None else policy.horizon,
            self.loop, self.vehicle, old.dx, len(self.columns), old.generation + 1)
        r.lane_ids = old.lane_ids
        self._pending.append(r)

    def _start_restarted(self, live: _Live, pending: list[_Scenario], inserted: bool) -> None:
        """The restarted scenarios after their insertion (done now with one SUMO step when
        every other scenario ended before the last one): read the leaders, look at the start
        and join the running ones; they are sensed with them."""
        if not inserted:
            for r in pending:
                r.add(self._api, self.vehicle)
            self._api.simulation.step()
            self._k += 1
        for r in pending:
            r.k0 = self._k
            if r.has_leader:
                r.read_leader(self._api, self.vehicle)
                r.lead_v = r.leader[1] / r.lead_scale if r.leader is not None else 0.0
        new = _Live(pending)
        new.idx = np.array([r.i for r in pending])
        self._look_at_start(new)
        self._running[new.idx] = True
        live.join(new)

    def rollout(self, i: int, wall_s: float = math.nan) -> Rollout:
        """Scenario ``i``'s log so far and its summary (``wall_s`` [s]: its share of the wall
        time, for the summary's rates)."""
        r = self._runs[i]
        if r.rows is None:
            raise ValueError(f"the log of scenario {i} has been freed")
        log = _Log.to_frame(r.rows[:r.steps].copy(), self.columns)
        name = r.policy.name if r.policy is not None else EXTERNAL
        return finish(r.scenario, log, r.end_reason or "running", r.error, wall_s, name)

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

    def __exit__(self, *exc) -> None:
        self.close()

    # -- the stages ---------------------------------------------------------------------------

    def _sense(self, live: _Live) -> None:
        """Camera and radar of every running scenario at its current state: the features of
        the next decision."""
        x, y, yaw, vx, vy = live.st[:5]
        v = np.hypot(vx, vy)
        d_front = self.vehicle.cog_to_front_bumper_m
        fx_, fy_ = x + d_front * np.cos(yaw), y + d_front * np.sin(yaw)
        # the camera: each scenario's lines, sampled per line and fitted all at once, then
        # each scenario's noise
        left, right = _camera_fits(live.runs, fx_, fy_, yaw)
        n = len(live.runs)
        v_lead, d_lead = np.empty(n), np.empty(n)
        for j, r in enumerate(live.runs):
            sen.add_lane_noise(left[j], right[j], r.scenario.sensors, r.rng)
            lead = r.leader
            radar = sen.radar_leader(np.array((fx_[j], fy_[j])), float(yaw[j]),
                                     None if lead is None else lead[0],
                                     0.0 if lead is None else r.lead_v, left[j], right[j],
                                     r.scenario.sensors, r.rng)
            v_lead[j], d_lead[j] = sen.leader_features(radar, float(v[j]), r.scenario.sensors)
        live.features = feats = planner_features(left, right, v, v_lead, d_lead)
        live.feature_log = feats[:, [0, 1, 2, 3, 4, 5, 7, 8]]
        live.front = (fx_, fy_)
        self._features[live.idx] = feats
        self._lap("sense")

    def _checked_plans(self, live: _Live, plans: np.ndarray | None) -> np.ndarray | None:
        """The running scenarios' rows ``(n, 3, 2)`` of ``plans`` (None: their policies
        plan); ``ValueError`` for plans of the wrong size or a missing policy."""
        if plans is None:
            if any(policy is None for policy, _ in live.c.planners):
                raise ValueError("a scenario without a policy needs its plans: step(plans)")
            return None
        given = np.asarray(plans, dtype=float)
        if given.size != 6 * len(self._runs):
            raise ValueError(f"plans must be ({len(self._runs)}, 3, 2) control points [m], got "
                             f"shape {given.shape}")
        return given.reshape(len(self._runs), 3, 2)[live.idx]

    def _checked_controls(self, live: _Live, controls: np.ndarray | None
                          ) -> np.ndarray | None:
        """The running scenarios' rows ``(n, 2)`` of ``controls`` (finite), or None."""
        if controls is None:
            return None
        given = np.asarray(controls, dtype=float)
        if given.shape != (len(self._runs), 2):
            raise ValueError(f"controls must be ({len(self._runs)}, 2): acceleration [m/s^2] "
                             f"and steering angle [rad], got shape {given.shape}")
        rows = given[live.idx]
        if not np.isfinite(rows).all():
            raise ValueError("controls must be finite")
        return rows

    def _plan(self, live: _Live, given: np.ndarray | None,
              controls: np.ndarray | None = None) -> None:
        """The plans of this decision (``given`` ``(n, 3, 2)``, or the policies'), prepared for
        tracking; or, with ``controls`` ``(n, 2)``, no plan: the commands are held instead."""
        n, t = len(live.runs), (self._k - live.c.k0) * self._dt  # each scenario's own time
        live.controls = controls
        if controls is not None:
            live.target = None
            live.t_plan = t.astype(float)
            live.plan_log = np.full((n, 10), np.nan)
            live.plan_log[:, 0] = live.t_plan
            self._lap("plan")
            return
        cps = given
        if cps is None:
            cps = np.empty((n, 3, 2))
            for policy, rows_of in live.c.planners:  # one call per planner object
                cps[rows_of] = np.asarray(policy.plan(live.features[rows_of]),
                                          float).reshape(-1, 3, 2)
        fx_, fy_ = live.front
        yaw = live.st[2]
        live.target = ctl.make_targets(cps, live.c.horizon, fx_, fy_, yaw)
        live.t_plan = t.astype(float)
        live.plan_log = np.column_stack([live.t_plan, fx_, fy_, yaw, cps.reshape(n, 6)])
        self._lap("plan")

    def _sub_step(self, live: _Live, k: int, last: bool, ev: Events) -> None:
        """Physics step ``k`` of every running scenario: drive, monitor, log, end."""
        moved = self._drive(live, k)
        rows, reason, departed, ttc_flag, hit = self._watch(live, k, moved)
        idx = live.idx
        ev.lane_departure[idx] |= departed
        ev.ttc_flag[idx] |= ttc_flag
        ev.collision[idx] |= hit
        ev.sub_steps[idx] += 1
        ended = reason != ""
        if last or ended.any():  # the observation: each scenario's latest row
            self._last[idx] = rows
        if ended.any():
            self._end(live, ended, reason, ev)
        self._lap("monitor")

    def _drive(self, live: _Live, k: int) -> tuple:
        """Track the plans, step the plant, find each front bumper on its lane, move the egos
        and command the leaders in SUMO, step SUMO."""
        c, dt, lap, vehicle = live.c, self._dt, self._lap, self.vehicle
        t = (k - c.k0) * dt  # (n,) each scenario's own time
        x, y, yaw, vx, vy, yaw_rate = live.st[:6]
        if live.controls is None:
            steer_cmd, accel_cmd, live.integral, live.prev_error = ctl.track_values(
                live.target, t - live.t_plan, x, y, yaw, vx, vy, yaw_rate, vehicle,
                live.integral, live.prev_error, self.controller, dt, ARRAYS)
        else:  # commands from outside (step(controls=...)), held over the period
            accel_cmd, steer_cmd = live.controls[:, 0].copy(), live.controls[:, 1].copy()
        throttle, brake = veh.pedals_from_accel_vx(accel_cmd, vx, vehicle, ARRAYS)
        lap("track")
        live.st = st = self._plant.step(live.st, steer_cmd, throttle, brake, ARRAYS)
        x, y, yaw, vx, vy = st[:5]
        v = np.hypot(vx, vy)
        d_front = vehicle.cog_to_front_bumper_m
        front_x, front_y = x + d_front * np.cos(yaw), y + d_front * np.sin(yaw)
        lap("plant")

        # where each front bumper is on its lane, then SUMO: move, command the leaders, step
        s, d, heading, live.ego_seg = c.lanes.project_near_many(front_x, front_y, live.ego_seg)
        lap("project")
        n = len(live.runs)
        inside = (lane_placeable(d, s, v * dt, 0.5 * c.lane_width, c.route_end).tolist()
                  if self.loop.ego_placement == "lane" else [False] * n)
        fxl, fyl, vl, sl = front_x.tolist(), front_y.tolist(), v.tolist(), s.tolist()
        api = self._api
        move_to, move_to_xy, set_speed = api.vehicle.moveTo, api.vehicle.moveToXY, api.vehicle.setSpeed
        for j, r in enumerate(live.runs):
            if inside[j]:
                move_to(r.ego, *_lane_position(r, sl[j], vl[j] * dt))
            else:
                move_to_xy(r.ego, "", -1, fxl[j] + r.dx, fyl[j], yaw_to_sumo_angle(float(yaw[j])),
                           2)
            set_speed(r.ego, vl[j])
            if r.leader is not None:
                v_cmd = r.lead_speeds[k - r.k0] * r.lead_scale
                if v_cmd != r.lead_cmd:  # SUMO keeps a commanded speed until the next command
                    set_speed(r.leader_id, v_cmd)
                    r.lead_cmd = v_cmd
        lap("sumo_move")
        api.simulation.step()
        colliding = set(api.simulation.getCollidingVehiclesIDList())
        hit = np.fromiter((r.ego in colliding for r in live.runs), bool, n)
        lap("sumo_step")
        return t, steer_cmd, accel_cmd, v, front_x, front_y, s, d, heading, hit, fxl, fyl

    def _watch(self, live: _Live, k: int, moved: tuple) -> tuple[np.ndarray, ...]:
        """Read the leaders, check footprints and run the monitors on the state at ``t + dt``;
        log the step. Returns the full log rows ``(n, 44)``, each row's end reason (``""``:
        goes on; in ``run_scenario``'s order) and the lane-departure, TTC and collision flags
        ``(n,)``."""
        t, steer_cmd, accel_cmd, v, front_x, front_y, s, d, heading, hit, fxl, fyl = moved
        c, st, n, vehicle = live.c, live.st, len(live.runs), self.vehicle
        length, width = vehicle.length_m, vehicle.width_m
        # the leaders, read per scenario and projected at once (NaN: none)
        lead_x, lead_y, v_lead_true = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        api = self._api
        for j, r in enumerate(live.runs):
            if r.leader is not None:
                r.read_leader(api, vehicle)
                if r.leader is not None:
                    (lead_x[j], lead_y[j]), v_sumo = r.leader[0], r.leader[1]
                    v_lead_true[j] = r.lead_v = v_sumo / r.lead_scale
        has_lead = ~np.isnan(v_lead_true)
        self._lap("sumo_read")
        s_rear, _, _, live.lead_seg = c.lanes.project_near_many(lead_x, lead_y, live.lead_seg)
        gap = np.where(has_lead, s_rear - s, np.inf)
        yaw = st[2]
        for j in np.flatnonzero(has_lead & ((gap < 2.0 * length) | c.multi_piece)):
            r = live.runs[j]
            if r.multi_piece:  # the next command's scale: the SUMO lane under its front
                r.lead_scale = r.road.piece_at(s_rear[j] + length).scale
            if gap[j] < 2.0 * length and not hit[j]:
                hit[j] = footprints_overlap((fxl[j], fyl[j]), float(yaw[j]), vehicle, r.leader,
                                            length, width)
        self._lap("project")

        d_min, d_max, departed, ttc, ttc_flag, fraction = _monitors(
            c, vehicle, yaw, heading, s, d, v, gap, v_lead_true, has_lead)
        rows = np.column_stack([
            t + self._dt, st[0], st[1], yaw, v, st[4], st[5], st[6], front_x,
            front_y, steer_cmd, accel_cmd, s, d, d_min, d_max, live.feature_log, lead_x, lead_y,
            v_lead_true, gap, ttc, departed, ttc_flag, hit, fraction, live.plan_log,
            np.where(has_lead, 0.0, np.nan),
        ])
        logged = rows if self._col_idx is None else rows[:, self._col_idx]
        for j, r in enumerate(live.runs):
            r.rows[k - r.k0] = logged[j]
            r.steps = k - r.k0 + 1
        loop = self.loop
        reason = np.select(
            [s >= c.path_end, hit, np.abs(d) > 0.5 * c.lane_width + loop.offroad_stop_m,
             (departed | ttc_flag) & loop.stop_on_flag, k + 1 - c.k0 >= c.n_max],
            ["completed", "collision", "off_road", "flag", "timeout"], "")
        return rows, reason, departed, ttc_flag, hit

    def _end(self, live: _Live, ended: np.ndarray, reason: np.ndarray, ev: Events) -> None:
        """The scenarios ``ended`` (rows) leave SUMO and the loop."""
        for j in np.flatnonzero(ended):
            r = live.runs[j]
            r.end_reason = str(reason[j])
            ev.ended[r.i], ev.end_reason[r.i] = True, r.end_reason
            self._running[r.i] = False
            for vid in (r.ego, r.leader_id) if r.has_leader and r.leader else (r.ego,):
                with suppress(Exception):  # it may have left the network already
                    self._api.vehicle.remove(vid)
        live.take(np.flatnonzero(~ended))

    def _look_at_start(self, live: _Live) -> None:
        """The monitors' view of the initial states, for reset's observation (footprint
        overlap as the collision; nothing the loop keeps is changed)."""
        c, vehicle = live.c, self.vehicle
        x, y, yaw, vx, vy = live.st[:5]
        v = np.hypot(vx, vy)
        d_front = vehicle.cog_to_front_bumper_m
        front_x, front_y = x + d_front * np.cos(yaw), y + d_front * np.sin(yaw)
        s, d, heading, _ = c.lanes.project_near_many(front_x, front_y, live.ego_seg)
        n = len(live.runs)
        lead_x, lead_y, v_lead = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        for j, r in enumerate(live.runs):
            if r.leader is not None:
                (lead_x[j], lead_y[j]), v_lead[j] = r.leader[0], r.lead_v
        has_lead = ~np.isnan(v_lead)
        s_rear = c.lanes.project_near_many(lead_x, lead_y, live.lead_seg)[0]
        gap = np.where(has_lead, s_rear - s, np.inf)
        hit = np.zeros(n, dtype=bool)
        for j in np.flatnonzero(has_lead & (gap < 2.0 * vehicle.length_m)):
            hit[j] = footprints_overlap((front_x[j], front_y[j]), float(yaw[j]), vehicle,
                                        live.runs[j].leader, vehicle.length_m, vehicle.width_m)
        _, _, departed, ttc, ttc_flag, fraction = _monitors(
            c, vehicle, yaw, heading, s, d, v, gap, v_lead, has_lead)
        for name, values in (("t", 0.0), ("x", x), ("y", y), ("yaw", yaw), ("v", v), ("s", s),
                             ("d", d), ("gap", gap), ("ttc", ttc), ("leader_v", v_lead),
                             ("path_fraction", fraction), ("lane_departure", departed),
                             ("ttc_flag", ttc_flag), ("collision", hit)):
            self._last[live.idx, _COL[name]] = values

    def _observation(self) -> Observation:
        last = self._last

        def col(name: str, dtype=float) -> np.ndarray:
            return last[:, _COL[name]].astype(dtype)  # a copy

        return Observation(
            col("t"), self._features.copy(), col("x"), col("y"), col("yaw"), col("v"), col("s"),
            col("d"), col("gap"), col("ttc"), col("leader_v"), col("path_fraction"),
            col("lane_departure", bool), col("ttc_flag", bool), col("collision", bool),
            self._running.copy())

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
    if policies is None or hasattr(policies, "plan"):
        return [policies] * n
    out = list(policies)
    if len(out) != n:
        raise ValueError(f"{n} scenarios but {len(out)} policies")
    return out


def _monitors(c: _Fixed, vehicle: veh.VehicleParams, yaw, heading, s, d, v, gap, v_lead,
              has_lead) -> tuple[np.ndarray, ...]:
    """The monitors on arrays ``(n,)``: ``d_min, d_max`` [m] (the footprint's lateral extent),
    lane departure, TTC [s], TTC flag, path completed [-]."""
    heading_err = (yaw - heading + math.pi) % (2.0 * math.pi) - math.pi
    d_min, d_max = mon.footprint_offset_range(d, heading_err, vehicle.length_m, vehicle.width_m,
                                              ARRAYS)
    departed = mon.lane_departure(d_min, d_max, c.lane_width, c.margin, ARRAYS)
    ttc = np.where(has_lead, mon.time_to_collision(gap, v, v_lead, ARRAYS), np.inf)
    ttc_flag = ttc <= c.ttc_threshold
    fraction = mon.path_completed(s, c.path_start, c.path_end, ARRAYS)
    return d_min, d_max, departed, ttc, ttc_flag, fraction


def _camera_fits(live: list[_Scenario], x: np.ndarray, y: np.ndarray, yaw: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The camera's left and right line fits ``(n, 4)`` (before noise) of every scenario: the
    lines each camera sees, then one sampling and one stacked fit per (line, camera setting)."""
    fits = np.empty((2 * len(live), 4))  # row 2j: scenario j's left line, 2j + 1: its right
    xl, yl = x.tolist(), y.tolist()
    groups: dict[tuple[int, int], tuple] = {}  # -> (line, camera setting, rows, arc lengths)
    for j, r in enumerate(live):
        lane, s_left, s_right = r.camera.lane_stations(xl[j], yl[j])
        config = r.scenario.sensors
        for row, line, s0 in ((2 * j, lane.left_boundary, s_left),
                              (2 * j + 1, lane.right_boundary, s_right)):
            key = (id(line), config.view_range_m, config.view_samples)  # what sampling reads
            g = groups.setdefault(key, (line, config, [], []))
            g[2].append(row)
            g[3].append(s0)
    # sampled per group, fitted in one stacked fit per number of samples (scenarios on many
    # roads have many groups; a fit is per point set, the same alone or stacked)
    points: dict[int, list[tuple[list[int], np.ndarray, np.ndarray]]] = {}
    for line, config, rows, s0 in groups.values():
        cars = np.array(rows) // 2
        px, py = sen.ego_points_many(line, np.array(s0), x[cars], y[cars], yaw[cars], config)
        points.setdefault(px.shape[1], []).append((rows, px, py))
    for parts in points.values():
        if len(parts) == 1:
            rows, px, py = parts[0]
        else:
            rows = [row for part in parts for row in part[0]]
            px, py = np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])
        fits[rows] = sen.polyfit3_batch(px, py)
    return fits[0::2], fits[1::2]


def _groups(items: list, key: Callable) -> list[tuple[object, np.ndarray | slice]]:
    """``(object, rows)`` for each distinct ``key(item)`` object (compared by identity: lanes
    and planners need not hash), in order; one group's rows are ``slice(None)``."""
    groups: dict[int, tuple[object, list[int]]] = {}
    for j, item in enumerate(items):
        obj = key(item)
        groups.setdefault(id(obj), (obj, []))[1].append(j)
    if len(groups) == 1:
        return [(next(iter(groups.values()))[0], slice(None))]
    return [(obj, np.array(rows)) for obj, rows in groups.values()]


@dataclass(frozen=True)
class _Fixed:
    """What stays fixed during a run, over the running scenarios (rebuilt when one ends)."""

    lane_width: np.ndarray  # (n,) [m]
    margin: np.ndarray  # (n,) lane monitor tolerance [m]
    ttc_threshold: np.ndarray  # (n,) [s]
    path_start: np.ndarray  # (n,) [m]
    path_end: np.ndarray  # (n,) [m]
    route_end: np.ndarray  # (n,) the end of SUMO's route along the ego lane [m]
    n_max: np.ndarray  # (n,) steps
    horizon: np.ndarray  # (n,) plan horizon [s]
    multi_piece: np.ndarray  # (n,) bool: a route of several SUMO lanes
    # each row's ego lane centre: the one polyline, or several (scenarios on different
    # roads) walked at once on their stack; NaN points give NaN and keep their segment
    lanes: Polyline | PolylineStack
    planners: list  # (planner or None, rows): one plan call each
    k0: np.ndarray  # (n,) int: the loop's physics step of each scenario's step 0 (restarts)

    @staticmethod
    def of(live: list[_Scenario]) -> _Fixed:
        def col(get, dtype=float) -> np.ndarray:
            return np.array([get(r) for r in live], dtype=dtype)

        return _Fixed(
            col(lambda r: r.lane.width), col(lambda r: r.scenario.monitors.lane_margin_m),
            col(lambda r: r.scenario.monitors.ttc_threshold_s),
            col(lambda r: r.road.path_start_s), col(lambda r: r.road.path_end_s),
            col(lambda r: r.road.ego_pieces[-1].s1),
            col(lambda r: r.n_max, int), col(lambda r: r.horizon),
            col(lambda r: r.multi_piece, bool), _lanes(live),
            _groups(live, lambda r: r.policy), col(lambda r: r.k0, int))


def _lanes(live: list[_Scenario]) -> Polyline | PolylineStack:
    """What projects each running scenario's points on its own ego lane centre."""
    groups = _groups(live, lambda r: r.centre)
    if len(groups) == 1:
        return groups[0][0]
    line_of = np.empty(len(live), dtype=int)
    for k, (_, rows) in enumerate(groups):
        line_of[rows] = k
    return PolylineStack([line for line, _ in groups], line_of)

