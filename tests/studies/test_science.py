"""The science study (studies/science.py): its pages (studies/science_pages.py: grids, targets,
figures, convergence) against hand-computed values, and its smoke version (studies/science.py
--smoke) end to end, rerun and refused. The statistics it builds on are the product's
(eval/reporting/multiseed.py, tests/eval/test_multiseed.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from eval.reporting import multiseed
from eval.testing.validity import DEGENERATE, POLICIES

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "studies" / "science.py"


@pytest.fixture(scope="module")
def pages(load_study):
    """studies/science_pages.py."""
    return load_study("science_pages")


# -- the pages ---------------------------------------------------------------------------------
def test_targets_need_a_discrete_and_a_continuous_pass_and_turns_learned_where_routes_turn(pages):
    def row(env, algo, passed, rc, ok):
        return {"env": env, "algorithm": algo, "passed": passed, "RC_turning_mean": rc, "turning_ok": ok,
                "turning_goal_mean": np.nan if np.isnan(rc) else 0.0}

    v = pd.DataFrame([
        # Four-way: ppo and td3 pass, dqn's turning slots' RC clears the safe non-turner's: met
        row("env_3", "ppo", True, 0.3, False), row("env_3", "td3", True, 0.3, False),
        row("env_3", "dqn", False, 0.8, True),
        # Roundabout: both kinds pass, but no algorithm's turns are learned: not met
        row("env_4", "a3c", True, 0.4, False), row("env_4", "ddpg", True, 0.4, False),
        # Straight: no turning slot, so passing algorithms of both kinds are enough
        row("env_1", "impala", True, np.nan, np.nan), row("env_1", "ddpg", True, np.nan, np.nan),
        # Merge: no continuous algorithm passes
        row("env_5", "ppo", True, 0.9, True), row("env_5", "td3", False, 0.9, True)])
    t = pages.targets(v).set_index("env")
    assert t.loc["env_3", "met"] and t.loc["env_3", "turning"] == ["dqn"]
    assert t.loc["env_3", "discrete"] == ["ppo"] and t.loc["env_3", "continuous"] == ["td3"]
    assert not t.loc["env_4", "met"] and t.loc["env_4", "turning"] == []
    assert t.loc["env_1", "met"] and not t.loc["env_1", "has_turns"]
    assert not t.loc["env_5", "met"] and t.loc["env_5", "continuous"] == []
    md = pages.targets_markdown(pages.targets(v))
    assert "(no turning slot)" in md and md.count("not met") == 2
    assert "| Four-way | PPO | TD3 | DQN | met |" in md  # the names as the other tables write them
    # read back from verdict.csv (True/False/NaN as text and floats): the same targets
    again = pages.targets(v.astype({"turning_ok": str}).replace({"turning_ok": {"nan": np.nan}}))
    assert again.set_index("env").loc["env_3", "turning"] == ["dqn"]


def test_the_grids_write_the_verdict_as_the_readme_does(pages, seed_frame, reference_frame):
    """The verdict test's case (tests/eval/test_multiseed.py) as the README's grids: each cell
    'DS [95% CI] (goal rate), verdict', the references and the strongest degenerate below."""
    refs = reference_frame(values={"autopilot": (1000, 1.0, 0.95, 0.9), "always-forward": (300, 0.1, 0.08),
                                   "always-brake": (-500, 0.0, 0.0), "safe-non-turner": (700, 0.5, 0.6, 0.3)})
    table = pd.concat([
        multiseed.seed_table(seed_frame({"DS": [0.2, 0.4, 0.6], "RC_turning": [0.4, 0.5, 0.6]}, "ppo")),
        multiseed.seed_table(seed_frame({"DS": [0.05, 0.5, 0.9], "RC_turning": [0.1, 0.5, 0.9]}, "dqn")),
        multiseed.seed_table(seed_frame({"DS": [0.08, 0.3, 0.4]}, "td3")),
    ])
    v = multiseed.verdict(table, refs).set_index("algorithm")
    one = multiseed.verdict(multiseed.seed_table(seed_frame({"DS": [0.5], "goal": [0.5]}, "a3c")),
                            refs).set_index("algorithm")
    grid = pages.grid_markdown(table, "DS", 1, refs)
    assert "| *autopilot* | 0.950 [0.950, 0.950] |" in grid
    assert [line.split(" | ")[0] for line in grid.splitlines()[2:5]] == ["| PPO", "| DQN", "| TD3"]
    assert "| *best degenerate* | 0.080 (always-forward) |" in grid
    both = pd.concat([v.reset_index(), one.reset_index()], ignore_index=True)
    cells = {line.split(" | ")[0].strip("| "): line.split(" | ")[1].rstrip(" |")
             for line in pages.verdict_grid_markdown(both, refs).splitlines()[2:]}
    assert cells["PPO"] == "0.400 [0.200, 0.600] (0.50), **pass**, turns"
    assert cells["DQN"].endswith("(0.50), FAIL") and cells["TD3"].endswith(", FAIL, turns")  # its RC_turning 0.5 > 0.3
    assert cells["A3C"] == "0.500 (0.50; 1 seed), not shown, turns"
    assert cells["*autopilot*"] == "0.950 (1.00)" and cells["*safe non-turner*"] == "0.600 (0.50)"
    no_turn = pages.verdict_grid_markdown(both.assign(RC_turning_mean=np.nan, turning_goal_mean=np.nan), refs)
    assert "*safe non-turner*" not in no_turn and "*autopilot*" in no_turn  # no route turns: it is the autopilot
    assert cells["*best degenerate*"] == "0.080 (always-forward)"


def test_iqm_figure_draws_each_algorithm_its_interval_and_the_reference_lines(pages, tmp_path, monkeypatch):
    """The IQM table drawn: a point and interval per algorithm in the paper's order (top down) at its
    values, lines at the autopilot, the strongest degenerate reference (named) and the safe non-turner."""
    import matplotlib

    matplotlib.use("Agg")
    t = pd.DataFrame([
        {"kind": "algorithm", "name": "dqn", "iqm": 0.7, "ci_low": 0.6, "ci_high": 0.8, "envs": 5, "runs": 15},
        {"kind": "algorithm", "name": "ppo", "iqm": 0.5, "ci_low": 0.45, "ci_high": 0.55, "envs": 5, "runs": 15},
        *({"kind": "reference", "name": n, "iqm": v, "ci_low": np.nan, "ci_high": np.nan, "envs": 5, "runs": 5}
          for n, v in (("autopilot", 1.0), ("safe-non-turner", 0.9), ("random", 0.0), ("always-brake", 0.78),
                       ("always-coast", 0.3)))])
    assert pages.iqm_lines(t) == [("autopilot", 1.0, "-"), ("best degenerate (always-brake)", 0.78, "--"),
                                    ("safe non-turner", 0.9, ":")]
    from eval.reporting import figures

    kept = []
    monkeypatch.setattr(figures, "_save", lambda fig, out, stem: kept.append(fig) or [out / f"{stem}.png"])
    assert pages.iqm_figure(t, tmp_path) == [tmp_path / "iqm.png"]
    (ax,) = kept[0].axes
    assert [x.get_text() for x in ax.get_yticklabels()] == ["PPO", "DQN"]  # the paper's order, top down
    points = sorted((float(line.get_ydata()[0]), float(line.get_xdata()[0])) for line in ax.lines
                    if line.get_marker() == "o")
    assert points == [(0.0, 0.5), (1.0, 0.7)]
    bars = sorted(tuple(seg[:, 0]) for c in ax.collections for seg in c.get_segments())
    assert bars == [pytest.approx((0.45, 0.55)), pytest.approx((0.6, 0.8))]
    assert sorted(float(line.get_xdata()[0]) for line in ax.lines if line.get_marker() != "o") == [0.78, 0.9, 1.0]
    assert "5 environments" in ax.get_xlabel()


def test_verdict_figure_draws_each_seed_the_interval_and_the_references_a_pair_must_clear(pages, seed_frame, reference_frame, tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    refs = pd.concat([reference_frame("env_1", {"autopilot": (1000, 1.0, 0.97), "always-forward": (300, 0.1, 0.1),
                                      "safe-non-turner": (700, 0.5, 0.97)}),
                      reference_frame("env_2", {"autopilot": (900, 0.9, 0.95, 0.9), "always-brake": (-500, 0.0, 0.0),
                                      "always-forward": (-900, 0.05, 0.04), "safe-non-turner": (100, 0.2, 0.5, 0.3)})])
    seeds = pd.concat([seed_frame({"DS": [0.2, 0.4, 0.6], "RC_turning": [np.nan] * 3, "goal_turning": [np.nan] * 3},
                              "ppo"),  # no route turns in env_1
                       seed_frame({"DS": [0.0, 0.02, 0.3], "RC_turning": [0.1, 0.5, 0.6]}, "dqn", env="env_2")])
    v = multiseed.verdict(multiseed.seed_table(seeds), refs)
    assert pages.verdict_lines(v, refs, "env_1", "DS") == [
        ("autopilot", 0.97, "-"), ("best degenerate (always-forward)", 0.1, "--")]  # no turns: no safe non-turner
    assert pages.verdict_lines(v, refs, "env_2", "RC_turning") == [
        ("autopilot", 0.9, "-"), ("safe non-turner", 0.3, ":")]

    from eval.reporting import figures

    kept = []
    monkeypatch.setattr(figures, "_save", lambda fig, out, stem: kept.append(fig) or [out / f"{stem}.png"])
    assert pages.verdict_figure(v, seeds, refs, tmp_path) == [tmp_path / "verdict.png"]
    (fig,) = kept
    ds1, ds2, turn1, turn2 = (fig.axes[i] for i in (0, 1, 2, 3))  # rows: DS, RC turning; columns: env_1, env_2
    assert ds1.get_title(loc="left") == "Straight" and ds1.get_yscale() == "linear"
    # the seed means as dots, each at its value
    assert sorted(ds2.collections[0].get_offsets()[:, 1]) == pytest.approx([0.0, 0.02, 0.3])
    assert sorted(turn2.collections[0].get_offsets()[:, 1]) == pytest.approx([0.1, 0.5, 0.6])
    # the reference lines across, at their values: the best degenerate here is always-forward's 0.04
    assert sorted(line.get_ydata()[0] for line in ds2.lines if len(line.get_ydata()) == 2
                  and line.get_ydata()[0] == line.get_ydata()[1]) == pytest.approx([0.04, 0.5, 0.95])
    # "pass" above PPO in env_1 (its CI clears always-forward), nothing above DQN in env_2
    assert [t.get_text() for t in ds1.texts] == ["pass"] and len(ds2.texts) == 0
    assert [t.get_text() for t in turn1.texts] == ["no turning slot"] and len(turn2.texts) == 0


def test_scenario_2_grid_gives_each_algorithm_alone_its_return_interval_and_goal_rate(pages, seed_frame):
    two = pd.concat([seed_frame({"return": [100.0, 200.0, 300.0], "goal": [1.0, 0.5, 0.0]}, "dqn").assign(scenario=2),
                     seed_frame({"return": [-50.0], "goal": [0.0]}, "ppo", env="env_2").assign(scenario=2),
                     seed_frame({"return": [9e9, 9e9, 9e9], "goal": [1.0, 1.0, 1.0]}, "td3")])  # Scenario 1: not shown
    table = multiseed.seed_table(two)
    dqn = table.query("scenario == 2 and name == 'dqn' and metric == 'return'").iloc[0]
    grid = pages.return_goal_grid_markdown(table, 2)
    assert grid.splitlines()[0] == "| algorithm | Straight | Three-way |"
    assert (f"| DQN | {dqn['mean']:,.1f} [{dqn['ci_low']:,.1f}, {dqn['ci_high']:,.1f}] (0.50) |  |" in grid
            and dqn["ci_low"] < 200.0 < dqn["ci_high"])
    assert "| PPO |  | -50.0 (0.00; 1 seed) |" in grid and "TD3" not in grid and "9" * 6 not in grid


def test_convergence_curve_is_the_mean_of_the_latest_episodes(pages):
    episodes = pd.DataFrame({"env_step": [10, 20, 30], "return": [1.0, 2.0, 6.0]})
    c = pages.convergence_curve(episodes, budget=30, points=4, window=2)
    np.testing.assert_allclose(c["env_step"], [0, 10, 20, 30])
    np.testing.assert_allclose(c["return"], [np.nan, 1.0, 1.5, 4.0])
    curves = pd.concat([c.assign(algorithm="ppo", env="env_1", seed=0),
                        c.assign(algorithm="ppo", env="env_1", seed=1,
                                 **{"return": c["return"] + [np.nan, np.nan, 1, 1]})])
    b = pages.convergence_bands(curves)
    # the mean only where both seeds have a value; the band spans them
    np.testing.assert_allclose(b["mean"], [np.nan, np.nan, 2.0, 4.5])
    np.testing.assert_allclose(b["high"] - b["low"], [np.nan, np.nan, 1.0, 1.0])


# -- the smoke study ---------------------------------------------------------------------------
def _run(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=400, cwd=ROOT)


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """One smoke study for the tests below (training it is most of their time)."""
    out = tmp_path_factory.mktemp("science") / "study"
    return out, _run(out)


def test_smoke_study_writes_every_result_and_resumes(smoke):
    out, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    plan = json.loads((out / "science.json").read_text())
    seeds, algos, envs = plan["benchmark"]["seeds"], plan["benchmark"]["algos"], plan["benchmark"]["envs"]
    assert seeds == 2 and plan["test"]["episode_seeds"][0] == 10_000

    results = pd.read_csv(out / "results.csv")
    ours = results[results["kind"] == "algorithm"]
    assert set(zip(ours["name"], ours["env"], strict=True)) == {(a, e) for a in algos for e in envs}
    assert ours.groupby(["name", "env"])["metric"].apply(set).map(
        lambda s: s == set(multiseed.METRICS)).all()
    always = ours[ours["metric"].isin(["return", "goal", "DISTANCE", "OS", "CO", "SPEED"])]
    assert (always["n"] == seeds).all() and np.isfinite(always["mean"]).all()
    applied = ours[ours["n"] > 0]
    assert (applied["n"] <= seeds).all()
    assert ((applied["ci_low"] <= applied["mean"] + 1e-9)
            & (applied["mean"] <= applied["ci_high"] + 1e-9)).all()
    refs = results[results["kind"] == "reference"]
    assert set(refs["name"]) == set(POLICIES)

    verdict = pd.read_csv(out / "verdict.csv")
    assert set(zip(verdict["algorithm"], verdict["env"], strict=True)) == {(a, e) for a in algos for e in envs}
    ref = refs[refs["name"].isin(DEGENERATE)].groupby(["env", "metric"])["mean"].max()
    def clears(low, value):
        return low > value and not np.isclose(low, value)

    for _, r in verdict.iterrows():  # pass iff the DS CI's lower end clears the best degenerate row
        expected = clears(r["DS_ci_low"], ref[(r["env"], "DS")]) and r["n"] >= multiseed.MIN_SEEDS
        assert bool(r["passed"]) == expected
        assert r["n"] == seeds

    iqm = pd.read_csv(out / "iqm.csv").set_index("name")
    for a in algos:
        assert iqm.loc[a, "ci_low"] <= iqm.loc[a, "iqm"] <= iqm.loc[a, "ci_high"]
        assert iqm.loc[a, "runs"] == seeds * len(envs)
    curves = pd.read_csv(out / "convergence.csv")
    assert curves.groupby(["algorithm", "env"])["seed"].nunique().eq(seeds).all()
    for name in ("convergence.pdf", "convergence.png", "verdict.png", "report/index.md", "results.md"):
        assert (out / name).stat().st_size > 0, name
    summary = (out / "summary.md").read_text()
    assert "| algorithm | environment | seeds |" in summary and summary.strip() in done.stdout
    assert "Alone (Scenario 2" not in summary  # the smoke study tests Scenario 1 only

    # rerun: nothing is trained or tested again
    cached = {p: p.stat().st_mtime_ns for p in (out / "test").glob("*.parquet")}
    assert len(cached) == len(envs) * seeds
    again = _run(out)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "all 4 runs finished" in again.stderr and "tested" not in again.stderr
    assert {p: p.stat().st_mtime_ns for p in cached} == cached
    assert pd.read_csv(out / "verdict.csv").equals(verdict)

    # other options on the same folder (fewer seeds, other episodes): refused in one line,
    # before any work
    for extra in (("--seeds", "1"), ("--episodes", "3")):
        other = _run(out, *extra)
        assert other.returncode == 2
        assert other.stderr.strip().startswith("science: error: ") and len(other.stderr.strip().splitlines()) == 1
        assert "repeat those options (only --seeds may grow)" in other.stderr


def _as_env(study: Path, dest: Path, env: str, seeds: int, first_seed: int = 0) -> None:
    """A copy of the smoke study (env_1) relabelled as ``env`` with ``seeds`` of its training
    seeds from ``first_seed``: what a separate study of that environment (and those seeds,
    ``--first-seed``) would have left."""
    plan = json.loads((study / "science.json").read_text())
    plan["benchmark"].update(envs=[env], seeds=seeds)
    if first_seed:
        plan["benchmark"]["first_seed"] = first_seed
    (dest / "test").mkdir(parents=True)
    (dest / "references").mkdir()
    (dest / "science.json").write_text(json.dumps(plan))
    refs = pd.read_csv(study / "references" / "env_1.csv")
    refs.assign(env=env).to_csv(dest / "references" / f"{env}.csv", index=False)
    means = pd.read_csv(study / "seeds.csv")
    means[means["train_seed"].between(first_seed, first_seed + seeds - 1)].assign(env=env).to_csv(
        dest / "seeds.csv", index=False)
    for k in range(first_seed, first_seed + seeds):
        rec = pd.read_parquet(study / "test" / f"env_1__seed{k}.parquet")
        rec.assign(env=env).to_parquet(dest / "test" / f"{env}__seed{k}.parquet", index=False)
        for algo in plan["benchmark"]["algos"]:
            link = dest / "bench" / "runs" / f"{env}__{algo}__{k}__bench"
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(study / "bench" / "runs" / f"env_1__{algo}__{k}__bench")


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_combine_gathers_studies_of_different_environments(smoke, tmp_path):
    """--combine: one table over studies run apart, each environment with its own seeds."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    _as_env(study, tmp_path / "s2", "env_2", seeds=1)
    both = tmp_path / "both"
    cmd = [sys.executable, str(SCRIPT), "--out", str(both), "--combine", str(study), str(tmp_path / "s2")]
    comb = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert comb.returncode == 0, comb.stderr[-2000:]
    assert "tested" not in comb.stderr and "references env" not in comb.stderr  # nothing rerun
    one = pd.read_csv(study / "results.csv")
    res = pd.read_csv(both / "results.csv")
    key = ["kind", "name", "metric", "scenario"]
    # env_1 is the first study's, to the digit; env_2 holds seed 0 of the same records only
    a = one.sort_values(key).reset_index(drop=True)
    b = res[res["env"] == "env_1"].sort_values(key).reset_index(drop=True)
    pd.testing.assert_frame_equal(a[key + ["mean", "ci_low", "ci_high", "n"]],
                                  b[key + ["mean", "ci_low", "ci_high", "n"]])
    seed0 = pd.read_csv(study / "seeds.csv").query("train_seed == 0")
    e2 = res[(res["env"] == "env_2") & (res["kind"] == "algorithm")].set_index(
        ["scenario", "name", "metric"])
    assert (e2.loc[e2.index.get_level_values("metric") == "return", "n"] == 1).all()
    for _, r in seed0.iterrows():
        assert e2.loc[(r["scenario"], r["algorithm"], "return"), "mean"] == pytest.approx(r["return"])
    verdict = pd.read_csv(both / "verdict.csv")
    assert set(verdict["env"]) == {"env_1", "env_2"}
    one_seed = verdict[verdict["env"] == "env_2"]
    assert (~one_seed["passed"]).all() and one_seed["why"].str.contains("1 seed").all()
    iqm = pd.read_csv(both / "iqm.csv").set_index("name")
    assert (iqm.loc[["ppo", "dqn"], "runs"] == 3).all()  # 2 env_1 seeds + 1 env_2 seed
    curves = pd.read_csv(both / "convergence.csv")
    assert curves.groupby("env")["seed"].nunique().to_dict() == {"env_1": 2, "env_2": 1}
    summary = (both / "summary.md").read_text()
    assert "seeds per environment: Straight 2, " in summary
    assert json.loads((both / "science.json").read_text())["benchmark"]["seeds"] == {
        "env_1": [0, 1], "env_2": [0]}

    # an environment twice, a study's own folder as the output, a study trained under another
    # collision rule, or study options: refused
    _as_env(study, tmp_path / "s3", "env_3", seeds=1)
    plan3 = json.loads((tmp_path / "s3" / "science.json").read_text())
    plan3["benchmark"]["collisions"] = "end"  # the smoke study trained under the default, continue
    (tmp_path / "s3" / "science.json").write_text(json.dumps(plan3))
    for extra, words in (([str(study), str(study)], "env_1 seed 0 is in two"),
                         ([str(study), str(tmp_path / "s3")], "in collisions;"),
                         ([str(tmp_path / "s2"), "--out", str(study)], "holds a study of its own"),
                         ([str(study), "--seeds", "2"], "drop --seeds")):
        bad = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "x"),
                              "--combine", *extra], capture_output=True, text=True, cwd=ROOT)
        assert bad.returncode == 2 and words in bad.stderr, bad.stderr


