"""The replay instrument's own check: the ``recorded`` pseudo-planner drives the human's path.

Pure parts (the pose source, the leader-drift correction, the line-crossing test, the NGSIM lane
grid) with hand-computed cases; real libsumo replays of fixtures from every source and of a
crafted long curved OpenACC drive, which must hold the recording: no flag, near-zero error.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from fixtures_data import (
    curved_openacc_text,
    ngsim_pairs_frame,
    openacc_text,
    straight_drive,
)

from safeil_sumo.data.importers import (
    NGSIM_LANE_WIDTH,
    import_ngsim_pairs,
    import_openacc,
    ngsim_lane_grid_offset,
)
from safeil_sumo.data.pipeline import (
    PipelineConfig,
    body_outside_lines,
    process_drive,
    remove_lane_changes,
)
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.planners import registry as pol
from safeil_sumo.roads import recorded_road as rr
from safeil_sumo.run import main as run_main
from safeil_sumo.sim.recorded_ego import RecordedPath, RecordedPathError

# ------------------------------------------------------------------------------------- pure


def test_recorded_path_interpolates_and_holds_the_ends():
    p = RecordedPath(np.array([0.0, 1.0, 2.0]), np.array([[0.0, 0.0], [10.0, 1.0], [20.0, 1.0]]),
                     np.array([0.0, 0.1, 0.0]), np.array([10.0, 10.0, 12.0]))
    assert p.pose_at(0.5) == pytest.approx((5.0, 0.5, 0.05, 10.0))
    assert p.pose_at(1.5) == pytest.approx((15.0, 1.0, 0.05, 11.0))
    assert p.pose_at(-1.0) == pytest.approx((0.0, 0.0, 0.0, 10.0))
    assert p.pose_at(5.0) == pytest.approx((20.0, 1.0, 0.0, 12.0))


def test_recorded_path_unwraps_heading_across_pi():
    yaw = np.array([math.pi - 0.05, -math.pi + 0.05])  # 0.1 rad turn across the seam
    p = RecordedPath(np.array([0.0, 1.0]), np.zeros((2, 2)), yaw, np.ones(2))
    assert p.pose_at(0.5)[2] == pytest.approx(math.pi)


def test_recorded_is_refused_outside_a_replay(capsys):
    with pytest.raises(RecordedPathError, match="replay"):
        RecordedPath().pose_at(0.0)
    with pytest.raises(RecordedPathError):
        RecordedPath(np.array([0.0, 1.0]), np.zeros((3, 2)), np.zeros(2), np.ones(2))
    with pytest.raises(pol.PolicyError, match="safeil_sumo.replay"):
        pol.load("recorded")
    assert isinstance(pol.load_for_replay("recorded"), RecordedPath)
    assert run_main(["--net", "curved500", "--policy", "recorded", "--scenarios", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "replay" in err[0]


def test_drift_corrected_speed_follows_the_positions():
    t = np.arange(0.0, 300.0 + 1e-9, 0.1)
    true_v = 28.0 + 3.0 * np.sin(2 * np.pi * t / 40.0)
    position = np.r_[0.0, np.cumsum(0.5 * (true_v[1:] + true_v[:-1]) * 0.1)]
    biased = 1.01 * true_v  # a speed sensor 1 % high: 84 m too far after 300 s
    travelled = np.r_[0.0, np.cumsum(0.5 * (biased[1:] + biased[:-1]) * 0.1)]
    assert travelled[-1] - position[-1] > 80.0
    v = rr.drift_corrected_speed(t, biased, position, window_s=5.0)
    integral = np.r_[0.0, np.cumsum(0.5 * (v[1:] + v[:-1]) * 0.1)]
    assert np.max(np.abs(integral - position)) < 0.05
    # the correction is slow: the speed keeps its shape (the 1 % bias is removed)
    assert np.max(np.abs(v - true_v)) < 0.05
    np.testing.assert_array_equal(rr.drift_corrected_speed(t, biased, position, 0.0), biased)
    # never negative, even where the correction would push a standing leader backwards
    assert rr.drift_corrected_speed(t[:50], np.zeros(50), -np.arange(50.0), 1.0).min() == 0.0



@pytest.mark.parametrize("n", [200, 31, 30, 7, 6])
@pytest.mark.parametrize("window_s", [5.0, 1.0, 0.5])
def test_drift_correction_is_exact_for_a_quadratic_drift(n: int, window_s: float):
    """A drift quadratic in time (0.01 t^2 m: a 2 % per 100 s speed bias growing linearly) is
    removed exactly at every sample, the first and last included: an order-2 Savitzky-Golay
    derivative is exact on it, whatever the window (capped at the samples there are), on a log
    that starts at t = 40 s."""
    t = 40.0 + 0.1 * np.arange(n)
    tau = t - t[0]
    v = rr.drift_corrected_speed(t, np.full(n, 25.0), 100.0 + 25.0 * tau + 0.01 * tau ** 2,
                                 window_s)
    np.testing.assert_allclose(v, 25.0 + 0.02 * tau, atol=1e-9)


def test_drift_correction_of_too_few_samples_is_the_mean_rate():
    """Fewer samples than a 5-point filter: the speed gains the mean drift rate
    (drift[-1] - drift[0]) / (t[-1] - t[0]). Here the positions run 1, 3 and 6 m ahead of 20
    m/s after 1, 2, 3 s: +2 m/s everywhere."""
    t = np.array([10.0, 11.0, 12.0, 13.0])
    v = rr.drift_corrected_speed(t, np.full(4, 20.0), np.array([0.0, 21.0, 43.0, 66.0]), 5.0)
    np.testing.assert_allclose(v, 22.0)
    two = rr.drift_corrected_speed(np.array([0.0, 1.0]), np.array([10.0, 10.0]),
                                   np.array([0.0, 12.0]), 5.0)
    np.testing.assert_allclose(two, 12.0)
    # no window: the speed itself, only clipped at 0
    np.testing.assert_array_equal(
        rr.drift_corrected_speed(t[:2], np.array([0.5, -1.0]), np.zeros(2), 0.0), [0.5, 0.0])


def test_recorded_leader_speed_and_travel_by_hand():
    """The leader's speed: the pipeline's ``v_lead``, else ``lead_v``, else the ego speed plus
    the derivative of the gap; gaps in the column filled from the derivative; clipped at 0.
    Its travel: the trapezoid integral."""
    t = np.array([0.0, 1.0, 2.0, 3.0])
    rows = pd.DataFrame({"time": t, "v_x": [20.0, 20.0, 21.0, 21.0],
                         "lead_x": [30.0, 32.0, 35.0, 35.0]})
    # np.gradient: one-sided at the ends, central inside: 2, 2.5, 1.5, 0
    np.testing.assert_allclose(rr.leader_speed(rows), [22.0, 22.5, 22.5, 21.0])
    np.testing.assert_allclose(rr.leader_speed(rows.assign(lead_v=[1.0, np.nan, -3.0, 4.0])),
                               [1.0, 22.5, 0.0, 4.0])
    # at 0.5 s steps the gap's rate doubles: 4, 5, 3, 0
    np.testing.assert_allclose(rr.leader_speed(rows.assign(time=0.5 * t)),
                               [24.0, 25.0, 24.0, 21.0])
    both = rows.assign(v_lead=[5.0, 6.0, 7.0, 8.0], lead_v=[1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(rr.leader_speed(both), [5.0, 6.0, 7.0, 8.0])
    uneven = rows.assign(time=[0.0, 0.5, 2.0, 3.0], v_lead=[10.0, 20.0, 20.0, 30.0])
    # 0.5 * (10 + 20) * 0.5 + 20 * 1.5 + 0.5 * (20 + 30) * 1 = 7.5 + 30 + 25
    assert rr.recorded_leader_travel(uneven) == pytest.approx(62.5)

def _lines(c0l: float, c0r: float, c1: float = 0.0) -> pd.DataFrame:
    return pd.DataFrame({"left_c0": [c0l], "left_c1": [c1], "left_c2": [0.0], "left_c3": [0.0],
                         "right_c0": [c0r], "right_c1": [c1], "right_c2": [0.0],
                         "right_c3": [0.0]})


@pytest.mark.parametrize(("c0l", "c0r", "c1", "outside"), [
    (1.75, -1.75, 0.0, False),  # centred in a 3.5 m lane
    (0.91, -2.59, 0.0, False),  # 0.84 m left of centre: the body edge 3 cm inside the line
    (0.87, -2.63, 0.0, True),  # the body's left edge 1 cm over the left line
    (1.75, -1.75, -0.2, True),  # yawed 0.2 rad left: the rear swings 0.9 m right, over
    (1.75, -1.75, -0.1, False),  # 0.1 rad: rear at -0.88 - 0.45 = -1.33, inside
    (math.nan, math.nan, 0.0, False),  # no lane lines: not a crossing
])
def test_body_outside_lines_hand_cases(c0l, c0r, c1, outside):
    assert bool(body_outside_lines(_lines(c0l, c0r, c1), 4.5, 1.76)[0]) is outside


def test_pipeline_drops_a_line_crossing_and_counts_it():
    d = straight_drive(duration=30.0)
    over = (d["time"] >= 10.0) & (d["time"] <= 11.0)  # drifts 1 m left for a second
    d.loc[over, "left_c0"] -= 1.0
    d.loc[over, "right_c0"] -= 1.0
    cfg = PipelineConfig()
    out, res = remove_lane_changes(d, cfg)
    assert res.events == {"lane_change": 0, "line_crossing": 1}
    kept = out["time"].to_numpy()
    assert not np.any((kept > 10.0 - cfg.line_crossing_window - 1e-9)
                      & (kept < 11.0 + cfg.line_crossing_window + 1e-9))
    assert len(out) == len(d) - 21  # 10.0 .. 11.0 s +- 0.5 s at 10 Hz


def test_ngsim_lane_grid_offset_centres_the_vehicles():
    lane = np.repeat([1.0, 2.0, 3.0], 100)
    lat = (lane - 0.5) * NGSIM_LANE_WIDTH - 0.37 + np.tile([-0.1, 0.1], 150)
    assert ngsim_lane_grid_offset(lat, lane) == pytest.approx(-0.37)
    # a wild file is clipped to a quarter lane; too few rows: no shift
    assert ngsim_lane_grid_offset(lat - 2.0, lane) == pytest.approx(-0.25 * NGSIM_LANE_WIDTH)
    assert ngsim_lane_grid_offset(lat[:10], lane[:10]) == 0.0


# ------------------------------------------------------------------------- real libsumo runs


def _recorded_replay(drive: pd.DataFrame, tmp_path) -> rp.ReplayResult:
    maneuvers, _ = process_drive(drive, PipelineConfig(rate_hz=10.0))
    mid = rp.maneuver_table(maneuvers)["duration_s"].idxmax()
    rows = maneuvers[maneuvers["maneuver_id"] == mid].reset_index(drop=True)
    return rp.replay_maneuver(rows, {"recorded": RecordedPath()}, tmp_path, maneuver_id=mid)


def _assert_holds(res: rp.ReplayResult, gap_rmse_m: float) -> pd.Series:
    row = res.metrics.set_index("policy").loc["recorded"]
    assert row["flag"] == "" and row["human_flag"] == ""
    assert row["end_reason"] == "timeout" and row["coverage"] == 1.0  # replayed to the end
    assert row["rmse_x"] < 1e-6 and row["rmse_y"] < 1e-6 and row["rmse_v"] < 1e-6
    assert row["rmse_gap"] <= gap_rmse_m
    return row


@pytest.mark.sumo
def test_recorded_replays_fixtures_of_every_source(tmp_path):
    openacc = tmp_path / "JRC-FIX_010119_part1.csv"
    openacc.write_text(openacc_text(n=300))
    ngsim = tmp_path / "pairs.parquet"
    ngsim_pairs_frame().to_parquet(ngsim)
    drives = {
        "openacc": import_openacc(openacc),
        "ngsim": import_ngsim_pairs(ngsim),
        "synthetic": straight_drive(duration=20.0).assign(x=lambda d: d["x"] + 3.0e5),
    }
    for name, drive in drives.items():
        res = _recorded_replay(drive, tmp_path / name)
        row = _assert_holds(res, gap_rmse_m=0.02)
        assert row["max_gap"] < 0.05, name


@pytest.mark.sumo
def test_recorded_replays_a_long_curved_drive_whole(tmp_path):
    """240 s, 7 km: a tight curve whose lane curvature the importer clips, an S-bend and a long
    curve, GNSS noise and speed sensors 0.5 % high."""
    path = tmp_path / "JRC-CURVED_010119_part1.csv"
    path.write_text(curved_openacc_text(duration=240.0))
    drive = import_openacc(path)
    assert drive.attrs["import_stats"]["curvature_clipped"] > 0
    res = _recorded_replay(drive, tmp_path / "replay")
    assert res.info["duration_s"] == pytest.approx(240.0)
    # driven by its speed alone the leader would end ~35 m off; corrected, within decimetres
    assert res.info["max_abs_leader_drift_uncorrected_m"] > 20.0
    assert res.info["max_abs_leader_drift_m"] < 0.3
    # the rebuilt lane holds the recorded path to centimetres (the follower's lane is its path):
    # measured 2.2 cm without GNSS noise (chords and smoothing through the R = 200 m clothoids),
    # 7.4 cm with the 2 cm white noise that stays in the recorded positions (3.5 sigma)
    assert res.info["max_abs_lane_rebuild_error_m"] < 0.1
    _assert_holds(res, gap_rmse_m=0.2)
