"""Statistics over training seeds: what ``cosim benchmark --seeds N`` reports beyond the pooled
Table RQ1, and what the science study (``studies/science.py``) builds its pages from.

A benchmark trains every (algorithm, environment) with N seeds and tests each seed's policies
on held-out episode seeds. The pooled table resamples episodes; this module treats the
*training seed* as the unit, as a claim about an algorithm needs:

- :func:`seed_means`: one value per (scenario, environment, algorithm, seed): the mean over
  that seed's test episodes (NaN-aware: TTFC and CP only where they apply, the goal rate and
  route completion of the turning slots only over the slots whose route turns,
  :func:`with_turning`); :func:`records_seed_means` from a test's per-step records;
- :func:`seed_table`: mean and 95% percentile-bootstrap CI over seeds
  (:func:`eval.reporting.stats.bootstrap_ci`: 2,000 resamples, fixed seed); n = seeds;
- :func:`reference_table`: the reference rows (eval/testing/validity.py: autopilot, uniform
  random, degenerate suite) with a CI over their episodes x ACs (a summary row: its mean);
- :func:`verdict`: per (algorithm, environment) of Scenario 1, on the driving score
  (cosim/score.py; docs/task.md, "Driving score"): a pair passes when the lower end of its DS
  interval over training seeds clears every degenerate reference's mean DS, with at least
  :data:`MIN_SEEDS` seeds; its turns are learned where the lower end of the turning slots'
  route completion interval clears the safe non-turner's (``turning_ok``). The return and
  goal rate stay in its rows as information;
- :func:`iqm_table`: the interquartile mean across environments per algorithm
  (rliable-style: the driving score normalised per environment between uniform random (0)
  and the autopilot (1), IQM over every (environment, seed) score, stratified bootstrap CI
  resampling seeds within each environment);
- :func:`budget_check`: did each run's training return still rise over the last part of its
  budget (a longer run would likely score more)?
- :func:`seed_tables` and :func:`seeds_markdown`: all of the above for a benchmark's report
  (eval/scale/benchmark.py ``write_report``, "Over training seeds").

rliable itself (PyPI) installs here but does not import: its ``arch`` dependency (7.2) fails
with pandas 3 (``deprecate_kwarg() missing 1 required positional argument``), so
:func:`eval.reporting.stats.iqm` and :func:`eval.reporting.stats.stratified_bootstrap`
implement its ``aggregate_iqm`` (scipy's 25% ``trim_mean`` over all scores) and its
stratified percentile bootstrap in numpy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eval.labels import algo_label, algo_order, env_title
from eval.reporting.page import md_table
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


def with_metrics(frame: pd.DataFrame, metrics: Sequence[str]) -> pd.DataFrame:
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
    per = with_metrics(per, metrics)
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
    seeds = with_metrics(seeds, metrics)  # seed means kept from before the driving score: '-'
    for (scenario, env, algo), g in seeds.groupby(["scenario", "env", "algorithm"], sort=True):
        for m in metrics:
            rows.append(_row(scenario, env, "algorithm", algo, m, g[m].to_numpy(float)))
    return pd.DataFrame(rows)


def reference_table(refs: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """Long table of the reference rows (eval/testing/validity.py per-(episode, AC) rows with an
    ``env`` column): mean and CI over episodes x ACs, under Scenario 1 conditions. Summary rows
    (one per policy and environment, as a test session's ``references``) give their mean, n = 1,
    and no turning slots' metrics (they have no ``agent`` to tell the slots apart)."""
    rows = []
    if ({"goal_turning", "RC_turning"} & set(metrics) and not {"goal_turning", "RC_turning"} <= set(refs)
            and "agent" in refs):
        refs = with_turning(refs)
    refs = with_metrics(refs, metrics)  # reference rows from before the driving score: '-'
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



def normalise(seeds: pd.DataFrame, references: pd.DataFrame, metric: str = VERDICT_METRIC) -> pd.DataFrame:
    """Scenario 1 ``metric`` (the driving score) per (env, algorithm, seed) as (x - random) /
    (autopilot - random), with the references' means in that environment; column ``score``.
    An environment where the autopilot does not score above random cannot be normalised: its
    scores are NaN."""
    s1 = with_metrics(seeds[seeds["scenario"] == VERDICT_SCENARIO], [metric])
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



def verdict_markdown(v: pd.DataFrame) -> str:
    """One row per (algorithm, environment) of a :func:`verdict`: seeds, the driving score and
    its interval against the strongest degenerate reference, the turning slots' route completion
    against the safe non-turner's, the return and goal rate, the verdict and what failed."""
    m, tm = VERDICT_METRIC, TURNING_METRIC
    rows = []
    for _, r in v.iterrows():
        turning = (f"{fmt(tm, r[f'{tm}_mean'], r[f'{tm}_ci_low'], r[f'{tm}_ci_high'])}"
                   if np.isfinite(r[f"{tm}_mean"]) else "-")
        ref = f"{r[f'{tm}_reference']:.3f}" if np.isfinite(r[f"{tm}_reference"]) else "-"
        rows.append([algo_label(r["algorithm"]), r["title"], r["n"],
                     fmt(m, r[f"{m}_mean"], r[f"{m}_ci_low"], r[f"{m}_ci_high"]),
                     f"{r[f'{m}_best_reference']} {r[f'{m}_reference']:.3f}",
                     turning, ref, turning_word(r["turning_ok"]),
                     fmt("return", r.get("return_mean", np.nan), r.get("return_ci_low", np.nan),
                         r.get("return_ci_high", np.nan)),
                     fmt("goal", r.get("goal_mean", np.nan), r.get("goal_ci_low", np.nan),
                         r.get("goal_ci_high", np.nan)),
                     verdict_word(r), r["why"]])
    return md_table(["algorithm", "environment", "seeds", "driving score [95% CI]", "best degenerate DS",
                     "RC turning slots [95% CI]", "safe non-turner RC turning", "turns learned",
                     "return [95% CI]", "goal rate [95% CI]", "verdict", "why"], rows)


def turning_word(ok) -> str:
    """'yes' / 'no' for a verdict row's ``turning_ok``; '-' where it does not apply (NaN)."""
    if ok is True or str(ok) == "True":
        return "yes"
    if ok is False or str(ok) == "False":
        return "no"
    return "-"


def verdict_word(r) -> str:
    """'pass', 'not shown' (its DS clears every reference, too few seeds) or 'FAIL' for a verdict row."""
    return "pass" if r["passed"] else ("not shown" if bool(r[f"{VERDICT_METRIC}_ok"]) else "FAIL")


def iqm_markdown(t: pd.DataFrame) -> str:
    """An :func:`iqm_table`: each algorithm's IQM and 95% CI, then the references' IQM (no CI)."""
    rows = []
    for _, r in t.iterrows():
        ci = f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}]" if np.isfinite(r["ci_low"]) else "-"
        label = algo_label(r["name"]) if r["kind"] == "algorithm" else f"*{r['name']}*"
        rows.append([label, f"{r['iqm']:.2f}", ci, r["envs"], r["runs"]])
    return md_table(["policy", "IQM (normalised driving score)", "95% CI", "environments", "scores"], rows)


