"""Closed-loop training signal: the planner rolled out behind recorded leaders, differentiably.

Open-loop imitation scores one 5 s plan per state; it cannot see a gap that drifts away over a
minute because each plan regulates the gap a little too weakly. Here the planner drives a
differentiable model of the longitudinal loop for tens of seconds behind the recorded leader of
a human maneuver, and the loss compares the gap and speed it produces with the human's.

The model of the loop (torch, batch of episodes, step ``dt_s``) mirrors the SUMO closed loop's
longitudinal path (:mod:`safeil_sumo.sim.controller`, :mod:`safeil_sumo.sim.vehicle`):

- every step the network plans from the features (the episode's lane lines, ego speed, the
  recorded leader's speed and the simulated gap);
- the tracker commands ``a_cmd = ff * a_ref + kp * (v_ref - v) + ki * integral`` with ``v_ref`` and ``a_ref``
  the plan's speed and acceleration (x only: straight-lane longitudinal), clipped to the
  controller's limits;
- the plant follows ``a_cmd`` with a first-order lag (drive 0.3 s, brake 0.15 s), speed >= 0.

Episodes are windows of the recorded maneuvers resampled to ``dt_s``; the leader keeps its
recorded position (the ego's recorded path plus the recorded gap), so the gap the planner keeps
is what is scored. Pure functions on tensors; :func:`rollout` is the only loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

from safeil_sumo.core.features import FEATURE_NAMES
from safeil_sumo.core.policy import PLAN_HORIZON_S
from safeil_sumo.data.tuples import Tuples
from safeil_sumo.learn.losses import BarrierConfig, envelope_barrier_terms
from safeil_sumo.learn.style import STANDSTILL_GAP_M

V_X, V_LEAD, D_LEAD = (FEATURE_NAMES.index(n) for n in ("v_x", "v_lead", "d_lead"))


@dataclass(frozen=True)
class LoopModel:
    """The differentiable loop's settings (defaults: the SUMO loop's controller and plant).

    dt_s: step and planning period [s]; kp: speed gain [1/s]; ki [1/s^2], integral_limit_m [m],
    integral_band_mps [m/s]: the PID's integral (integrated near the reference only); accel_ff: feed-forward gain [-];
    accel_preview_s: where the plan's acceleration is read [s]; accel_min/max_mps2: command
    limits [m/s^2]; drive_lag_s / brake_lag_s: plant time constants [s].
    """

    dt_s: float = 0.1
    kp: float = 1.5
    ki: float = 0.1
    integral_limit_m: float = 5.0
    integral_band_mps: float = 1.0
    accel_ff: float = 1.0
    accel_preview_s: float = 0.2
    accel_min_mps2: float = -8.0
    accel_max_mps2: float = 3.0
    drive_lag_s: float = 0.3
    brake_lag_s: float = 0.15


@dataclass(frozen=True)
class Episodes:
    """B recorded windows of T steps of ``dt_s`` [s]. All tensors float32.

    lanes: (B, 6) lane-line features (c0l, c1l, c2l, c0r, c1r, c2r) at the window start;
    v_human, gap_human, v_lead, s_lead: (B, T) [m/s, m, m/s, m] the human's speed and bumper
    gap, the leader's speed and position (ego start = 0); maneuver_id: (B,) str;
    style: (B, S) the style inputs of a style-conditioned planner (the driver's preferred time
    gap [s], :mod:`safeil_sumo.learn.style`), or None.
    """

    lanes: torch.Tensor
    v_human: torch.Tensor
    gap_human: torch.Tensor
    v_lead: torch.Tensor
    s_lead: torch.Tensor
    maneuver_id: np.ndarray
    dt_s: float
    style: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.lanes)

    def take(self, idx: np.ndarray) -> Episodes:
        return Episodes(self.lanes[idx], self.v_human[idx], self.gap_human[idx],
                        self.v_lead[idx], self.s_lead[idx], self.maneuver_id[np.asarray(idx)],
                        self.dt_s, None if self.style is None else self.style[idx])

    def with_style(self, style_by_maneuver: dict[str, float]) -> Episodes:
        """The same episodes with a style input per episode, looked up by its maneuver."""
        style = torch.tensor([[style_by_maneuver[m]] for m in self.maneuver_id],
                             dtype=torch.float32)
        return Episodes(self.lanes, self.v_human, self.gap_human, self.v_lead, self.s_lead,
                        self.maneuver_id, self.dt_s, style)


def episodes_from_tuples(tuples: Tuples, window_s: float, stride_s: float, dt_s: float = 0.1,
                         maneuvers: set[str] | None = None) -> Episodes:
    """Windows of ``window_s`` [s] every ``stride_s`` [s] of each maneuver's tuples (the states'
    ego speed, leader speed and gap), resampled to ``dt_s``; ``maneuvers``: only these ids.

    The ego's recorded path is the integral of its speed; the leader's position is that path plus
    the recorded gap. A maneuver shorter than the window gives no episode.
    """
    feats, mids, times = tuples.features, tuples.maneuver_id, tuples.t
    n_steps = round(window_s / dt_s)
    out: dict[str, list] = {k: [] for k in ("lanes", "v", "gap", "vl", "sl", "id")}
    for mid in np.unique(mids):
        if maneuvers is not None and mid not in maneuvers:
            continue
        rows = np.flatnonzero(mids == mid)
        rows = rows[np.argsort(times[rows])]
        t = times[rows] - times[rows[0]]
        if t[-1] < window_s:
            continue
        f = feats[rows]
        grid = np.arange(0.0, t[-1] + 1e-9, dt_s)
        v = np.interp(grid, t, f[:, V_X])
        gap = np.interp(grid, t, f[:, D_LEAD])
        v_lead = np.interp(grid, t, f[:, V_LEAD])
        s_ego = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt_s)])
        s_lead = s_ego + gap
        lane_rows = np.searchsorted(t, grid)
        for k0 in range(0, len(grid) - n_steps, max(1, round(stride_s / dt_s))):
            sl = slice(k0, k0 + n_steps)
            out["lanes"].append(f[min(lane_rows[k0], len(f) - 1), :6])
            out["v"].append(v[sl])
            out["gap"].append(gap[sl])
            out["vl"].append(v_lead[sl])
            out["sl"].append(s_lead[sl] - s_ego[k0])
            out["id"].append(mid)
    if not out["v"]:
        raise ValueError(f"no maneuver is {window_s} s long")

    def tensor(key: str) -> torch.Tensor:
        return torch.as_tensor(np.asarray(out[key]), dtype=torch.float32)

    return Episodes(tensor("lanes"), tensor("v"), tensor("gap"), tensor("vl"), tensor("sl"),
                    np.asarray(out["id"]), dt_s)


def plan_speed_accel(control_points: torch.Tensor, horizon: float, t: float,
                     preview: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The plan's x speed at ``t`` and x acceleration at ``t + preview`` [s] (cubic Bezier with
    the ego at its origin); ``control_points (N, 3, 2)`` [m]. As the SUMO controller's
    ``plan_speed_and_accel`` on x: backward plans mean stop, no acceleration past the horizon."""
    x1, x2, x3 = control_points[:, 0, 0], control_points[:, 1, 0], control_points[:, 2, 0]

    def derivs(tau: float) -> tuple[torch.Tensor, torch.Tensor]:
        u = 1.0 - tau
        dx = 3.0 * (u * u * x1 + 2.0 * u * tau * (x2 - x1) + tau * tau * (x3 - x2))  # X0 = 0
        ddx = 6.0 * (u * (x2 - 2.0 * x1) + tau * (x3 - 2.0 * x2 + x1))
        return dx / horizon, ddx / horizon**2

    v_ref, _ = derivs(min(max(t / horizon, 0.0), 1.0))
    v_ahead, a_ref = derivs(min(max((t + preview) / horizon, 0.0), 1.0))
    if t + preview > horizon:  # past the horizon the plan continues at its final speed
        a_ref = torch.zeros_like(a_ref)
    # each read sees its own time's direction, as the controller's two calls do
    return torch.where(v_ref < 0.0, 0.0, v_ref), torch.where(v_ahead < 0.0, 0.0, a_ref)


