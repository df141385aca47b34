"""How far can adapting one setting go? The best time-gap setting per left-out driver, in hindsight.

    python training/adaptation_bound.py [--grid 0.8 1.0 ... 2.3] [--adapt-first-s 60]
        [--standstill-grid 0 -10 10 -20 -30]
    python training/adaptation_bound.py --source zalazone [--grid ...]

Issue 20 asks the planner adapted to a driver (``replay --adapt-first-s``: its time-gap setting
estimated on a maneuver's first seconds, which are then not scored) to come within half the
population IDM's whole-maneuver gap error. This bounds what any adaptation of the one setting can
reach: every OpenACC maneuver left out by a fold of ``training/leave_one_driver_out.py`` (its
fold models in ``data/lodo/fold*/``, trained without that driver) is replayed in SUMO from
``--adapt-first-s`` to its end with the fold's ``safeil`` at each setting of ``--grid``
(``ReplayConfig.time_gap_s``, ``replay --time-gap-s``), and the setting with the smallest gap
RMSE on that scored part itself is kept: an oracle, chosen on the very seconds it is scored on.
Beside it, the same span replayed adapted as ``replay --adapt-first-s`` does (the setting
estimated from the first seconds). ``--standstill-grid``: every time gap also with these
standstill distances (the style ``s0 + T v``, ``ReplayConfig.standstill_m``), and the best of
both numbers per maneuver in hindsight beside the best one setting.
``--source zalazone``: the same for every ZalaZone maneuver long enough, with the shipped
``safeil`` (no fold: no planner has seen those drivers), in lane mode (longitudinal only, as
``results --only unseen``).

Writes ``<out>/settings.csv`` (maneuver, setting, gap RMSE), ``<out>/adapted.csv``,
``<out>/adaptation_curve.csv`` (how many seconds of a driver the estimate needs: the setting
estimated from the first 2 ... 60 s, scored on the same span, read off each maneuver's grid) and
prints the summary (``--from-csv``: of an earlier run's tables, without SUMO); ``<out>``
defaults to ``data/lodo/adaptation_bound`` (``..._zalazone``; not committed). Resumable.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "training"))
import leave_one_driver_out as lodo  # the folds' drivers, one source of truth

from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.sources import load_source
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.experiments.maneuver_replay import ReplayConfig
from safeil_sumo.learn.style import clip_time_gap

GRID_S = (0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0, 2.3)  # [s] settings tried
# [s] of a driver seen before the setting is estimated (adaptation_curve)
OBSERVED_S = (2.0, 5.0, 10.0, 20.0, 30.0, 45.0, 60.0)


def _gap_rmse(record: dict) -> float:
    """The one policy's gap RMSE [m] of a window record (NaN for a window that failed)."""
    if record.get("status") != "ok" or len(record.get("metrics") or []) != 1:
        print(f"{record['maneuver_id']}: {record.get('error') or 'failed'}", file=sys.stderr)
        return float("nan")
    return float(record["metrics"][0]["rmse_gap"])


def grid_runs(rows: pd.DataFrame, maneuvers: list[str], label: int | str, grid: tuple[float, ...],
              adapt_s: float, out: Path, workers: int, config: ReplayConfig,
              standstills: tuple[float, ...] = (0.0,)) -> tuple[list[dict], list[dict]]:
    """``maneuvers`` (at least ``adapt_s`` + 20 s long) replayed from ``adapt_s`` to their end
    with the ``safeil`` of ``label`` (:func:`planner_of`) at each style of ``grid`` (time gaps
    [s]) x ``standstills`` (standstill distances [m]; 0 is the one-number setting), and
    adapted (the style estimated on their first ``adapt_s``): gap RMSE per (maneuver, time
    gap, standstill), and per maneuver adapted; ``label`` in their ``fold`` column."""
    policy, tag = planner_of(label), _folder(label)
    adapted = ra.windows(rows, "whole", None, 20.0, maneuvers, adapt_s)
    # the same span, from adapt_s to the end, at a fixed setting
    plain = [ra.Window(w.maneuver_id, w.start_s, w.duration_s) for w in adapted]
    settings = []
    for s0 in standstills:
        for tg in grid:
            # s0 = 0 is the one-number setting, in the folder the one-number grid always used
            folder, style = ((f"tg{tg:g}", replace(config, time_gap_s=tg)) if s0 == 0.0 else
                             (f"tg{tg:g}_s0{s0:g}",
                              replace(config, time_gap_s=tg, standstill_m=s0)))
            recs = ra.replay_all(rows, plain, [str(policy)], out / tag / folder, style, workers,
                                 progress=False)
            settings += [{"fold": label, "maneuver_id": r["maneuver_id"], "time_gap_s": tg,
                          "standstill_m": s0, "gap_rmse_m": _gap_rmse(r)} for r in recs]
            print(f"{tag}: {tg:g} s, {s0:g} m done ({len(recs)} maneuvers)", flush=True)
    recs = ra.replay_all(rows, adapted, [str(policy)], out / tag / "adapted", config, workers,
                         progress=False)
    styles = [(r.get("adapted") or {}).get(str(policy), {}) for r in recs]
    adapt = [{"fold": label, "maneuver_id": r["maneuver_id"], "gap_rmse_m": _gap_rmse(r),
              "time_gap_s": style.get("time_gap_s", np.nan),
              "standstill_m": style.get("standstill_m", np.nan)}
             for r, style in zip(recs, styles, strict=True)]
    return settings, adapt


