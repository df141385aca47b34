"""training/leave_one_driver_out.py: its summary of the left-out drivers' replays, by hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scripts import load_training_script

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def lodo():
    return load_training_script("leave_one_driver_out")


def test_summary_by_hand(lodo) -> None:
    """Per source and planner (the fold's checkpoint and IDM file named by their role): gap
    RMSE median / mean / worst over the maneuvers, flags beyond the human's, collisions (flag OR
    end reason, each run once), runs ended early; per driver the mean; failed runs left out."""
    runs = pd.DataFrame({
        "status": ["ok"] * 6 + ["failed"],
        "source": ["openacc"] * 4 + ["ngsim"] * 3,
        "driver": ["openacc/f2", "openacc/f2", "openacc/f3", "openacc/f2", "ngsim/7",
                   "ngsim/7", "ngsim/7"],
        "policy": ["data/lodo/fold0/safeil.safetensors"] * 3 + ["data/lodo/fold0/idm.json"]
        + ["constant_speed", "data/lodo/fold1/safeil.safetensors", "constant_speed"],
        "rmse_gap": [2.0, 4.0, 9.0, 5.0, 30.0, 3.0, 99.0],
        "rmspe_gap": [0.1, 0.2, 0.3, 0.2, 1.0, 0.1, 9.0],
        "bias_headway": [0.5, -0.1, 0.2, 0.0, 3.0, 0.0, 9.0],
        "flag": ["", "ttc", "", "", "collision", "", "collision"],
        "human_flag": ["", "ttc", "", "", "", "", ""],
        "end_reason": ["timeout", "timeout", "timeout", "timeout", "timeout", "timeout",
                       "collision"],
        "coverage": [1.0, 1.0, 1.0, 1.0, 0.4, 1.0, 0.1],
    })
    summary, per_driver = lodo.summarise(runs)
    s = summary.set_index(["source", "policy"])
    row = s.loc[("openacc", "safeil (fold)")]
    assert (row["maneuvers"], row["drivers"]) == (3, 2)
    assert (row["gap_rmse_median_m"], row["gap_rmse_mean_m"], row["gap_rmse_max_m"]) == \
        (4.0, 5.0, 9.0)
    assert row["spacing_rmspe_median"] == pytest.approx(0.2)
    assert row["time_gap_error_median_s"] == pytest.approx(0.2)
    assert (row["flags"], row["flags_beyond_human"], row["collisions"]) == (1, 0, 0)
    idm = s.loc[("openacc", "idm (fold)")]
    assert (idm["maneuvers"], idm["gap_rmse_mean_m"]) == (1, 5.0)
    cs = s.loc[("ngsim", "constant_speed")]  # the failed run (99 m) is left out
    assert (cs["maneuvers"], cs["gap_rmse_max_m"], cs["collisions"], cs["ended_early"]) == \
        (1, 30.0, 1, 1)
    d = per_driver.set_index(["driver", "policy"])
    assert d.loc[("openacc/f2", "safeil (fold)"), "gap_rmse_mean_m"] == 3.0
    assert d.loc[("openacc/f2", "safeil (fold)"), "maneuvers"] == 2
    text = lodo.markdown(summary, per_driver)
    assert "| openacc | safeil (fold) | 3 (2) | 4.00 / 5.00 / 9.0 |" in text
    # f2: safeil 3.0 <= idm 5.0; f3 has no IDM run: compared where both exist
    assert "openacc: `safeil` (fold) at or below the fold IDM's mean gap RMSE for 1 of 1 " in text
    assert np.isfinite(summary["gap_rmse_mean_m"]).all()


def test_adaptation_bound_summary_by_hand() -> None:
    """training/adaptation_bound.py: the oracle keeps each maneuver's best setting (chosen on
    its own scored seconds); one setting for all is the mean per setting; the adapted rows'
    mean and median are their own."""
    bound = load_training_script("adaptation_bound")
    settings = pd.DataFrame({
        "maneuver_id": ["a", "a", "b", "b"], "time_gap_s": [1.0, 2.0, 1.0, 2.0],
        "gap_rmse_m": [4.0, 10.0, 9.0, 3.0]})
    adapted = pd.DataFrame({"maneuver_id": ["a", "b"], "gap_rmse_m": [5.0, 8.0],
                            "time_gap_s": [1.2, 1.4]})
    text = bound.summary(settings, adapted)
    assert "in hindsight): mean 3.50, median 3.50" in text  # min(4, 10), min(9, 3)
    assert "first seconds): mean 6.50, median 6.50" in text
    assert "1 s 6.50, 2 s 6.50" in text
    assert "a: 1 / 1.20, nan" in text and "b: 2 / 1.40, nan" in text
    lined = bound.summary(settings, adapted.assign(standstill_m=[-5.0, 2.5]))
    assert "a: 1 / 1.20, -5.0" in lined and "b: 2 / 1.40, 2.5" in lined
    assert "two numbers" not in lined  # one standstill distance: no second oracle


def test_adaptation_bound_two_number_oracle_by_hand() -> None:
    """With standstill distances besides 0, the one-number oracle keeps to s0 = 0 and the
    two-number oracle takes each maneuver's best (T, s0) of the whole grid."""
    bound = load_training_script("adaptation_bound")
    settings = pd.DataFrame({
        "maneuver_id": ["a", "a", "a", "b", "b", "b"],
        "time_gap_s": [1.0, 2.0, 1.0, 1.0, 2.0, 2.0],
        "standstill_m": [0.0, 0.0, 10.0, 0.0, 0.0, -10.0],
        "gap_rmse_m": [4.0, 10.0, 1.0, 9.0, 3.0, 5.0]})
    adapted = pd.DataFrame({"maneuver_id": ["a", "b"], "gap_rmse_m": [5.0, 8.0],
                            "time_gap_s": [1.2, 1.4]})
    text = bound.summary(settings, adapted)
    assert "in hindsight): mean 3.50, median 3.50" in text  # min(4, 10), min(9, 3): s0 = 0
    assert "per maneuver, in hindsight): mean 2.00, median 2.00" in text  # min(1, ...), 3
    assert "a (1, 10), b (2, 0)" in text


