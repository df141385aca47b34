"""The gap-regulation probe: metrics on hand-built step responses with closed-form rise and
settling times, the humans' steady-following bands on hand-built maneuvers, the step specs, the
table's targets, one real libsumo step response of the IDM, the CLI, and the real human data."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import brentq

from safeil_sumo.experiments import gap_step_responses as gp
from safeil_sumo.gap_probe import main
from safeil_sumo.planners import idm
from safeil_sumo.planners import registry as planner_registry

DT = 0.01  # [s] the closed loop's log step


def first_order(t, t_step, g0, gf, tau):
    """A first-order approach from g0 to gf with time constant tau, starting at t_step."""
    x = np.maximum(t - t_step, 0.0)
    return gf + (g0 - gf) * np.exp(-x / tau)


def second_order(t, t_step, g0, gf, zeta, omega):
    """The underdamped second-order step response from g0 to gf (zeta < 1), from t_step."""
    x = np.maximum(t - t_step, 0.0)
    wd = omega * math.sqrt(1 - zeta**2)
    shape = np.exp(-zeta * omega * x) * (np.cos(wd * x)
                                          + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * x))
    return gf + (g0 - gf) * shape


# ------------------------------------------------------------------------------ pure metrics


def test_first_order_approach_closed_form() -> None:
    t = np.arange(0.0, 200.0 + DT / 2, DT)
    t_step, g0, gf, tau = 10.0, 100.0, 30.0, 8.0
    gap = first_order(t, t_step, g0, gf, tau)
    v = np.full_like(t, 20.0)
    m = gp.response_metrics(t, gap, v, t_step)
    # 10 % -> 90 % of the change: tau ln 9; into gf +- 10 % gf: |g0 - gf| e^(-x/tau) = 0.1 gf
    assert m["rise_time_s"] == pytest.approx(tau * math.log(9.0), abs=1e-3)
    assert m["settling_time_s"] == pytest.approx(tau * math.log(70.0 / 3.0), abs=DT + 1e-9)
    assert m["settled"] is True
    assert m["overshoot_m"] == pytest.approx(0.0, abs=1e-6)
    assert m["final_gap_m"] == pytest.approx(gf, abs=1e-6)
    assert m["eq_time_gap_s"] == pytest.approx(1.5, abs=1e-6)
    assert m["min_time_gap_s"] == pytest.approx(1.5, abs=1e-6)
    assert m["min_gap_m"] == pytest.approx(gf, abs=1e-6) and m["max_gap_m"] == g0
    assert m["drift_m"] == pytest.approx(0.0, abs=1e-6)
    assert m["gap_at_step_m"] == g0 and m["time_gap_at_step_s"] == pytest.approx(5.0)
    assert m["step_time_s"] == t_step


def test_first_order_rising_gap_and_a_step_inside_the_band() -> None:
    t = np.arange(0.0, 120.0 + DT / 2, DT)
    v = np.full_like(t, 25.0)
    rising = gp.response_metrics(t, first_order(t, 0.0, 20.0, 40.0, 5.0), v, 0.0)
    assert rising["rise_time_s"] == pytest.approx(5.0 * math.log(9.0), abs=1e-3)
    # |20 - 40| e^(-x/5) = 4
    assert rising["settling_time_s"] == pytest.approx(5.0 * math.log(5.0), abs=DT + 1e-9)
    # a change smaller than 10 % of the final gap never leaves the band: settled at once;
    # below MIN_CHANGE_M there is no rise time nor overshoot
    small = gp.response_metrics(t, first_order(t, 0.0, 40.5, 40.0, 5.0), v, 0.0)
    assert small["settling_time_s"] == 0.0 and small["settled"] is True
    assert math.isnan(small["rise_time_s"]) and math.isnan(small["overshoot_m"])


def test_second_order_overshoot_rise_and_settling_closed_form() -> None:
    t = np.arange(0.0, 150.0 + DT / 2, DT)
    t_step, g0, gf, zeta, omega = 20.0, 100.0, 30.0, 0.3, 0.5
    gap = second_order(t, t_step, g0, gf, zeta, omega)
    v = np.full_like(t, 20.0)
    m = gp.response_metrics(t, gap, v, t_step)
    damp = math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2))  # the first peak's fraction
    assert m["overshoot_m"] == pytest.approx(70.0 * damp, rel=1e-4)
    assert m["min_gap_m"] == pytest.approx(gf - 70.0 * damp, abs=1e-3)
    assert m["min_time_gap_s"] == pytest.approx((gf - 70.0 * damp) / 20.0, abs=1e-4)

    def y(x):  # the continuous response after the step
        return float(second_order(np.array([t_step + x]), t_step, g0, gf, zeta, omega)[0])

    wd = omega * math.sqrt(1 - zeta**2)
    # 10 % and 90 % of the change are first reached before the first peak (x = pi / wd)
    x10 = brentq(lambda x: (g0 - y(x)) / 70.0 - 0.1, 0.0, math.pi / wd)
    x90 = brentq(lambda x: (g0 - y(x)) / 70.0 - 0.9, 0.0, math.pi / wd)
    assert m["rise_time_s"] == pytest.approx(x90 - x10, abs=1e-3)
    # extrema at k pi / wd deviate 70 damp^k from gf: the last beyond the band (3 m) is k*;
    # the gap enters the band for good on the way from that extremum to the next zero crossing
    k = max(k for k in range(1, 50) if 70.0 * damp**k > 3.0)
    x_zero = brentq(lambda x: y(x) - gf, k * math.pi / wd, (k + 1) * math.pi / wd)
    x_settle = brentq(lambda x: abs(y(x) - gf) - 3.0, k * math.pi / wd, x_zero)
    assert m["settling_time_s"] == pytest.approx(x_settle, abs=DT + 1e-6)
    assert m["settled"] is True


def test_settling_time_on_a_coarse_grid_exactly() -> None:
    """1 s samples, final 10 m, band 10 % ([9, 11] m, edges inside): the gap is out of the band
    up to t = 3 s and in from t = 4 s, so it settles 4 s after a step at 0 (the first sample
    after the last one outside), 3.5 s after a step at 0.5 s; no tolerance (a case found by
    mutation testing: the last sample outside, one sample early, passed a one-sample tolerance)."""
    t = np.arange(11.0)
    y = np.array([20.0, 15.0, 12.0, 11.5, 10.5, 10.0, 9.0, 11.0, 10.0, 10.0, 10.0])
    assert gp.settling_time(t, y, 0.0, 10.0) == 4.0
    assert gp.settling_time(t, y, 0.5, 10.0) == 3.5
    assert gp.settling_time(t, y, 4.0, 10.0) == 0.0  # never out after the step
    assert gp.settling_time(t, y, 0.0, 10.0, band=0.05) == 8.0  # 9 and 11 are out at 5 %
    gone = y.copy()
    gone[5] = math.nan  # a lost sample counts as out
    assert gp.settling_time(t, gone, 0.0, 10.0) == 6.0
    assert math.isnan(gp.settling_time(t, y, 11.0, 10.0))  # no sample after the step
    assert math.isnan(gp.settling_time(t, y, 0.0, math.inf))


def test_rise_and_overshoot_edges_on_a_coarse_grid() -> None:
    """1 s samples, the step at 3 s (cases found by mutation testing: the sample at the step
    belongs to the response, the one before it does not; a change of exactly min_change counts;
    no sample after the step or an infinite final value is no response)."""
    t = np.arange(11.0)
    ramp = np.array([0, 0, 5, 0, 2, 4, 6, 8, 10, 10, 10], float)
    # 10 % between 3 s (0) and 4 s (2): 3.5 s; 90 % between 7 s (8) and 8 s (10): 7.5 s
    assert gp.rise_time(t, ramp, 3.0, 10.0) == pytest.approx(4.0, abs=1e-12)
    unit = ramp / 10.0  # a change of exactly 1 m
    assert gp.rise_time(t, unit, 3.0, 1.0) == pytest.approx(4.0, abs=1e-12)
    assert math.isnan(gp.rise_time(t, unit, 3.0, 0.99))
    assert math.isnan(gp.rise_time(t, ramp, 11.0, 10.0))
    up = np.array([0, 0, 9.5, 0, 9.5, 12, 11, 10, 10, 10, 10], float)
    assert gp.overshoot(t, up, 3.0, 10.0) == 2.0
    assert gp.overshoot(t, np.array([0, 0, 9.5, 0, 1.5, 1, 1, 1, 1, 1, 1], float), 3.0,
                        1.0) == 0.5
    assert math.isnan(gp.overshoot(t, up, 11.0, 10.0))
    assert math.isnan(gp.overshoot(t, up, 3.0, math.inf))
    # settling from a step at 3 s: the sample at 3 s is out (11.5), so 1 s; from 3.5 s: 0
    y = np.array([20.0, 15.0, 12.0, 11.5, 10.5, 10.0, 9.0, 11.0, 10.0, 10.0, 10.0])
    assert gp.settling_time(t, y, 3.0, 10.0) == 1.0
    assert gp.settling_time(t, y, 3.5, 10.0) == 0.0


def test_response_metrics_edges_on_a_coarse_grid() -> None:
    """1 s samples, the step at 5 s: the gap is 40 m until 19 s (100 m at 4 s, before the
    step), then 20 m, opening by 0.1 m/s from 40 s; the ego at 20 m/s."""
    import warnings

    t = np.arange(61.0)
    gap = np.where(t < 20, 40.0, 20.0) + np.where(t >= 40, 0.1 * (t - 40), 0.0)
    gap[4] = 100.0
    v = np.full_like(t, 20.0)
    m = gp.response_metrics(t, gap, v, 5.0, window_s=5.0, band=0.3, hold_s=40.0)
    # the last 5 s: 21.5 .. 22 m, mean 21.75; in the 30 % band from 20 s: 15 s after the step,
    # held for 60 - 5 - 15 = 40 s exactly
    assert m["final_gap_m"] == pytest.approx(21.75, abs=1e-12)
    assert m["drift_m"] == pytest.approx(0.5, abs=1e-12)
    assert m["settling_time_s"] == 15.0 and m["settled"] is True
    assert m["final_speed_mps"] == 20.0 and m["max_gap_m"] == 40.0 and m["min_gap_m"] == 20.0
    assert not gp.response_metrics(t, gap, v, 5.0, window_s=5.0, band=0.3, hold_s=40.5)[
        "settled"]
    assert not gp.response_metrics(t, gap, v, 5.0, window_s=5.0, band=0.3, hold_s=45.0)[
        "settled"]
    # the default band (10 %) and window (15 s): settled only once the ramp's tail is inside
    assert gp.response_metrics(t, gap, v, 5.0)["drift_m"] == pytest.approx(1.5, abs=1e-12)
    # a gap of exactly the radar's range is still seen
    at_range = gp.response_metrics(t, np.full_like(t, gp.RADAR_RANGE_M), v, 5.0)
    assert at_range["beyond_radar"] is False
    # an ego too slow for a time gap all along: NaN, without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        slow = gp.response_metrics(t, gap, np.full_like(t, 0.5), 5.0)
    assert math.isnan(slow["min_time_gap_s"]) and math.isnan(slow["eq_time_gap_s"])


def test_probe_extras_of_a_hand_built_log() -> None:
    """What a probe task keeps: the kind, the response metrics of its log from the step (60 s
    for pull_away), ``settled`` only for a run that ran out its time, and the series at 2 Hz
    (every 5th sample of a 0.1 s log, the 5th first), rounded to mm."""
    from types import SimpleNamespace

    spec = gp.probe_task("idm", "pull_away", 15.0, settle_s=60.0, after_s=90.0)
    t = np.round(np.arange(0.1, 150.0 + 0.05, 0.1), 10)
    gap = first_order(t, 60.0, 15.0, 30.0, 5.0) + 0.0004
    log = pd.DataFrame({"t": t, "gap": gap, "v": np.full_like(t, 15.0),
                        "leader_v": np.where(t < 60.0, 15.0, 18.0)})
    ran = gp.probe_extras(spec, SimpleNamespace(log=log, summary={"end_reason": "timeout"}))
    want = gp.response_metrics(t, gap, log["v"].to_numpy(), 60.0)
    assert ran["kind"] == "pull_away" and ran["step_time_s"] == 60.0 and want["settled"]
    for key, value in want.items():
        assert ran[key] == value or (math.isnan(value) and math.isnan(ran[key])), key
    assert ran["series_t"][:3] == [0.5, 1.0, 1.5] and len(ran["series_t"]) == len(t) // 5
    assert ran["series_gap"][0] == round(gap[4], 3) == 15.0
    assert ran["series_leader_v"][-1] == 18.0 and ran["series_v"] == [15.0] * (len(t) // 5)
    # the same log ended by a collision: the same metrics, but not settled
    hit = gp.probe_extras(spec, SimpleNamespace(log=log, summary={"end_reason": "collision"}))
    assert hit["settled"] is False and hit["settling_time_s"] == ran["settling_time_s"]
    # a log of one row: only the kind; of two rows: metrics and series
    one = gp.probe_extras(spec, SimpleNamespace(log=log.iloc[:1], summary={}))
    assert one == {"kind": "pull_away"}
    two = gp.probe_extras(spec, SimpleNamespace(log=log.iloc[-2:], summary={}))
    assert two["series_t"] == [] and two["min_gap_m"] == pytest.approx(30.0, abs=1e-3)
    # a log of 1 s steps: every row is kept (the stride is never below 1)
    coarse = log.iloc[9::10]
    kept = gp.probe_extras(spec, SimpleNamespace(log=coarse, summary={}))
    assert kept["series_t"] == [round(x, 3) for x in coarse["t"]]


def test_steady_following_and_bands_at_their_edges() -> None:
    """Constant speeds (no acceleration): |dv| below 0.5 m/s is steady, exactly 0.5 is not; a
    gap of 0 is no leader ahead, 0.5 m is one; a speed exactly 3 m/s from the band's centre is
    in the band; the rows say who they are (cases found by mutation testing)."""
    rows = pd.concat([
        _maneuver("a#0", "d1", 25.0, 25.0, 25.0, n=50),
        _maneuver("b#0", "d2", 25.0, 25.5, 25.0, n=50),  # |dv| = 0.5: not steady
        _maneuver("c#0", "d3", 25.0, 25.0, 0.0, n=50),  # no gap: no leader ahead
        _maneuver("d#0", "d4", 22.0, 22.0, 0.5, n=50),  # 3 m/s below 25, a 0.5 m gap
    ], ignore_index=True)
    keep = gp.steady_following(rows)
    assert list(keep.reshape(4, 50).all(axis=1)) == [True, False, False, True]
    assert not keep.reshape(4, 50)[1:3].any()
    # a tighter dv limit passed on: only exact followers
    assert gp.steady_following(rows, max_dv=0.4).reshape(4, 50).all(axis=1).tolist() == [
        True, False, False, True]
    bands = gp.human_time_gap_bands(rows, speeds=(25.0,))
    assert bands.iloc[0][["policy", "kind", "speed_mps", "samples", "maneuvers",
                          "drivers"]].tolist() == ["humans", "steady_following", 25.0, 100, 2, 2]
    strict = gp.human_time_gap_bands(rows, speeds=(25.0,), max_accel=-1.0)
    assert strict.iloc[0]["samples"] == 0
    loose = gp.human_time_gap_bands(rows, speeds=(25.0,), max_dv=1.0)  # passed on: b is steady
    assert loose.iloc[0][["samples", "maneuvers"]].tolist() == [150, 3]
    # a time gap at exactly the lowest defined speed (1 m/s) is defined
    assert gp.time_gap(np.array([10.0]), np.array([1.0]))[0] == 10.0


def test_the_settling_band_is_the_one_asked_for() -> None:
    t = np.arange(61.0)
    gap = np.where(t < 20, 25.0, 20.0)
    v = np.full_like(t, 20.0)
    assert gp.response_metrics(t, gap, v, 5.0, band=0.3)["settling_time_s"] == 0.0
    assert gp.response_metrics(t, gap, v, 5.0)["settling_time_s"] == 15.0


def test_kind_of_every_index_of_a_kind() -> None:
    for kind, base in gp.KIND_BASE.items():
        assert gp.kind_of(base) == kind and gp.kind_of(base + 9999) == kind
    empty = gp.steady_following(pd.DataFrame(columns=["maneuver_id", "time", "v_x", "v_lead"]))
    assert empty.shape == (0,) and empty.dtype == bool


def test_run_step_runs_its_probe_spec_once_checked(monkeypatch) -> None:
    """The glue of one step response: the probe's spec, checked to fit the stretch, run as a
    probe task (the engine replaced by a recorder; the libsumo run is the IDM test's)."""
    ran = []
    monkeypatch.setattr(gp, "run_probe_task", lambda task: ran.append(task) or {"status": "ok"})
    assert gp.run_step("idm", "slow_down", 20.0, seed=4, settle_s=30.0, after_s=50.0) == {
        "status": "ok"}
    assert ran == [gp.probe_task("idm", "slow_down", 20.0, 4, 30.0, 50.0)]
    gp.run_step("bc", "far", 15.0)
    assert ran[-1] == gp.probe_task("bc", "far", 15.0, 0, gp.SETTLE_S, gp.AFTER_STEP_S)
    assert ran[-1].scenario == gp.probe_scenario("far", 15.0) and ran[-1].brake_guard
    with pytest.raises(ValueError):  # 2 hours at 35 m/s do not fit the stretch
        gp.run_step("idm", "pull_away", 35.0, after_s=7200.0)
    assert len(ran) == 2


def test_probe_tasks_are_every_policy_speed_and_kind() -> None:
    got = gp.probe_tasks(["idm", "safeil"], speeds=(15.0, 25.0), kinds=("far", "close"), seed=3)
    want = [gp.probe_task(p, k, v, 3) for p in ("idm", "safeil") for v in (15.0, 25.0)
            for k in ("far", "close")]
    assert got == want and got[0].scenario.master_seed == 3
    assert [t.planner.policy for t in got] == ["idm"] * 4 + ["safeil"] * 4
    assert gp.probe_tasks(["idm"], speeds=(15.0,), kinds=("far",))[0].scenario.master_seed == 0
    assert gp.probe_task("idm", "far", 15.0) == gp.probe_tasks(["idm"], (15.0,), ("far",))[0]


def test_not_settled_drift_and_time_gap_edges() -> None:
    t = np.arange(0.0, 90.0 + DT / 2, DT)
    v = np.full_like(t, 20.0)
    # a gap opening by 0.2 m/s: the drift over the last 15 s is 3 m; the final gap is the mean
    # over those 15 s (66.5 m). The ramp enters 66.5 +- 6.65 m at 49.25 s and stays: by the
    # band alone a slow drift counts as settled; the drift shows it
    ramp = 50.0 + 0.2 * t
    m = gp.response_metrics(t, ramp, v, 0.0)
    assert m["drift_m"] == pytest.approx(3.0, abs=1e-9)
    assert m["final_gap_m"] == pytest.approx(66.5, abs=1e-6)
    assert m["settling_time_s"] == pytest.approx((0.9 * 66.5 - 50.0) / 0.2, abs=DT + 1e-9)
    assert m["settled"] is True
    # a last sample outside the band: no settling time
    jump = np.full_like(t, 30.0)
    jump[-1] = 40.0
    assert math.isnan(gp.settling_time(t, jump, 0.0, 30.0))
    # a response that settles, but too late to hold the band for HOLD_S: not settled
    late = first_order(t, 0.0, 100.0, 30.0, 15.0)
    m_late = gp.response_metrics(t, late, v, 0.0)
    f = m_late["final_gap_m"]  # 30.3 m: the tail still decays; 70 e^(-x/15) = 1.1 f - 30
    assert m_late["settling_time_s"] == pytest.approx(15 * math.log(70 / (1.1 * f - 30)),
                                                      abs=DT + 1e-6)
    assert m_late["settling_time_s"] == pytest.approx(45.7, abs=0.1)
    assert m_late["settled"] is True  # holds the band for 44 s
    m_short = gp.response_metrics(t[:6000], late[:6000], v[:6000], 0.0)  # 60 s: holds 13 s
    assert m_short["settled"] is False
    # a run that ended before its step (e.g. off the road): no response, not settled
    early = gp.response_metrics(t[:3000], ramp[:3000], v[:3000], 60.0)
    assert early["settled"] is False and early["step_time_s"] == 60.0
    assert all(math.isnan(early[k]) for k in ("eq_time_gap_s", "min_time_gap_s", "drift_m"))
    assert set(early) == set(m)
    # the leader beyond the radar's range
    assert not m["beyond_radar"]
    assert gp.response_metrics(t, ramp + 100.0, v, 0.0)["beyond_radar"]
    # time gap: undefined below MIN_SPEED_TIME_GAP
    tg = gp.time_gap(np.array([10.0, 10.0, 10.0]), np.array([20.0, 0.5, 0.0]))
    assert tg[0] == 0.5 and np.isnan(tg[1:]).all()


# ------------------------------------------------------------------------------- the humans


def _maneuver(mid, driver, v, v_lead, gap, n=200, hz=10.0):
    t = np.arange(n) / hz
    return pd.DataFrame({"maneuver_id": mid, "driver": driver, "time": 1000.0 + t,
                         "v_x": v(t) if callable(v) else np.full(n, v),
                         "v_lead": np.full(n, v_lead), "lead_x": np.full(n, gap)})


def test_human_bands_on_hand_built_maneuvers() -> None:
    rows = pd.concat([
        _maneuver("a#0", "d1", 25.0, 25.0, 25.0),  # steady, 1.0 s
        _maneuver("b#0", "d2", 25.0, 25.0, 50.0, n=100),  # steady, 2.0 s
        _maneuver("c#0", "d2", 25.0, 26.0, 10.0),  # |dv| = 1 m/s: not steady
        _maneuver("d#0", "d3", lambda t: 24.0 + 1.0 * t, 25.0, 10.0, n=40),  # 1 m/s^2: no
        _maneuver("e#0", "d3", lambda t: 14.0 + 0.2 * t, 14.5, 30.0, n=50),  # 0.2 m/s^2: yes
    ], ignore_index=True)
    steady = gp.steady_following(rows)
    man, v = rows["maneuver_id"].to_numpy(), rows["v_x"].to_numpy()
    expected = np.isin(man, ["a#0", "b#0"]) | ((man == "e#0") & (np.abs(v - 14.5) < 0.5))
    np.testing.assert_array_equal(steady, expected)
    bands = gp.human_time_gap_bands(rows, speeds=(15.0, 25.0, 35.0)).set_index("speed_mps")
    b25 = bands.loc[25.0]
    assert (b25["samples"], b25["maneuvers"], b25["drivers"]) == (300, 2, 2)
    pooled = np.r_[np.full(200, 1.0), np.full(100, 2.0)]
    for q in gp.HUMAN_QUANTILES:
        assert b25[f"human_p{round(100 * q):02d}_s"] == pytest.approx(np.quantile(pooled, q))
    assert b25["human_p50_s"] == 1.0 and b25["human_p75_s"] == 2.0
    b15 = bands.loc[15.0]  # maneuver e: v 14.0..14.98, steady where |v - 14.5| < 0.5
    sel = expected & (man == "e#0")
    assert b15["samples"] == sel.sum() and b15["drivers"] == 1
    assert b15["human_p50_s"] == pytest.approx(np.median(30.0 / v[sel]))
    assert bands.loc[35.0, "samples"] == 0 and math.isnan(bands.loc[35.0, "human_p50_s"])


# ------------------------------------------------------------------------------ the specs


def test_step_specs() -> None:
    assert [gp.initial_gap_m("close", v) for v in (15, 25, 35)] == [5.0, 15.0, 25.0]
    assert gp.initial_gap_m("far", 25) == 100.0 and gp.initial_gap_m("pull_away", 20) == 30.0
    with pytest.raises(ValueError, match="unknown step kind"):
        gp.initial_gap_m("sideways", 25)
    pull = gp.probe_scenario("pull_away", 25.0)
    from safeil_sumo.scenarios.spec import leader_profile

    prof = leader_profile(pull, 25.0)
    assert prof.speed_at(59.9) == 25.0 and prof.speed_at(61.5) == pytest.approx(26.5)
    assert prof.speed_at(63.0) == 28.0 and prof.speed_at(149.0) == 28.0
    assert pull.max_time_s == gp.SETTLE_S + gp.AFTER_STEP_S and gp.step_time_s(pull) == 60.0
    slow = gp.probe_scenario("slow_down", 15.0)
    assert leader_profile(slow, 15.0).speed_at(100.0) == 12.0
    far = gp.probe_scenario("far", 35.0)
    assert gp.step_time_s(far) == 0.0 and far.max_time_s == gp.AFTER_STEP_S
    assert leader_profile(far, 35.0).speed_at(80.0) == 35.0
    assert [gp.kind_of(gp.probe_scenario(k, 25.0).index) for k in gp.KINDS] == list(gp.KINDS)
    # the leader's distance: gap + car + 60 s at 25 + the 3 s ramp at 26.5 + 87 s at 28
    assert gp.leader_distance_m(pull) == pytest.approx(37.5 + 4.54 + 1500 + 79.5 + 2436,
                                                       abs=0.5)
    gp.check_fits(gp.probe_scenario("pull_away", 40.0))
    with pytest.raises(ValueError, match="beyond the probe's"):
        gp.check_fits(gp.probe_scenario("pull_away", 55.0))


def test_step_spec_edges_by_hand() -> None:
    """Cases found by mutation testing: the speed range and its message, the stretch and task
    index, a slow_down to exactly 0 m/s (allowed), the step time of a braking leader, the
    leader's distance exactly (the 0.1 s grid holds the ramp's kinks) and the fit's edge."""
    from dataclasses import replace

    from safeil_sumo.sim.vehicle import VehicleParams

    car = VehicleParams.length_m
    for bad in (0.0, 100.0, -1.0):
        with pytest.raises(ValueError, match=rf"probe speed must be in \(0, 100\) m/s, got {bad}"):
            gp.probe_scenario("far", bad)
    low = gp.probe_scenario("far", 0.5)
    assert (low.from_km, low.to_km, low.net, low.master_seed) == (1.0, 8.0, "n74", 0)
    assert gp.probe_scenario("close", 15.25).index == 40_000 + 1525
    assert gp.probe_scenario("slow_down", 3.0).brake_to_mps == 0.0
    with pytest.raises(ValueError, match="slow_down at 2.9 m/s would need a negative leader "
                                         "speed: use speeds above 3 m/s"):
        gp.probe_scenario("slow_down", 2.9)
    with pytest.raises(ValueError, match="kinds: pull_away, slow_down, far, close"):
        gp.initial_gap_m("sideways", 25)
    assert gp.step_time_s(gp.probe_scenario("slow_down", 15.0)) == 60.0
    pull = gp.probe_scenario("pull_away", 25.0)
    # 37.5 m + a car + 60 s at 25 + the 3 s ramp at 26.5 on average + 87 s at 28
    assert gp.leader_distance_m(pull) == pytest.approx(37.5 + car + 4015.5, abs=1e-6)
    far = gp.probe_scenario("far", 25.0)
    assert gp.leader_distance_m(replace(far, max_time_s=None)) == 100.0 + car
    wide = replace(far, leader_speed_range_mps=(20.0, 30.0), max_time_s=10.0)
    assert gp.leader_distance_m(wide) == pytest.approx(100.0 + car + 200.0, abs=1e-9)
    # the fit's edge: a need of exactly the 7 km stretch fits; a millimetre more does not
    need = gp.leader_distance_m(pull)
    gp.check_fits(pull, margin_m=7000.0 - need)
    with pytest.raises(ValueError) as err:
        gp.check_fits(pull, margin_m=7000.001 - need)
    assert str(err.value) == (
        f"pull_away at 25 m/s: the leader would drive 7.0 km (with {7000.001 - need:g} m "
        "margin), beyond the probe's 7 km n74 stretch: use lower speeds")
    with pytest.raises(ValueError, match=r"would drive 7.1 km \(with 200 m margin\)"):
        gp.check_fits(replace(pull, max_time_s=pull.max_time_s + 100.0))
    with pytest.raises(ValueError, match=r"would drive 8.1 km"):  # 8,051 m
        gp.check_fits(pull, margin_m=8051.0 - need)


def test_first_crossing_and_window_mean_by_hand() -> None:
    import warnings

    t = np.array([5.0, 6.0, 8.0, 9.0])
    # at the first sample already: its time, not the next one's
    assert gp._first_crossing(t, np.array([0.5, 0.6, 0.9, 1.0]), 0.5) == 5.0
    # the first crossing, interpolated between 6 s and 8 s: 6 + (0.5 - 0.2) / 0.6 * 2 = 7
    assert gp._first_crossing(t, np.array([0.0, 0.2, 0.8, 1.0]), 0.5) == pytest.approx(7.0,
                                                                                      abs=1e-12)
    # reaching the level exactly on a plateau: the plateau's first sample
    assert gp._first_crossing(t, np.array([0.0, 0.5, 0.5, 1.0]), 0.5) == 6.0
    assert math.isnan(gp._first_crossing(t, np.array([0.0, 0.1, 0.2, 0.3]), 0.5))
    # the mean over the last 2 s takes the sample exactly 2 s before the end
    tt = np.arange(5.0)
    assert gp.window_mean(tt, np.array([0.0, 0.0, 10.0, 20.0, 30.0]), 2.0) == 20.0
    assert gp.window_mean(tt, np.array([0.0, 0.0, 10.0, math.nan, 30.0]), 2.0) == 20.0
    with warnings.catch_warnings():  # nothing finite in the window: NaN, without a warning
        warnings.simplefilter("error")
        assert math.isnan(gp.window_mean(tt, np.array([0.0, 0.0] + [math.nan] * 3), 2.0))


def _record(**over):
    base = {"policy": "p", "index": gp.KIND_BASE["far"] + 2500, "leader_speed_low_mps": 25.0,
            "eq_time_gap_s": 1.0, "min_time_gap_s": 0.9, "settling_time_s": 20.0,
            "settled": True, "time_gap_at_step_s": 4.0, "end_reason": "timeout",
            "status": "ok", "resp_collision": False, "resp_min_time_gap_s": 0.9}
    return base | over


def test_table_targets() -> None:
    records = pd.DataFrame([
        _record(),
        _record(min_time_gap_s=0.79),  # below 0.8 s
        _record(settling_time_s=46.0),  # too slow
        _record(settled=False),
        _record(eq_time_gap_s=1.5),  # outside the humans' IQR
        # close: started at 0.6 s and never went lower: not blamed for its start
        _record(index=gp.KIND_BASE["close"] + 2500, min_time_gap_s=0.6, time_gap_at_step_s=0.6),
        _record(index=gp.KIND_BASE["close"] + 2500, min_time_gap_s=0.55, time_gap_at_step_s=0.6),
        _record(end_reason="collision"),
    ])
    humans = pd.DataFrame([{"policy": "humans", "kind": "steady_following", "speed_mps": 25.0,
                            "samples": 10, "maneuvers": 2, "drivers": 2, "human_p05_s": 0.85,
                            "human_p25_s": 0.9, "human_p50_s": 1.1, "human_p75_s": 1.3}])
    t = gp.table(records, humans)
    runs = t[t["policy"] == "p"]
    assert list(runs["kind"]) == ["far"] * 5 + ["close"] * 2 + ["far"]
    # the floor is max(0.8, p05 = 0.85)
    assert list(runs["target_min_time_gap"]) == [True, False, True, True, True, True, False,
                                                 True]
    assert list(runs["target_settling"]) == [True, True, False, False, True, True, True, True]
    assert list(runs["target_eq_in_human_iqr"]) == [True, True, True, True, False, True, True,
                                                    True]
    assert list(runs["collision"]) == [False] * 7 + [True]
    assert t.iloc[-1]["policy"] == "humans" and t.iloc[-1]["drivers"] == 2
    # without the humans: the 0.8 s floor alone, and no IQR verdict
    bare = gp.table(records)
    assert list(bare["target_min_time_gap"])[:2] == [True, False]
    assert bare["target_eq_in_human_iqr"].isna().all()


def test_table_columns_and_edges_by_hand() -> None:
    """Cases found by mutation testing: a collision seen by the response metrics alone, the
    whole run's minimum time gap, JSON's null TTC of a run that ran (inf) against a run that
    failed (NaN), a minimum exactly at the floor, a settling of exactly 45 s, an unknown
    'settled', integer speeds, and the humans' rows appended with a fresh index."""
    records = pd.DataFrame([
        _record(leader_speed_low_mps=25, resp_collision=True, resp_min_time_gap_s=0.7,
                min_ttc_s=None),
        _record(leader_speed_low_mps=25, resp_collision=None, min_time_gap_s=0.85,
                settling_time_s=45.0, min_ttc_s=2.0),
        _record(leader_speed_low_mps=25, status="error", settled=None, min_ttc_s=None,
                end_reason=""),
    ])
    humans = pd.DataFrame([{"policy": "humans", "kind": "steady_following", "speed_mps": 25.0,
                            "samples": 10, "maneuvers": 2, "drivers": 2, "human_p05_s": 0.85,
                            "human_p25_s": 0.9, "human_p50_s": 1.1, "human_p75_s": 1.3}])
    t = gp.table(records, humans)
    assert list(t.index) == [0, 1, 2, 3] and t["speed_mps"].dtype == float
    assert list(t["collision"][:3]) == [True, False, False]
    assert t["run_min_time_gap_s"][0] == 0.7 and t["run_min_time_gap_s"][1] == 0.9
    assert t["min_ttc_s"][0] == math.inf and t["min_ttc_s"][1] == 2.0
    assert math.isnan(t["min_ttc_s"][2])
    assert list(t["target_min_time_gap"][:2]) == [True, True]  # 0.85 s: exactly the floor
    assert list(t["target_settling"][:3]) == [True, True, False]
    assert str(t["drivers"].dtype) == "Int64" and t["drivers"][3] == 2
    assert str(t["target_eq_in_human_iqr"].dtype) == "boolean"  # True / False / <NA>
    # records without the response's collision and minimum columns, and without a metric
    bare = pd.DataFrame([_record()]).drop(columns=["resp_collision", "resp_min_time_gap_s"])
    b = gp.table(bare)
    assert not b["collision"][0] and math.isnan(b["run_min_time_gap_s"][0])
    assert math.isnan(b["overshoot_m"][0])
    assert gp.table(pd.DataFrame([_record(end_reason="collision")]))["collision"][0]


# ------------------------------------------------------------------------ real closed loops


@pytest.mark.sumo
def test_idm_step_response_in_libsumo() -> None:
    # the ego starts 10 m closer than a 1 s time gap allows (5 m at 15 m/s) behind a leader at
    # 15 m/s; the calibrated IDM must open the gap to its own equilibrium (s0 + v T) /
    # sqrt(1 - (v/v0)^4), computed from the model file, and settle there
    r = gp.run_step("idm", "close", 15.0, after_s=30.0)
    assert r["status"] == "ok" and r["end_reason"] == "timeout" and r["flag"] == ""
    assert r["kind"] == "close" and r["gap_at_step_m"] == pytest.approx(5.0, abs=1e-3)
    params = planner_registry.load("idm").params
    v = r["final_speed_mps"]
    assert v == pytest.approx(15.0, abs=0.1)
    expected = float(idm.equilibrium_gap(v, params)) / v  # ~1.0 s at 15 m/s
    assert r["eq_time_gap_s"] == pytest.approx(expected, rel=0.03)
    assert r["final_gap_m"] > 12.0  # the gap opened from 5 m
    # it settled into the band within 20 s, opening the gap without overshooting by more than
    # the band, and never closed in below its start
    assert 2.0 < r["settling_time_s"] < 20.0
    assert 2.0 < r["rise_time_s"] < 20.0
    assert r["overshoot_m"] < 0.1 * r["final_gap_m"]
    assert r["min_gap_m"] == pytest.approx(5.0, abs=0.05)
    assert abs(r["drift_m"]) < 1.0
    assert len(r["series_t"]) == 60 and r["series_t"][-1] == pytest.approx(30.0)


@pytest.mark.sumo
def test_cli_writes_the_results(tmp_path, capsys) -> None:
    out = tmp_path / "probe"
    code = main(["--policy", "analytic", "--speeds-mps", "25", "--kinds", "close",
                 "--no-humans", "--no-progress", "--out", str(out)])
    assert code == 0
    for name in ("gap_probe.csv", "gap_probe.png", "series.parquet", "manifest.json"):
        assert (out / name).is_file(), name
    table = pd.read_csv(out / "gap_probe.csv")
    assert len(table) == 1 and table.loc[0, "kind"] == "close"
    # the analytic planner's desired gap is 5 m + 1.5 s v: 1.7 s at 25 m/s
    assert table.loc[0, "eq_time_gap_s"] == pytest.approx(1.7, abs=0.05)
    assert bool(table.loc[0, "settled"])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["speeds_mps"] == [25.0] and manifest["git_commit"]
    assert "results:" in capsys.readouterr().out
    # a rerun resumes: nothing runs again, the same table
    assert main(["--policy", "analytic", "--speeds-mps", "25", "--kinds", "close",
                 "--no-humans", "--no-progress", "--out", str(out)]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(out / "gap_probe.csv"), table)


@pytest.mark.parametrize("args, message", [
    (["--policy", "nosuchpolicy"], "unknown policy"),
    (["--speeds-mps", "55", "--kinds", "pull_away"], "beyond the probe's"),
])
def test_cli_bad_input_one_line(tmp_path, capsys, args, message) -> None:
    code = main([*args, "--no-humans", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and "Traceback" not in err and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_human_bands_from_the_real_data() -> None:
    from fixtures_data import NGSIM_PAIRS, OPENACC_DIR, SHARED, require_file

    require_file(NGSIM_PAIRS)
    require_file(OPENACC_DIR / "JRC-VC_280219_part2.csv.gz")
    bands = gp.human_time_gap_bands(gp.load_human_rows(SHARED)).set_index("speed_mps")
    for v, b in bands.iterrows():
        assert b["samples"] > 100, v
        q = [b[f"human_p{round(100 * q):02d}_s"] for q in gp.HUMAN_QUANTILES]
        assert q == sorted(q) and q[0] > 0.1 and q[-1] < 5.0
    # 15 m/s: NGSIM's congested I-80 (many followers); 35 m/s: OpenACC's four motorway drivers
    assert bands.loc[15.0, "drivers"] >= 10 and bands.loc[35.0, "drivers"] == 4


@pytest.mark.sumo
@pytest.mark.parametrize("kind", ["far", "pull_away"])
def test_shipped_safeil_regulates_the_gap_at_25_mps(kind):
    """Real libsumo, the shipped default at its default time-gap setting (docs/human_likeness.md:
    settles in 17.3 s from 100 m behind, 1.4 s after the leader pulls away; never below 1.5 s):
    it settles within 45 s, never below a 0.8 s time gap, at a time gap within 15 % of its
    setting (the open-loop model drifted to 0.58 s after 'far' and took 73 s; the first
    closed-loop model settled at 1.16 s for a 1.61 s setting)."""
    pytest.importorskip("libsumo")
    setting = planner_registry.load("safeil").style["time_gap_s"]
    rec = gp.run_step("safeil", kind, 25.0)
    assert rec["status"] == "ok" and rec["end_reason"] != "collision" and not rec["flag"]
    assert rec["settled"] and rec["settling_time_s"] < 45.0
    assert rec["min_time_gap_s"] >= 0.8
    assert abs(rec["eq_time_gap_s"] - setting) <= 0.15 * setting