def fold_runs(k: int, rows: pd.DataFrame, grid: tuple[float, ...], adapt_s: float,
              out: Path, workers: int, standstills: tuple[float, ...] = (0.0,)
              ) -> tuple[list[dict], list[dict]]:
    """Fold ``k``'s left-out OpenACC maneuvers with the fold's ``safeil``: :func:`grid_runs`."""
    policy = planner_of(k)
    if not policy.is_file():
        raise SystemExit(f"{policy} is missing: run training/leave_one_driver_out.py first")
    drivers = set(json.loads((policy.parent / "drivers.json").read_text()))
    held = lodo.held_out_maneuvers(drivers)["openacc"]
    return grid_runs(rows, held, k, grid, adapt_s, out, workers, ReplayConfig(), standstills)


SHIPPED = "shipped"  # the label of runs with the shipped safeil (ZalaZone: unseen by it)


def planner_of(label: int | str) -> Path:
    """The ``safeil`` checkpoint of rows labelled ``label``: fold k's (an int), or the shipped
    one (:data:`SHIPPED`)."""
    if str(label) == SHIPPED:
        return REPO / "safeil_sumo" / "models" / "safeil.safetensors"
    return lodo.WORK / _folder(label) / "safeil.safetensors"


def _folder(label: int | str) -> str:
    """The folder of ``label``'s replays (and of fold k's models)."""
    return SHIPPED if str(label) == SHIPPED else f"fold{int(label)}"


def one_number(settings: pd.DataFrame) -> pd.DataFrame:
    """The rows of ``settings`` at the one-number setting (standstill distance 0; tables of
    runs before the second number have no such column)."""
    return (settings if "standstill_m" not in settings
            else settings[settings["standstill_m"] == 0.0])


def summary(settings: pd.DataFrame, adapted: pd.DataFrame) -> str:
    table = one_number(settings).pivot_table(index="maneuver_id", columns="time_gap_s",
                                             values="gap_rmse_m")
    best = table.idxmin(axis=1)
    oracle = table.min(axis=1)
    by_setting = table.mean()
    lines = [
        f"{len(table)} maneuvers; gap RMSE [m] after the adaptation seconds, to each maneuver's end",
        (f"  oracle (best setting per maneuver, in hindsight): mean {oracle.mean():.2f}, "
         f"median {oracle.median():.2f}"),
        (f"  adapted (setting estimated on the first seconds): mean "
         f"{adapted['gap_rmse_m'].mean():.2f}, median {adapted['gap_rmse_m'].median():.2f}"),
        *two_number_lines(settings),
        "  one setting for every maneuver: " + ", ".join(
            f"{tg:g} s {v:.2f}" for tg, v in by_setting.items()),
        "  per maneuver: best setting [s] / estimated style, T [s] and s0 [m]:"]
    est = adapted.set_index("maneuver_id")
    s0 = est["standstill_m"] if "standstill_m" in est else pd.Series(np.nan, est.index)
    lines += [f"    {m}: {best[m]:g} / {est['time_gap_s'].get(m, np.nan):.2f}, "
              f"{s0.get(m, np.nan):.1f}" for m in table.index]
    return "\n".join(lines)


def two_number_lines(settings: pd.DataFrame) -> list[str]:
    """The summary's lines on the best (time gap, standstill) per maneuver in hindsight, if
    ``settings`` holds more than one standstill distance."""
    if "standstill_m" not in settings or settings["standstill_m"].nunique() < 2:
        return []
    best = settings.loc[settings.groupby("maneuver_id")["gap_rmse_m"].idxmin()]
    return [(f"  oracle of two numbers (best time gap and standstill per maneuver, in "
             f"hindsight): mean {best['gap_rmse_m'].mean():.2f}, median "
             f"{best['gap_rmse_m'].median():.2f}"),
            "    best (T [s], s0 [m]) per maneuver: " + ", ".join(
                f"{r.maneuver_id} ({r.time_gap_s:g}, {r.standstill_m:g})"
                for r in best.itertuples())]


def setting_from_first(rows: pd.DataFrame, seconds: float, default_s: float) -> float:
    """The setting [s] ``replay --adapt-first-s seconds`` gives the ``safeil_median`` row (a
    planner of default setting ``default_s``) on one maneuver's ``rows``: the driver's shrunk
    median time gap on its first ``seconds`` (:func:`window_replays.driver_time_gap`), clipped
    to the trained range. (The ``safeil`` row's, from the (s0, T) estimator, is
    :func:`window_replays.driver_setting`.)"""
    return clip_time_gap(ra.driver_time_gap(rp.window(rows, 0.0, seconds), default_s))


