"""Worker processes for the asynchronous trainers (A3C, IMPALA).

The driving simulator allows one simulation per process, so asynchronous
training means processes, each owning its environment. This module holds the
machinery both asynchronous algorithms share, and nothing algorithm-specific:

* :class:`WorkerPool`: starts N worker processes (``spawn`` or ``forkserver``),
  hands each a :class:`WorkerLink` (stop event + result queue), re-raises a
  worker's exception in the parent as :class:`WorkerError` carrying the
  worker's traceback text, and guarantees cleanup: on a normal end, on an
  exception, and on ``KeyboardInterrupt``/SIGINT/SIGTERM in the parent every
  worker is joined, or terminated, or killed. No orphan processes.
* :class:`Rollout` / :class:`RolloutBuilder`: one agent's consecutive
  transitions, the unit A3C learns from and IMPALA ships to its learner.
* :class:`EnvRunner`: steps a PettingZoo-ParallelEnv-like environment with one
  policy per agent id and cuts its stream into per-agent rollouts;
  :func:`make_parallel_env` builds the env inside a worker (a Gymnasium env is
  wrapped as a one-agent ParallelEnv); :func:`categorical_policy` samples from
  an actor-critic's logits.
* :class:`TrainProgress`: what an asynchronous trainer hands its callback.

Shutdown order (why it is safe): the parent sets the stop event, drains the
queues while it joins (a child blocked on a full pipe could never exit
otherwise), then ``terminate()`` (SIGTERM) the stragglers, then ``kill()``
(SIGKILL). Workers ignore SIGINT, so a Ctrl-C in a terminal (delivered to the
whole process group) is handled once, by the parent. A worker also dies when
the parent dies without cleaning up (SIGKILL): see :func:`_die_with_owner`.
"""

from __future__ import annotations

import copy
import logging
import os
import queue
import signal
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp

from agents.errors import CosimError

__all__ = [
    "EnvRunner",
    "EpisodeReport",
    "agents_for",
    "Rollout",
    "RolloutBuilder",
    "TrainProgress",
    "WorkerError",
    "WorkerLink",
    "WorkerPool",
    "categorical_policy",
    "get_context",
    "live_pids",
    "linear_learning_rate",
    "make_parallel_env",
    "private_copy",
    "worker_seed",
]

logger = logging.getLogger(__name__)

START_METHODS = ("spawn", "forkserver")


class WorkerError(CosimError, RuntimeError):
    """A worker process failed; the message carries the worker's own traceback.

    Attributes:
        worker_index: Index of the failed worker.
        worker_traceback: The traceback text formatted inside the worker, or ""
            when the worker died without a Python exception (a signal, a crash).
    """

    def __init__(self, worker_index: int, message: str, worker_traceback: str = ""):
        self.worker_index = worker_index
        self.worker_traceback = worker_traceback
        text = f"worker {worker_index} failed: {message}"
        if worker_traceback:
            text += f"\n--- traceback in worker {worker_index} ---\n{worker_traceback.rstrip()}"
        super().__init__(text)


def get_context(start_method: str = "spawn", preload: Sequence[str] = ("agents.workers",)):
    """Return the torch multiprocessing context for ``start_method``.

    ``fork`` is refused: forking a process that holds torch threads (or a
    simulator) can deadlock, and a forked child would share the parent's SUMO.

    Args:
        start_method: ``"spawn"`` (default; each worker imports everything
            afresh, ~2 s) or ``"forkserver"`` (workers fork from a server that
            imported ``preload`` once, ~0.05 s each).
        preload: Modules the fork server imports when it starts (forkserver
            only; the first start in a process fixes them). Nothing
            simulator-side belongs here: each worker builds its own simulation.

    Raises:
        ValueError: For a start method other than ``spawn`` or ``forkserver``.
    """
    if start_method not in START_METHODS:
        raise ValueError(
            f"start_method must be one of {START_METHODS}, got {start_method!r}; "
            "'fork' is unsafe with torch threads and one-simulation-per-process simulators"
        )
    context = mp.get_context(start_method)
    if start_method == "forkserver":
        context.set_forkserver_preload(list(preload))
    return context


