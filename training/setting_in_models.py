"""The gap regulation at every setting, without SUMO: is what is left the setting or the planner?

    python training/setting_in_models.py [--folds 4]

For each fold of ``training/leave_one_driver_out.py`` (its models in ``data/lodo/fold*/``), every
OpenACC maneuver is driven whole:

- by the fold's ``safeil`` in the differentiable loop model (``learn.closed_loop.rollout``: the
  planner, the tracker and the plant's lag behind the recorded leader), one episode per
  maneuver at each time-gap setting of ``SETTINGS_S``;
- by the fold's IDM in its own closed-trajectory simulation (``idm.evaluate_fit``), its T over
  ``IDM_T_S`` and the other four parameters as fitted.

Printed, on the left-out drivers' maneuvers: the gap RMSE at the shipped default setting / the
fitted T, at the best setting per maneuver chosen in hindsight, and at a default calibrated on
the fold's own OpenACC training maneuvers as ``fit_idm`` calibrates T (the setting with the
least pooled gap RMSE there). About 5 min on one core; ``--out`` keeps the tables (CSV).

``--idm-oracle-from-s S``: instead, how far the IDM's own numbers can go in hindsight on each
left-out maneuver from its S-th second to its end (the span ``adaptation_bound.py`` scores),
started from the recorded state there: its best T (``IDM_T_S``), its best (T, s0) (s0 over
``IDM_S0_M``), and all five parameters refitted on that very span; beside the fold's fit. About
2 min on one core.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.learn.torch_required import training_imports

with training_imports():  # without torch: one line that says what to install, no traceback
    import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "training"))
import leave_one_driver_out as lodo  # the folds' models and data, one source of truth

from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.sources import load_source
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import load_model
from safeil_sumo.learn.closed_loop import episodes_from_tuples, rollout
from safeil_sumo.planners import idm

SETTINGS_S = tuple(np.round(np.arange(0.8, 2.41, 0.1), 1))  # [s] the style input's settings
IDM_T_S = tuple(np.round(np.arange(0.4, 2.41, 0.1), 1))  # [s] the IDM's time gaps
IDM_S0_M = tuple(np.round(np.arange(0.5, 10.01, 0.5), 1))  # [m] its standstill distances


def safeil_rmse(checkpoint: Path, tuples: Tuples) -> pd.DataFrame:
    """Gap RMSE [m] of each whole maneuver (rows) at each setting (columns) in the loop model,
    with the maneuver's samples at 0.1 s (column ``steps``)."""
    model, meta = load_model(checkpoint)
    model.eval()
    settings = torch.tensor(SETTINGS_S, dtype=torch.float32)[:, None]
    rows = {}
    for mid in np.unique(tuples.maneuver_id):
        t = tuples.t[tuples.maneuver_id == mid]
        window = np.floor((t.max() - t.min()) * 10.0) / 10.0 - 0.1  # [s] the whole maneuver
        ep = episodes_from_tuples(tuples, window, stride_s=1e9, maneuvers={mid})
        # the maneuver's one episode, once per setting
        many = dataclasses.replace(ep.take(np.zeros(len(SETTINGS_S), dtype=int)), style=settings)
        with torch.no_grad():
            gap = rollout(model, many, horizon=float(meta["horizon_s"]))["gap"]
        rmse = (gap - many.gap_human).pow(2).mean(1).sqrt().numpy()
        rows[str(mid)] = {"steps": many.v_human.shape[1],
                          **dict(zip(SETTINGS_S, rmse.tolist(), strict=True))}
    return pd.DataFrame.from_dict(rows, orient="index")


def idm_rmse(fit: idm.IDMParams, maneuvers: list[idm.Maneuver]) -> pd.DataFrame:
    """Gap RMSE [m] of each whole maneuver at each T of ``IDM_T_S`` and at the fitted T."""
    rows = {}
    for m in maneuvers:
        r = {t: idm.evaluate_fit([m], dataclasses.replace(fit, time_gap_s=t))[0] for t in IDM_T_S}
        rows[m.maneuver_id] = {**r, "fitted": idm.evaluate_fit([m], fit)[0]}
    return pd.DataFrame.from_dict(rows, orient="index")


def idm_oracles(fit: idm.IDMParams, m: idm.Maneuver, from_s: float) -> dict[str, float]:
    """Gap RMSE [m] of the IDM on ``m`` from its ``from_s``-th second to its end: as fitted,
    at its best T, at its best (T, s0), and with all five parameters refitted on that span
    (each chosen on the very span it is scored on: oracles)."""
    keep = m.times >= m.times[0] + from_s
    span = idm.Maneuver(m.maneuver_id, m.times[keep], m.v[keep], m.gap[keep], m.v_lead[keep])

    def rmse(p: idm.IDMParams) -> float:
        return idm.evaluate_fit([span], p)[0]

    by_t = {t: rmse(dataclasses.replace(fit, time_gap_s=t)) for t in IDM_T_S}
    by_line = [rmse(dataclasses.replace(fit, time_gap_s=t, s0_m=s0))
               for t in IDM_T_S for s0 in IDM_S0_M]
    return {"idm_fitted_m": rmse(fit), "idm_best_t_m": min(by_t.values()),
            "idm_best_t_s0_m": min(by_line),
            "idm_refit_on_span_m": rmse(idm.fit_idm([span], seed=0).params)}


