"""studies/variant_table.py (arms of a pilot side by side) on fabricated `cosim test` records."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest


@pytest.fixture(scope="module")
def variant(load_study):
    return load_study("variant_table")


def _ac(agent: str, steps: int, goal_at: int | None = None, car_from: int | None = None,
        off_lane: bool = False, scenario: int = 1) -> pd.DataFrame:
    """One DQN AC of Four-way (env_3: ac_0 turns left, ac_2 goes straight) in episode 0: it drives
    at 5 m/s until ``goal_at``, or from step ``car_from`` stands against a background car
    (charged -50 a step) to the end, off its lane if ``off_lane``; -1 a step otherwise."""
    rows = []
    for k in range(1, steps + 1):
        held = car_from is not None and k >= car_from
        rows.append({"episode": 0, "seed": 10_000, "step": k, "agent": agent, "algorithm": "dqn",
                     "env": "env_3", "scenario": scenario, "x": 0.0, "y": 0.5 * min(k, car_from or k),
                     "spawn_x": 0.0, "spawn_y": 0.0, "goal_x": 0.0, "goal_y": 100.0,
                     "distance_to_goal": 100.0 - 0.5 * k, "speed": 0.0 if held else 5.0,
                     "goal_reached": goal_at == k, "off_road": held and off_lane, "wrong_lane": False,
                     "collision_object": False, "collision_vehicle": held,
                     "r_collision": -50.0 if held else 0.0, "reward": -50.0 - 1.0 if held else -1.0})
    return pd.DataFrame(rows)


def _report(folder: Path, frames: list[pd.DataFrame]) -> Path:
    folder.mkdir(parents=True)
    pd.concat(frames, ignore_index=True).to_parquet(folder / "records.parquet")
    (folder / "provenance.json").write_text(json.dumps({"policy": "trained"}))
    return folder


def test_an_arm_line_splits_the_contact_charge_the_turning_slots_and_the_unseen_runs(variant, tmp_path):
    held = _report(tmp_path / "plain", [_ac("ac_0", 20, goal_at=20),
                                        _ac("ac_2", 100, car_from=41, off_lane=True)])
    line = variant.arm_lines("plain", held).iloc[0]
    assert line["algorithm"] == "dqn" and line["AC-episodes"] == 2
    assert line["return"] == pytest.approx((-20.0 + -100.0 - 60 * 50.0) / 2)
    assert line["without contact charge"] == pytest.approx(-60.0)  # the charge of 60 steps taken off
    assert line["goal rate"] == 0.5
    assert line["turning slots' goal rate"] == 1.0  # ac_0 (left) reached it; ac_2 goes straight
    assert line["contact steps"] == 60 and line["unseen"] == 60  # one run of 60, begun off lane
    assert pd.isna(line["alone return"])  # no Scenario 2 in these records


def test_a_run_begun_on_its_lane_or_too_short_is_not_counted_unseen(variant, tmp_path):
    on_lane = _report(tmp_path / "a", [_ac("ac_2", 100, car_from=41, off_lane=False)])
    short = _report(tmp_path / "b", [_ac("ac_2", 100, car_from=71, off_lane=True)])  # 30 steps
    assert variant.arm_lines("a", on_lane).iloc[0]["unseen"] == 0
    assert variant.arm_lines("b", short).iloc[0]["unseen"] == 0
    assert variant.arm_lines("b", short, long=30).iloc[0]["unseen"] == 30


def test_the_table_puts_each_algorithms_arms_together_in_the_order_given(variant, tmp_path, capsys):
    plain = _report(tmp_path / "plain", [_ac("ac_2", 100, car_from=41, off_lane=True),
                                         _ac("ac_0", 50, scenario=2)])
    see = _report(tmp_path / "see", [_ac("ac_2", 100), _ac("ac_0", 50, scenario=2)])
    assert variant.main([f"see={see}", f"plain={plain}", "--csv", str(tmp_path / "lines.csv")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2].startswith("| DQN | see | -100.0 | -100.0 | 0.00 |  | 0 | 0 | -50.0 | 0.00 |")
    assert out[3].startswith("| DQN | plain | -3,100.0 | -100.0 | 0.00 |  | 60 | 60 | -50.0 | 0.00 |")
    assert pd.read_csv(tmp_path / "lines.csv")["arm"].tolist() == ["see", "plain"]


def test_an_arm_without_a_label_or_records_is_refused_naming_it(variant, tmp_path):
    with pytest.raises(SystemExit, match=r"'reports/x' is not LABEL=REPORT"):
        variant.main(["reports/x"])
    with pytest.raises(SystemExit, match=r"nowhere \(arm see\) does not exist"):
        variant.main([f"see={tmp_path / 'nowhere'}"])


def test_the_figure_draws_each_arm_and_a_reference_line(variant, tmp_path, capsys):
    plain = _report(tmp_path / "plain", [_ac("ac_2", 100, car_from=41, off_lane=True)])
    see = _report(tmp_path / "see", [_ac("ac_2", 100)])
    assert variant.main([f"see={see}", f"plain={plain}", "--figure", str(tmp_path / "fig"),
                         "--reference", "always-brake=-552.0"]) == 0
    assert (tmp_path / "fig" / "arms.png").stat().st_size > 0 and (tmp_path / "fig" / "arms.pdf").is_file()
    assert "wrote" in capsys.readouterr().out
    with pytest.raises(SystemExit, match=r"--reference 'brake' is not NAME=RETURN"):
        variant.main([f"see={see}", "--figure", str(tmp_path / "fig"), "--reference", "brake"])


def test_the_figure_puts_each_arm_at_its_return_and_without_its_charge(variant, tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    lines = pd.DataFrame([
        {"arm": "plain", "algorithm": "dqn", "return": -3100.0, "without contact charge": -100.0},
        {"arm": "see", "algorithm": "dqn", "return": -100.0, "without contact charge": -100.0},
        {"arm": "plain", "algorithm": "ppo", "return": -500.0, "without contact charge": -400.0}])
    captured = {}

    def keep(fig, out, stem):  # look at the axes before they are closed
        captured["ax"] = fig.axes[0]
        return []

    import eval.reporting.figures as figures

    monkeypatch.setattr(figures, "_save", keep)  # figure() imports _save when it draws
    variant.figure(lines, tmp_path, -552.0, "always-brake")
    ax = captured["ax"]
    filled = [ln for ln in ax.lines if ln.get_marker() == "o" and ln.get_markerfacecolor() != "white"]
    xs = sorted(x for ln in filled for x in ln.get_xdata())
    assert xs == [-3100.0, -500.0, -100.0]  # each arm's return, PPO in one arm only
    assert [t.get_text() for t in ax.get_yticklabels()] == ["PPO", "DQN"]  # the study's order
    assert any(list(ln.get_xdata()) == [-552.0, -552.0] for ln in ax.lines)  # the reference
