"""An upper bound on any invariant set of the longitudinal loop: an adversarial leader.

    python training/loop_adversary.py [--states 1000] [--seed 0] [--time-gaps 0.6 1.5 3.5]
        [--guard on off] [--policy safeil] [--encounters default|mild-sweep|random]
        [--random-count 60] [--sumo K] [--out results/loop_adversary.csv]

Issue 41 asks for a proven invariant set S covering >= 95 % of the recoverable envelope's
volume. S must lie inside the states from which the real loop is safe against every admissible
leader and sensing error, so the share of the envelope from which some admissible adversary
(``safeil_sumo.learn.loop_adversary.default_encounters``) takes the real loop's gap below the
1 m margin bounds S's share from above: at most one minus it. States are drawn uniformly from
the envelope's volume over ``loop_invariant.Grid()``'s box (seeded). Prints, per setting, that
share (and contact, the gap at or below 0) with its standard error and the encounters that find
it; writes one CSV row per setting and encounter (docs/certification.md). ``--encounters
random``: the default encounters and ``--random-count`` random leaders
(``loop_adversary.random_encounters``, drawn from ``[--seed, 1]``: a stream apart from the
states'). ``--sumo K``: instead, per setting, up to K counterexamples among ``--states``
cruising starts (drawn from ``[--seed, 2]``, exact sensing, the encounters' leaders) replayed
in libsumo (``safeil_sumo.experiments.loop_counterexamples``), one row each in
``<out>_sumo.csv``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from safeil_sumo.experiments import loop_counterexamples as lc
from safeil_sumo.learn import loop_adversary as adv
from safeil_sumo.learn.loop_invariant import LoopAssumptions, LoopParts
from safeil_sumo.planners import registry

REPO = Path(__file__).resolve().parents[1]


def _rows(m: adv.Measurement, a: LoopAssumptions, seconds: float) -> list[dict]:
    """The CSV rows of one setting: the union first, then every encounter."""
    union, union_err = m.share(m.union_failed(a.margin_m))
    contact, contact_err = m.share(m.union_failed(1e-12))
    common = {"time_gap_s": m.time_gap, "guard": "on" if m.guard_on else "off",
              "states": m.g_min.shape[1]}
    rows = [{**common, "encounter": "union", "margin_share": union, "margin_se": union_err,
             "contact_share": contact, "contact_se": contact_err, "only_this": float("nan"),
             "seconds": seconds}]
    for name, share, only in m.by_encounter(a.margin_m):
        rows.append({**common, "encounter": name, "margin_share": share, "only_this": only})
    return rows


def _print(rows: list[dict]) -> None:
    u = rows[0]
    print(f"time gap {u['time_gap_s']:.1f} s, guard {u['guard']}, {u['states']} states: "
          f"below the margin {100 * u['margin_share']:.1f} ± {100 * u['margin_se']:.1f} %, "
          f"contact {100 * u['contact_share']:.1f} ± {100 * u['contact_se']:.1f} % "
          f"=> S <= {100 * (1 - u['margin_share']):.1f} % ({u['seconds']:.0f} s)")
    for r in sorted(rows[1:], key=lambda r: -r["margin_share"])[:4]:
        print(f"    {r['encounter']:<58} {100 * r['margin_share']:5.1f} %  "
              f"(only this: {100 * r['only_this']:.1f} %)")


def _print_sumo(df: pd.DataFrame, margin_m: float) -> None:
    if df.empty:
        print("    SUMO: no counterexample from a cruising start")
        return
    ran = df[df["end_reason"] != "not replayed"]
    apart = ran[ran["end_reason"] != "collision"]
    diff = (apart["sumo_gap_m"] - apart["rollout_gap_m"]).abs()
    print(f"    {len(df)} counterexamples; replayed in libsumo {len(ran)}: "
          f"{int(ran['confirmed'].sum())} below {margin_m:g} m there too "
          f"({int((ran['end_reason'] == 'collision').sum())} collisions; without a collision "
          f"|SUMO - rollout| at most {diff.max() if len(diff) else float('nan'):.3f} m)")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--states", type=int, default=1000, help="states drawn per setting")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time-gaps", type=float, nargs="+", default=[0.6, 1.5, 3.5])
    p.add_argument("--guard", nargs="+", choices=("on", "off"), default=["on", "off"])
    p.add_argument("--policy", default="safeil", help="a shipped planner with a time gap")
    p.add_argument("--encounters", choices=("default", "mild-sweep", "random"),
                   default="default", help="default_encounters, mild_sweep_encounters (mild "
                   "braking swept), or random_encounters (the defaults and random leaders)")
    p.add_argument("--random-count", type=int, default=60,
                   help="random leaders with --encounters random")
    p.add_argument("--sumo", type=int, default=0, metavar="K",
                   help="instead of the share: replay up to K counterexamples per setting "
                   "in libsumo")
    p.add_argument("--out", type=Path, default=REPO / "results" / "loop_adversary.csv")
    args = p.parse_args(argv)
    sumo_out, confirmed = args.out.with_name(f"{args.out.stem}_sumo.csv"), []
    policy = registry.load(args.policy)
    a, rows = LoopAssumptions(), []
    encounters = {"default": adv.default_encounters, "mild-sweep": adv.mild_sweep_encounters,
                  "random": lambda a: adv.random_encounters(
                      args.random_count, np.random.default_rng([args.seed, 1]), a)
                  }[args.encounters](a)
    for guard in args.guard:
        for time_gap in args.time_gaps:
            if args.sumo:
                leaders = tuple(dict.fromkeys(e.leader for e in encounters))
                df = lc.confirm(policy, time_gap, guard == "on", args.states, args.sumo,
                                np.random.default_rng([args.seed, 2]), leaders, a)
                print(f"time gap {time_gap:.1f} s, guard {guard}, {args.states} cruising "
                      f"starts:")
                _print_sumo(df, a.margin_m)
                confirmed.append(df)
                sumo_out.parent.mkdir(parents=True, exist_ok=True)
                pd.concat(confirmed).to_csv(sumo_out, index=False)
                continue
            start = time.perf_counter()
            # the same states at every setting: one seed
            m = adv.measure(policy, time_gap, guard == "on", args.states,
                            np.random.default_rng(args.seed), a, LoopParts(),
                            encounters=encounters)
            new = _rows(m, a, time.perf_counter() - start)
            _print(new)
            rows += new
            args.out.parent.mkdir(parents=True, exist_ok=True)
            pd.DataFrame(rows).to_csv(args.out, index=False)  # after each setting: resumable
    print(f"wrote {sumo_out if args.sumo else args.out}")


if __name__ == "__main__":
    main()
