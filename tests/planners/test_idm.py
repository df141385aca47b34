"""The calibrated IDM baseline: the model (hand-computed), the closed-trajectory simulation, the
calibration recovering known parameters, the planner, its model file and a libsumo run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from safeil_sumo.experiments.leader_probe import probe, straight_lane_features
from safeil_sumo.planners import idm
from safeil_sumo.planners import registry as planner_registry

P = idm.IDMParams(v0_mps=30.0, time_gap_s=1.2, s0_m=2.0, a_max_mps2=1.5, b_mps2=2.0)


def test_free_road_and_equilibrium_hand_computed() -> None:
    # free road (huge gap): a (1 - (v/v0)^4); at v = 15, v0 = 30: 1.5 * (1 - 1/16)
    assert idm.idm_acceleration(15.0, 15.0, 1e9, P) == pytest.approx(1.5 * 15 / 16)
    # at v = v_lead the interaction term is (s0 + v T)^2 / s^2; at the equilibrium gap
    # s_e = s* / sqrt(1 - (v/v0)^4) the acceleration is zero
    v = 20.0
    s_star = 2.0 + v * 1.2
    s_e = s_star / math.sqrt(1 - (v / 30.0) ** 4)
    assert idm.idm_acceleration(v, v, s_e, P) == pytest.approx(0.0, abs=1e-12)
    # closing in: the dynamic term v dv / (2 sqrt(ab)) adds to s*
    dv = 5.0
    s_dyn = 2.0 + v * 1.2 + v * dv / (2 * math.sqrt(3.0))
    expected = 1.5 * (1 - (v / 30) ** 4 - (s_dyn / 40.0) ** 2)
    assert idm.idm_acceleration(v, v - dv, 40.0, P) == pytest.approx(expected)


def test_equilibrium_gap_hand_computed() -> None:
    # s_e = (s0 + v T) / sqrt(1 - (v/v0)^4): at v = 20, v0 = 30: 26 / sqrt(65/81)
    assert idm.equilibrium_gap(20.0, P) == pytest.approx(26.0 / math.sqrt(65.0 / 81.0))
    gaps = idm.equilibrium_gap(np.array([5.0, 15.0, 25.0]), P)
    assert idm.idm_acceleration(np.array([5.0, 15.0, 25.0]), np.array([5.0, 15.0, 25.0]), gaps,
                                P) == pytest.approx(np.zeros(3), abs=1e-12)
    assert idm.equilibrium_gap(30.0, P) == math.inf  # at v0 no gap holds it
    assert idm.equilibrium_gap(35.0, P) == math.inf


def test_params_validation() -> None:
    with pytest.raises(idm.IDMError, match="time_gap_s"):
        idm.IDMParams(time_gap_s=-1.0)
    with pytest.raises(idm.IDMError):
        idm.IDMParams(v0_mps=float("nan"))


def _leader(seed: int, n: int = 900, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A leader with real-looking speed changes: 22-32 m/s, a braking phase and a stop-go."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    v = 27 + 4 * np.sin(2 * np.pi * t / 40 + rng.uniform(0, 6)) - 6 * np.exp(-((t - 50) / 6) ** 2)
    return t, np.clip(v, 0, None)


def test_simulation_stacked_equals_scalar() -> None:
    t, vl = _leader(0)
    gap, v = idm.simulate_follower(t, vl, 25.0, 30.0, P)
    m = idm.Maneuver("m", t, v, gap, vl)
    g2, v2 = idm.simulate_stacked(idm._stacked([m]), P)
    np.testing.assert_allclose(g2[0], gap, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(v2[0], v, rtol=1e-12, atol=1e-9)
    assert (v >= 0).all() and gap.min() > 0


def test_fit_recovers_known_parameters() -> None:
    maneuvers = []
    for k in range(4):
        t, vl = _leader(k)
        gap, v = idm.simulate_follower(t, vl, 24.0 + k, 25.0 + 5 * k, P)
        maneuvers.append(idm.Maneuver(f"m{k}", t, v, gap, vl))
    fit = idm.fit_idm(maneuvers, seed=0)
    assert fit.rmse_gap_m < 0.05
    # the parameters that shape following are identified; v0 only weakly (never free driving)
    assert fit.params.time_gap_s == pytest.approx(1.2, rel=0.05)
    assert fit.params.s0_m == pytest.approx(2.0, abs=0.5)
    assert fit.params.a_max_mps2 == pytest.approx(1.5, rel=0.15)
    assert fit.params.b_mps2 == pytest.approx(2.0, rel=0.25)


def test_planner_shapes_and_leader_response() -> None:
    planner = idm.IDMPlanner(P)
    f = straight_lane_features(np.array([30.0, 30.0]), np.array([20.0, 30.0]),
                               np.array([20.0, 60.0]))
    batch = planner.plan(f)
    assert batch.shape == (2, 3, 2)
    np.testing.assert_allclose(batch[0], planner.plan(f[0]))
    assert batch[0, 2, 0] < batch[1, 2, 0]  # a slow close leader: a shorter plan
    summary, _ = probe(planner)
    assert summary["pass_rate"] < 0.005
    assert summary["gap_monotone_violations"] == 0


def test_model_file_round_trip_and_errors(tmp_path) -> None:
    fit = idm.IDMFit(P, 1.0, 0.5, ("a#0",), 100)
    path = tmp_path / "m.json"
    idm.save_model(path, {"openacc": fit, "ngsim": fit}, default="openacc",
                   per_driver={"openacc/f2": fit})
    assert idm.is_model_file(path)
    planner = planner_registry.load(str(path))
    assert isinstance(planner, idm.IDMPlanner) and planner.params == P
    assert idm.load_planner(path, fit="openacc/f2").params == P
    with pytest.raises(idm.IDMError, match="no fit"):
        idm.load_planner(path, fit="nope")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": idm.FORMAT, "type": "idm", "default": "x",
                               "fits": {"x": {"params": {"v0_mps": 30}}}}))
    with pytest.raises(planner_registry.PolicyError, match="lacks parameter"):
        planner_registry.load(str(bad))
    with pytest.raises(idm.IDMError, match="default fit"):
        idm.save_model(path, {"openacc": fit}, default="ngsim")


def test_shipped_idm_loads() -> None:
    planner = planner_registry.load("idm")
    assert isinstance(planner, idm.IDMPlanner) and planner.name == "idm"


@pytest.mark.sumo
def test_idm_completes_curved500_in_libsumo() -> None:
    from safeil_sumo.roads.catalogue import resolve_net
    from safeil_sumo.roads.road import load_road
    from safeil_sumo.scenarios.safety import safety_scenario
    from safeil_sumo.sim.loop_types import LoopConfig
    from safeil_sumo.sim.runner import run_scenario

    road = load_road(resolve_net("curved500"))
    rollout = run_scenario(safety_scenario(road, 0), planner_registry.load("idm"), LoopConfig())
    assert rollout.summary["completed"], rollout.summary
    assert rollout.summary["flag"] == ""


# ------------------------------------- cases found by mutation testing (docs/mutation_testing.md)


def test_idm_acceleration_floors_and_arrays() -> None:
    # a much faster leader: the dynamic term would make s* < s0; it is floored at s0 = 2 m
    assert idm.idm_acceleration(10.0, 40.0, 50.0, P) == pytest.approx(
        1.5 * (1 - (10 / 30) ** 4 - (2.0 / 50.0) ** 2))
    # a gap of 0 is floored at MIN_GAP_M = 0.1 m: s* = 2 + 12 = 14 m
    assert idm.idm_acceleration(10.0, 10.0, 0.0, P) == pytest.approx(
        1.5 * (1 - (10 / 30) ** 4 - (14.0 / 0.1) ** 2))
    a = idm.idm_acceleration(np.array([15.0, 20.0]), 20.0, np.array([1e9, 40.0]), P)
    assert a.shape == (2,) and a[0] == pytest.approx(1.5 * 15 / 16)
    assert a[1] == pytest.approx(1.5 * (1 - (20 / 30) ** 4 - (26.0 / 40.0) ** 2))


def test_maneuvers_from_rows_groups_and_sorts() -> None:
    import pandas as pd

    rows = pd.DataFrame({"maneuver_id": ["b#0", "a#1", "b#0", "a#1", "a#1"],
                         "time": [1.0, 0.2, 0.0, 0.0, 0.1],
                         "v_x": [11.0, 22.0, 10.0, 20.0, 21.0],
                         "lead_x": [31.0, 42.0, 30.0, 40.0, 41.0],
                         "v_lead": [13.0, 24.0, 12.0, 22.0, 23.0]})
    a, b = idm.maneuvers_from_rows(rows)
    assert (a.maneuver_id, b.maneuver_id) == ("a#1", "b#0")
    np.testing.assert_array_equal(a.times, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(a.v, [20.0, 21.0, 22.0])
    np.testing.assert_array_equal(a.gap, [40.0, 41.0, 42.0])
    np.testing.assert_array_equal(a.v_lead, [22.0, 23.0, 24.0])
    np.testing.assert_array_equal(b.gap, [30.0, 31.0])


def test_fit_needs_maneuvers() -> None:
    with pytest.raises(idm.IDMError, match="^no maneuvers to fit the IDM on$"):
        idm.fit_idm([])


def test_model_file_contents_and_loading_rules(tmp_path) -> None:
    fit = idm.IDMFit(P, 1.25, 0.5, ("a#0", "b#1"), 100)
    other = idm.IDMFit(idm.IDMParams(), 2.0, 1.0, ("c#0",), 7)
    path = tmp_path / "sub" / "dir" / "m.json"  # parent folders are made
    idm.save_model(path, {"openacc": fit, "x": fit}, default="openacc",
                   per_driver={"openacc/f2": other, "x": other}, extra={"note": "hi"})
    doc = json.loads(path.read_text())
    params = {"v0_mps": 30.0, "time_gap_s": 1.2, "s0_m": 2.0, "a_max_mps2": 1.5,
              "b_mps2": 2.0, "delta": 4.0}
    assert doc["fits"]["openacc"] == {"params": params, "rmse_gap_m": 1.25,
                                      "rmse_speed_mps": 0.5, "samples": 100,
                                      "maneuver_ids": ["a#0", "b#1"]}
    assert (doc["format"], doc["type"], doc["default"], doc["horizon_s"], doc["note"]) == \
        ("safeil-idm-1", "idm", "openacc", 5.0, "hi")
    assert doc["per_driver"]["openacc/f2"]["samples"] == 7
    assert path.read_text().endswith("}\n")
    assert sorted(tmp_path.rglob("*")) == [path.parent.parent, path.parent, path]
    assert path.read_text().count("\n") > 20  # one key per line: readable diffs
    planner = idm.load_planner(path, name="calibrated")
    assert (planner.params, planner.name, planner.horizon) == (P, "calibrated", 5.0)
    assert idm.load_planner(path, fit="openacc/f2").params == idm.IDMParams()
    assert idm.load_planner(path, fit="x").params == P  # a source fit wins over a driver's
    doc["horizon_s"] = 4.0
    path.write_text(json.dumps(doc))
    assert idm.load_planner(path).horizon == 4.0
    with pytest.raises(idm.IDMError, match=r"no fit 'nope' \(has \['openacc', 'openacc/f2', "
                                           r"'x'\]\)"):
        idm.load_planner(path, fit="nope")
    # older or hand-written files: no horizon (5 s), no source fits, a fit without parameters
    path.write_text(json.dumps({"format": idm.FORMAT, "type": "idm", "default": "d",
                                "per_driver": {"d": {"params": params}}, "fits_": {}}))
    assert idm.load_planner(path).horizon == 5.0 and idm.load_planner(path).params == P
    path.write_text(json.dumps({"format": idm.FORMAT, "default": "d", "fits": {"d": {}}}))
    with pytest.raises(idm.IDMError, match="fit 'd' lacks parameter 'v0_mps'"):
        idm.load_planner(path)
    # without per-driver fits, a file saves an empty table
    idm.save_model(tmp_path / "plain.json", {"openacc": fit}, default="openacc")
    assert json.loads((tmp_path / "plain.json").read_text())["per_driver"] == {}


def test_model_file_errors_name_the_file(tmp_path) -> None:
    missing = tmp_path / "missing.json"
    with pytest.raises(idm.IDMError, match=f"^{missing}: not a readable IDM model file"):
        idm.load_planner(missing)
    not_json = tmp_path / "x.json"
    not_json.write_text("{nope")
    assert not idm.is_model_file(not_json) and not idm.is_model_file(missing)
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]")
    assert not idm.is_model_file(listed)
    with pytest.raises(idm.IDMError, match=r"not an IDM model file \(format must be "
                                           r"'safeil-idm-1'\)"):
        idm.load_planner(listed)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"type": "idm", "format": "safeil-idm-0"}))
    assert idm.is_model_file(other)
    with pytest.raises(idm.IDMError, match="not an IDM model file"):
        idm.load_planner(other)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": idm.FORMAT, "type": "idm", "default": "x",
                               "fits": {"x": {"params": {"v0_mps": 30}}}}))
    with pytest.raises(idm.IDMError, match=f"^{bad}: fit 'x' lacks parameter 'time_gap_s'$"):
        idm.load_planner(bad)
    with pytest.raises(idm.IDMError, match=r"^default fit 'ngsim' not among \['openacc'\]$"):
        idm.save_model(tmp_path / "m.json", {"openacc": idm.IDMFit(P, 1, 1, (), 1)},
                       default="ngsim")
    assert not (tmp_path / "m.json").exists()


def test_params_vector_round_trip_and_messages() -> None:
    x = P.vector()
    np.testing.assert_array_equal(x, [30.0, 1.2, 2.0, 1.5, 2.0])
    assert idm.IDMParams.from_vector(x) == P
    assert idm.IDMParams.from_vector(x, delta=2.0).delta == 2.0
    assert isinstance(idm.IDMParams(v0_mps=30).v0_mps, float)
    with pytest.raises(idm.IDMError, match=r"^IDM parameter s0_m must be finite and > 0, got "
                                           r"0.0$"):
        idm.IDMParams(s0_m=0.0)


@pytest.mark.parametrize(("vl", "v0", "gap0"), [((20.0, 22.0, 24.0), 25.0, 30.0),
                                                ((40.0, 40.0, 40.0), 10.0, 20.0)])
def test_follower_simulation_two_steps_by_hand(vl, v0, gap0) -> None:
    """Explicit Euler at the log's own (uneven) steps: the acceleration of the state at the
    step's start, speed clipped at 0, the gap from the trapezoid of both speeds; a much faster
    leader makes the dynamic term negative: s* is then s0."""
    t = np.array([0.0, 0.5, 1.25])
    vl = np.array(vl)
    gap, v = idm.simulate_follower(t, vl, v0, gap0, P)
    g, s = gap0, v0
    want_g, want_v = [g], [s]
    for k in (1, 2):
        dt = t[k] - t[k - 1]
        s_star = 2.0 + max(0.0, s * 1.2 + s * (s - vl[k - 1]) / (2 * math.sqrt(1.5 * 2.0)))
        a = 1.5 * (1 - (s / 30.0) ** 4 - (s_star / g) ** 2)
        s_new = max(s + a * dt, 0.0)
        g += 0.5 * (vl[k - 1] + vl[k]) * dt - 0.5 * (s + s_new) * dt
        s = s_new
        want_g.append(g)
        want_v.append(s)
    np.testing.assert_allclose(gap, want_g, rtol=1e-12)
    np.testing.assert_allclose(v, want_v, rtol=1e-12)
    if v0 == 25.0:
        assert v[1] == pytest.approx(25.0 - 0.5 * 6.949, abs=1e-3)  # a = -6.949 m/s^2 first
    else:  # s* = s0 = 2 m: a = 1.5 (1 - (1/3)^4 - (2/20)^2)
        assert v[1] == pytest.approx(10.0 + 0.5 * 1.5 * (1 - 1 / 81 - 0.01), rel=1e-12)
    # a stopped leader close ahead: the follower stops and never reverses
    _, v_stop = idm.simulate_follower(np.arange(0.0, 20.0, 0.1), np.zeros(200), 10.0, 8.0, P)
    assert v_stop.min() == 0.0 and v_stop[-1] == 0.0


def test_fit_rmse_over_maneuvers_of_different_lengths() -> None:
    """The spacing / speed RMSE pools every recorded sample of every maneuver; the padding of
    the shorter one is not counted; the true parameters give zero."""
    ms = []
    for k, n in enumerate((120, 300)):
        t, vl = _leader(k, n=n)
        gap, v = idm.simulate_follower(t, vl, 24.0 + k, 25.0 + 5 * k, P)
        ms.append(idm.Maneuver(f"m{k}", t, v, gap, vl))
    assert idm.evaluate_fit(ms, P) == pytest.approx((0.0, 0.0), abs=1e-9)
    other = idm.IDMParams(v0_mps=30.0, time_gap_s=1.6, s0_m=2.0, a_max_mps2=1.5, b_mps2=2.0)
    each = [idm.evaluate_fit([m], other) for m in ms]
    pooled = idm.evaluate_fit(ms, other)
    for j in (0, 1):
        assert pooled[j] == pytest.approx(
            math.sqrt((120 * each[0][j] ** 2 + 300 * each[1][j] ** 2) / 420), rel=1e-9)
    assert pooled[0] > 1.0


def test_fit_recovers_parameters_from_one_start(monkeypatch) -> None:
    """The default start alone (2 maneuvers of 15 s) finds the generating parameters; the fit
    records what it was fitted on."""
    ms = []
    for k in range(2):
        t, vl = _leader(k, n=150)
        gap, v = idm.simulate_follower(t, vl, 24.0 + k, 25.0 + 5 * k, P)
        ms.append(idm.Maneuver(f"m{k}", t, v, gap, vl))
    fit = idm.fit_idm(ms, seed=0, starts=1)
    assert fit.rmse_gap_m < 1e-6 and fit.rmse_speed_mps < 1e-6
    np.testing.assert_allclose(fit.params.vector(), P.vector(), rtol=1e-6)
    assert (fit.maneuver_ids, fit.samples) == (("m0", "m1"), 300)
    # a second start, seeded, drawn within the bounds: the better of the two is kept, and the
    # same seed gives the same fit
    calls = []
    solve = idm.least_squares

    def counted(fun, x0, **kw):
        calls.append(np.array(x0))
        return solve(fun, x0, **kw)

    monkeypatch.setattr(idm, "least_squares", counted)
    two = idm.fit_idm(ms, seed=3, starts=2)
    assert len(calls) == 2 and np.all((calls[1] >= idm.LOWER) & (calls[1] <= idm.UPPER))
    np.testing.assert_array_equal(calls[0], idm.IDMParams().vector())
    assert two.rmse_gap_m <= fit.rmse_gap_m + 1e-9
    again = idm.fit_idm(ms, seed=3, starts=2)
    np.testing.assert_array_equal(calls[3], calls[1])
    assert again.params == two.params
    idm.fit_idm(ms, seed=4, starts=2)
    assert not np.array_equal(calls[5], calls[1])
    idm.fit_idm(ms, seed=3, starts=1)
    assert len(calls) == 7


def test_equilibrium_gap_at_and_above_the_desired_speed_is_inf_without_warnings() -> None:
    """At v0 the free-road term is 0 and above it negative: no steady following exists, the gap
    is inf, and no division or square-root warning escapes (mutation testing)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gaps = idm.equilibrium_gap(np.array([P.v0_mps, P.v0_mps + 5.0, 20.0]), P)
    assert np.isinf(gaps[0]) and np.isinf(gaps[1])
    assert gaps[2] == pytest.approx(26.0 / math.sqrt(65.0 / 81.0))


