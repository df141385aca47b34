"""The ``constant_speed`` pseudo-planner: the naive baseline of the car-following literature.

The ego keeps its initial speed for the whole replay, on the centre of its lane, and does not
react to the leader. Like the ``recorded`` pseudo-planner (:mod:`safeil_sumo.sim.recorded_ego`)
it is a kinematic pose source: the closed loop (:func:`safeil_sumo.sim.runner.run_scenario`)
calls ``pose_at(t)`` instead of planning, tracking and integrating the plant, and everything else
is the normal loop (SUMO, the recorded leader, the sensors, the monitors). When the leader slows
down the ego runs into it: the run then ends with ``end_reason == "collision"``, recorded like
any planner's.

Its gap error against the human is the error of predicting "the follower keeps its speed": a
planner worse than that has learned nothing about following.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from safeil_sumo.core.geometry import Polyline
from safeil_sumo.core.policy import PLAN_HORIZON_S
from safeil_sumo.sim.recorded_ego import RecordedPathError

CONSTANT_SPEED_NAME = "constant_speed"


@dataclass(frozen=True)
class ConstantSpeedPath:
    """The ego's front bumper on ``lane`` (its centre line, in the replay road's frame) at arc
    length ``s0 + speed * t`` [m], heading along the lane, speed ``speed`` [m/s] for ``t >= 0``
    [s]. An unbound instance (no lane) is what
    ``planner_registry.load_for_replay("constant_speed")`` returns;
    :func:`safeil_sumo.experiments.maneuver_replay.replay_policy` binds it to the maneuver it
    replays (the recorded start and initial speed)."""

    lane: Polyline | None = None
    s0: float = 0.0  # [m] arc length of the front bumper at t = 0
    speed: float = 0.0  # [m/s]
    name: str = CONSTANT_SPEED_NAME
    horizon: float = PLAN_HORIZON_S  # [s] unused (nothing is planned); kept for the Policy protocol

    def __post_init__(self) -> None:
        if self.speed < 0:
            raise RecordedPathError(f"constant_speed: speed {self.speed} m/s must be >= 0")

    @property
    def bound(self) -> bool:
        return self.lane is not None

    def pose_at(self, t: float) -> tuple[float, float, float, float]:
        """Front bumper ``x, y`` [m], heading [rad] and speed [m/s] at ``t`` [s] (held at the
        start for ``t < 0``)."""
        if self.lane is None:
            raise RecordedPathError(
                "the 'constant_speed' baseline keeps a recorded maneuver's initial speed: use "
                "it with python -m safeil_sumo.replay, not with run or sweep")
        xy, yaw = self.lane.point_at(self.s0 + self.speed * max(t, 0.0))
        return float(xy[0]), float(xy[1]), float(yaw), self.speed

    def plan(self, features: np.ndarray) -> np.ndarray:
        """Not a planner: the closed loop calls :meth:`pose_at` instead."""
        raise RecordedPathError("the 'constant_speed' pseudo-planner does not plan; the closed "
                                "loop drives it through pose_at()")
