"""Training arms side by side, slot by slot: runs of one algorithm and environment trained
differently (say the grid's cell and the same seed with ``--stall-truncate 50``), compared
where the turning slots fail (issue 27, target 2).

    python studies/arms.py --arm grid=grid27/runs/env_2__dqn__0__bench \\
        --arm stall50=pilot_stall/env_2__dqn__0__20261126-201641 --episodes 6 --out arms

For each arm and slot this writes, from the run's ``episodes.csv`` (training), the episodes
the AC had, its goals, the share of them in the last 20% of the budget, its mean episode
length and the nearest it ended to its goal; and from a test of the run's own ACs together,
each in its own slot with its own selected checkpoint (studies/pilot_task.py ``test_run``:
the test's rules, ``--episodes`` held-out seeds from 10,000, the scenario's horizon in steps), each slot's mean
return and goal rate. Files under ``--out``: ``training.csv``, ``test.csv``,
``records/<arm>.parquet`` (a rerun reuses these: delete one to test that arm again) and
``slots.md``, the table. Results: the stall pilot, task version 3; in git history at 1b59d82, docs/results/2026-11-26-stall-pilot.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

LATE = 0.8
"""A training episode that ended after this share of the run's budget counts as late."""


def parse_arm(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"--arm wants LABEL=RUN_FOLDER, got {text!r}")
    run = Path(path)
    if not (run / "episodes.csv").exists() or not (run / "config.yaml").exists():
        raise argparse.ArgumentTypeError(f"--arm {text}: {run} is not a training run folder "
                                         "(no episodes.csv or config.yaml); pass runs/<dir>")
    return label, run


def training_rows(label: str, run: Path, budget: int) -> pd.DataFrame:
    """Per slot: training episodes, goals, goals in the late part, mean length, nearest end."""
    e = pd.read_csv(run / "episodes.csv")
    late = e["env_step"] > LATE * budget
    g = e.assign(late_goal=e["goal_reached"] & late, late=late).groupby("agent")
    out = pd.DataFrame({
        "episodes": g.size(), "goals": g["goal_reached"].sum().astype(int),
        "late episodes": g["late"].sum().astype(int), "late goals": g["late_goal"].sum().astype(int),
        "mean length": g["length"].mean().round(0),
        "nearest end m": g["distance_to_goal"].min().round(1)})
    return out.reset_index().rename(columns={"agent": "slot"}).assign(arm=label)


def test_rows(label: str, run: Path, episodes: int, out: Path) -> pd.DataFrame:
    """Per slot: mean test return and goal rate of the run's own ACs together."""
    from pilot_task import per_slot, test_run

    from cosim.scenario import load_scenario
    from eval.training.runfolder import load_run_config

    cached = out / "records" / f"{label}.parquet"
    if cached.exists():
        records = pd.read_parquet(cached)
    else:
        cfg = load_run_config(run)
        records = test_run(run, cfg.algo, episodes, load_scenario(cfg.env).horizon)
        cached.parent.mkdir(parents=True, exist_ok=True)
        records.to_parquet(cached)
    t = per_slot(records).groupby("slot").agg(**{"test return": ("return", "mean"),
                                                 "test goal rate": ("goal", "mean"),
                                                 "test contact steps": ("contact_steps", "mean")})
    return t.round(2).reset_index().assign(arm=label)


def table(training: pd.DataFrame, test: pd.DataFrame | None, env: str) -> pd.DataFrame:
    """One row per (slot, arm), the slot's route beside it."""
    from eval.reporting.multiseed import slot_routes

    t = training if test is None else training.merge(test, on=["arm", "slot"], how="left")
    t = t.merge(slot_routes(env), on="slot", how="left")
    first = ["slot", "movement", "arm"]
    return t[first + [c for c in t.columns if c not in first + ["turning"]]].sort_values(["slot", "arm"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arm", type=parse_arm, action="append", required=True, metavar="LABEL=RUN",
                   help="a run folder and its label; give two or more")
    p.add_argument("--episodes", type=int, default=6, help="held-out test episodes (0: no test)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).parent))
    from eval.reporting.page import md_table
    from eval.training.runfolder import load_run_config

    configs = {label: load_run_config(run) for label, run in args.arm}
    envs = {c.env for c in configs.values()}
    if len(envs) != 1:
        p.error(f"--arm: the runs are of different environments ({', '.join(sorted(envs))}); compare one")
    args.out.mkdir(parents=True, exist_ok=True)
    training = pd.concat([training_rows(label, run, configs[label].steps) for label, run in args.arm])
    training.to_csv(args.out / "training.csv", index=False)
    test = None
    if args.episodes > 0:
        test = pd.concat([test_rows(label, run, args.episodes, args.out) for label, run in args.arm])
        test.to_csv(args.out / "test.csv", index=False)
    t = table(training, test, envs.pop())
    (args.out / "slots.md").write_text(md_table(list(t.columns), t.itertuples(index=False)))
    print(t.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
