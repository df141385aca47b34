"""Replay of recorded maneuvers: road geometry, scenario, selection, real libsumo runs, CLI."""

from __future__ import annotations

import glob
import math
import warnings

import numpy as np
import pandas as pd
import pytest
from fixtures_data import ARC_HALF as HALF
from fixtures_data import ARC_OFFSET as OFFSET
from fixtures_data import ARC_R as R
from fixtures_data import ARC_V as V
from fixtures_data import NGSIM_PAIRS, OPENACC_DIR, arc_drive, require_file

from safeil_sumo.data.schema import save_drive
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.roads import recorded_road as rr

# ------------------------------------------------------------------------------ pure geometry


def test_lane_centre_points_rotate_the_line_midpoint():
    pts = rr.lane_centre_points(np.array([10.0]), np.array([5.0]), np.array([math.pi / 2]),
                                np.array([2.0]), np.array([-1.0]))
    # midpoint 0.5 m to the ego's left; heading north -> left is west (-x)
    assert np.allclose(pts, [[9.5, 5.0]])


def test_lane_width_median_and_clip():
    assert rr.lane_width(np.array([1.8, 1.7, 1.9]), np.array([-1.7, -1.8, -9.0])) == \
        pytest.approx(3.5)
    assert rr.lane_width(np.array([1.0]), np.array([-1.0])) == rr.LANE_WIDTH_RANGE_M[0]
    assert rr.lane_width(np.array([4.0]), np.array([-4.0])) == rr.LANE_WIDTH_RANGE_M[1]


def test_decimate_keeps_points_within_tolerance():
    th = np.linspace(0.0, 0.5, 400)
    pts = np.stack([R * np.sin(th), R - R * np.cos(th)], axis=1)
    lean = rr.decimate(pts, 0.05)
    assert len(lean) < 40
    assert np.allclose(lean[[0, -1]], pts[[0, -1]])
    # chord sagitta for R and tolerance: every original point within 5 cm of the lean polyline
    from safeil_sumo.core.geometry import Polyline
    _, d = Polyline(lean).project(pts)
    assert np.max(np.abs(d)) <= 0.05 + 1e-9
    straight = rr.decimate(np.stack([np.linspace(0, 100, 50), np.zeros(50)], axis=1), 0.05)
    assert len(straight) == 2


def test_smoothing_removes_noise_and_keeps_the_radius():
    th = np.linspace(0.0, 0.4, 300)
    pts = np.stack([R * np.sin(th), R - R * np.cos(th)], axis=1)
    noisy = pts + np.random.default_rng(1).normal(scale=0.1, size=pts.shape)
    smooth = rr.smooth_path(noisy, 1.0, 41.0)
    assert rr.circle_radius(smooth) == pytest.approx(R, rel=0.01)
    r = np.hypot(smooth[:, 0], smooth[:, 1] - R)
    assert np.std(r - R) < 0.05  # 10 cm noise -> < 5 cm


# --------------------------------------------------------------------------- the SUMO road


def test_replay_road_from_recorded_arc_has_radius_width_and_path(tmp_path):
    rows = arc_drive()
    net = rr.build_replay_net(rows, tmp_path / "net", "arc#0", meta={"maneuver_id": "arc#0"})
    road, frame = rr.load_replay_road(net)
    assert net.name == "arc_0.net.xml"
    assert len(road.lanes) == 3 and road.ego_lane == 1
    assert all(lane.width == pytest.approx(2 * HALF) for lane in road.lanes)
    centre = road.lanes[1].centre
    # the recorded part of the lane (not the straight ends) is the R = 800 m arc
    sel = (centre.s > road.path_start_s + 1) & (centre.s < road.path_start_s + V * 15 - 1)
    assert sel.sum() >= 5
    assert rr.circle_radius(centre.points[sel]) == pytest.approx(R, rel=0.005)
    # lean shape: 5 cm chords
    assert len(centre.points) < 60
    # local frame: the road starts along +x at the recorded start
    start = frame.points(rows["x"].iloc[0], rows["y"].iloc[0])
    assert np.allclose(start, 0.0)
    s0, d0 = centre.project(start)
    assert s0 == pytest.approx(road.path_start_s, abs=1e-3)
    assert d0 == pytest.approx(OFFSET, abs=0.06)  # human 0.2 m left, up to the chord sagitta
    assert road.path_start_s == pytest.approx(30.0, abs=0.05)  # the run-in
    assert road.path_end_s > road.path_start_s + V * 15
    assert road.meta["kind"] == "replay" and road.meta["maneuver_id"] == "arc#0"
    for suffix in (".nod.xml", ".edg.xml", ".rou.xml", ".sumocfg", ".track.json"):
        assert (tmp_path / "net" / f"arc_0{suffix}").is_file()
    assert not list(tmp_path.glob(".arc_0-build-*"))  # the temporary folder is gone


