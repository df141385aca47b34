"""Certification (issue 23, part 1): sound network bounds, the planner as one network, the
margins' bounds, branch and bound with confirmed counterexamples, the certificate's loader.

Everything here is pure numpy (no torch, no SUMO) and small: the branch-and-bound runs use box
budgets of a few thousand boxes on the shipped checkpoints.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from safeil_sumo.core import bspline
from safeil_sumo.learn import bounds as bnd
from safeil_sumo.learn import branch_and_bound as cert
from safeil_sumo.learn import certify_margins as cm
from safeil_sumo.learn.branch_and_bound import Budget, CertifyError, certify
from safeil_sumo.learn.certificate import load_certificate, write_certificate
from safeil_sumo.learn.checkpoint import checkpoint_paths, load_checkpoint
from safeil_sumo.learn.envelope import EnvelopeConfig, sample_states
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.planners import registry as pol

TOL = 1e-9  # float slack when comparing sampled outputs with sound bounds [same units]


def random_net(rng: np.random.Generator, act: str, widths=(4, 16, 16, 3)) -> list[bnd.Layer]:
    layers = []
    for j in range(len(widths) - 1):
        w = rng.normal(size=(widths[j + 1], widths[j])) / np.sqrt(widths[j]) * 1.5
        kind = act if j < len(widths) - 2 else "identity"
        layers.append(bnd.Layer.dense(w, rng.normal(size=widths[j + 1]) * 0.5, kind))
    return layers


def random_boxes(rng: np.random.Generator, n: int, d: int) -> tuple[np.ndarray, np.ndarray]:
    centre = rng.normal(size=(n, d))
    half = np.exp(rng.uniform(np.log(1e-3), np.log(1.0), (n, d)))
    return centre - half, centre + half


def inside(lo: np.ndarray, hi: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """``k`` points per box ``(N, k, d)``, corners included."""
    pts = lo[:, None] + rng.uniform(size=(len(lo), k, lo.shape[1])) * (hi - lo)[:, None]
    pts[:, 0], pts[:, 1] = lo, hi
    return pts


# ------------------------------------------------------------------ bounds of a network


@pytest.mark.parametrize("act", ["tanh", "relu"])
def test_ibp_and_crown_contain_the_outputs_and_crown_is_tighter(act: str) -> None:
    rng = np.random.default_rng(23)
    widths_ibp, widths_crown = [], []
    for _ in range(3):
        layers = random_net(rng, act)
        lo, hi = random_boxes(rng, 64, 4)
        y = bnd.forward(layers, inside(lo, hi, 300, rng))  # (64, 300, 3)
        i_lo, i_hi = bnd.output_bounds(layers, lo, hi, method="ibp")
        c_lo, c_hi = bnd.output_bounds(layers, lo, hi, method="crown")
        for low, high in ((i_lo, i_hi), (c_lo, c_hi)):
            assert np.all(y >= low[:, None] - TOL) and np.all(y <= high[:, None] + TOL)
        # CROWN alone (not intersected with IBP) also contains them
        nb = bnd.propagate(layers, lo, hi)
        eye = np.eye(3)
        raw = bnd.crown(nb, layers, np.concatenate([eye, -eye])).lower
        assert np.all(y >= raw[:, None, :3] - TOL) and np.all(y <= -raw[:, None, 3:] + TOL)
        widths_ibp.append(i_hi - i_lo)
        widths_crown.append(-raw[:, 3:] - raw[:, :3])
    mean_ibp, mean_crown = np.mean(widths_ibp), np.mean(widths_crown)
    # measured: tanh 0.56x, relu 0.44x of IBP's mean width; assert a weak version
    assert mean_crown < 0.9 * mean_ibp, (mean_crown, mean_ibp)


def test_relaxation_lines_enclose_tanh_and_relu() -> None:
    rng = np.random.default_rng(1)
    lo = rng.uniform(-8, 3, 20000)
    hi = lo + rng.exponential(2, 20000) * rng.choice([1e-10, 1e-3, 1.0, 1.0], 20000)
    p = lo[:, None] + (hi - lo)[:, None] * np.linspace(0, 1, 101)
    for code, f in ((bnd.TANH, np.tanh), (bnd.RELU, lambda x: np.maximum(x, 0.0))):
        a_l, b_l, a_u, b_u = bnd.relax(np.full(len(lo), code), lo, hi)
        assert np.all(a_l[:, None] * p + b_l[:, None] <= f(p))
        assert np.all(a_u[:, None] * p + b_u[:, None] >= f(p))


def test_one_hidden_unit_by_hand() -> None:
    """``y = 3 tanh(2 x - 1) - 1`` on ``x in [0.5, 1.5]``: the pre-activation is in [0, 2], where
    tanh is concave: IBP gives [-1, 3 tanh 2 - 1]; CROWN's lower line is the chord (exact at
    p = 0: -1) and its upper line the tangent at p = 1, whose maximum at p = 2 is
    ``3 (tanh 1 + sech^2 1) - 1``, looser than IBP there, so the combined bound is IBP's."""
    layers = [bnd.Layer.dense([[2.0]], [-1.0], "tanh"), bnd.Layer.dense([[3.0]], [-1.0],
                                                                        "identity")]
    lo, hi = np.array([[0.5]]), np.array([[1.5]])
    i_lo, i_hi = bnd.output_bounds(layers, lo, hi, method="ibp")
    assert i_lo[0, 0] == pytest.approx(-1.0, abs=1e-9)
    assert i_hi[0, 0] == pytest.approx(3 * np.tanh(2.0) - 1, abs=1e-9)
    nb = bnd.propagate(layers, lo, hi)
    raw = bnd.crown(nb, layers, np.array([[1.0], [-1.0]])).lower[0]
    assert raw[0] == pytest.approx(-1.0, abs=1e-9)
    t1 = np.tanh(1.0)
    assert -raw[1] == pytest.approx(3 * (t1 + 1 - t1 ** 2) - 1, abs=1e-9)
    c_lo, c_hi = bnd.output_bounds(layers, lo, hi, method="crown")
    assert (c_lo[0, 0], c_hi[0, 0]) == pytest.approx((i_lo[0, 0], i_hi[0, 0]), abs=1e-9)
    # one ReLU unit on [-1, 2]: upper chord 2/3 (x + 1) (max 2 at x = 2), lower line x (slope 1
    # as u >= -l: min -1); IBP [0, 2]; combined [0, 2]
    relu = [bnd.Layer.dense([[1.0]], [0.0], "relu")]
    nb = bnd.propagate(relu, np.array([[-1.0]]), np.array([[2.0]]))
    raw = bnd.crown(nb, relu, np.array([[1.0], [-1.0]])).lower[0]
    assert (raw[0], -raw[1]) == pytest.approx((-1.0, 2.0), abs=1e-9)
    assert bnd.output_bounds(relu, np.array([[-1.0]]), np.array([[2.0]]))[0][0, 0] == \
        pytest.approx(0.0, abs=1e-9)
    # tanh across 0 on [-3, 0.5] (midpoint below 0): the upper line is (within the bisection's
    # tolerance) the tangent from (-3, tanh -3), i.e. of the largest secant slope from -3,
    # passing just above that point
    _, _, a_u, b_u = bnd.relax(np.array([bnd.TANH]), np.array([-3.0]), np.array([0.5]))
    p = np.linspace(-3, 0.5, 300001)[1:]
    best = np.max((np.tanh(p) - np.tanh(-3.0)) / (p + 3.0))
    assert best - 1e-3 <= a_u[0] <= best + 1e-9
    assert 0.0 <= -3.0 * a_u[0] + b_u[0] - np.tanh(-3.0) <= 1e-3
    # on [-0.2, 2] the midpoint's tangent (at 0.9) clears (-0.2, tanh -0.2): it is the upper line
    _, _, a_u, b_u = bnd.relax(np.array([bnd.TANH]), np.array([-0.2]), np.array([2.0]))
    assert a_u[0] == pytest.approx(1 - np.tanh(0.9) ** 2, abs=1e-12)
    assert b_u[0] == pytest.approx(np.tanh(0.9) - 0.9 * a_u[0], abs=1e-9)


