"""The state track (``obs="state"``, cosim/state.py; docs/task.md, "The state track"): the
vector's content in hand-made situations, the API checks, no PyBullet mirror, frame stacks
refused, and a state-trained policy sharing a camera test env builds the same vector."""

import math

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import cosim
from cosim.roadmap import road_map
from cosim.scenario import load_scenario
from cosim.state import (
    NEIGHBOUR_RANGE,
    PATH_AHEAD,
    PATH_SCALE,
    REL_SPEED_SCALE,
    SIGNAL_RANGE,
    SPEED_SCALE,
    STATE_DIM,
    STATE_LAYOUT,
    agent_state,
    is_state_space,
    state_space,
    state_vectors,
)
from cosim.sumo_bridge import Snapshot

L = STATE_LAYOUT


class _World:
    """What cosim.state reads of a cosim.world.World: a snapshot, each AC's pose and route."""

    def __init__(self, scenario: str, poses: dict, cars=(), people=(), signals=None):
        sc = load_scenario(scenario)
        self.vehicle = sc.vehicle
        self._routes = road_map(sc).routes
        self._poses = poses  # ac -> (x, y, heading, speed)
        ids = list(poses) + [c[0] for c in cars]
        rows = [p for p in poses.values()] + [c[1:] for c in cars]
        arr = np.array(rows, dtype=float).reshape(-1, 4)
        parr = np.array([p[1:] for p in people], dtype=float).reshape(-1, 4)
        self.snapshot = Snapshot(
            time=0.0, vehicle_ids=ids, vehicle_xy=arr[:, :2], vehicle_heading=arr[:, 2],
            vehicle_speed=arr[:, 3], vehicle_length=np.full(len(ids), 5.0), vehicle_width=np.full(len(ids), 2.0),
            vehicle_is_ac=np.array([i in poses for i in ids]), person_ids=[p[0] for p in people],
            person_xy=parr[:, :2], person_heading=parr[:, 2], person_speed=parr[:, 3], signals=signals or {})

    def ac_state(self, ac):
        return self._poses[ac]

    def route(self, ac):
        return self._routes[int(ac.split("_")[1])]


def _on_route(scenario: str, slot: int, s: float, left: float = 0.0, turn: float = 0.0, speed: float = 0.0):
    """A pose ``left`` metres left of route ``slot``'s centreline at arc length ``s``, heading
    ``turn`` radians from the route's direction."""
    route = road_map(load_scenario(scenario)).routes[slot]
    (x, y), h = route.path.point_at(s), route.path.heading_at(s)
    return (float(x - math.sin(h) * left), float(y + math.cos(h) * left), h + turn, speed)


def test_an_ac_on_its_straight_route_sees_the_centreline_ahead_and_a_car_10m_ahead():
    ego = _on_route("env_1", 0, 50.0, speed=5.0)  # Straight: route 0 runs east, no signal
    x, y, h, v = ego
    ahead = ("car_a", x + 10.0, y, h, 5.0)  # 10 m ahead, same speed: relative velocity 0
    far = ("car_b", x + 60.0, y, h, 5.0)  # beyond the 50 m range: not observed
    person = ("p_0", x, y + 3.0, 0.0, 0.0)  # 3 m to the left, standing
    world = _World("env_1", {"ac_0": ego}, cars=[ahead, far], people=[person])
    (state,) = state_vectors(world, ["ac_0"], {"ac_0": (0.5, -0.2)})
    assert state.dtype == np.float32 and state.shape == (STATE_DIM,) and state in state_space()
    assert state[L["speed"]] == pytest.approx([5.0 / SPEED_SCALE])
    assert state[L["lateral"]] == pytest.approx([0.0], abs=1e-5)
    assert state[L["heading_error"]] == pytest.approx([0.0, 1.0], abs=1e-5)
    expected = np.array([[d / PATH_SCALE, 0.0] for d in PATH_AHEAD]).ravel()
    np.testing.assert_allclose(state[L["path"]], expected, atol=1e-5)  # straight ahead
    route = world.route("ac_0")
    assert state[L["goal"]] == pytest.approx([(route.goal_s - 50.0) / (route.goal_s - route.spawn_s)])
    assert state[L["control"]] == pytest.approx([0.5, -0.2])
    assert state[L["signal"]] == pytest.approx([1, 0, 0, 0, 1])  # none
    cars = state[L["vehicles"]].reshape(-1, 5)
    np.testing.assert_allclose(cars[0], [1.0, 10.0 / NEIGHBOUR_RANGE, 0.0, 0.0, 0.0], atol=1e-5)
    assert not cars[1:].any()  # the ego is not its own neighbour; the far car is out of range
    people = state[L["pedestrians"]].reshape(-1, 5)
    np.testing.assert_allclose(people[0], [1.0, 0.0, 3.0 / NEIGHBOUR_RANGE, -5.0 / REL_SPEED_SCALE, 0.0],
                               atol=1e-5)
    assert not people[1:].any()


