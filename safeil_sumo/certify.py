"""``python -m safeil_sumo.certify``: prove a planner network's margins over its envelope.

    python -m safeil_sumo.certify --policy safeil [--time-gap-range-s LO HI] [--budget-s 600]
    python -m safeil_sumo.certify --policy path/to/model.safetensors --max-boxes 200000
    python -m safeil_sumo.certify --policy path/to/model.safetensors --check

Certifies, for every state of the operating envelope the training samples (lane width, offset,
heading and curvature, ego speed, leader speed and gap; recoverable leader states and the
no-leader states), that the one plan the network outputs keeps the leader margin (behind the
constant-speed leader at the control points' times) and the lane margin (Bernstein coefficients
of the lateral margins >= 0). Prints per margin the certified share of the envelope's volume,
the share holding confirmed counterexamples, the time taken and where the unproven volume lies,
and writes a certificate JSON next to the checkpoint (shipped models: into ``--out``, default
``runs/certify_<name>/``). ``--check`` reports whether the checkpoint has a valid certificate
(exit 0 if so, 1 if not): the one in ``--out`` if given, else the one beside the checkpoint
(``safeil`` ships its own), else ``runs/certify_<name>/``. See docs/certification.md.

    python -m safeil_sumo.certify --policy safeil --closed-loop [--time-gap-s T |
        --time-gap-range-s LO HI] [--no-brake-guard] [--search-s S] [--cells G V VL F]

``--closed-loop`` checks a barrier certificate of the longitudinal closed loop (planner, PI
tracker, brake guard unless ``--no-brake-guard``, plant; learn/loop_barrier.py): every grid
cell's change over one decision period bounded, then the gap floor checked, the recoverable
envelope's lower boundary (with ``--search-s S``: the last floor a search of S seconds finds).
Prints the verdict (proven only if every column passes), S's share of the recoverable envelope
(0 unless proven), the failing columns and their deficits, the worst failing cells as states
with their reason, and writes ``<name>.closed_loop_certificate.json`` and the floor's
``.safetensors`` where the one-plan certificate goes. ``--cells`` sets the cell widths (gap,
ego speed, leader speed, force; default 1.5 0.5 0.5 1.5). ``--closed-loop --check`` reports
whether the checkpoint has a valid closed-loop certificate that proves invariance (exit 0 only
then).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from safeil_sumo.cli_args import (
    CommandParser,
    add_policy_option,
    finite_float,
    interruptible,
    nonnegative_int,
    one_policy,
)
from safeil_sumo.learn import closed_loop_certificate as clc
from safeil_sumo.learn import loop_invariant as li
from safeil_sumo.learn.branch_and_bound import (
    Budget,
    CertEnvelope,
    CertifyError,
    CertifyResult,
    certify,
)
from safeil_sumo.learn.certificate import certificate_path, load_certificate, write_certificate
from safeil_sumo.learn.certify_margins import MARGINS
from safeil_sumo.learn.inference import MLPPolicy
from safeil_sumo.planners import registry as pol

ONE_PLAN_ONLY = {"margins": "--margins", "budget_s": "--budget-s", "max_boxes": "--max-boxes",
                 "batch": "--batch", "seed": "--seed", "cex_min_share": "--cex-min-share"}
CLOSED_LOOP_ONLY = {"time_gap_s": "--time-gap-s", "brake_guard": "--brake-guard/--no-brake-guard",
                    "search_s": "--search-s", "cells": "--cells"}
ONE_PLAN_DEFAULTS = {"margins": list(MARGINS), "budget_s": 600.0, "batch": 512, "seed": 0,
                     "cex_min_share": Budget.cex_min_share}


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.certify", description=__doc__.split("\n")[0])
    add_policy_option(p, ["safeil"], "a shipped network (safeil, safeil_openloop, safeil_paper, "
                      "bc) or a checkpoint path (.safetensors)", many=False)
    p.add_argument("--time-gap-range-s", type=finite_float, nargs=2, metavar=("LO", "HI"),
                   default=None,
                   help="certify a style-conditioned checkpoint over this range of its time-gap "
                        "setting [s] (an extra input dimension); default: at its default setting")
    p.rename(time_gap="--time-gap-range-s")
    p.add_argument("--margins", nargs="+", choices=MARGINS, default=None,
                   help="the margins to certify (default both; the budget is shared equally)")
    p.add_argument("--budget-s", type=finite_float, default=None,
                   help="wall-time budget for all margins [s] (default "
                        f"{ONE_PLAN_DEFAULTS['budget_s']:g})")
    p.add_argument("--max-boxes", type=nonnegative_int, default=None,
                   help="box budget for all margins (reproducible across machines)")
    p.add_argument("--batch", type=nonnegative_int, default=None,
                   help=f"boxes bounded together (default {ONE_PLAN_DEFAULTS['batch']})")
    p.add_argument("--seed", type=int, default=None,
                   help="seeds the counterexample search (default "
                        f"{ONE_PLAN_DEFAULTS['seed']})")
    p.add_argument("--cex-min-share", type=finite_float, default=None,
                   help="split a box holding a counterexample only while its share of the "
                        f"envelope exceeds this (default {ONE_PLAN_DEFAULTS['cex_min_share']:g})")
    add_closed_loop_options(p)
    p.add_argument("--out", type=Path, default=None,
                   help="folder for the certificate (default: next to the checkpoint; "
                        "runs/certify_<name>/ for a shipped model)")
    p.add_argument("--check", nargs="?", const="", default=None, metavar="CERTIFICATE",
                   help="only report whether the checkpoint has a valid certificate (default "
                        "path: in --out if given, else next to the checkpoint, else in "
                        "runs/certify_<name>/ for a shipped model)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def add_closed_loop_options(p: CommandParser) -> None:
    """``--closed-loop`` and the options only it reads."""
    p.add_argument("--closed-loop", action="store_true",
                   help="check a barrier certificate of the longitudinal closed loop instead "
                        "(planner, PI tracker, brake guard, plant; docs/certification.md)")
    p.add_argument("--time-gap-s", type=finite_float, default=None, metavar="T",
                   help="--closed-loop: at this time-gap setting [s] (default: the "
                        "checkpoint's default setting)")
    p.add_switch("--brake-guard", default=None,
                 help="--closed-loop: the brake guard in the loop (default on)")
    p.add_argument("--search-s", type=finite_float, default=None, metavar="S",
                   help="--closed-loop: search a floor for this long [s] and check its last "
                        "(default 0: check the recoverable envelope's lower boundary)")
    p.add_argument("--cells", type=finite_float, nargs=4, default=None,
                   metavar=("GAP_M", "SPEED_MPS", "LEADER_MPS", "FORCE_MPS2"),
                   help="--closed-loop: cell widths of gap, ego speed, leader speed and force "
                        "over 1-151 m, 0-50 m/s, 0-40 m/s, -9-3 m/s^2 (default 1.5 0.5 0.5 "
                        "1.5)")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    args.policy = one_policy(p, args, "certify each network in turn")
    given = {k for k in (*ONE_PLAN_ONLY, *CLOSED_LOOP_ONLY) if getattr(args, k) is not None}
    if args.closed_loop:
        wrong = [ONE_PLAN_ONLY[k] for k in ONE_PLAN_ONLY if k in given]
        if wrong:
            p.error(f"{', '.join(wrong)} certif{'ies' if len(wrong) == 1 else 'y'} one plan: "
                    "not with --closed-loop")
        if args.time_gap_s is not None and args.time_gap_range_s is not None:
            p.error("use either --time-gap-s (one setting) or --time-gap-range-s LO HI")
        if args.search_s is not None and args.search_s < 0:
            p.error(f"--search-s must be >= 0 s, got {args.search_s:g}")
        return args
    wrong = [CLOSED_LOOP_ONLY[k] for k in CLOSED_LOOP_ONLY if k in given]
    if wrong:
        p.error(f"{', '.join(wrong)} only with --closed-loop")
    for k, default in ONE_PLAN_DEFAULTS.items():
        if getattr(args, k) is None:
            setattr(args, k, default)
    return args


def resolve(policy: str) -> tuple[MLPPolicy, Path, bool]:
    """``(network, checkpoint path, shipped?)``; :class:`CertifyError` for what is no network."""
    shipped = policy in pol.SHIPPED
    path = pol.shipped_checkpoint(policy) if shipped else Path(policy)
    loaded = pol.load(policy)
    if not isinstance(loaded, MLPPolicy):
        raise CertifyError(f"{policy!r} is not a network checkpoint: certify needs one "
                           f"({', '.join(pol.SHIPPED)} or a .safetensors path)")
    return loaded, path, shipped


def print_result(r: CertifyResult) -> None:
    style = f" at style {r.style}" if r.style else ""
    print(f"{r.policy}{style}: {r.seconds:.0f} s")
    print(f"{'margin':8} {'certified':>10} {'leader st.':>10} {'no leader':>10} "
          f"{'counterex.':>10} {'unknown':>8} {'boxes':>9} {'time s':>7}  stopped by")
    for m in r.margins.values():
        part = m.certified_by_part
        print(f"{m.margin:8} {m.certified:10.4%} {part.get('leader') or 0:10.4%} "
              f"{part.get('free') or 0:10.4%} {m.with_counterexample:10.4%} {m.unknown:8.4%} "
              f"{m.boxes_bounded:9d} {m.seconds:7.1f}  {m.stopped_by}")
    for m in r.margins.values():
        if m.counterexamples:
            c = m.counterexamples[0]
            z = ", ".join(f"{k}={v:.4g}" for k, v in c["z"].items())
            print(f"worst {m.margin} counterexample: {c['row']} = {c['margin_m']:.3f} m at {z} "
                  f"({'confirmed' if c['confirmed'] else 'NOT confirmed'} by MLPPolicy)")
        if m.certified < 1.0:
            skew = sorted(m.unproven_by_dim.items(), key=lambda kv: -max(kv[1]))[:3]
            where = "; ".join(f"{k} quarters {v}" for k, v in skew)
            print(f"unproven {m.margin} volume by quarter of range: {where}")


def default_out(args: argparse.Namespace, shipped: bool) -> Path | None:
    """Where certificates go: ``--out``, else ``runs/certify_<name>/`` for a shipped model,
    else (None) next to the checkpoint."""
    if args.out is not None:
        return args.out
    return Path("runs") / f"certify_{args.policy}" if shipped else None


def check_path(args: argparse.Namespace, path: Path, out: Path | None,
               beside: Path) -> Path | None:
    """The certificate ``--check`` reads: a given file; else in ``--out``; else next to the
    checkpoint (``beside``, where a shipped model's own certificate is shipped), for a shipped
    model without one there in runs/ (``out``); None: the default beside the checkpoint."""
    if args.check:
        return Path(args.check)
    if out is not None and (args.out is not None or not beside.is_file()):
        return out / beside.name
    return None


def check_one_plan(args: argparse.Namespace, path: Path, out: Path | None) -> int:
    status = load_certificate(path, check_path(args, path, out, certificate_path(path)))
    shares = ", ".join(f"{k} {v:.4%}" for k, v in status.certified.items())
    print(f"{status.path}: {'valid' if status.valid else 'INVALID'} ({status.reason})"
          + (f"; certified {shares}" + (" (complete)" if status.complete else "")
             if status.certified else ""))
    return 0 if status.valid else 1


def certify_one_plan(args: argparse.Namespace, policy: MLPPolicy, path: Path,
                     out: Path | None) -> int:
    env = CertEnvelope(time_gap_s=tuple(args.time_gap_range_s) if args.time_gap_range_s
                       else None)
    budget = Budget(seconds=args.budget_s, boxes=args.max_boxes, batch=max(args.batch, 1),
                    seed=args.seed, cex_min_share=args.cex_min_share)
    result = certify(policy, env, budget=budget, margins=tuple(args.margins),
                     progress=not args.no_progress)
    print_result(result)
    written = write_certificate(result, path, out)
    print(f"certificate: {written}")
    return 0


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        policy, path, shipped = resolve(args.policy)
        out = default_out(args, shipped)
        if args.closed_loop:
            if args.check is not None:
                return check_closed_loop(args, path, out)
            return certify_closed_loop(args, policy, path, out)
        if args.check is not None:
            return check_one_plan(args, path, out)
        return certify_one_plan(args, policy, path, out)
    except (CertifyError, pol.PolicyError, clc.ClosedLoopError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


# ------------------------------------------------------------------ --closed-loop


def closed_loop_settings(args: argparse.Namespace, policy: MLPPolicy) -> clc.ClosedLoopSettings:
    """The settings the options ask for (the time gap by default the checkpoint's own)."""
    if args.time_gap_range_s is not None:
        time_gap = (args.time_gap_range_s[0], args.time_gap_range_s[1])
    elif args.time_gap_s is not None:
        time_gap = (args.time_gap_s, args.time_gap_s)
    elif "time_gap_s" in policy.style:
        time_gap = (policy.style["time_gap_s"], policy.style["time_gap_s"])
    else:
        raise clc.ClosedLoopError(f"{policy.name} has no time-gap input: the closed-loop bounds "
                                  "need a style-conditioned two-tower checkpoint")
    grid = clc.grid_with_widths(tuple(args.cells)) if args.cells is not None else li.Grid()
    return clc.ClosedLoopSettings(time_gap, args.brake_guard is not False, grid,
                                  search_s=args.search_s or 0.0)


def certify_closed_loop(args: argparse.Namespace, policy: MLPPolicy, path: Path,
                        out: Path | None) -> int:
    settings = closed_loop_settings(args, policy)
    try:
        result = clc.run(policy, settings, progress=not args.no_progress)
    except ValueError as exc:  # a checkpoint the bounds do not cover: they say why
        raise clc.ClosedLoopError(str(exc)) from None
    print_closed_loop(result)
    written = clc.write(result, path, out)
    floor = clc.certificate_path(path, out, clc.FLOOR_SUFFIX)
    print(f"certificate: {written} (the floor: {floor})")
    return 0


def check_closed_loop(args: argparse.Namespace, path: Path, out: Path | None) -> int:
    status = clc.load(path, check_path(args, path, out, clc.certificate_path(path)))
    said = ""
    if status.certificate is not None:
        c = status.certificate
        said = (f"; {c['verdict']}: {c['failing_columns']:,} of {c['columns']:,} columns fail, "
                f"S {c['share_of_recoverable_envelope']:.4%} of the recoverable envelope")
    print(f"{status.path}: {'valid' if status.valid else 'INVALID'} ({status.reason}){said}")
    return 0 if status.proven else 1


def _span(lo_hi: list[float], unit: str) -> str:
    return f"{lo_hi[0]:g}-{lo_hi[1]:g} {unit}"


def print_closed_loop(r: clc.ClosedLoopResult) -> None:
    s = r.settings
    (g0, g1, gw), (_, _, vw), (_, _, lw), (_, _, fw) = (s.grid.gap_m, s.grid.speed_mps,
                                                        s.grid.leader_speed_mps, s.grid.force_mps2)
    tg = s.time_gap_s
    times = ", ".join(f"{k} {v:.0f} s" for k, v in r.seconds.items() if k != "total")
    print(f"{r.policy} closed loop: time gap {tg[0]:g}" + (f"-{tg[1]:g}" if tg[1] != tg[0] else "")
          + f" s, brake guard {'on' if s.guard else 'off'}, "
          f"{' x '.join(map(str, s.grid.shape))} cells of {gw:g} m x {vw:g} m/s x {lw:g} m/s x "
          f"{fw:g} m/s^2 (gap {g0:g}-{g1:g} m); {r.seconds['total']:.0f} s ({times})")
    print(f"floor checked: {r.floor['source']}")
    deficits = (f"; median / max deficit {r.deficit_median_m:.2f} / {r.deficit_max_m:.2f} m"
                if r.deficit_max_m is not None else "")
    unbounded = f", {r.unbounded_deficits:,} unbounded" if r.unbounded_deficits else ""
    print(f"verdict: {r.verdict.upper()}: {r.failing_columns:,} of {r.columns:,} columns fail"
          f"{unbounded}{deficits}")
    print(f"S's share of the recoverable envelope: {r.share:.4%}"
          + (f" ± {r.share_stderr:.4%}" if r.proven else
             " (0: only a passing check proves anything)"))
    for reason, n in sorted(r.failing_by_reason.items(), key=lambda kv: -kv[1]):
        print(f"  {n:,} columns: {reason}")
    if r.worst:
        print("worst failing cells (where the proof fails):")
    for c in r.worst[:5]:
        d = "unbounded" if c["deficit_m"] is None else f"{c['deficit_m']:.2f} m"
        print(f"  gap {_span(c['gap_m'], 'm')}, ego {_span(c['speed_mps'], 'm/s')}, leader "
              f"{_span(c['leader_speed_mps'], 'm/s')}, force {_span(c['force_mps2'], 'm/s^2')}: "
              f"deficit {d} (reason {c['reason']}: {c['reason_text']})")


if __name__ == "__main__":
    sys.exit(main())
