"""Safety filter. mode="control_points": filtered plans satisfy the constraints at their control
points, always. mode="bernstein" (default): the exact Bernstein coefficients of the lane margins
along the spline are >= 0 (the whole spline is inside, on curves too) whenever the car is inside
at tau = 0, and lane-following plans on curves are left alone; closed loop on curved500."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.core import bspline
from safeil_sumo.core.features import planner_features
from safeil_sumo.core.policy import Policy
from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.planners.safety_filter import (
    SafeSet,
    SafetyFiltered,
    bernstein_margins,
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
    filtered, acted = project_plan(features, plan, horizon, safe_set, mode="control_points")
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
    once, _ = project_plan(features, plan, horizon, safe_set, mode="control_points")
    twice, _ = project_plan(features, once, horizon, safe_set, mode="control_points")
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
    filtered, acted = project_plan(feats, plans, 5.0, mode="control_points")
    tau = np.linspace(0, 1, 101)
    m = plan_margins(feats, filtered, 5.0, tau=tau)
    assert all(np.all(v >= -TOL) for v in m.values())
    assert acted.mean() > 0.9


def test_infeasible_lane_goes_to_the_middle() -> None:
    f = planner_features([0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], 20.0, 20.0, 50.0)  # 1 m lane
    plan = np.array([[10.0, 3.0], [20.0, 0.0], [30.0, -3.0]])
    for mode in ("control_points", "bernstein"):
        filtered, acted = project_plan(f, plan, 4.0, mode=mode)
        assert acted and np.allclose(filtered[:, 1], 0.0), mode


class _Straight:
    name = "straight"
    horizon = 5.0

    def plan(self, features: np.ndarray) -> np.ndarray:
        v = np.asarray(features)[..., 6]
        x = v[..., None] * bspline.control_point_times(self.horizon)
        return np.stack([x, np.full_like(x, 1.5)], axis=-1)  # drifting left


def test_wrapper_counts_interventions() -> None:
    filt = SafetyFiltered(_Straight(), SafeSet(gap_min=2.0), mode="control_points")
    assert isinstance(filt, Policy) and filt.name == "straight+filter" and filt.horizon == 5.0
    wide = planner_features([5.0, 0, 0], [-5.0, 0, 0], 20.0, 20.0, 100.0)
    narrow = planner_features([1.75, 0, 0], [-1.75, 0, 0], 20.0, 20.0, 100.0)
    np.testing.assert_array_equal(filt.plan(wide), _Straight().plan(wide))
    out = filt.plan(narrow)
    assert out[:, 1] == pytest.approx(1.75 - 0.88)
    filt.plan(np.stack([wide, narrow, narrow]))
    assert (filt.calls, filt.interventions) == (5, 3)
    assert filt.intervention_rate == pytest.approx(0.6)


def test_wrapper_filters_in_its_own_mode() -> None:
    """On a curve the two modes filter a drifting plan differently; the wrapper's plan is its
    mode's (a case found by mutation testing: the mode was not passed on)."""
    f = planner_features([1.75, 0.0, 1 / 1000], [-1.75, 0.0, 1 / 1000], 30.0, 30.0, 100.0)
    x = 30.0 * bspline.control_point_times(5.0)
    plan = np.stack([x, np.array([0.5, 1.5, 3.0])], axis=-1)

    class Drifting:
        name, horizon = "drifting", 5.0

        def plan(self, features: np.ndarray) -> np.ndarray:
            return plan

    by_mode = {m: project_plan(f, plan, 5.0, mode=m)[0] for m in ("control_points", "bernstein")}
    assert not np.allclose(by_mode["control_points"], by_mode["bernstein"])
    for mode, want in by_mode.items():
        np.testing.assert_array_equal(SafetyFiltered(Drifting(), mode=mode).plan(f), want)
    np.testing.assert_array_equal(SafetyFiltered(Drifting()).plan(list(f)), by_mode["bernstein"])
    with pytest.raises(ValueError, match="mode must be one of .*, got 'clip'"):
        SafetyFiltered(Drifting(), mode="clip")


# ---------------------------------------------------------------- mode="bernstein" (the default)

def _bernstein_ok(features, plan, safe_set, tol=TOL) -> bool:
    m = bernstein_margins(features, plan, safe_set)
    return bool(np.all(m["left"] >= -tol) and np.all(m["right"] >= -tol))


