"""The ``leader`` section of ``python -m safeil_sumo.results``: does each planner's plan respond
to its leader? The static leader probe on a grid of states (``leader_probe.csv``) and the
leader-response suite in SUMO (``leader_suite.csv``, ``leader_suite.png``), and their part of
``results/studies.md`` (:func:`leader_readme`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.studies.shared import COLORS, LABELS, POLICIES, md_table, save_csv, section_sweep


def leader(out: Path, work: Path, workers: int, seed: int, variants: int) -> dict:
    """The static probe and the leader-response suite, every planner."""
    from safeil_sumo.experiments import suite
    from safeil_sumo.experiments.leader_probe import probe
    from safeil_sumo.planners import registry as pol

    probes = []
    for p in POLICIES:
        summary, _ = probe(pol.load(p))
        probes.append({**summary, "policy": p})
    probe_table = pd.DataFrame(probes)
    save_csv(probe_table, out / "leader_probe.csv")
    df = section_sweep(suite.suite_tasks(list(POLICIES), seed + 6, variants), work, "suite",
                       workers)
    table = suite.aggregate(df[df["status"] == "ok"])
    save_csv(table, out / "leader_suite.csv")
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    fams = list(suite.FAMILIES)
    width = 0.8 / len(POLICIES)
    for k, p in enumerate(POLICIES):
        g = table[table["policy"] == p].set_index("family").reindex(fams)
        x = np.arange(len(fams)) - 0.4 + (k + 0.5) * width
        axes[0].bar(x, g["flags_avoidable"], width, color=COLORS[p], label=LABELS[p])
        axes[0].bar(x, g["collisions"], width, color="black", alpha=0.5)
        axes[1].bar(x, g["min_time_gap_s"], width, color=COLORS[p], label=LABELS[p])
    for ax, ylabel in zip(axes, ("avoidable flags (black: collisions)", "min time gap [s]"),
                          strict=True):
        ax.set_xticks(np.arange(len(fams)))
        ax.set_xticklabels(fams, fontsize=8)
        ax.set_ylabel(ylabel)
    axes[0].legend(fontsize=7)
    axes[0].set_title(f"leader-response suite: {2 * variants} scenarios per family", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "leader_suite.png", dpi=120)
    plt.close(fig)
    return {"probe": probe_table.to_dict(orient="records"),
            "suite": table.to_dict(orient="records"), "variants": variants}


def leader_readme(facts: dict) -> list[str]:
    """The static leader probe and the leader-response suite."""
    lines: list[str] = []
    lead = facts["leader"]
    rows = [dict(r, planner=LABELS.get(r["policy"], r["policy"])) for r in lead["probe"]]
    lines += ["## Does the plan respond to the leader? (static probe)", "",
              ("`python -m safeil_sumo.probe`: one plan per state of a grid (ego 15-35 m/s, "
              "leader 10 m/s slower to 5 m/s faster, gap 8-120 m); on the states where "
              "braking at 6 m/s² avoids the leader, the share of plans whose trajectory "
              "runs past the leader's predicted position, and the (speed, leader speed) "
              "pairs whose planned end position shrinks as the gap grows."), "",
              md_table(rows, {"planner": "planner", "pass_rate": "passes the leader",
                              "gap_monotone_violations": "non-monotone pairs (of 117)",
                              "max_end_x_decrease_m": "largest decrease [m]",
                              "end_speed_v30_lead25_gap10":
                                  "end speed, 30 m/s behind 25 m/s at 10 m [m/s]",
                              "end_speed_v30_lead25_gap50": "… at 50 m [m/s]"}), ""]
    rows = [dict(r, planner=LABELS.get(r["policy"], r["policy"])) for r in lead["suite"]]
    lines += ["## Leader-response suite", "",
              (f"`python -m safeil_sumo.sweep --suite leader-response` ({lead['variants']} "
              "variants per family on straight and curved500; families in "
              "`safeil_sumo/experiments/suite.py`). A flag is *unavoidable* when braking at "
              "6 m/s² from the start could not have kept TTC > 1 s."), "",
              md_table(rows, {"planner": "planner", "family": "family",
                              "scenarios": "runs", "collisions": "collisions",
                              "flags_avoidable": "avoidable flags",
                              "flags_unavoidable": "unavoidable flags",
                              "min_ttc_s": "min TTC [s]", "min_time_gap_s":
                              "min time gap [s]", "max_decel_mps2": "max decel [m/s²]",
                              "max_jerk_mps3": "max jerk [m/s³]"}),
              "", "![suite](leader_suite.png)", ""]
    return lines
