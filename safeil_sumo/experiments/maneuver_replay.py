"""Human-likeness replay (paper IV-C/D): a recorded maneuver rebuilt in SUMO and driven closed-loop.

The digital twin of a maneuver left out of training:
- the road: the recorded ego lane (:mod:`safeil_sumo.roads.recorded_road`);
- the leader: driven by the RECORDED leader speed (``v_lead`` of the pipeline, else ``lead_v``,
  else ``v_x + d(lead_x)/dt``), placed at the recorded initial bumper gap on the ego lane, with
  the speed's slow drift from the recorded positions removed (``leader_drift_window_s``, see
  :func:`safeil_sumo.roads.recorded_road.drift_corrected_speed`): over a long maneuver the
  leader stays where it was recorded, not metres off;
- the ego: starts exactly at the recorded front-bumper position and speed, with the recorded
  heading relative to its lane (from the lane lines, :func:`recorded_heading`; the lateral
  offset is the recorded position's offset from the rebuilt lane centre, i.e.
  ``-(c0l + c0r) / 2`` up to the smoothing of the lane centre);
- the duration: the maneuver's.

The ``recorded`` pseudo-planner (:mod:`safeil_sumo.sim.recorded_ego`) drives the ego along the
human's own path: its error is the instrument's floor (docs/replay_instrument.md). The
``constant_speed`` pseudo-planner (:mod:`safeil_sumo.sim.constant_speed_ego`) keeps the initial
speed on the lane centre: the literature's naive baseline. Each policy
runs closed-loop; its state is compared with the human's at the recorded timestamps
(:mod:`safeil_sumo.experiments.metrics`): x, y in the local frame (origin at the recorded start,
x along the initial lane heading, as the paper plots them), along-lane ``s`` and lateral offset
``d`` on the ego lane, ``v_x`` and ``d_lead`` (bumper gap along the lane): RMSE and max error;
time headway, speed and lateral offset distributions: Wasserstein-1 and KS statistic.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.core.policy import Policy
from safeil_sumo.data.importers import MIN_GAP
from safeil_sumo.data.pipeline import body_outside_lines
from safeil_sumo.experiments import metrics as hm
from safeil_sumo.roads import recorded_road as rr
from safeil_sumo.roads.road import Road
from safeil_sumo.sim import monitors as mon
from safeil_sumo.sim.constant_speed_ego import ConstantSpeedPath
from safeil_sumo.sim.leaders import SpeedProfile
from safeil_sumo.sim.loop_types import LoopConfig, Rollout, Scenario
from safeil_sumo.sim.recorded_ego import RecordedPath
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.vehicle import VehicleParams

PAPER_SPEED_MPS = 115.0 / 3.6  # the paper's left-out maneuver: 10 s at 115 km/h
PAPER_DURATION_S = 11.0  # [s] the span of the paper's replay figure
PAPER_GAP_M = 58.6  # [m] mean human gap in the paper's replay (paper/figures/dlead_human_*.csv)
# the compared time series: (column, unit) — same names in the human and the policy tables
SERIES = (("x", "m"), ("y", "m"), ("s", "m"), ("d", "m"), ("v", "m/s"), ("gap", "m"))
DISTRIBUTIONS = (("headway", "s"), ("v", "m/s"), ("d", "m"))
REQUIRED = ("time", "x", "y", "yaw", "v_x", "left_c0", "right_c0", "lead_x")


class ReplayError(ValueError):
    """A maneuver that cannot be replayed (unknown id, no leader, too short, ...)."""


@dataclass(frozen=True)
class ReplayConfig:
    """How a maneuver is replayed."""

    road: rr.ReplayRoadConfig = field(default_factory=rr.ReplayRoadConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    seed: int = 0  # SUMO and sensor-noise seed (sensors are noise-free by default)
    # low-pass window of the leader-drift correction [s] (rr.drift_corrected_speed); 0: drive
    # the leader by its recorded speed alone
    leader_drift_window_s: float = 5.0
    # a replay's lane is rebuilt from the recording, accurate to a few cm (chords within
    # rr.REPLAY_SAGITTA_M, smoothing, heading noise): a body less than this over its line is
    # within that error, not a departure [m] (MonitorConfig.lane_margin_m)
    lane_margin_m: float = 0.05
    # when the recorded heading is believed (rr.plausible_heading): a GNSS heading glitch, or a
    # heading at standstill, would turn the replayed body (and the planners' start) across lines
    heading: rr.HeadingCheck = field(default_factory=rr.HeadingCheck)
    # the planners' preferred time gap [s], like an ACC's distance setting: the style input of a
    # style-conditioned checkpoint, the IDM's T (planner_registry.with_time_gap); planners
    # without one keep theirs. None: each planner's default. An adapted window
    # (window_replays.adapt_planners) sets its own.
    time_gap_s: float | None = None
    # with it, the planners' standstill distance [m]: the style is the line s0 + T v
    # (planner_registry.with_time_gap). None: none
    standstill_m: float | None = None

    def __post_init__(self) -> None:
        if self.time_gap_s is not None and not (0 < self.time_gap_s <= 10):
            raise ValueError(f"time gap must be in (0, 10] s, got {self.time_gap_s}")
        if self.standstill_m is not None and self.time_gap_s is None:
            raise ValueError("a standstill distance needs a time gap (the style is the line "
                             "s0 + T v)")


@dataclass(frozen=True)
class ReplayResult:
    """A replayed maneuver: the human trace, each policy's rollout and their comparison.

    ``human``: one row per recorded sample: ``t`` [s from the start], ``x, y`` [m, local frame],
    ``s, d`` [m, ego lane], ``v`` [m/s], ``gap`` [m], ``headway`` [s], ``leader_drift`` [m].
    ``compared[name]``: the policy's values of the same columns at the same ``t`` (NaN after an
    early end). ``metrics``: one row per policy.
    """

    maneuver_id: str
    road: Road
    frame: rr.LocalFrame
    scenario: Scenario
    human: pd.DataFrame
    rollouts: dict[str, Rollout]
    compared: dict[str, pd.DataFrame]
    metrics: pd.DataFrame
    info: dict


# ------------------------------------------------------------------------ maneuver selection


def maneuver_table(maneuvers: pd.DataFrame) -> pd.DataFrame:
    """Per ``maneuver_id``: start/end time [s], duration [s], mean speed [m/s], mean gap [m]."""
    g = maneuvers.groupby("maneuver_id", sort=True)
    out = pd.DataFrame({
        "t_start": g["time"].min(), "t_end": g["time"].max(),
        "speed_mps": g["v_x"].mean(), "gap_m": g["lead_x"].mean(), "samples": g.size(),
    })
    out["duration_s"] = out["t_end"] - out["t_start"]
    return out


def window(rows: pd.DataFrame, start_s: float, duration_s: float | None) -> pd.DataFrame:
    """Rows of one maneuver from ``start_s`` [s after its first sample] for ``duration_s`` [s]
    (None or 0: to its end)."""
    t = rows["time"].to_numpy(float)
    t0 = t[0] + start_s
    t1 = t0 + duration_s if duration_s else t[-1]
    sel = (t >= t0 - 1e-9) & (t <= t1 + 1e-9)
    return rows.loc[sel].reset_index(drop=True)


def auto_window(maneuvers: pd.DataFrame, duration_s: float = PAPER_DURATION_S,
                target_speed_mps: float = PAPER_SPEED_MPS, target_gap_m: float = PAPER_GAP_M,
                speed_scale_mps: float = 1.0, gap_scale_m: float = 5.0, step_s: float = 1.0
                ) -> tuple[str, float]:
    """The maneuver and start [s] of the ``duration_s`` window most like the paper's replay:
    smallest ``(dv / speed_scale)^2 + (dgap / gap_scale)^2`` of the window's mean speed and mean
    gap against 115 km/h and the paper's human gap (58.6 m). Windows start every ``step_s``;
    ties go to the first maneuver id and the earliest start. On congested NGSIM this picks a
    fast, open window.
    """
    best: tuple[float, str, float] | None = None
    for mid, rows in maneuvers.groupby("maneuver_id", sort=True):
        t = rows["time"].to_numpy(float)
        if t[-1] - t[0] < duration_s - 1e-9:
            continue
        # window means from cumulative trapezoid integrals
        cum = {}
        for col in ("v_x", "lead_x"):
            v = rows[col].to_numpy(float)
            cum[col] = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
        starts = np.arange(0.0, t[-1] - t[0] - duration_s + 1e-9, step_s)
        a, b = t[0] + starts, t[0] + starts + duration_s
        mean = {c: (np.interp(b, t, cum[c]) - np.interp(a, t, cum[c])) / duration_s for c in cum}
        score = ((mean["v_x"] - target_speed_mps) / speed_scale_mps) ** 2 \
            + ((mean["lead_x"] - target_gap_m) / gap_scale_m) ** 2
        k = int(np.argmin(score))
        if best is None or score[k] < best[0] - 1e-12:
            best = (float(score[k]), str(mid), float(starts[k]))
    if best is None:
        raise ReplayError(f"no maneuver lasts {duration_s:g} s or more")
    return best[1], best[2]


def select_maneuver(maneuvers: pd.DataFrame, which: str = "auto", start_s: float = 0.0,
                    duration_s: float | None = PAPER_DURATION_S) -> tuple[str, float, pd.DataFrame]:
    """``(maneuver_id, start_s, rows)`` for ``which`` = a maneuver id, ``"longest"`` or ``"auto"``
    (:func:`auto_window`; ``start_s`` is then chosen). Raises :class:`ReplayError` naming the
    available maneuvers for an unknown id."""
    if "maneuver_id" not in maneuvers.columns or len(maneuvers) == 0:
        raise ReplayError("no maneuvers (the drive has no car-following maneuver)")
    table = maneuver_table(maneuvers)
    if which == "auto":
        mid, start_s = auto_window(maneuvers, duration_s or PAPER_DURATION_S)
    elif which == "longest":
        mid = str(table["duration_s"].idxmax())
    elif which in table.index:
        mid = which
    else:
        ids = list(table.index)
        shown = ", ".join(ids[:30]) + (f", ... ({len(ids)} in all)" if len(ids) > 30 else "")
        raise ReplayError(f"unknown maneuver {which!r}; available: {shown}")
    rows = maneuvers[maneuvers["maneuver_id"] == mid]
    dur = float(table.loc[mid, "duration_s"])
    if not 0 <= start_s < dur:
        raise ReplayError(f"start {start_s:g} s is outside maneuver {mid!r} ({dur:.2f} s long)")
    out = window(rows.reset_index(drop=True), start_s, duration_s)
    if len(out) < 3:
        raise ReplayError(f"maneuver {mid!r} has fewer than 3 samples from {start_s:g} s")
    return str(mid), float(start_s), out


# ----------------------------------------------------------------------------------- replay


def _check_rows(rows: pd.DataFrame) -> pd.DataFrame:
    missing = [c for c in REQUIRED if c not in rows.columns]
    if missing:
        raise ReplayError(f"drive rows lack column(s) {', '.join(missing)}")
    rows = rows.sort_values("time", kind="stable").reset_index(drop=True)
    if len(rows) < 3:
        raise ReplayError("a replay needs at least 3 samples")
    if not np.all(np.isfinite(rows["lead_x"].to_numpy(float))):
        raise ReplayError("the maneuver has samples without a leader (lead_x NaN): not a "
                          "car-following maneuver; run the processing pipeline first")
    if float(rows["lead_x"].iloc[0]) <= 0:
        raise ReplayError(f"initial gap {rows['lead_x'].iloc[0]:.2f} m must be > 0")
    return rows


def human_trace(rows: pd.DataFrame, road: Road, frame: rr.LocalFrame,
                leader_drift_window_s: float = 5.0,
                vehicle: VehicleParams = VehicleParams()) -> pd.DataFrame:
    """The recorded human in the replay's terms (see :class:`ReplayResult`); ``leader_v`` is
    the speed the replay drives the leader by (``rr.drift_corrected_speed``), ``leader_drift``
    how far that leader ends up from the recorded one; ``ttc`` [s] and ``lane_departure`` are
    the closed loop's monitors on the recorded samples, lanes from the recorded lane lines (the
    car's size from ``vehicle``)."""
    t = rows["time"].to_numpy(float)
    xy = frame.points(rows["x"].to_numpy(float), rows["y"].to_numpy(float))
    # along the lane from the recorded start: on a closed course the nearest pass may be a lap's
    s, d = rr.recorded_stations(road.lanes[road.ego_lane].centre, xy, road.path_start_s)
    v = rows["v_x"].to_numpy(float)
    gap = rows["lead_x"].to_numpy(float)
    lead_v = rr.drift_corrected_speed(t, rr.leader_speed(rows), s + gap, leader_drift_window_s)
    # the closed loop's monitors on the recording itself, against its own lane lines
    departed = body_outside_lines(rows, vehicle.length_m, vehicle.width_m)
    ttc = [mon.time_to_collision(g, vi, vl) for g, vi, vl in zip(gap, v, lead_v, strict=True)]
    return pd.DataFrame({
        "t": t - t[0], "x": xy[:, 0], "y": xy[:, 1], "s": s, "d": d, "v": v, "gap": gap,
        "headway": hm.time_headway(gap, v), "leader_v": lead_v,
        "leader_drift": hm.leader_drift(t, gap, s, lead_v),
        "ttc": ttc, "lane_departure": departed,
        # the offset from the lane centre the recorded lines give; d - d_lines is the error of
        # the rebuilt lane (smoothing, chords)
        "d_lines": -0.5 * (rows["left_c0"].to_numpy(float) + rows["right_c0"].to_numpy(float)),
    })


