"""The (s0, T) style estimator: a Kalman update of a driver's standstill distance and time gap."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.learn.style_estimator import (
    StyleEstimate,
    StylePrior,
    bounded_style,
    estimate_drive,
    forget,
    least_squares_style,
    steady_following,
    update,
)

# a prior whose numbers make the 2x2 algebra easy by hand: P0 = diag(4, 1), R = 1 per sample
# (noise_rel * g0 = 1 m at v = 0 with s0 = 2, T = 1: 0.5 * 2; correlation_s = dt_s: no inflation)
HAND = StylePrior(s0_m=2.0, time_gap_s=1.0, sd_s0_m=2.0, sd_time_gap_s=1.0, corr=0.0,
                  noise_rel=0.5, correlation_s=0.1)


def test_the_prior_alone_without_samples():
    prior = StylePrior()
    state = prior.initial()
    assert (state.s0_m, state.time_gap_s) == (prior.s0_m, prior.time_gap_s)
    np.testing.assert_allclose(state.cov, prior.cov)
    assert state.samples == 0 and math.isnan(state.mean_speed_mps)
    # a drive without one steady sample (always closing in) leaves it there
    t = np.arange(0.0, 30.0, 0.1)
    final, traj = estimate_drive(t, np.full(len(t), 40.0), np.full(len(t), 20.0),
                                 np.full(len(t), 15.0), prior)
    assert not traj.steady.any()
    np.testing.assert_allclose(final.mean, prior.mean)
    np.testing.assert_allclose(final.cov, prior.cov)
    np.testing.assert_allclose(traj.s0_m, prior.s0_m)


def test_one_update_by_hand_at_standstill_speed_zero():
    """h = [1, 0]: only s0 is observed. S = 4 + 1 = 5, K = [4/5, 0]; gap 7: innovation 5,
    s0 = 2 + 4/5 * 5 = 6, var s0 = 4 - 16/5 = 0.8, T untouched."""
    post = update(HAND.initial(), 7.0, 0.0, HAND, dt_s=0.1)
    assert post.s0_m == pytest.approx(6.0) and post.time_gap_s == pytest.approx(1.0)
    np.testing.assert_allclose(post.cov, [[0.8, 0.0], [0.0, 1.0]], atol=1e-12)
    assert post.samples == 1 and post.seen_s == pytest.approx(0.1)


def test_one_update_by_hand_at_speed():
    """v = 2 m/s, h = [1, 2]: prior gap 2 + 2 = 4 m, R = (0.5 * 4)^2 = 4 m^2.
    P h' = [4, 2], S = h P h' + R = 4 + 4 + 4 = 12, K = [1/3, 1/6]. Gap 10: innovation 6,
    s0 = 2 + 2 = 4, T = 1 + 1 = 2. P' = P - K (P h')' = [[4 - 4/3, -2/3], [-2/3, 1 - 1/3]]."""
    post = update(HAND.initial(), 10.0, 2.0, HAND, dt_s=0.1)
    assert post.s0_m == pytest.approx(4.0) and post.time_gap_s == pytest.approx(2.0)
    np.testing.assert_allclose(post.cov, [[8 / 3, -2 / 3], [-2 / 3, 2 / 3]], atol=1e-12)
    assert post.mean_speed_mps == 2.0
    # the speed the line is centred on: the running mean of the samples' speeds
    assert update(post, 10.0, 4.0, HAND).mean_speed_mps == pytest.approx(3.0)
    assert update(update(post, 10.0, 4.0, HAND), 10.0, 6.0, HAND).mean_speed_mps == 4.0


def test_the_prior_covariance_by_hand():
    prior = StylePrior(sd_s0_m=2.0, sd_time_gap_s=0.5, corr=-0.5)
    np.testing.assert_allclose(prior.cov, [[4.0, -0.5], [-0.5, 0.25]])
    np.testing.assert_allclose(prior.initial().cov, prior.cov)


