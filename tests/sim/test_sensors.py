"""Camera lane lines and radar: hand-computed cases on a straight road and on curved500."""

import math

import numpy as np
import pytest

from safeil_sumo.sim import sensors as sen

CFG = sen.SensorConfig()


def test_straight_lane_lines(straight_road):
    ego = np.array([100.0, 0.3])
    left, right, lane = sen.camera_lane_lines(straight_road, ego, 0.0, CFG)
    assert lane == 1
    assert np.allclose(left, [1.75 - 0.3, 0, 0, 0], atol=1e-9)
    assert np.allclose(right, [-1.75 - 0.3, 0, 0, 0], atol=1e-9)
    # heading 0.02 rad left of the road: lines appear with slope -tan(0.02)
    left, _, _ = sen.camera_lane_lines(straight_road, ego, 0.02, CFG)
    assert left[1] == pytest.approx(-math.tan(0.02), rel=1e-3)


def test_camera_follows_the_lane_the_car_is_in(straight_road):
    _, _, lane = sen.camera_lane_lines(straight_road, np.array([100.0, 3.0]), 0.0, CFG)
    assert lane == 2
    _, _, lane = sen.camera_lane_lines(straight_road, np.array([100.0, -20.0]), 0.0, CFG)
    assert lane == 0  # off the road: the outermost lane's lines


def test_curved500_lane_lines_match_the_circle(curved500):
    lane = curved500.lanes[curved500.ego_lane]
    s = curved500.path_start_s + 400.0
    xy, _ = lane.centre.point_at(s)
    # the tangent of the circle: the secant over +-20 m (a chord's own heading is off by up to
    # half the chord angle, ~9 mrad, which would show as c1)
    (a, b), _ = lane.centre.point_at(np.array([s - 20.0, s + 20.0]))
    heading = math.atan2(b[1] - a[1], b[0] - a[0])
    left, right, idx = sen.camera_lane_lines(curved500, xy, heading, CFG)
    assert idx == curved500.ego_lane
    assert left[0] == pytest.approx(1.75, abs=0.02)
    assert right[0] == pytest.approx(-1.75, abs=0.02)
    assert abs(left[1]) < 2e-3 and abs(right[1]) < 2e-3
    # left turn: y ~ c0 + x^2 / (2 (R - c0)) for a line at offset c0 from a centre of radius R
    assert left[2] == pytest.approx(1 / (2 * (500 - 1.75)), rel=0.03)
    assert right[2] == pytest.approx(1 / (2 * (500 + 1.75)), rel=0.03)


def test_radar_in_lane_out_of_lane_and_range():
    left = np.array([1.75, 0, 0, 0])
    right = np.array([-1.75, 0, 0, 0])
    ego = np.array([0.0, 0.0])
    hit = sen.radar_leader(ego, 0.0, np.array([40.0, 0.5]), 27.0, left, right, CFG)
    assert hit == sen.RadarTarget(40.0, 0.5, 27.0)
    assert sen.radar_leader(ego, 0.0, np.array([40.0, 3.5]), 27.0, left, right, CFG) is None
    assert sen.radar_leader(ego, 0.0, np.array([151.0, 0.0]), 27.0, left, right, CFG) is None
    assert sen.radar_leader(ego, 0.0, np.array([-5.0, 0.0]), 27.0, left, right, CFG) is None
    assert sen.leader_features(None, 29.0, CFG) == (29.0, 150.0)
    assert sen.leader_features(hit, 29.0, CFG) == (27.0, 40.0)


def test_radar_noise_is_seeded_and_quantized():
    cfg = sen.SensorConfig(radar_noise_m=0.5, quantization_m=0.25)
    left, right = np.array([1.75, 0, 0, 0]), np.array([-1.75, 0, 0, 0])
    args = (np.zeros(2), 0.0, np.array([40.0, 0.0]), 27.0, left, right, cfg)
    a = sen.radar_leader(*args, rng=np.random.default_rng(3))
    b = sen.radar_leader(*args, rng=np.random.default_rng(3))
    assert a == b and a.x != 40.0 and (a.x / 0.25).is_integer()


