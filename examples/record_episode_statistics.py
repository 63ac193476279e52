"""Gymnasium's RecordEpisodeStatistics on cosim's single-agent environment.

The wrapper writes ``info["episode"]`` (r, l, t) when an episode ends; cosim's own
per-episode summary sits beside it under ``info["cosim_episode"]`` (unscaled return,
reward terms, event counts, goal reached). Random actions in env_1 (empty straight
avenue) with ``reward_scale=0.01``.

    python examples/record_episode_statistics.py --steps 256
"""

from __future__ import annotations

import argparse

import gymnasium as gym

import cosim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=256, help="environment steps in all")
    parser.add_argument("--horizon", type=int, default=64, help="steps before truncation")
    args = parser.parse_args()

    env = cosim.single_env("env_1", background=False, pedestrians=False,
                           horizon=args.horizon, reward_scale=0.01)
    env = gym.wrappers.RecordEpisodeStatistics(env)
    env.action_space.seed(0)
    env.reset(seed=0)
    episodes = 0
    for _ in range(args.steps):
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        if terminated or truncated:
            stats, summary = info["episode"], info["cosim_episode"]
            print(f"episode {episodes}: return {float(stats['r']):.2f} (scaled), "
                  f"{summary['return']:.1f} (unscaled), length {int(stats['l'])}, "
                  f"goal reached {summary['goal_reached']}")
            episodes += 1
            env.reset()
    env.close()
    print(f"done: {args.steps} steps, {episodes} episodes")


if __name__ == "__main__":
    main()
