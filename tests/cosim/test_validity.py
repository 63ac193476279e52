"""Scenarios that demand driving (docs/scenarios.md): a solid town, goals that need the
car at the goal, red lights, turning routes, and the degenerate-policy suite."""

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest

from cosim.events import detect_all
from cosim.roadmap import movement, read_net
from cosim.scenario import SpawnJitter, load_scenario
from cosim.world import World
from eval.testing.validity import (
    POLICIES,
    REFERENCES,
    check_scenario,
    failures,
    format_table,
    run_policy,
    score_line,
    summarize,
)

ENVS = ["env_1", "env_2", "env_3", "env_4", "env_5"]
JUNCTIONS = ["env_2", "env_3", "env_4"]


def _quiet(env: str):
    """The scenario without spawn jitter (hand-made poses need exact spawns)."""
    return dataclasses.replace(load_scenario(env), spawn_jitter=SpawnJitter())


def test_driving_across_the_roundabout_island_hits_it_and_stops():
    with World(_quiet("env_4"), 1, background=False) as w:
        w.reset(seed=0)
        # on the west arm, heading straight east at the island, as an open-loop car would
        w.place_ac("ac_0", 148.0, -1.75, 0.0, 8.0)
        out = [w.step({"ac_0": (1.0, 0.0)})["ac_0"] for _ in range(60) if w.active]
    hits = [r for r in out if r.events.collision_object]
    assert hits, "drove through the island"
    assert hits[0].events.hit.startswith("island")
    assert hits[0].x < 175.0 - 14.0, "it hit the kerb, not the monument in the middle"
    # solid: each hit stops it (put back 1 m, standing; no reverse), it never gets across
    assert max(r.x for r in out) < 175.0
    assert not any(r.events.goal_reached for r in out)
    assert all(r.events.speed == 0.0 and r.events.progress == 0.0 for r in hits)


def test_leaving_a_junction_straight_on_a_turning_route_ends_at_a_wall():
    with World(_quiet("env_3"), 1, background=False) as w:
        w.reset(seed=0)  # ac_0 turns left; full throttle, wheel straight crosses the junction
        out = [w.step({"ac_0": (1.0, 0.0)})["ac_0"] for _ in range(250) if w.active]
    assert not any(r.events.goal_reached for r in out)


def _events_at(world: World, x: float, y: float, heading: float, previous_s: float):
    route = world.routes[0]
    state = np.array([[x, y, heading, 8.0]])
    prev = np.array([route.goal_s - previous_s])
    return detect_all(["ac_0"], state, world.vehicle.length, world.vehicle.width,
                      world.snapshot, world.roadmap, [route], prev, 3.0)[0]


def test_beside_the_goal_off_the_road_is_not_the_goal_and_pays_no_more_progress():
    with World(_quiet("env_1"), 1, background=False) as w:
        w.reset(seed=0)
        route = w.routes[0]
        h = route.path.heading_at(route.goal_s)
        gx, gy = route.goal_point
        normal = np.array([math.sin(h), -math.cos(h)])  # to the right of travel: off the road

        def at(s_back: float, side: float, previous: float):
            x, y = route.path.point_at(route.goal_s - s_back) + normal * side
            return _events_at(w, x, y, h, route.goal_s - previous)

        on = at(1.0, 0.0, 6.0)  # on the lane, 1 m before the goal, came 5 m
        assert on.goal_reached and not on.off_road and on.progress == pytest.approx(5.0, abs=0.1)
        # past the goal point, 6 m to the right (on the sidewalk): not reached, nothing credited
        past = at(-4.0, 6.0, 6.0)
        assert past.off_road and not past.goal_reached
        assert past.progress <= 0.0 < on.progress
        assert past.route_speed <= 0.0 < on.route_speed
        # within the radius but off the road (2.9 m to the side, beyond the kerb): not reached
        kerb = at(0.0, 2.9, 1.0)
        assert (kerb.off_road, kerb.goal_reached) == (True, False)
        # the same distance to the side but on the road (into the next lane): reached
        lane = at(0.0, -2.9, 1.0)
        assert (lane.off_road, lane.goal_reached) == (False, True)


