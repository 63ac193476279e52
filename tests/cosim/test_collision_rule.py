"""The collision rule of task version 4 (docs/task.md, "Collision rule"): a contact is charged
once per event and the episode goes on; the per-step rule and the paper's collision-ends rule are
one option away; solid cars; who is charged; route completion as driven."""

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from cosim.events import Events, reward_terms
from cosim.scenario import Contact, RewardWeights, SpawnJitter, load_scenario
from cosim.score import episode_score
from cosim.world import World


def _straight(**changes):
    base = load_scenario("env_1")
    return dataclasses.replace(base, spawn_jitter=SpawnJitter(), **changes)


def _press_into_parked_car(sc, steps=120):
    """One AC on Straight at full throttle towards a car parked 30 m ahead on its lane."""
    with World(sc, 1, background=False) as w:
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        w.bridge.place_car("stopped", x + 30 * math.cos(h), y + 30 * math.sin(h), h, "st_e")
        out = []
        for _ in range(steps):
            if not w.active:
                break
            out.append(w.step({"ac_0": (1.0, 0.0)})["ac_0"])
    return out


def test_default_charges_a_contact_once_per_event_and_the_episode_goes_on():
    out = _press_into_parked_car(_straight())
    contact = [k for k, r in enumerate(out) if r.events.collision_vehicle]
    events = [k for k, r in enumerate(out) if r.events.event_vehicle]
    assert len(out) == 120 and not any(r.terminated for r in out), "the episode goes on"
    assert len(contact) > 8, "the AC keeps pushing into the car it cannot pass (and bouncing off)"
    # the first contact step is an event; the same car again counts only 5 s (50 steps) later
    assert events[0] == contact[0]
    assert all(b - a >= 50 for a, b in zip(events, events[1:], strict=False))
    assert 2 <= len(events) <= 1 + (contact[-1] - contact[0]) // 50
    charged = [k for k, r in enumerate(out) if r.reward_terms["collision"] != 0.0]
    assert charged == events
    assert all(out[k].reward_terms["collision"] == -50.0 for k in events)


def test_bouncing_off_a_parked_car_earns_no_speed_credit_and_pays_less_than_waiting():
    """Task version 5: the speed term F pays only on new ground. Put back 1 m and driving it
    again, a car pushing into a parked car would earn F on every re-driven metre (about 14 per
    bounce at 7 m/s), as much as its charge of -50 every 5 s; now it earns none."""
    out = _press_into_parked_car(_straight(), steps=300)
    first = next(k for k, r in enumerate(out) if r.events.collision_vehicle)
    after = out[first + 1:]
    assert sum(r.events.collision_vehicle for r in after) > 10, "it keeps bouncing"
    bounces = sum(r.events.collision_vehicle for r in after)
    speed_credit = sum(r.reward_terms["efficiency"] - 10.0 * r.events.progress for r in after)
    # F on the last centimetres before the first contact point only, not on any re-driven metre
    assert speed_credit < 14.0 < 14.0 * bounces
    assert sum(not r.events.new_ground for r in after if r.events.speed > 0.0) > 5 * bounces
    push = sum(r.reward for r in out)
    with World(_straight(), 1, background=False) as w:  # the same car, braking 15 m before it
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        w.bridge.place_car("stopped", x + 30 * math.cos(h), y + 30 * math.sin(h), h, "st_e")
        wait = 0.0
        for _ in range(300):
            ax, ay, _, _ = w.ac_state("ac_0")
            gap = (x - ax) * math.cos(h) + (y - ay) * math.sin(h) + 30.0
            r = w.step({"ac_0": (1.0, 0.0) if gap > 15.0 else (-1.0, 0.0)})["ac_0"]
            assert not r.events.collision
            wait += r.reward
    assert push < wait - 50.0 * sum(r.events.event_vehicle for r in out) + 50.0


