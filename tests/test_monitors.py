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
