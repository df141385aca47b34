"""Falsification (issue 23 part 2): the search box, the objective and its avoidability filter,
the cross-entropy method against random sampling, seeded determinism, the replayable worst case
and a real libsumo run at a tiny budget."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.experiments import falsification_search as fz
from safeil_sumo.experiments.suite import braking_avoids
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.sim.leaders import constant, piecewise

# ------------------------------------------------------------------------- the CEM's update


def test_cem_update_by_hand() -> None:
    """4 points in the box, elite fraction 0.5 -> the 2 lowest scores; smoothing 0.5."""
    cfg = fz.SearchConfig(elite_fraction=0.5, smoothing=0.5, min_std=0.02)
    u = np.zeros((4, fz.DIM))
    u[:, 0] = [0.1, 0.9, 0.3, 0.5]
    u[:, 1] = [0.2, 0.2, 0.6, 0.6]
    u[:, 2] = 0.4  # equal in the elite: its std 0 -> floored
    scores = np.array([1.0, 5.0, 2.0, math.inf])  # elite: points 0 and 2
    mean, std = np.full(fz.DIM, 0.5), np.full(fz.DIM, 0.3)
    new_mean, new_std = fz.cem_update(u, scores, mean, std, cfg)
    # elite mean of coordinate 0: (0.1 + 0.3) / 2 = 0.2, std 0.1 -> 0.5*0.2 + 0.5*0.5 = 0.35,
    # 0.5*0.1 + 0.5*0.3 = 0.2; coordinate 1: (0.2 + 0.6) / 2 = 0.4, std 0.2 -> 0.45, 0.25
    assert new_mean[0] == pytest.approx(0.35) and new_std[0] == pytest.approx(0.2)
    assert new_mean[1] == pytest.approx(0.45) and new_std[1] == pytest.approx(0.25)
    # coordinate 2: 0.5*0.4 + 0.5*0.5 = 0.45; std 0.5*0 + 0.5*0.3 = 0.15
    assert new_mean[2] == pytest.approx(0.45) and new_std[2] == pytest.approx(0.15)
    # the rest: elite at 0 -> mean 0.25, std 0.15
    assert new_mean[3:] == pytest.approx(0.25) and new_std[3:] == pytest.approx(0.15)


def test_cem_update_floors_the_std_and_ignores_excluded_points() -> None:
    cfg = fz.SearchConfig(elite_fraction=0.5, smoothing=1.0, min_std=0.05)
    u = np.full((4, fz.DIM), 0.7)
    mean, std = np.full(fz.DIM, 0.5), np.full(fz.DIM, 0.3)
    new_mean, new_std = fz.cem_update(u, np.array([1.0, 2.0, 3.0, 4.0]), mean, std, cfg)
    assert new_mean == pytest.approx(0.7) and new_std == pytest.approx(0.05)
    # fewer than 2 avoidable (finite) scores: unchanged
    same = fz.cem_update(u, np.array([1.0, math.inf, math.inf, math.inf]), mean, std, cfg)
    assert same[0] is mean and same[1] is std


# ----------------------------------------------------------------------- the objective


def test_score_excludes_unavoidable_caps_and_counts_flags() -> None:
    assert fz.score(0.3, "collision", avoidable=False) == math.inf
    assert fz.score(0.3, "ttc", avoidable=True) == 0.3
    assert fz.score(4.0, "lane_departure", avoidable=True) == fz.TTC_FLAG_S  # a flag is <= 1 s
    assert fz.score(math.inf, "", avoidable=True) == fz.TTC_CAP_S  # never closing
    assert fz.score(math.nan, "", avoidable=True) == fz.TTC_CAP_S  # no leader seen
    assert fz.score(2.5, "", avoidable=True) == 2.5


def test_avoidability_filter() -> None:
    # a slower leader 60 m ahead: braking at 6 m/s^2 matches its speed long before
    assert fz.avoidable(constant(20.0).speed_at, 60.0, 30.0, 30.0)
    # a cut-in 5 m ahead, 10 m/s slower: TTC 0.5 s from the first step
    assert not fz.avoidable(constant(20.0).speed_at, 5.0, 30.0, 30.0)
    # a leader 10 m ahead at the ego's speed braking to a stop at 9 m/s^2: the ego stops in
    # 75 m, the leader in 50 m: no braking at 6 m/s^2 saves it; at 4 m/s^2 the leader needs
    # 112.5 m and the ego keeps behind
    hard = piecewise([0.0, 2.0, 2.0 + 30.0 / 9.0], [30.0, 30.0, 0.0])
    soft = piecewise([0.0, 2.0, 2.0 + 30.0 / 4.0], [30.0, 30.0, 0.0])
    assert not fz.avoidable(hard.speed_at, 10.0, 30.0, 20.0)
    assert fz.avoidable(soft.speed_at, 10.0, 30.0, 20.0)
    # it is the suite's notion: the same answer as braking_avoids at the same steps
    t = np.arange(0.0, 20.0 + 0.005, 0.01)
    for prof, gap in ((hard, 10.0), (soft, 10.0), (hard, 40.0)):
        assert fz.avoidable(prof.speed_at, gap, 30.0, 20.0) == braking_avoids(
            t, gap, 30.0, prof.speed_at(t))


def _braking_spec(gap_m: float) -> ScenarioSpec:
    """A leader 10 m/s slower than the ego (30 m/s), braking at 9 m/s^2 to a stop after 1 s."""
    return ScenarioSpec(net="straight", leader_kind="braking",
                        leader_speed_range_mps=(20.0, 20.0), initial_gap_m=gap_m,
                        ego_speed_mps=30.0, brake_time_s=1.0, brake_decel_mps2=9.0,
                        brake_to_mps=0.0, max_time_s=20.0)


@pytest.mark.parametrize(("gap_m", "flag", "score", "failure", "avoidable"), [
    (5.0, "collision", math.inf, False, False),  # no braking saves it: not a failure
    (5.0, "", math.inf, False, False),  # unavoidable and unflagged: excluded all the same
    (80.0, "collision", 0.0, True, True),  # braking at 6 m/s^2 from the start saves it
    (80.0, "ttc", 0.4, True, True),
    (80.0, "", 2.5, False, True),
    (80.0, "lane_departure", 1.0, True, True),  # a flag scores at most 1 s, whatever its TTC
])
def test_a_flagged_run_counts_as_a_failure_only_if_braking_could_avoid_it(
        gap_m, flag, score, failure, avoidable) -> None:
    """The record of a run against the scenario's own leader: a flagged run that no braking
    could have avoided is excluded (score inf), never counted as a failure (a case found by
    mutation testing: failure = flagged alone passed the whole suite)."""
    spec = _braking_spec(gap_m)
    min_ttc = {"collision": 0.0, "ttc": 0.4, "": 2.5, "lane_departure": 4.0}[flag]
    record = {"status": "ok", "sim_time_s": 20.0, "flag": flag, "min_ttc_s": min_ttc}
    out = fz.outcome_of(spec, record)
    assert (out.score, out.failure, out.avoidable, out.flag) == (score, failure, avoidable, flag)
    assert out.min_ttc_s == min_ttc
    # a run that did not run is excluded and is no failure
    err = fz.outcome_of(spec, {"status": "error", "error": "boom"})
    assert (err.score, err.failure, err.avoidable, err.error) == (math.inf, False, False, "boom")
    assert fz.outcome_of(spec, {"status": "timeout"}).error == ""


def test_failure_counts_and_first_failure_skip_unavoidable_flags() -> None:
    """Counts over a search: two flagged runs, one unavoidable: one failure, found at the 3rd
    simulation, not the 1st."""
    outcomes = [fz.Outcome(math.inf, False, 0.0, "collision", False),
                fz.Outcome(3.0, False, 3.0, "", True),
                fz.Outcome(0.5, True, 0.5, "ttc", True),
                fz.Outcome(math.inf, False, error="boom", avoidable=False)]
    result = fz.SearchResult(fz.SearchConfig(), np.zeros((4, fz.DIM)), outcomes)
    assert result.first_failure == 3 and result.best == 2
    np.testing.assert_array_equal(result.best_so_far, [math.inf, 3.0, 0.5, 0.5])
    s = fz.summary(result, "bc")
    assert (s["failures"], s["avoidable"]) == (1, 2)
    assert fz.first_at_or_below(result, 0.0) is None  # the only TTC 0 was unavoidable
    assert fz.first_at_or_below(result, 0.5) == 3


def _planted_record(task) -> dict:
    """A stand-in for a SUMO run's record: a TTC flag below 20 m/s of leader speed."""
    spec = task.scenario
    slow = spec.leader_speed_range_mps[0] < 20.0
    return {"status": "ok", "sim_time_s": spec.max_time_s, "flag": "ttc" if slow else "",
            "min_ttc_s": 0.5 if slow else math.inf}  # inf: never closing (null in a file)


