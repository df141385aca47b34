"""A driver's style (preferred time gap) as a planner input: estimation, model, checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from safeil_sumo.learn.checkpoint import CheckpointError, load_model, save_checkpoint
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.learn.model import PlannerMLP, with_style_input
from safeil_sumo.learn.style import (
    SETTING_RANGE_S,
    STANDSTILL_RANGE_M,
    TIME_GAP_RANGE_S,
    TimeGapPrior,
    adapted_time_gap,
    clip_time_gap,
    estimate_time_gap,
    maneuver_time_gaps,
    scheduled_time_gap,
    training_time_gaps,
)

STATE = np.array([1.75, 0.0, 0.0, -1.75, 0.0, 0.0, 25.0, 24.0, 40.0])


def test_time_gap_is_the_median_over_following_samples():
    gap = np.array([20.0, 30.0, 45.0, 2.0, 300.0, np.nan])
    v = np.array([20.0, 20.0, 30.0, 1.0, 20.0, 20.0])
    # kept: 1.0, 1.5, 1.5 s (2 m at 1 m/s is below the minimum speed, 15 s is no following,
    # NaN is no sample)
    assert estimate_time_gap(gap, v) == pytest.approx(1.5)
    assert np.isnan(estimate_time_gap(np.array([3.0]), np.array([2.0])))


def test_adapted_time_gap_weighs_the_seen_seconds_against_the_population():
    """By hand: equal spreads (0.5) and 10 s of following = 1 + 10/10 = 2 observations, so the
    driver's own median gets 2/0.25 / (2/0.25 + 1/0.25) = 2/3 of the weight in log time gap."""
    prior = TimeGapPrior(median_s=1.0, between_log_sd=0.5, within_log_sd=0.5, correlation_s=10.0)
    assert prior.weight(0.0) == 0.0
    assert prior.weight(10.0) == pytest.approx(2.0 / 3.0)
    assert prior.weight(1e6) == pytest.approx(1.0, abs=1e-4)
    assert prior.weight(5.0) < prior.weight(10.0) < prior.weight(60.0)
    v = np.full(100, 20.0)  # 100 samples 0.1 s apart: 10 s at 2 s
    assert adapted_time_gap(np.full(100, 40.0), v, 0.1, prior) == pytest.approx(2.0 ** (2 / 3))
    # samples below the minimum speed or too far back are not following: not seen, not counted
    slow = np.concatenate([np.full(100, 40.0), np.full(300, 3.0)])
    slow_v = np.concatenate([v, np.full(300, 2.0)])
    assert adapted_time_gap(slow, slow_v, 0.1, prior) == pytest.approx(2.0 ** (2 / 3))
    far = np.concatenate([np.full(100, 40.0), np.full(300, 200.0)])
    assert adapted_time_gap(far, np.full(400, 20.0), 0.1, prior) == pytest.approx(2.0 ** (2 / 3))
    # nothing seen: the population's median
    assert adapted_time_gap(np.array([3.0]), np.array([2.0]), 0.1, prior) == 1.0
    assert adapted_time_gap(np.array([]), np.array([]), 0.1, prior) == 1.0


def test_time_gap_per_maneuver_with_fallback():
    gap = np.array([20.0, 40.0, 60.0, 3.0])
    v = np.array([20.0, 20.0, 20.0, 2.0])
    ids = np.array(["a", "a", "b", "c"])
    np.testing.assert_allclose(maneuver_time_gaps(gap, v, ids, fallback_s=1.4),
                               [1.5, 1.5, 3.0, 1.4])


def test_training_time_gaps_per_training_maneuver_in_order_of_appearance():
    """Only training maneuvers with following samples: a held-out maneuver ("h") and one that
    never follows above the minimum speed ("q") have no estimate."""
    gap = np.array([45.0, 10.0, 20.0, 30.0, 3.0, 40.0, 20.0])
    v = np.array([30.0, 10.0, 20.0, 20.0, 2.0, 20.0, 20.0])
    ids = np.array(["b", "h", "a", "a", "q", "a", "b"])
    est = training_time_gaps(gap, v, ids, {"a", "b", "q"})
    # b: 45/30 = 1.5 and 20/20 = 1.0 -> 1.25; a: 1.0, 1.5, 2.0 -> 1.5
    assert list(est) == ["b", "a"]
    assert est["b"] == pytest.approx(1.25) and est["a"] == pytest.approx(1.5)


