"""The paper-ready report of ``cosim test`` (issue 13).

From the per-step records of the test protocol (eval/testing/protocol.py) this writes:

- Table RQ1 as one table shaped like the paper's: the environment (its scenario
  ``title``: Straight, Three-way, ...) as a row group, the metrics CV, CO, CP, OS,
  RL, TTFC (then SPEED, DISTANCE) as rows, algorithms as columns in the paper's
  order, Scenario 1 | Scenario 2 side by side. Each cell is the mean over episodes
  with a 95% bootstrap confidence interval (percentile, 2,000 resamples, fixed
  seed: the same records give the same table); ``n`` is the number of episodes.
  "-": the metric does not apply (CV with no other vehicle, CP with no
  pedestrian); "--": TTFC of an AC that never collided. Files: ``rq1.md``,
  ``rq1_long.csv`` (one row per cell: mean, ci_low, ci_high, n),
  ``rq1_wide.csv`` (the table as printed) and ``rq1.tex`` (booktabs + multirow,
  scaled to the page width: ``\\usepackage{booktabs,multirow,graphicx}``).
- Figures (eval/reporting/figures.py), each as PDF and PNG.
- ``index.md`` and ``index.html``: everything above with its provenance
  (``provenance.json``: runs and checkpoints with SHA-256, the rule that chose each
  AC, cosim version, git commit, seeds, the command line, the policy).
"""

from __future__ import annotations

import hashlib
import html
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eval.labels import ALGO_ORDER, SCENARIO_NAMES, algo_order, env_title  # noqa: F401 - re-exported
from eval.testing.metrics import episode_metrics, scenario_dt

TABLE_METRICS = ("CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED", "DISTANCE")
BOOTSTRAP = 2000
CI_SEED = 0
UNITS = {"TTFC": "s", "SPEED": "km/h", "DISTANCE": "m"}


def bootstrap_ci(values, resamples: int = BOOTSTRAP, seed: int = CI_SEED) -> tuple[float, float, float, int]:
    """(mean, low, high, n) of the finite values: a 95% percentile bootstrap of the mean.

    Deterministic (a fixed seed); n = 1 gives an interval of zero width, n = 0 NaNs.
    """
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    n = len(v)
    if n == 0:
        return float("nan"), float("nan"), float("nan"), 0
    mean = float(v.mean())
    if n == 1:
        return mean, mean, mean, 1
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, n, (resamples, n))].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return mean, float(lo), float(hi), n


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


def _digits(metric: str) -> int:
    return 2 if metric in UNITS else 3


def cell(metric: str, mean: float, lo: float, hi: float, n: int, episodes: int) -> str:
    """'mean ± half-width' (n appended when it is not every episode); '-' / '--' when none."""
    if n == 0:
        return "--" if metric == "TTFC" else "-"
    d = _digits(metric)
    text = f"{mean:.{d}f} ± {max(hi - mean, mean - lo):.{d}f}"
    return text + (f" (n={n})" if n != episodes else "")


def wide_rows(long: pd.DataFrame, metrics: Sequence[str] = TABLE_METRICS):
    """(header, rows, groups): the combined Table RQ1 as printed; groups = [(title, n_rows)]."""
    scenarios = sorted(long["scenario"].unique())
    algos = algo_order(long["algorithm"].unique())
    label = dict(zip(long["algorithm"], long["label"], strict=False))
    header = ["Environment", "Metric"] + [
        f"S{s} {label.get(a, a)}" for s in scenarios for a in algos]
    idx = long.set_index(["env", "scenario", "algorithm", "metric"])["cell"]
    eps = long.drop_duplicates(["env", "scenario", "algorithm"]).set_index(
        ["env", "scenario", "algorithm"])["episodes"]
    rows, groups = [], []
    envs = sorted(long["env"].unique())
    titles = dict(zip(long["env"], long["title"], strict=False))
    for env in envs:
        block = [[titles[env], "n (episodes)"] + [
            str(int(eps[(env, s, a)])) if (env, s, a) in eps.index else "" for s in scenarios
            for a in algos]]
        for m in metrics:
            block.append([titles[env], m] + [
                idx.get((env, s, a, m), "") for s in scenarios for a in algos])
        rows += block
        groups.append((titles[env], len(block)))
    return header, rows, groups, scenarios, algos


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
    if c in ("-", "--", ""):
        return c
    main, _, rest = c.partition(" (n=")
    m, _, hw = main.partition(" ± ")
    body = f"${m}\\pm{hw}$" if hw else f"${m}$"
    return body + (f"\\,$^{{n={rest.rstrip(')')}}}$" if rest else "")


