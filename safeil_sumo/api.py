"""The Python API: run a planner in SUMO and get the log as a DataFrame, in a few lines.

    from safeil_sumo import api

    result = api.run("curved500", policy="safeil", scenarios=2)
    result.summary          # one row per scenario (flags, path completed, min TTC, ...)
    result.log              # the per-step log of every scenario (column ``scenario``)

``policy`` is a shipped name (``safeil``, ``safeil_paper``, ``bc``, ``analytic``, ``idm``), a
checkpoint or IDM model path, or ANY object with the :class:`~safeil_sumo.core.policy.Policy` protocol
(``name``, ``horizon`` [s], ``plan(features (..., 9)) -> (..., 3, 2)``), so your own planner plugs
in. Scenarios are those of ``python -m safeil_sumo.run`` / ``sweep`` (the same seeds give the same
runs); :func:`sweep` and :func:`replay` wrap the sweep engine and the replay of many windows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm import tqdm

from safeil_sumo.core.policy import Policy
from safeil_sumo.experiments.maneuver_replay import ReplayConfig
from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH, run_sweep
from safeil_sumo.experiments.window_replays import DEFAULT_BATCH as REPLAY_BATCH
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.roads.road import Road
from safeil_sumo.scenarios.spec import ScenarioSpec, Task, build_scenario
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.vehicle import VehicleParams


@dataclass(frozen=True)
class RunResult:
    """``summary``: one row per scenario; ``log``: every step of every scenario (column
    ``scenario``); ``scenarios``: the scenarios that ran."""

    summary: pd.DataFrame
    log: pd.DataFrame
    scenarios: tuple[Scenario, ...] = ()


def load_policy(policy: str | Policy) -> Policy:
    """A shipped name, a checkpoint / IDM model path, or a Policy object (returned as it is)."""
    if isinstance(policy, str):
        return planner_registry.load(policy)
    if not isinstance(policy, Policy):
        raise TypeError(f"{policy!r} is no Policy: it needs name, horizon and plan(features)")
    return policy


def road(net: str = "curved500", route: Sequence[str] = (), from_km: float | None = None,
         to_km: float | None = None, lane: str | int | None = None) -> Road:
    """The road of a catalogue name (``curved500``, ``straight``, ``curved<R>``) or a
    ``.net.xml`` path, read once per process; on a multi-edge net, along ``route`` (SUMO edge
    ids in driving order, see :func:`safeil_sumo.roads.route.load_route`); ``n74``: the
    stretch of direction A between the kilometre posts ``from_km`` and ``to_km`` (default: all
    of it, see :func:`safeil_sumo.roads.n74.stretch_road`). ``lane``: the ego's lane,
    ``right``/``left`` on n74, a SUMO lane index of the first edge on a ``.net.xml`` (default:
    the middle lane)."""
    from safeil_sumo.scenarios.spec import resolve_road

    return resolve_road(net, tuple(route), from_km, to_km, "" if lane is None else str(lane))


def scenario(net: str = "curved500", index: int = 0, seed: int = 0, **spec: Any) -> Scenario:
    """Scenario ``index`` of master ``seed`` on ``net``; ``spec`` takes any
    :class:`~safeil_sumo.scenarios.spec.ScenarioSpec` field (``leader_kind="recorded"``,
    ``leader_profile="ngsim"``, ``leader_speed_range_mps=(20, 25)``, ``initial_gap_m=30``,
    ``route=("E0", "E1")``, ...)."""
    sc = ScenarioSpec(net=net, index=index, master_seed=seed, **spec)
    return build_scenario(sc, road(net, sc.route, sc.from_km, sc.to_km, sc.lane))


def build_scenarios(net: str = "curved500", count: int = 10, seed: int = 0,
                    **spec: Any) -> list[Scenario]:
    """Scenarios ``0..count-1`` of master ``seed`` (the sweep's builder: scenario i of a run is
    task i of a sweep)."""
    return [scenario(net, i, seed, **spec) for i in range(count)]


def run_scenarios(scenarios: Sequence[Scenario], policy: str | Policy,
                  loop: LoopConfig | None = None, vehicle: VehicleParams | None = None,
                  progress: bool = False) -> RunResult:
    """Run each scenario closed loop (one libsumo per scenario, in turn); a sumo-gui screenshot
    (``loop.gui_screenshot``) is taken in the first only."""
    planner = load_policy(policy)
    loop = loop or LoopConfig()
    vehicle = vehicle or VehicleParams()
    rows, logs = [], []
    bar = tqdm(scenarios, desc=planner.name, unit="scenario", disable=not progress or None)
    for i, sc in enumerate(bar):
        rollout = run_scenario(sc, planner, replace(loop, gui_screenshot=None) if i else loop,
                               vehicle)
        rows.append(rollout.summary)
        logs.append(rollout.log.assign(scenario=sc.name))
    return RunResult(pd.DataFrame(rows), pd.concat(logs, ignore_index=True), tuple(scenarios))


def styled_policy(policy: str | Policy, time_gap_s: float | None = None,
                  standstill_m: float | None = None,
                  style_changes: Sequence[Sequence[float | None]] = ()) -> Policy:
    """``policy`` (as :func:`load_policy` takes it) set to a driver's style: the time gap
    ``time_gap_s`` [s] and standstill distance ``standstill_m`` [m] of the steady gap's line
    ``s0 + T v`` (:func:`~safeil_sumo.planners.registry.with_time_gap`; a Policy object given is
    set in place where its setting is in place), changing during each run at ``style_changes``
    ``((t_s [s], time_gap_s [s], standstill_m [m] or None), ...)`` (a
    :class:`~safeil_sumo.planners.registry.ScheduledStyle`). Only a planner with a time-gap
    setting (a style-conditioned checkpoint, the IDM) takes a style: ``PolicyError``, as for a
    value it refuses; ``ValueError`` for a malformed one."""
    changes = planner_registry.checked_style_changes(style_changes)
    if isinstance(policy, str):
        return PlannerRef(policy, time_gap_s=time_gap_s, standstill_m=standstill_m,
                          style_changes=changes).load()
    planner = load_policy(policy)
    # the values checked as a task's
    ref = PlannerRef(planner.name, time_gap_s=time_gap_s, standstill_m=standstill_m)
    if ref.time_gap_s is not None:
        planner = planner_registry.with_time_gap(planner, ref.time_gap_s, ref.standstill_m)
    if changes:
        planner = planner_registry.ScheduledStyle(planner, changes)
    return planner


def run(net: str = "curved500", policy: str | Policy = "safeil", scenarios: int = 10,
        seed: int = 0, loop: LoopConfig | None = None, time_gap_s: float | None = None,
        standstill_m: float | None = None,
        style_changes: Sequence[Sequence[float | None]] = (), **spec: Any) -> RunResult:
    """Run ``scenarios`` scenarios (indices 0..n-1 of master ``seed``) closed loop in libsumo.

    A driver's style (:func:`styled_policy`): ``time_gap_s`` [s] and ``standstill_m`` [m], the
    steady gap's line ``s0 + T v`` from the start; ``style_changes`` ``[(t_s, time_gap_s,
    standstill_m), ...]`` ([s], [s], [m] or None), each set at the first decision at or after
    ``t_s`` of each scenario's time, e.g. ``api.run("straight", "idm", time_gap_s=1.0,
    style_changes=[(50.0, 2.5, 2.0)])``."""
    # a bad policy or style fails before any scenario is built
    planner = styled_policy(policy, time_gap_s, standstill_m, style_changes)
    return run_scenarios(build_scenarios(net, scenarios, seed, **spec), planner, loop)


def policy_names(policy: str | Sequence[str]) -> list[str]:
    """``policy=`` of :func:`sweep` and :func:`replay`, as the CLIs' ``--policy``: one name or
    path, or several."""
    names = [policy] if isinstance(policy, (str, Path)) else list(policy)
    if not names or not all(isinstance(n, (str, Path)) for n in names):
        raise TypeError(f"policy must be a name or path, or a sequence of them, got {policy!r}")
    return [str(n) for n in names]


def sweep(policy: str | Sequence[str], out: str | Path, scenarios: int = 10,
          nets: Sequence[str] = ("curved500",), seed: int = 0, workers: int = 1,
          batch: int = DEFAULT_BATCH, scheduler: str | None = None,
          loop: LoopConfig | None = None, safety_filter: bool = False,
          time_gap_s: float | None = None, standstill_m: float | None = None,
          style_changes: Sequence[Sequence[float | None]] = (), **spec: Any) -> pd.DataFrame:
    """A resumable sweep (nets x policies x scenarios) written to ``out``; returns its summary
    (one row per task). Each task is a :class:`~safeil_sumo.scenarios.spec.Task`: its scenario
    takes ``spec`` (any ScenarioSpec field), its planner ``policy`` (a name or path, or several:
    they travel to worker processes) with ``safety_filter`` and a driver's style (as
    :func:`run`: ``time_gap_s`` [s], ``standstill_m`` [m], ``style_changes`` ``[(t_s [s],
    time_gap_s [s], standstill_m [m] or None), ...]``), its loop ``loop`` (the plan rate, stop
    on flag and the brake guard; default: as shipped). Up to ``batch`` scenarios share one
    SUMO simulation (1: one each; each task with style changes has a planner of its own). A
    planner without a time-gap setting refuses a style before any task runs (``PolicyError``).
    ``scheduler`` (``"tcp://host:port"``): the tasks run on that Dask cluster instead of
    ``workers`` local processes."""
    loop = loop or LoopConfig()
    tasks = [Task(ScenarioSpec(net=n, index=i, master_seed=seed, **spec),
                  PlannerRef(p, safety_filter, time_gap_s, standstill_m,
                             planner_registry.checked_style_changes(style_changes)),
                  loop)
             for n in nets for p in policy_names(policy) for i in range(scenarios)]
    if time_gap_s is not None or style_changes:  # a planner refuses a style before any task
        for planner in dict.fromkeys(t.planner for t in tasks):
            planner.load()
    return run_sweep(tasks, out, workers=workers, scheduler=scheduler, progress=False,
                     batch=batch)


def replay(source: str | pd.DataFrame, policy: str | Sequence[str], out: str | Path,
           maneuvers: str | Sequence[str] = "all", windows: str = "sliding",
           workers: int = 1, duration_s: float | None = None, stride_s: float = 20.0,
           config: ReplayConfig | None = None, progress: bool = False,
           name: str | None = None, manifest: dict | None = None, batch: int = REPLAY_BATCH,
           adapt_first_s: float = 0.0, scheduler: str | None = None,
           retry_failed: bool = False, task_timeout_s: float | None = None
           ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Replay every window of ``maneuvers`` (``"all"`` or ids) of ``source`` (``openacc``,
    ``ngsim``, a drive file, or an already processed maneuvers frame) with each ``policy`` (a
    name or path, or several; ``recorded`` for the human's own path): ``(per-window table,
    per-policy aggregate)``; ``duration_s`` [s]: the length of ``paper`` / ``sliding`` windows (None: 11 s),
    or a cap on each ``whole`` maneuver from its start (None: the whole maneuver); both also written to ``out`` with the plots; resumable. ``name`` titles the
    plots and messages (default: the source). Up to ``batch`` windows of a worker task run side
    by side in one SUMO simulation (1: one simulation per run; the same records).
    ``adapt_first_s`` [s] (``whole`` windows): the planners are adapted to each driver on the
    maneuver's first seconds, which are then not scored (``window_replays.adapt_planners``);
    not with ``config.time_gap_s``, the planners' time-gap setting for every window.
    ``scheduler`` (``"tcp://host:port"``): the windows run on that Dask cluster instead of
    ``workers`` local processes. ``retry_failed``: windows whose record says failed run again;
    ``task_timeout_s`` [s]: a local worker's task is killed (recorded failed) after that long."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source
    from safeil_sumo.experiments import window_replays as ra

    if isinstance(source, pd.DataFrame):
        rows = source
    else:
        rows, _ = process_drive(load_source(source), PipelineConfig(rate_hz=10.0))
    config = config or ReplayConfig()
    if config.time_gap_s is not None and adapt_first_s:
        raise ValueError("a time-gap setting (config.time_gap_s) and adapt_first_s exclude "
                         "each other: adapting sets each driver's time gap")
    name = name or (str(source) if isinstance(source, str) else "maneuvers")
    only = None if maneuvers == "all" else list(maneuvers)
    wins = ra.windows(rows, windows, duration_s, stride_s, only, adapt_first_s)
    if not wins:
        raise ra.rp.ReplayError(
            f"no maneuver of {name} is long enough for "
            + (f"{adapt_first_s:g} s of adaptation and {ra.MIN_SCORED_S:g} s scored"
               if adapt_first_s else f"a {duration_s or ra.rp.PAPER_DURATION_S:g} s window"))
    names = policy_names(policy)
    records = ra.replay_all(rows, wins, names, Path(out), config, workers,
                            progress=progress, batch=batch, scheduler=scheduler,
                            retry_failed=retry_failed, task_timeout_s=task_timeout_s)
    return ra.write(Path(out), records, manifest or {"source": name, "policies": names,
                                                     "windows_mode": windows},
                    seed=config.seed, title=name)