def test_settings_are_clipped_to_the_iso_floor_and_the_trained_range():
    lo, hi = SETTING_RANGE_S
    assert lo == 0.8  # ISO 15622's smallest selectable ACC time gap
    assert TIME_GAP_RANGE_S[0] <= lo and hi <= TIME_GAP_RANGE_S[1]  # settings were trained
    assert clip_time_gap(0.1) == lo and clip_time_gap(9.0) == hi and clip_time_gap(1.7) == 1.7


def _style_model(seed: int = 0) -> PlannerMLP:
    torch.manual_seed(seed)
    base = PlannerMLP(output_mode="residual")
    with torch.no_grad():
        for p in base.net.parameters():
            p.normal_(0.0, 0.3)
    return base


def test_a_new_style_input_changes_nothing_until_trained():
    base = _style_model()
    styled = with_style_input(base, 1.5, 0.5)
    f9 = torch.as_tensor(STATE[None], dtype=torch.float32)
    for tg in (0.8, 1.5, 3.0):
        f10 = torch.cat([f9, torch.tensor([[tg]])], dim=1)
        torch.testing.assert_close(styled(f10), base(f9))
    assert styled.architecture["n_features"] == 10
    assert styled.architecture["style_names"] == ["time_gap_s"]
    with pytest.raises(ValueError, match="already"):
        with_style_input(styled, 1.5, 0.5)


def test_numpy_policy_folds_the_style_into_the_first_layer(tmp_path):
    styled = with_style_input(_style_model(), 1.5, 0.5)
    with torch.no_grad():
        styled.net[0].weight[:, 9].normal_(0.0, 0.5)
    save_checkpoint(tmp_path / "m", styled, name="styled", horizon=5.0,
                    style_default={"time_gap_s": 1.3})
    policy = load_policy(tmp_path / "m")
    assert policy.style == {"time_gap_s": 1.3}

    def torch_plan(tg: float) -> np.ndarray:
        f10 = torch.as_tensor(np.r_[STATE, tg][None], dtype=torch.float32)
        return styled(f10).detach().numpy()[0]

    np.testing.assert_allclose(policy.plan(STATE), torch_plan(1.3), atol=1e-4)
    policy.set_style(time_gap_s=2.6)
    np.testing.assert_allclose(policy.plan(STATE), torch_plan(2.6), atol=1e-4)
    np.testing.assert_allclose(policy.plan(np.stack([STATE, STATE]))[1], torch_plan(2.6),
                               atol=1e-4)
    assert np.abs(torch_plan(2.6) - torch_plan(1.3)).max() > 1e-2  # the input matters
    model, meta = load_model(tmp_path / "m")
    assert model.n_features == 10 and meta["feature_names"][-1] == "time_gap_s"


def test_scheduled_time_gap_by_hand():
    """``T + s0 / v`` inside the setting range; below 1 m/s the speed is taken as 1 m/s."""
    assert float(scheduled_time_gap(1.2, 8.0, 20.0)) == pytest.approx(1.6)
    assert float(scheduled_time_gap(2.0, -15.0, 30.0)) == pytest.approx(1.5)
    assert float(scheduled_time_gap(1.2, 8.0, 4.0)) == pytest.approx(3.2)
    assert float(scheduled_time_gap(1.2, 8.0, 2.0)) == SETTING_RANGE_S[1]  # 5.2 s, clipped
    assert float(scheduled_time_gap(1.0, -10.0, 20.0)) == SETTING_RANGE_S[0]  # 0.5 s, clipped
    assert float(scheduled_time_gap(1.0, 1.0, 0.0)) == pytest.approx(2.0)  # at 1 m/s
    np.testing.assert_allclose(scheduled_time_gap(1.2, 8.0, np.array([10.0, 40.0])),
                               [2.0, 1.4])


