"""A driver's style as a planner input: the preferred time gap.

Drivers differ most in the time gap they keep (about 1-3 s), and ACC products expose it as the
distance setting. A planner that cannot be told the preference cannot be close to every driver,
so a style-conditioned planner takes one more input after the paper's 9 features:
``time_gap_s``, the driver's preferred time gap [s].

- in training it is estimated per maneuver from the data (:func:`estimate_time_gap`);
- in use it is a setting (``run``/``sweep --time-gap``, default the humans' median stored in the
  checkpoint);
- in replay it is estimated from the first seconds of the recording only
  (``replay --adapt-first-s``), which are then left out of the score.

The barrier and the envelope keep the plan safe at every setting: envelope states are drawn
with styles across :data:`TIME_GAP_RANGE_S`.
"""

from __future__ import annotations

import numpy as np

STYLE_NAMES = ("time_gap_s",)
TIME_GAP_RANGE_S = (0.6, 3.5)  # [s] styles drawn for the envelope states; settings are clipped
MIN_SPEED_MPS = 5.0  # [m/s] slower samples say more about standstill distance than time gap
MAX_TIME_GAP_S = 6.0  # [s] a sample farther back is not following


def estimate_time_gap(gap_m: np.ndarray, speed_mps: np.ndarray,
                      min_speed_mps: float = MIN_SPEED_MPS) -> float:
    """The preferred time gap [s]: the median of ``gap / speed`` over following samples (speed
    above ``min_speed_mps``, time gap below :data:`MAX_TIME_GAP_S`); NaN when there is none."""
    gap, v = np.asarray(gap_m, float), np.asarray(speed_mps, float)
    ok = np.isfinite(gap) & np.isfinite(v) & (v > min_speed_mps)
    tg = gap[ok] / v[ok]
    tg = tg[tg < MAX_TIME_GAP_S]
    return float(np.median(tg)) if len(tg) else float("nan")


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


def clip_time_gap(time_gap_s: float) -> float:
    """A setting inside the trained range :data:`TIME_GAP_RANGE_S`."""
    lo, hi = TIME_GAP_RANGE_S
    return float(min(max(float(time_gap_s), lo), hi))
