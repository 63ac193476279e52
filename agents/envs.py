"""Small environments for testing and benchmarking agents without the simulator.

- :class:`SingleAgentParallel` presents one Gymnasium env as a one-agent
  PettingZoo-style ParallelEnv, so :func:`agents.loop.run_loop` trains on
  CartPole or Pendulum exactly as it trains on the driving env.
- :class:`ColourBar` is a synthetic image task (pure numpy) with the driving
  env's observation format (84x84x3 uint8) and a known optimal return.
- :class:`MultiColourBar` runs several independent ColourBar agents in one
  ParallelEnv, with episodes of different lengths, to exercise multi-agent loops.
- :class:`ScriptedParallelEnv` has observations that say which environment,
  agent, episode seed and step they belong to, and agents that finish at
  different steps: the check that a vector runner hands each agent its own
  transitions (tests/agents/test_vector.py, bench/train_throughput.py).
"""

from __future__ import annotations

import gymnasium
import numpy as np

__all__ = ["ColourBar", "MultiColourBar", "ScriptedParallelEnv", "SingleAgentParallel"]


class SingleAgentParallel:
    """A Gymnasium env seen as a ParallelEnv with one agent.

    ``reset(seed)`` returns ``({id: obs}, {id: info})``; ``step({id: action})``
    returns five dicts; once the episode ends ``agents`` is empty until the
    next ``reset``.

    Args:
        gym_env: Any Gymnasium env.
        agent_id: Name of the single agent.
    """

    def __init__(self, gym_env: gymnasium.Env, agent_id: str = "agent_0"):
        self.env = gym_env
        self.agent_id = agent_id
        self.possible_agents = [agent_id]
        self.agents: list[str] = []

    def observation_space(self, agent: str) -> gymnasium.Space:
        """The wrapped env's observation space (same object every call)."""
        return self.env.observation_space

    def action_space(self, agent: str) -> gymnasium.Space:
        """The wrapped env's action space (same object every call)."""
        return self.env.action_space

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Reset the wrapped env; returns ``(obs_dict, info_dict)``."""
        obs, info = self.env.reset(seed=seed, options=options)
        self.agents = [self.agent_id]
        return {self.agent_id: obs}, {self.agent_id: info}

    def step(self, actions: dict):
        """Step with ``actions[agent_id]``; returns obs, rewards, terminations, truncations, infos."""
        if self.agent_id not in actions:
            raise KeyError(f"step() needs an action for {self.agent_id!r}, got keys {sorted(actions)}")
        obs, reward, terminated, truncated, info = self.env.step(actions[self.agent_id])
        if terminated or truncated:
            self.agents = []
        a = self.agent_id
        return {a: obs}, {a: float(reward)}, {a: bool(terminated)}, {a: bool(truncated)}, {a: info}

    def close(self) -> None:
        """Close the wrapped env."""
        self.env.close()


class ColourBar(gymnasium.Env):
    """Move a coloured vertical bar to the centre of an image.

    Observation: ``Box(0, 255, (size, size, 3), uint8)``, black, with a vertical
    bar of a random bright colour (new each episode) at position ``p`` in
    ``[-1, 1]`` (left edge to right edge). Only its horizontal position matters.

    Actions:
        - discrete (``continuous=False``): ``Discrete(3)``: 0 left, 1 stay, 2 right;
          ``p <- clip(p + (a - 1) * step, -1, 1)`` with ``step = 0.25``.
        - continuous: ``Box(-1, 1, (1,))``: ``p <- clip(p + a * step, -1, 1)``.

    Reward per step: ``1 - |p'| / step`` (1 at the centre, 0 one step away, -3 at
    an edge). Episodes last ``episode_length = 10`` steps and end by truncation.
    Start positions are drawn from the 9-point grid ``{-1, -0.75, ..., 1}``
    (``options={"start": i}`` picks grid point ``i``).

    Optimal return: moving straight to the centre and staying there is optimal
    for both action spaces (one step moves at most ``step``). From a start ``d``
    steps from the centre it earns ``L - d(d-1)/2`` (``L = episode_length``):
    d=0: 10, d=1: 10, d=2: 9, d=3: 7, d=4: 4, so the mean over the 9 grid starts
    is ``70 / 9 = 7.78`` (:attr:`optimum`). Staying still earns -12.2 on
    average and a uniform random policy about -12, so >= 90% of the optimum
    (7.0) needs a policy that reads the bar's position from pixels.
    """

    metadata = {"render_modes": []}
    STEP = 0.25
    GRID = np.linspace(-1.0, 1.0, 9)
    COLOURS = np.array(
        [[255, 64, 64], [64, 255, 64], [64, 128, 255], [255, 255, 64], [255, 64, 255], [64, 255, 255]],
        dtype=np.uint8,
    )

    def __init__(self, continuous: bool = False, size: int = 84, episode_length: int = 10):
        if size < 9:
            raise ValueError(f"ColourBar size must be >= 9 pixels, got {size}")
        if episode_length < 1:
            raise ValueError(f"ColourBar episode_length must be >= 1, got {episode_length}")
        self.continuous = continuous
        self.size = size
        self.episode_length = episode_length
        self.bar_width = max(1, size // 9)
        self.observation_space = gymnasium.spaces.Box(0, 255, (size, size, 3), np.uint8)
        if continuous:
            self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        else:
            self.action_space = gymnasium.spaces.Discrete(3)
        self.position = 0.0
        self.colour = self.COLOURS[0]
        self.t = 0

    @classmethod
    def optimal_return(cls, start: int, episode_length: int = 10) -> float:
        """Return of the optimal policy from grid point ``start`` (0..8)."""
        distance = abs(int(start) - 4)
        total = 0.0
        for _ in range(episode_length):
            distance = max(0, distance - 1)
            total += 1.0 - distance
        return total

    @property
    def optimum(self) -> float:
        """Mean optimal return over the 9 grid starts (70/9 for 10-step episodes)."""
        return float(np.mean([self.optimal_return(i, self.episode_length) for i in range(9)]))

    def _render(self) -> np.ndarray:
        image = np.zeros((self.size, self.size, 3), np.uint8)
        left = int(round((self.position + 1.0) / 2.0 * (self.size - self.bar_width)))
        image[:, left : left + self.bar_width] = self.colour
        return image

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Start an episode at a random (or ``options["start"]``) grid point."""
        super().reset(seed=seed)
        start = (options or {}).get("start")
        if start is None:
            start = self.np_random.integers(0, len(self.GRID))
        self.position = float(self.GRID[int(start)])
        self.colour = self.COLOURS[self.np_random.integers(0, len(self.COLOURS))]
        self.t = 0
        return self._render(), {"position": self.position}

    def step(self, action):
        """Move the bar; returns obs, reward, terminated (always False), truncated, info."""
        if self.continuous:
            move = float(np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[0], -1.0, 1.0))
            if not np.isfinite(move):
                raise ValueError(f"ColourBar got a non-finite action {action!r}")
        else:
            if not self.action_space.contains(int(action)):
                raise ValueError(f"ColourBar action must be 0, 1 or 2, got {action!r}")
            move = float(int(action) - 1)
        self.position = float(np.clip(self.position + move * self.STEP, -1.0, 1.0))
        self.t += 1
        reward = 1.0 - abs(self.position) / self.STEP
        truncated = self.t >= self.episode_length
        return self._render(), reward, False, truncated, {"position": self.position}


