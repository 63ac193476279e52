"""Multi-step samples of the replay (ReplayBuffer.sample with ``n_step``; DQN's ``n_step``):
every row checked against the transitions as they happened, across episode ends,
truncations, the newest transition, full rings, several columns and frame stacks."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import agents
from agents.buffers import ReplayBuffer

GAMMA = 0.5


def frame(uid: int) -> np.ndarray:
    """A 2x2 RGB frame that names its transition: channels 0 and 1 hold uid in base 256."""
    out = np.zeros((2, 2, 3), np.uint8)
    out[..., 0], out[..., 1] = uid % 256, uid // 256
    return out


def fill(buffer: ReplayBuffer, k: int, seed: int = 0, episodes: int = 12):
    """Random episodes (random lengths, ends by termination, truncation or none for the last)
    into every column; returns each column's transitions in order, as (obs, reward, next_obs,
    terminated, truncated), and a map from an observation's newest-frame uid to (column, index)."""
    rng = np.random.default_rng(seed)
    truth = {c: [] for c in range(buffer.columns)}
    where = {}
    uid = 1
    for c in range(buffer.columns):
        for e in range(episodes):
            length = int(rng.integers(1, 8))
            stack = [frame(uid)] * k
            uid += 1
            for t in range(length):
                last = t == length - 1
                terminated = last and e < episodes - 1 and bool(rng.random() < 0.5)
                truncated = last and e < episodes - 1 and not terminated
                nxt = [*stack[1:], frame(uid)]
                uid += 1
                obs, next_obs = np.concatenate(stack, -1), np.concatenate(nxt, -1)
                reward = float(rng.integers(1, 10))
                buffer.add(obs, 0, reward, next_obs, terminated, truncated, column=c)
                where[int(obs[0, 0, -3]) + 256 * int(obs[0, 0, -2])] = (c, len(truth[c]))
                truth[c].append((obs, reward, next_obs, terminated, truncated))
                stack = nxt
    return truth, where


def expected(transitions, j: int, n: int):
    reward, m = transitions[j][1], 1
    while m < n and j + m < len(transitions) and not (transitions[j + m - 1][3] or transitions[j + m - 1][4]):
        reward += GAMMA ** m * transitions[j + m][1]
        m += 1
    obs, _, next_obs, terminated, _ = transitions[j + m - 1]
    return reward, next_obs, terminated, GAMMA ** m


@pytest.mark.parametrize(("k", "columns", "capacity"), [(1, 1, 10_000), (1, 3, 10_000), (1, 2, 40), (4, 2, 60)])
def test_every_n_step_row_matches_the_transitions_that_happened(k, columns, capacity):
    space = gym.spaces.Box(0, 255, (2, 2, 3 * k), np.uint8)
    buffer = ReplayBuffer(capacity, space, gym.spaces.Discrete(2), seed=1, columns=columns)
    truth, where = fill(buffer, k)
    data = buffer.sample(2000, n_step=3, gamma=GAMMA)
    obs, next_obs = data.obs.numpy(), data.next_obs.numpy()
    spans = set()
    for row in range(2000):
        c, j = where[int(obs[row, 0, 0, -3]) + 256 * int(obs[row, 0, 0, -2])]
        reward, want_next, terminated, discount = expected(truth[c], j, 3)
        np.testing.assert_array_equal(obs[row], truth[c][j][0])
        assert data.rewards[row].item() == pytest.approx(reward)
        assert bool(data.terminateds[row]) == terminated
        if not terminated:  # a terminal row's next_obs is never used (its slot is the next episode's)
            np.testing.assert_array_equal(next_obs[row], want_next)
        assert data.discounts[row].item() == pytest.approx(discount)
        spans.add(round(np.log(discount) / np.log(GAMMA)))
    assert spans == {1, 2, 3}  # rows of full length and rows cut by an episode's end both drawn


def test_one_step_samples_are_unchanged_and_have_no_discounts():
    space = gym.spaces.Box(0, 255, (2, 2, 3), np.uint8)
    a, b = (ReplayBuffer(10_000, space, gym.spaces.Discrete(2), seed=3) for _ in range(2))
    fill(a, 1), fill(b, 1)
    one, default = a.sample(64, n_step=1, gamma=GAMMA), b.sample(64)
    assert one.discounts is None and default.discounts is None
    for name in ("obs", "rewards", "next_obs", "terminateds"):
        assert torch.equal(getattr(one, name), getattr(default, name)), name


def test_dqn_bootstraps_with_the_rows_discount():
    """n_step 3 on a chain with reward 1 per step and a terminal after 3: once learned, Q of the
    first state is 1 + g + g^2 from 3-step targets (it needs no bootstrap at all)."""
    space = gym.spaces.Box(-1, 1, (3,), np.float32)
    cfg = agents.DQNConfig(hidden=(16,), n_step=3, gamma=0.9, batch_size=32, learning_rate=1e-2,
                           target_update_interval=50, huber_delta=10.0)
    dqn = agents.DQN(space, gym.spaces.Discrete(1), cfg, seed=0)
    states = np.eye(3, dtype=np.float32)
    for _ in range(20):
        for t in range(3):
            dqn.observe_demonstration(states[t], 0, 1.0, states[(t + 1) % 3], t == 2, False)
    dqn.pretrain(400)
    with torch.no_grad():
        q = dqn.q_network(torch.as_tensor(states)).squeeze(1).numpy()
    np.testing.assert_allclose(q, [1 + 0.9 + 0.81, 1 + 0.9, 1.0], atol=0.05)
