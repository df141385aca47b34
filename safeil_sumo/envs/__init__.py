"""Gymnasium environments on the project's closed loop (docs/gymnasium.md).

    import gymnasium as gym
    import safeil_sumo.envs  # registers the ids

    env = gym.make("safeil_sumo/Curved500-v0")
    venv = gym.make_vec("safeil_sumo/Curved500-v0", num_envs=64,
                        vectorization_mode="vector_entry_point")

Every id has a single env (:class:`SafeILEnv`) and a native vector env (:class:`SafeILVectorEnv`,
all sub-envs in one SUMO simulation). ``gym.make("safeil_sumo.envs:safeil_sumo/...")`` imports
the package on the way.
"""

from __future__ import annotations

import gymnasium as gym

from safeil_sumo.envs.single import SafeILEnv
from safeil_sumo.envs.spaces import RewardConfig
from safeil_sumo.envs.vector import SafeILVectorEnv

# id -> the task's arguments (safeil_sumo.envs.tasks.make_task)
IDS: dict[str, dict] = {
    "safeil_sumo/Curved500-v0": {"task": "curved500"},
    "safeil_sumo/Approach-v0": {"task": "approach"},
    "safeil_sumo/Braking-v0": {"task": "braking"},
    "safeil_sumo/CutIn-v0": {"task": "cut_in"},
    "safeil_sumo/StopAndGo-v0": {"task": "stop_and_go"},
    "safeil_sumo/Accelerating-v0": {"task": "accelerating"},
    "safeil_sumo/NGSIMLeader-v0": {"task": "recorded", "profile": "ngsim"},
    "safeil_sumo/OpenACCLeader-v0": {"task": "recorded", "profile": "openacc"},
    # your own leader profiles: gym.make("safeil_sumo/RecordedLeader-v0", profile="my/dir")
    "safeil_sumo/RecordedLeader-v0": {"task": "recorded"},
    # the n74 motorway among SUMO's traffic (N = 1 per SUMO: the vector entry point refuses
    # num_envs > 1; vectorization_mode="async" runs a process per sub-env)
    "safeil_sumo/N74Traffic-v0": {"task": "n74_traffic"},
    # a recorded maneuver's replay, rewarding closeness to the human: gym.make(...,
    # source="openacc", maneuver="auto") (the defaults; safeil_sumo/envs/replay_task.py)
    "safeil_sumo/Replay-v0": {"task": "replay"},
}
# ids that read the shared human recordings (../shared/data)
DATA_IDS = ("safeil_sumo/StopAndGo-v0", "safeil_sumo/NGSIMLeader-v0",
            "safeil_sumo/OpenACCLeader-v0", "safeil_sumo/RecordedLeader-v0",
            "safeil_sumo/Replay-v0")


def register() -> None:
    """Register every id (again: idempotent)."""
    for env_id, kwargs in IDS.items():
        if env_id in gym.registry:
            continue
        gym.register(env_id, entry_point="safeil_sumo.envs.single:SafeILEnv",
                     vector_entry_point="safeil_sumo.envs.vector:SafeILVectorEnv",
                     kwargs=dict(kwargs), disable_env_checker=False)


register()

__all__ = ["DATA_IDS", "IDS", "RewardConfig", "SafeILEnv", "SafeILVectorEnv", "register"]
