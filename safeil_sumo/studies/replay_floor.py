"""The ``instrument`` section of ``python -m safeil_sumo.results``: the replay's own error, the
``recorded`` pseudo-planner (the human's own path) over every whole maneuver of OpenACC, NGSIM
and the synthetic drives: gap error, lane rebuild error, leader drift and the flags beyond the
recording's own. It writes ``instrument.csv`` and its part of ``results/studies.md``
(:func:`instrument_readme`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.studies.shared import REPO, md_table, save_csv


def instrument(out: Path, work: Path, workers: int, seed: int) -> list[dict]:
    """The ``recorded`` pseudo-planner over every whole maneuver of each source: the replay's
    error floor (gap RMSE, lane rebuild error, leader drift before and after its correction) and
    its flags, apart from those the recording itself has."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source
    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.experiments import window_replays as ra

    rows = []
    for source, where in (("openacc", "openacc"), ("ngsim", "ngsim"),
                          ("synthetic", str(REPO / "data" / "synthetic" / "drives.parquet"))):
        try:
            maneuvers, _ = process_drive(load_source(where), PipelineConfig(rate_hz=10.0))
        except (OSError, ValueError) as exc:
            print(f"[instrument] {source} skipped: {exc}")
            continue
        wins = ra.windows(maneuvers, "whole")
        records = ra.replay_all(maneuvers, wins, ["recorded"], work / f"instrument_{source}",
                                rp.ReplayConfig(seed=seed), workers)
        df = ra.table(records)
        ok = df[df["status"] == "ok"]
        gap = ok["rmse_gap"].to_numpy(float)
        rows.append({
            "source": source, "maneuvers": len(ok), "failed": int((df["status"] != "ok").sum()),
            "longest_s": float(ok["duration_s"].max()),
            "gap_rmse_median_m": float(np.median(gap)),
            "gap_rmse_p95_m": float(np.quantile(gap, 0.95)), "gap_rmse_max_m": float(gap.max()),
            "gap_rmse_over_0.2m": int((gap > 0.2).sum()),
            "gap_max_abs_m": float(ok["max_gap"].max()),
            "lane_rebuild_max_m": float(ok["max_abs_lane_rebuild_error_m"].max()),
            "leader_drift_max_m": float(ok["max_abs_leader_drift_m"].max()),
            "leader_drift_uncorrected_max_m": float(
                ok["max_abs_leader_drift_uncorrected_m"].max()),
            "flags": int((ok["flag"] != "").sum()),
            "flags_beyond_human": int(((ok["flag"] != "") & (ok["human_flag"] == "")).sum()),
            "human_flags": int((ok["human_flag"] != "").sum()),
        })
        print(f"[instrument] {source}: {len(ok)} maneuvers replayed whole")
    if rows:
        save_csv(pd.DataFrame(rows), out / "instrument.csv")
    return rows


def instrument_readme(facts: dict) -> list[str]:
    """The replay's own error (the human's path replayed)."""
    lines: list[str] = []
    lines += ["## The replay's own error: the human's path replayed", "",
              ("The `recorded` pseudo-planner drives the ego along the human's own recorded "
              "path (`python -m safeil_sumo.replay --policy recorded ...`): on a faithful "
              "digital twin it raises no flag and its gap equals the human's. Every maneuver "
              "of each source, whole. Its gap error is the floor under every planner's "
              "above. A flag the recording itself has (its TTC <= 1 s, its body over a "
              "recorded lane line) is counted apart."), "",
              md_table(facts["instrument"], {
                  "source": "source", "maneuvers": "maneuvers", "longest_s": "longest [s]",
                  "gap_rmse_median_m": "gap RMSE median [m]",
                  "gap_rmse_p95_m": "p95 [m]", "gap_rmse_max_m": "max [m]",
                  "gap_rmse_over_0.2m": "> 0.2 m", "lane_rebuild_max_m":
                  "lane rebuild error max [m]", "leader_drift_uncorrected_max_m":
                  "leader drift, speed alone, max [m]", "leader_drift_max_m":
                  "corrected [m]", "flags": "flags", "human_flags":
                  "the recording's own flags", "flags_beyond_human":
                  "flags beyond the recording's"}), ""]
    return lines