def test_replay_scenario_starts_at_the_recorded_state(tmp_path):
    rows = arc_drive()
    net = rr.build_replay_net(rows, tmp_path / "net", "arc")
    road, frame = rr.load_replay_road(net)
    sc = rp.replay_scenario(rows, road, frame, "arc")
    assert sc.ego_speed_mps == V and sc.initial_gap_m == 50.0
    assert sc.max_time_s == pytest.approx(15.0)
    assert sc.ego_lateral_offset_m == pytest.approx(OFFSET, abs=0.06)
    assert abs(sc.ego_heading_offset_rad) < 0.01
    assert sc.leader.speed_at(7.0) == pytest.approx(V)


# ---------------------------------------------------------------------------- selection


def test_select_maneuver_by_id_longest_auto_and_unknown():
    a = arc_drive(duration=20.0)
    b = arc_drive(duration=12.0).assign(maneuver_id="slow#0", v_x=20.0, lead_x=30.0)
    m = pd.concat([a, b], ignore_index=True)
    mid, start, rows = rp.select_maneuver(m, "longest", duration_s=None)
    assert mid == "arc#0" and len(rows) == len(a)
    mid, start, rows = rp.select_maneuver(m, "slow#0", start_s=1.0, duration_s=5.0)
    assert start == 1.0
    assert mid == "slow#0" and rows["time"].iloc[0] == pytest.approx(1.0)
    assert rows["time"].iloc[-1] - rows["time"].iloc[0] == pytest.approx(5.0)
    mid, _, rows = rp.select_maneuver(m, "auto")  # 30 m/s is closer to 115 km/h
    assert mid == "arc#0" and len(rows) == 111
    with pytest.raises(rp.ReplayError, match=r"unknown maneuver 'x'; available: arc#0, slow#0"):
        rp.select_maneuver(m, "x")
    with pytest.raises(rp.ReplayError, match="no maneuver lasts"):
        rp.select_maneuver(m, "auto", duration_s=100.0)


def test_replay_rejects_rows_without_leader(tmp_path):
    rows = arc_drive().assign(lead_x=np.nan, lead_y=np.nan)
    with pytest.raises(rp.ReplayError, match="without a leader"):
        rp.replay_maneuver(rows, {"analytic": AnalyticPlanner()}, tmp_path)


# ---------------------------------------------------------------- closed loop in libsumo


def _check_result(res: rp.ReplayResult, folder) -> pd.Series:
    rp.write_replay(res, folder)
    for name in ("metrics.csv", "metrics.json", "steps.parquet", "human.parquet",
                 "compared.parquet", "replay.png", "manifest.json"):
        assert (folder / name).is_file(), name
    row = res.metrics.set_index("policy").loc["analytic"]
    assert row["end_reason"] == "timeout" and row["coverage"] == 1.0
    numeric = [c for c in res.metrics.columns if c.startswith(("rmse_", "max_", "w1_", "ks_"))]
    assert np.all(np.isfinite(row[numeric].to_numpy(float)))
    return row


@pytest.mark.sumo
def test_replay_synthetic_arc_end_to_end(tmp_path):
    res = rp.replay_maneuver(arc_drive(), {"analytic": AnalyticPlanner()}, tmp_path)
    row = _check_result(res, tmp_path)
    # the human holds speed and the analytic planner's own gap; the planner steers to the lane
    # centre 0.2 m right of the human
    assert row["rmse_d"] < 0.25 and row["max_d"] < 0.3
    assert row["rmse_gap"] < 1.0 and row["rmse_v"] < 0.5
    # the recorded leader is consistent; driven by its speed alone it would drift by the human's
    # arc 0.2 m inside the lane centre: 450 m x 0.2 / 800 = 0.11 m less along-lane distance
    # than the leader's; the replay's drift correction removes that
    assert res.info["max_abs_leader_drift_uncorrected_m"] == pytest.approx(450 * OFFSET / R,
                                                                           abs=0.03)
    assert res.info["max_abs_leader_drift_m"] < 0.01
    assert res.human["d"].iloc[0] == pytest.approx(OFFSET, abs=0.06)