def test_adaptation_curve_by_hand() -> None:
    """training/adaptation_bound.py's curve: the setting the replay's adaptation would give after
    S seconds (the driver's median time gap there shrunk towards the default, clipped; the
    default without a following sample), each maneuver's error read off its grid by linear
    interpolation, then mean and median over the maneuvers."""
    bound = load_training_script("adaptation_bound")
    t = np.round(np.arange(301) * 0.1, 10)  # 30 s at 10 Hz
    early = t <= 5.0
    # a: 1.2 s for its first 5 s (51 samples), then 2.0 s (250); b: below 5 m/s (not
    # following) for 5 s, then 1.5 s
    v_b = np.where(early, 3.0, 20.0)
    a = 20.0 * np.where(early, 1.2, 2.0)
    rows = pd.DataFrame({
        "maneuver_id": ["a"] * 301 + ["b"] * 301 + ["c"] * 301,
        "time": np.concatenate([t, t + 100.0, t]),
        "v_x": np.concatenate([np.full(301, 20.0), v_b, np.full(301, 20.0)]),
        "lead_x": np.concatenate([a, v_b * 1.5, a])})
    settings = pd.DataFrame({
        "maneuver_id": ["a", "a", "b", "b", "c", "c"],
        "time_gap_s": [1.0, 2.0, 1.0, 2.0, 1.0, 2.0],
        "gap_rmse_m": [4.0, 10.0, 9.0, 3.0, 1.0, 1.0]})
    curve = bound.adaptation_curve(rows, settings, {"a": 1.6, "b": 1.6, "c": 1.6},
                                   observed=(5.0, 30.0))
    # the settings: each driver's median shrunk towards the default 1.6 s by the weight of the
    # seconds of following seen (style.adapted_time_gap, tested by hand in test_style)
    from safeil_sumo.learn.style import TimeGapPrior

    def shrunk(own_s: float, seen_s: float) -> float:
        w = TimeGapPrior(1.6).weight(seen_s)
        return 1.6 ** (1 - w) * own_s ** w

    a5, a30, b30 = shrunk(1.2, 5.1), shrunk(2.0, 30.1), shrunk(1.5, 25.0)
    assert 1.2 < a5 < 1.6 and 1.6 < a30 < 2.0 and 1.5 < b30 < 1.6
    # 5 s: a -> 4 + 6 (a5 - 1); b none -> the default 1.6 -> 9 - 0.6 * 6 = 5.4; c 1
    # 30 s: a -> 4 + 6 (a30 - 1); b -> 9 - 6 (b30 - 1); c 1
    at5 = [4 + 6 * (a5 - 1), 5.4, 1.0]
    at30 = [4 + 6 * (a30 - 1), 9 - 6 * (b30 - 1), 1.0]
    assert curve["observed_s"].tolist() == [5.0, 30.0]
    assert curve["gap_rmse_mean_m"].tolist() == pytest.approx([np.mean(at5), np.mean(at30)])
    assert curve["gap_rmse_median_m"].tolist() == pytest.approx([np.median(at5),
                                                                 np.median(at30)])
    # a setting below the trained range is clipped to it; the grid's ends hold beyond it
    slow = rows[rows["maneuver_id"] == "a"].assign(lead_x=10.0).reset_index(drop=True)
    assert bound.setting_from_first(slow, 60.0, 1.6) == 0.8  # 0.5 s -> 0.54 s -> 0.8 s
    errors = pd.Series([4.0, 10.0], index=[1.0, 2.0])
    assert bound.read_off(errors, 0.8) == 4.0 and bound.read_off(errors, 3.0) == 10.0
    # whose safeil a row's label names: fold k's, or the shipped one (ZalaZone)
    assert bound.planner_of(2) == REPO / "data" / "lodo" / "fold2" / "safeil.safetensors"
    assert bound.planner_of("shipped") == REPO / "safeil_sumo" / "models" / "safeil.safetensors"


