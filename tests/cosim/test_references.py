"""The scripted references of docs/task.md, "Reference policies": the autopilot restricted to
Discrete(9) takes the turns the old steering mapping could not, and the safe non-turner
drives its lane and holds before its route's first turn.

Each case is one AC alone (no background cars, no pedestrians), so it measures the steering
and the controller, not the traffic; the full scenarios are checked by test_validity.py.
"""

import dataclasses
import math

import numpy as np
import pytest

from cosim.controller import Autopilot, NonTurner, first_turn_stop
from cosim.dynamics import VehicleParams, action_to_control
from cosim.roadmap import movement
from cosim.scenario import load_scenario
from cosim.world import World

SEED = 10_000  # a held-out seed (eval.testing.validity.HELD_OUT_SEED)


def _alone(env: str, slot: int):
    """The scenario with only the AC of ``slot`` (it becomes ac_0), nobody else on the road."""
    sc = load_scenario(env)
    return dataclasses.replace(sc, acs=(sc.acs[slot],), pedestrians=False)


def _drive(env: str, slot: int, pilot_cls=Autopilot, discrete: bool = True,
           vehicle: VehicleParams | None = None) -> dict:
    """One episode of one AC; discrete actions go through action_to_control as in the env."""
    with World(_alone(env, slot), 1, background=False, pedestrians=False, vehicle=vehicle) as w:
        w.reset(seed=SEED)
        pilot = pilot_cls(w, "ac_0")
        route = w.route("ac_0")
        out = {"steps": 0, "contact": 0, "lane": 0, "off_road": 0, "goal": False, "max_lat": 0.0,
               "actions": set(), "moves": movement(w.roadmap.net, route.edges), "hold_s": None}
        while w.active:
            if discrete:
                k = pilot.act_discrete()
                assert isinstance(k, int) and 0 <= k < 9
                out["actions"].add(k)
                control = action_to_control(k, True, "ac_0", w.vehicle)
            else:
                control = tuple(pilot.act())
            r = w.step({"ac_0": control})["ac_0"]
            ev = r.events
            out["steps"] += 1
            out["contact"] += ev.collision
            out["lane"] += ev.lane_violation
            out["off_road"] += ev.off_road
            out["goal"] |= ev.goal_reached
            out["max_lat"] = max(out["max_lat"], abs(route.path.project(r.x, r.y)[1]))
        out["s"] = route.arc_length(r.x, r.y)
        out["hold_s"] = getattr(pilot, "hold_s", None)
    return out


@pytest.mark.parametrize("env,slot,what", [
    ("env_2", 1, "right turn"),
    ("env_2", 5, "right turn"),
    ("env_4", 4, "roundabout, first exit"),
    ("env_4", 1, "roundabout, first exit"),
])
def test_a_discrete_only_autopilot_takes_the_turn_in_its_lane(env, slot, what):
    run = _drive(env, slot)
    assert run["moves"] == "right", what
    assert run["goal"], f"{env} ac_{slot} ({what}) did not reach its goal in {run['steps']} steps"
    assert run["contact"] == 0 and run["off_road"] == 0 and run["lane"] == 0, run
    assert run["max_lat"] < 1.0, f"left its lane by {run['max_lat']:.2f} m"  # spawn jitter is 0.5
    assert {1, 2, 7, 8} & run["actions"], "took the turn without a full-lock action"


def test_under_the_old_mapping_the_same_controller_leaves_its_lane_in_the_right_turn():
    """Fractions of 35 degrees (left = 17.5 degrees): the turn is too tight for the table."""
    old = VehicleParams(discrete_steer_reference=VehicleParams().max_steer)
    run = _drive("env_2", 1, vehicle=old)
    assert run["lane"] > 10 and run["max_lat"] > 2.0, run


def test_the_discrete_autopilot_is_about_as_fast_as_the_continuous_one():
    discrete, continuous = _drive("env_4", 4), _drive("env_4", 4, discrete=False)
    assert continuous["goal"] and discrete["goal"]
    assert discrete["steps"] <= 1.3 * continuous["steps"], (discrete["steps"], continuous["steps"])


def test_the_non_turner_holds_before_the_junction_of_its_turn():
    run = _drive("env_2", 1, NonTurner, discrete=False)  # right turn
    assert not run["goal"] and run["contact"] == 0 and run["lane"] == 0
    front = run["s"] + VehicleParams().length / 2
    assert run["hold_s"] - 4.0 < front < run["hold_s"], (front, run["hold_s"])  # behind the line


@pytest.mark.parametrize("env,slot", [("env_2", 2), ("env_1", 0)])
def test_the_non_turner_drives_a_straight_route_to_its_goal(env, slot):
    run = _drive(env, slot, NonTurner, discrete=False)
    assert run["moves"] == "straight" and run["hold_s"] is None
    assert run["goal"] and run["contact"] == 0


def test_the_first_turn_stop_is_the_end_of_the_approach_lane():
    with World(_alone("env_4", 0), 1, background=False, pedestrians=False) as w:
        route = w.route("ac_0")
        lane = w.roadmap.net.getLane(f"{route.edges[0]}_{route.sumo_lane}")  # the AC's own lane
        end = np.asarray(lane.getShape()[-1][:2])
        stop = first_turn_stop(w, "ac_0")  # xr_e -> ra_ws: the roundabout entry is a right turn
        assert stop is not None
        assert math.dist(route.path.point_at(stop), end) < 0.5
        assert route.spawn_s < stop < route.goal_s


def test_non_turners_on_the_main_road_do_not_wait_for_the_ramps_holding_ones():
    """env_5: ac_0 (ramp, a 62 degree turn onto the main road) holds at the ramp's end for good;
    ac_1 (main road) would give way to it at the merge (lower index first) and wait forever."""
    with World("env_5", 2, background=False) as w:
        w.reset(seed=SEED)
        pilots = {ac: NonTurner(w, ac) for ac in w.ac_ids}
        assert pilots["ac_0"].hold_s is not None and pilots["ac_1"].hold_s is None
        goal = dict.fromkeys(w.ac_ids, False)
        contact = 0
        while w.active:
            for ac, r in w.step({ac: tuple(pilots[ac].act()) for ac in w.active}).items():
                goal[ac] |= r.events.goal_reached
                contact += r.events.collision
    assert goal == {"ac_0": False, "ac_1": True} and contact == 0
