"""N scenarios in ONE SUMO simulation as a native ``gymnasium.vector.VectorEnv``.

``gymnasium.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point")`` builds it: sub-env
``i`` is scenario ``i`` of one :class:`~safeil_sumo.sim.stepper.ClosedLoop` (on its own copy of
the task's road), all stepped at once on the batched loop. Autoreset is Gymnasium 1.x's default,
``NEXT_STEP``: the step after sub-env ``i`` terminated or truncated restarts it (its action is
ignored; reward 0, neither terminated nor truncated, the new episode's first observation) while
the others step (:meth:`ClosedLoop.restart`); if every sub-env ended in the same step, the
next step is one reset of the simulation. Sub-env ``i`` draws its episodes from its own
generator, seeded ``seed + i`` by ``reset(seed=seed)`` (or by a list of seeds), so its
episodes are those of a single env reset with the same seed.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from safeil_sumo.core.policy import PLAN_HORIZON_S, PLAN_RATE_HZ
from safeil_sumo.envs import base
from safeil_sumo.envs import spaces as sp
from safeil_sumo.envs.tasks import make_task
from safeil_sumo.sim.rollout_log import SUMMARY_COLUMNS
from safeil_sumo.sim.stepper import ClosedLoop, Observation
from safeil_sumo.sim.vehicle import VehicleParams


class SafeILVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` sub-envs of one task in one SUMO simulation; the other arguments are
    :class:`~safeil_sumo.envs.single.SafeILEnv`'s (``style``: every sub-env's, kept across
    autoresets; :meth:`set_style` and ``reset(options={"style": ...})`` set all or one).
    ``info`` holds arrays ``(num_envs,)`` (and Gymnasium's ``_<key>`` masks)."""

    # gymnasium's VectorEnv declares metadata an instance attribute whose default is the class's
    # (gymnasium.make_vec reads it from the class)
    metadata: dict[str, Any] = {  # noqa: RUF012
        "render_modes": ["rgb_array"], "render_fps": 10, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, task: str = "curved500", action_level: str = "plan",
                 horizon_s: float = PLAN_HORIZON_S, reward: sp.RewardConfig | dict | None = None,
                 out_of_space: str = "clip", render_mode: str | None = None,
                 step_s: float = 0.01, plan_rate_hz: float = PLAN_RATE_HZ,
                 stop_on_flag: bool = False,
                 backend: str = "libsumo", brake_guard: bool = True,
                 style: dict | None = None, **task_options) -> None:
        first = base.check_style(style)
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) \
                or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if out_of_space not in sp.OUT_OF_SPACE:
            raise ValueError(f"out_of_space must be one of {sp.OUT_OF_SPACE}, got "
                             f"{out_of_space!r}")
        if not (np.isfinite(horizon_s) and horizon_s > 0):
            raise ValueError(f"horizon_s must be > 0 s, got {horizon_s}")
        self.num_envs = int(num_envs)
        # each sub-env's style: time gap [s] and standstill distance [m], NaN: none
        self._time_gap = np.full(self.num_envs, np.nan)
        self._standstill = np.full(self.num_envs, np.nan)
        self._set_styles([first] * self.num_envs)
        self.task = make_task(task, **task_options)
        self.action_level, self.vehicle = action_level, VehicleParams()
        self.single_observation_space = sp.observation_space()
        self.single_action_space: gym.spaces.Box = sp.action_space(action_level, self.vehicle)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        if self.task.traffic and self.num_envs > 1:
            raise ValueError(
                f"{self.task.name}: SUMO's traffic runs one scenario per simulation (its route "
                "files name the original net's edges), so the native vector env takes "
                f"num_envs=1 only, got {self.num_envs}; for more, one process per sub-env: "
                "gymnasium.make_vec(id, num_envs=N, vectorization_mode='async')")
        self.reward_config = sp.RewardConfig.of(
            reward, sp.REPLAY_REWARD if self.task.replay else None)
        self.out_of_space, self.horizon_s, self.render_mode = out_of_space, horizon_s, render_mode
        self.loop = ClosedLoop(base.loop_config(step_s, plan_rate_hz, stop_on_flag, backend,
                                           brake_guard),
                               self.vehicle,
                               log_columns=None if render_mode else SUMMARY_COLUMNS)
        self._rngs = [seeding.np_random(None)[0] for _ in range(self.num_envs)]
        self.indices = np.full(self.num_envs, -1)  # each sub-env's episode index
        self._obs: Observation | None = None
        self._autoreset = np.zeros(self.num_envs, bool)
        self._open = False  # SUMO runs (some scenario has not ended)
        self._lost = False  # another env of the process took SUMO (base.claim_sumo)

    def holds_sumo(self) -> bool:
        return self._open

    def lose_sumo(self) -> None:
        """Another env of this process takes SUMO: every episode ends here."""
        self.loop.close()
        self._open, self._lost = False, True

    def set_style(self, time_gap_s: float | None, standstill_m: float = 0.0,
                  index: int | None = None) -> None:
        """The driver's style of sub-env ``index`` (None: of all) from the next step on: time
        gap ``time_gap_s`` [s] and standstill distance ``standstill_m`` [m], the steady gap's
        line ``s0 + T v`` (``info["style_gap"]`` and the reward's ``style_gap_per_m2`` term);
        ``time_gap_s=None``: no style."""
        style = None if time_gap_s is None else base.style_values(time_gap_s, standstill_m)
        if index is None:
            self._set_styles([style] * self.num_envs)
            return
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not (
                0 <= index < self.num_envs):
            raise ValueError(f"index must be a sub-env in [0, {self.num_envs}) or None (all), "
                             f"got {index!r}")
        self._set_styles([style if i == index else self._style_of(i)
                          for i in range(self.num_envs)])

    @property
    def styles(self) -> list[dict[str, float] | None]:
        """Each sub-env's style, ``{"time_gap_s": T, "standstill_m": s0}`` [s, m], or None."""
        return [None if (st := self._style_of(i)) is None
                else dict(zip(base.STYLE_KEYS, st, strict=True)) for i in range(self.num_envs)]

    def _style_of(self, i: int) -> tuple[float, float] | None:
        t = float(self._time_gap[i])
        return None if np.isnan(t) else (t, float(self._standstill[i]))

    def _set_styles(self, styles: list[tuple[float, float] | None]) -> None:
        for i, st in enumerate(styles):
            self._time_gap[i], self._standstill[i] = st if st is not None else (np.nan, np.nan)

    def _style_gaps(self, obs: Observation) -> np.ndarray:
        """``(num_envs,)`` each style's gap [m] at the ego's speed in ``obs`` (NaN: none)."""
        return sp.style_gaps(self._time_gap, self._standstill, obs.v)

    def reset(self, *, seed: int | list | None = None, options: dict | None = None):
        # the vector env's own generator takes an int seed only (gymnasium's seeding refuses a
        # list, and numpy ints); a list seeds the sub-envs alone, as gymnasium's SyncVectorEnv
        super().reset(seed=int(seed) if isinstance(seed, (int, np.integer)) else None)
        seeds = _seeds(seed, self.num_envs)
        for i, s in enumerate(seeds):
            if s is not None or seed is not None:
                self._rngs[i] = seeding.np_random(s)[0]
        indices = _option_indices(options, self.num_envs, self.task.max_index)
        if options and "style" in options:
            self._set_styles(_option_styles(options["style"], self.num_envs))
        for i in range(self.num_envs):
            self.indices[i] = (indices[i] if indices is not None
                               else self.task.draw_index(self._rngs[i]))
        return self._reset_all()

    def _reset_all(self):
        base.claim_sumo(self, self.loop.loop)
        self._open = False
        scenarios = [self.task.scenario(int(i)) for i in self.indices]
        self._obs = obs = self.loop.reset(scenarios, horizon_s=self.horizon_s)
        self._open, self._autoreset[:], self._lost = True, False, False
        return sp.observe(obs.features), _with_masks(sp.infos(
            obs, human_gap=self.task.human_gap_at(obs.t), style_gap=self._style_gaps(obs)))

    def step(self, actions):
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        if self._lost:
            raise RuntimeError(base.LOST)
        a = sp.checked_actions(actions, self.single_action_space, self.out_of_space,
                               self.num_envs)
        n = self.num_envs
        if self._autoreset.all() or not self._open:  # every sub-env restarts: one reset
            for i in range(n):
                self.indices[i] = self.task.draw_index(self._rngs[i])
            obs, info = self._reset_all()
            return obs, np.zeros(n), np.zeros(n, bool), np.zeros(n, bool), info
        for k in np.flatnonzero(self._autoreset):
            self.indices[k] = self.task.draw_index(self._rngs[k])
            self.loop.restart(int(k), self.task.scenario(int(self.indices[k])),
                              horizon_s=self.horizon_s)
        before = self._obs.s
        try:
            obs, ev = base.step_loop(self.loop, self.action_level, a)
        except Exception:
            self._open = False
            self._autoreset[:] = True
            raise
        self._obs = obs
        self._open = bool(obs.running.any())
        human_gap = self.task.human_gap_at(obs.t)
        style_gap = self._style_gaps(obs)
        rewards = self.reward_config.rewards(before, obs, ev, human_gap, style_gap)
        self._autoreset = ev.ended.copy()
        return (sp.observe(obs.features), rewards, ev.terminated.copy(), ev.truncated.copy(),
                _with_masks(sp.infos(obs, ev, human_gap, style_gap)))

    def render(self):
        if self.render_mode != "rgb_array" or self._obs is None:
            return None
        return tuple(base.rgb_frame(self.loop.rollout(i).log, self._obs, i,
                                    self.task.scenario(int(self.indices[i])).road,
                                    self.vehicle, f"{self.task.name} #{self.indices[i]}")
                     for i in range(self.num_envs))

    def close_extras(self, **kwargs) -> None:
        self.loop.close()
        self._open = False


