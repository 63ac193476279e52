"""The same checkpoints, or the same cells trained otherwise, tested in variants side by side.

A pilot that changes the task (a scenario option, a training rule) is judged on the study's
held-out episodes: each arm is one `cosim test` report (or a science study's records) and this
puts them side by side, per algorithm and arm: Scenario 1 return, the same without the contact
charge, goal rate, the turning slots' goal rate (eval/reporting/science.with_turning), contact
steps and how many of them lie in runs of ``--long`` or more that began with the AC off its lane
against a background car (the runs SUMO's cars cannot see: studies/stops.contact_runs), and
Scenario 2's return and goal rate where the arm has it:

    python studies/variant_table.py plain=sci_3s2/test/env_3__seed2.parquet \\
        see=rep_grid_see/20261129-060435 trained-see=rep_pilot_see/20261129-071500

Results: docs/results/2026-11-29-cars-see-trained.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd
from stops import contact_runs, episode_rows, load_records

from eval.labels import algo_label, algo_order
from eval.reporting.page import md_table
from eval.reporting.science import with_turning

LONG = 50
"""Contact steps in one unbroken run that count as a long run (as on the contact-runs page)."""


def arm_lines(label: str, report: Path, long: int = LONG) -> pd.DataFrame:
    """One line per algorithm of one arm's records (a `cosim test` report folder or a records
    parquet): Scenario 1 means over its AC-episodes and Scenario 2's where present."""
    rows = episode_rows(report)
    rows = with_turning(rows)
    runs = contact_runs(load_records(report), long)
    unseen = (runs[(runs["with"] == "car") & (runs["partner"] == "") & runs["off lane at first"]]
              if len(runs) else runs)
    lines = []
    for algo in algo_order(rows.policy.unique()):
        one = rows[(rows.policy == algo) & (rows.scenario == 1)]
        alone = rows[(rows.policy == algo) & (rows.scenario == 2)]
        if not len(one):
            continue
        lines.append({
            "arm": label, "algorithm": algo, "AC-episodes": len(one),
            "return": one["return"].mean(),
            "without contact charge": (one["return"] - one["contact charge"]).mean(),
            "goal rate": one["goal"].mean(), "turning slots' goal rate": one["goal_turning"].mean(),
            "contact steps": int(one["contact steps"].sum()),
            "unseen": int(unseen[(unseen.policy == algo) & (unseen.scenario == 1)].steps.sum()) if len(unseen) else 0,
            "alone return": alone["return"].mean() if len(alone) else float("nan"),
            "alone goal rate": alone["goal"].mean() if len(alone) else float("nan")})
    return pd.DataFrame(lines)


def table(lines: pd.DataFrame, long: int = LONG) -> str:
    """The arms side by side, grouped by algorithm in the study's order."""
    order = {a: i for i, a in enumerate(algo_order(lines.algorithm.unique()))}
    arms = {a: i for i, a in enumerate(dict.fromkeys(lines.arm))}
    lines = lines.sort_values(["algorithm", "arm"], key=lambda c: c.map(order if c.name == "algorithm" else arms))

    def num(x, fmt):
        return "" if pd.isna(x) else format(x, fmt)

    body = [[algo_label(r.algorithm), r.arm, num(r["return"], ",.1f"), num(r["without contact charge"], ",.1f"),
             num(r["goal rate"], ".2f"), num(r["turning slots' goal rate"], ".2f"), f"{r['contact steps']:,}",
             f"{r['unseen']:,}", num(r["alone return"], ",.1f"), num(r["alone goal rate"], ".2f")]
            for _, r in lines.iterrows()]
    head = ["algorithm", "arm", "Scenario 1 return", "without the contact charge", "goal rate",
            "turning slots' goal rate", "contact steps",
            f"of them in runs of {long}+ begun off lane against a background car",
            "Scenario 2 return", "goal rate"]
    return md_table(head, body)


def parse_arm(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise SystemExit(f"variant_table: {text!r} is not LABEL=REPORT; give e.g. see=reports/20261129-060435")
    if not Path(path).exists():
        raise SystemExit(f"variant_table: {path} (arm {label}) does not exist; give a `cosim test` report "
                         "folder or a records .parquet")
    return label, Path(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("arms", nargs="+", help="LABEL=REPORT: a `cosim test` report folder or a records .parquet")
    p.add_argument("--long", type=int, default=LONG, metavar="N",
                   help=f"contact runs of N steps or more count in the off-lane column (default {LONG})")
    p.add_argument("--csv", type=Path, default=None, help="also write the lines as CSV")
    args = p.parse_args(argv)
    lines = pd.concat([arm_lines(label, path, args.long) for label, path in map(parse_arm, args.arms)],
                      ignore_index=True)
    if args.csv:
        lines.to_csv(args.csv, index=False)
    print(table(lines, args.long))
    return 0


if __name__ == "__main__":
    sys.exit(main())
