"""Refit a towers planner's lateral plan to its own longitudinal plan.

A towers checkpoint (:func:`safeil_sumo.learn.model.split_towers`) fine-tuned in closed loop
keeps the lateral tower of the open-loop model it started from, whose y control points were
learned together with *that* model's x control points. The fine-tune changes how far the plan
reaches (on a bend the open-loop model planned shorter), so at speed on a tight bend the kept y
points sit where the open-loop plan's x would have put them, not where the new x does, and the
plan's end leaves the lane (``certify``: counterexamples on most of the lane envelope).

The refit keeps what the open-loop model learned about lane keeping, its lateral offset from
the lane centre along the plan, and carries it over to the new plan's length:

    target y(tau) = centre(x_new(tau)) + [y_ref(tau) - centre_ref(x_ref(tau))]

with ``centre`` the lane-centre polynomial (the mean of both lines; ``centre_ref`` that of the
lane the reference planned for), ``(x_ref, y_ref)`` the reference (open-loop) plan and
``x_new`` the towers model's own plan; the y control points are its least-squares cubic fit
(:func:`lateral_targets`). By default the reference plans for the same state with the lane
straightened (``straight_reference``): its offsets are its lane keeping (back to the centre
from an offset or a heading error), learned on nearly straight lanes, and
the bend is followed geometrically; a share of the states lies on bends tighter than any
training lane (``bend_share``), where the reference alone would extrapolate: up to R = 40 m
at 6 m/s^2, with the heading errors and offsets a camera reports there and the two lines bent
apart as on a real bend (``bend_line_split``). Only the lateral tower is trained (the x control
points stay bit-identical), by plain regression on states drawn across the operating envelope
and from the data, with the envelope barrier's lane terms on top. It starts afresh
(``fresh_tower``), its inputs scaled to these states: the tower inherited from the open-loop
model read the lane curvature on the highway data's scale (c2 spread 0.0002, a handling
course's bends 50 standard deviations out), saturated there and, fitted on, followed its
targets only on the bends it had seen (CHANGELOG.md, "A fresh lateral tower for real
bends").
Where the plans are equally long (slow, or the fine-tune did not change x) on a straight lane
the target is the reference's y exactly, so low-speed lane keeping is kept.

With ``lateral_mode="lane"`` (the shipped recipe) the tower no longer outputs y: it outputs the
offsets of :func:`safeil_sumo.core.bspline.lane_following_y`, which builds the centre part of the
target in closed form from the lane lines and the plan's own x, and bounds the offsets by the
room the lane leaves; the refit fits the same targets through it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from safeil_sumo.core.features import N_FEATURES
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn import spline
from safeil_sumo.learn.checkpoint import load_model, save_checkpoint
from safeil_sumo.learn.closed_loop import envelope_terms
from safeil_sumo.learn.envelope import EnvelopeConfig, sample_states
from safeil_sumo.learn.losses import C0L, C0R, V_LEAD, V_X
from safeil_sumo.learn.model import LATERAL_MODES, PlannerMLP, keep_only_tower_gradients
from safeil_sumo.learn.style import TIME_GAP_RANGE_S
from safeil_sumo.learn.towers import LANE_FEATURES, Y_OUTPUTS, tower_rows
from safeil_sumo.learn.trainer import TrainConfig


@dataclass(frozen=True)
class LateralRefitConfig:
    """Settings of :func:`refit_lateral` (``training/refit_lateral.py`` has one option per
    field under its own name; the meaning and unit of each is its ``help``)."""

    steps: int = field(default=16000, metadata={"help": "optimiser steps"})
    batch: int = field(default=2048, metadata={
        "help": "states per step: half drawn across the envelope, half data states"})
    lr: float = field(default=1e-3, metadata={
        "help": "Adam learning rate, decayed linearly to 0 over the steps [-]"})
    lane_weight: float = field(default=0.01, metadata={
        "help": "weight of the envelope barrier's lane terms (K softplus(-b_k) on the exact "
                "Bernstein coefficients of both lateral margins) on the envelope states; 0.01 "
                "is the open-loop recipe's envelope weight [-]"})
    straight_reference: bool = field(default=True, metadata={
        "help": "take the reference's offsets from the lane centre on the same state with the "
                "lane straightened (c2 = 0): its lane keeping (back to the centre from an "
                "offset or heading error), with the bend itself followed geometrically; so the "
                "target holds on bends tighter than the reference ever saw"})
    bend_share: float = field(default=0.25, metadata={
        "help": "share of the envelope states drawn on tighter bends, up to "
                "--bend-curvature, at speeds keeping the lateral acceleration v^2 kappa within "
                "--bend-lateral-accel (0: the envelope's curvatures only; the training lanes "
                "have R >= 250 m, a handling course R = 45-80 m) [-]"})
    bend_curvature: float = field(default=1.0 / 40.0, metadata={
        "help": "largest curvature of the tighter bends [1/m]"})
    bend_lateral_accel: float = field(default=6.0, metadata={
        "help": "largest lateral acceleration of the tighter bends' states [m/s^2]"})
    bend_heading_error: float = field(default=0.08, metadata={
        "help": "largest lane slope c1 in the ego frame on the tighter bends' states (the "
                "envelope's own range is 0.03; on a handling course's bends the camera's "
                "lines reach 0.06) [-]"})
    bend_offset_m: float = field(default=0.8, metadata={
        "help": "largest lateral offset from the lane centre on the tighter bends' states [m]"})
    fresh_tower: bool = field(default=True, metadata={
        "help": "start the lateral tower afresh (seeded) instead of from the checkpoint's, with "
                "the lane features and y outputs scaled to the refit's own states and targets: "
                "the reference's highway data spread c2 by 0.0002, so a handling course's bends "
                "lie 50 standard deviations out and the inherited tower saturates there"})
    bend_line_split: float = field(default=2.0, metadata={
        "help": "how the tighter bends' two lane lines differ: each state's lines bend by "
                "kappa / (1 -+ s kappa w / 2), s drawn uniformly in [0, this] (0: one curvature "
                "for both; s = 1: concentric, as a camera sees a bend, the inner line bending "
                "more, by 5 percent at R = 40 m); a range teaches the plan to follow the centre "
                "whatever the split [-]"})
    lateral_mode: str = field(default="absolute", metadata={
        "help": "what the lateral tower outputs: 'absolute', the y control points [m] (the "
                "paper's); 'lane', offsets from the lane centre bounded by the lane's free half "
                "width, the centre along the plan built from the lane lines "
                "(bspline.lane_following_y): the plan follows any bend by construction "
                "(needs --fresh-tower)"})
    lane_clearance_m: float = field(default=0.05, metadata={
        "help": "with --lateral-mode lane: how far inside the lane (beyond half the track) the "
                "control points' offsets stay [m]"})
    n_tau: int = field(default=21, metadata={
        "help": "points along the plan at which the target path is fitted [-]"})
    seed: int = field(default=0, metadata={"help": "seed of the states drawn"})

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch < 2 or self.n_tau < 4:
            raise ValueError(f"steps >= 1, batch >= 2 and n_tau >= 4 needed, got {self.steps}, "
                             f"{self.batch}, {self.n_tau}")
        if self.lr <= 0 or self.lane_weight < 0:
            raise ValueError(f"lr > 0 and lane_weight >= 0 needed, got {self.lr}, "
                             f"{self.lane_weight}")
        if not (0.0 <= self.bend_share < 1.0 and self.bend_curvature > 0
                and self.bend_lateral_accel > 0):
            raise ValueError(f"bend_share in [0, 1), bend_curvature > 0 and bend_lateral_accel "
                             f"> 0 needed, got {self.bend_share}, {self.bend_curvature}, "
                             f"{self.bend_lateral_accel}")
        if self.lateral_mode not in LATERAL_MODES or self.lane_clearance_m < 0:
            raise ValueError(f"lateral_mode one of {LATERAL_MODES} and lane_clearance_m >= 0 "
                             f"needed, got {self.lateral_mode!r}, {self.lane_clearance_m}")
        if self.lateral_mode == "lane" and not self.fresh_tower:
            raise ValueError("lateral_mode 'lane' needs fresh_tower: an inherited lateral tower "
                             "outputs y control points, not offsets")
        if self.bend_heading_error < 0 or self.bend_offset_m < 0 or self.bend_line_split < 0:
            raise ValueError(f"bend_heading_error, bend_offset_m and bend_line_split >= 0 "
                             f"needed, got {self.bend_heading_error}, {self.bend_offset_m}, "
                             f"{self.bend_line_split}")


def _line(coef: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``c0 + c1 x + c2 x^2`` for ``coef (N, 3)`` at ``x (N, M)``."""
    return coef[:, 0, None] + coef[:, 1, None] * x + coef[:, 2, None] * x * x


