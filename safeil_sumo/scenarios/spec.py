"""Scenarios as data: a JSON-able :class:`ScenarioSpec`, its road and its built :class:`Scenario`.

The scenario layer of every closed-loop engine (one run, a sweep, the suite, the gap probe): a
spec names the net, the policy, the leader and the sensors; :func:`resolve_road` loads its road
(cached per process), :func:`build_scenario` draws the rest from the scenario seed
(``scenario_seed(master_seed, index)``), so a task is identical alone or in a sweep of any size.
Running specs (processes, Dask, resume) is :mod:`safeil_sumo.experiments.sweep_executor`'s, on the task
engine (:mod:`safeil_sumo.experiments.task_engine`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from safeil_sumo.core.policy import PLAN_RATE_HZ

if TYPE_CHECKING:
    from safeil_sumo.sim.leaders import SpeedProfile

LEADER_KINDS = ("constant", "braking", "accelerating", "recorded")
MAX_SPEED_MPS = 100.0  # [m/s] above: a unit mistake (SUMO refuses such departures)
DEFAULT_EGO_SPEED_MPS = 30.0  # [m/s] the ego's start speed unless given (~108 km/h)
N74_LANES = ("right", "left")  # --lane with --net n74: the main lanes of direction A


def lane_for_net(net: str, lane: str | None) -> str:
    """``--lane`` checked against ``--net``: ``""`` (the default lane), ``right``/``left`` (n74)
    or a SUMO lane index as text (a ``.net.xml``). Raises ``ValueError`` with a one-line reason;
    whether the index exists on the first edge is checked when the net is read."""
    if lane is None:
        return ""
    if net == "n74":
        if lane not in N74_LANES:
            raise ValueError(f"--lane with --net n74 is right or left (its main lanes), got "
                             f"{lane!r}")
        return lane
    if not net.endswith(".xml"):
        raise ValueError(f"--lane needs --net n74 or a .net.xml path; the {net} track is built "
                         "around its middle lane")
    if not lane.isdigit():
        raise ValueError(f"--lane with a .net.xml is a SUMO lane index >= 0 on the first edge, "
                         f"got {lane!r}")
    return str(int(lane))


@dataclass(frozen=True)
class ScenarioSpec:
    """One closed-loop task, JSON-able. Ranges are ``(low, high)``; draws are uniform."""

    net: str = "curved500"  # catalogue name (curved500, straight, curved<R>) or .net.xml path
    index: int = 0  # scenario index within the master seed [-]
    master_seed: int = 0  # with ``index`` gives the scenario seed (SUMO, sensors, draws) [-]
    # a name of safeil_sumo.planners.registry.NAMES or a checkpoint/IDM path
    policy: str = "analytic"
    safety_filter: bool = False  # wrap the policy in the inference-time safety filter
    # collision-avoidance braking under the planner (safeil_sumo.sim.brake_guard); False: the
    # planner and tracker alone, the paper's loop. In the JSON only when True: specs of earlier
    # versions, which ran without it, keep their task ids as brake_guard=False
    brake_guard: bool = True
    leader_kind: str = "constant"  # "constant" | "braking" | "accelerating" | "recorded"
    leader_speed_range_mps: tuple[float, float] = (25.0, 32.0)  # leader (initial) speed [m/s]
    brake_time_s: float = 5.0  # braking/accelerating leader: the change starts at this time [s]
    brake_decel_mps2: float = 3.0  # braking/accelerating leader: rate of the change [m/s^2]
    brake_to_mps: float = 15.0  # braking/accelerating leader: final speed [m/s]
    # ego initial speed [m/s]; None: DEFAULT_EGO_SPEED_MPS, or behind a recorded leader the
    # recording's start (the recorded follower's speed, or the leader's own speed for a profile
    # file: :func:`safeil_sumo.scenarios.recorded_leaders.draw`); stays None in the JSON then
    ego_speed_mps: float | None = None
    initial_gap_m: float | tuple[float, float] = 50.0  # bumper gap, fixed or (low, high) [m]
    lane_noise_c0_m: float = 0.0  # std of camera lane-offset noise [m]
    radar_noise_m: float = 0.0  # std of radar range noise [m]
    plan_rate_hz: float = PLAN_RATE_HZ  # re-planning rate [Hz]
    max_time_s: float | None = None  # scenario duration; None: the loop's default [s]
    stop_on_flag: bool = False  # end the scenario at its first safety flag
    # recorded leader: "ngsim", "openacc" or a CSV/Parquet profile file or folder
    # (:mod:`safeil_sumo.scenarios.recorded_leaders`); "" (other kinds) is left out of the JSON,
    # so the task ids of specs without it are those of earlier versions
    leader_profile: str = ""
    # SUMO edges the ego drives, in order, on a multi-edge ``net`` (:mod:`safeil_sumo.scenarios.
    # route`); () = the net's one edge. Left out of the JSON when empty, like leader_profile
    route: tuple[str, ...] = ()
    # ``net="n74"``: the stretch of direction A between these kilometre posts (None: its start /
    # end; :func:`safeil_sumo.roads.n74.stretch_road`); left out of the JSON when None
    from_km: float | None = None
    to_km: float | None = None
    # background traffic of the net's route files: "" (none) or a density of
    # :data:`safeil_sumo.sim.traffic.DENSITIES`; it replaces the scripted leader. Left out of the
    # JSON when ""
    traffic: str = ""
    # the ego's lane: "" (the net's default), "right"/"left" on n74, a SUMO lane index of the
    # first edge (as text) on a .net.xml (:func:`lane_for_net`); left out
    # of the JSON when ""
    lane: str = ""
    # the planner's preferred time gap [s] (an ACC's distance setting,
    # :func:`safeil_sumo.planners.registry.with_time_gap`); None: its default; left out of the
    # JSON then
    time_gap_s: float | None = None

    def __post_init__(self) -> None:
        self._normalise()
        self._check_numbers()
        self._check_leader()
        self._check_ego_and_loop()
        self._check_road()

    def _normalise(self) -> None:
        """Normalise types so that 25 and 25.0, or a JSON list and a tuple, hash the same."""
        set_ = object.__setattr__
        set_(self, "net", str(self.net))
        set_(self, "policy", str(self.policy))
        set_(self, "leader_profile", str(self.leader_profile))
        route = self.route.split() if isinstance(self.route, str) else self.route
        set_(self, "route", tuple(str(e) for e in route))
        if self.leader_kind == "recorded" and not self.leader_profile:
            set_(self, "leader_profile", "ngsim")
        if self.ego_speed_mps is None and self.leader_kind != "recorded":
            set_(self, "ego_speed_mps", DEFAULT_EGO_SPEED_MPS)  # the JSON of earlier versions
        set_(self, "index", int(self.index))
        set_(self, "master_seed", int(self.master_seed))
        set_(self, "safety_filter", bool(self.safety_filter))
        set_(self, "brake_guard", bool(self.brake_guard))
        set_(self, "stop_on_flag", bool(self.stop_on_flag))
        set_(self, "leader_speed_range_mps", _pair(self.leader_speed_range_mps, "leader speed"))
        gap = self.initial_gap_m
        set_(self, "initial_gap_m", float(gap) if isinstance(gap, numbers.Real)
             else _pair(gap, "initial gap"))
        for name in ("brake_time_s", "brake_decel_mps2", "brake_to_mps",
                     "lane_noise_c0_m", "radar_noise_m", "plan_rate_hz"):
            set_(self, name, float(getattr(self, name)))
        for name in ("max_time_s", "ego_speed_mps", "from_km", "to_km", "time_gap_s"):
            if getattr(self, name) is not None:
                set_(self, name, float(getattr(self, name)))
        set_(self, "traffic", "" if self.traffic in ("", "none", None) else str(self.traffic))
        set_(self, "lane", "" if self.lane in ("", None) else str(self.lane))

    def _check_numbers(self) -> None:
        """The time gap's range, non-negative seeds, every float finite."""
        if self.time_gap_s is not None and not (0 < self.time_gap_s <= 10):
            raise ValueError(f"time gap must be in (0, 10] s, got {self.time_gap_s}")
        if self.index < 0 or self.master_seed < 0:
            raise ValueError(f"scenario index and master seed must be >= 0, got {self.index}, "
                             f"{self.master_seed}")
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.type == "float"}
        values |= {"leader_speed_range_mps": self.leader_speed_range_mps,
                   "initial_gap_m": self.gap_range_m, "max_time_s": self.max_time_s or 1.0,
                   "ego_speed_mps": 0.0 if self.ego_speed_mps is None else self.ego_speed_mps}
        for name, value in values.items():  # NaN passes every < / > check below
            if not all(math.isfinite(v) for v in np.atleast_1d(value)):
                raise ValueError(f"{name} must be finite (no NaN/inf), got {value}")

    def _check_leader(self) -> None:
        """The leader's kind, speeds, gap, speed change and profile."""
        if self.leader_kind not in LEADER_KINDS:
            raise ValueError(f"leader kind must be one of {LEADER_KINDS}, got {self.leader_kind!r}")
        lo, hi = self.leader_speed_range_mps
        if not 0 <= lo <= hi <= MAX_SPEED_MPS:
            raise ValueError(f"leader speed range needs 0 <= low <= high <= {MAX_SPEED_MPS:g} "
                             f"m/s, got {lo}, {hi}")
        glo, ghi = self.gap_range_m
        if not 0 < glo <= ghi:
            raise ValueError(f"initial gap needs 0 < low <= high, got {glo}, {ghi}")
        if self.leader_kind in ("braking", "accelerating") and (
                self.brake_time_s < 0 or self.brake_decel_mps2 <= 0 or self.brake_to_mps < 0):
            raise ValueError(f"{self.leader_kind} leader needs a start time >= 0 s, a rate > 0 "
                             "m/s^2 and a final speed >= 0 m/s")
        if self.leader_profile and self.leader_kind != "recorded":
            raise ValueError("a leader profile needs leader kind 'recorded'")

    def _check_ego_and_loop(self) -> None:
        """The ego's speed, the sensors' noise and the plan rate."""
        if self.ego_speed_mps is not None and not 0 <= self.ego_speed_mps <= MAX_SPEED_MPS:
            raise ValueError(f"ego speed must be in [0, {MAX_SPEED_MPS:g}] m/s, "
                             f"got {self.ego_speed_mps}")
        if self.lane_noise_c0_m < 0 or self.radar_noise_m < 0:
            raise ValueError("sensor noise must be >= 0")
        if not 0 < self.plan_rate_hz <= 100:  # the loop's step is 0.01 s
            raise ValueError(f"plan rate must be in (0, 100] Hz, got {self.plan_rate_hz}")

    def _check_road(self) -> None:
        """The net's route, stretch, traffic and lane, and the duration."""
        if self.net == "n74" and self.route:
            raise ValueError("--net n74 drives a stretch of --from-km/--to-km; --route needs a "
                             ".net.xml path (e.g. sumo_scenarios/n74/n74.net.xml)")
        if (self.from_km is not None or self.to_km is not None) and self.net != "n74":
            raise ValueError("--from-km/--to-km need --net n74")
        if self.traffic:
            from safeil_sumo.sim.traffic import DENSITIES

            if self.traffic not in DENSITIES:
                raise ValueError(f"traffic must be one of none, {', '.join(DENSITIES)}, got "
                                 f"{self.traffic!r}")
            if self.net != "n74":
                raise ValueError("--traffic needs --net n74 (the net with traffic route files)")
        if self.max_time_s is not None and not self.max_time_s > 0:
            raise ValueError(f"max time must be > 0 s, got {self.max_time_s}")
        if self.lane:
            lane_for_net(self.net, self.lane)

    @property
    def gap_range_m(self) -> tuple[float, float]:
        """``initial_gap_m`` as a ``(low, high)`` range [m] (low == high when fixed)."""
        gap = self.initial_gap_m
        return (gap, gap) if isinstance(gap, float) else gap

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        if not out["leader_profile"]:
            del out["leader_profile"]
        if out["route"]:
            out["route"] = list(out["route"])
        else:
            del out["route"]
        for name in ("from_km", "to_km", "time_gap_s"):
            if out[name] is None:
                del out[name]
        if not out["traffic"]:
            del out["traffic"]
        if not out["lane"]:
            del out["lane"]
        if not out["brake_guard"]:
            del out["brake_guard"]
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ScenarioSpec:
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown ScenarioSpec fields: {sorted(unknown)}")
        return cls(**data)


