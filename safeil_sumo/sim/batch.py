"""N scenarios in ONE SUMO simulation: :func:`run_batch`, the closed loop over arrays.

Each scenario drives its own renamed copy of its track (:mod:`.batch_net`: scenarios may be
on different networks, each copy shifted along x by its ``dx``); one ``simulationStep`` moves
all of them. The loop is :func:`safeil_sumo.sim.runner.run_scenario`'s
sequence of stages, sense -> plan -> track -> plant -> move in SUMO -> step -> monitor, with
the per-step stages called ONCE for all running scenarios on arrays ``(N,)`` (the same stage
functions as the scalar loop, with the array namespace :data:`.xp.ARRAYS`) and the planner
called once per plan step on features ``(N, 9)``. What is per scenario by nature stays per
scenario: the camera and radar (each scenario's own road and noise generator), the walks
along each lane, SUMO's per-vehicle commands and reads.

Same answers as ``run_scenario`` (tests/test_batch.py): the same flags, flag times, path
completed and end reasons, trajectories equal to round-off (numpy's ``cos``/``sin`` may differ
from libm's by an ulp). SUMO has one ``--seed`` per simulation; the loop draws no random
number from SUMO (speed mode 0, every speed commanded) and each scenario keeps its own
``np.random.Generator(scenario.seed)`` for the sensor noise.

Not here (use ``run_scenario``): traffic, sumo-gui, SSM output, kinematic (``pose_at``) egos.
An exception inside the loop ends every scenario still running with ``end_reason="error"``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from safeil_sumo.features import planner_features
from safeil_sumo.geometry import Polyline, PolylineStack, yaw_to_sumo_angle
from safeil_sumo.policy import Policy
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.batch_net import mixed_batch_net, prefixed
from safeil_sumo.sim.runner import (
    ApiFactory,
    LoopConfig,
    Rollout,
    Scenario,
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


class StageClock:
    """Wall time [s] per stage of a batched run, summed over its steps (pass one to
    :func:`run_batch`; the bench reports it per ego-step)."""

    STAGES = ("sense", "plan", "track", "plant", "project", "sumo_move", "sumo_step",
              "sumo_read", "monitor")

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


class _Scenario:
    """What is per scenario in a batch: its road, noise, camera, leader and log."""

    def __init__(self, i: int, scenario: Scenario, policy: Policy, loop: LoopConfig,
                 vehicle: veh.VehicleParams, dx: float, log_width: int) -> None:
        self.i, self.scenario, self.policy = i, scenario, policy
        self.ego, self.leader_id = f"ego_{i}", f"leader_{i}"
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
        self.rows = np.empty((self.n_max, log_width))  # the log, row k = step k
        self.steps = 0  # rows filled
        self.rollout: Rollout | None = None
        self.lane_ids: dict[str, str] = {}  # SUMO lane id -> its id in this copy

    def add(self, api: sumo_api.SumoApi, vehicle: veh.VehicleParams) -> None:
        """Insert the ego and leader on this scenario's copy of the track; place the ego."""
        road, i = self.road, self.i
        ego_k, ego_lane, _, self.lead_scale = insert_vehicles(
            api, self.scenario, vehicle, self.ego, self.leader_id, partial(prefixed, i), f"_{i}")
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