def test_the_closed_loop_objective_runs_the_decoded_points_in_order(monkeypatch, tmp_path
                                                                    ) -> None:
    """The glue between the search and the task engine: each point decoded with the policy,
    time limit and guard setting, all run as one batch (one simulation), each record scored
    against its own spec; a batch already recorded in the tasks folder is read, not run. The
    simulation is replaced by a recorder here: the libsumo run is the CLI test's."""
    from safeil_sumo.experiments import sweep_executor

    batches = []

    def run_tasks(specs, on_record=None):
        batches.append(list(specs))
        for k, s in enumerate(specs):
            on_record(k, _planted_record(s))

    monkeypatch.setattr(sweep_executor, "run_tasks", run_tasks)
    u = np.random.default_rng(2).random((3, fz.DIM))
    outcomes = fz.closed_loop_objective("bc", max_time_s=12.0, brake_guard=False)(u)
    assert batches == [[fz.decode(x, "bc", 12.0, False) for x in u]]
    assert outcomes == [fz.outcome_of(s.scenario, _planted_record(s)) for s in batches[0]]
    objective = fz.closed_loop_objective("idm", tasks_dir=tmp_path)
    objective(u[:2])
    assert batches[-1] == [fz.decode(x, "idm", 30.0, True) for x in u[:2]]
    assert len(list(tmp_path.glob("*.json"))) == 2
    assert objective(u[:2]) == [fz.outcome_of(fz.decode_scenario(x, 30.0),
                                              _planted_record(fz.decode(x, "idm", 30.0, True)))
                                for x in u[:2]]
    assert len(batches) == 2  # read back from the records
    from safeil_sumo.experiments import task_engine

    calls = []
    monkeypatch.setattr(task_engine, "execute", lambda *a, **kw: calls.append((a[3:], kw)))
    fz.closed_loop_objective("idm", tasks_dir=tmp_path, workers=2, scheduler="tcp://h:1")(u[:1])
    assert calls == [((2, "tcp://h:1"), {"progress": False})]
    assert fz.decode(u[0], "idm", 12.0).scenario.max_time_s == 12.0


