"""Algorithm registry: name -> agent class, so a checkpoint can be rebuilt by name.

Entries are ``"module:Class"`` strings imported on first use, so importing the
registry does not import every algorithm (and cannot create import cycles).
"""

from __future__ import annotations

import importlib

__all__ = ["ALGORITHMS", "available", "get_agent_class"]

# ---------------------------------------------------------------------------------------
# REGISTERED ALGORITHMS: one line per algorithm, "name": "module:Class".
ALGORITHMS: dict[str, str] = {
    "ppo": "agents.ppo:PPO",
    "dqn": "agents.dqn:DQN",
    "ddpg": "agents.ddpg:DDPG",
    "td3": "agents.td3:TD3",
    "a3c": "agents.a3c:A3C",
    "impala": "agents.impala:IMPALA",
}
# ---------------------------------------------------------------------------------------


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
