"""An analytic planner: lane-centre following plus a constant-time-gap car-following law, fitted to
the same B-spline as the learned planners. It drives the loop before (and beside) the learned
models and is the sanity baseline of every experiment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo.core import bspline
from safeil_sumo.core.policy import DEFAULT_TIME_GAP_S, PLAN_HORIZON_S


@dataclass(frozen=True)
class AnalyticPlanner:
    """Implements :class:`safeil_sumo.core.policy.Policy`.

    Longitudinal: ``a = k_gap (d - d*) + k_speed (v_lead - v)`` with ``d* = gap_min + time_gap v``,
    capped to reach ``v_desired`` on a free road; simulated over the horizon with the leader at
    constant speed. Lateral: converge to the lane centre with time constant ``lateral_tau_s``.
    """

    name: str = "analytic"
    horizon: float = PLAN_HORIZON_S  # plan horizon T_h [s]
    samples: int = 20  # trajectory samples fitted by least squares [-]
    time_gap_s: float = DEFAULT_TIME_GAP_S  # desired time gap [s]
    gap_min_m: float = 5.0  # desired standstill gap [m]
    k_gap: float = 0.08  # gap-error gain [1/s^2]
    k_speed: float = 0.5  # speed-difference gain [1/s]
    v_desired_mps: float = 33.0  # free-road speed (~120 km/h) [m/s]
    k_free: float = 0.3  # free-road speed gain [1/s]
    accel_limits: tuple[float, float] = (-6.0, 2.0)  # [m/s^2]
    lateral_tau_s: float = 1.5  # lateral convergence time constant [s]

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Control points ``(..., 3, 2)`` [m] for features ``(..., 9)``."""
        f = np.asarray(features, dtype=float)
        if f.ndim > 1:
            return np.stack([self.plan(row) for row in f.reshape(-1, 9)]).reshape(
                f.shape[:-1] + (3, 2)
            )
        # plain floats: the same IEEE arithmetic as numpy scalars, ~5x cheaper per operation
        v, v_lead, d_lead = f[6:].tolist()
        n = self.samples
        dt = self.horizon / n
        x = [0.0] * n
        pos, speed, gap = 0.0, v, d_lead
        lo, hi = self.accel_limits
        gap_min, time_gap, k_gap, k_speed = self.gap_min_m, self.time_gap_s, self.k_gap, self.k_speed
        k_free, v_desired = self.k_free, self.v_desired_mps
        for k in range(n):
            desired = gap_min + time_gap * speed
            a_follow = k_gap * (gap - desired) + k_speed * (v_lead - speed)
            a_free = k_free * (v_desired - speed)
            a = min(max(min(a_follow, a_free), lo), hi)
            new_speed = max(speed + a * dt, 0.0)
            pos += 0.5 * (speed + new_speed) * dt
            gap += (v_lead - 0.5 * (speed + new_speed)) * dt
            speed = new_speed
            x[k] = pos
        return lane_following_plan(f, np.array(x), dt, self.lateral_tau_s)


def lane_following_plan(features: np.ndarray, x: np.ndarray, dt: float, lateral_tau_s: float
                        ) -> np.ndarray:
    """Control points ``(3, 2)`` [m] of a plan whose longitudinal positions ``x (n,)`` [m] at
    ``t = k dt`` (k = 1..n) are given: laterally it starts where the car is (y = 0) and converges
    on the lane centre with time constant ``lateral_tau_s`` [s]; least-squares spline fit.
    Shared by the analytic and the IDM planner (only their longitudinal law differs)."""
    c0l, c1l, c2l, c0r, c1r, c2r = features[:6].tolist()
    n = len(x)
    centre = (0.5 * (c0l + c0r), 0.5 * (c1l + c1r), 0.5 * (c2l + c2r))
    y_centre = centre[0] + centre[1] * x + centre[2] * x * x
    # start from where the car is (y = 0 at x = 0) and converge on the lane centre
    y = y_centre - centre[0] * _decay(n, dt, lateral_tau_s)
    return _fit_matrix(n) @ np.stack([x, y], axis=1)


_FIT_CACHE: dict[int, np.ndarray] = {}


def _fit_matrix(samples: int) -> np.ndarray:
    """Least-squares operator ``(3, samples)`` for equally spaced samples at tau = k / samples."""
    if samples not in _FIT_CACHE:
        tau = np.arange(1, samples + 1) / samples
        _FIT_CACHE[samples] = np.linalg.pinv(bspline.basis(tau)[:, 1:])
    return _FIT_CACHE[samples]


_DECAY_CACHE: dict[tuple[int, float, float], np.ndarray] = {}


def _decay(samples: int, dt: float, tau: float) -> np.ndarray:
    """``exp(-t / tau)`` at the sample times ``t = k dt``, k = 1..samples (read-only, cached)."""
    key = (samples, dt, tau)
    if key not in _DECAY_CACHE:
        out = np.exp(-(np.arange(1, samples + 1) * dt) / tau)
        out.flags.writeable = False
        _DECAY_CACHE[key] = out
    return _DECAY_CACHE[key]
