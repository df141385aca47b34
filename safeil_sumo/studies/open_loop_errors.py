"""The ``openloop`` section of ``python -m safeil_sumo.results``: each method (SafeIL with the
exact lane bound, SafeIL with the paper's barrier, BC) trained on each dataset with 20 % of its
maneuvers held out, and its plans' errors and constraint margins on them. It writes
``openloop.csv`` (the checkpoints stay in the work folder) and its part of
``results/studies.md`` (:func:`openloop_readme`); without torch it is skipped."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from safeil_sumo.studies.shared import LABELS, REPO, SHIPPED_DATA, md_table, save_csv

OPENLOOP_KEYS = ("cp_rmse", "ade", "fde", "ade_lateral", "violation_rate_any_cp",
                 "violation_rate_lateral_bern", "violation_rate_any_spline",
                 "min_margin_left_spline", "min_margin_right_spline", "min_margin_lead_spline",
                 "target_violation_rate_lateral_cp", "target_violation_rate_lateral_bern",
                 "target_violation_rate_lateral_spline")


def openloop(out: Path, work: Path) -> pd.DataFrame:
    """Per method and dataset: errors and constraint margins on held-out maneuvers."""
    from safeil_sumo.data.tuples import Tuples
    from safeil_sumo.learn.checkpoint import save_checkpoint, tuples_fingerprint
    from safeil_sumo.learn.inference import load_policy
    from safeil_sumo.learn.open_loop_metrics import open_loop_metrics
    from safeil_sumo.learn.torch_required import TORCH_MISSING, have_torch

    if not have_torch():  # this section trains; the runtime install has no torch
        print(f"[openloop] skipped: {TORCH_MISSING}")
        return pd.DataFrame()
    from safeil_sumo.learn.trainer import TrainConfig, split_by_maneuver, train

    datasets = {"synthetic": SHIPPED_DATA, "ngsim": REPO / "data" / "ngsim_tuples.parquet",
                "openacc": REPO / "data" / "openacc_tuples.parquet"}
    methods: dict[str, dict[str, Any]] = {
        "safeil": {"method": "safeil", "barrier_lateral": "bernstein"},
               "safeil_paper": {"method": "safeil"}, "bc": {"method": "bc"}}
    rows = []
    for data_name, path in datasets.items():
        if not path.is_file():
            print(f"[openloop] {data_name} skipped: {path} missing (training/build_*_datasets)")
            continue
        tuples = Tuples.load(path)
        tr, va = split_by_maneuver(tuples, 0.2, 0)
        for m, kw in methods.items():
            prefix = work / "openloop" / f"{data_name}_{m}"
            if not prefix.with_suffix(".safetensors").is_file():
                prefix.parent.mkdir(parents=True, exist_ok=True)
                cfg = TrainConfig(seed=0, **kw)
                model, hist = train(tr, va, cfg, progress=False)
                save_checkpoint(prefix, model, name=m, horizon=tuples.horizon, train_config=cfg,
                                data_fingerprint=tuples_fingerprint(tuples),
                                metrics={"seconds": hist.seconds}, history=hist)
            om = open_loop_metrics(load_policy(prefix), va)
            rows.append({"dataset": data_name, "method": m, "train_tuples": len(tr),
                         "val_tuples": len(va), "val_maneuvers": len(va.maneuvers),
                         **{k: om[k] for k in OPENLOOP_KEYS}})
    table = pd.DataFrame(rows)
    if len(table):
        save_csv(table, out / "openloop.csv")
    return table


def openloop_readme(facts: dict) -> list[str]:
    """Open loop on held-out maneuvers."""
    lines: list[str] = []
    rows = [dict(r, planner=LABELS.get(r["method"], r["method"])) for r in facts["openloop"]]
    lines += ["## Open loop: held-out maneuvers", "",
              ("Each method trained on each dataset (seed 0, 20 % of maneuvers held out). "
              "Errors of the plan against the demonstrated 5 s future; constraint violation "
              "rates at the control points (paper), of the exact Bernstein bound, and at 50 "
              "points sampled along the spline (the truth); `target_*`: the same checks on "
              "the human's own plans — on curves the paper's control-point test rejects "
              "human plans that stay inside the lane."), "",
              md_table(rows, {"dataset": "data", "planner": "planner",
                              "val_maneuvers": "held-out maneuvers", "cp_rmse":
                              "cp RMSE [m]", "ade": "ADE [m]", "fde": "FDE [m]",
                              "ade_lateral": "lateral ADE [m]",
                              "violation_rate_any_cp": "viol. cp",
                              "violation_rate_lateral_bern": "viol. Bernstein",
                              "violation_rate_any_spline": "viol. spline",
                              "target_violation_rate_lateral_cp": "human viol. cp",
                              "target_violation_rate_lateral_spline":
                              "human viol. spline"}), ""]
    return lines
