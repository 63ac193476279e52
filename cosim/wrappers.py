"""ParallelEnv wrappers: frame stacking (:class:`FrameStack`, :class:`FrameHistory`), and
:class:`BlackDeath` for libraries that need every agent present at every step.

A single camera frame has no velocity. :class:`FrameStack` gives each agent its last K
frames, stacked on the channel axis oldest first (84x84x3 -> 84x84x3K); at a reset the
history is K copies of the first frame. :class:`FrameHistory` is the stack of one camera,
which a policy that drives one car of a shared test environment keeps for itself
(eval/rollout.py ``StackedPolicy``), so training and testing stack identically.

SuperSuit's ``pettingzoo_env_to_vec_env_v1`` (and SB3 or CleanRL behind it) makes each
agent one slot of a vector env, so every agent must appear in every step's output
until the whole episode ends. SuperSuit's own ``black_death_v3`` (3.11) ends the
episode only when every agent is terminated *and* truncated, which never happens in
cosim (an AC that reaches its goal is terminated, not truncated), so it steps an
environment with no agents left. :class:`BlackDeath` is the same idea with the
episode ending when every agent has finished.
"""

from __future__ import annotations

import gymnasium
import numpy as np
from pettingzoo.utils.wrappers import BaseParallelWrapper


class FrameHistory:
    """The last ``k`` frames of one camera, concatenated on the last axis, oldest first.

    :meth:`push` adds a frame and returns the stack (a new array); the first push after
    construction or :meth:`clear` fills all ``k`` slots with that frame.
    """

    def __init__(self, k: int):
        if int(k) < 1:
            raise ValueError(f"a frame stack needs k >= 1 frames, got {k}")
        self.k = int(k)
        self.stack: np.ndarray | None = None

    def clear(self) -> None:
        """Forget the frames (an episode boundary): the next push starts a new stack."""
        self.stack = None

    def push(self, frame: np.ndarray) -> np.ndarray:
        frame = np.asarray(frame)
        if self.stack is None:
            self.stack = np.concatenate([frame] * self.k, axis=-1)
        else:
            self.stack = np.concatenate([self.stack[..., frame.shape[-1]:], frame], axis=-1)
        return self.stack


def stacked_space(space: gymnasium.spaces.Box, k: int) -> gymnasium.spaces.Box:
    """The observation space of ``k`` stacked frames of ``space`` (channels-last)."""
    return gymnasium.spaces.Box(np.concatenate([space.low] * k, axis=-1),
                                np.concatenate([space.high] * k, axis=-1), dtype=space.dtype)


class FrameStack(BaseParallelWrapper):
    """Each agent observes its last ``k`` camera frames, stacked oldest first (84x84x3k).

    ``reset`` starts every agent's history with ``k`` copies of its first frame; ``step``
    pushes each returned observation, the final one of an agent that finishes included,
    so a transition's next observation is the stack the agent would see next. ``k = 1``
    returns the frames unchanged.
    """

    def __init__(self, env, k: int):
        super().__init__(env)
        self.k = int(k)
        if self.k < 1:
            raise ValueError(f"FrameStack needs k >= 1 frames, got {k}")
        self._spaces = {a: stacked_space(env.observation_space(a), self.k) for a in env.possible_agents}
        self._history = {a: FrameHistory(self.k) for a in env.possible_agents}

    @property
    def agents(self) -> list:
        return self.env.agents

    @property
    def possible_agents(self) -> list:
        return self.env.possible_agents

    def observation_space(self, agent):
        return self._spaces[agent]

    def reset(self, seed=None, options=None):
        obs, infos = self.env.reset(seed=seed, options=options)
        for history in self._history.values():
            history.clear()
        return self._push(obs), infos

    def step(self, actions):
        obs, rewards, terms, truncs, infos = self.env.step(actions)
        return self._push(obs), rewards, terms, truncs, infos

    def _push(self, obs: dict) -> dict:
        return {a: self._history[a].push(o) for a, o in obs.items()}


def observation_wrappers(env, frame_stack: int = 1):
    """``env`` with the observation a run trains on: its last ``frame_stack`` camera frames
    (:class:`FrameStack`; 1 leaves the env as it is). The one place the training, validation
    and library factories build an AC's observation (docs/task.md, "Observation")."""
    k = check_frame_stack(frame_stack)
    return FrameStack(env, k) if k > 1 else env


def check_frame_stack(frame_stack) -> int:
    """``frame_stack`` as an int >= 1, or a ValueError naming it."""
    if isinstance(frame_stack, bool) or not isinstance(frame_stack, int | np.integer) or frame_stack < 1:
        raise ValueError(f"frame_stack must be an int >= 1 (1: a single camera frame), got {frame_stack!r}")
    return int(frame_stack)


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
