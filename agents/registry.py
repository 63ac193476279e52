"""The algorithm catalogue: every algorithm's name, class, action kind, training loop and
the kind of policy it learns.

This is the one place an algorithm and its facts are listed; the training layer
(``eval/``), the test protocol and a checkpoint's loader read them from here (the report's
presentation of an algorithm, its colour, is eval's: ``eval/labels.py``). Classes and
functions are given as ``"module:name"`` strings imported on first use, so importing the
catalogue does not import every algorithm (and cannot create import cycles).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

__all__ = ["ALGORITHMS", "ASYNC", "CATALOGUE", "CONTINUOUS", "DETERMINISTIC", "DISCRETE", "POLICY_NETWORKS", "STOCHASTIC", "TARGET_NETWORKS",
           "Algorithm", "available", "get", "get_agent_class", "get_actors", "get_async_trainer", "get_config_class"]


@dataclass(frozen=True)
class Algorithm:
    """One catalogue entry."""

    name: str
    """What ``--algo`` and checkpoints call it."""
    target: str
    """The agent class, ``"module:Class"``."""
    action: str
    """``"discrete"`` (Discrete(9)) or ``"continuous"`` (Box(-1, 1, (2,)))."""
    loop: str
    """``"sync"`` or ``"async"`` (actors and learner apart, in the algorithm's design: IMPALA's
    learner behind its actors' lag, A3C's actor-learners); both train on the one loop,
    agents.loop.run_loop, with the same hooks."""
    policy: tuple[str, ...]
    """The networks (keys of ``agent.networks``) that choose actions: all a policy
    checkpoint keeps (agents/checkpoint.py; run folders' ``best.pt``)."""
    stochastic: bool
    """True: the learned policy is a distribution (actor-critic), its training maximised the
    return of its samples, so an evaluation samples it (``act(obs)``; eval.testing.protocol.SAMPLED);
    False: a deterministic policy (greedy in Q, or a deterministic actor) whose exploration
    (epsilon, action noise) is training-only, so an evaluation acts greedily."""
    targets: tuple[tuple[str, str], ...] = ()
    """(target network, the online network it follows) pairs: what a warm start
    (agents.checkpoint.warm_start) sets to a copy of the online network it loaded."""
    config: str = ""
    """The hyperparameter dataclass, ``"agents.configs:Class"`` (torch-free, so the layers above
    hold a typed config without importing the algorithm); the agent class's ``config_class``."""
    async_trainer: str = ""
    """``loop == "async"``: the library's training function, ``"module:function"``, that
    builds its vector env and runs the loop on it (``agents.a3c:train_a3c``)."""
    actors: str = ""
    """``"module:function"`` giving the loop's actor-learner threads (``run_loop(actors=...)``,
    one thread per environment updating shared weights: A3C's ``actor_learners(agents, seed)``);
    empty: the loop's agents act and learn in the loop's thread."""

    @property
    def thread_per_env(self) -> bool:
        """One actor-learner thread per environment (:attr:`actors`), each taking one torch thread."""
        return bool(self.actors)


# ---------------------------------------------------------------------------------------
# THE CATALOGUE: one line per algorithm, in the paper's order (SPEC §5 tables).
CATALOGUE: tuple[Algorithm, ...] = (
    Algorithm("ppo", "agents.ppo:PPO", "discrete", "sync", ("net",), stochastic=True,
              config="agents.configs:PPOConfig"),
    Algorithm("a3c", "agents.a3c:A3C", "discrete", "async", ("actor_critic",), stochastic=True,
              config="agents.configs:A3CConfig", async_trainer="agents.a3c:train_a3c", actors="agents.a3c:actor_learners"),
    Algorithm("impala", "agents.impala:IMPALA", "discrete", "async", ("actor_critic",), stochastic=True,
              config="agents.configs:IMPALAConfig", async_trainer="agents.impala:train_impala"),
    Algorithm("dqn", "agents.dqn:DQN", "discrete", "sync", ("q_network",), stochastic=False,
              targets=(("target_network", "q_network"),), config="agents.configs:DQNConfig"),
    # DDPG/TD3: the actor acts on the critic's encoder (critic.encode), so the critic is policy too
    Algorithm("ddpg", "agents.ddpg:DDPG", "continuous", "sync", ("actor", "critic"), stochastic=False,
              targets=(("actor_target", "actor"), ("critic_target", "critic")), config="agents.configs:DDPGConfig"),
    Algorithm("td3", "agents.td3:TD3", "continuous", "sync", ("actor", "critic"), stochastic=False,
              targets=(("actor_target", "actor"), ("critic_target", "critic")), config="agents.configs:TD3Config"),
)
# ---------------------------------------------------------------------------------------

ALGORITHMS: dict[str, str] = {a.name: a.target for a in CATALOGUE}
"""name -> ``"module:Class"``, in catalogue order."""
DISCRETE: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.action == "discrete")
CONTINUOUS: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.action == "continuous")
ASYNC: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.loop == "async")
STOCHASTIC: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.stochastic)
"""The algorithms whose policy is a distribution (:attr:`Algorithm.stochastic`)."""
DETERMINISTIC: tuple[str, ...] = tuple(a.name for a in CATALOGUE if not a.stochastic)
"""The algorithms whose policy is deterministic (exploration only in training)."""
POLICY_NETWORKS: dict[str, tuple[str, ...]] = {a.name: a.policy for a in CATALOGUE}
"""name -> the networks a policy checkpoint keeps."""
TARGET_NETWORKS: dict[str, dict[str, str]] = {a.name: dict(a.targets) for a in CATALOGUE}
"""name -> {target network: the online network it follows}."""