def test_a_standstill_distance_schedules_the_setting_by_the_ego_speed(tmp_path):
    """With ``standstill_m`` every plan, single or batched, is the plan at the setting
    ``T + s0 / v`` of its own ego speed; the certificate's folded layers are refused."""
    styled = with_style_input(_style_model(), 1.5, 0.5)
    with torch.no_grad():
        styled.net[0].weight[:, 9].normal_(0.0, 0.5)
    save_checkpoint(tmp_path / "m", styled, name="styled", horizon=5.0)
    policy, fixed = load_policy(tmp_path / "m"), load_policy(tmp_path / "m")
    policy.set_style(time_gap_s=1.2, standstill_m=8.0)
    assert policy.style == {"time_gap_s": 1.2, "standstill_m": 8.0}
    states = np.repeat(STATE[None], 3, axis=0)
    states[:, 6] = [10.0, 20.0, 40.0]  # settings 2.0, 1.6, 1.4 s
    batch = policy.plan(states)
    for state, row, setting in zip(states, batch, (2.0, 1.6, 1.4), strict=True):
        fixed.set_style(time_gap_s=setting)
        np.testing.assert_allclose(policy.plan(state.copy()), fixed.plan(state), atol=1e-12)
        np.testing.assert_allclose(row, fixed.plan(state), atol=1e-12)
    assert np.abs(batch[0] - batch[2]).max() > 1e-3  # the setting matters
    with pytest.raises(ValueError, match="style_input"):
        policy.affine_layers()
    assert len(policy.affine_layers(style_input=True)[0][0][0]) == 10
    policy.set_style(time_gap_s=2.6, standstill_m=0.0)  # back to one number, clipped as before
    fixed.set_style(time_gap_s=2.6)
    np.testing.assert_array_equal(policy.plan(STATE), fixed.plan(STATE))
    assert policy.style == {"time_gap_s": 2.6}
    with pytest.raises(ValueError, match="standstill_m must be in"):
        policy.set_style(time_gap_s=1.2, standstill_m=40.0)
    with pytest.raises(ValueError, match="time_gap_s must be in"):
        policy.set_style(time_gap_s=-1.0, standstill_m=5.0)
    with pytest.raises(ValueError, match="style inputs are"):
        policy.set_style(standstill_m=5.0)


def test_a_policy_without_style_inputs_refuses_a_style(tmp_path):
    save_checkpoint(tmp_path / "plain", _style_model(), name="plain", horizon=5.0)
    policy = load_policy(tmp_path / "plain")
    assert policy.style == {}
    with pytest.raises(ValueError, match="none"):
        policy.set_style(time_gap_s=2.0)


def test_checkpoint_with_a_style_input_count_mismatch_is_refused(tmp_path):
    import json

    save_checkpoint(tmp_path / "m", with_style_input(_style_model(), 1.5, 0.5), name="m",
                    horizon=5.0)
    sidecar = tmp_path / "m.json"
    meta = json.loads(sidecar.read_text())
    del meta["architecture"]["style_names"]
    sidecar.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="expects 9 features"):
        load_policy(tmp_path / "m")


def test_with_time_gap_sets_the_style_or_the_idm_gap(tmp_path):
    from safeil_sumo.planners import registry as planner_registry
    from safeil_sumo.planners.analytic import AnalyticPlanner

    styled = with_style_input(_style_model(), 1.5, 0.5)
    save_checkpoint(tmp_path / "m", styled, name="m", horizon=5.0)
    p = planner_registry.with_time_gap(planner_registry.load(str(tmp_path / "m.safetensors")), 2.2)
    assert p.style == {"time_gap_s": 2.2}
    idm = planner_registry.with_time_gap(planner_registry.load("idm"), 2.4)
    assert idm.params.time_gap_s == 2.4
    assert planner_registry.load("idm").params.time_gap_s != 2.4  # the shipped fit is untouched
    with pytest.raises(planner_registry.PolicyError, match="no time-gap setting"):
        planner_registry.with_time_gap(AnalyticPlanner(), 2.0)
    with pytest.raises(planner_registry.PolicyError, match="> 0"):
        planner_registry.with_time_gap(idm, 0.0)
    # the second style number: the checkpoint's schedule, the IDM's s0 inside its bounds
    p = planner_registry.with_time_gap(p, 1.4, -6.0)
    assert p.style == {"time_gap_s": 1.4, "standstill_m": -6.0}
    assert planner_registry.with_time_gap(idm, 1.4, 3.0).params.s0_m == 3.0
    with pytest.raises(planner_registry.PolicyError, match="IDM's standstill distance"):
        planner_registry.with_time_gap(idm, 1.4, -6.0)
    with pytest.raises(planner_registry.PolicyError, match="standstill_m must be in"):
        planner_registry.with_time_gap(p, 1.4, 100.0)
    ref = planner_registry.PlannerRef(str(tmp_path / "m.safetensors"), time_gap_s=1.4,
                                      standstill_m=-6.0)
    assert ref.load().style == {"time_gap_s": 1.4, "standstill_m": -6.0}
    assert ref.to_json()["standstill_m"] == -6.0
    assert "standstill_m" not in planner_registry.PlannerRef("idm", time_gap_s=1.4).to_json()
    with pytest.raises(ValueError, match="needs a time gap"):
        planner_registry.PlannerRef("idm", standstill_m=2.0)


