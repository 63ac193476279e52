"""Tables and figures of the cross-play and robustness sweeps of ``cosim test`` (issue 13;
the episodes: eval/testing/robustness.py).

Cross-play: the matrix (rows: ego, columns: partner) gives the ego's collision rate (share of
episodes with a collision step with a vehicle) and goal rate (share reaching its goal), pooled
over environments, with 95% bootstrap intervals: who is dangerous to whom. Files:
``crossplay.csv`` (per environment and pooled), ``crossplay.md``, ``crossplay_heatmap.pdf/.png``.

Sweeps: ``sweep_<kind>.csv`` (per level, algorithm and metric: mean, CI, n) and
``sweep_<kind>.pdf/.png`` (metrics against the level, one line per algorithm with its
interval band).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from eval.labels import algo_order
from eval.reporting.report import per_episode
from eval.reporting.stats import bootstrap_ci

SWEEP_METRICS = (("safety", "Safety (collision-\nfree episodes)"), ("lane_keeping", "Lane keeping\n(1 - OS)"),
                 ("DISTANCE", "DISTANCE (m)"), ("SPEED", "SPEED (km/h)"))


def cross_play_table(records: pd.DataFrame, dt: float | None = None) -> pd.DataFrame:
    """Per (env or 'all', ego, partner): the ego's collision and goal rates with 95% CIs."""
    ego = records[records["agent"] == "ac_0"]
    rows = []
    for (ego_algo, partner), g in ego.groupby(["ego", "partner"], sort=False):
        per = per_episode(g.drop(columns=["ego", "partner"]), dt)
        per["crash"] = (per["CV"].fillna(0) > 0).astype(float)
        per["goal"] = per["goal"].astype(float)
        for env, sub in [*per.groupby("env", sort=True), ("all", per)]:
            row = {"env": env, "ego": ego_algo, "partner": partner}
            for m, name in (("crash", "collision_rate"), ("goal", "goal_rate")):
                mean, lo, hi, n = bootstrap_ci(sub[m].to_numpy())
                row.update({name: mean, f"{name}_low": lo, f"{name}_high": hi})
            row["n"] = n
            rows.append(row)
    return pd.DataFrame(rows)


def cross_play_markdown(table: pd.DataFrame, labels: dict) -> str:
    allt = table[table["env"] == "all"]
    egos = algo_order(allt["ego"].unique())
    partners = [p for p in [*egos, "autopilot"] if p in set(allt["partner"])]
    t = allt.set_index(["ego", "partner"])
    lines = ["| ego \\ among | " + " | ".join(labels.get(p, p) for p in partners) + " |",
             "|---|" + "---|" * len(partners)]
    for e in egos:
        cells = []
        for p in partners:
            r = t.loc[(e, p)]
            cells.append(f"{r.collision_rate:.2f} / {r.goal_rate:.2f} (n={int(r.n)})")
        lines.append(f"| {labels.get(e, e)} | " + " | ".join(cells) + " |")
    return ("Cells: the ego's collision rate (share of episodes with a vehicle collision) / "
            "goal rate, pooled over environments.\n\n" + "\n".join(lines) + "\n")


def cross_play_heatmap(table: pd.DataFrame, out: Path, labels: dict) -> list[Path]:
    from eval.reporting.figures import COLUMN_IN, _plt, _save

    plt = _plt()
    allt = table[table["env"] == "all"]
    egos = algo_order(allt["ego"].unique())
    partners = [p for p in [*egos, "autopilot"] if p in set(allt["partner"])]
    t = allt.set_index(["ego", "partner"])
    fig, axes = plt.subplots(1, 2, figsize=(2 * COLUMN_IN, 0.35 * len(egos) + 1.4))
    for ax, (col, title, cmap) in zip(axes, [("collision_rate", "Ego collision rate", "Reds"),
                                             ("goal_rate", "Ego goal rate", "Greens")], strict=True):
        m = np.array([[t.loc[(e, p), col] for p in partners] for e in egos], float)
        ax.imshow(m, vmin=0, vmax=1, cmap=cmap, aspect="auto")
        for i in range(len(egos)):
            for j in range(len(partners)):
                ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=6,
                        color="white" if m[i, j] > 0.6 else "black")
        ax.set_xticks(range(len(partners)))
        ax.set_xticklabels([labels.get(p, p) for p in partners], rotation=30, ha="right")
        ax.set_yticks(range(len(egos)))
        ax.set_yticklabels([labels.get(e, e) for e in egos])
        ax.set_xlabel("among (partner ACs)")
        ax.set_title(title)
    axes[0].set_ylabel("ego AC")
    fig.tight_layout()
    return _save(fig, Path(out), "crossplay_heatmap")


