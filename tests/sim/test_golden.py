"""Golden closed-loop logs: a change of the loop's numbers must be deliberate, on every machine.

Each scenario runs a short real libsumo closed loop on curved500 and compares its per-step log
with a stored reference, ``tests/golden/<name>.npz``:

- the discrete outcomes exactly: row count, end reason, and every step's lane-departure, TTC and
  collision flags (so the step of each flag);
- the continuous columns within tolerances that hold across machines: float64 results are not
  bit-identical across CPUs (SIMD code paths: AVX-512 vs AVX2) nor across numpy / OpenBLAS
  releases. Measured: the same logs on this project's AVX-512 machine and with numpy's AVX-512
  groups and OpenBLAS's AVX-512 kernels switched off differ by at most 3e-13 (ttc) and 6e-14 m
  (positions); the tolerances (tests/fixtures_golden.py: 1e-6 m, 1e-6 m/s, ...) leave six orders
  of margin and still catch any change of the loop's behaviour.

Bit-identity is what can be promised on ONE machine with one set of library versions:
``test_same_run_twice_is_bit_identical`` runs each scenario in this process and again in a new
process and demands equal SHA-256 hashes of the logs.

A change of the references is allowed only in its own commit that says why and shows the
largest difference. ``python tests/sim/test_golden.py --write`` rewrites them;
``python tests/sim/test_golden.py --hashes`` prints this machine's log hashes as JSON.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bad_policies import DriftLeft, blind_cruise
from fixtures_golden import GOLDEN_COLUMNS, GOLDEN_DIR, compare_with_reference, log_hash

from safeil_sumo.planners.analytic import AnalyticPlanner
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim.leaders import constant, piecewise
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.runner import run_scenario


def _noisy_analytic(road):
    """Analytic planner, all sensor noises on, a braking and re-accelerating leader."""
    sc = safety_scenario(road, 3, master_seed=7)
    sensors = replace(sc.sensors, radar_noise_m=0.3, radar_speed_noise_mps=0.2,
                      lane_noise_c0_m=0.02, lane_noise_c1=0.002, quantization_m=0.05)
    leader = piecewise([0.0, 2.0, 4.0, 6.0], [28.0, 28.0, 22.0, 30.0])
    sc = replace(sc, sensors=sensors, leader=leader, ego_lateral_offset_m=0.3,
                 ego_heading_offset_rad=0.01)
    return sc, AnalyticPlanner(), LoopConfig(max_time_s=8.0)


def _drift_left(road):
    """Lane departure, then off-road: the leader is lost from the radar corridor on the way."""
    sc = Scenario("drift", road, constant(30.0), 30.0, 50.0, seed=1)
    return sc, DriftLeft(), LoopConfig(max_time_s=12.0)


def _blind_collision(road):
    """Lane keeping at 30 m/s that ignores a 25 m/s leader: TTC flag, then a collision."""
    sc = Scenario("blind", road, constant(25.0), 30.0, 50.0, seed=2)
    planner = blind_cruise()
    # the collision is the point: without the brake guard, which would prevent it
    return sc, planner, LoopConfig(max_time_s=12.0, brake_guard=None)


def _free_road(road):
    """No leader at all: the radar's free-road substitute feeds the planner."""
    sc = Scenario("free", road, None, 25.0, 50.0, seed=4)
    return sc, AnalyticPlanner(), LoopConfig(max_time_s=4.0)


SCENARIOS = {
    "noisy_analytic": _noisy_analytic,
    "drift_left": _drift_left,
    "blind_collision": _blind_collision,
    "free_road": _free_road,
}

# (rows, end_reason) of each reference, also stored in its file: read here so that a rewrite of
# the references cannot silently change the outcome of a scenario
EXPECTED_OUTCOME = {
    "noisy_analytic": (800, "timeout"),
    "drift_left": (343, "off_road"),
    "blind_collision": (999, "collision"),
    "free_road": (400, "timeout"),
}

def run_golden(name: str, road):
    sc, policy, loop = SCENARIOS[name](road)
    return run_scenario(sc, policy, loop)


def write_reference(name: str, result) -> Path:
    """Store one scenario's golden columns, row count and end reason (float64, compressed)."""
    GOLDEN_DIR.mkdir(exist_ok=True)
    path = GOLDEN_DIR / f"{name}.npz"
    cols = {c: result.log[c].to_numpy(dtype=np.float64) for c in GOLDEN_COLUMNS}
    np.savez_compressed(path, rows=len(result.log), end_reason=result.summary["end_reason"],
                        **cols)
    return path