def _ego_inside(features, safe_set) -> bool:
    m = bernstein_margins(features, np.zeros((3, 2)), safe_set)  # coefficient 0: the car itself
    return bool(m["left"][0] >= 0 and m["right"][0] >= 0)


@settings(max_examples=500, deadline=None)
@given(scene=scenes())
def test_bernstein_filter_keeps_the_whole_spline_inside(scene) -> None:
    features, plan, horizon, safe_set = scene
    filtered, acted = project_plan(features, plan, horizon, safe_set)
    lead = plan_margins(features, filtered, horizon, safe_set)["lead"]
    assert np.all(lead >= -TOL)
    if not _ego_inside(features, safe_set):
        return  # no plan starting at the car is inside; see test_car_outside_the_band
    assert _bernstein_ok(features, filtered, safe_set), bernstein_margins(
        features, filtered, safe_set)
    tau = np.linspace(0.0, 1.0, 201)
    sampled = plan_margins(features, filtered, horizon, safe_set, tau)
    assert np.all(sampled["left"] >= -TOL) and np.all(sampled["right"] >= -TOL)
    # plans already inside (all 14 coefficients, leader at the control points) are kept exactly
    if _bernstein_ok(features, plan, safe_set, tol=0.0) and np.all(
        plan_margins(features, plan, horizon, safe_set)["lead"] >= 0
    ):
        assert not acted
        np.testing.assert_array_equal(filtered, plan)
    again, _ = project_plan(features, filtered, horizon, safe_set)
    np.testing.assert_allclose(again, filtered, atol=1e-9)


@st.composite
def following_scenes(draw: st.DrawFn) -> np.ndarray:
    """Features in the brief's realistic ranges, the car inside its lane, curved lanes included."""
    width = draw(st.floats(3.0, 4.5))
    half_band = (width - 1.76) / 2
    offset = draw(st.floats(-half_band, half_band))
    c1 = draw(st.floats(-0.05, 0.05))
    c2 = draw(st.floats(-0.002, 0.002))
    v_x, v_lead = draw(st.floats(0.0, 40.0)), draw(st.floats(0.0, 40.0))
    d_lead = draw(st.floats(5.0, 150.0))
    return planner_features(
        [width / 2 - offset, c1, c2], [-width / 2 - offset, c1, c2], v_x, v_lead, d_lead
    )


@settings(max_examples=300, deadline=None)
@given(features=following_scenes())
def test_lane_following_plans_are_changed_by_less_than_a_few_cm(features) -> None:
    plan = AnalyticPlanner().plan(features)
    filtered, _ = project_plan(features, plan, 5.0)
    x_clipped = not np.array_equal(filtered[:, 0], plan[:, 0])  # the leader clip, as before
    if not x_clipped:
        assert np.abs(filtered[:, 1] - plan[:, 1]).max() < 0.03
    assert _bernstein_ok(features, filtered, SafeSet())


def test_lane_following_on_the_paper_curve_is_untouched_by_the_new_filter_only() -> None:
    """R = 500 m at 30 m/s over 5 s: the control points sit ~2.5 m outside the centre, so the
    control-point clip bends the plan; the Bernstein filter leaves it exactly as it is."""
    c2 = 1 / 1000
    for offset in (-0.5, 0.0, 0.5):
        f = planner_features([1.75 - offset, 0.0, c2], [-1.75 - offset, 0.0, c2], 30.0, 30.0, 50.0)
        plan = AnalyticPlanner().plan(f)
        new, acted = project_plan(f, plan, 5.0)
        old, acted_old = project_plan(f, plan, 5.0, mode="control_points")
        assert not acted and np.array_equal(new, plan)
        assert acted_old and np.abs(old - plan).max() > 1.0
        tau = np.linspace(0, 1, 101)
        m_old = plan_margins(f, old, 5.0, tau=tau)
        assert min(m_old["left"].min(), m_old["right"].min()) < 0  # the old clip leaves the lane


def test_drifting_plan_on_a_curve_is_pulled_inside_by_the_smallest_blend() -> None:
    c2 = 1 / 1000
    f = planner_features([1.75, 0.0, c2], [-1.75, 0.0, c2], 30.0, 30.0, 100.0)
    x = 30.0 * bspline.control_point_times(5.0)
    plan = np.stack([x, np.array([0.5, 1.5, 3.0])], axis=-1)  # straight ahead, drifting left
    filtered, acted = project_plan(f, plan, 5.0)
    assert acted and np.array_equal(filtered[:, 0], x)
    m = bernstein_margins(f, filtered)
    # the smallest blend: some coefficient ends exactly on the boundary
    assert min(m["left"].min(), m["right"].min()) == pytest.approx(0.0, abs=1e-9)
    assert _bernstein_ok(f, filtered, SafeSet())