def human_flag(human: pd.DataFrame, monitors: mon.MonitorConfig = mon.MonitorConfig()
               ) -> mon.FirstFlag:
    """The recording's own first flag (TTC <= threshold, the body over a recorded lane line, or
    contact: a bumper gap at the importers' floor, ``MIN_GAP``, where the recording measured
    that little or less) at the recorded samples: a replay flag the human also has is not the
    instrument's, and a policy's flag there may be one the recording left no room to avoid."""
    ttc_flag = human["ttc"].to_numpy(float) <= monitors.ttc_threshold_s
    contact = human["gap"].to_numpy(float) <= MIN_GAP
    return mon.first_flag(human["t"].to_numpy(float), np.zeros(len(human)),
                          human["lane_departure"].to_numpy(bool), ttc_flag, contact)


def recorded_heading(rows: pd.DataFrame, road: Road, frame: rr.LocalFrame
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The recorded ego's heading on the rebuilt road: ``(local yaw (N,) [rad], heading relative
    to the ego lane (N,) [rad])``.

    Relative to its lane the recording states it through its lane lines, ``-atan(c1)`` (mean of
    the left and right line), where they are given; elsewhere the recorded ``yaw`` minus the
    lane's heading. The local yaw is the rebuilt lane's heading at the recorded position
    (walked, :func:`rr.recorded_stations`) plus that. The lines, not the yaw, because the
    recording's own lane departures (:func:`human_flag`) are judged from them: the body then
    stands in the rebuilt lane as it stood between the recorded lines. For NGSIM, whose lines
    come from its yaw, both agree to round-off; for OpenACC (lines centred on the path,
    ``c1 = 0``) the GNSS heading differs from the smoothed lane by <= 0.016 rad on Vicolungo,
    and is noise where the car stands or the receiver has just reacquired (ZalaZone).
    """
    centre = road.lanes[road.ego_lane].centre
    xy = frame.points(rows["x"].to_numpy(float), rows["y"].to_numpy(float))
    s, _ = rr.recorded_stations(centre, xy, road.path_start_s)
    _, lane_yaw = centre.point_at(s)
    c1 = 0.5 * (rows["left_c1"].to_numpy(float) + rows["right_c1"].to_numpy(float)) \
        if {"left_c1", "right_c1"} <= set(rows.columns) else np.full(len(rows), np.nan)
    from_yaw = (frame.yaw(rows["yaw"].to_numpy(float)) - lane_yaw + math.pi) % (2 * math.pi) \
        - math.pi
    relative = np.where(np.isfinite(c1), -np.arctan(c1), from_yaw)
    return lane_yaw + relative, relative


def recorded_path(rows: pd.DataFrame, road: Road, frame: rr.LocalFrame) -> RecordedPath:
    """The human's own path in the replay frame: the ``recorded`` pseudo-planner (positions as
    recorded, heading relative to the ego lane :func:`recorded_heading`, turning with it)."""
    t = rows["time"].to_numpy(float)
    return RecordedPath(t - t[0], frame.points(rows["x"].to_numpy(float),
                                               rows["y"].to_numpy(float)),
                        recorded_heading(rows, road, frame)[1], rows["v_x"].to_numpy(float),
                        lane=road.lanes[road.ego_lane].centre, lane_start_s=road.path_start_s)


def replay_scenario(rows: pd.DataFrame, road: Road, frame: rr.LocalFrame, name: str,
                    seed: int = 0, leader_speed_mps: np.ndarray | None = None,
                    monitors: mon.MonitorConfig = mon.MonitorConfig()) -> Scenario:
    """The closed-loop scenario of the recorded maneuver on its rebuilt road; the leader drives
    ``leader_speed_mps`` (default: the recorded speed, ``rr.leader_speed``). The ego starts at
    the recorded position and the recorded heading relative to its lane
    (:func:`recorded_heading`)."""
    t = rows["time"].to_numpy(float)
    lead_v = rr.leader_speed(rows) if leader_speed_mps is None else leader_speed_mps
    leader = SpeedProfile(t - t[0], lead_v, f"recorded leader of {name}")
    centre = road.lanes[road.ego_lane].centre
    start = frame.points(rows["x"].iloc[0], rows["y"].iloc[0])
    _, d0 = (float(v[0]) for v in rr.recorded_stations(centre, start, road.path_start_s))
    heading = float(recorded_heading(rows.iloc[:1], road, frame)[1][0])
    return Scenario(
        name=name, road=road, leader=leader,
        ego_speed_mps=float(rows["v_x"].iloc[0]), initial_gap_m=float(rows["lead_x"].iloc[0]),
        seed=seed, ego_lateral_offset_m=float(d0), ego_heading_offset_rad=heading,
        max_time_s=float(t[-1] - t[0]), monitors=monitors,
    )


def policy_trace(log: pd.DataFrame, human: pd.DataFrame) -> pd.DataFrame:
    """A rollout's values at the human's timestamps; ``t = 0`` is the shared initial state."""
    first = human.iloc[0]
    t = np.r_[0.0, log["t"].to_numpy(float)]
    gap = log["gap"].to_numpy(float)
    cols = {
        "x": log["front_x"], "y": log["front_y"], "s": log["s"], "d": log["d"],
        "v": log["v"], "gap": np.where(np.isfinite(gap), gap, np.nan),
    }
    out = {"t": human["t"].to_numpy(float)}
    for name, values in cols.items():
        series = np.r_[float(first[name]), np.asarray(values, float)]
        out[name] = hm.sample_at(out["t"], t, series)
    out["headway"] = hm.time_headway(out["gap"], out["v"])
    return pd.DataFrame(out)


def compare(human: pd.DataFrame, policy: pd.DataFrame) -> dict:
    """Flat metrics of one policy against the human (keys ``rmse_<col>``, ``max_<col>``,
    ``w1_<col>``, ``ks_<col>``, ``coverage``), and the car-following literature's: the spacing
    RMSPE ``rmspe_gap`` [-, a fraction], the time-gap RMSE ``rmse_headway`` [s] and the mean
    time-gap error ``bias_headway`` [s] (policy - human: > 0 keeps longer gaps)."""
    row: dict = {}
    for col, _unit in SERIES:
        e = hm.series_error(human[col].to_numpy(), policy[col].to_numpy())
        row[f"rmse_{col}"] = e.rmse
        row[f"max_{col}"] = e.max_abs
    row["rmspe_gap"] = hm.rmspe(human["gap"].to_numpy(), policy["gap"].to_numpy())
    row["rmse_headway"] = hm.series_error(human["headway"].to_numpy(),
                                          policy["headway"].to_numpy()).rmse
    row["bias_headway"] = hm.mean_error(human["headway"].to_numpy(),
                                        policy["headway"].to_numpy())
    for col, _unit in DISTRIBUTIONS:
        dd = hm.distribution_distance(human[col].to_numpy(), policy[col].to_numpy())
        row[f"w1_{col}"] = dd.wasserstein
        row[f"ks_{col}"] = dd.ks
    n_ok = np.isfinite(policy["s"].to_numpy(float)).sum()
    row["coverage"] = float(n_ok / len(policy)) if len(policy) else 0.0
    return row


@dataclass(frozen=True)
class ReplayPrep:
    """A maneuver ready to be driven (:func:`prepare_replay`): its checked rows, rebuilt net,
    road and local frame, the human trace (:func:`human_trace`), the closed-loop scenario and
    the recording's own first flag (:func:`human_flag`)."""

    maneuver_id: str
    rows: pd.DataFrame
    net: Path
    road: Road
    frame: rr.LocalFrame
    human: pd.DataFrame
    scenario: Scenario
    human_flag: mon.FirstFlag


