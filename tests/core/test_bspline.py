"""The numpy B-spline reference against scipy, its fit, the convex-hull property, and torch == numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.interpolate import BSpline
from scipy.optimize import linprog

from safeil_sumo.core import bspline
from safeil_sumo.learn import spline as tspline

TAU = np.linspace(0.0, 1.0, 41)
CP = np.array([[8.0, 0.3], [17.0, 0.2], [26.0, -0.4]])


@pytest.mark.parametrize("derivative", [0, 1, 2, 3])
def test_basis_matches_scipy(derivative: int) -> None:
    ref = BSpline(bspline.KNOTS, np.eye(4), bspline.DEGREE)(TAU, nu=derivative)
    np.testing.assert_allclose(bspline.basis(TAU, derivative), ref, atol=1e-12)


@pytest.mark.parametrize("derivative", [0, 1, 2])
def test_evaluate_matches_scipy(derivative: int) -> None:
    spl = BSpline(bspline.KNOTS, bspline.full_coefficients(CP), bspline.DEGREE)
    np.testing.assert_allclose(
        bspline.evaluate(CP, TAU, derivative), spl(TAU, nu=derivative), atol=1e-10
    )


def test_evaluate_time_scales_derivatives() -> None:
    horizon = 5.0
    t = TAU * horizon
    spl = BSpline(bspline.KNOTS * horizon, bspline.full_coefficients(CP), bspline.DEGREE)
    for k in (0, 1, 2):
        np.testing.assert_allclose(bspline.evaluate_time(CP, t, horizon, k), spl(t, nu=k),
                                   atol=1e-10)
    np.testing.assert_allclose(bspline.evaluate_time(CP, t, horizon), spl(t), atol=1e-10)


def test_plan_starts_at_origin_and_ends_at_last_control_point() -> None:
    pts = bspline.evaluate(CP, np.array([0.0, 1.0]))
    np.testing.assert_allclose(pts, [[0.0, 0.0], CP[-1]], atol=1e-15)


def test_fit_reproduces_a_known_cubic_trajectory_exactly() -> None:
    # A cubic polynomial through the origin, sampled at 20 times over a 5 s horizon.
    horizon = 5.0
    t = np.arange(1, 21) / 4.0
    x = 25.0 * t + 0.4 * t**2 - 0.03 * t**3
    y = 0.02 * t - 0.01 * t**2 + 0.002 * t**3
    pts = np.stack([x, y], axis=-1)
    cp = bspline.fit_control_points(pts, t / horizon)
    np.testing.assert_allclose(bspline.evaluate(cp, t / horizon), pts, atol=1e-9)
    # and the fit of a spline's own samples returns its control points; batched too
    batch = np.stack([CP, 2 * CP])
    fitted = bspline.fit_control_points(bspline.evaluate(batch, TAU[1:]), TAU[1:])
    np.testing.assert_allclose(fitted, batch, atol=1e-9)


def test_greville_times() -> None:
    knots = bspline.KNOTS
    greville = np.array([knots[j + 1 : j + 4].mean() for j in range(4)])
    np.testing.assert_allclose(bspline.GREVILLE, greville)
    np.testing.assert_allclose(bspline.control_point_times(6.0), [2.0, 4.0, 6.0])


finite = st.floats(-200.0, 200.0, allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None)
@given(cp=arrays(np.float64, (3, 2), elements=finite), tau=st.floats(0.0, 1.0))
def test_every_spline_point_lies_in_the_convex_hull(cp: np.ndarray, tau: float) -> None:
    coeffs = bspline.full_coefficients(cp)  # (4, 2): origin + 3 control points
    p = bspline.evaluate(cp, np.array([tau]))[0]
    # feasibility LP: lambda >= 0, sum lambda = 1, |coeffs^T lambda - p| <= tol; tol is the LP
    # solver's own feasibility scale (HiGHS: 1e-7; scipy 1.11's HiGHS called a point 1e-9 outside
    # a near-degenerate hull infeasible), far below any real departure from the hull
    tol = 1e-7 * (1.0 + np.abs(coeffs).max())
    a_ub = np.vstack([coeffs.T, -coeffs.T])
    b_ub = np.concatenate([p + tol, -p + tol])
    res = linprog(np.zeros(4), A_ub=a_ub, b_ub=b_ub, A_eq=np.ones((1, 4)), b_eq=[1.0],
                  bounds=[(0, None)] * 4)
    assert res.status == 0, (cp, tau, p)
    b = bspline.basis(np.array([tau]))[0]
    assert np.all(b >= 0) and b.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("derivative", [0, 1, 2, 3])
def test_torch_basis_and_evaluate_equal_numpy(derivative: int) -> None:
    tau_t = torch.as_tensor(TAU)
    np.testing.assert_allclose(
        tspline.basis(tau_t, derivative).numpy(), bspline.basis(TAU, derivative), atol=1e-12
    )
    batch = np.stack([CP, -CP, 0.5 * CP])
    np.testing.assert_allclose(
        tspline.evaluate(torch.as_tensor(batch), tau_t, derivative).numpy(),
        bspline.evaluate(batch, TAU, derivative), atol=1e-10,
    )


def test_torch_evaluate_is_differentiable() -> None:
    cp = torch.as_tensor(CP).requires_grad_(True)
    tspline.evaluate(cp, torch.as_tensor(TAU)).sum().backward()
    # d(sum of points)/d(cp_j) = sum over tau of basis j
    expected = bspline.basis(TAU)[:, 1:].sum(axis=0)
    np.testing.assert_allclose(cp.grad.numpy(), np.stack([expected, expected], axis=-1))


# ---------------------------------------------------------------- exact Bernstein lateral margins

lines = st.tuples(st.floats(-5.0, 5.0), st.floats(-0.1, 0.1), st.floats(-0.005, 0.005))


def _direct_margin(cp: np.ndarray, line: tuple, offset: float, tau: np.ndarray) -> np.ndarray:
    p = bspline.evaluate(cp, tau)
    x, y = p[:, 0], p[:, 1]
    return line[0] + line[1] * x + line[2] * x * x + offset - y


def test_elevation_and_product_constants() -> None:
    e = bspline.ELEVATE_3_TO_6
    assert e.shape == (7, 4) and np.allclose(e.sum(axis=1), 1.0)
    # B3 evaluated directly == the elevated combination of B6
    np.testing.assert_allclose(bspline.bernstein_basis(TAU, 6) @ e, bspline.basis(TAU), atol=1e-14)
    w = bspline.PRODUCT_WEIGHTS
    b3, b6 = bspline.basis(TAU), bspline.bernstein_basis(TAU, 6)
    for i in range(4):
        for j in range(4):
            np.testing.assert_allclose(b3[:, i] * b3[:, j], w[i + j, i, j] * b6[:, i + j],
                                       atol=1e-14)


@settings(max_examples=300, deadline=None)
@given(cp=arrays(np.float64, (3, 2), elements=st.floats(-300.0, 300.0)), line=lines,
       offset=st.floats(-3.0, 3.0), tau=arrays(np.float64, (5,), elements=st.floats(0.0, 1.0)))
def test_bernstein_margin_is_exact_and_a_lower_bound(cp, line, offset, tau) -> None:
    coeffs = bspline.lateral_margin_bernstein(cp, np.array(line), offset)
    assert coeffs.shape == (7,)
    direct = _direct_margin(cp, line, offset, tau)
    scale = 1.0 + abs(line[2]) * np.abs(cp[:, 0]).max() ** 2 + np.abs(cp).max()
    np.testing.assert_allclose(bspline.bernstein_basis(tau, 6) @ coeffs, direct,
                               atol=1e-9 * scale)
    # end points are coefficients 0 and 6; the minimum coefficient bounds every sample from below
    ends = _direct_margin(cp, line, offset, np.array([0.0, 1.0]))
    np.testing.assert_allclose(coeffs[[0, 6]], ends, atol=1e-9 * scale)
    sampled = _direct_margin(cp, line, offset, np.linspace(0.0, 1.0, 201))
    assert coeffs.min() <= sampled.min() + 1e-9 * scale


def test_bernstein_margin_batched_and_torch_equal_numpy() -> None:
    rng = np.random.default_rng(3)
    cp = rng.uniform(-50, 200, size=(6, 3, 2))
    line = rng.uniform([-3, -0.05, -0.003], [3, 0.05, 0.003], size=(6, 3))
    offset = rng.uniform(-1, 1, size=6)
    ref = bspline.lateral_margin_bernstein(cp, line, offset)
    assert ref.shape == (6, 7)
    for n in range(6):
        np.testing.assert_allclose(
            ref[n], bspline.lateral_margin_bernstein(cp[n], line[n], offset[n]), rtol=1e-13)
    got = tspline.lateral_margin_bernstein(torch.as_tensor(cp), torch.as_tensor(line),
                                           torch.as_tensor(offset))
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-12, atol=1e-10)


def test_bernstein_condition_on_a_straight_lane_is_implied_by_the_control_points() -> None:
    """c2 = 0: the margin is a cubic, its elevated coefficients are convex combinations of the
    control-point margins, so the Bernstein condition is never stricter than the paper's."""
    rng = np.random.default_rng(4)
    cp = rng.uniform([0, -3], [150, 3], size=(2000, 3, 2))
    line = np.array([1.0, 0.01, 0.0])
    coeffs = bspline.lateral_margin_bernstein(cp, line, -0.5)
    at_cp = line[0] + line[1] * cp[..., 0] - 0.5 - cp[..., 1]
    cp_ok = at_cp.min(axis=-1) >= 0
    assert np.all(coeffs[cp_ok, 1:].min(axis=-1) >= -1e-12)
    assert np.sum(coeffs[:, 1:].min(axis=-1) >= 0) > np.sum(cp_ok)  # strictly less conservative


