"""The env loop contract, the env adapters, the synthetic image task and the replay buffer."""

import gymnasium as gym
import numpy as np
import pytest

from agents.base import Agent, AgentConfig
from agents.buffers import ReplayBuffer
from agents.envs import ColourBar, MultiColourBar, SingleAgentParallel
from agents.loop import evaluate, run_loop
from agents.ppo import PPO
from agents.td3 import TD3, TD3Config

from .conftest import FAST


class Recorder(Agent):
    """A scripted agent that records every call the loop makes."""

    algo = "recorder"
    config_class = AgentConfig

    @classmethod
    def check_spaces(cls, observation_space, action_space):
        pass

    def _build(self):
        self.calls = []

    def act_batch(self, obs, columns, deterministic=False):
        self.calls += [("act", float(np.asarray(row).ravel()[0])) for row in obs]
        return np.ones(len(obs), np.int64)

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns):
        self.calls += [("observe", float(np.asarray(o).ravel()[0]), float(np.asarray(n).ravel()[0]), bool(t))
                       for o, n, t in zip(obs, next_obs, truncated, strict=True)]

    def update(self):
        self.calls.append(("update",))
        return {"charts/n": 1.0}


class CounterEnv(gym.Env):
    """obs = 100 * episode + t; episodes are truncated after 3 steps."""

    observation_space = gym.spaces.Box(0, 1e6, (1,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self):
        self.episode, self.t = -1, 0

    def reset(self, seed=None, options=None):
        self.episode, self.t = self.episode + 1, 0
        return np.array([100.0 * self.episode], np.float32), {}

    def step(self, action):
        self.t += 1
        obs = np.array([100.0 * self.episode + self.t], np.float32)
        return obs, 1.0, False, self.t == 3, {}


def test_loop_passes_final_observation_not_reset_observation():
    env = CounterEnv()
    agent = Recorder(env.observation_space, env.action_space)
    stats = run_loop({"agent_0": agent}, SingleAgentParallel(env), 6)
    observes = [c[1:] for c in agent.calls if c[0] == "observe"]
    # (obs, next_obs, truncated): the truncated step carries the final obs 3 / 103,
    # and the next episode starts from its reset obs 100.
    assert observes == [(0, 1, False), (1, 2, False), (2, 3, True),
                        (100, 101, False), (101, 102, False), (102, 103, True)]
    kinds = [c[0] for c in agent.calls]
    # the action of step t + 1 is chosen before step t is observed; update follows every observe
    assert kinds[:7] == ["act", "act", "observe", "update", "act", "observe", "update"]
    assert stats.episodes == 2 and stats.episode_lengths["agent_0"] == [3, 3]
    assert stats.episode_returns["agent_0"] == [3.0, 3.0]
    assert stats.updates == 6 and stats.env_time_s > 0 and stats.learn_time_s > 0


def test_loop_rejects_missing_agents():
    env = MultiColourBar([False, False], size=36)
    agent = Recorder(env.observation_space("agent_0"), env.action_space("agent_0"))
    with pytest.raises(KeyError, match="agent_1"):
        run_loop({"agent_0": agent}, env, 1)


def test_multi_agent_mixed_discrete_and_box_agents():
    env = MultiColourBar([False, True], size=36, episode_length=4)
    agents = {
        "agent_0": PPO.from_spaces(env.observation_space("agent_0"), env.action_space("agent_0"),
                                   FAST["ppo"].replace(rollout_steps=8, batch_size=4), seed=0),
        "agent_1": TD3.from_spaces(env.observation_space("agent_1"), env.action_space("agent_1"),
                                   TD3Config(learning_starts=4, batch_size=4, buffer_size=100), seed=1),
    }
    stats = run_loop(agents, env, 15)
    # agent_0 episodes last 4 steps, agent_1 5 steps: the env resets after 5 steps.
    assert stats.episodes == 3
    assert stats.episode_lengths == {"agent_0": [4, 4, 4], "agent_1": [5, 5, 5]}
    assert stats.agent_steps == 3 * 9
    assert agents["agent_1"].steps == 15 and agents["agent_0"].steps == 12
    assert "agent_0" in stats.last_metrics and "agent_1" in stats.last_metrics
    assert isinstance(agents["agent_1"].act(np.zeros((36, 36, 3), np.uint8)), np.ndarray)


def test_single_agent_parallel_contract():
    env = SingleAgentParallel(gym.make("CartPole-v1"))
    assert env.observation_space("agent_0") is env.observation_space("agent_0")
    obs, infos = env.reset(seed=0)
    assert set(obs) == {"agent_0"} and env.agents == ["agent_0"]
    done = False
    while not done:
        out = env.step({"agent_0": 0})
        assert all(set(d) == {"agent_0"} for d in out)
        done = out[2]["agent_0"] or out[3]["agent_0"]
    assert env.agents == []
    with pytest.raises(KeyError, match="agent_0"):
        env.step({"x": 0})


def test_colour_bar_optimum_and_dynamics():
    env = ColourBar()
    assert env.optimum == pytest.approx(70 / 9)
    assert [ColourBar.optimal_return(i) for i in range(5)] == [4.0, 7.0, 9.0, 10.0, 10.0]
    obs, _ = env.reset(seed=0, options={"start": 0})  # far left
    assert obs.shape == (84, 84, 3) and obs.dtype == np.uint8
    assert obs[:, :9].any() and not obs[:, 40:].any()  # the bar is at the left edge
    total = 0.0
    for t in range(10):
        _, reward, terminated, truncated, info = env.step(2 if t < 4 else 1)  # right x4, then stay
        total += reward
        assert not terminated and truncated == (t == 9)
    assert total == pytest.approx(ColourBar.optimal_return(0))
    assert info["position"] == 0.0
    cont = ColourBar(continuous=True)
    cont.reset(seed=0, options={"start": 8})
    assert cont.step(np.array([-0.5], np.float32))[1] == pytest.approx(1 - 0.875 / 0.25)
    with pytest.raises(ValueError, match="0, 1 or 2"):
        env.step(5)


def test_evaluate_counts_whole_episodes():
    env = SingleAgentParallel(ColourBar(size=36))
    agent = Recorder(env.observation_space("agent_0"), env.action_space("agent_0"))
    returns = evaluate({"agent_0": agent}, env, episodes=3)
    assert len(returns["agent_0"]) == 3
    assert not any(c[0] == "observe" for c in agent.calls)  # evaluation does not learn


def test_replay_buffer_stores_each_observation_once_and_keeps_truncation_obs():
    obs_space = gym.spaces.Box(0, 255, (1,), np.uint8)
    buf = ReplayBuffer(8, obs_space, gym.spaces.Discrete(2), seed=0)
    # episodes: 0 -> 1 -> 2 (terminated), 10 -> 11 -> 12 (truncated: final obs 99), 20 -> ...
    transitions = []
    for start, end_kind in [(0, "term"), (10, "trunc"), (20, None)]:
        for k in range(3):
            last = k == 2
            nxt = 99 if (last and end_kind == "trunc") else start + k + 1
            transitions.append((start + k, nxt, last and end_kind == "term", last and end_kind == "trunc"))
    for o, n, te, tr in transitions:
        buf.add(np.array([o]), o % 2, float(o), np.array([n]), te, tr)
    assert len(buf) == 8 and buf.obs.shape == (8, 1)  # no separate next_obs array
    sample = buf.sample(500)
    pairs = set(zip(sample.obs[:, 0].tolist(), sample.next_obs[:, 0].tolist(), sample.terminateds.tolist(), strict=True))
    # 9 adds into 8 slots: the oldest is overwritten, and once full the next-oldest's
    # slot holds the newest next_obs, so capacity - 1 transitions are sampled.
    expected = {(o, n, float(te)) for o, n, te, _ in transitions[2:]}
    expected = {p for p in expected if p[0] != 2}  # terminal's next obs is not used: checked below
    assert expected <= pairs
    assert all(p[2] == 1.0 for p in pairs if p[0] == 2)
    assert (12, 99, 0.0) in pairs  # truncated: real final observation, bootstraps
    assert not {0, 1} & set(sample.obs[:, 0].tolist())
    np.testing.assert_array_equal(sample.rewards.numpy(), sample.obs[:, 0].numpy().astype(np.float32))