def prepare_replay(drive_rows: pd.DataFrame, out_dir: Path,
                   config: ReplayConfig = ReplayConfig(), maneuver_id: str | None = None
                   ) -> ReplayPrep:
    """Rebuild the maneuver in SUMO (net written to ``out_dir/net``) and set up its scenario
    and human trace; the first half of :func:`replay_maneuver`. The recorded ``yaw`` is first
    checked against the direction of travel (:func:`rr.plausible_heading`, ``config.heading``).

    Raises :class:`ReplayError` for unusable rows; SUMO/netconvert errors propagate.
    """
    rows = _check_rows(drive_rows)
    rows = rows.assign(yaw=rr.plausible_heading(
        rows["time"].to_numpy(float), rows["x"].to_numpy(float), rows["y"].to_numpy(float),
        rows["yaw"].to_numpy(float), config.heading))
    if maneuver_id is None:
        maneuver_id = str(rows["maneuver_id"].iloc[0]) if "maneuver_id" in rows else "maneuver"
    name = rr.safe_name(maneuver_id)
    net = rr.build_replay_net(rows, Path(out_dir) / "net", name, config.road,
                              meta={"maneuver_id": maneuver_id})
    road, frame = rr.load_replay_road(net)
    human = human_trace(rows, road, frame, config.leader_drift_window_s, config.vehicle)
    scenario = replay_scenario(rows, road, frame, name, config.seed,
                               human["leader_v"].to_numpy(float),
                               mon.MonitorConfig(lane_margin_m=config.lane_margin_m))
    return ReplayPrep(maneuver_id, rows, net, road, frame, human, scenario,
                      human_flag(human, scenario.monitors))


