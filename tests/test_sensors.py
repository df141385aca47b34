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
    from safeil_sumo.geometry import Polyline
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
    from safeil_sumo.features import planner_features

    rng = np.random.default_rng(4)
    left, right = rng.normal(size=4), rng.normal(size=4)
    one = planner_features(left, right, 31.5, 29.25, 48.125)
    stacked = planner_features(left[None], right[None], np.array([31.5]), np.array([29.25]),
                               np.array([48.125]))[0]
    assert one.shape == (9,) and one.dtype == np.float64
    assert np.array_equal(one, stacked)
    assert np.array_equal(one, planner_features(left, right, np.float64(31.5), 29.25, 48.125))
