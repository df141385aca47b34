"""Section 4 of ``safeil-evaluate``: held-out maneuvers of the real human data replayed whole
(what ``safeil-replay --maneuver all --windows whole`` does), by the model beside the calibrated
IDM and the constant-speed follower; the best, the median and the worst maneuver (by the model's
gap RMSE against the human) replayed again (``safeil-replay --maneuver ID --duration-s 0``) to
draw the human's and each planner's gap and speed over time."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from safeil_sumo import planner_registry as pol
from safeil_sumo import report_figures as figs
from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.sources import load_source
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.learn.checkpoint import CheckpointError, held_out_maneuvers
from safeil_sumo.report_card import (
    Check,
    Number,
    Section,
    beats,
    best_median_worst,
    command_line,
    none_of,
)
from safeil_sumo.report_sections import (
    REPLAY_BASELINES,
    REPLAY_SOURCES,
    SHIPPED_SIDECAR,
    EvalContext,
    copy_figure,
    load_json,
    shown_path,
    temporary_folder,
)

MEASURES = (
    "Human-likeness on maneuvers held out of training: each maneuver of OpenACC (motorway) and "
    "NGSIM I-80 (congested) rebuilt in SUMO from its start to its end, the leader on its "
    "recorded speed, the ego driven closed loop by each planner; the gap RMSE [m] against the "
    "human over the maneuver, per planner: the median with its bootstrap 95 % interval, the "
    "worst; the calibrated IDM and a constant-speed follower (the literature's naive baseline) "
    "as references (docs/human_likeness.md).")


def held_out_sidecar(model: str) -> Path:
    """The checkpoint sidecar whose held-out maneuvers (``metrics.val_maneuvers``) are replayed:
    the model's own; an IDM model file's ``held_out_from`` (the shipped IDM was fitted without
    the shipped SafeIL's held-out maneuvers); else the shipped SafeIL's."""
    path = pol.policy_file(model)
    if path.suffix == ".safetensors":
        try:
            held_out_maneuvers(path.with_suffix(".json"))
            return path.with_suffix(".json")
        except CheckpointError:
            return SHIPPED_SIDECAR
    named = load_json(path).get("held_out_from") if path.suffix == ".json" else None
    if isinstance(named, list) and named:
        for base in (path.parent, pol.MODELS_DIR.parents[1]):  # as written: from the repo root
            if (base / named[0]).is_file():
                return base / named[0]
    return SHIPPED_SIDECAR


def planners(model: str) -> list[str]:
    """The model, then the baselines it is not."""
    return list(dict.fromkeys([model, *REPLAY_BASELINES]))


def _source(ctx: EvalContext, source: str, held: set[str]
            ) -> tuple[pd.DataFrame, pd.DataFrame, list[str]]:
    """Replay ``source``'s held-out maneuvers whole: (maneuvers, per-maneuver table, ids);
    ``OSError`` / ``ValueError`` when the source cannot be read."""
    s = ctx.settings
    maneuvers, _ = process_drive(load_source(source, s.data_dir), PipelineConfig(rate_hz=10.0))
    only = sorted(held & set(maneuvers["maneuver_id"].astype(str)))
    only = only if s.replay_maneuvers is None else only[:s.replay_maneuvers]
    if not only:
        return maneuvers, pd.DataFrame(), []
    folder = ctx.work / f"replay_{source}"
    wins = ra.windows(maneuvers, "whole", only=only)
    records = ra.replay_all(maneuvers, wins, planners(ctx.model), folder,
                            rp.ReplayConfig(seed=s.seed), s.workers, progress=False)
    df, _ = ra.write(folder, records, {"source": source, "maneuvers": only,
                                       "windows_mode": "whole"}, s.seed, f"{source} whole")
    copy_figure(folder / "replay_all.png", ctx, f"replay_{source}_cdf.png")
    return maneuvers, df.assign(source=source), only


def _traces(ctx: EvalContext, pooled: pd.DataFrame, maneuvers: dict[str, pd.DataFrame]
            ) -> tuple[list, dict, list[str]]:
    """The best, median and worst maneuver (the model's gap RMSE) replayed again for their
    series: (figure panels, numbers, commands)."""
    mine = pooled[(pooled["policy"] == ctx.model) & (pooled["status"] == "ok")].reset_index()
    picks = best_median_worst(mine["rmse_gap"].to_numpy(float).tolist())
    panels: list[tuple[str, pd.DataFrame, dict[str, pd.DataFrame]]] = []
    numbers: dict[str, Number] = {}
    commands: list[str] = []
    names = planners(ctx.model)
    for label, i in picks:
        row = mine.iloc[i]
        mid, source = str(row["maneuver_id"]), str(row["source"])
        rows = maneuvers[source]
        rows = rows[rows["maneuver_id"].astype(str) == mid].reset_index(drop=True)
        with temporary_folder() as tmp:
            res = rp.replay_maneuver(rp.window(rows, 0.0, None),
                                     {n: pol.load_for_replay(n) for n in names}, Path(tmp),
                                     rp.ReplayConfig(seed=ctx.settings.seed), maneuver_id=mid)
        rmse = float(row["rmse_gap"])
        title = (f"{label}: {mid} ({source}, {res.info['duration_s']:.0f} s), {ctx.model} gap "
                 f"RMSE {rmse:.2f} m")
        panels.append((title, res.human, res.compared))
        numbers |= {f"{label}_maneuver": f"{source}:{mid}", f"{label}_gap_rmse_m": rmse}
        commands.append(command_line("safeil-replay", [
            "--source", source, "--maneuver", mid, "--duration-s", 0, "--policy", *names,
            "--seed", ctx.settings.seed, "--out", f"runs/replay_evaluate_{label}"]))
    return panels, numbers, commands


def _source_command(ctx: EvalContext, source: str, only: list[str], sidecar: Path) -> str:
    """The ``safeil-replay`` command of one source's whole-maneuver replays."""
    which = (["--maneuver", "all", "--held-out-of", shown_path(sidecar)]
             if ctx.settings.replay_maneuvers is None else ["--maneuver", ",".join(only)])
    return command_line("safeil-replay", [
        "--source", source, *which, "--windows", "whole", "--policy", *planners(ctx.model),
        "--seed", ctx.settings.seed, "--out", f"runs/replay_evaluate_{source}"])


def _planner_numbers(agg: pd.DataFrame, model: str) -> dict:
    """Per planner (``model_``, ``idm_``, ``constant_speed_``): gap RMSE median with its
    bootstrap interval, mean and worst [m]; speed RMSE median [m/s]; collisions; flags where the
    human had none."""
    out: dict = {}
    for _, r in agg.iterrows():
        p = "model" if r["policy"] == model else str(r["policy"])
        out |= {f"{p}_gap_rmse_median_m": float(r["gap_rmse_median_m"]),
                f"{p}_gap_rmse_median_lo_m": float(r["gap_rmse_median_lo"]),
                f"{p}_gap_rmse_median_hi_m": float(r["gap_rmse_median_hi"]),
                f"{p}_gap_rmse_mean_m": float(r["gap_rmse_mean_m"]),
                f"{p}_gap_rmse_max_m": float(r["gap_rmse_max_m"]),
                f"{p}_speed_rmse_median_mps": float(r["speed_rmse_median_mps"]),
                f"{p}_collisions": int(r["collisions"]),
                f"{p}_flags_beyond_human": int(r["flags_beyond_human"])}
    return out


def _checks(numbers: dict, model: str) -> tuple[Check, ...]:
    """No collision of the model; its median gap RMSE below the constant-speed follower's."""
    med = numbers.get("model_gap_rmse_median_m", math.nan)
    naive = numbers.get("constant_speed_gap_rmse_median_m", math.nan)
    idm = numbers.get("idm_gap_rmse_median_m", math.nan)
    versus = "" if model == "idm" else f", calibrated IDM {idm:.2f} m"
    return (
        Check("no collision in the held-out replays",
              f"{numbers.get('model_collisions', 0)} collisions in "
              f"{numbers['maneuvers']} maneuvers", "no collision of the model",
              none_of(numbers.get("model_collisions", 0)) and numbers["maneuvers"] > 0),
        Check("closer to the human than a constant-speed follower",
              f"median gap RMSE {med:.2f} m (constant speed {naive:.2f} m{versus})",
              "the model's median gap RMSE below the constant-speed follower's",
              beats(med, naive)))


def replay(ctx: EvalContext) -> Section:
    """Section 4: whole held-out maneuvers, the table per planner and the traces figure."""
    sidecar = held_out_sidecar(ctx.model)
    held = set(held_out_maneuvers(sidecar))
    frames, maneuvers, commands, counts, skipped = [], {}, [], {}, []
    for source in REPLAY_SOURCES:
        try:
            maneuvers[source], df, only = _source(ctx, source, held)
        except (OSError, ValueError) as exc:  # e.g. a data folder without this source
            skipped.append(f"{source} skipped: {exc}.")
            df, only = pd.DataFrame(), []
        counts[f"{source}_maneuvers"] = len(only)
        if only:
            frames.append(df)
            commands.append(_source_command(ctx, source, only, sidecar))
    if not frames:  # nothing to judge: the section's error, not a failed check
        raise ValueError("no held-out maneuver to replay " + " ".join(skipped))
    pooled = pd.concat(frames, ignore_index=True)
    pooled.to_csv(ctx.table("replay_maneuvers.csv"), index=False)
    agg = ra.aggregate(pooled, ctx.settings.seed) if len(pooled) else pd.DataFrame()
    agg.to_csv(ctx.table("replay_planners.csv"), index=False)
    ok = pooled[pooled["status"] == "ok"].drop_duplicates(["source", "maneuver_id"])
    numbers: dict = {"maneuvers": len(ok), **counts,
                     "failed_to_run": int(sum(counts.values()) - len(ok))}
    numbers |= _planner_numbers(agg, ctx.model) if len(agg) else {}
    panels, picked, pick_commands = _traces(ctx, pooled, maneuvers)
    numbers |= picked
    figures = [f"figures/replay_{s}_cdf.png" for s in REPLAY_SOURCES
               if (ctx.figures / f"replay_{s}_cdf.png").is_file()]
    if panels:
        path, rel = ctx.figure("replay_best_median_worst.png")
        figs.plot_replay_traces(panels, path)
        figures.insert(0, rel)
    notes = (f"Held-out maneuvers: those of {shown_path(sidecar)} (`metrics.val_maneuvers`)"
             + ("" if ctx.settings.replay_maneuvers is None else
                f", the first {ctx.settings.replay_maneuvers} per source") + ".", *skipped)
    return Section("replay", "Whole-maneuver replays of held-out maneuvers", MEASURES, numbers,
                   _checks(numbers, ctx.model), (*commands, *pick_commands), tuple(figures),
                   notes)
