"""What A3C and IMPALA share on the one vector env (``agents/vector.py``).

Every algorithm steps its environments through the same code: a
:class:`~agents.vector.VectorEnv` of N worker processes (or, for one
environment, the in-process version). PPO, DQN, DDPG and TD3 drive it with
:func:`agents.loop.run_vector_loop`; IMPALA's learner drives it with batched
acting and double buffering (:func:`agents.impala.train_impala`); A3C's learner
threads each own one env index of it (:func:`agents.a3c.train_a3c`). This
module holds the pieces the two asynchronous trainers share:

* :func:`vector_env`: the vector env of a trainer's ``env_fn`` (a factory, or
  one factory per environment; Gymnasium envs become one-agent ParallelEnvs).
* :func:`act_for`: sample every live agent's action in some envs with ONE
  forward pass per agent, keeping the behaviour log-probabilities.
* :class:`Unrolls`: per-(env, agent) :class:`~agents.workers.RolloutBuilder`
  that cut unrolls; :func:`record` feeds them a vector step's transitions
  (the TRUE final observation at an episode end, never the reset one).
* :class:`EpisodeTracker`: per-env returns, lengths and the env's own episode
  summaries -> :class:`~agents.workers.EpisodeReport`.
* :func:`run_threads` / :func:`learner_thread` / :class:`ThreadRun`: A3C's
  actor-learner threads, thread k owning env index k (the vector env allows
  concurrent steps of disjoint envs); the algorithm's update is a callable.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from agents import observations
from agents.networks import obs_to_tensor
from agents.vector import VecStep, make_vector_env
from agents.workers import (
    EPISODE_INFO,
    EpisodeReport,
    Rollout,
    RolloutBuilder,
    TrainProgress,
    make_parallel_env,
    private_copy,
    rates,
    worker_seed,
)

__all__ = ["EpisodeTracker", "ThreadRun", "Unrolls", "act_for", "check_agents", "learner_thread", "record",
           "run_threads", "vector_env"]

logger = logging.getLogger(__name__)

# agent id -> (env indices, observations (copied), actions, behaviour log-probs)
Acted = dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def vector_env(env_fn: Callable[[], Any] | Sequence[Callable[[], Any]], num_envs: int | None,
               start_method: str = "spawn", processes: bool | None = None):
    """The vector env a trainer steps: ``num_envs`` copies of ``env_fn``, or one env per factory.

    Args:
        env_fn: A picklable zero-argument factory (a ParallelEnv or a Gymnasium env),
            or a sequence of them, one per environment.
        num_envs: Environments to build from a single factory (default 2); for a
            sequence, None or its length.
        start_method: ``"spawn"`` or ``"forkserver"`` for the worker processes.
        processes: Worker processes (True) or in process (False); default: processes
            when there is more than one environment.

    Raises:
        ValueError: For fewer than one environment, or a sequence whose length is not ``num_envs``.
    """
    if callable(env_fn):
        fns = [env_fn] * (2 if num_envs is None else int(num_envs))
    else:
        fns = list(env_fn)
        if num_envs is not None and num_envs != len(fns):
            raise ValueError(f"num_envs={num_envs} but {len(fns)} env factories were given")
    if not fns:
        raise ValueError("need at least one environment (num_envs >= 1)")
    wrapped = [functools.partial(make_parallel_env, fn) for fn in fns]
    return make_vector_env(wrapped, processes=processes, start_method=start_method)


def check_agents(venv, agent_ids: Sequence[str]) -> None:
    """Refuse an env with agents that have no model."""
    unknown = sorted(set(venv.possible_agents) - set(agent_ids))
    if unknown:
        raise ValueError(f"environment reports agents {unknown} that have no model; "
                         f"pass every learning agent in agent_ids (got {list(agent_ids)})")


@torch.no_grad()
def act_for(models: Mapping[str, torch.nn.Module], generators: Mapping[str, torch.Generator],
            envs: np.ndarray, obs: Mapping[str, np.ndarray], alive: Mapping[str, np.ndarray],
            num_envs: int) -> tuple[Acted, dict[str, np.ndarray]]:
    """Sample each agent's actions in the envs ``envs`` where it is alive, one forward pass per agent.

    Args:
        models: Agent id -> ``ActorCritic`` (``obs -> (logits, values)``).
        generators: Agent id -> the generator its actions are drawn with.
        envs: Env indices to act in.
        obs, alive: A :class:`~agents.vector.VecStep`'s ``obs`` and ``alive``.
        num_envs: N, the width of the action arrays for ``step_async``.

    Returns:
        ``(acted, actions)``: what each agent did (for :func:`record`), and the
        ``{agent: (N,) int64}`` actions to send (rows outside ``envs`` unused).
    """
    acted: Acted = {}
    actions: dict[str, np.ndarray] = {}
    for aid, model in models.items():
        rows = envs[alive[aid][envs]]
        if rows.size == 0:
            continue
        batch = observations.take(obs[aid], rows)  # a copy: the vector env overwrites its arrays on step
        device = next(model.parameters()).device
        logits, _ = model(obs_to_tensor(batch, device))
        log_probs = torch.log_softmax(logits, dim=-1)
        chosen = torch.multinomial(log_probs.exp(), 1, generator=generators[aid])
        behaviour = log_probs.gather(1, chosen).squeeze(1)
        chosen_np = chosen.squeeze(1).cpu().numpy().astype(np.int64)
        acted[aid] = (rows, batch, chosen_np, behaviour.cpu().numpy().astype(np.float32))
        full = np.zeros(num_envs, np.int64)
        full[rows] = chosen_np
        actions[aid] = full
    return acted, actions


class Unrolls:
    """Per-(env, agent) rollout builders: each cuts its own stream of consecutive steps."""

    def __init__(self):
        self.builders: dict[tuple[str, int], RolloutBuilder] = {}
        self.versions: dict[tuple[str, int], int] = {}

    def add(self, aid: str, env: int, obs, action, reward, next_obs, terminated, truncated, log_prob,
            version: int = 0) -> None:
        """One transition of agent ``aid`` in env ``env``; ``version`` tags the unroll's first step."""
        key = (aid, env)
        builder = self.builders.get(key)
        if builder is None:
            builder = self.builders[key] = RolloutBuilder(aid)
        if not len(builder):
            self.versions[key] = version
        builder.add(obs, action, reward, next_obs, terminated, truncated, log_prob)

    def take_ready(self, length: int) -> list[tuple[str, int, Rollout, int]]:
        """``(agent, env, rollout, version)`` for every builder holding ``length`` steps, in key order."""
        out = []
        for key in sorted(self.builders):
            if len(self.builders[key]) >= length:
                out.append((*key, self.builders[key].build(), self.versions[key]))
        return out

    def take_all(self) -> list[tuple[str, int, Rollout, int]]:
        """Every non-empty builder's rollout (A3C: the end of an n-step segment)."""
        return self.take_ready(1)


