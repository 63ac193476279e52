"""The one environment loop: every algorithm's agents stepping N ParallelEnvs.

:func:`run_loop` IS the contract between environments and agents (acme style).
It steps a vector env (``agents/vector.py``; one PettingZoo ParallelEnv is
taken as a vector env of one) and calls the same hooks of every algorithm:

1. ``state = venv.reset(seed=seed)``: env ``i``, episode ``k`` resets with
   ``seed + i + k * N``; ``state.alive[a]`` says where agent ``a`` acts.
2. Each agent acts for its slot in every environment of a group where it is
   alive in ONE batched forward pass: ``act_batch(obs, envs)``; ACs of one algorithm and
   architecture share one grouped pass for all of them (agents/batched.py, each config's
   ``batched_acting``), each then drawing its actions with its own generators.
3. The group steps (``step_async`` / ``step_wait``); an environment whose
   agents have all finished resets itself, and its episode's returns and
   lengths are recorded.
4. Each agent that acted records that group's transitions with their
   environment index (``observe_batch``; ``next_obs`` of a finished agent is
   its true final observation, never a reset one), then ``update()`` runs
   once, doing the learning those transitions made due.
5. One :class:`Progress` goes to the callback; True stops the loop.

Learning overlaps stepping: the actions of step t + 1 are sent before the
transitions of step t are learnt from, while the environments (worker
processes) take that step, so actions lag the weights by one step (as in
Sample Factory; PPO stores the acting policy's log-probabilities and IMPALA's
V-trace corrects the lag). With worker processes the envs form two groups
(double buffering): one half steps while this process acts and learns for the
other. The order of calls is fixed, so runs are reproducible for the same N and
seed.

Asynchronous actor-learners (A3C) run the same schedule: with ``actors`` the
loop starts one thread per environment, thread k stepping env k through the
schedule below with its own agents (``actors(k)``: workers whose updates go to
shared networks); their reports reach the callback, in this thread, as the
same :class:`Progress`. The budget of environment steps is shared, claimed one
group step at a time.

Every agent has its own networks (any mix of algorithms and of Discrete/Box
action spaces). The loop times the env's steps separately from the agents'
acting and learning, so the bottleneck is visible in :class:`LoopStats`.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from agents import batched, observations
from agents.base import Agent
from agents.vector import InProcessVectorEnv
from agents.workers import EPISODE_INFO, EpisodeReport

__all__ = ["LoopStats", "Progress", "evaluate", "run_loop"]

logger = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """The running totals of :func:`run_loop` (what it returns).

    Attributes:
        env_steps: Environment steps, summed over the environments.
        agent_steps: Transitions observed, summed over agents.
        episodes: Episodes finished, all environments counted.
        episode_returns: Agent id -> list of undiscounted episode returns.
        episode_lengths: Agent id -> list of episode lengths.
        env_time_s: Wall time inside ``reset``/``step_async``/``step_wait``.
        act_time_s: Wall time inside ``act_batch``.
        learn_time_s: Wall time inside ``observe_batch`` and ``update`` (and bookkeeping).
        updates: Number of ``update()`` calls that returned metrics (learning steps).
        last_metrics: Agent id -> the last non-empty metrics dict.
        started: ``time.perf_counter()`` just before the first reset.

    With actor-learner threads the three times are summed over the threads.
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
    started: float = field(default_factory=time.perf_counter)

    @property
    def wall_time_s(self) -> float:
        """Time spent in the env plus the agents."""
        return self.env_time_s + self.act_time_s + self.learn_time_s

    def summary(self) -> dict[str, float]:
        """Namespaced timing metrics (``time/...``) for logs: steps per second since the first
        reset (process and simulator start-up excluded), and where the time went."""
        elapsed = max(time.perf_counter() - self.started, 1e-9)
        total = max(self.wall_time_s, 1e-9)
        return {
            "time/env_steps_per_s": self.env_steps / elapsed,
            "time/agent_steps_per_s": self.agent_steps / elapsed,
            "time/env_fraction": self.env_time_s / total,
            "time/act_fraction": self.act_time_s / total,
            "time/learn_fraction": self.learn_time_s / total,
        }


