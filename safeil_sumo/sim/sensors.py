"""Sensor models — pure functions of the road geometry and vehicle states, no SUMO calls.

- camera: the left/right boundaries of the lane the ego is in, as cubic polynomials
  ``y = c0 + c1 x + c2 x^2 + c3 x^3`` in the ego frame (front-bumper origin, x forward, y left),
  fitted to the lane geometry within the camera's view range (like a MobilEye output);
- radar: the in-path leading vehicle's bumper-to-bumper distance, relative position and speed.
Optional Gaussian noise and quantisation draw from an explicit ``np.random.Generator``.

:func:`camera_lane_lines` is the reference; the closed loop uses :class:`LaneCamera`, which gives
bit-identical lines but replaces the full projections on the lane polylines (O(N) each) with O(1)
walks from where it looked last (:meth:`Polyline.project_near`, same result as ``project``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.roads.road import Lane, Road


@dataclass(frozen=True)
class SensorConfig:
    """Camera and radar settings."""

    view_range_m: float = 60.0  # camera lane-line fit from x = 0 to this distance ahead [m]
    view_samples: int = 16  # boundary points for the cubic fit (every 4 m) [-]
    # the lines are fitted only as far as they turn by at most this angle from where the camera
    # looks (:func:`view_range_within_turn`): a cubic y(x) in the ego frame cannot follow a
    # tighter bend over the whole view range (R = 50 m over 60 m turns 1.2 rad; its fit's c2 has
    # the wrong sign). At 60 m it shortens the view only below R = 200 m (motorways, curved500
    # and the golden tracks are untouched, bit for bit) [rad]
    max_view_turn_rad: float = 0.3
    min_view_range_m: float = 10.0  # the view is never shortened below this [m]
    radar_range_m: float = 150.0  # farthest detectable leader [m]
    # With no leader in range the paper's data has no sample; the closed loop must still feed
    # the planner, so "free road" is shown as a leader at the range limit at the ego's speed.
    no_leader_distance_m: float = 150.0
    lane_noise_c0_m: float = 0.0  # std of additive noise on c0 [m]
    lane_noise_c1: float = 0.0  # std of additive noise on c1 [-]
    radar_noise_m: float = 0.0  # std of range noise [m]
    radar_speed_noise_mps: float = 0.0  # std of leader-speed noise [m/s]
    quantization_m: float = 0.0  # radar range quantum (0 = none) [m]

    def __post_init__(self) -> None:
        if self.view_range_m <= 0 or self.radar_range_m <= 0 or self.view_samples < 4:
            raise ValueError("sensor ranges must be positive and view_samples >= 4")
        if not self.max_view_turn_rad > 0 or not 0 < self.min_view_range_m <= self.view_range_m:
            raise ValueError("max_view_turn_rad must be > 0 and min_view_range_m in "
                             "(0, view_range_m]")
        for name in ("lane_noise_c0_m", "lane_noise_c1", "radar_noise_m",
                     "radar_speed_noise_mps", "quantization_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"SensorConfig.{name} must be >= 0")


@dataclass(frozen=True)
class RadarTarget:
    """The detected leader: ``x, y`` [m] of its rear-bumper centre in the ego frame, ``v`` [m/s]."""

    x: float
    y: float
    v: float


def current_lane_index(road: Road, ego_xy: np.ndarray) -> int:
    """Index of the lane whose centre the point is nearest to, counted from the ego lane.

    Off the road the outermost lane is returned: a camera keeps reporting the nearest lines.
    """
    s, d = road.lanes[road.ego_lane].centre.project(ego_xy)
    return _lane_index_at(road, float(d), float(s))


def _lane_index_at(road: Road, d: float, s: float) -> int:
    """Lane index at signed offset ``d`` [m] from the ego lane's centre, at arc length ``s`` [m]
    along it (clipped to the lanes the road has there: on a route a neighbour can end)."""
    k = int(np.rint(d / road.lanes[road.ego_lane].width))
    lo, hi = road.lanes_at(s)
    return min(max(road.ego_lane + k, lo), hi)


def add_lane_noise(left: np.ndarray, right: np.ndarray, config: SensorConfig,
                    rng: np.random.Generator | None) -> None:
    """Seeded camera error on c0, c1, in place; it moves both lines together."""
    if rng is not None and (config.lane_noise_c0_m > 0 or config.lane_noise_c1 > 0):
        noise = rng.normal(size=2) * [config.lane_noise_c0_m, config.lane_noise_c1]
        left[:2] += noise
        right[:2] += noise


def fit_boundary(
    boundary: Polyline, ego_xy: np.ndarray, ego_yaw: float, config: SensorConfig
) -> np.ndarray:
    """Cubic coefficients ``(4,)`` (c0..c3) of one boundary in the ego frame over the view range."""
    s0, _ = boundary.project(ego_xy)
    return _fit_from(boundary, float(s0), ego_xy, ego_yaw, config)


def _fit_from(
    boundary: Polyline, s0: float, ego_xy: np.ndarray, ego_yaw: float, config: SensorConfig
) -> np.ndarray:
    """The fit of :func:`fit_boundary` from the ego's arc length ``s0`` [m] on the boundary."""
    return polyfit3(*_ego_points(boundary, s0, ego_xy, ego_yaw, config))


