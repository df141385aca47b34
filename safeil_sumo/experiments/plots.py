"""Plots of closed-loop runs (matplotlib, Agg backend: headless)."""

from __future__ import annotations

import math
from collections.abc import Collection
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.axes import Axes

from safeil_sumo.roads.road import Road

TTC_CLIP_S = 20.0  # TTC axis upper limit [s] (inf when not closing)


def _groups(logs: pd.DataFrame) -> Collection[tuple[Any, pd.DataFrame]]:
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


FLAG_STYLE = {  # kind -> (marker, colour, label) on route maps
    "ttc": ("^", "tab:orange", "TTC <= 1 s"),
    "lane_departure": ("x", "tab:blue", "lane departure"),
    "collision": ("*", "tab:red", "collision"),
}


def draw_flag_map(ax: Axes, route_xy: np.ndarray, events: pd.DataFrame, title: str,
                  km_at_start: float = 0.0, tick_km: float = 5.0) -> None:
    """The route (``(N, 2)`` [m], x-y) in grey, labelled every ``tick_km`` [km] (its first
    point is at ``km_at_start`` [km]), and flag events (columns ``kind``, ``x``, ``y`` [m])
    marked by kind; equal aspect."""
    ax.plot(route_xy[:, 0] / 1000.0, route_xy[:, 1] / 1000.0, color="0.6", lw=1.5, zorder=1)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(route_xy, axis=0), axis=1))])
    first = math.ceil(km_at_start / tick_km) * tick_km
    for km in np.arange(first, km_at_start + s[-1] / 1000.0, tick_km):
        i = min(int(np.searchsorted(s, 1000.0 * (km - km_at_start))), len(s) - 1)
        ax.plot(*(route_xy[i] / 1000.0), "o", color="0.3", ms=3, zorder=2)
        ax.annotate(f"{km:g}", route_xy[i] / 1000.0, fontsize=7, color="0.3",
                    xytext=(3, 3), textcoords="offset points")
    for kind, (marker, color, label) in FLAG_STYLE.items():
        sub = events[events["kind"] == kind]
        ax.scatter(sub["x"] / 1000.0, sub["y"] / 1000.0, marker=marker, color=color, s=40,
                   zorder=3, label=f"{label} ({len(sub)})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [km]")
    ax.set_ylabel("y [km]")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="best")


def plot_flag_map(road: Road, logs: pd.DataFrame, path: Path) -> None:
    """The ego lane of ``road`` and where each flag event of the runs started (see
    :func:`safeil_sumo.experiments.n74_drives.flag_events`)."""
    from safeil_sumo.experiments.n74_drives import flag_events

    events = pd.DataFrame([e for _, g in _groups(logs) for e in flag_events(g)],
                          columns=["kind", "t_s", "x", "y", "s_m"])
    fig, ax = plt.subplots(figsize=(8, 6))
    lo, hi = road.meta.get("stretch_km") or (0.0, road.path_end_s / 1000.0)
    km0 = lo - road.path_start_s / 1000.0  # the km post of the lane's first point
    draw_flag_map(ax, road.lanes[road.ego_lane].centre.points, events,
                  f"{road.net_path.name}, km {lo:g}-{hi:g}: ego lane (ticks: km) and where "
                  "each flag started", km0, 1.0 if hi - lo <= 12.0 else 5.0)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