def test_an_interrupted_search_resumes_from_its_finished_runs(monkeypatch, tmp_path) -> None:
    """Ctrl-C in the middle of a batch keeps the runs that ended; the same search started again
    simulates only the rest and ends with the table of a search never interrupted."""
    from safeil_sumo.experiments import sweep_executor

    ran, stop_after = [], [7]

    def run_tasks(specs, on_record=None):
        for k, s in enumerate(specs):
            if len(ran) == stop_after[0]:
                raise KeyboardInterrupt
            ran.append(s)
            on_record(k, _planted_record(s))

    monkeypatch.setattr(sweep_executor, "run_tasks", run_tasks)
    cfg = fz.SearchConfig(method="cem", budget=12, batch=4, seed=1, max_time_s=12.0)
    folder = tmp_path / "search"
    with pytest.raises(KeyboardInterrupt):
        fz.run_or_load("bc", cfg, folder)
    assert not (folder / "evaluations.csv").exists()
    assert len(list((folder / "tasks").glob("*.json"))) == 7  # 4 of batch 1, 3 of batch 2
    stop_after[0] = 10**6
    resumed = fz.run_or_load("bc", cfg, folder)
    assert len(ran) == 12  # 7 before, the 5 left now
    assert not (folder / "tasks").exists()  # every record is in evaluations.csv
    ran.clear()
    fresh = fz.run_or_load("bc", cfg, tmp_path / "fresh")
    assert len(ran) == 12
    pd.testing.assert_frame_equal(fz.table(resumed, "bc"), fz.table(fresh, "bc"))


def test_avoidability_is_judged_on_the_physics_grid_from_0_to_the_horizon() -> None:
    """The leader's speed is read at 0, 0.01, ..., the horizon (both ends included, nothing
    beyond): the braking reference starts with the run (cases found by mutation testing)."""
    seen = []

    def leader(t: np.ndarray) -> float:
        seen.append(np.array(t))
        return 20.0  # a scalar speed: a constant leader

    assert fz.avoidable(leader, 60.0, 30.0, 2.0)
    np.testing.assert_allclose(seen[0], np.arange(201) * 0.01, rtol=0, atol=1e-12)
    assert len(seen[0]) == 201 and seen[0][0] == 0.0
    fz.avoidable(leader, 60.0, 30.0, 0.001)  # a horizon below one step still takes one step
    np.testing.assert_allclose(seen[1], [0.0, 0.01], rtol=0, atol=1e-15)
    fz.avoidable(leader, 60.0, 30.0, 2.0, step_s=0.5)
    np.testing.assert_array_equal(seen[2], [0.0, 0.5, 1.0, 1.5, 2.0])


# -------------------------------------------------------------------------- the search box


def test_decode_maps_the_box_onto_valid_specs() -> None:
    rng = np.random.default_rng(0)
    for u in [np.zeros(fz.DIM), np.ones(fz.DIM), *rng.random((200, fz.DIM))]:
        task = fz.decode(u, "bc")
        assert task.planner == PlannerRef("bc") and task.brake_guard
        assert not fz.decode(u, "bc", brake_guard=False).brake_guard
        spec = task.scenario
        assert spec == fz.decode_scenario(u) and spec.index == 0 and spec.max_time_s == 30.0
        assert spec.net in fz.NETS and 0 <= spec.master_seed < fz.SCENARIO_SEEDS
        assert 0 <= spec.radar_noise_m <= 1.5 and 0 <= spec.lane_noise_c0_m <= 0.2
        if spec.leader_kind == "braking":
            lo, hi = spec.leader_speed_range_mps
            assert lo == hi and 10.0 <= lo <= 35.0 and 5.0 <= spec.initial_gap_m <= 80.0
            assert 0.0 <= spec.brake_to_mps <= lo and spec.ego_speed_mps == fz.EGO_SPEED_MPS
        else:
            assert spec.leader_kind == "recorded" and spec.leader_profile == "ngsim"
    u = np.full(fz.DIM, 0.5)
    v = fz.values(u)
    assert v["gap_m"] == pytest.approx(42.5) and v["brake_onset_s"] == pytest.approx(7.5)
    assert fz.decode_scenario(u).net == fz.NETS[2]  # 0.5 of 5 tracks: the middle one
    u[0] = fz.RECORDED_FROM
    assert fz.decode_scenario(u).leader_kind == "recorded"
    with pytest.raises(ValueError, match="coordinates"):
        fz.values(np.zeros(3))


