"""The closed loop's types: what a run is given (:class:`Scenario`, :class:`LoopConfig`) and what
it returns (:class:`Rollout`).

Their own module, below the loop: the scenario layer (:mod:`safeil_sumo.scenarios.spec`,
:mod:`safeil_sumo.scenarios.safety`) builds Scenarios without importing the loop that runs them
(docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from safeil_sumo.core.policy import PLAN_RATE_HZ
from safeil_sumo.roads.road import Road
from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim import sensors as sen
from safeil_sumo.sim import traffic as trf
from safeil_sumo.sim.brake_guard import BrakeGuard
from safeil_sumo.sim.leaders import SpeedProfile

GUI_SCREENSHOT_AT_S = 1.0  # simulation time of LoopConfig.gui_screenshot [s]
EGO_PLACEMENTS = ("xy", "lane")  # LoopConfig.ego_placement
LATERAL_MODES = ("free", "lane")  # LoopConfig.lateral
TIME_LIMIT_REASONS = ("timeout", "recording_end")  # Scenario.time_limit_reason


@dataclass(frozen=True)
class Scenario:
    """One closed-loop test: a road, a leader speed profile and the ego's initial state.

    The paper fixes the leader (constant speed in [25, 32] m/s) but leaves the ego's initial
    state open; we start the ego at ``ego_speed_mps`` = 30 m/s (~108 km/h, close to the paper's
    115 km/h data) with a bumper-to-bumper gap of ``initial_gap_m`` = 50 m (~1.7 s), at the
    start of the test path.
    """

    name: str
    road: Road
    leader: SpeedProfile | None
    ego_speed_mps: float = 30.0  # ego initial speed [m/s]
    initial_gap_m: float = 50.0  # initial bumper-to-bumper gap to the leader [m]
    seed: int = 0  # seeds SUMO and the sensor noise
    ego_lateral_offset_m: float = 0.0  # initial front-bumper offset from the lane centre, left + [m]
    ego_heading_offset_rad: float = 0.0  # initial yaw minus lane heading [rad]
    max_time_s: float | None = None  # scenario duration; None: the loop's default [s]
    # the end reason at max_time_s: "timeout", or "recording_end" where the time limit is the end
    # of a recorded leader's profile (a run that used up its recording ended normally)
    time_limit_reason: str = "timeout"
    sensors: sen.SensorConfig = field(default_factory=sen.SensorConfig)
    monitors: mon.MonitorConfig = field(default_factory=mon.MonitorConfig)
    # SUMO's own vehicles as leaders (the radar target is SUMO's leader of the ego); no
    # scripted leader then
    traffic: trf.Traffic | None = None

    def __post_init__(self) -> None:
        if self.traffic is not None and self.leader is not None:
            raise ValueError("a scenario with traffic has no scripted leader (leader=None)")
        if self.time_limit_reason not in TIME_LIMIT_REASONS:
            raise ValueError(f"time_limit_reason must be one of {TIME_LIMIT_REASONS}, got "
                             f"{self.time_limit_reason!r}")
        if not self.ego_speed_mps >= 0:
            raise ValueError(f"ego initial speed must be >= 0 m/s, got {self.ego_speed_mps}")
        if not self.initial_gap_m > 0:
            raise ValueError(f"initial gap must be > 0 m, got {self.initial_gap_m}")


@dataclass(frozen=True)
class LoopConfig:
    """How the loop runs."""

    step_s: float = 0.01  # SUMO and plant step [s] (the paper's digital-twin step)
    plan_rate_hz: float = PLAN_RATE_HZ  # re-planning rate [Hz]
    max_time_s: float | None = None  # None: 2x the path at the initial speed + 10 s [s]
    stop_on_flag: bool = False  # end the run at the first safety flag
    offroad_stop_m: float = 6.0  # end the run when the ego centre is this far off its lane [m]
    backend: str = "libsumo"  # "libsumo" | "traci"
    gui: bool = False  # sumo-gui (traci backend only)
    gui_screenshot: Path | None = None  # PNG of sumo-gui's view at GUI_SCREENSHOT_AT_S (gui only)
    ssm_file: Path | None = None  # write SUMO's SSM device output for the ego here
    # how SUMO is told where the ego is, every step: "xy" moveToXY, the exact pose (front
    # bumper, heading; ~25 us per call, the loop's largest SUMO cost); "lane" moveTo at the
    # front bumper's arc length on its lane (~1 us) while the front bumper is inside the lane,
    # moveToXY when it is not: SUMO then sees an ego inside its lane on the centre line, heading
    # along it. Our monitors never read the ego back from SUMO, and SUMO's collision check is per
    # lane and longitudinal, so both give the same logs with a scripted leader (tested); among
    # traffic, SUMO's vehicles react to the ego's SUMO position, so logs differ by millimetres.
    # sumo-gui always gets "xy" (it shows the true pose)
    ego_placement: str = "lane"
    # collision-avoidance braking under the planner (:mod:`.brake_guard`); None: the planner's
    # and tracker's commands alone (the paper's loop)
    brake_guard: BrakeGuard | None = field(default_factory=BrakeGuard)
    # a planned ego's lateral motion: "free", the plan tracked by pure pursuit on the plant
    # (the paper's loop); "lane", an INSTRUMENT MODE for longitudinal-only evaluation (a replay
    # of a road whose bends a planner cannot hold, docs/human_likeness.md): after every physics
    # step the ego is put on its lane centre (front bumper) at the station its own motion
    # reached, heading along the lane, no side slip; the planner (with its normal features),
    # the PID and the plant still drive the longitudinal part. Kinematic egos ignore it
    lateral: str = "free"

    def __post_init__(self) -> None:
        if self.lateral not in LATERAL_MODES:
            raise ValueError(f"lateral must be one of {LATERAL_MODES}, got {self.lateral!r}")
        if self.ego_placement not in EGO_PLACEMENTS:
            raise ValueError(f"ego_placement must be one of {EGO_PLACEMENTS}, got "
                             f"{self.ego_placement!r}")
        if not 0 < self.step_s <= 0.1:
            raise ValueError(f"step_s must be in (0, 0.1] s, got {self.step_s}")
        if not 0 < self.plan_rate_hz <= 1.0 / self.step_s:
            raise ValueError(f"plan rate must be in (0, {1.0 / self.step_s:g}] Hz, got "
                             f"{self.plan_rate_hz}")
        if self.gui_screenshot is not None and not self.gui:
            raise ValueError("gui_screenshot needs gui=True")


@dataclass(frozen=True)
class Rollout:
    """A finished run: per-step ``log`` and a flat ``summary`` of the scenario."""

    log: pd.DataFrame
    summary: dict[str, Any]
