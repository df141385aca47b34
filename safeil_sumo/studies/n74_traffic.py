"""The ``n74`` section of ``python -m safeil_sumo.results``: the planners' seeded drives on the
n74 road among SUMO's traffic, and a population of drivers at time-gap settings drawn from the
real training maneuvers: flag rates per 100 km with exact Poisson intervals, where the flags
happened, and time gaps against the recorded synthetic humans of the same road. It writes
``n74_drives.csv``, ``n74_rates.csv``, ``n74_flags.csv``, ``n74_flag_map.png``,
``n74_time_gap.csv`` and ``n74_time_gap.png`` and its part of ``results/studies.md``
(:func:`n74_readme`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from safeil_sumo.studies.shared import COLORS, LABELS, REPO, SHIPPED_SAFEIL, md_table, save_csv

SYNTHETIC_DRIVES = REPO / "data" / "synthetic" / "drives.parquet"  # the recorded n74 humans
QUICK_STRETCH_KM = (4.0, 5.0)  # the n74 section's --quick drive (one per planner)
# the real tuples the shipped safeil's style input was fine-tuned on (train_shipped_models.py):
# the n74 driver population draws its settings from their training maneuvers' time gaps
TRAINING_TUPLES = (REPO / "data" / "openacc_tuples.parquet", REPO / "data" / "ngsim_tuples.parquet")


def n74(out: Path, work: Path, workers: int, seed: int, quick: bool = False) -> dict:
    """The planners' seeded drives on the n74 road among SUMO's traffic: flag rates per 100 km
    with exact Poisson intervals, time gaps against the synthetic humans of the same road, and a
    map of where the flags happened (:mod:`safeil_sumo.experiments.n74_drives`)."""
    from safeil_sumo.experiments import n74_drives as nd
    from safeil_sumo.experiments.sweep_executor import run_sweep
    from safeil_sumo.learn.style import SETTING_RANGE_S

    # --quick: 1 km of each planner (a smoke test of the section)
    stretches, per = ((QUICK_STRETCH_KM,), 1) if quick else (nd.STRETCHES_KM,
                                                              nd.SEEDS_PER_STRETCH)
    tasks = nd.drive_tasks(nd.PLANNERS, seed, stretches, per)
    # a population of drivers: one setting per drive, from the real training maneuvers
    pop_per = 1 if quick else nd.POPULATION_SEEDS_PER_STRETCH
    try:
        estimates = nd.training_settings(SHIPPED_SAFEIL.with_suffix(".safetensors"),
                                         TRAINING_TUPLES)
    except (OSError, ValueError) as exc:
        print(f"[n74] no driver population ({exc}); build the real tuples with python "
              "training/build_real_datasets.py")
        estimates = {}
    population = nd.population_tasks(estimates, nd.POPULATION_PLANNERS, seed, stretches,
                                     pop_per, per) if estimates else []
    tasks += population
    names = [*nd.PLANNERS, *dict.fromkeys(nd.row_name(t.planner.policy, t.planner.time_gap_s)
                                          for t in population)]
    print(f"[n74] {len(tasks)} drives", flush=True)
    df = run_sweep(tasks, work / "n74", workers=workers, progress=True, task_fn=nd.drive_task)
    failed = df[df["status"] != "ok"]
    if len(failed):
        print(f"[n74] {len(failed)} drive(s) failed, e.g. {failed['error'].iloc[0]}")
    ok = df[df["status"] == "ok"].reset_index(drop=True)
    if "time_gap_s" not in ok:  # no drive with a setting
        ok["time_gap_s"] = math.nan
    ok["policy"] = [nd.row_name(p, t) for p, t in zip(ok["policy"], ok["time_gap_s"], strict=True)]
    cols = ["policy", "time_gap_s", "index", "from_km", "to_km", "km_driven", "end_reason",
            "ttc_events",
            "lane_departure_events", "collision_events", "min_ttc_s", "min_gap_m",
            "max_abs_lateral_offset_m", "leaders_met", "cut_ins_met"]
    save_csv(ok[cols], out / "n74_drives.csv")
    rates = nd.rates(ok)
    save_csv(rates, out / "n74_rates.csv")

    events = _n74_flag_map(out, ok, rates, names, stretches)
    table = _n74_time_gaps(out, ok, names, seed)
    design = {"planners": list(nd.PLANNERS), "stretches_km": [list(s) for s in stretches],
              "seeds_per_stretch": per, "traffic": nd.TRAFFIC,
              "master_seed": seed, "drives": len(tasks), "failed": len(failed),
              "time_gap_rate_hz": nd.TIME_GAP_RATE_HZ, "follow_max_gap_m": nd.FOLLOW_MAX_GAP_M,
              "follow_min_speed_mps": nd.FOLLOW_MIN_SPEED_MPS,
              # one core's time of every drive (stable across resumes, unlike the wall time)
              "drives_core_s": round(float(ok["task_wall_time_s"].sum()), 1)}
    if population:
        # every population drive has its setting (nd.population_tasks)
        drawn = np.array(sorted({t.scenario.index: t.planner.time_gap_s for t in population
                                 if t.planner.time_gap_s is not None}.values()))
        est = np.array(list(estimates.values()))
        design["population"] = {
            "planners": list(nd.POPULATION_PLANNERS), "seeds_per_stretch": pop_per,
            "drives_per_planner": len(drawn), "training_maneuvers": len(est),
            "estimates_median_s": float(np.median(est)),
            "estimates_p5_p95_s": np.quantile(est, [0.05, 0.95]).tolist(),
            "checkpoint_default_s": json.loads(SHIPPED_SAFEIL.read_text()).get(
                "style_default", {}).get("time_gap_s"),
            "setting_range_s": list(SETTING_RANGE_S), "settings_min_median_max_s": [
                float(drawn.min()), float(np.median(drawn)), float(drawn.max())]}
    return {"design": design, "rates": rates.to_dict(orient="records"),
            "time_gap": table.to_dict(orient="records"), "flags": len(events)}


def _n74_flag_map(out: Path, ok: pd.DataFrame, rates: pd.DataFrame, names: list[str],
                  stretches: tuple[tuple[float, float], ...]) -> pd.DataFrame:
    """``n74_flags.csv`` and ``n74_flag_map.png``: where each row's flags started; the events."""
    from safeil_sumo import api
    from safeil_sumo.experiments.plots import draw_flag_map

    # flag locations, with the kilometre post of each (linear along the stretch's ego lane)
    starts = {(a, b): api.road("n74", [], a, b).path_start_s for a, b in stretches}
    events = pd.DataFrame(
        [dict(e, policy=r["policy"], index=r["index"],
              km_post=r["from_km"] + (e["s_m"] - starts[(r["from_km"], r["to_km"])]) / 1000.0)
         for _, r in ok.iterrows() for e in r["flag_events"]],
        columns=["policy", "index", "kind", "t_s", "km_post", "x", "y", "s_m"])
    save_csv(events.drop(columns="s_m"), out / "n74_flags.csv")
    route = api.road("n74").lanes[api.road("n74").ego_lane].centre.points
    ncols = min(len(names), 2)
    nrows = math.ceil(len(names) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6 * ncols, 4.5 * nrows), squeeze=False)
    for ax, p in zip(axes.flat, names, strict=False):
        r = rates[rates["policy"] == p].iloc[0]
        draw_flag_map(ax, route, events[events["policy"] == p],
                      f"{LABELS[p]}: {r['km']:.0f} km in {r['drives']} drives")
    for ax in axes.flat[len(names):]:
        ax.axis("off")
    fig.suptitle("n74, direction A, right lane, default traffic: where the flags started "
                 "(ticks: km along the lane)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(out / "n74_flag_map.png", dpi=110)
    plt.close(fig)

    return events


def _n74_time_gaps(out: Path, ok: pd.DataFrame, names: list[str], seed: int) -> pd.DataFrame:
    """``n74_time_gap.csv`` and ``n74_time_gap.png``: each row's time gaps against the synthetic
    humans'; the table."""
    from safeil_sumo.experiments import n74_drives as nd

    # time gaps: each drive / recording is one group (its samples are correlated)
    groups = {p: [np.asarray(g, float) for g in ok.loc[ok["policy"] == p, "time_gaps_s"]]
              for p in names}
    try:
        humans = nd.human_time_gaps(pd.read_parquet(
            SYNTHETIC_DRIVES, columns=["recording_id", "lead_x", "v_x", "lane_index"]))
    except (OSError, ValueError) as exc:  # no dataset built: the planners' gaps alone
        print(f"[n74] no synthetic drives to compare the time gaps with ({exc}); build them "
              "with python training/build_synthetic_dataset.py")
        humans = pd.DataFrame({"recording_id": [], "lane_index": [], "time_gap_s": []})
    human_groups = [g["time_gap_s"].to_numpy() for _, g in humans.groupby("recording_id")]
    table = nd.compare_time_gaps(groups, human_groups, seed)
    right = humans[humans["lane_index"] == 0]
    extra = nd.compare_time_gaps(
        {}, [g["time_gap_s"].to_numpy() for _, g in right.groupby("recording_id")], seed)
    table = pd.concat([table, extra.assign(who=f"{nd.HUMANS} (right lane only)")],
                      ignore_index=True)
    save_csv(table, out / "n74_time_gap.csv")
    fig, (ax_e, ax_h) = plt.subplots(1, 2, figsize=(12, 4.5))
    bins = np.linspace(0.0, 4.0, 81)
    series = [(LABELS[p], np.concatenate(g) if g else np.zeros(0), COLORS[p])
              for p, g in groups.items()]
    series.append((f"{nd.HUMANS} ({len(human_groups)} drives)",
                   humans["time_gap_s"].to_numpy(), "black"))
    for label, values, color in series:
        v = np.sort(values)
        ax_e.step(v, np.arange(1, len(v) + 1) / max(len(v), 1), where="post", color=color,
                  label=label, lw=2.0 if color == "black" else 1.3)
        if len(values):
            ax_h.hist(np.clip(values, 0, 4.0), bins=bins, density=True, histtype="step",
                      color=color, lw=2.0 if color == "black" else 1.3, label=label)
    ax_e.set_xlim(0, 4.0)
    ax_e.set_xlabel("time gap = bumper gap / ego speed [s] (while following)")
    ax_e.set_ylabel("ECDF")
    ax_e.legend(fontsize=8)
    ax_h.set_xlabel("time gap [s] (clipped at 4 s)")
    ax_h.set_ylabel("density [1/s]")
    ax_e.set_title("n74 drives vs the recorded synthetic humans, same road and traffic",
                   fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "n74_time_gap.png", dpi=110)
    plt.close(fig)
    return table


def n74_readme(n74: dict) -> list[str]:
    d = n74["design"]
    stretches = ", ".join(f"{a:g}-{b:g}" for a, b in d["stretches_km"])
    rows = []
    for r in n74["rates"]:
        row = dict(r, planner=LABELS.get(r["policy"], r["policy"]), done=(
            f"{r['completed_drives']}/{r['drives']}"))
        for kind in ("ttc", "lane_departure", "collision"):
            row[kind] = (f"{r[f'{kind}_per_100km']:.3g} [{r[f'{kind}_lo']:.3g}, "
                         f"{r[f'{kind}_hi']:.3g}] ({r[f'{kind}_events']})")
        rows.append(row)
    tg = []
    for r in n74["time_gap"]:
        row = dict(r, planner=LABELS.get(r["who"], r["who"]))
        if isinstance(r.get("median_diff_s"), float) and not math.isnan(r["median_diff_s"]):
            row["diff"] = (f"{r['median_diff_s']:+.2f} [{r['median_diff_lo_s']:+.2f}, "
                           f"{r['median_diff_hi_s']:+.2f}]")
        tg.append(row)
    pop = d.get("population")
    pop_text = [] if not pop else [(
        "**A population of drivers.** Every ACC lets its driver choose the time-gap setting, "
        "and one driver at one setting cannot match a population of drivers. The *driver "
        f"population* rows drive each stretch {pop['seeds_per_stretch']} times "
        f"({pop['drives_per_planner']} drives per planner; the first {d['seeds_per_stretch']} "
        "per stretch on the other rows' traffic seeds), each drive at its own setting "
        "(`time_gap_s` in its spec and in `n74_drives.csv`), drawn (stratified, seeded) from "
        f"the preferred time gaps of the {pop['training_maneuvers']} real training maneuvers "
        "the shipped SafeIL's style input was fine-tuned on (OpenACC and NGSIM, its held-out "
        f"maneuvers left out; median {pop['estimates_median_s']:.2f} s, its default setting; "
        f"p5-p95 {pop['estimates_p5_p95_s'][0]:.2f}-{pop['estimates_p5_p95_s'][1]:.2f} s) and "
        f"clipped to the settable {pop['setting_range_s'][0]:g}-{pop['setting_range_s'][1]:g} "
        "s: settings {:.2f}-{:.2f} s, median {:.2f} s. ".format(
            *pop["settings_min_median_max_s"][::2], pop["settings_min_median_max_s"][1])
        + "The synthetic humans' own time gaps (the comparison set) are not used. The IDM's "
        "population row sets its time gap T to the same setting per drive. These rows test "
        "whether a planner reproduces a population's spread when told each driver's setting, "
        "not whether it infers a driver's style by itself."), ""]
    return [
        "## N74 drives: flags per 100 km and time gaps among traffic", "",
        (f"`python -m safeil_sumo.results --only n74` ({d['drives']} drives; their wall times "
        f"sum to {d.get('drives_core_s', math.nan) / 60:.0f} min, half that on 2 workers): "
        "every planner drives the "
        f"stretches {stretches} km of the n74 road (direction A, right lane) with the same "
        f"{d['seeds_per_stretch']} seeds each, among SUMO's `{d['traffic']}` traffic (main road "
        "and on-ramps; the leader is whichever vehicle is ahead in the ego lane; the ego never "
        "changes lane). A drive ends early at a collision or with the ego 6 m off its lane; its "
        "km count up to there. A flag event is a run of flagged steps of one kind; per 100 km "
        "with its "
        "exact Poisson (Garwood) 95 % interval over the total km, event count in brackets. "
        "Per drive: `n74_drives.csv`; every flag with its place: `n74_flags.csv`."), "",
        md_table(rows, {"planner": "planner", "done": "drives completed", "km": "km",
                        "ttc": "TTC ≤ 1 s /100 km [95 % CI] (n)",
                        "lane_departure": "lane departures /100 km",
                        "collision": "collisions /100 km", "min_ttc_s": "min TTC [s]",
                        "leaders_met": "leaders met", "cut_ins_met": "cut-ins met"}),
        "", "![n74 flag map](n74_flag_map.png)", "",
        ("**Time gaps against the recorded synthetic humans.** Time gap = bumper gap / ego "
        f"speed, at {d['time_gap_rate_hz']:g} Hz while following (leader within "
        f"{d['follow_max_gap_m']:g} m, ego faster than {d['follow_min_speed_mps']:g} m/s), on "
        "the planners' drives and on the synthetic human drives of `data/synthetic/drives.parquet` "
        "(same road, same traffic flows; the humans also change lanes). KS: the largest gap "
        "between the two ECDFs (no p-value: samples of one drive are correlated); median "
        "difference planner − humans with a 95 % bootstrap interval that resamples whole "
         "drives and recordings (seeded)."), "", *pop_text,
        md_table(tg, {"planner": "who", "groups": "drives", "samples": "samples",
                      "q05_s": "p5 [s]", "q25_s": "p25 [s]", "q50_s": "median [s]",
                      "q75_s": "p75 [s]", "q95_s": "p95 [s]",
                      "share_below_1s": "share < 1 s", "ks_to_humans": "KS to humans",
                      "diff": "median − humans [95 % CI] [s]"}),
        "", "![n74 time gaps](n74_time_gap.png)", ""]