def test_offset_heading_error_neighbours_in_the_ego_frame_and_the_next_signal():
    """Four-way (signalised): route 0's stop line is at s = 110 (light X, link 11)."""
    route = road_map(load_scenario("env_3")).routes[0]
    ((stop_s, tls, link),) = route.signals
    ego = _on_route("env_3", 0, stop_s - 20.0, left=1.0, turn=0.1, speed=2.0)
    x, y, h, _ = ego
    # another AC 8 m to the ego's left (in its frame), heading opposite at 3 m/s
    nx, ny = x - 8.0 * math.sin(h), y + 8.0 * math.cos(h)
    poses = {"ac_0": ego, "ac_1": (nx, ny, h + math.pi, 3.0)}
    red = {tls: "G" * link + "r" + "G" * 3}
    world = _World("env_3", poses, signals=red)
    s0, s1 = state_vectors(world, ["ac_0", "ac_1"])
    assert s0[L["lateral"]] == pytest.approx([1.0 / 5.0], abs=1e-3)  # 1 m left of the centreline
    assert s0[L["heading_error"]] == pytest.approx([math.sin(0.1), math.cos(0.1)], abs=1e-5)
    gap = (20.0 - world.vehicle.length / 2) / SIGNAL_RANGE
    assert s0[L["signal"]] == pytest.approx([0, 1, 0, 0, gap], abs=2e-3)  # red, front bumper to the line
    assert s0[L["control"]] == pytest.approx([0.0, 0.0])  # no previous step
    car = s0[L["vehicles"]][:5]
    v_rel = np.array([-3.0 - 2.0, 0.0]) / REL_SPEED_SCALE  # both along the ego's x axis
    np.testing.assert_allclose(car, [1.0, 0.0, 8.0 / NEIGHBOUR_RANGE, *v_rel], atol=1e-5)
    car_seen_by_1 = s1[L["vehicles"]][:5]  # the same pair from the other side: ac_0 to its right
    np.testing.assert_allclose(car_seen_by_1, [1.0, 0.0, 8.0 / NEIGHBOUR_RANGE, *v_rel], atol=1e-5)
    world.snapshot.signals = {tls: "r" * link + "G" + "r" * 3}
    assert state_vectors(world, ["ac_0"])[0][L["signal"]][:4] == pytest.approx([0, 0, 0, 1])  # green
    world._poses["ac_0"] = _on_route("env_3", 0, stop_s + 1.0)  # its centre past the stop line
    assert state_vectors(world, ["ac_0"])[0][L["signal"]] == pytest.approx([1, 0, 0, 0, 1])
    world._poses["ac_0"] = _on_route("env_3", 0, stop_s - SIGNAL_RANGE - 10.0)  # too far to see
    assert state_vectors(world, ["ac_0"])[0][L["signal"]] == pytest.approx([1, 0, 0, 0, 1])


def test_the_state_env_passes_the_pettingzoo_api_test_without_a_mirror(monkeypatch):
    import cosim.mirror

    def no_mirror(*args, **kwargs):
        raise AssertionError("the state track must not build the PyBullet mirror")

    monkeypatch.setattr(cosim.mirror.Mirror, "__init__", no_mirror)
    env = cosim.parallel_env("env_3", num_agents=3, action_types=["discrete", "continuous", "discrete"],
                             horizon=20, seed=0, obs="state")
    try:
        assert is_state_space(env.observation_space("ac_0")) and not env.unwrapped.camera
        parallel_api_test(env, num_cycles=25)
        assert env.unwrapped.mirror is None
    finally:
        env.close()


