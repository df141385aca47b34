"""The lateral closed loop's own code for one decision period on a circular lane (the camera's
fit, the network, pure pursuit and the plant), for the tests of the lateral bound
(tests/learn/test_loop_lateral.py)."""

from __future__ import annotations

import math

import numpy as np

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.sensors import SensorConfig, fit_boundary
from safeil_sumo.sim.xp import ARRAYS


def arc(curvature: float, offset_m: float, start_m: float = -30.0, end_m: float = 120.0,
        ds_m: float = 0.5) -> np.ndarray:
    """Points ``(n, 2)`` [m] of the line ``offset_m`` left of a lane centre that starts at the
    origin heading +x and turns with ``curvature`` [1/m] (a circle about ``(0, 1/curvature)``)."""
    s = np.arange(start_m, end_m, ds_m)
    if curvature == 0.0:
        return np.stack([s, np.full_like(s, offset_m)], 1)
    radius = 1.0 / curvature
    th = s * curvature
    return np.stack([(radius - offset_m) * np.sin(th),
                     radius - (radius - offset_m) * np.cos(th)], 1)


CAMERA = SensorConfig()


def camera_lines(e_y, e_psi, curvature, width, config=CAMERA):
    """The camera's lines ``(N, 3)`` x2 of the ego's front bumper at lane offset ``e_y`` and
    heading error ``e_psi`` (arrays ``(N,)``) at the start of the lane of :func:`arc`, by the
    simulation's own fit (:func:`safeil_sumo.sim.sensors.fit_boundary`)."""
    left, right = [], []
    for ey, ep, k, w in zip(e_y, e_psi, curvature, width, strict=True):
        xy = np.array([0.0, ey])
        left.append(fit_boundary(Polyline(arc(float(k), w / 2)), xy, float(ep), config)[:3])
        right.append(fit_boundary(Polyline(arc(float(k), -w / 2)), xy, float(ep), config)[:3])
    return np.array(left), np.array(right)


def lane_pose(x, y, yaw, curvature, vehicle):
    """The front bumper's offset from the lane centre of :func:`arc` [m] and the heading less
    the lane's there [rad], from the CoG pose (arrays ``(N,)``): plain geometry of the circle."""
    d = vehicle.cog_to_front_bumper_m
    fx, fy = x + d * np.cos(yaw), y + d * np.sin(yaw)
    k = np.asarray(curvature, float)
    straight = k == 0.0
    radius = 1.0 / np.where(straight, 1.0, k)
    ox, oy = fx, fy - radius  # F - O
    dist = np.hypot(ox, oy)
    e_y = np.where(straight, fy, (1.0 - np.abs(k) * dist) / np.where(straight, 1.0, k))
    sgn = np.sign(k)
    lane_yaw = np.where(straight, 0.0, np.arctan2(sgn * ox, -sgn * oy))
    e_psi = (yaw - lane_yaw + math.pi) % (2 * math.pi) - math.pi
    return e_y, e_psi