@pytest.mark.sumo
def test_replay_openacc_maneuver_with_analytic(tmp_path):
    from safeil_sumo.data.importers import import_openacc
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive

    files = sorted(glob.glob(str(OPENACC_DIR / "JRC-VC_280219_*.csv.gz")))
    require_file(OPENACC_DIR / "JRC-VC_280219_part3.csv.gz")
    drive = pd.concat([import_openacc(f) for f in files], ignore_index=True)
    maneuvers, _ = process_drive(drive, PipelineConfig(rate_hz=10.0))
    mid, start, rows = rp.select_maneuver(maneuvers, "auto")
    assert mid == "JRC-VC_280219_part3_f4#1" and start == 72.0  # 32.0 m/s, 58.2 m: like the paper
    res = rp.replay_maneuver(rows, {"analytic": AnalyticPlanner()}, tmp_path, maneuver_id=mid)
    assert res.info["duration_s"] == pytest.approx(11.0)
    assert res.info["mean_speed_mps"] > 25.0
    row = _check_result(res, tmp_path)
    # measured: d_lead RMSE 0.84 m (max 1.27 m), v_x RMSE 0.39 m/s, lateral RMSE 0.03 m
    assert row["rmse_gap"] < 2.0
    assert row["rmse_v"] < 1.0
    assert row["rmse_d"] < 0.2


@pytest.mark.sumo
def test_replay_ngsim_maneuver_with_analytic(tmp_path):
    from safeil_sumo.data.importers import import_ngsim_pairs
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive

    drive = import_ngsim_pairs(require_file(NGSIM_PAIRS))
    maneuvers, _ = process_drive(drive, PipelineConfig(rate_hz=10.0))
    mid, start, rows = rp.select_maneuver(maneuvers, "auto")
    assert (mid, start) == ("47-39#0", 14.0)  # congested: the fastest open window, 18.1 m/s
    res = rp.replay_maneuver(rows, {"analytic": AnalyticPlanner()}, tmp_path, maneuver_id=mid)
    assert res.info["duration_s"] == pytest.approx(11.0)
    assert res.info["lane_width_m"] == pytest.approx(3.658, abs=1e-3)
    assert res.road.meta["shape_points"] == 2  # NGSIM I-80 is straight
    row = _check_result(res, tmp_path)
    # measured on 47-39#0 @ 21 s (18.5 m/s): d_lead RMSE 8.8 m (before the lane-grid offset) — the human keeps a 2.8 s gap,
    # the analytic planner closes to its 1.5 s; a loose bound
    assert row["rmse_gap"] < 15.0
    assert row["rmse_d"] < 0.6


# ------------------------------------------------------------------------------------- CLI


@pytest.mark.sumo
def test_cli_on_a_drive_file(tmp_path, capsys):
    from safeil_sumo import replay as cli

    path = tmp_path / "arc.parquet"
    save_drive(arc_drive(), path)
    out = tmp_path / "out"
    code = cli.main(["--source", str(path), "--maneuver", "longest", "--duration-s", "10",
                     "--policy", "analytic", "--out", str(out)])
    text = capsys.readouterr().out
    assert code == 0
    assert "analytic" in text and "d_lead rmse/max" in text
    assert (out / "replay.png").is_file() and (out / "net" / "arc_0.net.xml").is_file()
    m = pd.read_csv(out / "metrics.csv")
    assert list(m["policy"]) == ["analytic"]


