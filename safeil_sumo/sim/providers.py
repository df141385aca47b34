"""Who leads the ego in the closed loop: one leader provider per scenario.

- :class:`ScriptedLeader`: a SUMO vehicle of its own driven along a speed profile
  (:class:`.leaders.SpeedProfile`: constant, piecewise-linear or a recorded human's), one speed
  command per step, converted to the SUMO lane's units where SUMO's lane lengths differ from
  the geometry (a route of several SUMO lanes).
- :class:`TrafficLeader`: whichever of SUMO's own vehicles (background traffic,
  :mod:`.traffic`) ``getLeader`` names ahead of the ego, with its own size; it counts the
  leaders met and the cut-ins among them for the summary. The traffic's route files name the
  net's own edges, so it runs on the original net (N = 1).

:class:`.stepper.ClosedLoop` calls a provider at fixed points of a physics step: ``start``
after the ego's insertion, ``command(api, k)`` before SUMO's step ``k``, ``read(api)`` after
it, and, for the scenarios whose leader ``needs_location`` (or is close to the ego),
``located(s_rear, gap)`` once its rear is projected on the ego lane. What the loop reads from
it: what ``read`` returns, ``(rear_x, rear_y, v)`` (:data:`NO_LEADER`: no leader), ``leader``
``(rear_xy, v_sumo, yaw, front_xy)`` or None, ``v`` its true speed [m/s], ``length`` and
``width`` [m] (the footprint check), ``no`` the log's ``leader_no``.
"""

from __future__ import annotations

import math
from typing import TypeAlias

import numpy as np

from safeil_sumo.core.geometry import sumo_angle_to_yaw
from safeil_sumo.sim import traffic as trf
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.loop_types import Scenario
from safeil_sumo.sim.sumo_api import SumoApi
from safeil_sumo.sim.sumo_setup import leader_speeds

# what the loop reads of a leader after a step: ``(rear_xy, v_sumo, yaw, front_xy)`` [m, m/s,
# rad, m], in the original track's coordinates
LeaderPose: TypeAlias = tuple[tuple[float, float], float, float, tuple[float, float]]
# what ``read`` returns: the leader's rear x, y [m] (the original track's) and true speed [m/s]
LeaderRead: TypeAlias = tuple[float, float, float]
NO_LEADER: LeaderRead = (math.nan, math.nan, math.nan)  # read: there is no leader


class ScriptedLeader:
    """The scenario's leader on its speed profile (it leaves the loop when SUMO lets it arrive
    at its route's end)."""

    traffic = False

    def __init__(self, scenario: Scenario, vehicle: veh.VehicleParams, veh_id: str, n_max: int,
                 dt: float, dx: float = 0.0) -> None:
        self.veh_id, self.vehicle, self.dx = veh_id, vehicle, dx
        self.road = scenario.road
        # SUMO lane position (and speed) per geometric metre differs per SUMO lane (lanes of a
        # curved edge share its length): on a route it is looked up where the leader is
        self.needs_location = len(self.road.ego_pieces) > 1
        speeds = leader_speeds(scenario, n_max, dt)
        if speeds is None:
            raise ValueError("a ScriptedLeader needs a scenario with a leader")
        self.speeds = speeds
        self.scale = 1.0  # SUMO speed per true speed on the lane it is commanded on
        self.cmd = math.nan  # the last speed command to SUMO [m/s]
        self.gone = False  # it has left the network
        self.leader: LeaderPose | None = None
        self.v = 0.0
        self.length, self.width = vehicle.length_m, vehicle.width_m
        self.no = 0.0  # the log's leader_no while there is a leader
        self.met, self.cut_ins = 0, 0  # the summary's (traffic only)

    def start(self, api: SumoApi, scale: float, ego_edge: str, ego_pos: float) -> None:
        """After the insertion: its speed scale on its departure lane."""
        self.scale = scale

    def command(self, api: SumoApi, k: int) -> None:
        """Its speed of step ``k``; SUMO keeps a commanded speed until the next command."""
        if not self.gone:
            v_cmd = self.speeds[k] * self.scale
            if v_cmd != self.cmd:
                api.vehicle.setSpeed(self.veh_id, v_cmd)
                self.cmd = v_cmd

    def read(self, api: SumoApi) -> LeaderRead:
        """Its pose and true speed after a step (in the original track's coordinates): its
        rear x, y and true speed (:data:`NO_LEADER` once it has left)."""
        if self.gone:
            return NO_LEADER
        vehicle = api.vehicle
        try:
            fx, fy = vehicle.getPosition(self.veh_id)
            yaw = sumo_angle_to_yaw(vehicle.getAngle(self.veh_id))
            v = vehicle.getSpeed(self.veh_id)
        # libsumo/traci raise TraCIException for a vehicle that has arrived
        except Exception:  # noqa: BLE001
            self.gone, self.leader = True, None
            return NO_LEADER
        length = self.length
        rx, ry = fx - length * math.cos(yaw), fy - length * math.sin(yaw)
        if self.dx:  # in the original track's coordinates
            rx, fx = rx - self.dx, fx - self.dx
        self.leader = (rx, ry), v, yaw, (fx, fy)
        self.v = v_true = v / self.scale
        return rx, ry, v_true

    def located(self, s_rear: float, gap: float, count: bool = True) -> float:
        """Its rear at ``s_rear`` [m along the ego lane]: the next command's scale is the SUMO
        lane's under its front. Returns its true speed."""
        if self.needs_location:
            self.scale = self.road.piece_at(s_rear + self.length).scale
        return self.v

    def vehicle_ids(self) -> tuple[str, ...]:
        """The SUMO vehicles to remove when the scenario ends."""
        return () if self.gone else (self.veh_id,)


