"""Gap-regulation probe: step responses of a planner's gap regulation, closed loop in SUMO.

    python -m safeil_sumo.gap_probe --policy safeil idm analytic [--speeds-mps 15 25 35]

Four step kinds at each speed v (the ego starts at v behind a leader at v, on n74's direction A
from km :data:`STRETCH_KM`, right lane, no traffic; the sweep engine's scripted leaders):

- ``pull_away``: ego and leader at v, gap ``START_TIME_GAP_S * v``; the planner settles for
  :data:`SETTLE_S`, then the leader speeds up by :data:`LEADER_STEP_MPS` at
  :data:`LEADER_RATE_MPS2` (a ramp of 3 s; the step time is the ramp's start);
- ``slow_down``: the same, the leader slowing by :data:`LEADER_STEP_MPS`;
- ``far``: the ego starts :data:`FAR_GAP_M` behind the leader (bumper gap), step at t = 0;
- ``close``: the ego starts at ``max(CLOSE_MIN_GAP_M, CLOSE_TIME_GAP_S * v - CLOSE_BELOW_M)``
  (10 m closer than a 1 s time gap, never under 5 m: 5, 15, 25 m at 15, 25, 35 m/s), step at
  t = 0. The same start for every planner, so their responses compare directly (a planner's own
  equilibrium is not known before it is measured).

Each response runs :data:`AFTER_STEP_S` after its step. Metrics of a response (pure functions on
the arrays ``t``, ``gap``, ``v`` of the log; everything after the step time ``t_step``):

- *final gap* and *equilibrium time gap*: the means of ``gap`` and ``gap / v`` over the last
  :data:`FINAL_WINDOW_S` of the run;
- *settling time*: from ``t_step`` to the first sample after which ``|gap - final|`` stays
  within :data:`BAND` (10 %) of the final gap to the end; NaN when the last sample is outside;
  *settled*: the run reached its full length and the gap stayed in the band for at least
  :data:`HOLD_S` at the end;
- *rise time*: from the first time the gap covers 10 % of its change (final gap minus the gap
  at ``t_step``) to the first time it covers 90 % (linear interpolation between samples); NaN
  for a change below :data:`MIN_CHANGE_M`;
- *overshoot*: how far [m] the gap went past the final gap in the direction of its change, and
  the *minimum time gap* and *minimum gap* after the step (the overshoot that matters for
  safety);
- *drift*: the gap change over the last :data:`FINAL_WINDOW_S`.

The humans' own equilibrium time gaps come from the processed maneuvers (OpenACC Vicolungo's
human day and NGSIM I-80, the pipeline at 10 Hz): *steady following* samples, with
``|dv_x/dt| <`` :data:`HUMAN_MAX_ACCEL_MPS2` (Savitzky-Golay derivative over the pipeline's
1 s window) and ``|v_x - v_lead| <`` :data:`HUMAN_MAX_DV_MPS`, in bands of ±
:data:`HUMAN_BAND_MPS` around each probe speed: the 5th, 25th, 50th and 75th percentile of
``lead_x / v_x``, with the numbers of samples, maneuvers and drivers behind them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.experiments.suite import MIN_SPEED_TIME_GAP
from safeil_sumo.experiments.sweep_executor import run_task
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
from safeil_sumo.sim.sensors import SensorConfig

KINDS = ("pull_away", "slow_down", "far", "close")
SPEEDS_MPS = (15.0, 25.0, 35.0)
NET = "n74"
STRETCH_KM = (1.0, 8.0)  # [km] n74 direction A: 7 km, long enough for 150 s at 38 m/s
LEADER_STEP_MPS = 3.0  # [m/s] the leader's speed change of pull_away / slow_down
LEADER_RATE_MPS2 = 1.0  # [m/s^2] how fast the leader changes its speed (a ramp, not a jump)
SETTLE_S = 60.0  # [s] pull_away / slow_down: constant leader before the step
AFTER_STEP_S = 90.0  # [s] run length after the step
START_TIME_GAP_S = 1.5  # [s] pull_away / slow_down: initial gap = this x v
FAR_GAP_M = 100.0  # [m] far: initial bumper gap
CLOSE_TIME_GAP_S = 1.0  # [s] close: initial gap = max(CLOSE_MIN_GAP_M, this x v - CLOSE_BELOW_M)
CLOSE_BELOW_M = 10.0  # [m]
CLOSE_MIN_GAP_M = 5.0  # [m]
FINAL_WINDOW_S = 15.0  # [s] final gap, equilibrium time gap and drift over the run's last
BAND = 0.10  # [-] settling band: this fraction of the final gap
HOLD_S = 30.0  # [s] settled: inside the band for at least this long at the end of the run
MIN_CHANGE_M = 1.0  # [m] rise time and overshoot need a gap change at least this large
SERIES_RATE_HZ = 2.0  # [Hz] the time series kept per run (for the plot)
RADAR_RANGE_M = SensorConfig().radar_range_m  # [m] beyond it the planner sees a free road
METRIC_COLUMNS = ("eq_time_gap_s", "final_gap_m", "final_speed_mps", "min_time_gap_s",
                  "min_gap_m", "max_gap_m", "settling_time_s", "settled", "rise_time_s",
                  "overshoot_m", "drift_m", "gap_at_step_m", "time_gap_at_step_s",
                  "step_time_s", "beyond_radar")
KIND_BASE = {kind: 10_000 * (k + 1) for k, kind in enumerate(KINDS)}  # task index = base + 100 v

# issue 20's targets, for the CSV's target_* columns (measured, never tuned to)
TARGET_MIN_TIME_GAP_S = 0.8  # [s] no response dips below this (nor below the humans' p05)
TARGET_SETTLING_S = 45.0  # [s] each response settles within the band inside this
START_TOLERANCE_S = 0.005  # [s] a close start's own time gap counts as reached below this

HUMAN_SOURCES = ("openacc", "ngsim")
HUMAN_BAND_MPS = 3.0  # [m/s] speed band half-width around each probe speed
HUMAN_MAX_ACCEL_MPS2 = 0.3  # [m/s^2] steady following: |ego acceleration| below
HUMAN_MAX_DV_MPS = 0.5  # [m/s] steady following: |v - v_lead| below
HUMAN_QUANTILES = (0.05, 0.25, 0.5, 0.75)
HUMANS = "humans"


# ------------------------------------------------------------------------- the step responses


def initial_gap_m(kind: str, speed_mps: float) -> float:
    """The bumper gap [m] a step of ``kind`` starts from at ``speed_mps`` (see the module doc)."""
    if kind in ("pull_away", "slow_down"):
        return START_TIME_GAP_S * speed_mps
    if kind == "far":
        return FAR_GAP_M
    if kind == "close":
        return max(CLOSE_MIN_GAP_M, CLOSE_TIME_GAP_S * speed_mps - CLOSE_BELOW_M)
    raise ValueError(f"unknown step kind {kind!r}; kinds: {', '.join(KINDS)}")


def probe_scenario(kind: str, speed_mps: float, seed: int = 0, settle_s: float = SETTLE_S,
                   after_s: float = AFTER_STEP_S) -> ScenarioSpec:
    """The scenario of one step response (its index encodes kind and speed)."""
    gap = initial_gap_m(kind, speed_mps)
    if not 0 < speed_mps < 100:
        raise ValueError(f"probe speed must be in (0, 100) m/s, got {speed_mps}")
    common = {"net": NET, "from_km": STRETCH_KM[0], "to_km": STRETCH_KM[1],
              "index": KIND_BASE[kind] + round(100 * speed_mps), "master_seed": seed,
              "leader_speed_range_mps": (speed_mps, speed_mps), "ego_speed_mps": speed_mps,
              "initial_gap_m": gap}
    if kind in ("pull_away", "slow_down"):
        target = speed_mps + (LEADER_STEP_MPS if kind == "pull_away" else -LEADER_STEP_MPS)
        if target < 0:
            raise ValueError(f"slow_down at {speed_mps:g} m/s would need a negative leader "
                             "speed: use speeds above 3 m/s")
        return ScenarioSpec(leader_kind="accelerating" if kind == "pull_away" else "braking",
                            brake_time_s=settle_s, brake_decel_mps2=LEADER_RATE_MPS2,
                            brake_to_mps=target, max_time_s=settle_s + after_s, **common)
    return ScenarioSpec(max_time_s=after_s, **common)


def probe_task(policy: str, kind: str, speed_mps: float, seed: int = 0,
               settle_s: float = SETTLE_S, after_s: float = AFTER_STEP_S) -> Task:
    """The sweep task of one step response: its scenario driven by ``policy``, the loop as
    shipped."""
    return Task(probe_scenario(kind, speed_mps, seed, settle_s, after_s), PlannerRef(policy))


def kind_of(index: int) -> str:
    """The step kind of a probe task index."""
    return KINDS[index // 10_000 - 1]


def step_time_s(spec: ScenarioSpec) -> float:
    """When the step of a probe task happens [s]: the leader's speed change, else the start."""
    return spec.brake_time_s if spec.leader_kind in ("accelerating", "braking") else 0.0


