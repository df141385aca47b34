"""Golden closed-loop logs: every speed-up of the loop must leave the results bit-identical.

Each scenario runs a short real libsumo closed loop on curved500 and hashes its per-step log:
SHA-256 over the column names and the float64 bytes of every column, in log order. The expected
hashes were computed from the loop BEFORE the performance work (issue 6); a change of a hash
means a change of the numbers, which is allowed only in its own commit that says why and shows
the largest difference of the logs (round-off level). ``python tests/test_golden.py`` prints the
current hashes (the values for EXPECTED).
"""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from bad_policies import DriftLeft, blind_cruise

from safeil_sumo.analytic import AnalyticPlanner
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim.leaders import constant, piecewise
from safeil_sumo.sim.runner import LoopConfig, Scenario, run_scenario


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
    return sc, planner, LoopConfig(max_time_s=12.0)


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

# (sha256 of the log, rows, end_reason), computed from the loop before the speed-ups
EXPECTED = {
    "noisy_analytic": (
        "40bf8ef1cd4590b66ef55603f8323fa44d8c39361ad214f7d2056f4cccafa4c0", 800, "timeout"),
    "drift_left": (
        "0cbae1dfcfdaf45a31edc5c08faf32e6bfed4395c0f6d22df30e3bcb758230f4", 343, "off_road"),
    "blind_collision": (
        "dbc3b4d35ea70ca90a2b40c3af5f23a60f9d511275e029041dfc489bf7640f1f", 999, "collision"),
    "free_road": (
        "4c0c831e4904dbf48afff0f5273c59949730b5ff56bfb5d22c0a0ae550cc32db", 400, "timeout"),
}


# the columns the hashes were computed over; columns added to the log later (the plan being
# tracked, for animations) are logged values, not new numbers of the loop
GOLDEN_COLUMNS = (
    "t", "x", "y", "yaw", "v", "vy", "yaw_rate", "steer", "front_x", "front_y", "steer_cmd",
    "accel_cmd", "s", "d", "d_min", "d_max", "c0l", "c1l", "c2l", "c0r", "c1r", "c2r",
    "v_lead_sensed", "d_lead_sensed", "leader_x", "leader_y", "leader_v", "gap", "ttc",
    "lane_departure", "ttc_flag", "collision", "path_fraction",
)


def log_hash(log: pd.DataFrame) -> str:
    """SHA-256 over each golden column's name and float64 bytes, in column order."""
    h = hashlib.sha256()
    for col in GOLDEN_COLUMNS:
        h.update(col.encode())
        h.update(np.ascontiguousarray(log[col].to_numpy(dtype=np.float64)).tobytes())
    return h.hexdigest()


def run_golden(name: str, road):
    sc, policy, loop = SCENARIOS[name](road)
    return run_scenario(sc, policy, loop)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_closed_loop_log_is_bit_identical(name, curved500):
    r = run_golden(name, curved500)
    assert r.summary["end_reason"] != "error", r.summary["error"]
    digest, rows, end_reason = EXPECTED[name]
    assert (r.summary["end_reason"], len(r.log)) == (end_reason, rows)
    assert log_hash(r.log) == digest


if __name__ == "__main__":  # print the current values of EXPECTED
    from safeil_sumo.scenarios.catalogue import resolve_net
    from safeil_sumo.scenarios.road import load_road

    road = load_road(resolve_net("curved500"))
    for name in SCENARIOS:
        r = run_golden(name, road)
        print(f'    "{name}": ("{log_hash(r.log)}", {len(r.log)}, "{r.summary["end_reason"]}"),')


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
