"""Does learning survive N environments? The ColourBar image task with 1 vs N envs.

Same image configs as bench/agents_image_task.py (docs/agents.md, benchmark 2),
trained through agents.loop.run_loop on N ColourBar copies (worker
processes when N > 1), evaluated every 1,000 env steps (summed over the envs)
on the 18-episode grid; target 90% of the optimum (7.0).

    python bench/vector_image_task.py [--algos ppo dqn td3] [--envs 1 2] [--seed 0]
"""

from __future__ import annotations

import argparse
import functools
import time

import gymnasium
import numpy as np
import torch
from agents_image_task import BUDGETS, CONFIGS, TARGET, grid_score

from agents.envs import ColourBar, SingleAgentParallel
from agents.loop import run_loop
from agents.registry import get_agent_class
from agents.vector import make_vector_env


def colour_bar(continuous: bool) -> SingleAgentParallel:
    return SingleAgentParallel(ColourBar(continuous=continuous))


def run(algo: str, n: int, seed: int, budget: int) -> dict:
    continuous = algo in ("ddpg", "td3")
    probe = ColourBar(continuous=continuous)
    agent = get_agent_class(algo)(probe.observation_space, probe.action_space, CONFIGS[algo], seed=seed)
    curve: list[tuple[int, float]] = []
    eval_time = [0.0]

    last = [0]

    def callback(progress) -> bool:
        step = progress.env_steps
        before, last[0] = last[0], step
        if step // 1000 > before // 1000:
            t0 = time.perf_counter()
            curve.append((step, grid_score(agent, continuous)))
            eval_time[0] += time.perf_counter() - t0
            return curve[-1][1] >= TARGET
        return False

    venv = make_vector_env([functools.partial(colour_bar, continuous) for _ in range(n)])
    t0 = time.perf_counter()
    try:
        run_loop({"agent_0": agent}, venv, total_steps=budget, callback=callback, seed=seed)
    finally:
        venv.close()
    wall = time.perf_counter() - t0 - eval_time[0]
    solved = [s for s, score in curve if score >= TARGET]
    return {"algo": algo, "envs": n, "seed": seed, "solved_at": solved[0] if solved else None,
            "curve": curve, "train_s": wall}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=["ppo", "dqn", "td3"])
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--budget", type=int, default=None, help="env steps (default: the image bench's)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    gymnasium.logger.min_level = 40
    rows = []
    for algo in args.algos:
        for n in args.envs:
            row = run(algo, n, args.seed, args.budget or BUDGETS[algo])
            rows.append(row)
            print(row, flush=True)
    print("\n| algo | envs | seed | steps to target (7.0) | evals (step: score) | train wall s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        curve = ", ".join(f"{s}: {v:.2f}" for s, v in r["curve"])
        print(f"| {r['algo']} | {r['envs']} | {r['seed']} | {r['solved_at'] or 'not solved'} | {curve} | "
              f"{r['train_s']:.0f} |")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
