"""One task engine for sweeps and window replays: tasks in, one JSON record file per task out.

- A kind of task is a :class:`Job`: it names a task (:meth:`Job.task_id`, the stem of its record
  file), groups the pending tasks into *units* that a worker runs at once (a batch of scenarios
  in one SUMO simulation, :meth:`Job.units`), runs a unit (:meth:`Job.run_unit`, handing each
  task's JSON-able record to ``emit`` as that task ends) and writes the record of a task that
  gave none (:meth:`Job.failed`). Sweeps (``sweep_executor.SweepJob``: ScenarioSpec tasks) and
  window replays (``window_replays.WindowJob``) are the two jobs.
- :func:`execute` runs a job's tasks in this process (``workers=1``), in local worker processes
  (one libsumo per process: docs/architecture.md) or on a Dask cluster (``scheduler``). Every
  record is written atomically to ``<tasks_dir>/<task_id>.json`` as its task ends, also inside
  a unit: a worker sends each record as it is emitted (Dask: its file's text, through a
  ``distributed.Queue``). A rerun skips the tasks whose record file is there (resume).
- Ctrl-C (SIGINT, to this process or its whole process group) ends :func:`execute` with
  ``KeyboardInterrupt`` once every record made before it is written: a record being made,
  written or read waits for its end (:func:`deferred_interrupt`); local workers stop their unit,
  send what they made and end (the parent sends them SIGINT too and waits at most
  :data:`INTERRUPT_GRACE_S`, then kills them); on Dask the records on the queue are written and
  the other units cancelled.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from functools import partial
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Protocol, Self, TypeVar

from tqdm import tqdm

from safeil_sumo.experiments import outputs

Record = dict[str, Any]
Emit = Callable[[int, Record], None]  # emit(k, record): the unit's k-th task has ended
T = TypeVar("T")
Unit = tuple  # the tasks a worker runs at once, in order
STATUS_OK = "ok"
STATUS_FAILED = "failed"


class Job(Protocol[T]):
    """A kind of task, as :func:`execute` runs it. An instance travels to the workers (pickled
    for Dask): a module-level class whose fields pickle."""

    def task_id(self, task: T) -> str:
        """The stem of the task's record file (``[A-Za-z0-9_.-]`` only)."""
        ...

    def units(self, todo: list[T], workers: int) -> list[tuple[T, ...]]:
        """The pending tasks ``todo`` grouped into the units a worker runs at once, in order."""
        ...

    def run_unit(self, unit: tuple[T, ...], emit: Emit) -> None:
        """Run ``unit``; ``emit(k, record)`` as its k-th task ends (a JSON-able dict with a
        ``status``). A task left without a record is recorded failed."""
        ...

    def failed(self, task: T, error: str) -> Record:
        """The record of a task that gave none (``error``: ``"Type: message"``)."""
        ...


def record_path(tasks_dir: Path, job: Job, task: Any) -> Path:
    return Path(tasks_dir) / f"{job.task_id(task)}.json"


def read_record(path: Path) -> Record | None:
    """A task's record, or None if missing or unreadable (then the task is run again)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and "status" in data else None


def is_done(path: Path, retry_failed: bool = False) -> bool:
    """A readable record is there (a failed one counts unless ``retry_failed``)."""
    record = read_record(path)
    if record is None:
        return False
    return not (retry_failed and record.get("status") == STATUS_FAILED)


def execute(tasks: Sequence[T], job: Job[T], tasks_dir: str | Path, workers: int = 1,
            scheduler: str | None = None, progress: bool = True, desc: str = "tasks",
            unit_name: str = "task", retry_failed: bool = False,
            task_timeout_s: float | None = None) -> list[T]:
    """Run every task of ``tasks`` without a record in ``tasks_dir``; return those it ran.

    ``workers=1``: in this process. ``workers>1``: that many local worker processes ('fork' on
    Linux), one unit each at a time; a worker that dies (crash, ``kill -9``, or a unit running
    longer than ``task_timeout_s`` [s]) has its unit's tasks without a record recorded failed and
    is replaced. ``scheduler="tcp://host:port"``: the units go to that Dask cluster. Failed
    records count as done unless ``retry_failed``. Each record is written as its task ends."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    tdir = Path(tasks_dir)
    tdir.mkdir(parents=True, exist_ok=True)
    todo = [t for t in dict.fromkeys(tasks)
            if not is_done(record_path(tdir, job, t), retry_failed)]
    if not todo:
        return todo
    units = job.units(todo, workers)
    with _Saver(job, tdir, len(todo), progress, desc, unit_name) as saver:
        if scheduler is not None:
            _run_dask(units, scheduler, job, saver)
        elif workers == 1:
            for unit in units:
                _run_unit(job, unit, partial(saver.save, unit))
        else:
            _run_local(units, min(workers, len(units)), job, saver, task_timeout_s)
    return todo


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