# -- a benchmark's seeds -------------------------------------------------------------------------
def records_seed_means(records: pd.DataFrame, metrics: Sequence[str] = METRICS) -> pd.DataFrame:
    """:func:`seed_means` of a test's per-step records that carry a ``train_seed`` column (each
    seed's episodes apart, eval/reporting/report.py ``per_episode``)."""
    from eval.reporting.report import per_episode

    per = pd.concat([per_episode(g).assign(train_seed=seed)
                     for seed, g in records.groupby("train_seed", sort=True)], ignore_index=True)
    return seed_means(per, metrics)


def seed_tables(records: pd.DataFrame, references: pd.DataFrame | None = None,
                runs: Mapping[tuple[str, str, int], Path] | None = None) -> dict[str, pd.DataFrame]:
    """Everything :func:`seeds_markdown` shows, by the name of its CSV file: ``seeds`` (the
    :func:`records_seed_means`), ``over_seeds`` (:func:`seed_table`), and where the references
    (per-(episode, AC) or summary rows with ``env`` and ``policy``) hold a degenerate policy's
    driving score ``verdict`` and ``iqm``; with ``runs`` ((algorithm, env, seed) -> run folder)
    ``budget`` (:func:`budget_check`)."""
    seeds = records_seed_means(records)
    tables = {"seeds": seeds, "over_seeds": seed_table(seeds)}
    if references is not None and len(references):
        ref_table = reference_table(references)
        degenerate = ref_table[ref_table["name"].isin(DEGENERATE) & (ref_table["metric"] == VERDICT_METRIC)]
        if np.isfinite(degenerate["mean"].astype(float)).any():
            tables["verdict"] = verdict(tables["over_seeds"], ref_table)
            tables["iqm"] = iqm_table(seeds, ref_table)
    if runs:
        tables["budget"] = budget_check(runs)
    return tables


