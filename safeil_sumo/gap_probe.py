"""``python -m safeil_sumo.gap_probe``: step responses of the planners' gap regulation in SUMO.

    python -m safeil_sumo.gap_probe --policy safeil idm analytic [--speeds-mps 15 25 35]
        [--workers 2] [--out runs/gap_probe]

At each speed (default 15, 25, 35 m/s) and for each step kind (the leader pulling away by
+3 m/s, slowing by -3 m/s, the ego starting 100 m behind, starting 10 m closer than a 1 s time
gap) every policy drives one closed loop on the n74 road; the humans' steady-following time
gaps per speed band come from the real data (``--data-dir``). Definitions:
:mod:`safeil_sumo.experiments.gap_step_responses` and ``docs/gap_probe.md``.

Writes into ``--out``: ``gap_probe.csv`` (one row per policy x speed x step kind, then the
``humans`` rows), ``gap_probe.png`` (time gap vs time, a panel per kind and speed),
``series.parquet`` (the time series at 2 Hz), ``manifest.json``, and the sweep's task files in
``runs/`` (rerunning the same command resumes). Exit codes: 0 ok, 1 a run failed, 2 bad
input, 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from safeil_sumo.cli_args import (
    CommandParser,
    add_policy_option,
    finite_float,
    interruptible,
    nonnegative_int,
    positive_int,
)
from safeil_sumo.core.atomic import atomic_path
from safeil_sumo.data.sources import DEFAULT_DATA_DIR
from safeil_sumo.experiments import gap_step_responses as gp
from safeil_sumo.experiments import outputs

if TYPE_CHECKING:
    import pandas as pd


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.gap_probe",
                      description=__doc__.split("\n")[0].split(": ", 1)[1])
    add_policy_option(p, ["safeil", "idm", "analytic"], "safeil, safeil_paper, bc, analytic, "
                      "idm, checkpoints or IDM model files")
    p.add_argument("--speeds-mps", nargs="+", type=finite_float, default=list(gp.SPEEDS_MPS),
                   metavar="V", help="probe speeds [m/s] (default 15 25 35)")
    p.rename(speeds="--speeds-mps")
    p.add_argument("--kinds", nargs="+", choices=gp.KINDS, default=list(gp.KINDS),
                   help="step kinds (default: all four)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="master seed (default 0)")
    p.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR,
                   help=f"real human data for the humans' rows (default {DEFAULT_DATA_DIR})")
    p.add_argument("--no-humans", action="store_true", help="leave out the humans' rows")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="local worker processes, one simulation each (default 1)")
    p.add_argument("--out", type=Path, default=Path("runs/gap_probe"),
                   help="results folder (default runs/gap_probe); rerun to resume")
    p.add_argument("--retry-failed", action="store_true", help="rerun runs that failed before")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    if any(not gp.LEADER_STEP_MPS < v <= 60.0 for v in args.speeds_mps):
        p.error(f"--speeds-mps must be in ({gp.LEADER_STEP_MPS:g}, 60] m/s")
    if args.out.exists() and not args.out.is_dir():
        p.error(f"--out {args.out} exists and is not a folder")
    return args


def format_table(table: pd.DataFrame) -> str:
    """The printed summary: one line per run, then the humans' bands."""
    runs = table[table["policy"] != gp.HUMANS]
    cols = {"policy": "policy", "speed_mps": "v[m/s]", "kind": "kind",
            "eq_time_gap_s": "eq tg[s]", "min_time_gap_s": "min tg[s]",
            "settling_time_s": "settle[s]", "settled": "settled", "rise_time_s": "rise[s]",
            "overshoot_m": "overshoot[m]", "drift_m": "drift[m]", "flag": "flag"}
    text = runs[list(cols)].rename(columns=cols).to_string(
        index=False, float_format=lambda v: f"{v:.2f}")
    humans = table[table["policy"] == gp.HUMANS]
    if len(humans):
        hcols = ["speed_mps", "human_p05_s", "human_p25_s", "human_p50_s", "human_p75_s",
                 "samples", "maneuvers", "drivers"]
        text += "\n\nhumans, steady following:\n" + humans[hcols].to_string(
            index=False, float_format=lambda v: f"{v:.2f}")
    return text


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from safeil_sumo.experiments.sweep_executor import run_sweep
    from safeil_sumo.planners import registry as planner_registry
    from safeil_sumo.scenarios.spec import resolve_road

    try:
        for name in dict.fromkeys(args.policy):  # fail fast, before any run
            planner_registry.load(name)
        tasks = gp.probe_tasks(args.policy, args.speeds_mps, args.kinds, args.seed)
        resolve_road(gp.NET, (), *gp.STRETCH_KM)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    humans = None
    if not args.no_humans:
        try:
            humans = gp.human_time_gap_bands(gp.load_human_rows(args.data_dir), args.speeds_mps)
        except (ValueError, OSError) as exc:  # SchemaError is a ValueError
            print(f"warning: no humans' rows ({exc})", file=sys.stderr)
    config = {"policies": args.policy, "speeds_mps": args.speeds_mps, "kinds": args.kinds,
              "net": gp.NET, "stretch_km": list(gp.STRETCH_KM),
              "leader_step_mps": gp.LEADER_STEP_MPS, "leader_rate_mps2": gp.LEADER_RATE_MPS2,
              "settle_s": gp.SETTLE_S, "after_step_s": gp.AFTER_STEP_S,
              "start_time_gap_s": gp.START_TIME_GAP_S, "far_gap_m": gp.FAR_GAP_M,
              "close_gap": f"max({gp.CLOSE_MIN_GAP_M:g}, {gp.CLOSE_TIME_GAP_S:g} s * v - "
                           f"{gp.CLOSE_BELOW_M:g}) m",
              "final_window_s": gp.FINAL_WINDOW_S, "band": gp.BAND, "hold_s": gp.HOLD_S,
              "humans": None if humans is None else {
                  "data_dir": str(args.data_dir), "sources": list(gp.HUMAN_SOURCES),
                  "band_mps": gp.HUMAN_BAND_MPS, "max_accel_mps2": gp.HUMAN_MAX_ACCEL_MPS2,
                  "max_dv_mps": gp.HUMAN_MAX_DV_MPS}}
    try:
        records = run_sweep(tasks, args.out / "runs", workers=args.workers,
                            progress=not args.no_progress, retry_failed=args.retry_failed,
                            task_fn=gp.run_probe_task, manifest_extra={"gap_probe": config})
    except KeyboardInterrupt:
        print(f"\ninterrupted: finished runs are saved in {args.out / 'runs'}; rerun the same "
              "command to resume", file=sys.stderr)
        return 130
    table = gp.table(records, humans)
    series = gp.series(records)
    with atomic_path(args.out / "gap_probe.csv") as tmp:
        table.to_csv(tmp, index=False)
    with atomic_path(args.out / "series.parquet") as tmp:
        series.to_parquet(tmp, index=False)
    with atomic_path(args.out / "gap_probe.png") as tmp:
        gp.plot(series, humans, tmp)
    from safeil_sumo.scenarios.safety import scenario_seed

    outputs.write_json(args.out / "manifest.json", outputs.manifest(
        config, [scenario_seed(t.scenario.master_seed, t.scenario.index) for t in tasks]))
    print(format_table(table))
    failed = records[records["status"] != "ok"]
    for _, row in failed.iterrows():
        print(f"run {row['policy']} {gp.kind_of(int(row['index']))} failed: {row['error']}",
              file=sys.stderr)
    print(f"results: {args.out}")
    return 1 if len(failed) else 0


if __name__ == "__main__":
    sys.exit(main())
