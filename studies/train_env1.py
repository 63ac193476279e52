"""Does training work? PPO and TD3 (quick preset, 3 ACs) on env_1 versus a random policy.

Trains each algorithm with `cosim train --preset quick`, then evaluates the best
checkpoint of every AC and a uniform random policy on the SAME held-out seeds
(episodes the training never saw), with collisions not ending the episode, and
prints mean return, DISTANCE and OS (lane violations) per policy, over all ACs
and per AC.

    python studies/train_env1.py [--algos ppo td3] [--episodes 5] [--out runs/train_env1]
    python studies/train_env1.py --eval runs/env_1__ppo__1__...   # evaluate finished runs only
    python studies/train_env1.py --algos ppo --lane-weight -5      # train with 10x the lane weight
    python studies/train_env1.py --eval --baselines                 # non-learning references only
    python studies/train_env1.py --algos ppo --jitter 5 0.5 --baselines   # env_1 with spawn jitter
"""

from __future__ import annotations

import argparse
import functools
import json
import shutil
import time
from pathlib import Path

import numpy as np
import yaml

import agents
from cosim.scenario import load_scenario, nets_dir
from eval.testing.conditions import TestConditions
from eval.testing.loading import drive
from eval.testing.metrics import episode_metrics
from eval.testing.rollout import AutopilotPolicy, RandomPolicy, run_episodes
from eval.training.train import DISCRETE_ALGOS, make_config, parse_set, train

HELD_OUT_SEEDS = [90_001, 90_002, 90_003, 90_004, 90_005, 90_006, 90_007, 90_008]
COLUMNS = ["return", "DISTANCE", "OS", "goal", "CV", "CO", "SPEED"]


def evaluate(policies_for, action_type: str, episodes: int, horizon: int, num_agents: int,
             scenario: str = "env_1") -> dict:
    env = TestConditions.of(1, horizon).env(scenario, action_type, num_agents)
    try:
        records = run_episodes(env, policies_for(env), HELD_OUT_SEEDS[:episodes])
    finally:
        env.close()
    m = episode_metrics(records, dt=load_scenario(scenario).dt)
    out = {k: float(m[k].mean()) for k in COLUMNS}
    out["per_ac"] = {aid: {k: round(float(g[k].mean()), 3) for k in ("return", "DISTANCE", "OS")}
                     for aid, g in m.groupby("agent")}
    return out


@functools.cache
def random_reference(action_type: str, episodes: int, horizon: int, num_agents: int, scenario: str) -> dict:
    """The uniform random policy (seed 7), evaluated once per setting and reused."""
    return evaluate(lambda env: {a: RandomPolicy(env.action_space(a), 7) for a in env.possible_agents},
                    action_type, episodes, horizon, num_agents, scenario)


def forward_policy(action_type: str):
    """Full throttle, wheel straight, every step: no camera needed on a straight road."""
    action = 3 if action_type == "discrete" else np.array([1.0, 0.0], np.float32)
    return lambda obs: action


def baselines(episodes: int, scenario: str = "env_1", horizon: int = 300, num_agents: int = 3) -> dict:
    """Non-learning references on the same held-out seeds: random, always-forward, the autopilot."""
    out = {}
    for action_type in ("discrete", "continuous"):
        out[f"random ({action_type})"] = random_reference(action_type, episodes, horizon, num_agents, scenario)
        out[f"forward ({action_type})"] = evaluate(
            lambda env, t=action_type: dict.fromkeys(env.possible_agents, forward_policy(t)),
            action_type, episodes, horizon, num_agents, scenario)
    out["autopilot (privileged)"] = evaluate(
        lambda env: {a: AutopilotPolicy(env, a) for a in env.possible_agents},
        "continuous", episodes, horizon, num_agents, scenario)
    return out


def evaluate_run(run: Path, episodes: int, scenario: str = "env_1") -> dict:
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    action_type = "discrete" if cfg["algo"] in DISCRETE_ALGOS else "continuous"
    n = cfg["agents"]
    # drive(): a checkpoint trained on K stacked frames gets K (its own frame history per AC)
    ckpts = {f"ac_{k}": drive(agents.load(run / "checkpoints" / f"ac_{k}" / "best.pt")) for k in range(n)}
    trained = evaluate(lambda env: ckpts, action_type, episodes, cfg["horizon"], n, scenario)
    rand = random_reference(action_type, episodes, cfg["horizon"], n, scenario)
    return {"algo": cfg["algo"], "steps": cfg["steps"], "trained": trained, "random": rand, "run": str(run)}