class MultiColourBar:
    """N independent ColourBar agents in one ParallelEnv, for multi-agent loop tests.

    Agent ``i`` has episodes of ``episode_length + i`` steps, so agents finish at
    different times and leave ``agents`` one by one, as cars do in the driving env.
    ``continuous`` is a list of flags: mixed Discrete/Box agents are allowed.
    """

    def __init__(self, continuous: list[bool], size: int = 84, episode_length: int = 10):
        self.possible_agents = [f"agent_{i}" for i in range(len(continuous))]
        self.envs = {
            a: ColourBar(c, size, episode_length + i)
            for i, (a, c) in enumerate(zip(self.possible_agents, continuous, strict=True))
        }
        self.agents: list[str] = []

    def observation_space(self, agent: str) -> gymnasium.Space:
        """Observation space of ``agent``."""
        return self.envs[agent].observation_space

    def action_space(self, agent: str) -> gymnasium.Space:
        """Action space of ``agent``."""
        return self.envs[agent].action_space

    def reset(self, seed: int | None = None, options: dict | None = None):
        """Reset every agent; returns ``(obs_dict, info_dict)``."""
        self.agents = list(self.possible_agents)
        obs, infos = {}, {}
        for i, a in enumerate(self.agents):
            obs[a], infos[a] = self.envs[a].reset(seed=None if seed is None else seed + i)
        return obs, infos

    def step(self, actions: dict):
        """Step every live agent; finished agents leave ``agents``."""
        out = ({}, {}, {}, {}, {})
        for a in list(self.agents):
            results = self.envs[a].step(actions[a])
            for d, value in zip(out, results, strict=True):
                d[a] = value
            if results[2] or results[3]:
                self.agents.remove(a)
        return out

    def close(self) -> None:
        """Nothing to release (a vector env closes every env it built)."""
        self.agents = []