def test_the_speed_term_pays_only_on_new_ground():
    weights = RewardWeights()
    ahead = Events(route_speed=7.0, progress=0.7)
    again = Events(route_speed=7.0, progress=0.7, new_ground=False)
    against = Events(route_speed=-7.0, progress=-0.7, new_ground=False)
    assert reward_terms(ahead, weights, 7.0)["efficiency"] == pytest.approx(10.0 * (0.7 + 1.0))
    assert reward_terms(again, weights, 7.0)["efficiency"] == pytest.approx(10.0 * 0.7), "progress, no F"
    assert reward_terms(against, weights, 7.0)["efficiency"] == pytest.approx(10.0 * (-0.7 - 1.0)), "F < 0 stays"


def test_the_per_step_rule_charges_every_contact_step():
    out = _press_into_parked_car(_straight(contact=Contact(charge="step")))
    contact = [r for r in out if r.events.collision_vehicle]
    assert contact and all(r.reward_terms["collision"] == -50.0 for r in contact)
    assert sum(r.events.event_vehicle for r in out) < len(contact), "events are still counted"


def test_the_papers_rule_ends_the_episode_at_the_first_contact():
    base = _straight()
    out = _press_into_parked_car(
        dataclasses.replace(base, termination=dataclasses.replace(base.termination, on_collision=True))
    )
    assert out[-1].terminated and out[-1].events.collision_vehicle
    assert sum(r.reward_terms["collision"] for r in out) == -50.0


def test_a_solid_car_stops_the_ac_where_it_was_and_the_blocked_step_gains_nothing():
    out = _press_into_parked_car(_straight(), steps=80)
    hits = [r for r in out if r.events.collision_vehicle]
    assert hits
    for r in hits:
        assert r.events.progress == 0.0 and r.events.speed == 0.0
        assert r.reward_terms["efficiency"] == 0.0
    # without solid cars the AC drives through the car for one charge
    through = _press_into_parked_car(_straight(solid_cars=False), steps=80)
    assert max(r.x for r in through) > max(r.x for r in out) + 5.0
    assert sum(r.events.event_vehicle for r in through) == 1


@pytest.mark.parametrize("back_off", [0.0, 1.0])
def test_a_blocked_ac_backs_off_and_can_steer_round_what_stopped_it(back_off, monkeypatch):
    """Put back exactly where it was, standing, a car with no reverse cannot turn away from what
    it touches (its heading turns only while it moves, and each move into it is undone): it is
    trapped. Put back BACK_OFF metres behind, it steers round the parked car."""
    import cosim.world

    monkeypatch.setattr(cosim.world, "BACK_OFF", back_off)
    with World(_straight(), 1, background=False) as w:
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        car = np.array([x + 30 * math.cos(h), y + 30 * math.sin(h)])
        w.bridge.place_car("stopped", *car, h, "st_e")
        touched, past, lat, turn = False, False, 0.0, 0.0
        for _ in range(250):
            # straight at it; once it has touched, into the lane on its left (3.2 m) and round it
            steer = -float(np.clip(0.3 * (3.2 - lat) - 1.0 * turn, -0.5, 0.5)) if touched else 0.0
            r = w.step({"ac_0": (0.6, steer)})["ac_0"]
            touched |= r.events.collision_vehicle
            ax, ay, ah, _ = w.ac_state("ac_0")
            lat = -(ax - car[0]) * math.sin(h) + (ay - car[1]) * math.cos(h)
            turn = math.remainder(ah - h, math.tau)
            past |= (ax - car[0]) * math.cos(h) + (ay - car[1]) * math.sin(h) > 6.0
            if past or not w.active:
                break
    assert touched
    assert past == (back_off > 0), "backed off it gets round the car; put back in place it stays stuck"


def _bare_world(**contact):
    """A World that is never reset: enough for the per-actor event count."""
    w = World(_straight(contact=Contact(**contact)), 1, background=False)
    w._events_seen, w._charged = [{}], [{}]
    w._state[0] = (0.0, 0.0, 0.0, 5.0)  # at the origin, facing +x, moving
    return w


def _count(w, t, touching, others=None):
    ids = [o for _, o in touching] if others is None else list(others)
    xy = np.array([[4.0, 0.0]] * len(ids)) if others is None else np.array(list(others.values()))
    w.snapshot = SimpleNamespace(time=t, vehicle_ids=ids, vehicle_xy=xy)
    ev = Events(touching=list(touching))
    w._count_events(0, ev)
    return ev


