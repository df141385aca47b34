"""One sweep engine for every sweep: a list of :class:`Task` -> one result file per task.

- A :class:`Task` is a JSON-able description of one closed-loop task; its random draws
  (leader speed, initial gap) come from ``scenario_seed(master_seed, index)`` only, so task i is
  identical alone or in a sweep of any size, sequential or parallel, and across resumes.
- :func:`run_task` runs one task and never raises (an exception becomes ``status="failed"``).
- :func:`run_sweep` runs the tasks on the task engine (:mod:`.task_engine`, as :class:`SweepJob`):
  in-process (``workers=1``), in local worker processes (one libsumo per process:
  docs/architecture.md) or on a Dask cluster; every result is written atomically to
  ``out_dir/tasks/<task_id>.json`` as its scenario ends, also inside a batch. Rerunning a sweep
  skips tasks that have a result file, so a sweep that stopped (Ctrl-C, crash, killed worker) is
  resumed by rerunning it.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.experiments import outputs
from safeil_sumo.experiments.task_engine import (
    STATUS_FAILED,
    STATUS_OK,
    Emit,
    deferred_interrupt,
    even_units,
    execute,
    read_record,
)
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import Task, build_scenario, resolve_road

TIMING_FIELDS = ("wall_time_s", "steps_per_s", "task_wall_time_s")  # differ run to run

TaskFn = Callable[["Task"], dict]


def task_id(task: Task) -> str:
    """Short stable id: a readable prefix (only ``[A-Za-z0-9_-]``) + a hash of the task's JSON.

    The prefix is sanitised, so a task id can never leave the tasks folder.
    """
    text = json.dumps(task.to_json(), sort_keys=True, separators=(",", ":"))
    # the policy's weights too: a retrained model never resumes the model before's results
    text += "|" + planner_registry.fingerprint(task.planner.policy)
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    net = Path(task.scenario.net).name.removesuffix(".net.xml")
    policy = Path(task.planner.policy).name.removesuffix(".safetensors")
    prefix = f"{net}_{policy}{'_f' if task.planner.safety_filter else ''}"
    prefix = re.sub(r"[^A-Za-z0-9_]+", "_", prefix)[:40]
    return f"{prefix}-{task.scenario.index:05d}-{digest}"


def spec_fields(task: Task) -> dict[str, Any]:
    """The task flattened for a table row (ranges as ``*_low`` / ``*_high`` columns)."""
    row = task.to_json()
    lo, hi = row.pop("leader_speed_range_mps")
    row["leader_speed_low_mps"], row["leader_speed_high_mps"] = lo, hi
    row.pop("initial_gap_m")  # the drawn gap is the summary's initial_gap_m
    row["gap_low_m"], row["gap_high_m"] = task.scenario.gap_range_m
    if "route" in row:  # one table cell
        row["route"] = " ".join(row["route"])
    if "style_changes" in row:  # one table cell, its JSON
        row["style_changes"] = json.dumps(row["style_changes"])
    return row


# -- one task ------------------------------------------------------------------------------------

_SHARED_POLICIES: dict[tuple, Any] = {}


def _load_policy(planner: PlannerRef, shared: bool = False):
    """The task's planner, loaded fresh (no state, e.g. filter counters, leaks between tasks);
    ``shared``: a batch shares the (stateless) planner itself, each task its own filter. A
    style that changes during the run is state: such a planner is the task's own."""
    if not shared or planner.style_changes:
        return planner.load()
    key = (planner.policy, planner.time_gap_s, planner.standstill_m)
    if key not in _SHARED_POLICIES:
        _SHARED_POLICIES[key] = planner.load_unfiltered()
    return planner.wrap(_SHARED_POLICIES[key])


def failed_record(task: Task, error: str) -> dict[str, Any]:
    """The record of a task that produced no summary."""
    return {"task_id": task_id(task), "status": STATUS_FAILED, "error": error,
            **spec_fields(task)}


