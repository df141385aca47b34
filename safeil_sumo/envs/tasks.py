"""What an env's episodes are: an :class:`EnvTask` draws the loop's :class:`Scenario` of an episode.

A task is a :class:`~safeil_sumo.scenarios.spec.ScenarioSpec` template on one road; episode
``index`` is the spec's scenario ``index`` (every draw from ``scenario_seed(master_seed,
index)``), so an env's episode ``index`` is scenario ``index`` of ``python -m safeil_sumo.run`` /
``sweep`` with the same options. ``reset(options={"index": i})`` picks it; otherwise the env's
seeded generator draws it. The road is fixed per task: a vector env's sub-env restarts on its
copy of the road in the one SUMO simulation (:meth:`safeil_sumo.sim.stepper.ClosedLoop.restart`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from safeil_sumo.experiments.suite import FAMILIES, NETS, family_scenario
from safeil_sumo.scenarios.spec import ScenarioSpec, build_scenario, resolve_road
from safeil_sumo.sim.loop_types import Scenario

if TYPE_CHECKING:
    from safeil_sumo.envs.replay_task import ReplayTask

MAX_INDEX = 2**31 - 1  # episode indices drawn in [0, MAX_INDEX)
# leader-response families: the variant is the index (< 1000: the suite's index encodes the
# family and net in its thousands)
FAMILY_VARIANTS = 1000
# the task kinds (the ``task`` argument of the envs)
TASKS = ("curved500", *FAMILIES, "recorded", "n74_traffic", "replay")
# the traffic densities of ``n74_traffic`` (safeil_sumo.sim.traffic.DENSITIES)
TRAFFIC_DENSITIES = ("light", "default", "dense")


@dataclass(frozen=True)
class EnvTask:
    """Episodes of one kind: ``spec`` with its ``index`` replaced per episode."""

    name: str
    spec: ScenarioSpec
    max_index: int = MAX_INDEX  # indices in [0, max_index)
    family: str = ""  # a leader-response family: the index is its variant
    replay: bool = False  # a recorded maneuver's replay (safeil_sumo.envs.replay_task.ReplayTask)

    def scenario(self, index: int) -> Scenario:
        """The loop's scenario of episode ``index``."""
        if not 0 <= index < self.max_index:
            raise ValueError(f"episode index must be in [0, {self.max_index}), got {index}")
        spec = self.spec_of(index)
        return build_scenario(spec, resolve_road(spec.net, spec.route, spec.from_km, spec.to_km,
                                                 spec.lane))

    def spec_of(self, index: int) -> ScenarioSpec:
        if self.family:
            return family_scenario(self.family, self.spec.net, index, self.spec.master_seed,
                                   self.spec.max_time_s or 40.0)
        return replace(self.spec, index=int(index))

    @property
    def traffic(self) -> bool:
        """SUMO's traffic leads (N = 1 only: :func:`safeil_sumo.sim.stepper.check_scope`)."""
        return bool(self.spec.traffic)

    def draw_index(self, rng: np.random.Generator) -> int:
        return int(rng.integers(0, self.max_index))

    def human_gap_at(self, t: np.ndarray) -> np.ndarray | None:
        """The recorded human's gap at ``t`` (replay tasks only): None here."""
        del t  # no recording: no human gap
        return None

    @property
    def net_path(self) -> Path:
        spec = self.spec_of(0)
        return resolve_road(spec.net, spec.route, spec.from_km, spec.to_km, spec.lane).net_path


def make_task(task: str = "curved500", net: str | None = None, master_seed: int = 0,
              max_time_s: float | None = None, profile: str = "", **spec: Any) -> EnvTask | ReplayTask:
    """The task ``task`` (one of :data:`TASKS`):

    - ``curved500``: the paper's safety test (a leader at a constant random speed in [25, 32]
      m/s, 50 m ahead of the ego at 30 m/s; ``net`` default curved500);
    - a leader-response family (``approach``, ``braking``, ``cut_in``, ``stop_and_go``,
      ``accelerating``; ``net`` straight or curved500, default curved500; 40 s);
    - ``recorded``: a recorded human leader (``profile``: ``ngsim``, ``openacc``, or a CSV /
      Parquet profile file or folder of your own; the ego starts as the recorded follower);
    - ``n74_traffic``: the n74 motorway stretch (``from_km``, ``to_km``, ``lane``) among SUMO's
      traffic (``traffic``: ``light``, ``default`` (default) or ``dense``), the leader being
      whichever vehicle SUMO puts ahead of the ego (``python -m safeil_sumo.run --net n74
      --traffic ...``; ``net`` must be n74). N = 1 per SUMO: the native vector env takes
      ``num_envs=1`` only;
    - ``replay``: a recorded maneuver's replay (:func:`safeil_sumo.envs.replay_task.replay_task`:
      ``source``, ``maneuver``, ``start_s``, ``duration_s``, ``data_dir``, sensor noise).

    ``spec``: any other :class:`ScenarioSpec` field (``initial_gap_m``, ``lane_noise_c0_m``,
    ...; not for the families, which fix theirs). ``ValueError`` for an unknown task or field.
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; tasks: {', '.join(TASKS)}")
    if task == "replay":  # a recorded maneuver: its own options (safeil_sumo.envs.replay_task)
        if net is not None or profile:
            raise ValueError("the replay rebuilds the maneuver's own road: no net or profile")
        from safeil_sumo.envs.replay_task import replay_task

        return replay_task(master_seed=master_seed, max_time_s=max_time_s, **spec)
    known = set(ScenarioSpec.__dataclass_fields__) - {"index", "master_seed", "net"}
    unknown = sorted(set(spec) - known)
    if unknown:
        raise ValueError(f"unknown scenario option(s) {unknown}; options: {sorted(known)}")
    if task in FAMILIES:
        if spec:
            raise ValueError(f"the {task} family fixes its scenario; got {sorted(spec)}")
        net = net or "curved500"
        if net not in NETS:
            raise ValueError(f"the leader-response families run on {NETS}, got {net!r}")
        return EnvTask(task, ScenarioSpec(net=net, master_seed=master_seed,
                                       max_time_s=max_time_s or 40.0), FAMILY_VARIANTS, task)
    if task == "n74_traffic":
        if net not in (None, "n74"):
            raise ValueError(f"n74_traffic runs on net 'n74', got {net!r}")
        traffic = spec.pop("traffic", "default")
        if traffic not in TRAFFIC_DENSITIES:
            raise ValueError(f"n74_traffic's traffic must be one of {TRAFFIC_DENSITIES}, got "
                             f"{traffic!r} (no traffic: Curved500-v0 with net='n74')")
        net, spec = "n74", {"traffic": traffic, **spec}
    if task == "recorded":
        spec = {"leader_kind": "recorded", "leader_profile": profile or "ngsim", **spec}
    elif profile:
        raise ValueError("profile (a recorded leader) needs task='recorded'")
    sc = ScenarioSpec(net=net or "curved500", master_seed=master_seed, max_time_s=max_time_s,
                      **spec)
    task_ = EnvTask(task, sc)
    task_.scenario(0)  # a bad net or profile fails here, before any SUMO starts
    return task_
