"""The adversarial leader's counterexamples replayed in SUMO (issue 41): a state from which the
real loop (:mod:`safeil_sumo.learn.loop_rollout`) breaks the margin against an admissible
leader is run again in libsumo, on the straight track, with that leader as a recorded speed
profile, and its smallest gap compared.

A SUMO run starts the ego cruising (its tyre force the resistance at its speed, the tracker's
integral and the guard's estimate at zero) and senses exactly, so the counterexamples searched
here start there too: states drawn uniformly over the recoverable envelope
(:func:`~safeil_sumo.learn.loop_adversary.envelope_states`), the force set to cruising, the
unrecoverable dropped, every leader of the encounters run with exact sensing; of the states it
fails, the ``count`` with the smallest gaps are replayed (all of them with a large ``count``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd

from safeil_sumo.learn import loop_adversary as adv
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.learn.loop_invariant import Grid, LoopAssumptions, LoopParts, recoverable
from safeil_sumo.learn.loop_rollout import leader_speed
from safeil_sumo.scenarios.spec import ScenarioSpec, build_scenario, resolve_road
from safeil_sumo.sim import brake_guard as grd
from safeil_sumo.sim.leaders import SpeedProfile, piecewise
from safeil_sumo.sim.loop_types import LoopConfig
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.vehicle import VehicleParams, resistance_force
from safeil_sumo.sim.xp import ARRAYS

EXACT = adv.SensingPattern("exact")
TRACK = "straight"  # the catalogue's straight track: no bend, one lane


def cruising_force(v_mps: np.ndarray, vehicle: VehicleParams) -> np.ndarray:
    """The tyre force per unit mass [m/s^2] ``(N,)`` that holds speeds ``v_mps (N,)``: the
    resistance (drag and rolling) at each speed, what a SUMO run starts the ego with."""
    return np.asarray(resistance_force(np.asarray(v_mps, float), vehicle, ARRAYS)
                      / vehicle.mass_kg)


def leader_profile(leader: adv.LeaderStrategy, speed_mps: float, seconds: float,
                   a: LoopAssumptions) -> SpeedProfile:
    """``leader`` from ``speed_mps`` [m/s] as a piecewise-linear speed profile, a knot at every
    physics step: the speed updated as the rollout updates it
    (:func:`~safeil_sumo.learn.loop_rollout.leader_speed`), which SUMO reads at each step's
    end."""
    period = a.step_s * a.steps_per_decision
    periods = math.ceil(seconds / period - 1e-9)
    acc = np.repeat(leader.accel(periods, period, a), a.steps_per_decision)
    speeds = [float(speed_mps)]
    for x in acc:
        speeds.append(float(leader_speed(speeds[-1], x, a)))
    return piecewise(list(np.arange(len(speeds)) * a.step_s), speeds)


@dataclasses.dataclass(frozen=True)
class Counterexample:
    """A cruising start ``(gap [m], ego speed [m/s], leader speed [m/s])`` and the leader that
    takes the rollout's gap to ``rollout_gap_m`` [m], below the margin."""

    gap_m: float
    speed_mps: float
    lead_speed_mps: float
    leader: adv.LeaderStrategy
    rollout_gap_m: float


def search(policy: MLPPolicy, time_gap: float, guard_on: bool, n: int,
           rng: np.random.Generator, leaders: tuple[adv.LeaderStrategy, ...],
           a: LoopAssumptions, parts: LoopParts, grid: Grid) -> list[Counterexample]:
    """The counterexamples among ``n`` cruising starts drawn from ``rng`` (module doc): per
    failing state its worst leader, the smallest gap first."""
    g, v, vl, _ = adv.envelope_states(n, grid, a, parts, rng)
    f = cruising_force(v, parts.vehicle)
    keep = recoverable(g, v, vl, f, a, parts.vehicle)
    g, v, vl, f = g[keep], v[keep], vl[keep], f[keep]
    encounters = tuple(adv.Encounter(lead, EXACT) for lead in leaders)
    g_min = adv.run_encounters(policy, (g, v, vl, f), time_gap, encounters, guard_on, a, parts)
    worst = np.argmin(g_min, axis=0)
    gap = g_min[worst, np.arange(g_min.shape[1])]
    order = [i for i in np.argsort(gap, kind="stable") if gap[i] < a.margin_m]
    return [Counterexample(float(g[i]), float(v[i]), float(vl[i]), leaders[worst[i]],
                           float(gap[i])) for i in order]


COLUMNS = ("time_gap_s", "guard", "gap_m", "speed_mps", "lead_speed_mps", "leader",
           "rollout_gap_m", "sumo_gap_m", "end_reason", "confirmed")


def replay(policy: MLPPolicy, case: Counterexample, time_gap: float, guard_on: bool,
           a: LoopAssumptions) -> dict:
    """``case`` in libsumo at the planner's ``time_gap`` [s], the guard on or off, for as long
    as its leader needs (:meth:`~safeil_sumo.learn.loop_adversary.LeaderStrategy.run_s`): the
    smallest gap and how the run ended, beside the rollout's (a row of :data:`COLUMNS`)."""
    seconds = case.leader.run_s(a)
    spec = ScenarioSpec(net=TRACK, initial_gap_m=case.gap_m, ego_speed_mps=case.speed_mps)
    sc = build_scenario(spec, resolve_road(spec.net))
    sc = dataclasses.replace(sc, leader=leader_profile(case.leader, case.lead_speed_mps,
                                                       seconds, a))
    policy.set_style(time_gap_s=float(time_gap))
    run = run_scenario(sc, policy, LoopConfig(max_time_s=seconds,
                                              brake_guard=grd.when(guard_on)))
    sumo_gap = float(run.log["gap"].min())
    return {**_case_row(case, time_gap, guard_on), "sumo_gap_m": sumo_gap,
            "end_reason": str(run.summary["end_reason"]), "confirmed": sumo_gap < a.margin_m}


def _case_row(case: Counterexample, time_gap: float, guard_on: bool) -> dict:
    return {"time_gap_s": time_gap, "guard": "on" if guard_on else "off", "gap_m": case.gap_m,
            "speed_mps": case.speed_mps, "lead_speed_mps": case.lead_speed_mps,
            "leader": case.leader.name, "rollout_gap_m": case.rollout_gap_m,
            "sumo_gap_m": math.nan, "end_reason": "not replayed", "confirmed": pd.NA}


def confirm(policy: MLPPolicy, time_gap: float, guard_on: bool, n: int, count: int,
            rng: np.random.Generator, leaders: tuple[adv.LeaderStrategy, ...] | None = None,
            a: LoopAssumptions | None = None, parts: LoopParts | None = None,
            grid: Grid | None = None) -> pd.DataFrame:
    """Every counterexample :func:`search` finds, one row each (:data:`COLUMNS`), the first
    ``count`` (the smallest gaps) :func:`replay`-ed in libsumo, the rest marked "not replayed"
    (defaults: the default leaders and the assumptions, parts and grid of
    :mod:`~safeil_sumo.learn.loop_invariant`)."""
    a, parts, grid = a or LoopAssumptions(), parts or LoopParts(), grid or Grid()
    leaders = adv.default_leaders(a) if leaders is None else leaders
    cases = search(policy, time_gap, guard_on, n, rng, leaders, a, parts, grid)
    rows = [replay(policy, c, time_gap, guard_on, a) if k < count
            else _case_row(c, time_gap, guard_on) for k, c in enumerate(cases)]
    return pd.DataFrame(rows, columns=list(COLUMNS))
