"""studies/arms.py (training arms side by side, slot by slot) on fabricated run folders."""

from __future__ import annotations

import argparse

import pandas as pd
import pytest


@pytest.fixture(scope="module")
def arms(load_study):
    return load_study("arms")


def _run(folder, rows):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text("algo: dqn\n")
    pd.DataFrame(rows, columns=["agent", "env_step", "goal_reached", "length", "distance_to_goal"]).to_csv(
        folder / "episodes.csv", index=False)
    return folder


def test_training_rows_count_goals_late_ones_and_the_nearest_end(arms, tmp_path):
    run = _run(tmp_path / "r", [
        ("ac_0", 100, False, 600, 40.0), ("ac_0", 900, True, 300, 2.0),   # late goal (> 0.8 x 1000)
        ("ac_1", 200, True, 250, 1.0), ("ac_1", 700, False, 600, 55.0),   # early goal only
    ])
    t = arms.training_rows("grid", run, budget=1000).set_index("slot")
    assert t.loc["ac_0", ["episodes", "goals", "late episodes", "late goals"]].tolist() == [2, 1, 1, 1]
    assert t.loc["ac_1", ["goals", "late episodes", "late goals"]].tolist() == [1, 0, 0]
    assert t.loc["ac_0", "mean length"] == 450 and t.loc["ac_1", "nearest end m"] == 1.0
    assert set(t["arm"]) == {"grid"}


def test_table_puts_each_slots_route_beside_its_arms(arms, tmp_path):
    rows = [(f"ac_{k}", 500, k == 2, 400, 5.0) for k in range(6)]
    a = arms.training_rows("a", _run(tmp_path / "a", rows), 1000)
    b = arms.training_rows("b", _run(tmp_path / "b", rows), 1000)
    test = pd.DataFrame({"slot": ["ac_0", "ac_0"], "arm": ["a", "b"], "test return": [1.0, 2.0]})
    t = arms.table(pd.concat([a, b]), test, "env_2")
    assert t[["slot", "arm"]].head(2).values.tolist() == [["ac_0", "a"], ["ac_0", "b"]]
    assert t.set_index(["slot", "arm"]).loc[("ac_0", "b"), "test return"] == 2.0
    assert dict(zip(t["slot"], t["movement"], strict=False))["ac_2"] == "straight"
    assert dict(zip(t["slot"], t["movement"], strict=False))["ac_0"] == "left"


@pytest.mark.parametrize("text", ["nolabel", "=x", "lab="])
def test_an_arm_without_label_or_folder_is_refused(arms, text):
    with pytest.raises(argparse.ArgumentTypeError, match="LABEL=RUN_FOLDER"):
        arms.parse_arm(text)


def test_an_arm_that_is_not_a_run_folder_is_refused_in_one_line(arms, tmp_path):
    with pytest.raises(argparse.ArgumentTypeError, match="not a training run folder"):
        arms.parse_arm(f"x={tmp_path}")