def live_pids(pids: Sequence[int]) -> list[int]:
    """The pids among ``pids`` that are still running (zombies count as gone).

    Uses ``os.kill(pid, 0)`` and, on Linux, ``/proc/<pid>/stat`` to tell a
    zombie (exited, not yet reaped) from a live process. Used to check that a
    trainer left no worker behind.
    """
    alive = []
    for pid in pids:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            continue
        except PermissionError:  # exists, owned by someone else
            pass
        try:
            with open(f"/proc/{pid}/stat") as stat:
                state = stat.read().rsplit(")", 1)[1].split()[0]
        except OSError:
            state = "?"
        if state not in ("Z", "X"):
            alive.append(pid)
    return alive


def worker_seed(seed: int, index: int) -> int:
    """An independent, reproducible seed for worker ``index`` of a run seeded ``seed``."""
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


@dataclass
class WorkerLink:
    """What a worker receives to talk to its parent (picklable).

    Attributes:
        index: Worker index, 0..N-1.
        stop_event: Set by the parent when every worker must stop.
        results: Queue of messages for the parent.
        owner_pid: Pid of the process that owns the pool (the trainer).
    """

    index: int
    stop_event: Any
    results: Any
    owner_pid: int

    def should_stop(self) -> bool:
        """True when the owner asked every worker to stop."""
        return self.stop_event.is_set()

    def send(self, message: Any) -> bool:
        """Put ``message`` on the result queue, waiting while it is full.

        Returns:
            False if the worker was told to stop before the message fit.
        """
        while not self.should_stop():
            try:
                self.results.put(message, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False


def _die_with_owner(owner_pid: int, poll_s: float = 0.5) -> None:
    """Make sure this worker dies when the pool's owner dies, even by SIGKILL.

    Nothing in the owner runs on SIGKILL, and a worker stuck in a simulator
    never looks at the stop event. Two guards: Linux's ``PR_SET_PDEATHSIG``
    (the kernel kills us with our parent; our parent is the owner under
    ``spawn`` but the fork server under ``forkserver``, which outlives the
    owner while any worker lives), and a watchdog thread that polls the
    owner's pid and kills this process once the owner is gone.
    """
    try:
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the watchdog alone
        pass

    def watch() -> None:
        while live_pids([owner_pid]):
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="owner-watchdog", daemon=True).start()


def _worker_entry(target: Callable, link: WorkerLink, args: tuple, errors) -> None:
    """Body of every worker process: set up, run ``target``, report any exception."""
    # One intra-op thread per worker: N workers with N threads each oversubscribe the CPU.
    torch.set_num_threads(1)
    # The parent owns Ctrl-C; it tells us to stop through the event.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_owner(link.owner_pid)
    try:
        target(link, *args)
    except BaseException as exc:  # KeyboardInterrupt, SystemExit too: all must reach the parent
        errors.put((link.index, f"{type(exc).__name__}: {exc}", traceback.format_exc()))
        raise SystemExit(1) from None


