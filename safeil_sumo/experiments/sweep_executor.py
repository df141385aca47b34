"""One sweep engine for every sweep: a list of :class:`ScenarioSpec` -> one result file per task.

- A :class:`ScenarioSpec` is a JSON-able description of one closed-loop task; its random draws
  (leader speed, initial gap) come from ``scenario_seed(master_seed, index)`` only, so task i is
  identical alone or in a sweep of any size, sequential or parallel, and across resumes.
- :func:`run_task` runs one spec and never raises (an exception becomes ``status="failed"``).
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
from safeil_sumo.scenarios.spec import ScenarioSpec, build_scenario, resolve_road

TIMING_FIELDS = ("wall_time_s", "steps_per_s", "task_wall_time_s")  # differ run to run

TaskFn = Callable[["ScenarioSpec"], dict]


def task_id(spec: ScenarioSpec) -> str:
    """Short stable id: a readable prefix (only ``[A-Za-z0-9_-]``) + a hash of the spec's JSON.

    The prefix is sanitised, so a task id can never leave the tasks folder.
    """
    text = json.dumps(spec.to_json(), sort_keys=True, separators=(",", ":"))
    # the policy's weights too: a retrained model never resumes the model before's results
    text += "|" + planner_registry.fingerprint(spec.policy)
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    net = Path(spec.net).name.removesuffix(".net.xml")
    policy = Path(spec.policy).name.removesuffix(".safetensors")
    prefix = f"{net}_{policy}{'_f' if spec.safety_filter else ''}"
    prefix = re.sub(r"[^A-Za-z0-9_]+", "_", prefix)[:40]
    return f"{prefix}-{spec.index:05d}-{digest}"


def spec_fields(spec: ScenarioSpec) -> dict[str, Any]:
    """The spec flattened for a table row (ranges as ``*_low`` / ``*_high`` columns)."""
    row = spec.to_json()
    lo, hi = row.pop("leader_speed_range_mps")
    row["leader_speed_low_mps"], row["leader_speed_high_mps"] = lo, hi
    row.pop("initial_gap_m")  # the drawn gap is the summary's initial_gap_m
    row["gap_low_m"], row["gap_high_m"] = spec.gap_range_m
    if "route" in row:  # one table cell
        row["route"] = " ".join(row["route"])
    return row


# -- one task ------------------------------------------------------------------------------------

_SHARED_POLICIES: dict[tuple, Any] = {}


def _load_policy(spec: ScenarioSpec, shared: bool = False):
    from safeil_sumo.planners import registry as planner_registry

    # loaded fresh for every task: no state (e.g. filter counters) leaks between tasks; a
    # batch shares the (stateless) planner itself
    def load():
        policy = planner_registry.load(spec.policy)
        return policy if spec.time_gap_s is None else planner_registry.with_time_gap(policy,
                                                                             spec.time_gap_s)

    if shared:
        key = (spec.policy, spec.time_gap_s)
        if key not in _SHARED_POLICIES:
            _SHARED_POLICIES[key] = load()
        policy = _SHARED_POLICIES[key]
    else:
        policy = load()
    if spec.safety_filter:
        from safeil_sumo.planners.safety_filter import SafetyFiltered  # lazily: optional component

        policy = SafetyFiltered(policy)
    return policy


def failed_record(spec: ScenarioSpec, error: str) -> dict[str, Any]:
    """The record of a task that produced no summary."""
    return {"task_id": task_id(spec), "status": STATUS_FAILED, "error": error,
            **spec_fields(spec)}


def run_task(spec: ScenarioSpec,
             extras: Callable[[ScenarioSpec, Any], dict] | None = None) -> dict[str, Any]:
    """Run one task closed-loop; returns a flat record (summary + spec fields). Never raises.

    ``status`` is ``"ok"``, or ``"failed"`` with ``error="Type: message"`` when the task could
    not be built or the loop ended with an exception. ``extras(spec, rollout)`` (a module-level
    function, e.g. via ``functools.partial(run_task, extras=f)`` as a sweep's ``task_fn``) adds
    JSON-able fields computed from the per-step log, which is not kept otherwise.
    """
    wall0 = time.perf_counter()
    try:
        from safeil_sumo.sim.runner import run_scenario

        road, scenario, policy, loop = _task_parts(spec)
        rollout = run_scenario(scenario, policy, loop)
        added = extras(spec, rollout) if extras is not None else {}
    except Exception as exc:  # noqa: BLE001 - a record, never an exception: the sweep goes on
        return failed_record(spec, f"{type(exc).__name__}: {exc}")
    return _record(spec, road, scenario, policy, rollout, time.perf_counter() - wall0, added)


def run_tasks(specs: Sequence[ScenarioSpec], on_record: Emit | None = None
              ) -> list[dict[str, Any]]:
    """The records of ``specs`` run side by side in ONE SUMO simulation (``sim.batch``), in
    order; one spec is :func:`run_task`. ``on_record(k, record)`` as the k-th spec's record is
    made (a scenario that ended, or a spec that cannot be built; a Ctrl-C waits for it). Never
    raises: a spec that cannot be built, or a batch that fails, gives failed records. Specs of a
    batch share their network and loop settings (:func:`batch_key`)."""
    records: list[dict[str, Any] | None] = [None] * len(specs)

    def give(k: int, record: dict[str, Any]) -> None:
        records[k] = record
        if on_record is not None:
            on_record(k, record)

    if len(specs) == 1:
        record = run_task(specs[0])
        give(0, record)
        return [record]
    wall0 = time.perf_counter()
    parts = []
    for k, spec in enumerate(specs):
        try:
            parts.append((k, *_task_parts(spec, shared=True)))
        except Exception as exc:  # noqa: BLE001 - a record, never an exception
            give(k, failed_record(spec, f"{type(exc).__name__}: {exc}"))
    if parts:
        _run_parts(specs, parts, time.perf_counter() - wall0, give)
    # run_batch reports every scenario it was given (on_done), so none is left without one
    return [failed_record(specs[k], "NoRecord: the batch ended without this task's record")
            if r is None else r for k, r in enumerate(records)]


def _run_parts(specs: Sequence[ScenarioSpec], parts: list, build_s: float,
               give: Callable[[int, dict[str, Any]], None]) -> None:
    """The buildable specs' ``parts`` (``(k, road, scenario, policy, loop)``) in one
    ``run_batch``, ``give(k, record)`` as each ends (a batch that fails: failed records for
    those left). ``build_s`` [s]: the time building the batch took."""
    from safeil_sumo.sim.batch import run_batch
    from safeil_sumo.sim.rollout_log import SUMMARY_COLUMNS

    loop = parts[0][4]  # the specs of a batch share their loop settings (batch_key)
    wall = build_s / len(specs)  # building, per task
    given: set[int] = set()

    def record(i: int, rollout) -> None:  # as each scenario ends: its log is freed then
        k, road, scenario, policy, _ = parts[i]
        with deferred_interrupt():  # an ended scenario's record is made and given
            given.add(k)
            give(k, _record(specs[k], road, scenario, policy, rollout,
                            wall + rollout.summary["wall_time_s"]))

    try:
        # a record reads the summary columns only: 12 of the log's 46, so batches 4x
        # larger fit the same memory
        run_batch([p[2] for p in parts], [p[3] for p in parts], loop, on_done=record,
                  keep_logs=False, log_columns=SUMMARY_COLUMNS)
    except Exception as exc:  # noqa: BLE001
        for k, *_ in parts:
            if k not in given:
                give(k, failed_record(specs[k], f"{type(exc).__name__}: {exc}"))


# scenarios per SUMO simulation in sweeps by default (``sweep --batch``): measured on curved500
# (docs/performance.md): 1,000 scenarios on 2 workers in 37 s at 256, 42 s at 128, 52 s at 64;
# memory grows with it (a scenario's summary log, ~0.4 MB per 40 s, stays until it ends)
DEFAULT_BATCH = 256


def batch_key(spec: ScenarioSpec) -> tuple | None:
    """Specs with equal keys can share a batch; None: this one runs alone (traffic: SUMO's
    own vehicles are per simulation)."""
    if spec.traffic:
        return None
    return (spec.net, spec.route, spec.from_km, spec.to_km, spec.lane, spec.policy,
            spec.time_gap_s, spec.safety_filter, spec.plan_rate_hz, spec.stop_on_flag,
            spec.brake_guard)


def batches(specs: Sequence[ScenarioSpec], size: int, workers: int = 1
            ) -> list[tuple[ScenarioSpec, ...]]:
    """``specs`` grouped into batches sharing a :func:`batch_key`, in order of their first
    spec, each group in :func:`even_units` (10 specs on 2 workers: two batches of 5, not one
    of 10)."""
    if size < 1:
        raise ValueError(f"batch size must be >= 1, got {size}")
    groups: dict[Any, list[ScenarioSpec]] = {}
    for k, spec in enumerate(specs):
        key = batch_key(spec)
        groups.setdefault(key if key is not None else ("alone", k), []).append(spec)
    return [unit for g in groups.values() for unit in even_units(g, size, workers)]


def _task_parts(spec: ScenarioSpec, shared: bool = False):
    """``(road, scenario, policy, loop)`` of a task. ``shared``: planners of the same name are
    one object (batched plan calls; a safety filter still gets its own wrapper per task)."""
    from safeil_sumo.sim.brake_guard import when as brake_guard_when
    from safeil_sumo.sim.loop_types import LoopConfig

    road = resolve_road(spec.net, spec.route, spec.from_km, spec.to_km, spec.lane)
    scenario = build_scenario(spec, road)
    policy = _load_policy(spec, shared)
    loop = LoopConfig(plan_rate_hz=spec.plan_rate_hz, stop_on_flag=spec.stop_on_flag,
                      brake_guard=brake_guard_when(spec.brake_guard))
    return road, scenario, policy, loop


def _record(spec: ScenarioSpec, road, scenario, policy, rollout, wall_s: float,
            extras: dict | None = None) -> dict[str, Any]:
    """The flat record of a finished task (``extras``: more fields, see :func:`run_task`)."""
    summary = dict(rollout.summary)
    if len(rollout.log):  # how it responded to its leader (the leader-response suite's)
        from safeil_sumo.experiments.suite import response_metrics

        summary.update({f"resp_{k}": v for k, v in response_metrics(rollout.log).items()})
    summary.update(extras or {})
    failed = summary.get("end_reason") == "error"
    record = {"task_id": task_id(spec), "status": STATUS_FAILED if failed else STATUS_OK,
              **spec_fields(spec)}
    summary["policy_name"] = summary.pop("policy")  # e.g. "safeil+filter"; spec keeps "safeil"
    summary["net_name"] = summary.pop("net")
    record.update(summary)
    # the draw (braking: pre-brake); with traffic there is no scripted leader
    scripted = scenario.leader
    record["leader_speed0_mps"] = scripted.initial_speed if scripted is not None else math.nan
    record["leader_label"] = scripted.label if scripted is not None else "traffic"
    record["radius_m"] = road.meta.get("radius_m", math.nan)
    if spec.safety_filter:
        record["filter_interventions"] = int(getattr(policy, "interventions", 0))
        record["filter_intervention_rate"] = float(getattr(policy, "intervention_rate", 0.0))
    record["task_wall_time_s"] = wall_s
    return record


def _safe_call(task_fn: TaskFn, spec: ScenarioSpec) -> dict[str, Any]:
    """``task_fn(spec)``, with any exception turned into a failed record."""
    try:
        record = task_fn(spec)
        if not isinstance(record, dict):
            raise TypeError(f"task function returned {type(record).__name__}, not dict")
        return record
    except Exception as exc:  # noqa: BLE001 - any task error becomes a failed record
        return failed_record(spec, f"{type(exc).__name__}: {exc}")


@dataclass(frozen=True)
class SweepJob:
    """ScenarioSpec tasks for the task engine (:class:`.task_engine.Job`): a task's record file is
    ``<task_id>.json``; with ``batch`` > 1 the specs that can share a simulation
    (:func:`batch_key`) run up to ``batch`` at a time in one (:func:`run_tasks`, for the default
    ``task_fn``), each record given as its scenario ends; else ``task_fn`` per spec.
    ``prepare_nets``: build the pending tasks' curved<R> nets once before the workers start.
    ``mixed_nets``: the tasks share their planner and loop settings by construction (a
    falsification batch), so units are even slices of them in order, their nets mixed in one
    simulation (``sim.batch.run_batch`` lays each on its own copy of its net)."""

    task_fn: TaskFn = run_task
    batch: int = 1
    prepare_nets: bool = False
    mixed_nets: bool = False

    def task_id(self, spec: ScenarioSpec) -> str:
        return task_id(spec)

    def units(self, todo: list[ScenarioSpec], workers: int) -> list[tuple[ScenarioSpec, ...]]:
        if self.prepare_nets:
            _prepare_nets(todo)
        if self.batch == 1:
            return [(s,) for s in todo]
        if self.mixed_nets:
            return even_units(todo, self.batch, workers)
        return batches(todo, self.batch, workers)

    def run_unit(self, unit: tuple[ScenarioSpec, ...], emit: Emit) -> None:
        if self.task_fn is run_task:  # one simulation for the unit (one spec: run_task)
            run_tasks(unit, on_record=emit)
            return
        for k, spec in enumerate(unit):
            emit(k, _safe_call(self.task_fn, spec))

    def failed(self, spec: ScenarioSpec, error: str) -> dict[str, Any]:
        return failed_record(spec, error)


# -- result files --------------------------------------------------------------------------------

def tasks_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "tasks"


# -- the sweep -----------------------------------------------------------------------------------

def run_sweep(
    specs: Iterable[ScenarioSpec],
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
    """Run every spec that has no result file yet; return the summary of all specs, in order.

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
    specs = list(dict.fromkeys(specs))  # a spec listed twice is one task
    out_dir = Path(out_dir)
    job = SweepJob(task_fn, batch, prepare_nets=scheduler is None and workers > 1)
    todo = execute(specs, job, tasks_dir(out_dir), workers, scheduler, progress, "sweep",
                   "task", retry_failed, task_timeout_s)

    summary = collect(specs, out_dir)
    with atomic_path(out_dir / "summary.csv") as tmp:  # a Ctrl-C here keeps the old summary
        summary.to_csv(tmp, index=False)
    outputs.write_json(out_dir / "summary.json", summary.to_dict(orient="records"))
    config = {"tasks": len(specs), "run_now": len(todo), "workers": workers, "batch": batch,
              "scheduler": scheduler, "retry_failed": retry_failed,
              "specs": [s.to_json() for s in specs], **(manifest_extra or {})}
    from safeil_sumo.scenarios.safety import scenario_seed

    seeds = [scenario_seed(s.master_seed, s.index) for s in specs]
    outputs.write_json(out_dir / "manifest.json", outputs.manifest(config, seeds))
    return summary


def collect(specs: Sequence[ScenarioSpec], out_dir: str | Path) -> pd.DataFrame:
    """The records of ``specs`` found in ``out_dir/tasks``, in spec order (missing ones skipped)."""
    tdir = tasks_dir(Path(out_dir))
    rows = []
    for order, spec in enumerate(specs):
        record = read_record(tdir / f"{task_id(spec)}.json")
        if record is not None:
            rows.append({"task_order": order, **record})
    return pd.DataFrame(rows)


def _prepare_nets(specs: Sequence[ScenarioSpec]) -> None:
    # build curved<R> networks once here (netconvert, no libsumo) instead of racing in workers;
    # a net that fails is left to its tasks, which record the error
    from safeil_sumo.roads.catalogue import resolve_net

    for net in dict.fromkeys(s.net for s in specs):
        with suppress(Exception):  # the tasks of this net record the error
            resolve_net(net)


def comparable(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` without fields that vary between identical runs (timing)."""
    drop = [c for c in TIMING_FIELDS if c in summary.columns]
    return summary.drop(columns=drop).reset_index(drop=True)


def load_specs(path: str | Path) -> list[ScenarioSpec]:
    """Specs from a JSON list (e.g. the ``specs`` of a sweep's ``manifest.json``)."""
    data = json.loads(Path(path).read_text())
    if isinstance(data, dict):
        data = data.get("config", data).get("specs", [])
    return [ScenarioSpec.from_json(d) for d in data]


__all__ = [
    "DEFAULT_BATCH",
    "ScenarioSpec",
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
