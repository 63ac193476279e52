"""The tables of one part of a grid run in parts (one environment, one training seed, as a
`studies/science.py --envs env_N --first-seed K --seeds 1` study trains) for its docs/results page:
each algorithm's budget, best validation return, Scenario 1 and 2 return and goal rate, beside
the same environment's other seeds (their exports' seeds.csv) and, with ``--combined``, the
seeds together (a ``--combine`` folder: mean [95% CI over seeds]); the reference rows; which
algorithms are above always-brake; the turning slots' goals; the contact (studies/stops.py: its
long runs by kind, to the episode's end, per algorithm, the longest); each ``ac_0`` alone (Scenario 2);
the commit each trial started at (its manifest.json) and whether the training code differs between them;
with ``--combined``, the verdict over the seeds and the environment's target (its verdict.csv and
targets.csv); with ``--contact``, the seeds' return without the contact charge (their contact.csv).

    python studies/part_page.py sci_2s1 --earlier docs/results/<seed 0's page>/study \\
        --combined comb_2 --contact docs/results/<seed 0's page>/study \\
        docs/results/<this part's page>/study > page-tables.md

The page's prose (what moved a mean, what did not work) is written by hand around it.
"""
from __future__ import annotations

import argparse
import ast
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pandas as pd
from contact_table import load as load_contact
from contact_table import table as contact_table
from science_pages import over_seeds, shows_reference
from stops import LONG, contact_runs, episode_rows, load_records

from eval.labels import algo_label, algo_order, env_title
from eval.reporting.multiseed import MIN_SEEDS
from eval.reporting.page import md_table
from eval.scale.gridstatus import grid_status
from eval.testing.validity import DEGENERATE

REFERENCES = {"autopilot": "autopilot", "autopilot-discrete": "discrete autopilot",
              "safe-non-turner": "safe non-turner", "always-brake": "always-brake"}
TRAINING_CODE = ("cosim", "agents", "sumo_nets", "eval/training", "eval/scale", "eval/cli")
"""What a trial's training runs or reads: trials whose commits differ only outside these trained
on the same code (reports, studies and docs change no trial)."""


def _part(study: Path, env: str | None, seed: int | None) -> tuple[str, int]:
    """(environment, training seed) of the page: given, or the study's only ones; SystemExit
    where the study has no such part or more than one to choose from."""
    saved = study / "science.json"
    if not saved.is_file() or not (study / "seeds.csv").is_file():
        raise SystemExit(f"part_page: {study} has no science.json and seeds.csv; give the --out folder "
                         "of a finished studies/science.py study")
    seeds = pd.read_csv(study / "seeds.csv")
    for name, value, have in (("--env", env, seeds.env), ("--seed", seed, seeds.train_seed)):
        found = sorted(have.unique())
        if value is None and len(found) != 1:
            raise SystemExit(f"part_page: {study} holds {name[2:]}s {', '.join(map(str, found))}; "
                             f"choose one with {name}")
        if value is not None and value not in found:
            raise SystemExit(f"part_page: {study} has no {name[2:]} {value}; it holds "
                             f"{', '.join(map(str, found))}")
    return env or str(seeds.env.iloc[0]), int(seed if seed is not None else seeds.train_seed.iloc[0])


def _scenario(seeds: pd.DataFrame, k: int) -> pd.DataFrame:
    return seeds[seeds.scenario == k].set_index("algorithm")


def _num(x: float, digits: int = 1) -> str:
    return "-" if pd.isna(x) else f"{x:,.{digits}f}"


