"""PPO (Stable-Baselines3, the ``rl`` extra) on the native vector env: a short example.

    pip install -c constraints.txt -e ".[rl]"
    python training/ppo_vector_env.py --envs 16 --steps 4096

Trains on ``safeil_sumo/Curved500-v0`` at the controller level (acceleration, steering), all
sub-envs in one SUMO simulation, and prints the mean episode reward of the last rollouts. A
smoke example (a few thousand steps learn little), not a recipe.
"""

from __future__ import annotations

import argparse

import gymnasium as gym

import safeil_sumo.envs  # noqa: F401 - registers the ids


def train(num_envs: int = 16, total_steps: int = 4096, seed: int = 0, n_steps: int = 64,
          env_id: str = "safeil_sumo/Curved500-v0", **env_kwargs):
    """The trained PPO model."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    from safeil_sumo.envs.sb3 import SB3VecEnv

    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                        action_level="control", **env_kwargs)
    env = VecMonitor(SB3VecEnv(venv))
    try:
        model = PPO("MlpPolicy", env, n_steps=n_steps, batch_size=min(64, n_steps * num_envs),
                    seed=seed, verbose=0, device="cpu")
        model.learn(total_timesteps=total_steps)
    finally:
        env.close()
    return model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--steps", type=int, default=4096)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = train(args.envs, args.steps, args.seed)
    rewards = [ep["r"] for ep in model.ep_info_buffer]
    mean = sum(rewards) / len(rewards) if rewards else float("nan")
    print(f"{model.num_timesteps} steps; {len(rewards)} episodes ended, mean reward {mean:.2f}")


if __name__ == "__main__":
    main()
