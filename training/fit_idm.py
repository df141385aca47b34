"""Calibrate the IDM baseline on the human car following the learned planners are trained on:

    python training/fit_idm.py [--data-dir ../shared/data] [--exclude-from safeil_sumo/models/safeil.json]
                               [--drives FILE ...] [--out safeil_sumo/models/idm.json]

Per source (OpenACC Vicolungo, NGSIM I-80, and any ``--drives`` file in the recorded-drive schema)
and per driver where the data identify drivers (OpenACC: the platoon position ``f<k>`` of one
campaign day, the same car and driver in every part; NGSIM: the follower's vehicle id), the 5 IDM
parameters are fitted by closed-trajectory simulation behind the recorded leader over whole
maneuvers (the processing pipeline's, at 10 Hz), minimising the spacing RMSE
(:func:`safeil_sumo.planners.idm.fit_idm`). The maneuvers a checkpoint held out (``--exclude-from``: its
``metrics.val_maneuvers``; default: the shipped ``safeil``) are left out of the fit and the fit is
also scored on them. ``--policy idm`` uses the OpenACC fit: motorway driving like the paper's.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.schema import load_drive
from safeil_sumo.data.sources import DEFAULT_DATA_DIR, driver_of, load_source
from safeil_sumo.learn.checkpoint import held_out_maneuvers
from safeil_sumo.planners import idm

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "safeil_sumo" / "models" / "idm.json"
DEFAULT_EXCLUDE = REPO / "safeil_sumo" / "models" / "safeil.json"
MIN_DRIVER_SAMPLES = 600  # [-] a driver needs >= 60 s at 10 Hz for a per-driver fit


def held_out_ids(paths: list[Path]) -> set[str]:
    """Maneuver ids held out by checkpoints (``metrics.val_maneuvers``) or plain JSON lists."""
    ids: set[str] = set()
    for p in paths:
        doc = json.loads(Path(p).read_text())
        ids |= set(map(str, doc)) if isinstance(doc, list) else set(held_out_maneuvers(p))
    return ids


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR)
    ap.add_argument("--drives", type=Path, nargs="*", default=[],
                    help="extra drive files (recorded-drive schema), one source each")
    ap.add_argument("--exclude-from", type=Path, nargs="*", default=None,
                    help="checkpoint sidecars / JSON lists of maneuver ids to leave out "
                         f"(default {DEFAULT_EXCLUDE.relative_to(REPO)})")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    exclude_paths = args.exclude_from if args.exclude_from is not None else (
        [DEFAULT_EXCLUDE] if DEFAULT_EXCLUDE.is_file() else [])
    try:
        held = held_out_ids(exclude_paths)
    except (OSError, ValueError) as exc:
        print(f"error: cannot read held-out maneuvers: {exc}", file=sys.stderr)
        return 2
    sources = {"openacc": lambda: load_source("openacc", args.data_dir),
               "ngsim": lambda: load_source("ngsim", args.data_dir)}
    for path in args.drives:
        sources[path.stem] = lambda path=path: load_drive(path)

    fits, per_driver, scores = {}, {}, {}
    for source, load in tqdm(sources.items(), desc="sources"):
        rows, _ = process_drive(load(), PipelineConfig(rate_hz=10.0))
        maneuvers = idm.maneuvers_from_rows(rows)
        train = [m for m in maneuvers if m.maneuver_id not in held]
        test = [m for m in maneuvers if m.maneuver_id in held]
        fit = idm.fit_idm(train, seed=args.seed)
        fits[source] = fit
        score = {"fit_rmse_gap_m": fit.rmse_gap_m, "fit_rmse_speed_mps": fit.rmse_speed_mps,
                 "fit_maneuvers": len(train), "held_out_maneuvers": len(test)}
        if test:
            g, v = idm.evaluate_fit(test, fit.params)
            score |= {"held_out_rmse_gap_m": g, "held_out_rmse_speed_mps": v}
        scores[source] = score
        by_driver: dict[str, list] = {}
        for m in train:
            by_driver.setdefault(driver_of(source, m.maneuver_id), []).append(m)
        for driver, ms in tqdm(sorted(by_driver.items()), desc=f"{source} drivers", leave=False):
            if sum(len(m.times) for m in ms) >= MIN_DRIVER_SAMPLES:
                per_driver[driver] = idm.fit_idm(ms, seed=args.seed, starts=2)
        print(f"{source}: {fit.params} | {json.dumps(score)}")
    idm.save_model(args.out, fits, default="openacc", per_driver=per_driver,
                   extra={"scores": scores,
                          "held_out_from": [str(p.relative_to(REPO)) if p.is_relative_to(REPO)
                                            else str(p) for p in exclude_paths]})
    print(f"wrote {args.out} ({len(per_driver)} per-driver fits)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