def idm_oracle_table(from_s: float, folds: int) -> pd.DataFrame:
    """:func:`idm_oracles` of every fold's left-out OpenACC maneuvers at least ``from_s`` + 20 s
    long, with the fold's own IDM fit."""
    rows, _ = process_drive(load_source("openacc"), PipelineConfig(rate_hz=10.0))
    maneuvers = {m.maneuver_id: m for m in idm.maneuvers_from_rows(rows)}
    out = {}
    for k in range(folds):
        fold = lodo.WORK / f"fold{k}"
        held = set(json.loads((fold / "held_out.json").read_text())) & set(maneuvers)
        fit = idm.IDMParams(**json.loads((fold / "idm.json").read_text())["fits"]["openacc"]["params"])
        for mid in sorted(held):
            m = maneuvers[mid]
            if m.times[-1] - m.times[0] >= from_s + 20.0:
                out[mid] = {"fold": k, **idm_oracles(fit, m, from_s)}
    return pd.DataFrame.from_dict(out, orient="index")


def pooled_best(table: pd.DataFrame) -> float:
    """The setting with the least pooled (sample-weighted) gap RMSE over the table's rows."""
    cols = list(SETTINGS_S)
    pooled = (table[cols] ** 2).mul(table["steps"], axis=0).sum() / table["steps"].sum()
    return float(pooled.idxmin())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--out", type=Path, default=None, help="folder for the per-maneuver CSVs")
    ap.add_argument("--idm-oracle-from-s", type=float, default=None, metavar="S",
                    help="the IDM's hindsight oracles from each maneuver's S-th second instead")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.idm_oracle_from_s is not None:
        oracles = idm_oracle_table(args.idm_oracle_from_s, args.folds)
        print(oracles.round(2).to_string())
        print(f"\n{len(oracles)} maneuvers, mean [m]:",
              oracles.drop(columns="fold").mean().round(2).to_dict())
        return 0
    all_tuples = Tuples.load(lodo.tuples_path("openacc"))
    rows, _ = process_drive(load_source("openacc"), PipelineConfig(rate_hz=10.0))
    idm_maneuvers = {m.maneuver_id: m for m in idm.maneuvers_from_rows(rows)}
    out = []
    for k in range(args.folds):
        fold = lodo.WORK / f"fold{k}"
        held = set(json.loads((fold / "held_out.json").read_text()))
        sidecar = json.loads((fold / "safeil.json").read_text())
        default = round(float(sidecar["style_default"]["time_gap_s"]), 1)
        train = safeil_rmse(fold / "safeil.safetensors", Tuples.load(fold / "openacc_tuples.parquet"))
        test = safeil_rmse(fold / "safeil.safetensors", all_tuples)
        test = test[test.index.isin(held)]
        calibrated = pooled_best(train)
        fit = idm.IDMParams(**json.loads((fold / "idm.json").read_text())["fits"]["openacc"]["params"])
        idm_test = idm_rmse(fit, [idm_maneuvers[m] for m in sorted(held & set(idm_maneuvers))])
        s_cols, t_cols = list(SETTINGS_S), list(IDM_T_S)
        table = pd.DataFrame({
            "fold": k,
            "safeil_default_m": test[default], "safeil_calibrated_m": test[calibrated],
            "safeil_best_m": test[s_cols].min(axis=1),
            "safeil_best_setting_s": test[s_cols].idxmin(axis=1),
            "idm_fitted_m": idm_test["fitted"], "idm_best_m": idm_test[t_cols].min(axis=1),
            "idm_best_t_s": idm_test[t_cols].idxmin(axis=1),
            "default_s": default, "calibrated_s": calibrated, "idm_t_s": fit.time_gap_s})
        out.append(table)
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            train.to_csv(args.out / f"fold{k}_safeil_training.csv")
            test.to_csv(args.out / f"fold{k}_safeil_left_out.csv")
            idm_test.to_csv(args.out / f"fold{k}_idm_left_out.csv")
    table = pd.concat(out)
    print(table.round(2).to_string())
    cols = ["safeil_default_m", "safeil_calibrated_m", "safeil_best_m", "idm_fitted_m",
            "idm_best_m"]
    print("\nmean  ", table[cols].mean().round(2).to_dict())
    print("median", table[cols].median().round(2).to_dict())
    return 0


if __name__ == "__main__":
    sys.exit(main())
