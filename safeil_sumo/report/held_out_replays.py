"""Section 4 of ``safeil-evaluate``: held-out maneuvers of the real human data, and of any
recordings given with ``--data``, replayed whole (what ``safeil-replay --maneuver all --windows
whole`` does), by the model beside the calibrated IDM (:func:`baseline_idm`) and the
constant-speed follower; the best, the median and the worst maneuver (by the model's gap RMSE
against the human) replayed again (``safeil-replay --maneuver ID --duration-s 0``) to draw the
human's and each planner's gap and speed over time."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import pandas as pd

from safeil_sumo.data.by_path import DataSpec, load_data
from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.sources import load_source
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.learn.checkpoint import CheckpointError, held_out_maneuvers
from safeil_sumo.planners import idm
from safeil_sumo.planners import registry as pol
from safeil_sumo.report import figures as figs
from safeil_sumo.report.card import (
    Check,
    Number,
    Section,
    beats,
    best_median_worst,
    command_line,
    none_of,
)
from safeil_sumo.report.sections import (
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
    "NGSIM I-80 (congested), or of the recordings the model names, and of any given with "
    "--data, rebuilt in SUMO from its start to its end, the leader on its recorded speed, the "
    "ego driven closed loop by each planner; the gap RMSE [m] against the human over the "
    "maneuver, per planner: the median with its bootstrap 95 % interval, the "
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


def baseline_idm(model: str) -> str:
    """The calibrated IDM the model is compared with: the one ``safeil-train`` calibrated on a
    checkpoint's training maneuvers beside it (:func:`safeil_sumo.planners.idm.baseline_path`), else the
    shipped ``idm`` (calibrated on the shipped SafeIL's training data)."""
    path = pol.policy_file(model)
    own = idm.baseline_path(path) if path.suffix == ".safetensors" else None
    return str(own) if own is not None and idm.is_model_file(own) else "idm"


def planners(model: str) -> list[str]:
    """The model, then the baselines it is not."""
    return list(dict.fromkeys([model, baseline_idm(model), *REPLAY_BASELINES[1:]]))


@dataclass(frozen=True)
class ReplaySource:
    """One source of maneuvers: ``name`` (tables and file names), how its drive frame loads,
    the ``safeil-replay`` options that name it, and whether the user gave it (``--data``:
    every maneuver is replayed when the model held none of them out)."""

    name: str
    load: Callable[[], pd.DataFrame]
    options: tuple[str, ...]
    given: bool = False


def data_name(spec: DataSpec, taken: set[str]) -> str:
    """A short name of a ``--data`` source: ``<format>_<file or folder name>`` (a number added
    when two share it)."""
    stem = Path(str(spec.paths[0]).rstrip("/")).name.split(".")[0] if spec.paths else ""
    base = re.sub(r"[^A-Za-z0-9_-]+", "_", f"{spec.format}_{stem}").strip("_")
    name, k = base, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    taken.add(name)
    return name


def _load_given(spec: DataSpec) -> pd.DataFrame:
    return load_data([spec])[0]


def training_sources(model: str) -> list[DataSpec] | None:
    """The recorded data a checkpoint ``safeil-train`` wrote was trained on (its sidecar's
    ``training_data``), one spec per path, without synthetic drivers (recorded in SUMO: no file
    to replay); None for a model that does not name its data (the shipped ones)."""
    path = pol.policy_file(model)
    docs = load_json(path.with_suffix(".json")).get("training_data") \
        if path.suffix == ".safetensors" else None
    if not docs:
        return None
    specs = [DataSpec.from_json(d) for d in docs]
    return [replace(s, paths=(p,)) for s in specs if s.format != "synthetic" for p in s.paths]


def _options(spec: DataSpec) -> tuple[str, ...]:
    """``safeil-replay``'s options naming one spec's (first) path."""
    csv = (*(("--map", spec.columns) if spec.columns else ()),
           *(("--speed-unit", spec.speed_unit) if spec.speed_unit != "m/s" else ()))
    return ("--source", f"{spec.format}:{shown_path(spec.paths[0])}", *csv)


def replay_sources(ctx: EvalContext) -> list[ReplaySource]:
    """The model's own training recordings when it names them (:func:`training_sources`), else
    OpenACC and NGSIM from the data folder; then each ``--data`` spec."""
    s = ctx.settings
    own = training_sources(ctx.model)
    taken: set[str] = set()
    if own is None:
        out = [ReplaySource(src, partial(load_source, src, s.data_dir),
                            ("--source", src, "--data-dir", shown_path(s.data_dir)))
               for src in REPLAY_SOURCES]
        taken |= set(REPLAY_SOURCES)
    else:
        out = [ReplaySource(data_name(spec, taken), partial(_load_given, spec), _options(spec))
               for spec in own]
    out += [ReplaySource(data_name(spec, taken), partial(_load_given, spec), _options(spec),
                         given=True) for spec in s.data]
    return out


def maneuvers_to_replay(ids: set[str], held: set[str], given: bool, cap: int | None
                        ) -> tuple[list[str], bool]:
    """Which of a source's maneuver ``ids`` are replayed, sorted, the first ``cap`` (None: all),
    and whether they are held-out ones: those the model held out; for a source the user gave
    that has none of them, every one (its recordings were not the training data's held-out
    part, so they may be new to the model or its training data: the report says which)."""
    only = sorted(ids & held)
    is_held = bool(only)
    if given and not is_held:
        only = sorted(ids)
    return (only if cap is None else only[:cap]), is_held


def _source(ctx: EvalContext, src: ReplaySource, held: set[str]
            ) -> tuple[pd.DataFrame, pd.DataFrame, list[str], bool]:
    """Replay ``src``'s held-out maneuvers whole (a given source without any: all of them):
    (maneuvers, per-maneuver table, ids, whether they are the held-out ones); ``OSError`` /
    ``ValueError`` when the source cannot be read."""
    s = ctx.settings
    maneuvers, _ = process_drive(src.load(), PipelineConfig(rate_hz=10.0))
    ids = set(maneuvers["maneuver_id"].astype(str)) if len(maneuvers) else set()
    only, is_held = maneuvers_to_replay(ids, held, src.given, s.replay_maneuvers)
    if not only:
        return maneuvers, pd.DataFrame(), [], is_held
    folder = ctx.work / f"replay_{src.name}"
    wins = ra.windows(maneuvers, "whole", only=only)
    records = ra.replay_all(maneuvers, wins, planners(ctx.model), folder,
                            rp.ReplayConfig(seed=s.seed), s.workers, progress=False)
    df, _ = ra.write(folder, records, {"source": src.name, "maneuvers": only,
                                       "windows_mode": "whole"}, s.seed, f"{src.name} whole")
    copy_figure(folder / "replay_all.png", ctx, f"replay_{src.name}_cdf.png")
    return maneuvers, df.assign(source=src.name), only, is_held


def _traces(ctx: EvalContext, pooled: pd.DataFrame, maneuvers: dict[str, pd.DataFrame],
            sources: dict[str, ReplaySource]) -> tuple[list, dict, list[str]]:
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
            *sources[source].options, "--maneuver", mid, "--duration-s", 0, "--policy", *names,
            "--seed", ctx.settings.seed, "--out", f"runs/replay_evaluate_{label}"]))
    return panels, numbers, commands