@pytest.mark.parametrize("action_type", ["discrete", "continuous"])
def test_the_state_single_env_passes_gymnasium_check_env(action_type):
    env = cosim.single_env("env_1", action_type=action_type, obs="state", horizon=20)
    try:
        assert env.observation_space.shape == (STATE_DIM,)
        check_env(env, skip_render_check=True)
        assert env.parallel.unwrapped.mirror is None
    finally:
        env.close()


def test_a_frame_stack_with_the_state_is_refused_naming_the_fix():
    from eval.training.config import TrainError, make_config

    with pytest.raises(ValueError, match=r"obs='state' observes one state vector.*use frame_stack=1"):
        cosim.parallel_env("env_1", obs="state", frame_stack=4)
    with pytest.raises(TrainError, match="--obs state observes one state vector"):
        make_config("dqn", "env_1", "smoke", obs="state", frame_stack=4)
    cfg = make_config("ppo", "env_2", "standard", obs="state")  # the preset's 4 frames are the camera's
    assert cfg.frame_stack == 1 and cfg.agent_config.hidden == (256, 256)
    assert make_config("ppo", "env_2", "standard").agent_config.hidden == (64, 64)  # image runs: unchanged
    assert make_config("ppo", "env_2", "smoke", obs="state", hyper={"hidden": "[32]"}).agent_config.hidden == (32,)


def test_the_training_env_of_a_state_run_has_its_cameras_off():
    from eval.training.config import make_config
    from eval.training.trainer import make_env

    env = make_env(make_config("dqn", "env_2", "smoke", agents=2, obs="state").to_dict())
    try:
        assert not env.unwrapped.camera and env.observation_space("ac_1") == state_space()
        obs, _ = env.reset(seed=0)
        assert env.unwrapped.mirror is None and obs["ac_0"].shape == (STATE_DIM,)
    finally:
        env.close()


def test_a_state_policy_in_a_camera_test_env_sees_its_training_observation():
    """`cosim test` drives every AC in one env that gives camera frames; a state-trained AC's
    policy (eval.testing.loading.drive -> StatePolicy) builds, from the env's world, what the
    state env gives, step after step (same seed, same actions)."""
    from eval.testing.loading import drive
    from eval.testing.rollout import StatePolicy

    actions = [{"ac_0": 3, "ac_1": 4}, {"ac_0": 5, "ac_1": 3}, {"ac_0": 3, "ac_1": 1}] * 2
    state_env = cosim.parallel_env("env_3", num_agents=2, horizon=10, seed=0, obs="state")
    try:
        first, _ = state_env.reset(seed=3)
        seen = [first] + [state_env.step(a)[0] for a in actions]
    finally:
        state_env.close()

    class Spy:
        algo = "dqn"
        observation_space = state_space()
        action_space = None

        def __init__(self):
            self.got = []

        def act(self, obs, deterministic=True):
            self.got.append(np.array(obs, copy=True))
            return 3

    camera_env = cosim.parallel_env("env_3", num_agents=2, horizon=10, seed=0, image_size=32)
    try:
        spies = {a: Spy() for a in camera_env.possible_agents}
        policies = {a: drive(spies[a], env=camera_env, slot=a) for a in spies}
        assert all(isinstance(p, StatePolicy) for p in policies.values())
        obs, _ = camera_env.reset(seed=3)
        assert obs["ac_0"].shape == (32, 32, 3)  # the camera env's own observation
        for a in actions:
            for ac, p in policies.items():
                p.act(obs[ac])
            obs = camera_env.step(a)[0]
        for ac, p in policies.items():
            p.act(obs[ac])
        for ac, spy in spies.items():
            np.testing.assert_allclose(np.array(spy.got), np.array([o[ac] for o in seen]), atol=1e-5)
            assert agent_state(camera_env, ac) == pytest.approx(seen[-1][ac], abs=1e-5)
    finally:
        camera_env.close()
