"""A synthetic human highway driver, calibrated on real humans (OpenACC, NGSIM) — no SUMO calls.

Longitudinal: the Intelligent Driver Model (IDM, Treiber et al. 2000) with the human-driver
extensions of the Human Driver Model (HDM, Treiber, Kesting & Helbing 2006):
- a reaction delay ``reaction_time_s``: the acceleration applied at ``t`` is the one the driver
  decided on from what they perceived at ``t - reaction_time_s`` (linear interpolation between
  steps, so the delay need not be a multiple of the step);
- perception errors as Ornstein-Uhlenbeck (OU) processes of unit variance and correlation time
  ``perception_tau_s``: the gap is seen as ``s exp(gap_error_rel w_s)`` and the approach rate as
  ``dv - s inv_ttc_error_ps w_r`` (HDM's estimation errors; values from the HDM paper);
- a reflex that needs no reaction time: below a time-to-collision of ``reflex_ttc_s`` the driver
  brakes on the CURRENT (noise-free) situation as well (keeps the delayed model collision-free).

Lateral: the driver holds an offset from the lane centre made of a per-driver bias
``lateral_bias_m``, a slow OU wander (``wander_std_m``, ``wander_tau_s``; fitted to NGSIM) and
curve cutting towards the inside, ``curve_cut_m2 * kappa`` with the curvature ``kappa`` [1/m]
``curve_preview_s`` ahead (0.35 m at R = 800 m by default: an assumption, see the docs).

Lane changes (optional, removable by the pipeline through ``lane_index``): in the right lane,
when the leader is slower than the desired speed by ``overtake_speed_gain_mps`` and is close,
and the left lane has room, the driver starts an overtake with hazard rate
``lane_change_rate_ps``; in the left lane the driver returns right (keep-right rule) once the
right lane has room. A change moves the lateral target with a quintic smoothstep over
``lane_change_duration_s``.

Everything random draws from an explicit ``np.random.Generator``; the maths are pure functions,
:class:`SyntheticDriver` only holds the state between steps.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np

PARAMS_JSON = Path(__file__).with_name("driver_params.json")


@dataclass(frozen=True)
class DriverParams:
    """One driver's parameters (SI units). Defaults: calibrated medians (see driver_params.json)."""

    # --- longitudinal: IDM -----------------------------------------------------------------
    desired_speed_mps: float = 33.0  # v0 [m/s]
    time_headway_s: float = 1.3  # T [s] desired time gap
    min_gap_m: float = 3.0  # s0 [m] bumper gap at standstill
    max_accel_mps2: float = 1.0  # a [m/s^2]
    comfort_decel_mps2: float = 1.5  # b [m/s^2]
    accel_exponent: float = 4.0  # delta [-]
    max_decel_mps2: float = 8.0  # [m/s^2] physical braking limit
    # --- human extensions (HDM) --------------------------------------------------------------
    reaction_time_s: float = 0.6  # [s]
    gap_error_rel: float = 0.1  # [-] std of the log gap-perception error (HDM V_s)
    inv_ttc_error_ps: float = 0.01  # [1/s] std of the inverse-TTC perception error (HDM sigma_r)
    perception_tau_s: float = 20.0  # [s] correlation time of the perception errors (HDM)
    reflex_ttc_s: float = 2.0  # [s] below this TTC the driver also brakes without delay
    # --- lateral ------------------------------------------------------------------------------
    lateral_bias_m: float = 0.0  # [m] mean offset from the lane centre, left +
    wander_std_m: float = 0.2  # [m] std of the OU lateral wander
    wander_tau_s: float = 5.0  # [s] correlation time of the wander
    curve_cut_m2: float = 280.0  # [m^2] offset towards the inside per curvature [1/m]
    curve_preview_s: float = 1.5  # [s] curvature is read this far ahead
    # --- lane changes -------------------------------------------------------------------------
    lane_changes: bool = True  # overtake / return right at all
    overtake_speed_gain_mps: float = 3.0  # [m/s] leader this much slower than v0 -> overtake
    lane_change_rate_ps: float = 0.3  # [1/s] hazard rate of starting a change when wanted
    lane_change_duration_s: float = 5.0  # [s]
    lane_change_min_interval_s: float = 10.0  # [s] between two changes
    lane_change_gap_ahead_s: float = 1.5  # [s] time gap needed to the vehicle ahead, target lane
    lane_change_gap_behind_s: float = 1.0  # [s] time gap the vehicle behind must keep (its speed)

    def __post_init__(self) -> None:
        positive = ("desired_speed_mps", "time_headway_s", "max_accel_mps2",
                    "comfort_decel_mps2", "max_decel_mps2", "perception_tau_s", "wander_tau_s",
                    "lane_change_duration_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"DriverParams.{name} must be > 0, got {getattr(self, name)}")
        for name in ("min_gap_m", "reaction_time_s", "gap_error_rel", "inv_ttc_error_ps",
                     "wander_std_m", "lane_change_rate_ps"):
            if getattr(self, name) < 0:
                raise ValueError(f"DriverParams.{name} must be >= 0, got {getattr(self, name)}")

    def without_noise(self) -> DriverParams:
        """The same driver with perception errors, wander and lane changes switched off."""
        return replace(self, gap_error_rel=0.0, inv_ttc_error_ps=0.0, wander_std_m=0.0,
                       lane_changes=False)


# ------------------------------------------------------------------------------- pure maths


def idm_acceleration(v: float, gap: float, dv: float, p: DriverParams) -> float:
    """IDM acceleration [m/s^2] at speed ``v``, bumper ``gap`` (inf = free road) and approach
    rate ``dv = v - v_lead`` [m/s]."""
    free = 1.0 - (max(v, 0.0) / p.desired_speed_mps) ** p.accel_exponent
    if math.isinf(gap):
        return p.max_accel_mps2 * free
    s_star = p.min_gap_m + max(0.0, v * p.time_headway_s
                               + v * dv / (2.0 * math.sqrt(p.max_accel_mps2 * p.comfort_decel_mps2)))
    return p.max_accel_mps2 * (free - (s_star / max(gap, 0.1)) ** 2)


def idm_equilibrium_gap(v: float, p: DriverParams) -> float:
    """Steady-state bumper gap [m] when following at constant speed ``v`` [m/s] (< v0)."""
    ratio = 1.0 - (v / p.desired_speed_mps) ** p.accel_exponent
    return (p.min_gap_m + v * p.time_headway_s) / math.sqrt(ratio)


def ou_step(x: float, std: float, tau: float, dt: float, z: float) -> float:
    """Exact OU update over ``dt`` [s] with stationary ``std`` and correlation time ``tau`` [s];
    ``z`` is a standard normal draw."""
    rho = math.exp(-dt / tau)
    return rho * x + std * math.sqrt(1.0 - rho * rho) * z


def curve_cut_offset(kappa: float, p: DriverParams) -> float:
    """Offset [m] towards the inside of a curve of curvature ``kappa`` [1/m] (left curve > 0)."""
    return p.curve_cut_m2 * kappa


def smoothstep5(u: float) -> float:
    """Quintic smoothstep on [0, 1]: zero slope and curvature at both ends."""
    u = min(max(u, 0.0), 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def delayed_value(history: np.ndarray, k: int, delay_steps: float) -> float:
    """``history`` sampled at steps ``0..k``, read at step ``k - delay_steps`` (linear interp.);
    before step 0 the value is 0 (no acceleration before the start)."""
    j = k - delay_steps
    j0 = math.floor(j)
    w = j - j0
    a0 = history[j0] if j0 >= 0 else 0.0
    a1 = history[j0 + 1] if j0 + 1 >= 0 else 0.0
    return (1.0 - w) * a0 + w * a1 if w > 0 else a0


def simulate_follower(
    leader_pos: np.ndarray, leader_speed: np.ndarray, v0: float, dt: float,
    desired_speed: np.ndarray, time_headway: np.ndarray, min_gap: np.ndarray,
    max_accel: np.ndarray, comfort_decel: np.ndarray, reaction_time: np.ndarray,
    accel_exponent: float = 4.0, max_decel: float = 8.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free delayed IDM follower behind a recorded leader, vectorised over P parameter sets.

    ``leader_pos`` (N,) [m]: the leader's REAR bumper along the lane in the follower's start frame
    (follower front bumper at 0 at t=0); ``leader_speed`` (N,) [m/s]; parameters ``(P,)``.
    Returns the follower's bumper gap and speed, each ``(N, P)``. Same maths as
    :func:`idm_acceleration` with the delay of :func:`delayed_value` (used by the calibration).
    """
    n = len(leader_pos)
    pn = len(desired_speed)
    x = np.zeros(pn)
    v = np.full(pn, float(v0))
    hist = np.zeros((n, pn))
    gaps = np.empty((n, pn))
    speeds = np.empty((n, pn))
    delay = reaction_time / dt
    sqrt_ab = 2.0 * np.sqrt(max_accel * comfort_decel)
    cols = np.arange(pn)
    for k in range(n):
        gap = leader_pos[k] - x
        gaps[k], speeds[k] = gap, v
        dv = v - leader_speed[k]
        s_star = min_gap + np.maximum(0.0, v * time_headway + v * dv / sqrt_ab)
        hist[k] = max_accel * (1.0 - (v / desired_speed) ** accel_exponent
                               - (s_star / np.maximum(gap, 0.1)) ** 2)
        j = k - delay
        j0 = np.floor(j).astype(int)
        w = j - j0
        a0 = np.where(j0 >= 0, hist[np.clip(j0, 0, n - 1), cols], 0.0)
        a1 = np.where(j0 + 1 >= 0, hist[np.clip(j0 + 1, 0, n - 1), cols], 0.0)
        a = np.clip((1.0 - w) * a0 + w * a1, -max_decel, None)
        v_new = np.maximum(v + a * dt, 0.0)
        x = x + 0.5 * (v + v_new) * dt
        v = v_new
    return gaps, speeds


# ------------------------------------------------------------------------ the driver (state)


@dataclass(frozen=True)
class LaneGaps:
    """What the driver sees in one lane: nearest vehicles ahead / behind (bumper gaps [m],
    ``inf`` when none within view) and their speeds [m/s]."""

    gap_ahead: float = math.inf
    v_ahead: float = math.nan
    gap_behind: float = math.inf
    v_behind: float = math.nan


@dataclass(frozen=True)
class Observation:
    """The driver's view at one step: own speed [m/s], per-lane gaps (index 0 = right lane),
    the road curvature [1/m] ``curve_preview_s`` ahead, and the lane width [m]."""

    v: float
    lanes: tuple[LaneGaps, ...]
    kappa_ahead: float = 0.0
    lane_width_m: float = 3.5


@dataclass(frozen=True)
class Command:
    """The driver's output: acceleration [m/s^2], lateral target [m] from the RIGHT lane's
    centre (left +), the lane the driver is in or heading to, and whether a change is on."""

    accel: float
    lateral_m: float
    lane: int
    changing_lane: bool


class SyntheticDriver:
    """Steps a :class:`DriverParams` driver at a fixed ``dt`` [s]; all draws from ``rng``."""

    def __init__(self, params: DriverParams, rng: np.random.Generator, dt: float = 0.1,
                 lane: int = 0, max_steps: int = 200_000) -> None:
        self.p = params
        self.rng = rng
        self.dt = dt
        self.k = 0
        self.lane_from = lane
        self.lane_to = lane
        self.lc_start = -math.inf  # [s] start of the current / last lane change
        self.hist = np.zeros(max_steps)  # decided accelerations [m/s^2]
        # OU states start in their stationary distribution
        self.w_gap = float(rng.normal())
        self.w_rate = float(rng.normal())
        self.wander = float(rng.normal()) * params.wander_std_m

    @property
    def time(self) -> float:
        return self.k * self.dt

    def _perceived_accel(self, v: float, lane: LaneGaps) -> float:
        p = self.p
        if math.isinf(lane.gap_ahead):
            return idm_acceleration(v, math.inf, 0.0, p)
        gap = max(lane.gap_ahead, 0.1)
        gap_seen = gap * math.exp(p.gap_error_rel * self.w_gap)
        dv_seen = (v - lane.v_ahead) - gap * p.inv_ttc_error_ps * self.w_rate
        return idm_acceleration(v, gap_seen, dv_seen, p)

    def _room(self, lane: LaneGaps, v: float) -> bool:
        """Enough room to move into ``lane`` at speed ``v``."""
        p = self.p
        ahead = lane.gap_ahead >= max(p.lane_change_gap_ahead_s * v, 15.0)
        v_b = 0.0 if math.isnan(lane.v_behind) else lane.v_behind
        behind = lane.gap_behind >= max(p.lane_change_gap_behind_s * v_b
                                        + 3.0 * max(v_b - v, 0.0), 10.0)
        return ahead and behind

    def _decide_lane(self, obs: Observation) -> None:
        p = self.p
        t = self.time
        if not p.lane_changes or t - self.lc_start < max(p.lane_change_min_interval_s,
                                                         p.lane_change_duration_s):
            return
        lane = self.lane_to
        own = obs.lanes[lane]
        want = None
        if lane + 1 < len(obs.lanes):  # overtake a slow, close leader
            slow = own.v_ahead < p.desired_speed_mps - p.overtake_speed_gain_mps
            close = own.gap_ahead < 2.0 * idm_equilibrium_gap(
                min(obs.v, 0.9 * p.desired_speed_mps), p) + 20.0
            left = obs.lanes[lane + 1]
            faster = math.isinf(left.gap_ahead) or left.v_ahead > own.v_ahead + 1.0
            if slow and close and faster and self._room(left, obs.v):
                want = lane + 1
        if want is None and lane > 0:  # keep right when the right lane has room
            right = obs.lanes[lane - 1]
            free = right.gap_ahead > 3.0 * obs.v + 20.0 or (
                right.v_ahead >= p.desired_speed_mps - 1.0 and right.gap_ahead > 2.0 * obs.v)
            if free and self._room(right, obs.v):
                want = lane - 1
        if want is not None and self.rng.random() < p.lane_change_rate_ps * self.dt:
            self.lane_from, self.lane_to, self.lc_start = lane, want, t

    def step(self, obs: Observation) -> Command:
        """Advance one step: perceive, decide, and return the command for this step."""
        p, dt = self.p, self.dt
        # perception errors and wander evolve every step
        z = self.rng.normal(size=3)
        self.w_gap = ou_step(self.w_gap, 1.0, p.perception_tau_s, dt, float(z[0]))
        self.w_rate = ou_step(self.w_rate, 1.0, p.perception_tau_s, dt, float(z[1]))
        self.wander = ou_step(self.wander, p.wander_std_m, p.wander_tau_s, dt, float(z[2]))

        self._decide_lane(obs)
        u = (self.time - self.lc_start) / p.lane_change_duration_s
        changing = 0.0 <= u < 1.0
        # while changing, the driver minds the leaders of both lanes
        relevant = {self.lane_to, self.lane_from} if changing else {self.lane_to}
        decided = min(self._perceived_accel(obs.v, obs.lanes[i]) for i in relevant)
        self.hist[self.k] = decided
        accel = delayed_value(self.hist, self.k, p.reaction_time_s / dt)
        # reflex: an imminent collision is braked for on the true situation, without delay
        for i in relevant:
            ln = obs.lanes[i]
            closing = obs.v - ln.v_ahead
            if closing > 0 and ln.gap_ahead / closing < p.reflex_ttc_s:
                accel = min(accel, idm_acceleration(obs.v, ln.gap_ahead, closing, p))
        accel = max(accel, -p.max_decel_mps2)

        lane_pos = self.lane_from + (self.lane_to - self.lane_from) * smoothstep5(u)
        lateral = (lane_pos * obs.lane_width_m + p.lateral_bias_m + self.wander
                   + curve_cut_offset(obs.kappa_ahead, p))
        self.k += 1
        return Command(accel, lateral, self.lane_to, changing)


# --------------------------------------------------------------- calibrated driver population


def load_calibration(path: Path = PARAMS_JSON) -> dict:
    """The committed calibration (fitted values, per-pair fits and errors)."""
    return json.loads(Path(path).read_text())


# Desired speed: OpenACC followers are always constrained by their leader, so v0 is not
# identified there (fits run into the bounds); drivers draw it around the n74 limit instead.
DESIRED_SPEED_MEAN_MPS = 33.0  # [m/s] ~119 km/h on a 120 km/h road
DESIRED_SPEED_STD_MPS = 1.5  # [m/s]
DESIRED_SPEED_RANGE_MPS = (29.0, 37.0)  # [m/s]


def params_from(cal: dict) -> DriverParams:
    """The calibrated median driver of a calibration dict."""
    names = {f.name for f in fields(DriverParams)}
    return DriverParams(**{k: v for k, v in cal["driver_median"].items() if k in names})


def default_params(path: Path = PARAMS_JSON) -> DriverParams:
    """The calibrated median driver (falls back to the dataclass defaults without the file)."""
    return params_from(load_calibration(path)) if Path(path).is_file() else DriverParams()


def sample_driver(rng: np.random.Generator, calibration: dict | None = None,
                  lane_changes: bool = True) -> DriverParams:
    """Draw one driver of the calibrated population.

    Car-following parameters: one OpenACC follower's fitted set (bootstrap), each jittered by a
    lognormal factor (5 %); desired speed ~ N(33, 1.5) m/s clipped to [29, 37] (not identified
    by the fits, see above). Lateral: bias ~ N(0, bias std), wander std and correlation time
    jittered (15 %) around the NGSIM fit.
    """
    cal = calibration if calibration is not None else load_calibration()
    fits = cal["car_following"]["per_pair"]
    fit = fits[int(rng.integers(len(fits)))]["params"]
    lat = cal["lateral"]
    jit = np.exp(rng.normal(0.0, 0.05, size=5))
    v0 = float(np.clip(rng.normal(DESIRED_SPEED_MEAN_MPS, DESIRED_SPEED_STD_MPS),
                       *DESIRED_SPEED_RANGE_MPS))
    return replace(
        params_from(cal),
        desired_speed_mps=v0,
        time_headway_s=fit["time_headway_s"] * jit[0],
        min_gap_m=fit["min_gap_m"] * jit[1],
        max_accel_mps2=fit["max_accel_mps2"] * jit[2],
        comfort_decel_mps2=fit["comfort_decel_mps2"] * jit[3],
        reaction_time_s=fit["reaction_time_s"] * jit[4],
        lateral_bias_m=float(rng.normal(0.0, lat["bias_std_m"])),
        wander_std_m=lat["wander_std_m"] * float(np.exp(rng.normal(0.0, 0.15))),
        wander_tau_s=lat["wander_tau_s"] * float(np.exp(rng.normal(0.0, 0.15))),
        lane_changes=lane_changes,
    )
