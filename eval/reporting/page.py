"""The report's index page (issue 28): what a reader sees first, in words and small tables.

Its first screen answers who drives best where (:func:`who_drives_markdown`: the driving-score
heat map, one sentence per environment), then says what produced the page (``cosim benchmark`` or ``cosim test``), what
was tested and how much: the command, the preset and training budget per algorithm, the ACs,
episodes and steps, the seeds, the task version (each environment's scenario files, hashed;
the observation and action settings), the date and the commit; then the headline, the driving
score DS, route completion RC and success rate of every column with their 95% intervals
(:func:`headline_markdown`; docs/task.md, "Driving score"). Then the legend (every
abbreviation on the page spelled out), Table RQ1, the figures, the failure replays, the
reference rows, and provenance as tables (never a Python dict).

Everything here is read from ``provenance.json`` (eval.reporting.report.provenance) and the
tables the report computed; :func:`markdown_to_html` turns the Markdown into the HTML page.
"""

from __future__ import annotations

import html
import re
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from eval.labels import algo_order, env_title
from eval.testing.metrics import DEFINITIONS

PAGE_TERMS = {
    "S1": "Scenario 1 (multi-agent): the ACs drive together among the scenario's background cars "
          "and pedestrians",
    "S2": "Scenario 2 (single-agent): each AC alone, no other vehicle, no pedestrian",
    "AC": "autonomous car: a car driven by a policy under test (the other cars are SUMO's)",
    "n": "episodes a cell averages (n=k: the metric applied in k of them); reference columns: "
         "episodes x ACs",
    "CI": "95% confidence interval, percentile bootstrap of the mean over episodes, printed "
          "[low, high]; one episode has none (n = 1: no interval)",
    "(ref)": "a scripted reference policy (eval/testing/validity.py) under Scenario 1 conditions, "
             "mean over episodes x ACs: autopilot = the privileged scripted driver, "
             "autopilot-discrete = the same restricted to the nine discrete actions (a discrete "
             "learner's ceiling), safe-non-turner = the autopilot that stops before its first "
             "turn, random = uniform over the nine discrete actions",
    "best degenerate": "the degenerate policy (always-forward, always-brake, full-left, ...) "
                       "with the highest mean driving score in that environment (the return "
                       "where the references have none), named in its n row",
    "CARLA": "the CARLA Leaderboard (leaderboard.carla.org), whose driving score (route completion "
             "x infraction penalty) and penalty factors DS and IP follow",
    "Safety": "share of episodes without a collision step (CV = CO = CP = 0)",
    "Lane keeping": "1 - OS: share of steps inside its own lanes",
    "-": "the metric does not apply (CV with no other vehicle, CP with no pedestrian)",
    "--": "TTFC of an AC that never collided",
}
"""The page's own terms, beside the metrics' definitions (eval.testing.metrics.DEFINITIONS)."""


def kind(prov: Mapping) -> str:
    """What produced the report: ``benchmark``, ``test`` or ``science study``, from its command."""
    words = str(prov.get("command") or "").split()
    if any("science" in w for w in words[:2]):
        return "science study"
    if "benchmark" in prov or words[1:2] == ["benchmark"]:
        return "benchmark"
    return "test"


def title(prov: Mapping) -> str:
    """The page title: what produced it (and the benchmark's preset)."""
    preset = (prov.get("benchmark") or {}).get("preset")
    return f"cosim {kind(prov)} report" + (f" (preset {preset})" if preset else "")


def _commit(prov: Mapping) -> str:
    git = prov.get("git") or {}
    if not git.get("commit"):
        return "unknown (not run from a git checkout)"
    return git["commit"][:10] + (" with uncommitted changes" if git.get("dirty") else " (clean)")


def _names(algos: Sequence[str], labels: Mapping[str, str]) -> str:
    names = [labels.get(a, a) for a in algos]
    return ", ".join(names[:-1]) + (" and " if len(names) > 1 else "") + names[-1] if names else "no algorithm"


