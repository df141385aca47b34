"""The paper's data processing (Section IV-A): a validated drive -> experience tuples.

Each step is a pure function ``(drive frame, config) -> (frame, StepResult)``; nothing is mutated.
Rows are removed, never repaired, so the row counts per step tell what happened. A *segment* is a
run of rows of one recording whose time steps are at most ``gap_factor`` times the recording's
median step: removing rows splits segments, and derivatives never reach across a removed piece.

1. :func:`remove_lane_changes` — a change of ``lane_index``, or a jump of ``left_c0`` and
   ``right_c0`` by more than ``lane_jump_fraction`` of the lane width between two samples, is a
   lane change; rows within ``lane_change_window`` [s] either side are dropped. A sample where a
   corner of the car's body (``body_length_m`` x ``body_width_m``, the closed loop's car) lies
   beyond a lane line (:func:`body_outside_lines`) is a *line crossing* — a lane change under
   way, or lateral tracking noise (NGSIM) — and rows within ``line_crossing_window`` [s] are
   dropped: a car-following maneuver keeps its lane, as the closed loop's lane-departure monitor
   requires of the planner (and of the recorded human replayed, see
   :mod:`safeil_sumo.sim.recorded_ego`).
2. :func:`keep_leader_samples` — spacing control only: rows without a leader are dropped.
3. :func:`leader_speed` — ``v_lead = d(lead_x)/dt + v_x`` (the paper's approximation, ignoring
   yaw rate) with a Savitzky-Golay derivative (order 2, window ``smooth_window`` [s]) per segment;
   ``a_lead`` is the same filter's second derivative of ``lead_x`` plus ``d(v_x)/dt``. When the
   source measures ``lead_v`` (and ``use_measured_lead_v``) it is used as ``v_lead``, and the
   computed one is kept as ``v_lead_diff`` and compared in the report.
4. :func:`remove_cut_events` — a cut-in / cut-out / merge shows as a jump of ``lead_x``
   (``|d lead_x / dt| > max_gap_rate``) or a physically impossible leader acceleration
   (``|a_lead| > max_lead_accel``). Flagged samples less than ``cut_window`` apart are one event
   (typed ``gap_jump`` if any sample jumped, else ``lead_accel``); rows within ``cut_window`` [s]
   of a flagged sample are dropped.
5. :func:`split_maneuvers` — each remaining segment (also split where a source ``maneuver_id``
   changes) is a car-following maneuver; those shorter than ``min_maneuver`` [s] are dropped.
6. :func:`resample` — each maneuver is linearly interpolated to ``rate_hz`` from its first sample
   (``yaw`` unwrapped first).
7. :func:`build_tuples` — at every sample with ``horizon_samples`` samples ahead in the same
   maneuver: the 9 features (:func:`safeil_sumo.core.features.planner_features`, ``d_lead = lead_x``),
   the future front-bumper positions in the ego frame at t, and their least-squares B-spline
   control points (``tau = k / H``, origin fixed).
8. :func:`leave_one_maneuver_out` / :func:`kfold_by_maneuver` — train/test splits by whole
   maneuvers.
"""

from __future__ import annotations

import itertools
import time as _time
from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd
from scipy.signal import savgol_filter