def constant_speed_path(prep: ReplayPrep) -> ConstantSpeedPath:
    """The ``constant_speed`` baseline of ``prep``'s replay: from the recorded start's place
    along the ego lane (``road.path_start_s``), on the lane centre, at the recorded initial
    speed."""
    road = prep.road
    return ConstantSpeedPath(road.lanes[road.ego_lane].centre, road.path_start_s,
                             prep.scenario.ego_speed_mps)


def replay_policy(prep: ReplayPrep, policy: Policy) -> Policy:
    """The planner that drives ``prep``'s replay: ``policy``, or for the kinematic
    pseudo-planners ``recorded`` the human's own path and ``constant_speed`` the initial speed
    held on the lane centre, in this replay's frame."""
    if isinstance(policy, RecordedPath):
        return recorded_path(prep.rows, prep.road, prep.frame)
    if isinstance(policy, ConstantSpeedPath):
        return constant_speed_path(prep)
    return policy


def compare_replay(prep: ReplayPrep, rollouts: dict[str, Rollout],
                   config: ReplayConfig = ReplayConfig()) -> ReplayResult:
    """Each policy's rollout against the human: the second half of :func:`replay_maneuver`
    (``rollouts``: label -> rollout of ``prep.scenario``, in the policies' order)."""
    rows, road, human, scenario, own = (prep.rows, prep.road, prep.human, prep.scenario,
                                        prep.human_flag)
    compared: dict[str, pd.DataFrame] = {}
    table = []
    for label, rollout in rollouts.items():
        trace = policy_trace(rollout.log, human)
        compared[label] = trace
        sm = rollout.summary
        table.append({"policy": label, **compare(human, trace),
                      "end_reason": sm["end_reason"], "flag": sm["flag"],
                      "flag_time_s": sm["flag_time_s"], "error": sm["error"],
                      "human_flag": own.reason, "human_flag_time_s": own.time_s})
    t = rows["time"].to_numpy(float)
    info = {
        "maneuver_id": prep.maneuver_id,
        "duration_s": float(t[-1] - t[0]),
        "samples": len(rows),
        "rate_hz": float((len(t) - 1) / (t[-1] - t[0])),
        "mean_speed_mps": float(rows["v_x"].mean()),
        "mean_gap_m": float(rows["lead_x"].mean()),
        "mean_leader_speed_mps": float(np.mean(rr.leader_speed(rows))),
        "lane_width_m": road.lanes[road.ego_lane].width,
        "initial_lateral_offset_m": scenario.ego_lateral_offset_m,
        "initial_lateral_offset_from_lines_m": float(
            -0.5 * (rows["left_c0"].iloc[0] + rows["right_c0"].iloc[0])),
        "initial_heading_offset_rad": scenario.ego_heading_offset_rad,
        "max_abs_leader_drift_m": float(np.nanmax(np.abs(human["leader_drift"]))),
        "max_abs_lane_rebuild_error_m": float(np.nanmax(np.abs(human["d"] - human["d_lines"]))),
        "max_abs_leader_drift_uncorrected_m": float(np.nanmax(np.abs(hm.leader_drift(
            t, human["gap"].to_numpy(), human["s"].to_numpy(), rr.leader_speed(rows))))),
        "road_shape_points": int(road.meta.get("shape_points", 0)),
        "net": str(prep.net),
        "config": asdict(config),
    }
    return ReplayResult(prep.maneuver_id, road, prep.frame, scenario, human, dict(rollouts),
                        compared, pd.DataFrame(table), info)