def test_correlated_samples_count_one_per_correlation_time():
    """correlation_s = 1 s, dt = 0.1 s: R is 10x that of one independent sample, so ten
    samples of 0.1 s move the estimate as one of 1 s would (to round-off: the same posterior
    in information form, 10 * h h' / (10 R) = h h' / R)."""
    prior = StylePrior(s0_m=2.0, time_gap_s=1.0, sd_s0_m=2.0, sd_time_gap_s=1.0, corr=0.0,
                       noise_rel=0.5, correlation_s=1.0)
    many = prior.initial()
    for _ in range(10):
        many = update(many, 7.0, 0.0, prior, dt_s=0.1)
    one = update(prior.initial(), 7.0, 0.0, prior, dt_s=1.0)
    np.testing.assert_allclose(many.mean, one.mean, rtol=1e-9)
    np.testing.assert_allclose(many.cov, one.cov, rtol=1e-9)
    assert many.seen_s == pytest.approx(1.0)


def test_forgetting_by_hand_and_none_by_default():
    """tau = 10 s, 10 s elapsed: a = 1/e, mean mu0 + a (m - mu0), P = a^2 P + (1 - a^2) P0."""
    prior = StylePrior(s0_m=2.0, time_gap_s=1.0, sd_s0_m=2.0, sd_time_gap_s=1.0, corr=0.0,
                       noise_rel=0.5, correlation_s=0.1, forget_tau_s=10.0)
    state = StyleEstimate(6.0, 2.0, 1.0, 0.5, 0.5)
    a = math.exp(-1.0)
    out = forget(state, prior, 10.0)
    np.testing.assert_allclose(out.mean, [2 + 4 * a, 1 + a])
    np.testing.assert_allclose(out.cov, a * a * state.cov + (1 - a * a) * prior.cov)
    assert math.isinf(StylePrior().forget_tau_s)
    assert forget(state, StylePrior(), 1e6) == state


def test_steady_following_criteria():
    v = np.array([20.0, 20.0, 1.5, 20.0, 20.0, 20.0, np.nan, 20.0])
    vl = np.array([20.5, 22.0, 1.5, 20.0, 20.0, 20.0, 20.0, 20.0])
    gap = np.array([30.0, 30.0, 3.0, 120.0, 30.0, 0.2, 30.0, 99.0])
    acc = np.array([0.1, 0.0, 0.0, 0.0, 0.8, 0.0, 0.0, 0.0])
    # kept: the first (small relative speed) and the last (99 m at 20 m/s: 4.95 s < 5 s);
    # closing at 2 m/s, walking pace, 6 s behind, accelerating, 0.2 m, NaN speed: not steady
    assert steady_following(gap, v, vl, acc).tolist() == [True, False, False, False, False,
                                                          False, False, True]
    assert steady_following(gap, v, vl)[4]  # no acceleration given: not a criterion


def test_bounded_style_keeps_the_gap_at_the_speed_seen():
    est = StyleEstimate(-8.0, 2.2, 30.0, -1.0, 0.05, samples=100, seen_s=10.0,
                        mean_speed_mps=28.0)
    s0, t_gap = bounded_style(est, (0.5, 10.0), (0.3, 3.5))
    assert s0 == 0.5
    assert s0 + t_gap * 28.0 == pytest.approx(est.gap_m(28.0))
    assert est.setting_s(28.0) == pytest.approx(est.gap_m(28.0) / 28.0)
    # before any sample: the prior's mean, clipped
    assert bounded_style(StylePrior().initial(), (0.5, 10.0), (0.3, 3.5)) == (
        0.5, pytest.approx(StylePrior().time_gap_s))


def test_least_squares_style():
    v = np.array([10.0, 20.0, 30.0])
    assert least_squares_style(3.0 + 1.2 * v, v) == (pytest.approx(3.0), pytest.approx(1.2))
    assert all(math.isnan(x) for x in least_squares_style([5.0, 6.0], [10.0, 10.0]))


speeds = st.floats(2.5, 40.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(1.0, 150.0), speeds), min_size=1, max_size=30))
def test_covariance_shrinks_with_every_sample_without_forgetting(samples):
    prior = StylePrior()
    state = prior.initial()
    for gap, v in samples:
        new = update(state, gap, v, prior, dt_s=0.1, elapsed_s=0.1)
        diff = state.cov - new.cov  # P - P' = K S K' is positive semi-definite
        assert np.linalg.eigvalsh(diff).min() >= -1e-9 * np.abs(state.cov).max()
        assert np.trace(new.cov) < np.trace(state.cov)
        assert np.linalg.eigvalsh(new.cov).min() > 0  # and stays a covariance
        state = new