def run_batch(
    scenarios: Sequence[Scenario],
    policy: Policy | Sequence[Policy],
    loop: LoopConfig = LoopConfig(),
    vehicle: veh.VehicleParams = veh.VehicleParams(),
    controller: ctl.ControllerParams = ctl.ControllerParams(),
    api_factory: ApiFactory | None = None,
    on_done: Callable[[int, Rollout], None] | None = None,
    clock: StageClock | None = None,
    keep_logs: bool = True,
    log_columns: Sequence[str] | None = None,
    net_dir: Path | None = None,
) -> list[Rollout]:
    """Run ``scenarios`` closed-loop side by side in one SUMO simulation; their rollouts in
    order. ``policy`` is one planner for all or one per scenario (scenarios sharing a planner
    object are planned in one call). ``on_done(i, rollout)`` is called as soon as scenario ``i`` ends (a sweep saves it
    then). ``clock``: filled with the time per stage. ``keep_logs=False``: the returned
    rollouts have empty logs (each log is freed once ``on_done`` has seen it: a sweep's memory
    is then the running scenarios' logs only). ``log_columns``: log only these columns (e.g.
    ``runner.SUMMARY_COLUMNS``, all a summary needs: a quarter of the memory per scenario).
    ``net_dir``: where the batch's net is written (default: the shared cache of
    :mod:`.batch_net`).

    Scenarios may be on different networks (each on its own copy of its net); every one must
    have a scripted leader or none (no traffic) and a planner that is no kinematic (``pose_at``)
    ego; ``loop`` must not ask for sumo-gui or SSM output. SUMO's ``--seed`` is the first
    scenario's.
    """
    if not scenarios:
        return []
    policies = ([policy] * len(scenarios) if hasattr(policy, "plan") else list(policy))
    if len(policies) != len(scenarios):
        raise ValueError(f"{len(scenarios)} scenarios but {len(policies)} policies")
    _check(scenarios, policies, loop)
    columns = tuple(log_columns) if log_columns is not None else _Log.COLUMNS
    unknown = sorted(set(columns) - set(_Log.COLUMNS))
    if unknown:
        raise ValueError(f"unknown log column(s) {unknown}; the log has {', '.join(_Log.COLUMNS)}")
    col_idx = None if columns == _Log.COLUMNS else np.array([_Log.COLUMNS.index(c) for c in columns])
    net, shifts = mixed_batch_net([sc.road.net_path for sc in scenarios], SPACING_M, net_dir)
    runs = [_Scenario(i, sc, p, loop, vehicle, dx, len(columns))
            for i, (sc, p, dx) in enumerate(zip(scenarios, policies, shifts))]
    args = sumo_args(scenarios[0], loop)
    args[args.index("-n") + 1] = str(net)
    api = (api_factory or _default_factory(loop))(args)
    wall0 = time.perf_counter()

    def done(r: _Scenario) -> None:
        """The rollout of a scenario that has ended; its log buffer is freed."""
        # the batch's wall time so far, shared out by steps (what one scenario cost of it)
        steps_all = max(sum(q.steps for q in runs), 1)
        wall = (time.perf_counter() - wall0) * r.steps / steps_all
        log = _Log.to_frame(r.rows[:r.steps].copy(), columns)
        rollout = finish(r.scenario, log, r.end_reason or "timeout", r.error, wall, r.policy.name)
        r.rows = None
        if on_done is not None:
            on_done(r.i, rollout)
        r.rollout = rollout if keep_logs else Rollout(rollout.log.iloc[:0], rollout.summary)

    try:
        for r in runs:
            r.add(api, vehicle)
        api.simulation.step()
        for r in runs:
            if r.has_leader:
                r.read_leader(api, vehicle)
                r.lead_v = r.leader[1] / r.lead_scale if r.leader is not None else 0.0
        # one BLAS thread: the batch's matrices are small, and a sweep already runs one worker
        # per core (OpenBLAS's own threads made 2 workers at batch 256 run 2.1x slower)
        with threadpool_limits(limits=1, user_api="blas"):
            _loop(api, runs, loop, vehicle, controller, done, clock, col_idx)
    except Exception as exc:  # every scenario still running ends with the reason
        for r in runs:
            if not r.end_reason:
                r.end_reason, r.error = "error", f"{type(exc).__name__}: {exc}"
    finally:
        try:
            api.close()
        except Exception:
            pass
    for r in runs:
        if r.rollout is None:  # the loop failed before it ended
            done(r)
    return [r.rollout for r in runs]


def _check(scenarios: Sequence[Scenario], policies: Sequence[Policy], loop: LoopConfig) -> None:
    if any(getattr(p, "pose_at", None) is not None for p in policies):
        raise ValueError("run_batch does not run kinematic (pose_at) egos: use run_scenario")
    if loop.gui or loop.ssm_file is not None:
        raise ValueError("run_batch runs headless without SSM output: use run_scenario")
    if any(sc.traffic is not None for sc in scenarios):
        raise ValueError("run_batch runs scripted leaders only (no traffic): use run_scenario")