def replay_maneuver(drive_rows: pd.DataFrame, policies: dict[str, Policy], out_dir: Path,
                    config: ReplayConfig = ReplayConfig(), maneuver_id: str | None = None
                    ) -> ReplayResult:
    """Rebuild the maneuver in SUMO (net written to ``out_dir/net``), run every policy
    closed-loop and compare with the human. ``drive_rows``: one maneuver's rows (schema columns,
    sorted by time, all with a leader), e.g. from :func:`select_maneuver`.

    Raises :class:`ReplayError` for unusable rows; SUMO/netconvert errors propagate.
    """
    prep = prepare_replay(drive_rows, out_dir, config, maneuver_id)
    rollouts = {label: run_scenario(prep.scenario, replay_policy(prep, policy), config.loop,
                                    config.vehicle)
                for label, policy in policies.items()}
    return compare_replay(prep, rollouts, config)


# ------------------------------------------------------------------------------------ outputs


def plot_replay(result: ReplayResult, path: Path) -> None:
    """The paper's figure: x, y, v_x and d_lead over time; human dashed, policies solid, the
    first safety flag of a policy marked by a vertical dotted line."""
    panels = (("x", "x [m]"), ("y", "y [m]"), ("v", "v_x [m/s]"), ("gap", "d_lead [m]"))
    fig, axes = plt.subplots(4, 1, figsize=(8, 10), sharex=True)
    h = result.human
    for ax, (col, label) in zip(axes, panels, strict=True):
        ax.plot(h["t"], h[col], "k--", lw=1.4, label="human")
        for i, (name, rollout) in enumerate(result.rollouts.items()):
            color = f"C{i % 10}"
            log = rollout.log
            series = {"x": log["front_x"], "y": log["front_y"], "v": log["v"],
                      "gap": log["gap"].where(np.isfinite(log["gap"]))}[col]
            ax.plot(log["t"], series, color=color, lw=1.2, label=name)
            ft = rollout.summary["flag_time_s"]
            if rollout.summary["flag"] and math.isfinite(ft):
                ax.axvline(ft, color=color, ls=":", lw=1.0)
                if col == "x":
                    ax.annotate(f"{name}: {rollout.summary['flag']}", (ft, 0.05),
                                xycoords=("data", "axes fraction"), color=color, fontsize=7,
                                rotation=90, va="bottom", ha="right")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    half = 0.5 * result.road.lanes[result.road.ego_lane].width
    axes[1].set_title("y: lateral in the local frame (lane centre at the start: y = 0 +- "
                      f"{half:.2f} m)", fontsize=8)
    axes[0].legend(fontsize=8, loc="upper left")
    axes[-1].set_xlabel("time [s]")
    info = result.info
    fig.suptitle(f"Human-like performance: replay of {result.maneuver_id} "
                 f"({info['duration_s']:.1f} s, {3.6 * info['mean_speed_mps']:.0f} km/h)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_replay(result: ReplayResult, folder: Path, manifest_extra: dict | None = None) -> None:
    """``metrics.csv/json``, ``steps.parquet`` (per-step logs, ``policy`` column),
    ``human.parquet``, ``compared.parquet`` (policies at the human timestamps), ``replay.png``,
    ``manifest.json`` into ``folder`` (the net is already in ``folder/net`` when the replay ran
    there)."""
    from safeil_sumo.core.atomic import atomic_path
    from safeil_sumo.experiments import outputs

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "metrics.csv") as tmp:
        result.metrics.to_csv(tmp, index=False)
    outputs.write_json(folder / "metrics.json", {
        "maneuver": {k: v for k, v in result.info.items() if k != "config"},
        "policies": result.metrics.to_dict(orient="records"),
    })
    logs = [r.log.assign(policy=name) for name, r in result.rollouts.items()]
    if logs:
        with atomic_path(folder / "steps.parquet") as tmp:
            pd.concat(logs, ignore_index=True).to_parquet(tmp, index=False)
        with atomic_path(folder / "compared.parquet") as tmp:
            pd.concat([c.assign(policy=name) for name, c in result.compared.items()],
                      ignore_index=True).to_parquet(tmp, index=False)
    with atomic_path(folder / "human.parquet") as tmp:
        result.human.to_parquet(tmp, index=False)
    plot_replay(result, folder / "replay.png")
    config = {"maneuver_id": result.maneuver_id, **result.info["config"],
              "summaries": [r.summary for r in result.rollouts.values()],
              **(manifest_extra or {})}
    outputs.write_json(folder / "manifest.json", outputs.manifest(config, [result.scenario.seed]))