from safeil_sumo.core.bspline import fit_control_points
from safeil_sumo.core.features import planner_features
from safeil_sumo.core.geometry import world_to_ego
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.sim.vehicle import VehicleParams


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the processing pipeline (SI units)."""

    gap_factor: float = 1.5  # [-] a step > gap_factor x median step breaks a segment
    lane_jump_fraction: float = 0.5  # [-] |d c0| above this x lane width = a lane change
    lane_change_window: float = 4.0  # [s] dropped either side of a lane change
    body_length_m: float = VehicleParams.length_m  # [m] car body for the line-crossing test
    body_width_m: float = VehicleParams.width_m  # [m]
    line_crossing_window: float = 0.5  # [s] dropped either side of a line crossing
    smooth_window: float = 1.0  # [s] Savitzky-Golay window for d/dt of lead_x and v_x
    use_measured_lead_v: bool = True  # use the source's lead_v when present
    max_gap_rate: float = 15.0  # [m/s] |d lead_x/dt| between two samples above = a jump
    max_lead_accel: float = 7.0  # [m/s^2] |a_lead| above = physically impossible
    cut_window: float = 2.0  # [s] dropped either side of a cut-in/out/merge sample
    min_maneuver: float = 8.0  # [s] shortest car-following maneuver kept
    rate_hz: float = 4.0  # [Hz] common sample rate of the tuples
    horizon_samples: int = 20  # [-] future samples per tuple (20 at 4 Hz = 5 s)

    @property
    def horizon(self) -> float:
        """Planning horizon T_h [s] = horizon_samples / rate_hz."""
        return self.horizon_samples / self.rate_hz


@dataclass(frozen=True)
class StepResult:
    """Rows in/out of one step, and what it found."""

    name: str
    rows_in: int
    rows_out: int
    events: dict[str, int] = field(default_factory=dict)
    notes: dict[str, float | int | str] = field(default_factory=dict)


@dataclass(frozen=True)
class PipelineReport:
    """What :func:`run_pipeline` did, step by step."""

    source: str
    config: PipelineConfig
    steps: tuple[StepResult, ...]
    maneuvers_kept: int
    maneuvers_dropped: int
    tuples: int
    recordings: int
    elapsed_s: float

    @property
    def events(self) -> dict[str, int]:
        """Events found per type, over all steps."""
        out: dict[str, int] = {}
        for s in self.steps:
            for k, v in s.events.items():
                out[k] = out.get(k, 0) + v
        return out

    @property
    def rows_per_s(self) -> float:
        """Input rows processed per second of wall time."""
        rows = self.steps[0].rows_in if self.steps else 0
        return rows / self.elapsed_s if self.elapsed_s > 0 else float("inf")

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "config": asdict(self.config) | {"horizon_s": self.config.horizon},
            "steps": [asdict(s) for s in self.steps],
            "events": self.events,
            "recordings": self.recordings,
            "maneuvers_kept": self.maneuvers_kept,
            "maneuvers_dropped": self.maneuvers_dropped,
            "tuples": self.tuples,
            "elapsed_s": self.elapsed_s,
            "rows_per_s": self.rows_per_s,
        }


# ------------------------------------------------------------------------------------- helpers


def segment_ids(df: pd.DataFrame, gap_factor: float) -> np.ndarray:
    """Integer id ``(N,)`` of the contiguous run each row belongs to (see module doc)."""
    n = len(df)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    rec = df["recording_id"].to_numpy()
    t = df["time"].to_numpy(float)
    new_rec = np.r_[True, rec[1:] != rec[:-1]]
    dt = np.r_[np.inf, np.diff(t)]
    rec_no = np.cumsum(new_rec) - 1
    inner = ~new_rec
    med = pd.Series(dt[inner]).groupby(rec_no[inner]).median()
    med_dt = med.reindex(range(rec_no[-1] + 1)).to_numpy()[rec_no]
    brk = new_rec | (dt > gap_factor * med_dt)
    if "maneuver_id" in df.columns:
        m = df["maneuver_id"].to_numpy()
        brk |= np.r_[True, m[1:] != m[:-1]]
    return np.cumsum(brk) - 1


def _bounds(ids: np.ndarray) -> np.ndarray:
    """Start index of each run of equal ids, plus the end (ids sorted by run)."""
    return np.r_[np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]), len(ids)]


def _near_flags(ids: np.ndarray, t: np.ndarray, flags: np.ndarray, window: float) -> np.ndarray:
    """Rows within ``window`` [s] of a flagged row of the same group ``ids`` (sorted by group)."""
    if not flags.any():
        return np.zeros(len(t), dtype=bool)
    # separate groups on one time axis so a window never crosses into another group
    span = (np.nanmax(t) - np.nanmin(t)) + 2.0 * window + 1.0
    g = ids * span + (t - np.nanmin(t))
    ev = g[flags]
    pos = np.searchsorted(ev, g)
    left = np.abs(g - ev[np.clip(pos - 1, 0, len(ev) - 1)])
    right = np.abs(ev[np.clip(pos, 0, len(ev) - 1)] - g)
    return np.minimum(left, right) <= window + 1e-9


def _runs(flags: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Start mask of runs of consecutive flagged rows within the same group."""
    prev = np.r_[False, flags[:-1] & (ids[1:] == ids[:-1])]
    return flags & ~prev


