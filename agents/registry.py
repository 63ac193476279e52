"""The algorithm catalogue: every algorithm's name, class, action kind and training loop.

This is the one place an algorithm is listed; the training layer (``eval/``), the
test protocol and a checkpoint's loader read it from here. Classes are given as
``"module:Class"`` strings imported on first use, so importing the catalogue does
not import every algorithm (and cannot create import cycles).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

__all__ = ["ALGORITHMS", "ASYNC", "CATALOGUE", "CONTINUOUS", "DISCRETE", "POLICY_NETWORKS", "Algorithm",
           "available", "get_agent_class"]


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
    """``"sync"``: one process steps the environments (agents.loop.run_vector_loop);
    ``"async"``: worker/actor processes, each with its own environment."""
    policy: tuple[str, ...]
    """The networks (keys of ``agent.networks``) that choose actions: all a policy
    checkpoint keeps (agents/checkpoint.py; run folders' ``best.pt``)."""


# ---------------------------------------------------------------------------------------
# THE CATALOGUE: one line per algorithm, in the paper's order (SPEC §5 tables).
CATALOGUE: tuple[Algorithm, ...] = (
    Algorithm("ppo", "agents.ppo:PPO", "discrete", "sync", ("net",)),
    Algorithm("a3c", "agents.a3c:A3C", "discrete", "async", ("actor_critic",)),
    Algorithm("impala", "agents.impala:IMPALA", "discrete", "async", ("actor_critic",)),
    Algorithm("dqn", "agents.dqn:DQN", "discrete", "sync", ("q_network",)),
    Algorithm("ddpg", "agents.ddpg:DDPG", "continuous", "sync", ("actor",)),
    Algorithm("td3", "agents.td3:TD3", "continuous", "sync", ("actor",)),
)
# ---------------------------------------------------------------------------------------

ALGORITHMS: dict[str, str] = {a.name: a.target for a in CATALOGUE}
"""name -> ``"module:Class"``, in catalogue order."""
DISCRETE: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.action == "discrete")
CONTINUOUS: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.action == "continuous")
ASYNC: tuple[str, ...] = tuple(a.name for a in CATALOGUE if a.loop == "async")
POLICY_NETWORKS: dict[str, tuple[str, ...]] = {a.name: a.policy for a in CATALOGUE}
"""name -> the networks a policy checkpoint keeps."""


def available() -> list[str]:
    """Names of the registered algorithms, sorted."""
    return sorted(ALGORITHMS)


def get_agent_class(name: str):
    """Return the agent class registered under ``name``.

    Raises:
        KeyError: If no algorithm has that name (the message lists the valid ones).
    """
    try:
        target = ALGORITHMS[name]
    except KeyError:
        raise KeyError(f"unknown algorithm {name!r}; registered algorithms: {available()}") from None
    module_name, class_name = target.split(":")
    return getattr(importlib.import_module(module_name), class_name)