def lateral_targets(features: torch.Tensor, reference: torch.Tensor, new_x: torch.Tensor,
                    n_tau: int = 21, reference_features: torch.Tensor | None = None
                    ) -> torch.Tensor:
    """The y control points ``(N, 3)`` [m] that carry the reference plans' lateral offsets from
    the lane centre over to new plan lengths: the least-squares cubic (origin fixed) through
    ``centre(x_new(tau)) + y_ref(tau) - centre(x_ref(tau))`` at ``n_tau`` points ``tau`` in
    [0, 1], for ``features (N, >= 6)`` (the lane lines' ``c0, c1, c2``), reference plans
    ``(N, 3, 2)`` and new x control points ``(N, 3)``. Exact (the target is a cubic) on straight
    lanes, or where the new plan has the reference's x. ``reference_features``: the states the
    reference plans were made for, if not ``features`` (e.g. the lane straightened): the
    offsets are taken from their lane centre."""
    dtype = reference.dtype
    if reference_features is None:
        reference_features = features
    tau = torch.linspace(0.0, 1.0, n_tau, dtype=dtype)
    free = spline.basis(tau)[:, 1:]  # (M, 3): the origin's coefficient is 0
    centre = 0.5 * (features[:, C0L:C0L + 3] + features[:, C0R:C0R + 3]).to(dtype)
    centre_ref = 0.5 * (reference_features[:, C0L:C0L + 3]
                        + reference_features[:, C0R:C0R + 3]).to(dtype)
    x_ref, y_ref = reference[..., 0] @ free.T, reference[..., 1] @ free.T  # (N, M)
    x_new = new_x.to(dtype) @ free.T
    target = _line(centre, x_new) + y_ref - _line(centre_ref, x_ref)
    return target @ torch.linalg.pinv(free).T


