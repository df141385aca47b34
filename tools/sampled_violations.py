"""Sampled (Monte Carlo) violation rates of a planner's certified margins over the envelope.

    python tools/sampled_violations.py safeil data/exp/lanebar/safeil_lanebar.safetensors \
        [--n 1000000] [--seed 0]

Per policy and margin: the share of the certificate's envelope measure where the margin truly
fails (``learn.certify_margins.sampled_violations``), i.e. the most ``certify`` could ever prove
is 100 % minus it. Not a proof: a sample.
"""

from __future__ import annotations

import argparse
import json
import time

from safeil_sumo.certify import resolve
from safeil_sumo.learn.certify_margins import Properties, sampled_violations


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("policies", nargs="+", help="shipped name or .safetensors path")
    ap.add_argument("--n", type=int, default=1_000_000, help="states per part (leader, none)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for name in args.policies:
        policy, _, _ = resolve(name)
        t0 = time.perf_counter()
        res = sampled_violations(policy, Properties.from_metadata(policy.metadata), args.n,
                                 args.seed)
        print(json.dumps({"policy": name, "n_per_part": args.n, "seed": args.seed,
                          "seconds": round(time.perf_counter() - t0, 1), **res}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
