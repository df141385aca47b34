"""Build the default synthetic dataset: several calibrated drivers x the full n74 road, in SUMO.

    python training/build_synthetic_dataset.py [--drivers 16] [--workers 2] [--seed 0]
                                               [--out data/synthetic/drives.parquet]

Driver ``i`` draws its parameters from the calibrated population
(:func:`safeil_sumo.data.synthetic.sample_driver`, generator seeded with ``(seed, i)``) and drives
the whole 29.2 km with SUMO seed ``seed * 1000 + i``. libsumo runs one simulation per process,
so each drive runs in its own worker process (a ``spawn`` pool: no libsumo state is inherited).
Writes the drives (schema-validated Parquet), ``drivers.json`` (each driver's parameters and
recording stats) beside it, then runs the paper's processing pipeline on them: ``tuples.parquet``
(the default training set), ``synthetic_report.{json,md}`` and ``synthetic_maneuver.png``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import pandas as pd

from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.data.pipeline import PipelineConfig, run_pipeline
from safeil_sumo.data.report import plot_maneuver, write_report
from safeil_sumo.data.schema import load_drive, save_drive
from safeil_sumo.data.synthetic_drives import record_drivers

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "data" / "synthetic" / "drives.parquet"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drivers", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-lane-changes", action="store_true", help="drivers never change lane")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--reuse-drives", action="store_true",
                    help="keep the recorded drives in --out (same seed and drivers) and only "
                         "rerun the processing pipeline into tuples")
    args = ap.parse_args(argv)
    if args.reuse_drives and args.out.is_file():
        build_tuples(load_drive(args.out), args.out)
        return

    t0 = time.perf_counter()
    drives, stats_list = record_drivers(args.drivers, args.seed, not args.no_lane_changes,
                                        args.workers)
    stats = dict(enumerate(stats_list))
    save_drive(drives, args.out)
    wall = time.perf_counter() - t0
    hours = sum(s["duration_s"] for s in stats.values()) / 3600.0
    km = sum(s["driven_m"] for s in stats.values()) / 1000.0
    summary = {
        "drivers": args.drivers,
        "seed": args.seed,
        "workers": args.workers,
        "rows": len(drives),
        "driving_hours": round(hours, 3),
        "driven_km": round(km, 1),
        "wall_s": round(wall, 1),
        "leader_fraction": round(float(drives["lead_x"].notna().mean()), 4),
        "lane_changes": int(sum(s["lane_changes"] for s in stats.values())),
        "collision_steps": int(sum(s["collision_steps"] for s in stats.values())),
        "recordings": [stats[i] for i in range(args.drivers)],
    }
    with atomic_path(args.out.with_name("drivers.json")) as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"{args.out}: {len(drives)} rows, {args.drivers} drivers, {hours:.2f} h of driving "
          f"({km:.0f} km) in {wall:.0f} s wall on {args.workers} workers "
          f"({hours * 3600 / wall:.0f}x real time); leader in "
          f"{summary['leader_fraction']:.0%} of samples, {summary['lane_changes']} lane changes, "
          f"{summary['collision_steps']} collision steps")

    build_tuples(drives, args.out)


def build_tuples(drives: pd.DataFrame, out: Path) -> None:
    """The processing pipeline over the recorded drives -> ``tuples.parquet`` and its report."""
    tuples, report = run_pipeline(drives, PipelineConfig(), source="synthetic")
    tuples.save(out.with_name("tuples.parquet"))
    write_report(report, out.parent, "synthetic")
    plot_maneuver(tuples, out.parent / "synthetic_maneuver.png")
    print(f"{out.with_name('tuples.parquet')}: {len(tuples)} tuples from "
          f"{len(tuples.maneuvers)} maneuvers; events {report.events}")


if __name__ == "__main__":
    main()

