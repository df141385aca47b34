"""The population prior of ``replay --adapt-first-s``: its spreads, and how well it predicts.

    python training/time_gap_prior.py

1. The spreads of :class:`safeil_sumo.learn.style.TimeGapPrior`, measured on the shipped
   ``safeil``'s real training maneuvers (NGSIM I-80 and OpenACC Vicolungo, its held-out
   maneuvers left out): the sd of log time gap between maneuvers, and per maneuver the sd of
   log(gap / speed) over its following samples and their integral correlation time (to the
   first zero crossing of the autocorrelation); medians over the maneuvers.
2. Without SUMO, how well a driver's first S seconds predict the time gap they keep after the
   first minute (:func:`safeil_sumo.learn.style.estimate_time_gap` of the rest), on the OpenACC
   maneuvers and the unseen ZalaZone ones of at least 80 s: mean |setting - later time gap| [s]
   for the default setting, the plain median of the first S seconds, and the shrunk estimate
   (:func:`safeil_sumo.learn.style.adapted_time_gap`). The closed-loop answer, in SUMO, is
   ``training/adaptation_bound.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "safeil_sumo" / "models" / "safeil.safetensors"
SEEN_S = (2.0, 5.0, 10.0, 20.0, 30.0, 45.0, 60.0)  # [s] first seconds seen
LATER_S = 60.0  # [s] the later time gap is the one kept after this
MIN_REST_S = 20.0  # [s] a maneuver needs this long after LATER_S


def source_rows(source: str) -> pd.DataFrame:
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source

    return process_drive(load_source(source), PipelineConfig(rate_hz=10.0))[0]


def correlation_time_s(x: np.ndarray, dt_s: float) -> float:
    """Integral correlation time [s] of ``x`` (samples ``dt_s`` apart): the sum of its
    autocorrelation up to the first negative lag, times ``2 dt_s`` (both sides)."""
    x = np.asarray(x, float) - np.mean(x)
    ac = np.correlate(x, x, "full")[len(x) - 1:] / (x.var() * len(x))
    first_negative = int(np.argmax(ac < 0)) if (ac < 0).any() else len(ac)
    return float(ac[:first_negative].sum() * 2.0 * dt_s)


def spreads(rows: pd.DataFrame, min_samples: int = 100) -> dict[str, float]:
    """The prior's spreads over the maneuvers of ``rows`` (10 Hz): see the module doc."""
    from safeil_sumo.learn.style import following_time_gaps

    between, within, corr = [], [], []
    for _, g in rows.groupby("maneuver_id", sort=False):
        tg = following_time_gaps(g["lead_x"].to_numpy(float), g["v_x"].to_numpy(float))
        if len(tg):
            between.append(float(np.log(np.median(tg))))  # log of estimate_time_gap
        x = np.log(tg)
        if len(x) >= min_samples:
            within.append(float(np.std(x)))
            corr.append(correlation_time_s(x, 0.1))
    return {"maneuvers": len(between), "between_log_sd": float(np.std(between)),
            "within_log_sd": float(np.median(within)), "correlation_s": float(np.median(corr))}


def scored_maneuvers(rows: pd.DataFrame):
    """Each maneuver of ``rows`` with ``MIN_REST_S`` after ``LATER_S`` and a time gap kept
    after ``LATER_S``: ``(its rows, t [s] from its start, that later time gap [s])``."""
    from safeil_sumo.learn.style import estimate_time_gap

    for _, g in rows.groupby("maneuver_id", sort=False):
        t = g["time"].to_numpy(float) - g["time"].iloc[0]
        gap, v = g["lead_x"].to_numpy(float), g["v_x"].to_numpy(float)
        later = estimate_time_gap(gap[t >= LATER_S], v[t >= LATER_S])
        if t[-1] >= LATER_S + MIN_REST_S and np.isfinite(later):
            yield g, t, later


def prediction_errors(rows: pd.DataFrame, default_s: float) -> pd.DataFrame:
    """Mean |setting - later time gap| [s] per estimator (rows) and first seconds seen
    (columns) over the maneuvers of ``rows`` long enough (module doc, part 2)."""
    from safeil_sumo.learn.style import (
        TimeGapPrior,
        adapted_time_gap,
        clip_time_gap,
        estimate_time_gap,
    )

    out = []
    for g, t, later in scored_maneuvers(rows):
        gap, v = g["lead_x"].to_numpy(float), g["v_x"].to_numpy(float)
        for seen in SEEN_S:
            first = t < seen
            plain = estimate_time_gap(gap[first], v[first])
            shrunk = adapted_time_gap(gap[first], v[first], 0.1, TimeGapPrior(default_s))
            for name, s in (("default", default_s),
                            ("plain median", plain if np.isfinite(plain) else default_s),
                            ("shrunk", shrunk)):
                out.append({"estimator": name, "seen_s": seen,
                            "error_s": abs(clip_time_gap(s) - later)})
    table = pd.DataFrame(out)
    return table.pivot_table(index="estimator", columns="seen_s", values="error_s")


def main() -> int:
    from safeil_sumo.learn.checkpoint import held_out_maneuvers
    from safeil_sumo.planners import registry as planner_registry

    held = set(held_out_maneuvers(SHIPPED))
    rows = {s: source_rows(s) for s in ("ngsim", "openacc", "zalazone")}
    training = pd.concat([rows[s] for s in ("ngsim", "openacc")], ignore_index=True)
    training = training[~training["maneuver_id"].isin(held)]
    print("TimeGapPrior spreads on the shipped safeil's training maneuvers:", spreads(training))
    default_s = planner_registry.load(str(SHIPPED)).style["time_gap_s"]
    for source in ("openacc", "zalazone"):
        table = prediction_errors(rows[source], default_s)
        n = rows[source].groupby("maneuver_id")["time"].agg(lambda t: t.iloc[-1] - t.iloc[0])
        print(f"\n{source} ({int((n >= LATER_S + MIN_REST_S).sum())} maneuvers of at least "
              f"{LATER_S + MIN_REST_S:g} s): mean |setting - time gap kept after "
              f"{LATER_S:g} s| [s], by first seconds seen")
        print(table.round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
