"""The statistics of the science study (``studies/science.py``, issue 14).

The study trains every (algorithm, environment, seed) with ``cosim benchmark`` and
tests each trained policy on held-out episode seeds under the test protocol
(collisions do not end an episode). This module turns those records into results
over *training seeds*:

- :func:`seed_means`: one value per (scenario, environment, algorithm, seed): the
  mean over that seed's test episodes (NaN-aware: TTFC and CP only where they apply, the
  goal rate and route completion of the turning slots only over the slots whose route turns,
  :func:`with_turning`);
- :func:`seed_table`: mean and 95% percentile-bootstrap CI over seeds
  (:func:`eval.reporting.stats.bootstrap_ci`: 2,000 resamples, fixed seed); n = seeds;
- :func:`reference_table`: the reference rows (eval/testing/validity.py: autopilot, uniform
  random, degenerate suite) with a CI over their episodes x ACs;
- :func:`verdict`: per (algorithm, environment) of Scenario 1, on the driving score
  (cosim/score.py; docs/task.md, "Driving score"; issue 61): a pair passes when the lower end
  of its DS interval over training seeds clears every degenerate reference's mean DS, with
  at least :data:`MIN_SEEDS` seeds; its turns are learned where the lower end of the turning
  slots' route completion interval clears the safe non-turner's (``turning_ok``). The return
  and goal rate stay in its rows as information;
- :func:`iqm_table`: the interquartile mean across environments per algorithm
  (rliable-style: the driving score normalised per environment between uniform random (0)
  and the autopilot (1), IQM over every (environment, seed) score, stratified bootstrap
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

METRICS = ("DS", "RC", "success", "RC_turning", "return", "goal", "goal_turning", "DISTANCE",
           "CV_events", "CO_events", "CP_events", "CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED")
"""The study's metrics (eval/testing/metrics.py names; the driving score's first; ``goal`` is
the goal rate, ``goal_turning`` and ``RC_turning`` the goal rate and route completion of the
AC-episodes whose slot's route turns: :func:`with_turning`)."""
NAMES = {"DS": "driving score", "RC": "route completion", "success": "success rate",
         "RC_turning": "route completion, turning slots", "return": "return", "goal": "goal rate",
         "goal_turning": "goal rate, turning slots", "CV_events": "CV events", "CO_events": "CO events",
         "CP_events": "CP events", "DISTANCE": "DISTANCE (m)", "TTFC": "TTFC (s)", "SPEED": "SPEED (km/h)"}
DIGITS = {"DS": 3, "RC": 3, "RC_turning": 3, "success": 2, "return": 1, "goal": 2, "goal_turning": 2,
          "CV_events": 2, "CO_events": 2, "CP_events": 2, "DISTANCE": 1, "TTFC": 2, "SPEED": 1}
VERDICT_METRIC = "DS"
"""What the verdict and the IQM score: the driving score (issue 61)."""
TURNING_METRIC, TURNING_REFERENCE = "RC_turning", "safe-non-turner"
"""Turns are learned where the turning slots' route completion clears the safe non-turner's."""
VERDICT_SCENARIO = 1
"""The references run under Scenario 1 conditions (every AC in the traffic)."""
MIN_SEEDS = 3
"""Issue 14, item 1 asks for 3 training seeds: with fewer the verdict is 'not shown', whatever
the (then degenerate or two-point) bootstrap interval says."""
NORM_LOW, NORM_HIGH = "random", "autopilot"
"""The IQM's normalisation of the driving score: uniform random over Discrete(9) scores 0, the
autopilot 1."""
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
    """``rows`` (per (episode, AC), with ``env``, ``agent``, ``goal`` and ``RC``) plus
    ``goal_turning`` and ``RC_turning``: the goal and the route completion where the AC's slot
    turns (:func:`slot_routes`), NaN on straight slots, so their means are the turning slots'
    goal rate and route completion (NaN in an environment without a turn; RC_turning NaN too
    where the rows have no RC)."""
    turning = {}
    for env in rows["env"].unique():
        r = slot_routes(env)
        turning[env] = set(r.loc[r["turning"], "slot"])
    mask = np.array([a in turning[e] for e, a in zip(rows["env"], rows["agent"], strict=True)], bool)
    rc = rows["RC"].astype(float) if "RC" in rows else pd.Series(np.nan, index=rows.index)
    return rows.assign(goal_turning=rows["goal"].astype(float).where(mask), RC_turning=rc.where(mask))


