"""What an AC observes by default: its own last 4 camera frames (docs/task.md, "Observation").
The stacked spaces pass PettingZoo's and Gymnasium's API checks; the stack holds this AC's
last K frames, oldest first, and a reset starts it again."""

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import cosim

SMALL = dict(background=False, pedestrians=False, image_size=32)


def test_the_stacked_parallel_env_passes_the_pettingzoo_api_test():
    env = cosim.parallel_env("env_3", frame_stack=4, num_agents=3, action_types=["discrete", "continuous", "discrete"],
                             horizon=20, seed=0, image_size=32)
    try:
        assert env.observation_space("ac_0").shape == (32, 32, 12)
        parallel_api_test(env, num_cycles=25)
    finally:
        env.close()


@pytest.mark.parametrize("action_type", ["discrete", "continuous"])
def test_the_stacked_single_env_passes_gymnasium_check_env(action_type):
    env = cosim.single_env("env_1", action_type=action_type, frame_stack=4, horizon=20, image_size=48)
    try:
        assert env.observation_space.shape == (48, 48, 12)
        check_env(env, skip_render_check=True)
    finally:
        env.close()


def test_the_stack_is_the_last_k_frames_of_this_ac_and_reset_clears_it():
    """Each AC's stack is made of the frames its own camera returned, oldest first; after a
    reset it is K copies of the new first frame (nothing of the last episode)."""
    k = 3
    raw = cosim.parallel_env("env_3", num_agents=2, horizon=10, seed=0, **SMALL)
    stacked = cosim.parallel_env("env_3", frame_stack=k, num_agents=2, horizon=10, seed=0, **SMALL)
    try:
        frames = {a: [] for a in raw.possible_agents}
        obs_raw, _ = raw.reset(seed=5)
        obs, _ = stacked.reset(seed=5)
        for a in raw.possible_agents:
            frames[a] += [obs_raw[a]] * k  # an episode starts with k copies of its first frame
            assert all((obs[a][..., 3 * j:3 * j + 3] == obs_raw[a]).all() for j in range(k))
        drive = {a: 3 for a in raw.possible_agents}  # forward: the camera image changes
        for _ in range(4):
            obs_raw, *_ = raw.step(drive)
            obs, *_ = stacked.step(drive)
            for a in raw.possible_agents:
                frames[a].append(obs_raw[a])
                np.testing.assert_array_equal(obs[a], np.concatenate(frames[a][-k:], axis=-1))
        assert not (frames["ac_0"][-1] == frames["ac_1"][-1]).all()  # two cameras, two stacks
        obs_raw, _ = raw.reset(seed=6)
        obs, _ = stacked.reset(seed=6)
        np.testing.assert_array_equal(obs["ac_0"], np.concatenate([obs_raw["ac_0"]] * k, axis=-1))
    finally:
        raw.close()
        stacked.close()


def test_one_frame_is_the_camera_itself_and_a_bad_k_is_refused():
    env = cosim.parallel_env("env_1", num_agents=1, **SMALL)
    try:
        assert isinstance(env, cosim.CosimParallelEnv) and env.observation_space("ac_0").shape == (32, 32, 3)
    finally:
        env.close()
    with pytest.raises(ValueError, match="frame_stack must be an int >= 1"):
        cosim.parallel_env("env_1", num_agents=1, frame_stack=0, **SMALL)


# -- the nav variant: image + measurements -------------------------------------------------

def test_the_nav_command_switches_at_the_documented_distance_on_a_hand_made_route():
    """A route whose junction spans arc lengths 100..120 m (goal at 150 m, spawn at 20 m):
    "follow" until 50 m before the junction, the movement through it, "follow" after."""
    from cosim.wrappers import NAV_COMMANDS, NAV_SWITCH_DISTANCE, RouteGuide, nav_measurements

    assert NAV_SWITCH_DISTANCE == 50.0
    guide = RouteGuide(entry_s=100.0, exit_s=120.0, movement="left", route_length=130.0, goal_s=150.0)
    at = lambda s: guide.command(150.0 - s)  # noqa: E731 - the command at arc length s
    assert [at(s) for s in (20.0, 49.9, 50.0, 99.0, 110.0, 119.9, 120.0, 149.0)] == [
        "follow", "follow", "left", "left", "left", "left", "follow", "follow"]
    m = guide.measurements(speed=13.89, distance_to_goal=65.0)  # at s = 85: inside the 50 m
    assert m.dtype == np.float32 and m.shape == (2 + len(NAV_COMMANDS),)
    assert m[0] == pytest.approx(1.0) and m[-1] == pytest.approx(0.5)
    assert NAV_COMMANDS[int(np.argmax(m[1:-1]))] == "left" and m[1:-1].sum() == 1
    straight = RouteGuide(0.0, 0.0, "straight", 100.0, 100.0)  # one edge: no junction
    assert straight.command(50.0) == "follow"
    np.testing.assert_array_equal(nav_measurements(-1.0, 500.0, 100.0, "follow")[[0, -1]], [0.0, 1.0])
    with pytest.raises(ValueError, match="movement must be one of"):
        RouteGuide(1.0, 2.0, "sideways", 10.0, 10.0).command(5.0)


@pytest.mark.parametrize("name", ["env_3", "env_4", "env_5"])
def test_a_real_route_gives_its_movement_before_the_junction(name):
    """Every slot's command is its route's movement from 50 m before the stop line (at the
    spawn in the junction scenarios), "follow" farther back (the Merge's spawns)."""
    from cosim.roadmap import movement, road_map
    from cosim.scenario import load_scenario
    from cosim.wrappers import RouteGuide

    rm = road_map(load_scenario(name))
    for route in rm.routes:
        guide = RouteGuide.of_route(route, rm.net)
        assert guide.movement == movement(rm.net, route.edges)
        assert guide.entry_s < guide.exit_s < guide.goal_s
        before = guide.entry_s - (guide.goal_s - guide.route_length)  # spawn to stop line
        at_spawn = guide.command(guide.route_length)
        assert at_spawn == (guide.movement if before <= 50.0 else "follow"), (route.edges, before)
        assert guide.command(guide.goal_s - (guide.entry_s - 49.0)) == guide.movement
        assert guide.command(guide.goal_s - guide.exit_s - 1.0) == "follow"  # past the junction


def test_the_nav_variant_passes_the_api_tests_with_a_dict_space():
    import gymnasium as gym

    env = cosim.parallel_env("env_3", frame_stack=4, obs="nav", num_agents=2, horizon=15, seed=0, image_size=32)
    try:
        space = env.observation_space("ac_0")
        assert isinstance(space, gym.spaces.Dict) and set(space) == {"image", "measurements"}
        assert space["image"].shape == (32, 32, 12)
        parallel_api_test(env, num_cycles=20)
    finally:
        env.close()
    single = cosim.single_env("env_1", obs="nav", frame_stack=4, horizon=15, image_size=48)
    try:
        check_env(single, skip_render_check=True)
        obs, info = single.reset(seed=0)
        assert obs["measurements"][-1] == pytest.approx(1.0, abs=0.02)  # at the spawn: the whole route left
    finally:
        single.close()
    with pytest.raises(ValueError, match="obs must be one of image, nav"):
        cosim.parallel_env("env_1", obs="measurements", **SMALL)