@dataclass(frozen=True)
class RefitResult:
    path: Path
    metrics: dict


def _with_style(states: torch.Tensor, model: PlannerMLP, rng: np.random.Generator
                ) -> torch.Tensor:
    """States with style inputs drawn across the trained range if ``model`` reads them."""
    if model.n_features == N_FEATURES:
        return states
    style = rng.uniform(*TIME_GAP_RANGE_S, (len(states), model.n_features - N_FEATURES))
    return torch.cat([states, torch.as_tensor(style, dtype=states.dtype)], dim=1)


def _bend_states(n: int, rng: np.random.Generator, config: LateralRefitConfig) -> np.ndarray:
    """Envelope states on bends up to ``config.bend_curvature``, with heading errors and offsets
    up to ``config.bend_heading_error`` and ``config.bend_offset_m`` and the lines bent apart by
    up to ``config.bend_line_split``; both speeds scaled down where ``v^2 kappa`` would exceed
    ``config.bend_lateral_accel`` (slower: still recoverable)."""
    k = config.bend_curvature
    h, o = config.bend_heading_error, config.bend_offset_m
    states = sample_states(n, rng, replace(EnvelopeConfig(), curvature_1pm=(-k, k),
                                           heading_error=(-h, h), lateral_offset_m=(-o, o)))
    kappa = np.abs(2.0 * states[:, C0L + 2])  # the centre line's
    if config.bend_line_split > 0.0:
        states = _split_lines(states, rng.uniform(0.0, config.bend_line_split, len(states)))
    v_max = np.sqrt(config.bend_lateral_accel / np.maximum(kappa, 1e-9))
    scale = np.minimum(1.0, v_max / np.maximum(states[:, V_X], 1e-9))
    states[:, V_X] *= scale
    states[:, V_LEAD] *= scale
    return states


