"""The leader-response suite: does a planner respond to its leader like a careful driver?

    python -m safeil_sumo.sweep --suite leader-response [--quick] --policy safeil idm analytic

Families (each on ``straight`` and ``curved500``; ``variants`` seeded scenarios per family and
net, from the sweep's master seed):

- ``approach``: the ego at 30 m/s closes on a slower leader (15-25 m/s: closing at 5-15 m/s)
  first seen 145 m ahead (the radar's range is 150 m);
- ``braking``: a leader at 25-32 m/s, 50 m ahead, brakes to a stop after 5 s, at 2, 4 or 6 m/s^2
  (by variant);
- ``cut_in``: a leader appears 10-25 m ahead at t = 0, 3-8 m/s slower than the ego's 30 m/s
  (the cut-in is modelled as its end state: the radar sees the car from the first step);
- ``stop_and_go``: a leader on a recorded NGSIM speed profile (congested traffic, real stops);
  the ego starts as the recorded human follower did;
- ``accelerating``: a leader 30 m ahead at 18-22 m/s accelerates at 1.5 m/s^2 to 32 m/s after 3 s
  (the ego at 20 m/s must not lag behind forever nor overshoot).

Per scenario (pure functions over the per-step log, :func:`response_metrics`): collision, first
flag, min TTC, min time gap, max deceleration, max jerk, and whether braking at 6 m/s^2 from the
start could have kept the ego behind the leader with TTC > 1 s (:func:`braking_avoids`): flags in
scenarios where it could not are counted apart as unavoidable.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task

FAMILIES = ("approach", "braking", "cut_in", "stop_and_go", "accelerating")
NETS = ("straight", "curved500")
BRAKE_AVOID_MPS2 = 6.0  # [m/s^2] the braking that decides whether a flag was avoidable
TTC_FLAG_S = 1.0  # [s] the monitors' TTC threshold
MIN_SPEED_TIME_GAP = 1.0  # [m/s] below, the time gap gap/v is not defined
FAMILY_BASE = {name: 10_000 * (k + 1) for k, name in enumerate(FAMILIES)}


def family_scenario(family: str, net: str, variant: int, seed: int,
                    max_time_s: float = 40.0) -> ScenarioSpec:
    """One scenario of ``family`` on ``net``; the index encodes the family and net."""
    if family not in FAMILY_BASE:
        raise ValueError(f"unknown family {family!r}; families: {', '.join(FAMILIES)}")
    index = FAMILY_BASE[family] + 1000 * NETS.index(net) + variant
    common = {"net": net, "index": index, "master_seed": seed, "max_time_s": max_time_s}
    if family == "approach":
        return ScenarioSpec(leader_speed_range_mps=(15.0, 25.0), initial_gap_m=145.0, **common)
    if family == "braking":
        decel = (2.0, 4.0, 6.0)[variant % 3]
        return ScenarioSpec(leader_kind="braking", brake_time_s=5.0, brake_decel_mps2=decel,
                            brake_to_mps=0.0, **common)
    if family == "cut_in":
        return ScenarioSpec(leader_speed_range_mps=(22.0, 27.0), initial_gap_m=(10.0, 25.0),
                            **common)
    if family == "stop_and_go":
        return ScenarioSpec(leader_kind="recorded", leader_profile="ngsim", **common)
    return ScenarioSpec(leader_kind="accelerating", leader_speed_range_mps=(18.0, 22.0),
                        brake_time_s=3.0, brake_decel_mps2=1.5, brake_to_mps=32.0,
                        ego_speed_mps=20.0, initial_gap_m=30.0, **common)


def suite_tasks(policies: list[str], seed: int = 0, variants: int = 3,
                families: tuple[str, ...] = FAMILIES, nets: tuple[str, ...] = NETS
                ) -> list[Task]:
    """Every family x net x variant x policy, the loop as shipped."""
    return [Task(family_scenario(f, n, v, seed), PlannerRef(p)) for p in policies
            for f in families for n in nets for v in range(variants)]


def family_of(index: int) -> str:
    """The family of a suite scenario index."""
    return FAMILIES[index // 10_000 - 1]


# ----------------------------------------------------------------------- pure metrics


def braking_avoids(times: np.ndarray, gap0: float, v0: float, leader_speed: np.ndarray,
                   decel: float = BRAKE_AVOID_MPS2, ttc_s: float = TTC_FLAG_S) -> bool:
    """Could the ego, braking at ``decel`` [m/s^2] from the start whenever it is faster than the
    leader (and holding the leader's speed otherwise), have kept ``gap > 0`` and TTC > ``ttc_s``?

    ``times (N,)`` [s], ``leader_speed (N,)`` [m/s] the leader's actual speeds; ``gap0`` [m],
    ``v0`` [m/s] the ego's initial bumper gap and speed. Explicit Euler at the log's steps.
    """
    gap, v = float(gap0), float(v0)
    for k in range(1, len(times)):
        dt = times[k] - times[k - 1]
        vl = float(leader_speed[k - 1])
        closing = v - vl
        if gap <= 0.0 or (closing > 0.0 and gap / closing <= ttc_s):
            return False
        v_new = max(v - decel * dt, vl) if v > vl else vl
        gap += (vl - 0.5 * (v + v_new)) * dt
        v = v_new
    return gap > 0.0


def response_metrics(log: pd.DataFrame) -> dict:
    """Per-scenario response metrics from a per-step log (columns ``t, v, gap, ttc,
    leader_v, collision``)."""
    t = log["t"].to_numpy(float)
    v = log["v"].to_numpy(float)
    gap = log["gap"].to_numpy(float)
    dt = np.diff(t)
    accel = np.diff(v) / dt if len(t) > 1 else np.zeros(0)
    # jerk from the acceleration averaged over 0.1 s (the plant's step is 0.01 s)
    k = max(1, round(0.1 / float(np.median(dt)))) if len(dt) else 1
    smooth = np.convolve(accel, np.ones(k) / k, mode="valid") if len(accel) >= k else accel
    jerk = np.diff(smooth) / float(np.median(dt)) if len(smooth) > 1 else np.zeros(0)
    moving = v > MIN_SPEED_TIME_GAP
    time_gap = gap[moving] / v[moving] if moving.any() else np.array([math.inf])
    ok = np.isfinite(gap)
    avoidable = braking_avoids(t[ok], gap[ok][0], v[ok][0], log["leader_v"].to_numpy(float)[ok]) \
        if ok.any() else False
    return {
        "min_ttc_s": float(np.nanmin(log["ttc"].to_numpy(float))) if len(log) else math.nan,
        "min_time_gap_s": float(np.nanmin(time_gap)),
        "max_decel_mps2": float(max(0.0, -accel.min())) if len(accel) else 0.0,
        "max_jerk_mps3": float(np.abs(jerk).max()) if len(jerk) else 0.0,
        "collision": bool(log["collision"].to_numpy(bool).any()),
        "avoidable": bool(avoidable),
    }


def aggregate(records: pd.DataFrame) -> pd.DataFrame:
    """Per policy x family: scenarios, collisions, flags (avoidable / unavoidable), min TTC, min
    time gap, max deceleration and jerk."""
    r = records.assign(family=records["index"].map(family_of),
                       flagged=records["flag"].fillna("").astype(str) != "")
    rows = []
    for (policy, family), g in r.groupby(["policy", "family"], sort=False):
        rows.append({
            "policy": policy, "family": family, "scenarios": len(g),
            "collisions": int((g["resp_collision"] | (g["end_reason"] == "collision")).sum()),
            "flags_avoidable": int((g["flagged"] & g["resp_avoidable"]).sum()),
            "flags_unavoidable": int((g["flagged"] & ~g["resp_avoidable"]).sum()),
            "min_ttc_s": float(g["resp_min_ttc_s"].min()),
            "min_time_gap_s": float(g["resp_min_time_gap_s"].min()),
            "max_decel_mps2": float(g["resp_max_decel_mps2"].max()),
            "max_jerk_mps3": float(g["resp_max_jerk_mps3"].max()),
        })
    return pd.DataFrame(rows)
