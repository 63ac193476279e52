"""Statistics over training seeds (eval/reporting/multiseed.py, what `cosim benchmark --seeds N`
reports and the science study builds on) against hand-computed values, and the benchmark
report's "Over training seeds" section on hand-made records."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from eval.reporting import multiseed, stats
from eval.testing.validity import DEGENERATE


def test_iqm_is_the_mean_of_the_middle_half():
    assert stats.iqm(np.arange(1, 9)) == pytest.approx(4.5)     # cut 2 each end: 3, 4, 5, 6
    assert stats.iqm(np.arange(15)) == pytest.approx(7.0)       # cut 3 each end: 3 .. 11
    assert stats.iqm([5.0, -100.0, 6.0, 100.0]) == pytest.approx(5.5)  # outliers cut
    rows = stats.iqm(np.array([[1, 2, 3, 4], [0, 0, 8, 8]]), axis=1)
    np.testing.assert_allclose(rows, [2.5, 4.0])


def test_stratified_bootstrap_resamples_seeds_within_each_environment():
    # no spread within an environment: every resample is the data itself
    assert stats.stratified_bootstrap({"a": [0, 0], "b": [1, 1]}) == pytest.approx((0.5, 0.5, 0.5))
    # a: [0, 10] resamples to [0, 0] (p 1/4), [0, 10] (1/2), [10, 10] (1/4); b stays [5, 5]:
    # pooled IQMs 2.5, 5, 7.5; both tails hold 25% > 2.5%, so the CI is [2.5, 7.5] exactly
    assert stats.stratified_bootstrap({"a": [0, 10], "b": [5, 5]}) == pytest.approx((5.0, 2.5, 7.5))
    # one environment [0, 0, 0, 10]: IQM (middle two of four) is 0 with at most one 10 drawn
    # (p 0.738), 5 with two (0.211), 10 with three or four (0.051 > 2.5%): CI [0, 10]
    assert stats.stratified_bootstrap({"a": [0, 0, 0, 10]}) == pytest.approx((0.0, 0.0, 10.0))
    with pytest.raises(ValueError, match="at least one score"):
        stats.stratified_bootstrap({"a": []})


def test_with_three_seeds_the_interval_runs_from_the_lowest_to_the_highest_seed():
    """What the README says a pass with 3 seeds means (every seed cleared the reference): each
    all-one-seed resample has probability 1/27 > 2.5%, so the percentile ends are the extremes."""
    from eval.reporting.stats import bootstrap_ci

    rng = np.random.default_rng(0)
    for values in [[740.9, 805.5, 1474.4], *rng.normal(0, 1000, (20, 3)).tolist()]:
        _, lo, hi, n = bootstrap_ci(values)
        assert n == 3 and (lo, hi) == pytest.approx((min(values), max(values)))


def test_seed_table_bootstraps_over_seeds(seed_frame):
    seeds = seed_frame({"return": [0, 0, 0, 10], "CP": [np.nan] * 4, "TTFC": [np.nan, 2, 4, np.nan]})
    t = multiseed.seed_table(seeds).set_index("metric")
    # mean 2.5; resample means: 0 with no 10 drawn (p 0.316), 7.5 with three or more
    # (0.051 > 2.5%) and 10 only with four (0.004 < 2.5%): the 95% CI is [0, 7.5]
    assert tuple(t.loc["return", ["mean", "ci_low", "ci_high", "n"]]) == pytest.approx((2.5, 0, 7.5, 4))
    assert t.loc["return", "cell"] == "2.5 [0.0, 7.5]"
    assert t.loc["CP", "n"] == 0 and t.loc["CP", "cell"] == "-"
    assert t.loc["TTFC", "n"] == 2 and t.loc["TTFC", "cell"].endswith("(n=2)")
    assert t.loc["goal", "cell"] == "0.50 [0.50, 0.50]"  # no spread: zero width


def test_the_turning_slots_goal_rate_counts_only_slots_whose_route_turns():
    """Four-way: ac_0/ac_4/ac_5 turn left, ac_1 right, ac_2/ac_3 go straight; Straight has no
    turn, so its turning-slot goal rate never applies ('-')."""
    slots = [f"ac_{i}" for i in range(6)]
    goals = {"ac_0": 1, "ac_1": 0, "ac_2": 1, "ac_3": 1, "ac_4": 0, "ac_5": 0}
    per = pd.DataFrame([{"scenario": 1, "env": env, "algorithm": "ppo", "train_seed": 0,
                         "episode": 0, "agent": a, "goal": bool(goals[a])}
                        for env in ("env_3", "env_1") for a in slots])
    routes = multiseed.slot_routes("env_3").set_index("slot")
    assert set(routes.index[routes["turning"]]) == {"ac_0", "ac_1", "ac_4", "ac_5"}
    means = multiseed.seed_means(per, metrics=("goal", "goal_turning")).set_index("env")
    assert means.loc["env_3", "goal"] == pytest.approx(0.5)
    assert means.loc["env_3", "goal_turning"] == pytest.approx(0.25)  # ac_0 of the four
    assert np.isnan(means.loc["env_1", "goal_turning"]) and means.loc["env_1", "goal"] == 0.5
    t = multiseed.seed_table(means.reset_index(), metrics=("goal", "goal_turning"))
    cell = t[(t["env"] == "env_1") & (t["metric"] == "goal_turning")]["cell"].item()
    assert cell == "-"


def test_verdict_needs_the_driving_score_ci_above_every_degenerate_reference(seed_frame, reference_frame):
    """A pair passes when its DS interval's lower end clears every degenerate reference's DS
    (the return no longer decides); its turns are learned where the turning slots' RC interval's
    lower end clears the safe non-turner's."""
    refs = reference_frame(values={"autopilot": (1000, 1.0, 0.95, 0.9), "always-forward": (300, 0.1, 0.08),
                                   "always-brake": (-500, 0.0, 0.0), "safe-non-turner": (700, 0.5, 0.6, 0.3)})
    table = pd.concat([
        multiseed.seed_table(seed_frame({"DS": [0.2, 0.4, 0.6], "return": [-4000, -3000, -900],
                                        "RC_turning": [0.4, 0.5, 0.6]}, "ppo")),
        multiseed.seed_table(seed_frame({"DS": [0.05, 0.5, 0.9], "return": [900, 950, 990],
                                        "RC_turning": [0.1, 0.5, 0.9]}, "dqn")),
        multiseed.seed_table(seed_frame({"DS": [0.08, 0.3, 0.4]}, "td3")),
    ])
    v = multiseed.verdict(table, refs).set_index("algorithm")
    assert list(v.index) == ["ppo", "dqn", "td3"]  # the paper's order
    # ppo: DS CI [0.2, 0.6] clears always-forward's 0.08, whatever its (negative) return
    assert v.loc["ppo", "passed"] and v.loc["ppo", "why"] == "" and v.loc["ppo", "return_mean"] < 0
    assert v.loc["ppo", "DS_best_reference"] == "always-forward" and v.loc["ppo", "DS_reference"] == 0.08
    assert v.loc["ppo", "turning_ok"] and v.loc["ppo", "RC_turning_reference"] == 0.3  # 0.4 > 0.3
    # dqn: a high return and mean DS, but its DS CI reaches down to 0.05; its turns not shown
    assert not v.loc["dqn", "passed"] and not v.loc["dqn", "DS_ok"] and not v.loc["dqn", "turning_ok"]
    assert v.loc["dqn", "why"] == "driving score CI low 0.050 <= always-forward 0.080"
    # td3's CI starts at 0.08 = always-forward's: not excluded
    assert not v.loc["td3", "passed"] and v.loc["td3", "why"].startswith("driving score CI low 0.080")
    # above every reference, but with one seed: the verdict asks for three
    one = multiseed.verdict(multiseed.seed_table(seed_frame({"DS": [0.5], "goal": [0.5]}, "a3c")),
                            refs).set_index("algorithm")
    assert one.loc["a3c", "DS_ok"] and not one.loc["a3c", "seeds_ok"]
    assert not one.loc["a3c", "passed"] and one.loc["a3c", "why"] == "1 seed(s), the verdict needs 3"
    assert "| A3C | Straight | 1 |" in multiseed.verdict_markdown(one.reset_index())  # the names as the README writes them
    assert "not shown" in multiseed.verdict_markdown(one.reset_index())
    assert set(DEGENERATE) >= {"random", "always-forward", "always-coast", "always-brake", "full-left"}
    with pytest.raises(ValueError, match="no degenerate reference's driving score"):
        multiseed.verdict(table, refs[refs["metric"] != "DS"])  # references from before the score