def _trained(prov: Mapping) -> dict[str, list[dict]]:
    """Algorithm -> the training settings (config.yaml) of every checkpoint of it tested."""
    out: dict[str, list[dict]] = {}
    for c in prov.get("checkpoints", []):
        if c.get("trained"):
            out.setdefault(c["algorithm"], []).append(c["trained"])
    return out


def _one(values) -> str:
    """A setting that should be one value: it, or every distinct value."""
    seen = list(dict.fromkeys(str(v) for v in values))
    return seen[0] if len(seen) == 1 else " / ".join(seen)


def budget_rows(prov: Mapping, algos: Sequence[str], labels: Mapping[str, str]) -> list[list[str]]:
    """Per algorithm: preset, environment steps per training run, ACs trained, training seeds,
    observation and action (from the checkpoints' run folders)."""
    from agents import registry

    trained = _trained(prov)
    rows = []
    for a in algos:
        runs = trained.get(a, [])
        action = "" if a not in registry.ALGORITHMS else (
            "Box(-1, 1, (2,)) continuous" if a in registry.CONTINUOUS else "Discrete(9)")
        if not runs:
            rows.append([labels.get(a, a), "-", "-", "-", "-", "-", action])
            continue
        obs = _one(f"{r.get('obs', '?')} {r.get('image_size', '?')}px x {r.get('frame_stack', '?')} frames"
                   for r in runs)
        repeat = _one(r.get("action_repeat", 1) for r in runs)
        action += "" if repeat == "1" else f", each held {repeat} steps"
        rows.append([labels.get(a, a), _one(r.get("preset") for r in runs),
                     _one(f"{int(r['steps']):,}" for r in runs if "steps" in r),
                     _one(r.get("agents") for r in runs),
                     ", ".join(dict.fromkeys(str(r.get("seed")) for r in runs)), obs, action])
    return rows