def _loop(api: sumo_api.SumoApi, runs: list[_Scenario], loop: LoopConfig,
          vehicle: veh.VehicleParams, controller: ctl.ControllerParams,
          done: Callable[[_Scenario], None], clock: StageClock | None = None,
          col_idx: np.ndarray | None = None) -> None:
    """The stages over arrays of the running scenarios, until every one has ended: each step
    writes the log row (its columns ``col_idx``; None: all) of every running scenario;
    ``done(scenario)`` as one ends."""
    dt = loop.step_s
    plan_every = max(int(round(1.0 / (loop.plan_rate_hz * dt))), 1)
    on_lane = loop.ego_placement == "lane"
    plant = veh.Plant.of(vehicle, dt)
    d_front = vehicle.cog_to_front_bumper_m
    length, width = vehicle.length_m, vehicle.width_m
    move_to_xy, move_to, set_speed = api.vehicle.moveToXY, api.vehicle.moveTo, api.vehicle.setSpeed
    sim_step, colliding_ids = api.simulation.step, api.simulation.getCollidingVehiclesIDList

    live = list(runs)  # the running scenarios; row j of every array below is live[j]
    st = tuple(np.array(col, dtype=float) for col in zip(*(
        (r.state0.x, r.state0.y, r.state0.yaw, r.state0.vx, r.state0.vy, r.state0.yaw_rate,
         r.state0.steer, r.state0.drive_force) for r in live)))
    n = len(live)
    integral, prev_error = np.zeros(n), np.full(n, np.nan)  # PID memory
    t_plan = np.zeros(n)
    feature_log = np.full((n, 8), np.nan)  # c0l..c2r, v_lead, d_lead as logged
    plan_log = np.full((n, 10), np.nan)  # the plan being tracked: time, pose, control points
    target = None
    c = _Fixed.of(live)
    ego_seg = np.array([r.centre.segment_index(r.s_ego0) for r in live])
    lead_seg = np.array([r.centre.segment_index(r.s_lead0) for r in live])
    lap = clock.lap if clock is not None else _no_lap
    for k in range(c.n_max.max()):  # every scenario ends by its n_max (timeout)
        lap("monitor")  # the end checks of the step before
        if clock is not None:
            clock.ego_steps += n
        t = k * dt
        if k % plan_every == 0:  # sense and plan, all scenarios at once
            x, y, yaw, vx, vy = st[:5]
            v = np.hypot(vx, vy)
            fx_, fy_ = x + d_front * np.cos(yaw), y + d_front * np.sin(yaw)
            # the camera: each scenario's lines, sampled per line and fitted all at once, then
            # each scenario's noise
            left, right = _camera_fits(live, fx_, fy_, yaw)
            v_lead, d_lead = np.empty(n), np.empty(n)
            for j, r in enumerate(live):
                sen.add_lane_noise(left[j], right[j], r.scenario.sensors, r.rng)
                lead = r.leader
                radar = sen.radar_leader(np.array((fx_[j], fy_[j])), float(yaw[j]),
                                         None if lead is None else lead[0],
                                         0.0 if lead is None else r.lead_v, left[j], right[j],
                                         r.scenario.sensors, r.rng)
                v_lead[j], d_lead[j] = sen.leader_features(radar, float(v[j]),
                                                           r.scenario.sensors)
            feats = planner_features(left, right, v, v_lead, d_lead)
            feature_log = feats[:, [0, 1, 2, 3, 4, 5, 7, 8]]
            lap("sense")
            plans = np.empty((n, 3, 2))
            for policy, rows_of in c.planners:  # one call per planner object
                plans[rows_of] = np.asarray(policy.plan(feats[rows_of]), float).reshape(-1, 3, 2)
            target = ctl.make_targets(plans, c.horizon, fx_, fy_, yaw)
            t_plan = np.full(n, t)
            plan_log = np.column_stack([t_plan, fx_, fy_, yaw, plans.reshape(n, 6)])
            lap("plan")

        # track and drive, all scenarios at once
        x, y, yaw, vx, vy, yaw_rate = st[:6]
        steer_cmd, accel_cmd, integral, prev_error = ctl.track_values(
            target, t - t_plan, x, y, yaw, vx, vy, yaw_rate, vehicle, integral, prev_error,
            controller, dt, ARRAYS)
        throttle, brake = veh.pedals_from_accel_vx(accel_cmd, vx, vehicle, ARRAYS)
        lap("track")
        st = plant.step(st, steer_cmd, throttle, brake, ARRAYS)
        x, y, yaw, vx, vy = st[:5]
        v = np.hypot(vx, vy)
        front_x, front_y = x + d_front * np.cos(yaw), y + d_front * np.sin(yaw)
        lap("plant")

        # where each front bumper is on its lane, then SUMO: move, command the leaders, step
        s, d, heading, ego_seg = c.lanes.project_near_many(front_x, front_y, ego_seg)
        lap("project")
        inside = (lane_placeable(d, s, v * dt, 0.5 * c.lane_width, c.route_end).tolist()
                  if on_lane else [False] * n)
        fxl, fyl, vl, sl = front_x.tolist(), front_y.tolist(), v.tolist(), s.tolist()
        for j, r in enumerate(live):
            if inside[j]:
                move_to(r.ego, *_lane_position(r, sl[j], vl[j] * dt))
            else:
                move_to_xy(r.ego, "", -1, fxl[j] + r.dx, fyl[j], yaw_to_sumo_angle(float(yaw[j])),
                           2)
            set_speed(r.ego, vl[j])
            if r.leader is not None:
                v_cmd = r.lead_speeds[k] * r.lead_scale
                if v_cmd != r.lead_cmd:  # SUMO keeps a commanded speed until the next command
                    set_speed(r.leader_id, v_cmd)
                    r.lead_cmd = v_cmd
        lap("sumo_move")
        sim_step()
        colliding = set(colliding_ids())
        hit = np.fromiter((r.ego in colliding for r in live), bool, n)
        lap("sumo_step")

        # the leaders, read per scenario and projected at once (NaN: none)
        lead_x, lead_y, v_lead_true = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        for j, r in enumerate(live):
            if r.leader is not None:
                r.read_leader(api, vehicle)
                if r.leader is not None:
                    (lead_x[j], lead_y[j]), v_sumo = r.leader[0], r.leader[1]
                    v_lead_true[j] = r.lead_v = v_sumo / r.lead_scale
        has_lead = ~np.isnan(v_lead_true)
        lap("sumo_read")
        s_rear, _, _, lead_seg = c.lanes.project_near_many(lead_x, lead_y, lead_seg)
        gap = np.where(has_lead, s_rear - s, np.inf)
        for j in np.flatnonzero(has_lead & ((gap < 2.0 * length) | c.multi_piece)):
            r = live[j]
            if r.multi_piece:  # the next command's scale: the SUMO lane under its front
                r.lead_scale = r.road.piece_at(s_rear[j] + length).scale
            if gap[j] < 2.0 * length and not hit[j]:
                hit[j] = footprints_overlap((fxl[j], fyl[j]), float(yaw[j]), vehicle, r.leader,
                                            length, width)

        lap("project")
        # monitors on the state at t + dt, all at once
        heading_err = (yaw - heading + math.pi) % (2.0 * math.pi) - math.pi
        d_min, d_max = mon.footprint_offset_range(d, heading_err, length, width, ARRAYS)
        departed = mon.lane_departure(d_min, d_max, c.lane_width, c.margin, ARRAYS)
        ttc = np.where(has_lead, mon.time_to_collision(gap, v, v_lead_true, ARRAYS), np.inf)
        ttc_flag = ttc <= c.ttc_threshold
        fraction = mon.path_completed(s, c.path_start, c.path_end, ARRAYS)
        rows = np.column_stack([
            np.full(n, t + dt), x, y, yaw, v, vy, st[5], st[6], front_x, front_y, steer_cmd,
            accel_cmd, s, d, d_min, d_max, feature_log, lead_x, lead_y, v_lead_true, gap, ttc,
            departed, ttc_flag, hit, fraction, plan_log, np.where(has_lead, 0.0, np.nan),
        ])
        if col_idx is not None:
            rows = rows[:, col_idx]
        for j, r in enumerate(live):
            r.rows[k] = rows[j]
            r.steps = k + 1

        # ends, in run_scenario's order
        reason = np.select(
            [s >= c.path_end, hit, np.abs(d) > 0.5 * c.lane_width + loop.offroad_stop_m,
             (departed | ttc_flag) & loop.stop_on_flag, k + 1 >= c.n_max],
            ["completed", "collision", "off_road", "flag", "timeout"], "")
        ended = reason != ""
        if ended.any():
            for j in np.flatnonzero(ended):
                r = live[j]
                r.end_reason = str(reason[j])
                for vid in (r.ego, r.leader_id) if r.has_leader and r.leader else (r.ego,):
                    try:
                        api.vehicle.remove(vid)
                    except Exception:  # noqa: BLE001  # it has already left the network
                        pass
                done(r)
            keep = np.flatnonzero(~ended)
            live = [live[j] for j in keep]
            if not live:
                return
            n, c = len(live), _Fixed.of(live)
            st = tuple(col[keep] for col in st)
            integral, prev_error, t_plan = integral[keep], prev_error[keep], t_plan[keep]
            ego_seg, lead_seg = ego_seg[keep], lead_seg[keep]
            feature_log, plan_log = feature_log[keep], plan_log[keep]
            target = target.take(keep)


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
    planners: list  # (planner, rows): one plan call each

    @staticmethod
    def of(live: list[_Scenario]) -> _Fixed:
        def col(get, dtype=float) -> np.ndarray:
            return np.array([get(r) for r in live], dtype=dtype)

        return _Fixed(
            col(lambda r: r.lane.width), col(lambda r: r.scenario.monitors.lane_margin_m),
            col(lambda r: r.scenario.monitors.ttc_threshold_s),
            col(lambda r: r.road.path_start_s), col(lambda r: r.road.path_end_s),
            col(lambda r: r.road.ego_pieces[-1].s1),
            col(lambda r: r.n_max, int), col(lambda r: r.policy.horizon),
            col(lambda r: r.multi_piece, bool), _lanes(live),
            _groups(live, lambda r: r.policy))


def _lanes(live: list[_Scenario]) -> Polyline | PolylineStack:
    """What projects each running scenario's points on its own ego lane centre."""
    groups = _groups(live, lambda r: r.centre)
    if len(groups) == 1:
        return groups[0][0]
    line_of = np.empty(len(live), dtype=int)
    for k, (_, rows) in enumerate(groups):
        line_of[rows] = k
    return PolylineStack([line for line, _ in groups], line_of)