def _ego_points(
    boundary: Polyline, s0: float, ego_xy: np.ndarray, ego_yaw: float, config: SensorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The boundary's points the camera fits, ``x, y (samples,)`` [m] in the ego frame (over
    the view range, shortened where the line turns more than ``config.max_view_turn_rad``)."""
    offsets = _view_offsets(config.view_range_m, config.view_samples)
    x, y = _to_ego(boundary.xy_at(s0 + offsets), ego_xy, ego_yaw)
    view = float(view_range_within_turn(x, y, offsets, config.max_view_turn_rad,
                                        config.min_view_range_m))
    if view < config.view_range_m:
        x, y = _points_within(boundary, s0, view, config.view_samples, ego_xy, ego_yaw)
    return x, y


def _points_within(line: Polyline, s0: float, view_m: float, samples: int, ego_xy: np.ndarray,
                   ego_yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """A line's ``samples`` points over a view shortened to ``view_m`` [m] from arc length
    ``s0`` [m], ``x, y (samples,)`` [m] in the ego frame."""
    return _to_ego(line.xy_at(s0 + np.linspace(0.0, view_m, samples)), ego_xy, ego_yaw)


def _to_ego(pts: np.ndarray, ego_xy: np.ndarray, ego_yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """World points ``(..., 2)`` in the ego frame, ``x, y (...)`` [m] (world_to_ego, unrolled:
    the same element-wise operations, no stacking)."""
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    d = pts - ego_xy
    dx, dy = d[..., 0], d[..., 1]
    return c * dx + s * dy, -s * dx + c * dy


def view_range_within_turn(x: np.ndarray, y: np.ndarray, offsets: np.ndarray, max_turn_rad: float,
                           min_range_m: float) -> np.ndarray:
    """How far along a line the camera fits: the arc length [m] over which the line turns by at
    most ``max_turn_rad`` from its first chord, of lines sampled at arc-length ``offsets (n,)``
    [m], ``x, y (..., n)`` [m] (any frame); ``offsets[-1]`` (the whole view) where it turns less,
    never below ``min_range_m``. Shape ``(...)``.

    The turn of chord i is its angle to chord 0, placed at the chords' midpoints
    ``m_i - m_0 = (offsets[i] + offsets[i + 1] - offsets[0] - offsets[1]) / 2``; the range is
    linearly interpolated where the turn first exceeds ``max_turn_rad`` (e.g. a circle of
    radius R sampled every 4 m: ``max_turn_rad * R``)."""
    dx, dy = np.diff(x, axis=-1), np.diff(y, axis=-1)  # chords (..., n - 1)
    turn = np.abs(np.arctan2(dx[..., :1] * dy - dy[..., :1] * dx,
                             dx[..., :1] * dx + dy[..., :1] * dy))
    mid = 0.5 * (offsets[:-1] + offsets[1:])
    along = mid - mid[0]
    over = turn > max_turn_rad
    full = np.full(turn.shape[:-1], float(offsets[-1]))
    if not over.any():
        return full
    i = np.argmax(over, axis=-1)  # the first chord beyond the turn (0 where none: unused)
    i_prev = np.maximum(i - 1, 0)
    t_prev = np.take_along_axis(turn, i_prev[..., None], -1)[..., 0]
    t_over = np.take_along_axis(turn, i[..., None], -1)[..., 0]
    frac = (max_turn_rad - t_prev) / np.maximum(t_over - t_prev, 1e-12)
    cut = along[i_prev] + frac * (along[i] - along[i_prev])
    return np.where(over.any(axis=-1), np.clip(cut, min_range_m, offsets[-1]), full)


# the margin [rad] below max_view_turn_rad under which a line's turn bound lets the camera skip
# view_range_within_turn: its chord angles come from rounded points (~1e-11 rad off on
# metre-long chords), far less than this
_TURN_MARGIN_RAD = 1e-3


def _may_turn_too_much(line: Polyline, config: SensorConfig) -> bool:
    """Whether :func:`view_range_within_turn` may shorten the view on ``line``: False where no
    stretch of the view range turns by more than ``max_view_turn_rad`` (less the margin; e.g. a
    circle of radius above ``view_range_m / max_view_turn_rad``): then no chord turns more
    from the first and the check would keep the whole view range."""
    return line.max_turn(config.view_range_m) > config.max_view_turn_rad - _TURN_MARGIN_RAD


@lru_cache(maxsize=8)
def _view_offsets(view_range_m: float, samples: int) -> np.ndarray:
    """Arc-length offsets ``(samples,)`` [m] of the fitted boundary points (read-only, shared)."""
    out = np.linspace(0.0, view_range_m, samples)
    out.flags.writeable = False
    return out


def polyfit3(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``np.polynomial.polynomial.polyfit(x, y, 3)`` without its argument checks: the same
    operations in the same order (Vandermonde, column scaling, LAPACK least squares), so the
    coefficients ``(4,)`` are bit-identical; about twice as fast on 16 points."""
    van = np.empty((4, len(x)))  # rows 1, x, x^2, x^3: polyvander's products, transposed
    van[0] = 1.0
    van[1] = x
    np.multiply(van[1], x, out=van[2])
    np.multiply(van[2], x, out=van[3])
    scl = np.sqrt(np.square(van).sum(1))
    scl[scl == 0] = 1
    c = np.linalg.lstsq(van.T / scl, y, len(x) * _EPS)[0]
    return c / scl