class _Saver:
    """Writes each record as it arrives (once per task of a unit) and counts it on the bar."""

    def __init__(self, job: Job, tdir: Path, total: int, progress: bool, desc: str,
                 unit_name: str) -> None:
        self.job, self.tdir, self.failed = job, tdir, 0
        self.bar = tqdm(total=total, desc=desc, unit=unit_name,
                        disable=not progress or None, dynamic_ncols=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.bar.close()

    def save(self, unit: Unit, k: int, record: Record, text: str | None = None) -> None:
        """Write ``record`` (as ``text``, its JSON, when given) for the unit's k-th task."""
        with deferred_interrupt():  # a Ctrl-C waits until the record is on disk
            outputs.write_text(record_path(self.tdir, self.job, unit[k]),
                               outputs.json_text(record) if text is None else text)
        self.failed += record.get("status") != STATUS_OK
        self.bar.update(1)
        if self.failed:
            self.bar.set_postfix(failed=self.failed)


def _raise_once(signum: int, frame: Any) -> None:
    """A worker's SIGINT handler: ``KeyboardInterrupt`` once (its unit stops), then ignored
    (the parent's forwarded SIGINT after the process group's)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise KeyboardInterrupt


_RAISING = (signal.default_int_handler, _raise_once)


def _interruptible() -> bool:
    """SIGINT raises ``KeyboardInterrupt`` here: the main thread, with a raising handler."""
    return (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) in _RAISING)


@contextmanager
def deferred_interrupt() -> Iterator[None]:
    """A SIGINT arriving inside the block raises ``KeyboardInterrupt`` at its end, not in the
    middle (a record half made, a file half written, a message half read). Only where SIGINT
    raises (:func:`_interruptible`); elsewhere the block just runs."""
    if not _interruptible():
        yield
        return
    handler = signal.getsignal(signal.SIGINT)
    caught: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)
    if caught and callable(handler):  # it is: one of _RAISING
        handler(signal.SIGINT, None)  # raises


def _run_unit(job: Job, unit: Unit, emit: Emit) -> None:
    """``job.run_unit(unit, emit)`` with each task's record emitted exactly once: a task left
    without one (the unit raised, or forgot it) gets a failed record. Never raises, but for
    ``KeyboardInterrupt`` (and an ``emit`` that raises)."""
    sent: set[int] = set()

    def once(k: int, record: Record) -> None:
        if k not in sent and 0 <= k < len(unit):
            sent.add(k)
            emit(k, record)

    try:
        job.run_unit(unit, once)
        error = "NoRecord: the unit ended without this task's record"
    except Exception as exc:  # noqa: BLE001 - failed records, never an exception
        error = f"{type(exc).__name__}: {exc}"
    for k, task in enumerate(unit):
        if k not in sent:
            once(k, job.failed(task, error))


# -- local worker processes ----------------------------------------------------------------------

def _die_with_parent() -> None:
    """Linux: the kernel sends this process SIGTERM when its parent dies (even by SIGKILL), so a
    worker never outlives its run holding a SUMO instance. Elsewhere: nothing (the worker
    still ends when its pipe to the parent closes)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


_END = "end"  # a worker's message: its unit is over
_INTERRUPTED = "interrupted"  # a worker's message: Ctrl-C stopped its unit; it ends


def _worker_main(conn: Connection, job: Job, interruptible: bool) -> None:
    """A worker: receive a unit, run it, send ``(k, record)`` as each task ends, then ``_END``;
    a unit ``None`` ends the worker. ``interruptible``: a SIGINT stops the unit (every record
    made before it is sent) and the worker ends with ``_INTERRUPTED``; else SIGINT is ignored
    (the parent's to handle)."""
    _die_with_parent()
    signal.signal(signal.SIGINT, _raise_once if interruptible else signal.SIG_IGN)

    def send(message: Any) -> None:
        with deferred_interrupt():
            conn.send(message)

    try:
        while True:
            unit = conn.recv()
            if unit is None:
                return
            _run_unit(job, unit, lambda k, record: send((k, record)))
            send(_END)
    except KeyboardInterrupt:
        with suppress(OSError):
            conn.send(_INTERRUPTED)
    except EOFError:
        return


class _Worker:
    def __init__(self, ctx: Any, job: Job, interruptible: bool) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, job, interruptible),
                                   daemon=True)
        self.process.start()
        child.close()
        self.unit: Unit | None = None  # the unit it runs
        self.got: set[int] = set()  # the unit's tasks whose record arrived
        self.started = 0.0

    def give(self, unit: Unit) -> None:
        self.unit, self.got, self.started = unit, set(), time.monotonic()
        self.conn.send(unit)

    def receive(self, saver: _Saver) -> bool:
        """Save every record the pipe holds now; True when the unit's end (or the worker's
        interruption) came with them."""
        assert self.unit is not None
        with deferred_interrupt():
            try:
                while self.conn.poll():
                    message = self.conn.recv()
                    if isinstance(message, str):  # _END or _INTERRUPTED
                        return True
                    k, record = message
                    self.got.add(k)
                    saver.save(self.unit, k, record)
            except (EOFError, OSError):
                pass  # the worker died: the caller records the rest
        return False

    def fail_rest(self, saver: _Saver, error: str) -> None:
        """Failed records for the unit's tasks whose record never came."""
        assert self.unit is not None
        for k, task in enumerate(self.unit):
            if k not in self.got:
                saver.save(self.unit, k, saver.job.failed(task, error))

    def stop(self) -> None:
        with suppress(OSError):
            self.conn.send(None)

    def kill(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join(timeout=5)
        self.conn.close()


def _mp_context() -> Any:
    # 'fork' keeps worker start cheap and works with any job; libsumo is imported (and
    # started) only inside the workers
    methods = mp.get_all_start_methods()
    return mp.get_context("fork" if "fork" in methods else "spawn")


# [s] how long an interrupted run waits for its workers' last records (a batch's step, SUMO's
# close); then they are killed
INTERRUPT_GRACE_S = 10.0


def _run_local(todo: list[Unit], workers: int, job: Job, saver: _Saver,
               task_timeout_s: float | None) -> None:
    """Own worker processes, one unit each at a time: the parent always knows which unit a
    worker runs, so a dead worker costs exactly that unit's tasks not yet recorded (recorded
    failed) and is replaced."""
    ctx = _mp_context()
    interruptible = _interruptible()
    queue = list(reversed(todo))  # pop() from the end keeps task order
    pool: list[_Worker] = []

    def start() -> _Worker:
        pool.append(_Worker(ctx, job, interruptible))
        return pool[-1]

    def assign(w: _Worker) -> None:
        while queue:
            unit = queue.pop()
            try:
                w.give(unit)
                return
            except OSError:  # died while idle: replace it and give it the same unit
                queue.append(unit)
                pool.remove(w)
                w.kill()
                w = start()

    try:
        for w in [start() for _ in range(workers)]:  # assign() may replace one in pool
            assign(w)
        while any(w.unit is not None for w in pool):
            busy = [w for w in pool if w.unit is not None]
            ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy],
                             timeout=1.0))
            for w in busy:
                if not _unit_over(w, ready, saver, task_timeout_s):
                    continue
                w.unit = None
                if not w.process.is_alive():
                    pool.remove(w)
                    w.kill()
                    if not queue:
                        continue
                    w = start()  # replace the dead worker
                assign(w)
        for w in pool:
            w.stop()
        for w in pool:
            w.process.join(timeout=5)
    except KeyboardInterrupt:  # Ctrl-C: the records the workers make until they stop
        _wind_down([w for w in pool if w.unit is not None], saver, interruptible)
        raise
    finally:
        for w in pool:
            w.kill()


