"""Frames, polylines and projections: hand-computed cases and hypothesis properties."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safeil_sumo.core.geometry import (
    Polyline,
    cumulative_length,
    ego_to_world,
    offset_polyline,
    rectangle_corners,
    rectangles_overlap,
    sumo_angle_to_yaw,
    world_to_ego,
    wrap_angle,
    yaw_to_sumo_angle,
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
    s_near, d_near, _, _ = arc.project_near(float(p[0]), float(p[1]), start)
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
    from safeil_sumo.core.geometry import PolylineStack

    rng = np.random.default_rng(seed)
    arc = np.linspace(0.0, 1.0, 54)
    lines = [Polyline(np.column_stack([500.0 * np.sin(arc), 500.0 * (1 - np.cos(arc))])),
             Polyline(np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 20.0]])),
             Polyline(np.array([[-30.0, 1.0], [400.0, 2.0]]))]
    line_of = rng.integers(0, len(lines), 40)
    s0 = np.array([rng.uniform(-20.0, lines[k].length + 20.0) for k in line_of])
    xy = np.array([lines[k].point_at(s)[0] for k, s in zip(line_of, s0, strict=True)])
    xy += rng.normal(0.0, spread, xy.shape)
    xy[::7] = np.nan
    hint = np.array([lines[k].segment_index(float(s)) for k, s in zip(line_of, s0, strict=True)])
    hint += rng.integers(-2, 3, len(hint))
    stacked = PolylineStack(lines, line_of).project_near_many(xy[:, 0], xy[:, 1], hint)
    assert all(a.dtype == np.float64 for a in stacked[:3])
    for k, line in enumerate(lines):
        rows = np.flatnonzero(line_of == k)
        own = line.project_near_many(xy[rows, 0], xy[rows, 1], hint[rows])
        for got, want in zip(stacked, own, strict=True):
            np.testing.assert_array_equal(got[rows], want)


# ------------------------------------- cases found by mutation testing (docs/mutation_testing.md)


def test_frames_and_corners_hand_computed():
    # several points at once keep their (N, 2) layout
    p = world_to_ego(np.array([[8.0, 8.0], [10.0, 6.0], [11.0, 5.0]]), np.array([10.0, 5.0]),
                     math.pi / 2)
    np.testing.assert_allclose(p, [[3.0, 2.0], [1.0, 0.0], [0.0, -1.0]], atol=1e-12)
    # a 4 m x 2 m box at (1, 2) heading north: front-left, front-right, rear-right, rear-left
    c = rectangle_corners(np.array([1.0, 2.0]), math.pi / 2, 4.0, 2.0)
    np.testing.assert_allclose(c, [[0.0, 4.0], [2.0, 4.0], [2.0, 0.0], [0.0, 0.0]], atol=1e-12)


def _segments_cross(p, q, a, b) -> bool:
    """Do the closed segments p-q and a-b intersect (orientation test)?"""
    def orient(u, v, w):
        return np.sign((v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0]))

    return orient(p, q, a) != orient(p, q, b) and orient(a, b, p) != orient(a, b, q)


def _inside(point, quad) -> bool:
    """Is ``point`` strictly inside the counter-clockwise or clockwise convex ``quad``?"""
    cross = [(quad[(k + 1) % 4][0] - quad[k][0]) * (point[1] - quad[k][1])
             - (quad[(k + 1) % 4][1] - quad[k][1]) * (point[0] - quad[k][0]) for k in range(4)]
    return all(c > 0 for c in cross) or all(c < 0 for c in cross)


def test_rectangles_overlap_against_edge_crossings():
    """Separating axes agree with an independent test (an edge crossing or one box inside the
    other) on random rotated boxes, near misses included."""
    rng = np.random.default_rng(4)
    for _ in range(400):
        a = rectangle_corners(rng.uniform(-1, 1, 2), rng.uniform(-3, 3), rng.uniform(1, 5),
                              rng.uniform(0.5, 2.5))
        b = rectangle_corners(rng.uniform(-4, 4, 2), rng.uniform(-3, 3), rng.uniform(1, 5),
                              rng.uniform(0.5, 2.5))
        truth = (any(_segments_cross(a[i], a[(i + 1) % 4], b[j], b[(j + 1) % 4])
                     for i in range(4) for j in range(4))
                 or _inside(a[0], b) or _inside(b[0], a))
        assert rectangles_overlap(a, b) == truth
    # general convex quadrilaterals (no parallel sides, so no axis is tested twice)
    for _ in range(400):
        quads = []
        for centre in (rng.uniform(-1, 1, 2), rng.uniform(-4, 4, 2)):
            ang = np.sort(rng.uniform(0.0, 2 * np.pi, 4))
            r = rng.uniform(0.5, 3.0, 2)
            quads.append(centre + np.column_stack([r[0] * np.cos(ang), r[1] * np.sin(ang)]))
        a, b = quads
        truth = (any(_segments_cross(a[i], a[(i + 1) % 4], b[j], b[(j + 1) % 4])
                     for i in range(4) for j in range(4))
                 or _inside(a[0], b) or _inside(b[0], a))
        assert rectangles_overlap(a, b) == truth
    # touching is contact: two boxes sharing an edge overlap
    box = rectangle_corners(np.array([0.0, 0.0]), 0.0, 4.0, 2.0)
    assert rectangles_overlap(box, rectangle_corners(np.array([4.0, 0.0]), 0.0, 4.0, 2.0))
    assert rectangles_overlap(rectangle_corners(np.array([-4.0, 0.0]), 0.0, 4.0, 2.0), box)


def test_offset_of_a_right_angle_and_integer_input():
    # an L turning left: offset 1 m to the left, the corner moves to (9, 1) (the miter)
    line = np.array([[0, 0], [10, 0], [10, 10]])  # integers are accepted
    np.testing.assert_allclose(offset_polyline(line, 1.0), [[0, 1], [9, 1], [9, 10]], atol=1e-12)
    np.testing.assert_allclose(offset_polyline(line, -2.0), [[0, -2], [12, -2], [12, 10]],
                               atol=1e-12)


def test_polyline_validation_and_storage():
    line = Polyline([[0, 0], [3, 4]])  # a list of integers
    assert isinstance(line.points, np.ndarray) and line.points.dtype == np.float64
    assert line.length == 5.0
    for bad in ([[0.0, 0.0]], [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], [0.0, 1.0, 2.0, 3.0]):
        with pytest.raises(ValueError, match=r"a polyline needs shape \(N>=2, 2\), got"):
            Polyline(np.array(bad))
    with pytest.raises(ValueError, match="^polyline has repeated consecutive vertices$"):
        Polyline(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [2.0, 0.0]]))
    assert line._arrays() is line._arrays()  # built once


def test_arc_length_helpers_hand_computed():
    pts = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 10.0], [11.0, 10.0]])
    np.testing.assert_allclose(cumulative_length(pts), [0.0, 5.0, 11.0, 19.0])
    line = Polyline(pts)
    # segment of an arc length: vertices belong to the segment they start; clipped at the ends
    assert [line.segment_index(s) for s in (-1.0, 0.0, 4.9, 5.0, 10.99, 11.0, 19.0, 30.0)] == \
        [0, 0, 0, 1, 1, 2, 2, 2]
    s = np.array([-5.0, 2.5, 5.0, 8.0, 15.0, 21.0])
    want = [[-3.0, -4.0], [1.5, 2.0], [3.0, 4.0], [3.0, 7.0], [7.0, 10.0], [13.0, 10.0]]
    xy, heading = line.point_at(s)
    np.testing.assert_allclose(xy, want, atol=1e-12)
    np.testing.assert_allclose(heading, [math.atan2(4, 3), math.atan2(4, 3), math.pi / 2,
                                         math.pi / 2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(line.xy_at(s), want, atol=1e-12)
    np.testing.assert_allclose(line.xy_at(s.reshape(2, 3)), np.reshape(want, (2, 3, 2)),
                               atol=1e-12)
    # resampling every 2 m: ceil(19 / 2) = 10 pieces of 1.9 m, both ends kept
    r = line.resample(2.0)
    assert len(r.points) == 11 and 18.0 < r.length <= 19.0  # chords cut the two corners
    np.testing.assert_allclose(r.points[[0, -1]], pts[[0, -1]], atol=1e-12)
    np.testing.assert_allclose(line.project(r.points)[0], np.linspace(0.0, 19.0, 11), atol=1e-9)
    np.testing.assert_allclose(line.project(r.points)[1], 0.0, atol=1e-9)  # on the line
    assert len(Polyline(np.array([[0.0, 0.0], [1.0, 0.0]])).resample(5.0).points) == 2


def test_max_turn_hand_computed():
    """The vertices' turns summed over the worst stretch: the L-shaped line above turns by
    atan2(3, 4) at s = 5 and by pi / 2 at s = 11 (6 m apart); a straight line not at all."""
    line = Polyline(np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 10.0], [11.0, 10.0]]))
    first, second = math.pi / 2 - math.atan2(4, 3), math.pi / 2
    assert line.max_turn(5.0) == pytest.approx(second, abs=1e-12)  # one bend at a time
    assert line.max_turn(6.0) == pytest.approx(first + second, abs=1e-12)  # both: 6 m apart
    assert line.max_turn(100.0) == pytest.approx(first + second, abs=1e-12)
    assert line.max_turn(6.0) is line.max_turn(6.0)  # cached per length
    assert Polyline(np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]])).max_turn(60.0) == 0.0
    assert Polyline(np.array([[0.0, 0.0], [1.0, 0.0]])).max_turn(60.0) == 0.0
    # a zigzag turns both ways, 2 atan(0.1) at each vertex (every 1.005 m): the absolute turns
    # add up, three of them within 3 m
    zigzag = Polyline(np.array([[float(i), 0.1 * (i % 2)] for i in range(20)]))
    assert zigzag.max_turn(3.0) == pytest.approx(3 * 2 * math.atan(0.1), abs=1e-12)


def test_projection_of_a_single_segment_and_of_an_uneven_bend():
    seg = Polyline(np.array([[0.0, 0.0], [10.0, 0.0]]))
    s, d = seg.project(np.array([[-5.0, 1.0], [15.0, -2.0], [4.0, 3.0]]))
    np.testing.assert_allclose(s, [-5.0, 15.0, 4.0])
    np.testing.assert_allclose(d, [1.0, -2.0, 3.0])
    # a 10 m segment then a 2.83 m one at 45 deg: (11, -1) lies outside the bend, beyond the
    # first segment; the nearest point is the vertex, taken on the first segment (the tie)
    bend = Polyline(np.array([[0.0, 0.0], [10.0, 0.0], [12.0, 2.0]]))
    s, d = bend.project(np.array([11.0, -1.0]))
    assert (float(s), float(d)) == pytest.approx((10.0, -1.0))
    # (10.5, -2) lies in the gap outside the bend, BEFORE the last segment's start: the vertex
    # again (the last segment extends forward only)
    s, d = bend.project(np.array([10.5, -2.0]))
    assert (float(s), float(d)) == pytest.approx((10.0, -2.0))


def _wiggly_road(rng: np.random.Generator) -> Polyline:
    """A zigzag road: 12 segments of 5-30 m, bends of 5-50 deg alternating left and right
    (no U-turn: the road never comes back near itself)."""
    turns = rng.uniform(0.09, 0.87, 12) * np.where(np.arange(12) % 2, 1.0, -1.0)
    heading = 0.5 * turns[0] + np.cumsum(turns) - np.cumsum(turns).mean()
    steps = rng.uniform(5.0, 30.0, 12)[:, None] * np.column_stack([np.cos(heading),
                                                                   np.sin(heading)])
    return Polyline(np.vstack([[0.0, 0.0], np.cumsum(steps, axis=0)]))


def _dense_projection(line: Polyline, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference (s, d): the nearest of points every 1 mm along the line and 30 m beyond each
    end, d signed by the side (interpolated by hand, not with the Polyline's methods)."""
    p, s_v = line.points, line.s
    s = np.arange(-30.0, line.length + 30.0, 0.001)
    x = np.interp(s, s_v, p[:, 0])
    y = np.interp(s, s_v, p[:, 1])
    t0, t1 = (p[1] - p[0]) / s_v[1], (p[-1] - p[-2]) / (s_v[-1] - s_v[-2])
    before, after = s < 0, s > s_v[-1]
    x[before], y[before] = p[0, 0] + s[before] * t0[0], p[0, 1] + s[before] * t0[1]
    x[after] = p[-1, 0] + (s[after] - s_v[-1]) * t1[0]
    y[after] = p[-1, 1] + (s[after] - s_v[-1]) * t1[1]
    out_s, out_d = [], []
    for px, py in xy:
        k = int(np.argmin((x - px) ** 2 + (y - py) ** 2))
        k = min(max(k, 1), len(s) - 2)
        tx, ty = x[k + 1] - x[k - 1], y[k + 1] - y[k - 1]
        side = np.sign(tx * (py - y[k]) - ty * (px - x[k]))
        out_s.append(s[k])
        out_d.append(side * math.hypot(px - x[k], py - y[k]))
    return np.array(out_s), np.array(out_d)


