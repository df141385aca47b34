"""``python -m safeil_sumo.bench``: speed of the closed loop, side by side in one run.

Measures on ``curved500`` (ego + leader, 0.01 s step, monitors on, planner at 10 Hz):
- bare SUMO stepping of the same scenario (both cars on SUMO's own car-following, no Python
  control) — the floor the closed loop cannot go below;
- SUMO's share of a closed-loop step: the loop's own libsumo calls (ego placement, setSpeed, step,
  leader reads) replayed along a recorded run, no Python maths;
- our closed loop over libsumo, and the same runner over traci (socket);
- planner inference per call: the analytic planner, and a small MLP trained here, numpy vs torch;
- data processing: NGSIM I-80 pairs import + processing pipeline, rows per second;
- SafeIL training wall time and samples per second on the pipeline's tuples;
- peak memory (RSS high-water mark) of a closed-loop run in a fresh process;
- N scenarios side by side in one SUMO simulation (``sim.batch.run_batch``) for N in
  BATCH_SIZES: ego-steps/s, the ratio to the scalar loop measured in the same run, and the time
  per ego-step of each stage;
- the loop on the multi-edge n74 road against one edge (µs per step) and a 10 km n74 drive's
  wall time, with a scripted leader and among SUMO's default traffic;
- a curved500 sweep with 1 and 2 workers (wall time, parallel efficiency, worker peak memory),
  one scenario per simulation and batched (``sweep --batch``);
- the Gymnasium envs (``python -m safeil_sumo.envs.env_benchmark`` in a subprocess):
  transitions/s of the single env, the native vector env at N = 64, Gymnasium's SyncVectorEnv
  of 64 traci envs and an AsyncVectorEnv of 4, peak memory.
Prints a table and writes it as JSON (``--out``). ``--quick`` shortens every measurement (CI).
It asserts nothing about time: numbers are reported, never tested. A part whose input is
missing (the NGSIM file) is skipped with a note.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from safeil_sumo.cli_args import CommandParser, add_policy_option, interruptible, one_policy
from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.core.features import planner_features
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.roads.catalogue import resolve_net
from safeil_sumo.roads.road import load_road
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim import sumo_api
from safeil_sumo.sim.loop_types import LoopConfig
from safeil_sumo.sim.runner import run_scenario
from safeil_sumo.sim.sumo_setup import (
    EGO_ID,
    LEADER_ID,
    ROUTE_ID,
    _configure,
    sumo_args,
    sumo_lane_position,
)
from safeil_sumo.sim.vehicle import VehicleParams

REPO = Path(__file__).resolve().parent.parent
NGSIM_PAIRS = REPO.parent / "shared" / "data" / "ngsim_i80" / "i80_pairs.parquet"


def _add_two_cars(api, road) -> None:
    """Ego at the test path's start at 30 m/s, leader 55 m ahead at 28 m/s, on the ego lane."""
    api.route.add(ROUTE_ID, [road.edge_id])
    lane = str(road.ego_lane)
    api.vehicle.add(EGO_ID, ROUTE_ID, depart="now", departLane=lane,
                    departPos=f"{road.path_start_s:.1f}", departSpeed="30")
    api.vehicle.add(LEADER_ID, ROUTE_ID, depart="now", departLane=lane,
                    departPos=f"{road.path_start_s + 55:.1f}", departSpeed="28")


def bare_sumo_steps_per_s(net: str, steps: int, backend: str = "libsumo") -> float:
    """SUMO stepping the same two-car scenario with its own car-following only."""
    road = load_road(net)
    sc = safety_scenario(road, 0)
    api = sumo_api.start(sumo_args(sc, LoopConfig()), backend=backend)
    try:
        _add_two_cars(api, road)
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
    r = run_scenario(sc, planner_registry.load(policy_name),
                     LoopConfig(max_time_s=max_time_s, backend=backend))
    if r.summary["end_reason"] == "error":
        raise RuntimeError(r.summary["error"])
    return r.summary["steps_per_s"], r.summary["steps"]