def format_metrics(metrics: pd.DataFrame) -> str:
    """The table printed by the CLI: RMSE / max per series, W1 / KS per distribution."""
    cols = ["policy"]
    out = pd.DataFrame({"policy": metrics["policy"]})
    for col, unit in SERIES:
        name = {"v": "v_x", "gap": "d_lead"}.get(col, col)
        out[f"{name} rmse/max [{unit}]"] = [
            f"{a:.2f}/{b:.2f}" for a, b in zip(metrics[f"rmse_{col}"], metrics[f"max_{col}"],
                                               strict=True)]
        cols.append(f"{name} rmse/max [{unit}]")
    for col, unit in DISTRIBUTIONS:
        name = {"v": "speed", "d": "lateral"}.get(col, col)
        out[f"{name} W1[{unit}]/KS"] = [
            f"{a:.2f}/{b:.2f}" for a, b in zip(metrics[f"w1_{col}"], metrics[f"ks_{col}"],
                                               strict=True)]
    out["flag"] = [f"{f}@{t:.1f}s" if f else "-" for f, t in
                   zip(metrics["flag"], metrics["flag_time_s"], strict=True)]
    out["end"] = metrics["end_reason"]
    if "human_flag" in metrics:  # the recording's own flag (the same for every policy)
        out["human flag"] = [f"{f}@{t:.1f}s" if f else "-" for f, t in
                             zip(metrics["human_flag"], metrics["human_flag_time_s"],
                                 strict=True)]
    return out.to_string(index=False)
