"""What outside libraries rely on (issue 10, item 5): the episode-summary key does not
collide with Gymnasium's, ``reward_scale`` scales only the returned reward, and the
environment pickles and deep-copies by rebuilding from its constructor arguments."""

import copy
import pickle

import gymnasium as gym
import numpy as np
import pytest

import cosim
from cosim.env import EPISODE_INFO

SMALL = dict(background=False, pedestrians=False, image_size=32)


def _run_single(env, steps: int):
    obs, info = env.reset(seed=0)
    rewards, infos = [], []
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(1)
        rewards.append(r)
        infos.append(info)
        if term or trunc:
            break
    return rewards, infos


def test_record_episode_statistics_wraps_the_single_env():
    env = gym.wrappers.RecordEpisodeStatistics(cosim.single_env("env_1", horizon=6, **SMALL))
    try:
        rewards, infos = _run_single(env, 10)
    finally:
        env.close()
    last = infos[-1]
    assert len(rewards) == 6
    assert last["episode"]["l"] == 6  # Gymnasium's own statistics
    assert last["episode"]["r"] == pytest.approx(sum(rewards), rel=1e-5)
    summary = last[EPISODE_INFO]  # ours, beside it
    assert EPISODE_INFO == "cosim_episode"
    assert summary["length"] == 6 and summary["return"] == pytest.approx(sum(rewards))
    assert all(EPISODE_INFO not in i for i in infos[:-1])


def test_reward_scale_scales_the_reward_but_not_the_terms_or_summary():
    runs = {}
    for scale in (1.0, 0.01):
        env = cosim.single_env("env_1", horizon=5, reward_scale=scale, **SMALL)
        try:
            assert env.parallel.reward_scale == scale
            runs[scale] = _run_single(env, 5)
        finally:
            env.close()
    (r1, i1), (r2, i2) = runs[1.0], runs[0.01]
    np.testing.assert_allclose(r2, 0.01 * np.asarray(r1), rtol=1e-9)
    for reward, a, b in zip(r1, i1, i2, strict=True):
        assert a["reward_terms"] == pytest.approx(b["reward_terms"])
        assert sum(b["reward_terms"].values()) == pytest.approx(reward)  # the unscaled reward
    assert i2[-1][EPISODE_INFO]["return"] == pytest.approx(sum(r1))  # unscaled


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), "0.1"])
def test_bad_reward_scale_is_refused(bad):
    with pytest.raises(ValueError, match="reward_scale must be a finite number > 0"):
        cosim.parallel_env("env_1", num_agents=1, reward_scale=bad)


def test_pickle_and_deepcopy_rebuild_from_the_constructor_arguments():
    env = cosim.parallel_env("env_1", num_agents=2, action_types=["discrete", "continuous"],
                             horizon=4, reward_scale=0.5, **SMALL)
    obs0, _ = env.reset(seed=3)
    env.step({a: env.action_space(a).sample() for a in env.agents})
    env.close()  # so a copy below may take the in-process libsumo
    for clone in (pickle.loads(pickle.dumps(env)), copy.deepcopy(env)):
        try:
            assert clone is not env and clone.possible_agents == env.possible_agents
            assert clone.agents == []  # a new, un-reset environment
            assert clone.reward_scale == 0.5 and clone.scenario == env.scenario
            assert clone.action_space("ac_1") == env.action_space("ac_1")
            obs, _ = clone.reset(seed=3)
            for a in obs0:
                np.testing.assert_array_equal(obs[a], obs0[a])
        finally:
            clone.close()


def test_single_env_deepcopies():
    env = cosim.single_env("env_1", horizon=3, **SMALL)
    clone = copy.deepcopy(env)
    try:
        assert clone.parallel is not env.parallel
        assert clone.observation_space == env.observation_space
        obs, _ = clone.reset(seed=0)
        assert obs.shape == (32, 32, 3)
    finally:
        clone.close()
        env.close()