def sumo_share_us_per_step(net: str, sim_s: float) -> tuple[float, float]:
    """The closed loop's libsumo calls alone, replayed along a recorded run: ``(us per step,
    of which placing the ego)``, placed as the loop does (``moveTo`` on its lane while inside
    it, else ``moveToXY``). The rest of a closed-loop step is our Python."""
    from safeil_sumo.core.geometry import yaw_to_sumo_angle
    from safeil_sumo.planners.analytic import AnalyticPlanner

    road = load_road(net)
    sc = safety_scenario(road, 0)
    log = run_scenario(sc, AnalyticPlanner(), LoopConfig(max_time_s=sim_s)).log
    half_width = 0.5 * road.lanes[road.ego_lane].width
    traj = list(zip(log["front_x"].tolist(), log["front_y"].tolist(),
                    [yaw_to_sumo_angle(y) for y in log["yaw"].tolist()], log["v"].tolist(),
                    log["s"].tolist(), (log["d"].abs() <= half_width).tolist(), strict=True))
    api = sumo_api.start(sumo_args(sc, LoopConfig()))
    try:
        _add_two_cars(api, road)
        for veh_id in (EGO_ID, LEADER_ID):
            _configure(api, veh_id, VehicleParams())
        api.simulation.step()
        vm, sim = api.vehicle, api.simulation
        move = 0.0
        t0 = time.perf_counter()
        for x, y, angle, v, s, inside in traj:
            a = time.perf_counter()
            if inside:
                vm.moveTo(EGO_ID, *sumo_lane_position(road, s, v * 0.01))
            else:
                vm.moveToXY(EGO_ID, "", -1, x, y, angle, 2)
            move += time.perf_counter() - a
            vm.setSpeed(EGO_ID, v)
            vm.setSpeed(LEADER_ID, 28.0)
            sim.step()
            sim.getCollidingVehiclesIDList()
            vm.getPosition(LEADER_ID)
            vm.getAngle(LEADER_ID)
            vm.getSpeed(LEADER_ID)
        total = time.perf_counter() - t0
        return total / len(traj) * 1e6, move / len(traj) * 1e6
    finally:
        api.close()


def planner_us_per_call(policy, calls: int) -> float:
    """Mean time [us] of ``policy.plan`` on one feature vector (a policy object or a name)."""
    if isinstance(policy, str):
        policy = planner_registry.load(policy)
    f = planner_features([1.75, 0.0, 1e-3], [-1.75, 0.0, 1e-3], 30.0, 27.0, 45.0)
    policy.plan(f)
    t0 = time.perf_counter()
    for _ in range(calls):
        policy.plan(f)
    return (time.perf_counter() - t0) / calls * 1e6


def torch_us_per_call(model, calls: int) -> float:
    """Mean time [us] of one torch forward on one feature vector (no grad, 1 thread)."""
    import torch

    f = torch.as_tensor(
        planner_features([1.75, 0.0, 1e-3], [-1.75, 0.0, 1e-3], 30.0, 27.0, 45.0)).float()[None]
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.inference_mode():
            model(f)
            t0 = time.perf_counter()
            for _ in range(calls):
                model(f)
            return (time.perf_counter() - t0) / calls * 1e6
    finally:
        torch.set_num_threads(prev)