@dataclass(frozen=True)
class Progress:
    """What the callback of :func:`run_loop` gets after each group of environments stepped
    and was learnt from: the one progress record of every algorithm.

    Attributes:
        env_steps: Environment steps so far, all environments counted.
        agent_steps: Transitions observed so far, all agents counted.
        metrics: Agent id -> the namespaced metrics of the ``update()`` calls of this step
            that learnt something (agents that did not learn are absent).
        episodes: The episodes this step finished, one :class:`~agents.workers.EpisodeReport`
            per environment that reset (its index, each agent's return and length, and the
            env's own episode summaries).
        summaries: ``(agent id, info[EPISODE_INFO])`` for every agent whose episode ended
            this step and whose env summarised it, in environment order (what a run's
            episode records are written from, as each agent finishes).
        stats: The loop's running totals (live: they change after the callback returns).
        worker_pids: Pids of the vector env's worker processes (none in process).
    """

    env_steps: int
    agent_steps: int
    metrics: dict[str, dict[str, float]]
    episodes: list[EpisodeReport]
    summaries: list[tuple[str, dict]]
    stats: LoopStats
    worker_pids: list[int]

    @property
    def timing(self) -> dict[str, float]:
        """:meth:`LoopStats.summary` now."""
        return self.stats.summary()


Callback = Callable[[Progress], "bool | None"]


def run_loop(
    agents: Mapping[str, Agent],
    env,
    total_steps: int,
    callback: Callback | None = None,
    seed: int | None = 0,
    learn: bool = True,
    deterministic: bool = False,
    learner_threads: int = 1,
    actors: Callable[[int], Mapping[str, Agent]] | None = None,
) -> LoopStats:
    """Step ``env`` until ``total_steps`` environment steps, every agent acting and learning.

    Args:
        agents: Agent id -> agent; must cover ``env.possible_agents``.
        env: An :class:`agents.vector.VectorEnv` or ``InProcessVectorEnv``, or one
            PettingZoo-ParallelEnv-like env (stepped as a vector env of one; not closed here).
        total_steps: Environment steps to make, summed over the environments
            (each group of envs that steps adds its size; the last may overshoot).
        callback: Called with a :class:`Progress` each time a group of envs (all N, or
            one half with double buffering, or one actor-learner's env) has stepped and
            been learnt from; True stops the loop (envs already stepping finish their step).
        seed: Reset seed (env ``i``, episode ``k`` gets ``seed + i + k * N``).
        learn: If False, agents only act: evaluation.
        deterministic: Passed to ``act_batch``.
        learner_threads: Run the agents' ``update()`` calls on up to this many
            threads at once. Every AC has its own networks, optimiser and
            generators, so the updates are independent and the result is the
            same bit for bit (torch releases the GIL inside its ops; each thread
            uses the process's torch thread count). While PPO updates, its
            environments wait, so a second core is otherwise idle.
        actors: Actor-learner threads (A3C): ``actors(k)`` gives the agents (id -> agent)
            that thread k acts and learns with in env k; every thread runs the same
            schedule, sharing the budget. ``agents`` are then the shared agents.

    Returns:
        The :class:`LoopStats` of the run.

    Raises:
        KeyError: If the env has an agent id that ``agents`` does not cover.
    """
    venv = env if hasattr(env, "step_wait") else InProcessVectorEnv([lambda: env])
    missing = sorted(set(venv.possible_agents) - set(agents))
    if missing:
        raise KeyError(f"run_loop has no agent for env agent(s) {missing}; pass one Agent per id")
    if learn and actors is None:
        for agent in agents.values():
            agent.prepare_envs(venv.num_envs)
    stats, budget, stop = LoopStats(), _Budget(total_steps), threading.Event()
    state = venv.reset(seed=seed)
    stats.env_time_s += time.perf_counter() - stats.started

    def report(step: _Report) -> None:
        _fold(stats, step, venv.possible_agents)
        progress = Progress(stats.env_steps, stats.agent_steps, step.metrics, step.episodes, step.summaries,
                            stats, list(getattr(venv, "pids", [])))
        if callback is not None and callback(progress) and not stop.is_set():
            logger.info("run_loop stopped by callback at env step %d", stats.env_steps)
            stop.set()

    if actors is not None:
        _run_actor_threads(venv, state, actors, budget, stop, learn, deterministic, report)
        return stats
    groups = [np.asarray(g) for g in getattr(venv, "groups", [np.arange(venv.num_envs)])]
    pool = ThreadPoolExecutor(learner_threads, "cosim-learner") if learn and learner_threads > 1 else None
    try:
        for step in _schedule(venv, groups, state, agents, budget, stop, learn, deterministic, pool):
            report(step)
    finally:
        if pool is not None:
            pool.shutdown()
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

    def stop(progress: Progress) -> bool:
        return progress.stats.episodes >= episodes

    stats = run_loop(agents, env, total_steps=10**9, callback=stop, seed=seed, learn=False, deterministic=deterministic)
    return stats.episode_returns


# ----------------------------------------------------------------------------- the schedule