class WorkerPool:
    """N worker processes running ``target(link, *args)``, as a context manager.

    Example::

        ctx = get_context("spawn")
        counter = ctx.Value("q", 0)
        with WorkerPool(run_worker, [(env_fn, counter)] * 2, context=ctx) as pool:
            while not done:
                message = pool.get(timeout=1.0)  # raises WorkerError if a worker failed

    Args:
        target: A picklable top-level function ``target(link: WorkerLink, *args)``.
        worker_args: One tuple of extra arguments per worker; its length is N.
        context: A multiprocessing context from :func:`get_context`; shared
            objects passed in ``worker_args`` must come from the same context.
        join_timeout: Seconds to wait for workers to stop before terminating them.
        queue_size: Bound of the result queue (0 = unbounded); a bound gives
            back-pressure to producers that outpace the parent.
        handle_sigterm: Turn SIGTERM in the parent into ``KeyboardInterrupt``
            while the pool is open, so ``kill <pid>`` also cleans up (main
            thread only; elsewhere the existing handler is left alone).
    """

    def __init__(
        self,
        target: Callable,
        worker_args: Sequence[tuple],
        *,
        context=None,
        join_timeout: float = 5.0,
        queue_size: int = 0,
        handle_sigterm: bool = True,
    ):
        if not worker_args:
            raise ValueError("WorkerPool needs at least one worker (worker_args is empty)")
        if join_timeout <= 0:
            raise ValueError(f"join_timeout must be > 0 seconds, got {join_timeout}")
        self.context = context if context is not None else get_context("spawn")
        self.target = target
        self.worker_args = [tuple(args) for args in worker_args]
        self.join_timeout = join_timeout
        self.handle_sigterm = handle_sigterm
        self.stop_event = self.context.Event()
        self.results = self.context.Queue(maxsize=queue_size)
        self.errors = self.context.Queue()
        self.processes: list = []
        self._previous_sigterm = None

    @property
    def pids(self) -> list[int]:
        """Pids of the started workers (empty before start)."""
        return [process.pid for process in self.processes]

    def __enter__(self) -> WorkerPool:
        self.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def start(self) -> None:
        """Start every worker (daemon processes: they die with an exiting parent)."""
        if self.processes:
            raise RuntimeError("WorkerPool.start() called twice")
        self._install_sigterm_handler()
        try:
            for index, args in enumerate(self.worker_args):
                link = WorkerLink(index, self.stop_event, self.results, os.getpid())
                process = self.context.Process(
                    target=_worker_entry,
                    args=(self.target, link, args, self.errors),
                    name=f"cosim-worker-{index}",
                    daemon=True,
                )
                process.start()
                self.processes.append(process)
        except BaseException:
            self.close()
            raise
        logger.debug("started %d workers: pids %s", len(self.processes), self.pids)

    def get(self, timeout: float = 1.0) -> Any | None:
        """Next message from any worker, or None after ``timeout`` seconds.

        Raises:
            WorkerError: If a worker raised (with its traceback) or died with a
                non-zero exit code.
        """
        self.check()
        try:
            return self.results.get(timeout=timeout)
        except queue.Empty:
            self.check()
            return None

    def check(self) -> None:
        """Raise :class:`WorkerError` if any worker has failed."""
        try:
            index, message, worker_traceback = self.errors.get_nowait()
        except queue.Empty:
            pass
        else:
            raise WorkerError(index, message, worker_traceback)
        for index, process in enumerate(self.processes):
            if process.exitcode not in (None, 0):
                # The error report may still be in flight through the pipe.
                try:
                    index, message, worker_traceback = self.errors.get(timeout=1.0)
                except queue.Empty:
                    raise WorkerError(index, f"exited with code {process.exitcode}") from None
                raise WorkerError(index, message, worker_traceback)

    def all_exited(self) -> bool:
        """True when every worker process has ended."""
        return all(process.exitcode is not None for process in self.processes)

    def close(self) -> None:
        """Stop, join, terminate, then kill every worker; idempotent."""
        try:
            self.stop_event.set()
            deadline = time.monotonic() + self.join_timeout
            while time.monotonic() < deadline and not self.all_exited():
                self._drain()
                for process in self.processes:
                    process.join(timeout=0.05)
            for process in self.processes:
                if process.is_alive():
                    logger.warning("worker pid %d did not stop in time; terminating", process.pid)
                    process.terminate()
                    process.join(timeout=1.0)
                if process.is_alive():
                    process.kill()
                    process.join(timeout=1.0)
            self._drain()
        finally:
            self._restore_sigterm_handler()

    def _drain(self) -> None:
        # Emptying the queues unblocks workers whose feeder thread waits on a full pipe.
        for q in (self.results, self.errors):
            try:
                while True:
                    q.get_nowait()
            except (queue.Empty, OSError, ValueError):
                pass

    def _install_sigterm_handler(self) -> None:
        if not self.handle_sigterm or threading.current_thread() is not threading.main_thread():
            return

        def _raise_interrupt(signum, frame):
            raise KeyboardInterrupt(f"received signal {signum}")

        self._previous_sigterm = signal.signal(signal.SIGTERM, _raise_interrupt)

    def _restore_sigterm_handler(self) -> None:
        if self._previous_sigterm is not None:
            signal.signal(signal.SIGTERM, self._previous_sigterm)
            self._previous_sigterm = None


# --------------------------------------------------------------------------- rollouts


