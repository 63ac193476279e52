"""The one environment loop: independent learners stepping one ParallelEnv.

This loop IS the contract between environments and agents (acme style):

1. ``obs, infos = env.reset(seed=seed)``; ``env.agents`` lists the live agents.
2. Each live agent ``a`` picks ``actions[a] = agents[a].act(obs[a])``.
3. ``obs2, rewards, terminations, truncations, infos = env.step(actions)``.
4. Each agent that acted gets ``observe(obs[a], actions[a], rewards[a], obs2[a],
   terminations[a], truncations[a])`` and then ``update()``; ``obs2[a]`` of a
   finished agent is its final observation, never a reset one.
5. A finished agent leaves ``env.agents`` and is not asked to act again; when
   no agent is left the env is reset (seed + episode index) and its episode
   return and length are recorded.

:func:`run_vector_loop` is the same contract over N environments at once
(``agents/vector.py``): each agent acts for its slot in every environment
where it is alive in ONE batched forward pass (``act_batch``), records that
slot's transitions with their environment index (``observe_batch``), and
``update()`` runs once per vector step, doing the learning those transitions
made due. Environments reset themselves when all their agents have finished.
Learning overlaps stepping: the transitions of step t are observed and learnt
from after the actions of step t + 1 were sent, while the environments (worker
processes) take that step, so actions lag the weights by one step (as in
Sample Factory; PPO stores the acting policy's log-probabilities, so its ratio
stays exact). With worker processes the envs form two groups (double
buffering): one half steps while this process acts and learns for the other.
The order of calls is fixed, so runs are reproducible for the same N and seed.

Every agent has its own networks (any mix of algorithms and of Discrete/Box
action spaces). The loop times ``env.step`` separately from the agents'
``act``/``observe``/``update`` so the bottleneck is visible in :class:`LoopStats`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from agents import observations
from agents.base import Agent

__all__ = ["LoopStats", "evaluate", "run_loop", "run_vector_loop"]

logger = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """What happened during :func:`run_loop`.

    Attributes:
        env_steps: Number of ``env.step`` calls.
        agent_steps: Transitions observed, summed over agents.
        episodes: Number of env resets after all agents finished.
        episode_returns: Agent id -> list of undiscounted episode returns.
        episode_lengths: Agent id -> list of episode lengths.
        env_time_s: Wall time inside ``env.reset``/``env.step``.
        act_time_s: Wall time inside ``act``.
        learn_time_s: Wall time inside ``observe`` and ``update``.
        updates: Number of ``update()`` calls that returned metrics (learning steps).
        last_metrics: Agent id -> the last non-empty metrics dict.
    """

    env_steps: int = 0
    agent_steps: int = 0
    episodes: int = 0
    episode_returns: dict[str, list[float]] = field(default_factory=dict)
    episode_lengths: dict[str, list[int]] = field(default_factory=dict)
    env_time_s: float = 0.0
    act_time_s: float = 0.0
    learn_time_s: float = 0.0
    updates: int = 0
    last_metrics: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def wall_time_s(self) -> float:
        """Time spent in the env plus the agents (loop bookkeeping excluded)."""
        return self.env_time_s + self.act_time_s + self.learn_time_s

    def summary(self) -> dict[str, float]:
        """Namespaced timing metrics (``time/...``) for logs."""
        total = max(self.wall_time_s, 1e-9)
        return {
            "time/env_steps_per_s": self.env_steps / total,
            "time/agent_steps_per_s": self.agent_steps / total,
            "time/env_fraction": self.env_time_s / total,
            "time/act_fraction": self.act_time_s / total,
            "time/learn_fraction": self.learn_time_s / total,
        }


def run_loop(
    agents: Mapping[str, Agent],
    env,
    total_steps: int,
    callback: Callable[[int, LoopStats, dict[str, dict[str, float]]], bool | None] | None = None,
    seed: int = 0,
    learn: bool = True,
    deterministic: bool = False,
) -> LoopStats:
    """Step ``env`` for ``total_steps`` env steps, with each agent acting and learning.

    Args:
        agents: Agent id -> agent; must cover ``env.possible_agents``.
        env: A PettingZoo-ParallelEnv-like object (see the module docstring).
        total_steps: Number of ``env.step`` calls to make.
        callback: Called after every env step as ``callback(step, stats, metrics)``
            where ``metrics`` holds this step's non-empty ``update()`` results by
            agent; returning True stops the loop early.
        seed: Seed of the first reset; episode ``k`` resets with ``seed + k``.
        learn: If False, agents only act (no ``observe``/``update``): evaluation.
        deterministic: Passed to ``act`` (greedy actions for evaluation).

    Returns:
        The :class:`LoopStats` of the run.

    Raises:
        KeyError: If the env has an agent id that ``agents`` does not cover.
    """
    missing = sorted(set(env.possible_agents) - set(agents))
    if missing:
        raise KeyError(f"run_loop has no agent for env agent(s) {missing}; pass one Agent per id")
    stats = LoopStats()
    clock = time.perf_counter
    returns: dict[str, float] = {}
    lengths: dict[str, int] = {}

    start = clock()
    obs, _ = env.reset(seed=seed)
    stats.env_time_s += clock() - start
    returns = dict.fromkeys(env.agents, 0.0)
    lengths = dict.fromkeys(env.agents, 0)

    for step in range(1, total_steps + 1):
        start = clock()
        live = list(env.agents)
        actions = {a: agents[a].act(obs[a], deterministic=deterministic) for a in live}
        stats.act_time_s += clock() - start

        start = clock()
        next_obs, rewards, terminations, truncations, _ = env.step(actions)
        stats.env_time_s += clock() - start
        stats.env_steps += 1

        start = clock()
        step_metrics: dict[str, dict[str, float]] = {}
        for a in live:
            reward = float(rewards[a])
            returns[a] += reward
            lengths[a] += 1
            if learn:
                agents[a].observe(obs[a], actions[a], reward, next_obs[a], bool(terminations[a]), bool(truncations[a]))
                metrics = agents[a].update()
                if metrics:
                    step_metrics[a] = metrics
                    stats.last_metrics[a] = metrics
                    stats.updates += 1
        stats.agent_steps += len(live)
        stats.learn_time_s += clock() - start

        if not env.agents:
            for a in returns:
                stats.episode_returns.setdefault(a, []).append(returns[a])
                stats.episode_lengths.setdefault(a, []).append(lengths[a])
            stats.episodes += 1
            start = clock()
            obs, _ = env.reset(seed=seed + stats.episodes)
            stats.env_time_s += clock() - start
            returns = dict.fromkeys(env.agents, 0.0)
            lengths = dict.fromkeys(env.agents, 0)
        else:
            obs = next_obs

        if callback is not None and callback(step, stats, step_metrics):
            logger.info("run_loop stopped by callback at step %d", step)
            break
    return stats


def evaluate(agents: Mapping[str, Agent], env, episodes: int, seed: int = 10_000, deterministic: bool = True) -> dict[str, list[float]]:
    """Run ``episodes`` full episodes without learning; return each agent's episode returns.

    Args:
        agents: Agent id -> agent.
        env: A ParallelEnv-like env (a separate instance from the training env).
        episodes: Number of complete episodes to play.
        seed: Seed of the first evaluation episode.
        deterministic: Greedy actions if True.
    """
    if episodes < 1:
        raise ValueError(f"evaluate needs episodes >= 1, got {episodes}")

    def stop(_step: int, stats: LoopStats, _metrics) -> bool:
        return stats.episodes >= episodes

    stats = run_loop(agents, env, total_steps=10**9, callback=stop, seed=seed, learn=False, deterministic=deterministic)
    return stats.episode_returns


def run_vector_loop(
    agents: Mapping[str, Agent],
    venv,
    total_steps: int,
    callback: Callable[[int, LoopStats, dict[str, dict[str, float]]], bool | None] | None = None,
    seed: int | None = 0,
    learn: bool = True,
    deterministic: bool = False,
    learner_threads: int = 1,
) -> LoopStats:
    """Step the N environments of ``venv`` until ``total_steps`` env steps, all agents acting and learning.

    Args:
        agents: Agent id -> agent; must cover ``venv.possible_agents``.
        venv: An :class:`agents.vector.VectorEnv` or ``InProcessVectorEnv``.
        total_steps: Environment steps to make, summed over the environments
            (each group of envs that steps adds its size; the last may overshoot).
        callback: Called each time a group of envs (all N, or one half with
            double buffering) has stepped and been learnt from, as
            ``callback(env_steps, stats, metrics)`` (``env_steps`` counted over all
            environments; ``metrics`` holds the non-empty ``update()`` results by
            agent); True stops the loop (envs already stepping finish their step).
        seed: Reset seed (env ``i``, episode ``k`` gets ``seed + i + k * N``).
        learn: If False, agents only act: evaluation.
        deterministic: Passed to ``act_batch``.
        learner_threads: Run the agents' ``update()`` calls on up to this many
            threads at once. Every AC has its own networks, optimiser and
            generators, so the updates are independent and the result is the
            same bit for bit (torch releases the GIL inside its ops; each thread
            uses the process's torch thread count). While PPO updates, its
            environments wait, so a second core is otherwise idle.

    Returns:
        The :class:`LoopStats` of the run; ``env_steps`` counts env steps over all
        environments and ``episodes`` the finished episodes of all of them.
    """
    missing = sorted(set(venv.possible_agents) - set(agents))
    if missing:
        raise KeyError(f"run_vector_loop has no agent for env agent(s) {missing}; pass one Agent per id")
    n = venv.num_envs
    if learn:
        for agent in agents.values():
            agent.prepare_envs(n)
    stats = LoopStats()
    clock = time.perf_counter
    ids = list(venv.possible_agents)

    pool = ThreadPoolExecutor(learner_threads, "cosim-learner") if learn and learner_threads > 1 else None

    def learn_from(acted, result) -> dict[str, dict[str, float]]:
        step_metrics: dict[str, dict[str, float]] = {}
        for a, (envs, obs, actions) in acted.items():
            next_obs, rewards, terminated, truncated = result[a]
            agents[a].observe_batch(obs, actions, rewards, next_obs, terminated, truncated, envs)
        if pool is not None and len(acted) > 1:
            updates = list(pool.map(lambda a: agents[a].update(), acted))
        else:
            updates = [agents[a].update() for a in acted]
        for a, metrics in zip(acted, updates, strict=True):
            if metrics:
                step_metrics[a] = metrics
                stats.last_metrics[a] = metrics
                stats.updates += 1
        return step_metrics

    def act_and_send(group: np.ndarray, obs_rows, alive) -> dict:
        """Act for every agent alive in the envs of ``group`` (one forward pass per agent) and send."""
        start = clock()
        acted: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # id -> (envs, obs copy, actions)
        full_actions = {}
        for a in ids:
            envs = group[alive[a][group]]
            if envs.size == 0:
                continue
            obs = observations.take(obs_rows[a], envs)  # a copy: the vector env overwrites its arrays on step
            actions = np.asarray(agents[a].act_batch(obs, envs, deterministic=deterministic))
            batch = np.zeros((n, *actions.shape[1:]), actions.dtype)
            batch[envs] = actions
            full_actions[a] = batch
            acted[a] = (envs, obs, actions)
        stats.act_time_s += clock() - start
        start = clock()
        venv.step_async(full_actions, group)
        stats.env_time_s += clock() - start
        return acted

    try:
        return _vector_steps(venv, total_steps, callback, seed, learn, stats, act_and_send, learn_from)
    finally:
        if pool is not None:
            pool.shutdown()


def _vector_steps(venv, total_steps, callback, seed, learn, stats, act_and_send, learn_from) -> LoopStats:
    """The stepping schedule of :func:`run_vector_loop` (its closures do the acting and learning)."""
    clock = time.perf_counter
    n = venv.num_envs
    ids = list(venv.possible_agents)
    returns = {a: np.zeros(n) for a in ids}
    lengths = {a: np.zeros(n, np.int64) for a in ids}
    start = clock()
    state = venv.reset(seed=seed)
    stats.env_time_s += clock() - start
    # Double buffering (Sample Factory): with two groups of envs, one steps in its worker
    # processes while this process acts and learns for the other.
    groups = [np.asarray(g) for g in getattr(venv, "groups", [np.arange(n)])]
    in_flight: dict[int, dict] = {}
    sent = 0
    for gi, group in enumerate(groups):
        if sent < total_steps:
            in_flight[gi] = act_and_send(group, state.obs, state.alive)
            sent += group.size
    stopping = False
    gi = 0
    while in_flight:
        if gi not in in_flight:
            gi = (gi + 1) % len(groups)
            continue
        group, acted = groups[gi], in_flight.pop(gi)
        start = clock()
        state = venv.step_wait(group)
        stats.env_time_s += clock() - start
        stats.env_steps += group.size

        start = clock()
        result = {}
        for a, (envs, _, _) in acted.items():
            if not state.active[a][envs].all():
                raise RuntimeError(f"agent {a} was alive in envs {envs.tolist()} but not all of them stepped it")
            rewards = state.rewards[a][envs]
            returns[a][envs] += rewards
            lengths[a][envs] += 1
            stats.agent_steps += envs.size
            # copies (fancy indexing): the shared arrays change during the next step
            result[a] = (observations.take(state.next_obs[a], envs), rewards, state.terminated[a][envs],
                         state.truncated[a][envs])
        for i in np.flatnonzero(state.env_reset):
            for a in ids:
                stats.episode_returns.setdefault(a, []).append(float(returns[a][i]))
                stats.episode_lengths.setdefault(a, []).append(int(lengths[a][i]))
                returns[a][i], lengths[a][i] = 0.0, 0
            stats.episodes += 1
        stats.learn_time_s += clock() - start

        if not stopping and sent < total_steps:
            in_flight[gi] = act_and_send(group, state.obs, state.alive)
            sent += group.size
        start = clock()
        step_metrics = learn_from(acted, result) if learn else {}
        stats.learn_time_s += clock() - start

        if callback is not None and callback(stats.env_steps, stats, step_metrics) and not stopping:
            logger.info("run_vector_loop stopped by callback at env step %d", stats.env_steps)
            stopping = True
        gi = (gi + 1) % len(groups)
    return stats