# ------------------------------------- cases found by mutation testing (docs/mutation_testing.md)


def test_basis_clips_tau_takes_scalars_and_vanishes_beyond_degree() -> None:
    # outside [0, 1] the plan holds its ends (tau is clipped), for positions and derivatives
    np.testing.assert_array_equal(bspline.basis(np.array([-0.5, 1.5])), bspline.basis([0.0, 1.0]))
    np.testing.assert_array_equal(bspline.basis(np.array([1.2]), 1), bspline.basis([1.0], 1))
    assert bspline.basis(0.5).shape == (4,)
    np.testing.assert_allclose(bspline.basis(0.5), [0.125, 0.375, 0.375, 0.125])
    np.testing.assert_array_equal(bspline.basis(TAU, 4), np.zeros((len(TAU), 4)))
    line = np.array([1.5, 0.01, 0.002])
    np.testing.assert_array_equal(bspline.lateral_margin_bernstein(CP, line),
                                  bspline.lateral_margin_bernstein(CP, line, 0.0))


# ------------------------------------------------ lane_following_y: a lateral plan that follows the lane

KEEP = 0.93  # [m] half a 1.76 m track plus 0.05 m


def _lines(width: float, offset: float, heading: float, kappa: float) -> np.ndarray:
    """Concentric-enough lines of a lane ``width`` wide, the ego ``offset`` left of its centre."""
    return np.array([width / 2 - offset, heading, kappa / 2, -width / 2 - offset, heading,
                     kappa / 2])