@pytest.mark.parametrize("seed", range(3))
def test_projections_agree_with_a_dense_reference_on_a_winding_road(seed, monkeypatch):
    """project, project_near (from ANY hint) and project_near_many give the nearest point of
    the line (its ends extended), within the reference's 1 mm; the batch resolves a point by
    the scalar rule exactly when its foot could lie on two segments (near a vertex), and walks
    every other point itself (the batched loop's speed rests on that)."""
    rng = np.random.default_rng(seed)
    line = _wiggly_road(rng)
    # anywhere along the line and beyond its ends, and within 1.5 m of each vertex on both
    # sides (inside a bend a point can project on both segments, outside on neither)
    near = np.repeat(line.s[1:-1], 4) + rng.uniform(-1.5, 1.5, 4 * (len(line.s) - 2))
    s0 = np.r_[rng.uniform(-20.0, line.length + 20.0, 40), near]
    n = len(s0)
    xy, heading = line.point_at(s0)
    side = rng.uniform(-3.0, 3.0, n)
    xy = xy + side[:, None] * np.column_stack([-np.sin(heading), np.cos(heading)])
    s_ref, d_ref = _dense_projection(line, xy)
    s, d = line.project(xy)
    np.testing.assert_allclose(s, s_ref, atol=2e-3)
    # (outside a bend the nearest point is the vertex, and d is the offset from the line of
    # the segment taken, not the distance to the vertex: compared elsewhere only)
    away = np.min(np.abs(s_ref[:, None] - line.s[None, 1:-1]), axis=1) > 0.01
    np.testing.assert_allclose(d[away], d_ref[away], atol=2e-3)
    seg = np.array([line.segment_index(float(v)) for v in s])
    hint = rng.integers(-2, len(line.points) + 2, n)
    for j in range(n):
        sj, dj, hj, ij = line.project_near(float(xy[j, 0]), float(xy[j, 1]), int(hint[j]))
        assert (sj, dj) == pytest.approx((s[j], d[j]), abs=1e-9)
        assert hj == pytest.approx(math.atan2(*line._tangents[ij][::-1]))
    # which points may project on two segments (a neighbour's foot inside it)
    pts, tang, seg_len = line.points, line._tangents, line._seg_len
    last = len(seg_len) - 1

    def along(k, j):
        return float((xy[j] - pts[k]) @ tang[k])

    ambiguous = {j for j in range(n)
                 if (seg[j] > 0 and (along(seg[j], j) <= 0.0
                                     or along(seg[j] - 1, j) <= seg_len[seg[j] - 1]))
                 or (seg[j] < last and (along(seg[j], j) >= seg_len[seg[j]]
                                        or along(seg[j] + 1, j) >= 0.0))}
    calls = []
    scalar = Polyline.project_near

    def counted(self, x, y, h):
        calls.append((x, y))
        return scalar(self, x, y, h)

    monkeypatch.setattr(Polyline, "project_near", counted)
    many = line.project_near_many(xy[:, 0], xy[:, 1], hint)
    np.testing.assert_allclose(many[0], s, atol=1e-9)
    np.testing.assert_allclose(many[1], d, atol=1e-9)
    assert all(m.dtype == np.float64 for m in many[:3])
    assert {tuple(c) for c in calls} == {(float(xy[j, 0]), float(xy[j, 1])) for j in ambiguous}
    assert 0 < len(ambiguous) < n


