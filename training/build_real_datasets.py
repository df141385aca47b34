"""Build the real-data tuple sets: NGSIM I-80 pairs and OpenACC Vicolungo (human followers).

    python training/build_real_datasets.py --data-dir ../shared/data --out data/

Writes to ``--out``: ``<name>_drive.parquet`` (the imported drive, schema of
:mod:`safeil_sumo.data.schema`), ``<name>_tuples.parquet``, ``<name>_report.json`` / ``.md`` and
``<name>_maneuver.png``, for ``name`` in ``ngsim``, ``openacc``. The outputs derive from the shared
data: do not commit them. The ACC file (``JRC-VC_260219_part3``) is imported only to report that it
holds no human followers (``--include-acc`` adds its ACC followers to a separate ``openacc_acc``
set).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from safeil_sumo.data.importers import import_ngsim_pairs, import_openacc_files
from safeil_sumo.data.pipeline import PipelineConfig, run_pipeline
from safeil_sumo.data.report import plot_maneuver, write_report
from safeil_sumo.data.schema import save_drive

NGSIM_FILE = "ngsim_i80/i80_pairs.parquet"
OPENACC_HUMAN = ("openacc_vicolungo/JRC-VC_280219_part2.csv.gz",
                 "openacc_vicolungo/JRC-VC_280219_part3.csv.gz")
OPENACC_ACC = ("openacc_vicolungo/JRC-VC_260219_part3.csv.gz",)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-dir", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path, default=Path("data"))
    ap.add_argument("--rate-hz", type=float, default=PipelineConfig.rate_hz)
    ap.add_argument("--horizon-samples", type=int, default=PipelineConfig.horizon_samples)
    ap.add_argument("--min-maneuver", type=float, default=PipelineConfig.min_maneuver,
                    help="shortest maneuver kept [s]")
    ap.add_argument("--max-lead-accel", type=float, default=PipelineConfig.max_lead_accel,
                    help="|a_lead| above this is a cut event [m/s^2]")
    ap.add_argument("--include-acc", action="store_true",
                    help="also build openacc_acc from the ACC-follower file")
    args = ap.parse_args(argv)
    cfg = PipelineConfig(rate_hz=args.rate_hz, horizon_samples=args.horizon_samples,
                         min_maneuver=args.min_maneuver, max_lead_accel=args.max_lead_accel)
    d = args.data_dir
    jobs = [
        ("ngsim", lambda: import_ngsim_pairs(d / NGSIM_FILE)),
        ("openacc", lambda: import_openacc_files([d / p for p in OPENACC_HUMAN])),
    ]
    if args.include_acc:
        jobs.append(("openacc_acc",
                     lambda: import_openacc_files([d / p for p in OPENACC_ACC], include_acc=True)))
    acc_check = import_openacc_files([d / p for p in OPENACC_ACC])
    n_acc_human = acc_check["recording_id"].nunique() if len(acc_check) else 0

    summary = []
    for name, load in tqdm(jobs, desc="datasets", unit="set"):
        drive = load()
        stats = drive.attrs.get("import_stats", {})
        save_drive(drive, args.out / f"{name}_drive.parquet")
        tuples, report = run_pipeline(drive, cfg, source=name)
        tuples.save(args.out / f"{name}_tuples.parquet")
        write_report(report, args.out, name, import_stats=stats)
        if len(tuples):
            plot_maneuver(tuples, args.out / f"{name}_maneuver.png")
        summary.append(
            f"{name}: {report.recordings} recordings, {drive.shape[0]} rows -> "
            f"{report.maneuvers_kept} maneuvers, {report.tuples} tuples, events {report.events}, "
            f"{report.rows_per_s:,.0f} rows/s"
        )
    summary.append(f"ACC file {OPENACC_ACC[0]}: {n_acc_human} human follower recordings")
    print("\n".join(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
