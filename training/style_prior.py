"""The population prior of the (s0, T) style estimator, and its forgetting time constant.

    python training/style_prior.py

1. On the shipped ``safeil``'s real training maneuvers (NGSIM I-80 and OpenACC Vicolungo, 10 Hz,
   its held-out maneuvers left out), each maneuver's steady-following samples
   (:func:`safeil_sumo.learn.style_estimator.steady_following`, at least ``MIN_SAMPLES``) give a
   least-squares line ``gap = s0 + T v`` and its estimation covariance ``V_i`` (the OLS
   covariance, inflated by the residuals' correlation time over the sample spacing). The
   population mean and covariance of (s0, T) are the random-effects maximum-likelihood fit
   ``theta_i_hat ~ N(mu, Sigma + V_i)``: a maneuver whose speeds span little has a wild
   intercept (OpenACC: s0 of -50 m) and so little weight. Also: the residuals' relative sd and
   correlation time (medians over the maneuvers): the observation noise of
   :class:`~safeil_sumo.learn.style_estimator.StylePrior`.
2. The forgetting time constant: each training maneuver filtered with every ``TAUS_S``; the
   estimate ``HORIZON_S`` seconds before each steady sample predicts its gap (``s0 + T v`` at the
   sample's speed). Mean absolute error per tau, on the training maneuvers and (unseen, for
   information) on ZalaZone.
3. Which setting a planner with a time-gap input only should get from a driver's first S
   seconds (as ``training/time_gap_prior.py`` part 2, without SUMO): mean |setting - the time
   gap kept after the first minute| [s] on OpenACC and ZalaZone maneuvers of at least 80 s, for
   the default, today's shrunk median (``style.adapted_time_gap``), the estimator's T alone, and
   its line's time gap at the mean speed seen (``StyleEstimate.setting_s``).

Prints the numbers the defaults of ``StylePrior`` were set from.
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import minimize

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "training"))
from time_gap_prior import (  # a sibling script: its data, helpers and targets
    LATER_S,
    SHIPPED,
    correlation_time_s,
    scored_maneuvers,
    source_rows,
)

MIN_SAMPLES = 50  # [-] steady samples (5 s at 10 Hz) a maneuver needs for a line
DT_S = 0.1  # [s] the rows' spacing
TAUS_S = (math.inf, 3600.0, 1200.0, 600.0, 300.0, 120.0, 60.0)
HORIZON_S = 30.0  # [s] how far ahead the estimate predicts


def maneuver_lines(rows: pd.DataFrame) -> pd.DataFrame:
    """Per maneuver with enough steady samples: OLS (s0, T), their covariance ``V_i``, the
    residuals' relative sd and correlation time."""
    from safeil_sumo.learn.style_estimator import acceleration_mps2, steady_following

    out = []
    for mid, g in rows.groupby("maneuver_id", sort=False):
        t, v, gap = (g[c].to_numpy(float) for c in ("time", "v_x", "lead_x"))
        ok = steady_following(gap, v, g["v_lead"].to_numpy(float), acceleration_mps2(t, v))
        if ok.sum() < MIN_SAMPLES or np.ptp(v[ok]) <= 0:
            continue
        x = np.column_stack([np.ones(ok.sum()), v[ok]])
        theta, *_ = np.linalg.lstsq(x, gap[ok], rcond=None)
        fitted = x @ theta
        res = gap[ok] - fitted
        tau = min(max(correlation_time_s(res, DT_S), DT_S), ok.sum() * DT_S)
        cov = res.var() * np.linalg.inv(x.T @ x) * (tau / DT_S)
        out.append({"maneuver_id": mid, "n": int(ok.sum()), "s0": theta[0], "T": theta[1],
                    "v00": cov[0, 0], "v01": cov[0, 1], "v11": cov[1, 1],
                    "rel_sd": float(np.std(res / np.maximum(fitted, 0.5))), "tau_s": tau})
    return pd.DataFrame(out)