def _wind_down(busy: list[_Worker], saver: _Saver, interruptible: bool) -> None:
    """After a Ctrl-C: every busy worker is sent SIGINT (a process group's Ctrl-C has reached
    it already; :func:`_raise_once` ignores the second), stops its unit and sends the records
    made before; they are saved, for at most :data:`INTERRUPT_GRACE_S`. Workers that ignore
    SIGINT: what their pipes hold now."""
    with deferred_interrupt():
        if interruptible:
            for w in busy:
                with suppress(OSError):
                    os.kill(w.process.pid, signal.SIGINT)
        deadline = time.monotonic() + (INTERRUPT_GRACE_S if interruptible else 0.0)
        while True:
            for w in list(busy):
                dead = not w.process.is_alive()  # then the pipe holds all it sent
                if w.receive(saver) or dead:
                    busy.remove(w)
            left = deadline - time.monotonic()
            if not busy or left <= 0:
                return
            wait([w.conn for w in busy] + [w.process.sentinel for w in busy], timeout=left)


def _unit_over(w: _Worker, ready: set, saver: _Saver, task_timeout_s: float | None) -> bool:
    """Save what a busy worker sent; True if its unit is over (ended, worker died or timed
    out: the tasks without a record then recorded failed)."""
    if w.conn in ready or w.process.sentinel in ready:
        if w.receive(saver):
            return True
        if not w.process.is_alive():
            w.receive(saver)  # all it sent before it died
            w.fail_rest(saver, f"WorkerDied: worker process died (exit code "
                               f"{w.process.exitcode}) while running the task")
            return True
    if task_timeout_s is not None and time.monotonic() - w.started > task_timeout_s:
        w.process.kill()
        w.process.join(timeout=5)
        w.receive(saver)
        w.fail_rest(saver, f"TaskTimeout: no result after {task_timeout_s:g} s; worker killed")
        return True
    return False


