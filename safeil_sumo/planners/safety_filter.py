"""Safe-set margins of plans and an optional inference-time safety filter (beyond the paper).

The safe set is the paper's barrier constraint set, in the ego frame (x forward, y left, [m]):

- left line:  ``y <= c0l + c1l x + c2l x^2 - T/2 - lateral_margin``
- right line: ``y >= c0r + c1r x + c2r x^2 + T/2 + lateral_margin``
- leader:     ``x <= d_lead + v_lead t - (gap_min + time_gap v_x)`` (constant-speed leader)

Margins are ``>= 0`` inside. :func:`project_plan` has two modes.

- ``mode="bernstein"`` (default): x as below; then y so that the exact degree-6 Bernstein
  coefficients of both lane margins along the spline (:func:`bernstein_margins`, 14 numbers) are
  ``>= 0``, which keeps the WHOLE spline inside the lanes, on curves too. y moves by the smallest
  blend toward a lane-following reference (see :func:`project_plan`), so plans already inside are
  kept exactly and lane-following plans on curves are not cut.
- ``mode="control_points"``: each control point is projected onto the set (longitudinal clip,
  then a lateral clip at the clipped x). On straight lanes the convex hull keeps the spline inside;
  on curves a lane-following plan's control points sit ``~c2 X^2 / 9`` outside the lane centre,
  so this clip bends such plans off the lane (measured: 0/10 curved500 scenarios completed).

Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo.core import bspline
from safeil_sumo.core.policy import Policy

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
# The inference-time filter keeps a margin behind the leader: with none, a plan may end touching
# the predicted leader and the loop settles centimetres behind it (measured: SafeIL + filter
# closed to a 1.6 cm gap on curved500 and was flagged for collision). 2 m + 1 s of headway keeps
# the steady-state TTC flag (<= 1 s) out of reach for any closing speed the plan can recover.
FILTER_SAFE_SET = SafeSet(gap_min=2.0, time_gap=1.0)


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
    mode: str = "bernstein",
) -> tuple[np.ndarray, np.ndarray]:
    """Project plans ``(..., 3, 2)`` onto the safe set; returns ``(filtered, acted (...,) bool)``.

    Both modes first clip ``x <- min(x, x_limit)`` at each control point. An ``x_limit`` below 0
    (leader closer than the margin) is kept: the plan then points backwards, i.e. "brake", rather
    than silently violating the gap.

    ``mode="control_points"``: ``y <- clip(y, y_min(x), y_max(x))`` per control point. If the lane
    is narrower than the track at that x (``y_min > y_max``, infeasible), y goes to the middle.

    ``mode="bernstein"`` (default): a plan whose 12 lane-margin Bernstein coefficients k = 1..6
    (:func:`bernstein_margins`) are all >= 0 keeps its y. Otherwise y moves toward the lane-following
    reference ``y_ref`` (the lane centre at the plan's x, reached from the car through
    ``(1 - tau)^3``) by the smallest blend ``lam in [0, 1]`` that puts all of them >= 0 (closed form:
    each coefficient is affine in lam). Then, if the car is inside the band at tau = 0, every
    coefficient is >= 0 and the whole spline is inside. Special cases:
    the car is outside the band at tau = 0 (or the lane is narrower than the track): no plan that
    starts at the car is inside; a plan whose coefficients k >= 1 are inside is kept, any other
    gets ``y_ref`` (back to the lane centre, x kept; coefficients k >= 4 are then inside on
    parallel lines, the earlier ones as far as the start allows);
    ``y_ref`` itself is outside the band (x far from constant speed, so that ``c2 x(tau)^2`` is far
    from any cubic): x is replaced by the constant-speed profile ending at ``min(x_3, leader
    limits)`` and y by the lane centre at it, exact (inside on parallel lane lines, best effort on
    lines whose band narrows).
    """
    if mode not in FILTER_MODES:
        raise ValueError(f"mode must be one of {FILTER_MODES}, got {mode!r}")
    features = np.asarray(features, dtype=float)
    cp = np.array(control_points, dtype=float)  # copy
    if mode == "bernstein":
        batch = np.broadcast_shapes(cp.shape[:-2], features.shape[:-1])
        cp = np.broadcast_to(cp, batch + (3, 2))
        features = np.broadcast_to(features, batch + features.shape[-1:])
        filtered = _project_bernstein(features, cp, horizon, safe_set)
        acted = np.any(filtered != cp, axis=(-2, -1))
        return filtered, acted
    x_max = x_limit(features, bspline.control_point_times(horizon), safe_set)
    x = np.minimum(cp[..., 0], x_max)
    y_min, y_max = lateral_bounds(features, x, safe_set)
    y = np.where(y_min <= y_max, np.clip(cp[..., 1], y_min, y_max), 0.5 * (y_min + y_max))
    acted = np.any((x != cp[..., 0]) | (y != cp[..., 1]), axis=-1)
    cp[..., 0], cp[..., 1] = x, y
    return cp, acted


def bernstein_margins(
    features: np.ndarray, control_points: np.ndarray, safe_set: SafeSet = SafeSet()
) -> dict[str, np.ndarray]:
    """Exact degree-6 Bernstein coefficients ``left``, ``right`` ``(..., 7)`` [m] of the lane margins
    along plans ``(..., 3, 2)``; features ``(..., 9)``. All >= 0 => the whole spline is inside;
    coefficient 0 is the margin of the car itself (tau = 0), coefficient 6 that of the end point."""
    features = np.asarray(features, dtype=float)
    cl = 0.5 * safe_set.track + safe_set.lateral_margin
    left = bspline.lateral_margin_bernstein(control_points, features[..., C0L : C0L + 3], -cl)
    right = -bspline.lateral_margin_bernstein(control_points, features[..., C0R : C0R + 3], cl)
    return {"left": left, "right": right}


# (3, 7): least-squares degree reduction 6 -> 3 of Bernstein coefficients with the origin fixed
# (the first coefficient of both is 0): exact for any degree-6 polynomial that is a cubic.
_REDUCE_6_TO_3 = np.linalg.pinv(bspline.ELEVATE_3_TO_6[:, 1:])
# tau^2 as a cubic: control points [0, 1/3, 1] (origin dropped): x^2 of a constant-speed plan.
_TAU_SQUARED = np.array([0.0, 1.0 / 3.0, 1.0])
FILTER_MODES = ("bernstein", "control_points")


def _lane_reference_y(features: np.ndarray, x: np.ndarray) -> np.ndarray:
    """y control points ``(..., 3)`` [m] of the lane-following reference for x ``(..., 3)``.

    The reference is ``centre(x(tau)) - centre(0) (1 - tau)^3``: the lane centre line at the plan's
    own x profile, reached from the car (y = 0 at tau = 0) by the cubic Bernstein weight of the
    origin. Its degree-6 coefficients stay inside the band by ``H (1 - E_k0) >= H / 2`` (H = half
    band, E_k0 = 1, 1/2, 1/5, 1/20, 0, 0, 0) on parallel lines. ``x(tau)^2`` is degree 6: it is
    reduced to a cubic by least squares on its Bernstein coefficients (exact for constant speed).
    """
    c = 0.5 * (features[..., C0L : C0L + 3] + features[..., C0R : C0R + 3])  # centre line (..., 3)
    x_full = np.concatenate([np.zeros(x.shape[:-1] + (1,)), x], axis=-1)
    x_sq = bspline.square_bernstein(x_full) @ _REDUCE_6_TO_3.T  # (..., 3) cubic ~ x(tau)^2
    # y_i = c0 + c1 x_i + c2 (x^2)_i for i = 1..3; the origin coefficient is 0, hence the
    # "- c0 (1 - tau)^3" of the docstring.
    return c[..., 0, None] + c[..., 1, None] * x + c[..., 2, None] * x_sq


def _blend_weight(u_plan: np.ndarray, u_ref: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Smallest ``lam (...,)`` in [0, 1] with ``lo <= (1 - lam) u_plan + lam u_ref <= hi`` on the last
    axis, given that ``u_ref`` satisfies it: each constraint is affine in lam, so lam is the largest
    of the per-constraint ratios of the violated ones."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        need_hi = np.where(u_plan > hi, (u_plan - hi) / (u_plan - u_ref), 0.0)
        need_lo = np.where(u_plan < lo, (lo - u_plan) / (u_ref - u_plan), 0.0)
    lam = np.maximum(need_hi, need_lo).max(axis=-1)
    return np.clip(np.nan_to_num(lam, nan=1.0), 0.0, 1.0)


def _project_bernstein(
    features: np.ndarray, cp: np.ndarray, horizon: float, safe_set: SafeSet
) -> np.ndarray:
    """The ``mode="bernstein"`` projection of plans ``(..., 3, 2)``; see :func:`project_plan`."""
    x_max = x_limit(features, bspline.control_point_times(horizon), safe_set)  # (..., 3)
    x = np.minimum(cp[..., 0], x_max)
    y_plan = cp[..., 1]
    cl = 0.5 * safe_set.track + safe_set.lateral_margin

    def bounds(x_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # band of the elevated y coefficients: lo_k <= (E y)_k <= hi_k, (..., 7) each
        flat = np.stack([x_, np.zeros_like(x_)], axis=-1)
        hi = bspline.lateral_margin_bernstein(flat, features[..., C0L : C0L + 3], -cl)
        lo = bspline.lateral_margin_bernstein(flat, features[..., C0R : C0R + 3], cl)
        return lo, hi

    def elevate(y: np.ndarray) -> np.ndarray:
        return y @ bspline.ELEVATE_3_TO_6[:, 1:].T  # (..., 7); origin coefficient is 0

    def inside(u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return np.all((u[..., 1:] >= lo[..., 1:]) & (u[..., 1:] <= hi[..., 1:]), axis=-1)

    lo, hi = bounds(x)
    y_ref = _lane_reference_y(features, x)
    u_plan, u_ref = elevate(y_plan), elevate(y_ref)
    ego_inside = (lo[..., 0] <= 0.0) & (hi[..., 0] >= 0.0)
    ref_ok = inside(u_ref, lo, hi)
    lam = np.where(ego_inside & ref_ok, _blend_weight(u_plan, u_ref, lo, hi), 1.0)
    lam = np.where(inside(u_plan, lo, hi), 0.0, lam)[..., None]
    y = np.where(lam == 0.0, y_plan, (1.0 - lam) * y_plan + lam * y_ref)
    # Fallback (car inside, but no cubic y follows the lane within the band at this x profile,
    # e.g. a far-from-constant-speed x): a constant-speed x ending no further than the plan and
    # behind the leader, whose x^2 is exactly a cubic, and the lane-following y at that x.
    fallback = ego_inside & ~ref_ok & ~inside(u_plan, lo, hi)
    if np.any(fallback):
        end = np.minimum(x[..., 2], np.min(x_max * 3.0 / np.arange(1, 4), axis=-1))  # (...,)
        x_lin = end[..., None] * bspline.GREVILLE[1:]
        c = 0.5 * (features[..., C0L : C0L + 3] + features[..., C0R : C0R + 3])
        y_lin = c[..., 0, None] + c[..., 1, None] * x_lin + c[..., 2, None] * (
            end[..., None] ** 2 * _TAU_SQUARED)
        x = np.where(fallback[..., None], x_lin, x)
        y = np.where(fallback[..., None], y_lin, y)
    return np.stack([x, y], axis=-1)


class SafetyFiltered:
    """A Policy wrapper that projects every plan onto the safe set and counts interventions.

    ``interventions``: number of plans changed; ``calls``: number of plans made;
    ``mode``: see :func:`project_plan` ("bernstein", the default, or "control_points").
    """

    def __init__(
        self, policy: Policy, safe_set: SafeSet = FILTER_SAFE_SET, mode: str = "bernstein"
    ) -> None:
        if mode not in FILTER_MODES:
            raise ValueError(f"mode must be one of {FILTER_MODES}, got {mode!r}")
        self.policy = policy
        self.safe_set = safe_set
        self.mode = mode
        self.name = f"{policy.name}+filter"
        self.horizon = float(policy.horizon)
        self.interventions = 0
        self.calls = 0

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Filtered plan ``(..., 3, 2)`` for ``features (..., 9)``."""
        features = np.asarray(features, dtype=float)
        filtered, acted = project_plan(
            features, self.policy.plan(features), self.horizon, self.safe_set, self.mode
        )
        self.calls += int(acted.size)
        self.interventions += int(np.count_nonzero(acted))
        return filtered

    @property
    def intervention_rate(self) -> float:
        return self.interventions / self.calls if self.calls else 0.0
