"""One sweep engine for every sweep: a list of :class:`ScenarioSpec` -> one result file per task.

- A :class:`ScenarioSpec` is a JSON-able description of one closed-loop task; its random draws
  (leader speed, initial gap) come from ``scenario_seed(master_seed, index)`` only, so task i is
  identical alone or in a sweep of any size, sequential or parallel, and across resumes.
- :func:`run_task` runs one spec and never raises (an exception becomes ``status="failed"``).
- :func:`run_sweep` runs the tasks in-process (``workers=1``), in local worker processes (one
  libsumo per process: docs/architecture.md) or on a Dask cluster, and writes every finished result at
  once and atomically to ``out_dir/tasks/<task_id>.json``. Rerunning a sweep skips tasks that have
  a result file, so a sweep that stopped (Ctrl-C, crash, killed worker) is resumed by rerunning it.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing as mp
import re
import signal
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import suppress
from functools import partial
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm import tqdm

from safeil_sumo import planner_registry
from safeil_sumo.atomic import atomic_path
from safeil_sumo.experiments import outputs
from safeil_sumo.scenarios.spec import ScenarioSpec, build_scenario, resolve_road

TIMING_FIELDS = ("wall_time_s", "steps_per_s", "task_wall_time_s")  # differ run to run
STATUS_OK = "ok"
STATUS_FAILED = "failed"

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
    from safeil_sumo import planner_registry

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
        from safeil_sumo.safety_filter import SafetyFiltered  # lazily: optional component

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


def run_tasks(specs: Sequence[ScenarioSpec]) -> list[dict[str, Any]]:
    """The records of ``specs`` run side by side in ONE SUMO simulation (``sim.batch``), in
    order; one spec is :func:`run_task`. Never raises: a spec that cannot be built, or a batch
    that fails, gives failed records. Specs of a batch share their network and loop settings
    (:func:`batch_key`)."""
    if len(specs) == 1:
        return [run_task(specs[0])]
    wall0 = time.perf_counter()
    records: list[dict[str, Any] | None] = [None] * len(specs)
    parts = []
    for k, spec in enumerate(specs):
        try:
            parts.append((k, *_task_parts(spec, shared=True)))
        except Exception as exc:  # noqa: BLE001 - a record, never an exception
            records[k] = failed_record(spec, f"{type(exc).__name__}: {exc}")
    if parts:
        from safeil_sumo.sim.batch import run_batch
        from safeil_sumo.sim.runner import SUMMARY_COLUMNS

        loop = parts[0][4]  # the specs of a batch share their loop settings (batch_key)
        wall = (time.perf_counter() - wall0) / len(specs)  # building, per task

        def record(i: int, rollout) -> None:  # as each scenario ends: its log is freed then
            k, road, scenario, policy, _ = parts[i]
            records[k] = _record(specs[k], road, scenario, policy, rollout,
                                 wall + rollout.summary["wall_time_s"])

        try:
            # a record reads the summary columns only: 12 of the log's 46, so batches 4x
            # larger fit the same memory
            run_batch([p[2] for p in parts], [p[3] for p in parts], loop, on_done=record,
                      keep_logs=False, log_columns=SUMMARY_COLUMNS)
        except Exception as exc:  # noqa: BLE001
            for k, *_ in parts:
                records[k] = failed_record(specs[k], f"{type(exc).__name__}: {exc}")
    # run_batch reports every scenario it was given (on_done), so none is left without one
    return [failed_record(specs[k], "NoRecord: the batch ended without this task's record")
            if r is None else r for k, r in enumerate(records)]


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


def even_units(items: Sequence, size: int, workers: int = 1) -> list[tuple]:
    """``items`` in order, in units of at most ``size``: as even as can be and, where there are
    enough, a multiple of ``workers`` many (140 items of size 64 on 2 workers: 4 of 35, not
    64 + 64 + 12, where one worker would run the 12 alone)."""
    if size < 1:
        raise ValueError(f"batch size must be >= 1, got {size}")
    if not items:
        return []
    k = -(-len(items) // size)  # units needed
    k = min(-(-k // max(workers, 1)) * max(workers, 1), len(items))
    n, extra = divmod(len(items), k)
    out, i = [], 0
    for j in range(k):
        m = n + (j < extra)
        out.append(tuple(items[i:i + m]))
        i += m
    return out


def _task_parts(spec: ScenarioSpec, shared: bool = False):
    """``(road, scenario, policy, loop)`` of a task. ``shared``: planners of the same name are
    one object (batched plan calls; a safety filter still gets its own wrapper per task)."""
    from safeil_sumo.sim.brake_guard import when as brake_guard_when
    from safeil_sumo.sim.runner import LoopConfig

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


_PROCESS_LOCK = threading.Lock()


Unit = tuple[ScenarioSpec, ...]  # what a worker runs at once: one task, or a batch of them


def _run_unit(task_fn: TaskFn, unit: Unit) -> list[dict[str, Any]]:
    """The records of a unit: a batch in one simulation (:func:`run_tasks`) for the default
    task function, else ``task_fn`` per spec. Never raises."""
    if task_fn is run_task and len(unit) > 1:
        try:
            return run_tasks(unit)
        except Exception as exc:  # noqa: BLE001 - any error becomes failed records
            return [failed_record(s, f"{type(exc).__name__}: {exc}") for s in unit]
    return [_safe_call(task_fn, s) for s in unit]


def _run_exclusive(task_fn: TaskFn, unit: Unit) -> list[dict[str, Any]]:
    # libsumo holds ONE simulation per process: a Dask worker with several threads must not
    # run two tasks at once in the same process
    with _PROCESS_LOCK:
        return _run_unit(task_fn, unit)


# -- result files --------------------------------------------------------------------------------

def tasks_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "tasks"


def read_record(path: Path) -> dict[str, Any] | None:
    """A task's result, or None if missing or unreadable (then the task is run again)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and "status" in data else None


