"""Learning: barrier loss (hand-computed), model, training determinism, BC vs SafeIL, evaluation.

The synthetic tuples are tests/fixtures_training.py's ``make_tuples``.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_training import make_tuples
from scripts import load_training_script

from safeil_sumo.core import bspline
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.losses import (
    BarrierConfig,
    barrier_terms,
    bernstein_lane_margins,
    imitation_loss,
    lane_margins,
    lead_margins,
    safe_loss,
)
from safeil_sumo.learn.model import PlannerMLP
from safeil_sumo.learn.open_loop_metrics import open_loop_metrics, plan_metrics
from safeil_sumo.learn.trainer import TrainConfig, split_by_maneuver, train
from safeil_sumo.planners.safety_filter import SafeSet, plan_margins

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def data() -> Tuples:
    return make_tuples()


FAST = TrainConfig(max_epochs=25, patience=25, batch_size=128, lr=3e-3)


# ---------------------------------------------------------------- barrier, hand-computed values

def _softplus(z: float) -> float:
    return math.log1p(math.exp(z))


def _one(features: list[float], cps: list[list[float]]) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.tensor([features], dtype=torch.float64),
            torch.tensor([cps], dtype=torch.float64))


STRAIGHT = [1.75, 0.0, 0.0, -1.75, 0.0, 0.0, 25.0, 25.0, 40.0]  # 3.5 m lane, leader at 40 m


def test_barrier_at_lane_centre_matches_formula() -> None:
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    left, right, lead = barrier_terms(f, cp, 3.0, BarrierConfig())
    # y - (c0l - T/2) = 0 - (1.75 - 0.88) = -0.87 at each of the 3 points
    assert left.item() == pytest.approx(1000 * 3 * _softplus(-0.87), rel=1e-12)
    assert right.item() == pytest.approx(1000 * 3 * _softplus(-0.87), rel=1e-12)
    # d_lead(i) = 40 + 25 * i (T_h = 3 s -> t_i = 1, 2, 3 s); margins 55, 70, 85 m
    expected = 1000 * sum(_softplus(x - (40 + 25 * t)) for x, t in ((10, 1), (20, 2), (30, 3)))
    assert lead.item() == pytest.approx(expected, rel=1e-12)
    assert lead.item() < 1e-20


def test_barrier_vanishes_deep_inside_safe_set() -> None:
    wide = [50.0, 0.0, 0.0, -50.0, 0.0, 0.0, 25.0, 25.0, 200.0]
    f, cp = _one(wide, [[10.0, 1.0], [20.0, -1.0], [30.0, 0.5]])
    terms = barrier_terms(f, cp, 3.0, BarrierConfig())
    assert all(t.item() < 1000 * 3 * math.exp(-45) for t in terms)


def test_barrier_grows_past_boundaries_as_the_formula_says() -> None:
    # curved lane: c1 = 0.01, c2 = 0.002; points past the left line, the right line, the leader
    feats = [1.75, 0.01, 0.002, -1.75, 0.01, 0.002, 20.0, 10.0, 15.0]
    cps = [[10.0, 2.5], [20.0, -1.0], [50.0, 0.0]]
    f, cp = _one(feats, cps)
    horizon, track = 4.5, 1.9
    left, right, lead = barrier_terms(f, cp, horizon, BarrierConfig(k=1000.0, track=track))
    exp_left = exp_right = exp_lead = 0.0
    for i, (x, y) in enumerate(cps, start=1):
        t = i * horizon / 3
        exp_left += _softplus(y - (1.75 + 0.01 * x + 0.002 * x * x - track / 2))
        exp_right += _softplus(-y + (-1.75 + 0.01 * x + 0.002 * x * x + track / 2))
        exp_lead += _softplus(x - (15.0 + 10.0 * t))
    assert left.item() == pytest.approx(1000 * exp_left, rel=1e-12)
    assert right.item() == pytest.approx(1000 * exp_right, rel=1e-12)
    assert lead.item() == pytest.approx(1000 * exp_lead, rel=1e-12)
    # each barrier is past its boundary on one point: it is above K * (violation) there
    assert left.item() > 1000 * (2.5 - (1.75 + 0.1 + 0.2 - 0.95))
    assert lead.item() > 1000 * (50.0 - (15.0 + 10.0 * 4.5))


def test_leader_safety_margin_option() -> None:
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.0], [60.0, 0.0]])
    cfg = BarrierConfig(gap_min=2.0, time_gap=1.0)
    _, _, lead = barrier_terms(f, cp, 3.0, cfg)
    # d_lead(i) - (gap_min + time_gap * v_ego) = 40 + 25 t - 27
    expected = 1000 * sum(
        _softplus(x - (40 + 25 * t - 27.0)) for x, t in ((10, 1), (20, 2), (60, 3))
    )
    assert lead.item() == pytest.approx(expected, rel=1e-12)


def test_barrier_on_sampled_points_adds_spline_points() -> None:
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    n = 4
    left, _, _ = barrier_terms(f, cp, 3.0, BarrierConfig(n_samples=n))
    pts = bspline.evaluate(cp.numpy()[0], np.arange(1, n + 1) / n)
    expected = 1000 * (3 * _softplus(-0.87) + sum(_softplus(y - 0.87) for y in pts[:, 1]))
    assert left.item() == pytest.approx(expected, rel=1e-12)


def test_barrier_on_spline_points_only() -> None:
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    n = 5
    left, _, _ = barrier_terms(f, cp, 3.0, BarrierConfig(n_samples=n, control_points=False))
    pts = bspline.evaluate(cp.numpy()[0], np.arange(1, n + 1) / n)
    expected = 1000 * sum(_softplus(y - 0.87) for y in pts[:, 1])
    assert left.item() == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError):
        BarrierConfig(control_points=False)
    with pytest.raises(ValueError):
        TrainConfig(barrier_control_points=False)


def test_bernstein_lateral_barrier_matches_formula() -> None:
    feats = [1.75, 0.01, 0.002, -1.75, 0.01, 0.002, 20.0, 10.0, 15.0]
    cps = [[10.0, 2.5], [20.0, -1.0], [50.0, 0.0]]
    f, cp = _one(feats, cps)
    cfg = BarrierConfig(lateral="bernstein", track=1.9)
    left, right, lead = barrier_terms(f, cp, 4.5, cfg)
    b_left = bspline.lateral_margin_bernstein(np.array(cps), np.array(feats[0:3]), -0.95)
    b_right = -bspline.lateral_margin_bernstein(np.array(cps), np.array(feats[3:6]), 0.95)
    # k = 0 (the origin, independent of the plan) is skipped: 6 terms per line
    assert left.item() == pytest.approx(1000 * sum(_softplus(-b) for b in b_left[1:]), rel=1e-12)
    assert right.item() == pytest.approx(1000 * sum(_softplus(-b) for b in b_right[1:]), rel=1e-12)
    # the leader term is the paper's, unchanged
    _, _, lead_cp = barrier_terms(f, cp, 4.5, BarrierConfig(track=1.9))
    assert lead.item() == lead_cp.item()
    # torch margins equal numpy margins
    tl, tr = bernstein_lane_margins(f, cp, 1.9)
    np.testing.assert_allclose(tl.numpy()[0], b_left, rtol=1e-12)
    np.testing.assert_allclose(tr.numpy()[0], b_right, rtol=1e-12)


def test_bernstein_barrier_with_samples_and_validation() -> None:
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    n = 4
    left, _, _ = barrier_terms(f, cp, 3.0, BarrierConfig(n_samples=n, lateral="bernstein"))
    pts = bspline.evaluate(cp.numpy()[0], np.arange(1, n + 1) / n)
    # straight lane, y = 0: every Bernstein coefficient k >= 1 of the left margin is 0.87
    expected = 1000 * (6 * _softplus(-0.87) + sum(_softplus(y - 0.87) for y in pts[:, 1]))
    assert left.item() == pytest.approx(expected, rel=1e-12)
    assert BarrierConfig().lateral == "control_points"  # the paper stays the default
    assert TrainConfig().barrier.lateral == "control_points"
    assert TrainConfig(barrier_lateral="bernstein").barrier.lateral == "bernstein"
    with pytest.raises(ValueError):
        BarrierConfig(lateral="spline")
    with pytest.raises(ValueError):
        TrainConfig(barrier_lateral="spline")


def test_bernstein_barrier_accepts_lane_following_on_a_curve() -> None:
    """R = 500 m, 30 m/s over 5 s: a plan on the lane centre has its control points ~2.5 m off the
    centre (the paper's barrier fires), its Bernstein coefficients stay inside (no penalty)."""
    c2 = 1 / 1000  # y = x^2 / (2 R)
    feats = [1.75, 0.0, c2, -1.75, 0.0, c2, 30.0, 30.0, 200.0]
    x = 30.0 * bspline.control_point_times(5.0)
    # y = c2 x(tau)^2 = c2 (150 tau)^2: control points of tau^2 are 0, 0, 1/3, 1
    cps = np.stack([x, c2 * 150.0**2 * np.array([0.0, 1 / 3, 1.0])], -1)
    f, t = _one(feats, cps.tolist())
    paper = barrier_terms(f, t, 5.0, BarrierConfig())
    exact = barrier_terms(f, t, 5.0, BarrierConfig(lateral="bernstein"))
    # paper: the middle control points sit c2 X^2 / 9 = 2.5 m right of the centre, 1.63 m past
    # the right limit
    assert paper[1].item() > 1000 * 2 * 1.62
    # exact: the plan IS the centre line, every coefficient is at the 0.87 m margin of the centre
    for term in exact[:2]:
        assert term.item() == pytest.approx(1000 * 6 * _softplus(-0.87), rel=1e-9)


def test_training_with_the_bernstein_barrier(data: Tuples) -> None:
    tr, va = split_by_maneuver(data, 0.2, seed=0)
    cfg = TrainConfig(**{**FAST.__dict__, "max_epochs": 10, "barrier_lateral": "bernstein"})
    _, hist = train(tr, va, cfg, progress=False)
    assert hist.best_val < hist.epochs[0]["val_total"]
    assert hist.epochs[0]["train_barrier_left"] > 0 and hist.epochs[0]["train_barrier_right"] > 0


def test_torch_margins_equal_numpy_margins(data: Tuples) -> None:
    f = torch.as_tensor(data.features)
    cp = torch.as_tensor(data.control_points) + 0.3
    safe = SafeSet(track=1.8, gap_min=1.0, time_gap=0.5)
    ref = plan_margins(data.features, cp.numpy(), data.horizon, safe)
    left, right = lane_margins(f, cp, 1.8)
    times = torch.as_tensor(bspline.control_point_times(data.horizon))
    lead = lead_margins(f, cp, times, 1.0, 0.5)
    np.testing.assert_allclose(left.numpy(), ref["left"], atol=1e-12)
    np.testing.assert_allclose(right.numpy(), ref["right"], atol=1e-12)
    np.testing.assert_allclose(lead.numpy(), ref["lead"], atol=1e-12)


def test_imitation_is_squared_norm_mean_over_batch() -> None:
    pred = torch.zeros(2, 3, 2, dtype=torch.float64)
    target = torch.tensor([[[1.0, 0.0], [0.0, 2.0], [0.0, 0.0]], [[0.0] * 2] * 3])
    assert imitation_loss(pred, target.double()).item() == pytest.approx((1 + 4) / 2)


def test_bc_and_safeil_losses_differ_only_by_the_barrier(data: Tuples) -> None:
    f = torch.as_tensor(data.features[:50])
    target = torch.as_tensor(data.control_points[:50])
    pred = target + torch.linspace(-1, 1, 300, dtype=torch.float64).reshape(50, 3, 2)
    safe = safe_loss(f, pred, target, data.horizon, BarrierConfig(), apply_barrier=True)
    bc = safe_loss(f, pred, target, data.horizon, BarrierConfig(), apply_barrier=False)
    for name in ("imitation", "barrier_left", "barrier_right", "barrier_lead"):
        assert getattr(safe, name).item() == getattr(bc, name).item()
    assert bc.total.item() == bc.imitation.item()
    barrier = safe.barrier_left + safe.barrier_right + safe.barrier_lead
    assert safe.total.item() == pytest.approx((safe.imitation + barrier).item(), rel=1e-15)


# ---------------------------------------------------------------- model

def test_model_shapes_and_initial_mean_plan(data: Tuples) -> None:
    model = PlannerMLP()
    model.set_scaling(data.features, data.control_points)
    out = model(torch.as_tensor(data.features[:7], dtype=torch.float32))
    assert out.shape == (7, 3, 2)
    # zero-initialised last layer: every plan starts at the mean control points
    mean = data.control_points.reshape(-1, 6).mean(axis=0).reshape(3, 2)
    np.testing.assert_allclose(out.detach().numpy(), np.broadcast_to(mean, (7, 3, 2)), rtol=1e-5)
    assert PlannerMLP(hidden=(8,), activation="relu").architecture["hidden"] == [8]
    with pytest.raises(ValueError):
        PlannerMLP(activation="gelu")


# ---------------------------------------------------------------- training

def test_split_leaves_whole_maneuvers_out(data: Tuples) -> None:
    tr, va = split_by_maneuver(data, 0.3, seed=1)
    assert len(tr) + len(va) == len(data)
    assert not set(tr.maneuvers) & set(va.maneuvers)
    assert len(va.maneuvers) == 3
    _, va2 = split_by_maneuver(data, val_maneuvers=["m00_001"])
    assert list(va2.maneuvers) == ["m00_001"]
    with pytest.raises(ValueError):
        split_by_maneuver(data, val_maneuvers=["nope"])


def test_training_reduces_loss(data: Tuples) -> None:
    tr, va = split_by_maneuver(data, 0.2, seed=0)
    for method in ("safeil", "bc"):
        cfg = TrainConfig(**{**FAST.__dict__, "method": method})
        model, hist = train(tr, va, cfg, progress=False)
        first, best = hist.epochs[0], hist.epochs[hist.best_epoch - 1]
        assert best["val_total"] < 0.5 * first["val_total"], method
        assert best["val_imitation"] < first["val_imitation"], method
        assert hist.best_val == best["val_total"]
        assert hist.samples_per_s > 0 and not model.training


def test_same_seed_same_weights_other_seed_differs(data: Tuples) -> None:
    tr, va = split_by_maneuver(data, 0.2, seed=0)
    cfg = TrainConfig(**{**FAST.__dict__, "max_epochs": 5})
    m1, h1 = train(tr, va, cfg, progress=False)
    m2, h2 = train(tr, va, cfg, progress=False)
    m3, _ = train(tr, va, TrainConfig(**{**cfg.__dict__, "seed": 1}), progress=False)
    for k, v in m1.state_dict().items():
        assert torch.equal(v, m2.state_dict()[k]), k
    assert [e["val_total"] for e in h1.epochs] == [e["val_total"] for e in h2.epochs]
    assert not torch.equal(m1.net[0].weight, m3.net[0].weight)
    assert torch.get_num_threads() >= 1  # restored, not left at the training setting by force


def test_bc_is_safeil_without_barrier(data: Tuples) -> None:
    """Same network, data and loop: SafeIL with K = 0 trains bit-identically to BC."""
    tr, va = split_by_maneuver(data, 0.2, seed=0)
    base = {**FAST.__dict__, "max_epochs": 5}
    bc, hb = train(tr, va, TrainConfig(**{**base, "method": "bc"}), progress=False)
    k0, hk = train(tr, va, TrainConfig(**{**base, "barrier_k": 0.0}), progress=False)
    for k, v in bc.state_dict().items():
        assert torch.equal(v, k0.state_dict()[k]), k
    assert [e["val_imitation"] for e in hb.epochs] == [e["val_imitation"] for e in hk.epochs]
    # ... while the paper's K pulls plans inside the lane
    safe, hs = train(tr, va, TrainConfig(**base), progress=False)
    assert not torch.equal(safe.net[0].weight, bc.net[0].weight)
    assert hs.epochs[-1]["train_barrier_left"] > 0


def test_train_config_validation() -> None:
    with pytest.raises(ValueError):
        TrainConfig(method="dagger")
    assert TrainConfig(hidden=[32, 16]).hidden == (32, 16)
    assert TrainConfig.from_dict(TrainConfig(hidden=(8,)).__dict__) == TrainConfig(hidden=(8,))


# ---------------------------------------------------------------- evaluation

class _Oracle:
    """A policy that returns the target control points of known features (by row lookup)."""

    name = "oracle"

    def __init__(self, t: Tuples) -> None:
        self.horizon = t.horizon
        self._t = t

    def plan(self, features: np.ndarray) -> np.ndarray:
        assert features is self._t.features
        return self._t.control_points


def test_open_loop_metrics_of_perfect_plans(data: Tuples) -> None:
    m = open_loop_metrics(_Oracle(data), data)
    assert m["cp_rmse"] == 0.0
    assert m["ade"] == pytest.approx(m["target_fit_ade"])
    assert m["ade"] < 0.2  # the cubic spline fits 5 s of smooth following well
    assert m["n"] == len(data)
    for where in ("cp", "spline"):
        for c in ("left", "right", "lead"):
            assert f"min_margin_{c}_{where}" in m
    assert 0.0 <= m["hull_gap_rate"] <= m["violation_rate_any_spline"]
    assert m["violation_rate_lateral_bern"] == m["target_violation_rate_lateral_bern"]


def test_demonstrations_on_curves_violate_the_paper_formulation_not_the_exact_one(
    data: Tuples,
) -> None:
    """Curved fixture (|R| >= 600 m): the paper's control-point condition rejects many human plans
    whose splines stay inside the lane; the Bernstein condition, exact on curves, rejects none."""
    m = open_loop_metrics(_Oracle(data), data)
    assert m["target_violation_rate_lateral_spline"] == 0.0  # the demonstrations are inside
    assert m["target_violation_rate_lateral_bern"] == 0.0
    assert m["target_violation_rate_lateral_cp"] > 0.2
    assert m["min_margin_left_bern"] > 0 and m["min_margin_right_bern"] > 0
    straight = make_tuples(n_maneuvers=4, curved=False)
    ms = open_loop_metrics(_Oracle(straight), straight)
    assert ms["target_violation_rate_lateral_cp"] == ms["target_violation_rate_lateral_bern"] == 0.0


def test_hull_gap_on_a_curve_is_measured() -> None:
    """Control points on the safe side of a curved left line, chord cutting across it."""
    feats = np.array([[1.75, 0.0, 0.005, -1.75, 0.0, 0.005, 20.0, 20.0, 100.0]])
    x = np.array([20.0, 40.0, 60.0])
    y = 1.75 + 0.005 * x**2 - 0.88 - 0.01  # 1 cm inside the left limit at each control point
    plans = np.stack([x, y], axis=-1)[None]
    m = plan_metrics(feats, plans, plans, np.zeros((1, 4, 2)), np.arange(1, 5.0), 4.0)
    assert m["violation_rate_any_cp"] == 0.0
    assert m["hull_gap_rate"] == 1.0 and m["min_margin_left_spline"] < 0


# ---------------------------------------------------------------- CLI

def test_cli_trains_and_writes_checkpoint(tmp_path: Path, data: Tuples) -> None:
    data.save(tmp_path / "tuples.parquet")
    out = tmp_path / "models" / "safeil_test"
    proc = subprocess.run(
        [sys.executable, str(REPO / "training" / "train.py"), "--data",
         str(tmp_path / "tuples.parquet"), "--method", "bc", "--epochs", "3", "--seed", "2", "--barrier-lateral", "bernstein",
         "--out", str(out), "--no-progress"],
        capture_output=True, text=True, cwd=REPO, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "cp_rmse" in proc.stdout and "target_violation_rate_lateral_bern" in proc.stdout
    assert '"barrier_lateral": "bernstein"' in proc.stdout
    assert (tmp_path / "models" / "safeil_test.safetensors").is_file()
    assert (tmp_path / "models" / "safeil_test.json").is_file()


# ------------------------------------- cases found by mutation testing (docs/mutation_testing.md)


def test_losses_by_hand_on_batches_and_weights() -> None:
    """Imitation: squared error summed over the 6 outputs (x and y weighted per sample), mean
    over a batch of 3; barriers: summed over the points, mean over the batch."""
    from safeil_sumo.learn.losses import constrained_points

    pred = torch.tensor([[[1.0, 1.0], [2.0, 0.0], [3.0, 0.0]]] * 3, dtype=torch.float64)
    target = pred.clone()
    target[0, 0, 0], target[1, 1, 1], target[2, 2, 0] = 3.0, 1.0, 0.0  # errors 2, 1, 3
    assert imitation_loss(pred, target).item() == pytest.approx((4 + 1 + 9) / 3)
    w = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.5, 1.0]], dtype=torch.float64)
    assert imitation_loss(pred, target, w).item() == pytest.approx((4 + 1 + 0.5 * 9) / 3)
    f = torch.tensor([STRAIGHT] * 3, dtype=torch.float64)
    terms = safe_loss(f, pred, target, 3.0, axis_weight=w)  # the barrier is on by default
    assert terms.imitation.item() == pytest.approx((4 + 1 + 4.5) / 3)
    assert terms.total.item() == pytest.approx(
        terms.imitation.item() + terms.barrier_left.item() + terms.barrier_right.item()
        + terms.barrier_lead.item())
    # two plans: one on the centre line, one 1 m left at every point; per-plan sums, batch mean
    f2, cp2 = f[:2], torch.tensor([[[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]],
                                   [[10.0, 1.0], [20.0, 1.0], [30.0, 1.0]]], dtype=torch.float64)
    left, _, _ = barrier_terms(f2, cp2, 3.0, BarrierConfig())
    assert left.item() == pytest.approx(1000 * (3 * _softplus(-0.87) + 3 * _softplus(0.13)) / 2)
    # the points and times the barrier acts on: by default the 3 control points only
    pts, times = constrained_points(cp2, 6.0)
    assert torch.equal(pts, cp2) and times.tolist() == [2.0, 4.0, 6.0]
    pts, times = constrained_points(cp2, 6.0, n_samples=2, include_control=False)
    np.testing.assert_allclose(pts[1].numpy(), bspline.evaluate(cp2[1].numpy(), [0.5, 1.0]))
    assert times.tolist() == [3.0, 6.0]
    _, times = constrained_points(cp2, 6.0, n_samples=1)
    assert times.tolist() == [2.0, 4.0, 6.0, 6.0]


