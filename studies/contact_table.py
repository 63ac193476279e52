"""A grid's return with and without the contact charge, over training seeds.

Under task version 3 a test episode charged every contact step (-50 each; collisions do not end
it), so one AC that stood against a car or a wall to the episode's end cost its algorithm's mean
thousands, and a seed's Scenario 1 mean moved with how many such runs its 24 episodes held (the
6x5 study on task version 3; in git history at 1b59d82, docs/results/2026-11-28-science-v3-seeds012).
Since task version 4 a contact is charged once per collision event (docs/task.md, "Collision
rule"). This puts beside the study's return (mean [95% bootstrap CI over seeds]) the same mean
without the contact charge (the records' ``r_collision``, under whichever rule they were tested):
how the cars drove apart from their collisions. A diagnostic beside the study's tables, not one of
its metrics (the verdict is by driving score: docs/task.md, "Driving score"; docs/scenarios.md,
"The check" for the references).

Reads each study part's ``contact.csv`` (``studies/stops.py --policy-out``: one line per policy,
environment, scenario and training seed) or the ``study/`` folder that holds it:

    python studies/stops.py sci_2s1/test/*.parquet --policy-out docs/results/<page>/study/contact.csv
    python studies/contact_table.py docs/results/<date>-<part>/study docs/results/<date>-<other part>/study
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd
from science_pages import over_seeds

from eval.labels import algo_label, algo_order, env_title
from eval.reporting.page import md_table
from eval.reporting.stats import bootstrap_ci

FILE = "contact.csv"
COLUMNS = ("mean_return", "without_contact_charge")
"""contact.csv's columns the table puts side by side: the return, the same without the contact charge."""


def load(paths: list[Path]) -> pd.DataFrame:
    """Every part's lines, one per (policy, env, scenario, train seed); SystemExit naming a path
    without a contact.csv, one without training seeds, or a seed given twice."""
    parts = []
    for p in paths:
        f = p if p.suffix == ".csv" else p / FILE
        if not f.is_file():
            raise SystemExit(f"contact_table: {p} has no {FILE}; write it with "
                             f"`python studies/stops.py <part>/test/*.parquet --policy-out {f}`")
        lines = pd.read_csv(f)
        if "train seed" not in lines:
            raise SystemExit(f"contact_table: {f} has no training seeds; write it from a science "
                             "study's records (its test/*.parquet)")
        parts.append(lines.assign(source=str(f)))
    every = pd.concat(parts, ignore_index=True)
    twice = every[every.duplicated(["policy", "env", "scenario", "train seed"], keep=False)]
    if len(twice):
        r = twice.iloc[0]
        raise SystemExit(f"contact_table: {r.env} seed {r['train seed']} ({r.policy}) is in "
                         f"{' and '.join(sorted(set(twice.source)))}; give each part once")
    return every


def table(lines: pd.DataFrame, scenario: int = 1) -> pd.DataFrame:
    """One row per (environment, policy): the seeds, and per column of :data:`COLUMNS` the
    mean over seeds with its 95% bootstrap interval."""
    rows = []
    for (env, policy), g in lines[lines.scenario == scenario].groupby(["env", "policy"], sort=True):
        g = g.sort_values("train seed")
        row = {"env": env, "policy": policy, "seeds": " ".join(map(str, g["train seed"]))}
        for col in COLUMNS:
            mean, lo, hi, n = bootstrap_ci(g[col].to_numpy(float))
            row.update({col: mean, f"{col}_low": lo, f"{col}_high": hi, f"{col}_cell": over_seeds(mean, lo, hi, n)})
        rows.append(row)
    return pd.DataFrame(rows)


def markdown(t: pd.DataFrame) -> str:
    """Algorithms (rows) x environments (columns), each cell 'return / without the contact
    charge (seeds)', both over seeds."""
    envs = sorted(t.env.unique())
    by = t.set_index(["policy", "env"])

    def text(r: pd.Series) -> str:
        n = len(r.seeds.split())
        return (f"{r.mean_return_cell} / {r.without_contact_charge_cell} "
                f"({n} seed{'s' if n > 1 else ''})")

    rows = [[algo_label(p)] + [text(by.loc[(p, e)]) if (p, e) in by.index else "" for e in envs]
            for p in algo_order(t.policy.unique())]
    return md_table(["algorithm", *[env_title(e) for e in envs]], rows)


def caption(scenario: int = 1) -> str:
    """The line above the :func:`markdown` table."""
    return (f"Scenario {scenario}: mean return / mean return without the contact charge, per "
            "AC-episode, mean over training seeds [95% bootstrap CI over seeds]")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("parts", nargs="+", type=Path, help=f"study parts' {FILE} files or the study/ folders holding them")
    p.add_argument("--scenario", type=int, default=1, choices=(1, 2), help="1: the ACs together (default); 2: alone")
    p.add_argument("--out", type=Path, default=None, help="also write the table as CSV")
    args = p.parse_args(argv)
    t = table(load(args.parts), args.scenario)
    if t.empty:
        raise SystemExit(f"contact_table: no Scenario {args.scenario} lines in the parts given")
    if args.out:
        t.drop(columns=[c for c in t if c.endswith("_cell")]).to_csv(args.out, index=False)
    print(caption(args.scenario) + "\n")
    print(markdown(t))
    return 0


if __name__ == "__main__":
    sys.exit(main())