def _link_runs(study, runs) -> None:
    """``runs/<run>`` links to each of the smoke study's run folders (what ``--runs`` takes)."""
    runs.mkdir(parents=True)
    for name in (p.name for p in (study / "bench" / "runs").iterdir()):
        (runs / name).symlink_to((study / "bench" / "runs" / name).resolve())


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_a_study_tested_alone_too_has_the_alone_table(smoke, tmp_path):
    """A part of a grid tested in Scenarios 1 and 2 (the smoke study's seed-0 runs, linked with
    --runs), exported and, as a clone has it, without its held-out records, combined on its own:
    its summary.md has the Scenario 2 table, each algorithm's cell its one seed's mean and goal rate."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    _link_runs(study, tmp_path / "runs" / "runs")
    part = tmp_path / "part"
    tested = _run(part, "--seeds", "1", "--scenarios", "1", "2", "--runs", str(tmp_path / "runs"))
    assert tested.returncode == 0, tested.stderr[-2000:]
    export = tmp_path / "page" / "study"
    exported = subprocess.run([sys.executable, str(SCRIPT), "--out", str(part), "--export", str(export)],
                              capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert exported.returncode == 0, exported.stderr[-2000:]
    for records in (export / "test").glob("*.parquet"):  # generated data, not in git
        records.unlink()
    assert (pd.read_csv(export / "seeds.csv")["scenario"] == 2).any()
    done = subprocess.run([sys.executable, str(SCRIPT), "--combine", str(export), "--out", str(tmp_path / "c")],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "holds no held-out records" in done.stderr  # the seed means came from seeds.csv
    summary = (tmp_path / "c" / "summary.md").read_text()
    alone = summary.split("Alone (Scenario 2, each algorithm's `ac_0` with no other AC)")[1].split("\n\n")[1]
    means = pd.read_csv(export / "seeds.csv").query("scenario == 2").set_index("algorithm")
    for algo, r in means.iterrows():
        assert f"| {algo.upper()} | {r['return']:,.1f} ({r['goal']:.2f}; 1 seed) |" in alone


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_combined_page_finds_every_section_of_a_five_environment_summary(smoke, load_study, tmp_path):
    """studies/combined_page.py reads the sections it shows from the summary.md that
    studies/science.py --combine writes: here the smoke study (Straight) combined with copies of
    it as the other four environments, every environment of a grid. The smoke study tests
    Scenario 1 only, so there is no alone table."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    parts = [study]
    for env in ("env_2", "env_3", "env_4", "env_5"):
        _as_env(study, tmp_path / env, env, seeds=1)
        parts.append(tmp_path / env)
    comb = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "all"), "--combine",
                           *map(str, parts)], capture_output=True, text=True, timeout=400, cwd=ROOT)
    assert comb.returncode == 0, comb.stderr[-2000:]
    s = load_study("combined_page").sections((tmp_path / "all" / "summary.md").read_text())
    assert s["grid"].startswith("| algorithm | Straight | Three-way | Four-way | Roundabout | Merge |")
    assert "*best degenerate*" in s["grid"] and "| DQN |" in s["iqm"] and "| Merge |" in s["target"]
    assert s["budget"].startswith("|") and "alone" not in s


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_an_exported_study_combines_without_its_checkpoints(smoke, tmp_path):
    """--export copies a finished study without checkpoints (run folders are not kept in git);
    --combine takes the copy as the study: the same table, curves and checkpoint provenance."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    exp = tmp_path / "page" / "study"
    run = subprocess.run([sys.executable, str(SCRIPT), "--out", str(study), "--export", str(exp)],
                         capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-2000:]
    copied = [p for p in exp.rglob("*") if p.is_file()]
    assert not [p for p in copied if p.suffix == ".pt"] and not [p for p in exp.rglob("*") if p.is_symlink()]
    exported_run = exp / "bench" / "runs" / "env_1__dqn__1__bench"
    assert {p.name for p in exported_run.iterdir()} == {"config.yaml", "episodes.csv", "manifest.json", "state.json"}
    manifest = json.loads((exported_run / "manifest.json").read_text())  # which commit and task trained it
    assert manifest["task_version"] >= 3 and len(manifest["git"]["commit"]) == 40
    original = json.loads((study / "report" / "provenance.json").read_text())["checkpoints"]
    recorded = json.loads((exp / "checkpoints.json").read_text())
    assert [(c["env"], c["seed"], c["algorithm"], c["sha256"]) for c in recorded] == [
        (c["env"], c["seed"], c["algorithm"], c["sha256"]) for c in original]
    # contact.csv: per (algorithm, scenario, seed) the mean return the study's seeds.csv has
    lines = pd.read_csv(exp / "contact.csv").set_index(["policy", "scenario", "train seed"])
    means = pd.read_csv(study / "seeds.csv").set_index(["algorithm", "scenario", "train_seed"])
    assert len(lines) == len(means) and set(lines.index) == set(means.index)
    for key, row in means.iterrows():
        assert lines.loc[key, "mean_return"] == pytest.approx(row["return"], abs=0.06)
        assert lines.loc[key, "without_contact_charge"] >= lines.loc[key, "mean_return"] - 0.06

    both = tmp_path / "both"
    comb = subprocess.run([sys.executable, str(SCRIPT), "--out", str(both), "--combine", str(exp)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert comb.returncode == 0, comb.stderr[-2000:]
    key = ["kind", "name", "env", "metric", "scenario"]
    for name in ("results.csv", "convergence.csv", "budget.csv"):
        a, b = (pd.read_csv(d / name) for d in (study, both))
        cols = [c for c in key if c in a.columns] or list(a.columns)
        pd.testing.assert_frame_equal(a.sort_values(cols).reset_index(drop=True),
                                      b.sort_values(cols).reset_index(drop=True))
    again = json.loads((both / "report" / "provenance.json").read_text())["checkpoints"]
    assert [c["sha256"] for c in again] == [c["sha256"] for c in original]

    # as a clone of the repository has it: the held-out records (generated data, out of git)
    # gone, the seed means (seeds.csv) kept: the same tables and curves, no pooled report
    for rec in (exp / "test").glob("*.parquet"):
        rec.unlink()
    bare = tmp_path / "bare"
    comb = subprocess.run([sys.executable, str(SCRIPT), "--out", str(bare), "--combine", str(exp)],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert comb.returncode == 0, comb.stderr[-2000:]
    assert "env_1 seed 1: " in comb.stderr and "holds no held-out records" in comb.stderr
    assert "tested" not in comb.stderr
    for name in ("results.csv", "verdict.csv", "iqm.csv", "convergence.csv"):
        a, b = (pd.read_csv(d / name) for d in (study, bare))
        cols = [c for c in key + ["algorithm", "name"] if c in a.columns]
        pd.testing.assert_frame_equal(a.sort_values(cols).reset_index(drop=True),
                                      b.sort_values(cols).reset_index(drop=True))
    assert not (bare / "report").exists() and "no report" in comb.stdout
    assert json.loads((bare / "science.json").read_text())["checkpoints"]  # finished

    refused = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "none"),
                              "--export", str(tmp_path / "x")], capture_output=True, text=True, cwd=ROOT)
    assert refused.returncode == 2 and "no finished study" in refused.stderr, refused.stderr


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_seed_parts_of_one_environment_combine_into_the_whole_study(smoke, tmp_path):
    """A grid run in parts: seed 0 in one study, seed 1 in another (``--first-seed 1``), one
    of them only as an export's seed means: --combine gives the 2-seed study's tables; a seed
    in two parts is refused."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    _as_env(study, tmp_path / "s0", "env_1", seeds=1)
    _as_env(study, tmp_path / "s1", "env_1", seeds=1, first_seed=1)
    (tmp_path / "s1" / "test" / "env_1__seed1.parquet").unlink()  # left on another machine
    both = tmp_path / "both"
    cmd = [sys.executable, str(SCRIPT), "--out", str(both), "--combine", str(tmp_path / "s1"),
           str(tmp_path / "s0")]
    comb = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert comb.returncode == 0, comb.stderr[-2000:]
    assert "env_1 (seeds 0 1)" in comb.stderr
    key = ["kind", "name", "env", "metric", "scenario", "mean", "ci_low", "ci_high", "n"]
    a, b = (pd.read_csv(d / "results.csv")[key].sort_values(key[:5]).reset_index(drop=True)
            for d in (study, both))
    pd.testing.assert_frame_equal(a, b)
    assert pd.read_csv(both / "convergence.csv")["seed"].unique().tolist() == [0, 1]
    provenance = (both / "report" / "index.md").read_text()
    assert "Not in this report" in provenance and "Straight seed 1" in provenance
    _as_env(study, tmp_path / "s01", "env_1", seeds=2)
    bad = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "x"), "--combine",
                          str(tmp_path / "s01"), str(tmp_path / "s1")], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "env_1 seed 1 is in two of the studies" in bad.stderr, bad.stderr


