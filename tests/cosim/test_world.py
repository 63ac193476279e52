"""The world in the real simulator: traffic, events on purpose, determinism, SUMO errors."""

import dataclasses
import math

import numpy as np
import pytest

from cosim.controller import Autopilot
from cosim.errors import EnvStateError, SumoError
from cosim.scenario import SpawnJitter, load_scenario
from cosim.world import World

ENVS = ["env_1", "env_2", "env_3", "env_4", "env_5"]


def drive(world: World, steps: int, seed: int):
    results = world.reset(seed=seed)
    pilots = {a: Autopilot(world, a) for a in world.ac_ids}
    final = dict(results)
    events = {a: set() for a in world.ac_ids}
    cars = peds = 0
    for _ in range(steps):
        if not world.active:
            break
        out = world.step({a: tuple(pilots[a].act()) for a in world.active})
        cars = max(cars, int((~world.snapshot.vehicle_is_ac).sum()))
        peds = max(peds, len(world.snapshot.person_ids))
        for a, r in out.items():
            final[a] = r
            ev = r.events
            for name in ("collision_vehicle", "collision_pedestrian", "collision_object", "off_road"):
                if getattr(ev, name):
                    events[a].add(name)
    return final, events, cars, peds


@pytest.mark.parametrize("env", ENVS)
def test_six_autopilot_acs_run_an_episode(env):
    with World(env, 6) as w:
        final, events, cars, peds = drive(w, w.scenario.horizon, seed=1)
    assert cars > 0, "background cars exist in every environment"
    if env in ("env_2", "env_3"):
        assert peds > 0
    else:
        assert peds == 0
    good = [
        a for a in w.ac_ids
        if (final[a].events.goal_reached or final[a].events.distance_to_goal < 15.0) and not events[a]
    ]
    assert len(good) >= 4, f"only {good} reached (or got within 15 m of) their goals cleanly: {events}"


def _straight_world(**kw) -> World:
    # no spawn jitter: these tests place and drive the car on exact, hand-made poses
    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter())
    return World(sc, 1, background=False, **kw)


def test_driving_into_a_background_car_and_passing_beside_it():
    base = load_scenario("env_1")
    paper_rule = dataclasses.replace(base, spawn_jitter=SpawnJitter(),
                                     termination=dataclasses.replace(base.termination, on_collision=True))
    with World(paper_rule, 1, background=False) as w:  # --collisions end: a collision ends it
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        w.bridge.place_car("stopped", x + 30, y, h, "st_e")
        hits = [w.step({"ac_0": (1.0, 0.0)})["ac_0"] for _ in range(60) if w.active]
        assert hits[-1].events.collision_vehicle and hits[-1].events.hit == "stopped"
        assert hits[-1].terminated and not w.active
    with _straight_world() as w:
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        # 0.5 m between the two cars' sides
        w.bridge.place_car("beside", x + 30, y + 1.8 + 0.5, h, "st_e")
        out = [w.step({"ac_0": (1.0, 0.0)})["ac_0"] for _ in range(60)]
        assert max(r.x for r in out) > x + 40, "it drove past the parked car"
        assert not any(r.events.collision for r in out)



@pytest.mark.parametrize("solid", [False, True])
def test_solid_cars_stop_an_ac_at_a_car_ahead(solid):
    """Scenario.solid_cars: an AC that drives into a parked car is put back 1 m behind where it
    was before that step, standing, and never gets past it; without the option it drives
    through."""
    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter(), solid_cars=solid)
    with World(sc, 1, background=False) as w:
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        w.bridge.place_car("stopped", x + 30, y, h, "st_e")
        out = []
        for _ in range(80):
            before = w.ac_state("ac_0")
            r = w.step({"ac_0": (1.0, 0.0)})["ac_0"]
            out.append((before, r, w.ac_state("ac_0")))
    hits = [(b, r, a) for b, r, a in out if r.events.collision_vehicle]
    assert hits and all(r.events.hit == "stopped" for _, r, _ in hits)
    if solid:
        for before, _r, after in hits:  # put back 1 m behind where it was (World.BACK_OFF), standing
            assert after[2] == pytest.approx(before[2]) and after[3] == 0.0
            back = (before[0] - after[0]) * math.cos(h) + (before[1] - after[1]) * math.sin(h)
            assert back == pytest.approx(1.0, abs=1e-6)
        assert max(a[0] for _, _, a in out) < x + 30 - 4.0, "it never reached past the car's tail"
    else:
        assert max(a[0] for _, _, a in out) > x + 35, "it drove through the parked car"


