"""What the single and the vector env share: the loop's settings, the one-SUMO-per-process
guard, the options a reset takes, a driver's style and the rgb_array frame."""

from __future__ import annotations

import math
import weakref
from typing import SupportsFloat

import numpy as np
import pandas as pd

from safeil_sumo.core.policy import PLAN_RATE_HZ
from safeil_sumo.sim.brake_guard import when as brake_guard_when
from safeil_sumo.sim.loop_types import LoopConfig
from safeil_sumo.sim.vehicle import VehicleParams

# reset(options={"index": i}): episode i of the task; {"style": {...}}: a driver's style
RESET_OPTIONS = ("index", "style")
STYLE_KEYS = ("time_gap_s", "standstill_m")  # a style: T [s] and s0 [m] of the line s0 + T v
_OWNER: list = [None]  # a weakref to the env whose SUMO simulation runs in this process


def loop_config(step_s: float = 0.01, plan_rate_hz: float = PLAN_RATE_HZ,
                stop_on_flag: bool = False, backend: str = "libsumo",
                brake_guard: bool = True) -> LoopConfig:
    """The loop's settings (headless; ``LoopConfig`` checks the values). ``brake_guard``: the
    collision-avoidance braking under plan-level actions (docs/brake_guard.md; commands given
    at the control level are never guarded); False: the plans tracked alone."""
    if backend not in ("libsumo", "traci"):
        raise ValueError(f"backend must be 'libsumo' or 'traci', got {backend!r}")
    return LoopConfig(step_s=step_s, plan_rate_hz=plan_rate_hz, stop_on_flag=stop_on_flag,
                      backend=backend, brake_guard=brake_guard_when(brake_guard))


def claim_sumo(env, loop: LoopConfig) -> None:
    """Make ``env`` (whose loop runs with ``loop``) the process's SUMO user. libsumo runs ONE
    simulation per process (a second start silently replaces the first) and sumo-gui uses
    traci's default connection, one too: an env of this process whose simulation still runs
    has it closed (:meth:`lose_sumo`; its next step raises with the reason) before ``env``
    starts its own. A headless traci env has its own connection and SUMO process, shared with
    no one: nothing to claim."""
    if loop.backend == "traci" and not loop.gui:
        return
    other = _OWNER[0]() if _OWNER[0] is not None else None
    if other is not None and other is not env and other.holds_sumo():
        other.lose_sumo()
    _OWNER[0] = weakref.ref(env)


LOST = ("this env's SUMO simulation was closed when another safeil_sumo env in the same process "
        "started one (libsumo runs one simulation per process): call reset(), step many "
        "scenarios in one simulation with gymnasium.make_vec(id, num_envs=N, "
        "vectorization_mode='vector_entry_point'), or give each env its own process "
        "(vectorization_mode='async')")


def step_loop(loop, action_level: str, actions: np.ndarray):
    """One decision step of ``loop`` with ``actions (N, ...)``: plans (``action_level="plan"``)
    or held acceleration/steering commands (``"control"``); its ``(Observation, Events)``."""
    return loop.step(actions) if action_level == "plan" else loop.step(controls=actions)


def check_options(options: dict | None, max_index: int) -> int | None:
    """The episode index of ``reset(options=...)`` (None: draw one)."""
    if not options:
        return None
    if not isinstance(options, dict):
        raise TypeError(f"reset options must be a dict, got {type(options).__name__}")
    unknown = sorted(set(options) - set(RESET_OPTIONS))
    if unknown:
        raise ValueError(f"unknown reset option(s) {unknown}; options: {list(RESET_OPTIONS)}")
    index = options.get("index")
    if index is None:
        return None
    return check_index(index, max_index)


