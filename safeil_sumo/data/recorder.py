"""Record a synthetic human drive on n74 in SUMO, with background traffic, into the drive schema.

The ego is driven by :class:`safeil_sumo.data.synthetic.SyntheticDriver`; SUMO drives everyone
else (direction-A flows of ``sumo_scenarios/n74/n74.rou.xml``, so cut-ins, merges from the
on-ramps and slow trucks happen for real). Every ``step_s`` (0.1 s = the 10 Hz logging rate):

1. read the vehicles around the ego (a libsumo context subscription, ``view_m`` around it);
2. log the sensors at the ego's current pose through the SAME code as the closed loop:
   :func:`safeil_sumo.sim.sensors.camera_lane_lines` on a :class:`~safeil_sumo.roads.road.Road`
   window of the main road (see below) and :func:`~safeil_sumo.sim.sensors.radar_leader` tried
   on the candidates ahead, nearest first (leader = nearest vehicle ahead inside the lane
   corridor, within radar range; NaN when none);
3. the driver perceives per-lane gaps (vehicles assigned to the main lanes by the lateral
   overlap of their footprint) and returns an acceleration and a lateral target;
4. the ego moves KINEMATICALLY along the road in Frenet coordinates of the reference line
   (arc length advanced by the driven distance, lateral offset = the driver's target), heading =
   road heading + ``atan(d'/ds)``; SUMO gets it with ``moveToXY(keepRoute=2)`` + ``setSpeed``
   (speed mode 0, lane-change mode 0), then steps.

Why kinematic: for RECORDING a plant adds nothing the paper's data would show at 4-10 Hz; the
closed loop uses :mod:`safeil_sumo.sim.vehicle`. Why our own road geometry: n74 has several
edges (ramps), so :func:`~safeil_sumo.roads.road.load_road` (one edge) does not apply; we
build a 2-lane ``Road`` over a window of the dense analytic reference line (5 m points; SUMO's
lane shapes are chords of the same curve within 3 cm) and reuse ``camera_lane_lines`` unchanged.
``lane_index`` is the main-road lane (0 right, 1 left), consistent across the merge edges.

Deterministic: SUMO ``--seed`` and the driver's ``np.random.Generator`` both come from ``seed``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.core.geometry import Polyline, sumo_angle_to_yaw, yaw_to_sumo_angle
from safeil_sumo.data.schema import validate_drive
from safeil_sumo.data.synthetic import DriverParams, LaneGaps, Observation, SyntheticDriver
from safeil_sumo.roads import n74
from safeil_sumo.roads.road import Lane, Road
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import sumo_api

EGO_ID = "ego"
EGO_LENGTH_M = 4.54  # [m] Toyota Prius (sim.vehicle.VehicleParams)
EGO_WIDTH_M = 1.76  # [m]
# TraCI constants (libsumo.constants / traci.constants); only sumo_api may import those modules
CMD_GET_VEHICLE_VARIABLE = 0xA4
VAR_SPEED, VAR_POSITION, VAR_ANGLE, VAR_LENGTH, VAR_WIDTH = 0x40, 0x42, 0x43, 0x44, 0x4D


@dataclass(frozen=True)
class RecordingConfig:
    """One recording on n74 (SI units)."""

    seed: int = 0  # SUMO --seed and the driver's random generator
    recording_id: str = "n74"
    duration_s: float | None = None  # [s] None: until the end of the road
    warmup_s: float = 400.0  # [s] background traffic fills the road before the ego enters
    start_s_m: float = 150.0  # [m] ego start along the reference line
    end_margin_m: float = 200.0  # [m] stop this far before the road's end
    start_lane: int = 0  # [-] 0 = right lane
    start_speed_mps: float = 25.0  # [m/s]
    step_s: float = 0.1  # [s] SUMO step = driver step = logging period
    view_m: float = 160.0  # [m] radius in which other vehicles are read
    window_m: float = 400.0  # [m] length of a Road window (+ margins either side)
    lane_change_duration_s: float = 3.0  # [s] SUMO's lanechange.duration for background traffic
    net_dir: Path = field(default_factory=n74.n74_dir)
    sensors: sen.SensorConfig = field(default_factory=sen.SensorConfig)

    def __post_init__(self) -> None:
        if not 0 < self.step_s <= 0.25:
            raise ValueError(f"step_s must be in (0, 0.25] s, got {self.step_s}")


def sumo_args(cfg: RecordingConfig) -> list[str]:
    net_dir = Path(cfg.net_dir)
    return [
        "-n", str(net_dir / f"{n74.NAME}.net.xml"),
        "-r", str(net_dir / f"{n74.NAME}.rou.xml"),  # direction A only: B is never seen
        "--step-length", f"{cfg.step_s}",
        "--seed", str(cfg.seed % 2**31),
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--collision.action", "warn",
        "--collision.mingap-factor", "0",
        "--time-to-teleport", "300",
        "--lanechange.duration", f"{cfg.lane_change_duration_s}",
    ]  # fmt: skip


class RoadWindows:
    """2-lane ``Road`` objects over windows of the main road, cached by window index."""

    def __init__(self, geo: n74.N74Geometry, window_m: float, margin_m: float = 260.0) -> None:
        self.geo, self.window_m, self.margin_m = geo, window_m, margin_m
        self._cache: dict[int, tuple[Road, Polyline, float]] = {}

    def at(self, s: float) -> tuple[Road, Polyline, float]:
        """The window around arc length ``s``: its Road, reference polyline and start arc length."""
        k = int(s // self.window_m)
        if k not in self._cache:
            s0 = max(k * self.window_m - self.margin_m, 0.0)
            s1 = min((k + 1) * self.window_m + self.margin_m, self.geo.length)
            ref = self.geo.reference(s0, s1, 5.0)
            lanes = []
            for i in range(n74.MAIN_LANES):
                centre = ref.offset(n74.lane_centre_offset(i))
                w = n74.LANE_WIDTH_M
                lanes.append(Lane(f"main_{i}", i, w, centre.length, centre,
                                  centre.offset(0.5 * w), centre.offset(-0.5 * w)))
            road = Road(Path(self.geo_name()), "main", tuple(lanes), 0, 0.0, ref.length, {})
            self._cache = {k: (road, ref, s0)}  # keep one window: the ego only moves forward
        return self._cache[k]

    @staticmethod
    def geo_name() -> str:
        return f"{n74.NAME}.net.xml"


@dataclass(frozen=True)
class Others:
    """Other vehicles around the ego (arrays of shape (M,))."""

    ids: tuple[str, ...]
    front: np.ndarray  # (M, 2) front-bumper centre [m]
    rear: np.ndarray  # (M, 2) rear-bumper centre [m]
    speed: np.ndarray  # [m/s]
    width: np.ndarray  # [m]


def read_others(api: sumo_api.SumoApi) -> Others:
    res = api.vehicle.getContextSubscriptionResults(EGO_ID) or {}
    ids = tuple(sorted(v for v in res if v != EGO_ID))
    m = len(ids)
    front, rear = np.zeros((m, 2)), np.zeros((m, 2))
    speed, width = np.zeros(m), np.zeros(m)
    for i, vid in enumerate(ids):
        r = res[vid]
        yaw = sumo_angle_to_yaw(r[VAR_ANGLE])
        front[i] = r[VAR_POSITION][:2]
        rear[i] = front[i] - r[VAR_LENGTH] * np.array([math.cos(yaw), math.sin(yaw)])
        speed[i], width[i] = r[VAR_SPEED], r[VAR_WIDTH]
    return Others(ids, front, rear, speed, width)


def lane_gaps(s_front_ego: float, s_front: np.ndarray, s_rear: np.ndarray, d: np.ndarray,
              width: np.ndarray, speed: np.ndarray) -> tuple[LaneGaps, ...]:
    """Per main lane: nearest vehicle ahead / behind the ego whose footprint overlaps the lane
    by more than 0.3 m (a merging car counts for both lanes while it crosses the line)."""
    out = []
    s_rear_ego = s_front_ego - EGO_LENGTH_M
    for lane in range(n74.MAIN_LANES):
        c = n74.lane_centre_offset(lane)
        half = 0.5 * n74.LANE_WIDTH_M
        overlap = np.minimum(d + 0.5 * width, c + half) - np.maximum(d - 0.5 * width, c - half)
        inside = overlap > 0.3
        ahead = inside & (s_rear > s_rear_ego)
        behind = inside & ~ahead
        g = LaneGaps()
        if ahead.any():
            i = np.flatnonzero(ahead)[np.argmin(s_rear[ahead])]
            g = LaneGaps(float(s_rear[i] - s_front_ego), float(speed[i]))
        if behind.any():
            j = np.flatnonzero(behind)[np.argmax(s_front[behind])]
            g = LaneGaps(g.gap_ahead, g.v_ahead, float(s_rear_ego - s_front[j]), float(speed[j]))
        out.append(g)
    return tuple(out)


def _insert_ego(api: sumo_api.SumoApi, cfg: RecordingConfig, route_edges: list[str]) -> None:
    """Add the ego once its start spot is free (no vehicle within -40 / +60 m in its lane)."""
    api.route.add("ego_route", route_edges)
    lane_id = f"{route_edges[0]}_{cfg.start_lane}"
    for _ in range(int(120.0 / cfg.step_s)):
        pos = [api.vehicle.getLanePosition(v) for v in api.lane.getLastStepVehicleIDs(lane_id)]
        if all(not (cfg.start_s_m - 40.0 < p < cfg.start_s_m + 60.0) for p in pos):
            break
        api.simulation.step()
    api.vehicle.add(EGO_ID, "ego_route", typeID="ego", depart="now",
                    departLane=str(cfg.start_lane), departPos=f"{cfg.start_s_m:.2f}",
                    departSpeed=f"{cfg.start_speed_mps:.2f}")
    api.vehicle.setSpeedMode(EGO_ID, 0)
    api.vehicle.setLaneChangeMode(EGO_ID, 0)


def radar_lead(others: Others, xy: np.ndarray, yaw: float, left: np.ndarray,
               right: np.ndarray, sensors: sen.SensorConfig
               ) -> tuple[sen.RadarTarget | None, str]:
    """The radar's leader: the nearest vehicle ahead (rear bumper along the ego's heading) that
    :func:`~safeil_sumo.sim.sensors.radar_leader` accepts, and its id; ``(None, "")`` if none."""
    if not len(others.ids):
        return None, ""
    local_x = (others.rear - xy) @ np.array([math.cos(yaw), math.sin(yaw)])
    for i in np.argsort(local_x):
        if local_x[i] <= 0.0:
            continue
        target = sen.radar_leader(xy, yaw, others.rear[i], float(others.speed[i]), left, right,
                                  sensors)
        if target is not None:
            return target, others.ids[i]
    return None, ""


def perceived_gaps(ref: Polyline, xy: np.ndarray, others: Others) -> tuple[LaneGaps, ...]:
    """What the driver perceives: per main lane, the gaps ahead and behind (:func:`lane_gaps`,
    arc lengths along the window's reference line ``ref``)."""
    if not len(others.ids):
        return tuple(LaneGaps() for _ in range(n74.MAIN_LANES))
    s_f, d_f = ref.project(others.front)
    s_r, _ = ref.project(others.rear)
    s_ego, _ = ref.project(xy)
    return lane_gaps(float(s_ego), s_f, s_r, d_f, others.width, others.speed)


def kinematic_step(geo: n74.N74Geometry, s: float, d: float, v: float, accel: float,
                   lateral_m: float, dt: float) -> tuple[float, float, float, float]:
    """The ego moved kinematically along the road for ``dt`` [s]: ``(s, d, v, yaw)`` after it.

    ``s`` arc length [m] and ``d`` lateral offset [m] of the reference line, ``v`` speed [m/s]
    (>= 0, changed by ``accel`` [m/s^2]); the new offset is the driver's ``lateral_m`` from the
    right lane's centre, reached in this step; ``yaw`` [rad] is the road's heading plus the
    angle of that lateral move over the distance driven."""
    v_new = max(v + accel * dt, 0.0)
    dist = 0.5 * (v + v_new) * dt
    kappa = float(geo.kappa_at(s))
    d_new = n74.lane_centre_offset(0) + lateral_m
    ds = dist / max(1.0 - kappa * d, 0.5)  # arc length of the reference line
    heading_err = math.atan2(d_new - d, max(dist, 1e-3))
    s_new = s + ds
    return s_new, d_new, v_new, float(geo.heading_at(s_new)) + heading_err


def record_drive(params: DriverParams, cfg: RecordingConfig = RecordingConfig(),
                 geo: n74.N74Geometry | None = None) -> pd.DataFrame:
    """Drive one synthetic driver on n74 and return the validated drive frame.

    ``df.attrs["recording_stats"]`` holds counts (steps, leader samples, lane changes, leader
    switches, collisions) and timings. SUMO is always closed.
    """
    geo = geo or n74.n74_geometry(_layout_seed(cfg))
    windows = RoadWindows(geo, cfg.window_m)
    rng = np.random.default_rng(cfg.seed)
    dt = cfg.step_s
    s_end = geo.length - cfg.end_margin_m
    max_t = cfg.duration_s if cfg.duration_s is not None else 3.0 * geo.length / 10.0
    n_max = math.ceil(max_t / dt)
    driver = SyntheticDriver(params, rng, dt=dt, lane=cfg.start_lane, max_steps=n_max + 1)

    wall0 = time.perf_counter()
    api = sumo_api.start(sumo_args(cfg))
    cols: dict[str, list[float]] = {k: [] for k in (
        "time", "x", "y", "yaw", "v_x", "left_c0", "left_c1", "left_c2", "left_c3",
        "right_c0", "right_c1", "right_c2", "right_c3", "lead_x", "lead_y", "lead_v",
        "lane_index", "s_road", "d_road", "accel")}
    leader_ids: list[str] = []
    collisions = 0
    try:
        for _ in range(int(cfg.warmup_s / dt)):
            api.simulation.step()
        _insert_ego(api, cfg, n74.main_route(geo))
        api.vehicle.subscribeContext(EGO_ID, CMD_GET_VEHICLE_VARIABLE, cfg.view_m,
                                     [VAR_POSITION, VAR_SPEED, VAR_ANGLE, VAR_LENGTH, VAR_WIDTH])
        s = cfg.start_s_m
        d = n74.lane_centre_offset(cfg.start_lane)
        v = cfg.start_speed_mps
        yaw = float(geo.heading_at(s))
        _move(api, geo, s, d, yaw, v)
        api.simulation.step()
        t0 = api.simulation.getTime()
        wall_sim0 = time.perf_counter()
        for k in range(n_max):
            if s >= s_end:
                break
            road, ref, _ = windows.at(s)
            xy = geo.frenet_to_xy(s, d)
            others = read_others(api)
            # sensors: the closed loop's code
            left, right, lane_idx = sen.camera_lane_lines(road, xy, yaw, cfg.sensors)
            target, lead_id = radar_lead(others, xy, yaw, left, right, cfg.sensors)
            leader_ids.append(lead_id)
            _log(cols, k * dt, xy, yaw, v, left, right, target, lane_idx, s, d)
            # driver
            kappa_ahead = float(geo.kappa_at(s + v * params.curve_preview_s))
            cmd = driver.step(Observation(v, perceived_gaps(ref, xy, others), kappa_ahead,
                                          n74.LANE_WIDTH_M))
            cols["accel"].append(cmd.accel)
            # kinematic ego along the road, then SUMO
            s, d, v, yaw = kinematic_step(geo, s, d, v, cmd.accel, cmd.lateral_m, dt)
            _move(api, geo, s, d, yaw, v)
            api.simulation.step()
            if EGO_ID in api.simulation.getCollidingVehiclesIDList():
                collisions += 1
        sim_time = api.simulation.getTime() - t0
    finally:
        api.close()
    wall = time.perf_counter() - wall0
    df = pd.DataFrame(cols)
    df.insert(0, "recording_id", cfg.recording_id)
    out = validate_drive(df, f"recording {cfg.recording_id}")
    out.attrs["recording_stats"] = {
        **recording_stats(df, leader_ids, cfg, sim_time, collisions),
        "wall_s": round(wall, 2),
        "wall_drive_s": round(time.perf_counter() - wall_sim0, 2) if len(df) else 0.0,
    }
    return out


def recording_stats(df: pd.DataFrame, leader_ids: list[str], cfg: RecordingConfig,
                    sim_time: float, collisions: int) -> dict:
    """The recording's counts: samples, distance driven [m], simulated duration [s], share of
    samples with a leader, lane changes, leader switches (leader to another leader) and steps
    in collision."""
    lane = df["lane_index"].to_numpy()
    lead = np.array(leader_ids)
    has = lead != ""
    return {
        "recording_id": cfg.recording_id,
        "seed": cfg.seed,
        "samples": len(df),
        "driven_m": round(float(df["s_road"].iloc[-1] - df["s_road"].iloc[0]), 1),
        "duration_s": round(float(sim_time), 1),
        "leader_fraction": round(float(has.mean()), 4),
        "lane_changes": int(np.count_nonzero(np.diff(lane) != 0)),
        "leader_switches": int(np.count_nonzero((lead[1:] != lead[:-1]) & has[1:] & has[:-1])),
        "collision_steps": collisions,
    }


def _layout_seed(cfg: RecordingConfig) -> int:
    import json

    meta = Path(cfg.net_dir) / f"{n74.NAME}.json"
    return int(json.loads(meta.read_text())["seed"]) if meta.is_file() else n74.DEFAULT_SEED


def _move(api: sumo_api.SumoApi, geo: n74.N74Geometry, s: float, d: float, yaw: float, v: float) -> None:
    x, y = geo.frenet_to_xy(s, d)
    api.vehicle.moveToXY(EGO_ID, "", -1, float(x), float(y), yaw_to_sumo_angle(yaw), keepRoute=2)
    api.vehicle.setSpeed(EGO_ID, v)


def _log(cols: dict, t: float, xy: np.ndarray, yaw: float, v: float, left: np.ndarray,
         right: np.ndarray, target: sen.RadarTarget | None, lane: int, s: float, d: float) -> None:
    cols["time"].append(t)
    cols["x"].append(float(xy[0]))
    cols["y"].append(float(xy[1]))
    cols["yaw"].append(float(math.remainder(yaw, 2 * math.pi)))
    cols["v_x"].append(v)
    for i in range(4):
        cols[f"left_c{i}"].append(float(left[i]))
        cols[f"right_c{i}"].append(float(right[i]))
    cols["lead_x"].append(math.nan if target is None else target.x)
    cols["lead_y"].append(math.nan if target is None else target.y)
    cols["lead_v"].append(math.nan if target is None else target.v)
    cols["lane_index"].append(float(lane))
    cols["s_road"].append(s)
    cols["d_road"].append(d)
