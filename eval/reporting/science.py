"""The statistics of the science study (``studies/science.py``, issue 14).

The study trains every (algorithm, environment, seed) with ``cosim benchmark`` and
tests each trained policy on held-out episode seeds under the test protocol
(collisions do not end an episode). This module turns those records into results
over *training seeds*:

- :func:`seed_means`: one value per (scenario, environment, algorithm, seed): the
  mean over that seed's test episodes (NaN-aware: TTFC and CP only where they apply, the
  goal rate of the turning slots only over the slots whose route turns, :func:`with_turning`);
- :func:`seed_table`: mean and 95% percentile-bootstrap CI over seeds
  (:func:`eval.reporting.stats.bootstrap_ci`: 2,000 resamples, fixed seed); n = seeds;
- :func:`reference_table`: the reference rows (eval/testing/validity.py: autopilot, uniform
  random, degenerate suite) with a CI over their episodes x ACs;
- :func:`verdict`: issue 14's item 1 per (algorithm, environment): mean return AND
  goal rate above every degenerate reference, the CI's lower end above its value, with
  at least :data:`MIN_SEEDS` training seeds;
- :func:`iqm_table`: the interquartile mean across environments per algorithm
  (rliable-style: returns normalised per environment between uniform random (0) and
  the autopilot (1), IQM over every (environment, seed) score, stratified bootstrap
  CI resampling seeds within each environment), drawn by :func:`iqm_figure`;
- :func:`convergence_curves` / :func:`convergence_figure`: training return against
  environment steps, one panel per algorithm, one curve per environment, mean over
  seeds with a min-max band.

rliable itself (PyPI) installs here but does not import: its ``arch`` dependency
(7.2) fails with pandas 3 (``deprecate_kwarg() missing 1 required positional
argument``), so :func:`iqm` and :func:`stratified_bootstrap` implement its
``aggregate_iqm`` (scipy's 25% ``trim_mean`` over all scores) and its stratified
percentile bootstrap in numpy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eval.labels import ENVS, algo_label, env_colour  # noqa: F401 - ENVS re-exported (studies/science.py)
from eval.reporting.page import md_table
from eval.reporting.report import algo_order, env_title
from eval.reporting.stats import BOOTSTRAP, CI_SEED, bootstrap_ci, iqm, stratified_bootstrap
from eval.testing.validity import DEGENERATE, POLICIES

METRICS = ("return", "goal", "goal_turning", "DISTANCE", "CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED")
"""The study's metrics (eval/testing/metrics.py names; ``goal`` is the goal rate, ``goal_turning``
the goal rate of the AC-episodes whose slot's route turns: :func:`with_turning`)."""
NAMES = {"return": "return", "goal": "goal rate", "goal_turning": "goal rate, turning slots",
         "DISTANCE": "DISTANCE (m)", "TTFC": "TTFC (s)", "SPEED": "SPEED (km/h)"}
DIGITS = {"return": 1, "goal": 2, "goal_turning": 2, "DISTANCE": 1, "TTFC": 2, "SPEED": 1}
VERDICT_SCENARIO = 1
"""The references run under Scenario 1 conditions (every AC in the traffic)."""
MIN_SEEDS = 3
"""Issue 14, item 1 asks for 3 training seeds: with fewer the verdict is 'not shown', whatever
the (then degenerate or two-point) bootstrap interval says."""
NORM_LOW, NORM_HIGH = "random", "autopilot"
"""The IQM's normalisation: uniform random over Discrete(9) scores 0, the autopilot 1."""
WINDOW = 20
"""Convergence: the mean return of the most recent episodes (any AC) finished by a step."""


# -- per seed ----------------------------------------------------------------------------
def slot_routes(env: str) -> pd.DataFrame:
    """Per slot (``ac_k``) of ``env``: its route's movement (cosim.roadmap.movement, entry to
    exit) and whether it turns anywhere (a pair of consecutive edges that is not straight:
    the turns the safe-non-turner holds before; every roundabout route turns on entering)."""
    from cosim.roadmap import movement, read_net
    from cosim.scenario import load_scenario

    sc = load_scenario(env)
    net = read_net(sc.net)
    rows = []
    for i, ac in enumerate(sc.acs):
        turns = any(movement(net, [a, b]) != "straight"
                    for a, b in zip(ac.route[:-1], ac.route[1:], strict=True))
        rows.append({"slot": f"ac_{i}", "movement": movement(net, list(ac.route)), "turning": turns})
    return pd.DataFrame(rows)


