"""The calibrated IDM baseline: the model (hand-computed), the closed-trajectory simulation, the
calibration recovering known parameters, the planner, its model file and a libsumo run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from safeil_sumo import idm, policies
from safeil_sumo.experiments.probe import probe, straight_lane_features

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
    planner = policies.load(str(path))
    assert isinstance(planner, idm.IDMPlanner) and planner.params == P
    assert idm.load_planner(path, fit="openacc/f2").params == P
    with pytest.raises(idm.IDMError, match="no fit"):
        idm.load_planner(path, fit="nope")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": idm.FORMAT, "type": "idm", "default": "x",
                               "fits": {"x": {"params": {"v0_mps": 30}}}}))
    with pytest.raises(policies.PolicyError, match="lacks parameter"):
        policies.load(str(bad))
    with pytest.raises(idm.IDMError, match="default fit"):
        idm.save_model(path, {"openacc": fit}, default="ngsim")


def test_shipped_idm_loads() -> None:
    planner = policies.load("idm")
    assert isinstance(planner, idm.IDMPlanner) and planner.name == "idm"


def test_idm_completes_curved500_in_libsumo() -> None:
    from safeil_sumo.scenarios.catalogue import resolve_net
    from safeil_sumo.scenarios.road import load_road
    from safeil_sumo.scenarios.safety import safety_scenario
    from safeil_sumo.sim.runner import LoopConfig, run_scenario

    road = load_road(resolve_net("curved500"))
    rollout = run_scenario(safety_scenario(road, 0), policies.load("idm"), LoopConfig())
    assert rollout.summary["completed"], rollout.summary
    assert rollout.summary["flag"] == ""
