"""Routes over several SUMO edges: the route builder on hand-written nets (no SUMO), and the
closed loop in real libsumo across a junction between a straight and a curved edge."""

from __future__ import annotations

import math

import numpy as np
import pytest

from safeil_sumo.roads.road import NetworkError, load_road
from safeil_sumo.roads.route import load_route
from safeil_sumo.sim.sensors import current_lane_index
from safeil_sumo.sim.sumo_setup import _depart

# A (2 lanes) -> junction J (internal lanes) -> B (3 lanes: a lane gained on the RIGHT, so
# SUMO's indices shift by one) -> C (1 lane, no internal lane; only B_2 continues). C_0's SUMO
# length is 10 % longer than its shape, as on a curved edge's outer lane.
TINY_NET = """<net version="1.20">
    <edge id=":J_0" function="internal">
        <lane id=":J_0_0" index="0" speed="30" length="2.00" width="3.50"
              shape="100,-1.75 102,-1.75"/>
        <lane id=":J_0_1" index="1" speed="30" length="2.00" width="3.50"
              shape="100,1.75 102,1.75"/>
    </edge>
    <edge id="A" from="a" to="J">
        <lane id="A_0" index="0" speed="30" length="100" width="3.50" shape="0,-1.75 100,-1.75"/>
        <lane id="A_1" index="1" speed="30" length="100" width="3.50" shape="0,1.75 100,1.75"/>
    </edge>
    <edge id="B" from="J" to="K">
        <lane id="B_0" index="0" speed="30" length="100" width="3.50" shape="102,-5.25 202,-5.25"/>
        <lane id="B_1" index="1" speed="30" length="100" width="3.50" shape="102,-1.75 202,-1.75"/>
        <lane id="B_2" index="2" speed="30" length="100" width="3.50" shape="102,1.75 202,1.75"/>
    </edge>
    <edge id="C" from="K" to="c">
        <lane id="C_0" index="0" speed="30" length="110" width="3.50" shape="202,1.75 302,1.75"/>
    </edge>
    <connection from="A" to="B" fromLane="0" toLane="1" via=":J_0_0" dir="s" state="M"/>
    <connection from="A" to="B" fromLane="1" toLane="2" via=":J_0_1" dir="s" state="M"/>
    <connection from=":J_0" to="B" fromLane="0" toLane="1" dir="s" state="M"/>
    <connection from=":J_0" to="B" fromLane="1" toLane="2" dir="s" state="M"/>
    <connection from="B" to="C" fromLane="2" toLane="0" dir="s" state="M"/>
</net>
"""


@pytest.fixture
def tiny_net(tmp_path):
    path = tmp_path / "tiny.net.xml"
    path.write_text(TINY_NET)
    return path


def test_route_follows_the_connections_and_concatenates_the_lanes(tiny_net) -> None:
    road = load_route(tiny_net, ["A", "B", "C"], ego_lane=1)
    assert road.route_edges == ("A", "B", "C") and road.edge_id == "A" and road.ego_lane == 1
    assert [p.lane_id for p in road.ego_pieces] == ["A_1", ":J_0_1", "B_2", "C_0"]
    assert [p.internal for p in road.ego_pieces] == [False, True, False, False]
    assert [p.route_index for p in road.ego_pieces] == [0, 0, 1, 2]
    ego = road.lanes[1].centre
    assert ego.length == pytest.approx(302.0)
    np.testing.assert_allclose(ego.points[[0, -1]], [[0, 1.75], [302, 1.75]])
    assert (road.path_start_s, road.path_end_s) == (0.0, pytest.approx(302.0))
    # the boundaries are the concatenated centre offset by half a lane
    _, d = road.lanes[1].left_boundary.project(np.array([[150.0, 3.5], [280.0, 3.5]]))
    np.testing.assert_allclose(d, 0.0, atol=1e-9)
    # the SUMO length scales positions per SUMO lane (C_0: 110 m on a 100 m shape)
    assert road.piece_at(50.0).scale == pytest.approx(1.0)
    assert road.piece_at(250.0).scale == pytest.approx(1.1)


def test_a_neighbour_that_ends_stops_being_offered(tiny_net) -> None:
    road = load_route(tiny_net, ["A", "B", "C"], ego_lane=1)
    right = road.lanes[0]  # A_0 -> B_1, which does not continue onto C
    assert right.centre.length == pytest.approx(202.0)
    assert right.ends_at_s == pytest.approx(202.0) and road.lanes[1].ends_at_s == math.inf
    assert road.lanes_at(150.0) == (0, 1) and road.lanes_at(250.0) == (1, 1)
    # the camera sees the right lane before its end, the ego's own lane after it
    assert current_lane_index(road, np.array([150.0, -1.75])) == 0
    assert current_lane_index(road, np.array([250.0, -1.75])) == 1


def test_the_lane_index_shift_of_a_gained_lane_is_followed(tiny_net) -> None:
    road = load_route(tiny_net, ["A", "B"], ego_lane=0)
    assert [p.lane_id for p in road.ego_pieces] == ["A_0", ":J_0_0", "B_1"]
    assert road.lanes[1].ends_at_s == math.inf  # A_1 -> B_2: the same neighbour on B
    assert road.lanes[1].centre.length == pytest.approx(202.0)


