"""studies/combined_page.py: the page of a --combine folder, its tables taken from summary.md.
The sections of a summary.md that studies/science.py --combine writes over five environments:
tests/studies/test_science.py, test_combined_page_finds_every_section_of_a_five_environment_summary."""

from __future__ import annotations

import pandas as pd
import pytest


@pytest.fixture(scope="module")
def cp(load_study):
    return load_study("combined_page")


SUMMARY = """Validity verdict ... Return [95% CI over seeds] (goal rate) and verdict per pair:

| algorithm | Straight |
|---|---|
| PPO | -2.0 (0.00), FAIL |

IQM across environments (...):

| policy | IQM |
|---|---|
| ppo | 0.60 |
| a3c | 0.57 |

Issue 27's target per environment: 0 of 1 met:

| environment | target |
|---|---|
| Straight | not met |
A line after the table that is not part of it.

Did the budgets suffice? ...

| algorithm | budget (env steps) |
|---|---|
| ppo | 55,000 |
"""


def test_each_section_is_the_first_table_after_its_heading(cp):
    s = cp.sections(SUMMARY)
    assert s["grid"].splitlines() == ["| algorithm | Straight |", "|---|---|", "| PPO | -2.0 (0.00), FAIL |"]
    assert s["iqm"].splitlines()[-1] == "| a3c | 0.57 |"
    assert s["target"].splitlines()[-1] == "| Straight | not met |"  # the table ends at its last row
    assert s["budget"].splitlines()[-1] == "| ppo | 55,000 |"


def test_the_alone_table_is_shown_where_summary_md_has_one(cp):
    assert "alone" not in cp.sections(SUMMARY)
    alone = SUMMARY + "\nAlone (Scenario 2, each algorithm's `ac_0` ...):\n\n| algorithm | Straight |\n|---|---|\n| DQN | 1.0 (1.00) |\n"
    assert cp.sections(alone)["alone"].splitlines()[-1] == "| DQN | 1.0 (1.00) |"


def test_a_summary_without_a_section_names_it(cp):
    with pytest.raises(SystemExit, match="Did the budgets suffice"):
        cp.sections(SUMMARY.split("Did the budgets")[0])


def test_seeds_per_environment_in_the_environments_order(cp):
    seeds = pd.DataFrame({"env": ["env_2", "env_1", "env_1", "env_2", "env_1"], "train_seed": [1, 1, 0, 0, 2]})
    assert cp.seeds_text(seeds) == "Straight 0, 1 and 2, Three-way 0 and 1"
    assert cp.seeds_text(seeds.iloc[[2]]) == "Straight 0"


def test_not_a_combine_folder_is_a_clear_error(cp, tmp_path):
    with pytest.raises(SystemExit, match="not a --combine folder"):
        cp.main([str(tmp_path), "--page", str(tmp_path / "page"), "--title", "t"])


def test_a_combine_folder_missing_a_file_names_it(cp, tmp_path):
    (tmp_path / "science.json").write_text('{"combined": ["a/study", "b/study"]}')
    with pytest.raises(SystemExit, match="lacks summary.md"):
        cp.main([str(tmp_path), "--page", str(tmp_path / "page"), "--title", "t"])
    assert not (tmp_path / "page").exists()  # nothing written


def test_per_environment_verdict_and_contact_bullets_in_the_targets_order(cp, tmp_path):
    """The per-environment section: each environment of targets.csv in its order with its verdict
    bullet; the without-contact-charge bullet where the parts' contact lines hold the environment,
    measured against that environment's always-brake and, where a route turns, its safe non-turner."""
    pd.DataFrame([{"env": "env_1", "title": "Straight", "discrete": "['dqn']", "continuous": "['ddpg']",
                   "has_turns": False, "turning": "[]", "met": True},
                  {"env": "env_3", "title": "Four-way", "discrete": "[]", "continuous": "[]",
                   "has_turns": True, "turning": "[]", "met": False}]).to_csv(tmp_path / "targets.csv", index=False)
    pd.DataFrame([{"algorithm": a, "env": e, "n": 3, "DS_mean": m, "DS_ci_low": m - 0.1,
                   "DS_ci_high": m + 0.1, "goal_mean": 0.5, "DS_ok": ok, "passed": ok}
                  for e, a, m, ok in (("env_1", "dqn", 0.9, True), ("env_1", "ddpg", 0.8, True),
                                      ("env_3", "dqn", 0.07, False), ("env_3", "ddpg", 0.05, False))]
                 ).to_csv(tmp_path / "verdict.csv", index=False)
    pd.DataFrame([{"kind": "reference", "scenario": 1, "metric": "return", "env": e, "name": n, "mean": v}
                  for e, n, v in (("env_1", "always-brake", -545.5), ("env_3", "always-brake", -552.0),
                                  ("env_3", "safe-non-turner", 402.5))]).to_csv(tmp_path / "results.csv", index=False)
    lines = pd.DataFrame([{"policy": a, "env": "env_3", "scenario": 1, "train seed": k, "mean_return": -800.0,
                           "without_contact_charge": -100.0 - k} for a in ("dqn", "ddpg") for k in range(3)])
    text = cp.per_env(tmp_path, lines)
    straight, fourway = text.split("**Four-way**")
    assert "**Straight**" in straight and "DQN and DDPG pass; Straight's target is met." in straight
    assert "contact charge" not in straight  # no contact lines of env_1
    assert "no pair passes; Four-way's target is not met." in fourway
    assert "would be above always-brake (-552.0) in all 3 seeds, all below the safe non-turner (402.5)." in fourway