def rollout(model: torch.nn.Module, ep: Episodes, loop: LoopModel = LoopModel(),
            horizon: float = PLAN_HORIZON_S, gap_offset_m: torch.Tensor | None = None,
            speed_offset_mps: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Drive every episode with ``model`` (features ``(N, 9)`` -> control points ``(N, 3, 2)``).
    ``gap_offset_m`` / ``speed_offset_mps`` (B,): the ego starts this much farther back / faster
    than the human did (perturbed starts: the planner must bring the gap back).

    Returns (B, T) tensors ``gap`` [m], ``v`` [m/s], ``accel`` [m/s^2] and the plans' leader
    margins ``lead_margin`` (B, T, 3) [m] (leader's predicted position minus each control point's
    x, as the paper's barrier). Step k holds the state at ``k dt`` (step 0: the recorded start).
    """
    b, n = ep.v_human.shape
    dt = ep.dt_s
    v = ep.v_human[:, 0] if speed_offset_mps is None else torch.clamp(
        ep.v_human[:, 0] + speed_offset_mps, min=0.0)
    s = torch.zeros(b) if gap_offset_m is None else -gap_offset_m
    a = torch.zeros(b)
    integral = torch.zeros(b)
    times = torch.arange(1, 4, dtype=torch.float32) * (horizon / 3.0)
    drive_k, brake_k = 1.0 - np.exp(-dt / loop.drive_lag_s), 1.0 - np.exp(-dt / loop.brake_lag_s)
    gaps, speeds, accels, margins = [], [], [], []
    for k in range(n):
        gap = ep.s_lead[:, k] - s
        parts = [ep.lanes, torch.stack([v, ep.v_lead[:, k], gap], dim=1)]
        feats = torch.cat(parts if ep.style is None else [*parts, ep.style], dim=1)
        cp = model(feats)
        margins.append(gap[:, None] + ep.v_lead[:, k, None] * times - cp[..., 0])
        gaps.append(gap)
        speeds.append(v)
        accels.append(a)
        v_ref, a_ref = plan_speed_accel(cp, horizon, 0.5 * dt, loop.accel_preview_s)
        error = v_ref - v
        integral = torch.where(error.abs() < loop.integral_band_mps,
                               torch.clamp(integral + error * dt, -loop.integral_limit_m,
                                           loop.integral_limit_m), integral)
        a_cmd = torch.clamp(loop.accel_ff * a_ref + loop.kp * error + loop.ki * integral,
                            loop.accel_min_mps2, loop.accel_max_mps2)
        a = a + torch.where(a_cmd >= a, drive_k, brake_k) * (a_cmd - a)
        v_next = torch.clamp(v + a * dt, min=0.0)
        s = s + 0.5 * (v + v_next) * dt
        v = v_next
    return {"gap": torch.stack(gaps, 1), "v": torch.stack(speeds, 1),
            "accel": torch.stack(accels, 1), "lead_margin": torch.stack(margins, 1)}


@dataclass(frozen=True)
class ClosedLoopTerms:
    """Named terms of the closed-loop loss (each a scalar tensor)."""

    gap: torch.Tensor  # mean squared gap error to the human [m^2]
    speed: torch.Tensor  # mean squared speed error [m^2/s^2]
    barrier: torch.Tensor  # the paper's leader barrier on the plans of the visited states
    total: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k).detach()) for k in ("gap", "speed", "barrier", "total")}


def closed_loop_loss(out: dict[str, torch.Tensor], ep: Episodes, speed_weight: float = 1.0,
                     barrier_k: float = 1000.0, barrier_weight: float = 0.01,
                     gap_scale_m: float = 1.0) -> ClosedLoopTerms:
    """Gap and speed errors to the human over the rollout, plus the leader barrier
    ``K softplus(-margin)`` on the plans of the states the rollout visits. From a perturbed
    start the errors score how the planner brings the gap back to the human's."""
    gap = ((out["gap"] - ep.gap_human) / gap_scale_m).pow(2).mean()
    speed = (out["v"] - ep.v_human).pow(2).mean()
    barrier = barrier_k * F.softplus(-out["lead_margin"]).sum(-1).mean()
    total = gap + speed_weight * speed + barrier_weight * barrier
    return ClosedLoopTerms(gap, speed, barrier, total)


@dataclass(frozen=True)
class SettlingConfig:
    """Synthetic gap-regulation episodes: a leader at constant speed, the ego started off the
    equilibrium of its time-gap setting; the planner must settle at that equilibrium.

    speed_mps: leader speeds drawn [m/s]; time_gap_s: settings drawn [s]; speed_step_mps: the
    ego starts up to this much slower or faster than the leader [m/s] (the leader has just
    changed speed); far_m: a "far" start is up to this much behind the equilibrium gap [m];
    close_factor: a "close" start is at this fraction of it [-]; settle_after_s: the gap is
    scored from this time on [s] (the transient before is free but for the floor);
    floor_time_gap_s: time gaps below this are penalised all along [s].
    """

    speed_mps: tuple[float, float] = (5.0, 36.0)
    time_gap_s: tuple[float, float] = (0.8, 3.0)
    speed_step_mps: float = 3.0
    far_m: float = 100.0
    close_factor: tuple[float, float] = (0.4, 1.0)
    settle_after_s: float = 30.0
    floor_time_gap_s: float = 0.8


def settling_episodes(n: int, lanes: torch.Tensor, rng: np.random.Generator, window_s: float,
                      dt_s: float = 0.1, cfg: SettlingConfig = SettlingConfig()
                      ) -> tuple[Episodes, torch.Tensor]:
    """``n`` synthetic episodes (lane lines drawn from ``lanes (M, 6)``) and their equilibrium
    gaps ``(n,)`` [m] ``max(T v_lead, STANDSTILL_GAP_M)``. Half start far behind (up to
    ``far_m`` beyond the equilibrium), half close (a fraction of it). The human fields hold the
    equilibrium (gap) and the leader's speed (the start speed first): there is no human."""

    steps = round(window_s / dt_s)
    v_lead = rng.uniform(*cfg.speed_mps, n)
    time_gap = rng.uniform(*cfg.time_gap_s, n)
    gap_eq = np.maximum(time_gap * v_lead, STANDSTILL_GAP_M)
    far = rng.uniform(size=n) < 0.5
    gap0 = np.where(far, gap_eq + rng.uniform(0.0, cfg.far_m, n),
                    np.maximum(gap_eq * rng.uniform(*cfg.close_factor, n), 1.0))
    v0 = np.maximum(v_lead + rng.uniform(-cfg.speed_step_mps, cfg.speed_step_mps, n), 0.0)
    t = np.arange(steps) * dt_s

    def f32(a: npt.ArrayLike) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), dtype=torch.float32)

    v_human = np.repeat(v_lead[:, None], steps, 1)
    v_human[:, 0] = v0  # the rollout starts at the human's first speed
    ep = Episodes(
        lanes=lanes[torch.as_tensor(rng.integers(len(lanes), size=n))],
        v_human=f32(v_human), gap_human=f32(np.repeat(gap_eq[:, None], steps, 1)),
        v_lead=f32(np.repeat(v_lead[:, None], steps, 1)),
        s_lead=f32(gap0[:, None] + v_lead[:, None] * t),
        maneuver_id=np.array(["settling"] * n), dt_s=dt_s, style=f32(time_gap[:, None]))
    return ep, f32(gap_eq)


