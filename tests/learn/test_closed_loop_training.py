"""The differentiable longitudinal loop used for closed-loop training (learn/closed_loop.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.learn.closed_loop import (
    Episodes,
    LoopModel,
    SettlingConfig,
    closed_loop_loss,
    episodes_from_tuples,
    plan_speed_accel,
    rollout,
    settling_episodes,
    settling_loss,
)
from safeil_sumo.sim.controller import make_target, plan_speed_and_accel

STRAIGHT = [1.75, 0.0, 0.0, -1.75, 0.0, 0.0]


class ConstantAccelPlanner(torch.nn.Module):
    """Plans x(t) = v t + a t^2 / 2 from the features' ego speed (a torch 'planner')."""

    def __init__(self, accel: float = 0.0, horizon: float = 5.0) -> None:
        super().__init__()
        self.accel, self.horizon = accel, horizon

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        t = torch.arange(1, 4, dtype=f.dtype) * self.horizon / 3.0
        v = f[:, 6, None]
        # the Bezier control points of x(t) = v t + a t^2 / 2 over [0, T]
        h = self.horizon
        x1 = v * h / 3.0
        x2 = 2.0 * v * h / 3.0 + self.accel * h * h / 6.0
        x3 = v * h + self.accel * h * h / 2.0
        x = torch.cat([x1, x2, x3], dim=1)
        return torch.stack([x, torch.zeros_like(t).expand_as(x)], dim=-1)


def _episode(v0: float, v_lead: float, gap0: float, steps: int, dt: float = 0.1) -> Episodes:
    t = np.arange(steps) * dt
    s_lead = torch.tensor(gap0 + v_lead * t, dtype=torch.float32)[None]
    return Episodes(torch.tensor([STRAIGHT]), torch.full((1, steps), v0),
                    torch.full((1, steps), gap0), torch.full((1, steps), v_lead), s_lead,
                    np.array(["m"]), dt)


@settings(max_examples=60, deadline=None)
@given(cp=st.lists(st.floats(-5.0, 200.0), min_size=3, max_size=3),
       t=st.floats(0.0, 4.5), horizon=st.floats(3.0, 8.0))
def test_plan_speed_and_accel_equal_the_controllers(cp, t, horizon):
    """The torch plan derivatives are the SUMO controller's (power-basis form), x only."""
    points = np.array([[cp[0], 0.0], [cp[1], 0.0], [cp[2], 0.0]])
    target = make_target(points, horizon, (0.0, 0.0, 0.0))
    v_ref, _ = plan_speed_and_accel(target.coeff_x, target.coeff_y, horizon, t)
    _, a_ref = plan_speed_and_accel(target.coeff_x, target.coeff_y, horizon, t + 0.2)
    v, a = plan_speed_accel(torch.tensor(points[None], dtype=torch.float64), horizon, t, 0.2)
    assert float(v[0]) == pytest.approx(v_ref, abs=1e-9)
    if v_ref > 0:  # backward plans stop: no feed-forward in either
        assert float(a[0]) == pytest.approx(a_ref, abs=1e-9)


def test_constant_speed_plan_behind_an_equal_speed_leader_keeps_the_gap():
    out = rollout(ConstantAccelPlanner(), _episode(25.0, 25.0, 40.0, 300))
    np.testing.assert_allclose(out["gap"].numpy(), 40.0, atol=1e-3)
    np.testing.assert_allclose(out["v"].numpy(), 25.0, atol=1e-4)


def test_plant_lag_and_limits():
    """A plan accelerating at 2 m/s^2: the command is 2 (feed-forward) and the plant reaches it
    with the drive lag: 1 - exp(-t / 0.3 s) after t; speed follows within the limits."""
    out = rollout(ConstantAccelPlanner(accel=2.0), _episode(20.0, 20.0, 1000.0, 31),
                  LoopModel(ki=0.0))
    a = out["accel"][0].numpy()
    # after 1 s (10 steps) the lag has covered 1 - exp(-1/0.3) = 96.4 % of a step; the plan's
    # speed error adds a little P term on top
    assert a[10] == pytest.approx(2.0, rel=0.1)
    # 3 s at <= 3 m/s^2: speed within [20 + 2*2.5, 20 + 3*3]
    assert 24.0 < float(out["v"][0, -1]) < 29.0
    hard = rollout(ConstantAccelPlanner(accel=-20.0), _episode(20.0, 20.0, 1000.0, 50))
    assert float(hard["accel"][0].min()) >= -8.0 - 1e-6  # the controller's braking limit
    assert float(hard["v"][0].min()) >= 0.0


