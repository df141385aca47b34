"""A driver's style as a planner input: the preferred time gap, and the standstill distance.

Drivers differ most in the time gap they keep (about 1-3 s), and ACC products expose it as the
distance setting. A planner that cannot be told the preference cannot be close to every driver,
so a style-conditioned planner takes one more input after the paper's 9 features:
``time_gap_s``, the driver's preferred time gap [s].

- in training it is estimated per maneuver from the data (:func:`estimate_time_gap`);
- in use it is a setting (``run``/``sweep --time-gap-s``, default the humans' median stored in the
  checkpoint; clipped at ISO 15622's 0.8 s floor);
- in replay it is estimated from the first seconds of the recording only
  (``replay --adapt-first-s``), which are then left out of the score.

One number cannot say how a driver's gap grows with speed, so a style is two: the steady gap's
line ``gap = s0 + T v`` (standstill distance s0 [m], time gap T [s]; estimated as the driver is
watched by :mod:`safeil_sumo.learn.style_estimator`). The network keeps its one input and is
given, at each plan, the setting that puts its steady gap ``setting * v`` on the line at the
ego's speed (:func:`scheduled_time_gap`, ``T + s0 / v`` inside :data:`SETTING_RANGE_S`): it
only ever sees settings it was trained on, and the certificate's style range (0.6-3.5 s)
covers every (s0, T) at every speed.

The barrier and the envelope keep the plan safe at every setting: envelope states are drawn
with styles across :data:`TIME_GAP_RANGE_S`.

numpy only, so a styled planner loads without torch; the torch terms that train the style
(``equilibrium_states``, ``equilibrium_residual``) are in :mod:`safeil_sumo.learn.closed_loop`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

STYLE_NAMES = ("time_gap_s",)
TIME_GAP_RANGE_S = (0.6, 3.5)  # [s] styles drawn for the envelope states
# [s] the settings a user (or an adapted replay) may choose: ISO 15622 asks an ACC's smallest
# selectable steady-state time gap to be at least 0.8 s
SETTING_RANGE_S = (0.8, 3.5)
MIN_SPEED_MPS = 5.0  # [m/s] slower samples say more about standstill distance than time gap
MAX_TIME_GAP_S = 6.0  # [s] a sample farther back is not following
STANDSTILL_GAP_M = 2.0  # [m] the equilibrium gap's floor at low speed
# the second style number (scheduled_time_gap): a driver's standstill distance s0 [m], the
# intercept of the steady gap's line s0 + T v
STANDSTILL_NAME = "standstill_m"
STANDSTILL_RANGE_M = (-30.0, 30.0)  # [m] the s0 a planner accepts (the population's +-4 sd)
SCHEDULE_MIN_SPEED_MPS = 1.0  # [m/s] s0 / v is taken at this speed below it


def following_time_gaps(gap_m: np.ndarray, speed_mps: np.ndarray,
                        min_speed_mps: float = MIN_SPEED_MPS) -> np.ndarray:
    """``gap / speed`` [s] of the following samples (speed above ``min_speed_mps``, time gap
    below :data:`MAX_TIME_GAP_S`), in order."""
    gap, v = np.asarray(gap_m, float), np.asarray(speed_mps, float)
    ok = np.isfinite(gap) & np.isfinite(v) & (v > min_speed_mps)
    tg = gap[ok] / v[ok]
    return tg[tg < MAX_TIME_GAP_S]


def estimate_time_gap(gap_m: np.ndarray, speed_mps: np.ndarray,
                      min_speed_mps: float = MIN_SPEED_MPS) -> float:
    """The preferred time gap [s]: the median of :func:`following_time_gaps`; NaN when there is
    none."""
    tg = following_time_gaps(gap_m, speed_mps, min_speed_mps)
    return float(np.median(tg)) if len(tg) else float("nan")


@dataclass(frozen=True)
class TimeGapPrior:
    """What is known of a driver's preferred time gap before any of their driving is seen: a
    log-normal population. The spreads were measured on the shipped ``safeil``'s 144 real
    training maneuvers (NGSIM I-80 and OpenACC Vicolungo, 10 Hz rows, following samples as in
    :func:`estimate_time_gap`; medians over the maneuvers)."""

    median_s: float  # [s] the population's median: a styled planner's default setting
    between_log_sd: float = 0.34  # [-] sd of log(time gap) between maneuvers (drivers)
    # [-] sd of log(gap / speed) over one maneuver's following samples (NGSIM 0.20, OpenACC 0.24)
    within_log_sd: float = 0.205
    # [s] how long a driver's time-gap deviation persists: the integral correlation time (to
    # its first zero crossing) of log(gap / speed) in a maneuver (NGSIM 6.2 s, OpenACC 22 s)
    correlation_s: float = 6.5

    def weight(self, seen_s: float) -> float:
        """The weight [0, 1) of the driver's own median after ``seen_s`` [s] of following
        samples: the normal-normal posterior's, with ``1 + seen_s / correlation_s``
        independent observations (the first sample is one, however short)."""
        if seen_s <= 0:
            return 0.0
        data = (1.0 + seen_s / self.correlation_s) / self.within_log_sd ** 2
        return data / (data + 1.0 / self.between_log_sd ** 2)


def adapted_time_gap(gap_m: np.ndarray, speed_mps: np.ndarray, dt_s: float,
                     prior: TimeGapPrior) -> float:
    """A driver's preferred time gap [s] from their first samples (``dt_s`` [s] apart), shrunk
    towards the population (empirical Bayes in log time gap): ``prior.median_s`` moved towards
    the samples' :func:`estimate_time_gap` by :meth:`TimeGapPrior.weight` of the seconds of
    following seen. Without a following sample, the prior's median.

    Why not the samples' median alone: the first seconds of a drive are few and often not
    steady (a queue pulling away keeps gaps that say more about standstill distance than time
    gap). Measured (``docs/human_likeness.md``, ``training/time_gap_prior.py``): predicting
    the time gap a driver keeps after the first minute from their first 2-10 s, the plain
    median erred more than no adaptation on ZalaZone; shrunk, it errs less than the plain
    median at every look up to 45 s on OpenACC and ZalaZone, and as much after a minute."""
    tg = following_time_gaps(gap_m, speed_mps)
    if len(tg) == 0:
        return float(prior.median_s)
    w = prior.weight(len(tg) * dt_s)
    return float(np.exp((1.0 - w) * np.log(prior.median_s) + w * np.log(np.median(tg))))


def maneuver_time_gaps(gap_m: np.ndarray, speed_mps: np.ndarray, maneuver_id: np.ndarray,
                       fallback_s: float) -> np.ndarray:
    """Per sample ``(N,)``: its maneuver's :func:`estimate_time_gap` (``fallback_s`` where a
    maneuver has no following sample, e.g. a queue below the minimum speed)."""
    ids = np.asarray(maneuver_id)
    out = np.full(len(ids), float(fallback_s))
    uniq, inverse = np.unique(ids, return_inverse=True)
    for k in range(len(uniq)):
        rows = inverse == k
        tg = estimate_time_gap(np.asarray(gap_m)[rows], np.asarray(speed_mps)[rows])
        if np.isfinite(tg):
            out[rows] = tg
    return out


def training_time_gaps(gap_m: np.ndarray, speed_mps: np.ndarray, maneuver_id: np.ndarray,
                       training_maneuvers: Iterable[str]) -> dict[str, float]:
    """Per training maneuver (its id in ``training_maneuvers``) that has following samples: its
    :func:`estimate_time_gap` [s], in order of first appearance. These are the style estimates
    a style-conditioned planner is trained with (``training/closed_loop_finetune.py --style``);
    its default setting is their median."""
    ids = np.asarray(maneuver_id)
    tg = maneuver_time_gaps(gap_m, speed_mps, ids, fallback_s=np.nan)
    rows = np.isin(ids, list(training_maneuvers)) & np.isfinite(tg)
    return dict(zip(ids[rows], tg[rows], strict=True))


def clip_time_gap(time_gap_s: float) -> float:
    """A setting inside :data:`SETTING_RANGE_S` (within the trained range)."""
    lo, hi = SETTING_RANGE_S
    return float(min(max(float(time_gap_s), lo), hi))


def scheduled_time_gap(time_gap_s: float, standstill_m: float,
                       speed_mps: float | np.ndarray) -> np.ndarray:
    """The time-gap setting [s] that makes a planner whose steady gap is ``setting * v`` keep a
    driver's line ``gap = standstill_m + time_gap_s * v`` instead: ``T + s0 / v`` at the ego's
    speed ``speed_mps`` [m/s] (a float or an array ``(N,)``; below
    :data:`SCHEDULE_MIN_SPEED_MPS` that speed), inside :data:`SETTING_RANGE_S`. A second style
    number without retraining: the network's input stays the one it was trained and certified
    on, so the setting it is given is always inside the certified range."""
    lo, hi = SETTING_RANGE_S
    v = np.maximum(speed_mps, SCHEDULE_MIN_SPEED_MPS)
    return np.clip(time_gap_s + standstill_m / v, lo, hi)
