"""The ``efficiency`` section of ``python -m safeil_sumo.results``: SafeIL and BC trained on
growing random subsets of the synthetic training maneuvers (several seeds), each checkpoint's
curved500 completion and its gap RMSE on the OpenACC paper-like replay. It writes
``sample_efficiency.csv`` and ``sample_efficiency.png`` and its part of ``results/studies.md``
(:func:`efficiency_readme`); without torch it is skipped."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.experiments.sweep_executor import comparable
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.studies.paper_replay import paper_like_window
from safeil_sumo.studies.shared import (
    COLORS,
    LABELS,
    SHIPPED_DATA,
    md_table,
    pct,
    save_csv,
    section_sweep,
)


def efficiency(out: Path, work: Path, workers: int, fractions: list[float], seeds: list[int],
               scenarios: int) -> pd.DataFrame:
    from safeil_sumo.data.tuples import Tuples
    from safeil_sumo.learn.checkpoint import save_checkpoint, tuples_fingerprint
    from safeil_sumo.learn.torch_required import TORCH_MISSING, have_torch

    if not have_torch():  # this section trains; the runtime install has no torch
        print(f"[efficiency] skipped: {TORCH_MISSING}")
        return pd.DataFrame()
    from safeil_sumo.learn.trainer import TrainConfig, split_by_maneuver, train

    if not SHIPPED_DATA.is_file():
        print(f"[efficiency] skipped: {SHIPPED_DATA} missing (training/build_synthetic_dataset.py)")
        return pd.DataFrame()
    tuples = Tuples.load(SHIPPED_DATA)
    tr_all, va = split_by_maneuver(tuples, 0.2, 0)
    ids = np.array(sorted(tr_all.maneuvers))
    methods: dict[str, dict[str, Any]] = {
        "safeil": {"method": "safeil", "barrier_lateral": "bernstein"},
               "bc": {"method": "bc"}}
    ckpt_dir = work / "efficiency" / "checkpoints"
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    runs = []
    for frac in fractions:
        for s in seeds:
            k = max(2, round(frac * len(ids)))
            chosen = np.random.default_rng([s, k]).choice(ids, size=k, replace=False)
            sub = tr_all.subset(np.isin(tr_all.maneuver_id, chosen))
            for m, kw in methods.items():
                prefix = ckpt_dir / f"{m}_m{k:03d}_s{s}"
                if not prefix.with_suffix(".safetensors").is_file():
                    cfg = TrainConfig(seed=s, **kw)
                    model, hist = train(sub, va, cfg, progress=False)
                    save_checkpoint(prefix, model, name=m, horizon=tuples.horizon,
                                    train_config=cfg, data_fingerprint=tuples_fingerprint(sub),
                                    metrics={"maneuvers": k, "tuples": len(sub)}, history=hist)
                runs.append({"method": m, "maneuvers": k, "tuples": len(sub), "seed": s,
                             "checkpoint": str(prefix.with_suffix(".safetensors"))})
    runs_df = pd.DataFrame(runs)
    specs = [Task(ScenarioSpec(index=i, master_seed=0), PlannerRef(c))
             for c in runs_df["checkpoint"] for i in range(scenarios)]
    df = comparable(section_sweep(specs, work, "efficiency_sweep", workers))
    agg = df.groupby("policy").agg(completion_rate=("completed", "mean"),
                                   mean_path_completed=("path_completed", "mean")).reset_index()
    runs_df = runs_df.merge(agg, left_on="checkpoint", right_on="policy").drop(columns="policy")
    runs_df["replay_gap_rmse_m"] = _efficiency_replay(runs_df["checkpoint"].tolist(), work)
    table = runs_df.drop(columns="checkpoint")
    save_csv(table, out / "sample_efficiency.csv")
    _plot_efficiency(table, out / "sample_efficiency.png", scenarios)
    return table


def _efficiency_replay(checkpoints: list[str], work: Path) -> list[float]:
    """d_lead RMSE vs the human on the OpenACC paper-like maneuver (NaN without the data)."""
    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.planners import registry as pol

    try:
        mid, _, rows = paper_like_window("openacc")
    except (OSError, ValueError):
        return [math.nan] * len(checkpoints)
    policies = {c: pol.load(c) for c in checkpoints}
    result = rp.replay_maneuver(rows, policies, work / "efficiency" / "replay",
                                rp.ReplayConfig(), maneuver_id=mid)
    m = result.metrics.set_index("policy")
    return [float(m.loc[c, "rmse_gap"]) for c in checkpoints]


def _plot_efficiency(table: pd.DataFrame, path: Path, scenarios: int) -> None:
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for m, g in table.groupby("method"):
        g = g.groupby("maneuvers").agg(rate=("completion_rate", "mean"),
                                       rate_sd=("completion_rate", "std"),
                                       gap=("replay_gap_rmse_m", "mean"),
                                       gap_sd=("replay_gap_rmse_m", "std")).reset_index()
        color = COLORS[m]
        a.errorbar(g["maneuvers"], 100 * g["rate"], yerr=100 * g["rate_sd"].fillna(0), fmt="o-",
                   color=color, capsize=3, label=LABELS[m])
        b.errorbar(g["maneuvers"], g["gap"], yerr=g["gap_sd"].fillna(0), fmt="o-", color=color,
                   capsize=3, label=LABELS[m])
    a.set_xscale("log")
    b.set_xscale("log")
    a.set_xlabel("training maneuvers")
    b.set_xlabel("training maneuvers")
    a.set_ylabel(f"curved500 completed without a flag [%] ({scenarios} scenarios)")
    b.set_ylabel("replay gap RMSE vs human [m] (OpenACC)")
    a.set_title("Safety vs data (mean ± sd over seeds)", fontsize=9)
    b.set_title("Human-likeness vs data", fontsize=9)
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def efficiency_readme(facts: dict) -> list[str]:
    """Sample efficiency."""
    lines: list[str] = []
    eff = pd.DataFrame(facts["efficiency"])
    agg = eff.groupby(["method", "maneuvers"]).agg(
        tuples=("tuples", "mean"), rate=("completion_rate", "mean"),
        path=("mean_path_completed", "mean"), gap=("replay_gap_rmse_m", "mean"),
        seeds=("seed", "count")).reset_index()
    rows = [dict(r, method=LABELS.get(r["method"], r["method"]), rate=pct(r["rate"]),
                 path=f"{100 * r['path']:.1f} %") for r in agg.to_dict(orient="records")]
    lines += ["## Sample efficiency", "",
              ("SafeIL (exact lane bound) and BC trained on random subsets of the training "
              "maneuvers; curved500 completion and the OpenACC replay gap RMSE, mean over "
              "seeds."), "",
              md_table(rows, {"method": "method", "maneuvers": "maneuvers",
                              "tuples": "tuples", "seeds": "seeds", "rate": "completed",
                              "path": "mean path", "gap": "replay gap RMSE [m]"}),
              "", "![efficiency](sample_efficiency.png)", ""]
    return lines
