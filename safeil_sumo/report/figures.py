"""The figures of the report card (:mod:`safeil_sumo.report.sections`) that no existing command
draws: rates with their Wilson intervals, the leader-response suite per family, the human's and
each planner's gap and speed over whole replayed maneuvers, and a falsification search's curve.
Each takes plain tables and writes one PNG."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.experiments.stats import wilson_interval


def plot_rates(rates: Sequence[tuple[str, int, int]], path: Path, title: str) -> None:
    """Horizontal bars of ``k / n`` [%] for ``(label, k, n)``, with Wilson 95 % intervals."""
    fig, ax = plt.subplots(figsize=(8, 0.55 * len(rates) + 1.4))
    y = np.arange(len(rates))[::-1]
    for yi, (_, k, n) in zip(y, rates, strict=True):
        lo, hi = wilson_interval(k, n) if n else (0.0, 1.0)
        rate = 100.0 * k / n if n else 0.0
        ax.barh(yi, rate, color="tab:blue", alpha=0.8)
        ax.errorbar(rate, yi, xerr=[[rate - 100 * lo], [100 * hi - rate]], color="k",
                    capsize=4, lw=1)
    ax.set_yticks(y)
    ax.set_yticklabels([f"{label} ({k}/{n})" for label, k, n in rates], fontsize=9)
    ax.set_xlim(0, 100)
    ax.set_xlabel("scenarios [%] (Wilson 95 % interval)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_suite(table: pd.DataFrame, path: Path, title: str) -> None:
    """Per family (rows of :func:`safeil_sumo.experiments.suite.aggregate`): min TTC [s] and
    min time gap [s] (bars), collisions and avoidable flags written above the bars."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    x = np.arange(len(table))
    ttc = np.minimum(table["min_ttc_s"].to_numpy(float), 20.0)  # inf (never closing): capped
    axes[0].bar(x, ttc, color="tab:blue")
    axes[0].axhline(1.0, color="tab:red", ls=":", lw=1, label="TTC flag (1 s)")
    axes[0].set_ylabel("min TTC [s] (capped at 20)")
    axes[1].bar(x, table["min_time_gap_s"].to_numpy(float), color="tab:green")
    axes[1].set_ylabel("min time gap [s]")
    for xi, (_, r) in zip(x, table.iterrows(), strict=True):
        axes[0].annotate(f"coll. {r['collisions']}\navoid. flags {r['flags_avoidable']}",
                         (xi, ttc[xi]), ha="center", va="bottom", fontsize=7)
    for ax in axes:
        ax.set_xticks(x)
        ax.set_xticklabels(table["family"], fontsize=8)
    axes[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_replay_traces(panels: Sequence[tuple[str, pd.DataFrame, dict[str, pd.DataFrame]]],
                       path: Path) -> None:
    """One row per ``(title, human, compared)``: the bumper gap [m] and the speed [m/s] over time
    [s] of the human (black dashed) and each planner (``compared[name]``: columns ``t, gap, v``
    at the human's timestamps, :class:`safeil_sumo.experiments.maneuver_replay.ReplayResult`)."""
    fig, axes = plt.subplots(len(panels), 2, figsize=(12, 3.0 * len(panels)), squeeze=False)
    for row, (title, human, compared) in enumerate(panels):
        for col, (name, label) in enumerate((("gap", "gap [m]"), ("v", "speed [m/s]"))):
            ax = axes[row][col]
            ax.plot(human["t"], human[name], "k--", lw=1.5, label="human")
            for k, (planner, trace) in enumerate(compared.items()):
                ax.plot(trace["t"], trace[name], color=f"C{k % 10}", lw=1.1, label=planner)
            if name == "gap":  # a baseline that drifts hundreds of metres away hides the rest
                top = np.nanmax(human["gap"].to_numpy(float))
                ax.set_ylim(0.0, 2.5 * top if np.isfinite(top) and top > 0 else None)
            ax.set_ylabel(label)
            ax.set_title(title if col == 0 else "", fontsize=9, loc="left")
            ax.grid(alpha=0.3)
        axes[row][0].legend(fontsize=7, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_falsify(evaluations: pd.DataFrame, path: Path, title: str) -> None:
    """A search's lowest min TTC of an avoidable run so far [s] (top, ``best_so_far`` of
    :func:`safeil_sumo.experiments.falsification_search.table`) and its failures found (bottom)
    against the simulations spent."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    sims = evaluations["sim"].to_numpy(int)
    best = evaluations["best_so_far"].to_numpy(float)
    top.step(sims, np.where(np.isfinite(best), best, np.nan), where="post", color="tab:blue")
    top.axhline(1.0, color="tab:red", lw=0.8, ls=":", label="failure: flagged (TTC <= 1 s)")
    top.set_ylabel("worst min TTC found [s]")
    top.legend(fontsize=7)
    bottom.plot(sims, np.cumsum(evaluations["failure"].to_numpy(bool)), color="tab:red")
    bottom.set_ylabel("failures found")
    bottom.set_xlabel("simulations spent")
    top.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