def test_lead_margin_options_each_alone() -> None:
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.0], [60.0, 0.0]])
    times = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    base = [40 + 25 * t - x for x, t in ((10, 1), (20, 2), (60, 3))]
    np.testing.assert_allclose(lead_margins(f, cp, times, gap_min=2.0).numpy()[0],
                               [b - 2.0 for b in base])
    np.testing.assert_allclose(lead_margins(f, cp, times, time_gap=1.0).numpy()[0],
                               [b - 25.0 for b in base])


def test_barrier_config_messages() -> None:
    with pytest.raises(ValueError, match=r"^lateral must be one of \('control_points', "
                                         r"'bernstein'\), got 'spline'$"):
        BarrierConfig(lateral="spline")
    with pytest.raises(ValueError, match="^the barrier needs control points or n_samples > 0$"):
        BarrierConfig(control_points=False)
    assert BarrierConfig(control_points=False, n_samples=1).n_samples == 1


def test_bernstein_barrier_on_spline_points_only() -> None:
    """lateral="bernstein" with control_points=False: the 6 Bernstein terms per line and ALL
    the sampled points (none of them is a control point to skip)."""
    f, cp = _one(STRAIGHT, [[10.0, 0.0], [20.0, 0.5], [30.0, 1.0]])
    n = 4
    cfg = BarrierConfig(n_samples=n, control_points=False, lateral="bernstein")
    left, _, _ = barrier_terms(f, cp, 3.0, cfg)
    b_left = bspline.lateral_margin_bernstein(cp.numpy()[0], np.array(STRAIGHT[0:3]), -0.88)
    pts = bspline.evaluate(cp.numpy()[0], np.arange(1, n + 1) / n)
    expected = 1000 * (sum(_softplus(-b) for b in b_left[1:])
                       + sum(_softplus(y - 0.87) for y in pts[:, 1]))
    assert left.item() == pytest.approx(expected, rel=1e-12)


