"""Exceptions a user can cause, each naming the bad input and the fix."""

from __future__ import annotations

# The root lives in agents/errors.py, a module that imports nothing, so that agents
# (which never imports cosim) and eval subclass the same class; the CLI catches it.
from agents.errors import CosimError

__all__ = [
    "ActionError",
    "CosimError",
    "EnvStateError",
    "NetError",
    "OptionError",
    "ScenarioError",
    "SimulatorUnavailable",
    "SumoError",
]


class ScenarioError(CosimError, ValueError):
    """A scenario name, YAML file or value is wrong."""


class NetError(CosimError):
    """A SUMO network, demand or additional file is malformed or out of date."""


class SumoError(CosimError):
    """SUMO refused or failed; carries SUMO's own message. SUMO is closed when this is raised."""


class ActionError(CosimError, ValueError):
    """An action has the wrong type, shape or a non-finite value."""


class OptionError(CosimError, ValueError):
    """An option or argument has an unknown name (the message lists the valid ones) or a bad value."""


class EnvStateError(CosimError, RuntimeError):
    """An environment method was called in a state that does not allow it (e.g. step before reset)."""


class SimulatorUnavailable(CosimError, RuntimeError):
    """SUMO or PyBullet is missing or broken on this machine."""