def tables(study: Path, earlier: list[Path], combined: Path | None, env: str | None = None,
           seed: int | None = None, contact: list[Path] | None = None) -> str:
    """The page's tables and bullets, as markdown (`env` and `seed`: see :func:`_part`;
    `contact`: the parts' contact.csv files or the study/ folders holding them)."""
    env, seed = _part(study, env, seed)
    seeds = pd.read_csv(study / "seeds.csv")
    seeds = seeds[(seeds.env == env) & (seeds.train_seed == seed)]
    s1, s2 = _scenario(seeds, 1), _scenario(seeds, 2)
    turning = s1["goal_turning"].notna().any()
    others = []
    for src in earlier:
        rows = pd.read_csv(src / "seeds.csv")
        rows = rows[(rows.env == env) & (rows.train_seed != seed)]
        if rows.empty:
            raise SystemExit(f"part_page: {src}/seeds.csv has no other seed of {env}; give studies "
                             f"or exports of {env}'s other seeds")
        others += [(int(k), _scenario(g, 1)) for k, g in rows.groupby("train_seed")]
    comb = None
    if combined is not None:
        comb = pd.read_csv(combined / "results.csv")
        comb = comb[(comb.scenario == 1) & (comb.kind != "reference") & (comb.metric == "return") & (comb.env == env)]
        comb = comb.set_index("name")
    status = grid_status(study / "bench")
    status = status[(status.env == env) & (status.seed == seed)].set_index("algo")
    results = pd.read_csv(study / "results.csv")
    refs = results[(results.kind == "reference") & (results.scenario == 1) & (results.env == env)]

    head = ["algorithm", "training budget (env steps)", "best validation return",
            f"Scenario 1 return, seed {seed}", "goal rate"] + (["turning slots' goal rate"] if turning else []) \
        + ["CV", "Scenario 2 return", "goal rate"] + [f"Scenario 1, seed {k} (goal rate)" for k, _ in others] \
        + (["seeds together: mean [95% CI over seeds]"] if comb is not None else [])
    lines = []
    for algo in algo_order(s1.index):
        a1, a2 = s1.loc[algo], s2.loc[algo] if algo in s2.index else None
        cells = [algo_label(algo), f"{int(status.loc[algo, 'budget']):,}", _num(status.loc[algo, "best"], 0),
                 _num(a1["return"]), _num(a1.goal, 2)] + ([_num(a1.goal_turning, 2)] if turning else []) \
            + [_num(a1.CV, 3), _num(a2["return"]) if a2 is not None else "-",
               _num(a2.goal, 2) if a2 is not None else "-"] \
            + [f"{_num(o.loc[algo, 'return'])} ({_num(o.loc[algo, 'goal'], 2)})" for _, o in others]
        if comb is not None:
            c = comb.loc[algo]
            cells.append(over_seeds(c["mean"], c.ci_low, c.ci_high, c.n))
        lines.append(cells)
    for name, label in REFERENCES.items():
        x = refs[refs.name == name].set_index("metric")
        if x.empty or not shows_reference(name, turning):
            continue
        r = x.loc["return"]
        cells = [f"*{label}*", "", "", over_seeds(r["mean"], r.ci_low, r.ci_high, r.n),
                 _num(x.loc["goal", "mean"], 2)]
        if turning:
            cells.append(_num(x.loc["goal_turning", "mean"], 2) if "goal_turning" in x.index else "-")
        lines.append(cells + [""] * (len(head) - len(cells)))

    brake = float(refs[(refs.name == "always-brake") & (refs.metric == "return")]["mean"].iloc[0])
    degen_goal = refs[refs.name.isin(set(DEGENERATE) - {"always-brake"}) & (refs.metric == "goal")]["mean"].max()
    above = [a for a in s1.index if s1.loc[a, "return"] > brake]
    every = [a for a in above if all(o.loc[a, "return"] > brake for _, o in others)]
    order = s1["return"].sort_values(ascending=False)
    bullets = [
        f"- **Above always-brake ({_num(brake)})** with seed {seed}: "
        + (", ".join(f"{algo_label(a)} {_num(s1.loc[a, 'return'])} (goal rate {_num(s1.loc[a, 'goal'], 2)})"
                     for a in above) or "no algorithm")
        + (f"; in every seed so far: {', '.join(algo_label(a) for a in every) or 'none'}" if others else "")
        + ". Order: " + ", ".join(f"{algo_label(a)} {_num(v)}" for a, v in order.items())
        + f". Best degenerate goal rate: {_num(degen_goal, 2)}."]
    if combined is not None and (combined / "verdict.csv").is_file() and (combined / "targets.csv").is_file():
        bullets.append(verdict_bullet(pd.read_csv(combined / "verdict.csv"), pd.read_csv(combined / "targets.csv"), env))
    if turning:
        turners = [f"{algo_label(a)} {_num(s1.loc[a, 'goal_turning'], 2)}" for a in algo_order(s1.index) if s1.loc[a, "goal_turning"] > 0]
        bullets.append("- **Turning slots' goals** (Scenario 1): " + (", ".join(turners) or "none, in any algorithm") + ".")
    records = study / "test" / f"{env}__seed{seed}.parquet"
    if records.is_file():
        rows = episode_rows(records)
        runs = contact_runs(load_records(records), LONG)
        bullets.append(contact_bullet(rows[rows.scenario == 1], runs[runs.scenario == 1] if len(runs) else runs,
                                      records.name))
    safe = refs[(refs.name == "safe-non-turner") & (refs.metric == "return")]["mean"]
    if contact:
        bullets.append(contact_charge_bullet(load_contact(contact), env, seed, brake,
                                             float(safe.iloc[0]) if turning and len(safe) else None))
    if records.is_file() and (rows.scenario == 2).any():
        bullets.append(alone_bullet(rows[rows.scenario == 2]))
    commits = trial_commits(study / "bench" / "runs", env, seed)
    if commits:
        bullets.append(commits_bullet(commits))
    return md_table(head, lines) + "\n" + "\n".join(bullets) + "\n"


