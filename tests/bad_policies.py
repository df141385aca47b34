"""Deliberately bad policies for closed-loop tests (shared by the monitor and golden tests)."""

import numpy as np

from safeil_sumo.planners.analytic import AnalyticPlanner


class DriftLeft:
    """Keeps its speed but plans 1 m further left every 5 s."""

    name = "drift_left"
    horizon = 5.0

    def plan(self, features):
        # (..., 9) -> (..., 3, 2): a batch of feature rows gives a batch of plans
        v = np.asarray(features)[..., 6, None]
        t = np.array([5 / 3, 10 / 3, 5.0])
        x = v * t
        return np.stack([x, np.broadcast_to(1.0 * t / 5.0, x.shape)], axis=-1)


def blind_cruise() -> AnalyticPlanner:
    """Lane keeping at a fixed 30 m/s that ignores the leader."""
    return AnalyticPlanner(name="blind", k_gap=0.0, k_speed=0.0, v_desired_mps=30.0)
