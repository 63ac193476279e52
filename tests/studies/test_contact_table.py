"""studies/contact_table.py: the return with and without the contact charge over seeds."""

from __future__ import annotations

import pandas as pd
import pytest


@pytest.fixture(scope="module")
def ct(load_study):
    return load_study("contact_table")


def _part(folder, seed: int, returns: dict[str, tuple[float, float]], scenario: int = 1):
    """A part's contact.csv: per policy (return, return without the contact charge) of env_2."""
    folder.mkdir(parents=True)
    pd.DataFrame([{"policy": p, "env": "env_2", "scenario": scenario, "train seed": seed,
                   "ac_episodes": 24, "goal_rate": 0.0, "mean_return": r, "without_contact_charge": w,
                   "contact_steps": 0, "AC_share": None, "standing_share": None}
                  for p, (r, w) in returns.items()]).to_csv(folder / "contact.csv", index=False)
    return folder


def test_each_cell_is_the_mean_over_seeds_with_and_without_the_charge(ct, tmp_path):
    parts = [_part(tmp_path / "s0", 0, {"dqn": (-1000.0, 400.0), "td3": (-300.0, -100.0)}),
             _part(tmp_path / "s1", 1, {"dqn": (-2000.0, 500.0)}),
             _part(tmp_path / "s2", 2, {"dqn": (0.0, 600.0)})]
    t = ct.table(ct.load(parts)).set_index("policy")
    assert t.loc["dqn", "mean_return"] == -1000.0 and t.loc["dqn", "without_contact_charge"] == 500.0
    assert t.loc["dqn", "seeds"] == "0 1 2"
    assert t.loc["dqn", "mean_return_low"] < -1000.0 < t.loc["dqn", "mean_return_high"]
    assert t.loc["td3", "mean_return_cell"] == "-300.0"
    text = ct.markdown(ct.table(ct.load(parts)))
    line = next(x for x in text.splitlines() if x.startswith("| DQN"))
    assert line.startswith("| DQN | -1,000.0 [") and "] / 500.0 [" in line and line.endswith("] (3 seeds) |")
    assert "| -300.0 / -100.0 (1 seed) |" in text and "| Three-way |" in text
    assert ct.table(ct.load(parts), scenario=2).empty  # Scenario 1 lines only


def test_a_seed_given_twice_or_a_part_without_its_file_is_refused_by_name(ct, tmp_path):
    a = _part(tmp_path / "a", 0, {"dqn": (1.0, 2.0)})
    b = _part(tmp_path / "b", 0, {"dqn": (3.0, 4.0)})
    with pytest.raises(SystemExit, match="env_2 seed 0 .dqn. is in .*a/contact.csv and .*b/contact.csv"):
        ct.load([a, b])
    with pytest.raises(SystemExit, match="nothing has no contact.csv; write it with"):
        ct.load([tmp_path / "nothing"])