def test_car_outside_the_band_returns_to_the_lane_centre() -> None:
    """The car is 1 m right of the allowed band: no plan starting at it is inside. The filter
    returns the lane-centre reference (x kept), whose coefficients k >= 4 are inside."""
    f = planner_features([3.6, 0.0, 0.001], [-0.1, 0.0, 0.001], 30.0, 30.0, 100.0)  # centre +1.75
    x = 30.0 * bspline.control_point_times(5.0)
    plan = np.stack([x, np.zeros(3)], axis=-1)
    filtered, acted = project_plan(f, plan, 5.0)
    assert acted and np.array_equal(filtered[:, 0], x)
    m = bernstein_margins(f, filtered)
    assert m["right"][0] < 0 and np.all(m["right"][4:] >= -TOL) and np.all(m["left"] >= 0)
    end = bspline.evaluate(filtered, np.array([1.0]))[0]
    assert end[1] == pytest.approx(1.75 + 0.001 * end[0] ** 2, abs=1e-6)  # on the lane centre


def test_car_outside_a_slanted_lane_returns_to_its_centre_line_batched_as_alone() -> None:
    """A lane at a heading (c1 = 0.05) whose allowed band starts 1.98 m left of the car: the
    filter returns the lane centre line at the plan's x, y = 2.85 + 0.05 x (cases found by
    mutation testing: every hand case had c1 = 0). In one batch with a plan that needs no
    change, each plan is filtered as it would be alone."""
    x = 30.0 * bspline.control_point_times(5.0)
    outside = planner_features([4.6, 0.05, 0.0], [1.1, 0.05, 0.0], 30.0, 30.0, 200.0)
    plan = np.stack([x, np.zeros(3)], axis=-1)
    got, acted = project_plan(outside, plan, 5.0)
    assert acted
    np.testing.assert_array_equal(got[:, 0], x)
    np.testing.assert_allclose(got[:, 1], 2.85 + 0.05 * x, rtol=0, atol=1e-12)
    inside = planner_features([1.75, 0.0, 0.0], [-1.75, 0.0, 0.0], 30.0, 30.0, 200.0)
    drift = np.stack([x, np.array([0.5, 1.5, 3.0])], axis=-1)  # leaves a straight lane
    calm = np.stack([x, np.zeros(3)], axis=-1)
    feats = np.stack([outside, inside, inside])
    plans = np.stack([plan, drift, calm])
    batch, acted = project_plan(feats, plans, 5.0)
    assert list(acted) == [True, True, False]
    for k in range(3):
        np.testing.assert_array_equal(batch[k], project_plan(feats[k], plans[k], 5.0)[0])
    np.testing.assert_array_equal(batch[2], calm)
    # the band starts only 0.5 m left of the car: outside is outside, the centre line it is
    near = planner_features([3.12, 0.0, 0.0], [-0.38, 0.0, 0.0], 30.0, 30.0, 200.0)
    got, _ = project_plan(near, calm, 5.0)
    np.testing.assert_allclose(got[:, 1], 1.37, rtol=0, atol=1e-12)


def test_bernstein_filter_on_straight_lanes_is_no_stricter_than_the_control_point_clip() -> None:
    rng = np.random.default_rng(0)
    f = planner_features([1.8, 0.0, 0.0], [-1.7, 0.0, 0.0], 30.0, 25.0, 30.0)
    plans = rng.uniform([-5, -3], [250, 3], size=(2000, 3, 2))
    feats = np.broadcast_to(f, (2000, 9))
    _, acted_cp = project_plan(feats, plans, 5.0, mode="control_points")
    filtered, acted = project_plan(feats, plans, 5.0)
    assert np.all(acted <= acted_cp) and acted.sum() <= acted_cp.sum()
    tau = np.linspace(0, 1, 101)
    m = plan_margins(feats, filtered, 5.0, tau=tau)
    assert all(np.all(v >= -TOL) for v in m.values())
    with pytest.raises(ValueError):
        project_plan(f, plans[0], 5.0, mode="nope")
    with pytest.raises(ValueError):
        SafetyFiltered(_Straight(), mode="nope")


