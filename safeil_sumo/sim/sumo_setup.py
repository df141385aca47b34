"""The loop's SUMO seam at the start of a run: SUMO's options, where the ego and the scripted leader
depart, how the ego is placed (``moveToXY`` or ``moveTo`` on its lane), the run's length and the
leader's speed commands, and the footprint overlap the monitors check.

Shared by every driver of the loop (:class:`.stepper.ClosedLoop`). The leader is read back by
its provider (:mod:`.providers`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from safeil_sumo.core.geometry import (
    rectangle_corners,
    rectangles_overlap,
    yaw_to_sumo_angle,
)
from safeil_sumo.roads.road import Road
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.xp import BoolOrArray, FloatOrArray, clip

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


def default_factory(loop: LoopConfig) -> ApiFactory:
    return lambda args: sumo_api.start(args, backend=loop.backend, gui=loop.gui)


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


def lane_placeable(d: FloatOrArray, s: FloatOrArray, advance_m: FloatOrArray,
                   half_width: FloatOrArray, route_end: FloatOrArray) -> BoolOrArray:
    """Whether ``LoopConfig.ego_placement="lane"`` may place the ego with ``moveTo``: its front
    bumper inside its lane (``|d| <= half_width`` [m]) and SUMO's step of ``advance_m`` [m]
    short of the route's end ``route_end`` [m along the ego lane] (SUMO lets a vehicle driven
    past its route's end arrive and leave; ``moveToXY`` keeps it). Floats, or arrays ``(N,)``."""
    # |d| <= half_width written as two comparisons (builtin abs() of float | array is untyped)
    return (d <= half_width) & (d >= -half_width) & (s + advance_m < route_end)


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
    return p.lane_id, clip(pos, 0.0, p.sumo_length)


def max_steps(scenario: Scenario, loop: LoopConfig) -> int:
    """Steps of a run that does not end earlier: the shorter duration of the scenario and the
    loop, default 2x the path at the initial speed + 10 s."""
    limits = [t for t in (scenario.max_time_s, loop.max_time_s) if t]
    road = scenario.road
    max_time = min(limits) if limits else (
        2.0 * road.path_length / max(scenario.ego_speed_mps, 5.0) + 10.0)
    return math.ceil(max_time / loop.step_s)


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


def warm_up(api: sumo_api.SumoApi, duration_s: float, step_s: float) -> None:
    """SUMO's own traffic driven for ``duration_s`` [s] (``int(duration_s / step_s)`` steps of
    ``step_s`` [s]) before an ego enters (the synthetic-drive recorder's background traffic)."""
    for _ in range(int(duration_s / step_s)):
        api.simulation.step()


def add_when_clear(api: sumo_api.SumoApi, veh_id: str, route_id: str, edges: Sequence[str],
                   lane: int, pos_m: float, speed_mps: float, type_id: str, step_s: float,
                   behind_m: float = 40.0, ahead_m: float = 60.0, max_wait_s: float = 120.0
                   ) -> None:
    """Add ``veh_id`` (vType ``type_id``) on lane ``lane`` of ``edges[0]`` at lane position
    ``pos_m`` [m] and ``speed_mps`` [m/s] once no vehicle in that lane is within ``behind_m``
    behind / ``ahead_m`` ahead of the spot [m] (SUMO stepped by ``step_s`` [s] meanwhile, at most
    ``max_wait_s`` [s]); speed and lane-change modes 0. It enters SUMO at the next step."""
    api.route.add(route_id, list(edges))
    lane_id = f"{edges[0]}_{lane}"
    for _ in range(int(max_wait_s / step_s)):
        pos = [api.vehicle.getLanePosition(v) for v in api.lane.getLastStepVehicleIDs(lane_id)]
        if all(not (pos_m - behind_m < p < pos_m + ahead_m) for p in pos):
            break
        api.simulation.step()
    api.vehicle.add(veh_id, route_id, typeID=type_id, depart="now", departLane=str(lane),
                    departPos=f"{pos_m:.2f}", departSpeed=f"{speed_mps:.2f}")
    api.vehicle.setSpeedMode(veh_id, 0)
    api.vehicle.setLaneChangeMode(veh_id, 0)


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


def footprints_overlap(front: tuple[float, float], yaw: float, vehicle: veh.VehicleParams,
                       leader: tuple[tuple[float, float], float, float, tuple[float, float]],
                       lead_length: float, lead_width: float) -> bool:
    """Whether the ego (front bumper ``front`` [m], heading ``yaw`` [rad]) overlaps the leader
    ``(rear_xy, speed, yaw, front_xy)`` of footprint ``lead_length`` x ``lead_width`` [m]."""
    half = 0.5 * vehicle.length_m
    centre = np.array([front[0] - half * math.cos(yaw), front[1] - half * math.sin(yaw)])
    lead_rear, _, lead_yaw, lead_front = leader
    lead_centre = 0.5 * (np.asarray(lead_rear) + np.asarray(lead_front))
    return rectangles_overlap(
        rectangle_corners(centre, yaw, vehicle.length_m, vehicle.width_m),
        rectangle_corners(lead_centre, lead_yaw, lead_length, lead_width))
