"""The closed loop: SUMO scenario + sensors + policy + tracking controller + vehicle plant + monitors.

Every step (``step_s``, 0.01 s by default): the controller tracks the current plan, our vehicle
plant advances the ego, the ego is moved in SUMO (``moveTo`` on its lane while the front bumper
is inside it, else ``moveToXY(keepRoute=2)``: ``LoopConfig.ego_placement``) + ``setSpeed``,
the leader gets its profile speed, SUMO steps, and the monitors log TTC, lane departure and
collisions. At ``plan_rate_hz`` the camera and radar are read and the policy re-plans.
The runner receives the SUMO API (libsumo, traci or a fake) through :mod:`sumo_api`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from safeil_sumo.features import planner_features
from safeil_sumo.geometry import (
    rectangle_corners,
    rectangles_overlap,
    sumo_angle_to_yaw,
    yaw_to_sumo_angle,
)
from safeil_sumo.policy import Policy
from safeil_sumo.scenarios.road import Road
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim import traffic as trf
from safeil_sumo.sim import vehicle as veh

# the loop's types, re-exported: they were defined here before
from safeil_sumo.sim.loop_types import (  # noqa: F401
    EGO_PLACEMENTS,
    GUI_SCREENSHOT_AT_S,
    LoopConfig,
    Rollout,
    Scenario,
)

EGO_ID = "ego"
LEADER_ID = "leader"
ROUTE_ID = "r_ego"
LEADER_ROUTE_ID = "r_leader"  # the route's edges from the leader's first edge (when not the ego's)
GUI_VIEW_WIDTH_M = 150.0  # sumo-gui's view width around the ego: it and a leader 50 m ahead [m]
# [m] two projections of one point on a lane this close along it are the same pass of the road
# (xy_placement_is_unambiguous)
SAME_STATION_M = 1.0
ApiFactory = Callable[[Sequence[str]], sumo_api.SumoApi]


def sumo_args(scenario: Scenario, loop: LoopConfig) -> list[str]:
    """SUMO command-line options of a run (collision detection for a remote-controlled ego:
    docs/architecture.md, "Facts about SUMO")."""
    args = [
        "-n", str(scenario.road.net_path),
        "--step-length", f"{loop.step_s}",
        "--seed", str(scenario.seed % 2**31),  # SUMO takes a signed 32-bit seed
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--collision.action", "warn",
        "--collision.mingap-factor", "0",
        "--time-to-teleport", "-1",
    ]
    if scenario.traffic is not None:
        args += scenario.traffic.sumo_args()
    if loop.ssm_file is not None:
        args += [
            "--device.ssm.explicit", EGO_ID,
            "--device.ssm.measures", "TTC DRAC PET",
            "--device.ssm.file", str(loop.ssm_file),
            "--device.ssm.trajectories", "true",
        ]
    return args


def _default_factory(loop: LoopConfig) -> ApiFactory:
    return lambda args: sumo_api.start(args, backend=loop.backend, gui=loop.gui)


def run_scenario(
    scenario: Scenario,
    policy: Policy,
    loop: LoopConfig = LoopConfig(),
    vehicle: veh.VehicleParams = veh.VehicleParams(),
    controller: ctl.ControllerParams = ctl.ControllerParams(),
    api_factory: ApiFactory | None = None,
) -> Rollout:
    """Run one scenario closed-loop and return its log and summary.

    SUMO is always closed, also on error; an exception inside the loop ends the run with
    ``end_reason="error"`` and keeps the log up to that step.
    """
    road = scenario.road
    # a policy with pose_at(t) (the recorded pseudo-planner) is a kinematic ego: it is moved to
    # its pose every step instead of being planned for, tracked and integrated by the plant
    pose_at = getattr(policy, "pose_at", None)
    lane = road.lanes[road.ego_lane]
    centre = lane.centre
    # SUMO lane position (and speed) per geometric metre differs per SUMO lane (lanes of a curved
    # edge share its length): on a route it is looked up where the leader is (Road.piece_at)
    multi_piece = len(road.ego_pieces) > 1
    rng = np.random.default_rng(scenario.seed)
    dt = loop.step_s
    plan_every = max(int(round(1.0 / (loop.plan_rate_hz * dt))), 1)
    n_max = max_steps(scenario, loop)
    s_ego0, s_leader_front0 = start_positions(scenario, vehicle)
    state = (initial_state(scenario, vehicle) if pose_at is None
             else veh.state_from_front_bumper(*pose_at(0.0), vehicle))

    factory = api_factory or _default_factory(loop)
    api = factory(sumo_args(scenario, loop))
    log = _Log(n_max)
    end_reason = "timeout"
    error = ""
    met, cut_ins = {}, 0  # traffic: the leaders met (ids, in order) and the cut-ins among them
    wall0 = time.perf_counter()
    try:
        ego_k, _, ego_pos, lead_scale = insert_vehicles(api, scenario, vehicle)
        has_leader = scenario.leader is not None
        traffic = scenario.traffic
        if traffic is not None:
            trf.prefill(api, traffic, road.route_edges[ego_k], float(ego_pos),
                        road.route_edges[-1], np.random.default_rng([scenario.seed, 1]))
        place_ego_at_start(api, road, state, vehicle, s_ego0)
        api.simulation.step()
        if loop.gui:  # the ego exists only after the first step
            sumo_api.track_in_gui(api, EGO_ID, GUI_VIEW_WIDTH_M)
        shot_k = round(GUI_SCREENSHOT_AT_S / dt) if loop.gui_screenshot is not None else -1

        # The loop works on plain floats (state tuple, PID memory) and the internal fast paths
        # of the plant, tracker and camera: bit-identical to the public functions, which build
        # frozen dataclasses and scan whole polylines (tests/test_golden.py pins the results).
        plant = veh.Plant.of(vehicle, dt)
        st = (state.x, state.y, state.yaw, state.vx, state.vy, state.yaw_rate, state.steer,
              state.drive_force)
        d_front = vehicle.cog_to_front_bumper_m
        camera = sen.LaneCamera(road, scenario.sensors, s_ego0)
        move_to_xy, set_speed = api.vehicle.moveToXY, api.vehicle.setSpeed
        on_lane = loop.ego_placement == "lane" and not loop.gui
        move_to = api.vehicle.moveTo if on_lane else None
        sim_step, colliding_ids = api.simulation.step, api.simulation.getCollidingVehiclesIDList
        integral, prev_error = 0.0, None  # PID memory (ControllerState's fields)
        target = None
        t_plan = 0.0
        features = np.zeros(9)
        feature_log = (math.nan,) * 8  # c0l..c2r, v_lead, d_lead as logged
        plan_log = (math.nan,) * 10  # the plan being tracked: time, pose, control points
        leader = _read_leader(api, vehicle) if has_leader else None
        # the leader's true speed [m/s]: SUMO's, in the units of the lane it was commanded on
        lead_v = leader[1] / lead_scale if leader is not None else 0.0
        lead_len, lead_wid = vehicle.length_m, vehicle.width_m  # the leader's footprint [m]
        # traffic: the leader is whichever SUMO vehicle getLeader names
        lead_id, last_id, last_gap = "", "", math.inf
        radar_dist = scenario.sensors.radar_range_m + 50.0
        sizes: dict[str, tuple[float, float]] = {}
        if traffic is not None:
            lead_id, leader, lead_v, lead_len, lead_wid, _, lead_seg0 = _traffic_leader(
                api, road, centre.segment_index(s_ego0), radar_dist, sizes)
        lead_speeds = leader_speeds(scenario, n_max, dt)
        lead_cmd = math.nan  # the leader's last speed command to SUMO [m/s]
        ego_seg = centre.segment_index(s_ego0)
        lead_seg = centre.segment_index(s_leader_front0) if traffic is None else lead_seg0
        half_width = 0.5 * lane.width
        route_end = road.ego_pieces[-1].s1  # [m] along the ego lane: where SUMO's route ends
        lane_margin, ttc_threshold = scenario.monitors.lane_margin_m, scenario.monitors.ttc_threshold_s
        length, width = vehicle.length_m, vehicle.width_m
        for k in range(n_max):
            t = k * dt
            x, y, yaw, vx, vy, yaw_rate = st[:6]
            v = math.hypot(vx, vy)
            if k % plan_every == 0:
                front = (x + d_front * math.cos(yaw), y + d_front * math.sin(yaw))
                front_xy = np.array(front)
                left, right, _ = camera.lane_lines(front_xy, yaw, rng)
                target_r = sen.radar_leader(
                    front_xy, yaw, None if leader is None else leader[0],
                    0.0 if leader is None else lead_v, left, right,
                    scenario.sensors, rng)
                v_lead, d_lead = sen.leader_features(target_r, v, scenario.sensors)
                features = planner_features(left, right, v, v_lead, d_lead)
                f = features.tolist()
                feature_log = (*f[:6], f[7], f[8])
                if pose_at is None:
                    plan = policy.plan(features)
                    target = ctl.make_target(plan, policy.horizon, (front[0], front[1], yaw))
                    t_plan = t
                    plan_log = (t, front[0], front[1], yaw,
                                *np.asarray(plan, float).reshape(6).tolist())
            if pose_at is None:
                steer_cmd, accel_cmd, integral, prev_error = ctl.track_values(
                    target, t - t_plan, x, y, yaw, vx, vy, yaw_rate, vehicle, integral,
                    prev_error, controller, dt)
                throttle, brake = veh.pedals_from_accel_vx(accel_cmd, vx, vehicle)
                st = plant.step(st, steer_cmd, throttle, brake)
            else:  # a kinematic ego (the recorded path): no plan, controller or plant
                st = _kinematic_state(pose_at(t + dt), vehicle)
                steer_cmd = accel_cmd = math.nan

            # move the ego in SUMO (front bumper, navigation angle), command the leader, step
            x, y, yaw, vx, vy = st[:5]
            v = math.hypot(vx, vy)
            c_yaw, s_yaw = math.cos(yaw), math.sin(yaw)
            front = (x + d_front * c_yaw, y + d_front * s_yaw)
            # where the front bumper is on the ego lane (O(1) walk from the last segment)
            s, d, lane_heading, ego_seg = centre.project_near(front[0], front[1], ego_seg)
            if on_lane and lane_placeable(d, s, v * dt, half_width, route_end):
                move_to(EGO_ID, *sumo_lane_position(road, s, v * dt))
            else:
                move_to_xy(EGO_ID, "", -1, front[0], front[1], yaw_to_sumo_angle(yaw), 2)
            set_speed(EGO_ID, v)
            if has_leader and leader is not None and lead_speeds[k] * lead_scale != lead_cmd:
                lead_cmd = lead_speeds[k] * lead_scale  # SUMO keeps it until the next command
                set_speed(LEADER_ID, lead_cmd)
            if k == shot_k:  # sumo-gui saves it during this step
                sumo_api.gui_screenshot(api, loop.gui_screenshot)
            sim_step()
            colliding = EGO_ID in colliding_ids()
            if traffic is None:
                leader = _read_leader(api, vehicle) if has_leader and leader is not None else None
            else:
                lead_id, leader, lead_v, lead_len, lead_wid, s_lead_rear, lead_seg = (
                    _traffic_leader(api, road, lead_seg if lead_id else ego_seg, radar_dist,
                                    sizes))

            # monitors on the state at t + dt
            heading_err = (yaw - lane_heading + math.pi) % (2.0 * math.pi) - math.pi
            d_min, d_max = mon.footprint_offset_range(d, heading_err, length, width)
            departed = mon.lane_departure(d_min, d_max, lane.width, lane_margin)
            gap, ttc, v_lead_true = math.inf, math.inf, math.nan
            lx = ly = math.nan
            if leader is not None:
                lead_rear, v_lead_sumo = leader[:2]
                lx, ly = lead_rear
                if traffic is None:
                    v_lead_true = lead_v = v_lead_sumo / lead_scale
                    s_lead_rear, _, _, lead_seg = centre.project_near(lx, ly, lead_seg)
                    if multi_piece:  # the next command's scale: the SUMO lane under its front
                        lead_scale = road.piece_at(s_lead_rear + length).scale
                else:
                    v_lead_true = lead_v
                gap = s_lead_rear - s
                if traffic is not None and gap <= scenario.sensors.radar_range_m:
                    if lead_id not in met:
                        met[lead_id] = len(met)
                        if last_id and gap < last_gap:
                            cut_ins += 1  # a newly met leader closer than the one before
                    last_id, last_gap = lead_id, gap
                ttc = mon.time_to_collision(gap, v, v_lead_true)
                if gap < 2.0 * length and not colliding:
                    colliding = footprints_overlap(front, yaw, vehicle, leader, lead_len,
                                                   lead_wid)
            ttc_flag = ttc <= ttc_threshold
            fraction = mon.path_completed(s, road.path_start_s, road.path_end_s)
            log.rows.append((
                t + dt, x, y, yaw, v, vy, st[5], st[6], front[0], front[1], steer_cmd,
                accel_cmd, s, d, d_min, d_max, *feature_log, lx, ly, v_lead_true, gap, ttc,
                departed, ttc_flag, colliding, fraction, *plan_log,
                (0.0 if traffic is None else float(met.get(lead_id, math.nan)))
                if leader is not None else math.nan,
            ))

            if s >= road.path_end_s:
                end_reason = "completed"
                break
            if colliding:
                end_reason = "collision"
                break
            if abs(d) > half_width + loop.offroad_stop_m:
                end_reason = "off_road"
                break
            if loop.stop_on_flag and (departed or ttc_flag):
                end_reason = "flag"
                break
    except Exception as exc:  # keep the log so far; the reason is recorded, not swallowed
        end_reason = "error"
        error = f"{type(exc).__name__}: {exc}"
    finally:
        try:
            api.close()
        except Exception:
            pass
    wall = time.perf_counter() - wall0
    return finish(scenario, log.frame(), end_reason, error, wall, policy.name, len(met), cut_ins)


def finish(scenario: Scenario, frame: pd.DataFrame, end_reason: str, error: str, wall_s: float,
           policy_name: str, leaders_met: int = 0, cut_ins: int = 0) -> Rollout:
    """The rollout of a finished run: its log and the summary (:func:`summarize`, distance
    and flag rates, leaders and cut-ins met with traffic)."""
    summary = summarize(scenario, frame, end_reason, error, wall_s, policy_name)
    summary |= drive_stats(frame, scenario.road.path_start_s)
    summary["leaders_met"] = (leaders_met if scenario.traffic is not None
                              else int(frame["leader_no"].notna().any()) if len(frame) else 0)
    summary["cut_ins_met"] = cut_ins if scenario.traffic is not None else 0
    summary["traffic"] = scenario.traffic.density if scenario.traffic is not None else ""
    return Rollout(frame, summary)


def summarize(
    scenario: Scenario, log: pd.DataFrame, end_reason: str, error: str, wall_s: float,
    policy_name: str,
) -> dict:
    """Flat per-scenario summary (what the sweeps and the paper's bar chart need)."""
    n = len(log)
    times = log["t"].to_numpy()
    flag = mon.first_flag(
        times, log["path_fraction"].to_numpy(), log["lane_departure"].to_numpy(bool),
        log["ttc_flag"].to_numpy(bool), log["collision"].to_numpy(bool),
    ) if n else mon.FirstFlag("", math.nan, 0.0)
    leader = scenario.leader
    return {
        "scenario": scenario.name,
        "policy": policy_name,
        "net": scenario.road.net_path.stem.removesuffix(".net"),
        "seed": scenario.seed,
        "leader_speed_mps": float(np.mean(leader.speeds)) if leader is not None else math.nan,
        "ego_speed0_mps": scenario.ego_speed_mps,
        "initial_gap_m": scenario.initial_gap_m,
        "end_reason": end_reason,
        "error": error,
        "completed": bool(end_reason == "completed" and flag.reason == ""),
        "path_completed": flag.path_fraction if flag.reason else (
            float(log["path_fraction"].iloc[-1]) if n else 0.0),
        "flag": flag.reason,
        "flag_time_s": flag.time_s,
        "min_ttc_s": float(log["ttc"].min()) if n else math.nan,
        "min_gap_m": float(log["gap"].min()) if n else math.nan,
        "max_abs_lateral_offset_m": float(log["d"].abs().max()) if n else math.nan,
        "sim_time_s": float(times[-1]) if n else 0.0,
        "steps": n,
        "wall_time_s": wall_s,
        "steps_per_s": n / wall_s if wall_s > 0 else math.nan,
    }


def _depart(road: Road, s: float, who: str) -> tuple[int, str, str, float]:
    """Where SUMO departs a vehicle whose front bumper is at arc length ``s`` [m] of the ego
    lane: ``(index of its first edge in road.route_edges, departLane, departPos, speed scale)``.

    SUMO's departPos is a position on one edge's lane; vehicles cannot depart inside a junction.
    """
    end = road.ego_pieces[-1].s1
    if s > end:
        raise ValueError(f"the {who} would start {s - end:.1f} m beyond the end of the road "
                         f"({end:.1f} m along the ego lane): use a smaller initial gap")
    p = road.piece_at(s)
    if p.internal:
        raise ValueError(f"the {who} would start inside junction lane {p.lane_id} ({s:.1f} m "
                         "along the ego lane) and SUMO departs vehicles on edges only: change "
                         "the initial gap by a few metres")
    return p.route_index, str(p.lane_index), f"{(s - p.s0) * p.scale:.3f}", p.scale


def lane_placeable(d, s, advance_m, half_width, route_end):
    """Whether ``LoopConfig.ego_placement="lane"`` may place the ego with ``moveTo``: its front
    bumper inside its lane (``|d| <= half_width`` [m]) and SUMO's step of ``advance_m`` [m]
    short of the route's end ``route_end`` [m along the ego lane] (SUMO lets a vehicle driven
    past its route's end arrive and leave; ``moveToXY`` keeps it). Floats, or arrays ``(N,)``."""
    return (abs(d) <= half_width) & (s + advance_m < route_end)


def sumo_lane_position(road: Road, s: float, advance_m: float = 0.0) -> tuple[str, float]:
    """Where ``LoopConfig.ego_placement="lane"`` puts the front bumper with ``moveTo``: the SUMO
    lane and position [m] on it from which SUMO's step, moving the ego ``advance_m`` [m] along
    its lane (speed x step: ``moveTo`` places, then the step drives on, unlike ``moveToXY``),
    ends at arc length ``s`` [m] of the ego lane. Clipped to the route's ends."""
    k = road.piece_index_at(s)
    p = road.ego_pieces[k]
    pos = (s - p.s0) * p.scale - advance_m
    if pos < 0.0 and k > 0:  # the step crosses into this lane from the one before
        p = road.ego_pieces[k - 1]
        pos += p.sumo_length
    return p.lane_id, min(max(pos, 0.0), p.sumo_length)


def max_steps(scenario: Scenario, loop: LoopConfig) -> int:
    """Steps of a run that does not end earlier: the shorter duration of the scenario and the
    loop, default 2x the path at the initial speed + 10 s."""
    limits = [t for t in (scenario.max_time_s, loop.max_time_s) if t]
    road = scenario.road
    max_time = min(limits) if limits else (
        2.0 * road.path_length / max(scenario.ego_speed_mps, 5.0) + 10.0)
    return int(math.ceil(max_time / loop.step_s))


def leader_speeds(scenario: Scenario, n_max: int, dt: float) -> list[float] | None:
    """The scripted leader's commanded speed [m/s] of every step (at its end time), in one
    vectorised call; None without a scripted leader."""
    if scenario.leader is None:
        return None
    return scenario.leader.speed_at(np.arange(n_max) * dt + dt).tolist()


def start_positions(scenario: Scenario, vehicle: veh.VehicleParams) -> tuple[float, float]:
    """Arc lengths [m] along the ego lane of the ego's front bumper (the path start) and the
    leader's front bumper (ahead by the gap and a car length)."""
    s_ego0 = scenario.road.path_start_s
    return s_ego0, s_ego0 + scenario.initial_gap_m + vehicle.length_m


def initial_state(scenario: Scenario, vehicle: veh.VehicleParams) -> veh.VehicleState:
    """The ego at the path start, offset and turned as the scenario says, at its speed."""
    centre = scenario.road.lanes[scenario.road.ego_lane].centre
    start_xy, lane_yaw = centre.point_at(scenario.road.path_start_s)
    normal = np.array([-math.sin(float(lane_yaw)), math.cos(float(lane_yaw))])
    start_xy = start_xy + scenario.ego_lateral_offset_m * normal
    return veh.state_from_front_bumper(
        float(start_xy[0]), float(start_xy[1]),
        float(lane_yaw) + scenario.ego_heading_offset_rad, scenario.ego_speed_mps, vehicle)


def insert_vehicles(api: sumo_api.SumoApi, scenario: Scenario, vehicle: veh.VehicleParams,
                    ego_id: str = EGO_ID, leader_id: str = LEADER_ID,
                    rename: Callable[[str], str] = str, tag: str = ""
                    ) -> tuple[int, str, str, float]:
    """Add the ego and the scripted leader (if any) to SUMO at the scenario's start, on the
    edges ``rename(edge)`` (a batch's copy of the track), with routes named ``...{tag}``.

    Returns ``(index of the ego's first edge in the route, its departLane, its departPos, the
    leader's SUMO speed scale)``.
    """
    road = scenario.road
    s_ego0, s_lead0 = start_positions(scenario, vehicle)
    centre = road.lanes[road.ego_lane].centre
    ego_k, ego_lane, ego_pos, _ = _depart(road, min(s_ego0, centre.length), "ego")
    route = ROUTE_ID + tag
    api.route.add(route, [rename(e) for e in road.route_edges[ego_k:]])
    api.vehicle.add(ego_id, route, depart="now", departLane=ego_lane, departPos=ego_pos,
                    departSpeed=f"{scenario.ego_speed_mps:.3f}")
    _configure(api, ego_id, vehicle)
    lead_scale = 1.0
    if scenario.leader is not None:
        lead_k, lead_lane, lead_pos, lead_scale = _depart(road, s_lead0, "leader")
        lead_route = route
        if lead_k != ego_k:  # departPos is per edge: the leader starts on a later edge
            lead_route = LEADER_ROUTE_ID + tag
            api.route.add(lead_route, [rename(e) for e in road.route_edges[lead_k:]])
        api.vehicle.add(leader_id, lead_route, depart="now", departLane=lead_lane,
                        departPos=lead_pos,
                        departSpeed=f"{scenario.leader.initial_speed * lead_scale:.3f}")
        _configure(api, leader_id, vehicle)
    return ego_k, ego_lane, ego_pos, lead_scale


def _configure(api: sumo_api.SumoApi, veh_id: str, vehicle: veh.VehicleParams) -> None:
    # speed mode 0 / lane-change mode 0: SUMO's own car-following must not leak in
    api.vehicle.setSpeedMode(veh_id, 0)
    api.vehicle.setLaneChangeMode(veh_id, 0)
    api.vehicle.setLength(veh_id, vehicle.length_m)
    api.vehicle.setWidth(veh_id, vehicle.width_m)


def place_ego(api: sumo_api.SumoApi, state: veh.VehicleState, vehicle: veh.VehicleParams,
              ego_id: str = EGO_ID, dx: float = 0.0, edge: str = "", lane: int = -1) -> None:
    """Put the ego at ``state`` in SUMO (its pose and speed; ``dx`` [m]: a batch copy's shift
    along x; ``edge``, ``lane``: a hint, which SUMO takes before the ego's insertion only
    with a lane index)."""
    x, y = veh.front_bumper(state, vehicle)
    api.vehicle.moveToXY(ego_id, edge, lane, x + dx, y, yaw_to_sumo_angle(state.yaw), 2)
    api.vehicle.setSpeed(ego_id, veh.speed(state))


def place_ego_at_start(api: sumo_api.SumoApi, road: Road, state: veh.VehicleState,
                       vehicle: veh.VehicleParams, s_front: float) -> None:
    """:func:`place_ego` at the start, unless a closed course's other lap is nearer there
    (:func:`xy_placement_is_unambiguous`): then the insertion on the ego's station is kept."""
    if xy_placement_is_unambiguous(road, veh.front_bumper(state, vehicle), s_front):
        place_ego(api, state, vehicle)
    else:
        api.vehicle.setSpeed(EGO_ID, veh.speed(state))


def xy_placement_is_unambiguous(road: Road, front_xy: tuple[float, float], s_front: float,
                                tolerance_m: float = SAME_STATION_M) -> bool:
    """Whether ``moveToXY`` puts a front bumper at ``front_xy`` [m] on its own station
    ``s_front`` [m along the ego lane]: SUMO maps a position to the NEAREST point of any lane,
    so where the road passes the same place again (the laps of a closed course) and another
    pass of some lane is nearer than the ego lane's own, it would put the ego there (and see a
    collision with a leader it overlaps). Own pass of each lane: walked from the ego's station
    scaled to that lane's length (:meth:`Polyline.project_near`)."""
    xy = np.asarray(front_xy, float)
    centre = road.lanes[road.ego_lane].centre
    _, own_d, _, _ = centre.project_near(float(xy[0]), float(xy[1]),
                                         centre.segment_index(s_front))
    for lane in road.lanes:
        line = lane.centre
        s_near, d_near = (float(v) for v in line.project(xy))
        if abs(d_near) >= abs(own_d):
            continue
        hint = line.segment_index(s_front * line.length / centre.length)
        s_own = line.project_near(float(xy[0]), float(xy[1]), hint)[0]
        if abs(s_near - s_own) > tolerance_m:
            return False
    return True


def _kinematic_state(pose: tuple[float, float, float, float], vehicle: veh.VehicleParams
                     ) -> tuple:
    """The loop's state tuple of an ego at front bumper ``pose[:2]``, heading ``pose[2]``,
    speed ``pose[3]``."""
    s = veh.state_from_front_bumper(*pose, vehicle)
    return (s.x, s.y, s.yaw, s.vx, s.vy, s.yaw_rate, s.steer, s.drive_force)


def footprints_overlap(front: tuple[float, float], yaw: float, vehicle: veh.VehicleParams,
                       leader: tuple, lead_length: float, lead_width: float) -> bool:
    """Whether the ego (front bumper ``front`` [m], heading ``yaw`` [rad]) overlaps the leader
    ``(rear_xy, speed, yaw, front_xy)`` of footprint ``lead_length`` x ``lead_width`` [m]."""
    half = 0.5 * vehicle.length_m
    centre = np.array([front[0] - half * math.cos(yaw), front[1] - half * math.sin(yaw)])
    lead_rear, _, lead_yaw, lead_front = leader
    lead_centre = 0.5 * (np.asarray(lead_rear) + np.asarray(lead_front))
    return rectangles_overlap(
        rectangle_corners(centre, yaw, vehicle.length_m, vehicle.width_m),
        rectangle_corners(lead_centre, lead_yaw, lead_length, lead_width))


def _traffic_leader(api: sumo_api.SumoApi, road: Road, hint: int, dist: float,
                    sizes: dict[str, tuple[float, float]]):
    """SUMO's leader of the ego (traffic): ``(id, (rear_xy, v_sumo, yaw, front_xy), true speed
    [m/s], length [m], width [m], arc length of its rear on the ego lane [m], segment)``;
    id ``""`` and leader None when there is none. Its speed is SUMO's divided by the SUMO
    lane scale under its front bumper."""
    lead_id = trf.read_leader(api, EGO_ID, dist)
    if not lead_id:
        return "", None, 0.0, 0.0, 0.0, math.nan, hint
    try:
        if lead_id not in sizes:
            sizes[lead_id] = (api.vehicle.getLength(lead_id), api.vehicle.getWidth(lead_id))
        length, width = sizes[lead_id]
        fx, fy = api.vehicle.getPosition(lead_id)
        yaw = sumo_angle_to_yaw(api.vehicle.getAngle(lead_id))
        v = api.vehicle.getSpeed(lead_id)
    except Exception:  # noqa: BLE001  # it arrived (left the network) this step
        return "", None, 0.0, 0.0, 0.0, math.nan, hint
    rear = (fx - length * math.cos(yaw), fy - length * math.sin(yaw))
    s_rear, _, _, seg = road.lanes[road.ego_lane].centre.project_near(rear[0], rear[1], hint)
    scale = road.piece_at(s_rear + length).scale
    return lead_id, (rear, v, yaw, (fx, fy)), v / scale, length, width, s_rear, seg


def drive_stats(log: pd.DataFrame, path_start_s: float) -> dict:
    """Distance driven and flag events per 100 km by kind (an event = a run of flagged steps)."""
    n = len(log)
    km = max(float(log["s"].iloc[-1]) - path_start_s, 0.0) / 1000.0 if n else 0.0
    out: dict = {"km_driven": km}
    for col, kind in (("ttc_flag", "ttc"), ("lane_departure", "lane_departure"),
                      ("collision", "collision")):
        events = len(mon.event_starts(log[col].to_numpy(bool)))
        out[f"{kind}_events"] = events
        out[f"{kind}_per_100km"] = 100.0 * events / km if km > 0 else math.nan
    return out


def _read_leader(api: sumo_api.SumoApi, vehicle: veh.VehicleParams, veh_id: str = LEADER_ID):
    """``(rear_xy, speed, yaw, front_xy)`` of the leader, or None once it has left the network."""
    try:
        fx, fy = api.vehicle.getPosition(veh_id)
        yaw = sumo_angle_to_yaw(api.vehicle.getAngle(veh_id))
        v = api.vehicle.getSpeed(veh_id)
    except Exception:  # libsumo/traci raise TraCIException for a vehicle that has arrived
        return None
    rear = (fx - vehicle.length_m * math.cos(yaw), fy - vehicle.length_m * math.sin(yaw))
    return rear, v, yaw, (fx, fy)


# the log columns a summary (summarize, drive_stats, leaders met) and a sweep's record (the
# leader-response metrics) read: a log of these columns only gives the same record
SUMMARY_COLUMNS = ("t", "v", "s", "d", "leader_v", "gap", "ttc", "lane_departure", "ttc_flag",
                   "collision", "path_fraction", "leader_no")


class _Log:
    """Per-step rows as tuples of floats (a list append per step), one array at the end."""

    COLUMNS = (
        "t", "x", "y", "yaw", "v", "vy", "yaw_rate", "steer", "front_x", "front_y", "steer_cmd",
        "accel_cmd", "s", "d", "d_min", "d_max", "c0l", "c1l", "c2l", "c0r", "c1r", "c2r",
        "v_lead_sensed", "d_lead_sensed", "leader_x", "leader_y", "leader_v", "gap", "ttc",
        "lane_departure", "ttc_flag", "collision", "path_fraction",
        # the plan being tracked: made at plan_t [s] at the front-bumper pose plan_x, plan_y
        # [m], plan_yaw [rad]; its free control points cp{i}_x, cp{i}_y [m] in that pose's frame
        "plan_t", "plan_x", "plan_y", "plan_yaw",
        "cp1_x", "cp1_y", "cp2_x", "cp2_y", "cp3_x", "cp3_y",
        # which leader [-]: 0, 1, ... in the order met (traffic); 0 the scripted one; NaN none
        "leader_no",
    )

    def __init__(self, n: int) -> None:
        self.rows: list[tuple] = []  # ``n`` (the most steps) is not needed by a list

    def frame(self) -> pd.DataFrame:
        return self.to_frame(np.array(self.rows, dtype=float).reshape(-1, len(self.COLUMNS)))

    @classmethod
    def to_frame(cls, data: np.ndarray, columns: Sequence[str] | None = None) -> pd.DataFrame:
        """The log of rows ``(steps, len(columns))`` (default: all of COLUMNS)."""
        df = pd.DataFrame(data, columns=list(columns or cls.COLUMNS))
        for col in ("lane_departure", "ttc_flag", "collision"):
            if col in df:
                df[col] = df[col].astype(bool)
        return df
