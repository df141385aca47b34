"""Human-likeness metrics: a closed-loop run against the recorded human — pure functions, no I/O.

Two kinds of comparison (paper Fig. "Human-like Performance Validation"):
- time series at the recorded timestamps (x, y, along-lane s, lateral offset d, v_x, d_lead):
  RMSE and max absolute error over the samples both sides have;
- distributions of time headway, speed and lateral offset over the maneuver: Wasserstein-1
  distance (in the quantity's unit) and the two-sample Kolmogorov-Smirnov statistic (0..1).

And the car-following literature's spacing RMSPE (:func:`rmspe`, as the FollowNet benchmark, Sci
Data 2023, reports it beside the spacing RMSE) and the mean signed error (:func:`mean_error`: a
time gap kept longer or shorter than the human's on average).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

MIN_HEADWAY_SPEED = 0.5  # [m/s] below, time headway gap/v is not defined (standstill)


@dataclass(frozen=True)
class SeriesError:
    """Error of a time series against the human's: RMSE, max |error| (unit of the series), and
    how many samples were compared (``n``) out of ``n_total`` (the run may end early)."""

    rmse: float
    max_abs: float
    n: int
    n_total: int


@dataclass(frozen=True)
class DistributionDistance:
    """Wasserstein-1 distance (unit of the quantity) and KS statistic [-] of two samples."""

    wasserstein: float
    ks: float
    n_human: int
    n_policy: int


def series_error(human: np.ndarray, policy: np.ndarray) -> SeriesError:
    """RMSE and max |policy - human| over the samples ``(N,)`` where both are finite."""
    h = np.asarray(human, dtype=float)
    p = np.asarray(policy, dtype=float)
    if h.shape != p.shape:
        raise ValueError(f"series must have the same shape, got {h.shape} and {p.shape}")
    ok = np.isfinite(h) & np.isfinite(p)
    n = int(ok.sum())
    if n == 0:
        return SeriesError(math.nan, math.nan, 0, int(h.size))
    err = p[ok] - h[ok]
    return SeriesError(float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err))), n,
                       int(h.size))


def _finite_pairs(human: np.ndarray, policy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples ``(N,)`` where both series are finite."""
    h = np.asarray(human, dtype=float)
    p = np.asarray(policy, dtype=float)
    if h.shape != p.shape:
        raise ValueError(f"series must have the same shape, got {h.shape} and {p.shape}")
    ok = np.isfinite(h) & np.isfinite(p)
    return h[ok], p[ok]


def rmspe(human: np.ndarray, policy: np.ndarray) -> float:
    """Root mean square percentage error ``sqrt(mean(((policy - human) / human)^2))`` as a
    fraction (0.1 = 10 %), over the samples ``(N,)`` where both are finite and ``human > 0`` (a
    gap of 0 has no relative error); NaN when there is none. Large where the human's gap is
    small: a 1 m error on a 2 m gap weighs as much as 25 m on 50 m."""
    h, p = _finite_pairs(human, policy)
    ok = h > 0
    if not ok.any():
        return math.nan
    return float(np.sqrt(np.mean(((p[ok] - h[ok]) / h[ok]) ** 2)))


def mean_error(human: np.ndarray, policy: np.ndarray) -> float:
    """Mean signed error ``mean(policy - human)`` over the samples ``(N,)`` where both are
    finite (positive: the policy's values are larger); NaN when there is none."""
    h, p = _finite_pairs(human, policy)
    return float(np.mean(p - h)) if len(h) else math.nan


def distribution_distance(human: np.ndarray, policy: np.ndarray) -> DistributionDistance:
    """Wasserstein-1 and KS statistic between the finite values of two samples."""
    h = np.asarray(human, dtype=float).ravel()
    p = np.asarray(policy, dtype=float).ravel()
    h, p = h[np.isfinite(h)], p[np.isfinite(p)]
    if len(h) == 0 or len(p) == 0:
        return DistributionDistance(math.nan, math.nan, len(h), len(p))
    return DistributionDistance(
        float(stats.wasserstein_distance(h, p)),
        float(stats.ks_2samp(h, p, method="asymp").statistic),  # the statistic is method-free
        len(h), len(p),
    )


def time_headway(gap_m: np.ndarray, speed_mps: np.ndarray,
                 min_speed_mps: float = MIN_HEADWAY_SPEED) -> np.ndarray:
    """Bumper-to-bumper time headway [s] ``gap / v``; NaN where ``v < min_speed_mps``."""
    g = np.asarray(gap_m, dtype=float)
    v = np.asarray(speed_mps, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(v >= min_speed_mps, g / v, np.nan)


def sample_at(t_query: np.ndarray, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values (N,)`` at ``t_query (M,)``; NaN outside ``[t0, tN]`` and
    where a neighbouring sample is NaN (a run that ended early has no value after its end)."""
    tq = np.asarray(t_query, dtype=float)
    t = np.asarray(t, dtype=float)
    v = np.asarray(values, dtype=float)
    if len(t) == 0:
        return np.full(tq.shape, np.nan)
    out = np.interp(tq, t, v)
    # NaN propagates through np.interp only for the exact neighbours; mark them explicitly
    i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 1)
    j = np.clip(i + 1, 0, len(t) - 1)
    between = tq > t[i] + 1e-12  # an exact hit of a sample needs only that sample
    bad = ~np.isfinite(v[i]) | (between & ~np.isfinite(v[j])) | (tq < t[0] - 1e-9) \
        | (tq > t[-1] + 1e-9)
    return np.where(bad, np.nan, out)


def leader_drift(t: np.ndarray, lead_gap_m: np.ndarray, ego_s_m: np.ndarray,
                 lead_speed_mps: np.ndarray) -> np.ndarray:
    """How far a leader driven by the recorded speed drifts from the recorded leader [m], ``(N,)``.

    The replay drives the leader by its speed profile from the recorded initial gap; its position
    is ``gap0 + s0 + integral(v_lead)`` (trapezoid), the recorded one is ``gap(t) + s(t)``. A
    large drift means the recorded speed and gap disagree (sensor error), which shows in the
    d_lead comparison and is not the policy's doing.
    """
    t = np.asarray(t, dtype=float)
    v = np.asarray(lead_speed_mps, dtype=float)
    gap = np.asarray(lead_gap_m, dtype=float)
    s = np.asarray(ego_s_m, dtype=float)
    travelled = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    return (gap[0] + s[0] + travelled) - (gap + s)