def _split_lines(states: np.ndarray, split: np.ndarray | float = 1.0) -> np.ndarray:
    """The states' lane lines (``c2 = kappa / 2`` of both on input) bent apart about the centre
    line's curvature ``kappa``: the left line's curvature ``kappa / (1 - s kappa w / 2)``, the
    right one's ``kappa / (1 + s kappa w / 2)``, ``w`` the lane width, ``s`` = ``split`` (one
    per state, or one for all). ``s = 1``: concentric (y to the left: a left bend, kappa > 0,
    has the left line inside)."""
    out = states.copy()
    kappa = 2.0 * states[:, C0L + 2]
    half = 0.5 * (states[:, C0L] - states[:, C0R]) * split
    out[:, C0L + 2] = 0.5 * kappa / (1.0 - kappa * half)
    out[:, C0R + 2] = 0.5 * kappa / (1.0 + kappa * half)
    return out


def _straightened(states: torch.Tensor) -> torch.Tensor:
    out = states.clone()
    out[:, C0L + 2] = 0.0
    out[:, C0R + 2] = 0.0
    return out


def _n_plain_and_bend(config: LateralRefitConfig) -> tuple[int, int]:
    """How many of a batch's first half (the envelope states) are on the envelope's own lanes
    (first; the lane terms act on them) and how many on the tighter bends (after them)."""
    half = config.batch // 2
    n_bend = round(config.bend_share * half)
    return half - n_bend, n_bend


def _draw_batch(config: LateralRefitConfig, data: torch.Tensor, model: PlannerMLP,
                rng: np.random.Generator, gen: torch.Generator) -> torch.Tensor:
    """One batch of states: envelope states (the bend states last), then data states."""
    n_plain, n_bend = _n_plain_and_bend(config)
    half = n_plain + n_bend
    env = torch.as_tensor(np.concatenate([sample_states(n_plain, rng),
                                          _bend_states(n_bend, rng, config)]),
                          dtype=torch.float32)
    rows = torch.randint(len(data), (config.batch - half,), generator=gen)
    return _with_style(torch.cat([env, data[rows]]), model, rng)


def _targets(config: LateralRefitConfig, states: torch.Tensor, ref: PlannerMLP,
             pred: torch.Tensor) -> torch.Tensor:
    seen = states[:, :N_FEATURES]
    if config.straight_reference:
        seen = _straightened(seen)
    return lateral_targets(states, ref(seen), pred[..., 0], config.n_tau, seen)


