"""The ``humanlike`` section of ``python -m safeil_sumo.results``: every 11 s window (every 20 s)
of the OpenACC and NGSIM maneuvers the shipped SafeIL held out of training, replayed with every
planner and the ``recorded`` human path; gap-RMSE distributions with bootstrap intervals. It
writes ``humanlike.csv`` and ``humanlike_<source>.png`` and its part of ``results/studies.md``
(:func:`humanlike_readme`); :func:`held_out_sources` gives the ``whole`` section the same
maneuvers."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pandas as pd

from safeil_sumo.studies.paper_replay import PAPER_REPLAY_GAP_RMSE_M
from safeil_sumo.studies.shared import LABELS, POLICIES, SHIPPED_SAFEIL, md_table, save_csv


def held_out_sources(tag: str) -> Iterator[tuple[str, pd.DataFrame, list[str]]]:
    """``(source, maneuvers, held-out ids)`` of OpenACC and NGSIM: the pipeline's maneuvers at
    10 Hz and the ids the shipped SafeIL held out; a source that cannot be read is skipped with
    a line naming ``tag`` (the section)."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source
    from safeil_sumo.learn.checkpoint import held_out_maneuvers

    held = set(held_out_maneuvers(SHIPPED_SAFEIL))
    for source in ("openacc", "ngsim"):
        try:
            maneuvers, _ = process_drive(load_source(source), PipelineConfig(rate_hz=10.0))
        except (OSError, ValueError) as exc:
            print(f"[{tag}] {source} skipped: {exc}")
            continue
        yield source, maneuvers, sorted(held & set(maneuvers["maneuver_id"].astype(str)))


def humanlike(out: Path, work: Path, workers: int, seed: int) -> list[dict]:
    """Every 11 s window (every 20 s) of the maneuvers the shipped SafeIL held out, per source."""
    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.experiments import window_replays as ra

    rows = []
    for source, maneuvers, only in held_out_sources("humanlike"):
        wins = ra.windows(maneuvers, "sliding", rp.PAPER_DURATION_S, 20.0, only)
        folder = work / f"humanlike_{source}"
        # "recorded" (the human's own path) is the instrument's floor beside the planners
        records = ra.replay_all(maneuvers, wins, [*POLICIES, "recorded"], folder,
                                rp.ReplayConfig(seed=seed), workers)
        _, agg = ra.write(folder, records, {"source": source, "maneuvers": only}, seed, source)
        shutil.copyfile(folder / "replay_all.png", out / f"humanlike_{source}.png")
        rows += [dict(r, source=source, maneuvers=len(only)) for r in agg.to_dict("records")]
        print(f"[humanlike] {source}: {len(records)} windows of {len(only)} held-out maneuvers")
    table = pd.DataFrame(rows)
    if len(table):
        save_csv(table, out / "humanlike.csv")
    return rows


def humanlike_readme(facts: dict) -> list[str]:
    """Every held-out 11 s window, replayed."""
    lines: list[str] = []
    rows = [dict(r, planner=LABELS.get(r["policy"], r["policy"]),
                 med=f"{r['gap_rmse_median_m']:.2f} [{r['gap_rmse_median_lo']:.2f}, "
                     f"{r['gap_rmse_median_hi']:.2f}]",
                 mean=f"{r['gap_rmse_mean_m']:.2f} [{r['gap_rmse_mean_lo']:.2f}, "
                      f"{r['gap_rmse_mean_hi']:.2f}]") for r in facts["humanlike"]]
    lines += ["## Human-likeness over every held-out window", "",
              ("Every 11 s window, every 20 s, of each maneuver the shipped SafeIL held out "
              "of training (20 % per source), replayed closed-loop with every planner "
              "(`python -m safeil_sumo.replay --source SOURCE --maneuver all --held-out-of "
              "safeil_sumo/models/safeil.json`). Gap RMSE against the human per window: "
              "median and mean with seeded bootstrap 95 % intervals. The paper reports "
              f"{PAPER_REPLAY_GAP_RMSE_M} m for SafeIL on ONE 11 s window."), "",
              md_table(rows, {"source": "source", "maneuvers": "maneuvers",
                              "windows": "windows", "planner": "planner",
                              "med": "gap RMSE median [95 % CI] [m]",
                              "mean": "mean [95 % CI] [m]",
                              "speed_rmse_median_mps": "speed RMSE median [m/s]",
                              "lateral_rmse_median_m": "lateral RMSE median [m]",
                              "time_gap_w1_median_s": "time-gap W1 median [s]",
                              "flags": "flags", "flags_beyond_human":
                              "flags where the human has none", "collisions":
                              "collisions"}), ""]
    lines += [f"![{s}](humanlike_{s}.png)"
              for s in dict.fromkeys(r["source"] for r in facts["humanlike"])]
    lines += [""]
    return lines