def record(unrolls: Unrolls, acted: Acted, step: VecStep, reward_scale: float,
           versions: Mapping[str, int] | None = None) -> int:
    """Add the transitions that followed ``acted`` (from ``step``) to ``unrolls``; return their count.

    Raises:
        RuntimeError: If an agent that acted in an env has no transition there.
    """
    count = 0
    for aid, (envs, obs, actions, log_probs) in acted.items():
        if not step.active[aid][envs].all():
            raise RuntimeError(f"agent {aid} acted in envs {envs.tolist()} but not all of them stepped it")
        next_obs = observations.take(step.next_obs[aid], envs)  # a copy (fancy indexing)
        rewards = step.rewards[aid][envs] * reward_scale
        terminated, truncated = step.terminated[aid][envs], step.truncated[aid][envs]
        version = 0 if versions is None else versions[aid]
        for j, env in enumerate(envs.tolist()):
            unrolls.add(aid, env, observations.take(obs, j), actions[j], rewards[j],
                        observations.take(next_obs, j), terminated[j], truncated[j], log_probs[j], version)
        count += envs.size
    return count


class EpisodeTracker:
    """Per-env episode returns and lengths (raw rewards) and the env's own summaries."""

    def __init__(self, agent_ids: Sequence[str], num_envs: int):
        self.ids = list(agent_ids)
        self.returns = {a: np.zeros(num_envs) for a in self.ids}
        self.lengths = {a: np.zeros(num_envs, np.int64) for a in self.ids}
        self.extras: list[dict[str, dict]] = [{} for _ in range(num_envs)]

    def record(self, step: VecStep, envs: Sequence[int]) -> list[EpisodeReport]:
        """Account the step of ``envs``; return the episodes it finished."""
        for a in self.ids:
            active = step.active[a]
            self.returns[a][active] += step.rewards[a][active]
            self.lengths[a][active] += 1
        finished = []
        for i in envs:
            for a, info in step.infos[i].items():
                if isinstance(info, Mapping) and EPISODE_INFO in info:
                    self.extras[i][a] = info[EPISODE_INFO]
            if step.env_reset[i]:
                played = [a for a in self.ids if self.lengths[a][i] > 0]
                finished.append(EpisodeReport(int(i), {a: float(self.returns[a][i]) for a in played},
                                              {a: int(self.lengths[a][i]) for a in played}, self.extras[i]))
                self.extras[i] = {}
                for a in self.ids:
                    self.returns[a][i], self.lengths[a][i] = 0.0, 0
        return finished


# ----------------------------------------------------------------------------- learner threads (A3C)


