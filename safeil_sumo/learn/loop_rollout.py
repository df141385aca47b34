"""The longitudinal closed loop's own code on a straight lane, vectorised over N states.

The same pieces SUMO's loop runs (:mod:`safeil_sumo.sim.runner`), without SUMO: the planner
re-planned at every decision from the sensed state, the real tracker
(:func:`safeil_sumo.sim.controller.track_values`, its PI integral carried), the brake guard's
override (:mod:`safeil_sumo.sim.brake_guard`, its leader-acceleration estimate carried between
decisions) and the plant (:meth:`safeil_sumo.sim.vehicle.Plant.step`, steering included). The
leader moves by explicit Euler on its new speed (SUMO's), its speed clipped to
``[0, LoopAssumptions.speed_limit_mps]``.

The state of a decision is ``(g, v, v_l, f)``: bumper gap [m], ego speed [m/s], leader speed
[m/s], the ego's longitudinal tyre force per unit mass [m/s^2]. The inputs an adversary
chooses: the leader's acceleration [m/s^2] per state and physics step (or per decision
period), and the sensing errors ``(ego speed [m/s], leader speed [m/s], gap [m])`` per state
and decision, added to the true values before the planner and the guard read them.

:func:`one_period` runs one decision period from given tracker and guard memories (the
containment tests of :mod:`.loop_invariant` and :mod:`.loop_barrier`); :func:`run` runs many
from a fresh start (the real loop's counterexamples, :mod:`.loop_adversary`). Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.learn.loop_invariant import LoopAssumptions, LoopParts
from safeil_sumo.sim import brake_guard as grd
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.xp import ARRAYS

LANE_WIDTH_M = 3.5  # the straight lane of run() [m]


def leader_per_step(leader_accel: float | np.ndarray, n: int, periods: int,
                    steps_per_decision: int) -> np.ndarray:
    """The leader's acceleration [m/s^2] ``(n, periods, steps_per_decision)`` (a read-only view
    where it repeats) of a float (every state, every step), ``(n,)`` (per state), ``(n,
    periods)`` (per decision period) or ``(n, periods * steps_per_decision)`` (per physics
    step)."""
    shape = (n, periods, steps_per_decision)
    acc = np.asarray(leader_accel, float)
    if acc.ndim == 0 or acc.shape == (n,):
        return np.broadcast_to(acc.reshape(-1, 1, 1), shape)
    if acc.shape == (n, periods * steps_per_decision):
        return acc.reshape(shape)
    if acc.shape == (n, periods):
        return np.broadcast_to(acc[:, :, None], shape)
    raise ValueError(f"leader acceleration must be a float, ({n},), ({n}, {periods}) or "
                     f"({n}, {periods * steps_per_decision}), got {acc.shape}")


def sensing_per_decision(sensing: np.ndarray, n: int, periods: int) -> np.ndarray:
    """The sensing errors ``(3, n, periods)`` [ego speed m/s, leader speed m/s, gap m] of
    ``(3,)`` (constant, every state), ``(3, n)`` (constant per state) or ``(3, n, periods)``."""
    err = np.asarray(sensing, float)
    if err.shape == (3,):
        return np.broadcast_to(err[:, None, None], (3, n, periods))
    if err.shape == (3, n):
        return np.broadcast_to(err[:, :, None], (3, n, periods))
    if err.shape == (3, n, periods):
        return err
    raise ValueError(f"sensing errors must be (3,), (3, {n}) or (3, {n}, {periods}), got "
                     f"{err.shape}")


def _guard(parts: LoopParts, guard_on: bool) -> grd.BrakeGuard:
    """The guard whose estimate and demand the loop computes (the default one when off: its
    demand is then not used)."""
    if parts.guard is None and guard_on:
        raise ValueError("guard_on needs LoopParts.guard")
    return parts.guard or grd.BrakeGuard()


def _override(accel: Any, demand: Any, vehicle: veh.VehicleParams) -> Any:
    """The guard's override of the tracker's command: ``-demand`` (at most full braking) where
    the guard demands more braking than the tracker asks for."""
    override = (demand > 0.0) & (demand > -accel)
    return np.where(override, np.maximum(-demand, -vehicle.max_brake_decel_mps2), accel)


def one_period(policy: MLPPolicy, g: np.ndarray, v: np.ndarray, vl: np.ndarray, f: np.ndarray,
               lane: tuple[np.ndarray, np.ndarray, np.ndarray], time_gap: float,
               integral: np.ndarray, leader_accel: np.ndarray, sensing: np.ndarray,
               a_est: np.ndarray, guard_on: bool, a: LoopAssumptions, parts: LoopParts
               ) -> tuple[np.ndarray, ...]:
    """One decision period from N states ``(N,)``, the ego's front bumper on the lane's
    ``lane = (width, offset, heading)`` ``(N,)`` each [m, m, -], the tracker's ``integral``
    ``(N,)`` [m] and the guard's leader estimate ``a_est`` ``(N,)`` [m/s^2] given; the leader
    at ``leader_accel`` ``(N, steps_per_decision)`` [m/s^2], the sensing errors ``sensing``
    ``(3, N)``. Returns the final ``(g, v, vl, f)`` and the smallest gap met, each ``(N,)``."""
    vehicle, guard = parts.vehicle, _guard(parts, guard_on)
    n = len(g)
    width, offset, heading = lane
    feats = np.stack([width / 2 - offset, heading, 0 * g, -width / 2 - offset, heading, 0 * g,
                      v + sensing[0], vl + sensing[1], g + sensing[2]], axis=1)
    policy.set_style(time_gap_s=float(time_gap))
    cps = policy.plan(feats)
    yaw = -np.arctan(heading)
    d = vehicle.cog_to_front_bumper_m
    state: Any = (-d * np.cos(yaw), offset - d * np.sin(yaw), yaw, v.copy(), 0 * g, 0 * g,
                  0 * g, f * vehicle.mass_kg)
    target = ctl.make_targets(cps, np.full(n, policy.horizon), 0 * g, offset + 0 * g, yaw)
    demand = grd.guard_decel(feats[:, 8], feats[:, 6], feats[:, 7], a_est, guard, ARRAYS)
    plant = veh.Plant.of(vehicle, a.step_s)
    # the guard's memory is not read here: its estimate a_est and demand are given
    loop = _Loop(state, g.copy(), vl.copy(), integral, np.full(n, math.nan), None, g.copy(),
                 np.zeros(n))
    for j in range(a.steps_per_decision):
        _physics_step(loop, target, j * a.step_s, demand, leader_accel[:, j], guard_on, a,
                      parts, plant, (j + 1) * a.step_s)
    state = loop.plant
    gap = loop.lead_x - (state[0] + d * np.cos(state[2]))
    return gap, state[3], loop.lead_v, state[7] / vehicle.mass_kg, loop.g_min


@dataclass
class Rollout:
    """What :func:`run` returns, per state ``(N,)``: the smallest gap met [m] and when [s] (0:
    the start), and the final gap [m], ego and leader speeds [m/s]."""

    g_min: np.ndarray
    t_min: np.ndarray
    g_end: np.ndarray
    v_end: np.ndarray
    vl_end: np.ndarray


@dataclass
class _Loop:
    """The loop's carried state between physics steps (arrays ``(N,)``; ``plant`` the plant's
    8-tuple), and its smallest gap so far."""

    plant: veh.PlantState
    lead_x: Any  # arrays (N,) (Any: the loop's functions type them as floats or arrays)
    lead_v: Any
    integral: Any
    prev_error: Any
    memory: Any  # the guard's: (a_lead, v_lead, gap, v_ego) as sensed
    g_min: Any
    t_min: Any


def _start(g: np.ndarray, v: np.ndarray, vl: np.ndarray, f: np.ndarray,
           vehicle: veh.VehicleParams) -> _Loop:
    """The ego's front bumper at x = 0 on the lane's centre, heading along it; the tracker and
    the guard with no history."""
    n, d = len(g), vehicle.cog_to_front_bumper_m
    zero = np.zeros(n)
    plant: veh.PlantState = (-d + zero, zero, zero, v.astype(float).copy(), zero, zero, zero,
             f * vehicle.mass_kg)
    return _Loop(plant, g.astype(float).copy(), vl.astype(float).copy(), zero.copy(),
                 np.full(n, math.nan), grd.no_history(n, ARRAYS), g.astype(float), zero.copy())


def _decide(policy: MLPPolicy, loop: _Loop, sensing: np.ndarray, a: LoopAssumptions,
            parts: LoopParts, guard: grd.BrakeGuard, lane_width: float
            ) -> tuple[ctl.BatchTarget, Any]:
    """The decision from the sensed state (``sensing (3, N)``): the tracker's target of the
    new plan and the guard's demand [m/s^2] ``(N,)``; the guard's memory updated."""
    state: Any = loop.plant
    d = parts.vehicle.cog_to_front_bumper_m
    zero = np.zeros(len(loop.lead_x))
    x0, y0, yaw = state[0] + d * np.cos(state[2]), state[1] + d * np.sin(state[2]), state[2]
    heading = -np.tan(yaw)
    v_s, vl_s, gap_s = state[3] + sensing[0], loop.lead_v + sensing[1], \
        loop.lead_x - x0 + sensing[2]
    feats = np.stack([lane_width / 2 - y0 + zero, heading, zero, -lane_width / 2 - y0 + zero,
                      heading, zero, v_s, vl_s, gap_s], axis=1)
    target = ctl.make_targets(policy.plan(feats), np.full(len(zero), policy.horizon), x0, y0,
                              yaw)
    period = a.step_s * a.steps_per_decision
    prev_a, prev_vl, prev_gap, prev_v = loop.memory
    a_lead = grd.leader_accel(prev_a, prev_vl, prev_gap, prev_v, vl_s, gap_s, period, guard,
                              ARRAYS)
    loop.memory = (a_lead, vl_s, gap_s, v_s)
    return target, grd.guard_decel(gap_s, v_s, vl_s, a_lead, guard, ARRAYS)


def leader_speed(v_mps: Any, accel_mps2: Any, a: LoopAssumptions) -> Any:
    """The leader's speed [m/s] one physics step after ``v_mps`` at ``accel_mps2`` [m/s^2]
    (floats or arrays): explicit Euler, kept in ``[0, a.speed_limit_mps]``."""
    return np.clip(v_mps + accel_mps2 * a.step_s, 0.0, a.speed_limit_mps)


def _physics_step(loop: _Loop, target: ctl.BatchTarget, t_plan: float, demand: Any,
                  leader_accel: np.ndarray, guard_on: bool, a: LoopAssumptions,
                  parts: LoopParts, plant: veh.Plant, t_now: float) -> None:
    """One physics step of tracker, guard override, plant and leader (``leader_accel (N,)``
    [m/s^2]), ``t_plan`` [s] after the decision; the smallest gap and its time updated."""
    vehicle, dt = parts.vehicle, a.step_s
    state, d = loop.plant, vehicle.cog_to_front_bumper_m
    steer, accel, loop.integral, loop.prev_error = ctl.track_values(
        target, np.full(len(loop.lead_x), t_plan), *state[:6], vehicle, loop.integral,
        loop.prev_error, parts.controller, dt, ARRAYS)
    if guard_on:
        accel = _override(accel, demand, vehicle)
    throttle, brake = veh.pedals_from_accel_vx(accel, state[3], vehicle, ARRAYS)
    loop.plant = state = plant.step(state, steer, throttle, brake, ARRAYS)
    loop.lead_v = leader_speed(loop.lead_v, leader_accel, a)
    loop.lead_x = loop.lead_x + loop.lead_v * dt
    gap = loop.lead_x - (state[0] + d * np.cos(state[2]))
    loop.t_min = np.where(gap < loop.g_min, t_now, loop.t_min)
    loop.g_min = np.minimum(loop.g_min, gap)


def _all_stand(loop: _Loop) -> bool:
    return bool(np.all(loop.plant[3] < 0.01) and np.all(loop.lead_v <= 0.0))


def run(policy: MLPPolicy, g: np.ndarray, v: np.ndarray, vl: np.ndarray, f: np.ndarray,
        time_gap: float, leader_accel: float | np.ndarray, sensing: np.ndarray,
        guard_on: bool, a: LoopAssumptions, parts: LoopParts, periods: int,
        lane_width: float = LANE_WIDTH_M, settle_s: float | None = None) -> Rollout:
    """``periods`` decisions of the real loop from N states ``(N,)`` on a straight lane of
    ``lane_width`` [m], the ego's front bumper on its centre: the plan re-made at every
    decision from the sensed state at the planner's ``time_gap`` [s] setting, the integral,
    the guard's estimate and the plant carried over. The leader accelerates at
    ``leader_accel`` [m/s^2] (:func:`leader_per_step`'s shapes) down to standstill, the sensing
    errors are ``sensing`` (:func:`sensing_per_decision`'s shapes). With ``settle_s`` [s] the
    run ends early once every ego (below 0.01 m/s) and every leader have stood that long."""
    n, steps = len(g), a.steps_per_decision
    acc = leader_per_step(leader_accel, n, periods, steps)
    err = sensing_per_decision(sensing, n, periods)
    loop, guard = _start(g, v, vl, f, parts.vehicle), _guard(parts, guard_on)
    plant = veh.Plant.of(parts.vehicle, a.step_s)
    policy.set_style(time_gap_s=float(time_gap))
    standing = 0  # decisions since every car stood
    for k in range(periods):
        standing = standing + 1 if _all_stand(loop) else 0
        if settle_s is not None and standing * a.step_s * steps > settle_s:
            break
        target, demand = _decide(policy, loop, err[:, :, k], a, parts, guard, lane_width)
        for j in range(steps):
            _physics_step(loop, target, j * a.step_s, demand, acc[:, k, j], guard_on, a, parts,
                          plant, (k * steps + j + 1) * a.step_s)
    gap = loop.lead_x - (loop.plant[0] + parts.vehicle.cog_to_front_bumper_m
                         * np.cos(loop.plant[2]))
    return Rollout(loop.g_min, loop.t_min, gap, np.asarray(loop.plant[3]), loop.lead_v)
