"""N74 drives: seeded closed-loop drives of the planners on the n74 road among SUMO's traffic,
their flag rates per distance with exact Poisson intervals, their time gaps against the recorded
synthetic humans of the same road, and where their flags happened.

Pure functions (:func:`garwood_interval`, :func:`time_gaps`, :func:`flag_events`,
:func:`human_time_gaps`, :func:`compare_time_gaps`) do the maths on logs and tables; the sweep
(:func:`drive_tasks`, :func:`drive_task`) runs the drives with the sweep engine and keeps, per
drive, only the time-gap samples and the flag events of its per-step log. A population of
drivers (:func:`population_tasks`) drives the planners that have a time-gap setting at one
setting per drive, drawn from the real training maneuvers' preferred time gaps
(:func:`training_settings`, :func:`draw_settings`).

Definitions (the same for planners and humans):

- a *time gap* [s] is the bumper gap to the leader divided by the ego speed, sampled at
  :data:`TIME_GAP_RATE_HZ` (the synthetic drives' rate) while *following*: a leader within the
  radar range (:data:`FOLLOW_MAX_GAP_M`, the range in which the synthetic driver's radar
  reports one) and an ego faster than :data:`FOLLOW_MIN_SPEED_MPS`;
- a flag *event* is a run of consecutive flagged steps of one kind (TTC <= 1 s, lane
  departure, collision), located at the ego's front bumper on its first step
  (:func:`safeil_sumo.sim.runner.drive_stats` counts them the same way).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.experiments.sweep_executor import run_task
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.sim.loop_types import Rollout
from safeil_sumo.sim.monitors import event_starts

PLANNERS = ("safeil", "safeil_openloop", "bc", "analytic", "idm")
# Three stretches covering direction A (km posts of n74.json, 29.2 km), each driven with
# SEEDS_PER_STRETCH traffic seeds by every planner (the same seeds: common random numbers).
STRETCHES_KM = ((0.2, 9.9), (9.9, 19.6), (19.6, 29.0))
SEEDS_PER_STRETCH = 2
TRAFFIC = "default"
FLAG_KINDS = (("ttc", "ttc_flag", "TTC <= 1 s"),
              ("lane_departure", "lane_departure", "lane departure"),
              ("collision", "collision", "collision"))
FOLLOW_MAX_GAP_M = 150.0  # [m] leader within radar range (SensorConfig.radar_range_m)
FOLLOW_MIN_SPEED_MPS = 5.0  # [m/s] below it a time gap is not meaningful
TIME_GAP_RATE_HZ = 10.0  # [Hz] time-gap samples kept per drive (the synthetic drives' rate)
TIME_GAP_QUANTILES = (0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95)
HUMANS = "synthetic humans"
# a population of drivers: the planners with a time-gap setting drive each stretch
# POPULATION_SEEDS_PER_STRETCH times, each drive at a setting drawn from the preferred time gaps
# of the real training maneuvers (:func:`population_tasks`)
POPULATION_PLANNERS = ("safeil", "idm")
POPULATION_SEEDS_PER_STRETCH = 6  # 18 drives; the first 2 per stretch on the other rows' seeds
POPULATION = "population"
SETTING_SALT = 74  # the settings' random stream, apart from the traffic's


# ------------------------------------------------------------------------------- statistics


def garwood_interval(events: int, exposure: float, confidence: float = 0.95
                     ) -> tuple[float, float]:
    """Exact (Garwood) interval ``(low, high)`` of a Poisson rate: ``events`` counted over
    ``exposure`` (e.g. km; the rate is per unit of it).

    ``low = chi2(a/2; 2k) / 2 / exposure`` (0 when ``k = 0``), ``high = chi2(1 - a/2; 2k + 2) /
    2 / exposure`` with ``a = 1 - confidence``: the means whose Poisson tails just reach the count.
    """
    from scipy.stats import chi2

    if events < 0 or int(events) != events:
        raise ValueError(f"events must be an integer >= 0, got {events}")
    if not exposure > 0 or not math.isfinite(exposure):
        raise ValueError(f"exposure must be finite and > 0, got {exposure}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    a = 1.0 - confidence
    k = int(events)
    low = 0.0 if k == 0 else float(chi2.ppf(a / 2, 2 * k)) / 2.0
    high = float(chi2.ppf(1 - a / 2, 2 * k + 2)) / 2.0
    return low / exposure, high / exposure


def time_gaps(log: pd.DataFrame, step_s: float, rate_hz: float = TIME_GAP_RATE_HZ
              ) -> np.ndarray:
    """Time gaps [s] of a closed-loop log (columns ``gap`` [m], ``v`` [m/s]) at ``rate_hz``,
    while following (see the module doc). ``step_s``: the log's step [s]."""
    stride = max(round(1.0 / (rate_hz * step_s)), 1)
    rows = log.iloc[::stride]
    gap, v = rows["gap"].to_numpy(float), rows["v"].to_numpy(float)
    return _following_time_gaps(gap, v)