_EPS = float(np.finfo(np.float64).eps)


def polyfit3_rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """:func:`polyfit3` of each row of ``x, y (K, n)``: coefficients ``(K, 4)``, bit-identical
    (the same operations row by row, and the same LAPACK least-squares solver, which
    ``np.linalg.lstsq`` wraps, called once for the K rows); the camera's left and right lines in
    one call, ~half the cost of two :func:`polyfit3`. A fit that is not finite (a degenerate
    point set) is redone by :func:`polyfit3`, which raises as ``np.linalg.lstsq`` does."""
    k, n = x.shape
    van = np.empty((k, 4, n))
    van[:, 0] = 1.0
    van[:, 1] = x
    np.multiply(van[:, 1], x, out=van[:, 2])
    np.multiply(van[:, 2], x, out=van[:, 3])
    scl = np.sqrt(np.square(van).sum(2))
    scl[scl == 0] = 1
    a = van.transpose(0, 2, 1) / scl[:, None, :]
    with np.errstate(all="ignore"):
        c = _lstsq(a, y[:, :, None], n * _EPS, signature="ddd->ddid")[0][:, :, 0]
    if not np.isfinite(c).all():
        return np.array([polyfit3(xi, yi) for xi, yi in zip(x, y, strict=True)])
    return c / scl


_lstsq: Callable[..., tuple[np.ndarray, ...]]
try:  # the gufunc np.linalg.lstsq calls (numpy 2.x); its wrapper's checks cost ~10 us a call
    from numpy.linalg._umath_linalg import lstsq as _lstsq
except ImportError:  # pragma: no cover - another numpy: through the public function
    def _lstsq(a: np.ndarray, b: np.ndarray, rcond: float, signature: str | None = None
               ) -> tuple[np.ndarray, ...]:
        return (np.stack([np.linalg.lstsq(ai, bi, rcond)[0]
                          for ai, bi in zip(a, b, strict=True)]),)