def _names(labels: list[str]) -> str:
    """'A', 'A and B', 'A, B and C'."""
    return labels[0] if len(labels) == 1 else f"{', '.join(labels[:-1])} and {labels[-1]}"


def verdict_bullet(verdict: pd.DataFrame, targets: pd.DataFrame, env: str) -> str:
    """The verdict over the seeds together (a ``--combine`` folder's verdict.csv and targets.csv):
    which pairs pass (on the driving score, eval/reporting/multiseed.py verdict), whether the
    environment's target is met and what it lacks; where none passes, the two nearest (highest
    mean driving score) with their intervals and goal rates."""
    v = verdict[verdict.env == env].set_index("algorithm")
    if v.empty:
        raise SystemExit(f"part_page: the --combined folder's verdict.csv has no {env}; combine "
                         f"{env}'s studies")
    n, title = int(v.n.max()), env_title(env)
    t = targets[targets.env == env]

    def cell(a: str) -> str:
        r = v.loc[a]
        ds = (f"{r.DS_mean:.3f}" if int(r.n) == 1 else f"{r.DS_mean:.3f} [{r.DS_ci_low:.3f}, {r.DS_ci_high:.3f}]")
        return f"{algo_label(a)}, DS {ds} (goal rate {r.goal_mean:.2f})"

    passed = [a for a in algo_order(v.index) if bool(v.loc[a, "passed"])]
    if n < MIN_SEEDS:  # too few seeds: a pair above every reference is "not shown", none passes
        above = [a for a in algo_order(v.index) if str(v.loc[a, "DS_ok"]) == "True"]
        text = (f"- **{n} seed{'s' if n != 1 else ''} so far, too few for a verdict ({MIN_SEEDS} needed): "
                + (f"{_names([algo_label(a) for a in above])} above every degenerate reference (not shown)"
                   if above else "no pair above every degenerate reference"))
    else:
        text = (f"- **The verdict with {n} seeds: "
                + (f"{_names([algo_label(a) for a in passed])} pass{'es' if len(passed) == 1 else ''}" if passed
                   else "no pair passes"))
    if len(t):
        row = t.iloc[0]
        met = bool(row.met)
        text += f"; {title}'s target is {'met' if met else 'not met'}{' so far' if n < MIN_SEEDS else ''}.**"
        if not met:
            lacks = [f"no {kind} algorithm passes" for kind in ("discrete", "continuous")
                     if not ast.literal_eval(str(row[kind]))]
            if bool(row.has_turns) and not ast.literal_eval(str(row.turning)):
                lacks.append("no algorithm's turns are learned (turning slots' route completion above "
                             "the safe non-turner's)")
            text += " It lacks: " + "; ".join(lacks) + "."
    else:
        text += ".**"
    if passed:
        return text + " " + "; ".join(cell(a) for a in passed) + "."
    nearest = v.sort_values("DS_mean", ascending=False).index[:2]
    return text + " Nearest: " + "; ".join(cell(a) for a in nearest) + "."


