"""Low-level tracking of a B-spline plan: pure pursuit (lateral) + PID on speed (longitudinal).

Paper, Section IV-B: the planned trajectory is tracked by a Pure Pursuit for the lateral dynamics
and a PID for the longitudinal dynamics; the acceleration command is then converted to throttle and
brake (:func:`safeil_sumo.sim.vehicle.pedals_from_accel`).

A plan is three control points ``(3, 2)`` [m] in the ego frame at plan time (origin = front-bumper
centre, x forward, y left), over a horizon ``T_h`` [s] (see :mod:`safeil_sumo.core.bspline`). At plan time
:func:`make_target` precomputes everything the per-step :func:`track` needs: dense path samples in
the plan frame (extended backwards along the initial tangent and forwards along the final tangent,
so a lookahead past either end still finds a point; a plan that curls back at its end, a stop,
is extended ahead along the chord to its end instead, never back past the ego) and the cubic's power-basis coefficients in
time, from which speed and acceleration are a handful of float operations.

Pure pursuit steers the rear axle towards the path point at distance ``L_d`` ahead:
``delta = atan(2 L sin(alpha) / L_d)``. Two optional corrections of the kinematic law for our
dynamic plant (both on by default, both documented in :class:`ControllerParams`): an understeer
feed-forward ``K_us v^2 kappa`` and measuring ``alpha`` from the rear axle's course (velocity
direction) instead of its heading, so tyre side slip does not bias the tracking on curves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from safeil_sumo.core import bspline
from safeil_sumo.sim.vehicle import (
    VehicleParams,
    VehicleState,
    available_drive_force,
    resistance_force,
)
from safeil_sumo.sim.xp import FLOATS, FloatOrArray, Namespace, clip, maximum

# how far the sampled path is extended beyond its ends along the end tangents [m]
_BACK_EXTENSION_M = 50.0
_FRONT_EXTENSION_M = 1000.0


@dataclass(frozen=True)
class ControllerParams:
    """Gains and limits of the tracking controller."""

    # pure pursuit lookahead L_d = clip(k_v v + L_min, L_min, L_max)
    lookahead_gain_s: float = 0.8  # k_v [s]
    lookahead_min_m: float = 5.0  # L_min [m]
    lookahead_max_m: float = 40.0  # L_max [m]
    # add K_us v^2 kappa to the kinematic angle, so an understeering car follows the curvature
    understeer_feedforward: bool = True
    # measure alpha from the rear axle's velocity direction (heading + rear side-slip angle)
    use_course_angle: bool = True
    # longitudinal: reference speed and feed-forward acceleration are read this far ahead in the
    # plan. The feed-forward is previewed by ~the actuator lag (brake 0.15 s, drive 0.3 s) so the
    # realised acceleration is on time; previewing the SPEED would make the car lead the plan by
    # preview * acceleration on every ramp, so it is 0 by default.
    speed_preview_s: float = 0.0  # [s]
    accel_preview_s: float = 0.2  # [s]
    kp: float = 1.5  # [1/s] (m/s^2 per m/s of speed error)
    ki: float = 0.1  # [1/s^2] (m/s^2 per m of integrated speed error)
    kd: float = 0.0  # [-] (m/s^2 per m/s^2 of error rate)
    # anti-windup: clamp on the integrated error, and integrate only within a band around the
    # reference (large errors are the proportional term's job, e.g. a new plan's speed step)
    integral_limit_m: float = 5.0  # [m]
    integral_band_mps: float = 1.0  # [m/s]
    accel_feedforward_gain: float = 1.0  # [-] times the plan's tangential acceleration
    # a plan slower than this asks to stop: the integral may then only brake
    stop_speed_mps: float = 0.1  # [m/s]
    accel_min_mps2: float = -8.0  # [m/s^2] strongest braking command
    accel_max_mps2: float = 3.0  # [m/s^2] strongest acceleration command


@dataclass(frozen=True, slots=True)
class ControllerState:
    """Memory of the PID."""

    integral: float = 0.0  # [m] integrated speed error
    prev_error: float | None = None  # [m/s] speed error of the last call (None: first call)


@dataclass(frozen=True)
class PathSegments:
    """A polyline ``(N, 2)`` prepared for the per-step lookahead search.

    Vertex coordinates as 1-D arrays (vector distance to all vertices) and as tuples of Python
    floats, segment data as tuples of Python floats (scalar work near the closest vertex).
    """

    vertex_x: np.ndarray  # (N,) [m]
    vertex_y: np.ndarray  # (N,) [m]
    seg_dx: tuple[float, ...]  # (N-1,) [m] segment vectors
    seg_dy: tuple[float, ...]  # (N-1,) [m]
    seg_len2: tuple[float, ...]  # (N-1,) [m^2] squared lengths, floored to avoid division by 0
    xs: tuple[float, ...] = ()  # (N,) [m] vertex_x as floats
    ys: tuple[float, ...] = ()  # (N,) [m] vertex_y as floats

    @staticmethod
    def from_path(path: np.ndarray) -> PathSegments:
        p = np.asarray(path, dtype=float)
        e = np.diff(p, axis=0)
        return PathSegments(
            vertex_x=np.ascontiguousarray(p[:, 0]),
            vertex_y=np.ascontiguousarray(p[:, 1]),
            seg_dx=tuple(e[:, 0].tolist()),
            seg_dy=tuple(e[:, 1].tolist()),
            seg_len2=tuple(np.maximum(e[:, 0] ** 2 + e[:, 1] ** 2, 1e-12).tolist()),
            xs=tuple(p[:, 0].tolist()),
            ys=tuple(p[:, 1].tolist()),
        )


@dataclass(frozen=True)
class TrackingTarget:
    """A plan prepared for tracking; everything in the PLAN frame unless named world."""

    horizon_s: float  # T_h [s]
    origin_x: float  # [m] world x of the front bumper at plan time
    origin_y: float  # [m] world y of the front bumper at plan time
    yaw: float  # [rad] world heading of the ego at plan time
    path: np.ndarray  # (N + 2, 2) [m] samples at ``times`` plus one point before and one after
    times: np.ndarray  # (N,) [s] sample times (the extension points have none)
    # power-basis coefficients of x(t), y(t) [m, m/s, m/s^2, m/s^3] (t in seconds)
    coeff_x: tuple[float, float, float, float]
    coeff_y: tuple[float, float, float, float]
    # per-segment arrays for :func:`lookahead_point`, derived from ``path`` (contiguous, 1-D)
    segments: PathSegments = field(init=False, repr=False)
    cos_yaw: float = field(init=False, repr=False)  # cos(yaw), sin(yaw): once per plan, not step
    sin_yaw: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "segments", PathSegments.from_path(self.path))
        object.__setattr__(self, "cos_yaw", math.cos(self.yaw))
        object.__setattr__(self, "sin_yaw", math.sin(self.yaw))

    def velocity(self, t: float) -> tuple[float, float]:
        """Plan velocity [m/s] at time ``t`` [s], clipped to [0, T_h]."""
        t = min(max(t, 0.0), self.horizon_s)
        cx, cy = self.coeff_x, self.coeff_y
        return (
            cx[1] + t * (2.0 * cx[2] + 3.0 * cx[3] * t),
            cy[1] + t * (2.0 * cy[2] + 3.0 * cy[3] * t),
        )

    def speed_and_accel(self, t: float) -> tuple[float, float]:
        """Plan speed [m/s] and tangential acceleration [m/s^2] at ``t`` [s] (see
        :func:`plan_speed_and_accel`)."""
        # FLOATS (the default) on floats gives floats
        return cast("tuple[float, float]",
                    plan_speed_and_accel(self.coeff_x, self.coeff_y, self.horizon_s, t))

    def lookahead(self, px: float, py: float, ld: float) -> tuple[float, float]:
        """:func:`lookahead_point` on this plan's path."""
        return lookahead_point(self.segments, px, py, ld)