class ScriptedParallelEnv:
    """A ParallelEnv whose observations encode where they come from; no simulator.

    Agent ``k`` (``agent_k``) of environment ``env_index`` sees the float32 vector
    ``[env_index, k, t, seed, action]``: ``t`` counts its steps in the episode
    (0 at reset), ``seed`` is the reset seed (-1 for None) and ``action`` the
    action it just took (-1 at reset). Its reward is ``t`` after the step plus
    ``100 * env_index + 10 * k``. It finishes after ``lengths[k] + seed % 3``
    steps (seed None counts as 0): terminated for even ``k``, truncated for odd.
    ``fail_at`` makes ``step`` raise ``ValueError`` at that step of the first
    episode (error propagation); ``image`` switches to uint8 ``(8, 8, 3)``
    observations holding the same numbers in the first pixels; ``nav`` to
    ``Dict(image=<uint8 (36, 36, 3), the numbers in the first pixels>,
    measurements=<the float32 vector>)``, the smallest image the Nature CNN takes beside a
    measurements vector (cosim's ``obs="nav"``): both parts say which step they belong to.
    """

    metadata = {"name": "scripted_v0"}

    def __init__(self, env_index: int = 0, num_agents: int = 3, lengths=(3, 5, 4), fail_at: int | None = None,
                 image: bool = False, nav: bool = False):
        self.env_index, self.lengths, self.fail_at = env_index, tuple(lengths), fail_at
        self.image, self.nav = image, nav
        self.possible_agents = [f"agent_{k}" for k in range(num_agents)]
        self.agents: list[str] = []
        if nav:
            self._obs_space = gymnasium.spaces.Dict({
                "image": gymnasium.spaces.Box(0, 255, (36, 36, 3), np.uint8),
                "measurements": gymnasium.spaces.Box(-np.inf, np.inf, (5,), np.float32)})
        elif image:
            self._obs_space = gymnasium.spaces.Box(0, 255, (8, 8, 3), np.uint8)
        else:
            self._obs_space = gymnasium.spaces.Box(-np.inf, np.inf, (5,), np.float32)
        self._act_space = gymnasium.spaces.Discrete(3)
        self.t: dict[str, int] = {}
        self.seed = -1
        self.episodes = 0

    def observation_space(self, agent: str) -> gymnasium.Space:
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.Space:
        return self._act_space

    def _obs(self, agent: str, action: int) -> np.ndarray:
        values = [self.env_index, self.possible_agents.index(agent), self.t[agent], self.seed, action]
        if not (self.image or self.nav):
            return np.array(values, np.float32)
        out = np.zeros((36, 36, 3) if self.nav else self._obs_space.shape, np.uint8)
        out.reshape(-1)[:5] = np.array(values) % 256
        return {"image": out, "measurements": np.array(values, np.float32)} if self.nav else out

    def reset(self, seed: int | None = None, options=None):
        self.seed = -1 if seed is None else int(seed)
        self.agents = list(self.possible_agents)
        self.t = dict.fromkeys(self.agents, 0)
        self.episodes += 1
        return {a: self._obs(a, -1) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        if set(actions) != set(self.agents):
            raise ValueError(f"actions for {sorted(actions)}, live agents {self.agents}")
        obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for a in self.agents:
            k = self.possible_agents.index(a)
            self.t[a] += 1
            if self.fail_at is not None and self.episodes == 1 and self.t[a] == self.fail_at:
                raise ValueError(f"scripted failure in env {self.env_index} at step {self.t[a]}")
            obs[a] = self._obs(a, int(actions[a]))
            rewards[a] = float(self.t[a] + 100 * self.env_index + 10 * k)
            done = self.t[a] >= self.lengths[k] + max(self.seed, 0) % 3
            terms[a], truncs[a] = done and k % 2 == 0, done and k % 2 == 1
            infos[a] = {"cosim_episode": {"t": self.t[a]}} if done else {}
        self.agents = [a for a in self.agents if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def close(self) -> None:
        self.agents = []
