"""The levers that make a learned planner follow its leader: residual output mode, per-source
lateral masks, mixed sources, envelope barrier states, gap monotonicity; and the static probe."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from fixtures_training import make_tuples

from safeil_sumo.data.tuples import Tuples
from safeil_sumo.experiments.leader_probe import (
    ProbeGrid,
    probe,
    recoverable,
    straight_lane_features,
)
from safeil_sumo.learn.checkpoint import save_checkpoint
from safeil_sumo.learn.envelope import EnvelopeConfig, sample_states
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.learn.losses import BarrierConfig, barrier_terms, envelope_barrier_terms
from safeil_sumo.learn.model import PlannerMLP, constant_speed_points
from safeil_sumo.learn.trainer import (
    TrainConfig,
    axis_weights,
    gap_monotone_penalty,
    split_by_maneuver,
    train,
)
from safeil_sumo.planners.analytic import AnalyticPlanner

SMALL = TrainConfig(max_epochs=3, patience=3, batch_size=64)


class ConstantSpeed:
    """Leader-blind: drives straight on at its current speed."""

    name = "constant_speed"
    horizon = 5.0

    def plan(self, features: np.ndarray) -> np.ndarray:
        return constant_speed_points(np.asarray(features)[..., 6], self.horizon)


@pytest.fixture(scope="module")
def data() -> Tuples:
    return make_tuples(n_maneuvers=6, per_maneuver=20)


# ------------------------------------------------------------------------------------ probe


def test_recoverable_hand_computed() -> None:
    # 30 -> 20 m/s closing: braking at 6 m/s^2 needs 10^2 / 12 = 8.33 m
    assert recoverable(30.0, 20.0, 8.4, 6.0)
    assert not recoverable(30.0, 20.0, 8.3, 6.0)
    assert recoverable(20.0, 30.0, 0.5, 6.0)  # a faster leader is always recoverable


def test_probe_counts_a_leader_blind_planner_exactly() -> None:
    grid = ProbeGrid(ego_speeds_mps=(30.0,), relative_speeds_mps=(-5.0, 0.0),
                     gaps_m=(10.0, 30.0))
    summary, states = probe(ConstantSpeed(), grid)
    # v 30, lead 25: over 5 s the ego gains 25 m -> passes at gap 10 and 30 m? 25 < 30: no
    # v 30, lead 30: never passes
    expected = {(25.0, 10.0): True, (25.0, 30.0): False, (30.0, 10.0): False, (30.0, 30.0): False}
    got = {(r.v_lead, r.gap): r.passes_leader for r in states.itertuples()}
    assert got == expected
    assert summary["pass_rate"] == pytest.approx(0.25)
    assert summary["gap_monotone_violations"] == 0


def test_probe_analytic_planner_stays_behind() -> None:
    summary, _ = probe(AnalyticPlanner())
    assert summary["pass_rate"] < 0.005
    assert summary["gap_monotone_violations"] == 0
    assert summary["end_speed_v30_lead25_gap10"] < 25.0


# ------------------------------------------------------------------------ residual outputs


def test_residual_mode_adds_constant_speed_motion(data: Tuples) -> None:
    model = PlannerMLP(output_mode="residual", horizon=5.0)
    model.set_scaling(data.features, data.control_points)
    with torch.no_grad():
        for p in model.net[-1].parameters():
            p.zero_()  # net output 0 -> the mean residual only
        f = torch.as_tensor(data.features[:4], dtype=torch.float32)
        out = model(f).numpy()
    resid = data.control_points - constant_speed_points(data.features[:, 6], 5.0)
    mean = resid.reshape(-1, 6).mean(axis=0).reshape(3, 2)
    expected = constant_speed_points(data.features[:4, 6], 5.0) + mean
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-3)


def test_residual_numpy_inference_equals_torch(tmp_path, data: Tuples) -> None:
    cfg = dataclasses.replace(SMALL, output_mode="residual")
    tr, va = split_by_maneuver(data, 0.3, 0)
    model, _ = train(tr, va, cfg, progress=False)
    save_checkpoint(tmp_path / "m", model, name="m", horizon=data.horizon, train_config=cfg)
    policy = load_policy(tmp_path / "m")
    with torch.no_grad():
        ref = model(torch.as_tensor(data.features, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(policy.plan(data.features), ref, atol=1e-3)
    np.testing.assert_allclose(policy.plan(data.features[0]), ref[0], atol=1e-3)


# --------------------------------------------------------------------------- mixed sources


def _with_source(t: Tuples, source: str, prefix: str) -> Tuples:
    return dataclasses.replace(t, source=np.full(len(t), source),
                               maneuver_id=np.char.add(prefix, t.maneuver_id.astype(str)))


def test_concat_and_per_source_split(data: Tuples) -> None:
    a = _with_source(data, "synthetic", "s")
    b = _with_source(data, "openacc", "o")
    both = Tuples.concat([a, b])
    assert len(both) == 2 * len(data)
    _, va = split_by_maneuver(both, 0.34, 0)
    for src in ("synthetic", "openacc"):  # every source held out in proportion (2 of 6)
        assert len(np.unique(va.maneuver_id[va.source == src])) == 2
    with pytest.raises(ValueError, match="disagree"):
        Tuples.concat([a, dataclasses.replace(b, horizon=4.0)])


def test_single_source_split_is_unchanged(data: Tuples) -> None:
    # the split of a single-source set is the one of earlier versions: seeded choice of ids
    _, va = split_by_maneuver(data, 0.34, 3)
    rng = np.random.default_rng(3)
    expected = np.sort(rng.choice(data.maneuvers, size=2, replace=False))
    np.testing.assert_array_equal(va.maneuvers, expected)


def test_per_source_axis_masks(data: Tuples) -> None:
    t = Tuples.concat([_with_source(data, "synthetic", "s"), _with_source(data, "openacc", "o")])
    cfg = TrainConfig(longitudinal_only_sources=("openacc",), lateral_only_sources=("synthetic",))
    w = axis_weights(t, cfg).numpy()
    np.testing.assert_array_equal(w[:, 0], (t.source == "openacc").astype(float))
    np.testing.assert_array_equal(w[:, 1], (t.source == "synthetic").astype(float))
    with pytest.raises(ValueError, match="teach nothing"):
        TrainConfig(longitudinal_only_sources=("a",), lateral_only_sources=("a",))
    from safeil_sumo.learn.losses import imitation_loss

    pred = torch.zeros(2, 3, 2)
    target = torch.zeros(2, 3, 2)
    target[:, :, 1] = 1.0  # 1 m lateral error on each control point
    target[:, :, 0] = 2.0  # 2 m longitudinal error
    # sample 0 counts both axes, sample 1 only x: (3*4 + 3*1 + 3*4) / 2
    loss = imitation_loss(pred, target, torch.tensor([[1.0, 1.0], [1.0, 0.0]]))
    assert float(loss) == pytest.approx((3 * 4 + 3 * 1 + 3 * 4) / 2)


# ------------------------------------------------------------------------------- envelope


def test_envelope_states_are_recoverable_and_seeded() -> None:
    cfg = EnvelopeConfig()
    a = sample_states(2000, np.random.default_rng(5), cfg)
    b = sample_states(2000, np.random.default_rng(5), cfg)
    np.testing.assert_array_equal(a, b)
    v, v_lead, gap = a[:, 6], a[:, 7], a[:, 8]
    assert recoverable(v, v_lead, gap, cfg.brake_mps2).all()
    assert (v >= 0).all() and (v <= 40).all() and (v_lead >= 0).all()
    width = a[:, 0] - a[:, 3]
    assert width.min() >= 3.3 - 1e-9 and width.max() <= 3.8 + 1e-9
    assert (v_lead - v < -5).mean() > 0.3  # slower leaders are well covered
    free = gap == cfg.radar_range_m
    assert 0.05 < free.mean() < 0.2 and np.allclose(v_lead[free], v[free])


def test_envelope_margin_only_where_reachable() -> None:
    # straight centred lane; plan = stand still (all control points at the origin)
    f = torch.as_tensor(straight_lane_features(np.array([30.0, 30.0]), np.array([30.0, 30.0]),
                                               np.array([10.0, 80.0])), dtype=torch.float32)
    still = torch.zeros(2, 3, 2)
    cfg = BarrierConfig(gap_min=2.0, time_gap=1.0)
    # gap 10 m < margin 32 m (unreachable): the zero-margin barrier, as the paper's
    _, _, lead_env = envelope_barrier_terms(f[:1], still[:1], 5.0, cfg)
    _, _, lead_paper = barrier_terms(f[:1], still[:1], 5.0, BarrierConfig())
    assert float(lead_env) == pytest.approx(float(lead_paper))
    # gap 80 m: the margin applies: margins 80 + 30 t_i - 32 at t = 5/3, 10/3, 5
    _, _, lead = envelope_barrier_terms(f[1:], still[1:], 5.0, cfg)
    m = np.array([80 + 30 * t - 32 for t in (5 / 3, 10 / 3, 5.0)])
    assert float(lead) == pytest.approx(1000 * np.log1p(np.exp(-m)).sum(), rel=1e-4)


def test_gap_monotone_penalty() -> None:
    class Linear(torch.nn.Module):
        def __init__(self, slope: float) -> None:
            super().__init__()
            self.slope = slope

        def forward(self, f: torch.Tensor) -> torch.Tensor:  # x_i = slope * gap, y = 0
            x = self.slope * f[:, 8:9].expand(-1, 3)
            return torch.stack([x, torch.zeros_like(x)], dim=-1)

    f = torch.as_tensor(sample_states(16, np.random.default_rng(0)), dtype=torch.float32)
    assert float(gap_monotone_penalty(Linear(0.5), f)) == 0.0
    # x shrinks by 0.5 * 2 m per control point when the gap grows by 2 m
    assert float(gap_monotone_penalty(Linear(-0.5), f)) == pytest.approx(3.0)
    # a margin asks for growth: a flat plan pays it on each of the 3 control points
    assert float(gap_monotone_penalty(Linear(0.0), f, margin_m=0.01)) == pytest.approx(0.03)
    assert float(gap_monotone_penalty(Linear(0.5), f, margin_m=0.01)) == 0.0


def test_envelope_training_runs_and_logs_its_terms(data: Tuples) -> None:
    cfg = dataclasses.replace(SMALL, output_mode="residual", envelope_weight=1.0, gap_min=2.0,
                              time_gap=1.0, monotone_weight=10.0, envelope_batch=32)
    tr, va = split_by_maneuver(data, 0.3, 0)
    m1, h1 = train(tr, va, cfg, progress=False)
    m2, _ = train(tr, va, cfg, progress=False)
    assert "val_barrier_envelope" in h1.epochs[0] and "train_gap_monotone" in h1.epochs[0]
    for a, b in zip(m1.state_dict().values(), m2.state_dict().values(), strict=True):
        assert torch.equal(a, b)  # same seed, same envelope draws, same weights
    assert TrainConfig.from_dict(dataclasses.asdict(cfg)) == cfg


# ------------------------------------- cases found by mutation testing (docs/mutation_testing.md)


def test_envelope_draws_each_quantity_per_state() -> None:
    """Every state gets its own lane width, offset, heading, curvature and leader, within the
    configured ranges: lines in the ego frame at +-width/2 - offset, both with the lane's c1 and
    c2 = curvature / 2; leader speeds clipped at 0 (not above); a 10 % share of "no leader"
    states drawn before the recoverability filter (about 11 % after it)."""
    a = sample_states(4000, np.random.default_rng(2))
    width, offset = a[:, 0] - a[:, 3], -(a[:, 0] + a[:, 3]) / 2
    for x, lo, hi in ((width, 3.3, 3.8), (offset, -0.6, 0.6), (a[:, 1], -0.03, 0.03),
                      (a[:, 2], -0.002, 0.002)):
        assert x.min() >= lo - 1e-9 and x.max() <= hi + 1e-9
        assert x.std() > 0.2 * (hi - lo)  # spread over the range, not one value for all
        assert x.max() - x.min() > 0.9 * (hi - lo)
    np.testing.assert_array_equal(a[:, 1], a[:, 4])
    np.testing.assert_array_equal(a[:, 2], a[:, 5])
    lead = a[a[:, 8] != 150.0]
    rel = lead[:, 7] - lead[:, 6]
    moving = lead[:, 7] > 0
    assert rel[moving].min() >= -15.0 - 1e-9 and rel.max() <= 5.0 + 1e-9
    assert rel[moving].std() > 3.0
    assert (lead[:, 7] == 0.0).mean() > 0.05  # a slow ego behind a stopped leader exists
    free = a[:, 8] == 150.0
    assert 0.09 < free.mean() < 0.13


def test_envelope_small_draws_and_always_recoverable_leaders() -> None:
    """Any n works (the batch is oversampled); a faster leader is recoverable at any gap (no
    closing: nothing to brake for), so a tiny-gap envelope of faster leaders is kept whole."""
    for n in (1, 2, 3):
        assert sample_states(n, np.random.default_rng(n)).shape == (n, 9)
    cfg = dataclasses.replace(EnvelopeConfig(), gap_m=(0.01, 0.05), relative_speed_mps=(0.5, 5.0),
                              ego_speed_mps=(10.0, 30.0), no_leader_share=0.0)
    gap = sample_states(50, np.random.default_rng(0), cfg)[:, 8]
    assert gap.max() <= 0.05