def _per_segment_savgol(values: np.ndarray, seg: np.ndarray, window_s: float,
                        t: np.ndarray, deriv: int) -> np.ndarray:
    """Savitzky-Golay (order 2) derivative per segment with each segment's own median step."""
    out = np.empty(len(values))
    b = _bounds(seg)
    for a, e in itertools.pairwise(b):
        v, n = values[a:e], e - a
        dt = float(np.median(np.diff(t[a:e]))) if n > 1 else 1.0
        w = round(window_s / dt) | 1
        w = min(w, n if n % 2 else n - 1)
        if w >= 3 and w > deriv:
            out[a:e] = savgol_filter(v, w, min(2, w - 1), deriv=deriv, delta=dt, mode="interp")
        elif n > 1 and deriv == 1:
            out[a:e] = np.gradient(v, t[a:e])
        else:
            out[a:e] = 0.0 if deriv else v
    return out


# --------------------------------------------------------------------------------------- steps


def body_outside_lines(df: pd.DataFrame, length_m: float, width_m: float) -> np.ndarray:
    """``(N,)`` True where a corner of the body lies beyond the left or right lane line.

    Corners in the ego frame: front bumper ``x = 0`` and rear ``x = -length_m``, ``y = ±width_m
    / 2``; a line is ``y = c0 + c1 x + c2 x^2 + c3 x^3`` (the schema's cubic, evaluated behind
    the origin for the rear corners). Rows without lane lines are False.
    """
    out = np.zeros(len(df), dtype=bool)
    half = 0.5 * width_m
    for x in (0.0, -length_m):
        for side, sign in (("left", 1.0), ("right", -1.0)):
            c = [df[f"{side}_c{k}"].to_numpy(float) for k in range(4)]
            line = c[0] + x * (c[1] + x * (c[2] + x * c[3]))
            with np.errstate(invalid="ignore"):
                out |= sign * (line - sign * half) < 0  # NaN compares False
    return out


def remove_lane_changes(df: pd.DataFrame, cfg: PipelineConfig) -> tuple[pd.DataFrame, StepResult]:
    """Step 1: drop a window around every lane change (lane_index change or lane-line jump) and
    every line crossing (the body beyond a lane line)."""
    seg = segment_ids(df, cfg.gap_factor)
    t = df["time"].to_numpy(float)
    same = np.r_[False, seg[1:] == seg[:-1]]
    c0l, c0r = df["left_c0"].to_numpy(float), df["right_c0"].to_numpy(float)
    width = np.abs(c0l - c0r)
    jump = same & (np.abs(np.r_[0.0, np.diff(c0l)]) > cfg.lane_jump_fraction * width) \
        & (np.abs(np.r_[0.0, np.diff(c0r)]) > cfg.lane_jump_fraction * width)
    lane_change = jump
    if "lane_index" in df.columns:
        lane = df["lane_index"].to_numpy(float)
        dl = np.r_[0.0, np.diff(lane)]
        lane_change = lane_change | (same & np.isfinite(dl) & (dl != 0))
    near_change = _near_flags(seg, t, lane_change, cfg.lane_change_window)
    # a body over a line away from any lane change (those windows are dropped already)
    crossing = body_outside_lines(df, cfg.body_length_m, cfg.body_width_m) & ~near_change
    drop = near_change | _near_flags(seg, t, crossing, cfg.line_crossing_window)
    out = df.loc[~drop].reset_index(drop=True)
    events = {"lane_change": int(_runs(lane_change, seg).sum()),
              "line_crossing": int(_runs(crossing, seg).sum())}
    return out, StepResult("remove_lane_changes", len(df), len(out), events)


def keep_leader_samples(df: pd.DataFrame) -> tuple[pd.DataFrame, StepResult]:
    """Step 2: keep only the samples with a leader (spacing control)."""
    has = df["lead_x"].notna().to_numpy()
    out = df.loc[has].reset_index(drop=True)
    seg = segment_ids(df, np.inf)
    gaps = int(_runs(~has, seg).sum())
    return out, StepResult("keep_leader_samples", len(df), len(out), {"no_leader": gaps})