def test_wrapper_default_is_the_bernstein_mode() -> None:
    filt = SafetyFiltered(_Straight())
    assert filt.mode == "bernstein"
    narrow = planner_features([1.75, 0, 0], [-1.75, 0, 0], 20.0, 20.0, 100.0)
    out = filt.plan(narrow)
    assert _bernstein_ok(narrow, out, SafeSet()) and filt.interventions == 1


# ---------------------------------------------------------------- closed loop, real libsumo

@pytest.mark.sumo
def test_analytic_planner_with_the_filter_completes_curved500() -> None:
    """Before the Bernstein mode, the control-point clip made this 0/10 (lane departure)."""
    from safeil_sumo.roads.catalogue import resolve_net
    from safeil_sumo.roads.road import load_road
    from safeil_sumo.scenarios.safety import safety_scenario
    from safeil_sumo.sim.runner import run_scenario

    road = load_road(resolve_net("curved500"))
    policy = SafetyFiltered(AnalyticPlanner())
    s = run_scenario(safety_scenario(road, 0, master_seed=0), policy).summary
    assert s["completed"] and s["flag"] == "" and s["path_completed"] == 1.0, s
    assert s["max_abs_lateral_offset_m"] < 0.5
    assert policy.calls > 100 and policy.intervention_rate < 0.05


# ------------------------------------------------- cases found by mutation testing (issue 43)


def test_margins_and_bounds_by_hand_with_a_lateral_margin() -> None:
    """A straight 3.5 m lane, a 1.8 m car, 0.1 m more clearance: the band is |y| <= 0.75 m; a
    plan at y = 0.5 has margins 0.25 left and 1.25 right, at every control point and every
    Bernstein coefficient but the car's own (its y is 0: 0.75 each side)."""
    f = planner_features([1.75, 0.0, 0.0], [-1.75, 0.0, 0.0], 30.0, 30.0, 100.0)
    safe = SafeSet(track=1.8, lateral_margin=0.1)
    y_min, y_max = lateral_bounds(f, np.array([0.0, 20.0]), safe)
    np.testing.assert_allclose([y_min, y_max], [[-0.75, -0.75], [0.75, 0.75]], atol=1e-12)
    plan = np.array([[10.0, 0.5], [20.0, 0.5], [30.0, 0.5]])
    m = plan_margins(f, plan, 5.0, safe)
    np.testing.assert_allclose(m["left"], 0.25, atol=1e-12)
    np.testing.assert_allclose(m["right"], 1.25, atol=1e-12)
    b = bernstein_margins(f, plan, safe)
    y_coef = plan[:, 1] @ bspline.ELEVATE_3_TO_6[:, 1:].T  # the plan's y, degree 6
    np.testing.assert_allclose(b["left"], 0.75 - y_coef, atol=1e-12)
    np.testing.assert_allclose(b["right"], 0.75 + y_coef, atol=1e-12)
    assert b["left"][0] == pytest.approx(0.75) and b["left"][6] == pytest.approx(0.25)


def test_an_unknown_mode_is_named() -> None:
    f = planner_features([1.75, 0.0, 0.0], [-1.75, 0.0, 0.0], 30.0, 30.0, 100.0)
    with pytest.raises(ValueError, match="mode must be one of .*'nope'"):
        project_plan(f, np.zeros((3, 2)), 5.0, mode="nope")


def test_a_lane_narrower_than_the_car_puts_the_control_points_on_its_centre() -> None:
    """control_points mode, a 1 m lane off centre (lines at 1.5 and 0.5): y = 1.0."""
    f = planner_features([1.5, 0.0, 0.0], [0.5, 0.0, 0.0], 20.0, 20.0, 50.0)
    plan = np.array([[10.0, 3.0], [20.0, 0.0], [30.0, -3.0]])
    filtered, acted = project_plan(f, plan, 4.0, mode="control_points")
    assert acted
    np.testing.assert_allclose(filtered[:, 1], 1.0, atol=1e-12)