def env_1_variant(folder: Path, lane_weight: float | None = None, jitter: list[float] | None = None) -> Path:
    """A copy of env_1's YAML with another lane weight and/or spawn jitter (paths made absolute)."""
    root = nets_dir()
    data = yaml.safe_load((root / "scenarios" / "env_1.yaml").read_text())
    for key in ("net", "additional", "demand"):
        value = data[key]
        absolute = [str((root / "scenarios" / v).resolve()) for v in ([value] if isinstance(value, str) else value)]
        data[key] = absolute[0] if isinstance(value, str) else absolute
    name = "env_1"
    if lane_weight is not None:
        data["reward"]["lane"] = lane_weight
        name += f"_lane{lane_weight:g}"
    if jitter is not None:
        data["spawn_jitter"] = {"heading_deg": jitter[0], "lateral": jitter[1]}
        name += f"_jitter{jitter[0]:g}deg{jitter[1]:g}m"
    data["name"] = name
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{data['name']}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=["ppo", "td3"])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("runs/train_env1"))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--docs", type=Path, default=None, help="copy convergence plots here")
    parser.add_argument("--steps", type=int, default=None, help="override the quick budget")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="override agent hyperparameters, e.g. buffer_size=50000")
    parser.add_argument("--env", default="env_1",
                        help="scenario to TRAIN on (e.g. an env_1 copy with other reward weights); "
                             "evaluation is on env_1 (or its --jitter variant)")
    parser.add_argument("--lane-weight", type=float, default=None,
                        help="train on a copy of env_1 with this lane-keeping weight (paper: -0.5)")
    parser.add_argument("--jitter", nargs=2, type=float, default=None, metavar=("DEG", "METRES"),
                        help="train AND evaluate on env_1 with this spawn jitter (heading, lateral)")
    parser.add_argument("--baselines", action="store_true",
                        help="also evaluate always-forward and the scripted autopilot")
    parser.add_argument("--eval", nargs="*", type=Path, default=None, metavar="RUN_DIR",
                        help="evaluate these finished runs instead of training")
    args = parser.parse_args()
    results = []
    eval_env = "env_1"
    if args.jitter is not None:
        eval_env = str(env_1_variant(args.out, jitter=args.jitter))
    if args.lane_weight is not None or args.jitter is not None:
        args.env = str(env_1_variant(args.out, args.lane_weight, args.jitter))
    if args.eval is not None:
        results = [evaluate_run(run, args.episodes, eval_env) for run in args.eval]
    hyper = parse_set(args.set)
    for algo in [] if args.eval is not None else args.algos:
        # agents=3: this study's figures (task version 1; in git history at 1b59d82, docs/results/2026-11-22-train-env1)
        # were taken with the quick preset's 3 ACs of the
        # time (the preset now trains 6, eval/training/hyperparams/runs.yaml).
        cfg = make_config(algo, args.env, "quick", agents=3, seed=args.seed, steps=args.steps, hyper=hyper)
        t0 = time.monotonic()
        run = train(cfg, args.out, quiet=True)
        minutes = (time.monotonic() - t0) / 60
        result = evaluate_run(run, args.episodes, eval_env)
        result["train_minutes"] = round(minutes, 1)
        results.append(result)
        if args.docs:
            args.docs.mkdir(parents=True, exist_ok=True)
            shutil.copy(run / "convergence.png", args.docs / f"convergence_{algo}_env_1.png")
        print(json.dumps(result, indent=2), flush=True)
    print("\n| algorithm | env steps | train min | policy | mean return | DISTANCE m | OS | goal rate |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        for who in ("trained", "random"):
            v = r[who]
            print(f"| {r['algo']} | {r['steps']:,} | {r.get('train_minutes', '')} | {who} | {v['return']:,.1f} | "
                  f"{v['DISTANCE']:.1f} | {v['OS']:.3f} | {v['goal']:.2f} |")
    if args.baselines:
        for name, v in baselines(args.episodes, eval_env).items():
            print(f"| {name} | | | | {v['return']:,.1f} | {v['DISTANCE']:.1f} | {v['OS']:.3f} | {v['goal']:.2f} |")
    print("\nper AC (trained): return / DISTANCE / OS")
    for r in results:
        cells = [f"{aid}: {v['return']:,.0f} / {v['DISTANCE']:.0f} m / {v['OS']:.2f}"
                 for aid, v in r["trained"]["per_ac"].items()]
        print(f"{r['algo']}: " + "; ".join(cells))


if __name__ == "__main__":
    main()
