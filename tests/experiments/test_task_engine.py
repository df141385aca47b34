"""The task engine (``experiments/task_engine.py``): sweeps and window replays run on its one
``execute`` (in-process, local workers, Dask), resume from its record files, and a Ctrl-C keeps
every task that ended, also inside a batch (a real sweep sent SIGINT mid-batch)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.experiments import sweep_executor, task_engine
from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.experiments.sweep_executor import SweepJob, run_sweep, task_id
from safeil_sumo.experiments.window_replays import WindowJob
from safeil_sumo.scenarios.spec import Task

REPO = Path(__file__).resolve().parents[2]


def _maneuvers() -> pd.DataFrame:
    """Two maneuvers' rows, enough for :func:`window_replays.windows` (no SUMO is run)."""
    t = np.linspace(0.0, 30.0, 301)
    return pd.concat([pd.DataFrame({"maneuver_id": m, "time": t, "v_x": 25.0, "lead_x": 40.0})
                      for m in ("a#0", "b#0")], ignore_index=True)


def _fake_windows(log: Path):
    """A ``run_windows`` that replays nothing: one record per window, each window logged to
    ``log`` (one line per window, across processes)."""

    def run_windows(wins, maneuvers, policies, config, on_record=None):
        records = []
        for k, w in enumerate(wins):
            with open(log, "a") as f:
                f.write(f"{w.maneuver_id}@{w.start_s:g}\n")
            records.append({"task_id": w.task_id, "maneuver_id": w.maneuver_id,
                            "start_s": w.start_s, "status": "ok", "policies": sorted(policies)})
            if on_record is not None:
                on_record(k, records[-1])
        return records

    return run_windows


def _runs(log: Path) -> list[str]:
    return log.read_text().split() if log.exists() else []


@pytest.fixture
def units_run(monkeypatch):
    """Every unit the engine runs in this process: ``(job, unit)``."""
    seen: list[tuple] = []
    run_unit = task_engine._run_unit

    def spy(job, unit, emit):
        seen.append((job, unit))
        return run_unit(job, unit, emit)

    monkeypatch.setattr(task_engine, "_run_unit", spy)
    return seen


# -- one engine for sweeps and replays (no SUMO) -------------------------------------------------

def test_replays_and_sweeps_run_on_the_one_engine(tmp_path, monkeypatch, units_run):
    monkeypatch.setattr(ra.planner_registry, "fingerprint", lambda name: "w")
    monkeypatch.setattr(ra, "run_windows", _fake_windows(tmp_path / "windows.log"))
    maneuvers = _maneuvers()
    wins = ra.windows(maneuvers, "sliding", duration_s=10.0, stride_s=10.0)
    assert len(wins) == 6
    records = ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "r", batch=4,
                            progress=False)
    assert [r["task_id"] for r in records] == [w.task_id for w in wins]
    # the engine ran the windows, in the replay's units, and wrote their record files
    assert [type(job) for job, _ in units_run] == [WindowJob, WindowJob]
    assert [len(u) for _, u in units_run] == [3, 3]
    job = units_run[0][0]
    files = sorted(p.name for p in (tmp_path / "r" / "tasks").iterdir())
    assert files == sorted(f"{job.task_id(w)}.json" for w in wins)
    # resume: a rerun replays only the window whose record is gone
    (tmp_path / "r" / "tasks" / f"{job.task_id(wins[4])}.json").unlink()
    again = ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "r", batch=4,
                          progress=False)
    assert again == records
    assert _runs(tmp_path / "windows.log")[6:] == ["b#0@10"]
    assert units_run[-1][1] == (wins[4],)

    # a sweep: the same engine entry, its own job
    specs = [Task.of(index=i, net="straight", policy="analytic") for i in range(3)]
    out = run_sweep(specs, tmp_path / "s", progress=False, task_fn=_fake_task)
    assert list(out["status"]) == ["ok"] * 3
    assert [type(job) for job, _ in units_run[3:]] == [SweepJob] * 3
    assert sweep_executor.execute is ra.execute is task_engine.execute


def test_a_replay_reruns_its_failed_windows_only_when_asked(tmp_path, monkeypatch, units_run):
    monkeypatch.setattr(ra.planner_registry, "fingerprint", lambda name: "w")
    monkeypatch.setattr(ra, "run_windows", _fake_windows(tmp_path / "windows.log"))
    maneuvers = _maneuvers()
    wins = ra.windows(maneuvers, "sliding", duration_s=10.0, stride_s=10.0)
    ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "r", batch=4, progress=False)
    job = units_run[0][0]
    failed = tmp_path / "r" / "tasks" / f"{job.task_id(wins[2])}.json"
    failed.write_text('{"status": "failed", "error": "RuntimeError: boom"}')
    ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "r", batch=4, progress=False)
    assert len(_runs(tmp_path / "windows.log")) == 6  # a failed record counts as done
    records = ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "r", batch=4,
                            progress=False, retry_failed=True)
    assert _runs(tmp_path / "windows.log")[6:] == [f"{wins[2].maneuver_id}@{wins[2].start_s:g}"]
    assert [r["status"] for r in records] == ["ok"] * 6


