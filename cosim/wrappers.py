"""ParallelEnv wrappers for libraries that need every agent present at every step.

SuperSuit's ``pettingzoo_env_to_vec_env_v1`` (and SB3 or CleanRL behind it) makes each
agent one slot of a vector env, so every agent must appear in every step's output
until the whole episode ends. SuperSuit's own ``black_death_v3`` (3.11) ends the
episode only when every agent is terminated *and* truncated, which never happens in
cosim (an AC that reaches its goal is terminated, not truncated), so it steps an
environment with no agents left. :class:`BlackDeath` is the same idea with the
episode ending when every agent has finished.
"""

from __future__ import annotations

import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper


class BlackDeath(BaseParallelWrapper):
    """Keep finished agents in the outputs until every agent has finished.

    A finished agent gets a zero observation, reward 0, empty info and
    ``terminated = truncated = False`` until the last agent finishes; at that step
    every agent gets its own final flags (terminated if it was, else truncated).
    ``agents`` stays ``possible_agents`` for the whole episode, and actions for
    finished agents are dropped.
    """

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        self.agents = list(self.env.possible_agents)
        self._final: dict[str, bool] = {}  # finished agent -> terminated (else truncated)
        return self._fill(obs), {a: infos.get(a, {}) for a in self.agents}

    def step(self, actions):
        live = {a: actions[a] for a in self.env.agents}
        obs, rewards, terms, truncs, infos = self.env.step(live)
        for a in live:
            if terms[a] or truncs[a]:
                self._final[a] = bool(terms[a])
        done = not self.env.agents
        terminated = {a: done and self._final.get(a, False) for a in self.possible_agents}
        truncated = {a: done and not self._final.get(a, False) for a in self.possible_agents}
        rewards = {a: rewards.get(a, 0.0) for a in self.possible_agents}
        infos = {a: infos.get(a, {}) for a in self.possible_agents}
        if done:
            self.agents = []
        return self._fill(obs), rewards, terminated, truncated, infos

    def _fill(self, obs: dict) -> dict:
        return {a: obs[a] if a in obs else np.zeros(self.observation_space(a).shape,
                                                     self.observation_space(a).dtype)
                for a in self.possible_agents}


def black_death(env) -> BlackDeath:
    """:class:`BlackDeath` around a ParallelEnv (for SuperSuit's vector-env conversions)."""
    return BlackDeath(env)
