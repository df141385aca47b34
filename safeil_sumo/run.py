"""``python -m safeil_sumo.run --net curved500``: the paper's safety test, closed loop in SUMO.

Runs N scenarios (leader at a constant random speed in [25, 32] m/s ahead of the ego) with one
policy, prints a summary table and writes a results folder:
``steps.parquet`` (per-step log), ``summary.csv`` / ``summary.json`` (per scenario),
``manifest.json`` (config, seeds, git commit, versions), PNG plots (on n74 also
``flag_map.png``: the stretch with the flag locations), and with ``--animate``
``animation_<scenario>.mp4`` (or ``.gif``, see :mod:`safeil_sumo.experiments.animation`).
"""

from __future__ import annotations

import argparse
import re
import sys
from dataclasses import asdict
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from safeil_sumo import api
from safeil_sumo.cli_args import (
    CommandParser,
    add_policy_option,
    add_scenario_options,
    check_scenario_options,
    interruptible,
    loop_config,
    one_policy,
    scenario_fields,
)
from safeil_sumo.experiments import animation, outputs, plots
from safeil_sumo.planners import registry as planner_registry
from safeil_sumo.planners.registry import PlannerRef
from safeil_sumo.roads.road import NetworkError, Road
from safeil_sumo.scenarios.spec import lane_for_net
from safeil_sumo.sim.leaders import ProfileError
from safeil_sumo.sim.loop_types import LoopConfig, Scenario
from safeil_sumo.sim.sumo_api import SumoError, has_display
from safeil_sumo.sim.vehicle import VehicleParams


def build_parser() -> CommandParser:
    p = CommandParser(
        "safeil_sumo.run",
        description="Closed-loop safety test of a planner in SUMO (the paper's curved track).",
    )
    p.add_argument("--net", default="curved500",
                   help="curved500, straight, curved<R> (e.g. curved300), n74 (29.2 km highway "
                        "with on-ramps; see --from-km/--to-km) or a .net.xml path")
    add_policy_option(p, [planner_registry.default_policy_name()],
                      "safeil, safeil_paper, bc, analytic, idm, a checkpoint .safetensors or an "
                      "IDM model .json", many=False)
    add_scenario_options(p)
    p.add_argument("--backend", choices=("libsumo", "traci"), default="libsumo")
    p.add_argument("--gui", action="store_true", help="watch in sumo-gui (implies traci)")
    p.add_argument("--gui-screenshot", type=Path, default=None, metavar="PNG",
                   help="with --gui: save sumo-gui's view 1 s into the first scenario")
    p.add_argument("--out", type=Path, default=None,
                   help="results folder (default runs/<net>_<policy>_seed<seed>)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--animate", nargs="*", default=None, metavar="SCENARIO",
                   help="also write animation_<scenario>.mp4 (.gif without an ffmpeg) of these "
                        "scenarios, e.g. s0000 s0003 (no name: the first); see "
                        "python -m safeil_sumo.animate")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    args.policy = one_policy(p, args, "compare planners with python -m safeil_sumo.sweep "
                                      "--policy A B ...")
    check_scenario_options(p, args, [args.net])
    args.lane = lane_for_net(args.net, args.lane)
    if args.gui_screenshot is not None and not args.gui:
        p.error("--gui-screenshot needs --gui")
    if args.gui:
        if not has_display():
            p.error("--gui needs a display (DISPLAY is not set): run without --gui, or under a "
                    "virtual display, e.g. xvfb-run -a python -m safeil_sumo.run --gui ...")
        args.backend = "traci"
    return args


def format_table(summaries: pd.DataFrame) -> str:
    """The short table printed at the end of a run."""
    cols = {
        "scenario": "scenario", "leader_speed_mps": "v_lead[m/s]",
        "path_completed": "path[%]", "flag": "flag", "min_ttc_s": "minTTC[s]",
        "max_abs_lateral_offset_m": "max|d|[m]", "end_reason": "end",
    }
    t = summaries[list(cols)].rename(columns=cols).copy()
    t["path[%]"] = (100 * t["path[%]"]).round(1)
    t["flag"] = t["flag"].replace("", "-")
    return t.to_string(index=False, float_format=lambda v: f"{v:.2f}")


