"""Demonstrations in a replay (Agent.observe_demonstration) and DQfD's margin loss and
pre-training (agents/dqn.py): flagged in samples, not counted as the agent's steps, and
enough on their own to make a DQN's greedy action the demonstrator's."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import agents
from agents.buffers import ReplayBuffer
from agents.dqn import margin_loss
from agents.shared import share

SPACE = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
ACTIONS = gym.spaces.Discrete(3)


def test_samples_flag_the_demonstrated_transitions():
    buffer = ReplayBuffer(64, SPACE, ACTIONS, seed=0)
    obs = np.zeros(4, np.float32)
    for t in range(20):
        nxt = np.full(4, (t + 1) / 100, np.float32)
        buffer.add(obs, t % 3, float(t), nxt, False, t == 19, demo=t < 10)
        obs = nxt
    data = buffer.sample(256)
    # transitions 0-9 (rewards 0-9) were demonstrations, 10-19 were not
    assert torch.equal(data.demos, data.rewards < 10)
    assert data.demos.any() and not data.demos.all()


def test_a_demonstration_is_stored_scaled_but_not_counted_as_a_step():
    dqn = agents.DQN(SPACE, ACTIONS, agents.DQNConfig(hidden=(8,), reward_scale=0.5, exploration_steps=10), seed=0)
    eps = dqn.epsilon
    obs, nxt = np.zeros(4, np.float32), np.ones(4, np.float32)
    dqn.observe_demonstration(obs, 2, 4.0, nxt, True, False)
    assert (dqn.steps, len(dqn.buffer), dqn.epsilon) == (0, 1, eps)
    assert dqn.buffer.rewards[0] == 2.0 and bool(dqn.buffer.demos[0])
    assert dqn.update() == {}  # nothing is due: the learning start counts the agent's own steps
    dqn.observe(obs, 1, 1.0, nxt, True, False)
    assert dqn.steps == 1 and not dqn.buffer.demos[1]


def test_on_policy_learners_refuse_demonstrations():
    ppo = agents.PPO(SPACE, ACTIONS, agents.PPOConfig(hidden=(8,)), seed=0)
    with pytest.raises(ValueError, match="ppo learns on-policy.*use dqn, ddpg or td3"):
        ppo.observe_demonstration(np.zeros(4, np.float32), 0, 0.0, np.zeros(4, np.float32), True, False)


def test_shared_slots_put_their_demonstrations_in_their_own_columns():
    core = agents.DQN(SPACE, ACTIONS, agents.DQNConfig(hidden=(8,), buffer_size=60), seed=0)
    slots = share(core, ["ac_0", "ac_1", "ac_2"])
    for slot in slots.values():
        slot.prepare_envs(1)
    obs, nxt = np.zeros(4, np.float32), np.ones(4, np.float32)
    slots["ac_2"].observe_demonstration(obs, 1, 1.0, nxt, False, True)
    assert core.buffer.sizes.tolist() == [0, 0, 1]  # ac_2's ring, not ac_0's


def test_margin_loss_is_zero_once_the_demonstrated_action_leads_by_the_margin():
    q = torch.tensor([[1.0, 2.0, 0.0], [3.0, 0.0, 0.0]])
    a = torch.tensor([[1], [0]])
    assert margin_loss(q, a, 0.8).item() == pytest.approx(0.0)  # leads by 1.0 and 3.0
    # first row: action 0 (1.0 + 0.8) is 0.2 short of beating 2.0 -> 0; now demonstrate action 0
    q2 = torch.tensor([[1.0, 2.0, 0.0]])
    assert margin_loss(q2, torch.tensor([[0]]), 0.8).item() == pytest.approx(2.0 + 0.8 - 1.0)


def test_pretraining_on_demonstrations_makes_the_greedy_action_the_demonstrators():
    rng = np.random.default_rng(0)
    states = rng.uniform(-1, 1, (300, 4)).astype(np.float32)
    expert = np.argmax(states[:, :3], axis=1)  # the demonstrator: the largest of the first three inputs
    cfg = agents.DQNConfig(hidden=(32,), demo_margin=0.8, batch_size=64, learning_rate=3e-3)
    dqn = agents.DQN(SPACE, ACTIONS, cfg, seed=0)
    for s, a in zip(states, expert, strict=True):  # one-step episodes, reward 0: only the margin teaches
        dqn.observe_demonstration(s, int(a), 0.0, s, True, False)
    with torch.no_grad():
        before = dqn.q_network(torch.as_tensor(states)).argmax(-1).numpy()
    metrics = dqn.pretrain(400)
    with torch.no_grad():
        after = dqn.q_network(torch.as_tensor(states)).argmax(-1).numpy()
    assert (before == expert).mean() < 0.6 and (after == expert).mean() > 0.9
    assert dqn.steps == 0 and dqn.gradient_updates == 400 and np.isfinite(metrics["losses/td_loss"])
    for key, tensor in dqn.q_network.state_dict().items():  # the target network copied at the end
        assert torch.equal(dqn.target_network.state_dict()[key], tensor), key
    # without the margin the same demonstrations (all rewards 0) teach no preference
    plain = agents.DQN(SPACE, ACTIONS, cfg.replace(demo_margin=0.0), seed=0)
    for s, a in zip(states, expert, strict=True):
        plain.observe_demonstration(s, int(a), 0.0, s, True, False)
    plain.pretrain(400)
    with torch.no_grad():
        assert (plain.q_network(torch.as_tensor(states)).argmax(-1).numpy() == expert).mean() < 0.6


def test_pretraining_an_empty_replay_is_refused():
    dqn = agents.DQN(SPACE, ACTIONS, agents.DQNConfig(hidden=(8,)), seed=0)
    with pytest.raises(ValueError, match="replay is empty"):
        dqn.pretrain(1)


def test_td3_pretrained_with_demo_bc_acts_like_its_demonstrator():
    """TD3's behaviour-cloning term on demonstrations (``demo_bc``): after pre-training the actor's
    action is near the demonstrated one; without it the same updates leave the actor where the
    critic of all-zero rewards puts it, nowhere near."""
    box = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    rng = np.random.default_rng(0)
    states = rng.uniform(-1, 1, (256, 4)).astype(np.float32)
    expert = np.clip(states[:, :2] * 0.8, -1, 1).astype(np.float32)  # a linear demonstrator

    def trained(weight, reward=0.0, updates=300):
        cfg = agents.TD3Config(hidden=(32,), demo_bc=weight, batch_size=64, actor_learning_rate=3e-3,
                               policy_delay=1)
        td3 = agents.TD3(SPACE, box, cfg, seed=0)
        for s, a in zip(states, expert, strict=True):
            td3.observe_demonstration(s, a, reward, s, False, False)
        td3.pretrain(updates)
        assert td3.steps == 0
        with torch.no_grad():
            return td3.actor(td3.critic.encode(torch.as_tensor(states))).numpy()

    assert np.abs(trained(2.5) - expert).mean() < 0.1
    assert np.abs(trained(0.0) - expert).mean() > 0.2
    # Rewards of 50 a step lift the critic's values to ~60 in 1,000 updates: the term is weighed
    # by mean|Q|, so the same weight still clones (a bare squared distance, unweighed, leaves
    # the actor 0.7 away: the critic's gradient drowns it).
    assert np.abs(trained(2.5, reward=50.0, updates=1000) - expert).mean() < 0.1
