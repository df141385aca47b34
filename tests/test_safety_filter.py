"""Safety filter: filtered plans satisfy the constraints at their control points, always."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo import bspline
from safeil_sumo.features import planner_features
from safeil_sumo.policy import Policy
from safeil_sumo.safety_filter import (
    SafeSet,
    SafetyFiltered,
    lateral_bounds,
    plan_margins,
    project_plan,
)

TOL = 1e-9  # [m] round-off of recomputing a clipped bound


@st.composite
def scenes(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, float, SafeSet]:
    """Random features (parallel lane lines, realistic ranges), a random plan and a safe set."""
    width = draw(st.floats(3.0, 4.5))
    offset = draw(st.floats(-0.5, 0.5))  # ego left of lane centre [m]
    c1 = draw(st.floats(-0.05, 0.05))
    c2 = draw(st.floats(-0.005, 0.005))
    v_x, v_lead = draw(st.floats(0.0, 40.0)), draw(st.floats(0.0, 40.0))
    d_lead = draw(st.floats(5.0, 150.0))
    features = planner_features(
        [width / 2 - offset, c1, c2], [-width / 2 - offset, c1, c2], v_x, v_lead, d_lead
    )
    horizon = draw(st.sampled_from([3.0, 5.0, 6.0]))
    xs = [draw(st.floats(-20.0, 300.0)) for _ in range(3)]
    ys = [draw(st.floats(-60.0, 60.0)) for _ in range(3)]
    safe_set = SafeSet(
        track=draw(st.floats(1.5, 2.0)),
        lateral_margin=draw(st.floats(0.0, 0.2)),
        gap_min=draw(st.floats(0.0, 4.0)),
        time_gap=draw(st.floats(0.0, 0.1)),  # keeps d_lead - margin > 0 in these ranges
    )
    return features, np.stack([xs, ys], axis=-1), horizon, safe_set


@settings(max_examples=300, deadline=None)
@given(scene=scenes())
def test_filtered_plans_satisfy_the_constraints(scene) -> None:
    features, plan, horizon, safe_set = scene
    filtered, acted = project_plan(features, plan, horizon, safe_set)
    margins = plan_margins(features, filtered, horizon, safe_set)
    for name, m in margins.items():
        assert np.all(m >= -TOL), (name, m)
    # it acts exactly when the input plan was unsafe, and leaves safe plans untouched
    unsafe = any(np.any(m < 0) for m in plan_margins(features, plan, horizon, safe_set).values())
    assert bool(acted) == unsafe
    if not unsafe:
        np.testing.assert_array_equal(filtered, plan)


@settings(max_examples=100, deadline=None)
@given(scene=scenes())
def test_projection_is_idempotent_and_minimal(scene) -> None:
    features, plan, horizon, safe_set = scene
    once, _ = project_plan(features, plan, horizon, safe_set)
    twice, _ = project_plan(features, once, horizon, safe_set)
    np.testing.assert_allclose(twice, once, atol=1e-9)
    # x only ever decreases, y moves no further than onto the nearest bound
    assert np.all(once[:, 0] <= plan[:, 0])
    y_min, y_max = lateral_bounds(features, once[:, 0], safe_set)
    assert np.all((once[:, 1] == plan[:, 1]) | np.isclose(once[:, 1], y_min)
                  | np.isclose(once[:, 1], y_max))


def test_straight_lane_whole_spline_is_safe_after_filtering() -> None:
    """Straight lane: the convex-hull argument holds, so the whole filtered spline is safe."""
    rng = np.random.default_rng(0)
    f = planner_features([1.8, 0.0, 0.0], [-1.7, 0.0, 0.0], 30.0, 25.0, 30.0)
    plans = rng.uniform([-5, -8], [250, 8], size=(500, 3, 2))
    feats = np.broadcast_to(f, (500, 9))
    filtered, acted = project_plan(feats, plans, 5.0)
    tau = np.linspace(0, 1, 101)
    m = plan_margins(feats, filtered, 5.0, tau=tau)
    assert all(np.all(v >= -TOL) for v in m.values())
    assert acted.mean() > 0.9


def test_infeasible_lane_goes_to_the_middle() -> None:
    f = planner_features([0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], 20.0, 20.0, 50.0)  # 1 m lane
    filtered, acted = project_plan(f, np.array([[10.0, 3.0], [20.0, 0.0], [30.0, -3.0]]), 4.0)
    assert acted and np.allclose(filtered[:, 1], 0.0)


class _Straight:
    name = "straight"
    horizon = 5.0

    def plan(self, features: np.ndarray) -> np.ndarray:
        v = np.asarray(features)[..., 6]
        x = v[..., None] * bspline.control_point_times(self.horizon)
        return np.stack([x, np.full_like(x, 1.5)], axis=-1)  # drifting left


def test_wrapper_counts_interventions() -> None:
    filt = SafetyFiltered(_Straight(), SafeSet(gap_min=2.0))
    assert isinstance(filt, Policy) and filt.name == "straight+filter" and filt.horizon == 5.0
    wide = planner_features([5.0, 0, 0], [-5.0, 0, 0], 20.0, 20.0, 100.0)
    narrow = planner_features([1.75, 0, 0], [-1.75, 0, 0], 20.0, 20.0, 100.0)
    np.testing.assert_array_equal(filt.plan(wide), _Straight().plan(wide))
    out = filt.plan(narrow)
    assert out[:, 1] == pytest.approx(1.75 - 0.88)
    filt.plan(np.stack([wide, narrow, narrow]))
    assert (filt.calls, filt.interventions) == (5, 3)
    assert filt.intervention_rate == pytest.approx(0.6)