def _source_command(ctx: EvalContext, src: ReplaySource, only: list[str], sidecar: Path,
                    is_held: bool) -> str:
    """The ``safeil-replay`` command of one source's whole-maneuver replays."""
    if ctx.settings.replay_maneuvers is not None:
        which = ["--maneuver", ",".join(only)]
    else:
        which = ["--maneuver", "all", *(["--held-out-of", shown_path(sidecar)] if is_held
                                        else [])]
    return command_line("safeil-replay", [
        *src.options, *which, "--windows", "whole", "--policy", *planners(ctx.model),
        "--seed", ctx.settings.seed, "--out", f"runs/replay_evaluate_{src.name}"])


def _label(policy: str, model: str) -> str:
    """A planner's prefix in the numbers: ``model``, ``idm`` (whichever calibrated IDM) or its
    own name."""
    if policy == model:
        return "model"
    return "idm" if policy == baseline_idm(model) else policy


def _planner_numbers(agg: pd.DataFrame, model: str) -> dict:
    """Per planner (``model_``, ``idm_``, ``constant_speed_``): gap RMSE median with its
    bootstrap interval, mean and worst [m]; speed RMSE median [m/s]; collisions; flags where the
    human had none."""
    out: dict = {}
    for _, r in agg.iterrows():
        p = _label(str(r["policy"]), model)
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