def test_a_shortcut_never_pays_more_progress_than_the_road():
    """Two cars make the same 8 m of route distance: one along its lane, one off it."""
    with World(_quiet("env_4"), 1, background=False) as w:
        w.reset(seed=0)
        route = w.routes[0]
        s0 = route.spawn_s + 60.0  # on the ring
        x, y = route.path.point_at(s0 + 8.0)
        road = _events_at(w, x, y, route.path.heading_at(s0 + 8.0), s0)
        inside = np.array([175.0, 0.0]) + 0.8 * (np.array([x, y]) - [175.0, 0.0])  # towards the island
        cut = _events_at(w, *inside, route.path.heading_at(s0 + 8.0), s0)
        assert not road.lane_violation and cut.lane_violation
        assert road.progress == pytest.approx(8.0, abs=0.2)
        assert cut.progress <= 0.0


def _stop_line(world: World):
    route = world.routes[0]
    assert route.signals, "env_3's routes cross the signalised junction"
    return route, route.signals[0]


@pytest.mark.parametrize("state,expected", [("r", True), ("R", True), ("G", False), ("g", False),
                                            ("y", False)])
def test_crossing_the_stop_line_on_red_is_a_red_light(state, expected):
    with World(_quiet("env_3"), 1, background=False) as w:
        w.reset(seed=0)
        route, (stop_s, tls, link) = _stop_line(w)
        signals = {tls: "G" * link + state + "G" * 20}
        w.snapshot = dataclasses.replace(w.snapshot, signals=signals)
        h = route.path.heading_at(stop_s)
        crossing = _events_at(w, *route.path.point_at(stop_s + 0.5), h, stop_s - 0.5)
        before = _events_at(w, *route.path.point_at(stop_s - 1.0), h, stop_s - 2.0)
        after = _events_at(w, *route.path.point_at(stop_s + 3.0), h, stop_s + 2.0)
    assert crossing.red_light is expected
    assert not before.red_light and not after.red_light, "only the step that crosses the line"


def test_red_light_in_the_real_signal_cycle():
    """Full throttle through env_3's signal: flagged exactly when SUMO shows red at the line."""
    flagged, red_at_line = [], []
    for seed in range(4):
        with World(_quiet("env_3"), 1, background=False) as w:
            w.reset(seed=seed)
            route, (stop_s, tls, link) = _stop_line(w)
            prev_s = route.spawn_s
            for _ in range(120):
                if not w.active:
                    break
                r = w.step({"ac_0": (0.6, 0.0) if prev_s < stop_s + 5 else (0.0, 0.0)})["ac_0"]
                s = route.arc_length(r.x, r.y)
                if prev_s < stop_s <= s:
                    red_at_line.append(w.snapshot.signals[tls][link] in "rR")
                    flagged.append(r.events.red_light)
                prev_s = s
    assert flagged == red_at_line and len(flagged) == 4


def _movements(env):
    sc = load_scenario(env)
    net = read_net(sc.net)
    return sc, [movement(net, ac.route) for ac in sc.acs]


@pytest.mark.parametrize("env", JUNCTIONS)
def test_every_prefix_of_acs_turns_and_straights_are_never_the_majority(env):
    sc, moves = _movements(env)
    assert len(moves) == 6
    for k in range(2, len(moves) + 1):
        prefix = moves[:k]
        assert {"left", "right"} & set(prefix), f"{env}: the first {k} ACs never turn: {prefix}"
        assert prefix.count("straight") * 2 <= k, f"{env}: straights are the majority of {prefix}"
    assert {"left", "right", "straight"} <= set(moves)


def test_movements_are_read_from_the_network():
    net = read_net(load_scenario("env_3").net)
    assert movement(net, ["tx_e", "xr_e"]) == "straight"
    assert movement(net, ["tx_e", "xn_n"]) == "left"
    assert movement(net, ["tx_e", "xs_s"]) == "right"
    # roundabout: first / second / third exit from the west arm
    assert movement(net, ["xr_e", "ra_ws", "rs_s"]) == "right"
    assert movement(net, ["xr_e", "ra_ws", "ra_se", "re_e"]) == "straight"
    assert movement(net, ["xr_e", "ra_ws", "ra_se", "ra_en", "rn_n"]) == "left"


def test_the_merge_takes_acs_from_both_roads_in_every_prefix():
    sc = load_scenario("env_5")
    for k in range(2, len(sc.acs) + 1):
        assert len({ac.route[0] for ac in sc.acs[:k]}) == 2


@pytest.mark.parametrize("env", ENVS)
def test_every_environment_starts_moving_with_jitter_by_default(env):
    sc = load_scenario(env)
    assert all(ac.depart_speed >= 5.5 for ac in sc.acs)  # 20 km/h and up
    assert sc.spawn_jitter.heading_deg > 0 and sc.spawn_jitter.lateral > 0