POLICY_DTYPES = ("float32", "float16")
"""How a policy checkpoint (agents/checkpoint.py, ``policy_only``) stores float weights:
float32, bit for bit (the default), or float16, half the bytes, rounded (a loaded policy acts
on the rounded weights, so its actions can differ from the trained network's; the ``smoke``
run preset's choice, whose numbers check the pipeline, not the algorithms)."""


def available() -> list[str]:
    """Names of the registered algorithms, sorted."""
    return sorted(ALGORITHMS)


def get(name: str) -> Algorithm:
    """The catalogue entry of ``name``.

    Raises:
        KeyError: If no algorithm has that name (the message lists the valid ones).
    """
    for entry in CATALOGUE:
        if entry.name == name:
            return entry
    raise KeyError(f"unknown algorithm {name!r}; registered algorithms: {available()}")


def _load(target: str):
    module_name, attr = target.split(":")
    return getattr(importlib.import_module(module_name), attr)


def get_agent_class(name: str):
    """Return the agent class registered under ``name``.

    Raises:
        KeyError: If no algorithm has that name (the message lists the valid ones).
    """
    return _load(get(name).target)


def get_config_class(name: str):
    """The hyperparameter dataclass of ``name`` (:attr:`Algorithm.config`), without importing
    the algorithm (or torch): ``get_agent_class(name).config_class`` is the same class.

    Raises:
        KeyError: If no algorithm has that name (the message lists the valid ones).
    """
    return _load(get(name).config)


def get_actors(name: str):
    """The actor-learner factory of ``name`` (:attr:`Algorithm.actors`), or None when its
    agents act and learn in the loop's own thread."""
    entry = get(name)
    return _load(entry.actors) if entry.actors else None


def get_async_trainer(name: str):
    """The training function of an ``async`` algorithm (:attr:`Algorithm.async_trainer`).

    Raises:
        KeyError: If no algorithm has that name, or it is a sync one (no such function).
    """
    entry = get(name)
    if not entry.async_trainer:
        raise KeyError(f"{name} has no asynchronous training function; async algorithms: {list(ASYNC)}")
    return _load(entry.async_trainer)