def test_interval_and_crown_output_bounds_of_a_cancelling_network_by_hand() -> None:
    """``y = relu(relu(x) - relu(x) + 1)`` on x in [-1, 2] (always 1). Interval propagation
    sees two independent units in [0, 2]: the inner sum in [-1, 3], y in [0, 3]. CROWN bounds
    each unit between x (below) and the chord 2/3 (x + 1) (above): the inner sum in [0, 2] and
    y in [0, 2]. And ``z = relu(x) - relu(x)``: [-2, 2] by intervals, [-1, 1] by CROWN (its
    lower bound x - 2/3 (x + 1) is -1 at x = -1). Each method is the one asked for (cases found
    by mutation testing)."""
    twin = bnd.Layer.dense([[1.0], [1.0]], [0.0, 0.0], "relu")
    lo, hi = np.array([[-1.0]]), np.array([[2.0]])
    y = [twin, bnd.Layer.dense([[1.0, -1.0]], [1.0], "relu"),
         bnd.Layer.dense([[1.0]], [0.0], "identity")]
    assert np.allclose(bnd.output_bounds(y, lo, hi, method="ibp"), ([[0.0]], [[3.0]]),
                       atol=1e-9)
    assert np.allclose(bnd.output_bounds(y, lo, hi), ([[0.0]], [[2.0]]), atol=1e-9)
    z = [twin, bnd.Layer.dense([[1.0, -1.0]], [0.0], "identity")]
    assert np.allclose(bnd.output_bounds(z, lo, hi, method="ibp"), ([[-2.0]], [[2.0]]),
                       atol=1e-9)
    assert np.allclose(bnd.output_bounds(z, lo, hi, method="crown"), ([[-1.0]], [[1.0]]),
                       atol=1e-9)


def test_widening_is_strictly_outward_by_hand() -> None:
    """Every interval is widened by 1e-12 (1 + |bound|) on each side: never inward, also at 0
    and for tiny and huge bounds (cases found by mutation testing: an inward widening passed
    every comparison made with a 1e-9 tolerance)."""
    lo = np.array([0.0, -2.0, 3.0, -1e-300, 1e6, -1e6])
    hi = np.array([0.0, 3.0, 3.0, 1e-300, 2e6, -1e6])
    w_lo, w_hi = bnd._widen(lo, hi)
    assert np.all(w_lo < lo) and np.all(w_hi > hi)
    np.testing.assert_array_equal(w_lo, lo - 1e-12 * (1.0 + np.abs(lo)))
    np.testing.assert_array_equal(w_hi, hi + 1e-12 * (1.0 + np.abs(hi)))
    assert bnd._widen(np.array(0.0), np.array(0.0)) == (-1e-12, 1e-12)
    assert bnd.INTERVAL_SLACK == 1e-12 and bnd.RELAX_SLACK == 1e-12


@pytest.mark.parametrize("act", ["tanh", "relu"])
@pytest.mark.parametrize("method", ["ibp", "crown"])
def test_point_boxes_bound_the_network_strictly_with_no_tolerance(act: str, method: str) -> None:
    """Over a box of one point, the bounds enclose the network's value strictly: the widening
    against rounding must point outwards (no tolerance here: rounding inwards by 1e-12 of the
    value is what this catches)."""
    rng = np.random.default_rng(5)
    layers = random_net(rng, act)
    x = rng.normal(size=(200, 4)) * 3.0
    y = bnd.forward(layers, x)
    low, high = bnd.output_bounds(layers, x, x, method=method)
    assert np.all(low < y) and np.all(y < high)
    # and they are tight: the float margin the caller subtracts (1e-6 m) dwarfs the width
    assert np.all(high - low < 1e-9 * (1.0 + np.abs(y)))
    pre = bnd.propagate(layers, x, x, method=method).pre
    for (pl, pu), h in zip(pre, _pre_activations(layers, x), strict=True):
        assert np.all(pl < h) and np.all(h < pu)


def _pre_activations(layers: list[bnd.Layer], x: np.ndarray) -> list[np.ndarray]:
    out, h = [], x
    for layer in layers:
        p = h @ layer.weight.T + layer.bias
        out.append(p)
        h = bnd.forward([layer], h)
    return out


# ------------------------------------------------------------------ the planner as one network


def _plans(policy: MLPPolicy, outputs: np.ndarray, features: np.ndarray) -> np.ndarray:
    """Plans ``(N, 6)`` from the composed network's plan rows ``outputs (N, 6)``: themselves,
    or for a lane-following head x and the lane head's y from its offsets' z."""
    if policy.lateral_mode != "lane":
        return outputs
    x, z = outputs[:, 0::2], outputs[:, 1::2]
    y = bspline.lane_following_y(features[:, :6], x, z, policy.lane_keep_m)
    return np.stack([x, y], axis=-1).reshape(-1, 6)


@pytest.fixture(scope="module")
def safeil() -> MLPPolicy:
    return pol.load("safeil")


def test_the_envelope_is_what_training_samples() -> None:
    env, cfg = cm.CertEnvelope(), EnvelopeConfig()
    for name in cm.DIM_NAMES:
        assert getattr(env, name) == getattr(cfg, name)
    assert (env.brake_mps2, env.radar_range_m, env.no_leader_share) == (
        cfg.brake_mps2, cfg.radar_range_m, cfg.no_leader_share)
    f = sample_states(4000, np.random.default_rng(0))
    z = np.stack([f[:, 0] - f[:, 3], -0.5 * (f[:, 0] + f[:, 3]), f[:, 1], 2 * f[:, 2], f[:, 6],
                  f[:, 7] - f[:, 6], f[:, 8]], axis=1)
    lo, hi = env.root_boxes()["leader"]
    assert np.all(z >= lo - 1e-9) and np.all(z <= hi + 1e-9)
    assert np.all(env.recoverable(z))
    stopped = f[:, 7] == 0.0  # a clipped leader: any dv below -v_x gives the same features
    z[stopped, 5] = -z[stopped, 4] - 1.0
    np.testing.assert_allclose(env.features(z), f, atol=1e-12)
    free = f[:, 8] == cfg.radar_range_m
    assert free.mean() == pytest.approx(cfg.no_leader_share, abs=0.03)
    assert np.all(f[free, 7] == f[free, 6])


@pytest.mark.parametrize("name", ["safeil", "bc", "safeil_paper"])
def test_the_composed_network_is_the_planner(name: str) -> None:
    """The network of envelope coordinates (features carried along, residual folded in) gives
    MLPPolicy's plans, and its bounds contain them (catches a dropped residual term)."""
    policy = pol.load(name)
    env = cm.CertEnvelope()
    rng = np.random.default_rng(5)
    root_lo, root_hi = env.root_boxes()["leader"]
    layers = cm.planner_layers(policy, style_range=False)
    z = root_lo + rng.uniform(size=(500, 7)) * (root_hi - root_lo)
    y = bnd.forward(layers, z)
    np.testing.assert_allclose(_plans(policy, y[:, :6], env.features(z)),
                               policy.plan(env.features(z)).reshape(-1, 6), atol=1e-9)
    np.testing.assert_allclose(y[:, 6:], env.features(z), atol=1e-12)
    centre = root_lo + rng.uniform(size=(40, 7)) * (root_hi - root_lo)
    half = (root_hi - root_lo) * rng.uniform(0.005, 0.05, (40, 7))
    lo, hi = np.maximum(centre - half, root_lo), np.minimum(centre + half, root_hi)
    pts = inside(lo, hi, 100, rng)
    outs = bnd.forward(layers, pts.reshape(-1, 7))[:, :6].reshape(40, 100, 6)
    out_lo, out_hi = bnd.output_bounds(layers, lo, hi)
    assert np.all(outs >= out_lo[:, None, :6] - TOL) and np.all(outs <= out_hi[:, None, :6] + TOL)


