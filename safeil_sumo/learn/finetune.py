"""Closed-loop fine-tuning of a SafeIL checkpoint behind recorded human leaders.

:func:`finetune` takes a :class:`~safeil_sumo.learn.closed_loop.FinetuneConfig`, the initial
checkpoint and Tuples files and writes the fine-tuned checkpoint
(``training/closed_loop_finetune.py`` is its command line, ``training/train_shipped_models.py``
calls it with the shipped recipe).

The planner drives the differentiable longitudinal loop of :mod:`safeil_sumo.learn.closed_loop`
for ``window`` seconds behind the recorded leaders of the training maneuvers (the checkpoint's
held-out maneuvers are left out) and learns to keep the human's gap and speed. Kept from the
initial checkpoint's recipe, in the same loss: the barrier and gap-monotonicity penalty on
states drawn across the operating envelope; the lateral outputs (y control points, i.e. lane
keeping, learned from the lane data) are held to the initial model's on the data and envelope
states, so only the longitudinal plan is re-learned. Deterministic for a seed (one torch thread
while it runs).

``style``: the planner gets the driver's preferred time gap as a 10th input
(:mod:`safeil_sumo.learn.style`; its first-layer weights start at zero), estimated per maneuver
from the data; envelope states draw it across the trained range, and the checkpoint stores the
training maneuvers' median as the default setting.

``settle_weight``: synthetic episodes behind a constant-speed leader, the ego started far
behind or too close, scored against the setting's equilibrium gap once the transient is over
(:class:`safeil_sumo.learn.closed_loop.SettlingConfig`): the setting then means the gap the
planner settles at, whatever the start.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import held_out_maneuvers, load_model, save_checkpoint
from safeil_sumo.learn.closed_loop import (
    D_LEAD,
    V_X,
    Episodes,
    FinetuneConfig,
    SettlingConfig,
    closed_loop_loss,
    envelope_terms,
    episodes_from_tuples,
    equilibrium_residual,
    equilibrium_states,
    rollout,
    settling_episodes,
    settling_loss,
)
from safeil_sumo.learn.envelope import sample_states
from safeil_sumo.learn.model import (
    PlannerMLP,
    keep_only_tower_gradients,
    split_towers,
    with_style_input,
)
from safeil_sumo.learn.style import (
    TIME_GAP_RANGE_S,
    maneuver_time_gaps,
    training_time_gaps,
)
from safeil_sumo.learn.trainer import TrainConfig, gap_monotone_penalty

DATA_ANCHOR_ROWS = 512  # data states per iteration holding the lateral outputs


@dataclass(frozen=True)
class FinetuneResult:
    """What :func:`finetune` wrote: the checkpoint prefix, the metrics stored in it (the initial
    checkpoint's, plus ``closed_loop``: the settings, the episodes, the first and final
    iteration's terms) and notes on the data (episodes, style; one line each) for a command line
    to print."""

    prefix: Path
    metrics: dict[str, Any]
    notes: tuple[str, ...]


@dataclass(frozen=True)
class _Start:
    """The fine-tune's starting point: the model (style input added if asked), the initial model
    (frozen: the lateral anchor), the initial checkpoint's metadata and recipe, the episodes and
    the data states."""

    model: PlannerMLP
    frozen: PlannerMLP
    meta: dict[str, Any]
    base: TrainConfig
    horizon: float
    episodes: Episodes
    features: torch.Tensor
    median_time_gap_s: float
    style_default: dict[str, float] | None
    notes: tuple[str, ...]


def _start(config: FinetuneConfig, init: Path, data_paths: Sequence[Path]) -> _Start:
    model, meta = load_model(init)
    frozen, _ = load_model(init)
    for p in frozen.parameters():
        p.requires_grad_(False)
    base = TrainConfig.from_dict(meta["train_config"])  # barrier, envelope, monotonicity kept
    held = set(held_out_maneuvers(init))
    tuples = Tuples.concat([Tuples.load(p) for p in data_paths])
    train_ids = {m for m in np.unique(tuples.maneuver_id) if m not in held}
    eps = episodes_from_tuples(tuples, config.window, config.stride, maneuvers=train_ids)
    notes = [(f"{len(eps)} episodes of {config.window:g} s from {len(set(eps.maneuver_id))} "
              f"training maneuvers ({len(held)} held out)")]
    feats = torch.as_tensor(tuples.features, dtype=torch.float32)
    style_default = None
    d_lead, v_x = tuples.features[:, D_LEAD], tuples.features[:, V_X]
    median = float(np.nanmedian(maneuver_time_gaps(d_lead, v_x, tuples.maneuver_id, np.nan)))
    if config.style:
        tg = maneuver_time_gaps(d_lead, v_x, tuples.maneuver_id, fallback_s=np.nan)
        per_maneuver = training_time_gaps(d_lead, v_x, tuples.maneuver_id, train_ids)
        median = float(np.median(list(per_maneuver.values())))
        tg = np.where(np.isfinite(tg), tg, median)
        style_default = {"time_gap_s": median}
        model = with_style_input(model, median, float(np.std(list(per_maneuver.values()))))
        eps = eps.with_style({m: per_maneuver.get(m, median) for m in set(eps.maneuver_id)})
        feats = torch.cat([feats, torch.as_tensor(tg, dtype=torch.float32)[:, None]], dim=1)
        notes.append(f"style: time gap per training maneuver, median {median:.2f} s, quartiles "
                     f"{np.quantile(list(per_maneuver.values()), [0.25, 0.75]).round(2).tolist()}"
                     " s")
    if config.towers and not model.towers:
        model = split_towers(model)
        notes.append(f"towers: hidden {list(model.hidden)}, the x control points read no lane line")
    return _Start(model, frozen, meta, base, float(meta["horizon_s"]), eps, feats, median,
                  style_default, tuple(notes))


def _iteration(config: FinetuneConfig, s: _Start, settling: SettlingConfig,
               opt: torch.optim.Optimizer, rng: np.random.Generator, gen: torch.Generator
               ) -> dict[str, float]:
    """One optimiser step on a batch of episodes; the loss terms, as floats."""
    model, base, horizon = s.model, s.base, s.horizon
    idx = torch.randperm(len(s.episodes), generator=gen)[: config.batch]
    ep = s.episodes.take(idx.numpy())
    model.train()
    gap_off = speed_off = None
    if config.perturb > 0:
        on = torch.as_tensor(rng.uniform(size=len(ep)) < config.perturb, dtype=torch.float32)
        factor = torch.as_tensor(rng.uniform(0.5, 1.8, len(ep)), dtype=torch.float32)
        gap0 = ep.gap_human[:, 0]
        gap_off = on * torch.clamp(gap0 * (factor - 1.0), min=3.0 - gap0)
        speed_off = on * torch.as_tensor(rng.uniform(-2.0, 2.0, len(ep)), dtype=torch.float32)
    terms = closed_loop_loss(rollout(model, ep, horizon=horizon, gap_offset_m=gap_off,
                                     speed_offset_mps=speed_off), ep,
                             speed_weight=config.speed_weight, barrier_k=base.barrier_k,
                             barrier_weight=base.envelope_weight)
    settle = floor = torch.zeros(())
    if config.settle_weight > 0:
        syn, gap_eq = settling_episodes(config.batch, s.episodes.lanes, rng, config.window,
                                        cfg=settling)
        settle, floor = settling_loss(rollout(model, syn, horizon=horizon), gap_eq, syn.dt_s,
                                      settling)
    env = torch.as_tensor(sample_states(base.envelope_batch, rng), dtype=torch.float32)
    if config.style:
        env = torch.cat([env, torch.as_tensor(rng.uniform(*TIME_GAP_RANGE_S, (len(env), 1)),
                                              dtype=torch.float32)], dim=1)
    env_term, lane, lead = envelope_terms(env, model(env), horizon, base.barrier,
                                          lane_by_steering=config.towers)
    mono = gap_monotone_penalty(model, env, margin_m=base.monotone_margin_m)
    equilibrium = torch.zeros(())
    if config.equilibrium_weight > 0:
        time_gap = env[:, 9] if config.style else torch.full((len(env),), s.median_time_gap_s)
        eq = equilibrium_states(env, time_gap)
        equilibrium = equilibrium_residual(model(eq), eq[:, V_X], horizon)
    data_rows = torch.randint(len(s.features), (DATA_ANCHOR_ROWS,), generator=gen)
    anchor = (torch.cat([s.features[data_rows], env]) if config.anchor_envelope
              else s.features[data_rows])
    lateral = (model(anchor)[..., 1] - s.frozen(anchor[:, :9])[..., 1]).pow(2).mean()
    loss = (terms.total + base.envelope_weight * env_term + base.monotone_weight * mono
            + config.lateral_weight * lateral + config.equilibrium_weight * equilibrium
            + config.settle_weight * (settle + floor))
    if config.lane_weight > 0:  # (not added at 0: the recipe before the option, bit for bit)
        loss = loss + config.lane_weight * lane
    if config.leader_weight > 0:
        loss = loss + config.leader_weight * lead
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if model.towers:  # the lateral plan stays the initial model's, exactly
        keep_only_tower_gradients(model, "longitudinal")
    torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
    opt.step()
    named = {"envelope": env_term, "lane": lane, "leader": lead, "monotone": mono,
             "lateral": lateral, "equilibrium": equilibrium, "settle": settle, "floor": floor,
             "loss": loss}
    return {**terms.as_floats(), **{k: float(v.detach()) for k, v in named.items()}}


def finetune(config: FinetuneConfig, init: str | Path, data_paths: Sequence[str | Path],
             out: str | Path, progress: bool = False) -> FinetuneResult:
    """Fine-tune the checkpoint ``init`` in closed loop with ``config`` on the Tuples files
    ``data_paths`` (concatenated; the checkpoint's held-out maneuvers left out) and write the
    checkpoint ``out`` (a prefix): the policy name, horizon, training config and data
    fingerprint of ``init``, its metrics plus ``closed_loop``, and with ``config.style`` the
    style input's default setting. Runs on one torch thread (restored afterwards)."""
    init, out = Path(init), Path(out)
    prev_threads = torch.get_num_threads()
    try:
        torch.manual_seed(config.seed)
        torch.set_num_threads(1)
        s = _start(config, init, [Path(p) for p in data_paths])
        settling = SettlingConfig(settle_after_s=min(config.settle_after, config.window / 2))
        rng = np.random.default_rng([config.seed, 3])
        gen = torch.Generator().manual_seed(config.seed)
        opt = torch.optim.Adam(s.model.parameters(), lr=config.lr)
        start = time.perf_counter()
        bar = tqdm(range(config.iters), disable=not progress, desc="closed loop")
        log = []
        for _ in bar:
            row = _iteration(config, s, settling, opt, rng, gen)
            log.append(row)
            bar.set_postfix(gap=f"{row['gap']:.1f}", v=f"{row['speed']:.2f}",
                            lat=f"{row['lateral']:.2g}", lane=f"{row['lane']:.0f}",
                            settle=f"{row['settle']:.1f}", refresh=False)
        s.model.eval()
        seconds = time.perf_counter() - start
    finally:
        torch.set_num_threads(prev_threads)
    metrics = {**s.meta.get("metrics", {}), "closed_loop": {
        "init": str(init), "window_s": config.window, "stride_s": config.stride,
        "iters": config.iters, "batch": config.batch, "lr": config.lr,
        "speed_weight": config.speed_weight, "lateral_weight": config.lateral_weight,
        "equilibrium_weight": config.equilibrium_weight, "perturb": config.perturb,
        "settle_weight": config.settle_weight, "settle_after_s": settling.settle_after_s,
        "lane_weight": config.lane_weight, "leader_weight": config.leader_weight,
        "anchor_envelope": config.anchor_envelope, "towers": config.towers,
        "seed": config.seed, "episodes": len(s.episodes), "seconds": seconds,
        "style": config.style, "final": log[-1], "first": log[0]}}
    save_checkpoint(out, s.model, name=s.meta["name"], horizon=s.horizon,
                    train_config=s.meta["train_config"],
                    data_fingerprint=s.meta.get("data_fingerprint"), metrics=metrics,
                    style_default=s.style_default)
    return FinetuneResult(out, metrics, s.notes)
