"""Torch version of the clamped cubic B-spline in :mod:`safeil_sumo.core.bspline` (the numpy reference).

Same conventions: knots ``[0, 0, 0, 0, 1, 1, 1, 1]``, the first coefficient is the ego-frame origin,
a plan is the three free control points ``(..., 3, 2)`` [m], ``tau = t / T_h``. Differentiable, so
the loss can constrain points sampled along the spline, not only the control points.
"""

from __future__ import annotations

import torch

from safeil_sumo.core.bspline import (
    ELEVATE_3_TO_6,
    LANE_FIT,
    LANE_FIT_RESIDUAL,
    LANE_FIT_WEIGHT,
    LANE_FREE,
    PRODUCT_WEIGHTS,
)


def basis(tau: torch.Tensor, derivative: int = 0) -> torch.Tensor:
    """Basis functions (or their ``derivative``-th derivative wrt tau) at ``tau (M,)`` -> ``(M, 4)``."""
    t = torch.clamp(torch.as_tensor(tau), 0.0, 1.0)
    u = 1.0 - t
    if derivative == 0:
        cols = [u**3, 3 * t * u**2, 3 * t**2 * u, t**3]
    elif derivative == 1:
        cols = [-3 * u**2, 3 * u**2 - 6 * t * u, 6 * t * u - 3 * t**2, 3 * t**2]
    elif derivative == 2:
        cols = [6 * u, -12 * u + 6 * t, 6 * u - 12 * t, 6 * t]
    elif derivative == 3:
        ones = torch.ones_like(t)
        cols = [-6 * ones, 18 * ones, -18 * ones, 6 * ones]
    else:
        return torch.zeros(t.shape + (4,), dtype=t.dtype)
    return torch.stack(cols, dim=-1)


def full_coefficients(control_points: torch.Tensor) -> torch.Tensor:
    """Prepend the fixed origin: ``(..., 3, 2)`` -> ``(..., 4, 2)``."""
    zero = control_points.new_zeros(control_points.shape[:-2] + (1, control_points.shape[-1]))
    return torch.cat([zero, control_points], dim=-2)


def evaluate(control_points: torch.Tensor, tau: torch.Tensor, derivative: int = 0) -> torch.Tensor:
    """Spline points ``(..., M, 2)`` at ``tau (M,)`` for plans ``(..., 3, 2)`` (origin implied)."""
    tau = torch.as_tensor(tau, dtype=control_points.dtype)
    return basis(tau, derivative) @ full_coefficients(control_points)


def lateral_margin_bernstein(
    control_points: torch.Tensor, line: torch.Tensor, offset: float | torch.Tensor = 0.0
) -> torch.Tensor:
    """Torch twin of :func:`safeil_sumo.core.bspline.lateral_margin_bernstein`: exact degree-6 Bernstein
    coefficients ``(..., 7)`` [m] of ``line(x(tau)) + offset - y(tau)`` for plans ``(..., 3, 2)``
    and lines ``(..., 3)`` = ``[c0, c1, c2]``. Left margin: ``offset = -T/2``; right margin: the
    negation with ``offset = +T/2``."""
    full = full_coefficients(control_points)  # (..., 4, 2)
    elevate = torch.as_tensor(ELEVATE_3_TO_6, dtype=full.dtype)
    weights = torch.as_tensor(PRODUCT_WEIGHTS, dtype=full.dtype)
    x, y = full[..., 0], full[..., 1]
    x6, y6 = x @ elevate.T, y @ elevate.T
    xx6 = torch.einsum("kij,...i,...j->...k", weights, x, x)
    c0 = line[..., 0, None] + torch.as_tensor(offset, dtype=full.dtype)[..., None]
    return c0 + line[..., 1, None] * x6 + line[..., 2, None] * xx6 - y6


def lane_following_y(lines: torch.Tensor, x: torch.Tensor, z: torch.Tensor,
                     keep_m: float) -> torch.Tensor:
    """Torch twin of :func:`safeil_sumo.core.bspline.lane_following_y`: y control points ``(..., 3)``
    [m] following the lane of ``lines (..., 6)``, offset from its centre by ``h_i tanh(z_i)``."""
    free = torch.as_tensor(LANE_FREE, dtype=x.dtype)
    fit = torch.as_tensor(LANE_FIT, dtype=x.dtype)
    residual = torch.as_tensor(LANE_FIT_RESIDUAL[1:], dtype=x.dtype)
    weight = torch.as_tensor(LANE_FIT_WEIGHT, dtype=x.dtype)
    centre = 0.5 * (lines[..., 0:3] + lines[..., 3:6])
    half = 0.5 * (lines[..., 0:3] - lines[..., 3:6])
    xs = x @ free.T
    s = (xs * xs) @ fit.T
    allowance = torch.amax(torch.einsum("kab,...a,...b->...k", residual, x, x).abs() * weight,
                           dim=-1)
    bend = torch.maximum(lines[..., 2].abs(), lines[..., 5].abs())
    room = (half[..., 0, None] + half[..., 1, None] * x + half[..., 2, None] * s - keep_m
            - (bend * allowance)[..., None])
    h = torch.clamp(room, min=0.0)
    return (centre[..., 0, None] + centre[..., 1, None] * x + centre[..., 2, None] * s
            + h * torch.tanh(z))
