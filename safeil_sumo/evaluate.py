"""``safeil-evaluate MODEL``: the report card of a planner, in one folder.

    safeil-evaluate safeil --quick                 # about 3 min on 2 cores
    safeil-evaluate idm --out runs/eval_idm         # the full budgets
    safeil-evaluate path/to/model.safetensors --only safety certificate

MODEL is a planner of the registry (``safeil``, ``safeil_paper``, ``bc``, ``analytic``,
``idm``, ...) or a checkpoint / IDM model path, as ``--policy`` takes it. Runs six sections
(:mod:`safeil_sumo.report.sections`, :mod:`safeil_sumo.report.held_out_replays`): the paper's safety test
and an N-scenario sweep, the leader-response suite, the gap probe, whole-maneuver replays of
held-out maneuvers, the certificate, and a budgeted falsification. Writes into ``--out``
(default ``runs/evaluate_<model>[_quick]``): ``report.md`` (a verdict table, then each section
with its numbers, figures and the one command that reproduces it), ``report.json`` (the same
numbers), ``figures/``, ``data/`` (each section's tables) and ``work/`` (the engines' task
files: rerunning the same command resumes). The report is rewritten after every section, so a
Ctrl-C keeps the sections finished. See docs/evaluate.md.

Exit codes: 0 every check passed (or does not apply), 1 a check failed or a section could not
run, 2 bad input, 130 interrupted.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
from dataclasses import replace
from pathlib import Path

from safeil_sumo.cli_args import (
    CommandParser,
    add_data_options,
    data_specs,
    finite_float,
    interruptible,
    nonnegative_int,
    positive_int,
)
from safeil_sumo.experiments import outputs
from safeil_sumo.planners import registry as pol
from safeil_sumo.report import card as rc
from safeil_sumo.report import held_out_replays as report_replay
from safeil_sumo.report import sections as rs

# (key, title, section function), in the report's order
SECTIONS: tuple[tuple[str, str, rs.SectionFn], ...] = (
    ("safety", "Safety test and sweep on curved500", rs.safety),
    ("suite", "Leader-response suite", rs.suite),
    ("gap_probe", "Gap probe: step responses of the gap regulation", rs.gap_probe),
    ("replay", "Whole-maneuver replays of held-out maneuvers", report_replay.replay),
    ("certificate", "Certificate of the network's margins", rs.certificate),
    ("falsify", "Falsification on a budget", rs.falsify),
)
KEYS = tuple(k for k, _, _ in SECTIONS)


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.evaluate", description=__doc__.split("\n")[0].split(": ")[1])
    p.add_argument("model", metavar="MODEL",
                   help="a planner name (safeil, safeil_paper, bc, analytic, idm, ...) or a "
                        "checkpoint .safetensors / IDM model .json path")
    p.add_argument("--quick", action="store_true",
                   help="smaller budgets (30-scenario sweep, one variant per suite family, the "
                        "gap probe at 25 m/s, 2 held-out maneuvers per source, 30 s of "
                        "certification, 50 falsification simulations): a few minutes")
    p.add_argument("--out", type=Path, default=None,
                   help="report folder (default runs/evaluate_<model>[_quick]); rerun to resume")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="master seed (default 0)")
    p.add_argument("--only", nargs="+", choices=KEYS, default=None, metavar="SECTION",
                   help=f"run these sections only ({', '.join(KEYS)}); the others are "
                        "reported as not run")
    p.add_argument("--scenarios", type=nonnegative_int, default=None,
                   help="scenarios of the curved500 sweep (default 1000; --quick 30)")
    p.add_argument("--maneuvers", type=nonnegative_int, default=None,
                   help="maneuvers replayed per source (default all; --quick 2)")
    add_data_options(p, "recordings of your own, replayed whole beside the held-out "
                        "maneuvers (the ones the model held out of training, else all)")
    p.add_argument("--speeds-mps", type=finite_float, nargs="+", default=None, metavar="V",
                   help="gap probe speeds [m/s] (default 15 25 35; --quick 25)")
    p.add_argument("--budget-s", type=finite_float, default=None, metavar="S",
                   help="certification budget [s] when the checkpoint has no valid "
                        "certificate (default 600; --quick 30)")
    p.add_argument("--budget-sims", type=nonnegative_int, default=None,
                   help="falsification simulations (default 1000; --quick 50)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="local worker processes of the sweeps and replays (default 1)")
    p.add_argument("--data-dir", type=Path, default=rs.DEFAULT_DATA_DIR,
                   help=f"real human data (default {rs.DEFAULT_DATA_DIR})")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    args.data_specs = data_specs(p, args) or []
    if args.scenarios == 0 or args.budget_sims == 0:
        p.error("--scenarios and --budget-sims must be >= 1")
    if args.budget_s is not None and args.budget_s <= 0:
        p.error("--budget-s must be > 0 s")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        p.error(f"--out {args.out} exists and is not a folder")
    return args


def default_out(model: str, quick: bool) -> Path:
    """``runs/evaluate_<model>[_quick]``, the model's file name without its suffix for a path."""
    is_path = "/" in model or "\\" in model or model.endswith((".safetensors", ".json"))
    name = Path(model).stem if is_path else model
    return Path("runs") / (re.sub(r"[^A-Za-z0-9_.-]+", "_", f"evaluate_{name}")
                           + ("_quick" if quick else ""))


