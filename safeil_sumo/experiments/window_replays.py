"""Human-likeness over the whole distribution: replay every maneuver window, aggregate, plot.

One *task* is one window of one maneuver (rebuilt once in SUMO) driven by every policy; its
metrics (one row per policy, :func:`safeil_sumo.experiments.maneuver_replay.compare`) and the
time-gap histograms of the human and each policy are written at once and atomically to
``<out>/tasks/<task>.json``, so an interrupted run resumes (done windows are skipped). Windows
run in ``workers`` processes (one libsumo each), up to ``batch`` windows of a worker's unit side
by side in ONE SUMO simulation (:func:`run_windows`: each window on its own copy of its net,
every (window, planner) run in one ``run_batch``; the same records as one simulation per run,
floats to round-off); each window's record is written as its runs end. The windows run on the
task engine (:mod:`.task_engine`, as a :class:`WindowJob`): in-process, local worker processes
or a Dask cluster (``scheduler``), resumed and interrupted as sweeps are.

Windows (``mode``):
- ``paper``: the paper's 11 s from the start of each maneuver;
- ``sliding``: 11 s windows every ``stride_s`` s through each maneuver (the default of
  ``replay --maneuver all``: many windows per maneuver, all its traffic situations);
- ``whole``: each maneuver from start to end (or, given a duration, for at most that long from
  its start).

The aggregate per policy (or per policy and driver, :func:`aggregate`'s ``by``): windows,
median and mean gap RMSE with seeded bootstrap 95 % intervals, the worst window's gap RMSE and
its id, the spacing RMSPE and the time-gap error (:func:`literature_summary`: the figures the
car-following literature reports), median speed and lateral RMSE, the time-gap Wasserstein
distance to the human, flags (also counted apart when the recording itself has a flag there,
``flags_beyond_human``) and collisions. Each record carries the window's ``driver``
(:func:`driver_id`).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.core.policy import Policy
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.experiments import outputs
from safeil_sumo.experiments.task_engine import (
    Emit,
    deferred_interrupt,
    even_units,
    execute,
    read_record,
    record_path,
)
from safeil_sumo.planners import registry as planner_registry

WINDOW_MODES = ("paper", "sliding", "whole")
HEADWAY_BINS = np.linspace(0.0, 5.0, 51)  # [s] time-gap histogram bins
BOOTSTRAP_SAMPLES = 2000
# the replay's own reconstruction error per window (replay.ReplayResult.info)
INSTRUMENT_KEYS = ("max_abs_lane_rebuild_error_m", "max_abs_leader_drift_m",
                   "max_abs_leader_drift_uncorrected_m")
# windows per worker task run side by side in one SUMO simulation (``replay --batch``):
# measured on OpenACC, docs/performance.md ("Batched replays")
DEFAULT_BATCH = 32
# an NGSIM pair recording "<follower>-<leader>", "_<n>" when the pair recurs (data.importers)
NGSIM_PAIR = re.compile(r"^(\d+)-\d+(?:_\d+)?$")
# one of several runs of an OpenACC follower "<file>_f<k>_s<i>" (data.importers)
OPENACC_RUN = re.compile(r"^(.+_f\d+)_s\d+$")


@dataclass(frozen=True)
class Window:
    """One replayed window: ``start_s`` [s after the maneuver's first sample], ``duration_s``
    (None: to the maneuver's end)."""

    maneuver_id: str
    start_s: float
    duration_s: float | None
    # [s] the planners were adapted to the driver on the maneuver's first adapt_s seconds
    # (adapt_planners), which the window then leaves out: start_s = adapt_s
    adapt_s: float = 0.0

    @property
    def task_id(self) -> str:
        text = f"{self.maneuver_id}|{self.start_s:.3f}|{self.duration_s}"
        if self.adapt_s:
            text += f"|adapt {self.adapt_s:.3f}"
        digest = hashlib.sha256(text.encode()).hexdigest()[:10]
        return re.sub(r"[^A-Za-z0-9_]+", "_", self.maneuver_id)[:40] + f"-{self.start_s:07.1f}-{digest}"


def driver_id(maneuver_id: str) -> str:
    """The driver of a maneuver ``"<recording>#<k>"`` (the processing pipeline's ids): the
    follower's vehicle id of an NGSIM pair ``"<follower>-<leader>"`` (one vehicle follows
    several leaders in turn), else the recording: an OpenACC follower ``"<file>_f<k>"`` (the
    runs ``"<file>_f<k>_s<i>"`` of one follower between receiver dropouts are that follower),
    a synthetic drive ``"n74_d<k>"``."""
    recording = maneuver_id.rsplit("#", 1)[0]
    pair = NGSIM_PAIR.match(recording)
    if pair:
        return pair.group(1)
    run = OPENACC_RUN.match(recording)
    return run.group(1) if run else recording


def window_id(maneuver_id: str, start_s: float) -> str:
    """A window's name in tables: ``"<maneuver>@<start>s"``."""
    return f"{maneuver_id}@{start_s:g}s"


def windows(maneuvers: pd.DataFrame, mode: str = "sliding",
            duration_s: float | None = None, stride_s: float = 20.0,
            only: list[str] | None = None, adapt_s: float = 0.0) -> list[Window]:
    """The windows of every maneuver (or of ``only``) in ``mode``. ``duration_s`` [s]: the
    window length in ``paper`` / ``sliding`` mode (None: the paper's 11 s; maneuvers shorter
    than one window are skipped), a cap from each maneuver's start in ``whole`` mode (None or 0:
    to its end; a maneuver no longer than the cap stays whole, the same window).
    ``adapt_s`` [s] (``whole`` mode only): the planners are adapted to the driver on each
    maneuver's first ``adapt_s`` seconds (:func:`adapt_planners`) and the window is the rest of
    the maneuver; a maneuver without :data:`MIN_SCORED_S` left after them is skipped."""
    if mode not in WINDOW_MODES:
        raise ValueError(f"windows must be one of {WINDOW_MODES}, got {mode!r}")
    if adapt_s and mode != "whole":
        raise ValueError("adapting to the driver (adapt_s) needs whole-maneuver windows")
    window_s = duration_s or rp.PAPER_DURATION_S  # paper / sliding: the windows' length [s]
    cap_s = duration_s or 0.0  # whole: the cap from each maneuver's start [s] (0: none)
    table = rp.maneuver_table(maneuvers)
    if only is not None:
        unknown = sorted(set(only) - set(table.index))
        if unknown:
            ids = list(table.index)
            raise rp.ReplayError(f"unknown maneuver(s) {unknown}; available: "
                                 f"{', '.join(ids[:10])}{' ...' if len(ids) > 10 else ''}")
        table = table.loc[sorted(set(only))]
    out = []
    for mid, row in table.iterrows():
        dur = float(row["duration_s"])
        if mode == "whole" and adapt_s:
            if dur - adapt_s < MIN_SCORED_S:
                continue
            capped = bool(cap_s) and cap_s < dur - adapt_s - 1e-9
            out.append(Window(str(mid), float(adapt_s), float(cap_s) if capped else None,
                              float(adapt_s)))
        elif mode == "whole":
            capped = bool(cap_s) and cap_s < dur - 1e-9
            out.append(Window(str(mid), 0.0, float(cap_s) if capped else None))
        elif dur >= window_s - 1e-9:
            starts = [0.0] if mode == "paper" else np.arange(0.0, dur - window_s + 1e-9,
                                                             stride_s)
            out += [Window(str(mid), float(s), window_s) for s in starts]
    return out


MIN_SCORED_S = 20.0  # [s] an adapted maneuver needs this much left to score
# the way adapt_planners adapts (a cached adapted result of another way is not reused)
ADAPTATION_METHOD = "style-estimator-2"


def driver_time_gap(first_rows: pd.DataFrame, default_s: float) -> float:
    """The driver's preferred time gap [s] estimated on a maneuver's first rows, a planner's
    default setting ``default_s`` [s] (the population's median) as the prior
    (:func:`safeil_sumo.learn.style.adapted_time_gap`; ``default_s`` itself without a following
    sample): what :func:`adapt_planners` sets a ``safeil_median`` checkpoint to."""
    from safeil_sumo.learn.style import TimeGapPrior, adapted_time_gap

    t = first_rows["time"].to_numpy(float)
    dt_s = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    return adapted_time_gap(first_rows["lead_x"].to_numpy(float),
                            first_rows["v_x"].to_numpy(float), dt_s, TimeGapPrior(default_s))


def driver_style(first_rows: pd.DataFrame, prior=None):
    """The driver's (s0, T) posterior (:class:`safeil_sumo.learn.style_estimator.
    StyleEstimate`) after a maneuver's first rows (``time, lead_x, v_x, v_lead``), from the
    population ``prior`` (default :class:`~safeil_sumo.learn.style_estimator.StylePrior`)."""
    from safeil_sumo.learn.style_estimator import estimate_drive

    rows = first_rows.sort_values("time")
    t, gap, speed, lead_speed = (rows[c].to_numpy(float) for c in ("time", "lead_x", "v_x",
                                                                   "v_lead"))
    est, _ = estimate_drive(t, gap, speed, lead_speed, prior)
    return est


def checkpoint_style(est, default_s: float) -> dict[str, float]:
    """The style a style-conditioned checkpoint gets from the estimate ``est``: the line itself,
    ``time_gap_s`` and ``standstill_m`` (s0 inside
    :data:`~safeil_sumo.learn.style.STANDSTILL_RANGE_M`, T keeping the line's gap at the mean
    speed of the steady samples seen, :func:`~safeil_sumo.learn.style_estimator.bounded_style`),
    so the setting follows the speed (:func:`~safeil_sumo.learn.style.scheduled_time_gap`);
    without a steady sample the default setting ``default_s`` [s] alone."""
    from safeil_sumo.learn.style import STANDSTILL_NAME, STANDSTILL_RANGE_M
    from safeil_sumo.learn.style_estimator import bounded_style

    if not est.samples:
        return {"time_gap_s": float(default_s)}
    s0, t_gap = bounded_style(est, STANDSTILL_RANGE_M, (0.05, 10.0))  # a T set_style takes
    return {"time_gap_s": t_gap, STANDSTILL_NAME: s0}


def driver_setting(first_rows: pd.DataFrame, default_s: float, prior=None) -> float:
    """The time-gap setting [s] a planner with a time-gap input only (``gap = T v``) gets from
    :func:`driver_style`: the estimated line's time gap at the mean speed of the steady samples
    seen, ``s0 / v + T`` (:meth:`~safeil_sumo.learn.style_estimator.StyleEstimate.setting_s`);
    ``default_s`` [s] without a steady sample."""
    est = driver_style(first_rows, prior)
    return est.setting_s(est.mean_speed_mps) if est.samples else float(default_s)


def idm_style_params(params, est):
    """The IDM's parameters ``params`` (:class:`safeil_sumo.planners.idm.IDMParams`) with a driver's
    style ``est`` (:class:`~safeil_sumo.learn.style_estimator.StyleEstimate`): s0 inside the
    IDM's calibration bounds, and T such that the IDM's own steady gap
    (:func:`safeil_sumo.planners.idm.equilibrium_gap`, ``(s0 + v T) / sqrt(1 - (v / v0)^delta)``) equals
    the estimated line's at the mean speed of the steady samples seen (the IDM's free-road term
    lengthens its gap near v0: at 30 m/s and the shipped v0 of 41 m/s by 18 %, so setting the
    line's T alone would set it farther back than the driver); v0, a, b and delta as calibrated.
    Without a steady sample (or at v0): the line's own s0 and T, inside the bounds
    (:func:`~safeil_sumo.learn.style_estimator.bounded_style`)."""
    from dataclasses import replace

    from safeil_sumo.learn.style_estimator import bounded_style
    from safeil_sumo.planners import idm

    k0, kt = idm.FIT_FIELDS.index("s0_m"), idm.FIT_FIELDS.index("time_gap_s")
    t_range = (idm.LOWER[kt], idm.UPPER[kt])
    s0, t_gap = bounded_style(est, (idm.LOWER[k0], idm.UPPER[k0]), t_range)
    v = est.mean_speed_mps
    free = 1.0 - (v / params.v0_mps) ** params.delta if est.samples and v > 0 else 0.0
    if free > 0.0:
        t_gap = min(max((est.gap_m(v) * math.sqrt(free) - s0) / v, t_range[0]), t_range[1])
    return replace(params, s0_m=s0, time_gap_s=t_gap)


def adapt_planners(policies: dict, first_rows: pd.DataFrame, seed: int = 0,
                   prior=None) -> dict:
    """The planners adapted to the driver of ``first_rows`` (a maneuver's first seconds, which
    the score then leaves out), each by its label's way
    (:func:`safeil_sumo.planners.registry.adaptation_of`):

    - by default, one estimate for all: the driver's (s0, T) from the steady-following samples
      of those seconds (:func:`driver_style`, the population ``prior``). Each planner is set so
      that its steady gap is the estimated line's at the speed seen: the IDM gets s0 and T
      (:func:`idm_style_params`), its v0, a, b and delta as calibrated; a style-conditioned
      checkpoint the line itself, its setting following the speed (:func:`checkpoint_style`);
    - ``safeil_one_setting``: the checkpoint set to one setting, the line's time gap at the mean
      speed seen (:func:`driver_setting`, its default setting without a steady sample);
    - ``idm_refit5``: the IDM's five parameters fitted on those seconds
      (:func:`safeil_sumo.planners.idm.fit_idm`, the same calibration as the shipped fit);
    - ``safeil_median``: the checkpoint set to today's shrunk median of gap / speed
      (:func:`driver_time_gap`);
    - ``*_unadapted``, and planners without a setting: as they are.

    Copies: ``policies`` is unchanged."""
    import copy
    from dataclasses import replace

    from safeil_sumo.planners import idm
    from safeil_sumo.planners import registry as pol

    est = None
    out = {}
    for label, policy in policies.items():
        how = pol.adaptation_of(label)
        if how == "unadapted" or not pol.has_time_gap(policy):
            out[label] = policy
        elif isinstance(policy, idm.IDMPlanner) and how == "refit5":
            fit = idm.fit_idm(idm.maneuvers_from_rows(first_rows), seed=seed, starts=2)
            out[label] = replace(policy, params=fit.params)
        elif how == "median":  # a styled checkpoint, the shrunk median's setting
            time_gap = driver_time_gap(first_rows, policy.style["time_gap_s"])
            out[label] = pol.with_time_gap(copy.deepcopy(policy), time_gap)
        else:
            est = est or driver_style(first_rows, prior)
            if isinstance(policy, idm.IDMPlanner):
                out[label] = replace(policy, params=idm_style_params(policy.params, est))
            elif how == "one_setting":
                setting = (est.setting_s(est.mean_speed_mps) if est.samples
                           else policy.style["time_gap_s"])
                out[label] = pol.with_time_gap(copy.deepcopy(policy), setting)
            else:  # a styled checkpoint
                style = checkpoint_style(est, policy.style["time_gap_s"])
                out[label] = pol.with_time_gap(copy.deepcopy(policy), style["time_gap_s"],
                                               style.get("standstill_m"))
    return out


def with_setting(policies: dict, time_gap_s: float | None, standstill_m: float | None = None
                 ) -> dict:
    """``policies`` with the planners that have a time-gap setting (style-conditioned
    checkpoints, the IDM) set to ``time_gap_s`` [s] and ``standstill_m`` [m]
    (:func:`safeil_sumo.planners.registry.with_time_gap`); the others as they are. None:
    ``policies`` itself. Copies: ``policies`` is unchanged."""
    import copy

    from safeil_sumo.planners import registry as pol

    if time_gap_s is None:
        return policies
    return {label: pol.with_time_gap(copy.deepcopy(p), time_gap_s, standstill_m)
            if pol.has_time_gap(p)
            else p for label, p in policies.items()}


def adaptation(planners: dict) -> dict:
    """What each adapted planner was set to (JSON-able, for the window's record): the style of
    a style-conditioned checkpoint, the IDM's parameters; ``{}`` for the others."""
    from dataclasses import asdict

    from safeil_sumo.planners import idm

    return {label: asdict(p.params) if isinstance(p, idm.IDMPlanner)
            else dict(getattr(p, "style", None) or {}) for label, p in planners.items()}


def _window_policies(window: Window, maneuvers: pd.DataFrame, policies: dict) -> dict:
    """``policies``, adapted on the maneuver's first ``window.adapt_s`` seconds if asked."""
    if not window.adapt_s:
        return policies
    rows = maneuvers[maneuvers["maneuver_id"] == window.maneuver_id].reset_index(drop=True)
    return adapt_planners(policies, rp.window(rows, 0.0, window.adapt_s))


def _headway_hist(values: np.ndarray) -> list[int]:
    v = np.asarray(values, float)
    return np.histogram(v[np.isfinite(v)], bins=HEADWAY_BINS)[0].tolist()


def _window_rows(window: Window, maneuvers: pd.DataFrame) -> pd.DataFrame:
    rows = maneuvers[maneuvers["maneuver_id"] == window.maneuver_id].reset_index(drop=True)
    return rp.window(rows, window.start_s, window.duration_s)


def _failed(window: Window, error: Exception | str) -> dict:
    """The record of a window that could not be replayed (``error``: the exception, or its
    ``"Type: message"``)."""
    if isinstance(error, Exception):
        error = f"{type(error).__name__}: {error}"
    return {"task_id": window.task_id, "maneuver_id": window.maneuver_id,
            "driver": driver_id(window.maneuver_id), "start_s": window.start_s,
            "status": "failed", "error": error}


def _record(window: Window, res: rp.ReplayResult, planners: dict | None = None) -> dict:
    """The JSON-able record of a replayed window (``planners``: those it ran, for the settings
    of an adapted window)."""
    metrics = res.metrics.replace({np.nan: None}).to_dict(orient="records")
    extra = {"adapted": adaptation(planners)} if window.adapt_s and planners else {}
    return {**extra,
        "task_id": window.task_id, "maneuver_id": window.maneuver_id,
        "driver": driver_id(window.maneuver_id),
        "start_s": window.start_s, "duration_s": res.info["duration_s"], "status": "ok",
        "adapt_s": window.adapt_s,
        "mean_speed_mps": res.info["mean_speed_mps"], "mean_gap_m": res.info["mean_gap_m"],
        **{k: res.info[k] for k in INSTRUMENT_KEYS},
        "metrics": metrics,
        "headway_hist": {"human": _headway_hist(res.human["headway"]),
                         **{name: _headway_hist(tr["headway"])
                            for name, tr in res.compared.items()}},
    }


def run_window(window: Window, maneuvers: pd.DataFrame, policies: dict, config: rp.ReplayConfig
               ) -> dict:
    """Replay one window with every policy: a JSON-able record (never raises)."""
    try:
        rows = _window_rows(window, maneuvers)
        policies = _window_policies(window, maneuvers, policies)
        with tempfile.TemporaryDirectory() as tmp:
            res = rp.replay_maneuver(rows, policies, Path(tmp), config,
                                     maneuver_id=window.maneuver_id)
    except Exception as exc:  # noqa: BLE001 - a record, never an exception: the run goes on
        return _failed(window, exc)
    return _record(window, res, policies)


def run_windows(wins: Sequence[Window], maneuvers: pd.DataFrame, policies: dict,
                config: rp.ReplayConfig, on_record: Emit | None = None) -> list[dict]:
    """Replay ``wins`` side by side: every (window, planner) run in ONE SUMO simulation
    (:func:`safeil_sumo.sim.batch.run_batch`, each window on its own copy of its net), the
    kinematic ``recorded`` runs each on ``run_scenario``. The records (window order) are
    :func:`run_window`'s; ``on_record(k, record)`` is called as the k-th window's runs have
    ended (a Ctrl-C waits for it). One window is :func:`run_window`. Never raises: a window that
    cannot be prepared, or a batch that fails, gives failed records.
    """
    if len(wins) == 1:  # today's path: one simulation per run
        records = [run_window(wins[0], maneuvers, policies, config)]
        if on_record is not None:
            on_record(0, records[0])
        return records
    return _run_batched(wins, maneuvers, policies, config, on_record)


def _run_batched(wins: Sequence[Window], maneuvers: pd.DataFrame, policies: dict,
                 config: rp.ReplayConfig, on_record: Emit | None) -> list[dict]:
    """:func:`run_windows` of several windows: their planners' runs in one batch."""
    from safeil_sumo.sim.batch import run_batch
    from safeil_sumo.sim.runner import run_scenario

    records: list[dict | None] = [None] * len(wins)
    preps: dict[int, rp.ReplayPrep] = {}
    rollouts: dict[int, dict] = {}  # window -> label -> rollout, until the window's record
    used: dict[int, dict] = {}  # window -> label -> the planner it ran (adapted or not)
    batched: list[tuple[int, str, Policy]] = []  # (window, label, planner) of the batch

    def settle(k: int, rec: dict | None = None) -> None:
        """Window ``k``'s record (``rec``, else its comparison once all its runs ended)."""
        if rec is None and len(rollouts[k]) < len(policies):
            return
        with deferred_interrupt():  # a window whose runs ended gets its record
            if rec is None:
                try:
                    rec = _record(wins[k], rp.compare_replay(
                        preps[k], {label: rollouts[k][label] for label in policies}, config),
                        used[k])
                except Exception as exc:  # noqa: BLE001 - a record: the batch goes on
                    rec = _failed(wins[k], exc)
            rollouts.pop(k, None)  # its logs are freed
            records[k] = rec
            if on_record is not None:
                on_record(k, rec)

    with tempfile.TemporaryDirectory() as tmp:
        for k, w in enumerate(wins):
            try:
                preps[k] = rp.prepare_replay(_window_rows(w, maneuvers), Path(tmp) / str(k),
                                             config, w.maneuver_id)
                rollouts[k] = {}
                used[k] = _window_policies(w, maneuvers, policies)
                for label, policy in used[k].items():
                    planner = rp.replay_policy(preps[k], policy)
                    if getattr(planner, "pose_at", None) is not None:  # kinematic: alone
                        rollouts[k][label] = run_scenario(preps[k].scenario, planner,
                                                          config.loop, config.vehicle)
                    else:
                        batched.append((k, label, planner))
            except Exception as exc:  # noqa: BLE001 - a record, never an exception
                batched = [b for b in batched if b[0] != k]
                settle(k, _failed(w, exc))
                continue
            settle(k)  # a window of kinematic runs only is done

        def done(i: int, rollout) -> None:
            k, label, _ = batched[i]
            rollouts[k][label] = rollout
            settle(k)

        if batched:
            try:
                run_batch([preps[k].scenario for k, _, _ in batched], [p for *_, p in batched],
                          config.loop, config.vehicle, on_done=done, keep_logs=False, net_dir=Path(tmp))
            except Exception as exc:  # noqa: BLE001 - failed records, never an exception
                for k in sorted(rollouts):
                    settle(k, _failed(wins[k], exc))
    # run_batch reports every scenario it was given (on_done), so every window is settled
    return [_failed(wins[k], RuntimeError("the batch ended without this window's record"))
            if r is None else r for k, r in enumerate(records)]


@dataclass(frozen=True, eq=False)
class WindowJob:
    """Window replays for the task engine (:class:`.task_engine.Job`): a window's record file is
    ``<window task_id>-<tag>.json`` (``tag``: the policies, their weights and the config), up
    to ``batch`` windows of a unit run side by side in one SUMO simulation
    (:func:`run_windows`), each record given as the window's runs end."""

    maneuvers: pd.DataFrame
    policy_names: tuple[str, ...]
    config: rp.ReplayConfig
    tag: str
    batch: int = DEFAULT_BATCH
    # the planners, loaded by each process that runs windows, once
    loaded: dict = field(default_factory=dict, repr=False)

    def task_id(self, window: Window) -> str:
        return f"{window.task_id}-{self.tag}"

    def units(self, todo: list[Window], workers: int) -> list[tuple[Window, ...]]:
        return even_units(todo, self.batch, workers)

    def run_unit(self, unit: tuple[Window, ...], emit: Emit) -> None:
        run_windows(unit, self.maneuvers, self.policies(), self.config, emit)

    def failed(self, window: Window, error: str) -> dict:
        return _failed(window, error)

    def policies(self) -> dict:
        """The planners by name (with the config's time-gap setting), loaded once per process."""
        from safeil_sumo.planners import registry as pol

        if not self.loaded:
            planners = {name: pol.load_for_replay(name) for name in self.policy_names}
            self.loaded.update(with_setting(planners, self.config.time_gap_s,
                                            self.config.standstill_m))
        return self.loaded


def job_tag(policy_names: Sequence[str], config: rp.ReplayConfig, adapted: bool) -> str:
    """What a window's result depends on besides the window: the policies (with their weights'
    fingerprints) and the config, and how planners are adapted (``adapted``), so a rerun with
    other policies, settings or a retrained model never reuses a stale result."""
    policies = sorted(f"{n}@{planner_registry.fingerprint(n)}" for n in policy_names)
    key = [policies, repr(config)]
    if adapted:
        key.append(ADAPTATION_METHOD)
    return hashlib.sha256(json.dumps(key).encode()).hexdigest()[:8]


def replay_all(maneuvers: pd.DataFrame, wins: list[Window], policy_names: list[str],
               out_dir: Path, config: rp.ReplayConfig | None = None, workers: int = 1,
               progress: bool = True, batch: int = DEFAULT_BATCH,
               scheduler: str | None = None, retry_failed: bool = False,
               task_timeout_s: float | None = None) -> list[dict]:
    """Run every window not done yet in ``out_dir/tasks``; return all records (window order).
    ``batch`` > 1: up to ``batch`` windows per worker task run side by side in one SUMO
    simulation (:func:`run_windows`; the same records); 1: one simulation per run. The windows
    run on the task engine (:func:`.task_engine.execute`, as a :class:`WindowJob`): in this
    process (``workers=1``), in ``workers`` local processes or on the Dask cluster at
    ``scheduler``; each window's record is written as its runs end (a Ctrl-C keeps them).
    ``retry_failed``: windows recorded failed run again; ``task_timeout_s`` [s]: a local worker
    running longer is killed and its windows without a record are recorded failed."""
    config = config or rp.ReplayConfig()
    tag = job_tag(policy_names, config, any(w.adapt_s for w in wins))
    job = WindowJob(maneuvers, tuple(policy_names), config, tag, batch)
    tasks = Path(out_dir) / "tasks"
    execute(wins, job, tasks, workers, scheduler, progress, "replay", "window", retry_failed,
            task_timeout_s)
    records = (read_record(record_path(tasks, job, w)) for w in wins)
    return [r for r in records if r is not None]


def table(records: list[dict]) -> pd.DataFrame:
    """One row per window x policy (failed windows: one row with the error)."""
    rows = []
    for r in records:
        base = {k: r.get(k) for k in ("maneuver_id", "start_s", "duration_s", "mean_speed_mps",
                                      "mean_gap_m", *INSTRUMENT_KEYS, "status")}
        # records written before drivers were recorded: the same rule
        base["driver"] = r.get("driver") or driver_id(str(r["maneuver_id"]))
        if r["status"] != "ok":
            rows.append({**base, "error": r.get("error")})
            continue
        rows += [{**base, **m} for m in r["metrics"]]
    df = pd.DataFrame(rows)
    for col in ("flag", "human_flag"):
        if col in df:
            df[col] = df[col].fillna("")
    return df


def bootstrap_ci(values: np.ndarray, stat=np.median, samples: int = BOOTSTRAP_SAMPLES,
                 seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap interval of ``stat`` (seeded: the same values give the same CI)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(v), size=(samples, len(v)))
    stats = stat(v[idx], axis=1)
    lo, hi = np.quantile(stats, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def _column(g: pd.DataFrame, name: str) -> np.ndarray:
    """``g[name]`` as floats; NaN where a table (records of an older version) lacks it."""
    return g[name].to_numpy(float) if name in g else np.full(len(g), np.nan)


def _nan_stat(stat, values: np.ndarray) -> float:
    """``stat`` (np.nanmedian, np.nanmean, ...) of the finite values; NaN when there is none."""
    v = np.asarray(values, float)
    return float(stat(v)) if np.isfinite(v).any() else math.nan


def literature_summary(g: pd.DataFrame) -> dict:
    """What the car-following literature reports, over the windows ``g`` (rows of
    :func:`table`, one group): the worst window's gap RMSE [m] and its :func:`window_id`, the
    spacing RMSPE's median and mean [-, fractions], the time-gap RMSE's median [s], the mean
    time-gap error's median and mean [s] (policy - human), and the windows whose run ended
    before the recording (a collision, off the road, at the road's end: compared up to there)."""
    gap = _column(g, "rmse_gap")
    worst = int(np.nanargmax(gap)) if np.isfinite(gap).any() else None
    return {
        "gap_rmse_max_m": math.nan if worst is None else float(gap[worst]),
        "gap_rmse_worst": "" if worst is None else window_id(
            str(g["maneuver_id"].iloc[worst]), float(g["start_s"].iloc[worst])),
        "spacing_rmspe_median": _nan_stat(np.nanmedian, _column(g, "rmspe_gap")),
        "spacing_rmspe_mean": _nan_stat(np.nanmean, _column(g, "rmspe_gap")),
        "time_gap_rmse_median_s": _nan_stat(np.nanmedian, _column(g, "rmse_headway")),
        "time_gap_error_median_s": _nan_stat(np.nanmedian, _column(g, "bias_headway")),
        "time_gap_error_mean_s": _nan_stat(np.nanmean, _column(g, "bias_headway")),
        "ended_early": int((_column(g, "coverage") < 1.0).sum()),
    }


def aggregate(df: pd.DataFrame, seed: int = 0, by: Sequence[str] = ("policy",)
              ) -> pd.DataFrame:
    """Per policy (or per group of the columns ``by``, e.g. ``("policy", "driver")``): windows,
    gap RMSE median/mean with bootstrap 95 % CIs, :func:`literature_summary`, speed and lateral
    RMSE medians, time-gap W1 median, flags, flags in windows whose recording has no flag of its
    own, and collisions: windows that end in one or have one as their first flag (a TTC flag
    usually comes first)."""
    ok = df[df["status"] == "ok"]
    rows = []
    for key, g in ok.groupby(list(by), sort=False):
        gap = g["rmse_gap"].to_numpy(float)
        med_lo, med_hi = bootstrap_ci(gap, np.median, seed=seed)
        mean_lo, mean_hi = bootstrap_ci(gap, np.mean, seed=seed)
        rows.append({
            **dict(zip(by, key, strict=True)), "windows": len(g),
            "gap_rmse_median_m": float(np.nanmedian(gap)), "gap_rmse_median_lo": med_lo,
            "gap_rmse_median_hi": med_hi, "gap_rmse_mean_m": float(np.nanmean(gap)),
            "gap_rmse_mean_lo": mean_lo, "gap_rmse_mean_hi": mean_hi,
            "speed_rmse_median_mps": float(np.nanmedian(g["rmse_v"])),
            "lateral_rmse_median_m": float(np.nanmedian(g["rmse_d"])),
            "time_gap_w1_median_s": float(np.nanmedian(g["w1_headway"])),
            **literature_summary(g),
            "flags": int((g["flag"] != "").sum()),
            # a flag in a window whose recording has none of its own (replay.human_flag)
            "flags_beyond_human": int(((g["flag"] != "") & (g["human_flag"] == "")).sum()),
            # windows where either says collision (each window counted once)
            "collisions": int(((g["flag"] == "collision")
                               | (g["end_reason"] == "collision")).sum()),
        })
    return pd.DataFrame(rows)


def plot(records: list[dict], df: pd.DataFrame, path: Path, title: str = "") -> None:
    """Gap-RMSE CDF per policy, and the time-gap histograms of the human and each policy."""
    ok = df[df["status"] == "ok"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.2))
    for policy, g in ok.groupby("policy", sort=False):
        v = np.sort(g["rmse_gap"].dropna().to_numpy(float))
        if len(v):
            a.step(v, np.arange(1, len(v) + 1) / len(v), where="post",
                   label=f"{policy} (median {np.median(v):.2f} m)")
    a.axvline(0.78, color="k", ls=":", lw=1, label="paper, SafeIL: 0.78 m (one window)")
    a.set_xscale("log")
    a.set_xlabel("gap RMSE vs the human over a window [m]")
    a.set_ylabel("share of windows")
    a.legend(fontsize=7)
    a.set_title(f"{title} closed-loop replays: gap RMSE CDF", fontsize=9)
    sums: dict[str, np.ndarray] = {}
    for r in records:
        for name, h in r.get("headway_hist", {}).items():
            sums[name] = sums.get(name, 0) + np.asarray(h, float)
    centres = 0.5 * (HEADWAY_BINS[1:] + HEADWAY_BINS[:-1])
    for name, h in sums.items():
        if h.sum() > 0:
            b.plot(centres, h / h.sum() / np.diff(HEADWAY_BINS), lw=2.5 if name == "human" else 1.2,
                   color="k" if name == "human" else None, label=name)
    b.set_xlabel("time gap [s]")
    b.set_ylabel("density [1/s]")
    b.legend(fontsize=7)
    b.set_title("time gap: human vs planners (all windows)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write(out_dir: Path, records: list[dict], extra_manifest: dict, seed: int = 0,
          title: str = "") -> tuple[pd.DataFrame, pd.DataFrame]:
    """``windows.csv`` (per window x policy), ``aggregate.csv`` (per policy),
    ``aggregate_by_driver.csv`` (per policy and driver), ``replay_all.png``, ``manifest.json``;
    returns (per-window table, aggregate)."""
    df = table(records)
    agg = aggregate(df, seed) if len(df) and "policy" in df else pd.DataFrame()
    by_driver = (aggregate(df, seed, ("policy", "driver")) if len(df) and "policy" in df
                 else pd.DataFrame())
    with atomic_path(out_dir / "windows.csv") as tmp:
        df.to_csv(tmp, index=False)
    with atomic_path(out_dir / "aggregate.csv") as tmp:
        agg.to_csv(tmp, index=False)
    with atomic_path(out_dir / "aggregate_by_driver.csv") as tmp:
        by_driver.to_csv(tmp, index=False)
    if len(agg):
        plot(records, df, out_dir / "replay_all.png", title)
    outputs.write_json(out_dir / "manifest.json", outputs.manifest(
        {**extra_manifest, "windows": len(records)}, [seed]))
    return df, agg
