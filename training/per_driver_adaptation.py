"""Per-driver adaptation: each driver's whole-maneuver gap RMSE, unadapted and adapted after
S s of looking, beside the equally adapted IDM and the best setting in hindsight (issue 42's
per-driver instrument).

    python training/per_driver_adaptation.py --looks 2=runs/zz_2 10=runs/zz_10 ... \
        [--bound data/lodo/adaptation_bound_zalazone] [--name zalazone] [--out results/per_driver]

Each ``S=DIR`` is a ``replay --windows whole --adapt-first-s S`` folder (its ``windows.csv``;
a glob for several, e.g. one per fold: ``60='data/lodo/fold*/replay_openacc_adapted'``): every
maneuver scored after its first S s; ``0=DIR``: unadapted replays of whole maneuvers. Its rows, by policy label: ``safeil`` (adapted by
the (s0, T) estimator: the line), ``safeil_unadapted`` (its default setting, the same seconds),
``idm`` (s0 and T from the same estimate), ``idm_unadapted``; others as they are named (a
fold's checkpoint path is read as its table label, ``leave_one_driver_out.POLICY_LABELS``).
``--bound DIR``: ``training/adaptation_bound.py``'s ``settings.csv`` (each maneuver replayed
after ``--bound-look-s`` at every setting of a grid): the best setting per maneuver in hindsight,
on that look's seconds.

Writes ``<out>/adaptation_<name>.csv`` (driver, look, planner: maneuvers and mean gap RMSE [m])
and ``<out>/adaptation_<name>.md`` (a driver per row, the looks as columns), and prints the
markdown. No SUMO: tables of earlier replays only.
"""

from __future__ import annotations

import argparse
import glob
import sys
from functools import partial
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "training"))

from safeil_sumo.data.sources import driver_of
from safeil_sumo.experiments.window_replays import driver_id

HINDSIGHT = "hindsight best setting"
HINDSIGHT_LINE = "hindsight best (T, s0)"  # of a grid over both numbers
# the columns of the markdown, in order (a label missing from the replays is left out)
SHOWN = ("safeil", "safeil_unadapted", "idm", HINDSIGHT, HINDSIGHT_LINE)


def label_of(policy: str) -> str:
    """A replay's policy column as a table label: a fold checkpoint's path by its file name
    (``safeil.safetensors`` -> ``safeil``, ``idm.json`` -> ``idm``), a name as it is."""
    name = Path(policy).name
    return {"safeil.safetensors": "safeil", "idm.json": "idm"}.get(name, policy)


def look_rows(look_s: float, folders: list[Path], driver=driver_id) -> pd.DataFrame:
    """One look's scored maneuvers (of the ``windows.csv`` of every folder of ``folders``, e.g.
    one per fold): ``maneuver_id, driver, look_s, planner, gap_rmse_m`` (windows that failed,
    and maneuvers whose replay broke for every planner (gap RMSE above 1 km: an instrument
    failure of that window), left out). ``driver``: a maneuver id's driver."""
    if not folders:
        raise SystemExit(f"no replay folder for the look of {look_s:g} s")
    w = pd.concat([pd.read_csv(f / "windows.csv") for f in folders], ignore_index=True)
    w = w[w["status"] == "ok"]
    broken = w.groupby("maneuver_id")["rmse_gap"].min() > 1e3
    w = w[~w["maneuver_id"].isin(broken[broken].index)]
    return pd.DataFrame({"maneuver_id": w["maneuver_id"].astype(str),
                         "driver": [driver(m) for m in w["maneuver_id"].astype(str)],
                         "look_s": float(look_s), "planner": w["policy"].map(label_of),
                         "gap_rmse_m": w["rmse_gap"].to_numpy(float)})


def hindsight_rows(bound: Path, look_s: float, driver=driver_id) -> pd.DataFrame:
    """The best setting per maneuver in hindsight (``settings.csv`` of adaptation_bound.py)
    as rows of :func:`look_rows`' shape: of the one-number settings (standstill 0), and, if
    the grid tried other standstill distances, of both numbers (:data:`HINDSIGHT_LINE`)."""
    s = pd.read_csv(bound / "settings.csv")
    if "standstill_m" not in s:
        s["standstill_m"] = 0.0
    kinds = [(HINDSIGHT, s[s["standstill_m"] == 0.0])]
    if s["standstill_m"].nunique() > 1:
        kinds.append((HINDSIGHT_LINE, s))
    parts = []
    for planner, rows in kinds:
        best = rows.groupby("maneuver_id")["gap_rmse_m"].min()
        parts.append(pd.DataFrame({"maneuver_id": best.index.astype(str),
                                   "driver": [driver(m) for m in best.index.astype(str)],
                                   "look_s": float(look_s), "planner": planner,
                                   "gap_rmse_m": best.to_numpy(float)}))
    return pd.concat(parts, ignore_index=True)


