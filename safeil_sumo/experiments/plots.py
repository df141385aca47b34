"""Plots of closed-loop runs (matplotlib, Agg backend: headless)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from safeil_sumo.scenarios.road import Road  # noqa: E402

TTC_CLIP_S = 20.0  # TTC axis upper limit [s] (inf when not closing)


def _groups(logs: pd.DataFrame):
    return logs.groupby("scenario", sort=False) if "scenario" in logs else [("run", logs)]


def plot_trajectories(road: Road, logs: pd.DataFrame, path: Path, vehicle_width: float) -> None:
    """Top-down view with lane lines, and the lateral offset along the path (where it shows)."""
    fig, (top, side) = plt.subplots(2, 1, figsize=(9, 9), height_ratios=(3, 2))
    for lane in road.lanes:
        for b in (lane.left_boundary, lane.right_boundary):
            top.plot(b.points[:, 0], b.points[:, 1], color="0.55", lw=0.8)
    for name, g in _groups(logs):
        top.plot(g["front_x"], g["front_y"], lw=1.2, label=str(name))
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title(f"{road.net_path.name}: ego paths (front bumper) and lane lines")
    half = road.lanes[road.ego_lane].width / 2
    for name, g in _groups(logs):
        side.plot(g["s"] - road.path_start_s, g["d"], lw=1.0, label=str(name))
    side.axhspan(-half, half, color="tab:green", alpha=0.08)
    for y in (-half, half):
        side.axhline(y, color="0.3", lw=1.0)
    for y in (-half + vehicle_width / 2, half - vehicle_width / 2):
        side.axhline(y, color="0.3", lw=0.8, ls=":")
    side.set_xlabel("distance along the test path [m]")
    side.set_ylabel("lateral offset [m]")
    side.set_title("lateral offset of the front-bumper centre (solid: lane lines, dotted: "
                   "where the body touches them)", fontsize=9)
    if len(_groups(logs)) <= 12:
        side.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_speed_gap(logs: pd.DataFrame, path: Path) -> None:
    """Ego and leader speed, and the bumper gap, over time."""
    fig, (ax_v, ax_g) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for i, (name, g) in enumerate(_groups(logs)):
        color = f"C{i % 10}"
        ax_v.plot(g["t"], g["v"], color=color, lw=1.2, label=f"{name} ego")
        ax_v.plot(g["t"], g["leader_v"], color=color, lw=0.8, ls="--")
        ax_g.plot(g["t"], g["gap"], color=color, lw=1.2)
    ax_v.set_ylabel("speed [m/s] (dashed: leader)")
    ax_g.set_ylabel("gap to leader [m]")
    ax_g.set_xlabel("time [s]")
    if len(_groups(logs)) <= 12:
        ax_v.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_ttc(logs: pd.DataFrame, path: Path, threshold_s: float) -> None:
    """Time to collision over time with the flag threshold."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for name, g in _groups(logs):
        ax.plot(g["t"], np.minimum(g["ttc"], TTC_CLIP_S), lw=1.0, label=str(name))
    ax.axhline(threshold_s, color="tab:red", ls="--", label=f"flag: TTC <= {threshold_s:g} s")
    ax.set_ylim(0, TTC_CLIP_S)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"TTC [s] (clipped at {TTC_CLIP_S:g}; not closing = top)")
    if len(_groups(logs)) <= 12:
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
