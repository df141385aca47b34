"""Frames, polylines and projections: hand-computed cases and hypothesis properties."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.geometry import (
    Polyline, ego_to_world, rectangle_corners, rectangles_overlap, sumo_angle_to_yaw,
    world_to_ego, wrap_angle, yaw_to_sumo_angle,
)

coord = st.floats(-1e4, 1e4, allow_nan=False)
angle = st.floats(-10, 10, allow_nan=False)


def test_world_to_ego_hand_computed():
    # ego at (10, 5) heading north: a point 3 m north and 2 m west is (3 ahead, 2 left)
    p = world_to_ego(np.array([8.0, 8.0]), np.array([10.0, 5.0]), math.pi / 2)
    assert np.allclose(p, [3.0, 2.0])


@given(coord, coord, coord, coord, angle)
def test_frame_round_trip(px, py, ox, oy, yaw):
    p = np.array([px, py])
    o = np.array([ox, oy])
    back = ego_to_world(world_to_ego(p, o, yaw), o, yaw)
    assert np.allclose(back, p, atol=1e-6)


@given(angle)
def test_sumo_angle_round_trip(yaw):
    assert math.isclose(
        float(wrap_angle(sumo_angle_to_yaw(yaw_to_sumo_angle(yaw)) - yaw)), 0.0, abs_tol=1e-9
    )


def test_sumo_angle_conventions():
    assert yaw_to_sumo_angle(0.0) == 90.0  # east
    assert yaw_to_sumo_angle(math.pi / 2) == 0.0  # north
    assert math.isclose(sumo_angle_to_yaw(180.0), -math.pi / 2)  # south


def test_projection_on_l_shaped_polyline():
    line = Polyline(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]))
    s, d = line.project(np.array([[4.0, 1.0], [11.0, 5.0], [-2.0, -1.0], [10.0, 13.0]]))
    assert np.allclose(s, [4.0, 15.0, -2.0, 23.0])
    assert np.allclose(d, [1.0, -1.0, -1.0, 0.0])
    assert line.length == 20.0


def test_point_at_and_offset():
    line = Polyline(np.array([[0.0, 0.0], [10.0, 0.0]]))
    xy, heading = line.point_at(4.0)
    assert np.allclose(xy, [4.0, 0.0]) and heading == 0.0
    left = line.offset(1.75)
    assert np.allclose(left.points, [[0.0, 1.75], [10.0, 1.75]])


@settings(max_examples=50)
@given(st.floats(50, 2000), st.floats(-3, 3), st.floats(0.05, 0.95))
def test_offset_of_arc_is_concentric(radius, offset, frac):
    # chords of an arc offset by the miter rule stay chords of the concentric arc
    th = np.linspace(0, 1.0, 60)
    arc = Polyline(np.stack([radius * np.sin(th), radius - radius * np.cos(th)], axis=1))
    off = arc.offset(offset)
    r = np.hypot(off.points[:, 0], off.points[:, 1] - radius)
    assert np.allclose(r, radius - offset, atol=1e-6 * radius)
    # projecting a point of the offset line returns the offset (up to the chord sagitta)
    p, _ = off.point_at(frac * off.length)
    _, d = arc.project(p)
    assert abs(float(d) - offset) < 0.01 * abs(offset) + 1e-3


def test_rectangles_overlap():
    a = rectangle_corners(np.array([0.0, 0.0]), 0.0, 4.5, 1.8)
    assert rectangles_overlap(a, rectangle_corners(np.array([4.0, 0.5]), 0.3, 4.5, 1.8))
    assert not rectangles_overlap(a, rectangle_corners(np.array([4.6, 0.0]), 0.0, 4.5, 1.8))
    assert not rectangles_overlap(a, rectangle_corners(np.array([0.0, 1.9]), 0.0, 4.5, 1.8))


@settings(max_examples=100)
@given(st.floats(100, 2000), st.floats(-4, 4), st.floats(0.0, 1.0), st.integers(0, 200))
def test_project_near_matches_full_projection(radius, d, frac, hint):
    th = np.linspace(0, 1.2, 150)
    arc = Polyline(np.stack([radius * np.sin(th), radius - radius * np.cos(th)], axis=1))
    p, _ = arc.offset(d).point_at(frac * arc.length)
    s_full, d_full = arc.project(p)
    # walking from a hint 0-3 segments away
    start = arc.segment_index(float(s_full)) + hint % 4 - 1
    s_near, d_near, heading, _ = arc.project_near(float(p[0]), float(p[1]), start)
    assert s_near == pytest.approx(float(s_full), abs=1e-6)
    assert d_near == pytest.approx(float(d_full), abs=1e-6)


def test_project_near_extends_the_ends():
    line = Polyline(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]))
    assert line.project_near(-2.0, -1.0, 1)[:2] == (-2.0, -1.0)
    s, d, heading, i = line.project_near(10.0, 13.0, 0)
    assert (s, d, i) == (23.0, 0.0, 1) and heading == pytest.approx(math.pi / 2)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([0.1, 3.0, 20.0]))
def test_project_near_many_equals_project_near(seed, spread):
    """The batch's projection gives project_near's (s, d, heading, segment) exactly, points
    near vertices and bends included (a curve and a polyline with right-angle bends)."""
    rng = np.random.default_rng(seed)
    arc = np.linspace(0.0, 1.0, 54)
    lines = [Polyline(np.column_stack([500.0 * np.sin(arc), 500.0 * (1 - np.cos(arc))])),
             Polyline(np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 20.0]]))]
    for line in lines:
        s0 = rng.uniform(-20.0, line.length + 20.0, 30)
        xy = line.point_at(s0)[0] + rng.normal(0.0, spread, (30, 2))
        hint = np.array([line.segment_index(float(s)) for s in s0]) + rng.integers(-2, 3, 30)
        many = line.project_near_many(xy[:, 0], xy[:, 1], hint)
        for j in range(30):
            one = line.project_near(float(xy[j, 0]), float(xy[j, 1]), int(hint[j]))
            assert tuple(float(m[j]) for m in many) == tuple(float(o) for o in one)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread=st.sampled_from([0.1, 3.0, 20.0]))
def test_polyline_stack_equals_each_polyline(seed, spread):
    """Points on different polylines walked at once (the batch on several roads) give each
    polyline's own project_near_many exactly, NaN points (no leader) included."""
    from safeil_sumo.geometry import PolylineStack

    rng = np.random.default_rng(seed)
    arc = np.linspace(0.0, 1.0, 54)
    lines = [Polyline(np.column_stack([500.0 * np.sin(arc), 500.0 * (1 - np.cos(arc))])),
             Polyline(np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 20.0]])),
             Polyline(np.array([[-30.0, 1.0], [400.0, 2.0]]))]
    line_of = rng.integers(0, len(lines), 40)
    s0 = np.array([rng.uniform(-20.0, lines[k].length + 20.0) for k in line_of])
    xy = np.array([lines[k].point_at(s)[0] for k, s in zip(line_of, s0)])
    xy += rng.normal(0.0, spread, xy.shape)
    xy[::7] = np.nan
    hint = np.array([lines[k].segment_index(float(s)) for k, s in zip(line_of, s0)])
    hint += rng.integers(-2, 3, len(hint))
    stacked = PolylineStack(lines, line_of).project_near_many(xy[:, 0], xy[:, 1], hint)
    for k, line in enumerate(lines):
        rows = np.flatnonzero(line_of == k)
        own = line.project_near_many(xy[rows, 0], xy[rows, 1], hint[rows])
        for got, want in zip(stacked, own):
            np.testing.assert_array_equal(got[rows], want)
