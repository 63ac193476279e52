"""The driving score (cosim/score.py; docs/task.md, "Driving score"), the headline test metric
(issue 61): route completion, the infraction factors, DS = RC x IP per AC-episode from the
per-step records, what older records give, and Table RQ1's first rows. Hand-made numbers,
then one short real drive."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pandas as pd
import pytest

from cosim.score import INFRACTION_FACTORS, RouteCompletion, driving_score, infraction_penalty
from eval.testing.metrics import SCORE_METRICS, ScoreColumnsMissing, episode_metrics
from eval.testing.records import record_row, to_frame


def test_a_route_driven_halfway_has_route_completion_one_half():
    rc = RouteCompletion(100.0)
    for _ in range(10):
        rc.update(6.0)                      # 60 m towards the goal ...
    assert rc.update(-10.0) == pytest.approx(0.6)  # ... 10 m back: the furthest point counts
    rc = RouteCompletion(100.0)
    values = [rc.update(p) for p in (20.0, 20.0, -5.0, 10.0, 5.0)]  # net 50 m of 100 m
    assert values[-1] == pytest.approx(0.5) and values == sorted(values)
    assert rc.update(0.0, goal_reached=True) == 1.0 and rc.update(-30.0) == 1.0  # from the goal on
    assert RouteCompletion(10.0).update(-3.0) == 0.0 and RouteCompletion(10.0).update(30.0) == 1.0
    with pytest.raises(ValueError, match="length must be > 0"):
        RouteCompletion(0.0)


def test_the_infraction_factors_multiply():
    assert INFRACTION_FACTORS == {"pedestrian": 0.50, "vehicle": 0.60, "object": 0.65, "red_light": 0.70}
    assert infraction_penalty(vehicle=2, red_light=1) == pytest.approx(0.6 * 0.6 * 0.7)
    assert infraction_penalty(pedestrian=1, obj=1) == pytest.approx(0.5 * 0.65)
    assert infraction_penalty() == 1.0
    with pytest.raises(ValueError, match="must be >= 0"):
        infraction_penalty(vehicle=-1)
    assert driving_score(0.5, 0.252) == pytest.approx(0.126)
    assert driving_score(1.3, 0.5) == 0.5 and driving_score(-0.2, 1.0) == 0.0  # RC clipped to 0..1


def _info(step: int, rc: float, **flags) -> dict:
    info = {"x": float(step), "y": 0.0, "heading": 0.0, "speed": 5.0, "distance_to_goal": 100.0 - step,
            "progress": 1.0, "n_vehicles": 2, "n_pedestrians": 0, "spawn_x": 0.0, "spawn_y": 0.0,
            "goal_x": 100.0, "goal_y": 0.0, "time": 0.1 * step, "route_completion": rc,
            "reward_terms": {"collision": 0.0, "efficiency": 1.0, "lane": 0.0, "step": -1.0}}
    from cosim.events import EVENT_FLAGS

    info.update(dict.fromkeys(EVENT_FLAGS, False), **flags)
    info["collision"] = info["collision_vehicle"] or info["collision_pedestrian"] or info["collision_object"]
    info["lane_violation"] = info["off_road"] or info["wrong_lane"]
    return info


def _episode(ep: int, infos: list[dict]) -> list[dict]:
    return [record_row(episode=ep, seed=ep, step=i + 1, agent="ac_0", algorithm="ppo", info=inf,
                       reward=0.0, terminated=False, truncated=False) for i, inf in enumerate(infos)]


def score_records() -> pd.DataFrame:
    """Three AC-episodes: 0 drives half its route with two vehicle events (the first a 2-step
    contact) and a red light; 1 reaches its goal clean; 2 reaches it after hitting an object."""
    contact = {2: {"collision_vehicle": True, "event_vehicle": True}, 3: {"collision_vehicle": True},
               6: {"collision_vehicle": True, "event_vehicle": True}, 8: {"red_light": True}}
    half = [_info(t, 0.05 * t, **contact.get(t, {})) for t in range(1, 11)]
    clean = [_info(t, 0.2 * t, goal_reached=t == 5) for t in range(1, 6)]
    bump = [_info(t, 0.25 * t, goal_reached=t == 4,
                  **({"collision_object": True, "event_object": True} if t == 2 else {})) for t in range(1, 5)]
    return to_frame(_episode(0, half) + _episode(1, clean) + _episode(2, bump))


def test_the_driving_score_is_route_completion_times_the_infraction_penalty():
    per = episode_metrics(score_records(), dt=0.1).set_index("episode")
    assert per.loc[0, "RC"] == pytest.approx(0.5)
    assert per.loc[0, "IP"] == pytest.approx(0.6 * 0.6 * 0.7)
    assert per.loc[0, "DS"] == pytest.approx(0.5 * 0.6 * 0.6 * 0.7)
    assert (per.loc[0, "CV_events"], per.loc[0, "CO_events"]) == (2, 0)
    assert per.loc[0, "CV"] == pytest.approx(0.3)  # the paper's CV counts the 3 contact steps
    assert np.isnan(per.loc[0, "CP_events"])      # no pedestrian existed, as CP
    assert per.loc[0, "success"] == 0.0
    assert tuple(per.loc[1, ["DS", "RC", "IP", "success"]]) == (1.0, 1.0, 1.0, 1.0)
    assert per.loc[2, "RC"] == 1.0 and per.loc[2, "DS"] == pytest.approx(0.65)
    assert per.loc[2, "success"] == 0.0 and per.loc[2, "CO_events"] == 1  # the goal, not clean
    np.testing.assert_allclose(per["DS"], per["RC"] * per["IP"])


def test_records_without_the_score_columns_give_nan_and_say_why():
    old = score_records().drop(columns=["event_vehicle", "event_pedestrian", "event_object", "route_completion"])
    with pytest.warns(ScoreColumnsMissing, match="event_vehicle, event_pedestrian, event_object, "
                                                 "route_completion.*NaN"):
        per = episode_metrics(old, dt=0.1)
    assert per[list(SCORE_METRICS)].isna().all().all()
    assert per["CV"].notna().all() and per["goal"].tolist() == [False, True, True]  # the rest as before
    info = _info(1, 0.0)
    for key in ("event_vehicle", "event_pedestrian", "event_object", "route_completion"):
        info.pop(key)
    row = record_row(episode=0, seed=0, step=1, agent="ac_0", algorithm="ppo", info=info, reward=0.0,
                     terminated=False, truncated=False)  # an older env's info: recorded, without them
    assert "route_completion" not in row and "event_vehicle" not in row and row["collision_vehicle"] is False


def test_table_rq1_and_the_pages_first_screen_open_with_ds_rc_and_success():
    from eval.reporting import page
    from eval.reporting.report import (
        HEADLINE,
        TABLE_METRICS,
        long_table,
        per_episode,
        row_name,
        wide_rows,
    )

    assert TABLE_METRICS[:3] == HEADLINE == ("DS", "RC", "success")
    records = score_records().assign(scenario=1, env="env_1")
    with warnings.catch_warnings():
        warnings.simplefilter("error", ScoreColumnsMissing)  # these records have every column
        long = long_table(per_episode(records, dt=0.1))
    header, rows, groups, _ = wide_rows(long)
    assert [r[1] for r in rows[:4]] == ["n (episodes)", "DS", "RC", "success rate"]
    assert rows[1][2] == long.query("metric == 'DS'")["cell"].item()
    mean = (0.126 + 1.0 + 0.65) / 3
    assert rows[1][2].startswith(f"{mean:.3f} [") and rows[3][2].startswith("0.33 [")
    assert [r[1] for r in rows].index("CV") > [r[1] for r in rows].index("CV events")  # the paper's after
    first = page.headline_markdown(long)
    assert first.splitlines()[2] == "| environment | scenario | policy | " + " | ".join(
        row_name(m) for m in HEADLINE) + " | n |"
    assert f"| Straight | S1 | ppo | {rows[1][2]} | {rows[2][2]} | {rows[3][2]} | 3 |" in first


def test_a_real_drive_halfway_along_the_route_completes_half_of_it():
    """The autopilot drives env_1's ac_0 (no traffic, no spawn jitter) until it is halfway along
    its route: the step's route_completion is the share driven; the env's info carries it."""
    from cosim.controller import Autopilot
    from cosim.scenario import SpawnJitter, load_scenario
    from cosim.world import World

    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter())
    with World(sc, 1, background=False, pedestrians=False) as w:
        w.reset(seed=0)
        route, pilot = w.routes[0], Autopilot(w, "ac_0")
        length = route.goal_s - route.spawn_s
        s = route.spawn_s
        while s < route.spawn_s + length / 2:
            r = w.step({"ac_0": tuple(pilot.act())})["ac_0"]
            s = route.arc_length(r.x, r.y)
        assert r.events.route_completion == pytest.approx((s - route.spawn_s) / length, abs=0.01)
        assert r.events.route_completion == pytest.approx(0.5, abs=0.05)
        assert "route_completion" in r.info() and not r.events.event_vehicle