def test_bad_sensor_config():
    with pytest.raises(ValueError):
        sen.SensorConfig(radar_noise_m=-1.0)


def test_batched_camera_fit_equals_the_scalar_one():
    """polyfit3_batch (a stacked QR) equals polyfit3 (LAPACK's SVD solver) to round-off, and
    ego_points_many equals the camera's points of each car, on seeded random lane views."""
    from safeil_sumo.core.geometry import Polyline
    from safeil_sumo.sim.sensors import _ego_points, ego_points_many, polyfit3, polyfit3_batch

    rng = np.random.default_rng(3)
    k = 50
    x = np.sort(rng.uniform(0.0, 60.0, (k, 16)), axis=1)
    y = (rng.normal(0, 2, (k, 1)) + rng.normal(0, 0.05, (k, 1)) * x
         + rng.normal(0, 1e-3, (k, 1)) * x**2 + rng.normal(0, 1e-5, (k, 1)) * x**3)
    one_by_one = np.array([polyfit3(x[i], y[i]) for i in range(k)])
    np.testing.assert_allclose(polyfit3_batch(x, y), one_by_one, rtol=1e-9, atol=1e-12)

    arc = np.linspace(0.0, 0.6, 40)
    line = Polyline(np.column_stack([500.0 * np.sin(arc), 500.0 * (1 - np.cos(arc))]))
    s0, ex, ey = rng.uniform(0, 200, 5), rng.uniform(0, 200, 5), rng.normal(0, 2, 5)
    yaw = rng.normal(0, 0.1, 5)
    config = sen.SensorConfig()
    bx, by = ego_points_many(line, s0, ex, ey, yaw, config)
    for i in range(5):
        sx, sy = _ego_points(line, s0[i], np.array([ex[i], ey[i]]), yaw[i], config)
        np.testing.assert_allclose(bx[i], sx, rtol=0, atol=1e-9)
        np.testing.assert_allclose(by[i], sy, rtol=0, atol=1e-9)


def test_polyfit3_rows_equals_polyfit3_bit_for_bit():
    """The camera's paired fit (one LAPACK call for both lines) gives polyfit3's coefficients
    exactly, also for a point set with a NaN."""
    from safeil_sumo.sim.sensors import polyfit3, polyfit3_rows

    rng = np.random.default_rng(3)
    for _ in range(300):
        x = np.sort(rng.uniform(-5.0, 80.0, (2, 16)), axis=1) * rng.choice([0.01, 1.0, 10.0])
        y = rng.normal(size=(2, 16)) * rng.choice([1e-3, 1.0, 50.0]) + 1e-3 * x**2
        want = np.array([polyfit3(x[0], y[0]), polyfit3(x[1], y[1])])
        assert np.array_equal(polyfit3_rows(x, y), want)
    y[1, 3] = np.nan  # not finite: each row redone by polyfit3, whatever it gives
    want = np.array([polyfit3(x[0], y[0]), polyfit3(x[1], y[1])])
    assert np.array_equal(polyfit3_rows(x, y), want, equal_nan=True)


def test_planner_features_of_one_car_equal_the_stacked_ones():
    from safeil_sumo.core.features import planner_features

    rng = np.random.default_rng(4)
    left, right = rng.normal(size=4), rng.normal(size=4)
    one = planner_features(left, right, 31.5, 29.25, 48.125)
    stacked = planner_features(left[None], right[None], np.array([31.5]), np.array([29.25]),
                               np.array([48.125]))[0]
    assert one.shape == (9,) and one.dtype == np.float64
    assert np.array_equal(one, stacked)
    assert np.array_equal(one, planner_features(left, right, np.float64(31.5), 29.25, 48.125))


