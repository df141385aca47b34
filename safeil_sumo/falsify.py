"""``python -m safeil_sumo.falsify``: search the closed-loop scenarios where a planner fails.

    python -m safeil_sumo.falsify --policy bc --method cem --budget-sims 2000 --batch 50 --seed 0
    python -m safeil_sumo.falsify --policy safeil --method random --budget-sims 2000 --out runs/f

Searches leader braking (onset, deceleration, duration), cut-ins (gap, speed), recorded NGSIM
leader windows, the track's radius and sensor noise for the lowest min TTC among scenarios that
braking at 6 m/s^2 could still avoid (docs/falsification.md), in batches of ``--batch``
scenarios per SUMO simulation, with the cross-entropy method or uniform random sampling. A
batch runs on the task engine: in this process, split over ``--workers`` local processes, or on
a Dask cluster (``--scheduler``).

Writes into ``--out`` (default ``runs/falsify_<policy>_<method>_s<seed>``): ``evaluations.csv``
(every simulation: its parameters, min TTC, flag, avoidability, score and spec),
``summary.json``, and the worst avoidable case as ``worst.json`` (its ScenarioSpec) and
``worst.toml``, which ``python -m safeil_sumo.sweep --config worst.toml`` reruns. A finished
search with the same options in ``--out`` is read back, not rerun; an interrupted one
(Ctrl-C) keeps every finished simulation in ``--out/tasks`` and the same command resumes it.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict
from pathlib import Path

from safeil_sumo.cli_args import (
    CommandParser,
    add_dataclass_options,
    add_policy_option,
    add_scheduler_option,
    check_scheduler,
    dataclass_from_args,
    interruptible,
    one_policy,
    positive_int,
)
from safeil_sumo.experiments import falsification_search as fz
from safeil_sumo.experiments import outputs
from safeil_sumo.sweep import check_inputs

HELPS = {
    "method": "cem (cross-entropy method) or random (uniform sampling)",
    "budget": "simulations (closed-loop scenarios) to spend",
    "batch": "scenarios per SUMO simulation and per CEM update",
    "seed": "seeds every draw of the search (same seed: same scenarios, same result)",
    "elite_fraction": "CEM: share of a batch (lowest scores) its Gaussian is refit to",
    "smoothing": "CEM: weight of the refit against the previous mean and std",
    "min_std": "CEM: floor of each coordinate's std (the box is [0, 1] per coordinate)",
    "max_time_s": "scenario duration [s]",
    "stop_at_failure": "end the search after the batch holding its first failure",
    "brake_guard": "the loop's brake guard under the planner, as shipped (--no-brake-guard: "
                   "the planner and tracker alone)",
}


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.falsify", description=__doc__.split("\n")[0])
    add_policy_option(p, ["safeil"], "a planner name (safeil, safeil_paper, bc, idm, analytic, "
                      "...) or a checkpoint path", many=False)
    # the budget is counted in simulations, not seconds (certify's --budget-s)
    add_dataclass_options(p, fz.SearchConfig, helps=HELPS, choices={"method": fz.METHODS},
                          names={"budget": "--budget-sims"})
    p.add_argument("--out", type=Path, default=None,
                   help="results folder (default runs/falsify_<policy>_<method>_s<seed>)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="local worker processes a batch is split over (default 1: one "
                        "simulation in this process)")
    add_scheduler_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    args.policy = one_policy(p, args, "search each planner in turn")
    check_scheduler(p, args)
    try:
        args.config = dataclass_from_args(fz.SearchConfig, args)
    except ValueError as exc:
        p.error(str(exc))
    if args.out is None:
        name = Path(args.policy).name.removesuffix(".safetensors")
        args.out = Path("runs") / (f"falsify_{name}_{args.method}_s{args.seed}"
                                   + ("" if args.brake_guard else "_noguard"))
    return args


def report(s: dict, toml: Path | None) -> str:
    """The lines printed at the end of a search."""
    first = s["first_failure"]
    lines = [f"{s['policy']} {s['method']} seed {s['seed']}: {s['simulations']} simulations, "
             f"{s['avoidable']} avoidable, {s['failures']} failures"
             + (f", {s['errors']} failed to run" if s["errors"] else ""),
             "first failure at simulation " + (str(first) if first else "- (none)")]
    if toml is not None:
        worst = (f"worst avoidable case: min TTC {s['best_min_ttc_s']:.3f} s "
                 f"({s['best_flag'] or 'no flag'}), simulation {s['best_sim']}")
        rerun = f"python -m safeil_sumo.sweep --config {toml} --out runs/worst_{s['policy']}"
        lines += [worst, f"rerun it: {rerun}"]
    return "\n".join(lines)


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:  # every net, the planner and the NGSIM library before SUMO starts
        check_inputs(list(fz.NETS), [args.policy], ["ngsim"])
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        result = fz.run_or_load(args.policy, args.config, args.out,
                                progress=not args.no_progress, workers=args.workers,
                                scheduler=args.scheduler)
    except KeyboardInterrupt:
        print(f"\ninterrupted: the finished simulations are kept in {args.out / 'tasks'}; the "
              "same command resumes the search", file=sys.stderr)
        return 130
    s = fz.summary(result, args.policy)
    toml = fz.write_worst(result, args.policy, args.out)
    config = {"policy": args.policy, **asdict(args.config)}
    outputs.write_json(args.out / "summary.json",
                       {**s, "manifest": outputs.manifest(config, [args.config.seed])})
    print(report(s, toml))
    print(f"results: {args.out}")
    return 1 if s["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
