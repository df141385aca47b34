"""The ``recorded`` pseudo-planner: the ego driven along the human's own recorded path.

It plans nothing. In the closed loop (:func:`safeil_sumo.sim.runner.run_scenario`) an object with
a ``pose_at(t)`` method replaces the planner, the tracking controller and the vehicle plant: the
ego's front bumper, heading and speed at each step are the recording's, linearly interpolated
between samples. Everything else is the normal loop: SUMO moves the ego with ``moveToXY``, the
recorded leader drives its speed profile, the sensors read the rebuilt lane and the monitors flag.

That makes it the sanity check of the replay instrument: on a faithful digital twin the recorded
ego raises no flag and its gap, speed and lateral offset equal the human's up to the
reconstruction error (road smoothing, leader speed integration). A policy's error in a replay is
only meaningful next to this floor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.core.policy import PLAN_HORIZON_S

RECORDED_NAME = "recorded"


class RecordedPathError(ValueError):
    """The recorded pseudo-planner used where there is no recording (run, sweep, ...)."""


@dataclass(frozen=True)
class RecordedPath:
    """The recorded ego as a kinematic pose source, in the replay road's frame.

    ``times`` (N,) [s from the replay start, increasing], ``front_xy`` (N, 2) [m] the recorded
    front bumper, ``yaw`` (N,) [rad] the recorded heading (unwrapped), ``speed`` (N,) [m/s] the
    recorded longitudinal speed. With a ``lane`` (the ego lane's centre), ``yaw`` is the heading
    RELATIVE to that lane and the heading at ``t`` is the lane's where the front bumper is then
    plus that (interpolated): between two samples the body turns with the lane, vertex by
    vertex, as the monitors see it (interpolating world headings would lag a lane vertex by up
    to a sample: 0.2 rad on the 4 m radii of GNSS wander at walking pace). ``lane_start_s``
    [m]: where along the lane the first sample lies (the walk starts there: a closed course
    passes the same place on every lap). An unbound instance (no samples) is what
    ``planner_registry.load("recorded")`` returns;
    :func:`safeil_sumo.experiments.maneuver_replay.replay_maneuver` binds it to the maneuver it replays.
    """

    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    front_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    yaw: np.ndarray = field(default_factory=lambda: np.zeros(0))
    speed: np.ndarray = field(default_factory=lambda: np.zeros(0))
    name: str = RECORDED_NAME
    horizon: float = PLAN_HORIZON_S  # [s] unused (nothing is planned); kept for the Policy protocol
    lane: Polyline | None = None
    lane_start_s: float = 0.0  # [m]
    # the lane segment under each sample, (n,): set by __post_init__
    _segments: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.times, float)
        xy = np.asarray(self.front_xy, float).reshape(-1, 2)
        yaw = np.unwrap(np.asarray(self.yaw, float)) if len(self.yaw) else np.zeros(0)
        v = np.asarray(self.speed, float)
        if not (len(t) == len(xy) == len(yaw) == len(v)):
            raise RecordedPathError("times, front_xy, yaw and speed need one row per sample")
        if len(t) and (np.any(np.diff(t) <= 0) or not np.all(np.isfinite(t))):
            raise RecordedPathError("recorded times must be finite and strictly increasing")
        if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(yaw)) and np.all(np.isfinite(v))):
            raise RecordedPathError("the recorded path has NaN/inf positions, headings or speeds")
        for name, value in (("times", t), ("front_xy", xy), ("yaw", yaw), ("speed", v)):
            object.__setattr__(self, name, value)
        # the lane segment under each sample: where pose_at's walk starts between samples
        segments = np.zeros(0, dtype=int)
        if self.lane is not None and len(t):
            s, _ = self.lane.project_along(xy, self.lane_start_s)
            segments = np.array([self.lane.segment_index(v) for v in s.tolist()], dtype=int)
        object.__setattr__(self, "_segments", segments)

    @property
    def bound(self) -> bool:
        return len(self.times) >= 2

    def pose_at(self, t: float) -> tuple[float, float, float, float]:
        """Front bumper ``x, y`` [m], heading [rad] and speed [m/s] at ``t`` [s] (held at the
        ends)."""
        if not self.bound:
            raise RecordedPathError(
                "the 'recorded' planner replays a recorded maneuver's own path: use it with "
                "python -m safeil_sumo.replay, not with run or sweep")
        ts = self.times
        x = float(np.interp(t, ts, self.front_xy[:, 0]))
        y = float(np.interp(t, ts, self.front_xy[:, 1]))
        yaw = float(np.interp(t, ts, self.yaw))
        if self.lane is not None:
            i = min(max(int(np.searchsorted(ts, t, side="right")) - 1, 0), len(ts) - 1)
            yaw += self.lane.project_near(x, y, int(self._segments[i]))[2]
        return x, y, yaw, max(float(np.interp(t, ts, self.speed)), 0.0)

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Not a planner: the closed loop calls :meth:`pose_at` instead."""
        raise RecordedPathError("the 'recorded' pseudo-planner does not plan; the closed loop "
                                "drives it through pose_at()")

