"""Static leader-response probe: how a planner's plan reacts to its leader, without SUMO.

Over a grid of car-following states (ego speed, leader speed relative to it, bumper gap) on a
straight, centred lane, every policy plans once (one batched ``Policy.plan`` call) and the probe
measures, on the *recoverable* states only (braking at ``brake_mps2`` keeps the ego behind a
constant-speed leader: ``v <= v_lead`` or ``gap > (v - v_lead)^2 / (2 brake)``):

- ``pass_rate``: the share of states whose planned trajectory x(t) runs past the leader's
  predicted rear ``gap + v_lead t`` at some t in [0, T_h] (checked on ``samples`` points);
- ``margin_violation_rate``: the same against ``gap + v_lead t - (gap_min + time_gap v_lead)``,
  the margin the safety monitors care about (TTC and time gap);
- ``gap_monotone_violations``: how many (ego speed, leader speed) pairs have a planned end
  position x(T_h) that DEcreases somewhere as the gap grows (a farther leader must never make the
  plan shorter), with the largest decrease [m];
- ``end_speed`` examples: the planned end speed [m/s] at a few named states.

All pure numpy: the same probe runs for any object with the Policy protocol.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from safeil_sumo.core import bspline
from safeil_sumo.core.policy import Policy

LANE_WIDTH_M = 3.5


@dataclass(frozen=True)
class ProbeGrid:
    """The probed states (straight lane, ego centred)."""

    ego_speeds_mps: tuple[float, ...] = tuple(np.arange(15.0, 35.01, 2.5))  # [m/s]
    relative_speeds_mps: tuple[float, ...] = tuple(np.arange(-10.0, 5.01, 1.25))  # v_lead - v [m/s]
    gaps_m: tuple[float, ...] = tuple(np.arange(8.0, 120.01, 4.0))  # bumper gap [m]
    brake_mps2: float = 6.0  # recoverable: braking this hard avoids the leader [m/s^2]
    gap_min_m: float = 2.0  # margin of margin_violation_rate: standstill part [m]
    time_gap_s: float = 1.0  # margin of margin_violation_rate: time-gap part [s]
    samples: int = 50  # points along the spline checked against the leader [-]


def straight_lane_features(v: np.ndarray, v_lead: np.ndarray, gap: np.ndarray,
                           lane_width_m: float = LANE_WIDTH_M, c2: float = 0.0) -> np.ndarray:
    """Planner features ``(..., 9)`` on a centred lane (``c2`` [1/m] bends both lines)."""
    half = 0.5 * lane_width_m
    v, v_lead, gap = np.broadcast_arrays(np.asarray(v, float), np.asarray(v_lead, float),
                                         np.asarray(gap, float))
    z = np.zeros_like(v)
    return np.stack([z + half, z, z + c2, z - half, z, z + c2, v, v_lead, gap], axis=-1)


def recoverable(v: np.ndarray, v_lead: np.ndarray, gap: np.ndarray, brake_mps2: float) -> np.ndarray:
    """Braking at ``brake_mps2`` from now keeps the ego behind a constant-speed leader."""
    closing = np.maximum(np.asarray(v, float) - v_lead, 0.0)
    return np.asarray(gap, float) > closing * closing / (2.0 * brake_mps2)


def grid_states(grid: ProbeGrid = ProbeGrid()) -> pd.DataFrame:
    """One row per probed state: ``v, v_lead, gap`` and ``recoverable``."""
    v, dv, gap = np.meshgrid(grid.ego_speeds_mps, grid.relative_speeds_mps, grid.gaps_m,
                             indexing="ij")
    v_lead = np.maximum(v + dv, 0.0)
    df = pd.DataFrame({"v": v.ravel(), "v_lead": v_lead.ravel(), "gap": gap.ravel(),
                       "dv": dv.ravel()})
    df["recoverable"] = recoverable(df["v"], df["v_lead"], df["gap"], grid.brake_mps2)
    return df


def plan_positions(control_points: np.ndarray, horizon_s: float, samples: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Planned x ``(N, samples)`` [m] at times ``(samples,)`` [s] in (0, T_h]."""
    tau = np.arange(1, samples + 1) / samples
    xy = bspline.evaluate(control_points, tau)
    return xy[..., 0], tau * horizon_s


def probe(policy: Policy, grid: ProbeGrid = ProbeGrid()) -> tuple[dict, pd.DataFrame]:
    """Run the probe: ``(summary, per-state table)``."""
    states = grid_states(grid)
    feats = straight_lane_features(states["v"].to_numpy(), states["v_lead"].to_numpy(),
                                   states["gap"].to_numpy())
    cps = np.asarray(policy.plan(feats), float)
    x, t = plan_positions(cps, policy.horizon, grid.samples)
    lead = states["gap"].to_numpy()[:, None] + states["v_lead"].to_numpy()[:, None] * t
    margin = grid.gap_min_m + grid.time_gap_s * states["v_lead"].to_numpy()[:, None]
    states["passes_leader"] = (x > lead).any(axis=1)
    states["violates_margin"] = (x > lead - margin).any(axis=1)
    states["end_x"] = x[:, -1]
    # end speed from the spline derivative at tau = 1 (d/dt = d/dtau / T_h)
    states["end_speed"] = bspline.evaluate(cps, np.array([1.0]), derivative=1)[:, 0, 0] / \
        policy.horizon
    rec = states[states["recoverable"]]
    worst = 0.0
    n_nonmono = 0
    for _, g in states.groupby(["v", "dv"], sort=False):
        steps = np.diff(g.sort_values("gap")["end_x"].to_numpy())
        if len(steps) and steps.min() < -1e-6:
            n_nonmono += 1
            worst = max(worst, float(-steps.min()))
    summary = {
        "policy": policy.name,
        "states": len(states),
        "recoverable_states": len(rec),
        "pass_rate": float(rec["passes_leader"].mean()),
        "margin_violation_rate": float(rec["violates_margin"].mean()),
        "gap_monotone_violations": n_nonmono,
        "gap_monotone_pairs": int(states.groupby(["v", "dv"]).ngroups),
        "max_end_x_decrease_m": worst,
    }
    for v, v_lead, gap in ((30.0, 25.0, 10.0), (30.0, 25.0, 50.0), (30.0, 20.0, 30.0),
                           (30.0, 30.0, 100.0)):
        f = straight_lane_features(np.array([v]), np.array([v_lead]), np.array([gap]))
        cp = np.asarray(policy.plan(f), float)
        end = bspline.evaluate(cp, np.array([1.0]), derivative=1)[0, 0, 0] / policy.horizon
        summary[f"end_speed_v{v:g}_lead{v_lead:g}_gap{gap:g}"] = float(end)
    return summary, states