class _Budget:
    """The environment steps of a run, claimed before a group steps (shared by actor threads)."""

    def __init__(self, total: int):
        self.total, self.claimed, self.done = int(total), 0, 0
        self.lock = threading.Lock()

    def claim(self, n: int) -> bool:
        """Claim ``n`` steps unless the budget is spent (the last claim may overshoot it)."""
        with self.lock:
            if self.claimed >= self.total:
                return False
            self.claimed += n
            return True

    def complete(self, n: int) -> None:
        with self.lock:
            self.done += n

    def remaining(self) -> float:
        """The fraction of the budget not yet stepped, 1 -> 0 (:attr:`Agent.progress_remaining`)."""
        return max(0.0, 1.0 - self.done / max(self.total, 1))


@dataclass
class _Report:
    """One group stepped and learnt from, as :func:`_schedule` reports it."""

    env_steps: int
    agent_steps: int
    metrics: dict[str, dict[str, float]]
    episodes: list[EpisodeReport]
    summaries: list[tuple[str, dict]]
    env_time_s: float
    act_time_s: float
    learn_time_s: float


def _fold(stats: LoopStats, step: _Report, ids) -> None:
    """Add one report to the running totals."""
    stats.env_steps += step.env_steps
    stats.agent_steps += step.agent_steps
    stats.env_time_s += step.env_time_s
    stats.act_time_s += step.act_time_s
    stats.learn_time_s += step.learn_time_s
    for episode in step.episodes:
        for a in ids:
            stats.episode_returns.setdefault(a, []).append(episode.returns[a])
            stats.episode_lengths.setdefault(a, []).append(episode.lengths[a])
        stats.episodes += 1
    for a, metrics in step.metrics.items():
        stats.last_metrics[a] = metrics
        stats.updates += 1


def _schedule(venv, groups: list[np.ndarray], state, agents: Mapping[str, Agent], budget: _Budget,
              stop: threading.Event, learn: bool, deterministic: bool,
              pool: ThreadPoolExecutor | None) -> Iterator[_Report]:
    """THE stepping schedule: the groups of ``venv`` in turn, each acting for its next step
    before learning from its last; one :class:`_Report` per group step. Stops sending when
    ``stop`` is set or the budget is spent, and ends when nothing is in flight."""
    clock = time.perf_counter
    n, ids = venv.num_envs, list(venv.possible_agents)
    returns = {a: np.zeros(n) for a in ids}
    lengths = {a: np.zeros(n, np.int64) for a in ids}
    extras: list[dict[str, dict]] = [{} for _ in range(n)]
    times = {"env": 0.0, "act": 0.0}

    grouper = batched.Grouper()  # the ACs' stacked weights for grouped acting, kept between steps

    def act_and_send(group: np.ndarray, obs_rows, alive) -> dict:
        """Act for every agent alive in the envs of ``group`` (one forward pass per agent, or one
        for all the ACs that act together: agents/batched.py) and send."""
        start = clock()
        acted: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # id -> (envs, obs copy, actions)
        full_actions = {}
        requests = []
        for a in ids:
            envs = group[alive[a][group]]
            if envs.size:  # a copy: the vector env overwrites its arrays on step
                requests.append((a, envs, observations.take(obs_rows[a], envs)))
        chosen = batched.act_all(agents, requests, deterministic, grouper)
        for a, envs, obs in requests:
            actions = chosen[a]
            batch = np.zeros((n, *actions.shape[1:]), actions.dtype)
            batch[envs] = actions
            full_actions[a] = batch
            acted[a] = (envs, obs, actions)
        times["act"] += clock() - start
        start = clock()
        venv.step_async(full_actions, group)
        times["env"] += clock() - start
        return acted

    def learn_from(acted, result) -> dict[str, dict[str, float]]:
        for a, (envs, obs, actions) in acted.items():
            next_obs, rewards, terminated, truncated = result[a]
            agents[a].observe_batch(obs, actions, rewards, next_obs, terminated, truncated, envs)
            agents[a].progress_remaining = budget.remaining()
        if pool is not None and len(acted) > 1:
            updates = list(pool.map(lambda a: agents[a].update(), acted))
        else:
            updates = [agents[a].update() for a in acted]
        return {a: metrics for a, metrics in zip(acted, updates, strict=True) if metrics}

    in_flight: dict[int, dict] = {}
    for gi, group in enumerate(groups):
        if budget.claim(group.size):
            in_flight[gi] = act_and_send(group, state.obs, state.alive)
    gi = 0
    while in_flight:
        if gi not in in_flight:
            gi = (gi + 1) % len(groups)
            continue
        group, acted = groups[gi], in_flight.pop(gi)
        start = clock()
        state = venv.step_wait(group)
        times["env"] += clock() - start
        budget.complete(group.size)

        start = clock()
        result, agent_steps = _transitions(state, acted, returns, lengths)
        summaries, episodes = _episodes(state, group, ids, returns, lengths, extras)
        bookkeeping = clock() - start

        if not stop.is_set() and budget.claim(group.size):
            in_flight[gi] = act_and_send(group, state.obs, state.alive)
        start = clock()
        metrics = learn_from(acted, result) if learn else {}
        learn_time = bookkeeping + clock() - start
        yield _Report(group.size, agent_steps, metrics, episodes, summaries, times["env"], times["act"], learn_time)
        times["act"] = times["env"] = 0.0
        gi = (gi + 1) % len(groups)


