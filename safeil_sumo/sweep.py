"""``python -m safeil_sumo.sweep``: closed-loop sweeps over nets x policies x filter x scenarios.

Example (the paper's safety test for both learned policies, two local worker processes)::

    python -m safeil_sumo.sweep --net curved500 curved300 --policy safeil bc \\
        --scenarios 10 --seed 0 --safety-filter both --workers 2 --out runs/sweep

Every finished task is saved at once in ``<out>/tasks/<task_id>.json``; rerunning the same
command resumes a sweep that stopped (only missing tasks run; ``--retry-failed`` also reruns
failed ones). At the end: ``<out>/summary.csv`` / ``summary.json`` (one row per task),
``manifest.json``, and a printed breakdown per (net, policy, filter) with Wilson 95 % intervals.
Exit codes: 0 all tasks ran, 1 some tasks failed, 2 bad arguments, 130 interrupted.

``--config study.toml`` reads the options from a file (see ``sumo_scenarios/studies/``); the
resolved arguments are written into the sweep's ``manifest.json``.

``--suite leader-response [--quick]`` runs the leader-response suite
(:mod:`safeil_sumo.experiments.suite`) for ``--policy`` instead of the grid and writes
``<out>/suite.csv`` (per policy x family: collisions, avoidable/unavoidable flags, min TTC, min
time gap, max deceleration and jerk).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from safeil_sumo.cli_args import (
    CommandParser,
    add_policy_option,
    add_scenario_options,
    add_scheduler_option,
    add_task_options,
    check_scheduler,
    check_task_options,
    interruptible,
    loop_config,
    positive_int,
    task,
)
from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.experiments.stats import breakdown, format_breakdown
from safeil_sumo.experiments.sweep_executor import DEFAULT_BATCH, run_sweep
from safeil_sumo.scenarios.spec import Task

FILTER_OPTIONS = {"off": (False,), "on": (True,), "both": (False, True)}


def toml_argv(path: Path, parser: CommandParser) -> list[str]:
    """A sweep file (TOML, keys = ``parser``'s long options without ``--``, ``-`` as ``_``) as
    arguments: ``workers = 2`` -> ``--workers 2``, ``policy = ["safeil", "bc"]`` -> ``--policy
    safeil bc``, ``stop_on_flag = true`` -> ``--stop-on-flag``, ``brake_guard = false`` ->
    ``--no-brake-guard`` (a flag without a ``--no-`` form: left out). ``ValueError`` naming the
    file and the key for a key that is no option (or an old spelling of one)."""
    import tomllib

    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: not a readable TOML sweep file ({exc})") from exc
    options = parser._option_string_actions  # exact names: a key is never an abbreviation
    argv: list[str] = []
    for key, value in data.items():
        flag = "--" + key.replace("_", "-")
        if flag == "--config":
            raise ValueError(f"{path}: a sweep file cannot name another config")
        if flag in parser.renamed:
            new = parser.renamed[flag].removeprefix("--").replace("-", "_")
            raise ValueError(f"{path}: key {key!r} was renamed {new!r}")
        if flag not in options or flag in ("--help", "-h"):
            raise ValueError(f"{path}: unknown key {key!r} (the keys are the long options of "
                             f"{parser.prog} without '--', e.g. policy, net, scenarios)")
        if flag in parser.switches and value in ("on", "off"):
            raise ValueError(f"{path}: {key} = {value!r} is now {key} = "
                             f"{'true' if value == 'on' else 'false'}")
        if isinstance(value, bool):
            negated = "--no-" + flag[2:]
            argv += [flag] if value else ([negated] if negated in options else [])
        elif isinstance(value, list):
            argv += [flag, *map(str, value)]
        elif isinstance(value, (int, float, str)):
            argv += [flag, str(value)]
        else:
            raise ValueError(  # noqa: TRY004 - a bad file, reported as such
                f"{path}: {key} = {value!r}: use a number, string, boolean or list")
    return argv


def with_config(parser: CommandParser, argv: list[str]) -> list[str]:
    """``argv`` with a ``--config FILE``'s options in its place, before the others (flags on
    the command line override the file's); a bad file, key or value is a one-line usage error
    naming the file."""
    if "--config" not in argv:
        return argv
    i = argv.index("--config")
    if i + 1 >= len(argv):
        parser.error("--config needs a TOML file")
    path = Path(argv[i + 1])
    try:
        from_file = toml_argv(path, parser)
    except ValueError as exc:
        parser.error(str(exc))
    parser.error_prefix = f"{path}: "  # the file's own values, parsed alone first
    parser.parse_args(from_file)
    parser.error_prefix = ""
    return from_file + argv[:i] + argv[i + 2:]


def build_parser() -> CommandParser:
    p = CommandParser(
        "safeil_sumo.sweep",
        description="Closed-loop scenario sweeps in SUMO (local processes or a Dask cluster).",
    )
    p.add_argument("--net", nargs="+", default=["curved500"], metavar="NET",
                   help="curved500, straight, curved<R> (e.g. curved300) or .net.xml paths")
    add_policy_option(p, ["safeil", "bc"], "safeil, safeil_paper, bc, analytic, idm, "
                      ".safetensors checkpoints or IDM model .json files")
    add_scenario_options(p)
    p.add_argument("--suite", choices=("leader-response",), default=None,
                   help="run a named suite instead of the grid (see docs; uses --policy, "
                        "--seed, --brake-guard, --workers, --out)")
    p.add_argument("--quick", action="store_true",
                   help="with --suite: one variant per family and net (CI)")
    p.add_argument("--safety-filter", choices=tuple(FILTER_OPTIONS), default="off",
                   help="run policies without (off), with (on) or both ways (default off)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="local worker processes, one simulation each (default 1: in-process)")
    p.add_argument("--batch", type=positive_int, default=DEFAULT_BATCH, metavar="N",
                   help=f"run up to N scenarios side by side in one SUMO simulation per worker "
                        f"(same net, planner and loop settings; traffic drives run alone); "
                        f"1: one simulation per scenario (default {DEFAULT_BATCH})")
    add_scheduler_option(p)
    add_task_options(p)
    p.add_argument("--out", type=Path, default=Path("runs/sweep"),
                   help="results folder (default runs/sweep); rerun to resume")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--config", metavar="STUDY.toml",
                   help="options from a TOML sweep file (keys = these long options, e.g. "
                        "sumo_scenarios/studies/*.toml); command-line flags override it")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    argv = with_config(p, list(sys.argv[1:] if argv is None else argv))
    args = p.parse_args(argv)
    args.resolved_argv = argv

    if args.scenarios < 1:  # the tasks' own rules are reported by main (build_tasks)
        p.error("--scenarios must be >= 1")
    check_scheduler(p, args)
    check_task_options(p, args)
    if args.quick and args.suite is None:
        p.error("--quick needs --suite")
    if (args.route or args.from_km is not None or args.to_km is not None
            or args.traffic not in (None, "none") or args.lane is not None) and args.suite is not None:
        p.error("--route, --from-km/--to-km, --traffic and --lane do not apply to --suite (the "
                "suite has its own nets)")
    if args.out.exists() and not args.out.is_dir():
        p.error(f"--out {args.out} exists and is not a folder")
    return args


def build_tasks(args: argparse.Namespace) -> list[Task]:
    """The grid: nets x policies x filter options x scenario indices (ValueError if invalid)."""
    if args.suite == "leader-response":
        from safeil_sumo.experiments.suite import suite_tasks

        return [replace(t, loop=loop_config(args),
                        planner=replace(t.planner, time_gap_s=args.time_gap_s,
                                        standstill_m=args.standstill_m))
                for t in suite_tasks(args.policy, args.seed, variants=1 if args.quick else 3)]
    return [task(args, net, index, policy, filt)
            for net, policy, filt, index in itertools.product(
                args.net, args.policy, FILTER_OPTIONS[args.safety_filter], range(args.scenarios))]


def check_inputs(nets: list[str], policies: list[str], profiles: Sequence[str] = (),
                 route: tuple[str, ...] = (), from_km: float | None = None,
                 to_km: float | None = None, lane: str = "",
                 time_gap_s: float | None = None, standstill_m: float | None = None) -> None:
    """Resolve every net (building curved<R> once; along ``route`` or the n74 stretch if given),
    load every policy
    and recorded-leader library before any task runs.

    Raises ``ValueError`` (NetworkError, PolicyError, ProfileError) with a one-line reason. No
    SUMO is started.
    """
    from safeil_sumo.scenarios import recorded_leaders

    for profile in dict.fromkeys(profiles):
        recorded_leaders.library(profile)
    from safeil_sumo.planners import registry as planner_registry
    from safeil_sumo.scenarios.spec import resolve_road

    for net in dict.fromkeys(nets):
        resolve_road(net, route, from_km, to_km, lane)
    for name in dict.fromkeys(policies):
        policy = planner_registry.load(name)
        if time_gap_s is not None:
            planner_registry.with_time_gap(policy, time_gap_s, standstill_m)


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        tasks = build_tasks(args)
        check_inputs(sorted({t.scenario.net for t in tasks}), args.policy,
                     sorted({t.scenario.leader_profile for t in tasks
                             if t.scenario.leader_profile}),
                     tuple(args.route), args.from_km, args.to_km, args.lane or "",
                     args.time_gap_s, args.standstill_m)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        summary = run_sweep(tasks, args.out, workers=args.workers, scheduler=args.scheduler,
                            progress=not args.no_progress, retry_failed=args.retry_failed,
                            task_timeout_s=args.task_timeout_s, batch=args.batch,
                            manifest_extra={"arguments": args.resolved_argv})
    except KeyboardInterrupt:
        print(f"\ninterrupted: finished tasks are saved in {args.out / 'tasks'}; "
              "rerun the same command to resume", file=sys.stderr)
        return 130
    except OSError as exc:  # e.g. the Dask scheduler cannot be reached
        print(f"error: {exc}", file=sys.stderr)
        return 2

    if args.suite == "leader-response":
        from safeil_sumo.experiments.suite import aggregate

        table = aggregate(summary[summary["status"] == "ok"])
        with atomic_path(args.out / "suite.csv") as tmp:
            table.to_csv(tmp, index=False)
        print(table.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    else:
        print(format_breakdown(breakdown(summary, by=["net", "policy", "safety_filter"])))
    failed = summary[summary["status"] != "ok"]
    for _, row in failed.head(20).iterrows():
        print(f"task {row['task_id']} failed: {row['error']}", file=sys.stderr)
    if len(failed) > 20:
        print(f"... and {len(failed) - 20} more failed tasks (see summary.csv)", file=sys.stderr)
    print(f"{len(summary)} tasks, {len(failed)} failed; results: {args.out}")
    return 1 if len(failed) else 0


if __name__ == "__main__":
    sys.exit(main())
