"""Closed-loop tasks as data: a :class:`Task` is a :class:`ScenarioSpec` (the road, the leader,
the ego's start, the sensors), a :class:`~safeil_sumo.planners.registry.PlannerRef` (which
planner) and a :class:`~safeil_sumo.sim.loop_types.LoopConfig` (how the loop runs), each a
frozen dataclass, the three JSON-able as one flat object.

The scenario layer of every closed-loop engine (one run, a sweep, the suite, the gap probe,
falsification): :func:`resolve_road` loads a scenario's road (cached per process),
:func:`build_scenario` draws the rest from the scenario seed (``scenario_seed(master_seed,
index)``), so a task is identical alone or in a sweep of any size. The command-line options of
a scenario are made from its fields (:func:`safeil_sumo.cli_args.add_scenario_options`). Running
tasks (processes, Dask, resume) is :mod:`safeil_sumo.experiments.sweep_executor`'s, on the task
engine (:mod:`safeil_sumo.experiments.task_engine`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.sim.brake_guard import BrakeGuard
from safeil_sumo.sim.brake_guard import when as brake_guard_when
from safeil_sumo.sim.loop_types import LoopConfig
from safeil_sumo.sim.traffic import DENSITIES

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


def _opt(help_: str, flag: str | None = None, **kw: Any) -> dict[str, Any]:
    """A field's command-line metadata: its help, and its flag when not ``--<field-name>``
    (:func:`safeil_sumo.cli_args.add_scenario_options` makes the options from these)."""
    return {"help": help_, "flag": flag, **kw}


@dataclass(frozen=True)
class ScenarioSpec:
    """One closed-loop scenario, JSON-able: the road, the leader, the ego's start, the sensors
    and the duration; which planner drives it and how the loop runs are the :class:`Task`'s
    other parts. Ranges are ``(low, high)``; draws are uniform."""

    net: str = "curved500"  # catalogue name (curved500, straight, curved<R>) or .net.xml path
    index: int = 0  # scenario index within the master seed [-]
    master_seed: int = field(default=0, metadata=_opt(
        "master seed: with the scenario index, the scenario seed (SUMO, sensors, draws)",
        "--seed"))
    leader_kind: str = field(default="constant", metadata=_opt(
        "constant speed (the paper); braking or accelerating (to --brake-to-mps at "
        "--brake-decel-mps2 after --brake-time-s); or recorded (a human leader's speed "
        "profile, the ego starting as the recorded follower did, or behind a profile file at "
        "the leader's speed)", "--leader", choices=LEADER_KINDS))
    leader_speed_range_mps: tuple[float, float] = field(default=(25.0, 32.0), metadata=_opt(
        "leader (initial) speed range [m/s], drawn per scenario (the paper's)",
        metavar=("LOW", "HIGH")))
    brake_time_s: float = field(default=5.0, metadata=_opt(
        "braking/accelerating leader: the change starts at [s]"))
    brake_decel_mps2: float = field(default=3.0, metadata=_opt(
        "braking/accelerating leader: rate of the change [m/s^2]"))
    brake_to_mps: float = field(default=15.0, metadata=_opt(
        "braking/accelerating leader: final speed [m/s]"))
    # None: DEFAULT_EGO_SPEED_MPS, or behind a recorded leader the recording's start (the
    # recorded follower's speed, or the leader's own speed for a profile file:
    # :func:`safeil_sumo.scenarios.recorded_leaders.draw`); stays None in the JSON then
    ego_speed_mps: float | None = field(default=None, metadata=_opt(
        f"ego initial speed [m/s] (default {DEFAULT_EGO_SPEED_MPS:g}; with --leader recorded: "
        "as the recorded follower started (ngsim, openacc), or the profile's speed where the "
        "scenario starts in it (a file); a speed given here wins)"))
    initial_gap_m: float | tuple[float, float] = field(default=50.0, metadata=_opt(
        "initial bumper gap [m]", "--gap-m"))  # or a (low, high) range: --gap-range-m
    lane_noise_c0_m: float = field(default=0.0, metadata=_opt(
        "camera lane-offset (c0) noise std [m]", "--lane-noise-m"))
    radar_noise_m: float = field(default=0.0, metadata=_opt("radar range noise std [m]"))
    max_time_s: float | None = field(default=None, metadata=_opt(
        "scenario duration [s] (default: 2x the path at the ego speed + 10 s)"))
    # "" (other kinds) is left out of the JSON, so the task ids of specs without it are those
    # of earlier versions
    leader_profile: str = field(default="", metadata=_opt(
        "with --leader recorded: ngsim (default) or openacc (from ../shared/data), or a "
        "CSV/Parquet file with columns time [s] and speed [m/s], or a folder of them"))
    # left out of the JSON when empty, like leader_profile
    route: tuple[str, ...] = field(default=(), metadata=_opt(
        "SUMO edges the ego drives, in driving order, on a multi-edge .net.xml (its lane is "
        "followed across the junctions; the route must end where that lane ends) (default: "
        "the net's one edge)", metavar="EDGE"))
    # net="n74": the stretch of direction A between these kilometre posts
    # (:func:`safeil_sumo.roads.n74.stretch_road`); left out of the JSON when None
    from_km: float | None = field(default=None, metadata=_opt(
        "with --net n74: start of the stretch driven, kilometre post of direction A (default "
        "0)"))
    to_km: float | None = field(default=None, metadata=_opt(
        "with --net n74: end of the stretch (default 29.2, the whole carriageway)"))
    # background traffic of the net's route files: "" (none) or a density of
    # :data:`safeil_sumo.sim.traffic.DENSITIES`; it replaces the scripted leader. Left out of
    # the JSON when ""
    traffic: str = field(default="", metadata=_opt(
        "with --net n74: SUMO's own traffic from sumo_scenarios/n74/n74.rou.xml (main road + "
        "on-ramps), flows scaled x0.5 light, x1 default, x2 dense, seeded by the scenario "
        "seed; the ego's leader is whichever vehicle is ahead in its lane (no scripted "
        "leader) (default none)", choices=("none", *DENSITIES)))
    # :func:`lane_for_net`; left out of the JSON when ""
    lane: str = field(default="", metadata=_opt(
        "the ego's lane: with --net n74 the main lane, right (the default) or left; with a "
        ".net.xml path the SUMO lane index (0 = rightmost) on the first edge of --route (or of "
        "the net's one edge) (default: the middle lane)"))

    def __post_init__(self) -> None:
        self._normalise()
        self._check_numbers()
        self._check_leader()
        self._check_ego()
        self._check_road()

    def _normalise(self) -> None:
        """Normalise types so that 25 and 25.0, or a JSON list and a tuple, hash the same."""
        set_ = object.__setattr__
        set_(self, "net", str(self.net))
        set_(self, "leader_profile", str(self.leader_profile))
        route = self.route.split() if isinstance(self.route, str) else self.route
        set_(self, "route", tuple(str(e) for e in route))
        if self.leader_kind == "recorded" and not self.leader_profile:
            set_(self, "leader_profile", "ngsim")
        if self.ego_speed_mps is None and self.leader_kind != "recorded":
            set_(self, "ego_speed_mps", DEFAULT_EGO_SPEED_MPS)  # the JSON of earlier versions
        set_(self, "index", int(self.index))
        set_(self, "master_seed", int(self.master_seed))
        set_(self, "leader_speed_range_mps", _pair(self.leader_speed_range_mps, "leader speed"))
        gap = self.initial_gap_m
        set_(self, "initial_gap_m", float(gap) if isinstance(gap, numbers.Real)
             else _pair(gap, "initial gap"))
        for name in ("brake_time_s", "brake_decel_mps2", "brake_to_mps",
                     "lane_noise_c0_m", "radar_noise_m"):
            set_(self, name, float(getattr(self, name)))
        for name in ("max_time_s", "ego_speed_mps", "from_km", "to_km"):
            if getattr(self, name) is not None:
                set_(self, name, float(getattr(self, name)))
        set_(self, "traffic", "" if self.traffic in ("", "none", None) else str(self.traffic))
        set_(self, "lane", "" if self.lane in ("", None) else str(self.lane))

    def _check_numbers(self) -> None:
        """Non-negative seeds, every float finite."""
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

    def _check_ego(self) -> None:
        """The ego's speed and the sensors' noise."""
        if self.ego_speed_mps is not None and not 0 <= self.ego_speed_mps <= MAX_SPEED_MPS:
            raise ValueError(f"ego speed must be in [0, {MAX_SPEED_MPS:g}] m/s, "
                             f"got {self.ego_speed_mps}")
        if self.lane_noise_c0_m < 0 or self.radar_noise_m < 0:
            raise ValueError("sensor noise must be >= 0")

    def _check_road(self) -> None:
        """The net's route, stretch, traffic and lane, and the duration."""
        if self.net == "n74" and self.route:
            raise ValueError("--net n74 drives a stretch of --from-km/--to-km; --route needs a "
                             ".net.xml path (e.g. sumo_scenarios/n74/n74.net.xml)")
        if (self.from_km is not None or self.to_km is not None) and self.net != "n74":
            raise ValueError("--from-km/--to-km need --net n74")
        if self.traffic:
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
        if out["route"]:
            out["route"] = list(out["route"])
        for name in ("leader_profile", "route", "from_km", "to_km", "traffic", "lane"):
            if out[name] in ("", (), None):
                del out[name]
        return out