def random_effects(lines: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """ML ``(mu (2,), Sigma (2, 2))`` of ``theta_i_hat ~ N(mu, Sigma + V_i)``."""
    th = lines[["s0", "T"]].to_numpy(float)
    vs = np.stack([[[r.v00, r.v01], [r.v01, r.v11]] for r in lines.itertuples()])

    def unpack(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        chol = np.array([[math.exp(p[2]), 0.0], [p[3], math.exp(p[4])]])
        return p[:2], chol @ chol.T

    def nll(p: np.ndarray) -> float:
        mu, sigma = unpack(p)
        c = sigma + vs
        d = th - mu
        inv = np.linalg.inv(c)
        return float(0.5 * (np.log(np.linalg.det(c)) + np.einsum("ni,nij,nj->n", d, inv, d)).sum())

    p0 = np.array([2.0, 1.5, math.log(2.0), 0.0, math.log(0.5)])
    res = minimize(nll, p0, method="Nelder-Mead", options={"maxiter": 20000, "xatol": 1e-6,
                                                           "fatol": 1e-9})
    return unpack(res.x)


def prediction_error(rows: pd.DataFrame, prior) -> float:
    """Mean |gap - (s0 + T v)| [m] over the steady samples, the estimate taken HORIZON_S s
    before each (module doc, part 2)."""
    from safeil_sumo.learn.style_estimator import estimate_drive

    errs = []
    lag = round(HORIZON_S / DT_S)
    for _, g in rows.groupby("maneuver_id", sort=False):
        t, v, gap = (g[c].to_numpy(float) for c in ("time", "v_x", "lead_x"))
        _, tr = estimate_drive(t, gap, v, g["v_lead"].to_numpy(float), prior)
        if len(t) <= lag:
            continue
        j = np.flatnonzero(tr.steady[lag:]) + lag
        errs.append(np.abs(gap[j] - (tr.s0_m[j - lag] + tr.time_gap_s[j - lag] * v[j])))
    return float(np.mean(np.concatenate(errs)))


SEEN_S = (2.0, 10.0, 30.0, 60.0)  # [s] first seconds seen (part 3)


def setting_errors(rows: pd.DataFrame, default_s: float, prior) -> pd.DataFrame:
    """Part 3 of the module doc: mean |setting - later time gap| [s] per way (rows) and first
    seconds seen (columns)."""
    from safeil_sumo.learn.style import TimeGapPrior, adapted_time_gap, clip_time_gap
    from safeil_sumo.learn.style_estimator import estimate_drive

    out = []
    for g, t, later in scored_maneuvers(rows):
        gap, v, vl = (g[c].to_numpy(float) for c in ("lead_x", "v_x", "v_lead"))
        for seen in SEEN_S:
            first = t < seen
            est, _ = estimate_drive(t[first], gap[first], v[first], vl[first], prior)
            ways = {"default": default_s,
                    "shrunk median (today)": adapted_time_gap(gap[first], v[first], DT_S,
                                                              TimeGapPrior(default_s)),
                    "estimator T": est.time_gap_s if est.samples else default_s,
                    "estimator s0/v+T at seen speed": est.setting_s(est.mean_speed_mps)
                    if est.samples else default_s}
            out += [{"way": k, "seen_s": seen, "error_s": abs(clip_time_gap(x) - later)}
                    for k, x in ways.items()]
    return pd.DataFrame(out).pivot_table(index="way", columns="seen_s", values="error_s")


def main() -> int:
    from safeil_sumo.learn.checkpoint import held_out_maneuvers
    from safeil_sumo.learn.style_estimator import StylePrior

    held = set(held_out_maneuvers(SHIPPED))
    rows = {s: source_rows(s) for s in ("ngsim", "openacc", "zalazone")}
    training = pd.concat([rows[s] for s in ("ngsim", "openacc")], ignore_index=True)
    training = training[~training["maneuver_id"].isin(held)]
    lines = maneuver_lines(training)
    mu, sigma = random_effects(lines)
    sd = np.sqrt(np.diag(sigma))
    print(f"{training['maneuver_id'].nunique()} training maneuvers, {len(lines)} with "
          f">= {MIN_SAMPLES} steady samples")
    print("per-maneuver OLS lines (raw spread):")
    print(lines[["n", "s0", "T", "rel_sd", "tau_s"]].describe().round(3).to_string())
    print(f"random effects: mean s0 {mu[0]:.3f} m, T {mu[1]:.3f} s; sd s0 {sd[0]:.3f} m, "
          f"T {sd[1]:.3f} s, corr {sigma[0, 1] / (sd[0] * sd[1]):.3f}")
    print(f"noise: relative sd median {lines['rel_sd'].median():.3f}, correlation time median "
          f"{lines['tau_s'].median():.2f} s")
    prior = StylePrior(s0_m=mu[0], time_gap_s=mu[1], sd_s0_m=sd[0], sd_time_gap_s=sd[1],
                       corr=sigma[0, 1] / (sd[0] * sd[1]),
                       noise_rel=float(lines["rel_sd"].median()),
                       correlation_s=float(lines["tau_s"].median()))
    print(f"\nmean |gap - predicted| [m] of steady samples, estimate {HORIZON_S:g} s before:")
    zz = rows["zalazone"]
    for tau in TAUS_S:
        p = replace(prior, forget_tau_s=tau)
        print(f"  tau {tau:>6g} s: training {prediction_error(training, p):.3f}  "
              f"zalazone {prediction_error(zz, p):.3f}")
    from safeil_sumo.planners import registry as planner_registry

    default_s = planner_registry.load(str(SHIPPED)).style["time_gap_s"]
    for source in ("openacc", "zalazone"):
        print(f"\n{source}: mean |setting - time gap kept after {LATER_S:g} s| [s], by first "
              "seconds seen")
        print(setting_errors(rows[source], default_s, prior).round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
