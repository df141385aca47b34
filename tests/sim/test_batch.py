"""run_batch (N scenarios in one libsumo simulation) gives run_scenario's answers, one by one.

A mixed batch on curved500: a clean completion, a lane departure then off-road (DriftLeft), a
collision (blind cruise), an early timeout and a free road, with per-scenario policies (two
scenarios share one analytic planner object: one batched plan call). Every log must equal the
scalar run's to round-off, and the summaries must agree (wall times aside).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from bad_policies import DriftLeft, blind_cruise

from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.roads.catalogue import resolve_net
from safeil_sumo.roads.road import load_road
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim.batch import run_batch
from safeil_sumo.sim.batch_net import (
    batch_net,
    copies_xml,
    copy_offset_m,
    mixed_batch_net,
    mixed_copies_xml,
)
from safeil_sumo.sim.leaders import constant, piecewise
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.runner import run_scenario

pytest.importorskip("libsumo")

WALL_KEYS = ("wall_time_s", "steps_per_s")
ATOL_M = 1e-6  # the bound on trajectory differences [m]


@pytest.fixture(scope="module")
def road():
    return load_road(resolve_net("curved500"))


def _mixed(road):
    analytic = AnalyticPlanner()
    noisy = safety_scenario(road, 3, master_seed=7)
    noisy = replace(
        noisy, name="noisy", max_time_s=8.0, ego_lateral_offset_m=0.3, ego_heading_offset_rad=0.01,
        leader=piecewise([0.0, 2.0, 4.0, 6.0], [28.0, 28.0, 22.0, 30.0]),
        sensors=replace(noisy.sensors, radar_noise_m=0.3, radar_speed_noise_mps=0.2,
                        lane_noise_c0_m=0.02, lane_noise_c1=0.002, quantization_m=0.05))
    return [
        (replace(safety_scenario(road, 0), name="clean"), analytic),
        (Scenario("drift", road, constant(30.0), 30.0, 50.0, seed=1), DriftLeft()),
        (Scenario("blind", road, constant(25.0), 30.0, 50.0, seed=2), blind_cruise()),
        (noisy, analytic),
        (Scenario("free", road, None, 25.0, 50.0, seed=4, max_time_s=4.0), AnalyticPlanner()),
    ]


def _largest_difference(batch, scalar) -> float:
    """The largest difference of any logged quantity but TTC (relative there)."""
    with np.errstate(invalid="ignore"):  # inf - inf in gap columns without a leader
        return max(float(np.nanmax(np.abs(np.where(
            np.isinf(s.log.to_numpy(float)), 0, b.log.to_numpy(float) - s.log.to_numpy(float))
        )[:, [c != "ttc" for c in s.log.columns]])) for b, s in zip(batch, scalar, strict=True))


def _assert_same(batch, scalar, atol=ATOL_M):
    """Same rows, flags, flag times (to the step) and end reasons; floats within ``atol``."""
    for b, s in zip(batch, scalar, strict=True):
        name = s.summary["scenario"]
        assert list(b.log.columns) == list(s.log.columns)
        assert len(b.log) == len(s.log), name
        for col in s.log.columns:
            # TTC = gap / closing speed: a closing speed near 0 makes round-off relative
            np.testing.assert_allclose(b.log[col].to_numpy(), s.log[col].to_numpy(),
                                       rtol=1e-6 if col == "ttc" else 0, atol=atol,
                                       err_msg=f"{name}: {col}")
        for key, value in s.summary.items():
            if key in WALL_KEYS:
                continue
            got = b.summary[key]
            if isinstance(value, float) and not pd.isna(value) and key != "flag_time_s":
                assert got == value or abs(got - value) <= atol * max(1.0, abs(value)), (
                    name, key, got, value)
            else:
                assert got == value or (pd.isna(value) and pd.isna(got)), (name, key, got, value)


@pytest.mark.sumo
@pytest.mark.parametrize("placement", ["xy", "lane"])
def test_mixed_batch_equals_scalar_runs(road, placement):
    cases = _mixed(road)
    loop = LoopConfig(max_time_s=60.0, ego_placement=placement)
    scalar = [run_scenario(sc, p, loop) for sc, p in cases]
    reasons = [r.summary["end_reason"] for r in scalar]
    # the batch covers every way to end, at different steps
    assert reasons == ["completed", "off_road", "collision", "timeout", "timeout"]
    assert scalar[1].summary["flag"] == "lane_departure"
    assert len({len(r.log) for r in scalar}) == len(scalar)
    done = []
    batch = run_batch([sc for sc, _ in cases], [p for _, p in cases], loop,
                      on_done=lambda i, r: done.append(i))
    _assert_same(batch, scalar)
    assert sorted(done) == list(range(len(cases)))
    print(f"largest difference ({placement}): {_largest_difference(batch, scalar):.3g}")


@pytest.mark.sumo
def test_stop_on_flag_and_one_policy(road):
    """stop_on_flag ends scenarios at their flag step while the others go on; one policy."""
    planner = blind_cruise()
    cases = [Scenario(f"lead{v:.0f}", road, constant(v), 30.0, gap, seed=i)
             for i, (v, gap) in enumerate([(15.0, 50.0), (20.0, 50.0), (31.0, 50.0)])]
    # the flags are the point: without the brake guard, which would prevent them
    loop = LoopConfig(max_time_s=6.0, stop_on_flag=True, ego_placement="lane", brake_guard=None)
    scalar = [run_scenario(sc, planner, loop) for sc in cases]
    assert [r.summary["end_reason"] for r in scalar] == ["flag", "flag", "timeout"]
    _assert_same(run_batch(cases, planner, loop), scalar)


@pytest.mark.sumo
def test_summary_columns_give_the_same_summaries(road):
    """A batch that logs only SUMMARY_COLUMNS (the sweeps') summarises exactly as a full log,
    and a sweep's record (the leader-response metrics) reads nothing else."""
    from safeil_sumo.experiments.suite import response_metrics
    from safeil_sumo.sim.rollout_log import SUMMARY_COLUMNS

    cases = _mixed(road)
    loop = LoopConfig(max_time_s=10.0, ego_placement="lane")
    full = run_batch([sc for sc, _ in cases], [p for _, p in cases], loop)
    lean = run_batch([sc for sc, _ in cases], [p for _, p in cases], loop,
                     log_columns=SUMMARY_COLUMNS)
    for f, s in zip(full, lean, strict=True):
        assert list(s.log.columns) == list(SUMMARY_COLUMNS)
        pd.testing.assert_frame_equal(s.log, f.log[list(SUMMARY_COLUMNS)])
        assert ({k: v for k, v in s.summary.items() if k not in WALL_KEYS}
                == {k: v for k, v in f.summary.items() if k not in WALL_KEYS})
        assert response_metrics(s.log) == response_metrics(f.log)
    with pytest.raises(ValueError, match="unknown log column"):
        run_batch(cases[0][:1], cases[0][1], loop, log_columns=("t", "speed"))


@pytest.mark.sumo
def test_the_loop_runs_on_one_blas_thread(road):
    """Planner calls inside a batch see one BLAS thread (a sweep runs a worker per core), and
    the limit is lifted after the batch."""
    from threadpoolctl import threadpool_info

    def blas_threads() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    seen = []

    class Watching(AnalyticPlanner):
        def plan(self, features):
            seen.append(blas_threads())
            return super().plan(features)

    before = blas_threads()
    run_batch([safety_scenario(road, i) for i in range(2)], Watching(),
              LoopConfig(max_time_s=0.5))
    assert seen and all(threads == [1] * len(before) for threads in seen)
    assert blas_threads() == before


@pytest.mark.sumo
def test_placements_agree_on_the_paper_scenarios(road):
    """moveTo on lane coordinates gives the flags and trajectories of moveToXY: 10 paper
    scenarios of BC (it leaves its lane: the off-lane steps fall back to moveToXY) and blind
    cruises into slower leaders (SUMO's collision check at the same step: moveTo's position is
    where the step starts, so the step's own advance is taken off)."""
    from safeil_sumo.planners import registry as planner_registry

    cases = [safety_scenario(road, i) for i in range(10)]
    policy = planner_registry.load("bc")
    xy = run_batch(cases, policy, LoopConfig(ego_placement="xy"))
    lane = run_batch(cases, policy, LoopConfig(ego_placement="lane"))
    _assert_same(lane, xy, atol=0.0)
    crashes = [Scenario(f"crash{v:.0f}", road, constant(v), 30.0, 20.0, seed=i)
               for i, v in enumerate((10.0, 20.0, 26.0))]
    blind = blind_cruise()
    # collisions at speed, without the brake guard (which would brake them to a touch, where
    # the contact step depends on millimetres)
    xy = [run_scenario(sc, blind, LoopConfig(ego_placement="xy", brake_guard=None))
          for sc in crashes]
    assert [r.summary["end_reason"] for r in xy] == ["collision"] * 3
    _assert_same([run_scenario(sc, blind, LoopConfig(ego_placement="lane", brake_guard=None))
                  for sc in crashes], xy, atol=0.0)


def test_bad_batches_are_refused(road):
    from safeil_sumo.sim.recorded_ego import RecordedPath

    sc = safety_scenario(road, 0)
    kinematic = RecordedPath(np.array([0.0, 1.0]), np.array([[0.0, 0.0], [30.0, 0.0]]),
                             np.zeros(2), np.full(2, 30.0))
    with pytest.raises(ValueError, match="kinematic"):
        run_batch([sc, sc], [AnalyticPlanner(), kinematic])
    with pytest.raises(ValueError, match="policies"):
        run_batch([sc, sc], [AnalyticPlanner()])
    assert run_batch([], AnalyticPlanner()) == []


def test_copies_are_renamed_and_side_by_side(road, tmp_path):
    text = copies_xml(road.net_path, 2, 3000.0).decode()
    assert 'id="c0_road"' in text and 'id="c1_road_1"' in text and 'id="road"' not in text
    assert text.count("<location") == 1
    assert batch_net(road.net_path, 2, tmp_path, 3000.0) == batch_net(road.net_path, 2, tmp_path,
                                                                       3000.0)


@pytest.mark.sumo
@pytest.mark.parametrize("placement", ["xy", "lane"])
def test_batch_of_different_nets_equals_runs_on_each_net(road, placement):
    """Scenarios on curved500 and on straight (one repeated) in one simulation: each copy of
    its own net, side by side; every log equals the run on that net alone."""
    straight = load_road(resolve_net("straight"))
    analytic = AnalyticPlanner()
    cases = [
        (replace(safety_scenario(straight, 0), name="straight0", max_time_s=8.0), analytic),
        (replace(safety_scenario(road, 1), name="curved1", max_time_s=10.0), analytic),
        (Scenario("drift", straight, constant(30.0), 30.0, 50.0, seed=1, max_time_s=10.0),
         DriftLeft()),
    ]
    loop = LoopConfig(ego_placement=placement)
    scalar = [run_scenario(sc, p, loop) for sc, p in cases]
    assert scalar[2].summary["flag"] == "lane_departure"
    batch = run_batch([sc for sc, _ in cases], [p for _, p in cases], loop)
    _assert_same(batch, scalar)


def test_mixed_batch_net_places_copies_apart_and_unions_the_location(road, tmp_path):
    straight = resolve_net("straight")
    nets = [straight, road.net_path, straight]
    path, shifts = mixed_batch_net(nets, 1000.0, tmp_path)
    # straight is 2000 m long, curved500 530 m wide: neighbours >= 1000 m apart
    assert shifts == [0.0, 3000.0, 4530.0]
    text = path.read_text()
    assert 'id="c0_road"' in text and 'id="c1_road"' in text and 'id="c2_road_1"' in text
    assert text.count("<location") == 1
    assert 'convBoundary="0.000,0.000,6530.000,1435.511"' in text
    assert mixed_batch_net(nets, 1000.0, tmp_path) == (path, shifts)  # cached
    # copies of one net: batch_net's file, as the sweep has always built it
    offset = copy_offset_m(straight, 1000.0)
    assert mixed_batch_net([straight] * 3, 1000.0, tmp_path) == (
        batch_net(straight, 3, tmp_path, offset), [0, offset, 2 * offset])
    assert mixed_copies_xml([straight] * 3, [0, offset, 2 * offset]) == copies_xml(straight, 3,
                                                                                  offset)


def _with_type(src, dst, type_xml: str):
    """A copy of the net ``src`` with ``type_xml`` added after its ``<location>``."""
    text = src.read_text()
    end = text.index(">", text.index("<location")) + 1
    dst.write_text(text[:end] + "\n    " + type_xml + text[end:])
    return dst


def test_mixed_nets_union_types_and_refuse_conflicts(road, tmp_path):
    straight = resolve_net("straight")
    fast = _with_type(straight, tmp_path / "fast.net.xml", '<type id="hw" speed="33.33"/>')
    same = _with_type(road.net_path, tmp_path / "same.net.xml", '<type id="hw" speed="33.33"/>')
    other = _with_type(road.net_path, tmp_path / "other.net.xml", '<type id="lo" speed="20"/>')
    slow = _with_type(road.net_path, tmp_path / "slow.net.xml", '<type id="hw" speed="20.00"/>')
    text = mixed_copies_xml([fast, same, other], [0.0, 3000.0, 4530.0]).decode()
    assert text.count('<type id="hw"') == 1 and text.count('<type id="lo"') == 1
    with pytest.raises(ValueError, match=r"<type id='hw'> of .*slow.net.xml differs"):
        mixed_copies_xml([fast, slow], [0.0, 3000.0])