def test_cli_one_line_errors(tmp_path, capsys):
    from safeil_sumo import replay as cli

    path = tmp_path / "arc.parquet"
    save_drive(arc_drive(), path)
    assert cli.main(["--source", str(path), "--maneuver", "nope", "--out",
                     str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown maneuver 'nope'; available:" in err
    assert "arc#0" in err
    assert cli.main(["--source", str(tmp_path / "missing.parquet")]) == 2
    assert cli.main(["--source", str(path), "--policy", str(tmp_path / "no.safetensors"),
                     "--out", str(tmp_path / "o")]) == 2
    assert "no.safetensors does not exist" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------- every window, aggregated


def test_windows_modes_and_unknown_ids():
    from safeil_sumo.experiments import window_replays as ra

    rows = pd.concat([arc_drive(35.0).assign(maneuver_id="a#0"),
                      arc_drive(8.0).assign(maneuver_id="b#0")], ignore_index=True)
    assert [(w.maneuver_id, w.start_s) for w in ra.windows(rows, "paper")] == [("a#0", 0.0)]
    assert [w.start_s for w in ra.windows(rows, "sliding", stride_s=10.0)] == [0.0, 10.0, 20.0]
    assert {w.maneuver_id for w in ra.windows(rows, "whole")} == {"a#0", "b#0"}
    with pytest.raises(rp.ReplayError, match="unknown maneuver"):
        ra.windows(rows, "paper", only=["nope"])


def test_bootstrap_ci_is_seeded_and_brackets_the_median():
    from safeil_sumo.experiments.window_replays import bootstrap_ci

    v = np.random.default_rng(0).lognormal(1.0, 0.5, 200)
    lo, hi = bootstrap_ci(v, seed=3)
    assert (lo, hi) == bootstrap_ci(v, seed=3)
    assert lo < np.median(v) < hi and hi - lo < 1.0


def test_bootstrap_ci_edge_cases() -> None:
    from safeil_sumo.experiments.window_replays import bootstrap_ci

    v = np.random.default_rng(0).lognormal(1.0, 0.5, 50)
    assert bootstrap_ci(v) == bootstrap_ci(v, seed=0)  # seeded by default
    assert bootstrap_ci(np.array([3.0, np.nan])) == (3.0, 3.0)  # one finite value
    assert all(math.isnan(x) for x in bootstrap_ci(np.array([np.nan, np.inf])))
    # every value can be drawn: the mean of one 10 among nine zeros varies
    lo, hi = bootstrap_ci(np.r_[10.0, np.zeros(9)], np.mean)
    assert lo == 0.0 and hi >= 2.0


def test_headway_histogram_bins_by_hand() -> None:
    from safeil_sumo.experiments.window_replays import _headway_hist

    h = _headway_hist(np.array([0.05, 0.15, 0.15, 4.99, 5.0, 7.0, -0.1, np.nan, np.inf]))
    assert len(h) == 50 and sum(h) == 5  # 0.1 s bins over 0-5 s; beyond and NaN left out
    assert (h[0], h[1], h[49]) == (1, 2, 2)  # the last bin holds its right edge


def test_replay_aggregate_by_hand() -> None:
    """Per policy, in order of appearance, over the replayed windows (a failed window left
    out): gap RMSE median and mean with their seeded bootstrap CIs, medians of the other
    errors, flags, flags where the human had none, and collisions (flagged OR ended by one,
    each window once)."""
    from safeil_sumo.experiments.window_replays import aggregate, bootstrap_ci, window_id

    gap_p = np.array([1.0, 2.0, 6.0, 0.5, 3.0, 4.0, 2.5, 8.0, 1.5, 0.8])
    df = pd.DataFrame({
        "status": ["ok"] * 12 + ["failed"],
        "policy": ["safeil"] * 10 + ["bc"] * 2 + ["safeil"],
        "rmse_gap": [*gap_p, 0.5, np.nan, 99.0],
        "rmse_v": [0.1, 0.3, 0.2, 0.1, 0.2, 0.2, 0.3, 0.1, 0.2, 0.2, 0.4, 0.6, 99.0],
        "rmse_d": [0.03] * 10 + [0.02, 0.04, 99.0],
        "w1_headway": [0.2] * 10 + [0.5, 0.7, 99.0],
        "flag": ["collision", "collision", ""] + [""] * 7 + ["ttc", "lane_departure",
                                                              "collision"],
        "human_flag": [""] * 10 + ["ttc", "", ""],
        "end_reason": ["collision", "completed", "collision"] + ["completed"] * 9
        + ["collision"],
        "maneuver_id": [f"m{i}" for i in range(13)],
        "start_s": [0.0] * 7 + [22.0] + [0.0] * 5,
    })
    table = aggregate(df)
    assert list(table["policy"]) == ["safeil", "bc"]
    p, q = table.iloc[0], table.iloc[1]
    assert (p["windows"], p["flags"], p["flags_beyond_human"], p["collisions"]) == (10, 2, 2, 3)
    assert (p["gap_rmse_median_m"], p["gap_rmse_mean_m"]) == (2.25, 2.93)
    # the worst window (8.0 m, m7 from 22 s), not the failed one's 99 m
    assert (p["gap_rmse_max_m"], p["gap_rmse_worst"]) == (8.0, window_id("m7", 22.0))
    assert (p["speed_rmse_median_mps"], p["lateral_rmse_median_m"],
            p["time_gap_w1_median_s"]) == pytest.approx((0.2, 0.03, 0.2))
    # the CIs: bootstrap_ci's, seeded with the aggregate's seed (default 0)
    assert (p["gap_rmse_median_lo"], p["gap_rmse_median_hi"]) == \
        bootstrap_ci(gap_p, np.median, seed=0)
    assert (p["gap_rmse_mean_lo"], p["gap_rmse_mean_hi"]) == bootstrap_ci(gap_p, np.mean, seed=0)
    other = aggregate(df, seed=5).iloc[0]
    assert (other["gap_rmse_mean_lo"], other["gap_rmse_mean_hi"]) == \
        bootstrap_ci(gap_p, np.mean, seed=5) != bootstrap_ci(gap_p, np.mean, seed=0)
    assert (other["gap_rmse_median_lo"], other["gap_rmse_median_hi"]) == \
        bootstrap_ci(gap_p, np.median, seed=5)
    # a NaN gap RMSE is left out of its statistics
    assert (q["windows"], q["gap_rmse_median_m"], q["gap_rmse_mean_m"]) == (2, 0.5, 0.5)
    assert (q["gap_rmse_median_lo"], q["gap_rmse_median_hi"]) == (0.5, 0.5)
    assert (q["flags"], q["flags_beyond_human"], q["collisions"]) == (2, 1, 0)
    assert (q["speed_rmse_median_mps"], q["time_gap_w1_median_s"]) == pytest.approx((0.5, 0.6))


@pytest.mark.sumo
def test_cli_replays_all_windows_aggregates_and_resumes(tmp_path, capsys):
    from safeil_sumo import replay as cli

    drive = pd.concat([arc_drive(24.0).assign(recording_id="a"),
                       arc_drive(12.0, origin=(6.0e5, 4.9e6)).assign(recording_id="b")],
                      ignore_index=True).drop(columns="maneuver_id")
    src = tmp_path / "drive.parquet"
    save_drive(drive, src)
    out = tmp_path / "all"
    args = ["--source", str(src), "--maneuver", "all", "--stride-s", "10", "--policy",
            "analytic", "idm", "--out", str(out)]
    assert cli.main(args) == 0
    table = pd.read_csv(out / "windows.csv")
    agg = pd.read_csv(out / "aggregate.csv")
    assert set(table["policy"]) == {"analytic", "idm"}
    assert table.groupby("policy").size().tolist() == [len(table) // 2] * 2
    assert list(agg["policy"]) == ["analytic", "idm"] and (agg["flags"] == 0).all()
    assert (out / "replay_all.png").is_file() and (out / "manifest.json").is_file()
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "tasks").iterdir()}
    capsys.readouterr()
    assert cli.main(args) == 0  # resumed: every window is done, nothing reruns
    assert {p.name: p.stat().st_mtime_ns for p in (out / "tasks").iterdir()} == stamps
    # other policies: new results, never the stale ones of the first run
    assert cli.main([*args[:-4], "analytic", "--out", str(out)]) == 0
    assert len(list((out / "tasks").iterdir())) == 2 * len(stamps)
    assert set(pd.read_csv(out / "windows.csv")["policy"]) == {"analytic"}
    # an unknown id: one error line, exit 2
    assert cli.main(["--source", str(src), "--maneuver", "a#0,zz", "--out",
                     str(tmp_path / "x")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_aggregate_counts_each_collision_window_once():
    from safeil_sumo.experiments import window_replays as ra

    # window 1 flags a collision and ends in one; window 2 ends in a collision after a lane
    # departure flag; window 3 neither: 2 windows with a collision (a bitwise OR of the two
    # counts, 1 | 2, gave 3)
    df = pd.DataFrame({
        "status": "ok", "policy": "p", "rmse_gap": [1.0, 2.0, 3.0], "rmse_v": 0.1,
        "rmse_d": 0.1, "w1_headway": 0.1, "human_flag": "", "maneuver_id": "m",
        "start_s": [0.0, 20.0, 40.0],
        "flag": ["collision", "lane_departure", "lane_departure"],
        "end_reason": ["collision", "collision", "timeout"]})
    row = ra.aggregate(df).iloc[0]
    assert row["collisions"] == 2
    assert row["flags"] == 3 and row["windows"] == 3


@pytest.mark.sumo
def test_duration_caps_whole_maneuver_replays(tmp_path, capsys):
    from safeil_sumo import replay as cli
    from safeil_sumo.experiments import window_replays as ra

    drive = pd.concat([arc_drive(24.0).assign(recording_id="a"),
                       arc_drive(12.0, origin=(6.0e5, 4.9e6)).assign(recording_id="b")],
                      ignore_index=True).drop(columns="maneuver_id")
    src = tmp_path / "drive.parquet"
    save_drive(drive, src)
    base = ["--source", str(src), "--maneuver", "all", "--windows", "whole", "--policy",
            "analytic"]
    # uncapped: each maneuver whole; --duration-s 5: each from its start for 5 s
    assert cli.main([*base, "--out", str(tmp_path / "whole")]) == 0
    whole = pd.read_csv(tmp_path / "whole" / "windows.csv").sort_values("duration_s")
    assert whole["duration_s"].tolist() == pytest.approx([12.0, 24.0], abs=0.15)
    assert cli.main([*base, "--duration-s", "5", "--out", str(tmp_path / "capped")]) == 0
    capped = pd.read_csv(tmp_path / "capped" / "windows.csv")
    assert capped["duration_s"].tolist() == pytest.approx([5.0, 5.0], abs=1e-6)
    assert (capped["start_s"] == 0.0).all()
    # the closed loop of a capped window lasts no longer than the cap
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive

    rows, _ = process_drive(drive, PipelineConfig(rate_hz=10.0))
    win = ra.windows(rows, "whole", 5.0)[0]
    assert win.duration_s == 5.0
    res = rp.replay_maneuver(ra._window_rows(win, rows), {"analytic": AnalyticPlanner()},
                             tmp_path / "one", maneuver_id=win.maneuver_id)
    assert 4.9 <= res.rollouts["analytic"].log["t"].max() <= 5.0 + 1e-9
    # a cap longer than a maneuver is that maneuver whole (the same window, the same task)
    assert [w.duration_s for w in ra.windows(rows, "whole", 30.0)] == [None, None]
    # --duration-s 0 (to the end) with windows of a length is refused (it silently was 11 s)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        cli.main([*base[:4], "--windows", "sliding", "--duration-s", "0"])
    assert exc.value.code == 2 and "--duration-s 0" in capsys.readouterr().err


def test_literature_summary_by_hand() -> None:
    """The figures the car-following literature reports, over one group of windows: the worst
    window and its id, spacing RMSPE median and mean, time-gap RMSE median, the mean time-gap
    error's median and mean (NaN left out), and the windows that ended before the recording."""
    from safeil_sumo.experiments.window_replays import literature_summary, window_id

    g = pd.DataFrame({
        "maneuver_id": ["a", "b", "c", "d"], "start_s": [0.0, 20.0, 0.0, 40.0],
        "rmse_gap": [2.0, np.nan, 7.5, 3.0],
        "rmspe_gap": [0.10, 0.30, 0.20, np.nan],
        "rmse_headway": [0.5, 0.1, 0.3, 0.9],
        "bias_headway": [-0.4, 0.2, np.nan, 0.5],
        "coverage": [1.0, 0.5, 0.999, 1.0],
    })
    s = literature_summary(g)
    assert (s["gap_rmse_max_m"], s["gap_rmse_worst"]) == (7.5, window_id("c", 0.0)) == (7.5, "c@0s")
    assert s["spacing_rmspe_median"] == pytest.approx(0.20)
    assert s["spacing_rmspe_mean"] == pytest.approx(0.20)
    assert s["time_gap_rmse_median_s"] == pytest.approx(0.4)
    assert s["time_gap_error_median_s"] == pytest.approx(0.2)
    assert s["time_gap_error_mean_s"] == pytest.approx((-0.4 + 0.2 + 0.5) / 3)
    assert s["ended_early"] == 2
    # a table without the newer columns, and no finite gap RMSE: NaN, no worst window
    old = g[["maneuver_id", "start_s"]].assign(rmse_gap=np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "All-NaN slice" warning: NaN is decided up front
        s = literature_summary(old)
    assert math.isnan(s["gap_rmse_max_m"]) and s["gap_rmse_worst"] == ""
    assert all(math.isnan(s[k]) for k in ("spacing_rmspe_median", "spacing_rmspe_mean",
                                          "time_gap_rmse_median_s", "time_gap_error_median_s",
                                          "time_gap_error_mean_s"))
    assert s["ended_early"] == 0