def real_lateral_period(policy, e_y, e_psi, steer, vy, r, v, curvature, width, lead, gap,
                        integral, force, accel, a, parts):
    """One decision period of the real camera, planner, tracker and plant for N states
    ``(N,)`` on the circular lane of :func:`arc`: sensed leader speed ``lead`` and gap ``gap``
    into the network, the PI ``integral`` and the plant's tyre force per mass ``force``;
    ``accel (N, steps)`` [m/s^2] replaces the tracker's acceleration command where finite (a
    guard's braking). Returns the final ``(e_y, e_psi, steer, vy, r, v)``, the front bumper's
    offsets at every physics step ``(N, steps)`` and the camera's lines ``(N, 3)`` x2."""
    vehicle = parts.vehicle
    n = len(e_y)
    left, right = camera_lines(e_y, e_psi, curvature, width)
    feats = np.concatenate([left, right, np.stack([v, lead, gap], 1)], 1)
    cps = policy.plan(feats)
    d = vehicle.cog_to_front_bumper_m
    yaw = np.asarray(e_psi, float).copy()
    state = (-d * np.cos(yaw), e_y - d * np.sin(yaw), yaw, v.copy(), vy.copy(), r.copy(),
             steer.copy(), force * vehicle.mass_kg)
    target = ctl.make_targets(cps, np.full(n, policy.horizon), 0 * e_y, e_y + 0.0, yaw)
    plant = veh.Plant.of(vehicle, a.step_s)
    prev_error = np.full(n, math.nan)
    path = []
    for j in range(a.steps_per_decision):
        steer_cmd, acc, integral, prev_error = ctl.track_values(
            target, np.full(n, j * a.step_s), *state[:6], vehicle, integral, prev_error,
            parts.controller, a.step_s, ARRAYS)
        acc = np.where(np.isfinite(accel[:, j]), accel[:, j], acc)
        throttle, brake = veh.pedals_from_accel_vx(acc, state[3], vehicle, ARRAYS)
        state = plant.step(state, steer_cmd, throttle, brake, ARRAYS)
        path.append(lane_pose(state[0], state[1], state[2], curvature, vehicle)[0])
    e_y1, e_psi1 = lane_pose(state[0], state[1], state[2], curvature, vehicle)
    return (e_y1, e_psi1, state[6], state[4], state[5], state[3]), np.stack(path, 1), (left,
                                                                                        right)


def random_loop_inputs(rng, n: int, a, parts):
    """The leader and actuator draws of a random period (arrays ``(n,)``; accelerations
    ``(n, steps)``): lane width [m], leader speed [m/s] and gap [m], overriding accelerations
    (30 % of the rows, else NaN) [m/s^2], PID integral [m], tyre force per mass [m/s^2]."""
    width = rng.uniform(*a.lane_width_m, n)
    lead = rng.uniform(0.0, 40.0, n)
    gap = np.exp(rng.uniform(np.log(3.0), np.log(150.0), n))
    accel = np.where(rng.random((n, 1)) < 0.3, rng.uniform(-9.0, 3.0, (n, a.steps_per_decision)),
                     np.nan)
    integral = rng.uniform(-1.0, 1.0, n) * parts.controller.integral_limit_m
    force = rng.uniform(-9.0, 3.0, n)
    return width, lead, gap, accel, integral, force


def logged_lateral_states(log, spec, vehicle=veh.VehicleParams()):
    """The lateral state of every row of a closed-loop log on a circular test track
    (:class:`safeil_sumo.roads.track.TrackSpec` ``spec``, the ego lane's centre a circle of
    radius ``spec.radius_m`` about ``(run_in_m, road_radius_m)``), as the lateral bound reads
    it: a dict of arrays ``(rows,)`` ``e_y`` (front bumper's offset from the exact circle) [m],
    ``e_psi`` [rad], ``steer`` (the plant's road-wheel angle) [rad], ``vy`` [m/s], ``r``
    [rad/s], ``v`` (the plant's longitudinal speed, from the logged speed ``hypot(vx, vy)``)
    [m/s] and ``curvature`` [1/m]."""
    k = 1.0 / spec.radius_m
    # lane_pose's circle is about (0, 1 / k): the track's, shifted
    x = log["x"].to_numpy() - spec.run_in_m
    y = log["y"].to_numpy() - (spec.road_radius_m - spec.radius_m)
    e_y, e_psi = lane_pose(x, y, log["yaw"].to_numpy(), np.full(len(x), k), vehicle)
    vy = log["vy"].to_numpy()
    return {"e_y": e_y, "e_psi": e_psi, "steer": log["steer"].to_numpy(), "vy": vy,
            "r": log["yaw_rate"].to_numpy(), "v": np.sqrt(log["v"].to_numpy() ** 2 - vy * vy),
            "curvature": np.full(len(x), k)}
