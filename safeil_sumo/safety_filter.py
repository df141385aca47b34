"""Safe-set margins of plans and an optional inference-time safety filter (beyond the paper).

The safe set is the paper's barrier constraint set, in the ego frame (x forward, y left, [m]):

- left line:  ``y <= c0l + c1l x + c2l x^2 - T/2 - lateral_margin``
- right line: ``y >= c0r + c1r x + c2r x^2 + T/2 + lateral_margin``
- leader:     ``x <= d_lead + v_lead t - (gap_min + time_gap v_x)`` (constant-speed leader)

Margins are ``>= 0`` inside. :func:`project_plan` projects each control point onto the set
(longitudinal clip first, then a lateral clip at the clipped x), so every filtered plan satisfies
the constraints at its control points by construction. By the convex-hull property the whole
spline then satisfies them on straight lanes; on curves the chords of the hull can cut the
non-convex side — :mod:`safeil_sumo.learn.evaluate` measures it. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo import bspline
from safeil_sumo.policy import Policy

C0L, C0R, V_X, V_LEAD, D_LEAD = 0, 3, 6, 7, 8


@dataclass(frozen=True)
class SafeSet:
    """Constraint parameters. track: vehicle width T [m]; lateral_margin: extra clearance to each
    lane line [m]; gap_min [m] and time_gap [s]: clearance behind the predicted leader's rear."""

    track: float = 1.76
    lateral_margin: float = 0.0
    gap_min: float = 0.0
    time_gap: float = 0.0


DEFAULT_SAFE_SET = SafeSet()


def _line(features: np.ndarray, c0: int, x: np.ndarray) -> np.ndarray:
    """Lane line ``c0 + c1 x + c2 x^2`` [m] at ``x (..., M)``; features ``(..., 9)``."""
    c = features[..., None, c0 : c0 + 3]
    return c[..., 0] + c[..., 1] * x + c[..., 2] * x * x


def lateral_bounds(
    features: np.ndarray, x: np.ndarray, safe_set: SafeSet = SafeSet()
) -> tuple[np.ndarray, np.ndarray]:
    """Allowed ``(y_min, y_max)`` ``(..., M)`` [m] at longitudinal positions ``x (..., M)``."""
    clearance = 0.5 * safe_set.track + safe_set.lateral_margin
    return _line(features, C0R, x) + clearance, _line(features, C0L, x) - clearance


def x_limit(features: np.ndarray, times: np.ndarray, safe_set: SafeSet = SafeSet()) -> np.ndarray:
    """Largest allowed x ``(..., M)`` [m] at ``times (M,)`` [s]: behind the leader with margin."""
    d = features[..., D_LEAD, None] + features[..., V_LEAD, None] * times
    return d - (safe_set.gap_min + safe_set.time_gap * features[..., V_X, None])


def point_margins(
    features: np.ndarray, points: np.ndarray, times: np.ndarray, safe_set: SafeSet = SafeSet()
) -> dict[str, np.ndarray]:
    """Margins ``left``, ``right``, ``lead`` ``(..., M)`` [m] of ``points (..., M, 2)`` at
    ``times (M,)`` [s]; >= 0 is safe."""
    x, y = points[..., 0], points[..., 1]
    y_min, y_max = lateral_bounds(features, x, safe_set)
    return {"left": y_max - y, "right": y - y_min, "lead": x_limit(features, times, safe_set) - x}


def plan_margins(
    features: np.ndarray,
    control_points: np.ndarray,
    horizon: float,
    safe_set: SafeSet = SafeSet(),
    tau: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Margins ``(..., M)`` of plans ``(..., 3, 2)`` at their control points (``tau=None``, M = 3)
    or at spline points ``tau (M,)``."""
    features = np.asarray(features, dtype=float)
    if tau is None:
        points, times = np.asarray(control_points, float), bspline.control_point_times(horizon)
    else:
        points, times = bspline.evaluate(control_points, tau), np.asarray(tau) * horizon
    return point_margins(features, points, times, safe_set)


def project_plan(
    features: np.ndarray,
    control_points: np.ndarray,
    horizon: float,
    safe_set: SafeSet = SafeSet(),
) -> tuple[np.ndarray, np.ndarray]:
    """Project plans ``(..., 3, 2)`` onto the safe set; returns ``(filtered, acted (...,) bool)``.

    Each control point: ``x <- min(x, x_limit)``, then ``y <- clip(y, y_min(x), y_max(x))``. If the
    lane is narrower than the track at that x (``y_min > y_max``, infeasible), y goes to the middle.
    An ``x_limit`` below 0 (leader closer than the margin) is kept: the plan then points backwards,
    i.e. "brake", rather than silently violating the gap.
    """
    features = np.asarray(features, dtype=float)
    cp = np.array(control_points, dtype=float)  # copy
    x_max = x_limit(features, bspline.control_point_times(horizon), safe_set)
    x = np.minimum(cp[..., 0], x_max)
    y_min, y_max = lateral_bounds(features, x, safe_set)
    y = np.where(y_min <= y_max, np.clip(cp[..., 1], y_min, y_max), 0.5 * (y_min + y_max))
    acted = np.any((x != cp[..., 0]) | (y != cp[..., 1]), axis=-1)
    cp[..., 0], cp[..., 1] = x, y
    return cp, acted


class SafetyFiltered:
    """A Policy wrapper that projects every plan onto the safe set and counts interventions.

    ``interventions``: number of plans changed; ``calls``: number of plans made.
    """

    def __init__(self, policy: Policy, safe_set: SafeSet = SafeSet()) -> None:
        self.policy = policy
        self.safe_set = safe_set
        self.name = f"{policy.name}+filter"
        self.horizon = float(policy.horizon)
        self.interventions = 0
        self.calls = 0

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Filtered plan ``(..., 3, 2)`` for ``features (..., 9)``."""
        features = np.asarray(features, dtype=float)
        filtered, acted = project_plan(
            features, self.policy.plan(features), self.horizon, self.safe_set
        )
        self.calls += int(acted.size)
        self.interventions += int(np.count_nonzero(acted))
        return filtered

    @property
    def intervention_rate(self) -> float:
        return self.interventions / self.calls if self.calls else 0.0