def test_the_driving_score_is_normalised_between_random_and_the_autopilot(seed_frame, reference_frame):
    refs = pd.concat([reference_frame("env_1", {"random": (-100, 0, 0.1), "autopilot": (300, 1, 0.9)}),
                      reference_frame("env_2", {"random": (50, 0, 0.5), "autopilot": (50, 1, 0.5)})])
    seeds = pd.concat([seed_frame({"DS": [0.1, 0.5, 0.9, 1.0], "return": [9e9] * 4}, env="env_1"),
                       seed_frame({"DS": [0.1, 0.2, 0.3, 0.4]}, env="env_2")])
    norm = multiseed.normalise(seeds, refs).set_index(["env", "train_seed"])["score"]
    np.testing.assert_allclose(norm.loc["env_1"], [0.0, 0.5, 1.0, 1.125])
    assert norm.loc["env_2"].isna().all()  # the autopilot scores no more than random: no scale
    t = multiseed.iqm_table(seeds, refs).set_index("name")
    assert t.loc["ppo", "iqm"] == pytest.approx(0.75) and t.loc["ppo", "envs"] == 1
    assert t.loc["ppo", "ci_low"] <= 0.75 <= t.loc["ppo", "ci_high"]
    assert t.loc["autopilot", "iqm"] == 1.0 and t.loc["random", "iqm"] == 0.0
    assert "IQM (normalised driving score)" in multiseed.iqm_markdown(t.reset_index())