def test_lane_following_y_by_hand() -> None:
    x = np.array([10.0, 20.0, 30.0])
    # centred on a straight lane, no offset asked: straight ahead
    assert np.allclose(bspline.lane_following_y(_lines(3.5, 0.0, 0.0, 0.0), x, np.zeros(3), KEEP),
                       0.0, atol=1e-12)
    # 0.25 m right of the centre: the control points on the centre line (y = +0.25)
    assert np.allclose(bspline.lane_following_y(_lines(3.5, -0.25, 0.0, 0.0), x, np.zeros(3),
                                                KEEP), 0.25)
    # a huge z saturates at the free half width: 1.75 - 0.93 = 0.82 m left of the centre
    assert np.allclose(bspline.lane_following_y(_lines(3.5, 0.0, 0.0, 0.0), x,
                                                np.full(3, 40.0), KEEP), 0.82)
    # a lane narrower than the track leaves no room: the centre
    assert np.allclose(bspline.lane_following_y(_lines(1.6, 0.0, 0.0, 0.0), x,
                                                np.full(3, 40.0), KEEP), 0.0)
    # a heading error: the centre's slope times x
    assert np.allclose(bspline.lane_following_y(_lines(3.5, 0.0, 0.02, 0.0), x, np.zeros(3),
                                                KEEP), 0.02 * x)