def test_loss_terms_are_hand_computed():
    ep = _episode(25.0, 25.0, 40.0, 4)
    out = {"gap": ep.gap_human + 2.0, "v": ep.v_human - 1.0,
           "lead_margin": torch.full((1, 4, 3), 50.0)}
    terms = closed_loop_loss(out, ep, speed_weight=3.0, barrier_weight=0.0)
    assert float(terms.gap) == pytest.approx(4.0)
    assert float(terms.speed) == pytest.approx(1.0)
    assert float(terms.total) == pytest.approx(7.0)
    out["lead_margin"] = torch.full((1, 4, 3), -1.0)  # every control point 1 m past the leader
    terms = closed_loop_loss(out, ep, barrier_k=1000.0, barrier_weight=1.0)
    assert float(terms.barrier) == pytest.approx(3 * 1000.0 * np.log1p(np.e), rel=1e-6)


def test_gradient_reaches_the_planner_through_the_loop():
    """The gap error at the end of the rollout depends on the plan: d loss / d accel != 0, and
    its sign says 'accelerate' when the ego falls behind the human's gap."""
    accel = torch.tensor(0.0, requires_grad=True)

    class P(ConstantAccelPlanner):
        def forward(self, f):
            h = self.horizon
            v = f[:, 6, None]
            x = torch.cat([v * h / 3.0, 2.0 * v * h / 3.0 + accel * h * h / 6.0,
                           v * h + accel * h * h / 2.0], dim=1)
            return torch.stack([x, torch.zeros_like(x)], dim=-1)

    ep = _episode(25.0, 27.0, 30.0, 100)  # leader pulls away; the human keeps 30 m
    terms = closed_loop_loss(rollout(P(), ep), ep, barrier_weight=0.0)
    terms.total.backward()
    assert accel.grad is not None and float(accel.grad) < 0.0


def test_episodes_from_tuples_rebuild_the_recorded_gap():
    """Windows of a maneuver: the leader's position minus the ego's recorded path is the
    recorded gap; a too-short maneuver gives none."""
    from safeil_sumo.data.tuples import Tuples

    n = 81  # 20 s at 4 Hz
    t = np.arange(n) / 4.0
    v = 20.0 + 0.1 * t
    gap = 30.0 + np.sin(t)
    feats = np.zeros((n, 9))
    feats[:, :6] = STRAIGHT
    feats[:, 6], feats[:, 7], feats[:, 8] = v, v + np.cos(t), gap
    tup = Tuples(feats, np.zeros((n, 3, 2)), np.zeros((n, 20, 2)), np.array(["a"] * n),
                 np.array(["s"] * n), t, 5.0, 4.0)
    eps = episodes_from_tuples(tup, window_s=10.0, stride_s=5.0)
    assert len(eps) == 3  # starts at 0, 5 and 10 s (the last ends at 19.9 s)
    grid = np.arange(100) * 0.1
    s_ego = 20.0 * grid + 0.05 * grid**2
    np.testing.assert_allclose(eps.s_lead[0].numpy() - s_ego, np.interp(grid, t, gap), atol=2e-3)
    np.testing.assert_allclose(eps.gap_human[1].numpy(), np.interp(grid + 5.0, t, gap),
                               atol=1e-5)
    with pytest.raises(ValueError, match="no maneuver"):
        episodes_from_tuples(tup, window_s=30.0, stride_s=5.0)


def test_perturbed_start_moves_the_ego_back_and_changes_its_speed():
    ep = _episode(25.0, 25.0, 40.0, 50)
    out = rollout(ConstantAccelPlanner(), ep, gap_offset_m=torch.tensor([12.0]),
                  speed_offset_mps=torch.tensor([0.0]))
    np.testing.assert_allclose(out["gap"].numpy(), 52.0, atol=1e-3)  # kept at constant speed
    fast = rollout(ConstantAccelPlanner(), ep, speed_offset_mps=torch.tensor([2.0]))
    assert float(fast["v"][0, 0]) == pytest.approx(27.0)
    assert float(fast["gap"][0, -1]) < 40.0 - 2.0 * 4.0  # closing at 2 m/s for ~4.9 s