def placeholder(key: str, title: str, status: str, error: str = "") -> rc.Section:
    """A section without results: ``not run`` (interrupted, or left out by --only) or
    ``error``."""
    return rc.Section(key, title, "", status=status, error=error)


def write_report(out: Path, header: dict, sections: list[rc.Section]) -> None:
    """report.md and report.json, from the same sections (atomically, each)."""
    from safeil_sumo.core.atomic import atomic_path

    with atomic_path(out / "report.md") as tmp:
        tmp.write_text(rc.render_markdown(header, sections))
    outputs.write_json(out / "report.json", rc.report_json(header, sections))


def run_section(fn: rs.SectionFn, ctx: rs.EvalContext, key: str, title: str) -> rc.Section:
    """One section timed; an exception is the section's ERROR (one line), not the run's end."""
    start = time.monotonic()
    try:
        section = fn(ctx)
    except (KeyboardInterrupt, SystemExit, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - reported in the card; the other sections run
        message = f"{type(exc).__name__}: {exc}".splitlines()[0]
        section = placeholder(key, title, "error", message)
    return replace(section, seconds=time.monotonic() - start)


def progress(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def evaluate(ctx: rs.EvalContext, only: tuple[str, ...], header: dict) -> list[rc.Section]:
    """Run the chosen sections in order, rewriting the report after each (a Ctrl-C keeps those
    finished: the report is rewritten with the rest not run, then the interrupt goes on)."""
    done: dict[str, rc.Section] = {}
    chosen = [s for s in SECTIONS if s[0] in only]
    start = time.monotonic()

    def current() -> list[rc.Section]:
        return [done.get(k) or placeholder(k, t, "not run") for k, t, _ in SECTIONS]

    try:
        for i, (key, title, fn) in enumerate(chosen, 1):
            progress(f"[{i}/{len(chosen)}] {key}: {title} ...")
            done[key] = run_section(fn, ctx, key, title)
            verdicts = " ".join(rc.section_verdicts(done[key]))
            extra = f" ({done[key].error})" if done[key].status == "error" else ""
            progress(f"[{i}/{len(chosen)}] {key}: {verdicts}{extra} in "
                     f"{done[key].seconds:.0f} s")
            header["seconds_total"] = time.monotonic() - start
            write_report(ctx.out, header, current())
    except KeyboardInterrupt:
        header["seconds_total"] = time.monotonic() - start
        write_report(ctx.out, header, current())
        raise
    return current()


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        pol.load(args.model)  # an unknown model: one line, before any section runs
    except pol.PolicyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    settings = rs.settings(args.quick, seed=args.seed, sweep_scenarios=args.scenarios,
                           replay_maneuvers=args.maneuvers, certify_budget_s=args.budget_s,
                           falsify_budget=args.budget_sims, workers=args.workers,
                           data_dir=args.data_dir, data=tuple(args.data_specs),
                           gap_speeds_mps=tuple(args.speeds_mps) if args.speeds_mps else None)
    out = args.out or default_out(args.model, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    header = {"model": args.model, "quick": args.quick, "seed": args.seed,
              "command": rc.command_line("safeil-evaluate", sys.argv[1:] if argv is None
                                         else argv),
              "commit": outputs.git_commit(), "seconds_total": math.nan,
              "settings": {**{k: (str(v) if isinstance(v, Path) else v)
                              for k, v in vars(settings).items()},
                           "data": [spec.label() for spec in settings.data]}}
    sections = evaluate(rs.EvalContext(args.model, out, settings), tuple(args.only or KEYS),
                        header)
    verdict = rc.overall(sections)
    print(f"{args.model}: {verdict}")
    print(f"report: {out / 'report.md'}")
    return 0 if verdict == rc.PASS else 1


if __name__ == "__main__":
    sys.exit(main())