def data_and_training(quick: bool, rows: dict, notes: list[str], calls: int) -> None:
    """NGSIM import + pipeline rows/s, SafeIL training, and the trained MLP's inference cost."""
    if not NGSIM_PAIRS.is_file():
        notes.append(f"skipped data processing and training: {NGSIM_PAIRS} is missing")
        return
    from safeil_sumo.data.importers import import_ngsim_pairs
    from safeil_sumo.data.pipeline import run_pipeline

    t0 = time.perf_counter()
    drive = import_ngsim_pairs(NGSIM_PAIRS)
    t1 = time.perf_counter()
    tuples, _ = run_pipeline(drive, source="ngsim")
    t2 = time.perf_counter()
    rows["ngsim_rows"] = len(drive)
    rows["ngsim_import_rows_per_s"] = len(drive) / (t1 - t0)
    rows["pipeline_rows_per_s"] = len(drive) / (t2 - t1)
    rows["import_plus_pipeline_rows_per_s"] = len(drive) / (t2 - t0)
    rows["tuples"] = len(tuples)

    try:
        import torch  # noqa: F401
    except ImportError:
        notes.append("skipped training and torch inference: torch is not installed")
        return
    from safeil_sumo.learn.checkpoint import save_checkpoint
    from safeil_sumo.learn.inference import load_policy
    from safeil_sumo.learn.trainer import TrainConfig, split_by_maneuver, train

    train_set, val_set = split_by_maneuver(tuples, 0.2, seed=0)
    epochs = 3 if quick else 30
    cfg = TrainConfig(method="safeil", max_epochs=epochs, patience=epochs)
    t0 = time.perf_counter()
    model, hist = train(train_set, val_set, cfg, progress=False)
    wall = time.perf_counter() - t0
    n_epochs = len(hist.epochs)
    rows["train_tuples"] = len(train_set)
    rows["train_epochs"] = n_epochs
    rows["train_wall_s"] = wall
    rows["train_samples_per_s"] = len(train_set) * n_epochs / wall
    with tempfile.TemporaryDirectory() as tmp:
        weights, _ = save_checkpoint(Path(tmp) / "bench", model, name="bench",
                                     horizon=float(train_set.horizon), train_config=cfg)
        mlp = load_policy(weights)
    rows["planner_mlp_numpy_us_per_call"] = planner_us_per_call(mlp, calls)
    rows["planner_mlp_torch_us_per_call"] = torch_us_per_call(model, calls // 4)


_PEAK_KB = """
import resource

def peak_kb():
    # VmHWM: this process's own RSS high-water mark. ru_maxrss of RUSAGE_SELF would also count
    # the parent's memory at fork, which Linux carries across exec (here: the bench with torch).
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
"""

_PEAK_SCRIPT = _PEAK_KB + """
import sys
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.roads.catalogue import resolve_net
from safeil_sumo.roads.road import load_road
from safeil_sumo.scenarios.safety import safety_scenario
from safeil_sumo.sim.runner import LoopConfig, run_scenario
road = load_road(resolve_net("curved500"))
r = run_scenario(safety_scenario(road, 0), planner_registry.load(sys.argv[1]),
                 LoopConfig(max_time_s=float(sys.argv[2])))
print(peak_kb())  # KiB
"""


def closed_loop_peak_rss_mb(policy_name: str, sim_s: float) -> float:
    """RSS high-water mark [MB] of a fresh process that runs one closed-loop scenario."""
    out = subprocess.run([sys.executable, "-c", _PEAK_SCRIPT, policy_name, str(sim_s)],
                         check=True, capture_output=True, text=True, cwd=REPO)
    return int(out.stdout.split()[-1]) / 1024.0


_SWEEP_SCRIPT = _PEAK_KB + """
import json, sys, time
from safeil_sumo.experiments.sweep_executor import run_sweep
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.scenarios.spec import ScenarioSpec, Task
n, workers, out, max_time = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
batch, policy = int(sys.argv[5]), sys.argv[6]
specs = [Task(ScenarioSpec(net="curved500", index=i,
                           max_time_s=None if max_time == "none" else float(max_time)),
              PlannerRef(policy))
         for i in range(n)]
t0 = time.perf_counter()
summary = run_sweep(specs, out, workers=workers, progress=False, batch=batch)
wall = time.perf_counter() - t0
print(json.dumps({"wall_s": wall, "tasks": len(summary),
                  "self_kb": peak_kb(),
                  "children_kb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))
"""


def sweep_rows(quick: bool, policy: str, rows: dict, notes: list[str]) -> None:
    """curved500 sweeps with 1 and 2 workers, each in a fresh process: one scenario per
    simulation (100 scenarios) and batched (1,000 scenarios, the sweep's default batch)."""
    from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH

    plans = ([("", 6, "5", 1), ("_batched", 6, "5", 3)] if quick
             else [("", 100, "none", 1), ("_batched", 1000, "none", DEFAULT_BATCH)])
    for tag, n, max_time, batch in plans:
        walls = {}
        for workers in (1, 2):
            with tempfile.TemporaryDirectory() as tmp:
                out = subprocess.run(
                    [sys.executable, "-c", _SWEEP_SCRIPT, str(n), str(workers), tmp, max_time,
                     str(batch), policy], check=True, capture_output=True, text=True, cwd=REPO)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            walls[workers] = res["wall_s"]
            rows[f"sweep{n}{tag}_{workers}w_wall_s"] = res["wall_s"]
            rows[f"sweep{n}{tag}_{workers}w_scenarios_per_s"] = n / res["wall_s"]
            # 1 worker runs in the sweep's own process; 2 workers are forked children
            # (ru_maxrss of RUSAGE_CHILDREN: the largest child, shared copy-on-write pages
            # included)
            peak_kb = res["self_kb"] if workers == 1 else res["children_kb"]
            rows[f"sweep{tag}_{workers}w_worker_peak_rss_mb"] = peak_kb / 1024.0
        rows[f"sweep{tag}_parallel_efficiency_2w"] = walls[1] / (2.0 * walls[2])
    if not quick:
        rows["sweep_batched_over_one_per_simulation"] = (
            rows["sweep1000_batched_2w_scenarios_per_s"] / rows["sweep100_2w_scenarios_per_s"])


def multi_edge_rows(policy: str, quick: bool, rows: dict) -> None:
    """The loop on a multi-edge route (the n74 road: junctions, internal lanes, ramps) against
    one edge (curved500), µs per step of the loop alone; the wall time of a 10 km n74 drive
    (task start included) with a scripted 30 m/s leader and, full runs only, among SUMO's
    default traffic."""
    from safeil_sumo.experiments.sweep_executor import run_task
    from safeil_sumo.planners.registry import PlannerRef
    from safeil_sumo.scenarios.spec import ScenarioSpec, Task

    def task(**kw) -> tuple[float, dict]:
        t0 = time.perf_counter()
        record = run_task(Task(ScenarioSpec(**kw), PlannerRef(policy)))
        if record["status"] != "ok":
            raise RuntimeError(f"bench drive {kw} failed: {record.get('error')}")
        return time.perf_counter() - t0, record

    km = 1.0 if quick else 10.0
    _, single = task(net="curved500", max_time_s=5.0 if quick else 30.0)
    wall, multi = task(net="n74", from_km=4.0, to_km=4.0 + km, ego_speed_mps=30.0,
                       leader_speed_range_mps=(30.0, 30.0))
    rows["single_edge_loop_us_per_step"] = 1e6 / single["steps_per_s"]
    rows["multi_edge_loop_us_per_step"] = 1e6 / multi["steps_per_s"]
    rows["multi_edge_over_single_edge"] = (rows["multi_edge_loop_us_per_step"]
                                           / rows["single_edge_loop_us_per_step"])
    rows[f"n74_{km:.0f}km_drive_wall_s"] = wall
    if not quick:
        wall, _ = task(net="n74", from_km=4.0, to_km=4.0 + km, traffic="default")
        rows[f"n74_{km:.0f}km_drive_traffic_wall_s"] = wall


BATCH_SIZES = (1, 8, 32, 64, 128, 256)


def batched_rows(net: str, policy_name: str, sim_s: float, quick: bool, rows: dict) -> None:
    """Ego-steps/s of ``run_batch`` (lane placement, the sweeps') for N in BATCH_SIZES and of
    ``run_scenario`` (today's defaults) one scenario after another on the same scenarios, SUMO
    start included in both; the batch's time per ego-step per stage (StageClock)."""
    from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH
    from safeil_sumo.sim.batch import run_batch
    from safeil_sumo.sim.stepper import StageClock

    road = load_road(net)
    policy = planner_registry.load(policy_name)
    loop = LoopConfig(max_time_s=sim_s)
    sizes = (1, 8) if quick else BATCH_SIZES
    scenarios = [safety_scenario(road, i) for i in range(max(sizes))]
    t0 = time.perf_counter()
    steps = sum(run_scenario(sc, policy, loop).summary["steps"] for sc in scenarios[:8])
    scalar = steps / (time.perf_counter() - t0)
    rows["scalar_ego_steps_per_s"] = scalar
    for n in sizes:
        for placement in ("lane", "xy"):
            clock = StageClock()
            t0 = time.perf_counter()
            steps = sum(r.summary["steps"] for r in run_batch(
                scenarios[:n], policy, LoopConfig(max_time_s=sim_s, ego_placement=placement),
                clock=clock))
            rate = steps / (time.perf_counter() - t0)
            tag = f"n{n}" if placement == "lane" else f"n{n}_xy"
            rows[f"batched_ego_steps_per_s_{tag}"] = rate
            rows[f"batched_over_scalar_{tag}"] = rate / scalar
            if placement == "lane":
                for stage, us in clock.us_per_ego_step().items():
                    rows[f"batched_{tag}_{stage}_us_per_ego_step"] = us
    n = DEFAULT_BATCH if DEFAULT_BATCH in sizes else max(sizes)
    rows["batched_ego_steps_per_s"] = rows[f"batched_ego_steps_per_s_n{n}"]
    rows["batched_over_scalar"] = rows[f"batched_over_scalar_n{n}"]


def gym_rows(quick: bool, rows: dict) -> None:
    """The Gymnasium envs (``python -m safeil_sumo.envs.env_benchmark`` in a subprocess, each
    part in a fresh process): transitions/s of the single env, the native vector env and a
    SyncVectorEnv of traci envs (a SUMO process each) at N = 64 (8 quick), an AsyncVectorEnv of
    4 single envs (a process each), and peak memory."""
    n = 8 if quick else 64
    out = subprocess.run([sys.executable, "-m", "safeil_sumo.envs.env_benchmark", "--n", str(n),
                          "--seconds", "3" if quick else "20", "--json"],
                         capture_output=True, text=True, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    single, vector, sync, async_ = result["rows"]
    rows["gym_single_transitions_per_s"] = single["transitions_per_s"]
    rows[f"gym_vector_n{n}_transitions_per_s"] = vector["transitions_per_s"]
    rows[f"gym_sync_traci_n{n}_transitions_per_s"] = sync["transitions_per_s"]
    rows[f"gym_async_n{async_['n']}_transitions_per_s"] = async_["transitions_per_s"]
    rows["gym_vector_over_single"] = result["vector_over_single"]
    rows["gym_vector_over_sync"] = result["vector_over_sync"]
    rows["gym_vector_over_async"] = result["vector_over_async"]
    rows[f"gym_vector_n{n}_peak_rss_mb"] = vector["peak_rss_mb"]


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.bench", description=__doc__,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="short measurements (for CI)")
    add_policy_option(p, None, "planner in the loop", many=False)
    p.add_argument("--no-extras", action="store_true",
                   help="closed loop and planner only (no data, training, memory, sweep)")
    p.add_argument("--out", type=Path, default=Path("runs/bench.json"))
    return p


@interruptible
def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    policy = (one_policy(p, args, "benchmark each planner in turn")
              or planner_registry.default_policy_name())
    net = str(resolve_net("curved500"))
    sim_s = 5.0 if args.quick else 30.0
    calls = 2000 if args.quick else 20000
    rows: dict[str, float] = {}
    notes: list[str] = []

    rows["bare_sumo_steps_per_s"] = bare_sumo_steps_per_s(net, int(sim_s / 0.01))
    rows["closed_loop_libsumo_steps_per_s"], _ = closed_loop_steps_per_s(net, policy, sim_s)
    rows["closed_loop_traci_steps_per_s"], _ = closed_loop_steps_per_s(
        net, policy, sim_s / 5, backend="traci")
    rows["closed_loop_us_per_step"] = 1e6 / rows["closed_loop_libsumo_steps_per_s"]
    rows["sumo_share_us_per_step"], rows["sumo_ego_placement_us_per_step"] = (
        sumo_share_us_per_step(net, sim_s))
    rows["python_us_per_step"] = rows["closed_loop_us_per_step"] - rows["sumo_share_us_per_step"]
    rows["planner_us_per_call"] = planner_us_per_call(policy, calls)
    if policy != "analytic":
        rows["planner_analytic_us_per_call"] = planner_us_per_call("analytic", calls)
    rows["closed_loop_x_realtime"] = rows["closed_loop_libsumo_steps_per_s"] * 0.01
    rows["bare_over_closed_loop"] = (rows["bare_sumo_steps_per_s"]
                                     / rows["closed_loop_libsumo_steps_per_s"])
    rows["libsumo_over_traci"] = (rows["closed_loop_libsumo_steps_per_s"]
                                  / rows["closed_loop_traci_steps_per_s"])
    batched_rows(net, policy, sim_s, args.quick, rows)
    multi_edge_rows(policy, args.quick, rows)
    if not args.no_extras:
        data_and_training(args.quick, rows, notes, calls)
        rows["closed_loop_peak_rss_mb"] = closed_loop_peak_rss_mb(policy, sim_s)
        sweep_rows(args.quick, policy, rows, notes)
        gym_rows(args.quick, rows)

    report = {
        "machine": {"cpus": _cpus(), "cpu": _cpu_model(), "platform": platform.platform(),
                    "python": platform.python_version(), "sumo": sumo_api.version()},
        "policy": policy, "quick": args.quick, "results": rows, "notes": notes,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(args.out) as tmp:
        tmp.write_text(json.dumps(report, indent=2) + "\n")
    width = max(map(len, rows))
    print(f"benchmark on curved500, policy {policy} ({'quick' if args.quick else 'full'}), "
          f"{_cpus()} CPUs, {_cpu_model()}")
    for k, v in rows.items():
        print(f"  {k:<{width}}  {v:12.1f}")
    for note in notes:
        print(f"  note: {note}")
    print(f"written: {args.out}")
    return 0


def _cpus() -> int:
    import os

    return (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
            else os.cpu_count() or 1)


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


if __name__ == "__main__":
    sys.exit(main())