# the default run checks a junction with people and the roundabout (~40 s each); the other three
# run with -m slow (docs/guide.md#running-the-tests), and `cosim check-scenarios` checks all five
@pytest.mark.parametrize("env", [pytest.param(e, marks=pytest.mark.slow) if e in ("env_1", "env_3", "env_5")
                                 else e for e in ENVS])
def test_the_degenerate_policy_suite_passes_on_short_episodes(env):
    rows = check_scenario(env, 3, episodes=2)  # the full horizon: the autopilot waits for people
    table = summarize(rows)
    assert failures(table) == [], format_table(table)


def _table(**rows) -> pd.DataFrame:
    """A summary table: policy -> (goal, return, collision_steps, DS)."""
    return pd.DataFrame({p: dict(zip(("goal", "return", "collision_steps", "DS"), v, strict=True))
                         for p, v in rows.items()}).T.astype(float)


def test_the_discrete_autopilot_is_held_to_the_autopilots_criteria():
    assert REFERENCES == ("autopilot", "autopilot-discrete", "safe-non-turner")
    assert POLICIES[:3] == REFERENCES  # they head every table, then the degenerate policies
    ok = dict(autopilot=(1.0, 2000.0, 0.0, 1.0), **{"autopilot-discrete": (0.95, 1900.0, 0.0, 0.95)})
    assert failures(_table(**ok)) == []
    weak = failures(_table(**(ok | {"autopilot-discrete": (0.6, 900.0, 0.0, 0.7)})))
    assert weak == ["autopilot-discrete scores DS 0.700 (needs >= 0.90)",
                    "autopilot-discrete reaches 60% of goals (needs >= 90%)"]
    crash = failures(_table(**(ok | {"autopilot-discrete": (1.0, 900.0, 2.0, 0.6)})))
    assert crash == ["autopilot-discrete scores DS 0.600 (needs >= 0.90)",
                     "autopilot-discrete collides (2.00 collision steps per AC)"]


def test_the_safe_non_turner_must_not_collide_but_may_score():
    ok = {"autopilot": (1.0, 2000.0, 0.0, 1.0), "always-brake": (0.0, -550.0, 0.0, 0.0)}
    # a third of the goals (the straight slots), a DS of 0.6 and 60% of the autopilot's return: a
    # reference row to beat, not a degenerate policy, so no limit of theirs applies to it
    assert failures(_table(**ok, **{"safe-non-turner": (0.33, 1200.0, 0.0, 0.6)})) == []
    assert failures(_table(**ok, **{"safe-non-turner": (0.0, -200.0, 1.5, 0.2)})) == [
        "safe-non-turner collides (1.50 collision steps per AC)"]
    assert failures(_table(**ok, **{"always-forward": (0.33, 1200.0, 0.0, 0.4)})) == [
        "always-forward scores DS 0.400 (allowed <= 0.10)",
        "always-forward reaches 33% of goals (allowed <= 20%)"]
    # always-coast's DS is the entry roll (eval/testing/validity.py ROLL_POLICY): its goals count
    assert failures(_table(**ok, **{"always-coast": (0.0, -500.0, 0.0, 0.3)})) == []
    assert failures(_table(**ok, **{"always-coast": (0.33, 1200.0, 0.0, 0.4)})) == [
        "always-coast reaches 33% of goals (allowed <= 20%)"]


def test_the_driving_score_criteria_on_hand_made_numbers():
    """Both autopilots DS >= 0.9 with no collision, every degenerate policy DS <= 0.1 (its return
    no longer judged); a table without DS fails as not measured; the safe non-turner's DS shows."""
    ok = {"autopilot": (1.0, 2000.0, 0.0, 0.9), "autopilot-discrete": (0.9, 1500.0, 0.0, 0.93),
          "safe-non-turner": (0.5, 900.0, 0.0, 0.62), "always-brake": (0.0, -550.0, 0.0, 0.1),
          "random": (0.0, 1900.0, 0.0, 0.02)}  # a return near the autopilot's is no failure now
    assert failures(_table(**ok)) == []
    assert failures(_table(**(ok | {"autopilot": (1.0, 2000.0, 0.0, 0.899)}))) == [
        "autopilot scores DS 0.899 (needs >= 0.90)"]
    assert failures(_table(**(ok | {"always-brake": (0.0, -550.0, 0.0, 0.101)}))) == [
        "always-brake scores DS 0.101 (allowed <= 0.10)"]
    assert failures(_table(**(ok | {"autopilot-discrete": (0.95, 1500.0, 0.5, 0.95)}))) == [
        "autopilot-discrete collides (0.50 collision steps per AC)"]  # a high DS is not enough
    unmeasured = failures(_table(**ok).drop(columns="DS"))
    assert unmeasured[0] == "autopilot: no driving score measured (needs >= 0.90)" and len(unmeasured) == 4
    line = score_line(_table(**ok))
    assert line.endswith("autopilot 0.900, autopilot-discrete 0.930, safe-non-turner 0.620, "
                         "best degenerate always-brake 0.100")
    assert "| safe-non-turner | 0.620 |" in format_table(_table(**ok).assign(
        RC=0.7, success=0.5, DISTANCE=0.0, CV=0.0, CO=0.0, CP=np.nan, OS=0.0, RL=0.0))