def test_solid_cars_do_not_put_back_an_ac_touched_from_behind():
    """A car touching the AC from behind does not put the AC back: it keeps its move and speed."""
    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter(), solid_cars=True)
    with World(sc, 1, background=False) as w:
        w.reset(seed=0)
        x, y, h, _ = w.ac_state("ac_0")
        w.bridge.place_car("behind", x - 3.0 * math.cos(h), y - 3.0 * math.sin(h), h, "st_e")
        first = w.step({"ac_0": (1.0, 0.0)})["ac_0"]
        after = w.ac_state("ac_0")
    assert first.events.collision_vehicle and first.events.hit == "behind"
    moved = (after[0] - x) * math.cos(h) + (after[1] - y) * math.sin(h)
    assert moved > 0.5 and after[3] > 0.0

def test_driving_into_a_pedestrian_on_a_crossing_and_a_near_miss():
    # ac_0 straight through from the west, as placed by hand below (env_3's ac_0 turns left)
    base = load_scenario("env_3")
    straight = dataclasses.replace(base.acs[0], route=("tx_e", "xr_e"), depart_pos=-45.0)
    sc = dataclasses.replace(base, acs=(straight,), spawn_jitter=SpawnJitter())
    route = None
    with World(sc, 1, background=False) as w:
        w.reset(seed=0)
        route = w.route("ac_0")
        crossing = min(
            w.roadmap.crossings,
            key=lambda c: route.path.project(*c.shape.mean(axis=0))[1] ** 2
            + 1e3 * (route.path.project(*c.shape.mean(axis=0))[0] < route.spawn_s),
        )
        cx, cy = crossing.shape.mean(axis=0)
        s, _ = route.path.project(cx, cy)
        px, py = route.path.point_at(s)
        w.bridge.place_person("walker", px, py, "tx_e")
        out = [w.step({"ac_0": (0.6, 0.0)})["ac_0"] for _ in range(150) if w.active]
        assert any(r.events.collision_pedestrian and r.events.hit == "walker" for r in out)
    with World(sc, 1, background=False) as w:
        w.reset(seed=0)
        h = route.path.heading_at(s)
        # 0.5 m from the car's right side (car half width 0.9, person radius 0.3)
        off = 0.9 + 0.5 + 0.3
        w.bridge.place_person("walker", px + off * math.sin(h), py - off * math.cos(h), "tx_e")
        x0 = w.ac_state("ac_0")[0]
        out = [w.step({"ac_0": (0.6, 0.0)})["ac_0"] for _ in range(150) if w.active]
        assert max(r.x for r in out) > px + 5 > x0
        assert not any(r.events.collision_pedestrian for r in out)


def _pole_beside_straight(w: World):
    route = w.route("ac_0")
    poles = [o for o in w.roadmap.objects if o.kind == "pole"]
    ahead = [
        p for p in poles
        if 40 < route.path.project(*p.centre)[0] < 150 and route.path.project(*p.centre)[1] < 0
    ]
    return route, min(ahead, key=lambda p: route.path.project(*p.centre)[0])


def test_steering_off_the_road_into_a_pole_and_a_near_miss():
    with _straight_world() as w:
        w.reset(seed=0)
        route, pole = _pole_beside_straight(w)
        px, py = pole.centre
        # 15 m before the pole, on the lane, heading 20 degrees right of the road towards it
        start = px - 15.0 * math.cos(math.radians(20)), py + 15.0 * math.sin(math.radians(20))
        w.place_ac("ac_0", *start, -math.radians(20), 8.0)
        out = [w.step({"ac_0": (0.3, 0.0)})["ac_0"] for _ in range(40) if w.active]
        assert any(r.events.collision_object and r.events.hit == pole.id for r in out)
        assert any(r.events.off_road for r in out), "it left the road before hitting the pole"
    with _straight_world() as w:
        w.reset(seed=0)
        route, pole = _pole_beside_straight(w)
        px, py = pole.centre
        # parallel to the road, its right side 0.5 m from the pole's face (pole half size 0.15)
        w.place_ac("ac_0", px - 20, py + 0.15 + 0.5 + 0.9, 0.0, 8.0)
        out = [w.step({"ac_0": (0.3, 0.0)})["ac_0"] for _ in range(40) if w.active]
        assert max(r.x for r in out) > px + 5
        assert not any(r.events.collision_object for r in out)