def md_table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A Markdown table (a ``|`` inside a cell is written ``/``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c).replace("|", "/") for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def first_screen(prov: Mapping, algos: Sequence[str], labels: Mapping[str, str]) -> list[str]:
    """What was tested and how much, in words and a small table (the page's first screen)."""
    plan = prov.get("plan", {})
    bench = prov.get("benchmark")
    task = prov.get("task", {})
    envs = plan.get("envs", [])
    titles = [task.get(e, {}).get("title") or env_title(e) for e in envs]
    dt = _one(task.get(e, {}).get("dt", "?") for e in envs) if envs else "?"
    steps, episodes = plan.get("steps"), plan.get("episodes")
    seconds = (f" ({steps * float(dt):g} s)" if isinstance(steps, int) and dt.replace(".", "", 1).isdigit()
               else "")
    if isinstance(steps, dict):  # each scenario's own horizon, and they differ
        steps = "/".join(str(v) for v in steps.values())
    scen = plan.get("scenarios", [1, 2])
    tested = " and ".join(
        [f"Scenario 1 ({plan.get('agents')} ACs together in the scenario's traffic)"] * (1 in scen)
        + ["Scenario 2 (each AC alone)"] * (2 in scen))
    trained = _trained(prov)
    budget = budget_rows(prov, algos, labels)
    if bench:  # a benchmark or a science study: trained here, each environment its own policies
        steps_of = {r[0]: r[2] for r in budget}
        per_algo = ("" if len(set(steps_of.values())) != 1 else f"{next(iter(steps_of.values()))} "
                    "environment steps per trial")
        acs = _one(r[3] for r in budget)
        what = (f"`{prov.get('command')}` trained {_names(algos, labels)} in {len(envs)} environment(s) "
                f"({', '.join(titles)}), {bench.get('seeds')} seed(s) each, with the "
                f"`{bench.get('preset')}` preset ({per_algo or 'budget per algorithm below'}, "
                f"{acs} ACs per trial), then tested each environment's own trained policies in {tested}")
    elif prov.get("policy", "trained") == "trained":
        where = {r["env"] for runs in trained.values() for r in runs if r.get("env")}
        trained_in = (f"trained in {', '.join(env_title(e) for e in sorted(map(str, where)))}" if where
                      else "where they were trained is unknown: their run folders hold no config.yaml")
        what = (f"`{prov.get('command')}` tested checkpoints of {_names(algos, labels)} ({trained_in}) in {len(envs)} "
                f"environment(s) ({', '.join(titles)}) in {tested}")
    else:
        what = (f"`{prov.get('command')}` drove every AC with the {prov.get('policy')} reference policy "
                f"(no trained checkpoint) in {len(envs)} environment(s) ({', '.join(titles)}) in {tested}")
    seeds = plan.get("episode_seeds", [])
    seed_text = (f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]}..{seeds[-1]}") if seeds else "?"
    md = [f"**What was tested.** {what}: {episodes} episode(s) of {steps} steps{seconds} per "
          f"environment and scenario, on episode seed(s) {seed_text}. Run {prov.get('date', '(date not recorded)')} "
          f"at commit {_commit(prov)}.\n"]
    rows = [["produced by", f"`{prov.get('command', '')}`"]]
    if bench:
        n_seeds = int(bench.get("seeds", 1))
        rows.append(["preset", f"{bench.get('preset')} (training seed{'s 0..' if n_seeds > 1 else ' '}"
                               f"{n_seeds - 1}, training episodes at a collision: {bench.get('collisions')})"])
    rows.append(["training budget", "; ".join(f"{r[0]} {r[2]} env steps x {r[3]} ACs" for r in budget
                                              if r[2] != "-") or "unknown (no run config.yaml)"])
    rows.append(["test", f"{plan.get('agents')} ACs, {episodes} episode(s) x {steps} steps per "
                         f"environment and scenario; episode seeds {seed_text}"])
    rows.append(["task version", f"{prov.get('task_version', '1 (not recorded)')} (cosim.TASK_VERSION); scenarios: " + "; ".join(
        f"{task.get(e, {}).get('title', e)} ({e}) {task.get(e, {}).get('sha256', '?')}" for e in envs)])
    obs = _one(r[5] for r in budget if r[5] != "-") if any(r[5] != "-" for r in budget) else "observation unknown"
    acts = {}
    for r in budget:
        acts.setdefault(r[6], []).append(r[0])
    rows.append(["observation / action", f"{obs}; " + "; ".join(f"{k}: {', '.join(v)}" for k, v in acts.items())])
    rows.append(["date, commit", f"{prov.get('date', '-')}, {_commit(prov)}"])
    md.append(md_table(["setting", "value"], rows))
    return md


def legend(terms: Sequence[str]) -> str:
    """Every metric and abbreviation on the page, spelled out."""
    from eval.reporting.cells import row_name

    rows = [[row_name(t), DEFINITIONS[t]] for t in terms if t in DEFINITIONS]
    rows += [[t, d] for t, d in PAGE_TERMS.items()]
    return md_table(["term", "meaning"], rows)


HEADLINE_NOTE = ("**Driving score** (the headline; docs/task.md, \"Driving score\"): per AC-episode "
                 "DS = RC x IP, route completion (the share of the route driven along its lanes, 1 at "
                 "the goal) times the infraction penalty (0.60 per vehicle collision event, 0.50 per "
                 "pedestrian, 0.65 per static object, 0.70 per red light); success: the goal reached "
                 "with no infraction. Mean [95% CI] over episodes; (ref) rows: scripted reference "
                 "policies under Scenario 1 conditions, mean over episodes x ACs. The paper's metrics "
                 "follow in Table RQ1.\n")


