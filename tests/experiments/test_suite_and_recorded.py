"""Recorded leaders in run/sweep and the leader-response suite (metrics hand-computed, a quick
suite in real libsumo)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from safeil_sumo import run as run_cli
from safeil_sumo import sweep as sweep_cli
from safeil_sumo.experiments import suite
from safeil_sumo.experiments.sweep_executor import run_sweep, task_id
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios import recorded_leaders as rl
from safeil_sumo.scenarios.spec import ScenarioSpec, Task, build_scenario
from safeil_sumo.scenarios.spec import resolve_road as _road
from safeil_sumo.sim.leaders import ProfileError
from safeil_sumo.sim.loop_types import LoopConfig
from safeil_sumo.sim.runner import run_scenario


def _profile(path, times, speeds) -> str:
    pd.DataFrame({"time": times, "speed": speeds}).to_csv(path, index=False)
    return str(path)


@pytest.fixture()
def stop_and_go(tmp_path) -> str:
    t = np.arange(0.0, 60.0, 0.1)
    v = np.clip(12 + 8 * np.sin(2 * np.pi * t / 25), 0, None)  # 4..20 m/s, real-ish waves
    return _profile(tmp_path / "stopgo.csv", t, v)


# ---------------------------------------------------------------------- avoidability (pure)


def test_braking_avoids_hand_computed() -> None:
    t = np.arange(0.0, 10.0, 0.01)
    # leader standing still 30 m ahead of an ego at 15 m/s: braking at 6 needs 18.75 m; TTC
    # stays above 1 s? at the start TTC = 2 s; it grows as the ego slows: avoidable
    assert suite.braking_avoids(t, 30.0, 15.0, np.zeros_like(t))
    # 15 m ahead: TTC 1 s at once -> not avoidable
    assert not suite.braking_avoids(t, 15.0, 15.0, np.zeros_like(t))
    # 20 m ahead at 20 m/s against a stopped car: 33 m needed -> collision, not avoidable
    assert not suite.braking_avoids(t, 20.0, 20.0, np.zeros_like(t))
    # a faster leader is always avoidable
    assert suite.braking_avoids(t, 5.0, 20.0, np.full_like(t, 25.0))


def test_response_metrics_hand_computed() -> None:
    t = np.arange(0.0, 4.0, 0.01)
    v = np.where(t < 2.0, 20.0, 20.0 - 3.0 * (t - 2.0))  # brakes at 3 m/s^2 from t = 2 s
    log = pd.DataFrame({"t": t, "v": v, "gap": np.full_like(t, 40.0), "ttc": np.inf,
                        "leader_v": 20.0, "collision": False})
    m = suite.response_metrics(log)
    assert m["max_decel_mps2"] == pytest.approx(3.0, rel=1e-6)
    assert m["min_time_gap_s"] == pytest.approx(40.0 / 20.0)
    assert m["max_jerk_mps3"] == pytest.approx(3.0 / 0.1, rel=0.05)  # the step, over 0.1 s
    assert m["avoidable"] and not m["collision"]



def test_braking_avoids_edge_cases_hand_computed() -> None:
    """Each clause of the rule alone decides one case (mutation testing, docs/mutation_testing.md)."""
    t = np.arange(0.0, 10.0, 0.01)
    lead = np.full_like(t, 20.0)
    # TTC exactly 1 s at the start is a flag (TTC <= 1 s), even where it rises at once after
    # (5 m, closing at 5 m/s: braking at 6 m/s^2 > 5 m/s^2 makes d(gap/closing)/dt > 0)
    assert not suite.braking_avoids(t, 10.0, 30.0, lead)
    assert not suite.braking_avoids(t, 5.0, 25.0, lead)
    # no TTC limit: 10 -> 0 m/s closing costs 100 / 12 = 8.33 m; 8.2 m collides, 8.8 m ends
    # 0.47 m behind (> 0: avoided)
    assert not suite.braking_avoids(t, 8.2, 30.0, lead, ttc_s=0.0)
    assert suite.braking_avoids(t, 8.8, 30.0, lead, ttc_s=0.0)
    # closing at 0.5 m/s 0.4 m behind: TTC 0.8 s at once
    assert not suite.braking_avoids(t, 0.4, 20.5, lead)
    # a faster leader 0.5 m ahead: never closer; at 0 m ahead: touching is not avoided
    assert suite.braking_avoids(t, 0.5, 15.0, lead)
    assert not suite.braking_avoids(t, 0.0, 15.0, lead)
    # the leader's speed at the START of each step counts: standing at t = 0, 30 m/s after,
    # 10 m ahead of an ego at 15 m/s: TTC 0.67 s at the first step
    jump = np.where(t > 0.0, 30.0, 0.0)
    assert not suite.braking_avoids(t, 10.0, 15.0, jump)
    # ... and the first step uses the first speed, the last speed is never used: 0.5 m behind
    # a leader as fast as the ego that stops at the log's last sample
    stops = np.where(t < t[-1], 30.0, 0.0)
    assert suite.braking_avoids(t, 0.5, 30.0, stops)
    # a log that starts at t = 100 s (steps are differences of times): 20 m, closing at 5 m/s
    assert suite.braking_avoids(100.0 + t, 20.0, 25.0, lead)


def _log(t, v, gap, leader_v=20.0, ttc=np.inf, collision=False) -> pd.DataFrame:
    return pd.DataFrame({"t": t, "v": v, "gap": gap, "ttc": ttc, "leader_v": leader_v,
                         "collision": collision})


def test_response_metrics_of_short_and_special_logs() -> None:
    """Empty, one-row and two-row logs, a standing ego, no leader, a collision, a log at 10 Hz
    (jerk unsmoothed) and one decelerating from its first row (no ramp at the edges)."""
    empty = suite.response_metrics(_log([], [], []))
    assert math.isnan(empty["min_ttc_s"]) and empty["min_time_gap_s"] == math.inf
    assert (empty["max_decel_mps2"], empty["max_jerk_mps3"], empty["avoidable"],
            empty["collision"]) == (0.0, 0.0, False, False)
    one = suite.response_metrics(_log([0.0], [20.0], [40.0], ttc=8.0))
    assert one == {"min_ttc_s": 8.0, "min_time_gap_s": 2.0, "max_decel_mps2": 0.0,
                   "max_jerk_mps3": 0.0, "collision": False, "avoidable": True}
    two = suite.response_metrics(_log([0.0, 0.5], [20.0, 19.0], [40.0, 40.0]))
    assert two["max_decel_mps2"] == pytest.approx(2.0) and two["max_jerk_mps3"] == 0.0
    accelerating = suite.response_metrics(_log([0.0, 0.5], [20.0, 21.0], [40.0, 40.0]))
    assert accelerating["max_decel_mps2"] == 0.0
    # 10 Hz: 0.1 s / 0.1 s = 1 sample of smoothing; accelerations 0, -2, -2, 0: jerk 20 m/s^3
    hz10 = suite.response_metrics(_log([0.0, 0.1, 0.2, 0.3, 0.4], [20.0, 20.0, 19.8, 19.6, 19.6],
                                       40.0))
    assert hz10["max_jerk_mps3"] == pytest.approx(20.0)
    assert hz10["max_decel_mps2"] == pytest.approx(2.0)
    # 3 samples at 10 Hz: accelerations 0 then -2: one jerk value of 20 m/s^3
    assert suite.response_metrics(_log([0.0, 0.1, 0.2], [20.0, 20.0, 19.8], 40.0)
                                  )["max_jerk_mps3"] == pytest.approx(20.0)
    # 100 Hz, 10-sample smoothing: a constant 3 m/s^2 braking from the first row has no jerk
    t = np.arange(0.0, 1.0, 0.01)
    steady = suite.response_metrics(_log(t, 25.0 - 3.0 * t, 40.0))
    assert steady["max_jerk_mps3"] == pytest.approx(0.0, abs=1e-6)
    # fewer samples than the smoothing window (5 < 10): the raw accelerations 0, 0, -3, -3
    short = suite.response_metrics(_log(t[:5], [25.0, 25.0, 25.0, 24.97, 24.94], 40.0))
    assert short["max_jerk_mps3"] == pytest.approx(300.0)
    # exactly one window of accelerations (11 rows, 10 accelerations): one smoothed value, no
    # jerk, however the raw accelerations vary
    wavy = 20.0 + 0.01 * np.sin(np.arange(11.0))
    assert suite.response_metrics(_log(t[:11], wavy, 40.0))["max_jerk_mps3"] == 0.0
    # the time gap needs v > 1 m/s: at exactly 1 m/s it is not defined
    standing = suite.response_metrics(_log([0.0, 1.0], [1.0, 0.5], [0.5, 0.5], leader_v=0.0))
    assert standing["min_time_gap_s"] == math.inf
    # no leader (no finite gap): nothing to avoid, so not "avoidable"
    assert not suite.response_metrics(_log([0.0, 1.0], 20.0, np.inf))["avoidable"]
    assert suite.response_metrics(_log([0.0, 1.0], 20.0, 40.0, collision=[False, True])
                                  )["collision"]
    # avoidability starts from the FIRST row's gap and speed: 5 m at 30 m/s behind 20 m/s
    # cannot be avoided, whatever follows
    first = suite.response_metrics(_log([0.0, 1.0, 2.0], [30.0, 20.0, 20.0], [5.0, 50.0, 50.0]))
    assert not first["avoidable"]


def test_suite_aggregate_hand_computed() -> None:
    """Per policy x family (family from the index): collisions (logged or the run's end
    reason), flags split by avoidability, extreme TTC, time gap, deceleration and jerk."""
    records = pd.DataFrame({  # listed out of alphabetical order: kept as listed
        "policy": ["a", "a", "a", "b"],
        "index": [10_000, 11_002, 20_001, 10_000],
        "flag": ["ttc", "", None, "collision"],
        "end_reason": ["completed", "collision", "completed", "collision"],
        "resp_collision": [False, False, False, True],
        "resp_avoidable": [True, False, False, False],
        "resp_min_ttc_s": [0.8, 3.0, 2.0, 0.0],
        "resp_min_time_gap_s": [0.5, 1.2, 1.0, 0.0],
        "resp_max_decel_mps2": [4.0, 6.0, 2.0, 9.0],
        "resp_max_jerk_mps3": [10.0, 30.0, 5.0, 50.0],
    })
    order = [3, 2, 0, 1]  # b/approach, a/braking, a/approach, a/approach
    assert list(suite.aggregate(records.iloc[order]).set_index(["policy", "family"]).index) == \
        [("b", "approach"), ("a", "braking"), ("a", "approach")]
    table = suite.aggregate(records).set_index(["policy", "family"])
    assert list(table.index) == [("a", "approach"), ("a", "braking"), ("b", "approach")]
    assert table.loc[("a", "approach")].to_dict() == {
        "scenarios": 2, "collisions": 1, "flags_avoidable": 1, "flags_unavoidable": 0,
        "min_ttc_s": 0.8, "min_time_gap_s": 0.5, "max_decel_mps2": 6.0, "max_jerk_mps3": 30.0}
    assert table.loc[("a", "braking"), "collisions"] == 0
    assert table.loc[("a", "braking"), "flags_unavoidable"] == 0  # no flag (None)
    b = table.loc[("b", "approach")]
    assert (b["collisions"], b["flags_avoidable"], b["flags_unavoidable"]) == (1, 0, 1)
    assert [suite.family_of(i) for i in (10_000, 20_999, 30_000, 40_001, 50_002)] == \
        list(suite.FAMILIES)


# ----------------------------------------------------------------------- recorded leaders


def test_recorded_draw_is_seeded_and_the_spec_id_is_stable(stop_and_go) -> None:
    spec = ScenarioSpec(net="straight", index=3, leader_kind="recorded", leader_profile=stop_and_go)
    road = _road("straight")
    a, b = build_scenario(spec, road), build_scenario(spec, road)
    assert a.leader.label == b.leader.label
    np.testing.assert_array_equal(a.leader.speeds, b.leader.speeds)
    assert a.max_time_s <= 60.0
    # specs without a profile keep the JSON (and task id) of earlier versions
    assert "leader_profile" not in ScenarioSpec().to_json()
    assert ScenarioSpec(**spec.to_json()) == spec
    assert task_id(Task(spec)) != task_id(Task(ScenarioSpec(net="straight", index=3)))


@pytest.mark.sumo
def test_recorded_profile_is_driven_in_sumo_within_5_cm_per_s(stop_and_go) -> None:
    spec = ScenarioSpec(net="straight", index=0, leader_kind="recorded",
                        leader_profile=stop_and_go, max_time_s=30.0)
    sc = build_scenario(spec, _road("straight"))
    from safeil_sumo.planners import registry as planner_registry

    log = run_scenario(sc, planner_registry.load("analytic"), LoopConfig()).log
    # the logged leader speed is SUMO's (read back each step) after the step it was set for
    expected = sc.leader.speed_at(log["t"].to_numpy() - 0.01)
    err = np.abs(log["leader_v"].to_numpy() - expected)
    assert err.max() < 0.05, err.max()


@pytest.mark.parametrize("bad,message", [
    ({"time": [0, 1, 2], "speed": [10, float("nan"), 10]}, "finite"),
    ({"time": [0, 1, 2], "speed": [10, -1, 10]}, "negative"),
    ({"time": [0, 0.5, 0.3], "speed": [10, 10, 10]}, "increase"),
])
def test_bad_profile_files_exit_2(tmp_path, capsys, bad, message) -> None:
    path = tmp_path / "bad.csv"
    pd.DataFrame(bad).to_csv(path, index=False)
    rl.library.cache_clear()
    out = tmp_path / "out"
    assert run_cli.main(["--leader", "recorded", "--leader-profile", str(path), "--scenarios",
                         "1", "--no-plots", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err and err.count("\n") == 1
    assert not out.exists()


def test_profile_too_short_for_the_scenario(tmp_path, capsys) -> None:
    path = _profile(tmp_path / "short.csv", np.arange(0, 30, 0.1), np.full(300, 20.0))
    rl.library.cache_clear()
    code = sweep_cli.main(["--net", "straight", "--policy", "analytic", "--leader", "recorded",
                           "--leader-profile", path, "--max-time-s", "60", "--scenarios", "1",
                           "--out", str(tmp_path / "sw"), "--no-progress"])
    assert code == 1  # the task fails with the reason recorded (the library itself is valid)
    summary = pd.read_csv(tmp_path / "sw" / "summary.csv")
    assert "too short" in summary["error"].iloc[0]
    with pytest.raises(ProfileError, match="too short"):
        rl.draw(rl.library(path), np.random.default_rng(0), max_time_s=60.0)


def test_recorded_ngsim_library_from_the_shared_data() -> None:
    from fixtures_data import NGSIM_PAIRS, require_file

    data_dir = require_file(NGSIM_PAIRS).parents[1]
    lib = rl.library("ngsim", str(data_dir))
    assert len(lib) > 100  # 143 maneuvers, all >= 20 s
    d = rl.draw(lib, np.random.default_rng(1))
    assert d.ego_speed_mps is not None and d.initial_gap_m > 0 and d.duration_s >= 20.0


# ------------------------------------------------------------------------------------ suite


def test_the_suite_families_by_hand() -> None:
    """Each family's scenario as the module doc describes it, on each net and variant; the index
    encodes family, net and variant (cases found by mutation testing: only the libsumo run of
    the quick suite built these specs)."""
    def want(family: str, net: str, variant: int, **fields) -> ScenarioSpec:
        index = {"approach": 10_000, "braking": 20_000, "cut_in": 30_000, "stop_and_go": 40_000,
                 "accelerating": 50_000}[family] + {"straight": 0, "curved500": 1000}[net]
        return ScenarioSpec(net=net, index=index + variant, master_seed=7, max_time_s=40.0,
                            **fields)

    for net in ("straight", "curved500"):
        for v in range(4):
            got = {f: suite.family_scenario(f, net, v, 7) for f in suite.FAMILIES}
            assert got["approach"] == want("approach", net, v, initial_gap_m=145.0,
                                           leader_speed_range_mps=(15.0, 25.0))
            assert got["braking"] == want("braking", net, v, leader_kind="braking",
                                          brake_time_s=5.0, brake_to_mps=0.0,
                                          brake_decel_mps2=(2.0, 4.0, 6.0, 2.0)[v])
            assert got["cut_in"] == want("cut_in", net, v, initial_gap_m=(10.0, 25.0),
                                         leader_speed_range_mps=(22.0, 27.0))
            assert got["stop_and_go"] == want("stop_and_go", net, v, leader_kind="recorded",
                                              leader_profile="ngsim")
            assert got["accelerating"] == want(
                "accelerating", net, v, leader_kind="accelerating",
                leader_speed_range_mps=(18.0, 22.0), brake_time_s=3.0, brake_decel_mps2=1.5,
                brake_to_mps=32.0, ego_speed_mps=20.0, initial_gap_m=30.0)
            for family, spec in got.items():
                assert suite.family_of(spec.index) == family
    assert suite.family_scenario("approach", "straight", 0, 7, max_time_s=12.0
                                 ).max_time_s == 12.0
    with pytest.raises(ValueError, match="unknown family 'merge'; families: approach, braking, "
                                         "cut_in, stop_and_go, accelerating"):
        suite.family_scenario("merge", "straight", 0, 0)


def test_suite_tasks_are_every_policy_family_net_and_variant() -> None:
    got = suite.suite_tasks(["idm", "bc"], seed=5, variants=2)
    assert len(got) == 2 * 5 * 2 * 2
    assert got == [Task(suite.family_scenario(f, n, v, 5), PlannerRef(p)) for p in ("idm", "bc")
                   for f in suite.FAMILIES for n in suite.NETS for v in range(2)]
    assert suite.suite_tasks(["idm"], families=("braking",), nets=("straight",)) == [
        Task(suite.family_scenario("braking", "straight", v, 0), PlannerRef("idm"))
        for v in range(3)]
    assert all(t.brake_guard for t in got)  # the loop as shipped


@pytest.mark.sumo
def test_quick_suite_runs_every_family_in_libsumo(tmp_path) -> None:
    specs = suite.suite_tasks(["analytic"], seed=0, variants=1)
    assert len(specs) == len(suite.FAMILIES) * len(suite.NETS)
    summary = run_sweep(specs, tmp_path, workers=1, progress=False)
    assert (summary["status"] == "ok").all(), summary["error"].tolist()
    table = suite.aggregate(summary)
    assert list(table["family"]) == list(suite.FAMILIES)
    for col in ("collisions", "flags_avoidable", "flags_unavoidable", "min_ttc_s",
                "min_time_gap_s", "max_decel_mps2", "max_jerk_mps3"):
        assert col in table.columns
    assert table["collisions"].sum() == 0
    acc = summary[summary["index"].map(suite.family_of) == "accelerating"]
    assert (acc["leader_label"] == "piecewise").all()


# ------------------------------------------------------- the ego's start behind a recorded leader


@pytest.fixture()
def slow_profile(tmp_path) -> str:
    """21 s of a leader at 6.5 m/s (congestion), a little stop-and-go after 10 s."""
    t = np.arange(0.0, 21.0, 0.1)
    return _profile(tmp_path / "slow.csv", t, 6.5 + np.where(t > 10.0, np.sin(t - 10.0), 0.0))


@pytest.mark.sumo
def test_run_starts_the_ego_at_the_profile_speed_unless_given(tmp_path, slow_profile) -> None:
    import json

    rl.library.cache_clear()
    args = ["--net", "straight", "--policy", "analytic", "--leader", "recorded",
            "--leader-profile", slow_profile, "--scenarios", "1", "--no-plots"]
    for extra, expected in (([], 6.5), (["--ego-speed-mps", "8"], 8.0)):
        out = tmp_path / f"run{len(extra)}"
        assert run_cli.main([*args, *extra, "--out", str(out)]) == 0
        steps = pd.read_parquet(out / "steps.parquet")
        # the first logged step is 0.01 s after the start: within 0.1 m/s of the start speed
        assert steps["v"].iloc[0] == pytest.approx(expected, abs=0.1)
        summary = pd.read_csv(out / "summary.csv")
        assert summary["ego_speed0_mps"].iloc[0] == pytest.approx(expected)
        config = json.loads((out / "manifest.json").read_text())["config"]
        assert config["ego_speeds_mps"] == pytest.approx([expected])
        assert summary["flag"].iloc[0] != "collision"  # NaN (no flag) or another flag


@pytest.mark.sumo
def test_sweep_and_api_resolve_the_ego_speed_alike(tmp_path, slow_profile) -> None:
    import json

    from safeil_sumo import api

    rl.library.cache_clear()
    # the API: the profile's first speed, or the one given; other leaders: 30 m/s as before
    assert api.scenario("straight", leader_kind="recorded",
                        leader_profile=slow_profile).ego_speed_mps == pytest.approx(6.5)
    assert api.scenario("straight", leader_kind="recorded", leader_profile=slow_profile,
                        ego_speed_mps=12.0).ego_speed_mps == 12.0
    assert api.scenario("straight").ego_speed_mps == 30.0
    assert ScenarioSpec().ego_speed_mps == 30.0  # the JSON (task id) of other leaders unchanged
    # the sweep: the task's record holds the resolved speed, its spec what was asked (None: the
    # recording's start)
    out = tmp_path / "sw"
    assert sweep_cli.main(["--net", "straight", "--policy", "analytic", "--leader", "recorded",
                           "--leader-profile", slow_profile, "--scenarios", "1", "--max-time-s",
                           "5", "--out", str(out), "--no-progress"]) == 0
    summary = pd.read_csv(out / "summary.csv")
    assert summary["ego_speed0_mps"].iloc[0] == pytest.approx(6.5)
    spec = json.loads((out / "manifest.json").read_text())["config"]["specs"][0]
    assert spec["ego_speed_mps"] is None


def test_explicit_ego_speed_wins_over_a_recorded_follower() -> None:
    from dataclasses import replace

    from fixtures_data import NGSIM_PAIRS, require_file

    from safeil_sumo.scenarios.safety import scenario_seed

    require_file(NGSIM_PAIRS)  # the library reads the default data folder, ../shared/data
    spec = ScenarioSpec(net="straight", index=2, leader_kind="recorded", leader_profile="ngsim")
    rng = np.random.default_rng(scenario_seed(0, 2))
    rng.uniform(25, 32)  # the spec's leader-speed draw comes first, as in build_scenario
    drawn = rl.draw(rl.library("ngsim"), rng)
    road = _road("straight")
    # by default the ego starts as the recorded follower did; a speed given explicitly wins
    assert build_scenario(spec, road).ego_speed_mps == pytest.approx(drawn.ego_speed_mps)
    assert build_scenario(replace(spec, ego_speed_mps=25.0), road).ego_speed_mps == 25.0


# ------------------------------------------------------------------- physically impossible profiles


def _dropout_profile(tmp_path) -> str:
    """30 s at 25.8 m/s whose speed sensor drops out to 0 for one sample at t = 112.3 s (the
    file's own clock starts at 100 s)."""
    t = np.round(np.arange(100.0, 130.0, 0.1), 1)
    v = np.where(np.isclose(t, 112.3), 0.0, 25.8)
    return _profile(tmp_path / "dropout.csv", t, v)


def test_a_speed_dropout_is_refused_by_run_and_sweep(tmp_path, capsys) -> None:
    path = _dropout_profile(tmp_path)
    rl.library.cache_clear()
    out = tmp_path / "run"
    assert run_cli.main(["--net", "straight", "--policy", "analytic", "--leader", "recorded",
                         "--leader-profile", path, "--scenarios", "1", "--no-plots", "--out",
                         str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1, err
    assert "dropout.csv" in err and "falls 25.8 m/s in 0.1 s at t = 112.3 s" in err, err
    assert not out.exists()
    rl.library.cache_clear()
    assert sweep_cli.main(["--net", "straight", "--policy", "analytic", "--leader",
                           "recorded", "--leader-profile", str(tmp_path), "--scenarios", "1",
                           "--out", str(tmp_path / "sw"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "dropout.csv" in err and "112.3 s" in err, err
    assert not (tmp_path / "sw").exists()


def test_a_hard_but_plausible_braking_profile_is_accepted(tmp_path) -> None:
    from safeil_sumo.sim.leaders import from_file

    # 30 -> 3 m/s at 9 m/s^2 (an emergency stop of an ordinary car), then 3 m/s
    t = np.arange(0.0, 25.0, 0.1)
    v = np.clip(30.0 - 9.0 * np.clip(t - 5.0, 0.0, None), 3.0, None)
    prof = from_file(_profile(tmp_path / "hard.csv", t, v))
    assert prof.speeds.min() == pytest.approx(3.0)


@pytest.mark.parametrize("source", ["ngsim", "openacc"])
def test_the_human_leader_libraries_are_plausible(source) -> None:
    from fixtures_data import NGSIM_PAIRS, OPENACC_DIR, require_file

    from safeil_sumo.sim.leaders import implausible_change

    require_file(NGSIM_PAIRS if source == "ngsim"
                 else OPENACC_DIR / "JRC-VC_280219_part2.csv.gz")
    # the check refuses no real leader the project drives (measured: NGSIM -5.6 / +4.6 m/s^2,
    # OpenACC -3.6 / +1.4 m/s^2 over 0.5 s)
    for rec in rl.library(source):
        assert implausible_change(rec.times, rec.speeds) is None, rec.recording_id


def test_the_suite_on_the_command_line_takes_the_planners_style() -> None:
    from safeil_sumo import sweep

    args = sweep.parse_args(["--suite", "leader-response", "--policy", "safeil", "--quick",
                             "--time-gap-s", "1.1", "--standstill-m", "6"])
    tasks = sweep.build_tasks(args)
    assert tasks and all(t.planner == PlannerRef("safeil", time_gap_s=1.1, standstill_m=6.0)
                         for t in tasks)
    plain = sweep.build_tasks(sweep.parse_args(["--suite", "leader-response", "--quick",
                                                "--policy", "safeil"]))
    assert [t.to_json() for t in plain] == [  # without a style: the suite's own task ids
        t.to_json() for t in suite.suite_tasks(["safeil"], 0, variants=1)]
