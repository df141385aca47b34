"""Safety monitors: hand-computed TTC, lane departure, path completion and first flag."""

import math

import numpy as np
import pytest

from safeil_sumo.sim import monitors as mon


def test_ttc_hand_computed():
    assert mon.time_to_collision(20.0, 30.0, 25.0) == 4.0
    assert mon.time_to_collision(20.0, 25.0, 25.0) == math.inf
    assert mon.time_to_collision(20.0, 20.0, 25.0) == math.inf
    assert mon.time_to_collision(-0.1, 30.0, 25.0) == 0.0


def test_footprint_offset_range_straight_and_rotated():
    assert mon.footprint_offset_range(0.5, 0.0, 4.5, 1.8) == pytest.approx((-0.4, 1.4))
    # heading 0.1 rad to the left: the rear corners swing right by 4.5 sin(0.1)
    c, s = math.cos(0.1), math.sin(0.1)
    corners = [0.9 * c, -0.9 * c, -4.5 * s - 0.9 * c, -4.5 * s + 0.9 * c]
    assert mon.footprint_offset_range(0.0, 0.1, 4.5, 1.8) == pytest.approx(
        (min(corners), max(corners)))
    corners = [0.9 * c, -0.9 * c, 4.5 * s - 0.9 * c, 4.5 * s + 0.9 * c]
    assert mon.footprint_offset_range(0.0, -0.1, 4.5, 1.8) == pytest.approx(
        (min(corners), max(corners)))


def test_lane_departure_at_the_boundary():
    w = 3.5
    assert not mon.lane_departure(-1.75, 1.75, w)
    assert mon.lane_departure(-1.0, 1.7501, w)
    assert mon.lane_departure(-1.7501, 1.0, w)
    assert not mon.lane_departure(-1.0, 1.8, w, margin=0.1)


def test_path_completed_clips():
    assert mon.path_completed(30.0, 30.0, 1030.0) == 0.0
    assert mon.path_completed(530.0, 30.0, 1030.0) == 0.5
    assert mon.path_completed(2000.0, 30.0, 1030.0) == 1.0


def test_first_flag_picks_earliest_and_names_it():
    t = np.arange(5) * 0.1
    frac = np.linspace(0, 0.4, 5)
    lane = np.array([0, 0, 0, 1, 1], bool)
    ttc = np.array([0, 0, 1, 1, 0], bool)
    col = np.zeros(5, bool)
    flag = mon.first_flag(t, frac, lane, ttc, col)
    assert flag.reason == mon.FLAG_TTC and flag.time_s == pytest.approx(0.2)
    assert flag.path_fraction == pytest.approx(0.2)
    none = mon.first_flag(t, frac, col, col, col)
    assert none.reason == "" and none.path_fraction == pytest.approx(0.4)


def test_event_starts_hand_computed():
    assert mon.event_starts([False, True, True, False, True]).tolist() == [1, 4]
    assert mon.event_starts([True, True, False]).tolist() == [0]
    assert mon.event_starts([]).tolist() == []


# ------------------------------------- cases found by mutation testing (docs/mutation_testing.md)


def test_ttc_at_the_edges_and_on_arrays():
    # closing slowly (0.5 m/s) still counts; a gap of exactly 0 or of 0.5 m is not "overlap"
    assert mon.time_to_collision(2.0, 25.5, 25.0) == 4.0
    assert mon.time_to_collision(0.0, 25.0, 25.0) == 0.0
    assert mon.time_to_collision(0.5, 30.0, 25.0) == pytest.approx(0.1)
    from safeil_sumo.sim.xp import ARRAYS

    ttc = mon.time_to_collision(np.array([20.0, 20.0, 0.0]), np.array([30.0, 20.0, 20.0]),
                                np.array([25.0, 25.0, 25.0]), xp=ARRAYS)
    np.testing.assert_array_equal(ttc, [4.0, math.inf, 0.0])


def test_monitor_config_needs_a_positive_ttc_threshold():
    assert mon.MonitorConfig(ttc_threshold_s=0.5).ttc_threshold_s == 0.5
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match=r"^MonitorConfig.ttc_threshold_s must be > 0$"):
            mon.MonitorConfig(ttc_threshold_s=bad)


def test_first_flag_ties_and_empty_logs():
    t = np.arange(3) * 0.1
    frac = np.array([0.1, 0.2, 0.3])
    on, off = np.ones(3, bool), np.zeros(3, bool)
    # the same step: collision > ttc > lane
    assert mon.first_flag(t, frac, on, on, on).reason == mon.FLAG_COLLISION
    assert mon.first_flag(t, frac, on, on, off).reason == mon.FLAG_TTC
    assert mon.first_flag(t, frac, on, off, off).reason == mon.FLAG_LANE
    none = mon.first_flag(t, frac, off, off, off)
    assert math.isnan(none.time_s) and none.path_fraction == 0.3
    empty = mon.first_flag(t[:0], frac[:0], off[:0], off[:0], off[:0])
    assert (empty.reason, empty.path_fraction) == ("", 0.0) and math.isnan(empty.time_s)