def test_budget_check_flags_a_run_whose_return_still_rises_at_its_end(tmp_path):
    # budget 100: windows (60, 80] and (80, 100]; episodes before 60 do not count
    flat = pd.DataFrame({"env_step": [10, 65, 70, 75, 85, 90, 95], "return": [-99, 1, 2, 3, 3, 1, 2]})
    gain, lo, hi, n = multiseed.late_gain(flat, 100)
    assert gain == pytest.approx(0.0) and -2 <= lo < 0 < hi <= 2 and n == 3  # resamples span +-2
    rising = flat.assign(**{"return": [-99, 1, 2, 3, 11, 12, 13]})
    gain, lo, hi, n = multiseed.late_gain(rising, 100)
    assert gain == pytest.approx(10.0) and 8 <= lo < 10 < hi <= 12 and n == 3  # any resample: 8..12
    assert np.isnan(multiseed.late_gain(flat[flat.env_step < 80], 100)[0])  # no late episode

    runs = {}
    for name, episodes in (("flat", flat), ("rising", rising)):
        run = tmp_path / name
        run.mkdir()
        (run / "config.yaml").write_text("steps: 100\n")
        episodes.to_csv(run / "episodes.csv", index=False)
        runs[("dqn", "env_1", len(runs))] = run
    check = multiseed.budget_check(runs)
    assert check["rising"].tolist() == [False, True]
    assert "**+5 (rising 1/2)**" in multiseed.budget_markdown(check)
    none = multiseed.budget_check({("td3", "env_1", 0): runs[("dqn", "env_1", 0)]}).assign(n=0)
    assert multiseed.budget_markdown(none).splitlines()[-1] == "| TD3 | 100 | - |"


def test_summary_reference_rows_give_their_mean_and_no_turning_metrics():
    """A test session's references are one summary row per (policy, environment): the table
    takes each mean as it is (n = 1) and leaves the turning slots' metrics out ('-')."""
    summary = pd.DataFrame({"policy": ["autopilot", "random"], "env": "env_3", "DS": [0.9, 0.05],
                            "goal": [1.0, 0.0], "return": [800.0, -50.0]})
    t = multiseed.reference_table(summary).set_index(["name", "metric"])
    assert t.loc[("autopilot", "DS"), "mean"] == 0.9 and t.loc[("random", "DS"), "n"] == 1
    assert t.loc[("random", "RC_turning"), "cell"] == "-" and t.loc[("random", "DS"), "scenario"] == 1


# -- `cosim benchmark --seeds N`: the report's "Over training seeds" --------------------------
def _step(rc: float, step: int, agent: str, algo: str, episode: int = 0) -> dict:
    """One record of an AC that drives on with no event: at ``rc`` of its route by its last step."""
    from cosim.events import EVENT_FLAGS
    from eval.testing.records import record_row

    info = {"x": 10.0 * step, "y": 0.0, "heading": 0.0, "speed": 10.0, "distance_to_goal": 50.0,
            "progress": 1.0, "n_vehicles": 2, "n_pedestrians": 0, "spawn_x": 0.0, "spawn_y": 0.0,
            "goal_x": 100.0, "goal_y": 0.0, "time": 0.1 * step, "route_completion": rc * step / 3,
            "reward_terms": {"step": -1.0}, **dict.fromkeys(EVENT_FLAGS, False),
            "collision": False, "lane_violation": False}
    return record_row(episode=episode, seed=10_000 + episode, step=step, agent=agent, algorithm=algo,
                      info=info, reward=1.0, terminated=False, truncated=step == 3, scenario=1, env="env_1")


DS_OF = {"ppo": [0.6, 0.7, 0.8], "dqn": [0.0, 0.02, 0.3]}
"""The benchmark's hand-made driving score per algorithm and training seed (each seed's one
test episode: route completion, no infraction)."""
REFERENCES = pd.DataFrame({"policy": ["autopilot", "random", "always-brake"], "env": "env_1",
                           "DS": [0.9, 0.05, 0.0], "goal": [1.0, 0.0, 0.0], "return": [90.0, -5.0, -9.0]})


