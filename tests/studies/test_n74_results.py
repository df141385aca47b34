"""The n74 drives section: exact Poisson intervals, time gaps, flag events, the comparison with
the synthetic humans (pure, hand-computed), one real libsumo drive task, and the section itself
(quick) keeping the other sections of results/."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import ks_2samp, poisson

from safeil_sumo.experiments import n74_drives as nd
from safeil_sumo.sim.rollout_log import drive_stats

REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------- Garwood interval


def test_garwood_interval_by_hand():
    # k = 0: P(X = 0; mu) = e^-mu = 0.025 -> mu = ln 40
    assert nd.garwood_interval(0, 1.0) == (0.0, pytest.approx(math.log(40.0), rel=1e-9))
    # k = 1: lower solves P(X >= 1) = 1 - e^-mu = 0.025 -> mu = -ln 0.975
    low, high = nd.garwood_interval(1, 1.0)
    assert low == pytest.approx(-math.log(0.975), rel=1e-9)
    # upper solves P(X <= 1) = e^-mu (1 + mu) = 0.025
    assert math.exp(-high) * (1.0 + high) == pytest.approx(0.025, rel=1e-9)
    assert high == pytest.approx(5.5716, abs=1e-4)
    # tabulated exact Poisson limits (Garwood 1936)
    assert nd.garwood_interval(2, 1.0) == (pytest.approx(0.2422, abs=1e-4),
                                           pytest.approx(7.2247, abs=1e-4))
    assert nd.garwood_interval(10, 1.0) == (pytest.approx(4.7954, abs=1e-4),
                                            pytest.approx(18.3904, abs=1e-4))
    # a rate over an exposure: 3 events in 250 km = 1.2 per 100 km
    lo, hi = nd.garwood_interval(3, 2.5)
    lo1, hi1 = nd.garwood_interval(3, 1.0)
    assert (lo, hi) == (pytest.approx(lo1 / 2.5), pytest.approx(hi1 / 2.5))


@pytest.mark.parametrize("k, exposure, conf", [(-1, 1.0, 0.95), (1.5, 1.0, 0.95),
                                               (1, 0.0, 0.95), (1, math.inf, 0.95),
                                               (1, 1.0, 1.0)])
def test_garwood_interval_refuses_bad_input(k, exposure, conf):
    with pytest.raises(ValueError):
        nd.garwood_interval(k, exposure, conf)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 500), st.floats(0.05, 0.5))
def test_garwood_limits_are_where_the_poisson_tails_reach_alpha_half(k, alpha):
    low, high = nd.garwood_interval(k, 1.0, 1.0 - alpha)
    assert low <= k <= high
    assert poisson.cdf(k, high) == pytest.approx(alpha / 2, rel=1e-6)
    if k:
        assert poisson.sf(k - 1, low) == pytest.approx(alpha / 2, rel=1e-6)


def test_rates_per_100km_with_intervals():
    drives = pd.DataFrame({
        "policy": ["a", "a", "b"], "km_driven": [30.0, 20.0, 10.0],
        "ttc_events": [1, 0, 0], "lane_departure_events": [0, 0, 2],
        "collision_events": [0, 0, 0], "min_ttc_s": [3.0, 0.8, 9.0],
        "leaders_met": [4, 5, 1], "cut_ins_met": [1, 0, 0],
        "end_reason": ["completed", "completed", "collision"]})
    r = nd.rates(drives).set_index("policy")
    assert r.loc["a", "km"] == 50.0 and r.loc["a", "drives"] == 2
    assert r.loc["a", "ttc_per_100km"] == pytest.approx(2.0)
    lo, hi = nd.garwood_interval(1, 0.5)
    assert (r.loc["a", "ttc_lo"], r.loc["a", "ttc_hi"]) == (pytest.approx(lo), pytest.approx(hi))
    assert r.loc["a", "min_ttc_s"] == 0.8 and r.loc["a", "leaders_met"] == 9
    assert r.loc["b", "lane_departure_per_100km"] == pytest.approx(20.0)
    assert r.loc["b", "completed_drives"] == 0 and r.loc["a", "completed_drives"] == 2


# ------------------------------------------------------------------------------- time gaps


def test_time_gaps_follow_only_and_resample():
    log = pd.DataFrame({"gap": [30.0, math.inf, 200.0, 30.0, math.nan, 15.0, -1.0],
                        "v": [30.0, 30.0, 30.0, 2.0, 15.0, 15.0, 20.0]})
    # no leader (inf/nan), beyond radar range, too slow, negative gap: left out
    assert nd.time_gaps(log, step_s=0.1).tolist() == [1.0, 1.0]
    # 100 Hz log -> every 10th row at 10 Hz
    dense = pd.DataFrame({"gap": np.arange(100.0) + 1.0, "v": np.full(100, 10.0)})
    np.testing.assert_allclose(nd.time_gaps(dense, step_s=0.01), (np.arange(0, 100, 10) + 1) / 10)


def test_human_time_gaps_from_the_drive_schema():
    drives = pd.DataFrame({"recording_id": ["h0", "h0", "h1", "h1"],
                           "lead_x": [25.0, math.nan, 40.0, 160.0],
                           "v_x": [25.0, 25.0, 20.0, 20.0], "lane_index": [0.0, 0.0, 1.0, 1.0]})
    h = nd.human_time_gaps(drives)
    assert h["recording_id"].tolist() == ["h0", "h1"]
    assert h["time_gap_s"].tolist() == [1.0, 2.0] and h["lane_index"].tolist() == [0.0, 1.0]


def test_ks_distance_by_hand_and_against_scipy():
    assert nd.ks_distance(np.array([1.0, 2, 3]), np.array([3.0, 2, 1])) == 0.0
    assert nd.ks_distance(np.array([1.0, 2]), np.array([5.0, 6])) == 1.0
    assert nd.ks_distance(np.array([1.0, 2]), np.array([2.0, 3])) == 0.5
    rng = np.random.default_rng(0)
    a, b = rng.normal(0, 1, 300), rng.normal(0.3, 1.2, 500)
    assert nd.ks_distance(a, b) == pytest.approx(ks_2samp(a, b).statistic, abs=1e-12)
    assert math.isnan(nd.ks_distance(np.zeros(0), b))


def test_median_difference_bootstrap_is_seeded_and_resamples_groups():
    rng = np.random.default_rng(1)
    a = [rng.normal(2.0, 0.2, 50) + rng.normal(0, 0.1) for _ in range(6)]
    b = [rng.normal(1.5, 0.2, 80) + rng.normal(0, 0.1) for _ in range(16)]
    d, lo, hi = nd.median_difference_ci(a, b, seed=3, reps=300)
    assert d == pytest.approx(np.median(np.concatenate(a)) - np.median(np.concatenate(b)))
    assert lo < d < hi and lo > 0.2 and hi < 0.8
    assert nd.median_difference_ci(a, b, seed=3, reps=300) == (d, lo, hi)
    # one sample per group and identical groups: no spread at all
    same = [np.array([1.0])] * 5
    assert nd.median_difference_ci(same, same, seed=0, reps=50) == (0.0, 0.0, 0.0)


def test_compare_time_gaps_rows():
    table = nd.compare_time_gaps({"p": [np.array([1.0, 2.0]), np.array([3.0])]},
                                 [np.array([1.0, 1.0, 1.0])], seed=0).set_index("who")
    assert table.loc["p", "samples"] == 3 and table.loc["p", "groups"] == 2
    assert table.loc["p", "q50_s"] == 2.0 and table.loc["p", "median_diff_s"] == 1.0
    assert table.loc["p", "ks_to_humans"] == pytest.approx(2 / 3)  # at 1 s: 1/3 vs 1
    assert table.loc[nd.HUMANS, "share_below_1s"] == 0.0
    assert math.isnan(table.loc[nd.HUMANS, "ks_to_humans"])


# ----------------------------------------------------------------------------- flag events


def _flag_log(ttc, lane, coll):
    n = len(ttc)
    return pd.DataFrame({"t": 0.01 * (np.arange(n) + 1), "front_x": np.arange(n) * 2.0,
                         "front_y": np.zeros(n), "s": 100.0 + np.arange(n) * 2.0,
                         "ttc_flag": ttc, "lane_departure": lane, "collision": coll})


def test_flag_events_locate_each_run_start():
    log = _flag_log([True, True, False, True], [False, False, True, True],
                    [False, False, False, False])
    events = nd.flag_events(log)
    assert [(e["kind"], e["x"], e["s_m"]) for e in events] == [
        ("ttc", 0.0, 100.0), ("lane_departure", 4.0, 104.0), ("ttc", 6.0, 106.0)]


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans(), st.booleans()), min_size=1,
                max_size=60))
def test_flag_events_count_as_drive_stats(rows):
    ttc, lane, coll = (list(c) for c in zip(*rows, strict=True))
    log = _flag_log(ttc, lane, coll)
    events = pd.DataFrame(nd.flag_events(log), columns=["kind", "t_s", "x", "y", "s_m"])
    stats = drive_stats(log, path_start_s=100.0)
    for kind, _, _ in nd.FLAG_KINDS:
        assert (events["kind"] == kind).sum() == stats[f"{kind}_events"]
    assert events["t_s"].is_monotonic_increasing


# ------------------------------------------------------------------- a population of drivers

ESTIMATES = {"d": 4.0, "a": 0.5, "c": 2.5, "b": 1.5}  # [s] per training maneuver


def test_draw_settings_by_hand():
    """As many drives as estimates: one per stratum, i.e. every estimate once, clipped to the
    settable 0.8-3.5 s; twice as many drives: every estimate twice (strata of 1/8 each)."""
    from safeil_sumo.learn.style import SETTING_RANGE_S

    assert SETTING_RANGE_S == (0.8, 3.5)
    assert sorted(nd.draw_settings(ESTIMATES, 0, 4)) == [0.8, 1.5, 2.5, 3.5]
    assert sorted(nd.draw_settings(ESTIMATES, 3, 8)) == [0.8, 0.8, 1.5, 1.5, 2.5, 2.5, 3.5, 3.5]
    low, high = sorted(nd.draw_settings(ESTIMATES, 0, 2))  # strata [0, 1/2) and [1/2, 1)
    assert low in (0.8, 1.5) and high in (2.5, 3.5)
    assert nd.draw_settings({"x": 9.0}, 0, 3) == [3.5, 3.5, 3.5]


def test_draw_settings_is_seeded_and_ignores_the_estimates_order():
    draw = nd.draw_settings(ESTIMATES, 5, 12)
    assert draw == nd.draw_settings(ESTIMATES, 5, 12)
    assert draw == nd.draw_settings(dict(sorted(ESTIMATES.items())), 5, 12)
    orders = {tuple(nd.draw_settings(ESTIMATES, seed, 12)) for seed in range(5)}
    assert len(orders) > 1  # the master seed changes which drive gets which setting
    many = nd.draw_settings({str(k): 0.3 * k for k in range(20)}, 1, 37)
    assert all(0.8 <= t <= 3.5 for t in many)
    with pytest.raises(ValueError, match="no time-gap estimates"):
        nd.draw_settings({}, 0, 3)
    with pytest.raises(ValueError, match="n >= 1"):
        nd.draw_settings(ESTIMATES, 0, 0)


def test_population_drives_share_the_other_rows_seeds_then_new_ones():
    # 3 stretches x 6 drives, the first 2 per stretch those of drive_tasks (indexes j * 2 + i)
    idx = [[nd.population_index(j, i, 3, 6, 2) for i in range(6)] for j in range(3)]
    assert idx == [[0, 1, 6, 7, 8, 9], [2, 3, 10, 11, 12, 13], [4, 5, 14, 15, 16, 17]]
    base = {(t.scenario.index, t.scenario.from_km)
            for t in nd.drive_tasks(("idm",), 0, nd.STRETCHES_KM, 2)}
    pop = {(t.scenario.index, t.scenario.from_km)
           for t in nd.population_tasks(ESTIMATES, ("idm",), 0)}
    assert base < pop and len(pop) == 18
    with pytest.raises(ValueError):
        nd.population_index(0, 6, 3, 6, 2)


def test_population_tasks_carry_their_setting():
    from safeil_sumo.experiments.sweep_executor import task_id
    from safeil_sumo.scenarios.spec import Task

    stretches = ((1.0, 2.0), (3.0, 4.0))
    specs = nd.population_tasks(ESTIMATES, ("safeil", "idm"), 0, stretches, per=4, base=2)
    assert len(specs) == 16
    settings_ = nd.draw_settings(ESTIMATES, 0, 8)
    assert sorted(settings_) == [0.8, 0.8, 1.5, 1.5, 2.5, 2.5, 3.5, 3.5]
    by = {}
    for task in specs:
        s, gap = task.scenario, task.planner.time_gap_s
        assert gap == settings_[s.index] and s.traffic == nd.TRAFFIC
        assert Task.from_json(task.to_json()) == task  # a task file
        by.setdefault(task.planner.policy, []).append((s.index, s.from_km, s.to_km, gap))
    assert by["safeil"] == by["idm"]  # the same drivers on the same traffic
    assert sorted(i for i, *_ in by["idm"]) == list(range(8))
    default = nd.drive_tasks(("idm",), 0, stretches, 2)[0]
    assert default.scenario == specs[8].scenario
    assert task_id(default) != task_id(specs[8])  # its own task, never the default row's cache
    assert nd.row_name("idm", None) == "idm" and nd.row_name("idm", math.nan) == "idm"
    assert nd.row_name("safeil", 1.2) == "safeil_population"


def _real_tuples(tmp_path: Path) -> tuple[Path, ...]:
    """The real tuple sets the shipped models trained on: ``data/`` where built, else built here
    from the shared data (a fresh clone has no ``data/``; a few seconds)."""
    from fixtures_data import NGSIM_PAIRS, OPENACC_DIR, require_file
    from scripts import load_training_script

    from safeil_sumo.studies import n74_traffic

    if all(p.is_file() for p in n74_traffic.TRAINING_TUPLES):
        return n74_traffic.TRAINING_TUPLES
    require_file(NGSIM_PAIRS)
    require_file(OPENACC_DIR / "JRC-VC_280219_part2.csv.gz")
    build_real_datasets = load_training_script("build_real_datasets")
    assert build_real_datasets.main(["--data-dir", str(NGSIM_PAIRS.parents[1]),
                                     "--out", str(tmp_path)]) == 0
    return tuple(tmp_path / p.name for p in n74_traffic.TRAINING_TUPLES)


def test_training_settings_are_the_shipped_safeils_training_estimates(tmp_path):
    """The real tuples the shipped safeil was fine-tuned on: the median of the estimates is its
    default setting, their spread its style input's scaling."""
    from safeil_sumo.learn.checkpoint import held_out_maneuvers
    from safeil_sumo.studies.shared import SHIPPED_SAFEIL

    meta = json.loads(SHIPPED_SAFEIL.read_text())
    ckpt = SHIPPED_SAFEIL.with_suffix(".safetensors")
    est = nd.training_settings(ckpt, _real_tuples(tmp_path))
    assert not set(est) & set(held_out_maneuvers(ckpt))
    values = np.array(list(est.values()))
    assert np.median(values) == meta["style_default"]["time_gap_s"]
    assert np.std(values) == pytest.approx(meta["scaling"]["feature_std"][9], rel=1e-6)