# ------------------------------------------------------------------ adaptation in replays


def _arc_rows(duration: float, gap: float = 50.0):
    from fixtures_data import ARC_V as V
    from fixtures_data import arc_drive

    rows = arc_drive(duration)
    rows["lead_x"] = gap
    rows["v_lead"] = V
    return rows


def test_adapted_windows_leave_out_the_adaptation_seconds():
    import pandas as pd

    from safeil_sumo.experiments import window_replays as ra

    maneuvers = pd.concat([_arc_rows(40.0), _arc_rows(25.0).assign(maneuver_id="short#0")],
                          ignore_index=True)
    wins = ra.windows(maneuvers, "whole", adapt_s=10.0)
    # 40 s: scored from 10 s to the end; 25 s: only 15 s left (< 20 s): skipped
    assert [(w.maneuver_id, w.start_s, w.duration_s, w.adapt_s) for w in wins] == [
        ("arc#0", 10.0, None, 10.0)]
    plain = ra.Window("arc#0", 10.0, None)
    assert wins[0].task_id != plain.task_id  # never mixed up with an unadapted run
    capped = ra.windows(maneuvers, "whole", duration_s=20.0, adapt_s=10.0)
    assert capped[0].duration_s == 20.0
    with pytest.raises(ValueError, match="whole"):
        ra.windows(maneuvers, "sliding", adapt_s=10.0)


@pytest.mark.sumo
def test_replay_adapts_to_one_named_maneuver(tmp_path):
    """``--adapt-first-s`` with one maneuver id (not only ``all`` or a list): scored after S."""
    import pandas as pd

    from safeil_sumo import replay

    assert replay.parse_args(["--maneuver", "arc#0", "--windows", "whole",
                              "--adapt-first-s", "10"]).many
    drive = tmp_path / "drive.csv"
    _arc_rows(40.0).to_csv(drive, index=False)
    out = tmp_path / "r"
    assert replay.main(["--source", str(drive), "--maneuver", "arc#0", "--windows", "whole",
                        "--adapt-first-s", "10", "--policy", "idm", "--out", str(out)]) == 0
    table = pd.read_csv(out / "windows.csv")
    assert table["maneuver_id"].tolist() == ["arc#0"]
    assert table["start_s"].tolist() == [10.0]


def test_adapt_planners_sets_every_planner_from_one_style_estimate(tmp_path):
    """The default way: one (s0, T) estimate of the first seconds; the styled checkpoint and
    the IDM are each set so that their steady gap is the estimate's at the speed seen (the IDM
    through its own equilibrium), the IDM's v0, a, b, delta kept."""
    from fixtures_data import ARC_V as V

    from safeil_sumo.experiments import window_replays as ra
    from safeil_sumo.planners import idm
    from safeil_sumo.planners import registry as pol

    save_checkpoint(tmp_path / "m", with_style_input(_style_model(), 1.5, 0.5), name="m",
                    horizon=5.0)
    styled = pol.load(str(tmp_path / "m.safetensors"))
    shipped_idm = pol.load("idm")
    planners = {"m": styled, "idm": shipped_idm, "analytic": pol.load("analytic"),
                "idm_unadapted": shipped_idm}
    rows = _arc_rows(20.0, gap=40.0)  # 20 s steady at 40 m behind, both at V
    est = ra.driver_style(rows)
    assert est.samples == len(rows) and est.mean_speed_mps == pytest.approx(V)
    assert est.gap_m(V) == pytest.approx(40.0, abs=0.5)  # 20 s of one speed: the gap there
    out = ra.adapt_planners(planners | {"safeil_one_setting": styled}, rows)
    # the checkpoint gets the line; at the speed seen its setting gives the line's gap there
    s0, t_gap = out["m"].style["standstill_m"], out["m"].style["time_gap_s"]
    assert s0 == pytest.approx(est.s0_m) and s0 != 0.0
    assert float(scheduled_time_gap(t_gap, s0, V)) == pytest.approx(est.gap_m(V) / V)
    # the named one-setting row: that time gap, constant
    assert out["safeil_one_setting"].style == {"time_gap_s": pytest.approx(est.gap_m(V) / V)}
    assert styled.style == {"time_gap_s": 1.5}  # the shared planner is untouched
    p = out["idm"].params
    assert float(idm.equilibrium_gap(V, p)) == pytest.approx(est.gap_m(V), rel=1e-6)
    assert (p.v0_mps, p.a_max_mps2, p.b_mps2, p.delta) == (
        shipped_idm.params.v0_mps, shipped_idm.params.a_max_mps2, shipped_idm.params.b_mps2,
        shipped_idm.params.delta)
    assert idm.LOWER[2] <= p.s0_m <= idm.UPPER[2]
    assert out["analytic"] is planners["analytic"]
    assert out["idm_unadapted"] is shipped_idm  # the named unadapted row: as it is


