"""The same checkpoints, or the same cells trained otherwise, tested in variants side by side.

A pilot that changes the task (a scenario option, a training rule) is judged on the study's
held-out episodes: each arm is one `cosim test` report (or a science study's records) and this
puts them side by side, per algorithm and arm: Scenario 1 return, the same without the contact
charge, goal rate, the turning slots' goal rate (eval/reporting/multiseed.with_turning), contact
steps and how many of them lie in runs of ``--long`` or more that began with the AC off its lane
against a background car (the runs SUMO's cars cannot see: studies/stops.contact_runs), and
Scenario 2's return and goal rate where the arm has it:

    python studies/variant_table.py plain=sci_3s2/test/env_3__seed2.parquet \\
        see=rep_grid_see/20261129-060435 trained-see=rep_pilot_see/20261129-070657 \\
        --figure docs/results/<page> --reference always-brake=-552.0

Results: task version 3; in git history at 1b59d82, docs/results/2026-11-29-cars-see-trained.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd
from stops import LONG, contact_runs, episode_rows, load_records

from eval.labels import algo_label, algo_order
from eval.reporting.multiseed import with_turning
from eval.reporting.page import md_table

SYMLOG_RETURN = 1_000.0
"""Return axis: linear within +-1,000, logarithmic beyond (returns run from -10^4 to 10^3)."""


def arm_lines(label: str, report: Path, long: int = LONG) -> pd.DataFrame:
    """One line per algorithm of one arm's records (a `cosim test` report folder or a records
    parquet): Scenario 1 means over its AC-episodes and Scenario 2's where present."""
    rows = with_turning(episode_rows(report))
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


def figure(lines: pd.DataFrame, out: Path, reference: float | None = None,
           reference_name: str = "reference") -> list[Path]:
    """The arms drawn: per algorithm (rows, the study's order) one marker per arm at its Scenario 1
    return (filled) and the same without the contact charge (hollow, joined to it: the gap is the
    contact), against ``reference`` (dashed red: what a mean must clear); the return axis linear
    within +-1,000 and logarithmic beyond, as the verdict figure's. PDF and PNG, stem ``arms``."""
    from eval.reporting.figures import COLUMN_IN, _plt, _save

    plt = _plt()
    Path(out).mkdir(parents=True, exist_ok=True)
    algos = algo_order(lines.algorithm.unique())
    arms = list(dict.fromkeys(lines.arm))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, ax = plt.subplots(figsize=(2 * COLUMN_IN, 0.9 + 0.42 * len(algos)))
    step = 0.7 / max(len(arms), 1)
    for k, arm in enumerate(arms):
        mine = lines[lines.arm == arm].set_index("algorithm")
        ys, got, without = [], [], []
        for y, algo in enumerate(algos):
            if algo in mine.index:
                ys.append(y - 0.35 + step * (k + 0.5))
                got.append(mine.loc[algo, "return"])
                without.append(mine.loc[algo, "without contact charge"])
        c = colours[k % len(colours)]
        ax.hlines(ys, got, without, color=c, lw=0.8, zorder=2)
        ax.plot(got, ys, "o", color=c, ms=4, zorder=3, label=arm)
        ax.plot(without, ys, "o", mfc="white", mec=c, ms=4, zorder=3)
    if reference is not None:
        ax.axvline(reference, color="#C00000", ls="--", lw=0.8, zorder=1, label=reference_name)
    ax.set_xscale("symlog", linthresh=SYMLOG_RETURN)  # returns span -10^4..10^3
    ax.set_yticks(range(len(algos)), [algo_label(a) for a in algos])
    ax.invert_yaxis()
    ax.grid(axis="x", lw=0.3)
    ax.set_xlabel("Scenario 1 return per AC-episode (filled) and without the contact charge (hollow)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False, fontsize="small")
    fig.tight_layout()
    return _save(fig, Path(out), "arms")


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
    p.add_argument("--figure", type=Path, default=None, metavar="DIR",
                   help="also draw the arms into DIR/arms.png and .pdf")
    p.add_argument("--reference", default=None, metavar="NAME=RETURN",
                   help="with --figure: a reference line, e.g. always-brake=-552.0")
    args = p.parse_args(argv)
    ref_name, ref = "reference", None
    if args.reference is not None:
        ref_name, _, value = args.reference.rpartition("=")
        try:
            ref = float(value)
        except ValueError:
            raise SystemExit(f"variant_table: --reference {args.reference!r} is not NAME=RETURN; "
                             "give e.g. always-brake=-552.0") from None
        ref_name = ref_name or "reference"
    lines = pd.concat([arm_lines(label, path, args.long) for label, path in map(parse_arm, args.arms)],
                      ignore_index=True)
    if args.csv:
        lines.to_csv(args.csv, index=False)
    print(table(lines, args.long))
    if args.figure:
        for path in figure(lines, args.figure, ref, ref_name):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
