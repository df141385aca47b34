"""``safeil-train`` (``python -m safeil_sumo.train``): train a planner from a recipe and recordings.

    safeil-train --out runs/my_model --recipe my_recipe.toml
    safeil-train --out runs/my_model --data openacc:path/to/openacc_dir ngsim:i80_pairs.parquet
    safeil-train --dry-run            # the shipped recipe: its data, stages and cost, no training

A recipe (TOML, docs/training.md) names the data by format and path, the held-out split and the
stages: open-loop imitation with the barrier, closed-loop fine-tune, lateral refit; then the
final checkpoint is certified. Without ``--recipe`` the shipped recipe runs (what reproduced the
shipped ``safeil``). ``--data FORMAT:PATH ...`` replaces the recipe's data. Before it trains it
prints the data, each stage's work and an estimated time. Writes into ``--out``: ``<name>.
safetensors`` + ``.json`` (loadable with ``--policy PATH``), ``<name>.certificate.json``,
``summary.json`` / ``summary.md``, and each stage's checkpoint in ``stages/``. Interrupted, a
rerun of the same command resumes after the last finished stage (same recipe and data: checked
by their digest). Deterministic for the recipe's seed on one machine. Needs torch (``pip install
'safeil-sumo[train]'``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from safeil_sumo.cli_args import CommandParser, add_data_options, data_specs, interruptible
from safeil_sumo.data.by_path import DataError
from safeil_sumo.learn.torch_required import training_imports


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.train", description=__doc__.split("\n")[0])
    p.add_argument("--recipe", type=Path, default=None, metavar="TOML",
                   help="the training recipe (default: the shipped one, "
                        "safeil_sumo/recipes/shipped.toml)")
    add_data_options(p, "the recordings, replacing the recipe's data (each source named after "
                        "its format)")
    p.add_argument("--data-dir", type=Path, default=None, metavar="DIR",
                   help="folder the recipe's relative data paths start from (default: the "
                        "recipe's data_dir, else its folder; the shipped recipe: ../shared/data "
                        "beside the checkout)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output folder (default runs/train_<recipe name>); a rerun into the "
                        "same folder resumes")
    p.add_argument("--dry-run", action="store_true",
                   help="process the data and print the plan and its cost; train nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return p


def parse_args(argv: list[str] | None = None) -> tuple[CommandParser, argparse.Namespace]:
    p = build_parser()
    args = p.parse_args(argv)
    args.data_specs = data_specs(p, args)
    return p, args


@interruptible
def main(argv: list[str] | None = None) -> int:
    parser, args = parse_args(argv)
    with training_imports():  # without torch: one line that says what to install
        from safeil_sumo.learn.checkpoint import CheckpointError
        from safeil_sumo.learn.recipe import RecipeError, load_recipe
        from safeil_sumo.learn.stages import run_recipe
    try:
        recipe = load_recipe(args.recipe, args.data_dir)
        if args.data_specs is not None:
            recipe = recipe.with_data(args.data_specs)
        out = args.out if args.out is not None else Path("runs") / f"train_{recipe.name}"
        summary = run_recipe(recipe, out, progress=not args.no_progress, dry_run=args.dry_run)
    except (RecipeError, DataError, CheckpointError) as exc:
        parser.error(str(exc))
    if args.dry_run:
        return 0
    cert = summary.get("certificate")
    shares = (", ".join(f"{m} {v:.4%}" for m, v in cert["certified"].items())
              if cert else "not certified")
    print(f"checkpoint: {summary['checkpoint']} (--policy {summary['checkpoint']}); "
          f"certificate: {shares}; IDM baseline: {summary['idm'].get('path', 'none')}; summary: "
          f"{out / 'summary.md'}; {summary['seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