def _with_metrics(frame: pd.DataFrame, metrics: Sequence[str]) -> pd.DataFrame:
    """``frame`` with a NaN column for each of ``metrics`` it lacks (rows written before the
    driving score: their DS, RC, ... are '-')."""
    missing = [m for m in metrics if m not in frame]
    return frame.assign(**dict.fromkeys(missing, np.nan)) if missing else frame


def seed_means(per: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """One row per (scenario, env, algorithm, train_seed): the mean over its test episodes
    (and ACs) of each metric; NaN where the metric never applied (CP without people,
    TTFC without a collision, the turning slots' metrics where no slot turns) or was not
    measured (records without the driving score's columns: eval/testing/metrics.py)."""
    per = per.assign(goal=per["goal"].astype(float))
    if {"goal_turning", "RC_turning"} & set(metrics) and not {"goal_turning", "RC_turning"} <= set(per):
        per = with_turning(per)
    per = _with_metrics(per, metrics)
    keys = ["scenario", "env", "algorithm", "train_seed"]
    return per.groupby(keys, sort=True)[[m for m in metrics]].mean().reset_index()


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
    seeds = _with_metrics(seeds, metrics)  # seed means kept from before the driving score: '-'
    for (scenario, env, algo), g in seeds.groupby(["scenario", "env", "algorithm"], sort=True):
        for m in metrics:
            rows.append(_row(scenario, env, "algorithm", algo, m, g[m].to_numpy(float)))
    return pd.DataFrame(rows)


def reference_table(refs: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """Long table of the reference rows (eval/testing/validity.py per-(episode, AC) rows with an
    ``env`` column): mean and CI over episodes x ACs, under Scenario 1 conditions."""
    rows = []
    if {"goal_turning", "RC_turning"} & set(metrics) and not {"goal_turning", "RC_turning"} <= set(refs):
        refs = with_turning(refs)
    refs = _with_metrics(refs, metrics)  # reference rows from before the driving score: '-'
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


def _clears(low: float, value: float) -> bool:
    """``low`` above ``value`` and not equal up to float rounding (the mean of three 0.1s is
    0.10000000000000002)."""
    return bool(low > value and not np.isclose(low, value))


def verdict(table: pd.DataFrame, references: pd.DataFrame,
            degenerate: Sequence[str] = tuple(DEGENERATE), min_seeds: int = MIN_SEEDS
            ) -> pd.DataFrame:
    """Per (algorithm, env) of Scenario 1, on the driving score (docs/task.md, "Driving score"):
    does the lower end of the DS 95% CI over training seeds clear the mean DS of every
    degenerate reference (CI low > value), over at least ``min_seeds`` seeds? And are its turns
    learned: does the lower end of the turning slots' route completion CI clear the safe
    non-turner's (``turning_ok``; NaN where no slot turns or no safe non-turner ran)?

    Columns: algorithm, env, n, DS mean and CI, the strongest degenerate reference (name and
    DS), DS_ok, RC_turning mean and CI, the safe non-turner's RC_turning, turning_ok, seeds_ok,
    passed (DS_ok and seeds_ok), why (what failed, or ''); as information the return and goal
    rate (mean and CI) and the turning slots' goal rate (``turning_goal_mean``).
    """
    m = VERDICT_METRIC
    t = table[(table["kind"] == "algorithm") & (table["scenario"] == VERDICT_SCENARIO)]
    rows = []
    for (algo, env), g in t.groupby(["name", "env"], sort=False):
        g = g.set_index("metric")
        row = {"algorithm": algo, "env": env, "title": env_title(env), "n": int(g.loc[m, "n"])}
        why = []
        for info in ("return", "goal"):  # what the verdict used to score: shown, not judged
            if info in g.index:
                row.update({f"{info}_{c}": float(g.loc[info, k]) for c, k in
                            (("mean", "mean"), ("ci_low", "ci_low"), ("ci_high", "ci_high"))})
        mean, lo, hi = (float(g.loc[m, c]) for c in ("mean", "ci_low", "ci_high"))
        env_refs = {k: v for k, v in degenerate_means(references, env, m, degenerate).items() if np.isfinite(v)}
        if not env_refs:
            raise ValueError(f"no degenerate reference's {NAMES[m]} ({m}) for {env}: run the references "
                             "again (rows from before the driving score have none)")
        best = max(env_refs, key=env_refs.get)
        beaten = [name for name, v in env_refs.items() if np.isfinite(lo) and _clears(lo, v)]
        ok = len(beaten) == len(env_refs)
        row.update({f"{m}_mean": mean, f"{m}_ci_low": lo, f"{m}_ci_high": hi,
                    f"{m}_best_reference": best, f"{m}_reference": env_refs[best], f"{m}_ok": ok})
        if not np.isfinite(mean):
            why.append(f"no {NAMES[m]} measured (records from before the driving score)")
        elif not ok:
            lost = len(env_refs) - len(beaten)
            why.append(f"{NAMES[m]} CI low {lo:.{DIGITS[m]}f} <= {best} {env_refs[best]:.{DIGITS[m]}f}"
                       + (f" (and {lost - 1} more)" if lost > 1 else ""))
        # the turns: the turning slots' route completion against the safe non-turner's
        tm = TURNING_METRIC
        t_mean, t_lo, t_hi = ((float(g.loc[tm, c]) for c in ("mean", "ci_low", "ci_high"))
                              if tm in g.index else (np.nan,) * 3)
        r = references[(references["env"] == env) & (references["metric"] == tm)
                       & (references["name"] == TURNING_REFERENCE)]["mean"]
        ref = float(r.iloc[0]) if len(r) else np.nan
        row.update({f"{tm}_mean": t_mean, f"{tm}_ci_low": t_lo, f"{tm}_ci_high": t_hi,
                    f"{tm}_reference": ref,
                    "turning_ok": _clears(t_lo, ref) if np.isfinite(t_mean) and np.isfinite(ref) else np.nan})
        row["turning_goal_mean"] = (float(g.loc["goal_turning", "mean"]) if "goal_turning" in g.index
                                    else float("nan"))
        row["seeds_ok"] = row["n"] >= min_seeds
        if not row["seeds_ok"]:
            why.append(f"{row['n']} seed(s), the verdict needs {min_seeds}")
        row["passed"] = bool(row[f"{m}_ok"] and row["seeds_ok"])
        row["why"] = "; ".join(why)
        rows.append(row)
    out = pd.DataFrame(rows)
    order = {a: i for i, a in enumerate(algo_order(out["algorithm"].unique()))}
    return out.sort_values(["algorithm", "env"], key=lambda c: c.map(order) if c.name == "algorithm"
                           else c).reset_index(drop=True)


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
        learned = g["turning_ok"].map(lambda x: _turning_word(x) == "yes").astype(bool)
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


def normalise(seeds: pd.DataFrame, references: pd.DataFrame, metric: str = VERDICT_METRIC) -> pd.DataFrame:
    """Scenario 1 ``metric`` (the driving score) per (env, algorithm, seed) as (x - random) /
    (autopilot - random), with the references' means in that environment; column ``score``.
    An environment where the autopilot does not score above random cannot be normalised: its
    scores are NaN."""
    s1 = _with_metrics(seeds[seeds["scenario"] == VERDICT_SCENARIO], [metric])
    ref = references[references["metric"] == metric].set_index(["env", "name"])["mean"]
    out = []
    for env, g in s1.groupby("env", sort=True):
        low, high = ref.get((env, NORM_LOW), np.nan), ref.get((env, NORM_HIGH), np.nan)
        span = high - low
        score = (g[metric] - low) / span if np.isfinite(span) and span > 0 else np.nan
        out.append(g[["env", "algorithm", "train_seed", metric]].assign(score=score))
    return pd.concat(out, ignore_index=True)


def iqm_table(seeds: pd.DataFrame, references: pd.DataFrame, metric: str = VERDICT_METRIC) -> pd.DataFrame:
    """Per algorithm: IQM of the normalised Scenario 1 driving score (``metric``) over every
    (env, seed), its stratified-bootstrap 95% CI, the environments and runs it pools; then the
    references' IQM over environments of their normalised mean (no seeds: no CI)."""
    norm = normalise(seeds, references, metric)
    rows = []
    for algo in algo_order(norm["algorithm"].unique()):
        g = norm[(norm["algorithm"] == algo) & np.isfinite(norm["score"])]
        if g.empty:
            continue
        by_env = {env: e["score"].to_numpy() for env, e in g.groupby("env", sort=True)}
        point, lo, hi = stratified_bootstrap(by_env)
        rows.append({"kind": "algorithm", "name": algo, "iqm": point, "ci_low": lo, "ci_high": hi,
                     "envs": len(by_env), "runs": len(g)})
    ref = references[references["metric"] == metric].pivot(index="env", columns="name", values="mean")
    if NORM_LOW in ref and NORM_HIGH in ref:
        span = ref[NORM_HIGH] - ref[NORM_LOW]
        ok = span > 0
        for name in [p for p in POLICIES if p in ref.columns]:
            scores = ((ref[name] - ref[NORM_LOW]) / span)[ok].to_numpy(float)
            scores = scores[np.isfinite(scores)]
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
    s1 = _with_metrics(seeds[seeds["scenario"] == VERDICT_SCENARIO], FIGURE_METRICS)
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
                        "turns" if row == 1 and _turning_word(r["turning_ok"]) == "yes" else "")
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


def verdict_markdown(v: pd.DataFrame) -> str:
    m, tm = VERDICT_METRIC, TURNING_METRIC
    rows = []
    for _, r in v.iterrows():
        turning = (f"{fmt(tm, r[f'{tm}_mean'], r[f'{tm}_ci_low'], r[f'{tm}_ci_high'])}"
                   if np.isfinite(r[f"{tm}_mean"]) else "-")
        ref = f"{r[f'{tm}_reference']:.3f}" if np.isfinite(r[f"{tm}_reference"]) else "-"
        rows.append([algo_label(r["algorithm"]), r["title"], r["n"],
                     fmt(m, r[f"{m}_mean"], r[f"{m}_ci_low"], r[f"{m}_ci_high"]),
                     f"{r[f'{m}_best_reference']} {r[f'{m}_reference']:.3f}",
                     turning, ref, _turning_word(r["turning_ok"]),
                     fmt("return", r.get("return_mean", np.nan), r.get("return_ci_low", np.nan),
                         r.get("return_ci_high", np.nan)),
                     fmt("goal", r.get("goal_mean", np.nan), r.get("goal_ci_low", np.nan),
                         r.get("goal_ci_high", np.nan)),
                     _verdict_word(r), r["why"]])
    return md_table(["algorithm", "environment", "seeds", "driving score [95% CI]", "best degenerate DS",
                     "RC turning slots [95% CI]", "safe non-turner RC turning", "turns learned",
                     "return [95% CI]", "goal rate [95% CI]", "verdict", "why"], rows)


def _turning_word(ok) -> str:
    """'yes' / 'no' for a verdict row's ``turning_ok``; '-' where it does not apply (NaN)."""
    if ok is True or str(ok) == "True":
        return "yes"
    if ok is False or str(ok) == "False":
        return "no"
    return "-"


def _verdict_word(r) -> str:
    """'pass', 'not shown' (its DS clears every reference, too few seeds) or 'FAIL' for a verdict row."""
    return "pass" if r["passed"] else ("not shown" if bool(r[f"{VERDICT_METRIC}_ok"]) else "FAIL")


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
        word = _verdict_word(r)
        cell = score_cell(r[f"{m}_mean"], r[f"{m}_ci_low"], r[f"{m}_ci_high"], r["n"], r.get("goal_mean", np.nan))
        cells[(r["algorithm"], r["env"])] = (f"{cell}, " + (f"**{word}**" if word == "pass" else word)
                                             + (", turns" if _turning_word(r["turning_ok"]) == "yes" else ""))
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


def iqm_markdown(t: pd.DataFrame) -> str:
    rows = []
    for _, r in t.iterrows():
        ci = f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}]" if np.isfinite(r["ci_low"]) else "-"
        label = algo_label(r["name"]) if r["kind"] == "algorithm" else f"*{r['name']}*"
        rows.append([label, f"{r['iqm']:.2f}", ci, r["envs"], r["runs"]])
    return md_table(["policy", "IQM (normalised driving score)", "95% CI", "environments", "scores"], rows)


__all__ = ["METRICS", "budget_check", "budget_markdown", "convergence_curve", "convergence_curves",
           "convergence_figure", "iqm_figure", "iqm_lines", "iqm_table", "normalise", "reference_table", "seed_means",
           "seed_table", "verdict",
           "verdict_figure", "verdict_grid_markdown", "verdict_lines", "over_seeds", "return_goal_grid_markdown"]
