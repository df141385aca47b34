"""``--lane`` of run and sweep: the ego's lane on n74 (right/left) or on a .net.xml route (a SUMO
lane index of the first edge); bad values are one error line and exit 2."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from safeil_sumo import api
from safeil_sumo.experiments.sweep_executor import task_id
from safeil_sumo.roads.n74 import LANE_WIDTH_M, n74_dir
from safeil_sumo.scenarios.spec import ScenarioSpec, Task, lane_for_net

N74_NET = str(n74_dir() / "n74.net.xml")


def test_lane_for_net():
    assert lane_for_net("n74", None) == "" and lane_for_net("n74", "left") == "left"
    assert lane_for_net("x.net.xml", "02") == "2"
    for net, lane, message in (("n74", "middle", "right or left"),
                               ("n74", "1", "right or left"),
                               ("x.net.xml", "-1", "lane index >= 0"),
                               ("x.net.xml", "left", "lane index >= 0"),
                               ("curved500", "1", "needs --net n74 or a .net.xml")):
        with pytest.raises(ValueError, match=message):
            lane_for_net(net, lane)


def test_spec_lane_is_validated_and_left_out_of_the_task_id_when_default():
    plain = Task.of(net="n74", from_km=1.0, to_km=2.0)
    assert "lane" not in plain.to_json()
    assert task_id(plain) == task_id(Task.of(net="n74", from_km=1.0, to_km=2.0, lane=""))
    left = Task.of(net="n74", from_km=1.0, to_km=2.0, lane="left")
    assert left.to_json()["lane"] == "left" and task_id(left) != task_id(plain)
    with pytest.raises(ValueError, match="right or left"):
        ScenarioSpec(net="n74", lane="centre")


def test_n74_left_lane_is_the_main_lane_left_of_the_right_one():
    right, left = api.road("n74", [], 4.0, 5.0), api.road("n74", [], 4.0, 5.0, "left")
    assert right.meta["lane"] == "right" and left.meta["lane"] == "left"
    a = right.lanes[right.ego_lane].centre.point_at(right.path_start_s)
    b = left.lanes[left.ego_lane].centre.point_at(left.path_start_s)
    assert float(np.linalg.norm(np.asarray(a[0]) - np.asarray(b[0]))) == pytest.approx(
        LANE_WIDTH_M, abs=0.05)


def test_route_lane_index_is_on_the_first_edge():
    road = api.road(N74_NET, ["main0", "merge1"], lane=1)
    assert road.ego_pieces[0].lane_id == "main0_1"
    assert road.ego_pieces[-1].lane_id == "merge1_2"  # the left main lane, shifted by the acc lane


def _err_lines(capsys) -> list[str]:
    return [ln for ln in capsys.readouterr().err.strip().splitlines() if "error" in ln]


@pytest.mark.parametrize("argv, message", [
    (["--net", "n74", "--lane", "middle"], "--lane with --net n74 is right or left"),
    (["--net", "curved500", "--lane", "0"], "--lane needs --net n74 or a .net.xml"),
    (["--net", N74_NET, "--route", "main0", "merge1", "--lane", "x"], "lane index >= 0"),
])
def test_run_bad_lane_is_one_error_line(tmp_path, capsys, argv, message):
    from safeil_sumo.run import main

    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(tmp_path / "r")])
    err = _err_lines(capsys)
    assert exc.value.code == 2 and len(err) == 1 and message in err[0]
    assert not (tmp_path / "r").exists()


def test_a_lane_that_appears_later_says_where_to_start(tmp_path, capsys):
    """main0 has 2 lanes, merge1 3 (its acceleration lane): lane 2 exists on merge1 only."""
    from safeil_sumo.run import main
    from safeil_sumo.sweep import main as sweep_main

    argv = ["--net", N74_NET, "--route", "main0", "merge1", "--lane", "2"]
    assert main([*argv, "--out", str(tmp_path / "r")]) == 2
    err = _err_lines(capsys)
    assert len(err) == 1 and err[0].startswith("error:")
    assert "edge 'main0' has 2 lane(s)" in err[0] and "--route merge1" in err[0]
    assert sweep_main([*argv, "--policy", "analytic", "--scenarios", "1",
                       "--out", str(tmp_path / "s")]) == 2
    err = _err_lines(capsys)
    assert len(err) == 1 and "--route merge1" in err[0]
    code = sweep_main(["--net", "n74", "--lane", "up", "--policy", "analytic",
                       "--out", str(tmp_path / "s2")])
    err = _err_lines(capsys)
    assert code == 2 and len(err) == 1 and "right or left" in err[0]


@pytest.mark.sumo
def test_run_and_sweep_drive_the_left_lane_of_n74(tmp_path, capsys):
    """Real libsumo: 300 m of n74 in the left main lane, by run and by sweep."""
    from safeil_sumo.run import main
    from safeil_sumo.sweep import main as sweep_main

    out = tmp_path / "run"
    assert main(["--net", "n74", "--from-km", "0.2", "--to-km", "0.5", "--lane", "left",
                 "--policy", "analytic", "--scenarios", "1", "--no-plots",
                 "--out", str(out)]) == 0, capsys.readouterr().err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["lane"] == "left"
    steps = pd.read_parquet(out / "steps.parquet")
    left = api.road("n74", [], 0.2, 0.5, "left")
    _, d = left.lanes[left.ego_lane].centre.project(
        steps[["front_x", "front_y"]].to_numpy())
    assert np.abs(d).max() < 0.5  # on the left lane's centre line all along
    summary = pd.read_csv(out / "summary.csv")
    assert summary["completed"].all()
    code = sweep_main(["--net", "n74", "--from-km", "0.2", "--to-km", "0.5", "--lane", "left",
                       "--policy", "analytic", "--scenarios", "1", "--workers", "1",
                       "--no-progress", "--out", str(tmp_path / "sweep")])
    assert code == 0, capsys.readouterr().err
    table = pd.read_csv(tmp_path / "sweep" / "summary.csv")
    assert table["lane"].tolist() == ["left"] and table["completed"].all()