def test_points_on_the_bisectors_of_every_bend():
    """At every vertex of a zigzag road: a point 1.5 m out along the outer bisector (in the gap:
    its nearest point is the vertex) and one 1.5 m in along the inner bisector (equally near
    both segments); project_near from either end and the batch agree with project()."""
    rng = np.random.default_rng(7)
    line = _wiggly_road(rng)
    t = line._tangents
    pts, extra = [], []
    for k in range(1, len(line.points) - 1):
        bis = t[k] - t[k - 1]  # points to the inside of the bend
        bis /= np.linalg.norm(bis)
        pts += [line.points[k] + 1.5 * bis, line.points[k] - 1.5 * bis]
        # inside, 1.5 m from one segment, 0.3 m short of / past the vertex: within reach of
        # both segments, whichever side the walk comes from
        for u, sign in ((t[k - 1], -0.3), (t[k], 0.3)):
            turn = t[k - 1][0] * t[k][1] - t[k - 1][1] * t[k][0]  # > 0: a left bend
            normal = np.array([-u[1], u[0]]) * np.sign(turn)
            extra.append(line.points[k] + sign * u + 1.5 * normal)
    xy = np.array(pts + extra)
    s, d = line.project(xy)
    for hint in (0, len(t) - 1):
        for j in range(len(xy)):
            got = line.project_near(float(xy[j, 0]), float(xy[j, 1]), hint)
            assert got[:2] == pytest.approx((s[j], d[j]), abs=1e-9)
        many = line.project_near_many(xy[:, 0], xy[:, 1], np.full(len(xy), hint))
        np.testing.assert_allclose(many[0], s, atol=1e-9)
        np.testing.assert_allclose(many[1], d, atol=1e-9)
    # outside: s at the vertex; inside: one of the two feet (a tie up to
    # rounding, resolved as project() does), 1.5 m sin(half the bend) from the vertex
    m = len(pts)
    np.testing.assert_allclose(s[1:m:2], line.s[1:-1], atol=1e-9)
    assert np.all(np.abs(s[0:m:2] - line.s[1:-1]) > 0.01)
