"""The brake guard: collision-avoidance braking under the learned planner (beyond the paper).

The planners are trained, and their barrier is written, against a leader predicted at constant
speed over the plan. A leader that keeps braking to a stop breaks that assumption: falsification
found avoidable collisions of the shipped ``safeil`` (and of the IDM and the analytic planner)
behind leaders braking at 2.8-6.5 m/s^2 (docs/falsification.md). Production cars answer this with
a separate layer under the ACC: the ACC brakes comfortably (ISO 15622 limits it to 3.5 m/s^2),
automatic emergency braking (AEB) brakes as hard as the situation needs. The guard is that layer.

At every decision it computes, from the radar's view (gap, leader speed) and the leader's
deceleration estimated from successive radar speeds, the smallest constant deceleration
``b_req`` [m/s^2] that keeps the ego ``standstill_gap_m`` behind a leader that keeps braking at
its current rate until it stops (:func:`required_decel`, exact kinematics). While ``b_req``
reaches ``activation_mps2`` and exceeds what the tracker asks for, the tracker's acceleration
command is replaced by ``-b_req`` (capped by the controller's strongest braking). Below the
activation level it never acts, so ordinary following stays the planner's.

Pure functions on floats or arrays (the loop's ``xp`` namespace, :mod:`.xp`); no SUMO.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from safeil_sumo.sim.xp import FloatOrArray, Namespace


@dataclass(frozen=True)
class BrakeGuard:
    """Settings of the brake guard."""

    # the guard acts once keeping the standstill gap needs at least this deceleration: above
    # comfortable braking, so that ordinary following is the planner's [m/s^2]
    activation_mps2: float = 3.0
    standstill_gap_m: float = 2.0  # bumper gap kept behind the stopped (or matched) leader [m]
    # the demand is computed once per decision and the brakes answer with a lag: the closing
    # speed times this is taken off the gap (decision period 0.1 s + brake lag 0.15 s, rounded up)
    reaction_s: float = 0.3  # [s]
    # low-pass time constant of the leader's acceleration estimate (radar speeds differenced
    # over a decision period) [s]
    leader_accel_tau_s: float = 0.3
    max_leader_decel_mps2: float = 10.0  # estimates beyond are clipped (a real car cannot) [m/s^2]
    # a radar range that jumps by more than this against the last one's prediction is a new
    # target (a cut-in, a leader lost): its acceleration estimate starts again at 0 [m]
    new_target_jump_m: float = 8.0

    def __post_init__(self) -> None:
        for name in ("activation_mps2", "standstill_gap_m", "reaction_s", "leader_accel_tau_s",
                     "max_leader_decel_mps2", "new_target_jump_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"BrakeGuard.{name} must be >= 0, got {getattr(self, name)}")


def when(enabled: bool) -> BrakeGuard | None:
    """The loop's ``brake_guard`` setting of an on/off choice: the default guard, or None."""
    return BrakeGuard() if enabled else None


def required_decel(gap: FloatOrArray, v_ego: FloatOrArray, v_lead: FloatOrArray,
                   b_lead: FloatOrArray, xp: Namespace) -> FloatOrArray:
    """Smallest constant ego deceleration [m/s^2] (>= 0) that keeps a positive ``gap`` [m] to a
    leader at ``v_lead`` [m/s] braking at ``b_lead`` [m/s^2] (>= 0) until it stops; the ego is at
    ``v_ego`` [m/s]. ``gap`` must be > 0 (the caller floors it).

    Two cases. (A) Closing while both move: the gap is smallest when the speeds match, at
    ``t* = 2 gap / dv`` under ``b = b_lead + dv^2 / (2 gap)``; valid when the leader still moves
    then (``v_lead - b_lead t* > 0``). (B) Otherwise the leader stops first, and the ego must
    stop within the leader's stopping point: ``b = v_ego^2 / (2 (gap + v_lead^2 / (2 b_lead)))``.
    A leader neither braking nor slower needs nothing.
    """
    where = xp.where
    dv = v_ego - v_lead
    closing = dv > 0.0
    dv_pos = xp.maximum(dv, 1e-9)  # finite on the branch not taken
    b_a = b_lead + dv_pos * dv_pos / (2.0 * gap)
    moving_at_match = xp.logical_or(b_lead <= 0.0, v_lead - b_lead * (2.0 * gap / dv_pos) > 0.0)
    b_lead_pos = xp.maximum(b_lead, 1e-9)
    b_b = where(b_lead > 0.0,
                v_ego * v_ego / (2.0 * (gap + v_lead * v_lead / (2.0 * b_lead_pos))), 0.0)
    return where(xp.logical_and(closing, moving_at_match), b_a, b_b)


def leader_accel(prev_accel: FloatOrArray, prev_v_lead: FloatOrArray, prev_gap: FloatOrArray,
                 prev_v_ego: FloatOrArray, v_lead: FloatOrArray, gap: FloatOrArray,
                 period_s: float, guard: BrakeGuard, xp: Namespace) -> FloatOrArray:
    """The leader's acceleration estimate [m/s^2] after a decision ``period_s`` [s]: the radar's
    speed difference, low-passed (``leader_accel_tau_s``); 0 at the first decision (NaN
    previous values) and for a new target (the range jumped by more than ``new_target_jump_m``
    against ``prev_gap + (prev_v_lead - prev_v_ego) period_s``)."""
    raw = (v_lead - prev_v_lead) / period_s
    alpha = period_s / (guard.leader_accel_tau_s + period_s)
    smoothed = prev_accel + alpha * (raw - prev_accel)
    predicted = prev_gap + (prev_v_lead - prev_v_ego) * period_s
    same = xp.abs(gap - predicted) <= guard.new_target_jump_m  # False on NaN: no history
    return xp.where(xp.logical_and(same, xp.isfinite(smoothed)), smoothed, 0.0)


def guard_decel(gap: FloatOrArray, v_ego: FloatOrArray, v_lead: FloatOrArray,
                a_lead: FloatOrArray, guard: BrakeGuard, xp: Namespace) -> FloatOrArray:
    """The guard's deceleration demand [m/s^2]: :func:`required_decel` on the gap less the
    standstill gap and the reaction distance, with the leader braking at ``-a_lead`` (clipped to
    ``[0, max_leader_decel_mps2]``); 0 below ``activation_mps2``."""
    closing = xp.maximum(v_ego - v_lead, 0.0)
    room = xp.maximum(gap - guard.standstill_gap_m - closing * guard.reaction_s, 0.05)
    b_lead = xp.clip(-a_lead, 0.0, guard.max_leader_decel_mps2)
    b = required_decel(room, v_ego, v_lead, b_lead, xp)
    return xp.where(b >= guard.activation_mps2, b, 0.0)


def no_history(n: int, xp: Namespace
               ) -> tuple[FloatOrArray, FloatOrArray, FloatOrArray, FloatOrArray]:
    """The guard's memory before the first decision: ``(a_lead, v_lead, gap, v_ego)``, 0 and
    NaNs (floats at N = 1, arrays ``(n,)`` else)."""
    return xp.full(n, 0.0), xp.full(n, math.nan), xp.full(n, math.nan), xp.full(n, math.nan)
