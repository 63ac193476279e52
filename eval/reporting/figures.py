"""Figures of the cosim test report (issue 13): RQ2 success rates, SPEED per timestep,
TTFC survival. Each is written as PDF and PNG, sized for a paper column (3.5 in) or
the page width (7 in), with the environments' titles, the paper's algorithm order and
one colour per algorithm in every figure (:data:`eval.labels.COLOURS`, Okabe-Ito, colour-blind safe).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from eval.labels import ALGO_ORDER, COLOURS, SCENARIO_NAMES, algo_order, colour, env_title  # noqa: F401 - re-exported
from eval.testing.metrics import scenario_dt

COLUMN_IN = 3.5
PAGE_IN = 7.0


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 7, "axes.titlesize": 7, "axes.labelsize": 7,
                         "xtick.labelsize": 6, "ytick.labelsize": 6, "legend.fontsize": 6,
                         "pdf.fonttype": 42, "svg.hashsalt": "cosim"})
    return plt


def _save(fig, out: Path, stem: str, dpi: int = 200) -> list[Path]:
    plt = _plt()
    paths = [out / f"{stem}.pdf", out / f"{stem}.png"]
    fig.savefig(paths[0], bbox_inches="tight", metadata={"CreationDate": None})
    fig.savefig(paths[1], dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return paths


def _legend(fig, algos, labels, ncol=3):
    from matplotlib.patches import Patch

    handles = [Patch(color=colour(a), label=labels.get(a, a)) for a in algos]
    fig.legend(handles=handles, loc="lower center", ncol=min(ncol, len(algos)),
               frameon=False, bbox_to_anchor=(0.5, -0.01))


def bar_figure(long: pd.DataFrame, metrics: list[tuple[str, str]], out: Path, stem: str,
               labels: Mapping[str, str], ylim01: bool = False) -> list[Path]:
    """Grouped bars (environments on x, one bar per algorithm) with 95% CI error bars;
    one panel per (metric, scenario)."""
    plt = _plt()
    scenarios = sorted(long["scenario"].unique())
    algos = algo_order(long["algorithm"].unique())
    envs = sorted(long["env"].unique())
    titles = dict(zip(long["env"], long["title"], strict=False))
    rows = len(metrics) * len(scenarios)
    fig, axes = plt.subplots(rows, 1, figsize=(COLUMN_IN, 1.35 * rows + 0.45), squeeze=False)
    width = 0.8 / max(1, len(algos))
    r = 0
    for metric, name in metrics:
        for s in scenarios:
            ax = axes[r][0]
            sub = long[(long["metric"] == metric) & (long["scenario"] == s)].set_index(["env", "algorithm"])
            top = max([float(v) for v in sub["mean"] if np.isfinite(v)] + [1e-9])
            for k, a in enumerate(algos):
                xs, ys, err = [], [], [[], []]
                for i, e in enumerate(envs):
                    x = i + (k - (len(algos) - 1) / 2) * width
                    if (e, a) not in sub.index or not np.isfinite(sub.loc[(e, a), "mean"]):
                        _mark(ax, x, top, "n/a")  # told apart from a bar of height zero
                        continue
                    row = sub.loc[(e, a)]
                    xs.append(x)
                    ys.append(row["mean"])
                    one = row["n"] < 2  # one value has no interval: no zero-width error bar
                    err[0].append(0.0 if one else max(0.0, row["mean"] - row["ci_low"]))
                    err[1].append(0.0 if one else max(0.0, row["ci_high"] - row["mean"]))
                    if row["mean"] == 0:
                        _mark(ax, x, top, "0", colour(a))  # a zero bar is visible as its label
                if xs:
                    ax.bar(xs, ys, width, color=colour(a), yerr=err if any(map(any, err)) else None,
                           capsize=1.2, error_kw={"lw": 0.6})
            ax.set_xticks(range(len(envs)))
            ax.set_xticklabels([titles[e] for e in envs])
            ax.set_ylabel(name)
            ax.set_title(SCENARIO_NAMES.get(s, f"Scenario {s}"), loc="left")
            if ylim01:
                ax.set_ylim(0, 1.05)
            ax.grid(axis="y", lw=0.3)
            r += 1
    fig.tight_layout(rect=(0, 0.06 if len(algos) <= 3 else 0.1, 1, 1))
    _legend(fig, algos, labels)
    return _save(fig, out, stem)


def _mark(ax, x: float, top: float, text: str, color: str = "#444444") -> None:
    """A small label at the foot of a bar's place: "0" for a bar of height zero, "n/a" where
    the metric does not apply (so that neither reads as the other, nor as a missing bar)."""
    ax.text(x, 0.02 * top, text, ha="center", va="bottom", fontsize=5, rotation=90 if len(text) > 1 else 0,
            color=color)


def speed_grid(records: pd.DataFrame, out: Path, labels: Mapping[str, str],
               dt: float | None = None) -> list[Path]:
    """SPEED per timestep: environments as rows, scenarios as columns; the line is the mean
    over episodes, the band its spread (min to max over episodes). ``dt``: seconds per step
    (None: each environment's scenario's, eval.testing.metrics.scenario_dt)."""
    plt = _plt()
    scenarios = sorted(records["scenario"].unique())
    envs = sorted(records["env"].unique())
    algos = algo_order(records["algorithm"].unique())

    fig, axes = plt.subplots(len(envs), len(scenarios), figsize=(PAGE_IN, 1.25 * len(envs) + 0.5),
                             squeeze=False, sharex=True)
    for i, env in enumerate(envs):
        for j, s in enumerate(scenarios):
            ax = axes[i][j]
            rec = records[(records["env"] == env) & (records["scenario"] == s)]
            for a in algos:
                g = rec[rec["algorithm"] == a]
                if g.empty:
                    continue
                per = g.assign(kmh=g["speed"] * 3.6).groupby(["step", "episode"])["kmh"].mean().unstack()
                t = per.index.to_numpy() * (scenario_dt(env) if dt is None else dt)
                ax.plot(t, per.mean(axis=1), color=colour(a), lw=0.9)
                if per.shape[1] > 1:
                    ax.fill_between(t, per.min(axis=1), per.max(axis=1), color=colour(a),
                                    alpha=0.18, lw=0)
            _label_panel(ax, env, s, ylabel="speed (km/h)" if j == 0 else None,
                         xlabel=i == len(envs) - 1)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    _legend(fig, algos, labels, ncol=6)
    return _save(fig, out, "speed_per_timestep")


def _label_panel(ax, env: str, scenario, ylabel: str | None, xlabel: bool) -> None:
    """Title, grid and axis labels of one panel of an environment x scenario grid."""
    ax.set_title(f"{env_title(env)}, {SCENARIO_NAMES.get(scenario, scenario)}", loc="left")
    ax.grid(lw=0.3)
    if ylabel:
        ax.set_ylabel(ylabel)
    if xlabel:
        ax.set_xlabel("time (s)")


def survival(per: pd.DataFrame, out: Path, labels: Mapping[str, str], steps_s: float) -> list[Path]:
    """TTFC survival: share of episodes without a collision against time (Kaplan-Meier
    without censoring: every episode runs the same horizon)."""
    plt = _plt()
    scenarios = sorted(per["scenario"].unique())
    envs = sorted(per["env"].unique())
    algos = algo_order(per["algorithm"].unique())

    fig, axes = plt.subplots(len(envs), len(scenarios), figsize=(PAGE_IN, 1.2 * len(envs) + 0.5),
                             squeeze=False, sharex=True, sharey=True)
    for i, env in enumerate(envs):
        for j, s in enumerate(scenarios):
            ax = axes[i][j]
            sub = per[(per["env"] == env) & (per["scenario"] == s)]
            for k, a in enumerate(algos):
                g = sub[sub["algorithm"] == a]
                if g.empty:
                    continue
                ttfc = np.sort(g["TTFC"].to_numpy(float))
                n = len(ttfc)
                hits = ttfc[np.isfinite(ttfc)]
                t = np.concatenate([[0.0], hits, [steps_s]])
                alive = np.concatenate([[1.0], 1.0 - np.arange(1, len(hits) + 1) / n,
                                        [1.0 - len(hits) / n]])
                ax.step(t, alive + 0.006 * (k - len(algos) / 2), where="post", color=colour(a), lw=0.9)
            ax.set_ylim(-0.05, 1.08)
            _label_panel(ax, env, s, ylabel="no collision yet" if j == 0 else None,
                         xlabel=i == len(envs) - 1)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    _legend(fig, algos, labels, ncol=6)
    return _save(fig, out, "ttfc_survival")


def driving_score_matrix(long: pd.DataFrame, references: pd.DataFrame | None,
                         labels: Mapping[str, str]) -> pd.DataFrame:
    """Scenario 1's mean driving score per row (each algorithm, then the reference columns of
    Table RQ1 marked "(ref)") and environment (columns), with ``lo``/``hi`` the algorithms'
    95% interval ends, ``floor`` the strongest degenerate reference of that environment (random
    and the best degenerate) and ``clears`` whether an algorithm's lower end is above it (NaN
    without references)."""
    from eval.reporting.cells import BEST_DEGENERATE, reference_rows

    ds = long[(long["metric"] == "DS") & (long["scenario"] == (1 if (long["scenario"] == 1).any() else
                                                               long["scenario"].min()))]
    rows = []
    floor: dict[str, float] = {}
    for env, col, name, r in reference_rows(references):
        value = float(r["DS"]) if "DS" in r.index else float("nan")
        rows.append({"row": f"{name if col != BEST_DEGENERATE else 'best degenerate'} (ref)",
                     "env": env, "DS": value, "lo": np.nan, "hi": np.nan, "reference": True})
        if col in ("random", BEST_DEGENERATE) and np.isfinite(value):
            floor[env] = max(floor.get(env, -np.inf), value)
    rank = {a: i for i, a in enumerate(algo_order(ds["algorithm"].unique()))}  # the paper's order
    for _, r in ds.sort_values("algorithm", key=lambda s: s.map(rank), kind="stable").iterrows():
        rows.append({"row": labels.get(r["algorithm"], r["algorithm"]), "env": r["env"], "DS": r["mean"],
                     "lo": r["ci_low"], "hi": r["ci_high"], "reference": False,
                     "floor": floor.get(r["env"], np.nan),
                     "clears": (float(r["ci_low"]) > floor[r["env"]]) if r["env"] in floor else np.nan})
    return pd.DataFrame(rows)


def driving_score_heatmap(long: pd.DataFrame, references: pd.DataFrame | None, out: Path,
                          labels: Mapping[str, str]) -> list[Path]:
    """Who drives best where: Scenario 1's driving score per algorithm x environment (colour and
    value; a box where the lower end of its interval clears every degenerate reference), the
    reference rows below a line (:func:`driving_score_matrix`). ds_heatmap.pdf/.png."""
    plt = _plt()
    table = driving_score_matrix(long, references, labels)
    if table.empty:
        return []
    envs = [e for e in dict.fromkeys(long["env"])]
    algos = list(dict.fromkeys(table.loc[~table["reference"], "row"]))
    refs = list(dict.fromkeys(table.loc[table["reference"], "row"]))
    order = algos + refs
    grid = table.pivot_table(index="row", columns="env", values="DS", aggfunc="first").reindex(
        index=order, columns=envs)
    fig, ax = plt.subplots(figsize=(1.1 + 0.9 * len(envs), 0.9 + 0.28 * len(order)))
    ax.imshow(grid.to_numpy(dtype=float), vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    clears = table[~table["reference"]].set_index(["row", "env"])["clears"]
    for i, row in enumerate(order):
        for j, env in enumerate(envs):
            v = grid.iloc[i, j]
            if not np.isfinite(v):
                continue
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=6,
                    color="black" if v > 0.6 else "white")
            if clears.get((row, env)) is True:
                ax.add_patch(plt.Rectangle((j - 0.47, i - 0.45), 0.94, 0.9, fill=False,
                                           edgecolor="#ff4040", linewidth=1.2))
    if refs:
        ax.axhline(len(algos) - 0.5, color="white", linewidth=2)
    ax.xaxis.tick_top()  # the environments above the grid: on the page's first screen with it
    ax.set_xticks(range(len(envs)), [env_title(e) for e in envs])
    ax.set_yticks(range(len(order)), order)
    ax.set_title("Driving score, Scenario 1 (box: lower 95% end above every degenerate reference)",
                 fontsize=8, pad=18)
    # 120 dpi: the page shows the PNG at its own size, and the whole grid of 6 algorithms and the
    # references x 5 environments then fits a 1280x800 first screen below the verdict lines
    return _save(fig, Path(out), "ds_heatmap", dpi=120)


def write_all(records: pd.DataFrame, per: pd.DataFrame, long: pd.DataFrame, out: Path,
              labels: Mapping[str, str], dt: float | None = None) -> list[Path]:
    out = Path(out)
    horizon_s = max((float(g["step"].max()) * (scenario_dt(env) if dt is None else dt)
                     for env, g in records.groupby("env")), default=0.0)
    written = []
    written += bar_figure(long, [("safety", "Safety (collision-free\nepisodes)")], out,
                          "rq2_safety", labels, ylim01=True)
    written += bar_figure(long, [("SPEED", "SPEED (km/h)"), ("DISTANCE", "DISTANCE (m)")], out,
                          "rq2_efficiency", labels)
    written += bar_figure(long, [("lane_keeping", "Lane keeping\n(1 - OS)")], out,
                          "rq2_lane_keeping", labels, ylim01=True)
    written += speed_grid(records, out, labels, dt)
    written += survival(per, out, labels, horizon_s)
    return written


__all__ = ["ALGO_ORDER", "COLOURS", "colour", "write_all"]