# the loop settings a task sets (the rest of LoopConfig is how a command runs it: a backend,
# sumo-gui, SSM output) and the JSON keys of a task, in the order of its table columns
LOOP_FIELDS = ("plan_rate_hz", "stop_on_flag", "brake_guard")
TASK_KEYS = ("net", "index", "master_seed", "policy", "safety_filter", "brake_guard",
             "leader_kind", "leader_speed_range_mps", "brake_time_s", "brake_decel_mps2",
             "brake_to_mps", "ego_speed_mps", "initial_gap_m", "lane_noise_c0_m",
             "radar_noise_m", "plan_rate_hz", "max_time_s", "stop_on_flag", "leader_profile",
             "route", "from_km", "to_km", "traffic", "lane", "time_gap_s", "standstill_m",
             "style_changes")


@dataclass(frozen=True)
class Task:
    """One closed-loop task: a scenario, the planner that drives it and how the loop runs, each
    a frozen dataclass. JSON-able as one flat object (:meth:`to_json`; a sweep's task id hashes
    it); the loop sets only :data:`LOOP_FIELDS`, its brake guard the shipped one or none."""

    scenario: ScenarioSpec = field(default_factory=ScenarioSpec)
    planner: PlannerRef = field(default_factory=PlannerRef)
    loop: LoopConfig = field(default_factory=LoopConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.scenario, ScenarioSpec) or not isinstance(
                self.planner, PlannerRef) or not isinstance(self.loop, LoopConfig):
            raise TypeError("a Task is a ScenarioSpec, a PlannerRef and a LoopConfig")
        if self.loop.brake_guard not in (None, BrakeGuard()):
            raise ValueError("a task's loop has the shipped brake guard or none")
        others = replace(self.loop, **{name: getattr(LoopConfig(), name) for name in LOOP_FIELDS})
        if others != LoopConfig():
            raise ValueError(f"a task's loop sets only {', '.join(LOOP_FIELDS)}")

    @property
    def brake_guard(self) -> bool:
        """Whether the loop has the brake guard."""
        return self.loop.brake_guard is not None

    def to_json(self) -> dict[str, Any]:
        """The three parts' fields in one object (keys in :data:`TASK_KEYS` order).
        ``brake_guard`` is there only when on: tasks of the versions before the guard, which
        ran without it, keep their ids as guard-off tasks."""
        out = {**self.scenario.to_json(), **self.planner.to_json(),
               "plan_rate_hz": float(self.loop.plan_rate_hz),
               "stop_on_flag": bool(self.loop.stop_on_flag)}
        if self.brake_guard:
            out["brake_guard"] = True
        return {k: out[k] for k in TASK_KEYS if k in out}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Task:
        """The task of :meth:`to_json`'s object (no ``brake_guard``: off; any other key left
        out has its part's default)."""
        return cls.of(**{"brake_guard": False, **data})

    @classmethod
    def of(cls, **fields_: Any) -> Task:
        """The task of flat fields (:data:`TASK_KEYS`, as a sweep file names them), each given
        to its part; any left out has its part's default (the brake guard on, as shipped)."""
        unknown = set(fields_) - set(TASK_KEYS)
        if unknown:
            raise ValueError(f"unknown task fields: {sorted(unknown)}")
        return cls(*_split_fields(fields_))


def _split_fields(data: dict[str, Any]) -> tuple[ScenarioSpec, PlannerRef, LoopConfig]:
    """A task's flat fields as its three parts."""
    planner_keys = {f.name for f in fields(PlannerRef)}
    scenario = ScenarioSpec(**{k: v for k, v in data.items()
                               if k not in planner_keys and k not in LOOP_FIELDS})
    planner = PlannerRef(**{k: v for k, v in data.items() if k in planner_keys})
    loop = LoopConfig(plan_rate_hz=float(data.get("plan_rate_hz", LoopConfig.plan_rate_hz)),
                      stop_on_flag=bool(data.get("stop_on_flag", False)),
                      brake_guard=brake_guard_when(bool(data.get("brake_guard", True))))
    return scenario, planner, loop


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