@pytest.mark.parametrize("source", [0.1, 0.9])  # a scripted and a recorded leader
@pytest.mark.parametrize("guard", [True, False])
def test_the_worst_case_reruns_from_its_sweep_file(tmp_path, source: float, guard: bool) -> None:
    """``sweep --config worst.toml`` builds exactly the spec the search ran."""
    from safeil_sumo import sweep

    u = np.random.default_rng(3).random(fz.DIM)
    u[0] = source
    spec = fz.decode(u, "safeil", 25.0, guard)
    assert ("brake_guard = false\n" in fz.sweep_toml(spec)) is not guard
    assert fz.sweep_toml(spec).startswith(f'net = ["{spec.scenario.net}"]\n')  # no comment: no head
    path = tmp_path / "worst.toml"
    path.write_text(fz.sweep_toml(spec, "a comment\non two lines"))
    assert sweep.build_tasks(sweep.parse_args(["--config", str(path)])) == [spec]


def _result(policy_seed: int, outcomes: list, **config) -> fz.SearchResult:
    u = np.random.default_rng(policy_seed).random((len(outcomes), fz.DIM))
    return fz.SearchResult(fz.SearchConfig(**config), u, outcomes)


def test_the_study_by_hand(tmp_path, monkeypatch) -> None:
    """The study's searches, folders, rows, medians and worst cases (cases found by mutation
    testing: the results section's toy run read few of these fields)."""
    run = fz.StudyRun("bc", 200, 20, (0, 1))
    assert fz.study_configs(run) == [fz.SearchConfig(method=m, budget=200, batch=20, seed=s)
                                     for s in (0, 1) for m in ("cem", "random")]
    cfg = fz.SearchConfig(method="cem", seed=3)
    assert fz.study_folder(tmp_path, "bc", cfg) == tmp_path / "bc_cem_s3"
    assert fz.study_folder(tmp_path, "bc", dataclasses.replace(cfg, brake_guard=False)) == \
        tmp_path / "bc_cem_s3_noguard"
    fail = fz.Outcome(0.0, True, 0.0, "collision", True)
    near = fz.Outcome(0.6, True, 0.6, "ttc", True)
    fine = fz.Outcome(2.0, False, 2.0, "", True)
    gone = fz.Outcome(math.inf, False, math.nan, "", False, "boom")
    a = _result(1, [fine, near, fail], method="cem", seed=0, budget=3, batch=3)
    b = _result(2, [fine, gone], method="random", seed=4, budget=2, batch=1)
    rows = fz.study_rows([("safeil", a), ("bc", b)]).to_dict("records")
    nan = math.nan
    want = [
        {"policy": "safeil", "method": "cem", "seed": 0, "budget": 3, "batch": 3,
         "simulations": 3, "first_failure": 2, "first_ttc0": 3, "failures": 2, "avoidable": 3,
         "errors": 0, "best_min_ttc_s": 0.0, "best_flag": "collision", "best_sim": 3},
        {"policy": "bc", "method": "random", "seed": 4, "budget": 2, "batch": 1,
         "simulations": 2, "first_failure": nan, "first_ttc0": nan, "failures": 0,
         "avoidable": 1, "errors": 1, "best_min_ttc_s": 2.0, "best_flag": "", "best_sim": 1}]
    for got, row in zip(rows, want, strict=True):  # a search without a failure: NaN
        assert list(got) == list(row)
        assert all(got[k] == v or (math.isnan(got[k]) and math.isnan(v)) for k, v in row.items()
                   if not isinstance(v, str))
        assert all(got[k] == v for k, v in row.items() if isinstance(v, str))
    # medians per planner and method in the order met; a seed without a failure counts as inf
    table = pd.DataFrame({"policy": ["safeil", "safeil", "bc", "safeil"],
                          "method": ["cem", "cem", "cem", "random"],
                          "first_failure": [4, None, 7, None]})
    assert fz.median_to_first(table).to_dict("records") == [
        {"policy": "safeil", "method": "cem", "seeds": 2, "found": 1, "median": math.inf},
        {"policy": "bc", "method": "cem", "seeds": 1, "found": 1, "median": 7.0},
        {"policy": "safeil", "method": "random", "seeds": 1, "found": 0, "median": math.inf}]
    # the worst case, in a folder made for it, named as asked; nothing avoidable: nothing
    monkeypatch.chdir(tmp_path)
    toml = fz.write_worst(a, "safeil", tmp_path / "x" / "y", stem="w")
    assert toml == tmp_path / "x" / "y" / "w.toml"
    spec = fz.decode(a.u[2], "safeil", 30.0, True)
    assert Task.from_json(json.loads((tmp_path / "x" / "y" / "w.json").read_text())) == spec
    assert toml.read_text() == fz.sweep_toml(spec, (
        "safeil: worst avoidable case of a cem search (seed 0, simulation 3 of 3): min TTC "
        "0.000 s, collision\nrerun: python -m safeil_sumo.sweep --config x/y/w.toml "
        "--out runs/w"))
    assert fz.write_worst(_result(3, [gone], budget=1, batch=1), "bc", tmp_path / "z") is None
    assert not (tmp_path / "z").exists()
    # a worst case without a flag says so, under the default name
    calm = fz.Outcome(2.5, False, 2.5, "", True)
    toml = fz.write_worst(_result(4, [calm], budget=1, batch=1), "bc", tmp_path / "v")
    assert toml == tmp_path / "v" / "worst.toml" and (tmp_path / "v" / "worst.json").is_file()
    assert "min TTC 2.500 s, no flag\n" in toml.read_text()