def run_task(task: Task,
             extras: Callable[[Task, Any], dict] | None = None) -> dict[str, Any]:
    """Run one task closed-loop; returns a flat record (summary + task fields). Never raises.

    ``status`` is ``"ok"``, or ``"failed"`` with ``error="Type: message"`` when the task could
    not be built or the loop ended with an exception. ``extras(task, rollout)`` (a module-level
    function, e.g. via ``functools.partial(run_task, extras=f)`` as a sweep's ``task_fn``) adds
    JSON-able fields computed from the per-step log, which is not kept otherwise.
    """
    wall0 = time.perf_counter()
    try:
        from safeil_sumo.sim.runner import run_scenario

        road, scenario, policy, loop = _task_parts(task)
        rollout = run_scenario(scenario, policy, loop)
        added = extras(task, rollout) if extras is not None else {}
    except Exception as exc:  # noqa: BLE001 - a record, never an exception: the sweep goes on
        return failed_record(task, f"{type(exc).__name__}: {exc}")
    return _record(task, road, scenario, policy, rollout, time.perf_counter() - wall0, added)


def run_tasks(tasks: Sequence[Task], on_record: Emit | None = None
              ) -> list[dict[str, Any]]:
    """The records of ``tasks`` run side by side in ONE SUMO simulation (``sim.batch``), in
    order; one task is :func:`run_task`. ``on_record(k, record)`` as the k-th task's record is
    made (a scenario that ended, or a task that cannot be built; a Ctrl-C waits for it). Never
    raises: a task that cannot be built, or a batch that fails, gives failed records. Specs of a
    batch share their network and loop settings (:func:`batch_key`)."""
    records: list[dict[str, Any] | None] = [None] * len(tasks)

    def give(k: int, record: dict[str, Any]) -> None:
        records[k] = record
        if on_record is not None:
            on_record(k, record)

    if len(tasks) == 1:
        record = run_task(tasks[0])
        give(0, record)
        return [record]
    wall0 = time.perf_counter()
    parts = []
    for k, task in enumerate(tasks):
        try:
            parts.append((k, *_task_parts(task, shared=True)))
        except Exception as exc:  # noqa: BLE001 - a record, never an exception
            give(k, failed_record(task, f"{type(exc).__name__}: {exc}"))
    if parts:
        _run_parts(tasks, parts, time.perf_counter() - wall0, give)
    # run_batch reports every scenario it was given (on_done), so none is left without one
    return [failed_record(tasks[k], "NoRecord: the batch ended without this task's record")
            if r is None else r for k, r in enumerate(records)]


def _run_parts(tasks: Sequence[Task], parts: list, build_s: float,
               give: Callable[[int, dict[str, Any]], None]) -> None:
    """The buildable tasks' ``parts`` (``(k, road, scenario, policy, loop)``) in one
    ``run_batch``, ``give(k, record)`` as each ends (a batch that fails: failed records for
    those left). ``build_s`` [s]: the time building the batch took."""
    from safeil_sumo.sim.batch import run_batch
    from safeil_sumo.sim.rollout_log import SUMMARY_COLUMNS

    loop = parts[0][4]  # the tasks of a batch share their loop settings (batch_key)
    wall = build_s / len(tasks)  # building, per task
    given: set[int] = set()

    def record(i: int, rollout) -> None:  # as each scenario ends: its log is freed then
        k, road, scenario, policy, _ = parts[i]
        with deferred_interrupt():  # an ended scenario's record is made and given
            given.add(k)
            give(k, _record(tasks[k], road, scenario, policy, rollout,
                            wall + rollout.summary["wall_time_s"]))

    try:
        # a record reads the summary columns only: 12 of the log's 46, so batches 4x
        # larger fit the same memory
        run_batch([p[2] for p in parts], [p[3] for p in parts], loop, on_done=record,
                  keep_logs=False, log_columns=SUMMARY_COLUMNS)
    except Exception as exc:  # noqa: BLE001
        for k, *_ in parts:
            if k not in given:
                give(k, failed_record(tasks[k], f"{type(exc).__name__}: {exc}"))


# scenarios per SUMO simulation in sweeps by default (``sweep --batch``): measured on curved500
# (docs/performance.md): 1,000 scenarios on 2 workers in 37 s at 256, 42 s at 128, 52 s at 64;
# memory grows with it (a scenario's summary log, ~0.4 MB per 40 s, stays until it ends)
DEFAULT_BATCH = 256


def batch_key(task: Task) -> tuple | None:
    """Specs with equal keys can share a batch; None: this one runs alone (traffic: SUMO's
    own vehicles are per simulation)."""
    s = task.scenario
    if s.traffic:
        return None
    return (s.net, s.route, s.from_km, s.to_km, s.lane, task.planner, task.loop)


