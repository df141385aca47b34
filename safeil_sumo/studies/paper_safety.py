"""The ``safety`` section of ``python -m safeil_sumo.results``: the paper's Fig. "Safety
Performance" (curved500, 10 scenarios, the leader at a constant random speed in [25, 32] m/s)
for the shipped planners, beside the paper's own bars. It writes ``safety_curved500.csv`` and
``safety_curved500.png``, and its part of ``results/README.md`` (:func:`safety_readme`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from safeil_sumo.experiments.sweep_executor import comparable
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.studies.shared import COLORS, LABELS, POLICIES, md_table, save_csv, section_sweep

# The paper's Fig. "Safety Performance" (path completed before the first flag, scenarios 1..10)
PAPER_SAFEIL = (1, 1, 1, 0.243652537072041, 1, 0.251206141365427, 0.286587934750144, 1, 1, 1)
PAPER_BC = (0.305120983855612, 0.085567405490334, 0.24590380413413, 0.188162182557627,
            0.386465200991958, 0.374438391522503, 0.121543460031289, 0.512563164392433,
            0.529482717115704, 0.442272382240267)


def safety(out: Path, work: Path, workers: int, seed: int) -> dict:
    specs = [Task(ScenarioSpec(net="curved500", index=i, master_seed=seed), PlannerRef(p))
             for p in POLICIES for i in range(10)]
    df = comparable(section_sweep(specs, work, "safety", workers))
    cols = ["policy", "index", "leader_speed_mps", "path_completed", "completed", "flag",
            "flag_time_s", "min_ttc_s", "min_gap_m", "max_abs_lateral_offset_m", "end_reason"]
    table = df[cols].sort_values(["policy", "index"])
    save_csv(table, out / "safety_curved500.csv")

    fig, ax = plt.subplots(figsize=(11, 4.5))
    bars: list[tuple[str, Any, str, str | None]] = [
            ("paper: SafeIL", PAPER_SAFEIL, "tab:green", "//"),
            ("paper: BC", PAPER_BC, "tab:red", "//")]
    for p in POLICIES:
        sub = df[df["policy"] == p].sort_values("index")
        bars.append((f"ours: {LABELS[p]}", sub["path_completed"].to_numpy(), COLORS[p], None))
    width = 0.8 / len(bars)
    x = np.arange(1, 11)
    for k, (label, values, color, hatch) in enumerate(bars):
        ax.bar(x - 0.4 + (k + 0.5) * width, 100 * np.asarray(values), width, label=label,
               color=color, alpha=0.45 if hatch else 0.9, hatch=hatch, edgecolor="black", lw=0.4)
    ax.set_xticks(x)
    ax.set_xlabel("test scenario # (leader speeds differ between the paper and ours)")
    ax.set_ylabel("path completed before the first flag [%]")
    ax.set_title("Safety performance on the 500 m-radius track (paper Fig. 'Safety Performance')")
    ax.legend(fontsize=7, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.08))
    fig.tight_layout()
    fig.savefig(out / "safety_curved500.png", dpi=120)
    plt.close(fig)

    summary = {}
    for p in POLICIES:
        sub = df[df["policy"] == p]
        summary[p] = {"completed": int(sub["completed"].sum()), "n": len(sub),
                      "mean_path_completed": float(sub["path_completed"].mean()),
                      "flags": sub["flag"].fillna("").replace("", "none").value_counts().to_dict()}
    summary["paper_safeil"] = {"completed": sum(v == 1 for v in PAPER_SAFEIL), "n": 10,
                               "mean_path_completed": float(np.mean(PAPER_SAFEIL)),
                               "flags": {"TTC (scenarios 4, 6, 7: leader near 25 m/s)": 3}}
    summary["paper_bc"] = {"completed": sum(v == 1 for v in PAPER_BC), "n": 10,
                           "mean_path_completed": float(np.mean(PAPER_BC)),
                           "flags": {"lane exit / lost leader": 10}}
    return summary


def safety_readme(facts: dict) -> list[str]:
    """The paper's safety test: our planners beside the paper's."""
    lines: list[str] = []
    s = facts["safety"]
    rows = [{"who": "paper", "planner": "SafeIL", **s["paper_safeil"]},
            {"who": "paper", "planner": "BC", **s["paper_bc"]}]
    rows += [{"who": "ours", "planner": LABELS[p], **s[p]} for p in POLICIES if p in s]
    for r in rows:
        r["done"] = f"{r['completed']}/{r['n']}"
        r["mean"] = f"{100 * r['mean_path_completed']:.1f} %"
        r["why"] = ", ".join(f"{k}: {v}" for k, v in r.get("flags", {}).items()
                             if k != "none") or "–"
    lines += ["## Safety on the 500 m-radius track (the paper's Fig. 'Safety Performance')",
              "", ("curved500, 10 scenarios, leader at a constant random speed in [25, 32] "
              "m/s, ego from 30 m/s with a 50 m gap; flag = lane exit or TTC ≤ 1 s."), "",
              md_table(rows, {"who": "", "planner": "planner", "done": "completed",
                              "mean": "mean path completed", "why": "first flags"}),
              "", "![safety](safety_curved500.png)", "",
              ("Per scenario: `safety_curved500.csv` (leader speed, path completed, flag and "
              "its time, min TTC, min gap, max lateral offset)."), ""]
    return lines
