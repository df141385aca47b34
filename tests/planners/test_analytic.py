"""The analytic planner: plans start at the car, follow the lane centre and keep the time gap."""

import numpy as np
import pytest

from safeil_sumo.core import bspline
from safeil_sumo.core.features import planner_features
from safeil_sumo.core.policy import Policy
from safeil_sumo.planners.analytic import AnalyticPlanner


def test_is_a_policy_and_free_road_cruise():
    p = AnalyticPlanner()
    assert isinstance(p, Policy)
    f = planner_features([1.75, 0, 0], [-1.75, 0, 0], 33.0, 33.0, 150.0)
    cp = p.plan(f)
    assert cp.shape == (3, 2)
    # at the desired speed on a free road: control points at v * i * T_h / 3, on the centre line
    assert np.allclose(cp[:, 0], 33.0 * bspline.control_point_times(5.0), rtol=1e-3)
    assert np.allclose(cp[:, 1], 0.0, atol=1e-9)


def test_converges_to_lane_centre_and_brakes_for_a_close_leader():
    p = AnalyticPlanner()
    f = planner_features([2.25, 0, 0], [-1.25, 0, 0], 30.0, 20.0, 20.0)  # 0.5 m right of centre
    cp = p.plan(f)
    end = bspline.evaluate(cp, np.array([1.0]))[0]
    assert end[1] == pytest.approx(0.5, abs=0.05)
    # braking: the plan covers less than cruising would, and stays behind the moving leader
    assert end[0] < 30.0 * 5.0
    assert np.all(cp[:, 0] < 20.0 + 20.0 * bspline.control_point_times(5.0))


def test_batched_plan_matches_single():
    p = AnalyticPlanner()
    f = np.stack([planner_features([1.75, 0, 1e-3], [-1.75, 0, 1e-3], 28.0, 26.0, 45.0),
                  planner_features([1.5, 0.01, 0], [-2.0, 0.01, 0], 31.0, 25.0, 60.0)])
    assert np.allclose(p.plan(f), np.stack([p.plan(f[0]), p.plan(f[1])]))
