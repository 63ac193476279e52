"""Reference benchmark of the asynchronous trainers: A3C and IMPALA on CartPole-v1.

Target: mean return >= 475 over 20 evaluation episodes within 300k env steps
(all environments counted), with real env worker processes.

Protocol (the figures in docs/agents_async.md come from this script):

* Train with ``train_a3c`` / ``train_impala`` on one vector env of ``--workers``
  environments (worker processes when more than one; A3C: one learner thread per
  environment; IMPALA: one learner acting in all of them), one torch thread.
* Every ``--eval-every`` env steps the parent snapshots the live weights (A3C
  threads keep training meanwhile; the snapshot's step count is the one
  reported) and plays ``--eval-episodes`` greedy episodes on a separate
  CartPole (seeds 10_000+). An evaluation stops early once the target has
  become unreachable (the remaining episodes could not lift the mean to it),
  which only saves time on policies that fail anyway.
* A run succeeds at the first snapshot whose 20-episode mean is >= the target;
  training stops there (unless ``--full-budget``: then it trains on and the
  policy at the end of the budget is evaluated too, to show whether it stays
  solved). A run that never gets there is evaluated once more, fully, at the
  end of its budget.

Usage::

    python bench/agents_async_reference.py                      # both, seeds 0 1 2
    python bench/agents_async_reference.py --algos a3c --seeds 0 --preset paper
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch

from agents import registry

ENV_ID = "CartPole-v1"
EVAL_SEED = 10_000


def evaluate(agent, episodes: int, target: float | None = None, deterministic: bool = True) -> tuple[float, int]:
    """Mean return over ``episodes`` episodes (seeds 10_000+), and episodes played.

    With ``target`` set, stops as soon as the mean can no longer reach it.
    """
    env = gymnasium.make(ENV_ID)
    max_return = env.spec.max_episode_steps
    returns: list[float] = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=EVAL_SEED + episode)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(agent.act(obs, deterministic=deterministic))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        best_possible = (sum(returns) + max_return * (episodes - len(returns))) / episodes
        if target is not None and best_possible < target:
            break
    env.close()
    return float(np.mean(returns)), len(returns)


def snapshot(agent):
    """A frozen copy of ``agent``'s current weights (the live ones keep changing)."""
    copy = type(agent).from_spaces(agent.observation_space, agent.action_space, agent.config)
    copy.model.load_state_dict(agent.model.state_dict())
    return copy


def run(algo: str, seed: int, args) -> dict:
    """Train one (algorithm, seed) with periodic evaluation; return its record."""
    probe = gymnasium.make(ENV_ID)
    spaces = (probe.observation_space, probe.action_space)
    env_fn = functools.partial(gymnasium.make, ENV_ID)
    evals: list[dict] = []
    state = {"next_eval": args.eval_every, "eval_time": 0.0, "solved": None}
    # the catalogue's class and config (the trained agents, live, are the ones built here)
    cls = registry.get_agent_class(algo)
    config = cls.config_class.preset(args.preset)
    agents = {"agent_0": cls.from_spaces(*spaces, config, seed=seed)}
    start = time.monotonic()

    def callback(progress) -> bool:
        if progress.env_steps < state["next_eval"]:
            return False
        state["next_eval"] = progress.env_steps + args.eval_every
        frozen, steps = snapshot(agents["agent_0"]), progress.env_steps
        t0 = time.monotonic()
        mean, played = evaluate(frozen, args.eval_episodes, target=args.target)
        state["eval_time"] += time.monotonic() - t0
        evals.append({"env_steps": steps, "mean_return": mean, "episodes": played,
                      "wall_s": round(t0 - start, 1)})
        print(f"  {algo} seed {seed}: {steps:>7} steps  mean {mean:6.1f} over {played:2d} ep  "
              f"({t0 - start:5.1f} s)", flush=True)
        if played == args.eval_episodes and mean >= args.target and state["solved"] is None:
            state["solved"] = {"env_steps": steps, "wall_s": round(t0 - start, 1), "agent": frozen}
            return not args.full_budget
        return False

    # the catalogue's async training function (train_a3c, train_impala)
    trained = registry.get_async_trainer(algo)(env_fn, *spaces, config=config, total_steps=args.total_steps,
                                               num_envs=args.workers, seed=seed, callback=callback,
                                               agents=agents)
    wall = time.monotonic() - start
    solved = state["solved"]
    final_agent = solved["agent"] if solved and not args.full_budget else snapshot(trained["agent_0"])
    greedy, _ = evaluate(final_agent, args.eval_episodes)
    stochastic, _ = evaluate(final_agent, args.eval_episodes, deterministic=False)
    record = {
        "algo": algo, "seed": seed, "preset": args.preset, "workers": args.workers,
        "config": config.to_dict(),
        "solved": solved is not None,
        "steps_to_target": solved["env_steps"] if solved else None,
        "wall_s_to_target": solved["wall_s"] if solved else None,
        "evaluated_policy": "at target" if solved and not args.full_budget
        else f"after {args.total_steps} steps",
        "eval_greedy_mean": greedy, "eval_stochastic_mean": stochastic,
        "train_wall_s": round(wall, 1), "eval_wall_s": round(state["eval_time"], 1),
        "evals": evals,
    }
    print(f"{algo} seed {seed}: {'SOLVED at ' + str(record['steps_to_target']) if solved else 'NOT solved'}"
          f" steps; greedy {greedy:.1f}, stochastic {stochastic:.1f}; wall {wall:.0f} s", flush=True)
    return record


def markdown(records: list[dict], args) -> str:
    """The results table for docs/agents_async.md."""
    lines = [
        f"| algo | seed | workers | reached {args.target:g} | env steps to target | wall s to target "
        "| evaluated policy | greedy mean (20 ep) | stochastic mean (20 ep) | total wall s (incl. eval) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        lines.append(
            f"| {r['algo']} | {r['seed']} | {r['workers']} | {'yes' if r['solved'] else 'no'} "
            f"| {r['steps_to_target'] if r['solved'] else '-'} | {r['wall_s_to_target'] if r['solved'] else '-'} "
            f"| {r['evaluated_policy']} | {r['eval_greedy_mean']:.1f} | {r['eval_stochastic_mean']:.1f} | {r['train_wall_s']} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=list(registry.ASYNC), choices=registry.ASYNC)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--workers", type=int, default=2, help="environments (env worker processes; A3C: one learner thread each)")
    parser.add_argument("--total-steps", type=int, default=300_000)
    parser.add_argument("--eval-every", type=int, default=10_000)
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--target", type=float, default=475.0)
    parser.add_argument("--preset", default="default", choices=["default", "paper"])
    parser.add_argument("--full-budget", action="store_true",
                        help="train the whole budget; the final evals are of the last policy")
    parser.add_argument("--out", type=Path, default=Path("bench/results/agents_async.json"))
    args = parser.parse_args()

    # One torch thread: the trainer shares the cores with the env workers.
    torch.set_num_threads(1)
    records = [run(algo, seed, args) for algo in args.algos for seed in args.seeds]
    machine = {
        "cpus": os.cpu_count(), "python": platform.python_version(), "torch": str(torch.__version__),
        "load_avg_at_end": os.getloadavg(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                    "machine": machine, "runs": records}, indent=2))
    print(markdown(records, args))
    print(f"machine: {machine}; results in {args.out}")


if __name__ == "__main__":
    main()
