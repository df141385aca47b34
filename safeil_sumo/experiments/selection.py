"""Closed-loop model selection: a short SUMO validation battery and a score to rank planners by.

Open-loop loss does not tell whether a planner follows its leader in closed loop (the shipped
models of an earlier version had the lowest validation loss and rammed slow leaders). Candidates
are therefore compared on a few closed-loop scenarios of the kinds that matter, with seeds apart
from the reported tests (master seed :data:`VALIDATION_SEED`, not the paper test's 0):

- ``paper``: curved500, leader at a constant random speed in [25, 32] m/s (the paper's test);
- ``approach``: straight, a slower leader 140 m ahead, closing at 5–15 m/s;
- ``braking``: curved500, the leader brakes at 4 m/s^2 to a stop after 5 s;
- ``cut_in``: straight, a leader 12–25 m ahead, 3–8 m/s slower (appears at t = 0).

The score ranks by safety first (collisions, then flags), then by how much of the path was
completed and how close the time gap stays to a human's (1.5 s, the median of the OpenACC human
followers is 1.3 s), so among safe candidates the least timid wins.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH, run_sweep
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task

VALIDATION_SEED = 7919  # master seed of the battery (the reported tests use 0)
FAMILIES = ("paper", "approach", "braking", "cut_in")


def battery(policy: str, per_family: int = 3, seed: int = VALIDATION_SEED) -> list[Task]:
    """The validation tasks of one policy (``per_family`` seeded scenarios per family)."""
    scenarios: list[ScenarioSpec] = []
    common: dict[str, Any] = {"master_seed": seed, "max_time_s": 40.0}
    for i in range(per_family):
        scenarios += [
            ScenarioSpec(net="curved500", index=1000 + i, **common),
            ScenarioSpec(net="straight", index=2000 + i, leader_speed_range_mps=(15.0, 25.0),
                         initial_gap_m=140.0, **common),
            ScenarioSpec(net="curved500", index=3000 + i, leader_kind="braking",
                         brake_time_s=5.0, brake_decel_mps2=4.0, brake_to_mps=0.0, **common),
            ScenarioSpec(net="straight", index=4000 + i, leader_speed_range_mps=(22.0, 27.0),
                         initial_gap_m=(12.0, 25.0), **common),
        ]
    return [Task(s, PlannerRef(policy)) for s in scenarios]


def family_of(index: int) -> str:
    """The battery family of a spec index."""
    return FAMILIES[index // 1000 - 1]


def score(summary: pd.DataFrame) -> dict:
    """Safety-first score of one policy's battery results (lower ``rank_key`` is better)."""
    collisions = int((summary["flag"] == "collision").sum())
    flags = int((summary["flag"] != "").sum())
    path = float(summary["path_completed"].mean())
    min_ttc = float(summary["min_ttc_s"].min())
    return {
        "collisions": collisions, "flags": flags, "mean_path": path, "min_ttc_s": min_ttc,
        "min_gap_m": float(summary["min_gap_m"].min()),
        "rank_key": (collisions, flags, -round(path, 3)),
        "flags_by_family": {
            fam: int((summary.loc[summary["index"].map(family_of) == fam, "flag"] != "").sum())
            for fam in FAMILIES
        },
    }


def evaluate(policies: Sequence[str], out_dir: str | Path, per_family: int = 3,
             workers: int = 2, progress: bool = True) -> pd.DataFrame:
    """Run the battery for each policy; one score row per policy, best first."""
    specs = [s for p in policies for s in battery(p, per_family)]
    summary = run_sweep(specs, out_dir, workers=workers, progress=progress, batch=DEFAULT_BATCH)
    rows = []
    for p in policies:
        sc = score(summary[summary["policy"] == p])
        rows.append({"policy": p, **sc})
    rows.sort(key=lambda r: r["rank_key"])  # stable: ties keep the given order
    return pd.DataFrame(rows)