def _seed_only(contact: Path, tmp_path: Path, seed: int) -> Path:
    """A copy of a contact.csv with one training seed's lines."""
    out = tmp_path / f"contact_seed{seed}.csv"
    pd.read_csv(contact).query("`train seed` == @seed").to_csv(out, index=False)
    return out


def test_part_page_tables_one_seed_beside_the_other_seeds_and_the_combination(smoke, load_study, tmp_path):
    """studies/part_page.py: seed 1's row of each algorithm holds its own seed means, seed 0's
    column the other seed's, the last column the study's mean [CI] over seeds; the contact
    bullet counts seed 1's Scenario 1 records; the verdict bullet comes with the combined folder,
    the without-contact-charge bullet with the seeds' contact lines (seed 1's alone last), and
    contact lines without this seed are refused; a seed the study lacks is refused by name."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    page, stops = load_study("part_page"), load_study("stops")
    text = page.tables(study, [study], study, seed=1)
    rows = {cells[0]: cells for cells in ([c.strip() for c in line.strip("|").split(" | ")]
                                          for line in text.splitlines() if line.startswith("| "))}
    head = rows["algorithm"]
    means = pd.read_csv(study / "seeds.csv").query("scenario == 1").set_index(["algorithm", "train_seed"])
    results = pd.read_csv(study / "results.csv").query("scenario == 1 and metric == 'return'").set_index("name")
    for algo in json.loads((study / "science.json").read_text())["benchmark"]["algos"]:
        row = dict(zip(head, rows[algo.upper()], strict=True))
        assert row["Scenario 1 return, seed 1"] == f"{means.loc[(algo, 1), 'return']:,.1f}"
        assert row["Scenario 1, seed 0 (goal rate)"] == (f"{means.loc[(algo, 0), 'return']:,.1f} "
                                                         f"({means.loc[(algo, 0), 'goal']:.2f})")
        assert row["seeds together: mean [95% CI over seeds]"].startswith(f"{results.loc[algo, 'mean']:,.1f} [")
    assert "*always-brake*" in rows and "*safe non-turner*" not in rows  # Straight: no route turns
    episodes = stops.episode_rows(study / "test" / "env_1__seed1.parquet").query("scenario == 1")
    assert (f"{int(episodes['contact steps'].sum()):,} contact steps in Scenario 1's "
            f"{len(episodes)} AC-episodes") in text
    assert "- **2 seeds so far, too few for a verdict (3 needed): " in text  # the study: its own --combined folder
    contact = tmp_path / "contact.csv"
    load_study("science").contact(sorted((study / "test").glob("env_1__seed*.parquet")), contact)
    with_charge = page.tables(study, [study], study, seed=1, contact=[contact])
    lines = pd.read_csv(contact).query("scenario == 1 and `train seed` == 1")
    alone = ", ".join(f"{a.upper()} {x:,.1f}" for a, x in lines.set_index("policy").without_contact_charge
                      .sort_values(ascending=False).items())
    assert "on the 2 seeds' exports): " in with_charge and f"Seed 1 alone: {alone}." in with_charge
    with pytest.raises(SystemExit, match="hold no Scenario 1 line of env_1 seed 1"):
        page.tables(study, [study], study, seed=1, contact=[_seed_only(contact, tmp_path, 0)])
    with pytest.raises(SystemExit, match="has no seed 7; it holds 0, 1"):
        page.tables(study, [], None, seed=7)
    with pytest.raises(SystemExit, match="choose one with --seed"):
        page.tables(study, [], None)


def test_part_page_contact_bullet_counts_the_long_runs_by_kind_end_and_algorithm(load_study):
    """The contact bullet sums what stops.contact_runs found: per kind of contact, those lasting to
    the episode's end, per algorithm (most steps first), and names the longest run's partner."""
    page = load_study("part_page")
    episodes = pd.DataFrame({"contact steps": [500, 120, 60, 0]})
    runs = pd.DataFrame([
        {"policy": "dqn", "agent": "ac_0", "episode seed": 10003, "first step": 176, "steps": 425, "ended": "end",
         "with": "car", "partner": "ac_4", "partner policy": "a3c"},
        {"policy": "a3c", "agent": "ac_5", "episode seed": 10004, "first step": 35, "steps": 75, "ended": "end",
         "with": "object", "partner": np.nan, "partner policy": np.nan},
        {"policy": "a3c", "agent": "ac_5", "episode seed": 10010, "first step": 44, "steps": 55, "ended": "left",
         "with": "object", "partner": np.nan, "partner policy": np.nan}])
    text = page.contact_bullet(episodes, runs, "env_1__seed2.parquet")
    assert "680 contact steps in Scenario 1's 4 AC-episodes, 555 of them in 3 runs of 50 steps or more" in text
    assert ": 1 against a car (425 steps), 2 against objects (130 steps). 2 last to the episode's end (500 steps)." in text
    assert "By algorithm: DQN 1 (425 steps), A3C 2 (130 steps)." in text
    assert text.endswith("The longest: DQN's `ac_0` against A3C's `ac_4` from step 176 of episode 10003, 425 steps (to the end).")
    unseen = runs.assign(partner=["", "", ""], **{"partner policy": ["", "", ""]})  # as stops.contact_runs writes it
    assert page.contact_bullet(episodes, unseen, "x.parquet").endswith(
        "The longest: DQN's `ac_0` against a background car from step 176 of episode 10003, 425 steps (to the end).")
    alone = page.contact_bullet(episodes, runs.iloc[1:], "x.parquet")
    assert alone.endswith("The longest: A3C's `ac_5` against an object from step 35 of episode 10004, 75 steps (to the end).")
    assert page.contact_bullet(episodes, runs.iloc[:0], "x.parquet").endswith("0 of them in 0 runs of 50 steps or more "
                                                                                "(`python studies/stops.py x.parquet --long 50`).")


def _verdict_rows(**passed) -> pd.DataFrame:
    """verdict.csv's rows of env_3 (3 seeds): each algorithm's driving score mean, interval, goal
    rate and whether it passed."""
    rows = []
    for algo, (mean, ok) in passed.items():
        rows.append({"algorithm": algo, "env": "env_3", "n": 3, "DS_mean": mean, "DS_ci_low": mean - 0.1,
                     "DS_ci_high": mean + 0.1, "goal_mean": 0.25, "passed": ok, "DS_ok": ok})
    return pd.DataFrame(rows)


def test_part_page_verdict_bullet_names_the_passes_the_target_and_what_it_lacks(load_study):
    """The verdict bullet: the pairs that pass, the environment's target and what it lacks (no
    discrete or continuous pass, no turning goal), or the two nearest where none passes."""
    page = load_study("part_page")
    targets = pd.DataFrame([{"env": "env_3", "discrete": "[]", "continuous": "['ddpg']", "has_turns": True,
                             "turning": "[]", "met": False}])
    none = page.verdict_bullet(_verdict_rows(ppo=(0.1, False), dqn=(0.3, False), td3=(0.2, False)),
                               targets, "env_3")
    assert none.startswith("- **The verdict with 3 seeds: no pair passes; Four-way's target is not met.** "
                           "It lacks: no discrete algorithm passes; no algorithm's turns are learned (turning "
                           "slots' route completion above the safe non-turner's). Nearest: ")
    assert none.endswith("Nearest: DQN, DS 0.300 [0.200, 0.400] (goal rate 0.25); TD3, DS 0.200 [0.100, 0.300] "
                         "(goal rate 0.25).")
    met = targets.assign(discrete="['dqn']", turning="['dqn']", met=True)
    two = page.verdict_bullet(_verdict_rows(dqn=(0.8, True), ddpg=(0.6, True), ppo=(0.1, False)), met, "env_3")
    assert two == ("- **The verdict with 3 seeds: DQN and DDPG pass; Four-way's target is met.** "
                   "DQN, DS 0.800 [0.700, 0.900] (goal rate 0.25); DDPG, DS 0.600 [0.500, 0.700] (goal rate 0.25).")
    few = page.verdict_bullet(_verdict_rows(dqn=(0.8, False), ppo=(0.1, False)).assign(
        n=2, DS_ok=[True, False]), targets, "env_3")
    assert few.startswith("- **2 seeds so far, too few for a verdict (3 needed): DQN above every degenerate "
                          "reference (not shown); Four-way's target is not met so far.**")
    with pytest.raises(SystemExit, match="verdict.csv has no env_4"):
        page.verdict_bullet(_verdict_rows(dqn=(0.0, False)), targets, "env_4")


def test_part_page_contact_charge_bullet_splits_every_seed_above_always_brake_from_the_rest(load_study):
    """Without the contact charge: an algorithm counts as above always-brake only when every seed
    is (a mean above it with one seed below is not), the safe non-turner is named where given, and
    the page's seed follows alone."""
    page = load_study("part_page")
    lines = pd.DataFrame([{"policy": p, "env": "env_3", "scenario": 1, "train seed": k, "mean_return": -2000.0,
                           "without_contact_charge": x}
                          for p, xs in (("dqn", (-100, -200, -300)), ("ppo", (200, 100, -600)),
                                        ("td3", (-700, -650, -800))) for k, x in enumerate(xs)])
    text = page.contact_charge_bullet(lines, "env_3", 2, -552.0, safe=402.5)
    assert text.startswith("- **Without its contact charge** (`studies/contact_table.py` on the 3 seeds' exports): "
                           "DQN -200.0 [")
    assert "would be above always-brake (-552.0) in all 3 seeds, below the safe non-turner (402.5); PPO" in text
    assert "TD3 -716.7 [" in text and text.endswith("would not. Seed 2 alone: DQN -300.0, PPO -600.0, TD3 -800.0.")
    assert "safe non-turner" not in page.contact_charge_bullet(lines, "env_3", 2, -552.0)
    some = page.contact_charge_bullet(lines.assign(without_contact_charge=lines.without_contact_charge.abs()),
                                      "env_3", None, -552.0, safe=500.0)  # TD3 716.7 above it, PPO 300 and DQN 200 below
    assert "in all 3 seeds; of them PPO and DQN below the safe non-turner (500.0)." in some and "alone" not in some
    two = page.contact_charge_bullet(lines[lines["train seed"] < 2], "env_3", 1, -552.0)
    assert "on the 2 seeds' exports" in two and "in both seeds" in two
    nobody = page.contact_charge_bullet(lines, "env_3", 0, -50.0)
    assert "no algorithm would be above always-brake (-50.0) in every seed. Seed 0 alone: PPO 200.0" in nobody
    with pytest.raises(SystemExit, match="hold no Scenario 1 line of env_3 seed 5"):
        page.contact_charge_bullet(lines, "env_3", 5, -552.0)


