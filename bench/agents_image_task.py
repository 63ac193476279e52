"""Image-task benchmark: do PPO, DQN, DDPG and TD3 learn from 84x84x3 pixels?

Task: :class:`agents.envs.ColourBar` (move a coloured bar to the image centre;
Discrete(3) for PPO/DQN, Box(1) for DDPG/TD3; optimal mean return 70/9 = 7.78).
Target: >= 90% of the optimum, measured every ``--eval-every`` steps as the
mean deterministic return over the 9 start positions (2 colours each, 18
episodes), within the env-step budgets in ``BUDGETS``. The configs below are the
default presets with the image-specific changes listed beside them (smaller
minibatches and rollouts, because each Nature-CNN gradient step costs ~35 ms on
one CPU core).

Usage::

    python bench/agents_image_task.py --algos ppo dqn ddpg td3 --seeds 0
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from agents_reference import markdown_table, report, train_until

from agents.ddpg import DDPGConfig
from agents.dqn import DQNConfig
from agents.envs import ColourBar
from agents.ppo import PPOConfig
from agents.td3 import TD3Config

OPTIMUM = ColourBar().optimum
TARGET = 0.9 * OPTIMUM

# Image configs: the default presets with these changes (stated in docs/agents.md).
CONFIGS = {
    "ppo": PPOConfig.preset("default", rollout_steps=512, batch_size=64, epochs=4, ent_coef=0.01),
    "dqn": DQNConfig.preset(
        "default", batch_size=32, buffer_size=20_000, learning_starts=1_000, train_freq=4,
        gradient_steps=1, target_update_interval=500, exploration_steps=5_000,
    ),
    "ddpg": DDPGConfig.preset("default", batch_size=32, buffer_size=20_000, learning_starts=1_000, train_freq=2),
    "td3": TD3Config.preset("default", batch_size=32, buffer_size=20_000, learning_starts=1_000, train_freq=2),
}
BUDGETS = {"ppo": 20_000, "dqn": 10_000, "ddpg": 10_000, "td3": 10_000}


def grid_score(agent, continuous: bool) -> float:
    """Mean deterministic return over the 9 grid starts x 2 colours."""
    env = ColourBar(continuous=continuous)
    returns = []
    for start in range(9):
        for colour_seed in range(2):
            obs, _ = env.reset(seed=colour_seed, options={"start": start})
            total, done = 0.0, False
            while not done:
                obs, reward, terminated, truncated, _ = env.step(agent.act(obs, deterministic=True))
                total += reward
                done = terminated or truncated
            returns.append(total)
    return float(np.mean(returns))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--eval-every", type=int, default=1_000)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"ColourBar optimum {OPTIMUM:.3f}, target (90%) {TARGET:.3f}")

    results = []
    for algo in args.algos:
        continuous = algo in {"ddpg", "td3"}
        for seed in args.seeds:
            result = train_until(
                algo, lambda continuous=continuous: ColourBar(continuous=continuous), BUDGETS[algo], TARGET,
                seed, args.eval_every, 0, config=CONFIGS[algo], task="ColourBar-84x84x3",
                eval_options=lambda agent, continuous=continuous: grid_score(agent, continuous),
            )
            results.append(result)
            print(markdown_table([result]).splitlines()[-1], flush=True)
    report(results, args.json)


if __name__ == "__main__":
    main()