def test_a_cached_replay_is_reused_only_with_the_same_planner_files(lodo, tmp_path,
                                                                    monkeypatch) -> None:
    """A fold's replay folder is reused when its stamp names the very planners (their
    fingerprints) the fold has now; a retrained planner replays again. The replay command itself
    is stood in for: the point is the cache, not SUMO."""
    fold = tmp_path / "fold0"
    fold.mkdir()
    (fold / "drivers.json").write_text('["openacc/f2"]')
    for name in ("safeil.safetensors", "safeil.json", "idm.json"):
        (fold / name).write_text(name)
    m = "JRC-VC_280219_part2_f2#0"
    monkeypatch.setattr(lodo, "held_out_maneuvers", lambda drivers: {"openacc": [m], "ngsim": []})
    calls = []

    def fake_run(cmd, log):  # writes the table replay would: one run of the maneuver
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"maneuver_id": [m], "policy": ["idm"], "rmse_gap": [1.0]}).to_csv(
            out / "windows.csv", index=False)
        calls.append(out.name)
        adapt[out.name] = float(cmd[cmd.index("--adapt-first-s") + 1]) \
            if "--adapt-first-s" in cmd else None

    adapt: dict[str, float | None] = {}
    monkeypatch.setattr(lodo, "_run", fake_run)
    first = lodo.replay_fold(0, fold, workers=1)
    looks = [f"replay_openacc_adapted{look:g}" for look in lodo.LOOKS_S]
    assert sorted(calls) == sorted(["replay_openacc", "replay_openacc_adapted", *looks])
    assert set(first["source"]) == {"openacc", "openacc (adapted)", *(
        f"openacc (adapted {look:g} s)" for look in lodo.LOOKS_S)}
    assert adapt == {"replay_openacc": None, "replay_openacc_adapted": lodo.ADAPT_S,
                     **dict(zip(looks, lodo.LOOKS_S, strict=True))}
    n = len(calls)
    lodo.replay_fold(0, fold, workers=1)
    assert len(calls) == n  # the same files: every replay reused
    (fold / "idm.json").write_text("a refitted IDM")
    lodo.replay_fold(0, fold, workers=1)
    assert len(calls) == 2 * n  # one file changed: every replay made again
    (fold / "replay_openacc" / "made_from.json").unlink()
    lodo.replay_fold(0, fold, workers=1)
    assert calls[2 * n:] == ["replay_openacc"]  # a replay without a stamp: made again


def test_time_gap_prior_correlation_time_by_hand() -> None:
    """training/time_gap_prior.py: a sign that flips every sample is correlated for one sample
    (2 dt); a step (+1 for 50 samples, -1 for 50) has autocorrelation (100 - 3k) / 100 until its
    first negative lag, 34: 2 dt sum_k<34 (100 - 3k) / 100 = 2 dt 17.17."""
    prior = load_training_script("time_gap_prior")
    assert prior.correlation_time_s(np.array([1.0, -1.0] * 50), 0.1) == pytest.approx(0.2)
    step = np.array([1.0] * 50 + [-1.0] * 50)
    assert prior.correlation_time_s(step, 0.1) == pytest.approx(2 * 0.1 * 17.17)


