"""Vector envs and batched acting (agents/vector.py, agents.loop.run_loop).

A scripted ParallelEnv (agents.envs.ScriptedParallelEnv) writes the env index,
agent, step and episode seed into every observation and ends its agents at
different steps, so each transition can be traced back to where it came from.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import agents
from agents.base import Agent, due
from agents.buffers import ReplayBuffer
from agents.envs import ScriptedParallelEnv
from agents.loop import run_loop
from agents.vector import InProcessVectorEnv, VectorEnv, VectorEnvError
from agents.workers import live_pids

REPO_ROOT = Path(__file__).resolve().parents[2]
LENGTHS = (3, 5, 4)  # agent k ends after LENGTHS[k] + seed % 3 steps


def env_fns(n, **kwargs):
    return [functools.partial(ScriptedParallelEnv, i, lengths=LENGTHS, **kwargs) for i in range(n)]


class Recorder(Agent):
    """Acts 1 and records every batched call (no learning)."""

    algo = "recorder"
    config_class = agents.PPOConfig

    @classmethod
    def check_spaces(cls, observation_space, action_space):
        pass

    def _build(self):
        self.transitions = []  # (env, obs, action, reward, next_obs, terminated, truncated)
        self.prepared = None

    def prepare_envs(self, num_envs):
        self.prepared = num_envs

    def act(self, obs, deterministic=False):
        return 1

    def act_batch(self, obs, columns, deterministic=False):
        return np.full(len(columns), 1, np.int64)

    def observe(self, *args):
        raise AssertionError("the vector loop must call observe_batch")

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns):
        for j, c in enumerate(columns):
            self.transitions.append((int(c), obs[j].copy(), int(actions[j]), float(rewards[j]), next_obs[j].copy(),
                                     bool(terminated[j]), bool(truncated[j])))

    def update(self):
        return {}


def _recorders(venv):
    space = venv.observation_space("agent_0")
    return {a: Recorder(space, venv.action_space(a)) for a in venv.possible_agents}


@pytest.mark.parametrize("n", [1, 3])
def test_each_agent_gets_exactly_its_own_cars_transitions_across_auto_resets(n):
    seed = 5
    with InProcessVectorEnv(env_fns(n)) as venv:
        recs = _recorders(venv)
        stats = run_loop(recs, venv, total_steps=40 * n, seed=seed)
    assert stats.env_steps == 40 * n and all(r.prepared == n for r in recs.values())
    for k, (aid, rec) in enumerate(recs.items()):
        for env in range(n):
            rows = [t for t in rec.transitions if t[0] == env]
            assert rows, f"{aid} has no transition from env {env}"
            episode = 0
            for j, (_, obs, action, reward, nxt, term, trunc) in enumerate(rows):
                ep_seed = seed + env + episode * n
                # whose and which: this env, this agent, this episode, the next step
                assert obs[:2].tolist() == [env, k] and nxt[:2].tolist() == [env, k]
                assert obs[3] == ep_seed and nxt[3] == ep_seed
                assert nxt[2] == obs[2] + 1 and nxt[4] == action == 1
                assert reward == nxt[2] + 100 * env + 10 * k
                ends = nxt[2] == LENGTHS[k] + ep_seed % 3
                assert (term or trunc) == ends and term == (ends and k % 2 == 0)
                if ends:
                    # the TRUE final observation, not the reset one
                    assert nxt[2] > 0
                    episode += 1
                    if j + 1 < len(rows):
                        assert rows[j + 1][1][2] == 0 and rows[j + 1][1][3] == seed + env + episode * n
                elif j + 1 < len(rows):
                    np.testing.assert_array_equal(rows[j + 1][1][:4], nxt[:4])  # consecutive steps
    # an episode ends when the slowest agent finishes: lengths are per agent, episodes per env
    assert stats.episodes == sum(len(v) for v in stats.episode_returns.values()) // len(recs)


def test_worker_processes_match_the_in_process_env_step_for_step():
    actions_rng = np.random.default_rng(0)
    with InProcessVectorEnv(env_fns(2, image=True)) as local, VectorEnv(env_fns(2, image=True)) as remote:
        a, b = local.reset(seed=3), remote.reset(seed=3)
        for _ in range(25):
            for key in ("obs", "alive"):
                for aid in local.possible_agents:
                    np.testing.assert_array_equal(getattr(a, key)[aid], getattr(b, key)[aid])
            acts = {aid: actions_rng.integers(3, size=2) for aid in local.possible_agents}
            a, b = local.step(acts), remote.step(acts)
            np.testing.assert_array_equal(a.env_reset, b.env_reset)
            assert a.infos == b.infos
            for key in ("next_obs", "active", "rewards", "terminated", "truncated"):
                for aid in local.possible_agents:
                    mask = a.active[aid]
                    np.testing.assert_array_equal(getattr(a, key)[aid][mask], getattr(b, key)[aid][mask])
        pids = remote.pids
        assert len(live_pids(pids)) == 2
    assert live_pids(pids) == []


def _ppo_run(n, seed, processes=False, learner_threads=1):
    fns = env_fns(n)
    venv = VectorEnv(fns) if processes else InProcessVectorEnv(fns)
    with venv:
        space = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)
        config = agents.PPOConfig(rollout_steps=10, batch_size=5, epochs=2, hidden=(8,))
        learners = {a: agents.PPO(space, gym.spaces.Discrete(3), config, seed=seed + k)
                    for k, a in enumerate(venv.possible_agents)}
        stats = run_loop(learners, venv, total_steps=30 * n, seed=seed,
                                learner_threads=learner_threads)
    weights = {a: torch.cat([p.detach().flatten() for p in ag.net.parameters()]) for a, ag in learners.items()}
    return stats, weights, learners


def test_same_seed_and_n_give_identical_runs_and_ppo_learns_per_env_columns():
    s1, w1, learners = _ppo_run(3, seed=1)
    s2, w2, _ = _ppo_run(3, seed=1)
    assert s1.episode_returns == s2.episode_returns and s1.updates == s2.updates > 0
    for a in w1:
        torch.testing.assert_close(w1[a], w2[a], rtol=0, atol=0)
    assert all(ag.iterations >= 1 for ag in learners.values())
    _, w3, _ = _ppo_run(3, seed=2)
    assert any(not torch.equal(w1[a], w3[a]) for a in w1)


def test_updates_on_several_threads_give_the_same_weights_bit_for_bit():
    s1, w1, _ = _ppo_run(2, seed=5)
    s3, w3, learners = _ppo_run(2, seed=5, learner_threads=3)
    assert s1.episode_returns == s3.episode_returns and s1.updates == s3.updates > 0
    for a in w1:
        torch.testing.assert_close(w1[a], w3[a], rtol=0, atol=0)
    assert not [t for t in threading.enumerate() if t.name.startswith("cosim-learner")]


def test_worker_processes_with_double_buffering_are_reproducible():
    s1, w1, _ = _ppo_run(2, seed=4, processes=True)
    s2, w2, _ = _ppo_run(2, seed=4, processes=True)
    assert s1.episode_returns == s2.episode_returns and s1.env_steps == s2.env_steps == 60
    for a in w1:
        torch.testing.assert_close(w1[a], w2[a], rtol=0, atol=0)


def test_ppo_stores_the_acting_policys_log_prob_and_value_for_each_transition():
    # The loop acts at t + 1 before it observes t: each transition must keep what act_batch gave for IT.
    space = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)
    ppo = {a: agents.PPO(space, gym.spaces.Discrete(3), agents.PPOConfig(rollout_steps=200, batch_size=10, hidden=(8,)),
                         seed=k) for k, a in enumerate(["agent_0", "agent_1", "agent_2"])}
    with InProcessVectorEnv(env_fns(2)) as venv:
        run_loop(ppo, venv, total_steps=60, seed=0)
    for agent in ppo.values():
        buf, n = agent.buffer, agent.buffer.pos
        assert n > 20 and agent.iterations == 0
        with torch.no_grad():
            logits, values = agent.net(torch.as_tensor(buf.obs[:n]))
        log_probs = torch.log_softmax(logits, -1).gather(1, torch.as_tensor(buf.actions[:n])[:, None])[:, 0]
        np.testing.assert_allclose(buf.log_probs[:n], log_probs.numpy(), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(buf.values[:n], values.numpy(), rtol=1e-5, atol=1e-6)


def test_ppo_bootstraps_each_env_column_from_its_own_next_observation():
    space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
    ppo = agents.PPO(space, gym.spaces.Discrete(2), agents.PPOConfig(rollout_steps=4, batch_size=2, gamma=0.5,
                                                                    gae_lambda=1.0), seed=0)
    obs = np.array([[0, 0], [1, 1]], np.float32)
    cols = np.array([0, 1])
    for t in range(2):  # two steps in two envs, env 1 terminates at its second step
        acts = ppo.act_batch(obs + t, cols)
        ppo.observe_batch(obs + t, acts, np.ones(2), obs + t + 1, np.array([False, t == 1]), np.zeros(2, bool), cols)
    buf = ppo.buffer
    assert buf.full and buf.columns[:4].tolist() == [0, 1, 0, 1]
    with torch.no_grad():
        v_next0 = ppo.net(torch.as_tensor(obs[:1] + 2))[1].item()
    next_values = buf.bootstrap_columns({0: v_next0})
    assert next_values[0] == buf.values[2] and next_values[1] == buf.values[3]  # inside each column
    assert next_values[2] == pytest.approx(v_next0)  # env 0 goes on: V(its next obs)
    assert ppo.update()["charts/iterations"] == 1.0


def test_off_policy_update_to_data_ratio_does_not_depend_on_the_number_of_envs():
    space = gym.spaces.Box(-1, 1, (2,), np.float32)
    counts = {}
    for n in (1, 4):
        dqn = agents.DQN(space, gym.spaces.Discrete(2), agents.DQNConfig(
            learning_starts=8, train_freq=4, gradient_steps=2, batch_size=4, buffer_size=64, hidden=(8,)), seed=0)
        dqn.prepare_envs(n)
        cols = np.arange(n)
        for _ in range(48 // n):
            o = np.zeros((n, 2), np.float32)
            dqn.observe_batch(o, np.zeros(n, np.int64), np.zeros(n), o, np.zeros(n, bool), np.zeros(n, bool), cols)
            dqn.update()
        counts[n] = dqn.gradient_updates
    assert counts[1] == counts[4] == 2 * (48 - 8 + 4) // 4  # steps 8, 12, ..., 48: 11 phases x 2
    assert due(0, 1, 1) == 1 and due(3, 7, 4, start=5) == 0 and due(3, 9, 4, start=5) == 1


def test_replay_rings_keep_each_envs_next_observation():
    space = gym.spaces.Box(0, 1000, (1,), np.float32)
    buf = ReplayBuffer(12, space, gym.spaces.Discrete(2), columns=3)
    for t in range(10):  # interleaved adds from three envs: obs = 100 * env + t
        for env in range(3):
            buf.add(np.array([100 * env + t]), 0, 0.0, np.array([100 * env + t + 1]), False, False, column=env)
    sample = buf.sample(300)
    obs, nxt = sample.obs[:, 0].numpy(), sample.next_obs[:, 0].numpy()
    np.testing.assert_array_equal(nxt, obs + 1)
    assert set((obs // 100).astype(int).tolist()) == {0, 1, 2}
    assert set((obs % 100).astype(int).tolist()) == {7, 8, 9}  # ring of 4: the newest 3 per env


def test_an_error_in_an_env_worker_names_the_env_and_leaves_no_worker():
    fns = [functools.partial(ScriptedParallelEnv, 0), functools.partial(ScriptedParallelEnv, 1, fail_at=2)]
    venv = VectorEnv(fns)
    pids = venv.pids
    try:
        venv.reset(seed=0)
        acts = {a: np.ones(2, np.int64) for a in venv.possible_agents}
        venv.step(acts)
        with pytest.raises(VectorEnvError, match="environment 1") as info:
            venv.step(acts)
        assert info.value.env_index == 1 and "scripted failure in env 1" in info.value.worker_traceback
    finally:
        venv.close()
    assert live_pids(pids) == []
    with pytest.raises(VectorEnvError, match="environment 0"):  # in process: same error, same index
        with InProcessVectorEnv([functools.partial(ScriptedParallelEnv, 0, fail_at=1)]) as local:
            local.reset()
            local.step({a: np.ones(1, np.int64) for a in local.possible_agents})


_CTRL_C_SCRIPT = """
import functools, sys, time
import numpy as np
from agents.envs import ScriptedParallelEnv
from agents.vector import VectorEnv
if __name__ == "__main__":
    venv = VectorEnv([functools.partial(ScriptedParallelEnv, i) for i in range(2)])
    venv.reset(seed=0)
    try:
        venv.step({a: np.ones(2, np.int64) for a in venv.possible_agents})
        print(" ".join(map(str, venv.pids)), flush=True)  # ready: inside the cleanup's try, stepping
        while True:
            venv.step({a: np.ones(2, np.int64) for a in venv.possible_agents})
    finally:
        venv.close()
"""
# VectorEnv.close() is bounded by its own timeouts (join 5 s, then terminate and kill, 1 s
# each per worker): under any load the owner is gone well within this; a hang still fails.
OWNER_EXIT_S = 120


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_ctrl_c_or_kill_9_of_the_owner_leaves_no_env_worker(tmp_path, sig):
    script = tmp_path / "owner.py"
    script.write_text(_CTRL_C_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO_ROOT, env={**os.environ, "PYTHONPATH": str(REPO_ROOT)})
    try:
        pids = [int(p) for p in proc.stdout.readline().split()]  # waits until the owner is stepping
        assert len(pids) == 2 and len(live_pids(pids)) == 2, proc.stderr.read() if proc.poll() else pids
        proc.send_signal(sig)
        proc.wait(timeout=OWNER_EXIT_S)
        deadline = time.monotonic() + 30  # the kernel's PDEATHSIG (kill -9) or close() (Ctrl-C)
        while live_pids(pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert live_pids(pids) == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