def test_one_edge_is_load_road(tiny_net) -> None:
    a, b = load_route(tiny_net, ["B"], 1), load_road(tiny_net, "B", 1)
    assert a.route_edges == b.route_edges == ("B",) and a.ego_pieces == b.ego_pieces
    assert [ln.lane_id for ln in a.lanes] == [ln.lane_id for ln in b.lanes]
    for la, lb in zip(a.lanes, b.lanes, strict=True):
        np.testing.assert_array_equal(la.centre.points, lb.centre.points)


@pytest.mark.parametrize(
    "edges, lane, message",
    [
        (["A", "X"], 1, "route edge 'X' does not exist (edges: A, B, C)"),
        (["A", "C"], 1, "route edge 'A' does not connect to 'C' (it leads to: B)"),
        (["B", "A"], 1, "does not connect to 'A'"),
        (["A", "B", "C"], 0, "the ego lane B_1 does not continue from edge 'B' onto 'C'"),
        (["A", "B", "C"], 0, "(only lanes 2 of 'B' do)"),
        (["A", "B"], 2, "needs lane index 2 but edge 'A' has 2 lane(s)"),
        ([], 0, "at least one edge"),
    ],
)
def test_a_refused_route_says_why_in_one_line(tiny_net, edges, lane, message) -> None:
    with pytest.raises(NetworkError) as exc:
        load_route(tiny_net, edges, lane)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_a_lane_width_change_is_refused(tmp_path) -> None:
    net = tmp_path / "w.net.xml"
    net.write_text(TINY_NET.replace('id="B_2" index="2" speed="30" length="100" width="3.50"',
                                    'id="B_2" index="2" speed="30" length="100" width="3.20"'))
    with pytest.raises(NetworkError, match="changes width from 3.5 m .A_1. to 3.2 m .B_2."):
        load_route(net, ["A", "B"], 1)


def test_departures_are_placed_on_the_right_edge(tiny_net) -> None:
    road = load_route(tiny_net, ["A", "B", "C"], ego_lane=1)
    assert _depart(road, 50.0, "leader") == (0, "1", "50.000", 1.0)
    k, lane, pos, scale = _depart(road, 250.0, "leader")
    assert (k, lane, pos, scale) == (2, "0", "52.800", pytest.approx(1.1))  # 48 m on C_0
    with pytest.raises(ValueError, match="inside junction lane :J_0_1"):
        _depart(road, 101.0, "leader")
    with pytest.raises(ValueError, match="beyond the end of the road"):
        _depart(road, 400.0, "leader")


def test_a_sweep_spec_without_a_route_keeps_its_json_and_task_id() -> None:
    from safeil_sumo.experiments.sweep_executor import spec_fields, task_id
    from safeil_sumo.scenarios.spec import Task

    plain = Task.of(net="x.net.xml")
    assert "route" not in plain.to_json()  # task ids of earlier sweeps are unchanged
    routed = Task.of(net="x.net.xml", route=["E0", "E1"])
    assert routed.scenario.route == ("E0", "E1") and routed.to_json()["route"] == ["E0", "E1"]
    assert Task.from_json(routed.to_json()) == routed
    assert task_id(routed) != task_id(plain)
    assert spec_fields(routed)["route"] == "E0 E1"


# -- closed loop in libsumo ----------------------------------------------------------------------

STRAIGHT_M = 300.0  # first edge: straight, east from the origin [m]
RADIUS_M = 600.0  # second edge: a left-turning arc of the road centre line [m]
ARC_M = 500.0


@pytest.fixture(scope="module")
def two_edge_net(tmp_path_factory):
    """A straight edge, a junction, and a curved edge (3 lanes x 3.5 m) built by netconvert."""
    from safeil_sumo.roads.network import run_netconvert

    work = tmp_path_factory.mktemp("two_edge")
    theta = np.linspace(0.0, ARC_M / RADIUS_M, 26)
    arc = np.stack([STRAIGHT_M + RADIUS_M * np.sin(theta), RADIUS_M * (1 - np.cos(theta))], 1)
    shape = " ".join(f"{x:.4f},{y:.4f}" for x, y in arc)
    (work / "t.nod.xml").write_text(
        f'<nodes>\n  <node id="a" x="0" y="0"/>\n  <node id="j" x="{STRAIGHT_M}" y="0"/>\n'
        f'  <node id="b" x="{arc[-1, 0]:.4f}" y="{arc[-1, 1]:.4f}"/>\n</nodes>\n')
    edge = ('  <edge id="{id}" from="{a}" to="{b}" numLanes="3" width="3.5" speed="36.1" '
            'spreadType="center"{extra}/>\n')
    (work / "t.edg.xml").write_text(
        "<edges>\n" + edge.format(id="E0", a="a", b="j", extra="")
        + edge.format(id="E1", a="j", b="b", extra=f' shape="{shape}"') + "</edges>\n")
    run_netconvert("t", work, "tests/roads/test_route.py")
    return work / "t.net.xml"


