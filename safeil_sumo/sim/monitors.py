"""Safety monitors — pure functions on footprints, lane geometry and speeds (no SUMO).

The paper raises a flag when the ego leaves its lane or when TTC <= 1 s, and reports the
percentage of the path completed before the first flag. Collisions are flagged too (footprint
overlap, cross-checked in the runner with SUMO's collision list).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from safeil_sumo.sim.xp import FLOATS, BoolOrArray, FloatOrArray, Namespace

_TINY = 1e-300  # a divisor's floor on the untaken side of a branch

FLAG_NONE = ""
FLAG_LANE = "lane_departure"
FLAG_TTC = "ttc"
FLAG_COLLISION = "collision"


@dataclass(frozen=True)
class MonitorConfig:
    """Thresholds of the safety flags."""

    ttc_threshold_s: float = 1.0  # flag when TTC <= this [s] (the paper's value)
    lane_margin_m: float = 0.0  # tolerance beyond the lane boundary before flagging [m]

    def __post_init__(self) -> None:
        if self.ttc_threshold_s <= 0:
            raise ValueError("MonitorConfig.ttc_threshold_s must be > 0")


def time_to_collision(gap: FloatOrArray, v_ego: FloatOrArray, v_lead: FloatOrArray,
                      xp: Namespace = FLOATS) -> FloatOrArray:
    """TTC [s] = bumper gap [m] / closing speed [m/s]; ``inf`` when not closing.

    A gap <= 0 (overlap) gives 0. Floats, or arrays ``(N,)`` with ``xp=ARRAYS``.
    """
    closing = v_ego - v_lead
    ttc = xp.where(closing > 0.0, gap / xp.maximum(closing, _TINY), math.inf)
    return xp.where(gap <= 0.0, 0.0, ttc)


def lane_departure(min_offset: FloatOrArray, max_offset: FloatOrArray, lane_width: FloatOrArray,
                   margin: FloatOrArray = 0.0, xp: Namespace = FLOATS) -> BoolOrArray:
    """True when any part of the footprint lies outside ``±(lane_width/2 + margin)`` [m]."""
    half = 0.5 * lane_width + margin
    return (max_offset > half) | (min_offset < -half)  # flags: | is logical_or


def footprint_offset_range(front_d: FloatOrArray, heading_error: FloatOrArray, length: float,
                           width: float, xp: Namespace = FLOATS
                           ) -> tuple[FloatOrArray, FloatOrArray]:
    """Smallest and largest lateral offset [m] of the footprint's corners from the lane centre.

    ``front_d``: signed offset of the FRONT-bumper centre [m]; ``heading_error``: vehicle yaw
    minus lane heading [rad]. A corner at ``(x, y)`` in the vehicle frame (front-bumper origin)
    lies at ``front_d + x sin(e) + y cos(e)``; the corners are x in {0, -length}, y = +-width/2.
    Exact on a straight lane; on a 500 m arc the error over a 4.5 m body is ~2 cm (sagitta).
    """
    s, c = xp.sin(heading_error), xp.cos(heading_error)
    half_w = 0.5 * width * xp.abs(c)
    rear = -length * s
    lo = front_d + xp.minimum(0.0, rear) - half_w
    hi = front_d + xp.maximum(0.0, rear) + half_w
    return lo, hi


def event_starts(flags: np.ndarray) -> np.ndarray:
    """Indices where a run of flagged steps begins (an event), of a boolean series ``(n,)``."""
    flags = np.asarray(flags, dtype=bool)
    return np.flatnonzero(flags & ~np.concatenate([[False], flags[:-1]]))


def path_completed(s: FloatOrArray, start: FloatOrArray, end: FloatOrArray,
                   xp: Namespace = FLOATS) -> FloatOrArray:
    """Fraction [0, 1] of the test path ``[start, end]`` [m] covered at arc length ``s``."""
    return xp.clip((s - start) / (end - start), 0.0, 1.0)


@dataclass(frozen=True)
class FirstFlag:
    """The first safety flag of a run: ``reason`` ("" when none), time [s], path fraction."""

    reason: str
    time_s: float
    path_fraction: float


def first_flag(
    times: np.ndarray, fractions: np.ndarray, lane: np.ndarray, ttc_flag: np.ndarray,
    collision: np.ndarray,
) -> FirstFlag:
    """The earliest flag in per-step boolean logs ``(N,)``; ties name collision > ttc > lane."""
    any_flag = lane | ttc_flag | collision
    if not np.any(any_flag):
        return FirstFlag(FLAG_NONE, math.nan, float(fractions[-1]) if len(fractions) else 0.0)
    i = int(np.argmax(any_flag))
    reason = FLAG_COLLISION if collision[i] else FLAG_TTC if ttc_flag[i] else FLAG_LANE
    return FirstFlag(reason, float(times[i]), float(fractions[i]))
