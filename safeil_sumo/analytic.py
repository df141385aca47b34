"""An analytic planner: lane-centre following plus a constant-time-gap car-following law, fitted to
the same B-spline as the learned planners. It drives the loop before (and beside) the learned
models and is the sanity baseline of every experiment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo import bspline


@dataclass(frozen=True)
class AnalyticPlanner:
    """Implements :class:`safeil_sumo.policy.Policy`.

    Longitudinal: ``a = k_gap (d - d*) + k_speed (v_lead - v)`` with ``d* = gap_min + time_gap v``,
    capped to reach ``v_desired`` on a free road; simulated over the horizon with the leader at
    constant speed. Lateral: converge to the lane centre with time constant ``lateral_tau_s``.
    """

    name: str = "analytic"
    horizon: float = 5.0  # plan horizon T_h [s]
    samples: int = 20  # trajectory samples fitted by least squares [-]
    time_gap_s: float = 1.5  # desired time gap [s]
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
        c0l, c1l, c2l, c0r, c1r, c2r, v, v_lead, d_lead = f
        dt = self.horizon / self.samples
        t = np.arange(1, self.samples + 1) * dt
        x = np.empty(self.samples)
        pos, speed, gap = 0.0, v, d_lead
        lo, hi = self.accel_limits
        for k in range(self.samples):
            desired = self.gap_min_m + self.time_gap_s * speed
            a_follow = self.k_gap * (gap - desired) + self.k_speed * (v_lead - speed)
            a_free = self.k_free * (self.v_desired_mps - speed)
            a = min(max(min(a_follow, a_free), lo), hi)
            new_speed = max(speed + a * dt, 0.0)
            pos += 0.5 * (speed + new_speed) * dt
            gap += (v_lead - 0.5 * (speed + new_speed)) * dt
            speed = new_speed
            x[k] = pos
        centre = 0.5 * np.array([c0l + c0r, c1l + c1r, c2l + c2r])
        y_centre = centre[0] + centre[1] * x + centre[2] * x * x
        # start from where the car is (y = 0 at x = 0) and converge on the lane centre
        y = y_centre - centre[0] * np.exp(-t / self.lateral_tau_s)
        return _fit_matrix(self.samples) @ np.stack([x, y], axis=1)


_FIT_CACHE: dict[int, np.ndarray] = {}


def _fit_matrix(samples: int) -> np.ndarray:
    """Least-squares operator ``(3, samples)`` for equally spaced samples at tau = k / samples."""
    if samples not in _FIT_CACHE:
        tau = np.arange(1, samples + 1) / samples
        _FIT_CACHE[samples] = np.linalg.pinv(bspline.basis(tau)[:, 1:])
    return _FIT_CACHE[samples]