def sweep_table(records: pd.DataFrame, dt: float | None = None) -> pd.DataFrame:
    """Per (level, algorithm, metric), pooled over environments: mean, 95% CI, n."""
    rows = []
    for level, g in records.groupby("level", sort=True):
        per = per_episode(g.drop(columns=["sweep", "level"]), dt)
        for algo, sub in per.groupby("algorithm", sort=False):
            for m, _ in SWEEP_METRICS:
                mean, lo, hi, n = bootstrap_ci(sub[m].to_numpy())
                rows.append({"sweep": records["sweep"].iloc[0], "level": level, "algorithm": algo,
                             "metric": m, "mean": mean, "ci_low": lo, "ci_high": hi, "n": n})
    return pd.DataFrame(rows)


def sweep_figure(table: pd.DataFrame, out: Path, labels: dict) -> list[Path]:
    from eval.reporting.figures import PAGE_IN, _legend, _plt, _save, colour

    plt = _plt()
    kind = table["sweep"].iloc[0]
    algos = algo_order(table["algorithm"].unique())
    fig, axes = plt.subplots(1, len(SWEEP_METRICS), figsize=(PAGE_IN, 1.9), squeeze=False)
    for ax, (m, name) in zip(axes[0], SWEEP_METRICS, strict=True):
        for a in algos:
            g = table[(table["metric"] == m) & (table["algorithm"] == a)].sort_values("level")
            ax.plot(g["level"], g["mean"], "o-", color=colour(a), lw=0.9, ms=2.5)
            ax.fill_between(g["level"], g["ci_low"], g["ci_high"], color=colour(a), alpha=0.15, lw=0)
        if m in ("safety", "lane_keeping"):
            ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel(kind.replace("_", " "))
        ax.set_ylabel(name)
        ax.grid(lw=0.3)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    _legend(fig, algos, labels, ncol=6)
    return _save(fig, Path(out), f"sweep_{kind}")


def sweep_markdown(table: pd.DataFrame, labels: dict) -> str:
    kind = table["sweep"].iloc[0]
    algos = algo_order(table["algorithm"].unique())
    lines = [f"| {kind} | metric | " + " | ".join(labels.get(a, a) for a in algos) + " |",
             "|---|---|" + "---|" * len(algos)]
    t = table.set_index(["level", "metric", "algorithm"])
    for level in sorted(table["level"].unique()):
        for m, _ in SWEEP_METRICS:
            cells = []
            for a in algos:
                r = t.loc[(level, m, a)]
                cells.append("-" if r.n == 0 else f"{r['mean']:.2f}" if r.n == 1 else
                             f"{r['mean']:.2f} [{r.ci_low:.2f}, {r.ci_high:.2f}]")
            lines.append(f"| {level:g} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write(out: Path, labels: dict, cross: pd.DataFrame | None = None,
          sweeps: dict[str, pd.DataFrame] | None = None) -> tuple[list[Path], str]:
    """Tables and figures of cross-play and sweeps; (files, Markdown for the index)."""
    out = Path(out)
    written, md = [], []
    if cross is not None and not cross.empty:
        table = cross_play_table(cross)
        table.to_csv(out / "crossplay.csv", index=False)
        text = cross_play_markdown(table, labels)
        (out / "crossplay.md").write_text(text)
        figs = cross_play_heatmap(table, out, labels)
        written += [out / "crossplay.csv", out / "crossplay.md", *figs]
        md += ["\n## Cross-play (Scenario 1 conditions: the ego AC among ACs of one partner policy)\n",
               text, "\n![crossplay_heatmap](crossplay_heatmap.png) ([PDF](crossplay_heatmap.pdf))\n"]
    for kind, rec in (sweeps or {}).items():
        table = sweep_table(rec)
        table.to_csv(out / f"sweep_{kind}.csv", index=False)
        figs = sweep_figure(table, out, labels)
        written += [out / f"sweep_{kind}.csv", *figs]
        md += [f"\n## Robustness sweep: {kind} (Scenario 1 conditions, pooled over environments)\n",
               "Mean [95% bootstrap CI] over episodes (n = 1: no interval).\n", sweep_markdown(table, labels),
               f"\n![sweep_{kind}](sweep_{kind}.png) ([PDF](sweep_{kind}.pdf))\n"]
    return written, "\n".join(md)