def read_off(errors: pd.Series, setting_s: float) -> float:
    """A maneuver's gap RMSE [m] at ``setting_s``, interpolated linearly between its replays at
    the grid's settings (``errors`` indexed by setting [s]; outside the grid, its end value)."""
    return float(np.interp(setting_s, errors.index.to_numpy(float), errors.to_numpy(float)))


def adaptation_curve(rows: pd.DataFrame, settings: pd.DataFrame, defaults: dict[str, float],
                     observed: tuple[float, ...] = OBSERVED_S) -> pd.DataFrame:
    """How much a driver must be seen: for each number of seconds in ``observed``, the gap RMSE
    [m] over the same scored span (after the adaptation seconds of ``settings``) with the setting
    estimated from that many first seconds, read off each maneuver's grid of replays
    (:func:`read_off`); mean and median over the maneuvers. ``defaults``: each maneuver's
    planner's default setting [s]."""
    table = one_number(settings).pivot_table(index="maneuver_id", columns="time_gap_s",
                                             values="gap_rmse_m")
    out = []
    for seconds in observed:
        errors = np.array([read_off(table.loc[m], setting_from_first(
            rows[rows["maneuver_id"] == m].reset_index(drop=True), seconds, defaults[m]))
            for m in table.index])
        out.append({"observed_s": seconds, "gap_rmse_mean_m": float(np.mean(errors)),
                    "gap_rmse_median_m": float(np.median(errors))})
    return pd.DataFrame(out)


def fold_defaults(settings: pd.DataFrame) -> dict[str, float]:
    """Each maneuver's ``safeil`` default setting [s] (its checkpoint's style)."""
    from safeil_sumo.planners import registry as planner_registry

    default = {k: planner_registry.load(str(planner_of(k))).style["time_gap_s"]
               for k in settings["fold"].unique()}
    return {m: default[k] for m, k in zip(settings["maneuver_id"], settings["fold"],
                                          strict=True)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--grid", type=float, nargs="+", default=list(GRID_S), metavar="S",
                   help="time-gap settings to try [s]")
    p.add_argument("--standstill-grid", type=float, nargs="+", default=[0.0], metavar="M",
                   help="standstill distances [m] tried with every time gap of --grid (the "
                   "style is the line s0 + T v; default 0: the one-number setting)")
    p.add_argument("--adapt-first-s", type=float, default=lodo.ADAPT_S, metavar="S",
                   help="seconds left out of the score (adapted on) (default %(default)s)")
    p.add_argument("--source", choices=("openacc", "zalazone"), default="openacc",
                   help="openacc: the drivers the folds left out, each with its fold's safeil; "
                   "zalazone: every maneuver, unseen by the shipped safeil, in lane mode "
                   "(longitudinal only, as results --only unseen)")
    p.add_argument("--folds", type=int, default=4)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", type=Path, default=None,
                   help="default data/lodo/adaptation_bound[_zalazone]")
    p.add_argument("--from-csv", action="store_true",
                   help="summarise <out>/settings.csv and adapted.csv of an earlier run (no SUMO)")
    args = p.parse_args(argv)
    args.out = args.out or lodo.WORK / ("adaptation_bound" + (
        "" if args.source == "openacc" else f"_{args.source}"))
    rows, _ = process_drive(load_source(args.source), PipelineConfig(rate_hz=10.0))
    if args.from_csv:
        settings_df = pd.read_csv(args.out / "settings.csv")
        adapted_df = pd.read_csv(args.out / "adapted.csv")
    elif args.source == "zalazone":
        lane = ReplayConfig()
        lane = replace(lane, loop=replace(lane.loop, lateral="lane"))
        settings, adapted = grid_runs(rows, sorted(rows["maneuver_id"].unique()), SHIPPED,
                                      tuple(args.grid), args.adapt_first_s, args.out,
                                      args.workers, lane, tuple(args.standstill_grid))
        settings_df, adapted_df = pd.DataFrame(settings), pd.DataFrame(adapted)
    else:
        settings, adapted = [], []
        for k in range(args.folds):
            s, a = fold_runs(k, rows, tuple(args.grid), args.adapt_first_s, args.out,
                             args.workers, tuple(args.standstill_grid))
            settings += s
            adapted += a
            print(f"fold {k}: {len(a)} maneuvers", flush=True)
        settings_df, adapted_df = pd.DataFrame(settings), pd.DataFrame(adapted)
    if not args.from_csv:
        args.out.mkdir(parents=True, exist_ok=True)
        settings_df.to_csv(args.out / "settings.csv", index=False)
        adapted_df.to_csv(args.out / "adapted.csv", index=False)
    print(summary(settings_df, adapted_df))
    curve = adaptation_curve(rows, settings_df, fold_defaults(settings_df))
    curve.to_csv(args.out / "adaptation_curve.csv", index=False)
    print("setting estimated from a driver's first seconds (read off the grid): gap RMSE [m]")
    print("\n".join(f"  {r.observed_s:g} s: mean {r.gap_rmse_mean_m:.2f}, median "
                    f"{r.gap_rmse_median_m:.2f}" for r in curve.itertuples()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
