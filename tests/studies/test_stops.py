"""studies/stops.py (where each AC stopped for good) on fabricated `cosim test` records."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest


@pytest.fixture(scope="module")
def stops(load_study):
    return load_study("stops")


def _episode(episode: int, agent: str, speeds: list[float], goal_at: int | None) -> pd.DataFrame:
    """An AC driving north from (0, 0) at ``speeds`` (m/s, dt 0.1 s) towards a goal at (0, 100)."""
    y, rows = 0.0, []
    for k, v in enumerate(speeds, start=1):
        y += v * 0.1
        rows.append({"episode": episode, "seed": 10_000 + episode, "step": k, "agent": agent,
                     "algorithm": "dqn", "env": "env_2", "scenario": 2, "x": 0.0, "y": y,
                     "spawn_x": 0.0, "spawn_y": 0.0, "goal_x": 0.0, "goal_y": 100.0,
                     "distance_to_goal": 100.0 - y, "speed": v,
                     "goal_reached": goal_at is not None and k == goal_at,
                     "off_road": k > 40, "wrong_lane": False, "collision_object": k == 30,
                     "collision_vehicle": False, "reward": -1.0})
    return pd.DataFrame(rows)


def _report(folder: Path, frames: list[pd.DataFrame], policy: str = "trained") -> Path:
    folder.mkdir(parents=True)
    pd.concat(frames, ignore_index=True).to_parquet(folder / "records.parquet")
    (folder / "provenance.json").write_text(json.dumps({"policy": policy}))
    return folder


def test_a_car_that_stands_still_is_found_with_its_last_moving_step(stops, tmp_path):
    stood = _episode(0, "ac_0", [10.0] * 30 + [0.0] * 170, goal_at=None)  # 30 m, then stands
    reached = _episode(1, "ac_0", [10.0] * 99 + [5.0], goal_at=100)
    rows = stops.episode_rows(_report(tmp_path / "r", [stood, reached]))
    first, second = rows.iloc[0], rows.iloc[1]
    assert first["last step moving"] == 30 and not first["goal"]
    assert first["driven m"] == pytest.approx(30.0) and first["route m left"] == pytest.approx(70.0)
    assert first["steps off road"] == 160 and first["object contacts"] == 1
    assert first["return"] == -200.0 and first["episode seed"] == 10_000
    assert second["last step moving"] == 100 and second["goal"]
    table = stops.summary(rows)
    assert len(table) == 1
    line = table.iloc[0]
    assert line["episodes"] == 2 and line["goal_rate"] == 0.5
    assert line["stood_still"] == 1  # the goal episode never stood; the other stood 170 steps
    assert line["policy"] == "dqn"


def test_a_reference_report_is_labelled_with_its_driver(stops, tmp_path):
    folder = _report(tmp_path / "a", [_episode(0, "ac_0", [5.0] * 20, None)], policy="autopilot")
    assert stops.episode_rows(folder)["policy"].tolist() == ["autopilot"]


def test_a_folder_without_records_is_refused_naming_it(stops, tmp_path):
    with pytest.raises(SystemExit, match=r"no records.parquet; give a `cosim test` report folder"):
        stops.main([str(tmp_path)])


def test_the_command_writes_the_rows_it_prints(stops, tmp_path, capsys):
    folder = _report(tmp_path / "r", [_episode(0, "ac_0", [10.0] * 30 + [0.0] * 170, None)])
    assert stops.main([str(folder), "--out", str(tmp_path / "rows.csv")]) == 0
    written = pd.read_csv(tmp_path / "rows.csv")
    assert written["last step moving"].tolist() == [30]
    assert "stood_still" in capsys.readouterr().out


def test_contacts_are_split_into_those_with_another_ac_and_those_standing(stops, tmp_path):
    driver = _episode(0, "ac_0", [10.0] * 30 + [0.0] * 70, None)  # reaches y = 30 at step 30, stands
    parked = _episode(0, "ac_1", [0.0] * 100, None).assign(y=33.0)  # stands 3 m ahead of it all along
    passer = _episode(0, "ac_2", [5.0] * 100, None).assign(x=100.0)  # far from both, always moving
    for frame in (driver, parked, passer):
        frame["collision_object"] = False
    touching = driver["step"] > 30
    driver["collision_vehicle"] = touching
    parked["collision_vehicle"] = touching.values
    passer["collision_vehicle"] = passer["step"] <= 10  # a background car, not an AC
    rows = stops.episode_rows(_report(tmp_path / "r", [driver, parked, passer])).set_index("agent")
    assert rows.loc["ac_0", "AC contacts"] == 70 and rows.loc["ac_0", "standing contacts"] == 70
    assert rows.loc["ac_1", "AC contacts"] == 70 and rows.loc["ac_1", "contact steps"] == 70
    assert rows.loc["ac_2", "vehicle contacts"] == 10
    assert rows.loc["ac_2", "AC contacts"] == 0 and rows.loc["ac_2", "standing contacts"] == 0
    # while ac_0 drove (steps 1-29) it was more than 5 m behind ac_1: no AC contact counted early
    early = driver.assign(collision_vehicle=driver["step"] <= 20)
    rows = stops.episode_rows(_report(tmp_path / "s", [early, parked])).set_index("agent")
    assert rows.loc["ac_0", "AC contacts"] == 0 and rows.loc["ac_0", "vehicle contacts"] == 20
    line = stops.summary(stops.episode_rows(tmp_path / "r")).set_index("agent")
    assert line.loc["ac_0", "AC_share"] == 1.0 and line.loc["ac_2", "AC_share"] == 0.0


def test_a_records_file_is_read_as_its_report(stops, tmp_path):
    folder = _report(tmp_path / "r", [_episode(0, "ac_0", [10.0] * 30 + [0.0] * 170, None)])
    assert stops.episode_rows(folder / "records.parquet")["last step moving"].tolist() == [30]


def test_a_studys_records_keep_each_scenario_2_run_apart(stops, tmp_path):
    """A science study's records hold Scenario 1 (ACs of several algorithms together) and
    Scenario 2 (each algorithm's ac_0 alone, in its own environment) with the same episode
    numbers: each (scenario, episode, AC, algorithm) is one row, and two ACs alone in their own
    runs are never counted as touching, however close their positions."""
    together = [_episode(0, "ac_0", [5.0] * 50, None).assign(scenario=1, algorithm="ppo"),
                _episode(0, "ac_1", [5.0] * 50, None).assign(scenario=1, algorithm="dqn", x=50.0)]
    alone = [_episode(0, "ac_0", [0.0] * 50, None).assign(algorithm=a, collision_vehicle=True)
             for a in ("ppo", "dqn")]  # the same place and steps: one background car each
    rows = stops.episode_rows(_report(tmp_path / "r", together + alone))
    assert len(rows) == 4 and (rows["steps"] == 50).all()
    s2 = rows[rows.scenario == 2].set_index("policy")
    assert s2.loc["ppo", "vehicle contacts"] == 50 and s2.loc["ppo", "AC contacts"] == 0
    assert s2.loc["dqn", "AC contacts"] == 0 and s2.loc["dqn", "standing contacts"] == 50
    assert rows[rows.scenario == 1].set_index("agent").loc["ac_0", "return"] == -50.0


def test_by_policy_gives_the_mean_return_without_the_contact_charge(stops, tmp_path):
    """The reward's collision term (r_collision) is taken out of each AC-episode's return."""
    hit = _episode(0, "ac_0", [0.0] * 50, None).assign(collision_vehicle=True, collision_object=False)
    hit = hit.assign(r_collision=-50.0, reward=-51.0)  # every step in contact: -1 and -50
    clear = _episode(1, "ac_0", [5.0] * 50, None).assign(r_collision=0.0, collision_object=False)
    line = stops.by_policy(stops.episode_rows(_report(tmp_path / "r", [hit, clear]))).iloc[0]
    assert line["ac_episodes"] == 2 and line["mean_return"] == (-51.0 * 50 - 50.0) / 2
    assert line["without_contact_charge"] == -50.0  # both episodes: -1 a step
    assert line["contact_steps"] == 50 and line["standing_share"] == 1.0 and line["AC_share"] == 0.0


def test_a_science_studys_seeds_get_a_line_each_and_policy_out_writes_them(stops, tmp_path):
    """A science study's records carry ``train_seed``: by_policy keeps each seed's mean apart
    (one seed in contact, the other not), ``--policy-out`` writes those lines (a part's
    contact.csv); a report without training seeds keeps its line beside them."""
    hit = _episode(0, "ac_0", [0.0] * 50, None).assign(collision_vehicle=True, collision_object=False,
                                                        r_collision=-50.0, reward=-51.0)
    clear = _episode(0, "ac_0", [5.0] * 50, None).assign(r_collision=0.0, collision_object=False)
    seeds = pd.concat([hit.assign(train_seed=0), clear.assign(train_seed=1)], ignore_index=True)
    (tmp_path / "study").mkdir()
    seeds.to_parquet(tmp_path / "study" / "env_2__seeds.parquet")
    plain = _report(tmp_path / "r", [clear.assign(algorithm="ppo")])
    out = tmp_path / "contact.csv"
    assert stops.main([str(tmp_path / "study" / "env_2__seeds.parquet"), str(plain), "--policy-out", str(out)]) == 0
    lines = pd.read_csv(out)
    dqn = lines[lines.policy == "dqn"].set_index("train seed")
    assert dqn.loc[0, "mean_return"] == -51.0 * 50 and dqn.loc[0, "without_contact_charge"] == -50.0
    assert dqn.loc[1, "mean_return"] == -50.0 and dqn.loc[1, "contact_steps"] == 0
    assert lines[lines.policy == "ppo"]["train seed"].isna().all() and len(lines) == 3


def test_a_long_contact_run_names_the_ac_it_was_held_against_and_who_drove_into_whom(stops, tmp_path):
    """ac_0 drives north into ac_1, which stands 33 m up the road, and both stand in contact to
    the end: each gets one run with the other as partner, ac_1 ahead of the car that drove in,
    ac_0 behind the standing one (outside its forward camera); a background car's short contact
    (ac_2) is a run with no partner, dropped below ``min_steps``, and counted as left."""
    driver = _episode(0, "ac_0", [10.0] * 30 + [0.0] * 70, None)
    parked = _episode(0, "ac_1", [0.0] * 100, None).assign(y=33.0)
    passer = _episode(0, "ac_2", [5.0] * 100, None).assign(x=100.0)
    for frame in (driver, parked, passer):
        frame["collision_object"] = False
        frame["heading"] = np.pi / 2  # north
    touching = driver["step"] > 29
    driver["collision_vehicle"] = touching
    parked["collision_vehicle"] = touching.values
    passer["collision_vehicle"] = passer["step"].between(10, 14)
    records = pd.concat([driver, parked, passer], ignore_index=True)
    runs = stops.contact_runs(records, min_steps=50).set_index("agent")
    assert sorted(runs.index) == ["ac_0", "ac_1"]
    rammer, stood = runs.loc["ac_0"], runs.loc["ac_1"]
    assert rammer["first step"] == 30 and rammer["steps"] == 71 and rammer["ended"] == "end"
    assert rammer["partner"] == "ac_1" and rammer["partner at"] == "ahead"
    assert rammer["partner along m"] == pytest.approx(3.0) and rammer["seen from partner"] == "behind"
    assert rammer["speed at first"] == 10.0 and rammer["partner speed at first"] == 0.0
    assert stood["partner"] == "ac_0" and stood["partner at"] == "behind" and stood["partner at last"] == "behind"
    assert stood["standing"] == 1.0
    # the same, but ac_1 not in contact itself (the car ac_0 touches is a background car): no partner
    apart = pd.concat([driver, parked.assign(collision_vehicle=False), passer], ignore_index=True)
    alone = stops.contact_runs(apart, min_steps=50).set_index("agent")
    assert list(alone.index) == ["ac_0"] and alone.loc["ac_0", "partner"] == ""
    rows = stops.episode_rows(_report(tmp_path / "apart", [driver, parked.assign(collision_vehicle=False)]))
    assert rows.set_index("agent").loc["ac_0", "AC contacts"] == 0
    short = stops.contact_runs(records).set_index("agent").loc["ac_2"]
    assert short["steps"] == 5 and short["partner"] == "" and short["ended"] == "left"
    assert short["with"] == "car" and rammer["with"] == "car"
    assert not rammer["off lane at first"]  # _episode puts an AC off the road from step 41 on
    table = stops.runs_summary(runs.reset_index(), all_contact_steps=71 + 71 + 5).set_index("kind")
    assert table.loc["AC ahead", "steps"] == 71 and table.loc["AC behind", "to_end"] == 1
    assert table.loc["AC ahead", "share_of_all_contact"] == round(71 / 147, 2)
    assert table.loc["AC ahead", "steps_off_lane"] == 0


def test_the_command_lists_long_contact_runs_and_refuses_a_negative_length(stops, tmp_path, capsys):
    stand = _episode(0, "ac_0", [0.0] * 80, None).assign(collision_vehicle=True, collision_object=False,
                                                         heading=0.0)
    folder = _report(tmp_path / "r", [stand])
    assert stops.main([str(folder), "--long", "50", "--runs-out", str(tmp_path / "runs.csv")]) == 0
    assert pd.read_csv(tmp_path / "runs.csv")["steps"].tolist() == [80]
    assert "background car" in capsys.readouterr().out
    with pytest.raises(SystemExit, match=r"--long -1 is negative; give a number of contact steps"):
        stops.main([str(folder), "--long", "-1"])
