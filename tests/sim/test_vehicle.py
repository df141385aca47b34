"""Vehicle plant: hand-computed steps and open-loop manoeuvres, no SUMO."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.sim.vehicle import (
    VehicleParams,
    VehicleState,
    front_bumper,
    pedals_from_accel,
    rear_axle,
    speed,
    state_from_front_bumper,
    step,
)

P = VehicleParams()
DT = 0.01
GRAVITY_DEG = 9.81 * 180.0 / math.pi  # [deg/g per rad/(m/s^2)]


def straight(v: float, drive_force: float = 0.0) -> VehicleState:
    return VehicleState(0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, drive_force)


def hold_speed(state: VehicleState, v_ref: float) -> tuple[float, float]:
    """Pedals of a stiff speed holder (the test's own, not the package's controller)."""
    return pedals_from_accel(2.0 * (v_ref - state.vx), state, P)


def fit_circle(xy: np.ndarray) -> tuple[float, float, float]:
    """Algebraic (Kasa) least-squares circle: centre x, y and radius."""
    x, y = xy[:, 0], xy[:, 1]
    a = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
    cx, cy, c = np.linalg.lstsq(a, x**2 + y**2, rcond=None)[0]
    return cx, cy, math.sqrt(c + cx**2 + cy**2)


def test_params_geometry():
    assert P.lf_m + P.lr_m == pytest.approx(P.wheelbase_m)
    assert P.lf_m < P.lr_m  # front-heavy FWD car: CoG nearer the front axle
    assert P.barrier_width_m == P.width_m == 1.76
    assert P.track_m == 1.53
    assert 0.0 < P.understeer_gradient * GRAVITY_DEG < 4.0  # 1-4 deg/g: mild understeer
    # front overhang + wheelbase + rear overhang = length, with a plausible rear overhang
    assert 0.7 < P.length_m - P.wheelbase_m - P.front_overhang_m < 1.1


def test_coasting_one_step_is_drag_plus_rolling():
    # hand computation at 30 m/s, no actuator force:
    # drag = 0.5 * 1.225 * 0.24 * 2.2 * 30^2 = 291.06 N; rolling = 0.010 * 1500 * 9.81 = 147.15 N
    # a = -(291.06 + 147.15) / 1500 = -0.29214 m/s^2
    s = step(straight(30.0), 0.0, 0.0, 0.0, P, DT)
    assert s.vx == pytest.approx(30.0 - 0.29214 * DT, abs=1e-9)
    assert s.x == pytest.approx(s.vx * DT, abs=1e-12)  # semi-implicit: new velocity moves it
    assert s.y == 0.0 and s.vy == 0.0 and s.yaw_rate == 0.0 and s.drive_force == 0.0


def test_full_brake_stops_within_physical_distance():
    s = straight(30.0, drive_force=0.0)
    x_prev, t = s.x, 0.0
    while s.vx > 0.0:
        s = step(s, 0.0, 0.0, 1.0, P, DT)
        assert s.x >= x_prev  # never moves backwards
        x_prev, t = s.x, t + DT
        assert t < 10.0
    ideal = 30.0**2 / (2.0 * P.max_brake_decel_mps2)  # 50 m
    lag_allowance = 30.0 * P.brake_time_constant_s  # the force builds up over ~tau
    assert ideal - 5.0 < s.x <= ideal + lag_allowance
    # braking at standstill holds the car
    for _ in range(200):
        s2 = step(s, 0.0, 0.0, 1.0, P, DT)
        assert s2.vx == 0.0 and s2.x == s.x
        s = s2


def test_kinematic_turning_radius_at_low_speed():
    delta = 0.2  # [rad]
    s = replace(straight(1.5), steer=delta)
    pts = []
    for k in range(3000):
        th, br = hold_speed(s, 1.5)
        s = step(s, delta, th, br, P, DT)
        if k >= 200:
            pts.append(rear_axle(s, P))
    _, _, radius = fit_circle(np.array(pts))
    assert radius == pytest.approx(P.wheelbase_m / math.tan(delta), rel=0.005)


def test_steady_state_yaw_rate_matches_linear_single_track():
    delta, v = 0.01, 25.0
    s = state_from_front_bumper(0.0, 0.0, 0.0, v, P)
    for _ in range(1000):  # 10 s
        th, br = hold_speed(s, v)
        s = step(s, delta, th, br, P, DT)
    expected = s.vx * delta / (P.wheelbase_m + P.understeer_gradient * s.vx**2)
    assert s.yaw_rate == pytest.approx(expected, rel=0.02)
    kinematic = s.vx * math.tan(delta) / P.wheelbase_m
    # characteristic speed sqrt(L / K_us) ~ 30 m/s: at 25 m/s the yaw gain is ~60 % of kinematic
    assert 0.5 * kinematic < s.yaw_rate < 0.7 * kinematic


@pytest.mark.parametrize("accel", [-6.0, -3.0, -1.0, 0.0, 0.5, 1.5])
def test_pedals_realise_commanded_acceleration(accel):
    s = state_from_front_bumper(0.0, 0.0, 0.0, 20.0, P)
    for _ in range(150):  # 1.5 s = 5 drive time constants
        th, br = pedals_from_accel(accel, s, P)
        assert th == 0.0 or br == 0.0
        prev, s = s, step(s, 0.0, th, br, P, DT)
    assert (s.vx - prev.vx) / DT == pytest.approx(accel, abs=0.05)


def test_drive_power_limit_saturates_throttle():
    s = straight(30.0)
    th, br = pedals_from_accel(3.0, s, P)
    assert th == 1.0 and br == 0.0
    s = replace(s, drive_force=P.max_drive_power_w / 30.0)
    s2 = step(s, 0.0, 1.0, 0.0, P, DT)
    assert (s2.vx - s.vx) / DT < 2.0  # ~81 kW at the wheels: < 2 m/s^2 at 30 m/s


def test_steering_actuator_rate_and_angle_limits():
    s = straight(10.0)
    s1 = step(s, 0.5, 0.0, 0.0, P, DT)
    assert s1.steer == pytest.approx(P.max_steer_rate_radps * DT)
    for _ in range(500):
        s = step(s, 2.0, 0.0, 0.0, P, DT)
    assert s.steer == pytest.approx(P.max_steer_rad, abs=1e-6)
    # small commands follow the first-order lag exactly
    s = straight(10.0)
    s1 = step(s, 0.001, 0.0, 0.0, P, DT)
    assert s1.steer == pytest.approx(0.001 * (1.0 - math.exp(-DT / P.steer_time_constant_s)))


def test_kinematic_dynamic_blend_is_continuous():
    delta = 0.05
    speeds = np.arange(0.5, 8.0, 0.01)
    rates = []
    for v in speeds:
        # the kinematic steady state at v is the starting point for both models
        r0 = v * math.tan(delta) / P.wheelbase_m
        s = VehicleState(0.0, 0.0, 0.0, v, P.lr_m * r0, r0, delta, 0.0)
        rates.append(step(s, delta, 0.0, 0.0, P, DT).yaw_rate)
    jumps = np.abs(np.diff(rates))
    assert jumps.max() < 5.0 * np.median(jumps) + 1e-4


def test_stable_at_40_mps_with_sine_steer():
    # 0.02 rad road wheel at 0.5 Hz: a lively lane-change-like slalom inside the linear range
    s = state_from_front_bumper(0.0, 0.0, 0.0, 40.0, P)
    for k in range(6000):  # 60 s
        th, br = hold_speed(s, 40.0)
        s = step(s, 0.02 * math.sin(2.0 * math.pi * 0.5 * k * DT), th, br, P, DT)
        assert abs(s.vy) < 1.0 and abs(s.yaw_rate) < 0.2 and abs(s.steer) <= 0.02
    assert abs(s.vx - 40.0) < 0.5
    assert all(math.isfinite(v) for v in (s.x, s.y, s.yaw, s.vx, s.vy, s.yaw_rate))


def test_bounded_beyond_the_friction_limit():
    # 0.06 rad at 40 m/s asks for ~3 g: the tyres saturate and the car slides (no ESC in the
    # model); the integration must stay bounded and the lateral acceleration within mu g.
    s = state_from_front_bumper(0.0, 0.0, 0.0, 40.0, P)
    for k in range(6000):
        th, br = hold_speed(s, 40.0)
        s2 = step(s, 0.06 * math.sin(2.0 * math.pi * 0.5 * k * DT), th, br, P, DT)
        ay = (s2.vy - s.vy) / DT + s.vx * s2.yaw_rate
        assert abs(ay) < 1.05 * P.friction_coefficient * 9.81
        assert speed(s2) < 41.0 and abs(s2.yaw_rate) < 1.0
        s = s2


def test_lateral_force_saturates_at_friction_limit():
    # a large constant steer at 30 m/s: the lateral acceleration cannot exceed mu g
    s = state_from_front_bumper(0.0, 0.0, 0.0, 30.0, P)
    ays = []
    for _ in range(300):
        s2 = step(s, 0.3, 0.0, 0.0, P, DT)
        ays.append((s2.vy - s.vy) / DT + s.vx * s2.yaw_rate)
        s = s2
    assert max(abs(a) for a in ays) < 1.02 * P.friction_coefficient * 9.81
    assert abs(ays[-1]) > 0.95 * P.friction_coefficient * 9.81  # it does reach the limit


@settings(max_examples=60, deadline=None)
@given(
    v0=st.floats(0.0, 40.0),
    pedals=st.lists(
        st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(-0.6, 0.6)),
        min_size=1,
        max_size=20,
    ),
)
def test_never_reverses(v0, pedals):
    s = state_from_front_bumper(0.0, 0.0, 0.0, v0, P)
    for th, br, steer in pedals:
        for _ in range(50):
            s = step(s, steer, th, br, P, DT)
            assert s.vx >= 0.0
            assert math.isfinite(s.x) and math.isfinite(s.yaw_rate)


@settings(max_examples=200, deadline=None)
@given(accel=st.floats(-20.0, 20.0), v=st.floats(0.0, 50.0))
def test_pedals_in_range_and_never_both(accel, v):
    th, br = pedals_from_accel(accel, straight(v), P)
    assert 0.0 <= th <= 1.0 and 0.0 <= br <= 1.0
    assert th == 0.0 or br == 0.0


@settings(max_examples=100, deadline=None)
@given(
    x=st.floats(-1e4, 1e4),
    y=st.floats(-1e4, 1e4),
    yaw=st.floats(-math.pi, math.pi),
    v=st.floats(0.0, 50.0),
)
def test_front_bumper_round_trip(x, y, yaw, v):
    s = state_from_front_bumper(x, y, yaw, v, P)
    assert front_bumper(s, P) == pytest.approx((x, y), abs=1e-9)
    assert speed(s) == pytest.approx(v)
    # initial state runs straight at constant speed under the feed-forward pedals
    th, br = pedals_from_accel(0.0, s, P)
    s2 = step(s, 0.0, th, br, P, DT)
    assert s2.vx == pytest.approx(v, abs=1e-9)
    assert s2.yaw == yaw
