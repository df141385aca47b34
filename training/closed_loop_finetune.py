"""Closed-loop fine-tuning of a SafeIL checkpoint behind recorded human leaders.

    python training/closed_loop_finetune.py --init safeil_sumo/models/safeil_openloop.safetensors \
        --data data/openacc_tuples.parquet data/ngsim_tuples.parquet --out data/models/safeil_cl

The command line of :func:`safeil_sumo.learn.finetune.finetune` (what it learns, and what it
keeps from the initial checkpoint: see there). Every field of
:class:`safeil_sumo.learn.closed_loop.FinetuneConfig` is an option under its own name
(``--window``, ``--style``, ``--settle-weight``, ...), checked by the config itself.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from safeil_sumo.cli_args import add_dataclass_options, config_or_usage_error
from safeil_sumo.learn.torch_required import training_imports

with training_imports():  # without torch: one line that says what to install, no traceback
    from safeil_sumo.learn.closed_loop import FinetuneConfig
    from safeil_sumo.learn.finetune import finetune


def build_parser() -> argparse.ArgumentParser:
    """The input and output options, and one option per :class:`FinetuneConfig` field under its
    own name, its help the field's ``help`` metadata."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--init", type=Path,
                    default=Path("safeil_sumo/models/safeil_openloop.safetensors"))
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="tuple Parquet files")
    ap.add_argument("--out", type=Path, required=True, help="checkpoint prefix")
    add_dataclass_options(ap, FinetuneConfig)
    ap.add_argument("--no-progress", action="store_true")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    config = config_or_usage_error(ap, FinetuneConfig, args)
    result = finetune(config, args.init, args.data, args.out, progress=not args.no_progress)
    run = result.metrics["closed_loop"]
    print("\n".join(result.notes))
    print(f"{run['seconds']:.0f} s; first {run['first']['gap']:.1f} m^2 gap, last "
          f"{run['final']['gap']:.1f}; wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