def polyfit3_batch(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """:func:`polyfit3` of K point sets ``(K, n)`` at once: coefficients ``(K, 4)``.

    The same scaled Vandermonde least squares, solved by a stacked QR instead of LAPACK's SVD
    solver: equal to :func:`polyfit3` to round-off (tests/sim/test_sensors.py), for full-rank fits
    (a camera's points spread over its view range).
    """
    van = np.stack([np.ones_like(x), x, x * x, x * x * x], axis=-1)  # (K, n, 4)
    scl = np.sqrt(np.square(van).sum(axis=1))  # (K, 4)
    scl[scl == 0] = 1
    q, r = np.linalg.qr(van / scl[:, None, :])
    c = np.linalg.solve(r, (q.transpose(0, 2, 1) @ y[..., None]))[..., 0]
    return c / scl


def camera_lane_lines(
    road: Road,
    ego_xy: np.ndarray,
    ego_yaw: float,
    config: SensorConfig,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Left and right lines ``(4,)`` each of the ego's current lane, and that lane's index."""
    lane = road.lanes[current_lane_index(road, ego_xy)]
    left = fit_boundary(lane.left_boundary, ego_xy, ego_yaw, config)
    right = fit_boundary(lane.right_boundary, ego_xy, ego_yaw, config)
    add_lane_noise(left, right, config, rng)
    return left, right, lane.index


def radar_leader(
    ego_xy: np.ndarray,
    ego_yaw: float,
    leader_rear_xy: tuple[float, float] | np.ndarray | None,
    leader_speed: float,
    left_line: np.ndarray,
    right_line: np.ndarray,
    config: SensorConfig,
    rng: np.random.Generator | None = None,
) -> RadarTarget | None:
    """The leader if it is ahead, within range and inside the ego's lane corridor, else None.

    The corridor is the region between the camera's lane lines at the leader's distance (how an
    ACC picks its in-path target), so a drifting ego loses its leader as a real car would.
    """
    if leader_rear_xy is None:
        return None
    # world_to_ego and polyval of one point, in plain floats (the same operations)
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    dx = float(leader_rear_xy[0]) - float(ego_xy[0])
    dy = float(leader_rear_xy[1]) - float(ego_xy[1])
    x, y = c * dx + s * dy, -s * dx + c * dy
    if not 0.0 < x <= config.radar_range_m:
        return None
    y_left = _polyval(x, left_line)
    y_right = _polyval(x, right_line)
    if not y_right <= y <= y_left:
        return None
    v = float(leader_speed)
    if rng is not None:
        if config.radar_noise_m > 0:
            x = x + rng.normal() * config.radar_noise_m
        if config.radar_speed_noise_mps > 0:
            v = v + rng.normal() * config.radar_speed_noise_mps
    if config.quantization_m > 0:
        x = np.round(x / config.quantization_m) * config.quantization_m
    return RadarTarget(float(x), float(y), v)


def _polyval(x: float, coefficients: np.ndarray) -> float:
    """``np.polynomial.polynomial.polyval`` at one point: Horner from the highest coefficient."""
    c = coefficients.tolist()
    value = c[-1] + x * 0.0
    for ci in reversed(c[:-1]):
        value = ci + value * x
    return value


def leader_features(
    target: RadarTarget | None, ego_speed: float, config: SensorConfig
) -> tuple[float, float]:
    """``(v_lead, d_lead)`` for the planner; no target -> a leader at the range limit, ego speed."""
    if target is None:
        return float(ego_speed), config.no_leader_distance_m
    return target.v, target.x


class LaneCamera:
    """:func:`camera_lane_lines` for a car that moves smoothly along a road (the closed loop).

    Same lines, bit for bit, but each projection on a lane polyline walks from the segment of the
    previous call instead of scanning all N segments. Keeps that memory, so use one camera per run.

    ``start_s`` [m along the ego lane]: where the car starts. The first look at a line then walks
    from there (scaled to the line's length) instead of taking the line's nearest point, which
    on a road that passes the same place again (a closed course's laps) may be another lap's.
    """

    def __init__(self, road: Road, config: SensorConfig, start_s: float | None = None) -> None:
        self.road = road
        self.config = config
        self._segment: dict[int, int] = {}  # id(polyline) -> segment of the last projection
        self._start_s = start_s

    def _project(self, line: Polyline, x: float, y: float, near_s: float | None = None
                 ) -> tuple[float, float]:
        """``s, d`` of ``(x, y)`` on ``line``, walking from the last look at it; a first look
        walks from ``near_s`` [m along the ego lane] scaled to the line's length, else from
        the start (``start_s``), else takes the nearest point of the whole line."""
        hint = self._segment.get(id(line))
        near_s = self._start_s if near_s is None else near_s
        if hint is None and near_s is not None:
            ego = self.road.lanes[self.road.ego_lane].centre
            hint = line.segment_index(near_s * line.length / ego.length)
        elif hint is None:  # first look at this line: one full projection finds the segment
            s_full, _ = line.project(np.array([x, y]))
            hint = line.segment_index(float(s_full))
        s, d, _, self._segment[id(line)] = line.project_near(x, y, hint)
        return s, d

    def lane_lines(
        self, ego_xy: np.ndarray, ego_yaw: float, rng: np.random.Generator | None = None
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Like :func:`camera_lane_lines` (same arguments, same result)."""
        config = self.config
        lane, s_left, s_right = self.lane_stations(float(ego_xy[0]), float(ego_xy[1]))
        # both lines' points (_ego_points' operations), fitted in one call (polyfit3_rows)
        offsets = _view_offsets(config.view_range_m, config.view_samples)
        pts = np.stack((lane.left_boundary.xy_at(s_left + offsets),
                        lane.right_boundary.xy_at(s_right + offsets)))
        x, y = _to_ego(pts, ego_xy, ego_yaw)
        # else no chord turns too much: the whole view range, without the check
        if (_may_turn_too_much(lane.left_boundary, config)
                or _may_turn_too_much(lane.right_boundary, config)):
            view = view_range_within_turn(x, y, offsets, config.max_view_turn_rad,
                                          config.min_view_range_m)
            if (view < config.view_range_m).any():  # a tight bend: each line as far as it holds
                (xl, yl), (xr, yr) = (
                    _points_within(line, s0, float(v), config.view_samples, ego_xy, ego_yaw)
                    for line, s0, v in ((lane.left_boundary, s_left, view[0]),
                                        (lane.right_boundary, s_right, view[1])))
                x, y = np.stack((xl, xr)), np.stack((yl, yr))
        left, right = polyfit3_rows(x, y)
        add_lane_noise(left, right, config, rng)
        return left, right, lane.index

    def lane_stations(self, x: float, y: float) -> tuple[Lane, float, float]:
        """The lane whose lines :meth:`lane_lines` fits and the ego's arc length [m] on its
        left and right boundary (a batch samples and fits many at once with
        :func:`ego_points_many` and :func:`polyfit3_batch`)."""
        road = self.road
        s, d = self._project(road.lanes[road.ego_lane].centre, x, y)
        lane = road.lanes[_lane_index_at(road, d, s)]
        # a neighbour's lines first seen mid-run: walked from the ego's station, not the start
        near_s = s if self._start_s is not None else None
        return (lane, self._project(lane.left_boundary, x, y, near_s)[0],
                self._project(lane.right_boundary, x, y, near_s)[0])


def ego_points_many(line: Polyline, s0: np.ndarray, ego_x: np.ndarray, ego_y: np.ndarray,
                    ego_yaw: np.ndarray, config: SensorConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_ego_points` of K cars with one camera setting on one line at once: the line's
    points from arc lengths ``s0 (K,)`` [m] over the view range (shortened per car where the
    line turns more than ``config.max_view_turn_rad``, as :func:`_ego_points`), in each car's
    frame, ``x, y (K, samples)``."""
    offsets = _view_offsets(config.view_range_m, config.view_samples)
    x, y = _ego_many(line, s0[:, None] + offsets, ego_x, ego_y, ego_yaw)
    if not _may_turn_too_much(line, config):
        return x, y
    view = view_range_within_turn(x, y, offsets, config.max_view_turn_rad,
                                  config.min_view_range_m)
    short = np.flatnonzero(view < config.view_range_m)
    if len(short):
        fraction = np.linspace(0.0, 1.0, config.view_samples)
        x[short], y[short] = _ego_many(line, s0[short, None] + view[short, None] * fraction,
                                       ego_x[short], ego_y[short], ego_yaw[short])
    return x, y


def _ego_many(line: Polyline, s: np.ndarray, ego_x: np.ndarray, ego_y: np.ndarray,
              ego_yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The line's points at arc lengths ``s (K, samples)`` [m] in each of K cars' frames."""
    pts = line.xy_at(s)
    c, s_ = np.cos(ego_yaw)[:, None], np.sin(ego_yaw)[:, None]
    dx, dy = pts[..., 0] - ego_x[:, None], pts[..., 1] - ego_y[:, None]
    return c * dx + s_ * dy, -s_ * dx + c * dy