@pytest.mark.sumo
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_closed_loop_log_matches_reference(name, curved500):
    r = run_golden(name, curved500)
    assert r.summary["end_reason"] != "error", r.summary["error"]
    assert (len(r.log), r.summary["end_reason"]) == EXPECTED_OUTCOME[name]
    with np.load(GOLDEN_DIR / f"{name}.npz") as ref:
        problems = compare_with_reference(r.log, r.summary["end_reason"], ref)
    assert not problems, "\n".join(problems)


@pytest.mark.sumo
def test_reference_comparison_catches_small_changes(curved500):
    """The comparison is not vacuous: a 1e-5 m shift of x, one flag step moved, or a changed
    end reason each fail it; round-off (1e-12) passes."""
    r = run_golden("blind_collision", curved500)
    with np.load(GOLDEN_DIR / "blind_collision.npz") as f:
        ref = {k: f[k] for k in f.files}
    log = r.log.copy()
    assert compare_with_reference(log, "collision", ref) == []
    log["x"] = log["x"] + 1e-12
    assert compare_with_reference(log, "collision", ref) == []
    log["x"] = log["x"] + 1e-5
    assert any(p.startswith("x:") for p in compare_with_reference(log, "collision", ref))
    log = r.log.copy()
    flag = log["ttc_flag"].to_numpy(dtype=np.float64)
    flag[np.flatnonzero(flag > 0)[0]] = 0.0  # the TTC flag one step later
    log["ttc_flag"] = flag
    assert any(p.startswith("ttc_flag:") for p in compare_with_reference(log, "collision", ref))
    assert compare_with_reference(r.log, "timeout", ref)


def _hashes(road) -> dict[str, str]:
    return {name: log_hash(run_golden(name, road).log) for name in SCENARIOS}


@pytest.mark.sumo
def test_same_run_twice_is_bit_identical(curved500):
    """Determinism on one machine: the same scenarios in this process and in a fresh process
    give logs equal bit for bit (no state leaks between runs, no unseeded draw)."""
    here = _hashes(curved500)
    assert _hashes(curved500) == here
    import safeil_sumo

    # the child imports the same package as this process (a checkout may shadow an install)
    root = str(Path(safeil_sumo.__file__).parent.parent)
    tests = str(Path(__file__).resolve().parents[1])  # the fixtures_*.py modules
    env = {**os.environ,
           "PYTHONPATH": os.pathsep.join([root, tests, os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, __file__, "--hashes"], capture_output=True, text=True,
                         check=True, env=env)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == here


if __name__ == "__main__":  # --write: rewrite the references; --hashes: print the log hashes
    from safeil_sumo.roads.catalogue import resolve_net
    from safeil_sumo.roads.road import load_road

    road = load_road(resolve_net("curved500"))
    if "--hashes" in sys.argv:
        print(json.dumps(_hashes(road)))
    elif "--write" in sys.argv:
        for name in SCENARIOS:
            r = run_golden(name, road)
            print(write_reference(name, r), len(r.log), r.summary["end_reason"])
    else:
        sys.exit("usage: python tests/sim/test_golden.py --write | --hashes")


def test_lane_camera_equals_the_reference_camera(curved500):
    """The loop's O(1) camera gives camera_lane_lines' lines bit for bit, also off the lane."""
    from safeil_sumo.sim import sensors as sen

    cfg = sen.SensorConfig()
    camera = sen.LaneCamera(curved500, cfg)
    centre = curved500.lanes[curved500.ego_lane].centre
    rng = np.random.default_rng(1)
    s = 5.0
    while s < centre.length - 5.0:
        s += rng.uniform(0.0, 6.0)
        p, h = centre.point_at(s)
        xy = p + rng.uniform(-6.0, 6.0) * np.array([-np.sin(h), np.cos(h)])
        yaw = float(h) + rng.uniform(-0.1, 0.1)
        a = sen.camera_lane_lines(curved500, xy, yaw, cfg)
        b = camera.lane_lines(xy, yaw)
        assert a[2] == b[2]
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_polyfit3_equals_numpy_polyfit():
    from safeil_sumo.sim.sensors import polyfit3

    rng = np.random.default_rng(2)
    for _ in range(200):
        x = np.sort(rng.uniform(-5.0, 80.0, 16))
        y = rng.normal(size=4) @ np.vstack([x**0, x, x**2 * 1e-3, x**3 * 1e-5]) + rng.normal(
            scale=0.01, size=16)
        assert np.array_equal(polyfit3(x, y), np.polynomial.polynomial.polyfit(x, y, 3))
