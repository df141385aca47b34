"""Closed-loop fine-tuning of a SafeIL checkpoint behind recorded human leaders.

    python training/closed_loop_finetune.py --init safeil_sumo/models/safeil_openloop.safetensors \
        --data data/openacc_tuples.parquet data/ngsim_tuples.parquet --out data/models/safeil_cl

The planner drives the differentiable longitudinal loop of :mod:`safeil_sumo.learn.closed_loop`
for ``--window`` seconds behind the recorded leaders of the training maneuvers (the checkpoint's
held-out maneuvers are left out) and learns to keep the human's gap and speed. Kept from the
initial checkpoint's recipe, in the same loss: the barrier and gap-monotonicity penalty on
states drawn across the operating envelope; the lateral outputs (y control points, i.e. lane
keeping, learned from the lane data) are held to the initial model's on the data and envelope
states, so only the longitudinal plan is re-learned. Deterministic for a seed.

``--style``: the planner gets the driver's preferred time gap as a 10th input
(:mod:`safeil_sumo.learn.style`; its first-layer weights start at zero), estimated per maneuver
from the data; envelope states draw it across the trained range, and the checkpoint stores the
training maneuvers' median as the default setting.

``--settle-weight``: synthetic episodes behind a constant-speed leader, the ego started far
behind or too close, scored against the setting's equilibrium gap once the transient is over
(:class:`safeil_sumo.learn.closed_loop.SettlingConfig`): the setting then means the gap the
planner settles at, whatever the start.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from safeil_sumo.cli_args import add_dataclass_options, dataclass_from_args
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import held_out_maneuvers, load_model, save_checkpoint
from safeil_sumo.learn.closed_loop import (
    D_LEAD,
    V_X,
    FinetuneConfig,
    SettlingConfig,
    closed_loop_loss,
    envelope_terms,
    episodes_from_tuples,
    rollout,
    settling_episodes,
    settling_loss,
)
from safeil_sumo.learn.envelope import sample_states
from safeil_sumo.learn.model import with_style_input
from safeil_sumo.learn.style import (
    TIME_GAP_RANGE_S,
    equilibrium_residual,
    equilibrium_states,
    maneuver_time_gaps,
    training_time_gaps,
)
from safeil_sumo.learn.trainer import TrainConfig, gap_monotone_penalty


def build_parser() -> argparse.ArgumentParser:
    """The input and output options, and one option per :class:`FinetuneConfig` field under its
    own name, its help the field's ``help`` metadata."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--init", type=Path,
                    default=Path("safeil_sumo/models/safeil_openloop.safetensors"))
    ap.add_argument("--data", type=Path, nargs="+", required=True, help="tuple Parquet files")
    ap.add_argument("--out", type=Path, required=True, help="checkpoint prefix")
    helps = {f.name: f.metadata["help"] for f in dataclasses.fields(FinetuneConfig)}
    add_dataclass_options(ap, FinetuneConfig, helps=helps)
    ap.add_argument("--no-progress", action="store_true")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        config = dataclass_from_args(FinetuneConfig, args)
    except ValueError as exc:  # the config's own checks: a usage error
        ap.error(str(exc))

    torch.manual_seed(config.seed)
    torch.set_num_threads(1)
    model, meta = load_model(args.init)
    frozen, _ = load_model(args.init)
    for p in frozen.parameters():
        p.requires_grad_(False)
    base = TrainConfig.from_dict(meta["train_config"])  # barrier, envelope, monotonicity kept
    horizon = float(meta["horizon_s"])
    held = set(held_out_maneuvers(args.init))
    tuples = Tuples.concat([Tuples.load(p) for p in args.data])
    train_ids = {m for m in np.unique(tuples.maneuver_id) if m not in held}
    eps = episodes_from_tuples(tuples, config.window, config.stride, maneuvers=train_ids)
    print(f"{len(eps)} episodes of {config.window:g} s from {len(set(eps.maneuver_id))} "
          f"training maneuvers ({len(held)} held out)")
    feats = torch.as_tensor(tuples.features, dtype=torch.float32)
    style_default = None
    median = float(np.nanmedian(maneuver_time_gaps(
        tuples.features[:, D_LEAD], tuples.features[:, V_X], tuples.maneuver_id, np.nan)))
    if config.style:
        tg = maneuver_time_gaps(tuples.features[:, D_LEAD], tuples.features[:, V_X],
                                tuples.maneuver_id, fallback_s=np.nan)
        per_maneuver = training_time_gaps(tuples.features[:, D_LEAD], tuples.features[:, V_X],
                                          tuples.maneuver_id, train_ids)
        median = float(np.median(list(per_maneuver.values())))
        tg = np.where(np.isfinite(tg), tg, median)
        style_default = {"time_gap_s": median}
        model = with_style_input(model, median, float(np.std(list(per_maneuver.values()))))
        eps = eps.with_style({m: per_maneuver.get(m, median) for m in set(eps.maneuver_id)})
        feats = torch.cat([feats, torch.as_tensor(tg, dtype=torch.float32)[:, None]], dim=1)
        print(f"style: time gap per training maneuver, median {median:.2f} s, quartiles "
              f"{np.quantile(list(per_maneuver.values()), [0.25, 0.75]).round(2).tolist()} s")
    settling = SettlingConfig(settle_after_s=min(config.settle_after, config.window / 2))
    rng = np.random.default_rng([config.seed, 3])
    gen = torch.Generator().manual_seed(config.seed)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    start = time.perf_counter()
    bar = tqdm(range(config.iters), disable=args.no_progress, desc="closed loop")
    log = []
    for _ in bar:
        idx = torch.randperm(len(eps), generator=gen)[: config.batch]
        ep = eps.take(idx.numpy())
        model.train()
        gap_off = speed_off = None
        if config.perturb > 0:
            on = torch.as_tensor(rng.uniform(size=len(ep)) < config.perturb, dtype=torch.float32)
            factor = torch.as_tensor(rng.uniform(0.5, 1.8, len(ep)), dtype=torch.float32)
            gap0 = ep.gap_human[:, 0]
            gap_off = on * torch.clamp(gap0 * (factor - 1.0), min=3.0 - gap0)
            speed_off = on * torch.as_tensor(rng.uniform(-2.0, 2.0, len(ep)),
                                             dtype=torch.float32)
        terms = closed_loop_loss(rollout(model, ep, horizon=horizon, gap_offset_m=gap_off,
                                         speed_offset_mps=speed_off), ep,
                                 speed_weight=config.speed_weight, barrier_k=base.barrier_k,
                                 barrier_weight=base.envelope_weight)
        settle = floor = torch.zeros(())
        if config.settle_weight > 0:
            syn, gap_eq = settling_episodes(config.batch, eps.lanes, rng, config.window,
                                            cfg=settling)
            settle, floor = settling_loss(rollout(model, syn, horizon=horizon), gap_eq,
                                          syn.dt_s, settling)
        env = torch.as_tensor(sample_states(base.envelope_batch, rng), dtype=torch.float32)
        if config.style:
            env = torch.cat([env, torch.as_tensor(rng.uniform(*TIME_GAP_RANGE_S, (len(env), 1)),
                                                  dtype=torch.float32)], dim=1)
        env_term, lane, lead = envelope_terms(env, model(env), horizon, base.barrier)
        mono = gap_monotone_penalty(model, env, margin_m=base.monotone_margin_m)
        equilibrium = torch.zeros(())
        if config.equilibrium_weight > 0:
            time_gap = env[:, 9] if config.style else torch.full((len(env),), median)
            eq = equilibrium_states(env, time_gap)
            equilibrium = equilibrium_residual(model(eq), eq[:, V_X], horizon)
        data_rows = torch.randint(len(feats), (512,), generator=gen)
        anchor = torch.cat([feats[data_rows], env]) if config.anchor_envelope else feats[
            data_rows]
        lateral = (model(anchor)[..., 1] - frozen(anchor[:, :9])[..., 1]).pow(2).mean()
        loss = (terms.total + base.envelope_weight * env_term + base.monotone_weight * mono
                + config.lateral_weight * lateral + config.equilibrium_weight * equilibrium
                + config.settle_weight * (settle + floor))
        if config.lane_weight > 0:  # (not added at 0: today's recipe, bit for bit)
            loss = loss + config.lane_weight * lane
        if config.leader_weight > 0:
            loss = loss + config.leader_weight * lead
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        row = {**terms.as_floats(), "envelope": float(env_term.detach()),
               "lane": float(lane.detach()), "leader": float(lead.detach()), "monotone": float(mono.detach()),
               "lateral": float(lateral.detach()), "equilibrium": float(equilibrium.detach()),
               "settle": float(settle.detach()), "floor": float(floor.detach()),
               "loss": float(loss.detach())}
        log.append(row)
        bar.set_postfix(gap=f"{row['gap']:.1f}", v=f"{row['speed']:.2f}",
                        lat=f"{row['lateral']:.2g}", lane=f"{row['lane']:.0f}", settle=f"{row['settle']:.1f}",
                        refresh=False)
    model.eval()
    seconds = time.perf_counter() - start
    metrics = {**meta.get("metrics", {}), "closed_loop": {
        "init": str(args.init), "window_s": config.window, "stride_s": config.stride,
        "iters": config.iters, "batch": config.batch, "lr": config.lr,
        "speed_weight": config.speed_weight, "lateral_weight": config.lateral_weight,
        "equilibrium_weight": config.equilibrium_weight, "perturb": config.perturb,
        "settle_weight": config.settle_weight, "settle_after_s": settling.settle_after_s,
        "lane_weight": config.lane_weight, "leader_weight": config.leader_weight,
        "anchor_envelope": config.anchor_envelope,
        "seed": config.seed, "episodes": len(eps), "seconds": seconds, "style": config.style,
        "final": log[-1], "first": log[0]}}
    save_checkpoint(args.out, model, name=meta["name"], horizon=horizon,
                    train_config=meta["train_config"], data_fingerprint=meta.get(
                        "data_fingerprint"), metrics=metrics, style_default=style_default)
    print(f"{seconds:.0f} s; first {log[0]['gap']:.1f} m^2 gap, last {log[-1]['gap']:.1f}; "
          f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
