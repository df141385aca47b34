"""Whole-maneuver replays: the car-following literature's metrics (spacing RMSPE, time-gap error,
worst window), the ``constant_speed`` baseline in real libsumo replays, and aggregates per driver.

Pure parts on hand-computed arrays and tables; the baseline on synthetic drives (a straight
recording whose leader brakes hard, the R = 800 m arc of tests/experiments/test_replay.py).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from fixtures_data import arc_drive

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.data.schema import validate_drive
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.experiments import metrics as hm
from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.planners import registry as pol
from safeil_sumo.sim.constant_speed_ego import ConstantSpeedPath
from safeil_sumo.sim.recorded_ego import RecordedPathError

# ------------------------------------------------------------------------------------- pure


def test_rmspe_hand_computed():
    # relative errors +0.2, 0, -0.25: sqrt((0.04 + 0 + 0.0625) / 3)
    assert hm.rmspe(np.array([10.0, 20.0, 40.0]), np.array([12.0, 20.0, 30.0])) == \
        pytest.approx(math.sqrt(0.1025 / 3))
    # a zero human gap has no relative error; NaN on either side is skipped
    assert hm.rmspe(np.array([10.0, 0.0, np.nan, 20.0]), np.array([11.0, 5.0, 3.0, np.nan])) == \
        pytest.approx(0.1)
    assert math.isnan(hm.rmspe(np.array([0.0, np.nan]), np.array([1.0, 1.0])))
    with pytest.raises(ValueError, match="same shape"):
        hm.rmspe(np.zeros(2), np.zeros(3))


def test_mean_error_is_signed_and_skips_missing():
    assert hm.mean_error(np.array([1.0, 2.0, np.nan]), np.array([1.5, 1.0, 4.0])) == \
        pytest.approx(-0.25)
    assert math.isnan(hm.mean_error(np.array([np.nan]), np.array([1.0])))


def test_compare_reports_spacing_rmspe_and_time_gap_errors():
    t = np.arange(4.0)
    human = pd.DataFrame({"t": t, "x": t, "y": 0.0, "s": t, "d": 0.0, "v": 10.0,
                          "gap": [20.0, 20.0, 10.0, 10.0]})
    human["headway"] = human["gap"] / human["v"]  # 2, 2, 1, 1 s
    policy = human.assign(gap=[20.0, 22.0, 8.0, np.nan])  # ended before the last sample
    policy["headway"] = policy["gap"] / policy["v"]  # 2, 2.2, 0.8, NaN s
    row = rp.compare(human, policy)
    assert row["rmse_gap"] == pytest.approx(math.sqrt((0 + 4 + 4) / 3))
    assert row["rmspe_gap"] == pytest.approx(math.sqrt((0 + 0.01 + 0.04) / 3))
    assert row["rmse_headway"] == pytest.approx(math.sqrt((0 + 0.04 + 0.04) / 3))
    assert row["bias_headway"] == pytest.approx((0 + 0.2 - 0.2) / 3, abs=1e-12)


@pytest.mark.parametrize(("maneuver", "driver"), [
    ("JRC-VC_280219_part3_f2#1", "JRC-VC_280219_part3_f2"),  # OpenACC: file + follower
    ("handling_part22_f3#0", "handling_part22_f3"),
    ("handling_part22_f7_s2#0", "handling_part22_f7"),  # one run of a follower with dropouts
    ("773-764#1", "773"),  # NGSIM: the follower vehicle
    ("773-770#0", "773"),  # ... behind another leader
    ("47-39_2#0", "47"),  # a pair that recurs (import_ngsim_csv)
    ("n74_d03#5", "n74_d03"),  # a synthetic drive
    ("arc", "arc"),
])
def test_driver_id_of_each_source(maneuver, driver):
    assert ra.driver_id(maneuver) == driver


def _window_table() -> pd.DataFrame:
    """Per-window rows of two policies; policy a over drivers 1 (two windows) and 2."""
    rows = [
        # policy, driver, maneuver, start, gap RMSE, RMSPE, headway RMSE, bias, flag, end
        ("a", "1", "1-0#0", 0.0, 1.0, 0.10, 0.2, 0.1, "", "timeout"),
        ("a", "1", "1-0#1", 20.0, 3.0, 0.30, 0.4, -0.3, "ttc", "collision"),
        ("a", "2", "2-1#0", 0.0, 8.0, 0.20, 0.6, 0.5, "collision", "collision"),
        ("b", "1", "1-0#0", 0.0, 2.0, np.nan, 0.1, 0.0, "lane_departure", "timeout"),
    ]
    df = pd.DataFrame(rows, columns=["policy", "driver", "maneuver_id", "start_s", "rmse_gap",
                                     "rmspe_gap", "rmse_headway", "bias_headway", "flag",
                                     "end_reason"])
    coverage = [1.0, 0.4, 0.9, 1.0]  # the collisions ended their runs early
    return df.assign(status="ok", rmse_v=0.5, rmse_d=0.1, w1_headway=0.2, human_flag="",
                     coverage=coverage)


def test_aggregate_per_policy_reports_worst_window_rmspe_and_collisions():
    agg = ra.aggregate(_window_table()).set_index("policy")
    a = agg.loc["a"]
    assert a["windows"] == 3
    assert a["gap_rmse_median_m"] == pytest.approx(3.0)
    assert a["gap_rmse_mean_m"] == pytest.approx(4.0)
    assert a["gap_rmse_max_m"] == pytest.approx(8.0)
    assert a["gap_rmse_worst"] == "2-1#0@0s"
    assert a["spacing_rmspe_median"] == pytest.approx(0.2)
    assert a["spacing_rmspe_mean"] == pytest.approx(0.2)
    assert a["time_gap_rmse_median_s"] == pytest.approx(0.4)
    assert a["time_gap_error_median_s"] == pytest.approx(0.1)
    assert a["time_gap_error_mean_s"] == pytest.approx(0.1)
    # windows with a collision (first flag TTC, or collision): 2, not the counts OR-ed (1 | 2)
    assert a["collisions"] == 2 and a["flags"] == 2 and a["ended_early"] == 2
    b = agg.loc["b"]
    assert math.isnan(b["spacing_rmspe_median"]) and b["collisions"] == 0
    assert b["ended_early"] == 0
    assert b["gap_rmse_worst"] == "1-0#0@0s" and b["flags"] == 1


def test_aggregate_per_policy_and_driver():
    agg = ra.aggregate(_window_table(), by=("policy", "driver"))
    assert list(zip(agg["policy"], agg["driver"], agg["windows"], strict=True)) == [
        ("a", "1", 2), ("a", "2", 1), ("b", "1", 1)]
    a1 = agg.iloc[0]
    assert a1["gap_rmse_mean_m"] == pytest.approx(2.0)
    assert a1["gap_rmse_max_m"] == pytest.approx(3.0) and a1["gap_rmse_worst"] == "1-0#1@20s"
    assert a1["spacing_rmspe_mean"] == pytest.approx(0.2)
    assert a1["collisions"] == 1
    assert agg.iloc[1]["collisions"] == 1


# -------------------------------------------------------------------- the constant-speed ego


def test_constant_speed_path_drives_the_lane_centre_at_its_speed():
    lane = Polyline(np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0]]))
    p = ConstantSpeedPath(lane, s0=50.0, speed=20.0)
    assert p.pose_at(0.0) == pytest.approx((50.0, 0.0, 0.0, 20.0))
    assert p.pose_at(2.0) == pytest.approx((90.0, 0.0, 0.0, 20.0))
    assert p.pose_at(4.0) == pytest.approx((100.0, 30.0, math.pi / 2, 20.0))  # round the corner
    assert p.pose_at(-1.0) == pytest.approx(p.pose_at(0.0))
    with pytest.raises(RecordedPathError, match="replay"):
        ConstantSpeedPath().pose_at(0.0)
    with pytest.raises(pol.PolicyError, match="safeil_sumo.replay"):
        pol.load("constant_speed")
    assert isinstance(pol.load_for_replay("constant_speed"), ConstantSpeedPath)


def braking_drive(duration: float = 12.0, v0: float = 30.0, v1: float = 10.0,
                  decel: float = 5.0, brake_at: float = 1.0, gap: float = 20.0,
                  hz: float = 10.0) -> pd.DataFrame:
    """A straight recording: the leader brakes from ``v0`` to ``v1`` [m/s] at ``decel``
    [m/s^2] from ``brake_at`` [s]; the human follower brakes with it, keeping ``gap`` [m]."""
    t = np.round(np.arange(0.0, duration + 1e-9, 1.0 / hz), 10)
    v = np.clip(v0 - decel * np.clip(t - brake_at, 0.0, None), v1, None)
    x = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))]
    n = len(t)
    return validate_drive(pd.DataFrame({
        "recording_id": "7-3", "time": t, "x": x, "y": np.zeros(n), "yaw": np.zeros(n),
        "v_x": v, "left_c0": 1.75, "left_c1": 0.0, "left_c2": 0.0, "left_c3": 0.0,
        "right_c0": -1.75, "right_c1": 0.0, "right_c2": 0.0, "right_c3": 0.0,
        "lead_x": np.full(n, gap), "lead_y": np.zeros(n), "lead_v": v, "maneuver_id": "7-3#0",
    }))


@pytest.mark.sumo
def test_constant_speed_runs_into_a_braking_leader_and_the_collision_is_recorded(tmp_path):
    pytest.importorskip("libsumo")
    res = rp.replay_maneuver(braking_drive(), {"constant_speed": ConstantSpeedPath()}, tmp_path)
    row = res.metrics.set_index("policy").loc["constant_speed"]
    # the leader closes 2.5 (t - 1)^2 m on a 30 m/s ego: the 20 m gap is gone at t = 3.83 s;
    # TTC <= 1 s comes first
    assert row["end_reason"] == "collision" and row["error"] == ""
    assert row["flag"] == "ttc" and row["human_flag"] == ""
    log = res.rollouts["constant_speed"].log
    assert log["t"].iloc[-1] == pytest.approx(1.0 + math.sqrt(20.0 / 2.5), abs=0.15)
    assert np.allclose(log["v"], 30.0) and np.abs(log["d"]).max() < 1e-6  # centre, 30 m/s
    assert 0.2 < row["coverage"] < 0.4  # compared until the collision only
    # its gap against the human's 20 m, at the recorded samples it reached
    trace = res.compared["constant_speed"]
    reached = trace["gap"].notna().to_numpy()
    t = trace["t"].to_numpy()[reached]
    expected = 20.0 - 2.5 * np.clip(t - 1.0, 0.0, None) ** 2
    # (to the leader's lag in SUMO: one 10 ms step at up to 20 m/s of closing speed)
    assert np.allclose(trace["gap"].to_numpy()[reached], expected, atol=0.1)
    assert row["rmspe_gap"] == pytest.approx(
        math.sqrt(np.mean(((expected - 20.0) / 20.0) ** 2)), abs=0.005)


@pytest.mark.sumo
def test_whole_replays_with_constant_speed_aggregate_per_policy_and_driver(tmp_path):
    pytest.importorskip("libsumo")
    maneuvers = pd.concat([braking_drive(), arc_drive(15.0).assign(maneuver_id="arc#0")],
                          ignore_index=True)
    wins = ra.windows(maneuvers, "whole")
    policies = ["idm", "constant_speed", "recorded"]
    records = ra.replay_all(maneuvers, wins, policies, tmp_path, workers=1, progress=False)
    assert [r["driver"] for r in records] == ["7", "arc"]  # NGSIM-like pair: the follower
    df, agg = ra.write(tmp_path, records, {"test": True})
    cs = df[df["policy"] == "constant_speed"].set_index("maneuver_id")
    assert cs.loc["7-3#0", "end_reason"] == "collision"
    # on the arc the leader holds the ego's speed: constant speed is the human's longitudinal
    # motion, on the lane centre 0.2 m right of the human; the human, 0.2 m inside the arc,
    # gains 450 m x 0.2 / 800 = 0.11 m along the lane over the 15 s (gap RMSE 0.06 m)
    assert cs.loc["arc#0", "end_reason"] == "timeout" and cs.loc["arc#0", "rmse_gap"] < 0.12
    assert cs.loc["arc#0", "rmse_v"] == pytest.approx(0.0, abs=1e-9)
    assert cs.loc["arc#0", "rmse_d"] == pytest.approx(0.2, abs=0.06)
    row = agg.set_index("policy").loc["constant_speed"]
    assert row["collisions"] == 1 and row["gap_rmse_worst"] == "7-3#0@0s"
    assert agg.set_index("policy").loc["idm", "collisions"] == 0
    by_driver = pd.read_csv(tmp_path / "aggregate_by_driver.csv", dtype={"driver": str})
    assert set(zip(by_driver["policy"], by_driver["driver"], strict=True)) == {
        (p, d) for p in policies for d in ("7", "arc")}
    assert (by_driver["windows"] == 1).all()
