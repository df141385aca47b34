"""The ``large`` and ``grids`` sections of ``python -m safeil_sumo.results``: many curved500
scenarios per planner with and without the safety filter (``safety_large.csv``,
``safety_large.png``), and the radius, braking-leader, sensor-noise and initial-gap grids
(``grid_<name>.csv``, ``grid_<name>.png``), with Wilson 95 % intervals, and their parts of
``results/studies.md`` (:func:`large_readme`, :func:`grids_readme`)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.experiments.stats import breakdown
from safeil_sumo.experiments.sweep_executor import comparable
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.studies.shared import (
    COLORS,
    LABELS,
    POLICIES,
    md_table,
    pct,
    save_csv,
    section_sweep,
)

NO_FILTER = ("analytic", "idm")  # rule-based planners: never run with the safety filter
DEFAULT_LARGE_N = 1000  # [-] scenarios of the default planner without the filter (the target)


def large(out: Path, work: Path, workers: int, seed: int, n: int) -> pd.DataFrame:
    # the shipped default without the filter gets at least 1,000 scenarios: its target is stated
    # over 1,000; the other bars keep n
    def count(p: str, f: bool) -> int:
        return max(n, DEFAULT_LARGE_N) if (p == "safeil" and not f and n >= 100) else n

    specs = [Task(ScenarioSpec(net="curved500", index=i, master_seed=seed + 1),
                  PlannerRef(p, safety_filter=f))
             for p in POLICIES for f in (False, True) for i in range(count(p, f))
             if not (p in NO_FILTER and f)]
    df = comparable(section_sweep(specs, work, "large", workers))
    table = breakdown(df, by=["policy", "safety_filter"])
    save_csv(table, out / "safety_large.csv")
    _plot_rates(table, out / "safety_large.png",
                f"curved500, {n} scenarios per bar (leader 25-32 m/s): completion with 95 % CI",
                lambda r: f"{LABELS[r['policy']]}" + (" + filter" if r["safety_filter"] else ""))
    return table


def _plot_rates(table: pd.DataFrame, path: Path, title: str,
                label: Callable[..., str]) -> None:
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(table) + 1.5))
    y = np.arange(len(table))[::-1]
    rate = 100 * table["completion_rate"].to_numpy()
    err = np.vstack([rate - 100 * table["ci_low"], 100 * table["ci_high"] - rate])
    colors = [COLORS.get(p, "tab:blue") for p in table["policy"]]
    ax.barh(y, rate, xerr=err, color=colors, alpha=0.85, capsize=3)
    ax.set_yticks(y)
    ax.set_yticklabels([label(r) for _, r in table.iterrows()], fontsize=8)
    ax.set_xlim(0, 100)
    ax.set_xlabel("scenarios completed without a flag [%] (Wilson 95 % interval)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def grids(out: Path, work: Path, workers: int, seed: int, n: int) -> dict[str, pd.DataFrame]:
    learned = ("safeil", "safeil_paper", "bc")
    groups: dict[str, tuple[list[Task], list[str]]] = {
        "radius": ([Task(ScenarioSpec(net=f"curved{r}", index=i, master_seed=seed + 2),
                         PlannerRef(p))
                    for r in (300, 500, 750, 1000) for p in learned for i in range(n)],
                   ["policy", "radius_m"]),
        "braking": ([Task(ScenarioSpec(index=i, master_seed=seed + 3, leader_kind="braking"),
                          PlannerRef(p, safety_filter=f))
                     for p in learned for f in (False, True) for i in range(n)],
                    ["policy", "safety_filter"]),
        "noise": ([Task(ScenarioSpec(index=i, master_seed=seed + 4, radar_noise_m=rn,
                                     lane_noise_c0_m=ln), PlannerRef(p))
                   for p in learned for rn, ln in ((0.0, 0.0), (0.5, 0.05), (1.0, 0.15))
                   for i in range(n)],
                  ["policy", "radar_noise_m", "lane_noise_c0_m"]),
        "gap": ([Task(ScenarioSpec(index=i, master_seed=seed + 5, initial_gap_m=(15.0, 80.0)),
                      PlannerRef(p))
                 for p in learned for i in range(n)], ["policy"]),
    }
    tables = {}
    for name, (specs, by) in groups.items():
        df = comparable(section_sweep(specs, work, f"grid_{name}", workers))
        table = breakdown(df, by=by)
        save_csv(table, out / f"grid_{name}.csv")
        tables[name] = table
    _plot_radius(tables["radius"], out / "grid_radius.png", n)
    for name in ("braking", "noise", "gap"):
        t = tables[name]
        keys = [c for c in t.columns[: list(t.columns).index("n")] if c != "policy"]
        _plot_rates(t, out / f"grid_{name}.png",
                    f"curved500, {name}: {n} scenarios per bar",
                    lambda r, keys=keys: LABELS[r["policy"]] + "".join(
                        f", {k}={r[k]}" for k in keys))
    return tables


def _plot_radius(table: pd.DataFrame, path: Path, n: int) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    for p, g in table.groupby("policy", sort=False):
        g = g.sort_values("radius_m")
        r = g["radius_m"].to_numpy()
        ax.plot(r, 100 * g["completion_rate"], "o-", color=COLORS[p], label=LABELS[p])
        ax.fill_between(r, 100 * g["ci_low"], 100 * g["ci_high"], color=COLORS[p], alpha=0.15)
    ax.set_xlabel("track radius of the ego lane [m]")
    ax.set_ylabel("completed without a flag [%]")
    ax.set_title(f"Completion vs curvature ({n} scenarios per point, 95 % CI)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def large_readme(facts: dict, args: dict) -> list[str]:
    """Many curved500 scenarios, with and without the safety filter."""
    lines: list[str] = []
    rows = [dict(r, planner=LABELS.get(r["policy"], r["policy"]),
                 rate=pct(r["completion_rate"], r["ci_low"], r["ci_high"]),
                 path=f"{100 * r['mean_path_completed']:.1f} %",
                 filt="on" if r["safety_filter"] else "off") for r in facts["large"]]
    lines += ["## Many scenarios, with and without the safety filter", "",
              (f"{args.get('large', '?')} scenarios per row (SafeIL without the filter: "
              f"{DEFAULT_LARGE_N}; master seed {args.get('seed', 0) + 1}); rate with its "
              "Wilson 95 % interval."), "",
              md_table(rows, {"planner": "planner", "filt": "filter", "completed":
                              "completed", "ok": "of", "rate": "rate [95 % CI]",
                              "path": "mean path", "flags": "first flags"}),
              "", "![large](safety_large.png)", ""]
    return lines


def grids_readme(facts: dict, args: dict) -> list[str]:
    """The grids: where each planner fails."""
    lines: list[str] = []
    lines += ["## Where each planner fails (grids)", "",
              f"{args.get('grid', '?')} scenarios per cell; tables `grid_*.csv`.", ""]
    for name, records in facts["grids"].items():
        keys = [k for k in ("radius_m", "safety_filter", "radar_noise_m", "lane_noise_c0_m")
                if records and k in records[0]]
        rows = [dict(r, planner=LABELS.get(r["policy"], r["policy"]),
                     rate=pct(r["completion_rate"], r["ci_low"], r["ci_high"]),
                     path=f"{100 * r['mean_path_completed']:.1f} %") for r in records]
        lines += [f"### {name}", "", md_table(
            rows, {"planner": "planner", **{k: k for k in keys}, "rate": "rate [95 % CI]",
                   "path": "mean path", "flags": "first flags"}),
            "", f"![{name}](grid_{name}.png)", ""]
    return lines
