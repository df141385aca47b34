"""Sensor models — pure functions of the road geometry and vehicle states, no SUMO calls.

- camera: the left/right boundaries of the lane the ego is in, as cubic polynomials
  ``y = c0 + c1 x + c2 x^2 + c3 x^3`` in the ego frame (front-bumper origin, x forward, y left),
  fitted to the lane geometry within the camera's view range (like a MobilEye output);
- radar: the in-path leading vehicle's bumper-to-bumper distance, relative position and speed.
Optional Gaussian noise and quantisation draw from an explicit ``np.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo.geometry import Polyline, world_to_ego
from safeil_sumo.scenarios.road import Road


@dataclass(frozen=True)
class SensorConfig:
    """Camera and radar settings."""

    view_range_m: float = 60.0  # camera lane-line fit from x = 0 to this distance ahead [m]
    view_samples: int = 16  # boundary points for the cubic fit (every 4 m) [-]
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
    ref = road.lanes[road.ego_lane]
    _, d = ref.centre.project(ego_xy)
    k = int(np.rint(float(d) / ref.width))
    return int(np.clip(road.ego_lane + k, 0, len(road.lanes) - 1))


def fit_boundary(
    boundary: Polyline, ego_xy: np.ndarray, ego_yaw: float, config: SensorConfig
) -> np.ndarray:
    """Cubic coefficients ``(4,)`` (c0..c3) of one boundary in the ego frame over the view range."""
    s0, _ = boundary.project(ego_xy)
    pts, _ = boundary.point_at(float(s0) + np.linspace(0.0, config.view_range_m,
                                                       config.view_samples))
    local = world_to_ego(pts, ego_xy, ego_yaw)
    return np.polynomial.polynomial.polyfit(local[:, 0], local[:, 1], 3)


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
    if rng is not None and (config.lane_noise_c0_m > 0 or config.lane_noise_c1 > 0):
        noise = rng.normal(size=2) * [config.lane_noise_c0_m, config.lane_noise_c1]
        left[:2] += noise  # a camera's error moves both lines together
        right[:2] += noise
    return left, right, lane.index


def radar_leader(
    ego_xy: np.ndarray,
    ego_yaw: float,
    leader_rear_xy: np.ndarray | None,
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
    x, y = world_to_ego(np.asarray(leader_rear_xy, dtype=float), ego_xy, ego_yaw)
    if not 0.0 < x <= config.radar_range_m:
        return None
    y_left = np.polynomial.polynomial.polyval(x, left_line)
    y_right = np.polynomial.polynomial.polyval(x, right_line)
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


def leader_features(
    target: RadarTarget | None, ego_speed: float, config: SensorConfig
) -> tuple[float, float]:
    """``(v_lead, d_lead)`` for the planner; no target -> a leader at the range limit, ego speed."""
    if target is None:
        return float(ego_speed), config.no_leader_distance_m
    return target.v, target.x
