"""cosim.wrappers.BlackDeath on a fake ParallelEnv (no simulator)."""

import numpy as np
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