def test_time_gap_prior_errors_by_hand() -> None:
    """A driver who keeps 1.0 s for the first 30 s and 2.0 s after (100 s at 20 m/s): the
    default 1.5 s errs 0.5 s at every look; the plain median of the first seconds 1.0 s up to
    45 s (more than half of them at 1.0 s) and 0.5 s at 60 s (half and half: 1.5 s); the shrunk
    estimate in between and closer to the default after a shorter look."""
    prior = load_training_script("time_gap_prior")
    t = np.arange(0.0, 100.0, 0.1)
    rows = pd.DataFrame({"maneuver_id": "m", "time": t, "v_x": 20.0,
                         "lead_x": np.where(t < 30.0, 20.0, 40.0)})
    table = prior.prediction_errors(rows, default_s=1.5)
    assert list(table.columns) == list(prior.SEEN_S)
    np.testing.assert_allclose(table.loc["default"], 0.5)
    np.testing.assert_allclose(table.loc["plain median"], [1.0] * 6 + [0.5], atol=1e-12)
    shrunk = table.loc["shrunk"].to_numpy()
    assert np.all((shrunk[:5] > 0.5) & (shrunk[:5] < 1.0)) and np.all(np.diff(shrunk[:5]) > 0)


def test_setting_calibrated_like_the_idm_weighs_maneuvers_by_their_samples() -> None:
    """``setting_in_models.pooled_best``: the setting with the least pooled (sample-weighted)
    gap RMSE. A long maneuver best at 1.0 s and a short one best at 2.0 s: pooled, the long one
    wins (sqrt((900 * 4 + 100 * 36) / 1000) = 2.68 m at 1.0 s against 5.73 m at 2.0 s), where an
    unweighted mean of the RMSEs would tie (4 m each)."""
    import pandas as pd

    mod = load_training_script("setting_in_models")
    grid = mod.SETTINGS_S
    table = pd.DataFrame({s: [9.0, 9.0] for s in grid}, index=["long#0", "short#0"])
    table[1.0] = [2.0, 6.0]
    table[2.0] = [6.0, 2.0]
    table["steps"] = [900, 100]
    assert mod.pooled_best(table) == 1.0
    table["steps"] = [100, 900]
    assert mod.pooled_best(table) == 2.0


def test_per_driver_adaptation_by_hand(tmp_path) -> None:
    """Two looks, folds in two folders, a broken maneuver and a failed window left out; the
    hindsight column is each maneuver's best setting; means per driver by hand."""
    pda = load_training_script("per_driver_adaptation")

    def windows(folder: Path, rows: list[tuple[str, str, float, str]]) -> None:
        folder.mkdir(parents=True)
        pd.DataFrame(rows, columns=["maneuver_id", "policy", "rmse_gap", "status"]).to_csv(
            folder / "windows.csv", index=False)

    a, b = "JRC-VC_280219_part2_f2#0", "JRC-VC_280219_part2_f2_s1#0"  # one driver: f2
    c = "JRC-VC_280219_part3_f3#0"
    windows(tmp_path / "fold0" / "look2", [
        (a, "data/lodo/fold0/safeil.safetensors", 4.0, "ok"), (a, "idm", 6.0, "ok"),
        (b, "data/lodo/fold0/safeil.safetensors", 8.0, "ok"), (b, "idm", 2.0, "ok")])
    windows(tmp_path / "fold1" / "look2", [
        (c, "safeil", 5.0, "ok"), (c, "idm", 1e9, "ok"),  # one planner sane: kept
        ("JRC-VC_280219_part3_f4#0", "safeil", 2e3, "ok"),  # every planner broke: out
        ("JRC-VC_280219_part3_f4#0", "idm", 3e3, "ok"),
        ("JRC-VC_280219_part3_f5#0", "safeil", 1.0, "failed")])
    windows(tmp_path / "look60", [(a, "safeil", 3.0, "ok"), (a, "safeil_unadapted", 9.0, "ok")])
    bound = tmp_path / "bound"
    bound.mkdir()
    pd.DataFrame({"maneuver_id": [a, a, b, b], "time_gap_s": [1.0, 1.5, 1.0, 1.5],
                  "gap_rmse_m": [2.5, 1.5, 0.5, 7.0]}).to_csv(bound / "settings.csv",
                                                              index=False)
    assert pda.main(["--looks", f"2={tmp_path}/fold*/look2", f"60={tmp_path}/look60",
                     "--bound", str(bound), "--name", "t", "--out", str(tmp_path)]) == 0
    t = pd.read_csv(tmp_path / "adaptation_t.csv").set_index(["driver", "look_s", "planner"])
    f2 = "JRC-VC_280219_part2_f2"
    assert t.loc[(f2, 2.0, "safeil"), "gap_rmse_mean_m"] == 6.0  # (4 + 8) / 2
    assert t.loc[(f2, 2.0, "idm"), "gap_rmse_mean_m"] == 4.0
    assert t.loc[(f2, 2.0, "safeil"), "maneuvers"] == 2
    assert t.loc[(f2, 60.0, pda.HINDSIGHT), "gap_rmse_mean_m"] == 1.0  # (1.5 + 0.5) / 2
    assert (f2, 60.0, pda.HINDSIGHT_LINE) not in t.index  # a one-number grid
    assert t.loc[(f2, 60.0, "safeil_unadapted"), "gap_rmse_mean_m"] == 9.0
    assert t.loc[("JRC-VC_280219_part3_f3", 2.0, "safeil"), "gap_rmse_mean_m"] == 5.0
    drivers = set(t.index.get_level_values("driver"))
    assert drivers == {f2, "JRC-VC_280219_part3_f3"}  # f4 broke, f5 failed
    text = (tmp_path / "adaptation_t.md").read_text()
    assert "After 60 s: adapted `safeil` at or below its unadapted default for 1 of 1" in text


