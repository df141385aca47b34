"""``run --net n74``: kilometre posts -> route of edges, departure mid-road, one-line errors;
and (real libsumo) background traffic as the ego's leaders."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.roads import n74
from safeil_sumo.roads.road import NetworkError
from safeil_sumo.run import main


def test_stretch_maps_kilometres_to_the_edges_and_the_ego_lane():
    road = n74.stretch_road(0.0, 3.0)
    assert road.route_edges == ("main0",) and road.ego_lane == 0
    assert road.path_start_s == 0.0 and road.path_end_s == pytest.approx(3000.0, abs=5.0)
    mid = n74.stretch_road(4.4, 10.0)  # starts on merge1: the right main lane is SUMO lane 1
    assert mid.route_edges == ("merge1", "main1", "merge2", "main2") and mid.ego_lane == 1
    assert mid.path_start_s == pytest.approx(91.0, abs=3.0)
    assert mid.path_length == pytest.approx(5600.0, abs=15.0)
    whole = n74.stretch_road()
    assert len(whole.route_edges) == 11 and whole.path_length == pytest.approx(29200, abs=30)
    assert n74.stretch_road(1, 2, lane="left").ego_lane == 1


@pytest.mark.parametrize("lo, hi, message", [
    (-1.0, 2.0, "outside n74"), (28.0, 31.0, "outside n74"), (3.0, 2.0, "shorter than"),
])
def test_stretch_outside_the_road_is_refused_in_one_line(lo, hi, message):
    with pytest.raises(NetworkError, match=message):
        n74.stretch_road(lo, hi)


@pytest.mark.sumo
def test_run_n74_drives_three_km_without_flags(tmp_path, capsys):
    out = tmp_path / "res"
    code = main(["--net", "n74", "--from-km", "0", "--to-km", "3", "--policy", "analytic",
                 "--scenarios", "1", "--no-plots", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    summary = pd.read_csv(out / "summary.csv")
    assert summary["completed"].all() and (summary["flag"].isna() | (summary["flag"] == "")).all()
    # (its speed is the benchmark's business, python -m safeil_sumo.bench: no wall-clock bound
    # here, which a loaded or slower machine would fail)


@pytest.mark.parametrize("args, message", [
    (["--net", "n74", "--from-km", "28", "--to-km", "31"], "outside n74"),
    (["--net", "n74", "--from-km", "3", "--to-km", "2"], "shorter than"),
    (["--net", "curved500", "--from-km", "1"], "need --net n74"),
    (["--net", "n74", "--route", "main0"], "--route needs"),
])
def test_run_n74_bad_stretch_gives_one_line_and_exit_2(tmp_path, capsys, args, message):
    out = tmp_path / "res"
    try:
        code = main([*args, "--out", str(out)])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and "Traceback" not in err
    assert not out.exists()


def _traffic_drive(seed: int = 0):
    from safeil_sumo import api

    sc = api.scenario("n74", 0, seed, from_km=4.0, to_km=5.5, traffic="dense")
    return sc, api.run_scenarios([sc], "analytic")


@pytest.mark.sumo
def test_traffic_leaders_change_and_the_gap_stays_consistent():
    """Real libsumo: dense n74 traffic across the merge of ramp 1; the leader is SUMO's."""
    sc, result = _traffic_drive()
    assert sc.leader is None and sc.traffic is not None and sc.traffic.density == "dense"
    s, log = result.summary.iloc[0], result.log
    assert s["end_reason"] == "completed", s["error"]
    following = log[log["leader_no"].notna()]
    assert following["leader_no"].nunique() >= 2 and s["leaders_met"] >= 2  # it changes
    changes = int((following["leader_no"].diff().fillna(0) != 0).sum())
    assert changes >= 1 and s["cut_ins_met"] <= changes
    gap = following["gap"].to_numpy()
    assert np.isfinite(gap).all() and (gap > 0).all()
    assert (following["leader_v"] > 0).all() and np.isfinite(following["ttc"]).any()
    # the radar sees the leader it is given: sensed distance (held between 10 Hz plans, so a
    # leader change shows up to 0.1 s late) ~ true gap while in range
    seen = following[following["d_lead_sensed"] < 140]
    err = (seen["d_lead_sensed"] - seen["gap"]).abs()
    assert len(seen) > 100 and err.median() < 0.5 and err.quantile(0.95) < 2.0
    assert s["km_driven"] == pytest.approx(1.5, abs=0.05)
    assert s["collision_events"] == 0 and s["collision_per_100km"] == 0.0


@pytest.mark.sumo
def test_traffic_is_seeded():
    a = _traffic_drive(3)[1].log
    b = _traffic_drive(3)[1].log
    pd.testing.assert_frame_equal(a, b)


def test_traffic_needs_n74(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--net", "curved500", "--traffic", "dense", "--out", str(tmp_path / "r")])
    assert exc.value.code == 2 and "--traffic needs --net n74" in capsys.readouterr().err


@pytest.mark.sumo
def test_sweep_over_n74_stretches(tmp_path, capsys):
    """Sweeps take the same stretch and traffic options as run; their tasks drive the stretch."""
    from safeil_sumo.sweep import main as sweep_main

    out = tmp_path / "sweep"
    code = sweep_main(["--net", "n74", "--from-km", "0", "--to-km", "1", "--policy",
                       "analytic", "--scenarios", "2", "--workers", "1", "--out", str(out),
                       "--no-progress"])
    assert code == 0, capsys.readouterr().err
    summary = pd.read_csv(out / "summary.csv")
    assert len(summary) == 2 and summary["completed"].all()
    assert summary["km_driven"].between(0.95, 1.1).all()
    capsys.readouterr()
    code = sweep_main(["--net", "curved500", "--traffic", "dense", "--policy", "analytic",
                       "--scenarios", "1", "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "n74" in err[0]