def rq1_latex(header, rows, groups, scenarios, algos, labels: Mapping[str, str]) -> str:
    """booktabs + multirow, scaled to the page width; needs \\usepackage{booktabs,multirow,graphicx}."""
    k = len(algos)
    cols = "ll" + "c" * (k * len(scenarios))
    lines = [
        "% Table RQ1 (cosim test): needs \\usepackage{booktabs,multirow,graphicx}",
        r"\begin{table*}[t]", r"\centering", r"\small", r"\setlength{\tabcolsep}{3pt}",
        r"\caption{Driving errors per environment (Table RQ1): mean $\pm$ 95\% bootstrap CI over "
        r"episodes. CV, CO, CP, OS, RL: fraction of steps; TTFC: s; SPEED: km/h; DISTANCE: m. "
        r"``-'': does not apply; ``--'': no collision.}",
        r"\label{tab:rq1}",
        r"\resizebox{\textwidth}{!}{%",  # twelve columns of mean ± CI: fit the page width
        rf"\begin{{tabular}}{{{cols}}}", r"\toprule",
    ]
    head = ["", ""] + [rf"\multicolumn{{{k}}}{{c}}{{{_tex(SCENARIO_NAMES.get(s, f'Scenario {s}'))}}}"
                       for s in scenarios]
    lines.append(" & ".join(head) + r" \\")
    lines.append(" ".join(rf"\cmidrule(lr){{{3 + i * k}-{2 + (i + 1) * k}}}"
                          for i in range(len(scenarios))))
    lines.append(" & ".join(["Environment", "Metric"] + [
        _tex(labels.get(a, a)) for _ in scenarios for a in algos]) + r" \\")
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
               selections: Mapping | None = None, command: Sequence[str] | None = None) -> dict:
    """What was tested and how: checkpoints with SHA-256 and the AC rule, seeds, and what ran it
    (eval.training.runfolder.software, as a run's manifest.json: command, versions, git commit)."""
    from eval.testing import selection
    from eval.testing.protocol import rules
    from eval.training.runfolder import software

    ran = software(" ".join(["cosim", *command]) if command is not None else None)
    tested = []
    for algo in algos:
        entry = {"algorithm": algo, "label": slot_label(policy, algo)}
        if checkpoints and algo in checkpoints:
            p = Path(checkpoints[algo])
            sel = (selections or {}).get(algo)
            entry.update(checkpoint=str(p), sha256=sha256(p),
                         run=str(p.parent.parent.parent) if p.parent.name.startswith("ac_") else None,
                         ac=sel.ac if sel else None, chosen_by=sel.basis if sel else None,
                         scores=sel.scores if sel else {})
        tested.append(entry)
    return {
        "policy": policy,
        "tested": tested,
        "ac_rule": selection.RULE,
        "cosim_version": ran["versions"]["cosim"],
        **ran,
        "plan": {"envs": list(plan.envs), "scenarios": list(plan.scenarios),
                 "episodes": plan.episodes, "steps": plan.steps, "agents": plan.agents,
                 "seed": plan.seed, "episode_seeds": [plan.seed + e for e in range(plan.episodes)],
                 **rules(plan)},
        "ci": f"95% percentile bootstrap of the mean over episodes, {BOOTSTRAP} resamples, seed {CI_SEED}",
    }


def slot_label(policy: str, algo: str) -> str:
    """Column label: the algorithm, or '<policy> (<algo> slot)' for a reference policy."""
    return algo if policy == "trained" else f"{policy} ({algo} slot)"


def write_paper_report(records: pd.DataFrame, out: Path, *, prov: dict | None = None,
                       references: pd.DataFrame | None = None, replays: Sequence[dict] = (),
                       dt: float | None = None, figures: bool = True, extra_md: str = "") -> list[Path]:
    """The combined Table RQ1 (md, csv long/wide, tex), figures, index.md/html, provenance."""
    from eval.reporting import figures as figs
    from eval.testing.protocol import metrics_table
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
    header, rows, groups, scenarios, algos = wide_rows(long)
    pd.DataFrame(rows, columns=header).to_csv(out / "rq1_wide.csv", index=False)
    md = rq1_markdown(header, rows, groups)
    (out / "rq1.md").write_text(md)
    (out / "rq1.tex").write_text(rq1_latex(header, rows, groups, scenarios, algos, labels))
    (out / "provenance.json").write_text(json.dumps(prov, indent=2, default=str))
    written = [out / n for n in ("records.parquet", "metrics.csv", "episodes.csv", "rq1_long.csv", "rq1_wide.csv", "rq1.md",
                                 "rq1.tex", "provenance.json")]
    figures_written = figs.write_all(records, per, long, out, labels, dt) if figures else []
    written += figures_written
    index_md = rq1_markdown(*with_replay_links(header, rows, groups, scenarios, algos, long, replays))
    written += write_index(out, index_md, prov, figures_written, references, replays, extra_md)
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
    "report.md": "this page as printed by cosim test",
    "crossplay.csv": "cross-play: the ego's collision and goal rates per partner (per environment and pooled)",
    "crossplay.md": "cross-play matrix, Markdown",
}