def test_out_of_lane_and_off_road():
    with _straight_world() as w:
        w.reset(seed=0)
        for _ in range(30):
            r = w.step({"ac_0": (0.5, 0.0)})["ac_0"]
        assert not r.events.wrong_lane and not r.events.off_road
        # it ends at the wall beyond the far sidewalk (docs/scenarios.md), so step while active
        lefts = [w.step({"ac_0": (0.3, -0.3)})["ac_0"] for _ in range(25) if w.active]
        wrong = [r for r in lefts if r.events.wrong_lane and not r.events.off_road]
        assert wrong, "crossed into the opposite direction"
        assert wrong[-1].reward_terms["lane"] == pytest.approx(-0.5)
    with _straight_world() as w:
        w.reset(seed=0)
        for _ in range(30):
            w.step({"ac_0": (0.5, 0.0)})
        rights = [w.step({"ac_0": (0.3, 0.3)})["ac_0"] for _ in range(40) if w.active]
        assert any(r.events.off_road for r in rights)
        assert not any(r.events.wrong_lane and not r.events.off_road for r in rights[:3])


def test_reward_terms_follow_the_formula():
    with _straight_world() as w:
        w.reset(seed=0)
        for _ in range(20):
            r = w.step({"ac_0": (1.0, 0.0)})["ac_0"]
        ev = r.events
        assert ev.progress == pytest.approx(ev.speed * 0.1, rel=0.05)  # straight: dD = v dt
        expected = 10 * (ev.progress + min(ev.speed / 13.89, 1.0)) - 1.0
        assert r.reward == pytest.approx(expected)
        assert set(r.reward_terms) == {"collision", "efficiency", "lane", "step", "red_light"}
        assert r.reward_terms["red_light"] == 0.0  # weight 0 by default: the paper's reward


def _trajectory(seed: int, steps: int = 150):
    with World("env_3", 6) as w:
        w.reset(seed=seed)
        pilots = {a: Autopilot(w, a) for a in w.ac_ids}
        poses, background = [], []
        for _ in range(steps):
            if not w.active:
                break
            out = w.step({a: tuple(pilots[a].act()) for a in w.active})
            poses.append([(a, r.x, r.y, r.events.collision, r.events.off_road) for a, r in sorted(out.items())])
            snap = w.snapshot
            background.append(sorted(
                (vid, round(float(x), 3), round(float(y), 3))
                for vid, (x, y), ac in zip(snap.vehicle_ids, snap.vehicle_xy, snap.vehicle_is_ac, strict=True)
                if not ac
            ))
    return poses, background


def test_same_seed_same_run_different_seed_different_traffic():
    a_poses, a_bg = _trajectory(7)
    b_poses, b_bg = _trajectory(7)
    _, c_bg = _trajectory(8)
    assert a_poses == b_poses and a_bg == b_bg
    assert a_bg != c_bg


def test_step_before_reset_and_after_done():
    with _straight_world() as w:
        with pytest.raises(EnvStateError, match="before reset"):
            w.step({"ac_0": (0.0, 0.0)})
        w.reset(seed=0)
        w.place_ac("ac_0", *w.route("ac_0").goal_xy, 0.0)
        assert w.step({"ac_0": (0.0, 0.0)})["ac_0"].events.goal_reached
        with pytest.raises(EnvStateError, match="reset"):
            w.step({"ac_0": (0.0, 0.0)})


def test_sumo_error_surfaces_with_sumos_message_and_sumo_is_closed(tmp_path):
    bad = tmp_path / "bad.rou.xml"
    bad.write_text('<routes><flow id="f" from="no_such_edge" to="xs_s" begin="0" end="10" period="1"/></routes>')
    sc = load_scenario("env_3").with_overrides(demand=(bad,))
    w = World(sc, 1)
    with pytest.raises(SumoError, match="no_such_edge"):
        w.reset(seed=0)
    assert not w.bridge.running
    with World("env_1", 1) as ok:  # SUMO was closed: a new simulation starts in this process
        ok.reset(seed=0)
        assert ok.step({"ac_0": (0.0, 0.0)})


def test_malformed_demand_names_the_file(tmp_path):
    bad = tmp_path / "garbled.rou.xml"
    bad.write_text("<routes><flow id=")
    sc = load_scenario("env_1").with_overrides(demand=(bad,))
    with World(sc, 1) as w, pytest.raises(SumoError, match="garbled.rou.xml"):
        w.reset(seed=0)