def test_adapt_planners_named_variants_refit5_and_median(tmp_path):
    """``idm_refit5`` refits the IDM's five parameters; ``safeil_median`` gets the shrunk
    median of gap / speed (style.adapted_time_gap)."""
    from fixtures_data import ARC_V as V

    from safeil_sumo.experiments import window_replays as ra
    from safeil_sumo.planners import idm
    from safeil_sumo.planners import registry as pol

    save_checkpoint(tmp_path / "m", with_style_input(_style_model(), 1.5, 0.5), name="m",
                    horizon=5.0)
    styled = pol.load(str(tmp_path / "m.safetensors"))
    shipped_idm = pol.load_for_replay("idm_refit5")
    assert shipped_idm.name == "idm_refit5" and pol.adaptation_of("idm_refit5") == "refit5"
    assert pol.adaptation_of("idm") == pol.ESTIMATOR
    rows = _arc_rows(20.0, gap=40.0)
    out = ra.adapt_planners({"safeil_median": styled, "idm_refit5": shipped_idm}, rows)
    # 20 s seen at 40 / V s, the default 1.5 s the prior (style.TimeGapPrior's spreads)
    w = TimeGapPrior(1.5).weight(20.0)
    assert 0.8 < w < 1.0
    assert out["safeil_median"].style == {
        "time_gap_s": pytest.approx(1.5 ** (1 - w) * (40.0 / V) ** w, rel=1e-3)}
    # the refitted IDM follows this driver better than the population fit
    man = idm.maneuvers_from_rows(rows)
    fitted, _ = idm.evaluate_fit(man, out["idm_refit5"].params)
    shipped, _ = idm.evaluate_fit(man, shipped_idm.params)
    assert fitted < shipped and out["idm_refit5"].params != shipped_idm.params
    refit, calibrated = out["idm_refit5"].params, shipped_idm.params
    # all five refitted, not only the style's two
    assert (refit.v0_mps, refit.a_max_mps2, refit.b_mps2) != (
        calibrated.v0_mps, calibrated.a_max_mps2, calibrated.b_mps2)
    with pytest.raises(pol.PolicyError, match="adapt-first-s"):
        pol.load("idm_refit5")


@pytest.mark.sumo
def test_an_adapted_whole_replay_in_sumo(tmp_path):
    import pandas as pd

    """Real libsumo: the arc maneuver replayed from 10 s on with the planners adapted on its
    first 10 s; the record says so and covers the rest only."""
    pytest.importorskip("libsumo")
    from safeil_sumo.experiments import window_replays as ra

    maneuvers = _arc_rows(35.0)
    wins = ra.windows(maneuvers, "whole", adapt_s=10.0)
    records = ra.replay_all(maneuvers, wins, ["idm", "recorded"], tmp_path, progress=False)
    (rec,) = records
    assert rec["status"] == "ok" and rec["adapt_s"] == 10.0 and rec["start_s"] == 10.0
    assert rec["duration_s"] == pytest.approx(25.0, abs=0.2)
    by_policy = {m["policy"]: m for m in rec["metrics"]}
    assert by_policy["recorded"]["rmse_gap"] < 0.2  # the instrument's floor on the rest
    assert by_policy["idm"]["end_reason"] != "collision"
    # the IDM ran with the (s0, T) estimated on the first 10 s, not the shipped ones
    from dataclasses import asdict

    from safeil_sumo.planners import registry as pol

    assert set(rec["adapted"]) == {"idm", "recorded"} and rec["adapted"]["recorded"] == {}
    assert rec["adapted"]["idm"] != asdict(pol.load("idm").params)
    # the same with two windows side by side in one simulation (the batched path)
    both = pd.concat([maneuvers, _arc_rows(35.0).assign(maneuver_id="arc#1")],
                     ignore_index=True)
    batched = ra.replay_all(both, ra.windows(both, "whole", adapt_s=10.0), ["idm"],
                            tmp_path / "b", progress=False, batch=2)
    assert [r["adapted"]["idm"] for r in batched] == [rec["adapted"]["idm"]] * 2


