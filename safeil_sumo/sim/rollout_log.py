"""A run's per-step log and its summary: :class:`_Log` (the columns), :func:`finish` (the
:class:`.loop_types.Rollout` of a finished run), :func:`summarize`, :func:`drive_stats`.

Re-exported by :mod:`.runner`, where they were defined before.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim.loop_types import Rollout, Scenario

COMPLETED_REASONS = ("completed", "recording_end")  # end reasons of a completed run


def finish(scenario: Scenario, frame: pd.DataFrame, end_reason: str, error: str, wall_s: float,
           policy_name: str, leaders_met: int = 0, cut_ins: int = 0) -> Rollout:
    """The rollout of a finished run: its log and the summary (:func:`summarize`, distance
    and flag rates, leaders and cut-ins met with traffic)."""
    summary = summarize(scenario, frame, end_reason, error, wall_s, policy_name)
    summary |= drive_stats(frame, scenario.road.path_start_s)
    summary["leaders_met"] = (leaders_met if scenario.traffic is not None
                              else int(frame["leader_no"].notna().any()) if len(frame) else 0)
    summary["cut_ins_met"] = cut_ins if scenario.traffic is not None else 0
    summary["traffic"] = scenario.traffic.density if scenario.traffic is not None else ""
    return Rollout(frame, summary)


def summarize(
    scenario: Scenario, log: pd.DataFrame, end_reason: str, error: str, wall_s: float,
    policy_name: str,
) -> dict[str, Any]:
    """Flat per-scenario summary (what the sweeps and the paper's bar chart need)."""
    n = len(log)
    times = log["t"].to_numpy()
    flag = mon.first_flag(
        times, log["path_fraction"].to_numpy(), log["lane_departure"].to_numpy(bool),
        log["ttc_flag"].to_numpy(bool), log["collision"].to_numpy(bool),
    ) if n else mon.FirstFlag("", math.nan, 0.0)
    leader = scenario.leader
    return {
        "scenario": scenario.name,
        "policy": policy_name,
        "net": scenario.road.net_path.stem.removesuffix(".net"),
        "seed": scenario.seed,
        "leader_speed_mps": float(np.mean(leader.speeds)) if leader is not None else math.nan,
        "ego_speed0_mps": scenario.ego_speed_mps,
        "initial_gap_m": scenario.initial_gap_m,
        "end_reason": end_reason,
        "error": error,
        # a recorded leader's run that used up its recording without a flag is a completed test
        "completed": bool(end_reason in COMPLETED_REASONS and flag.reason == ""),
        "path_completed": flag.path_fraction if flag.reason else (
            float(log["path_fraction"].iloc[-1]) if n else 0.0),
        "flag": flag.reason,
        "flag_time_s": flag.time_s,
        "min_ttc_s": float(log["ttc"].min()) if n else math.nan,
        "min_gap_m": float(log["gap"].min()) if n else math.nan,
        "max_abs_lateral_offset_m": float(log["d"].abs().max()) if n else math.nan,
        "sim_time_s": float(times[-1]) if n else 0.0,
        # how long the brake guard overrode the tracker [s] (NaN: no guard in this run)
        "brake_guard_s": _guard_time(log),
        "steps": n,
        "wall_time_s": wall_s,
        "steps_per_s": n / wall_s if wall_s > 0 else math.nan,
    }


def _guard_time(log: pd.DataFrame) -> float:
    """Time [s] the brake guard braked in ``log`` (its steps with ``guard_decel > 0``); NaN
    when it did not run (a column of NaN) or the log has no such column."""
    if "guard_decel" not in log or len(log) == 0:
        return math.nan
    guard = log["guard_decel"].to_numpy()
    if np.isnan(guard).all():
        return math.nan
    dt = float(log["t"].iloc[0]) if len(log) == 1 else float(np.median(np.diff(log["t"])))
    return float(np.count_nonzero(guard > 0.0) * dt)


def drive_stats(log: pd.DataFrame, path_start_s: float) -> dict[str, float]:
    """Distance driven and flag events per 100 km by kind (an event = a run of flagged steps)."""
    n = len(log)
    km = max(float(log["s"].iloc[-1]) - path_start_s, 0.0) / 1000.0 if n else 0.0
    out: dict[str, float] = {"km_driven": km}
    for col, kind in (("ttc_flag", "ttc"), ("lane_departure", "lane_departure"),
                      ("collision", "collision")):
        events = len(mon.event_starts(log[col].to_numpy(bool)))
        out[f"{kind}_events"] = events
        out[f"{kind}_per_100km"] = 100.0 * events / km if km > 0 else math.nan
    return out


# the log columns a summary (summarize, drive_stats, leaders met) and a sweep's record (the
# leader-response metrics) read: a log of these columns only gives the same record
SUMMARY_COLUMNS = ("t", "v", "s", "d", "leader_v", "gap", "ttc", "lane_departure", "ttc_flag",
                   "collision", "path_fraction", "leader_no", "guard_decel")


class _Log:
    """The log's columns, and the log of rows ``(steps, columns)`` as a frame."""

    COLUMNS = (
        "t", "x", "y", "yaw", "v", "vy", "yaw_rate", "steer", "front_x", "front_y", "steer_cmd",
        "accel_cmd", "s", "d", "d_min", "d_max", "c0l", "c1l", "c2l", "c0r", "c1r", "c2r",
        "v_lead_sensed", "d_lead_sensed", "leader_x", "leader_y", "leader_v", "gap", "ttc",
        "lane_departure", "ttc_flag", "collision", "path_fraction",
        # the plan being tracked: made at plan_t [s] at the front-bumper pose plan_x, plan_y
        # [m], plan_yaw [rad]; its free control points cp{i}_x, cp{i}_y [m] in that pose's frame
        "plan_t", "plan_x", "plan_y", "plan_yaw",
        "cp1_x", "cp1_y", "cp2_x", "cp2_y", "cp3_x", "cp3_y",
        # which leader [-]: 0, 1, ... in the order met (traffic); 0 the scripted one; NaN none
        "leader_no",
        # the brake guard's deceleration [m/s^2] where it overrode the tracker's command, else
        # 0; NaN without a guard (LoopConfig.brake_guard=None) or for held/kinematic commands
        "guard_decel",
    )

    @classmethod
    def to_frame(cls, data: np.ndarray, columns: Sequence[str] | None = None) -> pd.DataFrame:
        """The log of rows ``(steps, len(columns))`` (default: all of COLUMNS)."""
        df = pd.DataFrame(data, columns=list(columns or cls.COLUMNS))
        for col in ("lane_departure", "ttc_flag", "collision"):
            if col in df:
                df[col] = df[col].astype(bool)
        return df
