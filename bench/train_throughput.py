"""Training throughput per algorithm on env_1 with 3 ACs: env steps/s and env vs learner time.

Each algorithm trains for --steps environment steps with its quick-preset
hyperparameters, learning_starts lowered so learning happens inside the window.
For PPO, DQN, DDPG and TD3 (one process) the loop's own clocks split the time
between the environment (SUMO + cameras), acting and learning. A3C and IMPALA
step their environments in worker processes, so only their overall rate is given.

    python bench/train_throughput.py [--steps 1500]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from eval.train import ALGORITHMS, make_config, train


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--algos", nargs="+", default=list(ALGORITHMS))
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as out:
        for algo in args.algos:
            cfg = make_config(algo, "env_1", "quick", steps=args.steps, seed=3)
            if "learning_starts" in cfg.agent_config:
                cfg.agent_config["learning_starts"] = 200
            t0 = time.monotonic()
            run = train(cfg, Path(out), quiet=True, progress=False)
            wall = time.monotonic() - t0
            state = json.loads((run / "state.json").read_text())
            timing = state.get("timing", {})
            rows.append((algo, args.steps / wall, timing))
            print(algo, round(args.steps / wall, 1), timing, flush=True)
    print("\n| algorithm | env steps/s (3 ACs, wall) | env share | act share | learn share |")
    print("|---|---|---|---|---|")
    for algo, rate, t in rows:
        if t:
            print(f"| {algo} | {rate:.1f} | {t['time/env_fraction']:.0%} | {t['time/act_fraction']:.0%} "
                  f"| {t['time/learn_fraction']:.0%} |")
        else:
            print(f"| {algo} | {rate:.1f} | (in workers) | (in workers) | (learner in parent) |")


if __name__ == "__main__":
    main()