def test_part_page_commits_bullet_reads_each_trials_manifest_and_checks_the_training_code(load_study, tmp_path):
    """Which commit each trial trained at, from the manifests, and whether the training code differs
    between the first and the last commit (the page's claim, checked instead of written by hand)."""
    page = load_study("part_page")
    runs = tmp_path / "bench" / "runs"
    for algo, commit, created in (("dqn", "aaaaaaa1", "2026-11-28T11:31:45"), ("ppo", "aaaaaaa1", "2026-11-28T11:31:44"),
                                  ("td3", "bbbbbbb2", "2026-11-28T12:22:43"), ("impala", "ccccccc3", "2026-11-28T13:59:30"),
                                  ("ddpg", "bbbbbbb2", "2026-11-28T12:20:46")):
        run = runs / f"env_2__{algo}__2__bench"
        run.mkdir(parents=True)
        (run / "manifest.json").write_text(json.dumps({"created": created, "git": {"commit": commit, "dirty": False}}))
    other = runs / "env_2__a3c__1__bench"  # another seed's run: not this part's
    other.mkdir()
    (other / "manifest.json").write_text(json.dumps({"created": "2026-11-27T01:00:00", "git": {"commit": "ddddddd4"}}))
    commits = page.trial_commits(runs, "env_2", 2)
    assert [(c, a) for c, a, _ in commits] == [("aaaaaaa", ["ppo", "dqn"]), ("bbbbbbb", ["ddpg", "td3"]), ("ccccccc", ["impala"])]
    asked = []
    same = page.commits_bullet(commits, changed=lambda a, b: asked.append((a, b)) or [])
    assert asked == [("aaaaaaa", "ccccccc")]  # the first and the last commit the trials started at
    assert same.startswith("- **Commits** each trial started at (its manifest.json; ")
    assert ("the first started 2026-11-28 11:31 UTC): PPO and DQN aaaaaaa, DDPG and TD3 bbbbbbb, IMPALA ccccccc; "
            "`git diff aaaaaaa ccccccc -- cosim") in same
    assert same.endswith("is empty: every trial trained on the same code.")
    moved = page.commits_bullet(commits, changed=lambda a, b: ["agents/dqn.py"])
    assert "changes agents/dqn.py: read it before comparing the trials." in moved and "same code" not in moved
    assert "cannot be read" in page.commits_bullet(commits, changed=lambda a, b: None)
    assert page.commits_bullet(commits[:1], changed=None).endswith("PPO and DQN aaaaaaa: every trial trained on the same code.")
    # the real history (where this checkout has it): Three-way seed 2's commits differ in reports only,
    # Straight seed 2's in how `cosim benchmark` counts finished trials
    known = subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", "905e3b2^{commit}"], capture_output=True)
    if known.returncode == 0:
        assert page.git_changed("4125f67", "e4bef89") == []
        assert page.git_changed("905e3b2", "4125f67") == ["eval/cli/learn.py", "eval/scale/benchmark.py"]
    assert page.git_changed("0000000", "e4bef89") is None  # no such commit