def test_maneuvers_from_tuples_by_hand() -> None:
    """Samples grouped by maneuver id (sorted ids), each in time order, speed / leader speed /
    gap from the features' v_x, v_lead, d_lead columns."""
    from safeil_sumo.data.tuples import Tuples

    feats = np.zeros((4, 9))
    feats[:, 6:] = [[20.0, 21.0, 30.0], [10.0, 11.0, 15.0], [22.0, 23.0, 31.0],
                    [12.0, 13.0, 16.0]]
    t = Tuples(feats, np.zeros((4, 3, 2)), np.zeros((4, 2, 2)),
               np.array(["b", "a", "b", "a"]), np.array(["s"] * 4), np.array([0.2, 0.1, 0.1, 0.0]),
               horizon=0.2, rate_hz=10.0)
    a, b = idm.maneuvers_from_tuples(t)
    assert (a.maneuver_id, b.maneuver_id) == ("a", "b")
    assert a.times.tolist() == [0.0, 0.1] and b.times.tolist() == [0.1, 0.2]
    assert a.v.tolist() == [12.0, 10.0] and a.v_lead.tolist() == [13.0, 11.0]
    assert b.gap.tolist() == [31.0, 30.0] and b.v.tolist() == [22.0, 20.0]


def test_baseline_path_sits_beside_the_checkpoint() -> None:
    from pathlib import Path

    assert idm.baseline_path("runs/m/mine.safetensors") == Path("runs/m/mine.idm.json")
