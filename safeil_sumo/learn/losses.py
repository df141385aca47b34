"""Training losses with named terms: imitation (MSE) + the paper's softplus barrier (Sec. IV-B).

With margins ``m >= 0`` meaning "safe" (ego frame, x forward, y left, [m]):

- left line:  ``m_l = (c0l + c1l x + c2l x^2 - T/2) - y``
- right line: ``m_r = y - (c0r + c1r x + c2r x^2 + T/2)``
- leader:     ``m_d = d_lead + v_lead t - x  [- (gap_min + time_gap v_x)]``

the barrier is ``K sum_i softplus(-m)`` over the three control points (times ``t_i = i T_h / 3``),
exactly the paper's ``K sum sigma(alpha_yi - (...))`` etc. The bracketed leader margin and the
extra points sampled along the spline are options beyond the paper, OFF by default.

``BarrierConfig(lateral="bernstein")`` (beyond the paper) replaces the lane terms at the control
points by ``K sum_k softplus(-b_k)`` over the exact degree-6 Bernstein coefficients ``b_k`` of the
margin along the spline (:func:`safeil_sumo.core.bspline.lateral_margin_bernstein`), k = 1..6: all
``b_k >= 0`` keeps the whole trajectory inside, on curves too, where the control points of a
lane-following plan sit outside the lane centre. k = 0 is the margin at the plan's origin (the car
itself): it does not depend on the plan, so it is skipped, as the paper skips the origin. The leader
term needs no such change: ``d_lead + v_lead t`` is linear in tau, so its control-point margins
already are its exact Bernstein coefficients.
``d_lead`` is bumper to bumper from the ego's front bumper, which is the plan origin, so
``x < d_lead(t)`` means "behind the leader's rear".

Imitation: the paper's ``||alpha - alpha*||_2^2`` in metres, i.e. the squared error summed over
the 6 outputs, averaged over the batch (not divided by 6: that would change its weight vs K).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from safeil_sumo.core.bspline import GREVILLE
from safeil_sumo.learn import spline

# Column indices of the features (safeil_sumo.core.features.FEATURE_NAMES).
C0L, C1L, C2L, C0R, C1R, C2R, V_X, V_LEAD, D_LEAD = range(9)
LATERAL_MODES = ("control_points", "bernstein")


@dataclass(frozen=True)
class BarrierConfig:
    """Barrier settings. Defaults are the paper's (K = 1000, control points only, no margin).

    k: weight K [-]; track: vehicle track / width T [m];
    gap_min: extra leader gap [m]; time_gap: extra leader gap per ego speed [s];
    n_samples: also constrain this many points at ``tau = j / n_samples, j = 1..n`` on the spline;
    control_points: constrain the control points (the paper). On curves the control points of a
    lane-following plan sit ~``c2 X^2 / 9`` [m] outside the lane centre (X = plan length), so
    ``control_points=False, n_samples>0`` constrains the trajectory itself instead;
    lateral: "control_points" (the paper: lane terms at the control points, if ``control_points``)
    or "bernstein" (lane terms on the 6 exact Bernstein coefficients of the margin along the
    spline, whatever ``control_points`` says, which then applies to the leader term only).
    """

    k: float = 1000.0
    track: float = 1.76
    gap_min: float = 0.0
    time_gap: float = 0.0
    n_samples: int = 0
    control_points: bool = True
    lateral: str = "control_points"

    def __post_init__(self) -> None:
        if self.lateral not in LATERAL_MODES:
            raise ValueError(f"lateral must be one of {LATERAL_MODES}, got {self.lateral!r}")
        if not self.control_points and self.n_samples <= 0:
            raise ValueError("the barrier needs control points or n_samples > 0")


@dataclass(frozen=True)
class LossTerms:
    """Scalar loss terms (batch means); ``total`` is what is minimised."""

    imitation: torch.Tensor
    barrier_left: torch.Tensor
    barrier_right: torch.Tensor
    barrier_lead: torch.Tensor
    total: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        return {name: float(getattr(self, name).detach()) for name in self.__dataclass_fields__}


def _poly(features: torch.Tensor, c0: int, x: torch.Tensor) -> torch.Tensor:
    """Lane line ``c0 + c1 x + c2 x^2`` [m] at ``x (N, M)`` for the line starting at column c0."""
    c = features[:, c0 : c0 + 3, None]
    return c[:, 0] + c[:, 1] * x + c[:, 2] * x * x


def lane_margins(
    features: torch.Tensor, points: torch.Tensor, track: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Left and right margins ``(N, M)`` [m] of ``points (N, M, 2)``; >= 0 is inside the lane."""
    x, y = points[..., 0], points[..., 1]
    left = _poly(features, C0L, x) - 0.5 * track - y
    right = y - (_poly(features, C0R, x) + 0.5 * track)
    return left, right


