"""The env API contracts (PettingZoo, Gymnasium) on short real episodes, and bad input."""

import gymnasium as gym
import numpy as np
import pybullet
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

import cosim
from cosim.errors import ActionError, EnvStateError, ScenarioError

MIXED = ["discrete"] * 4 + ["continuous"] * 2


@pytest.mark.parametrize(
    "scenario, n, types",
    [("env_1", 2, "discrete"), ("env_5", 2, "continuous"), ("env_3", 6, MIXED)],
)
def test_pettingzoo_parallel_api(scenario, n, types):
    env = cosim.parallel_env(scenario, num_agents=n, action_types=types, horizon=25, seed=0)
    try:
        parallel_api_test(env, num_cycles=40)
    finally:
        env.close()


def test_pettingzoo_seed_test_mixed():
    # two environments alive at once in one process: the second runs SUMO in a child process
    parallel_seed_test(
        lambda: cosim.parallel_env("env_3", num_agents=3, action_types=["discrete", "continuous", "discrete"],
                                   horizon=15, image_size=32),
        num_cycles=15,
    )


@pytest.mark.parametrize("action_type", ["discrete", "continuous"])
def test_gymnasium_check_env(action_type):
    env = cosim.single_env("env_1", action_type=action_type, horizon=20, image_size=48)
    try:
        check_env(env, skip_render_check=True)
    finally:
        env.close()


def test_registered_ids_and_empty_world():
    assert set(cosim.GYM_IDS) <= set(gym.registry)
    env = gym.make(f"cosim/FourWay-v{cosim.TASK_VERSION}", background=False, pedestrians=False, horizon=5)
    try:
        obs, info = env.reset(seed=0)
        assert obs.shape == (84, 84, 3) and obs.dtype == np.uint8
        snap = env.unwrapped.parallel.world.snapshot
        assert (~snap.vehicle_is_ac).sum() == 0 and len(snap.person_ids) == 0
        assert set(info) >= {"collision_vehicle", "off_road", "distance_to_goal", "reward_terms"}
    finally:
        env.close()


def test_spaces_and_infos_of_a_mixed_env():
    env = cosim.parallel_env("env_3", num_agents=6, action_types=MIXED, horizon=5)
    try:
        assert env.action_space("ac_0") == gym.spaces.Discrete(9)
        assert env.action_space("ac_5") == gym.spaces.Box(-1, 1, (2,), np.float32)
        assert env.observation_space("ac_3") is env.observation_space("ac_3")
        obs, infos = env.reset(seed=3)
        actions = {a: env.action_space(a).sample() for a in env.agents}
        obs, rew, term, trunc, infos = env.step(actions)
        for a in env.possible_agents:
            terms = infos[a]["reward_terms"]
            assert rew[a] == pytest.approx(sum(terms.values()))
            assert obs[a].shape == (84, 84, 3)
    finally:
        env.close()


def test_bad_actions_name_the_agent_and_the_space():
    env = cosim.parallel_env("env_1", num_agents=2, action_types=["discrete", "continuous"], horizon=50)
    try:
        env.reset(seed=0)
        with pytest.raises(ActionError, match=r"ac_0.*Discrete\(9\)"):
            env.step({"ac_0": np.array([0.5, 0.0]), "ac_1": np.zeros(2)})
        with pytest.raises(ActionError, match=r"ac_1.*shape \(2,\).*Box"):
            env.step({"ac_0": 3, "ac_1": np.zeros(3)})
        with pytest.raises(ActionError, match=r"ac_1.*NaN"):
            env.step({"ac_0": 3, "ac_1": np.array([np.nan, 0.0])})
        with pytest.raises(ActionError, match=r"\['ac_7'\].*unknown agent.*ac_0"):
            env.step({"ac_0": 3, "ac_1": np.zeros(2), "ac_7": 1})
        with pytest.raises(ActionError, match=r"no action for active agent\(s\) \['ac_1'\]"):
            env.step({"ac_0": 3})
        # nothing was stepped by the failures
        assert env.world.step_count == 0
    finally:
        env.close()


def test_step_before_reset_after_done_and_after_close():
    env = cosim.parallel_env("env_1", num_agents=1, horizon=3)
    with pytest.raises(EnvStateError, match="before reset"):
        env.step({"ac_0": 0})
    env.reset(seed=0)
    for _ in range(3):
        env.step({"ac_0": 0})
    assert env.agents == []
    with pytest.raises(EnvStateError, match="every agent is done"):
        env.step({"ac_0": 0})
    client = env.mirror.client
    env.close()
    env.close()
    assert not env.world.bridge.running
    assert pybullet.getConnectionInfo(physicsClientId=client)["isConnected"] == 0
    with pytest.raises(EnvStateError, match="closed"):
        env.reset(seed=0)


def test_bad_constructor_arguments():
    with pytest.raises(ScenarioError, match="1..6"):
        cosim.parallel_env("env_1", num_agents=7)
    with pytest.raises(ScenarioError, match="valid: \\['discrete', 'continuous'\\]"):
        cosim.parallel_env("env_1", num_agents=1, action_types="hybrid")
    with pytest.raises(ScenarioError, match="2 types for 3 agents"):
        cosim.parallel_env("env_1", num_agents=3, action_types=["discrete", "continuous"])
    with pytest.raises(ScenarioError, match="available: env_1"):
        cosim.parallel_env("nowhere")