def test_settling_episodes_start_off_the_equilibrium_of_their_setting():
    cfg = SettlingConfig()
    ep, gap_eq = settling_episodes(400, torch.tensor([STRAIGHT]), np.random.default_rng(1),
                                   window_s=6.0, cfg=cfg)
    tg, v_lead = ep.style[:, 0], ep.v_lead[:, 0]
    assert ep.v_human.shape == (400, 60) and ep.s_lead.shape == (400, 60)
    torch.testing.assert_close(gap_eq, torch.clamp(tg * v_lead, min=2.0))
    assert float(tg.min()) >= 0.8 and float(tg.max()) <= 3.0
    # the leader drives at constant speed from the ego's start gap
    torch.testing.assert_close(ep.s_lead[:, 1] - ep.s_lead[:, 0], v_lead * 0.1, atol=1e-4, rtol=0)
    gap0 = ep.s_lead[:, 0]
    far = gap0 > gap_eq
    assert 150 < int(far.sum()) < 250  # half far behind, half close
    assert float((gap0[far] - gap_eq[far]).max()) <= cfg.far_m
    floor = torch.clamp(0.4 * gap_eq[~far], min=1.0)
    assert bool((gap0[~far] >= floor - 1e-4).all() and (gap0[~far] <= gap_eq[~far]).all())
    dv = ep.v_human[:, 0] - v_lead  # the rollout's start speed, within the speed step
    assert float(dv.abs().max()) <= cfg.speed_step_mps + 1e-5 and float(dv.abs().max()) > 2.0
    a, _ = settling_episodes(3, torch.tensor([STRAIGHT]), np.random.default_rng(1), 6.0)
    b, _ = settling_episodes(3, torch.tensor([STRAIGHT]), np.random.default_rng(1), 6.0)
    torch.testing.assert_close(a.s_lead, b.s_lead)  # seeded


def test_settling_loss_is_hand_computed():
    cfg = SettlingConfig(settle_after_s=0.2, floor_time_gap_s=1.0)
    # 4 steps of 0.1 s: scored from step 2; gap error 3 and 1 m there; the floor (1 s at
    # 10 m/s: 10 m) is missed by 4 m at step 0 only
    out = {"gap": torch.tensor([[6.0, 12.0, 23.0, 21.0]]), "v": torch.full((1, 4), 10.0)}
    settle, floor = settling_loss(out, torch.tensor([20.0]), 0.1, cfg)
    assert float(settle) == pytest.approx((9.0 + 1.0) / 2)
    assert float(floor) == pytest.approx(16.0 / 4)


def test_a_planner_that_holds_its_speed_does_not_settle():
    """Constant speed behind an equal-speed leader keeps the start gap: from a far start the
    settling term is the squared distance to the equilibrium; a start at it scores zero."""
    ep = _episode(20.0, 20.0, 60.0, 50)
    out = rollout(ConstantAccelPlanner(), ep)
    settle, floor = settling_loss(out, torch.tensor([30.0]), 0.1, SettlingConfig(settle_after_s=2.0))
    assert float(settle) == pytest.approx(900.0, rel=1e-4) and float(floor) == 0.0
    settle, _ = settling_loss(out, torch.tensor([60.0]), 0.1, SettlingConfig(settle_after_s=2.0))
    assert float(settle) == pytest.approx(0.0, abs=1e-4)


