"""Process and rollout helpers: what the vector env and the asynchronous trainers share.

Every environment of a training run steps in ONE place: the vector env of
``agents/vector.py`` (worker processes, or in process for one env). This module
holds what it, the loop (``agents/loop.py``) and the asynchronous algorithms'
trainers (A3C, IMPALA, ``agents/async_env.py``) share, nothing algorithm-specific:

* :func:`get_context` (``spawn`` or ``forkserver``, never ``fork``),
  :func:`_die_with_owner` (a worker dies with its owner, even on SIGKILL),
  :class:`WorkerError` (a worker's failure with its traceback text) and
  :func:`live_pids` (which of some pids still run: the no-orphan checks).
* :class:`Rollout` / :class:`RolloutBuilder`: one agent's consecutive
  transitions, the unit A3C learns from and IMPALA's learner batches.
* :class:`EpisodeReport`: one finished episode of one environment, as the
  loop's :class:`~agents.loop.Progress` reports it; :func:`agents_for`,
  :func:`make_parallel_env`, :func:`private_copy`, :func:`worker_seed`.

Workers ignore SIGINT, so a Ctrl-C in a terminal (delivered to the whole
process group) is handled once, by the owner, which then closes them.
"""

from __future__ import annotations

import copy
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as mp

from agents import observations
from agents.errors import AgentError

__all__ = [
    "EPISODE_INFO",
    "EpisodeReport",
    "Rollout",
    "RolloutBuilder",
    "WorkerError",
    "agents_for",
    "get_context",
    "live_pids",
    "make_parallel_env",
    "private_copy",
    "worker_seed",
]

logger = logging.getLogger(__name__)

START_METHODS = ("spawn", "forkserver")


class WorkerError(AgentError, RuntimeError):
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


def die_with_owner(owner_pid: int, poll_s: float = 0.5, sig: int = signal.SIGKILL) -> None:
    """Make this process (a worker any pool started, a child command) get ``sig`` when
    ``owner_pid`` dies, even by SIGKILL: :func:`_die_with_owner`'s two guards. Call it first
    thing in the child (a pool's initializer): ``cosim test --workers N``'s processes do
    (eval/testing/protocol.py) with SIGKILL, ``cosim train --algo all``'s per-algorithm
    commands with SIGTERM (handled as Ctrl-C: the run stops resumable, eval/cli/learn.py)."""
    _die_with_owner(owner_pid, poll_s, sig)


def _die_with_owner(owner_pid: int, poll_s: float = 0.5, sig: int = signal.SIGKILL) -> None:
    """Make sure this worker dies when its owner dies, even by SIGKILL.

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
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(sig), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the watchdog alone
        pass

    def watch() -> None:
        while live_pids([owner_pid]):
            time.sleep(poll_s)
        os.kill(os.getpid(), sig)
        if sig != signal.SIGKILL:  # a signal the process handles (its cleanup): 30 s for it
            time.sleep(30)
            os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="owner-watchdog", daemon=True).start()


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
        obs: ``(T, *obs_shape)`` observations ``s_t`` (a dict of such arrays for a
            ``Dict(image, measurements)`` space; agents/observations.py).
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
            obs=observations.concatenate([r.obs for r in rollouts]),
            actions=np.concatenate([r.actions for r in rollouts]),
            rewards=np.concatenate([r.rewards for r in rollouts]),
            terminateds=np.concatenate([r.terminateds for r in rollouts]),
            truncateds=np.concatenate([r.truncateds for r in rollouts]),
            log_probs=np.concatenate([r.log_probs for r in rollouts]),
            final_obs=observations.concatenate([r.final_obs for r in rollouts]),
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
        obs, next_obs = observations.asarray(obs), observations.asarray(next_obs)
        if self._steps and self._last_next_obs is not None:
            if not observations.equal(self._last_next_obs, obs):
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
            obs=observations.stack(obs),
            actions=np.asarray(actions, dtype=np.int64),
            rewards=np.asarray(rewards, dtype=np.float32),
            terminateds=np.asarray(terminateds, dtype=bool),
            truncateds=np.asarray(truncateds, dtype=bool),
            log_probs=np.asarray(log_probs, dtype=np.float32),
            final_obs=observations.stack([self._final[i] for i in index]),
            final_index=np.asarray(index, dtype=np.int64),
        )
        self._steps, self._final, self._last_next_obs = [], {}, None
        return rollout


# The info key of cosim's per-episode summary (cosim.env): not "episode", which
# Gymnasium's RecordEpisodeStatistics, gym.make_vec and SB3's Monitor write themselves.
EPISODE_INFO = "cosim_episode"


@dataclass
class EpisodeReport:
    """Per-agent return and length of one finished episode in one environment."""

    worker: int
    """Index of the environment (in the vector env) the episode ran in."""
    returns: dict[str, float] = field(default_factory=dict)
    lengths: dict[str, int] = field(default_factory=dict)
    extras: dict[str, dict] = field(default_factory=dict)
    """Per agent, the env's own episode summary (``info[EPISODE_INFO]``) when it gives one."""


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


def private_copy(module: torch.nn.Module) -> torch.nn.Module:
    """A copy of ``module`` with its own (not shared-memory) parameter storage.

    An A3C learner thread acts with such a copy and refreshes it from the shared
    module with ``load_state_dict``, so the shared weights never change under its
    forward pass.
    """
    local = copy.deepcopy(module)
    for param in local.parameters():
        param.data = param.data.clone()  # never alias the shared storage, whatever deepcopy did
    return local