@pytest.mark.parametrize("mode", ["bernstein", "control_points"])
def test_one_plan_for_many_states_and_many_plans_for_one_state(mode: str) -> None:
    """Plans (4, 3, 2) with features (9,) give (4, 3, 2), each row filtered as alone; in the
    default mode so do plans (3, 2) with features (4, 9) (control_points mode needs the plans'
    batch shape: it writes into a copy of them)."""
    rng = np.random.default_rng(5)
    feats = np.stack([planner_features([1.75 + o, 0.0, 0.0], [-1.75 + o, 0.0, 0.0], 30.0,
                                       30.0, 60.0) for o in (-1.0, -0.3, 0.3, 1.0)])
    plan = np.array([[50.0, 0.4], [100.0, 0.8], [150.0, 1.2]])
    if mode == "bernstein":
        got, acted = project_plan(feats, plan, 5.0, mode=mode)
        assert got.shape == (4, 3, 2) and acted.shape == (4,)
        for k in range(4):
            np.testing.assert_array_equal(got[k], project_plan(feats[k], plan, 5.0)[0])
    plans = rng.uniform([0.0, -2.0], [150.0, 2.0], size=(4, 3, 2))
    got, acted = project_plan(feats[1], plans, 5.0, mode=mode)
    assert got.shape == (4, 3, 2) and acted.shape == (4,)
    for k in range(4):
        np.testing.assert_array_equal(got[k], project_plan(feats[1], plans[k], 5.0, mode=mode)[0])


def test_a_plan_back_inside_from_a_car_outside_is_kept() -> None:
    """The car is 0.5 m right of the band (band y in [0.5, 2.24]): a plan whose coefficients
    k >= 1 are inside (y = 1.2, coefficient 1 = 0.6) is kept as it is, not replaced by the
    lane centre (1.37)."""
    near = planner_features([3.12, 0.0, 0.0], [-0.38, 0.0, 0.0], 30.0, 30.0, 200.0)
    x = 30.0 * bspline.control_point_times(5.0)
    plan = np.stack([x, np.full(3, 1.2)], axis=-1)
    got, acted = project_plan(near, plan, 5.0)
    assert not acted
    np.testing.assert_array_equal(got, plan)
    # far from constant speed on a bend, from outside: the reference at the plan's own x (the
    # constant-speed fallback is for a car inside the band)
    bend = planner_features([3.12, 0.0, 0.004], [-0.38, 0.0, 0.004], 30.0, 30.0, 200.0)
    wild = np.array([[1.0, 0.0], [2.0, 0.0], [150.0, 8.0]])
    got, acted = project_plan(bend, wild, 5.0)
    assert acted
    np.testing.assert_array_equal(got[:, 0], wild[:, 0])


def test_the_constant_speed_fallback_by_hand() -> None:
    """A bend (c2 = 0.004), a lane centred 0.3 m left, and an x profile far from constant
    speed (1, 2, 150 m): no cubic y follows the lane, so x becomes the constant-speed profile
    ending at min(x3, 3 x_max_i / i) and y the lane centre at it, 0.3 + 0.004 end^2 (0, 1/3,
    1). Far leader: end = 150 (the plan's own end); a leader 40 m ahead at 10 m/s: x_max =
    (56.7, 73.3, 90) at t = 5/3, 10/3, 5 s, end = 90. In one batch, each as alone."""
    def feats(d_lead: float) -> np.ndarray:
        return planner_features([2.05, 0.0, 0.004], [-1.45, 0.0, 0.004], 30.0, 10.0, d_lead)

    plan = np.array([[1.0, 0.0], [2.0, 0.0], [150.0, 8.0]])
    want = {}
    for d, end in ((200.0, 150.0), (40.0, 90.0)):
        got, acted = project_plan(feats(d), plan, 5.0)
        want[d] = np.stack([end * np.array([1 / 3, 2 / 3, 1.0]),
                            0.3 + 0.004 * end**2 * np.array([0.0, 1 / 3, 1.0])], axis=-1)
        assert acted
        np.testing.assert_allclose(got, want[d], rtol=0, atol=1e-9)
    both, _ = project_plan(np.stack([feats(200.0), feats(40.0)]), plan, 5.0)
    np.testing.assert_allclose(both, np.stack([want[200.0], want[40.0]]), rtol=0, atol=1e-9)
    # 2 m + 1 s of headway (32 m at 30 m/s): x_max = d - 32 + 10 t; the FIRST control point
    # binds, end = 3 x_max_1 = 14 m (d = 20) and 29 m (d = 25); in one batch, each its own
    headway = SafeSet(gap_min=2.0, time_gap=1.0)
    got, _ = project_plan(np.stack([feats(20.0), feats(25.0)]), plan, 5.0, headway)
    for k, end in enumerate((14.0, 29.0)):
        np.testing.assert_allclose(got[k], np.stack(
            [end * np.array([1 / 3, 2 / 3, 1.0]),
             0.3 + 0.004 * end**2 * np.array([0.0, 1 / 3, 1.0])], axis=-1), rtol=0, atol=1e-9)