def batches(tasks: Sequence[Task], size: int, workers: int = 1
            ) -> list[tuple[Task, ...]]:
    """``tasks`` grouped into batches sharing a :func:`batch_key`, in order of their first
    task, each group in :func:`even_units` (10 tasks on 2 workers: two batches of 5, not one
    of 10)."""
    if size < 1:
        raise ValueError(f"batch size must be >= 1, got {size}")
    groups: dict[Any, list[Task]] = {}
    for k, task in enumerate(tasks):
        key = batch_key(task)
        groups.setdefault(key if key is not None else ("alone", k), []).append(task)
    return [unit for g in groups.values() for unit in even_units(g, size, workers)]


def _task_parts(task: Task, shared: bool = False):
    """``(road, scenario, policy, loop)`` of a task. ``shared``: planners of the same name are
    one object (batched plan calls; a safety filter still gets its own wrapper per task)."""
    s = task.scenario
    road = resolve_road(s.net, s.route, s.from_km, s.to_km, s.lane)
    return road, build_scenario(s, road), _load_policy(task.planner, shared), task.loop


def _record(task: Task, road, scenario, policy, rollout, wall_s: float,
            extras: dict | None = None) -> dict[str, Any]:
    """The flat record of a finished task (``extras``: more fields, see :func:`run_task`)."""
    summary = dict(rollout.summary)
    if len(rollout.log):  # how it responded to its leader (the leader-response suite's)
        from safeil_sumo.experiments.suite import response_metrics

        summary.update({f"resp_{k}": v for k, v in response_metrics(rollout.log).items()})
    summary.update(extras or {})
    failed = summary.get("end_reason") == "error"
    record = {"task_id": task_id(task), "status": STATUS_FAILED if failed else STATUS_OK,
              **spec_fields(task)}
    summary["policy_name"] = summary.pop("policy")  # e.g. "safeil+filter"; task keeps "safeil"
    summary["net_name"] = summary.pop("net")
    record.update(summary)
    # the draw (braking: pre-brake); with traffic there is no scripted leader
    scripted = scenario.leader
    record["leader_speed0_mps"] = scripted.initial_speed if scripted is not None else math.nan
    record["leader_label"] = scripted.label if scripted is not None else "traffic"
    record["radius_m"] = road.meta.get("radius_m", math.nan)
    if task.planner.safety_filter:
        record["filter_interventions"] = int(getattr(policy, "interventions", 0))
        record["filter_intervention_rate"] = float(getattr(policy, "intervention_rate", 0.0))
    record["task_wall_time_s"] = wall_s
    return record


def _safe_call(task_fn: TaskFn, task: Task) -> dict[str, Any]:
    """``task_fn(task)``, with any exception turned into a failed record."""
    try:
        record = task_fn(task)
        if not isinstance(record, dict):
            raise TypeError(f"task function returned {type(record).__name__}, not dict")
        return record
    except Exception as exc:  # noqa: BLE001 - any task error becomes a failed record
        return failed_record(task, f"{type(exc).__name__}: {exc}")


@dataclass(frozen=True)
class SweepJob:
    """Task tasks for the task engine (:class:`.task_engine.Job`): a task's record file is
    ``<task_id>.json``; with ``batch`` > 1 the tasks that can share a simulation
    (:func:`batch_key`) run up to ``batch`` at a time in one (:func:`run_tasks`, for the default
    ``task_fn``), each record given as its scenario ends; else ``task_fn`` per task.
    ``prepare_nets``: build the pending tasks' curved<R> nets once before the workers start.
    ``mixed_nets``: the tasks share their planner and loop settings by construction (a
    falsification batch), so units are even slices of them in order, their nets mixed in one
    simulation (``sim.batch.run_batch`` lays each on its own copy of its net)."""

    task_fn: TaskFn = run_task
    batch: int = 1
    prepare_nets: bool = False
    mixed_nets: bool = False

    def task_id(self, task: Task) -> str:
        return task_id(task)

    def units(self, todo: list[Task], workers: int) -> list[tuple[Task, ...]]:
        if self.prepare_nets:
            _prepare_nets(todo)
        if self.batch == 1:
            return [(s,) for s in todo]
        if self.mixed_nets:
            return even_units(todo, self.batch, workers)
        return batches(todo, self.batch, workers)

    def run_unit(self, unit: tuple[Task, ...], emit: Emit) -> None:
        if self.task_fn is run_task:  # one simulation for the unit (one task: run_task)
            run_tasks(unit, on_record=emit)
            return
        for k, task in enumerate(unit):
            emit(k, _safe_call(self.task_fn, task))

    def failed(self, task: Task, error: str) -> dict[str, Any]:
        return failed_record(task, error)


