"""The replay buffer keeps K-frame stacks one frame per slot and rebuilds them exactly
(agents/buffers.py ReplayBuffer; docs/task.md, "Observation")."""

import gymnasium as gym
import numpy as np
import pytest

from agents.buffers import ReplayBuffer, frames_in
from cosim.wrappers import FrameHistory, stacked_space

K = 4
FRAME = gym.spaces.Box(0, 255, (2, 2, 3), np.uint8)


def _frame(value: int) -> np.ndarray:
    return np.full((2, 2, 3), value % 256, np.uint8)


def _episodes(lengths, ends, first_value=1):
    """Transitions (obs, next_obs, terminated, truncated) as cosim.wrappers.FrameStack makes
    them: each frame a distinct value, every stack from FrameHistory."""
    out, value = [], first_value
    for length, end in zip(lengths, ends, strict=True):
        history = FrameHistory(K)
        obs = history.push(_frame(value))
        for t in range(length):
            value += 1
            nxt = history.push(_frame(value))
            last = t == length - 1
            out.append((obs, nxt, last and end == "term", last and end == "trunc"))
            obs = nxt
        value += 1
    return out


def test_frames_in_reads_the_stack_from_the_space():
    assert frames_in(stacked_space(FRAME, K)) == K and frames_in(FRAME) == 1
    assert frames_in(gym.spaces.Box(0, 255, (84, 84, 4), np.uint8)) == 1  # Atari grey stack: not RGB
    assert frames_in(gym.spaces.Box(0, 1, (2, 2, 12), np.float32)) == 1


@pytest.mark.parametrize("columns", [1, 2])
def test_sampled_stacks_are_exactly_the_stacks_added(columns):
    space = stacked_space(FRAME, K)
    capacity = 20 * columns
    buf = ReplayBuffer(capacity, space, gym.spaces.Discrete(2), seed=0, columns=columns)
    assert buf.obs.shape == (capacity, 2, 2, 3)  # one frame per slot, not K
    added = {}
    for col in range(columns):
        trans = _episodes([7, 3, 9, 12], ["term", "trunc", "trunc", None], first_value=1 + 100 * col)
        for n, (o, x, te, tr) in enumerate(trans):
            buf.add(o, n % 2, float(n), x, te, tr, column=col)
            added[(col, float(n))] = (o, x, te)
    sample = buf.sample(400)
    obs, nxt = sample.obs.numpy(), sample.next_obs.numpy()
    keys = set()
    for row in range(400):
        col = int(obs[row, 0, 0, -1] >= 100)
        o, x, te = added[(col, float(sample.rewards[row]))]
        np.testing.assert_array_equal(obs[row], o)
        if not te:  # a terminal's next observation is never used
            np.testing.assert_array_equal(nxt[row], x)
        keys.add((col, float(sample.rewards[row])))
    # a ring of 20 after 31 adds: the newest 20 - K transitions of each column are sampled
    assert {r for c, r in keys if c == 0} == {float(n) for n in range(31 - 20 + K, 31)}


def test_an_episode_that_starts_mid_stack_keeps_its_older_frames():
    """A learner that joins an episode late (its first stack is not K copies of one frame)."""
    space = stacked_space(FRAME, K)
    buf = ReplayBuffer(10, space, gym.spaces.Discrete(2), seed=1)
    trans = _episodes([8], ["trunc"])[3:]  # starts at the 4th step: a stack of 4 different frames
    for n, (o, x, te, tr) in enumerate(trans):
        buf.add(o, 0, float(n), x, te, tr)
    sample = buf.sample(200)
    for row in range(200):
        o, x, _, _ = trans[int(sample.rewards[row])]
        np.testing.assert_array_equal(sample.obs[row].numpy(), o)
        np.testing.assert_array_equal(sample.next_obs[row].numpy(), x)


def test_observations_that_are_not_frame_stacks_are_refused():
    buf = ReplayBuffer(10, stacked_space(FRAME, K), gym.spaces.Discrete(2))
    rng = np.random.default_rng(0)
    a, b = (rng.integers(0, 255, (2, 2, 3 * K), dtype=np.uint8) for _ in range(2))
    with pytest.raises(ValueError, match="not frame stacks; build the ReplayBuffer with frame_stack=1"):
        buf.add(a, 0, 0.0, b, False, False)
    plain = ReplayBuffer(10, stacked_space(FRAME, K), gym.spaces.Discrete(2), frame_stack=1)
    plain.add(a, 0, 0.0, b, False, False)
    np.testing.assert_array_equal(plain.sample(1).next_obs[0].numpy(), b)


def test_stacked_replay_memory_is_that_of_single_frames():
    one = ReplayBuffer(1000, gym.spaces.Box(0, 255, (84, 84, 3), np.uint8), gym.spaces.Discrete(9))
    four = ReplayBuffer(1000, gym.spaces.Box(0, 255, (84, 84, 12), np.uint8), gym.spaces.Discrete(9))
    assert four.nbytes == one.nbytes == 1000 * 84 * 84 * 3
