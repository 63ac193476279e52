"""Greedy (the mode) versus sampled actions for the stochastic-policy algorithms.

    python studies/greedy_vs_sampled.py --runs runs/science_env1/bench/runs --env env_1

For every run of PPO, A3C and IMPALA under ``--runs`` trained in ``--env``: its ``ac_0``
(Scenario 2 drives ac_0's spawn and goal) alone on held-out episode seeds, once taking
the policy's mode and once sampling it (eval.testing.rollout.SampledPolicy). The test protocol
samples these algorithms (eval.testing.protocol.SAMPLED); this is the measurement behind it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import pandas as pd  # noqa: E402

from eval.reporting.report import per_episode  # noqa: E402
from eval.testing import selection  # noqa: E402
from eval.testing.conditions import TestConditions  # noqa: E402
from eval.testing.loading import drive, load_for_slot  # noqa: E402
from eval.testing.protocol import SAMPLED  # noqa: E402
from eval.testing.rollout import run_episodes  # noqa: E402
from eval.testing.validity import HELD_OUT_SEED  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=Path, required=True, help="folder of run folders")
    p.add_argument("--env", default="env_1")
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--steps", type=int, default=600)
    args = p.parse_args(argv)
    rows = []
    for run in sorted(args.runs.glob(f"{args.env}__*__*__*")):
        algo, seed = run.name.split("__")[1:3]
        path = selection.checkpoint_of(run, "ac_0")
        if algo not in SAMPLED or path is None:
            continue
        agent = load_for_slot(path, algo)
        env = TestConditions.of(2, args.steps).env(args.env, ["discrete"])
        try:
            for mode, policy in (("greedy", drive(agent)), ("sampled", drive(agent, 0))):
                seeds = [HELD_OUT_SEED + e for e in range(args.episodes)]
                rec = run_episodes(env, {"ac_0": policy}, seeds)
                per = per_episode(rec.assign(env=args.env, scenario=2))
                rows.append({"algorithm": algo, "train_seed": int(seed), "actions": mode,
                             **per[["SPEED", "DISTANCE", "return", "goal"]].mean().round(2).to_dict()})
                print(rows[-1], flush=True)
        finally:
            env.close()
    if not rows:
        print(f"no PPO/A3C/IMPALA run of {args.env} under {args.runs}", file=sys.stderr)
        return 2
    table = pd.DataFrame(rows)
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
