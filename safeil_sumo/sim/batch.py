"""N scenarios in ONE SUMO simulation, run to their ends: :func:`run_batch`.

A driver of :class:`.stepper.ClosedLoop`: it resets the stepper with the scenarios and their
planners, steps until every scenario has ended and builds each rollout (log and summary) as
it ends. The loop itself (each scenario on its own renamed copy of its track, the stages over
arrays of the running scenarios, the planner once per plan step on features ``(N, 9)``) is the
stepper's.

Same answers as ``run_scenario`` (tests/sim/test_batch.py): the same flags, flag times, path
completed and end reasons, trajectories equal to round-off (numpy's ``cos``/``sin`` may differ
from libm's by an ulp). SUMO has one ``--seed`` per simulation; the loop draws no random
number from SUMO (speed mode 0, every speed commanded) and each scenario keeps its own
``np.random.Generator(scenario.seed)`` for the sensor noise.

Traffic, sumo-gui and SSM output run one scenario at a time (``run_scenario``, N = 1); a
batch's egos are all planned or all kinematic (``pose_at``). An exception inside the loop ends
every scenario still running with ``end_reason="error"``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from safeil_sumo.core.policy import Policy
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.loop_types import LoopConfig, Rollout, Scenario
from safeil_sumo.sim.stepper import ClosedLoop, StageClock
from safeil_sumo.sim.sumo_setup import ApiFactory


def run_batch(
    scenarios: Sequence[Scenario],
    policy: Policy | Sequence[Policy],
    loop: LoopConfig = LoopConfig(),
    vehicle: veh.VehicleParams = veh.VehicleParams(),
    controller: ctl.ControllerParams = ctl.ControllerParams(),
    api_factory: ApiFactory | None = None,
    on_done: Callable[[int, Rollout], None] | None = None,
    clock: StageClock | None = None,
    keep_logs: bool = True,
    log_columns: Sequence[str] | None = None,
    net_dir: Path | None = None,
) -> list[Rollout]:
    """Run ``scenarios`` closed-loop side by side in one SUMO simulation; their rollouts in
    order. ``policy`` is one planner for all or one per scenario (scenarios sharing a planner
    object are planned in one call). ``on_done(i, rollout)`` is called as soon as scenario ``i`` ends (a sweep saves it
    then). ``clock``: filled with the time per stage. ``keep_logs=False``: the returned
    rollouts have empty logs (each log is freed once ``on_done`` has seen it: a sweep's memory
    is then the running scenarios' logs only). ``log_columns``: log only these columns (e.g.
    ``runner.SUMMARY_COLUMNS``, all a summary needs: a quarter of the memory per scenario).
    ``net_dir``: where the batch's net is written (default: the shared cache of
    :mod:`.batch_net`).

    Scenarios may be on different networks (each on its own copy of its net); with more than
    one, every one must have a scripted leader or none (no traffic) and ``loop`` must not ask
    for sumo-gui or SSM output; the egos are all planned or all kinematic (``pose_at``). SUMO's
    ``--seed`` is the first scenario's.
    """
    if not scenarios:
        return []
    sim = ClosedLoop(loop, vehicle, controller, api_factory, log_columns=log_columns,
                     net_dir=net_dir, clock=clock)
    rollouts: list[Rollout | None] = [None] * len(scenarios)
    wall0 = time.perf_counter()

    def done(i: int) -> Rollout:
        """The rollout of scenario ``i``, which has ended (kept in ``rollouts`` and returned);
        its log buffer is freed."""
        # the batch's wall time so far, shared out by steps (what one scenario cost of it)
        steps = sim.steps
        wall = (time.perf_counter() - wall0) * steps[i] / max(int(steps.sum()), 1)
        rollout = sim.rollout(i, wall)
        sim.free_log(i)
        if on_done is not None:
            on_done(i, rollout)
        if not keep_logs:
            rollout = Rollout(rollout.log.iloc[:0], rollout.summary)
        rollouts[i] = rollout
        return rollout

    try:
        # one BLAS thread: the batch's matrices are small, and a sweep already runs one worker
        # per core (OpenBLAS's own threads made 2 workers at batch 256 run 2.1x slower)
        with threadpool_limits(limits=1, user_api="blas"):
            running = sim.reset(scenarios, policy).running
            while running.any():
                now = sim.advance()
                for ended in np.flatnonzero(running & ~now):  # ended during this step
                    done(int(ended))
                running = now
    except Exception:  # the stepper has ended every running scenario with the error
        if not sim.started:  # refused before SUMO started: bad input
            raise
    finally:
        sim.close()
    # a rollout still None: the loop failed before it ended
    return [done(i) if rollout is None else rollout for i, rollout in enumerate(rollouts)]
