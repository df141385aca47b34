"""One scenario per episode as a ``gymnasium.Env`` (docs/gymnasium.md)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np

from safeil_sumo.core.policy import PLAN_HORIZON_S, PLAN_RATE_HZ
from safeil_sumo.envs import base
from safeil_sumo.envs import spaces as sp
from safeil_sumo.envs.tasks import make_task
from safeil_sumo.sim.loop_types import Rollout
from safeil_sumo.sim.stepper import LIMIT_REASONS, TERMINAL_REASONS, ClosedLoop, Observation
from safeil_sumo.sim.sumo_api import has_display
from safeil_sumo.sim.vehicle import VehicleParams


class SafeILEnv(gym.Env):
    """The closed loop of one task's scenario, one decision (``1 / plan_rate_hz``) per step.

    ``task`` and ``task_options`` (``net``, ``master_seed``, ``max_time_s``, ``profile``,
    ScenarioSpec fields): :func:`safeil_sumo.envs.tasks.make_task`. ``action_level``:
    ``"plan"`` (B-spline control points, tracked) or ``"control"`` (acceleration, steering).
    ``horizon_s`` [s]: the plans' horizon. ``reward``: a :class:`RewardConfig` or a dict of its
    terms. ``out_of_space``: ``"clip"`` or ``"raise"``. ``step_s`` [s], ``plan_rate_hz`` [Hz],
    ``stop_on_flag``, ``backend``, ``brake_guard``: the loop's settings. ``render_mode``: None,
    ``"rgb_array"`` (:meth:`render` draws the animation's frame) or ``"human"`` (sumo-gui shows
    the episode as it runs, following the ego; it needs a display and runs SUMO through traci,
    whatever ``backend`` says; :meth:`render` does nothing). Without a display ``"human"`` is
    refused and not listed in the instance's ``metadata["render_modes"]``.

    ``style``: the driver the agent should imitate, ``{"time_gap_s": T, "standstill_m": s0}``
    [s, m] (:func:`~safeil_sumo.envs.base.check_style`), the steady gap's line ``s0 + T v``;
    while one is set its gap at the step's end is ``info["style_gap"]`` (no such key without
    one: Gymnasium's env checker compares infos, and NaN equals nothing) and
    :attr:`RewardConfig.style_gap_per_m2` rewards keeping it. ``reset(options={"style": ...})``
    or :meth:`set_style` changes it (None: no style). The agent plans: the style changes no
    part of the loop.
    """

    # gymnasium's Env declares metadata an instance attribute whose default is the class's
    # (gymnasium.make reads it from the class, and __init__ narrows it per instance)
    metadata: dict[str, Any] = {  # noqa: RUF012
        "render_modes": ["human", "rgb_array"], "render_fps": 10}

    def __init__(self, task: str = "curved500", action_level: str = "plan",
                 horizon_s: float = PLAN_HORIZON_S, reward: sp.RewardConfig | dict | None = None,
                 out_of_space: str = "clip", render_mode: str | None = None,
                 step_s: float = 0.01, plan_rate_hz: float = PLAN_RATE_HZ,
                 stop_on_flag: bool = False,
                 backend: str = "libsumo", brake_guard: bool = True,
                 style: dict | None = None, **task_options) -> None:
        self._style = base.check_style(style)  # (T [s], s0 [m]) or None
        if not has_display():  # Gymnasium's check_env makes an env of every mode listed
            self.metadata = {**self.metadata, "render_modes": ["rgb_array"]}
            if render_mode == "human":
                raise ValueError("render_mode='human' shows the episode in sumo-gui, which needs "
                                 "a display (DISPLAY is not set): use render_mode='rgb_array', "
                                 "or run under a virtual display (xvfb-run -a)")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or one of "
                             f"{self.metadata['render_modes']}, got {render_mode!r}")
        if out_of_space not in sp.OUT_OF_SPACE:
            raise ValueError(f"out_of_space must be one of {sp.OUT_OF_SPACE}, got "
                             f"{out_of_space!r}")
        if not (np.isfinite(horizon_s) and horizon_s > 0):
            raise ValueError(f"horizon_s must be > 0 s, got {horizon_s}")
        self.task = make_task(task, **task_options)
        self.action_level = action_level
        self.vehicle = VehicleParams()
        self.observation_space = sp.observation_space()
        self.action_space: gym.spaces.Box = sp.action_space(action_level, self.vehicle)
        self.reward_config = sp.RewardConfig.of(
            reward, sp.REPLAY_REWARD if self.task.replay else None)
        self.out_of_space, self.horizon_s, self.render_mode = out_of_space, horizon_s, render_mode
        self.loop_config = base.loop_config(step_s, plan_rate_hz, stop_on_flag, backend,
                                           brake_guard)
        if render_mode == "human":  # sumo-gui: a process of its own, reached through traci
            self.loop_config = replace(self.loop_config, gui=True, backend="traci")
        self._loop: ClosedLoop | None = None
        self._obs: Observation | None = None
        self._done = True
        self._reset_once = self._lost = False
        self.index: int | None = None  # the episode's index in its task

    def holds_sumo(self) -> bool:
        return self._loop is not None and not self._done

    def lose_sumo(self) -> None:
        """Another env of this process takes SUMO: the episode ends here."""
        if self._loop is not None:  # it holds SUMO (holds_sumo)
            self._loop.close()
        self._done, self._lost = True, True

    def set_style(self, time_gap_s: float | None, standstill_m: float = 0.0) -> None:
        """The driver's style from the next step on: time gap ``time_gap_s`` [s] and standstill
        distance ``standstill_m`` [m], the steady gap's line ``s0 + T v`` (``info["style_gap"]``
        and the reward's :attr:`~RewardConfig.style_gap_per_m2` term); ``time_gap_s=None``:
        no style."""
        self._style = (None if time_gap_s is None
                       else base.style_values(time_gap_s, standstill_m))

    @property
    def style(self) -> dict[str, float] | None:
        """The style in force, ``{"time_gap_s": T, "standstill_m": s0}`` [s, m], or None."""
        return None if self._style is None else dict(zip(base.STYLE_KEYS, self._style,
                                                         strict=True))

    def _style_gap(self, v: float) -> float | None:
        """The style's gap [m] at ego speed ``v`` [m/s] (None: no style)."""
        if self._style is None:
            return None
        time_gap, standstill = self._style
        return standstill + time_gap * v

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        index = base.check_options(options, self.task.max_index)
        if options and "style" in options:
            self._style = base.check_style(options["style"])
        self.index = index if index is not None else self.task.draw_index(self.np_random)
        scenario = self.task.scenario(self.index)
        base.claim_sumo(self, self.loop_config)
        if self._loop is None:
            self._loop = ClosedLoop(self.loop_config, self.vehicle)
        self._done = True
        self._obs = self._loop.reset([scenario], horizon_s=self.horizon_s)
        self._done, self._reset_once, self._lost = False, True, False
        info = {k: v[0] for k, v in sp.infos(
            self._obs, human_gap=self.task.human_gap_at(self._obs.t),
            style_gap=None if self._style is None else np.array(
                [self._style_gap(float(self._obs.v[0]))])).items()}
        return sp.observe(self._obs.features[0]), info | {"index": self.index}

    def step(self, action):
        if self._lost:
            raise RuntimeError(base.LOST)
        if self._done:
            raise RuntimeError("step after the episode ended (terminated or truncated): call "
                               "reset()" if self._reset_once else "call reset() before step()")
        # an episode runs (not done): reset() made the loop and its observation
        assert self._loop is not None and self._obs is not None
        a = sp.checked_actions(action, self.action_space, self.out_of_space)[None]
        before = float(self._obs.s[0])
        try:
            obs, ev = base.step_loop(self._loop, self.action_level, a)
        except Exception:
            self._done = True
            raise
        self._obs = obs
        # one scenario: floats, not the vector env's (N,) arrays (the same values)
        human_gap = self.task.human_gap_at(obs.t[0])
        style_gap = self._style_gap(float(obs.v[0]))
        reward = self.reward_config.reward_one(before, obs, ev, human_gap, style_gap)
        ended, reason = bool(ev.ended[0]), ev.end_reason[0]
        terminated = ended and reason in TERMINAL_REASONS
        truncated = ended and reason in LIMIT_REASONS
        self._done = terminated or truncated
        info = sp.info_one(obs, ev, human_gap, style_gap)
        return sp.observe_one(obs.features[0]), reward, terminated, truncated, info

    def rollout(self) -> Rollout:
        """The episode's per-step log and summary so far (as ``python -m safeil_sumo.run``'s)."""
        if self._loop is None or not self._reset_once:
            raise RuntimeError("no episode yet: call reset()")
        return self._loop.rollout(0)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._loop is None or not self._reset_once or self.index is None:
            raise RuntimeError("call reset() before render()")
        return base.rgb_frame(self._loop.rollout(0).log, self._obs, 0,
                              self.task.scenario(self.index).road, self.vehicle,
                              f"{self.task.name} #{self.index}")

    def close(self) -> None:
        if self._loop is not None:
            self._loop.close()
        self._done = True
        super().close()