@dataclass(frozen=True)
class BatchTarget:
    """N plans prepared for tracking at once (:func:`track_values` with ``xp=ARRAYS``): what
    :func:`make_target` prepares for one plan, as arrays over N (see :func:`make_targets`)."""

    horizon_s: np.ndarray  # (N,) T_h [s]
    origin_x: np.ndarray  # (N,) [m]
    origin_y: np.ndarray  # (N,) [m]
    yaw: np.ndarray  # (N,) [rad]
    cos_yaw: np.ndarray  # (N,)
    sin_yaw: np.ndarray  # (N,)
    coeff_x: tuple[np.ndarray, ...]  # 4 x (N,) power-basis coefficients of x(t)
    coeff_y: tuple[np.ndarray, ...]  # 4 x (N,)
    path_x: np.ndarray  # (N, M) [m] path vertices in each plan's frame
    path_y: np.ndarray  # (N, M) [m]
    seg_dx: np.ndarray = field(init=False, repr=False)  # (N, M-1) [m] segment vectors
    seg_dy: np.ndarray = field(init=False, repr=False)
    seg_len2: np.ndarray = field(init=False, repr=False)  # (N, M-1) [m^2], floored

    def __post_init__(self) -> None:
        # PathSegments.from_path's arithmetic, once per plan rather than per step
        dx = np.diff(self.path_x, axis=1)
        dy = np.diff(self.path_y, axis=1)
        object.__setattr__(self, "seg_dx", dx)
        object.__setattr__(self, "seg_dy", dy)
        object.__setattr__(self, "seg_len2", np.maximum(dx**2 + dy**2, 1e-12))

    def take(self, keep: np.ndarray) -> BatchTarget:
        """The plans of rows ``keep`` (indices or a boolean mask)."""
        return BatchTarget(
            self.horizon_s[keep], self.origin_x[keep], self.origin_y[keep], self.yaw[keep],
            self.cos_yaw[keep], self.sin_yaw[keep], tuple(c[keep] for c in self.coeff_x),
            tuple(c[keep] for c in self.coeff_y), self.path_x[keep], self.path_y[keep])

    def lookahead(self, px: np.ndarray, py: np.ndarray, ld: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`lookahead_points` on these paths."""
        return lookahead_points(self.path_x, self.path_y, self.seg_dx, self.seg_dy,
                                self.seg_len2, px, py, ld)


def _units(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """:func:`_unit` of rows ``(N, 2)``."""
    n = np.hypot(v[:, 0], v[:, 1])[:, None]
    return np.where(n > 1e-9, v / np.where(n > 1e-9, n, 1.0), fallback)


def make_targets(
    control_points: np.ndarray,
    horizons: np.ndarray,
    origin_x: np.ndarray,
    origin_y: np.ndarray,
    yaw: np.ndarray,
    n_samples: int = 51,
) -> BatchTarget:
    """:func:`make_target` of N plans ``(N, 3, 2)`` [m] over ``horizons (N,)`` [s], made at the
    front-bumper poses ``origin_x, origin_y (N,)`` [m], ``yaw (N,)`` [rad]; the same arithmetic
    on arrays."""
    cp = np.asarray(control_points, dtype=float).reshape(-1, 3, 2)
    horizons = np.asarray(horizons, dtype=float)
    n = len(cp)
    path = np.empty((n, n_samples + 2, 2))
    for h in np.unique(horizons):  # the sample basis is per horizon (one, in practice)
        rows = horizons == h
        _, basis = _sample_basis(float(h), n_samples)
        path[rows, 1:-1] = basis @ bspline.full_coefficients(cp[rows])
    forward = np.broadcast_to(np.array([1.0, 0.0]), (n, 2))
    t0 = _units(cp[:, 0], forward)
    t1 = _units(cp[:, 2] - cp[:, 1], _units(cp[:, 2] - cp[:, 0], t0))
    chord = _units(cp[:, 2], forward)
    # a plan that stops curls back at its end: extend it ahead, never back past the ego
    t1 = np.where(t1[:, :1] > 0.0, t1, np.where(chord[:, :1] > 0.0, chord, forward))
    path[:, 0] = -_BACK_EXTENSION_M * t0
    path[:, -1] = path[:, -2] + _FRONT_EXTENSION_M * t1
    coeff = []
    for axis in (0, 1):
        p1, p2, p3 = cp[:, 0, axis], cp[:, 1, axis], cp[:, 2, axis]
        c_tau = (np.zeros(n), 3.0 * p1, -6.0 * p1 + 3.0 * p2, 3.0 * p1 - 3.0 * p2 + p3)
        coeff.append(tuple(c / horizons**k for k, c in enumerate(c_tau)))
    yaw = np.asarray(yaw, dtype=float)
    return BatchTarget(horizons, np.asarray(origin_x, float), np.asarray(origin_y, float), yaw,
                       np.cos(yaw), np.sin(yaw), coeff[0], coeff[1],
                       np.ascontiguousarray(path[:, :, 0]), np.ascontiguousarray(path[:, :, 1]))


def lookahead_points(
    vertex_x: np.ndarray, vertex_y: np.ndarray, seg_dx: np.ndarray, seg_dy: np.ndarray,
    seg_len2: np.ndarray, px: np.ndarray, py: np.ndarray, ld: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lookahead_point` of N points ``px, py (N,)`` on N polylines ``(N, M)`` (with
    their segment x, y and floored squared lengths ``(N, M-1)``, see :class:`BatchTarget`) at
    distances ``ld (N,)`` [m]: the same arithmetic, the walk replaced by a first-index search."""
    n, m = vertex_x.shape
    rows = np.arange(n)
    dx = vertex_x - px[:, None]
    dy = vertex_y - py[:, None]
    d2 = dx * dx + dy * dy
    i0 = d2.argmin(axis=1)
    best_f2, best_k, best_u = np.full(n, np.inf), np.zeros(n, int), np.zeros(n)
    for k in (i0 - 1, i0):  # the two segments at the closest vertex
        valid = (k >= 0) & (k < m - 1)
        kc = np.clip(k, 0, m - 2)
        ax, ay = dx[rows, kc], dy[rows, kc]
        sx, sy, q = seg_dx[rows, kc], seg_dy[rows, kc], seg_len2[rows, kc]
        dot = ax * sx + ay * sy
        u = np.minimum(np.maximum(-dot / q, 0.0), 1.0)
        f2 = ax * ax + ay * ay + u * (2.0 * dot + u * q)  # |d + u e|^2
        better = valid & (f2 < best_f2)
        best_f2 = np.where(better, f2, best_f2)
        best_k = np.where(better, kc, best_k)
        best_u = np.where(better, u, best_u)
    k, u = best_k, best_u
    ld2 = ld * ld
    # far off the path: its closest point
    near_x = px + dx[rows, k] + u * seg_dx[rows, k]
    near_y = py + dy[rows, k] + u * seg_dy[rows, k]
    # else the first vertex after segment k outside the circle ends the crossing segment j
    outside = (np.arange(m)[None, :] > k[:, None]) & (d2 >= ld2[:, None])
    beyond = ~outside.any(axis=1)  # the circle encloses the rest: the last vertex
    j = np.maximum(outside.argmax(axis=1) - 1, 0)
    ax, ay = dx[rows, j], dy[rows, j]
    sx, sy, qa = seg_dx[rows, j], seg_dy[rows, j], seg_len2[rows, j]
    qb = ax * sx + ay * sy
    qc = ax * ax + ay * ay - ld2
    s = (-qb + np.sqrt(np.maximum(qb * qb - qa * qc, 0.0))) / qa
    s = np.minimum(np.maximum(s, 0.0), 1.0)
    cross_x = np.where(beyond, vertex_x[:, -1], px + ax + s * sx)
    cross_y = np.where(beyond, vertex_y[:, -1], py + ay + s * sy)
    far = best_f2 >= ld2
    return np.where(far, near_x, cross_x), np.where(far, near_y, cross_y)


def plan_speed_and_accel(coeff_x: Sequence[FloatOrArray], coeff_y: Sequence[FloatOrArray],
                         horizon: FloatOrArray, t: FloatOrArray, xp: Namespace = FLOATS
                         ) -> tuple[FloatOrArray, FloatOrArray]:
    """Speed [m/s] and tangential acceleration [m/s^2] at ``t`` [s] of a plan whose x(t), y(t)
    have power-basis coefficients ``coeff_x``, ``coeff_y`` (4 each) over ``horizon`` [s].

    Past the horizon the plan is continued at its final speed (acceleration 0). A plan that
    runs backwards (x velocity < 0 in the plan frame: "stay behind the stopped car") asks for
    a stop: speed 0, no feed-forward (the car does not reverse; reading the speed as the
    velocity's magnitude would make it creep forwards into the car it is told to stay behind).
    Floats, or with ``xp=ARRAYS`` coefficients, ``horizon`` and ``t`` of arrays ``(N,)``.
    """
    return (plan_speed(coeff_x, coeff_y, horizon, t, xp),
            plan_accel(coeff_x, coeff_y, horizon, t, xp))


def plan_speed(coeff_x: Sequence[FloatOrArray], coeff_y: Sequence[FloatOrArray],
               horizon: FloatOrArray, t: FloatOrArray, xp: Namespace = FLOATS) -> FloatOrArray:
    """The speed of :func:`plan_speed_and_accel` alone (the tracker reads the speed and the
    acceleration at different times)."""
    cx, cy = coeff_x, coeff_y
    tc = xp.clip(t, 0.0, horizon)
    vx = cx[1] + tc * (2.0 * cx[2] + 3.0 * cx[3] * tc)
    vy = cy[1] + tc * (2.0 * cy[2] + 3.0 * cy[3] * tc)
    return xp.where(vx < 0.0, 0.0, xp.hypot(vx, vy))  # backwards: stop


def plan_accel(coeff_x: Sequence[FloatOrArray], coeff_y: Sequence[FloatOrArray],
               horizon: FloatOrArray, t: FloatOrArray, xp: Namespace = FLOATS) -> FloatOrArray:
    """The tangential acceleration of :func:`plan_speed_and_accel` alone."""
    cx, cy = coeff_x, coeff_y
    tc = xp.clip(t, 0.0, horizon)
    vx = cx[1] + tc * (2.0 * cx[2] + 3.0 * cx[3] * tc)  # plan_speed's velocity
    vy = cy[1] + tc * (2.0 * cy[2] + 3.0 * cy[3] * tc)
    v = xp.hypot(vx, vy)
    ax = 2.0 * cx[2] + 6.0 * cx[3] * tc
    ay = 2.0 * cy[2] + 6.0 * cy[3] * tc
    # starting from rest the acceleration points along the path (the floor keeps the other
    # side finite)
    accel = xp.where(v < 1e-6, xp.hypot(ax, ay), (vx * ax + vy * ay) / xp.maximum(v, 1e-6))
    accel = xp.where(t > horizon, 0.0, accel)
    return xp.where(vx < 0.0, 0.0, accel)  # backwards: no feed-forward


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = float(np.hypot(v[0], v[1]))
    return v / n if n > 1e-9 else fallback


def make_target(
    control_points: np.ndarray,
    horizon: float,
    plan_pose: tuple[float, float, float],
    n_samples: int = 51,
) -> TrackingTarget:
    """Prepare a plan ``(3, 2)`` [m] over ``horizon`` [s] made at ``plan_pose`` (x, y, yaw).

    ``plan_pose`` is the world pose of the front bumper at plan time: x, y [m], yaw [rad].
    """
    cp = np.asarray(control_points, dtype=float).reshape(3, 2)
    times, basis = _sample_basis(float(horizon), n_samples)
    # bspline.evaluate_time(cp, times, horizon) with the basis of the fixed sample times cached
    pts = basis @ bspline.full_coefficients(cp)
    # end tangents: derivative of the clamped cubic at its ends (fallbacks for degenerate plans)
    forward = np.array([1.0, 0.0])
    t0 = _unit(cp[0], forward)
    t1 = _unit(cp[2] - cp[1], _unit(cp[2] - cp[0], t0))
    if t1[0] <= 0.0:  # a plan that stops curls back: extend it ahead, never back past the ego
        chord = _unit(cp[2], forward)
        t1 = chord if chord[0] > 0.0 else forward
    path = np.empty((n_samples + 2, 2))
    path[0] = -_BACK_EXTENSION_M * t0
    path[1:-1] = pts
    path[-1] = pts[-1] + _FRONT_EXTENSION_M * t1
    # Bernstein -> power basis in tau, then tau = t / T_h (per coordinate, in floats)
    x0, y0, yaw = plan_pose
    coeff = []
    for p1, p2, p3 in (cp[:, 0].tolist(), cp[:, 1].tolist()):
        c_tau = (0.0, 3.0 * p1, -6.0 * p1 + 3.0 * p2, 3.0 * p1 - 3.0 * p2 + p3)
        coeff.append(tuple(c / horizon**k for k, c in enumerate(c_tau)))
    return TrackingTarget(
        horizon_s=float(horizon),
        origin_x=float(x0),
        origin_y=float(y0),
        yaw=float(yaw),
        path=path,
        times=times,
        coeff_x=coeff[0],
        coeff_y=coeff[1],
    )


_BASIS_CACHE: dict[tuple[float, int], tuple[np.ndarray, np.ndarray]] = {}


def _sample_basis(horizon: float, n_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample times ``(n,)`` [s] over the horizon and the B-spline basis ``(n, 4)`` there
    (read-only, cached: every plan of a run has the same horizon)."""
    key = (horizon, n_samples)
    if key not in _BASIS_CACHE:
        if len(_BASIS_CACHE) > 16:
            _BASIS_CACHE.clear()
        times = np.linspace(0.0, horizon, n_samples)
        basis = bspline.basis(np.asarray(times) / horizon)
        times.flags.writeable = basis.flags.writeable = False
        _BASIS_CACHE[key] = times, basis
    return _BASIS_CACHE[key]


def lookahead_distance(v: FloatOrArray, params: ControllerParams, xp: Namespace = FLOATS
                       ) -> FloatOrArray:
    """``L_d`` [m] at speed ``v`` [m/s]."""
    return xp.clip(params.lookahead_gain_s * v + params.lookahead_min_m, params.lookahead_min_m,
                   params.lookahead_max_m)


def lookahead_point(
    path: PathSegments | np.ndarray, px: float, py: float, ld: float
) -> tuple[float, float]:
    """The point of a polyline at distance ``ld`` [m] from ``(px, py)``, ahead.

    Projects ``(px, py)`` on the polyline (``(N, 2)`` or prepared :class:`PathSegments`): on the
    two segments next to the closest vertex, which is exact for the smooth, densely sampled paths
    of a plan. Then walks forward from that segment to the first crossing of the circle of radius
    ``ld``. If even the closest point of the path is farther than ``ld`` (far off the path), that
    closest point is the target; if the circle encloses the rest of the path, its last vertex.
    """
    seg = path if isinstance(path, PathSegments) else PathSegments.from_path(path)
    dx = seg.vertex_x - px  # vertices relative to (px, py): the one vector step
    dy = seg.vertex_y - py
    d2 = dx * dx + dy * dy
    i0 = int(d2.argmin())
    d2 = d2.tolist()
    xs, ys = seg.xs, seg.ys  # xs[k] - px == dx[k] exactly: the scalar work stays in floats
    seg_dx, seg_dy, seg_len2 = seg.seg_dx, seg.seg_dy, seg.seg_len2
    n_seg = len(seg_len2)
    best = (math.inf, 0, 0.0)  # (squared distance, segment, parameter)
    for k in (i0 - 1, i0):
        if 0 <= k < n_seg:
            ax, ay = xs[k] - px, ys[k] - py
            dot = ax * seg_dx[k] + ay * seg_dy[k]
            u = clip(-dot / seg_len2[k], 0.0, 1.0)
            f2 = ax * ax + ay * ay + u * (2.0 * dot + u * seg_len2[k])  # |d + u e|^2
            if f2 < best[0]:
                best = (f2, k, u)
    f2, k, u = best
    ld2 = ld * ld
    if f2 >= ld2:
        return (
            px + (xs[k] - px) + u * seg_dx[k],
            py + (ys[k] - py) + u * seg_dy[k],
        )
    # first end vertex of segments k, k+1, ... outside the circle
    j, n = k + 1, len(d2)
    while j < n and d2[j] < ld2:
        j += 1
    if j == n:
        return xs[-1], ys[-1]
    j -= 1  # the segment that crosses the circle
    # larger root of |d + s e|^2 = ld^2 on segment j: the crossing ahead
    ax, ay = xs[j] - px, ys[j] - py
    sx, sy, qa = seg_dx[j], seg_dy[j], seg_len2[j]
    qb = ax * sx + ay * sy
    qc = ax * ax + ay * ay - ld2
    s = clip((-qb + math.sqrt(maximum(qb * qb - qa * qc, 0.0))) / qa, 0.0, 1.0)
    return px + ax + s * sx, py + ay + s * sy


def pure_pursuit_steer(target_x: FloatOrArray, target_y: FloatOrArray, wheelbase: float,
                       xp: Namespace = FLOATS) -> tuple[FloatOrArray, FloatOrArray]:
    """Road-wheel angle [rad] and curvature [1/m] reaching a target given in the rear-axle frame.

    ``delta = atan(2 L sin(alpha) / l)`` with ``l`` the distance to the target and ``alpha`` its
    bearing; ``kappa = 2 sin(alpha) / l = 2 y / l^2`` (0 for a target on the axle).
    """
    l2 = target_x * target_x + target_y * target_y
    kappa = xp.where(l2 < 1e-12, 0.0, 2.0 * target_y / xp.maximum(l2, 1e-12))
    return xp.atan(wheelbase * kappa), kappa


def track(
    target: TrackingTarget,
    t_since_plan: float,
    state: VehicleState,
    vehicle: VehicleParams,
    ctrl_state: ControllerState,
    params: ControllerParams,
    dt: float,
) -> tuple[float, float, ControllerState]:
    """One control step: ``(steer_cmd [rad], accel_cmd [m/s^2], new controller state)``.

    ``t_since_plan`` [s] is the time elapsed since the plan was made; ``dt`` [s] the control period.
    """
    st = state
    # FLOATS (the default) on floats gives floats
    steer, accel, integral, error = cast("tuple[float, float, float, float]", track_values(
        target, t_since_plan, st.x, st.y, st.yaw, st.vx, st.vy, st.yaw_rate, vehicle,
        ctrl_state.integral, ctrl_state.prev_error, params, dt))
    return steer, accel, ControllerState(integral=integral, prev_error=error)


def track_values(
    target: TrackingTarget | BatchTarget,
    t_since_plan: FloatOrArray,
    x: FloatOrArray,
    y: FloatOrArray,
    yaw: FloatOrArray,
    vx: FloatOrArray,
    vy: FloatOrArray,
    yaw_rate: FloatOrArray,
    vehicle: VehicleParams,
    integral: FloatOrArray,
    prev_error: FloatOrArray | None,
    params: ControllerParams,
    dt: float,
    xp: Namespace = FLOATS,
) -> tuple[FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray]:
    """:func:`track` on plain floats (the closed loop's path: no per-step dataclasses).

    Takes the state's fields and the PID memory, returns ``(steer_cmd, accel_cmd, integral,
    error)``; the last two are the next call's ``integral`` and ``prev_error`` (None or NaN:
    no previous error). With ``xp=ARRAYS`` every argument but the parameters is an array
    ``(N,)`` and ``target`` a :class:`BatchTarget`: N cars tracked at once.
    """
    where = xp.where
    # --- rear axle in the plan frame ----------------------------------------------------------
    lr = vehicle.lr_m
    rx = x - lr * xp.cos(yaw) - target.origin_x
    ry = y - lr * xp.sin(yaw) - target.origin_y
    c0, s0 = target.cos_yaw, target.sin_yaw
    px, py = c0 * rx + s0 * ry, -s0 * rx + c0 * ry
    heading = yaw - target.yaw
    if params.use_course_angle:
        heading = where(vx > 1.0, heading + xp.atan2(vy - lr * yaw_rate, vx), heading)

    # --- lateral: pure pursuit ----------------------------------------------------------------
    v = vx
    ld = lookahead_distance(v, params, xp)
    # floats with a TrackingTarget, arrays with a BatchTarget: a pairing the union cannot say
    gx, gy = target.lookahead(px, py, ld)  # type: ignore[arg-type]
    ch, sh = xp.cos(heading), xp.sin(heading)
    lx, ly = ch * (gx - px) + sh * (gy - py), -sh * (gx - px) + ch * (gy - py)
    steer, kappa = pure_pursuit_steer(lx, ly, vehicle.wheelbase_m, xp)
    if params.understeer_feedforward:
        steer = steer + vehicle.understeer_gradient * v * v * kappa
    steer = xp.clip(steer, -vehicle.max_steer_rad, vehicle.max_steer_rad)

    # --- longitudinal: PID on speed + plan acceleration feed-forward ----------------------------
    horizon = target.horizon_s
    v_ref = plan_speed(target.coeff_x, target.coeff_y, horizon,
                       t_since_plan + params.speed_preview_s, xp)
    a_ref = plan_accel(target.coeff_x, target.coeff_y, horizon,
                       t_since_plan + params.accel_preview_s, xp)
    error = v_ref - v
    if prev_error is None:
        prev_error = math.nan
    deriv = where(xp.isnan(prev_error), 0.0, (error - prev_error) / dt)
    lim = params.integral_limit_m
    integral0 = integral
    # integrate near the reference only
    integral = where(xp.abs(error) < params.integral_band_mps,
                     xp.clip(integral + error * dt, -lim, lim), integral)
    base = params.accel_feedforward_gain * a_ref + params.kp * error + params.kd * deriv
    accel = base + params.ki * integral
    lo, hi = params.accel_min_mps2, params.accel_max_mps2
    # the integrator also stops where the powertrain saturates (power limit at high speed)
    hi_plant = (available_drive_force(v, vehicle, xp)
                - resistance_force(v, vehicle, xp)) / vehicle.mass_kg
    # flags: | and & are logical_or and logical_and
    windup = (((accel > xp.minimum(hi, hi_plant)) & (error > 0.0))
              | ((accel < lo) & (error < 0.0)))
    integral = where(windup, integral0, integral)  # anti-windup: stop integrating into it
    # a plan that (nearly) stops: what was integrated while the car lagged the plan must not
    # hold it rolling forwards (it crept into a standing leader at 0.1 m/s for seconds)
    integral = where(v_ref < params.stop_speed_mps, xp.minimum(integral, 0.0), integral)
    accel = base + params.ki * integral
    accel = xp.clip(accel, lo, hi)
    return steer, accel, integral, error
