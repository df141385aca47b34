"""Low-level tracking of a B-spline plan: pure pursuit (lateral) + PID on speed (longitudinal).

Paper, Section IV-B: the planned trajectory is tracked by a Pure Pursuit for the lateral dynamics
and a PID for the longitudinal dynamics; the acceleration command is then converted to throttle and
brake (:func:`safeil_sumo.sim.vehicle.pedals_from_accel`).

A plan is three control points ``(3, 2)`` [m] in the ego frame at plan time (origin = front-bumper
centre, x forward, y left), over a horizon ``T_h`` [s] (see :mod:`safeil_sumo.bspline`). At plan time
:func:`make_target` precomputes everything the per-step :func:`track` needs: dense path samples in
the plan frame (extended backwards along the initial tangent and forwards along the final tangent,
so a lookahead past either end still finds a point) and the cubic's power-basis coefficients in
time, from which speed and acceleration are a handful of float operations.

Pure pursuit steers the rear axle towards the path point at distance ``L_d`` ahead:
``delta = atan(2 L sin(alpha) / L_d)``. Two optional corrections of the kinematic law for our
dynamic plant (both on by default, both documented in :class:`ControllerParams`): an understeer
feed-forward ``K_us v^2 kappa`` and measuring ``alpha`` from the rear axle's course (velocity
direction) instead of its heading, so tyre side slip does not bias the tracking on curves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from safeil_sumo import bspline
from safeil_sumo.sim.vehicle import (
    VehicleParams,
    VehicleState,
    available_drive_force,
    resistance_force,
)

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
        """Plan speed [m/s] and tangential acceleration [m/s^2] at ``t`` [s].

        Past the horizon the plan is continued at its final speed (acceleration 0). A plan that
        runs backwards (x velocity < 0 in the plan frame: "stay behind the stopped car") asks for
        a stop: speed 0, no feed-forward (the car does not reverse; reading the speed as the
        velocity's magnitude would make it creep forwards into the car it is told to stay behind).
        """
        vx, vy = self.velocity(t)
        if vx < 0.0:
            return 0.0, 0.0
        v = math.hypot(vx, vy)
        if t > self.horizon_s:
            return v, 0.0
        tc = max(t, 0.0)
        cx, cy = self.coeff_x, self.coeff_y
        ax = 2.0 * cx[2] + 6.0 * cx[3] * tc
        ay = 2.0 * cy[2] + 6.0 * cy[3] * tc
        if v < 1e-6:  # starting from rest: the acceleration points along the path
            return v, math.hypot(ax, ay)
        return v, (vx * ax + vy * ay) / v


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


def lookahead_distance(v: float, params: ControllerParams) -> float:
    """``L_d`` [m] at speed ``v`` [m/s]."""
    ld = params.lookahead_gain_s * v + params.lookahead_min_m
    return min(max(ld, params.lookahead_min_m), params.lookahead_max_m)


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
    n_seg = len(seg.seg_len2)
    best = (math.inf, 0, 0.0)  # (squared distance, segment, parameter)
    for k in (i0 - 1, i0):
        if 0 <= k < n_seg:
            ax, ay = xs[k] - px, ys[k] - py
            dot = ax * seg.seg_dx[k] + ay * seg.seg_dy[k]
            u = min(max(-dot / seg.seg_len2[k], 0.0), 1.0)
            f2 = ax * ax + ay * ay + u * (2.0 * dot + u * seg.seg_len2[k])  # |d + u e|^2
            if f2 < best[0]:
                best = (f2, k, u)
    f2, k, u = best
    ld2 = ld * ld
    if f2 >= ld2:
        return (
            px + (xs[k] - px) + u * seg.seg_dx[k],
            py + (ys[k] - py) + u * seg.seg_dy[k],
        )
    # first end vertex of segments k, k+1, ... outside the circle
    j = k + 1
    while j < len(d2) and d2[j] < ld2:
        j += 1
    if j == len(d2):
        return xs[-1], ys[-1]
    j -= 1  # the segment that crosses the circle
    # larger root of |d + s e|^2 = ld^2 on segment j: the crossing ahead
    ax, ay = xs[j] - px, ys[j] - py
    sx, sy, qa = seg.seg_dx[j], seg.seg_dy[j], seg.seg_len2[j]
    qb = ax * sx + ay * sy
    qc = ax * ax + ay * ay - ld2
    s = (-qb + math.sqrt(max(qb * qb - qa * qc, 0.0))) / qa
    s = min(max(s, 0.0), 1.0)
    return px + ax + s * sx, py + ay + s * sy


def pure_pursuit_steer(target_x: float, target_y: float, wheelbase: float) -> tuple[float, float]:
    """Road-wheel angle [rad] and curvature [1/m] reaching a target given in the rear-axle frame.

    ``delta = atan(2 L sin(alpha) / l)`` with ``l`` the distance to the target and ``alpha`` its
    bearing; ``kappa = 2 sin(alpha) / l = 2 y / l^2``.
    """
    l2 = target_x * target_x + target_y * target_y
    if l2 < 1e-12:
        return 0.0, 0.0
    kappa = 2.0 * target_y / l2
    return math.atan(wheelbase * kappa), kappa


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
    steer, accel, integral, error = track_values(
        target, t_since_plan, st.x, st.y, st.yaw, st.vx, st.vy, st.yaw_rate, vehicle,
        ctrl_state.integral, ctrl_state.prev_error, params, dt)
    return steer, accel, ControllerState(integral=integral, prev_error=error)


def track_values(
    target: TrackingTarget,
    t_since_plan: float,
    x: float,
    y: float,
    yaw: float,
    vx: float,
    vy: float,
    yaw_rate: float,
    vehicle: VehicleParams,
    integral: float,
    prev_error: float | None,
    params: ControllerParams,
    dt: float,
) -> tuple[float, float, float, float]:
    """:func:`track` on plain floats (the closed loop's path: no per-step dataclasses).

    Takes the state's fields and the PID memory, returns ``(steer_cmd, accel_cmd, integral,
    error)``; the last two are the next call's ``integral`` and ``prev_error``.
    """
    # --- rear axle in the plan frame ----------------------------------------------------------
    lr = vehicle.lr_m
    rx = x - lr * math.cos(yaw) - target.origin_x
    ry = y - lr * math.sin(yaw) - target.origin_y
    c0, s0 = target.cos_yaw, target.sin_yaw
    px, py = c0 * rx + s0 * ry, -s0 * rx + c0 * ry
    heading = yaw - target.yaw
    if params.use_course_angle and vx > 1.0:
        heading += math.atan2(vy - lr * yaw_rate, vx)

    # --- lateral: pure pursuit ----------------------------------------------------------------
    v = vx
    ld = lookahead_distance(v, params)
    gx, gy = lookahead_point(target.segments, px, py, ld)
    ch, sh = math.cos(heading), math.sin(heading)
    lx, ly = ch * (gx - px) + sh * (gy - py), -sh * (gx - px) + ch * (gy - py)
    steer, kappa = pure_pursuit_steer(lx, ly, vehicle.wheelbase_m)
    if params.understeer_feedforward:
        steer += vehicle.understeer_gradient * v * v * kappa
    steer = min(max(steer, -vehicle.max_steer_rad), vehicle.max_steer_rad)

    # --- longitudinal: PID on speed + plan acceleration feed-forward ----------------------------
    v_ref, _ = target.speed_and_accel(t_since_plan + params.speed_preview_s)
    _, a_ref = target.speed_and_accel(t_since_plan + params.accel_preview_s)
    error = v_ref - v
    deriv = 0.0 if prev_error is None else (error - prev_error) / dt
    lim = params.integral_limit_m
    integral0 = integral
    if abs(error) < params.integral_band_mps:  # integrate near the reference only
        integral = min(max(integral + error * dt, -lim), lim)
    base = params.accel_feedforward_gain * a_ref + params.kp * error + params.kd * deriv
    accel = base + params.ki * integral
    lo, hi = params.accel_min_mps2, params.accel_max_mps2
    # the integrator also stops where the powertrain saturates (power limit at high speed)
    hi_plant = (available_drive_force(v, vehicle) - resistance_force(v, vehicle)) / vehicle.mass_kg
    if (accel > min(hi, hi_plant) and error > 0.0) or (accel < lo and error < 0.0):
        integral = integral0  # anti-windup: stop integrating into the saturation
        accel = base + params.ki * integral
    accel = min(max(accel, lo), hi)
    return steer, accel, integral, error
