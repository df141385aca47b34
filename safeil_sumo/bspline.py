"""The paper's trajectory parametrisation: a clamped cubic B-spline — pure numpy, the reference.

Knots ``[0, 0, 0, 0, 1, 1, 1, 1]`` give n = 8 - 3 - 1 = 4 basis functions, which on [0, 1] are the
cubic Bernstein polynomials. The first control point is the origin of the ego frame (the plan starts
where the vehicle is), so a plan is the three remaining control points ``(3, 2)`` [m]. Time along
the horizon ``T_h`` [s] maps to the spline parameter ``tau = t / T_h``.
"""

from __future__ import annotations

import numpy as np

KNOTS = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0])
DEGREE = 3
N_COEFFS = 4
# Greville abscissae of the four coefficients (mean of the 3 interior knots of each basis
# function): 0, 1/3, 2/3, 1 -> time of control point i is i * T_h / 3.
GREVILLE = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])


def basis(tau: np.ndarray, derivative: int = 0) -> np.ndarray:
    """Basis functions (or their ``derivative``-th derivative wrt tau) at ``tau (M,)`` -> ``(M, 4)``."""
    t = np.clip(np.asarray(tau, dtype=float), 0.0, 1.0)
    u = 1.0 - t
    if derivative == 0:
        cols = [u**3, 3 * t * u**2, 3 * t**2 * u, t**3]
    elif derivative == 1:
        cols = [-3 * u**2, 3 * u**2 - 6 * t * u, 6 * t * u - 3 * t**2, 3 * t**2]
    elif derivative == 2:
        cols = [6 * u, -12 * u + 6 * t, 6 * u - 12 * t, 6 * t]
    elif derivative == 3:
        ones = np.ones_like(t)
        cols = [-6 * ones, 18 * ones, -18 * ones, 6 * ones]
    else:
        return np.zeros(t.shape + (4,))
    return np.stack(cols, axis=-1)


def full_coefficients(control_points: np.ndarray) -> np.ndarray:
    """Prepend the fixed origin: ``(..., 3, 2)`` -> ``(..., 4, 2)``."""
    cp = np.asarray(control_points, dtype=float)
    zero = np.zeros(cp.shape[:-2] + (1, cp.shape[-1]))
    return np.concatenate([zero, cp], axis=-2)


def evaluate(
    control_points: np.ndarray, tau: np.ndarray, derivative: int = 0
) -> np.ndarray:
    """Spline points ``(..., M, 2)`` at ``tau (M,)`` for plans ``(..., 3, 2)`` (origin implied).

    With ``derivative=k`` the k-th derivative wrt tau; divide by ``T_h**k`` for time derivatives.
    """
    return basis(tau, derivative) @ full_coefficients(control_points)


def evaluate_time(
    control_points: np.ndarray, t: np.ndarray, horizon: float, derivative: int = 0
) -> np.ndarray:
    """Like :func:`evaluate` with time ``t`` [s] and derivatives wrt time (m/s, m/s^2)."""
    return evaluate(control_points, np.asarray(t) / horizon, derivative) / horizon**derivative


def control_point_times(horizon: float) -> np.ndarray:
    """Times ``(3,)`` [s] of the three free control points: ``i * T_h / 3``, i = 1..3."""
    return GREVILLE[1:] * horizon


def fit_control_points(points: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Least-squares control points ``(..., 3, 2)`` for samples ``(..., M, 2)`` at ``tau (M,)``.

    The first coefficient is fixed at the origin, so the fit solves only for the other three;
    ``points`` must be expressed in the frame where the trajectory starts at (0, 0).
    """
    a = basis(tau)[:, 1:]  # (M, 3): origin column drops out since its coefficient is 0
    pinv = np.linalg.pinv(a)  # (3, M)
    return pinv @ np.asarray(points, dtype=float)