def test_closed_loop_finetune_is_deterministic_and_keeps_its_recipe(tmp_path):
    """Two fine-tunes with one seed give the same weights, bit for bit (same machine); the
    checkpoint has the style input, its default (the training maneuvers' median) and the
    initial checkpoint's held-out maneuvers."""
    import importlib.util
    import json
    from pathlib import Path

    from fixtures_training import make_tuples

    from safeil_sumo.learn.checkpoint import held_out_maneuvers, save_checkpoint
    from safeil_sumo.learn.model import PlannerMLP
    from safeil_sumo.learn.trainer import TrainConfig

    tup = make_tuples(n_maneuvers=4, per_maneuver=60, curved=False)
    tup.save(tmp_path / "t.parquet")
    model = PlannerMLP(output_mode="residual")
    model.set_scaling(tup.features, tup.control_points)
    cfg = TrainConfig(envelope_weight=0.01, monotone_weight=1.0, output_mode="residual")
    held = [str(np.unique(tup.maneuver_id)[0])]
    save_checkpoint(tmp_path / "init", model, name="safeil", horizon=5.0, train_config=cfg,
                    metrics={"val_maneuvers": held})
    spec = importlib.util.spec_from_file_location(
        "finetune", Path(__file__).parents[2] / "training" / "closed_loop_finetune.py")
    ft = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ft)
    args = ["--init", str(tmp_path / "init.safetensors"), "--data", str(tmp_path / "t.parquet"),
            "--iters", "2", "--batch", "4", "--window", "8", "--stride", "4", "--style",
            "--perturb", "0.5", "--equilibrium-weight", "1", "--settle-weight", "1",
            "--no-progress"]
    for name in ("a", "b"):
        assert ft.main([*args, "--out", str(tmp_path / name)]) == 0
    # the weights, not the file bytes: safetensors writes its metadata map in no fixed order
    from safetensors.numpy import load_file

    a, b = load_file(tmp_path / "a.safetensors"), load_file(tmp_path / "b.safetensors")
    assert sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)
    meta = json.loads((tmp_path / "a.json").read_text())
    assert meta["architecture"]["style_names"] == ["time_gap_s"]
    assert 1.0 < meta["style_default"]["time_gap_s"] < 2.2  # make_tuples' drivers: 1.2-2.0 s
    assert held_out_maneuvers(tmp_path / "a.json") == held
    # the n74 driver population draws from the very estimates this default is the median of
    from safeil_sumo.experiments.n74_drives import training_settings

    est = training_settings(tmp_path / "a.safetensors", [tmp_path / "t.parquet"])
    assert sorted(est) == sorted(str(m) for m in np.unique(tup.maneuver_id)[1:])
    assert np.median(list(est.values())) == meta["style_default"]["time_gap_s"]


def test_envelope_lane_term_is_hand_computed():
    """The fine-tune's lane term is the paper's ``K sum softplus(-b_k)`` over the exact Bernstein
    coefficients k = 1..6 of both lateral margins, its leader term ``K sum softplus(-m_i)`` at
    the control points; together they are the envelope barrier. A plan x = L tau, y = 0: x^2 = L^2 tau^2 has degree-6 Bernstein coefficients
    L^2 k (k - 1) / 30, so on a lane curving left (c2 > 0) the left margin's are
    w/2 - T/2 + c2 L^2 k (k - 1) / 30 and the right margin's w/2 - T/2 - c2 L^2 k (k - 1) / 30."""
    import torch.nn.functional as F

    from safeil_sumo.learn.closed_loop import envelope_terms
    from safeil_sumo.learn.losses import BarrierConfig

    L, c2, half_w, track, k_barrier = 100.0, 0.002, 1.75, 1.76, 1000.0
    feats = torch.tensor([[half_w, 0.0, c2, -half_w, 0.0, c2, 20.0, 20.0, 150.0]],
                         dtype=torch.float64)
    cp = torch.tensor([[[L / 3, 0.0], [2 * L / 3, 0.0], [L, 0.0]]], dtype=torch.float64)
    cfg = BarrierConfig(k=k_barrier, track=track, lateral="bernstein")
    env, lane, lead = envelope_terms(feats, cp, 5.0, cfg)
    k = np.arange(1, 7)
    bend = c2 * L * L * k * (k - 1) / 30.0
    base = half_w - track / 2
    sp = lambda m: np.log1p(np.exp(-m))  # softplus(-m)
    want_lane = k_barrier * (sp(base + bend).sum() + sp(base - bend).sum())
    times = np.arange(1, 4) * 5.0 / 3.0
    want_lead = k_barrier * sp(150.0 + 20.0 * times - np.array([L / 3, 2 * L / 3, L])).sum()
    assert float(lane) == pytest.approx(want_lane, rel=1e-12)
    assert float(lead) == pytest.approx(want_lead, rel=1e-12)
    assert float(env) == pytest.approx(want_lane + want_lead, rel=1e-12)
    # the plan leaves the lane on the right (b_6 = 0.87 - 20 m): the term is dominated by it
    assert want_lane > k_barrier * (20.0 - base)
    # a straight lane: every coefficient is w/2 - T/2
    flat = feats.clone()
    flat[:, [2, 5]] = 0.0
    _, lane_flat, _ = envelope_terms(flat, cp, 5.0, cfg)
    assert float(lane_flat) == pytest.approx(k_barrier * 12 * float(F.softplus(
        torch.tensor(-base, dtype=torch.float64))), rel=1e-12)


