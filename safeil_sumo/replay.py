"""``python -m safeil_sumo.replay``: human-likeness replay of a recorded maneuver (paper IV-C/D).

    python -m safeil_sumo.replay --source openacc --maneuver auto --policy analytic safeil bc

Imports the source (``openacc``/``zalazone``/``ngsim`` from the shared data folder, or a drive
file in the schema of :mod:`safeil_sumo.data.schema`, e.g. a synthetic recording), runs the processing
pipeline (maneuvers), rebuilds the chosen maneuver in SUMO, drives it closed-loop with each policy
and prints the comparison with the human. Writes into ``--out``: ``metrics.csv/json``,
``steps.parquet``, ``human.parquet``, ``compared.parquet``, ``replay.png``, ``manifest.json``,
the SUMO files in ``net/``, and with ``--animate`` ``animation_<policy>.mp4`` (or ``.gif``, see
:mod:`safeil_sumo.animate`). Exit codes: 0 ok, 1 a run failed, 2 bad input, 3 SUMO error.

The maneuver should be one left out of the policies' training (``training/train.py
--val-maneuvers <id>``); the replay does not know which maneuvers a checkpoint was trained on.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import pandas as pd

from safeil_sumo import api
from safeil_sumo.cli_args import (
    CommandParser,
    add_brake_guard_option,
    add_csv_options,
    add_plan_rate_option,
    add_policy_option,
    add_scheduler_option,
    add_task_options,
    add_time_gap_option,
    check_scheduler,
    check_style_options,
    check_task_options,
    finite_float,
    interruptible,
    nonnegative_int,
    positive_int,
)
from safeil_sumo.data.pipeline import PipelineConfig, process_drive
from safeil_sumo.data.schema import SchemaError
from safeil_sumo.data.sources import (
    DEFAULT_DATA_DIR,
    load_source,
)
from safeil_sumo.experiments import maneuver_replay as rp
from safeil_sumo.experiments import outputs
from safeil_sumo.experiments import window_replays as ra
from safeil_sumo.learn.checkpoint import held_out_maneuvers
from safeil_sumo.planners import registry as pol
from safeil_sumo.roads.road import NetworkError
from safeil_sumo.sim.brake_guard import when as brake_guard_when
from safeil_sumo.sim.leaders import ProfileError
from safeil_sumo.sim.loop_types import LATERAL_MODES
from safeil_sumo.sim.sumo_api import SumoError


def build_parser() -> CommandParser:
    p = CommandParser("safeil_sumo.replay",
                      description="Replay a recorded maneuver in SUMO and compare the closed "
                                  "loop with the human.")
    p.add_argument("--source", default="openacc",
                   help="openacc (Vicolungo), zalazone (the ZalaZone handling course), ngsim "
                        "(from --data-dir), recordings by FORMAT:PATH (openacc:DIR, ngsim:FILE, "
                        "highd:DIR, csv:FILE, drive:FILE; docs/your_own_drives.md) or a drive "
                        "file (Parquet/CSV in the drive schema)")
    p.add_argument("--data-dir", type=Path, default=DEFAULT_DATA_DIR,
                   help=f"folder of the real data (default {DEFAULT_DATA_DIR})")
    add_csv_options(p)
    p.add_argument("--maneuver", default="auto",
                   help="a maneuver id (see --list), 'longest', 'auto' (the window most like "
                        "the paper's: 115 km/h, 58.6 m gap), or 'all' / a comma-separated list "
                        "of ids: every window of those maneuvers (see --windows)")
    p.add_argument("--windows", choices=ra.WINDOW_MODES, default="sliding",
                   help="with --maneuver all/list: the paper's 11 s from each maneuver start, "
                        "11 s windows every --stride-s s (default), or whole maneuvers")
    p.add_argument("--stride-s", type=finite_float, default=20.0, metavar="S",
                   help="sliding windows: time between window starts [s] (default 20)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="with --maneuver all/list: worker processes (default 1)")
    add_scheduler_option(p)
    add_task_options(p)
    p.add_argument("--batch", type=positive_int, default=ra.DEFAULT_BATCH,
                   help="with --maneuver all/list: windows run side by side in one SUMO "
                        f"simulation per worker task (default {ra.DEFAULT_BATCH}; 1: one "
                        "simulation per run; the same results)")
    p.add_argument("--held-out-of", type=Path, default=None, metavar="CHECKPOINT_JSON",
                   help="with --maneuver all: only the maneuvers this checkpoint held out of "
                        "training (its metrics.val_maneuvers)")
    p.add_argument("--start-s", type=finite_float, default=0.0, metavar="S",
                   help="start [s] within the maneuver (ignored with auto)")
    p.add_argument("--duration-s", type=finite_float, default=None, metavar="S",
                   help="replay length [s] (default 11, the paper's; 0 = to the maneuver end); "
                        "with --maneuver all/list: the length of paper/sliding windows, or with "
                        "--windows whole a cap on each maneuver from its start (default: whole)")
    p.add_argument("--adapt-first-s", type=finite_float, default=0.0, metavar="S",
                   help="with --windows whole: adapt the planners to each driver on the "
                        "maneuver's first S seconds, then score the rest: one estimate of the "
                        "driver's standstill distance and time gap (learn/style_estimator.py, "
                        "from the population prior) sets a style-conditioned checkpoint's style "
                        "(its setting then follows the speed) and the IDM's s0 and T; the "
                        "extra rows idm_refit5 (the IDM's five parameters refitted), "
                        "safeil_one_setting (one time gap, the estimate's at the speed seen), "
                        "safeil_median (the shrunk median of gap / speed), idm_unadapted and "
                        "safeil_unadapted adapt otherwise; "
                        "maneuvers without 20 s left are skipped. Default 0: no adaptation")
    add_policy_option(p, ["analytic"],
                      "safeil, safeil_paper, bc, analytic, idm, recorded (the human's own "
                      "path: the instrument's error floor), constant_speed (the initial speed "
                      "held on the lane centre, no reaction to the leader: the naive "
                      "baseline), with --adapt-first-s idm_refit5, safeil_one_setting, "
                      "safeil_median, idm_unadapted, safeil_unadapted, and/or checkpoint "
                      "paths")
    p.add_argument("--rate-hz", type=finite_float, default=10.0, metavar="HZ",
                   help="sample rate [Hz] of the maneuver rows compared (default 10, the source)")
    add_plan_rate_option(p)
    add_brake_guard_option(p)
    add_time_gap_option(p, planners="the planners'")
    p.add_argument("--lateral", choices=LATERAL_MODES, default="free",
                   help="planned egos' lateral motion: free (default: the plan tracked by pure "
                        "pursuit on the plant) or lane, an INSTRUMENT MODE for longitudinal-only "
                        "evaluation: after every physics step the ego is put on the rebuilt lane "
                        "centre at the station its own motion reached (the planner, with its "
                        "normal features, the PID and the plant still drive the longitudinal "
                        "part); for roads whose bends a planner cannot hold (ZalaZone, "
                        "docs/human_likeness.md). recorded and constant_speed ignore it")
    p.add_argument("--seed", type=nonnegative_int, default=0)
    p.add_argument("--list", action="store_true", help="list the maneuvers and exit")
    p.add_argument("--animate", action="store_true",
                   help="one maneuver: also write animation_<policy>.mp4 (.gif without an "
                        "ffmpeg) of each policy; see python -m safeil_sumo.animate")
    p.add_argument("--out", type=Path, default=None, help="results folder "
                   "(default runs/replay_<maneuver>)")
    p.rename(stride="--stride-s", start="--start-s", duration="--duration-s", rate="--rate-hz")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    if (args.duration_s is not None and args.duration_s < 0) or args.start_s < 0:
        p.error("--duration-s and --start-s must be >= 0")
    if not 0 < args.rate_hz <= 100 or not 0 < args.plan_rate_hz <= 100:
        p.error("--rate-hz and --plan-rate-hz must be in (0, 100] Hz")
    if args.stride_s <= 0:
        p.error("--stride-s must be > 0 s")
    # an adapted replay scores whole maneuvers after their first S s: the table path, also for one
    args.many = args.maneuver == "all" or "," in args.maneuver or args.adapt_first_s > 0
    if args.many and args.windows != "whole" and args.duration_s == 0:
        p.error(f"--duration-s 0 (to the maneuver's end) needs one maneuver or --windows whole; "
                f"{args.windows} windows need a length > 0 s")
    if args.adapt_first_s < 0 or (args.adapt_first_s and not (
            args.many and args.windows == "whole")):
        p.error("--adapt-first-s needs --windows whole (each whole maneuver is scored after "
                "its first S s), and S >= 0 s")
    if args.time_gap_s is not None and args.adapt_first_s:
        p.error("--time-gap-s and --adapt-first-s exclude each other (adapting sets each "
                "driver's time gap)")
    check_style_options(p, args)
    check_scheduler(p, args)
    check_task_options(p, args)
    if args.scheduler is not None and not args.many:
        p.error("--scheduler needs --maneuver all or a list (one maneuver runs here)")
    if args.held_out_of is not None and args.maneuver != "all":
        p.error("--held-out-of needs --maneuver all")
    if args.animate and args.many:
        p.error("--animate needs one maneuver (not --maneuver all or a list)")
    return args


def replay_config(args: argparse.Namespace) -> rp.ReplayConfig:
    """The replay's settings from the command line: seed, time-gap setting, re-planning rate,
    brake guard and lateral mode on the default loop."""
    config = rp.ReplayConfig(seed=args.seed, time_gap_s=args.time_gap_s,
                             standstill_m=args.standstill_m)
    return replace(config, loop=replace(config.loop, plan_rate_hz=args.plan_rate_hz,
                                        brake_guard=brake_guard_when(args.brake_guard),
                                        lateral=args.lateral))


def many_manifest(args: argparse.Namespace, only: list[str] | None) -> dict:
    """The manifest of a ``--maneuver all`` / list run: its arguments as used."""
    return {"source": args.source, "policies": args.policy, "windows_mode": args.windows,
            "stride_s": args.stride_s,
            # as used: the window length, or the cap on whole maneuvers (None: none)
            "duration_s": rp.PAPER_DURATION_S if args.duration_s is None
            and args.windows != "whole" else args.duration_s or None,
            "maneuvers": only or "all", "adapt_first_s": args.adapt_first_s,
            "lateral": args.lateral, "time_gap_s": args.time_gap_s,
            "standstill_m": args.standstill_m, "batch": args.batch}


def main_many(args: argparse.Namespace, maneuvers: pd.DataFrame,
              config: rp.ReplayConfig) -> int:
    """``--maneuver all`` / a list: every window, in workers, resumable; table + aggregate."""
    if args.maneuver == "all":
        only = None
        if args.held_out_of is not None:
            present = set(maneuvers["maneuver_id"].astype(str))
            only = [m for m in held_out_maneuvers(args.held_out_of) if m in present]
            if not only:
                raise rp.ReplayError(f"none of the maneuvers held out by {args.held_out_of} is "
                                     f"in {args.source}")
    else:
        only = [m.strip() for m in args.maneuver.split(",") if m.strip()]
    for name in args.policy:  # fail fast on a bad policy, before any worker starts
        pol.load_for_replay(name)
    out = args.out or Path("runs") / f"replay_all_{rp.rr.safe_name(Path(args.source).stem)}"
    try:
        table, agg = api.replay(
            maneuvers, args.policy, out, only or "all", args.windows, args.workers,
            args.duration_s, args.stride_s, config, progress=True,
            name=str(args.source), manifest=many_manifest(args, only),
            batch=args.batch, adapt_first_s=args.adapt_first_s, scheduler=args.scheduler,
            retry_failed=args.retry_failed, task_timeout_s=args.task_timeout_s)
    except KeyboardInterrupt:
        print(f"\ninterrupted: finished windows are saved in {out / 'tasks'}; rerun the same "
              "command to resume", file=sys.stderr)
        return 130
    except OSError as exc:  # e.g. the Dask scheduler cannot be reached
        print(f"error: {exc}", file=sys.stderr)
        return 2
    failed = table.drop_duplicates(["maneuver_id", "start_s"])
    failed = failed[failed["status"] != "ok"]
    n_windows = len(table.drop_duplicates(["maneuver_id", "start_s"]))
    print(f"{args.source}: {n_windows} windows of {table['maneuver_id'].nunique()} "
          f"maneuvers ({args.windows}), {len(failed)} failed")
    if len(agg):
        print(agg.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    for _, r in failed.head(10).iterrows():
        print(f"window {r['maneuver_id']} @ {r['start_s']:g} s failed: {r['error']}",
              file=sys.stderr)
    print(f"results: {out}")
    return 1 if len(failed) else 0


@interruptible
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        drive = load_source(args.source, args.data_dir, args.map, args.speed_unit)
        maneuvers, _ = process_drive(drive, PipelineConfig(rate_hz=args.rate_hz))
        if args.list:
            print(rp.maneuver_table(maneuvers).to_string(float_format=lambda v: f"{v:.2f}"))
            return 0
        if len(maneuvers) == 0 or "maneuver_id" not in maneuvers:
            raise rp.ReplayError(f"{args.source}: no car-following maneuver to replay")
        config = replay_config(args)  # its settings checked before any SUMO starts
        if args.many:
            return main_many(args, maneuvers, config)
        duration = rp.PAPER_DURATION_S if args.duration_s is None else args.duration_s or None
        mid, start, rows = rp.select_maneuver(maneuvers, args.maneuver, args.start_s, duration)
        policies = {}
        for name in args.policy:
            policy = pol.load_for_replay(name)
            label = name if name in ("analytic", *pol.REPLAY_ONLY, *pol.SHIPPED) else policy.name
            policies[label if label not in policies else name] = policy
    except (SchemaError, rp.ReplayError, pol.PolicyError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = args.out or Path("runs") / f"replay_{rp.rr.safe_name(mid)}"
    policies = ra.with_setting(policies, config.time_gap_s, config.standstill_m)
    try:
        with outputs.AtomicDir(out) as tmp:
            result = rp.replay_maneuver(rows, policies, tmp, config, maneuver_id=mid)
            rp.write_replay(result, tmp, {"source": args.source, "maneuver_start_s": start,
                                          "policies": args.policy, "rate_hz": args.rate_hz,
                                          "lateral": args.lateral,
                                          "time_gap_s": args.time_gap_s,
                                          "standstill_m": args.standstill_m})
    except (rp.ReplayError, ProfileError, NetworkError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except SumoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    info = result.info
    print(f"{args.source}: maneuver {mid} from {start:g} s, {info['duration_s']:.1f} s at "
          f"{info['mean_speed_mps']:.1f} m/s ({3.6 * info['mean_speed_mps']:.0f} km/h), mean gap "
          f"{info['mean_gap_m']:.1f} m, lane {info['lane_width_m']:.2f} m, recorded-leader drift "
          f"<= {info['max_abs_leader_drift_m']:.2f} m")
    print(rp.format_metrics(result.metrics))
    failed = result.metrics[result.metrics["end_reason"] == "error"]
    for _, row in failed.iterrows():
        print(f"policy {row['policy']} failed: {row['error']}", file=sys.stderr)
    if args.animate:  # from the written results folder, as the animate CLI does
        from safeil_sumo.experiments import animation

        for name in result.rollouts:
            try:
                print(f"animation: {animation.animate(out, policy=name)}")
            except animation.AnimateError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 1
    print(f"results: {out}")
    return 1 if len(failed) else 0


if __name__ == "__main__":
    sys.exit(main())