def test_replay_and_sweep_share_the_task_options() -> None:
    from safeil_sumo import replay, sweep

    for parser in (replay.build_parser(), sweep.build_parser()):
        flags = {a for action in parser._actions for a in action.option_strings}
        assert {"--task-timeout-s", "--retry-failed", "--scheduler"} <= flags
    with pytest.raises(SystemExit):
        replay.parse_args(["--source", "openacc", "--maneuver", "all", "--task-timeout-s", "0"])


def _fake_task(task: Task) -> dict:
    return {"task_id": task_id(task), "status": "ok", "index": task.scenario.index}


def test_replays_run_in_local_workers_and_on_dask(tmp_path, monkeypatch):
    """Replays have the sweeps' local workers and Dask cluster (the fake replay is patched in
    this process: forked workers and an in-process Dask cluster see it)."""
    monkeypatch.setattr(ra.planner_registry, "fingerprint", lambda name: "w")
    monkeypatch.setattr(ra, "run_windows", _fake_windows(tmp_path / "windows.log"))
    maneuvers = _maneuvers()
    wins = ra.windows(maneuvers, "sliding", duration_s=10.0, stride_s=10.0)
    local = ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "local", workers=2,
                          batch=2, progress=False)
    assert [r["task_id"] for r in local] == [w.task_id for w in wins]
    assert sorted(_runs(tmp_path / "windows.log")) == sorted(
        f"{w.maneuver_id}@{w.start_s:g}" for w in wins)

    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        on_dask = ra.replay_all(maneuvers, wins, ["analytic"], tmp_path / "dask", batch=4,
                                progress=False, scheduler=cluster.scheduler_address)
    assert on_dask == local
    assert len(list((tmp_path / "dask" / "tasks").glob("*.json"))) == len(wins)


# -- the engine itself (no SUMO) -----------------------------------------------------------------

class DyingJob:
    """Units of ints: each task's record as it ends; task ``die_at`` kills its worker."""

    def __init__(self, die_at: int) -> None:
        self.die_at = die_at

    def task_id(self, task: int) -> str:
        return f"t{task}"

    def units(self, todo: list[int], workers: int) -> list[tuple[int, ...]]:
        return task_engine.even_units(todo, 3, workers)

    def run_unit(self, unit: tuple[int, ...], emit) -> None:
        for k, task in enumerate(unit):
            if task == self.die_at:
                os.kill(os.getpid(), signal.SIGKILL)
            emit(k, {"status": "ok", "task": task})

    def failed(self, task: int, error: str) -> dict:
        return {"status": "failed", "task": task, "error": error}


def test_a_dead_worker_costs_only_the_tasks_of_its_unit_not_ended(tmp_path):
    ran = task_engine.execute(range(6), DyingJob(die_at=1), tmp_path, workers=2,
                              progress=False)
    assert ran == list(range(6))
    records = {t: json.loads((tmp_path / f"t{t}.json").read_text()) for t in range(6)}
    assert [records[t]["status"] for t in range(6)] == ["ok", "failed", "failed",
                                                        "ok", "ok", "ok"]
    assert records[1]["error"].startswith("WorkerDied")
    # failed records count as done, unless retried
    assert task_engine.execute(range(6), DyingJob(die_at=-1), tmp_path, 2, progress=False) == []
    assert task_engine.execute(range(6), DyingJob(die_at=-1), tmp_path, 2, progress=False,
                               retry_failed=True) == [1, 2]


class WaitingJob:
    """One unit of two tasks: the first's record, then the second only once ``go`` exists (it
    says whether it did, or 10 s passed)."""

    def __init__(self, go: Path) -> None:
        self.go = go

    def task_id(self, task: int) -> str:
        return f"t{task}"

    def units(self, todo: list[int], workers: int) -> list[tuple[int, ...]]:
        return [tuple(todo)]

    def run_unit(self, unit: tuple[int, ...], emit) -> None:
        emit(0, {"status": "ok", "task": unit[0]})
        deadline = time.monotonic() + 10
        while not self.go.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        emit(1, {"status": "ok", "task": unit[1], "go": self.go.exists()})

    def failed(self, task: int, error: str) -> dict:
        return {"status": "failed", "task": task, "error": error}


def test_on_dask_a_record_reaches_disk_as_its_task_ends(tmp_path):
    """The unit's second task waits for the first's record file on disk (written by the
    client from the queue, while the unit still runs)."""
    distributed = pytest.importorskip("dask.distributed")
    go = tmp_path / "go"

    def watch() -> None:  # go once the first record is on disk, never before
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if (tmp_path / "tasks" / "t0.json").exists():
                go.touch()
                return
            time.sleep(0.02)

    watcher = threading.Thread(target=watch)
    watcher.start()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        task_engine.execute([0, 1], WaitingJob(go), tmp_path / "tasks", progress=False,
                            scheduler=cluster.scheduler_address)
    watcher.join()
    assert json.loads((tmp_path / "tasks" / "t1.json").read_text())["go"] is True