def leader_speed(df: pd.DataFrame, cfg: PipelineConfig) -> tuple[pd.DataFrame, StepResult]:
    """Step 3: add ``v_lead_diff``, ``a_lead`` and ``v_lead`` [m/s, m/s^2] (see module doc)."""
    seg = segment_ids(df, cfg.gap_factor)
    t = df["time"].to_numpy(float)
    lx = df["lead_x"].to_numpy(float)
    vx = df["v_x"].to_numpy(float)
    v_diff = _per_segment_savgol(lx, seg, cfg.smooth_window, t, 1) + vx
    a_lead = _per_segment_savgol(lx, seg, cfg.smooth_window, t, 2) \
        + _per_segment_savgol(vx, seg, cfg.smooth_window, t, 1)
    notes: dict[str, float | int | str] = {"v_lead_source": "differentiated"}
    v_lead = v_diff
    if cfg.use_measured_lead_v and "lead_v" in df.columns:
        meas = df["lead_v"].to_numpy(float)
        have = np.isfinite(meas)
        if have.any():
            err = v_diff[have] - meas[have]
            notes = {
                "v_lead_source": "measured (differentiated where missing)",
                "v_lead_measured_rows": int(have.sum()),
                "v_lead_diff_minus_measured_median_mps": float(np.median(err)),
                "v_lead_diff_minus_measured_rmse_mps": float(np.sqrt(np.mean(err**2))),
                "v_lead_diff_minus_measured_p99_abs_mps": float(np.percentile(np.abs(err), 99)),
            }
            v_lead = np.where(have, meas, v_diff)
    out = df.assign(v_lead=v_lead, v_lead_diff=v_diff, a_lead=a_lead)
    return out, StepResult("leader_speed", len(df), len(out), {}, notes)


def remove_cut_events(df: pd.DataFrame, cfg: PipelineConfig) -> tuple[pd.DataFrame, StepResult]:
    """Step 4: drop a window around lead_x jumps and impossible leader accelerations.

    Needs the ``a_lead`` column of :func:`leader_speed`.
    """
    seg = segment_ids(df, cfg.gap_factor)
    t = df["time"].to_numpy(float)
    lx = df["lead_x"].to_numpy(float)
    same = np.r_[False, seg[1:] == seg[:-1]]
    rate = np.abs(np.r_[0.0, np.diff(lx)] / np.r_[1.0, np.diff(t)])
    jump = same & (rate > cfg.max_gap_rate)
    accel = np.abs(df["a_lead"].to_numpy(float)) > cfg.max_lead_accel
    flags = jump | accel
    # flagged samples closer than cut_window (same segment) belong to one event
    fi = np.flatnonzero(flags)
    new_event = np.r_[True, (seg[fi][1:] != seg[fi][:-1])
                      | (np.diff(t[fi]) > cfg.cut_window)] if len(fi) else np.zeros(0, bool)
    event_no = np.cumsum(new_event) - 1
    n_events = int(new_event.sum())
    n_jump = int(np.count_nonzero(np.bincount(event_no[jump[fi]], minlength=n_events)))
    drop = _near_flags(seg, t, flags, cfg.cut_window)
    out = df.loc[~drop].reset_index(drop=True)
    events = {"gap_jump": n_jump, "lead_accel": n_events - n_jump}
    return out, StepResult("remove_cut_events", len(df), len(out), events)


def split_maneuvers(df: pd.DataFrame, cfg: PipelineConfig) -> tuple[pd.DataFrame, StepResult]:
    """Step 5: label contiguous car-following runs ``maneuver_id = "<recording>#<k>"``; drop short.

    A source ``maneuver_id`` column is kept as ``source_maneuver_id`` and never split across.
    """
    seg = segment_ids(df, cfg.gap_factor)
    t = df["time"].to_numpy(float)
    b = _bounds(seg) if len(df) else np.zeros(1, dtype=np.int64)
    starts, ends = b[:-1], b[1:]
    dur = t[ends - 1] - t[starts] if len(starts) else np.zeros(0)
    keep_seg = dur >= cfg.min_maneuver - 1e-9
    keep = np.repeat(keep_seg, ends - starts)
    rec = df["recording_id"].to_numpy()
    # k counts kept maneuvers within the recording, from 0
    kept_starts = starts[keep_seg]
    rec_of = rec[kept_starts]
    k = pd.Series(rec_of).groupby(rec_of).cumcount().to_numpy() if len(rec_of) else []
    names = np.array([f"{r}#{i}" for r, i in zip(rec_of, k, strict=True)], dtype=object)
    out = df.loc[keep].reset_index(drop=True)
    if "maneuver_id" in out.columns:
        out = out.rename(columns={"maneuver_id": "source_maneuver_id"})
    out["maneuver_id"] = np.repeat(names, (ends - starts)[keep_seg]).astype(str)
    res = StepResult("split_maneuvers", len(df), len(out),
                     {"maneuver_kept": int(keep_seg.sum()),
                      "maneuver_too_short": int((~keep_seg).sum())},
                     {"kept_duration_s": float(dur[keep_seg].sum()),
                      "dropped_duration_s": float(dur[~keep_seg].sum())})
    return out, res