def test_search_config_is_checked() -> None:
    with pytest.raises(ValueError, match="method"):
        fz.SearchConfig(method="bayes")
    with pytest.raises(ValueError, match="budget"):
        fz.SearchConfig(budget=0)
    with pytest.raises(ValueError, match="elite"):
        fz.SearchConfig(elite_fraction=0.0)


def test_search_config_edges_and_messages() -> None:
    """Each range's ends (cases found by mutation testing)."""
    fz.SearchConfig(budget=1, batch=1, elite_fraction=1.0, smoothing=1.0, min_std=0.5,
                    max_time_s=0.5)
    for bad, message in (({"batch": 0}, "budget"),
                         ({"seed": -1}, "seed must be >= 0, got -1"),
                         ({"elite_fraction": 1.5},
                          r"^elite fraction and smoothing must be in \(0, 1\]$"),
                         ({"smoothing": 0.0}, "smoothing"), ({"smoothing": 1.5}, "smoothing"),
                         ({"min_std": 0.0}, r"min std must be in \(0, 0.5\], got 0.0"),
                         ({"min_std": 0.6}, "min std"),
                         ({"max_time_s": 0.0}, "max time must be > 0 s, got 0.0")):
        with pytest.raises(ValueError, match=message):
            fz.SearchConfig(**bad)


def test_the_box_draws_and_the_cem_update_by_hand() -> None:
    """The box's ends (a category's last choice at u = 1), clipping, the decoded values'
    rounding, the draws from a distribution or uniformly, and an elite of 3 of 4 (cases found
    by mutation testing)."""
    assert fz.uniform_std() == 1.0 / math.sqrt(12.0)
    assert fz.values(np.ones(fz.DIM))["track"] == len(fz.NETS) - 1
    assert fz.values(np.full(fz.DIM, 1.5)) == fz.values(np.ones(fz.DIM))
    assert fz.values(np.full(fz.DIM, -0.5)) == fz.values(np.zeros(fz.DIM))
    rng = np.random.default_rng(8)
    for u in rng.random((50, fz.DIM)):
        u[0] = 0.1  # a scripted leader
        v, spec = fz.values(u), fz.decode_scenario(u)
        assert spec.radar_noise_m == round(v["radar_noise_m"], 3)
        assert spec.lane_noise_c0_m == round(v["lane_noise_m"], 4)
        lo, hi = spec.leader_speed_range_mps
        assert lo == hi == round(v["leader_speed_mps"], 2)
        if spec.leader_kind == "braking":
            assert spec.initial_gap_m == round(v["gap_m"], 2) and spec.ego_speed_mps == 30.0
            assert spec.brake_time_s == round(v["brake_onset_s"], 2)
            assert spec.brake_decel_mps2 == round(v["brake_decel_mps2"], 2)
            assert spec.brake_to_mps == round(max(0.0, lo - spec.brake_decel_mps2
                                                  * v["brake_duration_s"]), 2)
    # draws: uniform without a distribution (also with a mean but no std); else clipped normal
    mean, std = np.full(fz.DIM, 0.9), np.full(fz.DIM, 1.0)
    np.testing.assert_array_equal(fz.draw(np.random.default_rng(1), 5, mean, None),
                                  np.random.default_rng(1).random((5, fz.DIM)))
    got = fz.draw(np.random.default_rng(1), 200, mean, std)
    np.testing.assert_array_equal(got, np.clip(
        mean + std * np.random.default_rng(1).standard_normal((200, fz.DIM)), 0.0, 1.0))
    assert got.min() == 0.0 and got.max() == 1.0
    # elite fraction 0.75 of 4 points: the 3 lowest scores; exactly 2 finite scores update
    cfg = fz.SearchConfig(elite_fraction=0.75, smoothing=1.0, min_std=0.01)
    u = np.zeros((4, fz.DIM))
    u[:, 0] = [0.1, 0.9, 0.3, 0.5]
    new_mean, _ = fz.cem_update(u, np.array([1.0, 5.0, 2.0, 3.0]), np.full(fz.DIM, 0.5),
                                np.full(fz.DIM, 0.3), cfg)
    assert new_mean[0] == pytest.approx(0.3, abs=1e-15)  # (0.1 + 0.3 + 0.5) / 3
    two, _ = fz.cem_update(u, np.array([1.0, math.inf, 2.0, math.inf]), np.full(fz.DIM, 0.5),
                           np.full(fz.DIM, 0.3), cfg)
    assert two[0] == pytest.approx(0.2, abs=1e-15)


def test_the_elite_among_tied_scores_is_the_first_drawn() -> None:
    """40 points, 5 distinct low scores and 35 tied at the cap: the elite (a quarter, 10) is the
    5 low ones and the first 5 tied ones in draw order (a stable sort: the result must not
    depend on the sort's algorithm)."""
    cfg = fz.SearchConfig(elite_fraction=0.25, smoothing=1.0, min_std=0.01)
    u = np.random.default_rng(9).random((40, fz.DIM))
    scores = np.full(40, fz.TTC_CAP_S)
    low = [3, 11, 19, 27, 35]
    scores[low] = [0.1, 0.2, 0.3, 0.4, 0.5]
    elite = low + [k for k in range(40) if k not in low][:5]
    new_mean, _ = fz.cem_update(u, scores, np.full(fz.DIM, 0.5), np.full(fz.DIM, 0.3), cfg)
    np.testing.assert_allclose(new_mean, u[elite].mean(axis=0), rtol=0, atol=1e-15)


