"""Per-driver equilibrium: does a planner set to a driver's style keep that driver's time gap
in each speed band? (issue 42's per-driver instrument)

    python training/per_driver_equilibrium.py [--data-dir ../shared/data] [--workers 2]
                                               [--out results/per_driver]

For every driver of OpenACC (Vicolungo), ZalaZone and NGSIM I-80 (``data.sources.driver_of``)
with steady following (the gap probe's human definition, ``experiments.gap_step_responses.
steady_following``) in at least two of the gap probe's speed bands (15, 25, 35 ± 3 m/s, at
least :data:`MIN_SAMPLES` samples each):

- the driver's own median time gap per band;
- the driver's (s0, T) from all their steady samples (``learn.style_estimator``, the population
  prior), and the planners set to it as an adapted replay sets them
  (``experiments.window_replays.adapt_planners``): the shipped ``safeil`` gets the line, its
  setting following the speed (``checkpoint_style``), the IDM s0 and T (its v0, a, b, delta as
  calibrated); ``safeil`` at one setting, the line's time gap at the mean speed seen (the
  ``safeil_one_setting`` row of the replays), beside them;
- each planner's equilibrium time gap per band: ``safeil``'s from a SUMO step response (the gap
  probe's ``close`` start behind a leader at the band's speed, its final-window time gap), the
  IDM's from its equilibrium gap in closed form (``idm.equilibrium_gap``); ``safeil``
  unadapted (its default setting) beside them.

Writes ``per_driver.csv`` (one row per driver and band) and ``summary.md`` (the share of
(driver, band) pairs within ±0.2 s of the driver's median, per planner).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.sources import DEFAULT_DATA_DIR, driver_of, load_source
from safeil_sumo.experiments import gap_step_responses as gp
from safeil_sumo.experiments.sweep_executor import run_sweep
from safeil_sumo.experiments.window_replays import (
    checkpoint_style,
    driver_style,
    idm_style_params,
)
from safeil_sumo.planners import idm
from safeil_sumo.planners import registry as pol
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import Task

SOURCES = ("openacc", "zalazone", "ngsim")
MIN_SAMPLES = 100  # [-] steady samples (10 s at 10 Hz) for a driver's band median
TOLERANCE_S = 0.2  # [s] the per-driver equilibrium target
KIND = "close"  # the gap probe's start that settles from closer than the planner's gap


def driver_rows(data_dir: Path) -> pd.DataFrame:
    """The pipeline's maneuver rows (10 Hz) of every source, with ``source`` and ``driver``."""
    frames = []
    for source in SOURCES:
        rows, _ = process_drive(load_source(source, data_dir), PipelineConfig(rate_hz=10.0))
        ids = rows["maneuver_id"].astype(str)
        drivers = {m: driver_of(source, m, data_dir) for m in ids.unique()}
        frames.append(rows.assign(source=source, driver=ids.map(drivers)))
    return pd.concat(frames, ignore_index=True)


def driver_bands(rows: pd.DataFrame) -> pd.DataFrame:
    """Per driver and speed band with at least :data:`MIN_SAMPLES` steady samples: the
    driver's median time gap [s] and the samples; only drivers with two bands or more."""
    steady = gp.steady_following(rows)
    v = rows["v_x"].to_numpy(float)
    tg = gp.time_gap(rows["lead_x"].to_numpy(float), v)
    out = []
    for speed in gp.SPEEDS_MPS:
        sel = steady & (np.abs(v - speed) <= gp.HUMAN_BAND_MPS) & np.isfinite(tg)
        for driver, g in pd.Series(tg[sel]).groupby(rows["driver"].to_numpy()[sel]):
            if len(g) >= MIN_SAMPLES:
                out.append({"driver": driver, "speed_mps": speed, "samples": len(g),
                            "driver_median_s": float(g.median())})
    table = pd.DataFrame(out)
    counts = table.groupby("driver")["speed_mps"].transform("size")
    return table[counts >= 2].reset_index(drop=True)