def test_lane_following_y_follows_a_bend_exactly_at_constant_speed() -> None:
    # x(tau) = L tau (control points L/3, 2L/3, L): the centre (kappa/2) L^2 tau^2 is a cubic
    # with control points (kappa/2) L^2 [0, 1/3, 1]; the control points on the centre line
    # itself ((kappa/2) x_i^2 = [1/9, 4/9, 1]) would cut the bend inwards
    length, kappa = 150.0, 1.0 / 250.0
    x = length * np.array([1.0, 2.0, 3.0]) / 3.0
    y = bspline.lane_following_y(_lines(3.5, 0.0, 0.0, kappa), x, np.zeros(3), KEEP)
    assert np.allclose(y, kappa / 2 * length**2 * np.array([0.0, 1.0 / 3.0, 1.0]), atol=1e-9)
    tau = np.linspace(0.0, 1.0, 11)
    plan = bspline.evaluate(np.stack([x, y], axis=-1), tau)
    assert np.allclose(plan[:, 1], kappa / 2 * plan[:, 0] ** 2, atol=1e-9)


def test_lane_following_y_torch_equals_numpy() -> None:
    rng = np.random.default_rng(3)
    lines = np.stack([_lines(w, o, h, k) for w, o, h, k in zip(
        rng.uniform(3.0, 4.0, 50), rng.uniform(-1, 1, 50), rng.uniform(-0.1, 0.1, 50),
        rng.uniform(-0.03, 0.03, 50), strict=True)])
    x = np.sort(rng.uniform(0, 150, (50, 3)), axis=1)
    z = rng.normal(size=(50, 3)) * 3
    want = bspline.lane_following_y(lines, x, z, KEEP)
    got = tspline.lane_following_y(torch.as_tensor(lines), torch.as_tensor(x), torch.as_tensor(z),
                                   KEEP)
    assert np.allclose(got.numpy(), want, atol=1e-10)


@settings(max_examples=300, deadline=None)
@given(width=st.floats(3.3, 3.8), offset=st.floats(-0.6, 0.6), heading=st.floats(-0.03, 0.03),
       kappa=st.floats(-1.0 / 250.0, 1.0 / 250.0), speed=st.floats(0.0, 40.0),
       accel=st.floats(-9.0, 3.0), shake=arrays(np.float64, 3, elements=st.floats(-10.0, 10.0)),
       z=arrays(np.float64, 3, elements=st.floats(-50.0, 50.0)))
