"""The envs' spaces, reward and ``info``, on arrays over N scenarios (one env is N = 1).

Observation: the planner's 9 features (:mod:`safeil_sumo.core.features`, ego frame, SI units), as
``float32``, clipped to :data:`OBS_LOW` / :data:`OBS_HIGH` (the unclipped ``float64`` features are
``info["features"]``).

Actions (``action_level``):

- ``"plan"``: the 3 free control points of the cubic B-spline plan, ``(x1, y1, x2, y2, x3, y3)``
  [m] in the ego frame at the decision (x forward from the front bumper, y left), tracked over
  the decision period by the project's pure pursuit + PID; the plan spans ``horizon_s``;
- ``"control"``: ``(acceleration [m/s^2], road-wheel steering angle [rad])`` held over the
  period (the plant's actuator lags and limits apply).

An action outside the space is clipped into it (``out_of_space="clip"``, the default) or
refused with ``ValueError`` (``"raise"``); a NaN or a wrong shape is always refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from gymnasium import spaces

from safeil_sumo.core.features import FEATURE_NAMES
from safeil_sumo.sim.controller import ControllerParams
from safeil_sumo.sim.vehicle import VehicleParams

# the observation's bounds: c0l, c1l, c2l, c0r, c1r, c2r [m, -, 1/m], v_x, v_lead [m/s],
# d_lead [m] (150 m, the radar's range, when no leader is seen)
OBS_LOW = np.array([-20.0, -2.0, -0.5, -20.0, -2.0, -0.5, 0.0, 0.0, 0.0], np.float32)
OBS_HIGH = np.array([20.0, 2.0, 0.5, 20.0, 2.0, 0.5, 100.0, 100.0, 250.0], np.float32)
# plan level: x in [0, 250] m ahead, y in [-80, 80] m (a 500 m curve is 20 m to the side 140 m
# ahead, where the shipped safeil puts its last point at 30 m/s), for each free control point
PLAN_LOW = np.array([0.0, -80.0] * 3)
PLAN_HIGH = np.array([250.0, 80.0] * 3)
ACTION_LEVELS = ("plan", "control")
OUT_OF_SPACE = ("clip", "raise")
MAX_GAP_ERROR_M = 100.0  # [m] the replay's and the style's gap error counted at most
INFO_KEYS = ("t", "ttc", "gap", "lateral_offset", "v", "leader_v", "path_fraction",
             "lane_departure", "ttc_flag", "collision", "end_reason")


def observation_space() -> spaces.Box:
    return spaces.Box(OBS_LOW, OBS_HIGH, dtype=np.float32)


def action_space(level: str, vehicle: VehicleParams = VehicleParams(),
                 controller: ControllerParams = ControllerParams()) -> spaces.Box:
    if level == "plan":
        return spaces.Box(PLAN_LOW, PLAN_HIGH, dtype=np.float64)
    if level == "control":
        return spaces.Box(np.array([controller.accel_min_mps2, -vehicle.max_steer_rad]),
                          np.array([controller.accel_max_mps2, vehicle.max_steer_rad]),
                          dtype=np.float64)
    raise ValueError(f"unknown action_level {level!r}; levels: {', '.join(ACTION_LEVELS)}")


def observe(features: np.ndarray) -> np.ndarray:
    """Features ``(..., 9)`` -> the observation (float32, clipped to the space)."""
    return np.clip(np.nan_to_num(features, nan=0.0), OBS_LOW, OBS_HIGH).astype(np.float32)


_OBS_LOW64, _OBS_HIGH64 = OBS_LOW.astype(float), OBS_HIGH.astype(float)


def observe_one(features: np.ndarray) -> np.ndarray:
    """:func:`observe` of one row ``(9,)``, the same values (NaN -> 0, inf -> the bound) at a
    third of its cost (np.clip and nan_to_num's overhead dominate on 9 numbers)."""
    f = np.minimum(np.maximum(features, _OBS_LOW64), _OBS_HIGH64)
    if np.isnan(f).any():  # NaN passes minimum/maximum: 0 then clipped
        f = np.clip(np.where(np.isnan(f), 0.0, f), _OBS_LOW64, _OBS_HIGH64)
    return f.astype(np.float32)


def checked_actions(actions, space: spaces.Box, out_of_space: str, n: int | None = None
                    ) -> np.ndarray:
    """Actions ``(n, dim)`` (or ``(dim,)`` when ``n`` is None) as float64, inside the space."""
    a = np.asarray(actions, dtype=float)
    shape = space.shape if n is None else (n, *space.shape)
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError("action must be finite (no NaN/inf)")
    inside = (a >= space.low) & (a <= space.high)
    if inside.all():
        return a
    if out_of_space == "raise":
        raise ValueError(f"action outside the action space [{space.low}, {space.high}]: {a} "
                         "(out_of_space='clip' clips it)")
    return np.clip(a, space.low, space.high)


@dataclass(frozen=True)
class RewardConfig:
    """The default reward per decision step: progress along the ego lane, penalties for the
    safety flags (at any physics step of the decision) and for the ends that terminate."""

    progress_per_m: float = 0.01  # [1/m] times the metres gained along the ego lane
    ttc_flag: float = -1.0  # TTC <= the threshold (1 s) during the step
    lane_departure: float = -1.0  # the footprint left its lane during the step
    collision: float = -10.0  # once, the step of the collision (terminates)
    off_road: float = -10.0  # once, when the ego is too far off its lane (terminates)
    # replay tasks (0 elsewhere): times the squared error [m^2] of the gap to the leader at the
    # step's end against the recorded human's gap at the same time (the error counted at most
    # MAX_GAP_ERROR_M, also where no leader is seen)
    human_gap_per_m2: float = -0.01
    # with a style set (the env's style option, set_style): times the squared error [m^2] of
    # the gap at the step's end against the style's gap s0 + T v at the ego's speed then
    # (info["style_gap"]; the error counted at most MAX_GAP_ERROR_M, also where no leader is
    # seen); 0: no term (a scenario without a style never has one)
    style_gap_per_m2: float = 0.0

    @classmethod
    def of(cls, value: RewardConfig | dict | None, base: RewardConfig | None = None
           ) -> RewardConfig:
        """``value`` as a config: None gives ``base`` (default: the class defaults); a dict
        replaces ``base``'s terms it names."""
        base = base if base is not None else cls()
        if value is None:
            return base
        if isinstance(value, cls):
            return value
        if not isinstance(value, dict):
            raise TypeError(f"reward must be a RewardConfig or a dict, got "
                            f"{type(value).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise ValueError(f"unknown reward term(s) {unknown}; terms: {sorted(known)}")
        out = replace(base, **{k: float(v) for k, v in value.items()})
        if not all(math.isfinite(getattr(out, k)) for k in known):
            raise ValueError("reward weights must be finite")
        return out

    def rewards(self, s_before: np.ndarray, obs, events, human_gap: np.ndarray | None = None,
                style_gap: np.ndarray | None = None) -> np.ndarray:
        """``(N,)`` rewards of one step (``obs``: the Observation after it, ``events``: its
        Events; ``human_gap`` [m]: the recorded human's gap at ``obs.t``, replay tasks only;
        ``style_gap`` [m]: the style's gap (:func:`style_gaps`), NaN where no style is set); a
        scenario that did not run in the step gets 0."""
        gained = np.nan_to_num(obs.s - s_before)
        r = (self.progress_per_m * gained + self.ttc_flag * events.ttc_flag
             + self.lane_departure * events.lane_departure + self.collision * events.collision
             + self.off_road * (events.end_reason == "off_road"))
        if human_gap is not None:
            err = np.nan_to_num(obs.gap - human_gap, nan=MAX_GAP_ERROR_M, posinf=MAX_GAP_ERROR_M,
                                neginf=MAX_GAP_ERROR_M)
            e = np.minimum(np.abs(err), MAX_GAP_ERROR_M)
            r = r + self.human_gap_per_m2 * (e * e)
        if style_gap is not None and self.style_gap_per_m2 != 0.0:
            err = np.nan_to_num(obs.gap - style_gap, nan=MAX_GAP_ERROR_M,
                                posinf=MAX_GAP_ERROR_M, neginf=MAX_GAP_ERROR_M)
            e = np.minimum(np.abs(err), MAX_GAP_ERROR_M)
            r = np.where(np.isnan(style_gap), r, r + self.style_gap_per_m2 * (e * e))
        return np.where(events.sub_steps > 0, r, 0.0)

    def reward_one(self, s_before: float, obs, events,
                   human_gap: float | np.ndarray | None = None,
                   style_gap: float | None = None) -> float:
        """:meth:`rewards` of a one-scenario step, on Python floats (the same operations in the
        same order: the same value, bit for bit, without numpy's per-call overhead)."""
        if events.sub_steps[0] <= 0:
            return 0.0
        gained = float(obs.s[0]) - s_before
        if math.isnan(gained):  # np.nan_to_num: NaN -> 0, +-inf -> the largest finite float
            gained = 0.0
        elif math.isinf(gained):
            gained = math.copysign(_MAX_FLOAT, gained)
        r = (self.progress_per_m * gained + self.ttc_flag * float(events.ttc_flag[0])
             + self.lane_departure * float(events.lane_departure[0])
             + self.collision * float(events.collision[0])
             + self.off_road * float(events.end_reason[0] == "off_road"))
        if human_gap is not None:
            err = float(obs.gap[0]) - float(human_gap)
            e = min(abs(err), MAX_GAP_ERROR_M) if math.isfinite(err) else MAX_GAP_ERROR_M
            r = r + self.human_gap_per_m2 * (e * e)
        if style_gap is not None and self.style_gap_per_m2 != 0.0 and not math.isnan(style_gap):
            err = float(obs.gap[0]) - style_gap
            e = min(abs(err), MAX_GAP_ERROR_M) if math.isfinite(err) else MAX_GAP_ERROR_M
            r = r + self.style_gap_per_m2 * (e * e)
        return r


_MAX_FLOAT = float(np.finfo(float).max)


# the replay's default reward: closeness to the human and the penalties, no progress term
REPLAY_REWARD = RewardConfig(progress_per_m=0.0)


def style_gaps(time_gap_s: np.ndarray, standstill_m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(N,)`` the styles' gaps [m] at ego speeds ``v`` [m/s]: ``standstill_m + time_gap_s *
    v``, the steady gap's line of a driver's style (NaN where ``time_gap_s`` is NaN: no
    style)."""
    return standstill_m + time_gap_s * v


def infos(obs, events=None, human_gap: np.ndarray | None = None,
          style_gap: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """``info`` arrays ``(N,)``: time [s], TTC [s] (inf: not closing), gap [m] (inf: no
    leader), lateral offset of the front bumper from the lane centre [m, left +], speed and the
    leader's [m/s], path fraction [-], the flags (during the step, or at the reset's state), the
    end reason ("" while running), the raw features ``(N, 9)``, in a replay the recorded
    human's gap at the same time ``human_gap`` [m], and the style's gap ``style_gap`` [m]
    (:func:`style_gaps`; NaN: no style) when given."""
    flags = (events.lane_departure, events.ttc_flag, events.collision) if events is not None \
        else (obs.lane_departure, obs.ttc_flag, obs.collision)
    reason = (events.end_reason.astype(str) if events is not None
              else np.full(len(obs.t), "", dtype=object).astype(str))
    out = {"t": obs.t, "ttc": obs.ttc, "gap": obs.gap, "lateral_offset": obs.d, "v": obs.v,
           "leader_v": obs.leader_v, "path_fraction": obs.path_fraction,
           "lane_departure": flags[0], "ttc_flag": flags[1], "collision": flags[2],
           "end_reason": reason, "features": obs.features}
    if human_gap is not None:
        out["human_gap"] = np.asarray(human_gap, float)
    if style_gap is not None:
        out["style_gap"] = np.asarray(style_gap, float)
    return out


def info_one(obs, events=None, human_gap: float | np.ndarray | None = None,
             style_gap: float | None = None) -> dict:
    """``{k: v[0] for k, v in infos(obs, events, human_gap, style_gap).items()}`` of a
    one-scenario step, built directly (the same keys and values)."""
    src = events if events is not None else obs
    out = {"t": obs.t[0], "ttc": obs.ttc[0], "gap": obs.gap[0], "lateral_offset": obs.d[0],
           "v": obs.v[0], "leader_v": obs.leader_v[0], "path_fraction": obs.path_fraction[0],
           "lane_departure": src.lane_departure[0], "ttc_flag": src.ttc_flag[0],
           "collision": src.collision[0],
           "end_reason": np.str_(events.end_reason[0] if events is not None else ""),
           "features": obs.features[0]}
    if human_gap is not None:
        out["human_gap"] = np.float64(human_gap)
    if style_gap is not None:
        out["style_gap"] = np.float64(style_gap)
    return out


FEATURES = FEATURE_NAMES  # the observation's order
