"""Open-loop evaluation of a planner on held-out tuples: accuracy and constraint margins.

Accuracy: control-point RMSE vs the fitted targets, ADE/FDE of the planned spline vs the
demonstrated future at its sample times (``tau = t_k / T_h``), and the same ADE/FDE of the target
control points (the spline's own fitting error: a floor for any planner).
Safety: margins (>= 0 safe, see :mod:`safeil_sumo.planners.safety_filter`) of every plan at its control
points (``_cp``) and at points sampled along the spline (``_spline``), per constraint (``left``,
``right``, ``lead``): the worst margin over all plans, the mean of each plan's worst margin, and
the fraction of plans violating. ``hull_gap_rate`` is the fraction of plans whose control points
are safe while some spline point is not — where the convex-hull argument fails (curves).
``_bern``: the same stats of the lane margins' exact degree-6 Bernstein coefficients k = 1..6
(:func:`safeil_sumo.planners.safety_filter.bernstein_margins`; k = 0 is the car itself, skipped as the
origin is skipped everywhere else): a lower bound of the margin along the whole spline, exact on
curves. ``target_violation_rate_{lateral,any}_{cp,bern,spline}``: the fraction of DEMONSTRATED
targets that each formulation rejects (``lateral`` = left or right line; ``any`` adds the leader at
the control points, which is already exact); on curves the paper's control-point formulation
rejects human plans whose spline stays inside the lane, the Bernstein one does not.
"""

from __future__ import annotations

import numpy as np

from safeil_sumo.core import bspline
from safeil_sumo.core.policy import Policy
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.planners.safety_filter import (
    DEFAULT_SAFE_SET,
    SafeSet,
    bernstein_margins,
    plan_margins,
)

CONSTRAINTS = ("left", "right", "lead")
LATERAL = ("left", "right")


def _margin_stats(
    margins: dict[str, np.ndarray], where: str, constraints: tuple[str, ...] = CONSTRAINTS
) -> tuple[dict[str, float], np.ndarray]:
    """Stats of margins ``(N, M)`` per constraint; also the per-plan "all safe" mask ``(N,)``."""
    out: dict[str, float] = {}
    safe = np.ones(next(iter(margins.values())).shape[0], dtype=bool)
    for c in constraints:
        worst = margins[c].min(axis=-1)  # (N,)
        safe &= worst >= 0
        out[f"min_margin_{c}_{where}"] = float(worst.min())
        out[f"mean_min_margin_{c}_{where}"] = float(worst.mean())
        out[f"violation_rate_{c}_{where}"] = float(np.mean(worst < 0))
    out[f"violation_rate_any_{where}"] = float(np.mean(~safe))
    return out, safe


def plan_metrics(
    features: np.ndarray,
    plans: np.ndarray,
    targets: np.ndarray,
    future: np.ndarray,
    future_times: np.ndarray,
    horizon: float,
    safe_set: SafeSet = DEFAULT_SAFE_SET,
    n_samples: int = 50,
) -> dict[str, float]:
    """Metrics of plans ``(N, 3, 2)`` vs targets ``(N, 3, 2)`` and futures ``(N, H, 2)`` at
    ``future_times (H,)`` [s]; features ``(N, 9)``. Future samples beyond the horizon are dropped."""
    plans = np.asarray(plans, dtype=float)
    keep = np.asarray(future_times) <= horizon + 1e-9
    tau_f = np.asarray(future_times)[keep] / horizon
    future = np.asarray(future, dtype=float)[:, keep]
    err = plans - targets
    out: dict[str, float] = {
        "n": float(len(plans)),
        "cp_rmse": float(np.sqrt(np.mean(err**2))),
        "cp_rmse_x": float(np.sqrt(np.mean(err[..., 0] ** 2))),
        "cp_rmse_y": float(np.sqrt(np.mean(err[..., 1] ** 2))),
    }
    for prefix, cps in (("", plans), ("target_fit_", targets)):
        d = np.linalg.norm(bspline.evaluate(cps, tau_f) - future, axis=-1)  # (N, H)
        out[f"{prefix}ade"] = float(d.mean())
        out[f"{prefix}fde"] = float(d[:, -1].mean())
    out["ade_lateral"] = float(
        np.abs(bspline.evaluate(plans, tau_f)[..., 1] - future[..., 1]).mean()
    )
    tau_s = np.arange(1, n_samples + 1) / n_samples
    cp_stats, cp_safe = _margin_stats(plan_margins(features, plans, horizon, safe_set), "cp")
    sp_stats, sp_safe = _margin_stats(
        plan_margins(features, plans, horizon, safe_set, tau_s), "spline"
    )
    out.update(cp_stats)
    out.update(sp_stats)
    out["hull_gap_rate"] = float(np.mean(cp_safe & ~sp_safe))
    bern = {k: v[..., 1:] for k, v in bernstein_margins(features, plans, safe_set).items()}
    bern_stats, _ = _margin_stats(bern, "bern", LATERAL)
    out.update({k: v for k, v in bern_stats.items() if k != "violation_rate_any_bern"})
    out["violation_rate_lateral_bern"] = bern_stats["violation_rate_any_bern"]
    out.update(_target_violation_rates(features, targets, horizon, safe_set, tau_s))
    return out


def _target_violation_rates(
    features: np.ndarray, targets: np.ndarray, horizon: float, safe_set: SafeSet, tau: np.ndarray
) -> dict[str, float]:
    """Fraction of target plans ``(N, 3, 2)`` rejected by each formulation (see module doc)."""
    cp = plan_margins(features, targets, horizon, safe_set)
    spline = plan_margins(features, targets, horizon, safe_set, tau)
    bern = {k: v[..., 1:] for k, v in bernstein_margins(features, targets, safe_set).items()}
    lead_ok = cp["lead"].min(axis=-1) >= 0  # exact already (linear in tau)
    out = {}
    for where, m in (("cp", cp), ("bern", bern), ("spline", spline)):
        lateral_ok = (m["left"].min(axis=-1) >= 0) & (m["right"].min(axis=-1) >= 0)
        out[f"target_violation_rate_lateral_{where}"] = float(np.mean(~lateral_ok))
        out[f"target_violation_rate_any_{where}"] = float(np.mean(~(lateral_ok & lead_ok)))
    return out


def open_loop_metrics(
    policy: Policy, tuples: Tuples, safe_set: SafeSet = DEFAULT_SAFE_SET, n_samples: int = 50
) -> dict[str, float]:
    """:func:`plan_metrics` of ``policy`` on ``tuples`` (a flat dict of floats)."""
    if len(tuples) == 0:
        raise ValueError("no tuples to evaluate")
    if not np.isclose(policy.horizon, tuples.horizon):
        raise ValueError(f"policy horizon {policy.horizon} != data horizon {tuples.horizon}")
    return plan_metrics(
        tuples.features, policy.plan(tuples.features), tuples.control_points, tuples.future,
        tuples.future_times, tuples.horizon, safe_set, n_samples,
    )
