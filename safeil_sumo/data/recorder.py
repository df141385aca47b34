"""Record a synthetic human drive on n74 in SUMO, with background traffic, into the drive schema.

The ego is driven by :class:`safeil_sumo.data.synthetic.SyntheticDriver`; SUMO drives everyone
else (direction-A flows of ``sumo_scenarios/n74/n74.rou.xml``, so cut-ins, merges from the
on-ramps and slow trucks happen for real). The recording is a driver of the project's one closed
loop, :class:`safeil_sumo.sim.stepper.ClosedLoop`: :class:`SyntheticEgo` is a self-driven ego
(:class:`~safeil_sumo.sim.stepper.SelfDrivenEgo`) on the n74 road
(:func:`~safeil_sumo.roads.n74.stretch_road`), one decision per step, with no leader
provider of the loop's. It enters SUMO itself after SUMO's own traffic has run ``warmup_s``
(:func:`~safeil_sumo.sim.sumo_setup.warm_up`; :func:`~safeil_sumo.sim.sumo_setup.add_when_clear`:
vType ``ego`` of the route file, once its start spot is free). The loop moves it, steps SUMO and
flags its collisions (the recording drives on through one and counts its steps); what the
recording logs is the ego's own per-step code, run when the loop asks for its next pose. Every
``step_s`` (0.1 s = the 10 Hz logging rate):

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
   road heading + ``atan(d'/ds)``; the loop gives SUMO that front bumper with
   ``moveToXY(keepRoute=2)`` + ``setSpeed`` (``LoopConfig.ego_placement = "xy"``; speed mode 0,
   lane-change mode 0), then steps.

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
from safeil_sumo.core.policy import PLAN_HORIZON_S
from safeil_sumo.data.schema import validate_drive
from safeil_sumo.data.synthetic import DriverParams, LaneGaps, Observation, SyntheticDriver
from safeil_sumo.roads import n74
from safeil_sumo.roads.road import Lane, Road
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.stepper import ClosedLoop, Pose
from safeil_sumo.sim.sumo_setup import add_when_clear, warm_up

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
    step_s: float = 0.1  # [s] SUMO step = driver step = logging period (the loop's <= 0.1 s)
    view_m: float = 160.0  # [m] radius in which other vehicles are read
    window_m: float = 400.0  # [m] length of a Road window (+ margins either side)
    lane_change_duration_s: float = 3.0  # [s] SUMO's lanechange.duration for background traffic
    net_dir: Path = field(default_factory=n74.n74_dir)
    sensors: sen.SensorConfig = field(default_factory=sen.SensorConfig)

    def __post_init__(self) -> None:
        if not 0 < self.step_s <= 0.1:
            raise ValueError(f"step_s must be in (0, 0.1] s (the closed loop's step), got "
                             f"{self.step_s}")


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


def read_others(api: sumo_api.SumoApi, ego_id: str = EGO_ID) -> Others:
    """The vehicles of ``ego_id``'s context subscription (itself left out), sorted by id."""
    res = api.vehicle.getContextSubscriptionResults(ego_id) or {}
    ids = tuple(sorted(v for v in res if v != ego_id))
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