def _pair(value: Any, what: str) -> tuple[float, float]:
    try:
        lo, hi = value
        return float(lo), float(hi)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a (low, high) pair, got {value!r}") from None


_ROADS: dict[tuple, Any] = {}  # per-process cache: (net, route) -> Road (geometry read once)


def resolve_road(net: str, route: tuple[str, ...] = (), from_km: float | None = None,
          to_km: float | None = None, lane: str = ""):
    """The road of ``net`` (a catalogue name or ``.net.xml`` path), along ``route`` if given;
    ``n74`` without a route: its stretch ``from_km``-``to_km`` (default the whole carriageway).
    ``lane`` (see :attr:`ScenarioSpec.lane`): ``right``/``left`` on n74, a SUMO lane index of
    the first edge on a ``.net.xml``."""
    from safeil_sumo.roads.catalogue import resolve_net
    from safeil_sumo.roads.road import NetworkError, load_road
    from safeil_sumo.roads.route import load_route

    key = (net, tuple(route), from_km, to_km, lane or "")
    if key not in _ROADS:
        if lane:
            try:
                lane = lane_for_net(net, lane)
            except ValueError as exc:
                raise NetworkError(str(exc)) from None
        if net == "n74" and not route:
            from safeil_sumo.roads.n74 import stretch_road

            _ROADS[key] = stretch_road(from_km or 0.0, to_km, lane=lane or "right")
        elif from_km is not None or to_km is not None:
            raise NetworkError("--from-km/--to-km apply to --net n74 (without --route) only")
        else:
            path = resolve_net(net)
            index = int(lane) if lane else None
            _ROADS[key] = (load_route(path, route, index) if route
                           else load_road(path, ego_lane=index))
    return _ROADS[key]