def leader_distance_m(spec: ScenarioSpec) -> float:
    """How far [m] the leader's front bumper gets from the ego's start over the run: its
    initial gap plus a car length plus the distance its speed profile drives."""
    from safeil_sumo.scenarios.spec import leader_profile
    from safeil_sumo.sim.vehicle import VehicleParams

    duration = spec.max_time_s or 0.0
    t = np.linspace(0.0, duration, max(int(duration * 10), 1) + 1)
    v = leader_profile(spec, spec.leader_speed_range_mps[0]).speed_at(t)
    driven = float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)))
    return spec.gap_range_m[1] + VehicleParams.length_m + driven


def check_fits(spec: ScenarioSpec, margin_m: float = 200.0) -> None:
    """Raise ValueError when the leader would leave the probe's stretch before the run ends."""
    room = 1000.0 * (STRETCH_KM[1] - STRETCH_KM[0])
    need = leader_distance_m(spec) + margin_m
    if need > room:
        raise ValueError(f"{kind_of(spec.index)} at {spec.ego_speed_mps:g} m/s: the leader "
                         f"would drive {need / 1000:.1f} km (with {margin_m:g} m margin), beyond "
                         f"the probe's {room / 1000:g} km n74 stretch: use lower speeds")


# ------------------------------------------------------------------------------ pure metrics


