"""Does training work? PPO and TD3 (quick preset, 3 ACs) on env_1 versus a random policy.

Trains each algorithm with `cosim train --preset quick`, then evaluates the best
checkpoint of every AC and a uniform random policy on the SAME held-out seeds
(episodes the training never saw), with collisions not ending the episode, and
prints mean return, DISTANCE and OS (lane violations) per policy.

    python bench/train_env1.py [--algos ppo td3] [--episodes 5] [--out bench/results]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import agents
import cosim
from eval.metrics import episode_metrics
from eval.rollout import RandomPolicy, run_episodes
from eval.train import make_config, train

HELD_OUT_SEEDS = [90_001, 90_002, 90_003, 90_004, 90_005, 90_006, 90_007, 90_008]


def evaluate(policies_for, action_type: str, episodes: int, horizon: int) -> dict:
    env = cosim.parallel_env("env_1", num_agents=3, action_types=action_type,
                             terminate_on_collision=False, horizon=horizon)
    try:
        records = run_episodes(env, policies_for(env), HELD_OUT_SEEDS[:episodes])
    finally:
        env.close()
    m = episode_metrics(records, dt=0.1)
    return {"return": float(m["return"].mean()), "DISTANCE": float(m["DISTANCE"].mean()),
            "OS": float(m["OS"].mean()), "goal": float(m["goal"].mean()),
            "CV": float(m["CV"].mean()), "SPEED": float(m["SPEED"].mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=["ppo", "td3"])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--docs", type=Path, default=None, help="copy convergence plots here")
    parser.add_argument("--steps", type=int, default=None, help="override the quick budget")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="override agent hyperparameters, e.g. buffer_size=50000")
    args = parser.parse_args()
    results = {}
    for algo in args.algos:
        hyper = dict(item.split("=", 1) for item in args.set)
        cfg = make_config(algo, "env_1", "quick", seed=args.seed, steps=args.steps, hyper=hyper)
        t0 = time.monotonic()
        run = train(cfg, args.out, quiet=True)
        minutes = (time.monotonic() - t0) / 60
        ckpts = {f"ac_{k}": agents.load(run / "checkpoints" / f"ac_{k}" / "best.pt") for k in range(3)}
        trained = evaluate(lambda env, c=ckpts: c, cfg.action_type, args.episodes, cfg.horizon)
        rand = evaluate(lambda env: {a: RandomPolicy(env.action_space(a), 7) for a in env.possible_agents},
                        cfg.action_type, args.episodes, cfg.horizon)
        results[algo] = {"trained": trained, "random": rand, "steps": cfg.steps,
                         "train_minutes": round(minutes, 1), "run": str(run)}
        if args.docs:
            args.docs.mkdir(parents=True, exist_ok=True)
            shutil.copy(run / "convergence.png", args.docs / f"convergence_{algo}_env_1.png")
        print(json.dumps({algo: results[algo]}, indent=2), flush=True)
    print("\n| algorithm | steps | train min | policy | mean return | DISTANCE m | OS | goal rate |")
    print("|---|---|---|---|---|---|---|---|")
    for algo, r in results.items():
        for who in ("trained", "random"):
            v = r[who]
            print(f"| {algo} | {r['steps']} | {r['train_minutes']} | {who} | {v['return']:.1f} | "
                  f"{v['DISTANCE']:.1f} | {v['OS']:.3f} | {v['goal']:.2f} |")


if __name__ == "__main__":
    main()