def leader_profile(spec: ScenarioSpec, speed_mps: float) -> SpeedProfile:
    """The leader's :class:`SpeedProfile` for an initial speed ``speed_mps`` [m/s]."""
    from safeil_sumo.sim.leaders import constant, piecewise

    target = spec.brake_to_mps
    changes = (spec.leader_kind == "braking" and target < speed_mps) or (
        spec.leader_kind == "accelerating" and target > speed_mps)
    if not changes:
        return constant(speed_mps)
    t0 = spec.brake_time_s
    t1 = t0 + abs(speed_mps - target) / spec.brake_decel_mps2
    if t0 <= 0.0:  # changes from the start
        return piecewise([0.0, t1], [speed_mps, target])
    return piecewise([0.0, t0, t1], [speed_mps, speed_mps, target])


def build_scenario(spec: ScenarioSpec, road):
    """The runner's :class:`Scenario` of a spec (every draw from the scenario seed)."""
    from safeil_sumo.scenarios.safety import scenario_seed
    from safeil_sumo.sim.loop_types import Scenario
    from safeil_sumo.sim.sensors import SensorConfig

    seed = scenario_seed(spec.master_seed, spec.index)
    rng = np.random.default_rng(seed)
    speed = float(rng.uniform(*spec.leader_speed_range_mps))  # first draw: as safety_scenario
    glo, ghi = spec.gap_range_m
    gap = float(rng.uniform(glo, ghi)) if ghi > glo else glo
    ego_speed, max_time, limit_reason = spec.ego_speed_mps, spec.max_time_s, "timeout"
    leader: SpeedProfile | None
    if spec.leader_kind == "recorded":  # the recording's leader and its follower's start
        from safeil_sumo.scenarios import recorded_leaders as rl

        drawn = rl.draw(rl.library(spec.leader_profile), rng, spec.max_time_s)
        leader = drawn.profile
        ego_speed = drawn.ego_speed_mps if ego_speed is None else ego_speed  # given: it wins
        gap = drawn.initial_gap_m if drawn.initial_gap_m is not None else gap
        # the recording ends the run unless a shorter duration was asked for
        limit_reason = ("recording_end" if drawn.duration_s < (max_time or math.inf)
                        else "timeout")
        max_time = min(max_time or math.inf, drawn.duration_s)
    else:
        leader = leader_profile(spec, speed)
    # given, or the recording's; __post_init__ sets the default for every other leader kind
    assert ego_speed is not None
    traffic = None
    if spec.traffic:  # SUMO's vehicles are the leaders: no scripted one
        from safeil_sumo.sim.traffic import n74_traffic

        traffic, leader = n74_traffic(spec.traffic), None
    return Scenario(
        name=f"s{spec.index:04d}", road=road, leader=leader,
        ego_speed_mps=ego_speed, initial_gap_m=gap, seed=seed,
        max_time_s=max_time, time_limit_reason=limit_reason,
        sensors=SensorConfig(lane_noise_c0_m=spec.lane_noise_c0_m,
                             radar_noise_m=spec.radar_noise_m),
        traffic=traffic,
    )
