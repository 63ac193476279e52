"""Throughput of our PPO, DQN and TD3 against stable-baselines3 on the same image task.

Both libraries train on :class:`agents.envs.ColourBar` (84x84x3 uint8) for the
same env-step budget with the same schedule, minibatch size and network sizes
(Nature CNN; PPO: shared CNN + linear heads; DQN: CNN + linear Q head (ours
adds the one-unit dueling value stream); TD3: ONE CNN shared by the actor's
[256, 256] head and two [256, 256] Q heads: SB3's ``share_features_extractor=True``
(there the actor loss trains the CNN, in ours the critic loss does), with
target networks, policy delay 2 and target noise 0.2 in both), on one CPU thread. Reported: env steps
per second over the whole run (acting + learning) and gradient updates per
second inside the learning phase. stable-baselines3 is a bench-only extra
(``pip install stable-baselines3``), never a runtime dependency.

Usage::

    python bench/agents_vs_sb3.py --algos ppo dqn td3 --repeats 1
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch

from agents.dqn import DQN, DQNConfig
from agents.envs import ColourBar, SingleAgentParallel
from agents.loop import run_loop
from agents.ppo import PPO, PPOConfig
from agents.td3 import TD3, TD3Config

BUDGET = {"ppo": 2048, "dqn": 3000, "td3": 1000}
# Small, so both libraries act with their networks for most of the run (SB3 acts
# uniformly at random before learning_starts; ours follows its epsilon schedule).
LEARNING_STARTS = 200
BATCH = {"ppo": 64, "dqn": 32, "td3": 32}


@dataclass
class Throughput:
    """One library's measurement on one algorithm."""

    library: str
    algo: str
    env_steps: int
    gradient_updates: int
    wall_time_s: float
    learn_time_s: float

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / self.wall_time_s

    @property
    def updates_per_s(self) -> float:
        return self.gradient_updates / self.learn_time_s