def settling_loss(out: dict[str, torch.Tensor], gap_eq_m: torch.Tensor, dt_s: float,
                  cfg: SettlingConfig = SettlingConfig()) -> tuple[torch.Tensor, torch.Tensor]:
    """``(settle, floor)`` [m^2]: the mean squared gap error to the equilibrium ``(B,)`` from
    ``cfg.settle_after_s`` on, and the mean squared shortfall below the floor time gap
    ``relu(floor v - gap)`` over the whole rollout."""
    k0 = round(cfg.settle_after_s / dt_s)
    settle = (out["gap"][:, k0:] - gap_eq_m[:, None]).pow(2).mean()
    floor = F.relu(cfg.floor_time_gap_s * out["v"] - out["gap"]).pow(2).mean()
    return settle, floor


def equilibrium_states(states: torch.Tensor, time_gap_s: torch.Tensor) -> torch.Tensor:
    """``states (N, >= 9)`` moved to the equilibrium of a driver with ``time_gap_s (N,)`` [s]:
    the leader at the ego's speed, at the gap ``max(T v, STANDSTILL_GAP_M)``."""
    out = states.clone()
    v = out[:, 6]
    out[:, 7] = v
    out[:, 8] = torch.clamp(time_gap_s * v, min=STANDSTILL_GAP_M)
    return out