def resample(df: pd.DataFrame, cfg: PipelineConfig) -> tuple[pd.DataFrame, StepResult]:
    """Step 6: linear interpolation of each maneuver to ``rate_hz`` from its first sample."""
    man = df["maneuver_id"].to_numpy()
    if len(df) == 0:
        return df.copy(), StepResult("resample", 0, 0)
    b = _bounds(man)
    starts, ends = b[:-1], b[1:]
    t = df["time"].to_numpy(float)
    step = 1.0 / cfg.rate_hz
    t0, t1 = t[starts], t[ends - 1]
    n_new = np.floor((t1 - t0) / step + 1e-9).astype(np.int64) + 1
    # one global axis with maneuvers far apart: a single np.interp per column
    span = float(t.max() - t.min()) + 10.0
    g = np.repeat(np.arange(len(starts)) * span, ends - starts) + (t - t.min())
    m_new = np.repeat(np.arange(len(starts)), n_new)
    local = np.arange(n_new.sum()) - np.repeat(np.cumsum(n_new) - n_new, n_new)
    t_new = np.repeat(t0, n_new) + local * step
    g_new = m_new * span + (t_new - t.min())
    cols: dict[str, np.ndarray] = {}
    for c in df.columns:
        v = df[c].to_numpy()
        if c == "time":
            cols[c] = t_new
        elif pd.api.types.is_numeric_dtype(df[c]) and not pd.api.types.is_bool_dtype(df[c]):
            v = v.astype(float)
            if c == "yaw":
                v = np.concatenate([np.unwrap(v[a:e]) for a, e in zip(starts, ends, strict=True)])
            cols[c] = np.interp(g_new, g, v)
            if c == "yaw":
                cols[c] = (cols[c] + np.pi) % (2 * np.pi) - np.pi
        else:  # labels are constant within a maneuver
            cols[c] = np.repeat(v[starts], n_new)
    out = pd.DataFrame(cols)
    return out, StepResult("resample", len(df), len(out), {}, {"rate_hz": cfg.rate_hz})


def build_tuples(df: pd.DataFrame, cfg: PipelineConfig, source: str = "drive"
                 ) -> tuple[Tuples, StepResult]:
    """Step 7: (features, future, control points) at every sample with a full future."""
    h = cfg.horizon_samples
    man = df["maneuver_id"].to_numpy() if len(df) else np.zeros(0, dtype=object)
    n = len(df)
    if n:
        b = _bounds(man)
        length = np.repeat(np.diff(b), np.diff(b))
        pos = np.arange(n) - np.repeat(b[:-1], np.diff(b))
        idx = np.flatnonzero(pos + h < length)
    else:
        idx = np.zeros(0, dtype=np.int64)
    xy = df[["x", "y"]].to_numpy(float) if n else np.zeros((0, 2))
    yaw = df["yaw"].to_numpy(float) if n else np.zeros(0)
    fut_idx = idx[:, None] + np.arange(1, h + 1)[None, :]
    future = world_to_ego(xy[fut_idx], xy[idx][:, None, :], yaw[idx][:, None])
    tau = np.arange(1, h + 1) / h  # future_times / horizon
    cps = fit_control_points(future, tau) if len(idx) else np.zeros((0, 3, 2))

    def col(name: str) -> np.ndarray:
        return df[name].to_numpy(float)[idx] if n else np.zeros(0)

    left = np.stack([col(f"left_c{i}") for i in range(3)], axis=-1)
    right = np.stack([col(f"right_c{i}") for i in range(3)], axis=-1)
    feats = planner_features(left, right, col("v_x"), col("v_lead"), col("lead_x"))
    tup = Tuples(
        features=feats.reshape(len(idx), -1), control_points=cps.reshape(len(idx), 3, 2),
        future=future.reshape(len(idx), h, 2), maneuver_id=man[idx].astype(str),
        source=np.full(len(idx), source), t=col("time"), horizon=cfg.horizon,
        rate_hz=cfg.rate_hz,
    )
    return tup, StepResult("build_tuples", n, len(tup), {}, {"horizon_s": cfg.horizon})


