"""The ``whole`` and ``unseen`` sections of ``python -m safeil_sumo.results``: whole maneuvers
(start to end) replayed with the planners, the ``constant_speed`` baseline and the ``recorded``
human path: the maneuvers the shipped SafeIL held out (``humanlike_whole.csv``,
``humanlike_whole_by_driver.csv``, ``humanlike_whole_<source>.png``) and every ZalaZone
maneuver, drivers no planner has seen, in the longitudinal instrument mode
(``unseen_whole.csv``, ``unseen_whole_by_driver.csv``, ``unseen_whole_zalazone.png``), and
their parts of ``results/studies.md`` (:func:`whole_readme`, :func:`unseen_readme`)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from safeil_sumo.studies.held_out_windows import held_out_sources
from safeil_sumo.studies.shared import LABELS, md_table, save_csv

if TYPE_CHECKING:  # the annotation only: maneuver_replay is imported when a section runs
    from safeil_sumo.experiments.maneuver_replay import ReplayConfig

# the whole-maneuver replays: the planners, the naive baseline and the instrument's floor
WHOLE_POLICIES = ("safeil", "safeil_openloop", "idm", "analytic", "bc", "constant_speed",
                  "recorded")
WHOLE_QUICK_MANEUVERS = 2  # [-] held-out maneuvers per source with --quick


def whole(out: Path, work: Path, workers: int, seed: int, quick: bool = False) -> list[dict]:
    """The maneuvers the shipped SafeIL held out (those of ``humanlike``), each replayed whole
    with :data:`WHOLE_POLICIES`, per source: ``humanlike_whole.csv`` (per planner),
    ``humanlike_whole_by_driver.csv`` (per planner and driver), ``humanlike_whole_<source>.png``.
    ``quick``: the first :data:`WHOLE_QUICK_MANEUVERS` held-out maneuvers per source."""
    from safeil_sumo.experiments import maneuver_replay as rp

    sources = [(source, maneuvers, only[:WHOLE_QUICK_MANEUVERS] if quick else only)
               for source, maneuvers, only in held_out_sources("whole")]
    return _replay_whole(out, work, workers, sources, rp.ReplayConfig(seed=seed), seed,
                         "humanlike_whole", "whole")


def unseen(out: Path, work: Path, workers: int, seed: int, quick: bool = False) -> list[dict]:
    """Every whole ZalaZone maneuver (24 drivers no planner or IDM fit has seen) replayed with
    :data:`WHOLE_POLICIES` in the longitudinal instrument mode (``--lateral lane``: the ego is
    kept on the lane centre, the planners drive the gap): ``unseen_whole.csv``,
    ``unseen_whole_by_driver.csv``, ``unseen_whole_zalazone.png``. ``quick``: the first
    :data:`WHOLE_QUICK_MANEUVERS` maneuvers."""
    from dataclasses import replace

    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source
    from safeil_sumo.experiments import maneuver_replay as rp

    try:
        maneuvers, _ = process_drive(load_source("zalazone"), PipelineConfig(rate_hz=10.0))
    except (OSError, ValueError) as exc:
        print(f"[unseen] zalazone skipped: {exc}")
        return []
    only = sorted(set(maneuvers["maneuver_id"].astype(str)))
    only = only[:WHOLE_QUICK_MANEUVERS] if quick else only
    config = rp.ReplayConfig(seed=seed)
    config = replace(config, loop=replace(config.loop, lateral="lane"))
    return _replay_whole(out, work, workers, [("zalazone", maneuvers, only)], config, seed,
                         "unseen_whole", "unseen")


def _replay_whole(out: Path, work: Path, workers: int,
                  sources: list[tuple[str, pd.DataFrame, list[str]]], config: ReplayConfig,
                  seed: int, stem: str, tag: str) -> list[dict]:
    """Replay ``sources`` ``[(source, maneuvers, ids)]`` whole with :data:`WHOLE_POLICIES` and
    ``config``: ``<stem>.csv`` (per source and planner, returned), ``<stem>_by_driver.csv``
    and ``<stem>_<source>.png`` in ``out``; ``work/<tag>_<source>`` holds the tasks."""
    from safeil_sumo.experiments import window_replays as ra

    rows, drivers = [], []
    for source, maneuvers, only in sources:
        wins = ra.windows(maneuvers, "whole", only=only)
        folder = work / f"{tag}_{source}"
        records = ra.replay_all(maneuvers, wins, list(WHOLE_POLICIES), folder, config, workers)
        df, agg = ra.write(folder, records, {"source": source, "maneuvers": only,
                                             "windows_mode": "whole"}, seed, f"{source} whole")
        shutil.copyfile(folder / "replay_all.png", out / f"{stem}_{source}.png")
        ok = df[df["status"] == "ok"].drop_duplicates("maneuver_id")
        span = {"maneuvers": len(only), "failed": len(records) - len(ok),
                "shortest_s": float(ok["duration_s"].min()) if len(ok) else math.nan,
                "longest_s": float(ok["duration_s"].max()) if len(ok) else math.nan}
        rows += [dict(r, source=source, **span) for r in agg.to_dict("records")]
        drivers += [dict(r, source=source) for r in
                    ra.aggregate(df, seed, ("policy", "driver")).to_dict("records")]
        print(f"[{tag}] {source}: {len(ok)} of {len(only)} maneuvers replayed whole "
              f"({span['shortest_s']:.0f}-{span['longest_s']:.0f} s)")
    if rows:
        save_csv(pd.DataFrame(rows), out / f"{stem}.csv")
        save_csv(pd.DataFrame(drivers), out / f"{stem}_by_driver.csv")
    return rows


def _whole_rows(whole: list[dict]) -> list[dict]:
    """The table rows of :func:`whole` / :func:`unseen` facts, formatted."""
    return [dict(
        r, planner=LABELS.get(r["policy"], r["policy"]),
        span=f"{r['maneuvers']} ({r['shortest_s']:.0f}–{r['longest_s']:.0f} s)",
        med=f"{r['gap_rmse_median_m']:.2f} [{r['gap_rmse_median_lo']:.2f}, "
            f"{r['gap_rmse_median_hi']:.2f}]",
        mean=f"{r['gap_rmse_mean_m']:.2f} [{r['gap_rmse_mean_lo']:.2f}, "
             f"{r['gap_rmse_mean_hi']:.2f}]",
        worst=f"{r['gap_rmse_max_m']:.2f} (`{str(r['gap_rmse_worst']).split('@')[0]}`)",
        rmspe=f"{100 * r['spacing_rmspe_median']:.1f} / {100 * r['spacing_rmspe_mean']:.1f} %",
        tg_err=f"{r['time_gap_error_median_s']:+.2f} / {r['time_gap_error_mean_s']:+.2f}")
        for r in whole]


WHOLE_COLUMNS = {"source": "source", "span": "maneuvers (length)", "planner": "planner",
                 "med": "gap RMSE median [95 % CI] [m]", "mean": "mean [95 % CI] [m]",
                 "worst": "worst [m] (maneuver)", "rmspe": "spacing RMSPE median / mean",
                 "time_gap_rmse_median_s": "time-gap RMSE median [s]",
                 "tg_err": "time-gap error median / mean [s]", "flags": "flags",
                 "flags_beyond_human": "flags where the human has none",
                 "collisions": "collisions", "ended_early": "runs ended early"}


def whole_readme(whole: list[dict]) -> list[str]:
    """The README section of :func:`whole`: one row per source and planner."""
    rows = _whole_rows(whole)
    return [
        "## Human-likeness over whole held-out maneuvers", "",
        "The maneuvers of the previous section (held out of the shipped SafeIL's training), each "
        "replayed from its start to its end (`python -m safeil_sumo.replay --source SOURCE "
        "--maneuver all --windows whole --held-out-of safeil_sumo/models/safeil.json --policy "
        + " ".join(WHOLE_POLICIES) + "`). Per maneuver: the gap RMSE against the human; the "
        "spacing RMSPE, sqrt(mean(((gap − human gap) / human gap)²)), as the FollowNet benchmark "
        "(Sci Data 2023) reports it; the time-gap RMSE and the mean time-gap error (planner − "
        "human: below 0 the planner follows closer). `constant_speed` keeps its initial speed on "
        "the lane centre and ignores the leader: the naive baseline of the car-following "
        "literature. `recorded` drives the human's own path: the instrument's floor. A run that "
        "ends before the recording (a collision, off the road, or past the road's end) is "
        "compared up to there (*runs ended early*). Median and mean over maneuvers with seeded "
        "bootstrap 95 % intervals; worst: the largest gap RMSE and its maneuver. Per driver "
        "(an OpenACC file's follower, an NGSIM follower vehicle): "
        "`humanlike_whole_by_driver.csv`.", "",
        md_table(rows, WHOLE_COLUMNS),
        "", *[f"![{s} whole](humanlike_whole_{s}.png)"
              for s in dict.fromkeys(r["source"] for r in whole)], ""]


def unseen_readme(unseen: list[dict]) -> list[str]:
    """The README section of :func:`unseen`."""
    return [
        "## Drivers no planner has seen: ZalaZone, whole maneuvers", "",
        "`python -m safeil_sumo.results --only unseen`: every whole maneuver of "
        "`../shared/data/openacc_zalazone` (24 human follower pairs in 8 car models on a "
        "handling course, 0–20 m/s; never used in training or in the IDM's calibration) "
        "replayed with `python -m safeil_sumo.replay --source zalazone --maneuver all --windows "
        "whole --lateral lane --policy " + " ".join(WHOLE_POLICIES) + "`. `--lateral lane` "
        "keeps the ego on the rebuilt lane centre at the station its own motion reached: the "
        "planners drive the gap and speed only, since the course's bends (R down to 45 m) are "
        "far tighter than any lane the networks were trained on (docs/human_likeness.md); "
        "lateral errors and lane flags mean nothing here. Columns as in the previous section; "
        "per car: `unseen_whole_by_driver.csv`.", "",
        md_table(_whole_rows(unseen), WHOLE_COLUMNS), "",
        "![zalazone whole](unseen_whole_zalazone.png)", ""]