def contact_charge_bullet(lines: pd.DataFrame, env: str, seed: int | None, brake: float,
                          safe: float | None = None) -> str:
    """Scenario 1's return without the contact charge (studies/contact_table.py's lines, one per
    policy and training seed): which algorithms would be above always-brake in every seed and
    which would not, each mean [95% CI over seeds]; against the safe non-turner where a route
    turns; then the page's seed alone (none: the seeds together only)."""
    lines = lines[(lines.env == env) & (lines.scenario == 1)]
    if lines.empty or (seed is not None and seed not in set(lines["train seed"])):
        raise SystemExit(f"part_page: the --contact parts hold no Scenario 1 line of {env} seed {seed}; "
                         "give this part's export (its study/ folder) among them")
    t = contact_table(lines).set_index("policy").sort_values("without_contact_charge", ascending=False)
    n = lines.groupby("policy")["train seed"].nunique().max()
    every = [a for a in t.index if (lines[lines.policy == a].without_contact_charge > brake).all()]
    rest = [a for a in t.index if a not in every]

    def cell(a: str) -> str:
        return f"{algo_label(a)} {t.loc[a, 'without_contact_charge_cell']}"

    text = (f"- **Without its contact charge** (`studies/contact_table.py` on the {n} seeds' exports): "
            + (f"{_names([cell(a) for a in every])} would be above always-brake ({_num(brake)}) in "
               f"{'its' if n == 1 else 'both' if n == 2 else f'all {n}'} seed{'s' if n > 1 else ''}" if every
               else f"no algorithm would be above always-brake ({_num(brake)}) in every seed"))
    if every and safe is not None:
        below = [a for a in every if t.loc[a, "without_contact_charge"] < safe]
        if len(below) == len(every):
            text += f", {'all ' if len(every) > 1 else ''}below the safe non-turner ({_num(safe)})"
        elif below:
            text += f"; of them {_names([algo_label(a) for a in below])} below the safe non-turner ({_num(safe)})"
    if rest and every:
        text += f"; {_names([cell(a) for a in rest])} would not"
    if seed is None:
        return text + "."
    alone = lines[lines["train seed"] == seed].set_index("policy").without_contact_charge.sort_values(ascending=False)
    return (text + f". Seed {seed} alone: "
            + ", ".join(f"{algo_label(a)} {_num(x)}" for a, x in alone.items()) + ".")


def alone_bullet(episodes: pd.DataFrame) -> str:
    """The Scenario 2 bullet (each algorithm's ``ac_0`` alone) from its AC-episodes
    (stops.episode_rows): per algorithm the goals, or how far the car drove, how far short of its
    goal it stopped and how much of the episode it spent off the road; the mean return."""
    parts = []
    for algo in algo_order(episodes.policy.unique()):
        e = episodes[episodes.policy == algo]
        goals, n = int(e.goal.sum()), len(e)
        off = e["steps off road"].sum() / max(int(e.steps.sum()), 1)
        if goals:
            what = f"reaches its goal in {goals} of {n} episodes"
        else:
            what = (f"reaches none: drives {_span(e['driven m'])} m and stands "
                    f"{_span(e['route m left'])} m short")
        parts.append(f"{algo_label(algo)} {what}, off the road in {off:.0%} of its steps ({e['return'].mean():,.1f})")
    return "- **Alone (Scenario 2, `ac_0` with no other AC)**: " + "; ".join(parts) + "."


def _span(values: pd.Series) -> str:
    """'72-75', or '72' where both ends round alike."""
    low, high = f"{values.min():,.0f}", f"{values.max():,.0f}"
    return low if low == high else f"{low}-{high}"


def _a(noun: str) -> str:
    """'a car', 'an object'."""
    return f"{'an' if noun[:1] in 'aeiou' else 'a'} {noun}"


def contact_bullet(episodes: pd.DataFrame, runs: pd.DataFrame, records: str, long: int = LONG) -> str:
    """The contact bullet of a part page from Scenario 1's AC-episodes (stops.episode_rows) and
    their contact runs of ``long``+ steps (stops.contact_runs): how many contact steps, how many in
    long runs, against what, how many last to the episode's end, per algorithm, and the longest."""
    text = (f"- **Contact**: {int(episodes['contact steps'].sum()):,} contact steps in Scenario 1's "
            f"{len(episodes)} AC-episodes, {int(runs.steps.sum()) if len(runs) else 0:,} of them in "
            f"{len(runs)} runs of {long} steps or more (`python studies/stops.py {records} --long {long}`)")
    if not len(runs):
        return text + "."
    kinds = runs.groupby("with").steps.agg(["count", "sum"]).sort_values("sum", ascending=False)
    text += ": " + ", ".join(f"{int(k['count'])} against {f'{w}s' if k['count'] > 1 else _a(w)} "
                             f"({int(k['sum']):,} steps)" for w, k in kinds.iterrows()) + "."
    ends = runs[runs.ended == "end"]
    text += (f" {len(ends)} last to the episode's end ({int(ends.steps.sum()):,} steps)." if len(ends) else
             " None lasts to the episode's end.")
    per = runs.groupby("policy").steps.agg(["count", "sum"]).sort_values("sum", ascending=False)
    text += " By algorithm: " + ", ".join(f"{algo_label(a)} {int(k['count'])} ({int(k['sum']):,} steps)"
                                          for a, k in per.iterrows()) + "."
    top = runs.sort_values("steps", ascending=False).iloc[0]
    if isinstance(top.partner, str) and top.partner:  # stops.contact_runs: "" where no AC is the partner
        held = f" against {algo_label(str(top['partner policy']))}'s `{top.partner}`"
    else:
        held = f" against {_a('background car' if top['with'] == 'car' else str(top['with']))}"
    text += (f" The longest: {algo_label(top.policy)}'s `{top.agent}`{held} from step {int(top['first step'])} of "
             f"episode {int(top['episode seed'])}, {int(top.steps)} steps"
             f"{' (to the end)' if top.ended == 'end' else ''}.")
    return text