def test_with_setting_sets_only_the_planners_that_have_one(tmp_path):
    from safeil_sumo.experiments import window_replays as ra
    from safeil_sumo.planners import registry as pol

    save_checkpoint(tmp_path / "m", with_style_input(_style_model(), 1.5, 0.5), name="m",
                    horizon=5.0)
    planners = {"m": pol.load(str(tmp_path / "m.safetensors")), "idm": pol.load("idm"),
                "analytic": pol.load("analytic")}
    out = ra.with_setting(planners, 2.2)
    assert out["m"].style == {"time_gap_s": 2.2}
    assert out["idm"].params.time_gap_s == 2.2
    assert out["analytic"] is planners["analytic"]
    assert planners["m"].style == {"time_gap_s": 1.5}  # copies: the loaded planners untouched
    assert planners["idm"].params.time_gap_s != 2.2
    assert ra.with_setting(planners, None) is planners


@pytest.mark.sumo
def test_a_replay_at_a_time_gap_setting_in_sumo(tmp_path):
    """Real libsumo: the same whole maneuver replayed with the IDM set to 1.0 s and to 2.5 s
    (``replay --time-gap-s``): it follows farther back at 2.5 s; the analytic planner, which has
    no setting, drives the same run in both."""
    pytest.importorskip("libsumo")
    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.experiments import window_replays as ra

    maneuvers = _arc_rows(30.0, gap=45.0)
    wins = ra.windows(maneuvers, "whole")
    runs = {}
    for tg in (1.0, 2.5):
        (rec,) = ra.replay_all(maneuvers, wins, ["idm", "analytic"], tmp_path / str(tg),
                               rp.ReplayConfig(time_gap_s=tg), progress=False)
        runs[tg] = {m["policy"]: m for m in rec["metrics"]}
    # time-gap error (planner - human) grows with the setting
    assert runs[2.5]["idm"]["bias_headway"] > runs[1.0]["idm"]["bias_headway"] + 0.5
    assert runs[2.5]["analytic"]["rmse_gap"] == runs[1.0]["analytic"]["rmse_gap"]
    with pytest.raises(ValueError, match="time gap"):
        rp.ReplayConfig(time_gap_s=0.0)


def test_replay_time_gap_is_refused_with_adaptation_or_out_of_range(capsys, tmp_path):
    from safeil_sumo import api, replay
    from safeil_sumo.experiments import maneuver_replay as rp

    with pytest.raises(SystemExit):
        replay.parse_args(["--maneuver", "all", "--windows", "whole", "--adapt-first-s", "60",
                           "--time-gap-s", "1.5"])
    assert "--adapt-first-s" in capsys.readouterr().err
    with pytest.raises(ValueError, match="exclude"):
        api.replay(_arc_rows(40.0), ["idm"], tmp_path, windows="whole",
                   config=rp.ReplayConfig(time_gap_s=1.5), adapt_first_s=10.0)
    drive = tmp_path / "drive.csv"
    _arc_rows(40.0).to_csv(drive, index=False)
    assert replay.main(["--source", str(drive), "--maneuver", "arc#0", "--time-gap-s", "0",
                        "--out", str(tmp_path / "r")]) == 2
    assert "time gap must be in (0, 10] s" in capsys.readouterr().err


# ------------------------------------------------------------- the setting in run and sweep


def test_sweep_specs_carry_the_time_gap():
    from safeil_sumo.experiments.sweep_executor import batch_key, task_id
    from safeil_sumo.scenarios.spec import Task

    plain = Task.of(policy="idm")
    set_ = Task.of(policy="idm", time_gap_s=2)
    assert "time_gap_s" not in plain.to_json()  # earlier task ids are unchanged
    assert set_.to_json()["time_gap_s"] == 2.0
    assert Task.from_json(set_.to_json()) == set_
    assert task_id(plain) != task_id(set_) and batch_key(plain) != batch_key(set_)
    with pytest.raises(ValueError, match="time gap"):
        Task.of(policy="idm", time_gap_s=0.0)


