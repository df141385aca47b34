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


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.certify", description=__doc__.split("\n")[0])
    add_policy_option(p, ["safeil"], "a shipped network (safeil, safeil_openloop, safeil_paper, "
                      "bc) or a checkpoint path (.safetensors)", many=False)
    p.add_argument("--time-gap-range-s", type=finite_float, nargs=2, metavar=("LO", "HI"),
                   default=None,
                   help="certify a style-conditioned checkpoint over this range of its time-gap "
                        "setting [s] (an extra input dimension); default: at its default setting")
    p.rename(time_gap="--time-gap-range-s")
    p.add_argument("--margins", nargs="+", choices=MARGINS, default=list(MARGINS),
                   help="the margins to certify (default both; the budget is shared equally)")
    p.add_argument("--budget-s", type=finite_float, default=600.0,
                   help="wall-time budget for all margins [s] (default 600)")
    p.add_argument("--max-boxes", type=nonnegative_int, default=None,
                   help="box budget for all margins (reproducible across machines)")
    p.add_argument("--batch", type=nonnegative_int, default=512, help="boxes bounded together")
    p.add_argument("--seed", type=int, default=0, help="seeds the counterexample search")
    p.add_argument("--cex-min-share", type=finite_float, default=Budget.cex_min_share,
                   help="split a box holding a counterexample only while its share of the "
                        f"envelope exceeds this (default {Budget.cex_min_share:g})")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for the certificate (default: next to the checkpoint; "
                        "runs/certify_<name>/ for a shipped model)")
    p.add_argument("--check", nargs="?", const="", default=None, metavar="CERTIFICATE",
                   help="only report whether the checkpoint has a valid certificate (default "
                        "path: in --out if given, else next to the checkpoint, else in "
                        "runs/certify_<name>/ for a shipped model)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    args.policy = one_policy(p, args, "certify each network in turn")
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


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        policy, path, shipped = resolve(args.policy)
        out = args.out if args.out is not None else (
            Path("runs") / f"certify_{args.policy}" if shipped else None)
        if args.check is not None:
            # a given file; else in --out; else next to the checkpoint (where a shipped model's
            # own certificate is shipped), for a shipped model without one in runs/
            cert = None
            if args.check:
                cert = Path(args.check)
            elif out is not None and (args.out is not None or not certificate_path(path).is_file()):
                cert = certificate_path(path, out)
            status = load_certificate(path, cert)
            shares = ", ".join(f"{k} {v:.4%}" for k, v in status.certified.items())
            print(f"{status.path}: {'valid' if status.valid else 'INVALID'} ({status.reason})"
                  + (f"; certified {shares}" + (" (complete)" if status.complete else "")
                     if status.certified else ""))
            return 0 if status.valid else 1
        env = CertEnvelope(time_gap_s=tuple(args.time_gap_range_s) if args.time_gap_range_s
                           else None)
        budget = Budget(seconds=args.budget_s, boxes=args.max_boxes, batch=max(args.batch, 1),
                        seed=args.seed, cex_min_share=args.cex_min_share)
        result = certify(policy, env, budget=budget, margins=tuple(args.margins),
                         progress=not args.no_progress)
    except (CertifyError, pol.PolicyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print_result(result)
    written = write_certificate(result, path, out)
    print(f"certificate: {written}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