def test_lane_following_plan_stays_in_the_lane_whatever_the_network_says(
        width, offset, heading, kappa, speed, accel, shake, z) -> None:
    # every output z of the network, on the certification envelope's lanes and x control points
    # of a plan that accelerates or brakes (to a stop) over 5 s, shaken by up to 10 m: wherever
    # the lane has room for the centre fit's residual, every Bernstein coefficient of both
    # margins keeps half the track and the clearance's share inside the lines (and so the
    # whole spline), exactly
    t = np.array([1.0, 2.0, 3.0]) * 5.0 / 3.0
    stop = speed / -accel if accel < 0 else np.inf
    tt = np.minimum(t, stop)
    x = speed * tt + 0.5 * accel * tt * tt + shake
    assume(width / 2 - KEEP - abs(kappa) / 2 * bspline.lane_fit_allowance(x) >= 0.0)
    lines = _lines(width, offset, heading, kappa)
    plan = np.stack([x, bspline.lane_following_y(lines, x, z, KEEP)], axis=-1)
    left = bspline.lateral_margin_bernstein(plan, lines[0:3], -0.88)
    right = -bspline.lateral_margin_bernstein(plan, lines[3:6], 0.88)
    # margin coefficient k >= E_k0 (the start's margin) + (1 - E_k0) (keep - T/2)
    share = bspline.ELEVATE_3_TO_6[:, 0]
    assert np.all(left >= share * (lines[0] - 0.88) + (1.0 - share) * (KEEP - 0.88) - 1e-9)
    assert np.all(right >= share * (-lines[3] - 0.88) + (1.0 - share) * (KEEP - 0.88) - 1e-9)
    points = bspline.evaluate(plan, np.linspace(0.0, 1.0, 401))
    px, py = points[:, 0], points[:, 1]
    assert np.all(lines[0] + lines[1] * px + lines[2] * px**2 - 0.88 - py >= -1e-9)
    assert np.all(py - (lines[3] + lines[4] * px + lines[5] * px**2) - 0.88 >= -1e-9)


def test_lane_fit_allowance_by_hand() -> None:
    # constant speed: x(tau)^2 is a quadratic, fitted exactly, nothing to allow for
    assert bspline.lane_fit_allowance(np.array([25.0, 50.0, 75.0])) == pytest.approx(0.0, abs=1e-9)
    # homogeneous of degree 2 in x, and the largest weighted |R_k|
    x = np.array([35.0, 55.0, 60.0])
    r = np.einsum("kab,a,b->k", bspline.LANE_FIT_RESIDUAL, x, x)
    assert r[0] == pytest.approx(0.0, abs=1e-9)
    assert bspline.lane_fit_allowance(x) == pytest.approx(
        np.max(np.abs(r[1:]) * bspline.LANE_FIT_WEIGHT))
    assert bspline.lane_fit_allowance(2.0 * x) == pytest.approx(4.0 * bspline.lane_fit_allowance(x))
    # 1 / (1 - E_k0): the cubic's first control point enters coefficient k with E_k0 = 1/2, 1/5,
    # 1/20, 0, 0, 0
    np.testing.assert_allclose(bspline.LANE_FIT_WEIGHT, [2.0, 1.25, 20.0 / 19.0, 1.0, 1.0, 1.0])


def test_a_plan_braking_on_a_bend_keeps_the_fits_residual_off_the_offsets_room() -> None:
    # braking at 6 m/s^2 from 30 m/s on the envelope's tightest bend (250 m): the fitted centre
    # misses the true one (its Bernstein coefficients by up to 0.32 m), so the offsets' room
    # shrinks by exactly that allowance (0.82 m on a straight lane)
    t = np.array([1.0, 2.0, 3.0]) * 5.0 / 3.0
    x = 30.0 * t - 3.0 * t * t
    allowance = bspline.lane_fit_allowance(x) / 500.0
    assert allowance == pytest.approx(0.317, abs=0.001)
    y_max = bspline.lane_following_y(_lines(3.5, 0.0, 0.0, 1.0 / 250.0), x, np.full(3, 60.0), KEEP)
    y_centre = bspline.lane_following_y(_lines(3.5, 0.0, 0.0, 1.0 / 250.0), x, np.zeros(3), KEEP)
    np.testing.assert_allclose(y_max - y_centre, 0.82 - allowance, atol=1e-9)