def _fresh_lateral_tower(model: PlannerMLP, ref: PlannerMLP, data: torch.Tensor,
                         config: LateralRefitConfig, n_batches: int = 8) -> None:
    """Re-initialise the lateral tower (seeded; ``nn.Linear``'s rule on the tower's own fan-in,
    zero y outputs: the plan starts straight ahead) and rescale the lane features and y outputs
    to the refit's own states and targets (``n_batches`` batches of them, drawn from a stream of
    their own). The lane features feed only the lateral tower, so the x plan is unchanged."""
    rng = np.random.default_rng([config.seed, 6])
    gen = torch.Generator().manual_seed(config.seed + 1)
    with torch.no_grad():
        states = torch.cat([_draw_batch(config, data, model, rng, gen) for _ in range(n_batches)])
        targets = _targets(config, states, ref, model(states))
        lane = list(LANE_FEATURES)
        model.feature_mean[lane] = states[:, lane].mean(dim=0)
        model.feature_std[lane] = states[:, lane].std(dim=0)
        y = list(Y_OUTPUTS)
        lane_mode = model.lateral_mode == "lane"  # the y outputs are z: tanh's own scale
        model.output_mean[y] = 0.0 if lane_mode else targets.mean(dim=0)
        model.output_std[y] = 1.0 if lane_mode else targets.std(dim=0)
        linears = [m for m in model.net if isinstance(m, torch.nn.Linear)]
        rows = tower_rows(model.hidden, "lateral")
        fan_in = [model.n_features] + [h // 2 for h in model.hidden]
        for j, (layer, row) in enumerate(zip(linears, rows, strict=True)):
            lateral = torch.as_tensor(row, dtype=torch.bool)
            if j == len(linears) - 1:
                layer.weight[lateral] = 0.0
                layer.bias[lateral] = 0.0
                continue
            bound = 1.0 / fan_in[j] ** 0.5
            shape = (int(lateral.sum()), layer.weight.shape[1])
            layer.weight[lateral] = (2.0 * torch.rand(shape, generator=gen) - 1.0) * bound
            layer.bias[lateral] = (2.0 * torch.rand(shape[0], generator=gen) - 1.0) * bound
            layer.weight.mul_(getattr(model, f"mask_{j}"))  # no weight across the towers


def refit_lateral(config: LateralRefitConfig, init: str | Path, reference: str | Path,
                  data_paths: Sequence[str | Path], out: str | Path,
                  progress: bool = False) -> RefitResult:
    """Refit the lateral tower of the towers checkpoint ``init`` to the targets of
    :func:`lateral_targets` from the checkpoint ``reference`` (a 9-input planner, e.g.
    ``safeil_openloop``) on envelope states and the states of the Tuples files ``data_paths``,
    and write the checkpoint ``out`` (a prefix) with ``init``'s name, horizon, configs and
    metrics plus ``lateral_refit``. The x control points are kept exactly. Deterministic for a
    seed (one torch thread while it runs)."""
    init, out = Path(init), Path(out)
    model, meta = load_model(init)
    ref, _ = load_model(reference)
    if not model.towers:
        raise ValueError(f"{init}: not a towers checkpoint (nothing to refit: its lateral plan "
                         "is trained with the longitudinal one)")
    if ref.n_features != N_FEATURES:
        raise ValueError(f"{reference}: the reference must read the paper's 9 features, "
                         f"it reads {ref.n_features}")
    for p in ref.parameters():
        p.requires_grad_(False)
    horizon = float(meta["horizon_s"])
    barrier = TrainConfig.from_dict(meta["train_config"]).barrier
    data = torch.as_tensor(Tuples.concat([Tuples.load(p) for p in data_paths]).features,
                           dtype=torch.float32)
    prev_threads = torch.get_num_threads()
    try:
        torch.manual_seed(config.seed)
        torch.set_num_threads(1)
        rng = np.random.default_rng([config.seed, 5])
        gen = torch.Generator().manual_seed(config.seed)
        opt = torch.optim.Adam(model.parameters(), lr=config.lr)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 1.0 - k / config.steps)
        n_plain, _ = _n_plain_and_bend(config)
        start = time.perf_counter()
        log = []
        model.train()
        if config.lateral_mode == "lane":
            model.lateral_mode = "lane"
            model.lane_keep_m = 0.5 * barrier.track + config.lane_clearance_m
        if config.fresh_tower:
            _fresh_lateral_tower(model, ref, data, config)
        for _ in tqdm(range(config.steps), disable=not progress, desc="lateral refit"):
            states = _draw_batch(config, data, model, rng, gen)
            pred = model(states)
            with torch.no_grad():
                target = _targets(config, states, ref, pred)
            fit = (pred[..., 1] - target).pow(2).sum(dim=-1).mean()
            lane = envelope_terms(states[:n_plain], pred[:n_plain], horizon, barrier,
                                  lane_by_steering=True)[1]
            loss = fit + config.lane_weight * lane
            opt.zero_grad(set_to_none=True)
            loss.backward()
            keep_only_tower_gradients(model, "lateral")
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            sched.step()
            log.append({"fit_m2": float(fit.detach()), "lane": float(lane.detach()),
                        "loss": float(loss.detach())})
        model.eval()
        seconds = time.perf_counter() - start
    finally:
        torch.set_num_threads(prev_threads)
    last = {k: float(np.mean([row[k] for row in log[-100:]])) for k in log[-1]}
    metrics = {**meta.get("metrics", {}), "lateral_refit": {
        "init": str(init), "reference": str(reference), **asdict(config), "seconds": seconds,
        "first": log[0], "last_100_mean": last}}
    save_checkpoint(out, model, name=meta["name"], horizon=horizon,
                    train_config=meta["train_config"],
                    data_fingerprint=meta.get("data_fingerprint"), metrics=metrics,
                    style_default=meta.get("style_default"))
    return RefitResult(out, metrics)