# -------------------------------------------------------------------------------------- splits


@dataclass(frozen=True)
class Split:
    """Indices ``(n,)`` into a Tuples of the training and test sets, and the test maneuvers."""

    train: np.ndarray
    test: np.ndarray
    test_maneuvers: tuple[str, ...]


def leave_one_maneuver_out(maneuver_id: np.ndarray) -> list[Split]:
    """One split per maneuver: that maneuver is the test set, all others train."""
    ids = np.asarray(maneuver_id).astype(str)
    return [Split(np.flatnonzero(ids != m), np.flatnonzero(ids == m), (str(m),))
            for m in np.unique(ids)]


def kfold_by_maneuver(maneuver_id: np.ndarray, k: int, seed: int = 0) -> list[Split]:
    """``k`` folds of whole maneuvers, shuffled with ``seed``; every maneuver is tested once."""
    ids = np.asarray(maneuver_id).astype(str)
    uniq = np.unique(ids)
    if not 2 <= k <= len(uniq):
        raise ValueError(f"k must be in [2, {len(uniq)}] (number of maneuvers), got {k}")
    order = np.random.default_rng(seed).permutation(uniq)
    out = []
    for fold in np.array_split(order, k):
        test = np.isin(ids, fold)
        out.append(Split(np.flatnonzero(~test), np.flatnonzero(test), tuple(str(m) for m in sorted(fold))))
    return out


def split_by_maneuver(maneuver_id: np.ndarray, k: int | None = None, seed: int = 0
                      ) -> list[Split]:
    """Leave-one-maneuver-out when ``k`` is None, else seeded k-fold by maneuver."""
    if k is None:
        return leave_one_maneuver_out(maneuver_id)
    return kfold_by_maneuver(maneuver_id, k, seed)


# ------------------------------------------------------------------------------------- pipeline


def process_drive(drive: pd.DataFrame, config: PipelineConfig | None = None
                  ) -> tuple[pd.DataFrame, list[StepResult]]:
    """Steps 1-6: the resampled maneuvers frame (one row per tuple-rate sample)."""
    cfg = config or PipelineConfig()
    steps: list[StepResult] = []
    df = drive

    def keep_leaders(d: pd.DataFrame, _: PipelineConfig) -> tuple[pd.DataFrame, StepResult]:
        return keep_leader_samples(d)  # the one step without options

    for step in (remove_lane_changes, keep_leaders, leader_speed, remove_cut_events,
                 split_maneuvers, resample):
        df, res = step(df, cfg)
        steps.append(res)
    return df, steps


def run_pipeline(drive: pd.DataFrame, config: PipelineConfig | None = None,
                 source: str = "drive") -> tuple[Tuples, PipelineReport]:
    """Steps 1-7 on a validated drive frame -> tuples and a report."""
    cfg = config or PipelineConfig()
    t0 = _time.perf_counter()
    df, steps = process_drive(drive, cfg)
    tup, res = build_tuples(df, cfg, source)
    steps.append(res)
    elapsed = _time.perf_counter() - t0
    split = next(s for s in steps if s.name == "split_maneuvers")
    report = PipelineReport(
        source=source, config=cfg, steps=tuple(steps),
        maneuvers_kept=split.events["maneuver_kept"],
        maneuvers_dropped=split.events["maneuver_too_short"],
        tuples=len(tup), recordings=int(drive["recording_id"].nunique()) if len(drive) else 0,
        elapsed_s=elapsed,
    )
    return tup, report