def time_gap(gap: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``gap / v`` [s]; NaN where the ego is slower than MIN_SPEED_TIME_GAP (undefined)."""
    gap, v = np.asarray(gap, float), np.asarray(v, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(v >= MIN_SPEED_TIME_GAP, gap / v, np.nan)


def window_mean(t: np.ndarray, y: np.ndarray, window_s: float) -> float:
    """Mean of the finite ``y (N,)`` over the last ``window_s`` [s] of ``t (N,)``."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    keep = (t >= t[-1] - window_s - 1e-9) & np.isfinite(y)
    return float(np.mean(y[keep])) if keep.any() else math.nan


def settling_time(t: np.ndarray, y: np.ndarray, t_step: float, final: float,
                  band: float = BAND) -> float:
    """Time [s] from ``t_step`` until ``y`` enters ``final ± band |final|`` for good (the first
    sample after the last one outside); 0 if it never leaves, NaN if the last sample is out."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    after = t >= t_step - 1e-9
    ta, ya = t[after], y[after]
    if not len(ta) or not math.isfinite(final):
        return math.nan
    with np.errstate(invalid="ignore"):
        outside = ~(np.abs(ya - final) <= band * abs(final))  # NaN counts as outside
    if outside[-1]:
        return math.nan
    if not outside.any():
        return 0.0
    last_out = int(np.flatnonzero(outside)[-1])
    return float(ta[last_out + 1] - t_step)


def _first_crossing(t: np.ndarray, z: np.ndarray, level: float) -> float:
    """First time ``z`` reaches ``level`` from below, interpolated between samples; NaN never."""
    hit = np.flatnonzero(z >= level)
    if not len(hit):
        return math.nan
    k = int(hit[0])
    if k == 0:
        return float(t[0])
    z0, z1 = z[k - 1], z[k]
    return float(t[k - 1] + (level - z0) / (z1 - z0) * (t[k] - t[k - 1]))


def rise_time(t: np.ndarray, y: np.ndarray, t_step: float, final: float, low: float = 0.1,
              high: float = 0.9, min_change: float = MIN_CHANGE_M) -> float:
    """Time [s] ``y`` takes from ``low`` to ``high`` of its change ``final - y(t_step)``, first
    crossings after ``t_step``; NaN for a change below ``min_change`` or a level never reached."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    after = t >= t_step - 1e-9
    ta, ya = t[after], y[after]
    if not len(ta) or not math.isfinite(final):
        return math.nan
    change = final - ya[0]
    if not abs(change) >= min_change:
        return math.nan
    z = (ya - ya[0]) / change  # 0 at the step, 1 at the final value, whichever the direction
    return _first_crossing(ta, z, high) - _first_crossing(ta, z, low)


def overshoot(t: np.ndarray, y: np.ndarray, t_step: float, final: float,
              min_change: float = MIN_CHANGE_M) -> float:
    """How far ``y`` went past ``final`` in the direction of its change after ``t_step`` (>= 0,
    the unit of ``y``); NaN for a change below ``min_change``."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    after = t >= t_step - 1e-9
    ya = y[after]
    if not len(ya) or not math.isfinite(final):
        return math.nan
    change = final - ya[0]
    if not abs(change) >= min_change:
        return math.nan
    return float(max(0.0, np.nanmax(np.sign(change) * (ya - final))))


def drift(t: np.ndarray, y: np.ndarray, window_s: float = FINAL_WINDOW_S) -> float:
    """Change of ``y`` over the last ``window_s`` [s]: ``y(end) - y(end - window_s)``."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    return float(y[-1] - np.interp(t[-1] - window_s, t, y))


def response_metrics(t: np.ndarray, gap: np.ndarray, v: np.ndarray, t_step: float,
                     window_s: float = FINAL_WINDOW_S, band: float = BAND,
                     hold_s: float = HOLD_S) -> dict:
    """Every metric of one step response from ``t, gap, v (N,)`` [s, m, m/s] (module doc)."""
    t, gap, v = np.asarray(t, float), np.asarray(gap, float), np.asarray(v, float)
    tg = time_gap(gap, v)
    after = t >= t_step - 1e-9
    if not after.any():  # the run ended before its step (e.g. off the road): no response
        return {"step_time_s": float(t_step), "settled": False} | {
            k: math.nan for k in METRIC_COLUMNS if k not in ("step_time_s", "settled")}
    final = window_mean(t, gap, window_s)
    settle = settling_time(t, gap, t_step, final, band)
    return {
        "step_time_s": float(t_step),
        "gap_at_step_m": float(np.interp(t_step, t, gap)),
        "time_gap_at_step_s": float(np.interp(t_step, t, tg)),
        "final_gap_m": final,
        "final_speed_mps": window_mean(t, v, window_s),
        "eq_time_gap_s": window_mean(t, tg, window_s),
        "settling_time_s": settle,
        "settled": bool(math.isfinite(settle) and t[-1] - t_step - settle >= hold_s - 1e-9),
        "rise_time_s": rise_time(t, gap, t_step, final),
        "overshoot_m": overshoot(t, gap, t_step, final),
        "min_time_gap_s": float(np.nanmin(tg[after])) if np.isfinite(tg[after]).any()
        else math.nan,
        "min_gap_m": float(np.min(gap[after])),
        "max_gap_m": float(np.max(gap[after])),
        "drift_m": drift(t, gap, window_s),
        # the radar sees no leader beyond its range: the planner then drives a free road
        "beyond_radar": bool(np.max(gap[after]) > RADAR_RANGE_M),
    }


# ------------------------------------------------------------------------------- the runs


def probe_extras(task: Task, rollout) -> dict:
    """What a probe task keeps of its log: the response metrics and the series at
    :data:`SERIES_RATE_HZ` (``series_t``, ``series_gap``, ``series_v``, ``series_leader_v``)."""
    log = rollout.log
    if len(log) < 2:
        return {"kind": kind_of(task.scenario.index)}
    t, gap, v = (log[c].to_numpy(float) for c in ("t", "gap", "v"))
    metrics = response_metrics(t, gap, v, step_time_s(task.scenario))
    # a run that ended early (collision, off the road) did not settle, whatever its tail did
    ran_out = rollout.summary.get("end_reason") == "timeout"
    metrics["settled"] = bool(metrics["settled"] and ran_out)
    stride = max(round(1.0 / (SERIES_RATE_HZ * float(t[1] - t[0]))), 1)
    rows = log.iloc[stride - 1::stride]
    series = {f"series_{name}": np.round(rows[col].to_numpy(float), 3).tolist()
              for name, col in (("t", "t"), ("gap", "gap"), ("v", "v"),
                                ("leader_v", "leader_v"))}
    return {"kind": kind_of(task.scenario.index), **metrics, **series}


run_probe_task = partial(run_task, extras=probe_extras)


def run_step(policy: str, kind: str, speed_mps: float, seed: int = 0,
             settle_s: float = SETTLE_S, after_s: float = AFTER_STEP_S) -> dict:
    """One step response closed loop in libsumo: the sweep record (summary, ``status``) with the
    response metrics and series of :func:`probe_extras`."""
    task = probe_task(policy, kind, speed_mps, seed, settle_s, after_s)
    check_fits(task.scenario)
    return run_probe_task(task)


def probe_tasks(policies: Sequence[str], speeds: Sequence[float] = SPEEDS_MPS,
                kinds: Sequence[str] = KINDS, seed: int = 0) -> list[Task]:
    """Every policy x speed x kind (checked to fit the stretch)."""
    tasks = [probe_task(p, k, s, seed) for p in policies for s in speeds for k in kinds]
    for task in tasks:
        check_fits(task.scenario)
    return tasks


# ------------------------------------------------------------------------------- the humans


def steady_following(rows: pd.DataFrame, max_accel: float = HUMAN_MAX_ACCEL_MPS2,
                     max_dv: float = HUMAN_MAX_DV_MPS) -> np.ndarray:
    """``(N,)`` True at the steady-following samples of the pipeline's maneuver rows (columns
    ``maneuver_id, time, v_x, v_lead, lead_x``; rows of a maneuver contiguous, in time order):
    ``|dv_x/dt| < max_accel`` [m/s^2] (Savitzky-Golay over the pipeline's smoothing window,
    per maneuver) and ``|v_x - v_lead| < max_dv`` [m/s], with a leader ahead."""
    from safeil_sumo.data.pipeline import PipelineConfig, _per_segment_savgol

    if not len(rows):
        return np.zeros(0, dtype=bool)
    man = rows["maneuver_id"].to_numpy()
    seg = np.cumsum(np.r_[True, man[1:] != man[:-1]]) - 1
    t, v = rows["time"].to_numpy(float), rows["v_x"].to_numpy(float)
    accel = _per_segment_savgol(v, seg, PipelineConfig().smooth_window, t, 1)
    dv = v - rows["v_lead"].to_numpy(float)
    gap = rows["lead_x"].to_numpy(float)
    with np.errstate(invalid="ignore"):
        return (np.abs(accel) < max_accel) & (np.abs(dv) < max_dv) & (gap > 0)


def human_time_gap_bands(rows: pd.DataFrame, speeds: Sequence[float] = SPEEDS_MPS,
                         band_mps: float = HUMAN_BAND_MPS,
                         max_accel: float = HUMAN_MAX_ACCEL_MPS2,
                         max_dv: float = HUMAN_MAX_DV_MPS) -> pd.DataFrame:
    """Per speed band ``[s - band_mps, s + band_mps]``: the humans' time-gap percentiles in steady
    following (:func:`steady_following`) and the samples, maneuvers and drivers behind them.
    ``rows`` also needs a ``driver`` column."""
    keep = steady_following(rows, max_accel, max_dv)
    v = rows["v_x"].to_numpy(float)
    tg = time_gap(rows["lead_x"].to_numpy(float), v)
    out = []
    for s in speeds:
        sel = keep & (np.abs(v - s) <= band_mps) & np.isfinite(tg)
        row = {"policy": HUMANS, "kind": "steady_following", "speed_mps": float(s),
               "samples": int(sel.sum()),
               "maneuvers": int(rows["maneuver_id"][sel].nunique()),
               "drivers": int(rows["driver"][sel].nunique())}
        for q in HUMAN_QUANTILES:
            row[f"human_p{round(100 * q):02d}_s"] = (float(np.quantile(tg[sel], q))
                                                     if sel.any() else math.nan)
        out.append(row)
    return pd.DataFrame(out)


def load_human_rows(data_dir: Path, sources: Sequence[str] = HUMAN_SOURCES) -> pd.DataFrame:
    """The processed maneuvers (pipeline at 10 Hz) of the human sources, with columns ``source``
    and ``driver`` (:func:`safeil_sumo.data.sources.driver_of`)."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import driver_of, load_source

    frames = []
    for source in sources:
        rows, _ = process_drive(load_source(source, Path(data_dir)), PipelineConfig(rate_hz=10.0))
        drivers = {m: driver_of(source, m, Path(data_dir)) for m in rows["maneuver_id"].unique()}
        frames.append(rows.assign(source=source, driver=rows["maneuver_id"].map(drivers)))
    return pd.concat(frames, ignore_index=True)


# ------------------------------------------------------------------------------- the table


SUMMARY_COLUMNS = ("end_reason", "flag", "flag_time_s", "min_ttc_s", "ttc_events",
                   "lane_departure_events", "collision_events", "status", "error")


def table(records: pd.DataFrame, humans: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per policy x speed x kind (the sweep records with :func:`probe_extras`), then
    the ``humans`` rows; each planner row carries its speed band's human percentiles and the
    issue's targets as ``target_*`` booleans (NaN without human data)."""
    r = records.copy()
    r["speed_mps"] = r["leader_speed_low_mps"].astype(float)  # a spec field: failed runs too
    r["kind"] = r["index"].map(kind_of)
    r["collision"] = r["end_reason"].eq("collision") | r.get(
        "resp_collision", pd.Series(False, index=r.index)).fillna(False).astype(bool)
    r["run_min_time_gap_s"] = r.get("resp_min_time_gap_s", math.nan)  # over the whole run
    for col in (*METRIC_COLUMNS, *SUMMARY_COLUMNS):
        if col not in r:
            r[col] = math.nan
    cols = ["policy", "speed_mps", "kind", *METRIC_COLUMNS, "run_min_time_gap_s", "collision",
            *SUMMARY_COLUMNS]
    out = r[cols].copy()
    ran = out["status"].eq("ok")
    out.loc[ran, "min_ttc_s"] = out.loc[ran, "min_ttc_s"].fillna(math.inf)  # JSON's null: inf
    human_cols = [f"human_p{round(100 * q):02d}_s" for q in HUMAN_QUANTILES]
    if humans is not None and len(humans):
        bands = humans.set_index("speed_mps")[human_cols]
        out = out.join(bands, on="speed_mps")
    else:
        for c in human_cols:
            out[c] = math.nan
    # a response must not sink below max(0.8 s, the humans' p05), nor below where it started
    # when it started closer (close): it is not blamed for its initial state
    floor = np.fmin(np.fmax(TARGET_MIN_TIME_GAP_S, out["human_p05_s"].to_numpy(float)),
                    out["time_gap_at_step_s"].to_numpy(float) - START_TOLERANCE_S)
    out["target_min_time_gap"] = out["min_time_gap_s"].to_numpy(float) >= floor
    out["target_settling"] = out["settled"].fillna(False).astype(bool) & (
        out["settling_time_s"] <= TARGET_SETTLING_S)
    in_iqr = out["eq_time_gap_s"].between(out["human_p25_s"], out["human_p75_s"])
    out["target_eq_in_human_iqr"] = in_iqr.where(out["human_p25_s"].notna()).astype("boolean")
    if humans is not None and len(humans):
        out = pd.concat([out, humans], ignore_index=True)
        for col in ("samples", "maneuvers", "drivers"):
            out[col] = out[col].astype("Int64")
    return out


def series(records: pd.DataFrame) -> pd.DataFrame:
    """The kept time series of every run, long: ``policy, speed_mps, kind, step_time_s, t, gap,
    v, leader_v, time_gap``."""
    parts = []
    for _, r in records.iterrows():
        if not isinstance(r.get("series_t"), list):
            continue
        gap, v = np.asarray(r["series_gap"], float), np.asarray(r["series_v"], float)
        parts.append(pd.DataFrame({
            "policy": r["policy"], "speed_mps": float(r["leader_speed_low_mps"]),
            "kind": kind_of(int(r["index"])), "step_time_s": float(r["step_time_s"]),
            "t": r["series_t"], "gap": gap, "v": v, "leader_v": r["series_leader_v"],
            "time_gap": time_gap(gap, v)}))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["policy", "speed_mps", "kind", "step_time_s", "t", "gap", "v", "leader_v",
                 "time_gap"])


