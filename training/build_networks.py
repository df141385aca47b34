"""Regenerate the committed SUMO test tracks under ``sumo_scenarios/``.

    python training/build_networks.py            # curved500 and straight
    python training/build_networks.py curved300  # any catalogue name, into sumo_scenarios/<name>/

The outputs are deterministic (no dates in the files): rerunning leaves ``git status`` clean.
"""

from __future__ import annotations

import argparse
import time

from safeil_sumo.roads.catalogue import CATALOGUE, COMMITTED_DIR, spec_for
from safeil_sumo.roads.network import build_network


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=list(CATALOGUE), help="track names")
    args = parser.parse_args(argv)
    for name in args.names:
        spec = spec_for(name)
        t0 = time.perf_counter()
        net = build_network(spec, COMMITTED_DIR / name)
        print(f"{name}: {net.relative_to(COMMITTED_DIR.parent)} ({time.perf_counter() - t0:.2f} s)")


if __name__ == "__main__":
    main()