def test_part_page_alone_bullet_gives_goals_or_how_far_short_each_algorithm_stood(load_study):
    page = load_study("part_page")
    episodes = pd.DataFrame([
        {"policy": "td3", "goal": False, "steps": 600, "steps off road": 540, "driven m": 30.0, "route m left": 170.0, "return": -400.0},
        {"policy": "td3", "goal": False, "steps": 600, "steps off road": 420, "driven m": 63.0, "route m left": 141.0, "return": -500.0},
        {"policy": "dqn", "goal": True, "steps": 150, "steps off road": 0, "driven m": 202.0, "route m left": 2.0, "return": 3100.0},
        {"policy": "dqn", "goal": False, "steps": 600, "steps off road": 75, "driven m": 90.0, "route m left": 110.0, "return": 1000.0},
        {"policy": "ddpg", "goal": False, "steps": 600, "steps off road": 0, "driven m": 71.9, "route m left": 61.7, "return": -90.0},
        {"policy": "ddpg", "goal": False, "steps": 600, "steps off road": 0, "driven m": 72.1, "route m left": 61.8, "return": -86.0}])
    text = page.alone_bullet(episodes)
    assert text == ("- **Alone (Scenario 2, `ac_0` with no other AC)**: DQN reaches its goal in 1 of 2 episodes, off the road "
                    "in 10% of its steps (2,050.0); DDPG reaches none: drives 72 m and stands 62 m short, off the road "
                    "in 0% of its steps (-88.0); TD3 reaches none: drives 30-63 m and stands 141-170 m short, off the "
                    "road in 80% of its steps (-450.0).")


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_a_study_from_a_first_seed_trains_and_tests_only_its_seeds(smoke, tmp_path):
    """--first-seed 1 --seeds 1 with the smoke study's runs: only seed 1 is tested, and its
    seed means are the smoke study's seed-1 rows."""
    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    _link_runs(study, tmp_path / "runs" / "runs")
    out = tmp_path / "part"
    part = _run(out, "--first-seed", "1", "--seeds", "1", "--runs", str(tmp_path / "runs"))
    assert part.returncode == 0, part.stderr[-2000:]
    assert "tested env_1 seed 1" in part.stderr and "seed 0" not in part.stderr
    assert json.loads((out / "science.json").read_text())["benchmark"]["first_seed"] == 1
    assert sorted(p.name for p in (out / "bench" / "runs").iterdir()) == [
        "env_1__dqn__1__bench", "env_1__ppo__1__bench"]
    cols = ["scenario", "env", "algorithm", "train_seed", "return", "goal", "DISTANCE"]
    mine = pd.read_csv(out / "seeds.csv")[cols]
    theirs = pd.read_csv(study / "seeds.csv").query("train_seed == 1")[cols]
    pd.testing.assert_frame_equal(mine.sort_values(cols[:3]).reset_index(drop=True),
                                  theirs.sort_values(cols[:3]).reset_index(drop=True))
    bad = _run(tmp_path / "neg", "--first-seed", "-1")
    assert bad.returncode == 2 and "--first-seed -1: give 0 or more" in bad.stderr


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_a_finished_study_grows_by_seeds(smoke, tmp_path):
    """A 1-seed study rerun with --seeds 2 and --runs: seed 0's test records are kept, only
    seed 1 is tested, and the results hold both seeds (as the 2-seed study's)."""
    import shutil

    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    out = tmp_path / "grown"
    (out / "test").mkdir(parents=True)
    shutil.copytree(study / "references", out / "references")
    shutil.copy(study / "test" / "env_1__seed0.parquet", out / "test")
    runs = tmp_path / "runs" / "runs"
    _link_runs(study, runs)
    # the 1-seed study as it was left: its plan, its seed-0 runs, its seed-0 records
    plan = json.loads((study / "science.json").read_text())
    plan["benchmark"]["seeds"] = 1
    (out / "science.json").write_text(json.dumps({k: plan[k] for k in ("benchmark", "test")}))
    (out / "bench" / "runs").mkdir(parents=True)
    for algo in plan["benchmark"]["algos"]:
        (out / "bench" / "runs" / f"env_1__{algo}__0__bench").symlink_to(runs / f"env_1__{algo}__0__bench")
    (out / "bench" / "benchmark.json").write_text(json.dumps({**plan["benchmark"], "seeds": 1}))
    seed0 = (out / "test" / "env_1__seed0.parquet").stat().st_mtime_ns

    grown = _run(out, "--runs", str(tmp_path / "runs"))
    assert grown.returncode == 0, grown.stderr[-2000:]
    assert "tested env_1 seed 1" in grown.stderr and "tested env_1 seed 0" not in grown.stderr
    assert (out / "test" / "env_1__seed0.parquet").stat().st_mtime_ns == seed0
    assert json.loads((out / "science.json").read_text())["benchmark"]["seeds"] == 2
    key = ["kind", "name", "metric", "scenario", "n"]
    ours = pd.read_csv(out / "results.csv")
    assert (ours.loc[(ours["kind"] == "algorithm") & (ours["metric"] == "return"), "n"] == 2).all()
    pd.testing.assert_frame_equal(ours[key], pd.read_csv(study / "results.csv")[key])