def _circle(radius: float, length: float = 200.0, chord: float = 0.5):
    """A left-turning circle of ``radius`` [m] from the origin heading +x, as a Polyline."""
    from safeil_sumo.core.geometry import Polyline

    arc = np.arange(0.0, length + chord, chord) / radius
    return Polyline(np.column_stack([radius * np.sin(arc), radius * (1.0 - np.cos(arc))]))


def test_view_range_within_turn_hand_computed():
    """On a circle of radius R the chord between samples at arc lengths a and b points along the
    tangent at (a + b) / 2, so chord i turns by (m_i - m_0) / R from chord 0: the range where the
    turn reaches 0.3 rad is 0.3 R exactly (R = 50 m: 15 m; R = 100 m: 30 m). Turns below it keep
    the whole view (R = 250 m over 60 m: 0.224 rad), and the view is never below its floor."""
    offsets = np.linspace(0.0, 60.0, 16)

    def points(radius: float) -> tuple[np.ndarray, np.ndarray]:
        if math.isinf(radius):
            return offsets.copy(), np.zeros(16)
        arc = offsets / radius
        return radius * np.sin(arc), radius * (1.0 - np.cos(arc))

    for radius, expected in ((50.0, 15.0), (100.0, 30.0), (-50.0, 15.0), (250.0, 60.0),
                             (500.0, 60.0), (math.inf, 60.0), (20.0, 10.0)):
        x, y = points(radius)
        got = sen.view_range_within_turn(x, y, offsets, 0.3, 10.0)
        assert float(got) == pytest.approx(expected, abs=1e-9), radius
    # stacked (K, n): each row its own range
    rows = [points(r) for r in (50.0, 250.0, 100.0)]
    got = sen.view_range_within_turn(np.stack([p[0] for p in rows]),
                                     np.stack([p[1] for p in rows]), offsets, 0.3, 10.0)
    np.testing.assert_allclose(got, [15.0, 60.0, 30.0], atol=1e-9)


def test_camera_fits_a_tight_bend():
    """An R = 50 m bend (the ZalaZone handling course's): over the whole 60 m view the cubic's
    c2 has the wrong sign (the bend goes into c1 and c3, which the planners do not see); over
    the range the line turns by <= 0.3 rad, c2 is the curvature's half within 4 %. The batched
    points (ego_points_many) equal the scalar camera's."""
    from safeil_sumo.sim.sensors import _ego_points, ego_points_many, polyfit3

    line, ego = _circle(50.0), np.zeros(2)
    whole = sen.SensorConfig(max_view_turn_rad=1e9)
    c_whole = polyfit3(*_ego_points(line, 0.0, ego, 0.0, whole))
    assert c_whole[2] < 0.0  # the defect: a left bend seen as curving right
    c = polyfit3(*_ego_points(line, 0.0, ego, 0.0, CFG))
    assert c[2] == pytest.approx(1.0 / 100.0, rel=0.04)
    assert abs(c[0]) < 1e-3 and abs(c[1]) < 1e-3
    rng = np.random.default_rng(5)
    s0 = rng.uniform(0.0, 100.0, 6)
    (xy, yaw) = line.point_at(s0)
    ex, ey = xy[:, 0] + rng.normal(0, 0.3, 6), xy[:, 1] + rng.normal(0, 0.3, 6)
    yaw = yaw + rng.normal(0, 0.05, 6)
    bx, by = ego_points_many(line, s0, ex, ey, yaw, CFG)
    for i in range(6):
        sx, sy = _ego_points(line, s0[i], np.array([ex[i], ey[i]]), yaw[i], CFG)
        np.testing.assert_allclose(bx[i], sx, rtol=0, atol=1e-9)
        np.testing.assert_allclose(by[i], sy, rtol=0, atol=1e-9)
        assert sx[-1] < 20.0  # the view was shortened


