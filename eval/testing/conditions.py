"""The test's conditions, built in one place (issue 26): every environment the test, its
replays, its robustness runs, the validity suite, training's validation and `cosim view`
drive is made here, under one rule set.

- Collisions do not end an episode: each collision event is charged once, the scenario's
  contact rule (docs/task.md, "Collision rule"); the paper's step fractions CV, CP, CO need
  the episode to go on.
- A fixed horizon: ``steps`` (None, the default everywhere: the scenario's own ``horizon``,
  the one source of the test's episode length).
- Each AC's action kind follows the policy that drives it (:func:`action_kinds`): an
  algorithm's (the catalogue's, agents/registry.py), the autopilot's continuous.
- Scenario 1 drives the ACs together in the scenario's traffic; Scenario 2 drives one AC
  alone: no background cars, no pedestrians (:meth:`TestConditions.of`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

from agents import registry
from cosim.scenario import Scenario


def action_kinds(policies: Sequence[str]) -> list[str]:
    """The action kind of each AC: continuous for a continuous algorithm or the autopilot,
    else discrete."""
    return ["continuous" if p in registry.CONTINUOUS or p == "autopilot" else "discrete" for p in policies]


@dataclass(frozen=True)
class TestConditions:
    """How the test runs an environment (module docstring)."""

    __test__ = False  # not a pytest test class, whatever its name

    steps: int | None = None
    background: bool = True
    pedestrians: bool = True

    @classmethod
    def of(cls, scenario: int, steps: int | None) -> TestConditions:
        """Test Scenario 1 (together, in traffic) or 2 (alone) with ``steps`` per episode."""
        return cls(steps=steps) if scenario == 1 else cls(steps=steps, background=False, pedestrians=False)

    def env(self, scenario: str | Scenario, action_types: str | Sequence[str],
            num_agents: int | None = None, **options):
        """The environment (``CosimParallelEnv``) of ``scenario`` under these conditions, an AC per
        entry of ``action_types`` (or ``num_agents`` ACs of one kind); ``options``: what the
        conditions leave open (seed, image_size, render_mode)."""
        from cosim.env import CosimParallelEnv

        if not isinstance(action_types, str):
            action_types, num_agents = list(action_types), len(action_types)
        return CosimParallelEnv(scenario, num_agents=num_agents, action_types=action_types,
                                terminate_on_collision=False, horizon=self.steps,
                                background=self.background, pedestrians=self.pedestrians, **options)

    def scenario(self, scenario: Scenario) -> Scenario:
        """``scenario`` under these conditions, for a :class:`cosim.world.World` without cameras
        (the validity suite): collisions do not end an episode, the horizon is ``steps``; the
        traffic is the scenario's (Scenario 1's conditions)."""
        term = dataclasses.replace(scenario.termination, on_collision=False)
        horizon = scenario.horizon if self.steps is None else int(self.steps)
        return dataclasses.replace(scenario, termination=term, horizon=horizon)