@pytest.mark.slow  # a second smoke study or combine run (~7-26 s): -m slow
def test_runs_trained_elsewhere_are_linked_instead_of_trained(smoke, tmp_path):
    """--runs: a study takes its finished runs from `cosim benchmark --train-only` folders
    (split across processes), after checking each run's config against the plan."""
    import shutil

    study, done = smoke
    assert done.returncode == 0, done.stderr[-2000:]
    # two folders of one algorithm each, as two processes would have left them
    for algo in ("ppo", "dqn"):
        (tmp_path / algo / "runs").mkdir(parents=True)
        for k in range(2):
            name = f"env_1__{algo}__{k}__bench"
            (tmp_path / algo / "runs" / name).symlink_to((study / "bench" / "runs" / name).resolve())
    out = tmp_path / "linked"
    out.mkdir()
    for stage in ("test", "references"):  # the same held-out records: nothing to rerun
        shutil.copytree(study / stage, out / stage)
    linked = _run(out, "--runs", str(tmp_path / "ppo"), str(tmp_path / "dqn"))
    assert linked.returncode == 0, linked.stderr[-2000:]
    assert "4 finished runs linked" in linked.stderr and "training: all 4 runs finished" in linked.stderr
    assert "cosim benchmark" not in linked.stderr and "tested" not in linked.stderr
    assert (out / "bench" / "runs" / "env_1__dqn__1__bench").resolve() == (
        study / "bench" / "runs" / "env_1__dqn__1__bench").resolve()
    key = ["kind", "name", "metric", "scenario", "mean", "ci_low", "ci_high"]
    pd.testing.assert_frame_equal(pd.read_csv(out / "results.csv")[key], pd.read_csv(study / "results.csv")[key])
    # a run missing from the folders, or trained under another rule: refused, naming it
    for extra, words in ((["--runs", str(tmp_path / "ppo")], "env_1__dqn__0__bench is in none of"),
                         (["--runs", str(tmp_path / "ppo"), str(tmp_path / "dqn"), "--collisions",
                           "end"], "with another collisions_end_episode")):
        bad = _run(tmp_path / "bad", *extra)
        assert bad.returncode == 2 and words in bad.stderr, bad.stderr[-2000:]
        shutil.rmtree(tmp_path / "bad")


def test_no_test_workers_is_refused_naming_the_option(tmp_path):
    bad = subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--test-workers", "0", "--out",
                          str(tmp_path / "s")], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "--test-workers 0: give 1 or more processes" in bad.stderr
    assert not (tmp_path / "s").exists()