# -- result files --------------------------------------------------------------------------------

def tasks_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "tasks"


# -- the sweep -----------------------------------------------------------------------------------

def run_sweep(
    tasks: Iterable[Task],
    out_dir: str | Path,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
    retry_failed: bool = False,
    task_fn: TaskFn = run_task,
    task_timeout_s: float | None = None,
    manifest_extra: dict[str, Any] | None = None,
    batch: int = 1,
) -> pd.DataFrame:
    """Run every task that has no result file yet; return the summary of all tasks, in order.

    ``workers=1``: in this process, one after another. ``workers>1``: that many local worker
    processes ('fork' on Linux), each running one task at a time; a worker that dies (crash,
    ``kill -9``, or ``task_timeout_s`` [s] exceeded) has its task recorded as failed and is
    replaced. ``scheduler="tcp://host:port"``: tasks go to that Dask cluster. Failed records count
    as done unless ``retry_failed``. ``task_fn`` (default :func:`run_task`) is a seam for tests.
    ``batch`` > 1: tasks that can share a simulation (:func:`batch_key`) run up to ``batch`` at
    a time in one SUMO simulation (:func:`run_tasks`); a worker that dies costs the tasks of its
    batch that had not ended, and ``task_timeout_s`` is per batch then. The tasks run on the
    task engine (:func:`.task_engine.execute`, as a :class:`SweepJob`).

    Writes ``tasks/<task_id>.json`` per task as it ends (a Ctrl-C keeps every task that ended,
    also inside a batch), then ``summary.csv``, ``summary.json`` and ``manifest.json``.
    """
    tasks = list(dict.fromkeys(tasks))  # a task listed twice is one task
    out_dir = Path(out_dir)
    job = SweepJob(task_fn, batch, prepare_nets=scheduler is None and workers > 1)
    todo = execute(tasks, job, tasks_dir(out_dir), workers, scheduler, progress, "sweep",
                   "task", retry_failed, task_timeout_s)

    summary = collect(tasks, out_dir)
    with atomic_path(out_dir / "summary.csv") as tmp:  # a Ctrl-C here keeps the old summary
        summary.to_csv(tmp, index=False)
    outputs.write_json(out_dir / "summary.json", summary.to_dict(orient="records"))
    config = {"tasks": len(tasks), "run_now": len(todo), "workers": workers, "batch": batch,
              "scheduler": scheduler, "retry_failed": retry_failed,
              "specs": [s.to_json() for s in tasks], **(manifest_extra or {})}
    from safeil_sumo.scenarios.safety import scenario_seed

    seeds = [scenario_seed(t.scenario.master_seed, t.scenario.index) for t in tasks]
    outputs.write_json(out_dir / "manifest.json", outputs.manifest(config, seeds))
    return summary


def collect(tasks: Sequence[Task], out_dir: str | Path) -> pd.DataFrame:
    """The records of ``tasks`` found in ``out_dir/tasks``, in task order (missing ones skipped)."""
    tdir = tasks_dir(Path(out_dir))
    rows = []
    for order, task in enumerate(tasks):
        record = read_record(tdir / f"{task_id(task)}.json")
        if record is not None:
            rows.append({"task_order": order, **record})
    return pd.DataFrame(rows)


def _prepare_nets(tasks: Sequence[Task]) -> None:
    # build curved<R> networks once here (netconvert, no libsumo) instead of racing in workers;
    # a net that fails is left to its tasks, which record the error
    from safeil_sumo.roads.catalogue import resolve_net

    for net in dict.fromkeys(t.scenario.net for t in tasks):
        with suppress(Exception):  # the tasks of this net record the error
            resolve_net(net)


def comparable(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` without fields that vary between identical runs (timing)."""
    drop = [c for c in TIMING_FIELDS if c in summary.columns]
    return summary.drop(columns=drop).reset_index(drop=True)


def load_specs(path: str | Path) -> list[Task]:
    """Tasks from a JSON list (e.g. the ``specs`` of a sweep's ``manifest.json``)."""
    data = json.loads(Path(path).read_text())
    if isinstance(data, dict):
        data = data.get("config", data).get("specs", [])
    return [Task.from_json(d) for d in data]


__all__ = [
    "DEFAULT_BATCH",
    "batches",
    "collect",
    "comparable",
    "load_specs",
    "run_sweep",
    "run_task",
    "run_tasks",
    "spec_fields",
    "task_id",
]