def _is_done(path: Path, retry_failed: bool) -> bool:
    record = read_record(path)
    if record is None:
        return False
    return not (retry_failed and record.get("status") == STATUS_FAILED)


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
    a time in one SUMO simulation (:func:`run_tasks`); a worker that dies costs its batch, and
    ``task_timeout_s`` is per batch then.

    Writes ``tasks/<task_id>.json`` per task as it finishes, then ``summary.csv``,
    ``summary.json`` and ``manifest.json``.
    """
    specs = list(dict.fromkeys(specs))  # a spec listed twice is one task
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    out_dir = Path(out_dir)
    tdir = tasks_dir(out_dir)
    tdir.mkdir(parents=True, exist_ok=True)
    ids = [task_id(s) for s in specs]
    todo = [s for s, i in zip(specs, ids, strict=True) if not _is_done(tdir / f"{i}.json", retry_failed)]
    if todo and scheduler is None and workers > 1:
        _prepare_nets(todo)

    units: list[Unit] = batches(todo, batch, workers) if batch > 1 else [(s,) for s in todo]
    bar = tqdm(total=len(todo), desc="sweep", unit="task", disable=not progress or None,
               initial=0, dynamic_ncols=True)
    failed = 0

    def save(unit: Unit, records: list[dict[str, Any]]) -> None:
        nonlocal failed
        for spec, record in zip(unit, records, strict=True):
            outputs.write_json(tdir / f"{task_id(spec)}.json", record)
            failed += record.get("status") != STATUS_OK
        bar.update(len(unit))
        if failed:
            bar.set_postfix(failed=failed)

    try:
        if not todo:
            pass
        elif scheduler is not None:
            _run_dask(units, scheduler, task_fn, save)
        elif workers == 1:
            for unit in units:
                save(unit, _run_unit(task_fn, unit))
        else:
            _run_local(units, min(workers, len(units)), task_fn, save, task_timeout_s)
    finally:
        bar.close()

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
    from safeil_sumo.scenarios.catalogue import resolve_net

    for net in dict.fromkeys(s.net for s in specs):
        with suppress(Exception):  # the tasks of this net record the error
            resolve_net(net)


# -- local worker processes ----------------------------------------------------------------------

def _die_with_parent() -> None:
    """Linux: the kernel sends this process SIGTERM when its parent dies (even by SIGKILL), so a
    worker never outlives its sweep holding a SUMO instance. Elsewhere: nothing (the worker
    still ends when its pipe to the parent closes)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _worker_main(conn: Connection, task_fn: TaskFn) -> None:
    """A worker: receive a unit, run it, send its records back; ``None`` ends the worker."""
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    while True:
        try:
            unit = conn.recv()
        except EOFError:
            return
        if unit is None:
            return
        conn.send(_run_unit(task_fn, unit))


