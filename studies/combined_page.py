"""The docs/results page of a `studies/science.py --combine` folder (a grid's exported parts
joined; task version 3's 6x5 study: in git history at 1b59d82, docs/results/2026-11-28-science-v3-seeds012):
copies its summary.md, results.md, verdict.md, iqm.md, budget.csv, convergence.png,
verdict.png and iqm.png into the page folder and writes README.md around them: the training seeds per
environment, the command, the verdict grid (summary.md's, the README's results table) and its
figure, issue 27's target per environment, per environment the verdict (the passes, or what the
target lacks and the nearest pairs) and the return without the contact charge (studies/part_page.py's
bullets), the convergence figure, the IQM (and its figure), the return with and without the contact charge
(studies/contact_table.py over the same parts) and the budgets.

    python studies/science.py --combine <the parts' study/ exports> --out comb
    python studies/combined_page.py comb --page docs/results/<date>-<study> \\
        --title "The 6x5 study, seeds 0, 1 and 2"

The page's prose beyond that (what moved a mean, what did not work) is written by hand.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
from contact_table import caption, load, markdown, table
from part_page import contact_charge_bullet, verdict_bullet

from eval.labels import env_title
from eval.reporting.multiseed import MIN_SEEDS

COPIED = ("summary.md", "results.md", "verdict.md", "iqm.md", "budget.csv", "convergence.png", "verdict.png", "iqm.png")
HEADINGS = {"grid": "verdict per pair:", "target": "Issue 27's target per environment",
            "iqm": "IQM across environments", "budget": "Did the budgets suffice?"}
"""summary.md's sections the page shows: each is the first table after its heading's line."""
OPTIONAL = {"alone": "Alone (Scenario 2"}
"""Sections shown where summary.md has them (a study tested without Scenario 2 has no alone table;
summary.md files written before 2026-11-28 neither)."""


def sections(summary: str) -> dict[str, str]:
    """The tables of summary.md the page shows (:data:`HEADINGS`), each as markdown; SystemExit
    naming the heading that summary.md lacks (a summary.md of another format)."""
    lines = summary.splitlines()
    out = {}
    for key, heading in {**HEADINGS, **OPTIONAL}.items():
        start = next((i for i, line in enumerate(lines) if heading in line), None)
        if start is None and key in OPTIONAL:
            continue
        if start is None:
            raise SystemExit(f"combined_page: summary.md has no '{heading}' section; give a folder "
                             "written by studies/science.py --combine")
        rows = []
        for line in lines[start + 1:]:
            if line.startswith("|"):
                rows.append(line)
            elif rows:
                break
        out[key] = "\n".join(rows)
    return out


def seeds_text(seeds: pd.DataFrame) -> str:
    """'Straight 0, 1 and 2, Three-way 0 and 1, ...': the training seeds per environment."""
    def listed(xs):
        xs = [str(x) for x in sorted(xs)]
        return " and ".join(xs) if len(xs) < 3 else f"{', '.join(xs[:-1])} and {xs[-1]}"

    per_env = seeds.groupby("env")["train_seed"].unique()
    return ", ".join(f"{env_title(e)} {listed(s)}" for e, s in per_env.items())


def per_env(comb: Path, lines: pd.DataFrame) -> str:
    """Per environment (the grid's order): its verdict bullet (the passes, or what its target lacks
    and the nearest pairs) and, where ``lines`` (the parts' contact.csv) hold it, the return
    without the contact charge against always-brake and, where a route turns, the safe non-turner."""
    verdict, targets = pd.read_csv(comb / "verdict.csv"), pd.read_csv(comb / "targets.csv")
    refs = pd.read_csv(comb / "results.csv").query("kind == 'reference' and scenario == 1 and metric == 'return'")
    out = []
    for env in targets.env:
        ref = refs[refs.env == env].set_index("name")["mean"]
        turns = bool(targets.set_index("env").loc[env, "has_turns"])
        out += [f"**{env_title(env)}**", "", verdict_bullet(verdict, targets, env)]
        if (lines.env == env).any():
            out.append(contact_charge_bullet(lines, env, None, float(ref["always-brake"]),
                                             float(ref["safe-non-turner"]) if turns and "safe-non-turner" in ref else None))
        out.append("")
    return "\n".join(out)


def page(comb: Path, title: str, parts: list[str], commit: str, contact: str, envs: str = "") -> str:
    """README.md of the page for the --combine folder ``comb`` of ``parts`` (repository paths)."""
    s = sections((comb / "summary.md").read_text())
    test = json.loads((comb / "science.json").read_text())["test"]
    first, last = min(test["episode_seeds"]), max(test["episode_seeds"])
    seeds = pd.read_csv(comb / "seeds.csv").query("scenario == 1")
    fewest = int(seeds.groupby("env")["train_seed"].nunique().min())
    verdict = (f"Every pair has {MIN_SEEDS} seeds or more, what a verdict needs." if fewest >= MIN_SEEDS else
               f"Fewer than {MIN_SEEDS} seeds (what issue 27 asks for) are too few for a verdict: a pair "
               "above every reference reads \"not shown\".")
    alone = ("" if "alone" not in s else "\nAlone (Scenario 2): each algorithm's `ac_0` with no other AC (in the "
             "junctions and on the Merge a turning slot), return [95% CI over seeds] (goal rate):\n\n" + s["alone"] + "\n")
    cmd = "python studies/science.py --combine \\\n      " + " \\\n      ".join(parts) + f" --out {comb.name}"
    return f"""# {title} (issue 27), {pd.Timestamp.now(tz="UTC"):%Y-%m-%d}

The 6x5 study's exported parts combined (their seed means join the tables; a fresh clone gives
the same files): training seeds per environment: {seeds_text(seeds)}. Each tested on the same
{test["episodes"]} held-out {test["steps"]}-step episodes (seeds {first:,}-{last:,}); Scenario 1, the six algorithms together (one AC each, rotated
over the slots). {verdict}

