"""An algorithm trained with as many ACs as Scenario 1 tests (6) against the same
algorithm trained with the preset's 3, in the science study's test.

    for s in 0 1 2; do cosim train --algo ppo --env env_1 --preset quick --agents 6 --seed $s --out runs/six_acs; done
    python studies/six_acs.py --science runs/science_env1 --runs runs/six_acs --algo ppo

Per training seed k: the science study's Scenario 1 test (eval/testing/protocol.py; rotated
slots, each slot driven by the run's AC trained in it, held-out episode seeds) with
seed k's checkpoints of ``--science``, once as they are (cached there) and once with
``--algo`` replaced by its 6-AC run of seed k under ``--runs``. Prints both rows.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "studies"):  # run as a script from a checkout; studies/science.py
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

import pandas as pd  # noqa: E402
import science  # noqa: E402

from eval.reporting.report import per_episode  # noqa: E402
from eval.scale.benchmark import BenchmarkPlan  # noqa: E402
from eval.testing import selection  # noqa: E402
from eval.testing.protocol import ProtocolPlan  # noqa: E402
from eval.testing.session import TestRequest, run_test  # noqa: E402
from eval.testing.validity import HELD_OUT_SEED  # noqa: E402

COLUMNS = ["return", "goal", "CV", "CO", "OS", "SPEED"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--science", type=Path, required=True, help="a studies/science.py folder")
    p.add_argument("--runs", type=Path, required=True, help="the 6-AC run folders")
    p.add_argument("--algo", default="ppo")
    args = p.parse_args(argv)
    study = json.loads((args.science / "science.json").read_text())
    b, t = study["benchmark"], study["test"]
    (env,) = b["envs"]
    plan = BenchmarkPlan(preset=b["preset"], envs=(env,), algos=tuple(b["algos"]), seeds=b["seeds"])
    rows = []
    for seed in range(plan.seeds):
        runs = sorted(args.runs.glob(f"{env}__{args.algo}__{seed}__*"))
        if not runs:
            continue
        ck = science.checkpoints(plan, args.science / "bench", env, seed)
        base = pd.read_parquet(args.science / "test" / f"{env}__seed{seed}.parquet")
        ck[args.algo] = selection.choose(runs[-1]).path
        cache = args.runs / f"test_{env}__seed{seed}.parquet"
        if not cache.exists():
            pp = ProtocolPlan(envs=(env,), scenarios=(1,), episodes=t["episodes"], steps=t["steps"],
                              seed=HELD_OUT_SEED, agents=len(plan.algos))
            run_test(TestRequest(pp, tuple(plan.algos), checkpoints={env: ck})).records.to_parquet(cache)
        for acs, rec in ((3, base[base.scenario == 1]), (6, pd.read_parquet(cache))):
            per = per_episode(rec)
            per = per[per.algorithm == args.algo]
            rows.append({"algorithm": args.algo, "train_seed": seed, "training ACs": acs,
                         **per[COLUMNS].mean().round(3).to_dict()})
    if not rows:
        print(f"no {args.algo} run of {env} under {args.runs}", file=sys.stderr)
        return 2
    table = pd.DataFrame(rows)
    print(table.to_string(index=False))
    print(table.groupby("training ACs")[COLUMNS].mean().round(3).to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
