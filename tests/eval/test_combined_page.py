"""studies/combined_page.py: the page of a --combine folder, its tables taken from summary.md."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

SEEDS01 = Path(__file__).resolve().parents[2] / "docs/results/2026-11-28-science-v3-seeds01/summary.md"


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
    assert "alone" not in cp.sections(SUMMARY) and "alone" not in cp.sections(SEEDS01.read_text())
    alone = SUMMARY + "\nAlone (Scenario 2, each algorithm's `ac_0` ...):\n\n| algorithm | Straight |\n|---|---|\n| DQN | 1.0 (1.00) |\n"
    assert cp.sections(alone)["alone"].splitlines()[-1] == "| DQN | 1.0 (1.00) |"


def test_a_summary_without_a_section_names_it(cp):
    with pytest.raises(SystemExit, match="Did the budgets suffice"):
        cp.sections(SUMMARY.split("Did the budgets")[0])


def test_science_py_summary_has_every_section(cp):
    """The sections' headings are those studies/science.py --combine writes (a combined page in git)."""
    s = cp.sections(SEEDS01.read_text())
    assert s["grid"].startswith("| algorithm | Straight | Three-way | Four-way | Roundabout | Merge |")
    assert "*best degenerate*" in s["grid"] and "| dqn |" in s["iqm"] and "| Merge |" in s["target"]


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