def headline_markdown(long: pd.DataFrame | None, references: pd.DataFrame | None = None,
                      labels: Mapping[str, str] | None = None) -> str:
    """The page's first table: per environment, scenario and column (then the reference columns
    of Table RQ1) the driving score, route completion and success rate with their intervals, as
    Table RQ1's cells (eval.reporting.report.long_table); empty without a table."""
    from eval.reporting.cells import HEADLINE, reference_cells, reference_columns, row_name

    if long is None or long.empty or not set(HEADLINE) & set(long["metric"]):
        return ""
    labels = dict(labels or {})
    cells = long.set_index(["env", "scenario", "algorithm", "metric"])["cell"]
    eps = long.drop_duplicates(["env", "scenario", "algorithm"]).set_index(
        ["env", "scenario", "algorithm"])["episodes"]
    refs = reference_cells(references, HEADLINE)
    algos = algo_order(long["algorithm"].unique())
    rows = []
    for env in sorted(long["env"].unique()):
        for s in sorted(long.loc[long["env"] == env, "scenario"].unique()):
            for a in algos:
                if (env, s, a) not in eps.index:
                    continue
                rows.append([env_title(env), f"S{s}", labels.get(a, a)]
                            + [cells.get((env, s, a, m), "") for m in HEADLINE] + [str(int(eps[(env, s, a)]))])
            if s == 1:
                for col in reference_columns(references):
                    c = refs.get((env, col))
                    if c:
                        rows.append([env_title(env), "S1", f"{col} (ref)"] + [c.get(m, "") for m in HEADLINE]
                                    + [c["n (episodes)"]])
    header = ["environment", "scenario", "policy", *[row_name(m) for m in HEADLINE], "n"]
    return HEADLINE_NOTE + "\n" + md_table(header, rows)


def who_drives_markdown(long: pd.DataFrame | None, references: pd.DataFrame | None,
                        labels: Mapping[str, str], figure: str | None) -> str:
    """The page's opening answer to "who drives best where": one sentence per environment, then
    the driving-score heat map (eval.reporting.figures.driving_score_heatmap). Each sentence: the best
    algorithm by mean DS with its interval, how many clear every degenerate reference by the
    lower end of their interval (the verdict's rule), and the safe non-turner and autopilot."""
    from eval.reporting.figures import driving_score_matrix

    if long is None or long.empty or "DS" not in set(long["metric"]):
        return ""
    table = driving_score_matrix(long, references, labels)
    lines = ["## Who drives best where\n"]
    for env in dict.fromkeys(long["env"]):
        here = table[table["env"] == env]
        algos = here[~here["reference"]].sort_values("DS", ascending=False, kind="stable")
        if algos.empty:
            continue
        best = algos.iloc[0]
        text = (f"**{env_title(env)}**: {best['row']} drives best, DS {best['DS']:.2f}"
                + (f" [{best['lo']:.2f}, {best['hi']:.2f}]" if np.isfinite(best["lo"]) else ""))
        refs = here[here["reference"]].set_index("row")["DS"]
        if algos["clears"].notna().any():
            passing = list(algos.loc[algos["clears"] == True, "row"])  # noqa: E712 - NaN-safe
            floor = algos["floor"].iloc[0]
            text += (f"; {len(passing)} of {len(algos)} clear every degenerate reference (the strongest"
                     f" {floor:.2f}) by their interval's lower end"
                     + (f" ({', '.join(passing)})" if passing else ""))
        for name, what in (("safe-non-turner (ref)", "the safe non-turner"), ("autopilot (ref)", "the autopilot")):
            if name in refs.index and np.isfinite(refs[name]):
                text += f"; {what} {refs[name]:.2f}"
        lines.append(text + ".\n")
    if figure:  # below the one-line verdicts, so that both fit the first screen
        lines.append(f"![{figure[:-4]}]({figure}) ([PDF]({figure[:-4]}.pdf))\n")
    return "\n".join(lines)


def interval_note(long: pd.DataFrame | None) -> str:
    """What the cells' intervals are; says so when every cell is one episode."""
    one = long is not None and not long.empty and int(long["episodes"].max()) == 1
    if one:
        return ("Every cell is one episode's value: **n = 1: no interval** (a confidence interval "
                "needs at least two episodes). ")
    return ("Cells: mean [95% CI low, high] over episodes (a percentile bootstrap: the interval "
            "need not be symmetric about the mean); n = 1: no interval. ")