def _transitions(state, acted, returns, lengths) -> tuple[dict, int]:
    """Per agent that acted, its transitions of ``state`` (copies) and the count of them; adds
    their rewards and steps to the running episode ``returns`` and ``lengths``.

    Raises:
        RuntimeError: an agent acted in an env that did not step it.
    """
    result, count = {}, 0
    for a, (envs, _, _) in acted.items():
        if not state.active[a][envs].all():
            raise RuntimeError(f"agent {a} was alive in envs {envs.tolist()} but not all of them stepped it")
        rewards = state.rewards[a][envs]
        returns[a][envs] += rewards
        lengths[a][envs] += 1
        count += envs.size
        # copies (fancy indexing): the shared arrays change during the next step
        result[a] = (observations.take(state.next_obs[a], envs), rewards, state.terminated[a][envs],
                     state.truncated[a][envs])
    return result, count


def _episodes(state, group: np.ndarray, ids, returns, lengths,
              extras: list[dict]) -> tuple[list[tuple[str, dict]], list[EpisodeReport]]:
    """The env summaries of agents that finished in ``group`` this step, and a report per env
    that reset (its running returns and lengths then start again from 0)."""
    summaries = []
    for i in group.tolist():
        for a, info in state.infos[i].items():
            if isinstance(info, Mapping) and EPISODE_INFO in info:
                summaries.append((a, info[EPISODE_INFO]))
                extras[i][a] = info[EPISODE_INFO]
    episodes = []
    for i in np.flatnonzero(state.env_reset).tolist():
        episodes.append(EpisodeReport(i, {a: float(returns[a][i]) for a in ids},
                                      {a: int(lengths[a][i]) for a in ids}, extras[i]))
        extras[i] = {}
        for a in ids:
            returns[a][i], lengths[a][i] = 0.0, 0
    return summaries, episodes


def _run_actor_threads(venv, state, actors: Callable[[int], Mapping[str, Agent]], budget: _Budget,
                       stop: threading.Event, learn: bool, deterministic: bool,
                       report: Callable[[_Report], None]) -> None:
    """One thread per env of ``venv``, thread k running :func:`_schedule` on env k with
    ``actors(k)``; their reports go to ``report`` in this thread, and a thread's exception
    is raised here. On any exit the threads are stopped and joined; if one does not end
    (stuck in a dead env), ``venv`` is closed so that it gets an error and ends."""
    reports: queue.Queue = queue.Queue()

    def body(k: int) -> None:
        try:
            own = actors(k)
            if learn:
                for agent in own.values():
                    agent.prepare_envs(venv.num_envs)
            for step in _schedule(venv, [np.array([k])], state, own, budget, stop, learn, deterministic, None):
                reports.put(("report", step))
        except BaseException as exc:  # noqa: BLE001 - everything must reach the loop's thread
            stop.set()
            reports.put(("error", exc))
        finally:
            reports.put(("exit", None))

    threads = [threading.Thread(target=body, args=(k,), name=f"cosim-actor-{k}", daemon=True)
               for k in range(venv.num_envs)]
    logger.info("run_loop: %d actor-learner threads, env pids %s, %d steps", len(threads),
                getattr(venv, "pids", []), budget.total)
    try:
        for thread in threads:
            thread.start()
        running = len(threads)
        while running:
            try:
                kind, payload = reports.get(timeout=0.5)
            except queue.Empty:
                continue
            if kind == "exit":
                running -= 1
            elif kind == "error":
                raise payload
            else:
                report(payload)
    finally:
        stop.set()
        for thread in threads:  # each finishes the env step it is in
            thread.join(timeout=10.0)
        if any(thread.is_alive() for thread in threads):
            venv.close()
            for thread in threads:
                thread.join(timeout=5.0)
