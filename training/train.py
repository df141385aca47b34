"""Train a SafeIL or BC planner on a Tuples Parquet file and write a checkpoint.

    python training/train.py --data tuples.parquet --method safeil --out models/safeil

Whole maneuvers are left out for validation (early stopping and the printed open-loop metrics).
Writes ``<out>.safetensors`` + ``<out>.json`` (architecture, scaling, config, data fingerprint,
metrics, per-epoch history).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from safeil_sumo.cli_args import finite_float, nonnegative_int
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import save_checkpoint, tuples_fingerprint
from safeil_sumo.learn.evaluate import open_loop_metrics
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.learn.losses import LATERAL_MODES
from safeil_sumo.learn.train import TrainConfig, split_by_maneuver, train
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


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    d = TrainConfig()
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, type=Path, nargs="+",
                   help="Tuples Parquet file(s); several are concatenated (e.g. sources)")
    p.add_argument("--method", choices=("safeil", "bc"), default=d.method)
    p.add_argument("--val-fraction", type=finite_float, default=0.2,
                   help="fraction of maneuvers left out for validation (default 0.2)")
    p.add_argument("--val-maneuvers", default=None,
                   help="comma-separated maneuver ids to leave out (overrides --val-fraction)")
    p.add_argument("--seed", type=nonnegative_int, default=d.seed)
    p.add_argument("--epochs", type=int, default=d.max_epochs, help="max epochs")
    p.add_argument("--patience", type=int, default=d.patience)
    p.add_argument("--batch-size", type=nonnegative_int, default=d.batch_size,
                   help="0 = full batch")
    p.add_argument("--lr", type=finite_float, default=d.lr)
    p.add_argument("--hidden", default=",".join(map(str, d.hidden)), help="e.g. 64,64")
    p.add_argument("--activation", choices=("tanh", "relu"), default=d.activation)
    p.add_argument("--barrier-k", type=finite_float, default=d.barrier_k)
    p.add_argument("--track", type=finite_float, default=d.track, help="vehicle track T [m]")
    p.add_argument("--gap-min", type=finite_float, default=d.gap_min, help="extra leader gap [m]")
    p.add_argument("--time-gap", type=finite_float, default=d.time_gap, help="extra leader gap [s]")
    p.add_argument("--barrier-samples", type=nonnegative_int, default=d.barrier_samples,
                   help="also constrain this many points along the spline (0 = paper)")
    p.add_argument("--no-barrier-control-points", action="store_true",
                   help="do not constrain the control points (needs --barrier-samples > 0)")
    p.add_argument("--barrier-lateral", choices=LATERAL_MODES, default=d.barrier_lateral,
                   help="lane barrier on the control points (paper) or on the exact Bernstein "
                        "coefficients of the margin along the spline")
    p.add_argument("--output-mode", choices=("absolute", "residual"), default=d.output_mode,
                   help="control points (paper) or their residual to constant-speed motion")
    p.add_argument("--longitudinal-only-sources", nargs="*", default=list(d.longitudinal_only_sources),
                   help="sources whose lateral (y) targets are not learned (e.g. openacc: no lanes)")
    p.add_argument("--lateral-only-sources", nargs="*", default=list(d.lateral_only_sources),
                   help="sources whose longitudinal (x) targets are not learned (e.g. synthetic)")
    p.add_argument("--envelope-weight", type=finite_float, default=d.envelope_weight,
                   help="weight of the barrier on states sampled across the operating envelope "
                        "(0 = paper)")
    p.add_argument("--monotone-weight", type=finite_float, default=d.monotone_weight,
                   help="weight of the penalty on plans that shorten as the gap grows "
                        "(on the envelope states)")
    p.add_argument("--monotone-margin", type=finite_float, default=d.monotone_margin_m,
                   help="growth [m] of the plan per 2 m of gap asked by the monotonicity penalty")
    p.add_argument("--envelope-batch", type=int, default=d.envelope_batch,
                   help="envelope states per minibatch")
    p.add_argument("--threads", type=int, default=d.num_threads)
    p.add_argument("--out", required=True, type=Path, help="checkpoint prefix")
    p.add_argument("--name", default=None,
                   help="policy name stored in the checkpoint (default: the method)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if not 0 <= args.val_fraction < 1:
        p.error("--val-fraction must be in [0, 1)")
    if args.epochs < 1 or args.patience < 1 or args.threads < 1:
        p.error("--epochs, --patience and --threads must be >= 1")
    if not args.lr > 0 or args.barrier_k < 0 or not args.track > 0:
        p.error("--lr and --track must be > 0, --barrier-k >= 0")
    if args.gap_min < 0 or args.time_gap < 0:
        p.error("--gap-min and --time-gap must be >= 0")
    try:
        hidden = tuple(int(h) for h in args.hidden.split(",") if h.strip())
    except ValueError:
        p.error(f"--hidden needs comma-separated layer widths, got {args.hidden!r}")
    if not hidden or min(hidden) < 1:
        p.error(f"--hidden needs widths >= 1, got {args.hidden!r}")
    args.hidden = hidden
    return args


def main(argv: list[str] | None = None) -> dict:
    """Train and save; returns the metrics. Bad input raises ValueError (see :func:`cli`)."""
    args = parse_args(argv)
    tuples = Tuples.concat([Tuples.load(path) for path in args.data])
    data_label = ",".join(map(str, args.data))
    if len(tuples) == 0:
        raise ValueError(f"{data_label}: no tuples to train on")
    val_ids = args.val_maneuvers.split(",") if args.val_maneuvers else None
    tr, va = split_by_maneuver(tuples, args.val_fraction, args.seed, val_ids)
    config = TrainConfig(
        method=args.method, hidden=args.hidden,
        activation=args.activation, lr=args.lr, batch_size=args.batch_size,
        max_epochs=args.epochs, patience=args.patience, seed=args.seed,
        barrier_k=args.barrier_k, track=args.track, gap_min=args.gap_min,
        time_gap=args.time_gap, barrier_samples=args.barrier_samples,
        barrier_control_points=not args.no_barrier_control_points, num_threads=args.threads,
        barrier_lateral=args.barrier_lateral, output_mode=args.output_mode,
        longitudinal_only_sources=tuple(args.longitudinal_only_sources),
        lateral_only_sources=tuple(args.lateral_only_sources),
        envelope_weight=args.envelope_weight, envelope_batch=args.envelope_batch,
        monotone_weight=args.monotone_weight, monotone_margin_m=args.monotone_margin,
    )
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
        args.out, model, name=args.name or args.method, horizon=tuples.horizon, train_config=config,
        data_fingerprint=tuples_fingerprint(tuples), metrics=metrics, history=history,
    )
    policy = load_policy(args.out)
    for split, part in (("train", tr), ("val", va)):
        if len(part):
            om = open_loop_metrics(policy, part, safe_set)
            metrics.update({f"open_loop_{split}_{k}": om[k] for k in SUMMARY_KEYS})
    save_checkpoint(
        args.out, model, name=args.name or args.method, horizon=tuples.horizon, train_config=config,
        data_fingerprint=tuples_fingerprint(tuples), metrics=metrics, history=history,
    )
    print(f"trained {args.method} in {history.seconds:.1f} s ({len(history.epochs)} epochs, "
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
