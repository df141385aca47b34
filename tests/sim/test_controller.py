"""Tracking controller: hand-computed pure pursuit and closed loops with the plant, no SUMO."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from safeil_sumo.core import bspline
from safeil_sumo.sim.controller import (
    ControllerParams,
    ControllerState,
    TrackingTarget,
    lookahead_distance,
    lookahead_point,
    make_target,
    pure_pursuit_steer,
    track,
)
from safeil_sumo.sim.vehicle import (
    VehicleParams,
    VehicleState,
    front_bumper,
    pedals_from_accel,
    rear_axle,
    state_from_front_bumper,
    step,
)

VP = VehicleParams()
CP = ControllerParams()
DT = 0.01
HORIZON = 5.0


def straight_plan(v: float) -> np.ndarray:
    """Control points of a constant-speed straight plan along the ego x axis."""
    return np.array([[v * HORIZON / 3.0 * i, 0.0] for i in (1, 2, 3)])


def state_with_rear_axle(x: float, y: float, yaw: float, v: float) -> VehicleState:
    return VehicleState(
        x + VP.lr_m * math.cos(yaw), y + VP.lr_m * math.sin(yaw), yaw, v, 0.0, 0.0, 0.0, 0.0
    )


def closed_loop_step(target: TrackingTarget, t: float, s: VehicleState, cs: ControllerState):
    steer, accel, cs = track(target, t, s, VP, cs, CP, DT)
    throttle, brake = pedals_from_accel(accel, s, VP)
    return step(s, steer, throttle, brake, VP, DT), cs


# --- pure pursuit geometry ------------------------------------------------------------------


def test_pure_pursuit_steer_hand_computed():
    # target 10 m ahead, 1 m left of the rear axle: kappa = 2 * 1 / 101, delta = atan(L kappa)
    delta, kappa = pure_pursuit_steer(10.0, 1.0, 2.7)
    assert kappa == pytest.approx(0.0198020, abs=1e-7)
    assert delta == pytest.approx(0.0534144, abs=1e-6)  # atan(0.0534653)


def test_lookahead_point_on_straight_path():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    # 1 m beside the path at x = 0: the circle of radius 5 cuts it at x = sqrt(24)
    assert lookahead_point(path, 0.0, 1.0, 5.0) == pytest.approx((math.sqrt(24.0), 0.0))
    # behind the path's last vertex the circle encloses the rest: the last vertex
    assert lookahead_point(path, 18.0, 0.0, 5.0) == pytest.approx((20.0, 0.0))
    # farther than ld from the path: its closest point
    assert lookahead_point(path, 5.0, 8.0, 5.0) == pytest.approx((5.0, 0.0))


def test_track_steering_hand_computed():
    # straight plan along world x; rear axle at (10, 1), heading along x, vx = 10 m/s
    # L_d = 0.8 * 10 + 5 = 13 m -> target (10 + sqrt(168), 0) -> relative (12.9615, -1)
    # kappa = 2 * (-1) / 169, delta = atan(2.7 * kappa) = -0.0319418 rad
    target = make_target(straight_plan(25.0), HORIZON, (0.0, 0.0, 0.0))
    s = state_with_rear_axle(10.0, 1.0, 0.0, 10.0)
    kinematic = replace(CP, understeer_feedforward=False, use_course_angle=False)
    assert lookahead_distance(10.0, CP) == pytest.approx(13.0)
    steer, _, _ = track(target, 0.0, s, VP, ControllerState(), kinematic, DT)
    assert steer == pytest.approx(-0.0319418, abs=1e-6)
    # with the understeer feed-forward: + K_us v^2 kappa
    steer_ff, _, _ = track(target, 0.0, s, VP, ControllerState(), CP, DT)
    assert steer_ff == pytest.approx(-0.0319418 + VP.understeer_gradient * 100.0 * -2.0 / 169.0)


def test_track_in_a_rotated_plan_frame():
    # the same situation rotated by 30 deg and shifted in the world gives the same command
    yaw0, ox, oy = math.radians(30.0), 100.0, -50.0
    c, s_ = math.cos(yaw0), math.sin(yaw0)
    target = make_target(straight_plan(25.0), HORIZON, (ox, oy, yaw0))
    rx, ry = ox + 10.0 * c - 1.0 * s_, oy + 10.0 * s_ + 1.0 * c
    s = state_with_rear_axle(rx, ry, yaw0, 10.0)
    kinematic = replace(CP, understeer_feedforward=False, use_course_angle=False)
    steer, _, _ = track(target, 0.0, s, VP, ControllerState(), kinematic, DT)
    assert steer == pytest.approx(-0.0319418, abs=1e-6)


def test_lookahead_past_the_plan_end_follows_the_final_tangent():
    # a plan turning left ends with heading atan2(dy, dx) of its last control-point leg
    cp = np.array([[40.0, 0.0], [80.0, 2.0], [120.0, 8.0]])
    target = make_target(cp, HORIZON, (0.0, 0.0, 0.0))
    end = cp[2]
    tangent = (cp[2] - cp[1]) / np.linalg.norm(cp[2] - cp[1])
    p = end + 5.0 * tangent  # already past the end, on the extension
    gx, gy = lookahead_point(target.segments, p[0], p[1], 20.0)
    assert np.allclose([gx, gy], end + 25.0 * tangent, atol=1e-9)


@pytest.mark.parametrize("cp, ahead", [
    # a stop planned at walking pace (curved500, the leader braking to a halt): the spline
    # reaches 5.6 m and curls back to 4.4 m; ahead of it: the chord from the ego to its end
    ([[4.55, 0.07], [5.56, 0.2], [4.44, 0.07]], (4.44, 0.07)),
    # a plan ending behind the ego: straight ahead
    ([[-1.0, 0.3], [-2.0, 0.5], [-3.0, 0.4]], (1.0, 0.0)),
])
def test_a_plan_that_curls_back_is_extended_ahead_never_behind(cp, ahead):
    """With a lookahead circle enclosing the whole plan, the target is on the plan's extension:
    it must lie ahead of the ego (following the final tangent back would put it 1,000 m behind
    and 70-120 m to the side: full steering lock at a stop)."""
    from safeil_sumo.sim.controller import make_targets

    cp = np.array(cp)
    direction = np.array(ahead) / np.hypot(*ahead)
    batch = make_targets(cp[None], np.array([HORIZON]), np.zeros(1), np.zeros(1), np.zeros(1))
    for path in (make_target(cp, HORIZON, (0.0, 0.0, 0.0)).path,
                 np.stack([batch.path_x[0], batch.path_y[0]], axis=1)):
        np.testing.assert_allclose(path[-1], path[-2] + 1000.0 * direction, atol=1e-9)
    gx, gy = lookahead_point(make_target(cp, HORIZON, (0.0, 0.0, 0.0)).segments, -2.7, 0.0, 9.0)
    assert gx > 0.0 and abs(gy) < 0.5


# --- plan evaluation ------------------------------------------------------------------------


def test_a_plan_running_backwards_asks_for_a_stop():
    # a stopped car told to stay 3-7 m behind where it is: x decreases along the plan
    cp = np.array([[-4.0, 0.0], [-6.0, 0.0], [-7.0, 0.0]])
    target = make_target(cp, HORIZON, (0.0, 0.0, 0.0))
    assert target.velocity(0.0)[0] < 0
    for t in (0.0, 1.0, 4.9):
        assert target.speed_and_accel(t) == (0.0, 0.0)
    # forwards at the start: the magnitude as before
    fwd = make_target(np.array([[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]]), HORIZON, (0.0, 0.0, 0.0))
    assert fwd.speed_and_accel(0.0)[0] == pytest.approx(30.0 / HORIZON)

control_points = arrays(np.float64, (3, 2), elements=st.floats(-100.0, 200.0))


@settings(max_examples=100, deadline=None)
@given(cp=control_points, t=st.floats(0.0, HORIZON))
def test_power_basis_matches_bspline(cp, t):
    target = make_target(cp, HORIZON, (0.0, 0.0, 0.0))
    vel = bspline.evaluate_time(cp, np.array([t]), HORIZON, derivative=1)[0]
    acc = bspline.evaluate_time(cp, np.array([t]), HORIZON, derivative=2)[0]
    assert target.velocity(t) == pytest.approx(tuple(vel), abs=1e-6)
    v, a = target.speed_and_accel(t)
    if vel[0] < 0.0 or (abs(vel[0]) < 1e-9 and (v, a) == (0.0, 0.0)):
        # a plan running backwards asks for a stop (at x velocity 0 rounding decides the side)
        assert (v, a) == (0.0, 0.0)
        return
    assert v == pytest.approx(float(np.linalg.norm(vel)), abs=1e-6)
    if v > 1e-3:
        assert a == pytest.approx(float(vel @ acc) / v, abs=1e-6)
    pts = bspline.evaluate_time(cp, target.times, HORIZON)
    assert np.allclose(target.path[1:-1], pts)


@settings(max_examples=150, deadline=None)
@given(
    cp=control_points,
    t=st.floats(0.0, 8.0),
    x=st.floats(-50.0, 250.0),
    y=st.floats(-30.0, 30.0),
    yaw=st.floats(-1.0, 1.0),
    v=st.floats(0.0, 45.0),
    integral=st.floats(-5.0, 5.0),
)
def test_outputs_within_limits(cp, t, x, y, yaw, v, integral):
    target = make_target(cp, HORIZON, (0.0, 0.0, 0.0))
    s = VehicleState(x, y, yaw, v, 0.0, 0.0, 0.0, 0.0)
    cs = ControllerState(integral=integral, prev_error=0.0)
    steer, accel, cs2 = track(target, t, s, VP, cs, CP, DT)
    assert abs(steer) <= VP.max_steer_rad
    assert CP.accel_min_mps2 <= accel <= CP.accel_max_mps2
    assert abs(cs2.integral) <= CP.integral_limit_m
    throttle, brake = pedals_from_accel(accel, s, VP)
    assert throttle == 0.0 or brake == 0.0


# --- closed loops with the plant --------------------------------------------------------------


def test_straight_plan_converges_from_a_lateral_offset():
    v = 25.0
    target = make_target(straight_plan(v), HORIZON, (0.0, 0.0, 0.0))
    s, cs = state_from_front_bumper(0.0, 0.5, 0.0, v, VP), ControllerState()
    lateral = []  # [m] CoG, rear axle and bumper offsets from the plan's line y = 0
    for k in range(800):
        s, cs = closed_loop_step(target, k * DT, s, cs)
        lateral.append((s.y, rear_axle(s, VP)[1], front_bumper(s, VP)[1]))
    lateral = np.array(lateral)
    after_5s = np.abs(lateral[500:]).max()
    assert after_5s < 0.05
    assert lateral.min() > -0.2  # overshoot below the line
    assert abs(s.vx - v) < 0.05


def _arc_plan(s: VehicleState, radius: float, v: float) -> tuple[np.ndarray, tuple]:
    """Control points of the arc (centre (0, R), driven counter-clockwise) from the bumper on."""
    bx, by = front_bumper(s, VP)
    s0 = radius * math.atan2(bx, radius - by)  # arc length of the bumper's projection
    tau = np.linspace(0.0, 1.0, 21)
    th = (s0 + v * HORIZON * tau) / radius
    pts = np.stack([radius * np.sin(th), radius - radius * np.cos(th)], axis=1)
    c, sn = math.cos(s.yaw), math.sin(s.yaw)
    d = pts - [bx, by]
    local = np.stack([c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]], axis=1)
    return bspline.fit_control_points(local, tau), (bx, by, s.yaw)


def test_constant_curvature_arc_steady_error():
    radius, v = 500.0, 30.0
    s, cs = state_from_front_bumper(0.0, 0.0, 0.0, v, VP), ControllerState()
    errors = []  # radial offsets [m] of CoG and front bumper (positive = outside)
    for k in range(3000):  # 30 s, re-planned every 0.1 s
        if k % 10 == 0:
            cp, pose = _arc_plan(s, radius, v)
            target, t0 = make_target(cp, HORIZON, pose), k
        s, cs = closed_loop_step(target, (k - t0) * DT, s, cs)
        bx, by = front_bumper(s, VP)
        errors.append(
            (math.hypot(s.x, s.y - radius) - radius, math.hypot(bx, by - radius) - radius)
        )
    steady = np.abs(np.array(errors[-1000:]))  # last 10 s
    assert steady.max() < 0.10
    assert abs(s.vx - v) < 0.1


def test_speed_step_settles():
    target = make_target(straight_plan(30.0), HORIZON, (0.0, 0.0, 0.0))
    s, cs = state_from_front_bumper(0.0, 0.0, 0.0, 25.0, VP), ControllerState()
    speeds = []
    for k in range(1000):
        s, cs = closed_loop_step(target, k * DT, s, cs)
        speeds.append(s.vx)
    speeds = np.array(speeds)
    assert speeds.max() - 30.0 < 0.5  # overshoot
    assert np.abs(speeds[400:] - 30.0).max() < 0.1  # within 2 % of the step after 4 s


def test_speed_step_down_and_hold():
    target = make_target(straight_plan(20.0), HORIZON, (0.0, 0.0, 0.0))
    s, cs = state_from_front_bumper(0.0, 0.0, 0.0, 30.0, VP), ControllerState()
    speeds = []
    for k in range(1000):
        s, cs = closed_loop_step(target, k * DT, s, cs)
        speeds.append(s.vx)
    speeds = np.array(speeds)
    assert speeds.min() > 19.5
    assert np.abs(speeds[400:] - 20.0).max() < 0.1


def test_decelerating_plan_uses_acceleration_feedforward():
    # plan from 25 m/s braking at 2 m/s^2: x(t) = 25 t - t^2 fitted exactly by the cubic
    t = np.linspace(0.0, HORIZON, 21)
    pts = np.stack([25.0 * t - t**2, np.zeros_like(t)], axis=1)
    cp = bspline.fit_control_points(pts, t / HORIZON)
    target = make_target(cp, HORIZON, (0.0, 0.0, 0.0))
    assert target.speed_and_accel(1.0) == pytest.approx((23.0, -2.0), abs=1e-9)
    s, cs = state_from_front_bumper(0.0, 0.0, 0.0, 25.0, VP), ControllerState()
    for k in range(400):
        s, cs = closed_loop_step(target, k * DT, s, cs)
    assert s.vx == pytest.approx(25.0 - 2.0 * 4.0, abs=0.15)


def test_integrator_does_not_wind_up_under_power_saturation():
    # 20 -> 35 m/s: the powertrain limits the acceleration for several seconds
    target = make_target(straight_plan(35.0), HORIZON, (0.0, 0.0, 0.0))
    s, cs = state_from_front_bumper(0.0, 0.0, 0.0, 20.0, VP), ControllerState()
    speeds = []
    for k in range(2000):
        s, cs = closed_loop_step(target, k * DT, s, cs)
        speeds.append(s.vx)
    assert max(speeds) - 35.0 < 0.3
    assert abs(speeds[-1] - 35.0) < 0.05


def test_a_stop_request_releases_the_forward_integral():
    # 0.12 m/s with 1.3 m of integrated error (the car lagged the plan while it started) behind
    # a plan asking for 0.05 m/s (< stop_speed_mps): the integral may only brake, so it is 0
    # and the command is the P term alone, kp * (0.05 - 0.12); a plan at 0.5 m/s keeps it
    s = state_from_front_bumper(0.0, 0.0, 0.0, 0.12, VP)
    stop = make_target(straight_plan(0.05), HORIZON, (0.0, 0.0, 0.0))
    _, accel, cs = track(stop, 0.0, s, VP, ControllerState(1.3, None), CP, DT)
    assert cs.integral == 0.0
    assert accel == pytest.approx(CP.kp * (0.05 - 0.12), abs=1e-9)
    slow = make_target(straight_plan(0.5), HORIZON, (0.0, 0.0, 0.0))
    _, accel, cs = track(slow, 0.0, s, VP, ControllerState(1.3, None), CP, DT)
    assert cs.integral == pytest.approx(1.3 + (0.5 - 0.12) * DT)
    assert accel == pytest.approx(CP.kp * (0.5 - 0.12) + CP.ki * cs.integral, abs=1e-9)


def test_a_stop_request_stops_the_car_within_centimetres():
    # the same start, closed loop: the car rolls ~ v / kp = 8 cm and stops (with the integral
    # holding it, it crept on at ~0.1 m/s into a standing leader 0.4 m ahead)
    stop = make_target(straight_plan(0.0), HORIZON, (0.0, 0.0, 0.0))
    s, cs = state_from_front_bumper(0.0, 0.0, 0.0, 0.12, VP), ControllerState(1.3, None)
    x0 = front_bumper(s, VP)[0]
    for k in range(1000):
        s, cs = closed_loop_step(stop, k * DT, s, cs)
    assert s.vx < 1e-3
    assert front_bumper(s, VP)[0] - x0 < 0.15


def test_batched_plans_and_lookahead_equal_the_scalar_ones():
    """make_targets and lookahead_points (the batch's tracker) are bit-identical to make_target
    and lookahead_point on seeded random plans, degenerate ones included, two horizons mixed."""
    from safeil_sumo.sim.controller import lookahead_point, make_target, make_targets

    rng = np.random.default_rng(1)
    n = 64
    cps = np.cumsum(rng.normal([10.0, 0.0], [8.0, 2.0], size=(n, 3, 2)), axis=1)
    cps[:5] = rng.normal(0.0, 1e-11, (5, 3, 2))  # a plan that stays put: tangent fallbacks
    cps[5, 2] = cps[5, 1]
    horizons = np.where(rng.random(n) < 0.5, 3.0, 5.0)
    ox, oy, yaw = rng.normal(0.0, 100.0, (3, n))
    batch = make_targets(cps, horizons, ox, oy, yaw)
    px, py, ld = rng.normal(0, 10, n), rng.normal(0, 5, n), rng.uniform(5.0, 40.0, n)
    gx, gy = batch.lookahead(px, py, ld)
    for i in range(n):
        one = make_target(cps[i], horizons[i], (ox[i], oy[i], yaw[i]))
        assert np.array_equal(one.path[:, 0], batch.path_x[i])
        assert np.array_equal(one.path[:, 1], batch.path_y[i])
        assert one.coeff_x == tuple(c[i] for c in batch.coeff_x)
        assert one.coeff_y == tuple(c[i] for c in batch.coeff_y)
        assert lookahead_point(one.segments, float(px[i]), float(py[i]), float(ld[i])) == (
            gx[i], gy[i])