def check_style(style: object) -> tuple[float, float] | None:
    """A driver's style given to an env (its ``style`` option, ``reset(options={"style":
    ...})``): a dict ``{"time_gap_s": T, "standstill_m": s0}`` (s0 0 m if left out) as ``(T
    [s], s0 [m])``, the steady gap's line ``s0 + T v``; None: no style. T in (0, 10] s, s0 in
    :data:`~safeil_sumo.learn.style.STANDSTILL_RANGE_M` (a planner's); ``ValueError`` else
    (``TypeError`` for no dict)."""
    if style is None:
        return None
    if not isinstance(style, dict):
        raise TypeError(f"a style is a dict {{'time_gap_s': T, 'standstill_m': s0}} [s, m] or "
                        f"None, got {style!r}")
    unknown = sorted(set(style) - set(STYLE_KEYS))
    if unknown or "time_gap_s" not in style:
        raise ValueError(f"a style takes time_gap_s [s] and standstill_m [m] (0 if left out), "
                         f"got {sorted(style)}")
    return style_values(style["time_gap_s"], style.get("standstill_m", 0.0))  # checked there


def style_values(time_gap_s: SupportsFloat, standstill_m: SupportsFloat) -> tuple[float, float]:
    """``(time_gap_s [s], standstill_m [m])`` of :meth:`set_style` checked as
    :func:`check_style` checks them."""
    from safeil_sumo.learn.style import STANDSTILL_RANGE_M

    try:
        t, s0 = float(time_gap_s), float(standstill_m)
    except (TypeError, ValueError):
        raise ValueError(f"a style's time gap [s] and standstill distance [m] are numbers, got "
                         f"{time_gap_s!r}, {standstill_m!r}") from None
    if isinstance(time_gap_s, bool) or not (math.isfinite(t) and 0.0 < t <= 10.0):
        raise ValueError(f"a style's time_gap_s must be in (0, 10] s, got {time_gap_s!r}")
    lo, hi = STANDSTILL_RANGE_M
    if isinstance(standstill_m, bool) or not (math.isfinite(s0) and lo <= s0 <= hi):
        raise ValueError(f"a style's standstill_m must be in [{lo:g}, {hi:g}] m, got "
                         f"{standstill_m!r}")
    return t, s0


def check_index(index: object, max_index: int) -> int:
    """An episode index of ``reset(options={"index": ...})``: an int in [0, ``max_index``)."""
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not (
            0 <= index < max_index):
        raise ValueError(f"options['index'] must be an int in [0, {max_index}), got {index!r}")
    return int(index)


def rgb_frame(log: pd.DataFrame, obs, i: int, road, vehicle: VehicleParams, name: str
              ) -> np.ndarray:
    """The animation's frame (``safeil_sumo.experiments.animation.FrameDrawer``) at the latest row of
    scenario ``i``: ``(H, W, 3)`` uint8. Before the first step, a row made of the reset's
    observation (no leader box, no plan)."""
    from safeil_sumo.experiments.animation import Episode, FrameDrawer

    if log.empty:
        d = vehicle.cog_to_front_bumper_m
        x, y, yaw = float(obs.x[i]), float(obs.y[i]), float(obs.yaw[i])
        log = pd.DataFrame([{
            "t": 0.0, "front_x": x + d * math.cos(yaw), "front_y": y + d * math.sin(yaw),
            "yaw": yaw, "v": float(obs.v[i]), "leader_x": math.nan, "leader_y": math.nan,
            "leader_v": float(obs.leader_v[i]), "gap": float(obs.gap[i]),
            "ttc": float(obs.ttc[i]), "d": float(obs.d[i])}])
    drawer = FrameDrawer(Episode(name, log.reset_index(drop=True), road, vehicle.length_m,
                                 vehicle.width_m))
    try:
        drawer.draw(len(log) - 1)
        drawer.fig.canvas.draw()
        # matplotlib types a figure's canvas as the base class; the Agg canvas the drawer's
        # figure has (its backend is Agg) has buffer_rgba
        rgba = drawer.fig.canvas.buffer_rgba()  # type: ignore[attr-defined]
        return np.asarray(rgba)[..., :3].copy()
    finally:
        drawer.close()