def plot(series_df: pd.DataFrame, humans: pd.DataFrame | None, path: Path) -> None:
    """Time gap vs time: one panel per step kind (rows) and speed (columns), a line per policy;
    the humans' interquartile range (shaded) and 5th percentile (dashed) of that speed band, and
    the 0.8 s target (dotted); a grey vertical line at a leader's speed change."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [k for k in KINDS if k in set(series_df["kind"])]
    speeds = sorted(set(series_df["speed_mps"]))
    policies = list(dict.fromkeys(series_df["policy"]))
    fig, axes = plt.subplots(len(kinds), len(speeds), figsize=(4.2 * len(speeds),
                             2.6 * len(kinds)), squeeze=False, sharex="row")
    bands = humans.set_index("speed_mps") if humans is not None and len(humans) else None
    for i, kind in enumerate(kinds):
        for j, s in enumerate(speeds):
            ax = axes[i][j]
            g = series_df[(series_df["kind"] == kind) & (series_df["speed_mps"] == s)]
            for k, p in enumerate(policies):
                gp = g[g["policy"] == p]
                ax.plot(gp["t"], gp["time_gap"], color=f"C{k % 10}", lw=1.2, label=p)
            if bands is not None and s in bands.index and np.isfinite(bands.loc[s, "human_p25_s"]):
                b = bands.loc[s]
                ax.axhspan(b["human_p25_s"], b["human_p75_s"], color="0.5", alpha=0.18,
                           label="humans IQR")
                ax.axhline(b["human_p05_s"], color="0.3", ls="--", lw=0.9, label="humans p05")
            ax.axhline(TARGET_MIN_TIME_GAP_S, color="tab:red", ls=":", lw=0.9, label="0.8 s")
            for step in set(g["step_time_s"]) - {0.0}:  # the leader's speed change
                ax.axvline(step, color="0.6", lw=0.8)
            top = np.nanquantile(g["time_gap"], 0.98) if len(g) else 3.0
            ax.set_ylim(0.0, max(3.0, min(float(top) * 1.1, 6.0)))
            ax.set_title(f"{kind}, {s:g} m/s", fontsize=9)
            if i == len(kinds) - 1:
                ax.set_xlabel("time [s]")
            if j == 0:
                ax.set_ylabel("time gap [s]")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 7), fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    fig.savefig(path, dpi=100)
    plt.close(fig)