def bernstein_lane_margins(
    features: torch.Tensor, control_points: torch.Tensor, track: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Left and right margins' exact degree-6 Bernstein coefficients ``(N, 7)`` [m] along plans
    ``(N, 3, 2)``; all >= 0 means the whole spline is inside (k = 0 is the plan's origin)."""
    left = spline.lateral_margin_bernstein(control_points, features[:, C0L : C0L + 3], -0.5 * track)
    right = -spline.lateral_margin_bernstein(control_points, features[:, C0R : C0R + 3], 0.5 * track)
    return left, right


def lead_margins(
    features: torch.Tensor,
    points: torch.Tensor,
    times: torch.Tensor,
    gap_min: float = 0.0,
    time_gap: float = 0.0,
) -> torch.Tensor:
    """Leader margin ``(N, M)`` [m] of ``points (N, M, 2)`` at ``times (M,)`` [s], constant-speed leader."""
    d_lead = features[:, D_LEAD, None] + features[:, V_LEAD, None] * times
    margin = d_lead - points[..., 0]
    if gap_min or time_gap:
        margin = margin - (gap_min + time_gap * features[:, V_X, None])
    return margin


def constrained_points(
    control_points: torch.Tensor, horizon: float, n_samples: int = 0, include_control: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Points ``(N, M, 2)`` the barrier acts on and their times ``(M,)`` [s]: the 3 control points
    (if ``include_control``) then ``n_samples`` spline points at ``tau = j / n_samples``."""
    points, times = [], []
    if include_control:
        points.append(control_points)
        times.append(torch.as_tensor(GREVILLE[1:] * horizon, dtype=control_points.dtype))
    if n_samples > 0:
        tau = torch.arange(1, n_samples + 1, dtype=control_points.dtype) / n_samples
        points.append(spline.evaluate(control_points, tau))
        times.append(tau * horizon)
    if len(points) == 1:
        return points[0], times[0]
    return torch.cat(points, dim=1), torch.cat(times)


def barrier_terms(
    features: torch.Tensor, control_points: torch.Tensor, horizon: float, cfg: BarrierConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batch means of the left, right and leader barriers for ``features (N, 9)``, plans ``(N, 3, 2)``."""
    points, times = constrained_points(
        control_points, horizon, cfg.n_samples, cfg.control_points
    )
    left, right = lane_margins(features, points, cfg.track)
    lead = lead_margins(features, points, times, cfg.gap_min, cfg.time_gap)
    if cfg.lateral == "bernstein":
        left_b, right_b = bernstein_lane_margins(features, control_points, cfg.track)
        # the sampled spline points (if any) follow the 3 control points in ``points``
        first = 3 if cfg.control_points else 0
        left = torch.cat([left_b[:, 1:], left[:, first:]], dim=1)
        right = torch.cat([right_b[:, 1:], right[:, first:]], dim=1)
    # F.softplus is ln(1 + e^z), switching to z itself for z > 20 (same value in float32).
    return tuple(cfg.k * F.softplus(-m).sum(dim=1).mean() for m in (left, right, lead))


def envelope_barrier_terms(
    features: torch.Tensor, control_points: torch.Tensor, horizon: float, cfg: BarrierConfig,
    brake_mps2: float = 6.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`barrier_terms` for states drawn across the envelope (no demonstrations).

    The leader margin ``gap_min + time_gap v_x`` is required only where braking at
    ``brake_mps2`` can still reach it (``gap - margin > closing^2 / (2 brake)``); closer states
    keep the paper's zero margin. Otherwise infeasible margins (a cut-in at 10 m, 30 m/s) would
    dominate the loss with a barrier no plan can satisfy and bend the network everywhere.
    """
    zero_margin = BarrierConfig(k=cfg.k, track=cfg.track, n_samples=cfg.n_samples,
                                control_points=cfg.control_points, lateral=cfg.lateral)
    left, right, lead = barrier_terms(features, control_points, horizon, zero_margin)
    if not (cfg.gap_min or cfg.time_gap):
        return left, right, lead
    v, v_lead, gap = features[:, V_X], features[:, V_LEAD], features[:, D_LEAD]
    margin = cfg.gap_min + cfg.time_gap * v
    closing = torch.clamp(v - v_lead, min=0.0)
    feasible = (gap - margin > closing * closing / (2.0 * brake_mps2)).to(features.dtype)
    points, times = constrained_points(control_points, horizon, cfg.n_samples, cfg.control_points)
    m = lead_margins(features, points, times) - (feasible * margin)[:, None]
    return left, right, cfg.k * F.softplus(-m).sum(dim=1).mean()


def imitation_loss(
    pred: torch.Tensor, target: torch.Tensor, axis_weight: torch.Tensor | None = None
) -> torch.Tensor:
    """``||pred - target||^2`` summed over the 6 outputs, mean over the batch ``(N, 3, 2)``.

    ``axis_weight (N, 2)`` scales the x and y errors per sample (0 for y: a source whose lateral
    positions do not match its lane features, e.g. OpenACC, teaches only the longitudinal plan;
    0 for x: a source that teaches only lane keeping).
    """
    err = (pred - target).square()
    if axis_weight is None:
        return err.sum(dim=(-2, -1)).mean()
    return (err.sum(dim=-2) * axis_weight).sum(dim=-1).mean()


def safe_loss(
    features: torch.Tensor,
    pred: torch.Tensor,
    target: torch.Tensor,
    horizon: float,
    barrier: BarrierConfig = BarrierConfig(),
    apply_barrier: bool = True,
    axis_weight: torch.Tensor | None = None,
) -> LossTerms:
    """SafeIL loss ``imitation + barriers``; ``apply_barrier=False`` is behavioural cloning.

    For BC the barrier terms are still computed and returned for logging (same config, so BC and
    SafeIL runs are comparable term by term), but detached and not added to ``total``.
    """
    imitation = imitation_loss(pred, target, axis_weight)
    if not apply_barrier:
        with torch.no_grad():
            left, right, lead = barrier_terms(features, pred, horizon, barrier)
        return LossTerms(imitation, left, right, lead, imitation)
    left, right, lead = barrier_terms(features, pred, horizon, barrier)
    return LossTerms(imitation, left, right, lead, imitation + left + right + lead)
