"""Parameter sharing (agents/shared.py): one network acts for and learns from every AC.

The scripted ParallelEnv (agents.envs.ScriptedParallelEnv) writes the env index, the agent and
its step into every observation, so each transition in the shared learner can be traced to the
car and environment it came from.
"""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest
import torch

import agents
from agents.envs import ScriptedParallelEnv
from agents.loop import run_loop
from agents.shared import SharedSlot, share, shared_core
from agents.vector import InProcessVectorEnv

SPACE = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)
ACTIONS = gym.spaces.Discrete(3)
IDS = ["agent_0", "agent_1", "agent_2"]


def env_fns(n):
    return [functools.partial(ScriptedParallelEnv, i) for i in range(n)]


def shared_ppo(seed=0, rollout_steps=24):
    core = agents.PPO(SPACE, ACTIONS, agents.PPOConfig(rollout_steps=rollout_steps, batch_size=8,
                                                       epochs=2, hidden=(8,)), seed=seed)
    return core, share(core, IDS)


def weights(agent) -> torch.Tensor:
    return torch.cat([p.detach().flatten().clone() for p in agent.net.parameters()])


def test_every_acs_transitions_reach_the_one_learner_each_in_its_own_column():
    core, slots = shared_ppo(rollout_steps=500)  # no update: the buffer keeps everything
    with InProcessVectorEnv(env_fns(2)) as venv:
        stats = run_loop(slots, venv, total_steps=40, seed=3)
    buf, n = core.buffer, core.buffer.pos
    assert n == stats.agent_steps == core.steps > 0
    # column = env * 3 + slot, and the observation in it came from that env and that AC
    obs, columns = buf.obs[:n], buf.columns[:n]
    np.testing.assert_array_equal(obs[:, 0] * 3 + obs[:, 1], columns)
    assert sorted(set(columns.tolist())) == list(range(6))
    for c in range(6):  # each column's steps follow one car's episodes in order
        t = obs[columns == c, 2]
        assert ((np.diff(t) == 1) | (t[1:] == 0)).all()


def test_one_network_acts_for_every_slot_and_learns_from_all_of_them():
    core, slots = shared_ppo()
    before = weights(core)
    with InProcessVectorEnv(env_fns(2)) as venv:
        run_loop(slots, venv, total_steps=60, seed=0)
    assert core.iterations >= 2 and not torch.equal(before, weights(core))
    assert all(s.net is core.net for s in slots.values()) and shared_core(slots) is core
    # the same observation gets the same logits from every slot: there is one policy
    o = np.zeros(5, np.float32)
    first = [s.act(o, deterministic=True) for s in slots.values()]
    assert len(set(first)) == 1


def test_updates_on_several_threads_learn_once_per_step_bit_for_bit():
    runs = {}
    for threads in (1, 3):
        core, slots = shared_ppo(seed=4)
        with InProcessVectorEnv(env_fns(2)) as venv:
            stats = run_loop(slots, venv, total_steps=60, seed=4, learner_threads=threads)
        runs[threads] = (weights(core), core.iterations, stats.updates)
    torch.testing.assert_close(runs[1][0], runs[3][0], rtol=0, atol=0)
    assert runs[1][1:] == runs[3][1:] and runs[1][1] == runs[1][2] > 0  # one update per iteration


def test_shared_dqn_learns_per_transition_as_independent_ones_do():
    config = agents.DQNConfig(learning_starts=8, train_freq=4, gradient_steps=1, batch_size=4,
                              buffer_size=600, hidden=(8,))
    with InProcessVectorEnv(env_fns(2)) as venv:
        independent = {a: agents.DQN(SPACE, ACTIONS, config, seed=k) for k, a in enumerate(IDS)}
        run_loop(independent, venv, total_steps=60, seed=1)
    with InProcessVectorEnv(env_fns(2)) as venv:
        core = agents.DQN(SPACE, ACTIONS, config, seed=0)
        run_loop(share(core, IDS), venv, total_steps=60, seed=1)
    steps = sum(a.steps for a in independent.values())
    assert core.steps == steps  # the same transitions, all in one replay
    assert core.buffer.columns == 6 and len(core.buffer) == steps
    # the same learning per transition: gradient steps every train_freq transitions
    assert core.gradient_updates == (steps - 8) // 4 + 1
    assert sum(a.gradient_updates for a in independent.values()) < core.gradient_updates + 3


def test_slots_work_in_the_one_environment_loop():
    core, slots = shared_ppo(rollout_steps=500)
    stats = run_loop(slots, ScriptedParallelEnv(0), total_steps=12, seed=0)
    buf = core.buffer
    assert buf.pos == stats.agent_steps
    np.testing.assert_array_equal(buf.obs[:buf.pos, 1], buf.columns[:buf.pos])  # column = slot


def test_each_slots_checkpoint_is_the_shared_network(tmp_path):
    core, slots = shared_ppo()
    with InProcessVectorEnv(env_fns(1)) as venv:
        run_loop(slots, venv, total_steps=30, seed=0)
    for aid, slot in slots.items():
        slot.save(tmp_path / f"{aid}.pt", policy_only=True)
    loaded = [agents.load(tmp_path / f"{a}.pt") for a in IDS]
    for agent in loaded:
        assert type(agent) is agents.PPO
        torch.testing.assert_close(weights(agent), weights(core), rtol=0, atol=0)


def test_share_refuses_nonsense():
    core, slots = shared_ppo()
    with pytest.raises(ValueError, match="at least one"):
        share(core, [])
    with pytest.raises(ValueError, match="already a SharedSlot"):
        share(slots["agent_0"], IDS)
    assert shared_core({"a": core}) is None
    other = share(shared_ppo()[0], IDS)
    with pytest.raises(ValueError, match="2 different cores"):
        shared_core({"x": slots["agent_0"], "y": other["agent_1"]})
    assert isinstance(slots["agent_1"], SharedSlot) and slots["agent_1"].algo == "ppo"