# -- Dask ----------------------------------------------------------------------------------------

_PROCESS_LOCK = threading.Lock()


def _dask_unit(job: Job, queue_name: str, index: int, unit: Unit) -> list[Record]:
    """A unit on a Dask worker: its records (in order), each also put on the queue as its task
    ends (the client writes it then)."""
    from dask.distributed import Queue

    queue: Any = None
    records: dict[int, Record] = {}

    def emit(k: int, record: Record) -> None:
        nonlocal queue
        records[k] = record
        with suppress(Exception):  # the unit's result still carries the record
            queue = queue or Queue(queue_name)
            queue.put([index, k, outputs.json_text(record)])  # the file's text

    # libsumo holds ONE simulation per process: a Dask worker with several threads must not
    # run two units at once in the same process
    with _PROCESS_LOCK:
        _run_unit(job, unit, emit)
    return [records[k] for k in range(len(unit))]


def _run_dask(units: list[Unit], address: str, job: Job, saver: _Saver) -> None:
    from dask.distributed import Client, Queue, as_completed

    client = Client(address)  # only the address the user gave
    saved: set[tuple[int, int]] = set()

    def save(index: int, k: int, record: Record, text: str | None = None) -> None:
        if (index, k) not in saved:
            saved.add((index, k))
            saver.save(units[index], k, record, text)

    def drain(queue: Any) -> None:  # the records the workers have put on the queue so far
        with deferred_interrupt(), suppress(Exception):
            for index, k, text in queue.get(batch=True):
                save(index, k, json.loads(text), text)

    try:
        queue = Queue(client=client)
        on_cluster = client.scatter(job, broadcast=True)  # the job once per worker
        futures = [client.submit(_dask_unit, on_cluster, queue.name, i, u, pure=False)
                   for i, u in enumerate(units)]
        index_of = {f.key: i for i, f in enumerate(futures)}
        ended = as_completed(futures, loop=client.loop)
        try:
            while not ended.is_empty():
                batch = ended.next_batch(block=False)
                drain(queue)
                for future in batch:
                    _save_result(index_of[future.key], future, units, job, save)
                if not batch:
                    time.sleep(0.25)
        except KeyboardInterrupt:  # Ctrl-C: the records the workers have put on the queue
            drain(queue)
            raise
        finally:
            client.cancel([f for f in futures if not f.done()])
            with suppress(Exception):
                queue.close()
    finally:
        client.close()


def _save_result(index: int, future: Any, units: list[Unit], job: Job,
                 save: Callable[[int, int, Record], None]) -> None:
    """The records of a finished Dask unit (those the queue did not bring already)."""
    unit = units[index]
    try:
        records = future.result()
    except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker after repeated worker deaths
        records = [job.failed(t, f"{type(exc).__name__}: {exc}") for t in unit]
    for k, record in enumerate(records):
        save(index, k, record)


__all__ = [
    "Emit",
    "Job",
    "Record",
    "deferred_interrupt",
    "even_units",
    "execute",
    "is_done",
    "read_record",
    "record_path",
]