class ThreadRun:
    """What the learner threads of one run share; counters are guarded by ``lock``.

    Args:
        agents: Agent id -> agent with a ``model`` (the shared network each thread copies).
        segment_steps: Env steps a thread takes between two updates (A3C's ``n_steps``).
        reward_scale: Multiplies the rewards the threads learn from.
        total_steps: Env steps of the run, all threads counted.
        seed: Thread k samples with a generator seeded ``worker_seed(seed, k)``; also the reset seed.
        learn: ``learn(run, agent_id, local_model, rollout, env_steps_done, updates_seen) -> metrics``:
            applies one segment's update to the shared agent (:func:`agents.a3c.train_a3c`).
    """

    def __init__(self, agents: Mapping[str, Any], segment_steps: int, reward_scale: float, total_steps: int,
                 seed: int, learn: Callable[..., dict[str, float]]):
        self.agents, self.segment_steps, self.reward_scale = dict(agents), segment_steps, reward_scale
        self.total_steps, self.seed, self.learn = total_steps, seed, learn
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.reports: queue.Queue = queue.Queue()
        self.claimed = 0  # env steps handed out to segments (never above total_steps + segment_steps)
        self.done = 0  # env steps taken
        self.agent_steps = 0  # transitions recorded
        self.started = time.perf_counter()  # reset by run_threads just before the first env reset


def learner_thread(k: int, venv, state: VecStep, run: ThreadRun) -> None:
    """Actor-learner k: owns env index k of ``venv``; segments of ``segment_steps``, then ``run.learn``."""
    try:
        ids = list(venv.possible_agents)
        local = {aid: private_copy(run.agents[aid].model) for aid in ids}
        generators = dict.fromkeys(ids, torch.Generator().manual_seed(worker_seed(run.seed, k)))
        envs, obs, alive = np.array([k]), state.obs, state.alive
        tracker = EpisodeTracker(ids, venv.num_envs)
        while not run.stop.is_set():
            with run.lock:
                if run.claimed >= run.total_steps:
                    break
                run.claimed += run.segment_steps
            seen = {}
            for aid in ids:  # 1. sync the local copy with the shared weights
                with run.lock:
                    seen[aid] = run.agents[aid].num_updates
                local[aid].load_state_dict(run.agents[aid].model.state_dict())
            unrolls, episodes = Unrolls(), []
            for _ in range(run.segment_steps):  # 2. act in env k
                if run.stop.is_set():
                    return
                acted, actions = act_for(local, generators, envs, obs, alive, venv.num_envs)
                venv.step_async(actions, envs)
                step = venv.step_wait(envs)
                transitions = record(unrolls, acted, step, run.reward_scale)
                episodes += tracker.record(step, envs)
                obs, alive = step.obs, step.alive  # only row k is read: this thread's env
                with run.lock:
                    run.agent_steps += transitions
            with run.lock:
                run.done += run.segment_steps
                done = run.done
            metrics = {aid: run.learn(run, aid, local[aid], rollout, done, seen[aid])  # 3. update
                       for aid, _env, rollout, _ in unrolls.take_all()}
            run.reports.put(("report", k, done, episodes, metrics))
    except BaseException as exc:  # noqa: BLE001 - everything must reach the trainer thread
        run.stop.set()
        run.reports.put(("error", k, exc))
    finally:
        run.reports.put(("exit", k))


def run_threads(run: ThreadRun, venv, callback: Callable[[TrainProgress], bool | None] | None,
                name: str) -> dict[str, Any]:
    """Run one :func:`learner_thread` per env of ``venv`` (threads ``<name>-<k>``); report; clean up.

    The calling thread hands each segment report to ``callback`` (True stops the run)
    and re-raises a thread's exception; on any exit the threads are stopped and joined
    and ``venv`` is closed (its worker processes with it). Returns ``run.agents``.
    """
    threads: list[threading.Thread] = []
    start = time.monotonic()
    try:
        check_agents(venv, list(run.agents))
        run.started = time.perf_counter()
        state = venv.reset(seed=run.seed)
        logger.info("%s: %d learner threads, env pids %s, %d steps", name, venv.num_envs, venv.pids,
                    run.total_steps)
        for k in range(venv.num_envs):
            threads.append(threading.Thread(target=learner_thread, args=(k, venv, state, run),
                                            name=f"{name}-{k}", daemon=True))
            threads[-1].start()
        running, stopping, done = len(threads), False, 0
        while running:
            try:
                kind, _k, *rest = run.reports.get(timeout=0.5)
            except queue.Empty:
                continue
            if kind == "exit":
                running -= 1
            elif kind == "error":
                raise rest[0]
            elif not stopping:
                done = max(done, rest[0])  # reports of two threads may arrive out of order
                progress = TrainProgress(done, rest[1], run.agents, venv.pids, time.monotonic() - start, rest[2],
                                         rates(run.done, run.agent_steps, run.started))
                if callback is not None and callback(progress):
                    logger.info("%s: callback stopped training at %d steps", name, done)
                    stopping = True
                    run.stop.set()
    finally:
        run.stop.set()
        for thread in threads:  # each finishes the env step it is in
            thread.join(timeout=10.0)
        venv.close()  # a thread stuck in a dead env gets an error and ends
        for thread in threads:
            thread.join(timeout=5.0)
    logger.info("%s: done, %d env steps in %.1f s", name, run.done, time.monotonic() - start)
    return run.agents
