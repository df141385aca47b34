"""``python -m safeil_sumo.probe``: does a planner's plan respond to its leader? (no SUMO)

    python -m safeil_sumo.probe --policy safeil safeil_paper bc analytic [--out DIR]

Plans once on every state of a grid (ego 15-35 m/s, leader 10 m/s slower to 5 m/s faster, bumper
gap 8-120 m, straight centred lane) and prints per planner: the share of recoverable states whose
planned trajectory runs past the leader's predicted position (``pass_rate``), the same against a
2 m + 1 s margin, how many (speed, leader speed) pairs plan a SHORTER trajectory for a farther
leader, and planned end speeds at named states. ``--out`` writes ``probe.csv`` (one row per
planner) and ``probe_states.parquet`` (every state and plan). See
:mod:`safeil_sumo.experiments.leader_probe`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

from safeil_sumo.cli_args import CommandParser, add_policy_option, interruptible
from safeil_sumo.experiments import outputs
from safeil_sumo.experiments.leader_probe import probe
from safeil_sumo.planners import registry as pol


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.probe", description=__doc__.split("\n")[0])
    add_policy_option(p, ["safeil", "safeil_paper", "bc", "analytic"],
                      "planner names or checkpoint paths")
    p.add_argument("--out", type=Path, default=None, help="folder for probe.csv (optional)")
    return p


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        loaded = {name: pol.load(name) for name in args.policy}
    except pol.PolicyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows, states = [], []
    for name, policy in loaded.items():
        summary, table = probe(policy)
        rows.append({**summary, "policy": name})
        states.append(table.assign(policy=name))
    df = pd.DataFrame(rows)
    cols = ["policy", "pass_rate", "margin_violation_rate", "gap_monotone_violations",
            "max_end_x_decrease_m", "end_speed_v30_lead25_gap10", "end_speed_v30_lead25_gap50"]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if args.out is not None:
        with outputs.AtomicDir(args.out) as tmp:
            df.to_csv(tmp / "probe.csv", index=False)
            pd.concat(states, ignore_index=True).to_parquet(tmp / "probe_states.parquet")
        print(f"results: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
