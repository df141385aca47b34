"""``python -m safeil_sumo.bench``: speed of the closed loop, side by side in one run.

Measures on ``curved500`` (ego + leader, 0.01 s step, monitors on, planner at 10 Hz):
- bare SUMO stepping of the same scenario (both cars on SUMO's own car-following, no Python
  control) — the floor the closed loop cannot go below;
- our closed loop over libsumo, and the same runner over traci (socket);
- planner inference per call.
Prints a table and writes it as JSON (``--out``). ``--quick`` shortens every measurement (CI).
It asserts nothing about time: numbers are reported, never tested.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from safeil_sumo import policies
from safeil_sumo.features import planner_features
from safeil_sumo.scenarios.catalogue import resolve_net
from safeil_sumo.scenarios.road import load_road
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim.runner import EGO_ID, LEADER_ID, ROUTE_ID, LoopConfig, run_scenario, sumo_args


def bare_sumo_steps_per_s(net: str, steps: int, backend: str = "libsumo") -> float:
    """SUMO stepping the same two-car scenario with its own car-following only."""
    road = load_road(net)
    sc = safety_scenario(road, 0)
    api = sumo_api.start(sumo_args(sc, LoopConfig()), backend=backend)
    try:
        api.route.add(ROUTE_ID, [road.edge_id])
        lane = str(road.ego_lane)
        api.vehicle.add(EGO_ID, ROUTE_ID, depart="now", departLane=lane,
                        departPos=f"{road.path_start_s:.1f}", departSpeed="30")
        api.vehicle.add(LEADER_ID, ROUTE_ID, depart="now", departLane=lane,
                        departPos=f"{road.path_start_s + 55:.1f}", departSpeed="28")
        api.simulation.step()
        t0 = time.perf_counter()
        for _ in range(steps):
            api.simulation.step()
        return steps / (time.perf_counter() - t0)
    finally:
        api.close()


def closed_loop_steps_per_s(net: str, policy_name: str, max_time_s: float,
                            backend: str = "libsumo") -> tuple[float, int]:
    road = load_road(net)
    sc = safety_scenario(road, 0)
    r = run_scenario(sc, policies.load(policy_name),
                     LoopConfig(max_time_s=max_time_s, backend=backend))
    if r.summary["end_reason"] == "error":
        raise RuntimeError(r.summary["error"])
    return r.summary["steps_per_s"], r.summary["steps"]


def planner_us_per_call(policy_name: str, calls: int) -> float:
    policy = policies.load(policy_name)
    f = planner_features([1.75, 0.0, 1e-3], [-1.75, 0.0, 1e-3], 30.0, 27.0, 45.0)
    policy.plan(f)
    t0 = time.perf_counter()
    for _ in range(calls):
        policy.plan(f)
    return (time.perf_counter() - t0) / calls * 1e6


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m safeil_sumo.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="short measurements (for CI)")
    p.add_argument("--policy", default=None, help="planner in the loop (default: the shipped)")
    p.add_argument("--out", type=Path, default=Path("runs/bench.json"))
    args = p.parse_args(argv)
    policy = args.policy or policies.default_policy_name()
    net = str(resolve_net("curved500"))
    sim_s = 5.0 if args.quick else 30.0
    rows: dict[str, float] = {}

    rows["bare_sumo_steps_per_s"] = bare_sumo_steps_per_s(net, int(sim_s / 0.01))
    rows["closed_loop_libsumo_steps_per_s"], _ = closed_loop_steps_per_s(net, policy, sim_s)
    rows["closed_loop_traci_steps_per_s"], _ = closed_loop_steps_per_s(
        net, policy, sim_s / 5, backend="traci")
    rows["planner_us_per_call"] = planner_us_per_call(policy, 2000 if args.quick else 20000)
    rows["closed_loop_x_realtime"] = rows["closed_loop_libsumo_steps_per_s"] * 0.01
    rows["bare_over_closed_loop"] = (rows["bare_sumo_steps_per_s"]
                                     / rows["closed_loop_libsumo_steps_per_s"])
    rows["libsumo_over_traci"] = (rows["closed_loop_libsumo_steps_per_s"]
                                  / rows["closed_loop_traci_steps_per_s"])

    report = {
        "machine": {"cpus": _cpus(), "platform": platform.platform(),
                    "python": platform.python_version()},
        "policy": policy, "quick": args.quick, "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    width = max(map(len, rows))
    print(f"benchmark on curved500, policy {policy} ({'quick' if args.quick else 'full'})")
    for k, v in rows.items():
        print(f"  {k:<{width}}  {v:12.1f}")
    print(f"written: {args.out}")
    return 0


def _cpus() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


if __name__ == "__main__":
    sys.exit(main())