def identical_scenarios_note(per: pd.DataFrame | None, labels: Mapping[str, str],
                             metrics: Sequence[str] = ("CO", "OS", "RL", "TTFC", "SPEED", "DISTANCE",
                                                       "return", "goal")) -> str:
    """A note naming the algorithms whose Scenario 1 and 2 columns agree in every environment,
    and why that happens (empty when none does)."""
    if per is None or per.empty or set(per["scenario"]) != {1, 2}:
        return ""
    same = []
    for algo, g in per.groupby("algorithm"):
        envs = sorted(g["env"].unique())
        equal = True
        for env in envs:
            a = g[(g["env"] == env) & (g["scenario"] == 1)].sort_values("episode")[list(metrics)]
            b = g[(g["env"] == env) & (g["scenario"] == 2)].sort_values("episode")[list(metrics)]
            if len(a) != len(b) or not a.reset_index(drop=True).equals(b.reset_index(drop=True)):
                equal = False
                break
        if equal:
            same.append(algo)
    if not same:
        return ""
    return (f"\n**Identical Scenario 1 and 2 columns** ({_names(algo_order(same), labels)}; CV and CP "
            "aside, which Scenario 2 cannot have): the same episode seed gives the same spawn and the "
            "same seeded actions in both scenarios, so an AC that met no other car or pedestrian in "
            "the steps it drove (short episodes, a policy that stops early or leaves the road first) "
            "drives the same trajectory in both.\n")


def _scores(scores: Mapping | None) -> str:
    return ", ".join(f"{k} {float(v):.1f}" for k, v in (scores or {}).items()) or "-"


def provenance_markdown(prov: Mapping) -> list[str]:
    """Provenance as tables: what ran, the test plan, the task version, every checkpoint."""
    md = ["\n## Provenance\n", "### What ran\n"]
    git = prov.get("git") or {}
    rows = [["command", f"`{prov.get('command', '')}`"], ["date", prov.get("date", "-")],
            ["git commit", git.get("commit", "unknown")],
            ["uncommitted changes", "yes" if git.get("dirty") else "no" if git else "unknown"]]
    started = prov.get("git_at_start") or {}
    if started.get("commit") and started.get("commit") != git.get("commit"):
        rows.append(["git commit of the code that ran (at the process's start)", started["commit"]
                     + (" (uncommitted changes)" if started.get("dirty") else "")])
    rows += [["policy", prov.get("policy", "trained")], ["Python", prov.get("python", "-")],
            ["platform", prov.get("platform", "-")], ["CPU", prov.get("cpu") or "-"]]
    rows += [[f"{pkg} version", v or "not installed"] for pkg, v in (prov.get("versions") or {}).items()]
    md.append(md_table(["what", "value"], rows))
    if prov.get("benchmark"):
        md.append("### Benchmark plan\n")
        md.append(md_table(["setting", "value"], [[k, _value(v)] for k, v in prov["benchmark"].items()]))
    md.append("### Test plan\n")
    md.append(md_table(["setting", "value"], [[k, _value(v)] for k, v in prov.get("plan", {}).items()]
                       + [["confidence intervals", prov.get("ci", "")],
                          ["AC chosen per run by", prov.get("ac_rule", "")]]))
    task = prov.get("task", {})
    if task:
        md.append("### Task version\n")
        md.append("The scenario files of each environment (YAML, network, demand, additional files), "
                  "hashed together: the same hash, the same task.\n")
        md.append(md_table(["environment", "title", "scenario files SHA-256 (first 12)", "seconds per step",
                            "scenario horizon (steps)"],
                           [[e, t.get("title", e), t.get("sha256", "?"), t.get("dt", "?"), t.get("horizon", "?")]
                            for e, t in task.items()]))
    md.append("### Checkpoints\n")
    ckpts = prov.get("checkpoints", [])
    if not ckpts:
        md.append(f"No checkpoint: every AC was driven by the {prov.get('policy')} policy.\n")
    else:
        md.append("Every checkpoint tested, with the environment it drove in and the one it was trained in "
                  "(its run's config.yaml).\n")
        rows = []
        for c in ckpts:
            env = c["env"]
            tested_in = ", ".join(env_title(e) for e in env) if isinstance(env, list) else env_title(env)
            t = c.get("trained") or {}
            trained = (f"{env_title(t['env'])} ({t.get('preset', '?')}, {int(t.get('steps', 0)):,} steps, "
                       f"{t.get('agents', '?')} ACs, seed {t.get('seed', '?')})" if t.get("env") else "-")
            rows.append([tested_in, "-" if c.get("seed") is None else c["seed"], c.get("label", c["algorithm"]),
                         trained, f"`{c['checkpoint']}`", c.get("sha256", "-"), c.get("ac") or "-",
                         c.get("chosen_by") or "-", _scores(c.get("scores"))])
        md.append(md_table(["tested in", "seed", "column", "trained in", "checkpoint", "SHA-256", "AC",
                            "chosen by", "scores per AC"], rows))
    return md