def driver_settings(rows: pd.DataFrame, drivers: list[str]) -> pd.DataFrame:
    """Per driver: the (s0, T) estimate of all their rows (maneuvers in order, each one's time
    shifted after the last so the estimator sees one drive), ``safeil``'s style (the line) and
    one setting, and the IDM's s0 and T set to it."""
    shipped_idm = pol.load("idm")
    out = []
    for driver in drivers:
        parts, end = [], 0.0
        for _, m in rows[rows["driver"] == driver].groupby("maneuver_id", sort=True):
            m = m.sort_values("time")
            parts.append(m.assign(time=m["time"] - m["time"].iloc[0] + end))
            end = float(parts[-1]["time"].iloc[-1]) + 60.0  # a minute apart: no false accel
        est = driver_style(pd.concat(parts, ignore_index=True))
        params = idm_style_params(shipped_idm.params, est)
        style = checkpoint_style(est, float("nan"))
        out.append({"driver": driver, "s0_m": float(est.mean[0]), "T_s": float(est.mean[1]),
                    "steady_samples": est.samples, "mean_speed_mps": est.mean_speed_mps,
                    "safeil_T_s": style["time_gap_s"],
                    "safeil_s0_m": style.get("standstill_m", float("nan")),
                    "safeil_setting_s": est.setting_s(est.mean_speed_mps),
                    "idm_s0_m": params.s0_m, "idm_T_s": params.time_gap_s})
    return pd.DataFrame(out)


def safeil_equilibria(pairs: pd.DataFrame, out: Path, workers: int) -> pd.Series:
    """``safeil``'s equilibrium time gap [s] per row of ``pairs`` (``speed_mps``, ``setting_s``
    and ``standstill_m``, NaN: its default setting, no standstill distance): the gap probe's
    final-window time gap."""
    specs = []
    for k, r in enumerate(pairs.itertuples()):
        setting = None if np.isnan(r.setting_s) else float(r.setting_s)
        s0 = None if np.isnan(r.standstill_m) else float(r.standstill_m)
        specs.append(Task(gp.probe_scenario(KIND, float(r.speed_mps), seed=k),
                          PlannerRef("safeil", time_gap_s=setting, standstill_m=s0)))
    records = run_sweep(specs, out / "runs", workers=workers, progress=True,
                        task_fn=gp.run_probe_task)
    table = gp.table(records)
    return pd.Series(table["eq_time_gap_s"].to_numpy(float), index=pairs.index)


def summary(table: pd.DataFrame) -> list[str]:
    lines = ["| planner | (driver, band) pairs | within ±0.2 s | share | median abs error [s] |",
             "|---|---:|---:|---:|---:|"]
    for col, name in (("safeil_eq_s", "`safeil` set to the driver's line"),
                      ("safeil_one_setting_eq_s", "`safeil` at one setting"),
                      ("safeil_default_eq_s", "`safeil` unadapted"),
                      ("idm_eq_s", "IDM set to the driver (closed form)")):
        err = (table[col] - table["driver_median_s"]).abs()
        ok = int((err <= TOLERANCE_S).sum())
        lines.append(f"| {name} | {len(table)} | {ok} | {ok / len(table):.0%} | "
                     f"{err.median():.2f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("results") / "per_driver")
    args = ap.parse_args(argv)
    rows = driver_rows(args.data_dir)
    bands = driver_bands(rows)
    settings = driver_settings(rows, sorted(bands["driver"].unique()))
    table = bands.merge(settings, on="driver")
    pairs = pd.concat([table.assign(setting_s=table["safeil_T_s"],
                                    standstill_m=table["safeil_s0_m"]),
                       table.assign(setting_s=table["safeil_setting_s"], standstill_m=np.nan),
                       table.assign(setting_s=np.nan, standstill_m=np.nan)], ignore_index=True)
    eq = safeil_equilibria(pairs, args.out, args.workers)
    n = len(table)
    table["safeil_eq_s"] = eq.iloc[:n].to_numpy()
    table["safeil_one_setting_eq_s"] = eq.iloc[n:2 * n].to_numpy()
    table["safeil_default_eq_s"] = eq.iloc[2 * n:].to_numpy()
    table["idm_eq_s"] = [float(idm.equilibrium_gap(r.speed_mps, dataclasses.replace(
        pol.load("idm").params, s0_m=r.idm_s0_m, time_gap_s=r.idm_T_s))) / r.speed_mps
        for r in table.itertuples()]
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "per_driver.csv", index=False)
    head = (f"`python training/per_driver_equilibrium.py`: {table['driver'].nunique()} "
            f"drivers with steady following in two speed bands or more, {n} (driver, band) "
            "pairs; every row in `per_driver.csv`.")
    text = ["# Per-driver equilibrium", "", head, "", *summary(table), ""]
    (args.out / "summary.md").write_text("\n".join(text))
    print("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