class TrafficLeader:
    """SUMO's leader of the ego among the background traffic."""

    traffic = True
    needs_location = True  # its true speed is read on the SUMO lane under its front

    def __init__(self, scenario: Scenario, ego_id: str) -> None:
        if scenario.traffic is None:
            raise ValueError("a TrafficLeader needs a scenario with traffic")
        self.spec, self.ego_id, self.road = scenario.traffic, ego_id, scenario.road
        self.seed = scenario.seed
        self.radar_range = scenario.sensors.radar_range_m
        self.dist = self.radar_range + 50.0  # getLeader's search distance [m]
        self.sizes: dict[str, tuple[float, float]] = {}
        self.id = ""  # SUMO's id of the current leader; "": none
        self.from_ego = True  # no leader before this read: its projection walks from the ego's
        self.met: dict[str, int] = {}  # the leaders met (ids, in order)
        self.cut_ins = 0  # newly met leaders closer than the one before
        self.last_id, self.last_gap = "", math.inf
        self.leader: LeaderPose | None = None
        self.v = 0.0
        self.length = self.width = 0.0

    def start(self, api: SumoApi, scale: float, ego_edge: str, ego_pos: float) -> None:
        """Fill the road with traffic at the flows' density (:func:`.traffic.prefill`)."""
        trf.prefill(api, self.spec, ego_edge, ego_pos, self.road.route_edges[-1],
                    np.random.default_rng([self.seed, 1]))

    def command(self, api: SumoApi, k: int) -> None:
        pass  # SUMO drives it

    def read(self, api: SumoApi) -> LeaderRead:
        """Whichever vehicle ``getLeader`` names, its pose and size: its rear x, y and 0.0
        (its true speed comes with ``located``; :data:`NO_LEADER`: none)."""
        self.from_ego = not self.id
        self.id, self.leader, self.v = "", None, 0.0
        lead_id = trf.read_leader(api, self.ego_id, self.dist)
        if not lead_id:
            return NO_LEADER
        try:
            if lead_id not in self.sizes:
                self.sizes[lead_id] = (api.vehicle.getLength(lead_id),
                                       api.vehicle.getWidth(lead_id))
            length, width = self.sizes[lead_id]
            fx, fy = api.vehicle.getPosition(lead_id)
            yaw = sumo_angle_to_yaw(api.vehicle.getAngle(lead_id))
            v = api.vehicle.getSpeed(lead_id)
        except Exception:  # noqa: BLE001  # it arrived (left the network) this step
            return NO_LEADER
        rear = (fx - length * math.cos(yaw), fy - length * math.sin(yaw))
        self.id, self.leader = lead_id, (rear, v, yaw, (fx, fy))
        self.length, self.width = length, width
        return rear[0], rear[1], 0.0

    def located(self, s_rear: float, gap: float, count: bool = True) -> float:
        """Its rear at ``s_rear`` [m along the ego lane], ``gap`` [m] ahead of the ego: its true
        speed (SUMO's divided by the scale of the SUMO lane under its front); ``count``: a
        leader within radar range is met (a cut-in if closer than the one before)."""
        assert self.leader is not None, "located after a read that found no leader"
        self.v = self.leader[1] / self.road.piece_at(s_rear + self.length).scale
        if count and gap <= self.radar_range:
            if self.id not in self.met:
                self.met[self.id] = len(self.met)
                if self.last_id and gap < self.last_gap:
                    self.cut_ins += 1
            self.last_id, self.last_gap = self.id, gap
        return self.v

    @property
    def no(self) -> float:
        """The log's leader_no: which leader, in the order met (NaN: not met yet)."""
        return float(self.met.get(self.id, math.nan))

    def vehicle_ids(self) -> tuple[str, ...]:
        return ()