def test_per_driver_two_number_hindsight_by_hand(tmp_path) -> None:
    """A grid over both numbers gives a second hindsight column: each maneuver's best (T, s0);
    the one-number column keeps to s0 = 0."""
    pda = load_training_script("per_driver_adaptation")
    a, b = "JRC-VC_280219_part2_f2#0", "JRC-VC_280219_part2_f2_s1#0"
    look = tmp_path / "look60"
    look.mkdir()
    pd.DataFrame([(a, "safeil", 3.0, "ok")], columns=["maneuver_id", "policy", "rmse_gap",
                                                     "status"]).to_csv(look / "windows.csv")
    bound = tmp_path / "bound"
    bound.mkdir()
    pd.DataFrame({"maneuver_id": [a, a, b, b], "time_gap_s": [1.0, 1.0, 1.0, 1.5],
                  "standstill_m": [0.0, 5.0, 0.0, -5.0],
                  "gap_rmse_m": [2.5, 0.5, 1.5, 0.5]}).to_csv(bound / "settings.csv")
    assert pda.main(["--looks", f"60={look}", "--bound", str(bound), "--name", "t",
                     "--out", str(tmp_path)]) == 0
    t = pd.read_csv(tmp_path / "adaptation_t.csv").set_index(["driver", "look_s", "planner"])
    f2 = "JRC-VC_280219_part2_f2"
    assert t.loc[(f2, 60.0, pda.HINDSIGHT), "gap_rmse_mean_m"] == 2.0  # (2.5 + 1.5) / 2
    assert t.loc[(f2, 60.0, pda.HINDSIGHT_LINE), "gap_rmse_mean_m"] == 0.5


def test_idm_oracles_find_the_idm_that_drove() -> None:
    """``setting_in_models.idm_oracles`` on a maneuver the IDM itself drove at T 1.2 s, s0
    3 m: the best (T, s0) of the grid is exact (0 m), the best T alone is not, and the fit it
    is given (T 1.5 s, s0 2 m) errs most; the span scored starts at the given second."""
    mod = load_training_script("setting_in_models")
    from safeil_sumo.planners import idm

    t = np.round(np.arange(600) * 0.1, 10)
    v_lead = 20.0 + 6.0 * np.sin(t / 8.0)  # speeds that show s0 apart from T
    driver = idm.IDMParams(time_gap_s=1.2, s0_m=3.0)
    seed = idm.Maneuver("m", t, np.full(600, 20.0), np.full(600, 30.0), v_lead)
    gap, v = idm.simulate_stacked(idm._stacked([seed]), driver)
    m = idm.Maneuver("m", t, v[0], gap[0], v_lead)
    r = mod.idm_oracles(idm.IDMParams(), m, from_s=10.0)
    assert r["idm_best_t_s0_m"] < 1e-9
    assert r["idm_best_t_m"] > 0.05
    assert r["idm_fitted_m"] > r["idm_best_t_m"]
    assert r["idm_refit_on_span_m"] < r["idm_best_t_m"]