def human_time_gaps(drives: pd.DataFrame) -> pd.DataFrame:
    """Time gaps of recorded drives in the drive schema (``lead_x`` [m]: the leader's rear
    bumper ahead of the ego's front, NaN without a leader; ``v_x`` [m/s]): columns
    ``recording_id``, ``lane_index``, ``time_gap_s``; following samples only."""
    gap, v = drives["lead_x"].to_numpy(float), drives["v_x"].to_numpy(float)
    keep = _following(gap, v)
    return pd.DataFrame({"recording_id": drives["recording_id"].to_numpy()[keep],
                         "lane_index": drives["lane_index"].to_numpy(float)[keep],
                         "time_gap_s": gap[keep] / v[keep]})


def _following(gap: np.ndarray, v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (np.isfinite(gap) & (gap > 0) & (gap <= FOLLOW_MAX_GAP_M)
                & (v > FOLLOW_MIN_SPEED_MPS))


def _following_time_gaps(gap: np.ndarray, v: np.ndarray) -> np.ndarray:
    keep = _following(gap, v)
    return gap[keep] / v[keep]


def flag_events(log: pd.DataFrame) -> list[dict]:
    """Every flag event of a log (a run of flagged steps of one kind), in time order:
    ``kind``, ``t_s`` [s], ``x``, ``y`` [m] (front bumper), ``s_m`` [m] (along the ego lane)."""
    out = []
    for kind, col, _ in FLAG_KINDS:
        for i in event_starts(log[col].to_numpy(bool)):
            row = log.iloc[int(i)]
            out.append({"kind": kind, "t_s": float(row["t"]), "x": float(row["front_x"]),
                        "y": float(row["front_y"]), "s_m": float(row["s"])})
    return sorted(out, key=lambda e: e["t_s"])


def ks_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Kolmogorov-Smirnov distance: the largest gap between the two ECDFs."""
    a, b = np.sort(np.asarray(a, float)), np.sort(np.asarray(b, float))
    if not len(a) or not len(b):
        return math.nan
    grid = np.concatenate([a, b])
    fa = np.searchsorted(a, grid, side="right") / len(a)
    fb = np.searchsorted(b, grid, side="right") / len(b)
    return float(np.max(np.abs(fa - fb)))


def median_difference_ci(groups_a: Sequence[np.ndarray], groups_b: Sequence[np.ndarray],
                         seed: int, reps: int = 1000, confidence: float = 0.95
                         ) -> tuple[float, float, float]:
    """``(median(a) - median(b), low, high)``: the difference of the pooled medians with a
    percentile bootstrap interval that resamples whole GROUPS (drives, recordings) with
    replacement — samples of one drive are strongly correlated, so resampling samples would
    give far too narrow intervals. Seeded."""
    groups_a = [g for g in groups_a if len(g)]  # a drive that never followed adds nothing
    groups_b = [g for g in groups_b if len(g)]
    if not groups_a or not groups_b:
        return math.nan, math.nan, math.nan
    rng = np.random.default_rng(seed)
    point = float(np.median(np.concatenate(groups_a)) - np.median(np.concatenate(groups_b)))
    diffs = np.empty(reps)
    for r in range(reps):
        ia = rng.integers(0, len(groups_a), len(groups_a))
        ib = rng.integers(0, len(groups_b), len(groups_b))
        diffs[r] = (np.median(np.concatenate([groups_a[i] for i in ia]))
                    - np.median(np.concatenate([groups_b[i] for i in ib])))
    a = (1.0 - confidence) / 2
    return point, float(np.quantile(diffs, a)), float(np.quantile(diffs, 1 - a))


def compare_time_gaps(planner_groups: dict[str, list[np.ndarray]],
                      human_groups: list[np.ndarray], seed: int) -> pd.DataFrame:
    """One row per planner and one for the humans: samples, groups, quantiles; for planners
    also the KS distance to the humans and the median difference with its bootstrap interval."""
    humans = np.concatenate(human_groups) if human_groups else np.zeros(0)
    rows = []
    for k, (name, groups) in enumerate([*planner_groups.items(), (HUMANS, human_groups)]):
        pooled = np.concatenate(groups) if groups else np.zeros(0)
        row = {"who": name, "groups": len(groups), "samples": len(pooled)}
        for q in TIME_GAP_QUANTILES:
            row[f"q{round(100 * q):02d}_s"] = float(np.quantile(pooled, q)) if len(pooled) \
                else math.nan
        row["share_below_1s"] = float(np.mean(pooled < 1.0)) if len(pooled) else math.nan
        if name != HUMANS:
            row["ks_to_humans"] = ks_distance(pooled, humans)
            d, lo, hi = median_difference_ci(groups, human_groups, seed + k)
            row |= {"median_diff_s": d, "median_diff_lo_s": lo, "median_diff_hi_s": hi}
        rows.append(row)
    return pd.DataFrame(rows)


def rates(drives: pd.DataFrame, confidence: float = 0.95) -> pd.DataFrame:
    """Per planner (column ``policy``): drives, km, flag events and events per 100 km by kind
    with exact Poisson intervals, min TTC, leaders and cut-ins met."""
    rows = []
    for planner, g in drives.groupby("policy", sort=False):
        km = float(g["km_driven"].sum())
        row = {"policy": planner, "drives": len(g), "km": km}
        for kind, _, _ in FLAG_KINDS:
            k = int(g[f"{kind}_events"].sum())
            row[f"{kind}_events"] = k
            if km > 0:
                lo, hi = garwood_interval(k, km / 100.0, confidence)
                row |= {f"{kind}_per_100km": 100.0 * k / km, f"{kind}_lo": lo, f"{kind}_hi": hi}
            else:
                row |= {f"{kind}_per_100km": math.nan, f"{kind}_lo": math.nan,
                        f"{kind}_hi": math.nan}
        row |= {"min_ttc_s": float(g["min_ttc_s"].min()),
                "leaders_met": int(g["leaders_met"].sum()),
                "cut_ins_met": int(g["cut_ins_met"].sum()),
                "completed_drives": int((g["end_reason"] == "completed").sum())}
        rows.append(row)
    return pd.DataFrame(rows)


# ------------------------------------------------------------------------------- the drives


def drive_tasks(planners: Sequence[str] = PLANNERS, master_seed: int = 0,
                stretches: Sequence[tuple[float, float]] = STRETCHES_KM,
                seeds_per_stretch: int = SEEDS_PER_STRETCH, traffic: str = TRAFFIC
                ) -> list[Task]:
    """Every planner drives every stretch with the same ``seeds_per_stretch`` traffic seeds
    (task index ``j * seeds_per_stretch + i`` = stretch ``j``, seed ``i``)."""
    return [Task(ScenarioSpec(net="n74", index=j * seeds_per_stretch + i,
                              master_seed=master_seed, from_km=a, to_km=b, traffic=traffic),
                 PlannerRef(p))
            for p in planners for j, (a, b) in enumerate(stretches)
            for i in range(seeds_per_stretch)]


# ---------------------------------------------------------------- a population of drivers


def training_settings(checkpoint: str | Path, tuple_paths: Sequence[str | Path]
                      ) -> dict[str, float]:
    """The preferred time gaps [s] a style-conditioned checkpoint was trained with: per training
    maneuver of the real tuple files it was fine-tuned on (``training/train_shipped_models.py``:
    the OpenACC and NGSIM tuples), its held-out maneuvers left out
    (:func:`safeil_sumo.learn.style.training_time_gaps`; their median is its default setting)."""
    from safeil_sumo.data.tuples import Tuples
    from safeil_sumo.learn.checkpoint import held_out_maneuvers
    from safeil_sumo.learn.closed_loop import D_LEAD, V_X
    from safeil_sumo.learn.style import training_time_gaps

    tuples = Tuples.concat([Tuples.load(p) for p in tuple_paths])
    held = set(held_out_maneuvers(checkpoint))
    train = {m for m in np.unique(tuples.maneuver_id) if m not in held}
    est = training_time_gaps(tuples.features[:, D_LEAD], tuples.features[:, V_X],
                             tuples.maneuver_id, train)
    return {str(k): float(v) for k, v in est.items()}


def draw_settings(estimates: dict[str, float], master_seed: int, n: int) -> list[float]:
    """``n`` drivers' time-gap settings [s], stratified: the estimates' empirical distribution is
    cut into ``n`` equal-probability strata, each drive draws one training maneuver's estimate
    uniformly within its own stratum, and the strata are assigned to the drives in a random
    order (so ``n`` drives cover the distribution evenly, not by the luck of ``n`` independent
    draws, and a drive's setting is independent of its traffic). Seeded by ``(SETTING_SALT,
    master_seed, n)``; each value clipped to the settable range
    :data:`safeil_sumo.learn.style.SETTING_RANGE_S`. With ``n`` equal to the number of
    estimates, the settings are the clipped estimates in a random order."""
    from safeil_sumo.learn.style import clip_time_gap

    if not estimates:
        raise ValueError("no time-gap estimates to draw a setting from")
    if n < 1:
        raise ValueError(f"need n >= 1 settings, got {n}")
    values = np.sort(np.asarray(list(estimates.values()), float))
    rng = np.random.default_rng([SETTING_SALT, int(master_seed), int(n)])
    u = (rng.permutation(n) + rng.uniform(size=n)) / n  # drive k's quantile, in stratum perm[k]
    pick = np.minimum((u * len(values)).astype(int), len(values) - 1)
    return [clip_time_gap(values[i]) for i in pick]


def population_index(stretch: int, seed: int, n_stretches: int, per: int,
                     base: int = SEEDS_PER_STRETCH) -> int:
    """The task index (traffic seed) of stretch ``stretch``'s ``seed``-th population drive: the
    first ``base`` of each stretch are the other rows' (:func:`drive_tasks`: common random
    numbers); the further ones are numbered after all of theirs."""
    if not (0 <= stretch < n_stretches and 0 <= seed < per):
        raise ValueError(f"stretch {stretch} / seed {seed} outside {n_stretches} x {per}")
    if seed < base:
        return stretch * base + seed
    return n_stretches * base + stretch * (per - base) + (seed - base)


def population_tasks(estimates: dict[str, float],
                     planners: Sequence[str] = POPULATION_PLANNERS, master_seed: int = 0,
                     stretches: Sequence[tuple[float, float]] = STRETCHES_KM,
                     per: int = POPULATION_SEEDS_PER_STRETCH, base: int = SEEDS_PER_STRETCH,
                     traffic: str = TRAFFIC) -> list[Task]:
    """A population of drivers: every stretch driven ``per`` times, each drive at its own
    setting (:func:`draw_settings`; drive ``index`` gets setting ``index``, recorded in its
    planner's ``time_gap_s``); every planner gets the same drives (index, stretch, setting)."""
    n = len(stretches)
    drives = [(population_index(j, i, n, per, min(base, per)), a, b)
              for j, (a, b) in enumerate(stretches) for i in range(per)]
    settings = draw_settings(estimates, master_seed, len(drives))  # indexes 0 .. n * per - 1
    return [Task(ScenarioSpec(net="n74", index=k, master_seed=master_seed, from_km=a, to_km=b,
                              traffic=traffic), PlannerRef(p, time_gap_s=settings[k]))
            for p in planners for k, a, b in drives]


def row_name(policy: str, time_gap_s: float | None) -> str:
    """A drive's row in the tables: its planner, or ``<planner>_population`` when its spec
    carries a setting."""
    if time_gap_s is None or not math.isfinite(float(time_gap_s)):
        return policy
    return f"{policy}_{POPULATION}"


def drive_extras(task: Task, rollout: Rollout) -> dict:
    """What the section keeps of a drive's log: time gaps (3 decimals) and flag events."""
    log = rollout.log
    if len(log) < 2:
        return {"time_gaps_s": [], "flag_events": []}
    step = float(log["t"].iloc[1] - log["t"].iloc[0])
    return {"time_gaps_s": np.round(time_gaps(log, step), 3).tolist(),
            "flag_events": flag_events(log)}


drive_task = partial(run_task, extras=drive_extras)