def test_the_search_loop_by_hand() -> None:
    """Two CEM batches: the first uniform, the second from the update of the uniform prior
    (mean 0.5, std 1 / sqrt 12) with smoothing 0.5; the progress callback gets each batch's
    size; a wrong number of outcomes is refused by name."""
    cfg = fz.SearchConfig(method="cem", budget=10, batch=4, seed=5, smoothing=0.5)
    sizes = []
    res = fz.search(cfg, planted, sizes.append)
    assert sizes == [4, 4, 2]
    rng = np.random.default_rng(5)
    u1 = fz.draw(rng, 4, None, None)
    mean, std = fz.cem_update(u1, np.array([o.score for o in planted(u1)]),
                              np.full(fz.DIM, 0.5), np.full(fz.DIM, fz.uniform_std()), cfg)
    u2 = fz.draw(rng, 4, mean, std)
    mean, std = fz.cem_update(u2, np.array([o.score for o in planted(u2)]), mean, std, cfg)
    u3 = fz.draw(rng, 2, mean, std)  # the third batch from the second update, not the prior
    np.testing.assert_array_equal(res.u, np.concatenate([u1, u2, u3]))
    with pytest.raises(ValueError, match="the objective gave 3 outcomes for 4 points"):
        fz.search(cfg, lambda u: planted(u)[:3])


def test_summary_by_hand() -> None:
    cfg = fz.SearchConfig(method="random", budget=3, batch=3, seed=2, max_time_s=12.0,
                          brake_guard=False)
    res = _result(4, [fz.Outcome(2.0, False, 2.0, "", True, ""),
                      fz.Outcome(0.5, True, 0.5, "ttc", True, ""),
                      fz.Outcome(math.inf, False, math.nan, "", False, "boom")],
                  **dataclasses.asdict(cfg))
    s = fz.summary(res, "bc")
    assert s == {"policy": "bc", "method": "random", "seed": 2, "simulations": 3,
                 "first_failure": 2, "failures": 1, "avoidable": 2, "errors": 1,
                 "best_score": 0.5, "best_min_ttc_s": 0.5, "best_flag": "ttc", "best_sim": 2,
                 "best_spec": fz.decode(res.u[1], "bc", 12.0, False).to_json()}
    guarded = dataclasses.replace(res, config=dataclasses.replace(cfg, brake_guard=True))
    assert fz.summary(guarded, "bc")["best_spec"] == fz.decode(res.u[1], "bc", 12.0,
                                                               True).to_json()
    empty = fz.summary(fz.SearchResult(cfg, np.zeros((0, fz.DIM)), []), "bc")
    assert empty == {"policy": "bc", "method": "random", "seed": 2, "simulations": 0,
                     "first_failure": None, "failures": 0, "avoidable": 0, "errors": 0}


# ------------------------------------------------------- the search on a planted failure


TARGET = np.array([0.85, 0.1, 0.9, 0.2, 0.8, 0.7, 0.3, 0.9, 0.15, 0.6])


def planted(u: np.ndarray) -> list[fz.Outcome]:
    """A toy objective: the distance to a point; a failure within 0.25 of it (a ball of
    ~2e-6 of the box's volume: random sampling almost never lands there)."""
    d = np.linalg.norm(u - TARGET, axis=1)
    return [fz.Outcome(float(x), bool(x < 0.25)) for x in d]


def test_cem_finds_a_planted_failure_far_sooner_than_random() -> None:
    firsts = {}
    for method in fz.METHODS:
        runs = [fz.search(fz.SearchConfig(method=method, budget=1500, batch=50, seed=s,
                                          stop_at_failure=True), planted).first_failure
                for s in range(5)]
        firsts[method] = float(np.median([r if r is not None else math.inf for r in runs]))
    assert firsts["cem"] <= 600
    assert firsts["random"] == math.inf  # none within 1,500 simulations
    assert firsts["cem"] <= firsts["random"] / 5


def test_search_is_seeded_and_spends_its_budget() -> None:
    cfg = fz.SearchConfig(method="cem", budget=130, batch=50, seed=7)
    a, b = fz.search(cfg, planted), fz.search(cfg, planted)
    assert a.u.shape == (130, fz.DIM) and len(a.outcomes) == 130  # 50 + 50 + 30
    assert np.array_equal(a.u, b.u) and a.outcomes == b.outcomes
    other = fz.search(fz.SearchConfig(method="cem", budget=130, batch=50, seed=8), planted)
    assert not np.array_equal(a.u, other.u)
    # random and CEM share their first (uniform) batch: the comparison starts level
    r = fz.search(fz.SearchConfig(method="random", budget=130, batch=50, seed=7), planted)
    assert np.array_equal(r.u[:50], a.u[:50]) and not np.array_equal(r.u[50:], a.u[50:])
    assert np.all(np.diff(a.best_so_far) <= 0)


