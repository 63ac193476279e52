"""Stable-Baselines3 PPO on the multi-agent env through SuperSuit (parameter sharing).

``pettingzoo_env_to_vec_env_v1`` makes each AC one slot of a vector env and
``concat_vec_envs_v1`` stacks copies of it (it pickles the env: cosim rebuilds a copy
from its constructor arguments). ACs finish at different times, so
``cosim.wrappers.black_death`` keeps a finished AC in the vector with zero
observations until the others are done (SuperSuit's ``black_death_v3`` waits for
every AC to be terminated *and* truncated, which never happens; see cosim/wrappers.py). SB3's VecMonitor writes ``info["episode"]``; cosim's own
summary is ``info["cosim_episode"]``. ``reward_scale=0.01`` keeps the value loss in
the range SB3's defaults expect.

    python examples/sb3_supersuit_ppo.py --steps 256
"""

from __future__ import annotations

import argparse

import supersuit as ss
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecMonitor

import cosim
from cosim.wrappers import black_death


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=256, help="total agent steps to learn from")
    parser.add_argument("--agents", type=int, default=2, help="ACs sharing one policy")
    parser.add_argument("--n-steps", type=int, default=64, help="PPO rollout length per slot")
    args = parser.parse_args()

    env = cosim.parallel_env("env_1", num_agents=args.agents, background=False,
                             pedestrians=False, horizon=64, reward_scale=0.01, seed=0)
    env = black_death(env)
    venv = ss.pettingzoo_env_to_vec_env_v1(env)
    venv = ss.concat_vec_envs_v1(venv, 1, num_cpus=0, base_class="stable_baselines3")
    venv = VecMonitor(venv)
    # no PPO(seed=...): SuperSuit's SB3 wrapper has no seed(); the env was seeded above
    model = PPO("CnnPolicy", venv, n_steps=args.n_steps, batch_size=args.n_steps,
                n_epochs=1, verbose=1)
    model.learn(total_timesteps=args.steps)
    venv.close()
    print(f"done: {model.num_timesteps} steps")


if __name__ == "__main__":
    main()
