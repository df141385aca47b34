"""Why the learned planners did not follow their leader, and what fixes it: one lever at a time.

    python training/leader_following_ablation.py [--workers 2] [--out results/]

Trains SafeIL variants (seed 0, the per-source maneuver split of ``train_shipped_models.py``),
from the recipe of the earlier shipped model (synthetic data, absolute control points, barrier on
the recorded tuples only) to the shipped recipe, and measures each:

- open loop: the held-out imitation error of the x control points per source [m^2];
- the static probe (:mod:`safeil_sumo.experiments.leader_probe`): plans that run past the
  predicted leader on recoverable states, and (speed, leader speed) pairs whose plan shrinks as
  the gap grows;
- closed loop: the validation battery (:mod:`safeil_sumo.experiments.selection`: flags and
  collisions over 12 scenarios), and the human-likeness replay of every 11 s window (every 20 s)
  of the held-out OpenACC maneuvers (median gap RMSE [m] against the human, flags).

Writes ``leader_ablation.csv`` and ``leader_ablation.md`` into ``--out``. Checkpoints are cached
in ``data/ablation/`` (delete it to retrain). Needs the datasets of ``train_shipped_models.py``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "data"
SOURCES = {"synthetic": DATA / "synthetic" / "tuples.parquet",
           "openacc": DATA / "openacc_tuples.parquet", "ngsim": DATA / "ngsim_tuples.parquet"}
SYN = ("synthetic",)
ALL = ("synthetic", "openacc", "ngsim")
MIX = {"longitudinal_only_sources": ("openacc",)}
ENV = {"envelope_weight": 1.0, "monotone_weight": 10000.0}  # weight 1: the first envelope tried
ENV_SHIPPED = {"envelope_weight": 0.01, "monotone_weight": 10000.0}
# name -> (sources, TrainConfig overrides); all SafeIL with the Bernstein lane bound unless said
VARIANTS: dict[str, tuple[tuple[str, ...], dict]] = {
    "synthetic (earlier shipped recipe)": (SYN, {}),
    "synthetic, residual outputs": (SYN, {"output_mode": "residual"}),
    "synthetic, residual, envelope": (SYN, {"output_mode": "residual", **ENV}),
    "real+synthetic, residual": (ALL, {"output_mode": "residual", **MIX}),
    "real+synthetic, residual, envelope": (ALL, {"output_mode": "residual", **MIX, **ENV}),
    "real+synthetic, residual, envelope weight 0.01": (
        ALL, {"output_mode": "residual", **MIX, **ENV_SHIPPED}),
    "real+synthetic, residual, envelope weight 0.01, monotone margin 2 mm (shipped recipe)": (
        ALL, {"output_mode": "residual", **MIX, **ENV_SHIPPED, "monotone_margin_m": 0.002}),
    "real+synthetic, residual, envelope, no monotonicity penalty": (
        ALL, {"output_mode": "residual", **MIX, "envelope_weight": 1.0}),
    "real+synthetic, residual, envelope, 128x128": (ALL, {"output_mode": "residual", **MIX,
                                                          **ENV, "hidden": (128, 128)}),
    "real+synthetic, residual, envelope, synthetic lateral only": (
        ALL, {"output_mode": "residual", **MIX, **ENV, "lateral_only_sources": ("synthetic",)}),
    "real+synthetic, absolute, envelope": (ALL, {**MIX, **ENV}),
    "real+synthetic, residual, envelope, margin 2 m": (ALL, {"output_mode": "residual", **MIX,
                                                             **ENV, "gap_min": 2.0}),
    "real+synthetic, residual, envelope, margin 2 m + 0.5 s": (
        ALL, {"output_mode": "residual", **MIX, **ENV, "gap_min": 2.0, "time_gap": 0.5}),
    "real+synthetic, residual, envelope, margin 2 m + 1 s": (
        ALL, {"output_mode": "residual", **MIX, **ENV, "gap_min": 2.0, "time_gap": 1.0}),
    "BC, real+synthetic, residual": (ALL, {"method": "bc", "output_mode": "residual", **MIX}),
}
REPLAY_STRIDE_S = 20.0  # [s] between the starts of the 11 s replay windows


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_")[:80]


def train_variant(name: str, sources: tuple[str, ...], overrides: dict, cache: Path) -> Path:
    from safeil_sumo.data.tuples import Tuples
    from safeil_sumo.learn.torch_required import training_imports

    with training_imports():  # without torch: one line that says what to install, no traceback
        from safeil_sumo.learn.checkpoint import save_checkpoint, tuples_fingerprint
        from safeil_sumo.learn.trainer import TrainConfig, split_by_maneuver, train

    prefix = cache / _slug(name)
    if prefix.with_suffix(".safetensors").is_file():
        return prefix
    tuples = Tuples.concat([Tuples.load(SOURCES[s]) for s in sources])
    tr, va = split_by_maneuver(tuples, 0.2, 0)
    cfg = TrainConfig(barrier_lateral="bernstein", **overrides)
    model, hist = train(tr, va, cfg, progress=False)
    save_checkpoint(prefix, model, name=_slug(name), horizon=tuples.horizon, train_config=cfg,
                    data_fingerprint=tuples_fingerprint(tuples),
                    metrics={"val_maneuvers": sorted(map(str, va.maneuvers))}, history=hist)
    return prefix


def mixed_held_out():
    """The held-out tuples of the mixed training set (20 % of each source's maneuvers, seed 0):
    every variant is scored on these (the synthetic-only variants held out other synthetic
    maneuvers, so their synthetic score is slightly optimistic)."""
    from safeil_sumo.data.tuples import Tuples
    from safeil_sumo.learn.trainer import split_by_maneuver

    return split_by_maneuver(Tuples.concat([Tuples.load(p) for p in SOURCES.values()]), 0.2, 0)[1]


def imitation_by_source(prefix: Path, va) -> dict[str, float]:
    """Held-out squared x error summed over the 3 control points, mean per source [m^2]."""
    from safeil_sumo.learn.inference import load_policy

    policy = load_policy(prefix)
    out = {}
    for src in SOURCES:
        part = va.subset(va.source.astype(str) == src)
        err = (policy.plan(part.features) - part.control_points)[..., 0]
        out[f"val_x_sq_err_{src}"] = float((err ** 2).sum(axis=1).mean())
    return out


def replay_windows(checkpoints: dict[str, str], held_out: list[str], work: Path) -> pd.DataFrame:
    """Gap RMSE of every policy on every 11 s window of the held-out OpenACC maneuvers."""
    from safeil_sumo.data.pipeline import PipelineConfig, process_drive
    from safeil_sumo.data.sources import load_source
    from safeil_sumo.experiments import maneuver_replay as rp
    from safeil_sumo.planners import registry as pol

    maneuvers, _ = process_drive(load_source("openacc"), PipelineConfig(rate_hz=10.0))
    policies = {name: pol.load(path) for name, path in checkpoints.items()}
    rows = []
    for mid in held_out:
        m = maneuvers[maneuvers["maneuver_id"] == mid].reset_index(drop=True)
        duration = float(m["time"].iloc[-1] - m["time"].iloc[0])
        for start in tqdm(np.arange(0.0, duration - rp.PAPER_DURATION_S, REPLAY_STRIDE_S),
                          desc=f"replay {mid}", leave=False):
            rows_w = rp.window(m, float(start), rp.PAPER_DURATION_S)
            res = rp.replay_maneuver(rows_w, policies, work / "replay", rp.ReplayConfig(),
                                     maneuver_id=mid)
            for _, r in res.metrics.iterrows():
                rows.append({"variant": r["policy"], "maneuver": mid, "start_s": start,
                             "rmse_gap": r["rmse_gap"], "flag": r["flag"]})
    return pd.DataFrame(rows)


def markdown(table: pd.DataFrame) -> str:
    """A plain Markdown table (3 significant digits, blanks for missing values)."""
    def cell(v) -> str:
        if isinstance(v, float):
            return "" if np.isnan(v) else f"{v:.3g}"
        return str(v)

    lines = ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in table.itertuples(index=False)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO / "results")
    ap.add_argument("--cache", type=Path, default=DATA / "ablation")
    args = ap.parse_args(argv)
    missing = [str(p) for p in SOURCES.values() if not p.is_file()]
    if missing:
        print(f"error: missing datasets {missing}: run training/build_real_datasets.py and "
              "training/build_synthetic_dataset.py", file=sys.stderr)
        return 2
    from safeil_sumo.experiments.leader_probe import probe
    from safeil_sumo.experiments.selection import evaluate
    from safeil_sumo.planners import registry as pol

    args.cache.mkdir(parents=True, exist_ok=True)
    prefixes = {name: train_variant(name, srcs, kw, args.cache)
                for name, (srcs, kw) in tqdm(VARIANTS.items(), desc="train")}
    paths = {name: str(p.with_suffix(".safetensors")) for name, p in prefixes.items()}
    battery = evaluate(list(paths.values()), args.cache / "battery", workers=args.workers,
                       progress=False).set_index("policy")

    # the OpenACC maneuvers held out of the mixed training set (the split draws per source)
    va = mixed_held_out()
    held_out = sorted(map(str, np.unique(va.maneuver_id[va.source.astype(str) == "openacc"])))
    replays = replay_windows({**paths, "analytic": "analytic"}, held_out, args.cache)
    rows = []
    for name, prefix in prefixes.items():
        summary, _ = probe(pol.load(paths[name]))
        b = battery.loc[paths[name]]
        r = replays[replays["variant"] == name]
        rows.append({
            "variant": name, **imitation_by_source(prefix, va),
            "probe_pass_rate": summary["pass_rate"],
            "probe_gap_monotone_violations": summary["gap_monotone_violations"],
            "probe_max_end_x_decrease_m": summary["max_end_x_decrease_m"],
            "battery_collisions": int(b["collisions"]), "battery_flags": int(b["flags"]),
            "replay_windows": len(r), "replay_gap_rmse_median_m": float(r["rmse_gap"].median()),
            "replay_flags": int((r["flag"].fillna("") != "").sum()),
        })
    a = replays[replays["variant"] == "analytic"]
    rows.append({"variant": "analytic planner", "replay_windows": len(a),
                 "replay_gap_rmse_median_m": float(a["rmse_gap"].median()),
                 "replay_flags": int((a["flag"].fillna("") != "").sum())})
    table = pd.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "leader_ablation.csv", index=False)
    (args.out / "leader_ablation.md").write_text(markdown(table))
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
