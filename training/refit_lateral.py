"""Refit a towers checkpoint's lateral plan to its own longitudinal plan.

    python training/refit_lateral.py --init data/models/safeil_cl.safetensors \
        --reference safeil_sumo/models/safeil_openloop.safetensors \
        --data data/synthetic/tuples.parquet data/openacc_tuples.parquet \
               data/ngsim_tuples.parquet --out data/models/safeil

The command line of :func:`safeil_sumo.learn.lateral_refit.refit_lateral` (what it learns and
keeps: see there). Every field of :class:`safeil_sumo.learn.lateral_refit.LateralRefitConfig`
is an option under its own name, checked by the config itself.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from safeil_sumo.cli_args import add_dataclass_options, config_or_usage_error
from safeil_sumo.learn.torch_required import training_imports

with training_imports():  # without torch: one line that says what to install, no traceback
    from safeil_sumo.learn.lateral_refit import LateralRefitConfig, refit_lateral


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--init", type=Path, required=True, help="towers checkpoint")
    ap.add_argument("--reference", type=Path,
                    default=Path("safeil_sumo/models/safeil_openloop.safetensors"),
                    help="9-input checkpoint whose lane keeping is carried over")
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="tuple Parquet files")
    ap.add_argument("--out", type=Path, required=True, help="checkpoint prefix")
    add_dataclass_options(ap, LateralRefitConfig)
    ap.add_argument("--no-progress", action="store_true")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    config = config_or_usage_error(ap, LateralRefitConfig, args)
    result = refit_lateral(config, args.init, args.reference, args.data, args.out,
                           progress=not args.no_progress)
    run = result.metrics["lateral_refit"]
    print(f"{run['seconds']:.0f} s; fit {run['first']['fit_m2']:.3g} -> "
          f"{run['last_100_mean']['fit_m2']:.3g} m^2; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