def test_envelope_barrier_keeps_every_setting_and_the_margin_where_reachable() -> None:
    """The envelope barrier is barrier_terms with the same settings (K, track, samples, control
    points, lateral mode): with the margin where braking at 6 m/s^2 can reach it, the paper's
    zero margin elsewhere; each state's terms summed over its points, averaged over the batch."""
    from safeil_sumo.learn.losses import envelope_barrier_terms

    cfg = BarrierConfig(k=10.0, track=2.0, n_samples=4, control_points=False,
                        lateral="bernstein", gap_min=2.0, time_gap=1.0)
    zero = BarrierConfig(k=10.0, track=2.0, n_samples=4, control_points=False,
                         lateral="bernstein")
    # x(t) = 28 t over 5 s (a straight spline), drifting left: the margins matter
    cp = torch.tensor([[[140 / 3, 0.3], [280 / 3, 0.6], [140.0, 0.9]]], dtype=torch.float64)

    def state(v: float, v_lead: float, gap: float) -> torch.Tensor:
        return torch.tensor([[1.75, 0.0, 0.0, -1.75, 0.0, 0.0, v, v_lead, gap]],
                            dtype=torch.float64)

    # with the margin the points sit 5 m short of it (reach) or past it (far, edge); without,
    # 37 m and more: each case below tells the two apart
    assert barrier_terms(state(30.0, 28.0, 37.0), cp, 5.0, cfg)[2].item() > 0.1
    assert barrier_terms(state(30.0, 28.0, 37.0), cp, 5.0, zero)[2].item() < 1e-9
    # reachable: closing at 2 m/s, gap - margin = 37 - 32 = 5 m > 4 / 12 m
    # (and > 4 / 3 m and < 48 m: a misplaced brake factor would decide otherwise)
    reach = state(30.0, 28.0, 37.0)
    env = envelope_barrier_terms(reach, cp, 5.0, cfg)
    for a, b in zip(env, barrier_terms(reach, cp, 5.0, cfg), strict=True):
        assert a.item() == pytest.approx(b.item(), rel=1e-12)
    # out of reach: closing at 10 m/s, 8 m < 100 / 12 m: the zero margin
    far = state(30.0, 20.0, 40.0)
    env_far = envelope_barrier_terms(far, cp, 5.0, cfg)
    assert env_far[2].item() < 0.5 * barrier_terms(far, cp, 5.0, cfg)[2].item()
    for a, b in zip(env_far, barrier_terms(far, cp, 5.0, zero), strict=True):
        assert a.item() == pytest.approx(b.item(), rel=1e-12)
    # opening by 5 m/s, 5 cm beyond the 22 m margin: reachable (nothing to brake for)
    edge = state(20.0, 25.0, 22.05)
    assert barrier_terms(edge, cp, 5.0, cfg)[2].item() > 10 * barrier_terms(edge, cp, 5.0,
                                                                           zero)[2].item()
    assert envelope_barrier_terms(edge, cp, 5.0, cfg)[2].item() == pytest.approx(
        barrier_terms(edge, cp, 5.0, cfg)[2].item(), rel=1e-12)
    # the gap margin alone (no time gap) is a margin too
    only_gap = BarrierConfig(gap_min=30.0)
    cp_paper = torch.tensor([[[50.0, 0.0], [75.0, 0.0], [100.0, 0.0]]], dtype=torch.float64)
    wide = state(25.0, 25.0, 60.0)
    assert envelope_barrier_terms(wide, cp_paper, 3.0, only_gap)[2].item() == pytest.approx(
        barrier_terms(wide, cp_paper, 3.0, only_gap)[2].item(), rel=1e-12)
    assert barrier_terms(wide, cp_paper, 3.0, only_gap)[2].item() > 1.0
    # the paper's lane terms on the sampled points only (no control points): kept too
    cfg_cp = BarrierConfig(n_samples=4, control_points=False, gap_min=2.0, time_gap=1.0)
    zero_cp = BarrierConfig(n_samples=4, control_points=False)
    for a, b in zip(envelope_barrier_terms(far, cp, 5.0, cfg_cp)[:2],
                    barrier_terms(far, cp, 5.0, zero_cp)[:2], strict=True):
        assert a.item() == pytest.approx(b.item(), rel=1e-12)
    # a batch of both: the mean of the two
    both = envelope_barrier_terms(torch.cat([reach, far]), cp.expand(2, 3, 2), 5.0, cfg)
    for k in range(3):
        assert both[k].item() == pytest.approx((env[k].item() + env_far[k].item()) / 2,
                                               rel=1e-12)