def with_turning(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` (per (episode, AC), with ``env``, ``agent`` and ``goal``) plus ``goal_turning``:
    the goal where the AC's slot turns (:func:`slot_routes`), NaN on straight slots, so its
    mean is the turning slots' goal rate (NaN in an environment without a turn)."""
    turning = {}
    for env in rows["env"].unique():
        r = slot_routes(env)
        turning[env] = set(r.loc[r["turning"], "slot"])
    mask = np.array([a in turning[e] for e, a in zip(rows["env"], rows["agent"], strict=True)], bool)
    return rows.assign(goal_turning=rows["goal"].astype(float).where(mask))


def seed_means(per: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """One row per (scenario, env, algorithm, train_seed): the mean over its test episodes
    (and ACs) of each metric; NaN where the metric never applied (CP without people,
    TTFC without a collision, the turning slots' goal rate where no slot turns)."""
    per = per.assign(goal=per["goal"].astype(float))
    if "goal_turning" in metrics and "goal_turning" not in per:
        per = with_turning(per)
    keys = ["scenario", "env", "algorithm", "train_seed"]
    return per.groupby(keys, sort=True)[list(metrics)].mean().reset_index()


def fmt(metric: str, mean: float, lo: float, hi: float, n: int | None = None,
        of: int | None = None) -> str:
    """'mean [low, high]', with '(n=k)' when the metric applied in k of ``of`` values only;
    '-' when it never applied ('--' for TTFC: no collision)."""
    if not np.isfinite(mean):
        return "--" if metric == "TTFC" else "-"
    d = DIGITS.get(metric, 3)
    text = f"{mean:.{d}f} [{lo:.{d}f}, {hi:.{d}f}]"
    return text + (f" (n={n})" if n is not None and of is not None and n != of else "")


def over_seeds(mean: float, lo: float, hi: float, n: int) -> str:
    """A mean return and its 95% interval as the README's tables write them: 'mean [low, high]'
    with thousands separators; one value (n = 1, no interval): the mean alone."""
    return f"{mean:,.1f}" if n == 1 else f"{mean:,.1f} [{lo:,.1f}, {hi:,.1f}]"


def return_goal_cell(mean: float, lo: float, hi: float, n: int, goal: float) -> str:
    """'return [95% CI] (goal rate)' as the README's grids write a cell; one seed:
    'return (goal rate; 1 seed)'."""
    return f"{over_seeds(mean, lo, hi, n)} ({goal:.2f}{'' if n > 1 else '; 1 seed'})"


def _row(scenario, env, kind, name, metric, values) -> dict:
    mean, lo, hi, n = bootstrap_ci(values)
    cell = fmt(metric, mean, lo, hi, n, len(values))
    if kind == "algorithm" and n == 1 and np.isfinite(mean):  # one seed: no interval to show
        cell = f"{mean:.{DIGITS.get(metric, 3)}f} (1 seed)"
    return {"scenario": int(scenario), "env": env, "title": env_title(env), "kind": kind,
            "name": name, "metric": metric, "mean": mean, "ci_low": lo, "ci_high": hi, "n": n,
            "cell": cell}


def seed_table(seeds: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """Long table: per (scenario, env, algorithm, metric) the mean over seeds, its 95%
    bootstrap CI and n (the seeds where the metric applied)."""
    rows = []
    for (scenario, env, algo), g in seeds.groupby(["scenario", "env", "algorithm"], sort=True):
        for m in metrics:
            rows.append(_row(scenario, env, "algorithm", algo, m, g[m].to_numpy(float)))
    return pd.DataFrame(rows)


def reference_table(refs: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """Long table of the reference rows (eval/testing/validity.py per-(episode, AC) rows with an
    ``env`` column): mean and CI over episodes x ACs, under Scenario 1 conditions."""
    rows = []
    if "goal_turning" in metrics and "goal_turning" not in refs:
        refs = with_turning(refs)
    for (env, policy), g in refs.groupby(["env", "policy"], sort=False):
        for m in metrics:
            rows.append(_row(VERDICT_SCENARIO, env, "reference", policy, m, g[m].to_numpy(float)))
    return pd.DataFrame(rows)


# -- verdict -------------------------------------------------------------------------------
def degenerate_means(references: pd.DataFrame, env: str, metric: str,
                     degenerate: Sequence[str] = tuple(DEGENERATE)) -> dict[str, float]:
    """Mean ``metric`` of every degenerate reference run in ``env`` (name -> value)."""
    r = references[(references["env"] == env) & (references["metric"] == metric)
                   & references["name"].isin(degenerate)]
    return dict(zip(r["name"], r["mean"].astype(float), strict=True))


def verdict(table: pd.DataFrame, references: pd.DataFrame,
            degenerate: Sequence[str] = tuple(DEGENERATE), min_seeds: int = MIN_SEEDS
            ) -> pd.DataFrame:
    """Per (algorithm, env) of Scenario 1: does the mean return AND goal rate beat every
    degenerate reference with the 95% CI excluding the reference's value (CI low > value),
    over at least ``min_seeds`` training seeds?

    Columns: algorithm, env, n, return/goal mean and CI, the strongest degenerate reference
    for each (name and value), return_ok, goal_ok, seeds_ok, passed, why (what failed, or '').
    """
    t = table[(table["kind"] == "algorithm") & (table["scenario"] == VERDICT_SCENARIO)]
    rows = []
    for (algo, env), g in t.groupby(["name", "env"], sort=False):
        g = g.set_index("metric")
        row = {"algorithm": algo, "env": env, "title": env_title(env), "n": int(g.loc["return", "n"])}
        why = []
        for m in ("return", "goal"):
            mean, lo, hi = (float(g.loc[m, c]) for c in ("mean", "ci_low", "ci_high"))
            env_refs = degenerate_means(references, env, m, degenerate)
            if not env_refs:
                raise ValueError(f"no degenerate reference for {env} ({m}); run the references first")
            best = max(env_refs, key=env_refs.get)
            # above, and not equal up to float rounding (the mean of three 0.1s is 0.10000000000000002)
            beaten = [name for name, v in env_refs.items() if lo > v and not np.isclose(lo, v)]
            ok = len(beaten) == len(env_refs)
            row.update({f"{m}_mean": mean, f"{m}_ci_low": lo, f"{m}_ci_high": hi,
                        f"{m}_best_reference": best, f"{m}_reference": env_refs[best], f"{m}_ok": ok})
            if not ok:
                lost = len(env_refs) - len(beaten)
                why.append(f"{NAMES.get(m, m)} CI low {lo:.{DIGITS[m]}f} <= {best} "
                           f"{env_refs[best]:.{DIGITS[m]}f}"
                           + (f" (and {lost - 1} more)" if lost > 1 else ""))
        # informational (issue 27's target): do the turning slots reach goals at all?
        row["turning_goal_mean"] = (float(g.loc["goal_turning", "mean"]) if "goal_turning" in g.index
                                    else float("nan"))
        row["seeds_ok"] = row["n"] >= min_seeds
        if not row["seeds_ok"]:
            why.append(f"{row['n']} seed(s), item 1 needs {min_seeds}")
        row["passed"] = row["return_ok"] and row["goal_ok"] and row["seeds_ok"]
        row["why"] = "; ".join(why)
        rows.append(row)
    out = pd.DataFrame(rows)
    order = {a: i for i, a in enumerate(algo_order(out["algorithm"].unique()))}
    return out.sort_values(["algorithm", "env"], key=lambda c: c.map(order) if c.name == "algorithm"
                           else c).reset_index(drop=True)


def targets(v: pd.DataFrame) -> pd.DataFrame:
    """Per environment, issue 27's target read off a :func:`verdict`: the discrete and the
    continuous algorithms that pass (clear every degenerate reference, 3+ seeds), and those
    whose turning slots reach goals (mean > 0; NaN where no slot's route turns)."""
    from agents.registry import CONTINUOUS, DISCRETE

    rows = []
    for env, g in v.groupby("env", sort=False):
        passed = g.loc[g["passed"], "algorithm"].tolist()
        turning = g["turning_goal_mean"]
        rows.append({"env": env, "title": env_title(env),
                     "discrete": [a for a in passed if a in DISCRETE],
                     "continuous": [a for a in passed if a in CONTINUOUS],
                     "has_turns": bool(turning.notna().any()),
                     "turning": g.loc[turning > 0, "algorithm"].tolist()})
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
                     "algorithms whose turning slots reach goals", "target"], rows)


def normalise(seeds: pd.DataFrame, references: pd.DataFrame) -> pd.DataFrame:
    """Scenario 1 returns per (env, algorithm, seed) as (R - random) / (autopilot - random),
    with the references' mean returns in that environment; column ``score``. An environment
    where the autopilot does not out-earn random cannot be normalised: its scores are NaN."""
    s1 = seeds[seeds["scenario"] == VERDICT_SCENARIO]
    ref = references[references["metric"] == "return"].set_index(["env", "name"])["mean"]
    out = []
    for env, g in s1.groupby("env", sort=True):
        low, high = ref.get((env, NORM_LOW), np.nan), ref.get((env, NORM_HIGH), np.nan)
        span = high - low
        score = (g["return"] - low) / span if np.isfinite(span) and span > 0 else np.nan
        out.append(g[["env", "algorithm", "train_seed", "return"]].assign(score=score))
    return pd.concat(out, ignore_index=True)


def iqm_table(seeds: pd.DataFrame, references: pd.DataFrame) -> pd.DataFrame:
    """Per algorithm: IQM of the normalised Scenario 1 returns over every (env, seed), its
    stratified-bootstrap 95% CI, the environments and runs it pools; then the degenerate
    references' IQM over environments of their normalised mean (no seeds: no CI)."""
    norm = normalise(seeds, references)
    rows = []
    for algo in algo_order(norm["algorithm"].unique()):
        g = norm[(norm["algorithm"] == algo) & np.isfinite(norm["score"])]
        if g.empty:
            continue
        by_env = {env: e["score"].to_numpy() for env, e in g.groupby("env", sort=True)}
        point, lo, hi = stratified_bootstrap(by_env)
        rows.append({"kind": "algorithm", "name": algo, "iqm": point, "ci_low": lo, "ci_high": hi,
                     "envs": len(by_env), "runs": len(g)})
    ref = references[references["metric"] == "return"].pivot(index="env", columns="name", values="mean")
    if NORM_LOW in ref and NORM_HIGH in ref:
        span = ref[NORM_HIGH] - ref[NORM_LOW]
        ok = span > 0
        for name in [p for p in POLICIES if p in ref.columns]:
            scores = ((ref[name] - ref[NORM_LOW]) / span)[ok].to_numpy()
            if len(scores):
                v = float(iqm(scores))
                rows.append({"kind": "reference", "name": name, "iqm": v, "ci_low": np.nan,
                             "ci_high": np.nan, "envs": len(scores), "runs": len(scores)})
    return pd.DataFrame(rows)


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


PLATEAU_FRACTION = 0.2
"""The share of a run's budget in each of the two windows :func:`budget_check` compares."""


def late_gain(episodes: pd.DataFrame, budget: int, fraction: float = PLATEAU_FRACTION,
              resamples: int = BOOTSTRAP, seed: int = CI_SEED) -> tuple[float, float, float, int]:
    """(gain, low, high, n): the mean training return of the episodes that ended in the last
    ``fraction`` of the budget minus that of the episodes in the ``fraction`` before, with a
    95% percentile bootstrap interval (each window's AC-episodes resampled apart; n: the
    smaller window's count). NaNs when a window has no episode. The episodes of one AC are
    not independent, so the interval is narrower than a repeat of the run would give."""
    steps = episodes["env_step"].to_numpy(float)
    returns = episodes["return"].to_numpy(float)
    late = returns[(steps > budget * (1 - fraction)) & (steps <= budget)]
    before = returns[(steps > budget * (1 - 2 * fraction)) & (steps <= budget * (1 - fraction))]
    if len(late) == 0 or len(before) == 0:
        return float("nan"), float("nan"), float("nan"), 0
    rng = np.random.default_rng(seed)
    draws = (late[rng.integers(0, len(late), (resamples, len(late)))].mean(axis=1)
             - before[rng.integers(0, len(before), (resamples, len(before)))].mean(axis=1))
    lo, hi = np.percentile(draws, [2.5, 97.5])
    return float(late.mean() - before.mean()), float(lo), float(hi), min(len(late), len(before))


def budget_check(runs: Mapping[tuple[str, str, int], Path], fraction: float = PLATEAU_FRACTION) -> pd.DataFrame:
    """Did each run's budget let its training curve flatten? Per run (``runs`` maps
    (algorithm, env, seed) to a run folder): :func:`late_gain` of its episodes.csv, and
    ``rising`` when the interval's lower end is above 0 (the return still grew over the
    last ``fraction`` of the budget: a longer run would likely score more). Columns:
    algorithm, env, seed, budget, gain, low, high, n, rising."""
    import yaml

    rows = []
    for (algo, env, seed), run in runs.items():
        budget = int(yaml.safe_load((Path(run) / "config.yaml").read_text())["steps"])
        csv = Path(run) / "episodes.csv"
        episodes = (pd.read_csv(csv, usecols=["env_step", "return"]) if csv.exists() and csv.stat().st_size
                    else pd.DataFrame({"env_step": [], "return": []}))
        gain, lo, hi, n = late_gain(episodes, budget, fraction)
        rows.append({"algorithm": algo, "env": env, "seed": int(seed), "budget": budget, "gain": gain,
                     "low": lo, "high": hi, "n": n, "rising": bool(n and lo > 0)})
    return pd.DataFrame(rows)


def budget_markdown(check: pd.DataFrame) -> str:
    """Algorithms x environments: the mean gain over seeds and how many seeds still rise
    (bold when any does); "-" where no run has episodes in both windows."""
    envs = sorted(check["env"].unique())
    rows = []
    for algo in algo_order(check["algorithm"].unique()):
        cells = []
        for env in envs:
            c = check[(check["algorithm"] == algo) & (check["env"] == env) & (check["n"] > 0)]
            rising = int(c["rising"].sum())
            text = f"{c['gain'].mean():+.0f} (rising {rising}/{len(c)})" if len(c) else "-"
            cells.append(f"**{text}**" if rising else text)
        budget = int(check.loc[check["algorithm"] == algo, "budget"].max())
        rows.append([algo_label(algo), f"{budget:,}", *cells])
    return md_table(["algorithm", "budget (env steps)", *[env_title(e) for e in envs]], rows)


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
SYMLOG_RETURN = 1_000.0
"""The verdict figure's return axis is linear within +-1,000 and logarithmic beyond: a run sunk by
contact reaches -10,000 where the references sit near -550 and the autopilot at 1,300-3,100."""
RETURN_TICKS = (-20_000, -10_000, -5_000, -2_000, -1_000, -500, 0, 500, 1_000, 2_000, 5_000, 10_000)


def verdict_lines(v: pd.DataFrame, references: pd.DataFrame, env: str, metric: str) -> list[tuple[str, float, str]]:
    """The reference lines of one :func:`verdict_figure` panel, (label, value, line style): the
    autopilot, the strongest degenerate reference (what a CI's lower end must clear, named) and,
    where a slot's route turns, the safe non-turner (:func:`shows_reference`)."""
    first = v[v["env"] == env].iloc[0]
    turns = bool(v.loc[v["env"] == env, "turning_goal_mean"].notna().any())
    r = references[(references["env"] == env) & (references["metric"] == metric)].set_index("name")["mean"]
    lines = [("autopilot", float(r["autopilot"]), "-")] if "autopilot" in r.index else []
    lines.append((f"best degenerate ({first[f'{metric}_best_reference']})", float(first[f"{metric}_reference"]), "--"))
    if "safe-non-turner" in r.index and shows_reference("safe-non-turner", turns):
        lines.append(("safe non-turner", float(r["safe-non-turner"]), ":"))
    return lines


def verdict_figure(v: pd.DataFrame, seeds: pd.DataFrame, references: pd.DataFrame, out: Path,
                   stem: str = "verdict") -> list[Path]:
    """The :func:`verdict` grid drawn: one column per environment, Scenario 1's return (top, axis
    :data:`SYMLOG_RETURN`) and goal rate (bottom); per algorithm each training seed's mean (dots) and
    the mean with its 95% CI over seeds (bar), "pass" above a pair that clears every degenerate
    reference; the :func:`verdict_lines` across. PDF and PNG."""
    from eval.labels import colour
    from eval.reporting.figures import PAGE_IN, _plt, _save

    plt = _plt()
    envs = sorted(v["env"].unique())
    algos = algo_order(v["algorithm"].unique())
    s1 = seeds[seeds["scenario"] == VERDICT_SCENARIO]
    width = min(PAGE_IN, 1.0 + 1.25 * len(envs))  # one environment: a column, not a stretched page
    fig, axes = plt.subplots(2, len(envs), figsize=(width, 3.6), squeeze=False)
    styles = {}
    for col, env in enumerate(envs):
        for row, metric in enumerate(("return", "goal")):
            ax = axes[row][col]
            for label, value, style in verdict_lines(v, references, env, metric):
                kind = label.split(" (")[0]
                ax.axhline(value, color="#444444" if kind != "best degenerate" else "#C00000",
                           ls=style, lw=0.8, zorder=1)
                styles.setdefault(kind, style)
            for x, algo in enumerate(algos):
                r = v[(v["env"] == env) & (v["algorithm"] == algo)]
                if r.empty:
                    continue
                r = r.iloc[0]
                c = colour(algo)
                pts = s1.loc[(s1["env"] == env) & (s1["algorithm"] == algo), metric].to_numpy(float)
                ax.scatter(x + np.linspace(-0.15, 0.15, len(pts)) if len(pts) > 1 else [x] * len(pts),
                           pts, s=6, color=c, alpha=0.6, lw=0, zorder=2)
                lo, hi, mean = r[f"{metric}_ci_low"], r[f"{metric}_ci_high"], r[f"{metric}_mean"]
                ax.errorbar([x], [mean], yerr=[[mean - lo], [hi - mean]], fmt="_", color=c, ms=8,
                            mew=1.4, elinewidth=1.2, capsize=0, zorder=3)
                if row == 0 and r["passed"]:
                    ax.annotate("pass", (x, hi), xytext=(0, 3), textcoords="offset points",
                                ha="center", fontsize=5.5, fontweight="bold")
            ax.set_xticks(range(len(algos)))
            ax.set_xticklabels([algo_label(a) for a in algos] if row == 1 else [], rotation=90)
            ax.set_xlim(-0.6, len(algos) - 0.4)
            ax.grid(axis="y", lw=0.3)
            if metric == "return":
                ax.set_yscale("symlog", linthresh=SYMLOG_RETURN)
                low, high = ax.get_ylim()
                ax.set_ylim(low, high + 0.6 * abs(high))  # room for "pass" above the autopilot's line
                ax.set_yticks([t for t in RETURN_TICKS if low <= t <= high])
                ax.yaxis.set_major_formatter(lambda t, _: f"{t:,.0f}")
                ax.yaxis.set_minor_locator(plt.NullLocator())
                ax.set_title(env_title(env), loc="left")
            else:
                ax.set_ylim(-0.04, 1.08)
        axes[0][col].tick_params(axis="y", labelsize=5)
    axes[0][0].set_ylabel("Scenario 1 return")
    axes[1][0].set_ylabel("goal rate")
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
    normalised Scenario 1 return with the 95% stratified bootstrap CI, against :func:`iqm_lines`.
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
    ax.set_xlabel(f"IQM of Scenario 1 return over {envs} environment{'s' if envs != 1 else ''} "
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


def verdict_markdown(v: pd.DataFrame) -> str:
    rows = []
    for _, r in v.iterrows():
        rows.append([algo_label(r["algorithm"]), r["title"], r["n"],
                     fmt("return", r["return_mean"], r["return_ci_low"], r["return_ci_high"]),
                     f"{r['return_best_reference']} {r['return_reference']:.1f}",
                     fmt("goal", r["goal_mean"], r["goal_ci_low"], r["goal_ci_high"]),
                     f"{r['goal_best_reference']} {r['goal_reference']:.2f}",
                     _verdict_word(r), r["why"]])
    return md_table(["algorithm", "environment", "seeds", "return [95% CI]", "best degenerate return",
                     "goal rate [95% CI]", "best degenerate goal rate", "verdict", "why"], rows)


def _verdict_word(r) -> str:
    """'pass', 'not shown' (above every reference, too few seeds) or 'FAIL' for a verdict row."""
    return "pass" if r["passed"] else ("not shown" if r["return_ok"] and r["goal_ok"] else "FAIL")


def shows_reference(name: str, route_turns: bool) -> bool:
    """Whether a table shows the reference row ``name`` for an environment: the safe non-turner
    only where some slot's route turns (elsewhere it drives as the autopilot does)."""
    return name != "safe-non-turner" or route_turns


def verdict_grid_markdown(v: pd.DataFrame, references: pd.DataFrame | None = None) -> str:
    """The :func:`verdict` as one algorithms x environments grid: each cell 'return [95% CI]
    (goal rate), verdict' ('return (goal rate; 1 seed)' with one seed), a pass in bold; with
    ``references`` (:func:`reference_table`'s Scenario 1 rows) the autopilot's and the safe
    non-turner's 'return (goal rate)' below (the safe non-turner only where a route turns: elsewhere
    it is the autopilot); last, each environment's strongest degenerate return and goal rate (what
    a cell's CI must clear). The README's results table."""
    envs = sorted(v["env"].unique())
    cells = {}
    for _, r in v.iterrows():
        word = _verdict_word(r)
        cell = return_goal_cell(r["return_mean"], r["return_ci_low"], r["return_ci_high"], r["n"], r["goal_mean"])
        cells[(r["algorithm"], r["env"])] = f"{cell}, " + (f"**{word}**" if word == "pass" else word)
    rows = [[algo_label(a)] + [cells.get((a, e), "") for e in envs] for a in algo_order(v["algorithm"].unique())]
    if references is not None:
        r = references.set_index(["name", "env", "metric"])["mean"]
        turns = v.groupby("env")["turning_goal_mean"].apply(lambda x: x.notna().any())
        for name, label in (("autopilot", "autopilot"), ("safe-non-turner", "safe non-turner")):
            row = [f"{r[(name, e, 'return')]:,.1f} ({r[(name, e, 'goal')]:.2f})"
                   if (name, e, "return") in r.index and shows_reference(name, turns[e]) else ""
                   for e in envs]
            if any(row):
                rows.append([f"*{label}*", *row])
    first = v.drop_duplicates("env").set_index("env")
    rows.append(["*best degenerate*"] + [
        f"{first.loc[e, 'return_reference']:,.1f} ({first.loc[e, 'return_best_reference']}); "
        f"{first.loc[e, 'goal_reference']:.2f} ({first.loc[e, 'goal_best_reference']})" for e in envs])
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


def iqm_markdown(t: pd.DataFrame) -> str:
    rows = []
    for _, r in t.iterrows():
        ci = f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}]" if np.isfinite(r["ci_low"]) else "-"
        label = algo_label(r["name"]) if r["kind"] == "algorithm" else f"*{r['name']}*"
        rows.append([label, f"{r['iqm']:.2f}", ci, r["envs"], r["runs"]])
    return md_table(["policy", "IQM (normalised return)", "95% CI", "environments", "scores"], rows)


__all__ = ["METRICS", "budget_check", "budget_markdown", "convergence_curve", "convergence_curves",
           "convergence_figure", "iqm_figure", "iqm_lines", "iqm_table", "normalise", "reference_table", "seed_means",
           "seed_table", "verdict",
           "verdict_figure", "verdict_grid_markdown", "verdict_lines", "over_seeds", "return_goal_grid_markdown"]