def equilibrium_residual(control_points: torch.Tensor, v_x: torch.Tensor,
                         horizon: float) -> torch.Tensor:
    """Mean squared departure [m^2] of the plans' x control points ``(N, 3, 2)`` from driving on
    at the current speed ``v_x (N,)``: zero when a driver at equilibrium keeps its speed. This
    gives the closed loop its fixed point at the preferred gap."""
    times = torch.arange(1, 4, dtype=control_points.dtype) * (horizon / 3.0)
    return (control_points[..., 0] - v_x[:, None] * times).pow(2).mean()


def envelope_terms(features: torch.Tensor, control_points: torch.Tensor, horizon: float,
                   barrier: BarrierConfig, lane_by_steering: bool = False,
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(envelope, lane, leader)`` on envelope states ``features (N, 9+)`` and their plans
    ``(N, 3, 2)``: the envelope barrier (left + right + leader,
    :func:`~safeil_sumo.learn.losses.envelope_barrier_terms`, the open-loop training's), its
    lane part alone (left + right: ``K sum_k softplus(-b_k)`` over the exact Bernstein
    coefficients k = 1..6 of both lateral margins when ``barrier.lateral == "bernstein"``) and
    its leader part, batch means. ``lane_by_steering``: the lane terms pass no gradient to the x
    control points, so the lane is kept by the lateral plan, never by a shorter plan."""
    terms = envelope_barrier_terms(features, control_points, horizon, barrier)
    if lane_by_steering:
        held = torch.stack([control_points[..., 0].detach(), control_points[..., 1]], dim=-1)
        terms = (*envelope_barrier_terms(features, held, horizon, barrier)[:2], terms[2])
    return sum(terms), terms[0] + terms[1], terms[2]


@dataclass(frozen=True)
class FinetuneConfig:
    """Settings of the closed-loop fine-tune (:func:`safeil_sumo.learn.finetune.finetune`; its
    command line ``training/closed_loop_finetune.py`` has one option per field under its own
    name). Each field's meaning and unit is its ``help`` (field
    metadata), the one place it is written. What the fine-tune keeps from the initial
    checkpoint's :class:`~safeil_sumo.learn.trainer.TrainConfig` (barrier, envelope, monotonicity)
    is not repeated here."""

    window: float = field(default=40.0, metadata={"help": "rollout length [s]"})
    stride: float = field(default=10.0, metadata={"help": "between window starts [s]"})
    iters: int = field(default=300, metadata={"help": "optimiser iterations"})
    batch: int = field(default=64, metadata={"help": "episodes per iteration"})
    lr: float = field(default=3e-4, metadata={"help": "Adam learning rate [-]"})
    speed_weight: float = field(default=4.0, metadata={
        "help": "weight of the speed error to the human [s^2] (the gap error's is 1)"})
    lateral_weight: float = field(default=100.0, metadata={
        "help": "weight holding the lateral (y) outputs to the initial model's [-]"})
    anchor_envelope: bool = field(default=True, metadata={
        "help": "hold the lateral outputs to the initial model's on the envelope states too, "
                "not only on the data states (off: the envelope's lane barrier alone shapes "
                "them there)"})
    lane_weight: float = field(default=0.0, metadata={
        "help": "weight of an extra lane barrier on the envelope states: the paper's "
                "K softplus(-b_k) on the exact Bernstein coefficients b_1..b_6 of both lateral "
                "margins of the plan (the envelope barrier's lane terms, "
                "learn/losses.envelope_barrier_terms; added to the envelope weight they already "
                "have) (0: none) [-]"})
    leader_weight: float = field(default=0.0, metadata={
        "help": "weight of an extra leader barrier on the envelope states: the paper's "
                "K softplus(-m) on the leader margins of the plan's control points (the "
                "envelope barrier's leader term again, on top of the envelope weight) (0: none) "
                "[-]"})
    equilibrium_weight: float = field(default=0.0, metadata={
        "help": "weight of the equilibrium term: behind a leader at its own speed at the "
                "preferred gap the plan keeps its speed (learn/style.py) [-]"})
    perturb: float = field(default=0.0, metadata={
        "help": "share of episodes started off the human's state: the gap scaled by a factor in "
                "[0.5, 1.8] and the speed changed by up to 2 m/s; the planner must bring the gap "
                "back (0: none) [-]"})
    settle_weight: float = field(default=0.0, metadata={
        "help": "weight of the settling term: as many synthetic episodes as --batch, a "
                "constant-speed leader and the ego started far behind or too close "
                "(SettlingConfig); the gap is scored against the setting's equilibrium from "
                "--settle-after on, and time gaps below 0.8 s all along (0: none; needs "
                "--style) [-]"})
    settle_after: float = field(default=30.0, metadata={
        "help": "the settling term scores the gap from this time on [s] (at most half the "
                "window)"})
    style: bool = field(default=False, metadata={
        "help": "add the driver's preferred time gap as an input (learn/style.py)"})
    towers: bool = field(default=False, metadata={
        "help": "split the network into a longitudinal tower that never reads the lane lines "
                "and a lateral one (learn/model.split_towers; hidden layers twice as wide): the "
                "plan's length cannot depend on the lane's curvature; only the longitudinal "
                "tower is trained, the lateral plan stays the initial model's exactly"})
    seed: int = field(default=0, metadata={
        "help": "seed of the episodes drawn, the perturbations and the envelope states"})

    def __post_init__(self) -> None:
        if self.settle_weight > 0 and not self.style:
            raise ValueError("settle_weight > 0 needs style: the settling episodes draw the "
                             "time-gap setting")
        if self.lane_weight < 0 or self.leader_weight < 0:
            raise ValueError("lane_weight and leader_weight must be >= 0")
        if not (self.window > 0 and self.stride > 0 and self.iters >= 1 and self.batch >= 1):
            raise ValueError("window and stride must be > 0, iters and batch >= 1")
