"""What the asynchronous algorithms' trainers (A3C, IMPALA) use beside the one loop.

Every algorithm steps its environments through the same code: a
:class:`~agents.vector.VectorEnv` of N worker processes (or, for one
environment, the in-process version), driven by :func:`agents.loop.run_loop`
(IMPALA's learner on it as PPO's is; A3C's actor-learners one thread per env
of it, ``actors=``). This module holds:

* :func:`vector_env`: the vector env of a trainer's ``env_fn`` (a factory, or
  one factory per environment; Gymnasium envs become one-agent ParallelEnvs).
* :class:`Unrolls`: per-(agent, env) :class:`~agents.workers.RolloutBuilder`
  that cut unrolls (IMPALA's, tagged with the learner's update count at their
  first step).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from agents.vector import make_vector_env
from agents.workers import (
    Rollout,
    RolloutBuilder,
    make_parallel_env,
)

__all__ = ["Unrolls", "vector_env"]

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
