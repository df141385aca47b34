"""One scenario closed-loop, to its end: :func:`run_scenario`, the loop's scalar driver.

The loop itself, SUMO scenario + sensors + policy + tracking controller + vehicle plant +
monitors, is :class:`.stepper.ClosedLoop`; ``run_scenario`` resets it with one scenario
(N = 1: the scenario's own net, the vehicles ``ego`` and ``leader``, the stages on floats) and
steps it until the scenario ends. Every step (``step_s``, 0.01 s by default): the controller
tracks the current plan, our vehicle plant advances the ego (or a kinematic ego is moved to its
recorded pose), the ego is moved in SUMO (``moveTo`` on its lane while the front bumper is
inside it, else ``moveToXY(keepRoute=2)``: ``LoopConfig.ego_placement``) + ``setSpeed``, the
leader gets its profile speed (or SUMO's traffic drives), SUMO steps, and the monitors log TTC,
lane departure and collisions. At ``plan_rate_hz`` the camera and radar are read and the policy
re-plans. SUMO comes through :mod:`.sumo_api` (libsumo, traci, sumo-gui or a fake). The loop's
types are :mod:`.loop_types`', its SUMO setup :mod:`.sumo_setup`'s and its log
:mod:`.rollout_log`'s.
"""

from __future__ import annotations

import time

from safeil_sumo.core.policy import Policy
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.loop_types import LoopConfig, Rollout, Scenario
from safeil_sumo.sim.stepper import ClosedLoop
from safeil_sumo.sim.sumo_setup import ApiFactory


def run_scenario(
    scenario: Scenario,
    policy: Policy,
    loop: LoopConfig = LoopConfig(),
    vehicle: veh.VehicleParams = veh.VehicleParams(),
    controller: ctl.ControllerParams = ctl.ControllerParams(),
    api_factory: ApiFactory | None = None,
) -> Rollout:
    """Run one scenario closed-loop and return its log and summary.

    A policy with ``pose_at(t)`` (the recorded pseudo-planner) is a kinematic ego: moved to its
    pose every step instead of being planned for, tracked and integrated by the plant.
    Bad input, and SUMO failing to start, raise. SUMO is always closed, also on error; an
    exception inside the loop ends the run with ``end_reason="error"`` and keeps the log up to
    that step.
    """
    sim = ClosedLoop(loop, vehicle, controller, api_factory)
    try:
        running = sim.reset([scenario], policy).running
        while running[0]:
            running = sim.advance()
    except Exception:  # the stepper has ended the run with the error and closed SUMO
        if not sim.started:  # refused before SUMO started, or SUMO did not start
            raise
    finally:
        sim.close()
    # the wall time from SUMO's start (the summary's steps per second: the loop's own)
    return sim.rollout(0, time.perf_counter() - sim.sumo_started_s)