def test_style_range_is_an_input_dimension(safeil: MLPPolicy) -> None:
    env = cm.CertEnvelope(time_gap_s=(0.8, 3.5))  # the settings a policy accepts
    lo, hi = env.root_boxes()["leader"]
    z = lo + np.random.default_rng(2).uniform(size=(50, 8)) * (hi - lo)
    y = bnd.forward(cm.planner_layers(safeil, style_range=True), z)
    policy = pol.load("safeil")
    for k in range(len(z)):
        policy.set_style(time_gap_s=z[k, 7])
        f = env.features(z[k])
        np.testing.assert_allclose(_plans(policy, y[k, None, :6], f[None])[0],
                                   policy.plan(f).ravel(), atol=1e-9)
    with pytest.raises(CertifyError, match="no style input"):
        certify(pol.load("bc"), env, budget=Budget(boxes=1), progress=False)


def test_a_head_and_properties_of_different_modes_are_refused() -> None:
    policy = pol.load("safeil")
    props = cm.Properties.from_metadata(policy.metadata)
    other = cm.Properties(props.horizon_s, props.track_m, lane_keep_m=(
        None if policy.lateral_mode == "lane" else 0.93))
    with pytest.raises(CertifyError, match="lane_keep_m"):
        certify(policy, props=other, budget=Budget(boxes=1), progress=False)


def test_the_lane_heads_bound_holds_whatever_its_offsets() -> None:
    """lane_head_lane_lower on random boxes and x intervals: at random points inside, with any
    offsets, the exact Bernstein coefficients of lane_following_y's plans are never below it;
    on a point where the residual's allowance covers the fit it is the clearance's share
    exactly (not vacuous), and where it may not (x too wide for the bend) it falls back."""
    props = cm.Properties(horizon_s=5.0, lane_keep_m=0.93)
    env = cm.CertEnvelope()
    root_lo, root_hi = env.root_boxes()["leader"]
    rng = np.random.default_rng(4)
    fallbacks = 0
    for _ in range(300):
        centre = root_lo + rng.uniform(size=7) * (root_hi - root_lo)
        half = (root_hi - root_lo) * rng.uniform(0.0005, 0.1)
        lo, hi = np.maximum(centre - half, root_lo), np.minimum(centre + half, root_hi)
        x_lo = np.sort(rng.uniform(-20.0, 200.0, 3))
        x_w = rng.uniform(0.0, 10.0, 3) * rng.choice([1.0, 10.0])
        bound = cm.lane_head_lane_lower(props, lo[None], hi[None], x_lo[None],
                                        (x_lo + x_w)[None])[0]
        fallbacks += bound.min() < 0.05 * 0.5 - 1e-9
        for _ in range(10):
            f = env.features(lo + rng.uniform(size=7) * (hi - lo))
            x = x_lo + rng.uniform(size=3) * x_w
            y = bspline.lane_following_y(f[:6], x, rng.normal(0.0, 5.0, 3), 0.93)
            plan = np.stack([x, y], axis=-1)
            m = np.r_[bspline.lateral_margin_bernstein(plan, f[0:3], -0.88)[1:],
                      -bspline.lateral_margin_bernstein(plan, f[3:6], 0.88)[1:]]
            assert np.all(m >= bound - 1e-9)
    assert 0 < fallbacks < 300  # both branches ran
    # tight on a point: x exact, the offsets at their limit -> the bound is reached
    z = np.array([3.5, 0.3, 0.0, 1.0 / 300.0, 25.0, 0.0, 50.0])
    x = np.array([30.0, 50.0, 60.0])
    bound = cm.lane_head_lane_lower(props, z[None], z[None], x[None], x[None])[0]
    share = bspline.ELEVATE_3_TO_6[1:, 0]
    np.testing.assert_allclose(bound[:6], share * (1.75 - 0.3 - 0.88) + (1.0 - share) * 0.05)
    f = env.features(z)
    y = bspline.lane_following_y(f[:6], x, np.full(3, 40.0), 0.93)
    exact = bspline.lateral_margin_bernstein(np.stack([x, y], -1), f[0:3], -0.88)[1:]
    assert np.all(exact >= bound[:6] - 1e-9)
    assert exact[-1] == pytest.approx(bound[5] + 0.5 / 300.0 * (
        bspline.lane_fit_allowance(x) + np.einsum("kab,a,b->k", bspline.LANE_FIT_RESIDUAL, x,
                                                  x)[-1]), abs=1e-9)


def test_the_residual_bound_from_linear_plan_bounds_holds() -> None:
    """_residual_from_linear_x: x between two linear functions of the box coordinates (as
    CROWN gives them), any x between them at any point of the box: R_k(x) inside its bounds
    (dropping the gap between the two linear bounds fails this)."""
    rng = np.random.default_rng(8)
    n, d = 200, 7
    lo = rng.uniform(-1.0, 1.0, (n, d))
    hi = lo + rng.uniform(0.0, 0.5, (n, d))
    a = rng.normal(0.0, 20.0, (n, 3, d))
    a[:, :, 0] = np.abs(a[:, :, 0]) * [1.0, 2.0, 3.0]
    c = rng.uniform(0.0, 100.0, (n, 3))
    gap = rng.uniform(0.0, 3.0, (n, 3))
    # rows 0..5: lower bounds of (x1, z1, x2, z2, x3, z3); 6..11: of their negatives
    coef = np.concatenate([np.repeat(a, 2, axis=1), -np.repeat(a, 2, axis=1)], axis=1)
    const = np.concatenate([np.repeat(c - gap, 2, axis=1), -np.repeat(c + gap, 2, axis=1)],
                           axis=1)
    plan = bnd.LinearBound(coef, const, np.zeros((n, 12)))
    r_lo, r_hi = cm._residual_from_linear_x(plan, lo, hi)
    for _ in range(50):
        z = lo + rng.uniform(size=(n, d)) * (hi - lo)
        x = np.einsum("nid,nd->ni", a, z) + c + rng.uniform(-1.0, 1.0, (n, 3)) * gap
        r = np.einsum("kab,na,nb->nk", bspline.LANE_FIT_RESIDUAL, x, x)
        assert np.all(r >= r_lo - 1e-6) and np.all(r <= r_hi + 1e-6)


def test_margin_bounds_contain_the_reference_margins(safeil: MLPPolicy) -> None:
    env = cm.CertEnvelope()
    props = cm.Properties.from_metadata(safeil.metadata)
    layers = cm.planner_layers(safeil, False)
    rng = np.random.default_rng(9)
    root_lo, root_hi = env.root_boxes()["leader"]
    centre = root_lo + rng.uniform(size=(200, 7)) * (root_hi - root_lo)
    half = (root_hi - root_lo) * np.exp(rng.uniform(np.log(0.003), np.log(0.3), (200, 7)))
    lo, hi = np.maximum(centre - half, root_lo), np.minimum(centre + half, root_hi)
    bb = cm.bound_boxes(layers, props, lo, hi)
    pts = inside(lo, hi, 100, rng)
    m = cm.reference_margins(safeil, env.features(pts.reshape(-1, 7)), props).reshape(200, 100,
                                                                                       15)
    assert np.all(m >= bb.lower[:, None] - TOL)
    for margin in cm.MARGINS:  # one margin alone (as branch and bound asks): sound too
        alone = cm.bound_boxes(layers, props, lo, hi, margin).lower
        assert np.all(m[..., cm.MARGIN_ROWS[margin]] >= alone[:, None] - TOL)