class _Worker:
    def __init__(self, ctx, task_fn: TaskFn) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, task_fn), daemon=True)
        self.process.start()
        child.close()
        self.unit: Unit | None = None  # the unit it runs
        self.started = 0.0

    def give(self, unit: Unit) -> None:
        self.unit, self.started = unit, time.monotonic()
        self.conn.send(unit)

    def stop(self) -> None:
        with suppress(OSError):
            self.conn.send(None)

    def kill(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join(timeout=5)
        self.conn.close()


def _mp_context():
    # 'fork' keeps worker start cheap and works with any task_fn; libsumo is imported (and
    # started) only inside the workers
    methods = mp.get_all_start_methods()
    return mp.get_context("fork" if "fork" in methods else "spawn")


def _run_local(
    todo: list[Unit], workers: int, task_fn: TaskFn,
    save: Callable[[Unit, list], None], task_timeout_s: float | None,
) -> None:
    """Own worker processes, one unit each at a time: the parent always knows which unit a
    worker runs, so a dead worker costs exactly that unit (recorded failed) and is replaced."""
    ctx = _mp_context()
    queue = list(reversed(todo))  # pop() from the end keeps task order
    pool: list[_Worker] = []

    def assign(w: _Worker) -> None:
        while queue:
            unit = queue.pop()
            try:
                w.give(unit)
                return
            except OSError:  # died while idle: replace it and give it the same task
                queue.append(unit)
                pool.remove(w)
                w.kill()
                w = _Worker(ctx, task_fn)
                pool.append(w)

    try:
        first: list[_Worker] = []
        for _ in range(workers):
            first.append(_Worker(ctx, task_fn))
            pool.append(first[-1])
        for w in first:  # assign() may replace a worker in pool, so iterate a separate list
            assign(w)
        while any(w.unit is not None for w in pool):
            busy = [(w, w.unit) for w in pool if w.unit is not None]
            ready = set(wait([w.conn for w, _ in busy] + [w.process.sentinel for w, _ in busy],
                             timeout=1.0))
            for w, unit in busy:
                records = _poll(w, unit, ready, task_timeout_s)
                if records is None:
                    continue
                save(unit, records)
                w.unit = None
                if not w.process.is_alive():
                    pool.remove(w)
                    w.kill()
                    if not queue:
                        continue
                    w = _Worker(ctx, task_fn)  # replace the dead worker
                    pool.append(w)
                assign(w)
        for w in pool:
            w.stop()
        for w in pool:
            w.process.join(timeout=5)
    finally:  # Ctrl-C or an error: unfinished tasks are simply not saved
        for w in pool:
            w.kill()


def _poll(w: _Worker, unit: Unit, ready: set, task_timeout_s: float | None
          ) -> list[dict[str, Any]] | None:
    """The records of a busy worker's ``unit`` if it is over (result, death or timeout), else
    None."""
    if w.conn in ready or w.process.sentinel in ready:
        try:
            if w.conn.poll():
                return w.conn.recv()
        except (EOFError, OSError):
            pass
        if not w.process.is_alive():
            return [failed_record(s, f"WorkerDied: worker process died (exit code "
                                     f"{w.process.exitcode}) while running the task")
                    for s in unit]
    if task_timeout_s is not None and time.monotonic() - w.started > task_timeout_s:
        w.process.kill()
        w.process.join(timeout=5)
        return [failed_record(s, f"TaskTimeout: no result after {task_timeout_s:g} s; "
                                 "worker killed") for s in unit]
    return None


# -- Dask ----------------------------------------------------------------------------------------

def _run_dask(
    todo: list[Unit], address: str, task_fn: TaskFn,
    save: Callable[[Unit, list], None],
) -> None:
    from dask.distributed import Client, as_completed

    client = Client(address)  # only the address the user gave
    try:
        futures = client.map(partial(_run_exclusive, task_fn), todo, pure=False)
        unit_of = {f.key: u for f, u in zip(futures, todo, strict=True)}
        try:
            for future in as_completed(futures):
                unit = unit_of[future.key]
                try:
                    records = future.result()
                except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker after repeated worker deaths
                    records = [failed_record(s, f"{type(exc).__name__}: {exc}") for s in unit]
                save(unit, records)
        finally:
            client.cancel([f for f in futures if not f.done()])
    finally:
        client.close()


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
    "even_units",
    "load_specs",
    "run_sweep",
    "run_task",
    "run_tasks",
    "spec_fields",
    "task_id",
]
