"""Tiny training inputs built in code for tests: synthetic car-following tuples, a towers
checkpoint with its reference, and the ``sitecustomize`` that hides torch from a Python process.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from safeil_sumo.core import bspline
from safeil_sumo.core.features import planner_features
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import save_checkpoint
from safeil_sumo.learn.model import PlannerMLP, split_towers, with_style_input
from safeil_sumo.learn.trainer import TrainConfig

# a ``sitecustomize.py`` that makes ``import torch`` fail as when torch is not installed
HIDE_TORCH = '''\
import sys


class _HideTorch:
    """torch is not installed (tests/test_without_torch.py)."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "torch":
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, _HideTorch())
'''


def make_tuples(
    n_maneuvers: int = 10,
    per_maneuver: int = 30,
    horizon: float = 5.0,
    rate_hz: float = 4.0,
    seed: int = 0,
    curved: bool = True,
) -> Tuples:
    """Synthetic car-following tuples: straight or curved lanes (|R| >= 600 m), a driver that
    follows at a constant time gap (linear ACC law) and returns to the lane centre; the target
    control points are least-squares fits of the future, as in the real pipeline."""
    rng = np.random.default_rng(seed)
    n_future = round(horizon * rate_hz)
    times = np.arange(1, n_future + 1) / rate_hz
    dt = 0.05
    n_steps = round(horizon / dt)
    step_of_sample = np.round(times / dt).astype(int)
    feats, futures, ids, ts = [], [], [], []
    for m in range(n_maneuvers):
        width = rng.uniform(3.3, 3.8)
        c2 = rng.uniform(-1 / 1200, 1 / 1200) if curved else 0.0
        v_lead_m = rng.uniform(22.0, 32.0)
        gap_time = rng.uniform(1.2, 2.0)  # [s] the driver's preferred time gap
        for j in range(per_maneuver):
            offset = rng.normal(0.0, 0.2)  # [m] ego left of lane centre
            c1 = rng.normal(0.0, 0.004) if curved else 0.0
            v = v_lead_m + rng.normal(0.0, 1.5)
            v_lead = v_lead_m + rng.normal(0.0, 0.5)
            d = max(gap_time * v + rng.normal(0.0, 4.0), 8.0)
            left = np.array([width / 2 - offset, c1, c2])
            right = np.array([-width / 2 - offset, c1, c2])
            feats.append(planner_features(left, right, v, v_lead, d))
            # longitudinal: constant-time-gap follower; lateral: exponential return to centre
            x, vx, gap = 0.0, v, d
            xs = np.empty(n_steps + 1)
            xs[0] = 0.0
            for k in range(n_steps):
                a = np.clip(0.1 * (gap - gap_time * vx) + 0.4 * (v_lead - vx), -4.0, 2.0)
                x += vx * dt + 0.5 * a * dt * dt
                gap += (v_lead - vx) * dt - 0.5 * a * dt * dt
                vx += a * dt
                xs[k + 1] = x
            fx = xs[step_of_sample]
            fy = -offset + c1 * fx + c2 * fx**2 + offset * np.exp(-times / 2.0)
            futures.append(np.stack([fx, fy], axis=-1))
            ids.append(f"m{seed:02d}_{m:03d}")
            ts.append(j / rate_hz)
    future = np.asarray(futures)
    cp = bspline.fit_control_points(future, times / horizon)
    n = len(feats)
    return Tuples(
        np.asarray(feats), cp, future, np.asarray(ids), np.full(n, "synthetic"),
        np.asarray(ts), horizon, rate_hz,
    )


def towers_checkpoint(tmp_path: Path) -> Path:
    """Tuples saved in ``tmp_path/tuples.parquet`` (returned), a dense residual reference
    checkpoint ``tmp_path/ref`` and its towers split with a style input, ``tmp_path/towers``,
    whose longitudinal plan is a different length than the reference's."""
    tup = make_tuples(n_maneuvers=3, per_maneuver=40, curved=True)
    data = tmp_path / "tuples.parquet"
    tup.save(data)
    torch.manual_seed(0)
    dense = PlannerMLP(hidden=(16, 16), output_mode="residual")
    dense.set_scaling(tup.features, tup.control_points)
    with torch.no_grad():
        for p in dense.net.parameters():
            p.normal_(0.0, 0.3)
    cfg = TrainConfig(envelope_weight=0.01, output_mode="residual", barrier_lateral="bernstein")
    save_checkpoint(tmp_path / "ref", dense, name="safeil", horizon=5.0, train_config=cfg)
    towers = split_towers(with_style_input(dense, 1.5, 0.5))
    with torch.no_grad():  # a different plan length than the reference's
        towers.net[-1].bias[[0, 2, 4]] += 0.5
    save_checkpoint(tmp_path / "towers", towers, name="safeil", horizon=5.0, train_config=cfg,
                    style_default={"time_gap_s": 1.5})
    return data