def test_the_same_actor_within_5_s_is_one_event_and_another_actor_is_its_own():
    w = _bare_world()
    assert _count(w, 10.0, [("vehicle", "car")]).event_vehicle
    assert not _count(w, 12.0, [("vehicle", "car")]).event_vehicle, "the same car 2 s later"
    assert not _count(w, 14.9, [("vehicle", "car")]).event_vehicle
    two = _count(w, 13.0, [("vehicle", "car"), ("object", "pole_1")])
    assert two.event_object and not two.event_vehicle, "a pole is another actor"
    assert _count(w, 13.5, [("vehicle", "other")]).event_vehicle, "another car is another event"
    assert _count(w, 15.0, [("vehicle", "car")]).event_vehicle, "5 s after its last event"
    w.close()


def test_at_fault_charges_only_the_car_that_drove_into_the_other():
    w = _bare_world()  # the default since task version 5
    assert w.scenario.contact.fault == "at_fault"
    hit = _count(w, 1.0, [("vehicle", "ahead")], {"ahead": (4.0, 0.0)})
    assert hit.event_vehicle and hit.charged_vehicle and hit.charged_event
    behind = _count(w, 1.0, [("vehicle", "behind")], {"behind": (-4.0, 0.0)})
    assert behind.event_vehicle, "the test's score counts every event the car is in"
    assert not behind.charged_vehicle and not behind.charged_event, "hit from behind: not its fault"
    w._state[0, 3] = 0.0  # standing: hit, not hitting
    standing = _count(w, 9.0, [("vehicle", "ahead")], {"ahead": (4.0, 0.0)})
    assert standing.event_vehicle and not standing.charged_vehicle
    w._state[0, 3] = 5.0  # hit from behind at 20 s, then drives into the same car 2 s later
    assert not _count(w, 20.0, [("vehicle", "x")], {"x": (-4.0, 0.0)}).charged_vehicle
    late = _count(w, 22.0, [("vehicle", "x")], {"x": (4.0, 0.0)})
    assert late.charged_vehicle and not late.event_vehicle, "its own fault is charged; the score's event began at 20 s"
    both = _bare_world(fault="both")
    both._state[0, 3] = 0.0
    ev = _count(both, 1.0, [("vehicle", "behind")], {"behind": (-4.0, 0.0)})
    assert ev.event_vehicle and ev.charged_vehicle
    w.close()
    both.close()


def test_the_reward_charges_the_cars_own_events_and_the_score_counts_all():
    weights = RewardWeights()
    mine = Events(event_vehicle=True, charged_vehicle=True)
    not_mine = Events(event_vehicle=True)
    assert reward_terms(mine, weights, 7.0)["collision"] == weights.collision == -50.0
    assert reward_terms(not_mine, weights, 7.0)["collision"] == 0.0
    for kind in ("pedestrian", "object"):  # a person or a pole: always the AC's own
        assert reward_terms(Events(**{f"event_{kind}": True}), weights, 7.0)["collision"] == -50.0
    one, clean = episode_score(1.0, True, vehicle=1), episode_score(1.0, True)
    assert one["DS"] == pytest.approx(0.6 * clean["DS"]) and one["success"] == 0.0 < clean["success"]


def test_route_completion_counts_the_route_driven():
    with World(_straight(), 1, background=False) as w:
        w.reset(seed=0)
        route = w.route("ac_0")
        length = route.goal_s - route.spawn_s
        r = None
        while True:
            r = w.step({"ac_0": (0.4, 0.0)})["ac_0"]
            if r.events.distance_to_goal <= length / 2:
                break
        assert r.events.route_completion == pytest.approx(0.5, abs=0.02)
        assert 0.5 * length - r.events.distance_to_goal == pytest.approx(0.0, abs=1.5)
        for _ in range(60):  # braking to a stop, then standing: what was driven, no more
            r = w.step({"ac_0": (-1.0, 0.0)})["ac_0"]
        assert r.events.speed == 0.0
        driven = (length - r.events.distance_to_goal) / length
        assert 0.5 < r.events.route_completion == pytest.approx(driven, abs=1e-6)
