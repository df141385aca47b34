"""Sweep engine: spec determinism, resume, sequential == parallel == Dask, failures, dead workers,
Wilson intervals and the CLI. Real libsumo on short runs of the straight track (2 s each)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from safeil_sumo.experiments import stats
from safeil_sumo.experiments.sweep_executor import (
    comparable,
    run_sweep,
    run_task,
    task_id,
)
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.scenarios.spec import ScenarioSpec, Task, build_scenario, leader_profile
from safeil_sumo.sweep import main as sweep_main

SHORT = {"net": "straight", "policy": "analytic", "max_time_s": 2.0}


def short_specs(n: int = 4, **kw) -> list[Task]:
    return [Task.of(index=i, **(SHORT | kw)) for i in range(n)]


class Counting:
    """A task function that logs every task it runs to a file (works across processes)."""

    def __init__(self, log: Path, kill_id: str | None = None, sleep_id: str | None = None):
        self.log, self.kill_id, self.sleep_id = log, kill_id, sleep_id

    def __call__(self, spec: Task) -> dict:
        tid = task_id(spec)
        with open(self.log, "a") as f:  # one short O_APPEND write per task
            f.write(tid + "\n")
        if tid == self.kill_id:
            os.kill(os.getpid(), signal.SIGKILL)
        if tid == self.sleep_id:
            time.sleep(900)  # far beyond any machine's run time: only the timeout ends it
        return run_task(spec)

    def runs(self) -> list[str]:
        return self.log.read_text().split() if self.log.exists() else []


# -- specs (no SUMO) -----------------------------------------------------------------------------

def test_spec_draws_depend_only_on_master_seed_and_index(curved500):
    a = build_scenario(ScenarioSpec(index=7, master_seed=3, initial_gap_m=(30, 80)), curved500)
    b = build_scenario(ScenarioSpec(index=7, master_seed=3, initial_gap_m=(30.0, 80.0)),
                       curved500)
    assert a.seed == b.seed and a.initial_gap_m == b.initial_gap_m
    assert 30 <= a.initial_gap_m <= 80
    # constant leader: the same scenario as the single-run CLI's safety_scenario
    ref = safety_scenario(curved500, 7, 3)
    c = build_scenario(ScenarioSpec(index=7, master_seed=3), curved500)
    assert c.seed == ref.seed and c.leader.initial_speed == ref.leader.initial_speed
    other = build_scenario(ScenarioSpec(index=7, master_seed=4), curved500)
    assert other.leader.initial_speed != c.leader.initial_speed


def test_task_id_is_stable_normalised_and_path_safe():
    a = Task.of(leader_speed_range_mps=[25, 32], ego_speed_mps=30)
    b = Task.of(leader_speed_range_mps=(25.0, 32.0), ego_speed_mps=30.0)
    assert task_id(a) == task_id(b)
    assert task_id(a) != task_id(Task.of(index=1))
    assert task_id(a) != task_id(Task.of(safety_filter=True))
    evil = task_id(Task.of(net="../../etc/x y.net.xml", policy="/tmp/../a.safetensors"))
    assert "/" not in evil and ".." not in evil and " " not in evil
    assert Task.from_json(a.to_json()) == a
    guard_off = Task.of(brake_guard=False, time_gap_s=1.2, plan_rate_hz=5)
    assert Task.from_json(guard_off.to_json()) == guard_off  # no brake_guard key: off
    assert "brake_guard" not in guard_off.to_json() and a.to_json()["brake_guard"] is True


def test_spec_rejects_bad_values():
    with pytest.raises(ValueError, match="leader kind"):
        ScenarioSpec(leader_kind="zigzag")
    with pytest.raises(ValueError, match="initial gap"):
        ScenarioSpec(initial_gap_m=(80, 30))
    with pytest.raises(ValueError, match="leader speed"):
        ScenarioSpec(leader_speed_range_mps=(32, 25))


def test_braking_leader_profile():
    spec = ScenarioSpec(leader_kind="braking", brake_time_s=5, brake_decel_mps2=2,
                        brake_to_mps=20)
    prof = leader_profile(spec, 30.0)
    assert prof.speed_at(4.9) == pytest.approx(30.0)
    assert prof.speed_at(7.5) == pytest.approx(25.0)  # 2.5 s at 2 m/s^2
    assert prof.speed_at(100.0) == pytest.approx(20.0)
    assert leader_profile(spec, 18.0).speed_at(100.0) == pytest.approx(18.0)  # already slower


# -- statistics ----------------------------------------------------------------------------------

def test_wilson_interval_hand_computed():
    # p = 0.7, z^2/n = 0.38416: centre 0.89208 / 1.38416 = 0.64448,
    # half = 1.96 sqrt(0.021 + 0.009604) / 1.38416 = 0.24772
    low, high = stats.wilson_interval(7, 10)
    assert low == pytest.approx(0.39677, abs=1e-4) and high == pytest.approx(0.89221, abs=1e-4)
    assert stats.wilson_interval(0, 10)[0] == 0.0 and stats.wilson_interval(10, 10)[1] == 1.0
    assert stats.wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        stats.wilson_interval(3, 2)


def test_breakdown_counts_flags_and_excludes_failed_tasks():
    df = pd.DataFrame({
        "policy": ["a"] * 4 + ["b"] * 3,
        "status": ["ok", "ok", "ok", "failed", "ok", "ok", "ok"],
        "completed": [True, False, False, None, False, False, False],
        "path_completed": [1.0, 0.5, 0.2, None, 0.1, 0.3, 0.2],
        "flag": ["", "ttc", "lane_departure", None, "lane_departure", "lane_departure", "ttc"],
        "min_ttc_s": [5.0, 0.9, 3.0, None, 2.0, 2.0, 0.5],
    })
    t = stats.breakdown(df, by=["policy"]).set_index("policy")
    assert t.loc["a", "n"] == 4 and t.loc["a", "failed"] == 1 and t.loc["a", "completed"] == 1
    assert t.loc["a", "completion_rate"] == pytest.approx(1 / 3)
    assert (t.loc["a", "ci_low"], t.loc["a", "ci_high"]) == pytest.approx(
        stats.wilson_interval(1, 3))
    assert t.loc["a", "mean_path_completed"] == pytest.approx(1.7 / 3)
    assert t.loc["b", "flag_lane_departure"] == 2 and t.loc["b", "flag_ttc"] == 1
    assert t.loc["b", "flags"] == "lane_departure:2 ttc:1"
    assert "[" in stats.format_breakdown(t.reset_index())


# -- sweeps with real libsumo ----------------------------------------------------------------------

@pytest.mark.sumo
def test_resume_runs_only_missing_tasks(tmp_path):
    specs = short_specs(4)
    counter = Counting(tmp_path / "runs.log")
    first = run_sweep(specs, tmp_path / "out", task_fn=counter, progress=False)
    assert len(counter.runs()) == 4 and (first["status"] == "ok").all()
    assert list(first["task_id"]) == [task_id(s) for s in specs]
    removed = [task_id(specs[1]), task_id(specs[3])]
    for tid in removed:
        (tmp_path / "out" / "tasks" / f"{tid}.json").unlink()
    second = run_sweep(specs, tmp_path / "out", task_fn=counter, progress=False)
    assert counter.runs()[4:] == removed  # only the missing ones, in task order
    pd.testing.assert_frame_equal(comparable(first), comparable(second))
    on_disk = pd.read_csv(tmp_path / "out" / "summary.csv")
    assert len(on_disk) == 4 and (tmp_path / "out" / "manifest.json").is_file()
    run_sweep(specs, tmp_path / "out", task_fn=counter, progress=False)
    assert len(counter.runs()) == 6  # nothing left to do


@pytest.mark.sumo
def test_sequential_equals_parallel_and_same_seed_twice(tmp_path):
    specs = short_specs(4, initial_gap_m=(30, 80), radar_noise_m=0.5)
    seq = run_sweep(specs, tmp_path / "seq", workers=1, progress=False)
    par = run_sweep(specs, tmp_path / "par", workers=2, progress=False)
    again = run_sweep(specs, tmp_path / "again", workers=1, progress=False)
    assert (seq["status"] == "ok").all() and seq["steps"].gt(0).all()
    pd.testing.assert_frame_equal(comparable(seq), comparable(par))
    pd.testing.assert_frame_equal(comparable(seq), comparable(again))
    assert seq["leader_speed_mps"].nunique() == 4


@pytest.mark.sumo
def test_failures_are_recorded_and_others_complete(tmp_path):
    specs = [
        Task.of(index=0, **SHORT),
        Task.of(index=1, **(SHORT | {"policy": str(tmp_path / "nope.safetensors")})),
        Task.of(index=2, **(SHORT | {"net": "no_such_track"})),
        Task.of(index=3, **SHORT),
    ]
    out = run_sweep(specs, tmp_path / "out", workers=2, progress=False)
    assert list(out["status"]) == ["ok", "failed", "failed", "ok"]
    assert out.loc[1, "error"].startswith("PolicyError: policy file")
    assert out.loc[2, "error"].startswith("NetworkError: unknown track 'no_such_track'")


@pytest.mark.sumo
def test_killed_worker_is_recorded_and_the_sweep_goes_on(tmp_path):
    specs = short_specs(5)
    victim = task_id(specs[1])
    counter = Counting(tmp_path / "runs.log", kill_id=victim)
    out = run_sweep(specs, tmp_path / "out", workers=2, task_fn=counter, progress=False)
    assert list(out["status"]) == ["ok", "failed", "ok", "ok", "ok"]
    assert "WorkerDied" in out.loc[1, "error"] and "-9" in out.loc[1, "error"]
    assert sorted(counter.runs()) == sorted(task_id(s) for s in specs)
    # a failed record counts as done ...
    run_sweep(specs, tmp_path / "out", workers=2, task_fn=counter, progress=False)
    assert len(counter.runs()) == 5
    # ... unless retried: only the failed task runs again
    counter.kill_id = None
    retried = run_sweep(specs, tmp_path / "out", workers=2, task_fn=counter, progress=False,
                        retry_failed=True)
    assert counter.runs()[5:] == [victim] and (retried["status"] == "ok").all()


@pytest.mark.sumo
def test_task_timeout_kills_a_stuck_worker(tmp_path):
    specs = short_specs(3)
    counter = Counting(tmp_path / "runs.log", sleep_id=task_id(specs[0]))
    t0 = time.monotonic()
    out = run_sweep(specs, tmp_path / "out", workers=2, task_fn=counter, progress=False,
                    task_timeout_s=1.0)
    # a hang guard, not a speed test: without the kill the stuck task would sleep 900 s
    assert time.monotonic() - t0 < 300
    assert list(out["status"]) == ["failed", "ok", "ok"]
    assert out.loc[0, "error"].startswith("TaskTimeout")


@pytest.mark.sumo
def test_dask_cluster_gives_the_sequential_results(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    specs = short_specs(4, initial_gap_m=(30, 80))
    seq = run_sweep(specs, tmp_path / "seq", workers=1, progress=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        dask_out = run_sweep(specs, tmp_path / "dask", scheduler=cluster.scheduler_address,
                             progress=False)
        dask_batched = run_sweep(specs, tmp_path / "dask_batched", progress=False, batch=2,
                                 scheduler=cluster.scheduler_address)
    pd.testing.assert_frame_equal(comparable(seq), comparable(dask_out))
    pd.testing.assert_frame_equal(comparable(seq), comparable(dask_batched), check_exact=False,
                                  rtol=1e-9, atol=1e-9)
    assert len(list((tmp_path / "dask" / "tasks").glob("*.json"))) == 4


# -- CLI -----------------------------------------------------------------------------------------

@pytest.mark.sumo
def test_cli_grid_breakdown_and_bad_arguments(tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["--net", "straight", "--policy", "analytic", "--scenarios", "2",
            "--max-time-s", "2", "--safety-filter", "both", "--gap-range-m", "30", "80",
            "--no-progress", "--out", str(out)]
    assert sweep_main(args) == 0
    printed = capsys.readouterr().out
    assert "rate [95% CI]" in printed and "4 tasks, 0 failed" in printed
    summary = pd.read_csv(out / "summary.csv")
    assert len(summary) == 4 and sorted(summary["safety_filter"]) == [False, False, True, True]
    assert np.all((summary["initial_gap_m"] >= 30) & (summary["initial_gap_m"] <= 80))
    assert {p.parent for p in out.rglob("*.json")} <= {out, out / "tasks"}

    assert sweep_main(["--net", "nowhere", "--policy", "analytic", "--out", str(out)]) == 2
    assert "unknown track" in capsys.readouterr().err
    assert sweep_main(["--policy", str(tmp_path / "x.safetensors"), "--out", str(out)]) == 2
    with pytest.raises(SystemExit) as exc:
        sweep_main(["--gap-m", "40", "--gap-range-m", "30", "80"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        sweep_main(["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"])
    assert exc.value.code == 2


# -- batches: many scenarios per SUMO simulation --------------------------------------------------

def test_batches_group_shareable_specs_in_order():
    from safeil_sumo.experiments.sweep_executor import batch_key, batches

    specs = (short_specs(5) + short_specs(2, policy="bc")
             + [Task.of(index=9, net="n74", from_km=0.0, to_km=1.0, traffic="light")])
    units = batches(specs, 2)
    assert [len(u) for u in units] == [2, 2, 1, 2, 1]
    assert [s for u in units for s in u] == specs  # every spec once, grouped in order
    assert {batch_key(s) for s in units[0] + units[1] + units[2]} == {batch_key(specs[0])}
    assert batch_key(specs[-1]) is None  # traffic: SUMO's vehicles are per simulation
    with pytest.raises(ValueError, match="batch size"):
        batches(specs, 0)
    # every worker gets a batch: 5 shareable specs on 2 workers -> 3 + 2
    assert [len(u) for u in batches(specs[:5], 32, workers=2)] == [3, 2]


@pytest.mark.sumo
def test_batched_sweep_equals_one_simulation_per_scenario(tmp_path):
    """The same records with --batch 3 on 2 workers as one scenario per simulation, a spec
    that cannot be built failing alone inside its batch."""
    specs = short_specs(7, initial_gap_m=(30, 80), radar_noise_m=0.5)
    specs[2] = Task.of(index=2, **(SHORT | {"policy": str(tmp_path / "nope.safetensors")}))
    one = run_sweep(specs, tmp_path / "one", workers=1, progress=False)
    batched = run_sweep(specs, tmp_path / "batched", workers=2, progress=False, batch=3)
    assert list(batched["status"]) == ["ok", "ok", "failed"] + ["ok"] * 4
    assert batched.loc[2, "error"].startswith("PolicyError: policy file")
    ok = one["status"] == "ok"
    pd.testing.assert_frame_equal(comparable(one[ok]), comparable(batched[ok]), check_exact=False,
                                  rtol=1e-9, atol=1e-9)


@pytest.mark.sumo
def test_killed_worker_loses_only_the_tasks_of_its_batch_not_ended(tmp_path):
    """Batch (0, 1) on one worker: task 0's record was sent as it ended, task 1 kills it."""
    specs = short_specs(5)
    counter = Counting(tmp_path / "runs.log", kill_id=task_id(specs[1]))
    out = run_sweep(specs, tmp_path / "out", workers=2, task_fn=counter, progress=False, batch=2)
    assert list(out["status"]) == ["ok", "failed", "ok", "ok", "ok"]
    assert "WorkerDied" in out.loc[1, "error"]


def test_a_retrained_checkpoint_never_resumes_the_results_of_the_one_before(tmp_path):
    """The task id carries the policy's weights: the same spec with another checkpoint at the
    same path gets a new id (a sweep or replay then runs it again), the same weights the same."""
    import json
    import shutil

    from safeil_sumo.planners import registry as reg

    ckpt = tmp_path / "m.safetensors"
    for name in ("safetensors", "json"):
        shutil.copyfile(reg.MODELS_DIR / f"bc.{name}", tmp_path / f"m.{name}")
    spec = Task.of(net="curved500", policy=str(ckpt))
    before = task_id(spec)
    assert task_id(spec) == before
    assert reg.fingerprint(str(ckpt)) == reg.fingerprint("bc")
    for name in ("safetensors", "json"):  # "retrained": other weights, same path
        shutil.copyfile(reg.MODELS_DIR / f"safeil_paper.{name}", tmp_path / f"m.{name}")
    assert task_id(spec) != before
    sha = json.loads((reg.MODELS_DIR / "safeil_paper.json").read_text())["weights_sha256"]
    assert reg.fingerprint(str(ckpt)) == sha
    assert reg.fingerprint("analytic") == "analytic"