@dataclass
class Rollout:
    """One agent's consecutive transitions ``t = 0..T-1`` (time-major numpy arrays).

    Within a rollout the observation after step t is ``obs[t + 1]``, except
    where an episode ended or the rollout stops; those next observations are
    kept in ``final_obs`` (rows) at ``final_index`` (steps). That keeps a
    truncated episode bootstrappable without shipping every image twice.

    Attributes:
        agent_id: The agent the transitions belong to.
        obs: ``(T, *obs_shape)`` observations ``s_t``.
        actions: ``(T,)`` int64 actions.
        rewards: ``(T,)`` float32 rewards.
        terminateds: ``(T,)`` bool, the episode terminated at t.
        truncateds: ``(T,)`` bool, the episode was cut at t.
        log_probs: ``(T,)`` float32 ``log mu(a_t|s_t)`` of the policy that acted.
        final_obs: ``(K, *obs_shape)`` next observations that are not ``obs[t+1]``.
        final_index: ``(K,)`` int64 steps those next observations belong to; the
            last step ``T - 1`` is always among them.
    """

    agent_id: str
    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminateds: np.ndarray
    truncateds: np.ndarray
    log_probs: np.ndarray
    final_obs: np.ndarray
    final_index: np.ndarray

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def dones(self) -> np.ndarray:
        """True where an episode ended at t (terminated or truncated)."""
        return self.terminateds | self.truncateds

    @property
    def boundaries(self) -> np.ndarray:
        """True where the stream stops after t (episode end, rollout end, gap).

        Return estimators must not reach across these steps; they bootstrap
        from the next value there unless the episode terminated.
        """
        mask = np.zeros(len(self), dtype=bool)
        mask[self.final_index] = True
        return mask

    @classmethod
    def concat(cls, rollouts: Sequence[Rollout]) -> Rollout:
        """Join rollouts of one agent into one batch; each keeps its own boundary."""
        if not rollouts:
            raise ValueError("Rollout.concat needs at least one rollout")
        offsets = np.cumsum([0] + [len(r) for r in rollouts[:-1]])
        return cls(
            agent_id=rollouts[0].agent_id,
            obs=np.concatenate([r.obs for r in rollouts]),
            actions=np.concatenate([r.actions for r in rollouts]),
            rewards=np.concatenate([r.rewards for r in rollouts]),
            terminateds=np.concatenate([r.terminateds for r in rollouts]),
            truncateds=np.concatenate([r.truncateds for r in rollouts]),
            log_probs=np.concatenate([r.log_probs for r in rollouts]),
            final_obs=np.concatenate([r.final_obs for r in rollouts]),
            final_index=np.concatenate([r.final_index + o for r, o in zip(rollouts, offsets, strict=True)]),
        )

    def next_values(self, values: np.ndarray, value_fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``V(s_{t+1})`` for every step, reusing ``values`` = ``V(obs)`` where possible.

        Args:
            values: ``(T,)`` values of ``obs``.
            value_fn: Maps a batch of observations to their ``(K,)`` values; it
                is only called on ``final_obs``.
        """
        next_values = np.empty(len(self), dtype=np.float32)
        next_values[:-1] = values[1:]
        next_values[self.final_index] = value_fn(self.final_obs)
        return next_values


class RolloutBuilder:
    """Accumulates one agent's transitions and cuts them into :class:`Rollout`.

    Robust to callers whose stream is not contiguous: if a transition's
    ``obs`` is not the previous transition's ``next_obs``, the previous step is
    treated as a rollout boundary (its ``next_obs`` is kept).
    """

    def __init__(self, agent_id: str):
        self.agent_id = agent_id
        self._steps: list[tuple] = []
        self._final: dict[int, np.ndarray] = {}
        self._last_next_obs: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._steps)

    def add(self, obs, action, reward, next_obs, terminated, truncated, log_prob=0.0) -> None:
        """Append one transition ``(s_t, a_t, r_t, s_{t+1})``."""
        obs, next_obs = np.asarray(obs), np.asarray(next_obs)
        if self._steps and self._last_next_obs is not None:
            if not np.array_equal(self._last_next_obs, obs):
                self._final[len(self._steps) - 1] = self._last_next_obs
        self._steps.append((obs, int(action), float(reward), bool(terminated), bool(truncated), float(log_prob)))
        done = bool(terminated) or bool(truncated)
        if done:
            self._final[len(self._steps) - 1] = next_obs
        # After an episode end the next obs comes from a reset: never compare with it.
        self._last_next_obs = None if done else next_obs

    def build(self) -> Rollout:
        """Return the accumulated transitions as a :class:`Rollout` and start afresh."""
        if not self._steps:
            raise ValueError(f"no transitions for agent {self.agent_id!r} to build a rollout from")
        last = len(self._steps) - 1
        if last not in self._final:
            self._final[last] = self._last_next_obs
        obs, actions, rewards, terminateds, truncateds, log_probs = zip(*self._steps, strict=True)
        index = sorted(self._final)
        rollout = Rollout(
            agent_id=self.agent_id,
            obs=np.stack(obs),
            actions=np.asarray(actions, dtype=np.int64),
            rewards=np.asarray(rewards, dtype=np.float32),
            terminateds=np.asarray(terminateds, dtype=bool),
            truncateds=np.asarray(truncateds, dtype=bool),
            log_probs=np.asarray(log_probs, dtype=np.float32),
            final_obs=np.stack([self._final[i] for i in index]),
            final_index=np.asarray(index, dtype=np.int64),
        )
        self._steps, self._final, self._last_next_obs = [], {}, None
        return rollout


# --------------------------------------------------------------------------- env runner


# The info key of cosim's per-episode summary (cosim.env): not "episode", which
# Gymnasium's RecordEpisodeStatistics, gym.make_vec and SB3's Monitor write themselves.
EPISODE_INFO = "cosim_episode"


@dataclass
class EpisodeReport:
    """Per-agent return and length of one finished episode in one worker."""

    worker: int
    returns: dict[str, float] = field(default_factory=dict)
    lengths: dict[str, int] = field(default_factory=dict)
    extras: dict[str, dict] = field(default_factory=dict)
    """Per agent, the env's own episode summary (``info[EPISODE_INFO]``) when it gives one."""


# A policy maps one observation to (action, log mu(action | obs)).
Policy = Callable[[np.ndarray], tuple[int, float]]


class EnvRunner:
    """Steps a ParallelEnv-like environment and cuts per-agent rollouts.

    The environment follows the PettingZoo ParallelEnv contract: ``reset(seed)
    -> (obs, infos)``, ``step(actions) -> (obs, rewards, terminations,
    truncations, infos)``, and ``agents`` shrinks as agents finish. An episode
    ends when ``agents`` is empty; the runner then resets (seeded only the
    first time, so episodes differ).

    Args:
        env: The environment (built inside the worker).
        agent_ids: The learning agents; every agent the env reports must be one.
        seed: Seed of the first reset.
        worker: Worker index, copied into episode reports.
        reward_scale: Rewards are multiplied by this in the rollouts (the agents'
            ``reward_scale``); episode reports keep the environment's own returns.
    """

    def __init__(self, env, agent_ids: Sequence[str], seed: int, worker: int = 0, reward_scale: float = 1.0):
        self.env = env
        self.reward_scale = float(reward_scale)
        self.agent_ids = list(agent_ids)
        self.worker = worker
        self.obs, _ = env.reset(seed=seed)
        self._check_agents(self.obs)
        self._returns = dict.fromkeys(self.obs, 0.0)
        self._lengths = dict.fromkeys(self.obs, 0)
        self._extras: dict[str, dict] = {}

    def _check_agents(self, obs: Mapping) -> None:
        unknown = set(obs) - set(self.agent_ids)
        if unknown:
            raise ValueError(
                f"environment reports agents {sorted(unknown)} that have no model; "
                f"pass every learning agent in agent_ids (got {self.agent_ids})"
            )

    def collect(self, policies: Mapping[str, Policy], num_steps: int) -> tuple[dict[str, Rollout], list[EpisodeReport], int]:
        """Step the env ``num_steps`` times with one policy per agent.

        Returns:
            ``(rollouts, episodes, env_steps)``: one :class:`Rollout` per agent
            that acted, the episodes that finished, and the env steps taken.
        """
        builders = {aid: RolloutBuilder(aid) for aid in self.agent_ids}
        episodes: list[EpisodeReport] = []
        for _ in range(num_steps):
            actions, log_probs = {}, {}
            for aid in self.env.agents:
                actions[aid], log_probs[aid] = policies[aid](self.obs[aid])
            next_obs, rewards, terminations, truncations, infos = self.env.step(actions)
            for aid, info in infos.items():
                if isinstance(info, Mapping) and EPISODE_INFO in info:
                    self._extras[aid] = info[EPISODE_INFO]
            for aid in actions:
                builders[aid].add(
                    self.obs[aid], actions[aid], rewards[aid] * self.reward_scale, next_obs[aid],
                    terminations[aid], truncations[aid], log_probs[aid],
                )
                self._returns[aid] += float(rewards[aid])
                self._lengths[aid] += 1
            self.obs = next_obs
            if not self.env.agents:
                episodes.append(
                    EpisodeReport(self.worker, self._returns, self._lengths, self._extras)
                )
                self._extras = {}
                self.obs, _ = self.env.reset()
                self._check_agents(self.obs)
                self._returns = dict.fromkeys(self.obs, 0.0)
                self._lengths = dict.fromkeys(self.obs, 0)
        rollouts = {aid: builder.build() for aid, builder in builders.items() if len(builder)}
        return rollouts, episodes, num_steps


def agents_for(cls, observation_space, action_space, agent_ids: Sequence[str], config, seed: int,
               agents: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The agents an asynchronous trainer trains: the given ones (to resume) or fresh ones.

    Fresh agent k (in ``agent_ids`` order) is seeded with ``seed + k``.
    """
    if agents is None:
        return {
            aid: cls.from_spaces(observation_space, action_space, config, seed=seed + k)
            for k, aid in enumerate(agent_ids)
        }
    if sorted(agents) != sorted(agent_ids):
        raise ValueError(f"agents covers {sorted(agents)} but agent_ids is {sorted(agent_ids)}")
    return dict(agents)


def make_parallel_env(env_fn: Callable[[], Any]):
    """Build an environment in the current process and present it as a ParallelEnv.

    Args:
        env_fn: Picklable zero-argument factory returning either a
            PettingZoo-ParallelEnv-like env (has ``possible_agents``) or a
            Gymnasium env, which is wrapped with ``SingleAgentParallel`` (one
            agent, ``"agent_0"``).

    Raises:
        TypeError: If ``env_fn`` returns neither.
    """
    env = env_fn()
    if hasattr(env, "possible_agents"):
        return env
    import gymnasium

    if isinstance(env, gymnasium.Env):
        from agents.envs import SingleAgentParallel

        return SingleAgentParallel(env)
    raise TypeError(
        f"env_fn returned {type(env).__name__}, which is neither a ParallelEnv (no "
        "possible_agents) nor a gymnasium.Env; return one of those from env_fn"
    )


def linear_learning_rate(optimizer: torch.optim.Optimizer, base_lr: float, steps_done: int, total_steps: int) -> float:
    """Set ``optimizer``'s learning rate to ``base_lr`` decayed linearly to 0 at ``total_steps``.

    Only the calling process's optimizer object changes (param-group values
    are not shared memory), so each asynchronous worker sets its own.

    Returns:
        The learning rate now in use.
    """
    lr = base_lr * max(0.0, 1.0 - steps_done / total_steps)
    for group in optimizer.param_groups:
        group["lr"] = lr
    return lr


def private_copy(module: torch.nn.Module) -> torch.nn.Module:
    """A copy of ``module`` with its own (not shared-memory) parameter storage.

    A worker acts with such a copy and refreshes it from the shared module with
    ``load_state_dict``, so the shared weights never change under its forward pass.
    """
    local = copy.deepcopy(module)
    for param in local.parameters():
        param.data = param.data.clone()  # never alias the shared storage, whatever deepcopy did
    return local


def categorical_policy(model: torch.nn.Module, generator: torch.Generator) -> Policy:
    """A :data:`Policy` sampling from ``model(obs) -> (logits, value)`` on the CPU."""
    from agents.networks import obs_to_tensor

    @torch.no_grad()
    def policy(obs: np.ndarray) -> tuple[int, float]:
        logits, _ = model(obs_to_tensor(np.asarray(obs)[None], "cpu"))
        log_probs = torch.log_softmax(logits[0], dim=-1)
        action = int(torch.multinomial(log_probs.exp(), 1, generator=generator))
        return action, float(log_probs[action])

    return policy


@dataclass
class TrainProgress:
    """What an asynchronous trainer passes to its callback after each report.

    Attributes:
        env_steps: Environment steps taken so far, all workers counted.
        episodes: Episodes that finished since the previous callback.
        agents: The agents being trained (their weights are live).
        worker_pids: Pids of the worker processes.
        elapsed: Seconds since training started.
        metrics: Agent id -> namespaced learning metrics of the updates this
            report covers (empty for agents that did not learn), as in
            :func:`agents.loop.run_loop`'s callback.
    """

    env_steps: int
    episodes: list[EpisodeReport]
    agents: dict[str, Any]
    worker_pids: list[int]
    elapsed: float
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
