"""The two-tower planner: the x control points never read the lane lines (learn/model.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.core import bspline
from safeil_sumo.learn.checkpoint import CheckpointError, load_model, save_checkpoint
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.learn.model import PlannerMLP, split_towers, with_style_input
from safeil_sumo.learn.towers import tower_masks, weight_across_towers

STATE = np.array([1.75, 0.01, 0.002, -1.75, 0.01, 0.002, 25.0, 24.0, 40.0])


def _dense(seed: int = 0, style: bool = False) -> PlannerMLP:
    torch.manual_seed(seed)
    model = PlannerMLP(hidden=(16, 16), output_mode="residual")
    with torch.no_grad():
        for p in model.net.parameters():
            p.normal_(0.0, 0.3)
        model.feature_mean.copy_(torch.as_tensor([1.8, 0, 0, -1.8, 0, 0, 25, 24, 40]))
        model.feature_std.copy_(torch.as_tensor([0.3, 0.02, 0.002, 0.3, 0.02, 0.002, 5, 5, 20]))
    return with_style_input(model, 1.5, 0.5) if style else model


def _features(n: int, seed: int = 1, n_features: int = 9) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    base = torch.as_tensor(np.r_[STATE, 1.5][:n_features], dtype=torch.float32)
    scale = torch.as_tensor([0.5, 0.1, 0.01, 0.5, 0.1, 0.01, 8, 8, 30, 1][:n_features])
    return base + scale * torch.randn(n, n_features, generator=g)


def test_masks_cut_the_lane_lines_from_the_x_tower_by_hand():
    m0, m1, m2 = tower_masks(9, (4, 4))
    # first layer: units 0-1 (x tower) read v_x, v_lead, d_lead only; units 2-3 read all 9
    np.testing.assert_array_equal(m0[:2], [[0, 0, 0, 0, 0, 0, 1, 1, 1]] * 2)
    np.testing.assert_array_equal(m0[2:], np.ones((2, 9)))
    np.testing.assert_array_equal(m1, [[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1], [0, 0, 1, 1]])
    # outputs (x1, y1, x2, y2, x3, y3): x from the x tower, y from the lateral one
    np.testing.assert_array_equal(m2, [[1, 1, 0, 0], [0, 0, 1, 1]] * 3)


def test_split_keeps_the_lateral_plan_and_straightens_the_longitudinal_one():
    dense = _dense(style=True)
    towers = split_towers(dense)
    assert towers.hidden == (32, 32) and towers.architecture["towers"] is True
    f = _features(200, n_features=10)
    torch.testing.assert_close(towers(f)[..., 1], dense(f)[..., 1])
    straight = f.clone()
    straight[:, :6] = dense.feature_mean[:6]  # the lane lines at their training mean
    torch.testing.assert_close(towers(f)[..., 0], dense(straight)[..., 0])
    assert (dense(f)[..., 0] - dense(straight)[..., 0]).abs().max() > 1e-2  # dense reads them
    with pytest.raises(ValueError, match="already"):
        split_towers(towers)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-5.0, 5.0), min_size=6, max_size=6))
def test_x_control_points_ignore_any_lane_lines(lanes):
    towers = split_towers(_dense())
    f = _features(1)
    g = f.clone()
    g[0, :6] = torch.as_tensor(lanes)
    torch.testing.assert_close(towers(g)[..., 0], towers(f)[..., 0])


def test_training_keeps_the_towers_apart():
    """Adam steps on a loss of every output leave the weights across the towers exactly 0."""
    towers = split_towers(_dense())
    opt = torch.optim.Adam(towers.parameters(), lr=1e-2)
    f = _features(64)
    for _ in range(5):
        loss = towers(f).pow(2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    weights = [towers.net[2 * j].weight.detach().numpy() for j in range(3)]
    assert weight_across_towers(weights, 9, towers.hidden) == 0.0
    g = f.clone()
    g[:, :6] += 1.0
    torch.testing.assert_close(towers(g)[..., 0], towers(f)[..., 0])


def test_checkpoint_round_trip_and_numpy_inference(tmp_path):
    towers = split_towers(_dense(style=True))
    save_checkpoint(tmp_path / "t", towers, name="t", horizon=5.0,
                    style_default={"time_gap_s": 1.4})
    model, meta = load_model(tmp_path / "t")
    assert model.towers and meta["architecture"]["towers"] is True
    f = _features(8, n_features=10)
    f[:, 9] = 1.4
    torch.testing.assert_close(model(f), towers(f))
    policy = load_policy(tmp_path / "t")
    np.testing.assert_allclose(policy.plan(f[:, :9].double().numpy()),
                               towers(f).detach().numpy(), atol=1e-4)


def test_lane_mode_round_trip_numpy_equals_torch_and_follows_the_lane(tmp_path):
    towers = split_towers(_dense(style=True))
    towers.lateral_mode, towers.lane_keep_m = "lane", 0.93
    save_checkpoint(tmp_path / "l", towers, name="l", horizon=5.0,
                    style_default={"time_gap_s": 1.4})
    model, meta = load_model(tmp_path / "l")
    assert meta["architecture"]["lateral_mode"] == "lane"
    assert (model.lateral_mode, model.lane_keep_m) == ("lane", 0.93)
    f = _features(8, n_features=10)
    f[:, 9] = 1.4
    plans = towers(f)
    torch.testing.assert_close(model(f), plans)
    policy = load_policy(tmp_path / "l")
    features = f[:, :9].double().numpy()
    np.testing.assert_allclose(policy.plan(features), plans.detach().numpy(), atol=1e-4)
    np.testing.assert_allclose(policy.plan(features[0]), plans[0].detach().numpy(), atol=1e-4)
    # the y control points are the lane head's, from the network's x and raw lateral outputs
    raw = towers.forward_normalised(f) * towers.output_std + towers.output_mean
    want = bspline.lane_following_y(features[:, :6], plans[..., 0].detach().double().numpy(),
                                    raw[:, 1::2].detach().double().numpy(), 0.93)
    np.testing.assert_allclose(plans[..., 1].detach().numpy(), want, atol=1e-4)
    # the x control points do not depend on the mode
    towers.lateral_mode = "absolute"
    torch.testing.assert_close(towers(f)[..., 0], plans[..., 0])


def test_a_towers_checkpoint_with_weights_across_the_towers_is_refused(tmp_path):
    towers = split_towers(_dense())
    with torch.no_grad():
        towers.net[0].weight[0, 2] = 0.5  # the x tower reading c2l
    save_checkpoint(tmp_path / "bad", towers, name="bad", horizon=5.0)
    with pytest.raises(CheckpointError, match="across the towers"):
        load_model(tmp_path / "bad")


def test_lane_by_steering_passes_no_lane_gradient_to_the_plan_length():
    """On a lane curving left, a plan straight ahead leaves it on the right; the lane term then
    pulls the plan shorter (dx) unless ``lane_by_steering``, which leaves only the pull to the
    left (dy); the leader term still reaches x, and the values are unchanged."""
    from safeil_sumo.learn.closed_loop import envelope_terms
    from safeil_sumo.learn.losses import BarrierConfig

    feats = torch.tensor([[1.75, 0.0, 0.002, -1.75, 0.0, 0.002, 20.0, 20.0, 60.0]],
                         dtype=torch.float64)
    cfg = BarrierConfig(k=1000.0, track=1.76, lateral="bernstein")
    grads = {}
    for steer in (False, True):
        cp = torch.tensor([[[33.0, 0.0], [66.0, 0.0], [100.0, 0.0]]], dtype=torch.float64,
                          requires_grad=True)
        _, lane, lead = envelope_terms(feats, cp, 5.0, cfg, lane_by_steering=steer)
        (g_lane,) = torch.autograd.grad(lane, cp, retain_graph=True)
        (g_lead,) = torch.autograd.grad(lead, cp)
        grads[steer] = (float(lane.detach()), g_lane, float(lead.detach()), g_lead)
    assert grads[True][0] == grads[False][0] and grads[True][2] == grads[False][2]
    assert (grads[False][1][..., 0] > 0).all()  # descent shortens the plan
    assert (grads[True][1][..., 0] == 0).all()
    torch.testing.assert_close(grads[True][1][..., 1], grads[False][1][..., 1])
    assert (grads[True][3][..., 0] > 0).all()  # the leader (60 m ahead) still pulls x back


@pytest.mark.parametrize("tower, kept, moved", [("longitudinal", 1, 0), ("lateral", 0, 1)])
def test_training_one_tower_leaves_the_other_towers_plan_exactly(tower, kept, moved):
    """Adam steps on a loss of every output, the gradients kept on one tower only: the other
    tower's control points (y for the longitudinal tower, x for the lateral one) are
    bit-identical, its own moved."""
    from safeil_sumo.learn.model import keep_only_tower_gradients

    towers = split_towers(_dense())
    f = _features(64)
    before = towers(f).detach().clone()
    opt = torch.optim.Adam(towers.parameters(), lr=1e-2)
    for _ in range(5):
        loss = towers(f).pow(2).sum()
        opt.zero_grad()
        loss.backward()
        keep_only_tower_gradients(towers, tower)
        torch.nn.utils.clip_grad_norm_(towers.parameters(), 10.0)
        opt.step()
    after = towers(f).detach()
    assert torch.equal(after[..., kept], before[..., kept])
    assert (after[..., moved] - before[..., moved]).abs().max() > 1e-3
    with pytest.raises(ValueError, match="towers"):
        keep_only_tower_gradients(_dense(), tower)
    with pytest.raises(ValueError, match="tower must be"):
        keep_only_tower_gradients(towers, "vertical")


@pytest.mark.sumo
def test_shipped_safeil_stops_behind_a_braking_leader_on_the_curve():
    """libsumo: the leader-response suite's case that a towers fine-tune which also trained the
    lateral tower failed (curved500, leader braking at 4 m/s^2 to a stop, 50 m ahead): at
    walking pace its lateral plan swung 3 m off and it left the lane at 12.9 s. The shipped
    `safeil` (lateral tower refitted to its plan length, learn/lateral_refit.py, tracked with
    curled-back stop plans extended ahead) stops behind it in its lane."""
    from safeil_sumo.experiments.sweep_executor import run_task
    from safeil_sumo.scenarios.spec import Task

    spec = Task.of(net="curved500", index=21001, master_seed=6, policy="safeil",
                        leader_kind="braking", brake_time_s=5.0, brake_decel_mps2=4.0,
                        brake_to_mps=0.0, ego_speed_mps=30.0, max_time_s=40.0,
                        stop_on_flag=False, initial_gap_m=50.0)
    out = run_task(spec)
    assert out["status"] == "ok" and out["flag"] == "" and out["end_reason"] != "collision"
    assert out["min_gap_m"] > 2.0 and out["max_abs_lateral_offset_m"] < 0.5