def test_train_cli_has_every_config_field_under_its_own_name() -> None:
    """training/train.py's options are generated from TrainConfig: each field is ``--<field>``,
    its default is the config's, and the options build the config they name (old flag names
    kept as aliases)."""
    import dataclasses

    from safeil_sumo.learn.trainer import TrainConfig

    cli = load_training_script("train")
    base = ["--data", "x.parquet", "--out", "o"]
    assert cli.config_of(cli.parse_args(base)) == TrainConfig()
    args = cli.parse_args([*base, "--weight-decay", "0.01", "--max-epochs", "7", "--hidden", "32,16",
                           "--no-barrier-control-points", "--barrier-samples", "4",
                           "--longitudinal-only-sources", "openacc", "ngsim", "--threads", "2",
                           "--monotone-margin", "0.002", "--envelope-weight", "0.1"])
    assert cli.config_of(args) == TrainConfig(
        weight_decay=0.01, max_epochs=7, hidden=(32, 16), barrier_control_points=False,
        barrier_samples=4, longitudinal_only_sources=("openacc", "ngsim"), num_threads=2,
        monotone_margin_m=0.002, envelope_weight=0.1)
    for field in dataclasses.fields(TrainConfig):
        flag = "--" + field.name.replace("_", "-")
        assert any(flag in a.option_strings for a in cli.build_parser()._actions), flag
    with pytest.raises(ValueError, match="weight_decay"):
        cli.config_of(cli.parse_args([*base, "--weight-decay", "-1"]))





