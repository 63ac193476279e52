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