- **Commit**: {commit}
- **Command** (from a checkout):
  ```bash
  {cmd}
  python studies/combined_page.py {comb.name} --page <this folder> --title "{title}"
  ```
- **Files**: [summary.md](summary.md) (driving score, route completion, success rate, return, goal rate,
  turning slots' route completion and goal rate, alone, verdict, IQM,
  issue 27's target per environment, budgets), [results.md](results.md) (every metric with the
  reference rows), [verdict.md](verdict.md), [iqm.md](iqm.md), [budget.csv](budget.csv)

## Driving score and verdict

Scenario 1: driving score [95% CI over seeds] (goal rate) and the verdict per pair (docs/task.md,
"Driving score"; ", turns": the turning slots' route completion clears the safe non-turner's);
reference rows: mean (goal rate) over episodes x ACs (their intervals: [results.md](results.md));
the best degenerate row is what a pair's lower CI end must clear (the safe non-turner brakes in
every turning slot and is not a degenerate reference).

{s["grid"]}

The same drawn: each training seed's mean (dots) and the mean with its 95% CI over seeds of the driving
score (top) and the turning slots' route completion (bottom), against the autopilot (solid), the best
degenerate reference (dashed red: what a lower CI end must clear) and, where a route turns, the safe
non-turner (dotted):

![Scenario 1 driving score and turning slots' route completion per algorithm and environment with the reference lines](verdict.png)

Issue 27's target per environment:

{s["target"]}

{envs}{alone}
## Convergence

Training return against environment steps, mean over the seeds, band: min-max over them:

![Training return against environment steps, mean over the seeds, five environments](convergence.png)

## IQM across the five environments

Scenario 1 return normalised per environment (uniform random = 0, autopilot = 1), interquartile
mean over the (environment, seed) scores, 95% stratified bootstrap CI:

{s["iqm"]}

![The IQM of each algorithm with its 95% CI against the autopilot, the best degenerate reference and the safe non-turner](iqm.png)

## Contact

{contact}

## Did the budgets suffice?

Training return of the last 20% of each run's budget minus the 20% before (mean over seeds); bold:
still rising in some seed ([budget.csv](budget.csv)):

{s["budget"]}
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("comb", type=Path, help="the --out folder of studies/science.py --combine")
    p.add_argument("--page", type=Path, required=True, help="the docs/results/<date>-<study> folder to write")
    p.add_argument("--title", required=True, help="the page's heading")
    a = p.parse_args(argv)
    saved = a.comb / "science.json"
    combined = json.loads(saved.read_text()).get("combined") if saved.is_file() else None
    if not combined:
        raise SystemExit(f"combined_page: {a.comb} is not a --combine folder (no 'combined' list in "
                         "its science.json); run studies/science.py --combine <parts> --out it first")
    root = Path(__file__).resolve().parent.parent
    parts = [str(Path(x).resolve().relative_to(root)) if Path(x).resolve().is_relative_to(root) else x
             for x in combined]
    missing = [name for name in COPIED if not (a.comb / name).is_file()]
    if missing:
        raise SystemExit(f"combined_page: {a.comb} lacks {', '.join(missing)}; run its --combine again")
    a.page.mkdir(parents=True, exist_ok=True)
    for name in COPIED:
        data = (a.comb / name).read_bytes()
        if name.endswith(".md"):  # the folder's own path -> its name (pages carry no machine paths)
            data = data.replace(str(a.comb.resolve()).encode(), a.comb.name.encode())
        (a.page / name).write_bytes(data)
    lines = load([Path(x) for x in combined])
    contact = f"{caption()} (`studies/contact_table.py`):\n\n" + markdown(table(lines)).strip()
    commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip() or "unknown"
    (a.page / "README.md").write_text(page(a.comb, a.title, parts, commit, contact, per_env(a.comb, lines)))
    print(f"combined_page: {a.page / 'README.md'} ({len(parts)} parts)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