def test_a_second_simulation_in_one_process_runs_in_a_child_process_with_identical_results():
    def run(world):
        world.reset(seed=5)
        pilot = Autopilot(world, "ac_0")
        return [world.step({"ac_0": tuple(pilot.act())})["ac_0"].x for _ in range(50)]

    with World("env_1", 1) as a:
        xs_a = run(a)
        with pytest.raises(SumoError, match="one SUMO simulation per process"):
            World("env_1", 1, backend="libsumo").reset(seed=0)
        with World("env_1", 1) as b:  # auto: libsumo is busy, so a child process's libsumo
            xs_b = run(b)
            assert b.bridge._ls is not a.bridge._ls
        assert a.step({"ac_0": (0.0, 0.0)})  # the first one is untouched
    assert xs_a == xs_b


def test_acs_enter_at_their_depart_speed():
    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter())
    assert all(ac.depart_speed == 8.0 for ac in sc.acs)
    with _straight_world() as w:
        w.reset(seed=0)
        x0, y0, h, speed = w.ac_state("ac_0")
        assert speed == pytest.approx(8.0)
        r = w.step({"ac_0": (0.0, 0.0)})["ac_0"]  # coasting: rolling resistance only
        moved = np.hypot(r.x - x0, r.y - y0)
        assert moved == pytest.approx(0.8, abs=0.02)
        assert r.events.speed == pytest.approx(8.0 - 0.1 * (0.3 + 0.0015 * 64), abs=1e-6)
    standing = dataclasses.replace(sc, acs=tuple(dataclasses.replace(a, depart_speed=0.0) for a in sc.acs))
    with World(standing, 1, background=False) as w:
        w.reset(seed=0)
        assert w.ac_state("ac_0")[3] == 0.0
        x0, y0 = w.ac_state("ac_0")[:2]
        r = w.step({"ac_0": (0.0, 0.0)})["ac_0"]
        assert (r.x, r.y) == pytest.approx((x0, y0))


def test_spawn_jitter_is_seeded_bounded_and_can_be_switched_off():

    assert load_scenario("env_1").spawn_jitter != SpawnJitter()  # on by default (docs/scenarios.md)
    sc = dataclasses.replace(load_scenario("env_1"), spawn_jitter=SpawnJitter())

    def spawn_poses(scenario, seed):
        with World(scenario, 3, background=False) as w:
            w.reset(seed=seed)
            return np.array([w.ac_state(a)[:3] for a in w.ac_ids]), [w.route(a) for a in w.ac_ids]

    exact, routes = spawn_poses(sc, 5)
    for (x, y, h), route in zip(exact, routes, strict=True):
        assert (x, y, h) == pytest.approx((*route.spawn_xy, route.spawn_heading))
    jittered = dataclasses.replace(sc, spawn_jitter=SpawnJitter(heading_deg=10.0, lateral=0.5))
    a, _ = spawn_poses(jittered, 5)
    b, _ = spawn_poses(jittered, 5)
    c, _ = spawn_poses(jittered, 6)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    for (x, y, h), route in zip(a, routes, strict=True):
        sx, sy = route.spawn_xy
        along = math.cos(route.spawn_heading) * (x - sx) + math.sin(route.spawn_heading) * (y - sy)
        side = -math.sin(route.spawn_heading) * (x - sx) + math.cos(route.spawn_heading) * (y - sy)
        assert abs(along) < 1e-9 and 0 < abs(side) <= 0.5
        assert 0 < abs(h - route.spawn_heading) <= math.radians(10.0)


def test_a_traci_simulation_catches_what_traci_raises_after_libsumo_was_imported():
    """libsumo's import replaces traci.exceptions.TraCIException with libsumo's class, but
    traci.connection raises its own: a TraCI bridge (a second simulation in one process, such as
    a training run's validation env) must still catch a vehicle that has left the simulation, as
    cars_see_acs asks for every car of the last step's subscription (a crash at 2026-11-29's
    cars-see pilot: "Vehicle 'ac_2' is not known")."""
    import libsumo  # noqa: F401  (the import that replaces the class)

    from cosim.sumo_bridge import SumoBridge

    with SumoBridge(load_scenario("env_1"), backend="traci") as bridge:
        bridge.start(0)
        assert bridge._car_half("nobody") is None
        with pytest.raises(bridge._errors):
            bridge._ls.vehicle.getWidth("nobody")