def with_replay_links(header, rows, groups, scenarios, algos, long: pd.DataFrame,
                      replays: Sequence[dict]):
    """The table for the index: a 'first collision' row after TTFC in each environment,
    linking the failure replay of each column that has one (eval/testing/replay.py)."""
    if not replays:
        return header, rows, groups
    by = {(r["title"], r["scenario"], r["algorithm"]): r for r in replays}
    cols = [(s, a) for s in scenarios for a in algos]
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
                extra_md: str = "") -> list[Path]:
    """index.md and index.html: the table, the figures, the replays, every file, provenance."""
    out = Path(out)
    policy = prov.get("policy", "trained")
    md = ["# cosim test report\n"]
    if policy != "trained":
        md.append(f"**Policy: {policy}.** Every AC was driven by the {policy} reference, not by "
                  f"a trained checkpoint; columns are labelled '{policy} (<algorithm> slot)'.\n")
    md.append("## Table RQ1\n")
    md.append("Mean ± 95% bootstrap CI over episodes (n = episodes; `(n=k)` when the metric "
              "applied in k of them). S1 = Scenario 1 (multi-agent), S2 = Scenario 2 "
              "(single-agent). \"-\": does not apply (no other vehicle / no pedestrian); "
              "\"--\": no collision. CV, CO, CP, OS, RL are fractions of steps; TTFC s, "
              "SPEED km/h, DISTANCE m.\n")
    md.append(rq1_md)
    md.append("\n## Figures\n")
    md.append("RQ2 success rates: **Safety** = share of episodes without a collision step "
              "(CV = CO = CP = 0); **Efficiency** = SPEED and DISTANCE; **Lane keeping** = "
              "1 - OS (share of steps inside its own lanes). Error bars: 95% bootstrap CI.\n")
    for f in figures:
        if f.suffix == ".png":
            md.append(f"![{f.stem}]({f.name}) ([PDF]({f.with_suffix('.pdf').name}))\n")
    if replays:
        md.append("\n## Failure replays (first collision per algorithm and environment)\n")
        md.append("The moment TTFC measures, and the first step counted by the metric named: "
                  "the AC's camera and a top-down view from 3 s before to 1 s after, and the "
                  "SUMO state at the collision step.\n")
        md.append("| scenario | environment | algorithm | episode | step | TTFC (s) | metric | "
                  "frames | camera | overview | SUMO state | reproduced |")
        md.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
        metric = {"vehicle": "CV", "object": "CO", "pedestrian": "CP"}
        for r in replays:
            md.append(f"| {r['scenario']} | {r['title']} | {r['label']} | {r['episode']} | "
                      f"{r['step']} | {r['ttfc']:.1f} | {metric.get(r['kind'], r['kind'])} | "
                      f"[strip]({r['strip']}) | [gif]({r['camera']}) | "
                      f"[gif]({r['overview']}) | [xml]({r['state']}) ([json]({r['meta']})) | "
                      f"{'yes' if r['reproduced'] else 'NO'} |")
        md.append("\nReopen a state with `cosim replay <state.json>` (prints the positions, "
                  "`--plot` draws them) or in sumo-gui (`--load-state`).\n")
    if references is not None and not references.empty:
        from eval.testing.protocol import references_markdown

        md.append("\n" + references_markdown(references))
    if extra_md:
        md.append(extra_md)
    md.append("\n## Provenance\n")
    md.append(f"- command: `{prov.get('command', '')}`")
    md.append(f"- policy: {policy}")
    md.append(f"- cosim version: {prov.get('cosim_version')}; git: {prov.get('git')}")
    plan = prov.get("plan", {})
    md.append(f"- plan: {plan}")
    md.append(f"- confidence intervals: {prov.get('ci', '')}")
    md.append(f"- AC chosen per run by: {prov.get('ac_rule', '')}\n")
    md.append("| column | checkpoint | SHA-256 | AC | chosen by | scores |")
    md.append("|---|---|---|---|---|---|")
    for t in prov.get("tested", []):
        md.append(f"| {t['label']} | {t.get('checkpoint', '(' + policy + ')')} | "
                  f"{t.get('sha256', '-')} | {t.get('ac') or '-'} | {t.get('chosen_by') or '-'} | "
                  f"{t.get('scores') or '-'} |")
    md.append("\n## Files\n")
    listed = sorted(p for p in out.rglob("*")
                    if p.is_file() and p.name not in ("index.md", "index.html", "report.md"))
    for p in listed:
        rel = p.relative_to(out).as_posix()
        md.append(f"- [{rel}]({rel}){': ' + FILE_NOTES[p.name] if p.name in FILE_NOTES else ''}")
    text = "\n".join(md) + "\n"
    (out / "index.md").write_text(text)
    (out / "index.html").write_text(markdown_to_html(text, "cosim test report"))
    return [out / "index.md", out / "index.html"]


def markdown_to_html(text: str, title: str) -> str:
    """The small Markdown subset index.md uses (headings, tables, lists, links, images)."""
    import re

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
                "<tr>" + "".join(f"<{'th' if i == 0 else 'td'}>{inline(c)}</{'th' if i == 0 else 'td'}>"
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
    style = ("body{font-family:sans-serif;max-width:1400px;margin:auto}table{border-collapse:collapse;"
             "font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
             "img{max-width:100%}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