def test_stop_at_failure_ends_after_the_batch_of_the_first_failure() -> None:
    def fails_at_7(u: np.ndarray) -> list[fz.Outcome]:
        fails_at_7.n += len(u)
        return [fz.Outcome(1.0, fails_at_7.n - len(u) + k + 1 == 7) for k in range(len(u))]

    fails_at_7.n = 0
    res = fz.search(fz.SearchConfig(method="random", budget=100, batch=5, seed=0,
                                    stop_at_failure=True), fails_at_7)
    assert res.first_failure == 7 and len(res.outcomes) == 10


def test_table_round_trips(tmp_path) -> None:
    res = fz.search(fz.SearchConfig(method="cem", budget=12, batch=4, seed=1), planted)
    df = fz.table(res, "bc")
    df.to_csv(tmp_path / "e.csv", index=False)
    back = fz.read_table(tmp_path / "e.csv", res.config)
    assert np.allclose(back.u, res.u, rtol=0, atol=1e-15)
    assert [o.score for o in back.outcomes] == [o.score for o in res.outcomes]
    assert Task.from_json(json.loads(df["spec"].iloc[0])) == fz.decode(res.u[0], "bc")
    assert list(df["spec"]) == [json.dumps(fz.decode(x, "bc").to_json(), sort_keys=True)
                                for x in res.u]


def _same(a: fz.Outcome, b: fz.Outcome) -> bool:
    return all(x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))
               for x, y in zip(dataclasses.astuple(a), dataclasses.astuple(b), strict=True))


def test_every_outcome_field_round_trips_and_the_table_says_what_ran(tmp_path) -> None:
    """Failures, unavoidable runs, a missing TTC, flags and an error text with a comma come back
    as they went (cases found by mutation testing: only scores were compared); each row says
    which simulation it was, the scenario it decoded to (the config's time limit and guard) and
    the lowest score so far."""
    cfg = fz.SearchConfig(method="random", budget=4, batch=4, seed=0, max_time_s=12.0,
                          brake_guard=False)
    u = np.random.default_rng(3).random((5, fz.DIM))
    # an error's text is any string, also one pandas would read as missing by default ("NA")
    outcomes = [fz.Outcome(0.5, True, 0.5, "ttc", True, ""),
                fz.Outcome(math.inf, False, math.nan, "", False, "boom, with a comma"),
                fz.Outcome(3.0, False, 3.0, "", True, ""),
                fz.Outcome(1.0, True, 4.0, "lane_departure", True, ""),
                fz.Outcome(math.inf, False, math.nan, "", False, "NA")]
    res = fz.SearchResult(cfg, u, outcomes)
    df = fz.table(res, "bc")
    specs = [fz.decode(x, "bc", 12.0, False) for x in u]
    assert list(df["sim"]) == [1, 2, 3, 4, 5] and list(df.columns[:3]) == ["sim", "u0", "u1"]
    assert list(df["net"]) == [s.scenario.net for s in specs]
    assert list(df["leader_kind"]) == [s.scenario.leader_kind for s in specs]
    assert list(df["spec"]) == [json.dumps(s.to_json(), sort_keys=True) for s in specs]
    assert list(df["best_so_far"]) == [0.5] * 5
    df.to_csv(tmp_path / "e.csv", index=False)
    back = fz.read_table(tmp_path / "e.csv", cfg)
    assert back.config is cfg and np.allclose(back.u, u, rtol=0, atol=1e-15)
    assert len(back.outcomes) == 5
    assert all(_same(a, b) for a, b in zip(back.outcomes, outcomes, strict=True))
    # a table read with pandas' defaults (empty cells and "NA" as NaN): empty texts, not "nan"
    loose = fz.from_table(pd.read_csv(tmp_path / "e.csv"), cfg)
    assert [o.flag for o in loose.outcomes] == ["ttc", "", "", "lane_departure", ""]
    assert [o.error for o in loose.outcomes] == ["", "boom, with a comma", "", "", ""]
    empty = fz.from_table(fz.table(fz.SearchResult(cfg, np.zeros((0, fz.DIM)), []), "bc"), cfg)
    assert empty.u.shape == (0, fz.DIM) and empty.outcomes == []
    with pytest.raises(ValueError):  # points and outcomes of different lengths
        fz.table(fz.SearchResult(cfg, u, outcomes[:3]), "bc")


# ----------------------------------------------------------------------- real libsumo


@pytest.mark.sumo
def test_cli_smoke_in_libsumo_is_deterministic(tmp_path, capsys) -> None:
    """A tiny CEM search of the analytic planner in SUMO, twice, its batches in one simulation
    and split over two workers: the same scenarios and outcomes; its worst case is written as a spec and a sweep file; a rerun reads it back."""
    pytest.importorskip("libsumo")
    from fixtures_data import NGSIM_PAIRS, require_file

    require_file(NGSIM_PAIRS)  # the search box holds recorded NGSIM leaders
    from safeil_sumo import falsify

    args = ["--policy", "analytic", "--method", "cem", "--budget-sims", "6", "--batch", "3",
            "--seed", "2", "--max-time-s", "4", "--no-progress"]
    tables = []
    for name, workers in (("a", "1"), ("b", "2")):  # one simulation per batch, or two
        assert falsify.main([*args, "--out", str(tmp_path / name), "--workers", workers]) == 0
        tables.append(pd.read_csv(tmp_path / name / "evaluations.csv"))
    out = capsys.readouterr().out
    assert "first failure at simulation" in out and "rerun it: python -m safeil_sumo.sweep" in out
    a, b = tables
    assert len(a) == 6 and a["error"].isna().all()
    pd.testing.assert_frame_equal(a, b)
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["simulations"] == 6 and summary["avoidable"] == a["avoidable"].sum()
    if summary.get("best_spec"):
        spec = Task.from_json(json.loads((tmp_path / "a" / "worst.json").read_text()))
        assert spec == Task.from_json(summary["best_spec"])
        assert (tmp_path / "a" / "worst.toml").is_file()
    before = (tmp_path / "a" / "evaluations.csv").stat().st_mtime_ns
    assert falsify.main([*args, "--out", str(tmp_path / "a")]) == 0  # read back, not rerun
    assert (tmp_path / "a" / "evaluations.csv").stat().st_mtime_ns == before