def test_the_margins_linear_enclosure_holds_at_every_plan_in_the_intervals() -> None:
    """``property_objective`` alone: for feature and plan intervals (no network), the linear
    lower bound ``C [plan; features] + const`` is below the exact margins (Bernstein
    coefficients from bspline, leader margin) at corners and random points of the intervals."""
    from safeil_sumo.core.bspline import lateral_margin_bernstein

    rng = np.random.default_rng(8)
    props = cm.Properties(horizon_s=5.0, track_m=1.76, gap_min_m=2.0, time_gap_margin_s=0.5)
    n, k = 300, 64
    f_mid = np.column_stack([rng.uniform(1.0, 2.5, n), rng.uniform(-0.03, 0.03, n),
                             rng.uniform(-0.002, 0.002, n), rng.uniform(-2.5, -1.0, n),
                             rng.uniform(-0.03, 0.03, n), rng.uniform(-0.002, 0.002, n),
                             rng.uniform(5, 35, n), rng.uniform(5, 35, n), rng.uniform(5, 150, n)])
    f_half = np.abs(f_mid) * rng.uniform(0.0, 0.3, (n, 9))
    f_half[: n // 3] = 0.0  # exact features: only the plan's products are relaxed
    y_mid = np.column_stack([f_mid[:, 6] * t + rng.normal(0, 5, n) if j % 2 == 0
                             else rng.normal(0, 3, n)
                             for j, t in enumerate(np.repeat([5 / 3, 10 / 3, 5.0], 2))])
    y_half = rng.uniform(0.0, 10.0, (n, 6))
    f_lo, f_hi, y_lo, y_hi = f_mid - f_half, f_mid + f_half, y_mid - y_half, y_mid + y_half
    C, const, _ = cm.property_objective(props, f_lo, f_hi, y_lo, y_hi)
    u = rng.uniform(size=(n, k, 15))
    u[:, : k // 2] = rng.integers(0, 2, (n, k // 2, 15))  # corners
    lo, hi = np.concatenate([y_lo, f_lo], 1), np.concatenate([y_hi, f_hi], 1)
    pts = lo[:, None] + u * (hi - lo)[:, None]  # (n, k, 15): plan, then features
    f, cp = pts[..., 6:], pts[..., :6].reshape(n, k, 3, 2)
    times = np.arange(1, 4) * 5.0 / 3.0
    lead = f[..., 8, None] + f[..., 7, None] * times - cp[..., 0]
    lead -= cm._lead_extra(f[..., 6], f[..., 7], f[..., 8], props)[..., None]
    left = lateral_margin_bernstein(cp, f[..., 0:3], -0.88)[..., 1:]
    right = -lateral_margin_bernstein(cp, f[..., 3:6], 0.88)[..., 1:]
    exact = np.concatenate([lead, left, right], axis=-1)
    bound = np.einsum("nmj,nkj->nkm", C, pts) + const[:, None]
    assert np.all(exact >= bound - 1e-9)
    # and it is not vacuous: on average within a few metres of the exact minimum
    assert np.mean(exact.min(axis=1) - bound.min(axis=1)) < 50.0


# the margins' bounds and branching scores of 12 seeded boxes of the shipped safeil, per box the
# sum over the margin's rows (measured 2026-11-28; float64, deterministic on one machine, equal
# across machines to ~1e-12): any change of the bound's algebra, looser or tighter, moves them
GOLDEN_MARGIN_BOUNDS = {
    ("leader", "lower_sum"): [160.5581756, 61.89591393, 128.4129537, 251.6565109, 145.1419621, 21.6325104, 96.20972932, 226.9612627, 4.076331567, 219.0716879, 254.3140639, 213.6541456],
    ("leader", "score_sum"): [150.1987408, 78.00332281, 123.7971256, 47.23707331, 103.8731833, 53.88374991, 91.79152119, 101.7501867, 177.3469822, 36.97234943, 159.9161865, 132.8209853],
    ("lane", "lower_sum"): [0.6400752694, -0.8010566679, -0.06119433709, 1.230320374, 0.8027353906, 0.7918198949, 0.216169842, 0.8289290241, -1.685293375, 0.7974833914, 0.09196976822, 1.02179015],
    ("lane", "score_sum"): [0.1866498794, 6.308013076, 5.265197672, 0.06224294101, 0.2057218635, 0.2488334388, 5.10409982, 0.04505315867, 8.235537833, 0.305766759, 4.986274038, 0.6264093526],
}


def test_margin_bounds_and_scores_are_the_golden_ones(safeil: MLPPolicy) -> None:
    """A regression pin (cases found by mutation testing: a looser residual bound, other
    branching scores and mis-sliced lane rows all stayed sound, so no soundness test saw
    them)."""
    env = cm.CertEnvelope()
    props = cm.Properties.from_metadata(safeil.metadata)
    layers = cm.planner_layers(safeil, False)
    rng = np.random.default_rng(43)
    root_lo, root_hi = env.root_boxes()["leader"]
    centre = root_lo + rng.uniform(size=(12, 7)) * (root_hi - root_lo)
    half = (root_hi - root_lo) * np.exp(rng.uniform(np.log(0.01), np.log(0.2), (12, 7)))
    lo, hi = np.maximum(centre - half, root_lo), np.minimum(centre + half, root_hi)
    for margin in ("leader", "lane"):
        bb = cm.bound_boxes(layers, props, lo, hi, margin)
        rows = cm.MARGIN_ROWS[margin]
        got = {"lower_sum": bb.lower[:, rows].sum(axis=1),
               "score_sum": bb.score[:, rows].sum(axis=(1, 2))}
        for name, value in got.items():
            np.testing.assert_allclose(value, GOLDEN_MARGIN_BOUNDS[margin, name], rtol=1e-8,
                                       atol=1e-8, err_msg=f"{margin} {name}")


def test_the_box_tree_grows_and_keeps_its_boxes() -> None:
    from safeil_sumo.learn.branch_and_bound import _Tree

    tree = _Tree(2, cap=4)
    first = tree.add(lo=np.zeros((3, 2)), hi=np.ones((3, 2)), part=0)
    more = tree.add(lo=np.full((10, 2), 2.0), hi=np.full((10, 2), 3.0), part=1)
    assert list(first) == [0, 1, 2] and list(more) == list(range(3, 13))
    assert tree.n == 13 and tree.cap == 13 and tree.lo.shape == (13, 2)
    assert np.all(tree.lo[:3] == 0.0) and np.all(tree.hi[3:13] == 3.0)
    assert list(tree.part[:13]) == [0] * 3 + [1] * 10 and np.all(tree.lower[:13] == -np.inf)
    tree.add(lo=np.zeros((1, 2)), hi=np.ones((1, 2)), part=0)
    assert tree.cap == 26 and tree.n == 14 and np.all(tree.hi[3:13] == 3.0)


def test_the_first_candidate_is_the_corner_minimising_the_linear_bound() -> None:
    from safeil_sumo.learn.branch_and_bound import _candidates

    env = cm.CertEnvelope()
    lo, hi = env.root_boxes()["free"]
    lo, hi = lo[None], hi[None]
    coef = np.array([[1.0, -1.0, 2.0, -3.0, 0.5, -0.5, 1.0]])
    pts, _ = _candidates(env, lo, hi, np.array([1]), coef, np.random.default_rng(0), 2)
    np.testing.assert_array_equal(pts[0, 0], np.where(coef[0] > 0, lo[0], hi[0]))
    np.testing.assert_array_equal(pts[0, 1], 0.5 * (lo[0] + hi[0]))
    assert pts.shape == (1, 4, 7)


def test_box_volumes_bracket_a_monte_carlo_estimate() -> None:
    env = cm.CertEnvelope()
    rng = np.random.default_rng(4)
    lo = np.array([3.3, -0.6, -0.03, -0.004, 5.0, -15.0, 3.0])
    hi = np.array([3.8, 0.6, 0.03, 0.004, 25.0, 0.0, 40.0])
    low, high = cm.box_shares(env, lo[None], hi[None], "leader")
    u = rng.uniform(size=(400000, 7))
    z = lo + u * (hi - lo)
    z[:, 6] = np.exp(np.log(lo[6]) + u[:, 6] * np.log(hi[6] / lo[6]))
    base = np.prod(hi[:6] - lo[:6]) * np.log(hi[6] / lo[6])
    mc = base * env.recoverable(z).mean()
    assert low[0] <= mc * 1.01 and mc <= high[0] * 1.01 and low[0] < high[0]
    assert (high[0] - low[0]) / high[0] < 0.1
    a, b = cm.envelope_volume(env, "leader")
    assert a <= b and (b - a) / b < 1e-3


# ------------------------------------------------------------------ branch and bound


def test_certified_mass_accounting_by_hand() -> None:
    """Two parts, weights 0.7 and 0.3; part 0's volume is known within [2, 2.5] (shares are of
    the upper volume, so the open boxes may hold 2.5 / 2 = 1.25 times their share), part 1's
    exactly (1)."""
    w = np.array([0.7, 0.3])
    vol = np.array([[2.0, 2.5], [1.0, 1.0]])
    zero = np.zeros(2)
    # nothing proven, every box open (the roots: share 1 each): nothing certified, exactly
    np.testing.assert_array_equal(cert.certified_mass(zero, w * 1.0, w, vol), [0.0, 0.0])
    # everything proven: the proven boxes' smallest volume says 0.8 of part 0 (2 / 2.5), the
    # empty rest says all of it: the larger wins
    np.testing.assert_array_equal(cert.certified_mass(np.array([0.56, 0.3]), zero, w, vol),
                                  [0.7, 0.3])
    # a mix. Part 0: proven share 0.5 (mass 0.35), open share 0.3 (mass 0.21): the rest is
    # 0.7 - 1.25 * 0.21 = 0.4375 > 0.35. Part 1: proven 0.5 (0.15), open 0.4 (0.12): the rest,
    # 0.3 - 0.12 = 0.18, beats 0.15
    got = cert.certified_mass(np.array([0.35, 0.15]), np.array([0.21, 0.12]), w, vol)
    np.testing.assert_allclose(got, [0.4375, 0.18], rtol=0, atol=1e-15)
    # open boxes whose upper volume overlaps (share sum 0.9 > 0.8 of the weight left): the
    # proven mass stands
    got = cert.certified_mass(np.array([0.07, 0.0]), np.array([0.63, 0.3]), w, vol)
    np.testing.assert_allclose(got, [0.07, 0.0], rtol=0, atol=1e-15)
    # a rest that is only a sum's rounding (<= 1e-12) is not certified
    tiny = cert.certified_mass(zero, np.array([0.0, 0.3 - 1e-13]), w, vol)
    np.testing.assert_array_equal(tiny, [0.7, 0.0])



@pytest.mark.parametrize(("margin", "boxes"), [("leader", 3000), ("lane", 1500)])
def test_sampled_points_in_proven_boxes_never_violate(safeil: MLPPolicy, margin: str,
                                                       boxes: int) -> None:
    env = cm.CertEnvelope()
    result = certify(safeil, env, budget=Budget(boxes=boxes, batch=256), margins=(margin,),
                     progress=False)
    props = result.properties
    rng = np.random.default_rng(11)
    for name, m in result.margins.items():
        assert m.proven_boxes > 0 and 0.0 < m.certified <= 1.0
        lo, hi, part = (m.boxes[k] for k in ("proven_lo", "proven_hi", "proven_part"))
        pick = rng.choice(len(lo), size=min(len(lo), 400), replace=False)
        pts = inside(lo[pick], hi[pick], 25, rng).reshape(-1, 7)
        ok = env.recoverable(pts) | (np.repeat(part[pick], 25) == 1)
        margins = cm.reference_margins(safeil, env.features(pts[ok]), props)
        assert np.all(margins[:, cm.MARGIN_ROWS[name]] >= 0.0), name
        for c in m.counterexamples:  # every counterexample is one for the network itself
            f = np.array(c["features"])
            assert c["confirmed"] and cm.reference_margins(safeil, f[None], props)[
                0, cm.MARGIN_ROWS[name]].min() < 0


def test_the_shipped_lane_head_is_certified_on_the_whole_envelope(safeil: MLPPolicy) -> None:
    # its offsets' room less the centre fit's allowance: proven on every box once the x control
    # points' bounds are tight enough to rule out a residual larger than the room (~5,000 boxes)
    result = certify(safeil, budget=Budget(boxes=20_000, batch=256), margins=("lane",),
                     progress=False)
    m = result.margins["lane"]
    assert m.stopped_by == "proven" and m.open_boxes == 0
    assert m.certified == pytest.approx(1.0, abs=1e-12)
    # its certificate says so: complete
    from safeil_sumo.learn.certificate import build_certificate

    body = build_certificate(result, pol.shipped_checkpoint("safeil"))
    assert body["margins"]["lane"]["complete"] is True and body["complete"] is True


def test_a_deliberately_unsafe_network_gets_confirmed_counterexamples() -> None:
    """The shipped safeil with its x control points pushed 300 m ahead: every plan passes the
    leader. Each counterexample, re-evaluated here with MLPPolicy, violates the leader margin."""
    arrays, meta = load_checkpoint(pol.shipped_checkpoint("safeil"))
    arrays = {k: v.copy() for k, v in arrays.items()}
    arrays["output_mean"][[0, 2, 4]] += 300.0
    unsafe = MLPPolicy(arrays, meta["architecture"], "unsafe", meta["horizon_s"], meta)
    result = certify(unsafe, budget=Budget(boxes=600, batch=64), margins=("leader",),
                     progress=False)
    m = result.margins["leader"]
    assert m.certified == 0.0 and m.counterexample_boxes > 0 and m.counterexamples
    for c in m.counterexamples:
        f = np.array(c["features"])
        plan = unsafe.plan(f)
        leader = f[8] + f[7] * np.arange(1, 4) * meta["horizon_s"] / 3.0
        assert np.any(plan[:, 0] > leader)
        assert c["confirmed"] and c["margin_m"] < 0
        assert result.envelope.recoverable(np.array(list(c["z"].values())))


def test_a_short_branch_and_bound_of_bc_is_the_golden_one() -> None:
    """600 boxes of bc (measured 2026-11-28, seed 0): shares, box counts, where the unproven
    volume lies and the proven boxes' summary, as a regression pin of branch and bound's
    accounting (cases found by mutation testing: the parts' weights, the split dimension and
    the final-box rule changed none of the properties the other tests assert)."""
    r = certify(pol.load("bc"), budget=Budget(boxes=600, batch=64, seed=0), progress=False)
    lead, lane = r.margins["leader"], r.margins["lane"]
    assert (lead.certified, lead.with_counterexample) == pytest.approx(
        (0.1893634795559093, 0.44755819148584813), rel=1e-9)
    assert (lead.proven_boxes, lead.counterexample_boxes, lead.open_boxes, lead.boxes_bounded,
            lead.stopped_by, len(lead.counterexamples)) == (10, 103, 282, 300, "boxes", 20)
    assert lead.unproven_by_dim["gap_m"] == pytest.approx([0.2493, 0.2493, 0.3057, 0.1958],
                                                          abs=1e-4)
    assert lead.unproven_by_dim["curvature_1pm"] == pytest.approx(
        [0.2439, 0.2585, 0.2537, 0.2439], abs=1e-4)
    assert lead.proven_summary["count"] == 10 and lead.proven_summary["depth_range"] == [0, 8]
    assert lead.proven_summary["smallest_share"] == pytest.approx(0.0038853686763438812,
                                                                  rel=1e-9)
    assert (lane.certified, lane.proven_boxes, lane.counterexample_boxes, lane.open_boxes) == (
        0.0, 0, 207, 302)
    assert lane.with_counterexample == pytest.approx(0.8146796687085203, rel=1e-9)
    assert lane.unproven_by_dim["relative_speed_mps"] == pytest.approx(
        [0.2033, 0.2033, 0.247, 0.3464], abs=1e-4)
    # the rest of the record: unknown is what neither proof nor counterexample covers, the
    # parts' certified shares weigh up to the whole, the boxes' fields by name
    weights = cm.CertEnvelope().part_weights()
    for m in (lead, lane):
        assert m.unknown == pytest.approx(max(0.0, 1.0 - m.certified - m.with_counterexample))
        assert sum(weights[p] * m.certified_by_part[p] for p in weights) == pytest.approx(
            m.certified, rel=1e-12)
        assert 0.0 < m.seconds < 120.0
        assert set(m.boxes) == {"proven_lo", "proven_hi", "proven_part", "open_lo", "open_hi",
                                "open_part", "open_cex_z"}
        for box in m.unproven_boxes:
            assert set(box) == {"part", "share", "lower_bound_m", "counterexample_m", "lo",
                                "hi"} and set(box["hi"]) == set(box["lo"])
    assert 0.0 < lead.proven_summary["median_share"] <= 1.0
    assert lead.certified_by_part["free"] > 0.0 and lead.certified_by_part["leader"] >= 0.0


def test_branch_and_bound_stops_when_only_small_counterexample_boxes_are_left() -> None:
    """Every leader plan of the pushed network fails: with boxes holding a counterexample final
    below 5 % of the envelope, the search ends before its budget, 'small', nothing certified."""
    arrays, meta = load_checkpoint(pol.shipped_checkpoint("safeil"))
    arrays = {k: v.copy() for k, v in arrays.items()}
    arrays["output_mean"][[0, 2, 4]] += 300.0
    unsafe = MLPPolicy(arrays, meta["architecture"], "unsafe", meta["horizon_s"], meta)
    m = certify(unsafe, budget=Budget(boxes=600, batch=64, cex_min_share=0.05),
                margins=("leader",), progress=False).margins["leader"]
    assert (m.stopped_by, m.certified, m.boxes_bounded) == ("small", 0.0, 60)
    assert m.open_boxes == m.counterexample_boxes == 31
    # every box left was bounded and refuted: each carries its lower bound and counterexample
    assert all(isinstance(b["lower_bound_m"], float) and b["lower_bound_m"] < 0.0
               and b["counterexample_m"] < 0.0 for b in m.unproven_boxes)


def test_bc_has_counterexamples_on_both_margins() -> None:
    result = certify(pol.load("bc"), budget=Budget(boxes=1200, batch=128), progress=False)
    for m in result.margins.values():
        assert m.counterexamples and all(c["confirmed"] for c in m.counterexamples)


def test_same_seed_same_result(safeil: MLPPolicy) -> None:
    a, b = (certify(safeil, budget=Budget(boxes=1500, batch=256, seed=3), margins=("lane",),
                    progress=False).margins["lane"] for _ in range(2))
    assert (a.certified, a.counterexamples, a.unproven_by_dim) == (
        b.certified, b.counterexamples, b.unproven_by_dim)


# ------------------------------------------------------------------ certificates


def _copy_checkpoint(name: str, folder) -> str:
    weights, sidecar = checkpoint_paths(pol.shipped_checkpoint(name))
    shutil.copy(weights, folder / weights.name)
    shutil.copy(sidecar, folder / sidecar.name)
    return str(folder / weights.name)


def test_the_loader_rejects_a_modified_checkpoint(tmp_path) -> None:
    """Every status in full: valid only when both hashes match; each reason word for word, the
    certificate's path, shares and completeness as far as it could be read (cases found by
    mutation testing: only ``valid`` and a word of the reason were checked)."""
    import hashlib

    from safetensors.numpy import load as st_load
    from safetensors.numpy import save as st_save

    from safeil_sumo.learn.certificate import CertificateStatus

    path = _copy_checkpoint("safeil", tmp_path)
    result = certify(pol.load(path), budget=Budget(boxes=100, batch=50), progress=False)
    cert = write_certificate(result, path)
    assert cert == tmp_path / "safeil.certificate.json"
    body = json.loads(cert.read_text())
    certified = {m: r["certified"] for m, r in body["margins"].items()}
    assert set(certified) == {"leader", "lane"} and body["complete"] is False

    def status(valid: bool, reason: str, at=cert) -> CertificateStatus:
        return CertificateStatus(valid, reason, at, certified, False, body)

    assert load_certificate(path) == status(True, "ok")
    assert body["checkpoint"]["weights_sha256"] == json.loads(
        (tmp_path / "safeil.json").read_text())["weights_sha256"]
    # the certificate given by path (a copy elsewhere) is the one read
    elsewhere = tmp_path / "elsewhere.json"
    shutil.copy(cert, elsewhere)
    assert load_certificate(path, elsewhere) == status(True, "ok", elsewhere)
    # another style default in the sidecar: the certified function changed
    sidecar = tmp_path / "safeil.json"
    original = sidecar.read_text()
    meta = json.loads(original)
    meta["style_default"] = {"time_gap_s": 2.5}
    sidecar.write_text(json.dumps(meta))
    assert load_certificate(path) == status(
        False, "sha256 mismatch: the checkpoint's sidecar (style default, horizon, "
        "architecture or margins) changed")
    sidecar.write_text(original)
    assert load_certificate(path).valid
    # retrained weights, consistent with their sidecar: the certificate no longer applies
    weights = tmp_path / "safeil.safetensors"
    arrays = st_load(weights.read_bytes())
    arrays["net.4.bias"] = arrays["net.4.bias"] + np.float32(0.01)
    blob = st_save(arrays, metadata={"format": "safeil-checkpoint", "format_version": "1"})
    weights.write_bytes(blob)
    meta = json.loads(original)
    meta["weights_sha256"] = hashlib.sha256(blob).hexdigest()
    sidecar.write_text(json.dumps(meta))
    assert load_certificate(path) == status(
        False, "sha256 mismatch: the checkpoint's weights are not the certified ones")
    # corrupted weights: unreadable checkpoint, no valid certificate (what it said is kept)
    weights.write_bytes(blob[:-10] + b"0123456789")
    got = load_certificate(path)
    assert got.reason.startswith("checkpoint unreadable: ")
    assert got == status(False, got.reason)
    # no certificate at all: nothing read
    nope = tmp_path / "nope.json"
    assert load_certificate(path, nope) == CertificateStatus(
        False, f"{nope}: no certificate", nope, {}, False, None)


def test_a_certificate_says_what_the_shipped_one_says_of_its_own_run(tmp_path) -> None:
    """A short run (stopped by its box budget) of a copy of the shipped safeil, written into a
    folder that does not exist yet: its static content (what the bounds are, what the
    certificate covers, the envelope and properties) is the shipped certificate's, its run's
    own (budget, shares, completeness, time) is this run's (cases found by mutation testing:
    none of the certificate's text or run fields was pinned)."""
    import dataclasses
    import math
    import time

    from safeil_sumo.learn.certificate import read_certificate

    path = _copy_checkpoint("safeil", tmp_path)
    shipped = read_certificate(
        checkpoint_paths(pol.shipped_checkpoint("safeil"))[0].with_name("safeil.certificate.json"))
    env = cm.CertEnvelope(**{k: tuple(v) if isinstance(v, list) else v
                             for k, v in shipped["envelope"].items()})
    budget = Budget(boxes=100, batch=50)
    result = certify(pol.load(path), env, budget=budget, progress=False)
    before = time.time()
    out = write_certificate(result, path, tmp_path / "a" / "b")
    after = time.time()
    assert out == tmp_path / "a" / "b" / "safeil.certificate.json"
    text = out.read_text()
    body = json.loads(text)
    assert text == json.dumps(body, indent=1) + "\n"
    for key in ("format", "format_version", "checkpoint", "policy", "style", "envelope",
                "coordinates", "parts", "volume_measure", "properties", "bounds_method",
                "float_margin_m", "covers"):
        assert body[key] == shipped[key], key
    assert set(body) == set(shipped)
    for part, (low, high) in body["envelope_volume"].items():
        assert (low, high) == pytest.approx(shipped["envelope_volume"][part], rel=1e-9)
    assert body["budget"] == dataclasses.asdict(budget) and body["seconds"] == result.seconds
    assert before <= body["created_unix_s"] <= after
    assert body["complete"] is False and shipped["complete"] is True
    for name, m in result.margins.items():
        got = body["margins"][name]
        assert set(got) == set(shipped["margins"][name]) and "boxes" not in got
        assert m.stopped_by == "boxes" and got["complete"] is False
        assert (got["certified"], got["stopped_by"], got["boxes_bounded"]) == (
            m.certified, "boxes", m.boxes_bounded)
    # a run whose margins were all proven is complete
    from safeil_sumo.learn.certificate import build_certificate

    proven = dataclasses.replace(result, margins={
        n: dataclasses.replace(m, stopped_by="proven") for n, m in result.margins.items()})
    done = build_certificate(proven, path)
    assert done["complete"] is True and all(m["complete"] for m in done["margins"].values())
    # a value JSON cannot hold (NaN) is refused before anything is written
    with pytest.raises(ValueError):
        write_certificate(dataclasses.replace(result, seconds=math.nan), path, tmp_path / "c")
    assert not (tmp_path / "c").exists() or not any((tmp_path / "c").iterdir())


def test_a_certificate_file_is_refused_with_its_reason(tmp_path) -> None:
    from safeil_sumo.learn.certificate import CertificateError, read_certificate

    good = json.loads((pol.shipped_checkpoint("safeil").parent / "safeil.certificate.json")
                      .read_text())
    path = tmp_path / "c.json"
    cases = ((b"{not json", "unreadable certificate"),
             (json.dumps([1, 2]).encode(), "not a safeil-certificate file"),
             (json.dumps({**good, "format": "other"}).encode(), "not a safeil-certificate file"),
             (json.dumps({**good, "format_version": 9}).encode(),
              "format version 9, this code reads 1"),
             (json.dumps({**good, "coordinates": ["a"]}).encode(),
              "envelope coordinates ['a'] are not this code's"),
             (json.dumps({k: v for k, v in good.items() if k != "coordinates"}).encode(),
              "envelope coordinates None are not this code's"))
    for body, reason in cases:
        path.write_bytes(body)
        with pytest.raises(CertificateError) as err:
            read_certificate(path)
        assert str(err.value).startswith(f"{path}: ") and reason in str(err.value), reason
    with pytest.raises(CertificateError, match="no certificate"):
        read_certificate(tmp_path / "none.json")
    assert read_certificate(pol.shipped_checkpoint("safeil").parent
                            / "safeil.certificate.json") == good


def test_cli_certifies_writes_and_checks(tmp_path, capsys) -> None:
    from safeil_sumo import certify as cli

    path = _copy_checkpoint("bc", tmp_path)
    assert cli.main(["--policy", path, "--max-boxes", "200", "--batch", "50",
                     "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "leader" in out and "lane" in out and "counterexample" in out
    assert (tmp_path / "bc.certificate.json").is_file()
    assert cli.main(["--policy", path, "--check"]) == 0
    assert "valid" in capsys.readouterr().out
    for argv, message in ((["--policy", "analytic"], "not a network checkpoint"),
                          (["--policy", path, "--time-gap-range-s", "1", "2"], "no style input"),
                          (["--policy", "nope.safetensors"], "does not exist")):
        assert cli.main([*argv, "--max-boxes", "10", "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error:") and message in err and err.count("\n") == 1


def test_the_shipped_safeil_carries_a_valid_complete_certificate(capsys) -> None:
    """Its certificate (both margins, the whole envelope and style range 0.6-3.5 s, written by
    training/train_shipped_models.py) matches the shipped weights: retraining without
    recertifying fails here."""
    from safeil_sumo import certify as cli

    path = pol.shipped_checkpoint("safeil")
    status = load_certificate(path)
    assert status.valid, status.reason
    assert status.complete and status.certified == {"leader": 1.0, "lane": 1.0}
    assert status.certificate["style"] == {"time_gap_s": [0.6, 3.5]}
    assert cli.main(["--policy", "safeil", "--check"]) == 0
    assert "valid (ok)" in capsys.readouterr().out


def test_sampled_violations_weigh_the_parts_and_match_reference_margins() -> None:
    """The Monte Carlo estimate: each part's share is the share of its sampled states whose
    reference margins fail (recomputed here), the total weighs them 90/10 as the envelope; an
    unsafe network is caught, and proven boxes bound it (bc fails far more than safeil_openloop)."""
    bc = pol.load("bc")
    props = cm.Properties.from_metadata(bc.metadata)
    res = cm.sampled_violations(bc, props, 2500, seed=4, chunk=1000)
    for m in cm.MARGINS:
        r = res[m]
        assert r["violated"] == pytest.approx(0.9 * r["leader_states"] + 0.1 * r["no_leader"])
    assert res["lane"]["violated"] > 0.5 and res["lane"]["worst_m"] >= res["lane"]["median_m"] > 0
    # both parts recomputed from the same draws: chunks of 1000, 1000 and 500 states, leader
    # states first, then no-leader states
    from dataclasses import replace

    rng = np.random.default_rng(4)
    mins = {}
    for part, share in (("leader_states", 0.0), ("no_leader", 1.0)):
        rows = np.concatenate([cm.reference_margins(bc, sample_states(k, rng, replace(
            EnvelopeConfig(), no_leader_share=share)), props) for k in (1000, 1000, 500)])
        for m in cm.MARGINS:
            mins[m, part] = rows[:, cm.MARGIN_ROWS[m]].min(1)
            assert res[m][part] == np.mean(mins[m, part] < 0), (m, part)
    for m in cm.MARGINS:
        both = np.concatenate([mins[m, "leader_states"], mins[m, "no_leader"]])
        assert res[m]["worst_m"] == -both.min() and res[m]["median_m"] == np.median(
            -both[both < 0])
    # no violation at all: both statistics are 0 (the shipped safeil's lane margin)
    safe = pol.load("safeil")
    none = cm.sampled_violations(safe, cm.Properties.from_metadata(safe.metadata), 500,
                                 seed=1)["lane"]
    assert none == {"violated": 0.0, "leader_states": 0.0, "no_leader": 0.0, "median_m": 0.0,
                    "worst_m": 0.0}
    ol = pol.load("safeil_openloop")
    good = cm.sampled_violations(ol, cm.Properties.from_metadata(ol.metadata), 3000, seed=4)
    assert good["lane"]["violated"] < 0.02 < res["lane"]["violated"]


# ------------------------------------------------- cases found by mutation testing (issue 43)


def test_budget_edges_and_messages() -> None:
    Budget(batch=1, cex_priority=1.0, n_random=0)  # the edges themselves are allowed
    for bad in ({"batch": 0}, {"n_random": -1}, {"cex_priority": 0.0}, {"cex_priority": 1.5}):
        with pytest.raises(CertifyError, match=r"batch must be >= 1, n_random >= 0 and "
                                               r"cex_priority in \(0, 1\]"):
            Budget(**bad)


def test_certify_refuses_with_reasons(safeil: MLPPolicy) -> None:
    with pytest.raises(CertifyError, match=r"margins must be among .*got \['nope'\]"):
        certify(safeil, margins=("nope",), progress=False)
    with pytest.raises(CertifyError, match="the lane margin would be bounded for the other head$"):
        certify(safeil, props=cm.Properties.from_metadata(pol.load("bc").metadata, 6.0),
                progress=False)
    with pytest.raises(CertifyError, match="applies only to style-conditioned checkpoints"):
        certify(pol.load("bc"), env=cm.CertEnvelope(time_gap_s=(1.0, 2.0)), progress=False)


def test_a_time_budget_alone_stops_branch_and_bound() -> None:
    m = certify(pol.load("bc"), budget=Budget(seconds=0.4), margins=("leader",),
                progress=False).margins["leader"]
    assert m.stopped_by == "seconds" and 0.2 <= m.seconds < 5.0 and m.boxes_bounded > 0


def test_a_part_without_weight_gets_no_box_and_no_share() -> None:
    r = certify(pol.load("bc"), env=cm.CertEnvelope(no_leader_share=0.0),
                budget=Budget(boxes=40, batch=8), margins=("leader",), progress=False)
    m = r.margins["leader"]
    assert m.certified_by_part["free"] is None and m.certified_by_part["leader"] == m.certified
    assert not np.any(m.boxes["open_part"]) and not np.any(m.boxes["proven_part"])


def test_counterexample_candidates_lift_onto_the_recoverable_gap_only_when_closing() -> None:
    from safeil_sumo.learn.branch_and_bound import _candidates

    env = cm.CertEnvelope()
    lo, hi = (b.copy() for b in env.root_boxes()["leader"])
    # closing at 10 m/s from 30 m/s: the recoverable gap is 100 / (2 b); the gap's low corner
    # is lifted onto it, just above
    lo[cm.V], hi[cm.V], lo[cm.DV], hi[cm.DV], lo[cm.GAP], hi[cm.GAP] = 30, 30, -10, -10, 1, 60
    floor = 100.0 / (2.0 * env.brake_mps2)
    coef = np.ones((1, len(lo)))  # every coefficient > 0: the low corner
    pts, ok = _candidates(env, lo[None], hi[None], np.array([0]), coef,
                          np.random.default_rng(0), 3)
    assert pts[0, 0, cm.GAP] == floor * (1 + 1e-9) + 1e-9 and ok[0, 0]
    assert pts[0, 1, cm.GAP] == 30.5  # the centre is recoverable as it is
    # opening (the leader pulls away): nothing to lift, even 0.1 m behind
    lo[cm.DV], hi[cm.DV], lo[cm.GAP], hi[cm.GAP] = 1.0, 2.0, 0.1, 0.2
    pts, ok = _candidates(env, lo[None], hi[None], np.array([0]), coef,
                          np.random.default_rng(0), 3)
    assert np.all(pts[..., cm.GAP] <= 0.2) and np.all(ok)


def test_a_point_box_counts_in_the_quarter_holding_it() -> None:
    from safeil_sumo.learn.branch_and_bound import _unproven_by_dim

    env = cm.CertEnvelope()
    lo, hi = env.root_boxes()["leader"]
    z = lo + 0.1 * (hi - lo)  # 10 % into every range, the gap's in log d
    z[cm.GAP] = lo[cm.GAP] * (hi[cm.GAP] / lo[cm.GAP]) ** 0.1
    wide_lo, wide_hi = lo.copy(), hi.copy()
    got = _unproven_by_dim(env, np.stack([z, wide_lo]), np.stack([z, wide_hi]),
                           np.array([1.0, 0.0]))
    assert all(v == [1.0, 0.0, 0.0, 0.0] for v in got.values()), got
    top = _unproven_by_dim(env, hi[None], hi[None], np.array([2.0]))  # the top edge: last
    assert all(v == [0.0, 0.0, 0.0, 1.0] for v in top.values()), top


def test_propagate_and_layers_say_what_is_wrong() -> None:
    layer = bnd.Layer(np.eye(2), np.zeros(2), [bnd.RELU, bnd.TANH])
    assert layer.activation.dtype == np.int8 and list(layer.activation) == [bnd.RELU, bnd.TANH]
    with pytest.raises(ValueError, match=r"boxes must be \(N, n_in\) twice"):
        bnd.propagate([layer], np.zeros((1, 2)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="box with hi < lo"):
        bnd.propagate([layer], np.ones((1, 2)), np.zeros((1, 2)))


def test_relaxation_of_a_point_interval_is_finite_and_exact() -> None:
    p = np.array([-2.0, -0.3, 0.0, 0.7, 3.0])
    for code, f in ((bnd.TANH, np.tanh), (bnd.RELU, lambda x: np.maximum(x, 0.0))):
        a_l, b_l, a_u, b_u = bnd.relax(np.full(len(p), code), p, p)
        assert np.all(np.isfinite([a_l, b_l, a_u, b_u]))
        assert np.all(a_l * p + b_l <= f(p)) and np.all(a_u * p + b_u >= f(p))


def test_properties_from_a_checkpoints_metadata_by_hand() -> None:
    meta = {"horizon_s": 6.0, "train_config": {"track": 1.9, "gap_min": 2.0, "time_gap": 0.5},
            "architecture": {"lateral_mode": "lane", "lane_keep_m": 0.3}}
    p = cm.Properties.from_metadata(meta)
    assert (p.horizon_s, p.track_m, p.gap_min_m, p.time_gap_margin_s, p.brake_mps2,
            p.lane_keep_m) == (6.0, 1.9, 2.0, 0.5, 6.0, 0.3)
    bare = cm.Properties.from_metadata({"horizon_s": 5.0})
    assert (bare.track_m, bare.gap_min_m, bare.time_gap_margin_s, bare.lane_keep_m) == (
        1.76, 0.0, 0.0, None)


def test_the_envelope_refuses_bad_ranges_naming_them() -> None:
    for bad in ({"gap_m": (0.0, 50.0)}, {"gap_m": (0.5, 50.0)}):
        if bad["gap_m"][0] > 0:
            cm.CertEnvelope(**bad)  # a positive gap below 1 m is allowed
            continue
        with pytest.raises(CertifyError, match=r"envelope gap_m must be > 0, got \(0.0, 50.0\)"):
            cm.CertEnvelope(**bad)
    for bad in ({"ego_speed_mps": (-np.inf, 40.0)}, {"ego_speed_mps": (3.0, np.nan)},
                {"ego_speed_mps": (40.0, 3.0)}, {"ego_speed_mps": (3.0, 20.0, 40.0)}):
        with pytest.raises(CertifyError, match="envelope ego_speed_mps must be a finite"):
            cm.CertEnvelope(**bad)


def test_the_recoverable_condition_and_the_leader_extra_by_hand() -> None:
    """Braking at 6 m/s^2: closing at 6 m/s needs 3 m; a leader pulling away needs nothing.
    The training's extra gap (2 m + 0.5 s) applies only where braking can still reach it."""
    env = cm.CertEnvelope()
    z = np.zeros((4, len(env.dims)))
    z[:, cm.V] = 20.0
    z[:, cm.DV] = [-6.0, -6.0, 3.0, 3.0]
    z[:, cm.GAP] = [3.0, 3.01, 0.01, 0.5]
    assert list(env.recoverable(z)) == [False, True, True, True]
    props = cm.Properties(horizon_s=5.0, track_m=1.76, gap_min_m=2.0, time_gap_margin_s=0.5,
                          brake_mps2=6.0, lane_keep_m=None)
    v, v_lead = np.array([20.0, 20.0, 20.0]), np.array([14.0, 14.0, 25.0])
    gap = np.array([15.1, 14.9, 12.1])  # margin 12 m; closing at 6 m/s needs more than 12 + 3
    np.testing.assert_array_equal(cm._lead_extra(v, v_lead, gap, props), [12.0, 0.0, 12.0])
