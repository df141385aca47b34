"""Train a SafeIL or BC planner on a Tuples Parquet file and write a checkpoint.

    python training/train.py --data tuples.parquet --method safeil --out models/safeil

The command line of :func:`safeil_sumo.learn.trainer.train_checkpoint`. Whole maneuvers are left
out for validation (early stopping and the printed open-loop metrics). Writes
``<out>.safetensors`` + ``<out>.json`` (architecture, scaling, config, data fingerprint,
metrics, per-epoch history). Every field of :class:`safeil_sumo.learn.trainer.TrainConfig` is an
option under its own name (``--max-epochs``, ``--weight-decay``, ...; ``--epochs``, ``--threads``
and ``--monotone-margin`` are kept as aliases), checked by the config itself.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from safeil_sumo.cli_args import add_dataclass_options, dataclass_from_args, finite_float
from safeil_sumo.learn.torch_required import training_imports

with training_imports():  # without torch: one line that says what to install, no traceback
    from safeil_sumo.learn.losses import LATERAL_MODES
    from safeil_sumo.learn.model import ACTIVATIONS, OUTPUT_MODES
    from safeil_sumo.learn.trainer import METHODS, TrainConfig, train_checkpoint

# the names these options had before they were generated from TrainConfig
ALIASES = {"max_epochs": ("--epochs",), "num_threads": ("--threads",),
           "monotone_margin_m": ("--monotone-margin",)}


def build_parser() -> argparse.ArgumentParser:
    """The data, split and output options, and one option per :class:`TrainConfig` field under
    its own name (``--max-epochs``, old names kept as aliases), its help the field's ``help``
    metadata. The config's own checks judge the values: see :func:`config_of`."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, type=Path, nargs="+",
                   help="Tuples Parquet file(s); several are concatenated (e.g. sources)")
    p.add_argument("--val-fraction", type=finite_float, default=0.2,
                   help="fraction of maneuvers left out for validation (default 0.2)")
    p.add_argument("--val-maneuvers", default=None,
                   help="comma-separated maneuver ids to leave out (overrides --val-fraction)")
    helps = {f.name: f.metadata["help"] for f in dataclasses.fields(TrainConfig)}
    add_dataclass_options(p, TrainConfig, helps=helps, aliases=ALIASES,
                          choices={"method": METHODS, "activation": ACTIVATIONS,
                                   "barrier_lateral": LATERAL_MODES,
                                   "output_mode": OUTPUT_MODES})
    p.add_argument("--out", required=True, type=Path, help="checkpoint prefix")
    p.add_argument("--name", default=None,
                   help="policy name stored in the checkpoint (default: the method)")
    p.add_argument("--no-progress", action="store_true")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    if not 0 <= args.val_fraction < 1:
        p.error("--val-fraction must be in [0, 1)")
    return args


def config_of(args: argparse.Namespace) -> TrainConfig:
    """The :class:`TrainConfig` of the parsed options (``ValueError`` naming a bad value)."""
    return dataclass_from_args(TrainConfig, args)


def main(argv: list[str] | None = None) -> dict:
    """Train and save; returns the metrics. Bad input raises ValueError (see :func:`cli`)."""
    args = parse_args(argv)
    config = config_of(args)  # bad values fail here, before any data is read
    val_ids = args.val_maneuvers.split(",") if args.val_maneuvers else None
    result = train_checkpoint(config, args.data, args.out, args.name,
                              val_fraction=args.val_fraction, val_maneuvers=val_ids,
                              progress=not args.no_progress)
    history = result.history
    print("\n".join(result.notes))
    print(f"trained {config.method} in {history.seconds:.1f} s ({len(history.epochs)} epochs, "
          f"{history.samples_per_s:,.0f} samples/s), best epoch {history.best_epoch}")
    print(json.dumps({"config": dataclasses.asdict(config), "metrics": result.metrics}, indent=1))
    print(f"wrote {args.out}.safetensors and {args.out}.json")
    return result.metrics


def cli(argv: list[str] | None = None) -> int:
    """Exit code: 0 trained, 2 bad input (one line on stderr, no checkpoint written)."""
    try:
        main(argv)
    except ValueError as exc:  # Tuples.load, split, config, training data
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(cli())