def _benchmark(tmp_path, monkeypatch, seeds: int) -> tuple[list[str], object]:
    """A smoke benchmark of PPO and DQN on Straight with ``seeds`` training seeds, each run a
    folder with a checkpoint, its budget and an episodes.csv whose return rises for DQN; the
    test session is a stand-in giving each seed's :data:`DS_OF` and the :data:`REFERENCES`,
    and the report writer one that keeps its page's extra Markdown."""
    from eval.reporting import report
    from eval.scale.benchmark import BenchmarkPlan, cell_name
    from eval.testing import session

    plan = BenchmarkPlan(preset="smoke", envs=("env_1",), algos=("ppo", "dqn"), seeds=seeds)
    out = tmp_path / "bench"
    for algo in plan.algos:
        for seed in plan.seed_list:
            run = out / "runs" / cell_name({"env": "env_1", "algo": algo, "seed": seed})
            (run / "checkpoints" / "ac_0").mkdir(parents=True)
            (run / "checkpoints" / "ac_0" / "best.pt").write_bytes(b"")
            (run / "config.yaml").write_text("steps: 100\n")
            rise = 10.0 if algo == "dqn" else 0.0
            pd.DataFrame({"agent": "ac_0", "env_step": [65, 70, 75, 85, 90, 95],
                          "return": [1, 2, 3, 3 + rise, 1 + rise, 2 + rise]}).to_csv(run / "episodes.csv", index=False)

    def stand_in(request):
        (ckpts,) = request.checkpoints.values()
        seed = int(Path(ckpts["ppo"]).parents[2].name.split("__")[2])
        records = pd.DataFrame([_step(DS_OF[algo][seed], step, f"ac_{i}", algo)
                                for i, algo in enumerate(request.algos) for step in (1, 2, 3)])
        return session.TestResult(request, records, REFERENCES.copy() if request.references else None)

    written = []
    monkeypatch.setattr(session, "run_test", stand_in)
    monkeypatch.setattr(report, "write_paper_report", lambda records, folder, **kw: written.append(kw["extra_md"]))
    from eval.scale.benchmark import write_report

    write_report(plan, out)
    return written, out / "report"


def test_a_benchmark_with_several_seeds_reports_the_verdict_iqm_and_budgets_over_seeds(tmp_path, monkeypatch):
    (page,), folder = _benchmark(tmp_path, monkeypatch, seeds=3)
    section = page.split("## Over training seeds\n", 1)[1]
    assert "mean over 3 seeds" in section
    seeds = pd.read_csv(folder / "seeds.csv")
    assert len(seeds) == 2 * 3 and set(seeds["train_seed"]) == {0, 1, 2}
    np.testing.assert_allclose(seeds.sort_values(["algorithm", "train_seed"])["DS"], [0.0, 0.02, 0.3, 0.6, 0.7, 0.8])
    v = pd.read_csv(folder / "verdict.csv").set_index("algorithm")
    # PPO's seeds 0.6..0.8 clear random's 0.05; DQN's reach down to 0.0
    assert bool(v.loc["ppo", "passed"]) and not bool(v.loc["dqn", "passed"]) and (v["n"] == 3).all()
    assert v.loc["ppo", "DS_best_reference"] == "random" and v.loc["ppo", "DS_ci_low"] == pytest.approx(0.6)
    assert "| PPO | Straight | 3 | 0.700 [0.600, 0.800] | random 0.050 |" in section
    assert "**pass**" not in section and "| pass |" in section and "| FAIL |" in section
    iqm = pd.read_csv(folder / "iqm.csv").set_index("name")
    # normalised (DS - 0.05) / (0.9 - 0.05); IQM of three values: the middle one
    assert iqm.loc["ppo", "iqm"] == pytest.approx((0.7 - 0.05) / 0.85) and iqm.loc["autopilot", "iqm"] == 1.0
    assert "IQM (normalised driving score)" in section
    budget = pd.read_csv(folder / "budget.csv")
    assert len(budget) == 6 and budget.groupby("algorithm")["rising"].all().to_dict() == {"dqn": True, "ppo": False}
    assert "**+10 (rising 3/3)**" in section and "+0 (rising 0/3)" in section


def test_a_benchmark_with_one_seed_has_no_section_over_seeds(tmp_path, monkeypatch):
    (page,), folder = _benchmark(tmp_path, monkeypatch, seeds=1)
    assert "Benchmark grid" in page and "Over training seeds" not in page
    assert not (folder / "seeds.csv").exists()
