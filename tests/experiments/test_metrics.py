"""Human-likeness metrics against hand-computed values (no simulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from safeil_sumo.experiments import metrics as hm


def test_series_error_hand_computed():
    human = np.array([0.0, 1.0, 2.0, 3.0])
    policy = np.array([1.0, 1.0, 2.0, 1.0])  # errors 1, 0, 0, -2
    e = hm.series_error(human, policy)
    assert e.rmse == pytest.approx(math.sqrt((1 + 0 + 0 + 4) / 4))
    assert e.max_abs == pytest.approx(2.0)
    assert (e.n, e.n_total) == (4, 4)


def test_series_error_skips_missing_samples_and_counts_them():
    e = hm.series_error(np.array([0.0, 0.0, 0.0]), np.array([3.0, np.nan, np.nan]))
    assert (e.rmse, e.max_abs, e.n, e.n_total) == (3.0, 3.0, 1, 3)
    empty = hm.series_error(np.zeros(2), np.full(2, np.nan))
    assert math.isnan(empty.rmse) and empty.n == 0
    with pytest.raises(ValueError, match="same shape"):
        hm.series_error(np.zeros(2), np.zeros(3))


def test_wasserstein_of_shifted_distribution_is_the_shift():
    rng = np.random.default_rng(0)
    a = rng.normal(size=500)
    d = hm.distribution_distance(a, a + 0.7)
    assert d.wasserstein == pytest.approx(0.7, abs=1e-12)
    assert hm.distribution_distance(a, a).wasserstein == pytest.approx(0.0, abs=1e-12)
    assert hm.distribution_distance(a, a).ks == 0.0


def test_ks_statistic_hand_computed():
    # ECDFs of {1,2,3,4} and {3,4,5,6}: largest gap 0.5 (at x = 2 and at x = 4...)
    d = hm.distribution_distance(np.array([1.0, 2, 3, 4]), np.array([3.0, 4, 5, 6]))
    assert d.ks == pytest.approx(0.5)
    # W1 between two 4-point uniform samples = mean |sorted difference| = 2
    assert d.wasserstein == pytest.approx(2.0)
    # disjoint supports: KS = 1
    assert hm.distribution_distance(np.zeros(3), np.ones(5)).ks == pytest.approx(1.0)


def test_distribution_ignores_nan_and_handles_empty():
    d = hm.distribution_distance(np.array([0.0, np.nan, 1.0]), np.array([0.0, 1.0]))
    assert d.wasserstein == 0.0 and (d.n_human, d.n_policy) == (2, 2)
    assert math.isnan(hm.distribution_distance(np.array([np.nan]), np.ones(2)).ks)


def test_time_headway():
    th = hm.time_headway(np.array([30.0, 10.0, 5.0]), np.array([20.0, 0.1, 0.5]))
    assert th[0] == pytest.approx(1.5)
    assert math.isnan(th[1])  # standstill: undefined
    assert th[2] == pytest.approx(10.0)


def test_sample_at_interpolates_and_marks_outside_and_missing():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    v = np.array([0.0, 10.0, np.nan, np.nan])  # the run ended after t = 1
    out = hm.sample_at(np.array([0.5, 1.0, 1.5, 4.0]), t, v)
    assert out[0] == pytest.approx(5.0)
    assert out[1] == pytest.approx(10.0)
    assert math.isnan(out[2]) and math.isnan(out[3])


def test_leader_drift_zero_for_consistent_recording_and_measures_speed_bias():
    t = np.arange(0.0, 10.01, 0.5)
    s = 25.0 * t  # ego at 25 m/s
    gap = 40.0 + 2.0 * t  # leader at 27 m/s
    assert np.allclose(hm.leader_drift(t, gap, s, np.full(len(t), 27.0)), 0.0)
    # a recorded leader speed 0.3 m/s too high drifts 0.3 m/s x 10 s = 3 m ahead
    drift = hm.leader_drift(t, gap, s, np.full(len(t), 27.3))
    assert drift[-1] == pytest.approx(3.0)