# ------------------------------------------------------------------ real drives (libsumo)


def test_drive_tasks_share_seeds_across_planners():
    tasks = nd.drive_tasks(("safeil", "idm"), 0, ((1.0, 2.0), (3.0, 4.0)), 2)
    assert len(tasks) == 8
    by = {}
    for t in tasks:
        s = t.scenario
        by.setdefault(t.planner.policy, []).append((s.index, s.from_km, s.to_km, s.traffic))
    assert by["safeil"] == by["idm"]
    assert by["idm"] == [(0, 1.0, 2.0, "default"), (1, 1.0, 2.0, "default"),
                         (2, 3.0, 4.0, "default"), (3, 3.0, 4.0, "default")]


@pytest.mark.sumo
def test_drive_task_keeps_time_gaps_and_flags_of_a_traffic_drive():
    """Real libsumo: half a kilometre among dense traffic, the sweep's task record."""
    spec = nd.drive_tasks(("analytic",), 0, ((4.0, 4.5),), 1, traffic="dense")[0]
    record = nd.drive_task(spec)
    assert record["status"] == "ok", record.get("error")
    assert record["leader_label"] == "traffic" and math.isnan(record["leader_speed0_mps"])
    assert record["km_driven"] == pytest.approx(0.5, abs=0.02)
    gaps = np.asarray(record["time_gaps_s"])
    assert len(gaps) > 50 and np.all(gaps > 0)
    assert isinstance(record["flag_events"], list)
    json.dumps(record)  # a task file


