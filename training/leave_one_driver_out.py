"""Leave-one-driver-out: train the shipped recipe without a driver, replay that driver whole.

    python training/leave_one_driver_out.py [--folds 4] [--workers 2] [--out results/lodo]

Generalisation across drivers (issue 20): the shipped ``safeil`` held out 20 % of the maneuvers,
but the drivers of those maneuvers also drove training maneuvers. Here each fold leaves whole
drivers out of everything, trains ``safeil`` with the shipped two-stage recipe
(``training/train_shipped_models.py``: the open-loop stage with the chosen candidate's options,
the closed-loop fine-tune of the longitudinal tower with the style input, the lateral refit) and calibrates the IDM on the same data
(``training/fit_idm.py --exclude-from``), then replays every maneuver of the left-out drivers
whole, in SUMO, beside the ``constant_speed`` baseline; the OpenACC drivers also adapted
(``replay --adapt-first-s 60``: the planner's time-gap setting estimated and the IDM refitted on
each maneuver's first 60 s, which the score leaves out).

Drivers (:func:`safeil_sumo.data.sources.driver_of`): OpenACC Vicolungo has 4 human followers, the
platoon positions ``f2``-``f5`` of one campaign day (the same car and driver in both parts):
fold k leaves out position ``f{k+2}``. NGSIM I-80 drivers are the follower vehicles (one vehicle
follows several leaders in turn), shuffled with seed 0 and dealt into the same number of folds;
fold k leaves out its share of each source at once. The synthetic drivers stay in every fold.
The style input is left at the fold's default (the training drivers' median time gap): the
left-out driver's preference is unknown to the planner, as it is to the IDM.

Writes ``<out>/windows.csv`` (one row per fold, policy and maneuver), ``<out>/per_driver.csv``,
``<out>/summary.csv`` and ``<out>/summary.md``; the fold models go to ``data/lodo/`` (not
committed). Each fold costs one open-loop training (≤ 10 min on one core), one closed-loop
fine-tune (≈ 22 min), one lateral refit (≈ 3 min), all in-process
(:func:`safeil_sumo.learn.trainer.train_checkpoint`, :func:`safeil_sumo.learn.finetune.finetune`,
:func:`safeil_sumo.learn.lateral_refit.refit_lateral`), and one IDM calibration; folds run ``--workers`` at
a time, each in a worker process of its own, resumed where their files exist.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "training"))
import train_shipped_models as shipped  # the shipped recipe, one source of truth

from safeil_sumo.data.sources import driver_of
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.torch_required import training_imports
from safeil_sumo.planners.registry import fingerprint

with training_imports():  # without torch: one line that says what to install, no traceback
    import torch

    from safeil_sumo.learn.finetune import finetune
    from safeil_sumo.learn.lateral_refit import refit_lateral
    from safeil_sumo.learn.trainer import train_checkpoint

SOURCES = ("openacc", "ngsim")
WORK = REPO / "data" / "lodo"
ADAPT_S = 60.0  # [s] the adapted replays' first seconds (style and IDM fitted, then left out)
LOOKS_S = (2.0, 10.0, 30.0)  # [s] shorter looks, replayed too (per-driver tables)
# the fold's planners are replayed by path: their table names
POLICY_LABELS = {"safeil.safetensors": "safeil (fold)", "idm.json": "idm (fold)"}


def tuples_path(source: str) -> Path:
    return shipped.DATA_DIR / f"{source}_tuples.parquet"


def fold_drivers(n_folds: int, seed: int = 0) -> list[set[str]]:
    """The drivers each fold leaves out: OpenACC position k+2 in fold k, NGSIM vehicles dealt
    round-robin after a seeded shuffle."""
    ids = {s: np.unique(pd.read_parquet(tuples_path(s), columns=["maneuver_id"])["maneuver_id"])
           for s in SOURCES}
    openacc = sorted({driver_of("openacc", m) for m in ids["openacc"]})
    if len(openacc) != n_folds:
        raise SystemExit(f"--folds must equal the {len(openacc)} OpenACC drivers {openacc}")
    ngsim = sorted({driver_of("ngsim", m) for m in ids["ngsim"]})
    order = np.random.default_rng(seed).permutation(len(ngsim))
    return [{openacc[k]} | {ngsim[i] for i in order[k::n_folds]} for k in range(n_folds)]


def held_out_maneuvers(drivers: set[str]) -> dict[str, list[str]]:
    """Per source, the maneuver ids of ``drivers``."""
    out = {}
    for s in SOURCES:
        ids = np.unique(pd.read_parquet(tuples_path(s), columns=["maneuver_id"])["maneuver_id"])
        out[s] = sorted(m for m in ids if driver_of(s, m) in drivers)
    return out


def _note(log: Path, text: str) -> None:
    with log.open("a") as f:
        f.write(text + "\n")


def _run(cmd: list[str], log: Path) -> None:
    with log.open("a") as f:
        f.write(f"$ {' '.join(cmd)}\n")
        f.flush()
        if subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, check=False).returncode:
            raise SystemExit(f"failed: {' '.join(cmd)} (see {log})")


def train_fold(k: int, drivers: set[str]) -> Path:
    """Train and calibrate fold ``k`` without ``drivers``; its folder (skips finished steps)."""
    fold = WORK / f"fold{k}"
    fold.mkdir(parents=True, exist_ok=True)
    log = fold / "log.txt"
    held = held_out_maneuvers(drivers)
    (fold / "held_out.json").write_text(json.dumps(sorted(m for ids in held.values() for m in ids))
                                         + "\n")
    (fold / "drivers.json").write_text(json.dumps(sorted(drivers)) + "\n")
    real = []
    for s in SOURCES:
        t = Tuples.load(tuples_path(s))
        path = fold / f"{s}_tuples.parquet"
        t.subset(~np.isin(t.maneuver_id, held[s])).save(path)
        real.append(path)
    chosen = json.loads((shipped.MODELS / "selection.json").read_text())["chosen"]
    if not (fold / "safeil_openloop.safetensors").is_file():
        config = shipped.SAFEIL_CANDIDATES[chosen]
        _note(log, f"train_checkpoint({config}) -> {fold / 'safeil_openloop'}")
        trained = train_checkpoint(config, [shipped.SYNTHETIC, *real], fold / "safeil_openloop",
                                   "safeil")
        _note(log, "\n".join(trained.notes))
    if not (fold / "safeil_cl.safetensors").is_file():
        _note(log, f"finetune({shipped.CLOSED_LOOP}) -> {fold / 'safeil_cl'}")
        tuned = finetune(shipped.CLOSED_LOOP, fold / "safeil_openloop.safetensors", real,
                         fold / "safeil_cl")
        _note(log, "\n".join(tuned.notes))
    if not (fold / "safeil.safetensors").is_file():
        _note(log, f"refit_lateral({shipped.LATERAL}) -> {fold / 'safeil'}")
        refit_lateral(shipped.LATERAL, fold / "safeil_cl.safetensors",
                      fold / "safeil_openloop.safetensors", [shipped.SYNTHETIC, *real],
                      fold / "safeil")
    if not (fold / "idm.json").is_file():
        _run([sys.executable, str(REPO / "training" / "fit_idm.py"), "--exclude-from",
              str(fold / "held_out.json"), "--out", str(fold / "idm.json")], log)
    return fold


def run_fold(k: int, drivers: set[str], t0: float) -> pd.DataFrame:
    """Train fold ``k`` without ``drivers``, then replay them: its windows table. Runs in a
    worker process of its own (one torch thread)."""
    fold = train_fold(k, drivers)
    print(f"fold {k}: trained ({time.time() - t0:.0f} s)", flush=True)
    return replay_fold(k, fold, workers=1)


def planner_fingerprints(fold: Path) -> dict[str, str]:
    """The fold's replayed planners' fingerprints (:func:`planner_registry.fingerprint`, what
    the replay's own task files are keyed by): a cached replay is reused only when it was made
    with these very planners (a retrained fold replays again)."""
    return {name: fingerprint(str(fold / name)) for name in ("safeil.safetensors", "idm.json")}


def replay_fold(k: int, fold: Path, workers: int) -> pd.DataFrame:
    """Replay fold ``k``'s left-out maneuvers whole with its planners; their windows table."""
    held = held_out_maneuvers(set(json.loads((fold / "drivers.json").read_text())))
    tables = []
    runs = [(s, "", ["constant_speed"]) for s in SOURCES if held[s]]
    # adapted to the driver on each maneuver's first ADAPT_S (NGSIM's 30-74 s leave too little),
    # and on the shorter LOOKS_S
    runs += [("openacc", "adapted", [])] if held["openacc"] else []
    runs += [("openacc", f"adapted{look:g}", []) for look in LOOKS_S if held["openacc"]]
    made_from = planner_fingerprints(fold)
    for s, mode, extra_policies in runs:
        out = fold / f"replay_{s}{'_' + mode if mode else ''}"
        stamp = out / "made_from.json"  # the planners a cached replay was made with
        if not ((out / "windows.csv").is_file() and stamp.is_file()
                and json.loads(stamp.read_text()) == made_from):
            look = ADAPT_S if mode == "adapted" else float(mode[len("adapted"):] or 0)
            adapt = ["--adapt-first-s", str(look)] if look else []
            _run([sys.executable, "-m", "safeil_sumo.replay", "--source", s, "--maneuver",
                  ",".join(held[s]), "--windows", "whole", "--workers", str(workers), *adapt,
                  "--policy", str(fold / "safeil.safetensors"), str(fold / "idm.json"),
                  *extra_policies, "--out", str(out)], fold / "log.txt")
            stamp.write_text(json.dumps(made_from, indent=1) + "\n")
        t = pd.read_csv(out / "windows.csv")
        label = f"adapted {mode[len('adapted'):]} s" if mode not in ("", "adapted") else mode
        tables.append(t.assign(fold=k, source=s + (f" ({label})" if label else ""),
                               driver=[driver_of(s, m) for m in t["maneuver_id"]]))
    return pd.concat(tables, ignore_index=True)


def summarise(df: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per source and policy: maneuvers, gap RMSE median / mean / worst [m], spacing RMSPE
    median, time-gap error median [s], flags, collisions, runs ended early; and the same per
    driver (mean gap RMSE over the driver's maneuvers)."""
    ok = df[df["status"] == "ok"].copy()
    ok["policy"] = ok["policy"].map(lambda p: POLICY_LABELS.get(Path(p).name, p))
    rows = []
    for (s, p), g in ok.groupby(["source", "policy"], sort=False):
        gap = g["rmse_gap"].to_numpy(float)
        rows.append({
            "source": s, "policy": p, "maneuvers": len(g),
            "drivers": g["driver"].nunique(),
            "gap_rmse_median_m": float(np.nanmedian(gap)),
            "gap_rmse_mean_m": float(np.nanmean(gap)),
            "gap_rmse_max_m": float(np.nanmax(gap)),
            "spacing_rmspe_median": float(np.nanmedian(g["rmspe_gap"])),
            "time_gap_error_median_s": float(np.nanmedian(g["bias_headway"])),
            "flags": int((g["flag"].fillna("") != "").sum()),
            "flags_beyond_human": int(((g["flag"].fillna("") != "")
                                       & (g["human_flag"].fillna("") == "")).sum()),
            "collisions": int(((g["flag"] == "collision")
                               | (g["end_reason"] == "collision")).sum()),
            "ended_early": int((g["coverage"] < 1.0).sum()),
        })
    per_driver = (ok.groupby(["source", "driver", "policy"], sort=False)["rmse_gap"]
                  .agg(["count", "mean", "max"]).reset_index()
                  .rename(columns={"count": "maneuvers", "mean": "gap_rmse_mean_m",
                                   "max": "gap_rmse_max_m"}))
    return pd.DataFrame(rows), per_driver


def markdown(summary: pd.DataFrame, per_driver: pd.DataFrame) -> str:
    header = ("| source | policy | maneuvers (drivers) | gap RMSE median / mean / worst [m] | "
              "spacing RMSPE median | time-gap error median [s] | flags (beyond human) | "
              "collisions | ended early |")
    lines = [header, "|---|---|---|---|---|---|---|---|---|"]
    for r in summary.itertuples():
        lines.append(f"| {r.source} | {r.policy} | {r.maneuvers} ({r.drivers}) | "
                     f"{r.gap_rmse_median_m:.2f} / {r.gap_rmse_mean_m:.2f} / "
                     f"{r.gap_rmse_max_m:.1f} | {r.spacing_rmspe_median:.3f} | "
                     f"{r.time_gap_error_median_s:+.2f} | {r.flags} ({r.flags_beyond_human}) | "
                     f"{r.collisions} | {r.ended_early} |")
    wide = per_driver.pivot_table(index=["source", "driver"], columns="policy",
                                  values="gap_rmse_mean_m").reset_index()
    a, b = POLICY_LABELS["safeil.safetensors"], POLICY_LABELS["idm.json"]
    if a in wide and b in wide:
        wide = wide.dropna(subset=[a, b])  # drivers both planners were replayed for
        better = wide[a] <= wide[b]
        for s, g in wide.groupby("source"):
            lines.append(f"\n{s}: `safeil` (fold) at or below the fold IDM's mean gap RMSE for "
                         f"{int(better[g.index].sum())} of {len(g)} left-out drivers.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folds", type=int, default=4, help="= the number of OpenACC drivers")
    ap.add_argument("--workers", type=int, default=2, help="folds trained at once")
    ap.add_argument("--out", type=Path, default=REPO / "results" / "lodo")
    args = ap.parse_args(argv)
    if not all(tuples_path(s).is_file() for s in SOURCES):
        subprocess.run([sys.executable, str(REPO / "training" / "build_real_datasets.py"),
                        "--out", str(shipped.DATA_DIR)], check=True)
    if not shipped.SYNTHETIC.is_file():
        subprocess.run([sys.executable, str(REPO / "training" / "build_synthetic_dataset.py")],
                       check=True)
    folds = fold_drivers(args.folds)
    t0 = time.time()
    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn"),
                             initializer=torch.set_num_threads, initargs=(1,)) as pool:
        runs = [pool.submit(run_fold, k, folds[k], t0) for k in range(args.folds)]
        df = pd.concat([r.result() for r in runs], ignore_index=True)
    summary, per_driver = summarise(df)
    args.out.mkdir(parents=True, exist_ok=True)
    df.to_csv(args.out / "windows.csv", index=False)
    per_driver.to_csv(args.out / "per_driver.csv", index=False)
    summary.to_csv(args.out / "summary.csv", index=False)
    (args.out / "summary.md").write_text(markdown(summary, per_driver))
    print(markdown(summary, per_driver))
    print(f"{args.folds} folds in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