@settings(max_examples=30, deadline=None)
@given(st.floats(0.5, 8.0), st.floats(0.6, 3.0), st.floats(2.5, 20.0), st.floats(5.0, 20.0))
def test_noise_free_samples_at_two_speeds_converge_to_the_truth(s0, t_gap, v1, spread):
    """Noise-free gaps of a driver (s0, T) at two speeds ``spread`` >= 5 m/s apart: the
    posterior mean goes to (s0, T) and the posterior sd to nearly nothing (samples counted as
    independent, correlation_s = dt, so 10,000 are many)."""
    v2 = v1 + spread
    prior = replace(StylePrior(), correlation_s=0.1)
    state = prior.initial()
    for k in range(10000):
        v = v1 if k % 2 else v2
        state = update(state, s0 + t_gap * v, v, prior, dt_s=0.1, elapsed_s=0.1)
    assert state.s0_m == pytest.approx(s0, abs=0.05)
    assert state.time_gap_s == pytest.approx(t_gap, abs=0.005)
    assert state.sd_time_gap_s < 0.05 * prior.sd_time_gap_s


@settings(max_examples=30, deadline=None)
@given(st.floats(30.0, 600.0), st.lists(st.tuples(st.floats(5.0, 80.0), speeds),
                                        min_size=200, max_size=400))
def test_forgetting_keeps_the_covariance_bounded_below(tau, samples):
    """With forgetting every step adds (1 - a^2) P0, so the information can never exceed
    P0^-1 / (1 - a^2) + sum of one step's h h' / R: the covariance stays above the bound
    (and below the prior's). Without forgetting the same samples drive it below that bound."""
    prior = StylePrior(forget_tau_s=tau)
    dt = 0.1
    a2 = math.exp(-2 * dt / tau)
    vmax = max(v for _, v in samples)
    h = np.array([1.0, vmax])
    # the most one sample can add: at the largest speed (R grows with speed less than h h')
    info = np.linalg.inv(prior.cov) / (1 - a2) + np.outer(h, h) / min(
        prior.noise_var_m2(v, dt) for _, v in samples)
    floor = np.linalg.eigvalsh(np.linalg.inv(info)).min()
    state = prior.initial()
    plain = StylePrior().initial()
    for _ in range(10):
        for gap, v in samples:
            state = update(state, gap, v, prior, dt_s=dt, elapsed_s=dt)
            plain = update(plain, gap, v, StylePrior(), dt_s=dt, elapsed_s=dt)
    lo = np.linalg.eigvalsh(state.cov).min()
    assert lo >= floor * (1 - 1e-6)
    assert np.linalg.eigvalsh(prior.cov - state.cov).min() >= -1e-9
    assert np.linalg.eigvalsh(plain.cov).min() < lo


def test_estimate_drive_follows_a_driver_and_knows_how_sure_it_is():
    """A seeded drive: a driver with s0 = 3 m, T = 1.2 s at 8-30 m/s, 10 % noise. The estimate
    ends near the truth and the whole-drive least squares, its sd shrinks over time."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 300.0, 0.1)
    v = 19.0 + 11.0 * np.sin(t / 40.0)
    gap = (3.0 + 1.2 * v) * (1 + 0.1 * rng.standard_normal(len(t)))
    final, traj = estimate_drive(t, gap, v, v + 0.2, StylePrior())
    assert traj.steady.mean() > 0.9
    assert final.s0_m == pytest.approx(3.0, abs=1.5)
    assert final.time_gap_s == pytest.approx(1.2, abs=0.08)
    ls = least_squares_style(gap[traj.steady], v[traj.steady])
    assert final.time_gap_s == pytest.approx(ls[1], abs=0.05)
    assert traj.sd_time_gap_s[-1] < 0.3 * traj.sd_time_gap_s[10]
    assert np.all(np.diff(traj.sd_time_gap_s) <= 1e-12)  # no forgetting: never less sure


def test_plot_convergence_writes_a_figure(tmp_path):
    from safeil_sumo.learn.style_estimator import plot_convergence

    t = np.arange(0.0, 20.0, 0.1)
    v = np.linspace(10.0, 20.0, len(t))
    _, traj = estimate_drive(t, 2.0 + 1.5 * v, v, v, StylePrior())
    plot_convergence(traj, tmp_path / "c.png", hindsight=(2.0, 1.5), title="t")
    assert (tmp_path / "c.png").stat().st_size > 1000