def _tiny_finetune_setup(tmp_path):
    """A tiny initial checkpoint and tuples (tmp_path); the fine-tune arguments and script."""
    from pathlib import Path

    from fixtures_training import make_tuples

    from safeil_sumo.learn.checkpoint import save_checkpoint
    from safeil_sumo.learn.model import PlannerMLP
    from safeil_sumo.learn.trainer import TrainConfig

    tup = make_tuples(n_maneuvers=4, per_maneuver=60, curved=True)
    tup.save(tmp_path / "t.parquet")
    torch.manual_seed(0)
    model = PlannerMLP(output_mode="residual")
    model.set_scaling(tup.features, tup.control_points)
    cfg = TrainConfig(envelope_weight=0.01, monotone_weight=1.0, output_mode="residual",
                      barrier_lateral="bernstein")
    held = [str(np.unique(tup.maneuver_id)[0])]
    save_checkpoint(tmp_path / "init", model, name="safeil", horizon=5.0, train_config=cfg,
                    metrics={"val_maneuvers": held})
    args = ["--init", str(tmp_path / "init.safetensors"), "--data", str(tmp_path / "t.parquet"),
            "--iters", "3", "--batch", "4", "--window", "8", "--stride", "4", "--style",
            "--perturb", "0.5", "--equilibrium-weight", "1", "--settle-weight", "1",
            "--no-progress"]
    return args, Path(__file__).parents[2] / "training" / "closed_loop_finetune.py"


def _load_script(path, name):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _weights(path):
    from safetensors.numpy import load_file

    return load_file(path)


def _same(a, b):
    return sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)


# the fine-tune script before the lane term and the envelope-anchor option
BEFORE_LANE_TERM = "5b51c15"


def test_lane_weight_0_is_the_recipe_before_the_option_bit_for_bit(tmp_path):
    """With the defaults (lane and leader weights 0, anchor on the envelope states too) the
    fine-tune gives
    the weights the script gave before these options existed (the commit before them, run here
    against the same package), bit for bit; a lane or leader weight or dropping the envelope
    anchor changes them."""
    import subprocess
    from pathlib import Path

    args, script = _tiny_finetune_setup(tmp_path)
    repo = Path(__file__).parents[2]
    try:
        old = subprocess.run(["git", "-C", str(repo), "show",
                              f"{BEFORE_LANE_TERM}:training/closed_loop_finetune.py"],
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("no git history: the script before the option is not available")
    # what moved since: learn/train.py -> trainer.py; the torch terms of learn/style.py ->
    # learn/closed_loop.py (style.py is numpy only, so a styled planner loads without torch)
    old = old.replace("safeil_sumo.learn.train import", "safeil_sumo.learn.trainer import")
    old = old.replace("    equilibrium_residual,\n    equilibrium_states,\n", "").replace(
        "from safeil_sumo.learn.style import (",
        "from safeil_sumo.learn.closed_loop import equilibrium_residual, equilibrium_states\n"
        "from safeil_sumo.learn.style import (")
    (tmp_path / "old_finetune.py").write_text(old)
    new_ft = _load_script(script, "finetune_new")
    old_ft = _load_script(tmp_path / "old_finetune.py", "finetune_old")
    assert old_ft.main([*args, "--out", str(tmp_path / "old")]) == 0
    assert new_ft.main([*args, "--out", str(tmp_path / "new")]) == 0
    assert new_ft.main([*args, "--lane-weight", "0", "--anchor-envelope",
                        "--out", str(tmp_path / "zero")]) == 0
    assert new_ft.main([*args, "--lane-weight", "0.5", "--out", str(tmp_path / "lane")]) == 0
    assert new_ft.main([*args, "--no-anchor-envelope", "--out", str(tmp_path / "free")]) == 0
    assert new_ft.main([*args, "--leader-weight", "0.5", "--out", str(tmp_path / "lead")]) == 0
    ref = _weights(tmp_path / "old.safetensors")
    assert _same(_weights(tmp_path / "new.safetensors"), ref)
    assert _same(_weights(tmp_path / "zero.safetensors"), ref)
    assert not _same(_weights(tmp_path / "lane.safetensors"), ref)
    assert not _same(_weights(tmp_path / "free.safetensors"), ref)
    assert not _same(_weights(tmp_path / "lead.safetensors"), ref)
    import json

    cl = json.loads((tmp_path / "lane.json").read_text())["metrics"]["closed_loop"]
    assert cl["lane_weight"] == 0.5 and cl["leader_weight"] == 0.0 and cl["anchor_envelope"]
    assert cl["final"]["lane"] > 0.0 and cl["final"]["leader"] >= 0.0
