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


# ------------------------------------------------ exact lateral margins in the degree-6 Bernstein basis
#
# Along a plan x(tau), y(tau) are cubic Bernstein polynomials (the B-spline above), so a lane-line
# margin ``c0 + c1 x + c2 x^2 + offset - y`` is a polynomial of degree 6 in tau. Written exactly in
# the degree-6 Bernstein basis, its 7 coefficients bound it from below on [0, 1] (convex hull of a
# Bernstein polynomial): all >= 0 => the WHOLE trajectory satisfies the constraint, curves included.


def _binom(n: int, k: int) -> float:
    from math import comb

    return float(comb(n, k)) if 0 <= k <= n else 0.0


# (7, 4): degree elevation 3 -> 6, ``B3_i = sum_k ELEVATE_3_TO_6[k, i] B6_k``,
# ``ELEVATE_3_TO_6[k, i] = C(3, i) C(3, k - i) / C(6, k)``; each row sums to 1.
ELEVATE_3_TO_6 = np.array(
    [[_binom(3, i) * _binom(3, k - i) / _binom(6, k) for i in range(4)] for k in range(7)]
)
# (7, 4, 4): Bernstein product rule, ``B3_i B3_j = PRODUCT_WEIGHTS[i + j, i, j] B6_{i+j}``, so the
# degree-6 coefficients of ``x(tau)^2`` are ``einsum("kij,i,j->k", PRODUCT_WEIGHTS, X, X)``.
PRODUCT_WEIGHTS = np.array(
    [
        [[_binom(3, i) * _binom(3, j) / _binom(6, k) if i + j == k else 0.0 for j in range(4)]
         for i in range(4)]
        for k in range(7)
    ]
)


def bernstein_basis(tau: np.ndarray, degree: int) -> np.ndarray:
    """Bernstein basis of ``degree`` at ``tau (M,)`` -> ``(M, degree + 1)`` (no clipping)."""
    t = np.asarray(tau, dtype=float)[..., None]
    k = np.arange(degree + 1)
    coef = np.array([_binom(degree, int(i)) for i in k])
    return coef * t**k * (1.0 - t) ** (degree - k)


def square_bernstein(coefficients: np.ndarray) -> np.ndarray:
    """Degree-6 Bernstein coefficients ``(..., 7)`` of the square of a cubic with ``(..., 4)``."""
    c = np.asarray(coefficients, dtype=float)
    return np.einsum("kij,...i,...j->...k", PRODUCT_WEIGHTS, c, c)


def lateral_margin_bernstein(
    control_points: np.ndarray, line: np.ndarray, offset: float | np.ndarray = 0.0
) -> np.ndarray:
    """Exact degree-6 Bernstein coefficients ``(..., 7)`` [m] of ``line(x(tau)) + offset - y(tau)``.

    control_points ``(..., 3, 2)`` [m] (origin implied); line ``(..., 3)`` = ``[c0, c1, c2]`` of
    ``c0 + c1 x + c2 x^2`` [m, -, 1/m]; offset [m], broadcast against ``(...)``.
    Left lane line: ``offset = -(T/2 + clearance)`` gives the left margin (>= 0 inside).
    Right lane line: the right margin ``y - (line_r(x) + T/2 + clearance)`` is the NEGATION of
    ``lateral_margin_bernstein(cp, line_r, +(T/2 + clearance))``.
    Coefficient 0 is the margin at tau = 0 (the plan's origin), coefficient 6 at tau = 1, and
    ``min_k coefficient_k <= min_{tau in [0, 1]} margin(tau)``.
    """
    full = full_coefficients(control_points)  # (..., 4, 2)
    line = np.asarray(line, dtype=float)
    x6 = full[..., 0] @ ELEVATE_3_TO_6.T  # (..., 7)
    y6 = full[..., 1] @ ELEVATE_3_TO_6.T
    xx6 = square_bernstein(full[..., 0])
    c0 = line[..., 0, None] + np.asarray(offset, dtype=float)[..., None]
    return c0 + line[..., 1, None] * x6 + line[..., 2, None] * xx6 - y6