def _seeds(seed: int | list | None, n: int) -> list[int | None]:
    if seed is None:
        return [None] * n
    if isinstance(seed, (int, np.integer)):
        return [int(seed) + i for i in range(n)]
    seeds = list(seed)
    if len(seeds) != n:
        raise ValueError(f"{n} sub-envs but {len(seeds)} seeds")
    return seeds


def _option_indices(options: dict | None, n: int, max_index: int) -> list[int] | None:
    """``options={"index": [i_0, ..., i_{n-1}]}``: each sub-env's episode (None: drawn)."""
    if not options:
        return None
    unknown = sorted(set(options) - set(base.RESET_OPTIONS))
    if unknown:
        raise ValueError(f"unknown reset option(s) {unknown}; options: {list(base.RESET_OPTIONS)}")
    index = options.get("index")
    if index is None:
        return None
    index = list(np.atleast_1d(index))
    if len(index) != n:
        raise ValueError(f"options['index'] needs {n} indices, got {len(index)}")
    return [base.check_index(int(i), max_index) for i in index]


def _option_styles(style: object, n: int) -> list[tuple[float, float] | None]:
    """``options={"style": ...}``: one style (a dict, or None) for every sub-env, or a list of
    ``n`` (each a dict or None)."""
    if isinstance(style, (list, tuple)):
        if len(style) != n:
            raise ValueError(f"options['style'] needs one style or {n}, got {len(style)}")
        return [base.check_style(st) for st in style]
    return [base.check_style(style)] * n


def _with_masks(info: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Gymnasium's vector info: each key with its ``_key`` mask (every sub-env has each, but
    ``style_gap`` only the sub-envs with a style: NaN and masked out in the others, which, as
    a single env, have no such key)."""
    out = dict(info)
    for k, v in info.items():
        out[f"_{k}"] = np.ones(len(v), bool)
    if "style_gap" in info:
        out["_style_gap"] = ~np.isnan(info["style_gap"])
    return out
