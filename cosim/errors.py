"""Exceptions a user can cause, each naming the bad input and the fix."""

from __future__ import annotations

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


class CosimError(Exception):
    """Base class of every error the simulation package (and ``eval`` on top of it) raises on
    purpose. ``agents`` has its own root, ``agents.errors.AgentError``, since it never imports
    cosim; the command line (``eval/cli/__init__.py``) catches both and prints one line
    (docs/reference.md#exit-codes-and-errors)."""


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