def _scenario(net, lane: int, gap: float = 50.0, leader_speed: float = 27.0):
    from safeil_sumo.sim.leaders import constant
    from safeil_sumo.sim.loop_types import Scenario

    road = load_route(net, ["E0", "E1"], lane)
    return Scenario("route", road, constant(leader_speed), ego_speed_mps=30.0,
                    initial_gap_m=gap)


def _run(net, lane: int, gap: float = 50.0, leader_speed: float = 27.0):
    from safeil_sumo.planners.analytic import AnalyticPlanner
    from safeil_sumo.sim.runner import run_scenario

    scenario = _scenario(net, lane, gap, leader_speed)
    return scenario.road, run_scenario(scenario, AnalyticPlanner())


@pytest.mark.sumo
def test_a_batch_drives_the_route_to_its_end_like_run_scenario(two_edge_net) -> None:
    """Across the junction and up to the route's end, where SUMO would let an ego that its
    own step carries past the end arrive: both loops place it with moveToXY there."""
    from safeil_sumo.planners.analytic import AnalyticPlanner
    from safeil_sumo.sim.batch import run_batch

    _, scalar = _run(two_edge_net, lane=1)
    (batch,) = run_batch([_scenario(two_edge_net, 1)], AnalyticPlanner())
    assert scalar.summary["end_reason"] == batch.summary["end_reason"] == "completed"
    assert len(batch.log) == len(scalar.log)
    for col in ("s", "d", "gap", "leader_x"):
        np.testing.assert_allclose(batch.log[col], scalar.log[col], rtol=0, atol=1e-6)


@pytest.mark.sumo
def test_the_analytic_planner_drives_across_the_junction(two_edge_net) -> None:
    road, rollout = _run(two_edge_net, lane=1)
    log, summary = rollout.log, rollout.summary
    assert summary["end_reason"] == "completed" and summary["completed"], summary
    assert not log["lane_departure"].any() and summary["flag"] == ""
    junction_s = road.ego_pieces[1].s0
    assert log["s"].min() < junction_s - 50 and log["s"].max() >= road.path_end_s
    # the camera's lane lines do not jump at the seam between the two edges' lanes
    plans = log.drop_duplicates("plan_t")
    for col in ("c0l", "c0r"):
        assert np.abs(np.diff(plans[col].to_numpy())).max() < 0.1, col
    # the leader, which started on E0, is still sensed on E1 (behind the junction)
    lead_s, _ = road.lanes[1].centre.project(log[["leader_x", "leader_y"]].to_numpy())
    after = plans[(lead_s[plans.index] > junction_s + 20) & (plans["gap"] < 100)]
    assert len(after) > 50
    assert np.isfinite(after["gap"]).all()
    np.testing.assert_allclose(after["d_lead_sensed"], after["gap"], atol=1.0)


@pytest.mark.sumo
def test_the_leader_keeps_its_speed_on_scaled_lanes(two_edge_net) -> None:
    """On the outer lane of the curve SUMO's positions are scaled (lanes share the edge's
    length); the runner scales the leader's speed per SUMO lane, so its true speed stays the
    profile's and its position drifts by centimetres only (one step at the internal lane)."""
    road, rollout = _run(two_edge_net, lane=0)
    assert abs(road.piece_at(400.0).scale - 1.0) > 0.004  # the outer lane is scaled
    log = rollout.log
    on = np.isfinite(log["leader_x"].to_numpy())
    np.testing.assert_allclose(log.loc[on, "leader_v"], 27.0, atol=1e-6)
    lead_s, _ = road.lanes[0].centre.project(log.loc[on, ["leader_x", "leader_y"]].to_numpy())
    t = log.loc[on, "t"].to_numpy()
    drift = (lead_s - lead_s[0]) - 27.0 * (t - t[0])
    assert lead_s[-1] > road.ego_pieces[1].s1 + 300  # well into the curved edge
    assert np.abs(drift).max() < 0.05


@pytest.mark.sumo
def test_a_leader_beyond_the_first_edge_departs_on_the_next(two_edge_net) -> None:
    _, rollout = _run(two_edge_net, lane=1, gap=350.0)
    log = rollout.log
    assert rollout.summary["end_reason"] == "completed", rollout.summary["error"]
    assert log["gap"].iloc[0] == pytest.approx(350.0, abs=0.1)
    assert log["leader_x"].iloc[0] > STRAIGHT_M


@pytest.mark.sumo
def test_run_cli_with_a_route(two_edge_net, tmp_path, capsys) -> None:
    import json

    from safeil_sumo.run import main

    out = tmp_path / "res"
    code = main(["--net", str(two_edge_net), "--route", "E0", "E1", "--policy", "analytic",
                 "--scenarios", "1", "--no-plots", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert "1/1 scenarios completed" in capsys.readouterr().out
    assert json.loads((out / "manifest.json").read_text())["config"]["route"] == ["E0", "E1"]
    # without the route, the error names the option to use
    assert main(["--net", str(two_edge_net), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "--route EDGE [EDGE ...]" in err and err.count("\n") == 1