# ------------------------------------------------ a lateral plan that follows the lane by construction
#
# ``lane_following_y`` builds the y control points from the x control points and the lane lines:
# the least-squares cubic (origin fixed, at ``LANE_FIT_TAU``) through the lane centre along the
# plan, plus an offset from the centre at each control point bounded by the lane's free half
# width. The centre's linear part is a cubic already (exact); its curvature part ``c2 x(tau)^2``
# (degree 6) is fitted, so on a bend the plan follows the centre instead of cutting it along the
# control points' chords. What that fit leaves (a plan that brakes hard on a bend: up to ~0.3 m
# at the envelope's tightest curvature) is taken off the offsets' room, so that every degree-6
# Bernstein coefficient of both lane margins, and by the convex hull the whole plan, stays inside
# the lane whatever the network outputs (``lane_fit_allowance``).

LANE_FIT_TAU = np.linspace(0.0, 1.0, 21)  # where the centre is fitted (the lateral refit's grid)
LANE_FREE = basis(LANE_FIT_TAU)[:, 1:]  # (21, 3): the origin's coefficient is 0
LANE_FIT = np.linalg.pinv(LANE_FREE)  # (3, 21)
# (7, 3, 3): R_k(x) = x^T LANE_FIT_RESIDUAL_k x, the degree-6 Bernstein coefficients of
# x(tau)^2 less those of its fitted cubic s(tau), for the free x control points (R_0 = 0)
LANE_FIT_RESIDUAL = PRODUCT_WEIGHTS[:, 1:, 1:] - np.einsum(
    "ki,im,ma,mb->kab", ELEVATE_3_TO_6[:, 1:], LANE_FIT, LANE_FREE, LANE_FREE)
# 1 / (1 - E_k0), k >= 1: the share of margin coefficient k that the offsets' room reaches
LANE_FIT_WEIGHT = 1.0 / (1.0 - ELEVATE_3_TO_6[1:, 0])


def lane_fit_allowance(x: np.ndarray) -> np.ndarray:
    """``max_k |R_k(x)| / (1 - E_k0)`` ``(...)`` [m^2] of x control points ``(..., 3)`` [m]:
    times the larger |c2| of the two lines, the room the centre fit's residual needs.

    Margin coefficient k of a lane head's plan is ``E_k0 (start margin) + sum_i E_ki (w_i/2 -
    h_i t_i) + c2 R_k - (1 - E_k0) T/2`` (``w_i/2``: the half width at ``x_i`` along the fitted
    centre, ``|t_i| < 1``): with ``h_i = w_i/2 - keep - |c2| A`` it is at least ``E_k0 (start
    margin) + (1 - E_k0) (keep - T/2)``, whatever the offsets."""
    r = np.einsum("kab,...a,...b->...k", LANE_FIT_RESIDUAL[1:], x, x)
    return np.max(np.abs(r) * LANE_FIT_WEIGHT, axis=-1)


def lane_following_y(lines: np.ndarray, x: np.ndarray, z: np.ndarray,
                     keep_m: float) -> np.ndarray:
    """y control points ``(..., 3)`` [m] of plans with x control points ``x (..., 3)`` [m] in the
    lane of ``lines (..., 6)`` (``c0l, c1l, c2l, c0r, c1r, c2r``), offset from its centre by
    ``h_i tanh(z_i)`` (``z (..., 3)``: the network's lateral outputs): ``h_i`` is the lane's
    half width at ``x_i`` less ``keep_m`` [m] (half the track plus a clearance) and less the
    centre fit's allowance (:func:`lane_fit_allowance`), floored at 0.

    ``y_i = cm0 + cm1 x_i + cm2 s_i + h_i tanh(z_i)``, ``cm`` the centre line (the mean of both
    lines), ``s`` the least-squares cubic of ``x(tau)^2`` at :data:`LANE_FIT_TAU`.
    """
    lines, x, z = (np.asarray(a, dtype=float) for a in (lines, x, z))
    centre = 0.5 * (lines[..., 0:3] + lines[..., 3:6])
    half = 0.5 * (lines[..., 0:3] - lines[..., 3:6])
    xs = x @ LANE_FREE.T  # (..., 21)
    s = (xs * xs) @ LANE_FIT.T
    bend = np.maximum(np.abs(lines[..., 2]), np.abs(lines[..., 5]))
    room = (half[..., 0, None] + half[..., 1, None] * x + half[..., 2, None] * s - keep_m
            - (bend * lane_fit_allowance(x))[..., None])
    h = np.maximum(room, 0.0)
    return (centre[..., 0, None] + centre[..., 1, None] * x + centre[..., 2, None] * s
            + h * np.tanh(z))
