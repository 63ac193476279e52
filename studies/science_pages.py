"""The science study's pages: the grids, figures, targets and convergence curves that
``studies/science.py`` (and the part and combined pages: studies/part_page.py,
studies/combined_page.py) write from the statistics over seeds of
:mod:`eval.reporting.multiseed` (seed means, verdict, IQM, budget check: the product's, which
``cosim benchmark --seeds N`` reports too).

- :func:`grid_markdown`, :func:`verdict_grid_markdown`, :func:`return_goal_grid_markdown`,
  :func:`metrics_markdown`: algorithms x environments, as the README's results tables;
- :func:`targets` / :func:`targets_markdown`: per environment, whether a discrete and a
  continuous algorithm pass and some algorithm's turns are learned;
- :func:`convergence_curves` / :func:`convergence_figure`: training return against
  environment steps, one panel per algorithm, one curve per environment, mean over seeds with
  a min-max band;
- :func:`verdict_figure` and :func:`iqm_figure`: the verdict and the IQM drawn.

A study script imports it as ``science_pages`` (studies/ is on ``sys.path`` when a study runs
or is loaded by the tests' ``load_study``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eval.labels import algo_label, algo_order, env_colour, env_title
from eval.reporting.multiseed import (
    DIGITS,
    METRICS,
    NAMES,
    TURNING_METRIC,
    VERDICT_METRIC,
    VERDICT_SCENARIO,
    degenerate_means,
    turning_word,
    verdict_word,
    with_metrics,
)
from eval.reporting.page import md_table
from eval.testing.validity import DEGENERATE, POLICIES

WINDOW = 20
"""Convergence: the mean return of the most recent episodes (any AC) finished by a step."""


def over_seeds(mean: float, lo: float, hi: float, n: int) -> str:
    """A mean return and its 95% interval as the README's tables write them: 'mean [low, high]'
    with thousands separators; one value (n = 1, no interval): the mean alone."""
    return f"{mean:,.1f}" if n == 1 else f"{mean:,.1f} [{lo:,.1f}, {hi:,.1f}]"


def return_goal_cell(mean: float, lo: float, hi: float, n: int, goal: float) -> str:
    """'return [95% CI] (goal rate)' as the README's grids write a cell; one seed:
    'return (goal rate; 1 seed)'."""
    return f"{over_seeds(mean, lo, hi, n)} ({goal:.2f}{'' if n > 1 else '; 1 seed'})"



def has_turns(v: pd.DataFrame) -> pd.Series:
    """Per environment of a :func:`verdict`: whether some slot's route turns (a turning slots'
    metric applies)."""
    cols = [c for c in (f"{TURNING_METRIC}_mean", "turning_goal_mean") if c in v]
    return v.groupby("env")[cols].apply(lambda x: bool(x.notna().to_numpy().any()))


def targets(v: pd.DataFrame) -> pd.DataFrame:
    """Per environment, issue 27's target read off a :func:`verdict`: the discrete and the
    continuous algorithms that pass (their DS clears every degenerate reference, 3+ seeds), and
    those whose turns are learned (``turning_ok``: the turning slots' route completion clears the
    safe non-turner's; where no slot's route turns, no turn is asked for)."""
    from agents.registry import CONTINUOUS, DISCRETE

    turns = has_turns(v)
    rows = []
    for env, g in v.groupby("env", sort=False):
        passed = g.loc[g["passed"].astype(bool), "algorithm"].tolist()
        learned = g["turning_ok"].map(lambda x: turning_word(x) == "yes").astype(bool)
        rows.append({"env": env, "title": env_title(env),
                     "discrete": [a for a in passed if a in DISCRETE],
                     "continuous": [a for a in passed if a in CONTINUOUS],
                     "has_turns": bool(turns[env]),
                     "turning": g.loc[learned, "algorithm"].tolist()})
    t = pd.DataFrame(rows)
    t["met"] = (t["discrete"].map(bool) & t["continuous"].map(bool)
                & (~t["has_turns"] | t["turning"].map(bool)))
    return t


def targets_markdown(t: pd.DataFrame) -> str:
    def names(xs):
        return ", ".join(algo_label(x) for x in xs) if xs else "none"
    rows = [[r["title"], names(r["discrete"]), names(r["continuous"]),
             names(r["turning"]) if r["has_turns"] else "(no turning slot)",
             "met" if r["met"] else "not met"] for _, r in t.iterrows()]
    return md_table(["environment", "discrete algorithms that pass", "continuous algorithms that pass",
                     "algorithms whose turns are learned (turning slots' RC above the safe non-turner's)",
                     "target"], rows)



# -- convergence ----------------------------------------------------------------------------
def convergence_curve(episodes: pd.DataFrame, budget: int, points: int = 100,
                      window: int = WINDOW) -> pd.DataFrame:
    """One run's training return on a grid of ``points`` env steps from 0 to ``budget``: the
    mean return of the ``window`` most recent episodes (any AC) finished by that step; NaN
    before the first episode ends."""
    grid = np.linspace(0, budget, points)
    e = episodes.sort_values("env_step", kind="stable")
    steps, returns = e["env_step"].to_numpy(float), e["return"].to_numpy(float)
    done = np.searchsorted(steps, grid, side="right")  # episodes finished by each grid step
    csum = np.concatenate([[0.0], np.cumsum(returns)])
    first = np.maximum(done - window, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        value = np.where(done > 0, (csum[done] - csum[first]) / (done - first), np.nan)
    return pd.DataFrame({"env_step": grid, "return": value})


def convergence_curves(runs: Mapping[tuple[str, str, int], Path], points: int = 100,
                       window: int = WINDOW) -> pd.DataFrame:
    """Every run's curve (:func:`convergence_curve`) from its episodes.csv and config.yaml;
    ``runs`` maps (algorithm, env, seed) to a run folder. Columns: algorithm, env, seed,
    env_step, return."""
    import yaml

    parts = []
    for (algo, env, seed), run in runs.items():
        cfg = yaml.safe_load((Path(run) / "config.yaml").read_text())
        csv = Path(run) / "episodes.csv"
        episodes = pd.read_csv(csv) if csv.exists() and csv.stat().st_size else pd.DataFrame(
            {"env_step": [], "return": []})
        curve = convergence_curve(episodes, int(cfg["steps"]), points, window)
        parts.append(curve.assign(algorithm=algo, env=env, seed=int(seed)))
    return pd.concat(parts, ignore_index=True)


def convergence_bands(curves: pd.DataFrame) -> pd.DataFrame:
    """Per (algorithm, env, env_step): mean, min and max over seeds, and the seeds with a
    value; the mean only where every seed of that (algorithm, env) has one (NaN before)."""
    g = curves.groupby(["algorithm", "env", "env_step"], sort=True)["return"]
    out = pd.DataFrame({"mean": g.mean(), "low": g.min(), "high": g.max(),
                        "seeds": g.count()}).reset_index()
    runs = curves.groupby(["algorithm", "env"])["seed"].nunique().rename("runs").reset_index()
    out = out.merge(runs, on=["algorithm", "env"])
    out.loc[out["seeds"] < out["runs"], ["mean", "low", "high"]] = np.nan
    return out.drop(columns="runs")


def convergence_figure(curves: pd.DataFrame, out: Path, stem: str = "convergence") -> list[Path]:
    """Six panels like the paper's (one per algorithm), one curve per environment: the mean
    training return over seeds with a min-max band over seeds. PDF and PNG."""
    from eval.reporting.figures import PAGE_IN, _plt, _save

    plt = _plt()
    bands = convergence_bands(curves)
    algos = algo_order(bands["algorithm"].unique())
    envs = sorted(bands["env"].unique())
    cols = min(3, len(algos))
    rows = -(-len(algos) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(PAGE_IN, 1.75 * rows + 0.5), squeeze=False)
    for ax in axes.ravel()[len(algos):]:
        ax.set_visible(False)
    seeds = curves.groupby(["algorithm", "env"])["seed"].nunique()
    for ax, algo in zip(axes.ravel(), algos, strict=False):
        for env in envs:
            b = bands[(bands["algorithm"] == algo) & (bands["env"] == env)]
            if b.empty:
                continue
            c = env_colour(env)
            lone = int(np.isfinite(b["mean"]).sum()) == 1  # a single point draws no line
            ax.plot(b["env_step"], b["mean"], color=c, lw=0.9, marker="o" if lone else None, ms=2)
            if seeds.get((algo, env), 1) > 1:
                ax.fill_between(b["env_step"], b["low"], b["high"], color=c, alpha=0.18, lw=0)
        ax.set_title(algo_label(algo), loc="left")
        ax.grid(lw=0.3)
        ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 3))
        ax.set_xlabel("environment steps")
    for r in range(rows):
        axes[r][0].set_ylabel("training return")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=env_colour(e), label=env_title(e)) for e in envs]
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.legend(handles=handles, loc="lower center", ncol=len(envs), frameon=False,
               bbox_to_anchor=(0.5, -0.01))
    return _save(fig, Path(out), stem)


# -- the verdict as a figure -----------------------------------------------------------------
FIGURE_METRICS = (VERDICT_METRIC, TURNING_METRIC)
"""The verdict figure's rows: the driving score (what a pair passes on) and the turning slots'
route completion (what says its turns are learned)."""


def verdict_lines(v: pd.DataFrame, references: pd.DataFrame, env: str, metric: str) -> list[tuple[str, float, str]]:
    """The reference lines of one :func:`verdict_figure` panel, (label, value, line style): the
    autopilot, the strongest degenerate reference (on the driving score: what a CI's lower end
    must clear, named) and, where a slot's route turns, the safe non-turner (on the turning
    slots' route completion, the value their CI's lower end must clear)."""
    first = v[v["env"] == env].iloc[0]
    turns = bool(has_turns(v[v["env"] == env]).get(env, False))
    r = references[(references["env"] == env) & (references["metric"] == metric)].set_index("name")["mean"]
    r = r[np.isfinite(r.astype(float))]
    lines = [("autopilot", float(r["autopilot"]), "-")] if "autopilot" in r.index else []
    if f"{metric}_best_reference" in first.index:
        lines.append((f"best degenerate ({first[f'{metric}_best_reference']})", float(first[f"{metric}_reference"]), "--"))
    if "safe-non-turner" in r.index and shows_reference("safe-non-turner", turns):
        lines.append(("safe non-turner", float(r["safe-non-turner"]), ":"))
    return lines


def verdict_figure(v: pd.DataFrame, seeds: pd.DataFrame, references: pd.DataFrame, out: Path,
                   stem: str = "verdict") -> list[Path]:
    """The :func:`verdict` grid drawn: one column per environment, Scenario 1's driving score
    (top) and the turning slots' route completion (bottom; "no turning slot" where no route
    turns); per algorithm each training seed's mean (dots) and the mean with its 95% CI over
    seeds (bar), "pass" above a pair whose DS clears every degenerate reference, "turns" above
    one whose turning slots' RC clears the safe non-turner's; the :func:`verdict_lines` across.
    PDF and PNG."""
    from eval.labels import colour
    from eval.reporting.figures import PAGE_IN, _plt, _save

    plt = _plt()
    envs = sorted(v["env"].unique())
    algos = algo_order(v["algorithm"].unique())
    s1 = with_metrics(seeds[seeds["scenario"] == VERDICT_SCENARIO], FIGURE_METRICS)
    width = min(PAGE_IN, 1.0 + 1.25 * len(envs))  # one environment: a column, not a stretched page
    fig, axes = plt.subplots(2, len(envs), figsize=(width, 3.6), squeeze=False)
    styles = {}
    for col, env in enumerate(envs):
        for row, metric in enumerate(FIGURE_METRICS):
            ax = axes[row][col]
            ax.set_ylim(-0.04, 1.12)
            ax.grid(axis="y", lw=0.3)
            ax.set_xticks(range(len(algos)))
            ax.set_xticklabels([algo_label(a) for a in algos] if row == 1 else [], rotation=90)
            ax.set_xlim(-0.6, len(algos) - 0.4)
            if row == 0:
                ax.set_title(env_title(env), loc="left")
            e = v[v["env"] == env]
            if metric == TURNING_METRIC and not e[f"{metric}_mean"].notna().any():
                ax.text(0.5, 0.5, "no turning slot", transform=ax.transAxes, ha="center", va="center",
                        fontsize=6, color="#666666")
                continue
            for label, value, style in verdict_lines(v, references, env, metric):
                kind = label.split(" (")[0]
                ax.axhline(value, color="#444444" if kind != "best degenerate" else "#C00000",
                           ls=style, lw=0.8, zorder=1)
                styles.setdefault(kind, style)
            for x, algo in enumerate(algos):
                r = e[e["algorithm"] == algo]
                if r.empty:
                    continue
                r = r.iloc[0]
                c = colour(algo)
                pts = s1.loc[(s1["env"] == env) & (s1["algorithm"] == algo), metric].to_numpy(float)
                pts = pts[np.isfinite(pts)]
                ax.scatter(x + np.linspace(-0.15, 0.15, len(pts)) if len(pts) > 1 else [x] * len(pts),
                           pts, s=6, color=c, alpha=0.6, lw=0, zorder=2)
                lo, hi, mean = r[f"{metric}_ci_low"], r[f"{metric}_ci_high"], r[f"{metric}_mean"]
                if not np.isfinite(mean):
                    continue
                ax.errorbar([x], [mean], yerr=[[mean - lo], [hi - mean]], fmt="_", color=c, ms=8,
                            mew=1.4, elinewidth=1.2, capsize=0, zorder=3)
                word = ("pass" if row == 0 and bool(r["passed"]) else
                        "turns" if row == 1 and turning_word(r["turning_ok"]) == "yes" else "")
                if word:
                    ax.annotate(word, (x, hi), xytext=(0, 3), textcoords="offset points",
                                ha="center", fontsize=5.5, fontweight="bold")
        axes[0][col].tick_params(axis="y", labelsize=5)
    axes[0][0].set_ylabel("Scenario 1 driving score")
    axes[1][0].set_ylabel("RC, turning slots")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color="#C00000" if k == "best degenerate" else "#444444", ls=st, lw=0.8, label=k)
               for k, st in styles.items()]
    handles.append(Line2D([], [], color="#444444", marker="_", ms=8, mew=1.4, ls="none",
                          label="mean, 95% CI over seeds (dots: seeds)"))
    ncol = len(handles) if len(envs) >= 3 else 1
    fig.tight_layout(rect=(0, 0.02 + 0.045 * -(-len(handles) // ncol), 1, 1))
    fig.legend(handles=handles, loc="lower center", ncol=ncol, frameon=False, bbox_to_anchor=(0.5, -0.01))
    return _save(fig, Path(out), stem)


def iqm_lines(t: pd.DataFrame) -> list[tuple[str, float, str]]:
    """The reference lines of :func:`iqm_figure`, (label, value, line style): the autopilot (1 by
    construction), the strongest degenerate reference (named) and the safe non-turner."""
    ref = t[t["kind"] == "reference"].set_index("name")["iqm"]
    degenerate = ref[[n for n in DEGENERATE if n in ref.index]]
    lines = [("autopilot", float(ref["autopilot"]), "-")] if "autopilot" in ref.index else []
    if len(degenerate):
        lines.append((f"best degenerate ({degenerate.idxmax()})", float(degenerate.max()), "--"))
    if "safe-non-turner" in ref.index:
        lines.append(("safe non-turner", float(ref["safe-non-turner"]), ":"))
    return lines


def iqm_figure(t: pd.DataFrame, out: Path, stem: str = "iqm") -> list[Path]:
    """The :func:`iqm_table` drawn: one row per algorithm (the paper's order, top down), its IQM of
    normalised Scenario 1 driving score with the 95% stratified bootstrap CI, against :func:`iqm_lines`.
    A column wide; PDF and PNG."""
    from eval.labels import colour
    from eval.reporting.figures import COLUMN_IN, _plt, _save

    plt = _plt()
    algos = t[t["kind"] == "algorithm"].set_index("name")
    order = algo_order(algos.index)
    fig, ax = plt.subplots(figsize=(COLUMN_IN, 0.75 + 0.24 * len(order)))
    for label, value, style in iqm_lines(t):
        ax.axvline(value, color="#C00000" if label.startswith("best degenerate") else "#444444",
                   ls=style, lw=0.8, zorder=1, label=label)
    for y, algo in enumerate(order):
        r = algos.loc[algo]
        ax.errorbar([r["iqm"]], [y], xerr=[[r["iqm"] - r["ci_low"]], [r["ci_high"] - r["iqm"]]], fmt="o",
                    color=colour(algo), ms=3.5, elinewidth=1.4, capsize=0, zorder=3)
    ax.set_yticks(range(len(order)), [algo_label(a) for a in order])
    ax.invert_yaxis()
    ax.grid(axis="x", lw=0.3)
    envs = int(algos["envs"].max()) if len(algos) else 0
    ax.set_xlabel(f"IQM of Scenario 1 driving score over {envs} environment{'s' if envs != 1 else ''} "
                  "(random 0, autopilot 1)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False)
    fig.tight_layout()
    return _save(fig, Path(out), stem)



# -- Markdown -------------------------------------------------------------------------------
def grid_markdown(table: pd.DataFrame, metric: str, scenario: int = VERDICT_SCENARIO,
                  references: pd.DataFrame | None = None,
                  reference_names: Sequence[str] = ("autopilot", "random")) -> str:
    """Algorithms (rows) x environments (columns) of one metric, 'mean [CI]'; reference rows
    (Scenario 1 only) below, then the strongest degenerate reference of each environment
    (the value an algorithm's CI must clear in the verdict, and its name)."""
    t = table[(table["metric"] == metric) & (table["scenario"] == scenario)]
    envs = sorted(t["env"].unique())
    cells = t.set_index(["name", "env"])["cell"]
    rows = [[algo_label(a)] + [cells.get((a, e), "") for e in envs] for a in algo_order(t["name"].unique())]
    if references is not None and scenario == VERDICT_SCENARIO:
        r = references[references["metric"] == metric].set_index(["name", "env"])["cell"]
        rows += [[f"*{n}*"] + [r.get((n, e), "") for e in envs] for n in reference_names
                 if any((n, e) in r.index for e in envs)]
        best = []
        for e in envs:
            means = {k: v for k, v in degenerate_means(references, e, metric).items() if np.isfinite(v)}
            name = max(means, key=means.get) if means else None
            best.append(f"{means[name]:.{DIGITS.get(metric, 3)}f} ({name})" if name else "")
        if any(best):
            rows.append(["*best degenerate*", *best])
    return md_table(["algorithm", *[env_title(e) for e in envs]], rows)


def metrics_markdown(table: pd.DataFrame, references: pd.DataFrame, scenario: int) -> str:
    """Every metric per (environment, algorithm or reference): the full results table."""
    t = table[table["scenario"] == scenario]
    if scenario == VERDICT_SCENARIO:
        t = pd.concat([t, references], ignore_index=True)
    cells = t.set_index(["env", "kind", "name", "metric"])["cell"]
    n = t.set_index(["env", "kind", "name", "metric"])["n"]
    rows = []
    for env in sorted(t["env"].unique()):
        e = t[t["env"] == env]
        names = [("algorithm", a) for a in algo_order(e.loc[e["kind"] == "algorithm", "name"].unique())]
        names += [("reference", p) for p in POLICIES if p in set(e.loc[e["kind"] == "reference", "name"])]
        for kind, name in names:
            label = algo_label(name) if kind == "algorithm" else f"*{name}*"
            rows.append([env_title(env), label, int(n.get((env, kind, name, "return"), 0))]
                        + [cells.get((env, kind, name, m), "") for m in METRICS])
    return md_table(["environment", "policy", "n", *[NAMES.get(m, m) for m in METRICS]], rows)



def score_cell(mean: float, lo: float, hi: float, n: int, goal: float) -> str:
    """'DS [95% CI] (goal rate)' as the README's grids write a cell; one seed:
    'DS (goal rate; 1 seed)'."""
    d = DIGITS[VERDICT_METRIC]
    ds = f"{mean:.{d}f}" if n == 1 else f"{mean:.{d}f} [{lo:.{d}f}, {hi:.{d}f}]"
    return f"{ds} ({goal:.2f}{'' if n > 1 else '; 1 seed'})"


def shows_reference(name: str, route_turns: bool) -> bool:
    """Whether a table shows the reference row ``name`` for an environment: the safe non-turner
    only where some slot's route turns (elsewhere it drives as the autopilot does)."""
    return name != "safe-non-turner" or route_turns


def verdict_grid_markdown(v: pd.DataFrame, references: pd.DataFrame | None = None) -> str:
    """The :func:`verdict` as one algorithms x environments grid: each cell 'DS [95% CI] (goal
    rate), verdict' ('DS (goal rate; 1 seed)' with one seed), a pass in bold, ', turns' where its
    turning slots' route completion clears the safe non-turner's; with ``references``
    (:func:`reference_table`'s Scenario 1 rows) the autopilot's and the safe non-turner's 'DS
    (goal rate)' below (the safe non-turner only where a route turns: elsewhere it is the
    autopilot); last, each environment's strongest degenerate DS (what a cell's CI must clear).
    The README's results table."""
    m = VERDICT_METRIC
    envs = sorted(v["env"].unique())
    cells = {}
    for _, r in v.iterrows():
        word = verdict_word(r)
        cell = score_cell(r[f"{m}_mean"], r[f"{m}_ci_low"], r[f"{m}_ci_high"], r["n"], r.get("goal_mean", np.nan))
        cells[(r["algorithm"], r["env"])] = (f"{cell}, " + (f"**{word}**" if word == "pass" else word)
                                             + (", turns" if turning_word(r["turning_ok"]) == "yes" else ""))
    rows = [[algo_label(a)] + [cells.get((a, e), "") for e in envs] for a in algo_order(v["algorithm"].unique())]
    if references is not None:
        r = references.set_index(["name", "env", "metric"])["mean"]
        turns = has_turns(v)
        for name, label in (("autopilot", "autopilot"), ("safe-non-turner", "safe non-turner")):
            row = [f"{r[(name, e, m)]:.3f} ({r[(name, e, 'goal')]:.2f})"
                   if (name, e, m) in r.index and (name, e, "goal") in r.index
                   and shows_reference(name, turns[e]) else "" for e in envs]
            if any(row):
                rows.append([f"*{label}*", *row])
    first = v.drop_duplicates("env").set_index("env")
    rows.append(["*best degenerate*"] + [
        f"{first.loc[e, f'{m}_reference']:.3f} ({first.loc[e, f'{m}_best_reference']})" for e in envs])
    return md_table(["algorithm", *[env_title(e) for e in envs]], rows)


def return_goal_grid_markdown(table: pd.DataFrame, scenario: int) -> str:
    """Algorithms x environments of one scenario, each cell 'return [95% CI over seeds] (goal
    rate)' as the README writes them (one seed: 'return (goal rate; 1 seed)'); no reference rows
    (they are measured under Scenario 1's conditions). Scenario 2's table: each algorithm alone."""
    t = table[(table["scenario"] == scenario) & table["metric"].isin(["return", "goal"])]
    envs = sorted(t["env"].unique())
    r = t.set_index(["name", "env", "metric"])
    cells = {}
    for a, e in {(a, e) for a, e, _ in r.index}:
        ret = r.loc[(a, e, "return")]
        cells[(a, e)] = return_goal_cell(ret["mean"], ret["ci_low"], ret["ci_high"], ret["n"], r.loc[(a, e, "goal"), "mean"])
    rows = [[algo_label(a)] + [cells.get((a, e), "") for e in envs] for a in algo_order(t["name"].unique())]
    return md_table(["algorithm", *[env_title(e) for e in envs]], rows)