@pytest.mark.sumo
def test_section_quick_keeps_the_other_sections(tmp_path, monkeypatch):
    """``--only n74 --quick`` adds its section to results/ without dropping the others'."""
    from safeil_sumo import results
    from safeil_sumo.studies import n74_traffic

    out = tmp_path / "results"
    out.mkdir()
    shutil.copyfile(REPO / "results" / "facts.json", out / "facts.json")
    before = json.loads((out / "facts.json").read_text())
    drives = pd.DataFrame({"recording_id": ["h0"] * 3 + ["h1"] * 3,
                           "lead_x": [30.0, 40.0, math.nan, 20.0, 25.0, 30.0],
                           "v_x": [30.0] * 6, "lane_index": [0.0] * 6})
    drives.to_parquet(tmp_path / "drives.parquet")
    monkeypatch.setattr(n74_traffic, "SYNTHETIC_DRIVES", tmp_path / "drives.parquet")
    monkeypatch.setattr(nd, "PLANNERS", ("analytic", "idm"))
    monkeypatch.setattr(n74_traffic, "QUICK_STRETCH_KM", (4.0, 4.3))
    monkeypatch.setattr(nd, "POPULATION_PLANNERS", ("idm",))
    monkeypatch.setattr(nd, "training_settings", lambda *a: {"m0": 1.2, "m1": 9.0})
    assert results.main(["--only", "n74", "--quick", "--out", str(out), "--work",
                         str(tmp_path / "work"), "--workers", "1"]) == 0
    facts = json.loads((out / "facts.json").read_text())
    assert set(before) <= set(facts)
    assert facts["safety"] == before["safety"] and "n74" in facts
    # the run-wide args and commit stay those of the full run; n74's own are per section
    assert facts["args"] == before["args"] and facts["git_commit"] == before["git_commit"]
    assert set(facts["section_git_commit"]) == set(before.get("section_git_commit", {})) | {"n74"}
    # the paper's figures on the front page, the studies (n74's among them) beside it
    assert "## Safety on the 500 m-radius track" in (out / "README.md").read_text()
    assert "## N74 drives" in (out / "studies.md").read_text()
    rates = pd.read_csv(out / "n74_rates.csv")
    assert rates["policy"].tolist() == ["analytic", "idm", "idm_population"]
    gaps = pd.read_csv(out / "n74_time_gap.csv").set_index("who")
    assert gaps.loc[nd.HUMANS, "samples"] == 5
    assert gaps.loc["idm_population", "groups"] == 1  # its row (0.3 km may hold no sample)
    drives = pd.read_csv(out / "n74_drives.csv").set_index("policy")
    # one drive (--quick) draws one of the two estimates, clipped to 0.8-3.5 s
    assert drives.loc["idm_population", "time_gap_s"] == nd.draw_settings(
        {"m0": 1.2, "m1": 9.0}, 0, 1)[0]
    assert drives.loc["idm_population", "time_gap_s"] in (1.2, 3.5)
    assert math.isnan(drives.loc["idm", "time_gap_s"])
    assert facts["n74"]["design"]["population"]["drives_per_planner"] == 1
    assert "A population of drivers" in (out / "studies.md").read_text()
    for name in ("n74_flag_map.png", "n74_time_gap.png", "n74_drives.csv", "n74_flags.csv"):
        assert (out / name).stat().st_size > 0


@pytest.mark.sumo
def test_run_on_n74_writes_the_flag_map(tmp_path, capsys):
    """Real libsumo: ``run --net n74`` puts flag_map.png beside its other plots."""
    from safeil_sumo.run import main

    out = tmp_path / "run"
    assert main(["--net", "n74", "--from-km", "0.2", "--to-km", "0.5", "--traffic", "dense",
                 "--policy", "analytic", "--scenarios", "1", "--out", str(out)]) == 0, \
        capsys.readouterr().err
    assert (out / "flag_map.png").stat().st_size > 10_000
    assert (out / "trajectory.png").is_file()


def test_median_difference_without_samples_is_nan():
    empty = [np.zeros(0)]
    assert all(math.isnan(v) for v in nd.median_difference_ci(empty, [np.ones(3)], seed=0))
    d, _, _ = nd.median_difference_ci([np.zeros(0), np.full(3, 2.0)], [np.ones(3)], seed=0)
    assert d == 1.0
