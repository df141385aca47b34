"""The numpy B-spline reference against scipy, its fit, the convex-hull property, and torch == numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.interpolate import BSpline
from scipy.optimize import linprog

from safeil_sumo import bspline
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
    # feasibility LP: lambda >= 0, sum lambda = 1, |coeffs^T lambda - p| <= tol (round-off)
    tol = 1e-9 * (1.0 + np.abs(coeffs).max())
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