def _per_source_numbers(pooled: pd.DataFrame, model: str, seed: int) -> dict:
    """Each source's median gap RMSE [m] per planner: ``<source>_<planner>_gap_rmse_median_m``
    (given data is judged on its own, not only in the pool)."""
    out: dict = {}
    for source, df in pooled.groupby("source", sort=False):
        agg = ra.aggregate(df, seed)
        out |= {f"{source}_{_label(str(r['policy']), model)}_gap_rmse_median_m":
                float(r["gap_rmse_median_m"]) for _, r in agg.iterrows()}
    return out


def _given_note(src: ReplaySource, only: list[str], is_held: bool) -> str:
    label = src.options[1]
    if is_held:
        return f"{label} ({src.name}): the {len(only)} of its maneuvers the model held out."
    return (f"{label} ({src.name}): none of its maneuvers is held out by the model; replayed: "
            f"{len(only)} (a held-out score only if the model never trained on these "
            "recordings).")


def replay(ctx: EvalContext) -> Section:
    """Section 4: whole held-out (and given) maneuvers, the table per planner and the traces
    figure."""
    sidecar = held_out_sidecar(ctx.model)
    held = set(held_out_maneuvers(sidecar))
    sources = replay_sources(ctx)
    frames, maneuvers, commands, counts, notes = [], {}, [], {}, []
    for src in sources:
        try:
            maneuvers[src.name], df, only, is_held = _source(ctx, src, held)
        except (OSError, ValueError) as exc:  # e.g. a data folder without this source
            if src.given:  # the user's own data must not be skipped quietly
                named = str(exc).startswith(src.options[1])  # the importer's line names it
                raise ValueError(str(exc) if named else f"{src.options[1]}: {exc}") from exc
            notes.append(f"{src.name} skipped: {exc}.")
            df, only, is_held = pd.DataFrame(), [], False
        counts[f"{src.name}_maneuvers"] = len(only)
        if src.given:
            notes.append(_given_note(src, only, is_held))
        if only:
            frames.append(df)
            commands.append(_source_command(ctx, src, only, sidecar, is_held))
    if not frames:  # nothing to judge: the section's error, not a failed check
        raise ValueError("no held-out maneuver to replay " + " ".join(notes))
    pooled = pd.concat(frames, ignore_index=True)
    pooled.to_csv(ctx.table("replay_maneuvers.csv"), index=False)
    agg = ra.aggregate(pooled, ctx.settings.seed) if len(pooled) else pd.DataFrame()
    agg.to_csv(ctx.table("replay_planners.csv"), index=False)
    ok = pooled[pooled["status"] == "ok"].drop_duplicates(["source", "maneuver_id"])
    numbers: dict = {"maneuvers": len(ok), **counts,
                     "failed_to_run": int(sum(counts.values()) - len(ok))}
    numbers |= _planner_numbers(agg, ctx.model) if len(agg) else {}
    numbers |= _per_source_numbers(pooled, ctx.model, ctx.settings.seed)
    panels, picked, pick_commands = _traces(ctx, pooled, maneuvers,
                                            {src.name: src for src in sources})
    numbers |= picked
    figures = [f"figures/replay_{src.name}_cdf.png" for src in sources
               if (ctx.figures / f"replay_{src.name}_cdf.png").is_file()]
    if panels:
        path, rel = ctx.figure("replay_best_median_worst.png")
        figs.plot_replay_traces(panels, path)
        figures.insert(0, rel)
    idm_used = baseline_idm(ctx.model)
    where = ("in the recordings the model was trained on (its sidecar's `training_data`)"
             if training_sources(ctx.model) is not None else "in OpenACC and NGSIM")
    notes = [f"Held-out maneuvers: those of {shown_path(sidecar)} (`metrics.val_maneuvers`), "
             f"{where}" + ("" if ctx.settings.replay_maneuvers is None else
                           f", the first {ctx.settings.replay_maneuvers} per source") + ".",
             "The calibrated IDM: " + ("the shipped `idm` (calibrated on the shipped SafeIL's "
                                        "training data)" if idm_used == "idm" else
                                        f"`{shown_path(Path(idm_used))}`, calibrated by "
                                        "safeil-train on the model's training maneuvers") + ".",
             *notes]
    return Section("replay", "Whole-maneuver replays of held-out maneuvers", MEASURES, numbers,
                   _checks(numbers, ctx.model), (*commands, *pick_commands), tuple(figures),
                   tuple(notes))
