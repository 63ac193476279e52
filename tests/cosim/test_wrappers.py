"""cosim.wrappers.BlackDeath on a fake ParallelEnv (no simulator)."""

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo import ParallelEnv

from cosim.wrappers import black_death


class Staggered(ParallelEnv):
    """a_0 terminates after 1 step, a_1 is truncated after 3."""

    metadata = {"name": "staggered"}
    possible_agents = ["a_0", "a_1"]

    def observation_space(self, agent):
        return spaces.Box(0, 255, (2,), np.uint8)

    def action_space(self, agent):
        return spaces.Discrete(2)

    def reset(self, seed=None, options=None):
        self.agents, self.t = list(self.possible_agents), 0
        return {a: np.full(2, 7, np.uint8) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        assert set(actions) == set(self.agents)  # never an action for a finished agent
        self.t += 1
        term = {a: a == "a_0" and self.t == 1 for a in self.agents}
        trunc = {a: a == "a_1" and self.t == 3 for a in self.agents}
        out = ({a: np.full(2, 7, np.uint8) for a in self.agents}, dict.fromkeys(self.agents, 1.0),
               term, trunc, {a: {"t": self.t} for a in self.agents})
        self.agents = [a for a in self.agents if not (term[a] or trunc[a])]
        return out


def test_finished_agents_stay_with_zero_obs_until_everyone_is_done():
    env = black_death(Staggered())
    obs, infos = env.reset(seed=0)
    assert set(obs) == {"a_0", "a_1"}
    flags = []
    for _ in range(3):
        obs, rew, term, trunc, info = env.step({"a_0": 1, "a_1": 0})
        assert set(obs) == set(rew) == set(term) == set(trunc) == {"a_0", "a_1"}
        flags.append((term, trunc))
    assert flags[0] == ({"a_0": False, "a_1": False}, {"a_0": False, "a_1": False})
    assert obs["a_0"].tolist() == [0, 0] and rew["a_0"] == 0.0 and info["a_0"] == {}
    assert obs["a_1"].tolist() == [7, 7] and rew["a_1"] == 1.0
    assert flags[2] == ({"a_0": True, "a_1": False}, {"a_0": False, "a_1": True})  # own flags
    assert env.agents == []


# -- FrameStack: each agent's last K frames, oldest first -------------------------------
def _steps(stacked: np.ndarray) -> list[int]:
    """The step counter t of each stacked ScriptedParallelEnv frame, oldest first."""
    return [int(stacked[0, 0, 3 * j + 2]) for j in range(stacked.shape[-1] // 3)]


def test_frame_stack_orders_frames_oldest_first_and_keeps_final_observations():
    from agents.envs import ScriptedParallelEnv
    from cosim.wrappers import FrameStack

    env = FrameStack(ScriptedParallelEnv(image=True, lengths=(3, 5, 4)), 3)
    assert env.observation_space("agent_0").shape == (8, 8, 9)
    obs, _ = env.reset(seed=0)
    assert all(_steps(o) == [0, 0, 0] for o in obs.values())  # the first frame fills the stack
    assert all(env.observation_space(a).contains(o) for a, o in obs.items())
    seen = {a: [] for a in env.possible_agents}
    while env.agents:
        obs, _, terms, truncs, _ = env.step({a: 1 for a in env.agents})
        for a, o in obs.items():
            seen[a].append((_steps(o), terms[a] or truncs[a]))
    assert seen["agent_0"] == [([0, 0, 1], False), ([0, 1, 2], False), ([1, 2, 3], True)]
    assert seen["agent_1"][-1] == ([3, 4, 5], True)  # its final observation, stacked
    assert seen["agent_2"][-1] == ([2, 3, 4], True)


def test_frame_stack_starts_again_at_every_reset():
    from agents.envs import ScriptedParallelEnv
    from cosim.wrappers import FrameStack

    env = FrameStack(ScriptedParallelEnv(image=True, lengths=(2, 2, 2)), 2)
    env.reset(seed=0)
    while env.agents:
        obs, *_ = env.step({a: 2 for a in env.agents})
    assert _steps(obs["agent_0"]) == [1, 2]
    obs, _ = env.reset(seed=4)
    assert _steps(obs["agent_0"]) == [0, 0]
    assert [int(obs["agent_0"][0, 1, 3 * j]) for j in range(2)] == [4, 4]  # both frames: the new episode's
    one = FrameStack(ScriptedParallelEnv(image=True), 1)
    assert one.observation_space("agent_0").shape == (8, 8, 3)


def test_a_policy_s_frame_history_stacks_as_the_training_env_does():
    from agents.envs import ScriptedParallelEnv
    from cosim.wrappers import FrameStack
    from eval.testing.rollout import StackedPolicy

    class Spy:
        algo = "spy"

        def __init__(self):
            self.seen, self.resets = [], 0

        def reset(self):
            self.resets += 1

        def act(self, obs, deterministic=True):
            self.seen.append(obs)
            return 1

    raw = ScriptedParallelEnv(image=True, lengths=(4, 4, 4))
    stacked = FrameStack(ScriptedParallelEnv(image=True, lengths=(4, 4, 4)), 3)
    spy = Spy()
    policy = StackedPolicy(spy, 3)
    assert (policy.algo, policy.frame_stack) == ("spy", 3)
    for seed in (0, 1):  # two episodes: the history must not leak across the reset
        frames, _ = raw.reset(seed=seed)
        expected, _ = stacked.reset(seed=seed)
        policy.reset()
        while raw.agents:
            policy.act(frames["agent_0"])
            assert np.array_equal(spy.seen[-1], expected["agent_0"])
            frames, *_ = raw.step({a: 1 for a in raw.agents})
            expected, *_ = stacked.step({a: 1 for a in stacked.agents})
    assert spy.resets == 2 and _steps(spy.seen[-2]) == [1, 2, 3] and _steps(spy.seen[4]) == [0, 0, 0]


# -- ActionRepeat: each action held for k steps, rewards summed --------------------------
def test_action_repeat_sums_rewards_and_lets_a_finished_agent_stop():
    from agents.envs import ScriptedParallelEnv
    from cosim.wrappers import ActionRepeat, observation_wrappers

    # agent_k's reward is its step count t after the step + 10 k; agent_0 ends at t = 3
    # (terminated), agent_1 at 5 (truncated), agent_2 at 4 (terminated): seed 0
    env = ActionRepeat(ScriptedParallelEnv(lengths=(3, 5, 4)), 2)
    obs, _ = env.reset(seed=0)
    obs, rew, terms, truncs, infos = env.step({a: 1 for a in env.agents})
    assert {a: int(o[2]) for a, o in obs.items()} == {"agent_0": 2, "agent_1": 2, "agent_2": 2}
    assert rew == {"agent_0": 1 + 2, "agent_1": 11 + 12, "agent_2": 21 + 22}
    assert not any(terms.values()) and not any(truncs.values())
    obs, rew, terms, truncs, infos = env.step({a: 2 for a in env.agents})
    # agent_0 finished at t = 3, the first inner step: it took no second one
    assert int(obs["agent_0"][2]) == 3 and rew["agent_0"] == 3 and terms["agent_0"]
    assert infos["agent_0"] == {"cosim_episode": {"t": 3}}
    assert int(obs["agent_2"][2]) == 4 and rew["agent_2"] == 23 + 24 and terms["agent_2"]
    assert int(obs["agent_1"][2]) == 4 and rew["agent_1"] == 13 + 14 and not truncs["agent_1"]
    assert env.agents == ["agent_1"]
    obs, rew, terms, truncs, _ = env.step({"agent_1": 0})  # 5 is its last step: it stops there
    assert set(obs) == {"agent_1"} and int(obs["agent_1"][2]) == 5 and rew == {"agent_1": 15}
    assert truncs["agent_1"] and env.agents == []
    assert observation_wrappers(ScriptedParallelEnv(), action_repeat=1).__class__ is ScriptedParallelEnv
    with pytest.raises(ValueError, match="action_repeat must be a whole number"):
        observation_wrappers(ScriptedParallelEnv(), action_repeat=0)


def test_a_repeat_policy_drives_the_test_env_as_the_training_env_does():
    """RepeatPolicy (the test: an action asked every step) around StackedPolicy gives the
    policy the same observations and the env the same actions as training's
    FrameStack(ActionRepeat(env)), across episodes."""
    from agents.envs import ScriptedParallelEnv
    from cosim.wrappers import observation_wrappers
    from eval.testing.rollout import RepeatPolicy, StackedPolicy

    class Counter:  # a different action at every decision, and what it saw
        algo = "counter"

        def __init__(self):
            self.seen = []

        def act(self, obs, deterministic=True):
            self.seen.append(obs)
            return len(self.seen) % 3

    raw = ScriptedParallelEnv(image=True, lengths=(7, 7, 7))
    trained = observation_wrappers(ScriptedParallelEnv(image=True, lengths=(7, 7, 7)), frame_stack=2,
                                   action_repeat=3)
    tested, expected = Counter(), Counter()
    policy = RepeatPolicy(StackedPolicy(tested, 2), 3)
    assert (policy.algo, policy.k) == ("counter", 3)
    raw_actions, trained_actions = [], []
    for seed in (0, 1):  # 7 and 8 steps: the last decision is cut short
        frames, _ = raw.reset(seed=seed)
        stacks, _ = trained.reset(seed=seed)
        policy.reset()
        while raw.agents:
            raw_actions.append(policy.act(frames["agent_0"]))
            frames, *_ = raw.step({a: raw_actions[-1] for a in raw.agents})
        while trained.agents:
            trained_actions.append(expected.act(stacks["agent_0"]))
            stacks, *_ = trained.step({a: trained_actions[-1] for a in trained.agents})
    assert len(tested.seen) == len(expected.seen) == 3 + 3  # ceil(7 / 3), ceil(8 / 3)
    assert all(np.array_equal(a, b) for a, b in zip(tested.seen, expected.seen, strict=True))
    assert _steps(tested.seen[2]) == [3, 6] and _steps(tested.seen[3]) == [0, 0]
    assert raw_actions == [a for a in trained_actions for _ in range(3)][:7] + [
        a for a in trained_actions[3:] for _ in range(3)][:8]