def test_cli_refuses_bad_options(capsys) -> None:
    from safeil_sumo import falsify

    for bad in (["--method", "bayes"], ["--budget-sims", "0"], ["--batch", "-1"],
                ["--workers", "0"], ["--workers", "2", "--scheduler", "tcp://h:1"]):
        with pytest.raises(SystemExit) as exit_:
            falsify.parse_args(bad)
        assert exit_.value.code == 2


def test_a_finished_search_is_reused_only_for_the_same_weights(tmp_path, monkeypatch) -> None:
    """run_or_load reads a finished search back for the same policy weights, and searches
    again when the policy's file changed (a retrained model must not inherit the old model's
    failures). The planted objective stands in for SUMO: the point is the cache."""
    import shutil

    from safeil_sumo.planners import registry as planner_registry

    weights = tmp_path / "m.safetensors"
    shutil.copy(planner_registry.policy_file("bc"), weights)
    shutil.copy(planner_registry.policy_file("bc").with_suffix(".json"),
                weights.with_suffix(".json"))
    calls, made, real_search = [], [], fz.search

    def counted(config, objective, on_batch):
        calls.append((config, objective))
        return real_search(config, objective, on_batch)

    def objective(*args, **kwargs):
        made.append((args, kwargs))
        return planted

    monkeypatch.setattr(fz, "search", counted)
    monkeypatch.setattr(fz, "closed_loop_objective", objective)
    cfg = fz.SearchConfig(method="random", budget=20, batch=10, seed=0, max_time_s=12.0,
                          brake_guard=False)
    folder = tmp_path / "studies" / "m"  # made with its parents
    first = fz.run_or_load(str(weights), cfg, folder, workers=3, scheduler="tcp://h:1")
    # searched with the planner's objective at the config's time limit and guard setting
    assert made == [((str(weights), 12.0, False), {"tasks_dir": folder / "tasks", "workers": 3,
                                                    "scheduler": "tcp://h:1"})]
    assert calls == [(cfg, planted)]
    assert sorted(p.name for p in folder.iterdir()) == ["config.json", "evaluations.csv"]
    # the table as written: no index column, each row's spec names the planner searched
    written = pd.read_csv(folder / "evaluations.csv")
    assert list(written.columns) == list(fz.table(first, str(weights)).columns)
    assert {json.loads(s)["policy"] for s in written["spec"]} == {str(weights)}
    assert json.loads((folder / "config.json").read_text()) == {
        "policy": str(weights), "policy_fingerprint": planner_registry.fingerprint(str(weights)),
        **dataclasses.asdict(cfg)}
    again = fz.run_or_load(str(weights), cfg, folder)
    assert len(calls) == 1 and np.array_equal(first.scores, again.scores)
    assert again.config == cfg
    pd.testing.assert_frame_equal(fz.table(again, "m"), fz.table(first, "m"))
    for suffix in (".safetensors", ".json"):  # retrained: other weights in the same file
        shutil.copy(planner_registry.policy_file("safeil_paper").with_suffix(suffix),
                    weights.with_suffix(suffix))
    fz.run_or_load(str(weights), cfg, folder)
    assert len(calls) == 2


def test_results_section_from_toy_searches(tmp_path, monkeypatch) -> None:
    """``results --only falsify``'s table, curves, worst cases and README lines (searches on
    the planted objective instead of SUMO)."""
    from safeil_sumo.studies import falsification

    study = (fz.StudyRun("bc", 300, 50, (0, 1)), fz.StudyRun("safeil", 200, 50, (0,)))
    monkeypatch.setattr(fz, "STUDY", study)
    monkeypatch.setattr(fz, "run_or_load",
                        lambda policy, cfg, folder, progress=False: fz.search(cfg, planted))
    facts = json.loads(json.dumps(falsification.falsify(tmp_path, tmp_path / "work")))
    rows = pd.read_csv(tmp_path / "falsify.csv")
    assert len(rows) == 6 and set(rows["method"]) == {"cem", "random"}
    assert (tmp_path / "falsify.png").stat().st_size > 0
    assert set(facts["worst"]) == {"bc", "safeil"}
    toml = tmp_path / facts["worst"]["bc"]["toml"]
    assert toml.is_file() and (toml.with_suffix(".json")).is_file()
    text = "\n".join(falsification.falsify_readme(facts))
    assert "## Falsification" in text and "falsify.png" in text
    assert "python -m safeil_sumo.sweep --config results/falsify/worst_bc.toml" in text