def test_lane_camera_equals_the_reference_in_a_tight_bend():
    """LaneCamera (the loop's) and camera_lane_lines give the same lines where the view is
    shortened (3 lanes on concentric circles, the ego lane R = 50 m)."""
    from pathlib import Path

    from safeil_sumo.roads.road import Lane, Road

    lanes = []
    for i in range(3):
        radius = 50.0 - (i - 1) * 3.5
        centre = _circle(radius, 150.0 * radius / 50.0)
        lanes.append(Lane(f"bend_{i}", i, 3.5, centre.length, centre, centre.offset(1.75),
                          centre.offset(-1.75)))
    road = Road(Path("bend_fixture.net.xml"), "bend", tuple(lanes), 1, 0.0, 100.0, {})
    camera = sen.LaneCamera(road, CFG, 0.0)
    for s in (5.0, 20.0, 40.0, 60.0):
        xy, yaw = lanes[1].centre.point_at(s)
        ego = xy + np.array([0.2, -0.1])
        want = sen.camera_lane_lines(road, ego, float(yaw) + 0.02, CFG)
        got = camera.lane_lines(ego, float(yaw) + 0.02)
        assert got[2] == want[2] == 1
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        assert got[0][2] == pytest.approx(1.0 / (2.0 * (50.0 - 1.75)), rel=0.05)
        assert got[1][2] == pytest.approx(1.0 / (2.0 * (50.0 + 1.75)), rel=0.05)


def test_the_view_check_is_skipped_only_where_no_chord_can_turn_too_much():
    """A line's turn bound (Polyline.max_turn over the view range) is never below the turn of
    a chord the view check computes (random wavy lines, random stations and poses), and where
    it is below the threshold the camera skips the check with the same lines: the view is
    whole, as the check would have kept it (curved500's lines turn 0.12 rad over 60 m)."""
    from safeil_sumo.core.geometry import Polyline
    from safeil_sumo.sim.sensors import _may_turn_too_much, _view_offsets

    rng = np.random.default_rng(11)
    offsets = _view_offsets(CFG.view_range_m, CFG.view_samples)
    for wave in (0.001, 0.005, 0.02):
        heading = np.cumsum(rng.normal(0.0, wave, 400))
        steps = rng.uniform(0.3, 3.0, 400)
        line = Polyline(np.column_stack([np.cumsum(steps * np.cos(heading)),
                                         np.cumsum(steps * np.sin(heading))]))
        bound = line.max_turn(CFG.view_range_m)
        s0 = rng.uniform(-20.0, line.length, 200)
        pts = line.xy_at(s0[:, None] + offsets)
        dx, dy = np.diff(pts[..., 0], axis=-1), np.diff(pts[..., 1], axis=-1)
        turn = np.abs(np.arctan2(dx[:, :1] * dy - dy[:, :1] * dx, dx[:, :1] * dx + dy[:, :1] * dy))
        assert turn.max() <= bound + 1e-12
        if not _may_turn_too_much(line, CFG):
            view = sen.view_range_within_turn(pts[..., 0], pts[..., 1], offsets,
                                              CFG.max_view_turn_rad, CFG.min_view_range_m)
            assert (view == CFG.view_range_m).all()
    assert not _may_turn_too_much(_circle(500.0), CFG)
    assert _may_turn_too_much(_circle(50.0), CFG)


def test_lane_camera_skipping_the_view_check_equals_the_reference(curved500):
    """On curved500 the loop's camera skips the view check (its lines turn too little): the
    same lines, bit for bit, as camera_lane_lines, which always checks."""
    from safeil_sumo.sim.sensors import _may_turn_too_much

    lane = curved500.lanes[curved500.ego_lane]
    assert not _may_turn_too_much(lane.left_boundary, CFG)
    camera = sen.LaneCamera(curved500, CFG, curved500.path_start_s)
    for s in np.linspace(curved500.path_start_s, curved500.path_end_s - 70.0, 9):
        xy, yaw = lane.centre.point_at(s)
        ego = xy + np.array([0.3, -0.2])
        want = sen.camera_lane_lines(curved500, ego, float(yaw) - 0.01, CFG)
        got = camera.lane_lines(ego, float(yaw) - 0.01)
        assert got[2] == want[2]
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
