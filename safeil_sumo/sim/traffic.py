"""Background traffic: SUMO's own vehicles from a net's route files, as the ego's leaders.

A :class:`Traffic` says which route files SUMO loads and how dense the traffic is. SUMO scales
the files' flows (``--scale``, seeded by the scenario's SUMO ``--seed``); those flows enter at
the start of the road and on the on-ramps, so a drive that starts at t = 0 would see an empty
road ahead. :func:`prefill` therefore inserts vehicles along the main road at the flows'
density at t = 0 (exponential headways from a seeded generator, the vTypeDistribution of the
files), keeping a clear zone around the ego. SUMO then drives them all with its own
car-following and lane-change models: trucks slower than the ego, cars overtaking it and cutting
in, ramp vehicles merging into its lane.

The runner picks the ego's radar target with ``vehicle.getLeader(ego, dist)``: SUMO's leader in
the ego's lane and its continuation along the ego's route (it needs the ego on a lane; the gap
it returns is ``gap - minGap``, so the runner measures the gap itself along the ego lane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from safeil_sumo.sim.sumo_api import SumoApi

# --traffic density -> factor on the flows of the route files [-]
DENSITIES: dict[str, float] = {"light": 0.5, "default": 1.0, "dense": 2.0}
PREFILL_BEHIND_M = 1000.0  # vehicles are also placed this far behind the ego's start [m]
MIN_HEADWAY_M = 25.0  # smallest front-to-front spacing of prefilled vehicles in a lane [m]
CLEAR_AHEAD_M = 60.0  # no prefilled vehicle this close ahead of the ego in any lane [m]
CLEAR_BEHIND_M = 30.0  # ... nor this close behind it [m]
PREFILL_SPEED_MPS = 30.0  # typical speed that turns a flow into a density [m/s]
LANE_CHANGE_DURATION_S = 3.0  # SUMO --lanechange.duration: cut-ins take time, as a human's


@dataclass(frozen=True)
class Traffic:
    """Background traffic of a scenario.

    ``route_files``: SUMO route files (vTypes + flows); ``scale``: factor on their flows [-];
    ``main_route``: the main road's edges in driving order (prefill); ``lanes``: per edge of
    ``main_route``, the SUMO lane indices of its through lanes (an acceleration lane is left
    empty); ``flow_vph``: per edge, the flow through it at scale 1 [veh/h]; ``vtype``: the
    vType (distribution) id of prefilled vehicles.
    """

    density: str
    route_files: tuple[Path, ...]
    scale: float
    main_route: tuple[str, ...]
    lanes: tuple[tuple[int, ...], ...]
    flow_vph: tuple[float, ...]
    vtype: str = "traffic"

    def sumo_args(self) -> list[str]:
        return ["-r", ",".join(str(p) for p in self.route_files), "--scale", f"{self.scale:g}",
                "--lanechange.duration", f"{LANE_CHANGE_DURATION_S:g}"]


def n74_traffic(density: str = "default", net_dir: Path | None = None) -> Traffic:
    """Direction-A traffic of ``sumo_scenarios/n74/n74.rou.xml`` (main flow + ramps; the
    opposite direction's file is not loaded: the ego never sees it)."""
    from safeil_sumo.roads import n74

    if density not in DENSITIES:
        raise ValueError(f"traffic density must be one of none, {', '.join(DENSITIES)}, got "
                         f"{density!r}")
    net_dir = net_dir or n74.n74_dir()
    meta = n74.layout(net_dir)
    flows = meta["flows_vph"]
    edges = [e["id"] for e in meta["edges"]]
    lanes, flow, ramps = [], [], 0
    for e in edges:
        merge = e.startswith("merge")
        ramps += merge
        lanes.append(tuple(range(1, meta["main_lanes"] + 1)) if merge
                     else tuple(range(meta["main_lanes"])))
        flow.append(flows["main"] + ramps * flows["per_ramp"])
    return Traffic(density, (net_dir / f"{n74.NAME}.rou.xml",), DENSITIES[density],
                   tuple(edges), tuple(lanes), tuple(flow))


def prefill(api: SumoApi, traffic: Traffic, ego_edge: str, ego_pos_m: float, end_edge: str,
            rng: np.random.Generator) -> int:
    """Insert vehicles along ``traffic.main_route`` from ``PREFILL_BEHIND_M`` behind the ego
    (on ``ego_edge`` at lane position ``ego_pos_m``) to the end of ``end_edge``; returns how
    many. Headways are ``MIN_HEADWAY_M`` + exponential, mean = speed / flow per lane."""
    route = list(traffic.main_route)
    k_ego, k_end = route.index(ego_edge), route.index(end_edge)
    lengths = [api.lane.getLength(f"{e}_{traffic.lanes[k][0]}") for k, e in enumerate(route)]
    start = np.concatenate([[0.0], np.cumsum(lengths)])
    ego_at = start[k_ego] + ego_pos_m
    n = 0
    for k in range(len(route)):
        if k > k_end or start[k + 1] < ego_at - PREFILL_BEHIND_M:
            continue
        per_lane_vps = traffic.flow_vph[k] * traffic.scale / 3600.0 / len(traffic.lanes[k])
        if per_lane_vps <= 0:
            continue
        mean_m = max(PREFILL_SPEED_MPS / per_lane_vps - MIN_HEADWAY_M, 1.0)
        route_id = f"tr_{route[k]}"
        added_route = False
        for lane in traffic.lanes[k]:
            pos = float(rng.uniform(0.0, MIN_HEADWAY_M + mean_m))
            while pos < lengths[k] - 1.0:
                at = start[k] + pos
                if at >= ego_at - PREFILL_BEHIND_M and not (
                        ego_at - CLEAR_BEHIND_M < at < ego_at + CLEAR_AHEAD_M):
                    if not added_route:
                        api.route.add(route_id, route[k:])
                        added_route = True
                    api.vehicle.add(f"tr{n}", route_id, typeID=traffic.vtype, depart="now",
                                    departLane=str(lane), departPos=f"{pos:.2f}",
                                    departSpeed="desired")
                    n += 1
                pos += MIN_HEADWAY_M + float(rng.exponential(mean_m))
    return n


def read_leader(api: SumoApi, ego_id: str, dist_m: float) -> str:
    """SUMO's leader of the ego in its lane (and its continuation) within at least ``dist_m``
    [m], or "" (libsumo answers ``("", -1)``, traci ``None`` when there is none, and both raise
    or answer nothing useful while the ego is off every lane)."""
    try:
        res = api.vehicle.getLeader(ego_id, dist_m)
    except Exception:  # noqa: BLE001  # TraCIException (traci) / its libsumo twin
        return ""
    if not res or not res[0] or not math.isfinite(res[1]):
        return ""
    return res[0]
