"""The paper-ready report of ``cosim test`` and ``cosim benchmark`` (issues 13, 28).

From the per-step records of the test protocol (eval/testing/protocol.py) this writes:

- Table RQ1 as one table shaped like the paper's: the environment (its scenario
  ``title``: Straight, Three-way, ...) as a row group, the metrics as rows: first the
  driving score DS, route completion RC and success rate (the headline; docs/task.md,
  "Driving score"), the infraction penalty IP and the collision events per AC-episode
  of each kind, then the paper's CV, CO, CP, OS, RL, TTFC, SPEED, DISTANCE, return and
  goal rate, algorithms as columns in
  the paper's order, Scenario 1 | Scenario 2 side by side, and the reference policies'
  columns beside Scenario 1's algorithms when references ran. Each cell is the mean over
  episodes and its 95% bootstrap confidence interval printed as its two ends
  ``[low, high]`` (percentile, 2,000 resamples, fixed seed: the same records give the
  same table; the interval need not be symmetric, so never ``±``); one episode has no
  interval ("n = 1: no interval"); ``n`` is the number of episodes.
  "-": the metric does not apply (CV with no other vehicle, CP with no
  pedestrian); "--": TTFC of an AC that never collided. Files: ``rq1.md``,
  ``rq1_long.csv`` (one row per cell: mean, ci_low, ci_high, n),
  ``rq1_wide.csv`` (the table as printed) and ``rq1.tex`` (booktabs + multirow,
  scaled to the page width: ``\\usepackage{booktabs,multirow,graphicx}``).
- Figures (eval/reporting/figures.py), each as PDF and PNG.
- ``index.md`` and ``index.html`` (eval/reporting/page.py): what was tested and how much
  on the first screen, then everything above with a legend and its provenance as tables
  (``provenance.json``: every checkpoint with SHA-256, the run it came from and how that
  was trained, the rule that chose each AC, the task version, cosim version, git commit,
  seeds, the command line, the policy, the date).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import pandas as pd

from eval.labels import ALGO_ORDER, SCENARIO_NAMES, algo_order, env_title  # noqa: F401 - re-exported
from eval.reporting.cells import (  # noqa: F401 - re-exported: Table RQ1's cells live there
    BEST_DEGENERATE,
    DIGITS,
    HEADLINE,
    NO_INTERVAL,
    REF,
    REFERENCE_COLUMNS,
    ROW_NAMES,
    TABLE_METRICS,
    UNITS,
    _digits,
    cell,
    reference_cells,
    reference_columns,
    row_name,
    strongest,
)
from eval.reporting.stats import BOOTSTRAP, CI_SEED, bootstrap_ci
from eval.testing.metrics import episode_metrics, scenario_dt
from eval.training.options import report_keys


def per_episode(records: pd.DataFrame, dt: float | None = None) -> pd.DataFrame:
    """One row per (scenario, env, episode, AC): the metrics and the RQ2 success indicators
    (``dt``: seconds per step; None: each environment's scenario's, eval.testing.metrics.scenario_dt)."""
    parts = []
    for (scenario, env), g in records.groupby(["scenario", "env"], sort=True):
        step_s = scenario_dt(env) if dt is None else dt
        parts.append(episode_metrics(g, step_s).assign(scenario=int(scenario), env=env))
    out = pd.concat(parts, ignore_index=True)
    crashes = out[["CV", "CO", "CP"]].fillna(0.0)
    out["safety"] = (crashes.sum(axis=1) == 0).astype(float)   # a collision-free episode
    out["lane_keeping"] = 1.0 - out["OS"]                       # share of steps in its lanes
    return out


def long_table(per: pd.DataFrame, labels: Mapping[str, str] | None = None,
               metrics: Sequence[str] = (*TABLE_METRICS, "safety", "lane_keeping")) -> pd.DataFrame:
    """One row per (scenario, env, algorithm, metric): mean, 95% CI, n, and the printed cell."""
    labels = dict(labels or {})
    rows = []
    titles = {e: env_title(e) for e in per["env"].unique()}
    for (scenario, env, algo), g in per.groupby(["scenario", "env", "algorithm"], sort=True):
        episodes = int(g["episode"].nunique())
        for m in metrics:
            mean, lo, hi, n = bootstrap_ci(g[m].to_numpy())
            rows.append({"scenario": int(scenario), "env": env, "title": titles[env],
                         "algorithm": algo, "label": labels.get(algo, algo), "metric": m,
                         "mean": mean, "ci_low": lo, "ci_high": hi, "n": n,
                         "episodes": episodes, "cell": cell(m, mean, lo, hi, n, episodes)})
    return pd.DataFrame(rows)




def wide_rows(long: pd.DataFrame, metrics: Sequence[str] = TABLE_METRICS,
              refs: pd.DataFrame | None = None):
    """(header, rows, groups, cols): the combined Table RQ1 as printed; groups = [(title,
    n_rows)], cols = the (scenario, algorithm or ``ref:<policy>``) of each value column."""
    scenarios = sorted(long["scenario"].unique())
    algos = algo_order(long["algorithm"].unique())
    label = dict(zip(long["algorithm"], long["label"], strict=False))
    ref_cols = reference_columns(refs) if 1 in scenarios else []
    cols = [(s, a) for s in scenarios for a in algos + ([REF + r for r in ref_cols] if s == 1 else [])]
    header = ["Environment", "Metric"] + [
        f"S{s} {a[len(REF):]} (ref)" if a.startswith(REF) else f"S{s} {label.get(a, a)}" for s, a in cols]
    idx = long.set_index(["env", "scenario", "algorithm", "metric"])["cell"]
    eps = long.drop_duplicates(["env", "scenario", "algorithm"]).set_index(
        ["env", "scenario", "algorithm"])["episodes"]
    ref_cells = reference_cells(refs, metrics)
    rows, groups = [], []
    envs = sorted(long["env"].unique())
    titles = dict(zip(long["env"], long["title"], strict=False))

    def value(env, s, a, m):
        if a.startswith(REF):
            return ref_cells.get((env, a[len(REF):]), {}).get(m, "")
        if m == "n (episodes)":
            return str(int(eps[(env, s, a)])) if (env, s, a) in eps.index else ""
        return idx.get((env, s, a, m), "")

    for env in envs:
        block = [[titles[env], row_name(m)] + [value(env, s, a, m) for s, a in cols]
                 for m in ("n (episodes)", *metrics)]
        rows += block
        groups.append((titles[env], len(block)))
    return header, rows, groups, cols


def rq1_markdown(header, rows, groups) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    k = 0
    for title, size in groups:
        for j in range(size):
            r = rows[k + j]
            first = f"**{title}**" if j == 0 else ""
            lines.append("| " + " | ".join([first, *map(str, r[1:])]) + " |")
        k += size
    return "\n".join(lines) + "\n"


def _tex(text: str) -> str:
    out = str(text)
    for a, b in (("\\", r"\textbackslash{}"), ("_", r"\_"), ("%", r"\%"), ("&", r"\&"),
                 ("#", r"\#")):
        out = out.replace(a, b)
    return out


def _tex_cell(c: str) -> str:
    """A printed cell in LaTeX: 'm [lo, hi] (n=k)' -> '$m$ {\\scriptsize[lo, hi]}\\,$^{n=k}$'."""
    import re

    found = re.match(r"^(-?[\d.]+)( \[[^\]]+\])?(?: \(n ?= ?(\d+)[^)]*\))?$", c)
    if not found:
        return _tex(c)
    m, ci, n = found.groups()
    return (f"${m}$" + (f" {{\\scriptsize{ci}}}" if ci else "")
            + (f"\\,$^{{n={n}}}$" if n else ""))


def rq1_latex(header, rows, groups, cols) -> str:
    """booktabs + multirow, scaled to the page width; needs \\usepackage{booktabs,multirow,graphicx}."""
    scenarios = list(dict.fromkeys(s for s, _ in cols))
    width = {s: sum(1 for c, _ in cols if c == s) for s in scenarios}
    lines = [
        "% Table RQ1 (cosim test): needs \\usepackage{booktabs,multirow,graphicx}",
        r"\begin{table*}[t]", r"\centering", r"\small", r"\setlength{\tabcolsep}{3pt}",
        r"\caption{Driving errors per environment (Table RQ1): mean and [95\% bootstrap CI] over "
        r"episodes (one episode: the value alone). DS: driving score = RC $\times$ IP; RC: route "
        r"completion; success rate: goal reached with no infraction; IP: infraction penalty; CV, CO, CP "
        r"events: collision events per AC-episode. CV, CO, CP, OS, RL: fraction of steps; TTFC: s; "
        r"SPEED: km/h; DISTANCE: m; return: undiscounted sum of rewards; goal rate: share of "
        r"episodes that reached the goal. (ref): a scripted reference policy under Scenario 1 "
        r"conditions, mean over episodes x ACs. ``-'': does not apply; ``--'': no collision.}",
        r"\label{tab:rq1}",
        r"\resizebox{\textwidth}{!}{%",  # many columns of mean and CI: fit the page width
        rf"\begin{{tabular}}{{ll{'c' * len(cols)}}}", r"\toprule",
    ]
    head = ["", ""] + [rf"\multicolumn{{{width[s]}}}{{c}}{{{_tex(SCENARIO_NAMES.get(s, f'Scenario {s}'))}}}"
                       for s in scenarios]
    lines.append(" & ".join(head) + r" \\")
    start, rules_ = 3, []
    for s in scenarios:
        rules_.append(rf"\cmidrule(lr){{{start}-{start + width[s] - 1}}}")
        start += width[s]
    lines.append(" ".join(rules_))
    lines.append(" & ".join(["Environment", "Metric"] + [_tex(h.split(" ", 1)[1]) for h in header[2:]])
                 + r" \\")
    lines.append(r"\midrule")
    i = 0
    for g, (title, size) in enumerate(groups):
        for j in range(size):
            r = rows[i + j]
            first = rf"\multirow{{{size}}}{{*}}{{{_tex(title)}}}" if j == 0 else ""
            lines.append(" & ".join([first, _tex(r[1])] + [_tex_cell(c) for c in r[2:]]) + r" \\")
        i += size
        lines.append(r"\midrule" if g < len(groups) - 1 else r"\bottomrule")
    lines += [r"\end{tabular}}", r"\end{table*}"]
    return "\n".join(lines) + "\n"


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def provenance(*, policy: str, plan, algos: Sequence[str], checkpoints: Mapping | None = None,
               selections: Mapping | None = None, command: Sequence[str] | None = None,
               env_checkpoints: Sequence[Mapping] | None = None,
               benchmark: Mapping | None = None) -> dict:
    """What was tested and how: checkpoints with SHA-256 and the AC rule, seeds, the task
    version (each environment's scenario files, hashed), how each checkpoint was trained (its
    run's config.yaml), the date, and what ran it (eval.training.runfolder.software, as a run's
    manifest.json: command, versions, git commit).

    ``checkpoints`` (algorithm -> path) are the policies one test drives in every environment
    of ``plan`` (`cosim test`); ``env_checkpoints`` lists, when each environment has its own
    (`cosim benchmark`), one ``{"env", "seed", "algorithm", "path"}`` per checkpoint tested;
    ``benchmark``: the benchmark's plan (its preset, seeds, ...: BenchmarkPlan.to_dict()).
    """
    import datetime as dt

    from eval.testing import selection
    from eval.testing.protocol import rules
    from eval.training.runfolder import software

    ran = software(" ".join(["cosim", *command]) if command is not None else None)
    task = task_version(plan.envs)
    selections = dict(selections or {})
    tested = []
    for algo in algos:
        entry = {"algorithm": algo, "label": slot_label(policy, algo)}
        if checkpoints and algo in checkpoints:
            entry.update(_checkpoint_entry(Path(checkpoints[algo]), selections.get(algo)))
        tested.append(entry)
    if env_checkpoints is not None:
        where = checkpoint_provenance(policy, env_checkpoints)
    else:  # one checkpoint per algorithm, driven in every environment tested
        where = [{"env": list(plan.envs), "seed": None, "algorithm": t["algorithm"], "label": t["label"],
                  **{k: v for k, v in t.items() if k not in ("algorithm", "label")}}
                 for t in tested if "checkpoint" in t]
    return {
        "policy": policy,
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "tested": tested,
        "checkpoints": where,
        "ac_rule": selection.RULE,
        "cosim_version": ran["versions"]["cosim"],
        **ran,
        **({"benchmark": dict(benchmark)} if benchmark is not None else {}),
        "plan": {"envs": list(plan.envs), "scenarios": list(plan.scenarios),
                 "episodes": plan.episodes, "steps": test_steps(plan.steps, task), "agents": plan.agents,
                 "seed": plan.seed, "episode_seeds": [plan.seed + e for e in range(plan.episodes)],
                 **rules(plan)},
        "task": task,
        "ci": f"95% percentile bootstrap of the mean over episodes, {BOOTSTRAP} resamples, seed {CI_SEED}",
    }


def checkpoint_provenance(policy: str, env_checkpoints: Sequence[Mapping]) -> list[dict]:
    """Provenance of each ``{"env", "seed", "algorithm", "path"}`` checkpoint (its SHA-256, run,
    AC and training, :func:`_checkpoint_entry`); an entry that already holds a ``sha256`` (an
    exported study's, whose checkpoint files stayed behind: studies/science.py --export) is
    kept as it was recorded."""
    return [dict(c) if "sha256" in c else
            {"env": c["env"], "seed": c.get("seed"), "algorithm": c["algorithm"],
             "label": slot_label(policy, c["algorithm"]),
             **_checkpoint_entry(Path(c["path"]), c.get("selection"))} for c in env_checkpoints]


def _checkpoint_entry(path: Path, sel) -> dict:
    """A checkpoint's provenance: path, SHA-256, its run, the AC chosen and why, and how its
    run was trained (:func:`trained_with`)."""
    from eval.testing import selection

    if sel is None and path.parent.name.startswith("ac_"):
        sel = selection.choose(path.parent.parent.parent)
    run = path.parent.parent.parent if path.parent.name.startswith("ac_") else None
    return {"checkpoint": str(path), "sha256": sha256(path), "run": str(run) if run else None,
            "ac": sel.ac if sel else None, "chosen_by": sel.basis if sel else None,
            "scores": sel.scores if sel else {}, "trained": trained_with(run)}


TRAINING_KEYS = report_keys()
"""What the report says of a checkpoint's training run: the config.yaml keys of the run options
declared ``report`` (eval/training/options.py) and the horizon and camera size; and its agents'
``action_repeat``, docs/task.md "Action repeat"."""


def trained_with(run: Path | None) -> dict:
    """The training settings of a run folder (its config.yaml, :data:`TRAINING_KEYS`); {} when
    the checkpoint has no run folder (a file given with --checkpoint) or it cannot be read."""
    if run is None or not (Path(run) / "config.yaml").exists():
        return {}
    import yaml

    try:
        cfg = yaml.safe_load((Path(run) / "config.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    repeat = (cfg.get("agent_config") or {}).get("action_repeat", 1)
    return {k: cfg[k] for k in TRAINING_KEYS if k in cfg} | {"action_repeat": repeat}


def test_steps(steps: int | None, task: Mapping) -> int | dict | None:
    """The steps per test episode a plan ran: ``steps``, or with None (each scenario's horizon)
    that horizon when the environments share it, else ``{env: horizon}`` (``task``:
    :func:`task_version`'s)."""
    if steps is not None:
        return int(steps)
    horizons = {env: t["horizon"] for env, t in task.items() if "horizon" in t}
    if len(set(horizons.values())) == 1 and len(horizons) == len(task):
        return next(iter(horizons.values()))
    return horizons or None


def task_version(envs: Sequence[str]) -> dict:
    """Per environment: its title, the SHA-256 (first 12 hex digits) of its scenario files (the
    YAML, the network, the demand and additional files: the task a result belongs to), its
    seconds per step and its horizon."""
    from cosim.scenario import load_scenario

    out = {}
    for env in envs:
        try:
            sc = load_scenario(env)
        except Exception:  # noqa: BLE001 - a report must not fail on a hash
            out[env] = {"title": env_title(env)}
            continue
        h = hashlib.sha256()
        for f in [sc.source, sc.net, *sc.demand, *sc.pedestrian_demand, *sc.additional]:
            h.update(Path(f).name.encode())
            h.update(Path(f).read_bytes())
        out[env] = {"title": sc.title or env, "sha256": h.hexdigest()[:12], "dt": float(sc.dt),
                    "horizon": int(sc.horizon)}
    return out


def slot_label(policy: str, algo: str) -> str:
    """Column label: the algorithm, or '<policy> (<algo> slot)' for a reference policy."""
    return algo if policy == "trained" else f"{policy} ({algo} slot)"


def write_paper_report(records: pd.DataFrame, out: Path, *, prov: dict | None = None,
                       references: pd.DataFrame | None = None, replays: Sequence[dict] = (),
                       dt: float | None = None, figures: bool = True, extra_md: str = "") -> list[Path]:
    """The combined Table RQ1 (md, csv long/wide, tex), figures, index.md/html, provenance."""
    from eval.reporting import figures as figs
    from eval.testing.metrics import metrics_table
    from eval.testing.records import save

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    prov = prov or {"policy": "trained", "tested": []}
    save(records, out / "records.parquet")
    metrics_table(records, dt).to_csv(out / "metrics.csv", index=False)
    if references is not None and not references.empty:
        references.to_csv(out / "references.csv", index=False)
    labels = {t["algorithm"]: t["label"] for t in prov.get("tested", [])}
    per = per_episode(records, dt)
    per.to_csv(out / "episodes.csv", index=False)
    long = long_table(per, labels)
    long.to_csv(out / "rq1_long.csv", index=False)
    header, rows, groups, cols = wide_rows(long, refs=references)
    pd.DataFrame(rows, columns=header).to_csv(out / "rq1_wide.csv", index=False)
    md = rq1_markdown(header, rows, groups)
    (out / "rq1.md").write_text(md)
    (out / "rq1.tex").write_text(rq1_latex(header, rows, groups, cols))
    (out / "provenance.json").write_text(json.dumps(prov, indent=2, default=str))
    written = [out / n for n in ("records.parquet", "metrics.csv", "episodes.csv", "rq1_long.csv", "rq1_wide.csv", "rq1.md",
                                 "rq1.tex", "provenance.json")]
    figures_written = figs.write_all(records, per, long, out, labels, dt) if figures else []
    if figures:
        figures_written += figs.driving_score_heatmap(long, references, out, labels)
    written += figures_written
    index_md = rq1_markdown(*with_replay_links(header, rows, groups, cols, replays))
    written += write_index(out, index_md, prov, figures_written, references, replays, extra_md,
                           long=long, per=per)
    (out / "report.md").write_text((out / "index.md").read_text())
    written.append(out / "report.md")
    if references is not None and not references.empty:
        written.append(out / "references.csv")
    return written


FILE_NOTES = {
    "records.parquet": "per-step records (one row per AC per step): the raw material of every metric",
    "metrics.csv": "means per scenario, environment and algorithm (earlier format)",
    "episodes.csv": "metrics per episode and AC (what the intervals resample)",
    "rq1.md": "Table RQ1, Markdown",
    "rq1_long.csv": "Table RQ1, one row per cell: mean, ci_low, ci_high, n",
    "rq1_wide.csv": "Table RQ1 as printed",
    "rq1.tex": "Table RQ1, LaTeX (booktabs, multirow)",
    "provenance.json": "what was tested: checkpoints, hashes, versions, seeds, command",
    "references.csv": "reference rows (scripted policies)",
    "ds_heatmap.png": "driving score per algorithm x environment, Scenario 1, references below (PDF beside)",
    "report.md": "this page as printed by cosim test",
    "crossplay.csv": "cross-play: the ego's collision and goal rates per partner (per environment and pooled)",
    "crossplay.md": "cross-play matrix, Markdown",
    "seeds.csv": "each training seed's means over its test episodes (eval/reporting/multiseed.py)",
    "over_seeds.csv": "mean and 95% CI over training seeds of every metric",
    "verdict.csv": "the verdict per (algorithm, environment): driving score over seeds against the references",
    "iqm.csv": "IQM of the normalised driving score per algorithm, stratified bootstrap CI",
    "budget.csv": "per run: did its training return still rise at the end of its budget?",
}


def with_replay_links(header, rows, groups, cols, replays: Sequence[dict]):
    """The table for the index: a 'first collision' row after TTFC in each environment,
    linking the failure replay of each column that has one (eval/testing/replay.py)."""
    if not replays:
        return header, rows, groups
    by = {(r["title"], r["scenario"], r["algorithm"]): r for r in replays}
    out_rows, out_groups, k = [], [], 0
    for title, size in groups:
        block = rows[k:k + size]
        k += size
        links = [title, "first collision"] + [
            f"[clip]({by[(title, s, a)]['strip']}) [state]({by[(title, s, a)]['meta']})"
            if (title, s, a) in by else "" for s, a in cols]
        at = next((i for i, r in enumerate(block) if r[1] == "TTFC"), len(block) - 1) + 1
        out_rows += [*block[:at], links, *block[at:]]
        out_groups.append((title, size + 1))
    return header, out_rows, out_groups


def write_index(out: Path, rq1_md: str, prov: dict, figures: Sequence[Path],
                references: pd.DataFrame | None, replays: Sequence[dict],
                extra_md: str = "", long: pd.DataFrame | None = None,
                per: pd.DataFrame | None = None) -> list[Path]:
    """index.md and index.html (eval/reporting/page.py): what was tested, the table, the
    figures, the replays, the references, provenance, every file."""
    from eval.reporting import page

    out = Path(out)
    listed = sorted(p.relative_to(out).as_posix() for p in out.rglob("*")
                    if p.is_file() and p.name not in ("index.md", "index.html", "report.md"))
    text = page.index_markdown(prov, rq1_md, figures=[f.name for f in figures], references=references,
                               replays=replays, extra_md=extra_md, long=long, per=per,
                               files={rel: FILE_NOTES.get(rel.rsplit("/", 1)[-1], "") for rel in listed})
    (out / "index.md").write_text(text)
    (out / "index.html").write_text(page.markdown_to_html(text, page.title(prov)))
    return [out / "index.md", out / "index.html"]

