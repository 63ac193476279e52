"""Reference-task benchmark: do our agents solve the classic control tasks?

Targets (from the issue): PPO and DQN reach a mean return >= 475 over 20
deterministic evaluation episodes on CartPole-v1 within 300k env steps; DDPG and
TD3 reach >= -250 on Pendulum-v1 within 50k env steps. Each run evaluates every
``--eval-every`` steps and stops at the first evaluation that meets the target.

Usage::

    python bench/agents_reference.py                      # all four, seed 0
    python bench/agents_reference.py --algos dqn --seeds 0 1 2 --json out.json

Runs single-threaded (``torch.set_num_threads(1)``) and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field

import gymnasium as gym
import numpy as np
import torch

from agents.envs import SingleAgentParallel
from agents.loop import Progress, evaluate, run_loop
from agents.registry import get_agent_class

TASKS = {
    # algo: (env id, env-step budget, target mean return)
    "ppo": ("CartPole-v1", 300_000, 475.0),
    "dqn": ("CartPole-v1", 300_000, 475.0),
    "ddpg": ("Pendulum-v1", 50_000, -250.0),
    "td3": ("Pendulum-v1", 50_000, -250.0),
}


@dataclass
class RunResult:
    """One training run until the target (or the budget) is reached."""

    algo: str
    task: str
    seed: int
    budget: int
    target: float
    solved: bool = False
    steps_to_target: int | None = None
    final_eval: float = float("nan")
    wall_time_s: float = 0.0
    env_steps_per_s: float = 0.0
    gradient_updates: int = 0
    curve: list[tuple[int, float]] = field(default_factory=list)


def train_until(
    algo: str,
    make_env,
    budget: int,
    target: float,
    seed: int,
    eval_every: int,
    eval_episodes: int,
    config=None,
    task: str = "",
    eval_options=None,
) -> RunResult:
    """Train one agent on ``make_env()`` until its evaluation mean reaches ``target``.

    Args:
        algo: Registered algorithm name.
        make_env: Zero-argument callable returning a Gymnasium env.
        budget: Maximum env steps.
        target: Mean evaluation return that counts as solved.
        seed: Agent and env seed.
        eval_every: Env steps between evaluations.
        eval_episodes: Deterministic episodes per evaluation.
        config: Agent config (default preset if None).
        task: Label for the report.
        eval_options: Optional callable ``evaluate(agent) -> float`` replacing the default evaluation.
    """
    cls = get_agent_class(algo)
    env = SingleAgentParallel(make_env())
    agent = cls.from_spaces(env.observation_space("agent_0"), env.action_space("agent_0"), config, seed=seed)
    result = RunResult(algo, task, seed, budget, target)
    eval_env = SingleAgentParallel(make_env())
    eval_time = 0.0

    def score() -> float:
        if eval_options is not None:
            return eval_options(agent)
        returns = evaluate({"agent_0": agent}, eval_env, eval_episodes, seed=10_000 + seed)
        return float(np.mean(returns["agent_0"]))

    def callback(progress: Progress) -> bool:
        nonlocal eval_time
        step = progress.env_steps
        if step % eval_every != 0:
            return False
        start = time.perf_counter()
        mean = score()
        eval_time += time.perf_counter() - start
        result.curve.append((step, mean))
        result.final_eval = mean
        print(f"  {algo} seed {seed} step {step}: eval {mean:.1f}", flush=True)
        if mean >= target:
            result.solved, result.steps_to_target = True, step
            return True
        return False

    start = time.perf_counter()
    stats = run_loop({"agent_0": agent}, env, budget, callback, seed=seed)
    result.wall_time_s = time.perf_counter() - start - eval_time
    result.env_steps_per_s = stats.env_steps / max(result.wall_time_s, 1e-9)
    result.gradient_updates = int(getattr(agent, "gradient_updates", stats.updates))
    return result


def report(results: list[RunResult], json_path: str | None) -> None:
    """Print the full table; write the results as JSON if a path is given."""
    print()
    print(markdown_table(results))
    if json_path:
        with open(json_path, "w") as fh:
            json.dump([asdict(r) for r in results], fh, indent=1)


def markdown_table(results: list[RunResult]) -> str:
    """Render results as a Markdown table."""
    lines = [
        "| algo | task | seed | target | solved | steps to target | last eval | train wall time (s) | env steps/s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        steps = f"{r.steps_to_target:,}" if r.steps_to_target else f"> {r.budget:,}"
        lines.append(
            f"| {r.algo} | {r.task} | {r.seed} | {r.target:g} | {'yes' if r.solved else 'no'} | {steps} "
            f"| {r.final_eval:.1f} | {r.wall_time_s:.0f} | {r.env_steps_per_s:.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--eval-every", type=int, default=0, help="default: budget / 30")
    parser.add_argument("--json", default=None, help="write the results here as JSON")
    args = parser.parse_args()
    torch.set_num_threads(1)

    results = []
    for algo in args.algos:
        env_id, budget, target = TASKS[algo]
        eval_every = args.eval_every or budget // 30
        for seed in args.seeds:
            result = train_until(
                algo, lambda env_id=env_id: gym.make(env_id), budget, target, seed, eval_every,
                args.eval_episodes, task=env_id,
            )
            results.append(result)
            print(markdown_table([result]).splitlines()[-1], flush=True)
    report(results, args.json)


if __name__ == "__main__":
    main()
