"""The closed loop's own code for one decision period, shared by the tests of the closed-loop
bounds (tests/learn/test_loop_invariant.py) and of the barrier (tests/learn/test_loop_barrier.py)."""

from __future__ import annotations

import math

import numpy as np

from safeil_sumo.sim import brake_guard as grd
from safeil_sumo.sim import controller as ctl
from safeil_sumo.sim import vehicle as veh
from safeil_sumo.sim.xp import ARRAYS


def real_period(policy, g, v, vl, f, lane, time_gap, integral, leader_accel, sensing, a_est,
                 guard_on, a, parts):
    """One decision period of the real tracker, guard and plant for N states ``(N,)``; the
    leader moves by explicit Euler on its new speed (SUMO's). Returns the final
    ``(g, v, vl, f)`` and the smallest gap met."""
    vehicle = parts.vehicle
    n = len(g)
    width, offset, heading = lane
    feats = np.stack([width / 2 - offset, heading, 0 * g, -width / 2 - offset, heading, 0 * g,
                      v + sensing[0], vl + sensing[1], g + sensing[2]], axis=1)
    policy.set_style(time_gap_s=float(time_gap))
    cps = policy.plan(feats)
    yaw = -np.arctan(heading)
    d = vehicle.cog_to_front_bumper_m
    state = (-d * np.cos(yaw), offset - d * np.sin(yaw), yaw, v.copy(), 0 * g, 0 * g, 0 * g,
             f * vehicle.mass_kg)
    target = ctl.make_targets(cps, np.full(n, policy.horizon), 0 * g, offset + 0 * g, yaw)
    demand = grd.guard_decel(feats[:, 8], feats[:, 6], feats[:, 7], a_est, parts.guard, ARRAYS)
    plant = veh.Plant.of(vehicle, a.step_s)
    lead_x, lead_v, g_min = g.copy(), vl.copy(), g.copy()
    prev_error = np.full(n, math.nan)
    for j in range(a.steps_per_decision):
        steer, accel, integral, prev_error = ctl.track_values(
            target, np.full(n, j * a.step_s), *state[:6], vehicle, integral, prev_error,
            parts.controller, a.step_s, ARRAYS)
        if guard_on:
            override = (demand > 0.0) & (demand > -accel)
            accel = np.where(override, np.maximum(-demand, -vehicle.max_brake_decel_mps2), accel)
        throttle, brake = veh.pedals_from_accel_vx(accel, state[3], vehicle, ARRAYS)
        state = plant.step(state, steer, throttle, brake, ARRAYS)
        lead_v = np.clip(lead_v + leader_accel[:, j] * a.step_s, 0.0, a.speed_limit_mps)
        lead_x = lead_x + lead_v * a.step_s
        gap = lead_x - (state[0] + d * np.cos(state[2]))
        g_min = np.minimum(g_min, gap)
    return gap, state[3], lead_v, state[7] / vehicle.mass_kg, g_min


def real_run(policy, g, v, vl, f, time_gap, leader_accel, sensing, guard_on, a, parts,
             periods, lane_width=3.5):
    """``periods`` decisions of the real loop from N states ``(N,)`` on a straight lane (the
    plan re-made at every decision from the sensed state, the integral, the guard's leader
    estimate and the plant carried over); the leader accelerates at ``leader_accel`` [m/s^2]
    (a float) down to standstill, the sensing errors ``sensing (3,)`` [ego speed, leader speed,
    gap] are constant. Returns the smallest gap met, per state."""
    vehicle, guard = parts.vehicle, parts.guard
    n, dt, period = len(g), a.step_s, a.step_s * a.steps_per_decision
    d = vehicle.cog_to_front_bumper_m
    zero = np.zeros(n)
    state = (-d + zero, zero, zero, v.astype(float).copy(), zero, zero, zero,
             f * vehicle.mass_kg)
    lead_x, lead_v, g_min = g.astype(float).copy(), vl.astype(float).copy(), g.astype(float)
    integral, prev_error, memory = zero.copy(), np.full(n, math.nan), grd.no_history(n, ARRAYS)
    plant = veh.Plant.of(vehicle, dt)
    policy.set_style(time_gap_s=float(time_gap))
    for _ in range(periods):
        x0, y0, yaw = state[0] + d * np.cos(state[2]), state[1] + d * np.sin(state[2]), state[2]
        heading = -np.tan(yaw)
        v_s, vl_s, gap_s = state[3] + sensing[0], lead_v + sensing[1], lead_x - x0 + sensing[2]
        feats = np.stack([lane_width / 2 - y0 + zero, heading, zero, -lane_width / 2 - y0 + zero,
                          heading, zero, v_s, vl_s, gap_s], axis=1)
        target = ctl.make_targets(policy.plan(feats), np.full(n, policy.horizon), x0, y0, yaw)
        a_lead = grd.leader_accel(*memory, vl_s, gap_s, period, guard, ARRAYS)
        memory = (a_lead, vl_s, gap_s, v_s)
        demand = grd.guard_decel(gap_s, v_s, vl_s, a_lead, guard, ARRAYS)
        for j in range(a.steps_per_decision):
            steer, accel, integral, prev_error = ctl.track_values(
                target, np.full(n, j * dt), *state[:6], vehicle, integral, prev_error,
                parts.controller, dt, ARRAYS)
            if guard_on:
                override = (demand > 0.0) & (demand > -accel)
                accel = np.where(override, np.maximum(-demand, -vehicle.max_brake_decel_mps2),
                                 accel)
            throttle, brake = veh.pedals_from_accel_vx(accel, state[3], vehicle, ARRAYS)
            state = plant.step(state, steer, throttle, brake, ARRAYS)
            lead_v = np.clip(lead_v + leader_accel * dt, 0.0, a.speed_limit_mps)
            lead_x = lead_x + lead_v * dt
            g_min = np.minimum(g_min, lead_x - (state[0] + d * np.cos(state[2])))
    return g_min
