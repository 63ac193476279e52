"""Metrics (SPEC §4) on hand-made records, where every number can be worked out by hand."""

import math

import numpy as np
import pandas as pd
import pytest

from cosim.events import EVENT_FLAGS
from eval.testing.metrics import episode_metrics, success_rates, summarize
from eval.testing.records import record_row, to_frame


def _info(x, speed=10.0, n_veh=3, n_ped=0, **events):
    info = {
        "x": x, "y": 0.0, "heading": 0.0, "speed": speed, "distance_to_goal": 100 - x,
        "progress": 1.0, "n_vehicles": n_veh, "n_pedestrians": n_ped,
        "spawn_x": 0.0, "spawn_y": 0.0, "goal_x": 100.0, "goal_y": 0.0, "time": 0.0,
        "route_completion": x / 100.0,
        "reward_terms": {"collision": 0.0, "efficiency": 1.0, "lane": 0.0, "step": -1.0},
    }
    flags = dict.fromkeys(EVENT_FLAGS, False)
    flags.update(events)
    flags["collision"] = flags["collision_vehicle"] or flags["collision_pedestrian"] or flags["collision_object"]
    flags["lane_violation"] = flags["off_road"] or flags["wrong_lane"]
    info.update(flags)
    return info


def _records(steps):
    return to_frame([
        record_row(episode=0, seed=0, step=i + 1, agent="ac_0", algorithm="ppo", info=inf,
                   reward=r, terminated=False, truncated=False)
        for i, (inf, r) in enumerate(steps)
    ])


def test_fractions_ttfc_speed_distance():
    steps = [
        (_info(10, speed=10), 1.0),
        (_info(20, speed=20, collision_vehicle=True), -49.0),
        (_info(30, speed=0, off_road=True), 2.0),
        (_info(40, speed=10, collision_object=True, wrong_lane=True), -50.0),
    ]
    m = episode_metrics(_records(steps), dt=0.1).iloc[0]
    assert m.CV == pytest.approx(0.25) and m.CO == pytest.approx(0.25)
    assert math.isnan(m.CP)  # no pedestrian ever existed: "-"
    assert m.OS == pytest.approx(0.5)
    assert m.TTFC == pytest.approx(0.2)  # first collision at step 2 of 0.1 s
    assert m.SPEED == pytest.approx(10 * 3.6)
    assert m.DISTANCE == pytest.approx(100 - 60)  # from 100 m away to 60 m away
    assert m["return"] == pytest.approx(-96.0) and m.steps == 4


def test_no_collision_no_others():
    steps = [(_info(5 * i, n_veh=0, n_ped=2), 1.0) for i in range(1, 5)]
    m = episode_metrics(_records(steps), dt=0.1).iloc[0]
    assert math.isnan(m.TTFC) and math.isnan(m.CV)
    assert m.CP == 0.0 and m.OS == 0.0


def test_summary_and_success_rates():
    rows = []
    for ep, cv in enumerate([0.0, 1.0]):
        for i in range(2):
            inf = _info(10 * (i + 1), collision_vehicle=bool(cv and i == 0))
            rows.append(record_row(episode=ep, seed=ep, step=i + 1, agent="ac_0", algorithm="dqn",
                                   info=inf, reward=1.0, terminated=False, truncated=False))
    per = episode_metrics(to_frame(rows), dt=0.1)
    s = summarize(per)
    assert s.loc[0, "CV"] == pytest.approx(0.25)  # (0 + 0.5) / 2
    rates = success_rates(s)
    # safety: 1 - mean(CV=0.25, CO=0, CP=NaN skipped)
    assert rates.loc[0, "safety"] == pytest.approx(1 - 0.125)
    assert rates.loc[0, "lane_keeping"] == 1.0
    assert np.isnan(s.loc[0, "CP"])


def test_seconds_come_from_the_scenario_dt(tmp_path):
    """TTFC and the report's time axes use the environment's own step length (Scenario.dt),
    not a fixed 0.1 s: a scenario YAML with dt 0.05 halves the seconds of the same steps."""
    from cosim.scenario import scenarios_dir
    from eval.reporting.report import per_episode
    from eval.testing.metrics import metrics_table, scenario_dt

    text = (scenarios_dir() / "env_1.yaml").read_text()
    assert "\ndt: 0.1 " in text
    fast = tmp_path / "fast.yaml"
    fast.write_text(text.replace("../", f"{scenarios_dir().parent}/").replace("\ndt: 0.1 ", "\ndt: 0.05 "))
    steps = [(_info(10), 1.0), (_info(20, collision_vehicle=True), -49.0), (_info(30), 1.0)]
    records = pd.concat([_records(steps).assign(env=env, scenario=1) for env in ("env_1", str(fast))])
    assert (scenario_dt("env_1"), scenario_dt(str(fast))) == (0.1, 0.05)
    ttfc = per_episode(records).set_index("env")["TTFC"]
    assert ttfc["env_1"] == pytest.approx(0.2) and ttfc[str(fast)] == pytest.approx(0.1)
    table = metrics_table(records).set_index("env")["TTFC"]
    assert table["env_1"] == pytest.approx(0.2) and table[str(fast)] == pytest.approx(0.1)
    assert per_episode(records, dt=1.0)["TTFC"].tolist() == [2.0, 2.0]  # an explicit dt wins
