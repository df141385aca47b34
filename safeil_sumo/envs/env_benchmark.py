"""``python -m safeil_sumo.envs.env_benchmark``: transitions/s and memory of the Gymnasium envs.

On ``safeil_sumo/Curved500-v0`` (10 Hz decisions, 0.01 s physics, the analytic planner's plans
as actions, resets included), each part in a fresh process: the single env; the native vector
env at ``--n`` (one SUMO); Gymnasium's SyncVectorEnv of ``--n`` single envs, each with its own
SUMO process behind traci (libsumo runs one simulation per process, so this is how N envs share
one Python process: sumo-rl's situation); and Gymnasium's AsyncVectorEnv of single envs (a
process and a libsumo per sub-env) at ``--async-n``. Memory: each process's peak RSS (the
SyncVectorEnv's SUMO processes and the AsyncVectorEnv's workers: the largest child's). Beside
the wall-clock rate, the single and native vector parts report transitions per CPU second of
their process (``time.process_time``: on a shared machine, less sensitive to other jobs than
wall time). Reports numbers, asserts nothing; ``safeil_sumo.bench`` runs it in a subprocess
(``--json``).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from typing import Any

import gymnasium as gym
import numpy as np

ENV_ID = "safeil_sumo/Curved500-v0"
MIN_STEPS = 5  # [-] vector steps measured at least, however long they take


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _children_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def measure(part: str, n: int, seconds: float, step_s: float = 0.01) -> dict:
    """Transitions/s of one part over ``seconds`` of stepping (after a warm-up reset), at the
    physics step ``step_s`` [s] (0.01: 10 physics steps per 10 Hz decision; 0.1: one)."""
    import safeil_sumo.envs  # noqa: F401 - registers the ids
    from safeil_sumo.planners.analytic import AnalyticPlanner

    planner = AnalyticPlanner()
    if part == "single":
        env = gym.make(ENV_ID, step_s=step_s)
        obs, _ = env.reset(seed=0)
        count, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds:
            a = np.asarray(planner.plan(np.asarray(obs, float)[None]), float).reshape(6)
            obs, _, te, tr, _ = env.step(a)
            count += 1
            if te or tr:
                obs, _ = env.reset()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        env.close()
        return {"part": part, "n": 1, "step_s": step_s, "transitions_per_s": count / wall,
                "transitions_per_cpu_s": count / cpu, "peak_rss_mb": _rss_mb()}
    mode = {"vector": "vector_entry_point", "sync": "sync", "async": "async"}[part]
    backend: dict[str, Any] = {"backend": "traci"} if part == "sync" else {}
    venv = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode=mode, step_s=step_s, **backend)
    obs, _ = venv.reset(seed=0)
    count, t0, c0 = 0, time.perf_counter(), time.process_time()
    # at least MIN_STEPS vector steps: a SyncVectorEnv of 64 traci envs takes seconds per step
    while time.perf_counter() - t0 < seconds or count < MIN_STEPS * n:
        actions = np.asarray(planner.plan(np.asarray(obs, float)), float).reshape(n, 6)
        obs, _, _, _, _ = venv.step(actions)
        count += n
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    venv.close()
    out = {"part": part, "n": n, "step_s": step_s, "transitions_per_s": count / wall,
           "peak_rss_mb": _rss_mb()}
    if part in ("sync", "async"):  # the SUMO processes' / workers' CPU time is not ours
        out["child_peak_rss_mb"] = _children_rss_mb()
    else:
        out["transitions_per_cpu_s"] = count / cpu
    return out


def run_part(part: str, n: int, seconds: float, step_s: float = 0.01) -> dict:
    """One part in a fresh process (its own libsumo, its own peak RSS)."""
    out = subprocess.run([sys.executable, "-m", "safeil_sumo.envs.env_benchmark", "--part", part,
                          "--n", str(n), "--seconds", str(seconds), "--step-s", str(step_s),
                          "--json"],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("all", "single", "vector", "sync", "async"),
                    default="all")
    ap.add_argument("--n", type=int, default=64,
                    help="sub-envs of the native vector env and of the SyncVectorEnv (traci)")
    ap.add_argument("--async-n", type=int, default=4,
                    help="sub-envs (processes) of the AsyncVectorEnv baseline")
    ap.add_argument("--seconds", type=float, default=20.0, help="stepping time per part [s]")
    ap.add_argument("--step-s", type=float, default=0.01,
                    help="physics step [s] (the envs' step_s; decisions stay at 10 Hz)")
    ap.add_argument("--json", action="store_true", help="print one JSON line")
    args = ap.parse_args(argv)
    if args.part != "all":
        row = measure(args.part, args.n, args.seconds, args.step_s)
        print(json.dumps(row) if args.json else row)
        return 0
    rows = [run_part("single", 1, args.seconds, args.step_s),
            run_part("vector", args.n, args.seconds, args.step_s),
            run_part("sync", args.n, args.seconds, args.step_s),
            run_part("async", args.async_n, args.seconds, args.step_s)]
    rate = {r["part"]: r["transitions_per_s"] for r in rows}
    result = {"rows": rows,
              "vector_over_single": rate["vector"] / rate["single"],
              "vector_over_sync": rate["vector"] / rate["sync"],
              "vector_over_async": rate["vector"] / rate["async"]}
    if args.json:
        print(json.dumps(result))
    else:
        for r in rows:
            extra = (f", largest child's peak {r['child_peak_rss_mb']:.0f} MB"
                     if "child_peak_rss_mb" in r else "")
            cpu = (f" ({r['transitions_per_cpu_s']:.0f} per CPU second)"
                   if "transitions_per_cpu_s" in r else "")
            print(f"{r['part']:>7} N={r['n']:<3} {r['transitions_per_s']:9.0f} transitions/s"
                  f"{cpu}  peak RSS {r['peak_rss_mb']:.0f} MB{extra}")
        print(f"vector / single: {result['vector_over_single']:.1f}x; vector / sync (traci): "
              f"{result['vector_over_sync']:.1f}x; vector / async: "
              f"{result['vector_over_async']:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
