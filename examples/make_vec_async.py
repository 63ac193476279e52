"""``gym.make_vec(..., vectorization_mode="async")`` on a registered cosim id.

Each sub-environment runs in its own worker process (one in-process SUMO each), and
Gymnasium's vector RecordEpisodeStatistics reports finished episodes. Importing
``cosim`` registers the ids (``cosim/Straight-v5`` ... ``cosim/Merge-v5``); keyword
arguments reach each environment's constructor.

    python examples/make_vec_async.py --steps 128 --num-envs 2
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import cosim  # noqa: F401  (registers the cosim/* ids)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=128, help="vector steps")
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--horizon", type=int, default=32, help="steps before truncation")
    args = parser.parse_args()

    envs = gym.make_vec("cosim/Straight-v5", num_envs=args.num_envs, vectorization_mode="async",
                        background=False, pedestrians=False, horizon=args.horizon,
                        reward_scale=0.01)
    envs = gym.wrappers.vector.RecordEpisodeStatistics(envs)
    envs.action_space.seed(0)
    obs, _ = envs.reset(seed=0)
    print(f"{envs.num_envs} async envs, observations {obs.shape} {obs.dtype}")
    returns = []
    for _ in range(args.steps):
        obs, _, _, _, infos = envs.step(envs.action_space.sample())
        if "episode" in infos:
            for i in np.flatnonzero(infos["_episode"]):
                returns.append(float(infos["episode"]["r"][i]))
                print(f"env {i}: episode return {returns[-1]:.2f}, "
                      f"length {int(infos['episode']['l'][i])}")
    envs.close()
    print(f"done: {args.steps} vector steps, {len(returns)} episodes")


if __name__ == "__main__":
    main()