def per_driver(rows: pd.DataFrame) -> pd.DataFrame:
    """Per (driver, look, planner): maneuvers and mean gap RMSE [m]."""
    return (rows.groupby(["driver", "look_s", "planner"])["gap_rmse_m"]
            .agg(maneuvers="count", gap_rmse_mean_m="mean").reset_index())


def markdown(table: pd.DataFrame, name: str) -> str:
    """A driver per row, per look the planners' mean gap RMSE [m], and a last row of means
    over the drivers."""
    looks = sorted(table["look_s"].unique())
    shown = [p for p in SHOWN if p in set(table["planner"])]
    wide = table.pivot_table(index="driver", columns=["look_s", "planner"],
                             values="gap_rmse_mean_m")
    heads = [f"{p} after {s:g} s" for s in looks for p in shown
             if (s, p) in wide.columns]
    cols = [(s, p) for s in looks for p in shown if (s, p) in wide.columns]
    lines = [f"# Per-driver adaptation: {name}", "",
             ("Mean whole-maneuver gap RMSE [m] per driver, scored after the first S s "
              "(`training/per_driver_adaptation.py`)."), "",
             "| driver | " + " | ".join(heads) + " |",
             "|---|" + "---:|" * len(cols)]
    for driver, r in wide.iterrows():
        lines.append(f"| {driver} | " + " | ".join(
            "" if pd.isna(r[c]) else f"{r[c]:.2f}" for c in cols) + " |")
    means = wide[cols].mean()
    lines.append("| **mean over drivers** | " + " | ".join(f"**{means[c]:.2f}**"
                                                           for c in cols) + " |")
    for s in looks:
        if (s, "safeil") in wide.columns and (s, "safeil_unadapted") in wide.columns:
            d = wide[(s, "safeil")] - wide[(s, "safeil_unadapted")]
            lines.append(f"\nAfter {s:g} s: adapted `safeil` at or below its unadapted default "
                         f"for {int((d <= 0).sum())} of {int(d.notna().sum())} drivers.")
        if (s, "safeil") in wide.columns and (s, "idm") in wide.columns:
            d = wide[(s, "safeil")] - wide[(s, "idm")]
            which = "adapted `safeil` at or below the equally adapted IDM" if s else \
                "unadapted `safeil` at or below the IDM"
            lines.append(f"After {s:g} s: {which} for {int((d <= 0).sum())} of "
                         f"{int(d.notna().sum())} drivers.")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--looks", nargs="+", required=True, metavar="S=DIR",
                    help="replay folders adapted on their first S s")
    ap.add_argument("--bound", type=Path, default=None,
                    help="adaptation_bound.py's output folder (settings.csv)")
    ap.add_argument("--bound-look-s", type=float, default=60.0,
                    help="the seconds --bound's replays left out (default 60)")
    ap.add_argument("--name", default="zalazone")
    ap.add_argument("--source", default=None,
                    help="the drivers as data.sources.driver_of names them for this source "
                         "(openacc: the platoon position, zalazone: the car); default: the "
                         "recording (window_replays.driver_id)")
    ap.add_argument("--out", type=Path, default=REPO / "results" / "per_driver")
    args = ap.parse_args(argv)
    driver = driver_id if args.source is None else partial(driver_of, args.source)
    parts = []
    for item in args.looks:
        look, _, pattern = item.partition("=")
        folders = [Path(f) for f in sorted(glob.glob(pattern))
                   if (Path(f) / "windows.csv").is_file()]
        parts.append(look_rows(float(look), folders, driver))
    if args.bound is not None:
        parts.append(hindsight_rows(args.bound, args.bound_look_s, driver))
    table = per_driver(pd.concat(parts, ignore_index=True))
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / f"adaptation_{args.name}.csv", index=False)
    text = markdown(table, args.name)
    (args.out / f"adaptation_{args.name}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