def test_a_ctrl_c_inside_a_deferred_block_raises_at_its_end():
    done = []
    with pytest.raises(KeyboardInterrupt), task_engine.deferred_interrupt():
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler has run by now: it did not raise here
        done.append(True)
    assert done == [True]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


MAKING = """
import sys, time
from pathlib import Path
from safeil_sumo.experiments import task_engine

class MakingJob:
    # task 0's record takes 1 s to make (marked on disk as it starts); task 1 never ends

    def __init__(self, folder):
        self.folder = folder

    def task_id(self, task):
        return f"t{task}"

    def units(self, todo, workers):
        return [tuple(todo)]

    def run_unit(self, unit, emit):
        with task_engine.deferred_interrupt():
            (self.folder / "making").touch()
            time.sleep(1.0)
            emit(0, {"status": "ok", "task": unit[0]})
        time.sleep(600)

    def failed(self, task, error):
        return {"status": "failed", "task": task, "error": error}

folder = Path(sys.argv[1])
try:
    task_engine.execute([0, 1], MakingJob(folder), folder / "tasks", int(sys.argv[2]),
                        progress=False)
except KeyboardInterrupt:
    sys.exit(130)
"""


def _interrupted(script: str, args: list[str], ready: Callable[[], bool]
                 ) -> subprocess.CompletedProcess:
    """``python -c script *args`` in its own process group, sent SIGINT (to the group, as a
    terminal's Ctrl-C) once ``ready()``; with Ctrl-C's default handling even when the tests run
    in a background job (started with SIGINT ignored, which children inherit)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO),
                                                        os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", script, *args], stderr=subprocess.PIPE,
                            text=True, env=env, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # noqa: PLW1509
    try:
        deadline = time.monotonic() + 240
        while not ready() and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return subprocess.CompletedProcess(proc.args, proc.returncode, "", err)


@pytest.mark.parametrize("workers", [1, 2])
def test_ctrl_c_while_a_record_is_made_keeps_it(tmp_path, workers):
    """A record being made when Ctrl-C comes is finished and saved (a local worker's too: the
    parent waits for it), then the run ends; the task still running has none."""
    done = _interrupted(MAKING, [str(tmp_path), str(workers)],
                        lambda: (tmp_path / "making").exists())
    assert done.returncode == 130, done.stderr
    assert json.loads((tmp_path / "tasks" / "t0.json").read_text())["status"] == "ok"
    assert not (tmp_path / "tasks" / "t1.json").exists()


# -- a real sweep interrupted mid-batch ----------------------------------------------------------

SWEEP = """
import sys
from safeil_sumo.experiments.sweep_executor import run_sweep
from safeil_sumo.scenarios.spec import Task

out, workers, ends = sys.argv[1], int(sys.argv[2]), sys.argv[3].split(",")
specs = [Task.of(index=i, net="straight", policy="analytic", max_time_s=float(t))
         for i, t in enumerate(ends)]
try:
    run_sweep(specs, out, workers=workers, progress=False, batch=64)
except KeyboardInterrupt:
    sys.exit(130)
"""
# [s] each task's simulated time: the short ones end long before the others, in every batch
ENDS = (1.0, 30.0, 1.0, 30.0, 2.0, 30.0)
SHORT = [i for i, t in enumerate(ENDS) if t < 10]


def _records(tasks: Path) -> list[Path]:
    """The record files written (not an atomic write's temporary ``.tmp-*``)."""
    return [p for p in tasks.glob("*.json") if not p.name.startswith(".")]


@pytest.mark.sumo
@pytest.mark.parametrize("workers", [1, 2])
def test_ctrl_c_mid_batch_keeps_the_tasks_that_ended_and_a_rerun_runs_the_rest(tmp_path,
                                                                              workers):
    """One batch per worker (batch 64 > 6 tasks): SIGINT to the sweep's process group once the
    short tasks' records are on disk, while the long ones still run in the same simulation."""
    pytest.importorskip("libsumo")
    out = tmp_path / "sweep"
    tasks = out / "tasks"
    done = _interrupted(SWEEP, [str(out), str(workers), ",".join(map(str, ENDS))],
                        lambda: len(_records(tasks)) >= len(SHORT))
    assert done.returncode == 130, done.stderr
    specs = [Task.of(index=i, net="straight", policy="analytic", max_time_s=t)
             for i, t in enumerate(ENDS)]
    saved = {i for i, s in enumerate(specs) if (tasks / f"{task_id(s)}.json").is_file()}
    assert set(SHORT) <= saved < set(range(len(ENDS))), saved  # ended ones kept, mid-batch
    for i in saved:
        record = json.loads((tasks / f"{task_id(specs[i])}.json").read_text())
        assert record["status"] == "ok" and record["end_reason"] == "timeout"
        assert record["sim_time_s"] == pytest.approx(ENDS[i], abs=0.02)

    summary = run_sweep(specs, out, workers=workers, progress=False, batch=64)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["run_now"] == len(ENDS) - len(saved)  # only the rest ran
    assert (summary["status"] == "ok").all() and len(summary) == len(ENDS)
