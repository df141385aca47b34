"""Training loop for SafeIL and its behavioural-cloning baseline (same network, data and loop).

:func:`train` turns tuples into a model; :func:`train_checkpoint` turns Tuples files into a
checkpoint (``training/train.py`` is its command line, ``training/train_shipped_models.py``
calls it with the shipped recipes).

Deterministic on CPU for a seed: ``torch.manual_seed`` for the initial weights, a private
``torch.Generator`` for shuffling, ``torch.use_deterministic_algorithms(True)`` and a fixed
thread count during training (both restored afterwards). Tensors are sliced directly (no
DataLoader): the data are small and the network is tiny, so Python overhead is what costs.
Early stopping watches the total loss on held-out maneuvers; the best-validation weights are
returned.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.checkpoint import save_checkpoint, tuples_fingerprint
from safeil_sumo.learn.envelope import sample_states
from safeil_sumo.learn.inference import load_policy
from safeil_sumo.learn.losses import (
    BarrierConfig,
    LossTerms,
    envelope_barrier_terms,
    safe_loss,
)
from safeil_sumo.learn.model import ACTIVATIONS, OUTPUT_MODES, PlannerMLP
from safeil_sumo.learn.open_loop_metrics import open_loop_metrics
from safeil_sumo.planners.safety_filter import SafeSet

METHODS = ("safeil", "bc")
TERMS = ("imitation", "barrier_left", "barrier_right", "barrier_lead", "total")
ENVELOPE_TERM = "barrier_envelope"
MONOTONE_TERM = "gap_monotone"
MONOTONE_STEP_M = 2.0  # [m] gap increment of the monotonicity pairs
# the open-loop metrics of the saved policy a checkpoint stores, per split
# (``open_loop_<split>_<key>``)
SUMMARY_KEYS = (
    "n", "cp_rmse", "cp_rmse_x", "cp_rmse_y", "ade", "fde", "ade_lateral", "target_fit_ade",
    "min_margin_left_cp", "min_margin_right_cp", "min_margin_lead_cp", "violation_rate_any_cp",
    "min_margin_left_spline", "min_margin_right_spline", "min_margin_lead_spline",
    "violation_rate_any_spline", "hull_gap_rate", "min_margin_left_bern", "min_margin_right_bern",
    "violation_rate_lateral_bern", "target_violation_rate_any_cp",
    "target_violation_rate_lateral_cp", "target_violation_rate_lateral_bern",
    "target_violation_rate_lateral_spline",
)


@dataclass(frozen=True)
class TrainConfig:
    """Training settings. Each field's meaning and unit is its ``help`` (field metadata), the one
    place it is written: ``training/train.py --help`` shows it under ``--<field-name>``. The
    horizon [s] is taken from the data."""

    method: str = field(default="safeil", metadata={
        "help": "safeil (imitation + barrier) or bc (imitation only; barrier logged, not "
                "trained)"})
    hidden: tuple[int, ...] = field(default=(64, 64), metadata={
        "help": "hidden layer widths, e.g. 64,64"})
    activation: str = field(default="tanh", metadata={"help": "hidden-layer activation"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate [-]"})
    weight_decay: float = field(default=0.0, metadata={"help": "Adam L2 weight decay [-]"})
    batch_size: int = field(default=512, metadata={"help": "minibatch size (0 = full batch)"})
    max_epochs: int = field(default=400, metadata={"help": "max epochs"})
    patience: int = field(default=40, metadata={
        "help": "epochs without a validation improvement before stopping"})
    seed: int = field(default=0, metadata={
        "help": "seed of the split, the initial weights and the minibatches"})
    barrier_k: float = field(default=1000.0, metadata={"help": "barrier weight K [-]"})
    track: float = field(default=1.76, metadata={"help": "vehicle track T [m]"})
    gap_min: float = field(default=0.0, metadata={"help": "extra leader margin [m] (0 = paper)"})
    time_gap: float = field(default=0.0, metadata={"help": "extra leader margin [s] (0 = paper)"})
    barrier_samples: int = field(default=0, metadata={
        "help": "also constrain this many points along the spline (0 = paper, control points "
                "only)"})
    barrier_control_points: bool = field(default=True, metadata={
        "help": "constrain the control points (the paper; --no-... needs --barrier-samples > "
                "0)"})
    num_threads: int = field(default=1, metadata={
        "help": "torch CPU threads while training (fixed for determinism)"})
    barrier_lateral: str = field(default="control_points", metadata={
        "help": "lane barrier on the control points (paper) or on the exact Bernstein "
                "coefficients of the margin along the spline (safeil_sumo.learn.losses)"})
    output_mode: str = field(default="absolute", metadata={
        "help": "control points (paper) or x relative to constant-speed motion "
                "(safeil_sumo.learn.model)"})
    longitudinal_only_sources: tuple[str, ...] = field(default=(), metadata={
        "help": "sources whose lateral (y) imitation error is not learned: their lateral "
                "positions do not match their lane features (e.g. openacc's GNSS)"})
    lateral_only_sources: tuple[str, ...] = field(default=(), metadata={
        "help": "sources whose longitudinal (x) imitation error is not learned (e.g. synthetic "
                "drivers: lane keeping on curves, but not human car following)"})
    envelope_weight: float = field(default=0.0, metadata={
        "help": "weight of the barrier on states drawn across the operating envelope "
                "(safeil_sumo.learn.envelope; 0 = paper, SafeIL only)"})
    envelope_batch: int = field(default=256, metadata={"help": "envelope states per minibatch"})
    monotone_weight: float = field(default=0.0, metadata={
        "help": "weight of the gap-monotonicity penalty on the envelope states (a farther "
                "leader must never shorten the plan; needs --envelope-weight > 0)"})
    monotone_margin_m: float = field(default=0.0, metadata={
        "help": "growth [m] of the plan per 2 m of gap asked by the monotonicity penalty (0: "
                "none)"})

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        for name in ("longitudinal_only_sources", "lateral_only_sources"):
            object.__setattr__(self, name, tuple(str(x) for x in getattr(self, name)))
        both = set(self.longitudinal_only_sources) & set(self.lateral_only_sources)
        if both:
            raise ValueError(f"sources {sorted(both)} would teach nothing (longitudinal-only and "
                             "lateral-only)")
        if self.output_mode not in OUTPUT_MODES:
            raise ValueError(f"output_mode must be one of {OUTPUT_MODES}, got {self.output_mode!r}")
        if self.envelope_weight < 0 or self.envelope_batch < 1 or self.monotone_weight < 0:
            raise ValueError("envelope_weight and monotone_weight must be >= 0, envelope_batch >= 1")
        if self.monotone_weight > 0 and not self.envelope_weight > 0:
            raise ValueError("monotone_weight acts on the envelope states: set envelope_weight > 0")
        if self.max_epochs < 1 or self.batch_size < 0 or self.patience < 1:
            raise ValueError("max_epochs and patience must be >= 1, batch_size >= 0")
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"hidden needs layer widths >= 1, got {self.hidden}")
        if not (math.isfinite(self.lr) and self.lr > 0) or not self.weight_decay >= 0:
            raise ValueError(f"lr must be > 0 and weight_decay >= 0, got {self.lr}, "
                             f"{self.weight_decay}")
        if not (math.isfinite(self.track) and self.track > 0) or not self.barrier_k >= 0:
            raise ValueError(f"track must be > 0 and barrier_k >= 0, got {self.track}, "
                             f"{self.barrier_k}")
        if not (self.gap_min >= 0 and self.time_gap >= 0 and self.monotone_margin_m >= 0):
            raise ValueError("gap_min, time_gap and monotone_margin_m must be >= 0")
        if self.seed < 0 or self.num_threads < 1 or self.barrier_samples < 0:
            raise ValueError("seed and barrier_samples must be >= 0, num_threads >= 1")
        _ = self.barrier  # validates the barrier settings

    @property
    def barrier(self) -> BarrierConfig:
        return BarrierConfig(
            k=self.barrier_k, track=self.track, gap_min=self.gap_min,
            time_gap=self.time_gap, n_samples=self.barrier_samples,
            control_points=self.barrier_control_points, lateral=self.barrier_lateral,
        )

    @staticmethod
    def from_dict(d: dict) -> TrainConfig:
        """Inverse of ``dataclasses.asdict`` (e.g. from a checkpoint's JSON)."""
        return TrainConfig(**{**d, "hidden": tuple(d.get("hidden", (64, 64))),
                              "longitudinal_only_sources":
                                  tuple(d.get("longitudinal_only_sources", ())),
                              "lateral_only_sources": tuple(d.get("lateral_only_sources", ()))})


@dataclass(frozen=True)
class TrainHistory:
    """Per-epoch logs and summary of one run.

    epochs: one dict per epoch with ``epoch``, ``train_<term>``, ``val_<term>`` for the terms in
    :data:`TERMS`, and ``seconds`` (wall time since start); best_epoch: epoch of the returned
    weights; best_val: its validation total; seconds: total wall time [s];
    samples_per_s: training samples processed per second; horizon [s];
    stopped_early: patience ran out before max_epochs.
    """

    epochs: tuple[dict[str, float], ...]
    best_epoch: int
    best_val: float
    seconds: float
    samples_per_s: float
    horizon: float
    stopped_early: bool = False


def split_by_maneuver(
    tuples: Tuples,
    val_fraction: float = 0.2,
    seed: int = 0,
    val_maneuvers: list[str] | None = None,
) -> tuple[Tuples, Tuples]:
    """Leave whole maneuvers out: ``(train, val)``.

    ``val_maneuvers`` names them explicitly; otherwise, per source (sorted by name),
    ``round(val_fraction * n_maneuvers)`` (at least 1 when the fraction is > 0 and the source has
    >= 2 maneuvers) are drawn with ``seed``; a single-source set gives the same split as before.
    """
    maneuvers = tuples.maneuvers
    if val_maneuvers is not None:
        unknown = set(val_maneuvers) - set(maneuvers.tolist())
        if unknown:
            raise ValueError(f"unknown maneuver ids: {sorted(unknown)}")
        chosen = np.asarray(sorted(val_maneuvers))
    else:
        # per source (sorted), so every source of a mixed set is held out in proportion
        rng = np.random.default_rng(seed)
        chosen_parts = []
        for src in np.unique(tuples.source.astype(str)):
            ids = np.unique(tuples.maneuver_id[tuples.source.astype(str) == src])
            n_val = round(val_fraction * len(ids))
            if val_fraction > 0 and len(ids) >= 2:
                n_val = min(max(n_val, 1), len(ids) - 1)
            chosen_parts.append(rng.choice(ids, size=n_val, replace=False))
        chosen = np.sort(np.concatenate(chosen_parts)) if chosen_parts else np.array([])
    is_val = np.isin(tuples.maneuver_id, chosen)
    return tuples.subset(~is_val), tuples.subset(is_val)


def _tensors(t: Tuples) -> tuple[torch.Tensor, torch.Tensor]:
    return (
        torch.as_tensor(np.ascontiguousarray(t.features), dtype=torch.float32),
        torch.as_tensor(np.ascontiguousarray(t.control_points), dtype=torch.float32),
    )


def axis_weights(t: Tuples, config: TrainConfig) -> torch.Tensor:
    """Per-tuple weights ``(N, 2)`` of the x and y imitation errors: y is 0 for
    longitudinal-only sources, x is 0 for lateral-only sources."""
    src = t.source.astype(str)
    x = ~np.isin(src, list(config.lateral_only_sources))
    y = ~np.isin(src, list(config.longitudinal_only_sources))
    return torch.as_tensor(np.stack([x, y], axis=1), dtype=torch.float32)


def gap_monotone_penalty(model: PlannerMLP, features: torch.Tensor,
                         step_m: float = MONOTONE_STEP_M, margin_m: float = 0.0) -> torch.Tensor:
    """Mean over states of ``sum_i relu(x_i(gap) - x_i(gap + step) + margin)`` [m]: how much the
    planned x control points shrink when the leader is ``step_m`` farther (0 for a plan monotone
    in gap). A small ``margin_m`` asks for a slight growth, so that the soft penalty leaves no
    shrinking pair between the sampled states either."""
    farther = features.clone()
    farther[:, 8] += step_m  # D_LEAD
    shrink = model(features)[..., 0] - model(farther)[..., 0]
    return torch.relu(shrink + margin_m).sum(dim=1).mean()


def build_model(train: Tuples, config: TrainConfig) -> PlannerMLP:
    """Fresh model for ``config`` (weights from ``config.seed``), scaling from the training data."""
    torch.manual_seed(config.seed)
    model = PlannerMLP(config.hidden, config.activation, config.output_mode, train.horizon)
    model.set_scaling(train.features, train.control_points)
    return model


def evaluate_loss(
    model: PlannerMLP, features: torch.Tensor, targets: torch.Tensor, horizon: float,
    config: TrainConfig, axis_weight: torch.Tensor | None = None,
) -> LossTerms:
    """Full-batch loss terms without gradients."""
    with torch.no_grad():
        return safe_loss(
            features, model(features), targets, horizon, config.barrier,
            apply_barrier=config.method == "safeil", axis_weight=axis_weight,
        )


def train(
    train: Tuples, val: Tuples, config: TrainConfig = TrainConfig(), progress: bool = True
) -> tuple[PlannerMLP, TrainHistory]:
    """Train a planner on ``train``; early-stop on ``val`` (if ``val`` is empty, on the train loss).

    Returns the model with the best-validation weights (eval mode) and the history.
    """
    if len(train) == 0:
        raise ValueError("no training tuples")
    if len(val) and not np.isclose(train.horizon, val.horizon):
        raise ValueError(f"train/val horizons differ: {train.horizon} vs {val.horizon}")
    horizon = float(train.horizon)
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_threads = torch.get_num_threads()
    try:
        torch.use_deterministic_algorithms(True)
        torch.set_num_threads(config.num_threads)
        return _train(train, val, config, horizon, progress)
    finally:
        torch.use_deterministic_algorithms(prev_det)
        torch.set_num_threads(prev_threads)


def _validation_terms(model: PlannerMLP, x_va: torch.Tensor, y_va: torch.Tensor,
                      w_va: torch.Tensor, env_val: torch.Tensor | None, horizon: float,
                      config: TrainConfig) -> dict[str, float]:
    """The validation loss terms of an epoch (``model`` in eval mode); with envelope states
    ``env_val``, also the envelope barrier and the gap-monotone penalty (without its margin),
    both added to the total with their weights."""
    val_terms = evaluate_loss(model, x_va, y_va, horizon, config, w_va).as_floats()
    if env_val is not None:
        with torch.no_grad():
            env_val_term = float(sum(envelope_barrier_terms(env_val, model(env_val), horizon,
                                                            config.barrier)))
            mono_val = float(gap_monotone_penalty(model, env_val))  # without the margin
        val_terms[ENVELOPE_TERM] = env_val_term
        val_terms[MONOTONE_TERM] = mono_val
        val_terms["total"] += (config.envelope_weight * env_val_term
                               + config.monotone_weight * mono_val)
    return val_terms


def _train(
    train: Tuples, val: Tuples, config: TrainConfig, horizon: float, progress: bool
) -> tuple[PlannerMLP, TrainHistory]:
    model = build_model(train, config)
    gen = torch.Generator().manual_seed(config.seed)
    x_tr, y_tr = _tensors(train)
    x_va, y_va = _tensors(val) if len(val) else (x_tr, y_tr)
    w_tr = axis_weights(train, config)
    w_va = axis_weights(val, config) if len(val) else w_tr
    n = len(x_tr)
    batch = n if config.batch_size == 0 else min(config.batch_size, n)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    apply_barrier = config.method == "safeil"
    use_envelope = apply_barrier and config.envelope_weight > 0
    env_rng = np.random.default_rng([config.seed, 1])  # envelope states: their own stream
    env_val = torch.as_tensor(sample_states(4096, np.random.default_rng([config.seed, 2])),
                              dtype=torch.float32) if use_envelope else None

    best_val, best_epoch = float("inf"), 0
    best_state = {k: v.clone() for k, v in model.state_dict().items()}
    epochs: list[dict[str, float]] = []
    start = time.perf_counter()
    bar = tqdm(range(1, config.max_epochs + 1), disable=not progress, desc=config.method)
    stopped_early = False
    for epoch in bar:
        model.train()
        perm = torch.randperm(n, generator=gen)
        sums = dict.fromkeys((*TERMS, ENVELOPE_TERM, MONOTONE_TERM), 0.0)
        n_batches = -(-n // batch)
        env = (torch.as_tensor(sample_states(n_batches * config.envelope_batch, env_rng),
                               dtype=torch.float32) if use_envelope else None)
        for j, lo in enumerate(range(0, n, batch)):
            idx = perm[lo : lo + batch]
            xb = x_tr[idx]
            terms = safe_loss(xb, model(xb), y_tr[idx], horizon, config.barrier, apply_barrier,
                              w_tr[idx])
            loss = terms.total
            if env is not None:
                e = env[j * config.envelope_batch : (j + 1) * config.envelope_batch]
                env_term = sum(envelope_barrier_terms(e, model(e), horizon, config.barrier))
                loss = loss + config.envelope_weight * env_term
                sums[ENVELOPE_TERM] += float(env_term.detach()) * len(idx)
                if config.monotone_weight > 0:
                    mono = gap_monotone_penalty(model, e, margin_m=config.monotone_margin_m)
                    loss = loss + config.monotone_weight * mono
                    sums[MONOTONE_TERM] += float(mono.detach()) * len(idx)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            for name, value in terms.as_floats().items():
                sums[name] += value * len(idx)
        model.eval()
        val_terms = _validation_terms(model, x_va, y_va, w_va, env_val, horizon, config)
        row = {"epoch": float(epoch)}
        row.update({f"train_{k}": v / n for k, v in sums.items()})
        row.update({f"val_{k}": v for k, v in val_terms.items()})
        row["seconds"] = time.perf_counter() - start
        epochs.append(row)
        if val_terms["total"] < best_val:
            best_val, best_epoch = val_terms["total"], epoch
            best_state = {k: v.clone() for k, v in model.state_dict().items()}
        elif epoch - best_epoch >= config.patience:
            stopped_early = True
            break
        bar.set_postfix(train=f"{row['train_total']:.3g}", val=f"{val_terms['total']:.3g}",
                        best=best_epoch, refresh=False)
    bar.close()
    seconds = time.perf_counter() - start
    model.load_state_dict(best_state)
    model.eval()
    history = TrainHistory(
        epochs=tuple(epochs), best_epoch=best_epoch, best_val=best_val, seconds=seconds,
        samples_per_s=n * len(epochs) / seconds, horizon=horizon, stopped_early=stopped_early,
    )
    return model, history


@dataclass(frozen=True)
class TrainedCheckpoint:
    """What :func:`train_checkpoint` wrote: the checkpoint prefix (``<prefix>.safetensors`` and
    ``<prefix>.json``), the metrics stored in it, the training history, and notes on the data
    (tuples, maneuvers, the split, the horizon; one line each) for a command line to print."""

    prefix: Path
    metrics: dict[str, Any]
    history: TrainHistory
    notes: tuple[str, ...]


def train_checkpoint(
    config: TrainConfig,
    data_paths: Sequence[str | Path],
    out: str | Path,
    name: str | None = None,
    *,
    val_fraction: float = 0.2,
    val_maneuvers: Sequence[str] | None = None,
    progress: bool = False,
) -> TrainedCheckpoint:
    """Train ``config`` on the Tuples files ``data_paths`` (concatenated) and write the
    checkpoint ``out`` (a prefix), storing the policy name ``name`` (default: the method).

    Whole maneuvers are left out for early stopping: ``val_maneuvers`` by id, else
    ``val_fraction`` of each source's drawn with ``config.seed`` (:func:`split_by_maneuver`).
    The checkpoint stores the architecture, scaling, config, data fingerprint, the metrics (the
    best epoch's losses, the data, the held-out maneuvers, and the open-loop metrics of the saved
    policy on both splits, :data:`SUMMARY_KEYS`) and the per-epoch history. Deterministic for a
    seed. Raises ValueError for unreadable or empty data and unknown maneuver ids.
    """
    paths = [Path(p) for p in data_paths]
    out = Path(out)
    tuples = Tuples.concat([Tuples.load(path) for path in paths])
    data_label = ",".join(map(str, paths))
    if len(tuples) == 0:
        raise ValueError(f"{data_label}: no tuples to train on")
    val_ids = list(val_maneuvers) if val_maneuvers else None
    tr, va = split_by_maneuver(tuples, val_fraction, config.seed, val_ids)
    note = (f"{data_label}: {len(tuples)} tuples, {len(tuples.maneuvers)} maneuvers; "
            f"train {len(tr)} ({len(tr.maneuvers)}), val {len(va)} ({len(va.maneuvers)}); "
            f"horizon {tuples.horizon:g} s")
    model, history = train(tr, va, config, progress=progress)
    best = history.epochs[history.best_epoch - 1]
    metrics: dict[str, Any] = {
        "best_epoch": history.best_epoch,
        **{k: v for k, v in best.items() if k.startswith(("train_", "val_"))},
        # which maneuvers were held out: a replay can then check "left out of training"
        "data": data_label, "val_maneuvers": sorted(map(str, va.maneuvers))}
    fingerprint = tuples_fingerprint(tuples)

    def save() -> None:
        save_checkpoint(out, model, name=name or config.method, horizon=tuples.horizon,
                        train_config=config, data_fingerprint=fingerprint, metrics=metrics,
                        history=history)

    # save, then evaluate the checkpoint through the numpy policy the closed loop will use
    save()
    policy = load_policy(out)
    safe_set = SafeSet(track=config.track, gap_min=config.gap_min, time_gap=config.time_gap)
    for split, part in (("train", tr), ("val", va)):
        if len(part):
            om = open_loop_metrics(policy, part, safe_set)
            metrics.update({f"open_loop_{split}_{k}": om[k] for k in SUMMARY_KEYS})
    save()
    return TrainedCheckpoint(out, metrics, history, (note,))