def trial_commits(runs: Path, env: str, seed: int) -> list[tuple[str, list[str], str]]:
    """(short commit, its algorithms, when the first of them started) per commit the part's trials
    started at, in that order, from each run's manifest.json (``git`` and ``created``)."""
    by_commit: dict[str, tuple[list[str], str]] = {}
    for path in sorted(runs.glob(f"{env}__*__{seed}__*/manifest.json")):
        m = json.loads(path.read_text())
        commit = ((m.get("git") or {}).get("commit") or "unknown")[:7]
        algos, first = by_commit.get(commit, ([], m.get("created", "")))
        by_commit[commit] = (algos + [path.parent.name.split("__")[1]], min(first, m.get("created", "")))
    rows = [(c, algo_order(a), t) for c, (a, t) in by_commit.items()]
    return sorted(rows, key=lambda r: r[2])


def git_changed(first: str, last: str, paths=TRAINING_CODE) -> list[str] | None:
    """The files under ``paths`` that differ between two commits; None where git cannot tell (a
    commit not in this checkout, no git)."""
    root = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(["git", "-C", str(root), "diff", "--name-only", first, last, "--", *paths],
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.split() if out.returncode == 0 else None


def commits_bullet(commits: list[tuple[str, list[str], str]],
                   changed: Callable[[str, str], list[str] | None] = git_changed) -> str:
    """Which commit each trial started at and, where they differ, whether the training code
    (:data:`TRAINING_CODE`) differs between the first and the last: the page's claim that its
    trials trained alike, checked instead of written by hand."""
    start = commits[0][2][:16].replace("T", " ") if commits and commits[0][2] else "?"
    text = (f"- **Commits** each trial started at (its manifest.json; a trial resumed after a cut ran on "
            f"at the commit of the resume, which the loop's log names; the first started {start} UTC): "
            + ", ".join(f"{_names([algo_label(x) for x in a])} {c}" for c, a, _ in commits))
    if len(commits) < 2:
        return text + ": every trial trained on the same code."
    first, last = commits[0][0], commits[-1][0]
    diff = changed(first, last)
    where = " ".join(TRAINING_CODE)
    if diff is None:
        return text + f"; `git diff {first} {last}` cannot be read in this checkout."
    if not diff:
        return text + f"; `git diff {first} {last} -- {where}` is empty: every trial trained on the same code."
    return (text + f"; `git diff {first} {last} -- {where}` changes {', '.join(diff)}: "
            "read it before comparing the trials.")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("study", type=Path, help="a finished studies/science.py --out folder (trained there)")
    p.add_argument("--env", default=None, help="the page's environment (default: the study's only one)")
    p.add_argument("--seed", type=int, default=None, help="the page's training seed (default: the study's only one)")
    p.add_argument("--earlier", nargs="*", type=Path, default=[], metavar="STUDY",
                   help="the same environment's other seeds: their studies or exports (for seeds.csv)")
    p.add_argument("--combined", type=Path, default=None, metavar="DIR",
                   help="a studies/science.py --combine folder of the seeds together (its results.csv)")
    p.add_argument("--contact", nargs="*", type=Path, default=[], metavar="PART",
                   help="the seeds' contact.csv files or the exports holding them, this part's among them "
                        "(studies/contact_table.py): the bullet of the return without the contact charge")
    args = p.parse_args(argv)
    print(tables(args.study, args.earlier, args.combined, args.env, args.seed, args.contact))
    return 0


if __name__ == "__main__":
    sys.exit(main())