def seeds_markdown(tables: Mapping[str, pd.DataFrame]) -> str:
    """The report's "Over training seeds" section from :func:`seed_tables`: the verdict, the IQM
    and the budget check, each with a line saying how it is computed."""
    seeds = tables["seeds"]
    k = int(seeds.groupby(["scenario", "env", "algorithm"])["train_seed"].nunique().max())
    files = "".join(f", `{name}.csv`" for name in ("verdict", "iqm", "budget") if name in tables)
    out = ["## Over training seeds\n",
           f"Each training seed's mean over its test episodes, then the mean over {k} seeds with a "
           f"95% percentile bootstrap interval over seeds ({BOOTSTRAP:,} resamples): the tables above "
           "pool the seeds' episodes, these treat the seed as the unit. Files: `seeds.csv` (per seed), "
           f"`over_seeds.csv`{files}.\n"]
    if "verdict" in tables:
        out += [f"**Verdict** (Scenario 1, driving score): a pair passes when the lower end of its "
                f"interval clears the mean driving score of every degenerate reference, over at least "
                f"{MIN_SEEDS} seeds ('not shown': it clears them with fewer).\n",
                verdict_markdown(tables["verdict"])]
    else:
        out.append("No verdict or IQM: no degenerate reference policy ran.\n")
    if "iqm" in tables and len(tables["iqm"]):
        out += [f"**IQM** of the driving score normalised per environment ({NORM_LOW} 0, {NORM_HIGH} 1) "
                "over every (environment, seed), 95% stratified bootstrap over seeds within each "
                "environment:\n", iqm_markdown(tables["iqm"])]
    if "budget" in tables and len(tables["budget"]):
        out += [f"**Did the budgets suffice?** Training return of the last {PLATEAU_FRACTION:.0%} of "
                f"each run's budget minus the {PLATEAU_FRACTION:.0%} before (mean over seeds); rising k/n: "
                "in k of n seeds the gain's 95% interval is above 0 (bold where any): a longer run would "
                "likely score more.\n", budget_markdown(tables["budget"])]
    return "\n".join(out)


__all__ = ["DIGITS", "METRICS", "MIN_SEEDS", "NAMES", "PLATEAU_FRACTION", "budget_check", "budget_markdown",
           "degenerate_means", "fmt", "iqm_markdown", "iqm_table", "late_gain", "normalise",
           "records_seed_means", "reference_table", "seed_means", "seed_table", "seed_tables",
           "seeds_markdown", "slot_routes", "turning_word", "verdict", "verdict_markdown", "verdict_word",
           "with_metrics", "with_turning"]
