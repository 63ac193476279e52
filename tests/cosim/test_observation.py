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
