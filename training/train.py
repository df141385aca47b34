"""Train a SafeIL or BC planner on a Tuples Parquet file and write a checkpoint.

    python training/train.py --data tuples.parquet --method safeil --out models/safeil

Whole maneuvers are left out for validation (early stopping and the printed open-loop metrics).
Writes ``<out>.safetensors`` + ``<out>.json`` (architecture, scaling, config, data fingerprint,
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
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import save_checkpoint, tuples_fingerprint
from safeil_sumo.learn.evaluate import open_loop_metrics
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.learn.losses import LATERAL_MODES
from safeil_sumo.learn.model import ACTIVATIONS, OUTPUT_MODES
from safeil_sumo.learn.trainer import METHODS, TrainConfig, split_by_maneuver, train
from safeil_sumo.safety_filter import SafeSet

SUMMARY_KEYS = (
    "n", "cp_rmse", "cp_rmse_x", "cp_rmse_y", "ade", "fde", "ade_lateral", "target_fit_ade",
    "min_margin_left_cp", "min_margin_right_cp", "min_margin_lead_cp", "violation_rate_any_cp",
    "min_margin_left_spline", "min_margin_right_spline", "min_margin_lead_spline",
    "violation_rate_any_spline", "hull_gap_rate", "min_margin_left_bern", "min_margin_right_bern",
    "violation_rate_lateral_bern", "target_violation_rate_any_cp",
    "target_violation_rate_lateral_cp", "target_violation_rate_lateral_bern",
    "target_violation_rate_lateral_spline",
)


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
    tuples = Tuples.concat([Tuples.load(path) for path in args.data])
    data_label = ",".join(map(str, args.data))
    if len(tuples) == 0:
        raise ValueError(f"{data_label}: no tuples to train on")
    val_ids = args.val_maneuvers.split(",") if args.val_maneuvers else None
    tr, va = split_by_maneuver(tuples, args.val_fraction, config.seed, val_ids)
    print(f"{data_label}: {len(tuples)} tuples, {len(tuples.maneuvers)} maneuvers; "
          f"train {len(tr)} ({len(tr.maneuvers)}), val {len(va)} ({len(va.maneuvers)}); "
          f"horizon {tuples.horizon:g} s")
    model, history = train(tr, va, config, progress=not args.no_progress)
    safe_set = SafeSet(track=config.track, gap_min=config.gap_min, time_gap=config.time_gap)
    best = history.epochs[history.best_epoch - 1]
    metrics = {"best_epoch": history.best_epoch,
               **{k: v for k, v in best.items() if k.startswith(("train_", "val_"))},
               # which maneuvers were held out: a replay can then check "left out of training"
               "data": data_label, "val_maneuvers": sorted(map(str, va.maneuvers))}
    # Save, then evaluate the checkpoint through the numpy policy the closed loop will use.
    save_checkpoint(
        args.out, model, name=args.name or config.method, horizon=tuples.horizon, train_config=config,
        data_fingerprint=tuples_fingerprint(tuples), metrics=metrics, history=history,
    )
    policy = load_policy(args.out)
    for split, part in (("train", tr), ("val", va)):
        if len(part):
            om = open_loop_metrics(policy, part, safe_set)
            metrics.update({f"open_loop_{split}_{k}": om[k] for k in SUMMARY_KEYS})
    save_checkpoint(
        args.out, model, name=args.name or config.method, horizon=tuples.horizon, train_config=config,
        data_fingerprint=tuples_fingerprint(tuples), metrics=metrics, history=history,
    )
    print(f"trained {config.method} in {history.seconds:.1f} s ({len(history.epochs)} epochs, "
          f"{history.samples_per_s:,.0f} samples/s), best epoch {history.best_epoch}")
    print(json.dumps({"config": dataclasses.asdict(config), "metrics": metrics}, indent=1))
    print(f"wrote {args.out}.safetensors and {args.out}.json")
    return metrics


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