class SyntheticEgo:
    """The synthetic driver as a self-driven ego of the closed loop
    (:class:`~safeil_sumo.sim.stepper.SelfDrivenEgo`): it enters SUMO after the warm-up
    (:meth:`enter`) and, every step the loop asks for its next pose (:meth:`drive`), reads the
    vehicles around it, logs its sensors at its current pose, lets the driver decide and moves
    kinematically along the road (:func:`kinematic_step`). ``cols``: the drive's columns so far,
    ``leader_ids``: the radar's leader per sample ("" none), ``k``: samples logged, ``s`` [m]:
    its arc length along the reference line, ``api``: SUMO, once entered."""

    name = "synthetic"
    horizon = PLAN_HORIZON_S  # [s] unused (nothing is planned); the loop's Policy protocol

    def __init__(self, params: DriverParams, cfg: RecordingConfig, geo: n74.N74Geometry,
                 n_max: int) -> None:
        self.params, self.cfg, self.geo = params, cfg, geo
        self.windows = RoadWindows(geo, cfg.window_m)
        rng = np.random.default_rng(cfg.seed)
        self.driver = SyntheticDriver(params, rng, dt=cfg.step_s, lane=cfg.start_lane,
                                      max_steps=n_max + 1)
        self.s, self.d, self.v = cfg.start_s_m, n74.lane_centre_offset(cfg.start_lane), \
            cfg.start_speed_mps
        self.yaw = float(geo.heading_at(self.s))
        self.cols: dict[str, list[float]] = {k: [] for k in (
            "time", "x", "y", "yaw", "v_x", "left_c0", "left_c1", "left_c2", "left_c3",
            "right_c0", "right_c1", "right_c2", "right_c3", "lead_x", "lead_y", "lead_v",
            "lane_index", "s_road", "d_road", "accel")}
        self.leader_ids: list[str] = []
        self.k = 0
        self.ego_id = EGO_ID
        self.api: sumo_api.SumoApi | None = None

    def pose_at(self, t: float) -> Pose:
        """Its front bumper ``x, y`` [m], heading [rad] and speed [m/s] now (the loop asks at
        t = 0 for its initial pose)."""
        x, y = self.geo.frenet_to_xy(self.s, self.d)
        return float(x), float(y), self.yaw, self.v

    def enter(self, api: sumo_api.SumoApi, ego_id: str) -> None:
        """SUMO's traffic for ``warmup_s``, then the ego added where its start spot is free,
        its neighbourhood subscribed (``view_m``) and put at its initial pose."""
        cfg = self.cfg
        self.api, self.ego_id = api, ego_id
        warm_up(api, cfg.warmup_s, cfg.step_s)
        add_when_clear(api, ego_id, "ego_route", n74.main_route(self.geo), cfg.start_lane,
                       cfg.start_s_m, cfg.start_speed_mps, "ego", cfg.step_s)
        api.vehicle.subscribeContext(ego_id, CMD_GET_VEHICLE_VARIABLE, cfg.view_m,
                                     [VAR_POSITION, VAR_SPEED, VAR_ANGLE, VAR_LENGTH, VAR_WIDTH])
        x, y, yaw, v = self.pose_at(0.0)
        api.vehicle.moveToXY(ego_id, "", -1, x, y, yaw_to_sumo_angle(yaw), keepRoute=2)
        api.vehicle.setSpeed(ego_id, v)

    def drive(self, api: sumo_api.SumoApi, t: float) -> Pose:
        """One step: sensors logged at the current pose, the driver's command, the kinematic
        move; the pose after it."""
        cfg, geo, s, d, v, yaw = self.cfg, self.geo, self.s, self.d, self.v, self.yaw
        road, ref, _ = self.windows.at(s)
        xy = geo.frenet_to_xy(s, d)
        others = read_others(api, self.ego_id)
        # sensors: the closed loop's code
        left, right, lane_idx = sen.camera_lane_lines(road, xy, yaw, cfg.sensors)
        target, lead_id = radar_lead(others, xy, yaw, left, right, cfg.sensors)
        self.leader_ids.append(lead_id)
        _log(self.cols, self.k * cfg.step_s, xy, yaw, v, left, right, target, lane_idx, s, d)
        # driver
        kappa_ahead = float(geo.kappa_at(s + v * self.params.curve_preview_s))
        cmd = self.driver.step(Observation(v, perceived_gaps(ref, xy, others), kappa_ahead,
                                           n74.LANE_WIDTH_M))
        self.cols["accel"].append(cmd.accel)
        # kinematic ego along the road; the loop moves it in SUMO and steps
        self.s, self.d, self.v, self.yaw = kinematic_step(geo, s, d, v, cmd.accel,
                                                          cmd.lateral_m, cfg.step_s)
        self.k += 1
        return self.pose_at(t)

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Not a planner: the closed loop calls :meth:`drive` instead."""
        raise TypeError("the synthetic ego drives itself: the closed loop calls drive()")


def recording_scenario(cfg: RecordingConfig, n_max: int) -> tuple[Scenario, LoopConfig]:
    """The closed loop's scenario and settings of a recording: the n74 road from the ego's
    start in its start lane (the loop's lane monitors; its path end beyond ``end_margin_m``),
    no leader of the loop's, a time limit after the recording's ``n_max`` steps; one decision
    per step, the ego placed with ``moveToXY``, no brake guard (nothing is planned)."""
    road = n74.stretch_road(cfg.start_s_m / 1000.0, lane=("right", "left")[cfg.start_lane],
                            net_dir=Path(cfg.net_dir))
    scenario = Scenario(f"record {cfg.recording_id}", road, None, cfg.start_speed_mps,
                        seed=cfg.seed, max_time_s=(n_max + 1) * cfg.step_s, sensors=cfg.sensors)
    loop = LoopConfig(step_s=cfg.step_s, plan_rate_hz=1.0 / cfg.step_s, ego_placement="xy",
                      brake_guard=None)
    return scenario, loop


def record_drive(params: DriverParams, cfg: RecordingConfig = RecordingConfig(),
                 geo: n74.N74Geometry | None = None) -> pd.DataFrame:
    """Drive one synthetic driver on n74 and return the validated drive frame.

    ``df.attrs["recording_stats"]`` holds counts (steps, leader samples, lane changes, leader
    switches, collisions) and timings. SUMO is always closed.
    """
    geo = geo or n74.n74_geometry(_layout_seed(cfg))
    dt = cfg.step_s
    s_end = geo.length - cfg.end_margin_m
    max_t = cfg.duration_s if cfg.duration_s is not None else 3.0 * geo.length / 10.0
    n_max = math.ceil(max_t / dt)
    ego = SyntheticEgo(params, cfg, geo, n_max)
    scenario, loop_cfg = recording_scenario(cfg, n_max)

    wall0 = time.perf_counter()
    # SUMO with the recorder's options (its route files, teleports), not the loop's
    with ClosedLoop(loop_cfg, api_factory=lambda _args: sumo_api.start(sumo_args(cfg))) as loop:
        loop.reset([scenario], [ego])
        assert ego.api is not None, "the ego entered SUMO in reset"
        t0 = ego.api.simulation.getTime()
        wall_sim0 = time.perf_counter()
        while ego.k < n_max and ego.s < s_end:
            if not loop.advance()[0]:
                raise RuntimeError(f"the closed loop ended the recording {cfg.recording_id}: "
                                   f"{loop.end_reasons[0]}")
        sim_time = ego.api.simulation.getTime() - t0
        collisions = int(loop.rollout(0).log["collision"].sum())
    wall = time.perf_counter() - wall0
    df = pd.DataFrame(ego.cols)
    df.insert(0, "recording_id", cfg.recording_id)
    out = validate_drive(df, f"recording {cfg.recording_id}")
    out.attrs["recording_stats"] = {
        **recording_stats(df, ego.leader_ids, cfg, sim_time, collisions),
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