def test_train_cli_round_trips_a_config_with_every_field_changed() -> None:
    """Every TrainConfig field has a help (its metadata, shown by --help) and a flag; a
    command line setting every field to a non-default value parses into that config."""
    import dataclasses

    cli = load_training_script("train")
    changed = TrainConfig(
        method="bc", hidden=(32, 16), activation="relu", lr=5e-4, weight_decay=0.01,
        batch_size=64, max_epochs=7, patience=3, seed=5, barrier_k=10.0, track=1.9, gap_min=2.0,
        time_gap=0.5, barrier_samples=4, barrier_control_points=False, num_threads=2,
        barrier_lateral="bernstein", output_mode="residual",
        longitudinal_only_sources=("openacc", "ngsim"), lateral_only_sources=("synthetic",),
        envelope_weight=0.1, envelope_batch=32, monotone_weight=3.0, monotone_margin_m=0.002)
    default = TrainConfig()
    for f in dataclasses.fields(TrainConfig):
        assert getattr(changed, f.name) != getattr(default, f.name), f.name  # all covered
        assert f.metadata["help"].strip(), f.name
    argv = ["--data", "x.parquet", "--out", "o", "--method", "bc", "--hidden", "32,16",
            "--activation", "relu", "--lr", "5e-4", "--weight-decay", "0.01", "--batch-size",
            "64", "--max-epochs", "7", "--patience", "3", "--seed", "5", "--barrier-k", "10",
            "--track", "1.9", "--gap-min", "2", "--time-gap", "0.5", "--barrier-samples", "4",
            "--no-barrier-control-points", "--num-threads", "2", "--barrier-lateral",
            "bernstein", "--output-mode", "residual", "--longitudinal-only-sources", "openacc",
            "ngsim", "--lateral-only-sources", "synthetic", "--envelope-weight", "0.1",
            "--envelope-batch", "32", "--monotone-weight", "3", "--monotone-margin-m", "0.002"]
    assert cli.config_of(cli.parse_args(argv)) == changed
    help_text = " ".join(cli.build_parser().format_help().split())
    assert "growth [m] of the plan per 2 m of gap" in help_text  # the field's own help


@pytest.mark.parametrize("bad", [
    ["--no-such-flag", "1"], ["--max-epochs", "ten"], ["--lr", "nan"], ["--hidden", "64,a"],
    ["--method", "ppo"], ["--epochs"],
])
def test_train_cli_refuses_bad_flags_with_a_usage_error(bad, capsys) -> None:
    """An unknown flag, a value of the wrong type, a choice not offered or a missing value is
    argparse's usage error (exit 2, one line naming the option), before any data is read."""
    cli = load_training_script("train")
    with pytest.raises(SystemExit) as exc:
        cli.parse_args(["--data", "x.parquet", "--out", "o", *bad])
    assert exc.value.code == 2
    assert bad[0] in capsys.readouterr().err
