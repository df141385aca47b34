"""The synthetic driver (pure, no SUMO) and a short real-libsumo recording on n74."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.data import synthetic as syn
from safeil_sumo.data.schema import load_drive, save_drive

DT = 0.1


def follow(params: syn.DriverParams, leader_speed, t_end: float, v0: float, gap0: float,
           seed: int = 0) -> dict[str, np.ndarray]:
    """Drive a SyntheticDriver behind a scripted leader in lane 0 (straight road)."""
    drv = syn.SyntheticDriver(params, np.random.default_rng(seed), dt=DT)
    n = round(t_end / DT)
    x_f, v, x_l = 0.0, v0, gap0
    out = {k: np.zeros(n) for k in ("t", "gap", "v", "a", "lat")}
    for k in range(n):
        vl = leader_speed(k * DT)
        lanes = (syn.LaneGaps(x_l - x_f, vl), syn.LaneGaps())
        cmd = drv.step(syn.Observation(v, lanes))
        out["t"][k], out["gap"][k], out["v"][k], out["a"][k] = k * DT, x_l - x_f, v, cmd.accel
        out["lat"][k] = cmd.lateral_m
        v_new = max(v + cmd.accel * DT, 0.0)
        x_f += 0.5 * (v + v_new) * DT
        v = v_new
        x_l += vl * DT
    return out


def quiet(**kw) -> syn.DriverParams:
    return replace(syn.DriverParams(), **kw).without_noise()


def test_reaction_delay_shifts_the_response():
    def brake(t):  # leader cruises, then slows at 1.5 m/s^2 from t = 20 s to 15 m/s
        return 25.0 if t < 20.0 else max(25.0 - 1.5 * (t - 20.0), 15.0)

    onset = {}
    for tau in (0.0, 1.0):
        p = quiet(desired_speed_mps=40.0, reaction_time_s=tau, reflex_ttc_s=0.0)
        gap0 = syn.idm_equilibrium_gap(25.0, p)
        r = follow(p, brake, 40.0, 25.0, gap0)
        onset[tau] = r["t"][np.argmax((r["t"] > 20.0) & (r["a"] < -0.3))]
    assert onset[1.0] - onset[0.0] == pytest.approx(1.0, abs=0.15)


def test_steady_state_time_gap_is_the_parameter():
    p = quiet(desired_speed_mps=80.0, time_headway_s=1.4, min_gap_m=0.0, reaction_time_s=0.5)
    r = follow(p, lambda t: 20.0, 300.0, 20.0, 60.0)
    time_gap = r["gap"][-1] / r["v"][-1]
    assert r["v"][-1] == pytest.approx(20.0, abs=0.01)
    assert time_gap == pytest.approx(1.4, rel=0.02)
    assert r["gap"][-1] == pytest.approx(syn.idm_equilibrium_gap(20.0, p), rel=1e-3)


def test_lateral_wander_std_and_correlation_time():
    p = replace(syn.DriverParams(), wander_std_m=0.3, wander_tau_s=5.0, lane_changes=False)
    r = follow(p, lambda t: 30.0, 4000.0, 30.0, 200.0, seed=3)
    y = r["lat"]
    assert np.std(y) == pytest.approx(0.3, rel=0.1)
    lag = int(5.0 / DT)
    rho = np.corrcoef(y[:-lag], y[lag:])[0, 1]
    assert rho == pytest.approx(math.exp(-1.0), abs=0.1)


def test_curve_cutting_moves_towards_the_inside():
    p = quiet(curve_cut_m2=280.0)
    drv = syn.SyntheticDriver(p, np.random.default_rng(0), dt=DT)
    free = (syn.LaneGaps(), syn.LaneGaps())
    left = drv.step(syn.Observation(30.0, free, kappa_ahead=1.0 / 800.0)).lateral_m
    right = drv.step(syn.Observation(30.0, free, kappa_ahead=-1.0 / 800.0)).lateral_m
    assert left == pytest.approx(0.35) and right == pytest.approx(-0.35)


def test_overtakes_a_slow_leader_and_not_when_disabled():
    p = replace(syn.DriverParams(), desired_speed_mps=33.0)
    r = follow(p, lambda t: 22.0, 60.0, 22.0, 40.0, seed=1)
    assert r["lat"].max() > 3.0  # moved over to the left lane (3.5 m)
    r0 = follow(replace(p, lane_changes=False), lambda t: 22.0, 60.0, 22.0, 40.0, seed=1)
    assert np.abs(r0["lat"]).max() < 1.5


def test_vectorised_calibration_model_matches_the_driver():
    p = quiet(reaction_time_s=0.35, reflex_ttc_s=0.0)

    def lead(t):
        return 25.0 + 3.0 * math.sin(0.2 * t)

    r = follow(p, lead, 60.0, 25.0, 30.0)
    t = r["t"]
    speeds = np.array([lead(tk) for tk in t])
    leader_pos = 30.0 + np.concatenate([[0.0], np.cumsum(speeds[:-1] * DT)])
    col = [np.array([getattr(p, k)]) for k in (
        "desired_speed_mps", "time_headway_s", "min_gap_m", "max_accel_mps2",
        "comfort_decel_mps2", "reaction_time_s")]
    gap, v = syn.simulate_follower(leader_pos, speeds, 25.0, DT, *col)
    np.testing.assert_allclose(v[:, 0], r["v"], atol=1e-9)
    np.testing.assert_allclose(gap[:, 0], r["gap"], atol=1e-9)


def test_sampled_drivers_are_seeded_and_plausible():
    a = syn.sample_driver(np.random.default_rng([0, 1]))
    b = syn.sample_driver(np.random.default_rng([0, 1]))
    assert a == b
    for i in range(20):
        d = syn.sample_driver(np.random.default_rng([0, i]))
        assert 29.0 <= d.desired_speed_mps <= 37.0
        assert 0.2 < d.time_headway_s < 3.5 and d.wander_std_m > 0


def test_params_validate():
    with pytest.raises(ValueError):
        syn.DriverParams(time_headway_s=0.0)
    with pytest.raises(ValueError):
        syn.DriverParams(wander_std_m=-0.1)


class _ArcRoad:
    """A road of constant curvature ``kappa`` [1/m], heading 0 at s = 0 (the two methods the
    recorder's kinematic step reads)."""

    def __init__(self, kappa: float) -> None:
        self.kappa = kappa

    def kappa_at(self, s: float) -> float:
        return self.kappa

    def heading_at(self, s: float) -> float:
        return self.kappa * s


def test_recorder_kinematic_step_by_hand():
    """Speed by the acceleration (never below 0), distance by the mean speed, the arc length of
    the reference line stretched by 1 / (1 - kappa d) for an offset lane, the new offset from
    the right lane's centre and the yaw = road heading + the angle of the lateral move."""
    from safeil_sumo.data.recorder import kinematic_step
    from safeil_sumo.roads.n74 import lane_centre_offset

    right = lane_centre_offset(0)
    s, d, v, yaw = kinematic_step(_ArcRoad(0.0), 100.0, right, 20.0, 1.0, 0.5, DT)
    assert v == pytest.approx(20.1) and s == pytest.approx(100.0 + 2.005)
    assert d == pytest.approx(right + 0.5) and yaw == pytest.approx(math.atan2(0.5, 2.005))
    # in a left bend, right of the reference line (outside): less reference arc than driven
    s, _, _, yaw = kinematic_step(_ArcRoad(0.01), 0.0, right, 20.0, 0.0, 0.0, DT)
    assert s == pytest.approx(2.0 / (1.0 - 0.01 * right))
    assert yaw == pytest.approx(0.01 * s)
    # braking to a stop: the speed stays 0, the lateral move keeps a finite angle
    s, _, v, yaw = kinematic_step(_ArcRoad(0.0), 5.0, right, 0.5, -10.0, 0.2, DT)
    assert v == 0.0 and s == pytest.approx(5.0 + 0.025)
    assert yaw == pytest.approx(math.atan2(0.2, 0.025))


# ------------------------------------------------------------------ real libsumo recording

@pytest.fixture(scope="module")
def recordings():
    pytest.importorskip("libsumo")
    from safeil_sumo.data.recorder import RecordingConfig, record_drive

    params = syn.sample_driver(np.random.default_rng([7, 0]))
    cfg = RecordingConfig(seed=7, recording_id="test_n74", duration_s=60.0)
    return record_drive(params, cfg), record_drive(params, cfg)


@pytest.mark.sumo
def test_recording_validates_against_the_schema(recordings, tmp_path):
    df, _ = recordings
    path = tmp_path / "drive.parquet"
    save_drive(df, path)
    back = load_drive(path)
    assert len(back) == 600 and back["time"].iloc[1] == pytest.approx(0.1)
    assert (back["left_c0"] > 0).all() and (back["right_c0"] < 0).all()
    assert set(back["lane_index"].unique()) <= {0.0, 1.0}


@pytest.mark.sumo
def test_recording_is_deterministic(recordings):
    a, b = recordings
    pd.testing.assert_frame_equal(a, b)


@pytest.mark.sumo
def test_recording_contains_leader_samples(recordings):
    df, _ = recordings
    lead = df["lead_x"].notna()
    assert lead.sum() > 50
    assert (df.loc[lead, "lead_x"] > 0).all() and (df.loc[lead, "lead_x"] <= 150.0).all()
    assert df.attrs["recording_stats"]["collision_steps"] == 0
