"""The benchmark suite runs in quick mode (CI). It asserts nothing about time: only that every
figure is measured and written."""

import json
import math

import pytest

from safeil_sumo.bench import main

# every test here runs SUMO (tests/conftest.py: the sumo marker)
pytestmark = pytest.mark.sumo


def test_bench_quick_runs_and_writes_every_figure(tmp_path):
    out = tmp_path / "bench.json"
    assert main(["--quick", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    results = report["results"]
    for key in ("bare_sumo_steps_per_s", "closed_loop_libsumo_steps_per_s",
                "closed_loop_traci_steps_per_s", "scalar_ego_steps_per_s",
                "batched_ego_steps_per_s", "batched_over_scalar", "batched_ego_steps_per_s_n8_xy",
                "batched_n8_sumo_move_us_per_ego_step", "batched_n8_sense_us_per_ego_step",
                "sweep6_batched_2w_wall_s", "sweep_batched_parallel_efficiency_2w",
                "multi_edge_over_single_edge", "n74_1km_drive_wall_s",
                "gym_single_transitions_per_s", "gym_vector_n8_transitions_per_s",
                "gym_vector_over_single", "gym_vector_over_async", "gym_vector_over_sync",
                "gym_sync_traci_n8_transitions_per_s", "gym_vector_n8_peak_rss_mb"):
        assert key in results and math.isfinite(results[key]) and results[key] > 0