def test_reference_rows_carry_the_driving_score():
    rows = run_policy(_quiet("env_1"), "autopilot", 1, episodes=1, steps=40)
    (r,) = rows.itertuples()
    assert 0.0 < r.RC < 1.0 and r.IP == 1.0 and r.DS == pytest.approx(r.RC * r.IP)
    assert r.success == 0.0 and r.CO_events == 0 and np.isnan(r.CP_events)  # 40 steps: not there yet


def test_the_criteria_catch_a_scenario_that_an_open_loop_policy_solves():
    # env_1 without jitter and without the walls' reason to matter: full throttle keeps its lane
    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter())
    rows = check_scenario(sc, 2, episodes=1, steps=300,
                          policies=("autopilot", "always-forward"))
    problems = failures(summarize(rows))
    assert any(p.startswith("always-forward reaches") for p in problems), problems


def test_reference_rows_carry_ttfc_and_speed_like_the_test_metrics():
    rows = check_scenario("env_1", 2, episodes=1, steps=100,
                          policies=("always-brake", "always-forward", "full-right"))
    dt = load_scenario("env_1").dt
    hit = rows["collision_steps"] > 0
    assert rows.loc[~hit, "TTFC"].isna().all()  # no collision: no TTFC ("--")
    assert ((rows.loc[hit, "TTFC"] >= dt) & (rows.loc[hit, "TTFC"] <= 100 * dt)).all()
    assert hit[rows["policy"] == "full-right"].all()  # steering into the wall collides
    speed = rows.groupby("policy")["SPEED"].mean()  # km/h
    assert speed["always-brake"] < speed["always-forward"] and speed["always-forward"] > 20


@pytest.mark.parametrize("speed,expected", [(0.0, False), (0.3, False), (0.6, True), (8.0, True)])
def test_a_pedestrian_walking_into_a_standing_car_is_not_its_collision(speed, expected):
    with World(_quiet("env_1"), 1, background=False) as w:
        w.reset(seed=0)
        route = w.routes[0]
        s0 = route.spawn_s + 30.0
        x, y = route.path.point_at(s0)
        h = route.path.heading_at(s0)
        # a person right at the car's front-left corner, inside its footprint
        px, py = x + 1.8 * math.cos(h) - 0.6 * math.sin(h), y + 1.8 * math.sin(h) + 0.6 * math.cos(h)
        w.snapshot = dataclasses.replace(
            w.snapshot, person_ids=["walker"], person_xy=np.array([[px, py]]),
            person_heading=np.zeros(1), person_speed=np.zeros(1))
        state = np.array([[x, y, h, speed]])
        ev = detect_all(["ac_0"], state, w.vehicle.length, w.vehicle.width, w.snapshot,
                        w.roadmap, [route], np.array([route.goal_s - s0]), 3.0)[0]
    assert ev.collision_pedestrian is expected


def test_a_held_controller_decides_every_rth_step_of_each_ac():
    from eval.testing.validity import held

    calls = []

    def act(ac):
        calls.append(ac)
        return (float(len(calls)), 0.0)

    repeat = held(act, 3)
    got = [repeat(ac) for _ in range(4) for ac in ("ac_0", "ac_1")]
    assert calls == ["ac_0", "ac_1", "ac_0", "ac_1"]  # their calls 0 and 3
    assert [a[0] for a in got[::2]] == [1, 1, 1, 3] and [a[0] for a in got[1::2]] == [2, 2, 2, 4]
    assert held(act, 1) is act