class _Timer:
    """Wraps a bound method, counting calls and the time spent inside it."""

    def __init__(self, owner, name: str):
        self.calls, self.seconds = 0, 0.0
        self._inner = getattr(owner, name)
        setattr(owner, name, self)

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self._inner(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start
            self.calls += 1


def ours(algo: str, seed: int = 0, budget: int | None = None) -> Throughput:
    """Train our agent for the budget; time the whole run and the gradient steps."""
    continuous = algo == "td3"
    env = ColourBar(continuous=continuous)
    if algo == "ppo":
        agent = PPO.from_spaces(env.observation_space, env.action_space,
                                PPOConfig(rollout_steps=512, batch_size=BATCH[algo], epochs=4), seed=seed)
    elif algo == "dqn":
        agent = DQN.from_spaces(env.observation_space, env.action_space, DQNConfig(
            batch_size=BATCH[algo], buffer_size=10_000, learning_starts=LEARNING_STARTS, train_freq=4,
            gradient_steps=1, target_update_interval=500, learning_rate=1e-4, double_q=False,
            # SB3's schedule: epsilon 1 -> 0.05 over the first 10% of the run (random actions skip the network)
            exploration_steps=BUDGET[algo] // 10, exploration_final_eps=0.05), seed=seed)
    else:
        agent = TD3.from_spaces(env.observation_space, env.action_space, TD3Config(
            batch_size=BATCH[algo], buffer_size=10_000, learning_starts=LEARNING_STARTS, train_freq=1),
            seed=seed)
    # Time the whole learning phase (update(): GAE / replay sampling + gradient steps), as
    # SB3's train() is timed below; update() calls that do not learn return at once.
    timer = _Timer(agent, "update")
    start = time.perf_counter()
    budget = budget or BUDGET[algo]
    run_loop({"agent_0": agent}, SingleAgentParallel(env), budget, seed=seed)
    wall = time.perf_counter() - start
    if algo == "ppo":
        cfg = agent.config
        updates = agent.iterations * cfg.epochs * (cfg.rollout_steps // cfg.batch_size)
    else:
        updates = agent.gradient_updates
    return Throughput("cosim agents", algo, budget, updates, wall, timer.seconds)


def sb3(algo: str, seed: int = 0, budget: int | None = None) -> Throughput:
    """Train stable-baselines3's agent for the same budget and schedule."""
    from stable_baselines3 import DQN as SB3DQN
    from stable_baselines3 import PPO as SB3PPO
    from stable_baselines3 import TD3 as SB3TD3
    from stable_baselines3.common.noise import NormalActionNoise

    continuous = algo == "td3"
    env = ColourBar(continuous=continuous)
    if algo == "ppo":
        model = SB3PPO("CnnPolicy", env, n_steps=512, batch_size=BATCH[algo], n_epochs=4, seed=seed,
                       device="cpu", verbose=0)
        per_train = 4 * 512 // BATCH[algo]
    elif algo == "dqn":
        model = SB3DQN("CnnPolicy", env, batch_size=BATCH[algo], buffer_size=10_000,
                       learning_starts=LEARNING_STARTS, train_freq=4, target_update_interval=500,
                       exploration_fraction=0.1, exploration_final_eps=0.05, policy_kwargs={"net_arch": []}, seed=seed, device="cpu", verbose=0)
        per_train = 1
    else:
        model = SB3TD3("CnnPolicy", env, batch_size=BATCH[algo], buffer_size=10_000,
                       learning_starts=LEARNING_STARTS, train_freq=1,
                       action_noise=NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)),
                       policy_kwargs={"net_arch": {"pi": [256, 256], "qf": [256, 256]},
                                      "share_features_extractor": True}, seed=seed, device="cpu",
                       verbose=0)
        per_train = 1
    timer = _Timer(model, "train")
    start = time.perf_counter()
    model.learn(total_timesteps=budget or BUDGET[algo])
    wall = time.perf_counter() - start
    # SB3 finishes the rollout it is in, so count the steps it really took.
    return Throughput("stable-baselines3", algo, model.num_timesteps, timer.calls * per_train, wall, timer.seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=["ppo", "dqn", "td3"], choices=["ppo", "dqn", "td3"])
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)

    rows = []
    print("| algo | library | env steps | gradient updates | env steps/s | updates/s |")
    print("|---|---|---|---|---|---|")
    for algo in args.algos:
        # Untimed warm-up of both libraries (first-call costs: kernel selection, allocator).
        for run in (ours, sb3):
            run(algo, budget=520 if algo == "ppo" else LEARNING_STARTS + 50)
        for repeat in range(args.repeats):
            # Alternate who goes first, so drifting load from other jobs hits both alike.
            for run in (ours, sb3) if repeat % 2 == 0 else (sb3, ours):
                result = run(algo)
                rows.append(result)
                print(f"| {algo} | {result.library} | {result.env_steps} | {result.gradient_updates} "
                      f"| {result.env_steps_per_s:.1f} | {result.updates_per_s:.1f} |", flush=True)
    print()
    print("| algo | env steps/s ratio (ours / SB3, medians) | updates/s ratio (ours / SB3, medians) |")
    print("|---|---|---|")
    for algo in args.algos:
        mine = [r for r in rows if r.algo == algo and r.library == "cosim agents"]
        theirs = [r for r in rows if r.algo == algo and r.library == "stable-baselines3"]
        steps = np.median([r.env_steps_per_s for r in mine]) / np.median([r.env_steps_per_s for r in theirs])
        updates = np.median([r.updates_per_s for r in mine]) / np.median([r.updates_per_s for r in theirs])
        print(f"| {algo} | {steps:.2f} | {updates:.2f} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump([asdict(r) | {"env_steps_per_s": r.env_steps_per_s, "updates_per_s": r.updates_per_s}
                       for r in rows], fh, indent=1)


if __name__ == "__main__":
    main()