def manifest_config(args: argparse.Namespace, road: Road, scenarios: list[Scenario],
                    loop: LoopConfig, vehicle: VehicleParams) -> dict:
    """The run's configuration for its manifest.json."""
    return {
        "net": str(road.net_path), "route": list(args.route), "lane": args.lane or None,
        "stretch_km": road.meta.get("stretch_km"), "policy": args.policy,
        "time_gap_s": args.time_gap_s, "standstill_m": args.standstill_m,
        "scenarios": args.scenarios,
        "master_seed": args.seed,
        "leader_speed_range_mps": list(args.leader_speed_range_mps),
        "leader": args.leader, "leader_profile": args.leader_profile,
        "leaders": [sc.leader.label if sc.leader is not None else "traffic"
                    for sc in scenarios],
        "traffic": args.traffic or "none",
        # as given (None: the default, or a recorded leader's start), and as each scenario began
        "ego_speed_mps": args.ego_speed_mps,
        "ego_speeds_mps": [sc.ego_speed_mps for sc in scenarios],
        "initial_gap_m": args.gap_m,
        "spec": scenario_fields(args),  # every scenario option, as ScenarioSpec fields
        "loop": asdict(loop), "vehicle": asdict(vehicle),
        "sensors": asdict(scenarios[0].sensors), "monitors": asdict(scenarios[0].monitors),
    }


def print_report(policy_name: str, summaries: pd.DataFrame, net: str) -> None:
    """The table and the totals printed at the end of a run."""
    print(format_table(summaries))
    done = int(summaries["completed"].sum())
    flagged = int((summaries["flag"] != "").sum())
    print(f"\n{policy_name}: {done}/{len(summaries)} scenarios completed without a flag "
          f"({flagged} flagged), mean path completed {100 * summaries['path_completed'].mean():.1f} %")
    if net == "n74":  # long drives: rates per distance, leaders met
        km = float(summaries["km_driven"].sum())
        rates = ", ".join(
            f"{kind} {100.0 * summaries[f'{col}_events'].sum() / km:.1f}" if km > 0 else
            f"{kind} -" for kind, col in (("TTC", "ttc"), ("lane departure", "lane_departure"),
                                         ("collision", "collision")))
        print(f"{km:.2f} km driven; flags per 100 km: {rates}; min TTC "
              f"{summaries['min_ttc_s'].min():.2f} s; leaders met "
              f"{int(summaries['leaders_met'].sum())}, cut-ins "
              f"{int(summaries['cut_ins_met'].sum())}")


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        road = api.road(args.net, args.route, args.from_km, args.to_km, args.lane)
        policy = PlannerRef(args.policy, time_gap_s=args.time_gap_s,
                            standstill_m=args.standstill_m).load()
    except (NetworkError, planner_registry.PolicyError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    net_name = args.net if not args.net.endswith(".xml") else road.net_path.stem
    # the policy name comes from a checkpoint's sidecar: keep it one plain folder name
    default_name = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{net_name}_{policy.name}_seed{args.seed}")
    out = args.out or Path("runs") / default_name
    loop = loop_config(args, backend=args.backend, gui=args.gui,
                       gui_screenshot=args.gui_screenshot)
    fields = scenario_fields(args)
    del fields["master_seed"]
    vehicle = VehicleParams()
    try:
        scenarios = api.build_scenarios(args.net, args.scenarios, args.seed, **fields)
    except (ValueError, ProfileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    names = [sc.name for sc in scenarios]
    animated = (args.animate or names[:1]) if args.animate is not None else []
    unknown = [a for a in animated if a not in names]
    if unknown:
        shown = ", ".join(names[:20]) + (", ..." if len(names) > 20 else "")
        print(f"error: --animate: unknown scenario {unknown[0]!r}; available: {shown}",
              file=sys.stderr)
        return 2

    try:
        result = api.run_scenarios(scenarios, policy, loop, vehicle, progress=True)
    except SumoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    summaries, steps = result.summary, result.log

    config = manifest_config(args, road, scenarios, loop, vehicle)
    with outputs.AtomicDir(out) as tmp:
        outputs.write_tables(tmp, steps, summaries)
        outputs.write_json(tmp / "manifest.json",
                           outputs.manifest(config, [s.seed for s in scenarios]))
        if not args.no_plots:
            plots.plot_trajectories(road, steps, tmp / "trajectory.png", vehicle.width_m)
            plots.plot_speed_gap(steps, tmp / "speed_gap.png")
            plots.plot_ttc(steps, tmp / "ttc.png", scenarios[0].monitors.ttc_threshold_s)
            if args.net == "n74":  # long drives: where on the route each flag started
                plots.plot_flag_map(road, steps, tmp / "flag_map.png")

    print_report(policy.name, summaries, args.net)
    errors = summaries[summaries["end_reason"] == "error"]
    for _, row in errors.iterrows():
        print(f"scenario {row['scenario']} failed: {row['error']}", file=sys.stderr)
    # after the results are in place (an animation never costs a run), from the Parquet log
    # just written, as the animate CLI does
    for name in tqdm(animated, desc="animating", unit="scenario", disable=None):
        try:
            print(f"animation: {animation.animate(out, scenario=name)}")
        except animation.AnimateError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
    print(f"results: {out}")
    return 1 if len(errors) else 0


if __name__ == "__main__":
    sys.exit(main())