def _value(v) -> str:
    if isinstance(v, list | tuple):
        return ", ".join(map(str, v)) or "-"
    if isinstance(v, dict):
        return "; ".join(f"{k}: {_value(x)}" for k, x in v.items()) or "-"
    return "-" if v is None else str(v)


def replays_markdown(replays: Sequence[dict]) -> list[str]:
    """The failure replays table; a replay not reproduced says why when the code knows."""
    md = ["\n## Failure replays (first collision per algorithm and environment)\n",
          "The moment TTFC measures, and the first step counted by the metric named: the AC's camera "
          "and a top-down view from 3 s before to 1 s after (the strip's frames are labelled with "
          "their time from the collision), and the SUMO state at the collision step.\n",
          "| scenario | environment | algorithm | episode | step | TTFC (s) | metric | frames | camera | "
          "overview | SUMO state | reproduced |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    metric = {"vehicle": "CV", "object": "CO", "pedestrian": "CP"}
    for r in replays:
        why = f": {r['why']}" if r.get("why") else ""
        md.append(f"| {r['scenario']} | {r['title']} | {r['label']} | {r['episode']} | "
                  f"{r['step']} | {r['ttfc']:.1f} | {metric.get(r['kind'], r['kind'])} | "
                  f"[strip]({r['strip']}) | [gif]({r['camera']}) | "
                  f"[gif]({r['overview']}) | [xml]({r['state']}) ([json]({r['meta']})) | "
                  f"{'yes' if r['reproduced'] else 'NO' + why} |")
    md.append("\nReopen a state with `cosim replay <state.json>` (prints the positions, "
              "`--plot` draws them) or in sumo-gui (`--load-state`).\n")
    return md


def references_markdown(refs: pd.DataFrame) -> str:
    """The whole reference suite per environment, headed by the environments' titles."""
    from eval.testing import validity

    parts = ["## Reference rows (Scenario 1 conditions, scripted policies)\n",
             "Fixed policies on the same environments, AC count, steps and episodes "
             "(docs/scenarios.md): a trained AC should beat every degenerate row; "
             "autopilot-discrete is the ceiling of a discrete learner, and a learner that "
             "beats safe-non-turner learned to turn (docs/task.md, \"Reference policies\"). "
             "Table RQ1 shows the main ones as (ref) columns.\n"]
    for env, g in refs.groupby("env", sort=False):
        parts.append(f"\n### {env_title(env)} ({env})\n\n" + validity.format_table(g.set_index("policy")) + "\n")
    return "\n".join(parts)


FIGURE_NOTE = ("RQ2 success rates: **Safety** = share of episodes without a collision step "
               "(CV = CO = CP = 0); **Efficiency** = SPEED and DISTANCE; **Lane keeping** = "
               "1 - OS (share of steps inside its own lanes). Error bars: 95% bootstrap CI (none "
               "where n = 1). A bar of height zero carries a \"0\" label; a missing bar (the metric "
               "does not apply) carries \"n/a\".\n")


def index_markdown(prov: Mapping, rq1_md: str, *, figures: Sequence[str], references: pd.DataFrame | None,
                   replays: Sequence[dict], extra_md: str, long: pd.DataFrame | None,
                   per: pd.DataFrame | None, files: Mapping[str, str]) -> str:
    """The whole index page as Markdown (module docstring)."""
    policy = prov.get("policy", "trained")
    tested = prov.get("tested", [])
    labels = {t["algorithm"]: t["label"] for t in tested}
    algos = [t["algorithm"] for t in tested] or (algo_order(long["algorithm"].unique()) if long is not None else [])
    md = [f"# {title(prov)}\n"]
    heatmap = next((f for f in figures if f == "ds_heatmap.png"), None)
    md.append(who_drives_markdown(long, references, labels, heatmap))
    md += first_screen(prov, algos, labels)
    headline = headline_markdown(long, references, labels)
    if headline:
        md += ["## Driving score\n", headline]
    if policy != "trained":
        md.append(f"**Policy: {policy}.** Every AC was driven by the {policy} reference, not by "
                  f"a trained checkpoint; columns are labelled '{policy} (<algorithm> slot)'.\n")
    md.append("## Table RQ1\n")
    md.append(interval_note(long) + "S1 = Scenario 1 (multi-agent), S2 = Scenario 2 (single-agent); "
              "(ref) columns: scripted reference policies under Scenario 1 conditions. Every "
              "abbreviation is defined in the legend below the table.\n")
    md.append(rq1_md)
    md.append(identical_scenarios_note(per, labels))
    md.append("\n### Legend\n")
    md.append(legend(list(DEFINITIONS)))
    md.append("\n## Figures\n")
    md.append(FIGURE_NOTE)
    for f in figures:
        if f.endswith(".png") and f != heatmap:
            md.append(f"![{f[:-4]}]({f}) ([PDF]({f[:-4]}.pdf))\n")
    if replays:
        md += replays_markdown(replays)
    if references is not None and not references.empty:
        md.append("\n" + references_markdown(references))
    if extra_md:
        md.append(extra_md)
    md += provenance_markdown(prov)
    md.append("\n## Files\n")
    md += [f"- [{rel}]({rel}){': ' + note if note else ''}" for rel, note in files.items()]
    return re.sub(r"\n{3,}", "\n\n", "\n".join(md)) + "\n"


NUMBER = re.compile(r"^(-?[\d.,]+( \[[^\]]*\])?( \([^)]*\))?|-{1,2}|\d+ AC-episodes)$")
"""A table cell that is a number (a value, its interval, its n; "-", "--"): right-aligned."""


def markdown_to_html(text: str, title: str) -> str:
    """The small Markdown subset index.md uses (headings, tables, lists, links, images)."""

    def inline(s: str) -> str:
        s = html.escape(s, quote=False)
        s = re.sub(r"!\[([^\]]*)\]\(([^)]+)\)", r'<img src="\2" alt="\1" style="max-width:100%">', s)
        s = re.sub(r"\[([^\]]+)\]\(([^)]+)\)", r'<a href="\2">\1</a>', s)
        s = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", s)
        return re.sub(r"`([^`]+)`", r"<code>\1</code>", s)

    body, table, lst = [], [], False
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            table.append(line)
            continue
        if table:
            cells = [[c.strip() for c in r.strip("|").split("|")] for r in table if not set(r) <= set("|-")]
            body.append("<table>" + "".join(
                "<tr>" + "".join(f"<th>{inline(c)}</th>" if i == 0 else
                                 f"<td class='n'>{inline(c)}</td>" if NUMBER.match(c) else f"<td>{inline(c)}</td>"
                                 for c in r) + "</tr>" for i, r in enumerate(cells)) + "</table>")
            table = []
        if line.startswith("- "):
            if not lst:
                body.append("<ul>")
                lst = True
            body.append(f"<li>{inline(line[2:])}</li>")
            continue
        if lst:
            body.append("</ul>")
            lst = False
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            body.append(f"<h{level}>{inline(line[level:].strip())}</h{level}>")
        elif line.strip():
            body.append(f"<p>{inline(line)}</p>")
    style = ("body{font-family:sans-serif;max-width:1400px;margin:auto;padding:0 8px}"
             "table{border-collapse:collapse;font-size:12px;margin-bottom:8px}"
             "td,th{border:1px solid #ccc;padding:2px 6px;text-align:left}td.n{text-align:right}"
             "img{max-width:100%}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