@pytest.mark.sumo
def test_run_time_gap_sets_the_planners_distance(tmp_path, capsys):
    """Real libsumo: the IDM told to keep 2.5 s settles farther back than told 1.0 s; a planner
    without the setting is refused in one line."""
    pytest.importorskip("libsumo")
    import pandas as pd

    from safeil_sumo import run

    gaps = {}
    for tg in (1.0, 2.5):
        out = tmp_path / f"tg{tg}"
        assert run.main(["--net", "straight", "--policy", "idm", "--time-gap-s", str(tg),
                         "--scenarios", "1", "--leader-speed-range-mps", "20", "20",
                         "--ego-speed-mps", "20",
                         "--gap-m", "40", "--no-plots", "--out", str(out)]) == 0
        log = pd.read_parquet(out / "steps.parquet")
        gaps[tg] = float(log["gap"].iloc[-1])
    # IDM equilibrium at 20 m/s: (s0 + v T) / sqrt(1 - (v/v0)^4) grows by 1.5 s x 20 m/s
    assert gaps[2.5] - gaps[1.0] > 20.0
    assert run.main(["--net", "straight", "--policy", "analytic", "--time-gap-s", "2",
                     "--scenarios", "1", "--no-plots", "--out", str(tmp_path / "a")]) == 2
    assert "no time-gap setting" in capsys.readouterr().err


def test_the_standstill_distance_travels_with_the_task_and_is_refused_alone(capsys):
    from safeil_sumo import replay
    from safeil_sumo.experiments.sweep_executor import task_id
    from safeil_sumo.scenarios.spec import Task

    line = Task.of(policy="idm", time_gap_s=1.2, standstill_m=4.0)
    assert line.to_json()["standstill_m"] == 4.0
    assert Task.from_json(line.to_json()) == line
    assert task_id(line) != task_id(Task.of(policy="idm", time_gap_s=1.2))
    with pytest.raises(SystemExit):
        replay.parse_args(["--standstill-m", "3"])
    assert "--standstill-m needs --time-gap-s" in capsys.readouterr().err


@pytest.mark.sumo
def test_run_with_a_standstill_distance_keeps_the_line(tmp_path):
    """Real libsumo, the shipped ``safeil`` behind a leader at 20 m/s: the line 10 m + 1.0 s v
    (1.5 s at 20 m/s) settles where the one setting 1.5 s does, and well behind 1.0 s alone."""
    pytest.importorskip("libsumo")
    import pandas as pd

    from safeil_sumo import run

    gaps = {}
    for style in (("1.5",), ("1.0", "10"), ("1.0",)):
        out = tmp_path / "_".join(style)
        flags = ["--time-gap-s", style[0]] + (["--standstill-m", style[1]] if len(style) > 1
                                              else [])
        assert run.main(["--net", "straight", "--policy", "safeil", *flags, "--scenarios", "1",
                         "--leader-speed-range-mps", "20", "20", "--ego-speed-mps", "20",
                         "--gap-m", "30", "--no-plots", "--out", str(out)]) == 0
        log = pd.read_parquet(out / "steps.parquet")
        gaps[style] = float(log["gap"].iloc[-1])
    assert gaps[("1.0", "10")] == pytest.approx(gaps[("1.5",)], abs=1.0)
    assert gaps[("1.0", "10")] - gaps[("1.0",)] > 6.0


@given(time_gap=st.floats(0.01, 10.0), standstill=st.floats(*STANDSTILL_RANGE_M),
       speed=st.floats(0.0, 60.0))
def test_every_two_number_style_is_inside_the_shipped_certificates_style_box(time_gap,
                                                                             standstill, speed):
    """The certificate covers the style box: every (s0, T) a planner accepts, at every speed,
    gives the network a setting inside the time-gap range the shipped ``safeil``'s
    certificate proves (0.6-3.5 s), so the one-plan proof holds for every two-number style."""
    import json

    from safeil_sumo.planners.registry import MODELS_DIR

    cert = json.loads((MODELS_DIR / "safeil.certificate.json").read_text())
    lo, hi = cert["style"]["time_gap_s"]
    assert cert["complete"]
    setting = float(scheduled_time_gap(time_gap, standstill, speed))
    assert lo <= SETTING_RANGE_S[0] <= setting <= SETTING_RANGE_S[1] <= hi
